"""int8 against fp32 on the SAME presses and items, with the noise of the comparison.

The bench scores each bundle on the same held-out presses (``accuracy.eval_presses`` depends on
the manifest's partition, not on the precision) and draws the same by-bins items (the scenes and
press orders come from a seed, never from a decision), so the difference of two bundles is paired:

- per press: ZSL, acc_t, acc_u and H at each bundle's beta; the delta with a 95 % bootstrap
  interval (presses resampled within each fabric, the per-class means recomputed) and the count
  of presses that flip (fp32 right and int8 wrong, and the reverse) with McNemar's exact p;
- per item (random presses of one fabric, the bench's own items): H with 5 presses and with the
  sequential rule, bootstrap over fabrics, items that flip;
- per item, by bins: pieces in the right bin, for the scene decision and the router's posterior,
  the delta with a bootstrap over fabrics and the items that flip.

Items are not independent pairs: a fabric's items (by bins, in every scene it is in) are drawn from
its presses, so their McNemar p is clustered by fabric (``mcnemar_clustered_p``); the exact test on
them counted one press that flips once per item showing it. For the same reason their intervals
resample fabrics, each with all its items (``_fabric_bootstrap``): resampling items within a fabric,
or scenes that share fabrics, drew the same presses again and again and made the interval narrow
(one press apart: item-5 H -8.9 [-11.1, -7.1]).

A delta whose interval holds 0 is inside the noise of this comparison.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

N_BOOT = 1000
ITEMS_PER_FABRIC = 4  # runtime.sorting.simulate_scenes' default, as accuracy.by_bins draws them


def view(model, out: dict) -> dict:
    """What the paired comparison needs of a scored bundle (no sessions kept alive)."""
    return {"beta": float(model.beta), "ct": len(model.touched), "classes": list(model.classes),
            "touched": list(model.touched), "untouched": list(model.untouched),
            "scene_model": getattr(model, "scene_model", None), "out": out}


def mcnemar_p(b: int, c: int) -> float:
    """Exact two-sided McNemar p for b and c discordant pairs (binomial, p = 1/2)."""
    n = b + c
    if n == 0:
        return 1.0
    k = min(b, c)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n
    return min(1.0, 2 * tail)


def mcnemar_clustered_p(worse: np.ndarray, better: np.ndarray, cluster: np.ndarray) -> float:
    """Two-sided McNemar p for pairs that come in clusters sharing their data (Durkalski et al.
    2003, Stat Med 22:2417): X^2 = (B - C)^2 / sum_k (b_k - c_k)^2, chi-square with 1 df; b_k, c_k
    the pairs of cluster k that flip worse and better. The bench's items are drawn from their
    fabric's presses (by bins, in every scene the fabric is in), so one press that flips flips every
    item that shows it: the exact test on items counted it that often (one press apart, p 4e-15).
    Clusters of one pair each give the classic (asymptotic) McNemar."""
    _, k = np.unique(np.asarray(cluster), return_inverse=True)
    d = np.bincount(k, weights=np.asarray(worse, float)) - np.bincount(k, weights=np.asarray(better, float))
    den = float(np.sum(d ** 2))
    if den == 0:
        return 1.0
    return min(1.0, math.erfc(math.sqrt(float(np.sum(d)) ** 2 / den / 2)))


def _fabric_bootstrap(rng: np.random.Generator, groups: list[list]) -> list:
    """One bootstrap draw of fabrics: each group (e.g. touched, untouched) resampled with replacement,
    so every draw still has fabrics of each group."""
    return [g[i] for g in groups if g for i in rng.integers(0, len(g), len(g))]


def _press_indicators(v: dict) -> dict[str, np.ndarray]:
    o = v["out"]
    lab, lp, lsu, nov, ct = o["label"], o["lp"], o["lsu"], o["novelty"], v["ct"]
    routed_u = nov > v["beta"]
    pred_t = np.argmax(lp[:, :ct], axis=1)
    pred_u = ct + np.argmax(lsu, axis=1)
    is_t = lab < ct
    return {"label": lab, "is_t": is_t, "zsl": pred_u == lab,
            "acc_t": (pred_t == lab) & ~routed_u, "acc_u": (pred_u == lab) & routed_u}


def _class_mean(x: np.ndarray, lab: np.ndarray, rows: list[np.ndarray]) -> float:
    return float(np.mean([np.mean(x[r]) for r in rows])) if rows else math.nan


def _h(a: float, b: float) -> float:
    return 0.0 if a + b == 0 else 2 * a * b / (a + b)


def _metrics(ind: dict, rows_t: list[np.ndarray], rows_u: list[np.ndarray]) -> dict[str, float]:
    at = _class_mean(ind["acc_t"], ind["label"], rows_t)
    au = _class_mean(ind["acc_u"], ind["label"], rows_u)
    return {"zsl": 100 * _class_mean(ind["zsl"], ind["label"], rows_u), "acc_t": 100 * at, "acc_u": 100 * au,
            "H": 100 * _h(at, au)}


def paired_press(v32: dict, v8: dict, n_boot: int = N_BOOT, seed: int = 0) -> dict:
    i32, i8 = _press_indicators(v32), _press_indicators(v8)
    if not np.array_equal(i32["label"], i8["label"]):
        raise ValueError("the two bundles were not scored on the same presses (labels differ); pair them on one dataset")
    lab, is_t = i32["label"], i32["is_t"]
    classes = np.unique(lab)
    rows = {c: np.flatnonzero(lab == c) for c in classes}
    ct = v32["ct"]

    def rows_of(idx: dict) -> tuple[list, list]:
        return [idx[c] for c in classes if c < ct], [idx[c] for c in classes if c >= ct]

    m32, m8 = _metrics(i32, *rows_of(rows)), _metrics(i8, *rows_of(rows))
    rng = np.random.default_rng(seed)
    boots = {k: [] for k in m32}
    for _ in range(n_boot):
        res = {c: r[rng.integers(0, len(r), len(r))] for c, r in rows.items()}
        a, b = _metrics(i32, *rows_of(res)), _metrics(i8, *rows_of(res))
        for k in boots:
            boots[k].append(b[k] - a[k])
    out: dict[str, Any] = {}
    for k in m32:
        lo, hi = np.percentile(boots[k], [2.5, 97.5])
        out[k] = {"fp32": m32[k], "int8": m8[k], "delta": m8[k] - m32[k], "ci95": [float(lo), float(hi)],
                  "presses": int(len(lab)), "flips_worse": None, "flips_better": None, "mcnemar_p": None}
        if k == "H":  # H is not one press's right or wrong: its interval only
            continue
        mask = is_t if k == "acc_t" else ~is_t
        x32, x8 = i32[k][mask], i8[k][mask]
        worse, better = int(np.sum(x32 & ~x8)), int(np.sum(~x32 & x8))
        out[k].update(presses=int(mask.sum()), flips_worse=worse, flips_better=better, mcnemar_p=mcnemar_p(worse, better))
    return out


def _bins_records(v: dict, name: str, scenes, seed: int):
    from vs2t_edge.bench.accuracy import BIN_MAX_PRESSES, SEQ_CONFIDENCE
    from vs2t_edge.runtime import sorting as so

    classes, o = v["classes"], v["out"]
    lab = o["label"]
    if name == "router":
        table = {classes[c]: so.posterior_presses(classes, o["lp"][lab == c]) for c in np.unique(lab)}
        rule = so.plain_evidence(SEQ_CONFIDENCE, BIN_MAX_PRESSES)
    else:
        table = {classes[c]: so.scene_model_presses(v["scene_model"], o["feature"][lab == c], np.float32)
                 for c in np.unique(lab)}
        rule = so.scene_evidence(v["scene_model"], BIN_MAX_PRESSES)
    return so.simulate_scenes(scenes, table, rule, max_presses=BIN_MAX_PRESSES, seed=seed + 1)


def paired_bins(v32: dict, v8: dict, n_boot: int = N_BOOT, seed: int = 0) -> dict:
    """Right bin per item for both bundles on the same scenes and press orders (accuracy.by_bins)."""
    from vs2t_edge.bench.accuracy import BIN_SCENES
    from vs2t_edge.runtime import sorting as so

    if len(v32["touched"]) < 2 or not v32["untouched"]:
        return {}
    scenes = so.draw_scenes(v32["touched"], v32["untouched"], (), BIN_SCENES, seed=seed)
    # simulate_scenes: scene by scene, every scene and off-scene fabric, ITEMS_PER_FABRIC items each
    n_items = sum((len(sc.classes) + len(sc.off_scene)) * ITEMS_PER_FABRIC for sc in scenes)
    out = {}
    for name in ("scene_model", "router"):
        if name == "scene_model" and (v32["scene_model"] is None or v8["scene_model"] is None):
            continue
        recs32, recs8 = _bins_records(v32, name, scenes, seed), _bins_records(v8, name, scenes, seed)
        r32 = np.array([r.outcome == so.RIGHT for r in recs32])
        r8 = np.array([r.outcome == so.RIGHT for r in recs8])
        fabric = np.array([r.truth for r in recs32])  # a fabric's items share its presses across scenes
        if len(recs32) != n_items or [r.truth for r in recs8] != fabric.tolist():
            raise RuntimeError("by-bins items of the two bundles do not line up")
        rng = np.random.default_rng(seed)
        of_fabric = {f: np.flatnonzero(fabric == f) for f in np.unique(fabric)}
        boots = []
        for _ in range(n_boot):  # fabrics, each with all its items (the scenes share them)
            m = np.concatenate([of_fabric[f] for f in _fabric_bootstrap(rng, [list(of_fabric)])])
            boots.append(100 * (r8[m].mean() - r32[m].mean()))
        worse, better = int(np.sum(r32 & ~r8)), int(np.sum(~r32 & r8))
        lo, hi = np.percentile(boots, [2.5, 97.5])
        out[name] = {"fp32": 100 * float(r32.mean()), "int8": 100 * float(r8.mean()),
                     "delta": 100 * float(r8.mean() - r32.mean()), "ci95": [float(lo), float(hi)],
                     "items": int(len(r32)), "flips_worse": worse, "flips_better": better,
                     "mcnemar_p": mcnemar_clustered_p(r32 & ~r8, ~r32 & r8, fabric)}
    return out


def paired_items(v32: dict, v8: dict, n_items: int = 100, n_boot: int = N_BOOT, seed: int = 0) -> dict:
    """Per item (accuracy.draw_items: the bench's own items, the same for both bundles): H with 5
    presses summed and with the sequential rule; delta, bootstrap over fabrics (each with its items,
    which share its presses), items that flip (right for one bundle only)."""
    from vs2t_edge.bench.accuracy import draw_items, sequential_items

    lab = v32["out"]["label"]
    if not np.array_equal(lab, v8["out"]["label"]):
        raise ValueError("the two bundles were not scored on the same presses (labels differ); pair them on one dataset")
    items, item_lab, _ = draw_items(lab, n_items, seed)
    ct = v32["ct"]
    right = {}
    for name, v in (("fp32", v32), ("int8", v8)):
        lp = v["out"]["lp"]
        right[name] = {"item5": np.argmax(lp[items[:, :5]].sum(axis=1), axis=1) == item_lab,
                       "sequential": sequential_items(v["classes"], lp, items, item_lab)[0]}
    rows = {c: np.flatnonzero(item_lab == c) for c in np.unique(item_lab)}
    groups = [[c for c in rows if c < ct], [c for c in rows if c >= ct]]

    def h(x: np.ndarray, classes) -> float:
        at = np.mean([np.mean(x[rows[c]]) for c in classes if c < ct])
        au = np.mean([np.mean(x[rows[c]]) for c in classes if c >= ct])
        return 100 * _h(float(at), float(au))

    rng = np.random.default_rng(seed)
    out = {}
    for key in ("item5", "sequential"):
        a, b = right["fp32"][key], right["int8"][key]
        boots = []
        for _ in range(n_boot):  # touched and untouched fabrics, each with all its items
            drawn = _fabric_bootstrap(rng, groups)
            boots.append(h(b, drawn) - h(a, drawn))
        lo, hi = np.percentile(boots, [2.5, 97.5])
        worse, better = int(np.sum(a & ~b)), int(np.sum(~a & b))
        out[f"{key}_H"] = {"fp32": h(a, rows), "int8": h(b, rows), "delta": h(b, rows) - h(a, rows),
                           "ci95": [float(lo), float(hi)], "items": int(len(a)), "flips_worse": worse,
                           "flips_better": better, "mcnemar_p": mcnemar_clustered_p(a & ~b, ~a & b, item_lab)}
    return out


def paired(v32: dict, v8: dict, n_boot: int = N_BOOT, seed: int = 0, n_items: int = 100) -> dict:
    return {"press": paired_press(v32, v8, n_boot, seed), "items": paired_items(v32, v8, n_items, n_boot, seed),
            "bins": paired_bins(v32, v8, n_boot, seed),
            "bootstrap": n_boot, "note": "int8 minus fp32 on the same presses / items; ci95 by bootstrap "
            "(presses within fabric per press; fabrics, each with all its items, for items and bins); "
            "flips = discordant pairs, McNemar exact p per press, clustered by fabric for items and bins "
            "(their items share the fabric's presses)"}


__all__ = ["paired", "paired_press", "paired_items", "paired_bins", "mcnemar_p", "mcnemar_clustered_p", "view"]

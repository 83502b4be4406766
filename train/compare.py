"""The whole comparison: baselines, modern generators and GZSL routers on the same splits.

Input is a feature table (one row per press: tactile feature, visual feature of the camera crop
at the press, fabric index; one attribute row per fabric) and a list of fabric splits
(touched / validation / untouched). Per split:

- touched presses of each touched fabric are divided train 70 % / val 10 % / test 20 % (seeded);
- CLS_t (the paper's CLS 512-512-n) is trained on touched train presses, shared by all methods;
- every method is fitted on touched train presses and gives CLS_u for the untouched fabrics, and
  (``retarget``) a CLS_u for the validation fabrics;
- every router is fitted on touched train presses (features, CLS_t logits); its beta is tuned on
  VALIDATION only: touched-val presses against the validation fabrics' presses (calibrated
  stacking scored with the validation CLS_u);
- reported on test: ZSL accuracy (per-class mean over untouched presses, classes = untouched),
  GZSL acc_t / acc_u / H at the validation beta, and AUSUC per router.

The recommendation (default model and router) uses validation numbers only: model by mean
validation ZSL accuracy, router by mean validation AUSUC for that model.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from vs2t_edge.runtime import novelty as nv
from vs2t_edge.train.baselines import (
    BASELINES,
    PAPER_GZSL_VS2T,
    PAPER_ZSL,
    Budget,
    FeatureScaler,
    ZSLData,
    ZSLMethod,
    predict_logits,
    train_classifier,
)
from vs2t_edge.train.generators_modern import MODERN

GAUSSIAN_ROUTER = "gaussian"  # the paper's router, used for every method's Table-4 GZSL row


@dataclass
class FeatureTable:
    """Cached features of one dataset."""

    x_t: np.ndarray  # (P, d_t) tactile feature per press
    x_v: np.ndarray  # (P, d_v) visual feature of the camera crop at the press
    fabric: np.ndarray  # (P,) index into fabric_ids
    fabric_ids: list[str]
    attributes: np.ndarray  # (F, 24)
    source: str = ""

    def __post_init__(self) -> None:
        p = len(self.fabric)
        if self.x_t.shape[0] != p or self.x_v.shape[0] != p:
            raise ValueError(f"feature table: {self.x_t.shape[0]} tactile, {self.x_v.shape[0]} visual rows "
                             f"for {p} presses")
        if self.attributes.shape[0] != len(self.fabric_ids):
            raise ValueError(f"feature table: {self.attributes.shape[0]} attribute rows for "
                             f"{len(self.fabric_ids)} fabrics")

    def save(self, path: Path) -> None:
        np.savez(path, x_t=self.x_t.astype(np.float32), x_v=self.x_v.astype(np.float32), fabric=self.fabric,
                 fabric_ids=np.array(self.fabric_ids), attributes=self.attributes, source=np.array(self.source))

    @classmethod
    def load(cls, path: Path) -> "FeatureTable":
        with np.load(path, allow_pickle=False) as z:
            missing = {"x_t", "x_v", "fabric", "fabric_ids", "attributes"} - set(z.files)
            if missing:
                raise ValueError(f"{path}: feature cache lacks {sorted(missing)}")
            return cls(z["x_t"], z["x_v"], z["fabric"].astype(np.int64), [str(s) for s in z["fabric_ids"]],
                       z["attributes"].astype(np.float64), str(z["source"]) if "source" in z.files else str(path))


@dataclass
class FabricSplit:
    touched: list[str]
    validation: list[str]
    untouched: list[str]
    seed: int = 0


def make_splits(fabric_ids: list[str], n_splits: int = 5, n_val: int | None = None, n_untouched: int | None = None,
                seed: int = 0) -> list[FabricSplit]:
    """Random splits like the paper's 40/5/5 (10 % validation, 10 % untouched by default)."""
    n = len(fabric_ids)
    n_val = n_val if n_val is not None else max(2, round(0.1 * n))
    n_untouched = n_untouched if n_untouched is not None else max(2, round(0.1 * n))
    if n - n_val - n_untouched < 2:
        raise ValueError(f"{n} fabrics are too few for {n_val} validation and {n_untouched} untouched")
    out = []
    for k in range(n_splits):
        perm = np.random.default_rng(seed * 1000 + k).permutation(n)
        ids = [fabric_ids[i] for i in perm]
        out.append(FabricSplit(touched=sorted(ids[n_val + n_untouched:]), validation=sorted(ids[:n_val]),
                               untouched=sorted(ids[n_val:n_val + n_untouched]), seed=seed * 1000 + k))
    return out


def _per_class_acc(pred: np.ndarray, y: np.ndarray) -> float:
    classes = np.unique(y)
    return float(np.mean([np.mean(pred[y == c] == c) for c in classes]))


@dataclass
class SplitViews:
    """Everything one split gives the methods, already scaled."""

    train: ZSLData  # attr_u / v_u = untouched (test) fabrics
    val: ZSLData  # same touched data, attr_u / v_u = validation fabrics
    touched_val: tuple[np.ndarray, np.ndarray, np.ndarray]  # x_t, x_v, y
    touched_test: tuple[np.ndarray, np.ndarray, np.ndarray]
    val_presses: tuple[np.ndarray, np.ndarray, np.ndarray]  # of validation fabrics, y in 0..n_val-1
    test_presses: tuple[np.ndarray, np.ndarray, np.ndarray]  # of untouched fabrics


def split_views(table: FeatureTable, split: FabricSplit) -> SplitViews:
    index = {f: i for i, f in enumerate(table.fabric_ids)}
    rng = np.random.default_rng(split.seed + 17)
    tr_rows, va_rows, te_rows = [], [], []
    for k, fid in enumerate(split.touched):
        rows = rng.permutation(np.flatnonzero(table.fabric == index[fid]))
        n = len(rows)
        if n < 5:
            raise ValueError(f"fabric {fid}: {n} presses, need at least 5 to split train/val/test")
        n_va, n_te = max(1, round(0.1 * n)), max(1, round(0.2 * n))
        va_rows.append((rows[:n_va], k))
        te_rows.append((rows[n_va:n_va + n_te], k))
        tr_rows.append((rows[n_va + n_te:], k))

    def gather(parts):
        rows = np.concatenate([r for r, _ in parts])
        y = np.concatenate([np.full(len(r), k) for r, k in parts])
        return rows, y

    tr, y_tr = gather(tr_rows)
    va, y_va = gather(va_rows)
    te, y_te = gather(te_rows)
    sx = FeatureScaler.fit(table.x_t[tr])
    sv = FeatureScaler.fit(table.x_v[tr])
    attr = lambda ids: table.attributes[[index[f] for f in ids]].astype(np.float64)  # noqa: E731

    def fabric_rows(ids):
        parts = [(np.flatnonzero(table.fabric == index[f]), k) for k, f in enumerate(ids)]
        return gather(parts)

    u_rows, u_y = fabric_rows(split.untouched)
    v_rows, v_y = fabric_rows(split.validation)
    common = dict(x_t=sx(table.x_t[tr]), x_v=sv(table.x_v[tr]), y=y_tr, attr_t=attr(split.touched),
                  names_t=list(split.touched))
    # Conditions of untouched fabrics: the camera crops at every press position (the camera sees
    # the whole piece without touching it); their tactile features are only used for testing.
    train = ZSLData(**common, attr_u=attr(split.untouched), v_u=sv(table.x_v[u_rows]), v_u_class=u_y,
                    names_u=list(split.untouched))
    val = ZSLData(**common, attr_u=attr(split.validation), v_u=sv(table.x_v[v_rows]), v_u_class=v_y,
                  names_u=list(split.validation))
    return SplitViews(
        train=train, val=val,
        touched_val=(sx(table.x_t[va]), sv(table.x_v[va]), y_va),
        touched_test=(sx(table.x_t[te]), sv(table.x_v[te]), y_te),
        val_presses=(sx(table.x_t[v_rows]), sv(table.x_v[v_rows]), v_y),
        test_presses=(sx(table.x_t[u_rows]), sv(table.x_v[u_rows]), u_y),
    )


def all_methods() -> dict[str, type[ZSLMethod]]:
    """Table 4's rows, the modern generators, and VS2T-ZSL.

    VS2T-ZSL here is ``generators_modern.VS2TPrivate``, a minimal feature-level re-implementation
    trained on the same cached features and splits as every other row (the training room's own
    model trains its trunk end to end and is reported by `vs2t-edge train`)."""
    from vs2t_edge.train.generators_modern import VS2TPrivate

    return {**BASELINES, **MODERN, "VS2T-ZSL": VS2TPrivate}


def _router_block(routers: dict[str, nv.Router], cls_t, views: SplitViews, logits_u_val, logits_u_test,
                  logits_u_touched_val, logits_u_touched_test):
    """Per router: beta from validation, test GZSL numbers, test and validation AUSUC.

    ``logits_u_*``: CLS_u on the validation / untouched presses, and on the touched val / test
    presses (calibrated stacking scores every press over touched + untouched classes; on
    validation the untouched classes are the validation fabrics)."""
    x_tv, _, y_tv = views.touched_val
    x_tt, _, y_tt = views.touched_test
    x_vp, _, y_vp = views.val_presses
    x_up, _, y_up = views.test_presses
    lt = {k: predict_logits(cls_t, x) for k, x in (("tv", x_tv), ("tt", x_tt), ("vp", x_vp), ("up", x_up))}
    ok_t = {"tv": lt["tv"].argmax(1) == y_tv, "tt": lt["tt"].argmax(1) == y_tt}
    ok_val_u = logits_u_val.argmax(1) == y_vp
    ok_test_u = logits_u_test.argmax(1) == y_up
    out = {}
    for name, router in routers.items():
        nov_tv = router.novelty(x_tv, lt["tv"], logits_u=logits_u_touched_val)
        nov_vp = router.novelty(x_vp, lt["vp"], logits_u=logits_u_val)
        nov_tt = router.novelty(x_tt, lt["tt"], logits_u=logits_u_touched_test)
        nov_up = router.novelty(x_up, lt["up"], logits_u=logits_u_test)
        beta = nv.tune_threshold(nov_tv, nov_vp)
        g = nv.gzsl_accuracies(nov_tt > beta, ok_t["tt"], nov_up > beta, ok_test_u, y_tt, y_up)
        out[name] = {
            "beta": beta, **g,
            "ausuc": nv.ausuc(nov_tt, ok_t["tt"], nov_up, ok_test_u, y_tt, y_up),
            "auroc": nv.auroc(nov_tt, nov_up),
            "val_ausuc": nv.ausuc(nov_tv, ok_t["tv"], nov_vp, ok_val_u, y_tv, y_vp),
        }
    return out


def run_split(table: FeatureTable, split: FabricSplit, methods: dict[str, type[ZSLMethod]], budget: Budget,
              routers: tuple[str, ...] = nv.ROUTERS, log: Callable[[str], None] = print,
              extra_methods: dict[str, Callable] | None = None) -> dict:
    views = split_views(table, split)
    seed = split.seed
    torch.manual_seed(seed)
    t0 = time.time()
    cls_t = train_classifier(views.train.x_t, views.train.y, views.train.n_t, hidden=[512, 512],
                             steps=budget.cls_steps * 2, seed=seed)
    x_tr = views.train.x_t
    fitted = {}
    for name in routers:
        opts = {"keep_covariance": False} if name in nv.FEATURE_ROUTERS else {}
        fitted[name] = nv.fit_router(name, x_tr, predict_logits(cls_t, x_tr), **opts)
    x_tt, _, y_tt = views.touched_test
    result = {"split": asdict(split), "cls_t_acc": _per_class_acc(predict_logits(cls_t, x_tt).argmax(1), y_tt),
              "methods": {}}
    log(f"split seed {seed}: CLS_t touched acc {100 * result['cls_t_acc']:.1f} % ({time.time() - t0:.0f} s)")
    for name, cls in methods.items():
        t1 = time.time()
        method = cls().fit(views.train, budget, seed)
        x_up, v_up, y_up = views.test_presses
        logits_test = method.untouched_logits(x_up, v_up)
        lu_tt = method.untouched_logits(*views.touched_test[:2])
        zsl_test = _per_class_acc(logits_test.argmax(1), y_up)
        method.retarget(views.val, budget, seed)
        x_vp, v_vp, y_vp = views.val_presses
        logits_val = method.untouched_logits(x_vp, v_vp)
        lu_tv = method.untouched_logits(*views.touched_val[:2])
        zsl_val = _per_class_acc(logits_val.argmax(1), y_vp)
        block = _router_block(fitted, cls_t, views, logits_val, logits_test, lu_tv, lu_tt)
        result["methods"][name] = {"zsl_acc": zsl_test, "val_zsl_acc": zsl_val, "routers": block,
                                   "seconds": round(time.time() - t1, 1)}
        g = block.get(GAUSSIAN_ROUTER, next(iter(block.values())))
        log(f"  {name:18s} ZSL {100 * zsl_test:5.1f} (val {100 * zsl_val:5.1f})  GZSL-gaussian "
            f"t {100 * g['acc_t']:5.1f} u {100 * g['acc_u']:5.1f} H {100 * g['H']:5.1f}  ({time.time() - t1:.0f} s)")
    return result


def summarise(split_results: list[dict]) -> dict:
    methods = list(split_results[0]["methods"])
    routers = list(split_results[0]["methods"][methods[0]]["routers"])
    summary: dict = {"methods": {}}
    for m in methods:
        rows = [r["methods"][m] for r in split_results]
        ms = {"zsl_acc": _ms([r["zsl_acc"] for r in rows]), "val_zsl_acc": _ms([r["val_zsl_acc"] for r in rows]),
              "seconds_per_split": float(np.mean([r["seconds"] for r in rows])), "routers": {}}
        for rt in routers:
            ms["routers"][rt] = {k: _ms([r["routers"][rt][k] for r in rows])
                                 for k in ("acc_t", "acc_u", "H", "ausuc", "auroc", "val_ausuc")}
        summary["methods"][m] = ms
    best_model = max(methods, key=lambda m: summary["methods"][m]["val_zsl_acc"]["mean"])
    rs = summary["methods"][best_model]["routers"]
    best_router = max(rs, key=lambda r: rs[r]["val_ausuc"]["mean"])
    summary["recommendation"] = {
        "model": best_model, "router": best_router,
        "rule": "model: highest mean validation ZSL accuracy; router: highest mean validation AUSUC "
                "for that model; test numbers were not looked at",
    }
    summary["cls_t_acc"] = _ms([r["cls_t_acc"] for r in split_results])
    return summary


def _ms(values) -> dict[str, float]:
    v = np.asarray(values, dtype=np.float64)
    return {"mean": float(v.mean()), "std": float(v.std()), "n": int(v.size)}


def _pct(d: dict) -> str:
    return f"{100 * d['mean']:.2f} ± {100 * d['std']:.2f}"


def _evidence_strength(result: dict) -> str:
    """Is the validation choice more than a coin toss? Paired over splits: the per-split
    difference of validation ZSL accuracy between the chosen model and the runner-up, a clear
    lead when its mean exceeds two standard errors."""
    s = result["summary"]
    vals = sorted(((ms["val_zsl_acc"]["mean"], m) for m, ms in s["methods"].items()), reverse=True)
    best, runner = vals[0][1], vals[1][1]
    diffs = np.array([r["methods"][best]["val_zsl_acc"] - r["methods"][runner]["val_zsl_acc"]
                      for r in result["splits"]])
    se = diffs.std(ddof=1) / np.sqrt(len(diffs)) if len(diffs) > 1 else float("inf")
    strong = diffs.mean() > 2 * se
    rec = s["recommendation"]
    rv = sorted(((v["val_ausuc"]["mean"], k) for k, v in s["methods"][best]["routers"].items()), reverse=True)
    rd = np.array([r["methods"][best]["routers"][rv[0][1]]["val_ausuc"]
                   - r["methods"][best]["routers"][rv[1][1]]["val_ausuc"] for r in result["splits"]])
    rse = rd.std(ddof=1) / np.sqrt(len(rd)) if len(rd) > 1 else float("inf")
    return (f"Strength of evidence (paired over {len(diffs)} splits): {best} leads {runner} on validation ZSL by "
            f"{100 * diffs.mean():.1f} points, standard error {100 * se:.1f}: "
            f"{'a clear lead' if strong else 'within two standard errors, so the model choice is weak'}. "
            f"Router {rec['router']} leads {rv[1][1]} on validation AUSUC by {100 * rd.mean():.1f} points, "
            f"standard error {100 * rse:.1f}: {'clear' if rd.mean() > 2 * rse else 'weak'}.")


def render_markdown(result: dict, real_md: str | None = None) -> str:
    s = result["summary"]
    meta = result["meta"]
    lines = [
        "# Comparison: baselines, modern generators and GZSL routers",
        "",
        f"Regenerate: `{meta['command']}`. Features: {meta['features']} ({meta['n_fabrics']} fabrics, "
        f"{meta['n_presses']} presses, d_t={meta['d_t']}, d_v={meta['d_v']}). {meta['n_splits']} splits "
        f"(touched/validation/untouched {meta['split_sizes']}). Budget: {meta['budget']}. "
        f"Wall time {meta['seconds']:.0f} s on {meta['host']}.",
        "",
        "Our numbers are mean ± std over splits (%). The paper's numbers are on FabricVST (real "
        "fabrics, not reachable here); ours are on the data named above, so the columns compare "
        "orderings, not values.",
        "",
        "## Table 4: ZSL and GZSL (paper's Gaussian router, beta tuned on validation fabrics)",
        "",
        "| method | paper ZSL | our ZSL | our val ZSL | acc_t | acc_u | H | AUSUC |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for m, ms in s["methods"].items():
        g = ms["routers"].get(GAUSSIAN_ROUTER) or next(iter(ms["routers"].values()))
        paper = PAPER_ZSL.get(m)
        lines.append(f"| {m} | {paper if paper is not None else '—'} | {_pct(ms['zsl_acc'])} | "
                     f"{_pct(ms['val_zsl_acc'])} | {_pct(g['acc_t'])} | {_pct(g['acc_u'])} | {_pct(g['H'])} | "
                     f"{_pct(g['ausuc'])} |")
    p = PAPER_GZSL_VS2T
    lines += ["", f"Paper, VS2T-ZSL GZSL: acc_t {p['acc_t']}, acc_u {p['acc_u']}, H {p['H']}. "
              f"CLS_t touched accuracy (all methods share it): {_pct(s['cls_t_acc'])}.", ""]
    routers = list(next(iter(s["methods"].values()))["routers"])
    lines += ["## AUSUC per router (test) — and validation AUSUC, which chooses", "",
              "| method | " + " | ".join(routers) + " |", "| --- | " + " | ".join("---" for _ in routers) + " |"]
    for m, ms in s["methods"].items():
        lines.append(f"| {m} | " + " | ".join(
            f"{100 * ms['routers'][r]['ausuc']['mean']:.1f} (val {100 * ms['routers'][r]['val_ausuc']['mean']:.1f})"
            for r in routers) + " |")
    lines += ["", "## H per router at the validation-tuned beta (test)", "",
              "| method | " + " | ".join(routers) + " |", "| --- | " + " | ".join("---" for _ in routers) + " |"]
    for m, ms in s["methods"].items():
        lines.append(f"| {m} | " + " | ".join(f"{100 * ms['routers'][r]['H']['mean']:.1f}" for r in routers) + " |")
    rec = s["recommendation"]
    rm = s["methods"][rec["model"]]
    lines += ["", "## Recommendation (chosen on validation fabrics only)", "",
              f"Default model **{rec['model']}**, default router **{rec['router']}**. Rule: {rec['rule']}.",
              f"On test this gives ZSL {_pct(rm['zsl_acc'])}, GZSL H {_pct(rm['routers'][rec['router']]['H'])}, "
              f"AUSUC {_pct(rm['routers'][rec['router']]['ausuc'])}.", "", _evidence_strength(result), "",
              "![comparison](comparison.png)", ""]
    lines += ["## Methods and adaptations", "",
              "- All methods use the same cached features, splits, touched train/val/test presses, "
              "the same CLS_t, and the same fused visual+semantic condition [x_v, s] where they condition "
              "on both (f-CLSWGAN, CADA-VAE, f-VAEGAN). DAP uses tactile only; VT-FC-ZSL maps "
              "[x_t, x_v] to attributes; Abderrahmane 2019 conditions on attributes only; Lee 2019 on "
              "the visual feature only.",
              "- Lee 2019 is adapted to feature level: a pix2pix-style conditional GAN from the crop's "
              "visual feature to the tactile feature (BCE adversarial + 100 x L1), not image-to-image.",
              "- f-VAEGAN is the inductive f-VAEGAN-D2 without D2 (D2 needs unlabelled untouched "
              "tactile data).",
              "- VS2T-ZSL in this table is a minimal feature-level re-implementation "
              "(`generators_modern.VS2TPrivate`: E, VS-F as a sigmoid gate on [x_v, s], G, D with the "
              "paper's losses and weights, widths from the shared budget), so that it runs on exactly "
              "the same features and splits as the other rows.",
              "- Budgets are shortened for a shared 2-core CPU (see Budget above); GAN learning rates "
              "are 5e-4 instead of 1e-4 to compensate.", ""]
    if meta.get("vs2t_note"):
        lines += [f"- VS2T-ZSL: {meta['vs2t_note']}", ""]
    if real_md:
        lines += [real_md]
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = result["summary"]
    methods = list(s["methods"])
    routers = list(next(iter(s["methods"].values()))["routers"])
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    x = np.arange(len(methods))
    ours = [100 * s["methods"][m]["zsl_acc"]["mean"] for m in methods]
    err = [100 * s["methods"][m]["zsl_acc"]["std"] for m in methods]
    hs = [100 * (s["methods"][m]["routers"].get(GAUSSIAN_ROUTER) or {}).get("H", {"mean": 0})["mean"] for m in methods]
    paper = [PAPER_ZSL.get(m, np.nan) for m in methods]
    axes[0].bar(x - 0.27, ours, 0.27, yerr=err, label="our ZSL acc")
    axes[0].bar(x, hs, 0.27, label="our GZSL H (gaussian)")
    axes[0].bar(x + 0.27, paper, 0.27, label="paper ZSL acc (FabricVST)")
    axes[0].set_xticks(x, methods, rotation=30, ha="right")
    axes[0].set_ylabel("%")
    axes[0].set_title("ZSL / GZSL per method")
    axes[0].legend(fontsize=8)
    w = 0.8 / len(routers)
    for k, r in enumerate(routers):
        axes[1].bar(x + (k - len(routers) / 2 + 0.5) * w,
                    [100 * s["methods"][m]["routers"][r]["ausuc"]["mean"] for m in methods], w, label=r)
    axes[1].set_xticks(x, methods, rotation=30, ha="right")
    axes[1].set_ylabel("AUSUC %")
    axes[1].set_title("AUSUC per router (test)")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def run_comparison(table: FeatureTable, splits: list[FabricSplit], budget: Budget,
                   methods: dict[str, type[ZSLMethod]] | None = None, log: Callable[[str], None] = print) -> dict:
    methods = methods or all_methods()
    t0 = time.time()
    per_split = []
    for k, split in enumerate(splits):
        log(f"[{k + 1}/{len(splits)}] split seed {split.seed}")
        per_split.append(run_split(table, split, methods, budget, log=log))
    return {"splits": per_split, "summary": summarise(per_split), "seconds": time.time() - t0,
            "budget": asdict(budget)}


# --------------------------------------------------------------------------------------------
# feature sources
# --------------------------------------------------------------------------------------------


def toy_feature_table(n_fabrics: int = 30, presses: int = 40, d_t: int = 128, d_v: int = 64, seed: int = 0,
                      noise: float = 0.8, private: float = 0.0) -> FeatureTable:
    """A synthetic feature world for tests and a no-data smoke run: tactile and visual features are
    ReLU maps of the fabric's attributes and a hidden per-fabric 'structure' that both camera and
    touch partly see (so vision adds information beyond the 24 attributes), plus press noise of
    std ``noise`` and a touch-only per-fabric part of scale ``private`` that neither attributes
    nor camera reveal (what makes zero-shot recognition hard)."""
    rng = np.random.default_rng(seed)
    attrs = rng.integers(0, 2, (n_fabrics, 24)).astype(np.float64)
    hidden = rng.normal(size=(n_fabrics, 8))
    secret = rng.normal(size=(n_fabrics, 8)) * private
    w_ta, w_th, w_ts = rng.normal(size=(24, d_t)) / 3, rng.normal(size=(8, d_t)) / 2, rng.normal(size=(8, d_t)) / 2
    w_va, w_vh = rng.normal(size=(24, d_v)) / 3, rng.normal(size=(8, d_v)) / 2
    xt, xv, fab = [], [], []
    for f in range(n_fabrics):
        xt.append(np.maximum(attrs[f] @ w_ta + hidden[f] @ w_th + secret[f] @ w_ts
                             + rng.normal(size=(presses, d_t)) * noise, 0))
        xv.append(np.maximum(attrs[f] @ w_va + hidden[f] @ w_vh + rng.normal(size=(presses, d_v)) * noise, 0))
        fab.append(np.full(presses, f))
    xt, xv = np.concatenate(xt), np.concatenate(xv)
    xt[:, :5] = 0.0  # dead channels, as a ReLU trunk has
    return FeatureTable(xt.astype(np.float32), xv.astype(np.float32), np.concatenate(fab),
                        [f"toy{f:02d}" for f in range(n_fabrics)], attrs, source=f"toy world seed {seed}")


def extract_feature_table(dataset_root: Path, size_px: int = 224, log: Callable[[str], None] = print,
                          max_presses: int | None = None) -> FeatureTable:
    """PRIVATE MINIMAL feature extraction (used only when no training-run feature cache is given):
    frozen ImageNet EfficientNet-Lite0 features of each preprocessed tactile frame (the one
    ``preprocess_tactile`` with the fabric's reference frame) and of the camera crop at each press
    (ImageNet normalisation). The VS2T run fine-tunes its tactile trunk on touched fabrics; this
    extractor does not, so all methods here see the same frozen features."""
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import TactilePreprocess, preprocess_tactile
    from vs2t_edge.train.realdata_check import IMAGENET_MEAN, IMAGENET_STD, make_trunk

    import cv2

    ds = load_dataset(dataset_root)
    trunk, _ = make_trunk(pretrained=True)
    trunk.eval()
    spec = TactilePreprocess(size=size_px)
    mean, std = np.asarray(IMAGENET_MEAN, np.float32), np.asarray(IMAGENET_STD, np.float32)
    xt, xv, fab = [], [], []
    t0 = time.time()
    for k, fabric in enumerate(ds.fabrics):
        ref = fabric.load_reference()
        camera = fabric.load_camera()
        n = len(fabric.presses) if max_presses is None else min(max_presses, len(fabric.presses))
        tac = np.stack([preprocess_tactile(fabric.load_press(i), ref, spec) for i in range(n)])
        vis = []
        for i in range(n):
            crop = cv2.resize(fabric.visual_crop(i, camera), (size_px, size_px), interpolation=cv2.INTER_AREA)
            vis.append(((crop[..., ::-1] / 255.0 - mean) / std).transpose(2, 0, 1).astype(np.float32))
        with torch.no_grad():
            xt.append(torch.cat([trunk(torch.from_numpy(tac[i:i + 32])) for i in range(0, n, 32)]).numpy())
            xv.append(torch.cat([trunk(torch.from_numpy(np.stack(vis[i:i + 32]))) for i in range(0, n, 32)]).numpy())
        fab.append(np.full(n, k))
        print(f"\rfeatures: fabric {k + 1}/{len(ds.fabrics)} ({time.time() - t0:.0f} s)", end="", file=sys.stderr,
              flush=True)
    print(file=sys.stderr)
    return FeatureTable(np.concatenate(xt), np.concatenate(xv), np.concatenate(fab), [f.id for f in ds.fabrics],
                        ds.attribute_matrix().astype(np.float64), source=f"{dataset_root} (frozen EfficientNet-Lite0)")


def write_results(result: dict, out_dir: Path, real: dict | None = None) -> dict[str, Path]:
    from vs2t_edge.train.realdata_check import render_markdown as real_markdown

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"md": out_dir / "comparison.md", "json": out_dir / "comparison.json", "png": out_dir / "comparison.png"}
    payload = dict(result)
    if real is not None:
        payload["real_sensor_check"] = real
    paths["json"].write_text(json.dumps(payload, indent=1, default=float))
    plot(result, paths["png"])
    paths["md"].write_text(render_markdown(result, real_markdown(real) if real else None))
    return paths


__all__ = ["FeatureTable", "FabricSplit", "make_splits", "run_comparison", "summarise", "render_markdown", "plot",
           "toy_feature_table", "extract_feature_table", "write_results"]

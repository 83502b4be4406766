"""The whole comparison: baselines, modern generators and GZSL routers on the same splits.

Input is a feature table (one row per press: tactile feature, visual feature of the camera crop
at the press, fabric index; one attribute row per fabric) and a list of fabric splits
(touched / validation / untouched). Per split:

- touched presses of each touched fabric are divided by press order (runtime.dataset.press_partition):
  the first 70 % train, the next 10 % validation, the last 20 % test - earlier presses fit, later test;
- CLS_t (the paper's CLS 512-512-n) is trained on touched train presses, shared by all methods;
- every method is fitted on touched train presses and gives CLS_u for the untouched fabrics, and
  (``retarget``) a CLS_u for the validation fabrics;
- every router is fitted on touched train presses (features, CLS_t logits); its beta is tuned on
  VALIDATION only: touched-val presses against the validation fabrics' presses (calibrated
  stacking scored with the validation CLS_u);
- reported on test: ZSL accuracy (per-class mean over untouched presses, classes = untouched),
  GZSL acc_t / acc_u / H at the validation beta, and AUSUC per router.

The recommendation (default model and router) is ``RECOMMENDATION_RULE``, implemented once by
``recommend``: validation numbers only, model by mean validation ZSL accuracy among the methods the
cell can run on tactile features alone (``CELL_INPUTS``), router by mean validation AUSUC for that
model. A report page pools every comparison JSON of a run (``pool_into``, ``write_report_set``:
the run's splits and new random splits) and prints the rule's choice over all their splits.

A `vs2t-edge train` run folder can be the source (``load_run``): its exact splits (metrics.json,
order and seeds kept), its budget (config.yaml), its frozen feature table, or (``finetuned_tables``)
per split the features its VS2T-ZSL saw (the run's stem cache through the trunk tail fine-tuned
on that split's touched-train presses, same recipe and seed; the visual tail too when config.yaml
says ``visual_tail: finetuned``, and every method then reads those visual features); the run's own VS2T-ZSL
numbers are kept beside this comparison's (``compare_with_run``). The VS2T-ZSL row itself is
``train/vs2t.py``'s model, so with the run's features and budget it reproduces the run.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime.progress import Line
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
    from vs2t_edge.runtime.dataset import press_partition

    index = {f: i for i, f in enumerate(table.fabric_ids)}
    tr_rows, va_rows, te_rows = [], [], []
    for k, fid in enumerate(split.touched):
        rows = np.flatnonzero(table.fabric == index[fid])  # press order: earlier presses fit, later test
        n = len(rows)
        if n < 5:
            raise ValueError(f"fabric {fid}: {n} presses, need at least 5 to split train/val/test")
        p_tr, p_va, p_te = press_partition(n)
        va_rows.append((rows[p_va], k))
        te_rows.append((rows[p_te], k))
        tr_rows.append((rows[p_tr], k))

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

    VS2T-ZSL is the training room's own model (``train/vs2t.py``, the class `vs2t-edge train`
    fits), run here through the same split machinery on the same features as every other row.
    A fresh subclass per call keeps its ``instances`` list private to this comparison."""
    from vs2t_edge.train import vs2t

    return {**BASELINES, **MODERN, "VS2T-ZSL": vs2t.variant_class("VS2T-ZSL")}


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
                             steps=budget.cls_steps * 2, seed=seed, label="CLS_t")
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


# What each method needs, per press on the cell, to score untouched classes: the inputs of its
# ``untouched_logits``. The bundle (docs/bundle.md, DESIGN.md) carries the tactile trunk, CLS_t,
# CLS_u and the router, and the cell sees a fabric only through the GelSight, so a method that
# needs the camera crop at every press (VT-FC-ZSL maps [x_t, x_v] to attributes) cannot run there.
# Every entry is checked against the method's code by tests/test_baselines_compare.py; a method
# missing here cannot be recommended until its inputs are written down.
CELL_INPUTS: dict[str, tuple[str, ...]] = {
    "DAP": ("tactile",),
    "VT-FC-ZSL": ("tactile", "visual"),
    "Abderrahmane 2019": ("tactile",),
    "Lee 2019": ("tactile",),
    "f-CLSWGAN": ("tactile",),
    "CADA-VAE": ("tactile",),
    "f-VAEGAN": ("tactile",),
    "VS2T-ZSL": ("tactile",),
}
CELL_SIDE_INPUTS = ("tactile",)  # what the cell has per press

# The one rule that picks the default model and router, stated once; ``recommend`` implements it
# and every report prints its result and this text.
RECOMMENDATION_RULE = (
    "model: among the methods whose cell-side inference needs tactile features only (compare.CELL_INPUTS; "
    "the cell sees a fabric only through the GelSight and its bundle has no visual trunk), the one with the "
    "highest mean validation ZSL accuracy; router: the highest mean validation AUSUC for that model; means "
    "over every split of the run's comparison JSONs pooled (its own splits and the new ones); test numbers "
    "are not read")


def recommend(methods: dict, cell_inputs: dict[str, tuple[str, ...]] | None = None) -> dict:
    """``RECOMMENDATION_RULE`` over ``summarise``'s per-method means. Ties go to the first method /
    router in evaluation order. Also records the methods the constraint excluded and which method
    would win without it. ``model`` and ``router`` are None when no compared method can run on the
    cell."""
    cell_inputs = CELL_INPUTS if cell_inputs is None else cell_inputs
    unknown = [m for m in methods if m not in cell_inputs]
    if unknown:
        raise ValueError(f"no cell-side inputs recorded for {unknown}: add them to compare.CELL_INPUTS")
    val_zsl = lambda m: methods[m]["val_zsl_acc"]["mean"]  # noqa: E731
    eligible = [m for m in methods if set(cell_inputs[m]) <= set(CELL_SIDE_INPUTS)]
    out = {"model": None, "router": None, "rule": RECOMMENDATION_RULE,
           "excluded": {m: list(cell_inputs[m]) for m in methods if m not in eligible},
           "best_any_inputs": max(methods, key=val_zsl)}
    if eligible:
        model = max(eligible, key=val_zsl)
        rs = methods[model]["routers"]
        out.update(model=model, router=max(rs, key=lambda r: rs[r]["val_ausuc"]["mean"]))
    return out


def summarise(split_results: list[dict], cell_inputs: dict[str, tuple[str, ...]] | None = None) -> dict:
    """Per method mean ± std over splits, and ``recommend``'s choice (``cell_inputs`` defaults to
    ``CELL_INPUTS``)."""
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
    summary["recommendation"] = recommend(summary["methods"], cell_inputs)
    summary["cls_t_acc"] = _ms([r["cls_t_acc"] for r in split_results])
    return summary


def _ms(values) -> dict[str, float]:
    v = np.asarray(values, dtype=np.float64)
    return {"mean": float(v.mean()), "std": float(v.std()), "n": int(v.size)}


def _pct(d: dict) -> str:
    return f"{100 * d['mean']:.2f} ± {100 * d['std']:.2f}"


def _paired(splits: list[dict], a: Callable[[dict], float], b: Callable[[dict], float]) -> tuple[float, float]:
    """Mean and standard error of the per-split difference a - b (points); se inf for one split."""
    d = 100 * np.array([a(r) - b(r) for r in splits])
    return float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("inf")


def _lead(mean: float, se: float) -> str:
    return "clear" if mean > 2 * se else "weak"


def _evidence_strength(result: dict) -> str:
    """Is the rule's choice more than a coin toss? Paired over splits: the per-split difference of
    validation ZSL accuracy between the chosen model and the next eligible one, of validation
    AUSUC between the chosen router and the next one (and the paper's Gaussian); a clear lead when
    the mean exceeds two standard errors. Also how far a method the constraint excluded leads."""
    s, splits = result["summary"], result["splits"]
    rec = s["recommendation"]
    best = rec.get("model")
    if best is None:
        return "Strength of evidence: no compared method runs on tactile features alone, so nothing is chosen."
    val = lambda m: (lambda r: r["methods"][m]["val_zsl_acc"])  # noqa: E731
    rauc = lambda rt: (lambda r: r["methods"][best]["routers"][rt]["val_ausuc"])  # noqa: E731
    others = sorted((m for m in s["methods"] if m != best and m not in rec.get("excluded", {})),
                    key=lambda m: -s["methods"][m]["val_zsl_acc"]["mean"])
    best_rs = s["methods"][best]["routers"]
    routers = sorted(best_rs, key=lambda rt: -best_rs[rt]["val_ausuc"]["mean"])
    parts = []
    if others:
        d, se = _paired(splits, val(best), val(others[0]))
        parts.append(f"{best} leads {others[0]} on validation ZSL by {d:.1f} points, standard error {se:.1f}: "
                     f"{'a clear lead' if d > 2 * se else 'within two standard errors, so the model choice is weak'}.")
    lead = rec.get("best_any_inputs")
    if lead and lead != best:
        d, se = _paired(splits, val(lead), val(best))
        parts.append(f"{lead} (needs {' + '.join(rec['excluded'].get(lead, []))} features per press on the cell, "
                     f"so not eligible) leads {best} by {d:.1f} points, standard error {se:.1f} ({_lead(d, se)}).")
    if len(routers) > 1:
        d, se = _paired(splits, rauc(rec["router"]), rauc(routers[1]))
        parts.append(f"Router {rec['router']} leads {routers[1]} on validation AUSUC by {d:.1f} points, "
                     f"standard error {se:.1f}: {_lead(d, se)}.")
        if rec["router"] != GAUSSIAN_ROUTER and GAUSSIAN_ROUTER in routers:
            d, se = _paired(splits, rauc(rec["router"]), rauc(GAUSSIAN_ROUTER))
            parts.append(f"Against the paper's Gaussian router it leads by {d:.1f} points, standard error "
                         f"{se:.1f}: {_lead(d, se)}.")
    if not parts:
        return "Strength of evidence: not assessed (fewer than two methods or routers compared)."
    return f"Strength of evidence (paired over {len(splits)} splits): " + " ".join(parts)


def _split_key(record: dict) -> tuple:
    sp = record.get("split") or {}
    return tuple(tuple(sp.get(k, ())) if isinstance(sp.get(k), list) else sp.get(k)
                 for k in ("touched", "validation", "untouched", "seed"))


def pool_results(results: list[dict], cell_inputs: dict[str, tuple[str, ...]] | None = None) -> dict:
    """Several comparison results (same methods and routers, e.g. the run's splits and new
    random splits on the same features) as one: their splits concatenated and summarised again
    (so ``recommend``'s rule runs over all of them), with the evidence text. The same fabric split
    twice would count twice: refused."""
    splits = [sp for r in results for sp in r["splits"]]
    methods = [list(r["splits"][0]["methods"]) for r in results]
    if any(m != methods[0] for m in methods):
        raise ValueError(f"results compare different methods: {methods}")
    keys = [_split_key(sp) for sp in splits]
    dup = sorted({k[3] for k in keys if keys.count(k) > 1}, key=str)
    if dup:
        raise ValueError(f"the same fabric split (seed {dup}) appears more than once in the pooled results")
    pooled = {"splits": splits, "summary": summarise(splits, cell_inputs)}
    pooled["evidence"] = _evidence_strength(pooled)
    return pooled


def pool_into(result: dict, extra: list[tuple[str, dict]], label: str,
              cell_inputs: dict[str, tuple[str, ...]] | None = None) -> dict:
    """The recommendation of ``result``'s page: ``recommend`` over ``result``'s splits and every
    ``extra`` (label, result)'s, pooled; stored in ``result["pooled"]`` with the rule's choice on
    each source alone (so a page can show why the pooled choice and a per-source one differ) and,
    when ``result["run_router"]`` names the router the trained run ships, how that router compares
    with the pooled choice for VS2T-ZSL."""
    sources = [(label, result), *extra]
    pooled = pool_results([r for _, r in sources], cell_inputs)
    out = {"sources": [lbl for lbl, _ in sources], "n_splits": len(pooled["splits"]),
           "summary": pooled["summary"], "evidence": pooled["evidence"], "per_source": []}
    for lbl, r in sources:
        rec = summarise(r["splits"], cell_inputs)["recommendation"]
        out["per_source"].append({"source": lbl, "n_splits": len(r["splits"]), "model": rec["model"],
                                  "router": rec["router"]})
    ship = (result.get("run_router") or {}).get("chosen")
    methods = pooled["summary"]["methods"]
    if ship and "VS2T-ZSL" in methods and ship in methods["VS2T-ZSL"]["routers"]:
        rs = methods["VS2T-ZSL"]["routers"]
        best = max(rs, key=lambda rt: rs[rt]["val_ausuc"]["mean"])  # the rule's router for the run's model
        auc = lambda rt: (lambda r: r["methods"]["VS2T-ZSL"]["routers"][rt]["val_ausuc"])  # noqa: E731
        d, se = _paired(pooled["splits"], auc(best), auc(ship))
        own = summarise(result["splits"], cell_inputs)["methods"]["VS2T-ZSL"]["routers"]
        out["shipped_router"] = {"router": ship, "pooled_best_for_vs2t": best, "lead": d, "se": se,
                                 "run_splits_best_for_vs2t": max(own, key=lambda rt: own[rt]["val_ausuc"]["mean"])}
    result["pooled"] = out
    # the page's answer, at the top of its JSON (summary.recommendation is the rule on its own splits alone)
    rec = pooled["summary"]["recommendation"]
    result["recommendation"] = {"model": rec["model"], "router": rec["router"], "rule": rec["rule"],
                                "n_splits": out["n_splits"], "sources": out["sources"]}
    return out


def compare_with_run(result: dict, run: RunSource) -> dict | None:
    """The run's own VS2T-ZSL numbers and, per split, how far this comparison's VS2T-ZSL row
    (same class, features, splits, seeds and budget when run on fine-tuned features) is from
    them. Stored in ``result["run_vs2t"]``; None when the run has no VS2T-ZSL record."""
    own = run_vs2t_numbers(run)
    if own is None:
        return None
    ours = [r["methods"].get("VS2T-ZSL", {}).get("zsl_acc") for r in result["splits"]]
    if len(ours) == len(own["per_split_zsl"]) and all(o is not None for o in ours):
        diffs = [float(a - b) for a, b in zip(ours, own["per_split_zsl"])]
        own["reproduction"] = {"per_split_zsl_diff": diffs, "max_abs_diff": float(np.max(np.abs(diffs)))}
    result["run_vs2t"] = own
    return own


def _table4_row(name: str, ms: dict, paper_zsl, paper_g: dict | None) -> str:
    g = ms["routers"].get(GAUSSIAN_ROUTER) or next(iter(ms["routers"].values()))
    pg = f"{paper_g['acc_t']} / {paper_g['acc_u']} / {paper_g['H']}" if paper_g else "—"
    opt = lambda d, k: _pct(d[k]) if k in d else "—"  # noqa: E731
    return (f"| {name} | {paper_zsl if paper_zsl is not None else '—'} | {_pct(ms['zsl_acc'])} | "
            f"{opt(ms, 'val_zsl_acc')} | {pg} | {_pct(g['acc_t'])} | {_pct(g['acc_u'])} | {_pct(g['H'])} | "
            f"{opt(g, 'ausuc')} |")


def _test_numbers(ms: dict, router: str) -> str:
    return (f"ZSL {_pct(ms['zsl_acc'])}, GZSL H {_pct(ms['routers'][router]['H'])}, "
            f"AUSUC {_pct(ms['routers'][router]['ausuc'])}")


def _recommendation_section(result: dict) -> list[str]:
    """The page's recommendation: ``RECOMMENDATION_RULE`` over the pooled splits when the page
    pools several comparisons (``pool_into``), else over its own splits; a page pooled into
    another says so and points there."""
    pooled = result.get("pooled")
    meta = result.get("meta", {})
    if pooled is None:
        s, n = result["summary"], len(result["splits"])
        rec = s["recommendation"]
        if meta.get("pooled_in"):
            head = (f"## The rule on these {n} splits alone (validation only)", "",
                    f"The recommendation pools these splits with the others: see "
                    f"[{meta['pooled_in']}]({meta['pooled_in']}). On these splits alone the rule gives:")
        else:
            head = (f"## Recommendation (validation only, these {n} splits)",)
        lines = ["", *head, ""]
        if rec.get("model") is None:
            return lines + [f"No compared method runs on tactile features alone: nothing to recommend. "
                            f"Rule: {rec['rule']}.", ""]
        return lines + [f"Default model **{rec['model']}**, default router **{rec['router']}**. Rule: {rec['rule']}.",
                        f"On test (reported, not used to choose) this gives "
                        f"{_test_numbers(s['methods'][rec['model']], rec['router'])}.", "",
                        _evidence_strength(result), ""]
    s = pooled["summary"]
    rec, sm = s["recommendation"], s["methods"]
    lines = ["", f"## Recommendation (validation only, pooled over {pooled['n_splits']} splits: "
             f"{', '.join(pooled['sources'])})", ""]
    if rec.get("model") is None:
        return lines + [f"No compared method runs on tactile features alone: nothing to recommend. "
                        f"Rule: {rec['rule']}.", ""]
    rs = sm[rec["model"]]["routers"]
    lines += [f"Default model **{rec['model']}**, default router **{rec['router']}**.", "",
              f"The rule (stated once, as `compare.RECOMMENDATION_RULE`; applied by `compare.recommend`): "
              f"{rec['rule']}.", "",
              "| method | cell-side inputs per press | pooled val ZSL | its best val router (val AUSUC) |",
              "| --- | --- | --- | --- |"]
    for m in sorted(sm, key=lambda k: -sm[k]["val_zsl_acc"]["mean"]):
        br = max(sm[m]["routers"], key=lambda r: sm[m]["routers"][r]["val_ausuc"]["mean"])
        inputs = " + ".join(rec["excluded"][m]) + " (not eligible)" if m in rec["excluded"] else "tactile"
        name = f"**{m}**" if m == rec["model"] else m
        lines.append(f"| {name} | {inputs} | {_pct(sm[m]['val_zsl_acc'])} | {br} "
                     f"({100 * sm[m]['routers'][br]['val_ausuc']['mean']:.1f}) |")
    lines += ["", f"Validation AUSUC of {rec['model']} per router, pooled: "
              + ", ".join(f"{r} {100 * rs[r]['val_ausuc']['mean']:.1f}"
                          for r in sorted(rs, key=lambda r: -rs[r]['val_ausuc']['mean'])) + ".", "",
              pooled["evidence"], "",
              "The rule on each source alone (the pooled choice above is the recommendation):", "",
              "| source | splits | model | router |", "| --- | --- | --- | --- |"]
    for ps in pooled["per_source"]:
        lines.append(f"| {ps['source']} | {ps['n_splits']} | {ps['model']} | {ps['router']} |")
    lines += ["", f"On test (reported, not used to choose), pooled: {_test_numbers(sm[rec['model']], rec['router'])}.",
              ""]
    run_router = result.get("run_router") or {}
    ship = pooled.get("shipped_router")
    if run_router and ship:
        src = run_router.get("source", "the run's metrics.json")
        text = (f"**What the trained run ships.** `{src}` records router **{ship['router']}** for its VS2T-ZSL "
                f"(its rule: {run_router.get('rule') or 'not recorded'}, over its own "
                f"{len(result['splits'])} splits; this page's VS2T-ZSL row on those splits gives "
                f"{ship['run_splits_best_for_vs2t']}). ")
        if ship["router"] == rec["router"] and rec["model"] == "VS2T-ZSL":
            text += "That is the router the rule recommends."
        else:
            text += (f"Pooled over {pooled['n_splits']} splits the rule gives {ship['pooled_best_for_vs2t']} for "
                     f"VS2T-ZSL, {ship['lead']:.1f} validation AUSUC points ahead of {ship['router']} (standard error "
                     f"{ship['se']:.1f}, {_lead(ship['lead'], ship['se'])})")
            text += (f": the two differ because the run chose on its own splits' validation fabrics and this page on "
                     f"all {pooled['n_splits']} splits. A bundle exported from that run routes with "
                     f"{ship['router']}." if ship["pooled_best_for_vs2t"] != ship["router"] else ".")
            if rec["model"] != "VS2T-ZSL":
                text += f" The run's model is VS2T-ZSL; the rule recommends {rec['model']}."
        lines += [text, ""]
    elif result.get("run_vs2t") is not None:
        lines += ["**What the trained run ships.** Its metrics.json records no router choice (older runs ship "
                  "the paper's Gaussian).", ""]
    return lines


def _vs2t_condition_lines(result: dict) -> list[str]:
    """What VS2T-ZSL's condition was in this JSON, from the budget it records (``VS2TBudget``
    fields; ``train/vs2t.py`` ``VS2TZSL._visual``), not what today's default would be."""
    if not any("VS2T-ZSL" in sp["methods"] for sp in result.get("splits", [])):
        return []
    from vs2t_edge.train.vs2t import CLIP_SD

    b = result.get("budget", {})
    vc = b.get("visual_condition")
    clip = f"every channel clipped to ±{CLIP_SD:g} standard deviations of the touched training presses"
    if vc == "fabric":
        x_v = (f"each fabric's mean crop feature ({clip} first; `visual_condition: fabric`), the same for all "
               f"of a fabric's presses, so within-fabric variation must come from its latent")
    elif vc == "press":
        x_v = f"the crop feature at each press, {clip} (`visual_condition: press`)"
    else:
        x_v = ("the crop feature at each press as the other generators read it (this JSON's budget records no "
               "`visual_condition`: it predates the per-fabric condition and the clip)")
    extra = []
    if int(b.get("cond_pca", 0) or 0) > 0:
        extra.append(f"projected on its top {int(b['cond_pca'])} whitened principal components (touched presses)")
    if float(b.get("cond_noise", 0.0) or 0.0) > 0:
        extra.append(f"with Gaussian noise of std {b['cond_noise']} on the condition in training")
    tail = f", {'; '.join(extra)}" if extra else ""
    return [f"- VS2T-ZSL also conditions on [x_v, s] (through VS-F), but its x_v is {x_v}{tail}."]


def render_markdown(result: dict, real_md: str | None = None) -> str:
    s = result["summary"]
    meta = result["meta"]
    lines = [
        f"# Comparison: baselines, modern generators and GZSL routers{meta.get('title_suffix', '')}",
        "",
    ]
    if meta.get("see_also"):
        lines += [meta["see_also"], ""]
    if meta.get("full_command"):
        lines += [f"Regenerate the whole comparison (the run's splits, new splits, the real-sensor check, the pooled "
                  f"recommendation and these pages) with one command: `{meta['full_command']}`. Rebuild the pages "
                  f"from the committed JSONs alone (no training): `{meta['rebuild_command']}`.", ""]
    lines += [
        f"{'These numbers were made by' if meta.get('full_command') else 'Regenerate:'} `{meta['command']}`. "
        f"Features: {meta['features']} ({meta['n_fabrics']} fabrics, "
        f"{meta['n_presses']} presses, d_t={meta['d_t']}, d_v={meta['d_v']}). {meta['n_splits']} splits "
        f"(touched/validation/untouched {meta['split_sizes']}{meta.get('splits_source', '')}). "
        f"Budget: {meta['budget']}. Wall time {meta['seconds']:.0f} s on {meta['host']}.",
        "",
        "Our numbers are mean ± std over splits (%). The paper's numbers are on FabricVST (real "
        "fabrics, not reachable here); ours are on the data named above, so the columns compare "
        "orderings, not values.",
        "",
        "## Table 4: ZSL and GZSL (paper's Gaussian router, beta tuned on validation fabrics)",
        "",
        "| method | paper ZSL | our ZSL | our val ZSL | paper acc_t / acc_u / H | acc_t | acc_u | H | AUSUC |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for m, ms in s["methods"].items():
        lines.append(_table4_row(m, ms, PAPER_ZSL.get(m), PAPER_GZSL_VS2T if m == "VS2T-ZSL" else None))
    own = result.get("run_vs2t")
    if own:
        lines.append(_table4_row("VS2T-ZSL, the run's own metrics.json", own, PAPER_ZSL["VS2T-ZSL"],
                                 PAPER_GZSL_VS2T))
    p = PAPER_GZSL_VS2T
    lines += ["", f"Paper, VS2T-ZSL GZSL: acc_t {p['acc_t']}, acc_u {p['acc_u']}, H {p['H']} (the paper gives "
              f"GZSL only for VS2T-ZSL). CLS_t touched accuracy (all methods share it): {_pct(s['cls_t_acc'])}.", ""]
    if own and own.get("reproduction"):
        rp = own["reproduction"]
        same = rp["max_abs_diff"] < 1e-9
        lines += [f"The VS2T-ZSL row is `train/vs2t.py`'s model trained here; its per-split ZSL accuracy "
                  f"differs from the run's own metrics.json by at most {100 * rp['max_abs_diff']:.2f} points "
                  f"({'identical: same model, features, splits, seeds and budget' if same else 'per split: ' + ', '.join(f'{100 * d:+.1f}' for d in rp['per_split_zsl_diff'])}).",
                  ""]
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
    lines += _recommendation_section(result)
    lines += [f"![comparison]({meta.get('png', 'comparison.png')})", ""]
    lines += ["## Methods and adaptations", "",
              "- All methods use the same features, splits, touched train/val/test presses and the same CLS_t. "
              "f-CLSWGAN, CADA-VAE and f-VAEGAN condition on the fused visual+semantic [x_v, s] with x_v the "
              "standardised visual feature of the camera crop at each press, as it is (for an untouched fabric: "
              "each of its crops). DAP uses tactile only; VT-FC-ZSL maps [x_t, x_v] to attributes; "
              "Abderrahmane 2019 conditions on attributes only; Lee 2019 on the per-press visual feature only.",
              *_vs2t_condition_lines(result),
              "- Lee 2019 is adapted to feature level: a pix2pix-style conditional GAN from the crop's "
              "visual feature to the tactile feature (BCE adversarial + 100 x L1), not image-to-image.",
              "- f-VAEGAN is the inductive f-VAEGAN-D2 without D2 (D2 needs unlabelled untouched "
              "tactile data).",
              "- VS2T-ZSL is `train/vs2t.py`'s `VS2TZSL` (the model `vs2t-edge train` fits), trained "
              "through the same split machinery as every other row.",
              "- Budgets are shortened for a shared 2-core CPU (see Budget above); GAN learning rates "
              "are 5e-4 instead of 1e-4 to compensate.", ""]
    for note in meta.get("notes", []):
        lines += [f"- {note}"]
    if meta.get("notes"):
        lines += [""]
    if meta.get("vs2t_note"):
        lines += [f"- VS2T-ZSL: {meta['vs2t_note']}", ""]
    if real_md:
        lines += [real_md]
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    """Test ZSL / GZSL per method and AUSUC per router; with a pooled recommendation (``pool_into``)
    a second row shows what chose it: pooled validation ZSL per method (not-eligible methods
    hatched) and the chosen model's pooled validation AUSUC per router."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = result["summary"]
    methods = list(s["methods"])
    routers = list(next(iter(s["methods"].values()))["routers"])
    pooled = result.get("pooled")
    fig, grid = plt.subplots(2 if pooled else 1, 2, figsize=(12, 8.4 if pooled else 4.2), squeeze=False)
    axes = grid[0]
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
    axes[0].set_title(f"ZSL / GZSL per method (test, {len(result['splits'])} splits)")
    axes[0].legend(fontsize=8)
    w = 0.8 / len(routers)
    for k, r in enumerate(routers):
        axes[1].bar(x + (k - len(routers) / 2 + 0.5) * w,
                    [100 * s["methods"][m]["routers"][r]["ausuc"]["mean"] for m in methods], w, label=r)
    axes[1].set_xticks(x, methods, rotation=30, ha="right")
    top = max(100 * s["methods"][m]["routers"][r]["ausuc"]["mean"] for m in methods for r in routers)
    axes[1].set_ylim(0, top * 1.35)  # room for the legend above the bars
    axes[1].set_ylabel("AUSUC %")
    axes[1].set_title("AUSUC per router (test)")
    axes[1].legend(fontsize=7, ncol=3, loc="upper center")
    if pooled:
        ps = pooled["summary"]
        rec = ps["recommendation"]
        order = sorted(ps["methods"], key=lambda m: -ps["methods"][m]["val_zsl_acc"]["mean"])
        ax = grid[1][0]
        xs = np.arange(len(order))
        for i, m in enumerate(order):
            ms = ps["methods"][m]["val_zsl_acc"]
            n = ms["n"]
            ax.bar(i, 100 * ms["mean"], 0.6, yerr=100 * ms["std"] / np.sqrt(max(n, 1)), capsize=3,
                   color="tab:green" if m == rec["model"] else "tab:gray",
                   hatch="//" if m in rec["excluded"] else None, edgecolor="black", linewidth=0.5)
        ax.set_xticks(xs, order, rotation=30, ha="right")
        ax.set_ylabel("validation ZSL %  (bar: mean, whisker: s.e.)")
        ax.set_title(f"what chose the model: validation, {pooled['n_splits']} splits pooled\n"
                     f"(green: chosen; hatched: needs the camera on the cell, not eligible)", fontsize=9)
        ax = grid[1][1]
        if rec["model"] is not None:
            rs = ps["methods"][rec["model"]]["routers"]
            rorder = sorted(rs, key=lambda r: -rs[r]["val_ausuc"]["mean"])
            ax.bar(np.arange(len(rorder)), [100 * rs[r]["val_ausuc"]["mean"] for r in rorder], 0.6,
                   yerr=[100 * rs[r]["val_ausuc"]["std"] / np.sqrt(max(rs[r]["val_ausuc"]["n"], 1)) for r in rorder],
                   capsize=3, color=["tab:green" if r == rec["router"] else "tab:gray" for r in rorder])
            ax.set_xticks(np.arange(len(rorder)), rorder, rotation=30, ha="right")
            ship = (pooled.get("shipped_router") or {}).get("router")
            note = f"; the trained run ships {ship}" if ship else ""
            ax.set_title(f"what chose the router: {rec['model']}'s validation AUSUC, pooled\n"
                         f"(green: chosen{note})", fontsize=9)
            ax.set_ylabel("validation AUSUC %")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def run_comparison(table: FeatureTable, splits: list[FabricSplit], budget: Budget,
                   methods: dict[str, type[ZSLMethod]] | None = None, log: Callable[[str], None] = print,
                   table_for_split: Callable[[FabricSplit], FeatureTable] | None = None,
                   on_split: Callable[[list[dict]], None] | None = None) -> dict:
    """Every method on every split. ``table_for_split`` (optional) gives the feature table of one
    split, e.g. the tactile features of a training run's per-split fine-tuned trunk
    (``finetuned_tables``); ``table`` is used otherwise. ``on_split`` gets the per-split results
    after every split (a stopped run still leaves numbers)."""
    methods = methods or all_methods()
    check_splits(table, splits)
    t0 = time.time()
    per_split = []
    for k, split in enumerate(splits):
        done = time.time() - t0
        eta = f", ~{done / k * (len(splits) - k):.0f} s left" if k else ""
        log(f"[{k + 1}/{len(splits)}] split seed {split.seed} ({done:.0f} s elapsed{eta})")
        t_split = table_for_split(split) if table_for_split is not None else table
        per_split.append(run_split(t_split, split, methods, budget, log=log))
        if on_split is not None:
            on_split(per_split)
    return {"splits": per_split, "summary": summarise(per_split), "seconds": time.time() - t0,
            "budget": asdict(budget)}


def check_splits(table: FeatureTable, splits: list[FabricSplit]) -> None:
    """Every split names known fabrics, in three disjoint non-empty groups."""
    known = set(table.fabric_ids)
    for k, sp in enumerate(splits):
        groups = {"touched": sp.touched, "validation": sp.validation, "untouched": sp.untouched}
        for g, ids in groups.items():
            if not ids:
                raise ValueError(f"split {k} (seed {sp.seed}): no {g} fabrics")
            unknown = sorted(set(ids) - known)
            if unknown:
                raise ValueError(f"split {k} (seed {sp.seed}): {g} fabrics {unknown} are not in the feature "
                                 f"table ({table.source or 'features'})")
        seen: set[str] = set()
        for g, ids in groups.items():
            if seen & set(ids) or len(set(ids)) != len(ids):
                raise ValueError(f"split {k} (seed {sp.seed}): {g} fabrics overlap another group or repeat")
            seen |= set(ids)


# --------------------------------------------------------------------------------------------
# a training run (`vs2t-edge train`) as the source: its features, its splits, its VS2T numbers
# --------------------------------------------------------------------------------------------

RUN_FEATURE_TABLE = Path("features") / "feature_table.npz"
RUN_STEM_CACHE = Path("features") / "stem_cache.npz"


@dataclass
class RunSource:
    """What a comparison needs from a `vs2t-edge train` run folder."""

    run_dir: Path
    table: FeatureTable  # frozen-trunk features (features/feature_table.npz)
    splits: list[FabricSplit]  # exactly the run's splits, in its order (metrics.json)
    profile: dict  # config.yaml "profile" ({} when config.yaml is absent)
    vs2t_splits: list[dict]  # the run's own VS2T-ZSL record per split (metrics.json), fractions
    budget: dict = field(default_factory=dict)  # config.yaml "budget" (newer runs write the full VS2TBudget)
    router: dict = field(default_factory=dict)  # metrics.json "router": the router the run ships and its rule


def read_run_splits(path: Path) -> tuple[list[FabricSplit], list[dict]]:
    """The splits recorded by a training run: ``path`` is the run folder or its metrics.json.
    Returns (splits, per-split method records). Names the file and key on any problem."""
    path = Path(path)
    metrics = path / "metrics.json" if path.is_dir() else path
    if not metrics.is_file():
        partial = metrics.with_name("metrics_partial.json")
        hint = " (only metrics_partial.json: the run did not finish)" if partial.is_file() else ""
        raise FileNotFoundError(f"{metrics} does not exist{hint}")
    try:
        m = json.loads(metrics.read_text())
    except ValueError as exc:
        raise ValueError(f"{metrics}: not JSON ({exc})") from exc
    records = m.get("splits")
    if not isinstance(records, list) or not records:
        raise ValueError(f"{metrics}: no 'splits' list")
    splits = []
    for k, r in enumerate(records):
        sp = r.get("split") if isinstance(r, dict) else None
        if not isinstance(sp, dict):
            raise ValueError(f"{metrics}: splits[{k}] has no 'split' record")
        missing = {"touched", "validation", "untouched", "seed"} - set(sp)
        if missing:
            raise ValueError(f"{metrics}: splits[{k}].split lacks {sorted(missing)}")
        splits.append(FabricSplit(touched=[str(f) for f in sp["touched"]],
                                  validation=[str(f) for f in sp["validation"]],
                                  untouched=[str(f) for f in sp["untouched"]], seed=int(sp["seed"])))
    return splits, [r.get("methods", {}) for r in records]


def load_run(run_dir: Path) -> RunSource:
    """The run's cached frozen feature table, its exact splits, profile and VS2T numbers."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder {run_dir} does not exist")
    feats = run_dir / RUN_FEATURE_TABLE
    if not feats.is_file():
        raise FileNotFoundError(f"{feats} does not exist (written by `vs2t-edge train`)")
    table = FeatureTable.load(feats)
    splits, records = read_run_splits(run_dir)
    check_splits(table, splits)
    profile: dict = {}
    budget: dict = {}
    cfg = run_dir / "config.yaml"
    if cfg.is_file():
        import yaml

        try:
            conf = yaml.safe_load(cfg.read_text()) or {}
            profile = dict(conf.get("profile") or {})
            budget = dict(conf.get("budget") or {})
        except (yaml.YAMLError, AttributeError, TypeError, ValueError) as exc:
            raise ValueError(f"{cfg}: unreadable profile/budget ({exc})") from exc
    vs2t_splits = [r.get("VS2T-ZSL", {}) for r in records]
    return RunSource(run_dir, table, splits, profile, vs2t_splits, budget, read_run_router(run_dir))


def read_run_router(path: Path) -> dict:
    """The router a training run ships: metrics.json's "router" ({"chosen", "rule"}) with the file
    it came from under "source"; {} when the run does not record one (older runs: the Gaussian)."""
    path = Path(path)
    metrics = path / "metrics.json" if path.is_dir() else path
    try:
        router = json.loads(metrics.read_text()).get("router")
    except (OSError, ValueError, AttributeError):
        return {}
    if not isinstance(router, dict) or not router.get("chosen"):
        return {}
    return {"chosen": str(router["chosen"]), "rule": str(router.get("rule", "")), "source": str(metrics)}


def run_budget(profile: dict, budget: dict | None = None, **overrides) -> Budget:
    """The run's generator budget (``train/vs2t.py``'s ``VS2TBudget``) so that every row trains
    with the budget the VS2T run used: from its profile, then its config.yaml "budget" section
    (newer runs record every VS2TBudget field there; fields this VS2TBudget lacks are ignored),
    then ``overrides`` (not None). Fields the run did not record keep train/vs2t.py's defaults."""
    from vs2t_edge.train import vs2t

    known = {f.name for f in fields(vs2t.VS2TBudget)}
    keys = {"steps", "batch", "cls_steps", "n_synth_per_class", "lr_scale", "latent", "hidden"}
    kw = {k: profile[k] for k in keys if profile.get(k) is not None}
    kw.update({k: v for k, v in (budget or {}).items() if k in known and v is not None})
    kw.update({k: v for k, v in overrides.items() if v is not None})
    return vs2t.VS2TBudget(**kw)


def run_visual_tail(run: RunSource) -> str:
    """The visual tail the run's features went through: config.yaml ``profile.visual_tail``;
    runs written before that field existed were frozen."""
    vt = str(run.profile.get("visual_tail") or "frozen")
    if vt not in ("frozen", "finetuned"):
        raise ValueError(f"{run.run_dir / 'config.yaml'}: profile.visual_tail {vt!r} is neither 'frozen' nor "
                         f"'finetuned'")
    return vt


def finetuned_tables(run: RunSource, log: Callable[[str], None] = print,
                     weights: Path | None = None, tactile: bool = True) -> Callable[[FabricSplit], FeatureTable]:
    """Per split, the features the VS2T run's models saw: its cached stem activations through a
    copy of the trunk whose tail is fine-tuned on that split's touched-train presses, with the
    run's epochs, row cap and seed (``train/features.py``, as `vs2t-edge train` does) — the
    tactile tail (``tactile=False``: the cache's frozen tactile features instead) and, when the
    run's profile says ``visual_tail: finetuned``, the visual tail too (the camera crops at the
    same touched-train presses, seed split seed + 1, as train/run.py); otherwise the cache's
    frozen visual features. Every method of the comparison gets these visual features."""
    from vs2t_edge.train import features as ft
    from vs2t_edge.train.trunks import build_trunk

    visual = run_visual_tail(run) == "finetuned"
    path = run.run_dir / RUN_STEM_CACHE
    cache = ft.StemCache.load(path)
    if cache is None:
        raise FileNotFoundError(f"{path} does not exist (fine-tuned features need the run's stem cache; "
                                f"use frozen tactile features instead)" if not visual else
                                f"{path} does not exist (the run fine-tuned its visual tail: its features "
                                f"need the run's stem cache)")
    if visual and cache.stem_v is None:
        raise ValueError(f"{path} has no visual stem, but config.yaml says the run fine-tuned its visual tail "
                         f"(profile.visual_tail: finetuned)")
    arch = str(run.profile.get("trunk", cache.meta.get("arch", "")))
    if cache.meta.get("arch") != arch:
        raise ValueError(f"{path}: stem cache of trunk {cache.meta.get('arch')!r}, config.yaml names {arch!r}")
    if list(cache.fabric_ids) != list(run.table.fabric_ids) or len(cache.fabric) != len(run.table.fabric):
        raise ValueError(f"{path}: fabrics/presses differ from {run.run_dir / RUN_FEATURE_TABLE}")
    # `vs2t-edge train` seeds torch with the profile seed just before building its trunk: the same
    # here, so that even a trunk without pretrained weights (tiny, resnet50) starts identical
    torch.manual_seed(int(run.profile.get("seed", 0)))
    trunk = build_trunk(arch, pretrained=True, weights_path=weights)
    epochs = int(run.profile.get("ft_epochs", 2))
    max_rows = run.profile.get("ft_max_rows", None)
    what = " + ".join(w for w, on in (("tactile", tactile), ("visual", visual)) if on)

    def table_for(split: FabricSplit) -> FeatureTable:
        t0 = time.time()
        # training's own per-split fine-tuning (run.run_split calls the same function)
        feats = ft.finetune_split(cache, trunk, split, epochs=epochs, max_rows=max_rows, tactile=tactile,
                                  visual=visual, progress=False)
        log(f"  {what} tail fine-tuned on {feats.n_rows} touched-train presses ({time.time() - t0:.0f} s)")
        return FeatureTable(feats.x_t, feats.x_v, cache.fabric, cache.fabric_ids, cache.attributes,
                            source=f"{path} ({what} tail fine-tuned per split, seed = split seed"
                                   + (f", visual {ft.visual_tail_seed(split.seed)}" if visual else "") + ")")

    return table_for


def run_vs2t_numbers(run: RunSource) -> dict | None:
    """The run's own VS2T-ZSL numbers (metrics.json, Gaussian router) in ``summarise``'s format,
    or None when the run has no VS2T-ZSL record."""
    recs = run.vs2t_splits
    if not recs or not all(r.get("routers", {}).get(GAUSSIAN_ROUTER) for r in recs):
        return None
    g = [r["routers"][GAUSSIAN_ROUTER] for r in recs]
    out = {"zsl_acc": _ms([r["zsl_acc"] for r in recs]), "per_split_zsl": [float(r["zsl_acc"]) for r in recs],
           "routers": {GAUSSIAN_ROUTER: {k: _ms([x[k] for x in g]) for k in ("acc_t", "acc_u", "H")}}}
    if all("val_zsl_acc" in r for r in recs):
        out["val_zsl_acc"] = _ms([r["val_zsl_acc"] for r in recs])
    for k in ("ausuc", "val_ausuc"):
        if all(k in x for x in g):
            out["routers"][GAUSSIAN_ROUTER][k] = _ms([x[k] for x in g])
    return out


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
    line = Line()
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
        line.draw(f"features: fabric {k + 1}/{len(ds.fabrics)} ({time.time() - t0:.0f} s)", (k + 1) / len(ds.fabrics))
    line.keep()
    return FeatureTable(np.concatenate(xt), np.concatenate(xv), np.concatenate(fab), [f.id for f in ds.fabrics],
                        ds.attribute_matrix().astype(np.float64), source=f"{dataset_root} (frozen EfficientNet-Lite0)")


# A report page is generated down to this line; everything from it on is hand-written (a reading
# of the numbers, caveats) and is carried over verbatim when the page is regenerated.
HAND_MARKER = "<!-- hand-written below: kept on regeneration -->"


class UnmarkedReportError(ValueError):
    """An existing report has no HAND_MARKER line, so which part is hand-written is unknown."""


def hand_written_tail(path: Path, unmarked: str = "refuse") -> str:
    """The hand-written part of the report at ``path``: from its first line that is exactly
    ``HAND_MARKER`` to the end, the marker line included; "" when the file does not exist.

    A file without the marker may hold hand text anywhere, so ``unmarked="refuse"`` (default)
    raises ``UnmarkedReportError`` naming the file, and ``unmarked="replace"`` returns "" (the
    file is then rewritten whole, its old text lost)."""
    if unmarked not in ("refuse", "replace"):
        raise ValueError(f"unmarked must be 'refuse' or 'replace', not {unmarked!r}")
    path = Path(path)
    if not path.is_file():
        return ""
    text = path.read_text()
    offset = 0
    for line in text.splitlines(keepends=True):
        if line.strip() == HAND_MARKER:
            return text[offset:]
        offset += len(line)
    if unmarked == "replace":
        return ""
    raise UnmarkedReportError(
        f"{path} has no line '{HAND_MARKER}': regenerating would erase any hand-written text in it. "
        f"Put that line above the hand-written part (everything from it on is kept), or replace the "
        f"whole file (vs2t-edge compare --replace-unmarked)")


def with_hand_text(generated: str, tail: str) -> str:
    """The generated page followed by the kept hand-written tail (or a bare marker line, so that
    text added below it later survives the next regeneration)."""
    return generated.rstrip("\n") + "\n\n" + (tail or HAND_MARKER + "\n")


def write_results(result: dict, out_dir: Path, real: dict | None = None, name: str = "comparison",
                  unmarked: str = "refuse") -> dict[str, Path]:
    """``out_dir/{name}.md|json|png``. The .md is generated down to ``HAND_MARKER``; the existing
    page's text from that line on is kept (see ``hand_written_tail`` for a page without it: by
    default nothing is written and ``UnmarkedReportError`` says why)."""
    from vs2t_edge.train.realdata_check import render_markdown as real_markdown

    paths = {"md": out_dir / f"{name}.md", "json": out_dir / f"{name}.json", "png": out_dir / f"{name}.png"}
    tail = hand_written_tail(paths["md"], unmarked)  # before writing anything: a refusal leaves the old files
    out_dir.mkdir(parents=True, exist_ok=True)
    result.setdefault("meta", {})["png"] = paths["png"].name
    payload = dict(result)
    if real is not None:
        payload["real_sensor_check"] = real
    paths["json"].write_text(json.dumps(payload, indent=1, default=float))
    plot(result, paths["png"])
    paths["md"].write_text(with_hand_text(render_markdown(result, real_markdown(real) if real else None), tail))
    return paths


def full_command(run: str | Path, out_dir: str | Path, name: str, n_extra: int, extra_seed: int) -> str:
    """The one command that regenerates a run's whole comparison (``vs2t-edge compare --full``)."""
    return (f"vs2t-edge compare --run {run} --full --splits {n_extra} --extra-seed {extra_seed} --threads 1 "
            f"--out {out_dir} --out-name {name}")


def rebuild_command(main_json: str | Path, extra_jsons: list) -> str:
    """The command that rebuilds a comparison's pages from its JSONs (``vs2t-edge compare --rebuild``)."""
    return f"vs2t-edge compare --rebuild {main_json}" + "".join(f" --pool {p}" for p in extra_jsons)


def write_report_set(main: tuple[str, dict], extra: list[tuple[str, dict]], out_dir: Path, real: dict | None = None,
                     unmarked: str = "refuse", meta: dict | None = None,
                     cell_inputs: dict[str, tuple[str, ...]] | None = None) -> dict[str, dict[str, Path]]:
    """The pages of one comparison, in ``out_dir``: ``main`` (name, result) gets the recommendation
    pooled over its splits and every ``extra`` (name, result)'s (``pool_into``) and the
    real-sensor check (``real``, else the one main's JSON holds); each extra gets its own page that
    points to main's. Every result is summarised again from its splits, so pages rebuilt from an
    older JSON apply today's rule. ``meta`` entries (e.g. the regenerate commands) go into every
    page's meta. Nothing is written when a page's hand-written text could not be kept."""
    for n in [main[0], *(n for n, _ in extra)]:
        hand_written_tail(out_dir / f"{n}.md", unmarked)
    main_name, main_result = main
    real = real if real is not None else main_result.pop("real_sensor_check", None)
    for _, r in [main, *extra]:
        r["summary"] = summarise(r["splits"], cell_inputs)
        r.setdefault("meta", {}).update(meta or {})
    pool_into(main_result, [(f"{n}.json", r) for n, r in extra], f"{main_name}.json", cell_inputs)
    paths = {}
    for n, r in extra:
        r.pop("pooled", None)
        r["meta"]["pooled_in"] = f"{main_name}.md"
        paths[n] = write_results(r, out_dir, r.pop("real_sensor_check", None), n, unmarked)
    main_result["meta"].pop("pooled_in", None)
    paths[main_name] = write_results(main_result, out_dir, real, main_name, unmarked)
    return paths


def _main(argv: list[str] | None = None) -> int:
    """``python -m vs2t_edge.train.compare pool A.json B.json ...``: the validation-chosen default
    and its evidence over the splits of several comparison JSONs."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m vs2t_edge.train.compare")
    ap.add_argument("verb", choices=["pool"])
    ap.add_argument("results", nargs="+", type=Path)
    args = ap.parse_args(argv)
    pooled = pool_results([json.loads(p.read_text()) for p in args.results])
    rec, sm = pooled["summary"]["recommendation"], pooled["summary"]["methods"]
    print(f"{len(pooled['splits'])} splits; default model {rec['model']}, router {rec['router']} ({rec['rule']})")
    if rec["excluded"]:
        print("  not eligible (cell-side inputs): "
              + ", ".join(f"{m} ({' + '.join(v)})" for m, v in rec["excluded"].items()))
    for m in sorted(sm, key=lambda k: -sm[k]["val_zsl_acc"]["mean"]):
        best_r = max(sm[m]["routers"], key=lambda r: sm[m]["routers"][r]["val_ausuc"]["mean"])
        print(f"  {m:18s} val ZSL {_pct(sm[m]['val_zsl_acc'])}  best val router {best_r} "
              f"(val AUSUC {100 * sm[m]['routers'][best_r]['val_ausuc']['mean']:.1f})")
    print(pooled["evidence"])
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())


__all__ = ["FeatureTable", "FabricSplit", "make_splits", "run_comparison", "summarise", "render_markdown", "plot",
           "toy_feature_table", "extract_feature_table", "write_results", "RunSource", "load_run",
           "read_run_splits", "run_budget", "finetuned_tables", "run_visual_tail", "run_vs2t_numbers", "compare_with_run",
           "check_splits", "pool_results", "HAND_MARKER", "UnmarkedReportError", "hand_written_tail",
           "with_hand_text", "CELL_INPUTS", "RECOMMENDATION_RULE", "recommend", "pool_into", "write_report_set",
           "full_command", "rebuild_command", "read_run_router"]

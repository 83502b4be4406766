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

Three rooms: this module runs and summarises the comparison; ``compare_sources`` gives it
features and splits (a run folder, a dataset, a toy world); ``compare_report`` writes its pages.
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
from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.inference import gzsl_log_posterior
from vs2t_edge.runtime import router_eval as reval
from vs2t_edge.train.baselines import (
    BASELINES,
    Budget,
    FeatureScaler,
    ZSLData,
    ZSLMethod,
    predict_logits,
    train_classifier,
)
from vs2t_edge.train.generators_modern import MODERN
from vs2t_edge.train.stats import sample_sd
from vs2t_edge.train.splits import FabricSplit, make_splits  # make_splits: in __all__, as callers reach it here

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


# Per item, by bins (runtime/sorting.py: the evaluation the bench, the demo and training's report use):
# the cell's evidence on each method's per-press posterior, at the confidence the cell used before
# the scene decision, on scenes of 5 touched + 3 untouched test fabrics per split; off-scene pieces
# are the test fabrics a scene leaves out.
ITEM_CONFIDENCE, ITEM_MAX_PRESSES, ITEM_SCENES = 0.95, 5, 12
ITEM_KEYS = ("item_right", "item_mis_sort", "item_reject", "item_presses")


def by_bins(names_t: list[str], names_u: list[str], lp_t: np.ndarray, y_t: np.ndarray, lp_u: np.ndarray,
            y_u: np.ndarray, seed: int = 0) -> dict:
    """right / mis-sort / reject per item (fractions) and presses per item, over all pieces and per
    kind, from per-press log posteriors over ``names_t + names_u`` of touched test presses (labels
    ``y_t``) and untouched presses (``y_u``)."""
    classes = list(names_t) + list(names_u)
    tables = {names[k]: so.posterior_presses(classes, lp[y == k])
              for lp, y, names in ((lp_t, y_t, names_t), (lp_u, y_u, names_u)) for k in range(len(names))}
    scenes = so.draw_scenes(names_t, names_u, (), ITEM_SCENES, seed=seed)
    records = so.simulate_scenes(scenes, tables, so.plain_evidence(ITEM_CONFIDENCE, ITEM_MAX_PRESSES),
                                 max_presses=ITEM_MAX_PRESSES, seed=seed + 1)
    summary = so.summarise(records)
    a = summary["all"]
    return {"item_right": a[so.RIGHT], "item_mis_sort": a[so.MIS_SORT], "item_reject": a[so.REJECT],
            "item_presses": a["presses"], "item_by_kind": summary["by_kind"]}


def _router_block(routers: dict[str, nv.Router], cls_t, views: SplitViews, logits_u_val, logits_u_test,
                  logits_u_touched_val, logits_u_touched_test, seed: int = 0):
    """Per router: beta from validation, test GZSL numbers, test and validation AUSUC, and per item
    by bins (``by_bins``) with the gate's temperature fitted on validation as export fits it.

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
        beta = reval.tune_threshold(nov_tv, nov_vp)
        g = reval.gzsl_accuracies(nov_tt > beta, ok_t["tt"], nov_up > beta, ok_test_u, y_tt, y_up)
        scale = reval.gating_scale(nov_tv) if name in nv.FEATURE_ROUTERS else None
        temperature = reval.fit_gating_temperature(nov_tv, nov_vp, beta, scale)
        lp_tt = gzsl_log_posterior(lt["tt"], logits_u_touched_test, nov_tt, beta, temperature, scale)
        lp_up = gzsl_log_posterior(lt["up"], logits_u_test, nov_up, beta, temperature, scale)
        out[name] = {
            "beta": beta, **g,
            "ausuc": reval.ausuc(nov_tt, ok_t["tt"], nov_up, ok_test_u, y_tt, y_up),
            "auroc": reval.auroc(nov_tt, nov_up),
            "val_ausuc": reval.ausuc(nov_tv, ok_t["tv"], nov_vp, ok_val_u, y_tv, y_vp),
            **by_bins(views.train.names_t, views.train.names_u, lp_tt, y_tt, lp_up, y_up, seed),
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
    for name in routers:  # on the touched training presses and their classes (the discriminant router models each)
        opts = {"keep_covariance": False} if name in nv.GAUSSIAN_ROUTERS else {}
        fitted[name] = nv.fit_router(name, x_tr, predict_logits(cls_t, x_tr), touched_labels=views.train.y, **opts)
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
        block = _router_block(fitted, cls_t, views, logits_val, logits_test, lu_tv, lu_tt, seed)
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
            # per item by bins only where every split has it (JSONs from before it are still pooled)
            keys = ("acc_t", "acc_u", "H", "ausuc", "auroc", "val_ausuc") + tuple(
                k for k in ITEM_KEYS if all(k in r["routers"][rt] for r in rows))
            ms["routers"][rt] = {k: _ms([r["routers"][rt][k] for r in rows]) for k in keys}
        summary["methods"][m] = ms
    summary["recommendation"] = recommend(summary["methods"], cell_inputs)
    summary["cls_t_acc"] = _ms([r["cls_t_acc"] for r in split_results])
    return summary


def _ms(values) -> dict[str, float]:
    v = np.asarray(values, dtype=np.float64)
    return {"mean": float(v.mean()), "std": sample_sd(v), "n": int(v.size)}


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


def own_split_choices(splits: list[dict], cell_inputs: dict[str, tuple[str, ...]] | None = None) -> dict:
    """The rule applied to each split alone, on that split's validation fabrics, and the test
    numbers of each split's own choice. Splits are drawn independently, so a choice pooled over
    splits reads fabrics that are another split's untouched ones: its test numbers flatter a
    little; these do not. ``choices``: (model, router) per split."""
    cell_inputs = CELL_INPUTS if cell_inputs is None else cell_inputs
    choices, zsl, h, ausuc = [], [], [], []
    for sp in splits:
        ms = sp["methods"]
        eligible = [m for m in ms if set(cell_inputs.get(m, ("?",))) <= set(CELL_SIDE_INPUTS)]
        if not eligible:
            return {}
        model = max(eligible, key=lambda m: ms[m]["val_zsl_acc"])
        rs = ms[model]["routers"]
        router = max(rs, key=lambda r: rs[r]["val_ausuc"])
        choices.append((model, router))
        zsl.append(ms[model]["zsl_acc"])
        h.append(rs[router]["H"])
        ausuc.append(rs[router]["ausuc"])
    return {"choices": choices, "zsl_acc": _ms(zsl), "H": _ms(h), "ausuc": _ms(ausuc)}


def pool_results(results: list[dict], cell_inputs: dict[str, tuple[str, ...]] | None = None) -> dict:
    """Several comparison results (same methods and routers, e.g. the run's splits and new
    random splits on the same features) as one: their splits concatenated and summarised again
    (so ``recommend``'s rule runs over all of them), with the evidence text. The same fabric split
    twice would count twice: refused."""
    splits = [sp for r in results for sp in r["splits"]]
    methods = [list(r["splits"][0]["methods"]) for r in results]
    if any(m != methods[0] for m in methods):
        raise ValueError(f"results compare different methods: {methods}")
    routers = [sorted(sp["methods"][m]["routers"]) for sp in splits for m in sp["methods"]]
    if any(r != routers[0] for r in routers):  # e.g. a result made before a router was added
        odd = sorted(set().union(*map(set, routers)) - set.intersection(*map(set, routers)))
        raise ValueError(f"results compare different routers (not in every split: {', '.join(odd)}): "
                         "re-run the older comparison with today's code before pooling")
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
    out["own_split"] = own_split_choices(pooled["splits"], cell_inputs)
    result["pooled"] = out
    # the page's answer, at the top of its JSON (summary.recommendation is the rule on its own splits alone)
    rec = pooled["summary"]["recommendation"]
    result["recommendation"] = {"model": rec["model"], "router": rec["router"], "rule": rec["rule"],
                                "n_splits": out["n_splits"], "sources": out["sources"]}
    return out


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


def _main(argv: list[str] | None = None) -> int:
    """``python -m vs2t_edge.train.compare pool A.json B.json ...``: the validation-chosen default
    and its evidence over the splits of several comparison JSONs."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m vs2t_edge.train.compare")
    ap.add_argument("verb", choices=["pool"])
    ap.add_argument("results", nargs="+", type=Path)
    args = ap.parse_args(argv)
    try:
        pooled = pool_results([json.loads(p.read_text()) for p in args.results])
    except ValueError as exc:  # different methods or routers, a split twice, a file that is not JSON
        print(f"pool: {exc}", file=sys.stderr)
        return 2
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


__all__ = ["FeatureTable", "FabricSplit", "make_splits", "split_views", "SplitViews", "all_methods", "run_split",
           "run_comparison", "summarise", "check_splits", "pool_results", "pool_into", "CELL_INPUTS",
           "RECOMMENDATION_RULE", "recommend", "GAUSSIAN_ROUTER"]

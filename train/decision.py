"""The scene decision, fitted and calibrated on validation jobs only (runtime/scene_model.py).

Per split (``fit_scene_decision``):

1. a *validation model*: the touched fabrics' real training presses, and the validation fabrics
   playing the untouched part (their means synthesised by the generator from camera and
   attributes, as the untouched fabrics' will be) - so every choice below is made on fabrics whose
   tactile data the generator never read, and never on the split's untouched (test) fabrics. With
   ``folds`` (train/folds.py) there are more such *worlds*: folds of the touched fabrics, each held
   out of a generator trained on the others, playing validation fabrics; every choice below is
   then made on all worlds' jobs together;
2. for each subspace size ``k``: temperature and untouched bias by the class-balanced negative log
   likelihood of the touched fabrics' validation presses and the validation fabrics' presses
   (temperature scaling with a calibrated-stacking bias); the ``k`` with the lowest one is kept;
3. the item rule - evidence weight, known-class margin, whether a piece surely of a known fabric
   the job leaves out is refused at once (``refuse_early``, runtime/evidence.py) and the confidence
   that sorts - by simulating scenes of validation fabrics (the vectorised simulation of
   train/item_search.py, which decides every item as the cell's own ``Evidence`` does in
   ``runtime.sorting.simulate_scenes``; each rule's chosen point is decided once more by the cell's
   own evidence): the most pieces in the right bin among the settings whose mis-sort rate meets
   ``target_mis_sort`` (the fewest mis-sorts when none does), and of settings that put as many
   pieces in their bins, the one with the fewest mis-sorts (``ns.fewer_mis_sorts``; the same for
   the offset rule and the outlier ratio); the open-set threshold is a quantile
   (``OPEN_QUANTILES``) of the in-scene validation presses' distances to their own class; then the
   same for the offset item rule (runtime/scene_model.py: a piece's presses share an offset from
   their class mean, larger for a synthesised class) over its own knobs, on the same jobs; the
   item rule that scores better is kept (a tie keeps the sum rule);
4. the deployed model: the same ``k`` and scalars, with the untouched fabrics' synthesised means,
   and knowing the validation fabrics only to refuse them (``with_known``: their training presses'
   real means; runtime/scene_model.py ``known_only``) - they were pressed, and a line that meets a
   piece of one should send it to the reject bin, not into the bin of the job fabric it feels like.

``stranger_jobs`` prices that on the same test jobs with the validation fabrics' later presses as
off-scene pieces. ``evaluate_scenes`` scores a model on scenes of the split's TEST fabrics (touched test presses,
untouched fabrics' presses) with the same simulation, and the same scenes as jobs with operator
labels (``operator_label_jobs``, runtime/feedback.py: a mode outside the zero-shot protocol,
reported beside it; a sum-rule model learns with the offset candidate kept as its ``labels_rule``); ``press_tables`` gives the cell's per-press view (log
posterior and squared distances) that both use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Mapping

import numpy as np

from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.scene_model import LABELS_KEYS, OFFSET_KEYS, SceneModel
from vs2t_edge.train import item_search as ns

K_CHOICES = (32, 64, 128)
BIASES = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0)
WEIGHTS = (1.0, 0.5, 0.25)
MARGINS = (0.0, 2.0, math.inf)
CONFIDENCES = (0.5, 0.7, 0.9, 0.97, 0.99, 0.999)
# outlier-press rule candidates (runtime/scene_model.py ``outlier_ratio``; inf: off), tried on the
# chosen item rule; of the best scores the fewest mis-sorts, and the first of those (a full tie leaves
# it off)
OUTLIER_RATIOS = (math.inf, 50.0, 20.0, 10.0, 5.0, 3.0)
# the mis-sort targets training's report prices beside the one it chose for (``train --mis-sort-target``)
MIS_SORT_TARGETS = (0.005, 0.01, 0.02)
# open-set threshold candidates: quantiles of the squared distance of in-scene validation presses
# to their own class (1.0: no threshold)
OPEN_QUANTILES = (0.8, 0.9, 0.95, 0.99, 1.0)
N_SCENES = 12
MAX_PRESSES = 5
# extra presses (runtime/evidence.py) tried on the validation jobs once the rest of the operating point
# is chosen (0 is that point itself): the most pieces in the right bin within the mis-sort target, and
# of equals the fewest mis-sorts, then the fewest presses (the first)
EXTRA_PRESSES = (2, 4, 8)


def press_tables(model: SceneModel, rows: dict[str, np.ndarray]) -> dict[str, list[so.Press]]:
    """Per fabric, its presses as the cell scores them with ``model``."""
    return {fabric: so.scene_model_presses(model, x) for fabric, x in rows.items()}


def _balanced_nll(scores: np.ndarray, labels: np.ndarray) -> float:
    lp = so.log_softmax(scores)
    per = -lp[np.arange(len(labels)), labels]
    return float(np.mean([per[labels == c].mean() for c in np.unique(labels)]))


def _fit_t_b(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[float, float, float]:
    """(temperature, untouched bias, balanced NLL) by a scan over both; ``parts``: one (squared
    distances, labels, untouched mask) per validation world, their NLLs averaged."""
    best = (math.inf, 1.0, 0.0)
    for b in BIASES:
        for t in np.geomspace(0.05, 200.0, 33):
            nll = float(np.mean([_balanced_nll(-0.5 * d2 / t + b * is_u, labels) for d2, labels, is_u in parts]))
            if nll < best[0]:
                best = (nll, float(t), float(b))
    return best[1], best[2], best[0]


def evidence_for(model: SceneModel, max_presses: int = MAX_PRESSES, extra_presses: int | None = None):
    """The evidence the cell builds for a scene from the model's operating point (``extra_presses``
    overriding its own, as the config's ``evidence.extra_presses`` does)."""
    return so.scene_evidence(model, max_presses, extra_presses)


@dataclass(frozen=True)
class ValidationWorld:
    """What one set of validation jobs is drawn from: ``touched`` fabrics, whose training presses
    (``train_x``, ``train_y`` indexing ``touched``) fit the class means and whose validation presses
    (``touched_val``: x, index into ``touched``) are the touched pieces; and ``val_fabrics`` playing
    the untouched part, their presses (``val_presses``: x, index into ``val_fabrics``) the pieces and
    their means the generator's samples (``synth_val``: x, index into ``val_fabrics``) from a
    generator that never read their tactile data. The split's own (its validation fabrics), or a
    fold of its touched fabrics held out of a generator trained on the others (train/folds.py)."""

    train_x: np.ndarray
    train_y: np.ndarray
    touched: list
    touched_val: tuple
    val_fabrics: list
    val_presses: tuple
    synth_val: tuple


WORLD_SEED_STEP = 7919  # world j's jobs are drawn with seed + j * this (world 0's with the seed itself)


@dataclass(frozen=True)
class _Jobs:
    """A world's validation jobs and what the choice reads of them."""

    world: ValidationWorld
    val_in: list  # validation fabrics with a synthesised mean (one more, when there are three, plays a stranger)
    rows: dict  # fabric -> its presses the jobs' pieces are drawn from
    labels: np.ndarray  # class index (validation model's order) of each row of ``x_known``
    x_known: np.ndarray  # in-scene validation presses: touched fabrics' and the validation fabrics' with a mean
    synth_keep: np.ndarray  # the generator's samples of ``val_in``
    scenes: list
    seed: int

    @classmethod
    def of(cls, world: ValidationWorld, seed: int) -> "_Jobs":
        touched, val_fabrics = list(world.touched), list(world.val_fabrics)
        xv_t, yv_t = world.touched_val
        xv_u, yv_u = world.val_presses
        # One validation fabric (when there are three or more) plays a fabric the cell has never seen:
        # the validation model gets no synthesised mean for it, so the open-set threshold is chosen
        # against a real stranger instead of only accepting a share of the known ones.
        n_in = len(val_fabrics) - 1 if len(val_fabrics) >= 3 else len(val_fabrics)
        val_in, strangers = val_fabrics[:n_in], val_fabrics[n_in:]
        rows = {touched[c]: xv_t[yv_t == c] for c in range(len(touched))}
        rows.update({val_fabrics[c]: xv_u[yv_u == c] for c in range(len(val_fabrics))})
        keep = yv_u < n_in
        scenes = so.draw_scenes(touched, val_in, tuple(strangers), N_SCENES, n_untouched=min(3, len(val_in)), seed=seed)
        return cls(world, val_in, rows, np.concatenate([yv_t, len(touched) + yv_u[keep]]),
                   np.concatenate([xv_t, xv_u[keep]]), world.synth_val[1] < n_in, scenes, seed)

    @cached_property
    def axes(self) -> np.ndarray:
        """The principal axes of the world's touched training presses (one SVD for every ``k``)."""
        return SceneModel.principal_axes(self.world.train_x)

    def model(self, k: int) -> SceneModel:
        w = self.world
        return SceneModel.fit(w.train_x, w.train_y, list(w.touched), w.synth_val[0][self.synth_keep],
                              w.synth_val[1][self.synth_keep], self.val_in, k=k, axes=self.axes)


def _simulate(models: list[SceneModel], jobs: list[_Jobs], tables: list[dict] | None = None,
              extra_presses: int | None = None) -> dict:
    """The summary of every world's validation jobs decided by its model (``tables``: each world's
    press tables, when the caller has them; ``extra_presses``: instead of the model's own,
    runtime/evidence.py)."""
    recs = []
    for w, (m, j) in enumerate(zip(models, jobs)):
        recs += so.simulate_scenes(j.scenes, tables[w] if tables else press_tables(m, j.rows),
                                   evidence_for(m, MAX_PRESSES, extra_presses), seed=j.seed,
                                   max_presses=MAX_PRESSES)  # as ``_prepare`` draws them (and more for extra presses)
    return so.summarise(recs)


def _open_thresholds(own_d2: np.ndarray) -> dict[float, float]:
    """Open-set threshold candidates: each of ``OPEN_QUANTILES`` of the in-scene validation presses'
    squared distances to their own class (1.0: no threshold)."""
    return {q: float(np.quantile(own_d2, q)) if q < 1 else math.inf for q in OPEN_QUANTILES}


def _prepare(vm: SceneModel, jobs: _Jobs) -> tuple[dict, ns.Prepared]:
    """(each fabric's validation presses projected into ``vm``'s space, the items of the world's
    jobs prepared for the vectorised search, train/item_search.py): what both item rules' searches
    read. The items are the ones ``_simulate`` feeds the cell's evidence (same scenes and seed)."""
    projections = {f: vm.project(x) for f, x in jobs.rows.items()}
    items = ns.draw_items(jobs.scenes, projections, vm.classes, max_presses=MAX_PRESSES, seed=jobs.seed)
    return projections, ns.Prepared.of(items, vm)


def _offset_candidate(vms: list[SceneModel], jobs: list[_Jobs], prepared: list[tuple[dict, ns.Prepared]],
                      open_thresholds: list[dict], target: float) -> tuple[list[SceneModel], dict]:
    """The offset item rule (runtime/scene_model.py) searched on the same validation jobs as the
    sum rule (train/item_search.py, vectorised), one model per world (``prepared``: each world's
    ``_prepare``; ``open_thresholds``: its ``_open_thresholds``), and their summary from the cell's
    own evidence."""
    worlds = []
    for vm, (projections, items), thresholds in zip(vms, prepared, open_thresholds):
        # each world's own variance estimates: a fold's generator saw fewer fabrics than the deployed
        # one, so its syntheses' offset is its own, not the deployed model's (the search chooses scales)
        worlds.append(ns.World(items, ns.offset_estimates(vm, projections), thresholds))
    base = {"press_var_scale": 1.0, "touched_scale": 1.0, "item_bias": 0.0, "known_margin": 0.0, "open_quantile": 1.0,
            "confidence": 0.9, "untouched_confidence": 0.9, "refuse_early": True, "likeness_ratio": math.inf}
    point, _ = ns.search_offset_rule(worlds, base, CONFIDENCES, lambda summary: _score(summary, target))
    cands = [replace(vm, item_rule="offset", **ns.offset_setting(point, w)) for vm, w in zip(vms, worlds)]
    return cands, _simulate(cands, jobs)


def _labels_rule(cand_off: SceneModel) -> dict:
    """The offset candidate's setting a sum-rule model keeps for operator labels (``labels_rule``)."""
    return {key: float(getattr(cand_off, key)) for key in LABELS_KEYS}


def _as_priced(chosen: list[SceneModel], cand_off: list[SceneModel]) -> list[SceneModel]:
    """Each world's chosen model as the cell would decide with it: a sum-rule model carries the
    offset candidate's setting, which its press spread (the outlier rule) reads."""
    return [m if m.item_rule == "offset" else replace(m, labels_rule=_labels_rule(c)) for m, c in zip(chosen, cand_off)]


def _outlier_rule(chosen: list[SceneModel], summary_off: dict, cand_off: list[SceneModel], jobs: list[_Jobs],
                  target: float, tables: list[dict] | None = None) -> tuple[list[SceneModel], dict, list[dict]]:
    """The chosen item rule (one model per world) with the outlier-press ratio (``OUTLIER_RATIOS``)
    that scores best on the same validation jobs (the mis-sort target first, then pieces in the
    right bin, then the fewest mis-sorts): (models, their validation summary, one row per ratio
    tried). ``summary_off``: the chosen rule's own summary on those jobs (the ratio off, the first
    candidate), not decided again. A sum-rule model measures a press's spread with the offset
    candidate's setting, which it keeps for operator labels. ``tables``: each world's press tables
    of the chosen models when the caller has them (``_validation_tables``)."""
    probes = _as_priced(chosen, cand_off)
    tables = tables if tables is not None else _validation_tables(chosen, jobs)
    tried = []
    for ratio in OUTLIER_RATIOS:
        cands = [replace(m, outlier_ratio=ratio) for m in chosen]
        summary = summary_off if math.isinf(ratio) else _simulate(
            [replace(p, outlier_ratio=ratio) for p in probes], jobs, tables)
        tried.append((_score(summary, target), cands, summary))
    _, best, summary = max(tried, key=lambda t: ns.fewer_first(t[0], t[2]))
    rows_out = [{"outlier_ratio": c[0].outlier_ratio, "right": s["all"]["right"], "mis_sort": s["all"]["mis-sort"],
                 "reject": s["all"]["reject"], "presses": s["all"]["presses"]} for _, c, s in tried]
    return best, summary, rows_out


def _extra_presses(chosen: list[SceneModel], summary0: dict, cand_off: list[SceneModel], jobs: list[_Jobs],
                   target: float, tables: list[dict] | None = None) -> tuple[list[SceneModel], dict, list[dict]]:
    """The chosen operating point (one model per world) with the extra presses (0 and
    ``EXTRA_PRESSES``, runtime/evidence.py) that score best on the same validation jobs - the
    mis-sort target first, then pieces in the right bin, then the fewest mis-sorts; of full ties
    the fewest presses: (models, their validation summary, one row per number tried).
    ``summary0``: the point's own summary (0 extra presses), not decided again. The validation jobs
    see extra presses only where a touched fabric has more validation presses than the press
    limit (the paper profile extracts 90 presses a fabric for it: docs/training.md). ``tables``:
    as ``_outlier_rule``'s."""
    probes = _as_priced(chosen, cand_off)  # a sum-rule model as the outlier search priced it
    tables = tables if tables is not None else _validation_tables(chosen, jobs)
    tried = [(0, summary0)] + [(n, _simulate(probes, jobs, tables, extra_presses=n)) for n in EXTRA_PRESSES]
    n, summary = max(tried, key=lambda t: ns.fewer_first(_score(t[1], target), t[1]))  # the first of equals
    rows = [{"extra_presses": m, "chosen": m == n, **{key: s["all"][o] for key, o in (
        ("right", "right"), ("mis_sort", "mis-sort"), ("reject", "reject"), ("presses", "presses"))}} for m, s in tried]
    return [replace(m, extra_presses=n) for m in chosen], summary, rows


def _validation_tables(chosen: list[SceneModel], jobs: list[_Jobs]) -> list[dict]:
    """Each world's validation presses as the chosen model scores them (``press_tables``), once for
    the outlier and extra-press searches: their candidates differ in rules that read the table, not
    in what it holds (projection, distances, posterior)."""
    return [press_tables(m, j.rows) for m, j in zip(chosen, jobs)]


def _score(summary: dict, target: float) -> tuple:
    """How a setting ranks on validation jobs: the mis-sort target met first, then pieces in the
    right bin (the searches then polish with ``ns.fewer_mis_sorts``)."""
    a = summary["all"]
    return (a["mis-sort"] <= target, a["right"] - (0 if a["mis-sort"] <= target else 10 * a["mis-sort"]))


def fit_scene_decision(train_x: np.ndarray, train_y: np.ndarray, touched: list[str],
                       touched_val: tuple[np.ndarray, np.ndarray], val_fabrics: list[str],
                       val_presses: tuple[np.ndarray, np.ndarray], synth_val: tuple[np.ndarray, np.ndarray],
                       untouched: list[str], synth_u: tuple[np.ndarray, np.ndarray], *,
                       target_mis_sort: float = 0.01, seed: int = 0, folds: list[ValidationWorld] = (),
                       log=lambda m: None) -> tuple[SceneModel, dict]:
    """The deployed scene model and what its choice was based on (validation only, module doc).

    ``touched_val``: touched fabrics' validation presses (x, index into ``touched``);
    ``val_presses``: the validation fabrics' presses (x, index into ``val_fabrics``); ``synth_*``:
    the generator's samples (x, class index) for the validation and the untouched fabrics.
    ``folds``: more validation worlds (``ValidationWorld``: touched fabrics held out of a generator
    trained on the others, train/folds.py); every choice is made on all worlds' jobs together, and
    the deployed model takes its scalars from the split's own world."""
    worlds = [ValidationWorld(train_x, train_y, list(touched), touched_val, list(val_fabrics), val_presses, synth_val),
              *folds]
    jobs = [_Jobs.of(w, seed + WORLD_SEED_STEP * i) for i, w in enumerate(worlds)]
    # the subspace by validation NLL after temperature scaling (the item rule below is cheap to
    # search for one k, not for each)
    fits = []
    for k in K_CHOICES:
        vms = [j.model(k) for j in jobs]
        parts = [(vm.sq_distances(j.x_known), j.labels, np.array([c in vm.untouched for c in vm.classes], np.float64))
                 for vm, j in zip(vms, jobs)]
        nll0 = float(np.mean([_balanced_nll(-0.5 * d2, labels) for d2, labels, _ in parts]))
        t, b, nll = _fit_t_b(parts)
        log(f"scene decision k={k}: temperature {t:.3g}, untouched bias {b:g}, validation NLL {nll0:.2f} -> {nll:.2f}")
        fits.append((nll, k, nll0, t, b, vms, [d2[np.arange(len(labels)), labels] for d2, labels, _ in parts]))
    nll, k, nll0, t, b, vms, own_d2 = min(fits, key=lambda f: f[0])
    vms = [replace(vm, temperature=t, untouched_bias=b) for vm in vms]
    open_thresholds = [_open_thresholds(d2) for d2 in own_d2]  # per world, once for both item rules' searches
    # The item rule by coordinate search (each knob over its values with the others held, three
    # rounds): a full grid of the six knobs would cost thousands of simulated scene sets.
    grid = {"untouched_bias": sorted({0.0, b / 2, b}), "open_quantile": OPEN_QUANTILES, "evidence_weight": WEIGHTS,
            "known_margin": MARGINS, "confidence": CONFIDENCES, "untouched_confidence": CONFIDENCES,
            "refuse_early": (True, False)}  # True first: fewer presses where validation cannot tell them apart at all
    point = {"untouched_bias": b, "open_quantile": 1.0, "evidence_weight": 0.5, "known_margin": 2.0,
             "confidence": 0.9, "untouched_confidence": 0.9, "refuse_early": True}
    prepared = [_prepare(vm, j) for vm, j in zip(vms, jobs)]
    items = [p for _, p in prepared]
    tried: dict[tuple, tuple] = {}

    def candidates(p: dict) -> list[SceneModel]:
        """Each world's validation model at the sum rule's point ``p``."""
        return [replace(vm, untouched_bias=p["untouched_bias"], evidence_weight=p["evidence_weight"],
                        known_margin=p["known_margin"], confidence=p["confidence"],
                        untouched_confidence=p["untouched_confidence"], refuse_early=p["refuse_early"],
                        open_threshold=thresholds[p["open_quantile"]])
                for vm, thresholds in zip(vms, open_thresholds)]

    def trial(p: dict) -> tuple:
        """(score, summary) of the sum rule at ``p``, vectorised: the same outcomes as the cell's
        evidence on these jobs (train/item_search.py)."""
        key = tuple(sorted(p.items()))
        if key not in tried:
            parts = [ns.sum_rule(it, temperature=vm.temperature, untouched_bias=p["untouched_bias"],
                                 weight=p["evidence_weight"], confidence=p["confidence"],
                                 untouched_confidence=p["untouched_confidence"], known_margin=p["known_margin"],
                                 open_threshold=thresholds[p["open_quantile"]], refuse_early=p["refuse_early"])
                     for vm, thresholds, it in zip(vms, open_thresholds, items)]
            s = ns.summary(items, np.concatenate([o for o, _ in parts]), np.concatenate([n for _, n in parts]))
            tried[key] = (_score(s, target_mis_sort), s)
        return tried[key]

    for _ in range(3):
        for knob, values in grid.items():
            point[knob] = max(values, key=lambda v: trial({**point, knob: v})[0])
    point = ns.fewer_mis_sorts(point, grid, trial)
    tried_rows = [{**dict(key), "right": s["all"]["right"], "mis_sort": s["all"]["mis-sort"],
                   "reject": s["all"]["reject"], "presses": s["all"]["presses"]} for key, (_, s) in tried.items()]
    # the two item rules (runtime/scene_model.py) on the same validation jobs; the better one by
    # the same score (the mis-sort target first, then pieces in the right bin) is kept
    cand_sum = candidates(point)
    summary_sum = _simulate(cand_sum, jobs)  # the cell's own evidence decides the sum rule's point
    score_sum = _score(summary_sum, target_mis_sort)
    cand_off, summary_off = _offset_candidate(vms, jobs, prepared, open_thresholds, target_mis_sort)
    by_rule = {"sum": (score_sum, cand_sum, summary_sum), "offset": (_score(summary_off, target_mis_sort), cand_off, summary_off)}
    _, chosen, val_summary = max(by_rule.values(), key=lambda r: r[0])
    tables = _validation_tables(chosen, jobs)
    chosen, val_summary, outlier_rows = _outlier_rule(chosen, val_summary, cand_off, jobs, target_mis_sort, tables)
    chosen, val_summary, extra_rows = _extra_presses(chosen, val_summary, cand_off, jobs, target_mis_sort, tables)
    chosen, cand_off = chosen[0], cand_off[0]  # the split's own world's: its touched means are the deployed model's
    # the split's own world's touched presses are the deployed model's: its principal axes serve
    deployed = SceneModel.fit(train_x, train_y, touched, synth_u[0], synth_u[1], untouched, k=chosen.k, axes=jobs[0].axes)
    # a sum-rule model keeps the offset candidate's setting for operator labels (runtime/feedback.py
    # updates means only under the offset rule); it was searched on the same validation jobs
    labels_rule = None if chosen.item_rule == "offset" else _labels_rule(cand_off)
    # with folds, what the choice does on the split's own validation jobs alone (the rule as the
    # outlier search priced it: a sum-rule model's press spread is its labels rule's)
    own_world = _simulate([replace(chosen, labels_rule=labels_rule)], jobs[:1]) if folds else None
    deployed = replace(chosen, classes=deployed.classes, untouched=deployed.untouched, center=deployed.center,
                       basis=deployed.basis, means=deployed.means, labels_rule=labels_rule,
                       info={**deployed.info, "target_mis_sort": target_mis_sort})
    rule = {"evidence_weight": chosen.evidence_weight} if chosen.item_rule == "sum" else \
        {key: getattr(chosen, key) for key in OFFSET_KEYS}
    report = {"chosen": {"k": chosen.k, "temperature": chosen.temperature, "untouched_bias": chosen.untouched_bias,
                         "item_rule": chosen.item_rule, **rule, "known_margin": chosen.known_margin,
                         "confidence": chosen.confidence, "untouched_confidence": chosen.untouched_confidence,
                         "open_threshold": chosen.open_threshold, "refuse_early": chosen.refuse_early,
                         "outlier_ratio": chosen.outlier_ratio, "likeness_ratio": chosen.likeness_ratio,
                         "extra_presses": chosen.extra_presses},
              "validation": val_summary, "validation_nll": {"nll_before": nll0, "nll_after": nll, "k": k},
              "validation_worlds": [{"touched": len(w.touched), "validation_fabrics": len(w.val_fabrics)} for w in worlds],
              **({"validation_own_world": own_world} if own_world else {}),
              "target_mis_sort": target_mis_sort,
              "meets_target_on_validation": bool(val_summary["all"]["mis-sort"] <= target_mis_sort),
              "item_rules": {name: {"right": r[2]["all"]["right"], "mis_sort": r[2]["all"]["mis-sort"],
                                    "reject": r[2]["all"]["reject"], "presses": r[2]["all"]["presses"]}
                             for name, r in by_rule.items()},
              "tried": tried_rows, "outlier_ratios": outlier_rows, "extra_presses": extra_rows}
    log(f"scene decision chosen on validation ({len(worlds)} world(s), "
        f"{sum(len(w.val_fabrics) for w in worlds)} validation fabrics): k={chosen.k}, item rule {chosen.item_rule}, "
        f"margin {chosen.known_margin:g}{', refuse early' if chosen.refuse_early else ''}, "
        f"outlier presses {'kept' if math.isinf(chosen.outlier_ratio) else f'beyond {chosen.outlier_ratio:g} spreads left out'}, "
        f"likeness {'not asked' if math.isinf(chosen.likeness_ratio) else f'within {chosen.likeness_ratio:g} times'}, "
        f"{chosen.extra_presses} extra presses, "
        f"confidence {chosen.confidence:g} (untouched {chosen.untouched_confidence:g}): "
        f"right {val_summary['all']['right']:.1%}, mis-sort {val_summary['all']['mis-sort']:.1%}, "
        f"reject {val_summary['all']['reject']:.1%} (sum rule {summary_sum['all']['right']:.1%} / "
        f"{summary_sum['all']['mis-sort']:.1%}, offset rule {summary_off['all']['right']:.1%} / "
        f"{summary_off['all']['mis-sort']:.1%})")
    return deployed, report


def with_known(model: SceneModel, x: np.ndarray, y: np.ndarray, names: list[str]) -> tuple[SceneModel, dict]:
    """``model`` that also knows ``names`` (fabrics no bundle class is: the validation fabrics)
    only to refuse them: one class each at the mean of its training presses (the first part of
    each fabric's presses in press order, ``runtime.dataset.press_partition``, as touched fabrics'
    means are) in the model's own space, appended as ``known_only``; every choice stays as it
    was. ``x``, ``y``: each fabric's presses in press order (``y`` indexes ``names``). Returns the
    model and each fabric's later presses (the rest), which no mean read."""
    from vs2t_edge.runtime.dataset import press_partition

    clash = sorted(set(names) & set(model.classes))
    if clash:
        raise ValueError(f"scene model: {clash} are classes already")
    z = model.project(x)
    means, later = [], {}
    for c, name in enumerate(names):
        rows = np.flatnonzero(y == c)
        if len(rows) < 5:
            raise ValueError(f"fabric {name}: {len(rows)} presses, need at least 5 to split train/val/test")
        p_tr, p_va, p_te = press_partition(len(rows))
        means.append(z[rows[p_tr]].mean(axis=0))
        later[name] = x[rows[np.concatenate([p_va, p_te])]]
    if not names:
        return model, later
    return replace(model, classes=tuple(model.classes) + tuple(names),
                   means=np.concatenate([model.means, np.stack(means)]),
                   known_only=tuple(model.known_only) + tuple(names)), later


def _test_rows(touched: list[str], touched_test: tuple[np.ndarray, np.ndarray], untouched: list[str],
               untouched_presses: tuple[np.ndarray, np.ndarray], extra: dict[str, np.ndarray] | None) -> dict:
    """fabric -> presses of the test jobs: touched fabrics' test presses, untouched fabrics' presses,
    and ``extra`` (off-scene pools)."""
    (xt, yt), (xu, yu) = touched_test, untouched_presses
    rows = {touched[c]: xt[yt == c] for c in range(len(touched))}
    rows.update({untouched[c]: xu[yu == c] for c in range(len(untouched))})
    rows.update(extra or {})
    return rows


def stranger_jobs(models: dict[str, SceneModel], touched: list[str], touched_test: tuple[np.ndarray, np.ndarray],
                  untouched: list[str], untouched_presses: tuple[np.ndarray, np.ndarray],
                  strangers: dict[str, np.ndarray], *, n_scenes: int = N_SCENES, seed: int = 0) -> dict:
    """The test jobs of ``evaluate_scenes`` with ``strangers`` (fabric -> presses) in the pool of
    off-scene pieces, decided by each of ``models`` on the same jobs and presses: name -> summary
    (runtime.sorting.summarise)."""
    rows = _test_rows(touched, touched_test, untouched, untouched_presses, strangers)
    scenes = so.draw_scenes(touched, untouched, tuple(strangers), n_scenes, n_untouched=min(3, len(untouched)),
                            seed=seed + 3)
    return {name: so.summarise(so.simulate_scenes(scenes, press_tables(m, rows), evidence_for(m), seed=seed + 3))
            for name, m in models.items()}


def evaluate_scenes(model: SceneModel, touched: list[str], touched_test: tuple[np.ndarray, np.ndarray],
                    untouched: list[str], untouched_presses: tuple[np.ndarray, np.ndarray], *,
                    off_pool: dict[str, np.ndarray] | None = None, n_scenes: int = N_SCENES, seed: int = 0,
                    items_per_fabric: int = 4, targets: Mapping[float, SceneModel] | None = None,
                    folds: Mapping[int, SceneModel] | None = None) -> dict:
    """Item-level numbers on scenes of the split's test fabrics (module doc), the risk-coverage
    curve and the per-press and per-item calibration error. ``targets``: mis-sort target -> the
    model validation chose for it (``model`` itself at its own), priced on the same jobs beside the
    operator's knobs; ``folds``: the same for the number of validation folds (train/folds.py)."""
    xt, yt = touched_test
    xu, yu = untouched_presses
    rows = _test_rows(touched, touched_test, untouched, untouched_presses, off_pool)
    tables = press_tables(model, rows)
    n_u = min(3, len(untouched))
    scenes = so.draw_scenes(touched, untouched, tuple(off_pool or ()), n_scenes, n_untouched=n_u, seed=seed + 1)
    recs = so.simulate_scenes(scenes, tables, evidence_for(model), seed=seed + 1, items_per_fabric=items_per_fabric)
    out = so.summarise(recs)
    checks = scene_checks(model, scenes)  # once: the outcomes and the label jobs' teach_flagged read them
    out["job_check"] = job_check_outcomes(model, scenes, recs, items_per_fabric, checks)
    rc = so.risk_coverage(recs)
    out["risk_coverage"] = {"area": rc["area"], "coverage": rc["coverage"][::max(1, len(rc["coverage"]) // 50)],
                            "mis_sort": rc["mis_sort"][::max(1, len(rc["mis_sort"]) // 50)]}
    # the operator's knobs on the same jobs, one at a time (a price list; the choice was validation's)
    # (and the outlier-press and likeness rules, training's choices, priced beside them; the likeness
    # rule acts under the offset item rule only: a sum-rule model's rows repeat the operating point)
    out["knobs"] = so.knob_prices(model, scenes, tables, max_presses=MAX_PRESSES, items_per_fabric=items_per_fabric,
                                  seed=seed + 1, records=recs, grid={**so.KNOB_GRID, "outlier_ratio": OUTLIER_RATIOS,
                                        "likeness_ratio": ns.OFFSET_GRID["likeness_ratio"]})
    out["knobs"] += twin_prices(model, scenes, tables, items_per_fabric=items_per_fabric, seed=seed + 1)
    choices = [("mis_sort_target", 100 * float(t), m) for t, m in sorted((targets or {}).items())] + \
        [("validation_folds", float(n), m) for n, m in sorted((folds or {}).items())]
    for knob, value, m in choices:  # each a whole operating point validation chose for it
        own = m is model
        row = out["knobs"][0] if own else so.knob_prices(m, scenes, press_tables(m, rows), max_presses=MAX_PRESSES,
                                                          items_per_fabric=items_per_fabric, seed=seed + 1, grid={})[0]
        out["knobs"].append({**row, "knob": knob, "value": value, "own": own})
    in_scene = [r for r in recs if r.kind != "off-scene"]
    out["item_ece"] = so.expected_calibration_error([r.confidence for r in in_scene],
                                                    [r.candidate == r.truth for r in in_scene])
    # per press over all bundle classes (not the fabrics it knows only to refuse: the paper's
    # protocol is over touched and untouched classes)
    x = np.concatenate([xt, xu])
    lab = np.concatenate([yt, len(touched) + yu])
    pm = model.subset([c for c in model.classes if c not in model.known_only])
    d2 = pm.sq_distances(x)
    raw = so.log_softmax(-0.5 * d2)
    cal = so.log_softmax(pm.scores(d2))
    out["press_ece"] = {"before": so.expected_calibration_error(np.exp(raw.max(1)), raw.argmax(1) == lab),
                        "after": so.expected_calibration_error(np.exp(cal.max(1)), cal.argmax(1) == lab)}
    out["press_accuracy"] = float(np.mean(cal.argmax(1) == lab))
    # the paper's per-press protocol for the same one-softmax model over every bundle class (no
    # router): per-class mean accuracy on touched test presses and on untouched presses, and H
    pred = cal.argmax(1)
    acc_t = float(np.mean([np.mean(pred[lab == c] == c) for c in range(len(touched)) if np.any(lab == c)]))
    acc_u = float(np.mean([np.mean(pred[lab == c] == c) for c in range(len(touched), len(touched) + len(untouched))
                           if np.any(lab == c)])) if len(untouched) else float("nan")
    out["press_gzsl"] = {"acc_t": acc_t, "acc_u": acc_u,
                         "H": 2 * acc_t * acc_u / (acc_t + acc_u) if acc_t + acc_u > 0 else 0.0}
    out["n_scenes"] = n_scenes
    if model.for_labels() is not None:
        out["operator_labels"] = operator_label_jobs(model, tables, scenes, seed=seed + 2, checks=checks)
    return out


TWIN_RATIOS = (0.5, 1.0, 2.0)  # evidence.twin_ratio, priced on the test jobs (runtime/operating_point.py)


def twin_prices(model: SceneModel, scenes, tables: dict, *, items_per_fabric: int, seed: int) -> list[dict]:
    """The same jobs with each job's twins (``SceneModel.twins``: touched fabrics within that many
    times the generator's expected error of an untouched fabric's synthesis) held to
    ``TWIN_CONFIDENCE``, one row per ratio: what sending their doubtful pieces to the reject bin buys
    in mis-sorts and costs in pieces right. Priced, not chosen (the cell config's key)."""
    rows = []
    for ratio in TWIN_RATIOS:
        recs = so.simulate_scenes(scenes, tables, so.scene_evidence(model, MAX_PRESSES, twin_ratio=ratio), seed=seed,
                                  items_per_fabric=items_per_fabric, max_presses=MAX_PRESSES)
        row = so.knob_prices(model, scenes, tables, max_presses=MAX_PRESSES, items_per_fabric=items_per_fabric,
                             seed=seed, grid={}, records=recs)[0]
        rows.append({**row, "knob": "twin_ratio", "value": ratio, "own": False})
    return rows


def scene_checks(model: SceneModel, scenes) -> dict:
    """The job check (runtime/job_check.py) of each scene with the model's own evidence: scene ->
    its ``FabricCheck`` list."""
    from vs2t_edge.runtime.job_check import check_job

    make = evidence_for(model)
    return {scene: check_job(model, scene.classes, lambda: make(scene), MAX_PRESSES) for scene in scenes}


def job_check_outcomes(model: SceneModel, scenes, recs, items_per_fabric: int, checks: dict | None = None) -> dict:
    """How well the job check (runtime/job_check.py, run before a job on the model alone) foretold
    the bins of these jobs: per kind, the scene fabrics it passed and those it flagged, with the share
    of their pieces in the right bin (each job's fabric counted once per job). ``recs``: the jobs'
    records as ``runtime.sorting.simulate_scenes`` made them from ``scenes`` (in their order);
    ``checks``: ``scene_checks`` of them, when the caller has it."""
    checks = checks if checks is not None else scene_checks(model, scenes)
    groups: dict[str, dict[str, list]] = {}
    start = 0
    for scene in scenes:
        n = items_per_fabric * len(scene.classes + scene.off_scene)
        mine = recs[start:start + n]
        start += n
        for check in checks[scene]:
            right = [r.outcome == so.RIGHT for r in mine if r.truth == check.fabric]
            if right:
                groups.setdefault(check.kind, {}).setdefault("passed" if check.sorts else "flagged", []).append(
                    float(np.mean(right)))
    if start != len(recs):
        raise ValueError(f"job check: {len(recs)} records for jobs that make {start}")
    return {kind: {name: {"fabrics": len(v), "right": float(np.mean(v))} for name, v in g.items()}
            for kind, g in groups.items()}


LABEL_JOB_LENGTHS = (4, 10)  # pieces of each fabric in one job


def operator_label_jobs(model: SceneModel, tables: dict, scenes, *, seed: int = 0, checks: dict | None = None) -> dict:
    """Learning from the reject bin (runtime/feedback.py), outside the zero-shot protocol: the
    same scenes as jobs whose pieces come in a random order, each rejected piece of a scene fabric
    labelled by the operator before the next; beside the same jobs, orders and presses without
    labels (paired); ``teach``: the same with one labelled teach piece of each untouched fabric
    pressed before the job; and ``teach_flagged``: a teach piece only of the untouched fabrics the
    job check flags (runtime/job_check.py; what the demo's operator does). Per job length (pieces
    per fabric, ``LABEL_JOB_LENGTHS``); ``checks``: ``scene_checks`` of the scenes, when the caller has it."""
    checks = checks if checks is not None else scene_checks(model, scenes)
    flagged = {scene: [c.fabric for c in cs if c.kind == "untouched" and not c.sorts] for scene, cs in checks.items()}
    per_job = float(np.mean([len(flagged[scene]) for scene in scenes]))
    out = {}
    for n in LABEL_JOB_LENGTHS:
        out[str(n)] = {name: so.summarise(so.simulate_with_labels(
            scenes, tables, model, labels=on, items_per_fabric=n, max_presses=MAX_PRESSES, seed=seed, teach=teach))
            for name, on, teach in (("without", False, False), ("with", True, False), ("teach", True, True),
                                    ("teach_flagged", True, flagged.__getitem__))}
        out[str(n)]["teach_flagged"]["teach_pieces_per_job"] = per_job
    return out


__all__ = ["MIS_SORT_TARGETS", "ValidationWorld", "fit_scene_decision", "with_known", "stranger_jobs", "evaluate_scenes", "scene_checks", "job_check_outcomes", "operator_label_jobs", "press_tables", "evidence_for", "K_CHOICES"]

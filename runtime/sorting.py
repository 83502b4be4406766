"""How a sorting line judges the cell: per item, by its bins.

Each piece ends in one of three ways:

- **right**: a scene fabric in its own bin, or an off-scene piece in the reject bin;
- **mis-sort**: a piece in a bin that is not its own and not the reject bin - bad cloth in a good
  batch, found late and expensive (an off-scene piece sorted as a scene fabric is one);
- **reject**: a scene fabric in the reject bin - a person looks at it.

Pieces are counted by kind: touched (a scene fabric the cell was trained on), untouched (a scene
fabric it knows only zero-shot) and off-scene (any fabric the scene does not list). The same
functions score the demo's stream, the bench's scenes and training's scene evaluation
(``simulate_scenes``: items drawn from held-out presses, decided by the cell's own
``runtime.evidence.Evidence``), so every report counts the same way.

Also here: the risk-coverage curve (mis-sort rate against the fraction of items sorted, as the
confidence needed to sort moves), the expected calibration error of a posterior, and the
temperature that minimises a posterior's negative log likelihood. Numpy only.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Callable, Iterable, Sequence

import numpy as np

from vs2t_edge.runtime.evidence import UNKNOWN, Evidence
from vs2t_edge.runtime.names import OFF_SCENE_PREFIX
from vs2t_edge.runtime.operating_point import held_back, scene_model_rule

RIGHT, MIS_SORT, REJECT = "right", "mis-sort", "reject"
OUTCOMES = (RIGHT, MIS_SORT, REJECT)
KINDS = ("touched", "untouched", "off-scene")
# why a piece went to the reject bin (runtime/evidence.py ``stopped_by`` and the cell's own), in words
REASONS = {"press_limit": "never confident within the press limit", "off_scene": "refused as off-scene",
           "confident": "confident", "unlabelled_guard": "the zero-shot guard",
           "confusable_guard": "the guard of an untaught twin", "no_usable_frames": "no usable frames",
           "camera_reopened": "the camera reopened", "fault": "a fault", "stop": "the service stopped"}


def reject_reason(label: str, stopped_by: str) -> str:
    """Why a piece decided ``label`` went to the reject bin, in words, for the person there (the demo's
    line and `vs2t-edge label --list`): a stranger the operator taught, else its decision's rule."""
    if label.startswith(OFF_SCENE_PREFIX):
        return "a stranger the operator taught"
    return REASONS.get(stopped_by, stopped_by)


def outcome(truth: str, label: str, scene: Iterable[str], sorted_: bool = True) -> str:
    """right / mis-sort / reject of one piece. ``sorted_`` False: the cell sent it to the reject
    bin whatever its label (a fault)."""
    scene = set(scene)
    to_reject = (not sorted_) or label == UNKNOWN or label not in scene
    if truth not in scene:
        return RIGHT if to_reject else MIS_SORT
    if to_reject:
        return REJECT
    return RIGHT if label == truth else MIS_SORT


@dataclass(frozen=True)
class ItemRecord:
    truth: str
    kind: str  # touched | untouched | off-scene
    label: str  # what the cell decided (UNKNOWN: reject bin)
    confidence: float  # the leading scene class's posterior
    presses: int
    outcome: str
    candidate: str = ""  # the leading scene class, sorted or not (for the risk-coverage curve)
    off_scene: bool = False  # the off-scene checks refused it (never sorted at any confidence)


def record(truth: str, kind: str, decision, scene: Sequence[str], sorted_: bool = True) -> ItemRecord:
    """An ItemRecord from a ``runtime.evidence.ItemDecision`` (or anything with label, confidence,
    presses, stopped_by and log_posterior)."""
    lp = getattr(decision, "log_posterior", None) or {}
    candidate = max(lp, key=lp.get) if lp else decision.label
    return ItemRecord(truth, kind, decision.label, float(decision.confidence), int(decision.presses),
                      outcome(truth, decision.label, scene, sorted_), candidate,
                      getattr(decision, "stopped_by", "") == "off_scene")


def _rates(records: Sequence[ItemRecord]) -> dict:
    n = len(records)
    out = {o: (sum(r.outcome == o for r in records) / n if n else math.nan) for o in OUTCOMES}
    out["n"] = n
    out["presses"] = float(np.mean([r.presses for r in records])) if n else math.nan
    return out


def _refused(records: Sequence[ItemRecord]) -> float:
    return sum(r.off_scene for r in records) / len(records) if records else math.nan


def summarise(records: Sequence[ItemRecord], seconds_per_press: float | None = None,
              seconds_per_item: float = 0.0) -> dict:
    """Rates of right / mis-sort / reject over all items and per kind, presses per item, and items
    per minute when the arm's time per press (and per item: reference frame, gate) is given."""
    out = {"all": _rates(records), "by_kind": {k: _rates([r for r in records if r.kind == k]) for k in KINDS
                                               if any(r.kind == k for r in records)}}
    # the share of pieces the off-scene rules sent to the reject bin (the rest there: not confident, a
    # labels' guard, a stranger the operator taught, or a fault)
    out["off_scene_rule"] = {"all": _refused(records),
                             "by_kind": {k: _refused([r for r in records if r.kind == k]) for k in out["by_kind"]}}
    if seconds_per_press is not None and records:
        per_item = seconds_per_item + seconds_per_press * out["all"]["presses"]
        out["items_per_min"] = 60.0 / per_item if per_item > 0 else math.inf
    return out


@dataclass(frozen=True)
class ArmTimes:
    """The arm's time per press, s (medians): to above the next grid point, the press, the lift.
    ``from_bench`` reads the JSON of ``python -m vs2t_edge.sim.ursim --bench N --json FILE`` (the
    simulated UR5 through the real ur_rtde client, docs/arm.md) or the same measured on a robot."""

    move_above_s: float
    press_s: float
    retract_s: float

    @property
    def per_press_s(self) -> float:
        return self.move_above_s + self.press_s + self.retract_s

    @classmethod
    def from_bench(cls, data: dict, name: str = "arm times") -> "ArmTimes":
        try:
            values = {k: float(data[k]["median"]) for k in ("move_above_s", "press_s", "retract_s")}
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{name}: needs move_above_s, press_s and retract_s, each with a median "
                             "(the JSON of `python -m vs2t_edge.sim.ursim --bench 9 --json FILE`)") from None
        if not all(math.isfinite(v) and v >= 0 for v in values.values()) or sum(values.values()) <= 0:
            raise ValueError(f"{name}: arm times must be finite, >= 0 and not all 0: {values}")
        return cls(**values)


def items_per_minute(presses: float, arm: ArmTimes, score_s: float, overlap: bool) -> float:
    """Pieces per minute from presses per piece, the arm's times and the model's time per press.

    Sequential, every press waits for its score: arm + score. Overlapped
    (runtime/press_pipeline.py), a press is scored while the gel lifts and the arm never waits; a
    score slower than the lift makes one speculative press at the end of a piece the evidence
    decides early, counted here as one more press per piece (an upper bound of its cost). The
    piece's own overheads (reference frame, gate) are left out: they are the same either way."""
    if presses <= 0:
        return math.nan
    if not overlap:
        per_piece = presses * (arm.per_press_s + score_s)
    else:
        per_piece = (presses + (1.0 if score_s > arm.retract_s else 0.0)) * arm.per_press_s
    return 60.0 / per_piece


def risk_coverage(records: Sequence[ItemRecord]) -> dict:
    """Mis-sort rate (of all items) against coverage (fraction of items sorted) as the confidence
    needed to sort moves from 1 down to 0, at the presses each item took. An item the off-scene
    checks refused is never sorted. Returns the curve's points and the area under it (lower is better)."""
    n = len(records)
    if not n:
        return {"coverage": [], "mis_sort": [], "threshold": [], "area": math.nan}
    sortable = [r for r in records if not r.off_scene and r.candidate]
    sortable.sort(key=lambda r: -r.confidence)
    cov, mis, thr = [0.0], [0.0], [1.0]
    wrong = 0
    for i, r in enumerate(sortable):
        in_scene_right = r.candidate == r.truth
        wrong += 0 if in_scene_right else 1
        cov.append((i + 1) / n)
        mis.append(wrong / n)
        thr.append(r.confidence)
    area = float(np.sum(np.diff(cov) * (np.asarray(mis[1:]) + np.asarray(mis[:-1])) / 2)) if len(cov) > 1 else 0.0
    return {"coverage": cov, "mis_sort": mis, "threshold": thr, "area": area}


def expected_calibration_error(confidence: np.ndarray, correct: np.ndarray, n_bins: int = 10) -> float:
    """ECE: the confidence-weighted gap between confidence and accuracy over equal-width bins."""
    conf = np.asarray(confidence, np.float64).reshape(-1)
    ok = np.asarray(correct, np.float64).reshape(-1)
    if conf.size == 0:
        return math.nan
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    idx = np.clip(np.digitize(conf, edges[1:-1], right=True), 0, n_bins - 1)
    total = 0.0
    for b in range(n_bins):
        m = idx == b
        if m.any():
            total += m.mean() * abs(conf[m].mean() - ok[m].mean())
    return float(total)


def _nll(scores: np.ndarray, labels: np.ndarray, t: float) -> float:
    s = scores / t
    m = s.max(axis=1, keepdims=True)
    lse = (m + np.log(np.exp(s - m).sum(axis=1, keepdims=True)))[:, 0]
    return float(np.mean(lse - s[np.arange(len(labels)), labels]))


def fit_temperature(scores: np.ndarray, labels: np.ndarray, lo: float = 1e-2, hi: float = 1e3) -> float:
    """T > 0 minimising the NLL of softmax(scores / T) (temperature scaling, Guo et al. 2017): a
    log-spaced scan, then a golden-section refinement (the NLL is unimodal in log T)."""
    scores = np.asarray(scores, np.float64)
    labels = np.asarray(labels, np.int64)
    grid = np.geomspace(lo, hi, 41)
    i = int(np.argmin([_nll(scores, labels, t) for t in grid]))
    a, b = math.log(grid[max(i - 1, 0)]), math.log(grid[min(i + 1, len(grid) - 1)])
    g = (math.sqrt(5) - 1) / 2
    for _ in range(40):
        c, d = b - g * (b - a), a + g * (b - a)
        if _nll(scores, labels, math.exp(c)) < _nll(scores, labels, math.exp(d)):
            b = d
        else:
            a = c
    return float(math.exp((a + b) / 2))


def log_softmax(scores: np.ndarray) -> np.ndarray:
    s = np.asarray(scores, np.float64)
    m = s.max(axis=1, keepdims=True)
    return s - (m + np.log(np.exp(s - m).sum(axis=1, keepdims=True)))


# ------------------------------------------------------------------ scenes drawn from held-out presses


@dataclass(frozen=True)
class Press:
    """What ``Evidence.add`` reads of a press (a ``runtime.inference.PressScore`` has the same)."""

    log_posterior: dict
    sq_distance: dict | None = None
    scene_z: np.ndarray | None = None


def scene_model_presses(scene_model, features: np.ndarray, dtype=np.float64) -> list[Press]:
    """Presses of ``features`` (N, D) as the cell scores them with a scene model: log posterior and
    squared distance over its classes, and the projection its offset item rule reads."""
    z = scene_model.project(features, dtype)
    lp, d2 = scene_model.log_posterior_projected(z)
    classes = scene_model.classes
    return [Press(dict(zip(classes, a.tolist())), dict(zip(classes, b.tolist())), c) for a, b, c in zip(lp, d2, z)]


@dataclass(frozen=True)
class Scene:
    touched: tuple[str, ...]
    untouched: tuple[str, ...]
    off_scene: tuple[str, ...]

    @property
    def classes(self) -> tuple[str, ...]:
        return self.touched + self.untouched

    def kind(self, fabric: str) -> str:
        return "touched" if fabric in self.touched else "untouched" if fabric in self.untouched else "off-scene"


def posterior_presses(classes: Sequence[str], log_posteriors: np.ndarray) -> list[Press]:
    """Presses of one fabric from their per-press log posteriors over ``classes`` (rows)."""
    return [Press(dict(zip(classes, row.tolist()))) for row in log_posteriors]


def draw_scenes(touched: Sequence[str], untouched: Sequence[str], off_pool: Sequence[str], n_scenes: int, *,
                n_touched: int = 5, n_untouched: int = 3, n_off: int = 3, seed: int = 0) -> list[Scene]:
    """Seeded scenes: ``n_touched`` of the touched fabrics, ``n_untouched`` of the untouched ones,
    and ``n_off`` off-scene fabrics from ``off_pool`` plus the touched and untouched ones the scene
    left out (fabrics the cell knows that this job does not list)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_scenes):
        st = tuple(sorted(rng.choice(touched, min(n_touched, len(touched)), replace=False).tolist()))
        su = tuple(sorted(rng.choice(untouched, min(n_untouched, len(untouched)), replace=False).tolist())) \
            if len(untouched) else ()
        pool = [f for f in list(touched) + list(untouched) + list(off_pool) if f not in st and f not in su]
        so = tuple(sorted(rng.choice(pool, min(n_off, len(pool)), replace=False).tolist())) if pool else ()
        out.append(Scene(st, su, so))
    return out


def _draw_limit(evidence, max_presses: int) -> int:
    """How many of a fabric's presses a simulated piece may draw: ``max_presses``, or the
    evidence's ``press_limit`` when that is more (its extra presses)."""
    return max(max_presses, getattr(evidence, "press_limit", 0))


def simulate_scenes(scenes: Sequence[Scene], presses: dict[str, list[Press]],
                    evidence_factory: Callable[[Scene], object], *, items_per_fabric: int = 4,
                    max_presses: int = 5, seed: int = 0) -> list[ItemRecord]:
    """Items of every scene fabric and off-scene fabric, each a random order of that fabric's
    held-out ``presses`` fed to the cell's own evidence (``evidence_factory(scene)``) until it
    decides or the presses (``max_presses``, or the evidence's ``press_limit`` when that is more:
    its extra presses) run out."""
    rng = np.random.default_rng(seed)
    records = []
    for scene in scenes:
        for fabric in scene.classes + scene.off_scene:
            pool = presses[fabric]
            for _ in range(items_per_fabric):
                ev = evidence_factory(scene)
                order = rng.permutation(len(pool))[:_draw_limit(ev, max_presses)]
                decision = _press_until_decided(ev, pool, order)
                records.append(record(fabric, scene.kind(fabric), decision, scene.classes))
    return records


def _press_until_decided(ev, pool: list[Press], order):
    """The item's decision: ``pool``'s presses in ``order`` fed to the evidence ``ev`` until it
    decides, else its decision once they run out."""
    for i in order:
        decision = ev.add(pool[i])
        if decision is not None:
            return decision
    return ev.decide()


def simulate_with_labels(scenes: Sequence[Scene], presses: dict[str, list[Press]], model, *,
                         labels: bool = True, items_per_fabric: int = 4, max_presses: int = 5,
                         seed: int = 0, teach: bool | Callable[[Scene], Sequence[str]] = False) -> list[ItemRecord]:
    """Each scene one job: its pieces (``items_per_fabric`` of every scene and off-scene fabric)
    in a random order, decided by the cell's evidence with ``model``'s operating point; with
    ``labels``, every piece that lands in the reject bin is labelled by the operator before the
    next piece: a scene fabric's label re-estimates its mean if it is untouched, an off-scene
    piece's teaches the cell that stranger (runtime/feedback.py). ``labels`` False gives the same
    jobs, orders and presses without them: the paired zero-shot baseline. Needs an offset-rule
    setting (``SceneModel.for_labels``); the model's own rule decides until a label teaches.
    ``teach``: before each job, one known piece of every untouched fabric of the job is pressed and
    labelled (the operator's teach pieces; not counted); a function of the scene instead names the
    fabrics to teach (the job check's flagged ones, train/decision.py). No piece of a job shows a press a labelled
    or teach piece of the job showed (what taught a mean never tests it); a piece left no press of
    its own is not counted."""
    from vs2t_edge.runtime.feedback import adapt, item_evidence

    def make(m, classes):
        confidence, opts = scene_model_rule(m)
        return Evidence(classes, confidence, max_presses, **opts)

    base = model.for_labels()  # what labels update: the offset-rule setting (a sum-rule model's stored one)
    if base is None:
        raise ValueError("simulate_with_labels: the scene model has no offset-rule setting to learn with "
                         "(a sum-rule model exported before labels_rule)")

    rng = np.random.default_rng(seed)
    records = []
    for scene in scenes:
        stream = [f for f in scene.classes + scene.off_scene for _ in range(items_per_fabric)]
        rng.shuffle(stream)
        labelled: dict[str, list] = {}
        strangers: dict[str, list] = {}
        shown: dict[str, set] = {}  # presses of the job's teach and labelled pieces, kept out of its other pieces
        for fabric in _taught(scene, teach):
            taught = rng.permutation(len(presses[fabric]))[:max_presses]
            shown[fabric] = set(taught.tolist())
            zs = np.stack([np.asarray(presses[fabric][i].scene_z, np.float64) for i in taught])
            labelled[fabric] = [(zs.mean(axis=0), len(zs))]
        current = adapt(base, labelled)
        for fabric in stream:
            pool = presses[fabric]
            perm = rng.permutation(len(pool))  # drawn alike with and without labels: the runs pair
            unseen = [i for i in perm.tolist() if i not in shown.get(fabric, ())]
            if not unseen:  # every press of the fabric taught this job already
                continue
            ev = item_evidence(model, current, scene.classes, labelled, strangers, make)
            order = unseen[:_draw_limit(ev, max_presses)]
            rec = record(fabric, scene.kind(fabric), _press_until_decided(ev, pool, order), scene.classes)
            records.append(rec)
            # in the reject bin the operator says what it was; an untouched fabric's or a stranger's
            # label teaches the cell (a touched fabric's mean is its training presses')
            rejected = rec.label not in scene.classes
            if labels and rejected and (fabric in model.untouched or fabric not in scene.classes):
                (labelled if fabric in scene.classes else strangers).setdefault(fabric, []).append(
                    (ev.z_mean, ev.mean_presses))
                shown.setdefault(fabric, set()).update(order[:ev.presses])
                current = adapt(base, labelled, strangers)
    return records


def _taught(scene: Scene, teach) -> Sequence[str]:
    """The fabrics ``simulate_with_labels`` presses a teach piece of before ``scene``'s job."""
    return teach(scene) if callable(teach) else scene.untouched if teach else ()


def teach_presses(scenes: Sequence[Scene], presses: dict[str, list[Press]],
                  teach: bool | Callable[[Scene], Sequence[str]], max_presses: int = 5) -> int:
    """The presses ``simulate_with_labels``' teach pieces take over ``scenes`` (``max_presses``
    each, or what the fabric has): no piece of the records, yet arm time the jobs spent - what
    pieces per minute must pay with them."""
    return sum(min(max_presses, len(presses[f])) for scene in scenes for f in _taught(scene, teach))


def scene_evidence(model, max_presses: int = 5, extra_presses: int | None = None,
                   twin_ratio: float | None = None) -> Callable[[Scene], Evidence]:
    """The evidence the cell builds for a scene from a scene model's operating point
    (``runtime.scene_model.SceneModel``: confidences, press weight, open-set and known-class rules,
    its extra presses), ``extra_presses`` overriding the model's as the config's
    ``evidence.extra_presses`` does (runtime/evidence.py; such an evidence may take up to
    ``press_limit`` presses); ``twin_ratio``: the config's ``evidence.twin_ratio``, each scene's twins
    held back as the cell holds them (runtime/operating_point.py ``held_back``)."""
    confidence, opts = scene_model_rule(model)
    if extra_presses is not None:
        opts = {**opts, "extra_presses": int(extra_presses)}

    def make(scene: Scene) -> Evidence:
        twins = model.twins(scene.classes, float(twin_ratio)) if twin_ratio else []
        return Evidence(scene.classes, confidence, max_presses, **held_back(opts, twins, confidence))
    return make


# The operator's knobs (the cell config's evidence.confidence, evidence.untouched_confidence,
# evidence.max_presses and evidence.extra_presses; runtime/operating_point.py) and the values
# ``knob_prices`` moves each to
KNOB_GRID = {"confidence": (0.5, 0.7, 0.8, 0.9, 0.95, 0.99),
             "untouched_confidence": (0.5, 0.7, 0.8, 0.9, 0.95, 0.99),
             "max_presses": (1, 2, 3, 5, 9),
             "extra_presses": (0, 2, 4, 8)}


def knob_prices(model, scenes: Sequence[Scene], presses: dict[str, list[Press]], *, max_presses: int = 5,
                items_per_fabric: int = 4, seed: int = 0, grid: dict | None = None,
                records: Sequence[ItemRecord] | None = None) -> list[dict]:
    """The same jobs decided with one operator knob moved at a time, the others at the scene
    model's operating point (its own confidences, ``max_presses``): per setting, right / mis-sort /
    reject of all pieces and per kind, presses per piece, and the coverage (share of pieces sorted
    into a fabric's bin) and mis-sort rate a risk-coverage plot marks. A price list for the person
    who runs the cell, measured on the jobs it is given; choosing stays on validation (training).
    ``records``: the jobs' item records at the operating point when the caller decided them already
    (training's report); a knob at the operating point's own value is that row, not decided again.
    ``grid`` may also move the scene model's ``outlier_ratio`` and ``likeness_ratio`` (training's
    choices, no config key)."""

    def price(recs: Sequence[ItemRecord]) -> dict:
        s = summarise(recs)
        a, off = s["all"], s["by_kind"].get("off-scene", {RIGHT: 0.0, "n": 0})
        in_reject_bin = a[REJECT] + off[RIGHT] * off["n"] / a["n"]  # rejected scene pieces and refused strangers
        return {"right": a[RIGHT], "mis-sort": a[MIS_SORT], "reject": a[REJECT], "presses": a["presses"],
                "coverage": 1.0 - in_reject_bin, "by_kind": {k: {o: r[o] for o in OUTCOMES} for k, r in s["by_kind"].items()}}

    def run(m, mp: int, extra: int | None = None) -> dict:
        return price(simulate_scenes(scenes, presses, scene_evidence(m, mp, extra), items_per_fabric=items_per_fabric,
                                     max_presses=mp, seed=seed))

    base = price(records) if records is not None else run(model, max_presses)
    rows = [{"knob": "operating point", "value": None, **base}]
    own = {"confidence": float(model.confidence), "untouched_confidence": float(model.untouched_confidence),
           "max_presses": max_presses, "extra_presses": int(getattr(model, "extra_presses", 0)),
           "outlier_ratio": float(model.outlier_ratio), "likeness_ratio": float(model.likeness_ratio)}
    for knob, values in (KNOB_GRID if grid is None else grid).items():
        for v in values:
            if v == own[knob]:
                rows.append({"knob": knob, "value": v, "own": True, **base})
                continue
            if knob in ("max_presses", "extra_presses"):
                row = run(model, int(v)) if knob == "max_presses" else run(model, max_presses, int(v))
            else:
                row = run(replace(model, **{knob: float(v)}), max_presses)
            rows.append({"knob": knob, "value": v, "own": False, **row})
    return rows


def plain_evidence(confidence: float, max_presses: int = 5) -> Callable[[Scene], Evidence]:
    """The evidence of a bundle without a scene model: one confidence, log posteriors summed as if
    presses were independent, no off-scene rule but the scene restriction (the baseline)."""
    return lambda scene: Evidence(scene.classes, confidence, max_presses)


def as_dict(records: Sequence[ItemRecord]) -> list[dict]:
    return [asdict(r) for r in records]


__all__ = ["RIGHT", "MIS_SORT", "REJECT", "OUTCOMES", "KINDS", "outcome", "ItemRecord", "record", "summarise",
           "REASONS", "reject_reason", "ArmTimes", "items_per_minute", "risk_coverage", "expected_calibration_error", "fit_temperature",
           "log_softmax", "Press", "scene_model_presses", "Scene", "posterior_presses", "draw_scenes", "simulate_scenes", "as_dict",
           "simulate_with_labels", "teach_presses",
           "KNOB_GRID", "knob_prices"]

"""The per-item measure a sorting line pays for (runtime/sorting.py), the scene model
(runtime/scene_model.py) and the evidence's off-scene checks (runtime/evidence.py), on hand-made cases."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.evidence import UNKNOWN, Evidence
from vs2t_edge.runtime.scene_model import LABELS_KEYS, PARAMS_KEYS, SceneModel, SceneModelError

SCENE = ("a", "b")


@pytest.mark.parametrize("truth, label, sorted_, expected", [
    ("a", "a", True, so.RIGHT),
    ("a", "b", True, so.MIS_SORT),
    ("a", UNKNOWN, True, so.REJECT),
    ("a", "a", False, so.REJECT),  # a fault sent it to the reject bin
    ("x", UNKNOWN, True, so.RIGHT),  # off-scene in the reject bin is its right bin
    ("x", "c", True, so.RIGHT),  # a label outside the scene goes to the reject bin
    ("x", "a", True, so.MIS_SORT),  # off-scene sorted as a scene fabric
])
def test_outcome_of_a_piece(truth, label, sorted_, expected):
    assert so.outcome(truth, label, SCENE, sorted_) == expected


def _rec(truth, kind, cand, conf, off=False, presses=2):
    label = cand if not off else UNKNOWN
    return so.ItemRecord(truth, kind, label, conf, presses, so.outcome(truth, label, SCENE), cand, off)


def test_summary_rates_per_kind_and_items_per_minute():
    recs = [_rec("a", "touched", "a", 0.9), _rec("a", "touched", "b", 0.8), _rec("b", "untouched", "b", 0.9),
            _rec("x", "off-scene", "a", 0.5, off=True, presses=4)]
    s = so.summarise(recs, seconds_per_press=1.5, seconds_per_item=3.0)
    assert s["all"]["right"] == 0.75 and s["all"]["mis-sort"] == 0.25 and s["all"]["reject"] == 0.0
    assert s["by_kind"]["touched"]["mis-sort"] == 0.5 and s["by_kind"]["off-scene"]["right"] == 1.0
    assert s["all"]["presses"] == 2.5
    assert s["items_per_min"] == pytest.approx(60 / (3.0 + 1.5 * 2.5))
    # why the reject bin holds its pieces: the off-scene rules' share, apart from the not confident
    recs += [_rec("a", "touched", "a", 0.99, off=True), _rec("b", "touched", UNKNOWN, 0.4)]
    s = so.summarise(recs)
    assert s["by_kind"]["touched"]["reject"] == 0.5 and s["off_scene_rule"]["by_kind"]["touched"] == 0.25
    assert s["off_scene_rule"]["by_kind"]["off-scene"] == 1.0 and s["off_scene_rule"]["all"] == pytest.approx(2 / 6)
    assert s["off_scene_rule"]["by_kind"]["untouched"] == 0.0


def test_risk_coverage_on_a_hand_made_case():
    # confidences 0.9 (right), 0.8 (wrong), 0.7 (right); one item refused as off-scene (never sorted)
    recs = [_rec("a", "touched", "a", 0.9), _rec("a", "touched", "b", 0.8), _rec("b", "untouched", "b", 0.7),
            _rec("x", "off-scene", "a", 0.99, off=True)]
    rc = so.risk_coverage(recs)
    assert rc["coverage"] == [0.0, 0.25, 0.5, 0.75]
    assert rc["mis_sort"] == [0.0, 0.0, 0.25, 0.25]
    assert rc["threshold"] == [1.0, 0.9, 0.8, 0.7]
    assert rc["area"] == pytest.approx(0.25 * 0.125 + 0.25 * 0.25)


def test_temperature_scaling_lowers_the_calibration_error_of_an_overconfident_model():
    rng = np.random.default_rng(0)
    n, c = 4000, 5
    labels = rng.integers(0, c, n)
    true_logits = rng.normal(0, 1, (n, c))
    true_logits[np.arange(n), labels] += 1.0  # about 55 % accurate
    scores = 6.0 * true_logits  # the same ranking, six times too sure
    p = np.exp(so.log_softmax(scores))
    ece_before = so.expected_calibration_error(p.max(1), p.argmax(1) == labels)
    t = so.fit_temperature(scores, labels)
    q = np.exp(so.log_softmax(scores / t))
    ece_after = so.expected_calibration_error(q.max(1), q.argmax(1) == labels)
    assert 4.0 < t < 8.0
    assert ece_before > 0.2 and ece_after < 0.05
    assert np.array_equal(p.argmax(1), q.argmax(1))  # calibration never changes a decision per press


def _blobs(seed=0, d=20, per=60):
    rng = np.random.default_rng(seed)
    centres = rng.normal(0, 4, (5, d))
    x = np.concatenate([c + rng.normal(0, 1, (per, d)) for c in centres])
    y = np.repeat(np.arange(5), per)
    return centres, x, y, rng


def test_scene_model_classifies_touched_real_and_untouched_synthesised_classes():
    centres, x, y, rng = _blobs()
    touched, untouched = ["t0", "t1", "t2"], ["u0", "u1"]
    tx, ty = x[y < 3], y[y < 3]
    synth = np.concatenate([centres[3 + k] + rng.normal(0, 0.5, (80, 20)) for k in range(2)])  # the "generator"
    m = SceneModel.fit(tx, ty, touched, synth, np.repeat([0, 1], 80), untouched, k=8)
    lp, d2 = m.log_posterior(x)
    assert lp.shape == (300, 5) and np.allclose(np.exp(lp).sum(1), 1)
    assert np.mean(lp.argmax(1) == y) > 0.95
    # a scene is a subset of rows: same scores, renormalised over the scene's classes
    sub = m.subset(["t1", "u0"])
    lps, _ = sub.log_posterior(x[y == 3])
    assert np.mean(lps.argmax(1) == 1) > 0.95
    again = SceneModel.from_params(m.to_params())
    assert again.classes == m.classes and again.untouched == m.untouched
    assert np.allclose(again.log_posterior(x)[0], lp)


def test_one_svd_serves_every_subspace_size():
    centres, x, y, rng = _blobs()
    tx, ty = x[y < 3], y[y < 3]
    synth, sy = x[y == 3], np.zeros(int(np.sum(y == 3)), int)
    axes = SceneModel.principal_axes(tx)
    for k in (2, 4, 8):
        plain = SceneModel.fit(tx, ty, ["a", "b", "c"], synth, sy, ["d"], k=k)
        shared = SceneModel.fit(tx, ty, ["a", "b", "c"], synth, sy, ["d"], k=k, axes=axes)
        assert np.array_equal(plain.basis, shared.basis) and np.array_equal(plain.means, shared.means)
    with pytest.raises(SceneModelError, match="principal axes"):
        SceneModel.fit(tx, ty, ["a", "b", "c"], synth, sy, ["d"], k=4, axes=axes[:, :5])


def test_scene_model_parameters_are_checked():
    centres, x, y, _ = _blobs()
    m = SceneModel.fit(x[y < 3], y[y < 3], ["a", "b", "c"], x[y == 3], np.zeros(60, int), ["d"], k=4)
    p = m.to_params()
    for key, bad in (("temperature", 0.0), ("evidence_weight", 1.5), ("means", np.zeros((4, 3))),
                     ("center", np.full(20, np.nan))):
        with pytest.raises(SceneModelError):
            SceneModel.from_params({**p, key: bad})
    with pytest.raises(SceneModelError, match="lack 'basis'"):
        SceneModel.from_params({k: v for k, v in p.items() if k != "basis"})
    with pytest.raises(SceneModelError):
        m.log_posterior(np.zeros((1, 19)))


def test_a_scene_model_key_this_runtime_does_not_know_is_refused_by_name():
    # a newer training's rule as a key this runtime would skip: sorting without it could put a
    # piece in a wrong bin, so the file is refused, naming the key
    centres, x, y, _ = _blobs()
    m = SceneModel.fit(x[y < 3], y[y < 3], ["a", "b", "c"], x[y == 3], np.zeros(60, int), ["d"], k=4)
    full = replace(m, known_only=(), refuse_early=True, outlier_ratio=20.0,
                   labels_rule={key: 1.0 for key in LABELS_KEYS}).to_params()
    assert set(full) <= PARAMS_KEYS  # every key the writer writes is one the reader knows
    assert SceneModel.from_params(full).outlier_ratio == 20.0
    with pytest.raises(SceneModelError, match="'crease_rule', which this runtime does not know"):
        SceneModel.from_params({**full, "crease_rule": np.array(3.0)})


class _P:
    def __init__(self, lp, d2=None):
        self.log_posterior, self.sq_distance = lp, d2


def _lp(**probs):
    return {k: math.log(v) for k, v in probs.items()}


def test_evidence_weight_slows_the_posterior_down():
    press = _P(_lp(a=0.8, b=0.2))
    full, tempered = Evidence(SCENE, 0.99, 9), Evidence(SCENE, 0.99, 9, weight=0.25)
    n_full = next(i for i in range(1, 10) if full.add(press) is not None)
    n_temp = next(i for i in range(1, 10) if tempered.add(press) is not None)
    assert n_full == 4 and n_temp == 9  # 4^n / (4^n + 1) >= 0.99 at n = 4; with weight 1/4, n >= 14 > limit


def test_a_known_fabric_outside_the_scene_is_refused_not_sorted():
    # the press looks like "c", which the bundle knows but this scene does not list
    press = _P(_lp(a=0.08, b=0.02, c=0.9))
    plain = Evidence(SCENE, 0.7, 3)
    checked = Evidence(SCENE, 0.7, 3, known_margin=0.0)
    d_plain = plain.add(press)
    assert d_plain is not None and d_plain.label == "a"  # restricted to the scene: a confident mis-sort
    d = None
    while d is None:
        d = checked.add(press)
    assert d.label == UNKNOWN and d.stopped_by == "off_scene"


def test_a_piece_far_from_every_scene_class_is_refused():
    far = _P(_lp(a=0.99, b=0.01), {"a": 500.0, "b": 900.0})
    near = _P(_lp(a=0.99, b=0.01), {"a": 20.0, "b": 900.0})
    assert Evidence(SCENE, 0.9, 2, open_threshold=100.0).add(near).label == "a"
    ev = Evidence(SCENE, 0.9, 2, open_threshold=100.0)
    assert ev.add(far) is None
    d = ev.add(far)
    assert d.label == UNKNOWN and d.stopped_by == "off_scene"


def test_class_confidence_asks_more_of_an_untouched_class():
    press = _P(_lp(a=0.1, b=0.9))
    assert Evidence(SCENE, 0.85, 1).add(press).label == "b"
    d = Evidence(SCENE, 0.85, 1, class_confidence={"b": 0.95}).add(press)
    assert d.label == UNKNOWN and d.stopped_by == "press_limit"


def test_simulated_scenes_use_every_scene_and_off_scene_fabric():
    scenes = so.draw_scenes(["t0", "t1", "t2", "t3"], ["u0", "u1"], ["s0"], 3, n_touched=2, n_untouched=1,
                            n_off=2, seed=1)
    presses = {f: [_P(_lp(**{g: (0.9 if g == f else 0.1 / 6) for g in ["t0", "t1", "t2", "t3", "u0", "u1"]}))] * 5
               for f in ["t0", "t1", "t2", "t3", "u0", "u1"]}
    presses["s0"] = [_P(_lp(**{g: 1 / 6 for g in ["t0", "t1", "t2", "t3", "u0", "u1"]}))] * 5
    recs = so.simulate_scenes(scenes, presses, lambda sc: Evidence(sc.classes, 0.8, 3, known_margin=0.0),
                              items_per_fabric=2)
    assert len(recs) == 3 * (2 + 1 + 2) * 2
    s = so.summarise(recs)
    assert s["by_kind"]["touched"]["right"] == 1.0 and s["by_kind"]["untouched"]["right"] == 1.0
    assert s["all"]["mis-sort"] == 0.0  # known off-scene fabrics refused by the margin, the stranger unsure


def test_pieces_per_minute_overlapped_hides_a_fast_score_and_prices_a_slow_one():
    """Sequential: every press waits for its score. Overlapped: a score faster than the lift costs
    nothing; a slower one costs one speculative press per piece, never more than sequential would
    for a score that slow."""
    arm = so.ArmTimes(move_above_s=0.5, press_s=1.5, retract_s=0.5)
    assert arm.per_press_s == pytest.approx(2.5)
    assert so.items_per_minute(4, arm, 0.1, overlap=False) == pytest.approx(60 / (4 * 2.6))
    assert so.items_per_minute(4, arm, 0.1, overlap=True) == pytest.approx(60 / (4 * 2.5))
    assert so.items_per_minute(4, arm, 1.0, overlap=True) == pytest.approx(60 / (5 * 2.5))  # one speculative press
    assert so.items_per_minute(4, arm, 1.0, overlap=False) == pytest.approx(60 / (4 * 3.5))
    assert math.isnan(so.items_per_minute(0, arm, 0.1, overlap=True))


def test_arm_times_read_the_arm_bench_json_and_refuse_what_is_not_one():
    good = {k: {"median": v, "max": v} for k, v in (("move_above_s", 0.3), ("press_s", 1.9), ("retract_s", 0.33))}
    assert so.ArmTimes.from_bench(good) == so.ArmTimes(0.3, 1.9, 0.33)
    with pytest.raises(ValueError, match="arm.json: needs move_above_s"):
        so.ArmTimes.from_bench({"press_s": {"median": 1.0}}, "arm.json")
    with pytest.raises(ValueError, match="finite"):
        so.ArmTimes.from_bench({**good, "press_s": {"median": float("nan")}})


def test_the_operators_knobs_are_priced_on_the_same_jobs():
    """``knob_prices``: the operating point's row is the jobs' own summary; one knob moved at a time
    on the same pieces and presses; asking more of untouched classes sorts fewer untouched pieces
    and mis-sorts no more of them on a world whose syntheses lie off the real means."""
    from dataclasses import replace

    centres, x, y, rng = _blobs(seed=3)
    touched, untouched = ["t0", "t1", "t2"], ["u0", "u1"]
    # the generator's error: each synthesis half way towards a touched fabric; a soft posterior
    synth = np.concatenate([centres[3 + k] + (centres[k] - centres[3 + k]) / 2 + rng.normal(0, 0.5, (80, 20))
                            for k in range(2)])
    m = SceneModel.fit(x[y < 3], y[y < 3], touched, synth, np.repeat([0, 1], 80), untouched, k=8)
    m = replace(m, confidence=0.9, untouched_confidence=0.7, evidence_weight=0.5, temperature=10.0)
    names = touched + untouched
    presses = {f: so.scene_model_presses(m, x[y == i]) for i, f in enumerate(names)}
    scenes = so.draw_scenes(touched, untouched, (), 6, n_touched=2, n_untouched=2, n_off=1, seed=0)
    rows = so.knob_prices(m, scenes, presses, max_presses=5, seed=7)
    assert len(rows) == 1 + sum(len(v) for v in so.KNOB_GRID.values())
    own = so.summarise(so.simulate_scenes(scenes, presses, so.scene_evidence(m, 5), max_presses=5, seed=7))
    assert rows[0]["knob"] == "operating point" and rows[0]["right"] == own["all"]["right"]
    assert rows[0]["mis-sort"] == own["all"]["mis-sort"] and rows[0]["presses"] == own["all"]["presses"]
    by = {(r["knob"], r["value"]): r for r in rows}
    assert by[("confidence", 0.9)]["own"] and by[("confidence", 0.9)]["right"] == rows[0]["right"]
    assert not by[("confidence", 0.5)]["own"]
    assert by[("max_presses", 1)]["presses"] == 1.0 and by[("max_presses", 5)]["right"] == rows[0]["right"]
    lo, hi = by[("untouched_confidence", 0.5)], by[("untouched_confidence", 0.99)]
    assert hi["by_kind"]["untouched"]["reject"] > lo["by_kind"]["untouched"]["reject"]
    assert hi["by_kind"]["untouched"]["mis-sort"] <= lo["by_kind"]["untouched"]["mis-sort"]
    assert 0.0 <= hi["coverage"] < lo["coverage"] <= 1.0


def test_teach_pieces_presses_are_paid_in_the_pieces_per_minute():
    """simulate_with_labels' teach pieces are no records (not counted), but each took up to
    max_presses of the arm: the bench's pieces per minute of a teach row pays them
    (``teach_presses`` per counted piece), where it priced only the counted pieces' presses."""
    from vs2t_edge.bench.accuracy import pieces_per_minute

    scenes = so.draw_scenes(["a", "b", "c"], ["u", "v"], (), 4, n_touched=2, n_untouched=2, seed=0)
    presses = {f: [so.Press({})] * n for f, n in (("a", 9), ("b", 9), ("c", 9), ("u", 9), ("v", 3))}
    assert so.teach_presses(scenes, presses, True, 5) == 4 * (5 + 3)  # each job teaches u (5) and v (3 it has)
    assert so.teach_presses(scenes, presses, False, 5) == 0
    assert so.teach_presses(scenes, presses, lambda s: ["v"], 5) == 4 * 3
    arm = so.ArmTimes(0.3, 1.9, 0.3)
    row = {"press": {"2": {"p50_ms": 4.0}},
           "accuracy": {"bins": {"scene_model": {"all": {"presses": 2.0}},
                                 "scene_model_teach": {"all": {"presses": 2.0, "teach_presses": 0.5}}}}}
    pieces_per_minute(row, arm)
    ppm = row["accuracy"]["bins"]["pieces_per_min"]
    assert ppm["scene_model"]["sequential"] == pytest.approx(so.items_per_minute(2.0, arm, 4e-3, False))
    assert ppm["scene_model_teach"]["sequential"] == pytest.approx(so.items_per_minute(2.5, arm, 4e-3, False))

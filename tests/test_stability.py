"""Numerical stability at the extremes (issue 5): log-softmax of +-1e4 logits, evidence over 225
presses, beta at +-inf, all / no presses touched, bad frames refused and never routed, int8 on
saturated inputs. (The density's own extremes are tests/test_novelty_stability.py.)"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from test_bundle_fixtures import SIZE, TOUCHED, UNTOUCHED, shared_bundle, world_frames
from vs2t_edge.runtime.evidence import UNKNOWN, Evidence
from vs2t_edge.runtime.inference import LOG_ZERO, PressScore, TactileModel, gzsl_log_posterior
from vs2t_edge.runtime.preprocess import FrameError

CLASSES = TOUCHED + UNTOUCHED


def _score(lp: np.ndarray, novelty=0.0, beta=0.0) -> PressScore:
    return PressScore(dict(zip(CLASSES, map(float, lp))), novelty, novelty > beta, 0.0)


@given(st.lists(st.floats(-1e4, 1e4), min_size=3, max_size=3), st.lists(st.floats(-1e4, 1e4), min_size=2, max_size=2),
       st.floats(-1e12, 1e12), st.floats(-1e12, 1e12), st.floats(1e-3, 1e3))
@settings(max_examples=200, deadline=None)
def test_posterior_of_extreme_logits_is_finite_and_normalised(lt, lu, nov, beta, temp):
    for scale in (None, 1.0, 1e6):
        lp = gzsl_log_posterior(np.array([lt]), np.array([lu]), np.array([nov]), beta, temp, scale)[0]
        assert np.all(np.isfinite(lp)) and np.all(lp <= 1e-12)
        top = lp.max()
        assert abs(top + math.log(np.exp(lp - top).sum())) < 1e-9


def test_log_softmax_of_pm_1e4_is_exact():
    lp = gzsl_log_posterior(np.array([[1e4, -1e4, 0.0]]), np.array([[-1e4, 1e4]]), np.array([0.0]), 0.0, 1.0)[0]
    # gate exactly 1/2 at novelty == beta; the winners get log(1/2), the losers their exact gaps
    assert lp[0] == pytest.approx(math.log(0.5)) and lp[4] == pytest.approx(math.log(0.5))
    assert lp[1] == pytest.approx(math.log(0.5) - 2e4) and lp[3] == pytest.approx(math.log(0.5) - 2e4)


def test_evidence_over_225_extreme_presses_does_not_underflow():
    """All 225 presses accumulated (a decision returned early is ignored and the presses keep
    coming): logits of +-1e4, novelty swinging +-1e3 around beta, the item's class (TOUCHED[1])
    winning 60 % of presses and a random other class the rest by gaps of ~1e4. After every press
    the posterior is finite and normalised; at the end it equals a float64 reference summed with
    math.fsum, and TOUCHED[1] leads."""
    rng = np.random.default_rng(0)
    true = CLASSES.index(TOUCHED[1])
    ev = Evidence(CLASSES, confidence=0.95, max_presses=225)
    per_press = []
    for k in range(225):
        lt, lu = rng.uniform(-1e4, 1e4, (1, 3)), rng.uniform(-1e4, 1e4, (1, 2))
        winner = true if rng.random() < 0.6 else int(rng.choice([c for c in range(len(CLASSES)) if c != true]))
        if winner < 3:
            lt[0, winner] = lt.max() + 1e4
            nov = rng.uniform(-1e3, -1.0)  # routed touched
        else:
            lu[0, winner - 3] = lu.max() + 1e4
            nov = rng.uniform(1.0, 1e3)
        lp = gzsl_log_posterior(lt, lu, np.array([nov]), 0.0, 1.0)[0]
        per_press.append(lp)
        ev.add(_score(lp))
        post = np.array(list(ev.decide().log_posterior.values()))
        assert np.all(np.isfinite(post)) and abs(sum(math.exp(v) for v in post) - 1) < 1e-9, f"press {k + 1}"
    d = ev.decide()
    assert ev.presses == d.presses == 225
    # reference: per press renormalised over the scene, summed exactly, renormalised
    ref = []
    for c in range(len(CLASSES)):
        ref.append(math.fsum(float(lp[c] - np.logaddexp.reduce(lp)) for lp in per_press))
    ref = np.array(ref) - np.logaddexp.reduce(np.array(ref))
    got = np.array([d.log_posterior[c] for c in CLASSES])
    assert np.all(np.isfinite(got)) and np.max(np.abs(got - ref)) <= 1e-6 * max(1.0, np.max(np.abs(ref)))
    assert min(ref) < -1e5  # the losers really are ~1e5+ nats behind: exp() of them underflows
    assert d.label == TOUCHED[1] and d.confidence == pytest.approx(1.0)


def test_evidence_over_225_mild_presses_accumulates_exactly():
    # 225 presses each favouring t0 by a factor 1.01: the float64 sum of logs stays exact where a
    # product of probabilities would underflow (0.2 ** 225 ~ 1e-157 is fine; 1e-4 ** 225 is not)
    p = np.array([1e-4 * 1.01, 1e-4, 1e-4, 1e-4, 1 - 4.01e-4])
    ev = Evidence(["t0", "t1"], confidence=1.0, max_presses=225)
    for _ in range(225):
        d = ev.add(PressScore(dict(zip(CLASSES, np.log(p))), 0.0, False, 0.0))
    assert d.presses == 225 and d.label in ("t0", UNKNOWN)
    assert d.log_posterior["t0"] - d.log_posterior["t1"] == pytest.approx(225 * math.log(1.01), rel=1e-9)


@pytest.mark.parametrize("beta", [math.inf, -math.inf])
def test_beta_at_infinity_all_or_none_touched(beta):
    _, raws, ref = world_frames()
    m = TactileModel.load(shared_bundle("fp32"), threads=1, beta_override=beta)
    m.set_reference(ref)
    scene_t, scene_u = Evidence(TOUCHED, 0.9, 9), Evidence(UNTOUCHED, 0.9, 9)
    for frame in raws[:9]:
        s = m.score_press(frame)
        assert s.untouched is (beta == -math.inf)
        dt, du = scene_t.add(s), scene_u.add(s)
        for d in (dt, du):
            if d is not None:
                assert all(math.isfinite(v) for v in d.log_posterior.values())
    dt, du = scene_t.decide(), scene_u.decide()
    # beta=+inf: every press is touched, so an untouched-only scene learns nothing (uniform) and
    # ends unknown; beta=-inf symmetrically for a touched-only scene
    empty = du if beta == math.inf else dt
    assert empty.label == UNKNOWN
    assert max(empty.log_posterior.values()) - min(empty.log_posterior.values()) < 1e-9


def test_scene_of_one_class_is_always_confident():
    ev = Evidence(["t1"], 0.99, 9)
    d = ev.add(_score(np.array([LOG_ZERO, LOG_ZERO, LOG_ZERO, 0.0, LOG_ZERO])))
    assert d is not None and d.label == "t1" and d.confidence == 1.0 and d.presses == 1


def _bad_frames(good: np.ndarray):
    h, w = good.shape[:2]
    nan = good.astype(np.float32)
    nan[0, 0, 0] = np.nan
    inf = good.astype(np.float32)
    inf[1, 1, 1] = np.inf
    sat = good.copy()
    sat[: int(0.8 * h)] = 255
    return {"nonfinite": nan, "nonfinite_inf": inf, "black": np.zeros_like(good), "white": np.full_like(good, 255),
            "saturated": sat, "size": good[: h // 2], "dtype": good.astype(np.uint16), "shape": good[..., 0]}


# what the operator reads for each bad frame (runtime/preprocess.py): the problem, named. (A press
# frame of the wrong size is compared with the item's reference frame, both sizes given.)
_BAD_FRAME_WORDS = {"nonfinite": "contains NaN or Inf", "nonfinite_inf": "contains NaN or Inf",
                    "black": "all black", "white": "all white", "saturated": "saturated; lower the exposure",
                    "size": "frame: size 160x60 does not match the no-contact reference frame's 160x120", "dtype": "dtype uint16, expected uint8",
                    "shape": "expected HxWx3"}


def _counting_forward(m: TactileModel) -> list:
    """Make ``m.forward`` (trunk -> heads -> router) record every batch that reaches it."""
    calls, forward = [], m.forward
    m.forward = lambda x: calls.append(x) or forward(x)
    return calls


def test_bad_frames_are_refused_by_name_before_the_model_runs():
    _, raws, ref = world_frames()
    m = TactileModel.load(shared_bundle("fp32"), threads=1)
    m.set_reference(ref)
    ran = _counting_forward(m)
    timing = dict(m.last_timing)
    ev = Evidence(CLASSES, 0.5, 3)
    bad = _bad_frames(raws[0])
    assert set(bad) == set(_BAD_FRAME_WORDS)
    for kind, frame in bad.items():
        # as the cell loop does: a scored press goes to the evidence, a FrameError skips it
        with pytest.raises(FrameError) as e:
            ev.add(m.score_press(frame))
        assert e.value.reason == kind.split("_")[0], kind
        assert _BAD_FRAME_WORDS[kind] in str(e.value), (kind, str(e.value))
    assert ran == []  # no bad frame reached the trunk, the heads or the router
    assert ev.presses == 0 and m.last_timing == timing  # nor the evidence; no timing was taken
    for kind in ("black", "white", "saturated", "dtype"):
        with pytest.raises(FrameError, match=_BAD_FRAME_WORDS[kind]) as e:
            m.set_reference(bad[kind])
        assert "reference frame" in str(e.value)
    m.set_reference(ref)
    s = m.score_press(raws[0])  # the good frame still scores afterwards, and can be routed
    assert len(ran) == 1 and np.isfinite(s.novelty)
    ev.add(s)
    assert ev.presses == 1  # the same path does feed the evidence once a frame is good


class _BadFrameCamera:
    """The gel up: the good no-contact reference. Pressed: the next frame of ``pressed`` as is."""

    def __init__(self, arm, reference: np.ndarray, pressed: list[np.ndarray]):
        self.arm, self.reference, self.pressed, self.grabs = arm, reference, list(pressed), 0

    def connect(self):
        pass

    def disconnect(self):
        pass

    def grab(self):
        from vs2t_edge.runtime.devices import Frame

        self.grabs += 1
        is_pressed = bool(self.arm.calls) and self.arm.calls[-1] == "press"
        image = self.pressed.pop(0) if is_pressed else self.reference
        return Frame(image, float(self.grabs), self.grabs)


def _cell_with(tmp_path, reference, pressed, max_presses):
    from vs2t_edge.sim.fake_devices import FakeArm
    from vs2t_edge.runtime.cell import Cell, SceneSpec
    from vs2t_edge.runtime.items import ContinuousFeed
    from vs2t_edge.sim.fake_devices import FakeGate
    from vs2t_edge.runtime.journal import Journal
    from vs2t_edge.runtime.notify import Notifier

    arm, gate = FakeArm(), FakeGate()
    arm.connect()
    gate.connect()
    model = TactileModel.load(shared_bundle("fp32"), threads=1)
    ran = _counting_forward(model)
    evidences: list[Evidence] = []

    def evidence():
        evidences.append(Evidence(CLASSES, 0.9, max_presses))
        return evidences[-1]

    scene = SceneSpec(bins={c: i + 1 for i, c in enumerate(CLASSES)}, reject_bin=0,
                      points_mm=arm.config.grid_points_mm()[: len(pressed)], max_presses=max_presses,
                      confidence=0.9, fault_file=tmp_path / "FAULT", wait_item_timeout_s=0.01)
    cell = Cell(camera=_BadFrameCamera(arm, reference, pressed), arm=arm, gate=gate, model=model,
                journal=Journal.open(tmp_path / "journal.jsonl"), notifier=Notifier(address=""), scene=scene,
                evidence_factory=evidence, items=ContinuousFeed(), sleep=lambda s: None)
    return cell, gate, ran, evidences


def test_bad_frames_in_the_cell_loop_are_journalled_and_never_routed(tmp_path):
    """Every kind of bad press frame through the daemon's own loop (real bundle, real evidence):
    each is skipped with its reason and message in the journal, none reaches the model or the
    evidence, and the item - all its frames bad - goes to the reject bin as 'unknown'."""
    from vs2t_edge.runtime.journal import read_records

    _, raws, ref = world_frames()
    bad = _bad_frames(raws[0])
    cell, gate, ran, evidences = _cell_with(tmp_path, ref, list(bad.values()), max_presses=len(bad))
    (result,) = cell.run(max_items=1)
    recs = read_records(tmp_path / "journal.jsonl")
    skipped = [r for r in recs if r["type"] == "frame_skipped"]
    assert [r["reason"] for r in skipped] == [k.split("_")[0] for k in bad]
    for r, kind in zip(skipped, bad):
        assert _BAD_FRAME_WORDS[kind] in r["message"], (kind, r["message"])
    assert ran == []  # no bad frame was scored
    assert len(evidences) == 1 and evidences[0].presses == 0  # nor added to the item's evidence
    (pre,) = [r for r in recs if r["type"] == "pre_sort"]
    assert pre["presses"] == 0 and pre["scores"] == [] and pre["log_posterior"] is None
    assert (pre["label"], pre["bin"], pre["stopped_by"]) == ("unknown", 0, "no_usable_frames")
    assert (result.label, result.bin, result.skipped_frames) == ("unknown", 0, len(bad))
    assert gate.sorted == [0]  # the gate was told the reject bin, never a fabric's bin
    assert cell.fault is None  # bad frames are skipped, not a fault


def test_good_frames_after_bad_ones_decide_on_the_good_ones_only(tmp_path):
    _, raws, ref = world_frames()
    bad = _bad_frames(raws[0])
    frames = [bad["black"], raws[0], bad["nonfinite"], raws[1], raws[2]]
    cell, gate, ran, evidences = _cell_with(tmp_path, ref, frames, max_presses=3)
    (result,) = cell.run(max_items=1)
    from vs2t_edge.runtime.journal import read_records

    (pre,) = [r for r in read_records(tmp_path / "journal.jsonl") if r["type"] == "pre_sort"]
    # a confident decision may stop early: the evidence saw exactly the good presses the loop
    # scored (grid points 1, 3, 4), the bad ones at points 0 and 2 only as skipped
    good_points = [1, 3, 4][: result.presses]
    assert result.presses >= 1 and [sc["point"] for sc in pre["scores"]] == good_points
    assert evidences[0].presses == result.presses == len(ran)
    assert result.skipped_frames == (2 if result.presses >= 2 else 1)
    assert gate.sorted == [result.bin]


def test_a_bad_reference_frame_latches_a_fault_and_routes_nothing(tmp_path):
    _, raws, ref = world_frames()
    cell, gate, ran, evidences = _cell_with(tmp_path, np.zeros_like(ref), [raws[0]] * 3, max_presses=3)
    (result,) = cell.run(max_items=1)
    assert result.outcome == "rejected_fault" and "reference frame unusable" in cell.fault
    assert "all black" in cell.fault
    assert ran == [] and evidences[0].presses == 0
    assert gate.sorted == [] and gate.to_reject_calls >= 1  # no sort at all; the gate sits at reject


def test_int8_on_saturated_inputs_stays_finite_and_ordered():
    m8 = TactileModel.load(shared_bundle("int8"), threads=1)
    m32 = TactileModel.load(shared_bundle("fp32"), threads=1)
    s = m8.preprocess_spec
    # the extremes preprocessing can produce: a difference of +-255 everywhere, and a half split
    hi = np.full((1, 3, SIZE, SIZE), (255 / 255 - s.mean[0]) / s.std[0], np.float32)
    half = hi.copy()
    half[..., : SIZE // 2] *= -1
    for x in (hi, -hi, half):
        o8, o32 = m8.forward(x), m32.forward(x)
        assert np.all(np.isfinite(o8.feature)) and np.all(np.isfinite(o8.logits_t)) and np.isfinite(o8.novelty).all()
        lp = m8.log_posterior(o8)
        assert np.all(np.isfinite(lp))
        # far outside the calibration range int8 clips, but must not wrap around: the
        # out-of-range press must still look more novel than a typical press does
        x0, _, _ = world_frames()
        typical = float(np.median(m8.forward(x0[:20]).novelty))
        assert o8.novelty[0] > typical and o32.novelty[0] > typical


def test_fp32_and_int8_agree_on_world_frames():
    x, _, _ = world_frames()
    m8 = TactileModel.load(shared_bundle("int8"), threads=1)
    m32 = TactileModel.load(shared_bundle("fp32"), threads=1)
    o8, o32 = m8.forward(x), m32.forward(x)
    cos = np.sum(o8.feature * o32.feature, 1) / (np.linalg.norm(o8.feature, axis=1) * np.linalg.norm(o32.feature, axis=1))
    assert np.median(cos) > 0.99 and cos.min() > 0.9
    agree = np.mean(np.argmax(o8.logits_t, 1) == np.argmax(o32.logits_t, 1))
    assert agree >= 0.9
    route_agree = np.mean((o8.novelty > m8.beta) == (o32.novelty > m32.beta))
    assert route_agree >= 0.85

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
    rng = np.random.default_rng(0)
    ev = Evidence(CLASSES, confidence=1.0, max_presses=225)  # confidence 1: never stops early... unless exact
    d = None
    for k in range(225):
        lt, lu = rng.uniform(-1e4, 1e4, (1, 3)), rng.uniform(-1e4, 1e4, (1, 2))
        lp = gzsl_log_posterior(lt, lu, np.array([rng.uniform(-10, 10)]), 0.0, 1.0)[0]
        d = ev.add(_score(lp))
        if d is not None:
            break
    d = d or ev.decide()
    assert all(math.isfinite(v) for v in d.log_posterior.values())
    assert 0.0 <= d.confidence <= 1.0 and abs(sum(math.exp(v) for v in d.log_posterior.values()) - 1) < 1e-9


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


def test_bad_frames_are_refused_and_never_routed():
    _, raws, ref = world_frames()
    m = TactileModel.load(shared_bundle("fp32"), threads=1)
    m.set_reference(ref)
    ev = Evidence(CLASSES, 0.5, 3)
    for kind, frame in _bad_frames(raws[0]).items():
        with pytest.raises(FrameError) as e:
            m.score_press(frame)
        assert e.value.reason == kind.split("_")[0], kind
        assert str(e.value)  # an operator-readable message
    assert ev.presses == 0  # nothing reached the evidence: no bin was chosen from a bad frame
    for kind in ("black", "white", "saturated", "dtype"):
        with pytest.raises(FrameError):
            m.set_reference(_bad_frames(raws[0])[kind])
    m.set_reference(ref)
    assert np.isfinite(m.score_press(raws[0]).novelty)  # the good frame still scores afterwards


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

"""The per-press core: frames -> PressScore with a normalised GZSL log posterior over the bundle's
classes, the paper's hard route as its limit, and frames the cell must not classify refused."""
from __future__ import annotations

import math

import numpy as np
import pytest

from test_bundle_fixtures import TOUCHED, UNTOUCHED, shared_bundle, world_frames
from vs2t_edge.runtime.inference import LOG_ZERO, PressScore, TactileModel, gzsl_log_posterior
from vs2t_edge.runtime.preprocess import FrameError


@pytest.fixture(scope="module")
def model():
    return TactileModel.load(shared_bundle("fp32"), threads=1)


def _lse(v):
    v = np.asarray(list(v), float)
    return float(v.max() + np.log(np.exp(v - v.max()).sum()))


def test_score_press_on_world_frames(model):
    _, raws, ref = world_frames()
    model.set_reference(ref)
    s = model.score_press(raws[3])
    assert isinstance(s, PressScore)
    assert list(s.log_posterior) == list(TOUCHED + UNTOUCHED)
    assert abs(_lse(s.log_posterior.values())) < 1e-9
    assert s.untouched == (s.novelty > model.beta)
    assert s.latency_ms > 0 and set(model.last_timing) >= {"preprocess_ms", "trunk_ms", "heads_ms", "router_ms",
                                                          "decision_ms"}
    # the same press scored twice gives the same answer (no state leaks between presses)
    assert model.score_press(raws[3]).log_posterior == s.log_posterior


def test_posterior_mass_follows_the_route(model):
    _, raws, ref = world_frames()
    model.set_reference(ref)
    for frame in raws[:12]:
        s = model.score_press(frame)
        p_u = sum(math.exp(s.log_posterior[c]) for c in UNTOUCHED)
        assert (p_u > 0.5) == s.untouched or abs(p_u - 0.5) < 1e-9


def test_beta_override_and_infinite_beta():
    _, raws, ref = world_frames()
    for beta, untouched in ((math.inf, False), (-math.inf, True)):
        m = TactileModel.load(shared_bundle("fp32"), threads=1, beta_override=beta)
        m.set_reference(ref)
        for frame in raws[:5]:
            s = m.score_press(frame)
            assert s.untouched is untouched
            zero = UNTOUCHED if not untouched else TOUCHED
            assert all(s.log_posterior[c] == LOG_ZERO for c in zero)
            assert all(math.isfinite(v) for v in s.log_posterior.values())
            assert abs(_lse(v for c, v in s.log_posterior.items() if c not in zero)) < 1e-9


def test_missing_reference_is_a_frame_error():
    m = TactileModel.load(shared_bundle("fp32"), threads=1)
    _, raws, _ = world_frames()
    with pytest.raises(FrameError) as e:
        m.score_press(raws[0])
    assert e.value.reason == "reference"


def test_soft_gating_limits():
    lt, lu = np.array([[2.0, 0.0, -1.0]]), np.array([[0.5, 0.1]])
    # far below beta: all mass on the touched head, equal to its softmax
    lp = gzsl_log_posterior(lt, lu, np.array([0.0]), beta=1e6, temperature=1.0)
    ls = lt - np.log(np.exp(lt).sum())
    assert np.allclose(lp[0, :3], ls) and np.all(lp[0, 3:] < -1e5)
    # at beta: half the mass on each head
    lp = gzsl_log_posterior(lt, lu, np.array([5.0]), beta=5.0, temperature=2.0)
    assert np.isclose(np.exp(lp[0, 3:]).sum(), 0.5)
    with pytest.raises(ValueError):
        gzsl_log_posterior(lt, lu, np.array([np.nan]), beta=0.0, temperature=1.0)
    with pytest.raises(ValueError):
        gzsl_log_posterior(lt, lu, np.array([0.0]), beta=0.0, temperature=0.0)


def test_a_bundle_on_the_reduced_path_scores_full_and_camera_reduced_frames_alike(tmp_path):
    """Train and serve are one function: the model's preprocessing of a full frame is training's
    (preprocess_batch on the dataset frame), and a frame the camera reduced by the same box
    average (Frame.reduced_by) scores exactly as the full frame does."""
    from test_bundle_fixtures import SIZE, make_bundle
    from vs2t_edge.runtime.preprocess import TactilePreprocess, preprocess_batch, reduce_frame

    spec = TactilePreprocess(size=SIZE, reduce=2)
    make_bundle(tmp_path / "b", "fp32", preprocess=spec)
    model = TactileModel.load(tmp_path / "b", threads=1)
    assert model.preprocess_spec == spec and model.bundle.manifest["preprocess"]["reduce"] == 2
    _, raws, ref = world_frames()
    model.set_reference(ref)
    np.testing.assert_array_equal(model.preprocess(raws[5])[0], preprocess_batch([raws[5]], ref, spec)[0])
    full = model.score_press(raws[5])
    model.set_reference(reduce_frame(ref, 2), reduced_by=2)
    reduced = model.score_press(reduce_frame(raws[5], 2), reduced_by=2)
    assert reduced.log_posterior == full.log_posterior and reduced.novelty == full.novelty
    with pytest.raises(FrameError) as exc:
        model.score_press(reduce_frame(raws[5], 4), reduced_by=4)
    assert exc.value.reason == "scale"


def test_a_float_path_bundle_keeps_its_manifest_and_scores_frames_decoded_reduced(model):
    """A float-path bundle takes the frames a camera decoded at 1/2 (``devices.camera.decode_scale``
    auto) against a reference decoded the same way, and runs its float path on them unchanged; a
    reduced frame against a full-size reference is refused by size."""
    from vs2t_edge.runtime.preprocess import preprocess_tactile, reduce_frame

    assert "reduce" not in model.bundle.manifest["preprocess"] and model.preprocess_spec.reduce == 0
    _, raws, ref = world_frames()
    model.set_reference(ref)
    with pytest.raises(FrameError) as exc:
        model.score_press(reduce_frame(raws[1], 2), reduced_by=2)
    assert exc.value.reason == "size"
    model.set_reference(reduce_frame(ref, 2), reduced_by=2)
    x = model.preprocess(reduce_frame(raws[1], 2), reduced_by=2)
    assert x.shape == (1, 3, model.preprocess_spec.size, model.preprocess_spec.size)
    np.testing.assert_array_equal(x[0], preprocess_tactile(reduce_frame(raws[1], 2), reduce_frame(ref, 2),
                                                           model.preprocess_spec))
    s = model.score_press(reduce_frame(raws[1], 2), reduced_by=2)
    assert all(np.isfinite(v) for v in s.log_posterior.values())

"""Numerical stability of the novelty models at the extremes (issue 5): dead and collinear
channels, fewer samples than dimensions, feature norms 1e-6..1e6 in float32 against a float64
reference, logits of +-1e4.

Stated tolerance: the float32 scoring path agrees with float64 scoring of the same float32
features within rtol 1e-4 on the squared Mahalanobis distance (measured ~3e-7 at d=256).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vs2t_edge.runtime import novelty as nv

F32_RTOL = 1e-4


def _relu_features(n, d, seed, dead=20, collinear=10):
    """Trunk-like features: non-negative, low-rank structure, dead and collinear channels."""
    rng = np.random.default_rng(seed)
    x = np.maximum(rng.normal(size=(n, 8)) @ rng.normal(size=(8, d)) + rng.normal(size=(n, d)) * 0.3, 0)
    x[:, :dead] = 0.0
    x[:, dead:dead + collinear] = 3.0 * x[:, dead + collinear:dead + 2 * collinear]
    return x


@pytest.mark.parametrize("name", nv.GAUSSIAN_ROUTERS)
def test_dead_collinear_and_n_below_d_give_finite_scores(name):
    x = _relu_features(n=30, d=300, seed=0)  # n < d, 20 dead, 10 collinear channels
    r = nv.fit_router(name, x)
    assert np.all(np.isfinite(r.whitening)) and np.isfinite(r.log_det)
    q = _relu_features(n=50, d=300, seed=1)
    q[:5, :20] = 20.0  # dead channels firing hard at test time: large but finite novelty
    for dtype in (np.float64, np.float32):
        s = r.novelty(q, dtype=dtype)
        assert s.dtype == np.float64 and np.all(np.isfinite(s))
    # a press that wakes dead channels is more novel than a typical one
    s = r.novelty(q)
    assert s[:5].min() > np.median(s[5:])


@pytest.mark.parametrize("name", nv.GAUSSIAN_ROUTERS)
def test_constant_and_all_zero_features_do_not_break_the_fit(name):
    for x in (np.zeros((10, 16)), np.ones((10, 16)) * 3.0):
        r = nv.fit_router(name, x)
        s = r.novelty(np.vstack([x[:2], np.full((1, 16), 1e6)]), dtype=np.float32)
        assert np.all(np.isfinite(s))
        assert s[2] > s[0]


def test_float64_fit_at_2048_dimensions_with_few_samples():
    x = _relu_features(n=40, d=2048, seed=2, dead=300, collinear=100)
    for name in ("gaussian",):  # the paper's router, floored; shrinkage routers are checked at d=300
        r = nv.fit_router(name, x, keep_covariance=False)
        q = _relu_features(n=8, d=2048, seed=3, dead=300, collinear=100)
        a = r.novelty(q.astype(np.float32).astype(np.float64))
        b = r.novelty(q.astype(np.float32), dtype=np.float32)
        assert np.all(np.isfinite(b))
        np.testing.assert_allclose(r.squared_mahalanobis(q.astype(np.float32), dtype=np.float32),
                                   r.squared_mahalanobis(q.astype(np.float32)), rtol=F32_RTOL)
        assert np.all(np.isfinite(a))


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1.0, 1e3, 1e6])
@pytest.mark.parametrize("name", nv.GAUSSIAN_ROUTERS)
def test_float32_scores_agree_with_float64_across_feature_norms(name, scale):
    x = _relu_features(n=120, d=256, seed=4) * scale
    r = nv.fit_router(name, x)
    q = (_relu_features(n=60, d=256, seed=5) * scale).astype(np.float32)
    ref = r.squared_mahalanobis(q.astype(np.float64))
    fast = r.squared_mahalanobis(q, dtype=np.float32)
    np.testing.assert_allclose(fast, ref, rtol=F32_RTOL)


class _Session:
    """Stands in for an onnxruntime session: returns the given outputs, so TactileModel.forward
    runs the cell's own router path (float32 parameters, float32 scoring) on chosen features."""

    def __init__(self, name, outputs):
        self._name, self.outputs = name, outputs

    def get_inputs(self):
        return [type("I", (), {"name": self._name})()]

    def run(self, names, feeds):
        return self.outputs(feeds[self._name])


def _cell_model(router, beta):
    """A TactileModel whose router is ``router`` as the cell gets it from a bundle (saved with
    to_params, read back with from_params, then inference._float32_router), and whose trunk
    'outputs' are whatever features forward is given."""
    from types import SimpleNamespace

    from vs2t_edge.runtime.inference import TactileModel

    loaded = nv.Router.from_params({k: np.asarray(v) for k, v in router.to_params().items()})
    bundle = SimpleNamespace(manifest={}, touched=("t0", "t1"), untouched=("u0",), classes=("t0", "t1", "u0"),
                             beta=beta, gating_temperature=1.0, gating_scale=None, router=loaded, preprocess=None,
                             scene_model=None, descriptor=None, camera_jpeg=0)
    trunk = _Session("image", lambda x: [np.asarray(x, np.float32)])
    heads = _Session("feature", lambda f: [np.zeros((len(f), 2), np.float32), np.zeros((len(f), 1), np.float32)])
    model = TactileModel(bundle, trunk, heads, threads=1)
    assert model.router.mean.dtype == np.float32 and model.router.whitening.dtype == np.float32
    return model


def _check_cell_against_float64(router, q32):
    """The cell's novelty (TactileModel.forward, float32) against float64 scoring with the
    float64 parameters of the same float32 features: the squared distance part within F32_RTOL,
    the log-density constant exact, the ranking and the route at a mid beta the same."""
    ref = router.novelty(q32.astype(np.float64))  # float64 throughout
    m2_ref = router.squared_mahalanobis(q32.astype(np.float64))
    beta = float(np.median(ref))
    model = _cell_model(router, beta)
    got = model.forward(q32).novelty
    assert got.dtype == np.float64 and np.all(np.isfinite(got))
    np.testing.assert_array_less(np.abs(got - ref), F32_RTOL * np.maximum(np.abs(m2_ref), 1e-30) + 1e-9 * np.abs(ref))
    far = np.abs(ref - beta) > 2 * F32_RTOL * np.abs(m2_ref) + 1e-9 * np.abs(ref)  # not within rounding of beta
    assert np.array_equal((got > beta)[far], (ref > beta)[far])
    order = np.argsort(ref)
    gaps = np.diff(ref[order]) > 2 * F32_RTOL * np.abs(m2_ref[order][1:])
    assert np.all(np.diff(got[order])[gaps] > 0)


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1.0, 1e3, 1e6])
@pytest.mark.parametrize("name", nv.GAUSSIAN_ROUTERS)
def test_cell_float32_novelty_agrees_with_float64_across_feature_norms(name, scale):
    """Trunk features at norms 1e-6..1e6 (fit and presses at the same scale): the novelty the cell
    computes in TactileModel.forward, not only squared_mahalanobis."""
    x = _relu_features(n=120, d=256, seed=4) * scale
    r = nv.fit_router(name, x)
    q = (_relu_features(n=60, d=256, seed=5) * scale).astype(np.float32)
    _check_cell_against_float64(r, q)


@pytest.mark.parametrize("name", nv.GAUSSIAN_ROUTERS)
def test_cell_float32_novelty_of_presses_from_1e_minus6_to_1e6(name):
    """Fitted at norm ~1, presses whose features have norms 1e-6..1e6 (dead channels at 1e6):
    finite, and within F32_RTOL of float64, through the cell's forward."""
    r = nv.fit_router(name, _relu_features(n=80, d=128, seed=6))
    direction = np.abs(np.random.default_rng(7).normal(size=128))
    q = np.stack([direction * s for s in np.logspace(-6, 6, 13)]).astype(np.float32)
    q[-3:, :20] = np.float32(1e6)
    _check_cell_against_float64(r, q)


@pytest.mark.parametrize("name", nv.GAUSSIAN_ROUTERS)
def test_float32_far_outliers_do_not_overflow(name):
    """Fit at norm ~1, score presses with norms up to 1e6 in float32: no inf, same ranking."""
    x = _relu_features(n=80, d=128, seed=6)
    r = nv.fit_router(name, x)
    rng = np.random.default_rng(7)
    direction = np.abs(rng.normal(size=128))
    q = np.stack([direction * s for s in (1e-6, 1e-2, 1.0, 1e2, 1e4, 1e6)]).astype(np.float32)
    q[:, :20] = np.float32(1e6)  # dead channels at extreme values
    ref = r.squared_mahalanobis(q.astype(np.float64))
    fast = r.squared_mahalanobis(q, dtype=np.float32)
    assert np.all(np.isfinite(fast))
    np.testing.assert_allclose(fast, ref, rtol=F32_RTOL)


@settings(max_examples=25, deadline=None)
@given(log_scale=st.floats(-6, 6), seed=st.integers(0, 2**16))
def test_property_float32_agrees_and_is_scale_covariant(log_scale, seed):
    """Mahalanobis distance is scale invariant: fitting and scoring at s*x gives the same value."""
    scale = 10.0**log_scale
    x = _relu_features(n=40, d=32, seed=seed, dead=4, collinear=3)
    q = _relu_features(n=10, d=32, seed=seed + 1, dead=4, collinear=3)
    r1 = nv.fit_router("mahalanobis_lw", x)
    rs = nv.fit_router("mahalanobis_lw", x * scale)
    np.testing.assert_allclose(rs.squared_mahalanobis(q * scale), r1.squared_mahalanobis(q), rtol=1e-6)
    qs = (q * scale).astype(np.float32)
    np.testing.assert_allclose(rs.squared_mahalanobis(qs, dtype=np.float32),
                               rs.squared_mahalanobis(qs.astype(np.float64)), rtol=F32_RTOL)


def test_nan_or_inf_features_are_refused_not_scored():
    r = nv.fit_router("gaussian", _relu_features(20, 30, 8, dead=2, collinear=2))
    for bad in (np.nan, np.inf, -np.inf):
        q = np.zeros((1, 30))
        q[0, 3] = bad
        with pytest.raises(nv.RouterError, match="NaN or Inf"):
            r.novelty(q)
    with pytest.raises(nv.RouterError, match="NaN or Inf"):
        nv.fit_router("gaussian", np.full((5, 3), np.nan))


def test_log_softmax_and_logit_routers_at_plus_minus_1e4():
    z = np.array([[1e4, -1e4, 0.0], [-1e4, -1e4, -1e4], [1e4, 1e4 - 1.0, -1e4]])
    ls = nv.log_softmax(z)
    assert np.all(np.isfinite(ls) | (ls == -np.inf)) and not np.any(np.isnan(ls))
    assert ls[0, 0] == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(ls[1], np.log(1 / 3) * np.ones(3))
    assert ls[2, 0] == pytest.approx(-np.log1p(np.exp(-1.0)), rel=1e-12)
    energy = nv.fit_router("energy", None).novelty(None, z)
    np.testing.assert_allclose(energy, [-1e4, 1e4 - np.log(3), -(1e4 + np.log1p(np.exp(-1.0)))], rtol=1e-12)
    msp = nv.fit_router("max_softmax", None).novelty(None, z)
    np.testing.assert_allclose(msp, [-1.0, -1 / 3, -1 / (1 + np.exp(-1.0))], rtol=1e-12)
    cs = nv.fit_router("calibrated_stacking", None).novelty(None, z, logits_u=z[::-1])
    assert np.all(np.isfinite(cs))
    for router in ("energy", "max_softmax"):
        s = nv.fit_router(router, None).novelty(None, z.astype(np.float32))
        assert np.all(np.isfinite(s))

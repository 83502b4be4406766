"""The ``discriminant`` router (runtime/novelty.py, fitted by runtime/covariance.py): class
Gaussians in Fisher's discriminant subspace of the touched classes - what wins the novelty AUROC
on real GelSight frames (docs/realism.md) - against its formula, on a constructed few-presses case,
through its parameters, in float32 as the cell scores it, and with clear errors."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from vs2t_edge.runtime import covariance as cv
from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime import router_eval as reval


def _world(seed=0, d=80, n=6, n_t=5):
    """Few presses per class in a wide feature, as on the real sensor: touched class centres, an
    unseen class amid them (at their centroid, where a single Gaussian of all touched presses is
    densest), and one away from all; the within-class noise is anisotropic (a few loud
    directions shared by every class)."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(n_t, d)) * 1.5
    loud = rng.normal(size=(4, d)) * 3.0  # nuisance directions: big spread, same for every class

    def presses(c, k):
        return c + rng.normal(size=(k, d)) + rng.normal(size=(k, 4)) @ loud

    x = np.concatenate([presses(c, n) for c in centres])
    y = np.repeat(np.arange(n_t), n)
    held = np.concatenate([presses(c, n) for c in centres])
    between = presses(centres.mean(0), 3 * n)
    away = presses(rng.normal(size=d) * 1.5, 3 * n)
    return x, y, held, between, away


def test_fit_needs_labels_and_two_classes():
    x, y, *_ = _world()
    with pytest.raises(nv.RouterError, match="needs touched_labels"):
        nv.fit_router("discriminant", x)
    with pytest.raises(nv.RouterError, match="at least 2 touched classes"):
        nv.fit_router("discriminant", x, touched_labels=np.zeros(len(x)))
    with pytest.raises(nv.RouterError, match="touched_labels has 3 entries"):
        nv.fit_router("discriminant", x, touched_labels=y[:3])
    with pytest.raises(nv.RouterError, match="no option"):
        nv.fit_router("discriminant", x, touched_labels=y, keep_covariance=False)
    # the other routers ignore labels, so a trainer passes them to every router alike
    g = nv.fit_router("mahalanobis_lw", x, touched_labels=y)
    np.testing.assert_array_equal(g.novelty(x), nv.fit_router("mahalanobis_lw", x).novelty(x))


def test_novelty_is_the_smallest_distance_in_the_discriminant_subspace():
    """Against the formula written another way: the subspace is the span of the whitened, centred
    class means (a QR basis instead of the SVD's), the distance the whitened one projected on it."""
    x, y, held, between, away = _world(seed=1)
    r = nv.fit_router("discriminant", x, touched_labels=y * 10 + 3)  # any label values
    means, w, shrink, _ = cv.within_class_whitening(x, y, 5)
    assert 0.0 < shrink < 1.0 and r.shrinkage == pytest.approx(shrink)
    q_basis, _ = np.linalg.qr(((means - means.mean(0)) @ w).T)
    q_basis = q_basis[:, :4]  # C - 1 = 4 directions
    q = np.concatenate([held, between, away])
    d2 = np.stack([(((q - m) @ w @ q_basis) ** 2).sum(1) for m in means], axis=1)
    np.testing.assert_allclose(r.sq_distances(q), d2, rtol=1e-8)
    np.testing.assert_allclose(r.novelty(q), d2.min(1), rtol=1e-8)
    assert r.projection.shape == (80, 4) and r.class_means.shape == (5, 4) and r.dim == 80


def test_an_unseen_class_between_or_away_from_the_touched_ones_is_flagged():
    """Held-out presses of the touched classes score low; an unseen class amid the touched ones and
    one away from all score high. A Gaussian of all touched presses misses the one amid them: it
    sits where that density is highest."""
    x, y, held, between, away = _world(seed=2)
    r = nv.fit_router("discriminant", x, touched_labels=y)
    lw = nv.fit_router("mahalanobis_lw", x)
    for unseen in (between, away):
        a = reval.auroc(r.novelty(held), r.novelty(unseen))
        assert a >= 0.95, a
    assert reval.auroc(lw.novelty(held), lw.novelty(between)) < 0.8
    assert np.median(r.novelty(away)) > np.max(r.novelty(held))


def test_params_round_trip_through_an_npz_file(tmp_path):
    x, y, held, *_ = _world(seed=3)
    r = nv.fit_router("discriminant", x, touched_labels=y)
    np.savez(tmp_path / "router.npz", **{k: np.asarray(v) for k, v in r.to_params().items()})
    with np.load(tmp_path / "router.npz") as z:
        r2 = nv.Router.from_params(dict(z))
    assert type(r2) is nv.DiscriminantRouter and r2.name == "discriminant"
    np.testing.assert_array_equal(r2.novelty(held), r.novelty(held))
    assert r2.variance_floor == r.variance_floor and r2.shrinkage == r.shrinkage
    with pytest.raises(ValueError):
        r2.projection[0, 0] = 1.0  # immutable, as every router


@pytest.mark.parametrize("edit, says", [
    (lambda p: p.pop("class_means"), "lack 'class_means'"),
    (lambda p: p.update(projection=p["projection"][:-1]), "must be"),
    (lambda p: p.update(class_means=p["class_means"][:, :-1]), "must be"),
    (lambda p: p.update(centre=np.full_like(p["centre"], np.nan)), "NaN"),
])
def test_bad_params_are_named(edit, says):
    x, y, *_ = _world(seed=4)
    p = nv.fit_router("discriminant", x, touched_labels=y).to_params()
    edit(p)
    with pytest.raises(nv.RouterError, match=says):
        nv.Router.from_params(p)


def test_wrong_width_and_nan_features_are_refused():
    x, y, *_ = _world(seed=5)
    r = nv.fit_router("discriminant", x, touched_labels=y)
    with pytest.raises(nv.RouterError, match="fitted on 80"):
        r.novelty(np.zeros((2, 79)))
    bad = x[:2].copy()
    bad[0, 3] = np.nan
    with pytest.raises(nv.RouterError, match="NaN"):
        r.novelty(bad)


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_float32_scores_agree_with_float64(scale):
    """The cell's float32 feature: centring and the D x K matmul in float32, the distances summed
    in float64; within 1e-4 relative of float64 scoring of the same float32 features, and the
    same through the cell's own TactileModel.forward (router read back from its parameters)."""
    from vs2t_edge.runtime.inference import TactileModel

    x, y, held, between, away = _world(seed=6)
    r = nv.fit_router("discriminant", x * scale, touched_labels=y)
    q32 = (np.concatenate([held, between, away]) * scale).astype(np.float32)
    ref = r.novelty(q32.astype(np.float64))
    np.testing.assert_allclose(r.novelty(q32, dtype=np.float32), ref, rtol=1e-4)
    loaded = nv.Router.from_params({k: np.asarray(v) for k, v in r.to_params().items()})
    bundle = SimpleNamespace(manifest={}, touched=("t0",), untouched=("u0",), classes=("t0", "u0"), beta=0.0,
                             gating_temperature=1.0, gating_scale=None, router=loaded, preprocess=None,
                             scene_model=None, descriptor=None, camera_jpeg=0)

    class Session:
        def __init__(self, name, fn):
            self.name, self.fn = name, fn

        def get_inputs(self):
            return [SimpleNamespace(name=self.name)]

        def run(self, names, feeds):
            return self.fn(feeds[self.name])

    model = TactileModel(bundle, Session("image", lambda f: [np.asarray(f, np.float32)]),
                         Session("feature", lambda f: [np.zeros((len(f), 1), np.float32)] * 2), threads=1)
    got = model.forward(q32).novelty
    assert got.dtype == np.float64
    np.testing.assert_allclose(got, ref, rtol=1e-4)

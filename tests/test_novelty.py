"""runtime/novelty.py: estimators against their formulas, round trips, thresholds, AUSUC, AUROC."""

from __future__ import annotations

import numpy as np
import pytest

from vs2t_edge.runtime import covariance as cv
from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime import router_eval as reval


def _data(n=60, d=40, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, d)) @ rng.normal(size=(d, d)) * 0.3 + rng.normal(size=d)


def test_router_names_are_the_published_api():
    assert nv.ROUTERS == ("gaussian", "mahalanobis_lw", "mahalanobis_oas", "discriminant", "energy", "max_softmax",
                          "calibrated_stacking")
    assert nv.FEATURE_ROUTERS == (*nv.GAUSSIAN_ROUTERS, "discriminant")


def test_ledoit_wolf_shrinkage_matches_the_definition_by_loops():
    x = _data(30, 12, seed=1)
    xc = x - x.mean(0)
    n, p = xc.shape
    s = xc.T @ xc / n
    mu = np.trace(s) / p
    norm2 = lambda a: np.sum(a * a) / p  # Ledoit-Wolf's normalised Frobenius norm
    d2 = norm2(s - mu * np.eye(p))
    b_bar2 = sum(norm2(np.outer(v, v) - s) for v in xc) / n**2
    expected = min(b_bar2, d2) / d2
    assert cv.ledoit_wolf_shrinkage(xc) == pytest.approx(expected, rel=1e-10)


def test_oas_shrinkage_matches_chen_2010_eq23():
    x = _data(25, 10, seed=2)
    xc = x - x.mean(0)
    n, p = xc.shape
    s = xc.T @ xc / n
    tr_s2, tr2_s = np.trace(s @ s), np.trace(s) ** 2
    expected = min(((1 - 2 / p) * tr_s2 + tr2_s) / ((n + 1 - 2 / p) * (tr_s2 - tr2_s / p)), 1.0)
    assert cv.oas_shrinkage(xc) == pytest.approx(expected, rel=1e-10)


def test_shrinkage_is_one_for_isotropic_and_small_for_many_samples():
    rng = np.random.default_rng(3)
    big = rng.normal(size=(5000, 5)) * np.array([1, 2, 3, 4, 5.0])
    assert cv.ledoit_wolf_shrinkage(big - big.mean(0)) < 0.01
    assert cv.oas_shrinkage(big - big.mean(0)) < 0.01
    few = rng.normal(size=(5, 200))
    assert cv.oas_shrinkage(few - few.mean(0)) > 0.5


def test_gaussian_negative_log_density_matches_direct_formula():
    x = _data(200, 8, seed=4)
    r = nv.fit_router("gaussian", x, variance_floor=0.0)
    mean = x.mean(0)
    cov = np.cov(x.T, bias=True)
    q = _data(5, 8, seed=5)
    diff = q - mean
    m2 = np.einsum("nd,de,ne->n", diff, np.linalg.inv(cov), diff)
    expected = 0.5 * (m2 + np.linalg.slogdet(cov)[1] + 8 * np.log(2 * np.pi))
    np.testing.assert_allclose(r.novelty(q), expected, rtol=1e-9)


@pytest.mark.parametrize("name", nv.ROUTERS)
def test_every_router_round_trips_through_params(name):
    x = _data(50, 16, seed=6)
    rng = np.random.default_rng(7)
    lt, lu = rng.normal(size=(9, 4)) * 5, rng.normal(size=(9, 3)) * 5
    r = nv.fit_router(name, x, lt, touched_labels=np.arange(50) % 4)
    params = r.to_params()
    assert params["name"] == name
    r2 = nv.Router.from_params(params)
    assert type(r2) is type(r) and r2.name == name
    q = _data(9, 16, seed=8)
    np.testing.assert_array_equal(r.novelty(q, lt, logits_u=lu), r2.novelty(q, lt, logits_u=lu))
    assert r.novelty(q, lt, logits_u=lu).dtype == np.float64


def test_from_params_names_what_is_wrong():
    with pytest.raises(nv.RouterError, match="unknown router 'nope'"):
        nv.Router.from_params({"name": "nope"})
    with pytest.raises(nv.RouterError, match="lack 'mean'"):
        nv.Router.from_params({"name": "gaussian"})
    p = nv.fit_router("gaussian", _data(20, 4)).to_params()
    p["whitening"] = p["whitening"][:3]
    with pytest.raises(nv.RouterError, match="whitening"):
        nv.Router.from_params(p)
    with pytest.raises(nv.RouterError, match="needs logits_t"):
        nv.fit_router("energy", None).novelty(None)
    with pytest.raises(nv.RouterError, match="fitted on 4"):
        nv.fit_router("gaussian", _data(20, 4)).novelty(np.zeros((2, 5)))


def test_router_is_immutable():
    r = nv.fit_router("mahalanobis_lw", _data(20, 4))
    with pytest.raises(Exception):
        r.name = "x"
    with pytest.raises(ValueError):
        r.mean[0] = 1.0


def test_covariance_only_params_rebuild_the_same_scores():
    r = nv.fit_router("mahalanobis_oas", _data(40, 10))
    p = r.to_params()
    del p["whitening"]
    r2 = nv.Router.from_params(p)
    q = _data(6, 10, seed=9)
    np.testing.assert_allclose(r2.novelty(q), r.novelty(q), rtol=1e-8)


def test_ausuc_on_a_constructed_case():
    # touched novelty 0, 2; untouched 1, 3; all correct. Curve corners:
    # (acc_u, acc_t) = (0,1) (.5,1) (.5,.5) (1,.5) (1,0) -> area 0.5 + 0.25 = 0.75
    assert reval.ausuc([0, 2], [1, 1], [1, 3], [1, 1]) == pytest.approx(0.75)
    # perfectly separated, perfect heads -> 1; heads that are always wrong -> 0
    assert reval.ausuc([0, 1], [1, 1], [2, 3], [1, 1]) == pytest.approx(1.0)
    assert reval.ausuc([0, 1], [0, 0], [2, 3], [1, 1]) == pytest.approx(0.0)
    # half-right touched head, perfect separation: rectangle 1 x 0.5
    assert reval.ausuc([0, 1], [1, 0], [2, 3], [1, 1]) == pytest.approx(0.5)


def test_seen_unseen_curve_ends_and_per_class_weights():
    acc_u, acc_t, betas = reval.seen_unseen_curve([0, 0, 0, 5], [1, 1, 1, 0], [9], [1],
                                               labels_touched=[0, 0, 0, 1])
    assert betas[0] == np.inf and betas[-1] == -np.inf
    assert acc_t[0] == pytest.approx(0.5)  # class 0 all right, class 1 wrong -> mean 0.5
    assert acc_u[0] == 0.0 and acc_u[-1] == 1.0 and acc_t[-1] == 0.0
    assert np.all(np.diff(acc_u) >= 0) and np.all(np.diff(acc_t) <= 0)


def test_auroc_known_values():
    assert reval.auroc([0, 1, 2], [3, 4]) == 1.0
    assert reval.auroc([3, 4], [0, 1, 2]) == 0.0
    assert reval.auroc([1, 1], [1, 1]) == 0.5
    assert reval.auroc([0, 2], [1, 3]) == pytest.approx(0.75)


def test_gzsl_accuracies_and_h():
    out = reval.gzsl_accuracies([False, True], [True, True], [True, True], [True, False])
    assert out["acc_t"] == 0.5 and out["acc_u"] == 0.5 and out["H"] == pytest.approx(0.5)


@pytest.mark.parametrize("name", nv.ROUTERS)
def test_params_survive_an_npz_file(name, tmp_path):
    """Bundles store router parameters as .npz: 0-d string arrays must rebuild the router."""
    x = _data(30, 8, seed=10)
    logits = x[:, :3]
    r = nv.fit_router(name, x, logits, touched_labels=np.arange(30) % 3)
    np.savez(tmp_path / "router.npz", **r.to_params())
    with np.load(tmp_path / "router.npz") as z:
        r2 = nv.Router.from_params(dict(z))
    np.testing.assert_allclose(r2.novelty(x, logits, logits_u=logits[:, :2]),
                               r.novelty(x, logits, logits_u=logits[:, :2]), rtol=1e-12)

"""Issues 4/5: export ships any GZSL router and the cell decides with the one the bundle names.

One tiny bundle per router in runtime.novelty.ROUTERS, all from the same tiny modules and frames
(test_bundle_fixtures.make_bundle; only the router and its beta differ), so the whole file costs
one export per router. Each bundle must load with the cell's own TactileModel.load (hashes, seal,
probe), name its router in the manifest, score presses with exactly that router's rule, and give
finite, normalised posteriors. A router.npz that holds another router than the manifest names is
refused even when the hashes and the seal are consistent.
"""
from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from test_bundle_fixtures import TOUCHED, UNTOUCHED, fit_fixture_router, make_bundle, world_frames
from vs2t_edge.runtime import bundle as rb
from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime.inference import TactileModel

ROUTERS = nv.ROUTERS  # gaussian, mahalanobis_lw, mahalanobis_oas, discriminant, energy, max_softmax, calibrated_stacking


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    root = tmp_path_factory.mktemp("router_bundles")
    return {name: (root / name, make_bundle(root / name, "fp32", router=name)) for name in ROUTERS}


def test_the_routers_of_issues_4_and_5_are_all_covered():
    # ROUTERS parametrises this file: a router dropped from it would silently lose its tests
    assert set(ROUTERS) >= {"gaussian", "mahalanobis_lw", "mahalanobis_oas", "discriminant", "energy", "max_softmax",
                            "calibrated_stacking"}


def _log_softmax(z):
    z = np.asarray(z, np.float64)
    z = z - z.max(1, keepdims=True)
    return z - np.log(np.exp(z).sum(1, keepdims=True))


def _expected_novelty(name, out, reference_router):
    """Each router's rule written out independently of runtime.novelty where it is a formula; the
    density routers against the router fitted on torch features (float64 reference)."""
    lt, lu = np.asarray(out.logits_t, np.float64), np.asarray(out.logits_u, np.float64)
    if name == "energy":
        return -np.log(np.exp(lt).sum(1))  # temperature 1
    if name == "max_softmax":
        return -np.exp(_log_softmax(lt)).max(1)
    if name == "calibrated_stacking":
        return _log_softmax(lu).max(1) - _log_softmax(lt).max(1)
    return reference_router.novelty(np.asarray(out.feature, np.float64))


@pytest.mark.parametrize("name", ROUTERS)
def test_bundle_decides_with_the_router_it_names(bundles, name):
    path, manifest = bundles[name]
    assert manifest["router"] == {"name": name, "file": "router.npz"}
    with np.load(path / "router.npz") as z:
        assert str(z["name"]) == name
    model = TactileModel.load(path, threads=1)  # verifies hashes, seal, shapes and runs the probe
    assert model.router.name == name and json.loads((path / rb.MANIFEST).read_text())["router"]["name"] == name
    tol = manifest["probe"]["tolerance"]
    limit = {"feature": tol["feature"], "logits_t": tol["logits"], "logits_u": tol["logits"], "novelty": tol["novelty"]}
    if name in nv.GAUSSIAN_ROUTERS:  # the fused graph's whitened vector, and its novelty against router.npz's
        limit.update(router_z=tol["novelty"], novelty_vs_router_file=tol["novelty"])
    if name in rb.LOGIT_ROUTERS:  # folded into the graph: its output, and its novelty against router.npz's
        limit.update(router_novelty=tol["novelty"], novelty_vs_router_file=tol["novelty"])
    assert set(model.probe_errors) == set(limit)
    assert all(model.probe_errors[k] <= limit[k] for k in limit), model.probe_errors

    x, raws, ref = world_frames()
    out = model.forward(x[40:60])  # held-out touched presses, not the ones the router was fitted on
    reference_router, beta, _ = fit_fixture_router(name)
    assert model.beta == pytest.approx(beta) == manifest["beta"]
    want = _expected_novelty(name, out, reference_router)
    assert np.all(np.isfinite(out.novelty))
    assert np.allclose(out.novelty, want, rtol=1e-3, atol=1e-4 * max(1.0, float(np.abs(want).max())))

    model.set_reference(ref)
    for frame in raws[:12]:
        s = model.score_press(frame)
        assert list(s.log_posterior) == list(TOUCHED + UNTOUCHED)
        lp = np.array(list(s.log_posterior.values()))
        assert np.all(np.isfinite(lp)) and np.all(lp <= 1e-12)
        assert math.fsum(np.exp(lp)) == pytest.approx(1.0, abs=1e-9)
        assert math.isfinite(s.novelty) and s.untouched == (s.novelty > model.beta)


def test_the_routers_really_differ_on_the_same_presses(bundles):
    """Same graphs, different routers: if the runtime ignored the bundle's router (say, always the
    Gaussian) the novelty of the logit routers would equal the Gaussian's."""
    x, _, _ = world_frames()
    nov = {n: TactileModel.load(bundles[n][0], threads=1).forward(x[40:52]).novelty for n in ROUTERS}
    for a in ROUTERS:
        for b in ROUTERS:
            if a < b:
                assert not np.allclose(nov[a], nov[b]), (a, b)


def _reseal_with_router(src, dst, router):
    """dst = src with router.npz replaced by ``router``'s parameters, its hash updated and the
    manifest re-sealed - everything consistent except the router's name."""
    shutil.copytree(src, dst)
    np.savez(dst / "router.npz", **{k: np.asarray(v) for k, v in router.to_params().items()})
    m = json.loads((dst / rb.MANIFEST).read_text())
    m["files"]["router.npz"] = rb.sha256_file(dst / "router.npz")
    (dst / rb.MANIFEST).write_text(json.dumps(rb.seal_manifest(m)))


@pytest.mark.parametrize("named, held", [("energy", "max_softmax"), ("gaussian", "energy"),
                                         ("max_softmax", "mahalanobis_oas"), ("mahalanobis_lw", "gaussian"),
                                         ("calibrated_stacking", "energy")])
def test_router_file_holding_another_router_is_refused(bundles, tmp_path, named, held, capsys):
    from vs2t_edge.cli import main

    other, _, _ = fit_fixture_router(held)
    dst = tmp_path / "b"
    _reseal_with_router(bundles[named][0], dst, other)
    with pytest.raises(rb.BundleError, match=rf"router\.npz holds router '{held}', the manifest says '{named}'"):
        TactileModel.load(dst, threads=1)
    assert main(["verify-bundle", str(dst)]) != 0
    assert f"holds router '{held}'" in capsys.readouterr().err
    # the same file under its own name is accepted: the refusal is about the name, not the edit
    _reseal_with_router(bundles[named][0], tmp_path / "same", fit_fixture_router(named)[0])
    assert TactileModel.load(tmp_path / "same", threads=1).router.name == named

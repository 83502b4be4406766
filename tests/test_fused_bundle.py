"""The fused press graph (format 2, export/fuse.py): one onnxruntime call per press gives what the
two-graph path (format 1) gave, old bundles keep loading and scoring as before, and a fused graph
that computes something else than the bundle's router / scene model files is refused. A scene
model's bundle (format 3, tests/test_split_bundle.py) writes format 2 with ``--heads-in-press-graph``,
as every export did before it: what these tests build."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from test_bundle_fixtures import SIZE, TOUCHED, UNTOUCHED, tiny_modules, world_frames
from vs2t_edge.runtime import bundle as rb
from vs2t_edge.runtime.inference import TactileModel

# |log p_fused - log p_two_graphs| per class and press: both paths are float32 up to the
# projections, which run in another order (one onnxruntime graph vs numpy); measured ~2e-6 here
LOG_POSTERIOR_ATOL = 1e-4
# novelty against the squared distance it is made of: the float32 router's own contract
# (tests/test_novelty_stability.py F32_RTOL); measured up to ~1.2e-5 here, as the numpy float32 path
NOVELTY_RTOL = 1e-4


def _router(kind: str):
    """gaussian on 40 presses (n > D = 16: the full whitening), gaussian on 8 presses (rank 7: the
    low-rank form), energy (a logit router: its formula folded in as router_novelty)."""
    import torch

    from vs2t_edge.runtime import novelty as nv

    trunk, cls_t, cls_u = tiny_modules(0)
    x, _, _ = world_frames(SIZE)
    with torch.no_grad():
        f = trunk(torch.from_numpy(x[:40]))
        lt, lu = cls_t(f).numpy(), cls_u(f).numpy()
    f = f.numpy()
    if kind == "energy":
        router = nv.fit_router("energy", None)
    else:
        router = nv.fit_router("gaussian", f[:8] if kind == "gaussian_low_rank" else f, keep_covariance=False)
    return router, float(np.quantile(router.novelty(f, lt, logits_u=lu), 0.9)), f


def _scene_params(f: np.ndarray) -> dict:
    from vs2t_edge.runtime.scene_model import SceneModel

    rng = np.random.default_rng(0)
    y = np.arange(len(f)) % len(TOUCHED)
    fu = rng.standard_normal((20, f.shape[1])) * f.std(0) + f.mean(0)
    sm = SceneModel.fit(f, y, list(TOUCHED), fu, np.arange(20) % len(UNTOUCHED), list(UNTOUCHED), k=6)
    return sm.to_params()


def _write(out, kind: str, fuse: bool, scene: bool = True, precision: str = "fp32", heads: str = "fp32",
           heads_in_press_graph: bool = True):
    from vs2t_edge.export.export import write_bundle
    from vs2t_edge.runtime.preprocess import TactilePreprocess

    trunk, cls_t, cls_u = tiny_modules(0)
    x, _, _ = world_frames(SIZE)
    router, beta, f = _router(kind)
    return write_bundle(out, trunk=trunk, cls_t=cls_t, cls_u=cls_u, router=router, touched=TOUCHED,
                        untouched=UNTOUCHED, preprocess=TactilePreprocess(size=SIZE), beta=beta, calibration=x[:40],
                        trunk_precision=precision, trunk_arch="tiny-test", validation=x[60:], touched_heldout=x[40:60],
                        scene_model=_scene_params(f) if scene else None, fuse=fuse, heads_precision=heads,
                        heads_in_press_graph=heads_in_press_graph)


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    """{router kind: (fused bundle, two-graph bundle)} of the same modules."""
    root = tmp_path_factory.mktemp("fused")
    out = {}
    for kind in ("gaussian", "gaussian_low_rank", "energy"):
        _write(root / f"{kind}_fused", kind, True)
        _write(root / f"{kind}_two", kind, False)
        out[kind] = (root / f"{kind}_fused", root / f"{kind}_two")
    return out


@pytest.mark.parametrize("kind,form", [("gaussian", "whitened"), ("gaussian_low_rank", "low_rank"), ("energy", None)])
def test_fused_bundle_scores_as_the_two_graph_path(pairs, kind, form):
    fused_dir, two_dir = pairs[kind]
    fused, two = TactileModel.load(fused_dir, threads=1), TactileModel.load(two_dir, threads=1)
    m = fused.manifest
    assert m["format_version"] == 2 and fused.fused and not two.fused
    assert "heads" not in m["graphs"] and "heads.onnx" not in m["files"] and not (fused_dir / "heads.onnx").exists()
    want = {"feature", "logits_t", "logits_u", "scene_z"} | ({"router_z"} if form else {"router_novelty"})
    assert set(m["graphs"]["trunk"]["outputs"]) == want
    assert (m["graphs"]["trunk"]["fused"].get("router_z") or {}).get("form") == form
    assert two.manifest["format_version"] == 1 and set(two.manifest["graphs"]) == {"trunk", "heads"}
    # the probe covers every output of the fused graph, and its agreement with router.npz / decision.npz
    assert set(fused.probe_errors) >= want - {"logits_t", "logits_u"} | {"scene_z_vs_decision_file"}
    _, raws, ref = world_frames(SIZE)
    fused.set_reference(ref)
    two.set_reference(ref)
    for frame in raws[::3]:
        a, b = fused.score_press(frame), two.score_press(frame)
        assert list(a.log_posterior) == list(b.log_posterior) == list(fused.classes)
        lp_a, lp_b = np.array(list(a.log_posterior.values())), np.array(list(b.log_posterior.values()))
        np.testing.assert_allclose(lp_a, lp_b, rtol=0, atol=LOG_POSTERIOR_ATOL)
        # relative to the squared distance: the Gaussian's log-density constant nearly cancels it
        feature = two.forward(two.preprocess(frame)).feature
        scale = 0.5 * float(two.bundle.router.squared_mahalanobis(feature)[0]) if form else abs(b.novelty)
        assert abs(a.novelty - b.novelty) <= NOVELTY_RTOL * max(scale, abs(b.novelty))
        assert a.untouched == b.untouched
        d_a, d_b = np.array(list(a.sq_distance.values())), np.array(list(b.sq_distance.values()))
        np.testing.assert_allclose(d_a, d_b, rtol=1e-5, atol=1e-6)
        assert fused.last_timing["heads_ms"] == 0.0  # one onnxruntime call


def test_low_rank_router_projection_is_smaller_and_exact(pairs):
    """Fitted on 8 presses, the 16-d covariance has rank 7: the graph computes 7 scaled directions
    and the residual instead of the 16 x 16 whitening, and the novelty is the float64 router's."""
    fused = TactileModel.load(pairs["gaussian_low_rank"][0], threads=1)
    info = fused.manifest["graphs"]["trunk"]["fused"]["router_z"]
    assert info["rank"] == 7 and info["width"] == 7 + 16 and info["macs"] == 2 * 7 * 16
    out = fused.forward(world_frames(SIZE)[0][60:])
    f64 = out.feature.astype(np.float64)
    ref, m2 = fused.bundle.router.novelty(f64), fused.bundle.router.squared_mahalanobis(f64)
    assert np.all(np.abs(out.novelty - ref) <= NOVELTY_RTOL * 0.5 * m2)  # the log-density's constant is exact
    assert fused.manifest["checks"]["fused_vs_two_graphs"]["novelty_vs_router_float64"] <= 1e-4


def _scaled(head, k: float):
    """The head with its logits times ``k``: logits of +-1e3 test the folded formula's stability
    (logsumexp and softmax shift by the max, as runtime/novelty.py does)."""
    import torch

    class Scaled(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.head = head

        def forward(self, f):
            return self.head(f) * k

    return Scaled()


@pytest.mark.parametrize("params", [{"name": "energy", "temperature": 1.0}, {"name": "energy", "temperature": 3.5},
                                    {"name": "max_softmax", "temperature": 1.0},
                                    {"name": "max_softmax", "temperature": 0.5},
                                    {"name": "calibrated_stacking", "scores": "log_softmax"},
                                    {"name": "calibrated_stacking", "scores": "logits"}])
@pytest.mark.parametrize("k", [1.0, 300.0])
def test_folded_logit_router_is_the_numpy_router(params, k, tmp_path):
    """router_novelty from the graph (float32) = the numpy router's float64 novelty on the graph's
    own logits, to 1e-5 of the largest novelty, for every router on the logits."""
    from vs2t_edge.export import fuse as fz
    from vs2t_edge.runtime import novelty as nv
    from vs2t_edge.runtime.bundle import open_session

    router = nv.Router.from_params({**params, "params_version": nv.PARAMS_VERSION})
    rule = fz.logit_router_rule(router)
    assert rule == params
    _, cls_t, cls_u = tiny_modules(0)
    names = fz.export_tail(tmp_path / "tail.onnx", _scaled(cls_t, k), _scaled(cls_u, k), 16, None, None, 20, rule)
    assert names == ["logits_t", "logits_u", "router_novelty"]
    f = np.random.default_rng(1).standard_normal((64, 16)).astype(np.float32) * 3
    lt, lu, nov = open_session(tmp_path / "tail.onnx", 1).run(None, {"feature": f})
    assert nov.shape == (64, 1) and nov.dtype == np.float32
    ref = router.novelty(f, lt.astype(np.float64), logits_u=lu.astype(np.float64))
    assert np.max(np.abs(nov[:, 0] - ref)) <= 1e-5 * np.max(np.abs(ref))
    assert np.ptp(ref) > 1e-3 * np.max(np.abs(ref))  # the presses do not all score alike


def test_feature_routers_fold_no_logit_rule():
    from vs2t_edge.export import fuse as fz

    assert fz.logit_router_rule(_router("gaussian")[0]) is None


def _fused_without_router_output(fused_dir, two_dir, tmp_path):
    """A copy of a fused bundle whose press graph is re-fused with no router output (router_z or
    router_novelty): the heads and the scene projection only. Manifest and probe left as they were."""
    from vs2t_edge.export import fuse as fz

    b = _copy(fused_dir, tmp_path)
    _, cls_t, cls_u = tiny_modules(0)
    sm = TactileModel.load(fused_dir, threads=1).scene_model
    fz.export_tail(tmp_path / "tail.onnx", cls_t, cls_u, 16, None, {"center": sm.center, "basis": sm.basis}, 20)
    fz.merge_into_trunk(two_dir / "trunk.onnx", tmp_path / "tail.onnx", b / "trunk.onnx")
    return b


def test_fused_energy_bundle_without_router_novelty_scores_in_numpy(pairs, tmp_path):
    """A fused bundle exported before the logit routers were folded in (no router_novelty): it loads,
    and its novelty is the numpy router's, as before."""
    from vs2t_edge.export.export import graph_io

    fused_dir = pairs["energy"][0]
    b = _fused_without_router_output(*pairs["energy"], tmp_path)
    z = dict(np.load(b / "probe_expected.npz"))
    del z["router_novelty"]
    np.savez(b / "probe_expected.npz", **z)

    def old_manifest(m):
        m["graphs"]["trunk"]["outputs"] = graph_io(b / "trunk.onnx")["outputs"]
        del m["graphs"]["trunk"]["fused"]["router_novelty"]

    _reseal(b, old_manifest)
    old, new = TactileModel.load(b, threads=1), TactileModel.load(fused_dir, threads=1)
    assert "router_novelty" not in old._press_outputs and "router_novelty" in new._press_outputs
    x = world_frames(SIZE)[0][60:]
    a, c = old.forward(x), new.forward(x)
    assert a.router_novelty is None and c.router_novelty is not None
    np.testing.assert_allclose(a.novelty, c.novelty, rtol=1e-5, atol=1e-6)
    assert np.array_equal(a.novelty, old.bundle.router.novelty(a.feature, a.logits_t, logits_u=a.logits_u))


def test_folded_router_that_is_not_router_npz_is_refused(pairs, tmp_path):
    """The graph folds energy at temperature 2, router.npz says 1 (probe regenerated, re-sealed):
    the probe's cross-check against router.npz refuses it."""
    from vs2t_edge.export import fuse as fz
    from vs2t_edge.runtime.bundle import open_session

    fused_dir, two_dir = pairs["energy"]
    b = _copy(fused_dir, tmp_path)
    _, cls_t, cls_u = tiny_modules(0)
    sm = TactileModel.load(fused_dir, threads=1).scene_model
    fz.export_tail(tmp_path / "tail.onnx", cls_t, cls_u, 16, None, {"center": sm.center, "basis": sm.basis}, 20,
                   {"name": "energy", "temperature": 2.0})
    fz.merge_into_trunk(two_dir / "trunk.onnx", tmp_path / "tail.onnx", b / "trunk.onnx")
    sess = open_session(b / "trunk.onnx", 1)
    got = dict(zip([o.name for o in sess.get_outputs()], sess.run(None, {"image": np.load(b / "probe_input.npy")})))
    got["novelty"] = got["router_novelty"][:, 0].astype(np.float64)
    np.savez(b / "probe_expected.npz", **got)
    _reseal(b)
    with pytest.raises(rb.BundleError, match=r"probe check failed: 'novelty_vs_router_file'"):
        TactileModel.load(b)


def test_probe_reads_a_novelty_near_zero_relative_to_one_unit(pairs, tmp_path):
    """Calibrated stacking on a press both heads are sure of: novelty is the difference of two
    log-probabilities near 0 (a demo world's probe press: 2.86e-6 from the float32 graph, 2.82e-6 from
    numpy's float64). Relative to itself that is 1.4 % off and the probe refused the sound bundle,
    so its export failed; relative to one unit it is 4e-8. A shift the size of a threshold's
    resolution still fails, and a graph whose novelty differs from its expected probe output by a
    hundredth of a unit is refused on load."""
    from vs2t_edge.runtime import inference as inf

    assert inf.probe_error("novelty_vs_router_file", np.array([2.86101886e-06]), np.array([2.82146396e-06])) < 1e-6
    assert inf.probe_error("router_novelty", np.array([0.01]), np.array([0.0])) > 1e-4
    assert inf.probe_error("novelty", np.array([1000.5]), np.array([1000.0])) > 1e-4
    assert inf.probe_error("feature", np.array([2.86101886e-06]), np.array([2.82146396e-06])) > 1e-4  # features stay relative
    b = _copy(pairs["energy"][0], tmp_path)
    exp = dict(np.load(b / "probe_expected.npz"))
    exp["novelty"] = exp["novelty"] + 0.01 * max(1.0, float(np.max(np.abs(exp["novelty"]))))
    np.savez(b / "probe_expected.npz", **exp)
    _reseal(b)
    with pytest.raises(rb.BundleError, match=r"probe check failed: 'novelty'"):
        TactileModel.load(b)


def test_two_graph_bundles_still_load(pairs):
    """Format 1 (every bundle before the fused graph): the committed replay bundle (opset 17) and a
    fresh --two-graphs export load, run two sessions, and pass their probes."""
    from pathlib import Path

    old = TactileModel.load(Path(__file__).parent / "replays" / "bundle", threads=1)
    assert old.manifest["format_version"] == 1 and not old.fused and old._heads is not None
    assert max(old.probe_errors.values()) <= 1e-3
    two = TactileModel.load(pairs["gaussian"][1], threads=1)
    assert set(two.probe_errors) == {"feature", "logits_t", "logits_u", "novelty"}


def _copy(src, tmp_path):
    dst = tmp_path / "b"
    shutil.copytree(src, dst)
    return dst


def _reseal(b, fn=lambda m: None):
    """As an exporter (or someone who recomputes every digest) would leave it: hashes and seal match."""
    m = json.loads((b / "manifest.json").read_text())
    fn(m)
    for name in m["files"]:
        m["files"][name] = rb.sha256_file(b / name)
    (b / "manifest.json").write_text(json.dumps(rb.seal_manifest(m)))


def test_changed_fused_graph_is_refused_by_hash(pairs, tmp_path):
    b = _copy(pairs["gaussian"][0], tmp_path)
    with open(b / "trunk.onnx", "ab") as f:
        f.write(b"\0")
    with pytest.raises(rb.BundleError, match=r"trunk\.onnx: sha256"):
        TactileModel.load(b)


def _refuse_graph_with_router(pairs, tmp_path, other_router, match):
    """trunk.onnx re-fused with another router's projection, every probe expectation regenerated
    from that graph and the bundle re-sealed: only the cross-check against router.npz can tell."""
    from vs2t_edge.export import fuse as fz
    from vs2t_edge.runtime.bundle import open_session
    from vs2t_edge.runtime.inference import fused_novelty

    fused_dir, two_dir = pairs["gaussian"]
    b = _copy(fused_dir, tmp_path)
    trunk, cls_t, cls_u = tiny_modules(0)
    from vs2t_edge.runtime.scene_model import SceneModel

    sm = TactileModel.load(fused_dir, threads=1).scene_model
    fz.export_tail(tmp_path / "tail.onnx", cls_t, cls_u, 16, fz.router_projection(other_router),
                   {"center": sm.center, "basis": sm.basis}, 20)
    fz.merge_into_trunk(two_dir / "trunk.onnx", tmp_path / "tail.onnx", b / "trunk.onnx")
    sess = open_session(b / "trunk.onnx", 1)
    names = [o.name for o in sess.get_outputs()]
    got = dict(zip(names, sess.run(None, {"image": np.load(b / "probe_input.npy")})))
    bundle_router = rb.load_bundle(fused_dir).router
    got["novelty"] = fused_novelty(bundle_router, got["feature"], got["logits_t"], got["logits_u"], got["router_z"])
    np.savez(b / "probe_expected.npz", **got)
    _reseal(b)
    assert isinstance(SceneModel, type)
    with pytest.raises(rb.BundleError, match=match):
        TactileModel.load(b)


def test_fused_graph_whose_router_is_not_router_npz_is_refused(pairs, tmp_path):
    from vs2t_edge.runtime import novelty as nv

    _, _, f = _router("gaussian")
    other = nv.fit_router("gaussian", f[::-1][:30] * 1.5, keep_covariance=False)
    _refuse_graph_with_router(pairs, tmp_path, other, r"probe check failed: 'novelty_vs_router_file'")


def test_fused_graph_without_the_router_output_is_refused(pairs, tmp_path):
    """A Gaussian router's bundle whose graph does not give router_z (re-fused without it, manifest
    re-declared and re-sealed): the outputs are not what this router needs."""
    from vs2t_edge.export.export import graph_io

    b = _fused_without_router_output(*pairs["gaussian"], tmp_path)
    _reseal(b, lambda m: m["graphs"]["trunk"].__setitem__("outputs", graph_io(b / "trunk.onnx")["outputs"]))
    with pytest.raises(rb.BundleError, match=r"trunk\.onnx: outputs \[.*\], this bundle's router 'gaussian'.*need"):
        TactileModel.load(b)


def test_fused_probe_must_cover_the_projections(pairs, tmp_path):
    b = _copy(pairs["gaussian"][0], tmp_path)
    z = dict(np.load(b / "probe_expected.npz"))
    del z["scene_z"]
    np.savez(b / "probe_expected.npz", **z)
    _reseal(b)
    with pytest.raises(rb.BundleError, match=r"probe_expected\.npz lacks 'scene_z'"):
        TactileModel.load(b)
    z["scene_z"] = np.load(pairs["gaussian"][0] / "probe_expected.npz")["scene_z"] * 1.01
    np.savez(b / "probe_expected.npz", **z)
    _reseal(b)
    with pytest.raises(rb.BundleError, match=r"probe check failed: 'scene_z'"):
        TactileModel.load(b)


def test_unknown_format_version_names_the_readable_ones(pairs, tmp_path):
    b = _copy(pairs["energy"][0], tmp_path)
    _reseal(b, lambda m: m.__setitem__("format_version", 4))
    with pytest.raises(rb.BundleError, match=r"format version 4, this runtime reads versions 1, 2, 3"):
        TactileModel.load(b)


def test_int8_trunk_is_fused_with_float_heads(tmp_path):
    """The int8 QDQ trunk (export/quantize.py, untouched) gets the same float32 tail appended."""
    m = _write(tmp_path / "b8", "gaussian", True, scene=False, precision="int8")
    assert m["format_version"] == 2 and m["graphs"]["trunk"]["precision"] == "int8"
    assert set(m["graphs"]["trunk"]["outputs"]) == {"feature", "logits_t", "logits_u", "router_z"}
    c = m["checks"]["fused_vs_two_graphs"]
    assert c["feature"] <= 1e-6 and c["logits_t"] <= 1e-4  # the same int8 kernels, then the same heads
    model = TactileModel.load(tmp_path / "b8", threads=1)
    assert model.probe_errors["novelty_vs_router_file"] <= m["probe"]["tolerance"]["novelty"]


@pytest.mark.parametrize("kind", ["energy", "gaussian"])
def test_int8_heads_fold_into_the_press_graph_and_keep_the_projections_float(pairs, kind, tmp_path):
    """--heads-precision int8: the heads' Gemms become MatMulInteger with int8 weights, the
    projections (router_z, scene_z) stay float MatMuls; the logits stay within the int8 tolerance
    of the float heads', the scores the bundle's router and scene model make of them hold."""
    import onnx

    m = _write(tmp_path / "b", kind, True, heads="int8")
    fused = m["graphs"]["trunk"]["fused"]
    assert "int8" in fused["heads"] and m["probe"]["tolerance"]["logits"] == 2e-2
    assert m["probe"]["tolerance"]["projection"] == 1e-4  # scene_z stays float32
    c = m["checks"]["fused_vs_two_graphs"]
    assert 0.0 < c["logits_t"] <= 2e-2 and c["scene_z_vs_float64"] <= 1e-4
    g = onnx.load(str(tmp_path / "b" / "trunk.onnx")).graph
    tail = [n for n in g.node if n.name.startswith("press_tail/")]
    assert sum(n.op_type == "MatMulInteger" for n in tail) == 4  # the test heads: 2 linear layers each
    assert not any(n.op_type == "Gemm" for n in tail)
    floats = [n for n in tail if n.op_type == "MatMul"]
    assert len(floats) == (2 if kind == "gaussian" else 1)  # router_z (whitened) and scene_z
    int8 = TactileModel.load(tmp_path / "b", threads=1)
    ref = TactileModel.load(pairs[kind][0], threads=1)
    x = world_frames(SIZE)[0][60:]
    a, b = int8.forward(x), ref.forward(x)
    np.testing.assert_array_equal(a.feature, b.feature)
    assert np.max(np.abs(a.logits_t - b.logits_t)) <= 2e-2 * np.max(np.abs(b.logits_t))
    np.testing.assert_allclose(a.scene_z, b.scene_z, rtol=1e-5, atol=1e-6)
    if kind == "energy":  # the folded router reads the int8 logits: its novelty is the router's of them
        want = int8.bundle.router.novelty(a.feature, a.logits_t.astype(np.float64),
                                          logits_u=a.logits_u.astype(np.float64))
        np.testing.assert_allclose(a.novelty, want, rtol=1e-5)


def test_int8_heads_need_the_fused_graph(tmp_path):
    from vs2t_edge.export.export import ExportError

    with pytest.raises(ExportError, match="heads precision"):
        _write(tmp_path / "b", "energy", False, heads="int8")


@pytest.mark.parametrize("kind,bad", [("gaussian", "feature"), ("gaussian", "router_z"), ("gaussian", "scene_z"),
                                      ("energy", "logits_t"), ("energy", "scene_z"), ("energy", "router_novelty")])
def test_non_finite_press_graph_output_is_a_frame_error(pairs, kind, bad):
    """A NaN in any output the cell reads is never routed to a bin: FrameError, as the two-graph
    path raises for a non-finite feature or logits."""
    from vs2t_edge.runtime.preprocess import FrameError

    model = poison_output(TactileModel.load(pairs[kind][0], threads=1), bad)
    _, raws, ref = world_frames(SIZE)
    model.set_reference(ref)
    with pytest.raises(FrameError, match="model output not usable"):
        model.score_press(raws[0])


def poison_output(model: TactileModel, bad: str) -> TactileModel:
    """``model`` whose press graph puts a NaN in output ``bad`` of every run."""
    real = model._trunk

    class Poisoned:
        def get_inputs(self):
            return real.get_inputs()

        def run(self, names, feeds):
            out = real.run(names, feeds)
            i = names.index(bad)
            out[i] = out[i].copy()
            out[i][0, 0] = np.nan
            return out

    model._trunk = Poisoned()
    return model

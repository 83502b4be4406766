"""Format 3 (export/fuse.py): a scene model's bundle whose press graph ends at the scene projection.
The cell's press is one onnxruntime call that runs no head and no router, and decides exactly as
the format-2 graph of the same modules (heads folded in) decided; the heads and the router's
outputs sit in heads.onnx for the probe, the bench's accuracy and calibration."""
from __future__ import annotations

import json

import numpy as np
import pytest

from test_bundle_fixtures import SIZE, world_frames
from test_fused_bundle import LOG_POSTERIOR_ATOL, _copy, _reseal, _write, poison_output
from vs2t_edge.runtime import bundle as rb
from vs2t_edge.runtime.inference import TactileModel
from vs2t_edge.runtime.preprocess import FrameError


@pytest.fixture(scope="module")
def formats(tmp_path_factory):
    """{router kind: (format-3 bundle, format-2 bundle)} of the same modules and scene model."""
    root = tmp_path_factory.mktemp("split")
    out = {}
    for kind in ("gaussian", "energy"):
        _write(root / f"{kind}_3", kind, True, heads_in_press_graph=False)
        _write(root / f"{kind}_2", kind, True)
        out[kind] = (root / f"{kind}_3", root / f"{kind}_2")
    return out


@pytest.mark.parametrize("kind", ["gaussian", "energy"])
def test_press_graph_ends_at_the_scene_projection_and_decides_as_format_2(formats, kind):
    split_dir, fused_dir = formats[kind]
    split, fused = TactileModel.load(split_dir, threads=1), TactileModel.load(fused_dir, threads=1)
    m = split.manifest
    assert m["format_version"] == 3 and split.split and split.fused and not fused.split
    assert set(m["graphs"]["trunk"]["outputs"]) == {"feature", "scene_z"}
    router_out = "router_z" if kind == "gaussian" else "router_novelty"
    assert set(m["graphs"]["heads"]["outputs"]) == {"logits_t", "logits_u", router_out}
    assert (split_dir / "heads.onnx").exists() and "heads.onnx" in m["files"]
    import onnx  # the merged press graph imports each opset domain once (onnxruntime's quantiser needs it)

    domains = [o.domain for o in onnx.load(str(split_dir / "trunk.onnx")).opset_import]
    assert len(domains) == len(set(domains))
    # the probe still covers every output of both graphs, and their agreement with the files
    assert set(split.probe_errors) >= {"feature", "logits_t", "logits_u", "novelty", "scene_z", router_out,
                                       "novelty_vs_router_file", "scene_z_vs_decision_file"}
    _, raws, ref = world_frames(SIZE)
    split.set_reference(ref)
    fused.set_reference(ref)
    for frame in raws[::3]:
        a, b = split.score_press(frame), fused.score_press(frame)
        assert a.novelty is None and a.untouched is None and b.novelty is not None
        assert split.last_timing["heads_ms"] == 0.0 and split.last_timing["router_ms"] == 0.0
        assert list(a.log_posterior) == list(b.log_posterior) == list(split.scene_model.classes)
        np.testing.assert_allclose(list(a.log_posterior.values()), list(b.log_posterior.values()),
                                   rtol=0, atol=LOG_POSTERIOR_ATOL)
        np.testing.assert_allclose(list(a.sq_distance.values()), list(b.sq_distance.values()), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(a.scene_z, b.scene_z, rtol=1e-5, atol=1e-6)
    # off the press path the heads and the router give what format 2's one graph gives
    x = world_frames(SIZE)[0][60:]
    o3, o2 = split.forward(x), fused.forward(x)
    assert split.last_timing["heads_ms"] > 0.0
    np.testing.assert_allclose(o3.logits_t, o2.logits_t, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(o3.novelty, o2.novelty, rtol=1e-4, atol=1e-5)
    assert split.press_novelty(raws[0]) == pytest.approx(fused.press_novelty(raws[0]), rel=1e-4, abs=1e-5)


def test_the_journal_of_a_format_3_press_has_no_router_numbers(formats):
    """score_dict (what the journal keeps of a press) leaves out the router's novelty and route
    rather than writing nulls, and keeps the posterior the decision read."""
    from vs2t_edge.runtime.press_pipeline import score_dict

    model = TactileModel.load(formats["energy"][0], threads=1)
    _, raws, ref = world_frames(SIZE)
    model.set_reference(ref)
    d = score_dict(model.score_press(raws[1]))
    assert "novelty" not in d and "untouched" not in d and set(d["log_posterior"]) == set(model.scene_model.classes)
    json.dumps(d, allow_nan=False)


def test_int8_heads_go_to_the_heads_graph(tmp_path):
    import onnx

    m = _write(tmp_path / "b", "gaussian", True, heads="int8", heads_in_press_graph=False)
    assert m["format_version"] == 3 and m["graphs"]["heads"]["precision"] == "int8"
    assert "int8" in m["graphs"]["heads"]["fused"]["heads"] and "heads" not in m["graphs"]["trunk"]["fused"]
    press = onnx.load(str(tmp_path / "b" / "trunk.onnx")).graph.node
    heads = onnx.load(str(tmp_path / "b" / "heads.onnx")).graph.node
    assert not any(n.op_type in ("MatMulInteger", "Gemm") for n in press if n.name.startswith("press_tail/"))
    assert sum(n.op_type == "MatMulInteger" for n in heads) == 4 and not any(n.op_type == "Gemm" for n in heads)
    TactileModel.load(tmp_path / "b", threads=1)


def test_format_3_without_a_scene_model_is_refused(formats, tmp_path):
    """Format 3 is a scene decision's press graph: without decision.npz nothing would read scene_z
    and nothing would decide, so the manifest is refused in words."""
    b = _copy(formats["energy"][0], tmp_path)
    (b / "decision.npz").unlink()

    def drop(m):
        del m["decision"], m["files"]["decision.npz"]

    _reseal(b, drop)
    with pytest.raises(rb.BundleError, match=r"format version 3 is a scene decision's press graph.*no scene model"):
        TactileModel.load(b)


def test_format_3_press_graph_with_heads_is_refused(formats, tmp_path):
    """A format-3 manifest over a press graph that still computes the heads (format 2's graph,
    re-declared and re-sealed): the outputs are not what format 3's press graph gives."""
    from vs2t_edge.export.export import graph_io

    split_dir, fused_dir = formats["energy"]
    b = _copy(split_dir, tmp_path)
    (b / "trunk.onnx").write_bytes((fused_dir / "trunk.onnx").read_bytes())
    _reseal(b, lambda m: m["graphs"]["trunk"].__setitem__("outputs", graph_io(b / "trunk.onnx")["outputs"]))
    with pytest.raises(rb.BundleError, match=r"trunk\.onnx: outputs \[.*logits_t.*\].*need \['feature', 'scene_z'\]"):
        TactileModel.load(b)


def test_format_2_still_written_on_request_and_without_a_scene_model(tmp_path):
    m = _write(tmp_path / "b", "energy", True, scene=False, heads_in_press_graph=False)
    assert m["format_version"] == 2 and "heads" not in m["graphs"]


@pytest.mark.parametrize("bad", ["feature", "scene_z"])
def test_non_finite_format_3_press_output_is_a_frame_error(formats, bad):
    model = poison_output(TactileModel.load(formats["gaussian"][0], threads=1), bad)
    _, raws, ref = world_frames(SIZE)
    model.set_reference(ref)
    with pytest.raises(FrameError, match="model output not usable"):
        model.score_press(raws[0])


def test_heads_graph_of_another_feature_width_is_refused_in_words(formats, tmp_path):
    """heads.onnx re-exported for 17-d features beside a 16-d trunk (manifest re-declared, re-sealed):
    refused naming the file, before onnxruntime's own error at the probe could surface."""
    import torch

    from vs2t_edge.export.export import export_onnx, graph_io

    class Wide(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.t, self.u, self.z = torch.nn.Linear(17, 3), torch.nn.Linear(17, 2), torch.nn.Linear(17, 16)

        def forward(self, f):
            return self.t(f), self.u(f), self.z(f)

    b = _copy(formats["gaussian"][0], tmp_path)
    export_onnx(Wide().eval(), torch.zeros(1, 17), b / "heads.onnx", "feature", ["logits_t", "logits_u", "router_z"], 20)
    _reseal(b, lambda m: m["graphs"]["heads"].update(graph_io(b / "heads.onnx")))
    with pytest.raises(rb.BundleError, match=r"heads\.onnx: inputs .*the heads take one \(N, 16\) feature"):
        TactileModel.load(b)


def _world_bundle(out, heads_in_press_graph: bool) -> dict:
    """A trained-style fp32 bundle over the tiny world's fabrics (its manifest records which
    presses trained it, as int8-sensitivity needs), with a scene model."""
    import torch

    from test_bundle_fixtures import tiny_modules, tiny_world

    from vs2t_edge.export.export import write_bundle
    from vs2t_edge.runtime import novelty as nv
    from vs2t_edge.runtime.preprocess import TactilePreprocess
    from vs2t_edge.runtime.scene_model import SceneModel

    touched, untouched = ("f00", "f01", "f02"), ("f03", "f04")
    trunk, cls_t, cls_u = tiny_modules(0)
    x, _, _ = world_frames(SIZE)
    with torch.no_grad():
        f = trunk(torch.from_numpy(x[:40])).numpy()
    fu = np.random.default_rng(0).standard_normal((20, f.shape[1])) * f.std(0) + f.mean(0)
    sm = SceneModel.fit(f, np.arange(40) % 3, list(touched), fu, np.arange(20) % 2, list(untouched), k=6)
    part = {fid: {"train": [0, 1, 2, 3, 4, 5], "val": [6, 7], "test": [8], "unused": []} for fid in touched}
    return write_bundle(out, trunk=trunk, cls_t=cls_t, cls_u=cls_u, router=nv.fit_router("gaussian", f, keep_covariance=False),
                        touched=touched, untouched=untouched, preprocess=TactilePreprocess(size=SIZE), beta=0.0,
                        calibration=x[:40], trunk_arch="tiny-test", validation=x[60:], touched_heldout=x[40:60],
                        scene_model=sm.to_params(), heads_in_press_graph=heads_in_press_graph,
                        provenance={"data": {"dataset": str(tiny_world()), "touched_presses": part, "validation": []}})


def test_int8_sensitivity_reads_format_3_heads_and_refuses_format_2_in_words(tmp_path):
    """`vs2t-edge int8-sensitivity` quantises the trunk graph alone and reads the logits from
    heads.onnx: a format-3 bundle's heads graph also gives the router's output, fetched by name; a
    format-2 bundle has no heads graph and is refused saying which formats it reads."""
    from vs2t_edge.export.sensitivity_cli import scan

    for fmt in (3, 2):
        assert _world_bundle(tmp_path / f"b{fmt}", heads_in_press_graph=fmt == 2)["format_version"] == fmt
    res = scan(tmp_path / "b3", calibration_frames=6, validation_presses=2, ops=["Conv"], top=1)
    assert res["rows"] and 0.0 <= res["fp32"]["cls_t_agreement"] <= 1.0
    with pytest.raises(ValueError, match=r"heads are inside its press graph \(format 2\).*format 3.*--two-graphs"):
        scan(tmp_path / "b2", calibration_frames=6, validation_presses=2, ops=["Conv"], top=1)


def test_int8_sensitivity_out_file_is_what_export_reads(tmp_path, capsys):
    """`vs2t-edge int8-sensitivity B --out FILE` writes the scan as JSON and `export
    --int8-float-nodes @FILE` reads its recommended nodes; the scan says which camera JPEG it read
    the frames through (0: lossless). The scan's quantiser once shadowed that quality, so the JSON
    write failed after the whole scan (TypeError) and the documented @FILE route never worked."""
    import json

    from vs2t_edge.cli import main
    from vs2t_edge.export.cli import parse_float_nodes

    _world_bundle(tmp_path / "b3", heads_in_press_graph=False)
    out = tmp_path / "scan.json"
    assert main(["int8-sensitivity", str(tmp_path / "b3"), "--calibration-frames", "6", "--validation-presses", "2",
                 "--ops", "Conv", "--top", "1", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["camera_jpeg"] == 0 and res["recommended"]
    assert parse_float_nodes(f"@{out}") == res["recommended"]

"""A bundle whose tactile feature is the shading_markers descriptor (runtime/tactile_descriptor.py),
written by export's write_bundle: no trunk graph, loads in TactileModel as strictly as a trunk
bundle (hashes, seal, probe - the descriptor function included), refuses tampering, and scores a
press through heads, router and the decision exactly as a CNN feature."""

from __future__ import annotations

import functools
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from test_bundle_fixtures import TOUCHED, UNTOUCHED, tiny_world
from vs2t_edge.runtime import bundle as rb
from vs2t_edge.runtime import tactile_descriptor as td
from vs2t_edge.runtime.inference import BundleError, TactileModel


@functools.lru_cache(maxsize=1)
def world_descriptors():
    """(raw descriptors (N, 240), fabric index per press, frames, references) of the tiny world."""
    from vs2t_edge.runtime.dataset import load_dataset

    ds = load_dataset(tiny_world())
    xs, ys, frames, refs = [], [], [], []
    for k, fab in enumerate(ds.fabrics[:5]):
        ref = fab.load_reference()
        prepared = td.prepare_reference(ref)
        for i in range(len(fab.presses)):
            f = fab.load_press(i)
            xs.append(td.shading_markers(f, prepared))
            ys.append(k)
            frames.append(f)
            refs.append(ref)
    return np.stack(xs), np.array(ys), frames, refs


def make_descriptor_bundle(out: Path, router: str = "gaussian") -> dict:
    import torch
    from torch import nn

    from vs2t_edge.export.descriptor import Descriptor
    from vs2t_edge.export.export import write_bundle
    from vs2t_edge.runtime import novelty as nv

    x, y, frames, refs = world_descriptors()
    touched_rows = np.flatnonzero(y < 3)
    mean, std = x[touched_rows].mean(0), x[touched_rows].std(0) + 1e-3
    z = (x - mean) / std
    torch.manual_seed(0)
    cls_t = nn.Sequential(nn.Linear(240, 16), nn.LeakyReLU(0.2), nn.Linear(16, len(TOUCHED))).eval()
    cls_u = nn.Sequential(nn.Linear(240, 16), nn.LeakyReLU(0.2), nn.Linear(16, len(UNTOUCHED))).eval()
    if router == "discriminant":  # the touched fabrics' own classes: fabric k is TOUCHED[k]
        router = nv.fit_router(router, z[touched_rows], touched_labels=y[touched_rows])
    else:
        router = nv.fit_router(router, z[touched_rows], keep_covariance=False)
    beta = float(np.quantile(router.novelty(z[touched_rows]), 0.9))
    probe = touched_rows[0]
    return write_bundle(out, trunk=None, cls_t=cls_t, cls_u=cls_u, router=router, touched=TOUCHED,
                        untouched=UNTOUCHED, preprocess=None, beta=beta, calibration=x[touched_rows[::2]],
                        touched_heldout=x[touched_rows[1::2]], validation=x[y == 3], threads=1,
                        descriptor=Descriptor("shading_markers", mean, std, np.stack([refs[probe], frames[probe]])))


@functools.lru_cache(maxsize=1)
def shared_descriptor_bundle() -> Path:
    out = Path(tempfile.mkdtemp(prefix="vs2t_dbundle_")) / "bundle"
    make_descriptor_bundle(out)
    return out


@pytest.fixture()
def bundle_copy(tmp_path):
    dst = tmp_path / "b"
    shutil.copytree(shared_descriptor_bundle(), dst)
    return dst


def _edit(b, fn):
    m = json.loads((b / "manifest.json").read_text())
    fn(m)
    (b / "manifest.json").write_text(json.dumps(rb.seal_manifest(m)))


def test_descriptor_bundle_loads_verifies_and_has_no_trunk_graph():
    model = TactileModel.load(shared_descriptor_bundle(), threads=1)
    m = model.manifest
    assert m["trunk"] == {**m["trunk"], "kind": "descriptor", "name": "shading_markers", "dim": 240}
    assert m["feature_dim"] == 240 and set(m["graphs"]) == {"heads"}
    assert set(m["files"]) == {"heads.onnx", "descriptor.npz", "router.npz", "probe_input.npy", "probe_frames.npy",
                               "probe_expected.npz"}
    assert set(model.probe_errors) == {"descriptor", "feature", "logits_t", "logits_u", "novelty"}
    assert max(model.probe_errors.values()) <= 1e-4


def test_descriptor_bundle_scores_a_press_like_a_trunk_bundle():
    """descriptor -> standardise -> heads.onnx -> router -> soft-gated posterior over all classes."""
    model = TactileModel.load(shared_descriptor_bundle(), threads=1)
    x, y, frames, refs = world_descriptors()
    for i in (0, int(np.flatnonzero(y == 4)[0])):
        model.set_reference(refs[i])
        s = model.score_press(frames[i])
        assert set(s.log_posterior) == set(TOUCHED + UNTOUCHED)
        assert np.isclose(np.logaddexp.reduce(list(s.log_posterior.values())), 0.0, atol=1e-6)
        assert {"preprocess_ms", "heads_ms", "router_ms"} <= set(model.last_timing)
        out = model.forward(x[i:i + 1])
        assert np.isclose(s.novelty, float(out.novelty[0]), rtol=1e-5)
        assert s.untouched == (s.novelty > model.beta)


def test_a_descriptor_bundle_with_the_discriminant_router_writes_loads_and_scores(tmp_path):
    """What wins on a real GelSight (docs/realism.md) as the cell runs it: the shading_markers
    descriptor with the discriminant router. router.npz holds its projection, centre and class
    means; the cell reads it back, checks the probe's novelty, and scores a press with the router's
    own rule on the standardised descriptor. A router.npz fitted on other classes is refused."""
    from vs2t_edge.runtime import novelty as nv

    m = make_descriptor_bundle(tmp_path / "b", router="discriminant")
    assert m["router"] == {"name": "discriminant", "file": "router.npz"}
    with np.load(tmp_path / "b" / "router.npz") as z:
        assert {"centre", "projection", "class_means"} <= set(z.files)
        assert z["projection"].shape == (240, len(TOUCHED) - 1) and z["class_means"].shape == (3, 2)
    model = TactileModel.load(tmp_path / "b", threads=1)
    assert isinstance(model.router, nv.DiscriminantRouter)
    assert model.probe_errors["novelty"] <= 1e-4
    x, y, frames, refs = world_descriptors()
    for i in (1, int(np.flatnonzero(y == 4)[0])):
        model.set_reference(refs[i])
        s = model.score_press(frames[i])
        f = model.descriptor.standardise(x[i:i + 1]).astype(np.float64)
        assert s.novelty == pytest.approx(float(model.router.novelty(f)[0]), rel=1e-5)
        assert np.isclose(np.logaddexp.reduce(list(s.log_posterior.values())), 0.0, atol=1e-6)
    # fitted on two classes while the manifest names three touched ones: refused, and said why
    z = (x - x.mean(0)) / (x.std(0) + 1e-3)
    two = nv.fit_router("discriminant", z[y < 2], touched_labels=y[y < 2])
    np.savez(tmp_path / "b" / "router.npz", **{k: np.asarray(v) for k, v in two.to_params().items()})
    _edit(tmp_path / "b", lambda man: man["files"].update({"router.npz": rb.sha256_file(tmp_path / "b" / "router.npz")}))
    with pytest.raises(BundleError, match="models 2 touched classes, the manifest's classes.touched names 3"):
        TactileModel.load(tmp_path / "b", threads=1)


def test_missing_reference_is_a_frame_error():
    from vs2t_edge.runtime.preprocess import FrameError

    model = TactileModel.load(shared_descriptor_bundle(), threads=1)
    _, _, frames, _ = world_descriptors()
    with pytest.raises(FrameError):
        model.score_press(frames[0])


def test_changed_standardisation_is_refused_by_hash(bundle_copy):
    np.savez(bundle_copy / "descriptor.npz", mean=np.zeros(240, np.float32), std=np.ones(240, np.float32))
    with pytest.raises(BundleError, match="descriptor.npz: sha256"):
        TactileModel.load(bundle_copy, threads=1)


@pytest.mark.parametrize("edit, says", [
    (lambda m: m["trunk"].__setitem__("name", "shading"), "trunk.name"),
    (lambda m: m["trunk"].__setitem__("kind", "cnn"), "trunk.kind"),
    (lambda m: m["trunk"].__setitem__("dim", 144), "trunk.dim"),
    (lambda m: m["probe"].pop("frames"), "probe.frames"),
])
def test_a_manifest_that_does_not_describe_the_descriptor_is_refused(bundle_copy, edit, says):
    _edit(bundle_copy, edit)
    with pytest.raises(BundleError, match=says.replace(".", r"\.")):
        TactileModel.load(bundle_copy, threads=1)


def test_a_descriptor_that_computes_otherwise_fails_the_probe(bundle_copy):
    """Other probe frames (rehashed and resealed, as a broken exporter would write them): the cell's
    descriptor of them is not the recorded probe input."""
    frames = np.load(bundle_copy / "probe_frames.npy")
    np.save(bundle_copy / "probe_frames.npy", np.stack([frames[0], np.ascontiguousarray(frames[1][:, ::-1])]))
    _edit(bundle_copy, lambda m: m["files"].__setitem__("probe_frames.npy", rb.sha256_file(bundle_copy / "probe_frames.npy")))
    with pytest.raises(BundleError, match="probe check failed: the shading_markers descriptor"):
        TactileModel.load(bundle_copy, threads=1)


def test_verify_bundle_cli_names_the_descriptor(capsys):
    from vs2t_edge.cli import main

    assert main(["verify-bundle", str(shared_descriptor_bundle()), "--threads", "1"]) == 0
    assert "shading_markers descriptor (no trunk graph), 240-d" in capsys.readouterr().out


def test_bench_refuses_a_descriptor_bundle_by_name(capsys):
    """The bench measures ONNX trunks; a descriptor bundle is refused in words, not a traceback."""
    from vs2t_edge.cli import main

    b = shared_descriptor_bundle()
    assert main(["bench", str(b), "--no-accuracy"]) == 2
    err = capsys.readouterr().err
    assert str(b) in err and "descriptor bundle" in err


@pytest.mark.slow
def test_train_with_the_descriptor_then_export_gives_a_bundle_that_scores(tmp_path):
    """`train --tactile-feature shading_markers` on the tiny world, then `export` of the run: a
    descriptor bundle (no trunk graph) that the cell verifies and that scores an untouched press."""
    from vs2t_edge.export.from_run import export_run
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.train.artifacts import load_run_artifacts
    from vs2t_edge.train.run import train

    world = tiny_world()
    m = train(world, tmp_path / "run", profile="tiny", figures=False, tactile_feature="shading_markers",
              ft_attributes=1.0)
    assert m["profile"]["tactile_feature"] == "shading_markers"
    # no tactile tail is fine-tuned for a descriptor: the attribute task asked for is recorded as off
    assert m["profile"]["ft_attributes"] == 0.0 and "to say their attributes" not in (tmp_path / "run" / "report.md").read_text()
    art = load_run_artifacts(tmp_path / "run")
    assert art.tactile_feature == "shading_markers" and art.trunk_state == {} and art.feature_dim == 240
    man = export_run(tmp_path / "run", tmp_path / "bundle", calibration_frames=16, threads=1)
    assert man["trunk"]["name"] == "shading_markers" and "trunk.onnx" not in man["files"]
    assert set(man["provenance"]["data"]["calibration_fabrics"]) <= set(art.touched)
    model = TactileModel.load(tmp_path / "bundle", threads=1)
    assert list(model.untouched) == list(art.untouched) and model.beta == pytest.approx(art.beta)
    fab = load_dataset(world).by_id(art.untouched[0])
    model.set_reference(fab.load_reference())
    s = model.score_press(fab.load_press(0))
    # the scene model also knows the run's validation fabrics, only to refuse them
    assert model.scene_model.known_only == tuple(art.validation)
    assert set(s.log_posterior) == set(model.classes) | set(art.validation) and np.isfinite(s.novelty)
    assert all(np.isfinite(v) for v in s.log_posterior.values())
    # the run as if trained with --camera-jpeg 90: its descriptors are read through that JPEG at
    # export too (the gating is fitted on them), and the manifest says so
    from dataclasses import replace

    from vs2t_edge.train.artifacts import save_run_artifacts

    save_run_artifacts(tmp_path / "run90", replace(art, camera_jpeg=90))
    man90 = export_run(tmp_path / "run90", tmp_path / "bundle90", calibration_frames=16, threads=1)
    assert man90["camera_jpeg"] == 90 and "camera_jpeg" not in man
    assert man90["gating"]["scale"] != man["gating"]["scale"]
    assert TactileModel.load(tmp_path / "bundle90", threads=1).camera_jpeg == 90
    from vs2t_edge.export.export import ExportError

    with pytest.raises(ExportError, match="apply to a trunk"):  # not silently a trunk export
        export_run(tmp_path / "run", tmp_path / "b2", router="gaussian", threads=1)
    for asked in ({"heads_precision": "int8"}, {"fuse": False}, {"heads_in_press_graph": True}):
        with pytest.raises(ExportError, match="apply to a trunk"):  # were silently left out of the bundle
            export_run(tmp_path / "run", tmp_path / "b2", threads=1, **asked)
    from vs2t_edge.cli import main

    assert main(["export", str(tmp_path / "run"), "--out", str(tmp_path / "b3"), "--calibration-frames", "8"]) == 0
    assert main(["verify-bundle", str(tmp_path / "b3"), "--threads", "1"]) == 0

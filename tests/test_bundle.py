"""runtime.bundle refuses, naming which, a bundle whose hashes, shapes, opset, version or probe
do not match; a good bundle loads, warms up and passes its probe."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from test_bundle_fixtures import SIZE, TOUCHED, UNTOUCHED, shared_bundle
from vs2t_edge.runtime import bundle as rb
from vs2t_edge.runtime.inference import TactileModel


@pytest.fixture()
def bundle_copy(tmp_path):
    dst = tmp_path / "b"
    shutil.copytree(shared_bundle("fp32"), dst)
    return dst


def _edit(b, fn, seal=True):
    """Change the manifest as an exporter would have written it (re-sealed), or by hand (seal=False)."""
    m = json.loads((b / "manifest.json").read_text())
    fn(m)
    (b / "manifest.json").write_text(json.dumps(rb.seal_manifest(m) if seal else m))


def _rehash(b, name):
    _edit(b, lambda m: m["files"].__setitem__(name, rb.sha256_file(b / name)))


def test_good_bundle_loads_and_passes_probe():
    model = TactileModel.load(shared_bundle("fp32"), threads=1)
    assert model.touched == TOUCHED and model.untouched == UNTOUCHED
    assert model.manifest["format_version"] == rb.FORMAT_VERSION
    # format 2: one press graph; the probe covers its router_z and checks it against router.npz
    assert set(model.probe_errors) == {"feature", "logits_t", "logits_u", "novelty", "router_z", "novelty_vs_router_file"}
    assert max(model.probe_errors.values()) <= 1e-4
    m = model.manifest
    assert m["graphs"]["trunk"]["opset"] >= 17 and m["graphs"]["trunk"]["inputs"]["image"] == [None, 3, SIZE, SIZE]
    assert set(m["files"]) == {"trunk.onnx", "router.npz", "probe_input.npy", "probe_expected.npz"}
    for key in ("time_utc", "git_commit", "versions"):
        assert key in m["provenance"]


def test_opset_read_from_protobuf_matches_onnx():
    import onnx

    p = shared_bundle("fp32") / "trunk.onnx"
    want = {(o.domain if o.domain != "ai.onnx" else ""): o.version for o in onnx.load(str(p)).opset_import}
    assert rb.read_onnx_opsets(p) == want


def test_changed_graph_is_refused_by_hash(bundle_copy):
    with open(bundle_copy / "trunk.onnx", "ab") as f:
        f.write(b"\0")
    with pytest.raises(rb.BundleError, match=r"trunk\.onnx: sha256"):
        TactileModel.load(bundle_copy)


def test_missing_file_is_named(bundle_copy):
    (bundle_copy / "router.npz").unlink()
    with pytest.raises(rb.BundleError, match=r"router\.npz is missing"):
        TactileModel.load(bundle_copy)


@pytest.mark.parametrize("what, edit", [
    ("beta", lambda m: m.__setitem__("beta", m["beta"] * 0.5)),
    ("class list", lambda m: m["classes"]["untouched"].reverse()),
    ("preprocessing", lambda m: m["preprocess"]["std"].__setitem__(0, m["preprocess"]["std"][0] * 2)),
])
def test_manifest_edited_by_hand_is_refused(bundle_copy, what, edit):
    _edit(bundle_copy, edit, seal=False)
    with pytest.raises(rb.BundleError, match=r"manifest\.json was changed after export"):
        TactileModel.load(bundle_copy)


def test_manifest_byte_flip_in_a_number_is_refused(bundle_copy):
    text = (bundle_copy / "manifest.json").read_text()
    i = text.index('"beta": ') + len('"beta": ')
    digit = next(j for j in range(i, i + 30) if text[j].isdigit() and text[j] != "0")
    (bundle_copy / "manifest.json").write_text(text[:digit] + str((int(text[digit]) % 9) + 1) + text[digit + 1:])
    with pytest.raises(rb.BundleError, match=r"manifest\.json was changed after export"):
        rb.load_bundle(bundle_copy)


def test_unsealed_manifest_is_refused(bundle_copy):
    _edit(bundle_copy, lambda m: m.pop(rb.SEAL_KEY), seal=False)
    with pytest.raises(rb.BundleError, match="carries no 'manifest_sha256'"):
        rb.load_bundle(bundle_copy)


def test_seal_ignores_layout_but_not_values():
    m = {"b": [1, 2.5, float("inf")], "a": {"z": "\u00e9", "y": None}}
    shuffled = json.loads(json.dumps({"a": {"y": None, "z": "\u00e9"}, "b": [1, 2.5, float("inf")]}, indent=3))
    assert rb.manifest_digest(m) == rb.manifest_digest(shuffled)
    assert rb.manifest_digest(rb.seal_manifest(m)) == rb.manifest_digest(m)  # the seal is not part of itself
    assert rb.manifest_digest(m) != rb.manifest_digest({**m, "b": [1, 2.5000001, float("inf")]})
    assert rb.manifest_digest(m) != rb.manifest_digest({**m, "b": [1.0, 2.5, float("inf")]})  # 1 vs 1.0 is a change


def test_format_version_mismatch_is_refused(bundle_copy):
    _edit(bundle_copy, lambda m: m.__setitem__("format_version", 4))
    with pytest.raises(rb.BundleError, match="format version 4"):
        TactileModel.load(bundle_copy)


def test_opset_mismatch_is_refused(bundle_copy):
    real = rb.read_onnx_opsets(bundle_copy / "trunk.onnx")[""]
    _edit(bundle_copy, lambda m: m["graphs"]["trunk"].__setitem__("opset", real + 1))
    with pytest.raises(rb.BundleError, match=rf"trunk\.onnx: opset {real}, the manifest says {real + 1}"):
        TactileModel.load(bundle_copy)


def _stamp_opset(b, version):
    """trunk.onnx re-stamped with another ai.onnx opset, hash and manifest updated to match (as an
    exporter of that opset would have written it): only the opset range can refuse it."""
    import onnx

    model = onnx.load(str(b / "trunk.onnx"))
    for imp in model.opset_import:
        if imp.domain in ("", "ai.onnx"):
            imp.version = version
    onnx.save(model, str(b / "trunk.onnx"))

    def declare(m):
        m["graphs"]["trunk"]["opset"] = version
        m["files"]["trunk.onnx"] = rb.sha256_file(b / "trunk.onnx")
    _edit(b, declare)


def test_export_opset_is_within_what_the_installed_onnxruntime_runs():
    """MAX_OPSET comes from the installed onnxruntime's kernel registry (1.32: 28), the exporter's
    opset (the newest torch's TorchScript exporter writes) is inside the accepted range, and the
    documented floor (onnxruntime 1.17, the oldest pyproject allows, implements 20) covers it."""
    import onnxruntime

    export = pytest.importorskip("vs2t_edge.export.export")
    assert rb.MAX_OPSET == rb.onnxruntime_max_opset() >= rb.ORT_FLOOR_OPSET
    if tuple(int(v) for v in onnxruntime.__version__.split(".")[:2]) >= (1, 32):
        assert rb.MAX_OPSET >= 28
    assert rb.MIN_OPSET <= export.OPSET <= rb.ORT_FLOOR_OPSET <= rb.MAX_OPSET
    assert rb.read_onnx_opsets(shared_bundle("fp32") / "trunk.onnx")[""] == export.OPSET


def test_opset_newer_than_onnxruntime_is_refused_with_the_reason(bundle_copy):
    _stamp_opset(bundle_copy, rb.MAX_OPSET + 1)
    with pytest.raises(rb.BundleError, match=rf"trunk\.onnx: opset {rb.MAX_OPSET + 1} is newer than the installed "
                                             rf"onnxruntime .* implements \(up to {rb.MAX_OPSET}\); upgrade"):
        TactileModel.load(bundle_copy)


def test_opset_older_than_accepted_is_refused_with_the_reason(bundle_copy):
    _stamp_opset(bundle_copy, rb.MIN_OPSET - 1)
    with pytest.raises(rb.BundleError, match=rf"trunk\.onnx: opset {rb.MIN_OPSET - 1} is older than this runtime "
                                             r"accepts .*re-export"):
        TactileModel.load(bundle_copy)


def test_committed_opset_17_bundle_still_loads():
    """tests/replays/bundle was exported at opset 17, before the exporter moved to 20; it is not
    re-exported (replay outcomes depend on it) and must keep loading."""
    from pathlib import Path

    b = Path(__file__).parent / "replays" / "bundle"
    assert rb.read_onnx_opsets(b / "trunk.onnx")[""] == 17
    model = TactileModel.load(b, threads=1)
    assert max(model.probe_errors.values()) <= 1e-3


def test_shape_mismatch_is_refused(bundle_copy):
    _edit(bundle_copy, lambda m: m["graphs"]["trunk"]["outputs"].__setitem__("feature", [None, 99]))
    with pytest.raises(rb.BundleError, match=r"trunk\.onnx: output 'feature' has shape \[None, 16\]"):
        TactileModel.load(bundle_copy)


def test_class_list_that_does_not_fit_the_heads_is_refused(bundle_copy):
    _edit(bundle_copy, lambda m: m["classes"]["touched"].append("extra"))
    with pytest.raises(rb.BundleError, match=r"logits_t"):
        TactileModel.load(bundle_copy)


def test_preprocessing_size_that_does_not_fit_the_trunk_is_refused(bundle_copy):
    _edit(bundle_copy, lambda m: m["preprocess"].__setitem__("size", SIZE * 2))
    with pytest.raises(rb.BundleError, match="probe_input|preprocessing"):
        TactileModel.load(bundle_copy)


def test_wrong_probe_expectation_is_refused(bundle_copy):
    z = dict(np.load(bundle_copy / "probe_expected.npz"))
    z["logits_u"] = z["logits_u"] + 0.5
    np.savez(bundle_copy / "probe_expected.npz", **z)
    _rehash(bundle_copy, "probe_expected.npz")
    with pytest.raises(rb.BundleError, match="probe check failed: 'logits_u'"):
        TactileModel.load(bundle_copy)


def test_router_of_another_dimension_is_refused(bundle_copy):
    from vs2t_edge.runtime import novelty as nv

    r = nv.fit_router("gaussian", np.random.default_rng(0).normal(size=(40, 8)))
    np.savez(bundle_copy / "router.npz", **r.to_params())
    _rehash(bundle_copy, "router.npz")
    with pytest.raises(rb.BundleError, match=r"router fitted on 8-d features, feature_dim is 16"):
        TactileModel.load(bundle_copy)


def test_not_a_bundle(tmp_path):
    with pytest.raises(rb.BundleError, match="no manifest.json"):
        TactileModel.load(tmp_path)
    with pytest.raises(rb.BundleError, match="not a folder"):
        TactileModel.load(tmp_path / "nope")


def test_not_a_bundle_says_what_the_folder_is_and_what_to_do(tmp_path, capsys):
    """A training run or a dataset given as a bundle (the usual mix-ups) is named, with the command
    that makes a bundle of it."""
    from vs2t_edge.cli import main

    run, ds = tmp_path / "run", tmp_path / "ds"
    run.mkdir(), ds.mkdir()
    (run / "metrics.json").write_text("{}"), (run / "config.yaml").write_text("{}")
    (ds / "dataset.yaml").write_text("{}")
    with pytest.raises(rb.BundleError, match=r"training run: export it first, `vs2t-edge export "):
        TactileModel.load(run)
    with pytest.raises(rb.BundleError, match=r"it is a dataset: train on it"):
        TactileModel.load(ds)
    with pytest.raises(rb.BundleError, match=r"a bundle is the folder `vs2t-edge export RUN --out BUNDLE` writes"):
        TactileModel.load(tmp_path)
    assert main(["verify-bundle", str(run)]) == 2
    assert "not a bundle (no manifest.json): it is a training run" in capsys.readouterr().err


def test_verify_bundle_cli(bundle_copy, capsys):
    from vs2t_edge.cli import main

    assert main(["verify-bundle", str(bundle_copy)]) == 0
    assert "ok" in capsys.readouterr().out
    with open(bundle_copy / "trunk.onnx", "ab") as f:
        f.write(b"\0")
    assert main(["verify-bundle", str(bundle_copy)]) == 1
    assert "trunk.onnx: sha256" in capsys.readouterr().err


def test_verify_bundle_on_what_is_not_a_bundle_is_bad_input(tmp_path, capsys):
    """Exit 1 is a bundle that fails its check; a folder without a manifest is no bundle at all:
    bad input, exit 2, as `replay` on a folder that is no replay file (README's exit codes)."""
    from vs2t_edge.cli import main

    assert main(["verify-bundle", str(tmp_path)]) == 2
    assert "not a bundle (no manifest.json)" in capsys.readouterr().err
    assert main(["verify-bundle", str(tmp_path / "nope")]) == 2
    (tmp_path / "manifest.json").write_text("{")  # a bundle, damaged: its check fails
    assert main(["verify-bundle", str(tmp_path)]) == 1
    assert "REFUSED" in capsys.readouterr().err

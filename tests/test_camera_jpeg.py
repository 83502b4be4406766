"""Training on what the camera hands (train --camera-jpeg Q): the one camera function of the
runtime, the feature cache read through it and keyed by it, export reading the run's frames the
same way and recording ``camera_jpeg`` in the manifest, and the bench scoring a bundle on its own
camera's frames by default."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import cv2
import numpy as np
import pytest

pytest.importorskip("torch")

from test_bundle_fixtures import shared_bundle, tiny_world, world_frames  # noqa: E402
from test_export import tiny_run  # noqa: F401,E402  (the module-scoped run-folder fixture)

from vs2t_edge.runtime import bundle as rb  # noqa: E402
from vs2t_edge.runtime.preprocess import (  # noqa: E402
    FrameError, TactilePreprocess, camera_press, camera_reference, check_camera_jpeg, decode_jpeg, prepare_reference,
    preprocess_tactile, through_camera_jpeg)


def test_through_camera_jpeg_is_encode_then_the_cells_decode_and_is_not_the_lossless_frame():
    _, raws, ref = world_frames()
    frame = raws[7]
    for q, scale in ((95, 1), (60, 2)):
        ok, enc = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, q])
        want = decode_jpeg(enc.tobytes(), scale)
        got = through_camera_jpeg(frame, q, scale)
        assert ok and np.array_equal(got, want)
        assert got.shape[:2] == ((frame.shape[0] + scale - 1) // scale, (frame.shape[1] + scale - 1) // scale)
    assert np.abs(through_camera_jpeg(frame, 95).astype(int) - frame).max() > 0  # JPEG is lossy even at q95
    # the network input through the camera: what the cell computes from the decoded frames
    spec = TactilePreprocess(size=32, reduce=2)
    x = camera_press(frame, camera_reference(ref, spec, 90), spec, 90)
    cell = preprocess_tactile(through_camera_jpeg(frame, 90, 2), prepare_reference(through_camera_jpeg(ref, 90, 2),
                                                                                   spec, 2), spec, 2)
    assert np.array_equal(x, cell)
    assert not np.allclose(x, camera_press(frame, camera_reference(ref, spec, 0), spec, 0), atol=1e-3)


def test_a_bad_quality_or_frame_is_refused_by_name():
    _, raws, _ = world_frames()
    for bad in (101, -1, 9.5, True, "95"):
        with pytest.raises(ValueError, match="camera_jpeg"):
            check_camera_jpeg(bad)
    with pytest.raises(ValueError, match="JPEG quality"):
        through_camera_jpeg(raws[0], 0)
    with pytest.raises(FrameError, match="f03 press 4"):
        through_camera_jpeg(np.zeros((48, 64, 3), np.uint8), 90, name="f03 press 4")


def test_the_feature_cache_reads_through_the_camera_and_is_keyed_by_its_quality(tmp_path):
    """extract_cache with camera_jpeg: different stems from the lossless ones, equal to the trunk's
    stem of the camera's frames; the key differs, so neither cache is taken for the other."""
    import torch

    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.train import features as ft
    from vs2t_edge.train.run import PROFILES, get_cache
    from vs2t_edge.train.trunks import build_trunk

    world = tiny_world()
    trunk = build_trunk("tiny", pretrained=False).eval()
    lossless = get_cache(world, replace(PROFILES["tiny"], max_presses=5), tmp_path / "a", trunk)
    prof = replace(PROFILES["tiny"], max_presses=5, camera_jpeg=80)
    jpeg = get_cache(world, prof, tmp_path / "b", trunk)
    assert "camera_jpeg" not in lossless.meta and jpeg.meta == {**lossless.meta, "camera_jpeg": 80}
    assert ft.StemCache.load(tmp_path / "b" / "stem_cache.npz", lossless.meta) is None
    assert ft.StemCache.load(tmp_path / "a" / "stem_cache.npz", jpeg.meta) is None
    assert np.array_equal(jpeg.fabric, lossless.fabric)
    assert np.abs(jpeg.stem_t.astype(np.float32) - lossless.stem_t.astype(np.float32)).max() > 1e-2
    np.testing.assert_array_equal(jpeg.x_v, lossless.x_v)  # the visual camera's crops are left as they are
    fab = load_dataset(world).fabrics[0]
    spec = TactilePreprocess(size=64)
    x = camera_press(fab.load_press(0), camera_reference(fab.load_reference(), spec, 80), spec, 80)
    with torch.no_grad():
        want = trunk.stem(torch.from_numpy(x[None])).half().float().numpy()[0]
    np.testing.assert_allclose(jpeg.stem_t[0].astype(np.float32), want, rtol=3e-3, atol=2e-5)
    # the descriptor path reads through the camera too, and keys its cache by it
    d0 = ft.descriptor_table(world, "shading_markers", 2, progress=False)
    d80 = ft.descriptor_table(world, "shading_markers", 2, progress=False, camera_jpeg=80)
    assert d0.shape == d80.shape and not np.allclose(d0, d80)


def test_train_refuses_a_bad_camera_jpeg_naming_the_option(tmp_path, capsys):
    from vs2t_edge.cli import main

    for bad in ("101", "-5"):
        assert main(["train", str(tiny_world()), "--profile", "tiny", "--out", str(tmp_path / "r"),
                     "--camera-jpeg", bad]) == 2
        assert "--camera-jpeg" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


@pytest.fixture(scope="module")
def jpeg_bundle(tiny_run, tmp_path_factory):  # noqa: F811
    """The tiny run as if trained with --camera-jpeg 90, exported (fp32)."""
    from vs2t_edge.export import from_run as fr
    from vs2t_edge.train.artifacts import save_run_artifacts

    _, art = tiny_run
    run = tmp_path_factory.mktemp("run_jpeg90")
    save_run_artifacts(run, replace(art, camera_jpeg=90))
    out = run.parent / "b_jpeg90"
    return out, fr.export_run(run, out, calibration_frames=8)


def test_export_reads_the_runs_frames_through_its_camera_jpeg_and_records_it(jpeg_bundle):
    from vs2t_edge.runtime.dataset import load_dataset

    out, m = jpeg_bundle
    assert m["camera_jpeg"] == 90
    b = rb.load_bundle(out)
    assert b.camera_jpeg == 90
    # the probe is the first calibration press, read through the camera's JPEG as the run trained
    fid, idx = next(iter(m["provenance"]["data"]["calibration_presses"].items()))
    fab = load_dataset(m["provenance"]["data"]["dataset"]).by_id(fid)
    spec = b.preprocess
    want = camera_press(fab.load_press(idx[0]), camera_reference(fab.load_reference(), spec, 90), spec, 90)
    np.testing.assert_array_equal(b.probe_input[0], want)
    assert not np.allclose(b.probe_input[0], preprocess_tactile(fab.load_press(idx[0]), fab.load_reference(), spec),
                           atol=1e-3)


def test_manifest_camera_jpeg_absent_is_lossless_and_a_bad_one_is_refused_by_key(tmp_path):
    src = shared_bundle("fp32")
    assert "camera_jpeg" not in json.loads((src / rb.MANIFEST).read_text())  # lossless bundles stay as they were
    assert rb.load_bundle(src).camera_jpeg == 0
    for bad in (101, "90", True, 9.5):
        dst = tmp_path / f"b{bad!r}"
        shutil.copytree(src, dst)
        m = json.loads((dst / rb.MANIFEST).read_text())
        m["camera_jpeg"] = bad
        (dst / rb.MANIFEST).write_text(json.dumps(rb.seal_manifest(m)))
        with pytest.raises(rb.BundleError, match="camera_jpeg"):
            rb.load_bundle(dst)


def test_the_bench_scores_a_bundle_on_its_own_cameras_frames_and_pairs_two_scorings(jpeg_bundle):
    from vs2t_edge.bench import accuracy as acc
    from vs2t_edge.bench.measure import frames_said
    from vs2t_edge.bench.paired import paired, view
    from vs2t_edge.bench.report import render_pairs
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.inference import TactileModel

    out, m = jpeg_bundle
    model = TactileModel.load(out, threads=1)
    assert acc.accuracy_frames(model, 95, False)[0] == 90  # its own camera by default
    assert acc.accuracy_frames(model, 95, True)[0] == 95  # --accuracy-through-jpeg keeps working
    assert acc.accuracy_frames(model, 95, False, lossless=True)[0] is None
    assert acc.accuracy_frames(TactileModel.load(shared_bundle("fp32"), threads=1), 95, False)[0] is None
    rows = [{"name": "a", "accuracy_frames": acc.accuracy_frames(model, 95, False)[1]},
            {"name": "b", "accuracy_frames": "lossless (the dataset's PNG)"}]
    assert "camera_jpeg" in frames_said(rows, 95, False) and "b: lossless" in frames_said(rows, 95, False)
    ds = load_dataset(m["provenance"]["data"]["dataset"])
    presses = acc.eval_presses(m, ds, 2)
    own = acc.press_outputs(model, ds, presses, log=lambda s: None, jpeg_quality=90)
    lossless = acc.press_outputs(model, ds, presses, log=lambda s: None)
    assert not np.allclose(own["feature"], lossless["feature"], atol=1e-3)
    p = paired(view(model, lossless), view(model, own), n_boot=20, n_items=2)
    text = render_pairs({"pairs": [{"a": "lossless", "b": "q90", "paired": p}]})
    assert "| q90 | lossless | press acc_t |" in text


def test_calibrate_threshold_scores_a_dataset_through_the_bundles_camera_jpeg(jpeg_bundle):
    from pathlib import Path

    from vs2t_edge.runtime.calibrate import novelty_from_dataset
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.inference import TactileModel

    out, m = jpeg_bundle
    model = TactileModel.load(out, threads=1)
    ds_root = Path(m["provenance"]["data"]["dataset"])
    val = [f for f in load_dataset(ds_root).ids if f not in model.classes][:1]
    touched, _ = novelty_from_dataset(model, ds_root, val)
    fab = next(f for f in load_dataset(ds_root).fabrics if f.id in model.touched)
    model.set_reference(through_camera_jpeg(fab.load_reference(), 90))
    want = model.press_novelty(through_camera_jpeg(fab.load_press(0), 90))
    model.set_reference(fab.load_reference())
    lossless = model.press_novelty(fab.load_press(0))
    assert touched[0] == pytest.approx(want, rel=1e-6) and touched[0] != pytest.approx(lossless, rel=1e-4)

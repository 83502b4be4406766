"""Training through the camera's JPEG at the scale the cell's camera decodes at (``train
--camera-jpeg Q``, ``--camera-decode auto``, the default): the preprocessing records that scale
(``jpeg_scale``), the feature cache is keyed by it, export reads the run's frames at it and the
cell's UVC camera decodes at it. A run or bundle trained on full decodes keeps them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from vs2t_edge.runtime import bundle as rb
from vs2t_edge.runtime.preprocess import (FrameError, TactilePreprocess, camera_press, camera_reference,
                                          camera_scale, through_camera_jpeg)

pytest.importorskip("torch")

from test_bundle_fixtures import shared_bundle, tiny_world  # noqa: E402
from test_bundle import _edit, bundle_copy  # noqa: F401,E402  (a copy of the shared bundle; a sealed manifest edit)
from test_export import tiny_run  # noqa: F401,E402  (the module-scoped run-folder fixture)

TINY_HALF = 48  # px: the tiny world's 160x120 frames keep 60 px across at 1/2, 30 at 1/4


def test_jpeg_scale_is_the_float_paths_alone_and_old_manifests_stay_as_they_were():
    assert TactilePreprocess(size=128).to_dict() == TactilePreprocess(size=128, jpeg_scale=1).to_dict()
    assert "jpeg_scale" not in TactilePreprocess(size=128).to_dict()
    half = TactilePreprocess(size=128, jpeg_scale=2)
    assert half.to_dict()["jpeg_scale"] == 2 and TactilePreprocess.from_dict(half.to_dict()) == half
    assert camera_scale(half) == 2 and camera_scale(TactilePreprocess(size=128)) == 1
    assert camera_scale(TactilePreprocess(size=128, reduce=4)) == 4
    for bad in (3, 0, 2.0, True):
        with pytest.raises(ValueError, match="jpeg_scale"):
            TactilePreprocess(size=128, jpeg_scale=bad)
    for other in ({"reduce": 2}, {"inpaint_markers": True}, {"normalise_exposure": True}):
        with pytest.raises(ValueError, match="jpeg_scale = 2"):
            TactilePreprocess(size=128, jpeg_scale=2, **other)


def test_the_run_trains_at_the_scale_the_cells_camera_decodes_at_unless_told_full():
    from vs2t_edge.train.run import PROFILES, tactile_spec

    world, tiny = tiny_world(), replace(PROFILES["tiny"], size_px=TINY_HALF)
    assert tactile_spec(replace(tiny, camera_jpeg=80), world) == TactilePreprocess(size=TINY_HALF, jpeg_scale=2)
    assert tactile_spec(replace(tiny, camera_jpeg=80, camera_decode="full"), world) == TactilePreprocess(size=TINY_HALF)
    assert tactile_spec(tiny, world) == TactilePreprocess(size=TINY_HALF)  # lossless: any scale at the cell
    assert tactile_spec(replace(tiny, size_px=64, camera_jpeg=80), world) == TactilePreprocess(size=64)  # 60 < 64
    assert tactile_spec(replace(tiny, camera_jpeg=80, preprocess_reduce="2"), world) == TactilePreprocess(
        size=TINY_HALF, reduce=2)  # the reduced path decodes at its own 1/reduce
    assert tactile_spec(replace(tiny, camera_jpeg=80, tactile_feature="shading_markers"), world) == TactilePreprocess(
        size=TINY_HALF)  # a descriptor reads full frames
    with pytest.raises(ValueError, match="camera_decode 'half'"):
        tactile_spec(replace(tiny, camera_jpeg=80, camera_decode="half"), world)


def test_the_feature_cache_reads_the_jpeg_at_the_runs_scale_and_is_keyed_by_it(tmp_path):
    import torch

    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.train import features as ft
    from vs2t_edge.train.run import PROFILES, get_cache
    from vs2t_edge.train.trunks import build_trunk

    world = tiny_world()
    trunk = build_trunk("tiny", pretrained=False).eval()
    prof = replace(PROFILES["tiny"], size_px=TINY_HALF, max_presses=5, camera_jpeg=80)
    half = get_cache(world, prof, tmp_path / "half", trunk)
    full = get_cache(world, replace(prof, camera_decode="full"), tmp_path / "full", trunk)
    assert half.meta == {**full.meta, "jpeg_scale": 2} and full.meta["camera_jpeg"] == 80
    assert ft.StemCache.load(tmp_path / "full" / "stem_cache.npz", half.meta) is None  # neither taken for the other
    assert ft.StemCache.load(tmp_path / "half" / "stem_cache.npz", full.meta) is None
    fab = load_dataset(world).fabrics[0]
    spec = TactilePreprocess(size=TINY_HALF, jpeg_scale=2)
    ref = camera_reference(fab.load_reference(), spec, 80)  # at the spec's own scale by default
    x = camera_press(fab.load_press(0), ref, spec, 80)
    np.testing.assert_array_equal(x, camera_press(fab.load_press(0), camera_reference(
        fab.load_reference(), spec, 80, scale=2), spec, 80, scale=2))
    with torch.no_grad():
        want = trunk.stem(torch.from_numpy(x[None])).half().float().numpy()[0]
    np.testing.assert_allclose(half.stem_t[0].astype(np.float32), want, rtol=3e-3, atol=2e-5)
    assert np.abs(half.stem_t.astype(np.float32) - full.stem_t.astype(np.float32)).max() > 1e-2


def test_the_float_path_takes_the_half_decode_and_a_full_frame_but_refuses_an_upscale():
    """A jpeg_scale 2 bundle scores its camera's 1/2 decodes; a full frame (the simulated camera, a
    PNG replay, decode_scale full) goes through the float path as any float-path bundle's does."""
    from vs2t_edge.runtime.dataset import load_dataset

    fab = load_dataset(tiny_world()).fabrics[0]
    spec = TactilePreprocess(size=TINY_HALF, jpeg_scale=2)
    ref = camera_reference(fab.load_reference(), spec, 90)
    assert camera_press(fab.load_press(1), ref, spec, 90).shape == (3, TINY_HALF, TINY_HALF)
    whole = camera_press(fab.load_press(1), camera_reference(fab.load_reference(), spec, 90, scale=1), spec, 90,
                         scale=1)
    assert whole.shape == (3, TINY_HALF, TINY_HALF)
    with pytest.raises(FrameError, match="1/4"):  # 30 px across: the float path would upscale it
        camera_press(fab.load_press(1), camera_reference(through_camera_jpeg(fab.load_reference(), 90), spec,
                                                         scale=1), spec, 90, scale=4)


def test_a_manifest_with_a_jpeg_scale_and_no_camera_jpeg_is_refused_by_key(bundle_copy):  # noqa: F811
    dst = bundle_copy
    _edit(dst, lambda m: m["preprocess"].__setitem__("jpeg_scale", 2))
    with pytest.raises(rb.BundleError, match="jpeg_scale 2 .* no 'camera_jpeg'"):
        rb.load_bundle(dst)
    _edit(dst, lambda m: m.__setitem__("camera_jpeg", 90))  # with the quality it trained through, it loads
    b = rb.load_bundle(dst)
    assert b.preprocess.jpeg_scale == 2 and b.camera_jpeg == 90
    _edit(dst, lambda m: m["preprocess"].__setitem__("jpeg_scale", 3))
    with pytest.raises(rb.BundleError, match="'preprocess'.*jpeg_scale = 3"):
        rb.load_bundle(dst)


@pytest.fixture(scope="module")
def half_bundle(tiny_run, tmp_path_factory):  # noqa: F811
    """The tiny run as if trained with --camera-jpeg 90 decoded at 1/2 (at 48 px), exported (fp32)."""
    from vs2t_edge.export import from_run as fr
    from vs2t_edge.train.artifacts import save_run_artifacts

    _, art = tiny_run
    run = tmp_path_factory.mktemp("run_jpeg90_half")
    spec = TactilePreprocess(size=TINY_HALF, jpeg_scale=2)
    save_run_artifacts(run, replace(art, camera_jpeg=90, preprocess=spec.to_dict()))
    out = run.parent / "b_jpeg90_half"
    return out, fr.export_run(run, out, calibration_frames=8)


def test_export_reads_the_runs_frames_at_its_jpeg_scale_and_the_cell_decodes_there(half_bundle):
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.inference import TactileModel
    from vs2t_edge.runtime.wiring import model_decode_scale

    out, m = half_bundle
    assert m["camera_jpeg"] == 90 and m["preprocess"]["jpeg_scale"] == 2
    b = rb.load_bundle(out)
    fid, idx = next(iter(m["provenance"]["data"]["calibration_presses"].items()))
    fab = load_dataset(m["provenance"]["data"]["dataset"]).by_id(fid)
    want = camera_press(fab.load_press(idx[0]), camera_reference(fab.load_reference(), b.preprocess, 90, scale=2),
                        b.preprocess, 90, scale=2)
    np.testing.assert_array_equal(b.probe_input[0], want)  # the probe: a press decoded at 1/2, as trained
    model = TactileModel.load(out, threads=1)
    assert model_decode_scale(model, (120, 160)) == 2 and model_decode_scale(model, (120, 160), "full") == 1


def test_the_report_says_which_decodes_a_camera_jpeg_run_read():
    from vs2t_edge.train.report import _full_decodes

    assert not _full_decodes({"camera_jpeg": 95, "camera_decode": "auto"})
    assert _full_decodes({"camera_jpeg": 95, "camera_decode": "full"})
    assert _full_decodes({"camera_jpeg": 95})  # a run before --camera-decode: full decodes
    assert not _full_decodes({"camera_jpeg": 95, "camera_decode": "full", "preprocess_reduce": "2"})  # 1/reduce
    assert _full_decodes({"camera_jpeg": 95, "camera_decode": "auto", "tactile_feature": "shading_markers"})


def test_camera_decode_where_it_does_nothing_is_said(tmp_path, monkeypatch):
    """--camera-decode without --camera-jpeg (or on the reduced path) is logged as doing nothing;
    the run goes on (checked up to its first work: the dataset is stubbed out)."""
    from vs2t_edge.train import run as tr

    said: list = []
    monkeypatch.setattr(tr, "_log", said.append)
    monkeypatch.setattr(tr, "build_trunk", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("stop here")))
    with pytest.raises(RuntimeError, match="stop here"):
        tr.train(tiny_world(), tmp_path / "r", "tiny", camera_decode="full", figures=False)
    assert any("camera_decode full: does nothing here" in m for m in said), said


def test_verify_bundle_says_what_frames_the_bundle_trained_on(half_bundle, capsys):
    from vs2t_edge.cli import main

    out, _ = half_bundle
    assert main(["verify-bundle", str(out)]) == 0
    assert "frames: through the camera's JPEG at q90, decoded at 1/2" in capsys.readouterr().out
    assert main(["verify-bundle", str(shared_bundle("fp32"))]) == 0
    assert "frames: lossless" in capsys.readouterr().out

"""The scale a UVC camera decodes its frames at for a bundle (``devices.camera.decode_scale``):
a float-path bundle's 640x480 frames at 1/2 by default, the reduced path's own scale, the scale a
bundle trained through the camera's JPEG was decoded at (tests/test_camera_jpeg_scale.py), full
size when asked."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from vs2t_edge.runtime.preprocess import (TactilePreprocess, decode_jpeg, float_path_scale, prepare_reference,
                                          preprocess_tactile, through_camera_jpeg)
from vs2t_edge.runtime.wiring import DECODE_SCALES, match_camera, model_decode_scale


@pytest.mark.parametrize("hw,size,crop,scale", [
    ((480, 640), 128, 1.0, 2), ((480, 640), 224, 1.0, 2), ((480, 640), 64, 1.0, 4), ((480, 640), 32, 1.0, 8),
    ((240, 320), 128, 1.0, 1), ((480, 640), 128, 0.5, 1), ((480, 640), 240, 1.0, 2), ((480, 640), 241, 1.0, 1)])
def test_float_path_scale_keeps_the_input_size_across_the_crop(hw, size, crop, scale):
    spec = TactilePreprocess(size=size, crop_fraction=crop)
    assert float_path_scale(spec, hw) == scale
    assert min(hw) * crop / scale >= size or scale == 1


def test_float_path_scale_is_full_size_for_a_real_gelsights_corrections_and_the_reduced_path():
    assert float_path_scale(TactilePreprocess(size=128, inpaint_markers=True), (480, 640)) == 1
    assert float_path_scale(TactilePreprocess(size=128, normalise_exposure=True), (480, 640)) == 1
    assert float_path_scale(TactilePreprocess(size=128, reduce=2), (480, 640)) == 1  # its own: model_decode_scale


def _model(spec, camera_jpeg=0, descriptor=None):
    return SimpleNamespace(preprocess_spec=spec, camera_jpeg=camera_jpeg, descriptor=descriptor)


def test_model_decode_scale_follows_the_setting_and_the_bundle():
    hw = (480, 640)
    floatp, reduced = TactilePreprocess(size=128), TactilePreprocess(size=128, reduce=2)
    assert model_decode_scale(_model(floatp), hw) == 2  # auto: the float path's frames at 1/2
    assert model_decode_scale(_model(floatp), hw, "full") == 1
    assert model_decode_scale(_model(floatp), None) == 1  # no configured size: nothing to choose from
    assert model_decode_scale(_model(floatp, camera_jpeg=95), hw) == 1  # trained through the JPEG at full size
    at_half = TactilePreprocess(size=128, jpeg_scale=2)  # trained through the JPEG decoded at 1/2
    assert model_decode_scale(_model(at_half, camera_jpeg=95), hw) == 2
    assert model_decode_scale(_model(at_half, camera_jpeg=95), None) == 1
    assert model_decode_scale(_model(at_half, camera_jpeg=95), hw, "full") == 1
    assert model_decode_scale(_model(at_half, camera_jpeg=95), hw, "auto", "yuyv") == 1
    # behind a camera whose 1/2 frames leave fewer than 128 px across: full frames, not refused ones
    assert model_decode_scale(_model(at_half, camera_jpeg=95), (240, 320)) == 1
    assert model_decode_scale(_model(reduced), hw) == 2 and model_decode_scale(_model(reduced), None) == 2
    assert model_decode_scale(_model(reduced), hw, "full") == 1  # the model reduces full frames itself
    assert model_decode_scale(_model(floatp, descriptor=object()), hw) == 1
    assert model_decode_scale(object(), hw) == 1
    # a YUYV camera keeps a float-path bundle's frames whole; the reduced path keeps its own scale
    assert model_decode_scale(_model(floatp), hw, "auto", "yuyv") == 1
    assert model_decode_scale(_model(reduced), hw, "auto", "yuyv") == 2
    with pytest.raises(ValueError, match="decode_scale 'half'"):
        model_decode_scale(_model(floatp), hw, "half")


def test_the_start_log_says_when_full_frames_go_to_a_bundle_trained_on_half_decodes():
    from vs2t_edge.runtime.wiring import decode_scale_note

    at_half = _model(TactilePreprocess(size=128, jpeg_scale=2), camera_jpeg=95)
    note = decode_scale_note(at_half, "full")
    assert "decoded at 1/2" in note and "not as it trained" in note
    assert decode_scale_note(at_half, "auto") == ""
    assert decode_scale_note(_model(TactilePreprocess(size=128), camera_jpeg=95), "full") == ""  # trained full
    assert decode_scale_note(_model(TactilePreprocess(size=128)), "full") == ""  # lossless: any scale
    assert decode_scale_note(_model(TactilePreprocess(size=128, reduce=2), camera_jpeg=95), "full") == ""
    assert decode_scale_note(object(), "full") == ""


def test_match_camera_gives_a_uvc_camera_the_scale_for_its_configured_size():
    from vs2t_edge.runtime.camera import UVCCamera

    cam = UVCCamera(0, expected_hw=(480, 640))  # not connected: only its settings
    match_camera(cam, _model(TactilePreprocess(size=128)))
    assert cam.decode_scale == 2
    match_camera(cam, _model(TactilePreprocess(size=128)), "full")
    assert cam.decode_scale == 1
    yuyv = UVCCamera(0, expected_hw=(480, 640), pixel_format="yuyv")
    match_camera(yuyv, _model(TactilePreprocess(size=128)))
    assert yuyv.decode_scale == 1
    small = UVCCamera(0, expected_hw=(240, 320))
    match_camera(small, _model(TactilePreprocess(size=128)))
    assert small.decode_scale == 1


def test_the_config_key_and_the_benchs_choices_are_the_cells():
    from vs2t_edge.bench.press_timing import DECODE_SCALES as bench_scales
    from vs2t_edge.runtime.config import _SCHEMA

    leaf = _SCHEMA["devices"]["camera"]["decode_scale"]
    assert bench_scales == DECODE_SCALES
    assert "auto" in str(leaf) and "full" in str(leaf)


def test_a_config_with_another_decode_scale_is_refused_by_key(tmp_path):
    from vs2t_edge.runtime.config import ConfigError, load_config

    (tmp_path / "b").mkdir()
    path = tmp_path / "cell.yaml"
    scene = "scene:\n  reject_bin: 0\n  fabrics:\n    - {name: denim, kind: touched, bin: 1}\n"
    path.write_text("bundle: b\ndevices:\n  camera:\n    decode_scale: half\n" + scene)
    with pytest.raises(ConfigError, match="decode_scale"):
        load_config(path)
    path.write_text("bundle: b\n" + scene)
    assert load_config(path).camera["decode_scale"] == "auto"


def test_a_float_path_input_from_the_half_decode_is_about_as_close_to_training_as_the_full_decode():
    """Training reads lossless frames; a UVC camera hands MJPEG. Decoded at 1/2 (the JPEG's scaled
    inverse DCT standing in for the first half of the float path's INTER_AREA decimation) the
    network input is about as far from training's as the full decode's: the rendered press at q95,
    128 px 0.90 -> 0.83 grey levels mean (p99 3.8 -> 3.3); 224 px 1.10 -> 1.08 (4.6 -> 4.3); at q85
    and q75 the half decode is about 1 % farther at 224 px. Bound: 5 % farther at most."""
    from frame_fixtures import rendered_press_jpeg

    frame, ref, jpeg = rendered_press_jpeg()
    for size in (128, 224):
        spec = TactilePreprocess(size=size)
        trained = preprocess_tactile(frame, ref, spec)

        def gap(scale):
            small = [decode_jpeg(j, scale) for j in jpeg]
            served = preprocess_tactile(small[0], prepare_reference(small[1], spec, scale), spec, reduced_by=scale)
            return np.abs(served - trained) * np.asarray(spec.std)[:, None, None] * 255  # grey levels

        full, half = gap(1), gap(float_path_scale(spec, frame.shape[:2]))
        assert full.mean() > 0.3  # the JPEG loss is there to compare with
        assert half.mean() <= 1.05 * full.mean() and np.percentile(half, 99) <= 1.05 * np.percentile(full, 99)


def test_the_bench_scores_a_float_path_bundle_on_frames_decoded_at_the_cells_scale(tmp_path):
    """``press_outputs(scale=2)`` on a float-path bundle: the frames and the no-contact frame are
    decoded at 1/2 as the cell's camera hands them with decode_scale auto, and score as the cell
    scores such frames; without ``scale`` they are decoded at full size, as training's camera_jpeg."""
    from test_bundle_fixtures import SIZE, make_bundle, world_frames

    from vs2t_edge.bench import accuracy as acc
    from vs2t_edge.runtime.inference import TactileModel

    make_bundle(tmp_path / "b", "fp32", preprocess=TactilePreprocess(size=SIZE))
    model = TactileModel.load(tmp_path / "b", threads=1)
    _, raws, ref = world_frames()
    fabric = SimpleNamespace(load_reference=lambda: ref, load_press=lambda i: raws[i])
    ds = SimpleNamespace(by_id=lambda fid: fabric)
    half = acc.press_outputs(model, ds, {model.classes[0]: [3, 5]}, log=lambda m: None, jpeg_quality=90, scale=2)
    full = acc.press_outputs(model, ds, {model.classes[0]: [3, 5]}, log=lambda m: None, jpeg_quality=90)

    def camera(frame, scale):
        return through_camera_jpeg(frame, 90, scale)
    for out, scale in ((half, 2), (full, 1)):
        model.set_reference(camera(ref, scale), reduced_by=scale)
        expected = model.forward(np.concatenate([model.preprocess(camera(raws[i], scale), reduced_by=scale)
                                                 for i in (3, 5)]))
        np.testing.assert_allclose(out["feature"], expected.feature, rtol=1e-5, atol=1e-5)
    assert not np.allclose(half["feature"], full["feature"], atol=1e-4)


@pytest.mark.parametrize("scale,reason", [(4, "scale"), (8, "scale"), (3, "scale")])
def test_the_float_path_refuses_a_frame_it_would_have_to_upscale_or_no_camera_decodes(scale, reason):
    """A 640x480 frame at 1/4 has 120 px across the crop, fewer than a 128 px bundle's input: a
    recording made at 1/4 for another bundle is refused by name, never scored upscaled; 1/3 is no
    scale a camera decodes at. At 1/2 (240 px) the same bundle takes it."""
    from vs2t_edge.runtime.preprocess import FrameError

    spec = TactilePreprocess(size=128)
    rng = np.random.default_rng(0)
    full = rng.integers(30, 220, (480, 640, 3), dtype=np.uint8)
    small = cv2.resize(full, (640 // scale, 480 // scale), interpolation=cv2.INTER_AREA)
    with pytest.raises(FrameError) as exc:
        preprocess_tactile(small, None, TactilePreprocess(size=128, use_reference=False), reduced_by=scale)
    assert exc.value.reason == reason and f"1/{scale}" in str(exc.value)
    with pytest.raises(FrameError):
        prepare_reference(small, spec, scale)
    half = cv2.resize(full, (320, 240), interpolation=cv2.INTER_AREA)
    assert preprocess_tactile(half, prepare_reference(half, spec, 2), spec, reduced_by=2).shape == (3, 128, 128)

"""The UVC camera's MJPEG path (frames handed undecoded and decoded at the bundle's scale, or
full frames when the backend decodes itself) and the per-press contact check on exact window sums."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from test_camera import _RecordingCapture
from vs2t_edge.runtime.camera import UVCCamera
from vs2t_edge.runtime.contact import ContactCheck
from vs2t_edge.runtime.devices import CameraError


class _MjpegCapture(_RecordingCapture):
    """A V4L2 capture that honours CAP_PROP_CONVERT_RGB = 0 (``undecoded``): read() hands the MJPEG
    frame's bytes as one row, as OpenCV's V4L2 backend does; a backend that ignores it hands the
    decoded frame. ``payload`` replaces the next frame's bytes (a truncated or black frame)."""

    undecoded = True
    payload = None

    def set(self, prop, value):
        if prop == cv2.CAP_PROP_CONVERT_RGB and not self.undecoded:
            return False
        return super().set(prop, value)

    def get(self, prop):
        return self.props.get(prop, 1.0 if prop == cv2.CAP_PROP_CONVERT_RGB else 0.0)

    def read(self):
        ok, frame = super().read()
        frame = cv2.GaussianBlur(frame, (5, 5), 0)  # a sensor image, not noise the JPEG would smear
        if self.props.get(cv2.CAP_PROP_CONVERT_RGB, 1.0) != 0:
            return ok, frame
        jpeg = type(self).payload if type(self).payload is not None else cv2.imencode(".jpg", frame)[1].tobytes()
        return ok, np.frombuffer(jpeg, np.uint8)[None].copy()


@pytest.fixture
def mjpeg_capture(monkeypatch):
    _RecordingCapture.instances = []
    _MjpegCapture.undecoded, _MjpegCapture.payload = True, None
    monkeypatch.setattr(cv2, "VideoCapture", _MjpegCapture)
    return _RecordingCapture.instances


def test_uvc_takes_mjpeg_undecoded_and_decodes_it_at_the_bundles_scale(mjpeg_capture):
    with UVCCamera(0, flush_frames=0, expected_hw=(480, 640), decode_scale=2) as cam:
        cap = mjpeg_capture[0]
        assert (cv2.CAP_PROP_CONVERT_RGB, 0.0) in cap.sets
        assert (cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter_fourcc(*"MJPG"))) in cap.sets
        assert cam.settings_applied["mjpeg_undecoded"] is True and cam.settings_applied["decode_scale"] == 2
        frame = cam.grab()
        # checked at the reduced size the configured 640x480 becomes
        assert frame.image.shape == (240, 320, 3) and frame.reduced_by == 2
        _MjpegCapture.payload = cv2.imencode(".jpg", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
        with pytest.raises(CameraError) as exc:
            cam.grab()
        assert exc.value.kind == "corrupt" and exc.value.reason == "black"  # bad frames refused by name
        _MjpegCapture.payload = cv2.imencode(".jpg", np.full((480, 640, 3), 120, np.uint8))[1].tobytes()[:300]
        with pytest.raises(CameraError) as exc:
            cam.grab()
        assert exc.value.kind == "corrupt" and exc.value.reason in ("jpeg", "size")  # truncated
        _MjpegCapture.payload = cv2.imencode(".jpg", np.full((240, 320, 3), 120, np.uint8))[1].tobytes()
        with pytest.raises(CameraError) as exc:
            cam.grab()  # a 320x240 stream where 640x480 was configured: 160x120 at 1/2
        assert exc.value.reason == "size" and "expected 320x240" in str(exc.value)


def test_uvc_falls_back_to_full_frames_when_the_backend_decodes_itself(mjpeg_capture):
    _MjpegCapture.undecoded = False  # e.g. a backend other than V4L2
    with UVCCamera(0, flush_frames=0, expected_hw=(480, 640), decode_scale=2) as cam:
        assert cam.settings_applied["mjpeg_undecoded"] is False
        frame = cam.grab()
    assert frame.image.shape == (480, 640, 3) and frame.reduced_by == 1  # the model reduces it


def test_uvc_decodes_at_full_size_by_default(mjpeg_capture):
    with UVCCamera(0, flush_frames=0) as cam:
        assert "mjpeg_undecoded" not in cam.settings_applied
        assert all(prop != cv2.CAP_PROP_CONVERT_RGB for prop, _ in mjpeg_capture[0].sets)
        assert cam.grab().reduced_by == 1
    with pytest.raises(ValueError, match="decode_scale"):
        UVCCamera(0, decode_scale=3)


def _contact_before(frame, reference, check):
    """The contact check as it was (int16 difference, float box mean): the reference the fast form
    must agree with."""
    diff = cv2.blur(np.abs(frame.astype(np.int16) - reference.astype(np.int16)).max(axis=2).astype(np.float32),
                    (check.window_px, check.window_px))
    return float(np.mean(diff > check.threshold_levels)), float(diff.max())


@pytest.mark.parametrize("seed", range(4))
def test_contact_check_reads_what_it_read_before(seed):
    rng = np.random.default_rng(seed)
    check = ContactCheck()
    reference = cv2.GaussianBlur(rng.integers(60, 200, (120, 160, 3), dtype=np.uint8), (5, 5), 0)
    frame = np.clip(reference.astype(int) + rng.integers(-3, 4, reference.shape), 0, 255).astype(np.uint8)
    frame[40:70, 50:90] = np.clip(frame[40:70, 50:90].astype(int) + rng.integers(0, 40), 0, 255)  # an imprint
    got = check.read(frame, reference)
    area, peak = _contact_before(frame, reference, check)
    assert got.area_fraction == pytest.approx(area, abs=2 / frame[..., 0].size)  # a tie may round either way
    assert got.peak_levels == pytest.approx(peak, rel=1e-6)
    assert got.pressed == (area >= check.min_area_fraction)


@pytest.mark.parametrize("threshold", [3.04, 12.0, 12.3, 12.5, 40.0])
@pytest.mark.parametrize("window", [3, 5, 16, 17])
def test_contact_check_counts_what_float32_window_sums_count(threshold, window):
    """The uint16 window sums (windows up to 16 px; float32 past that) give the area and peak the
    float32 sums gave, for thresholds whose bound on a window's sum is a fraction too."""
    rng = np.random.default_rng(window)
    check = ContactCheck(threshold_levels=threshold, window_px=window)
    reference = cv2.GaussianBlur(rng.integers(60, 200, (120, 160, 3), dtype=np.uint8), (5, 5), 0)
    noise = rng.integers(-2, 3, reference.shape)
    noise[:, 80:] = rng.integers(-14, 15, (120, 80, 3))  # a noisier half: some windows over, some not
    frame = np.clip(reference.astype(int) + noise, 0, 255).astype(np.uint8)
    frame[40:70, 50:90] = np.clip(frame[40:70, 50:90].astype(int) + 60, 0, 255)  # an imprint
    b, g, r = cv2.split(cv2.absdiff(frame, reference))
    sums32 = cv2.boxFilter(cv2.max(cv2.max(b, g), r), cv2.CV_32F, (window, window), normalize=False)
    got = check.read(frame, reference)
    n = window * window
    assert got.area_fraction == float(np.mean(sums32 > np.float32(threshold * n)))
    assert got.peak_levels == float(sums32.max()) / n
    assert 0.0 < got.area_fraction < 1.0  # neither nothing nor everything over: the count is tested


def test_contact_check_decides_a_fractional_bound_exactly():
    """threshold 12.3 over 5 x 5 windows: a window sum of 308 is over (mean 12.32), 307 is not -
    also on uint16 sums, where the bound 307.5 is no value of the array's type."""
    check = ContactCheck(threshold_levels=12.3, min_area_fraction=0.0, window_px=5)
    reference = np.full((20, 20, 3), 100, np.uint8)
    frame = reference.copy()
    frame[..., 1] += 12  # every window sums to 300
    frame[10, 10, 1] = 100 + 12 + 7  # the 25 windows holding it: 307
    assert check.read(frame, reference).area_fraction == 0.0
    frame[10, 10, 1] = 100 + 12 + 8  # 308
    assert check.read(frame, reference).area_fraction == 25 / 400


def test_contact_check_decides_a_tie_on_exact_window_sums():
    check = ContactCheck(threshold_levels=12.0, min_area_fraction=0.0, window_px=5)
    reference = np.full((20, 20, 3), 100, np.uint8)
    frame = reference.copy()
    frame[..., 1] += 12  # every window's mean change is exactly the threshold: not over it
    assert check.read(frame, reference).area_fraction == 0.0
    frame[10, 10, 2] = 113  # one level more in one pixel: the 25 windows holding it are over
    assert check.read(frame, reference).area_fraction == 25 / 400


@pytest.mark.parametrize("hw", [(1, 1), (1, 7), (5, 1), (13, 17), (240, 320), (480, 640)])
def test_channel_max_is_the_largest_channel_of_each_pixel(hw):
    """The contact check's two-call channel maximum (dilate over the interleaved row, nearest
    resize to every third column) is numpy's max over the channels, bit for bit, at every size -
    widths of one pixel and odd ones included, where a wrong anchor or rounding would read a
    neighbour's byte."""
    from vs2t_edge.runtime.contact import _channel_max

    rng = np.random.default_rng(hw[0] * 1000 + hw[1])
    image = rng.integers(0, 256, (*hw, 3), dtype=np.uint8)
    image[..., 2] = np.where(rng.random(hw) < 0.3, 255, image[..., 2])  # ties and the top value
    assert np.array_equal(_channel_max(image), image.max(axis=2))


def test_a_float_path_bundle_scores_what_its_uvc_camera_decodes_reduced(mjpeg_capture, tmp_path):
    """The cell's chain for a float-path bundle on an MJPEG camera with decode_scale auto:
    match_camera gives the camera the bundle's float_path_scale, the camera hands frames decoded
    at it (reference and press alike), the model takes them and scores the press; with `full`
    the same camera hands full frames."""
    from test_bundle_fixtures import SIZE, make_bundle

    from vs2t_edge.runtime.inference import TactileModel
    from vs2t_edge.runtime.preprocess import TactilePreprocess, float_path_scale, reduced_hw
    from vs2t_edge.runtime.wiring import match_camera

    make_bundle(tmp_path / "b", "fp32", preprocess=TactilePreprocess(size=SIZE))
    model = TactileModel.load(tmp_path / "b", threads=1)
    n = float_path_scale(model.preprocess_spec, (480, 640))
    assert n > 1
    cam = UVCCamera(0, flush_frames=0, expected_hw=(480, 640))
    match_camera(cam, model)
    with cam:
        ref, press = cam.grab(), cam.grab()
    assert cam.decode_scale == n and ref.reduced_by == press.reduced_by == n
    assert press.image.shape[:2] == reduced_hw((480, 640), n)
    model.set_reference(ref.image, reduced_by=ref.reduced_by)
    score = model.score_press(press.image, reduced_by=press.reduced_by)
    assert all(np.isfinite(v) for v in score.log_posterior.values())
    match_camera(cam, model, "full")
    with cam:
        assert cam.grab().image.shape == (480, 640, 3)


class _DefaultYuyvCapture(_MjpegCapture):
    """A UVC camera offering YUYV and MJPEG that streams YUYV until asked for MJPG (OpenCV's V4L2
    backend prefers YUYV to MJPEG when it picks the format itself); its MJPEG is at quality 90."""

    def read(self):
        ok, frame = _RecordingCapture.read(self)
        frame = cv2.GaussianBlur(frame, (5, 5), 0)
        if self.props.get(cv2.CAP_PROP_FOURCC) != float(cv2.VideoWriter_fourcc(*"MJPG")):
            return ok, frame  # YUYV made BGR by the backend: no JPEG loss
        jpeg = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, 90])[1]
        if self.props.get(cv2.CAP_PROP_CONVERT_RGB, 1.0) != 0:
            return ok, cv2.imdecode(jpeg, cv2.IMREAD_COLOR)
        return ok, jpeg.reshape(1, -1).copy()


@pytest.mark.parametrize("model_kind, camera_jpeg, setting", [("trunk", 90, "full"), ("descriptor", 90, "auto"),
                                                              ("trunk", 0, "full")])
def test_a_bundle_trained_through_the_cameras_jpeg_gets_the_mjpeg_stream_at_full_scale(monkeypatch, model_kind,
                                                                                      camera_jpeg, setting):
    """A bundle trained through the camera's MJPEG that the camera decodes at full size - a descriptor
    bundle, `decode_scale: full`, a float-path bundle trained on full decodes - had the camera left
    in the format the driver picks: OpenCV's V4L2 backend picks YUYV before MJPEG, and the bundle
    scored uncompressed frames it never trained on, with no quality read to say so (the same frames
    refused for an explicit `pixel_format: yuyv`). It now asks for MJPEG and takes it undecoded,
    decodes it at full size itself and reads its quality; a lossless-trained bundle is left as it was."""
    from types import SimpleNamespace

    from vs2t_edge.runtime.preprocess import TactilePreprocess
    from vs2t_edge.runtime.wiring import match_camera

    _RecordingCapture.instances = []
    monkeypatch.setattr(cv2, "VideoCapture", _DefaultYuyvCapture)
    model = SimpleNamespace(preprocess_spec=TactilePreprocess(size=128), camera_jpeg=camera_jpeg,
                            descriptor=object() if model_kind == "descriptor" else None)
    cam = UVCCamera(0, flush_frames=0, expected_hw=(480, 640))
    match_camera(cam, model, setting)
    assert cam.decode_scale == 1
    with cam:
        frame = cam.grab()
    asked_mjpeg = (cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter_fourcc(*"MJPG"))) in _RecordingCapture.instances[0].sets
    assert frame.image.shape == (480, 640, 3) and frame.reduced_by == 1
    if camera_jpeg:
        assert asked_mjpeg and cam.settings_applied["mjpeg_undecoded"] is True
        assert cam.settings_applied["mjpeg_quality"] == 90  # read from the frame, said if it is not the bundle's
    else:
        assert not asked_mjpeg and "mjpeg_undecoded" not in cam.settings_applied


@pytest.mark.parametrize("camera_jpeg, reduce, jpeg_scale, said", [(90, 0, 2, True), (90, 2, 1, True), (90, 0, 1, True),
                                                                  (0, 0, 1, False), (0, 2, 1, False)])
def test_a_backend_that_decodes_the_mjpeg_itself_is_said_for_a_bundle_trained_through_it(
        mjpeg_capture, camera_jpeg, reduce, jpeg_scale, said):
    """The fallback - a backend that will not hand the MJPEG undecoded - gives full frames the
    backend decoded: a bundle trained through the camera's JPEG at 1/2 (or on the reduced path, at
    1/reduce) then scores full decodes, not as it trained (a tiny demo-world run at q90 and 1/2:
    61 of 528 test-job pieces decided otherwise than training's report), and no quality is read to
    tell. The start log says it (as for `decode_scale: full`); for a lossless-trained bundle the
    fallback is training's own path (the box average) and nothing is said."""
    from types import SimpleNamespace

    from vs2t_edge.runtime.preprocess import TactilePreprocess
    from vs2t_edge.runtime.wiring import decode_fallback_note, match_camera

    _MjpegCapture.undecoded = False
    model = SimpleNamespace(preprocess_spec=TactilePreprocess(size=128, reduce=reduce, jpeg_scale=jpeg_scale),
                            camera_jpeg=camera_jpeg, descriptor=None)
    cam = UVCCamera(0, flush_frames=0, expected_hw=(480, 640))
    match_camera(cam, model)
    with cam:
        note = decode_fallback_note(model, cam)
        assert cam.settings_applied["mjpeg_undecoded"] is False
    assert bool(note) == said, note
    if said:
        assert f"q{camera_jpeg}" in note and "CAP_PROP_CONVERT_RGB" in note
    _MjpegCapture.undecoded = True
    with cam:
        assert decode_fallback_note(model, cam) == ""  # undecoded as asked: as it trained


def test_a_camera_without_mjpeg_at_the_size_is_refused_at_connect_in_words(monkeypatch):
    """The cell asks for MJPG (and CONVERT_RGB 0) at decode scale 1 for a bundle trained through the
    camera's JPEG. A camera that does not offer MJPEG at the configured size keeps YUYV, and with
    CONVERT_RGB 0 hands raw YUYV bytes as one row: connect succeeded, and every grab was refused as
    'a truncated MJPEG frame?' - each press retried, each piece faulted, the cause never named
    (review, 2026-11-29). The format is read back and refused at connect, in words, as for yuyv."""
    from types import SimpleNamespace

    import cv2
    import numpy as np
    import pytest

    from test_camera import _RecordingCapture
    from vs2t_edge.runtime.camera import UVCCamera
    from vs2t_edge.runtime.devices import CameraError
    from vs2t_edge.runtime.preprocess import TactilePreprocess
    from vs2t_edge.runtime.wiring import match_camera

    yuyv = float(cv2.VideoWriter_fourcc(*"YUYV"))

    class YuyvOnly(_RecordingCapture):
        def set(self, prop, value):
            if prop == cv2.CAP_PROP_FOURCC:
                self.sets.append((prop, value))
                return False  # no MJPEG at this size: the driver keeps YUYV
            return super().set(prop, value)

        def get(self, prop):
            if prop == cv2.CAP_PROP_FOURCC:
                return yuyv
            return self.props.get(prop, 1.0 if prop == cv2.CAP_PROP_CONVERT_RGB else 0.0)

        def read(self):
            ok, frame = super().read()
            if self.props.get(cv2.CAP_PROP_CONVERT_RGB, 1.0) != 0:
                return ok, frame
            return ok, np.zeros((1, 640 * 480 * 2), np.uint8) + 128  # raw YUYV, one row (V4L2 backend)

    _RecordingCapture.instances = []
    monkeypatch.setattr(cv2, "VideoCapture", YuyvOnly)
    model = SimpleNamespace(preprocess_spec=TactilePreprocess(size=128), camera_jpeg=90, descriptor=None)
    cam = UVCCamera(0, flush_frames=0, expected_hw=(480, 640))
    match_camera(cam, model, "full")
    with pytest.raises(CameraError) as exc:
        cam.connect()
        try:
            cam.grab()
        finally:
            cam.disconnect()
    assert "YUYV" in str(exc.value) and "MJPEG" in str(exc.value), str(exc.value)

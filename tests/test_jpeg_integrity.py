"""An MJPEG frame cut short in transit (runtime/jpeg_integrity.py): libjpeg decodes it with its lost
part filled and only warns, so the UVC camera must refuse it by its marks - never score it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from frame_fixtures import rendered_press_jpeg
from test_camera import SHARED_REAL, _RecordingCapture, needs_real
from test_camera_mjpeg import _MjpegCapture, mjpeg_capture  # noqa: F401 - the fixture
from vs2t_edge.runtime.camera import UVCCamera
from vs2t_edge.runtime.contact import ContactCheck
from vs2t_edge.runtime.devices import CameraError
from vs2t_edge.runtime.jpeg_integrity import damaged_jpeg, ends_with_eoi, filled_bottom_row
from vs2t_edge.runtime.preprocess import decode_jpeg


def _scan_start(jpeg: bytes) -> int:
    sos = jpeg.find(b"\xff\xda")
    return sos + 2 + (jpeg[sos + 2] << 8) + jpeg[sos + 3]


def cut_short(jpeg: bytes, kept: float, eoi: bool = True) -> bytes:
    """The frame with only ``kept`` of its scan arrived (the rest lost on the bus), the end marker
    still there (``eoi``: its last payload arrived) or not."""
    start = _scan_start(jpeg)
    return jpeg[:start + int((len(jpeg) - 2 - start) * kept)] + (b"\xff\xd9" if eoi else b"")


def test_an_unpressed_frame_cut_short_in_transit_decodes_and_passes_the_contact_check():
    # why it must be refused: the decode succeeds (libjpeg only warns), and its grey fill against the
    # no-contact reference reads as an imprint - an unpressed gel's frame would be scored as a press
    _, ref, (_, ref_jpeg) = rendered_press_jpeg()
    reference = decode_jpeg(np.frombuffer(ref_jpeg, np.uint8), 2)
    damaged = decode_jpeg(np.frombuffer(cut_short(ref_jpeg, 0.7), np.uint8), 2)
    assert damaged is not None and damaged.shape == reference.shape
    assert ContactCheck().read(damaged, reference).pressed
    assert filled_bottom_row(damaged) and not filled_bottom_row(reference)


@pytest.mark.parametrize("kept", [0.0, 0.5, 0.9, 0.99])
def test_a_mjpeg_frame_cut_short_in_transit_is_refused_as_corrupt(mjpeg_capture, kept):
    _, _, (press_jpeg, _) = rendered_press_jpeg()
    with UVCCamera(0, flush_frames=0, expected_hw=(480, 640), decode_scale=2) as cam:
        _MjpegCapture.payload = press_jpeg
        assert cam.grab().image.shape == (240, 320, 3)  # the intact frame is taken
        _MjpegCapture.payload = cut_short(press_jpeg, kept)
        with pytest.raises(CameraError) as exc:
            cam.grab()
    assert exc.value.kind == "corrupt" and exc.value.reason == "jpeg" and "fill" in str(exc.value)


def test_a_frame_without_its_end_marker_is_refused_whatever_opencv_decodes(mjpeg_capture, monkeypatch):
    # OpenCV 5 refuses such a buffer; OpenCV 4 (pyproject allows >= 4.8) decodes it, its tail filled
    _, _, (press_jpeg, _) = rendered_press_jpeg()
    whole = decode_jpeg(np.frombuffer(press_jpeg, np.uint8), 2)
    monkeypatch.setattr("vs2t_edge.runtime.camera.decode_jpeg", lambda data, scale: whole.copy())  # as 4.x would
    with UVCCamera(0, flush_frames=0, expected_hw=(480, 640), decode_scale=2) as cam:
        _MjpegCapture.payload = cut_short(press_jpeg, 0.8, eoi=False)
        with pytest.raises(CameraError) as exc:
            cam.grab()
    assert exc.value.reason == "jpeg" and "end marker" in str(exc.value)
    assert ends_with_eoi(np.frombuffer(press_jpeg + b"\x00" * 40, np.uint8))  # padding after it is no damage
    assert ends_with_eoi(press_jpeg + b"\x00" * 4000)  # longer than the tail it looks in first; bytes too
    assert not ends_with_eoi(press_jpeg[:-2] + b"\x00" * 4000) and not ends_with_eoi(b"\x00" * 10)
    assert not ends_with_eoi(np.frombuffer(cut_short(press_jpeg, 0.8, eoi=False), np.uint8))


class _DecodingBackend(_MjpegCapture):
    """A backend that decodes the MJPEG itself (the fallback): it hands the damaged frame decoded."""

    undecoded = False

    def read(self):
        ok, _ = _RecordingCapture.read(self)
        return ok, cv2.imdecode(np.frombuffer(type(self).payload, np.uint8), cv2.IMREAD_COLOR)


def test_a_frame_the_backend_decoded_from_a_damaged_jpeg_is_refused_by_its_fill(monkeypatch):
    _RecordingCapture.instances = []
    monkeypatch.setattr(cv2, "VideoCapture", _DecodingBackend)
    _, _, (press_jpeg, _) = rendered_press_jpeg()
    with UVCCamera(0, flush_frames=0, expected_hw=(480, 640), decode_scale=2) as cam:
        _DecodingBackend.payload = press_jpeg
        assert cam.grab().image.shape == (480, 640, 3)
        _DecodingBackend.payload = cut_short(press_jpeg, 0.6)
        with pytest.raises(CameraError) as exc:
            cam.grab()
    _DecodingBackend.payload = None
    assert exc.value.kind == "corrupt" and exc.value.reason == "jpeg"


def _no_mark_at_any_quality_or_scale(frame: np.ndarray) -> None:
    for quality in (50, 75, 95):
        jpeg = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, quality])[1].reshape(-1)
        for scale in (1, 2, 4, 8):
            assert damaged_jpeg(jpeg, decode_jpeg(jpeg, scale)) == ""


def test_intact_rendered_frames_show_no_mark():
    press, ref, _ = rendered_press_jpeg()
    for frame in (press, ref):
        _no_mark_at_any_quality_or_scale(frame)


@needs_real
def test_intact_real_gelsight_frames_show_no_mark():
    files = sorted(SHARED_REAL.glob("gelsight_mini_materials/*/*.png"))
    assert len(files) == 200
    for f in files:
        _no_mark_at_any_quality_or_scale(cv2.imread(str(f)))

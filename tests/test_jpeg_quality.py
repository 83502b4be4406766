"""The MJPEG quality a camera streams at, read from its frames' quantisation table
(runtime/jpeg_quality.py), read by the UVC camera at connect and said by the daemon at start when
the bundle was trained for other frames."""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest

from vs2t_edge.runtime.jpeg_quality import (_LUMINANCE, _ZIGZAG, QUALITY_SLACK, estimate_quality, quality_note,
                                            quantisation_tables)


def _frame() -> np.ndarray:
    rng = np.random.default_rng(0)
    return cv2.GaussianBlur(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8), (5, 5), 0)


@pytest.mark.parametrize("q", [5, 30, 50, 75, 85, 92, 95, 100])
def test_the_quality_opencvs_encoder_used_is_read_back_exactly(q):
    jpeg = cv2.imencode(".jpg", _frame(), [cv2.IMWRITE_JPEG_QUALITY, q])[1]  # as a camera's bytes: one array
    got = estimate_quality(jpeg)
    assert got is not None and got.quality == q and got.exact
    assert sorted(quantisation_tables(jpeg)) == [0, 1]  # luminance and chrominance


def _dqt_offset(jpeg: bytes) -> int:
    i = jpeg.index(b"\xff\xdb")
    assert jpeg[i + 4] & 0x0F == 0  # the luminance table comes first
    return i + 5


def test_an_encoders_own_table_gets_the_nearest_quality_not_an_exact_one():
    jpeg = bytearray(cv2.imencode(".jpg", _frame(), [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes())
    at = _dqt_offset(bytes(jpeg))
    for k in (5, 20, 40):  # three entries of the luminance table nudged, as a camera's own tables differ
        jpeg[at + k] += 1
    got = estimate_quality(bytes(jpeg))
    assert got is not None and got.quality == 80 and not got.exact


def test_a_16_bit_table_is_read():
    """A DQT of precision 1 (two bytes an entry), built by hand: the q50 table is the standard's own."""
    table = _LUMINANCE[_ZIGZAG]
    dqt = bytes([0x10]) + struct.pack(">64H", *table.tolist())
    jpeg = b"\xff\xd8" + b"\xff\xdb" + struct.pack(">H", 2 + len(dqt)) + dqt + b"\xff\xda\x00\x02"
    np.testing.assert_array_equal(quantisation_tables(jpeg)[0], table)
    got = estimate_quality(jpeg)
    assert got is not None and (got.quality, got.exact) == (50, True)


@pytest.mark.parametrize("data", [b"", b"not a jpeg at all", b"\xff\xd8\xff\xdb\x00", b"\xff\xd8\xff\xdb\x00\x50\x00",
                                  b"\xff\xd8\x00\x00\x00\x00"])
def test_no_table_no_quality(data):
    assert estimate_quality(data) is None


def test_the_note_names_the_quality_to_train_with_and_is_silent_when_they_match():
    assert quality_note(95, 95) is None and quality_note(95 - QUALITY_SLACK, 95) is None
    assert quality_note(None, 0) is None and quality_note(True, 0) is None  # unknown: nothing to say
    lossless = quality_note(82, 0)
    assert "about q82" in lossless and "trained on lossless frames" in lossless and "--camera-jpeg 82" in lossless
    other = quality_note(75, 95)
    assert "through JPEG q95" in other and "--camera-jpeg 75" in other


def test_the_uvc_camera_reads_the_quality_from_its_first_good_frame_and_tells_it_once(monkeypatch):
    """A header parse of the first frame a grab decodes after connect, no extra read (a read at
    connect would add to the bounded open); told once a connect, also when the frame has no table."""
    from test_camera import _RecordingCapture
    from test_camera_mjpeg import _MjpegCapture

    from vs2t_edge.runtime.camera import UVCCamera

    monkeypatch.setattr(cv2, "VideoCapture", _MjpegCapture)
    for undecoded, scale, want in ((True, 2, [95]), (False, 2, []), (True, 1, [])):
        _RecordingCapture.instances = []
        _MjpegCapture.undecoded, _MjpegCapture.payload = undecoded, None
        told: list = []
        cam = UVCCamera(0, flush_frames=0, expected_hw=(480, 640), decode_scale=scale)
        cam.on_stream_quality = told.append
        with cam:
            assert "mjpeg_quality" not in cam.settings_applied  # nothing read at connect
            # the fake encodes at OpenCV's default quality, 95; a backend that decodes hands no table
            assert cam.grab().image.shape[0] == 480 // (scale if undecoded else 1)
            cam.grab()
            assert cam.settings_applied.get("mjpeg_quality") == (want[0] if want else None) and told == want
        if want:  # a reopen reads it again
            with cam:
                cam.grab()
            assert told == want * 2
    # a frame with no table the estimate can read: the quality is unknown, told as None
    import vs2t_edge.runtime.camera as camera_module

    monkeypatch.setattr(camera_module, "estimate_quality", lambda jpeg: None)
    _RecordingCapture.instances = []
    _MjpegCapture.undecoded = True
    told = []
    cam = UVCCamera(0, flush_frames=0, expected_hw=(480, 640), decode_scale=2)
    cam.on_stream_quality = told.append
    with cam:
        cam.grab()
        assert told == [None] and cam.settings_applied["mjpeg_quality"] is None
    _RecordingCapture.instances = []
    cam = UVCCamera(0, flush_frames=0, expected_hw=(480, 640), decode_scale=2)
    cam.on_stream_quality = lambda q: 1 / 0  # a teller that fails costs the press nothing
    with cam:
        assert cam.grab().reduced_by == 2


def test_the_daemon_says_once_when_the_camera_streams_another_quality_than_the_bundle_trained_for():
    from vs2t_edge.runtime.daemon import stream_quality_teller

    for streams, trained, said in ((80, 0, True), (95, 95, False), (80, 95, True), (None, 0, False)):
        logged: list = []
        tell = stream_quality_teller(trained, logged.append)
        tell(streams)
        tell(streams)  # a reopen tells it again; the log says it once
        assert len(logged) == int(said), logged
        if said:
            assert "the camera streams MJPEG at about" in logged[0] and f"--camera-jpeg {streams}" in logged[0]


def test_the_daemon_gives_a_uvc_camera_its_teller_and_others_none(tmp_path):
    from cell_fakes import FakeModel, ScriptedCamera
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.notify import Notifier
    from vs2t_edge.sim.fake_devices import FakeArm, FakeGate
    from vs2t_edge.sim.scene import fake_cell_yaml

    class TellingCamera(ScriptedCamera):
        on_stream_quality = None

        def grab(self):
            frame = super().grab()
            if self.on_stream_quality is not None:
                self.on_stream_quality(80)
            return frame

    cfg_path = tmp_path / "cell.yaml"
    cfg_path.write_text(fake_cell_yaml(fabrics=(("denim", "touched", 1), ("silk", "untouched", 2)), threads=1,
                                       evidence={"confidence": 0.95, "max_presses": 4, "without_scene_model": "allow"}))
    cfg = load_config(cfg_path)
    arm, gate, logged = FakeArm(config=cfg.arm), FakeGate(), []
    camera = TellingCamera(arm, [50])
    code = run_daemon(cfg, model=FakeModel({50: "denim"}, cfg.scene_classes), camera=camera, arm=arm, gate=gate,
                      notifier=Notifier(""), max_items=1, install_signals=False, log=logged.append)
    assert code == 0, logged
    notes = [line for line in logged if "the camera streams MJPEG at about q80" in line]
    assert len(notes) == 1 and "trained on lossless frames" in notes[0], logged

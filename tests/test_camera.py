"""GelSight capture: OpenCV reading real files (a written video, real GelSight image sequences),
frame guards (frozen, corrupt, ended), the simulated camera's faults and the contact check."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from vs2t_edge.runtime.camera import ReplayCamera, UVCCamera
from vs2t_edge.runtime.contact import ContactCheck, capture_reference
from vs2t_edge.runtime.frame_guard import FrameGuard
from vs2t_edge.sim.devices import SimulatedCamera
from vs2t_edge.runtime.devices import CameraError, NotConnectedError, TactileCamera
from vs2t_edge.runtime.preprocess import TactilePreprocess, preprocess_tactile

SHARED_REAL = Path(__file__).resolve().parents[2] / "shared" / "real"
H, W = 120, 160


def _pattern(i: int) -> np.ndarray:
    """A frame a codec keeps recognisable: a bright disc that moves with i on a mid-grey gel."""
    image = np.full((H, W, 3), 110, np.uint8)
    cv2.circle(image, (30 + 8 * i, 60), 18, (200, 170, 140), -1)
    return image


@pytest.fixture
def video(tmp_path) -> Path:
    path = tmp_path / "press.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (W, H))
    assert writer.isOpened()
    for i in range(10):
        writer.write(_pattern(i))
    writer.release()
    return path


def test_replay_reads_back_a_written_video(video):
    cam = ReplayCamera(video)
    assert isinstance(cam, TactileCamera)
    with pytest.raises(NotConnectedError):
        cam.grab()
    with cam:
        assert len(cam) == 10
        frames = [cam.grab() for _ in range(10)]
        with pytest.raises(CameraError) as exc:
            cam.grab()
    assert exc.value.kind == "ended"
    assert [f.index for f in frames] == list(range(10))
    for i, f in enumerate(frames):
        assert f.image.shape == (H, W, 3) and f.image.dtype == np.uint8
        # MJPEG is lossy: the disc is where it was written, within a few grey levels on average.
        assert np.abs(f.image.astype(int) - _pattern(i)).mean() < 4.0
    assert frames[-1].timestamp_s >= frames[0].timestamp_s


def test_replay_loops(video):
    with ReplayCamera(video, loop=True) as cam:
        frames = [cam.grab().image for _ in range(13)]
    assert np.array_equal(frames[10], frames[0]) and np.array_equal(frames[12], frames[2])


def test_uvc_camera_through_videocapture_on_a_path(video):
    # A file path exercises the same cv2.VideoCapture read path a /dev/video path does (a file
    # ignores size, fps, exposure and buffer settings: those are tested with _RecordingCapture).
    with UVCCamera(str(video), flush_frames=0, buffer_size=None, read_timeout_s=2.0) as cam:
        first = cam.grab()
        assert np.abs(first.image.astype(int) - _pattern(0)).mean() < 4.0
        for _ in range(9):
            cam.grab()
        with pytest.raises(CameraError) as exc:
            cam.grab()
        assert exc.value.kind == "unplugged"  # the stream ended: for a device, unplugged


def test_uvc_flush_drops_buffered_frames(video):
    with UVCCamera(str(video), flush_frames=2, buffer_size=None) as cam:  # a file has no driver queue
        image = cam.grab().image
    assert np.abs(image.astype(int) - _pattern(2)).mean() < 4.0  # frames 0 and 1 were stale


class _RecordingCapture:
    """A cv2.VideoCapture for a UVC driver: records every set(), answers get() with what the
    driver accepted (it clamps the frame rate and rounds the exposure, as V4L2 drivers do),
    and counts grab()/read() calls. Frames carry sensor noise unless ``frozen``."""

    instances: list = []

    def __init__(self, device, api=None):
        self.device, self.api = device, api
        self.sets: list[tuple[int, float]] = []
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: 640.0, cv2.CAP_PROP_FRAME_HEIGHT: 480.0, cv2.CAP_PROP_FPS: 30.0,
                      cv2.CAP_PROP_EXPOSURE: 0.0, cv2.CAP_PROP_BUFFERSIZE: 4.0}
        self.grabs = self.reads = 0
        self.frozen = False
        self._rng = np.random.default_rng(0)
        self._frame = None
        _RecordingCapture.instances.append(self)

    def isOpened(self):
        return True

    def set(self, prop, value):
        self.sets.append((prop, value))
        if prop == cv2.CAP_PROP_FPS:
            value = min(value, 30.0)  # the sensor's top rate
        elif prop == cv2.CAP_PROP_EXPOSURE:
            value = float(round(value / 10) * 10)  # the driver's exposure step
        self.props[prop] = value
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def grab(self):
        self.grabs += 1
        return True

    def read(self):
        self.reads += 1
        if self._frame is None or not self.frozen:
            h, w = int(self.props[cv2.CAP_PROP_FRAME_HEIGHT]), int(self.props[cv2.CAP_PROP_FRAME_WIDTH])
            self._frame = self._rng.integers(90, 130, (h, w, 3), dtype=np.uint8)
        return True, self._frame.copy()

    def release(self):
        pass


@pytest.fixture
def recording_capture(monkeypatch):
    _RecordingCapture.instances = []
    monkeypatch.setattr(cv2, "VideoCapture", _RecordingCapture)
    return _RecordingCapture.instances


def test_uvc_settings_reach_the_driver_and_what_it_accepted_is_read_back(recording_capture):
    with UVCCamera("/dev/video2", width=320, height=240, fps=60.0, exposure=156.0, flush_frames=3) as cam:
        cap = recording_capture[0]
        assert cap.device == "/dev/video2"
        assert dict(cap.sets) == {cv2.CAP_PROP_FRAME_WIDTH: 320.0, cv2.CAP_PROP_FRAME_HEIGHT: 240.0,
                                  cv2.CAP_PROP_FPS: 60.0, cv2.CAP_PROP_AUTO_EXPOSURE: 1,
                                  cv2.CAP_PROP_EXPOSURE: 156.0, cv2.CAP_PROP_BUFFERSIZE: 1.0}
        # manual exposure is switched on before the exposure is written, or the driver ignores it
        props = [prop for prop, _ in cap.sets]
        assert props.index(cv2.CAP_PROP_AUTO_EXPOSURE) < props.index(cv2.CAP_PROP_EXPOSURE)
        assert cam.settings_applied == {"width": 320.0, "height": 240.0, "fps": 30.0, "exposure": 160.0,
                                        "buffersize": 1.0, "flush_frames": 3, "decode_scale": 1}
        image = cam.grab().image
        assert image.shape == (240, 320, 3)
        assert (cap.grabs, cap.reads) == (3, 1)  # the buffered frames were dropped before the read
        cam.grab()
        assert (cap.grabs, cap.reads) == (6, 2)


def test_a_driver_that_ignores_the_buffer_size_has_its_whole_queue_dropped(recording_capture):
    """Asked for one buffer, a driver that keeps its default queue (V4L2: 4) held frames taken
    before the press - the gel in the air, or the last piece's imprint - and the 2 frames dropped
    before each read left them to be read as this press (or as the next piece's no-contact
    reference). Every buffer it may hold is dropped then, plus one."""
    class Deaf(_RecordingCapture):
        def set(self, prop, value):
            return False if prop == cv2.CAP_PROP_BUFFERSIZE else super().set(prop, value)

        def get(self, prop):
            return 0.0 if prop == cv2.CAP_PROP_BUFFERSIZE else super().get(prop)

    cv2.VideoCapture = Deaf  # the fixture's monkeypatch puts the real one back
    with UVCCamera(0) as cam:
        cap = recording_capture[-1]
        assert (cam.settings_applied["buffersize"], cam.settings_applied["flush_frames"]) == (None, 5)
        cam.grab()
        assert (cap.grabs, cap.reads) == (5, 1)
    with UVCCamera(0, flush_frames=7) as cam:  # more asked for: more dropped
        cam.grab()
        assert (recording_capture[-1].grabs, cam.settings_applied["flush_frames"]) == (7, 7)


def test_uvc_without_settings_leaves_the_driver_alone_but_the_buffer(recording_capture):
    with UVCCamera(0):
        cap = recording_capture[0]
    assert cap.sets == [(cv2.CAP_PROP_BUFFERSIZE, 1.0)]  # size, fps, auto exposure: the driver's own


def test_a_frozen_uvc_stream_is_a_fault_at_the_first_repeated_frame(recording_capture):
    from vs2t_edge.runtime.devices import CameraFrozen

    with UVCCamera(0, flush_frames=0) as cam:
        cam.grab()
        recording_capture[0].frozen = True  # the driver hands out its last buffer again
        with pytest.raises(CameraFrozen) as exc:
            cam.grab()
    assert exc.value.kind == "frozen" and exc.value.retryable and "2 times in a row" in str(exc.value)


def test_uvc_missing_device_is_unplugged(tmp_path):
    with pytest.raises(CameraError) as exc:
        UVCCamera(str(tmp_path / "video99.avi")).connect()
    assert exc.value.kind == "unplugged"


def test_frozen_frames_detected(tmp_path):
    for i in range(6):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), _pattern(0))
    with ReplayCamera(tmp_path, frozen_after=4) as cam:
        for _ in range(3):
            cam.grab()
        with pytest.raises(CameraError) as exc:
            cam.grab()
    assert exc.value.kind == "frozen"


def test_corrupt_and_black_images_named(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), _pattern(0))
    (tmp_path / "b.png").write_bytes(b"not a png")
    cv2.imwrite(str(tmp_path / "c.png"), np.zeros((H, W, 3), np.uint8))
    with ReplayCamera(tmp_path) as cam:
        cam.grab()
        with pytest.raises(CameraError, match="b.png") as exc:
            cam.grab()
        assert exc.value.kind == "corrupt"
        with pytest.raises(CameraError, match="c.png") as exc:
            cam.grab()
        assert exc.value.kind == "corrupt" and exc.value.reason == "black"


def test_a_reopened_recording_resumes_where_it_stopped(tmp_path, video):
    """The cell reopens the camera before a retry; a recording, standing in for a live sensor,
    must go on from where it was - not score the next pieces on the first frames again."""
    for i in range(4):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), _pattern(i))
    cam = ReplayCamera(tmp_path)
    cam.connect()
    first = [cam.grab().image for _ in range(2)]
    (tmp_path / "f0.png").unlink()  # listed once: a later reopen does not shift the frames
    cam.disconnect()
    cam.connect()
    third = cam.grab().image
    assert np.array_equal(third, _pattern(2)) and not np.array_equal(third, first[0])
    (tmp_path / "f3.png").unlink()
    with pytest.raises(CameraError, match="frame file missing: .*f3.png"):
        cam.grab()
    cam.disconnect()

    with ReplayCamera(video) as cam:
        frames = [cam.grab().image for _ in range(3)]
        cam.disconnect()
        cam.connect()
        resumed = cam.grab().image
    with ReplayCamera(video) as cam:
        expected = [cam.grab().image for _ in range(4)][3]
    assert np.array_equal(resumed, expected) and not np.array_equal(resumed, frames[0])


def test_expected_size_enforced(video):
    with ReplayCamera(video, expected_hw=(240, 320)) as cam:
        with pytest.raises(CameraError) as exc:
            cam.grab()
    assert exc.value.reason == "size"


def test_the_default_threshold_refuses_the_first_repeated_frame():
    """A live sensor never gives two bit-identical frames: the first repeat is a frozen camera,
    so no frozen frame reaches the model (the cell scores every frame grab() returns)."""
    from vs2t_edge.runtime.devices import CameraFrozen

    cam = SimulatedCamera(lambda: _pattern(0))
    cam.connect()
    fresh = [cam.grab() for _ in range(20)]  # noisy frames of one press are all admitted
    assert len({f.image.tobytes() for f in fresh}) == 20
    cam.inject("frozen", 1)
    with pytest.raises(CameraFrozen, match="2 times in a row"):
        cam.grab()
    cam.grab()


def test_a_frame_that_differs_only_between_the_pre_checked_rows_is_not_frozen():
    """The frozen check compares every 16th row first; a frame that differs from the last one
    only in other rows (or in one pixel) is still a fresh frame, and an exact repeat is frozen."""
    from vs2t_edge.runtime.devices import CameraFrozen

    guard = FrameGuard("cam", None, 2)
    first = _pattern(0)
    guard.admit(first)
    for row, col in ((1, 0), (17, 5), (first.shape[0] - 1, first.shape[1] - 1)):  # none of them a multiple of 16
        other = guard._last.copy()
        other[row, col, 2] ^= 1
        guard.admit(other)  # admitted: one bit differs
    other = guard._last.copy()
    other[32, 7, 0] ^= 1  # in a pre-checked row
    guard.admit(other)
    with pytest.raises(CameraFrozen):
        guard.admit(other.copy())  # bit for bit the last frame: frozen, however it was compared
    guard.reset()
    guard.admit(first[:, :10].copy())
    guard.admit(first[:, :11].copy())  # another size is never the same frame


def test_simulated_camera_faults():
    press = {"i": 0}
    cam = SimulatedCamera(lambda: _pattern(press["i"]), frozen_after=3)
    cam.inject("unplugged")
    with pytest.raises(CameraError):
        cam.connect()
    cam.connect()
    a, b = cam.grab().image, cam.grab().image
    assert not np.array_equal(a, b)  # sensor noise: two grabs of one press still differ
    assert np.abs(a.astype(int) - _pattern(0)).mean() < 2
    cam.inject("unplugged", 2)  # out at the next grab, back after one more failed connect
    for _ in range(2):
        with pytest.raises(CameraError) as exc:
            cam.grab()
        assert exc.value.kind == "unplugged" and exc.value.retryable
    with pytest.raises(CameraError):
        cam.connect()
    cam.connect()
    cam.grab()
    cam.inject("frozen", 2)
    cam.grab()
    with pytest.raises(CameraError) as exc:
        cam.grab()
    assert exc.value.kind == "frozen"
    cam.inject("black")
    with pytest.raises(CameraError) as exc:
        cam.grab()
    assert exc.value.reason == "black"
    cam.inject("truncated")
    cam._guard.expected_hw = (H, W)
    with pytest.raises(CameraError) as exc:
        cam.grab()
    assert exc.value.reason == "size"
    press["i"] = 5
    assert np.abs(cam.grab().image.astype(int) - _pattern(5)).mean() < 2


def test_simulated_unplug_is_a_disconnect_until_connect():
    """As a UVC device gone from the bus: after the cable comes out every grab fails - also once
    it is back - until connect() is called again; connect() fails while it is out."""
    cam = SimulatedCamera(lambda: _pattern(0))
    cam.connect()
    cam.inject("unplugged")  # out at the next grab, back for the next connect
    with pytest.raises(CameraError, match=r"no frame \(unplugged\)") as exc:
        cam.grab()
    assert exc.value.kind == "unplugged" and exc.value.retryable and cam.cable_out
    for _ in range(3):  # no grab brings it back by itself
        with pytest.raises(CameraError, match="not connected") as exc:
            cam.grab()
        assert exc.value.kind == "unplugged" and exc.value.retryable
    cam.disconnect()
    cam.connect()
    assert not cam.cable_out and cam.connects == 2 and cam.connected_count == 2
    cam.grab()
    cam.unplug()  # out for good: until the operator plugs it back
    for _ in range(3):
        with pytest.raises(CameraError, match="cannot open"):
            cam.connect()
    with pytest.raises(CameraError, match="not connected"):
        cam.grab()
    cam.replug()
    with pytest.raises(CameraError, match="not connected"):
        cam.grab()  # back in, but not reopened yet
    cam.connect()
    assert np.abs(cam.grab().image.astype(int) - _pattern(0)).mean() < 2
    assert cam.connects == 6 and cam.connected_count == 3


def test_a_frozen_frame_is_still_frozen_after_a_reconnect():
    """The cell reopens the camera before retrying a camera fault: a hung buffer that survives
    the reopen must still be reported frozen, not admitted as a fresh first frame."""
    cam = SimulatedCamera(lambda: _pattern(0), frozen_after=3)
    cam.connect()
    cam.grab()
    cam.inject("frozen", 3)
    cam.grab()
    with pytest.raises(CameraError) as exc:
        cam.grab()
    assert exc.value.kind == "frozen"
    cam.disconnect()
    cam.connect()
    with pytest.raises(CameraError) as exc:
        cam.grab()  # the same image again, right after the reopen
    assert exc.value.kind == "frozen"
    cam.grab()  # a fresh (noisy) frame is admitted


def test_contact_check_on_synthetic_frames():
    reference = _pattern(0)
    check = ContactCheck()
    rng = np.random.default_rng(1)
    noisy = np.clip(reference + rng.normal(0, 3, reference.shape), 0, 255).astype(np.uint8)
    brighter = np.clip(reference.astype(int) + 6, 0, 255).astype(np.uint8)
    assert not check.is_pressed(noisy, reference)
    assert not check.is_pressed(brighter, reference)  # lighting drift is not a press
    assert check.is_pressed(_pattern(4), reference)
    with pytest.raises(ValueError, match="differ in size"):
        check.read(reference[:10], reference)


def test_capture_reference_refuses_a_touched_gel():
    frames = iter([_pattern(0)] * 4 + [_pattern(3)])
    cam = SimulatedCamera(lambda: next(frames), noise_levels=1.0)
    cam.connect()
    with pytest.raises(CameraError, match="touches the gel"):
        capture_reference(cam, n_frames=5)
    steady = SimulatedCamera(lambda: _pattern(0), noise_levels=1.0)
    steady.connect()
    reference = capture_reference(steady, n_frames=5)
    assert np.abs(reference.astype(int) - _pattern(0)).max() <= 3



# --- the camera section of the cell config ------------------------------------------------------

CELL_YAML = """\
bundle: bundle
devices:
  camera:
    kind: uvc
    device: /dev/video2
    fps: 25
{camera_extra}  arm: {{kind: fake}}
  gate: {{kind: fake}}
scene:
  fabrics:
    - {{name: denim, kind: touched, bin: 1}}
journal: state/journal.jsonl
"""


def _cell_config(tmp_path, camera_extra: str):
    from vs2t_edge.runtime.config import load_config

    path = tmp_path / "cell.yaml"
    path.write_text(CELL_YAML.format(camera_extra=camera_extra))
    return path, lambda: load_config(path)


def test_capture_settings_from_the_config_reach_the_camera(tmp_path):
    from vs2t_edge.runtime.camera import camera_from_config

    _, load = _cell_config(tmp_path, "    timeout_s: 4.5\n    flush_frames: 5\n    frozen_after: 3\n")
    camera = camera_from_config(load().camera)
    assert isinstance(camera, UVCCamera) and camera.device == "/dev/video2" and camera.buffer_size == 1
    assert (camera.read_timeout_s, camera.flush_frames, camera._guard.frozen_after) == (4.5, 5, 3)
    _, load = _cell_config(tmp_path, "")
    camera = camera_from_config(load().camera)
    assert (camera.read_timeout_s, camera.flush_frames, camera._guard.frozen_after) == (2.0, 2, 2)  # defaults


def test_the_frame_timeout_stays_below_the_units_watchdog():
    """A hung grab (and its retry) must become a latched camera fault, not a SIGABRT from
    systemd: the bound on devices.camera.timeout_s is checked against the unit file."""
    from vs2t_edge.runtime.config import _SCHEMA

    unit = (Path(__file__).resolve().parents[1] / "systemd" / "vs2t-edge.service").read_text()
    watchdog_s = float(next(line.split("=", 1)[1] for line in unit.splitlines() if line.startswith("WatchdogSec=")))
    _lo, hi = _SCHEMA["devices"]["camera"]["timeout_s"]["bounds"]
    assert 2 * hi < watchdog_s, (hi, watchdog_s)


def test_exposure_from_the_config_reaches_the_uvc_camera(tmp_path):
    from vs2t_edge.runtime.wiring import build_live_devices

    _, load = _cell_config(tmp_path, "    exposure: 156\n")
    cfg = load()
    assert cfg.camera["exposure"] == 156.0
    camera, _arm, _gate = build_live_devices(cfg)
    assert isinstance(camera, UVCCamera) and camera.device == "/dev/video2"
    assert camera.requested == {"width": 640, "height": 480, "fps": 25.0, "exposure": 156.0}
    # absent: the driver's auto exposure is left alone (connect() only sets what was asked)
    _, load = _cell_config(tmp_path, "")
    camera, _arm, _gate = build_live_devices(load())
    assert camera.requested["exposure"] is None
    # the staleness settings reach the camera `run` builds, not only camera_from_config's
    _, load = _cell_config(tmp_path, "    flush_frames: 5\n    frozen_after: 3\n")
    camera, _arm, _gate = build_live_devices(load())
    assert (camera.flush_frames, camera._guard.frozen_after) == (5, 3)


@pytest.mark.parametrize("extra, words", [
    ("    exposure: 0\n", "devices.camera.exposure = 0.0: must be between 1.0 and 10000.0"),
    ("    exposure: 20000\n", "devices.camera.exposure = 20000.0: must be between 1.0 and 10000.0"),
    ("    exposure: auto\n", "devices.camera.exposure = 'auto': must be a number"),
    ("    exposure_ms: 15\n", "devices.camera.exposure_ms: unknown key"),
    ("    timeout_s: 45\n", "devices.camera.timeout_s = 45.0: must be between 0.05 and 10.0 (a hung grab must "
                          "become a latched camera fault, not a kill by systemd's WatchdogSec=30 s"),
    ("    flush_frames: -1\n", "devices.camera.flush_frames = -1: must be between 0 and 30"),
    ("    flush_frames: 1.5\n", "devices.camera.flush_frames = 1.5: must be a whole number"),
    ("    frozen_after: 1\n", "devices.camera.frozen_after = 1: must be between 2 and 100"),
])
def test_a_bad_exposure_names_file_line_and_key(tmp_path, extra, words):
    from vs2t_edge.runtime.config import ConfigError

    path, load = _cell_config(tmp_path, extra)
    with pytest.raises(ConfigError) as exc:
        load()
    problems = exc.value.problems
    assert len(problems) == 1 and problems[0].startswith(f"{path}:7: {words}"), problems  # line 7: the key's


# --- real GelSight frames (skip on a machine without ../shared) -------------------------------

needs_real = pytest.mark.skipif(not SHARED_REAL.is_dir(), reason="../shared/real is absent")


@needs_real
def test_contact_check_on_real_ball_presses():
    pack = SHARED_REAL / "taxim_calib" / "dataPack_small.npz"
    if not pack.is_file():
        pytest.skip("taxim_calib/dataPack_small.npz absent")
    data = np.load(pack)
    reference, presses = data["f0"], data["imgs"]  # a real no-contact frame and 49 real presses
    check = ContactCheck()
    readings = [check.read(p, reference) for p in presses]
    assert all(r.pressed for r in readings), [round(r.area_fraction, 4) for r in readings]
    rng = np.random.default_rng(0)
    unpressed = np.clip(reference + rng.normal(0, 3, reference.shape), 0, 255).astype(np.uint8)
    assert not check.is_pressed(unpressed, reference)


def _real_sequences() -> list[Path]:
    if not SHARED_REAL.is_dir():
        return []
    folders = sorted((SHARED_REAL / "gelsight_mini_materials").glob("material_*"))
    folders += [SHARED_REAL / "vitac_cloth11" / name for name in ("11t", "11t_test")]
    return [f for f in folders if f.is_dir()]


@needs_real
@pytest.mark.parametrize("folder", _real_sequences(), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_real_sequences_through_capture_and_preprocessing(folder):
    spec = TactilePreprocess()
    with ReplayCamera(folder) as cam:
        n = len(cam)
        frames = [cam.grab() for _ in range(n)]
        with pytest.raises(CameraError):
            cam.grab()
    assert n >= 2
    shapes = {f.image.shape for f in frames}
    assert len(shapes) == 1, f"{folder}: frames of different sizes {shapes}"
    # No no-contact frame was recorded: the first frame of the sequence stands in for it.
    reference = frames[0].image
    tensors = [preprocess_tactile(f.image, reference, spec) for f in frames]
    for t in tensors:
        assert t.shape == (3, spec.size, spec.size) and t.dtype == np.float32 and np.all(np.isfinite(t))
    assert np.abs(tensors[0]).max() == 0.0  # the reference minus itself
    assert max(np.abs(t).mean() for t in tensors[1:]) > 0.01  # other presses differ from it


@pytest.mark.hardware(needs="the real sensor (VS2T_CAMERA, default 0)")
def test_live_gelsight_on_uvc():
    import os

    device = os.environ.get("VS2T_CAMERA", "0")
    with UVCCamera(int(device) if device.isdigit() else device, read_timeout_s=2.0) as cam:
        reference = capture_reference(cam, n_frames=5)
        frame = cam.grab()
    assert frame.image.shape == reference.shape


class _HangingCapture:
    """Stands in for a cv2.VideoCapture whose driver stops delivering (cable pulled mid-read)."""

    def __init__(self):
        import threading

        self.release_read = threading.Event()
        self.released = False

    def grab(self):
        return True

    def read(self):
        self.release_read.wait(5)
        return False, None

    def release(self):
        self.released = True


def test_uvc_read_timeout_is_bounded_and_reported():
    import time

    cam = UVCCamera(0, read_timeout_s=0.2, flush_frames=0)
    cam._cap = _HangingCapture()  # what connect() would have opened
    t0 = time.monotonic()
    with pytest.raises(CameraError) as exc:
        cam.grab()
    assert exc.value.kind == "timeout" and time.monotonic() - t0 < 1.0
    with pytest.raises(CameraError, match="still stuck"):
        cam.grab()
    hanging = cam._cap
    cam.disconnect()
    assert not hanging.released  # not released under a read still inside the driver
    hanging.release_read.set()

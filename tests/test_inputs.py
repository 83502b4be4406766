"""Frames and files from outside the cell (issue 17, inputs): a frame that is not what the
sensor sends (grey, RGBA, 16-bit, wrong size) is refused at every entry - the replay camera, the
replay file, the dataset reader - never converted and scored; an image too large is refused from
its header before it is decoded; a FIFO is refused instead of blocking; a replay frame reached
through a link out of the replay folder is not read."""

from __future__ import annotations

import json
import os
import shutil
import struct
import threading
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from vs2t_edge.runtime.camera import ReplayCamera
from vs2t_edge.runtime.dataset import DatasetError, read_image, validate_dataset
from vs2t_edge.runtime.devices import CameraError
from vs2t_edge.runtime.files import InputRefused, image_header, read_image_file, read_regular_file
from vs2t_edge.runtime.preprocess import FrameError, TactilePreprocess, check_frame, preprocess_tactile
from vs2t_edge.runtime.replay import ReplayCameraDevice, ReplayError, ReplayFile

HERE = Path(__file__).parent
H, W = 48, 64


def _frame(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(40, 200, (H, W, 3), dtype=np.uint8)


# the frames that are not what a GelSight sends; each decodes fine with IMREAD_COLOR
NOT_SENSOR_FRAMES = {
    "grey": (lambda: cv2.cvtColor(_frame(), cv2.COLOR_BGR2GRAY), "shape"),
    "rgba": (lambda: cv2.cvtColor(_frame(), cv2.COLOR_BGR2BGRA), "shape"),
    "16-bit": (lambda: _frame().astype(np.uint16) * 257, "dtype"),
    "wrong size": (lambda: np.random.default_rng(1).integers(40, 200, (H // 2, W, 3), dtype=np.uint8), "size"),
}


def huge_png_header(side: int = 30000) -> bytes:
    """The start of a PNG of side x side px: all a header check needs (the real hostile file,
    under 3 MB on disk, decoded to 2.7 GB and peaked at 5.3 GB)."""
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return b"\x89PNG\r\n\x1a\n" + chunk + b"\x00" * 64


def _finishes(fn, timeout_s: float = 10.0):
    """fn() in a thread: (finished, its exception). A FIFO read that blocks never finishes."""
    box: dict = {}

    def run():
        try:
            fn()
        except BaseException as exc:  # noqa: BLE001
            box["exc"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        # unblock the reader (open a writer on the FIFO and close it) so the test process can end
        for fifo in _finishes.fifos:
            try:
                fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
                os.close(fd)
            except OSError:
                pass
    return not t.is_alive(), box.get("exc")


_finishes.fifos = []


# --- the frame check ------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", NOT_SENSOR_FRAMES)
def test_check_frame_refuses_frames_the_sensor_does_not_send(kind):
    make, reason = NOT_SENSOR_FRAMES[kind]
    with pytest.raises(FrameError) as exc:
        check_frame(make(), (H, W))
    assert exc.value.reason == reason


def test_preprocessing_refuses_an_oversized_frame_before_allocating_per_pixel():
    # a broadcast view: 30000 x 30000 x 3 "pixels" that take no memory; the float32 crop would be 10 GiB
    huge = np.broadcast_to(np.uint8(100), (30000, 30000, 3))
    with pytest.raises(FrameError) as exc:
        preprocess_tactile(_frame(), huge, TactilePreprocess(size=32))
    assert exc.value.reason == "size"


# --- the replay camera (config kind replay: a folder of frames) ------------------------------------

@pytest.mark.parametrize("kind", NOT_SENSOR_FRAMES)
def test_replay_camera_refuses_what_the_sensor_does_not_send(tmp_path, kind):
    make, reason = NOT_SENSOR_FRAMES[kind]
    cv2.imwrite(str(tmp_path / "000.png"), make())
    with ReplayCamera(tmp_path, expected_hw=(H, W)) as cam, pytest.raises(CameraError) as exc:
        cam.grab()
    assert exc.value.kind == "corrupt" and exc.value.reason == reason, str(exc.value)


def test_replay_camera_refuses_an_oversized_png_before_decoding_it(tmp_path):
    (tmp_path / "000.png").write_bytes(huge_png_header())
    with ReplayCamera(tmp_path) as cam, pytest.raises(CameraError) as exc:
        cam.grab()
    assert exc.value.reason == "too_large" and "30000x30000" in str(exc.value)


def test_replay_camera_refuses_a_fifo_instead_of_hanging(tmp_path):
    cv2.imwrite(str(tmp_path / "000.png"), _frame())
    os.mkfifo(tmp_path / "001.png")
    _finishes.fifos.append(tmp_path / "001.png")
    cam = ReplayCamera(tmp_path)
    cam.connect()
    cam.grab()
    finished, exc = _finishes(cam.grab)
    assert finished, "the replay camera blocked on a FIFO frame"
    assert isinstance(exc, CameraError) and "FIFO" in str(exc)


# --- the replay file (vs2t-edge replay) ------------------------------------------------------------

@pytest.fixture
def replay_copy(tmp_path) -> Path:
    out = tmp_path / "s.replay"
    shutil.copytree(HERE / "replays" / "touched.replay", out)
    return out


@pytest.mark.parametrize("kind", ["grey", "rgba", "16-bit"])
def test_replayed_frames_the_sensor_does_not_send_are_read_as_stored_and_refused(replay_copy, kind):
    make, reason = NOT_SENSOR_FRAMES[kind]
    cv2.imwrite(str(replay_copy / "frames" / "000002.png"), make())
    rf = ReplayFile.open(replay_copy)
    stored = rf.load_frame("frames/000002.png")
    assert (stored.shape, stored.dtype) != ((H, W, 3), np.uint8)  # read as stored, not converted

    class Q:  # the one grab the device asks its queues for
        def __init__(self):
            self.rf = rf

        def pop(self, dev, call):
            return {"frame": "frames/000002.png"}

    # as recorded (a fake camera's bad frames are recorded too, and must replay as they were);
    # the cell's frame check then refuses it: skipped, never scored
    frame = ReplayCameraDevice(Q()).grab()
    with pytest.raises(FrameError) as exc:
        check_frame(frame.image)
    assert exc.value.reason == reason


def test_replay_frame_through_a_link_out_of_the_folder_is_not_read(replay_copy, tmp_path):
    outside = tmp_path / "secret.png"
    cv2.imwrite(str(outside), _frame())
    frame = replay_copy / "frames" / "000002.png"
    frame.unlink()
    frame.symlink_to(outside)
    rf = ReplayFile.open(replay_copy)
    with pytest.raises(ReplayError, match="outside the replay folder"):
        rf.load_frame("frames/000002.png")
    # a link to the frames folder itself is followed the same way: refused too
    (replay_copy / "frames").rename(replay_copy / "real_frames")
    (replay_copy / "frames").symlink_to(tmp_path)
    with pytest.raises(ReplayError, match="outside the replay folder"):
        rf.load_frame("frames/000002.png")


def test_replay_index_through_a_link_out_of_the_folder_is_not_read(replay_copy, tmp_path):
    (replay_copy / "index.json").rename(tmp_path / "index.json")
    (replay_copy / "index.json").symlink_to(tmp_path / "index.json")
    with pytest.raises(ReplayError, match="outside the replay folder"):
        ReplayFile.open(replay_copy)


def test_replay_fifo_frame_is_refused_instead_of_hanging(replay_copy):
    frame = replay_copy / "frames" / "000002.png"
    frame.unlink()
    os.mkfifo(frame)
    _finishes.fifos.append(frame)
    rf = ReplayFile.open(replay_copy)
    finished, exc = _finishes(lambda: rf.load_frame("frames/000002.png"))
    assert finished and isinstance(exc, ReplayError) and "FIFO" in str(exc)


def test_replay_oversized_frame_is_refused_before_decoding(replay_copy):
    (replay_copy / "frames" / "000002.png").write_bytes(huge_png_header())
    rf = ReplayFile.open(replay_copy)
    with pytest.raises(ReplayError, match="30000x30000"):
        rf.load_frame("frames/000002.png")


def test_replay_index_that_is_a_fifo_or_too_large_is_refused(replay_copy):
    index = replay_copy / "index.json"
    index.unlink()
    os.mkfifo(index)
    _finishes.fifos.append(index)
    finished, exc = _finishes(lambda: ReplayFile.open(replay_copy))
    assert finished and isinstance(exc, ReplayError)
    index.unlink()
    with open(index, "wb") as f:  # sparse: 100 MB that take no disk
        f.truncate(100 * 1024 * 1024)
    with pytest.raises(ReplayError, match="bytes, more than"):
        ReplayFile.open(replay_copy)


# --- the dataset reader ---------------------------------------------------------------------------

@pytest.mark.parametrize("kind", NOT_SENSOR_FRAMES)
def test_dataset_reader_refuses_what_the_sensor_does_not_send(tmp_path, kind):
    make, _ = NOT_SENSOR_FRAMES[kind]
    path = tmp_path / "press.png"
    cv2.imwrite(str(path), make())
    with pytest.raises(ValueError) as exc:
        read_image(path, (H, W))
    assert isinstance(exc.value, InputRefused), exc.value


def test_validate_dataset_names_a_grey_press_and_an_oversized_reference(tmp_path):
    from test_dataset import _build

    root = _build(tmp_path / "ds")
    cv2.imwrite(str(root / "f01" / "tactile" / "press_000.png"), cv2.cvtColor(_frame(), cv2.COLOR_BGR2GRAY))
    (root / "f02" / "reference.png").write_bytes(huge_png_header())
    with pytest.raises(DatasetError) as info:
        validate_dataset(root, deep=True)
    msg = "\n".join(info.value.problems)
    assert "fabric 'f01' press 0" in msg and "1 channel(s)" in msg
    assert "fabric 'f02' no-contact reference frame" in msg and "30000x30000" in msg


# --- the bounded readers themselves ---------------------------------------------------------------

def test_image_headers_give_the_size_without_decoding(tmp_path):
    image = _frame()
    for ext in (".png", ".jpg", ".bmp", ".tif"):
        ok, buf = cv2.imencode(ext, image)
        head = image_header(buf.tobytes())
        assert head is not None and (head.width, head.height) == (W, H), ext
    assert image_header(b"GIF89a" + b"\x00" * 20) is None
    assert image_header(b"\x89PNG\r\n\x1a\n") is None  # cut short


def test_a_device_or_folder_is_not_a_regular_file(tmp_path):
    for path in ("/dev/zero", tmp_path):
        with pytest.raises(InputRefused) as exc:
            read_regular_file(path, 1024)
        assert exc.value.reason == "not_regular"
    with pytest.raises(InputRefused, match="not a PNG"):
        (tmp_path / "x.gif").write_bytes(b"GIF89a" + b"\x00" * 20)
        read_image_file(tmp_path / "x.gif")


# --- the live camera (config kind uvc) --------------------------------------------------------------

def test_uvc_camera_from_config_refuses_frames_of_another_size_or_format():
    """The guard every live grab goes through, with the configured sensor's size: OpenCV's V4L2
    capture converts to BGR, but a driver that ignored the size asked for (or a misconfigured
    width_px) gives frames the bundle was not made for - refused, never scored."""
    from vs2t_edge.runtime.camera import camera_from_config

    cam = camera_from_config({"kind": "uvc", "device": "/dev/null-camera", "width_px": W, "height_px": H,
                              "fps": 30.0, "exposure": None, "timeout_s": 1.0, "flush_frames": 0,
                              "frozen_after": 2})
    assert cam._guard.expected_hw == (H, W)
    for kind, (make, reason) in NOT_SENSOR_FRAMES.items():
        with pytest.raises(CameraError) as exc:
            cam._guard.admit(make())
        assert exc.value.kind == "corrupt" and exc.value.reason == reason, kind
    assert cam._guard.admit(_frame()).image.shape == (H, W, 3)


def test_the_replay_verb_refuses_an_oversized_frame_in_words_exit_2(replay_copy, capsys):
    """`vs2t-edge replay` on a session whose frame is a 30000 x 30000 PNG peaked at 5.2 GB; now the
    frame is refused from its header and the verb says which file (exit 2: unreadable file)."""
    from vs2t_edge.cli import main

    (replay_copy / "frames" / "000001.png").write_bytes(huge_png_header())
    assert main(["replay", str(replay_copy), "--bundle", str(HERE / "replays" / "bundle")]) == 2
    err = capsys.readouterr().err
    assert "000001.png" in err and "30000x30000" in err


def test_dataset_text_files_are_bounded(tmp_path):
    from test_dataset import _build

    root = _build(tmp_path / "ds")
    with open(root / "f01" / "fabric.yaml", "ab") as f:
        f.truncate(50 * 1024 * 1024)  # sparse: a 50 MB fabric.yaml
    with pytest.raises(DatasetError) as info:
        validate_dataset(root, deep=False)
    assert any("f01/fabric.yaml" in p and "bytes, more than" in p for p in info.value.problems), info.value.problems
    (root / "dataset.yaml").unlink()
    os.mkfifo(root / "dataset.yaml")
    _finishes.fifos.append(root / "dataset.yaml")
    finished, exc = _finishes(lambda: validate_dataset(root, deep=False))
    assert finished and isinstance(exc, DatasetError), exc


def test_a_frame_decoded_reduced_is_recorded_and_replayed_so(replay_copy):
    """A UVC camera on the reduced path hands frames decoded at 1/n (Frame.reduced_by): the
    recording notes it and the replay hands the model the same, or the model would reduce the
    frame a second time; a hand-edited scale is refused naming the frame."""
    import time as _time

    from vs2t_edge.runtime.devices import Frame
    from vs2t_edge.runtime.recording import Recorder, RecordingCamera
    from vs2t_edge.runtime.replay import _FileUnreadable

    class Reduced:  # a camera that decoded its MJPEG frame at 1/2
        def grab(self):
            return Frame(_frame(), _time.monotonic(), 7, reduced_by=2)

    rec = Recorder()
    RecordingCamera(Reduced(), rec).grab()
    ev = rec.events[-1]
    assert ev["reduced_by"] == 2 and ev["index"] == 7
    rf = ReplayFile.open(replay_copy)

    class Q:
        def __init__(self, scale):
            self.rf, self.scale = rf, scale

        def pop(self, dev, call):
            return {"frame": "frames/000002.png", "index": 7, **({"reduced_by": self.scale} if self.scale else {})}

    assert ReplayCameraDevice(Q(2)).grab().reduced_by == 2
    assert ReplayCameraDevice(Q(None)).grab().reduced_by == 1  # every replay recorded before it
    for bad in (3, True, "2"):
        with pytest.raises(_FileUnreadable) as exc:
            ReplayCameraDevice(Q(bad)).grab()
        assert "frames/000002.png" in str(exc.value.error) and "reduced_by" in str(exc.value.error)
    # calibrate-threshold reads a replay's frames directly: the session's one scale, or refused
    assert rf.frame_scale() == 1
    grabs = [ev for ev in rf.index["events"] if ev["dev"] == "camera" and ev.get("frame")]
    for ev in grabs:
        ev["reduced_by"] = 2
    assert rf.frame_scale() == 2
    grabs[0]["reduced_by"] = 4
    with pytest.raises(ReplayError, match="scales"):
        rf.frame_scale()

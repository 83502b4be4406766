"""GelSight capture: frames in, nothing else (preprocessing stays in runtime/preprocess.py).

Two implementations of :class:`vs2t_edge.runtime.devices.TactileCamera` (the simulated cell's
camera, ``SimulatedCamera``, is in vs2t_edge.sim.devices: simulators stay out of the cell's code):

* :class:`UVCCamera` - the sensor as a UVC camera through ``cv2.VideoCapture`` (device index or
  path); resolution, fps and exposure set where the driver accepts them (what it accepted is
  read back into ``settings_applied``); a bounded read; stale buffered frames flushed, and where the
  driver stamps its frames with their capture time (V4L2), any frame taken before the grab was
  asked read past (``stale_dropped``) or refused (reason ``stale``). For a
  bundle on the reduced pixel path (``preprocess.reduce`` n >= 2, runtime/preprocess.py) - or a
  float-path one the cell decodes reduced (below) - it asks
  the driver for the MJPEG stream undecoded (``CAP_PROP_FOURCC`` MJPG, ``CAP_PROP_CONVERT_RGB`` 0;
  OpenCV's V4L2 backend honours it and hands the JPEG bytes) and decodes each frame itself at 1/n
  scale (``decode_jpeg``: libjpeg skips most of the work), handing ``Frame(reduced_by=n)``; a frame
  cut short in transit, which libjpeg decodes filled, is refused by its marks (runtime/jpeg_integrity.py). A
  backend that still hands decoded frames (other backends, a camera without MJPEG) is the
  fallback: its full frames go to the model as they are, which reduces them with the very
  function training used (``settings_applied["mjpeg_undecoded"]`` says which). A float-path
  bundle's MJPEG is decoded so too, at ``preprocess.float_path_scale`` (``devices.camera.decode_scale``
  auto, the default: runtime/wiring.py ``model_decode_scale``; its YUYV frames stay whole), and it
  takes the frames the fallback hands at full size as they are. Taking the MJPEG undecoded, it
  reads the quality the camera streams at from the first good frame's quantisation table
  (``settings_applied["mjpeg_quality"]``, told to ``on_stream_quality``: runtime/jpeg_quality.py). With
  ``pixel_format="yuyv"`` it asks for uncompressed YUYV 4:2:2 instead (``CAP_PROP_FOURCC`` YUYV,
  raw bytes) and makes each frame BGR at 1/n itself (runtime/yuyv.py: no JPEG to decode, no JPEG
  loss; ``settings_applied["pixel_format"]`` is what the driver runs); a camera that runs another
  format then is refused at connect, in words, rather than scored on frames it was not set up for.
* :class:`ReplayCamera` - recorded frames (a video file, an image folder or a glob), same
  interface; loops or ends with ``CameraError(kind="ended")``.

Every grab, of these and of the simulated camera, goes through one guard (``FrameGuard``,
runtime/frame_guard.py: the frame check and frozen-frame detection). Its frozen-frame count
goes on across a reconnect of a live or simulated camera (the cell reopens the camera before
retrying a camera fault): a frozen image that survives a reopen is still frozen.
Faults are ``CameraError(kind=...)`` with kind one of: unplugged, timeout, frozen, ended, corrupt.

Whether the gel is actually pressed (the press frame against the no-contact reference) is
runtime/contact.py's.
"""

from __future__ import annotations

import glob as globmod
import math
import threading
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from vs2t_edge.runtime.camera_warmup import settle
from vs2t_edge.runtime.devices import CameraError, Frame, NotConnectedError
from vs2t_edge.runtime.files import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE_PX, InputRefused, read_image_file
from vs2t_edge.runtime.frame_guard import FROZEN_AFTER, CameraBase, FrameGuard
from vs2t_edge.runtime.jpeg_integrity import damaged_jpeg
from vs2t_edge.runtime.jpeg_quality import estimate_quality
from vs2t_edge.runtime.preprocess import REDUCE_FACTORS, decode_jpeg
from vs2t_edge.runtime.yuyv import BYTES_PER_PIXEL, decode_yuyv

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
PIXEL_FORMATS = ("mjpeg", "yuyv")  # what a UVC camera is asked to stream (devices.camera.pixel_format)


# --- live UVC camera ----------------------------------------------------------------------

# A UVC open takes well under a second; one that hangs in the driver is ended past this.
UVC_OPEN_TIMEOUT_S = 5.0
V4L2_DEFAULT_BUFFERS = 4  # what a V4L2 driver queues when it does not take CAP_PROP_BUFFERSIZE
WARMUP_OPEN_MARGIN_S = 1.0  # the warm-up ends this long before the open's bound, whatever warmup_s says
# frames read past the flush while the driver's capture time is before the grab (OpenCV's V4L2 queue max)
MAX_STALE_DROPS = 10
# A driver whose frame times once fall this close to the monotonic clock stamps with it (OpenCV's
# V4L2 backend: the buffer's timestamp, CLOCK_MONOTONIC for uvcvideo); from then on every frame it
# hands must carry a time after the grab was asked - one from minutes ago most of all (a queue that
# kept the frames taken just after the last grab while the cell stood). Times that never come close
# (another backend, a file's position, 0 before the first frame) leave the blind flush alone.
CAPTURE_CLOCK_SLACK_MS = 10_000.0


def _pos_ms(cap) -> float | None:
    """CAP_PROP_POS_MSEC of the last frame read, when the backend gives a positive number."""
    try:
        t = float(cap.get(cv2.CAP_PROP_POS_MSEC))
    except Exception:  # noqa: BLE001 - a capture time is extra evidence; asking for it never fails a read
        return None
    return t if t > 0 and math.isfinite(t) else None


def is_compressed(image: object) -> bool:
    """A backend's undecoded frame (MJPEG, or raw YUYV): one row (or a flat run) of uint8 bytes, not HxWx3."""
    return (isinstance(image, np.ndarray) and image.dtype == np.uint8
            and (image.ndim == 1 or (image.ndim == 2 and 1 in image.shape)))


class UVCCamera(CameraBase):
    """A GelSight (Mini, R1.5, ...) enumerating as a UVC camera."""

    def __init__(self, device: int | str = 0, *, width: int | None = None, height: int | None = None,
                 fps: float | None = None, exposure: float | None = None, read_timeout_s: float = 1.0,
                 frozen_after: int = FROZEN_AFTER, flush_frames: int = 2, buffer_size: int | None = 1,
                 expected_hw: tuple[int, int] | None = None, api_preference: int = cv2.CAP_ANY,
                 open_timeout_s: float = UVC_OPEN_TIMEOUT_S, decode_scale: int = 1,
                 pixel_format: str = "mjpeg", warmup_s: float = 0.0) -> None:
        if read_timeout_s <= 0 or open_timeout_s <= 0:
            raise ValueError("read_timeout_s and open_timeout_s must be positive")
        if not 0 <= warmup_s < open_timeout_s:
            raise ValueError(f"warmup_s must be >= 0 and below open_timeout_s ({open_timeout_s:g} s: the warm-up "
                             f"runs inside the bounded open), got {warmup_s!r}")
        # after each open, frames read until the picture holds still (runtime/camera_warmup.py)
        self.warmup_s = warmup_s
        if decode_scale not in REDUCE_FACTORS:
            raise ValueError(f"decode_scale must be one of {REDUCE_FACTORS} (1/n JPEG decode), got {decode_scale!r}")
        if pixel_format not in PIXEL_FORMATS:
            raise ValueError(f"pixel_format must be one of {PIXEL_FORMATS}, got {pixel_format!r}")
        self.decode_scale = decode_scale  # > 1: MJPEG taken undecoded and decoded at 1/decode_scale
        # MJPEG taken undecoded at full scale too: a bundle trained through the camera's JPEG (manifest
        # camera_jpeg; runtime/wiring.py match_camera sets it). Left to itself, OpenCV's V4L2 backend
        # picks YUYV before MJPEG, frames that bundle never trained on, with no quality to read.
        self.take_mjpeg = False
        self.pixel_format = pixel_format  # yuyv: raw frames, made BGR (at 1/decode_scale) here
        if flush_frames < 0:
            raise ValueError("flush_frames must be >= 0")
        if buffer_size is not None and buffer_size < 1:
            raise ValueError("buffer_size must be >= 1 (or None: the driver's default)")
        self.device = device
        self.name = f"camera {device}"
        self.requested = {"width": width, "height": height, "fps": fps, "exposure": exposure}
        self.read_timeout_s = read_timeout_s
        self.open_timeout_s = open_timeout_s
        self.flush_frames = flush_frames  # V4L2 queues a few buffers: drop those taken before the press
        # V4L2 queues 4 buffers by default: at 30 fps a grab could return a frame 130 ms old, taken
        # before the gel settled. One buffer (CAP_PROP_BUFFERSIZE, honoured by the V4L2 backend)
        # bounds that to one frame, which flush_frames then drops.
        self.buffer_size = buffer_size
        self.api_preference = api_preference
        self.settings_applied: dict[str, object] = {}
        # told once per connect the MJPEG quality of the first frame a grab decodes (None: no table
        # in it; read while settings_applied, a new dict each connect, has no "mjpeg_quality"); the
        # daemon says what it means for the bundle (runtime/jpeg_quality.py)
        self.on_stream_quality: Callable[[int | None], None] | None = None
        self._guard = FrameGuard(self.name, expected_hw, frozen_after)
        self._cap = None
        self._reader: threading.Thread | None = None  # a read still stuck in the driver
        self._stuck: list = []  # captures abandoned with a read inside the driver
        self.stale_dropped = 0  # frames read past the flush because the driver's capture time predated the grab
        # the driver has shown it stamps frames with the monotonic clock (kept across a reopen: the same driver)
        self._stamped = False

    @property
    def expected_hw(self) -> tuple[int, int] | None:
        """The full frame size configured (height, width), or None: any size is taken."""
        return self._guard.expected_hw

    def connect(self) -> None:
        """Open the device and apply the settings, in a thread bounded by ``open_timeout_s``: a
        driver that hangs in open or in a setting becomes a camera fault the cell can latch,
        not a loop that starves systemd's watchdog (runtime/budget.py leases the reopen for this
        bound). A late open is released by its thread, never used."""
        box: dict = {}
        late = threading.Lock()
        abandoned = False

        def open_() -> None:
            try:
                result = self._open()
            except Exception as exc:  # noqa: BLE001 - handed to the caller below
                box["error"] = exc
                return
            with late:
                if abandoned:
                    result[0].release()
                else:
                    box["result"] = result

        opener = threading.Thread(target=open_, daemon=True, name="uvc-open")
        opener.start()
        opener.join(self.open_timeout_s)
        with late:
            if "result" not in box and "error" not in box:
                abandoned = True
                raise CameraError(f"{self.name}: did not open within {self.open_timeout_s} s (the driver hangs)",
                                  device=self.name, kind="timeout")
        if "error" in box:
            raise box["error"]
        self._cap, self.settings_applied = box["result"]
        # no _guard.reset(): the frozen-frame history survives a reopen - a frame bit-identical
        # to the last one before it is the same hung buffer, not a fresh start

    def _open(self) -> tuple[object, dict[str, object]]:
        opened_at = time.monotonic()
        cap = cv2.VideoCapture(self.device, self.api_preference)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"{self.name}: cannot open (unplugged, wrong index/path or busy)",
                              device=self.name, kind="unplugged")
        req = self.requested
        applied: dict[str, object] = {}
        # the format before the size: V4L2 sizes and rates are per format, and a format set after
        # them may change them (what the driver runs is read back once all are set, below)
        fourcc = "YUYV" if self.pixel_format == "yuyv" else "MJPG" if self._mjpeg_undecoded else None
        if fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter_fourcc(*fourcc)))
        sizes = (("width", cv2.CAP_PROP_FRAME_WIDTH), ("height", cv2.CAP_PROP_FRAME_HEIGHT), ("fps", cv2.CAP_PROP_FPS))
        for key, prop in sizes:
            if req[key] is not None:
                cap.set(prop, float(req[key]))
        for key, prop in sizes:
            applied[key] = cap.get(prop) or None  # what the driver actually runs at
        if req["exposure"] is not None:
            # V4L2 convention: auto-exposure 1 = manual, 3 = aperture priority (auto).
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)
            cap.set(cv2.CAP_PROP_EXPOSURE, float(req["exposure"]))
            applied["exposure"] = cap.get(cv2.CAP_PROP_EXPOSURE)
        if self.buffer_size is not None:
            cap.set(cv2.CAP_PROP_BUFFERSIZE, float(self.buffer_size))
            applied["buffersize"] = cap.get(cv2.CAP_PROP_BUFFERSIZE) or None  # 0: backend ignores it
            # frames dropped before each read: every buffer the driver may hold, plus one. A driver
            # that ignores the buffer size keeps its default queue, and the 2 dropped then left a
            # frame taken before the press (or of the last piece's press) to be read as this one's
            queue = applied["buffersize"]
            queue = int(queue) if queue is not None and queue >= 1 else V4L2_DEFAULT_BUFFERS
            applied["flush_frames"] = max(self.flush_frames, queue + 1)
        if fourcc:
            # what the driver runs is read back, and a camera that keeps another format at this
            # size is refused in words: its frames would be refused one by one as bad JPEG or YUYV
            applied["pixel_format"] = runs = _fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
            if runs not in (None, fourcc):  # None: the backend does not say; the frames' size will
                cap.release()
                size = "x".join(str(int(v)) if v else "?" for v in (applied.get("width"), applied.get("height")))
                fix = ("set pixel_format: mjpeg, or a size it streams uncompressed" if fourcc == "YUYV" else
                       "set a size it streams as MJPEG (the bundle was trained on the camera's JPEG)")
                err = CameraError(f"{self.name}: the cell asks for {fourcc}, but the camera runs {runs} at {size} "
                                  f"(it does not offer {fourcc} there): {fix}", device=self.name, kind="corrupt")
                err.reason = "pixel_format"
                raise err
        if self.pixel_format == "yuyv":
            # uncompressed frames, taken raw and made BGR here (runtime/yuyv.py)
            applied["yuyv_raw"] = _raw_frames(cap)
        elif self._mjpeg_undecoded:
            # the JPEG bytes, not the frame the backend would decode at full size (module doc)
            applied["mjpeg_undecoded"] = _raw_frames(cap)
        applied["decode_scale"] = self.decode_scale  # 1/n: devices.camera.decode_scale for this bundle
        if self.warmup_s > 0:  # the next grab is a piece's no-contact reference: not one taken mid-ramp
            # inside the open's bound, whatever the open and the settings took: a camera that never
            # settles must not make every open a timeout
            left = self.open_timeout_s - WARMUP_OPEN_MARGIN_S - (time.monotonic() - opened_at)
            applied["warmup"] = settle(cap.read, min(self.warmup_s, max(left, 0.0)))
        return cap, applied

    def disconnect(self) -> None:
        if self._cap is not None:
            if self._reader is not None and self._reader.is_alive():
                self._reader.join(self.read_timeout_s)
            if self._reader is not None and self._reader.is_alive():
                # Releasing under a read still inside the driver can crash OpenCV: leave it.
                self._stuck.append(self._cap)
            else:
                self._cap.release()
        self._cap = None
        self._reader = None

    def _read_bounded(self) -> tuple[np.ndarray | None, float | None]:
        """(the frame read after the flush, or None; its capture time in monotonic s, or None when
        the driver gives none)."""
        if self._reader is not None and self._reader.is_alive():
            raise CameraError(f"{self.name}: the previous read is still stuck in the driver",
                              device=self.name, kind="timeout")
        box: dict = {}
        cap = self._cap

        flush = int(self.settings_applied.get("flush_frames") or self.flush_frames)
        asked_ms = 1e3 * time.monotonic()  # the press has settled: a frame taken before now is stale

        def taken_ms() -> float | None:
            t = _pos_ms(cap)
            if t is not None and abs(t - asked_ms) < CAPTURE_CLOCK_SLACK_MS:
                self._stamped = True  # the driver stamps with the monotonic clock (module constant's note)
            return t

        def stale(t: float | None) -> bool:  # taken before the grab was asked, or without a time
            return self._stamped and (t is None or t < asked_ms)

        def read() -> None:
            try:
                for _ in range(flush):
                    cap.grab()
                ok, image = cap.read()
                taken = taken_ms()
                # the driver's own capture times, once it has shown it gives them: frames it still held
                # from before the grab was asked, or handed without a time, are read past, whatever its
                # queue (the blind flush above is the floor)
                dropped = 0
                while ok and stale(taken) and dropped < MAX_STALE_DROPS:
                    ok, image = cap.read()
                    taken, dropped = taken_ms(), dropped + 1
                box.update(image=image if ok else None, taken_ms=taken, dropped=dropped)
            except Exception as exc:  # noqa: BLE001 - said by grab(), not lost in a thread's traceback
                box["error"] = exc

        self._reader = threading.Thread(target=read, daemon=True, name="uvc-read")
        self._reader.start()
        self._reader.join(self.read_timeout_s)
        if self._reader.is_alive():
            raise CameraError(f"{self.name}: no frame within {self.read_timeout_s} s", device=self.name,
                              kind="timeout")
        if "error" in box:  # the backend raised inside the read (cv2.error, ...): as a lost frame, named
            raise CameraError(f"{self.name}: the driver's read failed: {box['error']!r}", device=self.name,
                              kind="unplugged")
        self.stale_dropped += box.get("dropped", 0)
        taken = box.get("taken_ms")
        if box.get("image") is not None and stale(taken):
            what = ("one without a capture time" if taken is None else
                    f"one taken {asked_ms - taken:.0f} ms before the grab was asked (its capture time)")
            err = CameraError(f"{self.name}: {MAX_STALE_DROPS} more frames read after the flush, and the driver still "
                              f"hands {what}: a stale queue, never scored as this press", device=self.name,
                              kind="timeout")
            err.reason = "stale"
            raise err
        return box.get("image"), None if taken is None else taken / 1e3

    def grab(self) -> Frame:
        if self._cap is None:
            raise NotConnectedError(f"{self.name} used before connect()", device=self.name)
        image, taken = self._read_bounded()  # taken: the driver's capture time, or None (stamped when checked)
        if image is None:
            raise CameraError(f"{self.name}: no frame (unplugged or stream ended)", device=self.name,
                              kind="unplugged")
        if self.pixel_format == "yuyv" and (is_compressed(image) or _two_channel(image)):
            return self._guard.admit(self._from_yuyv(image), reduced_by=self.decode_scale, taken_s=taken)
        if self._mjpeg_undecoded and is_compressed(image):
            decoded = decode_jpeg(image, self.decode_scale)
            # a frame cut short in transit decodes with its lost part filled (runtime/jpeg_integrity.py)
            why = ("that do not decode as a JPEG (a truncated MJPEG frame?)" if decoded is None
                   else damaged_jpeg(image, decoded))
            self._refuse_damaged(why, f"{image.size} bytes")
            frame = self._guard.admit(decoded, reduced_by=self.decode_scale, taken_s=taken)
            if "mjpeg_quality" not in self.settings_applied:
                self._stream_quality(image)
            return frame
        if self.pixel_format == "mjpeg" and isinstance(image, np.ndarray) and image.ndim == 3:
            self._refuse_damaged(damaged_jpeg(None, image), "decoded by the backend,")  # its fill tells
        return self._guard.admit(image, taken_s=taken)  # decoded by the backend: a full frame (the fallback)

    @property
    def _mjpeg_undecoded(self) -> bool:
        """Whether the MJPEG stream is asked for and taken undecoded (decoded here at 1/decode_scale)."""
        return self.pixel_format == "mjpeg" and (self.decode_scale > 1 or self.take_mjpeg)

    def _refuse_damaged(self, why: str, what: str) -> None:
        if why:
            err = CameraError(f"{self.name} frame {self._guard.index}: {what} {why}", device=self.name, kind="corrupt")
            err.reason = "jpeg"
            raise err

    def _stream_quality(self, jpeg: np.ndarray) -> None:
        """The MJPEG quality of the first good frame since connect, from its quantisation table, into
        ``settings_applied["mjpeg_quality"]`` and told to ``on_stream_quality``: a header parse, no read."""
        q = estimate_quality(jpeg)
        self.settings_applied["mjpeg_quality"] = q.quality if q is not None else None
        if self.on_stream_quality is not None:
            try:
                self.on_stream_quality(self.settings_applied["mjpeg_quality"])
            except Exception:  # noqa: BLE001 - a log line must not cost the press its frame
                pass

    def _from_yuyv(self, raw: np.ndarray) -> np.ndarray:
        """A raw YUYV frame at the size the driver runs (else the configured one) -> BGR at
        1/decode_scale; a buffer of another length is a corrupt frame, named with both sizes."""
        applied = self.settings_applied
        hw = (applied.get("height"), applied.get("width"))
        if not all(hw):
            hw = self._guard.expected_hw or (None, None)
        image = decode_yuyv(raw, hw, self.decode_scale) if all(hw) else None
        if image is None:
            size = f"{int(hw[1])}x{int(hw[0])}" if all(hw) else "an unknown size (no width/height read back or configured)"
            err = CameraError(f"{self.name} frame {self._guard.index}: {raw.size} bytes, not a YUYV frame of {size} "
                              f"({BYTES_PER_PIXEL} bytes a pixel; a truncated frame, or the driver runs another format)",
                              device=self.name, kind="corrupt")
            err.reason = "yuyv"
            raise err
        return image


def _raw_frames(cap) -> bool:
    """Ask the backend for its frames as the driver hands them (CAP_PROP_CONVERT_RGB 0); did it take it?"""
    return bool(cap.set(cv2.CAP_PROP_CONVERT_RGB, 0.0) and cap.get(cv2.CAP_PROP_CONVERT_RGB) == 0)


def _two_channel(image: object) -> bool:
    """A backend's raw YUYV frame already shaped HxWx2 (not OpenCV's V4L2 backend, which hands one row)."""
    return isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 2


def _fourcc_text(code: float) -> str | None:
    """A FOURCC read back from the driver as its four letters (None when the backend says 0)."""
    n = int(code or 0)
    return "".join(chr((n >> (8 * i)) & 0xFF) for i in range(4)) if n else None


# --- replay -------------------------------------------------------------------------------

def _list_images(source: str | Path) -> list[Path]:
    path = Path(source)
    if path.is_dir():
        files = [p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
    else:
        files = [Path(p) for p in globmod.glob(str(source))
                 if Path(p).suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files)


class ReplayCamera(CameraBase):
    """Recorded frames through the camera interface: a video file, an image folder or a glob."""

    def __init__(self, source: str | Path, *, loop: bool = False, frozen_after: int = FROZEN_AFTER,
                 expected_hw: tuple[int, int] | None = None) -> None:
        self.source = str(source)
        self.name = f"replay {Path(self.source).name}"
        self.loop = loop
        self._guard = FrameGuard(self.name, expected_hw, frozen_after)
        self._files: list[Path] | None = None
        self._listed: list[Path] | None = None
        self._video = None
        self._pos = 0
        self._connected = False

    @property
    def is_video(self) -> bool:
        p = Path(self.source)
        return p.is_file() and p.suffix.lower() not in IMAGE_SUFFIXES

    def __len__(self) -> int:
        if self._files is not None:
            return len(self._files)
        if self._video is not None:
            return int(self._video.get(cv2.CAP_PROP_FRAME_COUNT))
        return 0

    def connect(self) -> None:
        """Open the recording; a reopen (the cell's camera retry) resumes where it stopped.

        A recording stands in for a live sensor, whose frames go on in time while it is
        reconnected: starting again at frame 0 would score the next pieces on the first
        piece's frames (and hit the same bad file again).
        """
        if self.is_video:
            video = cv2.VideoCapture(self.source)
            if not video.isOpened():
                raise CameraError(f"{self.name}: cannot open video {self.source}", device=self.name,
                                  kind="unplugged")
            w, h = int(video.get(cv2.CAP_PROP_FRAME_WIDTH)), int(video.get(cv2.CAP_PROP_FRAME_HEIGHT))
            if max(w, h) > MAX_IMAGE_SIDE_PX or w * h > MAX_IMAGE_PIXELS:  # from the container, not decoded
                video.release()
                raise CameraError(f"{self.name}: video frames of {w}x{h} px, over the {MAX_IMAGE_SIDE_PX} px a side "
                                  "this cell decodes", device=self.name, kind="corrupt")
            if self._pos:
                video.set(cv2.CAP_PROP_POS_FRAMES, self._pos)
            self._video = video
        else:
            # the list is taken once: a frame file that vanishes later is reported by name at its grab
            files = self._listed if self._listed is not None else _list_images(self.source)
            if not files:
                raise CameraError(f"{self.name}: no images at {self.source}", device=self.name,
                                  kind="unplugged")
            self._files = self._listed = files
        self._guard.reset()
        self._connected = True

    def disconnect(self) -> None:
        if self._video is not None:
            self._video.release()
        self._video, self._files, self._connected = None, None, False

    def _rewind(self) -> None:
        self._pos = 0
        if self._video is not None:
            self._video.set(cv2.CAP_PROP_POS_FRAMES, 0)

    def grab(self) -> Frame:
        if not self._connected:
            raise NotConnectedError(f"{self.name} used before connect()", device=self.name)
        for attempt in range(2):
            if self._video is not None:
                ok, image = self._video.read()
                where = f" (video frame {self._pos})"
                if ok:
                    self._pos += 1
                    return self._guard.admit(image, where)
            elif self._pos < len(self._files):
                path = self._files[self._pos]
                self._pos += 1
                try:
                    # as stored (grey, RGBA, 16-bit stay what they are, for the frame check to
                    # refuse); a FIFO or an oversized image is refused before it is read or decoded
                    image = read_image_file(path, self._guard.expected_hw)
                except InputRefused as exc:
                    raise self._guard.refuse(exc) from exc
                except OSError as exc:
                    problem = "cannot read" if path.exists() else "frame file missing:"
                    raise CameraError(f"{self.name}: {problem} {path} ({exc.strerror or exc})", device=self.name,
                                      kind="corrupt") from exc
                return self._guard.admit(image, f" ({path.name})")
            if not self.loop or attempt:
                break
            self._rewind()
        raise CameraError(f"{self.name}: end of the recording after {self._pos} frames", device=self.name,
                          kind="ended")


def camera_from_config(cam: dict, decode_scale: int = 1):
    """The live camera a config's ``devices.camera`` section describes (kind uvc or replay).

    ``cam`` is ``CellConfig.camera`` (validated by runtime/config.py, bounds in docs/cell.md);
    kind ``sim`` is built by the simulated cell, not here. ``decode_scale``: a UVC camera's MJPEG
    decode (runtime/wiring.py ``match_camera`` sets it from the bundle when the model is loaded).
    """
    if cam["kind"] == "uvc":
        dev = cam["device"]
        # frames of another size than the one configured are refused (the bundle was made for it)
        return UVCCamera(int(dev) if str(dev).isdigit() else dev, width=cam["width_px"], height=cam["height_px"],
                         fps=cam["fps"], exposure=cam["exposure"], read_timeout_s=cam["timeout_s"],
                         flush_frames=cam["flush_frames"], frozen_after=cam["frozen_after"],
                         expected_hw=(cam["height_px"], cam["width_px"]), decode_scale=decode_scale,
                         pixel_format=cam.get("pixel_format", "mjpeg"), warmup_s=cam.get("warmup_s", 0.0))
    if cam["kind"] == "replay":
        return ReplayCamera(cam["path"], frozen_after=cam["frozen_after"])
    raise ValueError(f"devices.camera.kind = {cam['kind']!r}: built by the simulated cell, not from a config")

"""Uncompressed UVC frames: YUYV 4:2:2, which most UVC cameras offer besides MJPEG.

An MJPEG frame costs the cell its JPEG decode on every press (0.6-0.9 ms for a 640x480 frame at
q95 on the bench's 2-core CPU, entropy decoding being the floor even at 1/8 scale) and loses the
fine texture the tactile trunk reads (docs/results/bench/jpeg_quality.md). A YUYV frame is two
bytes a pixel - a luma sample per pixel, one blue-difference and one red-difference sample per
pair of pixels - which OpenCV turns into BGR in one pass (``cv2.COLOR_YUV2BGR_YUYV``, BT.601 video
range, as UVC cameras send it). What is lost is the chroma's horizontal resolution and the
rounding of video range (219 luma levels), not the texture: the luma is every pixel's own.

640x480 YUYV at 30 fps is 18.4 MB/s, within USB 2.0 (a UVC camera's isochronous limit is ~24 MB/s);
a camera that does not offer it at the configured size and rate is told by ``settings_applied``.

* ``decode_yuyv``: the camera's raw bytes -> HxWx3 BGR at 1/n (``reduce_frame``: the box average
  training reduces its frames with, so a reduced-path bundle sees what it trained on);
* ``yuyv_bytes`` / ``through_camera_yuyv``: a lossless frame as such a camera would send / hand it
  (the bench prices the format's accuracy with it; tests build camera buffers with it).
"""

from __future__ import annotations

import cv2
import numpy as np

from vs2t_edge.runtime.preprocess import FrameError, check_frame, reduce_frame

BYTES_PER_PIXEL = 2


def decode_yuyv(data: bytes | np.ndarray, hw: tuple[int, int], factor: int = 1) -> np.ndarray | None:
    """The camera's YUYV frame (its raw bytes: flat, one row, or HxWx2) as HxWx3 uint8 BGR at
    1/``factor``, or None when it is not ``hw``'s size (a truncated or foreign buffer)."""
    h, w = int(hw[0]), int(hw[1])
    buf = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else np.asarray(data)
    if buf.dtype != np.uint8 or h < 1 or w < 2 or w % 2 or buf.size != h * w * BYTES_PER_PIXEL:
        return None
    return reduce_frame(cv2.cvtColor(buf.reshape(h, w, BYTES_PER_PIXEL), cv2.COLOR_YUV2BGR_YUYV), factor)


def yuyv_bytes(frame: np.ndarray, name: str = "frame") -> np.ndarray:
    """``frame`` (HxWx3 uint8 BGR, even width) as a UVC camera sends it in YUYV: HxWx2 uint8, BT.601
    video range (luma 16-235, chroma 16-240), each pixel pair's chroma averaged - the inverse of
    ``cv2.COLOR_YUV2BGR_YUYV`` up to that averaging and rounding."""
    frame = check_frame(frame, name=name)
    h, w = frame.shape[:2]
    if w % 2:
        raise FrameError(f"{name}: width {w} is odd; YUYV carries pixels in pairs", "size")
    b, g, r = (frame[..., i].astype(np.float32) for i in range(3))
    y = 0.299 * r + 0.587 * g + 0.114 * b
    u = (b - y) * np.float32(224.0 / 255.0 / 1.772) + 128.0
    v = (r - y) * np.float32(224.0 / 255.0 / 1.402) + 128.0
    out = np.empty((h, w, BYTES_PER_PIXEL), np.uint8)
    out[..., 0] = np.clip(np.rint(16.0 + y * np.float32(219.0 / 255.0)), 0, 255)
    out[:, 0::2, 1] = np.clip(np.rint((u[:, 0::2] + u[:, 1::2]) * 0.5), 0, 255)
    out[:, 1::2, 1] = np.clip(np.rint((v[:, 0::2] + v[:, 1::2]) * 0.5), 0, 255)
    return out


def through_camera_yuyv(frame: np.ndarray, scale: int = 1, name: str = "frame") -> np.ndarray:
    """``frame`` (lossless) as the cell's UVC camera hands it when it streams YUYV: sent as YUYV
    (``yuyv_bytes``), then made BGR at 1/``scale`` by ``decode_yuyv``, the cell's own conversion."""
    raw = yuyv_bytes(frame, name)
    out = decode_yuyv(raw, raw.shape[:2], scale)
    if out is None:  # cannot happen for a frame yuyv_bytes accepted; said rather than assumed
        raise FrameError(f"{name}: could not pass it through YUYV", "yuyv")
    return out


__all__ = ["BYTES_PER_PIXEL", "decode_yuyv", "yuyv_bytes", "through_camera_yuyv"]

"""A UVC camera's first frames after it opens: read past them until the picture holds still.

OpenCV's V4L2 backend starts the stream at the first read, and a camera on auto exposure (the
default: ``devices.camera.exposure`` absent) then ramps its exposure over its first frames. The
cell's first grab after an open is the next piece's no-contact reference, and every press of that
piece is scored and contact-checked against it: a reference taken mid-ramp is a global offset in
the model's input, and a ramp of about 10 % makes the untouched gel read as pressed
(docs/cell.md, "Camera warm-up"). So the camera reads frames after each open - the service's
start, the reopen before a retry, the operator's clear - until ``SETTLE_RUN`` + 1 consecutive
frames lie within ``SETTLE_LEVELS`` mean grey levels of each other, for at most ``limit_s``.

Numpy and OpenCV only: the cell runtime never imports torch.
"""

from __future__ import annotations

import time
from typing import Callable

import cv2
import numpy as np

WARMUP_MIN_FRAMES = 4  # read at least this many, settled or not (the stream's first frames)
SETTLE_RUN = 3  # consecutive frame-to-frame steps that must stay within SETTLE_LEVELS
SETTLE_LEVELS = 0.5  # mean grey levels: far above a frame mean's noise, far below a ramp's step
FAILED_READS = 3  # reads in a row without a readable frame that end the warm-up


def frame_level(image: object) -> float | None:
    """The mean grey level of a frame as the backend hands it: decoded BGR (every 4th pixel), MJPEG
    bytes (decoded at 1/8, grey: a fraction of a full decode), raw YUYV (its luma bytes), or None
    for what is none of these."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.size == 0:
        return None
    if image.ndim == 3 and image.shape[2] == 3:
        return float(image[::4, ::4].mean())
    if image.ndim == 3 and image.shape[2] == 2:  # YUYV as H x W x 2: Y is the first byte of each pair
        return float(image[::4, ::4, 0].mean())
    flat = image.reshape(-1)
    if flat.size > 2 and flat[0] == 0xFF and flat[1] == 0xD8:  # a JPEG's start of image
        grey = cv2.imdecode(flat, cv2.IMREAD_REDUCED_GRAYSCALE_8)
        return None if grey is None else float(grey.mean())
    return float(flat[::8].mean())  # raw YUYV bytes: every 8th is a luma byte


def settle(read: Callable[[], tuple[bool, object]], limit_s: float,
           clock: Callable[[], float] = time.monotonic) -> dict:
    """Read frames with ``read()`` (``cv2.VideoCapture.read``) until the last ``SETTLE_RUN`` + 1
    frames' mean levels span at most ``SETTLE_LEVELS`` (after at least ``WARMUP_MIN_FRAMES``), or
    ``limit_s`` has passed, or ``FAILED_READS`` reads in a row gave no readable frame (the grab that
    follows says why). A failed read or an undecodable frame alone - common as a stream starts - is
    read past, and breaks the run of steady frames. What happened, for
    ``settings_applied["warmup"]`` (journaled in the start record, logged as ``camera runs:``):
    frames read, settled or not, the last level, and the seconds it took."""
    start, run, frames, failed, first, last, why = clock(), [], 0, 0, None, None, "time limit"
    while True:
        ok, image = read()
        level = frame_level(image) if ok else None
        if level is None:
            failed, run = failed + 1, []  # a steady run must be unbroken
            if failed >= FAILED_READS:
                why = "no frame" if not ok or image is None else "unreadable frames"
                break
        else:
            failed, frames, last = 0, frames + 1, level
            first = level if first is None else first
            run = (run + [level])[-(SETTLE_RUN + 1):]
            if frames >= WARMUP_MIN_FRAMES and len(run) == SETTLE_RUN + 1 and max(run) - min(run) <= SETTLE_LEVELS:
                return {"frames": frames, "settled": True, "level": round(level, 2),
                        "seconds": round(clock() - start, 3)}
        if clock() - start >= limit_s:
            break
    out = {"frames": frames, "settled": False, "why": why, "seconds": round(clock() - start, 3)}
    if first is not None:
        out["level"], out["level_first"] = round(last, 2), round(first, 2)
    return out


__all__ = ["frame_level", "settle", "WARMUP_MIN_FRAMES", "SETTLE_RUN", "SETTLE_LEVELS", "FAILED_READS"]

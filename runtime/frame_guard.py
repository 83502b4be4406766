"""The one guard every camera's grab goes through - the UVC and replay cameras
(runtime/camera.py), the simulated one (vs2t_edge.sim.devices) and the bench's press timing - so
the loop cannot tell them apart: ``check_frame`` from the runtime (dtype, size, NaN, black, white,
saturated) and frozen-frame detection (the same frame ``frozen_after`` times in a row: a hung
driver hands out its last buffer again; a live sensor's noise never repeats bit for bit). The
default, 2, raises ``CameraFrozen`` at the first frame identical to the one before it, so a frozen
frame is never handed to the model (config ``devices.camera.frozen_after``). A refused frame is a
``CameraError`` of kind ``corrupt`` naming the check (``reason``). Also the context-manager
plumbing the cameras share (``CameraBase``)."""

from __future__ import annotations

import time

import numpy as np

from vs2t_edge.runtime.devices import CameraError, CameraFrozen, Frame
from vs2t_edge.runtime.files import InputRefused
from vs2t_edge.runtime.preprocess import FrameError, check_frame, reduced_hw

FROZEN_AFTER = 2  # identical consecutive frames that are a frozen camera: the first repeat


class FrameGuard:
    """Checks shared by every camera: frame sanity, frozen frames, running index, timestamp.
    Public because the simulated camera (vs2t_edge.sim.devices) must admit frames by the same rule."""

    def __init__(self, name: str, expected_hw: tuple[int, int] | None, frozen_after: int) -> None:
        if frozen_after < 2:
            raise ValueError(f"{name}: frozen_after must be at least 2, got {frozen_after}")
        self.name = name
        self.expected_hw = tuple(expected_hw) if expected_hw is not None else None
        self.frozen_after = frozen_after
        self._last: np.ndarray | None = None
        self._repeats = 1
        self.index = 0

    def reset(self) -> None:
        self._last, self._repeats = None, 1

    def refuse(self, exc: FrameError | InputRefused) -> CameraError:
        err = CameraError(str(exc), device=self.name, kind="corrupt")
        err.reason = exc.reason  # the precise check that failed (black, size, shape, dtype, ...)
        return err

    def admit(self, image: object, where: str = "", reduced_by: int = 1, taken_s: float | None = None) -> Frame:
        """``reduced_by``: the camera decoded the frame at 1/n scale (its size is checked at that scale).
        ``taken_s``: the driver's capture time (monotonic s) when it gives one; else the frame is
        stamped when admitted."""
        hw = self.expected_hw if self.expected_hw is None or reduced_by == 1 else reduced_hw(self.expected_hw, reduced_by)
        try:
            image = check_frame(image, hw, name=f"{self.name} frame {self.index}{where}")
        except FrameError as exc:
            raise self.refuse(exc) from exc
        if self._last is not None and _same_image(image, self._last):
            self._repeats += 1
            if self._repeats >= self.frozen_after:
                raise CameraFrozen(f"{self.name}: the same frame {self._repeats} times in a row (bit for bit; "
                                   "a live sensor's noise never repeats); the camera is frozen",
                                   device=self.name, kind="frozen")
        else:
            self._repeats = 1
        self._last = image
        frame = Frame(image=image, timestamp_s=time.monotonic() if taken_s is None else taken_s, index=self.index,
                      reduced_by=reduced_by)
        self.index += 1
        return frame


_PRECHECK_ROW_STRIDE = 16  # rows of the frozen-frame pre-check (every 16th row: 1/16 of the bytes)


def _same_image(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit-identical frames? The middle row's bytes first, then every 16th row: two live frames'
    noise differs there already, so the full comparison (a pass over both frames, cold after the
    trunk's run: 0.1 ms of the per-press budget) only runs for a frame that may be frozen. The
    verdict is the full one's (for uint8 frames equal bytes are equal values). The one row as bytes,
    without numpy's comparison: 0.055 -> 0.010 ms a press on a 320x240 frame after the trunk."""
    if a.shape != b.shape:
        return False
    mid = a.shape[0] // 2
    if a.dtype == b.dtype == np.uint8 and a.size and a[mid].tobytes() != b[mid].tobytes():
        return False
    if not np.array_equal(a[::_PRECHECK_ROW_STRIDE], b[::_PRECHECK_ROW_STRIDE]):
        return False
    return bool(np.array_equal(a, b))


class CameraBase:
    """Context-manager plumbing shared by the cameras (and the simulated one in vs2t_edge.sim)."""

    name = "camera"

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()


__all__ = ["FROZEN_AFTER", "FrameGuard", "CameraBase"]

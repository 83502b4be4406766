"""Is the gel pressed? A press frame against the item's no-contact reference frame.

:class:`ContactCheck` answers it from the per-pixel change, box-averaged so that sensor noise
cancels while an imprint stays; the cell refuses a press frame that is still the reference (a
piece missing, a wrong height, a stale frame: runtime/cell.py, config ``devices.camera.contact_check``).
:func:`capture_reference` takes a session's no-contact frame as the median of several grabs,
refused if something touched the gel meanwhile. Out of runtime/camera.py, which captures frames
and checks them as frames; this compares two of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vs2t_edge.runtime.devices import CameraError
from vs2t_edge.runtime.preprocess import centre_square


@dataclass(frozen=True)
class ContactReading:
    pressed: bool
    area_fraction: float  # of pixels that changed by more than the threshold
    peak_levels: float  # largest locally averaged change, grey levels
    model_area_fraction: float | None = None  # the same inside the square the model sees (``crop_fraction``)


@dataclass(frozen=True)
class ContactCheck:
    """Is the gel pressed? Compares a frame with the session's no-contact reference.

    The per-pixel change (largest over the three channels) is averaged over a small window so
    that sensor noise cancels while an imprint (a few mm, tens of pixels) stays; the gel counts
    as pressed when enough of the image changed by more than ``threshold_levels``. A global
    lighting drift of a few levels stays under the threshold.

    ``crop_fraction`` (the bundle's: the centred square of the shorter side the model reads): the
    imprint must also cover ``min_area_fraction`` of that square. A press whose imprint falls only
    in the bands beside it (a piece's edge under the gel's side) shows the model an untouched gel,
    which no class was trained on and which scores as whatever fabric lies nearest.
    """

    threshold_levels: float = 12.0
    min_area_fraction: float = 0.005
    window_px: int = 5
    crop_fraction: float | None = None

    def difference(self, frame: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """HxW float32: the largest change over the channels, box-averaged over ``window_px``."""
        return self._window_sums(frame, reference) * np.float32(1.0 / self.window_px ** 2)

    def _window_sums(self, frame: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """HxW sums (exact integers; uint16, or float32 for windows over 16 px) of the largest change
        over the channels, per window.

        In OpenCV on uint8 (absdiff, a max over the planes, an unnormalised box filter): 0.1 ms
        instead of the 20 ms of the int16/numpy form it replaced on a 640x480 frame (it runs on
        every press of a UVC cell); sums of integers, so "the window's mean is over the threshold"
        is decided exactly, where the float mean could round either way on a tie."""
        if frame.shape != reference.shape:
            raise ValueError(f"frame {frame.shape} and no-contact reference {reference.shape} differ in size")
        k = (self.window_px, self.window_px)
        if frame.dtype == np.uint8 and reference.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3:
            # uint16 sums while a window's can't overflow (255 * 16^2 < 2^16): the same integers in
            # half the bytes of float32, 0.08 ms less a press on a 320x240 frame after the trunk's run
            depth = cv2.CV_16U if 255 * self.window_px ** 2 < 2 ** 16 else cv2.CV_32F
            return cv2.boxFilter(_channel_max(cv2.absdiff(frame, reference)), depth, k, normalize=False)
        diff = np.abs(frame.astype(np.int32) - reference.astype(np.int32)).max(axis=2).astype(np.float32)
        return cv2.boxFilter(diff, cv2.CV_32F, k, normalize=False)

    def read(self, frame: np.ndarray, reference: np.ndarray) -> ContactReading:
        sums = self._window_sums(frame, reference)
        n = self.window_px ** 2
        changed = cv2.compare(sums, float(self.threshold_levels) * n, cv2.CMP_GT)
        area = cv2.countNonZero(changed) / sums.size
        seen = None
        if self.crop_fraction is not None:
            square = changed[centre_square(changed.shape, self.crop_fraction)]
            seen = cv2.countNonZero(square) / square.size
        pressed = area >= self.min_area_fraction and (seen is None or seen >= self.min_area_fraction)
        return ContactReading(pressed=pressed, area_fraction=area, peak_levels=float(cv2.minMaxLoc(sums)[1]) / n,
                              model_area_fraction=seen)

    def is_pressed(self, frame: np.ndarray, reference: np.ndarray) -> bool:
        return self.read(frame, reference).pressed


_THREE = np.ones((1, 3), np.uint8)


def _channel_max(image: np.ndarray) -> np.ndarray:
    """HxW uint8: the largest of each pixel's three channels (HxWx3 uint8, C-contiguous). The row
    of interleaved channels, grown by a 1x3 window anchored at its left, holds at column 3x the
    largest of pixel x's three bytes; INTER_NEAREST at a third of the width reads exactly columns
    3x. Two OpenCV calls: half the time of splitting the planes and taking two maxima."""
    h, w = image.shape[:2]
    grown = cv2.dilate(image.reshape(h, w * 3), _THREE, anchor=(0, 0))
    return cv2.resize(grown, (w, h), interpolation=cv2.INTER_NEAREST)


def capture_reference(camera, n_frames: int = 5, check: ContactCheck | None = None) -> np.ndarray:
    """The session's no-contact frame: the median of n grabs, refused if the gel moved meanwhile."""
    if n_frames < 1:
        raise ValueError("n_frames must be at least 1")
    frames = [camera.grab().image for _ in range(n_frames)]
    reference = np.median(np.stack(frames), axis=0).astype(np.uint8)
    check = check or ContactCheck()
    for i, image in enumerate(frames):
        if check.is_pressed(image, reference):
            raise CameraError(f"no-contact reference: frame {i} of {n_frames} differs from the others; "
                              "something touches the gel", device=getattr(camera, "name", "camera"),
                              kind="corrupt")
    return reference

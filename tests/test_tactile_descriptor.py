"""runtime/tactile_descriptor.py: the no-network tactile feature the cell and `real-check` share -
fixed length whatever the frame, the marker dots' sub-pixel shift against the item's no-contact
frame, exposure cancelled, and the frame checks of the one preprocessing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vs2t_edge.runtime import tactile_descriptor as td
from vs2t_edge.runtime.preprocess import FrameError


def _gel(hw=(160, 120), shift=(0.0, 0.0), gain=1.0, dots=True) -> np.ndarray:
    """A gel frame: a colour gradient, a 4 x 3 (or 3 x 4) grid of dark dots, moved by ``shift`` px."""
    h, w = hw
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([150 + 30 * xx / w, 120 + 20 * yy / h, 170 - 20 * xx / w], -1)
    if dots:
        pitch = min(h, w) // 3
        for cy in range(pitch // 2, h, pitch):
            for cx in range(pitch // 2, w, pitch):
                cv2.circle(img, (cx * 16, cy * 16), 5 * 16, (40, 40, 40), -1, shift=4)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    img = cv2.warpAffine(img, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (w, h), borderMode=cv2.BORDER_REPLICATE)
    return np.clip(img * gain, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("hw", [(160, 120), (120, 160), (400, 300)])
def test_fixed_length_float32_whatever_the_frame(hw):
    x = td.shading_markers(_gel(hw), _gel(hw))
    assert x.shape == (td.DIM["shading_markers"],) == (240,) and x.dtype == np.float32
    assert np.all(np.isfinite(x))


def test_displacement_is_the_dots_sub_pixel_shift_against_the_reference():
    """Every dot moved 0.4 px right and 0.2 px down: each cell holding a dot says so, the rest 0."""
    ref, moved = _gel(), _gel(shift=(0.4, 0.2))
    d = td.marker_displacement(moved, td.prepare_reference(ref)).reshape(-1, 2)
    has_dot = np.bincount(td.prepare_reference(ref).cell, minlength=td.GRID_CELLS) > 0
    assert has_dot.sum() == 12
    assert np.allclose(d[has_dot], [0.4, 0.2], atol=0.1)
    assert np.all(d[~has_dot] == 0)
    assert np.allclose(td.marker_displacement(ref, td.prepare_reference(ref)), 0, atol=1e-9)


def test_prepared_reference_gives_what_the_raw_one_gives():
    ref, frame = _gel(), _gel(shift=(0.3, -0.5))
    assert np.array_equal(td.shading_markers(frame, ref), td.shading_markers(frame, td.prepare_reference(ref)))


def test_exposure_is_cancelled_and_an_unmarked_gel_gives_no_displacement():
    ref = _gel()
    a, b = td.shading_markers(_gel(), ref), td.shading_markers(_gel(gain=1.1), ref)
    assert np.abs(a - b).max() < 0.02  # log colour and px
    plain = td.shading_markers(_gel(dots=False), _gel(dots=False))
    assert np.all(plain[144:] == 0)


def test_bad_frames_are_refused_as_the_cell_refuses_them():
    with pytest.raises(FrameError) as e:
        td.shading_markers(_gel((160, 120)), _gel((120, 160)))
    assert e.value.reason == "size"
    with pytest.raises(FrameError) as e:
        td.shading_markers(np.zeros((160, 120, 3), np.uint8), _gel())
    assert e.value.reason == "black"
    with pytest.raises(FrameError):
        td.prepare_reference(np.full((160, 120), 128, np.uint8))

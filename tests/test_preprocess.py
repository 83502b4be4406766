"""The one preprocessing: the cell's per-item prepared reference gives what training computes
from the raw reference, and both equal the textbook order (difference, crop, resize)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vs2t_edge.runtime.preprocess import FrameError, TactilePreprocess, prepare_reference, preprocess_tactile


def _textbook(frame, reference, spec):
    """diff -> crop -> resize -> scale, in float64: the definition the fast path must match."""
    image = frame.astype(np.float64) - reference.astype(np.float64)
    h, w = image.shape[:2]
    side = max(1, int(round(min(h, w) * spec.crop_fraction)))
    y0, x0 = (h - side) // 2, (w - side) // 2
    image = cv2.resize(image[y0:y0 + side, x0:x0 + side], (spec.size, spec.size), interpolation=cv2.INTER_AREA)
    image = (image[..., ::-1] / 255.0 - np.asarray(spec.mean)) / np.asarray(spec.std)
    return image.transpose(2, 0, 1)


@settings(max_examples=25, deadline=None)
@given(h=st.integers(20, 120), w=st.integers(20, 160), size=st.sampled_from([8, 16, 32]),
       crop=st.sampled_from([1.0, 0.8, 0.5]), seed=st.integers(0, 2**31 - 1))
def test_prepared_reference_equals_raw_reference_and_the_textbook_order(h, w, size, crop, seed):
    rng = np.random.default_rng(seed)
    frame = rng.integers(10, 245, (h, w, 3), dtype=np.uint8)
    reference = rng.integers(10, 245, (h, w, 3), dtype=np.uint8)
    spec = TactilePreprocess(size=size, crop_fraction=crop, mean=(0.01, -0.02, 0.0), std=(0.08, 0.1, 0.05))
    raw = preprocess_tactile(frame, reference, spec)
    prepared = preprocess_tactile(frame, prepare_reference(reference, spec), spec)
    assert raw.dtype == np.float32 and raw.shape == (3, size, size)
    np.testing.assert_array_equal(raw, prepared)  # train (raw) and serve (prepared) are bit-identical
    np.testing.assert_allclose(raw, _textbook(frame, reference, spec), atol=2e-4)  # resizing is linear


def test_reference_of_another_size_or_spec_is_refused():
    rng = np.random.default_rng(0)
    spec = TactilePreprocess(size=16)
    frame = rng.integers(10, 245, (48, 64, 3), dtype=np.uint8)
    small_ref = prepare_reference(rng.integers(10, 245, (24, 32, 3), dtype=np.uint8), spec)
    with pytest.raises(FrameError, match="frame: size 64x48 does not match the no-contact reference frame's 32x24"):
        preprocess_tactile(frame, small_ref, spec)
    other = prepare_reference(rng.integers(10, 245, (48, 64, 3), dtype=np.uint8), TactilePreprocess(size=8))
    with pytest.raises(ValueError, match="another preprocessing"):
        preprocess_tactile(frame, other, spec)
    with pytest.raises(FrameError, match="all black"):
        prepare_reference(np.zeros((48, 64, 3), np.uint8), spec)


def test_saturation_counts_pixels_per_channel():
    frame = np.full((40, 40, 3), 120, np.uint8)
    frame[:, :21, 2] = 255  # 52.5% of one channel clipped: refused
    with pytest.raises(FrameError, match="saturated"):
        preprocess_tactile(frame, None, TactilePreprocess(size=8, use_reference=False))
    frame[:, 19:21, 2] = 120  # 47.5%: a bright but usable frame
    assert np.isfinite(preprocess_tactile(frame, None, TactilePreprocess(size=8, use_reference=False))).all()

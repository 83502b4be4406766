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


# --- real GelSight options (issue 13): off by default, the same path for frame and reference ----------


def _gel_frame(seed: int = 0, gain: float = 1.0) -> np.ndarray:
    """An LED-lit gel with a 4 x 3 grid of dark marker dots."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:96, 0:72]
    img = np.stack([110 + 30 * xx / 72, 90 + 40 * yy / 96, 130 - 20 * xx / 72], -1) + rng.normal(0, 2, (96, 72, 3))
    img *= gain
    for cy in range(12, 96, 24):
        for cx in range(12, 72, 24):
            cv2.circle(img, (cx, cy), 4, (25, 25, 25), -1)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_real_sensor_options_are_off_by_default_and_round_trip_a_manifest():
    spec = TactilePreprocess()
    assert not spec.inpaint_markers and not spec.normalise_exposure
    on = TactilePreprocess(size=16, inpaint_markers=True, normalise_exposure=True)
    assert TactilePreprocess.from_dict(on.to_dict()) == on
    old = {k: v for k, v in on.to_dict().items() if k not in ("inpaint_markers", "normalise_exposure")}
    assert TactilePreprocess.from_dict(old) == TactilePreprocess(size=16)  # a bundle from before: both off


def test_exposure_normalisation_cancels_a_gain_and_inpainting_removes_the_dots():
    """Without a reference: a 6 % brighter exposure changes the plain input and not the normalised
    one; with markers inpainted, the dots are gone from the input. With a reference, the prepared
    reference takes the same path as the raw one."""
    frame, brighter = _gel_frame(), _gel_frame(gain=1.06)
    plain = TactilePreprocess(size=24, use_reference=False)
    fixed = TactilePreprocess(size=24, use_reference=False, normalise_exposure=True)

    def gap(spec):
        return np.abs(preprocess_tactile(brighter, None, spec) - preprocess_tactile(frame, None, spec)).mean()

    assert gap(fixed) < 0.15 * gap(plain)
    inpainted = TactilePreprocess(size=72, crop_fraction=1.0, use_reference=False, inpaint_markers=True, std=(1, 1, 1))
    x = preprocess_tactile(frame, None, inpainted)
    assert x.min() * 255 > 60  # the 25-grey dots are filled from the gel around them
    both = TactilePreprocess(size=24, inpaint_markers=True, normalise_exposure=True)
    ref = _gel_frame(seed=1)
    np.testing.assert_array_equal(preprocess_tactile(brighter, ref, both),
                                  preprocess_tactile(brighter, prepare_reference(ref, both), both))
    # the press differs from its reference by the exposure only: nearly nothing is left
    assert np.abs(preprocess_tactile(brighter, ref, both)).mean() < 0.2 * np.abs(
        preprocess_tactile(brighter, ref, TactilePreprocess(size=24))).mean()

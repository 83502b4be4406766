"""The one preprocessing: the cell's per-item prepared reference gives what training computes
from the raw reference, and both equal the textbook order (difference, crop, resize)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vs2t_edge.runtime.preprocess import (FrameError, TactilePreprocess, auto_reduce, decode_jpeg, prepare_reference,
                                          preprocess_batch, preprocess_tactile, reduce_frame)


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


# --- the float path keeps every earlier bundle's numbers; the reduced uint8 path ---------------------


def _float_path_before(frame, reference, spec):
    """The float path exactly as it was written before the reduced path came (whole-array scaling)."""
    def crop_resize(image):
        h, w = image.shape[:2]
        side = max(1, int(round(min(h, w) * spec.crop_fraction)))
        y0, x0 = (h - side) // 2, (w - side) // 2
        crop = image[y0:y0 + side, x0:x0 + side].astype(np.float32)
        return cv2.resize(crop, (spec.size, spec.size), interpolation=cv2.INTER_AREA)

    image = crop_resize(frame) - crop_resize(reference)
    image = image[..., ::-1] * np.float32(1.0 / 255.0)
    image = (image - np.asarray(spec.mean, np.float32)) / np.asarray(spec.std, np.float32)
    return np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32)


def _frames(h=120, w=160, seed=0):
    rng = np.random.default_rng(seed)
    ref = cv2.GaussianBlur(rng.integers(40, 220, (h, w, 3), dtype=np.uint8), (5, 5), 0)
    frame = np.clip(ref.astype(int) + rng.integers(-25, 26, (h, w, 3)), 0, 255).astype(np.uint8)
    return frame, ref


@pytest.mark.parametrize("size,crop", [(32, 1.0), (128, 1.0), (24, 0.7)])
def test_float_path_is_bit_identical_to_what_it_was(size, crop):
    frame, ref = _frames(240, 320)
    spec = TactilePreprocess(size=size, crop_fraction=crop, mean=(0.01, -0.02, 0.0), std=(0.08, 0.1, 0.05))
    before = _float_path_before(frame, ref, spec)
    np.testing.assert_array_equal(preprocess_tactile(frame, ref, spec), before)
    np.testing.assert_array_equal(preprocess_tactile(frame, prepare_reference(ref, spec), spec), before)


def test_reduce_is_off_by_default_and_absent_from_old_manifests():
    d = TactilePreprocess(size=128).to_dict()
    assert "reduce" not in d  # a float-path bundle's manifest is what it was
    assert TactilePreprocess.from_dict(d).reduce == 0
    new = TactilePreprocess(size=128, reduce=2)
    assert new.to_dict()["reduce"] == 2 and TactilePreprocess.from_dict(new.to_dict()) == new
    for bad in (3, -1, True, 16, 2.0):
        with pytest.raises(ValueError, match="reduce"):
            TactilePreprocess(size=128, reduce=bad)
    with pytest.raises(ValueError, match="inpaint_markers"):
        TactilePreprocess(size=128, reduce=2, inpaint_markers=True)


def test_auto_reduce_keeps_at_least_the_input_size_across_the_crop():
    assert auto_reduce((480, 640), 128) == 2 and auto_reduce((480, 640), 224) == 2
    assert auto_reduce((240, 320), 128) == 1 and auto_reduce((480, 640), 96) == 4
    assert auto_reduce((480, 640), 60) == 8 and auto_reduce((100, 100), 224) == 1


@pytest.mark.parametrize("reduce,size", [(1, 32), (2, 32), (2, 56), (4, 24)])
def test_reduced_path_train_and_serve_are_one_function(reduce, size):
    frame, ref = _frames(120, 160, seed=reduce)
    spec = TactilePreprocess(size=size, reduce=reduce, mean=(0.01, -0.02, 0.0), std=(0.08, 0.1, 0.05))
    train = preprocess_batch([frame], ref, spec)[0]  # what training's feature extraction runs
    cell = preprocess_tactile(frame, prepare_reference(ref, spec), spec)  # the cell: reference once per item
    assert train.shape == (3, size, size) and train.dtype == np.float32
    np.testing.assert_array_equal(train, cell)
    np.testing.assert_array_equal(train, preprocess_tactile(frame, ref, spec))
    # a frame the camera already reduced by the same function gives the same numbers
    small, small_ref = reduce_frame(frame, reduce), reduce_frame(ref, reduce)
    got = preprocess_tactile(small, prepare_reference(small_ref, spec, reduce), spec, reduced_by=reduce) \
        if reduce > 1 else preprocess_tactile(small, small_ref, spec)
    np.testing.assert_array_equal(train, got)
    # the definition: reduce (box), crop, uint8 linear resize, difference, scale
    def side(img):
        img = cv2.resize(img, ((160 + reduce - 1) // reduce, (120 + reduce - 1) // reduce),
                         interpolation=cv2.INTER_AREA) if reduce > 1 else img
        h, w = img.shape[:2]
        s0 = min(h, w)
        y0, x0 = (h - s0) // 2, (w - s0) // 2
        return cv2.resize(img[y0:y0 + s0, x0:x0 + s0], (size, size), interpolation=cv2.INTER_LINEAR).astype(np.float64)
    want = ((side(frame) - side(ref))[..., ::-1] / 255.0 - np.asarray(spec.mean)) / np.asarray(spec.std)
    np.testing.assert_allclose(train, want.transpose(2, 0, 1), atol=1e-4)


def _reduced_before(frame, ref, spec):
    """The reduced path as it was before its scaling became one OpenCV call: float32 difference,
    then per RGB plane diff * (1 / (255 std)) - mean / std."""
    def side(img):
        img = reduce_frame(img, spec.reduce)
        h, w = img.shape[:2]
        s0 = min(h, w)
        y0, x0 = (h - s0) // 2, (w - s0) // 2
        return cv2.resize(img[y0:y0 + s0, x0:x0 + s0], (spec.size, spec.size), interpolation=cv2.INTER_LINEAR)
    image = side(frame).astype(np.float32)
    if ref is not None:
        image -= side(ref).astype(np.float32)
    out = np.empty((3, spec.size, spec.size), np.float32)
    mean, std = np.asarray(spec.mean, np.float32), np.asarray(spec.std, np.float32)
    for c in range(3):
        np.multiply(image[:, :, 2 - c], np.float32(1.0) / (np.float32(255.0) * std[c]), out=out[c])
        np.subtract(out[c], mean[c] / std[c], out=out[c])
    return out


@pytest.mark.parametrize("reduce,size,std", [(1, 32, 0.08), (2, 56, 0.08), (4, 24, 0.08), (2, 40, 0.0731),
                                             (2, 40, 1.0)])
@pytest.mark.parametrize("use_reference", [True, False])
def test_reduced_path_one_call_scaling_is_the_per_plane_scaling_bit_for_bit(reduce, size, std, use_reference):
    """mean 0 and one std for all channels (every bundle's) and other specs: the scaling over the
    whole tensor (runtime/preprocess.py ``_scaled_chw``) gives the very floats of the per-plane loop."""
    frame, ref = _frames(120, 160, seed=size)
    spec = TactilePreprocess(size=size, reduce=reduce, std=(std,) * 3, use_reference=use_reference)
    got = preprocess_tactile(frame, prepare_reference(ref, spec) if use_reference else None, spec)
    want = _reduced_before(frame, ref if use_reference else None, spec)
    assert got.shape == want.shape and got.dtype == want.dtype and got.flags.c_contiguous
    np.testing.assert_array_equal(got, want)
    assert np.ptp(got) > 0
    other = TactilePreprocess(size=size, reduce=reduce, std=(std, std, std * 1.5), mean=(0.0, 0.01, 0.0),
                              use_reference=use_reference)
    np.testing.assert_array_equal(preprocess_tactile(frame, ref if use_reference else None, other),
                                  _reduced_before(frame, ref if use_reference else None, other))


def test_the_mjpeg_cameras_scaled_decode_adds_little_to_the_gap_mjpeg_already_makes():
    """Training reads lossless frames; a UVC camera hands MJPEG. On the float path the camera's full
    decode already differs from training's pixels (JPEG loss); on the reduced path the camera hands
    libjpeg's 1/2 decode where training box-averages: the gap may grow by at most half (demo world
    at 640x480, 18 presses: 0.90 -> 1.08 grey levels mean, p99 4.2 -> 4.3; this rendered press:
    0.90 -> 1.08, p99 3.8 -> 4.0)."""
    from frame_fixtures import rendered_press_jpeg

    frame, ref, jpeg = rendered_press_jpeg()

    def gap(spec, scale):
        small = [decode_jpeg(j, scale) for j in jpeg]
        served = preprocess_tactile(small[0], prepare_reference(small[1], spec, scale), spec, reduced_by=scale)
        trained = preprocess_tactile(frame, ref, spec)
        return np.abs(served - trained) * np.asarray(spec.std)[:, None, None] * 255  # grey levels

    before, after = gap(TactilePreprocess(size=128), 1), gap(TactilePreprocess(size=128, reduce=2), 2)
    assert decode_jpeg(jpeg[0], 2).shape == (240, 320, 3)
    assert before.mean() > 0.3  # the JPEG loss is there to compare with
    assert after.mean() < 1.5 * before.mean() and np.percentile(after, 99) < 1.5 * np.percentile(before, 99)


def test_reduced_frames_are_refused_by_name_where_they_do_not_belong():
    frame, ref = _frames(120, 160)
    small = reduce_frame(frame, 2)
    reduced = TactilePreprocess(size=32, reduce=2)
    with pytest.raises(FrameError) as exc:  # the camera decoded at 1/4, the bundle takes 1/2
        preprocess_tactile(reduce_frame(frame, 4), prepare_reference(ref, reduced), reduced, reduced_by=4)
    assert exc.value.reason == "scale"
    with pytest.raises(FrameError) as exc:  # a float-path bundle correcting a real GelSight takes only full frames
        preprocess_tactile(small, ref, TactilePreprocess(size=32, normalise_exposure=True), reduced_by=2)
    assert exc.value.reason == "scale"
    with pytest.raises(FrameError) as exc:  # a reduced frame against a full-size reference: named by size
        preprocess_tactile(small, ref, TactilePreprocess(size=32), reduced_by=2)
    assert exc.value.reason == "size"
    with pytest.raises(FrameError, match="does not match the no-contact reference frame's 80x60") as exc:
        preprocess_tactile(reduce_frame(small, 2), prepare_reference(ref, reduced), reduced, reduced_by=2)
    for bad, reason in ((np.zeros_like(small), "black"), (np.full_like(small, 255), "white"),
                        (small.astype(np.float32), "dtype"), (small[..., 0], "shape")):
        with pytest.raises(FrameError) as exc:
            preprocess_tactile(bad, prepare_reference(ref, reduced), reduced, reduced_by=2)
        assert exc.value.reason == reason
    assert decode_jpeg(b"\xff\xd8 not a jpeg", 2) is None and decode_jpeg(b"", 1) is None

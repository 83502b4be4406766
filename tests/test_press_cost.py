"""The per-press work outside the trunk made cheaper (issue 14) decides exactly as before: each
faster form is compared here with the plain form it replaced, on rendered GelSight frames and on
crafted edge cases."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from frame_fixtures import rendered_press_jpeg
from test_item_rule import _offset, _world
from test_jpeg_integrity import cut_short
from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.evidence import Evidence
from vs2t_edge.runtime.frame_guard import _same_image
from vs2t_edge.runtime.jpeg_integrity import EOI, FILLED_TAIL, JPEG_FILL, TAIL_BYTES, ends_with_eoi, filled_bottom_row
from vs2t_edge.runtime.preprocess import TactilePreprocess, decode_jpeg, prepare_reference, preprocess_tactile


# --- runtime/jpeg_integrity.py: the fast answers for a frame's usual end ----------------------

def _ends_with_eoi_scan(data) -> bool:
    """``ends_with_eoi`` as it was: the last nonzero byte searched for, every time."""
    flat = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray)) else np.asarray(data, np.uint8).ravel()
    nonzero = np.flatnonzero(flat[-TAIL_BYTES:])
    offset = max(0, flat.size - TAIL_BYTES)
    if nonzero.size == 0:
        nonzero, offset = np.flatnonzero(flat), 0
        if nonzero.size == 0:
            return False
    end = offset + int(nonzero[-1]) + 1
    return end >= 2 and (int(flat[end - 2]), int(flat[end - 1])) == EOI


def _filled_bottom_row_scan(image: np.ndarray) -> bool:
    """``filled_bottom_row`` as it was: the row's grey tail counted, every time."""
    if image.ndim < 2 or image.shape[0] == 0 or image.shape[1] == 0:
        return False
    row = image[-1].reshape(image.shape[1], -1)
    grey = np.all(row == JPEG_FILL, axis=1)
    tail = grey.size - int(np.flatnonzero(~grey)[-1]) - 1 if not grey.all() else grey.size
    return tail >= max(1, int(np.ceil(FILLED_TAIL * grey.size)))


def _camera_jpegs() -> list[bytes]:
    """The rendered press and no-contact frames as the camera's JPEG, whole and cut short."""
    _, _, jpegs = rendered_press_jpeg()
    return [*jpegs, *(cut_short(j, kept, eoi) for j in jpegs for kept in (0.0, 0.3, 0.9, 0.999) for eoi in (True, False))]


def test_the_end_marker_check_answers_as_the_full_search():
    cases = [b"", b"\xd9", b"\xff\xd9", b"\x00" * 10, b"\xff\xd9" + b"\x00" * 3, b"\x00\xff\xd9\x00"]
    for jpeg in _camera_jpegs():
        for pad in (0, 1, 40, TAIL_BYTES - 1, TAIL_BYTES, 4000):
            cases += [jpeg + b"\x00" * pad, jpeg[:-1] + b"\x00" * pad]
    for data in cases:
        for given in (data, np.frombuffer(data, np.uint8), bytearray(data)):
            assert ends_with_eoi(given) == _ends_with_eoi_scan(given), (len(data), type(given))


def test_the_fill_check_answers_as_the_full_scan():
    decoded = (decode_jpeg(np.frombuffer(j, np.uint8), scale) for j in _camera_jpegs() for scale in (1, 2, 4, 8))
    images = [image for image in decoded if image is not None]  # OpenCV 5 refuses a frame without its end
    rng = np.random.default_rng(0)
    for channels in (None, 1, 3):  # a row that ends in grey tails of every length, and none
        for tail in (0, 1, 2, 5, 39, 40, 41, 79, 80):
            shape = (4, 80) if channels is None else (4, 80, channels)
            image = rng.integers(0, 256, shape, dtype=np.uint8)
            image[-1, 80 - tail:] = JPEG_FILL
            images += [image, image[:, ::2], np.ascontiguousarray(image[:, ::-1])]
    images += [np.zeros((0, 3, 3), np.uint8), np.full((2, 2, 3), JPEG_FILL, np.uint8)]
    marked = 0
    for image in images:
        assert filled_bottom_row(image) == _filled_bottom_row_scan(image), image.shape
        marked += filled_bottom_row(image)
    assert 0 < marked < len(images)  # both answers were asked for


# --- runtime/frame_guard.py: the frozen-frame check's middle row first ---------------------------

def test_the_frozen_frame_check_answers_as_the_full_comparison():
    _, _, jpegs = rendered_press_jpeg()
    press, reference = (decode_jpeg(np.frombuffer(j, np.uint8), 2) for j in jpegs)
    pairs = [(press, reference), (press, press.copy()), (press, press[:-1]), (press[:0], press[:0])]
    for row in (0, 1, 16, 119, 120, 121, 239):  # one pixel changed: on, beside and off the rows looked at first
        other = press.copy()
        other[row, 7, 1] ^= 1
        pairs.append((press, other))
    as_float = press.astype(np.float32)
    signed = as_float.copy()
    signed[120] = -0.0  # equal values, other bytes: the byte check is for uint8 frames only
    pairs += [(as_float, as_float.copy()), (np.zeros_like(as_float), signed * 0), (press, press.astype(np.int16)),
              (press[:, ::2], np.ascontiguousarray(press[:, ::2]))]
    for a, b in pairs:
        want = a.shape == b.shape and bool(np.array_equal(a, b))
        assert _same_image(a, b) == want == _same_image(b, a), (a.shape, a.dtype, b.dtype)
    assert sum(_same_image(a, b) for a, b in pairs) >= 4 and not all(_same_image(a, b) for a, b in pairs)


# --- runtime/preprocess.py: the scaling in fewer numpy calls -----------------------------------

def _reduced_one_call(frame, reference, spec, scale):
    """The reduced path's tail as it was: the float32 difference, then one blobFromImage (scaling,
    channel swap, transpose) - for mean 0 and one std, every bundle's."""
    def side(image):
        return cv2.resize(image[:, (image.shape[1] - image.shape[0]) // 2:][:, :image.shape[0]], (spec.size,) * 2,
                          interpolation=cv2.INTER_LINEAR)
    diff = cv2.subtract(side(frame), side(reference).astype(np.float32), dtype=cv2.CV_32F)
    s = float(np.float32(1.0) / (np.float32(255.0) * np.float32(spec.std[0])))
    return cv2.dnn.blobFromImage(diff, scalefactor=s, swapRB=True, ddepth=cv2.CV_32F)[0]


def _float_per_plane(frame, reference, spec):
    """The float path's tail as it was: the difference in place, then per RGB plane
    ``* (1 / 255)``, ``- mean``, ``/ std`` on the strided channel."""
    def side(image):
        crop = image[:, (image.shape[1] - image.shape[0]) // 2:][:, :image.shape[0]].astype(np.float32)
        return cv2.resize(crop, (spec.size,) * 2, interpolation=cv2.INTER_AREA)
    image = side(frame)
    image -= side(reference)
    mean, std = np.asarray(spec.mean, np.float32), np.asarray(spec.std, np.float32)
    out = np.empty((3, spec.size, spec.size), np.float32)
    for c in range(3):
        np.multiply(image[:, :, 2 - c], np.float32(1.0 / 255.0), out=out[c])
        np.subtract(out[c], mean[c], out=out[c])
        np.divide(out[c], std[c], out=out[c])
    return out


@pytest.mark.parametrize("size", [128, 224])
def test_the_cells_press_tensor_is_the_one_it_was_bit_for_bit(size):
    # the camera's frames at 1/2 (640x480 -> 320x240), on both paths, at both trunks' sizes
    _, _, jpegs = rendered_press_jpeg()
    press, reference = (decode_jpeg(np.frombuffer(j, np.uint8), 2) for j in jpegs)
    frames = [press, reference, cv2.flip(press, 1), np.ascontiguousarray(press[::-1])]
    for spec, before in ((TactilePreprocess(size=size, reduce=2), _reduced_one_call),
                         (TactilePreprocess(size=size), _float_per_plane),
                         (TactilePreprocess(size=size, mean=(0.01, -0.02, 0.0), std=(0.08, 0.1, 0.05)),
                          _float_per_plane)):
        prepared = prepare_reference(reference, spec, 2)
        np.testing.assert_array_equal(prepared.planes, prepared.resized.transpose(2, 0, 1)[::-1])
        for frame in frames:
            args = (frame, reference, spec) + ((2,) if spec.reduce else ())
            want = before(*args)
            got = preprocess_tactile(frame, prepared, spec, 2)
            assert got.dtype == np.float32 and got.flags.c_contiguous and got.shape == (3, size, size)
            np.testing.assert_array_equal(got, want)
            assert np.ptp(got) > 0 or frame is reference


# --- runtime/scene_model.py, runtime/evidence.py: one press's distances kept, per-n terms made once ----

def _fresh(model):
    """The same scene model with nothing cached (``dataclasses.replace`` builds a new one)."""
    return replace(model)


def _sq_distances_plain(model, z):
    z = np.asarray(z, np.float64)
    means = np.asarray(model.means, np.float64)
    return (np.sum(z * z, axis=1)[:, None] - 2.0 * z @ means.T + np.sum(means * means, axis=1)[None, :]).clip(min=0.0)


def test_a_press_distances_kept_are_the_ones_computed_again():
    plain, held, *_ = _world()
    assert plain.sq_distances_projected(plain.project(held["f0"][:1])).flags.writeable  # no rule asks twice: none kept
    model = replace(plain, outlier_ratio=3.0)
    z = model.project(np.concatenate([held["f0"][:4], held["f7"][:3]]))
    asks = [z[i:i + 1] for i in (0, 0, 1, 0, 2, 2)] + [z[3:4].astype(np.float32), z, z[4:5], z[4]]
    for q in asks:  # one press again (kept), another press, a batch, a 1-d press
        got = model.sq_distances_projected(np.atleast_2d(q))
        np.testing.assert_array_equal(got, _sq_distances_plain(model, np.atleast_2d(q)))
        np.testing.assert_array_equal(got, _fresh(model).sq_distances_projected(np.atleast_2d(q)))
    kept = model.sq_distances_projected(z[:1])
    assert not kept.flags.writeable  # kept for the next ask: nobody may change it meanwhile
    with pytest.raises(ValueError):
        kept += 1.0


def test_the_offset_rules_item_scores_are_the_formula_bit_for_bit():
    model, held, *_ = _world()
    m = _offset(model)
    z = m.project(held["f1"][:9])
    synth = np.array([c in m.untouched and c not in m.taught for c in m.classes], np.float64)
    offset_var = np.where([c in m.untouched for c in m.classes], m.offset_var_untouched, m.offset_var_touched)
    for n in (1, 2, 3, 5, 9, 2, 1):  # each n twice: made, then kept
        zbar = z[:n].mean(0)
        d2 = (float(zbar @ zbar) - 2.0 * (zbar @ m.means.T) + np.sum(m.means * m.means, axis=1)).clip(min=0.0)
        v = offset_var + m.press_var / n
        want = (-0.5 * d2 / v - 0.5 * m.k * np.log(v)) / m.item_temperature + m.item_bias * synth
        np.testing.assert_array_equal(m.item_log_lik(zbar, n), want)
        np.testing.assert_array_equal(m.item_ratios(zbar, n), d2 / (m.k * v))


@pytest.mark.parametrize("rule", ["sum", "offset"])
def test_the_evidence_decides_every_piece_as_with_nothing_kept(rule):
    # the same presses through the cell's evidence twice: on the model, its distances kept from the
    # decision to the evidence, and on fresh copies for every ask (nothing kept anywhere)
    model, held, touched, untouched, strangers = _world()
    model = replace(_offset(model) if rule == "offset" else model, outlier_ratio=3.0, open_threshold=60.0,
                    known_margin=0.0)
    scene = so.Scene(tuple(touched[:4]), tuple(untouched[:2]), ())
    confidence, opts = so.scene_model_rule(model)
    decided = {}
    for kept in (True, False):
        decided[kept] = []
        for fabric in (*touched, *untouched, *strangers):
            x = held[fabric]
            for piece in range(0, len(x) - 5, 5):
                ev = Evidence(scene.classes, confidence, 5, **opts)
                for z in model.project(x[piece:piece + 5]):
                    m = model if kept else _fresh(model)
                    if not kept:
                        ev.item_model = None if ev.item_model is None else _fresh(model)
                        ev.outlier_model = None if ev.outlier_model is None else _fresh(model)
                    lp, d2 = m.log_posterior_projected(z[None])
                    if (d := ev.add(so.Press(dict(zip(m.classes, lp[0].tolist())),
                                             dict(zip(m.classes, d2[0].tolist())), z))) is not None:
                        break
                decided[kept].append(repr(d or ev.decide()))
    assert decided[True] == decided[False]
    assert len(set(decided[True])) > 10 and any("off_scene" in d for d in decided[True])


if __name__ == "__main__":  # pragma: no cover
    pytest.main([__file__, "-q"])

"""The one preprocessing of a tactile frame: training imports this, the cell runs this.

frame (HxWx3 uint8 BGR) and the session's no-contact reference frame ->
  checked (dtype, size, finite, not black/white/saturated) ->
  [real GelSight options, off by default: marker dots inpainted; each colour channel scaled to
  a mean of 128, which cancels exposure and LED drift between presses] ->
  centre crop to the square of the shorter side (times ``crop_fraction``) ->
  resize to ``size`` x ``size`` (INTER_AREA on float32: an anti-aliased decimation) ->
  difference to the reference, cropped and resized the same way (what the press changed,
  lighting and gel removed) ->
  scale: (diff / 255 - mean) / std, per channel ->
  float32 CHW, channels in RGB order.

Resizing is linear, so resize(frame) - resize(reference) is resize(frame - reference) up to
float32 rounding; doing it in this order lets the cell resize the reference once per item
(``prepare_reference``) instead of once per press: on a 640x480 frame at 128 px the whole step
went from 6.0 to under 1 ms. Training calls the same function with the raw reference, which takes
the very same path, so train and serve stay bit-identical.

The reduced uint8 path (``reduce`` >= 1; 0, the default, is the float path above, which every
bundle made before it keeps):

  frame reduced by ``reduce`` (1, 2, 4 or 8: a box average, INTER_AREA on uint8; a camera that
  streams MJPEG hands the frame already reduced by the JPEG decoder's own scaled decode,
  ``decode_jpeg``, which skips most of the decoding work) ->
  centre crop -> resize to ``size`` x ``size`` on uint8 (INTER_LINEAR: after the box reduction
  the rest is a small factor, e.g. 240 -> 128 px for a 640x480 frame at 128 px) ->
  float32 difference to the reference (reduced, cropped and resized the same way) ->
  scale -> CHW RGB, one multiply-subtract per channel.

Training reads the dataset's lossless frames and reduces them with ``reduce_frame``; the
simulated camera and PNG replays hand full frames and the cell reduces them with the same function
(bit-identical to training). A UVC camera in MJPEG mode hands ``decode_jpeg``'s frame instead: the
scaled inverse DCT is not a box average bit for bit. Against training's lossless frames, the
network input then differs by 1.08 grey levels on average on the synthetic 640x480 GelSight frames
at q95, where the float path's full MJPEG decode already differs by 0.90 (the JPEG loss;
tests/test_preprocess.py bounds the ratio). ``auto_reduce`` picks the factor: the largest that
leaves at least ``size`` pixels across the crop.

A float-path bundle on a UVC camera (cell config ``devices.camera.decode_scale: auto``, the
default) in MJPEG gets its frames decoded at ``float_path_scale`` - 1/2 of a 640x480 frame at 128
or 224 px - and runs the float path on them unchanged: the decoder's reduction stands in for the
first part of the INTER_AREA decimation, and the frame's decode, checks and crop shrink fourfold.
A YUYV camera keeps a float-path bundle's frames whole (its uint8 box average would round what
the float path averages in float: runtime/wiring.py ``model_decode_scale``).

The camera's JPEG itself: a UVC camera's MJPEG frames are lossy where the dataset's are lossless
(at q95 the float-path paper bundle lost 7.3 points of touched accuracy per press, a train/serve
skew). ``through_camera_jpeg(frame, quality, scale)`` is that camera: encode at ``quality``,
``decode_jpeg`` at 1/scale. A run trained with ``camera_jpeg`` Q reads every press and no-contact
frame through it (``camera_reference``, ``camera_press``), and so do its export and the bench, at
the scale its camera decodes at: 1/reduce on the reduced path; on the float path ``jpeg_scale``,
since 2026-11-29 the ``float_path_scale`` of the dataset's frames (train --camera-decode auto;
1 - full decodes - for the runs before it and with ``full``).
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from vs2t_edge.runtime.files import MAX_FRAME_PIXELS


REDUCE_FACTORS = (1, 2, 4, 8)  # the scaled decodes OpenCV's JPEG reader offers


class FrameError(ValueError):
    """A frame the cell must not classify. ``reason`` is a short machine-readable word."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class TactilePreprocess:
    size: int = 224  # side of the square network input, px
    crop_fraction: float = 1.0  # of the shorter side, centred
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)  # of diff/255, RGB
    std: tuple[float, float, float] = (0.08, 0.08, 0.08)  # typical spread of a pressed diff
    use_reference: bool = True  # subtract the no-contact frame
    # Real GelSight frames (issue 13, docs/realism.md). Both off: the synthetic world's frames and
    # every bundle so far were made without them, and the frozen trunk does not gain from them alone.
    inpaint_markers: bool = False  # fill the gel's dark marker dots from their rims (cv2.inpaint)
    normalise_exposure: bool = False  # scale each colour channel to a frame mean of 128
    # The reduced uint8 path (module doc): 0 = the float path of every bundle before it; 1, 2, 4, 8 =
    # the frame reduced by that factor (the camera's scaled MJPEG decode), then uint8 crop + resize.
    reduce: int = 0
    # The float path of a model trained through the camera's JPEG (train --camera-jpeg): the scale
    # 1/n its training frames were decoded at, the one its camera decodes at (``camera_scale``).
    # 1: full decodes (every bundle before it; a lossless-trained bundle takes any scale
    # ``float_path_scale`` allows). The reduced path decodes at 1/reduce and keeps 1 here.
    jpeg_scale: int = 1

    def __post_init__(self) -> None:
        # the other fields are the bundle check's (runtime/bundle.py); these two pick a code path
        if type(self.reduce) is not int or self.reduce not in (0, *REDUCE_FACTORS):
            raise ValueError(f"reduce = {self.reduce!r}: 0 (the float path) or one of {REDUCE_FACTORS}")
        if self.reduce and (self.inpaint_markers or self.normalise_exposure):
            raise ValueError("reduce >= 1 (the reduced uint8 path) has no inpaint_markers / normalise_exposure; "
                             "use reduce 0 for a real GelSight's corrections")
        if type(self.jpeg_scale) is not int or self.jpeg_scale not in REDUCE_FACTORS:
            raise ValueError(f"jpeg_scale = {self.jpeg_scale!r}: one of {REDUCE_FACTORS}")
        if self.jpeg_scale > 1 and (self.reduce or self.inpaint_markers or self.normalise_exposure):
            raise ValueError(f"jpeg_scale = {self.jpeg_scale} is the float path's: the reduced path decodes at "
                             "1/reduce, and a real GelSight's corrections read full frames")

    def to_dict(self) -> dict:
        d = asdict(self)
        if d["reduce"] == 0:  # the float path's manifests stay byte for byte what they were
            del d["reduce"]
        if d["jpeg_scale"] == 1:  # and so do those of every bundle trained on full decodes
            del d["jpeg_scale"]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TactilePreprocess":
        known = {k: d[k] for k in cls.__dataclass_fields__ if k in d}
        for key in ("mean", "std"):
            if key in known:
                known[key] = tuple(float(v) for v in known[key])
        unknown = sorted(set(d) - set(cls.__dataclass_fields__))
        if unknown:
            raise ValueError(f"preprocessing: unknown key(s) {unknown}")
        return cls(**known)


# A frame whose pixels are this close to black or white everywhere is no sensor image.
_DARK_MEAN, _BRIGHT_MEAN = 3.0, 252.0
_SATURATED_FRACTION = 0.5  # more than half the pixels clipped in some channel


def check_frame(frame: object, expected_hw: tuple[int, int] | None = None, name: str = "frame") -> np.ndarray:
    """Return the frame as HxWx3 uint8 or raise FrameError saying what is wrong with it.

    Nothing is converted: a grey (HxW), RGBA (HxWx4) or 16-bit frame is not what the sensor sends
    and is refused (reasons ``shape``, ``dtype``), never made three-channel and scored."""
    if not isinstance(frame, np.ndarray):
        raise FrameError(f"{name}: not an image array ({type(frame).__name__})", "type")
    if frame.dtype != np.uint8:
        if np.issubdtype(frame.dtype, np.floating) and not np.all(np.isfinite(frame)):
            raise FrameError(f"{name}: contains NaN or Inf", "nonfinite")
        raise FrameError(f"{name}: dtype {frame.dtype}, expected uint8", "dtype")
    if frame.ndim != 3 or frame.shape[2] != 3:
        raise FrameError(f"{name}: shape {frame.shape}, expected HxWx3", "shape")
    if frame.shape[0] * frame.shape[1] > MAX_FRAME_PIXELS:
        # before anything allocates per pixel: the float32 crop of a 30000 x 30000 frame is 10 GiB
        raise FrameError(f"{name}: size {frame.shape[1]}x{frame.shape[0]}, over the {MAX_FRAME_PIXELS} pixels "
                         "a tactile frame may have", "size")
    if expected_hw is not None and tuple(frame.shape[:2]) != tuple(expected_hw):
        raise FrameError(f"{name}: size {frame.shape[1]}x{frame.shape[0]}, expected "
                         f"{expected_hw[1]}x{expected_hw[0]}", "size")
    if frame.size == 0:
        raise FrameError(f"{name}: empty image", "shape")
    # cv2.mean is ~5x faster than ndarray.mean on a 640x480 frame (this runs every press)
    mean = float(sum(cv2.mean(frame)[:3]) / 3.0) if frame.flags.c_contiguous else float(frame.mean())
    if mean < _DARK_MEAN:
        raise FrameError(f"{name}: all black (mean {mean:.1f}); camera covered or off", "black")
    if mean > _BRIGHT_MEAN:
        raise FrameError(f"{name}: all white (mean {mean:.1f}); overexposed", "white")
    if frame.max() == 255 and _clipped_anywhere(frame) > _SATURATED_FRACTION * frame.shape[0] * frame.shape[1]:
        # per channel only when the clipped values of all channels together could make one channel
        # clipped past the limit: that count, along an axis, took 1 ms of a 320x240 frame
        clipped = float(np.count_nonzero(frame.reshape(-1, 3) == 255, axis=0).max()) / (frame.shape[0] * frame.shape[1])
        if clipped > _SATURATED_FRACTION:
            raise FrameError(f"{name}: {clipped:.0%} of pixels saturated; lower the exposure", "saturated")
    return frame


def _clipped_anywhere(frame: np.ndarray) -> int:
    """Values at 255 over all channels (>= the clipped pixels of any one channel)."""
    if frame.flags.c_contiguous:
        return cv2.countNonZero(cv2.compare(frame.reshape(frame.shape[0], -1), 255, cv2.CMP_EQ))
    return int(np.count_nonzero(frame == 255))


def marker_mask(image: np.ndarray, depth: float = 18.0) -> np.ndarray:
    """The gel's marker dots, HxW uint8 0/1: pixels darker than their 21 px median neighbourhood by
    ``depth`` grey levels (the dots are dark and small next to any contact shading)."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    local = cv2.medianBlur(grey, 21).astype(np.float32)
    return ((local - grey.astype(np.float32)) > depth).astype(np.uint8)


def inpaint_markers(image: np.ndarray) -> np.ndarray:
    """The frame (HxWx3 uint8) with its marker dots, grown by 2 px, filled from their rims."""
    mask = cv2.dilate(marker_mask(image), np.ones((5, 5), np.uint8))
    return cv2.inpaint(image, mask, 3, cv2.INPAINT_TELEA)


def _exposure_normalised(image: np.ndarray) -> np.ndarray:
    """float32, each channel scaled to a mean of 128 (a gain per channel cancels exactly)."""
    x = image.astype(np.float32)
    x *= np.float32(128.0) / np.maximum(np.asarray(cv2.mean(x)[:3], np.float32), np.float32(1.0))
    return x


def _sensor_corrected(image: np.ndarray, spec: TactilePreprocess) -> np.ndarray:
    if spec.inpaint_markers:
        image = inpaint_markers(image)
    if spec.normalise_exposure:
        image = _exposure_normalised(image)
    return image


_IMREAD = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
           8: cv2.IMREAD_REDUCED_COLOR_8}


def reduced_hw(hw: tuple[int, int], factor: int) -> tuple[int, int]:
    """Size of a frame reduced by ``factor``: rounded up, as the JPEG decoder's scaled output is."""
    return (-(-int(hw[0]) // factor), -(-int(hw[1]) // factor))


def reduce_frame(frame: np.ndarray, factor: int) -> np.ndarray:
    """The frame (HxWx3 uint8) reduced by ``factor``: a box average (INTER_AREA on uint8), what
    training and every camera that hands full frames use; ``decode_jpeg`` is the MJPEG camera's."""
    if factor == 1:
        return frame
    h, w = reduced_hw(frame.shape[:2], factor)
    return cv2.resize(frame, (w, h), interpolation=cv2.INTER_AREA)


def decode_jpeg(data: bytes | np.ndarray, factor: int = 1) -> np.ndarray | None:
    """A JPEG (an MJPEG camera's frame) decoded at 1/``factor`` scale, HxWx3 uint8 BGR, or None if
    it does not decode. libjpeg scales inside its inverse DCT, so a reduced decode skips most of the
    work after entropy decoding (a 640x480 q95 frame on the 2-core bench CPU: about 0.8 ms full,
    0.6 ms at 1/2, 0.55 ms at 1/4; entropy decoding is the floor)."""
    if factor not in _IMREAD:
        raise ValueError(f"JPEG decode scale 1/{factor}: OpenCV decodes at 1/1, 1/2, 1/4 or 1/8 only")
    buf = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else data.reshape(-1)
    if buf.dtype != np.uint8 or buf.size == 0:
        return None
    return cv2.imdecode(buf, _IMREAD[factor])


def check_camera_jpeg(quality: object, what: str = "camera_jpeg") -> int:
    """``quality`` as the camera's MJPEG quality a model is trained for: 0 (lossless frames, every
    run and bundle before it) or a JPEG quality 1..100; ValueError naming ``what`` otherwise."""
    if isinstance(quality, bool) or not isinstance(quality, (int, np.integer)) or not 0 <= int(quality) <= 100:
        raise ValueError(f"{what} = {quality!r}: 0 (lossless frames) or a JPEG quality from 1 to 100")
    return int(quality)


def camera_scale(spec: TactilePreprocess) -> int:
    """The scale a model's frames were trained at through the camera (``camera_jpeg``): 1/reduce on
    the reduced path, 1/``jpeg_scale`` on the float path (full size for runs before it). The cell's
    UVC camera decodes at it, or - a float-path bundle trained on lossless frames - at
    ``float_path_scale`` (runtime/wiring.py)."""
    return spec.reduce or spec.jpeg_scale


def float_path_scale(spec: TactilePreprocess, frame_hw: tuple[int, int]) -> int:
    """The smallest scale a camera may decode ``frame_hw`` frames at for a float-path bundle: the
    largest 1/n that leaves ``spec.size`` px across the crop (``auto_reduce``; 640x480 at 128 or
    224 px: 2), where the decoder's own reduction - the JPEG's scaled inverse DCT - stands in for
    the first part of the float path's INTER_AREA decimation (runtime/wiring.py asks it of an
    MJPEG camera only). 1 for a
    bundle that corrects a real GelSight's full frames. The float path then runs unchanged on the
    smaller frame (``preprocess_tactile``); docs/cell.md ``devices.camera.decode_scale`` says what
    it costs and buys."""
    if spec.reduce or spec.inpaint_markers or spec.normalise_exposure:
        return 1
    return auto_reduce(frame_hw, spec.size, spec.crop_fraction)


def through_camera_jpeg(frame: np.ndarray, quality: int, scale: int = 1, name: str = "frame") -> np.ndarray:
    """``frame`` (HxWx3 uint8 BGR, lossless) as a UVC camera streaming MJPEG at ``quality`` hands
    it to the cell: JPEG-encoded by OpenCV's libjpeg at that quality, then decoded at 1/``scale``
    by ``decode_jpeg``, the cell's own decode. Training (``camera_jpeg``), export and the bench read
    a dataset's lossless frames through it so the model sees what the cell's camera hands it.
    Raises FrameError (reason ``jpeg``) naming ``name`` when the frame does not encode or decode."""
    quality = check_camera_jpeg(quality, "JPEG quality")
    if quality == 0:
        raise ValueError("JPEG quality 0: no JPEG; pass the lossless frame on (camera_jpeg 0)")
    frame = check_frame(frame, name=name)
    ok, enc = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, quality])
    out = decode_jpeg(enc, scale) if ok else None
    if out is None or out.ndim != 3 or out.shape[2] != 3:
        raise FrameError(f"{name}: could not pass it through JPEG at quality {quality} "
                         f"({'encode' if not ok else 'decode'} failed)", "jpeg")
    return out


def auto_reduce(frame_hw: tuple[int, int], size: int, crop_fraction: float = 1.0) -> int:
    """The largest factor of REDUCE_FACTORS that leaves at least ``size`` px across the crop
    (640x480 at 128 or 224 px: 2; 320x240 at 128 px: 1)."""
    side = min(frame_hw) * crop_fraction
    return max(f for f in REDUCE_FACTORS if f == 1 or side / f >= size)


def _reduced_input(image: np.ndarray, spec: TactilePreprocess, reduced_by: int) -> np.ndarray:
    """The frame at 1/spec.reduce: reduced here (``reduced_by`` 1) or already by the camera."""
    if reduced_by == 1:
        return reduce_frame(image, spec.reduce)
    if reduced_by != spec.reduce:
        raise FrameError(f"frame: decoded at 1/{reduced_by} scale, but the bundle's preprocessing reduces by "
                         f"{spec.reduce}", "scale")
    return image


def centre_square(hw: tuple[int, ...], crop_fraction: float) -> tuple[slice, slice]:
    """The centred square of the shorter side times ``crop_fraction``: the part of a frame the
    model reads (the contact check asks for the imprint there too, runtime/contact.py)."""
    h, w = hw[:2]
    side = max(1, int(round(min(h, w) * crop_fraction)))
    y0, x0 = (h - side) // 2, (w - side) // 2
    return slice(y0, y0 + side), slice(x0, x0 + side)


def _crop_resize_u8(image: np.ndarray, spec: TactilePreprocess) -> np.ndarray:
    """The reduced path: centre square crop -> uint8 INTER_LINEAR to size x size."""
    return cv2.resize(image[centre_square(image.shape, spec.crop_fraction)], (spec.size, spec.size),
                      interpolation=cv2.INTER_LINEAR)


def _crop_resize(image: np.ndarray, spec: TactilePreprocess) -> np.ndarray:
    """Centre square crop (uint8 view, no copy) -> float32 -> INTER_AREA to size x size."""
    image = _sensor_corrected(image, spec)
    crop = image[centre_square(image.shape, spec.crop_fraction)].astype(np.float32)
    return cv2.resize(crop, (spec.size, spec.size), interpolation=cv2.INTER_AREA)


def shading_grid(hw: tuple[int, int]) -> tuple[int, int]:
    """(rows, columns) of the shading grid: 8 x 6 cells on a portrait frame, 6 x 8 on a landscape one
    (about 50 px cells on the GelSight Mini's 400 x 300)."""
    return (8, 6) if hw[0] >= hw[1] else (6, 8)


def shading_descriptor(frame: np.ndarray, grid: tuple[int, int] | None = None) -> np.ndarray:
    """The gel's shading under a press, (rows * columns * 3,) float64: markers inpainted, each colour
    channel divided by its frame mean, then the log of the mean colour of each grid cell.

    A GelSight's colour at a pixel encodes the gel's slope there (each LED lights it from one
    side), so the coarse colour field is the shape the material pressed into the gel - its
    thickness and give. On real GelSight Mini frames it is what separates materials on later
    presses; their fine texture barely shows and the frozen ImageNet trunk mostly sees the marker
    grid (docs/realism.md). Dividing by the channel mean cancels exposure or LED drift between
    presses; the log makes a gain a shift. No reference frame is needed. Numpy and OpenCV only, so
    the cell can compute it; no bundle uses it yet."""
    frame = check_frame(frame)
    rows, cols = grid or shading_grid(frame.shape[:2])
    x = inpaint_markers(frame).astype(np.float32) + 1.0
    x /= x.reshape(-1, 3).mean(axis=0)
    return np.log(cv2.resize(x, (cols, rows), interpolation=cv2.INTER_AREA)).astype(np.float64).ravel()


@dataclass(frozen=True)
class PreparedReference:
    """A checked no-contact reference frame, cropped and resized for ``spec`` (once per item)."""

    frame_hw: tuple[int, int]  # of the frame as given (float path) or at 1/spec.reduce (reduced path)
    resized: np.ndarray  # (size, size, 3) float32, BGR, 0..255
    spec: TactilePreprocess
    # ``resized`` as the network's planes, (3, size, size) float32 RGB: what each press subtracts
    planes: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "planes", np.ascontiguousarray(self.resized.transpose(2, 0, 1)[::-1]))


def _check_reduced_by(reduced_by: int, spec: TactilePreprocess, hw: tuple[int, int] | None = None) -> None:
    """The float path takes a frame the camera decoded at 1/n (``float_path_scale``, n one of
    REDUCE_FACTORS) while the crop keeps at least ``spec.size`` px across - it never upscales a
    reduced frame (a recording made at 1/4 for another bundle is refused, not scored) - and not
    for a bundle that corrects a real GelSight's frames, whose marker and exposure steps were set
    at full size. The reduced path checks its own factor (``_reduced_input``)."""
    if reduced_by == 1 or spec.reduce:
        return
    if reduced_by not in REDUCE_FACTORS:
        raise FrameError(f"frame: decoded at 1/{reduced_by} scale; a camera decodes at 1/n, n one of "
                         f"{REDUCE_FACTORS}", "scale")
    if spec.inpaint_markers or spec.normalise_exposure:
        raise FrameError(f"frame: decoded at 1/{reduced_by} scale, but the bundle's preprocessing corrects a real "
                         "GelSight's full frames (inpaint_markers / normalise_exposure)", "scale")
    if hw is not None and min(hw) * spec.crop_fraction < spec.size:
        raise FrameError(f"frame: decoded at 1/{reduced_by} scale, {hw[1]}x{hw[0]}: fewer than the bundle's "
                         f"{spec.size} px across its crop (a float-path bundle is not scored on upscaled frames)",
                         "scale")


def prepare_reference(reference: np.ndarray, spec: TactilePreprocess, reduced_by: int = 1) -> PreparedReference:
    """``reduced_by``: 1 for a full frame, else the scale the camera decoded it at (as for
    ``preprocess_tactile``)."""
    reference = check_frame(reference, name="reference frame")
    _check_reduced_by(reduced_by, spec, reference.shape[:2])
    if spec.reduce == 0:
        return PreparedReference(tuple(reference.shape[:2]), _crop_resize(reference, spec), spec)
    small = _reduced_input(reference, spec, reduced_by)
    return PreparedReference(tuple(small.shape[:2]), _crop_resize_u8(small, spec).astype(np.float32), spec)


def preprocess_tactile(frame: np.ndarray, reference: np.ndarray | PreparedReference | None,
                       spec: TactilePreprocess, reduced_by: int = 1) -> np.ndarray:
    """One frame -> (3, size, size) float32, as the tactile trunk expects it. ``reference`` is the
    raw no-contact frame or, on the cell, its ``prepare_reference`` (same result, less work).
    ``reduced_by``: 1 for a full frame; the scale the camera decoded it at otherwise - the reduced
    path's ``spec.reduce``, or on the float path ``float_path_scale``'s (``decode_jpeg``)."""
    frame = check_frame(frame)
    _check_reduced_by(reduced_by, spec, frame.shape[:2])
    if spec.reduce == 0:
        image, hw = _crop_resize(frame, spec), tuple(frame.shape[:2])
    else:
        small = _reduced_input(frame, spec, reduced_by)
        image, hw = _crop_resize_u8(small, spec), tuple(small.shape[:2])  # uint8 until the difference
    if spec.use_reference:
        if reference is None:
            raise FrameError("no-contact reference frame missing", "reference")
        if not isinstance(reference, PreparedReference):
            reference = prepare_reference(reference, spec)
        if reference.frame_hw != hw:
            # Neither is "the" right size: say both. On the cell the reference is the item's own
            # no-contact frame, so it is usually the press frame that is off.
            h, w = reference.frame_hw
            raise FrameError(f"frame: size {hw[1]}x{hw[0]} does not match the no-contact "
                             f"reference frame's {w}x{h}", "size")
        if reference.spec != spec:
            raise ValueError("reference frame was prepared for another preprocessing")
    return _scaled_chw(image, reference if spec.use_reference else None, spec)


@functools.lru_cache(maxsize=16)
def _scaling(spec: TactilePreprocess) -> tuple:
    """(multiplier, mean to subtract or None, std to divide by or None), each a float32 scalar when
    the channels share it, else (3, 1, 1): ``_scaled_chw``'s constants, made once per spec (after the
    trunk's run every numpy call is paid cold). A zero mean is left out (x - 0 is x, bit for bit)."""
    def per_channel(v: np.ndarray) -> np.ndarray:
        return v[0] if np.all(v == v[0]) else v[:, None, None]

    mean, std = np.asarray(spec.mean, np.float32), np.asarray(spec.std, np.float32)
    if spec.reduce:
        mul, sub, div = np.float32(1.0) / (np.float32(255.0) * std), mean / std, None
    else:
        mul, sub, div = np.full(3, 1.0 / 255.0, np.float32), mean, std
    return (per_channel(mul), per_channel(sub) if np.any(sub) else None,
            None if div is None else per_channel(div))


def _scaled_chw(image: np.ndarray, reference: PreparedReference | None, spec: TactilePreprocess) -> np.ndarray:
    """(S, S, 3) BGR frame (float32 on the float path, uint8 on the reduced path) less the
    reference -> (3, S, S) float32 RGB, scaled.

    The very float32 operations, in the same order, of the per-plane forms they replaced
    (bit-identical, tests/test_preprocess.py and tests/test_press_cost.py), in fewer numpy calls and
    passes over the frame (after the trunk's run each is paid cold):
    float path: ``((frame - reference) / 255 - mean) / std`` as ``* (1 / 255)``, ``- mean``,
    ``/ std``, its first step reading the BGR difference as RGB planes (one strided pass);
    reduced path: the uint8 frame's planes each less the reference's (``PreparedReference.planes``)
    into the output - exact, the values are integers - then ``* (1 / (255 std))`` and
    ``- mean / std``. 224 px after ResNet50's run: 0.52 -> 0.42 ms (float), 0.39 -> 0.28 (reduced)."""
    mul, sub, div = _scaling(spec)
    out = np.empty((3, *image.shape[:2]), np.float32)
    if spec.reduce:
        planes = cv2.split(image)  # B, G, R
        for c in range(3):  # RGB plane c is BGR channel 2 - c
            if reference is None:
                out[c] = planes[2 - c]
            else:
                cv2.subtract(planes[2 - c], reference.planes[c], dst=out[c], dtype=cv2.CV_32F)
        np.multiply(out, mul, out=out)
    else:
        if reference is not None:
            image -= reference.resized  # the float32 crop is this call's own
        np.multiply(image.transpose(2, 0, 1)[::-1], mul, out=out)
    if sub is not None:
        np.subtract(out, sub, out=out)
    if div is not None:
        np.divide(out, div, out=out)
    return out


def camera_frame(frame: np.ndarray, camera_jpeg: int, scale: int = 1, name: str = "frame") -> np.ndarray:
    """A dataset's lossless frame as the camera hands it: through its JPEG at ``camera_jpeg``,
    decoded at 1/``scale`` (``through_camera_jpeg``), or as it is for 0."""
    return through_camera_jpeg(frame, camera_jpeg, scale, name) if camera_jpeg else frame


def camera_reference(reference: np.ndarray, spec: TactilePreprocess, camera_jpeg: int = 0,
                     name: str = "reference frame", scale: int | None = None) -> PreparedReference:
    """A dataset's lossless no-contact frame prepared as the cell prepares its camera's: with
    ``camera_jpeg`` Q > 0 through the camera's JPEG at Q, decoded at ``scale`` (default
    ``camera_scale(spec)``, training's; the bench passes the cell's: ``float_path_scale``)
    (``through_camera_jpeg``); 0: the lossless frame as it is (every run before the option)."""
    if not camera_jpeg:
        return prepare_reference(reference, spec)
    scale = camera_scale(spec) if scale is None else scale
    return prepare_reference(through_camera_jpeg(reference, camera_jpeg, scale, name), spec, scale)


def camera_press(frame: np.ndarray, reference: PreparedReference | None, spec: TactilePreprocess,
                 camera_jpeg: int = 0, name: str = "frame", scale: int | None = None) -> np.ndarray:
    """A dataset's lossless press frame -> (3, S, S) float32 as the cell scores its camera's frame
    (``camera_reference``'s rule; ``reference`` from ``camera_reference`` with the same quality
    and scale)."""
    if not camera_jpeg:
        return preprocess_tactile(frame, reference, spec)
    scale = camera_scale(spec) if scale is None else scale
    return preprocess_tactile(through_camera_jpeg(frame, camera_jpeg, scale, name), reference, spec, scale)


def preprocess_batch(frames: list[np.ndarray], reference: np.ndarray | None, spec: TactilePreprocess) -> np.ndarray:
    """Full frames (a dataset's) against their raw reference; the path training takes."""
    if spec.use_reference and reference is not None and frames:
        reference = prepare_reference(check_frame(reference, frames[0].shape[:2], name="reference frame"), spec)
    return np.stack([preprocess_tactile(f, reference, spec) for f in frames])

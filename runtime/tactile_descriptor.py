"""A tactile feature without a network: the gel's coarse shading and its marker dots' shear.

``shading_markers(frame, reference)`` is what won on real GelSight Mini recordings (issue 13,
docs/realism.md: 94.5 % temporal-split accuracy against the frozen ImageNet trunk's 54.5 %; on the
fold that fits half the presses, 91 against 45 %). It is
the cell's tactile feature when a bundle's manifest says ``"trunk": {"kind": "descriptor", ...}``
(docs/bundle.md) and the feature `vs2t-edge real-check` measures as ``shading_markers``: one
function for both, numpy and OpenCV only.

    frame, the item's no-contact reference ->
      shading: markers inpainted, each colour channel divided by its frame mean, the log of the
               mean colour of each cell of a 6 x 8 grid (8 x 6 on a portrait frame): 144 numbers
               (``runtime.preprocess.shading_descriptor``);
      markers: every reference dot's darkness-weighted centre matched to the nearest dot of the
               frame; the displacement (x, y) averaged over the reference dots of each grid cell:
               96 numbers, zero where a cell has no matched dot
    -> 240 float32 numbers, whatever the frame size.

Why the displacement against the reference and not the dots' absolute centres: a gel's marker
grid sits a little differently on every sensor and drifts as the gel ages; the shift the press
made is the gel's shear, the material's. Pooling by grid cell gives a fixed length even when a
dot is lost at the edge or two merge under a press, which a per-dot list cannot.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vs2t_edge.runtime.preprocess import FrameError, check_frame, marker_mask, shading_descriptor, shading_grid

NAMES = ("shading_markers",)
GRID_CELLS = 48  # 6 x 8 either way round (runtime.preprocess.shading_grid)
DIM = {"shading_markers": 5 * GRID_CELLS}  # 3 shading + 2 displacement numbers per cell
_MIN_DOT_PX = 15  # blobs of the marker mask smaller than this are noise, not dots
_MATCH_PITCHES = 0.5  # a frame dot farther than half a grid pitch from a reference dot is another dot


def dot_centres(image: np.ndarray) -> np.ndarray:
    """(n, 2) sub-pixel centres (x, y) of the marker dots, in no particular order; (0, 2) if none.

    Each centre is the dot's centroid weighted by how much darker than the surrounding gel each
    pixel is, not the centre of its thresholded blob: the gel's shear moves a dot by a pixel or
    less between materials, below what a binary blob resolves, and a blob's area changes with
    exposure (docs/realism.md: blob centres add about 1 point beside the shading, these about 4)."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    darkness = np.clip(cv2.medianBlur(grey, 21).astype(np.float64) - grey, 0.0, None)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(marker_mask(image))
    keep = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] > _MIN_DOT_PX)
    keep = keep[keep > 0]
    if len(keep) == 0:
        return np.zeros((0, 2))
    yy, xx = np.indices(labels.shape)
    lab, w = labels.ravel(), darkness.ravel()
    mass = np.bincount(lab, w, n)[keep]
    c = np.stack([np.bincount(lab, w * xx.ravel(), n)[keep], np.bincount(lab, w * yy.ravel(), n)[keep]], 1)
    return c / np.maximum(mass, 1e-9)[:, None]


def grid_pitch(c: np.ndarray) -> float:
    """The marker grid's pitch, px: the median distance from a dot to its nearest neighbour."""
    d = np.hypot(*(c[:, None, :] - c[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def grid_order(c: np.ndarray) -> np.ndarray:
    """Indices that put dot centres (n, 2) in grid order: rows top to bottom, each row by x; a row
    is the dots within half a grid pitch in y."""
    return np.lexsort((c[:, 0], np.round(c[:, 1] / grid_pitch(c))))


@dataclass(frozen=True)
class DescriptorReference:
    """An item's no-contact frame as the descriptor needs it, computed once per item."""

    frame_hw: tuple[int, int]
    dots: np.ndarray  # (n, 2) reference dot centres, px
    cell: np.ndarray  # (n,) grid cell of each reference dot (row-major)
    pitch: float  # px; inf when the reference has fewer than 2 dots


def prepare_reference(reference: np.ndarray) -> DescriptorReference:
    """Check the no-contact frame and find its dots and their grid cells (FrameError if unusable)."""
    reference = check_frame(reference, name="reference frame")
    h, w = reference.shape[:2]
    rows, cols = shading_grid((h, w))
    dots = dot_centres(reference)
    cell = (np.minimum((dots[:, 1] * rows / h).astype(int), rows - 1) * cols
            + np.minimum((dots[:, 0] * cols / w).astype(int), cols - 1))
    pitch = grid_pitch(dots) if len(dots) >= 2 else float("inf")
    return DescriptorReference((h, w), dots, cell, pitch)


def marker_displacement(frame: np.ndarray, reference: DescriptorReference) -> np.ndarray:
    """(cells * 2,) float64: per grid cell, the mean (dx, dy) of its reference dots to their
    nearest frame dots, px; a dot with no frame dot within half a pitch, and a cell without dots,
    count as no displacement."""
    out = np.zeros((GRID_CELLS, 2))
    dots = dot_centres(frame)
    if len(reference.dots) == 0 or len(dots) == 0:
        return out.ravel()
    diff = dots[None, :, :] - reference.dots[:, None, :]  # (reference dots, frame dots, 2)
    dist = np.hypot(diff[..., 0], diff[..., 1])
    nearest = dist.argmin(axis=1)
    found = dist[np.arange(len(nearest)), nearest] <= _MATCH_PITCHES * reference.pitch
    shift = diff[np.arange(len(nearest)), nearest][found]
    cell = reference.cell[found]
    count = np.bincount(cell, minlength=GRID_CELLS)
    for k in (0, 1):
        out[:, k] = np.bincount(cell, shift[:, k], minlength=GRID_CELLS) / np.maximum(count, 1)
    return out.ravel()


def shading_markers(frame: np.ndarray, reference: np.ndarray | DescriptorReference) -> np.ndarray:
    """One press -> (240,) float32: the shading (144) and the marker displacement (96), module doc.
    ``reference`` is the item's raw no-contact frame or its ``prepare_reference`` (same result)."""
    frame = check_frame(frame)
    if not isinstance(reference, DescriptorReference):
        reference = prepare_reference(reference)
    if reference.frame_hw != tuple(frame.shape[:2]):
        h, w = reference.frame_hw
        raise FrameError(f"frame: size {frame.shape[1]}x{frame.shape[0]} does not match the no-contact "
                         f"reference frame's {w}x{h}", "size")
    shading = shading_descriptor(frame)
    return np.concatenate([shading, marker_displacement(frame, reference)]).astype(np.float32)


DESCRIPTORS = {"shading_markers": shading_markers}
KIND = "descriptor"  # a bundle manifest's "trunk": {"kind": KIND, "name", "dim", "file"}


def describe(name: str, frame: np.ndarray, reference: np.ndarray | DescriptorReference) -> np.ndarray:
    """The named descriptor of one press (``NAMES``); KeyError for a name this runtime lacks."""
    return DESCRIPTORS[name](frame, reference)


@dataclass(frozen=True)
class DescriptorFeature:
    """A bundle's tactile feature when it is a descriptor: the function's name and the
    per-dimension standardisation fitted on touched training presses (what an ONNX trunk folds in)."""

    name: str
    mean: np.ndarray  # (D,) float32
    std: np.ndarray  # (D,) float32, > 0

    def standardise(self, raw: np.ndarray) -> np.ndarray:
        return ((np.asarray(raw, np.float32) - self.mean) / self.std).astype(np.float32)


def load_descriptor_feature(root, manifest: dict, dim: int) -> tuple[DescriptorFeature, np.ndarray]:
    """(the feature, the probe's [reference, press] frames) of a descriptor bundle, checked as
    strictly as a graph: known kind and name, the name's dimension, finite mean and positive std
    of that dimension, two usable frames of one size. Raises runtime.bundle.BundleError."""
    from vs2t_edge.runtime.bundle import _DATA_ERRORS, BundleError, _inside, _need, _npz, _short

    kind = _need(manifest, root, "trunk", "kind")
    if kind != KIND:
        raise BundleError(root, f"manifest.json 'trunk.kind' = {_short(kind)}: this runtime knows {KIND!r} "
                                "(an ONNX trunk is 'graphs.trunk', not 'trunk')")
    name = _need(manifest, root, "trunk", "name")
    if name not in NAMES:
        raise BundleError(root, f"manifest.json 'trunk.name' = {_short(name)}: this runtime computes {list(NAMES)}")
    declared = _need(manifest, root, "trunk", "dim")
    if declared != DIM[name] or dim != DIM[name] or isinstance(declared, bool):
        raise BundleError(root, f"manifest.json 'trunk.dim' = {_short(declared)}, feature_dim {dim}: "
                                f"{name} has {DIM[name]} numbers")
    path = _inside(root, _need(manifest, root, "trunk", "file"), "trunk.file")
    frames_path = _inside(root, _need(manifest, root, "probe", "frames"), "probe.frames")
    try:
        with _npz(path, root, "trunk.file") as z:
            mean, std = (np.asarray(z[k]) for k in ("mean", "std"))
        frames = np.load(frames_path, allow_pickle=False)
    except _DATA_ERRORS as exc:
        raise BundleError(root, f"{path.name} or {frames_path.name} unreadable ({exc})") from None
    for key, v in (("mean", mean), ("std", std)):
        if v.shape != (dim,) or not np.issubdtype(v.dtype, np.floating) or not np.all(np.isfinite(v)):
            raise BundleError(root, f"{path.name}: '{key}' is {v.dtype} {v.shape}, expected {dim} finite numbers")
    if not np.all(std > 0):
        raise BundleError(root, f"{path.name}: 'std' has values <= 0")
    if not isinstance(frames, np.ndarray) or frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[0] != 2 \
            or frames.shape[3] != 3:
        raise BundleError(root, f"{frames_path.name}: expected uint8 (2, H, W, 3) [reference, press], got "
                                f"{getattr(frames, 'dtype', '?')} {getattr(frames, 'shape', '?')}")
    try:
        for k, what in enumerate(("reference", "press")):
            check_frame(frames[k], name=f"{frames_path.name} {what}")
    except FrameError as exc:
        raise BundleError(root, str(exc)) from None
    return DescriptorFeature(str(name), mean.astype(np.float32), std.astype(np.float32)), frames


__all__ = ["NAMES", "DIM", "KIND", "DescriptorReference", "DescriptorFeature", "prepare_reference", "shading_markers",
           "marker_displacement", "dot_centres", "grid_order", "grid_pitch", "describe", "load_descriptor_feature"]

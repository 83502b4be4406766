"""Feature extraction with a cached frozen stem, and tail fine-tuning on TOUCHED fabrics only.

The expensive part of a trunk (its stem, see ``trunks.py``) is run once per press and cached:
- ``stem_t``: the tactile stem activation of ``preprocess_tactile(press, reference, spec)``
  (the runtime's one preprocessing function), float16;
- ``stem_v``: the visual stem activation of the camera crop at the press (ImageNet
  normalisation), float16 — so the visual tail can be fine-tuned as cheaply as the tactile one;
- ``x_v``: the frozen trunk's visual feature of that crop (used when the visual tail is frozen,
  the default; see docs/training.md "Visual tail: frozen or fine-tuned");
- ``x_t0``: the frozen trunk's tactile feature (the baselines' ``FeatureTable`` uses it).

Zero-shot guard: ``touched_training_rows`` is the only way fine-tuning gets rows; it returns the
SAME touched-train presses ``compare.split_views`` uses for training (touched val/test presses
stay out too) and refuses any row of a fabric outside ``split.touched``. ``finetune_tail``
receives a copy of exactly those rows — of ``stem_t`` for the tactile tail, of ``stem_v`` (the
camera crops at those presses) for the visual tail.
"""

from __future__ import annotations

import copy
import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from vs2t_edge.train.progress import Line
from vs2t_edge.train.trunks import IMAGENET_MEAN, IMAGENET_STD, Trunk

CACHE_VERSION = 1


class ZeroShotViolation(RuntimeError):
    """A training step was about to see tactile data of a fabric that is not touched."""


@dataclass
class StemCache:
    stem_t: np.ndarray  # (P, C, h, w) float16
    x_v: np.ndarray  # (P, D) float32
    x_t0: np.ndarray  # (P, D) float32 frozen tactile features
    fabric: np.ndarray  # (P,) int64 index into fabric_ids
    fabric_ids: list[str]
    attributes: np.ndarray  # (F, 24)
    meta: dict
    stem_v: np.ndarray | None = None  # (P, C, h, w) float16 visual stem; None in caches made before it existed

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        extra = {} if self.stem_v is None else {"stem_v": self.stem_v}
        np.savez(tmp, stem_t=self.stem_t, x_v=self.x_v, x_t0=self.x_t0, fabric=self.fabric,
                 fabric_ids=np.array(self.fabric_ids), attributes=self.attributes,
                 meta=np.array(repr(sorted(self.meta.items()))), **extra)
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path, expect_meta: dict | None = None) -> "StemCache | None":
        """The cache, or None when it is absent or was made with other settings."""
        if not path.is_file():
            return None
        with np.load(path, allow_pickle=False) as z:
            meta = dict(eval(str(z["meta"])))  # noqa: S307 - our own repr of a sorted list of str/int pairs
            if expect_meta is not None and meta != expect_meta:
                return None
            return cls(z["stem_t"], z["x_v"], z["x_t0"], z["fabric"].astype(np.int64),
                       [str(s) for s in z["fabric_ids"]], z["attributes"].astype(np.float64), meta,
                       z["stem_v"] if "stem_v" in z.files else None)


def trunk_fingerprint(trunk: nn.Module) -> str:
    """sha256 of the trunk's weights and buffers, the stem cache's key for *which* trunk made it.
    The exported trunk is the run's own (its stem included); tails fine-tuned on another trunk's
    cached stems give features the exported graph never computes (a tiny trunk is random per
    ``--seed``, a ResNet50 without ``--weights`` too, and ``--weights`` names another file)."""
    h = hashlib.sha256()
    for name, t in trunk.state_dict().items():
        a = t.detach().cpu().contiguous().numpy()
        h.update(f"{name}|{a.dtype}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def dataset_fingerprint(dataset_root: Path) -> str:
    """sha256 over every file of the dataset folder (its relative path, size and modification time,
    no content read): the stem cache's key for *which* frames it holds. A world drawn again into the
    same folder (`vs2t-edge demo --seed 1` in a work folder of seed 0) keeps the path, and a cache
    keyed by the path alone fed the old world's stems to the new run while export, the probe and
    the cell read the new world's frames. A copy that changes times only costs an extraction."""
    h = hashlib.sha256()
    root = Path(dataset_root).resolve()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        st = path.stat()
        h.update(f"{path.relative_to(root).as_posix()}|{st.st_size}|{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def _visual_input(crop_bgr: np.ndarray, size: int) -> np.ndarray:
    import cv2

    img = cv2.resize(crop_bgr, (size, size), interpolation=cv2.INTER_AREA)[..., ::-1] / 255.0
    img = (img - np.asarray(IMAGENET_MEAN)) / np.asarray(IMAGENET_STD)
    return img.transpose(2, 0, 1).astype(np.float32)


def extracted_presses(n_presses: int, max_presses: int | None) -> np.ndarray:
    """The presses of a fabric ``extract_cache`` reads: at most ``max_presses``, evenly spaced over
    the press order (the grid), not the first rows of the grid."""
    n = n_presses if max_presses is None or max_presses <= 0 else min(max_presses, n_presses)
    return np.unique(np.linspace(0, n_presses - 1, n).round().astype(int))


@torch.no_grad()
def extract_cache(dataset_root: Path, trunk: Trunk, size: int, max_presses: int | None = None,
                  batch: int = 64, progress: bool = True, spec=None, camera_jpeg: int = 0) -> StemCache:
    """Read every press once: tactile and visual stem activations, frozen visual and tactile features.
    ``spec``: the run's TactilePreprocess (default: the float path at ``size``), the cell's own.
    ``camera_jpeg`` Q > 0: every press frame and the no-contact frame pass through the camera's JPEG
    at Q, decoded at the bundle's scale (``runtime.preprocess.camera_press``: what the cell does
    with a UVC camera's MJPEG frame); 0 reads the lossless frames. The camera crops (the visual
    side) are another camera's and stay as they are."""
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import TactilePreprocess, camera_press, camera_reference, check_camera_jpeg

    camera_jpeg = check_camera_jpeg(camera_jpeg)
    ds = load_dataset(dataset_root)
    spec = spec or TactilePreprocess(size=size)
    if spec.size != size:
        raise ValueError(f"extract_cache: spec.size {spec.size} != size {size}")
    trunk.eval()
    key = stem_cache_key(dataset_root, trunk, size, max_presses, spec, camera_jpeg)
    stems, stems_v, xv, xt0, fab = [], [], [], [], []
    line = Line()
    t0 = time.time()
    total = sum(len(extracted_presses(len(f.presses), max_presses)) for f in ds.fabrics)
    total = max(total, 1)
    done = 0
    for k, fabric in enumerate(ds.fabrics):
        # prepared once per fabric, as the cell prepares it once per item (the same result as the raw frame)
        ref = camera_reference(fabric.load_reference(), spec, camera_jpeg, name=f"{fabric.id} reference frame")
        camera = fabric.load_camera()
        chosen = extracted_presses(len(fabric.presses), max_presses)
        n = len(chosen)
        for i0 in range(0, n, batch):
            idx = chosen[i0:i0 + batch]
            tac = torch.from_numpy(np.stack([camera_press(fabric.load_press(i), ref, spec, camera_jpeg,
                                                          name=f"{fabric.id} press {i}") for i in idx]))
            vis = torch.from_numpy(np.stack([_visual_input(fabric.visual_crop(i, camera), size) for i in idx]))
            a = trunk.stem(tac)
            stems.append(a.half().numpy())
            xt0.append(trunk.features_from_stem(a).numpy())
            av = trunk.stem(vis)
            stems_v.append(av.half().numpy())
            xv.append(trunk.features_from_stem(av).numpy())  # == trunk(vis)
            done += len(idx)
            if progress:
                el = time.time() - t0
                line.draw(f"features: fabric {k + 1}/{len(ds.fabrics)}, press {done}/{total} "
                          f"({el:.0f} s, ~{el / done * (total - done):.0f} s left)", done / total)
        fab.append(np.full(n, k))
    if progress:
        line.keep()
    # C order, as a cache read back from its file is: a conv's output may come out in another memory
    # layout (the visual stem's did), and the tails fine-tuned on such an array came out differently
    # from the same run's reruns on its saved cache (oneDNN picks its kernels by layout)
    c = np.ascontiguousarray
    return StemCache(c(np.concatenate(stems)), c(np.concatenate(xv), np.float32), c(np.concatenate(xt0), np.float32),
                     np.concatenate(fab).astype(np.int64), list(ds.ids), ds.attribute_matrix().astype(np.float64),
                     key, c(np.concatenate(stems_v)))


def stem_cache_key(dataset_root: Path, trunk: Trunk, size: int, max_presses: int | None, spec,
                   camera_jpeg: int) -> dict:
    """What a stem cache was made from, the key ``StemCache.load`` checks (train.run.get_cache):
    trunk, size, presses, cache version, dataset folder; the trunk's weights (``trunk_fingerprint``)
    and the dataset's files (``dataset_fingerprint``) - another seed's or weights file's stems, or a
    world drawn again into the same folder, would train tails, heads and a scene model on features
    the exported trunk never computes from the frames the cell is shown; and ``cache_key_extra``."""
    return {"size": size, "arch": trunk.arch, "max_presses": -1 if max_presses is None else max_presses,
            "version": CACHE_VERSION, "dataset": str(Path(dataset_root).resolve()),
            "trunk_sha256": trunk_fingerprint(trunk), "dataset_files_sha256": dataset_fingerprint(dataset_root),
            **cache_key_extra(spec, camera_jpeg)}


# The rest of the preprocessing as every run so far has used it (TactilePreprocess's defaults when
# the key left them out), written out here so that a default changed later changes the key too.
_KEYED_AS_BEFORE = {"crop_fraction": 1.0, "mean": (0.0, 0.0, 0.0), "std": (0.08, 0.08, 0.08), "use_reference": True,
                    "inpaint_markers": False, "normalise_exposure": False}


def cache_key_extra(spec, camera_jpeg: int) -> dict:
    """The feature cache's key beyond size, trunk, presses and dataset: the pixel path, the
    camera's JPEG and the scale it is decoded at, each only when set (a float-path, lossless cache
    keeps its old key, and a JPEG cache of full decodes its own); and every other field of the
    preprocessing that differs from what the key assumed before it held them (``_KEYED_AS_BEFORE``):
    stems of another crop, normalisation, reference use or sensor correction are another input."""
    other = {k: (tuple(float(x) for x in v) if isinstance(v, (tuple, list)) else v)
             for k, v in ((k, getattr(spec, k)) for k in _KEYED_AS_BEFORE)}
    return {**({"reduce": spec.reduce} if spec.reduce else {}), **({"camera_jpeg": camera_jpeg} if camera_jpeg else {}),
            **({"jpeg_scale": spec.jpeg_scale} if spec.jpeg_scale > 1 else {}),
            **{f"preprocess_{k}": repr(v) for k, v in other.items() if v != _KEYED_AS_BEFORE[k]}}


def descriptor_table(dataset_root: Path, name: str, max_presses: int | None = None,
                     progress: bool = True, camera_jpeg: int = 0) -> np.ndarray:
    """(P, D) float32: the no-network tactile descriptor ``name`` (runtime/tactile_descriptor.py,
    the cell's own function) of every press ``extract_cache`` reads, in its row order, each
    against its fabric's no-contact reference. Nothing in it is fitted: the per-dimension
    standardisation comes later from touched training rows only (``compare.split_views``).
    ``camera_jpeg`` Q > 0: each frame through the camera's JPEG at Q first, decoded at full size
    (``camera_frame``; a descriptor reads full frames)."""
    from vs2t_edge.runtime import tactile_descriptor as td
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import camera_frame, check_camera_jpeg

    camera_jpeg = check_camera_jpeg(camera_jpeg)
    ds = load_dataset(dataset_root)
    rows, line, t0 = [], Line(), time.time()
    for k, fabric in enumerate(ds.fabrics):
        ref = td.prepare_reference(camera_frame(fabric.load_reference(), camera_jpeg, 1,
                                                 f"{fabric.id} reference frame"))
        rows += [td.describe(name, camera_frame(fabric.load_press(i), camera_jpeg, 1, f"{fabric.id} press {i}"), ref)
                 for i in extracted_presses(len(fabric.presses), max_presses)]
        if progress:
            line.draw(f"{name}: fabric {k + 1}/{len(ds.fabrics)} ({time.time() - t0:.0f} s)", (k + 1) / len(ds.fabrics))
    if progress:
        line.keep()
    return np.stack(rows).astype(np.float32)


def touched_training_rows(fabric: np.ndarray, fabric_ids: list[str], split) -> tuple[np.ndarray, np.ndarray]:
    """(rows, class index) of the touched TRAINING presses of ``split`` — the same partition
    (``runtime.dataset.press_partition``: the first 70 % of each fabric's presses in press order;
    the next 10 % validate, the last 20 % test) as ``compare.split_views``."""
    # the rows below follow split.touched, so a split that also calls an untouched or validation
    # fabric touched would hand its tactile data to fine-tuning: refuse it here, where every
    # training path (run.run_split, compare.finetuned_tables) takes its rows
    leak = sorted(set(split.touched) & (set(split.untouched) | set(split.validation)))
    if leak:
        raise ZeroShotViolation(f"split (seed {split.seed}) lists {leak} as touched and as untouched/validation: "
                                f"their tactile data would reach fine-tuning")
    from vs2t_edge.runtime.dataset import press_partition

    index = {f: i for i, f in enumerate(fabric_ids)}
    rows, ys = [], []
    for k, fid in enumerate(split.touched):
        r = np.flatnonzero(fabric == index[fid])  # in press order (extract_cache keeps it)
        train = r[press_partition(len(r))[0]]
        rows.append(train)
        ys.append(np.full(len(train), k))
    return np.concatenate(rows), np.concatenate(ys)


def finetune_tail(trunk: Trunk, stem_touched: np.ndarray, y: np.ndarray, n_classes: int, *, epochs: int = 2,
                  max_rows: int | None = None, batch: int = 64, lr: float = 3e-4, seed: int = 0,
                  progress: bool = True, what: str = "tactile", aux: np.ndarray | None = None,
                  aux_weight: float = 0.0) -> Trunk:
    """A copy of ``trunk`` whose tail is fine-tuned (softmax over touched classes) on the given
    touched-train stem activations (tactile frames, or ``what="visual"`` the camera crops at those
    presses). The stem is unchanged (frozen). ``aux``: (rows, k) targets of the same rows, which a
    linear head beside the softmax regresses from the feature, its mean squared error weighted by
    ``aux_weight`` (``attribute_targets``: the touched fabrics' attributes); 0 or None: the softmax
    alone, and the same random draws as before it existed."""
    if aux is not None and len(aux) != len(y):
        raise ValueError(f"fine-tune {what} tail: {len(aux)} auxiliary targets for {len(y)} rows")
    out = copy.deepcopy(trunk)
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    rows = np.arange(len(y))
    if max_rows is not None and len(rows) > max_rows:
        rows = np.sort(np.random.default_rng(seed).choice(rows, max_rows, replace=False))
    a = torch.from_numpy(np.ascontiguousarray(stem_touched[rows], dtype=np.float32))  # one layout: one result
    yt = torch.as_tensor(np.asarray(y)[rows], dtype=torch.long)
    head = nn.Linear(out.feature_dim, n_classes)
    params = [{"params": out.tail.parameters(), "lr": lr}, {"params": head.parameters(), "lr": 10 * lr}]
    at = None
    if aux is not None and aux_weight > 0:
        at = torch.from_numpy(np.ascontiguousarray(np.asarray(aux)[rows], dtype=np.float32))
        aux_head = nn.Linear(out.feature_dim, at.shape[1])  # drawn after the softmax head: its draws unchanged
        params.append({"params": aux_head.parameters(), "lr": 10 * lr})
    opt = torch.optim.Adam(params)
    out.tail.train()
    line = Line()
    t0 = time.time()
    for ep in range(epochs):
        perm = torch.randperm(len(yt), generator=gen)
        for j, i0 in enumerate(range(0, len(perm), batch)):
            idx = perm[i0:i0 + batch]
            if len(idx) < 2:  # BatchNorm needs 2 samples
                continue
            f = out.features_from_stem(a[idx])
            loss = nn.functional.cross_entropy(head(f), yt[idx])
            if at is not None:
                loss = loss + aux_weight * nn.functional.mse_loss(aux_head(f), at[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
        if progress:
            line.draw(f"fine-tune {what} tail: epoch {ep + 1}/{epochs} loss {loss.item():.3f} "
                      f"({time.time() - t0:.0f} s)", (ep + 1) / epochs)
    if progress:
        line.keep()
    out.eval()
    return out


def attribute_targets(attributes: np.ndarray, fabric: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Per row of ``rows`` (touched-train presses), its fabric's attributes, each standardised over
    the distinct fabrics of those rows - the touched ones, no other fabric's row is read - as
    ``finetune_tail``'s auxiliary targets. An attribute constant over them is 0 (nothing to learn)."""
    fab = np.asarray(fabric)[rows]
    a = np.asarray(attributes, np.float64)
    seen = a[np.unique(fab)]
    z = (a[fab] - seen.mean(0)) / (seen.std(0) + 1e-6)
    return z.astype(np.float32)


def visual_tail_seed(split_seed: int) -> int:
    """The visual tail's fine-tuning seed (the tactile tail's is the split seed)."""
    return split_seed + 1


@dataclass
class SplitFeatures:
    """``finetune_split``'s result: features of every press, and what it took."""

    x_t: np.ndarray
    x_v: np.ndarray
    n_rows: int  # touched-train presses the tails were fine-tuned on
    tactile_trunk: Trunk | None  # the tactile-tuned trunk (None: tactile features frozen)
    seconds_t: float  # rows + tactile tail
    seconds_v: float  # visual tail (0 when frozen)


def finetune_split(cache: StemCache, trunk: Trunk, split, *, epochs: int, max_rows: int | None,
                   tactile: bool = True, visual: bool = False, progress: bool = True,
                   attributes: float = 0.0) -> SplitFeatures:
    """The features of one split as `vs2t-edge train` makes them (and `compare --run` re-makes
    them): ``split``'s touched-train rows, the tactile tail fine-tuned on them (seed split seed)
    and, with ``visual``, the visual tail on the camera crops at the same presses (seed
    ``visual_tail_seed``); each tail starts from ``trunk``'s weights (``finetune_tail`` copies it).
    A tail not fine-tuned gives the cache's frozen features. ``attributes``: the weight of the
    tactile tail's second task, regressing each press's fabric attributes (``attribute_targets``;
    ``Profile.ft_attributes``, docs/training.md "Touch that attributes can predict")."""
    t0 = time.time()
    rows, y = touched_training_rows(cache.fabric, cache.fabric_ids, split)
    x_t, x_v, tuned = cache.x_t0, cache.x_v, None
    if tactile:
        aux = attribute_targets(cache.attributes, cache.fabric, rows) if attributes > 0 else None
        tuned = finetune_tail(trunk, cache.stem_t[rows], y, len(split.touched), epochs=epochs, max_rows=max_rows,
                              seed=split.seed, progress=progress, aux=aux, aux_weight=attributes)
        x_t = features_from_stem(tuned, cache.stem_t)
    t_t, t_v = time.time() - t0, 0.0
    if visual:
        # the camera crops at the same touched-train presses, softmax over the same touched
        # classes; untouched and validation crops only pass through the tuned tail afterwards
        t1 = time.time()
        tuned_v = finetune_tail(trunk, cache.stem_v[rows], y, len(split.touched), epochs=epochs, max_rows=max_rows,
                                seed=visual_tail_seed(split.seed), progress=progress, what="visual")
        x_v = features_from_stem(tuned_v, cache.stem_v)
        t_v = time.time() - t1
    return SplitFeatures(x_t, x_v, len(rows), tuned, t_t, t_v)


@torch.no_grad()
def features_from_stem(trunk: Trunk, stem: np.ndarray, chunk: int = 512) -> np.ndarray:
    trunk.eval()
    out = []
    for i in range(0, len(stem), chunk):
        x = torch.from_numpy(np.ascontiguousarray(stem[i:i + chunk], np.float32))  # one layout: one result
        out.append(trunk.features_from_stem(x).numpy())
    return np.concatenate(out).astype(np.float32)


__all__ = ["StemCache", "ZeroShotViolation", "extract_cache", "stem_cache_key", "trunk_fingerprint", "dataset_fingerprint", "extracted_presses", "cache_key_extra", "descriptor_table", "touched_training_rows", "finetune_tail",
           "features_from_stem", "attribute_targets", "visual_tail_seed", "SplitFeatures", "finetune_split"]

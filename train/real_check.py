"""`vs2t-edge real-check`: does the tactile trunk tell materials apart on a real sensor's frames?

Input is a folder of ``material_*/`` folders, each holding one material's press images in press
order (file names sort in time: ``press_001.png``, ...). Evaluated as a cell lives: earlier
presses fit, later presses test, never a random permutation within a material (neighbouring
presses share lighting, gel state and position, and flatter). Without ``--test``, the temporal
split of the one folder: fold A fits each material's first half and tests its second half, fold B
its first three quarters and tests the last quarter (never the reverse: a cell never meets its
earlier presses after its later ones). With ``--test``, the train folder fits and the test folder tests (one fold).

Per feature pipeline (``PIPELINES``):

- closed-set accuracy over all materials: nearest class mean on L2-normalised features; linear
  discriminant analysis (``runtime.scene_model.SceneModel``: shared-covariance Gaussians in a
  whitened principal subspace of the fit presses); and shrunk LDA (the same shared covariance in
  the full feature space, shrunk towards a multiple of the identity by the Ledoit-Wolf amount);
- novelty AUROC with 70 % of the materials touched and the rest untouched, over ``n_seeds``
  seeded material draws (mean and spread), each draw reading the touched materials' fit presses
  alone (its standardisation, and the background or marker count of a pipeline that fits one;
  the ``finetuned`` trunk, tuned on every material, gets none): k-nearest-neighbour cosine distance to the touched fit
  presses, the LDA model's smallest squared distance to a touched class, and each of the cell's
  routers (``CHECK_ROUTERS``, runtime/novelty.py) fitted with ``fit_router`` on the touched fit
  presses as training fits them - among them ``discriminant`` (discriminant Gaussians: the
  smallest distance to a touched class in Fisher's discriminant subspace of the touched classes,
  ``discriminant_sq_distances``); the logit routers read the shrunk LDA's logits of the touched
  materials (``router_aurocs``).

Pipelines: ``frozen`` (the floor: the frozen ImageNet EfficientNet-Lite0 on the whole frame
resized, as the cell's trunk sees it before fine-tuning); ``finetuned`` (the same trunk and input,
its tail tuned per fold on the fit presses only with shifts and brightness / contrast jitter,
epochs chosen inside the fit presses: train/real_finetune.py); ``inpainted`` (GelSight-aware: markers
found as dark dots and inpainted, the session's median fit frame subtracted as the background -
these recordings have no no-contact frame - the LED gradient removed by a low-pass, contrast
normalised, then the same trunk); ``markers`` (no network: the marker grid's centres and areas,
the gel's shear and compliance); ``shading`` (no network: the gel's coarse colour field, markers
inpainted and exposure cancelled, ``shading_features``); ``shading_markers`` (the cell's own
descriptor, ``runtime.tactile_descriptor.shading_markers``: the shading and the marker dots'
sub-pixel displacement against a no-contact frame - here the median fit press, as these recordings
have none - averaged per grid cell).

Nothing is tuned on test presses. ``--within-fit`` evaluates inside each fold's fit presses only
(split the same way: earlier ones fit, later ones test); the shading grid, the exposure
normalisation, the marker centres and the novelty score were chosen on those numbers
(docs/realism.md). Shrinkage is estimated from the fit presses; the LDA subspace size is a fixed
fraction of them.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# the real-sensor preprocessing lives with the cell's one preprocessing (numpy and OpenCV only)
# shading_grid: real-check's callers (and tests) read it here  # noqa below
from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime.covariance import within_class_whitening
from vs2t_edge.runtime.preprocess import check_frame, inpaint_markers, marker_mask, shading_grid  # noqa: F401
from vs2t_edge.runtime.preprocess import shading_descriptor as shading_features
from vs2t_edge.runtime.tactile_descriptor import dot_centres, grid_order
from vs2t_edge.runtime.tactile_descriptor import prepare_reference as prepare_descriptor_reference
from vs2t_edge.runtime.tactile_descriptor import shading_markers as tactile_descriptor
from vs2t_edge.train.stats import sample_sd

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
PIPELINES = ("frozen", "finetuned", "inpainted", "markers", "shading", "shading_markers")
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406])
IMAGENET_STD = np.array([0.229, 0.224, 0.225])
TRUNK_PX = 224
N_SEEDS = 10
TOUCHED_SHARE = 0.7
KNN = 3
FIT_SHARES = (0.5, 0.75)  # each temporal fold fits this share of a material's presses, the first ones
# pipelines whose features read the fit presses of every material (a median background, a marker
# count): for novelty they are made again per draw from the touched materials' fit presses alone
REFIT_PER_DRAW = ("inpainted", "markers", "shading_markers")
# a trunk tuned on every material's fit presses has seen the untouched ones: no novelty AUROC
NO_NOVELTY = ("finetuned",)
ACCURACY_KEYS = ("nearest_mean", "lda", "shrunk_lda")
# the cell's routers (runtime/novelty.py) the check can fit: every feature router, and the logit
# routers on a touched classifier's logits; calibrated stacking needs an untouched head (CLS_u, from
# the untouched classes' attributes and images), which a folder of press images has not
CHECK_ROUTERS = (*nv.FEATURE_ROUTERS, "energy", "max_softmax")
AUROC_KEYS = ("knn", "lda", *CHECK_ROUTERS)


class RealCheckError(ValueError):
    """A folder that is not a real-check layout, or a frame that cannot be used; names the path."""


@dataclass
class Materials:
    names: list[str]
    frames: list[list[np.ndarray]]  # per material, HxWx3 uint8 BGR in press order
    files: list[list[Path]]


def _natural(path: Path) -> tuple:
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name))


def load_materials(root: Path | str) -> Materials:
    """The ``material_*/`` folders of ``root`` and their images in press order; every frame of
    one size (the first frame's). Raises RealCheckError naming the folder or file."""
    from vs2t_edge.runtime.dataset import read_image

    root = Path(root)
    if not root.is_dir():
        raise RealCheckError(f"{root}: not a folder")
    folders = sorted((p for p in root.iterdir() if p.is_dir() and p.name.startswith("material_")), key=_natural)
    if len(folders) < 2:
        raise RealCheckError(f"{root}: needs at least 2 material_*/ folders of press images, found {len(folders)}")
    names, frames, files, hw = [], [], [], None
    for folder in folders:
        paths = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural)
        if len(paths) < 2:
            raise RealCheckError(f"{folder}: needs at least 2 press images ({', '.join(IMAGE_SUFFIXES)}), found {len(paths)}")
        imgs = []
        for p in paths:
            try:
                # the cell's own frame check too: a black, white or saturated frame is no press
                img = check_frame(read_image(p), name=str(p))
            except ValueError as exc:
                raise RealCheckError(str(exc)) from None
            if hw is None:
                hw = img.shape[:2]
            elif img.shape[:2] != hw:
                raise RealCheckError(f"{p}: {img.shape[1]}x{img.shape[0]} px, but the first frame is {hw[1]}x{hw[0]}: "
                                     "one sensor, one frame size")
            imgs.append(img)
        names.append(folder.name)
        frames.append(imgs)
        files.append(paths)
    return Materials(names, frames, files)


def temporal_folds(n_presses: list[int]) -> list[tuple[list[np.ndarray], list[np.ndarray]]]:
    """Per fold, per material: (fit press indices, test press indices). Every fold fits earlier
    presses and tests later ones, as the cell lives: fold A fits the first half of each material's
    presses and tests the second; fold B fits the first three quarters and tests the last quarter
    (a test set inside A's, with more to fit). Never the reverse, never interleaved; B is left out
    where it would be A again (two presses a material)."""
    folds = []
    for share in FIT_SHARES:
        cut = [min(n - 1, max(1, int(n * share))) for n in n_presses]
        fold = ([np.arange(c) for c in cut], [np.arange(c, n) for c, n in zip(cut, n_presses)])
        if not any(all(len(a) == len(b) for a, b in zip(fold[0], f[0])) for f in folds):
            folds.append(fold)
    return folds


# ------------------------------------------------------------------ features

def inpainted_difference(image: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Markers inpainted, the background subtracted, the LED gradient (a 25 px low-pass) removed,
    contrast normalised: HxWx3 float RGB in [0, 1]."""
    import cv2

    clean = inpaint_markers(image).astype(np.float32)
    d = clean - background
    d = d - cv2.GaussianBlur(d, (0, 0), 25)
    d = d / (float(d.std()) + 1e-6)
    return np.clip(0.5 + 0.15 * d, 0.0, 1.0)[..., ::-1]


def marker_features(image: np.ndarray) -> np.ndarray:
    """Centres (x, y) and areas of the marker dots in grid order. Empty when no dot is found."""
    import cv2

    n, _, stats, centres = cv2.connectedComponentsWithStats(marker_mask(image))
    keep = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] > 15]
    c, a = centres[keep], stats[keep, cv2.CC_STAT_AREA].astype(np.float64)
    if len(c) < 2:
        return np.zeros(0)
    order = grid_order(c)
    return np.concatenate([c[order].ravel(), a[order]])


def marker_centroids(image: np.ndarray) -> np.ndarray:
    """Sub-pixel centres (x, y) of the marker dots in grid order, flattened; empty when none
    (``runtime.tactile_descriptor.dot_centres``, the cell's own)."""
    c = dot_centres(image)
    return c[grid_order(c)].ravel() if len(c) >= 2 else np.zeros(0)


def session_reference(frames: list[list[np.ndarray]], fit: list[np.ndarray]) -> np.ndarray:
    """The resting gel of a recording without no-contact frames: the median of the fit presses of
    every material (uint8). Where the cell has the item's own no-contact frame, this stands in."""
    return np.median(np.stack([fs[i] for fs, idx in zip(frames, fit) for i in idx]), axis=0).astype(np.uint8)


class FrozenTrunk:
    """The frozen ImageNet EfficientNet-Lite0 (offline weights, the [train] extra), batch features."""

    def __init__(self) -> None:
        import torch

        from vs2t_edge.train.realdata_check import make_trunk

        torch.set_num_threads(1)
        self.torch = torch
        self.net, self.dim = make_trunk(pretrained=True)
        self.net.eval()

    def __call__(self, rgb01: list[np.ndarray]) -> np.ndarray:
        with self.torch.no_grad():
            return self.net(self.torch.from_numpy(trunk_input(rgb01))).numpy().astype(np.float64)


def trunk_input(rgb01: list[np.ndarray]) -> np.ndarray:
    """Frames (HxWx3 float RGB in [0, 1]) as the trunk's batch: resized to TRUNK_PX square,
    ImageNet-normalised, (N, 3, TRUNK_PX, TRUNK_PX) float32."""
    import cv2

    x = np.stack([cv2.resize(im, (TRUNK_PX, TRUNK_PX), interpolation=cv2.INTER_AREA) for im in rgb01])
    return ((x - IMAGENET_MEAN) / IMAGENET_STD).transpose(0, 3, 1, 2).astype(np.float32)


def pipeline_features(pipeline: str, frames: list[list[np.ndarray]], fit: list[np.ndarray],
                      trunk: FrozenTrunk | None, log=lambda m: None) -> list[np.ndarray]:
    """Per material, (presses, D) features of every press. The background of ``inpainted`` is the
    median of the fit presses only (of every material: the session's resting gel); ``finetuned``
    tunes a fresh copy of the trunk on the fit presses only (train/real_finetune.py). A pipeline
    that reads ``fit`` belongs in ``REFIT_PER_DRAW`` (or ``NO_NOVELTY``): else its novelty draws
    read the untouched materials' presses."""
    if pipeline == "finetuned":
        from vs2t_edge.train.real_finetune import finetuned_features

        return finetuned_features(frames, fit, log=log)
    if pipeline == "frozen":
        return [trunk([im[..., ::-1].astype(np.float64) / 255 for im in fs]) for fs in frames]
    if pipeline == "inpainted":
        background = np.median(np.stack([fs[i] for fs, idx in zip(frames, fit) for i in idx]), axis=0).astype(np.float32)
        return [trunk([inpainted_difference(im, background) for im in fs]) for fs in frames]
    if pipeline == "shading":
        return [np.stack([shading_features(im) for im in fs]) for fs in frames]
    if pipeline == "shading_markers":  # the cell's descriptor, against the session's resting gel
        reference = prepare_descriptor_reference(session_reference(frames, fit))
        return [np.stack([tactile_descriptor(im, reference) for im in fs]).astype(np.float64) for fs in frames]
    if pipeline == "markers":
        return _dot_grid(marker_features, frames, fit)
    raise RealCheckError(f"unknown pipeline {pipeline!r}: choose from {', '.join(PIPELINES)}")


def _dot_grid(describe, frames: list[list[np.ndarray]], fit: list[np.ndarray]) -> list[np.ndarray]:
    """Per material, (presses, D) of a marker-dot description (``marker_features``)."""
    raw = [[describe(im) for im in fs] for fs in frames]
    # a frame whose dot count differs from the fit frames' usual one (a dot lost at the edge,
    # merged dots) has no comparable grid: NaN, read as the fit mean when standardised
    n = int(np.median([len(vs[i]) for vs, idx in zip(raw, fit) for i in idx]))
    if n == 0:
        raise RealCheckError("markers: no marker dots found in the fit frames (an unmarked gel?)")
    return [np.stack([v if len(v) == n else np.full(n, np.nan) for v in vs]) for vs in raw]


# ------------------------------------------------------------------ evaluation

def _l2(x: np.ndarray) -> np.ndarray:
    return x / (np.linalg.norm(x, axis=-1, keepdims=True) + 1e-12)


def _standardise(fit_x: np.ndarray, *xs: np.ndarray) -> list[np.ndarray]:
    mu = np.nanmean(fit_x, axis=0)
    sd = np.nanstd(fit_x, axis=0) + 1e-9
    return [np.where(np.isnan(x), 0.0, (x - mu) / sd) for x in (fit_x, *xs)]


def _lda(x: np.ndarray, y: np.ndarray, n_classes: int):
    from vs2t_edge.runtime.scene_model import SceneModel

    k = int(max(2, min(32, len(x) - n_classes, x.shape[1])))
    return SceneModel.fit(x, y, [str(c) for c in range(n_classes)], np.zeros((0, x.shape[1])), np.zeros(0), [],
                          k=k, shrinkage=0.3)


def _whitened(x: np.ndarray, y: np.ndarray, n_classes: int) -> tuple[np.ndarray, np.ndarray]:
    """(class means, W): W whitens the pooled within-class covariance, shrunk towards a multiple of
    the identity by the Ledoit-Wolf amount - estimated from the fit presses, so no knob is tuned
    (``runtime.covariance.within_class_whitening``, the discriminant router's own)."""
    means, w, _, _ = within_class_whitening(x, y, n_classes)
    return means, w


def shrunk_lda_sq_distances(x: np.ndarray, y: np.ndarray, n_classes: int, query: np.ndarray) -> np.ndarray:
    """(queries, classes) squared Mahalanobis distances under the shared, shrunk within-class
    covariance in the full feature space (linear discriminant analysis without a PCA cut)."""
    means, w = _whitened(x, y, n_classes)
    return _sq_to_means(query, means, w)


def _sq_to_means(query: np.ndarray, means: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(queries, classes) squared distances to ``means`` after the whitening ``w``."""
    return (((query @ w)[:, None, :] - (means @ w)[None]) ** 2).sum(-1)


def discriminant_sq_distances(x: np.ndarray, y: np.ndarray, n_classes: int, query: np.ndarray) -> np.ndarray:
    """(queries, classes) squared distances to the class means in Fisher's discriminant subspace:
    the ``n_classes - 1`` directions of largest between- over within-class variance (within-class
    covariance whitened and shrunk as ``_whitened``), where every class is a unit Gaussian. With a
    few presses per class in a wide feature, the full-space distance is dominated by directions
    the fit presses never pinned down; the subspace keeps only what tells the fit classes apart,
    so a press of an unseen material lands far from every class instead of near some. It is the
    cell's ``discriminant`` router (runtime/novelty.py); ``y`` holds every class 0..n_classes-1."""
    if set(np.unique(y).tolist()) != set(range(n_classes)):
        raise RealCheckError(f"discriminant: labels must be 0..{n_classes - 1}, each with presses")
    return nv.DiscriminantRouter.fit(x, y).sq_distances(query)


def router_aurocs(x: np.ndarray, y: np.ndarray, n_classes: int, q_in: np.ndarray, q_out: np.ndarray) -> dict:
    """Novelty AUROC (touched test presses ``q_in`` against untouched ``q_out``) of each router the
    cell can run here (``CHECK_ROUTERS``), fitted with ``runtime.novelty.fit_router`` on the touched
    fit presses ``x`` (labels ``y`` in 0..n_classes-1) as training fits them. The logit routers
    read a touched classifier fitted on the same presses: the shrunk LDA, logits = -1/2 its squared
    distances (its class log-likelihoods). None where a router cannot be fitted (the discriminant
    router on one touched class)."""
    from vs2t_edge.runtime.router_eval import auroc

    means, w = _whitened(x, y, n_classes)  # the shrunk LDA's, once for both query sets
    logits = [-0.5 * _sq_to_means(q, means, w) for q in (q_in, q_out)]
    out = {}
    for name in CHECK_ROUTERS:
        opts = {"keep_covariance": False} if name in nv.GAUSSIAN_ROUTERS else {}
        try:
            router = nv.fit_router(name, x, touched_labels=y, **opts)
        except nv.RouterError:
            out[name] = None
            continue
        out[name] = auroc(*(router.novelty(q, lt) for q, lt in zip((q_in, q_out), logits)))
    return out


def evaluate_fold(feats: list[np.ndarray], fit: list[np.ndarray], test: list[np.ndarray], *,
                  n_seeds: int = N_SEEDS, seed: int = 0, touched_features=None, novelty: bool = True) -> dict:
    """Closed-set accuracy over every material and novelty AUROC over seeded material draws. Each
    draw reads what a cell that touched only its touched materials would have: the standardisation
    is fitted on their fit presses, and ``touched_features(touched)`` (for a pipeline whose features
    read fit presses) makes the features again from theirs alone. ``novelty=False``: no draw, no
    AUROC (empty lists), for features that have seen every material."""
    from vs2t_edge.runtime.router_eval import auroc

    n = len(feats)
    fy = np.concatenate([np.full(len(i), c) for c, i in enumerate(fit)])
    ty = np.concatenate([np.full(len(i), c) for c, i in enumerate(test)])

    def stacked(fs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        return (np.concatenate([f[i] for f, i in zip(fs, fit)]), np.concatenate([f[i] for f, i in zip(fs, test)]))

    fx, tx = _standardise(*stacked(feats))
    fxn, txn = _l2(fx), _l2(tx)
    means = _l2(np.stack([fxn[fy == c].mean(0) for c in range(n)]))
    acc_ncm = float(np.mean(np.argmax(txn @ means.T, axis=1) == ty))
    lda = _lda(fx, fy, n)
    acc_lda = float(np.mean(lda.sq_distances(tx).argmin(1) == ty))
    acc_shrunk = float(np.mean(shrunk_lda_sq_distances(fx, fy, n, tx).argmin(1) == ty))
    n_t = max(1, min(n - 1, round(TOUCHED_SHARE * n)))
    knn, gauss = [], []
    routers: dict[str, list] = {name: [] for name in CHECK_ROUTERS}
    for s in range(n_seeds if novelty else 0):
        perm = np.random.default_rng(seed + s).permutation(n)
        touched = perm[:n_t]
        raw_f, raw_t = stacked(touched_features(touched) if touched_features else feats)
        keep_f = np.isin(fy, touched)
        t_in, t_out = np.isin(ty, touched), ~np.isin(ty, touched)
        dx, dt = _standardise(raw_f[keep_f], raw_t)
        ref = _l2(dx)

        def knn_score(q: np.ndarray) -> np.ndarray:
            d = np.sort(1.0 - _l2(q) @ ref.T, axis=1)
            return d[:, :min(KNN, d.shape[1])].mean(1)

        knn.append(auroc(knn_score(dt[t_in]), knn_score(dt[t_out])))
        remap = {c: j for j, c in enumerate(touched)}
        y_t = np.array([remap[c] for c in fy[keep_f]])
        m = _lda(dx, y_t, n_t)
        gauss.append(auroc(m.sq_distances(dt[t_in]).min(1), m.sq_distances(dt[t_out]).min(1)))
        for name, a in router_aurocs(dx, y_t, n_t, dt[t_in], dt[t_out]).items():
            routers[name].append(a)
    return {"accuracy": {"nearest_mean": acc_ncm, "lda": acc_lda, "shrunk_lda": acc_shrunk},
            "auroc": {"knn": knn, "lda": gauss, **routers}, "touched_materials": n_t}


def _touched_only(name: str, frames: list[list[np.ndarray]], fit: list[np.ndarray], trunk):
    """A draw's features for ``name``: made from the fit presses of its touched materials alone."""
    return lambda touched: pipeline_features(name, frames, [f if m in touched else f[:0] for m, f in enumerate(fit)],
                                             trunk)


def run_real_check(train_dir: Path, test_dir: Path | None = None, pipelines: tuple[str, ...] = PIPELINES,
                   n_seeds: int = N_SEEDS, log=lambda m: None, within_fit: bool = False) -> dict:
    """The check. ``within_fit``: instead of testing, split each fold's fit presses in two by press
    order as ``temporal_folds`` splits a material's presses and evaluate there - the numbers to
    choose a pipeline or setting by; the fold's test presses are never read."""
    t0 = time.time()
    train = load_materials(train_dir)
    if test_dir is not None:
        test = load_materials(test_dir)
        if test.names != train.names:
            raise RealCheckError(f"{test_dir}: materials {test.names} differ from {train_dir}'s {train.names}")
        if test.frames[0][0].shape != train.frames[0][0].shape:
            raise RealCheckError(f"{test.files[0][0]}: frame size differs from {train.files[0][0]}'s")
        frames = [a + b for a, b in zip(train.frames, test.frames)]
        folds = [([np.arange(len(a)) for a in train.frames],
                  [np.arange(len(a), len(a) + len(b)) for a, b in zip(train.frames, test.frames)])]
        protocol = "fit on --train, test on --test"
    else:
        frames = train.frames
        folds = temporal_folds([len(fs) for fs in frames])
        protocol = "temporal: fold A fits each material's first half of presses and tests the second, " \
                   "fold B its first three quarters and tests the last quarter"
    # (frames, fit, test) per evaluated fold
    runs = [(frames, fit, test_idx) for fit, test_idx in folds]
    if within_fit:
        runs = []
        for fit, _ in folds:
            if min(map(len, fit)) < 2:
                raise RealCheckError("--within-fit needs at least 2 fit presses per material in every fold")
            sub = [[fs[i] for i in idx] for fs, idx in zip(frames, fit)]
            runs += [(sub, f, t) for f, t in temporal_folds([len(x) for x in sub])]
        protocol = f"within the fit presses only ({protocol}): each fold's fit presses split by press order " \
                   "the same way, earlier ones fit and later ones test; test presses never read"
    h, w = frames[0][0].shape[:2]
    log(f"real-check: {len(frames)} materials, {sum(map(len, frames))} presses of {w}x{h} px; {protocol}")
    trunk = FrozenTrunk() if {"frozen", "inpainted"} & set(pipelines) else None
    results = {}
    for name in pipelines:
        folds_out = []
        for k, (fr, fit, test_idx) in enumerate(runs):
            log(f"real-check: {name}, fold {k + 1}/{len(runs)}")
            feats = pipeline_features(name, fr, fit, trunk, log)
            refit = _touched_only(name, fr, fit, trunk) if name in REFIT_PER_DRAW else None
            folds_out.append(evaluate_fold(feats, fit, test_idx, n_seeds=n_seeds, touched_features=refit,
                                           novelty=name not in NO_NOVELTY))
        results[name] = summarise(folds_out)
    return {"train": str(train_dir), "test": str(test_dir) if test_dir else None, "protocol": protocol,
            "materials": train.names, "presses": [len(fs) for fs in frames], "frame_px": [w, h],
            "n_seeds": n_seeds, "touched_share": TOUCHED_SHARE, "pipelines": results,
            "seconds": round(time.time() - t0, 1)}


def summarise(folds: list[dict]) -> dict:
    out = {"folds": folds}
    for clf in ACCURACY_KEYS:
        v = [f["accuracy"][clf] for f in folds]
        out[f"accuracy_{clf}"] = {"mean": float(np.mean(v)), "std": sample_sd(v)}
    for score in AUROC_KEYS:
        # over every seeded draw of every fold; None where the router could not be fitted
        v = [a for f in folds for a in f["auroc"][score] if a is not None]
        out[f"auroc_{score}"] = {"mean": float(np.mean(v)), "std": sample_sd(v)} if v else \
            {"mean": None, "std": None}
    return out


TARGET_ACCURACY, TARGET_AUROC = 0.90, 0.85


COLUMN_NAMES = {"accuracy_nearest_mean": "accuracy, nearest mean", "accuracy_lda": "accuracy, LDA",
                "accuracy_shrunk_lda": "accuracy, shrunk LDA", "auroc_knn": "AUROC, kNN", "auroc_lda": "AUROC, LDA",
                **{f"auroc_{r}": f"AUROC, router {r}" for r in CHECK_ROUTERS},
                "auroc_discriminant": "AUROC, router discriminant (discriminant Gaussians)"}


def render_table(result: dict) -> str:
    cols = [f"accuracy_{k}" for k in ACCURACY_KEYS] + [f"auroc_{k}" for k in AUROC_KEYS]
    lines = [f"{result['protocol']}; {len(result['materials'])} materials, frames {result['frame_px'][0]}x"
             f"{result['frame_px'][1]} px; novelty: {result['touched_share']:.0%} of materials touched, "
             f"{result['n_seeds']} seeded draws per fold; mean ± std, %",
             "| pipeline | " + " | ".join(COLUMN_NAMES[c] for c in cols) + " |",
             "| --- |" + " --- |" * len(cols)]
    for name, r in result["pipelines"].items():
        cells = ("n/a" if r[c]["mean"] is None else f"{100 * r[c]['mean']:.1f} ± {100 * r[c]['std']:.1f}"
                 for c in cols)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")

    def verdict(prefix: str, target: float, form: str) -> str:
        scored = [(r[c]["mean"], f"{name}, {COLUMN_NAMES[c]}") for name, r in result["pipelines"].items()
                  for c in cols if c.startswith(prefix) and r[c]["mean"] is not None]
        if not scored:  # the finetuned trunk alone has no novelty AUROC
            return "not measured"
        value, at = max(scored)
        return f"best {value:{form}}, {at}: {'met' if value >= target else 'missed'}"

    lines.append(f"targets: accuracy >= {TARGET_ACCURACY:.0%} ({verdict('accuracy', TARGET_ACCURACY, '.1%')}), "
                 f"AUROC >= {TARGET_AUROC:.2f} ({verdict('auroc', TARGET_AUROC, '.2f')})")
    return "\n".join(lines)


__all__ = ["RealCheckError", "load_materials", "temporal_folds", "run_real_check", "render_table", "PIPELINES"]

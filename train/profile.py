"""What a run trains with: the profile (``Profile``, ``PROFILES``), the tactile preprocessing it
implies for a dataset (``tactile_spec``: the one the bundle ships and the cell runs), and the checks
of a profile against a world (touched fabrics, validation folds). `vs2t-edge train` is train/run.py."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime.preprocess import TactilePreprocess, auto_reduce, float_path_scale
from vs2t_edge.train.folds import folds_fit


@dataclass
class Profile:
    name: str
    trunk: str = "efficientnet_lite0"
    size_px: int = 128  # tactile and visual network input side
    splits: int = 1
    max_presses: int | None = None  # per fabric, feature extraction
    ft_epochs: int = 2
    ft_max_rows: int | None = 3000  # touched-train presses used to fine-tune the tactile (and visual) tail
    # "frozen": visual features from the ImageNet trunk as is; "finetuned": the visual tail is
    # fine-tuned per split like the tactile one (softmax over touched classes, the camera crops at
    # the touched-train presses only). Chosen per profile on its validation fabrics
    # (docs/training.md "Visual tail: frozen or fine-tuned"): small profile frozen (VS2T-ZSL val
    # ZSL 67.1 vs 64.0 over 3 splits of 3 validation fabrics); paper profile fine-tuned (61.8 vs
    # 61.4, and every ablation that sees vision +1.5..+4.3, 5 splits of 5 validation fabrics).
    visual_tail: str = "frozen"
    # the tactile tail's second task beside the softmax: regress each touched-train press's fabric
    # attributes (standardised over the touched fabrics), its squared error weighted so; 0: the
    # softmax alone (every run before 2026-11-30, and the tiny test profile). It makes the features
    # carry what attributes can predict, where a generator conditioned on them can reach
    # (docs/training.md "Touch that attributes can predict"): 1 in the small and paper profiles,
    # chosen on validation jobs of both worlds (demo world +5.7 points right, paper +1.4; 3 was
    # no better on the demo world's).
    ft_attributes: float = 0.0
    encoder_condition: bool = False  # E = q(z | x, v, s) as the paper's (True) or q(z | x) (docs/training.md)
    steps: int = 800  # generator optimiser steps
    batch: int = 64
    cls_steps: int = 300
    n_synth_per_class: int = 200
    lr_scale: float = 5.0
    latent: int = 64
    hidden: int | None = 512  # E / G width; None = feature size (the paper's 2048 for 2048-d); 512 for CPU time
    seed: int = 0
    # GZSL routers evaluated on every split (beta of each tuned on the validation fabrics); each
    # split's is chosen by VALIDATION AUSUC of VS2T-ZSL on its own validation fabrics (``choose_router``).
    # "gaussian" (the paper's) is always reported beside it.
    routers: tuple[str, ...] = nv.ROUTERS
    # the tactile feature: "cnn" = the trunk above, its tail fine-tuned per split; or a no-network
    # descriptor of runtime/tactile_descriptor.py ("shading_markers", what wins on a real GelSight:
    # docs/realism.md), nothing fine-tuned, exported as a descriptor bundle (docs/bundle.md). The
    # visual side keeps the trunk either way.
    tactile_feature: str = "cnn"
    # the tactile frames' pixel path (runtime/preprocess.py): "off" = the float path of every run
    # before it; "auto" = the reduced uint8 path at the largest reduction that leaves ``size_px``
    # pixels across the crop (2 on 640x480 frames at 128 or 224 px); or a factor "1", "2", "4", "8".
    preprocess_reduce: str = "off"
    # the tactile camera's MJPEG quality the model trains for: 0 = the dataset's lossless frames
    # (every run before it); Q in 1..100 = every press and no-contact frame through a JPEG at Q,
    # decoded at the bundle's scale, as a UVC camera hands them (runtime.preprocess.through_camera_jpeg;
    # docs/training.md "The camera's JPEG"). Export and the bench read the run's frames the same way.
    camera_jpeg: int = 0
    # with ``camera_jpeg`` on the float path: the scale the camera's JPEG is decoded at, as the cell's
    # devices.camera.decode_scale: "auto" = ``float_path_scale`` of the dataset's frames (1/2 of
    # 640x480 at 128 or 224 px), what the cell's camera then decodes at; "full" = full decodes (every
    # such run before 2026-11-29). The reduced path decodes at 1/reduce either way.
    camera_decode: str = "auto"
    # per split, train on only this many of its touched fabrics (``splits.fewer_touched``: a nested
    # draw with the split's seed; the rest take no part); None: all of them. Prices the fabrics a
    # cell has touched (docs/results/zero_shot_limits_paper.md, "More touched fabrics").
    touched: int | None = None
    # the share of pieces in a wrong bin the scene decision's search on validation jobs must keep
    # under (train/decision.py); the report prices decision.MIS_SORT_TARGETS beside it
    mis_sort_target: float = 0.01
    # the scene decision's validation worlds beyond the split's own validation fabrics: folds of the
    # touched fabrics, each held out of a generator trained on the others (train/folds.py); 0: none
    validation_folds: int = 0


REDUCE_CHOICES = ("off", "auto", "1", "2", "4", "8")
CAMERA_DECODES = ("auto", "full")


def tactile_spec(prof: Profile, dataset: Path, frame_hw: tuple[int, int] | None = None) -> TactilePreprocess:
    """The one preprocessing this run trains with and its bundle ships (the cell runs the same).
    ``frame_hw``: the dataset's frame size when the caller has it (else read from its geometry,
    only by the choices that need it)."""
    if prof.preprocess_reduce not in REDUCE_CHOICES:
        raise ValueError(f"preprocess_reduce {prof.preprocess_reduce!r}: choose one of {', '.join(REDUCE_CHOICES)}")
    if prof.camera_decode not in CAMERA_DECODES:
        raise ValueError(f"camera_decode {prof.camera_decode!r}: choose one of {', '.join(CAMERA_DECODES)}")
    spec = TactilePreprocess(size=prof.size_px)
    if prof.tactile_feature != "cnn":  # a descriptor reads full frames
        return spec
    if prof.preprocess_reduce == "off":
        if not _camera_decode_applies(prof) or prof.camera_decode == "full":
            return spec
        # trained on the frames the cell's camera decodes at auto (runtime/wiring.py model_decode_scale)
        return replace(spec, jpeg_scale=float_path_scale(spec, frame_hw or _frame_hw(dataset)))
    if prof.preprocess_reduce == "auto":
        return replace(spec, reduce=auto_reduce(frame_hw or _frame_hw(dataset), prof.size_px))
    return replace(spec, reduce=int(prof.preprocess_reduce))


def _camera_decode_applies(prof: Profile) -> bool:
    """Whether ``camera_decode`` picks anything: a float-path CNN run through the camera's JPEG (the
    reduced path decodes at 1/reduce, a descriptor full frames, lossless frames have no JPEG)."""
    return bool(prof.camera_jpeg) and prof.preprocess_reduce == "off" and prof.tactile_feature == "cnn"


def _frame_hw(dataset: Path) -> tuple[int, int]:
    """The tactile frames' size, from the dataset's geometry (no frame read)."""
    from vs2t_edge.runtime.dataset import load_dataset

    return load_dataset(dataset).geometry.frame_hw


PROFILES = {
    "tiny": Profile("tiny", trunk="tiny", size_px=64, ft_epochs=2, steps=150, cls_steps=100, n_synth_per_class=60),
    "small": Profile("small", size_px=128, steps=400, cls_steps=200, n_synth_per_class=150, ft_attributes=1.0),
    # paper: 50 fabrics x 225 presses; features from 90 evenly spaced presses per fabric so extraction
    # fits the CPU budget, and a touched fabric has 9 validation presses: a validation piece can
    # press past the cell's limit of 5, so validation can choose extra presses; see docs/training.md
    "paper": Profile("paper", size_px=128, splits=5, max_presses=90, ft_epochs=2, ft_max_rows=2000, steps=400,
                     cls_steps=200, n_synth_per_class=150, visual_tail="finetuned", validation_folds=4,
                     ft_attributes=1.0),
}


def n_holdout(n_fabrics: int) -> int:
    """Validation = untouched count: the paper's 5 of 50; 15 % (>= 2) for smaller worlds (3 of 20)."""
    return 5 if n_fabrics >= 50 else max(2, round(0.15 * n_fabrics))


def touched_problem(n_fabrics: int, touched: int | None, dataset: Path | str) -> str | None:
    """What is wrong with training on ``touched`` of each split's touched fabrics (``Profile.touched``)
    in a world of ``n_fabrics``, or None."""
    most = n_fabrics - 2 * n_holdout(n_fabrics)
    if touched is None or 2 <= touched <= most:
        return None
    return f"--touched {touched}: a split of {dataset}'s {n_fabrics} fabrics has {most} touched ones; give 2 to {most}"


def split_touched(n_fabrics: int, prof: Profile) -> int:
    """How many touched fabrics each split of a world of ``n_fabrics`` trains on."""
    return prof.touched or n_fabrics - 2 * n_holdout(n_fabrics)


def folds_problem(n_fabrics: int, prof: Profile, dataset: Path | str) -> str | None:
    """What is wrong with ``prof.validation_folds`` for a split of ``dataset``'s ``n_fabrics``, or None
    (train/folds.py ``folds_fit``)."""
    n, touched = prof.validation_folds, split_touched(n_fabrics, prof)
    if n == 0 or folds_fit(n, touched):
        return None
    return (f"--validation-folds {n}: a split of {dataset}'s {n_fabrics} fabrics trains on {touched} touched ones; "
            f"give 0 (none) or 2 to {touched // 2} (at least 2 held out per fold)")


def profile_folds(n_fabrics: int, prof: Profile) -> int:
    """The profile's own number of validation folds, shrunk to what a split can give (0 when it
    can give none): a profile default is no request to refuse a world or a ``--touched`` for."""
    n, touched = prof.validation_folds, split_touched(n_fabrics, prof)
    return n if n == 0 or folds_fit(n, touched) else (touched // 2 if touched >= 4 else 0)


VISUAL_TAILS = ("frozen", "finetuned")
TACTILE_FEATURES = ("cnn", "shading_markers")

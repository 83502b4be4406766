"""`vs2t-edge train DATASET --profile tiny|small|paper --out RUN [--splits N] [--trunk ARCH]
[--visual-tail frozen|finetuned] [--ft-attributes W] [--tactile-feature cnn|shading_markers] [--camera-jpeg Q [--camera-decode auto|full]]`."""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser, verb: str) -> None:
    parser.add_argument("dataset", type=Path, help="dataset folder (docs/dataset.md)")
    parser.add_argument("--profile", default="small", choices=("tiny", "small", "paper"),
                        help="training budget and input size (docs/training.md); default small")
    parser.add_argument("--out", type=Path, required=True, help="run folder to write")
    parser.add_argument("--splits", type=int, help="number of seeded random splits (profile default)")
    parser.add_argument("--trunk", choices=("efficientnet_lite0", "resnet50", "tiny"), help="feature trunk")
    parser.add_argument("--weights", type=Path, help="trunk weights file (e.g. a torchvision resnet50 state dict)")
    parser.add_argument("--seed", type=int, help="split and training seed (default 0)")
    parser.add_argument("--max-presses", type=int, metavar="N",
                        help="presses per fabric to extract features from, in press order (0: all; profile "
                             "default: all, 90 for paper)")
    parser.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    parser.add_argument("--visual-tail", choices=("frozen", "finetuned"),
                        help="fine-tune the visual trunk's tail on touched fabrics' camera crops per split, or keep "
                             "it frozen (profile default: frozen; docs/training.md)")
    parser.add_argument("--ft-attributes", type=float, metavar="W",
                        help="weight of the tactile tail's second task while it is fine-tuned: regress each touched "
                             "press's fabric attributes beside the softmax over touched fabrics (0: the softmax alone; "
                             "profile default; docs/training.md \"Touch that attributes can predict\")")
    parser.add_argument("--tactile-feature", choices=("cnn", "shading_markers"),
                        help="tactile feature: the trunk (cnn, default) or the no-network shading_markers descriptor "
                             "that wins on a real GelSight (docs/realism.md); exported as a descriptor bundle")
    parser.add_argument("--preprocess-reduce", choices=("off", "auto", "1", "2", "4", "8"),
                        help="tactile pixel path: off (default; the float path of every earlier bundle) or the "
                             "reduced uint8 path - the frame reduced by a factor (auto: the largest leaving the "
                             "input size across the crop; the cell's MJPEG camera then decodes at that scale), "
                             "cropped and resized on uint8 (runtime/preprocess.py, docs/bundle.md)")
    parser.add_argument("--camera-jpeg", type=int, metavar="Q",
                        help="the tactile camera's MJPEG quality (1..100): every press and no-contact frame is read "
                             "through a JPEG at Q, decoded at the bundle's scale, as a UVC camera hands them to the "
                             "cell; export and the bench then read the same way (0: the dataset's lossless frames; "
                             "profile default 0; docs/training.md)")
    parser.add_argument("--camera-decode", choices=("auto", "full"),
                        help="with --camera-jpeg on the float path, the scale its frames are decoded at: auto "
                             "(default; the largest 1/n leaving the input size across the crop, 1/2 of 640x480 at "
                             "128 px - what the cell's camera decodes such a bundle's frames at) or full (full "
                             "decodes, as such runs were made before 2026-11-29; the camera then decodes full frames)")
    parser.add_argument("--touched", type=int, metavar="N",
                        help="train each split on only N of its touched fabrics (a nested draw with the split's "
                             "seed; the others take no part): what touching fewer fabrics costs zero-shot "
                             "(default: all; docs/results/zero_shot_limits_paper.md, \"More touched fabrics\")")
    parser.add_argument("--mis-sort-target", type=float, metavar="PCT",
                        help="the share of pieces in a wrong bin, in percent, that the scene decision's search on "
                             "validation jobs must keep under (default 1); the report prices 0.5, 1 and 2 on the same "
                             "test jobs (docs/decision.md)")
    parser.add_argument("--validation-folds", type=int, metavar="N",
                        help="more validation fabrics for the scene decision: split each split's touched fabrics "
                             "into N folds, hold each out of a generator trained on the others, and choose the "
                             "operating point on those jobs too (0: the validation fabrics alone; paper profile 4, "
                             "others 0; each fold costs one generator training per split; docs/decision.md)")


def run(args: argparse.Namespace) -> int:
    from vs2t_edge.runtime.dataset import load_dataset

    if not (args.dataset / "fabrics.csv").is_file() and not args.dataset.is_dir():
        print(f"vs2t-edge train: dataset folder {args.dataset} does not exist", file=sys.stderr)
        return 2
    try:
        n_fabrics = len(load_dataset(args.dataset).fabrics)
    except Exception as exc:  # the loader names the file and key
        print(f"vs2t-edge train: {args.dataset} is not a readable dataset: {exc}", file=sys.stderr)
        return 2
    from vs2t_edge.train.run import touched_problem

    problem = touched_problem(n_fabrics, args.touched, args.dataset)
    if problem is None and args.validation_folds is not None:  # a profile's own folds shrink to fit instead
        from vs2t_edge.train.run import PROFILES, folds_problem

        problem = folds_problem(n_fabrics, replace(PROFILES[args.profile], touched=args.touched,
                                                   validation_folds=args.validation_folds), args.dataset)
    if problem:
        print(f"vs2t-edge train: {problem}", file=sys.stderr)
        return 2
    if args.splits is not None and args.splits < 1:
        print("vs2t-edge train: --splits must be at least 1", file=sys.stderr)
        return 2
    if args.max_presses is not None and not (args.max_presses == 0 or args.max_presses >= 5):
        print("vs2t-edge train: --max-presses must be 0 (all) or at least 5 (train, validation and test presses)",
              file=sys.stderr)
        return 2
    if args.camera_jpeg is not None and not 0 <= args.camera_jpeg <= 100:
        print(f"vs2t-edge train: --camera-jpeg {args.camera_jpeg}: give the camera's JPEG quality from 1 to 100 "
              "(0: lossless frames)", file=sys.stderr)
        return 2
    if args.mis_sort_target is not None and not 0 < args.mis_sort_target < 100:
        print(f"vs2t-edge train: --mis-sort-target {args.mis_sort_target}: a percentage above 0 and below 100",
              file=sys.stderr)
        return 2
    if args.ft_attributes is not None and not 0 <= args.ft_attributes < float("inf"):
        print(f"vs2t-edge train: --ft-attributes {args.ft_attributes}: a finite weight of 0 or more", file=sys.stderr)
        return 2
    if args.weights is not None and not args.weights.is_file():
        print(f"vs2t-edge train: weights file {args.weights} does not exist", file=sys.stderr)
        return 2
    from vs2t_edge.train.report import legend_lines
    from vs2t_edge.train.run import train

    t0 = time.time()
    m = train(args.dataset, args.out, args.profile, splits=args.splits, trunk_arch=args.trunk, weights=args.weights,
              seed=args.seed, figures=not args.no_figures, visual_tail=args.visual_tail,
              max_presses=args.max_presses, tactile_feature=args.tactile_feature,
              preprocess_reduce=args.preprocess_reduce, camera_jpeg=args.camera_jpeg, touched=args.touched,
              mis_sort_target=None if args.mis_sort_target is None else args.mis_sort_target / 100,
              validation_folds=args.validation_folds, camera_decode=args.camera_decode,
              ft_attributes=args.ft_attributes)
    s = m["summary"]["VS2T-ZSL"]
    print(f"VS2T-ZSL: ZSL {s['zsl']['mean']:.1f} %, GZSL acc_t {s['acc_t']['mean']:.1f} acc_u {s['acc_u']['mean']:.1f} "
          f"H {s['H']['mean']:.1f} ({time.time() - t0:.0f} s); report {args.out / 'report.md'}")
    print("How to read these numbers:")
    print("\n".join(legend_lines()))
    return 0

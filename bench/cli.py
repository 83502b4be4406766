"""`vs2t-edge bench BUNDLE... [--out DIR]`: the speed-for-accuracy table (runtime/bench.py).

Prints the table; with --out writes bench.md, bench.json and (with matplotlib) pareto.png.
Make the variants with `vs2t-edge export`; for the committed run, docs/results/bench/bench.md's
'How these bundles were made' rebuilds the export commands from bench.json and says what was not
recorded (that section is written by hand: --out rewrites bench.md without it).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from vs2t_edge.bench.press_timing import CAMERA_FORMATS, DECODE_SCALES


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("bundles", nargs="+", help="bundle folders, one per variant")
    parser.add_argument("--out", default=None, help="folder for bench.md, bench.json, pareto.png")
    parser.add_argument("--dataset", default=None, help="dataset folder (default: each bundle's own)")
    parser.add_argument("--threads", default="1,2", help="thread counts to time (default 1,2)")
    parser.add_argument("--budget-s", type=float, default=4.0, help="seconds of timed runs per thread count")
    parser.add_argument("--items", type=int, default=100, help="simulated items per class (default 100)")
    parser.add_argument("--max-eval-presses", type=int, default=0,
                        help="at most this many held-out presses per fabric, evenly spread (default 0: every press "
                             "the bundle never trained on; 60, the default until 2026-11-27, left 300 untouched "
                             "presses on the paper world, where a 1-point difference is 3 presses, inside the noise)")
    parser.add_argument("--no-accuracy", action="store_true", help="speed only")
    parser.add_argument("--jpeg-quality", type=int, default=95,
                        help="JPEG quality of the camera's MJPEG frames the press is timed on (default 95)")
    parser.add_argument("--camera-format", default="mjpeg", choices=CAMERA_FORMATS,
                        help="what the camera streams, for the press timing: mjpeg (at --jpeg-quality; the default) or "
                             "yuyv (uncompressed 4:2:2, devices.camera.pixel_format yuyv)")
    parser.add_argument("--camera-decode", default="auto", choices=DECODE_SCALES,
                        help="the scale the cell's camera decodes frames at (devices.camera.decode_scale): auto (the "
                             "default: the reduced path's own; a float-path bundle's 640x480 MJPEG frames at 1/2) or full")
    frames = parser.add_mutually_exclusive_group()
    frames.add_argument("--accuracy-through-jpeg", action="store_true",
                        help="score accuracy on frames passed through that JPEG, decoded at each bundle's scale as "
                             "the camera hands them (default: a bundle trained through the camera's JPEG, manifest "
                             "camera_jpeg, reads frames through its own; any other the dataset's lossless frames)")
    frames.add_argument("--accuracy-through-yuyv", action="store_true",
                        help="score accuracy on frames passed through an uncompressed YUYV camera (4:2:2 chroma, "
                             "video range), made BGR at each bundle's scale as the camera hands them")
    frames.add_argument("--accuracy-lossless", action="store_true",
                        help="score every bundle on the dataset's lossless frames, even one trained through the "
                             "camera's JPEG")
    parser.add_argument("--pair", action="append", default=[], metavar="A:B",
                        help="pair two scored variants (bundle folder names): B minus A on the same presses and items, "
                             "with 95 %% bootstrap intervals and flips, as int8 is paired with fp32 (repeatable)")
    parser.add_argument("--arm-times", default=None, metavar="JSON",
                        help="the arm's times per press, for pieces per minute: the JSON of "
                             "`python -m vs2t_edge.sim.ursim --bench 9 --json FILE` (or the same on a robot)")


def run(args) -> int:
    from vs2t_edge.bench.measure import run_bench
    from vs2t_edge.bench.report import arm_times_line, render_bins, render_pairs, render_table
    from vs2t_edge.runtime.bundle import BundleError, is_descriptor, read_manifest
    from vs2t_edge.runtime.preprocess import FrameError
    from vs2t_edge.runtime.sorting import ArmTimes

    bundles = [Path(b) for b in args.bundles]
    try:
        threads = tuple(int(t) for t in args.threads.split(","))
        if not threads or min(threads) < 1:
            raise ValueError
    except ValueError:
        print(f"bench: --threads {args.threads!r}: give thread counts like 1,2", file=sys.stderr)
        return 2
    if not 1 <= args.jpeg_quality <= 100:
        print(f"bench: --jpeg-quality {args.jpeg_quality}: give a JPEG quality from 1 to 100", file=sys.stderr)
        return 2
    pairs = []
    names = [b.name for b in bundles]
    for p in args.pair:
        a, sep, b = p.partition(":")
        if not sep or a not in names or b not in names or a == b:
            print(f"bench: --pair {p!r}: give A:B, two different bundle folder names of this bench ({', '.join(names)})",
                  file=sys.stderr)
            return 2
        pairs.append((a, b))
    arm = None
    if args.arm_times:
        try:
            arm = ArmTimes.from_bench(json.loads(Path(args.arm_times).read_text(encoding="utf-8")), args.arm_times)
        except (OSError, ValueError) as exc:  # json.JSONDecodeError is a ValueError
            print(f"bench: --arm-times {args.arm_times}: {exc}", file=sys.stderr)
            return 2
    for b in bundles:
        try:
            manifest = read_manifest(b)
        except BundleError as exc:
            print(f"bench: {exc}", file=sys.stderr)
            return 2
        if is_descriptor(manifest):
            print(f"bench: {b}: a descriptor bundle (trunk.kind descriptor, docs/bundle.md) - the bench measures "
                  "bundles with an ONNX trunk only; its per-press cost is in docs/realism.md", file=sys.stderr)
            return 2
    try:
        result = run_bench(bundles, Path(args.out) if args.out else None, dataset=args.dataset, threads=threads,
                           budget_s=args.budget_s, n_items=args.items, cap=args.max_eval_presses,
                           accuracy_on=not args.no_accuracy, arm=arm, jpeg_quality=args.jpeg_quality,
                           accuracy_through_jpeg=args.accuracy_through_jpeg, accuracy_lossless=args.accuracy_lossless,
                           pairs=pairs, camera_format=args.camera_format,
                           accuracy_through_yuyv=args.accuracy_through_yuyv, camera_decode=args.camera_decode)
    except (BundleError, FrameError, FileNotFoundError, RuntimeError) as exc:
        print(f"bench: {exc}", file=sys.stderr)
        return 1
    print(render_table(result))
    for r in result.get("recommendation", []):
        print(f"recommended on this machine: {r['recommended']} ({r['why']})")
    pairs_text = render_pairs(result)
    if pairs_text:
        print("\npaired (--pair), B minus A on the same presses and items:\n" + pairs_text)
    bins = render_bins(result)
    if bins:
        print("\nper item, by bins (right / mis-sort / reject, %):\n" + bins + "\n" + arm_times_line(result))
    if args.out:
        print(f"bench: wrote {args.out}/bench.md, bench.json" + (", pareto.png" if (Path(args.out) / "pareto.png").exists() else ""))
    return 0

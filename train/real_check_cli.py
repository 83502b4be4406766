"""`vs2t-edge real-check --train DIR [--test DIR] [--out JSON] [--pipelines ...]`: the tactile
features on a real sensor's recordings (train/real_check.py), as a table and a JSON file."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser, verb: str) -> None:
    parser.add_argument("--train", type=Path, required=True,
                        help="folder of material_*/ folders of press images in press order (file names sort in time)")
    parser.add_argument("--test", type=Path,
                        help="the same layout, later presses of the same materials; without it the temporal split "
                             "of --train (fold A: the first half fits, the second tests; fold B: the first three quarters fit, "
                             "the last quarter tests)")
    parser.add_argument("--out", type=Path, default=Path("real-check.json"), help="JSON result (default real-check.json)")
    parser.add_argument("--pipelines", default="frozen,inpainted,markers,shading,shading_markers",
                        help="comma-separated: frozen (floor), finetuned (the frozen trunk's tail tuned per fold on "
                             "the fit presses with shifts and exposure jitter; minutes, not in the default), inpainted (GelSight-aware trunk input), markers "
                             "(no network), shading (the gel's coarse colour field, no network), shading_markers "
                             "(shading and the marker dots' sub-pixel centres)")
    parser.add_argument("--seeds", type=int, default=10, help="material draws per fold for novelty AUROC")
    parser.add_argument("--within-fit", action="store_true",
                        help="evaluate inside each fold's fit presses only (split the same way: earlier ones fit, later "
                             "ones test): the numbers to choose a pipeline by; test presses never read")


def run(args: argparse.Namespace) -> int:
    from vs2t_edge.train import real_check as rc

    pipelines = tuple(p.strip() for p in args.pipelines.split(",") if p.strip())
    unknown = [p for p in pipelines if p not in rc.PIPELINES]
    if unknown or not pipelines:
        print(f"vs2t-edge real-check: unknown pipeline(s) {unknown or '(none)'}; choose from {', '.join(rc.PIPELINES)}",
              file=sys.stderr)
        return 2
    if args.seeds < 1:
        print("vs2t-edge real-check: --seeds must be at least 1", file=sys.stderr)
        return 2
    try:
        result = rc.run_real_check(args.train, args.test, pipelines, n_seeds=args.seeds, within_fit=args.within_fit,
                                   log=lambda m: print(m, file=sys.stderr, flush=True))
    except rc.RealCheckError as exc:
        print(f"vs2t-edge real-check: {exc}", file=sys.stderr)
        return 2
    print(rc.render_table(result))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"real-check: wrote {args.out}", file=sys.stderr)
    return 0

"""`vs2t-edge synth OUT`: write the synthetic fabric world as a dataset folder."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from vs2t_edge.runtime.dataset import DatasetError, validate_dataset
from vs2t_edge.sim.synth import PROFILES, generate


def add_arguments(parser: argparse.ArgumentParser, verb: str) -> None:
    parser.add_argument("out", type=Path, help="dataset folder to write (must not exist or be empty)")
    # the default is the FabricVST-sized world the issue describes (640x480 frames, 1000 px camera);
    # the demo and the tests name their smaller profiles
    parser.add_argument("--profile", choices=sorted(PROFILES), default="paper",
                        help="paper (default: 50 fabrics x 225 presses, 640x480 frames, 1000 px camera; "
                             "~12-35 min on 2 cores, 5 GB), demo (the main job's world: 24 x 49, 320x240, "
                             "~2-4 min), small (20 x 25, 320x240, 25 s), tiny (tests, seconds)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fabrics", type=int, default=None, help="override the profile's number of fabrics")
    parser.add_argument("--workers", type=int, default=None, help="processes (default: 2)")
    parser.add_argument("--no-markers", dest="markers", action="store_false",
                        help="render the GelSight frames without marker dots (an unmarked gel); "
                             "the world is otherwise the same as with markers")


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    if out.exists() and any(out.iterdir()):
        print(f"synth: {out} exists and is not empty; choose a new folder", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    generate(out, args.profile, seed=args.seed, n_fabrics=args.fabrics, workers=args.workers, markers=args.markers)
    try:
        ds = validate_dataset(out, deep=False)
    except DatasetError as exc:  # would be a bug in the world: say so loudly
        print(f"synth: the generated dataset does not validate:\n{exc}", file=sys.stderr)
        return 1
    n = sum(len(f.presses) for f in ds.fabrics)
    print(f"{out}: {len(ds.fabrics)} fabrics, {n} presses ({args.profile}, seed {args.seed}"
          f"{'' if args.markers else ', no markers'}) "
          f"in {time.monotonic() - t0:.1f} s")
    return 0

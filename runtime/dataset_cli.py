"""`vs2t-edge validate-data DATASET`: say exactly what is wrong with a dataset folder."""

from __future__ import annotations

import argparse
import sys

from vs2t_edge.runtime.dataset import DatasetError, validate_dataset


def add_arguments(parser: argparse.ArgumentParser, verb: str) -> None:
    parser.add_argument("dataset", help="dataset folder (docs/dataset.md)")
    parser.add_argument("--shallow", action="store_true",
                        help="check metadata and file presence only, do not decode every image")


def run(args: argparse.Namespace) -> int:
    try:
        ds = validate_dataset(args.dataset, deep=not args.shallow)
    except DatasetError as exc:
        print(exc, file=sys.stderr)
        return 2
    n_presses = sum(len(f.presses) for f in ds.fabrics)
    g = ds.geometry
    print(f"{ds.root}: ok — {len(ds.fabrics)} fabrics, {n_presses} presses, "
          f"frames {g.frame_width_px}x{g.frame_height_px}, camera {g.camera_image_px} px")
    return 0

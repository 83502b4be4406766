"""`vs2t-edge label CONFIG ITEM_ID FABRIC [--off-scene]`: the operator says what a piece in the reject bin was.

The label is appended, durably, to the file the cell config names (``evidence.operator_labels``);
the running service reads it before its next piece and re-estimates that untouched fabric's mean
from the piece's presses (runtime/feedback.py), journaling whether it applied it and why not.
Checked here first: the config turns the mode on, and FABRIC is a fabric of its scene (or, with
``--off-scene``, is not: a stranger the cell then learns to refuse). Whether
ITEM_ID is a decided item of this journal only the service knows; it journals a label it cannot use.
"""

from __future__ import annotations

import sys

from vs2t_edge.runtime.config import ConfigError, load_config
from vs2t_edge.runtime.feedback import append_label


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("config", help="the cell config the service runs (evidence.operator_labels names the file)")
    parser.add_argument("item_id", help="the piece's item id, as the journal and the status screen show it")
    parser.add_argument("fabric", help="what the piece was: a fabric of the config's scene, or with --off-scene "
                                       "any name for a fabric the job does not list")
    parser.add_argument("--off-scene", action="store_true",
                        help="the piece is none of the job's fabrics: the cell learns it as a stranger, and pieces "
                             "like it go to the reject bin")


def run(args) -> int:
    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    if cfg.operator_labels is None:
        print(f"label: {cfg.path} does not turn operator labels on; set evidence.operator_labels to a file "
              "(docs/cell.md, \"Learning from the reject bin\")", file=sys.stderr)
        return 2
    in_scene = args.fabric in cfg.scene_classes
    if in_scene == args.off_scene:
        print(f"label: {args.fabric!r} is {'a' if in_scene else 'not a'} fabric of the scene in {cfg.path} "
              f"({', '.join(cfg.scene_classes)})"
              + ("; drop --off-scene" if in_scene else "; a piece the job does not list takes --off-scene"),
              file=sys.stderr)
        return 2
    try:
        append_label(cfg.operator_labels, args.item_id, args.fabric, off_scene=args.off_scene)
    except OSError as exc:
        print(f"label: cannot write {cfg.operator_labels}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    kind = next((f.kind for f in cfg.fabrics if f.name == args.fabric), "off-scene")
    note = {"untouched": "", "off-scene": " (off-scene: pieces like it will go to the reject bin)",
            "touched": f" ({args.fabric} is touched: recorded, its mean stays the training one)"}[kind]
    print(f"{args.item_id} labelled {args.fabric} in {cfg.operator_labels}{note}")
    return 0

"""`vs2t-edge validate-config FILE`: check a cell config; every problem with file, line and key.

Exit 0 when valid (prints a one-line summary), 2 with every problem on stderr. The systemd unit
runs it as ExecStartPre, so a bad config stops the service before any device is touched.
"""

from __future__ import annotations

import sys
from typing import Any


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("config", help="cell config file (YAML)")
    parser.add_argument("--check-bundle", action="store_true",
                        help="also require the bundle folder to exist")


def run(args) -> int:
    from vs2t_edge.runtime.config import load_config_or_say

    if (cfg := load_config_or_say(args.config)) is None:
        return 2
    if args.check_bundle and not cfg.bundle.is_dir():
        print(f"config {cfg.path}: bundle folder {cfg.bundle} does not exist", file=sys.stderr)
        return 2
    if args.check_bundle and cfg.without_scene_model != "allow":
        # what `run` refuses at start (runtime/wiring.py evidence_factory_for), said before it starts
        from vs2t_edge.runtime.bundle import BundleError, read_manifest

        try:
            has_scene_model = "decision" in read_manifest(cfg.bundle)
        except BundleError as exc:
            print(f"config {cfg.path}: {exc}", file=sys.stderr)
            return 2
        if not has_scene_model:
            print(f"config {cfg.path}: bundle {cfg.bundle} has no scene model (decision.npz), so the cell could not "
                  "refuse a piece of a fabric outside the scene; re-export it with `vs2t-edge export RUN --out "
                  "BUNDLE`, or set `evidence.without_scene_model: allow` knowing that risk (docs/cell.md)",
                  file=sys.stderr)
            return 2
    if args.check_bundle:
        read = read_scene_model(cfg)  # once, for the checks below
        if read[1]:  # the bundle's load refuses it too (runtime/bundle.py): said here, not as "no scene model"
            print(f"config {cfg.path}: {read[1]}", file=sys.stderr)
            return 2
        if problem := scene_problem(cfg, read[0]):  # what `run` refuses at start (runtime/wiring.py), said before it
            print(problem if problem.startswith(str(cfg.path)) else f"config {cfg.path}: {problem}", file=sys.stderr)
            return 2
        if cfg.operator_labels is not None:
            problem = operator_labels_problem(cfg, read)  # what `run` refuses at start (runtime/wiring.py), said before it
            if problem:
                print(f"config {cfg.path}: {problem}", file=sys.stderr)
                return 2
        # said at the start too (runtime/daemon.py); a warning, not a refusal
        from vs2t_edge.runtime.operating_point import confidence_override_note

        note = confidence_override_note(cfg, read[0])
        if note:
            print(f"warning: {note}", file=sys.stderr)
    from vs2t_edge.runtime.operating_point import config_sets_confidence

    fabrics = ", ".join(f"{f.name}({f.kind[0]})->{f.bin}" for f in cfg.fabrics)
    confidence = (f"confidence {cfg.confidence}" if config_sets_confidence(cfg)
                  else f"confidence the scene model's (or {cfg.confidence} for a bundle without one)")
    print(f"{cfg.path}: ok - camera {cfg.camera['kind']}, arm {cfg.arm_kind}, gate {cfg.gate['kind']}, "
          f"{len(cfg.fabrics)} fabrics [{fabrics}], reject bin {cfg.reject_bin}, "
          f"{confidence}, max {cfg.max_presses} presses"
          + (" (extra presses for a piece a touched fabric leads: the scene model's)" if cfg.extra_presses is None
             else f" (+{cfg.extra_presses} for a piece a touched fabric leads, with a scene model)"
             if cfg.extra_presses else " (no extra presses)"))
    return 0


def scene_problem(cfg, scene_model) -> str:
    """Why the start would refuse the job's fabrics with the bundle (runtime/operating_point.py
    ``scene_bundle_problem``), from its manifest and scene model alone; '' when it would not."""
    from vs2t_edge.runtime.bundle import BundleError, manifest_classes, read_manifest
    from vs2t_edge.runtime.operating_point import scene_bundle_problem

    try:
        manifest = read_manifest(cfg.bundle)
        touched, untouched = manifest_classes(cfg.bundle, manifest)
    except BundleError as exc:
        return str(exc)
    return scene_bundle_problem(cfg, touched, untouched, manifest, scene_model)


def read_scene_model(cfg) -> tuple[Any, str]:
    """(the bundle's scene model, read from its decision file alone - no ONNX session - or None;
    why it could not be read, '' when it was or the manifest lists none)."""
    import numpy as np

    from vs2t_edge.runtime.bundle import BundleError, read_manifest
    from vs2t_edge.runtime.scene_model import SceneModel, SceneModelError

    try:
        manifest = read_manifest(cfg.bundle)
    except BundleError as exc:
        return None, str(exc)
    decision = manifest.get("decision") if isinstance(manifest, dict) else None
    file = decision.get("file") if isinstance(decision, dict) else None
    if not isinstance(file, str):
        return None, ""
    try:
        with np.load(cfg.bundle / file, allow_pickle=False) as z:
            return SceneModel.from_params({k: z[k] for k in z.files}), ""
    except (OSError, ValueError, KeyError, SceneModelError) as exc:
        return None, f"bundle {cfg.bundle}: {file} unreadable ({exc})"


def operator_labels_problem(cfg, read: tuple[Any, str] | None = None) -> str:
    """Why the bundle cannot learn from operator labels (runtime/feedback.py needs the scene model's
    offset item rule), or '' when it can; ``read``: ``read_scene_model(cfg)`` when done already."""
    model, problem = read_scene_model(cfg) if read is None else read
    if problem:
        return problem
    if model is None:
        return (f"evidence.operator_labels is set and bundle {cfg.bundle} has no scene model (decision.npz) to "
                "learn with; re-export it from its run, or remove the key")
    if model.for_labels() is None:
        return (f"evidence.operator_labels is set and bundle {cfg.bundle}'s scene model uses the {model.item_rule} "
                "item rule without an offset setting for labels (exported before bundles carried one): re-export it "
                "from its run, or remove the key")
    return ""

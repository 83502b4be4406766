"""`vs2t-edge validate-config FILE`: check a cell config; every problem with file, line and key.

Exit 0 when valid (prints a one-line summary), 2 with every problem on stderr. The systemd unit
runs it as ExecStartPre, so a bad config stops the service before any device is touched.
"""

from __future__ import annotations

import sys


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
    if args.check_bundle and cfg.operator_labels is not None:
        problem = operator_labels_problem(cfg)  # what `run` refuses at start (runtime/wiring.py), said before it
        if problem:
            print(f"config {cfg.path}: {problem}", file=sys.stderr)
            return 2
    if args.check_bundle:  # said at the start too (runtime/daemon.py); a warning, not a refusal
        from vs2t_edge.runtime.operating_point import confidence_override_note

        note = confidence_override_note(cfg, bundle_scene_model(cfg))
        if note:
            print(f"warning: {note}", file=sys.stderr)
    from vs2t_edge.runtime.operating_point import config_sets_confidence

    fabrics = ", ".join(f"{f.name}({f.kind[0]})->{f.bin}" for f in cfg.fabrics)
    confidence = (f"confidence {cfg.confidence}" if config_sets_confidence(cfg)
                  else f"confidence the scene model's (or {cfg.confidence} for a bundle without one)")
    print(f"{cfg.path}: ok - camera {cfg.camera['kind']}, arm {cfg.arm_kind}, gate {cfg.gate['kind']}, "
          f"{len(cfg.fabrics)} fabrics [{fabrics}], reject bin {cfg.reject_bin}, "
          f"{confidence}, max {cfg.max_presses} presses")
    return 0


def bundle_scene_model(cfg):
    """The bundle's scene model read from its decision file alone (no ONNX session), or None when
    it has none or it cannot be read (the start says why, with the whole bundle's checks)."""
    import numpy as np

    from vs2t_edge.runtime.bundle import BundleError, read_manifest
    from vs2t_edge.runtime.scene_model import SceneModel, SceneModelError

    try:
        manifest = read_manifest(cfg.bundle)
        decision = manifest.get("decision") if isinstance(manifest, dict) else None
        if not isinstance(decision, dict) or not isinstance(decision.get("file"), str):
            return None
        with np.load(cfg.bundle / decision["file"], allow_pickle=False) as z:
            return SceneModel.from_params({k: z[k] for k in z.files})
    except (BundleError, OSError, ValueError, KeyError, SceneModelError):
        return None


def operator_labels_problem(cfg) -> str:
    """Why the bundle cannot learn from operator labels (runtime/feedback.py needs the scene model's
    offset item rule), or '' when it can."""
    import numpy as np

    from vs2t_edge.runtime.bundle import BundleError, read_manifest

    try:
        manifest = read_manifest(cfg.bundle)
    except BundleError as exc:
        return str(exc)
    file = (manifest.get("decision") or {}).get("file") if isinstance(manifest.get("decision"), dict) else None
    if not isinstance(file, str):
        return (f"evidence.operator_labels is set and bundle {cfg.bundle} has no scene model (decision.npz) to "
                "learn with; re-export it from its run, or remove the key")
    try:
        with np.load(cfg.bundle / file, allow_pickle=False) as z:
            rule = str(z["item_rule"]) if "item_rule" in z.files else "sum"
            has_labels_rule = "labels_press_var" in z.files
    except (OSError, ValueError, KeyError) as exc:
        return f"bundle {cfg.bundle}: {file} unreadable ({exc})"
    if rule != "offset" and not has_labels_rule:
        return (f"evidence.operator_labels is set and bundle {cfg.bundle}'s scene model uses the {rule} item rule "
                "without an offset setting for labels (exported before bundles carried one): re-export it from its "
                "run, or remove the key")
    return ""

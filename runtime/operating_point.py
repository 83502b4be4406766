"""The cell's operating point, owned in one place: which numbers decide, where each comes from,
and which source wins.

Two parts:

* **beta**, the GZSL router's threshold. Sources, first wins: the config's ``beta_override``
  number; the override file the config's ``beta_override_file`` names; the default override file
  ``<bundle>.beta_override.json`` beside the bundle (``vs2t-edge calibrate-threshold`` writes it,
  atomically); the bundle manifest's own beta. A replay pins the beta its session ran with by
  writing it as the config's number (runtime/replay.py), so a later calibration does not change a
  recorded session. An override file names the bundle it was calibrated for (its manifest's seal,
  ``manifest_sha256``); the daemon refuses one written for another bundle - beta is in the units
  of the router it was calibrated on, and a file left beside the bundle folder outlives a new
  bundle deployed to that folder.
* **the item rule** of a bundle that carries a scene model (``decision.npz``,
  runtime/scene_model.py): press weight, off-scene threshold and margin, and the confidence that
  sorts, per kind, all chosen in training for the mis-sort target. The config's
  ``evidence.confidence``, when written, overrides the touched confidence, and
  ``evidence.untouched_confidence`` the untouched one (the knob that trades untouched pieces in
  their bin for fewer mis-sorts; training's report prices both); ``evidence.max_presses`` is the
  config's. A bundle without a scene model uses the config's confidence alone.

``runtime/wiring.py`` (the model's beta and the item evidence of run, record, replay and the
demo), ``runtime/calibrate.py`` (the override file) and ``runtime/sorting.py`` (the simulated
jobs of training's report and the bench) read and write through these functions only.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

from vs2t_edge.runtime.bundle import SEAL_KEY
from vs2t_edge.runtime.files import MAX_JSON_BYTES, atomic_write, read_regular_file
from vs2t_edge.runtime.jpeg_quality import camera_format_problem
from vs2t_edge.runtime.names import OFF_SCENE_PREFIX


class OverrideFileError(ValueError):
    """A beta override file that cannot be used; names the file."""


def override_path_for(bundle: Path | str) -> Path:
    """The default override file: ``<bundle>.beta_override.json`` beside the bundle folder."""
    bundle = Path(bundle)
    return bundle.parent / f"{bundle.name}.beta_override.json"


def override_file_for(cfg) -> tuple[Path | None, str]:
    """(the override file the daemon of ``cfg`` reads, problem). A config with a ``beta_override``
    number reads no file: a beta written to one would be ignored, and the problem says so."""
    if cfg.beta_override is not None:
        return None, (f"{cfg.path}: beta_override = {cfg.beta_override:g} is set, and the daemon uses it before any "
                      "override file - a new beta written now would be ignored. Remove beta_override from the config "
                      "and run again (--dry-run prints the beta without writing)")
    return (Path(cfg.beta_override_file) if cfg.beta_override_file else override_path_for(cfg.bundle)), ""


def resolve_beta(cfg, bundle_manifest: dict | None = None) -> tuple[float | None, str]:
    """(beta, its source) for the daemon of ``cfg``; (None, "bundle manifest") when the bundle's own
    beta stands. With ``bundle_manifest`` (the manifest of ``cfg``'s bundle) an override file
    calibrated for another bundle is refused (``read_beta_override``)."""
    if cfg.beta_override is not None:
        return float(cfg.beta_override), f"{cfg.path}: beta_override"
    path, _ = override_file_for(cfg)
    beta = read_beta_override(path, bundle_manifest)
    return (beta, str(path)) if beta is not None else (None, "bundle manifest")


def read_beta_override(path: Path | None, bundle_manifest: dict | None = None) -> float | None:
    """The override file's beta, None when there is no file. With ``bundle_manifest``, a file
    calibrated for another bundle is an ``OverrideFileError``: the file names its bundle's seal
    (``bundle_seal``); a file written before it did is judged by the bundle's own beta it kept
    (``bundle_beta``), which a re-export almost always changes."""
    if path is None or not Path(path).exists():
        return None
    try:
        data = json.loads(read_regular_file(path, MAX_JSON_BYTES, "beta override file"))
    except OSError as exc:
        raise OverrideFileError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise OverrideFileError(f"{path}: not a beta override file ({exc})") from None
    if not isinstance(data, dict) or "beta" not in data:
        raise OverrideFileError(f"{path}: not a beta override file (no key 'beta')")
    try:
        beta = float(data["beta"])
    except (ValueError, TypeError):
        raise OverrideFileError(f"{path}: 'beta' {data['beta']!r} is not a number") from None
    if not math.isfinite(beta):
        raise OverrideFileError(f"{path}: beta {beta} is not finite")
    if bundle_manifest is not None and "decision" not in bundle_manifest \
            and "bundle_seal" not in data and not _is_number(data.get("bundle_beta")):
        # where beta routes the presses (no scene model) a file that names no bundle may be another
        # bundle's, in its router's units; with a scene model beta sorts nothing and the file is taken
        raise OverrideFileError(f"{path}: names no bundle (no key 'bundle_seal', no 'bundle_beta'), so its beta may "
                                "be another bundle's, in that bundle's router's units. Run calibrate-threshold for "
                                "this bundle, or remove the file to use the bundle's own beta")
    other = _for_another_bundle(data, bundle_manifest) if bundle_manifest is not None else ""
    if other:
        raise OverrideFileError(f"{path}: calibrated for another bundle ({other}); its beta is in that bundle's "
                                "router's units. Run calibrate-threshold for this bundle, or remove the file to "
                                "use the bundle's own beta")
    return beta


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _for_another_bundle(data: dict, manifest: dict) -> str:
    """Why an override file's ``data`` was not written for the bundle of ``manifest`` ("" = it was)."""
    seal, written = manifest.get(SEAL_KEY), data.get("bundle_seal")
    if written is not None:
        return "" if written == seal else f"written for {SEAL_KEY} {str(written)[:12]}..., this bundle's is " \
                                          f"{str(seal)[:12]}..."
    was, own = data.get("bundle_beta"), manifest.get("beta")
    if _is_number(was) and _is_number(own) and float(was) != float(own):
        return f"written when the bundle's own beta was {float(was):.6g}, this bundle's is {float(own):.6g}"
    return ""


def write_beta_override(path: Path, cal: Any, *, bundle_beta: float | None, source: str,
                        bundle_seal: str | None = None) -> Path:
    """Atomic: at every instant ``path`` holds either the old override or the new one, whole.

    ``cal`` is a calibration (``runtime.calibrate.Calibration``: beta and how it was chosen);
    ``bundle_seal`` the calibrated bundle's ``manifest_sha256`` (the daemon refuses the file for any
    other bundle, ``read_beta_override``). The old
    file is copied to ``.prev`` (itself via a temp file and rename), the new one written to a temp
    file, fsynced and renamed over ``path``, and the folder fsynced. A crash anywhere leaves the
    old override in force (and perhaps a stray ``.tmp``); never no override at all, which would
    silently put the bundle's own beta back in charge.
    """
    path = Path(path)
    history = []
    old_text = path.read_text() if path.exists() else None
    if old_text is not None:
        try:
            old = json.loads(old_text)
            history = old.get("history", []) + [{k: old.get(k) for k in ("beta", "written", "objective")}]
        except (ValueError, AttributeError):
            history = []  # a damaged old file is still kept as .prev below, byte for byte
    fields = asdict(cal) if is_dataclass(cal) else dict(cal)
    data = {"beta": fields["beta"], "bundle_beta": bundle_beta,
            **({"bundle_seal": bundle_seal} if bundle_seal is not None else {}),
            "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "source": source, **{k: v for k, v in fields.items() if k != "beta"}, "history": history}
    if old_text is not None:
        atomic_write(path.with_name(path.name + ".prev"), old_text)
    atomic_write(path, json.dumps(data, indent=2) + "\n")
    return path


def scene_model_rule(scene_model) -> tuple[float, dict]:
    """(touched confidence, the other keyword arguments of ``runtime.evidence.Evidence``) of a
    scene model's operating point, as training chose it for the mis-sort target: press weight,
    off-scene threshold and margin, the confidence per kind (every untouched class at the
    untouched one), the outlier-press rule when it has one, the extra presses it chose and the
    classes that earn them (``touched_classes``; runtime/evidence.py), and for the offset
    item rule the model itself (its item scores replace the weighted sum). Its temperature
    and untouched bias act inside the model's posterior (runtime/scene_model.py) and have no
    override."""
    m = scene_model
    return m.confidence, {"weight": m.evidence_weight, "open_threshold": m.open_threshold,
                          "known_margin": m.known_margin,
                          "class_confidence": {c: m.untouched_confidence for c in m.untouched},
                          "item_model": m if m.item_rule == "offset" else None, "refuse_early": m.refuse_early,
                          "outlier_model": m if math.isfinite(m.outlier_ratio) else None,
                          "extra_presses": int(getattr(m, "extra_presses", 0)), "extend_classes": touched_classes(m)}


def touched_classes(scene_model) -> tuple[str, ...]:
    """The scene model's touched classes a job can list: not untouched (a synthesis, or a mean
    operator labels taught), not known only to refuse (``known_only``), not a stranger labels taught
    (runtime/feedback.py). The classes whose pieces earn extra presses (runtime/evidence.py): their
    evidence keeps growing with presses where a synthesis's stops. A taught untouched class's mean
    is real presses too, but it earns none: on the paper world's label jobs that put pieces of an
    untaught twin into its bin (docs/results/operator_labels_paper.md)."""
    m = scene_model
    return tuple(c for c in m.classes
                 if c not in m.untouched and c not in m.known_only and not c.startswith(OFF_SCENE_PREFIX))


def config_sets_confidence(cfg) -> bool:
    """Whether the config's file writes ``evidence.confidence`` (a default does not count: it
    must not override the scene model's fitted confidence; nor does ``confidence: null``, which
    loads as the default)."""
    return ((cfg.raw or {}).get("evidence") or {}).get("confidence") is not None


def extra_presses_of(cfg, scene_model) -> int:
    """The extra presses the cell's evidence takes: the config's ``evidence.extra_presses`` when
    its file writes it (null or absent: not written), else the scene model's own (training's
    choice on validation; 0 for a bundle without one)."""
    ours = getattr(cfg, "extra_presses", None)
    if ours is not None:
        return int(ours)
    return int(getattr(scene_model, "extra_presses", 0) or 0)


def evidence_settings(cfg, model: Any = None) -> tuple[float, dict]:
    """(confidence, keyword arguments of ``runtime.evidence.Evidence``) for ``cfg``'s scene with
    ``model``: the scene model's operating point when the bundle has one, the config's
    ``evidence.confidence`` overriding its touched confidence when written there; for a bundle
    without a scene model, the config's confidence alone."""
    scene_model = getattr(model, "scene_model", None)
    if scene_model is None:
        return cfg.confidence, {}
    return scene_model_settings(cfg, scene_model)


def confidence_override_note(cfg, scene_model) -> str:
    """What the config's written ``evidence.confidence``, ``evidence.untouched_confidence`` and
    ``evidence.extra_presses`` do to a scene model's operating point, in words for the start log
    and ``validate-config --check-bundle``; '' when the config writes none of them (the model's own
    operating point decides) or they equal the model's. Without a scene model only
    ``evidence.confidence`` acts, and a written ``evidence.untouched_confidence`` or
    ``evidence.extra_presses`` is said to do nothing. Also said: the fabrics a written
    ``evidence.twin_ratio`` holds back (or that it holds none), and a scene model's own extra presses
    that a short ``evidence.grid_points`` list cuts (the cell stops a piece at its last point)."""
    if scene_model is None:
        idle = [f"evidence.{key} {value:g}" for key, value in (
            ("untouched_confidence", getattr(cfg, "untouched_confidence", None)),
            ("extra_presses", getattr(cfg, "extra_presses", None)),
            ("twin_ratio", getattr(cfg, "twin_ratio", None))) if value is not None]
        return "" if not idle else (
            f"{cfg.path}: {' and '.join(idle)} {'does' if len(idle) == 1 else 'do'} nothing: the bundle has no "
            "scene model, and its router's posterior sorts every class at evidence.confidence within max_presses")
    said = []
    for key, kind, ours, model_key in (
            ("confidence", "touched", float(cfg.confidence) if config_sets_confidence(cfg) else None, "confidence"),
            ("untouched_confidence", "untouched", getattr(cfg, "untouched_confidence", None), "untouched_confidence")):
        if ours is None or float(ours) == (theirs := float(getattr(scene_model, model_key))):
            continue
        effect = ("bolder: expect more pieces in wrong bins" if ours < theirs
                  else "more cautious: expect more pieces in the reject bin")
        said.append(f"evidence.{key} {float(ours):g} overrides the {kind} confidence {theirs:g} that training chose "
                    f"on validation for the scene model's mis-sort target ({effect})")
    ours, theirs = getattr(cfg, "extra_presses", None), int(getattr(scene_model, "extra_presses", 0) or 0)
    if ours is not None and int(ours) != theirs:
        effect = ("more presses for unconfident pieces a touched fabric leads than validation priced" if ours > theirs
                  else "expect more touched pieces in the reject bin")
        said.append(f"evidence.extra_presses {int(ours)} overrides the {theirs} extra presses training chose on "
                    f"validation ({effect})")
    if getattr(cfg, "twin_ratio", None) is not None and twin_ratio_idle(scene_model):
        said.append(f"evidence.twin_ratio {float(cfg.twin_ratio):g} does nothing: the scene model has no offset "
                    "setting to say where a synthesis's error reaches (re-export the bundle)")
    elif getattr(cfg, "twin_ratio", None) is not None:
        twins = job_twins(cfg, scene_model)
        said.append(f"evidence.twin_ratio {float(cfg.twin_ratio):g} holds " + (
            f"{', '.join(twins)} to confidence {TWIN_CONFIDENCE:g} or more (an untouched fabric of the job lies within "
            "that many times the generator's error of them: expect their pieces in the reject bin unless "
            "near-certain)" if twins else "no fabric of this job back (no touched fabric lies that near an "
                                          "untouched one's synthesis)"))
    points = len(getattr(cfg, "grid_points", ()) or ())
    needed = int(getattr(cfg, "max_presses", 0)) + theirs
    cut = ""
    listed = getattr(cfg, "grid_order", "list") == "list"  # spread and rows order the whole grid: nothing to list
    if ours is None and listed and points and needed > points:  # a written key is held to the grid by the config check
        cut = (f"the scene model's {theirs} extra presses need {needed} press points with evidence.max_presses "
               f"{cfg.max_presses}, and evidence.grid_points lists {points}: a piece stops at {points} presses, "
               "short of what validation priced (list more points, or write evidence.extra_presses)")
    if not said:
        return f"{cfg.path}: {cut}" if cut else ""
    return (f"{cfg.path}: " + "; ".join(said) + "; remove the key to sort at the model's own operating point"
            + (f"; {cut}" if cut else ""))


def scene_model_settings(cfg, scene_model) -> tuple[float, dict]:
    """``evidence_settings`` of a scene model itself (operator labels build evidence from a model
    they adapted, runtime/feedback.py): its rule, the config's written confidences over its own
    (``evidence.confidence`` for touched classes, ``evidence.untouched_confidence`` for untouched
    ones), the config's ``evidence.extra_presses`` over its own (``extra_presses_of``), and the
    job's twins that a written ``evidence.twin_ratio`` holds back (``job_twins``)."""
    confidence, opts = scene_model_rule(scene_model)
    untouched = getattr(cfg, "untouched_confidence", None)
    if untouched is not None:
        opts = {**opts, "class_confidence": {c: float(untouched) for c in opts["class_confidence"]}}
    opts = {**opts, "extra_presses": extra_presses_of(cfg, scene_model)}
    confidence = cfg.confidence if config_sets_confidence(cfg) else confidence
    return confidence, held_back(opts, job_twins(cfg, scene_model), confidence)


TWIN_CONFIDENCE = 0.9999  # what a touched fabric an untouched fabric of the job may be needs (evidence.twin_ratio)


def held_back(opts: dict, twins, confidence: float) -> dict:
    """``Evidence`` keyword arguments ``opts`` with each of ``twins`` needing ``TWIN_CONFIDENCE``, and
    never less than the touched ``confidence`` (a written evidence.confidence may be higher)."""
    if not twins:
        return opts
    held = {t: max(TWIN_CONFIDENCE, float(confidence)) for t in twins}
    return {**opts, "class_confidence": {**opts["class_confidence"], **held}}


def job_twins(cfg, scene_model) -> list[str]:
    """The touched fabrics of the config's job that ``evidence.twin_ratio`` holds to ``TWIN_CONFIDENCE``:
    those whose mean lies within that many times the generator's expected error of an untouched
    fabric's synthesis (``SceneModel.twins``; a fabric operator labels taught is no synthesis). []
    when the key is not written, or the scene model has no offset setting (``twin_ratio_idle``). On
    the demo world's test jobs, 4 splits, ratio 1: mis-sorted 2.4 -> 0.4 %, untouched pieces
    mis-sorted 7.1 -> 0.0 %, right bin 56.8 -> 50.8 % (docs/decision.md, "Twins in a job")."""
    ratio = getattr(cfg, "twin_ratio", None)
    if ratio is None:
        return []
    return scene_model.twins([f.name for f in getattr(cfg, "fabrics", ())], float(ratio))


def twin_ratio_idle(scene_model) -> bool:
    """A scene model that cannot say where a synthesis's error reaches: a sum-rule one without the
    offset setting labels use (a file from before it), or an untouched offset variance of 0."""
    m = scene_model.for_labels()  # the model itself under the offset rule
    return m is None or not float(m.offset_var_untouched or 0.0) > 0


def refuses_off_scene(scene_model) -> bool:
    """The scene model's item rule has an off-scene rule on (a finite threshold or margin)."""
    return math.isfinite(float(scene_model.open_threshold)) or math.isfinite(float(scene_model.known_margin))


def one_fabric_problem(cfg, scene_model) -> str:
    """Why a one-fabric scene cannot start with this bundle's scene model ('' when it can, or the
    scene has more fabrics). Restricted to one class the posterior is 1 on every press; only the
    scene model's off-scene rules (runtime/evidence.py) can send a piece to the reject bin - and
    training's search may turn both off (a choice for scenes of several fabrics, whose posterior can
    refuse). The rule operator labels switch to keeps them (``SceneModel.for_labels``). The start
    refuses the job (runtime/wiring.py), and ``validate-config --check-bundle`` says so before it."""
    if len(cfg.fabrics) != 1:
        return ""
    if scene_model is None:
        why, fix = "has no scene model (decision.npz)", "Export the bundle with its scene model"
    elif not refuses_off_scene(scene_model):
        why = "has a scene model with both off-scene rules off (open_threshold and known_margin infinite)"
        fix = "Deploy a bundle whose training chose an off-scene rule"
    else:
        return ""
    return (f"{cfg.path}: the scene has one fabric ({cfg.fabrics[0].name}) and bundle {cfg.bundle} {why}, so nothing "
            f"could refuse a piece: every piece on the line would be sorted into that fabric's bin. {fix}, or list "
            "the other fabrics the line carries")


def scene_bundle_problem(cfg, touched, untouched, manifest, scene_model) -> str:
    """Why the job's fabrics cannot be sorted with a bundle of these classes, manifest and scene
    model ('' when they can). Every scene fabric is a class of the bundle, of the kind the scene
    says: a fabric the scene calls touched that the bundle only knows zero-shot (or the reverse) is
    a wrong config or a wrong bundle, and the cell would sort it with the wrong expectation. A
    one-fabric scene needs an off-scene rule (``one_fabric_problem``). The camera must hand the frames
    the bundle trained on (runtime/jpeg_quality.py ``camera_format_problem``: no YUYV camera for a
    bundle trained through the camera's JPEG). The start refuses the job
    (runtime/wiring.py, on the loaded bundle); `validate-config --check-bundle` asks the same of the
    bundle's files (runtime/config_cli.py), so the unit's ExecStartPre stops what `run` would."""
    touched, untouched = list(touched), list(untouched)
    provenance = (manifest or {}).get("provenance") or {}
    if provenance.get("trained") is False:
        # `export --random-trunk`: the shapes and cost of a trained bundle, with real fabric names,
        # and decisions that mean nothing (on the paper world 17 of 21 pieces into wrong bins)
        return (f"bundle {cfg.bundle} was never trained (manifest provenance.trained: false, operating "
                f"point {(manifest or {}).get('operating_point', '?')!r}): a latency bundle for "
                "`vs2t-edge bench`, not one to sort with; deploy a bundle exported from a training run")
    missing = [f.name for f in cfg.fabrics if f.name not in touched + untouched]
    refuse_only = [f for f in missing if f in getattr(scene_model, "known_only", ())]
    if refuse_only:
        return (f"scene fabric(s) {refuse_only} are known to bundle {cfg.bundle} only to refuse their "
                "pieces (fabrics its training run held out to choose with: no classifier has them); "
                "train a run that touches them to sort them")
    if missing:
        return (f"scene fabric(s) {missing} are not classes of bundle {cfg.bundle} "
                f"(touched: {touched}, untouched: {untouched})")
    wrong = [f"{f.name} (scene: {f.kind}, bundle: {'touched' if f.name in touched else 'untouched'})"
             for f in cfg.fabrics if (f.name in touched) != (f.kind == "touched")]
    if wrong:
        return (f"{cfg.path}: scene fabric kind disagrees with bundle {cfg.bundle}: {'; '.join(wrong)} "
                "- fix scene.fabrics[].kind, or deploy the bundle trained for this scene")
    camera = camera_format_problem(getattr(cfg, "camera", None) or {}, (manifest or {}).get("camera_jpeg", 0))
    return one_fabric_problem(cfg, scene_model) or (f"{cfg.path}: {camera}" if camera else "")


__all__ = ["OverrideFileError", "override_path_for", "override_file_for", "resolve_beta", "read_beta_override",
           "write_beta_override", "scene_model_rule", "config_sets_confidence", "extra_presses_of",
           "confidence_override_note",
           "evidence_settings", "scene_model_settings", "refuses_off_scene", "one_fabric_problem",
           "scene_bundle_problem"]

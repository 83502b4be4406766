"""How a cell is wired: from a cell config to the parts a session runs on, and to a ready
:class:`~vs2t_edge.runtime.cell.Cell`.

The parts: the verified, warmed model of the config's bundle, checked against the scene; the
camera, arm and gate the config names; the item rule (``runtime.evidence.Evidence`` with the
operating point's numbers); the press-frame contact check. Every verb that runs the cell goes
through these functions: `run` (runtime/daemon.py), `record` (runtime/record_cli.py), `replay`
and session recording (runtime/recording.py), `calibrate-threshold --live-*` (through `record`) and
the demo and its reference sessions (sim/demo.py, sim/scene.py, which inject simulated devices
and their own model). One wiring means a replay or a demo runs the cell exactly as `run` does.

Which numbers decide (beta, the scene model's item rule and the config's overrides) is
runtime/operating_point.py's to say; this module asks it and builds what it says.

Devices of kind ``sim`` are built by the simulated cell (vs2t_edge.sim.scene), which passes them
in; a config's simulated gate or fake arm and gate (a dry run) are looked up by name
(runtime/devices.py ``SIMULATORS``): the cell runtime never imports vs2t_edge.sim.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

from vs2t_edge.runtime.arm_isolated import IsolatedURArm
from vs2t_edge.runtime.bundle import SEAL_KEY, BundleError, read_manifest
from vs2t_edge.runtime.camera import UVCCamera, camera_from_config
from vs2t_edge.runtime.contact import ContactCheck
from vs2t_edge.runtime.cell import Cell, SceneSpec
from vs2t_edge.runtime.config import CellConfig, ConfigError
from vs2t_edge.runtime.devices import simulator
from vs2t_edge.runtime.evidence import Evidence
from vs2t_edge.runtime.labels import OperatorFeedback
from vs2t_edge.runtime.jpeg_quality import trained_quality
from vs2t_edge.runtime.gate import SerialGate
from vs2t_edge.runtime.inference import TactileModel
from vs2t_edge.runtime.items import ContinuousFeed
from vs2t_edge.runtime.preprocess import camera_scale, float_path_scale
from vs2t_edge.runtime.operating_point import evidence_settings, resolve_beta, scene_bundle_problem, scene_model_settings


class SceneModelMissing(ValueError):
    """A bundle without a scene model, and a config that did not opt in to run it; or operator
    labels on one without an offset-rule setting to learn with."""


def load_model(cfg: CellConfig) -> TactileModel:
    """Verified, warmed model of the bundle, with the beta the operating point says (an override
    file calibrated for another bundle is refused), checked against the scene (raises on any
    mismatch, naming it)."""
    manifest = read_manifest(cfg.bundle)
    model = TactileModel.load(cfg.bundle, threads=cfg.threads, beta_override=resolve_beta(cfg, manifest)[0])
    if model.manifest.get(SEAL_KEY) != manifest.get(SEAL_KEY):  # the override was checked against this one
        raise BundleError(cfg.bundle, "the bundle was replaced while it was being loaded; start again")
    check_scene_against_bundle(cfg, model)
    return model


def check_scene_against_bundle(cfg: CellConfig, model) -> None:
    """Raise ValueError when the job's fabrics cannot be sorted with this loaded bundle
    (runtime/operating_point.py ``scene_bundle_problem``, which `validate-config --check-bundle`
    asks of the bundle's files before the start)."""
    problem = scene_bundle_problem(cfg, model.touched, model.untouched, getattr(model, "manifest", None) or {},
                                   getattr(model, "scene_model", None))
    if problem:
        raise ValueError(problem)


def evidence_factory_for(cfg: CellConfig, model: Any = None) -> Callable[[], Evidence]:
    """A fresh item evidence per piece for the config's scene, with the item rule
    runtime/operating_point.py chooses for ``cfg`` and ``model`` (the scene model's, when the
    bundle has one, with the config's written confidence over it).

    A bundle without a scene model is refused (``SceneModelMissing``) unless the config opts in
    (``evidence.without_scene_model: allow``): its posterior has no off-scene rule, so a piece of a
    fabric outside the scene is sorted into the likeliest scene fabric's bin."""
    require_scene_model(model, cfg.bundle, cfg.without_scene_model,
                        f"set `evidence.without_scene_model: allow` in {cfg.path}")
    if cfg.operator_labels is not None:  # learning from the reject bin (runtime/feedback.py)
        scene_model = getattr(model, "scene_model", None)
        if scene_model is None or scene_model.for_labels() is None:
            raise SceneModelMissing(f"{cfg.path}: evidence.operator_labels needs a scene model with an offset item rule "
                             f"setting; bundle {cfg.bundle} has "
                             + ("no scene model" if scene_model is None else "a sum-rule one without it (re-export it)"))

        def make(m, classes):
            conf, kw = scene_model_settings(cfg, m)
            return Evidence(classes, conf, cfg.max_presses, **kw)
        return OperatorFeedback(scene_model, cfg.scene_classes, cfg.operator_labels, make)
    confidence, opts = evidence_settings(cfg, model)
    return lambda: Evidence(cfg.scene_classes, confidence, cfg.max_presses, **opts)


def require_scene_model(model: Any, bundle, without_scene_model: str | None, opt_in: str) -> None:
    """Raise ``SceneModelMissing`` for a ``model`` without a scene model unless ``without_scene_model``
    is "allow"; ``opt_in`` says how the caller's user opts in (the config key, the demo's flag)."""
    if getattr(model, "scene_model", None) is None and without_scene_model != "allow":
        raise SceneModelMissing(
            f"bundle {bundle} has no scene model (decision.npz): its posterior has no off-scene rule, so a "
            "piece of a fabric outside the scene would be sorted into the likeliest scene fabric's bin, never "
            "the reject bin (27-41 % of pieces mis-sorted wherever the project measured that posterior). "
            "Re-export it with `vs2t-edge export RUN --out BUNDLE` (RUN: its training run), which writes the "
            f"scene model, or - knowing that risk - {opt_in}")


def contact_check_for(cfg: CellConfig, model=None) -> ContactCheck | None:
    """The press-frame contact check the config asks for, or None (docs/cell.md, "Contact check").
    With a trunk ``model``, the imprint must also lie in the square its preprocessing crops."""
    cam = cfg.camera
    on = cam["contact_check"] == "on" or (cam["contact_check"] == "auto" and cam["kind"] == "uvc")
    if not on:
        return None
    return ContactCheck(threshold_levels=cam["contact_threshold_levels"], min_area_fraction=cam["contact_min_area"],
                        crop_fraction=model_crop_fraction(model))


def model_crop_fraction(model) -> float | None:
    """The share of a frame's shorter side a trunk model crops, centred (None: a descriptor bundle,
    which reads the whole frame, or no model)."""
    if model is None or getattr(model, "descriptor", None) is not None:
        return None
    spec = getattr(model, "preprocess_spec", None)
    return float(spec.crop_fraction) if spec is not None else None


DECODE_SCALES = ("auto", "full")  # devices.camera.decode_scale (runtime/config.py holds the literal)


def model_decode_scale(model: Any, frame_hw: tuple[int, int] | None = None, setting: str = "auto",
                       pixel_format: str = "mjpeg") -> int:
    """The scale a UVC camera decodes its frames at for ``model``'s bundle (``devices.camera.decode_scale``):

    - ``full``: full size; a reduced-path bundle then reduces the frames itself with training's
      box average;
    - ``auto`` (the default): the reduced path's own 1/reduce; a float-path bundle trained on
      lossless frames, from an MJPEG camera, the largest 1/n that leaves its input size across the
      crop of ``frame_hw`` frames (runtime/preprocess.py ``float_path_scale``: 1/2 of 640x480 at
      128 or 224 px); a float-path bundle trained through the camera's JPEG (manifest
      ``camera_jpeg``), from an MJPEG camera, the scale it trained at (``camera_scale``: preprocess
      ``jpeg_scale``, full size before 2026-11-29), or a larger one where a smaller camera's frames
      would leave fewer than its input size across the crop; full size for a float-path bundle on a YUYV camera (its frames
      reduced in uint8 lie farther from training's float average than whole ones: 0.43 against
      0.30 grey levels at 128 px on a rendered press), without ``frame_hw``, for a descriptor
      bundle and for any other model."""
    if setting not in DECODE_SCALES:
        raise ValueError(f"decode_scale {setting!r}: one of {DECODE_SCALES}")
    spec = getattr(model, "preprocess_spec", None)
    if getattr(model, "descriptor", None) is not None or spec is None or setting == "full":
        return 1
    if int(getattr(spec, "reduce", 0)):
        return int(spec.reduce)
    if frame_hw is None or pixel_format != "mjpeg":
        return 1
    if trained_quality(model):  # as it trained, where the camera's frames leave enough pixels
        return min(camera_scale(spec), float_path_scale(spec, frame_hw))
    return float_path_scale(spec, frame_hw)


def decode_scale_note(model: Any, setting: str) -> str:
    """What the start log says when ``devices.camera.decode_scale: full`` hands full frames to a
    bundle trained through the camera's JPEG decoded smaller (preprocess ``jpeg_scale``): they are
    scored, but not as it trained. '' otherwise."""
    spec = getattr(model, "preprocess_spec", None)
    # jpeg_scale > 1 is a float-path camera_jpeg bundle's alone (TactilePreprocess, runtime/bundle.py)
    if setting != "full" or spec is None or spec.jpeg_scale == 1:
        return ""
    return (f"devices.camera.decode_scale full: this bundle trained on its camera's JPEG decoded at "
            f"1/{spec.jpeg_scale} (preprocess.jpeg_scale); full frames are scored on the float path, not as it "
            "trained - remove the key (auto) to decode as it trained")


def decode_fallback_note(model: Any, camera: Any) -> str:
    """What the start log says when a connected UVC camera's backend decodes the MJPEG itself (the
    fallback: ``settings_applied["mjpeg_undecoded"]`` false) for a bundle trained through the camera's
    JPEG: the stream's quality cannot be read against the bundle's, and a bundle trained on decodes
    at 1/n (``camera_scale``) scores the backend's full decodes, not as it trained (on the demo
    world, a tiny run at q90 and 1/2 decided 61 of 528 test-job pieces otherwise so). '' otherwise: a
    lossless-trained bundle's fallback is training's own path.

    Said, not refused, unlike a YUYV camera for such a bundle (``camera_format_problem``): that is a
    setting of the cell config, which the operator changes; a backend that decodes for itself is the
    machine's OpenCV build, and on the audit's run it moved right and wrong bins far less than
    uncompressed frames did (61 against 87 of 528 pieces)."""
    q = trained_quality(model)
    spec = getattr(model, "preprocess_spec", None)
    applied = getattr(camera, "settings_applied", None)
    if not q or spec is None or not isinstance(camera, UVCCamera) or not isinstance(applied, dict) \
            or applied.get("mjpeg_undecoded") is not False:
        return ""
    note = (f"the camera's backend decodes its MJPEG itself (it did not take CAP_PROP_CONVERT_RGB 0): the stream's "
            f"quality cannot be read to check it against the q{q} this bundle trained through")
    n = camera_scale(spec) if getattr(model, "descriptor", None) is None else 1
    if n > 1:
        how = "reduced by a box average" if spec.reduce else "on the float path"
        note += (f"; and it trained on that JPEG decoded at 1/{n}: the backend's full decodes are scored {how}, not as "
                 "it trained (OpenCV's V4L2 backend hands the MJPEG undecoded)")
    return note


def match_camera(camera: Any, model: Any, setting: str = "auto") -> None:
    """Before connect: a UVC camera decodes its frames at the scale ``model_decode_scale`` gives
    ``model``'s bundle for the camera's configured size, and takes the MJPEG stream (undecoded, its
    quality read) whenever the bundle was trained through the camera's JPEG - at full scale too,
    where the driver would otherwise pick the format (YUYV, in OpenCV's V4L2 backend); other cameras
    hand full frames, which the model reduces itself (reduced path) or takes whole (float path)."""
    if isinstance(camera, UVCCamera):
        camera.decode_scale = model_decode_scale(model, camera.expected_hw, setting, camera.pixel_format)
        # a bundle trained through the camera's JPEG gets the MJPEG stream at any scale (runtime/camera.py)
        camera.take_mjpeg = bool(trained_quality(model))


def build_live_devices(cfg: CellConfig):
    """(camera, arm, gate) from the config, not yet connected. Vendor SDKs (ur_rtde) are imported
    by the drivers only when connected; devices of kind ``sim`` are the simulated cell's to build.
    A UVC camera decodes at full size until ``match_camera`` gives it the model's scale."""
    cam, gate_cfg = cfg.camera, cfg.gate
    if cam["kind"] == "sim":
        raise ConfigError(cfg.path, [f"{cfg.path}: devices.camera.kind = sim is built by the simulated cell "
                                     "(`vs2t-edge demo`), not by `run`"])
    camera = camera_from_config(cam)
    if cfg.arm_kind == "ur_rtde":
        # ur_rtde in a worker process: a client crash (it can segfault on a flapping link)
        # costs one press, not the service (docs/arm.md).
        arm = IsolatedURArm(cfg.arm)
    elif cfg.arm_kind == "fake":
        arm = simulator("fake_arm")(config=cfg.arm)  # a dry run: in-process, from vs2t_edge.sim
    else:
        raise ConfigError(cfg.path, [f"{cfg.path}: devices.arm.kind = sim is built by the simulated cell "
                                     "(`vs2t-edge demo`), not by `run`"])
    if gate_cfg["kind"] == "serial":
        gate = SerialGate(gate_cfg["url"], timeout_s=gate_cfg["timeout_s"], retries=gate_cfg["retries"])
    elif gate_cfg["kind"] == "sim":
        gate = simulator("gate")()  # the MCU simulator on a pty, from vs2t_edge.sim, imported only now
    else:
        gate = simulator("fake_gate")()  # a dry run: in-process, from vs2t_edge.sim
    return camera, arm, gate


def build_cell(cfg: CellConfig, *, model, camera, arm, gate, journal, notifier, items=None,
               evidence_factory: Callable[[], Any] | None = None, stop_event: threading.Event | None = None,
               on_item=None, log: Callable[[str], None] | None = None) -> Cell:
    """The cell loop of ``cfg`` on the given model, devices (connected by the caller, which owns
    their lifetime), journal and notifier. What is not injected comes from the config: the item
    rule (:func:`evidence_factory_for`), the items (a continuous feed numbered on from the
    journal, so a restart never reuses a piece id), the contact check and the scene."""
    return Cell(camera=camera, arm=arm, gate=gate, model=model, journal=journal, notifier=notifier,
                scene=SceneSpec.from_config(cfg),
                evidence_factory=evidence_factory or evidence_factory_for(cfg, model),
                items=items or ContinuousFeed(first_number=journal.next_item_number()), stop_event=stop_event,
                on_item=on_item, log=log, contact_check=contact_check_for(cfg, model))


__all__ = ["SceneModelMissing", "load_model", "check_scene_against_bundle", "evidence_factory_for",
           "contact_check_for", "model_crop_fraction", "DECODE_SCALES", "model_decode_scale",
           "decode_fallback_note", "match_camera", "build_live_devices", "build_cell"]

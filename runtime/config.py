"""The cell's config file: YAML, every key known, every bound checked, errors with file:line.

One file describes one cell: which bundle, which devices, which scene (the fabrics that may
arrive, touched or untouched, and their bins), the stopping rule, the journal and the watchdog.
``load_config(path)`` returns a :class:`CellConfig` or raises :class:`ConfigError` listing
*every* problem found, each as ``FILE:LINE: key.path: what is wrong`` (line numbers come from
the YAML node marks, so the operator lands on the right line at once).

The reference of every key, with bounds and defaults, is in docs/cell.md; ``_SCHEMA`` below is
the single source of truth and a test checks the two agree.
"""

from __future__ import annotations

import math
import os
import stat
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vs2t_edge.firmware_bridge.gate_client import move_problems as gate_move_problems
from vs2t_edge.firmware_bridge.gate_client import timing_problems as gate_timing_problems
from vs2t_edge.firmware_bridge.protocol import REJECT_BIN as GATE_REJECT_BIN
from vs2t_edge.runtime.arm import GRID_N, ArmConfig, ArmConfigError
from vs2t_edge.runtime.budget import SYSTEMD_WATCHDOG_S, bounds_of, watchdog_problems
from vs2t_edge.runtime.config_yaml import ConfigError, parse_yaml_with_lines
from vs2t_edge.runtime.files import MAX_CONFIG_BYTES
from vs2t_edge.runtime.names import OFF_SCENE_PREFIX, name_key

CAMERA_KINDS = ("uvc", "replay", "sim")
ARM_KINDS = ("ur_rtde", "fake", "sim")
GATE_KINDS = ("serial", "sim", "fake")
GRID_ORDERS = ("spread", "rows", "list")
WITHOUT_SCENE_MODEL = ("refuse", "allow")
SHARED_BINS = ("refuse", "allow")  # scene.shared_bins
N_GRID_X = N_GRID_Y = GRID_N  # 15: the paper's 15 x 15 grid of press points on the 8 cm piece


# --- the schema --------------------------------------------------------------------------
# A leaf is (type, default, bounds-or-choices, help). type: "float", "int", "str", "path",
# "bool", "optfloat", "optint", "list". Nested dicts are sections. REQUIRED marks keys without default.

REQUIRED = object()


def _leaf(kind: str, default: Any, bounds: Any = None, help_text: str = "", why: str = "") -> dict:
    """``why``: said after an out-of-bounds error, when the bound is not obvious from the key."""
    return {"__leaf__": True, "kind": kind, "default": default, "bounds": bounds, "help": help_text, "why": why}


# A hung grab must become a latched camera fault, not a kill by systemd's watchdog: the waits of
# the loop against WatchdogSec are runtime/budget.py's, checked below (watchdog_problems).
CAMERA_TIMEOUT_MAX_S = 10.0


_ARM_PRESS_KEYS = {name: f for name, f in ArmConfig.__dataclass_fields__.items() if name != "host"}

_SCHEMA: dict[str, Any] = {
    "bundle": _leaf("path", REQUIRED, None, "model bundle folder (relative paths: to this file)"),
    "beta_override": _leaf("optfloat", None, (-1e9, 1e9), "novelty threshold replacing the bundle's beta"),
    "beta_override_file": _leaf("optpath", None, None, "beta_override.json written by calibrate-threshold "
                                                      "(default: next to the bundle, if present)"),
    "threads": _leaf("int", 2, (1, 64), "onnxruntime intra-op threads"),
    "devices": {
        "camera": {
            "kind": _leaf("str", "uvc", CAMERA_KINDS, "uvc (cv2.VideoCapture), replay (recorded files), sim"),
            "device": _leaf("str", "/dev/video0", None, "uvc: device path or index"),
            "width_px": _leaf("int", 640, (16, 4096), "uvc: frame width"),
            "height_px": _leaf("int", 480, (16, 4096), "uvc: frame height"),
            "fps": _leaf("float", 30.0, (1.0, 240.0), "uvc: frame rate asked for"),
            # runtime/camera.py PIXEL_FORMATS (a literal here: importing the camera loads cv2)
            "pixel_format": _leaf("str", "mjpeg", ("mjpeg", "yuyv"),
                                  "uvc: mjpeg (compressed, decoded per press) or yuyv (uncompressed 4:2:2)"),
            # runtime/wiring.py DECODE_SCALES (a literal here, as above): the scale the camera decodes
            # its frames at for the bundle (docs/cell.md, "Decode scale")
            "decode_scale": _leaf("str", "auto", ("auto", "full"),
                                  "uvc: auto (the reduced path's scale; a float-path bundle's MJPEG frames at the "
                                  "smallest size that keeps its input size across the crop) or full"),
            # V4L2's exposure_time_absolute, in its units of 100 us (1 = 0.1 ms .. 10000 = 1 s);
            # absent = the camera's auto exposure. A GelSight's LEDs are constant, so a fixed
            # exposure keeps frames comparable with the no-contact reference across a shift.
            "exposure": _leaf("optfloat", None, (1.0, 10000.0),
                              "uvc: manual exposure, V4L2 units of 100 us (absent: auto exposure)"),
            "timeout_s": _leaf("float", 2.0, (0.05, CAMERA_TIMEOUT_MAX_S), "longest wait for one frame",
                               why=f"a hung grab must become a latched camera fault, not a kill by systemd's "
                                   f"WatchdogSec={SYSTEMD_WATCHDOG_S:g} s (a press and its retry each wait this long)"),
            # after each open (start, the reopen before a retry, the operator's clear), frames read
            # until the picture's brightness holds still: auto exposure ramps over a stream's first
            # frames, and the first grab is a piece's no-contact reference (runtime/camera_warmup.py).
            # Below UVC_OPEN_TIMEOUT_S (5 s), inside whose bound it runs.
            "warmup_s": _leaf("float", 2.0, (0.0, 4.0),
                              "uvc: after each open, read frames until their brightness holds still, at most "
                              "this long (0: none)"),
            "flush_frames": _leaf("int", 2, (0, 30),
                                  "uvc: buffered frames dropped before each grab (taken before the press settled)"),
            "frozen_after": _leaf("int", 2, (2, 100),
                                  "identical consecutive frames that are a frozen-camera fault (2: the first repeat)"),
            "path": _leaf("optpath", None, None, "replay: replay file; sim: dataset folder"),
            # Is the gel really pressed? (runtime/contact.py ContactCheck against the item's no-contact
            # frame.) auto = on for a live sensor, off for replay and simulated frames, whose rendered
            # imprints are fainter than a real GelSight's (docs/cell.md, "Contact check").
            "contact_check": _leaf("str", "auto", ("auto", "on", "off"),
                                   "press frames must differ from the no-contact frame: auto (uvc only), on, off"),
            "contact_threshold_levels": _leaf("float", 12.0, (1.0, 255.0),
                                              "contact check: change in grey levels that counts as an imprint"),
            "contact_min_area": _leaf("float", 0.005, (0.0001, 0.5),
                                      "contact check: fraction of the image that must change"),
        },
        "arm": {
            "kind": _leaf("str", "ur_rtde", ARM_KINDS, "ur_rtde (live robot), fake or sim (loopback simulator)"),
            "host": _leaf("str", "192.168.1.10", None, "ur_rtde: the robot's IPv4 address"),
            # Every other key is a press parameter of runtime/arm.py ArmConfig, bounds included.
            "__open__": "arm",
        },
        "gate": {
            "kind": _leaf("str", "serial", GATE_KINDS, "serial (the gate MCU), sim (MCU simulator on a pty), fake"),
            "url": _leaf("str", "/dev/ttyACM0", None, "serial: device path or pyserial URL"),
            "timeout_s": _leaf("float", 0.5, (0.05, 10.0), "ack timeout per try"),
            "retries": _leaf("int", 3, (0, 10), "retransmissions before a gate fault"),
        },
    },
    "scene": {
        "reject_bin": _leaf("int", 0, (0, 7), "bin for unknown items, faults and anything off-scene: the "
                                              "gate's own reject bin, 0"),
        "fabrics": _leaf("list", REQUIRED, None, "list of {name, kind: touched|untouched, bin}"),
        # a copied bin line merges two fabrics: refused while a bin stays free, unless written here
        "shared_bins": _leaf("str", "refuse", SHARED_BINS,
                             "two fabrics in one bin while a bin of the gate stays free: refuse the config "
                             "(a copied line?) or allow it"),
    },
    "evidence": {
        "confidence": _leaf("float", 0.9, (0.5, 0.99999), "stop pressing once the posterior reaches this"),
        "max_presses": _leaf("int", 5, (1, N_GRID_X * N_GRID_Y), "press limit per item"),
        # runtime/evidence.py: past max_presses, while a touched fabric of the job leads, unrefused
        "extra_presses": _leaf("optint", None, (0, N_GRID_X * N_GRID_Y),
                               "a bundle with a scene model: presses past max_presses for a piece a touched fabric "
                               "leads, not yet confident, refused by no off-scene rule (default: the model's, "
                               "chosen in training)"),
        # runtime/operating_point.py: the knob that prices mis-sorts against untouched right-bin
        "untouched_confidence": _leaf("optfloat", None, (0.5, 0.99999),
                                      "a bundle with a scene model: the posterior that sorts a piece into an "
                                      "untouched fabric's bin (default: the model's, chosen in training)"),
        # runtime/operating_point.py: touched fabrics an untouched fabric of the job may be, held back
        "twin_ratio": _leaf("optfloat", None, (0.01, 100.0),
                            "a bundle with a scene model: hold a touched fabric of the job to confidence "
                            "0.9999 where its mean lies within this many times the generator's expected "
                            "error of an untouched fabric's synthesis (default: off)"),
        "grid_order": _leaf("str", "spread", GRID_ORDERS, "spread (far-apart points first), rows, or list"),
        "grid_points": _leaf("list", None, None, "grid_order list: press indices 0..224 (row-major 15x15)"),
        # runtime/wiring.py evidence_factory_for: without decision.npz nothing refuses an off-scene piece
        "without_scene_model": _leaf("str", "refuse", WITHOUT_SCENE_MODEL,
                                     "a bundle without a scene model (decision.npz): refuse it at start, or allow "
                                     "it - then no off-scene rule: a piece of a fabric outside the scene goes to the "
                                     "likeliest scene fabric's bin (27-41 % of pieces mis-sorted where measured)"),
        # runtime/feedback.py: outside the zero-shot protocol, so off unless a file is named
        "operator_labels": _leaf("optpath", None, None,
                                 "learn from the reject bin: a JSON-lines file of operator labels (`vs2t-edge "
                                 "label`); each re-estimates an untouched fabric's mean from the labelled piece"),
    },
    "cell": {
        # runtime/press_pipeline.py: decisions are the same either way; off = the model's time
        # adds to every press, as before issue 14
        "overlap_scoring": _leaf("bool", True, None,
                                 "score a press in a worker thread while the arm lifts and moves on"),
    },
    "journal": _leaf("path", "/var/lib/vs2t-edge/journal.jsonl", None, "append-only decision journal"),
    "fault_file": _leaf("optpath", None, None, "latched-fault marker (default: next to the journal)"),
    "watchdog": {
        "item_timeout_s": _leaf("float", 60.0, (1.0, 3600.0), "an item taking longer is a fault"),
        "wait_item_timeout_s": _leaf("float", 1.0, (0.01, 60.0), "longest wait for an item before a WATCHDOG ping"),
    },
}


# --- the result --------------------------------------------------------------------------

@dataclass(frozen=True)
class SceneFabric:
    name: str
    kind: str  # "touched" or "untouched"
    bin: int


@dataclass(frozen=True)
class CellConfig:
    path: Path
    bundle: Path
    beta_override: float | None
    beta_override_file: Path | None
    threads: int
    camera: dict
    arm_kind: str
    arm: ArmConfig
    gate: dict
    reject_bin: int
    fabrics: tuple[SceneFabric, ...]
    confidence: float
    max_presses: int
    grid_order: str
    grid_points: tuple[int, ...]
    journal: Path
    fault_file: Path
    item_timeout_s: float
    wait_item_timeout_s: float
    overlap_scoring: bool = True
    without_scene_model: str = "refuse"  # evidence.without_scene_model: "allow" is the written opt-in
    operator_labels: Path | None = None  # evidence.operator_labels (runtime/feedback.py)
    untouched_confidence: float | None = None  # evidence.untouched_confidence (runtime/operating_point.py)
    extra_presses: int | None = None  # evidence.extra_presses; None: the scene model's (runtime/operating_point.py)
    twin_ratio: float | None = None  # evidence.twin_ratio; None: off (runtime/operating_point.py)
    raw: dict = field(default_factory=dict, repr=False)

    @property
    def scene_classes(self) -> list[str]:
        return [f.name for f in self.fabrics]

    def bin_for(self, label: str) -> int:
        """The scene's bin for a decided label; anything else (unknown, off-scene) -> reject."""
        for f in self.fabrics:
            if f.name == label:
                return f.bin
        return self.reject_bin

    def press_points_mm(self) -> list[tuple[float, float]]:
        grid = self.arm.grid_points_mm(N_GRID_X, N_GRID_Y)
        return [grid[i] for i in self.grid_points]


def spread_order(n_x: int = N_GRID_X, n_y: int = N_GRID_Y) -> list[int]:
    """Grid indices, each next point the farthest from those already pressed (centre first).

    Far-apart presses see different parts of the weave, so early stopping sees more of the
    fabric per press than a row-by-row scan would; deterministic (ties: lowest index).
    """
    pts = [(i % n_x, i // n_x) for i in range(n_x * n_y)]
    centre = (n_y // 2) * n_x + n_x // 2
    chosen = [centre]
    d2 = [(x - pts[centre][0]) ** 2 + (y - pts[centre][1]) ** 2 for x, y in pts]
    while len(chosen) < len(pts):
        best = max(range(len(pts)), key=lambda i: (d2[i], -i))
        chosen.append(best)
        bx, by = pts[best]
        d2 = [min(d, (x - bx) ** 2 + (y - by) ** 2) for d, (x, y) in zip(d2, pts)]
        for c in chosen:
            d2[c] = -1
    return chosen


def _finite(value: int | float) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer past float range
        return False


# --- validation --------------------------------------------------------------------------

class _Checker:
    def __init__(self, path: Path, lines: dict[str, int]) -> None:
        self.path, self.lines, self.problems = path, lines, []

    def err(self, key: str, msg: str) -> None:
        line = self.lines.get(key)
        while line is None and "." in key:
            key_parent = key.rsplit(".", 1)[0]
            line = self.lines.get(key_parent)
            key = key_parent if line is None else key
        where = f"{self.path}:{line}" if line else str(self.path)
        self.problems.append(f"{where}: {msg}")

    def leaf(self, key: str, spec: dict, value: Any) -> Any:
        kind, bounds = spec["kind"], spec["bounds"]
        fallback = None if spec["default"] is REQUIRED else spec["default"]  # after an error
        if value is None and spec["default"] is REQUIRED:
            self.err(key, f"{key}: required ({spec['help']})")
            return None
        if value is None:
            if spec["default"] is None:
                return None
            value = spec["default"]  # defaults go through the same conversion (paths, floats)
        if kind in ("float", "optfloat"):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not _finite(value):
                self.err(key, f"{key} = {value!r}: must be a number")
                return fallback
            value = float(value)
        elif kind in ("int", "optint"):
            if isinstance(value, bool) or not isinstance(value, int):
                self.err(key, f"{key} = {value!r}: must be a whole number")
                return fallback
        elif kind in ("str", "path", "optpath"):
            if isinstance(value, (dict, list)) or isinstance(value, bool):
                self.err(key, f"{key} = {value!r}: must be a text value")
                return fallback
            value = str(value)
            if kind in ("path", "optpath"):
                try:
                    p = Path(value).expanduser()
                except RuntimeError:  # ~user of an unknown user
                    self.err(key, f"{key} = {value!r}: cannot expand the ~ (no such user's home)")
                    return fallback
                value = p if p.is_absolute() else (self.path.parent / p)
        elif kind == "bool":
            if not isinstance(value, bool):  # "false" in quotes is text, and text is truthy
                self.err(key, f"{key} = {value!r}: must be true or false")
                return fallback
        elif kind == "list":
            if not isinstance(value, list):
                self.err(key, f"{key}: must be a list")
                return fallback
        if bounds is not None and kind in ("float", "optfloat", "int", "optint"):
            lo, hi = bounds
            if not lo <= value <= hi:
                why = f" ({spec['why']})" if spec.get("why") else ""
                self.err(key, f"{key} = {value!r}: must be between {lo} and {hi}{why}")
        elif bounds is not None and kind == "str" and value not in bounds:
            self.err(key, f"{key} = {value!r}: must be one of {', '.join(bounds)}")
        return value

    def section(self, prefix: str, schema: dict, data: Any) -> dict:
        if data is None:
            data = {}
        if not isinstance(data, dict):
            self.err(prefix, f"{prefix or 'the file'}: must be a mapping of keys")
            data = {}
        out: dict[str, Any] = {}
        open_kind = schema.get("__open__")
        for k in data:
            if k not in schema and not (open_kind == "arm" and k in _ARM_PRESS_KEYS):
                known = sorted(s for s in schema if not s.startswith("__"))
                if open_kind == "arm":
                    known += sorted(_ARM_PRESS_KEYS)
                sub = f"{prefix}.{k}" if prefix else str(k)
                self.err(sub, f"{sub}: unknown key (known here: {', '.join(known)})")
        for k, spec in schema.items():
            if k.startswith("__"):
                continue
            sub = f"{prefix}.{k}" if prefix else k
            if isinstance(spec, dict) and spec.get("__leaf__"):
                out[k] = self.leaf(sub, spec, data.get(k))
            else:
                out[k] = self.section(sub, spec, data.get(k))
        if open_kind == "arm":
            out["__press__"] = {k: data[k] for k in data if k in _ARM_PRESS_KEYS}
        return out


def shared_bins(fabrics: list[SceneFabric], reject_bin: int) -> str:
    """Fabrics that share a bin while a bin of the gate (1..7) stays free, in words, or "": a
    copied line that merged two fabrics in one bin mis-sorts every piece of one of them. A job with
    more fabrics than the gate has bins must share (sim/scene.assign_bins): said nothing. The config
    does not know the gate: bins 1..7 of the gate's 8 (firmware_bridge's default) are assumed."""
    by_bin: dict[int, list[str]] = {}
    for f in fabrics:
        by_bin.setdefault(f.bin, []).append(f.name)
    shared = {b: names for b, names in sorted(by_bin.items()) if len(names) > 1}
    free = [b for b in range(1, 8) if b != reject_bin and b not in by_bin]
    if not shared or not free:
        return ""
    return "; ".join(f"{' and '.join(names)} share bin {b}" for b, names in shared.items()) + \
        f", while bin(s) {free} stay free"


def validate_config_dict(data: Any, lines: dict[str, int], path: Path) -> CellConfig:
    chk = _Checker(path, lines)
    for dup in lines.get("__dup__", []):  # type: ignore[union-attr]
        chk.err(dup, f"{dup}: given twice")
    v = chk.section("", _SCHEMA, data)

    # arm: press parameters are ArmConfig's, with its own bounds and cross-checks.
    arm_sec = v["devices"]["arm"]
    press = dict(arm_sec.pop("__press__", {}))
    arm_cfg = ArmConfig()
    try:
        arm_cfg = ArmConfig.from_dict({"host": arm_sec["host"], **press})
    except ArmConfigError as exc:
        msg = str(exc)
        bad = msg.split(" ", 1)[0].split("=")[0].strip().removeprefix("arm.").rstrip(":")
        chk.err(f"devices.arm.{bad}", f"devices.{msg}")
    except (TypeError, ValueError) as exc:
        chk.err("devices.arm", f"devices.arm: {exc}")

    # scene
    fabrics: list[SceneFabric] = []
    seen_names: set[str] = set()
    alike: dict[str, str] = {}  # name_key -> the first fabric spelled so: one fabric to a person, or to a label
    reject_bin = v["scene"]["reject_bin"]
    if reject_bin is not None and reject_bin != GATE_REJECT_BIN:
        # the gate moves its flap there by itself (the cell's to_reject on a fault or stop, its
        # heartbeat fail-safe, boot, clear): another reject bin would put those pieces in bin 0,
        # a fabric's bin perhaps, while the journal says reject_bin
        chk.err("scene.reject_bin", f"scene.reject_bin = {reject_bin}: the gate's own reject bin is "
                                    f"{GATE_REJECT_BIN} - it moves the flap there on every fault, fail-safe, "
                                    "boot and clear, and the cell's to_reject sends it there - so the reject "
                                    f"bin must be {GATE_REJECT_BIN}")
    for i, item in enumerate(v["scene"]["fabrics"] or []):
        key = f"scene.fabrics[{i}]"
        if not isinstance(item, dict):
            chk.err(key, f"{key}: must be a mapping with name, kind and bin")
            continue
        unknown = sorted(set(item) - {"name", "kind", "bin"})
        if unknown:
            chk.err(key, f"{key}: unknown key(s) {unknown} (known: name, kind, bin)")
        name, kind, bin_ = item.get("name"), item.get("kind"), item.get("bin")
        if not isinstance(name, str) or not name:
            chk.err(f"{key}.name", f"{key}.name: required, the fabric's class name in the bundle")
            continue
        if name in seen_names:
            chk.err(f"{key}.name", f"{key}.name = {name!r}: listed twice")
        elif name_key(name) in alike:
            # an operator's label names a fabric as typed (Unicode form, case, spaces set aside:
            # runtime/labels.py), so two such names would take each other's labels - pieces of one
            # taught into the other's bin
            chk.err(f"{key}.name", f"{key}.name = {name!r}: the same name to a person, or to an operator's label, "
                                   f"as {alike[name_key(name)]!r} (Unicode form, case, width, spaces, '-' and '_' "
                                   "set aside): give the fabrics names that differ")
        seen_names.add(name)
        alike.setdefault(name_key(name), name)
        if name == "unknown":
            chk.err(f"{key}.name", f"{key}.name: 'unknown' is reserved for undecided items")
        if name.startswith(OFF_SCENE_PREFIX):  # a stranger operator labels teach (runtime/feedback.py): reject bin
            chk.err(f"{key}.name", f"{key}.name = {name!r}: '{OFF_SCENE_PREFIX}' is reserved for strangers the "
                                   "operator labels off-scene, whose pieces go to the reject bin")
        if kind not in ("touched", "untouched"):
            chk.err(f"{key}.kind", f"{key}.kind = {kind!r}: must be touched or untouched")
        if isinstance(bin_, bool) or not isinstance(bin_, int) or not 0 <= bin_ <= 7:
            chk.err(f"{key}.bin", f"{key}.bin = {bin_!r}: must be a bin number 0..7")
            continue
        if bin_ == reject_bin:
            chk.err(f"{key}.bin", f"{key}.bin = {bin_}: that is the reject bin")
        fabrics.append(SceneFabric(name, str(kind), int(bin_)))
    if v["scene"]["fabrics"] is not None and not v["scene"]["fabrics"]:
        chk.err("scene.fabrics", "scene.fabrics: the scene needs at least one fabric")
    said = shared_bins(fabrics, reject_bin)
    if said and v["scene"]["shared_bins"] != "allow":
        # refused, not warned: every piece of one of them would go to the other's bin, and a start
        # log's warning is easy to miss (it was one until 2026-11-29)
        chk.err("scene.fabrics", f"scene.fabrics: {said} - one bin for two fabrics puts the pieces of one in "
                                 "the other's bin; give each its own bin, or set scene.shared_bins: allow if "
                                 "that is meant (or if the gate has fewer than 8 bins and the job must share them)")

    # evidence: which grid points, in which order
    ev = v["evidence"]
    n_points = N_GRID_X * N_GRID_Y
    if ev["grid_order"] == "list":
        pts = ev["grid_points"]
        if not pts:
            chk.err("evidence.grid_points", "evidence.grid_points: required when grid_order is list")
            pts = [0]
        bad = [p for p in pts if isinstance(p, bool) or not isinstance(p, int) or not 0 <= p < n_points]
        if bad:
            chk.err("evidence.grid_points", f"evidence.grid_points: {bad} are not grid indices 0..{n_points - 1}")
            pts = [0]
        if len(set(pts)) != len(pts):
            chk.err("evidence.grid_points", "evidence.grid_points: a point is listed twice")
        grid_points = tuple(int(p) for p in pts)
    else:
        if ev["grid_points"] is not None:
            chk.err("evidence.grid_points", "evidence.grid_points: only used with grid_order: list")
        grid_points = tuple(spread_order() if ev["grid_order"] == "spread" else range(n_points))
    if ev["max_presses"] > len(grid_points):
        chk.err("evidence.max_presses", f"evidence.max_presses = {ev['max_presses']}: more than the "
                                        f"{len(grid_points)} grid points listed")
    elif ev["extra_presses"] is not None and ev["max_presses"] + ev["extra_presses"] > len(grid_points):
        chk.err("evidence.extra_presses", f"evidence.extra_presses = {ev['extra_presses']}: with max_presses "
                                          f"{ev['max_presses']}, more presses than the {len(grid_points)} grid points listed")

    cam, gate = v["devices"]["camera"], v["devices"]["gate"]
    if cam["kind"] in ("replay", "sim") and cam["path"] is None:
        chk.err("devices.camera.path", f"devices.camera.path: required for camera kind {cam['kind']}")
    # every constraint the device drivers enforce, from the drivers' own functions: a config this
    # passes must not make a constructor refuse at `run` (a traceback, exit 1, restarted by systemd)
    if gate["kind"] == "serial" and gate["timeout_s"] is not None and gate["retries"] is not None:
        for problem in gate_timing_problems(gate["timeout_s"], gate["retries"]):
            chk.err("devices.gate.timeout_s", f"devices.gate.timeout_s = {gate['timeout_s']!r}, retries = "
                                              f"{gate['retries']!r}: the gate driver refuses them: {problem}")
        for problem in gate_move_problems(gate["timeout_s"]):  # the driver takes it; the live gate's flap does not
            chk.err("devices.gate.timeout_s", f"devices.gate.timeout_s = {gate['timeout_s']!r}: {problem}")
    if not chk.problems:  # the watchdog budget needs every number valid
        bounds = bounds_of(cam, arm_sec["kind"], arm_cfg, gate)
        for key, problem in watchdog_problems(bounds, v["watchdog"]["wait_item_timeout_s"]):
            chk.err(key, f"{key}: {problem}")
    if not chk.problems:  # the paths are paths only when every key is valid
        journal = v["journal"]
        fault_file = v["fault_file"] or journal.with_name("FAULT")
        _state_files_apart(chk, {"journal": journal, "fault_file": fault_file,
                                 "evidence.operator_labels": ev["operator_labels"],
                                 "beta_override_file": v["beta_override_file"]}, default_fault_file=v["fault_file"] is None)
    if chk.problems:
        raise ConfigError(path, chk.problems)
    return CellConfig(
        path=path, bundle=v["bundle"], beta_override=v["beta_override"],
        beta_override_file=v["beta_override_file"], threads=v["threads"], camera=cam,
        arm_kind=arm_sec["kind"], arm=arm_cfg, gate=gate, reject_bin=reject_bin, fabrics=tuple(fabrics),
        confidence=ev["confidence"], max_presses=ev["max_presses"], grid_order=ev["grid_order"],
        grid_points=grid_points, journal=journal,
        fault_file=fault_file,
        item_timeout_s=v["watchdog"]["item_timeout_s"],
        wait_item_timeout_s=v["watchdog"]["wait_item_timeout_s"],
        overlap_scoring=v["cell"]["overlap_scoring"], without_scene_model=ev["without_scene_model"],
        operator_labels=ev["operator_labels"], untouched_confidence=ev["untouched_confidence"],
        extra_presses=ev["extra_presses"], twin_ratio=ev["twin_ratio"], raw=data if isinstance(data, dict) else {},
    )


def _state_files_apart(chk: _Checker, files: dict[str, Path | None], default_fault_file: bool) -> None:
    """The journal, the fault file, the labels file and the beta override file (``files``, by key;
    None: not used) are four files: the fault latch writes and deletes its file whole, so a fault
    file that is the journal would replace every decision record with the fault's text (and
    clearing the fault would delete the journal)."""
    seen: dict[str, str] = {}
    for key, p in files.items():
        if p is None:
            continue
        where = os.path.normpath(os.path.abspath(p))
        if where in seen:
            default = " (the fault file's default: FAULT beside the journal)" if key == "fault_file" and \
                default_fault_file else ""
            chk.err(key, f"{key}: {p} is also the {seen[where]}{default}; each needs a file of its own - a fault "
                         "latch writes and deletes its file whole, and the journal must keep every record")
        else:
            seen[where] = key


def load_config(path: Path | str) -> CellConfig:
    """Read, check and return the config; a world-writable file is refused before it is parsed."""
    path = Path(path)
    try:
        text = _read_private(path)
    except OSError as exc:
        raise ConfigError(path, [f"{path}: cannot read ({exc.strerror or exc})"]) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(path, [f"{path}: not UTF-8 text (byte {exc.start}); a cell config is YAML text"]) from None
    data, lines = parse_yaml_with_lines(text, path)
    return validate_config_dict(data, lines, path)


def load_config_or_say(path: Path | str) -> CellConfig | None:
    """``load_config`` for a command: the config, or None after every problem went to stderr (the
    command then exits 2)."""
    try:
        return load_config(path)
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)
        return None


def _read_private(path: Path) -> str:
    """The file's text, refused when anyone on the machine may write it.

    The config names the bundle, the journal and the devices: a world-writable file would let any
    local user point the daemon at their own model or move the arm to their own points. The mode
    is checked on the open file descriptor (fstat), so the file cannot be swapped between the
    check and the read. Group-writable is allowed (an operators' group owning /etc/vs2t-edge).
    """
    # O_NONBLOCK: opening a FIFO for reading would otherwise wait for a writer, for ever
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        mode = st.st_mode
        if not stat.S_ISREG(mode):
            raise ConfigError(path, [f"{path}: not a regular file (a FIFO, device or folder); a cell config is "
                                     "a YAML file"])
        if st.st_size > MAX_CONFIG_BYTES:  # a 5 MB YAML took 73 s and 1.6 GB to reach its error
            raise ConfigError(path, [f"{path}: {st.st_size} bytes; a cell config is a few KB (at most "
                                     f"{MAX_CONFIG_BYTES})"])
        if mode & stat.S_IWOTH:
            raise ConfigError(path, [f"{path}: world-writable (mode {stat.S_IMODE(mode):o}): any local user "
                                     f"could change which bundle and journal the cell uses; fix with "
                                     f"`chmod o-w {path}`"])
        data = f.read(MAX_CONFIG_BYTES + 1)
        if len(data) > MAX_CONFIG_BYTES:  # grew after the fstat
            raise ConfigError(path, [f"{path}: more than {MAX_CONFIG_BYTES} bytes; a cell config is a few KB"])
        return data.decode("utf-8")


def schema_reference() -> list[tuple[str, str, str, str]]:
    """(key, default, bounds, help) for every key - docs/cell.md's table is checked against it."""
    rows: list[tuple[str, str, str, str]] = []

    def walk(prefix: str, schema: dict) -> None:
        for k, spec in schema.items():
            if k.startswith("__"):
                continue
            key = f"{prefix}.{k}" if prefix else k
            if spec.get("__leaf__"):
                default = "required" if spec["default"] is REQUIRED else repr(spec["default"])
                b = spec["bounds"]
                bounds = "" if b is None else (" | ".join(b) if spec["kind"] == "str" else f"{b[0]} .. {b[1]}")
                rows.append((key, default, bounds, spec["help"]))
            else:
                walk(key, spec)

    walk("", _SCHEMA)
    return rows

"""The simulated cell: a stream of fabric pieces, the loopback UR simulator, the gate MCU on a pty,
and a tactile camera fed from a dataset - wired to the same daemon the real cell runs.

* Items: a seeded sequence of the dataset's fabrics (scene fabrics, touched and untouched, and
  optionally off-scene ones that must go to the reject bin); the true fabric travels with the
  item for scoring the run, never to the loop's decision.
* Arm: ``URArm`` (the real ur_rtde client) against ``URSimProcess`` on a free 127.x address,
  or ``FakeArm`` for quick runs; wrapped in :class:`TrackingArm` so the camera knows where the
  gel is and whether it is pressed.
* Camera: ``SimulatedCamera`` whose frame is the item's no-contact reference frame while the
  gel is up, and the dataset press nearest to the arm's grid point while it is pressed.
* Gate: ``simulated_serial_gate()`` (the real host driver against the MCU simulator over a
  pty), or ``FakeGate``.
* Faults: ``schedule_fault(item_index, press_number, kind)`` injects a protective stop (in the
  UR simulator) or a camera fault at that press; ``operator_clear()`` is what the operator does.
"""

from __future__ import annotations

import json
import math
import random
import sys
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vs2t_edge.runtime.config import load_config
from vs2t_edge.runtime.dataset import Dataset, Fabric, load_dataset
from vs2t_edge.runtime.inference import TactileModel
from vs2t_edge.runtime.items import Item
from vs2t_edge.runtime.recording import record_session
from vs2t_edge.runtime.replay import SCORE_RTOL
from vs2t_edge.sim.fake_devices import PressTrackingArm


@dataclass(frozen=True)
class SimItem:
    id: str
    fabric_id: str
    truth: str  # the fabric's id: a bundle class (bundles name classes by dataset id), or an off-scene fabric


class SceneItems:
    """ItemSource over a fixed list; ``current`` is the piece under the gel (for the camera)."""

    def __init__(self, items: list[SimItem]) -> None:
        self.items = list(items)
        self.index = -1

    @property
    def current(self) -> SimItem | None:
        return self.items[self.index] if 0 <= self.index < len(self.items) else None

    def next_item(self, timeout_s: float) -> Item | None:
        if self.index + 1 >= len(self.items):
            return None
        self.index += 1
        it = self.items[self.index]
        return Item(it.id, it.truth)

    def exhausted(self) -> bool:
        return self.index + 1 >= len(self.items)


def item_stream(dataset: Dataset, names: list[str], n_items: int, seed: int = 0) -> list[SimItem]:
    """n_items pieces, cycling through ``names`` (fabric names or ids) in a seeded shuffle."""
    by_name = {f.name: f for f in dataset.fabrics} | {f.id: f for f in dataset.fabrics}
    missing = [n for n in names if n not in by_name]
    if missing:
        raise ValueError(f"dataset {dataset.root} has no fabric(s) {missing}")
    rng = random.Random(seed)
    order: list[str] = []
    while len(order) < n_items:
        batch = list(names)
        rng.shuffle(batch)
        order.extend(batch)
    return [SimItem(f"item-{i + 1:04d}", by_name[n].id, by_name[n].id) for i, n in enumerate(order[:n_items])]


@dataclass
class _Scheduled:
    item_index: int
    press_number: int  # 1-based press of that item
    kind: str  # protective_stop | camera_timeout | black_frame


class TrackingArm(PressTrackingArm):
    """An Arm proxy that remembers the target point and whether the gel is pressed; injects faults."""

    def __init__(self, inner, items: SceneItems, sim=None, camera=None) -> None:
        super().__init__(inner, lambda: items.index)
        self.items, self.sim, self.camera = items, sim, camera
        self.target: tuple[float, float] | None = None
        self.schedule: list[_Scheduled] = []

    def move_above(self, x_mm: float, y_mm: float) -> None:
        self.target = (x_mm, y_mm)
        super().move_above(x_mm, y_mm)

    def before_press(self, item: int, number: int) -> None:
        for s in list(self.schedule):
            if s.item_index == item and s.press_number == number:
                self.schedule.remove(s)
                self._inject(s.kind)

    def _inject(self, kind: str) -> None:
        if kind == "protective_stop":
            if self.sim is not None:
                self.sim.trigger_protective_stop()
            else:
                self.inner.fail_next.insert(0, "protective_stop")
        elif kind == "camera_timeout" and self.camera is not None:
            self.camera.inject("timeout", 1)
        elif kind == "black_frame" and self.camera is not None:
            self.camera.inject("black", 1)
        else:
            raise ValueError(f"cannot inject {kind!r} here")

    def operator_clear(self) -> bool:
        """What the operator does at the pendant: release the protective stop."""
        if self.sim is not None:
            self.sim.reset()
        clear = getattr(self.inner, "clear_protective_stop", None)
        if clear is not None:
            try:
                clear()
            except Exception:  # noqa: BLE001 - the cell's clear reconnects and reports
                pass
        return True


class DatasetFrames:
    """The frame under the gel: reference when up, nearest recorded press when pressed.

    Every piece is pressed at the same arm points, but each piece is another region of the cloth:
    a press shows the recorded press nearest to the point among those no earlier piece of that
    fabric showed (then among those this piece did not show, then any). Without it every piece of
    a fabric showed the same frames, so what one labelled piece taught the cell was tested on the
    very frames that taught it."""

    def __init__(self, dataset: Dataset, items: SceneItems, arm: TrackingArm, cache_size: int = 256,
                 allowed: dict[str, list[int]] | None = None) -> None:
        self.dataset, self.items, self.arm = dataset, items, arm
        # per fabric id, the recorded presses a piece may show (None: all); the demo keeps the
        # touched fabrics to presses no training step saw (runtime.dataset.press_partition)
        self.allowed = allowed or {}
        self._shown: dict[tuple, int] = {}  # (item id, arm point) -> recorded press shown
        self._seen: dict[str, set[int]] = {}  # fabric id -> presses shown to any piece of it so far
        self._cache: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self.cache_size = cache_size
        self._fallback: np.ndarray | None = None

    def _load(self, key: tuple, loader) -> np.ndarray:
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        image = loader()
        self._cache[key] = image
        if len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return image

    def nearest_press(self, fabric: Fabric, x_mm: float, y_mm: float, taken: set[int] = frozenset(),
                      seen: set[int] = frozenset()) -> int:
        """The recorded press nearest to the arm's point among the allowed ones no piece of the
        fabric showed yet (``seen``), else among those this piece did not show (``taken``), else
        any allowed one."""
        allowed = list(self.allowed.get(fabric.id) or range(len(fabric.presses)))
        ok = [i for i in allowed if i not in seen and i not in taken] or [i for i in allowed if i not in taken] \
            or allowed
        return min(ok, key=lambda i: (fabric.presses[i].x_mm - x_mm) ** 2 + (fabric.presses[i].y_mm - y_mm) ** 2)

    def __call__(self) -> np.ndarray:
        item = self.items.current
        fabric = self.dataset.by_id(item.fabric_id) if item else self.dataset.fabrics[0]
        if not self.arm.pressed or self.arm.target is None:
            return self._load((fabric.id, "ref"), fabric.load_reference)
        key = (item.id if item else "", tuple(self.arm.target))
        if key not in self._shown:  # one recorded press per point of a piece, never one press twice
            taken = {k for (it, _), k in self._shown.items() if it == key[0]}
            seen = self._seen.setdefault(fabric.id, set())
            self._shown[key] = self.nearest_press(fabric, *self.arm.target, taken=taken, seen=seen)
            seen.add(self._shown[key])
        k = self._shown[key]
        return self._load((fabric.id, k), lambda: fabric.load_press(k))


# Fast press settings for the simulated cell (the physics is simulated in real time; these keep
# a press near one second instead of two and a half, within the arm's documented bounds).
FAST_PRESS = {"approach_height_mm": 4.0, "travel_speed_m_s": 0.25, "travel_accel_m_s2": 1.5,
              "press_speed_m_s": 0.03, "settle_s": 0.05, "press_timeout_s": 4.0, "move_timeout_s": 6.0,
              "reconnect_backoff_s": 0.2}


def scene_config_yaml(*, bundle: Path, dataset: Path, journal: Path, fabrics: list[tuple[str, str, int]],
                      arm_host: str = "127.0.0.1", confidence: float = 0.95, max_presses: int = 5,
                      threads: int = 1, reject_bin: int = 0, extra_arm: dict | None = None) -> dict:
    return {
        "bundle": str(bundle), "threads": threads,
        "devices": {"camera": {"kind": "sim", "path": str(dataset)},
                    "arm": {"kind": "sim", "host": arm_host, **FAST_PRESS, **(extra_arm or {})},
                    "gate": {"kind": "sim"}},
        "scene": {"reject_bin": reject_bin,
                  "fabrics": [{"name": n, "kind": k, "bin": b} for n, k, b in fabrics]},
        "evidence": {"confidence": confidence, "max_presses": max_presses, "grid_order": "spread"},
        "journal": str(journal),
        "watchdog": {"item_timeout_s": 120.0, "wait_item_timeout_s": 0.05},
    }


def write_scene_config(path: Path, data: dict):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_config(path)


# The fault matrix's and the loop tests' scene: three fabrics in bins 1-3, wool never touched.
THREE_FABRICS = (("denim", "touched", 1), ("silk", "touched", 2), ("wool", "untouched", 3))


def fake_cell_yaml(*, fabrics=THREE_FABRICS, camera: dict | None = None, arm: dict | None = None,
                   gate: dict | None = None, bundle: str = "bundle", reject_bin: int = 0,
                   journal: str = "state/journal.jsonl", **sections) -> str:
    """The YAML of a cell config on fake devices, which the fault matrix and the tests write
    instead of pasting the same text (the pasted copies drifted apart). Devices default to a replay
    camera on ``frames`` and the fake arm and gate; ``fabrics`` are (name, kind, bin);
    ``sections`` adds top-level keys (threads, evidence, watchdog, fault_file, ...), each
    as its mapping. A key left out takes the config's own default (runtime/config.py)."""
    data = {"bundle": bundle, **({"threads": sections.pop("threads")} if "threads" in sections else {}),
            "devices": {"camera": camera or {"kind": "replay", "path": "frames"},
                        "arm": arm or {"kind": "fake"}, "gate": gate or {"kind": "fake"}},
            "scene": {"reject_bin": reject_bin,
                      "fabrics": [{"name": n, "kind": k, "bin": b} for n, k, b in fabrics]},
            **sections, "journal": journal}
    return yaml.safe_dump(data, sort_keys=False)


def assign_bins(touched: list[str], untouched: list[str], n_bins: int = 8, reject_bin: int = 0):
    """Scene fabrics -> bins 1..n-1 in turn (several fabrics may share a bin on a small gate)."""
    out = []
    bins = [b for b in range(n_bins) if b != reject_bin]
    for i, (name, kind) in enumerate([(n, "touched") for n in touched] + [(n, "untouched") for n in untouched]):
        out.append((name, kind, bins[i % len(bins)]))
    return out


@dataclass
class SimulatedCell:
    """Context manager: the simulated devices for one session (``arm``: "ursim" or "fake")."""

    dataset_root: Path
    items: list[SimItem]
    arm_kind: str = "ursim"
    gate_kind: str = "pty"
    camera_seed: int = 0
    press_settings: dict = field(default_factory=lambda: dict(FAST_PRESS))
    allowed_presses: dict | None = None  # fabric id -> press indices a piece may show (DatasetFrames)
    sim: Any = None
    camera: Any = None
    arm: Any = None
    gate: Any = None
    source: SceneItems | None = None

    def __enter__(self) -> "SimulatedCell":
        from vs2t_edge.runtime.arm import ArmConfig
        from vs2t_edge.sim.fake_devices import FakeArm, FakeGate
        from vs2t_edge.sim.devices import SimulatedCamera, simulated_serial_gate

        self.dataset = load_dataset(self.dataset_root)
        self.source = SceneItems(self.items)
        if self.arm_kind == "ursim":
            from vs2t_edge.runtime.arm_isolated import IsolatedURArm as URArm  # as the service runs it
            from vs2t_edge.sim.ursim import free_loopback_host
            from vs2t_edge.sim.ursim_model import PressScene
            from vs2t_edge.sim.ursim_process import URSimProcess

            scene = PressScene(home_pose=(0.42, -0.08, 0.110, 0.0, math.pi, 0.0))
            self.sim = URSimProcess(scene, host=free_loopback_host()).start()
            inner = URArm(ArmConfig(host=self.sim.host, **self.press_settings))
        else:
            inner = FakeArm(config=ArmConfig(**self.press_settings))
        self.arm = TrackingArm(inner, self.source, sim=self.sim)
        frames = DatasetFrames(self.dataset, self.source, self.arm, allowed=self.allowed_presses)
        g = self.dataset.geometry
        self.camera = SimulatedCamera(frames, noise_levels=1.0, seed=self.camera_seed,
                                      expected_hw=None)
        self.arm.camera = self.camera
        self.gate = simulated_serial_gate() if self.gate_kind == "pty" else FakeGate()
        self.frame_hw = g.frame_hw
        return self

    @property
    def arm_host(self) -> str:
        return self.sim.host if self.sim is not None else "127.0.0.1"

    def schedule_fault(self, item_index: int, press_number: int, kind: str) -> None:
        self.arm.schedule.append(_Scheduled(item_index, press_number, kind))

    def operator_clear(self) -> bool:
        return self.arm.operator_clear()

    def __exit__(self, *exc) -> None:
        for dev in (self.camera, self.arm, self.gate):
            try:
                if dev is not None:
                    dev.disconnect()
            except Exception:  # noqa: BLE001
                pass
        if self.sim is not None:
            self.sim.stop()


def score_run(results, items: list[SimItem], scene_names: set[str]) -> dict:
    """Accuracy as the demo reports it: a scene fabric must get its own label; an off-scene piece
    must go to the reject bin (label 'unknown' or anything not in the scene)."""
    truth = {it.id: it.truth for it in items}
    rows = []
    for r in results:
        t = truth.get(r.item.id)
        in_scene = t in scene_names
        correct = (r.label == t) if in_scene else (r.label not in scene_names)
        rows.append({"item": r.item.id, "truth": t, "label": r.label, "bin": r.bin, "outcome": r.outcome,
                     "presses": r.presses, "correct": bool(correct and r.outcome == "sorted"),
                     "latency_ms": float(np.mean(r.latency_ms)) if r.latency_ms else math.nan,
                     "item_s": r.item_s})
    n = len(rows)
    lat = [x for r in results for x in r.latency_ms]
    return {
        "items": n,
        "accuracy": sum(r["correct"] for r in rows) / n if n else math.nan,
        "presses_per_item": float(np.mean([r["presses"] for r in rows])) if n else math.nan,
        "latency_ms_median": float(np.median(lat)) if lat else math.nan,
        "latency_ms_p95": float(np.percentile(lat, 95)) if lat else math.nan,
        "item_s_median": float(np.median([r["item_s"] for r in rows])) if n else math.nan,
        "rows": rows,
    }


# --- the committed reference replays (tests/replays) ----------------------------------------

REFERENCE_SESSIONS = {
    # name: (which fabrics, n items, scheduled fault or None)
    "touched": ("touched", 3, None),
    "untouched": ("untouched", 3, None),
    "unknown": ("off_scene", 2, None),
    "fault": ("mixed", 3, (1, 2, "protective_stop")),
}


# The world the reference sessions are recorded in: the tiny profile's 10 fabrics and 3 x 3
# presses, at 64 x 48 px frames instead of 160 x 120. The replays carry every grabbed frame and
# tests/replays must stay under 3 MB with the bundle (whose 512-512 heads alone are 2.4 MB): a
# 160 x 120 press is ~33 KB of noisy PNG, a 64 x 48 one ~5 KB. The tiny trunk's input is 64 px
# either way.
REFERENCE_WORLD = {"n_fabrics": 10, "grid": (3, 3), "frame_px": (64, 48), "camera_px": 200}
REFERENCE_WORLD_PROFILE = "replay-tiny"


def make_reference_world(out: Path, seed: int = 0, progress: bool = True) -> Path:
    """Generate the reference sessions' fabric world (``REFERENCE_WORLD``) into ``out``."""
    from vs2t_edge.sim import synth

    # synth has no frame-size option; a named profile beside tiny/small/paper, recorded in the
    # dataset's provenance, keeps the world reproducible from this function alone.
    synth.PROFILES.setdefault(REFERENCE_WORLD_PROFILE, synth.SynthProfile(**REFERENCE_WORLD))
    # One process: the profile registered here is not in a spawned worker's table.
    return synth.generate(out, REFERENCE_WORLD_PROFILE, seed=seed, progress=progress, workers=1)


def record_reference_sessions(dataset: Path, bundle: Path, out_dir: Path, *, arm_kind: str = "ursim",
                              gate_kind: str = "pty", seed: int = 0, max_presses: int = 3,
                              confidence: float = 0.95, log=print) -> list[Path]:
    """Record the simulated-cell sessions the replay tests run (touched, untouched, off-scene
    pieces, and a protective stop mid-item cleared by the operator).

    The scene is the bundle's classes minus its last untouched class, which is kept off-scene:
    pieces of it must go to the reject bin whatever the model calls them. The item rule is the
    daemon's own for the config and the model (runtime/wiring.py), the one a replay runs again.
    """
    model = TactileModel.load(bundle, threads=1, beta_override=None)
    touched, untouched = list(model.touched), list(model.untouched)
    off_scene = [untouched.pop()] if len(untouched) > 1 else []
    ds = load_dataset(dataset)
    others = [f.id for f in ds.fabrics if f.id not in set(model.touched) | set(model.untouched)]
    off_scene += others[:1]
    groups = {"touched": touched, "untouched": untouched, "off_scene": off_scene or untouched,
              "mixed": touched[:1] + untouched[:1] + touched[1:2]}
    fabrics = assign_bins(touched, untouched)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for k, (name, (group, n_items, fault)) in enumerate(REFERENCE_SESSIONS.items()):
        items = item_stream(ds, groups[group], n_items, seed=seed + k)
        with SimulatedCell(dataset, items, arm_kind=arm_kind, gate_kind=gate_kind, camera_seed=seed + k) as cell:
            data = scene_config_yaml(bundle=Path(bundle).resolve(), dataset=Path(dataset).resolve(),
                                     journal=out_dir / "unused.jsonl", fabrics=fabrics, arm_host=cell.arm_host,
                                     confidence=confidence, max_presses=max_presses, threads=1)
            # Sequential scoring: a reference is a golden sequence of device calls, and overlapped
            # scoring makes a speculative press depend on the machine's timing (press_pipeline.py).
            data["cell"] = {"overlap_scoring": False}
            if model.scene_model is None:  # the committed test bundle decides with its router: the
                # references record that path on purpose (runtime/wiring.py evidence_factory_for)
                data["evidence"]["without_scene_model"] = "allow"
            # The recorded config names the bundle relatively: replays find it via --bundle or beside them.
            cfg = write_scene_config(out_dir / f".{name}.yaml", data)
            if fault is not None:
                cell.schedule_fault(*fault)
            path = record_session(cfg, out_dir / f"{name}.replay", model=model, camera=cell.camera, arm=cell.arm,
                                  gate=cell.gate, items=cell.source, operator_clear=cell.operator_clear,
                                  meta={"made_by": "python -m vs2t_edge.sim.scene record-references",
                                        "session": name, "seed": seed + k})
            (out_dir / f".{name}.yaml").unlink()
        _relative_paths(path)
        written.append(path)
        index = json.loads((path / "index.json").read_text())
        finals = [f"{d['label']}->{d['bin']}" for d in index["decisions"] if d["type"] == "final"]
        margins = ", ".join(f"{k} {v:.3g}" for k, v in decision_margins(index).items())
        log(f"recorded {path}: truth {[it['truth'] for it in index['items']]}, decided {finals}; "
            f"closest to flipping: {margins}")
    return written


def decision_margins(index: dict) -> dict:
    """How far a recorded session's decisions are from flipping, from its own reference decisions.

    For every scored press: the scene posterior after it against ``evidence.confidence`` (the stop
    and unknown rule), the gap between the two leading classes (the label), and the novelty
    against beta in log units (the press's touched/untouched route; absent when no press has a
    novelty: a format-3 bundle's press runs no router). A replay on another CPU
    differs in the last bits of a score; a margin well above the replay tolerance (1e-3) means
    that cannot change a decision.
    """
    confidence = float(index["config"].get("evidence", {}).get("confidence", 0.9))
    beta = index.get("meta", {}).get("beta")
    # The evidence uses the scene's classes only (an off-scene class never wins), renormalised.
    scene = [f["name"] for f in index["config"].get("scene", {}).get("fabrics", [])]
    out = {"confidence": math.inf, "label_gap": math.inf, "novelty_log_ratio": math.inf}
    routed = False  # a format-3 bundle's presses carry no router novelty: no route to flip
    for d in index["decisions"]:
        if d.get("type") != "pre_sort":
            continue
        acc = None
        for sc in d.get("scores", []):
            lp = sc.get("log_posterior")
            if isinstance(lp, dict) and all(c in lp for c in scene):
                v = np.array([float(lp[c]) for c in scene], dtype=np.float64)
                v = np.maximum(v - np.logaddexp.reduce(v), -1e300)
                acc = v if acc is None else acc + v
                post = np.exp(acc - np.logaddexp.reduce(acc))
                top = np.sort(post)[::-1]
                out["confidence"] = min(out["confidence"], abs(float(top[0]) - confidence))
                if len(top) > 1:
                    out["label_gap"] = min(out["label_gap"], float(top[0] - top[1]))
            nov = sc.get("novelty")
            routed = routed or nov is not None
            if beta and nov and nov > 0 and beta > 0:
                out["novelty_log_ratio"] = min(out["novelty_log_ratio"], abs(math.log(float(nov) / float(beta))))
    if not routed:
        del out["novelty_log_ratio"]
    return out


def _relative_paths(replay: Path) -> None:
    """No machine's absolute paths in a committed replay: the bundle and dataset are given at replay."""
    index_path = replay / "index.json"
    index = json.loads(index_path.read_text())
    index["config"]["bundle"] = "bundle"
    index["config"]["devices"]["camera"]["path"] = "dataset"
    index["config"]["journal"] = "journal.jsonl"
    index_path.write_text(json.dumps(index, indent=1, sort_keys=True) + "\n")


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m vs2t_edge.sim.scene")
    sub = ap.add_subparsers(dest="cmd", required=True)
    rr = sub.add_parser("record-references", help="record the replay tests' reference sessions")
    rr.add_argument("--dataset", required=True)
    rr.add_argument("--bundle", required=True)
    rr.add_argument("--out", default="tests/replays")
    rr.add_argument("--arm", choices=("ursim", "fake"), default="ursim")
    rr.add_argument("--seed", type=int, default=0, help="item order and camera noise seed (session k uses seed + k)")
    rw = sub.add_parser("reference-world", help="generate the reference sessions' small-frame fabric world")
    rw.add_argument("out", help="dataset folder to write (must not exist or be empty)")
    rw.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if a.cmd == "reference-world":
        make_reference_world(Path(a.out), seed=a.seed)
        print(f"reference world written to {a.out}")
        return 0
    written = record_reference_sessions(Path(a.dataset), Path(a.bundle), Path(a.out), arm_kind=a.arm, seed=a.seed)
    fragile = [p.stem for p in written
               if min(decision_margins(json.loads((p / "index.json").read_text())).values()) <= SCORE_RTOL]
    if fragile:
        # tests/test_replay_sessions.py refuses these: a CPU with other rounding could flip a decision.
        print(f"WARNING: {', '.join(fragile)}: a decision is within the replay tolerance ({SCORE_RTOL:g}) of "
              "flipping; re-record with another --seed", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

"""Run the whole daemon again from a replay file, and compare its decisions with the recorded ones.

A replay file is a folder ``NAME.replay/`` (format in docs/cell.md):

* ``index.json`` - format name and version, the cell config the session ran with (as a YAML
  mapping), the items in order (id, and the true fabric when known), every device event in
  order, and the reference decisions (the journal's decision records);
* ``frames/NNNNNN.png`` - every grabbed frame, PNG (lossless, so a replay scores the same
  pixels).

Reading the file - the bounds on what is read and the index's shape - is runtime/replay_file.py;
recording a session into one is runtime/recording.py.

Replaying gives the cell loop devices that answer from those logs (``ReplayArm`` raises the
recorded ``ArmSafetyStop`` at the same press, ``ReplayCamera`` returns the recorded frames), with
the operator's recorded fault clears played back, and runs the same daemon code
(runtime/daemon.run_daemon). Then :func:`compare` checks the new decisions against the
reference: exact on label, bin, outcome, presses and fault kinds, a tolerance on scores and
confidences, timestamps ignored. ``--update-refs`` rewrites the reference decisions from the new
run, never by hand.
"""

from __future__ import annotations

import json
import math
import tempfile
from collections import defaultdict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from vs2t_edge.runtime import devices as dv
from vs2t_edge.runtime.items import Item
from vs2t_edge.runtime.config import parse_yaml_with_lines, validate_config_dict
from vs2t_edge.runtime.bundle import SEAL_KEY, BundleError, read_manifest
from vs2t_edge.runtime.daemon import bundle_seal, run_daemon
from vs2t_edge.runtime.devices import Frame, PressResult
from vs2t_edge.runtime.labels import append_label, bound_piece
from vs2t_edge.runtime.preprocess import REDUCE_FACTORS
from vs2t_edge.runtime.journal import read_records
from vs2t_edge.runtime.notify import Notifier
from vs2t_edge.runtime.replay_file import (  # noqa: F401 - ReplayFile, ReplayError: callers import them from here
    ReplayError,
    ReplayFile,
    decisions_of,
    error_from_json,
    without_timing,
)

SCORE_RTOL, SCORE_ATOL = 1e-3, 1e-3  # onnxruntime thread counts and CPUs differ in the last bits


class ReplayDivergence(BaseException):
    """The replayed cell asked for something the recording does not have (it took another path).

    A BaseException, like KeyboardInterrupt: it ends the replay run, it is not a cell fault. As an
    Exception the cell loop would latch it as an internal fault and the replay would report a
    decision mismatch instead of saying where the paths parted."""


class _FileUnreadable(BaseException):
    """A recorded frame the replay may not read (refused, missing, outside the folder). It ends
    the run like a divergence, not as a cell fault - run_replay raises the ReplayError it carries,
    so the operator reads which file and why (exit 2), not a divergence it caused."""

    def __init__(self, error: ReplayError) -> None:
        super().__init__(str(error))
        self.error = error




# --- replay devices ------------------------------------------------------------------------

class _Queues:
    def __init__(self, rf: ReplayFile) -> None:
        self.rf = rf
        self.by: dict[tuple[int, str], deque] = defaultdict(deque)
        self.clears: dict[int, int] = defaultdict(int)  # operator clears after item i
        # Safety steps are called inside guards that must not fail (a fault latch, a stop), so they
        # are not answered from the queues (a divergence raised there would be swallowed or skip
        # the rest of the latch): each call is logged and the sequence compared after the run.
        steps = rf.index.get("safety_steps")  # None: recorded before safety steps were
        self.safety_recorded: list[tuple[int, str, str]] | None = (
            None if steps is None else [(st["item"], st["dev"], st["call"]) for st in steps])
        self.safety_called: list[tuple[int, str, str]] = []
        for ev in rf.index["events"]:
            if ev["dev"] == "operator":
                self.clears[ev["item"]] += 1
            else:
                self.by[(ev["item"], ev["dev"])].append(ev)
        self.item_index = -1

    def safety_call(self, dev: str, call: str) -> None:
        self.safety_called.append((self.item_index, dev, call))

    def safety_mismatches(self) -> list[str]:
        """The fault's safety steps the replay made against the recorded ones (exact, in order)."""
        if self.safety_recorded is None or self.safety_recorded == self.safety_called:
            return []
        rec, now = self.safety_recorded, self.safety_called
        i = next((k for k, (a, b) in enumerate(zip(rec, now)) if a != b), min(len(rec), len(now)))
        say = lambda seq: f"{seq[i][1]}.{seq[i][2]} at item {seq[i][0]}" if i < len(seq) else "nothing more"
        return [f"safety steps (arm.stop, gate.to_reject): {len(rec)} recorded, {len(now)} now; "
                f"call {i}: recorded {say(rec)}, now {say(now)}"]

    def pop(self, dev: str, call: str) -> dict:
        q = self.by[(self.item_index, dev)]
        if not q:
            raise ReplayDivergence(f"item {self.item_index}: the replayed cell called {dev}.{call} but the "
                                   f"recording has no more {dev} events for this item")
        ev = q.popleft()
        if ev["call"] != call:
            raise ReplayDivergence(f"item {self.item_index}: the replayed cell called {dev}.{call}, the "
                                   f"recording has {dev}.{ev['call']} here")
        return ev


class _ReplayBase:
    def __init__(self, queues: _Queues) -> None:
        self.q = queues
        self.connected = False

    def connect(self) -> None:
        self.connected = True

    def disconnect(self) -> None:
        self.connected = False

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.disconnect()


class ReplayCameraDevice(_ReplayBase):
    def grab(self) -> Frame:
        ev = self.q.pop("camera", "grab")
        if "error" in ev:
            raise error_from_json(ev["error"])
        if ev.get("frame") is None:
            raise dv.CameraError("recorded grab returned no image", device="camera", kind="corrupt")
        try:
            image = self.q.rf.load_frame(ev["frame"])
        except ReplayError as exc:
            raise _FileUnreadable(exc) from None
        scale = ev.get("reduced_by", 1)
        if type(scale) is not int or scale not in REDUCE_FACTORS:
            raise _FileUnreadable(ReplayError(f"camera grab of {ev['frame']}: reduced_by {scale!r}, not one of "
                                              f"{REDUCE_FACTORS}"))
        return Frame(image, float(ev.get("timestamp_s", 0.0)), int(ev.get("index", 0)), reduced_by=scale)


class ReplayArm(_ReplayBase):
    def _replay(self, call: str, args: tuple) -> Any:
        ev = self.q.pop("arm", call)
        if args and [round(float(a), 6) for a in args] != [round(float(a), 6) for a in ev.get("args", [])]:
            raise ReplayDivergence(f"item {self.q.item_index}: arm.{call}{args} but the recording has "
                                   f"{tuple(ev.get('args', []))}")
        if "error" in ev:
            raise error_from_json(ev["error"])
        return ev.get("result")

    def move_above(self, x_mm: float, y_mm: float) -> None:
        self._replay("move_above", (x_mm, y_mm))

    def press(self) -> PressResult:
        r = self._replay("press", ())
        return PressResult(x_mm=r["x_mm"], y_mm=r["y_mm"], force_n=r["force_n"], depth_mm=r["depth_mm"],
                           tcp_pose=tuple(r.get("tcp_pose", ())), telemetry=r.get("telemetry", {}))

    def retract(self) -> None:
        self._replay("retract", ())

    def stop(self) -> None:
        self.q.safety_call("arm", "stop")  # compared after the run (_Queues.safety_mismatches)

    def clear_protective_stop(self) -> None:
        pass


class ReplayGate(_ReplayBase):
    """Sorts and clears answer as recorded; to_reject is logged for the comparison and moves the
    flap to the configured reject bin; status is the simulated gate's."""

    def __init__(self, queues: _Queues, reject_bin: int = 0) -> None:
        super().__init__(queues)
        self.sorted: list[int] = []
        self.reject_bin = reject_bin
        self.bin = reject_bin

    def sort(self, bin_index: int) -> None:
        ev = self.q.pop("gate", "sort")
        if ev.get("args") != [bin_index]:
            raise ReplayDivergence(f"item {self.q.item_index}: gate.sort({bin_index}) but the recording sorted "
                                   f"to {ev.get('args')}")
        if "error" in ev:
            raise error_from_json(ev["error"])
        self.sorted.append(bin_index)
        self.bin = bin_index

    def clear(self) -> None:
        ev = self.q.pop("gate", "clear")
        if "error" in ev:
            raise error_from_json(ev["error"])

    def to_reject(self) -> None:
        self.q.safety_call("gate", "to_reject")
        self.bin = self.reject_bin

    def status(self) -> dv.GateStatus:
        return dv.GateStatus(state="ready", bin=self.bin)


class ReplayItems:
    """The recorded pieces in order; with ``labels`` (the replay's labels file), the operator
    labels the session read before a piece are written there as that piece is handed out, so the
    cell reads them at the same point (runtime/labels.py)."""

    def __init__(self, queues: _Queues, labels: Path | None = None) -> None:
        self.q = queues
        self.items = [Item(d["id"], d.get("truth")) for d in queues.rf.index["items"]]
        self.labels_path = labels
        self.labels = list(queues.rf.index.get("labels") or []) if labels is not None else []

    def next_item(self, timeout_s: float):
        if self.q.item_index + 1 >= len(self.items):
            return None
        self.q.item_index += 1
        item = self.items[self.q.item_index]
        for rec in [r for r in self.labels if isinstance(r, dict) and r.get("before_item") == item.id]:
            append_label(self.labels_path, str(rec.get("item_id")),
                         None if rec.get("retract") else str(rec.get("fabric")), bool(rec.get("off_scene")),
                         bound_piece(rec))  # bound to the presses the label verb saw (runtime/labels.py)
        return item

    def exhausted(self) -> bool:
        return self.q.item_index + 1 >= len(self.items)


# --- comparing -----------------------------------------------------------------------------

EXACT_KEYS = ("type", "item", "item_id", "label", "bin", "outcome", "presses", "skipped_frames", "stopped_by",
              "kind", "reason", "point", "step")


# A press score's router numbers: a format-3 bundle (runtime/bundle.py is_split) decides with its
# scene model and never computes them, so a session recorded with the format-2 export of the same
# run replays with them on one side only; where both sides have them they are compared as before.
ROUTER_SCORE_KEYS = frozenset({"novelty", "untouched"})


def _close(a: Any, b: Any, path: str, out: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) ^ set(b) and set(a) ^ set(b) <= ROUTER_SCORE_KEYS and "log_posterior" in a:
            a, b = ({k: v for k, v in d.items() if k not in ROUTER_SCORE_KEYS} for d in (a, b))
        if set(a) != set(b):
            out.append(f"{path}: keys {sorted(set(a) ^ set(b))} differ")
            return
        for k in a:
            _close(a[k], b[k], f"{path}.{k}", out)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(f"{path}: {len(a)} entries recorded, {len(b)} now")
            return
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{path}[{i}]", out)
    elif isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        if a is None or b is None or not math.isclose(float(a), float(b), rel_tol=SCORE_RTOL, abs_tol=SCORE_ATOL):
            out.append(f"{path}: recorded {a}, now {b}")
    elif a != b:
        out.append(f"{path}: recorded {a!r}, now {b!r}")


def compare(reference: list[dict], new: list[dict]) -> list[str]:
    """Mismatches between two decision lists; [] when the replay reproduced the recording."""
    problems: list[str] = []
    if len(reference) != len(new):
        problems.append(f"{len(reference)} decision records recorded, {len(new)} now: "
                        f"{[r['type'] for r in reference]} vs {[r['type'] for r in new]}")
    reference, new = without_timing(reference), without_timing(new)  # files recorded before timings were dropped
    for i, (a, b) in enumerate(zip(reference, new)):
        where = f"record {i} ({a.get('type')} item {a.get('item')})"
        for k in EXACT_KEYS:
            if a.get(k) != b.get(k):
                problems.append(f"{where}: {k} recorded {a.get(k)!r}, now {b.get(k)!r}")
        rest_a = {k: v for k, v in a.items() if k not in EXACT_KEYS}
        rest_b = {k: v for k, v in b.items() if k not in EXACT_KEYS}
        _close(rest_a, rest_b, where, problems)
    return problems


@dataclass
class ReplayReport:
    file: Path
    items: int
    mismatches: list[str] = field(default_factory=list)
    decisions: list[dict] = field(default_factory=list)
    diverged: str = ""

    @property
    def ok(self) -> bool:
        return not self.mismatches and not self.diverged


def config_for_replay(rf: ReplayFile, workdir: Path, bundle: Path | None):
    """The recorded config with the bundle swapped in and the journal in a scratch folder."""
    raw = json.loads(json.dumps(rf.index["config"]))
    if bundle is not None:
        raw["bundle"] = str(Path(bundle).resolve())
    raw["journal"] = str(workdir / "journal.jsonl")
    raw.pop("fault_file", None)
    raw.pop("beta_override_file", None)
    # The replayed devices answer at once, so an overlapped score is never ready when the gel is
    # up and the arm would press on where the recording stopped. The decisions do not depend on
    # it (runtime/press_pipeline.py); the device calls would.
    raw.setdefault("cell", {})
    if isinstance(raw["cell"], dict):
        raw["cell"]["overlap_scoring"] = False
    # A session that ran a bundle without a scene model either opted in (evidence.without_scene_model)
    # or was recorded before the daemon refused such bundles; its replay sorts nothing and must reproduce
    # it, so the replay allows it, as it pins beta below. Which bundle it replays with is checked by seal.
    if not isinstance(raw.get("evidence"), dict):
        raw["evidence"] = {}
    raw["evidence"]["without_scene_model"] = "allow"
    if raw["evidence"].get("operator_labels"):  # the session's labels, handed over as it read them
        raw["evidence"]["operator_labels"] = str(workdir / "labels.jsonl")
    beta = rf.index.get("meta", {}).get("beta")
    if beta is not None:
        raw["beta_override"] = float(beta)
    text = yaml.safe_dump(raw)
    path = workdir / "replay-config.yaml"
    path.write_text(text)
    data, lines = parse_yaml_with_lines(text, path)
    return validate_config_dict(data, lines, path)


def recorded_bundle(rf: ReplayFile) -> Path:
    """The bundle a replay names: absolute as recorded, or relative - inside the replay folder
    or beside it (tests/replays/bundle next to tests/replays/*.replay)."""
    rec = Path(str(rf.index["config"].get("bundle", "")))
    if rec.is_absolute():
        return rec
    tried = [rf.folder / rec, rf.folder.parent / rec]
    for candidate in tried:
        if candidate.is_dir():
            return candidate
    raise ReplayError(f"{rf.folder}: the recorded bundle {str(rec)!r} is at neither {tried[0]} nor {tried[1]}; "
                      "give --bundle")


def check_same_bundle(rf: ReplayFile, bundle: Path | None, model=None) -> None:
    """Refuse (ReplayError) to replay a session against another bundle than the one it ran: its
    recorded seal (``meta.manifest_sha256``, from the session's start record) against the seal of
    ``model`` or of the bundle folder. A session recorded before seals were, a model that names no
    seal, or a bundle whose manifest cannot be read (the daemon refuses that one itself) is not judged."""
    recorded = rf.index.get("meta", {}).get(SEAL_KEY)
    if not isinstance(recorded, str) or not recorded:
        return
    if model is not None:
        now = bundle_seal(model)
    else:
        try:
            now = read_manifest(bundle).get(SEAL_KEY)
        except (BundleError, OSError, ValueError):
            return
    if isinstance(now, str) and now and now != recorded:
        ran = rf.index.get("config", {}).get("bundle")
        raise ReplayError(f"{rf.folder}: replaying against another bundle than the session ran: it ran {ran} "
                          f"sealed {SEAL_KEY} {recorded[:12]}..., the replay's bundle {bundle or 'given'} is sealed "
                          f"{now[:12]}... - its decisions would say nothing about the session. Give the bundle it "
                          "ran (--bundle), or --allow-other-bundle to compare against this one anyway")


def run_replay(file: Path | str, *, model=None, bundle: Path | None = None, evidence_factory=None,
               update_refs: bool = False, allow_other_bundle: bool = False) -> ReplayReport:
    """Run the daemon from a replay file and compare its decisions with the recorded ones. A
    session that recorded its bundle's seal replays only against that bundle, unless
    ``allow_other_bundle`` (:func:`check_same_bundle`)."""
    rf = ReplayFile.open(file)
    with tempfile.TemporaryDirectory(prefix="vs2t-replay-") as tmp:
        work = Path(tmp)
        if bundle is None and model is None:
            bundle = recorded_bundle(rf)
        if not allow_other_bundle:
            check_same_bundle(rf, bundle, model)
        cfg = config_for_replay(rf, work, bundle)
        queues = _Queues(rf)
        items = ReplayItems(queues, labels=cfg.operator_labels)
        clears = dict(queues.clears)
        fault_file = cfg.fault_file

        def stop_when() -> bool:
            # The operator's recorded clears, played back at the same point of the session.
            if fault_file.exists():
                if clears.get(queues.item_index, 0) > 0:
                    clears[queues.item_index] -= 1
                    fault_file.unlink()
                    return False
                return True  # latched and never cleared in the recording: the session ended here
            return items.exhausted()

        diverged = ""
        said: list[str] = []  # the daemon's log, kept to say why it refused to start
        try:
            code = run_daemon(cfg, model=model, camera=ReplayCameraDevice(queues), arm=ReplayArm(queues),
                              gate=ReplayGate(queues, cfg.reject_bin), items=items, evidence_factory=evidence_factory,
                              notifier=Notifier(address=""), stop_when=stop_when, install_signals=False,
                              log=said.append)
            if code != 0:
                why = "; ".join(str(m) for m in said[-3:])
                diverged = f"the daemon exited with {code} (bundle or config refused){': ' + why if why else ''}"
        except ReplayDivergence as exc:
            diverged = str(exc)
        except _FileUnreadable as exc:
            raise exc.error from None
        new = decisions_of(read_records(cfg.journal)) if cfg.journal.exists() else []
    safety = [] if diverged else queues.safety_mismatches()
    if update_refs and safety:
        # the recorded device events are not references: --update-refs cannot accept other calls
        diverged = safety[0] + " - the recording is stale for this code; re-record it"
    report = ReplayReport(Path(file), len(rf.index["items"]), decisions=new, diverged=diverged)
    if update_refs and not diverged:
        rf.save_decisions(new)
    elif not diverged:
        report.mismatches = compare(rf.index["decisions"], new) + safety
    return report



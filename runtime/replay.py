"""Record a cell session into a replay file, and run the whole daemon again from it.

A replay file is a folder ``NAME.replay/`` (format in docs/cell.md):

* ``index.json`` - format name and version, the cell config the session ran with (as a YAML
  mapping), the items in order (id, and the true fabric when known), every device event in
  order, and the reference decisions (the journal's decision records);
* ``frames/NNNNNN.png`` - every grabbed frame, PNG (lossless, so a replay scores the same
  pixels).

Recording wraps the session's camera, arm, gate and item source in proxies that log each call
with its result or its typed error (``RecordingCamera`` ...), tagged with the item in hand.
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
import re
import shutil
import tempfile
import threading
import time
from collections import defaultdict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from vs2t_edge.runtime import devices as dv
from vs2t_edge.runtime.cell import Item
from vs2t_edge.runtime.devices import Frame, PressResult
from vs2t_edge.runtime.files import MAX_REPLAY_INDEX_BYTES, InputRefused, inside, read_image_file, read_regular_file

FORMAT = "vs2t-edge-replay"
VERSION = 1
# The safety steps of a fault, a stop and a start. Kept in their own list ``safety_steps``, not in
# ``events``: they are called inside guards that must not fail, so the replay devices do not answer
# them from the event queues (a divergence raised there would cut the latch short); the replay
# logs each call and compares the sequence after the run. A file recorded before they were
# (no ``safety_steps`` key) replays as before, its safety steps not compared.
SAFETY_CALLS = frozenset({("arm", "stop"), ("gate", "to_reject")})
DECISION_TYPES = ("pre_sort", "final", "fault", "fault_cleared", "frame_skipped", "retry")
SCORE_RTOL, SCORE_ATOL = 1e-3, 1e-3  # onnxruntime thread counts and CPUs differ in the last bits

_ERRORS = {cls.__name__: cls for cls in (dv.CameraError, dv.ArmConnectionError, dv.ArmSafetyStop, dv.PressFailed,
                                         dv.ArmError, dv.GateError, dv.DeviceError, dv.NotConnectedError)}


class ReplayError(ValueError):
    """A replay file that cannot be read, named with what is wrong."""


class ReplayDivergence(BaseException):
    """The replayed cell asked for something the recording does not have (it took another path).

    A BaseException, like KeyboardInterrupt: it ends the replay run, it is not a cell fault. As an
    Exception the cell loop would latch it as an internal fault and the replay would report a
    decision mismatch instead of saying where the paths parted."""


def _error_to_json(exc: dv.DeviceError) -> dict:
    return {"type": type(exc).__name__, "message": str(exc), "kind": exc.kind, "device": exc.device,
            "retryable": bool(exc.retryable)}


def _error_from_json(d: dict) -> dv.DeviceError:
    cls = _ERRORS.get(d["type"], dv.DeviceError)
    exc = cls(d["message"], device=d.get("device", ""), kind=d.get("kind", ""))
    if exc.retryable != d.get("retryable", exc.retryable):
        exc.retryable = d["retryable"]
    return exc


# --- recording -----------------------------------------------------------------------------

class Recorder:
    """Collects events and frames; ``save(folder, config_dict, journal_records)`` writes the file."""

    def __init__(self) -> None:
        self.events: list[dict] = []
        self.frames: list[bytes] = []
        self.items: list[dict] = []
        self.safety_steps: list[dict] = []  # arm.stop / gate.to_reject calls, in order (SAFETY_CALLS)
        self.item_index = -1  # index into items of the piece in hand
        self._lock = threading.Lock()

    def event(self, dev: str, call: str, **fields) -> dict:
        with self._lock:
            ev = {"item": self.item_index, "dev": dev, "call": call, **fields}
            self.events.append(ev)
            return ev

    def safety_step(self, dev: str, call: str, **fields) -> None:
        with self._lock:
            self.safety_steps.append({"item": self.item_index, "dev": dev, "call": call, **fields})

    def add_frame(self, image: np.ndarray) -> str:
        ok, buf = cv2.imencode(".png", image)
        if not ok:
            raise ReplayError("could not PNG-encode a frame")
        with self._lock:
            self.frames.append(buf.tobytes())
            return f"frames/{len(self.frames):06d}.png"

    def save(self, folder: Path, config: dict, journal_records: list[dict], meta: dict | None = None) -> Path:
        folder = Path(folder)
        tmp = folder.with_name(folder.name + ".partial")
        if tmp.exists():
            shutil.rmtree(tmp)
        (tmp / "frames").mkdir(parents=True)
        for i, data in enumerate(self.frames, 1):
            (tmp / "frames" / f"{i:06d}.png").write_bytes(data)
        index = {"format": FORMAT, "version": VERSION, "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                 "meta": meta or {}, "config": config, "items": self.items, "events": self.events,
                 "safety_steps": self.safety_steps,
                 "decisions": decisions_of(journal_records)}
        (tmp / "index.json").write_text(json.dumps(index, indent=1, sort_keys=True) + "\n")
        if folder.exists():
            shutil.rmtree(folder)
        tmp.rename(folder)
        return folder


class RecordingCamera:
    def __init__(self, inner, rec: Recorder) -> None:
        self.inner, self.rec = inner, rec

    def connect(self) -> None:
        self.inner.connect()

    def disconnect(self) -> None:
        self.inner.disconnect()

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.disconnect()

    def grab(self) -> Frame:
        try:
            frame = self.inner.grab()
        except dv.DeviceError as exc:
            self.rec.event("camera", "grab", error=_error_to_json(exc))
            raise
        name = self.rec.add_frame(frame.image) if isinstance(frame.image, np.ndarray) and frame.image.ndim == 3 \
            and frame.image.dtype == np.uint8 else None
        self.rec.event("camera", "grab", frame=name, timestamp_s=frame.timestamp_s, index=frame.index)
        return frame


class _RecordingDevice:
    DEV = ""
    RECORDED: tuple[str, ...] = ()

    def __init__(self, inner, rec: Recorder) -> None:
        self.inner, self.rec = inner, rec

    def __getattr__(self, name):
        attr = getattr(self.inner, name)
        if (self.DEV, name) in SAFETY_CALLS and callable(attr):
            def safety(*args):
                try:
                    result = attr(*args)
                except Exception as exc:  # noqa: BLE001 - recorded, then raised as the device did
                    self.rec.safety_step(self.DEV, name, error=f"{type(exc).__name__}: {exc}")
                    raise
                self.rec.safety_step(self.DEV, name)
                return result

            return safety
        if name not in self.RECORDED or not callable(attr):
            return attr

        def call(*args):
            try:
                result = attr(*args)
            except dv.DeviceError as exc:
                self.rec.event(self.DEV, name, args=list(args), error=_error_to_json(exc))
                raise
            self.rec.event(self.DEV, name, args=list(args), result=_result_json(result))
            return result

        return call

    def __enter__(self):
        self.inner.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.inner.disconnect()


def _result_json(result: Any) -> Any:
    if isinstance(result, PressResult):
        return {"x_mm": result.x_mm, "y_mm": result.y_mm, "force_n": result.force_n, "depth_mm": result.depth_mm,
                "tcp_pose": list(result.tcp_pose), "telemetry": _plain(result.telemetry)}
    return None


def _plain(x: Any) -> Any:
    try:
        return json.loads(json.dumps(x, default=str))
    except (TypeError, ValueError):
        return str(x)


class RecordingArm(_RecordingDevice):
    DEV = "arm"
    RECORDED = ("move_above", "press", "retract")  # and stop, into safety_steps (SAFETY_CALLS)


class RecordingGate(_RecordingDevice):
    DEV = "gate"
    RECORDED = ("sort", "clear")  # and to_reject, into safety_steps (SAFETY_CALLS)


class RecordingItems:
    def __init__(self, inner, rec: Recorder) -> None:
        self.inner, self.rec = inner, rec

    def next_item(self, timeout_s: float):
        item = self.inner.next_item(timeout_s)
        if item is not None:
            self.rec.items.append({"id": item.id, "truth": item.truth})
            self.rec.item_index = len(self.rec.items) - 1
        return item

    def __getattr__(self, name):
        return getattr(self.inner, name)


# Measurements of the machine, not decisions: wall-clock stamps and the model's time per press
# (1.9 ms when recorded beside a UR simulator, 0.6 ms replayed alone). Dropped from reference
# decisions at any depth and never compared.
TIMING_KEYS = frozenset({"t", "latency_ms", "timestamp_s", "load_s", "item_s"})


def _without_timing(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _without_timing(v) for k, v in x.items() if k not in TIMING_KEYS}
    if isinstance(x, list):
        return [_without_timing(v) for v in x]
    return x


def decisions_of(records: list[dict]) -> list[dict]:
    """The journal records a replay compares, timestamps and timings dropped."""
    out = []
    for r in records:
        if r.get("type") in DECISION_TYPES:
            out.append(_without_timing({k: v for k, v in r.items() if k != "steps_failed"}))
    return out


# --- the replay file -----------------------------------------------------------------------

@dataclass
class ReplayFile:
    folder: Path
    index: dict

    @classmethod
    def open(cls, folder: Path | str) -> "ReplayFile":
        folder = Path(folder)
        path = folder / "index.json"
        if not path.is_file():
            raise ReplayError(f"{folder}: not a replay file (no index.json)")
        if not inside(folder, path):
            raise ReplayError(f"{path}: a link to outside the replay folder; nothing outside it is read")
        try:
            index = json.loads(read_regular_file(path, MAX_REPLAY_INDEX_BYTES, "replay index"))
        except InputRefused as exc:
            raise ReplayError(str(exc)) from None
        except OSError as exc:
            raise ReplayError(f"{path}: cannot be read ({exc.strerror or exc})") from None
        except RecursionError:
            raise ReplayError(f"{path}: nested too deeply to be a replay index") from None
        except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, integers past 4300 digits
            raise ReplayError(f"{path}: not valid JSON ({str(exc)[:200]})") from None
        if not isinstance(index, dict):
            raise ReplayError(f"{path}: must be a JSON object")
        if index.get("format") != FORMAT:
            raise ReplayError(f"{path}: format {index.get('format')!r}, expected {FORMAT!r}")
        if index.get("version") != VERSION or isinstance(index.get("version"), bool):
            raise ReplayError(f"{path}: version {str(index.get('version'))[:40]}, this build reads {VERSION}")
        _check_index(index, path)
        return cls(folder, index)

    def load_frame(self, name: str) -> np.ndarray:
        """The frame as stored (the frame check refuses a grey, RGBA or 16-bit one). Refused
        before reading: a frame whose path, links resolved, leaves the replay folder (the index
        names only ``frames/NNNNNN.png``, and a link must not widen that), a FIFO (it would block
        the read forever) and an image over the size caps (before it is decoded)."""
        path = self.folder / name
        if not inside(self.folder, path):
            raise ReplayError(f"{path}: a link to outside the replay folder; nothing outside it is read")
        try:
            return read_image_file(path)
        except InputRefused as exc:
            raise ReplayError(f"{path}: frame refused: {str(exc).split(': ', 1)[-1]}") from None
        except OSError as exc:
            raise ReplayError(f"{path}: frame missing or unreadable ({exc.strerror or exc})") from None

    def frames_by_item(self):
        """(reference frame, pressed frames) per item: the first grab of an item is its reference."""
        grabs: dict[int, list[str]] = defaultdict(list)
        for ev in self.index["events"]:
            if ev["dev"] == "camera" and ev.get("frame"):
                grabs[ev["item"]].append(ev["frame"])
        for item in sorted(grabs):
            names = grabs[item]
            yield self.load_frame(names[0]), [self.load_frame(n) for n in names[1:]]

    def save_decisions(self, decisions: list[dict]) -> None:
        self.index["decisions"] = decisions
        tmp = self.folder / "index.json.tmp"
        tmp.write_text(json.dumps(self.index, indent=1, sort_keys=True) + "\n")
        tmp.replace(self.folder / "index.json")


_FRAME_NAME = re.compile(r"^frames/[0-9]{6}\.png$")  # nothing outside the replay folder is ever read


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check_index(index: Any, path: Path) -> None:
    """Shape of every part the replay reads; a ReplayError naming the first bad entry."""
    if not isinstance(index, dict):
        raise ReplayError(f"{path}: must be a JSON object")
    for key, typ in (("config", dict), ("items", list), ("events", list), ("decisions", list)):
        if not isinstance(index.get(key), typ):
            raise ReplayError(f"{path}: {key!r} missing or not a {typ.__name__}")
    if not isinstance(index.get("meta", {}), dict):
        raise ReplayError(f"{path}: 'meta' must be an object")
    beta = index.get("meta", {}).get("beta")
    if beta is not None and not (_number(beta) and not math.isnan(beta)):  # replayed as beta_override
        raise ReplayError(f"{path}: meta.beta {str(beta)[:40]!r} is not a number")
    if not isinstance(index["config"].get("bundle", ""), str):
        raise ReplayError(f"{path}: config.bundle must be a folder name (text)")
    for i, it in enumerate(index["items"]):
        if not isinstance(it, dict) or not isinstance(it.get("id"), str):
            raise ReplayError(f"{path}: items[{i}] needs an 'id' text")
    for i, ev in enumerate(index["events"]):
        if not (isinstance(ev, dict) and isinstance(ev.get("dev"), str) and isinstance(ev.get("call"), str)
                and isinstance(ev.get("item"), int) and not isinstance(ev.get("item"), bool)):
            raise ReplayError(f"{path}: events[{i}] needs dev, call (text) and item (number)")
        frame = ev.get("frame")
        if frame is not None and (not isinstance(frame, str) or not _FRAME_NAME.match(frame)):
            raise ReplayError(f"{path}: events[{i}].frame {str(frame)[:60]!r} is not frames/NNNNNN.png")
        if "error" in ev and not (isinstance(ev["error"], dict) and isinstance(ev["error"].get("message"), str)
                                  and isinstance(ev["error"].get("type"), str)
                                  and all(isinstance(ev["error"].get(k, ""), str) for k in ("kind", "device"))):
            raise ReplayError(f"{path}: events[{i}].error needs type and message (and text kind, device)")
        # a replayed grab's Frame is built from these: float(timestamp_s), int(index)
        if "timestamp_s" in ev and not _number(ev["timestamp_s"]):
            raise ReplayError(f"{path}: events[{i}].timestamp_s {str(ev['timestamp_s'])[:40]!r} is not a number")
        if "index" in ev and not (isinstance(ev["index"], int) and not isinstance(ev["index"], bool)):
            raise ReplayError(f"{path}: events[{i}].index {str(ev['index'])[:40]!r} is not a whole number")
        if "args" in ev and not (isinstance(ev["args"], list)
                                 and all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in ev["args"])):
            raise ReplayError(f"{path}: events[{i}].args must be a list of numbers")
        if ev["call"] == "press" and "error" not in ev:
            r = ev.get("result")
            if not (isinstance(r, dict) and all(_number(r.get(k)) for k in ("x_mm", "y_mm", "force_n", "depth_mm"))):
                raise ReplayError(f"{path}: events[{i}] press result needs x_mm, y_mm, force_n, depth_mm")
            if not (isinstance(r.get("tcp_pose", []), list) and all(_number(v) for v in r.get("tcp_pose", []))
                    and isinstance(r.get("telemetry", {}), dict)):
                raise ReplayError(f"{path}: events[{i}] press result: tcp_pose must be numbers, telemetry an object")
    steps = index.get("safety_steps", [])
    if not isinstance(steps, list):
        raise ReplayError(f"{path}: 'safety_steps' must be a list")
    for i, st in enumerate(steps):
        if not (isinstance(st, dict) and isinstance(st.get("item"), int) and not isinstance(st.get("item"), bool)
                and isinstance(st.get("dev"), str) and isinstance(st.get("call"), str)
                and (st["dev"], st["call"]) in SAFETY_CALLS):
            raise ReplayError(f"{path}: safety_steps[{i}] needs item (number) and dev/call arm/stop or gate/to_reject")
    for i, d in enumerate(index["decisions"]):
        if not isinstance(d, dict) or not isinstance(d.get("type"), str):
            raise ReplayError(f"{path}: decisions[{i}] needs a 'type'")


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
            raise _error_from_json(ev["error"])
        if ev.get("frame") is None:
            raise dv.CameraError("recorded grab returned no image", device="camera", kind="corrupt")
        return Frame(self.q.rf.load_frame(ev["frame"]), float(ev.get("timestamp_s", 0.0)), int(ev.get("index", 0)))


class ReplayArm(_ReplayBase):
    def _replay(self, call: str, args: tuple) -> Any:
        ev = self.q.pop("arm", call)
        if args and [round(float(a), 6) for a in args] != [round(float(a), 6) for a in ev.get("args", [])]:
            raise ReplayDivergence(f"item {self.q.item_index}: arm.{call}{args} but the recording has "
                                   f"{tuple(ev.get('args', []))}")
        if "error" in ev:
            raise _error_from_json(ev["error"])
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
            raise _error_from_json(ev["error"])
        self.sorted.append(bin_index)
        self.bin = bin_index

    def clear(self) -> None:
        ev = self.q.pop("gate", "clear")
        if "error" in ev:
            raise _error_from_json(ev["error"])

    def to_reject(self) -> None:
        self.q.safety_call("gate", "to_reject")
        self.bin = self.reject_bin

    def status(self) -> dv.GateStatus:
        return dv.GateStatus(state="ready", bin=self.bin)


class ReplayItems:
    def __init__(self, queues: _Queues) -> None:
        self.q = queues
        self.items = [Item(d["id"], d.get("truth")) for d in queues.rf.index["items"]]

    def next_item(self, timeout_s: float):
        if self.q.item_index + 1 >= len(self.items):
            return None
        self.q.item_index += 1
        return self.items[self.q.item_index]

    def exhausted(self) -> bool:
        return self.q.item_index + 1 >= len(self.items)


# --- comparing -----------------------------------------------------------------------------

EXACT_KEYS = ("type", "item", "item_id", "label", "bin", "outcome", "presses", "skipped_frames", "stopped_by",
              "kind", "reason", "point", "step")


def _close(a: Any, b: Any, path: str, out: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
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
    reference, new = _without_timing(reference), _without_timing(new)  # files recorded before timings were dropped
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
    from vs2t_edge.runtime.config import validate_config_dict

    raw = json.loads(json.dumps(rf.index["config"]))
    if bundle is not None:
        raw["bundle"] = str(Path(bundle).resolve())
    raw["journal"] = str(workdir / "journal.jsonl")
    raw.pop("fault_file", None)
    raw.pop("beta_override_file", None)
    beta = rf.index.get("meta", {}).get("beta")
    if beta is not None:
        raw["beta_override"] = float(beta)
    text = yaml.safe_dump(raw)
    path = workdir / "replay-config.yaml"
    path.write_text(text)
    from vs2t_edge.runtime.config import parse_yaml_with_lines

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


def run_replay(file: Path | str, *, model=None, bundle: Path | None = None, evidence_factory=None,
               update_refs: bool = False) -> ReplayReport:
    """Run the daemon from a replay file and compare its decisions with the recorded ones."""
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.journal import read_records
    from vs2t_edge.runtime.notify import Notifier

    rf = ReplayFile.open(file)
    with tempfile.TemporaryDirectory(prefix="vs2t-replay-") as tmp:
        work = Path(tmp)
        if bundle is None and model is None:
            bundle = recorded_bundle(rf)
        cfg = config_for_replay(rf, work, bundle)
        queues = _Queues(rf)
        items = ReplayItems(queues)
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


def record_session(cfg, out: Path | str, *, model=None, camera, arm, gate, items, evidence_factory=None,
                   max_items: int | None = None, operator_clear=None, meta: dict | None = None,
                   on_item=None, log=lambda m: None, stop_event: threading.Event | None = None) -> Path:
    """Run the daemon on the given devices, recording everything into the replay folder ``out``.

    The session journals into a fresh journal beside the replay (``out``.journal.jsonl), so the
    reference decisions are this session's alone. ``operator_clear()`` is called when a fault
    is latched: it fixes the cause (in simulation: clears the injected fault) and returns True
    to clear the fault, which is recorded; returning False ends the session in fault.

    What was recorded is saved however the session ends: ``stop_event`` (set by the caller's
    SIGINT/SIGTERM handler, runtime/record_cli.py) stops it as a signal stops the service (the item
    in hand aborted to reject, ``meta.stopped_by`` names the signal from the event's
    ``signal_name``), and an exception escaping the daemon is re-raised only after the save
    (``meta.crashed`` names it). A session cut short mid-item does not replay as is (its last item
    has no more device events); its frames and decisions are there for calibration and review.
    """
    import dataclasses

    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.journal import read_records
    from vs2t_edge.runtime.notify import Notifier

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    journal = out.with_name(out.name + ".journal.jsonl")
    for p in (journal, journal.with_name("FAULT." + out.name)):
        if p.exists():
            p.unlink()
    cfg = dataclasses.replace(cfg, journal=journal, fault_file=journal.with_name("FAULT." + out.name))
    rec = Recorder()
    r_items = RecordingItems(items, rec)

    def stop_when() -> bool:
        if cfg.fault_file.exists():
            if operator_clear is not None and operator_clear():
                rec.event("operator", "clear_fault")
                cfg.fault_file.unlink()
                return False
            return True
        exhausted = getattr(items, "exhausted", None)
        return bool(exhausted and exhausted())

    stop_event = stop_event or threading.Event()
    code: int | None = None
    crashed: BaseException | None = None
    try:
        code = run_daemon(cfg, model=model, camera=RecordingCamera(camera, rec), arm=RecordingArm(arm, rec),
                          gate=RecordingGate(gate, rec), items=r_items, evidence_factory=evidence_factory,
                          notifier=Notifier(address=""), max_items=max_items, stop_when=stop_when,
                          install_signals=False, stop_event=stop_event, on_item=on_item, log=log)
    except BaseException as exc:  # noqa: BLE001 - saved below, then re-raised
        crashed = exc
    raw = json.loads(json.dumps(cfg.raw, default=str))
    records = read_records(journal) if journal.exists() else []
    start = next((r for r in records if r.get("type") == "start"), {})
    # The beta the session ran with: a replay uses it, so a later calibration does not change it.
    # and how the session ended (0 clean, 2 refused, 3 device fault at start), for `vs2t-edge record`.
    stop = next((r for r in reversed(records) if r.get("type") == "stop"), {})
    meta = dict(meta or {}, beta=start.get("beta"), daemon_exit=code)
    if stop_event.is_set() and crashed is None:
        meta["stopped_by"] = getattr(stop_event, "signal_name", None) or stop.get("reason") or "stop requested"
    if crashed is not None:
        meta["crashed"] = f"{type(crashed).__name__}: {crashed}"
    folder = rec.save(out, raw, records, meta)
    if journal.exists():
        journal.unlink()
    if crashed is not None:
        raise crashed
    return folder

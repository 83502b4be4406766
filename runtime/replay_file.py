"""The replay file on disk: its format, and the reader that refuses anything it should not read.

A replay file is a folder, ``NAME.replay/index.json`` and ``NAME.replay/frames/NNNNNN.png``
(docs/cell.md, "Record and replay"). :class:`ReplayFile` opens it: the index is read only as a
regular file under a size cap and its shape is checked entry by entry (``_check_index``); a
frame is read only when its path, every link resolved, stays inside the folder, is a regular
file, and its header gives a size under the caps - then decoded as stored, for the cell's frame
check to judge. Recording and replaying a session is runtime/replay.py.
"""

from __future__ import annotations

import json
import math
import re
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vs2t_edge.runtime import devices as dv
from vs2t_edge.runtime.fault_latch import FILE_WRITTEN
from vs2t_edge.runtime.files import MAX_REPLAY_INDEX_BYTES, InputRefused, inside, read_image_file, read_regular_file
from vs2t_edge.runtime.labels import bound_piece, judged_anew

FORMAT = "vs2t-edge-replay"
VERSION = 1
# The safety steps of a fault, a stop and a start. Kept in their own list ``safety_steps``, not in
# ``events``: they are called inside guards that must not fail, so the replay devices do not answer
# them from the event queues (a divergence raised there would cut the latch short); the replay
# logs each call and compares the sequence after the run. A file recorded before they were
# (no ``safety_steps`` key) replays as before, its safety steps not compared.
SAFETY_CALLS = frozenset({("arm", "stop"), ("gate", "to_reject")})


# A recorded device error: its type by name, so a replay raises the same class.
_ERRORS = {cls.__name__: cls for cls in (dv.CameraError, dv.ArmConnectionError, dv.ArmSafetyStop, dv.PressFailed,
                                         dv.ArmError, dv.GateError, dv.DeviceError, dv.NotConnectedError)}


def error_to_json(exc: dv.DeviceError) -> dict:
    """A device error as the index records it (a recorded call that raised)."""
    return {"type": type(exc).__name__, "message": str(exc), "kind": exc.kind, "device": exc.device,
            "retryable": bool(exc.retryable)}


def error_from_json(d: dict) -> dv.DeviceError:
    """The recorded error, raised again by the replay device at the same call."""
    cls = _ERRORS.get(d["type"], dv.DeviceError)
    exc = cls(d["message"], device=d.get("device", ""), kind=d.get("kind", ""))
    if exc.retryable != d.get("retryable", exc.retryable):
        exc.retryable = d["retryable"]
    return exc


# The journal records that are a session's decisions: what a replay must reproduce.
DECISION_TYPES = ("pre_sort", "final", "fault", "fault_cleared", "frame_skipped", "retry")
# Measurements of the machine, not decisions: wall-clock stamps and the model's time per press
# (1.9 ms when recorded beside a UR simulator, 0.6 ms replayed alone). Dropped from reference
# decisions at any depth and never compared. ``speculative_presses`` too: whether a score came in
# before the gel was up is a race of the machine (runtime/press_pipeline.py), the decision is not.
# ``speculative_error``: that speculative press's device error (a sequential replay never makes it).
# ``stale_frames_read_past``: the live camera driver's queue (a replay camera has none).
TIMING_KEYS = frozenset({"t", "latency_ms", "timestamp_s", "load_s", "item_s", "speculative_presses",
                         "speculative_error", "stale_frames_read_past"})


# Of a fault record: the latch's steps that failed (the devices of that day) and where its fault file
# was written (the session's state folder; a replay writes its own): neither is the decision
NOT_DECISIONS = frozenset({"steps_failed", "fault_file"})
# Fault records that say only that a fault file that could not be written is there at last
# (runtime/fault_latch.py): that day's disk, not a decision; a replay's file is written at once
NOT_DECISION_FAULT_KINDS = frozenset({FILE_WRITTEN})


def without_timing(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: without_timing(v) for k, v in x.items() if k not in TIMING_KEYS}
    if isinstance(x, list):
        return [without_timing(v) for v in x]
    return x


def decisions_of(records: list[dict]) -> list[dict]:
    """The journal records a replay compares, timestamps and timings dropped."""
    out = []
    for r in records:
        if r.get("type") == "fault" and r.get("kind") in NOT_DECISION_FAULT_KINDS:
            continue
        if r.get("type") in DECISION_TYPES:
            out.append(without_timing({k: v for k, v in r.items() if k not in NOT_DECISIONS}))
    return out


def labels_of(records: list[dict]) -> list[dict]:
    """The operator labels a session read (runtime/labels.py), each with the item it was read
    before: a replay hands them to the cell at the same points, so its decisions can match. A line
    judged before its file was read again (``read_before``: an editor's stale copy) changed nothing
    live; handed over, it would be a new label to the replay - a withdrawn one back in force. A line
    bound to a piece (``piece_sha256``) keeps its binding: unbound, one the live cell refused as naming
    another piece would teach the replay that piece's presses."""
    out, before = [], None
    for r in records:
        if r.get("type") == "item":
            before = r.get("item_id")
        elif r.get("type") == "label" and isinstance(r.get("line"), int) and before is not None \
                and judged_anew(r):  # a line read, not a note about the file (unreadable, read again)
            out.append({"before_item": before, "item_id": str(r.get("item_id") or ""), "fabric": str(r.get("fabric") or ""),
                        **({"off_scene": True} if r.get("off_scene") else {}),
                        **({"retract": True} if r.get("retract") else {}),
                        **({"piece_sha256": piece} if (piece := bound_piece(r)) is not None else {})})
    return out


class ReplayError(ValueError):
    """A replay file that cannot be read, named with what is wrong."""


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
            raise ReplayError(f"{folder}: not a replay file ({'no index.json' if folder.is_dir() else 'no such folder'}; "
                              "`vs2t-edge record --config CONFIG --out NAME.replay` or `vs2t-edge demo --record "
                              "NAME.replay` writes one)")
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
        """(item, reference frame, pressed frames) per item with a grab, ``item`` its index in
        ``index["items"]`` (an item with no grab - one that faulted before its reference - is not
        yielded, so a caller pairs by this index, never by position): the first grab of an item is its
        reference; its pressed frames are the presses the cell scored against that reference (its
        pre_sort record's ``scores``, in press order), each the last frame grabbed after a press at
        its point. A grab the cell never scored - a press frame the contact check refused (the gel at
        rest), the retry's after the camera was reopened mid-piece, a speculative press - is no press
        of the piece, nor is any press of an item that ended before its decision."""
        ids = [it["id"] for it in self.index["items"]]
        scored: dict[str, list] = {}  # item id -> the points of its scored presses, in order
        for d in self.index["decisions"]:
            if d.get("type") == "pre_sort" and isinstance(d.get("item_id"), str) and isinstance(d.get("scores"), list):
                scored[d.get("item_id")] = [_point(s.get("x_mm"), s.get("y_mm")) if isinstance(s, dict) else None
                                            for s in d["scores"]]
        refs: dict[int, str] = {}
        pressed_at: dict[int, dict] = defaultdict(dict)  # item -> point -> the last frame grabbed pressed there
        point, pressed = None, False  # where the arm is above, and whether it pressed there since
        for ev in self.index["events"]:
            if ev["dev"] == "arm" and ev["call"] == "move_above":
                args = [*(ev.get("args") or []), None, None]
                point, pressed = _point(args[0], args[1]), False
            elif ev["dev"] == "arm" and ev["call"] == "press":
                pressed = "error" not in ev
            elif ev["dev"] == "camera" and ev.get("frame"):
                if ev["item"] not in refs:
                    refs[ev["item"]] = ev["frame"]
                elif pressed and point is not None:
                    pressed_at[ev["item"]][point] = ev["frame"]
        for item in sorted(refs):
            points = scored.get(ids[item], []) if 0 <= item < len(ids) else []
            names = [pressed_at[item][p] for p in points if p in pressed_at[item]]
            yield item, self.load_frame(refs[item]), [self.load_frame(n) for n in names]

    def frame_scale(self) -> int:
        """The scale the recorded frames were decoded at: 1 (full frames), or n for a UVC camera that
        decoded at 1/n for its bundle (the reduced pixel path, or a float-path bundle's
        ``devices.camera.decode_scale``; its grabs carry ``reduced_by``; docs/cell.md)."""
        scales = [ev.get("reduced_by", 1) for ev in self.index["events"] if ev["dev"] == "camera" and ev.get("frame")]
        if any(type(s) is not int or s not in (1, 2, 4, 8) for s in scales) or len(set(scales)) > 1:
            raise ReplayError(f"{self.folder}: camera grabs decoded at scales {sorted(set(map(str, scales)))}; one "
                              "of 1, 2, 4, 8 expected for the whole session")
        return scales[0] if scales else 1

    def save_decisions(self, decisions: list[dict]) -> None:
        self.index["decisions"] = decisions
        tmp = self.folder / "index.json.tmp"
        tmp.write_text(json.dumps(self.index, indent=1, sort_keys=True) + "\n")
        tmp.replace(self.folder / "index.json")


_FRAME_NAME = re.compile(r"^frames/[0-9]{6}\.png$")  # nothing outside the replay folder is ever read


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _point(x: Any, y: Any) -> tuple[float, float] | None:
    """A press point (mm) as a key: a move_above's args and a score's x_mm, y_mm are the same grid floats."""
    return (round(float(x), 6), round(float(y), 6)) if _number(x) and _number(y) else None


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
    if not isinstance(index.get("labels", []), list):  # absent in files recorded before operator labels
        raise ReplayError(f"{path}: 'labels' must be a list")
    for i, lab in enumerate(index.get("labels", [])):
        if not isinstance(lab, dict) or not all(isinstance(lab.get(k), str) for k in ("before_item", "item_id", "fabric")):
            raise ReplayError(f"{path}: labels[{i}] needs 'before_item', 'item_id' and 'fabric' texts")
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

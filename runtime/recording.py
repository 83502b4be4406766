"""Record a cell session into a replay file (format: runtime/replay_file.py, docs/cell.md).

Recording wraps the session's camera, arm, gate and item source in proxies that log each call
with its result or its typed error (``RecordingCamera`` ...), tagged with the item in hand, and
``record_session`` runs the daemon on them (runtime/daemon.run_daemon) and saves the folder:
every grabbed frame as PNG, every device event in order, the session's decisions as the
reference a replay (runtime/replay.py) is compared with.
"""

from __future__ import annotations

import json
import shutil
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vs2t_edge.runtime import devices as dv
from vs2t_edge.runtime.bundle import SEAL_KEY
from vs2t_edge.runtime.daemon import run_daemon
from vs2t_edge.runtime.devices import Frame, PressResult
from vs2t_edge.runtime.journal import read_records
from vs2t_edge.runtime.notify import Notifier
from vs2t_edge.runtime.replay_file import (FORMAT, SAFETY_CALLS, VERSION, ReplayError, decisions_of, error_to_json,
                                            labels_of)


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
                 "decisions": decisions_of(journal_records), "labels": labels_of(journal_records)}
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
            self.rec.event("camera", "grab", error=error_to_json(exc))
            raise
        name = self.rec.add_frame(frame.image) if isinstance(frame.image, np.ndarray) and frame.image.ndim == 3 \
            and frame.image.dtype == np.uint8 else None
        scale = getattr(frame, "reduced_by", 1)  # recorded as decoded; replay tells the model the same
        self.rec.event("camera", "grab", frame=name, timestamp_s=frame.timestamp_s, index=frame.index,
                       **({"reduced_by": scale} if scale != 1 else {}))
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
                self.rec.event(self.DEV, name, args=list(args), error=error_to_json(exc))
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


def recording_journal(out: Path | str) -> Path:
    """The journal a recording into the replay folder ``out`` writes (beside it: its decisions
    alone; `vs2t-edge label --recording OUT` finds the recorded pieces there)."""
    out = Path(out)
    return out.with_name(out.name + ".journal.jsonl")


def record_session(cfg, out: Path | str, *, model=None, camera, arm, gate, items, evidence_factory=None,
                   max_items: int | None = None, operator_clear=None, meta: dict | None = None,
                   on_item=None, log=lambda m: None, stop_event: threading.Event | None = None,
                   keep_journal: Path | None = None) -> Path:
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
    ``keep_journal``: move the session's journal there once saved instead of deleting it (the demo
    keeps it as its own journal, which its totals and `vs2t-edge label --list` read).
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    journal = recording_journal(out)
    for p in (journal, journal.with_name("FAULT." + out.name)):
        if p.exists():
            p.unlink()
    cfg = replace(cfg, journal=journal, fault_file=journal.with_name("FAULT." + out.name))
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
    # and the bundle's seal: a replay refuses another bundle than the one the session ran.
    meta = dict(meta or {}, beta=start.get("beta"), daemon_exit=code,
                **({SEAL_KEY: start[SEAL_KEY]} if start.get(SEAL_KEY) else {}))
    if stop_event.is_set() and crashed is None:
        meta["stopped_by"] = getattr(stop_event, "signal_name", None) or stop.get("reason") or "stop requested"
    if crashed is not None:
        meta["crashed"] = f"{type(crashed).__name__}: {crashed}"
    folder = rec.save(out, raw, records, meta)
    if journal.exists():
        if keep_journal is not None:
            shutil.move(str(journal), str(keep_journal))  # across file systems too
        else:
            journal.unlink()
    if crashed is not None:
        raise crashed
    return folder

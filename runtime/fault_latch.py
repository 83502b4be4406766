"""The cell's fault latch (runtime/cell.py's module doc, "Latched fault"): latch, wait for the
operator's clear, clear, and what a restart restores - the part of the loop that decides whether
anything may move. ``Cell`` inherits it; it uses the cell's devices, journal, notifier, scene,
log and ``_reopen_camera``.

Only a fault file that was there and is gone clears a fault: one that could not be written (a
full disk, a folder the service may not write) is written again while the fault stays latched,
and a restart that finds no file restores a fault whose journal record says its file was never
written, or names another file that is still there (a config changed before the clear). A file
written late (by that retry, or by a restart) is journalled, so its removal is a clear."""

from __future__ import annotations

import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from vs2t_edge.runtime.devices import DeviceError
from vs2t_edge.runtime.evidence import UNKNOWN
from vs2t_edge.runtime.files import atomic_write, read_regular_file
from vs2t_edge.runtime.journal import JournalError

INTERNAL = "internal"  # fault kind of an exception the loop has no rule for (Cell._latch_internal)
MAX_FAULT_FILE_BYTES = 64 * 1024  # a fault reason is one line
FAULT_FILE_FAILED = "fault file failed"  # the latch step a fault record's steps_failed names
# fault record kind: a fault file that could not be written when its fault latched, written at last
# by the loop's retry (a restart that writes it journals kind "restored"): its removal is then a clear
FILE_WRITTEN = "file_written"


def _fault_file_never_written(fault: dict | None) -> bool:
    """Whether a journal's latched fault record says its fault file could not be written."""
    steps = fault.get("steps_failed") if isinstance(fault, dict) else None
    return isinstance(steps, list) and any(isinstance(s, str) and s.startswith(FAULT_FILE_FAILED) for s in steps)


def _fault_file_of(fault: dict | None) -> Path | None:
    """The fault file a journal's latched fault record says it was written to (None: not said)."""
    where = fault.get("fault_file") if isinstance(fault, dict) else None
    return Path(where) if isinstance(where, str) and where else None


def _fault_file_reason(path: Path) -> str:
    """A fault file's reason, read bounded (never a FIFO's endless wait): the fault stays latched either way."""
    try:
        text = read_regular_file(path, MAX_FAULT_FILE_BYTES, "fault file").decode("utf-8", "replace")
    except (OSError, ValueError) as exc:
        text = f"fault file {path} unreadable ({exc})"
    return text.strip() or "fault latched before restart"


@dataclass(frozen=True)
class LatchedFault:
    """A latched fault as a start finds it: its reason, the file that holds it (None: its file was
    never written, only the journal holds it) and whether that file is the config's own."""

    reason: str
    file: Path | None
    moved: bool = False  # held by another file than the config's (a config changed before the clear)


def find_latched_fault(ff: Path, last_fault: Callable[[], dict | None]) -> LatchedFault | None:
    """The one reading of where a latched fault is, for a restart (``FaultLatch.recover``) and the
    operator's clear (``vs2t-edge run --clear-fault``): the config's fault file ``ff`` if it is
    there; else, from the journal's last uncleared fault record (``last_fault``, read only then),
    the other fault file it names if that is still there, or the record itself if it says its
    file was never written. None: no fault latched."""
    if ff.exists():
        return LatchedFault(_fault_file_reason(ff), ff)
    last = last_fault()
    moved = _fault_file_of(last)
    if moved is not None and moved != ff and moved.exists():
        return LatchedFault(_fault_file_reason(moved), moved, moved=True)
    if _fault_file_never_written(last):
        return LatchedFault(str(last.get("reason") or "fault latched before restart"), None)
    return None


class FaultLatch:
    """The fault latch's half of ``Cell``, whose ``__init__`` sets ``fault`` (None) and
    ``_fault_file_written`` (False: only a fault file that was there and is gone clears a fault)."""

    fault: str | None
    _fault_file_written: bool

    def recover(self) -> list[dict]:
        """Resolve items the last run left between pre_sort and final; restore a latched fault."""
        resolved = self._resolve_open_items()
        ff = self.scene.fault_file
        if ff is None:
            return resolved
        found = find_latched_fault(ff, lambda: self.journal.latched_fault())  # the journal only when ff is absent
        if found is None:
            return resolved
        self.fault = found.reason
        if found.file == ff:
            self._fault_file_written = True
            self.notifier.status(f"FAULT (latched before restart): {self.fault}")
        elif found.moved:
            # latched under another fault file, still there: the config changed, the operator cleared nothing
            failed = self._write_fault_file()  # where this config's operator clears it
            # the journal's latched fault names that file now: cleared there while the service is
            # stopped (`run --clear-fault`), the next start is clean, not latched again by the old one
            self.journal.append(self._fault_record(self.fault, "restored",
                                                   [f"{FAULT_FILE_FAILED}: {failed}"] if failed else []))
            self.notifier.status(f"FAULT (latched before restart, its fault file {found.file} still there; this "
                                 f"config's is {ff}): {self.fault}")
        else:
            # the journal's last fault, its file never written: no operator can have cleared it
            self._write_fault_file_late("restored")  # now, if it can
            self.notifier.status(f"FAULT (latched before restart; its fault file was never written): {self.fault}")
        return resolved

    def _resolve_open_items(self, cause: str = "process stopped") -> list[dict]:
        """One final record for every item the journal has open (a restart, or a failed journal
        write in this run: ``cause`` says which): after its pre_sort the gate may have moved, before
        it the gate was not told."""
        resolved = []
        for pre in self.journal.unresolved_items():
            if pre.get("type") == "pre_sort":
                rec = self._final(pre["item"], pre.get("item_id", ""), label=pre.get("label", UNKNOWN),
                                  bin_=self.scene.reject_bin, outcome="unknown_outcome",
                                  maybe_bin=pre.get("bin", self.scene.reject_bin),
                                  note=f"{cause} after the pre-sort record (bin {pre.get('bin')}) "
                                       "and before the gate's ack; the gate may have moved - check the bins")
                self.log(f"recovered item {pre['item']}: unknown outcome, logged as reject")
            else:
                rec = self._final(pre["item"], pre.get("item_id", ""), label=UNKNOWN, bin_=self.scene.reject_bin,
                                  outcome="aborted", note=f"{cause} before a decision; the gate was "
                                                           "not told - the piece is still at the station")
                self.log(f"recovered item {pre['item']}: stopped before a decision, logged as aborted")
            resolved.append(rec)
        return resolved

    # --- journal helpers ---------------------------------------------------------------

    def _final(self, number: int, item_id: str, *, label: str, bin_: int, outcome: str, **extra) -> dict:
        rec = {"type": "final", "item": number, "item_id": item_id, "label": label, "bin": bin_,
               "outcome": outcome, **extra}
        return self.journal.append(rec)

    # --- the fault latch ---------------------------------------------------------------

    def latch_fault(self, reason: str, kind: str = "fault") -> None:
        """Arm stopped, gate to reject, reason journalled and reported; every step guarded."""
        self.fault = reason
        steps: list[str] = []
        try:
            self.notifier.ping_if_due()  # the stop and to-reject below are un-leased waits
        except Exception:  # noqa: BLE001 - a failing notifier must not skip the latch
            pass
        for what, fn in (("arm.stop", self.arm.stop), ("gate.to_reject", self.gate.to_reject)):
            try:
                fn()
            except Exception as exc:  # noqa: BLE001 - one failing step must not skip the rest
                steps.append(f"{what} failed: {exc}")
        # the fault file before the journal record: that record then says whether the file was
        # written, which a restart needs (a file never written is no operator's clear)
        failed = self._write_fault_file()
        if failed:
            steps.append(f"{FAULT_FILE_FAILED}: {failed}")
        try:
            self.journal.append(self._fault_record(reason, kind, steps))
        except Exception as exc:  # noqa: BLE001
            steps.append(f"journal failed: {exc}")
        try:
            self.notifier.status(f"FAULT: {reason} - clear with `vs2t-edge run --clear-fault`")
        except Exception:  # noqa: BLE001
            pass
        self.log(f"FAULT latched: {reason}" + (f" ({'; '.join(steps)})" if steps else ""))

    def fault_cleared_by_operator(self) -> bool:
        """Whether the operator cleared the latched fault: removed its fault file. A fault file that
        could not be written (a full disk, a folder the service may not write) is written again
        here, never taken for a clear: until it is there, nothing clears the fault."""
        ff = self.scene.fault_file
        if ff is None:
            return True
        if not self._fault_file_written:
            failed = self._write_fault_file_late(FILE_WRITTEN)
            if not failed:
                self.log(f"fault file {ff} written at last; clear the fault with `vs2t-edge run --clear-fault`")
            elif self._fault_file_written:  # the file is there, its record is not: the clear will say the journal
                self.log(f"fault file {ff} written at last, but {failed}: clearing the fault fails until the "
                         "journal can be written")
            return False  # else the file is still not there (latch_fault said why)
        return not ff.exists()

    def _write_fault_file_late(self, kind: str) -> str:
        """Write the fault file of a fault whose file could not be written when it latched, and once
        it is there journal a ``fault`` record of ``kind`` naming it with no failed step: the
        operator who removes it while the service is stopped has cleared the fault, which the next
        start then sees (``find_latched_fault``), instead of the first record's file never written.
        '' when written and journalled, else why not; until the file is there the loop writes it again."""
        failed = self._write_fault_file()
        if failed:
            return failed
        try:
            self.journal.append(self._fault_record(self.fault, kind, []))
        except JournalError as exc:
            # the file stays counted as written: the operator's removal is taken as a clear, whose
            # own journal record then fails and latches the fault again, saying why - not a file
            # written back behind the operator's back every turn
            return f"journal failed: {exc}"
        return ""

    def _fault_record(self, reason: str, kind: str, steps: list[str]) -> dict:
        """A ``fault`` journal record, naming where its fault file is: a restart on a config naming
        another place still finds it (``recover``)."""
        where = {"fault_file": str(self.scene.fault_file)} if self.scene.fault_file is not None else {}
        return {"type": "fault", "reason": reason, "kind": kind, "steps_failed": steps, **where, "t": time.time()}

    def _write_fault_file(self) -> str:
        """The latched fault's reason into the fault file (if the scene has one); '' when written,
        else why not. ``_fault_file_written`` says which."""
        self._fault_file_written = False
        if self.scene.fault_file is None:
            return ""
        try:
            atomic_write(self.scene.fault_file, f"{self.fault}\n")
        except Exception as exc:  # noqa: BLE001 - any failure leaves the fault latched, said by the caller
            return str(exc)
        self._fault_file_written = True
        return ""

    def clear_fault(self) -> bool:
        """Called when the operator removed the fault file: clear the gate, journal, resume."""
        try:
            # an item a failed journal write left open gets its final record first (the disk
            # must be writable again, else the fault latches again here)
            # only a failed journal write leaves an item open in a running cell (runtime/cell.py)
            self._resolve_open_items("a journal write failed (the fault the operator cleared)")
            with self.notifier.bounded_wait(self.scene.bounds.clear_s if self.scene.bounds else None):
                self.gate.clear()
                clear_arm = getattr(self.arm, "clear_protective_stop", None)
                if clear_arm is not None:
                    clear_arm()
                    connect = getattr(self.arm, "connect", None)
                    if connect is not None:
                        connect()
                # a camera that left the bus (cable out, driver reset) only comes back through a new
                # open; still gone -> the clear fails and the fault latches again, naming the camera
                self._reopen_camera("the operator's clear", raise_on_failure=True)
            self.journal.append({"type": "fault_cleared", "reason": self.fault, "t": time.time()})
        except (DeviceError, JournalError) as exc:
            self.latch_fault(f"could not clear the fault: {exc}", "clear_failed")
            return False
        self.log(f"fault cleared by the operator: {self.fault}")
        self.fault = None
        self.notifier.status("fault cleared; sorting")
        return True

    def _latch_internal(self, exc: BaseException, where: str) -> str:
        """An exception the loop has no rule for (a model RuntimeError, a device used while not
        connected, a bug) latches a fault like any other: without it the service would exit,
        systemd would restart it and the cell would resume with no operator. The traceback goes
        to the log; the reason names the exception's type and text."""
        reason = f"{where}internal error: {type(exc).__name__}: {exc}"
        self.log("".join(traceback.format_exception(type(exc), exc, exc.__traceback__)).rstrip())
        self.latch_fault(reason, INTERNAL)
        return reason

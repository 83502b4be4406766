"""Fault-matrix rows at the journal: a torn write at power loss, a full disk, EIO from fsync.

The failing disk is injected into the journal module's ``os`` only (``_DiskFull``, ``_OsProxy``:
no tmpfs or loop device without root); registered in sim/faults.py SCENARIOS.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

from vs2t_edge.runtime.journal import read_records
from vs2t_edge.sim.fakes import BINS, REJECT
from vs2t_edge.sim.fault_rig import Rig, _at, _check, _outcome_words, audit, build_rig, run_rig


# --- journal rows ---------------------------------------------------------------------------

def power_loss_mid_write(w: Path):
    """The power goes while the pre_sort record is half written: the restarted cell (a new rig on
    the same state folder, as the service restarts) cuts the torn tail on open and keeps it aside,
    its recovery gives the open item exactly one final record (aborted, reject bin), and it sorts on."""
    from vs2t_edge.runtime.journal import _encode

    w.mkdir(parents=True, exist_ok=True)
    rig = build_rig(w, ["denim", "silk"])
    rig.cell.run(max_items=1)
    rig.cell.journal.close()  # every append was fsynced: what is on disk is what the power cut left
    # piece 2 started, then the power went mid pre_sort write
    line = _encode({"type": "item", "item": 2, "item_id": "piece-0001", "t": 0.0})
    torn = _encode({"type": "pre_sort", "item": 2, "item_id": "piece-0001", "label": "silk", "bin": 2})
    torn_part = torn[: len(torn) // 2]
    with open(rig.journal_path, "ab") as f:
        f.write(line + torn_part)
    good_size = rig.journal_path.stat().st_size - len(torn_part)
    problems: list[str] = []
    rig2 = _reopen_rig(rig.journal_path, ["wool"])  # the restart: same journal, recover() ran
    cut = rig2.cell.journal.torn_bytes
    recovered = [r for r in read_records(rig.journal_path) if r.get("type") == "final"]
    run_rig(rig2)
    a = audit(rig.journal_path, {"piece-0000": "denim", "piece-0001": "silk", "piece-0000b": "wool"})
    problems += a["problems"]
    kept = Path(str(rig.journal_path) + ".torn")
    _check(problems, cut == len(torn_part), f"the restart's journal cut {cut} bytes, the torn tail was {len(torn_part)}")
    _check(problems, kept.exists() and kept.read_bytes() == torn_part,
           f"the torn bytes are not kept aside in {kept.name}")
    data = rig.journal_path.read_bytes()
    _check(problems, data.endswith(b"\n") and len(a["records"]) == data.count(b"\n"),
           "the journal still holds a partial or corrupt line")
    _check(problems, not list(w.glob("run-*")), "the restart opened another journal")
    f2 = [r for r in a["finals"] if r["item"] == 2]
    _check(problems, len(f2) == 1 and f2[0]["outcome"] == "aborted" and f2[0]["bin"] == REJECT,
           f"open item 2 resolved as {f2}")
    _check(problems, [r["item"] for r in recovered] == [1, 2],
           f"the restart's recovery (before any new piece) closed items {[r['item'] for r in recovered]}, wanted [1, 2]")
    wool = [r for r in a["finals"] if r.get("item_id") == "piece-0000b"]
    _check(problems, len(wool) == 1 and wool[0]["item"] == 3 and wool[0]["outcome"] == "sorted",
           f"the piece after the restart: {wool}")
    _check(problems, rig.journal_path.stat().st_size > good_size, "nothing was written after the restart")
    return _outcome_words(a, f"restart cut {cut} torn bytes (kept aside), recovery aborted item 2 once, "
                             "then sorted on"), problems


def _reopen_rig(journal_path: Path, truths: list[str]) -> Rig:
    """The service restarted: a new cell on the same state folder (build_rig's journal.jsonl
    there), so the same journal file is reopened (its torn tail cut) and recover() runs in
    build_rig. Piece ids get a "b" so that they differ from the first run's."""
    rig = build_rig(journal_path.parent, truths)
    for it in rig.pieces.items:
        object.__setattr__(it, "id", it.id + "b")
    return rig


class _DiskFull:
    """os.write / os.fsync for the journal module that fail on the first record of a type once
    armed: ``write`` lands half the bytes, then ENOSPC on every write until ``freed`` (a filling
    disk); ``fsync`` raises EIO once (a dying disk). The journal must cut the half record back."""

    def __init__(self, fail_on_type: str, how: str = "write", real=os) -> None:
        self.fail_on_type, self.how, self.real = fail_on_type, how, real
        self.hit = 0
        self.freed = False
        self.armed = True
        self._full = False
        self._fsync_next = False

    def write(self, fd: int, data: bytes) -> int:
        if self.armed and not self.freed and f'"type":"{self.fail_on_type}"'.encode() in data:
            self.armed = False
            self.hit += 1
            if self.how == "fsync":
                self._fsync_next = True
                return self.real.write(fd, data)
            n = self.real.write(fd, data[: len(data) // 2])
            self._full = True
            return n
        if self._full and not self.freed:
            raise OSError(errno.ENOSPC, "No space left on device (injected)")
        return self.real.write(fd, data)

    def fsync(self, fd: int) -> None:
        if self._fsync_next:
            self._fsync_next = False
            raise OSError(errno.EIO, "Input/output error (injected)")
        return self.real.fsync(fd)


class _OsProxy:
    """What the journal module sees as ``os``: the injected write/fsync, the rest real."""

    def __init__(self, disk: _DiskFull) -> None:
        self._disk = disk

    def __getattr__(self, name):
        return getattr(self._disk, name) if name in ("write", "fsync") else getattr(os, name)


def _journal_clean(path: Path) -> str:
    """'' when the journal ends on a whole record and no torn bytes were ever cut, else why not."""
    torn = Path(str(path) + ".torn")
    data = path.read_bytes()
    if torn.exists():
        return f"{torn.stat().st_size} torn bytes were cut from the journal (a partial record was left)"
    if data and not data.endswith(b"\n"):
        return "the journal ends in a partial record"
    if len(read_records(path)) != data.count(b"\n"):
        return "the journal holds a corrupt line"
    return ""


def disk_failure(w: Path, *, mode: str):
    """The journal's disk fails mid-item (no tmpfs or loop device here without root, so the
    failure is injected into the journal module's ``os``). ``mode``:

    * ``clear``: ENOSPC while writing piece 1's pre_sort record (half the bytes land). The record
      is cut back, a fault latched naming the journal, the gate not moved for that piece. The
      operator's first clear while the disk is still full is refused (latched again); after space
      is freed the clear resolves the open piece (aborted, reject) and the rest are sorted.
    * ``restart``: the same, but the service is stopped while the disk is still full (the stop
      record cannot be written; the stop must not crash); space freed, a restart resolves it.
    * ``fsync_eio``: fsync of piece 1's final record fails with EIO after the gate moved it: cut
      back, fault latched; the clear resolves it as unknown_outcome (the gate may have moved).
    """
    import vs2t_edge.runtime.journal as jmod

    w.mkdir(parents=True, exist_ok=True)
    how = "fsync" if mode == "fsync_eio" else "write"
    disk = _DiskFull("final" if how == "fsync" else "pre_sort", how)
    clears = {"n": 0}

    def operator_fix():
        clears["n"] += 1
        if clears["n"] >= 2 or how == "fsync":
            disk.freed = True  # the operator made space (first try: not yet)

    truths = ["denim", "silk", "wool"]
    rig = build_rig(w, truths, operator_fix=operator_fix if mode != "restart" else None)
    problems: list[str] = []
    crashed = ""
    fault_reason = ""
    real_os = jmod.os

    def arm_on_second():
        disk.armed = True

    disk.armed = False
    _at(rig, 1, 1, arm_on_second)
    jmod.os = _OsProxy(disk)  # only the journal module sees the failing disk
    try:
        if mode == "restart":
            def stop_when():
                nonlocal fault_reason
                if rig.fault_file.exists():
                    fault_reason = rig.fault_file.read_text()
                    return True  # the operator stops the service instead of clearing
                return rig.pieces.exhausted()

            try:
                rig.cell.run(stop_when=stop_when)
                rig.cell.shutdown("SIGTERM")  # stop record fails on the full disk: logged, no crash
            except Exception as exc:  # noqa: BLE001 - that is the measured outcome
                crashed = repr(exc)
        else:
            try:
                run_rig(rig)
            except Exception as exc:  # noqa: BLE001
                crashed = repr(exc)
            fault_reason = rig.operator[0] if rig.operator else ""
    finally:
        jmod.os = real_os
    gate_sorted = list(rig.gate.sorted)
    _check(problems, not crashed, f"the loop crashed: {crashed}")
    _check(problems, disk.hit == 1, f"the failure was injected {disk.hit} times")
    want = "No space left" if how == "write" else "Input/output error"
    _check(problems, "journal write failed" in fault_reason and want in fault_reason,
           f"the latched fault does not name the journal and {want!r}: {fault_reason[:160]!r}")
    why = _journal_clean(rig.journal_path)
    _check(problems, not why, why)
    expect_gate = [BINS["denim"], BINS["silk"]] if how == "fsync" else [BINS["denim"]]
    if mode == "restart":
        _check(problems, gate_sorted == expect_gate, f"gate sorted {gate_sorted}; only piece 0 was decided on disk")
        rig2 = _reopen_rig(rig.journal_path, ["wool"])
        run_rig(rig2)
        truths_by_id = {"piece-0000": "denim", "piece-0001": "silk", "piece-0000b": "wool"}
        expect_finals = 3
    else:
        _check(problems, gate_sorted[: len(expect_gate)] == expect_gate and len(gate_sorted) == 2 + (how == "fsync"),
               f"gate sorted {gate_sorted}")
        truths_by_id = {it.id: it.truth for it in rig.pieces.items}
        expect_finals = 3
        n_clears = 1 if how == "fsync" else 2
        _check(problems, len(rig.operator) == n_clears, f"operator cleared {len(rig.operator)} times, "
                                                        f"expected {n_clears}")
    a = audit(rig.journal_path, truths_by_id)
    problems += a["problems"]
    _check(problems, len(a["finals"]) == expect_finals, f"{len(a['finals'])} finals")
    f2 = [r for r in a["finals"] if r["item"] == 2]
    want_outcome = "unknown_outcome" if how == "fsync" else "aborted"
    _check(problems, len(f2) == 1 and f2[0]["bin"] == REJECT and f2[0]["outcome"] == want_outcome,
           f"the piece whose record failed resolved as {f2}")
    _check(problems, a["outcomes"].get("sorted", 0) == 2, f"outcomes {dict(a['outcomes'])}")
    extra = {"clear": "record cut back, fault latched; clear refused while full, then resolved",
             "restart": "record cut back, fault latched, stopped while full; restart resolved it",
             "fsync_eio": "record cut back after the gate moved, fault latched; clear resolved it"}[mode]
    return _outcome_words(a, f"{extra}; gate sorted {gate_sorted}"), problems


def disk_full(w: Path):
    return disk_failure(w, mode="clear")


def disk_full_restart(w: Path):
    return disk_failure(w, mode="restart")


def fsync_eio(w: Path):
    return disk_failure(w, mode="fsync_eio")

"""The decision journal: append-only JSON lines, each fsynced before the call returns.

One line per record: ``{"crc": <crc32 of the body>, "rec": {...}}``. A record is on disk when
``append`` returns (write + flush + fsync of the file; the folder is fsynced once on creation),
so the cell writes the decision *before* telling the gate, and a power cut leaves either the
whole record or a torn last line. ``Journal.open`` reads the file back, detects a torn or
corrupt last line (no newline, bad JSON or bad CRC), moves those bytes to ``<journal>.torn``
(kept for a human) and truncates the journal to its last good record. A journal (or ``.torn``)
found more open than 0640 - readable or writable by other users, e.g. after a hand copy - is
tightened to 0640 on open and the log says so; one that cannot be tightened is refused.

Record types (field ``type``), see docs/cell.md for every field:

* ``start`` / ``stop``: the daemon started or stopped (reason).
* ``pre_sort``: the decision for an item, written before ``gate.sort``.
* ``final``: exactly one per item: the outcome (``sorted``, ``rejected_fault``,
  ``unknown_outcome``, ``aborted``) and the bin the item went to.
* ``fault`` / ``fault_cleared``: the latched fault and its clearing.
* ``frame_skipped``: a bad frame, skipped and counted.

On open, an item with a ``pre_sort`` but no ``final`` (the process died between the two) is
reported by ``unresolved_items()``; the daemon then writes its final record as
``unknown_outcome`` to the reject bin (the gate may or may not have moved; a human checks).

Memory stays bounded however long the daemon runs: the journal file is the record, the object
keeps only ``records`` (the last ``RECENT_RECORDS`` records, for status and debugging) and what
the loop needs to carry on - the next item number, the items without a final record (normally
none, at most the one in hand), the latched fault and counts by record type and by outcome. These
are built by one streaming pass over the file in ``open`` and kept up to date by ``append``; whole
history queries (``items()``, ``read_records``) read the file.

A failed append (ENOSPC, EIO, a failed fsync) never leaves a partial record: the file is cut back
to the last good record and :class:`JournalWriteError` says so (the cell then latches a fault and
moves nothing). If even the cut fails the journal refuses every later append until reopened
(``open`` cuts a torn tail), so a half line can never end up in the middle of the file.
"""

from __future__ import annotations

import errno
import json
import os
import zlib
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator


class JournalError(RuntimeError):
    pass


# Modes of what the cell creates in its state folder, set after creation so that no umask can
# change them: deleting FAULT clears a latched fault and the journal is the record of every
# decision, so neither may be writable by other users (nor the folder listable by them).
STATE_FILE_MODE = 0o640
STATE_DIR_MODE = 0o750


def make_state_dir(folder: Path) -> None:
    """Create `folder` and its missing parents with STATE_DIR_MODE. Folders that already exist keep
    their mode (an operator, or systemd's StateDirectoryMode=, chose it)."""
    missing = []
    folder = Path(folder)
    while not folder.exists() and folder.parent != folder:
        missing.append(folder)
        folder = folder.parent
    for d in reversed(missing):
        try:
            os.mkdir(d, STATE_DIR_MODE)
        except FileExistsError:
            continue  # made meanwhile by someone else: not ours to chmod
        os.chmod(d, STATE_DIR_MODE)  # mkdir's mode went through the umask


def _encode(rec: dict) -> bytes:
    body = json.dumps(rec, sort_keys=True, separators=(",", ":"), allow_nan=False)
    crc = zlib.crc32(body.encode("utf-8")) & 0xFFFFFFFF
    return f'{{"crc":{crc},"rec":{body}}}\n'.encode("utf-8")


def _decode(line: bytes) -> dict | None:
    """The record of one complete line, or None when it is corrupt."""
    try:
        outer = json.loads(line.decode("utf-8"))
        rec = outer["rec"]
        body = json.dumps(rec, sort_keys=True, separators=(",", ":"), allow_nan=False)
        if zlib.crc32(body.encode("utf-8")) & 0xFFFFFFFF != outer["crc"]:
            return None
        return rec if isinstance(rec, dict) else None
    except (ValueError, KeyError, TypeError, UnicodeDecodeError):
        return None


_SAID_CORRUPT: set[tuple[str, int]] = set()  # (journal, line) said on stderr by iter_records: once each


def iter_records(path: Path | str, *, log: Callable[[str], None] | None = None) -> Iterator[dict]:
    """Every good record of a journal, streamed line by line (torn or corrupt lines are skipped,
    not repaired); memory does not grow with the file. A torn last line is normal (a write under
    way, or a power cut ``Journal.open`` will cut) and read past quietly; a corrupt line with good
    records after it (disk damage, a hand edit) has lost a record - were it a session's ``start``,
    that session's pieces would read as the previous one's - so ``log`` (default: stderr, the
    service's log) says it, naming the file and the line, once per process. ``Journal.open`` (the
    service's start, before it restores anything from here) refuses such a journal."""
    path = Path(path)
    if not path.exists():
        return
    bad: list[int] = []  # corrupt lines since the last good record (the torn tail, if nothing follows)
    with open(path, "rb") as f:
        for number, line in enumerate(f, 1):
            if not line.strip():
                continue
            rec = _decode(line.rstrip(b"\n"))
            if rec is None:
                bad.append(number)
                continue
            if bad:
                _say_corrupt(path, bad, log)
                bad = []
            yield rec


def _say_corrupt(path: Path, lines: list[int], log: Callable[[str], None] | None) -> None:
    new = [n for n in lines if (str(path), n) not in _SAID_CORRUPT]
    if not new:
        return
    _SAID_CORRUPT.update((str(path), n) for n in new)
    which = f"line {new[0]}" if len(new) == 1 else f"lines {', '.join(map(str, new))}"
    (log or _stderr_log)(f"journal {path}: {which} corrupt (bad JSON or CRC) with good records after it, skipped: "
                         "a record is lost there (disk damage or a hand edit); the service refuses to start on "
                         "this journal until a human repairs it")


def read_records(path: Path | str) -> list[dict]:
    """Every good record of a journal as a list (tools and tests; the daemon never calls it)."""
    return list(iter_records(path))


def latched_fault_in(path: Path | str) -> dict | None:
    """The last fault record not followed by a fault_cleared record, read without opening the
    journal for appending (``Journal.latched_fault`` of an open journal): what the operator's
    clear needs while the service may hold the journal."""
    fault = None
    for rec in iter_records(path):
        fault = _latched_after(fault, rec)
    return fault


def _latched_after(fault: dict | None, rec: dict) -> dict | None:
    """The latched fault after ``rec``, given the one before it: the one rule for an open journal
    (``Journal._apply``) and a closed one (``latched_fault_in``)."""
    kind = rec.get("type")
    return rec if kind == "fault" else None if kind == "fault_cleared" else fault


RECENT_RECORDS = 128  # records kept in memory (``Journal.records``); the file keeps them all


class JournalWriteError(JournalError):
    """An append failed; the file was cut back to its last good record (``cut_back`` true) or
    could not be (the journal then refuses appends until reopened). ``errno`` of the OS error."""

    def __init__(self, message: str, errno_: int | None, cut_back: bool) -> None:
        super().__init__(message)
        self.errno, self.cut_back = errno_, cut_back


@dataclass
class Journal:
    path: Path
    records: deque = field(default_factory=lambda: deque(maxlen=RECENT_RECORDS))  # the most recent only
    torn_bytes: int = 0  # bytes cut off the end on open (0 when the file was clean)
    counts: Counter = field(default_factory=Counter)  # records by type, whole file
    outcomes: Counter = field(default_factory=Counter)  # final records by outcome, whole file
    _fd: int | None = None
    _open_items: dict = field(default_factory=dict)  # item -> its last item / pre_sort record, no final yet
    _max_item: int = 0
    _fault: dict | None = None  # the last fault record not followed by fault_cleared
    _broken: str = ""  # non-empty: a failed write could not be cut back; appends refused
    mode_tightened_from: int | None = None  # the too-open mode an existing journal had on open

    @classmethod
    def open(cls, path: Path | str, *, log: Callable[[str], None] | None = None) -> "Journal":
        """Open (or create) the journal, cut a torn tail. An existing journal more open than
        STATE_FILE_MODE (e.g. 0666 from a hand copy) is tightened to it and ``log`` says so
        (default: stderr, the service's log); if it cannot be tightened the open is refused."""
        path = Path(path)
        make_state_dir(path.parent)
        fd, created, was_mode = _open_state_file(path, os.O_RDWR, log)
        j = cls(path=path, _fd=fd, mode_tightened_from=was_mode)
        good_end = 0  # byte after the last good record
        bad_at = None  # (line number, byte) of the first corrupt line
        number = 0  # lines read
        try:
            if created:
                _fsync_dir(path.parent)
            # One streaming pass. Only the tail may be torn or corrupt; a corrupt line with real
            # records after it is a damaged journal and is refused (a human looks at it). A blank
            # line (a hand edit) holds no record: it loses nothing and refuses nothing.
            with open(path, "rb") as f:
                pos = 0
                for line in f:
                    number += 1
                    if bad_at is not None:
                        if line.strip():
                            raise JournalError(f"journal {path}: line {bad_at[0]} (byte {bad_at[1]}) is "
                                               "corrupt and is not the last one; refusing to append to a "
                                               "damaged journal")
                        pos += len(line)
                        continue
                    if line.endswith(b"\n") and not line.strip():
                        pos += len(line)
                        continue
                    rec = _decode(line[:-1]) if line.endswith(b"\n") else None
                    if rec is None:
                        if not line.endswith(b"\n"):
                            break  # bytes after the last newline: a torn last write
                        bad_at = (number, pos)
                        pos += len(line)
                        continue
                    j._apply(rec)
                    pos += len(line)
                    good_end = pos
            size = os.fstat(fd).st_size
        except BaseException:
            os.close(fd)
            raise
        torn = size - good_end
        if torn:
            torn_fd = _open_state_file(Path(str(path) + ".torn"), os.O_WRONLY, log)[0]
            with open(path, "rb") as src, os.fdopen(torn_fd, "ab") as f:
                src.seek(good_end)
                f.write(src.read())
                f.flush()
                os.fsync(f.fileno())
            os.ftruncate(fd, good_end)
            os.fsync(fd)
        j.torn_bytes = torn
        return j

    def _apply(self, rec: dict) -> None:
        """Fold one record into the bounded in-memory state."""
        self.records.append(rec)
        kind = rec.get("type")
        self.counts[kind] += 1
        self._fault = _latched_after(self._fault, rec)
        item = rec.get("item")
        if isinstance(item, (list, dict)):
            item = json.dumps(item, sort_keys=True)  # a hand-edited record: a key, not a crash
        if isinstance(item, int) and not isinstance(item, bool):
            self._max_item = max(self._max_item, item)
        if kind == "final":
            self.outcomes[rec.get("outcome")] += 1
            self._open_items.pop(item, None)
        elif kind == "pre_sort":
            self._open_items[item] = rec
        elif kind == "item" and item not in self._open_items:
            self._open_items[item] = rec

    def append(self, rec: dict[str, Any]) -> dict:
        if self._fd is None:
            raise JournalError(f"journal {self.path}: closed")
        if self._broken:
            raise JournalWriteError(f"journal {self.path}: {self._broken}; nothing more is written until the "
                                    "service restarts (the restart cuts the torn tail)", None, False)
        line = _encode(rec)
        start = os.fstat(self._fd).st_size  # the last good record ends here
        try:
            written = 0
            while written < len(line):
                n = os.write(self._fd, line[written:])
                if n <= 0:
                    raise OSError(errno.EIO, "write wrote nothing")
                written += n
            os.fsync(self._fd)  # the record is durable before the caller moves anything
        except OSError as exc:
            self._cut_back(start, rec, exc)
        self._apply(rec)
        return rec

    def _cut_back(self, start: int, rec: dict, exc: OSError) -> None:
        """A write or fsync failed: remove whatever part of the record landed, then raise."""
        what = f"writing a {rec.get('type', '?')} record failed ({exc.strerror or exc})"
        try:
            os.ftruncate(self._fd, start)
            os.fsync(self._fd)
        except OSError as exc2:
            self._broken = (f"a failed write could not be cut back to byte {start} ({exc2.strerror or exc2}); "
                            "the file may end in a partial record")
            raise JournalWriteError(f"{what}; {self._broken} (journal {self.path})", exc.errno, False) from exc
        raise JournalWriteError(f"{what}; the partial record was cut back to the last good record (byte "
                                f"{start}), the journal stays clean (journal {self.path})", exc.errno, True) from exc

    def close(self) -> None:
        if self._fd is not None:
            try:
                os.fsync(self._fd)
            except OSError:
                pass  # every append was fsynced already; a failing disk must not block the close
            os.close(self._fd)
            self._fd = None

    @property
    def closed(self) -> bool:
        return self._fd is None

    def __enter__(self) -> "Journal":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- queries (bounded state; the whole history is in the file) -----------------------

    def items(self) -> Iterator[dict]:
        """Every final record, streamed from the file."""
        return (r for r in iter_records(self.path) if r.get("type") == "final")

    def unresolved_items(self) -> list[dict]:
        """Items without a final record: the last ``pre_sort`` (stopped between telling the gate
        and its ack) or ``item`` record (stopped before a decision) of each, in item order."""
        return [self._open_items[k] for k in sorted(self._open_items, key=_item_order)]

    def next_item_number(self) -> int:
        return self._max_item + 1

    def latched_fault(self) -> dict | None:
        """The last fault record not followed by a fault_cleared record."""
        return self._fault


def _item_order(k: Any) -> tuple:
    return (0, k, "") if isinstance(k, int) else (1, 0, str(k))  # a hand-edited journal may hold odd ids


def _open_state_file(path: Path, flags: int, log: Callable[[str], None] | None) -> tuple[int, bool, int | None]:
    """A descriptor on ``path`` (``flags`` | O_APPEND), the file created if missing. One created
    here gets STATE_FILE_MODE whatever the umask; an existing one more open than that is tightened
    and ``log`` says so (default: stderr, the service's log), or refused (JournalError) if it
    cannot be. Returns (fd, created, the mode it had before tightening or None)."""
    try:
        fd = os.open(path, flags | os.O_APPEND | os.O_CREAT | os.O_EXCL, STATE_FILE_MODE)
        created = True
    except FileExistsError:
        fd = os.open(path, flags | os.O_APPEND)
        created = False
    tightened = None
    try:
        if created:
            os.fchmod(fd, STATE_FILE_MODE)  # os.open's mode went through the umask
        else:
            tightened = _tighten(fd, path)
    except BaseException:
        os.close(fd)
        raise
    if tightened is None:
        return fd, created, None
    (log or _stderr_log)(f"journal {path}: mode was {tightened[0]:04o} (readable or writable by others); "
                         f"tightened to {tightened[1]:04o}")
    return fd, created, tightened[0]


def _tighten(fd: int, path: Path) -> tuple[int, int] | None:
    """Remove every permission bit an existing state file has beyond STATE_FILE_MODE (never adds
    one). Returns (old, new) mode when it changed anything; refuses (JournalError) when it cannot."""
    import stat

    old = stat.S_IMODE(os.fstat(fd).st_mode)
    new = old & STATE_FILE_MODE
    if new == old:
        return None
    try:
        os.fchmod(fd, new)
    except OSError as exc:
        raise JournalError(f"journal {path}: mode {old:04o} lets other users read or change the record of "
                           f"every decision, and it cannot be tightened ({exc.strerror or exc}); run "
                           f"`chmod {new:o} {path}` as its owner") from exc
    return old, new


def _stderr_log(msg: str) -> None:
    import sys

    print(f"vs2t-edge: {msg}", file=sys.stderr, flush=True)


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)

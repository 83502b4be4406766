"""The decision journal: append-only JSON lines, each fsynced before the call returns.

One line per record: ``{"crc": <crc32 of the body>, "rec": {...}}``. A record is on disk when
``append`` returns (write + flush + fsync of the file; the folder is fsynced once on creation),
so the cell writes the decision *before* telling the gate, and a power cut leaves either the
whole record or a torn last line. ``Journal.open`` reads the file back, detects a torn or
corrupt last line (no newline, bad JSON or bad CRC), moves those bytes to ``<journal>.torn``
(kept for a human) and truncates the journal to its last good record.

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
"""

from __future__ import annotations

import json
import os
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator


class JournalError(RuntimeError):
    pass


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


def read_records(path: Path | str) -> list[dict]:
    """Every good record of a journal (a torn last line is ignored, not repaired)."""
    data = Path(path).read_bytes() if Path(path).exists() else b""
    records = []
    for line in data.split(b"\n"):
        rec = _decode(line) if line else None
        if rec is not None:
            records.append(rec)
    return records


@dataclass
class Journal:
    path: Path
    records: list[dict] = field(default_factory=list)
    torn_bytes: int = 0  # bytes cut off the end on open (0 when the file was clean)
    _fd: int | None = None

    @classmethod
    def open(cls, path: Path | str) -> "Journal":
        path = Path(path)
        created = not path.exists()
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o640)
        if created:
            _fsync_dir(path.parent)
        data = path.read_bytes()
        records: list[dict] = []
        good_end = 0
        pos = 0
        # Only the tail may be torn; a corrupt line in the middle is a real problem, reported.
        lines = data.split(b"\n")
        for i, line in enumerate(lines):
            is_last_piece = i == len(lines) - 1
            if is_last_piece:
                break  # bytes after the last newline: empty on a clean file, torn otherwise
            rec = _decode(line)
            if rec is None:
                rest = b"\n".join(lines[i + 1:]).strip()
                if rest:
                    os.close(fd)
                    raise JournalError(f"journal {path}: record {len(records) + 1} (byte {pos}) is corrupt "
                                       "and is not the last one; refusing to append to a damaged journal")
                break
            records.append(rec)
            pos += len(line) + 1
            good_end = pos
        torn = len(data) - good_end
        if torn:
            with open(str(path) + ".torn", "ab") as f:
                f.write(data[good_end:])
                f.flush()
                os.fsync(f.fileno())
            os.ftruncate(fd, good_end)
            os.fsync(fd)
        return cls(path=path, records=records, torn_bytes=torn, _fd=fd)

    def append(self, rec: dict[str, Any]) -> dict:
        if self._fd is None:
            raise JournalError(f"journal {self.path}: closed")
        line = _encode(rec)
        written = 0
        while written < len(line):
            written += os.write(self._fd, line[written:])
        os.fsync(self._fd)  # the record is durable before the caller moves anything
        self.records.append(rec)
        return rec

    def close(self) -> None:
        if self._fd is not None:
            os.fsync(self._fd)
            os.close(self._fd)
            self._fd = None

    @property
    def closed(self) -> bool:
        return self._fd is None

    def __enter__(self) -> "Journal":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- queries -----------------------------------------------------------------------

    def items(self) -> Iterator[dict]:
        return (r for r in self.records if r.get("type") == "final")

    def unresolved_items(self) -> list[dict]:
        """Items without a final record: the last ``pre_sort`` (stopped between telling the gate
        and its ack) or ``item`` record (stopped before a decision) of each, in item order."""
        finals = {r.get("item") for r in self.records if r.get("type") == "final"}
        last: dict = {}
        for r in self.records:
            if r.get("type") in ("item", "pre_sort") and r.get("item") not in finals:
                if r.get("type") == "pre_sort" or r.get("item") not in last:
                    last[r.get("item")] = r
        return [last[k] for k in sorted(last)]

    def next_item_number(self) -> int:
        nums = [int(r["item"]) for r in self.records if isinstance(r.get("item"), int)]
        return max(nums, default=0) + 1

    def latched_fault(self) -> dict | None:
        """The last fault record not followed by a fault_cleared record."""
        last = None
        for r in self.records:
            if r.get("type") == "fault":
                last = r
            elif r.get("type") == "fault_cleared":
                last = None
        return last


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)

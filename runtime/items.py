"""What the cell loop takes in and gives back, per piece: the item stream and the item's result.

The loop (runtime/cell.py) asks an ``ItemSource`` for the next piece (``ContinuousFeed`` on the
live cell; the simulated cell and replay have their own) and makes one ``ItemResult`` for each.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from typing import Protocol


@dataclass(frozen=True)
class Item:
    id: str  # the feeder's id for the piece (sim: "item-0007")
    truth: str | None = None  # known label in simulation/replay, never used to decide


class ItemSource(Protocol):
    def next_item(self, timeout_s: float) -> Item | None: ...  # None: nothing yet, ask again


class ContinuousFeed:
    """Live cell: the feeder presents the next piece as soon as the last one is sorted.

    Pieces are numbered from ``first_number``: the daemon passes the journal's next item number,
    so a restarted service goes on where the last one stopped instead of naming the next piece
    ``piece-000001`` again (two pieces with one id would make the journal ambiguous). ``prefix``
    names them (``piece``): a recording's own prefix keeps its ids out of the live journal's, so a
    label given a recorded piece can never name a live one (runtime/record_cli.py)."""

    def __init__(self, limit: int | None = None, first_number: int = 1, prefix: str = "piece") -> None:
        self.limit, self.count, self.first_number, self.prefix = limit, 0, first_number, prefix

    def next_item(self, timeout_s: float) -> Item | None:
        if self.limit is not None and self.count >= self.limit:
            time.sleep(min(timeout_s, 0.05))
            return None
        self.count += 1
        return Item(id=f"{self.prefix}-{self.first_number + self.count - 1:06d}")

    def exhausted(self) -> bool:
        return self.limit is not None and self.count >= self.limit


@dataclass
class ItemResult:
    item: Item
    label: str
    bin: int
    outcome: str  # sorted | rejected_fault | unknown_outcome (gate ack lost) | aborted
    presses: int
    confidence: float
    stopped_by: str
    skipped_frames: int
    latency_ms: list[float] = field(default_factory=list)  # model time per press
    item_s: float = 0.0


def summary_json(results: list[ItemResult]) -> str:
    return json.dumps([r.__dict__ | {"item": r.item.id} for r in results], default=str)

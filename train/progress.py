"""Progress on stderr (``Line``): feature extraction and tail fine-tuning (``features.py``) and
the long training loops (``steps``: generator, classifiers, every compared method's fit),
``label: step i/n (elapsed s, ~left s)``. On a terminal it is one line rewritten in place
(carriage return), erased when a loop ends so the per-method log lines stay readable. Anywhere
else (a log file, a pipe) carriage returns would pile up into one very long line, so it is plain
lines instead: a loop's first step, then one line each time it passes another tenth.

The loops (``steps``) show it only when stderr is a terminal; ``VS2T_PROGRESS=1`` forces it (a
log file, a test), ``VS2T_PROGRESS=0`` silences it. It only prints: it draws no random numbers
and touches no tensor, so a seeded fit gives the same weights with and without it
(tests/test_train.py).
"""

from __future__ import annotations

import os
import sys
import time
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")
ENV = "VS2T_PROGRESS"
MIN_INTERVAL_S = 0.5  # redraw at most twice a second (and always at the first and last step)
PLAIN_LINES = 10  # off a terminal, a plain line per tenth of a loop


def _stderr_is_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stream
        return False


def enabled() -> bool:
    """``VS2T_PROGRESS`` "1"/"0" if set, else whether stderr is a terminal."""
    flag = os.environ.get(ENV, "").strip()
    if flag in ("0", "1"):
        return flag == "1"
    return _stderr_is_terminal()


class Line:
    """One progress line on stderr. On a terminal (``terminal=None``: whether stderr is one) it is
    rewritten in place, a shorter message padded over a longer earlier one. Elsewhere each
    ``draw`` whose ``fraction`` (0..1 of the loop done) enters a new tenth is a plain line, and so
    is one without a fraction; the others are held back, and ``keep`` writes the last of them."""

    def __init__(self, terminal: bool | None = None) -> None:
        self.terminal = _stderr_is_terminal() if terminal is None else terminal
        self.width = 0
        self.tenth = -1  # plain lines: the last tenth of the loop written
        self.held = ""  # plain lines: the last message not written

    def draw(self, msg: str, fraction: float | None = None) -> None:
        if self.terminal:
            self.width = max(self.width, len(msg))
            print(f"\r{msg:<{self.width}}", end="", file=sys.stderr, flush=True)
            return
        tenth = self.tenth + 1 if fraction is None else int(fraction * PLAIN_LINES + 1e-9)
        if tenth > self.tenth:
            print(msg, file=sys.stderr, flush=True)
            self.tenth, self.held = tenth, ""
        else:
            self.held = msg

    def erase(self) -> None:
        if self.terminal and self.width:
            print(f"\r{'':<{self.width}}\r", end="", file=sys.stderr, flush=True)
        self.width, self.tenth, self.held = 0, -1, ""  # plain lines stay written: a log keeps them

    def keep(self) -> None:
        """Leave the last message standing and move on to a new line."""
        if self.terminal:
            print(file=sys.stderr)
        elif self.held:
            print(self.held, file=sys.stderr, flush=True)
        self.width, self.tenth, self.held = 0, -1, ""


def steps(it: Iterable[T], total: int, label: str) -> Iterator[T]:
    """Yield ``it``'s items unchanged, drawing ``label: step i/total`` on stderr when ``enabled()``."""
    if not enabled() or total <= 0:
        yield from it
        return
    t0 = last = time.monotonic()
    line = Line()
    for done, item in enumerate(it):  # done = steps finished before this one
        now = time.monotonic()
        if done + 1 >= total:
            # erased before the last step is handed out: a consumer that stops calling next()
            # at exactly ``total`` items (generators_modern's critic loops) still leaves a clean line
            line.erase()
        elif done == 0 or now - last >= MIN_INTERVAL_S or not line.terminal:  # plain: Line keeps tenths
            el = now - t0
            left = f", ~{el / done * (total - done):.0f} s left" if done else ""
            line.draw(f"{label}: step {done + 1}/{total} ({el:.0f} s{left})", done / total)
            last = now
        yield item
    line.erase()


__all__ = ["ENV", "Line", "enabled", "steps"]

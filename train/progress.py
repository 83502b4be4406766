"""Progress on stderr (``runtime.progress.Line``): feature extraction and tail fine-tuning (``features.py``) and
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
import time
from typing import Iterable, Iterator, TypeVar

from vs2t_edge.runtime.progress import Line, stderr_is_terminal

T = TypeVar("T")
ENV = "VS2T_PROGRESS"
MIN_INTERVAL_S = 0.5  # redraw at most twice a second (and always at the first and last step)


def enabled() -> bool:
    """``VS2T_PROGRESS`` "1"/"0" if set, else whether stderr is a terminal."""
    flag = os.environ.get(ENV, "").strip()
    if flag in ("0", "1"):
        return flag == "1"
    return stderr_is_terminal()


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

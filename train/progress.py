"""Progress of the long training loops (generator, classifiers, every compared method's fit) on
stderr, in the carriage-return style of feature extraction (``features.py``): one line rewritten
in place, ``label: step i/n (elapsed s, ~left s)``, erased when the loop ends so the per-method
log lines stay readable.

Shown only when stderr is a terminal; ``VS2T_PROGRESS=1`` forces it (a log file, a test),
``VS2T_PROGRESS=0`` silences it. It only prints: it draws no random numbers and touches no
tensor, so a seeded fit gives the same weights with and without it (tests/test_train.py).
"""

from __future__ import annotations

import os
import sys
import time
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")
ENV = "VS2T_PROGRESS"
MIN_INTERVAL_S = 0.5  # redraw at most twice a second (and always at the first and last step)


def enabled() -> bool:
    """``VS2T_PROGRESS`` "1"/"0" if set, else whether stderr is a terminal."""
    flag = os.environ.get(ENV, "").strip()
    if flag in ("0", "1"):
        return flag == "1"
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stream
        return False


def steps(it: Iterable[T], total: int, label: str) -> Iterator[T]:
    """Yield ``it``'s items unchanged, drawing ``label: step i/total`` on stderr when ``enabled()``."""
    if not enabled() or total <= 0:
        yield from it
        return
    t0 = last = time.monotonic()
    width = 0
    for done, item in enumerate(it):  # done = steps finished before this one
        now = time.monotonic()
        if done + 1 >= total:
            # erased before the last step is handed out: a consumer that stops calling next()
            # at exactly ``total`` items (generators_modern's critic loops) still leaves a clean line
            if width:
                print(f"\r{'':<{width}}\r", end="", file=sys.stderr, flush=True)
                width = 0
        elif done == 0 or now - last >= MIN_INTERVAL_S:
            el = now - t0
            left = f", ~{el / done * (total - done):.0f} s left" if done else ""
            msg = f"{label}: step {done + 1}/{total} ({el:.0f} s{left})"
            width = max(width, len(msg))
            print(f"\r{msg:<{width}}", end="", file=sys.stderr, flush=True)
            last = now
        yield item
    if width:
        print(f"\r{'':<{width}}\r", end="", file=sys.stderr, flush=True)


__all__ = ["ENV", "enabled", "steps"]

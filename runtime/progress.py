"""One progress line on stderr (``Line``) for every long job that reports as it goes: synth,
training, bench, calibrate-threshold, the comparison's tools.

On a terminal it is one line rewritten in place (carriage return). Anywhere else (a log file, a
pipe, the demo's captured output) carriage returns pile up into one very long line, so it is
plain lines instead: the first message, then one each time the job passes another tenth.
Standard library only: the cell's room, so that sim/, train/ and runtime/ all draw it the same way.
"""

from __future__ import annotations

import sys

PLAIN_LINES = 10  # off a terminal, a plain line per tenth of a job


def stderr_is_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stream
        return False


class Line:
    """One progress line on stderr. On a terminal (``terminal=None``: whether stderr is one) it is
    rewritten in place, a shorter message padded over a longer earlier one. Elsewhere each
    ``draw`` whose ``fraction`` (0..1 of the loop done) enters a new tenth is a plain line, and so
    is one without a fraction; the others are held back, and ``keep`` writes the last of them."""

    def __init__(self, terminal: bool | None = None) -> None:
        self.terminal = stderr_is_terminal() if terminal is None else terminal
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


__all__ = ["PLAIN_LINES", "Line", "stderr_is_terminal"]

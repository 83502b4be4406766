"""sd_notify without libsystemd: one datagram per message on $NOTIFY_SOCKET.

systemd's protocol (sd_notify(3)): newline-separated ``KEY=VALUE`` assignments sent as one
datagram to the AF_UNIX socket named in ``NOTIFY_SOCKET``; a leading ``@`` means the abstract
namespace (a NUL byte). Without the variable (run by hand, tests) every call is a no-op that
still records the message, so the loop never needs to know whether systemd is there.

The watchdog interval comes from ``WATCHDOG_USEC`` (set by systemd when the unit has
WatchdogSec=); ``watchdog_due()`` says when half of it has passed, the usual ping rate.
"""

from __future__ import annotations

import os
import socket
import time
from collections import deque

# The last messages, for tests and for what an operator asks about; the daemon runs for months,
# so the record is a window (the soak showed an unbounded list as its only remaining RSS growth).
KEEP_MESSAGES = 256


class Notifier:
    def __init__(self, address: str | None = None, clock=time.monotonic) -> None:
        address = os.environ.get("NOTIFY_SOCKET") if address is None else address
        self.address = address or None
        self.sent: deque[str] = deque(maxlen=KEEP_MESSAGES)  # the last messages, also without a socket
        self.n_sent = 0  # every message ever, for counters
        self._sock: socket.socket | None = None
        self._clock = clock
        usec = os.environ.get("WATCHDOG_USEC", "")
        pid = os.environ.get("WATCHDOG_PID", "")
        for_us = not pid or pid == str(os.getpid())
        self.watchdog_s = int(usec) / 1e6 if usec.isdigit() and for_us else None
        self._last_ping = -1e18
        self.status_line = ""

    def _send(self, message: str) -> bool:
        self.sent.append(message)
        self.n_sent += 1
        if not self.address:
            return False
        addr = self.address
        if addr.startswith("@"):
            addr = "\0" + addr[1:]
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(message.encode("utf-8"), addr)
            return True
        except OSError:
            return False  # a lost notification must never stop the cell

    def ready(self, status: str = "") -> None:
        self._send("READY=1" + (f"\nSTATUS={status}" if status else ""))
        if status:
            self.status_line = status

    def status(self, text: str) -> None:
        text = text.replace("\n", " ")
        if text != self.status_line:
            self.status_line = text
            self._send(f"STATUS={text}")

    def watchdog(self) -> None:
        self._last_ping = self._clock()
        self._send("WATCHDOG=1")

    def watchdog_due(self) -> bool:
        interval = self.watchdog_s if self.watchdog_s else 5.0
        return self._clock() - self._last_ping >= interval / 2

    def ping_if_due(self) -> None:
        if self.watchdog_due():
            self.watchdog()

    def stopping(self, status: str = "") -> None:
        self._send("STOPPING=1" + (f"\nSTATUS={status}" if status else ""))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

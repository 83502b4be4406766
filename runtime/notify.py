"""sd_notify without libsystemd: one datagram per message on $NOTIFY_SOCKET.

systemd's protocol (sd_notify(3)): newline-separated ``KEY=VALUE`` assignments sent as one
datagram to the AF_UNIX socket named in ``NOTIFY_SOCKET``; a leading ``@`` means the abstract
namespace (a NUL byte). Without the variable (run by hand, tests) every call is a no-op that
still records the message, so the loop never needs to know whether systemd is there.

The watchdog interval comes from ``WATCHDOG_USEC`` (set by systemd when the unit has
WatchdogSec=); ``watchdog_due()`` says when a tenth of it has passed (``PING_FRACTION``; the
usual half let a ping due just before a long step arrive after the watchdog had fired), and
``bounded_wait(bound_s)`` keeps pinging while the loop waits in a device call that ends by itself
within ``bound_s`` - never longer (runtime/budget.py).
"""

from __future__ import annotations

import os
import socket
import threading
import time
from collections import deque
from contextlib import contextmanager

# The last messages, for tests and for what an operator asks about; the daemon runs for months,
# so the record is a window (the soak showed an unbounded list as its only remaining RSS growth).
KEEP_MESSAGES = 256
PING_FRACTION = 0.1  # ping once this fraction of the watchdog interval has passed


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
        self._lock = threading.RLock()  # re-entrant: the SIGTERM handler sends from the main thread

    def _send(self, message: str) -> bool:
        with self._lock:  # the bounded_wait feeder sends from its own thread
            return self._send_locked(message)

    def _send_locked(self, message: str) -> bool:
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
        return self._clock() - self._last_ping >= interval * PING_FRACTION

    @contextmanager
    def bounded_wait(self, bound_s: float | None):
        """The loop waits in a call that its device ends within ``bound_s`` (the arm worker is
        ended, the grab times out): feed the watchdog meanwhile, for at most that long. A call
        hung past its own bound is a hung loop - the pings stop and systemd does its job.
        ``None``: no bound known, nothing is leased (just a ping if due)."""
        self.ping_if_due()
        if not bound_s or not self.watchdog_s or not self.address:
            yield
            return
        until = time.monotonic() + bound_s
        done = threading.Event()

        def feed() -> None:
            while not done.wait(self.watchdog_s * PING_FRACTION) and time.monotonic() < until:
                self.watchdog()

        feeder = threading.Thread(target=feed, name="watchdog-lease", daemon=True)
        feeder.start()
        try:
            yield
        finally:
            done.set()
            feeder.join()
            self.ping_if_due()

    def ping_if_due(self) -> None:
        if self.watchdog_due():
            self.watchdog()

    def stopping(self, status: str = "") -> None:
        self._send("STOPPING=1" + (f"\nSTATUS={status}" if status else ""))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

"""Host driver for the sorting gate over pyserial (docs/protocol.md).

Stop-and-wait: one request on the wire at a time (``_lock``), retransmitted with the same SEQ
on timeout at most ``retries`` times. A background thread sends HEARTBEATs so the MCU's
watchdog stays fed; it shares the lock and skips a beat when a request is on the wire.
Every reply carries the MCU's boot id, so a reboot is noticed on the next exchange.

Any pyserial URL works: a device path (``/dev/ttyACM0``, a pty's ``/dev/pts/N``), ``loop://``,
``socket://host:port``. Errors are ``GateClientError`` with ``kind`` in
timeout / nak / jam / fault_latched / link / bad_ack; ``runtime.gate`` turns them into the runtime's
``GateError``. This module imports pyserial and the stdlib only.
"""

from __future__ import annotations

import collections
import logging
import secrets
import threading
import time
from dataclasses import dataclass

import serial

from vs2t_edge.firmware_bridge import protocol as p

log = logging.getLogger(__name__)

FAULT_REPORTS_KEPT = 64  # the most recent unsolicited FAULT frames a client keeps

# bad_ack: an ACK of a SORT or CLEAR (right CRC, SEQ and type) that reports something else than
# what was asked - another bin, a moving or latched gate, a fault. The flap's position is then
# what the gate says, not what the host asked: never a success.
ERROR_KINDS = ("timeout", "nak", "jam", "fault_latched", "link", "bad_ack")


class GateClientError(RuntimeError):
    """A gate request failed; ``kind`` is one of ERROR_KINDS, ``reason`` the NAK reason name.
    ``maybe_executed``: the request went out whole and the gate may have acted on it (a link lost
    while waiting for its reply, or a reboot seen after an unanswered try) - for a SORT, the flap
    may be at the bin. A timeout always may have been executed. A NAK of a gate that stays ready
    was not; one of a gate latched in fault (a jam: the flap stuck between the last bin it reached,
    ``reported_bin``, and the bin asked, its servo let go; latched, it refuses the move to reject
    and does not fail safe) leaves the piece where that flap sends it, so it counts as maybe executed."""

    def __init__(self, message: str, *, kind: str, reason: str = "", reported_bin: int | None = None,
                 maybe_executed: bool = False, reported_state: str | None = None) -> None:
        super().__init__(message)
        assert kind in ERROR_KINDS, kind
        self.kind = kind
        self.reason = reason
        # where the gate's reply (a contradicting ACK, a NAK) says the flap is, and the gate's state
        # then: a NAK of a latched gate leaves the flap there - it refuses the move to reject too
        self.reported_bin = reported_bin
        self.reported_state = reported_state
        self.maybe_executed = maybe_executed


@dataclass(frozen=True)
class GateReport:
    """The gate's answer to STATUS, in words."""

    state: str  # ready, busy, fault, failsafe
    bin: int
    fault: str  # "", heartbeat_lost, jam, boot
    n_bins: int
    boot_id: int
    uptime_ms: int
    sorts_done: int
    seq: int


def _state_name(code: int) -> str:
    return p.STATE_NAMES.get(code, f"unknown({code})")


def _fault_name(code: int) -> str:
    return p.FAULT_NAMES.get(code, f"unknown({code})")


def timing_problems(timeout_s: float, retries: int,
                    heartbeat_period_s: float | None = p.HEARTBEAT_PERIOD_S) -> list[str]:
    """Every constraint :class:`GateClient` puts on its timing, in words ([] = accepted).

    The one source for the driver and for config validation (runtime/config.py), so that a
    config ``validate-config`` passes never makes the driver refuse to start."""
    problems = []
    if not timeout_s > 0 or retries < 0:
        problems.append(f"timeout_s must be > 0 and retries >= 0 (got {timeout_s}, {retries})")
    elif heartbeat_period_s and timeout_s + heartbeat_period_s >= p.HEARTBEAT_TIMEOUT_MS / 1000:
        # While a request waits for its reply no heartbeat goes out; the gate must not time
        # out in that silence.
        problems.append(f"timeout_s + heartbeat_period_s ({timeout_s} + {heartbeat_period_s} s) must stay "
                        f"under the gate's heartbeat timeout of {p.HEARTBEAT_TIMEOUT_MS / 1000} s")
    return problems


MOVE_TIMEOUT_S = p.MOVE_TIMEOUT_MS / 1000  # the longest a working flap may take to reach a bin (then: a jam)


def move_problems(timeout_s: float, move_time_s: float = MOVE_TIMEOUT_S) -> list[str]:
    """Why a try of ``timeout_s`` is too short for the gate's flap, in words ([] = long enough).

    The gate ACKs a SORT or CLEAR only once the flap reached its bin (docs/protocol.md), and a
    retransmission is ignored while it moves: a try no longer than the move times out, and so does
    each retransmission of it until the move ends - the first sort (or connect's CLEAR) a gate
    fault. A working flap may take up to the firmware's MOVE_TIMEOUT. The cell config refuses such a
    ``timeout_s`` (runtime/config.py); the driver itself takes it, for simulated gates whose flap
    moves faster (``start_simulated_gate(move_time_ms=...)``)."""
    if timeout_s <= move_time_s:
        return [f"not longer than the flap's move time of up to {move_time_s:g} s (the gate's MOVE_TIMEOUT): the "
                f"gate ACKs a sort only when the flap is there, so a try of {timeout_s:g} s times out on a slow move "
                "and the gate faults at the first piece"]
    return []


WRITE_TIMEOUT_S = 0.25  # a frame is ~10 bytes: a write the line has not taken by then has failed
HEARTBEAT_STOP_SLACK_S = 0.5  # stop_heartbeat(): the thread's last look at its stop flag


def try_worst_case_s(timeout_s: float) -> float:
    """One try of a request: the write (bounded by ``WRITE_TIMEOUT_S``), then ``timeout_s`` for the reply."""
    return WRITE_TIMEOUT_S + timeout_s


def request_worst_case_s(timeout_s: float, retries: int,
                         heartbeat_period_s: float | None = p.HEARTBEAT_PERIOD_S) -> float:
    """Longest a caller of one request (``sort``, ``status``, ``clear``) waits before it returns
    or fails, as the caller sees it: requests are stop-and-wait (``_lock``), so it may first wait
    behind a heartbeat already on the wire (one try: the background heartbeat never
    retransmits), then its own first try and every retransmission. The one source for the
    watchdog budget (runtime/budget.py) and the driver (tests/test_gate_budget.py measures it)."""
    behind = try_worst_case_s(timeout_s) if heartbeat_period_s else 0.0
    return behind + (retries + 1) * try_worst_case_s(timeout_s)


def heartbeat_stop_s(timeout_s: float) -> float:
    """``stop_heartbeat()``'s longest wait: a heartbeat on the wire finishes its one try."""
    return try_worst_case_s(timeout_s) + HEARTBEAT_STOP_SLACK_S


def to_reject_worst_case_s(timeout_s: float, retries: int,
                           heartbeat_period_s: float | None = p.HEARTBEAT_PERIOD_S) -> float:
    """``to_reject()``'s longest wait: the SORT to reject and, when it fails, stopping the
    heartbeats so the gate fails safe on its own."""
    stop = heartbeat_stop_s(timeout_s) if heartbeat_period_s else 0.0
    return request_worst_case_s(timeout_s, retries, heartbeat_period_s) + stop


class GateClient:
    """Thread-safe host side of the gate protocol. ``connect()`` before use; a context manager."""

    def __init__(self, port: str, *, timeout_s: float = 0.5, retries: int = 3,
                 heartbeat_period_s: float | None = p.HEARTBEAT_PERIOD_S, baudrate: int = p.BAUDRATE,
                 arm_latches: tuple[str, ...] = ("boot",)) -> None:
        problems = timing_problems(timeout_s, retries, heartbeat_period_s)
        if problems:
            raise ValueError("; ".join(problems))
        self.port = port
        self.timeout_s = timeout_s
        self.retries = retries
        self.heartbeat_period_s = heartbeat_period_s
        self.baudrate = baudrate
        # Latches connect() clears by itself: by default only the power-on one (see protocol.md).
        self.arm_latches = arm_latches
        self._serial: serial.SerialBase | None = None
        self._reader = p.FrameReader()
        self._pending: collections.deque[p.Frame] = collections.deque()
        self._lock = threading.RLock()
        # A random start, and a STATUS as the first request (connect), keep a new session's first
        # SORT from matching the previous session's last one in the MCU's duplicate memory.
        self._seq = secrets.randbelow(256)
        self._boot_id: int | None = None
        self._reboot: tuple[int, int] | None = None  # (old, new) boot id once a reboot is seen
        self._hb_stop = threading.Event()
        self._hb_thread: threading.Thread | None = None
        # to_reject() failed and stopped the heartbeats: the gate is left to fail safe on its own,
        # and routes nothing after that until clear() or a new connect()
        self.failing_safe = False
        self.last_state = ""
        self.last_bin = p.REJECT_BIN  # the flap's bin in the gate's last reply or report
        self.armed_from = ""  # the latch connect() cleared, if any
        self.last_fault = ""
        # Unsolicited FAULT frames, the most recent FAULT_REPORTS_KEPT in order: a gate (or a line)
        # that floods FAULT frames must not grow the host's memory; the rest are only counted.
        self.fault_reports: collections.deque[p.FaultReport] = collections.deque(maxlen=FAULT_REPORTS_KEPT)
        self.fault_reports_seen = 0
        self._last_logged_report: p.FaultReport | None = None
        self.retransmissions = 0
        self.bad_acks = 0  # ACKs of SORT/CLEAR that contradicted the request (_require_ack_of)
        self.heartbeats_ok = 0
        self.heartbeat_errors = 0

    # --- lifecycle -----------------------------------------------------------------------------
    def connect(self) -> GateReport:
        with self._lock:
            if self._serial is not None:
                return self.status()
            try:
                self._serial = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.01,
                                                     write_timeout=WRITE_TIMEOUT_S)
            except (serial.SerialException, OSError, ValueError) as exc:
                raise GateClientError(f"cannot open the gate's serial port {self.port}: {exc}",
                                      kind="link") from exc
            self._serial.reset_input_buffer()
            self._reader = p.FrameReader()
            self._pending.clear()
            try:
                # The first request of a session is a STATUS: it also resets the MCU's duplicate memory.
                report = self.status()
                self._boot_id = report.boot_id
                self._reboot = None
                if report.state in ("fault", "failsafe") and report.fault in self.arm_latches:
                    log.info("gate latched (%s) at connect; arming it", report.fault)
                    self.armed_from = report.fault
                    self.clear()
                    report = self.status()
            except GateClientError:
                self.disconnect()
                raise
            self.failing_safe = False
        self.start_heartbeat()
        return report

    def disconnect(self) -> None:
        self.stop_heartbeat()
        with self._lock:
            if self._serial is not None:
                try:
                    self._serial.close()
                except (serial.SerialException, OSError):
                    pass
                self._serial = None

    @property
    def connected(self) -> bool:
        return self._serial is not None

    def __enter__(self) -> "GateClient":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()

    # --- heartbeat -------------------------------------------------------------------------------
    def start_heartbeat(self) -> None:
        if not self.heartbeat_period_s or (self._hb_thread and self._hb_thread.is_alive()):
            return
        self._hb_stop.clear()
        self.failing_safe = False
        self._hb_thread = threading.Thread(target=self._heartbeat_loop, name="gate-heartbeat", daemon=True)
        self._hb_thread.start()

    def stop_heartbeat(self) -> None:
        self._hb_stop.set()
        thread, self._hb_thread = self._hb_thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=heartbeat_stop_s(self.timeout_s))

    def _heartbeat_loop(self) -> None:
        logged_failure, failing_since = False, 0.0
        while not self._hb_stop.wait(self.heartbeat_period_s):
            if not self._lock.acquire(blocking=False):
                continue  # a request is on the wire; it feeds the watchdog too
            try:
                if self._serial is None:
                    return
                self._request(p.HEARTBEAT, b"", retries=0)
                self.heartbeats_ok += 1
                if logged_failure:
                    log.warning("gate heartbeat answered again after %.1f s", time.monotonic() - failing_since)
                    logged_failure, failing_since = False, 0.0
            except GateClientError as exc:
                self.heartbeat_errors += 1
                failing_since = failing_since or time.monotonic()
                if not logged_failure:  # once per outage, not four times a second
                    log.warning("gate heartbeat failed: %s", exc)
                    logged_failure = True
            finally:
                self._lock.release()

    # --- requests --------------------------------------------------------------------------------
    def sort(self, bin_index: int) -> None:
        """Route the next item to ``bin_index``; returns once the gate confirmed the flap is there."""
        if not 0 <= bin_index <= 255:
            raise GateClientError(f"bin {bin_index} is not a gate bin (0..255)", kind="nak", reason="bad_bin")
        with self._lock:
            self._refuse_after_reboot()
            tries_before = self.retransmissions
            reply = self._request(p.SORT, bytes((bin_index,)))
            try:
                self._refuse_after_reboot()  # a reboot explains a NAK better than the NAK does
            except GateClientError as exc:
                # an unanswered earlier try of this SORT may have been executed before the reboot
                exc.maybe_executed = self.retransmissions > tries_before
                raise
            if isinstance(reply, p.Nak):
                raise self._nak_error(reply, f"sort to bin {bin_index}")
            self._require_ack_of(reply, bin_index, f"sort to bin {bin_index}")

    def status(self) -> GateReport:
        with self._lock:
            seq = self._next_seq()
            reply = self._request(p.STATUS, b"", seq=seq)
            if not isinstance(reply, p.StatusReply):
                raise self._nak_error(reply, "status") if isinstance(reply, p.Nak) else \
                    GateClientError(f"gate answered STATUS with {reply}", kind="link")
            return GateReport(_state_name(reply.state), reply.bin, _fault_name(reply.fault), reply.n_bins,
                              reply.boot_id, reply.uptime_ms, reply.sorts_done, seq)

    def heartbeat(self) -> None:
        """One HEARTBEAT now, retransmitted like any request (the background thread sends its own)."""
        with self._lock:
            self._request(p.HEARTBEAT, b"")

    def clear(self) -> None:
        """Clear a latched fault (and acknowledge a reboot): the flap goes back to reject (bin 0); on
        a READY gate a harmless no-op."""
        with self._lock:
            # CLEAR of a latched gate ACKs once the flap is back at reject; CLEAR of a READY gate is a
            # harmless ACK with the flap where it was (protocol.md). The host's last word from the
            # gate may be a beat old, so reject is always a right answer.
            allowed = (p.REJECT_BIN,) + ((self.last_bin,) if self.last_state == "ready" else ())
            reply = self._request(p.CLEAR, b"", check_reboot=False)
            if isinstance(reply, p.Nak):
                raise self._nak_error(reply, "clear")
            expected = reply.bin if reply.bin in allowed else p.REJECT_BIN
            self._require_ack_of(reply, expected, "clear")
            self._boot_id = reply.boot_id
            self._reboot = None
            self.failing_safe = False
        self.start_heartbeat()

    def to_reject(self) -> None:
        """Best effort, never raises: route to reject; if that fails, stop heartbeats so the MCU's
        own watchdog puts the flap at reject within HEARTBEAT_TIMEOUT."""
        try:
            self.sort(p.REJECT_BIN)
        except Exception as exc:  # noqa: BLE001 - must not raise, whatever went wrong
            log.warning("gate to reject failed (%s); stopping heartbeats so the gate fails safe", exc)
            self.stop_heartbeat()
            self.failing_safe = True

    # --- internals -----------------------------------------------------------------------------
    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _refuse_after_reboot(self) -> None:
        if self._reboot is not None:
            old, new = self._reboot
            raise GateClientError(f"the gate controller rebooted (boot id {old} -> {new}); the item in flight "
                                  "may not have been routed; clear the gate to continue", kind="link")

    def _require_ack_of(self, ack: p.Ack, bin_index: int, what: str) -> None:
        """The ACK of a SORT or CLEAR is the gate's word that the flap reached ``bin_index`` and the
        gate is READY with no fault. An ACK reporting anything else contradicts the request - the
        flap is where the gate says, or nobody knows where - so it is a fault, never a success."""
        wrong = []
        if ack.bin != bin_index:
            wrong.append(f"the flap at bin {ack.bin}")
        if ack.state != p.STATE_READY:
            wrong.append(f"state {_state_name(ack.state)}")
        if ack.fault != p.FAULT_NONE:
            wrong.append(f"fault {_fault_name(ack.fault)}")
        if wrong:
            self.bad_acks += 1
            log.error("%s: the gate's ACK reports %s", what, ", ".join(wrong))
            raise GateClientError(f"{what}: the gate acknowledged it but reports {', '.join(wrong)} - the ACK "
                                  f"contradicts the request, so the flap's position is not known",
                                  kind="bad_ack", reason="contradicting_ack", reported_bin=ack.bin,
                                  reported_state=_state_name(ack.state))

    def _nak_error(self, nak: p.Nak, what: str) -> GateClientError:
        reason = p.NAK_NAMES.get(nak.reason, f"unknown({nak.reason})")
        kind = p.NAK_ERROR_KIND.get(nak.reason, "nak")
        words = {
            "bad_bin": "the gate has no such bin",
            "bad_length": "the gate did not understand the message length",
            "unknown_type": "the gate does not know this message",
            "busy": "the gate is still moving",
            "latched": f"the gate is latched in {_state_name(nak.state)} ({_fault_name(nak.fault)}) "
                       "and refuses to route until cleared",
            "jam": "the flap jammed and did not reach the bin; clear the jam, then clear the gate",
            "jam_present": "the flap is still blocked; free it before clearing",
        }.get(reason, reason)
        latched = nak.state == p.STATE_FAULT  # the flap stays where it stuck (class doc)
        return GateClientError(f"{what} refused: {words}", kind=kind, reason=reason, maybe_executed=latched,
                               reported_bin=nak.bin if latched else None, reported_state=_state_name(nak.state))

    def _request(self, msg_type: int, payload: bytes, *, seq: int | None = None, retries: int | None = None,
                 check_reboot: bool = True) -> p.Ack | p.Nak | p.StatusReply:
        """Send one request and wait for its reply, retransmitting the same frame on timeout."""
        with self._lock:
            if self._serial is None:
                raise GateClientError("the gate is not connected", kind="link")
            seq = self._next_seq() if seq is None else seq
            frame = p.encode_frame(seq, msg_type, payload)
            attempts = 1 + (self.retries if retries is None else retries)
            sent = False  # a whole try went out: from then on the gate may have acted on it
            for attempt in range(attempts):
                if attempt:
                    self.retransmissions += 1
                try:
                    self._write(frame)
                    sent = True
                    reply = self._wait_reply(seq, msg_type, time.monotonic() + self.timeout_s)
                except GateClientError as exc:  # the link, lost after (or before) a try went out
                    exc.maybe_executed = sent
                    raise
                if reply is not None:
                    self._note_state(reply.state, reply.fault, reply.bin)
                    if check_reboot:
                        self._check_boot(reply.boot_id)
                    return reply
            name = p.TYPE_NAMES[msg_type]
            raise GateClientError(f"the gate did not answer {name} (seq {seq}) within {self.timeout_s:.2f} s "
                                  f"after {attempts} attempts on {self.port}", kind="timeout", maybe_executed=sent)

    def _write(self, frame: bytes) -> None:
        try:
            self._serial.write(frame)
            self._serial.flush()
        except (serial.SerialException, OSError) as exc:
            raise GateClientError(f"writing to the gate on {self.port} failed: {exc}", kind="link") from exc

    def _wait_reply(self, seq: int, msg_type: int, deadline: float) -> p.Ack | p.Nak | p.StatusReply | None:
        want = p.STATUS_REPLY if msg_type == p.STATUS else None
        while True:
            # One read can bring several frames (a NAK and its FAULT report); those after the
            # reply wait in _pending for the next look, never lost.
            self._pending.extend(self._reader.feed(self._read_some()))
            while self._pending:
                frame = self._pending.popleft()
                try:
                    reply = p.parse_reply(frame)
                except p.MessageError as exc:
                    log.warning("ignoring a malformed frame from the gate: %s", exc)
                    continue
                if isinstance(reply, p.FaultReport):
                    self._on_fault_report(reply)
                    continue
                if frame.seq != seq:
                    continue  # a late reply to an earlier request, or a duplicate
                if isinstance(reply, p.StatusReply):
                    if want == p.STATUS_REPLY:
                        self._drain_fault_reports()
                        return reply
                elif reply.acked_type == msg_type:
                    self._drain_fault_reports()
                    return reply
            if time.monotonic() >= deadline:
                return None

    def _drain_fault_reports(self) -> None:
        """Handle FAULT reports already received behind the reply (keeps replies queued)."""
        rest = collections.deque()
        while self._pending:
            frame = self._pending.popleft()
            if frame.type == p.FAULT:
                try:
                    self._on_fault_report(p.parse_reply(frame))
                except p.MessageError:
                    pass
            else:
                rest.append(frame)
        self._pending = rest

    def _read_some(self) -> bytes:
        try:
            return self._serial.read(max(1, self._serial.in_waiting))
        except (serial.SerialException, OSError, TypeError) as exc:
            raise GateClientError(f"reading from the gate on {self.port} failed: {exc}", kind="link") from exc

    @property
    def fault_reports_dropped(self) -> int:
        """FAULT frames received but no longer kept in ``fault_reports``."""
        return self.fault_reports_seen - len(self.fault_reports)

    def _on_fault_report(self, report: p.FaultReport) -> None:
        self.fault_reports.append(report)
        self.fault_reports_seen += 1
        self._note_state(report.state, report.fault, report.bin)
        if report != self._last_logged_report:  # a flood of the same report is one log line
            self._last_logged_report = report
            log.warning("gate reports fault %s (state %s, bin %d; %d FAULT frames so far)",
                        _fault_name(report.fault), _state_name(report.state), report.bin, self.fault_reports_seen)
        self._check_boot(report.boot_id)

    def _note_state(self, state: int, fault: int, bin_index: int) -> None:
        self.last_state = _state_name(state)
        self.last_fault = _fault_name(fault)
        self.last_bin = bin_index

    def _check_boot(self, boot_id: int) -> None:
        if self._boot_id is not None and boot_id != self._boot_id and self._reboot is None:
            self._reboot = (self._boot_id, boot_id)
            log.error("gate controller rebooted: boot id %d -> %d", self._boot_id, boot_id)

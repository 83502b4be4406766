"""The sorting gate as the cell sees it: the ``Gate`` protocol of runtime/devices.py.

* ``SerialGate`` — the live gate: the serial host driver of firmware_bridge (pyserial, any URL),
  with its faults turned into ``GateError(kind=...)``.
* ``FakeGate`` — in process, no serial line, the same latching rules as the firmware (a jam or a
  fail-safe refuses every sort until ``clear()``), with injectable faults; for fast cell tests.

The ``SerialGate`` wired to the MCU simulator over a real pty (config ``devices.gate.kind: sim``,
the demo) is ``vs2t_edge.sim.devices.simulated_serial_gate``: simulators stay out of the cell's
code, and the daemon imports it only when a config asks for it (runtime/devices.py SIMULATORS).
"""

from __future__ import annotations

import logging
import threading

from vs2t_edge.firmware_bridge import protocol as proto
from vs2t_edge.firmware_bridge.gate_client import GateClient, GateClientError, GateReport
from vs2t_edge.runtime.devices import GateError, GateStatus, NotConnectedError

log = logging.getLogger(__name__)

REJECT_BIN = proto.REJECT_BIN


def _to_gate_error(exc: GateClientError) -> GateError:
    error = GateError(str(exc), device="gate", kind=exc.kind)
    error.retryable = exc.kind == "timeout"  # one more try may help a noisy line; nothing else
    error.reported_bin = exc.reported_bin  # bad_ack: where the gate says the flap is
    return error


class SerialGate:
    """The live gate over a serial port (``/dev/ttyACM0``, ``/dev/pts/N``, ``socket://...``)."""

    def __init__(self, port: str, *, timeout_s: float = 0.5, retries: int = 3,
                 heartbeat_period_s: float = proto.HEARTBEAT_PERIOD_S,
                 arm_latches: tuple[str, ...] = ("boot",)) -> None:
        """``arm_latches``: latches connect() clears by itself. Only the power-on one by default:
        a heartbeat-lost or jam latch found at start-up waits for the operator's clear()."""
        self.port = port
        self._client = GateClient(port, timeout_s=timeout_s, retries=retries,
                                  heartbeat_period_s=heartbeat_period_s, arm_latches=arm_latches)
        self._connected = False

    def connect(self) -> None:
        try:
            self._client.connect()
        except GateClientError as exc:
            raise _to_gate_error(exc) from exc
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False
        self._client.disconnect()

    def _need_connection(self) -> None:
        if not self._connected:
            raise NotConnectedError(f"gate on {self.port} used before connect()", device="gate",
                                    kind="not_connected")

    def sort(self, bin_index: int) -> None:
        self._need_connection()
        try:
            self._client.sort(bin_index)
        except GateClientError as exc:
            raise _to_gate_error(exc) from exc

    def status(self) -> GateStatus:
        self._need_connection()
        try:
            report: GateReport = self._client.status()
        except GateClientError as exc:
            raise _to_gate_error(exc) from exc
        return GateStatus(state=report.state, bin=report.bin, fault=report.fault, seq=report.seq)

    def clear(self) -> None:
        self._need_connection()
        try:
            self._client.clear()
        except GateClientError as exc:
            raise _to_gate_error(exc) from exc

    def to_reject(self) -> None:
        if self._connected:
            self._client.to_reject()  # never raises; falls back on the MCU's watchdog

    @property
    def client(self) -> GateClient:
        return self._client

    def __enter__(self) -> "SerialGate":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()


class FakeGate:
    """In-process gate with the firmware's latching rules and injectable faults. Thread-safe."""

    def __init__(self, n_bins: int = proto.DEFAULT_N_BINS) -> None:
        self.n_bins = n_bins
        self.sorted: list[int] = []  # bins routed, in order
        self._lock = threading.Lock()
        self._connected = False
        self._state = "ready"
        self._fault = ""
        self._bin = REJECT_BIN
        self._seq = 0
        self._jam_next = False
        self._timeouts_left = 0
        self.to_reject_calls = 0

    # injections
    def jam_next_sort(self) -> None:
        self._jam_next = True

    def lose_heartbeat(self) -> None:
        """What the firmware does when the host goes quiet: reject position, latched."""
        with self._lock:
            self._state, self._fault, self._bin = "failsafe", "heartbeat_lost", REJECT_BIN

    def time_out_next(self, n: int = 1) -> None:
        self._timeouts_left = n

    # Gate protocol
    def connect(self) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    def _need_connection(self) -> None:
        if not self._connected:
            raise NotConnectedError("fake gate used before connect()", device="gate", kind="not_connected")

    def sort(self, bin_index: int) -> None:
        self._need_connection()
        with self._lock:
            self._seq = (self._seq + 1) & 0xFF
            if self._timeouts_left > 0:
                self._timeouts_left -= 1
                error = GateError("the gate did not answer SORT (fake timeout)", device="gate", kind="timeout")
                error.retryable = True
                raise error
            if not 0 <= bin_index < self.n_bins:
                raise GateError(f"sort to bin {bin_index} refused: the gate has no such bin", device="gate",
                                kind="nak")
            if self._state in ("fault", "failsafe"):
                raise GateError(f"sort to bin {bin_index} refused: the gate is latched in {self._state} "
                                f"({self._fault}) and refuses to route until cleared", device="gate",
                                kind="fault_latched")
            if self._jam_next:
                self._jam_next = False
                self._state, self._fault = "fault", "jam"
                raise GateError(f"sort to bin {bin_index} refused: the flap jammed", device="gate", kind="jam")
            self._bin = bin_index
            self.sorted.append(bin_index)

    def status(self) -> GateStatus:
        self._need_connection()
        with self._lock:
            return GateStatus(state=self._state, bin=self._bin, fault=self._fault, seq=self._seq)

    def clear(self) -> None:
        self._need_connection()
        with self._lock:
            self._state, self._fault, self._bin = "ready", "", REJECT_BIN

    def to_reject(self) -> None:
        self.to_reject_calls += 1
        with self._lock:
            if self._connected and self._state == "ready":
                self._bin = REJECT_BIN

    def __enter__(self) -> "FakeGate":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()

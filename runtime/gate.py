"""The sorting gate as the cell sees it: the ``Gate`` protocol of runtime/devices.py.

``SerialGate`` is the live gate: the serial host driver of firmware_bridge (pyserial, any URL),
with its faults turned into ``GateError(kind=...)``.

The in-process ``FakeGate`` (the firmware's latching rules, injectable faults; config
``devices.gate.kind: fake``) is ``vs2t_edge.sim.fake_devices.FakeGate``, and the ``SerialGate``
wired to the MCU simulator over a real pty (``devices.gate.kind: sim``, the demo) is
``vs2t_edge.sim.devices.simulated_serial_gate``: simulators and fakes stay out of the cell's code,
and the wiring imports one only when a config asks for it (runtime/devices.py SIMULATORS).
"""

from __future__ import annotations

import logging

from vs2t_edge.firmware_bridge import protocol as proto
from vs2t_edge.firmware_bridge.gate_client import GateClient, GateClientError, GateReport
from vs2t_edge.runtime.devices import GateError, GateStatus, NotConnectedError

log = logging.getLogger(__name__)

REJECT_BIN = proto.REJECT_BIN


def _to_gate_error(exc: GateClientError) -> GateError:
    error = GateError(str(exc), device="gate", kind=exc.kind)
    error.retryable = exc.kind == "timeout"  # one more try may help a noisy line; nothing else
    error.reported_bin = exc.reported_bin  # bad_ack, NAK: where the gate says the flap is
    error.reported_state = exc.reported_state  # and the gate's state: "fault" holds the flap there
    error.maybe_executed = exc.maybe_executed  # the request went out: a SORT may have moved the flap
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
        return GateStatus(state=report.state, bin=report.bin, fault=report.fault, seq=report.seq, n_bins=report.n_bins)

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
    def failing_safe(self) -> bool:
        """``to_reject`` failed and left the gate to fail safe on its own (heartbeats stopped): it
        routes nothing until ``clear``, however its status answers right now (the daemon asks the
        status first: a latched gate refuses ``to_reject`` too)."""
        return self._client.failing_safe

    @property
    def client(self) -> GateClient:
        return self._client

    def __enter__(self) -> "SerialGate":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()

"""In-process fakes of the arm and the gate: the cell's interfaces and typed faults, no robot,
no serial line.

A config's ``devices.arm.kind: fake`` / ``devices.gate.kind: fake`` (a dry run of the cell, the
demo's quick path) reaches them through the runtime's lazy registry (runtime/devices.py
``SIMULATORS``); tests and the fault matrix import them directly. They were in runtime/arm.py and
runtime/gate.py: harness stays out of the cell's rooms (docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import threading
from typing import Any, Callable
from dataclasses import dataclass, field

from vs2t_edge.firmware_bridge import protocol as proto
from vs2t_edge.runtime.arm import ArmConfig
from vs2t_edge.runtime.devices import (
    ArmConnectionError,
    ArmError,
    ArmSafetyStop,
    GateError,
    GateStatus,
    NotConnectedError,
    PressFailed,
    PressResult,
)
from vs2t_edge.runtime.gate import REJECT_BIN

# --- the fake arm ------------------------------------------------------------------------

@dataclass
class FakeArm:
    """In-process arm with the same interface and typed faults, no robot, no sockets.

    ``fail_next`` queues faults by kind, consumed one per call of the named step:
    connection_lost (move_above/press), protective_stop, emergency_stop, force_not_reached,
    overforce, timeout (press). The contact is the same spring model as the simulator's.
    """

    config: ArmConfig = field(default_factory=ArmConfig)
    fabric_thickness_mm: float = 2.0
    fabric_stiffness_n_per_mm: float = 6.0
    table_stiffness_n_per_mm: float = 400.0
    fail_next: list[str] = field(default_factory=list)
    calls: list[str] = field(default_factory=list)
    connected: bool = False
    latched: str = ""
    _target: tuple[float, float] | None = None

    def connect(self) -> None:
        self.config.validate()
        self.connected = True
        self.calls.append("connect")

    def disconnect(self) -> None:
        self.connected = False
        self.calls.append("disconnect")

    def __enter__(self) -> "FakeArm":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self.disconnect()

    def _check(self, step: str) -> None:
        if not self.connected:
            raise NotConnectedError("arm used before connect()", device="arm")
        if self.latched:
            raise ArmSafetyStop(f"{self.latched} still active", device="arm", kind=self.latched)
        if self.fail_next and self.fail_next[0] in ("connection_lost", "protective_stop", "emergency_stop"):
            kind = self.fail_next.pop(0)
            if kind == "connection_lost":
                raise ArmConnectionError(f"link lost during {step}", device="arm", kind=kind)
            self.latched = kind
            raise ArmSafetyStop(f"{kind} during {step}", device="arm", kind=kind)

    def move_above(self, x_mm: float, y_mm: float) -> None:
        self.calls.append(f"move_above({x_mm}, {y_mm})")
        self.config.surface_pose(x_mm, y_mm)  # same bounds as the live arm
        self._check("move_above")
        self._target = (x_mm, y_mm)

    def depth_for_force(self, force_n: float) -> float:
        full = self.fabric_stiffness_n_per_mm * self.fabric_thickness_mm
        if force_n <= full:
            return force_n / self.fabric_stiffness_n_per_mm
        return self.fabric_thickness_mm + (force_n - full) / self.table_stiffness_n_per_mm

    def press(self) -> PressResult:
        self.calls.append("press")
        self._check("press")
        if self._target is None:
            raise ArmError("press() before move_above()", device="arm", kind="sequence")
        if self.fail_next and self.fail_next[0] in ("force_not_reached", "overforce", "timeout"):
            kind = self.fail_next.pop(0)
            raise PressFailed(f"{kind} (injected)", device="arm", kind=kind)
        cfg = self.config
        x_mm, y_mm = self._target
        pose = cfg.surface_pose(x_mm, y_mm)
        depth = self.depth_for_force(cfg.force_n)
        pose[2] -= depth / 1000.0
        return PressResult(x_mm=x_mm, y_mm=y_mm, force_n=cfg.force_n, depth_mm=depth, tcp_pose=tuple(pose),
                           telemetry={"fake": True})

    def retract(self) -> None:
        self.calls.append("retract")
        self._check("retract")

    def stop(self) -> None:
        self.calls.append("stop")

    def clear_protective_stop(self) -> None:
        if self.latched == "protective_stop":
            self.latched = ""


# --- the fake gate ------------------------------------------------------------------------

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
                error = GateError(f"sort to bin {bin_index} refused: the flap jammed", device="gate", kind="jam")
                error.reported_bin, error.reported_state = self._bin, self._state  # as the firmware's NAK
                error.maybe_executed = True  # the flap stuck on its way (firmware_bridge GateClientError)
                raise error
            self._bin = bin_index
            self.sorted.append(bin_index)

    def status(self) -> GateStatus:
        self._need_connection()
        with self._lock:
            return GateStatus(state=self._state, bin=self._bin, fault=self._fault, seq=self._seq, n_bins=self.n_bins)

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


# --- an arm proxy for the simulated cells --------------------------------------------------------

class PressTrackingArm:
    """An arm proxy that knows whether the gel is down (a simulated camera shows a press only
    then) and which press of the current item comes next; ``before_press(item, number)`` (1-based
    per item) is where a subclass injects a fault. Everything else passes through to ``inner``."""

    def __init__(self, inner, current_item: Callable[[], int]) -> None:
        self.inner, self._current_item = inner, current_item
        self.pressed = False
        self.presses_this_item = 0
        self._item_seen = -1

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def connect(self) -> None:
        self.inner.connect()

    def disconnect(self) -> None:
        self.inner.disconnect()

    def move_above(self, x_mm: float, y_mm: float) -> None:
        self.pressed = False
        self.inner.move_above(x_mm, y_mm)

    def press(self):
        item = self._current_item()
        if item != self._item_seen:
            self._item_seen, self.presses_this_item = item, 0
        self.presses_this_item += 1
        self.before_press(item, self.presses_this_item)
        result = self.inner.press()
        self.pressed = True
        return result

    def before_press(self, item: int, number: int) -> None:
        """Called just before press ``number`` of item ``item`` reaches the arm."""

    def retract(self) -> None:
        self.pressed = False
        self.inner.retract()

    def stop(self) -> None:
        self.pressed = False
        self.inner.stop()

"""The three devices the cell touches, each as one small interface.

Live and replay implementations live beside each other: camera.py (UVC + replay), arm.py
(settings + fake) with arm_ur.py (ur_rtde) and arm_isolated.py (ur_rtde in a worker process),
gate.py (serial host driver from firmware_bridge + in-process fake). The simulators are in
vs2t_edge.sim.devices, out of the cell's code; a config reaches one only through
:func:`simulator` below. The cell loop (cell.py) sees only these protocols, so the live daemon,
replay and the demo run the same code.

Every device: ``connect()``, ``disconnect()``, usable as a context manager, and raises
``NotConnectedError`` when used before ``connect()``. Faults are typed so the loop can
decide (retry the press, reject the item, or latch a fault) without parsing strings.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


class DeviceError(RuntimeError):
    """Base of every device fault. ``retryable`` says whether one retry of the step may help."""

    retryable = False

    def __init__(self, message: str, *, device: str = "", kind: str = "") -> None:
        super().__init__(message)
        self.device = device
        self.kind = kind or type(self).__name__


class NotConnectedError(DeviceError):
    """A device was used before connect() or after disconnect()."""


# --- camera -------------------------------------------------------------------------------

class CameraError(DeviceError):
    """No frame: unplugged, timed out, frozen (same frame again) or corrupt."""

    retryable = True


class CameraFrozen(CameraError):
    """The frame repeats the previous one bit for bit (kind ``frozen``): the driver handed out its
    last buffer again. Never scored; retried once after a reopen like any camera fault."""


@dataclass(frozen=True)
class Frame:
    image: np.ndarray  # HxWx3 uint8, BGR as OpenCV delivers it
    timestamp_s: float  # monotonic seconds of the grab
    index: int = 0  # running frame number of this camera
    # 1: the sensor's full frame; n > 1: decoded at 1/n scale by the camera (a UVC camera in MJPEG
    # mode for a bundle on the reduced pixel path, runtime/preprocess.py): the model is told so
    reduced_by: int = 1


@runtime_checkable
class TactileCamera(Protocol):
    def connect(self) -> None: ...
    def disconnect(self) -> None: ...
    def grab(self) -> Frame: ...
    def __enter__(self) -> "TactileCamera": ...
    def __exit__(self, *exc: object) -> None: ...


# --- arm ----------------------------------------------------------------------------------

class ArmError(DeviceError):
    """kind: connection_lost, protective_stop, emergency_stop, force_not_reached, overforce, timeout."""


class ArmConnectionError(ArmError):
    retryable = True


class ArmSafetyStop(ArmError):
    """Protective or emergency stop: never retried automatically; the cell latches a fault."""


class PressFailed(ArmError):
    """Force never reached or exceeded, or a timeout during the press: the press may be retried."""

    retryable = True


@dataclass(frozen=True)
class PressResult:
    x_mm: float  # grid position on the 8 cm x 8 cm piece
    y_mm: float
    force_n: float  # contact force at the moment of the grab
    depth_mm: float  # travel below first contact
    tcp_pose: tuple[float, ...] = ()  # x, y, z, rx, ry, rz (m, rad) at the grab
    telemetry: dict = field(default_factory=dict)


@runtime_checkable
class Arm(Protocol):
    def connect(self) -> None: ...
    def disconnect(self) -> None: ...
    def move_above(self, x_mm: float, y_mm: float) -> None: ...
    def press(self) -> PressResult: ...  # down to the contact force, settled; camera grabs next
    def retract(self) -> None: ...
    def stop(self) -> None: ...  # stop motion now; must not raise
    def __enter__(self) -> "Arm": ...
    def __exit__(self, *exc: object) -> None: ...


# --- gate ---------------------------------------------------------------------------------

class GateError(DeviceError):
    """kind: timeout (no ack after retries), nak, jam, fault_latched, link, bad_ack (an ACK that
    reports another bin or state than the one asked). ``reported_bin`` / ``reported_state``, when
    set: where the gate's reply (that ACK, or a NAK) says the flap is, and the gate's state then."""


@dataclass(frozen=True)
class GateStatus:
    state: str  # "ready", "busy", "fault", "failsafe"
    bin: int  # current bin position
    fault: str = ""  # reason when state is fault/failsafe
    seq: int = 0
    n_bins: int | None = None  # the bins the gate has (0 .. n_bins - 1), where it says (STATUS)


@runtime_checkable
class Gate(Protocol):
    def connect(self) -> None: ...
    def disconnect(self) -> None: ...
    def sort(self, bin_index: int) -> None: ...  # returns once the gate acknowledged the move
    def status(self) -> GateStatus: ...
    def clear(self) -> None: ...
    def to_reject(self) -> None: ...  # best effort, must not raise
    def __enter__(self) -> "Gate": ...
    def __exit__(self, *exc: object) -> None: ...


# --- simulators, by name ------------------------------------------------------------------

# The simulated devices a config may name (``devices.gate.kind: sim``: the gate's MCU simulator on
# a pty), as "module:factory" inside vs2t_edge.sim. Only names: the runtime never imports sim/ at
# load time (docs/ARCHITECTURE.md, checked by tests/test_architecture.py), so a cell that runs live
# devices never loads a simulator; the module is imported when a config asks for one.
SIMULATORS = {"gate": "vs2t_edge.sim.devices:simulated_serial_gate",  # devices.gate.kind: sim
              "fake_gate": "vs2t_edge.sim.fake_devices:FakeGate",  # devices.gate.kind: fake
              "fake_arm": "vs2t_edge.sim.fake_devices:FakeArm"}  # devices.arm.kind: fake


def simulator(device: str):
    """The factory of the simulated ``device`` (a key of SIMULATORS), imported only now."""
    module, _, factory = SIMULATORS[device].partition(":")
    return getattr(importlib.import_module(module), factory)

"""The simulated devices of the cell: the GelSight camera and the gate on its MCU simulator.

Simulators stay out of the cell's code (docs/ARCHITECTURE.md): these were in runtime/camera.py
and runtime/gate.py. They satisfy the same protocols (runtime/devices.py) and admit frames through
the same guard as the live camera (runtime/frame_guard.py ``FrameGuard``), so the loop cannot tell.
The simulated cell (sim/scene.py), the demo, the soak and the fault matrix build them directly; a
config's ``devices.gate.kind: sim`` reaches ``simulated_serial_gate`` through the runtime's lazy
registry (runtime/devices.py ``SIMULATORS``), the only way the runtime gets to this module.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from vs2t_edge.firmware_bridge.mcu_sim import start_simulated_gate
from vs2t_edge.runtime.frame_guard import FROZEN_AFTER, CameraBase, FrameGuard
from vs2t_edge.runtime.devices import CameraError, Frame, NotConnectedError
from vs2t_edge.runtime.gate import SerialGate


# --- the simulated camera -------------------------------------------------------------------

class SimulatedCamera(CameraBase):
    """The simulated cell's sensor. ``frame_fn()`` returns the frame for the current press
    (the demo wires it to the synthetic dataset: item fabric + grid index).

    Sensor noise (``noise_levels``, 1-sigma in grey levels) is added to every grab, as a real
    sensor's would be, so that only an injected freeze repeats a frame bit for bit.
    ``inject(kind, count)`` queues faults: unplugged, frozen (the last frame again), black (a dark
    frame), truncated (a frame of the wrong size), timeout; each but unplugged spoils ``count`` grabs.

    Unplugged is a real disconnect, as a UVC device vanishing from the bus is: the grab it lands
    on fails, the camera is disconnected, and every grab after it fails (``CameraError``, kind
    unplugged - retryable, the cable may come back) until ``connect()`` succeeds. ``connect()``
    fails while the cable is out. ``inject("unplugged", count)`` pulls the cable at the next grab
    (or connect) and it is back after ``count - 1`` more failed connects; ``unplug()`` pulls it
    until ``replug()`` (the operator plugs it back in).
    """

    FAULTS = ("unplugged", "frozen", "black", "truncated", "timeout")

    def __init__(self, frame_fn: Callable[[], np.ndarray], *, noise_levels: float = 1.0, seed: int = 0,
                 frozen_after: int = FROZEN_AFTER, expected_hw: tuple[int, int] | None = None) -> None:
        self.frame_fn = frame_fn
        self.name = "simulated camera"
        self.noise_levels = noise_levels
        self._rng = np.random.default_rng(seed)
        self._guard = FrameGuard(self.name, expected_hw, frozen_after)
        self._faults: list[str] = []
        self._last: np.ndarray | None = None
        self._connected = False
        self.cable_out = False
        self._failed_connects_left: int | None = None  # while out: None = until replug()
        self._lost = False  # unplugged since the last successful connect()
        self.grabs = 0
        self.connects = 0  # connect() calls, successful or not
        self.connected_count = 0  # successful ones

    def inject(self, kind: str, count: int = 1) -> None:
        if kind not in self.FAULTS:
            raise ValueError(f"unknown camera fault {kind!r}; known: {self.FAULTS}")
        self._faults.extend([kind] * count)

    def clear_faults(self) -> None:
        """Drop the faults still queued (the operator power-cycles the sensor)."""
        self._faults.clear()

    def unplug(self, failed_connects: int | None = None) -> None:
        """The cable comes out now: disconnected; back after ``failed_connects`` failed
        ``connect()`` calls, or (None) when ``replug()`` is called."""
        self.cable_out = True
        self._lost = True
        self._connected = False
        self._failed_connects_left = failed_connects

    @property
    def is_connected(self) -> bool:
        return self._connected

    def replug(self) -> None:
        """The cable is back in: the next ``connect()`` succeeds (grabs still need it)."""
        self.cable_out = False
        self._failed_connects_left = None

    def _pull_cable_if_queued(self) -> bool:
        if not self._faults or self._faults[0] != "unplugged":
            return False
        n = 0
        while self._faults and self._faults[0] == "unplugged":
            self._faults.pop(0)
            n += 1
        self.unplug(failed_connects=n - 1)
        return True

    def connect(self) -> None:
        self.connects += 1
        if self._pull_cable_if_queued():
            raise CameraError(f"{self.name}: cannot open (unplugged)", device=self.name, kind="unplugged")
        if self.cable_out:
            if self._failed_connects_left is None or self._failed_connects_left > 0:
                if self._failed_connects_left is not None:
                    self._failed_connects_left -= 1
                raise CameraError(f"{self.name}: cannot open (unplugged)", device=self.name, kind="unplugged")
            self.replug()
        self._connected = True
        self._lost = False
        self.connected_count += 1
        # no _guard.reset(): the frozen-frame history survives a reopen - a frame bit-identical
        # to the last one before it is the same hung buffer, not a fresh start

    def disconnect(self) -> None:
        self._connected = False

    def grab(self) -> Frame:
        if not self._connected:
            if self._lost:
                raise CameraError(f"{self.name}: not connected (unplugged); connect() again once it is back",
                                  device=self.name, kind="unplugged")
            raise NotConnectedError(f"{self.name} used before connect()", device=self.name)
        self.grabs += 1
        if self._pull_cable_if_queued():
            raise CameraError(f"{self.name}: no frame (unplugged)", device=self.name, kind="unplugged")
        fault = self._faults.pop(0) if self._faults else ""
        if fault == "timeout":
            raise CameraError(f"{self.name}: no frame in time", device=self.name, kind="timeout")
        if fault == "frozen" and self._last is not None:
            return self._guard.admit(self._last)
        image = np.asarray(self.frame_fn())
        if self.noise_levels > 0 and image.dtype == np.uint8:
            noisy = image.astype(np.float32) + self._rng.normal(0.0, self.noise_levels, image.shape)
            image = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
        if fault == "black":
            image = np.zeros_like(image)
        elif fault == "truncated":
            image = image[: max(1, image.shape[0] // 2)]
        self._last = image
        return self._guard.admit(image)


# --- the simulated gate ---------------------------------------------------------------------

class SimulatedSerialGate(SerialGate):
    """A ``SerialGate`` on its own MCU simulator (pty); ``disconnect()`` also stops the simulator."""

    def __init__(self, *, timeout_s: float = 0.5, retries: int = 3, **sim_kwargs) -> None:
        path, self.simulator = start_simulated_gate(**sim_kwargs)
        super().__init__(path, timeout_s=timeout_s, retries=retries)

    def disconnect(self) -> None:
        super().disconnect()
        self.simulator.stop()


def simulated_serial_gate(**sim_kwargs) -> SimulatedSerialGate:
    """The live driver against the simulated MCU over a real pty (config gate kind sim, the demo)."""
    return SimulatedSerialGate(**sim_kwargs)

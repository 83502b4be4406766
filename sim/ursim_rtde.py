"""The RTDE side of the loopback UR simulator: the wire protocol's constants and one client's
session (its recipes, the packages it sends, the output stream at the frequency it asked for).

RTDE protocol v2 on port 30004: protocol version, controller version, output and input recipes,
start/pause, data packages both ways. Outputs are streamed at the frequency each client asks for
(capped at 500 Hz). What the values mean is the controller model's business
(``sim/ursim_model.py``: ``_output_values`` / ``_write_inputs``); this module only frames them.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vs2t_edge.sim.ursim import URSim

# --- RTDE wire constants (the protocol's package types are ASCII letters) ----------------

RTDE_REQUEST_PROTOCOL_VERSION = ord("V")
RTDE_GET_URCONTROL_VERSION = ord("v")
RTDE_TEXT_MESSAGE = ord("M")
RTDE_DATA_PACKAGE = ord("U")
RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
RTDE_CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
RTDE_CONTROL_PACKAGE_START = ord("S")
RTDE_CONTROL_PACKAGE_PAUSE = ord("P")

_TYPE_FORMAT = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}

# Output variable types as the RTDE guide lists them (only names a client may ask for here).
_V6 = "VECTOR6D"
OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE", "target_q": _V6, "target_qd": _V6, "target_qdd": _V6,
    "target_current": _V6, "target_moment": _V6, "actual_q": _V6, "actual_qd": _V6,
    "actual_current": _V6, "joint_control_output": _V6, "actual_TCP_pose": _V6,
    "actual_TCP_speed": _V6, "actual_TCP_force": _V6, "target_TCP_pose": _V6,
    "target_TCP_speed": _V6, "actual_digital_input_bits": "UINT64", "joint_temperatures": _V6,
    "actual_execution_time": "DOUBLE", "robot_mode": "INT32", "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32", "safety_status": "INT32", "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE", "actual_joint_voltage": _V6,
    "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D", "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32", "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE", "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE", "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE", "ft_raw_wrench": _V6, "payload": "DOUBLE", "payload_cog": "VECTOR3D",
    "payload_inertia": _V6, "tcp_force_scalar": "DOUBLE", "actual_qdd": _V6,
    "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
}
for _i in range(48):
    OUTPUT_TYPES[f"output_int_register_{_i}"] = "INT32"
    OUTPUT_TYPES[f"output_double_register_{_i}"] = "DOUBLE"

INPUT_TYPES: dict[str, str] = {
    "external_force_torque": _V6, "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32", "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
}
for _i in range(48):
    INPUT_TYPES[f"input_int_register_{_i}"] = "INT32"
    INPUT_TYPES[f"input_double_register_{_i}"] = "DOUBLE"


class _Stop(Exception):
    pass


class RTDESession:
    """One RTDE client connection: its recipes and its output stream."""

    def __init__(self, sim: "URSim", conn: socket.socket) -> None:
        self.sim, self.conn = sim, conn
        self.send_lock = threading.Lock()
        self.output_names: list[str] = []
        self.output_fmt = ""
        self.frequency_hz = 125.0
        self.input_recipes: dict[int, tuple[list[str], str]] = {}
        self.started = threading.Event()
        self.closed = threading.Event()

    def send(self, ptype: int, payload: bytes) -> None:
        with self.send_lock:
            self.conn.sendall(struct.pack(">HB", len(payload) + 3, ptype) + payload)

    def _recv_exact(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.conn.recv(n - len(data))
            if not chunk:
                raise _Stop()
            data += chunk
        return data

    def serve(self) -> None:
        streamer = threading.Thread(target=self._stream, daemon=True, name="ursim-rtde-out")
        streamer.start()
        try:
            while not self.closed.is_set():
                size, ptype = struct.unpack(">HB", self._recv_exact(3))
                self._handle(ptype, self._recv_exact(size - 3))
        except (_Stop, OSError):
            pass
        finally:
            self.closed.set()
            self.started.set()  # wake the streamer so it can exit
            close_socket(self.conn)

    def _handle(self, ptype: int, body: bytes) -> None:
        sim = self.sim
        if ptype == RTDE_REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", body[:2])
            self.send(ptype, struct.pack(">B", 1 if version in (1, 2) else 0))
        elif ptype == RTDE_GET_URCONTROL_VERSION:
            self.send(ptype, struct.pack(">IIII", *sim.controller_version))
        elif ptype == RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS:
            (freq,) = struct.unpack(">d", body[:8])
            names = [n for n in body[8:].decode().split(",") if n]
            types = [OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            self.output_names = names
            self.output_fmt = ">B" + "".join(_TYPE_FORMAT.get(t, "") for t in types)
            self.frequency_hz = min(max(freq, 1.0), 500.0)
            self.send(ptype, struct.pack(">B", 1) + ",".join(types).encode())
            sim._record("rtde_outputs", names)
        elif ptype == RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
            names = [n for n in body.decode().split(",") if n]
            types = [INPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            recipe_id = len(self.input_recipes) + 1
            if "NOT_FOUND" not in types:
                self.input_recipes[recipe_id] = (names, ">" + "".join(_TYPE_FORMAT[t] for t in types))
            else:
                recipe_id = 0
            self.send(ptype, struct.pack(">B", recipe_id) + ",".join(types).encode())
        elif ptype == RTDE_CONTROL_PACKAGE_START:
            self.send(ptype, struct.pack(">B", 1))
            self.started.set()
        elif ptype == RTDE_CONTROL_PACKAGE_PAUSE:
            self.started.clear()
            self.send(ptype, struct.pack(">B", 1))
        elif ptype == RTDE_DATA_PACKAGE:
            recipe_id = body[0]
            if recipe_id not in self.input_recipes:
                return  # the real controller drops packages of unknown recipes too
            names, fmt = self.input_recipes[recipe_id]
            need = struct.calcsize(fmt)
            if len(body) - 1 < need:
                sim._record("bad_packages", (recipe_id, len(body) - 1, need))
                return
            values = struct.unpack(fmt, body[1:1 + need])
            sim._write_inputs(names, fmt, values)

    def _stream(self) -> None:
        next_t = time.monotonic()
        while not self.closed.is_set():
            if not self.started.wait(0.2):
                continue
            if self.closed.is_set():
                break
            if self.output_fmt:
                values = self.sim._output_values(self.output_names)
                try:
                    self.send(RTDE_DATA_PACKAGE, struct.pack(self.output_fmt, 1, *values))
                except OSError:
                    break
            next_t += 1.0 / self.frequency_hz
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.monotonic()


def close_socket(sock: socket.socket | None) -> None:
    """Shut down and close, whatever state the socket is in (a dropped link cannot be closed politely)."""
    if sock is None:
        return
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        sock.close()
    except OSError:
        pass

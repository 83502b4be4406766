"""A loopback UR controller that the real ``ur_rtde`` client talks to, for the press scene only.

What it speaks (see docs/arm.md for the full list and what is *not* emulated):

* RTDE protocol v2 on ``rtde_port`` (30004): protocol version, controller version, output and
  input recipes, start/pause, data packages both ways. Outputs are streamed at the frequency each
  client asks for (capped at 500 Hz).
* The dashboard server on ``dashboard_port`` (29999): the line commands ur_rtde and our arm
  backend send (version, serial number, robot/safety mode, program state, stop, unlock
  protective stop, close safety popup, power on, brake release, quit).
* The script ports (30001-30003): ur_rtde uploads its control script there. The script is
  accepted and *not interpreted*: this module plays the role of that script by emulating its
  register handshake - ``input_int_register_0`` carries the command, ``output_int_register_0``
  answers 1 (ready) or 2 (done), the arguments travel in the input int/double registers.

Physics is only the press: the TCP moves along straight lines at the commanded speed; a table
top at ``table_z_m`` carries a fabric of thickness ``fabric_thickness_mm``; the contact force is a
spring (fabric stiffness while the fabric is being compressed, the table's far higher stiffness
once it is flat); over ``protective_stop_force_n`` the controller goes into protective stop.
Faults are injected through :class:`SimFaults` and a few methods (drop connections, protective
stop, emergency stop).

ur_rtde hardcodes the RTDE port (30004) and the script port (30003) of RTDEControlInterface and
RTDEReceiveInterface, so a simulator always listens on those ports; to let several simulators
(or test processes) coexist, each one may bind its own loopback address (127.x.y.z, the whole
127/8 is loopback on Linux) - see :func:`free_loopback_host` - and a lock file per address
serialises two simulators that want the same address.
"""

from __future__ import annotations

import fcntl
import ipaddress
import math
import os
import random
import socket
import struct
import tempfile
import threading
import time
from dataclasses import asdict, dataclass
from typing import Callable

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

# Controller enums (RTDE guide / dashboard server manual).
ROBOT_MODE = {"POWER_OFF": 3, "POWER_ON": 4, "IDLE": 5, "RUNNING": 7}
SAFETY_MODE = {"NORMAL": 1, "PROTECTIVE_STOP": 3, "ROBOT_EMERGENCY_STOP": 7}
RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
# safety_status_bits: 0 normal, 2 protective stopped, 6 robot e-stopped, 7 e-stopped (any).
_SAFETY_BITS = {1: 1 << 0, 3: 1 << 2, 7: (1 << 6) | (1 << 7)}

# Commands of the ur_rtde control script that the press needs (input_int_register_0 values).
CMD_NONE, CMD_MOVEL, CMD_FORCE_MODE, CMD_FORCE_MODE_STOP, CMD_ZERO_FT = 0, 3, 6, 7, 8
CMD_STOPL, CMD_MOVE_UNTIL_CONTACT, CMD_STOP_SCRIPT = 33, 51, 255
# Commands the script answers on the spot without waiting (its "realtime" set).
_REALTIME_CMDS = {6, 9, 10, 11, 24, 25, 26, 27, 38, 58}
READY, DONE = 1, 2

SCRIPT_PORTS = (30001, 30002, 30003)


@dataclass
class PressScene:
    """The only physics: a tool above a table with a fabric piece on it, along base z."""

    table_z_m: float = 0.100  # table top height in the base frame
    fabric_thickness_mm: float = 2.0
    fabric_stiffness_n_per_mm: float = 6.0  # while the fabric compresses
    table_stiffness_n_per_mm: float = 400.0  # once the fabric is flat (gel + table)
    protective_stop_force_n: float = 120.0  # the controller's force limit
    ft_bias_n: float = 3.0  # offset of the force sensor until zeroFtSensor()
    force_noise_n: float = 0.05  # 1-sigma noise of the force reading
    contact_threshold_n: float = 1.0  # tool_contact sensitivity for moveUntilContact
    force_mode_time_constant_s: float = 0.08  # how briskly force mode settles on its target
    home_pose: tuple[float, ...] = (0.40, -0.10, 0.200, 0.0, math.pi, 0.0)
    seed: int = 0

    @property
    def surface_z_m(self) -> float:
        return self.table_z_m + self.fabric_thickness_mm / 1000.0


@dataclass
class SimFaults:
    """Injectable faults; change the fields while the simulator runs."""

    protective_stop_above_n: float | None = None  # protective stop once the force passes this
    no_surface: bool = False  # nothing under the tool: the force is never reached
    command_delay_s: float = 0.0  # the controller answers 'done' this much later (slow robot)
    motion_speed_factor: float = 1.0  # < 1: the robot moves slower than commanded
    hard_spot_n: float = 0.0  # a button or seam under the gel: extra force once in contact


class _Stop(Exception):
    pass


def _check_loopback(host: str) -> None:
    if not ipaddress.ip_address(host).is_loopback:
        raise ValueError(f"URSim serves loopback only, not {host}")


def free_loopback_host() -> str:
    """A 127.x.y.z address whose RTDE port is free, so a simulator can run beside others."""
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    for _ in range(200):
        host = f"127.{rng.randint(1, 254)}.{rng.randint(0, 254)}.{rng.randint(1, 254)}"
        probe = socket.socket()
        try:
            probe.bind((host, 30004))
            return host
        except OSError:
            continue
        finally:
            probe.close()
    raise RuntimeError("no free loopback address for a UR simulator")


class _RTDESession:
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
            _close(self.conn)

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


def _close(sock: socket.socket | None) -> None:
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


class URSim:
    """The simulated controller. Use as a context manager; ``host`` must be a loopback address."""

    def __init__(self, scene: PressScene | None = None, *, host: str = "127.0.0.1",
                 rtde_port: int = 30004, dashboard_port: int = 29999,
                 script_ports: tuple[int, ...] = SCRIPT_PORTS,
                 controller_version: tuple[int, int, int, int] = (5, 11, 6, 108549),
                 tick_hz: float = 250.0, lock_timeout_s: float = 120.0,
                 unlock_delay_s: float = 0.0) -> None:
        _check_loopback(host)
        self.scene = scene or PressScene()
        self.faults = SimFaults()
        self.host = host
        self.rtde_port, self.dashboard_port, self.script_ports = rtde_port, dashboard_port, script_ports
        self.controller_version = controller_version
        self.tick_s = 1.0 / tick_hz
        self.lock_timeout_s = lock_timeout_s
        self.unlock_delay_s = unlock_delay_s  # the real robot wants 5 s before unlocking
        self._rng = random.Random(self.scene.seed)
        self._lock = threading.RLock()
        self._threads: list[threading.Thread] = []
        self._listeners: dict[int, socket.socket] = {}
        self._conns: set[socket.socket] = set()
        self._running = threading.Event()
        self._lockfile = None
        self.log: dict[str, list] = {}
        self._reset_state()

    # --- state ---------------------------------------------------------------------------

    def _reset_state(self) -> None:
        s = self.scene
        self.pose = list(s.home_pose)
        self.speed = [0.0] * 6
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.robot_mode = ROBOT_MODE["RUNNING"]
        self.safety_mode = SAFETY_MODE["NORMAL"]
        self.runtime_state = RUNTIME_STOPPED
        self.program_loaded_at: float | None = None
        self.safety_stop_at = 0.0
        self.ft_offset = 0.0
        self.force_n = 0.0  # contact force along +z (the table pushing the tool up)
        self.measured_fz = 0.0
        self._executing = False
        self._pending: dict | None = None  # the blocking command in progress
        self._motion: dict | None = None  # linear move, speed move or stop in progress
        self._force_mode: dict | None = None
        self._history: list[tuple[float, float]] = []  # (z, force) for moveUntilContact
        self._start_time = time.monotonic()

    def _record(self, key: str, value) -> None:
        with self._lock:
            self.log.setdefault(key, []).append(value)

    def contact_force_at(self, z_m: float) -> float:
        """The spring model: force of the table+fabric on the tool at TCP height z."""
        s = self.scene
        if self.faults.no_surface:
            return 0.0
        depth_mm = (s.surface_z_m - z_m) * 1000.0
        if depth_mm <= 0:
            return 0.0
        t = s.fabric_thickness_mm
        extra = self.faults.hard_spot_n  # the force controller below does not know about it
        if depth_mm <= t:
            return s.fabric_stiffness_n_per_mm * depth_mm + extra
        return s.fabric_stiffness_n_per_mm * t + s.table_stiffness_n_per_mm * (depth_mm - t) + extra

    def _z_for_force(self, force_n: float) -> float:
        """Inverse of the spring model: the TCP height where the contact force equals force_n."""
        s = self.scene
        if self.faults.no_surface:
            return -math.inf
        if force_n <= 0:
            return s.surface_z_m
        fabric_full = s.fabric_stiffness_n_per_mm * s.fabric_thickness_mm
        if force_n <= fabric_full:
            depth_mm = force_n / s.fabric_stiffness_n_per_mm
        else:
            depth_mm = s.fabric_thickness_mm + (force_n - fabric_full) / s.table_stiffness_n_per_mm
        return s.surface_z_m - depth_mm / 1000.0

    def _output_values(self, names: list[str]) -> list:
        with self._lock:
            values: list = []
            safety_bits = _SAFETY_BITS.get(self.safety_mode, 0)
            robot_bits = (1 if self.robot_mode >= ROBOT_MODE["POWER_ON"] else 0) | (
                2 if self.runtime_state == RUNTIME_PLAYING else 0)
            for name in names:
                t = OUTPUT_TYPES.get(name)
                if name == "timestamp":
                    values.append(time.monotonic() - self._start_time)
                elif name in ("actual_TCP_pose", "target_TCP_pose"):
                    values.extend(self.pose)
                elif name in ("actual_TCP_speed", "target_TCP_speed"):
                    values.extend(self.speed)
                elif name in ("actual_TCP_force", "ft_raw_wrench"):
                    values.extend([0.0, 0.0, self.measured_fz, 0.0, 0.0, 0.0])
                elif name == "tcp_force_scalar":
                    values.append(abs(self.measured_fz))
                elif name in ("actual_q", "target_q"):
                    values.extend([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])  # no kinematics here
                elif name == "robot_mode":
                    values.append(self.robot_mode)
                elif name in ("safety_mode", "safety_status"):
                    values.append(self.safety_mode)
                elif name == "joint_mode":
                    values.extend([255] * 6)  # JOINT_RUNNING_MODE
                elif name == "runtime_state":
                    values.append(self.runtime_state)
                elif name == "robot_status_bits":
                    values.append(robot_bits)
                elif name == "safety_status_bits":
                    values.append(safety_bits)
                elif name in ("speed_scaling", "target_speed_fraction"):
                    values.append(1.0)
                elif name.startswith("output_int_register_"):
                    values.append(self.out_int[int(name.rsplit("_", 1)[1])])
                elif name.startswith("output_double_register_"):
                    values.append(self.out_double[int(name.rsplit("_", 1)[1])])
                elif t is None:
                    continue  # was answered NOT_FOUND; the client refused the recipe
                else:
                    n = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}.get(t, 1)
                    zero = 0.0 if t in ("DOUBLE", "VECTOR3D", "VECTOR6D") else 0
                    values.extend([zero] * n)
            return values

    def _write_inputs(self, names: list[str], fmt: str, values: tuple) -> None:
        with self._lock:
            i = 0
            for name in names:
                if name.startswith("input_int_register_"):
                    self.in_int[int(name.rsplit("_", 1)[1])] = values[i]
                    i += 1
                elif name.startswith("input_double_register_"):
                    self.in_double[int(name.rsplit("_", 1)[1])] = values[i]
                    i += 1
                else:
                    t = INPUT_TYPES[name]
                    i += {"VECTOR6D": 6, "VECTOR3D": 3}.get(t, 1)

    # --- fault injection -----------------------------------------------------------------

    def trigger_protective_stop(self, reason: str = "injected") -> None:
        with self._lock:
            self._safety_stop(SAFETY_MODE["PROTECTIVE_STOP"], reason)

    def trigger_emergency_stop(self) -> None:
        with self._lock:
            self._safety_stop(SAFETY_MODE["ROBOT_EMERGENCY_STOP"], "emergency stop pressed")
            self.robot_mode = ROBOT_MODE["POWER_OFF"]

    def release_emergency_stop(self) -> None:
        """The operator twists the e-stop button out; power on + brake release still needed."""
        with self._lock:
            if self.safety_mode == SAFETY_MODE["ROBOT_EMERGENCY_STOP"]:
                self.safety_mode = SAFETY_MODE["NORMAL"]

    def drop_connections(self, refuse_s: float = 1.0) -> None:
        """Cut every client connection and refuse new ones for ``refuse_s``.

        With refuse_s = 0 the real ur_rtde 1.6.5 client's own reconnect succeeds at once and
        then loops (reconnecting again after every success) until it crashes its process with a
        segfault - a client bug, see docs/arm.md. Keep a refusal window unless that is the test.
        """
        if refuse_s > 0:
            self._close_listeners()
            timer = threading.Timer(refuse_s, self._open_listeners)
            timer.daemon = True
            timer.start()
        with self._lock:
            conns = list(self._conns)
            self._conns.clear()
        for conn in conns:
            _close(conn)
        self._record("drops", time.monotonic())

    def _safety_stop(self, mode: int, reason: str) -> None:
        if self.safety_mode == mode:
            return
        self.safety_mode = mode
        self.safety_stop_at = time.monotonic()
        self.runtime_state = RUNTIME_STOPPED  # a safety stop aborts the running program
        self._motion = None
        self._force_mode = None
        self._pending = None
        self.speed = [0.0] * 6
        self.log.setdefault("safety_stops", []).append((mode, reason, round(self.force_n, 2)))

    # --- the control script's register handshake -------------------------------------------

    def _program_started(self) -> None:
        with self._lock:
            if self.safety_mode != SAFETY_MODE["NORMAL"] or self.robot_mode != ROBOT_MODE["RUNNING"]:
                return  # a program cannot start in a safety stop or without power
            self.runtime_state = RUNTIME_PLAYING
            self._executing = False
            self._pending = None
            self._force_mode = None
            self.out_int[0] = READY

    def _controller_step(self, now: float) -> None:
        if self.runtime_state != RUNTIME_PLAYING:
            return
        if self._pending is not None:
            if self._pending_finished(now):
                self._pending = None
                self.out_int[0] = DONE
            return
        cmd = self.in_int[0]
        if cmd == CMD_NONE:
            self._executing = False
            self.out_int[0] = READY
            return
        if cmd in _REALTIME_CMDS:
            if self.log.get("commands", [None])[-1] != cmd:
                self._record_cmd(cmd)  # once per run of the same realtime command
            self._start_command(cmd, now)
            self.out_int[0] = READY
            return
        if self._executing:
            return  # waits for the client to clear the command register
        self._executing = True
        self._record_cmd(cmd)
        self._start_command(cmd, now)

    def _record_cmd(self, cmd: int) -> None:
        self.log.setdefault("commands", []).append(cmd)

    def _start_command(self, cmd: int, now: float) -> None:
        d, n = self.in_double, self.in_int
        done_at = now + self.faults.command_delay_s
        if cmd == CMD_MOVEL:
            self._force_mode = None
            target = list(d[0:6])
            self._motion = {"kind": "line", "start": list(self.pose), "target": target,
                            "v": max(d[6], 1e-5), "a": max(d[7], 1e-3), "s": 0.0, "vel": 0.0}
            if n[1] == 1:  # async: the script returns at once and the move goes on
                self._pending = {"until": "time", "at": done_at}
            else:
                self._pending = {"until": "motion", "at": done_at}
        elif cmd == CMD_FORCE_MODE:
            self._motion = None
            selection = list(n[2:8])
            wrench = list(d[6:12])
            limits = list(d[12:18])
            if selection != [0, 0, 1, 0, 0, 0] or any(abs(v) > 1e-9 for v in d[3:6]):
                self._record("unsupported", ("force_mode", selection, list(d[0:6])))
            # A positive force along +z of a base-aligned task frame pushes the tool up; the
            # tool presses down with wrench z = -F, so the contact force settles at -wrench_z.
            self._force_mode = {"target_n": -wrench[2], "vmax": max(abs(limits[2]), 1e-4)}
            if self._force_mode["target_n"] > self.scene.protective_stop_force_n:
                self._safety_stop(SAFETY_MODE["PROTECTIVE_STOP"], "force mode target over the limit")
        elif cmd == CMD_FORCE_MODE_STOP:
            self._force_mode = None
            self._motion = None
            self.speed = [0.0] * 6
            self._pending = {"until": "time", "at": done_at}
        elif cmd == CMD_ZERO_FT:
            self.ft_offset = self._raw_force_reading()
            self._pending = {"until": "time", "at": done_at}
        elif cmd == CMD_STOPL:
            self._force_mode = None
            self._motion = {"kind": "stop", "a": max(d[0], 0.1)}
            self._pending = {"until": "motion", "at": done_at}
        elif cmd == CMD_MOVE_UNTIL_CONTACT:
            self._force_mode = None
            self._history = []
            self._motion = {"kind": "contact", "xd": list(d[0:6]), "a": max(d[12], 1e-3), "vel": 0.0}
            self._pending = {"until": "motion", "at": done_at}
        elif cmd == CMD_STOP_SCRIPT:
            self._force_mode = None
            self._motion = None
            self.runtime_state = RUNTIME_STOPPED
            self.out_int[0] = 0
        elif cmd in _REALTIME_CMDS:
            self._record("unsupported", ("realtime", cmd))
        else:
            # Not part of the press: acknowledged so the client does not hang, and logged.
            self._record("unsupported", ("command", cmd))
            self._pending = {"until": "time", "at": done_at}

    def _pending_finished(self, now: float) -> bool:
        p = self._pending
        if now < p["at"]:
            return False
        return p["until"] == "time" or self._motion is None

    # --- physics -------------------------------------------------------------------------

    def _raw_force_reading(self) -> float:
        return self.force_n + self.scene.ft_bias_n

    def _physics_step(self, dt: float) -> None:
        s, z0 = self.scene, self.pose[2]
        factor = self.faults.motion_speed_factor
        m = self._motion
        if self.safety_mode != SAFETY_MODE["NORMAL"]:
            self.speed = [0.0] * 6
        elif m is not None and m["kind"] == "line":
            start, target = m["start"], m["target"]
            length = math.dist(start[:3], target[:3])
            remaining = length - m["s"]
            v_max = m["v"] * factor
            # Trapezoidal profile along the line: accelerate, cruise, brake to stop on target.
            v = min(v_max, m["vel"] + m["a"] * dt, math.sqrt(max(2 * m["a"] * remaining, 0.0)))
            step = min(v * dt, remaining)
            m["s"] += step
            m["vel"] = v
            frac = 1.0 if length < 1e-9 else m["s"] / length
            self.pose[:3] = [a + (b - a) * frac for a, b in zip(start[:3], target[:3])]
            if remaining - step <= 1e-7:
                self.pose = list(target)
                self._motion = None
        elif m is not None and m["kind"] == "stop":
            vz = self.speed[2]
            mag = abs(vz)
            if mag <= m["a"] * dt:
                self._motion = None
                vz = 0.0
            else:
                vz -= math.copysign(m["a"] * dt, vz)
            self.pose[2] += vz * dt
        elif m is not None and m["kind"] == "contact":
            xd = m["xd"]
            m["vel"] = min(1.0, m["vel"] + m["a"] * dt / max(math.hypot(*xd[:3]), 1e-9))
            for k in range(3):
                self.pose[k] += xd[k] * m["vel"] * factor * dt
            self._history.append((self.pose[2], self.force_n))
        elif self._force_mode is not None:
            fm = self._force_mode
            z_eq = self._z_for_force(fm["target_n"])
            vmax = fm["vmax"] * factor
            vz = 0.0 if math.isinf(z_eq) and z_eq > 0 else (
                -vmax if math.isinf(z_eq) else (z_eq - self.pose[2]) / s.force_mode_time_constant_s)
            vz = max(-vmax, min(vmax, vz))
            self.pose[2] += vz * dt
        dz = (self.pose[2] - z0) / dt if dt > 0 else 0.0
        self.speed = [0.0, 0.0, dz, 0.0, 0.0, 0.0] if self.safety_mode == SAFETY_MODE["NORMAL"] else [0.0] * 6
        self.force_n = self.contact_force_at(self.pose[2])
        self.measured_fz = self._raw_force_reading() - self.ft_offset + self._rng.gauss(0.0, s.force_noise_n)
        if m is not None and m["kind"] == "contact" and self._motion is m:
            if self.measured_fz >= s.contact_threshold_n:
                # Contact: go back to where it was first seen, as the script's tool_contact does.
                first = next((z for z, f in self._history if f > 0.0), self.pose[2])
                self.pose[2] = first
                self.force_n = self.contact_force_at(first)
                self._motion = None
        limit = self.faults.protective_stop_above_n
        if self.force_n > s.protective_stop_force_n:
            self._safety_stop(SAFETY_MODE["PROTECTIVE_STOP"], "force over the limit")
        elif limit is not None and self.force_n > limit:
            self._safety_stop(SAFETY_MODE["PROTECTIVE_STOP"], "injected mid-press")

    def _tick_loop(self) -> None:
        last = time.monotonic()
        while self._running.is_set():
            time.sleep(self.tick_s)
            now = time.monotonic()
            with self._lock:
                self._physics_step(now - last)
                self._controller_step(now)
            last = now

    # --- servers -------------------------------------------------------------------------

    def _open_listeners(self) -> None:
        if not self._running.is_set():
            return
        for port, handler in self._port_handlers().items():
            if port in self._listeners:
                continue
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host, port))
            sock.listen(8)
            self._listeners[port] = sock
            self._spawn(self._accept_loop, sock, handler, name=f"ursim-accept-{port}")

    def _close_listeners(self) -> None:
        listeners, self._listeners = self._listeners, {}
        for sock in listeners.values():
            _close(sock)

    def _port_handlers(self) -> dict[int, Callable[[socket.socket], None]]:
        handlers: dict[int, Callable[[socket.socket], None]] = {
            self.rtde_port: self._serve_rtde, self.dashboard_port: self._serve_dashboard}
        for port in self.script_ports:
            handlers[port] = self._serve_script
        return handlers

    def _spawn(self, target, *args, name: str) -> None:
        t = threading.Thread(target=target, args=args, daemon=True, name=name)
        t.start()
        self._threads.append(t)

    def _accept_loop(self, sock: socket.socket, handler) -> None:
        while self._running.is_set():
            try:
                conn, _ = sock.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._conns.add(conn)
            self._spawn(self._serve_and_forget, handler, conn, name="ursim-conn")

    def _serve_and_forget(self, handler, conn: socket.socket) -> None:
        try:
            handler(conn)
        finally:
            with self._lock:
                self._conns.discard(conn)
            _close(conn)

    def _serve_rtde(self, conn: socket.socket) -> None:
        self._record("rtde_connections", time.monotonic())
        _RTDESession(self, conn).serve()

    def _serve_script(self, conn: socket.socket) -> None:
        """Accept a URScript program: not interpreted, only 'a program is now running'."""
        conn.settimeout(0.05)
        buf = b""
        while self._running.is_set():
            try:
                chunk = conn.recv(65536)
                if not chunk:
                    break
                buf += chunk
                continue
            except socket.timeout:
                pass
            except OSError:
                break
            if buf:
                # A quiet gap after data: one program (or one line of script) has arrived.
                self._record("scripts", buf.decode(errors="replace"))
                if b"def " in buf:  # a program; a secondary one ("sec") or a single line is not
                    self._program_started()
                buf = b""
        if buf:
            self._record("scripts", buf.decode(errors="replace"))
            if b"def " in buf:
                self._program_started()

    def _dashboard_answer(self, line: str) -> str | None:
        cmd = line.strip()
        low = cmd.lower()
        with self._lock:
            safety = {v: k for k, v in SAFETY_MODE.items()}[self.safety_mode]
            robot = {v: k for k, v in ROBOT_MODE.items()}[self.robot_mode]
            playing = self.runtime_state == RUNTIME_PLAYING
            if low == "polyscopeversion":
                major, minor, bugfix, build = self.controller_version
                return f"URSoftware {major}.{minor}.{bugfix}.{build} (simulated)"
            if low == "get serial number":
                return "20185500001"
            if low == "get robot model":
                return "UR5"
            if low == "robotmode":
                return f"Robotmode: {robot}"
            if low == "safetymode":
                return f"Safetymode: {safety}"
            if low == "safetystatus":
                return f"Safetystatus: {safety}"
            if low == "programstate":
                return ("PLAYING" if playing else "STOPPED") + " <unnamed>"
            if low == "running":
                return f"Program running: {'true' if playing else 'false'}"
            if low == "is in remote control":
                return "true"
            if low == "stop":
                self.runtime_state = RUNTIME_STOPPED
                self._force_mode = None
                self._motion = None
                return "Stopped"
            if low == "unlock protective stop":
                if self.safety_mode != SAFETY_MODE["PROTECTIVE_STOP"]:
                    return "Protective stop releasing"
                if time.monotonic() - self.safety_stop_at < self.unlock_delay_s:
                    return ("Cannot unlock protective stop until 5s after occurrence. "
                            "Always inspect cause of protective stop before unlocking")
                self.safety_mode = SAFETY_MODE["NORMAL"]
                return "Protective stop releasing"
            if low == "close safety popup":
                return "closing safety popup"
            if low == "close popup":
                return "closing popup"
            if low == "power on":
                if self.safety_mode == SAFETY_MODE["NORMAL"]:
                    self.robot_mode = ROBOT_MODE["IDLE"]
                return "Powering on"
            if low == "brake release":
                if self.safety_mode == SAFETY_MODE["NORMAL"] and self.robot_mode >= ROBOT_MODE["POWER_ON"]:
                    self.robot_mode = ROBOT_MODE["RUNNING"]
                return "Brake releasing"
            if low == "power off":
                self.robot_mode = ROBOT_MODE["POWER_OFF"]
                self.runtime_state = RUNTIME_STOPPED
                return "Powering off"
            if low.startswith("addtolog"):
                return "Added log message"
            if low == "quit":
                return None
        return f"could not understand: '{cmd}'"

    def _serve_dashboard(self, conn: socket.socket) -> None:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        buf = b""
        while self._running.is_set():
            try:
                chunk = conn.recv(4096)
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                self._record("dashboard", line.decode(errors="replace"))
                answer = self._dashboard_answer(line.decode(errors="replace"))
                if answer is None:
                    conn.sendall(b"Disconnected\n")
                    return
                conn.sendall(answer.encode() + b"\n")

    # --- lifecycle -----------------------------------------------------------------------

    def start(self) -> "URSim":
        lock_path = os.path.join(tempfile.gettempdir(), f"vs2t-ursim-{self.host}.lock")
        self._lockfile = open(lock_path, "w")
        deadline = time.monotonic() + self.lock_timeout_s
        while True:
            try:
                fcntl.flock(self._lockfile, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    self._lockfile.close()
                    raise RuntimeError(f"another UR simulator holds {self.host} (lock {lock_path})")
                time.sleep(0.1)
        self._running.set()
        try:
            self._open_listeners()
        except OSError as exc:
            self.stop()
            raise RuntimeError(f"UR simulator cannot listen on {self.host}: {exc}") from exc
        self._spawn(self._tick_loop, name="ursim-tick")
        return self

    def stop(self) -> None:
        self._running.clear()
        self._close_listeners()
        with self._lock:
            conns = list(self._conns)
            self._conns.clear()
        for conn in conns:
            _close(conn)
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()
        if self._lockfile is not None:
            if self.host != "127.0.0.1":
                # Per-simulator addresses are used once; do not leave a lock file per test run.
                try:
                    os.unlink(self._lockfile.name)
                except OSError:
                    pass
            fcntl.flock(self._lockfile, fcntl.LOCK_UN)
            self._lockfile.close()
            self._lockfile = None

    def __enter__(self) -> "URSim":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- test helpers --------------------------------------------------------------------

    def set_faults(self, **fields) -> None:
        with self._lock:
            for key, value in fields.items():
                if not hasattr(self.faults, key):
                    raise KeyError(f"unknown fault {key!r}")
                setattr(self.faults, key, value)

    def set_scene(self, **fields) -> None:
        with self._lock:
            for key, value in fields.items():
                if not hasattr(self.scene, key):
                    raise KeyError(f"unknown scene field {key!r}")
                setattr(self.scene, key, value)

    def reset(self) -> None:
        """Back to a normal, powered robot at the home pose with no faults (between tests)."""
        with self._lock:
            self.faults = SimFaults()
            self.safety_mode = SAFETY_MODE["NORMAL"]
            self.robot_mode = ROBOT_MODE["RUNNING"]
            self.pose = list(self.scene.home_pose)
            self._motion = self._force_mode = self._pending = None
            self.speed = [0.0] * 6

    def get_log(self) -> dict:
        with self._lock:
            return {k: list(v) for k, v in self.log.items()}

    def clear_log(self) -> None:
        with self._lock:
            self.log.clear()

    def snapshot(self) -> dict:
        with self._lock:
            return {"pose": list(self.pose), "force_n": self.force_n, "measured_fz": self.measured_fz,
                    "safety_mode": self.safety_mode, "robot_mode": self.robot_mode,
                    "runtime_state": self.runtime_state, "force_mode": self._force_mode is not None}


class URSimProcess:
    """Runs :class:`URSim` in a child interpreter and forwards fault injection to it.

    The real ur_rtde client must not share a process with the simulator: its pybind11
    constructors (RTDEControlInterface, RTDEReceiveInterface) keep the GIL while they block on
    the handshake, so an in-process simulator thread could never answer them. The child is
    ``python -m vs2t_edge.sim.ursim --serve-stdio``; calls travel as JSON lines on its stdin and
    stdout, so any script can use this without a ``__main__`` guard.
    """

    _ALLOWED = {"trigger_protective_stop", "trigger_emergency_stop", "release_emergency_stop",
                "drop_connections", "snapshot", "set_faults", "set_scene", "get_log", "clear_log", "reset",
                "contact_force_at"}

    def __init__(self, scene: PressScene | None = None, *, host: str = "127.0.0.1",
                 start_timeout_s: float = 140.0, **kwargs) -> None:
        _check_loopback(host)
        self.scene = scene or PressScene()
        self.host = host
        self._kwargs = kwargs
        # Longer than the child's wait for another simulator's lock on the same address.
        self._start_timeout_s = start_timeout_s
        self._proc = None
        self._call_lock = threading.Lock()

    def start(self) -> "URSimProcess":
        import json
        import subprocess
        import sys

        spec = {"scene": asdict(self.scene), "host": self.host, "kwargs": self._kwargs}
        # The child's stderr goes to a file, not a pipe nobody drains (a full pipe would stall it).
        self._stderr = tempfile.TemporaryFile(mode="w+")
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "vs2t_edge.sim.ursim", "--serve-stdio", json.dumps(spec)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._stderr, text=True, bufsize=1)
        status, detail = self._read_reply(self._start_timeout_s)
        if status != "ready":
            self.stop()
            raise RuntimeError(f"UR simulator process failed to start: {detail}")
        return self

    def _read_reply(self, timeout_s: float):
        import json
        import select

        ready, _, _ = select.select([self._proc.stdout], [], [], timeout_s)
        line = self._proc.stdout.readline() if ready else ""
        if not line:
            return "error", f"no answer from the simulator process {self.stderr_text()[-2000:]}".strip()
        reply = json.loads(line)
        return reply["status"], reply.get("value")

    def call(self, method: str, *args, **kwargs):
        import json

        if method not in self._ALLOWED:
            raise AttributeError(method)
        with self._call_lock:
            if self._proc is None or self._proc.poll() is not None:
                raise RuntimeError("UR simulator is not running")
            self._proc.stdin.write(json.dumps({"method": method, "args": args, "kwargs": kwargs}) + "\n")
            self._proc.stdin.flush()
            status, value = self._read_reply(10.0)
        if status != "ok":
            raise RuntimeError(f"UR simulator {method}: {value}")
        return value

    def stderr_text(self) -> str:
        """What the child wrote on stderr (tracebacks of simulator threads end up here)."""
        if getattr(self, "_stderr", None) is None:
            return ""
        self._stderr.flush()
        self._stderr.seek(0)
        return self._stderr.read()

    def __getattr__(self, name: str):
        if name in URSimProcess._ALLOWED:
            return lambda *a, **k: self.call(name, *a, **k)
        raise AttributeError(name)

    def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()  # EOF: the child stops its servers and exits
        except OSError:
            pass
        try:
            proc.wait(timeout=5.0)
        except Exception:
            proc.terminate()
            try:
                proc.wait(timeout=2.0)
            except Exception:
                proc.kill()
                proc.wait()
        try:
            proc.stdout.close()
        except OSError:
            pass

    def __enter__(self) -> "URSimProcess":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _serve_stdio(spec_json: str) -> None:
    """The child side of URSimProcess: one JSON request per stdin line, one reply per line."""
    import json
    import sys

    spec = json.loads(spec_json)
    scene = PressScene(**{k: tuple(v) if isinstance(v, list) else v for k, v in spec["scene"].items()})
    out = sys.stdout
    sys.stdout = sys.stderr  # nothing else may write on the reply channel

    def reply(status: str, value=None) -> None:
        out.write(json.dumps({"status": status, "value": value}) + "\n")
        out.flush()

    try:
        sim = URSim(scene, host=spec["host"], **spec["kwargs"]).start()
    except Exception as exc:
        reply("error", f"{type(exc).__name__}: {exc}")
        return
    reply("ready", sim.host)
    try:
        for line in sys.stdin:
            request = json.loads(line)
            method = request["method"]
            if method not in URSimProcess._ALLOWED:
                reply("error", f"unknown method {method}")
                continue
            try:
                reply("ok", getattr(sim, method)(*request["args"], **request["kwargs"]))
            except Exception as exc:
                reply("error", f"{type(exc).__name__}: {exc}")
    finally:
        sim.stop()


def bench_press(n_points: int = 9, json_path: str | None = None, **arm_overrides) -> dict:
    """Time move_above / press / retract with the real ur_rtde client against the simulator.

    Uses the default ArmConfig (the cell's settings) unless overridden; the points are spread
    over the 15 x 15 grid. Prints a table; writes the numbers as JSON when json_path is given.
    """
    import json
    import statistics
    import sys

    from vs2t_edge.runtime.arm import ArmConfig
    from vs2t_edge.runtime.arm_ur import URArm

    host = free_loopback_host()
    config = ArmConfig(host=host, **arm_overrides)
    grid = config.grid_points_mm()
    points = [grid[round(i * (len(grid) - 1) / max(n_points - 1, 1))] for i in range(n_points)]
    rows = []
    with URSimProcess(PressScene(), host=host) as sim:
        arm = URArm(config)
        t0 = time.monotonic()
        arm.connect()
        connect_s = time.monotonic() - t0
        try:
            for k, (x, y) in enumerate(points):
                t0 = time.monotonic()
                arm.move_above(x, y)
                t1 = time.monotonic()
                result = arm.press()
                t2 = time.monotonic()
                arm.retract()
                t3 = time.monotonic()
                rows.append({"x_mm": x, "y_mm": y, "move_above_s": t1 - t0, "press_s": t2 - t1,
                             "retract_s": t3 - t2, "force_n": result.force_n, "depth_mm": result.depth_mm,
                             "contact_after_s": result.telemetry["contact_after_s"]})
                print(f"\rpress {k + 1}/{len(points)}", end="", file=sys.stderr)
            print(file=sys.stderr)
        finally:
            arm.disconnect()
        unsupported = sim.get_log().get("unsupported", [])

    def stats(key: str) -> dict:
        values = [r[key] for r in rows[1:] or rows]  # the first move starts from home, far away
        return {"median": statistics.median(values), "max": max(values)}

    summary = {
        "client": "ur_rtde (real) " + _ur_rtde_version(),
        "config": {k: v for k, v in config.to_dict().items() if k != "host"},
        "connect_s": connect_s,
        "presses": rows,
        "move_above_s": stats("move_above_s"), "press_s": stats("press_s"),
        "retract_s": stats("retract_s"), "force_n": stats("force_n"),
        "force_error_n_max": max(abs(r["force_n"] - config.force_n) for r in rows),
        "unsupported_commands": unsupported,
    }
    print(f"{'step':<12}{'median s':>10}{'max s':>10}")
    for key in ("move_above_s", "press_s", "retract_s"):
        print(f"{key[:-2]:<12}{summary[key]['median']:>10.3f}{summary[key]['max']:>10.3f}")
    print(f"force at grab: median {summary['force_n']['median']:.2f} N, worst error "
          f"{summary['force_error_n_max']:.2f} N (target {config.force_n} N); connect {connect_s:.2f} s")
    if json_path:
        with open(json_path, "w") as f:
            json.dump(summary, f, indent=1, default=float)
    return summary


def _ur_rtde_version() -> str:
    try:
        from importlib.metadata import version

        return version("ur_rtde")
    except Exception:
        return "?"


def _main() -> None:  # pragma: no cover - manual use: python -m vs2t_edge.sim.ursim
    import argparse

    parser = argparse.ArgumentParser(description="loopback UR simulator for the press scene")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--serve-stdio", metavar="SPEC_JSON", help=argparse.SUPPRESS)
    parser.add_argument("--bench", type=int, metavar="N", help="time N presses with the real ur_rtde client")
    parser.add_argument("--json", help="with --bench: write the numbers here")
    args = parser.parse_args()
    if args.serve_stdio:
        _serve_stdio(args.serve_stdio)
        return
    if args.bench:
        bench_press(args.bench, args.json)
        return
    with URSim(host=args.host) as sim:
        print(f"UR simulator on {sim.host} (RTDE {sim.rtde_port}, dashboard {sim.dashboard_port}); Ctrl-C stops")
        try:
            while True:
                time.sleep(1)
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":  # pragma: no cover
    _main()

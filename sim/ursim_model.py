"""The loopback UR controller without its sockets: the robot's state, the press physics and the
control script's register handshake. :class:`vs2t_edge.sim.ursim.URSim` serves it on the wire.

Physics is only the press: the TCP moves along straight lines at the commanded speed; a table
top at ``table_z_m`` carries a fabric of thickness ``fabric_thickness_mm``; the contact force is a
spring (fabric stiffness while the fabric is being compressed, the table's far higher stiffness
once it is flat); over ``protective_stop_force_n`` the controller goes into protective stop.
Faults are injected through :class:`SimFaults` and the ``trigger_*`` methods.

The script ports accept ur_rtde's control script without interpreting it: this model plays the
role of that script by emulating its register handshake - ``input_int_register_0`` carries the
command, ``output_int_register_0`` answers 1 (ready) or 2 (done), the arguments travel in the
input int/double registers.
"""

from __future__ import annotations

import math
import random
import threading
import time
from dataclasses import dataclass

from vs2t_edge.sim.ursim_rtde import INPUT_TYPES, OUTPUT_TYPES

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


class ControllerModel:
    """The controller's state and how it changes: commands in the registers, the physics tick,
    safety stops. No threads and no sockets: the public methods take ``_lock``, the physics
    clock and the servers (URSim) call the rest under it."""

    def __init__(self, scene: PressScene | None = None) -> None:
        self.scene = scene or PressScene()
        self.faults = SimFaults()
        self._rng = random.Random(self.scene.seed)
        self._lock = threading.RLock()
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

"""The UR5 press's settings: what the rest of the cell imports.

Three implementations of :class:`vs2t_edge.runtime.devices.Arm` share :class:`ArmConfig`:

* :class:`vs2t_edge.runtime.arm_ur.URArm` on ``ur_rtde``, the live arm (the press sequence and
  why it uses force mode are told there).
* :class:`vs2t_edge.runtime.arm_isolated.IsolatedURArm`, the same in a supervised worker
  process, as the service runs it.
* ``vs2t_edge.sim.fake_devices.FakeArm``, in-process with the same spring model and injectable
  faults, for dry runs (``devices.arm.kind: fake``) and fast cell tests.

ArmConfig lives apart from the drivers so that the config, the watchdog budget and the fakes
never load the ur_rtde driver's code.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from vs2t_edge.runtime.dataset import PIECE_MM


class ArmConfigError(ValueError):
    """A bad arm setting; the message names the key and the allowed range."""


# key: (min, max) - checked by ArmConfig.validate(); units are in the names.
_BOUNDS: dict[str, tuple[float, float]] = {
    "rtde_frequency_hz": (10.0, 500.0),
    "travel_speed_m_s": (0.001, 0.25),
    "travel_accel_m_s2": (0.01, 1.5),
    "press_speed_m_s": (0.001, 0.05),
    "force_n": (1.0, 40.0),
    "force_tolerance_n": (0.1, 5.0),
    "force_max_n": (2.0, 60.0),
    "contact_threshold_n": (0.2, 5.0),
    "approach_height_mm": (1.0, 100.0),
    "max_press_depth_mm": (0.5, 30.0),
    "settle_s": (0.0, 5.0),
    "press_timeout_s": (0.5, 60.0),
    "move_timeout_s": (0.5, 120.0),
    "position_tolerance_mm": (0.01, 2.0),
    "command_timeout_s": (0.5, 60.0),
    "client_reconnect_grace_s": (0.0, 10.0),
    "reconnect_attempts": (0, 10),
    "reconnect_backoff_s": (0.0, 10.0),
    "grid_step_x_mm": (1.0, 20.0),
    "grid_step_y_mm": (1.0, 20.0),
    "piece_mm": (10.0, 200.0),
    # the piece's turn about base z: any orientation is within half a turn either way
    "piece_yaw_rad": (-math.pi, math.pi),
}
_INT_KEYS = ("reconnect_attempts",)  # counts: 2.5 attempts is a typo, not a setting
GRID_N = 15  # the paper's 15 x 15 press grid; config.py's N_GRID_X / N_GRID_Y are this


@dataclass(frozen=True)
class ArmConfig:
    host: str = "127.0.0.1"
    rtde_frequency_hz: float = 125.0  # 125 is plenty at press speeds (0.08 mm per cycle at 10 mm/s)
    # TCP pose (m, rad, base frame) touching the piece's top-left corner at the fabric surface,
    # tool pointing down; piece x/y run along base x/y rotated by piece_yaw_rad about base z.
    piece_origin_pose: tuple[float, ...] = (0.40, -0.10, 0.102, 0.0, math.pi, 0.0)
    piece_yaw_rad: float = 0.0
    tool_offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # gel centre minus TCP, piece axes
    piece_mm: float = PIECE_MM
    grid_step_x_mm: float = 4.9
    grid_step_y_mm: float = 4.6
    travel_speed_m_s: float = 0.10
    travel_accel_m_s2: float = 0.5
    press_speed_m_s: float = 0.01  # force mode's speed limit along z
    force_n: float = 15.0
    force_tolerance_n: float = 1.0
    force_max_n: float = 30.0  # abort the press above this (the controller's own limit is higher)
    contact_threshold_n: float = 1.0  # first contact, for the depth measurement
    approach_height_mm: float = 10.0
    max_press_depth_mm: float = 8.0  # below the expected surface without reaching the force: abort
    settle_s: float = 0.3
    press_timeout_s: float = 8.0
    move_timeout_s: float = 15.0
    position_tolerance_mm: float = 0.1
    command_timeout_s: float = 5.0  # one control call (zeroFtSensor, forceModeStop, ...) at most
    client_reconnect_grace_s: float = 2.0  # let ur_rtde's own reconnect finish before ours
    reconnect_attempts: int = 3
    reconnect_backoff_s: float = 0.5  # doubles after each failed attempt

    def validate(self) -> "ArmConfig":
        for key, (lo, hi) in _BOUNDS.items():
            value = getattr(self, key)
            if key in _INT_KEYS and (not isinstance(value, int) or isinstance(value, bool)):
                raise ArmConfigError(f"arm.{key} = {value!r}: must be a whole number between {lo} and {hi}")
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not lo <= value <= hi:
                raise ArmConfigError(f"arm.{key} = {value!r}: must be between {lo} and {hi}")
        # The 15 x 15 grid, centred, must fit on the piece (press_grid_mm refuses it later, when
        # the daemon builds its scene - too late for validate-config to say so).
        largest = self.piece_mm / (GRID_N - 1)
        for key in ("grid_step_x_mm", "grid_step_y_mm"):
            step = getattr(self, key)
            if (GRID_N - 1) * step > self.piece_mm:  # press_grid_mm's own test, to the last bit
                raise ArmConfigError(f"arm.{key} = {step!r}: the {GRID_N} x {GRID_N} press grid would span "
                                     f"{(GRID_N - 1) * step:g} mm, more than the {self.piece_mm:g} mm piece "
                                     f"(piece_mm); at most {math.floor(largest * 1000) / 1000:g} mm")
        if self.force_max_n <= self.force_n + self.force_tolerance_n:
            raise ArmConfigError(f"arm.force_max_n = {self.force_max_n}: must exceed force_n + "
                                 f"force_tolerance_n ({self.force_n + self.force_tolerance_n})")
        if self.contact_threshold_n >= self.force_n:
            raise ArmConfigError(f"arm.contact_threshold_n = {self.contact_threshold_n}: must be below force_n")
        if len(self.piece_origin_pose) != 6 or not all(math.isfinite(v) for v in self.piece_origin_pose):
            raise ArmConfigError(f"arm.piece_origin_pose = {self.piece_origin_pose!r}: needs 6 finite numbers")
        if len(self.tool_offset_mm) != 3 or not all(math.isfinite(v) and abs(v) <= 200 for v in self.tool_offset_mm):
            raise ArmConfigError(f"arm.tool_offset_mm = {self.tool_offset_mm!r}: needs 3 numbers within 200 mm")
        if not isinstance(self.host, str) or not self.host:
            raise ArmConfigError("arm.host: the robot's address is missing")
        return self

    @classmethod
    def from_dict(cls, d: dict) -> "ArmConfig":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ArmConfigError(f"arm: unknown key(s) {unknown}; known: {sorted(known)}")
        values = dict(d)
        for key in ("piece_origin_pose", "tool_offset_mm"):
            if key in values:
                values[key] = tuple(float(v) for v in values[key])
        return cls(**values).validate()

    def to_dict(self) -> dict:
        return asdict(self)

    def grid_points_mm(self, n_x: int = GRID_N, n_y: int = GRID_N) -> list[tuple[float, float]]:
        from vs2t_edge.runtime.dataset import press_grid_mm

        return press_grid_mm(n_x, n_y, self.grid_step_x_mm, self.grid_step_y_mm, self.piece_mm)

    def surface_pose(self, x_mm: float, y_mm: float) -> list[float]:
        """TCP pose with the gel centre on piece point (x_mm, y_mm) at the fabric surface."""
        if not (0.0 <= x_mm <= self.piece_mm and 0.0 <= y_mm <= self.piece_mm):
            raise ValueError(f"press point ({x_mm}, {y_mm}) mm is off the {self.piece_mm} mm piece")
        px = (x_mm - self.tool_offset_mm[0]) / 1000.0
        py = (y_mm - self.tool_offset_mm[1]) / 1000.0
        c, s = math.cos(self.piece_yaw_rad), math.sin(self.piece_yaw_rad)
        o = self.piece_origin_pose
        return [o[0] + c * px - s * py, o[1] + s * px + c * py, o[2] - self.tool_offset_mm[2] / 1000.0,
                o[3], o[4], o[5]]

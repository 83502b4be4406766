"""The UR5 press: move above a grid point of the piece, press to ~15 N, hold, retract.

Two implementations of :class:`vs2t_edge.runtime.devices.Arm`:

* :class:`URArm` on ``ur_rtde`` (RTDEControlInterface, RTDEReceiveInterface, DashboardClient),
  imported only when this backend is built. Tested against ``sim/ursim.py`` with the real client.
* :class:`FakeArm`, in-process with the same spring model and injectable faults, for fast cell
  tests.

The press uses force mode, not moveUntilContact (docs/arm.md says why in full): force mode
*regulates* the contact force, so the gel is held at 15 N while the camera grabs, whatever the
fabric's thickness and stiffness; it is non-blocking, so this process watches depth, force,
safety and time on every RTDE cycle and can abort; and it exists on CB3 and e-Series alike.
moveUntilContact stops at first contact (near 0 N), blocks without a bound of its own and
needs PolyScope >= 5.4.

Press sequence (all in the base frame, tool pointing down, piece surface at ``piece_origin_pose``
z): moveL to ``approach_height_mm`` above the point -> zeroFtSensor (no contact there, so the
sensor's offset is removed) -> forceMode along -z with the press speed as the speed limit ->
wait until the force has stayed within tolerance for ``settle_s`` -> return; force mode keeps
holding while the camera grabs -> retract(): forceModeStop, moveL back to the approach height.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import asdict, dataclass, field, fields

from vs2t_edge.runtime.dataset import PIECE_MM
from vs2t_edge.runtime.devices import (
    ArmConnectionError,
    ArmError,
    ArmSafetyStop,
    NotConnectedError,
    PressFailed,
    PressResult,
)

# Robot safety modes (RTDE "safety_mode"), the ones the press tells apart.
_SAFETY_NORMAL, _SAFETY_REDUCED = 1, 2
_SAFETY_PROTECTIVE = {3, 5, 12, 13}  # protective, safeguard, automatic-mode safeguard, 3PE stop
_SAFETY_EMERGENCY = {6, 7}  # system / robot emergency stop
_SAFETY_FAULT = {8, 9, 10, 11}  # violation, fault, validate joint id, undefined


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


class _CallTimeout(Exception):
    pass


def _bounded(fn, timeout_s: float):
    """Run a blocking ur_rtde call with a time bound.

    The client waits for its 'done' register with a 300 s timeout of its own and never notices
    a silently restarted control script; its Python bindings release the GIL, so a helper
    thread can wait for it while this one gives up. A call that overruns is abandoned (the
    thread ends when the client's own timeout fires) and the link is treated as lost.
    """
    box: dict = {}

    def run() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:  # handed to the caller's thread
            box["error"] = exc

    worker = threading.Thread(target=run, daemon=True, name="ur_rtde-call")
    worker.start()
    worker.join(timeout_s)
    if worker.is_alive():
        raise _CallTimeout()
    if "error" in box:
        raise box["error"]
    return box.get("value")


def _quiet(fn):
    def run() -> None:
        try:
            fn()
        except Exception:  # a dead link cannot be closed politely; it is dropped anyway
            pass
    return run


def _reconnected(what: str) -> ArmConnectionError:
    """The link broke during ``what`` and is back: the step was lost, the arm is usable."""
    err = ArmConnectionError(f"link to the robot lost during {what}; reconnected", device="arm",
                             kind="connection_lost")
    err.reconnected = True
    return err


def _safety_error(mode: int, where: str) -> ArmError | None:
    if mode in _SAFETY_EMERGENCY:
        return ArmSafetyStop(f"emergency stop ({where}); release it, power on and brake release "
                             "before clearing the cell", device="arm", kind="emergency_stop")
    if mode in _SAFETY_PROTECTIVE:
        return ArmSafetyStop(f"protective stop (safety mode {mode}, {where}); inspect the cause, "
                             "then unlock it on the pendant or with clear_protective_stop()",
                             device="arm", kind="protective_stop")
    if mode in _SAFETY_FAULT:
        return ArmSafetyStop(f"robot safety fault (safety mode {mode}, {where})", device="arm",
                             kind="safety_fault")
    return None


class URArm:
    """The live arm on ur_rtde. Not thread-safe: the cell loop is its only caller."""

    def __init__(self, config: ArmConfig | None = None) -> None:
        self.config = (config or ArmConfig()).validate()
        self._ctl = None
        self._rcv = None
        self._dash = None
        self._target: tuple[float, float] | None = None
        self.reconnects = 0
        self.last_telemetry: dict = {}
        self._abandoned: list = []  # client objects whose calls overran; kept alive, never reused

    # --- connection ----------------------------------------------------------------------

    def _build(self) -> None:
        import dashboard_client  # noqa: F401 - vendor SDK only when this backend is used
        import rtde_control
        import rtde_receive

        host, freq = self.config.host, self.config.rtde_frequency_hz
        dash = dashboard_client.DashboardClient(host)
        dash.connect()
        self._dash = dash  # available to the safety check even if the rest fails
        try:
            # Stop any program first. Otherwise the control constructor sends stopScript through
            # the register handshake, which never completes if the old script is still busy with
            # an earlier command - and that constructor holds the GIL, so nothing here could
            # time it out.
            dash.stop()
        except RuntimeError:
            pass  # "Failed to execute: stop" when nothing runs
        rcv = rtde_receive.RTDEReceiveInterface(host, freq)
        # Uploads the control script on the script port and waits for it to run.
        ctl = rtde_control.RTDEControlInterface(host, freq)
        self._dash, self._rcv, self._ctl = dash, rcv, ctl

    def _teardown(self) -> None:
        # The client's disconnect() sleeps 0.5 s each; closing them side by side halves that.
        objs = [o for o in (self._ctl, self._rcv, self._dash) if o is not None]
        workers = [threading.Thread(target=_quiet(o.disconnect), daemon=True) for o in objs]
        for w in workers:
            w.start()
        for obj, w in zip(objs, workers):
            w.join(3.0)
            if w.is_alive():
                self._abandoned.append(obj)  # still closing; keep it alive, never reuse it
        self._ctl = self._rcv = self._dash = None

    def connect(self) -> None:
        self._connect_with_backoff("connect")

    def _connect_with_backoff(self, why: str) -> None:
        cfg = self.config
        delay = cfg.reconnect_backoff_s
        last: Exception | None = None
        for attempt in range(cfg.reconnect_attempts + 1):
            if attempt:
                time.sleep(delay)
                delay *= 2
            self._teardown()
            try:
                self._build()
                if attempt or why != "connect":
                    self.reconnects += 1
                self._raise_if_unsafe("on connect")
                return
            except ArmSafetyStop:
                raise
            except Exception as exc:  # RuntimeError from the C++ client: refused, reset, timeout
                last = exc
                # A program cannot start in a safety stop: that is not a network problem.
                error = _safety_error(self.safety_mode(ask_dashboard=True), why)
                if error is not None:
                    self._teardown()
                    raise error from exc
        self._teardown()
        raise ArmConnectionError(f"robot at {cfg.host} unreachable after {cfg.reconnect_attempts + 1} "
                                 f"attempt(s) ({why}): {last}", device="arm", kind="connection_lost")

    def _recover_link(self, why: str) -> None:
        """The link broke. ur_rtde's control interface reconnects by itself from its receive
        thread; tearing it down while that runs crashed the client (a segfault, seen against
        the simulator), so it gets a grace period first, and only then is everything rebuilt."""
        deadline = time.monotonic() + self.config.client_reconnect_grace_s
        while time.monotonic() < deadline:
            if self._link_ok():
                self.reconnects += 1
                return
            time.sleep(0.02)
        self._connect_with_backoff(why)

    def disconnect(self) -> None:
        if self._ctl is not None and self._link_ok():
            try:
                _bounded(self._ctl.stopScript, 2.0)
            except Exception:
                pass
        self._teardown()

    def __enter__(self) -> "URArm":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self.disconnect()

    def _require(self) -> None:
        if self._ctl is None or self._rcv is None:
            raise NotConnectedError("arm used before connect()", device="arm")

    def _link_ok(self) -> bool:
        if self._ctl is None or self._rcv is None:
            return False
        try:
            return bool(self._ctl.isConnected() and self._rcv.isConnected() and self._ctl.isProgramRunning())
        except Exception:
            return False

    # --- safety --------------------------------------------------------------------------

    def safety_mode(self, ask_dashboard: bool = False) -> int:
        """Safety mode from the receive stream; from the dashboard when the stream is gone or
        when asked (a synchronous answer: the control stream can be a package ahead of the
        receive stream, so a stopped program may show before the stop that caused it)."""
        if not ask_dashboard:
            try:
                if self._rcv is not None and self._rcv.isConnected():
                    if self._rcv.isEmergencyStopped():
                        return 7
                    if self._rcv.isProtectiveStopped():
                        return 3
                    return int(self._rcv.getSafetyMode())
            except Exception:
                pass
        try:
            text = self._dash.safetymode() if self._dash is not None else ""
        except Exception:  # no stream and no dashboard: nothing says unsafe; the link check decides
            text = ""
        for name, mode in (("ROBOT_EMERGENCY_STOP", 7), ("SYSTEM_EMERGENCY_STOP", 6),
                           ("PROTECTIVE_STOP", 3), ("SAFEGUARD_STOP", 5), ("FAULT", 9),
                           ("VIOLATION", 8), ("NORMAL", 1), ("REDUCED", 2)):
            if name in text:
                return mode
        return 1

    def _raise_if_unsafe(self, where: str) -> None:
        mode = self.safety_mode()
        if _safety_error(mode, where) is None and not self._link_ok():
            mode = self.safety_mode(ask_dashboard=True)  # the link looks broken: is it a stop?
        error = _safety_error(mode, where)
        if error is not None:
            self.stop()
            raise error

    def clear_protective_stop(self) -> None:
        """Operator action after inspecting the cause: unlock, close the popup, restart the script."""
        self._require()
        self._dash.closeSafetyPopup()
        self._dash.unlockProtectiveStop()  # raises with the controller's words if refused (< 5 s)
        # The safety stop aborted the control script; reuploadScript() does not wait for it to run.
        if not _bounded(self._ctl.reuploadScript, self.config.command_timeout_s):
            raise ArmConnectionError("control script could not be re-uploaded", device="arm",
                                     kind="connection_lost")
        deadline = time.monotonic() + self.config.command_timeout_s
        while not self._link_ok():
            if time.monotonic() > deadline:
                raise ArmConnectionError("control script not running after re-upload", device="arm",
                                         kind="connection_lost")
            time.sleep(0.01)
        self._raise_if_unsafe("after clearing the protective stop")

    # --- motion helpers ------------------------------------------------------------------

    def _after_failed_call(self, what: str, *, retry) -> None:
        """A control call returned False or raised: say why, reconnecting if the link broke."""
        self._raise_if_unsafe(what)
        if not self._link_ok():
            self._recover_link(f"link lost during {what}")
            self._raise_if_unsafe(what)
            if retry is not None:
                retry()
                return
            raise _reconnected(what)
        raise PressFailed(f"robot refused {what}", device="arm", kind="timeout")

    def _call(self, what: str, fn, *, retry=None):
        try:
            ok = _bounded(fn, self.config.command_timeout_s)
        except _CallTimeout:
            # Overran: the client is stuck on a stale state; forget these objects.
            self._abandoned.extend(o for o in (self._ctl, self._rcv, self._dash) if o is not None)
            self._ctl = self._rcv = self._dash = None
            self._connect_with_backoff(f"{what} did not return within {self.config.command_timeout_s} s")
            self._raise_if_unsafe(what)
            raise PressFailed(f"{what} did not return within {self.config.command_timeout_s} s; "
                              "link re-established", device="arm", kind="timeout")
        except RuntimeError:
            ok = False
        if ok is False:
            self._after_failed_call(what, retry=retry)
        return ok

    def _pose(self) -> list[float]:
        return list(self._rcv.getActualTCPPose())

    def _force_along_press(self) -> float:
        # The contact pushes the tool up (+z in the base frame) while it presses down.
        return float(self._rcv.getActualTCPForce()[2])

    def _move_to(self, pose: list[float], what: str) -> float:
        """moveL asynchronously and wait here, so a move has a bounded time. Returns seconds."""
        cfg = self.config
        t0 = time.monotonic()
        self._call(what, lambda: self._ctl.moveL(pose, cfg.travel_speed_m_s, cfg.travel_accel_m_s2, True),
                   retry=lambda: self._move_to(pose, what))
        tol_m = cfg.position_tolerance_mm / 1000.0
        deadline = t0 + cfg.move_timeout_s
        period = 1.0 / cfg.rtde_frequency_hz
        while True:
            try:
                current = self._pose() if self._link_ok() else None
            except RuntimeError:
                current = None
            if current is not None and math.dist(current[:3], pose[:3]) <= tol_m and self._still():
                return time.monotonic() - t0
            if time.monotonic() > deadline:
                self.stop()
                self._raise_if_unsafe(what)
                if not self._link_ok():
                    self._recover_link(f"link lost during {what}")
                    return self._move_to(pose, what) + (time.monotonic() - t0)
                raise PressFailed(f"{what}: not at the target after {cfg.move_timeout_s} s", device="arm",
                                  kind="timeout")
            if current is None:
                self._raise_if_unsafe(what)
                self._recover_link(f"link lost during {what}")
                return self._move_to(pose, what) + (time.monotonic() - t0)
            self._raise_if_unsafe(what)
            time.sleep(period)

    def _still(self) -> bool:
        try:
            return math.hypot(*self._rcv.getActualTCPSpeed()[:3]) < 1e-3  # below 1 mm/s
        except RuntimeError:
            return False

    def _approach_pose(self, x_mm: float, y_mm: float) -> list[float]:
        pose = self.config.surface_pose(x_mm, y_mm)
        pose[2] += self.config.approach_height_mm / 1000.0
        return pose

    # --- the Arm interface ---------------------------------------------------------------

    def move_above(self, x_mm: float, y_mm: float) -> None:
        self._require()
        pose = self._approach_pose(x_mm, y_mm)  # raises ValueError off the piece
        self._raise_if_unsafe("before move_above")
        self._target = None
        self.last_telemetry = {"move_above_s": self._move_to(pose, f"move above ({x_mm}, {y_mm}) mm")}
        self._target = (x_mm, y_mm)

    def press(self) -> PressResult:
        self._require()
        if self._target is None:
            raise ArmError("press() before move_above()", device="arm", kind="sequence")
        try:
            return self._press_once()
        except ArmConnectionError as exc:
            if not getattr(exc, "reconnected", False):
                raise
            # The link came back: the script restarted, force mode is gone. Back up and press again.
            x, y = self._target
            self._move_to(self._approach_pose(x, y), "return to approach after reconnect")
            return self._press_once()

    def _press_once(self) -> PressResult:
        cfg = self.config
        x_mm, y_mm = self._target
        t0 = time.monotonic()
        self._call("zeroFtSensor", self._ctl.zeroFtSensor)
        time.sleep(2.0 / cfg.rtde_frequency_hz)  # the next RTDE packages carry the zeroed force
        surface_z = cfg.surface_pose(x_mm, y_mm)[2]
        limits = [0.1, 0.1, cfg.press_speed_m_s, 0.17, 0.17, 0.17]
        wrench = [0.0, 0.0, -cfg.force_n, 0.0, 0.0, 0.0]
        self._call("forceMode", lambda: self._ctl.forceMode([0.0] * 6, [0, 0, 1, 0, 0, 0], wrench, 2, limits))
        period = 1.0 / cfg.rtde_frequency_hz
        contact_z = contact_t = settled_since = None
        samples: list[tuple[float, float, float]] = []  # (t, z, force)
        max_force = 0.0
        while True:
            now = time.monotonic()
            try:
                link_ok = self._link_ok()
                if link_ok:
                    self._raise_if_unsafe("press")
                    pose = self._pose()
                    force = self._force_along_press()
            except RuntimeError:  # the C++ client raises when the stream broke under it
                link_ok = False
            if not link_ok:
                self._raise_if_unsafe("press")
                self.stop()
                self._recover_link("link lost during press")
                raise _reconnected("press")
            samples.append((now - t0, pose[2], force))
            max_force = max(max_force, force)
            if contact_z is None and force >= cfg.contact_threshold_n:
                contact_z, contact_t = pose[2], now
                if len(samples) >= 2 and force > samples[-2][2]:
                    # Interpolate to where the force crossed the threshold between two packages,
                    # so the depth does not depend on the RTDE cycle at which contact was seen.
                    _, z_prev, f_prev = samples[-2]
                    frac = (cfg.contact_threshold_n - f_prev) / (force - f_prev)
                    contact_z = z_prev + min(max(frac, 0.0), 1.0) * (pose[2] - z_prev)
            if force > cfg.force_max_n:
                self.stop()
                raise PressFailed(f"overforce: {force:.1f} N > {cfg.force_max_n} N at ({x_mm}, {y_mm}) mm",
                                  device="arm", kind="overforce")
            depth_below_surface_mm = (surface_z - pose[2]) * 1000.0
            if depth_below_surface_mm > cfg.max_press_depth_mm and force < cfg.force_n - cfg.force_tolerance_n:
                self.stop()
                raise PressFailed(f"force never reached: {force:.1f} N at {depth_below_surface_mm:.1f} mm "
                                  f"below the expected surface at ({x_mm}, {y_mm}) mm", device="arm",
                                  kind="force_not_reached")
            if abs(force - cfg.force_n) <= cfg.force_tolerance_n:
                settled_since = settled_since or now
                if now - settled_since >= cfg.settle_s:
                    break
            else:
                settled_since = None
            if now - t0 > cfg.press_timeout_s:
                self.stop()
                raise PressFailed(f"press timed out after {cfg.press_timeout_s} s at {force:.1f} N "
                                  f"(target {cfg.force_n} N)", device="arm", kind="timeout")
            time.sleep(period)
        # The force "at the grab": mean of the last 50 ms, so one noisy package does not count.
        window = [f for t, _, f in samples if t >= samples[-1][0] - 0.05]
        held = sum(window) / len(window)
        depth_mm = 0.0 if contact_z is None else (contact_z - pose[2]) * 1000.0
        telemetry = {
            **self.last_telemetry,
            "press_s": round(time.monotonic() - t0, 4),
            "contact_after_s": None if contact_t is None else round(contact_t - t0, 4),
            "max_force_n": round(max_force, 3),
            "contact_z_m": contact_z,
            "samples": len(samples),
            "reconnects": self.reconnects,
        }
        self.last_telemetry = telemetry
        return PressResult(x_mm=x_mm, y_mm=y_mm, force_n=held, depth_mm=depth_mm,
                           tcp_pose=tuple(pose), telemetry=telemetry)

    def retract(self) -> None:
        self._require()
        self._call("forceModeStop", self._ctl.forceModeStop)
        pose = self._pose()
        pose[2] = self.config.surface_pose(*(self._target or (0.0, 0.0)))[2] + self.config.approach_height_mm / 1000.0
        self._move_to(pose, "retract")

    def stop(self) -> None:
        """Stop now: leave force mode and brake. Never raises (used on every fault path)."""
        ctl = self._ctl
        if ctl is None or not self._link_ok():
            return  # nothing to command over a dead link; the controller's own watchdogs stop it
        for step in (ctl.forceModeStop, lambda: ctl.stopL(2.0)):
            try:
                _bounded(step, 1.5)
            except Exception:
                pass


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


# --- the live arm in a supervised worker process ------------------------------------------

_WORKER_METHODS = ("connect", "disconnect", "move_above", "press", "retract", "stop", "clear_protective_stop")
_ERRORS = {cls.__name__: cls for cls in (ArmError, ArmConnectionError, ArmSafetyStop, PressFailed,
                                         NotConnectedError, ArmConfigError, ValueError)}


WORKER_START_TIMEOUT_S = 30.0  # IsolatedURArm: a new worker process starting (runtime/budget.py counts it)


def isolated_call_bound_s(c: ArmConfig) -> float:
    """The longest one IsolatedURArm call may take before the worker is ended and the call fails:
    a move or press plus every reconnect it may do. runtime/budget.py's watchdog budget uses it."""
    backoff = sum(c.reconnect_backoff_s * 2 ** i for i in range(c.reconnect_attempts))
    return (c.move_timeout_s + c.press_timeout_s + 3 * c.command_timeout_s + backoff
            + c.client_reconnect_grace_s + 15.0 * (c.reconnect_attempts + 1))


class IsolatedURArm:
    """:class:`URArm` in a worker process, so that a crash of the ur_rtde client costs one
    step and not the cell.

    ur_rtde 1.6.5 segfaults its process when the robot drops the link and accepts it again at
    once (its own reconnect loops; docs/arm.md). Here the worker dies instead: the call raises
    ``ArmConnectionError(kind="connection_lost")`` naming the exit code, and the next call starts
    a new worker and connects it (``worker_restarts`` counts them). Calls travel as JSON lines
    over two private pipes; the client's own stdout chatter goes to a log file.
    """

    def __init__(self, config: ArmConfig | None = None, *, start_timeout_s: float = WORKER_START_TIMEOUT_S) -> None:
        self.config = (config or ArmConfig()).validate()
        self.start_timeout_s = start_timeout_s
        self.worker_restarts = 0
        self.worker_exit_codes: list[int] = []
        self._proc = None
        self._req = None
        self._rep = None
        self._log = None
        self._wanted = False  # connect() was called and disconnect() not yet

    def _call_bound_s(self) -> float:
        return isolated_call_bound_s(self.config)

    def _spawn(self) -> None:
        import json
        import os
        import subprocess
        import sys
        import tempfile

        req_r, req_w = os.pipe()
        rep_r, rep_w = os.pipe()
        self._log = tempfile.TemporaryFile(mode="w+")
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "vs2t_edge.runtime.arm", "--worker", str(req_r), str(rep_w),
             json.dumps(self.config.to_dict())],
            pass_fds=(req_r, rep_w), stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log)
        os.close(req_r)
        os.close(rep_w)
        self._req = os.fdopen(req_w, "w", buffering=1)
        self._rep = os.fdopen(rep_r, "r")

    def _reap(self) -> None:
        proc, self._proc = self._proc, None
        for stream in (self._req, self._rep):
            try:
                if stream is not None:
                    stream.close()
            except OSError:
                pass
        self._req = self._rep = None
        if proc is not None:
            try:
                proc.wait(timeout=5.0)
            except Exception:
                proc.kill()
                proc.wait()
            self.worker_exit_codes.append(proc.returncode)

    def worker_log(self) -> str:
        if self._log is None:
            return ""
        self._log.flush()
        self._log.seek(0)
        return self._log.read()

    def _send(self, method: str, args: tuple, timeout_s: float):
        import json
        import select

        hung = False
        try:
            self._req.write(json.dumps({"method": method, "args": list(args)}) + "\n")
            self._req.flush()
            ready, _, _ = select.select([self._rep], [], [], timeout_s)
            hung = not ready
            line = self._rep.readline() if ready else ""
        except (OSError, ValueError):
            line = ""
        if not line:
            if hung and self._proc is not None:
                self._proc.kill()  # past every bound of its own: end it
            self._reap()  # waits for the exit (a crash closes the pipe a moment before it ends)
            code = self.worker_exit_codes[-1] if self.worker_exit_codes else None
            raise ArmConnectionError(f"arm worker {'hung' if hung else 'died'} during {method} "
                                     f"(exit code {code}); it is restarted on the next call",
                                     device="arm", kind="connection_lost")
        reply = json.loads(line)
        if reply["status"] == "ok":
            return reply.get("value")
        cls = _ERRORS.get(reply["type"], ArmError)
        if issubclass(cls, ArmError) or cls is NotConnectedError:
            err = cls(reply["message"], device="arm", kind=reply.get("kind", ""))
            if reply.get("reconnected"):
                err.reconnected = True
        else:
            err = cls(reply["message"])
        raise err

    def _call(self, method: str, *args):
        if self._proc is None or self._proc.poll() is not None:
            if self._proc is not None:
                self._reap()
            if method in ("stop", "disconnect"):
                return None  # nothing to stop: the worker is gone and its robot link with it
            if not self._wanted and method != "connect":
                raise NotConnectedError("arm used before connect()", device="arm")
            self._spawn()
            if self.worker_exit_codes:
                self.worker_restarts += 1
            self._send("connect", (), self.start_timeout_s + self._call_bound_s())
            if method == "connect":
                return None
        return self._send(method, args, self._call_bound_s())

    def connect(self) -> None:
        self._wanted = True
        self._call("connect")

    def disconnect(self) -> None:
        self._wanted = False
        try:
            self._call("disconnect")
        except ArmError:
            pass
        if self._proc is not None:
            try:
                self._req.close()  # EOF: the worker leaves its loop and exits
            except OSError:
                pass
            self._reap()

    def move_above(self, x_mm: float, y_mm: float) -> None:
        self.config.surface_pose(x_mm, y_mm)  # off the piece: refused here, no worker needed
        self._call("move_above", x_mm, y_mm)

    def press(self) -> PressResult:
        d = self._call("press")
        d["tcp_pose"] = tuple(d["tcp_pose"])
        return PressResult(**d)

    def retract(self) -> None:
        self._call("retract")

    def stop(self) -> None:
        if self._proc is None or self._proc.poll() is not None:
            return  # no worker, no link: nothing to command
        try:
            self._send("stop", (), 5.0)  # stop is quick or the worker is hung (then it is ended)
        except Exception:  # must not raise: the fault paths call it
            pass

    def clear_protective_stop(self) -> None:
        self._call("clear_protective_stop")

    def __enter__(self) -> "IsolatedURArm":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self.disconnect()


def _worker_main(req_fd: int, rep_fd: int, config_json: str) -> None:
    import json
    import os

    rep = os.fdopen(rep_fd, "w", buffering=1)
    arm = URArm(ArmConfig.from_dict(json.loads(config_json)))

    def reply(payload: dict) -> None:
        rep.write(json.dumps(payload, default=float) + "\n")
        rep.flush()

    try:
        with os.fdopen(req_fd, "r") as req:
            for line in req:
                request = json.loads(line)
                method = request["method"]
                if method not in _WORKER_METHODS:
                    reply({"status": "error", "type": "ArmError", "message": f"unknown method {method}"})
                    continue
                try:
                    value = getattr(arm, method)(*request["args"])
                    if isinstance(value, PressResult):
                        value = asdict(value)
                    reply({"status": "ok", "value": value})
                except Exception as exc:
                    reply({"status": "error", "type": type(exc).__name__, "message": str(exc),
                           "kind": getattr(exc, "kind", ""), "reconnected": getattr(exc, "reconnected", False)})
    finally:
        arm.stop()
        arm.disconnect()


if __name__ == "__main__":  # the worker of IsolatedURArm: python -m vs2t_edge.runtime.arm --worker R W CONFIG
    import sys

    if len(sys.argv) == 5 and sys.argv[1] == "--worker":
        _worker_main(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])
    else:
        print("usage: python -m vs2t_edge.runtime.arm --worker REQ_FD REP_FD CONFIG_JSON", file=sys.stderr)
        sys.exit(2)

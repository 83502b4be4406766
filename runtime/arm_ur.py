"""The live UR5 press on ur_rtde: move above a grid point of the piece, press to ~15 N, hold,
retract.

:class:`URArm` drives the robot with ``ur_rtde`` (RTDEControlInterface, RTDEReceiveInterface,
DashboardClient), imported only when a connection is built. Tested against the loopback
simulator (``sim/ursim.py``) with the real client. The service runs it in a worker process
(``runtime/arm_isolated.py``); its settings are ``runtime/arm.py``'s ArmConfig.

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

from vs2t_edge.runtime.arm import ArmConfig
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

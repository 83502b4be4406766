"""Fault-matrix rows at the arm: stops, force not reached, a lost link, a slow piece; the UR simulator.

Loop rows on FakeArm (the loop's logic), and ``ursim`` rows on the real ur_rtde client
(IsolatedURArm) against the loopback UR simulator; registered in sim/faults.py SCENARIOS.
"""

from __future__ import annotations

import math
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from vs2t_edge.sim.fault_rig import Rig, _at, _check, _loop_row


def _fake_arm_fault(kind: str, count: int = 1):
    def inject(r: Rig):
        _at(r, 1, 2, lambda: r.arm.inner.fail_next.extend([kind] * count))
    return inject


def _release(r: Rig):
    return lambda: setattr(r.arm.inner, "latched", "")  # the operator releases the stop at the pendant


def protective_stop_fake(w: Path):
    return _loop_row(w, inject=_fake_arm_fault("protective_stop"), operator_fix_for=_release,
                     expect_outcomes={"sorted": 3, "rejected_fault": 1}, fault_words="protective_stop")


def emergency_stop_fake(w: Path):
    return _loop_row(w, inject=_fake_arm_fault("emergency_stop"), operator_fix_for=_release,
                     expect_outcomes={"sorted": 3, "rejected_fault": 1}, fault_words="emergency_stop")


def force_not_reached_once(w: Path):
    return _loop_row(w, inject=_fake_arm_fault("force_not_reached"), expect_outcomes={"sorted": 4},
                     fault_words=None, retries=1)


def force_never_reached(w: Path):
    return _loop_row(w, inject=_fake_arm_fault("force_not_reached", 2),
                     expect_outcomes={"sorted": 3, "rejected_fault": 1}, fault_words="failed twice", retries=1)


class LinkDrop:
    """The robot link drops in the middle of a press, and the arm really is disconnected.

    Wraps FakeArm the way IsolatedURArm behaves: ``press`` starts (the gel goes down), then the
    link drops - the inner arm is disconnected (any call on it now raises NotConnectedError), the
    press state (the target, force mode) is gone, and the press raises ArmConnectionError. The
    next motion call reconnects first (a new worker, a new link), as the real arm does; ``stop``
    and ``disconnect`` on a dead link do nothing. ``log`` records what happened, in order."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.drop_in_next_press = False
        self.down = False
        self.reconnects = 0
        self.log: list[str] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def _up(self) -> None:
        if self.down:
            self.inner.connect()
            self.down = False
            self.reconnects += 1
            self.log.append("reconnect")

    def connect(self) -> None:
        self.down = False
        self.inner.connect()

    def disconnect(self) -> None:
        if not self.down:
            self.inner.disconnect()

    def stop(self) -> None:
        if not self.down:
            self.inner.stop()

    def move_above(self, x_mm: float, y_mm: float) -> None:
        self._up()
        self.log.append("move_above")
        self.inner.move_above(x_mm, y_mm)

    def press(self):
        self._up()
        self.log.append("press")
        result = self.inner.press()  # the descent is under way ...
        if self.drop_in_next_press:
            from vs2t_edge.runtime.devices import ArmConnectionError

            self.drop_in_next_press = False
            self.inner.disconnect()  # ... and the link goes: really disconnected
            self.inner._target = None  # the controller's script restarted: no target, no force mode
            self.down = True
            self.log.append("drop")
            raise ArmConnectionError("link to the robot lost during press (injected mid-press)", device="arm",
                                     kind="connection_lost")
        return result

    def retract(self) -> None:
        self._up()
        self.log.append("retract")
        self.inner.retract()

    def clear_protective_stop(self) -> None:
        self._up()
        self.inner.clear_protective_stop()


def arm_connection_lost_fake(w: Path):
    """The link drops mid-press (FakeArm really disconnected, see LinkDrop): the arm reconnects on
    the next call and the cell retries the whole press (move_above first: the old target is gone,
    a bare re-press would be refused). One retry record, no fault, all sorted, nothing lost."""
    from vs2t_edge.runtime.arm import ArmConfig
    from vs2t_edge.sim.fake_devices import FakeArm
    from vs2t_edge.sim.scene import FAST_PRESS

    link = LinkDrop(FakeArm(config=ArmConfig(**FAST_PRESS)))

    def inject(r: Rig) -> None:
        _at(r, 1, 2, lambda: setattr(link, "drop_in_next_press", True))

    held: dict = {}
    words, problems = _loop_row(w, inject=inject, arm=link, expect_outcomes={"sorted": 4}, fault_words=None,
                                retries=1, holder_out=held)
    log = link.log
    after = log[log.index("drop") + 1:] if "drop" in log else []
    _check(problems, "drop" in log, "the link never dropped")
    _check(problems, link.reconnects == 1 and after[:1] == ["reconnect"],
           f"expected one reconnect right after the drop, got {link.reconnects}: {after[:4]}")
    _check(problems, "press" in after and "move_above" in after and after.index("move_above") < after.index("press"),
           f"the press was not retried from move_above after the reconnect: {after[:6]}")
    retry = held["audit"]["retries"]
    _check(problems, len(retry) == 1 and retry[0].get("item") == 2 and retry[0].get("kind") == "connection_lost"
           and retry[0].get("step", "").startswith("press"),
           f"the retry record does not name piece 2's press and the lost link: {retry}")
    return words + f"; link dropped mid-press, {link.reconnects} reconnect, press redone from move_above", problems


def item_over_time_budget(w: Path):
    # a slow robot: the piece takes longer than item_timeout_s -> latched fault, piece rejected
    def inject(r: Rig):
        _at(r, 1, 1, lambda: r.cell.scene.__setattr__("item_timeout_s", 0.0))

    def restore(r: Rig):
        return lambda: r.cell.scene.__setattr__("item_timeout_s", 60.0)
    return _loop_row(w, inject=inject, operator_fix_for=restore,
                     expect_outcomes={"sorted": 3, "rejected_fault": 1}, fault_words="longer than")


# --- UR simulator rows (real ur_rtde client in a worker process, loopback simulator) ---------

@contextmanager
def _ursim_arm():
    """(the loopback UR simulator, an IsolatedURArm on it: the real ur_rtde client); the simulator
    is stopped on leaving."""
    from vs2t_edge.runtime.arm import ArmConfig
    from vs2t_edge.runtime.arm_isolated import IsolatedURArm
    from vs2t_edge.sim.scene import FAST_PRESS
    from vs2t_edge.sim.ursim import free_loopback_host
    from vs2t_edge.sim.ursim_model import PressScene
    from vs2t_edge.sim.ursim_process import URSimProcess

    sim = URSimProcess(PressScene(home_pose=(0.42, -0.08, 0.110, 0.0, math.pi, 0.0)),
                       host=free_loopback_host()).start()
    try:
        yield sim, IsolatedURArm(ArmConfig(host=sim.host, **FAST_PRESS))
    finally:
        sim.stop()


def _ursim_row(w: Path, trigger: str, expect_outcomes: dict, fault_words: str | None, retries=None):
    pytest_skip = _need_rtde()
    if pytest_skip:
        return pytest_skip, ["ur_rtde not installed"]
    with _ursim_arm() as (sim, arm):
        def inject(r: Rig):
            if trigger == "overforce_in_descent":
                # the controller's protective stop trips on the way down, once the gel is in contact
                _at(r, 1, 1, lambda: sim.set_faults(protective_stop_above_n=8.0))
            elif trigger == "trigger_emergency_stop":
                # the button is hit while the press is under way, not between commands
                _at(r, 1, 1, lambda: threading.Timer(0.12, sim.trigger_emergency_stop).start())
            else:
                raise ValueError(f"_ursim_row: unknown trigger {trigger!r}")

        def operator(r: Rig):
            def fix():
                if trigger == "trigger_emergency_stop":
                    sim.release_emergency_stop()
                sim.reset()
            return fix
        return _loop_row(w, inject=inject, operator_fix_for=operator, truths=["denim", "silk", "tweed"],
                         arm=arm, expect_outcomes=expect_outcomes, fault_words=fault_words,
                         retries=retries, max_presses=2)


def _need_rtde() -> str:
    try:
        import rtde_control  # noqa: F401
    except ImportError:
        return "skipped: ur_rtde missing"
    return ""


def protective_stop_ursim(w: Path):
    return _ursim_row(w, "overforce_in_descent", {"sorted": 2, "rejected_fault": 1}, "protective")


def emergency_stop_ursim(w: Path):
    return _ursim_row(w, "trigger_emergency_stop", {"sorted": 2, "rejected_fault": 1}, "emergency")


def connection_drop_ursim(w: Path):
    """The controller drops every connection while the arm is in force mode, pressing piece 1
    (refusing new ones for 1 s). The arm must reconnect (URArm's own link recovery, or a new
    worker if the ur_rtde client crashed its process) and the interrupted press must be done
    again (inside the arm, or by the cell's one retry); no fault, all sorted, nothing lost."""
    pytest_skip = _need_rtde()
    if pytest_skip:
        return pytest_skip, ["ur_rtde not installed"]
    from vs2t_edge.sim.ursim_model import CMD_ZERO_FT

    seen: dict = {}
    calls: list[dict] = []  # every press call on the arm: start, end, error, reconnects in its telemetry
    with _ursim_arm() as (sim, arm):
        real_press = arm.press

        def press():
            c = {"start": time.monotonic()}
            calls.append(c)
            try:
                res = real_press()
                c["reconnects"] = (res.telemetry or {}).get("reconnects", 0)
                return res
            except Exception as exc:  # noqa: BLE001 - recorded, raised as the cell sees it
                c["error"] = type(exc).__name__ + ": " + str(exc)[:120]
                raise
            finally:
                c["end"] = time.monotonic()
        arm.press = press

        def drop_in_force_mode() -> None:
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                snap = sim.snapshot()
                if snap["force_mode"] and snap["force_n"] >= 1.0:  # in force mode, the gel on the piece
                    sim.drop_connections()
                    seen.update(at=time.monotonic(), force_n=snap["force_n"], z=snap["pose"][2])
                    return
                time.sleep(0.002)

        def inject(r: Rig) -> None:
            _at(r, 1, 1, lambda: threading.Thread(target=drop_in_force_mode, daemon=True).start())

        words, problems = _loop_row(w, inject=inject, truths=["denim", "silk", "tweed"], arm=arm,
                                    expect_outcomes={"sorted": 3}, fault_words=None, max_presses=2,
                                    holder_out=seen)
        rig = seen["rig"]
        drops = len(sim.get_log().get("drops", []))
        zero_ft = sim.get_log().get("commands", []).count(CMD_ZERO_FT)
    at = seen.get("at")
    _check(problems, drops == 1 and at is not None, f"{drops} drops; the force-mode drop did not fire")
    hit = [c for c in calls if at is not None and c["start"] <= at <= c.get("end", 0.0)]
    _check(problems, len(hit) == 1, f"the drop did not land inside one press call: drop at {at}, calls {calls}")
    c = hit[0] if hit else {}
    restarts = arm.worker_restarts
    inside = "error" not in c and c.get("reconnects", 0) >= 1  # URArm reconnected and pressed again itself
    by_cell = "error" in c and restarts >= 1  # the worker died; the cell retried on a new one
    _check(problems, inside or by_cell,
           f"no reconnect seen for the interrupted press: {c}, worker restarts {restarts}")
    retries = len(seen["audit"]["retries"])
    _check(problems, retries == (1 if by_cell else 0), f"{retries} cell retries (press call {c})")
    # each press starts with zeroFtSensor: the interrupted one shows as one more than the presses done
    _check(problems, zero_ft == rig.arm.press_count + 1,
           f"{zero_ft} presses started for {rig.arm.press_count} done: the interrupted press was not redone")
    how = (f"arm reconnected itself (telemetry reconnects {c.get('reconnects')}) and pressed again" if inside
           else f"worker died ({c.get('error', '')[:60]}), cell retried on a new worker" if by_cell else "no reconnect")
    return words + (f"; link dropped in force mode ({seen.get('force_n', 0):.1f} N); {how}; "
                    f"{zero_ft} presses started for {rig.arm.press_count} done"), problems


def force_never_reached_ursim(w: Path):
    # nothing under the tool for piece 1: force not reached twice -> fault; fabric back, clear
    pytest_skip = _need_rtde()
    if pytest_skip:
        return pytest_skip, ["ur_rtde not installed"]
    with _ursim_arm() as (sim, arm):
        return _loop_row(w, inject=lambda r: _at(r, 1, 1, lambda: sim.set_faults(no_surface=True)),
                         # the operator puts the fabric back; the controller is not reset: the cell
                         # lifted the sensor before latching, so nothing is in the way
                         operator_fix_for=lambda r: (lambda: sim.set_faults(no_surface=False)),
                         truths=["denim", "silk", "tweed"], arm=arm, max_presses=2,
                         expect_outcomes={"sorted": 2, "rejected_fault": 1}, fault_words="twice", retries=1)

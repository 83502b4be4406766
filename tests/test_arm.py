"""The press routine: config bounds, the fake arm, and URArm on the real ur_rtde client against
the loopback UR simulator - full press, protective stop, e-stop, link loss, force faults."""

from __future__ import annotations

import dataclasses
import math
import threading
import time

import pytest

from vs2t_edge.runtime.arm import ArmConfig, ArmConfigError
from vs2t_edge.sim.fake_devices import FakeArm
from vs2t_edge.runtime.arm_isolated import IsolatedURArm
from vs2t_edge.runtime.arm_ur import URArm
from vs2t_edge.runtime.devices import (
    Arm,
    ArmConnectionError,
    ArmSafetyStop,
    NotConnectedError,
    PressFailed,
)
from vs2t_edge.sim.ursim import free_loopback_host
from vs2t_edge.sim.ursim_model import PressScene
from vs2t_edge.sim.ursim_process import URSimProcess

SURFACE_Z = 0.102  # PressScene(): table 0.100 + 2 mm fabric


# --- config -------------------------------------------------------------------------------

@pytest.mark.parametrize("key,value", [
    ("force_n", 0.5), ("force_n", 41.0), ("travel_speed_m_s", 1.0), ("press_speed_m_s", 0.0),
    ("approach_height_mm", 0.0), ("press_timeout_s", 0.1), ("reconnect_attempts", 11),
    ("grid_step_x_mm", 0.0), ("travel_accel_m_s2", float("nan")),
])
def test_config_bounds_name_the_key(key, value):
    with pytest.raises(ArmConfigError, match=f"arm.{key}"):
        dataclasses.replace(ArmConfig(), **{key: value}).validate()


@pytest.mark.parametrize("key,value", [
    ("piece_yaw_rad", float("nan")), ("piece_yaw_rad", float("inf")), ("piece_yaw_rad", 4.0),
    ("reconnect_attempts", 2.5), ("reconnect_attempts", True),
])
def test_yaw_is_finite_and_bounded_and_attempts_are_counts(key, value):
    with pytest.raises(ArmConfigError, match=f"arm.{key} = {value!r}"):
        dataclasses.replace(ArmConfig(), **{key: value}).validate()
    assert ArmConfig(piece_yaw_rad=-math.pi / 2, reconnect_attempts=2).validate()


@pytest.mark.parametrize("key", ["grid_step_x_mm", "grid_step_y_mm"])
def test_a_grid_step_too_wide_for_the_piece_is_refused_naming_the_largest(key):
    """10 mm steps are within the key's own bounds but the 15 x 15 grid would span 140 mm of an
    80 mm piece; the error must come from validate(), not later from press_grid_mm."""
    with pytest.raises(ArmConfigError, match=rf"arm.{key} = 10.0: .*140 mm.*80 mm piece.*at most 5.714 mm"):
        ArmConfig(**{key: 10.0}).validate()
    largest = ArmConfig(**{key: 80 / 14}).validate()  # exactly the piece: accepted, and usable
    assert len(largest.grid_points_mm()) == 225
    steps = {"grid_step_x_mm": 3.5, "grid_step_y_mm": 3.5, key: 4.9}  # a smaller piece: its largest step
    with pytest.raises(ArmConfigError, match=rf"arm.{key} = 4.9: .*68.6 mm.*50 mm piece.*at most 3.571 mm"):
        ArmConfig(piece_mm=50.0, **steps).validate()


def test_config_cross_checks_and_unknown_keys():
    with pytest.raises(ArmConfigError, match="force_max_n"):
        ArmConfig(force_n=20.0, force_max_n=20.5).validate()
    with pytest.raises(ArmConfigError, match="unknown key"):
        ArmConfig.from_dict({"force": 15})
    cfg = ArmConfig.from_dict({"force_n": 12, "piece_origin_pose": [0.3, 0, 0.1, 0, math.pi, 0]})
    assert cfg.force_n == 12 and cfg.piece_origin_pose[0] == 0.3


def test_grid_and_piece_geometry():
    cfg = ArmConfig(piece_origin_pose=(0.5, 0.0, 0.1, 0.0, math.pi, 0.0), piece_yaw_rad=math.pi / 2,
                    tool_offset_mm=(0.0, 0.0, 1.0))
    points = cfg.grid_points_mm()
    assert len(points) == 225
    assert points[1][0] - points[0][0] == pytest.approx(4.9)
    assert points[15][1] - points[0][1] == pytest.approx(4.6)
    pose = cfg.surface_pose(10.0, 0.0)
    # piece x runs along base +y when the piece is turned 90 degrees; the offset lifts the TCP.
    assert pose[:3] == pytest.approx([0.5, 0.01, 0.099])
    with pytest.raises(ValueError, match="off the"):
        cfg.surface_pose(81.0, 5.0)


# --- fake arm -----------------------------------------------------------------------------

def test_fake_arm_press_and_faults():
    arm = FakeArm(fail_next=["connection_lost", "force_not_reached", "protective_stop"])
    assert isinstance(arm, Arm)
    with pytest.raises(NotConnectedError):
        arm.move_above(5.7, 7.8)
    arm.connect()
    with pytest.raises(ArmConnectionError):
        arm.move_above(5.7, 7.8)
    arm.move_above(5.7, 7.8)
    with pytest.raises(PressFailed) as exc:
        arm.press()
    assert exc.value.kind == "force_not_reached" and exc.value.retryable
    with pytest.raises(ArmSafetyStop):
        arm.press()
    with pytest.raises(ArmSafetyStop):  # latched until cleared
        arm.retract()
    arm.clear_protective_stop()
    result = arm.press()
    assert result.force_n == 15.0 and result.depth_mm == pytest.approx(2.0 + (15 - 12) / 400)


# --- URArm on the real ur_rtde client against the simulator ----------------------------------

@pytest.fixture(scope="module")
def sim():
    pytest.importorskip("rtde_control")
    # Home right above the piece so moves stay short in tests.
    scene = PressScene(home_pose=(0.42, -0.08, 0.110, 0.0, math.pi, 0.0))
    with URSimProcess(scene, host=free_loopback_host()) as s:
        yield s


def _config(sim, **kw) -> ArmConfig:
    base = dict(host=sim.host, approach_height_mm=5.0, travel_speed_m_s=0.25, travel_accel_m_s2=1.5,
                press_speed_m_s=0.02, reconnect_backoff_s=0.2, press_timeout_s=3.0, move_timeout_s=5.0,
                client_reconnect_grace_s=0.5)
    base.update(kw)
    return ArmConfig(**base)


@pytest.fixture
def arm(sim):
    sim.reset()
    sim.clear_log()
    a = URArm(_config(sim))
    a.connect()
    yield a
    a.stop()
    a.disconnect()
    sim.reset()


def test_full_press_at_a_grid_point(arm, sim):
    assert isinstance(arm, Arm)
    x, y = arm.config.grid_points_mm()[112]  # the centre of the 15 x 15 grid
    t0 = time.monotonic()
    arm.move_above(x, y)
    t_move = time.monotonic()
    result = arm.press()
    t_press = time.monotonic()
    # The camera grabs now (the cell calls grab() between press() and retract()); a GelSight frame
    # takes a frame period or two, so the robot's state is read at the start and 0.1 s later.
    at_grab = [sim.snapshot()]
    time.sleep(0.1)
    at_grab.append(sim.snapshot())
    arm.retract()
    t_retract = time.monotonic()
    after = sim.snapshot()
    assert (result.x_mm, result.y_mm) == (x, y)
    assert result.force_n == pytest.approx(15.0, abs=arm.config.force_tolerance_n)
    # Force mode still regulates 15 N on the gel during the grab: the controller's contact force
    # and the tool height (the gel stays pressed into the fabric) are those of the press.
    for state in at_grab:
        assert state["force_mode"] is True
        assert state["force_n"] == pytest.approx(15.0, abs=arm.config.force_tolerance_n)
        assert state["pose"][2] == pytest.approx(result.tcp_pose[2], abs=1e-4)
    assert after["force_mode"] is False and after["force_n"] == 0.0  # retract() left force mode, lifted the gel
    expected = arm.config.surface_pose(x, y)
    assert result.tcp_pose[:2] == pytest.approx(expected[:2], abs=1e-4)
    # 2 mm fabric at 6 N/mm gives 12 N, the last 3 N come from the table: 2.0075 mm below the
    # surface; first contact (1 N) is 1/6 mm below it, so the depth after contact is 1.84 mm.
    assert result.depth_mm == pytest.approx(2.0075 - 1 / 6, abs=0.15)
    assert result.tcp_pose[2] == pytest.approx(SURFACE_Z - 0.0020075, abs=2e-4)
    assert result.telemetry["contact_after_s"] is not None
    assert sim.snapshot()["pose"][2] == pytest.approx(SURFACE_Z + 0.005, abs=2e-4)
    commands = sim.get_log()["commands"]
    assert commands[:5] == [3, 8, 6, 7, 3]  # moveL, zeroFtSensor, forceMode, forceModeStop, moveL
    print(f"timings: move_above {t_move - t0:.3f} s, press {t_press - t_move:.3f} s, "
          f"retract {t_retract - t_press:.3f} s")


def test_protective_stop_mid_press_then_operator_clears_it(arm, sim):
    arm.move_above(20.0, 20.0)
    sim.set_faults(protective_stop_above_n=8.0)
    with pytest.raises(ArmSafetyStop) as exc:
        arm.press()
    assert exc.value.kind == "protective_stop" and not exc.value.retryable
    assert sim.get_log()["safety_stops"][0][1] == "injected mid-press"
    with pytest.raises(ArmSafetyStop):
        arm.move_above(20.0, 20.0)  # stays refused until cleared
    sim.set_faults(protective_stop_above_n=None)
    arm.clear_protective_stop()
    arm.move_above(20.0, 20.0)
    assert arm.press().force_n == pytest.approx(15.0, abs=1.0)


def test_emergency_stop_is_reported_as_such(arm, sim):
    arm.move_above(30.0, 30.0)
    threading.Timer(0.2, sim.trigger_emergency_stop).start()
    with pytest.raises(ArmSafetyStop) as exc:
        arm.press()
    assert exc.value.kind == "emergency_stop"


def test_connection_drop_mid_press_reconnects_and_presses(arm, sim):
    arm.move_above(40.0, 40.0)
    # Cut every link and refuse new ones for 0.5 s: the client's own reconnect fails, ours backs off.
    threading.Timer(0.25, lambda: sim.drop_connections(0.5)).start()
    result = arm.press()
    assert arm.reconnects >= 1
    assert result.force_n == pytest.approx(15.0, abs=1.0)
    assert len(sim.get_log()["drops"]) == 1


def test_connection_drop_during_a_move_redoes_the_move(arm, sim):
    arm.move_above(10.0, 10.0)
    arm.config = dataclasses.replace(arm.config, travel_speed_m_s=0.02)  # a long move to cut into
    threading.Timer(0.3, lambda: sim.drop_connections(0.5)).start()
    arm.move_above(60.0, 60.0)
    assert arm.reconnects >= 1
    expected = arm.config.surface_pose(60.0, 60.0)
    assert sim.snapshot()["pose"][:3] == pytest.approx([expected[0], expected[1], expected[2] + 0.005], abs=2e-4)


def test_force_never_reached(arm, sim):
    arm.move_above(50.0, 50.0)
    sim.set_faults(no_surface=True)
    with pytest.raises(PressFailed) as exc:
        arm.press()
    assert exc.value.kind == "force_not_reached" and exc.value.retryable
    # The arm stopped itself just past the allowed depth, not somewhere below the table.
    assert sim.snapshot()["pose"][2] > SURFACE_Z - (arm.config.max_press_depth_mm + 1.0) / 1000.0
    arm.retract()  # back up before the table "returns", or it would be inside the tool
    sim.set_faults(no_surface=False)
    arm.move_above(50.0, 50.0)


def test_overforce_on_a_hard_spot(arm, sim):
    arm.move_above(60.0, 10.0)
    sim.set_faults(hard_spot_n=20.0)
    with pytest.raises(PressFailed) as exc:
        arm.press()
    assert exc.value.kind == "overforce"


def test_slow_robot_times_out(arm, sim):
    arm.move_above(10.0, 60.0)
    sim.set_faults(motion_speed_factor=0.02)
    arm.config = dataclasses.replace(arm.config, press_timeout_s=1.0)
    with pytest.raises(PressFailed) as exc:
        arm.press()
    assert exc.value.kind == "timeout"


@pytest.mark.slow
def test_isolated_arm_survives_a_client_crash(sim):
    """A drop the robot takes back at once makes ur_rtde's own reconnect loop and segfault
    (docs/arm.md); in a worker process that costs one press, not the cell."""
    sim.reset()
    arm = IsolatedURArm(_config(sim))
    assert isinstance(arm, Arm)
    with pytest.raises(NotConnectedError):
        arm.press()
    arm.connect()
    try:
        arm.move_above(25.0, 25.0)
        assert arm.press().force_n == pytest.approx(15.0, abs=1.0)
        arm.retract()
        sim.set_faults(protective_stop_above_n=8.0)  # typed faults cross the process boundary
        with pytest.raises(ArmSafetyStop) as exc:
            arm.press()
        assert exc.value.kind == "protective_stop"
        sim.set_faults(protective_stop_above_n=None)
        arm.clear_protective_stop()
        arm.retract()
        assert arm.worker_restarts == 0 and arm.worker_exit_codes == []
        first_worker = arm._proc.pid
        # The drop should land mid-press, and the robot takes the link back at once: the client's
        # own reconnect segfaults the worker (exit -11, docs/arm.md), and the press fails in words.
        # Under load the press can end before the drop, or the client reconnect cleanly (a race
        # inside ur_rtde): then the press succeeds and the worker may die idle. Either way the cell
        # needs the same: no crash of its own, and the next move and press work on a new worker.
        drop = threading.Timer(0.3, lambda: sim.drop_connections(0.0))
        drop.start()
        try:
            arm.press()
            failed = None
        except ArmConnectionError as e:
            failed = e
        drop.join()
        if failed is not None:
            assert failed.kind == "connection_lost" and "worker died" in str(failed), str(failed)
            assert arm.worker_exit_codes == [-11], arm.worker_exit_codes  # the crash, and only one
            assert f"exit code {arm.worker_exit_codes[0]}" in str(failed)
        time.sleep(0.5)
        for attempt in range(2):  # a worker that dies idle after the drop fails one call in words
            try:
                arm.move_above(35.0, 35.0)  # a dead worker is replaced and connected first
                break
            except ArmConnectionError as e:
                assert attempt == 0 and failed is None and "worker died" in str(e), str(e)
        assert arm.press().force_n == pytest.approx(15.0, abs=1.0)
        assert arm.worker_exit_codes in ([], [-11]), arm.worker_exit_codes
        assert arm.worker_restarts == len(arm.worker_exit_codes)
        assert (arm._proc.pid != first_worker) == bool(arm.worker_exit_codes)
        print(f"worker exit codes after the drop: {arm.worker_exit_codes}")
    finally:
        arm.stop()
        arm.disconnect()
        sim.reset()


def test_connection_refused_is_a_typed_error():
    host = free_loopback_host()  # nothing listens there
    arm = URArm(ArmConfig(host=host, reconnect_attempts=1, reconnect_backoff_s=0.05))
    t0 = time.monotonic()
    with pytest.raises(ArmConnectionError) as exc:
        arm.connect()
    assert host in str(exc.value) and "2 attempt" in str(exc.value)
    assert time.monotonic() - t0 < 10
    with pytest.raises(NotConnectedError):
        arm.press()


def test_controller_not_answering_a_command_is_bounded(arm, sim):
    arm.move_above(70.0, 70.0)
    arm.config = dataclasses.replace(arm.config, command_timeout_s=1.0)
    sim.set_faults(command_delay_s=4.0)  # the script answers 'done' 4 s late
    t0 = time.monotonic()
    with pytest.raises(PressFailed) as exc:
        arm.press()
    assert exc.value.kind == "timeout" and "zeroFtSensor" in str(exc.value)
    assert time.monotonic() - t0 < 4.0  # bounded by command_timeout_s + one reconnect
    sim.set_faults(command_delay_s=0.0)
    assert arm.press().force_n == pytest.approx(15.0, abs=1.0)  # the re-established link works


@pytest.mark.hardware(needs="the real robot (VS2T_UR_HOST, default 192.168.1.10)")
def test_live_robot_reports_a_safe_state():
    """On the cell: connect to the UR at VS2T_UR_HOST and read its state; no motion."""
    import os

    arm = URArm(ArmConfig(host=os.environ.get("VS2T_UR_HOST", "192.168.1.10")))
    with arm:
        assert arm.safety_mode() in (1, 2)

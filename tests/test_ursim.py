"""The loopback UR simulator: its RTDE/dashboard wire protocol, its physics, and the real
ur_rtde client (RTDEControlInterface, RTDEReceiveInterface, DashboardClient) running against it."""

from __future__ import annotations

import dataclasses
import math
import socket
import struct
import time

import pytest

from vs2t_edge.sim.ursim import URSim, free_loopback_host
from vs2t_edge.sim.ursim_model import CMD_MOVEL, PressScene
from vs2t_edge.sim.ursim_process import URSimProcess


def _rtde(sock: socket.socket, ptype: str, payload: bytes = b"") -> tuple[str, bytes]:
    sock.sendall(struct.pack(">HB", len(payload) + 3, ord(ptype)) + payload)
    return _read_package(sock)


def _read_package(sock: socket.socket) -> tuple[str, bytes]:
    head = b""
    while len(head) < 3:
        head += sock.recv(3 - len(head))
    size, ptype = struct.unpack(">HB", head)
    body = b""
    while len(body) < size - 3:
        body += sock.recv(size - 3 - len(body))
    return chr(ptype), body


@pytest.fixture
def sim():
    with URSim(PressScene(), host=free_loopback_host()) as s:
        yield s


def test_only_loopback_is_served():
    with pytest.raises(ValueError, match="loopback"):
        URSim(host="0.0.0.0")
    with pytest.raises(ValueError, match="loopback"):
        URSimProcess(host="192.168.1.10")


def test_spring_model_fabric_then_table():
    s = URSim(PressScene(table_z_m=0.1, fabric_thickness_mm=2.0, fabric_stiffness_n_per_mm=5.0,
                         table_stiffness_n_per_mm=500.0))
    surface = 0.102
    assert s.contact_force_at(surface + 0.001) == 0.0
    assert s.contact_force_at(surface - 0.001) == pytest.approx(5.0)
    assert s.contact_force_at(surface - 0.003) == pytest.approx(10.0 + 500.0)
    for force in (0.5, 9.9, 15.0, 40.0):
        assert s.contact_force_at(s._z_for_force(force)) == pytest.approx(force)


def test_rtde_handshake_recipes_and_stream(sim):
    with socket.create_connection((sim.host, sim.rtde_port), timeout=2) as c:
        assert _rtde(c, "V", struct.pack(">H", 2)) == ("V", b"\x01")
        ptype, body = _rtde(c, "v")
        assert struct.unpack(">IIII", body)[:2] == (5, 11)
        ptype, body = _rtde(c, "O", struct.pack(">d", 100.0) + b"actual_TCP_pose,runtime_state,no_such_thing")
        assert body[1:].decode() == "VECTOR6D,UINT32,NOT_FOUND"
        ptype, body = _rtde(c, "O", struct.pack(">d", 100.0) + b"actual_TCP_pose,output_int_register_0")
        assert body[1:].decode() == "VECTOR6D,INT32"
        _, body = _rtde(c, "I", b"input_int_register_0,input_double_register_0,input_double_register_1,"
                                b"input_double_register_2,input_double_register_3,input_double_register_4,"
                                b"input_double_register_5,input_double_register_6,input_double_register_7,"
                                b"input_int_register_1")
        assert body[0] == 1 and body[1:].decode().startswith("INT32,DOUBLE")
        assert _rtde(c, "S") == ("S", b"\x01")
        t0, packages = time.monotonic(), []
        while len(packages) < 20:
            ptype, body = _read_package(c)
            if ptype == "U":
                packages.append(struct.unpack(">B6di", body))
        rate = 20 / (time.monotonic() - t0)
        assert 50 < rate < 200, rate  # streamed at the requested 100 Hz
        assert packages[-1][1:7] == pytest.approx(PressScene().home_pose)
        # No program uploaded yet: the register handshake is idle.
        assert packages[-1][7] == 0


def test_register_handshake_runs_a_movel_without_interpreting_the_script(sim):
    with socket.create_connection((sim.host, sim.script_ports[-1]), timeout=2) as script:
        script.sendall(b"def rtde_control():\n  textmsg(\"not interpreted\")\nend\n")
        deadline = time.monotonic() + 2
        while sim.snapshot()["runtime_state"] != 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    assert sim.snapshot()["runtime_state"] == 2
    assert sim.out_int[0] == 1  # ready for a command
    target = list(PressScene().home_pose)
    target[2] -= 0.01
    with sim._lock:
        sim.in_double[0:8] = target + [0.1, 1.0]
        sim.in_int[1] = 0
        sim.in_int[0] = CMD_MOVEL
    deadline = time.monotonic() + 2
    while sim.out_int[0] != 2 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert sim.out_int[0] == 2  # done only once the move has ended
    assert sim.snapshot()["pose"][2] == pytest.approx(target[2], abs=1e-6)
    with sim._lock:
        sim.in_int[0] = 0
    time.sleep(0.05)
    assert sim.out_int[0] == 1


def test_dashboard_lines(sim):
    with socket.create_connection((sim.host, sim.dashboard_port), timeout=2) as d:
        f = d.makefile("rw")
        assert "Dashboard Server" in f.readline()

        def ask(line: str) -> str:
            f.write(line + "\n")
            f.flush()
            return f.readline().strip()

        assert ask("PolyscopeVersion").startswith("URSoftware 5.11")
        assert ask("safetymode") == "Safetymode: NORMAL"
        sim.trigger_protective_stop()
        assert ask("safetymode") == "Safetymode: PROTECTIVE_STOP"
        assert ask("unlock protective stop") == "Protective stop releasing"
        assert ask("safetymode") == "Safetymode: NORMAL"
        sim.trigger_emergency_stop()
        assert ask("safetystatus") == "Safetystatus: ROBOT_EMERGENCY_STOP"
        assert ask("robotmode") == "Robotmode: POWER_OFF"
        assert ask("bogus").startswith("could not understand")


def test_real_ur_rtde_client_press_calls_and_protective_stop():
    """The real ur_rtde package: connect, upload its script, moveL, zeroFtSensor,
    moveUntilContact, forceMode/forceModeStop, stopL, and a protective stop seen by all three."""
    rtde_control = pytest.importorskip("rtde_control")
    rtde_receive = pytest.importorskip("rtde_receive")
    dashboard_client = pytest.importorskip("dashboard_client")
    scene = PressScene(home_pose=(0.4, -0.1, 0.106, 0.0, math.pi, 0.0))
    with URSimProcess(scene, host=free_loopback_host()) as sim:
        host = sim.host
        rcv = rtde_receive.RTDEReceiveInterface(host, 125.0)
        ctl = rtde_control.RTDEControlInterface(host, 125.0)
        dash = dashboard_client.DashboardClient(host)
        dash.connect()
        try:
            assert ctl.isProgramRunning()
            log = sim.get_log()
            assert any("def " in s for s in log["scripts"]), "control script was not uploaded"
            assert "input_int_register_0" not in log.get("unsupported", [])
            pose = rcv.getActualTCPPose()
            assert pose[2] == pytest.approx(0.106)
            pose[2] = 0.105
            assert ctl.moveL(pose, 0.05, 0.5)
            assert rcv.getActualTCPPose()[2] == pytest.approx(0.105, abs=2e-4)
            assert abs(rcv.getActualTCPForce()[2] - scene.ft_bias_n) < 0.5  # the sensor's offset
            assert ctl.zeroFtSensor()
            time.sleep(0.05)
            assert abs(rcv.getActualTCPForce()[2]) < 0.5
            assert ctl.moveUntilContact([0, 0, -0.02, 0, 0, 0], [0, 0, -1, 0, 0, 0], 0.5)
            assert rcv.getActualTCPPose()[2] == pytest.approx(scene.surface_z_m, abs=2e-4)
            assert ctl.forceMode([0.0] * 6, [0, 0, 1, 0, 0, 0], [0, 0, -15.0, 0, 0, 0], 2,
                                 [0.1, 0.1, 0.02, 0.17, 0.17, 0.17])
            time.sleep(0.8)
            assert rcv.getActualTCPForce()[2] == pytest.approx(15.0, abs=0.5)
            assert ctl.forceModeStop()
            ctl.stopL(1.0)
            commands = sim.get_log()["commands"]
            assert [c for c in commands if c in (3, 8, 51, 6, 7, 33)] == [3, 8, 51, 6, 7, 33]
            sim.trigger_protective_stop()
            time.sleep(0.05)
            assert rcv.isProtectiveStopped() and rcv.getSafetyMode() == 3
            assert "PROTECTIVE_STOP" in dash.safetymode()
            assert not ctl.isProgramRunning()  # a safety stop aborts the control script
            assert ctl.moveL(pose, 0.05, 0.5) is False
        finally:
            ctl.disconnect()
            rcv.disconnect()
            dash.disconnect()


def test_controller_force_limit_stops_a_move_into_the_table():
    """The simulator's own force limit (PressScene.protective_stop_force_n), not an injected
    threshold: a piece origin calibrated 2.5 mm too low makes move_above drive the real ur_rtde
    client 1.5 mm into the 2 mm fabric (9 N at 6 N/mm). That is far below the 120 N default, so
    only the 6 N limit of this scene can stop it: the controller goes into protective stop, the
    receive interface reports it and the arm raises its typed safety stop."""
    pytest.importorskip("rtde_control")
    rtde_receive = pytest.importorskip("rtde_receive")
    from vs2t_edge.runtime.arm import ArmConfig
    from vs2t_edge.runtime.arm_ur import URArm
    from vs2t_edge.runtime.devices import ArmSafetyStop

    scene = PressScene(protective_stop_force_n=6.0, home_pose=(0.40, -0.10, 0.106, 0.0, math.pi, 0.0))
    too_low = scene.surface_z_m - 0.0025
    config = ArmConfig(piece_origin_pose=(0.40, -0.10, too_low, 0.0, math.pi, 0.0), approach_height_mm=1.0,
                       travel_speed_m_s=0.01, travel_accel_m_s2=0.5, move_timeout_s=5.0, reconnect_backoff_s=0.2)
    with URSimProcess(scene, host=free_loopback_host()) as sim:
        arm = URArm(dataclasses.replace(config, host=sim.host))
        rcv = rtde_receive.RTDEReceiveInterface(sim.host, 125.0)
        arm.connect()
        try:
            assert not rcv.isProtectiveStopped()
            with pytest.raises(ArmSafetyStop) as exc:
                arm.move_above(0.0, 0.0)
            assert exc.value.kind == "protective_stop" and not exc.value.retryable
            time.sleep(0.05)
            assert rcv.isProtectiveStopped() and rcv.getSafetyMode() == 3
            (mode, reason, force_n), = sim.get_log()["safety_stops"]
            assert reason == "force over the limit"
            assert 6.0 <= force_n < 9.0  # stopped at the limit (logged to 0.01 N: 6.001 shows as 6.0), before 9 N
            # stopped where the limit was crossed: 1 mm into the fabric, short of the 1.5 mm target
            assert rcv.getActualTCPPose()[2] == pytest.approx(scene.surface_z_m - 0.001, abs=2e-4)
            with pytest.raises(ArmSafetyStop):
                arm.move_above(0.0, 0.0)  # refused until the stop is cleared
        finally:
            arm.stop()
            arm.disconnect()
            rcv.disconnect()

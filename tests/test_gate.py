"""The gate host driver against the simulated MCU over a real pseudo-terminal pair.

Every test talks through /dev/pts/N with pyserial, as the cell does through the USB-serial
adapter. Faults are injected on the simulated line and MCU (mcu_sim.LineFaults).
"""

from __future__ import annotations

import os
import threading
import time

import pytest
import serial

from vs2t_edge.cli import main as cli_main
from vs2t_edge.firmware_bridge import protocol as p
from vs2t_edge.firmware_bridge.gate_client import GateClient, GateClientError
from vs2t_edge.firmware_bridge.mcu_sim import LineFaults, start_simulated_gate
from vs2t_edge.runtime.devices import Gate, GateError, GateStatus, NotConnectedError
from vs2t_edge.runtime.gate import SerialGate
from vs2t_edge.sim.fake_devices import FakeGate
from vs2t_edge.sim.devices import simulated_serial_gate

MOVE_MS = 60


@pytest.fixture
def sim():
    path, simulator = start_simulated_gate(move_time_ms=MOVE_MS)
    yield simulator
    simulator.stop()


@pytest.fixture
def client(sim):
    gate = GateClient(sim.device_path, timeout_s=0.3, retries=3, heartbeat_period_s=0.1)
    gate.connect()
    yield gate
    gate.disconnect()


def sort_frames(sim, seq=None):
    return [f for f in sim.rx_frames if f.type == p.SORT and (seq is None or f.seq == seq)]


def wait_for(predicate, timeout_s=2.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


# --- the happy path ---------------------------------------------------------------------------

def test_connect_arms_a_freshly_booted_gate(sim, client):
    assert client.armed_from == "boot"
    report = client.status()
    assert (report.state, report.bin, report.fault, report.n_bins) == ("ready", 0, "", 8)


def test_sort_is_acked_once_the_flap_reached_the_bin(sim, client):
    started = time.monotonic()
    client.sort(3)
    elapsed_s = time.monotonic() - started
    assert sim.executed == [3]
    assert elapsed_s >= MOVE_MS / 1000 * 0.9  # the ACK waits for the move
    report = client.status()
    assert (report.state, report.bin, report.sorts_done) == ("ready", 3, 1)
    assert client.retransmissions == 0


def test_heartbeats_keep_the_gate_armed(sim):
    path, fast_sim = start_simulated_gate(heartbeat_timeout_ms=300)
    try:
        with GateClient(path, timeout_s=0.3, heartbeat_period_s=0.08) as gate:
            time.sleep(0.9)  # three watchdog windows
            assert gate.status().state == "ready"
            assert gate.heartbeats_ok >= 5 and gate.heartbeat_errors == 0
    finally:
        fast_sim.stop()


# --- retransmission and duplicates -------------------------------------------------------------

def test_dropped_ack_is_retransmitted_and_the_sort_runs_once(sim, client):
    sim.faults.drop_tx = 1
    client.sort(5)
    assert client.retransmissions == 1
    frames = sort_frames(sim)
    assert len(frames) == 2 and frames[0] == frames[1]  # the same SEQ went twice
    assert sim.executed == [5]


def test_lost_request_is_retransmitted_and_runs_once(sim, client):
    sim.faults.drop_rx = 1
    client.sort(4)
    assert client.retransmissions == 1
    assert sim.executed == [4]


def test_duplicate_sort_frame_is_acked_again_not_executed_twice(sim, client):
    client.disconnect()  # talk raw to the MCU, no driver in between
    with serial.serial_for_url(sim.device_path, timeout=0.05) as line:
        reader = p.FrameReader()

        def replies(n, timeout_s=1.0):
            got, deadline = [], time.monotonic() + timeout_s
            while len(got) < n and time.monotonic() < deadline:
                got += reader.feed(line.read(64))
            return got

        line.write(p.encode_frame(40, p.STATUS))
        assert replies(1)[0].type == p.STATUS_REPLY
        sort = p.encode_frame(41, p.SORT, b"\x02")
        line.write(sort + sort)  # the second arrives while the flap is still moving: ignored
        first = replies(1)
        assert [f.type for f in first] == [p.ACK] and first[0].seq == 41
        assert replies(1, timeout_s=0.2) == []  # exactly one ACK for the two copies
        line.write(sort)  # after the move: the cached ACK again
        again = replies(1)
        assert again == first
        assert sim.executed == [2]
        # A new SEQ with the same bin is a new sort.
        line.write(p.encode_frame(42, p.SORT, b"\x02"))
        assert replies(1)[0].seq == 42
        assert sim.executed == [2, 2]


def test_a_fail_safe_forgets_the_duplicate_memory():
    """After a fail-safe the same SORT frame (the host's 8-bit SEQ wrapped after 255 lost frames)
    must be refused as latched: the ACK cached before the latch says READY at bin 3 while the flap
    is at reject, and the host would have journaled the piece as sorted there."""
    from vs2t_edge.firmware_bridge.mcu_sim import GateFirmware

    fw = GateFirmware(now_ms=0, boot_id=1, heartbeat_timeout_ms=500, move_time_ms=60)
    fw.on_frame(p.Frame(1, p.CLEAR, b""), 0)
    assert [p.decode_frame(f).type for f in fw.tick(60)] == [p.ACK]  # out of the boot latch
    sort = p.Frame(5, p.SORT, b"\x03")
    fw.on_frame(sort, 60)
    assert fw.tick(120) and fw.bin == 3
    fw.tick(700)  # 580 ms of silence: fail-safe, flap at reject
    assert fw.state == p.STATE_FAILSAFE and fw.bin == p.REJECT_BIN
    (reply,) = [p.decode_frame(f) for f in fw.on_frame(sort, 701)]
    assert reply.type == p.NAK and reply.payload[1] == p.NAK_LATCHED  # Nak: acked type, reason, ...


def test_duplicated_mcu_frames_do_not_confuse_the_host(sim, client):
    sim.faults.duplicate_tx = 10
    for bin_index in (1, 2, 3, 1):
        client.sort(bin_index)
    assert sim.executed == [1, 2, 3, 1]
    assert client.status().sorts_done == 4


def test_serial_noise_between_frames_is_resynchronised(sim, client):
    sim.faults.noise_bytes = 12  # sync bytes included
    for bin_index in (1, 6, 2, 7, 3):
        client.sort(bin_index)
    assert sim.executed == [1, 6, 2, 7, 3]
    assert client._reader.dropped_bytes >= 5 * 6  # the noise was really there and thrown away


# --- NAK, timeouts --------------------------------------------------------------------------------

def test_bad_bin_is_naked_and_not_retried(sim, client):
    with pytest.raises(GateClientError) as caught:
        client.sort(8)  # bins are 0..7
    assert (caught.value.kind, caught.value.reason) == ("nak", "bad_bin")
    assert "no such bin" in str(caught.value)
    assert client.retransmissions == 0 and sim.executed == []


def test_unknown_type_and_bad_length_are_naked(sim, client):
    with client._lock:
        reply = client._request(0x42, b"")
        assert isinstance(reply, p.Nak) and reply.reason == p.NAK_UNKNOWN_TYPE
        reply = client._request(p.SORT, b"\x01\x02")
        assert isinstance(reply, p.Nak) and reply.reason == p.NAK_BAD_LENGTH
    assert sim.executed == []


def test_slow_ack_within_the_timeout_succeeds(sim, client):
    sim.faults.ack_delay_s = 0.15  # + 60 ms move, under the 0.3 s timeout
    client.sort(2)
    assert client.retransmissions == 0 and sim.executed == [2]


def test_slow_ack_over_the_timeout_is_a_timeout_and_the_sort_ran_once(sim, client):
    client.stop_heartbeat()
    sim.faults.ack_delay_s = 2.0
    started = time.monotonic()
    with pytest.raises(GateClientError) as caught:
        client.sort(6)
    elapsed_s = time.monotonic() - started
    assert caught.value.kind == "timeout"
    assert 4 * 0.3 <= elapsed_s < 4 * 0.3 + 1.0  # 4 attempts of 0.3 s, bounded (slack for a loaded CI)
    assert len(sort_frames(sim)) == 4 and sim.executed == [6]
    # Once the MCU is fast again, the late ACKs of the old SEQ are ignored and work goes on.
    sim.faults.ack_delay_s = 0.0
    client.sort(1)
    assert sim.executed == [6, 1]


def test_loop_url_echo_is_not_taken_for_a_reply():
    gate = GateClient("loop://", timeout_s=0.05, retries=1, heartbeat_period_s=None)
    with pytest.raises(GateClientError) as caught:
        gate.connect()  # our own STATUS comes back: not a reply, so a timeout
    assert caught.value.kind == "timeout"
    assert not gate.connected


def test_unopenable_port_is_a_link_error():
    with pytest.raises(GateClientError) as caught:
        GateClient("/dev/vs2t-no-such-gate").connect()
    assert caught.value.kind == "link" and "/dev/vs2t-no-such-gate" in str(caught.value)


# --- fail-safe, jam, reboot ------------------------------------------------------------------------

def test_heartbeat_loss_fails_safe_refuses_then_clear_rearms():
    path, sim = start_simulated_gate(heartbeat_timeout_ms=300, move_time_ms=MOVE_MS)
    try:
        with GateClient(path, timeout_s=0.3, heartbeat_period_s=0.08) as gate:
            gate.sort(4)
            gate.stop_heartbeat()  # the host goes quiet
            assert wait_for(lambda: sim.state == p.STATE_FAILSAFE, 1.0)
            with pytest.raises(GateClientError) as caught:
                gate.sort(3)
            assert caught.value.kind == "fault_latched"
            assert "failsafe (heartbeat_lost)" in str(caught.value)
            report = gate.status()
            assert (report.state, report.fault, report.bin) == ("failsafe", "heartbeat_lost", 0)  # at reject
            assert [r.fault for r in gate.fault_reports] == [p.FAULT_HEARTBEAT_LOST]
            gate.clear()
            gate.sort(3)
            assert sim.executed == [4, 3]
    finally:
        sim.stop()


def test_jam_is_reported_latched_and_cleared_once_freed(sim, client):
    sim.jam()
    with pytest.raises(GateClientError) as caught:
        client.sort(2)
    assert (caught.value.kind, caught.value.reason) == ("jam", "jam")
    report = client.status()
    assert (report.state, report.fault) == ("fault", "jam")
    assert [r.fault for r in client.fault_reports] == [p.FAULT_JAM]  # the FAULT frame behind the NAK
    with pytest.raises(GateClientError) as latched:
        client.sort(1)
    assert latched.value.kind == "fault_latched"
    with pytest.raises(GateClientError) as still:
        client.clear()  # nobody freed the flap yet
    assert (still.value.kind, still.value.reason) == ("jam", "jam_present")
    sim.jam(False)
    client.clear()
    assert client.status().state == "ready"
    client.sort(1)
    assert sim.executed == [1]


def test_mcu_reboot_is_detected_and_sorting_refused_until_clear(sim, client):
    client.sort(2)
    old_boot = client.status().boot_id
    sim.reboot()
    with pytest.raises(GateClientError) as caught:
        client.sort(5)
    assert caught.value.kind == "link"
    assert f"boot id {old_boot} -> {old_boot + 1}" in str(caught.value)
    sent = len(sort_frames(sim))
    with pytest.raises(GateClientError):
        client.sort(5)  # still refused, and not even sent
    assert len(sort_frames(sim)) == sent
    client.clear()
    client.sort(5)
    assert sim.executed[-1] == 5 and client.status().boot_id == old_boot + 1


def test_reboot_seen_by_the_heartbeat_alone(sim, client):
    sim.reboot()
    assert wait_for(lambda: client._reboot is not None, 1.0)
    sent = len(sort_frames(sim))
    with pytest.raises(GateClientError, match="rebooted"):
        client.sort(1)
    assert len(sort_frames(sim)) == sent


def test_concurrent_sorts_and_heartbeats_are_serialised(sim, client):
    errors = []

    def worker(bin_index):
        try:
            for _ in range(6):
                client.sort(bin_index)
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(b,)) for b in (1, 2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=10)
    assert errors == []
    assert sorted(sim.executed) == [1] * 6 + [2] * 6  # each sort exactly once, none lost


# --- the runtime's Gate ---------------------------------------------------------------------------

def test_serial_gate_satisfies_the_gate_protocol_and_maps_errors():
    gate = simulated_serial_gate(move_time_ms=MOVE_MS, faults=LineFaults())
    assert isinstance(gate, Gate)
    with pytest.raises(NotConnectedError):
        gate.sort(1)
    with gate:
        gate.sort(1)
        status = gate.status()
        assert isinstance(status, GateStatus) and (status.state, status.bin) == ("ready", 1)
        with pytest.raises(GateError) as caught:
            gate.sort(99)
        assert caught.value.kind == "nak" and caught.value.device == "gate"
        gate.simulator.jam()
        with pytest.raises(GateError) as jam:
            gate.sort(2)
        assert jam.value.kind == "jam" and not jam.value.retryable
        gate.to_reject()  # latched and jammed: must not raise
        gate.simulator.jam(False)
        gate.clear()
        gate.sort(2)
        assert gate.simulator.executed == [1, 2]


def test_serial_gate_open_failure_is_a_link_gate_error():
    with pytest.raises(GateError) as caught:
        SerialGate("/dev/vs2t-no-such-gate").connect()
    assert caught.value.kind == "link"


def test_fake_gate_latches_like_the_firmware():
    gate = FakeGate()
    assert isinstance(gate, Gate)
    with pytest.raises(NotConnectedError):
        gate.sort(1)
    with gate:
        gate.sort(3)
        gate.jam_next_sort()
        with pytest.raises(GateError) as jam:
            gate.sort(2)
        assert jam.value.kind == "jam"
        with pytest.raises(GateError) as latched:
            gate.sort(2)
        assert latched.value.kind == "fault_latched"
        gate.clear()
        gate.lose_heartbeat()
        assert gate.status() == GateStatus(state="failsafe", bin=0, fault="heartbeat_lost", seq=gate.status().seq,
                                           n_bins=gate.n_bins)
        gate.to_reject()
        gate.clear()
        gate.time_out_next()
        with pytest.raises(GateError) as timeout:
            gate.sort(1)
        assert timeout.value.kind == "timeout" and timeout.value.retryable
        gate.sort(1)
        with pytest.raises(GateError):
            gate.sort(8)
        assert gate.sorted == [3, 1]


# --- the hand commands -------------------------------------------------------------------------------

def test_cli_sort_status_clear_against_the_simulator(sim, capsys):
    port = ["--port", sim.device_path, "--timeout-s", "0.3"]
    assert cli_main(["sort", "3", *port]) == 0
    assert "sorted to bin 3" in capsys.readouterr().out
    assert cli_main(["gate-status", *port]) == 0
    assert "gate ready, flap at bin 3 of 8" in capsys.readouterr().out
    assert cli_main(["sort", "9", *port]) == 2  # bad input, not a device fault
    assert "no such bin" in capsys.readouterr().err
    sim.jam()
    assert cli_main(["sort", "2", *port]) == 3
    assert "[jam]" in capsys.readouterr().err
    assert cli_main(["gate-status", *port]) == 3
    assert "gate fault (jam)" in capsys.readouterr().out
    assert cli_main(["sort", "2", *port]) == 3  # a jam is never armed away by sort
    assert "[fault_latched]" in capsys.readouterr().err
    sim.jam(False)
    assert cli_main(["gate-clear", *port]) == 0
    assert "gate cleared: gate ready" in capsys.readouterr().out
    assert cli_main(["sort", "1", *port]) == 0
    assert sim.executed == [3, 1]


def test_cli_sort_to_a_bin_the_gate_lacks_is_bad_input_and_touches_nothing(sim, capsys):
    """`sort 99` was a device fault (exit 3) after arming the gate; it is bad input (exit 2),
    refused once the gate's STATUS says how many bins it has, before any latch is cleared."""
    port = ["--port", sim.device_path, "--timeout-s", "0.3"]
    assert sim.state == p.STATE_FAILSAFE  # power-on latch (boot) until someone arms the gate
    assert cli_main(["sort", "99", *port]) == 2
    err = capsys.readouterr().err
    assert "no such bin 99" in err and "bins 0..7" in err and "armed" not in err
    assert sim.state == p.STATE_FAILSAFE and sim.executed == []
    assert cli_main(["sort", "7", *port]) == 0  # the last bin it has: armed and sorted
    assert "armed it" in capsys.readouterr().err
    assert sim.executed == [7]
    assert cli_main(["sort", "99", "--simulate"]) == 2


def test_cli_sort_status_and_sort_clear_as_the_issue_names_them(sim, capsys):
    """`vs2t-edge sort BIN`, `sort status`, `sort clear` (issue 6); gate-status / gate-clear stay
    as aliases and say the same."""
    port = ["--port", sim.device_path, "--timeout-s", "0.3"]
    assert cli_main(["sort", "5", *port]) == 0
    assert cli_main(["sort", "status", *port]) == 0
    out = capsys.readouterr().out
    assert "gate ready, flap at bin 5 of 8" in out and "1 sorts since boot" in out
    sim.jam()
    assert cli_main(["sort", "2", *port]) == 3
    capsys.readouterr()
    assert cli_main(["sort", "status", *port]) == 3  # latched: a device fault to a script asking
    status = capsys.readouterr().out
    assert "gate fault (jam)" in status
    assert cli_main(["gate-status", *port]) == 3
    assert capsys.readouterr().out.split(", up ")[0] == status.split(", up ")[0]  # the alias says the same
    sim.jam(False)
    assert cli_main(["sort", "clear", *port]) == 0
    assert "gate cleared: gate ready" in capsys.readouterr().out
    assert cli_main(["sort", "status", *port]) == 0
    assert cli_main(["sort", "1", *port]) == 0
    assert sim.executed == [5, 1]  # status and clear moved nothing
    capsys.readouterr()
    assert cli_main(["sort", "stauts", *port]) == 2
    assert "neither a bin number nor status or clear" in capsys.readouterr().err
    assert cli_main(["sort", "clear", "--no-arm", *port]) == 2
    assert sim.executed == [5, 1]


def test_cli_help_names_sort_status_and_clear(capsys):
    with pytest.raises(SystemExit):
        cli_main(["sort", "--help"])
    text = capsys.readouterr().out
    assert "{BIN,status,clear}" in text and "gate-status" in text and "gate-clear" in text
    with pytest.raises(SystemExit):
        cli_main(["--help"])
    top = capsys.readouterr().out
    assert "sort status" in top and "sort clear" in top


def test_cli_sort_arms_a_heartbeat_lost_gate_unless_told_not_to(capsys):
    path, sim = start_simulated_gate(heartbeat_timeout_ms=200, move_time_ms=MOVE_MS)
    try:
        port = ["--port", path, "--timeout-s", "0.3"]
        assert cli_main(["gate-clear", *port]) == 0
        assert wait_for(lambda: sim.state == p.STATE_FAILSAFE, 1.0)  # nobody sends heartbeats
        assert cli_main(["sort", "2", "--no-arm", *port]) == 3
        assert "[fault_latched]" in capsys.readouterr().err
        assert cli_main(["sort", "2", *port]) == 0
        assert "armed it" in capsys.readouterr().err
        assert sim.executed == [2]
    finally:
        sim.stop()


def test_cli_port_from_environment_and_simulate(monkeypatch, sim, capsys):
    monkeypatch.setenv("VS2T_GATE_PORT", sim.device_path)
    assert cli_main(["sort", "4"]) == 0 and sim.executed == [4]
    assert cli_main(["sort", "1", "--simulate"]) == 0
    assert "simulated gate on /dev/" in capsys.readouterr().err
    monkeypatch.delenv("VS2T_GATE_PORT")
    assert cli_main(["gate-status"]) == 2
    assert "no gate port" in capsys.readouterr().err
    assert cli_main(["sort", "-1", "--simulate"]) == 2


# --- other pyserial URLs, a lost link, the real gate -----------------------------------------------

def test_socket_url_reaches_the_simulated_gate():
    url, sim = start_simulated_gate(transport="tcp", move_time_ms=MOVE_MS)
    try:
        assert url.startswith("socket://127.0.0.1:")
        with GateClient(url, timeout_s=0.3, heartbeat_period_s=0.1) as gate:
            gate.sort(6)
            assert gate.status().bin == 6
        assert sim.executed == [6]
    finally:
        sim.stop()


def test_lost_link_is_reported_not_hung(sim, client):
    client.stop_heartbeat()
    sim.stop()  # the USB adapter is unplugged: the pty's other end is gone
    started = time.monotonic()
    with pytest.raises(GateClientError) as caught:
        client.sort(1)
    assert caught.value.kind == "link" and sim.device_path in str(caught.value)
    assert time.monotonic() - started < 0.5  # noticed at once, not after the retries


@pytest.mark.hardware(needs="the real gate", env=("VS2T_GATE_PORT",))
def test_real_gate_routes_and_returns_to_reject():
    with GateClient(os.environ["VS2T_GATE_PORT"], arm_latches=("boot", "heartbeat_lost")) as gate:
        report = gate.status()
        assert report.state == "ready", f"the real gate is {report.state} ({report.fault}); clear it first"
        before = report.sorts_done
        gate.sort(1)
        gate.sort(p.REJECT_BIN)
        after = gate.status()
        assert (after.bin, after.sorts_done) == (p.REJECT_BIN, before + 2)


_GATE_CONFIG = """\
bundle: bundle
devices:
  camera: {kind: replay, path: frames}
  arm: {kind: fake}
  gate: {kind: GATE_KIND}
scene:
  reject_bin: 0
  fabrics:
    - {name: denim, kind: touched, bin: 1}
journal: state/journal.jsonl
"""


def test_a_config_gate_of_kind_sim_is_the_mcu_simulator_and_only_then_is_sim_loaded(tmp_path):
    """The simulated gate lives in vs2t_edge.sim; `run` on a config with ``gate: {kind: sim}`` still
    gets it (runtime/devices.py SIMULATORS, imported by name), and a config with any other gate
    never loads the simulators (checked in a fresh interpreter): a dry run with ``kind: fake``
    loads only the in-process fakes."""
    import subprocess
    import sys

    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.wiring import build_live_devices
    from vs2t_edge.sim.devices import SimulatedSerialGate

    path = tmp_path / "cell.yaml"
    path.write_text(_GATE_CONFIG.replace("GATE_KIND", "sim"))
    _camera, _arm, gate = build_live_devices(load_config(path))
    try:
        assert isinstance(gate, SimulatedSerialGate) and gate.simulator is not None
        gate.connect()
        gate.sort(1)
        assert gate.status().bin == 1
    finally:
        gate.disconnect()
    path.write_text(_GATE_CONFIG.replace("GATE_KIND", "fake"))
    probe = ("import sys; from vs2t_edge.runtime.config import load_config; "
             "from vs2t_edge.runtime.wiring import build_live_devices; "
             f"build_live_devices(load_config({str(path)!r})); "
             "print(sorted(m for m in sys.modules if m.startswith('vs2t_edge.sim')))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert set(eval(out.stdout)) <= {"vs2t_edge.sim", "vs2t_edge.sim.fake_devices"}, out.stdout

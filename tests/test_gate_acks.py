"""Issue 17, the gate: an ACK is believed only when it reports what was asked; FAULT floods are
bounded; a gate found latched at start latches the cell before any piece is pressed.

The host driver talks to the MCU simulator over a real pty; the lying MCU is the simulator with
``LineFaults.lie_acks`` (right CRC, SEQ and type, fields replaced)."""

from __future__ import annotations

import time

import pytest

from vs2t_edge.firmware_bridge import protocol as p
from vs2t_edge.firmware_bridge.gate_client import GateClient, GateClientError
from vs2t_edge.firmware_bridge.mcu_sim import start_simulated_gate
from vs2t_edge.runtime.devices import GateError
from vs2t_edge.runtime.gate import SerialGate

MOVE_MS = 40


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


def wait_for(predicate, timeout_s=2.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


# The lies the adversary told: the flap at another bin, the gate latched or still moving.
LIES = {
    "another bin": dict(lie_bin=7),
    "reject bin": dict(lie_bin=0),
    "fault (jam)": dict(lie_state=p.STATE_FAULT, lie_fault=p.FAULT_JAM),
    "failsafe": dict(lie_state=p.STATE_FAILSAFE, lie_fault=p.FAULT_HEARTBEAT_LOST, lie_bin=0),
    "busy": dict(lie_state=p.STATE_BUSY),
    "fault code while ready": dict(lie_fault=p.FAULT_BOOT),
}


def _lie(sim, **fields) -> None:
    for name, value in fields.items():
        setattr(sim.faults, name, value)
    sim.faults.lie_acks = 1


@pytest.mark.parametrize("lie", LIES)
def test_an_ack_that_contradicts_the_sort_is_a_fault_not_a_success(sim, client, lie):
    _lie(sim, **LIES[lie])
    with pytest.raises(GateClientError) as caught:
        client.sort(5)
    assert caught.value.kind == "bad_ack"
    assert "contradicts" in str(caught.value)
    assert caught.value.reported_bin == LIES[lie].get("lie_bin", 5)
    assert sim.lies_told == 1 and client.bad_acks == 1
    assert client.retransmissions == 0  # an answer, not a silence: not retried
    client.sort(5)  # an honest ACK is believed again
    assert sim.executed == [5, 5]


def test_the_runtime_gate_reports_a_contradicting_ack_as_a_gate_error(sim):
    gate = SerialGate(sim.device_path, timeout_s=0.3)
    with gate:
        _lie(sim, lie_bin=3)
        with pytest.raises(GateError) as caught:
            gate.sort(5)
    assert caught.value.kind == "bad_ack" and caught.value.reported_bin == 3
    assert not caught.value.retryable


@pytest.mark.parametrize("lie", ["another bin", "fault (jam)", "busy"])
def test_a_clear_ack_that_contradicts_the_clear_is_refused(sim, client, lie):
    sim.reboot()  # a latch to clear: the MCU rebooted
    with pytest.raises(GateClientError):
        client.sort(2)
    _lie(sim, **LIES[lie])
    with pytest.raises(GateClientError) as caught:
        client.clear()
    assert caught.value.kind == "bad_ack"
    with pytest.raises(GateClientError, match="rebooted"):
        client.sort(2)  # the reboot was not acknowledged by a clear nobody can believe
    client.clear()  # an honest clear does it
    client.sort(2)
    assert sim.executed == [2]


def test_clear_of_a_ready_gate_is_a_harmless_ack_where_the_flap_is(sim, client):
    """protocol.md: CLEAR while READY is a harmless ACK - the flap stays at its bin. That ACK is
    no contradiction; the same bin reported after clearing a latch would be one."""
    client.sort(3)
    client.clear()
    assert client.status().bin == 3 and client.bad_acks == 0
    with GateClient(sim.device_path, timeout_s=0.3, heartbeat_period_s=None) as by_hand:  # `vs2t-edge sort clear`
        by_hand.clear()
    sim.jam()
    with pytest.raises(GateClientError):
        client.sort(5)  # latched FAULT/JAM, the flap stuck short of bin 5
    sim.jam(False)
    _lie(sim, lie_bin=3)  # cleared, but the flap "is" where it was before the latch
    with pytest.raises(GateClientError) as caught:
        client.clear()
    assert caught.value.kind == "bad_ack"


def test_to_reject_does_not_believe_a_contradicting_ack_and_lets_the_gate_fail_safe():
    path, sim = start_simulated_gate(move_time_ms=MOVE_MS, heartbeat_timeout_ms=300)
    try:
        with GateClient(path, timeout_s=0.15, heartbeat_period_s=0.08) as client:
            client.sort(4)
            _lie(sim, lie_bin=4)  # the ACK of SORT 0 says the flap is still at bin 4
            client.to_reject()  # never raises
            # not believed: heartbeats stop, the MCU's own watchdog puts the flap at reject
            assert wait_for(lambda: sim.state == p.STATE_FAILSAFE, 2.0)
            assert sim.firmware.bin == p.REJECT_BIN and client.bad_acks == 1
    finally:
        sim.stop()


def test_the_daemon_journals_a_contradicted_sort_as_a_fault_never_sorted(tmp_path):
    """End to end: the real daemon (a subprocess) on the real host driver; the MCU simulator in
    this process lies once in the ACK of a SORT after the daemon has sorted a piece honestly."""
    from vs2t_edge.runtime.journal import read_records
    from vs2t_edge.sim import fault_rig, faults_process

    path, sim = start_simulated_gate(move_time_ms=MOVE_MS)
    try:
        proc, journal = faults_process.start_daemon(tmp_path, gate_url=path)
        try:
            assert faults_process.wait_for(journal, lambda rs: any(r.get("outcome") == "sorted" for r in rs),
                                           limit_s=60)
            _lie(sim, lie_bin=7)
            latched = faults_process.wait_for(journal, lambda rs: any(r["type"] == "fault" for r in rs), limit_s=30)
        finally:
            code, err = faults_process._stop(proc)
        executed = sim.executed
    finally:
        sim.stop()
    assert code == 0, err[-500:]
    recs = read_records(journal)
    finals = [r for r in recs if r["type"] == "final"]
    assert latched and sim.lies_told == 1
    assert [r["kind"] for r in recs if r["type"] == "fault"] == ["bad_ack"]
    odd = [f for f in finals if f["outcome"] != "sorted"]
    assert [f["outcome"] for f in odd] == ["unknown_outcome"]
    assert odd[0]["bin"] == 0 and odd[0]["reported_bin"] == 7 and "contradicts" in odd[0]["reason"]
    # every sorted record matches a move the MCU made, and the lied-about move is accounted for
    assert fault_rig._moves_match_journal(executed, finals) == ""
    assert fault_rig.audit(journal, faults_process._daemon_truths(recs))["problems"] == []


# --- a flood of FAULT frames ------------------------------------------------------------------------

def test_a_flood_of_fault_frames_is_bounded_counted_and_logged_once(sim, client, caplog):
    from vs2t_edge.firmware_bridge import gate_client

    kept = getattr(gate_client, "FAULT_REPORTS_KEPT", 64)  # getattr: on a client without a bound, fail below

    def seen() -> int:
        return getattr(client, "fault_reports_seen", len(client.fault_reports))

    boot_id = client.status().boot_id
    frame = p.encode_frame(9, p.FAULT, p.FaultReport(p.FAULT_JAM, p.STATE_FAULT, 3, boot_id).pack())
    sent = 0
    with caplog.at_level("WARNING", logger="vs2t_edge.firmware_bridge.gate_client"):
        for _ in range(40):  # 40 bursts of 250 frames, read by the heartbeats in between
            sim.inject_noise(frame * 250)
            sent += 250
            time.sleep(0.02)
        last = -1
        while seen() != last:  # until the heartbeats have read what arrived
            last = seen()
            time.sleep(0.5)
        client.status()
    n_seen = seen()
    assert n_seen > 4 * kept, (n_seen, sent)  # a flood arrived (a full pty buffer loses some: a UART would)
    assert len(client.fault_reports) == kept
    assert client.fault_reports_dropped == n_seen - kept
    assert all(r.fault == p.FAULT_JAM for r in client.fault_reports)
    floods = [r for r in caplog.records if "reports fault" in r.getMessage()]
    assert len(floods) == 1  # the same report ten thousand times is one log line


# --- a gate found latched at start ----------------------------------------------------------------

def _daemon_in_process(tmp_path, gate, truths, *, stop_when):
    """The real daemon (run_daemon) on the fault matrix's fake arm, camera and grey model."""
    from vs2t_edge.sim.fake_devices import FakeArm
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.notify import Notifier
    from vs2t_edge.sim import fakes, fault_rig, faults_process
    from vs2t_edge.sim.devices import SimulatedCamera

    (tmp_path / "cell.yaml").write_text(faults_process.DAEMON_CONFIG)
    (tmp_path / "cell.yaml").chmod(0o640)
    cfg = load_config(tmp_path / "cell.yaml")
    pieces = fault_rig.Pieces(truths)
    arm = fault_rig.FaultArm(FakeArm(config=cfg.arm), pieces)
    camera = SimulatedCamera(fault_rig.grey_frames(arm, pieces), noise_levels=1.0, seed=0)
    code = run_daemon(cfg, model=fakes.GreyModel(), camera=camera, arm=arm, gate=gate, items=pieces,
                      evidence_factory=lambda: fakes.GreyEvidence(fakes.CLASSES, 0.95, 3),
                      notifier=Notifier(address=""), install_signals=False, stop_when=stop_when,
                      log=lambda m: None)
    return code, arm, cfg


@pytest.mark.parametrize("latch", ["heartbeat_lost", "jam"])
def test_a_gate_latched_at_start_latches_the_cell_before_any_piece_is_pressed(tmp_path, latch):
    from vs2t_edge.sim.fake_devices import FakeGate
    from vs2t_edge.runtime.journal import read_records

    gate = FakeGate()
    if latch == "heartbeat_lost":
        gate.lose_heartbeat()  # the service was down longer than the gate's heartbeat timeout
    else:
        gate.jam_next_sort()
        gate.connect()
        with pytest.raises(GateError):
            gate.sort(1)
    fault_file = tmp_path / "state" / "FAULT"
    code, arm, cfg = _daemon_in_process(tmp_path, gate, ["denim", "silk"], stop_when=fault_file.exists)
    assert code == 0
    recs = read_records(cfg.journal)
    types = [r["type"] for r in recs]
    assert "fault" in types and "item" not in types  # latched before the first piece
    fault = next(r for r in recs if r["type"] == "fault")
    assert fault["kind"] == "fault_latched" and "gate latched at start" in fault["reason"] and latch in fault["reason"]
    assert arm.press_count == 0 and gate.sorted == []
    assert latch in fault_file.read_text()


def test_a_gate_whose_start_to_reject_failed_latches_the_cell_before_any_piece(tmp_path, sim):
    """The start sends the gate to reject; when every try's ACK is lost, the driver stops its
    heartbeats so the gate fails safe on its own - but a STATUS right after still says ready. The
    first piece was pressed, and its decision refused at the sort a second later (the gate failed
    safe meanwhile): lost. Now the cell latches before any piece, naming the link."""
    from vs2t_edge.runtime.journal import read_records

    class LosingStartReject(SerialGate):
        def to_reject(self) -> None:
            sim.faults.drop_tx = 4  # the SORT(0)'s four tries answered, every ACK lost on the line
            super().to_reject()

    gate = LosingStartReject(sim.device_path, timeout_s=0.3, retries=3, heartbeat_period_s=0.1)
    fault_file = tmp_path / "state" / "FAULT"
    deadline = time.monotonic() + 30
    code, arm, cfg = _daemon_in_process(tmp_path, gate, ["denim", "silk"],
                                        stop_when=lambda: fault_file.exists() or time.monotonic() > deadline)
    assert code == 0
    recs = read_records(cfg.journal)
    assert "item" not in [r["type"] for r in recs]  # latched before the first piece
    fault = next(r for r in recs if r["type"] == "fault")
    assert "to reject at start failed" in fault["reason"] and fault["kind"] == "link"
    assert arm.press_count == 0


def test_a_serial_gate_latched_at_start_is_named_latched_not_a_link_failure(tmp_path, sim):
    """A latched gate refuses the start's send to reject too, which stops the driver's heartbeats
    (``failing_safe``); its status says why, and that is what the fault names."""
    from vs2t_edge.runtime.journal import read_records

    feeder = GateClient(sim.device_path, timeout_s=0.3, retries=3, heartbeat_period_s=0.1)
    feeder.connect()
    feeder.stop_heartbeat()  # the service went down: no heartbeats past the gate's timeout
    time.sleep(p.HEARTBEAT_TIMEOUT_MS / 1000 + 0.5)  # no request at all: a STATUS feeds the watchdog too
    assert feeder.status().state == "failsafe"
    feeder.disconnect()
    gate = SerialGate(sim.device_path, timeout_s=0.3, retries=3, heartbeat_period_s=0.1)
    fault_file = tmp_path / "state" / "FAULT"
    deadline = time.monotonic() + 30
    code, arm, cfg = _daemon_in_process(tmp_path, gate, ["denim", "silk"],
                                        stop_when=lambda: fault_file.exists() or time.monotonic() > deadline)
    assert code == 0 and arm.press_count == 0
    fault = next(r for r in read_records(cfg.journal) if r["type"] == "fault")
    assert fault["kind"] == "fault_latched" and "gate latched at start: failsafe" in fault["reason"]


def test_after_the_operator_clears_a_gate_latched_at_start_the_cell_sorts(tmp_path):
    from vs2t_edge.sim.fake_devices import FakeGate
    from vs2t_edge.runtime.journal import read_records

    gate = FakeGate()
    gate.lose_heartbeat()
    fault_file = tmp_path / "state" / "FAULT"
    cleared = []

    def operator_then_done():
        if fault_file.exists():  # the operator checks the gate and clears (vs2t-edge run --clear-fault)
            cleared.append(fault_file.read_text())
            fault_file.unlink()
        return len(gate.sorted) >= 2

    code, arm, cfg = _daemon_in_process(tmp_path, gate, ["denim", "silk"], stop_when=operator_then_done)
    assert code == 0 and len(cleared) == 1
    recs = read_records(cfg.journal)
    assert [r["type"] for r in recs if r["type"] in ("fault", "fault_cleared", "item")][:3] == \
        ["fault", "fault_cleared", "item"]
    assert [r["outcome"] for r in recs if r["type"] == "final"] == ["sorted", "sorted"]
    assert gate.sorted == [1, 2]


def test_a_gate_with_fewer_bins_than_the_scene_names_refuses_the_start(tmp_path, sim):
    """A scene bin the gate does not have was found by the first piece sorted there: a fault
    latched mid-job (the piece to reject, the line stopped until someone read the config). The
    start now asks the gate its bins (STATUS) and refuses, naming the fabrics and the bins."""
    from vs2t_edge.sim.fake_devices import FakeGate
    from vs2t_edge.runtime.journal import read_records

    gate = SerialGate(sim.device_path, timeout_s=0.5, retries=2, heartbeat_period_s=0.05)
    gate.connect()
    try:
        assert gate.status().n_bins == sim.firmware.n_bins  # what the firmware's STATUS says
    finally:
        gate.disconnect()
    small = FakeGate(n_bins=3)  # bins 0..2; the grey world's wool goes to bin 3
    fault_file = tmp_path / "state" / "FAULT"  # where the old start ended: a fault at wool's sort
    code, arm, cfg = _daemon_in_process(tmp_path, small, ["denim", "wool"],
                                        stop_when=lambda: len(small.sorted) >= 2 or fault_file.exists())
    assert code == 2 and arm.press_count == 0 and small.sorted == []
    recs = read_records(cfg.journal)
    assert [r["type"] for r in recs] == ["start_failed"]
    assert "bins 0..2" in recs[0]["reason"] and "wool (bin 3)" in recs[0]["reason"]
    fine = FakeGate(n_bins=4)
    code, arm, cfg = _daemon_in_process(tmp_path, fine, ["denim", "wool"], stop_when=lambda: len(fine.sorted) >= 2)
    assert code == 0 and fine.sorted == [1, 3]


# --- the fault matrix's noise row must catch a parser that loses frames ---------------------------

def _lossy_check_frame(buf):
    """The classic resync bug docs/protocol.md warns of: on a CRC mismatch drop the whole frame
    LEN announces, not just up to the next sync - a good frame starting inside a false one is lost."""
    answer = _good_check_frame(buf)
    if answer.kind == p.DROP and len(buf) > 1 and buf[0] == p.SYNC and buf[1] <= p.MAX_PAYLOAD:
        return p.Check(p.DROP, min(len(buf), p.MIN_FRAME + buf[1]))
    return answer


_good_check_frame = p.check_frame


def test_the_lossy_parser_really_loses_noise_prefixed_frames():
    import random

    rng = random.Random(5)
    frame = p.encode_frame(3, p.ACK, p.Ack(p.SORT, 0, 1, 0, 1).pack())
    stream = b"".join(bytes(rng.choice((p.SYNC, rng.randrange(256))) for _ in range(7)) + frame for _ in range(2000))
    good, lossy = p.FrameReader(), p.FrameReader()
    n_good = len(good.feed(stream + bytes(p.MAX_FRAME)))
    try:
        p.check_frame = _lossy_check_frame
        n_lossy = len(lossy.feed(stream + bytes(p.MAX_FRAME)))
    finally:
        p.check_frame = _good_check_frame
    assert n_good == 2000
    assert 0.02 < 1 - n_lossy / 2000 < 0.2  # a few percent lost: what the noise row must see


@pytest.mark.slow
def test_the_serial_noise_row_fails_with_a_parser_that_loses_frames(tmp_path, monkeypatch):
    from vs2t_edge.sim import faults, faults_gate

    monkeypatch.setattr(p, "check_frame", _lossy_check_frame)
    # one seed of the row's three is enough to see it (and each lost frame costs a timeout)
    monkeypatch.setattr(faults_gate, "NOISE_SEEDS", faults_gate.NOISE_SEEDS[1:2])
    row = faults.run_scenario(next(s for s in faults.SCENARIOS if s.name == "gate_serial_noise"), tmp_path)
    assert not row.passed
    assert any("lost" in problem for problem in row.problems), row.problems


def test_the_moves_reconciliation_tries_every_split():
    """Seen in a daemon_sigkill run: item 4 was killed after its pre_sort before its SORT got out,
    item 6 was sorted to the same bin. A greedy match gave item 6's move to item 4 and failed."""
    from vs2t_edge.sim.fault_rig import _moves_match_journal

    def final(item, outcome, bin_=0, **extra):
        return {"item": item, "outcome": outcome, "bin": bin_, **extra}

    finals = [final(1, "sorted", 1), final(2, "unknown_outcome", maybe_bin=2),
              final(4, "unknown_outcome", maybe_bin=1), final(6, "sorted", 1)]
    assert _moves_match_journal([0, 1, 2, 1], finals) == ""
    assert _moves_match_journal([0, 1, 2, 1, 1], finals) == ""  # item 4's move did happen
    assert "journal says" in _moves_match_journal([0, 1, 2], finals)  # item 6 sorted without a move
    assert "journal says" in _moves_match_journal([0, 1, 2, 1, 3], finals)  # a move nobody knows of
    # a contradicted ACK: the flap may have gone where the gate reported
    contradicted = [final(1, "unknown_outcome", maybe_bin=2, reported_bin=7)]
    assert _moves_match_journal([7], contradicted) == "" and _moves_match_journal([2], contradicted) == ""


def test_a_link_lost_after_the_sort_went_out_may_have_moved_the_flap(sim, client):
    """The USB adapter goes while the gate's ACK is on its way: the SORT was executed (the flap is
    at the bin) but the host only sees a link error. That error must say the SORT may have been
    executed, as a timeout does - the cell then records the piece unknown_outcome with the bin
    it may be in, not rejected_fault in the reject bin. A link lost before anything was sent
    says the opposite."""
    import threading

    sim.faults.ack_delay_s = 0.2  # the ACK leaves late: the line dies in between
    unplug = threading.Thread(target=lambda: wait_for(lambda: sim.executed == [3]) and sim.stop())
    unplug.start()
    with pytest.raises(GateClientError) as caught:
        client.sort(3)
    unplug.join()
    assert sim.executed == [3] and caught.value.kind == "link"
    assert caught.value.maybe_executed is True
    with pytest.raises(GateClientError) as again:  # nothing can go out now: certain
        client.sort(4)
    assert again.value.kind == "link" and again.value.maybe_executed is False


# --- a refused sort that leaves the flap at another piece's bin ------------------------------------

def test_a_jam_says_where_the_flap_is_held_and_the_latched_gate_keeps_it_there(sim, client):
    """The firmware's NAK of a jammed SORT reports the flap at the last bin it reached, in state
    FAULT; latched, the gate refuses the move to reject too, so the flap stays at the bin of the
    piece before - the error carries both, for the cell's record."""
    client.sort(3)
    sim.jam()
    with pytest.raises(GateClientError) as caught:
        client.sort(5)
    assert (caught.value.kind, caught.value.reported_bin, caught.value.reported_state) == ("jam", 3, "fault")
    client.to_reject()  # refused (latched), never raises
    assert client.status().bin == 3


def test_the_cell_records_a_piece_whose_sort_jammed_as_unknown_naming_both_bins(tmp_path):
    """A jam leaves the flap stuck between the last bin the gate reached and the one asked, with its
    servo let go, latched: the refused piece is recorded unknown_outcome with maybe_bin (asked) and
    reported_bin (the last bin reached, which the NAK reports) - never a plain reject."""
    from test_cell import BINS, finals, make_cell

    cell, _arm, _cam, gate, journal = make_cell(tmp_path, [50, 50, 50] + [60, 60, 60])
    assert [r.outcome for r in cell.run(max_items=1)] == ["sorted"] and gate.sorted == [BINS["denim"]]
    gate.jam_next_sort()
    result = cell.run(max_items=2)[-1]  # max_items counts the cell's pieces
    last = finals(journal.path)[-1]
    assert result.outcome == last["outcome"] == "unknown_outcome" and last["bin"] == 0
    assert (last["maybe_bin"], last["reported_bin"]) == (BINS["silk"], BINS["denim"])
    assert f"may be in bin {BINS['silk']}, bin {BINS['denim']} (the last bin the latched gate" in last["reason"]
    assert cell.fault and gate.status().bin == BINS["denim"]

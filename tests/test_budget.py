"""Issue 17, items 3 and 4: a config validate-config passes never makes a driver refuse at `run`,
and the loop's waits fit systemd's watchdog (runtime/budget.py)."""

from __future__ import annotations

import contextlib
import itertools
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from cell_fakes import FakeEvidence, FakeModel
from vs2t_edge.firmware_bridge.gate_client import GateClient, GateClientError, timing_problems
from vs2t_edge.firmware_bridge.gate_client import move_problems as gate_move_problems
from vs2t_edge.sim.fake_devices import FakeArm
from vs2t_edge.runtime.budget import SYSTEMD_WATCHDOG_S, StepBounds, allowed_wait_s, bounds_of, unleased_waits
from vs2t_edge.runtime.cell import Cell, SceneSpec
from vs2t_edge.runtime.items import ContinuousFeed
from vs2t_edge.runtime.config import ConfigError, load_config
from vs2t_edge.runtime.devices import CameraError, Frame
from vs2t_edge.sim.fake_devices import FakeGate
from vs2t_edge.runtime.journal import Journal, read_records
from vs2t_edge.runtime.notify import Notifier
from vs2t_edge.sim.scene import fake_cell_yaml

HERE = Path(__file__).parent
REPO = HERE.parent

DENIM = (("denim", "touched", 1),)


def _cfg(tmp_path, timeout=0.5, retries=3, wait=1.0):
    path = tmp_path / "cell.yaml"
    path.write_text(fake_cell_yaml(fabrics=DENIM, gate={"kind": "serial", "url": "/dev/null", "timeout_s": timeout,
                                                        "retries": retries},
                                   journal="j.jsonl", watchdog={"wait_item_timeout_s": wait}))
    return path


# --- item 3: one source for the driver's constraints and validation ------------------------------

def test_a_gate_timeout_the_driver_refuses_is_refused_by_validation(tmp_path):
    # 0.9 s is inside the documented 0.05 .. 10, but 0.9 + the 0.25 s heartbeat period is past the
    # gate's 1 s heartbeat timeout: `run` died with a ValueError traceback, exit 1, restarted
    path = _cfg(tmp_path, timeout=0.9)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert "devices.gate.timeout_s = 0.9" in str(err.value) and "heartbeat timeout" in str(err.value)
    line = next(n for n, text in enumerate(path.read_text().splitlines(), 1) if "timeout_s: 0.9" in text)
    assert f"{path}:{line}:" in str(err.value)  # file and line of the key, as every config problem


def test_a_gate_timeout_shorter_than_the_flaps_move_is_refused_by_validation(tmp_path):
    """The gate ACKs a SORT (and connect's CLEAR) only once its flap reached the bin, which a working
    flap may take up to the firmware's MOVE_TIMEOUT (0.3 s) to do. `timeout_s: 0.2` passed validation,
    and every try of a slow move timed out (a retransmission is ignored while the flap moves): a
    latched gate fault at connect or at the first piece. Refused now, naming the key and both values."""
    path = _cfg(tmp_path, timeout=0.2)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    msg = str(err.value)
    assert "devices.gate.timeout_s = 0.2" in msg and "0.3 s" in msg and "move" in msg, msg
    line = next(n for n, text in enumerate(path.read_text().splitlines(), 1) if "timeout_s: 0.2" in text)
    assert f"{path}:{line}:" in msg
    p = subprocess.run([sys.executable, "-m", "vs2t_edge.cli", "validate-config", str(path)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "devices.gate.timeout_s = 0.2" in p.stderr and "0.3 s" in p.stderr, p.stderr
    load_config(_cfg(tmp_path, timeout=0.35))  # longer than the longest move: accepted


def test_what_the_move_rule_prevents_a_slow_flap_outlasts_every_short_try():
    """The simulated MCU with a 250 ms move (inside MOVE_TIMEOUT): with tries of 0.2 s the driver's
    CLEAR at connect never gets its ACK; with 0.35 s it does."""
    from vs2t_edge.firmware_bridge.mcu_sim import start_simulated_gate

    for timeout, ok in ((0.2, False), (0.35, True)):
        path, sim = start_simulated_gate(move_time_ms=250)
        client = GateClient(path, timeout_s=timeout, retries=0)
        try:
            client.connect()
            connected = True
        except GateClientError as exc:
            connected = False
            assert exc.kind == "timeout"
        finally:
            client.disconnect()
            sim.stop()
        assert connected == ok == (not gate_move_problems(timeout)), timeout


@pytest.mark.parametrize("timeout, retries", list(itertools.product([0.05, 0.3, 0.7, 0.74, 0.75, 0.9, 10.0], [0, 3, 10])))
def test_validation_passes_exactly_what_the_gate_driver_accepts(tmp_path, timeout, retries):
    try:
        GateClient("/dev/null", timeout_s=timeout, retries=retries)
        driver_ok = True
    except ValueError:
        driver_ok = False
    try:
        load_config(_cfg(tmp_path, timeout=timeout, retries=retries))
        config_ok = True
    except ConfigError:
        config_ok = False
    # the driver takes a try shorter than the flap's move (a simulator's flap moves in 60 ms); a cell config does not
    assert driver_ok == (not timing_problems(timeout, retries))
    assert config_ok == (driver_ok and not gate_move_problems(timeout))


def test_run_refuses_a_gate_the_driver_rejects_in_words_not_a_traceback(tmp_path):
    cfg = _cfg(tmp_path, timeout=0.9)
    p = subprocess.run([sys.executable, "-m", "vs2t_edge.cli", "run", "--config", str(cfg)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "heartbeat timeout" in p.stderr and "Traceback" not in p.stderr, p.stderr


# --- item 4: the watchdog budget -------------------------------------------------------------------

def test_the_budget_uses_the_units_watchdog():
    unit = (REPO / "systemd" / "vs2t-edge.service").read_text()
    assert f"WatchdogSec={SYSTEMD_WATCHDOG_S:g}\n" in unit


def test_a_wait_for_a_piece_longer_than_the_watchdog_allows_is_refused(tmp_path):
    # 60 s was within the documented bounds: no ping for 60 s against WatchdogSec=30
    with pytest.raises(ConfigError, match="watchdog.wait_item_timeout_s: the wait for the next piece may take 60"):
        load_config(_cfg(tmp_path, wait=60))
    assert load_config(_cfg(tmp_path, wait=allowed_wait_s())).wait_item_timeout_s == allowed_wait_s()


def test_every_unleased_wait_of_the_shipped_and_the_worst_valid_gate_fits_the_watchdog(tmp_path):
    cfg = load_config(REPO / "systemd" / "cell.yaml")
    waits = unleased_waits(bounds_of(cfg.camera, cfg.arm_kind, cfg.arm, cfg.gate), cfg.wait_item_timeout_s)
    assert all(s <= allowed_wait_s() for _, s, _ in waits), waits
    worst = load_config(_cfg(tmp_path, timeout=0.74, retries=10))  # the slowest gate validation passes
    waits = unleased_waits(bounds_of(worst.camera, worst.arm_kind, worst.arm, worst.gate), 1.0)
    assert max(s for _, s, _ in waits) <= allowed_wait_s()


class _SlowArm(FakeArm):
    """Every move takes ``move_s`` of real time, as a real arm's do."""

    def __init__(self, move_s, **kw):
        super().__init__(**kw)
        self.move_s = move_s

    def move_above(self, x_mm, y_mm):
        time.sleep(self.move_s)
        return super().move_above(x_mm, y_mm)

    def retract(self):
        time.sleep(self.move_s)
        return super().retract()


class _HungCamera:
    """The reference grab works; every press grab waits out its timeout and fails."""

    def __init__(self, timeout_s):
        self.timeout_s, self.grabs = timeout_s, 0

    def connect(self):
        pass

    def disconnect(self):
        pass

    def grab(self):
        import numpy as np

        self.grabs += 1
        if self.grabs == 1:
            return Frame(np.full((48, 64, 3), 100, np.uint8), time.monotonic(), 0)
        time.sleep(self.timeout_s)
        raise CameraError(f"no frame within {self.timeout_s} s", device="camera", kind="timeout")


def test_pings_come_often_enough_through_a_hung_grab_and_its_retry(tmp_path, monkeypatch):
    """Scaled to a 1 s watchdog: moves of 0.15 s and a grab that hangs 0.5 s, twice. One press try
    takes ~0.95 s, a try plus the retry's preparation ~1.6 s: with pings only at press boundaries,
    every half watchdog, the gap passed the watchdog (measured 1.10 s). The fault must latch
    with no gap in the pings longer than the watchdog."""
    watchdog_s = 1.0
    sock_path = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(sock_path)
    monkeypatch.setenv("WATCHDOG_USEC", str(int(watchdog_s * 1e6)))
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    notifier = Notifier(address=sock_path)
    arm = _SlowArm(0.15)
    arm.connect()
    camera = _HungCamera(0.5)
    bounds = StepBounds(arm_call_s=0.3, grab_s=0.6, gate_request_s=0.1)  # each wait's own bound
    scene = SceneSpec(bins={"denim": 1}, reject_bin=0, points_mm=[(40.0, 40.0)] * 4, max_presses=2,
                      confidence=0.9, wait_item_timeout_s=0.05, fault_file=tmp_path / "FAULT", bounds=bounds)
    journal = Journal.open(tmp_path / "j.jsonl")
    cell = Cell(camera=camera, arm=arm, gate=FakeGate(), model=FakeModel({100: "denim"}, ["denim"]),
                journal=journal, notifier=notifier, scene=scene,
                evidence_factory=lambda: FakeEvidence(["denim"], 0.9, 2), items=ContinuousFeed(limit=1),
                log=lambda m: None)
    server.setblocking(False)
    pings: list[float] = []
    notifier.watchdog()
    start = time.monotonic()
    import threading

    def listen():
        while time.monotonic() - start < 10 and not done.is_set():
            try:
                if server.recv(4096) == b"WATCHDOG=1":
                    pings.append(time.monotonic())
            except BlockingIOError:
                time.sleep(0.005)

    done = threading.Event()
    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    cell.run(max_items=1, stop_when=lambda: cell.fault is not None)
    notifier.watchdog()
    time.sleep(0.05)
    done.set()
    listener.join()
    journal.close()
    assert cell.fault and "failed twice" in cell.fault
    gaps = [b - a for a, b in zip(pings, pings[1:])]
    assert pings and max(gaps) < watchdog_s * 0.5, f"largest gap between pings {max(gaps):.2f} s"
    assert [r["type"] for r in read_records(tmp_path / "j.jsonl")].count("fault") == 1


@pytest.mark.parametrize("edge", ["low", "high"])
def test_every_device_a_valid_config_describes_can_be_built(tmp_path, edge):
    """The audit of issue 17 item 3 as a test: at both ends of every device bound validation
    accepts, the live constructors (camera, arm, gate) accept the settings too."""
    from vs2t_edge.runtime.arm_isolated import IsolatedURArm
    from vs2t_edge.runtime.camera import camera_from_config
    from vs2t_edge.runtime.gate import SerialGate

    low = edge == "low"
    text = fake_cell_yaml(
        fabrics=DENIM, journal="j.jsonl", arm={"kind": "ur_rtde"},
        camera={"kind": "uvc", "device": "/dev/null-camera", "width_px": 16 if low else 4096,
                "height_px": 16 if low else 4096, "fps": 1 if low else 240, "timeout_s": 0.05 if low else 10,
                "flush_frames": 0 if low else 30, "frozen_after": 2 if low else 100},
        gate={"kind": "serial", "url": "/dev/null", "timeout_s": 0.31 if low else 0.74, "retries": 0 if low else 10},
        watchdog={"wait_item_timeout_s": 0.01 if low else 26})
    (tmp_path / "cell.yaml").write_text(text)
    cfg = load_config(tmp_path / "cell.yaml")
    camera_from_config(cfg.camera)  # constructors only: nothing is opened
    IsolatedURArm(cfg.arm)
    SerialGate(cfg.gate["url"], timeout_s=cfg.gate["timeout_s"], retries=cfg.gate["retries"])


class _SlowClearGate(FakeGate):
    """The gate's CLEAR answers after ``clear_s`` of real time (within its own request bound)."""

    def __init__(self, clear_s):
        super().__init__()
        self.clear_s = clear_s

    def clear(self):
        time.sleep(self.clear_s)
        return super().clear()


def test_the_operators_clear_is_leased_so_a_slow_clear_does_not_starve_the_watchdog(tmp_path, monkeypatch):
    """Scaled to a 1 s watchdog: a gate whose CLEAR takes 1.3 s (a slow MCU, within the bound the
    driver enforces). The clear was not leased: no ping went out while it lasted, so systemd would
    kill the service the operator was bringing back. Now the pings go on through it."""
    watchdog_s = 1.0
    arm = FakeArm()
    arm.connect()
    bounds = StepBounds(arm_call_s=0.3, grab_s=0.6, gate_request_s=0.1, camera_open_s=0.6)
    assert bounds.clear_s > 1.3
    scene = SceneSpec(bins={"denim": 1}, reject_bin=0, points_mm=[(40.0, 40.0)], max_presses=1,
                      confidence=0.9, wait_item_timeout_s=0.05, fault_file=tmp_path / "FAULT", bounds=bounds)
    journal = Journal.open(tmp_path / "j.jsonl")
    gate = _SlowClearGate(1.3)
    gate.connect()
    with _watched(tmp_path, monkeypatch, watchdog_s) as (notifier, pings):
        cell = Cell(camera=_HungCamera(0.0), arm=arm, gate=gate, model=FakeModel({100: "denim"}, ["denim"]),
                    journal=journal, notifier=notifier, scene=scene,
                    evidence_factory=lambda: FakeEvidence(["denim"], 0.9, 1), items=ContinuousFeed(limit=1),
                    log=lambda m: None)
        cell.latch_fault("operator test", "fault")
        (tmp_path / "FAULT").unlink(missing_ok=True)
        start = time.monotonic()
        assert cell.clear_fault()
        took = time.monotonic() - start
    journal.close()
    assert took >= 1.3 and cell.fault is None
    gaps = [b - a for a, b in zip(pings, pings[1:])]
    assert len(pings) >= 3 and max(gaps) < watchdog_s * 0.8, f"largest gap between pings {max(gaps):.2f} s"


@contextlib.contextmanager
def _watched(tmp_path, monkeypatch, watchdog_s=1.0):
    """A notify socket under a ``watchdog_s`` watchdog: yields the Notifier and the times of the
    pings it sends. The block starts with a ping and ends with one, as the loop's step boundaries
    before and after a device wait would."""
    sock_path = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(sock_path)
    server.setblocking(False)
    monkeypatch.setenv("WATCHDOG_USEC", str(int(watchdog_s * 1e6)))
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    notifier = Notifier(address=sock_path)
    pings: list[float] = []
    done = threading.Event()

    def listen():
        while not done.is_set():
            try:
                if server.recv(4096) == b"WATCHDOG=1":
                    pings.append(time.monotonic())
            except BlockingIOError:
                time.sleep(0.005)

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    notifier.watchdog()
    try:
        yield notifier, pings
    finally:
        notifier.watchdog()
        time.sleep(0.05)
        done.set()
        listener.join()
        server.close()


def _gaps(pings):
    return [b - a for a, b in zip(pings, pings[1:])]


def _cell(tmp_path, notifier, bounds, *, arm, gate=None, camera=None, stop_event=None):
    arm.connect()
    gate = gate or FakeGate()
    gate.connect()
    scene = SceneSpec(bins={"denim": 1}, reject_bin=0, points_mm=[(40.0, 40.0)] * 2, max_presses=2,
                      confidence=0.9, wait_item_timeout_s=0.05, fault_file=tmp_path / "FAULT", bounds=bounds)
    return Cell(camera=camera or _HungCamera(0.0), arm=arm, gate=gate, model=FakeModel({100: "denim"}, ["denim"]),
                journal=Journal.open(tmp_path / "j.jsonl"), notifier=notifier, scene=scene,
                evidence_factory=lambda: FakeEvidence(["denim"], 0.9, 2), items=ContinuousFeed(limit=1),
                stop_event=stop_event, log=lambda m: None)


def test_a_clear_hung_past_its_bound_is_left_to_the_watchdog(tmp_path, monkeypatch):
    """The lease of the operator's clear feeds the watchdog for clear_s (1.9 s here) and no
    longer: a CLEAR hung for 3.2 s, past every bound its devices enforce, leaves a gap longer
    than the 1 s watchdog - systemd kills a hung loop, as it should."""
    bounds = StepBounds(arm_call_s=0.3, grab_s=0.6, gate_request_s=0.1, camera_open_s=0.6)
    assert bounds.clear_s == pytest.approx(1.9)
    with _watched(tmp_path, monkeypatch) as (notifier, pings):
        cell = _cell(tmp_path, notifier, bounds, arm=FakeArm(), gate=_SlowClearGate(3.2))
        cell.latch_fault("operator test", "fault")
        (tmp_path / "FAULT").unlink()
        start = time.monotonic()
        assert cell.clear_fault()
    cell.journal.close()
    last_leased = max(t for t in pings if t - start < 3.1)  # the later ones: after the CLEAR answered
    assert last_leased - start >= bounds.clear_s - 0.3, "the lease stopped before its bound"
    assert last_leased - start < bounds.clear_s + 0.05, "the lease went on past its bound"
    assert max(_gaps(pings)) > 1.0, f"largest gap between pings {max(_gaps(pings)):.2f} s"


class _SlowRetractArm(FakeArm):
    """Lifting the gel takes ``retract_s`` of real time (within the arm call's bound)."""

    def __init__(self, retract_s, **kw):
        super().__init__(**kw)
        self.retract_s = retract_s

    def retract(self):
        time.sleep(self.retract_s)
        return super().retract()


def test_lifting_the_gel_before_a_fault_is_leased(tmp_path, monkeypatch):
    """Scaled to a 1 s watchdog: the press fails twice ('force never reached') and the gel is
    lifted before the fault latches, a retract of 1.3 s (the arm's call bound is 1.5 s). The lift
    was not leased: no ping for 1.3 s."""
    bounds = StepBounds(arm_call_s=1.5, grab_s=0.6, gate_request_s=0.1)
    arm = _SlowRetractArm(1.3, fail_next=["force_not_reached", "force_not_reached"])
    with _watched(tmp_path, monkeypatch) as (notifier, pings):
        cell = _cell(tmp_path, notifier, bounds, arm=arm)
        cell.run(max_items=1, stop_when=lambda: cell.fault is not None)
    cell.journal.close()
    assert cell.fault and "failed twice" in cell.fault
    assert arm.calls.count("retract") == 2  # the retry's preparation, then the lift before the fault
    assert max(_gaps(pings)) < 0.8, f"largest gap between pings {max(_gaps(pings)):.2f} s"


class _StopAtReference(_HungCamera):
    """SIGTERM arrives while the reference frame is taken."""

    def __init__(self, stop_event):
        super().__init__(0.0)
        self.stop_event = stop_event

    def grab(self):
        self.stop_event.set()
        return super().grab()


def test_the_abort_on_sigterm_is_leased(tmp_path, monkeypatch):
    """Scaled to a 1 s watchdog: SIGTERM mid-item lifts the gel (1.3 s, within the arm's 1.5 s
    bound) and sends the gate to reject before the item's final record. The abort was not leased."""
    bounds = StepBounds(arm_call_s=1.5, grab_s=0.6, gate_request_s=0.1)
    stop = threading.Event()
    arm = _SlowRetractArm(1.3)
    gate = FakeGate()
    with _watched(tmp_path, monkeypatch) as (notifier, pings):
        cell = _cell(tmp_path, notifier, bounds, arm=arm, gate=gate, camera=_StopAtReference(stop), stop_event=stop)
        cell.run(max_items=1)
    cell.journal.close()
    final = [r for r in read_records(tmp_path / "j.jsonl") if r["type"] == "final"]
    assert [r["outcome"] for r in final] == ["aborted"] and arm.calls[-1] == "retract" and gate.to_reject_calls
    assert max(_gaps(pings)) < 0.8, f"largest gap between pings {max(_gaps(pings)):.2f} s"


class _LiveWorker:
    def poll(self):
        return None


def _isolated_arm_waits(monkeypatch, *calls):
    """The timeouts an IsolatedURArm whose worker died waits for, call by call: the first call
    starts a new worker and connects it (no process is started here)."""
    from vs2t_edge.runtime.arm import ArmConfig
    from vs2t_edge.runtime.arm_isolated import IsolatedURArm

    arm = IsolatedURArm(ArmConfig())
    arm._wanted = True  # connected before; the worker has died since
    waits: list[tuple[str, float]] = []
    monkeypatch.setattr(arm, "_spawn", lambda: setattr(arm, "_proc", _LiveWorker()))
    monkeypatch.setattr(arm, "_send", lambda method, args, timeout_s: waits.append((method, timeout_s)))
    for call in calls:
        getattr(arm, call)()
    return arm, waits


@pytest.mark.parametrize("lease, calls", [("lift_s", ["retract"]),
                                          ("clear", ["clear_protective_stop", "connect"])])
def test_a_lease_of_the_live_arm_covers_a_new_workers_start(monkeypatch, lease, calls):
    """After the arm worker died (what IsolatedURArm exists for), the next call starts a new
    worker and connects it first - up to start_timeout_s + two call bounds for a lift. The lift
    was leased for one call bound and the clear for one call bound less than it may take."""
    arm, waits = _isolated_arm_waits(monkeypatch, *calls)
    assert [m for m, _ in waits] == ["connect", *calls]
    bounds = bounds_of({"timeout_s": 1.0}, "ur_rtde", arm.config, {"kind": "sim"})
    arm_part = bounds.lift_s if lease == "lift_s" else bounds.clear_s - bounds.gate_request_s - bounds.camera_reopen_s
    assert sum(t for _, t in waits) <= arm_part
    assert bounds_of({"timeout_s": 1.0}, "fake", arm.config, {"kind": "sim"}).arm_start_s == 0  # no worker

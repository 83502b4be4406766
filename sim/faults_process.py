"""Fault-matrix rows at the process: the real daemon in a subprocess, signalled and killed.

``daemon_child`` is the daemon with fake devices and the grey model (``python -m
vs2t_edge.sim.faults daemon-child CONFIG [GATE_URL]``); ``GateProcess`` is the MCU simulator in
its own process, so the gate outlives a killed service as the real one does; registered in
sim/faults.py SCENARIOS.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Callable

from vs2t_edge.runtime.items import Item
from vs2t_edge.runtime.journal import read_records
from vs2t_edge.runtime.notify import Notifier
from vs2t_edge.sim.fakes import CLASSES, REJECT, GreyEvidence, GreyModel
from vs2t_edge.sim.fault_rig import (
    TRUTHS,
    FaultArm,
    Pieces,
    _check,
    _moves_match_journal,
    _outcome_words,
    audit,
    grey_frames,
)
from vs2t_edge.sim.scene import fake_cell_yaml


# --- daemon subprocess rows -------------------------------------------------------------------

# The daemon rows' cell: fake devices, the grey world's three fabrics (sim/fakes.py BINS).
DAEMON_SECTIONS = {"threads": 1, "evidence": {"confidence": 0.95, "max_presses": 3}, "fault_file": "state/FAULT",
                   "watchdog": {"wait_item_timeout_s": 0.05}}
DAEMON_CONFIG = fake_cell_yaml(**DAEMON_SECTIONS)


def daemon_child(config: str, score_delay_s: float = 0.03, gate_travel_s: float = 0.08,
                 gate_url: str | None = None) -> int:
    """The real daemon with fake devices and the grey model (``python -m vs2t_edge.sim.faults
    daemon-child CONFIG [GATE_URL]``): signals, journal, recovery are the production code path.
    With ``gate_url`` the gate is the real host driver on that port (an MCU simulator in another
    process, so it outlives this one, as the real gate outlives a killed service)."""
    from vs2t_edge.sim.fake_devices import FakeArm
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.sim.fake_devices import FakeGate
    from vs2t_edge.sim.devices import SimulatedCamera

    cfg = load_config(config)

    class Endless(Pieces):
        def next_item(self, timeout_s):
            self.items.append(Item(f"piece-{os.getpid()}-{len(self.items):05d}", TRUTHS[len(self.items) % 4]))
            self.index = len(self.items) - 1
            return self.items[-1]

    class SlowGrey(GreyModel):
        def score_press(self, frame):
            time.sleep(score_delay_s)  # a press takes time: signals land mid-item
            return super().score_press(frame)

    class MovingGate(FakeGate):
        def sort(self, bin_index):
            time.sleep(gate_travel_s)  # the flap takes time to move: a kill lands between pre_sort and ack
            return super().sort(bin_index)

    pieces = Endless([])
    arm = FaultArm(FakeArm(config=cfg.arm), pieces)
    camera = SimulatedCamera(grey_frames(arm, pieces), noise_levels=1.0, seed=0)
    if gate_url:
        from vs2t_edge.runtime.gate import SerialGate

        gate = SerialGate(gate_url, timeout_s=0.3)
    else:
        gate = MovingGate()
    return run_daemon(cfg, model=SlowGrey(), camera=camera, arm=arm, gate=gate, items=pieces,
                      evidence_factory=lambda: GreyEvidence(CLASSES, cfg.confidence, cfg.max_presses),
                      notifier=Notifier(address=""))


def start_daemon(w: Path, gate_url: str | None = None) -> tuple[subprocess.Popen, Path]:
    w.mkdir(parents=True, exist_ok=True)
    cfg = w / "cell.yaml"
    if not cfg.exists():
        cfg.write_text(DAEMON_CONFIG)
        cfg.chmod(0o640)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("NOTIFY_SOCKET", None)
    proc = subprocess.Popen([sys.executable, "-m", "vs2t_edge.sim.faults", "daemon-child", str(cfg),
                             *([gate_url] if gate_url else [])], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, w / "state" / "journal.jsonl"


def wait_for(journal: Path, pred: Callable[[list], bool], limit_s: float = 30.0, poll_s: float = 0.002) -> bool:
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        recs = read_records(journal)
        if recs and pred(recs):
            return True
        time.sleep(poll_s)
    return False


def _stop(proc: subprocess.Popen, sig=signal.SIGTERM) -> tuple[int, str]:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        _out, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        _out, err = proc.communicate()
    return proc.returncode, err


def _daemon_truths(recs: list[dict]) -> dict:
    return {r["item_id"]: TRUTHS[int(r["item_id"].rsplit("-", 1)[1]) % 4]
            for r in recs if r.get("type") == "item"}


def daemon_sigterm(w: Path):
    proc, journal = start_daemon(w)
    try:
        ok = wait_for(journal, lambda rs: sum(r["type"] == "final" for r in rs) >= 3 and rs[-1]["type"] == "item")
    finally:
        code, err = _stop(proc, signal.SIGTERM)
    problems: list[str] = []
    _check(problems, ok, "never saw three items and a fourth started")
    recs = read_records(journal)
    a = audit(journal, _daemon_truths(recs))
    problems += a["problems"]
    _check(problems, code == 0, f"exit code {code}: {err[-300:]}")
    _check(problems, recs[-1].get("type") == "stop" and recs[-1].get("reason") == "SIGTERM",
           f"last record {recs[-1]}")
    _check(problems, a["finals"][-1]["outcome"] == "aborted" and a["finals"][-1]["bin"] == REJECT,
           f"the item in hand ended as {a['finals'][-1]}")
    last_before = max(r["item"] for r in recs if r.get("type") == "item")

    def after_restart(rs: list) -> list:
        starts = [i for i, r in enumerate(rs) if r["type"] == "start"]
        return rs[starts[1] + 1:] if len(starts) >= 2 else []

    proc2, _ = start_daemon(w)  # restart: nothing open, carries on with new numbers
    ok2 = wait_for(journal, lambda rs: sum(r["type"] == "final" and r.get("outcome") == "sorted"
                                           for r in after_restart(rs)) >= 3)
    code2, err2 = _stop(proc2)
    recs2 = read_records(journal)
    a2 = audit(journal, _daemon_truths(recs2))
    problems += a2["problems"]
    _check(problems, code2 == 0, f"restart exit code {code2}: {err2[-300:]}")
    new = after_restart(recs2)
    sorted_new = [r for r in new if r["type"] == "final" and r.get("outcome") == "sorted"]
    _check(problems, ok2 and len(sorted_new) >= 3, f"the restarted daemon sorted {len(sorted_new)} pieces (wanted 3)")
    _check(problems, all(r["item"] > last_before for r in new if "item" in r),
           f"the restart reused item numbers <= {last_before}: {sorted({r['item'] for r in new if 'item' in r})}")
    _check(problems, not [r for r in new if r["type"] == "final" and r["item"] <= last_before],
           "the restart wrote a final record for an item the first run had closed")
    return _outcome_words(a2, f"exit {code}; restart sorted {len(sorted_new)} more (items {last_before + 1}+), "
                              f"exit {code2}"), problems


class GateProcess:
    """The MCU simulator in its own process (``python -m vs2t_edge.firmware_bridge.mcu_sim``): a
    gate that outlives a killed daemon, as the real one does. ``executed`` (the SORT moves it
    made) is known once ``stop()`` has run."""

    def __init__(self, move_ms: int = 80) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "vs2t_edge.firmware_bridge.mcu_sim",
                                      "--move-ms", str(move_ms)],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        first = self.proc.stdout.readline()  # "simulated gate on /dev/pts/N ..."
        if " on " not in first:
            self.proc.kill()
            raise RuntimeError(f"the MCU simulator did not start: {first!r} {self.proc.stderr.read()[-300:]}")
        self.path = first.split(" on ", 1)[1].split()[0]
        self.executed: list[int] | None = None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, _err = self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _err = self.proc.communicate()
        for line in out.splitlines():
            if line.startswith("executed "):
                self.executed = json.loads(line[len("executed "):])

    def __enter__(self) -> "GateProcess":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class Operator:
    """Clears a latched fault as soon as it appears (``vs2t-edge run --clear-fault``), for daemon rows."""

    def __init__(self, w: Path) -> None:
        self.fault_file = w / "state" / "FAULT"
        self.cleared: list[str] = []

    def waiting(self, pred: Callable[[list], bool]) -> Callable[[list], bool]:
        def check(recs: list) -> bool:
            if self.fault_file.exists():
                self.cleared.append(self.fault_file.read_text().strip())
                self.fault_file.unlink()
            return pred(recs)
        return check


def _after_start(recs: list, n: int) -> list:
    """The records after the ``n``-th start record (1-based), [] before it."""
    starts = [i for i, r in enumerate(recs) if r["type"] == "start"]
    return recs[starts[n - 1] + 1:] if len(starts) >= n else []


def _gate_reconciled(problems: list[str], gate: GateProcess, finals: list[dict]) -> str:
    _check(problems, gate.executed is not None, "the MCU simulator did not report its moves")
    executed = gate.executed or []
    why = _moves_match_journal(executed, finals)
    _check(problems, not why, why)
    return f"gate executed {executed}"


def daemon_sigkill(w: Path):
    """kill -9 mid-item (both right after a pre_sort and mid-press, alternately), restart: the open
    item gets exactly one final record (unknown_outcome with the bin it may be in after pre_sort,
    aborted before). The gate is the MCU simulator in its own process, so it outlives each kill as
    the real gate does and its moves must reconcile with the journal: one move per sorted piece, a
    killed sort's move (if the SORT got out) accounted by its unknown_outcome. Once the service
    stays down past the gate's heartbeat timeout: the restart finds the gate fail-safe and latches
    a fault before pressing, which the operator clears."""
    problems: list[str] = []
    seen = Counter()
    operator = Operator(w)
    journal = w / "state" / "journal.jsonl"
    with GateProcess() as gate:
        for round_, after in enumerate(["pre_sort", "item", "pre_sort", "item"]):
            proc, journal = start_daemon(w, gate_url=gate.path)
            starts = sum(r["type"] == "start" for r in read_records(journal))
            ok = wait_for(journal, operator.waiting(
                lambda rs: any(r["type"] == "final" for r in _after_start(rs, starts + 1)) and rs[-1]["type"] == after))
            if proc.poll() is None:
                proc.kill()  # SIGKILL: no handler, no shutdown record, the gate left where it was
            proc.wait(timeout=10)
            recs = read_records(journal)
            open_ = {r["item"] for r in recs if r["type"] == after} - {r["item"] for r in recs if r["type"] == "final"}
            if ok and open_:
                seen[after] += 1
            if round_ == 1:
                time.sleep(1.5)  # down longer than the gate's heartbeat timeout: it fails safe
        proc, journal = start_daemon(w, gate_url=gate.path)
        ok = wait_for(journal, operator.waiting(lambda rs: any(r.get("outcome") == "sorted" for r in _after_start(rs, 5))))
        code, err = _stop(proc)
    recs = read_records(journal)
    a = audit(journal, _daemon_truths(recs))
    problems += a["problems"]
    _check(problems, code == 0, f"final exit {code}: {err[-300:]}")
    _check(problems, ok, "the last restart sorted nothing")
    _check(problems, seen["pre_sort"] >= 1 and seen["item"] >= 1,
           f"kills that left an item open: {dict(seen)} (timing; rerun)")
    o = a["outcomes"]
    _check(problems, o.get("unknown_outcome", 0) == seen["pre_sort"],
           f"{o.get('unknown_outcome', 0)} unknown_outcome for {seen['pre_sort']} kills after pre_sort")
    _check(problems, all(r.get("maybe_bin") is not None for r in a["finals"] if r["outcome"] == "unknown_outcome"),
           "an unknown_outcome record does not name the bin the gate may have moved to")
    at_start = [f for f in a["faults"] if f.startswith("gate latched at start")]
    _check(problems, at_start and len(at_start) == len(a["faults"]),
           f"faults: {a['faults']} (wanted only 'gate latched at start', at least once)")
    _check(problems, len(operator.cleared) == len(a["faults"]), f"operator cleared {len(operator.cleared)} times")
    moves = _gate_reconciled(problems, gate, a["finals"])
    n_sorted = sum(f["outcome"] == "sorted" and f["bin"] != REJECT for f in a["finals"])
    n_killed_moves = sum(b != REJECT for b in gate.executed or []) - n_sorted
    return _outcome_words(a, f"{sum(seen.values())} kills left an item open; {len(at_start)} gate latched at "
                             f"start, cleared; {moves} ({n_killed_moves} made for a killed sort, "
                             "accounted by its unknown_outcome)"), problems


def gate_latched_at_start(w: Path):
    """The service is killed and stays down 1.5 s, past the gate's heartbeat timeout: the gate (its
    own process) fails safe. The restarted daemon must see the latch before pressing a piece - a
    fault record before any item record - and sort again once the operator has cleared it."""
    problems: list[str] = []
    operator = Operator(w)
    with GateProcess() as gate:
        proc, journal = start_daemon(w, gate_url=gate.path)
        ok = wait_for(journal, lambda rs: sum(r.get("outcome") == "sorted" for r in rs) >= 2)
        proc.kill()
        proc.wait(timeout=10)
        time.sleep(1.5)
        proc, journal = start_daemon(w, gate_url=gate.path)
        ok2 = wait_for(journal, lambda rs: any(r["type"] == "fault" for r in _after_start(rs, 2)))
        first_after = [r["type"] for r in _after_start(read_records(journal), 2) if r["type"] in ("fault", "item")][:1]
        ok3 = wait_for(journal, operator.waiting(
            lambda rs: sum(r.get("outcome") == "sorted" for r in _after_start(rs, 2)) >= 2))
        code, err = _stop(proc)
    recs = read_records(journal)
    a = audit(journal, _daemon_truths(recs))
    problems += a["problems"]
    _check(problems, ok and ok2 and ok3, f"never saw: 2 sorted {ok}, a fault after restart {ok2}, "
                                         f"2 sorted after the clear {ok3}")
    _check(problems, first_after == ["fault"], f"after the restart the first of fault/item was {first_after}")
    _check(problems, len(a["faults"]) == 1 and "heartbeat_lost" in a["faults"][0],
           f"expected one fault naming heartbeat_lost, got {a['faults']}")
    _check(problems, len(operator.cleared) == 1, f"operator cleared {len(operator.cleared)} times")
    _check(problems, code == 0, f"exit {code}: {err[-300:]}")
    moves = _gate_reconciled(problems, gate, a["finals"])
    return _outcome_words(a, moves), problems

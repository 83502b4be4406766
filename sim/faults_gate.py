"""Fault-matrix rows at the gate: the real host driver against the MCU simulator on a pty.

Noise, dropped, duplicated, slow, lost and lying ACKs, a jam, a reboot, a FAULT flood; every row
checks the MCU's moves against the journal; registered in sim/faults.py SCENARIOS.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from vs2t_edge.sim.fakes import BINS
from vs2t_edge.sim.fault_rig import Rig, _at, _check, _loop_row, _moves_match_journal, audit


# --- pty gate rows (real host driver, MCU simulator on a pty) ---------------------------------

def _gate_row(w: Path, set_fault: Callable[[Any], None], expect_outcomes: dict, fault_words: str | None,
              fix: Callable[[Any], None] | None = None, timeout_s: float = 0.3,
              fired: Callable[[Any, Any], str] | None = None, seed: int = 1,
              exercise: Callable[[Any], None] | None = None):
    """``fired(gate, sim)``: why the injected fault did not happen ("" when it did), so a row
    cannot pass because the line stayed clean. ``exercise(gate)`` runs right after the fault is
    set (more traffic on the faulty line); ``seed`` seeds the line's noise."""
    from vs2t_edge.firmware_bridge.mcu_sim import LineFaults
    from vs2t_edge.sim.devices import simulated_serial_gate

    faults = LineFaults(seed=seed)
    gate = simulated_serial_gate(faults=faults, timeout_s=timeout_s)
    sim = gate.simulator

    def at_fault() -> None:
        set_fault(sim)
        if exercise is not None:
            exercise(gate)

    def inject(r: Rig):
        _at(r, 1, 1, at_fault)

    words, problems = _loop_row(w, inject=inject, gate=gate, expect_outcomes=expect_outcomes,
                                fault_words=fault_words,
                                operator_fix_for=(lambda r: (lambda: fix(sim))) if fix else None)
    a = audit(w / "journal.jsonl")
    executed = list(sim.executed)
    why = _moves_match_journal(executed, a["finals"])
    _check(problems, not why, why)
    if fired is not None:
        why = fired(gate, sim)
        _check(problems, not why, f"the fault did not fire: {why}")
    return words + f"; gate executed {executed}", problems


def _retransmitted(gate, sim) -> str:
    n = gate._client.retransmissions
    return "" if n >= 1 else "the host never retransmitted"


NOISE_SEEDS = (1, 2, 3)
NOISE_EXCHANGES = 100  # STATUS + HEARTBEAT pairs per seed on the noisy line, beside the cell's own traffic


def serial_noise(w: Path):
    """7 random bytes (sync bytes included) before every MCU frame, on several seeds and hundreds
    of frames: every frame the MCU sent must come out of the host's parser - none lost. A parser
    that drops a whole false frame (CRC mismatch) swallows the good frame starting inside it; the
    cell would still sort (a retransmission recovers), so only the count shows it. The stream is
    flushed with non-sync bytes at the end, as the next traffic would, so a frame still waiting
    behind an undisproved false start is counted, not lost."""
    from vs2t_edge.firmware_bridge.protocol import MAX_FRAME

    words, problems = [], []
    for seed in NOISE_SEEDS:
        counts: dict = {}

        def exercise(gate) -> None:
            for _ in range(NOISE_EXCHANGES):
                gate.client.status()
                gate.client.heartbeat()

        def fired(gate, sim, counts=counts) -> str:
            reader = gate.client._reader
            reader.feed(bytes(MAX_FRAME))  # the stream goes on: disproves any false start left
            counts.update(sent=sim.tx_frames, parsed=reader.frames, dropped=reader.dropped_bytes)
            if reader.dropped_bytes == 0:
                return "the host dropped no byte"
            if sim.tx_frames < 2 * NOISE_EXCHANGES:
                return f"only {sim.tx_frames} frames on the noisy line"
            return ""

        outcome, probs = _gate_row(w / f"seed{seed}", lambda s: setattr(s.faults, "noise_bytes", 7), {"sorted": 4},
                                   None, fired=fired, seed=seed, exercise=exercise)
        _check(probs, counts.get("parsed") == counts.get("sent"),
               f"the MCU sent {counts.get('sent')} frames, the host parsed {counts.get('parsed')}: "
               f"{(counts.get('sent') or 0) - (counts.get('parsed') or 0)} lost")
        words.append(f"seed {seed}: {outcome.split(';')[0]}, {counts.get('parsed')}/{counts.get('sent')} frames "
                     f"parsed, {counts.get('dropped')} noise bytes dropped")
        problems += [f"seed {seed}: {p}" for p in probs]
    return "; ".join(words), problems


def dropped_ack(w: Path):
    return _gate_row(w, lambda s: setattr(s.faults, "drop_tx", 1), {"sorted": 4}, None,
                     fired=lambda g, s: f"drop_tx left at {s.faults.drop_tx}" if s.faults.drop_tx else _retransmitted(g, s))


def dropped_request(w: Path):
    return _gate_row(w, lambda s: setattr(s.faults, "drop_rx", 1), {"sorted": 4}, None,
                     fired=lambda g, s: f"drop_rx left at {s.faults.drop_rx}" if s.faults.drop_rx else _retransmitted(g, s))


def duplicated_frames(w: Path):
    return _gate_row(w, lambda s: setattr(s.faults, "duplicate_tx", 3), {"sorted": 4}, None,
                     fired=lambda g, s: f"duplicate_tx left at {s.faults.duplicate_tx}" if s.faults.duplicate_tx else "")


def slow_ack_within_timeout(w: Path):
    return _gate_row(w, lambda s: setattr(s.faults, "ack_delay_s", 0.15), {"sorted": 4}, None, timeout_s=0.5,
                     fired=lambda g, s: "" if s.faults.ack_delay_s == 0.15 else "no delay set")


def ack_lost_past_timeout(w: Path):
    """The MCU answers 2 s late, past every retry of a 0.3 s timeout: the flap reached the bin but
    the host never heard. The piece's record must say unknown_outcome with the bin it may be in,
    not claim the reject bin; the operator (the MCU back to speed) clears and the rest are sorted."""
    return _gate_row(w, lambda s: setattr(s.faults, "ack_delay_s", 2.0), {"sorted": 3, "unknown_outcome": 1},
                     "may be in bin", fix=lambda s: setattr(s.faults, "ack_delay_s", 0.0))


def gate_jam(w: Path):
    """The flap jams on the second piece's SORT, after the first went to its bin: latched, the gate
    lets its servo go where the flap stuck, between the two bins, and refuses the move to reject, so
    the piece is recorded unknown_outcome with both bins, never a plain reject."""
    return _gate_row(w, lambda s: s.jam(True), {"sorted": 3, "unknown_outcome": 1}, "may be in bin",
                     fix=lambda s: s.jam(False))


def gate_reboot(w: Path):
    return _gate_row(w, lambda s: s.reboot(), {"sorted": 3, "rejected_fault": 1}, "boot id")


def fault_flood(w: Path):
    """A stuck MCU (or the line) floods FAULT frames mid-run - 5000 JAM reports while the gate in
    fact works: the host keeps only the most recent few (the rest counted) and sorts on the
    honest ACKs."""
    from vs2t_edge.firmware_bridge import protocol as gp
    from vs2t_edge.firmware_bridge.gate_client import FAULT_REPORTS_KEPT

    def flood(sim) -> None:
        report = gp.FaultReport(gp.FAULT_JAM, gp.STATE_FAULT, 3, sim.firmware.boot_id).pack()
        frame = gp.encode_frame(1, gp.FAULT, report)
        for _ in range(20):
            sim.inject_noise(frame * 250)
            time.sleep(0.01)  # the heartbeats read in between, as from a real UART

    seen: dict = {}

    def fired(gate, sim) -> str:
        c = gate.client
        seen.update(kept=len(c.fault_reports), seen=c.fault_reports_seen)
        if c.fault_reports_seen <= 4 * FAULT_REPORTS_KEPT:  # a pty loses what the host does not read in time
            return f"only {c.fault_reports_seen} FAULT frames reached the host: no flood"
        if len(c.fault_reports) != FAULT_REPORTS_KEPT or c.fault_reports_dropped + FAULT_REPORTS_KEPT != seen["seen"]:
            return f"kept {len(c.fault_reports)} of {c.fault_reports_seen} FAULT frames (bound {FAULT_REPORTS_KEPT})"
        return ""

    words, problems = _gate_row(w, flood, {"sorted": 4}, None, fired=fired)
    return words + f"; host kept {seen.get('kept')} of {seen.get('seen')} FAULT frames", problems


# What a lying MCU's ACK of a SORT reports instead of "READY at the bin asked" (LineFaults fields).
ACK_LIES = {
    "another bin": {"lie_bin": 7},
    "jam": {"lie_state": 2, "lie_fault": 2},  # FAULT / JAM, at the bin asked
    "failsafe at reject": {"lie_state": 3, "lie_fault": 1, "lie_bin": 0},  # FAILSAFE / HEARTBEAT_LOST
    "busy": {"lie_state": 1},
}


def ack_contradicts_sort(w: Path):
    """The MCU acknowledges item 2's SORT with the right CRC, SEQ and type, but the ACK reports
    the flap at another bin, or the gate jammed, fail-safe or still moving. The piece must not be
    journalled sorted: a fault latches naming the contradiction, the record says unknown_outcome
    with the bin asked (and the bin reported), and after the operator's clear the rest are sorted."""
    words, problems = [], []
    for name, lie in ACK_LIES.items():
        def set_fault(sim, lie=lie):
            for field_, value in lie.items():
                setattr(sim.faults, field_, value)
            sim.faults.lie_acks = 1

        outcome, probs = _gate_row(w / name.replace(" ", "_"), set_fault, {"sorted": 3, "unknown_outcome": 1},
                                   "contradicts",
                                   fired=lambda g, s: "" if s.lies_told == 1 else f"{s.lies_told} lies told")
        finals = audit(w / name.replace(" ", "_") / "journal.jsonl")["finals"]
        odd = [f for f in finals if f["outcome"] != "sorted"]
        reported = lie.get("lie_bin", BINS["silk"])
        _check(probs, len(odd) == 1 and odd[0].get("maybe_bin") == BINS["silk"]
               and odd[0].get("reported_bin", BINS["silk"]) == reported,
               f"the piece's record does not name the bin asked ({BINS['silk']}) and reported ({reported}): {odd}")
        words.append(f"{name}: {outcome.split(';')[0]}")
        problems += [f"{name}: {p}" for p in probs]
    return "; ".join(words), problems

"""The fault matrix: the simulated cell under every fault of issue 8, each row checked.

Every scenario builds a small cell (a few items), injects one fault at a known press, runs the
real loop (runtime/cell.py) or the real daemon (runtime/daemon.py, in a subprocess for the
signal rows) and then audits the journal with the same promises for every row:

* exactly one ``final`` record per ``item`` record, no item number or piece id twice;
* no piece sorted on a guess: a ``sorted`` piece is in its own fabric's bin or in the reject bin;
* the gate executed exactly one move per sorted piece (pty gate rows: counted in the MCU sim);
* the daemon either carried on (retry, skipped frame) or latched a fault with a reason, and after
  the operator's clear the remaining pieces were sorted.

Which boundary each row exercises is in its ``where`` column: ``loop`` rows use the in-process
fakes (FakeArm, FakeGate, SimulatedCamera) because the row is about the loop's logic; ``ursim``
rows use the real ur_rtde client (IsolatedURArm) against the loopback UR simulator; ``pty gate``
rows use the real host driver against the MCU simulator on a pty; ``daemon`` rows run the real
daemon as a subprocess and signal it; ``journal`` rows damage the journal file or its write path.

This module is the matrix: the list of rows (``SCENARIOS``), the runner and the row's result.
The rig and the audit are in sim/fault_rig.py, the grey-level fake model in sim/fakes.py, and the
rows by boundary in sim/faults_camera.py, faults_arm.py, faults_gate.py, faults_journal.py,
faults_process.py, faults_startup.py and faults_inputs.py (issue 17's inputs).

The model is a grey-level fake (a pressed frame's mean grey level votes for one fabric), as in the
cell tests: the rows check the loop's promises, not a bundle's accuracy. Run it all with
``vs2t-edge reliability`` (sim/faults_cli.py), which writes docs/reliability.md.
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from vs2t_edge.sim.faults_arm import (
    arm_connection_lost_fake,
    connection_drop_ursim,
    emergency_stop_fake,
    emergency_stop_ursim,
    force_never_reached,
    force_never_reached_ursim,
    force_not_reached_once,
    item_over_time_budget,
    protective_stop_fake,
    protective_stop_ursim,
)
from vs2t_edge.sim.faults_camera import (
    all_frames_black,
    camera_frozen,
    camera_unplugged_and_back,
    camera_unplugged_for_good,
    corrupt_frames,
    replay_camera_bad_frames,
)
from vs2t_edge.sim.faults_gate import (
    ack_contradicts_sort,
    ack_lost_past_timeout,
    dropped_ack,
    dropped_request,
    duplicated_frames,
    fault_flood,
    gate_jam,
    gate_reboot,
    serial_noise,
    slow_ack_within_timeout,
)
from vs2t_edge.sim.faults_journal import disk_full, disk_full_restart, fsync_eio, power_loss_mid_write
from vs2t_edge.sim.faults_process import daemon_child, daemon_sigkill, daemon_sigterm, gate_latched_at_start
from vs2t_edge.sim.faults_startup import bundle_manifest_edited, bundle_tampered, disk_full_at_start, hostile_configs


# --- the matrix -----------------------------------------------------------------------------

@dataclass(frozen=True)
class Scenario:
    name: str
    where: str
    fault: str
    expect: str
    fn: Callable[[Path], tuple[str, list[str]]]
    slow: bool = False
    known_bug: str = ""  # non-empty: the row fails today because of this bug (owner named)


@dataclass
class Row:
    name: str
    where: str
    fault: str
    expect: str
    outcome: str = ""
    passed: bool = False
    seconds: float = 0.0
    problems: list[str] = field(default_factory=list)
    pending: str = ""  # non-empty: the row cannot run yet, and why
    known_bug: str = ""  # the scenario's known bug (a failing row then reads KNOWN BUG, not FAIL)

    @property
    def result(self) -> str:
        if self.passed:
            return "PASS" + (" (known bug fixed? drop known_bug)" if self.known_bug else "")
        if self.pending:
            return "pending"
        return "KNOWN BUG" if self.known_bug else "FAIL"

    @property
    def blocking(self) -> bool:
        """A failure the command must report with exit 1 (known bugs are listed, not blocking)."""
        return not (self.passed or self.pending or self.known_bug)


def _labels_row(w: Path):
    from vs2t_edge.sim import faults_labels  # operator labels' file faults

    return faults_labels.labels_file_faults(w)


def _inputs_row(name: str, w: Path):
    from vs2t_edge.sim import faults_inputs  # issue 17's input rows, kept in their own module

    return getattr(faults_inputs, name)(w)


SCENARIOS = [
    Scenario("camera_unplugged_and_back", "loop", "camera unplugged mid-press, back for the retry",
             "camera reopened, press retried once; that piece to reject (its reference predates the reopen), "
             "the rest sorted", camera_unplugged_and_back),
    Scenario("camera_unplugged_for_good", "loop", "camera unplugged mid-press and stays out",
             "retry fails -> fault latched, piece rejected; rest sorted after clear", camera_unplugged_for_good),
    Scenario("camera_frozen", "loop", "frozen camera (same frame repeated)",
             "camera fault latched, piece rejected; rest sorted after clear", camera_frozen),
    Scenario("corrupt_frames", "loop", "one black frame, one truncated frame",
             "refused by the frame guard, press retried after a reopen, never scored; those pieces to reject, "
             "the rest sorted", corrupt_frames),
    Scenario("replay_camera_bad_frames", "loop", "ReplayCamera: a corrupt and a missing frame file",
             "each refused naming the file, press retried on the next recorded frame, none served twice; "
             "those pieces to reject (camera reopened), the other sorted",
             replay_camera_bad_frames),
    Scenario("replay_camera_not_sensor_frames", "loop", "ReplayCamera: grey, RGBA, 16-bit, wrong-size, "
             "30000x30000 and FIFO frame files",
             "each refused naming the file and why, before decoding (size) or reading (FIFO); none scored; "
             "those pieces to reject (camera reopened), the good pieces between them sorted",
             lambda w: _inputs_row("replay_camera_not_sensor_frames", w)),
    Scenario("watchdog_hung_grab", "loop", "grab hangs to its timeout on a press and its retry (watchdog 1 s)",
             "camera fault latched before the watchdog: pings every < 0.5 s through the waits",
             lambda w: _inputs_row("watchdog_through_hung_grab", w)),
    Scenario("watchdog_gate_behind_heartbeat", "loop", "silent gate: a sort queued behind a heartbeat on the wire, "
             "then a failing gate-to-reject", "each wait within the bound the watchdog budget leases for it",
             lambda w: _inputs_row("watchdog_gate_behind_heartbeat", w)),
    Scenario("camera_covered", "loop", "black frames on a press and its retry",
             "camera fault latched naming 'all black', piece rejected; rest sorted", all_frames_black),
    Scenario("operator_labels_file", "loop", "operator labels: a label, the labels file a folder, back with junk and "
             "a withdrawal, a FIFO, back with a new label (between pieces)",
             "sorting goes on; wool pieces in wool's bin exactly while a label stands, else reject; denim and silk "
             "in theirs; each unreadable "
             "state journaled once; a restart rebuilds the same learned model", _labels_row),
    Scenario("protective_stop", "loop", "protective stop mid-press (FakeArm)",
             "fault latched, piece rejected, resumes after operator clear", protective_stop_fake),
    Scenario("emergency_stop", "loop", "emergency stop mid-press (FakeArm)",
             "fault latched, piece rejected, resumes after operator clear", emergency_stop_fake),
    Scenario("force_not_reached_once", "loop", "force not reached once", "press retried, all sorted",
             force_not_reached_once),
    Scenario("force_never_reached", "loop", "force not reached twice", "fault latched, piece rejected",
             force_never_reached),
    Scenario("arm_connection_lost", "loop", "link lost mid-press, FakeArm really disconnected",
             "reconnect on the next call, press redone from move_above (one retry), all sorted",
             arm_connection_lost_fake),
    Scenario("item_over_time_budget", "loop", "piece exceeds item_timeout_s", "fault latched, piece rejected",
             item_over_time_budget),
    Scenario("ursim_protective_stop", "ursim", "protective stop in the force descent (limit 8 N, UR simulator)",
             "fault latched, piece rejected, resumes after clear", protective_stop_ursim),
    Scenario("ursim_emergency_stop", "ursim", "emergency stop 0.12 s into a press (UR simulator)",
             "fault latched, piece rejected, resumes after release + clear", emergency_stop_ursim),
    Scenario("ursim_connection_drop", "ursim", "controller drops every connection in force mode, gel on the "
             "piece (refused 1 s)", "reconnect, the interrupted press redone, all sorted", connection_drop_ursim),
    Scenario("ursim_force_never_reached", "ursim", "nothing under the tool (force never reached)",
             "retried once, then fault; piece rejected", force_never_reached_ursim),
    Scenario("gate_serial_noise", "pty gate", "7 noise bytes before every MCU frame; 3 seeds, 200+ frames each",
             "every MCU frame parsed by the host (none lost); all sorted, one move each", serial_noise),
    Scenario("gate_dropped_ack", "pty gate", "MCU's ack lost", "retransmitted, sorted once", dropped_ack),
    Scenario("gate_dropped_request", "pty gate", "host's sort frame lost", "retransmitted, sorted once",
             dropped_request),
    Scenario("gate_duplicated_frames", "pty gate", "MCU frames sent twice", "duplicates ignored, sorted once",
             duplicated_frames),
    Scenario("gate_slow_ack", "pty gate", "acks 0.15 s late (timeout 0.5 s)", "all sorted", slow_ack_within_timeout),
    Scenario("gate_ack_lost", "pty gate", "acks 2 s late, past all retries (timeout 0.3 s)",
             "fault latched, piece recorded unknown_outcome with the bin it may be in; resumes after clear",
             ack_lost_past_timeout),
    Scenario("gate_jam", "pty gate", "flap jammed", "fault latched, piece recorded unknown_outcome with the bin asked "
             "and the last bin the gate reached; resumes once freed + cleared", gate_jam),
    Scenario("gate_reboot", "pty gate", "MCU reboots mid-run", "fault latched (boot id changed), cleared, resumes",
             gate_reboot),
    Scenario("gate_ack_contradicts", "pty gate", "ACK of a SORT reports another bin / jam / fail-safe / busy "
             "(right CRC, SEQ, type)", "never journalled sorted: fault latched, piece unknown_outcome with the bins "
             "asked and reported; resumes after clear", ack_contradicts_sort),
    Scenario("gate_fault_flood", "pty gate", "5000 FAULT frames (jam) sent mid-run, gate working",
             "host keeps the last 64 and counts the rest; all sorted", fault_flood),
    Scenario("daemon_sigterm", "daemon", "SIGTERM mid-item, restart",
             "item in hand aborted to reject, exit 0, restart carries on", daemon_sigterm),
    Scenario("daemon_sigkill", "daemon", "SIGKILL mid-item (after pre_sort / mid-press) x4, restart; the gate "
             "(MCU simulator, own process) survives, once past its heartbeat timeout",
             "open item resolved once: unknown_outcome (bin it may be in) / aborted; gate moves reconcile with the "
             "journal; a fail-safe gate latched at start and cleared", daemon_sigkill),
    Scenario("gate_latched_at_start", "daemon", "service down 1.5 s (past the gate's heartbeat timeout), restart",
             "fault latched before any piece is pressed, cleared by the operator, sorting resumes; moves reconcile",
             gate_latched_at_start),
    Scenario("power_loss_mid_write", "journal", "power lost mid pre_sort write (torn last line)",
             "torn tail cut and kept aside, open item aborted once", power_loss_mid_write),
    Scenario("disk_full", "journal", "ENOSPC mid pre_sort write (half lands; injected os.write)",
             "partial record cut back, fault latched naming the journal, gate not moved; clear refused while "
             "full, then the piece is aborted once and the rest sorted", disk_full),
    Scenario("disk_full_restart", "journal", "ENOSPC mid pre_sort write, service stopped while full",
             "cut back, no crash on stop; after space freed the restart resolves the piece", disk_full_restart),
    Scenario("disk_full_at_start", "journal", "ENOSPC on the journal's start record (disk full at service start)",
             "exit 2 in words, no READY, gate at reject, nothing sorted; starts once space is freed",
             disk_full_at_start),
    Scenario("fsync_eio", "journal", "EIO from fsync of a final record after the gate moved",
             "cut back, fault latched; the clear resolves the piece as unknown_outcome", fsync_eio),
    Scenario("restart_piece_ids", "daemon", "daemon restarted on its journal (run_daemon's own feed)",
             "piece ids go on (piece-000003 after piece-000002), none twice",
             lambda w: _inputs_row("restart_piece_ids", w)),
    Scenario("hostile_config", "config", "alias bomb, python tag, NaN, junk, 5 MB, a gate timeout the driver "
             "refuses, a piece wait past the watchdog, ...",
             "refused with exit 2 naming the file, no traceback", hostile_configs),
    Scenario("bundle_tampered", "bundle", "graph byte flipped / truncated, file missing, manifest truncated, "
             "a newer format (4), opset 11, probe mismatch",
             "refused before READY, exit 2, file named, journal never opened", bundle_tampered),
    Scenario("bundle_manifest_edited", "bundle", "manifest.json beta edited by hand, hashes untouched",
             "refused before READY, exit 2, manifest.json named", bundle_manifest_edited),
]


def run_scenario(sc: Scenario, workdir: Path | None = None) -> Row:
    row = Row(sc.name, sc.where, sc.fault, sc.expect, known_bug=sc.known_bug)
    own = workdir is None
    tmp = Path(tempfile.mkdtemp(prefix=f"fault-{sc.name}-")) if own else workdir
    t0 = time.monotonic()
    try:
        outcome, problems = sc.fn(tmp)
    except Exception as exc:  # noqa: BLE001 - a crashing scenario is a failed row, in words
        import traceback

        outcome, problems = f"scenario crashed: {exc!r}", [traceback.format_exc(limit=6)]
    row.seconds = time.monotonic() - t0
    row.outcome, row.problems = outcome, problems
    row.passed = not problems and not outcome.startswith("skipped")
    if outcome.startswith("skipped"):
        row.pending = outcome
    if own:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
    return row


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["daemon-child"]:
        return daemon_child(argv[1], gate_url=argv[2] if len(argv) > 2 else None)
    names = set(argv)
    rows = [run_scenario(s) for s in SCENARIOS if not names or s.name in names]
    for r in rows:
        print(f"{r.result} {r.name} ({r.seconds:.1f} s): "
              f"{r.outcome}" + ("".join(f"\n    {p}" for p in r.problems)))
    return 0 if not any(r.blocking for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())

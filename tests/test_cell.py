"""The cell loop with fake devices: decisions, bins, journal order, retries, latched faults."""

from __future__ import annotations

from pathlib import Path

import pytest

from cell_fakes import LOOP_CONFIG, FakeEvidence, FakeModel, ScriptedCamera
from vs2t_edge.sim.fake_devices import FakeArm
from vs2t_edge.runtime.cell import Cell, SceneSpec
from vs2t_edge.runtime.devices import GateError
from vs2t_edge.runtime.items import ContinuousFeed, Item
from vs2t_edge.sim.fake_devices import FakeGate
from vs2t_edge.runtime.journal import Journal, read_records
from vs2t_edge.runtime.notify import Notifier

CLASSES = ["denim", "silk", "wool"]
BINS = {"denim": 1, "silk": 2, "wool": 3}
VOTES = {50: "denim", 60: "silk", 70: "wool"}  # grey level of a pressed frame -> class it votes for


class OrderedGate(FakeGate):
    """A FakeGate that checks the pre-sort record is on disk when sort() is called."""

    def __init__(self, journal_path: Path):
        super().__init__()
        self.journal_path = journal_path
        self.on_disk_at_sort: list[bool] = []

    def sort(self, bin_index):
        recs = read_records(self.journal_path)
        self.on_disk_at_sort.append(bool(recs) and recs[-1]["type"] == "pre_sort" and recs[-1]["bin"] == bin_index)
        super().sort(bin_index)


def make_cell(tmp_path, script, *, max_presses=4, confidence=0.95, gate=None, arm=None, items=None,
              contact_check=None):
    arm = arm or FakeArm()
    arm.connect()
    camera = ScriptedCamera(arm, script)
    journal = Journal.open(tmp_path / "journal.jsonl")
    gate = gate or OrderedGate(tmp_path / "journal.jsonl")
    gate.connect()
    points = arm.config.grid_points_mm()
    scene = SceneSpec(bins=dict(BINS), reject_bin=0, points_mm=points[:20], max_presses=max_presses,
                      confidence=confidence, fault_file=tmp_path / "FAULT", wait_item_timeout_s=0.01)
    cell = Cell(camera=camera, arm=arm, gate=gate, model=FakeModel(VOTES, CLASSES), journal=journal,
                notifier=Notifier(address=""), scene=scene,
                evidence_factory=lambda: FakeEvidence(CLASSES, confidence, max_presses),
                items=items or ContinuousFeed(), sleep=lambda s: None, contact_check=contact_check)
    return cell, arm, camera, gate, journal


def finals(path):
    return [r for r in read_records(path) if r["type"] == "final"]


def test_confident_item_goes_to_its_bin_and_journal_precedes_the_gate(tmp_path):
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60, 60, 60])
    results = cell.run(max_items=1)
    assert [r.label for r in results] == ["silk"]
    assert gate.sorted == [BINS["silk"]]
    assert gate.on_disk_at_sort == [True]
    f = finals(journal.path)
    assert len(f) == 1 and f[0]["outcome"] == "sorted" and f[0]["bin"] == 2
    # stop rule: one press gives p = 1/(1+2e-3) = 0.91 < 0.95, two give 0.995: stop after two
    assert results[0].presses == 2
    assert arm.calls.count("press") == 2 and arm.calls.count("retract") == 2


def test_ambiguous_item_is_unknown_and_rejected(tmp_path):
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50, 60, 70, 100], max_presses=4, confidence=0.99)
    results = cell.run(max_items=1)
    assert results[0].label == "unknown" and results[0].bin == 0
    assert gate.sorted == [0]
    assert results[0].presses == 4


def test_off_scene_label_goes_to_reject(tmp_path):
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50, 50, 50])
    cell.scene.bins.pop("denim")  # denim is in the model but not in this scene
    results = cell.run(max_items=1)
    assert gate.sorted == [0] and results[0].bin == 0


class _GuardedCamera(ScriptedCamera):
    """The scripted camera behind the production frame guard (runtime/frame_guard.py), as every live,
    replay and simulated camera is: a black frame is the camera's fault, never the model's."""

    def __init__(self, arm, script):
        from vs2t_edge.runtime.frame_guard import FrameGuard

        super().__init__(arm, script)
        self.guard = FrameGuard("camera", None, frozen_after=10 ** 6)  # scripted frames repeat by design

    def grab(self):
        return self.guard.admit(super().grab().image)


class _ModelThatFailsOn(FakeModel):
    """A model whose output is not finite for frames of grey level ``bad`` (inference.py raises
    FrameError "model_output" then): the one bad frame the cell skips."""

    def __init__(self, bad):
        super().__init__(VOTES, CLASSES)
        self.bad = bad

    def score_press(self, frame):
        from vs2t_edge.runtime.preprocess import FrameError

        if int(round(float(frame[..., 0].mean()))) == self.bad:
            raise FrameError("model output not usable for this frame (non-finite logits)", "model_output")
        return super().score_press(frame)


def test_a_black_frame_is_a_camera_fault_retried_once_never_skipped(tmp_path):
    """The frame rule (docs/cell.md): black, white, saturated or wrong-size frames come from a
    camera in trouble - retried once (camera reopened, so that piece goes to reject), then a
    latched fault; the next piece is sorted. They are never skipped into a decision."""
    cell, arm, cam, gate, journal = make_cell(tmp_path, ["black", 70, 70, 70])
    cell.camera = _GuardedCamera(arm, ["black", 70, 70, 70])
    cell.camera.connect()
    results = cell.run(max_items=2)
    recs = read_records(journal.path)
    assert (results[0].label, results[0].stopped_by, results[0].skipped_frames) == ("unknown", "camera_reopened", 0)
    assert results[1].label == "wool" and results[1].skipped_frames == 0
    assert [r for r in recs if r["type"] == "retry"] and not [r for r in recs if r["type"] == "frame_skipped"]
    cell2, arm2, _, _, journal2 = make_cell(tmp_path / "twice", ["black", "black"])
    cell2.camera = _GuardedCamera(arm2, ["black", "black"])
    cell2.camera.connect()
    cell2.run(max_items=1)
    assert cell2.fault and "black" in cell2.fault


def test_a_frame_the_model_cannot_score_is_skipped_counted_and_never_routed(tmp_path):
    cell, arm, cam, gate, journal = make_cell(tmp_path, [13, 70, 70])
    cell.model = _ModelThatFailsOn(13)
    results = cell.run(max_items=1)
    assert results[0].label == "wool" and results[0].skipped_frames == 1
    recs = read_records(journal.path)
    assert [r["reason"] for r in recs if r["type"] == "frame_skipped"] == ["model_output"]
    assert cell.model.scored == 2  # the unusable press never reached the evidence


def test_camera_error_is_retried_once(tmp_path):
    # the retry reopens the camera; it works, but the piece's reference predates the reopen: the
    # piece goes to the reject bin (test_a_camera_reopened_mid_item_sends_the_piece_to_reject)
    cell, arm, cam, gate, journal = make_cell(tmp_path, ["error", 50, 50, 50])
    results = cell.run(max_items=2)
    assert (results[0].outcome, results[0].label, results[0].bin) == ("sorted", "unknown", 0)
    assert (results[1].outcome, results[1].label) == ("sorted", "denim")
    assert [r for r in read_records(journal.path) if r["type"] == "retry"]
    assert cell.fault is None


def test_press_failed_twice_latches_a_fault(tmp_path):
    arm = FakeArm(fail_next=["force_not_reached", "force_not_reached"])
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50, 50], arm=arm)
    results = cell.run(max_items=1)
    assert results[0].outcome == "rejected_fault" and results[0].bin == 0
    assert cell.fault and "failed twice" in cell.fault
    assert (tmp_path / "FAULT").exists()
    assert "stop" in arm.calls and gate.to_reject_calls >= 1
    assert gate.sorted == []  # a faulted item is not routed by sort(); the gate sits at reject
    assert "FAULT" in cell.notifier.status_line


def test_safety_stop_latches_and_nothing_moves_until_cleared(tmp_path):
    arm = FakeArm()
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50] * 10, arm=arm)
    arm.fail_next = ["protective_stop"]
    polls = {"n": 0}

    def stop_when():
        polls["n"] += 1
        return polls["n"] > 20

    cell.run(max_items=3, stop_when=stop_when)
    assert cell.fault and "safety stop" in cell.fault
    presses_while_faulted = arm.calls.count("press")
    cell.run(max_items=3, stop_when=lambda: True)  # still latched: no motion
    assert arm.calls.count("press") == presses_while_faulted
    # operator clears: the fault file goes, the loop clears gate and arm and carries on
    (tmp_path / "FAULT").unlink()
    results = cell.run(max_items=2)
    assert cell.fault is None and results[-1].outcome == "sorted"
    recs = read_records(journal.path)
    assert [r["type"] for r in recs].count("fault_cleared") == 1


def test_gate_jam_latches_fault_after_pre_sort(tmp_path):
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60, 60, 60])
    gate.jam_next_sort()
    results = cell.run(max_items=1)
    # the flap stuck on its way from reject to silk's bin: where the piece is, nobody knows
    assert results[0].outcome == "unknown_outcome" and finals(journal.path)[0]["maybe_bin"] == BINS["silk"]
    assert "reported_bin" not in finals(journal.path)[0]
    recs = read_records(journal.path)
    types = [r["type"] for r in recs]
    assert types.index("pre_sort") < types.index("fault") < types.index("final")
    assert len(finals(journal.path)) == 1


def test_gate_timeout_is_retried_once(tmp_path):
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60, 60, 60])
    gate.time_out_next(1)
    results = cell.run(max_items=1)
    assert results[0].outcome == "sorted" and gate.sorted == [2]


class AcksLostThenLatchedGate(OrderedGate):
    """The first SORT is executed but its acks are lost (a timeout); in that silence the gate's
    heartbeat timed out, so the retry is refused by a latched gate."""

    def sort(self, bin_index):
        if not self.sorted:
            super().sort(bin_index)  # the flap moved to the bin ...
            self.lose_heartbeat()  # ... then the host's silence latched the gate (flap back at reject)
            error = GateError("the gate did not answer SORT (acks lost)", device="gate", kind="timeout")
            error.retryable = True
            raise error
        super().sort(bin_index)


def test_a_sort_that_timed_out_stays_uncertain_when_its_retry_is_refused(tmp_path):
    """A SORT that timed out may have been executed (docs/protocol.md): the piece may be in its
    bin. Its retry then refused (a latched gate, a jam, a NAK) proves nothing about the first one,
    yet the item was recorded rejected_fault in the reject bin - no maybe_bin for the operator to
    check, the piece's true bin never looked at."""
    gate = AcksLostThenLatchedGate(tmp_path / "journal.jsonl")
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60, 60, 60], gate=gate)
    results = cell.run(max_items=1)
    assert gate.sorted == [BINS["silk"]]  # the flap went to silk's bin once
    f = finals(journal.path)
    assert len(f) == 1 and f[0]["outcome"] == "unknown_outcome" and f[0]["maybe_bin"] == BINS["silk"], f
    assert results[0].outcome == "unknown_outcome" and "check both" in f[0]["reason"]


class LinkLostAfterTheSortGate(OrderedGate):
    """The SORT went out and was executed; the link died before its ACK came back."""

    def sort(self, bin_index):
        super().sort(bin_index)
        error = GateError("reading from the gate failed: device disconnected", device="gate", kind="link")
        error.maybe_executed = True  # what runtime/gate.py passes on from the driver
        raise error


def test_a_link_lost_after_the_sort_went_out_is_an_unknown_outcome(tmp_path):
    gate = LinkLostAfterTheSortGate(tmp_path / "journal.jsonl")
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60, 60, 60], gate=gate)
    results = cell.run(max_items=1)
    f = finals(journal.path)
    assert len(f) == 1 and f[0]["outcome"] == "unknown_outcome" and f[0]["maybe_bin"] == BINS["silk"], f
    assert results[0].outcome == "unknown_outcome" and gate.sorted == [BINS["silk"]]


class FailingStopArm(FakeArm):
    def stop(self):
        raise RuntimeError("stop failed (injected)")


def test_fault_steps_are_each_guarded(tmp_path):
    arm = FailingStopArm(fail_next=["emergency_stop"])
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50] * 5, arm=arm)
    cell.run(max_items=1)
    fault = [r for r in read_records(journal.path) if r["type"] == "fault"][0]
    assert any("arm.stop failed" in s for s in fault["steps_failed"])
    assert gate.to_reject_calls >= 1  # the failing arm.stop did not skip the gate step
    assert (tmp_path / "FAULT").exists()


def test_stop_request_mid_item_aborts_to_reject(tmp_path):
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50, 60, 70, 50, 60, 70], confidence=0.999999)
    original = cell.model.score_press

    def score_and_stop(frame):
        cell.stop_event.set()  # SIGTERM arrives during the first press
        return original(frame)

    cell.model.score_press = score_and_stop
    cell.process_item(Item("x"))
    f = finals(journal.path)
    assert f[-1]["outcome"] == "aborted" and f[-1]["bin"] == 0
    assert gate.sorted == [] and gate.to_reject_calls >= 1


def test_restart_resolves_item_left_between_pre_sort_and_final(tmp_path):
    path = tmp_path / "journal.jsonl"
    j = Journal.open(path)
    j.append({"type": "item", "item": 7, "item_id": "p7"})
    j.append({"type": "pre_sort", "item": 7, "item_id": "p7", "label": "silk", "bin": 2})
    j.close()  # the process died before the gate's ack
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50, 50])
    resolved = cell.recover()
    assert len(resolved) == 1 and resolved[0]["outcome"] == "unknown_outcome" and resolved[0]["bin"] == 0
    assert resolved[0]["maybe_bin"] == 2  # the bin the gate may have moved to, for reconciling its moves
    cell.run(max_items=1)
    f = finals(path)
    assert [r["item"] for r in f] == [7, 8]  # exactly one final per item, numbering continues
    assert Journal.open(path).unresolved_items() == []


def test_fault_file_survives_restart(tmp_path):
    (tmp_path / "FAULT").write_text("gate jam\n")
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50, 50])
    cell.recover()
    cell.run(max_items=1, stop_when=lambda: True)
    assert cell.fault == "gate jam" and arm.calls.count("press") == 0


def test_restart_resolves_item_stopped_before_its_decision(tmp_path):
    path = tmp_path / "journal.jsonl"
    with Journal.open(path) as j:
        j.append({"type": "item", "item": 4, "item_id": "p4"})  # died while pressing
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50, 50])
    resolved = cell.recover()
    assert [(r["item"], r["outcome"], r["bin"]) for r in resolved] == [(4, "aborted", 0)]
    assert cell.recover() == []  # resolved once, not again


def test_journal_write_failure_latches_and_the_clear_resolves_the_item(tmp_path, monkeypatch):
    """A pre_sort record that cannot be written (disk full): the gate is not told, a fault is
    latched naming the journal; the operator's clear writes the open item's final record (aborted)
    and the loop carries on. No partial record is left in the file."""
    import errno

    import vs2t_edge.runtime.journal as jmod

    real_os = jmod.os

    class FullDisk:
        full = False

        def __getattr__(self, name):
            return getattr(real_os, name)

        def write(self, fd, data):
            if b'"type":"pre_sort"' in data and not self.full and not cleared["done"]:
                self.full = True
                real_os.write(fd, data[: len(data) // 2])  # half lands, then the disk is full
            if self.full:
                raise OSError(errno.ENOSPC, "No space left on device")
            return real_os.write(fd, data)

    cleared = {"done": False}
    disk = FullDisk()
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50, 50, 50, 50, 60, 60, 60, 60])
    monkeypatch.setattr(jmod, "os", disk)
    cell.run(max_items=1, stop_when=lambda: cell.fault is not None)
    assert cell.fault and "journal write failed" in cell.fault and "No space" in cell.fault
    assert gate.sorted == [] and "stop" in arm.calls  # nothing routed on a decision that is not on disk
    assert (tmp_path / "FAULT").exists() and cell.items_done == 0
    assert journal.path.read_bytes().endswith(b"\n")  # the half record was cut back
    # the operator clears while the disk is still full: refused, latched again
    (tmp_path / "FAULT").unlink()
    cell.run(max_items=1, stop_when=lambda: (tmp_path / "FAULT").exists())
    assert "could not clear" in cell.fault
    # space freed, cleared again: the open item gets its final record, the next one is sorted
    disk.full, cleared["done"] = False, True
    (tmp_path / "FAULT").unlink()
    results = cell.run(max_items=1)
    recs = read_records(journal.path)
    f = [r for r in recs if r["type"] == "final"]
    assert [(r["item"], r["outcome"]) for r in f] == [(1, "aborted"), (2, "sorted")] and f[0]["bin"] == 0
    # the note says what happened: the journal write failed, the process did not stop
    assert "journal write failed" in f[0]["note"] and "process stopped" not in f[0]["note"], f[0]["note"]
    assert results[-1].outcome == "sorted" and gate.sorted == [f[1]["bin"]] and f[1]["bin"] != 0
    assert jmod.Journal.open(journal.path).torn_bytes == 0


def test_a_camera_reopened_mid_item_sends_the_piece_to_reject(tmp_path):
    """A camera that vanished delivers nothing until it is reopened. Reopened mid-item, the sensor
    may expose differently than for the item's no-contact reference (taken before the reset), and
    every later press would be scored - and contact-checked - against that stale reference: the
    piece goes to the reject bin, no fault; the next piece takes a fresh reference and is sorted."""
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50, "unplugged", 50, 60, 60])
    results = cell.run(max_items=2)
    assert cell.fault is None and cam.connects == 1 and cam.connected  # reopened once, at the failure
    assert (results[0].label, results[0].bin, results[0].stopped_by) == ("unknown", 0, "camera_reopened")
    assert (results[1].label, results[1].outcome) == ("silk", "sorted")
    recs = read_records(journal.path)
    assert [r["kind"] for r in recs if r["type"] == "retry"] == ["unplugged"]
    pre = [r for r in recs if r["type"] == "pre_sort"][0]
    assert (pre["label"], pre["bin"], pre["stopped_by"], pre["presses"]) == ("unknown", 0, "camera_reopened", 1)
    assert gate.sorted == [0, 2]
    # the retried press still tests the camera (a second failure latches a fault, as before), but
    # its frame decides nothing: scored are the first piece's one press and the second's two
    assert arm.calls.count("press") == 3 + 2 and cell.model.scored == 1 + 2


def test_a_camera_reopened_mid_piece_on_pieces_in_a_row_latches_a_fault(tmp_path):
    """A camera that drops out on every press but reopens each time would send every piece to the
    reject bin without an alarm: the second piece in a row ended that way latches a fault (rejected,
    nothing lost); a piece pressed normally in between starts the count again."""
    from vs2t_edge.runtime.cell import STALE_PIECES_TO_FAULT

    assert STALE_PIECES_TO_FAULT == 3
    glitch = [50, "unplugged", 50]
    cell, arm, cam, gate, journal = make_cell(tmp_path, glitch * 2 + [60, 60] + glitch * 3)
    cell.run(max_items=6, stop_when=lambda: cell.fault is not None)
    assert cell.fault and "reopened mid-piece on 3 pieces in a row" in cell.fault
    f = [(r["item"], r["outcome"], r["bin"]) for r in read_records(journal.path) if r["type"] == "final"]
    assert f == [(1, "sorted", 0), (2, "sorted", 0), (3, "sorted", 2), (4, "sorted", 0), (5, "sorted", 0),
                 (6, "rejected_fault", 0)]
    assert (tmp_path / "FAULT").exists()


def test_a_camera_reopened_for_the_reference_frame_keeps_the_piece(tmp_path):
    """Reopened while the reference frame is being taken, the reference is the reopened camera's
    own: the piece is pressed and sorted as any other."""
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60, 60])
    cam.cable_out = cam.lost = True  # the reference grab finds the cable out; back on reopen
    results = cell.run(max_items=1)
    assert cell.fault is None and cam.connects == 1
    assert (results[0].label, results[0].outcome) == ("silk", "sorted")
    assert [r["step"] for r in read_records(journal.path) if r["type"] == "retry"] == ["reference frame"]


def test_camera_gone_for_good_latches_and_the_clear_reopens_it(tmp_path):
    cell, arm, cam, gate, journal = make_cell(tmp_path, [50, "unplugged"] + [60] * 6)
    cam.back_on_reconnect = False
    cell.run(max_items=1)
    assert "reopening the camera for the retry failed" in cell.fault and "unplugged" in cell.fault
    presses = arm.calls.count("press")
    assert presses == 2  # no second press into a camera that did not reopen
    # cleared while the cable is still out: the clear's reopen fails, the fault latches again
    (tmp_path / "FAULT").unlink()
    cell.run(max_items=2, stop_when=lambda: (tmp_path / "FAULT").exists())
    assert "could not clear" in cell.fault and "unplugged" in cell.fault
    assert arm.calls.count("press") == presses
    # plugged back in and cleared: the clear reopens it and the next piece needs no retry
    cam.back_on_reconnect = True
    (tmp_path / "FAULT").unlink()
    results = cell.run(max_items=2)
    assert cell.fault is None and results[-1].outcome == "sorted" and results[-1].label == "silk"
    recs = read_records(journal.path)
    assert [r["type"] for r in recs].count("retry") == 1 and cam.connected


REFERENCE = 100  # ScriptedCamera's gel-up frame: a pressed frame of 100 is the reference again


def test_press_frame_identical_to_the_reference_is_retried_then_latches_no_contact(tmp_path):
    """The gel never touched the piece: each press frame is the no-contact reference again. The
    press is retried once (journalled like any retry), then a fault naming 'no contact' latches;
    such a frame is never scored."""
    from vs2t_edge.runtime.contact import ContactCheck

    cell, arm, cam, gate, journal = make_cell(tmp_path, [REFERENCE, REFERENCE, 50, 50],
                                              contact_check=ContactCheck())
    results = cell.run(max_items=1)
    assert results[0].outcome == "rejected_fault" and results[0].bin == 0 and gate.sorted == []
    assert "no contact" in cell.fault and "failed twice" in cell.fault
    assert cell.model.scored == 0 and arm.calls.count("press") == 2
    recs = read_records(journal.path)
    assert [(r["kind"], r["step"].split(" at ")[0]) for r in recs if r["type"] == "retry"] == [("no_contact", "press 1")]
    fault = [r for r in recs if r["type"] == "fault"]
    assert len(fault) == 1 and "no contact" in fault[0]["reason"]
    assert cam.connects == 0  # not a camera fault: the camera is not reopened for it


def test_no_contact_once_is_retried_and_the_piece_sorted(tmp_path):
    from vs2t_edge.runtime.contact import ContactCheck

    cell, arm, cam, gate, journal = make_cell(tmp_path, [REFERENCE, 60, 60], contact_check=ContactCheck())
    results = cell.run(max_items=1)
    assert results[0].outcome == "sorted" and results[0].label == "silk" and cell.fault is None
    assert cell.model.scored == 2  # the untouched frame was never scored
    assert [r["kind"] for r in read_records(journal.path) if r["type"] == "retry"] == ["no_contact"]


def test_without_a_contact_check_the_loop_scores_an_untouched_frame(tmp_path):
    # what the daemon does today (it gives the Cell no contact check, docs/cell.md says why)
    cell, arm, cam, gate, journal = make_cell(tmp_path, [REFERENCE, 60, 60])
    results = cell.run(max_items=1)
    assert results[0].outcome == "sorted" and cell.model.scored == 3
    assert not [r for r in read_records(journal.path) if r["type"] == "retry"]


# --- an exception the loop has no rule for (issue 7 audit, item 1) -----------------------------

def test_model_runtime_error_latches_an_internal_fault_instead_of_escaping(tmp_path):
    """An onnxruntime RuntimeError from score_press used to escape Cell.run: the daemon re-raised,
    no FAULT file, systemd restarted the service and the cell sorted on with no operator."""
    logged: list[str] = []
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60] * 10)
    cell.log = logged.append
    original, n = cell.model.score_press, {"calls": 0}

    def flaky(frame):
        n["calls"] += 1
        if n["calls"] == 2:
            raise RuntimeError("[ONNXRuntimeError] : 6 : RUNTIME_EXCEPTION (injected)")
        return original(frame)

    cell.model.score_press = flaky
    results = cell.run(max_items=2, stop_when=lambda: cell.fault is not None and n["calls"] >= 2)
    assert [r.outcome for r in results] == ["rejected_fault"] and results[0].bin == 0
    assert "internal error: RuntimeError: [ONNXRuntimeError]" in cell.fault
    assert "RuntimeError" in (tmp_path / "FAULT").read_text()
    recs = read_records(journal.path)
    fault = [r for r in recs if r["type"] == "fault"]
    assert len(fault) == 1 and fault[0]["kind"] == "internal"
    assert [r["outcome"] for r in finals(journal.path)] == ["rejected_fault"]
    assert Journal.open(journal.path).unresolved_items() == []  # nothing lost
    # sensor lifted before the stop, then gate to reject; nothing sorted
    assert arm.calls[-2:] == ["retract", "stop"] and gate.to_reject_calls >= 1 and gate.sorted == []
    assert any("Traceback" in m and "flaky" in m for m in logged)  # the traceback is in the log
    # a restart refuses until the operator clears
    cell2, arm2, *_ = make_cell(tmp_path, [60] * 4)
    cell2.recover()
    cell2.run(max_items=1, stop_when=lambda: True)
    assert cell2.fault and "RuntimeError" in cell2.fault and arm2.calls.count("press") == 0
    (tmp_path / "FAULT").unlink()
    assert cell2.run(max_items=1)[-1].outcome == "sorted"


class DeadLinkGate(OrderedGate):
    """The gate's port went away between the pre-sort record and the SORT: NotConnectedError, a
    DeviceError the loop's gate rule (GateError) did not know."""

    def sort(self, bin_index):
        from vs2t_edge.runtime.devices import NotConnectedError

        super().sort(bin_index)  # the flap moved; the ack path then fails
        raise NotConnectedError("gate used while not connected", device="gate")


def test_not_connected_gate_after_the_sort_is_an_unknown_outcome(tmp_path):
    gate = DeadLinkGate(tmp_path / "journal.jsonl")
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60, 60, 60], gate=gate)
    results = cell.run(max_items=1)
    assert results[0].outcome == "unknown_outcome"
    f = finals(journal.path)
    assert len(f) == 1 and f[0]["outcome"] == "unknown_outcome" and f[0]["maybe_bin"] == BINS["silk"]
    assert f[0]["bin"] == 0 and "NotConnectedError" in f[0]["reason"] and "check both" in f[0]["reason"]
    assert (tmp_path / "FAULT").exists() and "stop" in arm.calls and gate.to_reject_calls >= 1


def test_an_exception_outside_an_item_latches_too(tmp_path):
    class BrokenFeed:
        def next_item(self, timeout_s):
            raise ValueError("feeder sent garbage (injected)")

    cell, arm, cam, gate, journal = make_cell(tmp_path, [60], items=BrokenFeed())
    cell.run(max_items=1, stop_when=lambda: cell.fault is not None)
    assert "internal error: ValueError: feeder sent garbage" in cell.fault
    assert (tmp_path / "FAULT").exists()


def test_an_error_repeating_every_turn_latches_once_not_in_a_tight_loop(tmp_path):
    """A notifier that fails on every turn latches one fault; the loop then waits instead of
    writing a fault record per turn (which would fill the disk in seconds)."""
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60], items=[])
    turns = []

    def broken_ping():
        turns.append(1)
        if len(turns) >= 40:
            cell.stop_event.set()  # a bound for the old behaviour, which never slept
        raise OSError("notify socket gone (injected)")

    def sleep(s):
        if len(turns) >= 20:
            cell.stop_event.set()  # the SIGTERM path: the loop's own checks come after the ping

    cell.notifier.ping_if_due = broken_ping
    cell.sleep = sleep
    cell.run()
    faults = [r for r in read_records(journal.path) if r["type"] == "fault"]
    assert len(turns) >= 20 and len(faults) == 1, (len(turns), faults)
    assert "internal error: OSError: notify socket gone" in faults[0]["reason"]


def test_keyboard_interrupt_still_ends_the_loop(tmp_path):
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60, 60])

    def interrupted(frame):
        raise KeyboardInterrupt

    cell.model.score_press = interrupted
    with pytest.raises(KeyboardInterrupt):
        cell.run(max_items=1)
    assert not (tmp_path / "FAULT").exists()


def test_piece_ids_go_on_across_daemon_restarts_on_one_journal(tmp_path):
    """Each run of the daemon used to start its pieces at piece-000001 again: after a restart the
    journal held two pieces of each id. The feed now goes on from the journal's next item."""
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.daemon import run_daemon

    (tmp_path / "cell.yaml").write_text(LOOP_CONFIG)
    cfg = load_config(tmp_path / "cell.yaml")
    for _ in range(2):  # two runs of the service on one journal
        arm = FakeArm(config=cfg.arm)
        assert run_daemon(cfg, model=FakeModel(VOTES, CLASSES), camera=ScriptedCamera(arm, [50] * 40), arm=arm,
                          gate=FakeGate(), evidence_factory=lambda: FakeEvidence(CLASSES, 0.95, 4), max_items=2,
                          install_signals=False, log=lambda m: None) == 0
    ids = [r["item_id"] for r in read_records(tmp_path / "j.jsonl") if r.get("type") == "final"]
    assert ids == ["piece-000001", "piece-000002", "piece-000003", "piece-000004"]


def test_frames_the_camera_read_past_as_stale_are_journaled_with_the_piece(tmp_path):
    """A UVC camera reads past frames its driver took before the grab (runtime/camera.py
    ``stale_dropped``); the piece's pre_sort record says how many, so a camera whose queue runs
    deep shows in the journal, not only as a fault once it gives up."""
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60, 60, 60, 60, 60, 60])
    cam.stale_dropped = 0
    grab, grabs = cam.grab, []

    def grab_reading_past():
        cam.stale_dropped += 2
        grabs.append(1)
        return grab()

    cam.grab = grab_reading_past
    cell.run(max_items=1)
    (pre,) = [r for r in read_records(journal.path) if r["type"] == "pre_sort"]
    assert grabs and pre["stale_frames_read_past"] == 2 * len(grabs)
    cell, arm, cam, gate, journal = make_cell(tmp_path / "fresh", [60, 60, 60])  # a camera that read past none
    cell.run(max_items=1)
    (pre,) = [r for r in read_records(journal.path) if r["type"] == "pre_sort"]
    assert "stale_frames_read_past" not in pre


def test_a_journal_write_failing_between_a_failed_press_and_its_retry_lifts_the_gel_first(tmp_path, monkeypatch):
    """'Force never reached' leaves the tool at depth; the retry's record cannot be written (disk
    full): the fault latches as any journal failure does, but with the gel lifted first, as every
    other fault after a failed press (Cell._lift_gel)."""
    from vs2t_edge.runtime.journal import JournalWriteError

    arm = FakeArm()
    arm.fail_next = ["force_not_reached"]
    cell, arm, _, gate, journal = make_cell(tmp_path, [60] * 4, arm=arm)
    real_append = journal.append

    def append(rec):
        if rec.get("type") == "retry":
            raise JournalWriteError("writing a retry record failed (No space left on device)", 28, True)
        return real_append(rec)
    monkeypatch.setattr(journal, "append", append)
    cell.run(max_items=1, stop_when=lambda: cell.fault is not None)
    assert cell.fault and "journal write failed" in cell.fault and gate.sorted == []
    after = arm.calls[arm.calls.index("press"):]
    assert after[:2] == ["press", "retract"], after  # lifted before the latch stopped the arm


@pytest.mark.parametrize("where", ["labels poll", "evidence factory"])
def test_an_exception_before_the_press_records_the_fault_on_the_piece(tmp_path, where):
    """An exception from the operator labels' poll or from the evidence factory (before the piece
    is pressed) used to escape the piece: its journal item stayed open until the operator's clear,
    which recorded it "aborted ... process stopped" - not what happened. The piece's final record
    now says the fault, written when it latched: nothing open, the next piece sorted after the clear."""
    cell, arm, cam, gate, journal = make_cell(tmp_path, [60] * 10)
    calls = {"n": 0}

    class Factory:
        def __call__(self):
            if where == "evidence factory" and calls["n"] == 0:
                calls["n"] += 1
                raise ValueError("evidence broken (injected)")
            return FakeEvidence(CLASSES, 0.95, 4)

        def poll(self, j):
            if where == "labels poll" and calls["n"] == 0:
                calls["n"] += 1
                raise ValueError("labels broken (injected)")
            return []

        def remember(self, item_id, ev):
            pass

        def journal_z_mean(self, ev):
            return None

    cell.evidence_factory = Factory()
    results = cell.run(max_items=1, stop_when=lambda: cell.fault is not None)
    assert [r.outcome for r in results] == ["rejected_fault"] and results[0].bin == 0
    assert cell.fault.startswith("item 1 (") and "internal error: ValueError" in cell.fault
    f = finals(journal.path)
    assert [(r["item"], r["outcome"], r["bin"]) for r in f] == [(1, "rejected_fault", 0)]
    assert "ValueError" in f[0]["reason"] and "process stopped" not in str(f[0])
    assert Journal.open(journal.path).unresolved_items() == []  # nothing left open
    assert gate.sorted == [] and arm.calls.count("press") == 0 and gate.to_reject_calls >= 1
    (tmp_path / "FAULT").unlink()
    assert cell.run(max_items=2)[-1].outcome == "sorted"
    assert [r["outcome"] for r in finals(journal.path)] == ["rejected_fault", "sorted"]

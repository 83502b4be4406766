"""A latched fault holds until an operator clears it, also when its fault file cannot be written
(runtime/fault_latch.py): the loop took a fault file that was never there for one the operator had
removed, and resumed on its own - a protective stop cleared by software, the next piece sorted."""

from __future__ import annotations

from cell_fakes import FakeEvidence, FakeModel, ScriptedCamera
from vs2t_edge.runtime.cell import Cell, SceneSpec
from vs2t_edge.runtime.items import ContinuousFeed
from vs2t_edge.runtime.journal import Journal, read_records
from vs2t_edge.runtime.notify import Notifier
from vs2t_edge.sim.fake_devices import FakeArm, FakeGate

CLASSES = ["denim", "silk", "wool"]
BINS = {"denim": 1, "silk": 2, "wool": 3}
VOTES = {50: "denim", 60: "silk", 70: "wool"}


def _cell(tmp_path, fault_file, arm=None):
    arm = arm or FakeArm()
    arm.connect()
    gate = FakeGate()
    gate.connect()
    journal = Journal.open(tmp_path / "journal.jsonl")
    scene = SceneSpec(bins=dict(BINS), reject_bin=0, points_mm=arm.config.grid_points_mm()[:20], max_presses=4,
                      confidence=0.95, fault_file=fault_file, wait_item_timeout_s=0.01)
    cell = Cell(camera=ScriptedCamera(arm, [60] * 40), arm=arm, gate=gate, model=FakeModel(VOTES, CLASSES),
                journal=journal, notifier=Notifier(address=""), scene=scene,
                evidence_factory=lambda: FakeEvidence(CLASSES, 0.95, 4), items=ContinuousFeed(), sleep=lambda s: None)
    return cell, arm, gate, journal


def _turns(n):
    polls = {"n": 0}

    def stop_when():
        polls["n"] += 1
        return polls["n"] > n

    return stop_when


def _latched_where_its_file_cannot_be_written(tmp_path, turns):
    """A protective stop latched while the fault file's folder is a file (as EROFS or a full disk
    would refuse it): (its folder, the fault file, and the cell's parts)."""
    state = tmp_path / "state"
    state.write_text("a file where the fault file's folder should be")
    fault_file = state / "FAULT"
    cell, arm, gate, journal = _cell(tmp_path, fault_file, FakeArm(fail_next=["protective_stop"]))
    cell.run(max_items=2, stop_when=_turns(turns))
    return state, fault_file, cell, arm, gate, journal


def test_a_fault_whose_file_cannot_be_written_stays_latched_until_the_operator_clears_it(tmp_path):
    state, fault_file, cell, arm, gate, journal = _latched_where_its_file_cannot_be_written(tmp_path, 30)
    recs = read_records(journal.path)
    fault = [r for r in recs if r["type"] == "fault"]
    assert len(fault) == 1 and fault[0]["kind"] == "protective_stop"
    assert any(s.startswith("fault file failed") for s in fault[0]["steps_failed"])  # said in the record
    assert not any(r["type"] == "fault_cleared" for r in recs) and gate.sorted == [] and cell.fault
    # a restart while the file is still unwritable: the journal's fault latches again, nothing moves
    journal.close()
    cell, arm, gate, journal = _cell(tmp_path, fault_file)
    cell.recover()
    cell.run(max_items=2, stop_when=_turns(10))
    assert cell.fault == fault[0]["reason"] and arm.calls.count("press") == 0 and gate.sorted == []
    # the folder comes back: the file is written at last, and still nothing moves until it is removed
    state.unlink()
    state.mkdir()
    cell.run(max_items=2, stop_when=_turns(10))
    assert fault_file.read_text().strip() == fault[0]["reason"] and arm.calls.count("press") == 0
    fault_file.unlink()  # the operator's clear (`vs2t-edge run --clear-fault`)
    results = cell.run(max_items=1)
    assert cell.fault is None and results[-1].outcome == "sorted" and gate.sorted == [BINS["silk"]]
    assert [r["type"] for r in read_records(journal.path)].count("fault_cleared") == 1


def test_a_restart_after_the_operators_clear_starts_clean(tmp_path):
    """The fault file was written and the operator removed it while the service was down: a clear."""
    cell, arm, gate, journal = _cell(tmp_path, tmp_path / "FAULT", FakeArm(fail_next=["protective_stop"]))
    cell.run(max_items=1, stop_when=_turns(5))
    assert cell.fault and (tmp_path / "FAULT").exists()
    journal.close()
    (tmp_path / "FAULT").unlink()
    cell, arm, gate, journal = _cell(tmp_path, tmp_path / "FAULT")
    cell.recover()
    assert cell.fault is None
    assert cell.run(max_items=1)[-1].outcome == "sorted"


def _latched_with_its_file_unwritable(tmp_path):
    state, fault_file, cell, arm, gate, journal = _latched_where_its_file_cannot_be_written(tmp_path, 10)
    assert cell.fault and not fault_file.exists()
    state.unlink()
    state.mkdir()  # the folder comes back
    return cell, journal, fault_file


def test_a_fault_file_the_retry_wrote_and_the_operator_removed_while_stopped_is_a_clear(tmp_path):
    """The loop's retry wrote the fault file at last, the service stopped, the operator removed the
    file (`--clear-fault`): the journal's only fault record said the file was never written, so the
    next start latched the fault again and wrote the file anew - the operator's clear ignored."""
    cell, journal, fault_file = _latched_with_its_file_unwritable(tmp_path)
    cell.run(max_items=2, stop_when=_turns(5))
    assert fault_file.exists() and cell.fault
    journal.close()
    fault_file.unlink()  # the operator's clear while the service is stopped
    cell, arm, gate, journal = _cell(tmp_path, fault_file)
    cell.recover()
    assert cell.fault is None and not fault_file.exists(), f"cleared, yet latched again: {cell.fault}"
    assert cell.run(max_items=1)[-1].outcome == "sorted"
    fault = [r for r in read_records(journal.path) if r["type"] == "fault"]
    assert [r["kind"] for r in fault] == ["protective_stop", "file_written"] and fault[1]["steps_failed"] == []
    assert fault[1]["reason"] == fault[0]["reason"] and fault[1]["fault_file"] == str(fault_file)


def test_a_late_fault_file_whose_record_the_journal_refuses_is_not_written_back_behind_the_operator(tmp_path):
    """The retry wrote the fault file at last but the journal refused its record: the file stays
    counted as written and the log says the journal is why a clear will fail. Removing it is then the
    operator's clear, whose own record fails and latches the fault again saying why - it used to be
    written back every turn with no word in the log."""
    cell, journal, fault_file = _latched_with_its_file_unwritable(tmp_path)
    logs = []
    cell.log = logs.append
    journal._broken = "a failed write could not be cut back (simulated)"  # appends refused from here
    cell.run(max_items=2, stop_when=_turns(3))
    assert fault_file.exists() and cell.fault
    assert any("written at last, but journal failed" in m and "simulated" in m for m in logs), logs
    fault_file.unlink()  # the operator's clear
    logs.clear()
    cell.run(max_items=2, stop_when=_turns(3))
    assert cell.fault and "could not clear the fault" in cell.fault and "simulated" in cell.fault, cell.fault
    assert any("could not clear the fault" in m for m in logs), logs


def test_a_fault_file_a_restart_wrote_and_the_operator_removed_while_stopped_is_a_clear(tmp_path):
    """The same with the file written by a restart that found the journal's fault never written."""
    cell, journal, fault_file = _latched_with_its_file_unwritable(tmp_path)
    journal.close()
    cell, arm, gate, journal = _cell(tmp_path, fault_file)
    cell.recover()
    assert cell.fault and fault_file.exists()
    journal.close()
    fault_file.unlink()
    cell, arm, gate, journal = _cell(tmp_path, fault_file)
    cell.recover()
    assert cell.fault is None, f"cleared, yet latched again: {cell.fault}"
    assert [r["kind"] for r in read_records(journal.path) if r["type"] == "fault"] == ["protective_stop", "restored"]

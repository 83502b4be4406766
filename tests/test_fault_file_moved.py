"""A latched fault outlives a restart whose config names another fault file (runtime/fault_latch.py
``recover``): only a fault file that was there and is gone is the operator's clear."""

from __future__ import annotations

from test_fault_latch import _cell, _turns
from vs2t_edge.sim.fake_devices import FakeArm


def test_a_restart_with_the_fault_file_moved_keeps_the_fault_latched(tmp_path):
    """The service latched a fault (its file at FAULT beside the journal); the operator, before
    any clear, restarts it on a config whose fault_file names another place (a new state folder):
    no file there, so the restart took the fault for cleared and sorted the next piece."""
    cell, arm, gate, journal = _cell(tmp_path, tmp_path / "FAULT", FakeArm(fail_next=["protective_stop"]))
    cell.run(max_items=1, stop_when=_turns(5))
    assert cell.fault and (tmp_path / "FAULT").exists()
    journal.close()
    (tmp_path / "run").mkdir()
    cell, arm, gate, journal = _cell(tmp_path, tmp_path / "run" / "FAULT")
    cell.recover()
    cell.run(max_items=1, stop_when=_turns(10))
    assert cell.fault is not None and gate.sorted == [], (
        f"the fault latched under {tmp_path / 'FAULT'} was dropped: the cell sorted into {gate.sorted}")
    assert (tmp_path / "run" / "FAULT").exists()  # where this config's operator clears it
    journal.close()
    # cleared there while the service is stopped (what `vs2t-edge run --clear-fault` does): the next
    # start is clean, though the old file is still there
    (tmp_path / "run" / "FAULT").unlink()
    cell, arm, gate, journal = _cell(tmp_path, tmp_path / "run" / "FAULT")
    cell.recover()
    assert cell.fault is None and (tmp_path / "FAULT").exists()
    cell.run(max_items=1)
    assert gate.sorted, "a fault cleared at the config's fault file latched again from the old one"

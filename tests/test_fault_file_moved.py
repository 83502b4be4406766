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


def _clear_fault_on(journal_path, fault_file, capsys) -> tuple[int, str]:
    """`vs2t-edge run --clear-fault` on a config naming ``journal_path`` and ``fault_file``."""
    from types import SimpleNamespace

    from vs2t_edge.runtime.daemon import clear_fault

    rc = clear_fault(SimpleNamespace(journal=journal_path, fault_file=fault_file))
    return rc, capsys.readouterr().out


def test_clear_fault_finds_a_fault_latched_under_an_earlier_configs_fault_file(tmp_path, capsys):
    """Latched under FAULT, the config then moved its fault_file to run/FAULT, the service stopped:
    `--clear-fault` read only run/FAULT and said "no latched fault", and the next start latched
    again from the journal's record naming FAULT - the operator was told wrong."""
    cell, arm, gate, journal = _cell(tmp_path, tmp_path / "FAULT", FakeArm(fail_next=["protective_stop"]))
    cell.run(max_items=1, stop_when=_turns(5))
    assert cell.fault and (tmp_path / "FAULT").exists()
    journal.close()
    (tmp_path / "run").mkdir()
    rc, out = _clear_fault_on(journal.path, tmp_path / "run" / "FAULT", capsys)
    assert "no latched fault" not in out and str(tmp_path / "FAULT") in out, out
    assert rc == 0 and not (tmp_path / "FAULT").exists()
    cell, arm, gate, journal = _cell(tmp_path, tmp_path / "run" / "FAULT")
    cell.recover()
    assert cell.fault is None, f"cleared, yet the next start latched again: {cell.fault}"
    cell.run(max_items=1)
    assert gate.sorted
    journal.close()


def test_clear_fault_says_where_a_fault_whose_file_was_never_written_is(tmp_path, capsys):
    """The journal's fault record says its file could not be written: no file to remove, and the
    next start restores the fault. `--clear-fault` must not say "no latched fault"."""
    state = tmp_path / "state"
    state.write_text("a file where the fault file's folder should be")
    cell, arm, gate, journal = _cell(tmp_path, state / "FAULT", FakeArm(fail_next=["protective_stop"]))
    cell.run(max_items=1, stop_when=_turns(5))
    assert cell.fault
    journal.close()
    rc, out = _clear_fault_on(journal.path, state / "FAULT", capsys)
    assert "no latched fault" not in out and "never written" in out and str(journal.path) in out, out
    assert rc != 0

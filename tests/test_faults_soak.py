"""Short soak-style checks (the long soak is `python -m vs2t_edge.sim.soak`)."""

from __future__ import annotations

import pytest

from vs2t_edge.sim import faults


def run_items(tmp_path, n):
    rig = faults.build_rig(tmp_path, [faults.TRUTHS[i % 4] for i in range(n)])
    faults.run_rig(rig)
    return rig


def test_many_items_one_final_each(tmp_path):
    rig = run_items(tmp_path, 120)
    a = faults.audit(rig.journal_path, {it.id: it.truth for it in rig.pieces.items})
    assert not a["problems"] and len(a["finals"]) == 120


@pytest.mark.xfail(strict=True, reason="BUG (runtime/journal.py, runtime/cell.py): Journal.records keeps every "
                   "record and Cell.results every item in memory, so a daemon's RSS grows with uptime "
                   "(soak: ~1.6 MiB per 1000 presses)")
def test_in_memory_state_is_bounded(tmp_path):
    rig = run_items(tmp_path, 300)
    assert len(rig.cell.journal.records) < 200 and len(rig.cell.results) < 200

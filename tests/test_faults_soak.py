"""Short soak-style checks (the long soak is `python -m vs2t_edge.sim.soak`)."""

from __future__ import annotations

from vs2t_edge.sim import faults


def run_items(tmp_path, n):
    rig = faults.build_rig(tmp_path, [faults.TRUTHS[i % 4] for i in range(n)])
    faults.run_rig(rig)
    return rig


def test_many_items_one_final_each(tmp_path):
    rig = run_items(tmp_path, 120)
    a = faults.audit(rig.journal_path, {it.id: it.truth for it in rig.pieces.items})
    assert not a["problems"] and len(a["finals"]) == 120


def test_in_memory_state_is_bounded(tmp_path):
    # Journal.records and Cell.results used to keep everything (daemon RSS grew ~1.6 MiB per 1000
    # presses): now bounded windows plus counters over the whole run, the file has the rest.
    seen = []
    rig = faults.build_rig(tmp_path, [faults.TRUTHS[i % 4] for i in range(300)])
    rig.cell.on_item = seen.append
    faults.run_rig(rig)
    assert len(rig.cell.journal.records) < 200 and len(rig.cell.results) < 200
    assert rig.cell.items_done == 300 == len(seen) == sum(rig.cell.outcomes.values())
    assert [r.item.id for r in rig.cell.results] == [r.item.id for r in seen[-len(rig.cell.results):]]
    j = rig.cell.journal
    assert j.counts["final"] == 300 and j.next_item_number() == 301 and not j.unresolved_items()

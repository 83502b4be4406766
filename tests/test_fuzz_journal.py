"""Fuzz the journal reader: any bytes on disk (power loss, disk errors) give a journal or a
JournalError naming the record, never another exception; a torn tail never loses a good record."""

from __future__ import annotations

import tempfile
from pathlib import Path

from hypothesis import example, given, settings
from hypothesis import strategies as st

from vs2t_edge.runtime.journal import Journal, JournalError, _encode


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=400))
def test_any_bytes_open_or_are_refused(data):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "j.jsonl"
        p.write_bytes(data)
        try:
            j = Journal.open(p)
        except JournalError as exc:
            assert "j.jsonl" in str(exc)
            return
        j.append({"type": "start"})
        j.close()
        assert Journal.open(p).records[-1] == {"type": "start"}


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, 10**6), min_size=1, max_size=6), st.data())
def test_cut_anywhere_in_the_last_record_keeps_every_earlier_one(items, data):
    lines = [_encode({"type": "final", "item": n}) for n in items]
    cut = data.draw(st.integers(0, len(lines[-1]) - 1))
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "j.jsonl"
        p.write_bytes(b"".join(lines[:-1]) + lines[-1][:cut])
        j = Journal.open(p)
        assert [r["item"] for r in j.records] == items[:-1]
        assert j.torn_bytes == cut
        j.close()


@settings(max_examples=50, deadline=None)
@given(st.lists(st.fixed_dictionaries({"type": st.sampled_from(["item", "pre_sort", "final", "fault",
                                                                  "fault_cleared", "x"])},
                                      optional={"item": st.one_of(st.integers(-5, 50), st.text(max_size=3),
                                                                  st.none(), st.lists(st.integers(), max_size=2)),
                                                "outcome": st.text(max_size=3)}), max_size=40))
@example(recs=[{"type": "item", "item": -1}])  # only negative numbers: the next one is still 1 (found by CI)
def test_any_valid_records_give_the_same_state_as_the_full_history(recs):
    """The bounded in-memory state (open items, next number, latched fault) equals what the whole
    history says, however odd the records (hand-edited journals), both after appends and a reopen."""
    import json

    def canon(rs):
        return sorted(json.dumps(r, sort_keys=True) for r in rs)

    def expected(rs):
        nums = [r["item"] for r in rs if isinstance(r.get("item"), int) and not isinstance(r.get("item"), bool)]
        fault = None
        for r in rs:
            fault = r if r["type"] == "fault" else None if r["type"] == "fault_cleared" else fault
        last_final = {}
        for i, r in enumerate(rs):
            if r["type"] == "final":
                last_final[json.dumps(r.get("item"))] = i
        open_ = {}
        for i, r in enumerate(rs):
            k = json.dumps(r.get("item"))
            if r["type"] in ("item", "pre_sort") and i > last_final.get(k, -1):
                if r["type"] == "pre_sort" or k not in open_:
                    open_[k] = r
        return canon(open_.values()), max([0, *nums]) + 1, fault  # numbering starts at 1 whatever a hand edit wrote

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "j.jsonl"
        with Journal.open(p) as j:
            for r in recs:
                j.append(r)
            live = (canon(j.unresolved_items()), j.next_item_number(), j.latched_fault())
        with Journal.open(p) as j2:
            reopened = (canon(j2.unresolved_items()), j2.next_item_number(), j2.latched_fault())
    assert live == reopened == expected(recs)

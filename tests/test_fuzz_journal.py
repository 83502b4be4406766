"""Fuzz the journal reader: any bytes on disk (power loss, disk errors) give a journal or a
JournalError naming the record, never another exception; a torn tail never loses a good record."""

from __future__ import annotations

import tempfile
from pathlib import Path

from hypothesis import given, settings
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

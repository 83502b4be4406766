"""The journal: durable appends, a torn last record detected and cut on open, nothing else lost."""

from __future__ import annotations

import pytest

from vs2t_edge.runtime.journal import Journal, JournalError, read_records


def test_append_survives_reopen(tmp_path):
    p = tmp_path / "j.jsonl"
    with Journal.open(p) as j:
        j.append({"type": "start"})
        j.append({"type": "final", "item": 1, "bin": 2})
    j2 = Journal.open(p)
    assert [r["type"] for r in j2.records] == ["start", "final"] and j2.torn_bytes == 0
    assert j2.next_item_number() == 2


@pytest.mark.parametrize("tail", [b'{"crc":1,"rec":{"type":"fi', b'{"crc":123,"rec":{"type":"final"}}\n', b"\x00\x00"])
def test_torn_or_corrupt_last_record_is_cut_and_kept_aside(tmp_path, tail):
    p = tmp_path / "j.jsonl"
    with Journal.open(p) as j:
        j.append({"type": "pre_sort", "item": 1, "bin": 3})
    good = p.read_bytes()
    with open(p, "ab") as f:
        f.write(tail)  # a power cut in the middle of the next write (or a flipped byte)
    j = Journal.open(p)
    assert j.torn_bytes == len(tail) and len(j.records) == 1
    assert p.read_bytes() == good
    assert (tmp_path / "j.jsonl.torn").read_bytes() == tail
    j.append({"type": "final", "item": 1, "bin": 0})
    j.close()
    assert [r["type"] for r in read_records(p)] == ["pre_sort", "final"]


def test_corruption_in_the_middle_is_refused(tmp_path):
    p = tmp_path / "j.jsonl"
    with Journal.open(p) as j:
        for i in range(3):
            j.append({"type": "final", "item": i})
    lines = p.read_bytes().split(b"\n")
    lines[1] = lines[1].replace(b'"item":1', b'"item":9')  # CRC no longer matches
    p.write_bytes(b"\n".join(lines))
    with pytest.raises(JournalError, match="record 2 .* corrupt"):
        Journal.open(p)


def test_unresolved_and_latched_fault_queries(tmp_path):
    with Journal.open(tmp_path / "j.jsonl") as j:
        j.append({"type": "pre_sort", "item": 1})
        j.append({"type": "final", "item": 1})
        j.append({"type": "pre_sort", "item": 2})
        j.append({"type": "fault", "reason": "jam"})
        j.append({"type": "item", "item": 3})
        assert [(r["item"], r["type"]) for r in j.unresolved_items()] == [(2, "pre_sort"), (3, "item")]
        assert j.latched_fault()["reason"] == "jam"
        j.append({"type": "fault_cleared"})
        assert j.latched_fault() is None


def test_append_fsyncs(tmp_path, monkeypatch):
    import os

    calls = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (calls.append(fd), real(fd)))
    j = Journal.open(tmp_path / "j.jsonl")
    n = len(calls)
    j.append({"type": "x"})
    assert len(calls) == n + 1
    j.close()

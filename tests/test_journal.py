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
    with pytest.raises(JournalError, match="line 2 .* corrupt"):
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


def test_memory_is_bounded_and_state_comes_from_the_file(tmp_path):
    from vs2t_edge.runtime.journal import RECENT_RECORDS

    p = tmp_path / "j.jsonl"
    with Journal.open(p) as j:
        for n in range(1, 401):
            j.append({"type": "item", "item": n})
            j.append({"type": "final", "item": n, "outcome": "sorted" if n % 4 else "aborted", "bin": 1})
        j.append({"type": "fault", "reason": "jam"})
        j.append({"type": "item", "item": 401})
        assert len(j.records) == RECENT_RECORDS < 802
    j = Journal.open(p)  # a restart: the same answers from one streaming pass, memory still bounded
    assert len(j.records) == RECENT_RECORDS and j.records[-1] == {"type": "item", "item": 401}
    assert j.next_item_number() == 402 and [r["item"] for r in j.unresolved_items()] == [401]
    assert j.latched_fault()["reason"] == "jam"
    assert j.counts["final"] == 400 and j.outcomes == {"sorted": 300, "aborted": 100}
    assert sum(1 for _ in j.items()) == 400  # whole-history queries stream the file
    j.close()


class _FailingOs:
    """The journal module's view of ``os``: a write that lands half the bytes then fails, or a
    failing fsync (what a full or dying disk does)."""

    def __init__(self, fail: str, err: int):
        import os

        self.os, self.fail, self.err, self.armed = os, fail, err, True

    def __getattr__(self, name):
        return getattr(self.os, name)

    def write(self, fd, data):
        if self.armed and self.fail == "write":
            self.armed = False
            self.os.write(fd, data[: len(data) // 2])
            raise OSError(self.err, self.os.strerror(self.err))
        return self.os.write(fd, data)

    def fsync(self, fd):
        if self.armed and self.fail == "fsync":
            self.armed = False
            raise OSError(self.err, self.os.strerror(self.err))
        return self.os.fsync(fd)


@pytest.mark.parametrize("fail,err", [("write", 28), ("write", 5), ("fsync", 5)])  # ENOSPC, EIO
def test_failed_append_is_cut_back_and_raises_in_words(tmp_path, monkeypatch, fail, err):
    import os

    import vs2t_edge.runtime.journal as jmod
    from vs2t_edge.runtime.journal import JournalWriteError

    p = tmp_path / "j.jsonl"
    j = Journal.open(p)
    j.append({"type": "item", "item": 1})
    good = p.read_bytes()
    monkeypatch.setattr(jmod, "os", _FailingOs(fail, err))
    with pytest.raises(JournalWriteError) as exc:
        j.append({"type": "pre_sort", "item": 1, "bin": 2})
    assert exc.value.cut_back and exc.value.errno == err
    assert "pre_sort" in str(exc.value) and os.strerror(err) in str(exc.value) and str(p) in str(exc.value)
    assert p.read_bytes() == good  # no partial record left behind
    assert [r["type"] for r in j.unresolved_items()] == ["item"]  # the failed record did not count
    j.append({"type": "final", "item": 1, "bin": 0})  # the disk is back: appends carry on cleanly
    j.close()
    j2 = Journal.open(p)
    assert j2.torn_bytes == 0 and [r["type"] for r in j2.records] == ["item", "final"]


def test_a_write_that_cannot_be_cut_back_stops_all_later_appends(tmp_path, monkeypatch):
    import vs2t_edge.runtime.journal as jmod
    from vs2t_edge.runtime.journal import JournalWriteError

    p = tmp_path / "j.jsonl"
    j = Journal.open(p)
    j.append({"type": "start"})
    failing = _FailingOs("write", 5)

    def no_truncate(fd, n):
        raise OSError(5, "Input/output error")

    failing.ftruncate = no_truncate
    monkeypatch.setattr(jmod, "os", failing)
    with pytest.raises(JournalWriteError, match="could not be cut back") as exc:
        j.append({"type": "item", "item": 1})
    assert not exc.value.cut_back
    with pytest.raises(JournalWriteError, match="nothing more is written"):
        j.append({"type": "stop"})  # would land after the half line and be lost with it
    monkeypatch.undo()
    j.close()
    j2 = Journal.open(p)  # the restart cuts the torn half line; nothing before it is lost
    assert j2.torn_bytes > 0 and [r["type"] for r in j2.records] == ["start"]


@pytest.mark.parametrize("mode,want", [(0o666, 0o640), (0o604, 0o600), (0o777, 0o640)])
def test_an_existing_too_open_journal_is_tightened_and_logged(tmp_path, mode, want):
    """Created files get 0640 whatever the umask; one that already exists (a hand copy, an old
    version, a restore) used to be used as it was: 0666 let anyone rewrite the record."""
    import stat

    p = tmp_path / "j.jsonl"
    with Journal.open(p) as j:
        j.append({"type": "start"})
    p.chmod(mode)
    said: list[str] = []
    j = Journal.open(p, log=said.append)
    j.close()
    assert stat.S_IMODE(p.stat().st_mode) == want
    assert j.mode_tightened_from == mode
    assert len(said) == 1 and f"{mode:04o}" in said[0] and f"{want:04o}" in said[0] and str(p) in said[0]
    said.clear()
    Journal.open(p, log=said.append).close()  # already tight: nothing to say, nothing changed
    assert said == [] and stat.S_IMODE(p.stat().st_mode) == want


def test_a_tight_journal_is_left_as_it_is(tmp_path):
    import stat

    p = tmp_path / "j.jsonl"
    Journal.open(p).close()
    p.chmod(0o600)  # tighter than 0640: never loosened
    said: list[str] = []
    j = Journal.open(p, log=said.append)
    j.close()
    assert stat.S_IMODE(p.stat().st_mode) == 0o600 and said == [] and j.mode_tightened_from is None


def test_a_too_open_journal_that_cannot_be_tightened_is_refused(tmp_path, monkeypatch):
    import os

    p = tmp_path / "j.jsonl"
    Journal.open(p).close()
    p.chmod(0o666)

    def eperm(fd, mode):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "fchmod", eperm)  # another user's file: only its owner may chmod it
    with pytest.raises(JournalError, match=r"mode 0666 .*cannot be tightened.*chmod 640"):
        Journal.open(p)


def test_an_existing_too_open_torn_file_is_tightened(tmp_path):
    import stat

    p = tmp_path / "j.jsonl"
    with Journal.open(p) as j:
        j.append({"type": "start"})
    torn = tmp_path / "j.jsonl.torn"
    torn.write_bytes(b"old")
    torn.chmod(0o666)
    with open(p, "ab") as f:
        f.write(b'{"crc":1,"rec":{"ty')
    Journal.open(p).close()
    assert stat.S_IMODE(torn.stat().st_mode) == 0o640 and torn.read_bytes().startswith(b"old")


def _three_sessions(p):
    with Journal.open(p) as j:
        for s in ("a", "b", "c"):
            j.append({"type": "start", "manifest_sha256": s})
            j.append({"type": "pre_sort", "item_id": f"piece-{s}"})
    return p.read_bytes().split(b"\n")


def test_a_corrupt_middle_line_is_said_once_naming_the_file_and_line(tmp_path, capsys):
    """Reading a journal (`label`, `--clear-fault`, replay, tools) skipped a corrupt line in the
    middle without a word: were it a session's start record, that session's pieces would read as
    the previous session's. The reader says it on stderr (the service's log) once per line; the
    start itself refuses such a journal (test_corruption_in_the_middle_is_refused)."""
    from vs2t_edge.runtime.journal import iter_records

    p = tmp_path / "j.jsonl"
    lines = _three_sessions(p)
    lines[2] = lines[2].replace(b'"manifest_sha256":"b"', b'"manifest_sha256":"x"')  # CRC no longer matches
    p.write_bytes(b"\n".join(lines))
    assert [r.get("item_id", r.get("manifest_sha256")) for r in iter_records(p)] == ["a", "piece-a", "piece-b",
                                                                                     "c", "piece-c"]
    err = capsys.readouterr().err
    assert f"journal {p}: line 3 " in err and "corrupt" in err and err.count("\n") == 1, err
    list(iter_records(p))
    assert capsys.readouterr().err == ""  # once, not at every read
    with pytest.raises(JournalError, match="line 3 .* corrupt"):
        Journal.open(p)  # the service does not start (nor restore labels) on a damaged journal


def test_a_torn_last_line_is_read_past_quietly(tmp_path, capsys):
    """The last line of a journal the service is writing may be half there: normal, not damage."""
    from vs2t_edge.runtime.journal import iter_records

    p = tmp_path / "j.jsonl"
    _three_sessions(p)
    with open(p, "ab") as f:
        f.write(b'{"crc":1,"rec":{"type":"fi')
    assert len(list(iter_records(p))) == 6 and capsys.readouterr().err == ""


def test_a_blank_line_in_the_middle_loses_nothing_and_does_not_refuse_the_start(tmp_path):
    """A blank line (a hand edit) holds no record: the start used to refuse it as a corrupt one."""
    p = tmp_path / "j.jsonl"
    lines = _three_sessions(p)
    p.write_bytes(b"\n".join(lines[:2] + [b"", b"  "] + lines[2:]))
    with Journal.open(p) as j:
        assert j.torn_bytes == 0 and j.counts["start"] == 3 and j.counts["pre_sort"] == 3
        j.append({"type": "stop"})
    assert [r["type"] for r in read_records(p)][-2:] == ["pre_sort", "stop"]
    lines = p.read_bytes().split(b"\n")
    lines[4] = lines[4].replace(b'"manifest_sha256":"b"', b'"manifest_sha256":"x"')  # after the blank lines
    p.write_bytes(b"\n".join(lines))
    with pytest.raises(JournalError, match=f"journal {p}: line 5 .* corrupt"):
        Journal.open(p)  # named by its line in the file, blank lines counted

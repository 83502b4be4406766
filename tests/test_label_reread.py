"""A labels file read again from line 1 (runtime/labels.py ``OperatorFeedback.poll``: it no longer
begins with the lines read - an editor's save, a copy put back, a line taken out) must leave what the
operator's labels taught as it was: its lines the cell judged already are not judged again. Judged
again, a label the operator withdrew came back into force, and a label read before its piece id
existed (a labels file kept across a new journal, whose pieces are numbered from piece-000001 again)
was applied to the new piece of that id - either way a fabric no label names taught wool's mean, and
its next pieces went to wool's bin."""

from __future__ import annotations

import json
import os

from feedback_fakes import BINS, ListJournal, PieceModel, decide_with, labelled_cell, operator_feedback
from vs2t_edge.runtime.journal import iter_records
from vs2t_edge.runtime.labels import append_label

LINEN = (8.0, 2.0)  # a fabric the job does not list: zero-shot it goes to the reject bin (never sure)


class _LinenModel(PieceModel):
    z = LINEN


def _save_over(path, text):
    """An editor's save: a new file with ``text`` renamed over ``path``."""
    tmp = path.with_name(path.name + ".swp")
    tmp.write_text(text)
    os.replace(tmp, path)


def test_a_withdrawn_label_stays_withdrawn_when_an_editor_saves_a_stale_copy(tmp_path):
    """The operator labels a linen piece wool by mistake, withdraws it (`label --retract`), and an
    editor opened on the labels file before the withdrawal saves its copy: the file no longer begins
    with the lines read, so the cell reads it again from line 1. The wrong label must stay withdrawn
    - it came back, and the next linen piece went to wool's bin."""
    fb = operator_feedback(tmp_path)
    cell, gate, journal = labelled_cell(tmp_path, fb, [80] * 40, _LinenModel())
    first = cell.run(max_items=1)[0]
    assert first.bin == 0  # linen, zero-shot: the reject bin
    append_label(fb.path, first.item.id, "wool")  # the mistake
    stale = fb.path.read_text()  # what the editor holds
    cell.run(max_items=2)
    assert gate.sorted[-1] == BINS["wool"]  # the wrong label in force: linen into wool's bin
    append_label(fb.path, first.item.id, None)  # withdrawn
    cell.run(max_items=3)
    assert gate.sorted[-1] == 0 and fb.item_labels == {}
    _save_over(fb.path, stale)
    cell.run(max_items=4)
    assert fb.item_labels == {} and gate.sorted[-1] == 0, (
        f"after the editor's save: labels {fb.item_labels}, the linen piece went to bin {gate.sorted[-1]}")
    reread = [r for r in iter_records(journal.path) if r.get("type") == "label"][-2:]
    assert reread[0].get("reread") and reread[1].get("read_before") and not reread[1]["applied"]
    journal.close()
    restarted = operator_feedback(tmp_path)  # a restart rebuilds the same: the label stays withdrawn
    restarted.restore(iter_records(journal.path), seal=None)
    assert restarted.item_labels == {} and decide_with(restarted(), LINEN).label != "wool"


def test_a_label_read_before_its_piece_id_existed_does_not_name_a_later_piece_of_that_id(tmp_path):
    """A new journal numbers its pieces from piece-000001 again (a damaged one moved aside, say);
    the labels file kept at its path holds the last journal's labels. The first poll judges them:
    no piece of that id decided. Once the new journal has a piece-000001 - a linen piece - an edit of
    the file (a bad line taken out) has it read again from line 1: the old line must still name no
    piece here - it taught wool the linen piece's presses, and the next linen piece went to wool's bin."""
    fb = operator_feedback(tmp_path)
    old = ['{"item_id": "piece-000001", "fabric": wool}\n',  # a typo the operator fixes later
           json.dumps({"item_id": "piece-000001", "fabric": "wool"}, sort_keys=True) + "\n"]
    fb.path.write_text("".join(old))
    j = ListJournal()
    assert [r["applied"] for r in fb.poll(j)] == [False, False]  # no piece-000001 in this journal yet
    ev = fb()
    assert decide_with(ev, LINEN).label != "wool"
    fb.remember("piece-000001", ev)  # the new journal's piece-000001: linen
    _save_over(fb.path, old[1])  # the bad line taken out
    got = fb.poll(j)
    assert fb.item_labels == {} and decide_with(fb(), LINEN).label != "wool", (
        f"after the edit: labels {fb.item_labels}, a linen piece decided {decide_with(fb(), LINEN).label}")
    assert got[0].get("reread") and not any(r["applied"] for r in got[1:])
    restarted = operator_feedback(tmp_path)
    pre_sort = {"type": "pre_sort", "item_id": "piece-000001", "presses": ev.presses,
                "scene_z_mean": fb.journal_z_mean(ev)}
    restarted.restore(j.records[:2] + [pre_sort] + j.records[2:], seal=None)  # in the journal's order
    assert restarted.item_labels == {}


def test_a_labels_file_first_read_after_a_new_journal_began_names_no_piece_of_it(tmp_path, capsys):
    """The same kept labels file, first read late: the service could not read it when the new journal
    began (written by `label` as another user with mode 0640 - the unit's DynamicUser - or put back
    from a backup), sorted on, and read it once its group was fixed. The last job's label of
    piece-000001 - a wool piece, so labelled by the verb - named the new journal's piece-000001, a
    linen piece: wool learned linen's presses, and the next linen piece went to wool's bin. The verb
    now binds a label to the presses of the piece it looked up; a piece of that id with other presses
    is another piece."""
    from feedback_fakes import labels_config
    from vs2t_edge.cli import main
    from vs2t_edge.runtime.journal import Journal

    cfg = labels_config(tmp_path, "journal.jsonl")
    with Journal.open(tmp_path / "journal.jsonl") as j:  # the last job's piece-000001: wool
        j.append({"type": "pre_sort", "item_id": "piece-000001", "label": "unknown", "presses": 4,
                  "scene_z_mean": [7.5, 2.5]})
    assert main(["label", str(cfg.path), "piece-000001", "wool"]) == 0, capsys.readouterr().err
    (tmp_path / "journal.jsonl").rename(tmp_path / "last-job.jsonl")  # a new job: a new journal
    kept = tmp_path / "labels.jsonl"
    kept.rename(tmp_path / "labels.unreadable")  # not readable by the service yet
    fb, j = operator_feedback(tmp_path), ListJournal()
    assert fb.poll(j) == []
    ev = fb()
    assert decide_with(ev, LINEN).label != "wool"
    fb.remember("piece-000001", ev)  # the new journal's piece-000001: linen
    (tmp_path / "labels.unreadable").rename(kept)  # readable now
    got = fb.poll(j)
    assert not got[0]["applied"] and "another piece" in got[0]["why"], got
    assert fb.item_labels == {} and decide_with(fb(), LINEN).label != "wool"
    restarted = operator_feedback(tmp_path)  # a restart judges the line the same way
    pre_sort = {"type": "pre_sort", "item_id": "piece-000001", "presses": ev.presses,
                "scene_z_mean": fb.journal_z_mean(ev)}
    restarted.restore([pre_sort, *j.records], seal=None)
    assert restarted.item_labels == {}
    # a label the verb binds to this journal's piece-000001 is applied, live and at a restart
    with Journal.open(tmp_path / "journal.jsonl") as jj:
        jj.append(pre_sort)
    assert main(["label", str(cfg.path), "piece-000001", "wool"]) == 0, capsys.readouterr().err
    assert [r["applied"] for r in fb.poll(j)] == [True]
    again = operator_feedback(tmp_path)
    again.restore([pre_sort, *j.records], seal=None)
    assert again.item_labels == {"piece-000001": ("wool", False)}


def test_a_restart_that_names_the_labels_file_by_another_path_resumes_where_it_was(tmp_path):
    """The journal's label records name the labels file by the path string the config gave (a config
    loaded as `cell.yaml` from its folder names `labels.jsonl`; given by its full path, the full path).
    A restart that named the same file by another string found none of its records: it read the file
    from line 1 again, with every piece of the journal known - a line that named no piece when it was
    read (the last journal's piece-000001) then named this journal's piece-000001, a linen piece, and
    the next linen piece went to wool's bin. Records naming the same file are the file's."""
    (tmp_path / "sub").mkdir()
    other = str(tmp_path / "sub" / ".." / "labels.jsonl")  # the same file, by another string
    first = operator_feedback(tmp_path)
    first.path = type(first.path)(other)
    first.path.write_text(json.dumps({"item_id": "piece-000001", "fabric": "wool"}, sort_keys=True) + "\n")
    j = ListJournal()
    assert [r["applied"] for r in first.poll(j)] == [False]  # the last journal's line: no such piece here
    ev = first()
    assert decide_with(ev, LINEN).label != "wool"
    pre_sort = {"type": "pre_sort", "item_id": "piece-000001", "presses": ev.presses,
                "scene_z_mean": first.journal_z_mean(ev)}
    restarted = operator_feedback(tmp_path)  # the same file by its plain path
    restarted.restore([*j.records, pre_sort], seal=None)
    assert restarted.lines_read == 1
    restarted.poll(ListJournal())
    assert restarted.item_labels == {} and decide_with(restarted(), LINEN).label != "wool", restarted.item_labels

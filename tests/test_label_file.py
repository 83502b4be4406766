"""The operator's labels file (runtime/labels.py): the cell reads it between pieces, journals
what it applied and why not, resumes it after a restart, and replays it; and the `label` verb that
appends to it."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from cell_fakes import ScriptedCamera
from feedback_fakes import (BINS, CLASSES, WOOL_PIECE, ListJournal, PieceModel, decide_piece, labelled_cell,
                            labels_config, operator_feedback, scene_model)
from vs2t_edge.cli import main
from vs2t_edge.runtime.bundle import SEAL_KEY
from vs2t_edge.runtime.evidence import UNKNOWN, Evidence
from vs2t_edge.runtime.items import ContinuousFeed
from vs2t_edge.runtime.journal import Journal, iter_records, read_records
from vs2t_edge.runtime.labels import append_label, read_labels
from vs2t_edge.sim.fake_devices import FakeArm, FakeGate
from vs2t_edge.sim.scene import fake_cell_yaml

_model, _decide = scene_model, decide_piece


_Journal, _feedback = ListJournal, operator_feedback


def test_the_poll_applies_journals_and_refuses_in_words(tmp_path):
    fb, j = _feedback(tmp_path), _Journal()
    _, ev = _decide(fb.model, WOOL_PIECE)
    fb.remember("piece-1", ev)
    path = tmp_path / "labels.jsonl"
    append_label(path, "piece-9", "wool")  # never decided here
    append_label(path, "piece-1", "silk")  # touched: its mean is the training one
    append_label(path, "piece-1", "linen")  # not in the job, and not said to be off-scene
    with open(path, "a") as f:
        f.write("{not json\n")
    append_label(path, "piece-1", "wool")
    with open(path, "a") as f:
        f.write('{"item_id": "piece-2", "fab')  # still being written: left for the next poll
    recs = fb.poll(j)
    assert [r["applied"] for r in recs] == [False, False, False, False, True]
    assert "no decided item 'piece-9'" in recs[0]["why"] and "touched fabric" in recs[1]["why"]
    assert "not a fabric of this job (an off-scene piece" in recs[2]["why"]
    assert f"{path} line 4: not JSON" in recs[3]["why"]
    assert fb.model.means[2][0] > 5 and fb.lines_read == 5
    assert fb.poll(j) == []  # nothing new: nothing journaled twice
    with open(path, "a") as f:
        f.write('ric": "wool"}\n')
    assert [r["line"] for r in fb.poll(j)] == [6]
    ev = fb()  # the next piece's evidence: the adapted model, guarded by the zero-shot one
    assert ev.adapted.item_model is fb.model and ev.zero_shot.item_model is fb.base
    fresh = _feedback(tmp_path / "nothing-learned")()
    assert isinstance(fresh, Evidence) and fresh.item_model.classes == CLASSES  # nothing learned: zero-shot


def test_a_piece_counts_once_a_new_label_replaces_its_last_and_a_retraction_withdraws_it(tmp_path):
    """A wrong label would pull its fabric's mean towards another fabric for the rest of the job (and
    a restart rebuilds from the journal, so it would stay): the operator corrects it by labelling the
    piece again or withdraws it; the same label twice must not count the piece twice."""
    fb, j = _feedback(tmp_path), _Journal()
    for item in ("piece-1", "piece-2"):
        _, ev = _decide(fb.model, WOOL_PIECE)
        fb.remember(item, ev)
    path = tmp_path / "labels.jsonl"
    append_label(path, "piece-1", "wool")
    once = fb.poll(j)[0]
    learned_once = fb.model.means.copy()
    assert fb.model.taught == {"wool"}
    append_label(path, "piece-1", "wool")  # said twice (a double click): counted once
    again = fb.poll(j)[0]
    assert once["applied"] and not again["applied"] and "already" in again["why"]
    assert np.array_equal(fb.model.means, learned_once)
    append_label(path, "piece-1", "stray", off_scene=True)  # corrected: it was none of the job's fabrics
    fixed = fb.poll(j)[0]
    assert fixed["applied"] and fixed["replaces"] == "wool"
    assert np.array_equal(fb.model.means[:3], _model().means) and fb.model.classes[-1] == "off-scene:stray"
    assert fb.labelled == {} and list(fb.strangers) == ["stray"] and fb.model.taught == frozenset()
    append_label(path, "piece-2", "wool")
    append_label(path, "piece-1", None)  # withdrawn: the cell forgets the piece
    append_label(path, "piece-1", None)  # nothing left to withdraw: said, not a crash
    got = fb.poll(j)
    assert [r["applied"] for r in got] == [True, True, False] and got[1]["withdrew"] == "stray"
    assert "no applied label to retract" in got[2]["why"]
    assert fb.model.classes == CLASSES and list(fb.labelled) == ["wool"]
    assert np.array_equal(fb.model.means, learned_once)  # piece-2 is the same piece as piece-1 was
    # a restart rebuilds exactly this from the journal: the correction and the withdrawal included
    fresh = _feedback(tmp_path)
    fresh.restore([{"type": "pre_sort", "item_id": i, "presses": 4, "scene_z_mean": list(WOOL_PIECE)}
                   for i in ("piece-1", "piece-2")] + j.records, seal=None)
    assert fresh.model.classes == CLASSES and np.array_equal(fresh.model.means, fb.model.means)
    assert fresh.item_labels == fb.item_labels == {"piece-2": ("wool", False)}
    # corrected to a touched fabric: that teaches nothing, so the earlier label is withdrawn
    append_label(path, "piece-2", "silk")
    to_touched = fb.poll(j)[0]
    assert to_touched["applied"] and to_touched["replaces"] == "wool" and fb.item_labels == {}
    assert np.array_equal(fb.model.means, _model().means) and fb.model.taught == frozenset()
    append_label(path, "piece-2", "silk")  # once nothing is learned from it, a touched label is only recorded
    assert "touched fabric" in fb.poll(j)[0]["why"]
    again = _feedback(tmp_path)
    again.restore([{"type": "pre_sort", "item_id": i, "presses": 4, "scene_z_mean": list(WOOL_PIECE)}
                   for i in ("piece-1", "piece-2")] + j.records, seal=None)
    assert again.item_labels == {} and np.array_equal(again.model.means, _model().means)
    # malformed withdrawals are refused in words, never taken for a label
    with open(path, "a") as f:
        f.write('{"item_id": "piece-2", "retract": "yes"}\n{"item_id": "piece-2", "fabric": "wool", "retract": true}\n')
    bad = fb.poll(j)
    assert [r["applied"] for r in bad] == [False, False] and all('"retract": true}' in r["why"] for r in bad)
    assert fb.item_labels == {}


def test_a_bad_or_missing_labels_file_never_stops_the_cell(tmp_path):
    fb = _feedback(tmp_path)
    assert fb.poll(_Journal()) == []  # no file yet: nothing to read
    (tmp_path / "labels.jsonl").mkdir()  # a folder where the file should be: said once, sorting goes on
    j = _Journal()
    said = fb.poll(j) + fb.poll(j)
    assert len(said) == 1 and not said[0]["applied"] and "unreadable" in said[0]["why"]
    (tmp_path / "labels.jsonl").rmdir()
    os.mkfifo(tmp_path / "labels.jsonl")  # a FIFO would block a plain read for ever
    said = fb.poll(j)
    assert len(said) == 1 and "not a regular file" in said[0]["why"]
    (tmp_path / "labels.jsonl").unlink()
    (tmp_path / "labels.jsonl").write_bytes(b"\n" + b"x" * 5000 + b"\n" + b"[1, 2]\n")
    got = read_labels(tmp_path / "labels.jsonl")
    assert [k for k, _ in got] == [1, 2, 3] and all(isinstance(r, str) for _, r in got)
    assert "empty line" in got[0][1] and "5000 bytes" in got[1][1] and "item_id" in got[2][1]


class _ZModel(PieceModel):
    """Every pressed frame of grey level 80 is a wool piece at WOOL_PIECE in the scene model's space."""

    z = WOOL_PIECE


def _cell(tmp_path, feedback, script):
    return labelled_cell(tmp_path, feedback, script, _ZModel())


def test_the_cell_learns_between_pieces_and_a_restart_resumes_it(tmp_path):
    fb = _feedback(tmp_path)
    cell, gate, journal = _cell(tmp_path, fb, [80] * 4)
    first = cell.run(max_items=1)[0]
    assert first.label == UNKNOWN and gate.sorted == [0]
    pre = [r for r in read_records(journal.path) if r["type"] == "pre_sort"][0]
    assert pre["scene_z_mean"] == list(WOOL_PIECE)  # what a later label reads, journaled with the decision
    append_label(tmp_path / "labels.jsonl", first.item.id, "wool")  # the person at the reject bin
    cell.camera.script = [80] * 4
    second = cell.run(max_items=2)[-1]
    assert second.label == "wool" and gate.sorted[-1] == BINS["wool"]
    recs = read_records(journal.path)
    kinds = [r["type"] for r in recs]
    # the label is journaled before the piece it changed was decided: item 2's record, the label, its decision
    assert kinds == ["item", "pre_sort", "final", "item", "label", "pre_sort", "final"]
    journal.close()
    # a restarted service: same journal, same labels file, a fresh factory - the same model
    fresh = _feedback(tmp_path)
    fresh.restore(iter_records(journal.path), seal=None)
    assert np.allclose(fresh.model.means, fb.model.means) and fresh.lines_read == 1
    assert fresh.poll(_Journal()) == []  # the label is not read (and journaled) a second time
    # a damaged or hand-edited projection is skipped, never a crash at start
    odd = _feedback(tmp_path)
    odd.restore([{"type": "pre_sort", "item_id": "x1", "presses": 2, "scene_z_mean": [1.0, "a"]},
                 {"type": "pre_sort", "item_id": "x2", "presses": 2, "scene_z_mean": [1.0, 2.0, 3.0]},
                 {"type": "pre_sort", "item_id": "x3", "presses": 2, "scene_z_mean": [1.0, float("nan")]}], seal=None)
    assert odd.pieces == {}
    # sessions of another bundle are skipped: their projections are another model's
    other = _feedback(tmp_path)
    other.restore([{"type": "start", SEAL_KEY: "other"}, *iter_records(journal.path)], seal="mine")
    assert np.array_equal(other.model.means, _model().means)


def test_the_label_verb_checks_the_config_and_appends(tmp_path, capsys):
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(fake_cell_yaml(journal="state/journal.jsonl"))
    assert main(["label", str(cfg), "piece-000001", "wool"]) == 2
    assert "does not turn operator labels on" in capsys.readouterr().err
    cfg.write_text(fake_cell_yaml(journal="state/journal.jsonl", evidence={"operator_labels": "labels.jsonl"}))
    assert main(["label", str(cfg), "piece-000001", "linen"]) == 2  # a typo must not become a stranger
    assert "'linen' is not a fabric of the scene" in capsys.readouterr().err
    assert main(["label", str(cfg), "piece-000001", "wool", "--off-scene"]) == 2
    assert "drop --off-scene" in capsys.readouterr().err
    for typed in (["WOOL", "--off-scene"], ["Wool"]):  # wool's presses must not teach a stranger
        assert main(["label", str(cfg), "piece-000001", *typed]) == 2
        assert f"'{typed[0]}' is not a fabric of the scene in {cfg}, but 'wool' is" in capsys.readouterr().err
    assert main(["label", str(cfg), "piece-000001", "wool"]) == 2  # no journal yet: no decided piece to label
    assert "has no decided piece 'piece-000001' (no piece decided yet)" in capsys.readouterr().err
    (tmp_path / "state").mkdir()
    with Journal.open(tmp_path / "state" / "journal.jsonl") as j:
        for item, label in (("piece-000001", UNKNOWN), ("piece-000002", "silk"), ("piece-000003", UNKNOWN)):
            j.append({"type": "pre_sort", "item_id": item, "label": label, "presses": 5})
    assert main(["label", str(cfg), "piece-00001", "wool"]) == 2  # a typo'd id is caught here, not in the journal
    assert "(the last decided is piece-000003)" in capsys.readouterr().err
    assert main(["label", str(cfg), "piece-000001", "wool"]) == 0
    assert "the cell had decided the reject bin after 5 press(es)" in capsys.readouterr().out
    assert main(["label", str(cfg), "piece-000002", "linen", "--off-scene"]) == 0
    lines = (tmp_path / "labels.jsonl").read_text().splitlines()
    assert [json.loads(x) for x in lines] == [{"fabric": "wool", "item_id": "piece-000001"},
                                              {"fabric": "linen", "item_id": "piece-000002", "off_scene": True}]
    # --list: the pieces in the reject bin and what became of their labels, from the journal
    with Journal.open(tmp_path / "state" / "journal.jsonl") as j:
        for rec in ({"type": "final", "item": 1, "item_id": "piece-000001", "label": UNKNOWN, "bin": 0, "outcome": "sorted"},
                    {"type": "final", "item": 2, "item_id": "piece-000002", "label": "silk", "bin": 2, "outcome": "sorted"},
                    {"type": "final", "item": 3, "item_id": "piece-000003", "label": UNKNOWN, "bin": 0,
                     "outcome": "rejected_fault", "reason": "gate jam"},
                    {"type": "label", "line": 1, "item_id": "piece-000001", "fabric": "wool", "applied": True}):
            j.append(rec)
    capsys.readouterr()
    assert main(["label", str(cfg), "--list"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert len(listed) == 3 and "piece-000002" not in "".join(listed)  # sorted to silk: not in the reject bin
    assert "labelled wool: applied" in listed[1] and "gate jam" in listed[2] and "no label yet" in listed[2]
    assert main(["label", str(cfg)]) == 2 and "--list" in capsys.readouterr().err
    # --retract withdraws a label; it takes the item alone
    assert main(["label", str(cfg), "piece-000001", "wool", "--retract"]) == 2
    assert "--retract takes ITEM_ID alone" in capsys.readouterr().err
    assert main(["label", str(cfg), "piece-000001", "--retract"]) == 0
    assert json.loads((tmp_path / "labels.jsonl").read_text().splitlines()[-1]) == {"item_id": "piece-000001",
                                                                                 "retract": True}
    with Journal.open(tmp_path / "state" / "journal.jsonl") as j:
        j.append({"type": "label", "line": 3, "item_id": "piece-000001", "retract": True, "applied": True})
    assert main(["label", str(cfg), "piece-000003", "--retract"]) == 0  # not read by the service yet
    capsys.readouterr()
    assert main(["label", str(cfg), "--list"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert "withdrawn: applied" in listed[1] and "withdrawn: the service reads it before its next piece" in listed[2]
    # --last: the piece the cell decided last, e.g. a teach piece pressed just now (whatever its bin)
    assert main(["label", str(cfg), "piece-000003", "--last", "wool"]) == 2
    assert "--last FABRIC takes no ITEM_ID" in capsys.readouterr().err
    assert main(["label", str(cfg), "--last", "wool"]) == 0
    assert capsys.readouterr().out.startswith("piece-000003 labelled wool")
    assert json.loads((tmp_path / "labels.jsonl").read_text().splitlines()[-1]) == {"item_id": "piece-000003",
                                                                                 "fabric": "wool"}
    # once the cell has begun another piece, the piece decided last may be a later one than the
    # operator saw: --last refuses and asks for the id (the label names a piece, never "whatever is last")
    with Journal.open(tmp_path / "state" / "journal.jsonl") as j:
        j.append({"type": "item", "item": 4, "item_id": "piece-000004"})
    capsys.readouterr()
    assert main(["label", str(cfg), "--last", "wool"]) == 2
    err = capsys.readouterr().err
    assert "--last is ambiguous" in err and "begun piece piece-000004 since it decided piece-000003" in err
    assert len((tmp_path / "labels.jsonl").read_text().splitlines()) == 5  # nothing appended
    assert main(["label", str(cfg), "piece-000003", "wool"]) == 0  # by its id it still can be
    with Journal.open(tmp_path / "state" / "journal.jsonl") as j:
        j.append({"type": "pre_sort", "item_id": "piece-000004", "label": UNKNOWN, "presses": 5})
    capsys.readouterr()
    assert main(["label", str(cfg), "--last", "wool"]) == 0  # decided, nothing begun since: it is the last one
    assert capsys.readouterr().out.startswith("piece-000004 labelled wool")
    # a label the service has not read yet says off-scene as a read one does (it said "labelled linen")
    assert main(["label", str(cfg), "piece-000003", "linen", "--off-scene"]) == 0
    capsys.readouterr()
    assert main(["label", str(cfg), "--list"]) == 0
    assert "labelled linen (off-scene): the service reads it before its next piece" in capsys.readouterr().out


def test_label_list_says_why_the_cell_sent_a_piece_to_the_reject_bin(tmp_path, capsys):
    """--list's reason column was empty for every piece the cell itself sent to the reject bin (only a
    fault's reason was journalled on the final record): it now says the decision's, as the demo does."""
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(fake_cell_yaml(journal="state/journal.jsonl", evidence={"operator_labels": "labels.jsonl"}))
    with Journal.open(tmp_path / "state" / "journal.jsonl") as j:
        for i, (label, stopped_by) in enumerate([(UNKNOWN, "press_limit"), (UNKNOWN, "off_scene"),
                                                 ("off-scene:felt", "confident")], 1):
            for kind in ("pre_sort", "final"):
                j.append({"type": kind, "item": i, "item_id": f"piece-00000{i}", "label": label, "bin": 0,
                          **({"stopped_by": stopped_by} if kind == "pre_sort" else {"outcome": "sorted"})})
    assert main(["label", str(cfg), "--list"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert "never confident within the press limit" in listed[1] and "refused as off-scene" in listed[2]
    assert "a stranger the operator taught" in listed[3], listed


def test_the_label_verb_refuses_a_piece_decided_under_another_bundle(tmp_path, capsys):
    """The service learns only from pieces decided under the bundle it runs (their projections are
    that model's); a label of a piece decided under another was accepted here and refused there,
    said only in the journal - the operator believed the cell had learned."""
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(fake_cell_yaml(journal="state/journal.jsonl", evidence={"operator_labels": "labels.jsonl"}))
    (tmp_path / "bundle").mkdir()
    from vs2t_edge.runtime.bundle import FORMAT, READ_VERSIONS

    (tmp_path / "bundle" / "manifest.json").write_text(json.dumps({"format": FORMAT, "format_version": max(READ_VERSIONS),
                                                                   "manifest_sha256": "b" * 64}))
    (tmp_path / "state").mkdir()
    with Journal.open(tmp_path / "state" / "journal.jsonl") as j:
        j.append({"type": "start", "manifest_sha256": "a" * 64})
        j.append({"type": "pre_sort", "item_id": "piece-000001", "label": UNKNOWN, "presses": 5})
        j.append({"type": "start", "manifest_sha256": "b" * 64})
        j.append({"type": "pre_sort", "item_id": "piece-000002", "label": UNKNOWN, "presses": 5})
    assert main(["label", str(cfg), "piece-000001", "wool"]) == 2
    err = capsys.readouterr().err
    assert "piece-000001 was decided under another bundle" in err and "seal aaaaaaaaaaaa" in err
    assert not (tmp_path / "labels.jsonl").exists()  # nothing written
    assert main(["label", str(cfg), "piece-000002", "wool"]) == 0  # this bundle's piece
    assert main(["label", str(cfg), "--last", "wool"]) == 0


def _recorded_with_labels(tmp_path, operator, pieces=3):
    """A session of ``pieces`` pieces recorded with operator labels (``operator(cfg, result)`` after each
    piece), the wool piece's presses every time: (replay folder, ReplayFile, the model class)."""
    from vs2t_edge.runtime.recording import record_session
    from vs2t_edge.runtime.replay import ReplayFile

    class Model(_ZModel):
        scene_model = _model()

    cfg = labels_config(tmp_path, "j.jsonl")
    arm = FakeArm(config=cfg.arm)
    out = record_session(cfg, tmp_path / "s.replay", model=Model(), camera=ScriptedCamera(arm, [80] * 4 * pieces),
                         arm=arm, gate=FakeGate(), items=ContinuousFeed(limit=pieces),
                         on_item=lambda result: operator(cfg, result))
    return out, ReplayFile.open(out), Model


def test_a_recorded_session_replays_its_labels_at_the_same_points(tmp_path):
    from vs2t_edge.runtime.replay import run_replay

    def operator(cfg, result):  # the person at the reject bin, before the next piece comes
        if result.label == UNKNOWN:
            append_label(cfg.operator_labels, result.item.id, "wool")

    out, rf, Model = _recorded_with_labels(tmp_path, operator)
    finals = [d["label"] for d in rf.index["decisions"] if d["type"] == "final"]
    assert finals == [UNKNOWN, "wool", "wool"]  # the first piece taught the cell
    assert rf.index["labels"] == [{"before_item": "piece-000002", "item_id": "piece-000001", "fabric": "wool"}]
    assert run_replay(out, model=Model()).ok
    # without its labels the same frames decide otherwise: the replay used them (and it says where)
    index = json.loads((out / "index.json").read_text())
    index["labels"] = []
    (out / "index.json").write_text(json.dumps(index))
    report = run_replay(out, model=Model())
    assert not report.ok and "gate.sort(0) but the recording sorted to [3]" in report.diverged


def test_a_withdrawn_label_is_recorded_and_replayed_at_its_point(tmp_path):
    from vs2t_edge.runtime.replay import run_replay

    def operator(cfg, result):  # labels the first piece, then thinks better of it
        if result.item.id == "piece-000001":
            append_label(cfg.operator_labels, result.item.id, "wool")
        elif result.item.id == "piece-000002":
            append_label(cfg.operator_labels, "piece-000001", None)

    out, rf, Model = _recorded_with_labels(tmp_path, operator)
    assert [d["label"] for d in rf.index["decisions"] if d["type"] == "final"] == [UNKNOWN, "wool", UNKNOWN]
    assert rf.index["labels"][-1] == {"before_item": "piece-000003", "item_id": "piece-000001", "fabric": "",
                                      "retract": True}
    assert run_replay(out, model=Model()).ok
    index = json.loads((out / "index.json").read_text())
    index["labels"] = index["labels"][:-1]  # without the withdrawal the third piece is sorted: it was used
    (out / "index.json").write_text(json.dumps(index))
    assert not run_replay(out, model=Model()).ok


def test_a_label_bound_to_another_piece_changes_nothing_in_the_replay_either(tmp_path):
    """A label the `label` verb bound to other presses than this journal's piece of that id (a label
    given in an earlier journal, whose ids this one gives again) changes nothing live. Its replay
    must hand it over with its binding: unbound, the replay learned wool from the piece and sorted
    the next pieces into wool's bin where the session sent them to reject."""
    from vs2t_edge.runtime.replay import run_replay

    def operator(cfg, result):
        if result.item.id == "piece-000001":
            append_label(cfg.operator_labels, result.item.id, "wool", piece="0" * 64)

    out, rf, Model = _recorded_with_labels(tmp_path, operator)
    assert [d["label"] for d in rf.index["decisions"] if d["type"] == "final"] == [UNKNOWN, UNKNOWN, UNKNOWN]
    report = run_replay(out, model=Model())
    assert report.ok, (report.diverged, report.mismatches[:3])


def test_a_line_read_again_that_changed_nothing_live_changes_nothing_in_the_replay(tmp_path):
    """An editor's stale copy of the labels file brings back a withdrawn label's line: the live cell
    reads the file again, judges that line read before and changes nothing. Its replay must not hand
    it over as a new label - the fourth piece would be sorted to wool's bin where it went to reject."""
    from vs2t_edge.runtime.replay import run_replay

    def operator(cfg, result):
        path = cfg.operator_labels
        if result.item.id == "piece-000001":
            append_label(path, result.item.id, "wool")
        elif result.item.id == "piece-000002":
            append_label(path, "piece-000001", None)
        elif result.item.id == "piece-000003":  # the stale copy: the first line alone
            path.write_text(path.read_text().splitlines(keepends=True)[0])

    out, rf, Model = _recorded_with_labels(tmp_path, operator, pieces=4)
    assert [d["label"] for d in rf.index["decisions"] if d["type"] == "final"] == [UNKNOWN, "wool", UNKNOWN, UNKNOWN]
    report = run_replay(out, model=Model())
    assert report.ok, (report.diverged, report.mismatches[:3])


def test_label_list_into_a_reader_that_stops_early_exits_quietly(tmp_path):
    """`vs2t-edge label CONFIG --list | head` printed "label: [Errno 32] Broken pipe" (and exit 2):
    a reader that has seen enough closing the pipe is no error. Now nothing on stderr."""
    import subprocess
    import sys

    cfg = tmp_path / "cell.yaml"
    cfg.write_text(fake_cell_yaml(journal="state/journal.jsonl", evidence={"operator_labels": "labels.jsonl"}))
    (tmp_path / "state").mkdir()
    with Journal.open(tmp_path / "state" / "journal.jsonl") as j:
        for i in range(1, 2001):  # more lines than a pipe's buffer holds: the writer meets the closed pipe
            for kind in ("pre_sort", "final"):
                j.append({"type": kind, "item": i, "item_id": f"piece-{i:06d}", "label": UNKNOWN, "bin": 0,
                          **({"stopped_by": "press_limit"} if kind == "pre_sort" else {"outcome": "sorted"})})
    p = subprocess.run(["sh", "-c", f'"{sys.executable}" -m vs2t_edge.cli label "{cfg}" --list 2000 | head -n 2'],
                       capture_output=True, text=True, timeout=120)
    assert len(p.stdout.splitlines()) == 2 and "piece-000001" in p.stdout, p.stdout
    assert p.stderr == "", p.stderr


MERINO = "laine-m\u00e9rinos"  # composed (NFC), as the config and the bundle spell it
MERINO_NFD = "laine-me\u0301rinos"  # the same name as another keyboard (or a Mac's file dialog) sends it


def test_a_fabric_name_typed_decomposed_is_the_scenes_fabric(tmp_path, capsys):
    """The label verb compared the typed name with the scene's byte for byte: 'laine-mérinos' typed
    decomposed (NFD) was 'not a fabric of the scene' - and with --off-scene became a stranger that
    taught the cell to reject the job's own merino. Names are compared as Unicode text now (NFC),
    and the label is written in the scene's own spelling, which the service compares exactly."""
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(fake_cell_yaml(fabrics=(("denim", "touched", 1), (MERINO, "untouched", 2)),
                                  journal="state/journal.jsonl", evidence={"operator_labels": "labels.jsonl"}))
    (tmp_path / "state").mkdir()
    with Journal.open(tmp_path / "state" / "journal.jsonl") as j:
        j.append({"type": "pre_sort", "item_id": "piece-000001", "label": UNKNOWN, "presses": 5})
    assert main(["label", str(cfg), "piece-000001", MERINO_NFD, "--off-scene"]) == 2
    assert "drop --off-scene" in capsys.readouterr().err  # merino's presses must not teach a stranger
    assert main(["label", str(cfg), "piece-000001", MERINO_NFD.upper(), "--off-scene"]) == 2
    assert f"but {MERINO!r} is" in capsys.readouterr().err
    assert main(["label", str(cfg), "piece-000001", MERINO_NFD]) == 0, capsys.readouterr().err
    assert main(["label", str(cfg), "pi\u0065ce-000001", "cor\u0064uroy\u0301", "--off-scene"]) == 0
    lines = [json.loads(x) for x in (tmp_path / "labels.jsonl").read_text().splitlines()]
    assert lines[0] == {"item_id": "piece-000001", "fabric": MERINO}  # the scene's spelling
    assert lines[1]["fabric"] == "corduro\u00fd"  # a stranger's name is written composed too


def test_the_service_refuses_an_off_scene_label_naming_a_job_fabric_in_other_letters(tmp_path):
    """The service compared an off-scene label's name with the job's fabrics byte for byte: 'WOOL'
    (labelled off-scene in a job without wool, restored into one with it, or a line written by hand)
    taught a stranger 'off-scene:WOOL' from a wool piece, and the cell refused wool's next pieces. It
    is not applied, as `--off-scene wool` is not (docs/operator_labels.md), and a decomposed name of a job
    fabric counts as that fabric."""
    fb, j = _feedback(tmp_path), _Journal()
    _, ev = _decide(fb.model, WOOL_PIECE)
    fb.remember("piece-1", ev)
    fb.remember("piece-2", ev)
    path = tmp_path / "labels.jsonl"
    append_label(path, "piece-1", "WOOL", off_scene=True)
    append_label(path, "piece-2", "wo\u006fl ", off_scene=True)  # a stray space: the label verb refuses it too
    recs = fb.poll(j)
    assert [r["applied"] for r in recs] == [False, False], recs
    assert "a fabric of this job" in recs[0]["why"] and not fb.strangers
    assert "off-scene:WOOL" not in fb.model.classes


def test_a_broken_pipe_that_is_not_stdout_is_not_swallowed(monkeypatch):
    """The front door ended any verb quietly (exit 141, no word) on any BrokenPipeError out of its
    run() - also one from a pipe or socket to a device; only stdout's reader going away is quiet
    (review, 2026-11-29)."""
    from vs2t_edge.cli import main
    from vs2t_edge.runtime import label_cli

    def run(args):
        raise BrokenPipeError(32, "Broken pipe (the arm's socket)")

    monkeypatch.setattr(label_cli, "run", run)
    with pytest.raises(BrokenPipeError, match="the arm's socket"):
        main(["label", "cell.yaml", "--list"])

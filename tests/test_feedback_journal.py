"""Operator labels: what the cell learns is what its journal holds, live and after a restart, and a
label reaches only the piece it names (runtime/feedback.py, runtime/cell.py, runtime/record_cli.py)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from cell_fakes import ScriptedCamera
from feedback_fakes import ListJournal, PieceModel, decide_with, labelled_cell, labels_config, operator_feedback, scene_model
from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.evidence import Evidence
from vs2t_edge.runtime.labels import OperatorFeedback, append_label
from vs2t_edge.runtime.journal import Journal, JournalError, iter_records
from vs2t_edge.sim.fake_devices import FakeArm, FakeGate

_model, _feedback = scene_model, operator_feedback


# --- 1. restart rebuilds other learned means than the live cell had -------------------------------

PIECE_Z = (8.123456789, 2.987654321)  # a real press mean is never a round number


class _ZModel(PieceModel):
    z = PIECE_Z


def _cell(tmp_path, feedback, script):
    cell, _, journal = labelled_cell(tmp_path, feedback, script, _ZModel())
    return cell, journal


def _boundary(fb, a, b, iters=60):
    """t in [0, 1] where fb's decision of a piece at a + t (b - a) stops being 'wool'."""
    lo, hi = 0.0, 1.0
    assert decide_with(fb(), a).label == "wool" and decide_with(fb(), b).label != "wool"
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        if decide_with(fb(), a + mid * (b - a)).label == "wool":
            lo = mid
        else:
            hi = mid
    return lo, hi


def test_restart_rebuilds_the_same_learned_means_as_the_live_cell(tmp_path):
    """The live cell learns from the piece's unrounded press mean (feedback.remember), the journal
    keeps it rounded to 5 decimals (cell.py pre_sort 'scene_z_mean'), and a restart learns from the
    rounded one: the restarted cell's wool mean is not the live cell's, so the same presses can be
    decided differently before and after a restart (the doc: 'rebuilds the same state')."""
    live = _feedback(tmp_path)
    cell, journal = _cell(tmp_path, live, [80] * 4)
    first = cell.run(max_items=1)[0]
    append_label(tmp_path / "labels.jsonl", first.item.id, "wool")
    cell.camera.script = [80] * 4
    cell.run(max_items=2)
    assert "wool" in live.labelled  # the live cell learned from the piece
    journal.close()
    restarted = _feedback(tmp_path)
    restarted.restore(iter_records(journal.path), seal=None)
    # the piece whose presses sit on the live cell's decision boundary is decided differently
    a, b = live.model.means[2].copy(), np.array([10.0, 0.0])
    lo_live, hi_live = _boundary(live, a, b)
    lo_rest, hi_rest = _boundary(restarted, a, b)
    z_between = a + 0.5 * (min(hi_live, hi_rest) + max(lo_live, lo_rest)) * (b - a)
    live_label, restarted_label = decide_with(live(), z_between).label, decide_with(restarted(), z_between).label
    assert np.array_equal(restarted.model.means, live.model.means), (
        f"restart learned wool mean {restarted.model.means[2].tolist()}, live {live.model.means[2].tolist()}; "
        f"a piece at {z_between.tolist()}: live {live_label}, after restart {restarted_label}")


class _FailingOnce:
    """A journal whose first label append fails (disk full), then works."""

    def __init__(self):
        self.records, self.failed = [], False

    def append(self, rec):
        if rec.get("type") == "label" and not self.failed:
            self.failed = True
            raise JournalError("writing a label record failed (No space left on device)")
        self.records.append(rec)
        return rec


def _decided(fb, *items):
    """Each item decided by ``fb``'s evidence at PIECE_Z and remembered; their pre_sort records."""
    pre_sorts = []
    for item in items:
        ev = fb()
        decide_with(ev, PIECE_Z)
        fb.remember(item, ev)
        pre_sorts.append({"type": "pre_sort", "item_id": item, "presses": ev.presses,
                          "scene_z_mean": fb.journal_z_mean(ev)})
    return pre_sorts


def test_a_label_that_cannot_be_journaled_is_not_applied_and_is_read_again(tmp_path):
    """A label whose journal record fails (disk full: the cell latches 'journal write failed')
    leaves the model as it was - what the journal does not hold, a restart could not rebuild - and
    the next poll, once the operator has cleared the fault, reads the line again, applies it and
    journals it: live and restarted cells then hold the same labels."""
    fb = _feedback(tmp_path)
    pre_sorts = _decided(fb, "piece-1", "piece-2")
    j = _FailingOnce()
    means_before = fb.model.means.copy()
    append_label(fb.path, "piece-1", "wool")
    with pytest.raises(JournalError):
        fb.poll(j)
    assert fb.item_labels == {} and np.array_equal(fb.model.means, means_before)
    again = fb.poll(j)  # the fault cleared: the same line, read again
    assert [(r["item_id"], r["applied"]) for r in again] == [("piece-1", True)]
    append_label(fb.path, "piece-2", "wool")
    fb.poll(j)
    restarted = _feedback(tmp_path)
    restarted.restore(pre_sorts + j.records, seal=None)
    assert restarted.item_labels == fb.item_labels == {"piece-1": ("wool", False), "piece-2": ("wool", False)}
    assert np.array_equal(restarted.model.means, fb.model.means)


# --- 2b. a labels file replaced, truncated or edited: none of its lines is skipped -----------------

def _label_lines(*labels):
    return "".join(json.dumps({"item_id": i, "fabric": f}, sort_keys=True) + "\n" for i, f in labels)


def test_a_labels_file_put_in_place_of_the_one_read_is_read_from_its_first_line(tmp_path):
    """The cell reads the labels file on from the last line it read. A new file in its place (a new
    job's, or an editor's save), or the old one cut short, has other lines there: reading on from
    that line number skipped its first lines without a word - labels the operator gave, lost. Now
    the file is checked to begin with the lines read (their SHA-256, journaled with each line, so a
    restart checks it too), and read again from line 1 when it does not, said in the journal."""
    fb = _feedback(tmp_path)
    pre_sorts = _decided(fb, "piece-1", "piece-2", "piece-3")
    j = ListJournal()
    fb.path.write_text(_label_lines(("piece-9", "wool"), ("piece-8", "wool")))  # two lines naming no piece here
    assert [r["applied"] for r in fb.poll(j)] == [False, False] and fb.item_labels == {}
    # an editor's save: a new file (new inode), the same two lines and one more - read on, nothing twice
    tmp = tmp_path / "labels.new"
    tmp.write_text(_label_lines(("piece-9", "wool"), ("piece-8", "wool"), ("piece-1", "wool")))
    os.replace(tmp, fb.path)
    got = fb.poll(j)
    assert [(r["line"], r["item_id"], r["applied"]) for r in got] == [(3, "piece-1", True)]
    # a new file for the next job: one line, the same size as before or not - read from its first line
    tmp.write_text(_label_lines(("piece-2", "wool")))
    os.replace(tmp, fb.path)
    got = fb.poll(j)
    assert [r.get("reread") for r in got] == [True, None] and "read again from line 1" in got[0]["why"]
    assert (got[1]["line"], got[1]["item_id"], got[1]["applied"]) == (1, "piece-2", True)
    assert fb.item_labels == {"piece-1": ("wool", False), "piece-2": ("wool", False)}  # what was learned stays
    # the same file edited in place, its line count unchanged: read again, the label in force a no-op
    fb.path.write_text(_label_lines(("piece-3", "wool")))
    got = fb.poll(j)
    assert [r.get("reread") for r in got] == [True, None] and got[1]["applied"]
    assert fb.poll(j) == []  # and nothing twice
    # a restart checks the file against the journal: a file replaced while the service was down
    restarted = _feedback(tmp_path)
    restarted.restore(pre_sorts + j.records, seal=None)
    assert restarted.item_labels == fb.item_labels and restarted.lines_read == 1
    assert restarted.poll(ListJournal()) == []  # the file it journaled: nothing read twice
    fb.path.write_text(_label_lines(("piece-9", "wool"), ("piece-1", "silk")))  # while it was down
    restarted = _feedback(tmp_path)
    restarted.restore(pre_sorts + j.records, seal=None)
    got = restarted.poll(ListJournal())
    assert [r.get("reread") for r in got] == [True, None, None] and got[2]["item_id"] == "piece-1" and got[2]["applied"]
    assert restarted.item_labels == {"piece-2": ("wool", False), "piece-3": ("wool", False)}
    # a journal written before the checksums: at least as many lines as it read, else read again
    old = [{k: v for k, v in r.items() if k not in ("file_bytes", "file_sha256")} for r in j.records]
    fb.path.write_text("")
    restarted = _feedback(tmp_path)
    restarted.restore(pre_sorts + old, seal=None)
    assert [r.get("reread") for r in restarted.poll(ListJournal())] == [True]  # fewer lines than it read
    append_label(fb.path, "piece-1", None)
    got = restarted.poll(ListJournal())
    assert [(r["line"], r.get("retract"), r["applied"]) for r in got] == [(1, True, True)]


# --- 3. a recording shares the live labels file: its pieces' ids must never be live ones --------------

def test_a_label_given_a_recorded_piece_is_applied_by_that_recording_alone(tmp_path, capsys):
    """`vs2t-edge record CONFIG` runs the live config with its own journal but the config's
    operator-labels file, which the live service reads too. Its pieces are named by
    ``record_cli.recording_feed`` (``rec<time>-NNNNNN``), never a live journal's ``piece-NNNNNN``:
    the label the operator gives a recorded piece (`vs2t-edge label CONFIG ITEM FABRIC --recording
    OUT`) is read by the recording before its next piece, and the live service, restarted on its journal and the same
    file, journals it as naming no piece of its own - its piece-000001, between denim and silk,
    does not pull wool's mean to it (with the recording numbered from piece-000001, it did)."""
    from vs2t_edge.cli import main
    from vs2t_edge.runtime.record_cli import recording_feed
    from vs2t_edge.runtime.recording import record_session
    from vs2t_edge.runtime.replay import ReplayFile

    class Model(_ZModel):
        scene_model = _model()

    cfg = labels_config(tmp_path, "live.jsonl")
    other_piece = (3.0, 0.0)  # the live service's piece-000001: rejected, unlabelled
    with Journal.open(cfg.journal) as live:
        live.append({"type": "start"})
        live.append({"type": "item", "item": 1, "item_id": "piece-000001"})
        live.append({"type": "pre_sort", "item": 1, "item_id": "piece-000001", "label": "unknown", "bin": 0,
                     "presses": 4, "scene_z_mean": list(other_piece)})
        live.append({"type": "final", "item": 1, "item_id": "piece-000001", "label": "unknown", "bin": 0,
                     "outcome": "sorted"})
    out = tmp_path / "s.replay"
    recorded = []

    def operator(result):  # the person at the reject bin labels the recorded piece, as the tool says
        recorded.append(result.item.id)
        assert main(["label", str(cfg.path), result.item.id, "wool"]) == 2  # not a piece of the live journal
        assert "--recording" in capsys.readouterr().err
        assert main(["label", str(cfg.path), result.item.id, "wool", "--recording", str(out)]) == 0

    arm = FakeArm(config=cfg.arm)
    feed = recording_feed(2)
    record_session(cfg, out, model=Model(), camera=ScriptedCamera(arm, [80] * 8), arm=arm, gate=FakeGate(),
                   items=feed, on_item=operator)
    assert recorded[0].startswith("rec") and recorded[0] != "piece-000001"
    index = ReplayFile.open(out).index
    assert [(lab["item_id"], lab["before_item"]) for lab in index["labels"]] == [(recorded[0], recorded[1])]
    # the live service restarts on its journal and the shared labels file
    fb = _feedback(tmp_path)
    fb.restore(iter_records(cfg.journal), seal=None)
    before = decide_with(fb(), other_piece).label
    polled = fb.poll(ListJournal())
    assert polled and not any(r.get("applied") for r in polled)
    assert all("no decided item" in r["why"] for r in polled)
    assert decide_with(fb(), other_piece).label == before


def test_a_retraction_or_correction_given_while_its_fabric_was_out_of_the_job_holds_when_it_is_back(tmp_path):
    """Same bundle, three jobs. Job 1 lists wool: piece P (silk) is labelled wool by mistake. Job 2
    leaves wool out: the restart drops P's label, and the operator's retraction is journaled "no
    applied label to retract". Job 3 lists wool again: the restart applied only records applied in
    their session, so the wrong label came back for good (wool's mean on silk's presses) - and so
    did a wrong label corrected to a touched fabric in a job without wool."""
    labels, journal = tmp_path / "labels.jsonl", ListJournal()
    silk = np.array([10.0, 0.0])
    make = lambda m, classes: Evidence(classes, 0.95, 4, item_model=m)  # noqa: E731

    def session(scene):
        journal.append({"type": "start", "manifest_sha256": "SEAL"})
        fb = OperatorFeedback(scene_model(), scene, labels, make)
        fb.restore(list(journal.records), "SEAL")
        return fb

    def piece(fb, item):
        ev = fb()
        for _ in range(4):
            if ev.add(so.Press({}, None, silk + 0.3)) is not None:
                break
        journal.append({"type": "pre_sort", "item_id": item, "presses": ev.presses, "scene_z_mean": fb.journal_z_mean(ev)})
        fb.remember(item, ev)

    first = session(["denim", "silk", "wool"])
    piece(first, "P")
    piece(first, "Q")
    append_label(labels, "P", "wool")
    append_label(labels, "Q", "wool")
    assert [r["applied"] for r in first.poll(journal)] == [True, True]
    second = session(["denim", "silk"])
    assert second.item_labels == {}  # wool is no fabric of this job
    append_label(labels, "P", None)  # withdrawn
    append_label(labels, "Q", "silk")  # corrected: a touched fabric's label withdraws it
    assert [r["applied"] for r in second.poll(journal)] == [False, False]  # nothing in force to withdraw here
    third = session(["denim", "silk", "wool"])
    assert third.item_labels == {} and third.poll(journal) == []
    assert np.allclose(third.model.means, scene_model().means)  # wool's mean is its synthesis again



def _four_fabrics():
    """The fakes' scene model with a second untouched fabric, linen, at (10, 10)."""
    from dataclasses import replace

    return replace(scene_model(), classes=("denim", "silk", "wool", "linen"), untouched=frozenset({"wool", "linen"}),
                   means=np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]]))


def _labels_session(base, scene, labels, journal):
    """A service start on ``scene``: its start record, then the state restored from the journal."""
    journal.append({"type": "start", "manifest_sha256": "SEAL"})
    fb = OperatorFeedback(base, scene, labels, lambda m, classes: Evidence(classes, 0.95, 4, item_model=m))
    fb.restore(list(journal.records), "SEAL")
    return fb


def _decide_linen(ev):
    for _ in range(4):
        if (d := ev.add(so.Press({}, None, np.array([9.0, 9.0])))) is not None:
            return d
    return ev.decide()


def _linen_piece(fb, journal, item="P"):
    """A linen piece decided by ``fb``'s evidence, journalled and remembered as the cell does."""
    ev = fb()
    _decide_linen(ev)
    journal.append({"type": "pre_sort", "item_id": item, "presses": ev.presses, "scene_z_mean": fb.journal_z_mean(ev)})
    fb.remember(item, ev)


def test_a_correction_this_job_cannot_apply_still_withdraws_the_earlier_label(tmp_path):
    """A piece P of linen is labelled wool by mistake, then corrected to linen, in a job that can
    apply the correction. A restart into a job that cannot (linen left out of it: a plain label of
    a fabric outside the job; or, the other way round, an off-scene label of a fabric the new job
    lists) refused the correction and applied the wool label again: wool's mean on linen's presses,
    the next linen piece into wool's bin. The latest label counts: the earlier one is withdrawn
    wherever the correction cannot be applied, live and at a restart."""
    base = _four_fabrics()

    def run(name, first_job, correction_off_scene, second_job):
        labels, journal = tmp_path / f"{name}.jsonl", ListJournal()
        first = _labels_session(base, first_job, labels, journal)
        _linen_piece(first, journal)
        append_label(labels, "P", "wool")
        append_label(labels, "P", "linen", off_scene=correction_off_scene)
        assert [(r["applied"], r.get("replaces")) for r in first.poll(journal)] == [(True, None), (True, "wool")]
        return first, _labels_session(base, second_job, labels, journal)

    # a plain correction, then a job without linen
    first, second = run("plain", ["denim", "silk", "wool", "linen"], False, ["denim", "silk", "wool"])
    assert first.item_labels == {"P": ("linen", False)}
    assert second.item_labels == {}  # not wool again
    assert np.allclose(second.model.means[:3], base.means[:3])  # wool's mean is its synthesis
    # an off-scene correction in a job without linen, then a job with it
    first, second = run("off", ["denim", "silk", "wool"], True, ["denim", "silk", "wool", "linen"])
    assert first.item_labels == {"P": ("linen", True)}
    assert second.item_labels == {} and np.allclose(second.model.means, base.means)
    assert _decide_linen(second()).label != "wool"  # the next linen piece is not sorted into wool's bin

    # live: a label of a fabric outside the job withdraws the piece's wool label, said in the journal
    labels, journal = tmp_path / "live.jsonl", ListJournal()
    fb = _labels_session(base, ["denim", "silk", "wool"], labels, journal)
    _linen_piece(fb, journal)
    append_label(labels, "P", "wool")
    append_label(labels, "P", "linen")
    wool, refused = fb.poll(journal)
    assert wool["applied"] and not refused["applied"] and refused["withdrew"] == "wool"
    assert "earlier label 'wool' is withdrawn" in refused["why"] and fb.item_labels == {}


def test_the_same_fabric_labelled_in_two_jobs_keeps_its_label_at_a_restart(tmp_path):
    """Piece P labelled linen with --off-scene in a job without linen, and linen in one that lists
    it (what `vs2t-edge label` asks for in each): the same fabric, so neither line withdraws the
    other at a restart - only a label of another fabric does."""
    base = _four_fabrics()
    without, with_linen = ["denim", "silk", "wool"], ["denim", "silk", "wool", "linen"]
    labels, journal = tmp_path / "labels.jsonl", ListJournal()
    first = _labels_session(base, without, labels, journal)
    _linen_piece(first, journal)
    append_label(labels, "P", "linen", off_scene=True)
    assert [r["applied"] for r in first.poll(journal)] == [True]
    second = _labels_session(base, with_linen, labels, journal)
    append_label(labels, "P", "linen")
    assert [r["applied"] for r in second.poll(journal)] == [True]
    assert second.item_labels == {"P": ("linen", False)}
    assert _labels_session(base, without, labels, journal).item_labels == {"P": ("linen", True)}
    assert _labels_session(base, with_linen, labels, journal).item_labels == {"P": ("linen", False)}

"""Fault-matrix row of operator labels (runtime/feedback.py; registered in sim/faults.py SCENARIOS).

The cell learns from the reject bin through a file the operator's `vs2t-edge label` appends to, so
the file is an input like the camera: it can vanish, turn into a folder or a FIFO, hold junk, and
the operator can be wrong and withdraw a label. None of that may stop a piece or put one in a bin
on a guess, and a restart must rebuild what the running cell had learned.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from vs2t_edge.sim.fakes import BINS, CLASSES, GREY, GreyModel

# The scene model's space (2-d): the touched fabrics' means are real; wool's is the generator's
# synthesis, far from where real wool lands, so zero-shot a wool piece is refused (between silk and
# the synthesis) until a label moves wool's mean to its real presses.
REAL = {"denim": (0.0, 0.0), "silk": (10.0, 0.0), "wool": (8.0, 2.0)}
MEANS = ((0.0, 0.0), (10.0, 0.0), (0.0, 10.0))  # the model's: denim's and silk's real, wool's synthesised
PRESSES = 4  # at most, per piece


class _ProjectingGreyModel(GreyModel):
    """The grey-level fake model, each press also projected into the scene model's space (a fused
    bundle's ``scene_z``) at its fabric's real place."""

    def score_press(self, frame):
        from vs2t_edge.runtime import sorting as so

        score = super().score_press(frame)
        level = float(frame[..., 0].mean())
        fabric = min(REAL, key=lambda c: abs(GREY[c] - level))
        return so.Press(score.log_posterior, None, np.array(REAL[fabric]))


def _scene_model():
    from vs2t_edge.runtime.scene_model import SceneModel

    return SceneModel(tuple(CLASSES), frozenset({"wool"}), np.zeros(2), np.eye(2), np.array(MEANS),
                      item_rule="offset", press_var=1.0, offset_var_touched=0.1, offset_var_untouched=20.0,
                      item_temperature=2.0)  # the row's evidence sets the confidence (0.95)


def _said(rec: dict) -> str:
    """A label record in a few words (no paths: the matrix is a committed doc)."""
    why = rec.get("why", "")
    if rec.get("applied"):
        return "withdrawn" if rec.get("retract") else f"{rec.get('item_id')} {rec.get('fabric')}"
    for words in ("a folder", "a FIFO", "not JSON"):
        if words in why:
            return f"refused ({words})"
    return "refused"


def labels_file_faults(w: Path):
    """Six wool pieces among denim and silk; between pieces the operator labels the first wool
    piece, the labels file turns into a folder (twice in a row), comes back with a junk line and a
    withdrawal of that label, turns into a FIFO (a plain read would block for ever), and comes back
    with a new label. Wool pieces go to the wool bin exactly while a label stands, to the reject bin
    otherwise, denim and silk pieces to their own bins throughout; each unreadable state is journaled
    once; a service restarted on the journal rebuilds the same learned model."""
    from vs2t_edge.runtime.evidence import Evidence
    from vs2t_edge.runtime.labels import OperatorFeedback, append_label
    from vs2t_edge.runtime.journal import iter_records
    from vs2t_edge.sim.fault_rig import _at, _check, _loop_row

    labels = w / "labels.jsonl"
    aside = w / "labels.aside"

    def feedback():
        return OperatorFeedback(_scene_model(), CLASSES, labels,
                                lambda m, classes: Evidence(classes, 0.95, PRESSES, item_model=m))

    fb = feedback()
    truths = ["wool", "denim", "wool", "silk", "wool", "wool", "denim", "wool", "wool"]

    def to_folder():
        os.replace(labels, aside)
        labels.mkdir()

    def back_with_junk_and_withdrawal():
        labels.rmdir()
        os.replace(aside, labels)
        with open(labels, "a") as f:
            f.write("{not json\n")
        append_label(labels, "piece-0000", None)

    def to_fifo():
        os.replace(labels, aside)
        os.mkfifo(labels)

    def back_with_a_new_label():
        labels.unlink()
        os.replace(aside, labels)
        append_label(labels, "piece-0005", "wool")

    def inject(r):  # before press 1 of piece k: read before piece k + 1
        _at(r, 1, 1, lambda: append_label(labels, "piece-0000", "wool"))
        _at(r, 2, 1, to_folder)
        _at(r, 4, 1, back_with_junk_and_withdrawal)
        _at(r, 5, 1, to_fifo)
        _at(r, 6, 1, back_with_a_new_label)

    w.mkdir(parents=True, exist_ok=True)
    held: dict = {}
    words, problems = _loop_row(w, inject=inject, expect_outcomes={"sorted": len(truths)}, fault_words=None,
                                truths=truths, model=_ProjectingGreyModel(), evidence_factory=fb, holder_out=held,
                                max_presses=PRESSES)
    finals = sorted(held["audit"]["finals"], key=lambda r: r["item"])
    wool_bins = [f["bin"] for f, t in zip(finals, truths) if t == "wool"]
    wool = BINS["wool"]  # reject zero-shot and once withdrawn; wool's bin while a label stands (folder included)
    _check(problems, wool_bins == [0, wool, wool, 0, wool, wool],
           f"wool pieces went to bins {wool_bins}: expected reject while no label stood (zero-shot, withdrawn), "
           "wool's bin while one did")
    others = [f["bin"] for f, t in zip(finals, truths) if t != "wool"]
    _check(problems, others == [BINS[t] for t in truths if t != "wool"],
           f"the denim and silk pieces went to bins {others}, expected each to its own")
    records = [r for r in held["audit"]["records"] if r.get("type") == "label"]
    said = [_said(r) for r in records]
    unreadable = [r for r in records if "unreadable" in r.get("why", "")]
    _check(problems, len(unreadable) == 2 and "(a folder)" in unreadable[0]["why"]
           and "(a FIFO)" in unreadable[1]["why"],
           f"expected the folder and the FIFO journaled once each, got {[r.get('why') for r in unreadable]}")
    _check(problems, [r.get("retract", False) for r in records if r["applied"]] == [False, True, False]
           and any("not JSON" in r.get("why", "") for r in records),
           f"expected label, withdrawal, label applied and the junk line refused; the journal says {said}")
    fresh = feedback()
    fresh.restore(iter_records(w / "journal.jsonl"), seal=None)
    _check(problems, fresh.item_labels == fb.item_labels == {"piece-0005": ("wool", False)}
           and np.array_equal(fresh.model.means, fb.model.means),
           f"a restart rebuilt {fresh.item_labels}, the running cell had {fb.item_labels}")
    if labels.is_fifo():  # a row stopped half-way must not leave a FIFO for the next reader of its folder
        labels.unlink()
    return words + f"; labels journaled: {', '.join(said)}", problems

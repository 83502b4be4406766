"""Shared by the operator-label tests (tests/test_feedback.py, test_label_file.py, test_feedback_journal.py): a
three-class scene model whose untouched class is 'wool', a model whose every pressed frame is one
point of its space, a journal in a list, and a cell that learns from labels."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from cell_fakes import ScriptedCamera
from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.cell import Cell, SceneSpec
from vs2t_edge.runtime.evidence import Evidence
from vs2t_edge.runtime.labels import OperatorFeedback
from vs2t_edge.runtime.items import ContinuousFeed
from vs2t_edge.runtime.journal import Journal
from vs2t_edge.runtime.notify import Notifier
from vs2t_edge.runtime.preprocess import check_frame
from vs2t_edge.runtime.scene_model import SceneModel
from vs2t_edge.sim.fake_devices import FakeArm, FakeGate

CLASSES = ("denim", "silk", "wool")  # wool untouched: its mean (0, 10) is the generator's
MANIFEST_CLASSES = {"touched": ["denim", "silk"], "untouched": ["wool"]}  # a bundle manifest's "classes" of them
BINS = {"denim": 1, "silk": 2, "wool": 3}


def scene_model(**kw) -> SceneModel:
    m = SceneModel(CLASSES, frozenset({"wool"}), np.zeros(2), np.eye(2), np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]]),
                   item_rule="offset", press_var=1.0, offset_var_touched=0.1, offset_var_untouched=20.0,
                   item_temperature=3.0)
    return replace(m, **kw)


WOOL_PIECE = (8.0, 2.0)  # where real wool presses land: unsure between silk and the synthesis


def decide_piece(model, z, n=4):
    """(decision, evidence) of a piece whose ``n`` presses all land at ``z``, scene ``CLASSES``."""
    ev = Evidence(list(CLASSES), 0.95, n, item_model=model)
    return decide_with(ev, z, n), ev


def decide_with(evidence, z, n=4):
    """The decision of ``evidence`` (a fresh one) for a piece whose ``n`` presses all land at ``z``."""
    for _ in range(n):
        d = evidence.add(so.Press({c: -1.0 for c in CLASSES}, None, np.asarray(z, float)))
        if d is not None:
            return d
    return evidence.decide()


class ListJournal:
    """A journal that keeps its records in a list."""

    def __init__(self):
        self.records = []

    def append(self, rec):
        self.records.append(rec)
        return rec


def operator_feedback(tmp_path, model=None) -> OperatorFeedback:
    return OperatorFeedback(model or scene_model(), CLASSES, tmp_path / "labels.jsonl",
                            lambda m, classes: Evidence(classes, 0.95, 4, item_model=m))


class PieceModel:
    """Every pressed frame is a piece at ``z`` in the scene model's space (a subclass sets ``z``)."""

    z: tuple = (0.0, 0.0)

    def set_reference(self, frame):
        check_frame(frame, name="reference frame")

    def score_press(self, frame):
        check_frame(frame)
        return so.Press({c: -1.0 for c in CLASSES}, None, np.array(self.z))


def labelled_cell(tmp_path, feedback, script, model):
    """A cell on fake devices that learns from ``feedback``: (cell, gate, journal)."""
    arm = FakeArm()
    arm.connect()
    gate = FakeGate()
    gate.connect()
    journal = Journal.open(tmp_path / "journal.jsonl")
    scene = SceneSpec(bins=dict(BINS), reject_bin=0, points_mm=arm.config.grid_points_mm()[:20], max_presses=4,
                      confidence=0.95, fault_file=tmp_path / "FAULT", wait_item_timeout_s=0.01)
    cell = Cell(camera=ScriptedCamera(arm, script), arm=arm, gate=gate, model=model, journal=journal,
                notifier=Notifier(address=""), scene=scene, evidence_factory=feedback,
                items=ContinuousFeed(first_number=journal.next_item_number()), sleep=lambda s: None)
    return cell, gate, journal


def labels_config(tmp_path, journal: str):
    """A replay-camera cell config at ``tmp_path``/cell.yaml that journals to ``journal`` and reads
    operator labels from labels.jsonl beside it (scoring not overlapped), loaded."""
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.sim.scene import fake_cell_yaml

    (tmp_path / "cell.yaml").write_text(fake_cell_yaml(
        camera={"kind": "replay", "path": "x"}, journal=journal, cell={"overlap_scoring": False},
        evidence={"max_presses": 4, "operator_labels": "labels.jsonl"}))
    return load_config(tmp_path / "cell.yaml")

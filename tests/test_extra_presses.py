"""Extra presses (runtime/evidence.py ``extra_presses``, the cell config's evidence.extra_presses):
a piece a touched fabric leads at the press limit, not yet confident and refused by no off-scene
rule, presses on; any other piece is decided at the limit as before. The cell's press loop lets
the evidence take them, the config checks them against the grid, and training's report prices them."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import pytest

from feedback_fakes import PieceModel, labelled_cell
from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.evidence import UNKNOWN, Evidence
from vs2t_edge.runtime.journal import iter_records
from vs2t_edge.runtime.operating_point import scene_model_rule
from vs2t_edge.runtime.scene_model import SceneModel

CLASSES = ("denim", "silk", "wool")
NEAR_DENIM = (0.4, 0.0)  # between denim and silk, nearer denim: surer with every press, slowly


def _model(**kw) -> SceneModel:
    """denim (0, 0) and silk (1, 0) touched and close together; wool untouched, far off."""
    return SceneModel(CLASSES, frozenset({"wool"}), np.zeros(2), np.eye(2),
                      np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 10.0]]), item_rule="offset", press_var=1.0,
                      offset_var_touched=0.1, offset_var_untouched=20.0, item_temperature=1.0, **kw)


def _evidence(scene=CLASSES, extra=3, model=None, **kw):
    m = model or _model()
    conf, opts = scene_model_rule(m)
    opts.update(kw)
    return Evidence(list(scene), 0.6, 4, **{**opts, "extra_presses": extra})


def _run(ev, z, n=12):
    for _ in range(n):
        d = ev.add(so.Press({}, None, np.asarray(z, float)))
        if d is not None:
            return d
    return ev.decide()


def test_a_piece_a_touched_fabric_leads_presses_on_until_it_is_confident():
    # denim's posterior at 4 presses of this point is 0.57, at 7 it passes 0.6
    without = _run(_evidence(extra=0), NEAR_DENIM)
    assert (without.label, without.presses, without.stopped_by) == (UNKNOWN, 4, "press_limit")
    ev = _evidence(extra=3)
    assert ev.press_limit == 7
    d = _run(ev, NEAR_DENIM)
    assert (d.label, d.presses, d.stopped_by) == ("denim", 7, "confident") and d.confidence >= 0.6
    # two extra presses are not enough: decided at the new limit, to the reject bin
    short = _run(_evidence(extra=2), NEAR_DENIM)
    assert (short.label, short.presses, short.stopped_by) == (UNKNOWN, 6, "press_limit")


def test_a_piece_an_untouched_fabric_leads_or_a_rule_refuses_is_decided_at_the_limit():
    # wool leads, never confident at its own confidence: no extra presses (its synthesis's evidence saturates)
    untouched = _evidence(class_confidence={"wool": 1.0})
    d = _run(untouched, (0.0, 5.0))
    assert (d.label, d.presses) == (UNKNOWN, 4) and untouched.at_limit()
    # a job that leaves silk out: a piece silk explains better is refused, at the limit, not later
    refused = _evidence(scene=("denim", "wool"), known_margin=0.0)
    d = _run(refused, (0.9, 0.0))
    assert (d.label, d.presses, d.stopped_by) == (UNKNOWN, 4, "off_scene")
    # while it presses on, the evidence says so; at the last extra press it is at its limit
    ev = _evidence(extra=2)
    for _ in range(4):
        assert ev.add(so.Press({}, None, np.asarray(NEAR_DENIM))) is None
    assert not ev.at_limit()
    ev.add(so.Press({}, None, np.asarray(NEAR_DENIM)))
    ev.add(so.Press({}, None, np.asarray(NEAR_DENIM)))
    assert ev.at_limit()
    with pytest.raises(ValueError, match="extra_presses"):
        _evidence(extra=-1)


class _NearDenim(PieceModel):
    z = NEAR_DENIM


class _SlowNearDenim(_NearDenim):
    """Scores after the arm has moved on: with overlapped scoring a score is late at every press."""

    def score_press(self, frame):
        time.sleep(0.03)
        return super().score_press(frame)


@pytest.mark.parametrize("overlap", [False, True])
@pytest.mark.parametrize("extra, presses, label", [(0, 4, UNKNOWN), (3, 7, "denim")])
def test_the_cell_presses_past_max_presses_for_a_piece_that_earns_it(tmp_path, extra, presses, label, overlap):
    m = _model()
    make = lambda: _evidence(model=m, extra=extra)  # noqa: E731
    cell, _, journal = labelled_cell(tmp_path, make, [120] * 12, _SlowNearDenim() if overlap else _NearDenim())
    cell.scene = replace(cell.scene, overlap_scoring=overlap)
    result = cell.run(max_items=1)[0]
    assert (result.presses, result.label) == (presses, label)
    journal.close()
    pre = [r for r in iter_records(tmp_path / "journal.jsonl") if r["type"] == "pre_sort"]
    assert pre[0]["presses"] == presses and len(pre[0]["scores"]) == presses
    assert not pre[0].get("speculative_presses")  # past max_presses the loop waits for each score
    assert result.bin == (1 if label == "denim" else 0)  # feedback_fakes.BINS: denim's bin 1, reject 0


def test_the_config_refuses_more_presses_than_the_grid_has(tmp_path):
    from vs2t_edge.runtime.config import ConfigError, load_config
    from vs2t_edge.sim.scene import fake_cell_yaml

    path = tmp_path / "cell.yaml"
    path.write_text(fake_cell_yaml(evidence={"max_presses": 5, "extra_presses": 4}))
    assert load_config(path).extra_presses == 4
    path.write_text(fake_cell_yaml(evidence={"grid_order": "list", "grid_points": [0, 1, 2, 3, 4, 5],
                                             "max_presses": 5, "extra_presses": 4}))
    with pytest.raises(ConfigError, match="evidence.extra_presses = 4: with max_presses 5, more presses than the 6"):
        load_config(path)


def test_the_knob_table_prices_extra_presses_on_the_same_jobs():
    m = _model(confidence=0.6, untouched_confidence=0.6)
    rng = np.random.default_rng(0)
    presses = {c: so.scene_model_presses(m, np.asarray(NEAR_DENIM if c == "denim" else m.means[i])
                                         + 0.05 * rng.normal(size=(12, 2)))
               for i, c in enumerate(CLASSES)}
    scenes = [so.Scene(("denim", "silk"), ("wool",), ())]
    rows = so.knob_prices(m, scenes, presses, max_presses=4, items_per_fabric=3, seed=1,
                          grid={"extra_presses": (0, 3)})
    base, none, three = rows
    assert none["own"] and none["right"] == base["right"]
    assert three["right"] > base["right"] and three["presses"] > base["presses"]
    assert math.isclose(three["by_kind"]["touched"]["right"], 1.0)


def test_labels_keep_extra_presses_for_touched_leaders_only():
    """With operator labels the guarded evidence takes its limit from the adapted one, and a
    stranger the operator taught (a real mean, yet no fabric of the job) earns no extra presses."""
    from vs2t_edge.runtime.feedback import OFF_SCENE_PREFIX, GuardedEvidence, TrackedEvidence, adapt

    m = _model()
    adapted = adapt(m, {}, strangers={"terry": [(np.array([0.0, 4.0]), 4)]})
    stranger = OFF_SCENE_PREFIX + "terry"
    conf, opts = scene_model_rule(adapted)
    assert opts["extend_classes"] == ("denim", "silk")
    # never confident for the stranger: led by it at the limit, the piece is decided there
    need = {**opts["class_confidence"], stranger: 1.0}
    ev = Evidence([*CLASSES, stranger], 0.6, 4, **{**opts, "class_confidence": need, "extra_presses": 3})
    d = _run(ev, (0.0, 4.0))
    assert d.label == UNKNOWN and d.presses == 4 and max(d.log_posterior, key=d.log_posterior.get) == stranger
    guarded = GuardedEvidence(_evidence(extra=3), _evidence(extra=3), trusted=("denim", "silk"))
    assert guarded.press_limit == 7
    d = _run(guarded, NEAR_DENIM)
    assert (d.label, d.presses) == ("denim", 7)
    assert TrackedEvidence(_evidence(extra=2), 2).press_limit == 6


def test_the_job_check_presses_a_picture_as_often_as_the_cell_would():
    """Before a job the cell presses each fabric's picture through its own evidence: with extra
    presses, a touched fabric that sorts only past max_presses is no longer flagged."""
    from vs2t_edge.runtime.job_check import check_job

    m = _model()  # denim's own picture: 0.81 at 4 presses, 0.92 at 9 (silk is one unit away)
    conf, opts = scene_model_rule(m)
    checks = {extra: {c.fabric: c for c in check_job(m, CLASSES, lambda: Evidence(list(CLASSES), 0.9, 4, **{
        **opts, "extra_presses": extra}), 4)} for extra in (0, 5)}
    assert not checks[0]["denim"].sorts and checks[0]["denim"].label == UNKNOWN
    assert checks[5]["denim"].sorts


def test_the_scene_model_carries_trainings_choice_and_a_written_key_overrides_it(tmp_path):
    """Training's choice travels in decision.npz (written only when not 0, so older files read as
    0); the cell takes it unless its config writes evidence.extra_presses, and says so when it does."""
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.operating_point import confidence_override_note, scene_model_settings
    from vs2t_edge.runtime.scene_model import SceneModelError
    from vs2t_edge.sim.scene import fake_cell_yaml

    m = _model(extra_presses=3)
    params = m.to_params()
    assert SceneModel.from_params(params).extra_presses == 3
    assert "extra_presses" not in _model().to_params()
    assert SceneModel.from_params(_model().to_params()).extra_presses == 0
    for bad in (np.array(-1), np.array(2.5), np.array(65), np.array([3])):
        with pytest.raises(SceneModelError, match="extra_presses"):
            SceneModel.from_params({**params, "extra_presses": bad})
    path = tmp_path / "cell.yaml"
    for written, limit in ((None, 7), (0, 4), (1, 5)):
        path.write_text(fake_cell_yaml(evidence={"max_presses": 4, "extra_presses": written}))
        cfg = load_config(path)
        assert cfg.extra_presses == written
        conf, opts = scene_model_settings(cfg, m)
        assert Evidence(list(CLASSES), conf, 4, **opts).press_limit == limit
        note = confidence_override_note(cfg, m)
        assert (f"evidence.extra_presses {written} overrides the 3 extra presses" in note) == (written is not None)


def test_a_grid_too_short_for_the_models_extra_presses_is_said(tmp_path):
    """A written evidence.extra_presses is held to the grid by the config check; the scene model's
    own is only known with the bundle: the start log and validate-config --check-bundle say the cut."""
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.operating_point import confidence_override_note
    from vs2t_edge.sim.scene import fake_cell_yaml

    path = tmp_path / "cell.yaml"
    for points, said in ((list(range(6)), True), (list(range(7)), False)):
        path.write_text(fake_cell_yaml(evidence={"max_presses": 4, "grid_order": "list", "grid_points": points}))
        note = confidence_override_note(load_config(path), _model(extra_presses=3))
        assert ("need 7 press points" in note and "lists 6: a piece stops at 6 presses" in note) == said, note
        assert "remove the key" not in note
    assert confidence_override_note(load_config(path), _model()) == ""
    path.write_text(fake_cell_yaml(evidence={"max_presses": 225}))  # spread: the whole grid, nothing to list
    assert confidence_override_note(load_config(path), _model(extra_presses=3)) == ""
    path.write_text(fake_cell_yaml(evidence={"max_presses": 4, "grid_order": "list", "grid_points": list(range(6)),
                                             "confidence": 0.5}))
    both = confidence_override_note(load_config(path), _model(extra_presses=3))
    assert "remove the key" in both and both.endswith("write evidence.extra_presses)")


def test_training_chooses_the_extra_presses_validation_scores_best(monkeypatch):
    """The mis-sort target first, then pieces in the right bin; of full ties the fewest presses."""
    from vs2t_edge.train import decision as dc

    def summary(right, mis):
        return {"all": {"right": right, "mis-sort": mis, "reject": 1 - right - mis, "presses": 4.0}}

    def choose(by_n):
        monkeypatch.setattr(dc, "_simulate", lambda models, jobs, tables=None, extra_presses=None: by_n[extra_presses])
        monkeypatch.setattr(dc, "press_tables", lambda model, rows: {})
        jobs = [type("J", (), {"rows": {}})()]
        models, s, rows = dc._extra_presses([_model()], by_n[0], [_model()], jobs, 0.01)
        assert [r["extra_presses"] for r in rows] == [0, *dc.EXTRA_PRESSES]
        assert [r["chosen"] for r in rows].count(True) == 1 and s is by_n[models[0].extra_presses]
        return models[0].extra_presses

    # 4 puts the most pieces right but breaks the target; 2 and 8 tie: the fewer presses
    assert choose({0: summary(0.70, 0.005), 2: summary(0.72, 0.008), 4: summary(0.74, 0.012),
                   8: summary(0.72, 0.008)}) == 2
    # as many right, fewer mis-sorts
    assert choose({0: summary(0.70, 0.005), 2: summary(0.70, 0.004), 4: summary(0.70, 0.006),
                   8: summary(0.70, 0.004)}) == 2
    # validation cannot tell them apart: none
    assert choose({n: summary(0.70, 0.005) for n in (0, 2, 4, 8)}) == 0


def test_an_untouched_fabric_labels_taught_earns_no_extra_presses():
    """Only touched classes press on: a taught untouched class's mean is real presses too, but
    pressing on for it sent pieces of an untaught twin into its bin on the paper world's label
    jobs (docs/results/operator_labels_paper.md), so a piece it leads is decided at the limit."""
    from vs2t_edge.runtime.feedback import adapt

    m = _model()
    taught = adapt(m, {"wool": [(np.array([0.0, 10.0]), 5)]})
    conf, opts = scene_model_rule(taught)
    assert "wool" in taught.taught and opts["extend_classes"] == ("denim", "silk")

    def piece(**kw):  # denim leads the first 4 presses, taught wool from the 5th: 0.57, 0.91, 0.985
        need = {**opts["class_confidence"], "wool": 0.98}
        return _run(Evidence(list(CLASSES), 0.99, 4, **{**opts, "class_confidence": need, **kw}), (0.0, 4.2))

    # denim (touched) leads at the limit: the piece presses on, and stops once wool leads
    d = piece(extra_presses=3)
    assert (d.label, d.presses) == (UNKNOWN, 5)
    # were taught classes to earn them, wool would take it at the 7th press
    d = piece(extra_presses=3, extend_classes=CLASSES)
    assert (d.label, d.presses, d.stopped_by) == ("wool", 7, "confident")
    assert piece(extra_presses=0).presses == 4


def test_simulations_take_the_models_own_extra_presses():
    """Training's test jobs, knob table and label jobs decide with the model's extra presses, as the
    cell does: pieces are drawn long enough, the knob table's own row is the model's number, and its
    max_presses rows keep it; an explicit number overrides it."""
    m = _model(confidence=0.6, untouched_confidence=0.6, extra_presses=3)
    assert so.scene_evidence(m, 4)(so.Scene(CLASSES, (), ())).press_limit == 7
    assert so.scene_evidence(m, 4, 0)(so.Scene(CLASSES, (), ())).press_limit == 4
    rng = np.random.default_rng(0)
    presses = {c: so.scene_model_presses(m, np.asarray(NEAR_DENIM if c == "denim" else m.means[i])
                                         + 0.05 * rng.normal(size=(12, 2)))
               for i, c in enumerate(CLASSES)}
    scenes = [so.Scene(("denim", "silk"), ("wool",), ())]
    recs = so.simulate_scenes(scenes, presses, so.scene_evidence(m, 4), items_per_fabric=3, max_presses=4, seed=1)
    denim = [r for r in recs if r.truth == "denim"]
    assert all(4 < r.presses <= 7 and r.outcome == so.RIGHT for r in denim)  # past the 4 the caller named
    rows = so.knob_prices(m, scenes, presses, max_presses=4, items_per_fabric=3, seed=1,
                          grid={"extra_presses": (0, 3), "max_presses": (4, 5)})
    base, none, three, four, five = rows
    assert three["own"] and not none["own"] and three["right"] == base["right"]
    assert none["by_kind"]["touched"]["right"] < base["by_kind"]["touched"]["right"]
    assert four["own"] and five["presses"] >= base["presses"]  # 5 + 3 extra: no fewer presses
    labelled = so.simulate_with_labels(scenes, presses, m, labels=False, items_per_fabric=3, max_presses=4, seed=1)
    assert max(r.presses for r in labelled if r.truth == "denim") > 4


def test_an_absent_key_is_the_models_number(tmp_path):
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.operating_point import extra_presses_of
    from vs2t_edge.sim.scene import fake_cell_yaml

    path = tmp_path / "cell.yaml"
    path.write_text(fake_cell_yaml(evidence={"max_presses": 4}))
    assert "extra_presses" not in path.read_text()
    cfg = load_config(path)
    assert cfg.extra_presses is None and extra_presses_of(cfg, _model(extra_presses=2)) == 2
    assert extra_presses_of(cfg, None) == 0

"""Twins in a job (``evidence.twin_ratio``): a touched fabric whose mean lies within the generator's
expected error of an untouched fabric's synthesis is held to ``TWIN_CONFIDENCE``, so that the
untouched fabric's pieces that feel like it go to the reject bin, not into its bin."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from vs2t_edge.runtime import operating_point as op
from vs2t_edge.runtime.config import load_config
from vs2t_edge.runtime.evidence import UNKNOWN
from vs2t_edge.runtime.scene_model import LABELS_KEYS, SceneModel
from vs2t_edge.runtime.sorting import Press, Scene, scene_evidence
from vs2t_edge.runtime.wiring import evidence_factory_for

# wool (untouched): its synthesis at (0, 10), its expected error k s_u = 2 x 2.0 = 4; cashmere (touched)
# 0.2 from it (0.04: a twin at any ratio >= 0.01); denim 10 away (100: a twin only from ratio 25)
CLASSES = ("denim", "silk", "cashmere", "wool")
MEANS = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 9.8], [0.0, 10.0]])


def model(**kw) -> SceneModel:
    m = SceneModel(CLASSES, frozenset({"wool"}), np.zeros(2), np.eye(2), MEANS, item_rule="offset", press_var=0.01,
                   offset_var_touched=0.0001, offset_var_untouched=2.0, item_temperature=1.0, confidence=0.9,
                   untouched_confidence=0.9, known_margin=0.0)
    return replace(m, **kw)


def test_twins_are_the_touched_fabrics_of_the_job_within_the_ratio_of_a_synthesis():
    m = model()
    job = ["denim", "cashmere", "wool"]
    assert m.twins(job, 1.0) == ["cashmere"]
    assert m.twins(job, 30.0) == ["denim", "cashmere"]
    assert m.twins(["denim", "cashmere"], 30.0) == []  # no untouched fabric in the job
    assert m.twins(job, float("inf")) == [] and m.twins(job, 0.0) == []
    # a fabric operator labels taught is real presses, no synthesis: it makes no twins
    assert replace(m, taught=frozenset({"wool"})).twins(job, 30.0) == []
    # a fabric known only to refuse is no job's, and so no twin
    assert replace(m, known_only=("cashmere",)).twins(job, 1.0) == []
    # a sum-rule model reads the offset setting it keeps for labels; without one, none, and the
    # config's key is said to do nothing
    setting = {key: float(getattr(m, key)) for key in LABELS_KEYS}
    assert replace(m, item_rule="sum", labels_rule=setting).twins(job, 1.0) == ["cashmere"]
    assert replace(m, item_rule="sum").twins(job, 1.0) == [] and op.twin_ratio_idle(replace(m, item_rule="sum"))


def test_an_untouched_piece_that_feels_like_its_touched_twin_goes_to_the_reject_bin_not_the_twins_bin():
    """wool's real pieces lie on cashmere (the generator put wool's synthesis 0.2 off): decided
    without the rule, they go into cashmere's bin - a mis-sort; with it, to the reject bin."""
    m = model()
    scene = Scene(("denim", "cashmere"), ("wool",), ())
    z = MEANS[2][None, :]
    lp, d2 = m.log_posterior_projected(z)
    press = Press(dict(zip(CLASSES, lp[0].tolist())), dict(zip(CLASSES, d2[0].tolist())), z[0])

    def decide(ratio):
        ev = scene_evidence(m, 5, twin_ratio=ratio)(scene)
        for _ in range(5):
            if (d := ev.add(press)) is not None:
                return d
        return ev.decide()

    assert decide(None).label == "cashmere"
    assert decide(1.0).label == UNKNOWN


CFG = ("bundle: bundle\ndevices: {camera: {kind: replay, path: x}, arm: {kind: fake}, gate: {kind: fake}}\n"
       "scene: {fabrics: [{name: denim, kind: touched, bin: 1}, {name: cashmere, kind: touched, bin: 2}, "
       "{name: wool, kind: untouched, bin: 3}]}\njournal: j.jsonl\n")


def test_the_cell_holds_the_configs_twins_as_the_simulated_jobs_do(tmp_path):
    from types import SimpleNamespace

    m = model()
    (tmp_path / "c.yaml").write_text(CFG + "evidence: {twin_ratio: 1.0}\n")
    cfg = load_config(tmp_path / "c.yaml")
    assert cfg.twin_ratio == 1.0 and op.job_twins(cfg, m) == ["cashmere"]
    cell = evidence_factory_for(cfg, SimpleNamespace(scene_model=m))()
    jobs = scene_evidence(m, cfg.max_presses, twin_ratio=1.0)(Scene(("denim", "cashmere"), ("wool",), ()))
    for ev in (cell, jobs):
        needed = dict(zip(ev.classes, ev._needed.tolist()))
        assert needed["cashmere"] == op.TWIN_CONFIDENCE and needed["denim"] == 0.9 and needed["wool"] == 0.9
    assert "evidence.twin_ratio 1 holds cashmere to confidence 0.9999" in op.confidence_override_note(cfg, m)
    assert "evidence.twin_ratio 1 does nothing: the scene model has no offset setting" in \
        op.confidence_override_note(cfg, replace(m, item_rule="sum"))
    assert "evidence.twin_ratio 1 does nothing: the bundle has no scene model" in op.confidence_override_note(cfg, None)
    # a written touched confidence above the twins' is what they need too: holding back is never bolder
    (tmp_path / "c.yaml").write_text(CFG + "evidence: {twin_ratio: 1.0, confidence: 0.99999}\n")
    strict = op.evidence_settings(load_config(tmp_path / "c.yaml"), SimpleNamespace(scene_model=m))[1]
    assert strict["class_confidence"]["cashmere"] == 0.99999
    (tmp_path / "c.yaml").write_text(CFG)
    plain = load_config(tmp_path / "c.yaml")
    assert plain.twin_ratio is None and op.job_twins(plain, m) == []
    assert dict(zip(*(lambda e: (e.classes, e._needed.tolist()))(
        evidence_factory_for(plain, SimpleNamespace(scene_model=m))())))["cashmere"] == 0.9

"""The job check (runtime/job_check.py): before a job, which of its fabrics does the cell send to
the reject bin (or another bin) even when a piece feels exactly like the model's picture of it?
Hand-made scene models in 2-d, the cell's own evidence; the daemon's start says it; training's
report measures how well it foretold its test jobs (train/decision.py job_check_outcomes)."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from vs2t_edge.runtime import job_check as jc
from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.evidence import UNKNOWN, Evidence
from vs2t_edge.runtime.operating_point import scene_model_rule
from vs2t_edge.runtime.scene_model import SceneModel

# denim and silk far apart; twill (touched) a hair from denim; wool (untouched, a wide synthesised
# class) with a touched sibling, cashmere, close to its synthesis
CLASSES = ("denim", "silk", "twill", "cashmere", "wool")
MEANS = np.array([[0.0, 0.0], [10.0, 0.0], [0.3, 0.0], [0.0, 9.8], [0.0, 10.0]])


def model(**kw) -> SceneModel:
    m = SceneModel(CLASSES, frozenset({"wool"}), np.zeros(2), np.eye(2), MEANS, item_rule="offset", press_var=1.0,
                   offset_var_touched=0.1, offset_var_untouched=2.0, item_temperature=1.0, confidence=0.9,
                   untouched_confidence=0.9, known_margin=0.0)
    return replace(m, **kw)


def factory(m: SceneModel, scene, max_presses: int = 5):
    confidence, opts = scene_model_rule(m)
    return lambda: Evidence(list(scene), confidence, max_presses, **opts)


def test_twins_in_one_job_are_both_flagged_and_the_others_pass():
    m = model()
    scene = ["denim", "silk", "twill"]
    checks = {c.fabric: c for c in jc.check_job(m, scene, factory(m, scene), 5)}
    assert checks["silk"].sorts and checks["silk"].label == "silk"
    for a, b in (("denim", "twill"), ("twill", "denim")):
        assert not checks[a].sorts and checks[a].label == UNKNOWN and checks[a].stopped_by == "press_limit"
        assert checks[a].rival == b and checks[a].rival_in_job
    said = "\n".join(jc.summary_lines(list(checks.values())))
    assert said.startswith("job check: 2 of 3 fabrics cannot be sorted")
    assert "denim (touched): even its own picture goes to the reject bin (never confident within the press " \
           "limit; nearest twill, in this job)" in said
    assert "silk" not in said


def test_a_touched_sibling_the_job_leaves_out_refuses_an_untouched_fabric_as_off_scene():
    """At wool's own synthesised mean the narrow touched cashmere explains it better than wool's
    wide class: the known-class rule refuses it - the demo's felt f02 and its touched twin f09."""
    m = model()
    scene = ["denim", "silk", "wool"]
    checks = {c.fabric: c for c in jc.check_job(m, scene, factory(m, scene), 5)}
    w = checks["wool"]
    assert not w.sorts and w.stopped_by == "off_scene" and w.rival == "cashmere" and not w.rival_in_job
    assert "refused as off-scene; nearest cashmere, a fabric the cell knows that this job leaves out" in w.describe()
    assert w.describe().endswith("start the job with a teach piece of it")
    assert checks["denim"].sorts and checks["silk"].sorts  # twill is out of this job: denim's own picture sorts
    # without the known-class rule wool's picture sorts
    m2 = model(known_margin=math.inf)
    assert {c.fabric: c.sorts for c in jc.check_job(m2, scene, factory(m2, scene), 5)}["wool"]


def test_a_wide_synthesised_sibling_in_the_job_holds_back_the_touched_one_too():
    """cashmere and wool in one job: wool's wide class takes a share of cashmere's own picture, so
    even cashmere is never confident (the paper world's touched pieces in the reject bin)."""
    m = model()
    scene = ["silk", "cashmere", "wool"]
    checks = {c.fabric: c for c in jc.check_job(m, scene, factory(m, scene), 5)}
    assert not checks["cashmere"].sorts and checks["cashmere"].rival == "wool" and checks["cashmere"].rival_in_job
    assert checks["cashmere"].describe().endswith("leave its rival out of the job, or teach the rival if it is untouched")
    assert not checks["wool"].sorts and checks["silk"].sorts
    assert jc.summary_lines(jc.check_job(m, ["silk", "denim"], factory(m, ["silk", "denim"]), 5)) == [
        "job check: every fabric of the job sorts at its own picture (2 fabrics)"]


def test_a_scene_class_the_model_lacks_is_refused_in_words():
    m = model()
    with pytest.raises(ValueError, match="no class 'linen'"):
        jc.check_job(m, ["denim", "linen"], factory(m, ["denim"]), 5)


def test_the_daemon_says_the_check_before_the_first_piece_and_only_with_a_scene_model():
    from vs2t_edge.runtime.daemon import job_check_lines

    m = model()
    cfg = SimpleNamespace(scene_classes=["denim", "silk", "twill"], max_presses=5)
    lines = job_check_lines(cfg, SimpleNamespace(scene_model=m), factory(m, cfg.scene_classes))
    assert lines[0].startswith("job check: 2 of 3 fabrics") and len(lines) == 3
    assert job_check_lines(cfg, SimpleNamespace(), factory(m, cfg.scene_classes)) == []
    bad = SimpleNamespace(scene_classes=["denim", "linen"], max_presses=5)
    assert job_check_lines(bad, SimpleNamespace(scene_model=m), factory(m, ["denim"]))[0].startswith("job check skipped")


def test_training_counts_how_the_check_foretold_its_jobs():
    """Two jobs: one with the twins denim and twill, one without; the pieces are the fabrics' own
    pictures with noise. The flagged twins' pieces miss their bins, the passed fabrics' do not."""
    from vs2t_edge.train.decision import evidence_for, job_check_outcomes

    m = model()
    rng = np.random.default_rng(0)
    presses = {c: so.scene_model_presses(m, MEANS[i] + 0.05 * rng.standard_normal((12, 2)))
               for i, c in enumerate(CLASSES)}
    scenes = [so.Scene(("denim", "silk", "twill"), (), ()), so.Scene(("denim", "silk"), (), ())]
    recs = so.simulate_scenes(scenes, presses, evidence_for(m), items_per_fabric=3, max_presses=5, seed=1)
    out = job_check_outcomes(m, scenes, recs, 3)
    assert out["touched"]["flagged"] == {"fabrics": 2, "right": 0.0}  # denim and twill in job 1
    assert out["touched"]["passed"] == {"fabrics": 3, "right": 1.0}
    with pytest.raises(ValueError, match="records for jobs"):
        job_check_outcomes(m, scenes, recs[:-1], 3)


def test_the_demo_teaches_exactly_the_flagged_untouched_fabrics():
    """`vs2t-edge demo` (teach on) starts the job with a teach piece of each untouched fabric the
    job check flags - never a touched one (a label teaches a touched fabric nothing) - and of none
    for a bundle without a scene model."""
    from vs2t_edge.sim.demo import teach_fabrics

    m = SimpleNamespace(scene_model=model())
    assert teach_fabrics(m, ["silk", "cashmere", "wool"], None, 5) == ["wool"]  # cashmere is flagged too, touched
    assert teach_fabrics(m, ["denim", "silk", "wool"], None, 5) == ["wool"]
    assert teach_fabrics(SimpleNamespace(scene_model=model(known_margin=math.inf)), ["denim", "silk", "wool"], None, 5) == []
    assert teach_fabrics(SimpleNamespace(), ["silk", "wool"], None, 5) == []


def test_check_job_says_the_check_for_a_config_before_the_service_starts(tmp_path, capsys):
    """`vs2t-edge check-job CONFIG` loads the config's bundle as the service does, runs the same
    check with the evidence the service would build, prints one line per fabric and exits 1 when a
    fabric cannot be sorted at its own picture (0 when all can); a bundle without a scene model is
    said and refused (2)."""
    from test_bundle_fixtures import TOUCHED, UNTOUCHED
    from test_fused_bundle import _write

    from vs2t_edge.cli import main
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.inference import TactileModel
    from vs2t_edge.runtime.wiring import evidence_factory_for
    from vs2t_edge.sim.scene import fake_cell_yaml

    _write(tmp_path / "bundle", "energy", True)
    fabrics = [(c, "touched", i + 1) for i, c in enumerate(TOUCHED)] + [(UNTOUCHED[0], "untouched", 4)]
    (tmp_path / "cell.yaml").write_text(fake_cell_yaml(fabrics=fabrics, bundle=str(tmp_path / "bundle")))
    code = main(["check-job", str(tmp_path / "cell.yaml")])
    said = capsys.readouterr().out.splitlines()
    cfg = load_config(tmp_path / "cell.yaml")
    model = TactileModel.load(tmp_path / "bundle", threads=1)
    want = jc.check_job(model.scene_model, cfg.scene_classes, evidence_factory_for(cfg, model), cfg.max_presses)
    assert said[:-1] == [c.describe() for c in want] and len(want) == 4
    assert code == (0 if all(c.sorts for c in want) else 1)
    assert said[-1].endswith("sorts at its own picture" if code == 0 else "cannot be sorted even at their own picture")
    _write(tmp_path / "plain", "energy", True, scene=False)
    (tmp_path / "plain.yaml").write_text(fake_cell_yaml(fabrics=fabrics, bundle=str(tmp_path / "plain")))
    assert main(["check-job", str(tmp_path / "plain.yaml")]) == 2
    assert "no scene model" in capsys.readouterr().err


def test_teaching_the_named_fabrics_is_teaching_them_all_or_none_at_the_ends():
    """``simulate_with_labels(teach=f)``: a function naming every untouched fabric of the job is the
    teach-all run, one naming none is the labels-only run, record for record; training's
    ``teach_flagged`` row names the job check's flagged ones."""
    m = model()
    rng = np.random.default_rng(3)
    presses = {c: so.scene_model_presses(m, MEANS[i] + 0.3 * rng.standard_normal((30, 2)))
               for i, c in enumerate(CLASSES)}
    scenes = [so.Scene(("denim", "silk", "cashmere"), ("wool",), ("twill",)), so.Scene(("silk", "twill"), ("wool",), ())]
    run = lambda teach: so.simulate_with_labels(scenes, presses, m, items_per_fabric=3, seed=2, teach=teach)  # noqa: E731
    assert run(lambda s: list(s.untouched)) == run(True)
    assert run(lambda s: []) == run(False)
    assert run(True) != run(False)  # the teach piece changes something, so the two checks above can fail
    from vs2t_edge.train.decision import operator_label_jobs

    out = operator_label_jobs(m, presses, scenes, seed=0)
    for n in out.values():
        assert set(n) == {"without", "with", "teach", "teach_flagged"}
        assert 0 <= n["teach_flagged"]["teach_pieces_per_job"] <= 1

"""Fabrics the run pressed but kept out of the bundle's heads - its validation fabrics - are known to
the deployed scene model only to refuse them (runtime/scene_model.py ``known_only``, train/decision.py
``with_known``). A piece of one goes to the reject bin where a model that never heard of it sent it
into the bin of the job fabric it feels like; it round-trips through decision.npz; a job cannot
list one. Hand-made 2-d models, the cell's own evidence."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.scene_model import SceneModel, SceneModelError
from vs2t_edge.train.decision import evidence_for, stranger_jobs, with_known

# denim and silk touched, wool untouched; twill (a validation fabric) 2.5 from denim: near enough
# that a model which never heard of twill sorts its pieces as denim, far enough to be told apart
CLASSES = ("denim", "silk", "wool")
MEANS = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
TWILL = np.array([2.5, 0.0])


def model(**kw) -> SceneModel:
    m = SceneModel(CLASSES, frozenset({"wool"}), np.zeros(2), np.eye(2), MEANS, item_rule="offset", press_var=1.0,
                   offset_var_touched=0.1, offset_var_untouched=2.0, item_temperature=1.0, confidence=0.9,
                   untouched_confidence=0.9, known_margin=0.0, open_threshold=30.0)
    return replace(m, **kw)


def presses(mean: np.ndarray, n: int, seed: int) -> np.ndarray:
    return mean + 0.3 * np.random.default_rng(seed).standard_normal((n, 2))


def test_with_known_appends_each_fabric_at_its_training_presses_mean_and_returns_the_rest():
    x = np.concatenate([presses(TWILL, 20, 0), presses(np.array([5.0, 5.0]), 10, 1)])
    y = np.repeat([0, 1], [20, 10])
    m, later = with_known(model(), x, y, ["twill", "felt"])
    assert m.classes == CLASSES + ("twill", "felt") and m.known_only == ("twill", "felt")
    assert m.untouched == frozenset({"wool"})  # real means: touched kind
    # press order: the first 70 % make the mean (as a touched fabric's), the rest is left to test with
    np.testing.assert_allclose(m.means[3], x[:14].mean(0))
    np.testing.assert_allclose(later["twill"], x[14:20])
    np.testing.assert_allclose(m.means[4], x[20:27].mean(0))
    with pytest.raises(ValueError, match="classes already"):
        with_known(model(), x, y, ["twill", "denim"])
    with pytest.raises(ValueError, match="need at least 5"):
        with_known(model(), x[:4], y[:4], ["twill"])


def test_a_piece_of_a_known_only_fabric_goes_to_the_reject_bin_not_its_twins():
    x = presses(TWILL, 40, 2)
    m, later = with_known(model(), x, np.zeros(40, int), ["twill"])
    scene = so.Scene(("denim", "silk"), ("wool",), ("twill",))
    rows = {"denim": presses(MEANS[0], 30, 3), "silk": presses(MEANS[1], 30, 4), "wool": presses(MEANS[2], 30, 5),
            "twill": later["twill"]}

    def run(mm):
        recs = so.simulate_scenes([scene], {f: so.scene_model_presses(mm, v) for f, v in rows.items()},
                                  evidence_for(mm), items_per_fabric=8, seed=0)
        return so.summarise(recs)["by_kind"]

    unaware, knowing = run(model()), run(m)
    assert unaware["off-scene"]["mis-sort"] == 1.0  # every twill piece into denim's bin
    assert knowing["off-scene"]["right"] == 1.0  # an off-scene piece's right bin is the reject bin
    assert knowing["touched"]["right"] == 1.0  # denim's own pieces still sort
    # training's measure of the same: the test jobs with the known fabrics' later presses as strangers
    out = stranger_jobs({"unaware": model(), "knowing": m}, ["denim", "silk"],
                        (np.concatenate([rows["denim"], rows["silk"]]), np.repeat([0, 1], 30)), ["wool"],
                        (rows["wool"], np.zeros(30, int)), {"twill": later["twill"]}, n_scenes=3)
    assert out["knowing"]["all"]["mis-sort"] < out["unaware"]["all"]["mis-sort"]


def test_known_only_round_trips_through_the_bundle_file_and_is_checked():
    m, _ = with_known(model(), presses(TWILL, 10, 6), np.zeros(10, int), ["twill"])
    back = SceneModel.from_params(m.to_params())  # what export writes and the cell reads (decision.npz)
    assert back.known_only == ("twill",) and back.classes == m.classes
    np.testing.assert_allclose(back.means, m.means)
    assert "known_only" not in model().to_params()  # a model without them writes the file it always did
    assert SceneModel.from_params(model().to_params()).known_only == ()
    bad = {**m.to_params(), "known_only": np.array(["silk"])}  # not the last class
    with pytest.raises(SceneModelError, match="known_only"):
        SceneModel.from_params(bad)
    assert m.subset(["denim", "twill"]).known_only == ("twill",)


def test_a_job_cannot_list_a_fabric_the_bundle_knows_only_to_refuse():
    from vs2t_edge.runtime.wiring import check_scene_against_bundle

    m, _ = with_known(model(), presses(TWILL, 10, 7), np.zeros(10, int), ["twill"])
    bundle = SimpleNamespace(touched=("denim", "silk"), untouched=("wool",), scene_model=m)
    cfg = SimpleNamespace(bundle="b", path="cell.yaml", fabrics=[SimpleNamespace(name="denim", kind="touched"),
                                                                 SimpleNamespace(name="twill", kind="touched")])
    with pytest.raises(ValueError, match=r"\['twill'\] are known to bundle b only to refuse"):
        check_scene_against_bundle(cfg, bundle)


def test_the_per_press_protocol_stays_over_the_bundle_classes_and_the_report_pairs_the_price():
    """The paper's per-press numbers (train/decision.py evaluate_scenes) are over touched and
    untouched classes: the fabrics the model knows only to refuse do not enter them. The report's
    line pairs the stranger jobs by split."""
    from vs2t_edge.train.decision import evaluate_scenes
    from vs2t_edge.train.report import stranger_lines

    # twill right on denim: it would take denim's presses if it counted per press
    m, _ = with_known(model(), presses(MEANS[0], 20, 8), np.zeros(20, int), ["twill"])
    rows = {c: presses(MEANS[i], 20, 9 + i) for i, c in enumerate(CLASSES)}
    args = (["denim", "silk"], (np.concatenate([rows["denim"], rows["silk"]]), np.repeat([0, 1], 20)), ["wool"],
            (rows["wool"], np.zeros(20, int)))
    plain, knowing = evaluate_scenes(model(), *args, n_scenes=2), evaluate_scenes(m, *args, n_scenes=2)
    assert knowing["press_gzsl"] == plain["press_gzsl"] and knowing["press_gzsl"]["acc_t"] == 1.0
    assert knowing["all"]["right"] < plain["all"]["right"]  # per item, twill refuses denim's pieces: its price

    def summary(right, mis):
        return {"all": {"right": right, "mis-sort": mis}, "by_kind": {"off-scene": {"right": 1 - mis, "mis-sort": mis}}}

    sd = [{"test": {"pressed_strangers": {"unaware": summary(0.7, u), "knowing": summary(0.7, k)}}}
          for u, k in ((0.02, 0.01), (0.01, 0.01), (0.03, 0.02))]
    line = stranger_lines(sd)[0]
    assert "mis-sorts -0.7 ± 0.6 points paired by split, fewer in 2, more in 0" in line  # sample sd of -1, 0, -1
    assert stranger_lines([{"test": {}}]) == []


def test_the_job_check_names_a_rival_the_bundle_knows_only_to_refuse():
    """denim's own picture cannot sort (cloth, a twin, is in the job) and the class nearest it is
    twill, a fabric the bundle knows only to refuse: the check says so, and that leaving twill out
    of a job changes nothing (no job can list it)."""
    from vs2t_edge.runtime import job_check as jc
    from vs2t_edge.runtime.evidence import Evidence
    from vs2t_edge.runtime.operating_point import scene_model_rule

    base = replace(model(), classes=CLASSES + ("cloth",), means=np.concatenate([MEANS, [[0.3, 0.0]]]))
    m, _ = with_known(base, np.full((20, 2), [0.05, 0.0]), np.zeros(20, int), ["twill"])
    scene = ["denim", "silk", "cloth"]
    conf, opts = scene_model_rule(m)
    checks = {c.fabric: c for c in jc.check_job(m, scene, lambda: Evidence(scene, conf, 5, **opts), 5)}
    d = checks["denim"]
    assert not d.sorts and d.rival == "twill" and d.rival_refuse_only and not d.rival_in_job
    assert "nearest twill, a fabric the cell knows only to refuse, pressed in training and in no classifier" in d.describe()
    assert d.describe().endswith("no job can list that rival, so leaving it out changes nothing")
    assert checks["silk"].sorts and not checks["silk"].rival_refuse_only

"""The scene model's offset item rule (runtime/scene_model.py), the evidence that runs it, and the
vectorised search that chooses it (train/item_search.py) against the cell's own evidence."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.evidence import UNKNOWN, Evidence
from vs2t_edge.runtime.scene_model import SceneModel, SceneModelError
from vs2t_edge.train import decision as dc
from vs2t_edge.train import item_search as ns

D = 12


def _world(seed=0, n_touched=6, n_untouched=3, n_strangers=1, per=40, offset=2.0):
    """Fabrics as blobs; the generator's means for untouched fabrics are off by a per-fabric offset."""
    rng = np.random.default_rng(seed)
    n = n_touched + n_untouched + n_strangers
    centres = rng.normal(0, 3.0, (n, D))
    presses = {f"f{i}": centres[i] + rng.normal(0, 1, (per, D)) for i in range(n)}
    touched = [f"f{i}" for i in range(n_touched)]
    untouched = [f"f{i}" for i in range(n_touched, n_touched + n_untouched)]
    strangers = [f"f{i}" for i in range(n_touched + n_untouched, n)]
    tx = np.concatenate([presses[f][:per // 2] for f in touched])
    ty = np.repeat(np.arange(n_touched), per // 2)
    sx = np.concatenate([centres[n_touched + j] + offset * rng.normal(0, 1, D) + rng.normal(0, 1, (50, D))
                         for j in range(n_untouched)])
    sy = np.repeat(np.arange(n_untouched), 50)
    model = SceneModel.fit(tx, ty, touched, sx, sy, untouched, k=8)
    held = {f: (x[per // 2:] if f in touched else x) for f, x in presses.items()}
    return model, held, touched, untouched, strangers


def _offset(model, **kw):
    rule = dict(press_var=1.2, offset_var_touched=0.05, offset_var_untouched=0.6, item_temperature=4.0, item_bias=0.5)
    rule.update(kw)
    return replace(model, item_rule="offset", **rule)


def test_item_scores_follow_the_formula_and_a_synthesised_class_saturates():
    model, held, *_ = _world()
    m = _offset(model)
    z = m.project(held["f0"][:5])
    zbar, n = z.mean(0), len(z)
    v = np.where([c in m.untouched for c in m.classes], 0.6, 0.05) + 1.2 / n
    d2 = np.sum((zbar - m.means) ** 2, axis=1)
    expected = (-0.5 * d2 / v - 0.5 * m.k * np.log(v)) / 4.0 + 0.5 * np.array([c in m.untouched for c in m.classes])
    assert np.allclose(m.item_log_lik(zbar, n), expected)
    # a piece whose presses all sit at one point: its log odds of an untouched class against a
    # touched one settle (the generator's error does not shrink with presses) under the offset rule,
    # and grow with every press when neither class has an offset
    point = 0.5 * (m.means[0] + m.means[-1])
    gap = lambda mm, n: float(np.diff(mm.item_log_lik(point, n)[[0, -1]])[0])  # noqa: E731
    assert abs(gap(m, 20000) - gap(m, 10000)) < 0.01 * abs(gap(m, 10000))
    flat = _offset(model, offset_var_touched=0.0, offset_var_untouched=0.0, item_bias=0.0)
    assert gap(flat, 400) == pytest.approx(2 * gap(flat, 200), rel=1e-6)
    with pytest.raises(SceneModelError, match="0 presses"):
        m.item_log_lik(zbar, 0)


def test_offset_rule_parameters_round_trip_and_are_checked():
    model, held, *_ = _world()
    m = _offset(model)
    again = SceneModel.from_params(m.to_params())
    assert again.item_rule == "offset" and np.allclose(again.item_log_lik(m.means[2], 3), m.item_log_lik(m.means[2], 3))
    older = {k: v for k, v in model.to_params().items()
             if k not in ("item_rule", "press_var", "offset_var_touched", "offset_var_untouched", "item_temperature",
                          "item_bias")}
    assert SceneModel.from_params(older).item_rule == "sum"  # a file written before the rule: as it was
    p = m.to_params()
    for key, bad in (("item_rule", np.array("median")), ("press_var", 0.0), ("offset_var_untouched", -1.0),
                     ("item_temperature", math.inf)):
        with pytest.raises(SceneModelError):
            SceneModel.from_params({**p, key: bad})
    with pytest.raises(SceneModelError, match="lack 'item_bias'"):
        SceneModel.from_params({k: v for k, v in p.items() if k != "item_bias"})
    # refuse_early: written only when on (older files read as off), a boolean or refused
    assert "refuse_early" not in p and not SceneModel.from_params(p).refuse_early
    on = replace(m, refuse_early=True).to_params()
    assert SceneModel.from_params(on).refuse_early
    with pytest.raises(SceneModelError, match="refuse_early"):
        SceneModel.from_params({**on, "refuse_early": np.array(0.5)})


def test_the_evidence_runs_the_offset_rule_on_the_presses_projection():
    model, held, touched, untouched, _ = _world()
    m = _offset(model)
    scene = touched[:3] + untouched[:2]
    presses = so.scene_model_presses(m, held[touched[1]][:5])
    ev = Evidence(scene, 0.9, 5, item_model=m, known_margin=0.0)
    d = None
    for p in presses:
        d = ev.add(p)
        if d is not None:
            break
    assert d is not None and d.label == touched[1]
    # the same piece on a job that leaves its fabric out: a class the cell knows explains it better
    ev = Evidence(touched[2:4] + untouched[:1], 0.9, 5, item_model=m, known_margin=0.0)
    d = None
    for p in presses:
        d = ev.add(p) or d
    d = d or ev.decide()
    assert d.label == UNKNOWN and d.stopped_by == "off_scene"
    with pytest.raises(ValueError, match="scene_z"):
        Evidence(scene, 0.9, 5, item_model=m).add(so.Press(presses[0].log_posterior, presses[0].sq_distance))
    with pytest.raises(ValueError, match="no class"):
        Evidence(["nope"], 0.9, 5, item_model=m)


@pytest.mark.parametrize("rule", ["sum", "offset", "offset, likeness asked"])
def test_the_vectorised_search_decides_every_item_as_the_cells_evidence(rule):
    model, held, touched, untouched, strangers = _world(seed=3)
    scenes = so.draw_scenes(touched, untouched, tuple(strangers), 6, n_touched=3, n_untouched=2, n_off=2, seed=5)
    prepared = ns.Prepared.of(ns.draw_items(scenes, {f: model.project(x) for f, x in held.items()}, model.classes,
                                            seed=7), model)
    thresholds = np.quantile(prepared.d2.min(-1)[prepared.items.valid], [0.5, 1.0]).tolist() + [math.inf]
    settings = [(conf, margin, thr, early) for conf in (0.6, 0.95) for margin in (0.0, 2.0, math.inf)
                for thr in thresholds for early in (False, True)]
    refused_early = 0
    for conf, margin, thr, early in settings:
        common = dict(confidence=conf, untouched_confidence=0.8, known_margin=margin, open_threshold=thr,
                      refuse_early=early)
        if rule == "sum":
            cand = replace(model, temperature=2.0, untouched_bias=0.5, evidence_weight=0.5, **common)
            fast = ns.sum_rule(prepared, temperature=2.0, untouched_bias=0.5, weight=0.5, **common)
        else:
            likeness = 1.5 if "likeness" in rule else math.inf
            cand = replace(_offset(model, **common), likeness_ratio=likeness)
            fast = ns.offset_rule(prepared, press_var=1.2, offset_var_touched=0.05, offset_var_untouched=0.6,
                                  item_temperature=4.0, item_bias=0.5, likeness_ratio=likeness, **common)
        tables = {f: so.scene_model_presses(cand, x) for f, x in held.items()}  # the press posterior is cand's
        recs = so.simulate_scenes(scenes, tables, so.scene_evidence(cand), seed=7)
        assert [r.outcome for r in recs] == fast[0].tolist(), (conf, margin, thr, early)
        assert [r.presses for r in recs] == fast[1].tolist()
        assert ns.summary(prepared, *fast)["all"] == pytest.approx(so.summarise(recs)["all"])
        refused_early += early and sum(r.off_scene and r.presses < 5 for r in recs)
    assert refused_early > 0  # the early refusal was exercised, not only its absence


def test_the_decision_search_keeps_the_better_item_rule_on_validation_fabrics():
    rng = np.random.default_rng(11)
    n_t, n_v, n_u, per, d = 8, 4, 3, 30, 16
    centres = rng.normal(0, 3.0, (n_t + n_v + n_u, d))
    presses = [c + rng.normal(0, 1, (per, d)) for c in centres]
    train = np.concatenate([p[:20] for p in presses[:n_t]])
    train_y = np.repeat(np.arange(n_t), 20)
    val_t = np.concatenate([p[20:25] for p in presses[:n_t]]), np.repeat(np.arange(n_t), 5)

    def synth(rows):  # the generator: each fabric's mean off by its own error
        x = np.concatenate([centres[i] + 1.5 * rng.normal(0, 1, d) + rng.normal(0, 1, (40, d)) for i in rows])
        return x, np.repeat(np.arange(len(rows)), 40)
    vals = [f"v{j}" for j in range(n_v)]
    val_presses = np.concatenate(presses[n_t:n_t + n_v]), np.repeat(np.arange(n_v), per)
    touched, untouched = [f"t{j}" for j in range(n_t)], [f"u{j}" for j in range(n_u)]
    model, report = dc.fit_scene_decision(train, train_y, touched, val_t, vals, val_presses,
                                          synth(range(n_t, n_t + n_v)), untouched, synth(range(n_t + n_v, n_t + n_v + n_u)),
                                          seed=2)
    rules = report["item_rules"]
    assert set(rules) == {"sum", "offset"}
    score = {r: dc._score({"all": {"mis-sort": v["mis_sort"], "right": v["right"]}}, 0.01) for r, v in rules.items()}
    assert report["chosen"]["item_rule"] == model.item_rule == max(score, key=score.get)
    # the item rules compared with every press as evidence; then the outlier ratio on the kept rule
    tried = report["outlier_ratios"]
    assert math.isinf(tried[0]["outlier_ratio"]) and tried[0]["right"] == rules[model.item_rule]["right"]
    kept = next(r for r in tried if r["outlier_ratio"] == model.outlier_ratio)
    assert report["validation"]["all"]["right"] == kept["right"] == max(
        (r for r in tried), key=lambda r: dc._score({"all": {"mis-sort": r["mis_sort"], "right": r["right"]}}, 0.01))["right"]
    assert model.classes == tuple(touched + untouched)  # deployed with the untouched fabrics' means
    again = SceneModel.from_params(model.to_params())
    assert again.item_rule == model.item_rule


def test_among_settings_that_sort_the_same_pieces_right_the_search_keeps_the_fewest_mis_sorts():
    """Where a class's pieces are never right on validation (a feature the generator cannot
    synthesise: the demo world with ``--tactile-feature shading_markers``), every confidence for it
    puts the same pieces in their bins, and the search's ``max`` kept the first - the lowest, which
    lets its pieces into wrong bins. ``fewer_mis_sorts`` keeps the one with the fewest; pieces in
    their bins still come first."""
    mis = {0.5: 0.008, 0.7: 0.004, 0.9: 0.004, 0.9999: 0.0}

    untouched_right, right_at = [0.0], {}

    def rank(q, bonus=0.0):
        right = 0.6 - (0.05 if q["confidence"] == 0.5 else 0.0) + (bonus if q["untouched_confidence"] == 0.5 else 0.0)
        s = {"all": {"right": right, "mis-sort": mis[q["untouched_confidence"]]},
             "by_kind": {"touched": {"right": 0.9},
                         "untouched": {"right": right_at.get(q["untouched_confidence"], untouched_right[0])}}}
        return dc._score(s, 0.01), s

    grid = {"untouched_confidence": tuple(mis), "confidence": (0.5, 0.9)}
    start = {"untouched_confidence": 0.5, "confidence": 0.9}
    assert max(grid["untouched_confidence"], key=lambda v: rank({**start, "untouched_confidence": v})[0]) == 0.5
    assert ns.fewer_mis_sorts(start, grid, rank) == {"untouched_confidence": 0.9999, "confidence": 0.9}
    # one more piece in its bin at the lowest confidence, within the target: that still wins
    assert ns.fewer_mis_sorts(start, grid, lambda q: rank(q, 0.001))["untouched_confidence"] == 0.5
    # where validation cannot tell the confidences apart at all and sorted no untouched piece right,
    # the highest (it sorts the fewest); where it sorted some right, the grid's first, as before
    mis.update({0.7: 0.008, 0.9: 0.008, 0.9999: 0.008})
    assert ns.fewer_mis_sorts(start, grid, rank)["untouched_confidence"] == 0.9999
    untouched_right[0] = 0.3
    assert ns.fewer_mis_sorts(start, grid, rank)["untouched_confidence"] == 0.5
    right_at.update({0.5: 0.0, 0.7: 0.0})  # right at some of the tied values is enough to keep the first
    assert ns.fewer_mis_sorts(start, grid, rank)["untouched_confidence"] == 0.5
    # the touched confidence: touched pieces were right, so a full tie keeps the first
    assert ns.fewer_mis_sorts({**start, "confidence": 0.5}, {"confidence": (0.5, 0.9)},
                              lambda q: rank({**q, "confidence": 0.9}))["confidence"] == 0.5


def test_the_mis_sort_target_is_what_the_validation_search_keeps_under():
    """``train --mis-sort-target``: none at all, or 2 % that buys pieces in their bin, on a world
    whose validation jobs cannot have both (the search is greedy: no monotone law is claimed)."""
    rng = np.random.default_rng(11)
    n_t, n_v, n_u, per, d = 8, 4, 3, 30, 16
    centres = rng.normal(0, 3.0, (n_t + n_v + n_u, d))
    presses = [c + rng.normal(0, 1, (per, d)) for c in centres]

    def synth(rows):  # the generator: each fabric's mean off by its own error
        x = np.concatenate([centres[i] + 1.5 * rng.normal(0, 1, d) + rng.normal(0, 1, (40, d)) for i in rows])
        return x, np.repeat(np.arange(len(rows)), 40)

    args = (np.concatenate([p[:20] for p in presses[:n_t]]), np.repeat(np.arange(n_t), 20),
            [f"t{j}" for j in range(n_t)],
            (np.concatenate([p[20:25] for p in presses[:n_t]]), np.repeat(np.arange(n_t), 5)),
            [f"v{j}" for j in range(n_v)], (np.concatenate(presses[n_t:n_t + n_v]), np.repeat(np.arange(n_v), per)),
            synth(range(n_t, n_t + n_v)), [f"u{j}" for j in range(n_u)], synth(range(n_t + n_v, n_t + n_v + n_u)))
    (strict, s_rep), (loose, l_rep) = (dc.fit_scene_decision(*args, seed=2, target_mis_sort=t) for t in (0.0001, 0.02))
    s_val, l_val = s_rep["validation"]["all"], l_rep["validation"]["all"]
    assert (s_rep["target_mis_sort"], l_rep["target_mis_sort"]) == (0.0001, 0.02)
    assert s_val["mis-sort"] == 0.0 and 0.0 < l_val["mis-sort"] <= 0.02 and l_val["right"] > s_val["right"]


def test_train_refuses_a_mis_sort_target_that_is_no_percentage(tmp_path, capsys):
    from test_bundle_fixtures import tiny_world

    from vs2t_edge.cli import main
    from vs2t_edge.train.run import train

    for bad in ("0", "100", "-1"):
        assert main(["train", str(tiny_world()), "--profile", "tiny", "--out", str(tmp_path / "r"),
                     "--mis-sort-target", bad]) == 2
        assert "--mis-sort-target" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
    with pytest.raises(ValueError, match="mis_sort_target 1.5"):
        train(tiny_world(), tmp_path / "r", "tiny", mis_sort_target=1.5)

"""The likeness rule of the offset item rule (runtime/scene_model.py ``likeness_ratio``): a piece
goes into a class's bin only when its presses' mean lies about where that class's own pieces lie,
whatever the posterior says; the evidence runs it, the vectorised search prices it
(test_item_rule.py holds the two equal), and the bundle stores it."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.evidence import UNKNOWN, Evidence
from vs2t_edge.runtime.scene_model import SceneModel, SceneModelError

D = 12


def _model(seed=0):
    """Four touched fabrics as blobs of unit spread, and one untouched fabric whose real presses lie
    one and a half press spreads from touched t0 while the generator synthesised it at t1."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(0, 6.0, (4, D))
    touched = [f"t{i}" for i in range(4)]
    tx = np.concatenate([c + rng.normal(0, 1, (60, D)) for c in centres])
    ty = np.repeat(np.arange(4), 60)
    real_u = centres[0] + 1.5 * rng.normal(0, 1, D)
    synth = centres[1] + rng.normal(0, 1, (80, D))  # the generator's miss
    model = SceneModel.fit(tx, ty, touched, synth, np.zeros(80, int), ["u0"], k=8, shrinkage=0.0)
    model = replace(model, item_rule="offset", press_var=1.0, offset_var_touched=0.0, offset_var_untouched=0.5,
                    item_temperature=1.0, item_bias=0.0)
    pieces = {"u0": real_u + rng.normal(0, 1, (5, D)), "t0": centres[0] + rng.normal(0, 1, (5, D))}
    return model, touched, pieces


def _decide(model, scene, x):
    ev = Evidence(scene, 0.9, 5, item_model=model)
    for p in so.scene_model_presses(model, x):
        d = ev.add(p)
        if d is not None:
            return d
    return ev.decide()


def test_item_ratios_are_the_distance_over_what_the_class_s_own_pieces_lie_at():
    model, _, pieces = _model()
    z = model.project(pieces["t0"])
    zbar, n = z.mean(0), len(z)
    v = np.where([c in model.untouched for c in model.classes], 0.5, 0.0) + 1.0 / n
    expected = np.sum((zbar - model.means) ** 2, axis=1) / (model.k * v)
    assert np.allclose(model.item_ratios(zbar, n), expected)
    # a piece of t0 lies about where t0's own pieces lie; a piece of u0 several times farther
    assert model.item_ratios(zbar, n)[0] < 2.0
    zu = model.project(pieces["u0"])
    assert model.item_ratios(zu.mean(0), n)[0] > 4.0
    with pytest.raises(SceneModelError, match="0 presses"):
        model.item_ratios(zbar, 0)


def test_a_piece_that_leads_a_class_it_does_not_feel_like_goes_to_the_reject_bin():
    model, touched, pieces = _model()
    scene = touched + ["u0"]
    # without the rule the untouched piece goes, confident, into touched t0's bin: a mis-sort
    wrong = _decide(model, scene, pieces["u0"])
    assert wrong.label == "t0" and wrong.stopped_by == "confident"
    asked = replace(model, likeness_ratio=3.0)
    refused = _decide(asked, scene, pieces["u0"])
    assert refused.label == UNKNOWN and refused.stopped_by == "off_scene" and refused.presses == 5
    z = asked.project(pieces["u0"])  # refused at every press: at each, its leader t0 is too far
    assert all(asked.item_ratios(z[:n].mean(0), n)[0] > 3.0 for n in range(1, 6))
    # a piece of t0 itself still goes into t0's bin, as confident as without the rule
    right = _decide(asked, scene, pieces["t0"])
    assert right.label == "t0" and right.stopped_by == "confident"
    assert right.presses == _decide(model, scene, pieces["t0"]).presses
    # the rule reads the leader: a ratio no piece reaches refuses nothing
    assert _decide(replace(model, likeness_ratio=1e9), scene, pieces["u0"]).label == "t0"


def test_the_likeness_ratio_is_stored_only_when_asked_and_checked_on_load():
    model, _, _ = _model()
    p = model.to_params()
    assert "likeness_ratio" not in p and math.isinf(SceneModel.from_params(p).likeness_ratio)  # older files: off
    on = replace(model, likeness_ratio=3.0).to_params()
    assert SceneModel.from_params(on).likeness_ratio == 3.0
    for bad, match in ((0.5, "at least 1"), (np.array("3"), "not a number"), (np.array([3.0, 4.0]), "not a number")):
        with pytest.raises(SceneModelError, match=match):
            SceneModel.from_params({**on, "likeness_ratio": bad})

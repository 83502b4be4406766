"""Property tests of the evidence rule: order of presses, scene restriction, stopping."""
from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vs2t_edge.runtime.evidence import UNKNOWN, Evidence
from vs2t_edge.runtime.inference import PressScore

CLASSES = ("a", "b", "c", "d")
press = st.lists(st.floats(-50, 0), min_size=4, max_size=4)


def _s(v):
    return PressScore(dict(zip(CLASSES, v)), 0.0, False, 0.0)


@given(st.lists(press, min_size=1, max_size=12), st.randoms())
@settings(max_examples=80, deadline=None)
def test_order_of_presses_does_not_change_the_posterior(presses, rnd):
    a = Evidence(CLASSES, confidence=1.0, max_presses=len(presses) + 1)
    b = Evidence(CLASSES, confidence=1.0, max_presses=len(presses) + 1)
    shuffled = list(presses)
    rnd.shuffle(shuffled)
    for p, q in zip(presses, shuffled):
        a.add(_s(p))
        b.add(_s(q))
    da, db = a.decide(), b.decide()
    for c in CLASSES:
        assert math.isclose(da.log_posterior[c], db.log_posterior[c], rel_tol=1e-9, abs_tol=1e-9)


@given(st.lists(press, min_size=1, max_size=6))
@settings(max_examples=80, deadline=None)
def test_scene_restriction_is_renormalisation(presses):
    ev = Evidence(["b", "d"], confidence=1.0, max_presses=10)
    for p in presses:
        ev.add(_s(p))
    d = ev.decide()
    acc = np.sum([[p[1], p[3]] for p in presses], axis=0)
    want = acc - (acc.max() + math.log(np.exp(acc - acc.max()).sum()))
    assert set(d.log_posterior) == {"b", "d"}
    assert np.allclose([d.log_posterior["b"], d.log_posterior["d"]], want, atol=1e-9)


@given(st.lists(press, min_size=9, max_size=9), st.floats(0.5, 0.999))
@settings(max_examples=80, deadline=None)
def test_stops_exactly_when_confident_or_at_the_limit(presses, conf):
    ev = Evidence(CLASSES, confidence=conf, max_presses=9)
    for k, p in enumerate(presses, 1):
        d = ev.add(_s(p))
        if d is not None:
            break
    assert d is not None and d.presses == k
    if d.stopped_by == "confident":
        assert d.confidence >= conf and d.label in CLASSES
    else:
        assert k == 9 and d.label == UNKNOWN and d.confidence < conf

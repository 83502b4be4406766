"""Each router's threshold tuning on synthetic scores with a known optimum (beta chosen on
validation only), and the beta = +-inf extremes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime import router_eval as reval


def test_balanced_threshold_known_optimum():
    # touched 0..9, untouched 7..16: every gap from (6,7) to (9,10) scores 0.85 on the balanced
    # rule (e.g. kept 0.7 + flagged 1.0, or kept 0.8 + flagged 0.9); ties go to the lowest: 6.5.
    t = np.arange(10.0)
    u = np.arange(7.0, 17.0)
    assert reval.tune_threshold(t, u) == pytest.approx(6.5)


def test_balanced_threshold_weights_each_side_equally():
    # 100 touched at 0, 1 untouched at 1, 1 untouched at -1: the balanced rule flags the one
    # at 1 (gain 0.25) without losing touched; accuracy objective gives the same gap.
    t = np.zeros(100)
    u = np.array([-1.0, 1.0])
    beta = reval.tune_threshold(t, u)
    assert beta == pytest.approx(0.5)
    kept, flagged = reval.threshold_rates(t, u, [beta])
    assert kept[0] == 1.0 and flagged[0] == 0.5


def test_target_false_untouched():
    t = np.linspace(0, 1, 101)  # 101 touched presses
    u = np.linspace(0.5, 2, 50)
    beta = reval.tune_threshold(t, u, target_false_untouched=0.05)
    kept, flagged = reval.threshold_rates(t, u, [beta])
    assert 1 - kept[0] <= 0.05 and 1 - kept[0] > 0.03
    # the next lower gap would exceed the budget
    assert np.sum(t > beta) == 5


def test_separated_scores_give_beta_between_the_groups():
    assert reval.tune_threshold([1, 2, 3], [10, 11]) == pytest.approx(6.5)
    # reversed groups (touched scores above untouched): no finite gap does better than routing all
    # one way (balanced score 0.5); the tie goes to the lowest beta, -inf: everything flagged
    t, u = [10, 11], [1, 2, 3]
    b = reval.tune_threshold(t, u)
    assert b == -np.inf
    kept, flagged = reval.threshold_rates(t, u, [b])
    assert (kept[0], flagged[0]) == (0.0, 1.0)
    k, f = reval.threshold_rates(t, u, [0.5, 1.5, 2.5, 6.5, 10.5, 11.5])
    assert np.all(0.5 * (k + f) <= 0.5)


def test_beta_extremes_route_all_or_none():
    nov = np.array([-1e300, -5.0, 0.0, 7.0, 1e300])
    assert not nv.route_untouched(nov, np.inf).any()
    assert nv.route_untouched(nov, -np.inf).all()
    with pytest.raises(nv.RouterError):
        nv.route_untouched(np.array([np.nan]), 0.0)
    with pytest.raises(nv.RouterError):
        nv.route_untouched(nov, np.nan)


def _synthetic_world(seed=0, n=300, d=24, n_t=4, n_u=3):
    """Touched classes near the origin, untouched further out; logits from a nearest-mean head."""
    rng = np.random.default_rng(seed)
    centres_t = rng.normal(size=(n_t, d)) * 2.0
    # untouched fabrics lie between touched ones (ambiguous for a touched head, as in practice)
    # and off to the side of them (far for a density)
    pairs = [(i, (i + 1) % n_t) for i in range(n_u)]
    centres_u = np.array([(centres_t[a] + centres_t[b]) / 2 for a, b in pairs])
    centres_u += rng.normal(size=centres_u.shape) * 1.5
    yt = rng.integers(0, n_t, n)
    yu = rng.integers(0, n_u, n)
    xt = centres_t[yt] + rng.normal(size=(n, d))
    xu = centres_u[yu] + rng.normal(size=(n, d))

    def head(x, centres):
        return -0.5 * ((x[:, None, :] - centres[None]) ** 2).sum(-1) / 4.0

    return xt, xu, head, centres_t, centres_u, yt


@pytest.mark.parametrize("name", nv.ROUTERS)
def test_each_router_tuned_on_validation_separates_test(name):
    xt, xu, head, ct, cu, yt = _synthetic_world()
    train, val_t, test_t = xt[:100], xt[100:200], xt[200:]
    val_u, test_u = xu[:150], xu[150:]  # validation fabrics stand in for untouched ones
    r = nv.fit_router(name, train, head(train, ct), touched_labels=yt[:100])

    def nov(x):
        return r.novelty(x, head(x, ct), logits_u=head(x, cu))

    beta = reval.tune_threshold(nov(val_t), nov(val_u))
    assert np.isfinite(beta)
    kept, flagged = reval.threshold_rates(nov(test_t), nov(test_u), [beta])
    assert 0.5 * (kept[0] + flagged[0]) > 0.9, (name, kept, flagged)
    assert reval.auroc(nov(test_t), nov(test_u)) > 0.95


@settings(max_examples=60, deadline=None)
@given(
    t=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=1, max_size=30),
    u=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=1, max_size=30),
)
def test_tuned_beta_is_optimal_among_all_gaps(t, u):
    """Property: no beta does better on the balanced objective than the one chosen."""
    beta = reval.tune_threshold(t, u)
    kept, flagged = reval.threshold_rates(t, u, [beta])
    best = 0.5 * (kept[0] + flagged[0])
    cand = np.concatenate([[-np.inf, np.inf], np.asarray(t), np.asarray(u)])
    k, f = reval.threshold_rates(t, u, cand)
    assert best >= np.max(0.5 * (k + f)) - 1e-12
    assert best >= 0.5 - 1e-12  # never worse than "all touched"


@example(t=[100.0], u=[99.99999999999999])  # one ulp apart: the midpoint rounds onto the upper value
@settings(max_examples=40, deadline=None)
@given(
    t=st.lists(st.floats(-100, 100, allow_nan=False), min_size=1, max_size=20),
    u=st.lists(st.floats(-100, 100, allow_nan=False), min_size=1, max_size=20),
)
def test_ausuc_is_within_unit_square_and_dominated_by_perfect(t, u):
    ones_t, ones_u = np.ones(len(t), bool), np.ones(len(u), bool)
    a = reval.ausuc(t, ones_t, u, ones_u)
    assert -1e-12 <= a <= 1 + 1e-12
    # with every head wrong no operating point classifies anything: the curve is 0
    assert reval.ausuc(t, ~ones_t, u, ~ones_u) == 0.0
    # with perfect heads AUSUC equals the AUROC of the router (ties count half)
    assert a == pytest.approx(reval.auroc(t, u), abs=1e-9)

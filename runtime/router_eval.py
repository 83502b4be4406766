"""A router's beta and its scores: the threshold that routes a press to CLS_u, and the GZSL numbers.

``runtime/novelty.py`` gives each press a novelty score (higher = more likely untouched); this
module chooses the threshold and measures it (``novelty.route_untouched`` applies it):
``tune_threshold`` (beta from touched and validation presses, never untouched ones),
``threshold_rates`` and ``seen_unseen_curve`` / ``ausuc`` / ``auroc`` (how well a router separates
them) and ``gzsl_accuracies`` (acc_t, acc_u and H at one beta); and the gate's softness around beta
(``fit_gating_temperature``, ``gating_scale``) that export ships and the comparison uses. Numpy
only: the cell's calibration uses it.
"""

from __future__ import annotations

import math

import numpy as np

from vs2t_edge.runtime.novelty import RouterError


def _clean(a: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    if a.size == 0:
        raise RouterError(f"{what} is empty")
    if np.any(np.isnan(a)):
        raise RouterError(f"{what} contains NaN")
    return a


def _gap_thresholds(values: np.ndarray) -> np.ndarray:
    """One beta per gap of the sorted unique values: -inf, midpoints, +inf. A beta routes
    novelty <= beta as touched, so each must lie below the gap's upper value: where the midpoint of
    two neighbouring floats rounds up onto it (values one ulp apart), the lower value stands in."""
    u = np.unique(values)
    with np.errstate(over="ignore", invalid="ignore"):
        mids = u[:-1] + 0.5 * (u[1:] - u[:-1])  # avoids (a+b) overflow near float max
    mids = np.where(np.isfinite(mids) & (mids < u[1:]), mids, u[:-1])
    return np.concatenate([[-np.inf], mids, [np.inf]])


def threshold_rates(novelty_touched, novelty_untouched, betas) -> tuple[np.ndarray, np.ndarray]:
    """(fraction of touched kept touched, fraction of untouched flagged untouched) per beta."""
    t = np.sort(_clean(novelty_touched, "novelty_touched"))
    u = np.sort(_clean(novelty_untouched, "novelty_untouched"))
    betas = np.asarray(betas, dtype=np.float64)
    kept = np.searchsorted(t, betas, side="right") / t.size  # novelty <= beta
    flagged = 1.0 - np.searchsorted(u, betas, side="right") / u.size  # novelty > beta
    return kept, flagged


def tune_threshold(
    novelty_touched: np.ndarray,
    novelty_untouched: np.ndarray,
    objective: str = "balanced",
    target_false_untouched: float | None = None,
) -> float:
    """Choose beta on validation data (touched presses vs. presses of validation fabrics).

    - ``"balanced"`` (the paper's rule): maximise the mean of the fraction of touched presses
      kept as touched and the fraction of validation presses flagged untouched.
    - ``"accuracy"``: maximise the fraction of all presses routed correctly.
    - ``"target"`` (or any objective with ``target_false_untouched`` given): flag as many
      validation presses as possible while at most ``target_false_untouched`` of the touched
      presses are flagged untouched.

    beta is taken in the middle of the winning gap between observed scores (so it does not sit
    on a sample), -inf / +inf at the ends; ties go to the lowest such beta.
    """
    t = _clean(novelty_touched, "novelty_touched")
    u = _clean(novelty_untouched, "novelty_untouched")
    betas = _gap_thresholds(np.concatenate([t, u]))
    kept, flagged = threshold_rates(t, u, betas)
    # Integer counts for the comparisons, so float rounding never breaks a tie the wrong way.
    kept_n = np.rint(kept * t.size).astype(np.int64)
    flagged_n = np.rint(flagged * u.size).astype(np.int64)
    if target_false_untouched is not None or objective == "target":
        if target_false_untouched is None:
            raise RouterError("objective 'target' needs target_false_untouched")
        if not 0.0 <= target_false_untouched <= 1.0:
            raise RouterError(f"target_false_untouched must be in [0, 1], got {target_false_untouched}")
        ok = (t.size - kept_n) <= np.floor(target_false_untouched * t.size + 1e-9)
        score = np.where(ok, flagged_n, -1)
    elif objective == "balanced":
        score = kept_n * u.size + flagged_n * t.size  # = 2 |t| |u| x mean of the two rates
    elif objective == "accuracy":
        score = kept_n + flagged_n
    else:
        raise RouterError(f"unknown threshold objective '{objective}'; use balanced, accuracy or target")
    return float(betas[int(np.argmax(score))])


def _class_weights(labels: np.ndarray | None, n: int) -> np.ndarray:
    """Weights that make a sum over samples the per-class mean accuracy."""
    if labels is None:
        return np.full(n, 1.0 / n)
    labels = np.asarray(labels).reshape(-1)
    if labels.size != n:
        raise RouterError(f"{labels.size} labels for {n} samples")
    classes, inverse, counts = np.unique(labels, return_inverse=True, return_counts=True)
    return 1.0 / (counts[inverse] * classes.size)


def seen_unseen_curve(
    novelty_touched: np.ndarray,
    correct_touched: np.ndarray,
    novelty_untouched: np.ndarray,
    correct_untouched: np.ndarray,
    labels_touched: np.ndarray | None = None,
    labels_untouched: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The seen-unseen accuracy curve (Chao et al. 2016) swept over beta.

    ``correct_touched[i]``: CLS_t classifies touched test press i correctly (if routed to it);
    ``correct_untouched[j]``: CLS_u classifies untouched press j correctly. A press counts only
    when routed to the right head. With labels the accuracies are per-class means (as the
    paper's acc_t / acc_u). Returns (acc_untouched, acc_touched, betas) with acc_untouched
    non-decreasing, from beta=+inf (everything touched) to beta=-inf (everything untouched).
    """
    nt = _clean(novelty_touched, "novelty_touched")
    nu = _clean(novelty_untouched, "novelty_untouched")
    ct = np.asarray(correct_touched, dtype=bool).reshape(-1)
    cu = np.asarray(correct_untouched, dtype=bool).reshape(-1)
    if ct.size != nt.size or cu.size != nu.size:
        raise RouterError("correct_* must have one entry per novelty score")
    wt = _class_weights(labels_touched, nt.size) * ct
    wu = _class_weights(labels_untouched, nu.size) * cu
    betas = _gap_thresholds(np.concatenate([nt, nu]))[::-1]  # +inf first
    order_t = np.argsort(nt)
    cum_t = np.concatenate([[0.0], np.cumsum(wt[order_t])])
    order_u = np.argsort(nu)
    cum_u = np.concatenate([[0.0], np.cumsum(wu[order_u])])
    k_t = np.searchsorted(nt[order_t], betas, side="right")
    k_u = np.searchsorted(nu[order_u], betas, side="right")
    acc_t = cum_t[k_t]  # touched with novelty <= beta and correct
    acc_u = cum_u[-1] - cum_u[k_u]  # untouched with novelty > beta and correct
    return acc_u, acc_t, betas


def ausuc(*args, **kwargs) -> float:
    """Area under the seen-unseen curve (x = acc_untouched, y = acc_touched), trapezoid rule.

    Same arguments as ``seen_unseen_curve``. 1.0 = a router and heads that are perfect.
    """
    acc_u, acc_t, _ = seen_unseen_curve(*args, **kwargs)
    return float(np.sum(np.diff(acc_u) * 0.5 * (acc_t[1:] + acc_t[:-1])))


def auroc(novelty_touched: np.ndarray, novelty_untouched: np.ndarray) -> float:
    """P(novelty of an untouched press > that of a touched press), ties counting half."""
    t = _clean(novelty_touched, "novelty_touched")
    u = _clean(novelty_untouched, "novelty_untouched")
    allv = np.concatenate([t, u])
    # average ranks (1-based) with ties shared: Mann-Whitney U
    order = np.argsort(allv, kind="mergesort")
    sorted_v = allv[order]
    ranks = np.empty(allv.size, dtype=np.float64)
    uniq, first, counts = np.unique(sorted_v, return_index=True, return_counts=True)
    avg = first + (counts + 1) / 2.0
    ranks[order] = np.repeat(avg, counts)
    r_u = float(np.sum(ranks[t.size:]))
    return (r_u - u.size * (u.size + 1) / 2.0) / (t.size * u.size)


def gzsl_accuracies(
    untouched_mask_touched: np.ndarray,
    correct_touched: np.ndarray,
    untouched_mask_untouched: np.ndarray,
    correct_untouched: np.ndarray,
    labels_touched: np.ndarray | None = None,
    labels_untouched: np.ndarray | None = None,
) -> dict[str, float]:
    """acc_t, acc_u (per-class means when labels given) and their harmonic mean H at one beta."""
    wt = _class_weights(labels_touched, np.asarray(correct_touched).size)
    wu = _class_weights(labels_untouched, np.asarray(correct_untouched).size)
    acc_t = float(np.sum(wt * (np.asarray(correct_touched, bool) & ~np.asarray(untouched_mask_touched, bool))))
    acc_u = float(np.sum(wu * (np.asarray(correct_untouched, bool) & np.asarray(untouched_mask_untouched, bool))))
    h = 0.0 if acc_t + acc_u == 0 else 2 * acc_t * acc_u / (acc_t + acc_u)
    return {"acc_t": acc_t, "acc_u": acc_u, "H": h}


# --- the gate's softness: how sure a press is of its route (runtime/inference.gzsl_log_posterior) ---

def gating_scale(novelty: np.ndarray) -> float:
    """s of the gate's g(n) = asinh(n / s): the typical magnitude of touched presses' scores."""
    n = np.abs(np.asarray(novelty, np.float64))
    s = float(np.median(n)) if n.size else 1.0
    return s if s > 0 and math.isfinite(s) else 1.0


def fit_gating_temperature(nov_touched: np.ndarray, nov_untouched: np.ndarray, beta: float,
                           scale: float | None = None) -> float:
    """T of P(untouched|x) = sigmoid((g(novelty) - g(beta)) / T), g = asinh(. / scale) (identity
    when scale is None), by maximum likelihood of the route labels (touched presses 0,
    validation-fabric presses 1) with the offset fixed at g(beta): the hard decision stays the
    tuned operating point and only its softness is learned. Log-grid search (the likelihood is
    unimodal in log T), then golden-section refinement."""
    from vs2t_edge.runtime.inference import gate_logit

    t = np.asarray(nov_touched, np.float64)
    u = np.asarray(nov_untouched, np.float64)
    if t.size == 0 or u.size == 0 or not math.isfinite(beta):
        return robust_temperature(np.concatenate([t, u]) if t.size + u.size else np.zeros(1), scale)
    d = gate_logit(np.concatenate([t, u]), beta, 1.0, scale)
    y = np.concatenate([np.zeros(t.size), np.ones(u.size)])
    spread = max(float(np.median(np.abs(d))), 1e-12)

    def nll(log_t: float) -> float:
        z = d / math.exp(log_t)
        # -log sigmoid(z) for y=1, -log sigmoid(-z) for y=0, stably
        return float(np.mean(np.where(y > 0, np.logaddexp(0, -z), np.logaddexp(0, z))))

    grid = np.log(spread) + np.linspace(-12, 6, 73)
    vals = [nll(g) for g in grid]
    k = int(np.argmin(vals))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    for _ in range(40):
        m1, m2 = lo + 0.382 * (hi - lo), lo + 0.618 * (hi - lo)
        if nll(m1) < nll(m2):
            hi = m2
        else:
            lo = m1
    return float(math.exp(0.5 * (lo + hi)))


def robust_temperature(novelty: np.ndarray, scale: float | None = None) -> float:
    """Fallback T without validation presses: the spread (1.4826 MAD) of the gate's input."""
    n = np.asarray(novelty, np.float64)
    if scale is not None:
        n = np.arcsinh(n / scale)
    mad = 1.4826 * float(np.median(np.abs(n - np.median(n))))
    return mad if mad > 0 else max(float(np.max(np.abs(n))), 1.0) * 1e-3

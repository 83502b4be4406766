"""Covariance estimators the novelty routers share (runtime/novelty.py), numpy only, float64.

Written from their papers (no sklearn on the cell): the empirical covariance, the Ledoit & Wolf
(2004) and Oracle Approximating (Chen, Wiesel, Eldar & Hero 2010) shrinkage amounts, a covariance
shrunk towards a multiple of the identity by either; and, for class-conditional routers, the
pooled within-class covariance shrunk the same way and whitened (``within_class_whitening``) and
Fisher's discriminant subspace of the classes under it (``discriminant_subspace``).
"""

from __future__ import annotations

import numpy as np


def empirical_covariance(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, maximum-likelihood covariance S = Xc^T Xc / n) in float64."""
    x = np.asarray(x, dtype=np.float64)
    mean = x.mean(axis=0)
    xc = x - mean
    return mean, (xc.T @ xc) / x.shape[0]


def ledoit_wolf_shrinkage(xc: np.ndarray) -> float:
    """Ledoit & Wolf (2004) optimal shrinkage of S towards mu*I for centred samples xc (n, p).

    With S = Xc^T Xc / n, mu = tr(S)/p, d^2 = ||S - mu I||_F^2 / p,
    b_bar^2 = 1/n^2 sum_k ||x_k x_k^T - S||_F^2 / p, b^2 = min(b_bar^2, d^2); shrinkage = b^2/d^2.
    The sums are taken through the n x n Gram matrix and row norms, never a p x p x n tensor:
    sum_k ||x_k x_k^T - S||_F^2 = sum_k ||x_k||^4 - n ||S||_F^2.
    """
    xc = np.asarray(xc, dtype=np.float64)
    n, p = xc.shape
    gram = xc @ xc.T  # ||S||_F^2 = ||Xc Xc^T||_F^2 / n^2, cheaper when n < p
    s_fro2 = float(np.sum(gram * gram)) / n**2
    mu = float(np.trace(gram)) / (n * p)
    d2 = (s_fro2 - 2.0 * mu * mu * p + mu * mu * p) / p  # ||S - mu I||^2 = ||S||^2 - p mu^2
    row_norm2 = np.diag(gram)
    b_bar2 = (float(np.sum(row_norm2**2)) - n * s_fro2) / (n**2 * p)
    b2 = min(max(b_bar2, 0.0), d2)
    if d2 <= 0.0:
        return 1.0  # S is already a multiple of the identity
    return float(b2 / d2)


def oas_shrinkage(xc: np.ndarray) -> float:
    """Oracle Approximating Shrinkage, Chen et al. (2010) eq. 23, for centred samples xc (n, p).

    rho = min( ((1 - 2/p) tr(S^2) + tr(S)^2) / ((n + 1 - 2/p) (tr(S^2) - tr(S)^2 / p)), 1 ).
    """
    xc = np.asarray(xc, dtype=np.float64)
    n, p = xc.shape
    gram = xc @ xc.T
    tr_s = float(np.trace(gram)) / n
    tr_s2 = float(np.sum(gram * gram)) / n**2
    den = (n + 1.0 - 2.0 / p) * (tr_s2 - tr_s * tr_s / p)
    if den <= 0.0:
        return 1.0
    num = (1.0 - 2.0 / p) * tr_s2 + tr_s * tr_s
    return float(min(max(num / den, 0.0), 1.0))


def shrunk_covariance(x: np.ndarray, estimator: str) -> tuple[np.ndarray, np.ndarray, float]:
    """(mean, covariance, shrinkage) for estimator in {"empirical", "ledoit_wolf", "oas"}."""
    mean, s = empirical_covariance(x)
    if estimator == "empirical":
        return mean, s, 0.0
    xc = np.asarray(x, dtype=np.float64) - mean
    if estimator == "ledoit_wolf":
        shrink = ledoit_wolf_shrinkage(xc)
    elif estimator == "oas":
        shrink = oas_shrinkage(xc)
    else:
        raise ValueError(f"unknown covariance estimator '{estimator}'")
    mu = float(np.trace(s)) / s.shape[0]
    cov = (1.0 - shrink) * s
    cov[np.diag_indices_from(cov)] += shrink * mu
    return mean, cov, shrink


def within_class_whitening(x: np.ndarray, y: np.ndarray, n_classes: int,
                           variance_floor: float = 1e-6) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(class means (C, D), W (D, D), shrinkage, floor) for samples ``x`` (N, D) with labels ``y`` in
    0..C-1: W W^T is the inverse of the pooled within-class covariance (residuals from each class's
    mean, over all N), shrunk towards a multiple of the identity by the Ledoit-Wolf amount of those
    residuals - estimated from the samples, so no knob is tuned. Eigenvalues below ``variance_floor``
    x the largest are raised to it: directions in which every class's samples agree exactly (a
    tiny set, a dead channel) stay finite."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y)
    means = np.stack([x[y == c].mean(0) for c in range(n_classes)])
    r = x - means[y]
    cov = r.T @ r / len(x)
    shrink = ledoit_wolf_shrinkage(r)
    mean_variance = float(np.trace(cov)) / len(cov)
    cov *= 1.0 - shrink
    cov[np.diag_indices_from(cov)] += shrink * mean_variance
    w, u = np.linalg.eigh(0.5 * (cov + cov.T))
    top = float(w.max())
    # no spread within any class at all: every direction gets the same floor, relative to the features' size
    scale = top if top > 0 else float(np.mean(x * x))
    floor = max(variance_floor * scale, 1e-30)
    return means, u / np.sqrt(np.maximum(w, floor)), float(shrink), floor


def discriminant_subspace(x: np.ndarray, y: np.ndarray, n_classes: int,
                          variance_floor: float = 1e-6) -> dict:
    """Fisher's discriminant subspace of ``n_classes`` classes: the ``n_classes - 1`` directions of
    largest between- over within-class variance, the within-class covariance whitened and shrunk as
    ``within_class_whitening``, so every class there is a unit Gaussian. Returns ``centre`` (D,) the
    mean of the class means, ``projection`` (D, K) = W times the subspace's basis, ``class_means``
    (C, K) = (means - centre) @ projection, ``shrinkage`` and ``floor``; a point x sits at
    (x - centre) @ projection. K = min(C - 1, D), at least 1."""
    means, w, shrink, floor = within_class_whitening(x, y, n_classes, variance_floor)
    centre = means.mean(0)
    _, _, vt = np.linalg.svd((means - centre) @ w, full_matrices=False)
    projection = w @ vt[:max(1, n_classes - 1)].T
    return {"centre": centre, "projection": projection, "class_means": (means - centre) @ projection,
            "shrinkage": shrink, "floor": floor}

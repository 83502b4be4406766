"""GZSL routers: decide whether a press comes from a touched fabric (CLS_t) or an untouched one (CLS_u).

Every router maps a press to a *novelty* score, HIGHER = more likely untouched, and the cell
predicts "untouched" when ``novelty > beta``. The same code fits the routers in training, is
serialised into the run folder and the bundle (``to_params`` / ``Router.from_params``), and
scores presses on the cell, so this module is numpy only (the cell never imports torch).

Routers (``ROUTERS``):

- ``gaussian`` — the paper's rule: a Gaussian fitted on touched tactile features, novelty is the
  negative log density. The empirical covariance of a 2048-d feature from a few hundred presses
  is singular (dead ReLU channels, collinear channels, n < d), so its eigenvalues are floored
  at ``variance_floor`` x the mean variance before inversion.
- ``mahalanobis_lw`` / ``mahalanobis_oas`` — the same density with a shrinkage covariance
  (Ledoit & Wolf 2004; Chen, Wiesel, Eldar & Hero 2010), novelty = squared Mahalanobis distance.
- ``discriminant`` — class Gaussians in Fisher's discriminant subspace of the touched classes: the
  pooled within-class covariance shrunk (Ledoit-Wolf) and whitened, the C - 1 directions that tell
  the C touched classes apart, novelty = the smallest squared distance to a touched class mean
  there. Needs the touched presses' class labels to fit (``fit_router(..., touched_labels=)``).
  With a few presses per class in a wide feature, a density over all of it is dominated by
  directions the presses never pinned down; this subspace keeps what separates the touched
  classes, and an unseen fabric lands far from every one of them (docs/realism.md).
- ``energy`` — novelty = -T * logsumexp(logits_t / T) (Liu et al. 2020).
- ``max_softmax`` — novelty = -max softmax(logits_t) (Hendrycks & Gimpel 2017).
- ``calibrated_stacking`` — (Chao et al. 2016) the all-class decision argmax[s_t - gamma, s_u];
  novelty = max(s_u) - max(s_t), so "untouched" iff novelty > beta with beta = -gamma.

Numerics: every fit is in float64; the covariance is factorised once at fit time (eigh) into a
whitening matrix W with W W^T = Sigma^-1 and the log-determinant is the sum of log-eigenvalues,
so scoring is a centring, one matmul and a squared norm. The squared norm is always summed in
float64 (with the float32 path the matmul runs in float32 and each row is rescaled before
squaring), which keeps float32 scores within ~1e-4 relative of the float64 reference for
feature norms from 1e-6 to 1e6 (tests/test_novelty_stability.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np

from vs2t_edge.runtime.covariance import discriminant_subspace, shrunk_covariance

ROUTERS: tuple[str, ...] = (
    "gaussian",
    "mahalanobis_lw",
    "mahalanobis_oas",
    "discriminant",
    "energy",
    "max_softmax",
    "calibrated_stacking",
)
# Gaussian densities of all touched features (``GaussianRouter``; a fused press graph folds them).
GAUSSIAN_ROUTERS: tuple[str, ...] = ("gaussian", "mahalanobis_lw", "mahalanobis_oas")
# Routers that need only the tactile feature (others need the heads' logits).
FEATURE_ROUTERS: tuple[str, ...] = (*GAUSSIAN_ROUTERS, "discriminant")

PARAMS_VERSION = 1
_LOG_2PI = float(np.log(2.0 * np.pi))


class RouterError(ValueError):
    """A router was asked something it cannot answer (bad shapes, missing logits, NaN)."""


# --------------------------------------------------------------------------------------------
# numerically stable pieces shared by the routers and the evidence code
# --------------------------------------------------------------------------------------------


def log_softmax(logits: np.ndarray, axis: int = -1) -> np.ndarray:
    """log softmax in float64, exact for logits of +-1e4 (subtract the max before exp)."""
    z = np.asarray(logits, dtype=np.float64)
    m = np.max(z, axis=axis, keepdims=True)
    shifted = z - m
    return shifted - np.log(np.sum(np.exp(shifted), axis=axis, keepdims=True))


def logsumexp(logits: np.ndarray, axis: int = -1) -> np.ndarray:
    z = np.asarray(logits, dtype=np.float64)
    m = np.max(z, axis=axis, keepdims=True)
    out = m + np.log(np.sum(np.exp(z - m), axis=axis, keepdims=True))
    return np.squeeze(out, axis=axis)


def _as_features(features: np.ndarray, dim: int | None, what: str = "features") -> np.ndarray:
    x = np.asarray(features)
    if x.ndim == 1:
        x = x[None, :]
    if x.ndim != 2:
        raise RouterError(f"{what} must be (N, D), got shape {x.shape}")
    if dim is not None and x.shape[1] != dim:
        raise RouterError(f"{what} have {x.shape[1]} dimensions, the router was fitted on {dim}")
    if not np.all(np.isfinite(x)):
        raise RouterError(f"{what} contain NaN or Inf; refuse to score them")
    return x


def _as_logits(logits: np.ndarray | None, router: str, what: str = "logits_t") -> np.ndarray:
    if logits is None:
        raise RouterError(f"router '{router}' needs {what} (the classifier head's logits)")
    z = np.asarray(logits)
    if z.ndim == 1:
        z = z[None, :]
    if z.ndim != 2 or z.shape[1] < 1:
        raise RouterError(f"{what} must be (N, C), got shape {z.shape}")
    if not np.all(np.isfinite(z)):
        raise RouterError(f"{what} contain NaN or Inf; refuse to score them")
    return z


def squared_norm(z: np.ndarray) -> np.ndarray:
    """Per row sum of squares in float64, each row rescaled by its peak before squaring so the sum
    never overflows (z may reach ~1e21 when a 1e6-norm feature meets a floored dead channel)."""
    z = np.asarray(z).astype(np.float64)
    if z.ndim == 1:
        z = z[None, :]
    peak = np.max(np.abs(z), axis=1)
    safe = np.where(peak > 0, peak, 1.0)
    return np.sum((z / safe[:, None]) ** 2, axis=1) * safe * safe


def cast_once(model, dtype, *names: str) -> tuple[np.ndarray, ...]:
    """A frozen model's arrays ``names`` in ``dtype``, C-contiguous, cast once and kept with it (the
    routers here, the scene model): casting the Gaussian's 1280 x 1280 whitening on every press cost
    the cell ~1 ms of its ~1.3 ms router time."""
    cache = model.__dict__.setdefault("_cast_cache", {})
    key = np.dtype(dtype)
    if key not in cache:
        cache[key] = tuple(np.ascontiguousarray(getattr(model, n), dtype=key) for n in names)
    return cache[key]


def _frozen(a: np.ndarray, dtype=np.float64) -> np.ndarray:
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


# --------------------------------------------------------------------------------------------
# routers
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Router:
    """Base of all routers: immutable, numpy only, rebuilt from ``to_params`` output."""

    name: str
    _registry: ClassVar[dict[str, type["Router"]]] = {}

    def novelty(
        self,
        features: np.ndarray | None,
        logits_t: np.ndarray | None = None,
        *,
        logits_u: np.ndarray | None = None,
    ) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def is_untouched(self, novelty: np.ndarray, beta: float) -> np.ndarray:
        """The GZSL decision: True = route to CLS_u. beta=+inf -> all touched, -inf -> none."""
        return route_untouched(novelty, beta)

    def to_params(self) -> dict[str, Any]:  # pragma: no cover - abstract
        raise NotImplementedError

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> "Router":
        name = _scalar_str(params, "name")
        if name not in ROUTERS:
            raise RouterError(f"router parameters name unknown router '{name}'; known: {', '.join(ROUTERS)}")
        version = int(np.asarray(params.get("params_version", PARAMS_VERSION)))
        if version != PARAMS_VERSION:
            raise RouterError(f"router parameters version {version}, this runtime reads {PARAMS_VERSION}")
        impl = Router._registry[name]
        if cls is not Router and not issubclass(impl, cls):
            raise RouterError(f"parameters are for '{name}', not a {cls.__name__}")
        return impl._from_params(params)

    @classmethod
    def _from_params(cls, params: Mapping[str, Any]) -> "Router":  # pragma: no cover
        raise NotImplementedError


def _scalar_str(params: Mapping[str, Any], key: str) -> str:
    if key not in params:
        raise RouterError(f"router parameters lack '{key}'")
    v = params[key]
    if isinstance(v, np.ndarray):
        v = v.item() if v.shape == () else str(v)
    if isinstance(v, bytes):
        v = v.decode()
    return str(v)


def _scalar_float(params: Mapping[str, Any], key: str, default: float | None = None) -> float:
    if key not in params:
        if default is None:
            raise RouterError(f"router parameters lack '{key}'")
        return default
    return float(np.asarray(params[key], dtype=np.float64))


def _register(*names: str):
    def deco(cls):
        for n in names:
            Router._registry[n] = cls
        return cls

    return deco


@_register("gaussian", "mahalanobis_lw", "mahalanobis_oas")
@dataclass(frozen=True)
class GaussianRouter(Router):
    """A Gaussian density of touched features; novelty = -log N(x; mean, cov) (``gaussian``) or
    the squared Mahalanobis distance (shrinkage routers; same ranking, no 2048-d constant)."""

    mean: np.ndarray = field(repr=False, default=None)  # (D,) float64
    whitening: np.ndarray = field(repr=False, default=None)  # (D, D) float64, W W^T = cov^-1
    log_det: float = 0.0  # log det of the (floored) covariance
    shrinkage: float = 0.0
    variance_floor: float = 0.0  # absolute eigenvalue floor actually used
    covariance: np.ndarray | None = field(repr=False, default=None)  # (D, D) float64 (for export)

    _ESTIMATOR: ClassVar[dict[str, str]] = {
        "gaussian": "empirical",
        "mahalanobis_lw": "ledoit_wolf",
        "mahalanobis_oas": "oas",
    }

    @property
    def dim(self) -> int:
        return int(self.mean.shape[0])

    @property
    def uses_log_density(self) -> bool:
        return self.name == "gaussian"

    @classmethod
    def fit(
        cls,
        name: str,
        touched_features: np.ndarray,
        *,
        variance_floor: float = 1e-6,
        keep_covariance: bool = True,
    ) -> "GaussianRouter":
        """Fit on touched features (N, D) in float64.

        ``variance_floor`` is relative: eigenvalues below ``variance_floor * mean variance`` are
        raised to it, so a dead channel (zero variance) or a collinear pair gets a finite, large
        but bounded Mahalanobis weight instead of inf/NaN.
        """
        if name not in cls._ESTIMATOR:
            raise RouterError(f"'{name}' is not a Gaussian router")
        x = _as_features(touched_features, None, "touched_features").astype(np.float64)
        if x.shape[0] < 2:
            raise RouterError(f"need at least 2 touched feature vectors to fit '{name}', got {x.shape[0]}")
        mean, cov, shrink = shrunk_covariance(x, cls._ESTIMATOR[name])
        cov = 0.5 * (cov + cov.T)
        evals, evecs = np.linalg.eigh(cov)
        mean_var = float(np.trace(cov)) / cov.shape[0]
        # All-identical samples: no scale at all; fall back to the feature magnitude so the floor
        # is still relative to something, and a tiny absolute value for all-zero features.
        scale = mean_var if mean_var > 0 else float(np.mean(mean * mean))
        floor = max(variance_floor * scale, 1e-30)
        evals = np.maximum(evals, floor)
        whitening = evecs / np.sqrt(evals)[None, :]
        log_det = float(np.sum(np.log(evals)))
        cov_out = (evecs * evals[None, :]) @ evecs.T if keep_covariance else None
        return cls(
            name=name,
            mean=_frozen(mean),
            whitening=_frozen(whitening),
            log_det=log_det,
            shrinkage=float(shrink),
            variance_floor=floor,
            covariance=None if cov_out is None else _frozen(cov_out),
        )

    def squared_mahalanobis(self, features: np.ndarray, dtype=np.float64) -> np.ndarray:
        """(x - mean)^T cov^-1 (x - mean) per row; ``dtype=np.float32`` is the cell's fast path."""
        x = _as_features(features, self.dim)
        dtype = np.dtype(dtype)
        mean, whitening = cast_once(self, dtype, "mean", "whitening")
        return squared_norm((x.astype(dtype, copy=False) - mean) @ whitening)

    def novelty(self, features, logits_t=None, *, logits_u=None, dtype=np.float64) -> np.ndarray:
        return self.novelty_from_squared(self.squared_mahalanobis(features, dtype=dtype))

    def novelty_from_squared(self, m2: np.ndarray) -> np.ndarray:
        """novelty from the squared Mahalanobis distance (``squared_norm`` of a whitened vector,
        e.g. the ``router_z`` output of a fused bundle graph, docs/bundle.md)."""
        if self.uses_log_density:
            return 0.5 * (m2 + self.log_det + self.dim * _LOG_2PI)
        return m2

    def to_params(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name,
            "params_version": PARAMS_VERSION,
            "mean": np.array(self.mean),
            "whitening": np.array(self.whitening),
            "log_det": float(self.log_det),
            "shrinkage": float(self.shrinkage),
            "variance_floor": float(self.variance_floor),
        }
        if self.covariance is not None:
            out["covariance"] = np.array(self.covariance)
        return out

    @classmethod
    def _from_params(cls, params):
        name = _scalar_str(params, "name")
        if "mean" not in params:
            raise RouterError(f"router '{name}' parameters lack 'mean'")
        mean = np.asarray(params["mean"], dtype=np.float64).reshape(-1)
        cov = params.get("covariance")
        if "whitening" in params:
            whitening = np.asarray(params["whitening"], dtype=np.float64)
            log_det = _scalar_float(params, "log_det")
            floor = _scalar_float(params, "variance_floor", 0.0)
        elif cov is not None:
            # Rebuild the factorisation from a covariance alone (e.g. written by another tool).
            cov = np.asarray(cov, dtype=np.float64)
            evals, evecs = np.linalg.eigh(0.5 * (cov + cov.T))
            floor = max(_scalar_float(params, "variance_floor", 0.0), 1e-30)
            evals = np.maximum(evals, floor)
            whitening = evecs / np.sqrt(evals)[None, :]
            log_det = float(np.sum(np.log(evals)))
        else:
            raise RouterError(f"router '{name}' parameters need 'whitening' or 'covariance'")
        d = mean.shape[0]
        if whitening.shape != (d, d):
            raise RouterError(f"router '{name}': whitening is {whitening.shape}, mean has {d} dimensions")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(whitening)) and np.isfinite(log_det)):
            raise RouterError(f"router '{name}': parameters contain NaN or Inf")
        return cls(
            name=name,
            mean=_frozen(mean),
            whitening=_frozen(whitening),
            log_det=float(log_det),
            shrinkage=_scalar_float(params, "shrinkage", 0.0),
            variance_floor=floor,
            covariance=None if cov is None else _frozen(cov),
        )


@_register("discriminant")
@dataclass(frozen=True)
class DiscriminantRouter(Router):
    """Class Gaussians in Fisher's discriminant subspace of the touched classes (module doc):
    z = (x - centre) @ projection, K = C - 1 numbers; novelty = min over touched classes c of
    ||z - class_means[c]||^2, each summed in float64 (``squared_norm``)."""

    centre: np.ndarray = field(repr=False, default=None)  # (D,) float64, mean of the touched class means
    projection: np.ndarray = field(repr=False, default=None)  # (D, K): whitening x discriminant basis
    class_means: np.ndarray = field(repr=False, default=None)  # (C, K) touched class means in the subspace
    shrinkage: float = 0.0
    variance_floor: float = 0.0  # absolute eigenvalue floor actually used

    @property
    def dim(self) -> int:
        return int(self.centre.shape[0])

    @property
    def n_classes(self) -> int:
        return int(self.class_means.shape[0])

    @classmethod
    def fit(cls, touched_features: np.ndarray, touched_labels: np.ndarray | None, *,
            variance_floor: float = 1e-6) -> "DiscriminantRouter":
        """Fit on touched features (N, D) and their class labels (N,) in float64. ``variance_floor``
        is relative to the largest eigenvalue of the shrunk within-class covariance."""
        if touched_labels is None:
            raise RouterError("router 'discriminant' needs touched_labels (the class of every touched "
                              "feature vector) to fit: it models each touched class")
        x = _as_features(touched_features, None, "touched_features").astype(np.float64)
        labels = np.asarray(touched_labels).reshape(-1)
        if labels.shape[0] != x.shape[0]:
            raise RouterError(f"touched_labels has {labels.shape[0]} entries, touched_features {x.shape[0]} rows")
        classes, y = np.unique(labels, return_inverse=True)
        if len(classes) < 2:
            raise RouterError(f"router 'discriminant' needs at least 2 touched classes, got {len(classes)}")
        fit = discriminant_subspace(x, y, len(classes), variance_floor)
        return cls(name="discriminant", centre=_frozen(fit["centre"]), projection=_frozen(fit["projection"]),
                   class_means=_frozen(fit["class_means"]), shrinkage=fit["shrinkage"],
                   variance_floor=fit["floor"])

    def sq_distances(self, features: np.ndarray, dtype=np.float64) -> np.ndarray:
        """(N, C) squared distances to every touched class in the subspace, float64; ``dtype``
        float32 runs the centring and the D x K matmul in float32 (the cell's float32 feature)."""
        x = _as_features(features, self.dim)
        dtype = np.dtype(dtype)
        centre, projection = cast_once(self, dtype, "centre", "projection")
        z = (x.astype(dtype, copy=False) - centre) @ projection
        diff = z.astype(np.float64)[:, None, :] - self.class_means[None]
        return squared_norm(diff.reshape(-1, diff.shape[2])).reshape(diff.shape[:2])

    def novelty(self, features, logits_t=None, *, logits_u=None, dtype=np.float64) -> np.ndarray:
        return np.min(self.sq_distances(features, dtype=dtype), axis=1)

    def to_params(self) -> dict[str, Any]:
        return {"name": self.name, "params_version": PARAMS_VERSION, "centre": np.array(self.centre),
                "projection": np.array(self.projection), "class_means": np.array(self.class_means),
                "shrinkage": float(self.shrinkage), "variance_floor": float(self.variance_floor)}

    @classmethod
    def _from_params(cls, params):
        for key in ("centre", "projection", "class_means"):
            if key not in params:
                raise RouterError(f"router 'discriminant' parameters lack '{key}'")
        centre = np.asarray(params["centre"], dtype=np.float64).reshape(-1)
        projection = np.asarray(params["projection"], dtype=np.float64)
        means = np.asarray(params["class_means"], dtype=np.float64)
        d = centre.shape[0]
        if projection.ndim != 2 or projection.shape[0] != d or means.ndim != 2 or means.shape[1] != projection.shape[1]:
            raise RouterError(f"router 'discriminant': projection is {projection.shape} and class_means "
                              f"{means.shape}, for a centre of {d} dimensions they must be ({d}, K) and (C, K)")
        if not all(np.all(np.isfinite(a)) for a in (centre, projection, means)):
            raise RouterError("router 'discriminant': parameters contain NaN or Inf")
        return cls(name="discriminant", centre=_frozen(centre), projection=_frozen(projection),
                   class_means=_frozen(means), shrinkage=_scalar_float(params, "shrinkage", 0.0),
                   variance_floor=_scalar_float(params, "variance_floor", 0.0))


@_register("energy")
@dataclass(frozen=True)
class EnergyRouter(Router):
    """novelty = -T logsumexp(logits_t / T): low free energy = familiar (Liu et al. 2020)."""

    temperature: float = 1.0

    def novelty(self, features, logits_t=None, *, logits_u=None) -> np.ndarray:
        z = _as_logits(logits_t, self.name).astype(np.float64)
        t = self.temperature
        return -t * logsumexp(z / t, axis=1)

    def to_params(self):
        return {"name": self.name, "params_version": PARAMS_VERSION, "temperature": float(self.temperature)}

    @classmethod
    def _from_params(cls, params):
        t = _scalar_float(params, "temperature", 1.0)
        if not (t > 0 and np.isfinite(t)):
            raise RouterError(f"energy temperature must be > 0, got {t}")
        return cls(name="energy", temperature=t)


@_register("max_softmax")
@dataclass(frozen=True)
class MaxSoftmaxRouter(Router):
    """novelty = -max softmax(logits_t / T) (Hendrycks & Gimpel 2017)."""

    temperature: float = 1.0

    def novelty(self, features, logits_t=None, *, logits_u=None) -> np.ndarray:
        z = _as_logits(logits_t, self.name).astype(np.float64)
        return -np.exp(np.max(log_softmax(z / self.temperature, axis=1), axis=1))

    def to_params(self):
        return {"name": self.name, "params_version": PARAMS_VERSION, "temperature": float(self.temperature)}

    @classmethod
    def _from_params(cls, params):
        t = _scalar_float(params, "temperature", 1.0)
        if not (t > 0 and np.isfinite(t)):
            raise RouterError(f"max_softmax temperature must be > 0, got {t}")
        return cls(name="max_softmax", temperature=t)


@_register("calibrated_stacking")
@dataclass(frozen=True)
class CalibratedStackingRouter(Router):
    """Calibrated stacking (Chao et al. 2016) on all-class scores [s_t, s_u].

    The decision argmax[s_t - gamma, s_u] picks an untouched class iff max s_u > max s_t - gamma,
    i.e. iff novelty = max s_u - max s_t > -gamma; so beta = -gamma and the threshold machinery
    (tune_threshold, the seen-unseen curve) is shared with the other routers.
    ``scores = "log_softmax"`` first turns each head's logits into log-probabilities, which puts
    two separately trained heads on one scale; ``"logits"`` uses them as they are.
    """

    scores: str = "log_softmax"

    def novelty(self, features, logits_t=None, *, logits_u=None) -> np.ndarray:
        zt = _as_logits(logits_t, self.name, "logits_t").astype(np.float64)
        zu = _as_logits(logits_u, self.name, "logits_u").astype(np.float64)
        if zt.shape[0] != zu.shape[0]:
            raise RouterError(f"logits_t has {zt.shape[0]} rows, logits_u {zu.shape[0]}")
        if self.scores == "log_softmax":
            zt, zu = log_softmax(zt, axis=1), log_softmax(zu, axis=1)
        return np.max(zu, axis=1) - np.max(zt, axis=1)

    def to_params(self):
        return {"name": self.name, "params_version": PARAMS_VERSION, "scores": self.scores}

    @classmethod
    def _from_params(cls, params):
        scores = _scalar_str(params, "scores") if "scores" in params else "log_softmax"
        if scores not in ("log_softmax", "logits"):
            raise RouterError(f"calibrated_stacking scores must be 'log_softmax' or 'logits', got '{scores}'")
        return cls(name="calibrated_stacking", scores=scores)


def fit_router(
    name: str,
    touched_features: np.ndarray | None,
    touched_logits: np.ndarray | None = None,
    *,
    touched_labels: np.ndarray | None = None,
    **options: Any,
) -> Router:
    """Fit router ``name`` on touched training data.

    ``touched_labels``: the class of every touched feature vector; ``discriminant`` needs them
    (RouterError without), the other routers ignore them, so a trainer passes them to every router.
    Options: ``variance_floor`` (Gaussian and discriminant routers, relative, default 1e-6),
    ``keep_covariance`` (Gaussian); ``temperature`` (energy, max_softmax); ``scores``
    (calibrated_stacking). The logit-based routers have no fitted parameters beyond their
    options; their threshold (and gamma) is chosen on validation fabrics with ``tune_threshold``.
    """
    if name in GAUSSIAN_ROUTERS:
        allowed = {"variance_floor", "keep_covariance"}
        _check_options(name, options, allowed)
        return GaussianRouter.fit(name, touched_features, **options)
    if name == "discriminant":
        _check_options(name, options, {"variance_floor"})
        return DiscriminantRouter.fit(touched_features, touched_labels, **options)
    if name in ("energy", "max_softmax"):
        _check_options(name, options, {"temperature"})
        t = float(options.get("temperature", 1.0))
        if not (t > 0 and np.isfinite(t)):
            raise RouterError(f"{name} temperature must be > 0, got {t}")
        return (EnergyRouter if name == "energy" else MaxSoftmaxRouter)(name=name, temperature=t)
    if name == "calibrated_stacking":
        _check_options(name, options, {"scores"})
        return CalibratedStackingRouter._from_params({"name": name, **options})
    raise RouterError(f"unknown router '{name}'; known: {', '.join(ROUTERS)}")


def _check_options(name: str, options: Mapping[str, Any], allowed: set[str]) -> None:
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise RouterError(f"router '{name}' has no option(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed))}")


# --------------------------------------------------------------------------------------------
# thresholds, curves, areas
# --------------------------------------------------------------------------------------------


def route_untouched(novelty: np.ndarray, beta: float) -> np.ndarray:
    """True where the press goes to CLS_u. beta=+inf: all touched; beta=-inf: all untouched."""
    nov = np.asarray(novelty, dtype=np.float64)
    if np.any(np.isnan(nov)):
        raise RouterError("novelty contains NaN; refuse to route")
    if np.isnan(beta):
        raise RouterError("beta is NaN")
    return nov > beta

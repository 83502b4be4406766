"""The lean inference core: one verified bundle, one press in, one GZSL log posterior out.

Per press: check + preprocess the frame (runtime/preprocess.py, the one preprocessing) ->
trunk (onnxruntime) -> heads CLS_t / CLS_u (onnxruntime) -> router novelty (numpy) -> the GZSL
posterior by soft gating of the paper's route (docs/bundle.md "Decision"). A format-2 bundle runs
trunk, heads and the router's and scene model's projections as ONE onnxruntime call (the fused
press graph, export/fuse.py; a router on the logits is folded in as ``router_novelty``); numpy then
only sums squares and handles C class scores.

    P(untouched | x) = sigmoid((g(novelty) - g(beta)) / T),   g(n) = asinh(n / s)
    log p(c | x) = log P(touched | x)   + log softmax(logits_t)[c]   for touched c
                   log P(untouched | x) + log softmax(logits_u)[c]   for untouched c

so the posterior sums to 1 over all bundle classes, its hard version is exactly the paper's route
(``untouched = novelty > beta``, g is increasing), and beta = +inf / -inf sends everything to
CLS_t / CLS_u. g is a signed log beyond the scale s: the Gaussian router's negative log density
is heavy-tailed (1e7 .. 1e12 on one run), and a logistic in the raw score would need T so large
that every press sat near 0.5. T and s come from the manifest (fitted at export, docs/bundle.md).
Probabilities that are exactly zero (beta at +-inf) are written as ``LOG_ZERO`` instead of -inf
so journals stay valid JSON and sums over presses never meet inf - inf.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vs2t_edge.runtime import tactile_descriptor as td
from vs2t_edge.runtime.bundle import (NOVELTY_OUT, ROUTER_OUT, SCENE_OUT, Bundle, BundleError, check_session_shapes, graph_keys,
                                      is_fused, is_split, load_bundle, open_session)
from vs2t_edge.runtime.novelty import GaussianRouter, RouterError, log_softmax, squared_norm
from vs2t_edge.runtime.preprocess import FrameError, PreparedReference, prepare_reference, preprocess_tactile

LOG_ZERO = -1e30  # log of a probability that is exactly 0 (finite on purpose, see module doc)
WARMUP_RUNS = 3


@dataclass(frozen=True)
class PressScore:
    log_posterior: dict[str, float]  # over the bundle's classes (touched + untouched; a scene model adds its known_only), normalised in log space
    # router score, higher = more likely untouched; None on a format-3 bundle's press path, which
    # decides with its scene model and never runs the heads (runtime/bundle.py is_split)
    novelty: float | None
    untouched: bool | None  # novelty > beta (None with novelty)
    latency_ms: float
    # squared distance to every bundle class in the scene model's space (runtime/scene_model.py);
    # None when the bundle has no scene model (its log posterior is then the router's, below)
    sq_distance: dict[str, float] | None = None
    # the press in the scene model's space, (k,) float64 (its offset item rule averages these)
    scene_z: np.ndarray | None = None


def log_sigmoid(z: np.ndarray) -> np.ndarray:
    """log(1 / (1 + exp(-z))) without overflow for |z| up to inf."""
    return -np.logaddexp(0.0, -np.asarray(z, dtype=np.float64))


def gate_logit(novelty: np.ndarray, beta: float, temperature: float, scale: float | None = None) -> np.ndarray:
    """z with P(untouched | x) = sigmoid(z); scale None = linear in the score (no asinh)."""
    nov = np.asarray(novelty, dtype=np.float64).reshape(-1)
    if scale is None:
        return (nov - beta) / temperature  # beta = +inf -> -inf (all touched), -inf -> +inf
    return (np.arcsinh(nov / scale) - np.arcsinh(beta / scale)) / temperature  # asinh(+-inf) = +-inf


def gzsl_log_posterior(logits_t: np.ndarray, logits_u: np.ndarray, novelty: np.ndarray, beta: float,
                       temperature: float, scale: float | None = None) -> np.ndarray:
    """(N, C_t + C_u) log posterior by soft gating (module doc); float64, finite, rows sum to 1."""
    if not temperature > 0 or math.isinf(temperature):
        raise ValueError(f"gating temperature {temperature} must be finite and > 0")
    if scale is not None and not (scale > 0 and math.isfinite(scale)):
        raise ValueError(f"gating scale {scale} must be finite and > 0")
    if math.isnan(beta):
        raise ValueError("beta is NaN")
    nov = np.asarray(novelty, dtype=np.float64).reshape(-1)
    if np.any(~np.isfinite(nov)):
        raise ValueError("novelty is NaN or Inf")
    z = gate_logit(nov, beta, temperature, scale)
    log_pu, log_pt = log_sigmoid(z), log_sigmoid(-z)
    out = np.concatenate([log_pt[:, None] + log_softmax(logits_t, axis=1),
                          log_pu[:, None] + log_softmax(logits_u, axis=1)], axis=1)
    return np.where(np.isneginf(out), LOG_ZERO, out)


@dataclass(frozen=True)
class Outputs:
    feature: np.ndarray  # (N, D) float32
    logits_t: np.ndarray
    logits_u: np.ndarray
    novelty: np.ndarray  # (N,) float64
    # fused press graph only (format 2): the router's whitened vector, the scene model's projection
    router_z: np.ndarray | None = None
    scene_z: np.ndarray | None = None
    router_novelty: np.ndarray | None = None  # (N, 1) float32, a router on the logits folded into the graph


def _rel_err(actual: np.ndarray, expected: np.ndarray, floor: float = 1e-6) -> float:
    """max |a - e| / max(max |e|, floor): one number per output, scale-free above ``floor``."""
    a, e = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
    if a.shape != e.shape:
        return math.inf
    if not np.all(np.isfinite(a)):
        return math.inf
    return float(np.max(np.abs(a - e)) / max(float(np.max(np.abs(e))), floor)) if a.size else 0.0


# A router's novelty is a log-probability, a logit, a probability or a squared distance: one unit
# of it is the least a threshold (beta) ever resolves. Calibrated stacking's novelty on a press both
# heads are sure of is the difference of two log-probabilities near 0 (2.8e-6 on a demo world's
# probe press), where float32 cancellation alone is a few percent of it: relative to itself, the
# probe refused a sound bundle (the float32 graph 4e-8 off numpy's float64). Relative to at least
# one unit, the probe still refuses a graph that computes another router (tests/test_fused_bundle.py).
NOVELTY_UNIT = 1.0
NOVELTY_CHECKS = frozenset({"novelty", NOVELTY_OUT, "novelty_vs_router_file"})


def probe_error(name: str, actual: np.ndarray, expected: np.ndarray) -> float:
    """The probe's error of output ``name``: relative, a novelty's relative to at least one unit."""
    return _rel_err(actual, expected, NOVELTY_UNIT if name in NOVELTY_CHECKS else 1e-6)


def _float32_router(router):
    """The same router with its mean and whitening stored in float32 once: its float32 scoring
    path casts them on every call otherwise (a 1280 x 1280 copy, ~0.5 ms of a press)."""
    if isinstance(router, GaussianRouter):
        return dataclasses.replace(router, mean=router.mean.astype(np.float32),
                                   whitening=router.whitening.astype(np.float32))
    return router


def fused_novelty(router, feature: np.ndarray, logits_t: np.ndarray, logits_u: np.ndarray,
                  router_z: np.ndarray | None, router_novelty: np.ndarray | None = None) -> np.ndarray:
    """The novelty of a fused press graph's outputs (the cell's and the exporter's one way): from
    router_z's squared norm (float64) for Gaussian routers; the graph's own router_novelty (N, 1)
    for a router on the logits folded into it; else the numpy router on the logits."""
    if router_novelty is not None:
        nov = router_novelty[:, 0].astype(np.float64)
        # non-finite logits give a non-finite novelty here (logsumexp, softmax and max propagate NaN
        # and +inf); score_press refuses non-finite logits either way, as the numpy router does
        if not np.all(np.isfinite(nov)):
            raise RouterError("logits contain NaN or Inf; refuse to score them")
        return nov
    if router_z is None:
        return router.novelty(feature, logits_t, logits_u=logits_u)
    z = np.asarray(router_z, dtype=np.float64)
    # float32 z squares to < 1.2e77 and D of them sum far below float64's range: no rescaling needed
    # (squared_norm's, for float64 z), one pass instead of its ten (~0.1 ms a press on the bench)
    m2 = np.einsum("ij,ij->i", z, z) if router_z.dtype == np.float32 else squared_norm(z)
    if not (np.all(np.isfinite(m2)) and np.all(np.isfinite(feature))):
        raise RouterError("features contain NaN or Inf; refuse to score them")  # as the numpy router says
    return router.novelty_from_squared(m2)


def _full_frames_only(reduced_by: int) -> None:
    if reduced_by != 1:
        raise FrameError(f"frame: decoded at 1/{reduced_by} scale, but a descriptor bundle takes full frames", "scale")


class TactileModel:
    """A loaded, verified, warmed bundle. ``load`` is the only constructor the cell uses."""

    def __init__(self, bundle: Bundle, trunk_session, heads_session, threads: int) -> None:
        self.bundle = bundle
        self.manifest = bundle.manifest
        self.touched: tuple[str, ...] = bundle.touched
        self.untouched: tuple[str, ...] = bundle.untouched
        self.classes: tuple[str, ...] = bundle.classes
        self.beta: float = bundle.beta
        self.temperature: float = bundle.gating_temperature
        self.gate_scale: float | None = bundle.gating_scale
        self.router = _float32_router(bundle.router)
        self.scene_model = bundle.scene_model
        self.preprocess_spec = bundle.preprocess
        self.camera_jpeg: int = bundle.camera_jpeg  # the camera's MJPEG quality it trained on (0: lossless frames)
        self.threads = threads
        # the tactile feature: the ONNX trunk, or a numpy descriptor (runtime/tactile_descriptor.py)
        self.descriptor: td.DescriptorFeature | None = bundle.descriptor
        self._trunk, self._heads = trunk_session, heads_session
        self._trunk_in = trunk_session.get_inputs()[0].name if trunk_session is not None else None
        self._heads_in = heads_session.get_inputs()[0].name if heads_session is not None else None
        # format 2: trunk.onnx is the whole press graph, fetched by name in this order
        self.fused = is_fused(bundle.manifest) if isinstance(bundle.manifest, dict) else False
        # format 3: the press graph ends at scene_z; the heads' graph (logits, router) runs on demand
        self.split = is_split(bundle.manifest) if isinstance(bundle.manifest, dict) else False
        graphs = bundle.manifest["graphs"] if self.fused else {}
        self._press_outputs = ["feature", *([] if self.split else ["logits_t", "logits_u"]),
                               *[k for k in (ROUTER_OUT, NOVELTY_OUT, SCENE_OUT) if k in graphs["trunk"]["outputs"]]] \
            if self.fused else []
        self._heads_outputs = ["logits_t", "logits_u", *[k for k in (ROUTER_OUT, NOVELTY_OUT)
                                                         if k in graphs["heads"]["outputs"]]] if self.split else []
        self._reference: PreparedReference | td.DescriptorReference | None = None
        self.last_timing: dict[str, float] = {}
        self.probe_errors: dict[str, float] = {}

    # -------------------------------------------------------------- loading

    @classmethod
    def load(cls, bundle_dir: Path | str, threads: int = 2, beta_override: float | None = None) -> "TactileModel":
        """Verify (hashes, opsets, shapes, version), open, warm up and check the probe. Raises
        BundleError naming what mismatches."""
        bundle = load_bundle(bundle_dir, beta_override=beta_override)
        sessions = {"trunk": None}
        for key in graph_keys(bundle.manifest):
            try:
                sessions[key] = open_session(bundle.path(key), threads)
            except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own types; say which file
                raise BundleError(bundle.root, f"{bundle.path(key).name}: onnxruntime cannot open it ({exc})") from None
            check_session_shapes(bundle, key, sessions[key])
        model = cls(bundle, sessions["trunk"], sessions.get("heads"), threads)
        model._warm_and_probe()
        return model

    def _warm_and_probe(self) -> None:
        x = self.bundle.probe_input
        if self.descriptor is not None:  # the cell's own descriptor function on the exporter's frames
            self.set_reference(self.bundle.probe_frames[0])
            err = _rel_err(self.preprocess(self.bundle.probe_frames[1]), x)
            self._reference = None
            self.probe_errors["descriptor"] = err
            if not err <= self.bundle.probe_tolerance["feature"]:
                raise BundleError(self.bundle.root, f"probe check failed: the {self.descriptor.name} descriptor of "
                                                    f"the probe frames differs from the exporter's by {err:.3g} "
                                                    f"(relative), tolerance {self.bundle.probe_tolerance['feature']:.3g}")
        for _ in range(WARMUP_RUNS):  # first runs allocate the arena and pick kernels
            self.forward(x)
        out = self.forward(x)
        exp = self.bundle.probe_expected
        tol = self.bundle.probe_tolerance
        checks = {"feature": (out.feature, exp["feature"], tol["feature"]),
                  "logits_t": (out.logits_t, exp["logits_t"], tol["logits"]),
                  "logits_u": (out.logits_u, exp["logits_u"], tol["logits"]),
                  "novelty": (out.novelty, exp["novelty"], tol["novelty"])}
        if out.router_z is not None:  # every output of the fused graph, and that it computes what
            # router.npz / decision.npz say on the feature it gives (a graph and files that disagree are refused)
            checks[ROUTER_OUT] = (out.router_z, exp[ROUTER_OUT], tol["novelty"])
            checks["novelty_vs_router_file"] = (out.novelty, self.bundle.router.novelty(out.feature.astype(np.float64)),
                                                tol["novelty"])
        if out.router_novelty is not None:  # the folded router against router.npz's on the graph's logits
            checks[NOVELTY_OUT] = (out.router_novelty, exp[NOVELTY_OUT], tol["novelty"])
            checks["novelty_vs_router_file"] = (out.novelty, self.bundle.router.novelty(
                out.feature, out.logits_t.astype(np.float64), logits_u=out.logits_u.astype(np.float64)), tol["novelty"])
        if out.scene_z is not None:
            checks[SCENE_OUT] = (out.scene_z, exp[SCENE_OUT], tol["projection"])
            checks["scene_z_vs_decision_file"] = (out.scene_z, self.scene_model.project(out.feature), tol["projection"])
        for name, (a, e, t) in checks.items():
            err = probe_error(name, a, e)
            self.probe_errors[name] = err
            if not err <= t:
                raise BundleError(self.bundle.root, f"probe check failed: '{name}' differs from the exporter's "
                                                    f"by {err:.3g} (relative), tolerance {t:.3g}")

    # -------------------------------------------------------------- per press

    def set_reference(self, frame: np.ndarray, reduced_by: int = 1) -> None:
        """The session's no-contact frame; refused (FrameError) if it is no usable image.
        ``reduced_by``: 1 for a full frame, else the scale the camera decoded it at - the bundle's
        ``preprocess.reduce``, or a float-path bundle's ``float_path_scale`` (runtime/preprocess.py)."""
        # checked, cropped and resized once per item: each press then only subtracts it
        if self.descriptor is not None:  # its marker dots found once per item instead
            _full_frames_only(reduced_by)
            self._reference = td.prepare_reference(frame)
            return
        self._reference = prepare_reference(frame, self.preprocess_spec, reduced_by)

    def preprocess(self, frame: np.ndarray, reduced_by: int = 1) -> np.ndarray:
        """One frame -> the batch ``forward`` takes: (1, 3, S, S) for the trunk, or the raw
        descriptor (1, D) float32 (standardised in ``forward``, as the trunk graph standardises)."""
        if self.descriptor is not None:
            _full_frames_only(reduced_by)
            if self._reference is None:
                raise FrameError("no no-contact reference frame set (call set_reference first)", "reference")
            return td.describe(self.descriptor.name, frame, self._reference)[None]
        spec = self.preprocess_spec
        ref = self._reference if spec.use_reference else None
        if spec.use_reference and ref is None:
            raise FrameError("no no-contact reference frame set (call set_reference first)", "reference")
        return preprocess_tactile(frame, ref, spec, reduced_by)[None]

    def forward(self, x: np.ndarray) -> Outputs:
        """Preprocessed batch (N, 3, S, S) float32, or raw descriptors (N, D) -> all outputs (for the
        probe, bench and calibration)."""
        t0 = time.perf_counter()
        if self.fused:
            return self._forward_fused(x, t0)
        if self.descriptor is not None:
            feature = self.descriptor.standardise(x)
        else:
            feature = self._trunk.run(None, {self._trunk_in: np.ascontiguousarray(x, dtype=np.float32)})[0]
        t1 = time.perf_counter()
        logits_t, logits_u = self._heads.run(["logits_t", "logits_u"], {self._heads_in: feature})
        t2 = time.perf_counter()
        if isinstance(self.router, GaussianRouter):
            novelty = self.router.novelty(feature, logits_t, logits_u=logits_u, dtype=np.float32)
        else:
            novelty = self.router.novelty(feature, logits_t, logits_u=logits_u)
        t3 = time.perf_counter()
        self.last_timing = {"trunk_ms": 1e3 * (t1 - t0), "heads_ms": 1e3 * (t2 - t1), "router_ms": 1e3 * (t3 - t2)}
        return Outputs(feature, logits_t, logits_u, np.asarray(novelty, dtype=np.float64))

    def _forward_fused(self, x: np.ndarray, t0: float) -> Outputs:
        """One onnxruntime call gives feature, logits and the projections; numpy sums squares.
        Format 3: the press graph's call, then the heads' graph on its feature."""
        got = dict(zip(self._press_outputs, self._press_run(x)))
        t1 = t2 = time.perf_counter()
        if self.split:
            got.update(zip(self._heads_outputs, self._heads.run(self._heads_outputs, {self._heads_in: got["feature"]})))
            t2 = time.perf_counter()
        feature, logits_t, logits_u = got["feature"], got["logits_t"], got["logits_u"]
        router_z, scene_z, graph_nov = got.get(ROUTER_OUT), got.get(SCENE_OUT), got.get(NOVELTY_OUT)
        novelty = fused_novelty(self.router, feature, logits_t, logits_u, router_z, graph_nov)
        t3 = time.perf_counter()
        self.last_timing = {"trunk_ms": 1e3 * (t1 - t0), "heads_ms": 1e3 * (t2 - t1), "router_ms": 1e3 * (t3 - t2)}
        return Outputs(feature, logits_t, logits_u, np.asarray(novelty, dtype=np.float64), router_z, scene_z, graph_nov)

    def _press_run(self, x: np.ndarray) -> list:
        return self._trunk.run(self._press_outputs, {self._trunk_in: np.ascontiguousarray(x, dtype=np.float32)})

    def press_novelty(self, frame: np.ndarray, reduced_by: int = 1) -> float:
        """The router's novelty of one press frame (``vs2t-edge calibrate``'s beta), the heads run
        even where the cell's press path leaves them out (format 3). FrameError as ``score_press``."""
        try:
            novelty = float(self.forward(self.preprocess(frame, reduced_by)).novelty[0])
        except RouterError as exc:
            raise FrameError(f"model output not usable for this frame ({exc})", "model_output") from None
        if not math.isfinite(novelty):
            raise FrameError("model output not usable for this frame (non-finite novelty)", "model_output")
        return novelty

    def scene_projection(self, out: Outputs) -> np.ndarray:
        """(N, k) the presses in the scene model's space: the graph's scene_z when the bundle is
        fused, else the numpy projection of the feature (float32, as before)."""
        if out.scene_z is not None:
            if not np.all(np.isfinite(out.scene_z)):
                raise FrameError("model output not usable for this frame (non-finite scene projection)", "model_output")
            return out.scene_z
        return self.scene_model.project(out.feature, dtype=np.float32)

    def log_posterior(self, out: Outputs, beta: float | None = None) -> np.ndarray:
        return gzsl_log_posterior(out.logits_t, out.logits_u, out.novelty, self.beta if beta is None else beta,
                                  self.temperature, self.gate_scale)

    def score_press(self, frame: np.ndarray, reduced_by: int = 1) -> PressScore:
        """One press frame (HxWx3 uint8 BGR; ``reduced_by`` as in ``set_reference``) -> PressScore.
        Raises FrameError for frames the cell must not classify (bad frame, or a model output that
        is not finite)."""
        t0 = time.perf_counter()
        x = self.preprocess(frame, reduced_by)
        t1 = time.perf_counter()
        if self.split:  # the loader refuses format 3 without a scene model
            return self._score_scene(x, t0, t1)
        try:
            out = self.forward(x)
        except RouterError as exc:  # NaN/Inf features: never route such a press to a bin
            raise FrameError(f"model output not usable for this frame ({exc})", "model_output") from None
        t2 = time.perf_counter()
        if not (np.all(np.isfinite(out.logits_t)) and np.all(np.isfinite(out.logits_u))):
            raise FrameError("model output not usable for this frame (non-finite logits)", "model_output")
        novelty = float(out.novelty[0])
        if self.scene_model is not None:
            log_posterior, sq, z = self._scene_posterior(self.scene_projection(out))
        else:
            log_posterior, sq, z = dict(zip(self.classes, self.log_posterior(out)[0].tolist())), None, None
        t3 = time.perf_counter()
        timing = dict(self.last_timing)
        timing.update(preprocess_ms=1e3 * (t1 - t0), decision_ms=1e3 * (t3 - t2), total_ms=1e3 * (t3 - t0))
        self.last_timing = timing
        return PressScore(log_posterior, novelty, bool(novelty > self.beta), timing["total_ms"], sq, z)

    def _score_scene(self, x: np.ndarray, t0: float, t1: float) -> PressScore:
        """``score_press`` of a format-3 bundle: the press graph's one call (feature, scene_z), the
        scene model's posterior; no heads, no router (novelty None)."""
        feature, z = self._press_run(x)
        t2 = time.perf_counter()
        if not np.isfinite(feature).all():  # the method: np.all's Python wrapper is paid cold after the trunk
            raise FrameError("model output not usable for this frame (non-finite feature)", "model_output")
        if not np.isfinite(z).all():
            raise FrameError("model output not usable for this frame (non-finite scene projection)", "model_output")
        log_posterior, sq, z64 = self._scene_posterior(z)
        t3 = time.perf_counter()
        self.last_timing = {"trunk_ms": 1e3 * (t2 - t1), "heads_ms": 0.0, "router_ms": 0.0, "preprocess_ms": 1e3 * (t1 - t0),
                            "decision_ms": 1e3 * (t3 - t2), "total_ms": 1e3 * (t3 - t0)}
        return PressScore(log_posterior, None, None, self.last_timing["total_ms"], sq, z64)

    def _scene_posterior(self, z: np.ndarray) -> tuple[dict, dict, np.ndarray]:
        """One press's (1, k) projection -> its log posterior and squared distances over the scene
        model's classes (the bundle's, then those it knows only to refuse), and the projection (k,)
        float64 (tolist: python floats, one C call)."""
        lp, d2 = self.scene_model.log_posterior_projected(z)
        classes = self.scene_model.classes
        return dict(zip(classes, lp[0].tolist())), dict(zip(classes, d2[0].tolist())), np.asarray(z[0], np.float64)


__all__ = ["PressScore", "TactileModel", "Outputs", "fused_novelty", "gzsl_log_posterior", "gate_logit", "log_sigmoid", "LOG_ZERO",
           "BundleError", "FrameError"]

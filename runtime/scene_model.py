"""The scene decision: one classifier over exactly the classes a scene lists, and a way to say "none of them".

Every bundle class is a Gaussian with one shared covariance in a low-dimensional subspace of the
tactile feature (linear discriminant analysis, as in the generative GZSL protocol of f-CLSWGAN /
f-VAEGAN: real features of the touched fabrics, features synthesised by the generator for the
untouched ones, one softmax). The subspace is the top ``k`` principal axes of the touched training
presses; the shared covariance is their within-class scatter there (shrunk towards its mean
variance), folded into the projection so that distances in the model's space are Mahalanobis
distances. Touched class means are real presses' means; untouched class means are the means of the
generator's samples - the generator never saw an untouched fabric's tactile data.

Per press the model gives, for every bundle class c, the squared distance d2_c and the score

    s_c = -d2_c / (2 T) + b [c synthesised]

``T`` (temperature) and ``b`` (the untouched bias of calibrated stacking, Chao et al. 2016:
synthesised means sit off the real ones, so untouched classes need a head start) are fitted on
validation fabrics only (train/decision.py). [c synthesised]: c is untouched and no operator label
re-estimated its mean (``taught``, runtime/feedback.py). A scene's classifier is the softmax of s over the
scene's classes: restricting the model to a scene is picking rows, no retraining, no torch.

Off-scene pieces are told by two numbers that ``runtime.evidence.Evidence`` accumulates over an
item: the mean over presses of ``min_{c in scene} d2_c`` (far from every scene class: something
never seen; refused above ``open_threshold``), and whether a bundle class outside the scene
explains the presses better than the best scene class by ``known_margin`` (a fabric the cell knows
that does not belong to this job). Both thresholds are fitted on validation fabrics too.

Fabrics the run pressed but kept out of the bundle's heads - its validation fabrics, whose presses
chose the operating point - are known to the model only to be refused (``known_only``): classes
after the bundle's, at their training presses' real means (train/decision.py ``with_known``),
never a job's fabric. A piece of one goes to the reject bin by the known-class rule instead of
into the bin of the job fabric that feels most like it.

Per item there are two rules (``item_rule``), both chosen on validation fabrics:

* ``"sum"``: the per-press log posteriors, restricted to the scene, summed with ``evidence_weight``
  (runtime/evidence.py);
* ``"offset"``: a piece's presses share an offset from their class mean - a piece's region differs
  from the training presses', and a synthesised mean is off its fabric's real one by the
  generator's error, the same on every press. Presses z_i = mu_c + e + eps_i with eps_i ~ N(0,
  ``press_var`` I) and e ~ N(0, s_c I), s_c = ``offset_var_touched`` or ``offset_var_untouched``;
  so the mean of n presses zbar ~ N(mu_c, (s_c + press_var / n) I) and the item's score of class c
  is

      L_c = (-||zbar - mu_c||^2 / (2 v_c) - k/2 log v_c) / item_temperature + item_bias [c synthesised],
      v_c = s_c + press_var / n

  (``item_log_lik``): evidence for a synthesised class stops growing once the presses have pinned
  the piece's mean down to the generator's error, where the sum rule grows it with every press.

A press farther from every class than ``outlier_ratio`` times that class's expected spread
(``press_spread``: k (s_c + press_var), the offset model's variance of one press around its class
mean) is no evidence for any class (``is_outlier_press``; runtime/evidence.py): a press on a knot,
a pulled thread or a fold of the piece lands far from every fabric, and averaged into the piece's
mean it would carry the piece to whichever class is broadest - a synthesised one. Chosen on
validation (train/decision.py), off (inf) in files written before it.

Under the offset rule a piece goes into a class's bin only when it feels like that class: the mean
of its n presses must lie within ``likeness_ratio`` times the squared distance the offset model
expects of the class's own pieces, k (s_c + press_var / n) (``item_ratios``; runtime/evidence.py
``off_scene``). A piece of a fabric no class describes well - an untouched fabric whose synthesis
is far off, nearer some touched fabric of the job than its own synthesis - can still lead a
touched class by a wide posterior, since the posterior only compares classes; this asks whether
the leader itself could have made the presses. For a touched class the expected distance is
small, so the rule is tight there; a synthesised class's offset variance makes it loose. Chosen
on validation with the offset rule's other knobs, off (inf) in files written before it.

``extra_presses``: a piece that at the press limit is not confident, led by a touched class and
refused by no off-scene rule takes up to that many presses more (runtime/evidence.py); a touched
class's evidence keeps growing with presses where a synthesis's stops. Chosen on validation after
the rest of the operating point (0, 2, 4 or 8: the most pieces in the right bin within the
mis-sort target, the fewest presses among equals); the cell config's ``evidence.extra_presses``
overrides it when written. 0 (off) in files written before it.

Numpy only: fitted in training, stored in the bundle (``to_params`` / ``from_params``, an .npz),
scored on the cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Mapping

import numpy as np

from vs2t_edge.runtime.novelty import cast_once

PARAMS_VERSION = 1
KIND = "scene_gaussian"
ITEM_RULES = ("sum", "offset")
OFFSET_KEYS = ("press_var", "offset_var_touched", "offset_var_untouched", "item_temperature", "item_bias")
# the offset rule's whole operating point, stored as "labels_<key>" by a sum-rule model (``labels_rule``)
LABELS_KEYS = OFFSET_KEYS + ("known_margin", "open_threshold", "confidence", "untouched_confidence")
# every key ``to_params`` can write: a file with any other is refused (``from_params``). Rules were
# added as optional keys (known_only, refuse_early, outlier_ratio, likeness_ratio, extra_presses); a
# runtime that skipped a key it does not know would sort with the rule left out - a piece on a knot
# into a wrong bin - so a bundle from a newer training is refused by name until the runtime is updated.
PARAMS_KEYS = frozenset(("kind", "params_version", "classes", "untouched", "center", "basis", "means", "temperature",
                         "untouched_bias", "evidence_weight", "open_threshold", "known_margin", "confidence",
                         "untouched_confidence", "item_rule", "known_only", "refuse_early", "outlier_ratio",
                         "likeness_ratio", "extra_presses")
                        + OFFSET_KEYS + tuple(f"labels_{key}" for key in LABELS_KEYS))


class SceneModelError(ValueError):
    """The scene model's parameters are unusable, or it was asked about a class it does not have."""


@dataclass(frozen=True)
class SceneModel:
    classes: tuple[str, ...]  # bundle classes, touched first, in the manifest's order; then ``known_only``
    untouched: frozenset[str]
    center: np.ndarray = field(repr=False)  # (D,) float64
    basis: np.ndarray = field(repr=False)  # (D, k) float64: projection and whitening in one
    means: np.ndarray = field(repr=False)  # (C, k) float64, class means in the whitened subspace
    temperature: float = 1.0
    untouched_bias: float = 0.0
    evidence_weight: float = 1.0  # per-press log posteriors are multiplied by it before summing
    open_threshold: float = math.inf  # mean over an item's presses of min scene d2; above: off-scene
    known_margin: float = math.inf  # log evidence a non-scene class needs over the scene's best to refuse
    confidence: float = 0.95  # leading scene posterior that sorts an item into a touched class
    untouched_confidence: float = 0.95  # ... into an untouched class (both chosen for the mis-sort target)
    info: Mapping[str, Any] = field(default_factory=dict, repr=False)
    # the item rule (module doc): "sum" reads the five fields above; "offset" these five instead of
    # evidence_weight (the confidences, open_threshold and known_margin serve both)
    item_rule: str = "sum"
    press_var: float = 1.0
    offset_var_touched: float = 0.0
    offset_var_untouched: float = 0.0
    item_temperature: float = 1.0
    item_bias: float = 0.0
    # per class, the offset variance that replaces the two above (runtime/feedback.py: an untouched
    # class whose mean operator-labelled pieces re-estimated); None = the two. Cell state, not stored.
    class_offset_var: np.ndarray | None = field(default=None, repr=False)
    # untouched classes whose means operator labels re-estimated (runtime/feedback.py): real presses
    # now, scored without the biases that price a synthesis. Cell state, not stored.
    taught: frozenset[str] = frozenset()
    # a sum-rule model's offset setting for operator labels (runtime/feedback.py needs the offset
    # rule): the offset candidate training searched on the same validation jobs (LABELS_KEYS); None
    # for an offset-rule model (its own setting serves) and for files written before it
    labels_rule: Mapping[str, float] | None = field(default=None, repr=False)
    # the last classes: fabrics the run pressed that are no bundle class (its validation fabrics),
    # real means, known only to refuse their pieces (module doc); () for files written before them
    known_only: tuple[str, ...] = ()
    # a piece that surely is a known fabric the job leaves out goes to the reject bin at that press,
    # not at the press limit (runtime/evidence.py refuse_early); chosen on validation, off in older files
    refuse_early: bool = False
    # a press farther than this from every class, in units of the class's ``press_spread``, is no
    # evidence (module doc); chosen on validation, off (inf) in older files
    outlier_ratio: float = math.inf
    # the offset rule sorts a piece into a class's bin only within this many times the squared
    # distance of the class's own pieces (module doc); chosen on validation, off (inf) in older files
    likeness_ratio: float = math.inf
    # presses past the press limit for a piece a touched class leads, unconfident and unrefused
    # (module doc); chosen on validation, 0 (off) in older files
    extra_presses: int = 0

    @property
    def dim(self) -> int:
        return int(self.center.shape[0])

    @property
    def k(self) -> int:
        return int(self.basis.shape[1])

    def project(self, features: np.ndarray, dtype=np.float64) -> np.ndarray:
        x = np.asarray(features)
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise SceneModelError(f"scene model: features of shape {x.shape}, expected (N, {self.dim})")
        if not np.all(np.isfinite(x)):
            raise SceneModelError("scene model: features contain NaN or Inf")
        center, basis = cast_once(self, dtype, "center", "basis")
        return ((x.astype(dtype, copy=False) - center) @ basis).astype(np.float64)

    def _consts(self) -> tuple[np.ndarray, ...]:
        """Per class, computed once: (means^T, squared norms of the means, untouched bias, 1.0 for a
        synthesised class - untouched and not ``taught`` -, offset variance of the offset item rule)."""
        cache = self.__dict__.setdefault("_cast_cache", {})
        if "consts" not in cache:
            # the biases price a synthesised mean: a taught class's is real presses (``taught``)
            synth = np.array([c in self.untouched and c not in self.taught for c in self.classes], dtype=np.float64)
            cache["consts"] = (self.means.T, np.sum(self.means * self.means, axis=1), self.untouched_bias * synth,
                               synth, self.offset_vars())
        return cache["consts"]

    def offset_vars(self) -> np.ndarray:
        """(C,) the offset item rule's offset variance per class: ``class_offset_var`` when set (a
        class operator labels re-estimated), else the touched or untouched one by kind."""
        if self.class_offset_var is not None:
            return np.array(self.class_offset_var, np.float64)
        is_u = np.array([c in self.untouched for c in self.classes])
        return np.where(is_u, self.offset_var_untouched, self.offset_var_touched).astype(np.float64)

    def press_spread(self) -> np.ndarray:
        """(C,) a press's expected squared distance to its own class mean under the offset item
        rule, k (s_c + press_var); a sum-rule model reads its stored offset setting (``labels_rule``),
        one without any reads press variance 1 (the whitened within-class scatter)."""
        m = self if self.item_rule == "offset" or self.labels_rule is None else self.for_labels()
        return m.k * (m.offset_vars() + m.press_var)

    def twins(self, scene, ratio: float) -> list[str]:
        """The touched classes of ``scene`` whose mean lies within ``ratio`` times the expected squared
        error of a synthesised class of the scene (an untouched class no label taught): k s_u, the
        offset rule's variance of a synthesis around its fabric's real mean (a sum-rule model reads
        its stored offset setting, as ``press_spread``). Zero-shot, the cell cannot tell that
        untouched fabric's pieces from such a touched fabric's: on the demo world its pieces went into
        the touched fabric's bin (docs/decision.md, "Twins in a job"). [] for ``ratio`` inf or 0, or a
        model without an offset setting."""
        m = self.for_labels()  # the model itself under the offset rule
        if m is None or not 0 < ratio < math.inf:
            return []
        index = {c: i for i, c in enumerate(self.classes)}
        var = m.offset_vars()
        synth = [index[c] for c in scene if c in self.untouched and c not in self.taught]
        touched = [c for c in scene if c in index and c not in self.untouched and c not in self.known_only]
        return [t for t in touched if any(float(np.sum((self.means[index[t]] - self.means[u]) ** 2))
                                          <= ratio * self.k * float(var[u]) for u in synth)]

    def is_outlier_press(self, z: np.ndarray | None = None, sq_distance: Mapping[str, float] | None = None) -> bool:
        """Whether a press lies farther than ``outlier_ratio`` spreads (``press_spread``) from every
        class (module doc), given by its projection ``z`` (k,) or, without one, its squared
        distances by class name (a class it lacks counts as infinitely far); False when it is off."""
        if not math.isfinite(self.outlier_ratio):
            return False
        if z is not None:
            d2 = self.sq_distances_projected(np.asarray(z, np.float64).reshape(1, -1))[0]
        elif sq_distance:
            d2 = np.array([float(sq_distance.get(c, math.inf)) for c in self.classes])
        else:
            return False
        cache = self.__dict__.setdefault("_cast_cache", {})
        if "spread" not in cache:
            cache["spread"] = self.press_spread()
        return bool((d2 / cache["spread"]).min() > self.outlier_ratio)

    def sq_distances(self, features: np.ndarray, dtype=np.float64) -> np.ndarray:
        """(N, C) squared Mahalanobis distance of each press to each bundle class's mean."""
        return self.sq_distances_projected(self.project(features, dtype))

    def sq_distances_projected(self, z: np.ndarray) -> np.ndarray:
        """The same from projected presses z = (x - center) @ basis, (N, k) (``project``, or the
        ``scene_z`` output of a fused bundle graph, docs/bundle.md); float64.

        One press's answer is kept until the next press, read-only, by a model whose evidence asks
        it of the same projection again (the outlier rule; the offset rule's open-set rule): the cell
        then asks it twice a press (its decision, then the evidence), and each of its dozen numpy
        calls is paid cold after the trunk's run."""
        z = np.asarray(z, np.float64)
        cache = self.__dict__.setdefault("_cast_cache", {})
        one = z.ndim == 2 and z.shape[0] == 1 and self._asks_distances_twice()
        if one:
            key = z.tobytes()
            last = cache.get("last_press")
            if last is not None and last[0] == key:
                return last[1]
        means_t, means_sq = self._consts()[:2]
        d2 = (np.sum(z * z, axis=1)[:, None] - 2.0 * z @ means_t + means_sq[None, :]).clip(min=0.0)
        if one:
            d2.setflags(write=False)
            cache["last_press"] = (key, d2)
        return d2

    def _asks_distances_twice(self) -> bool:
        """Whether the evidence asks a press's distances again after the decision did: the outlier
        rule, or the offset rule's open-set rule."""
        return math.isfinite(self.outlier_ratio) or (self.item_rule == "offset" and math.isfinite(self.open_threshold))

    def scores(self, sq_distances: np.ndarray) -> np.ndarray:
        """(N, C) class scores s_c (module doc) from squared distances."""
        return -0.5 * np.asarray(sq_distances, np.float64) / self.temperature + self._consts()[2]

    def log_posterior(self, features: np.ndarray, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
        """(log softmax of the scores over all bundle classes, squared distances), both (N, C)."""
        return self.log_posterior_from_sq(self.sq_distances(features, dtype))

    def log_posterior_projected(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``log_posterior`` from projected presses (``sq_distances_projected``)."""
        return self.log_posterior_from_sq(self.sq_distances_projected(z))

    def log_posterior_from_sq(self, d2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = self.scores(d2)
        m = s.max(axis=1, keepdims=True)
        return s - (m + np.log(np.exp(s - m).sum(axis=1, keepdims=True))), d2

    def _item_terms(self, z_mean: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(squared distance of a piece's mean of ``n`` presses to each class mean, the offset
        rule's variance v_c = s_c + press_var / n, the synthesised-class mask), each (C,)."""
        if n < 1:
            raise SceneModelError(f"scene model: an item of {n} presses has no score")
        z = np.asarray(z_mean, np.float64).reshape(-1)
        means_t, means_sq, _, synth, offset_var = self._consts()
        d2 = (float(z @ z) - 2.0 * (z @ means_t) + means_sq).clip(min=0.0)
        return d2, self._offset_terms(n)[0], synth

    def _offset_terms(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The offset rule's terms that depend on ``n`` only, made once per ``n``: (v_c, the log
        term 0.5 k log v_c, the synthesised classes' bias)."""
        cache = self.__dict__.setdefault("_cast_cache", {}).setdefault("offset_terms", {})
        if n not in cache:
            _, _, _, synth, offset_var = self._consts()
            v = offset_var + self.press_var / n
            cache[n] = (v, 0.5 * self.k * np.log(v), self.item_bias * synth)
        return cache[n]

    def item_log_lik(self, z_mean: np.ndarray, n: int) -> np.ndarray:
        """(C,) the offset rule's item scores L_c (module doc) of a piece whose ``n`` presses have
        the mean projection ``z_mean`` (k,)."""
        d2, v, _ = self._item_terms(z_mean, n)
        _, log_term, bias = self._offset_terms(n)
        return (-0.5 * d2 / v - log_term) / self.item_temperature + bias

    def item_ratios(self, z_mean: np.ndarray, n: int) -> np.ndarray:
        """(C,) the squared distance of a piece's mean of ``n`` presses to each class mean over what
        the offset rule expects of that class's own pieces, k (s_c + press_var / n): about 1 for a
        piece of the class (``likeness_ratio``, module doc)."""
        d2, v, _ = self._item_terms(z_mean, n)
        return d2 / (self.k * v)

    def for_labels(self) -> "SceneModel | None":
        """The offset-rule model operator labels update (runtime/feedback.py): this one when its
        rule is the offset rule, a sum-rule model with its stored offset setting, else None.

        The stored setting never drops an off-scene rule the bundle's own rule has. Its open
        threshold is the stricter of the two (the same units in both rules: the mean over presses of
        the nearest scene class's squared distance). Where it has no known-class rule and the bundle's
        has one, it takes margin 0 - a known fabric the job leaves out that leads refuses the piece -
        since the two rules' margins are in different units. Else a first label, even of a stranger,
        would hand the job's classes to a rule that refuses nothing the bundle's rule refused."""
        if self.item_rule == "offset":
            return self
        if self.labels_rule is None:
            return None
        rule = dict(self.labels_rule)
        rule["open_threshold"] = min(float(rule.get("open_threshold", math.inf)), float(self.open_threshold))
        if not math.isfinite(float(rule.get("known_margin", math.inf))) and math.isfinite(float(self.known_margin)):
            rule["known_margin"] = 0.0
        return replace(self, item_rule="offset", labels_rule=None, **rule)

    def subset(self, classes) -> "SceneModel":
        """The same model over ``classes`` only (bundle classes, in the given order)."""
        missing = [c for c in classes if c not in self.classes]
        if missing:
            raise SceneModelError(f"scene model has no class {missing}")
        rows = [self.classes.index(c) for c in classes]
        var = None if self.class_offset_var is None else np.asarray(self.class_offset_var)[rows]
        return replace(self, classes=tuple(classes), untouched=frozenset(c for c in classes if c in self.untouched),
                       means=self.means[rows], class_offset_var=var, info=dict(self.info),
                       known_only=tuple(c for c in classes if c in self.known_only))

    # ------------------------------------------------------------------ fitting (numpy)

    @classmethod
    def fit(cls, touched_x: np.ndarray, touched_y: np.ndarray, touched: list[str],
            untouched_x: np.ndarray, untouched_y: np.ndarray, untouched: list[str], *, k: int = 64,
            shrinkage: float = 0.1, axes: np.ndarray | None = None) -> "SceneModel":
        """Subspace, shared covariance and touched means from real touched training presses
        (``touched_y`` indexes ``touched``); untouched means from synthesised features. ``axes``:
        the principal axes of these presses (``principal_axes``), when the caller fits several
        ``k`` on them - one SVD serves them all."""
        x = np.asarray(touched_x, np.float64)
        y = np.asarray(touched_y)
        if x.ndim != 2 or len(x) != len(y) or len(x) < 2:
            raise SceneModelError(f"scene model: need (N, D) touched features with N labels, got {x.shape}")
        center = x.mean(axis=0)
        vt = cls.principal_axes(x) if axes is None else axes
        if vt.ndim != 2 or vt.shape[1] != x.shape[1]:
            raise SceneModelError(f"scene model: principal axes of shape {vt.shape} for features of {x.shape[1]}")
        k = int(min(k, vt.shape[0]))
        proj = vt[:k].T
        z = (x - center) @ proj
        means_t = np.stack([z[y == c].mean(axis=0) for c in range(len(touched))])
        w = z - means_t[y]
        cov = w.T @ w / max(len(w) - len(touched), 1)
        cov = (1.0 - shrinkage) * cov + shrinkage * (np.trace(cov) / k) * np.eye(k)
        evals, evecs = np.linalg.eigh(0.5 * (cov + cov.T))
        evals = np.maximum(evals, 1e-12 * max(float(evals.max()), 1e-30))
        white = evecs / np.sqrt(evals)[None, :]
        basis = proj @ white
        zu = (np.asarray(untouched_x, np.float64) - center) @ basis
        uy = np.asarray(untouched_y)
        means_u = np.stack([zu[uy == c].mean(axis=0) for c in range(len(untouched))]) if untouched else \
            np.zeros((0, k))
        return cls(tuple(touched) + tuple(untouched), frozenset(untouched), center, basis,
                   np.concatenate([means_t @ white, means_u]), info={"k": k, "shrinkage": float(shrinkage)})

    @staticmethod
    def principal_axes(touched_x: np.ndarray) -> np.ndarray:
        """(min(N, D), D) the principal axes of the touched training presses, largest first: what
        ``fit`` projects onto (its ``axes``)."""
        x = np.asarray(touched_x, np.float64)
        return np.linalg.svd(x - x.mean(axis=0), full_matrices=False)[2]

    # ------------------------------------------------------------------ (de)serialisation

    def to_params(self) -> dict[str, Any]:
        return {"kind": KIND, "params_version": PARAMS_VERSION, "classes": np.array(self.classes),
                "untouched": np.array([c in self.untouched for c in self.classes]),
                "center": np.array(self.center), "basis": np.array(self.basis), "means": np.array(self.means),
                "temperature": float(self.temperature), "untouched_bias": float(self.untouched_bias),
                "evidence_weight": float(self.evidence_weight), "open_threshold": float(self.open_threshold),
                "known_margin": float(self.known_margin), "confidence": float(self.confidence),
                "untouched_confidence": float(self.untouched_confidence), "item_rule": np.array(self.item_rule),
                **{key: float(getattr(self, key)) for key in OFFSET_KEYS},
                **{f"labels_{key}": float(v) for key, v in (self.labels_rule or {}).items()},
                **({"known_only": np.array(self.known_only)} if self.known_only else {}),
                **({"refuse_early": np.array(True)} if self.refuse_early else {}),
                **({"outlier_ratio": float(self.outlier_ratio)} if math.isfinite(self.outlier_ratio) else {}),
                **({"likeness_ratio": float(self.likeness_ratio)} if math.isfinite(self.likeness_ratio) else {}),
                **({"extra_presses": np.array(int(self.extra_presses))} if self.extra_presses else {})}

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> "SceneModel":
        def scalar(key: str) -> float:
            if key not in params:
                raise SceneModelError(f"scene model parameters lack '{key}'")
            try:
                return float(np.asarray(params[key]).reshape(()))
            except (TypeError, ValueError):
                raise SceneModelError(f"scene model '{key}' is not a number") from None

        if str(np.asarray(params.get("kind", "")).reshape(())) != KIND:
            raise SceneModelError(f"scene model parameters are not '{KIND}'")
        if int(scalar("params_version")) != PARAMS_VERSION:
            raise SceneModelError(f"scene model parameters version {params['params_version']}, "
                                  f"this runtime reads {PARAMS_VERSION}")
        unknown = sorted(str(key) for key in params if key not in PARAMS_KEYS)
        if unknown:
            raise SceneModelError(f"scene model parameters carry {', '.join(map(repr, unknown))}, which this runtime "
                                  "does not know: a rule of a newer training that it would leave out of every "
                                  "decision. Update the runtime, or export the bundle with the runtime's version")
        for key in ("classes", "untouched", "center", "basis", "means"):
            if key not in params:
                raise SceneModelError(f"scene model parameters lack '{key}'")
        classes = tuple(str(c) for c in np.asarray(params["classes"]).reshape(-1))
        flags = np.asarray(params["untouched"]).reshape(-1).astype(bool)
        center = np.asarray(params["center"], np.float64).reshape(-1)
        basis = np.asarray(params["basis"], np.float64)
        means = np.asarray(params["means"], np.float64)
        d = center.shape[0]
        if basis.ndim != 2 or basis.shape[0] != d or means.shape != (len(classes), basis.shape[1]) \
                or flags.shape != (len(classes),):
            raise SceneModelError(f"scene model shapes disagree: center {center.shape}, basis {basis.shape}, "
                                  f"means {means.shape}, {len(classes)} classes")
        if not (np.all(np.isfinite(center)) and np.all(np.isfinite(basis)) and np.all(np.isfinite(means))):
            raise SceneModelError("scene model parameters contain NaN or Inf")
        temperature, bias = scalar("temperature"), scalar("untouched_bias")
        weight, conf, conf_u = scalar("evidence_weight"), scalar("confidence"), scalar("untouched_confidence")
        open_thr, margin = (_refusal_rule(scalar(key), key) for key in ("open_threshold", "known_margin"))
        if not (temperature > 0 and math.isfinite(temperature) and math.isfinite(bias)
                and 0 < weight <= 1 and 0 < conf <= 1 and 0 < conf_u <= 1):
            raise SceneModelError(f"scene model scalars out of range: temperature {temperature}, bias {bias}, "
                                  f"evidence_weight {weight}, confidence {conf}/{conf_u}, open_threshold {open_thr}, "
                                  f"known_margin {margin}")
        known_only = tuple(str(c) for c in np.asarray(params.get("known_only", np.array([], str))).reshape(-1))
        if known_only and (classes[len(classes) - len(known_only):] != known_only
                           or any(flags[len(classes) - len(known_only):]) or len(set(classes)) != len(classes)):
            raise SceneModelError(f"scene model known_only {list(known_only)} are not its last classes, touched "
                                  "kind, each once")
        refuse_early = np.asarray(params.get("refuse_early", False)).reshape(())
        if refuse_early.dtype != bool:
            raise SceneModelError(f"scene model refuse_early is {refuse_early.dtype}, not a boolean")
        # below 1 a press (a piece) at its class's own spread would be no evidence (refused)
        outlier_ratio, likeness_ratio = _ratio(params, "outlier_ratio"), _ratio(params, "likeness_ratio")
        model = cls(classes, frozenset(c for c, u in zip(classes, flags) if u), center, basis, means,
                    temperature, bias, weight, open_thr, margin, conf, conf_u, known_only=known_only,
                    refuse_early=bool(refuse_early), outlier_ratio=outlier_ratio, likeness_ratio=likeness_ratio,
                    extra_presses=_count(params, "extra_presses"))
        # a file written before the offset rule has none of its keys: the sum rule, as it was
        rule = str(np.asarray(params.get("item_rule", "sum")).reshape(()))
        if rule not in ITEM_RULES:
            raise SceneModelError(f"scene model item_rule {rule!r}: this runtime knows {', '.join(ITEM_RULES)}")
        if rule == "sum":
            if not any(f"labels_{key}" in params for key in LABELS_KEYS):
                return model
            labels = {key: scalar(f"labels_{key}") for key in LABELS_KEYS}
            _check_offset(labels, "labels_")
            for key in ("open_threshold", "known_margin"):
                _refusal_rule(labels[key], f"labels_{key}")
            if not (0 < labels["confidence"] <= 1 and 0 < labels["untouched_confidence"] <= 1):
                raise SceneModelError(f"scene model labels_ operating point out of range: {labels}")
            return replace(model, labels_rule=labels)
        offset = {key: scalar(key) for key in OFFSET_KEYS}
        _check_offset(offset, "")
        return replace(model, item_rule=rule, **offset)


def _refusal_rule(value: float, key: str) -> float:
    """``open_threshold`` / ``known_margin`` (and their ``labels_`` twins): a number of at least 0,
    or +inf - the rule off, as training's grids write it. -inf was taken for off too (the rules run
    on a finite value only), though by its arithmetic it refuses every piece; below 0 the open-set
    rule refuses every piece (a mean squared distance is never negative) and the known-class rule
    refuses pieces the job explains better than any class it leaves out; NaN compares false
    everywhere. None of these is a choice training makes: refused, naming the key."""
    if not value >= 0:
        raise SceneModelError(f"scene model '{key}' = {value:g}: must be a number of at least 0, or inf (the rule "
                              "off)")
    return value


def _ratio(params: Mapping[str, Any], key: str) -> float:
    """An optional ratio of the parameters (inf, off, when absent): a number of at least 1."""
    if key not in params:
        return math.inf
    raw = np.asarray(params[key])
    if raw.shape != () or raw.dtype.kind not in "fiu":
        raise SceneModelError(f"scene model {key} is {raw.dtype} of shape {raw.shape}, not a number")
    if not float(raw) >= 1:
        raise SceneModelError(f"scene model {key} {float(raw)} must be at least 1 (inf: off)")
    return float(raw)


MAX_EXTRA_PRESSES = 64  # more than a grid's points: a file asking for more is not one training wrote


def _count(params: Mapping[str, Any], key: str) -> int:
    """An optional press count of the parameters (0 when absent): a whole number 0..MAX_EXTRA_PRESSES."""
    if key not in params:
        return 0
    raw = np.asarray(params[key])
    if raw.shape != () or raw.dtype.kind not in "iu":
        raise SceneModelError(f"scene model {key} is {raw.dtype} of shape {raw.shape}, not a whole number")
    if not 0 <= int(raw) <= MAX_EXTRA_PRESSES:
        raise SceneModelError(f"scene model {key} {int(raw)} must be between 0 and {MAX_EXTRA_PRESSES}")
    return int(raw)


def _check_offset(offset: Mapping[str, float], prefix: str) -> None:
    if not (offset["press_var"] > 0 and offset["offset_var_touched"] >= 0 and offset["offset_var_untouched"] >= 0
            and offset["item_temperature"] > 0 and all(math.isfinite(offset[k]) for k in OFFSET_KEYS)):
        raise SceneModelError(f"scene model {prefix}offset rule scalars out of range: "
                              f"{ {k: offset[k] for k in OFFSET_KEYS} }")


__all__ = ["SceneModel", "SceneModelError", "KIND", "PARAMS_VERSION", "PARAMS_KEYS", "ITEM_RULES", "OFFSET_KEYS",
           "LABELS_KEYS"]

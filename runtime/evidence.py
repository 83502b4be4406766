"""Evidence over several presses of one item, in log space, with a sequential stopping rule.

Each press gives a normalised log posterior over the bundle's classes (runtime/inference.py).
Only the scene's classes count: the per-press posterior is restricted to them and renormalised,
then log posteriors are summed, each multiplied by ``weight`` (1: independent presses; below 1:
presses of one piece are not independent - they share the piece, and a model's error on a fabric
repeats on every press - so summing them at full weight makes the posterior overconfident; the
bundle's scene model carries a weight fitted on validation fabrics, runtime/scene_model.py), and
renormalised with a stable logsumexp, so 225 presses never underflow. Stop when the leading class
reaches ``confidence`` (after ``min_presses``) or at ``max_presses``; at the limit an unconfident
item is "unknown" (the reject bin).

Off-scene checks (off unless set; the scene model sets both):
- ``open_threshold``: the mean over presses of the smallest squared distance to a scene class
  (``PressScore.sq_distance``; with an ``item_model``, from the press's projection to that model's
  means, which operator labels may have moved) above it means the piece is like none of the
  scene's fabrics;
- ``known_margin``: a bundle class outside the scene whose summed (weighted) log posterior beats
  the leading scene class's by more than it means the piece is a fabric the cell knows that this
  job does not list.
- under the offset rule (``item_model`` below) with a finite ``likeness_ratio``: the presses'
  mean lies farther from the leading scene class than that many times what the class's own pieces
  lie at (``SceneModel.item_ratios``): the piece leads a class it does not feel like.
Any of them makes the item "unknown" (``stopped_by`` "off_scene"), confident or not.
``refuse_early``: a piece whose leading class over every known class is one the job leaves out,
at ``confidence`` (and by ``known_margin`` over the scene's best), goes to the reject bin at that
press instead of at the press limit: more presses would only risk it becoming confident for a job
fabric. Off unless set (the scene model's operating point sets it when validation keeps it).
``class_confidence`` sets the posterior needed per class where it differs from ``confidence``.
``outlier_model`` (a scene model with a finite ``outlier_ratio``, or anything with its
``is_outlier_press``, runtime/feedback.py ``FarFromBoth``): a press it calls an outlier - farther
from every class than that many spreads, ``SceneModel.is_outlier_press`` - counts as a press (it
took the arm's time and one of ``max_presses``) but is no evidence: nothing is added, and the
offset rule's mean leaves it out; the open-set rule still reads it (far from every fabric is what
a stranger's presses are). A piece none of whose presses was evidence is decisive for no
class: at the limit it goes to the reject bin (``stopped_by`` "off_scene": like no fabric known).

``extra_presses`` (0: off): a piece that at ``max_presses`` is not confident, is led by one of
``extend_classes`` (the scene model's touched classes: real means, whose evidence keeps growing
with presses where a synthesised class's saturates; runtime/operating_point.py
``touched_classes``) and is refused by no off-scene rule takes up to that many presses more, and
is decided as soon as it is confident or refused or the leader changes kind (``press_limit``: the
most presses an item may take; ``at_limit``: whether it has taken all it may). On the paper
world's test jobs the touched pieces left unconfident at 5 presses are nearly all led by their
own fabric (docs/results/scene_decision_rules_paper.md).

``item_model`` (a ``runtime.scene_model.SceneModel`` whose ``item_rule`` is "offset") replaces the
summed log posteriors by the model's item scores of the presses' mean projection
(``PressScore.scene_z``; ``SceneModel.item_log_lik``): the scene posterior is their softmax over
the scene's classes, and the known-class rule compares them for classes outside and inside the
scene. ``weight`` is then unused; the confidences and the open-set rule are as above.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

UNKNOWN = "unknown"


@dataclass(frozen=True)
class ItemDecision:
    label: str
    confidence: float
    presses: int
    log_posterior: dict[str, float]
    stopped_by: str  # "confident" | "press_limit" | "off_scene"


def _logsumexp(x: np.ndarray) -> float:
    # ndarray methods, not np.max / np.sum: the same reductions without their Python wrappers (the
    # evidence runs a dozen of them a press, each paid cold after the trunk's run)
    m = float(x.max())
    if not math.isfinite(m):
        return m
    return m + math.log(float(np.exp(x - m).sum()))


class Evidence:
    def __init__(self, scene_classes, confidence: float = 0.95, max_presses: int = 9,
                 min_presses: int = 1, unknown_floor: float | None = None, *, weight: float = 1.0,
                 open_threshold: float = math.inf, known_margin: float = math.inf,
                 class_confidence: dict[str, float] | None = None, item_model=None, refuse_early: bool = False,
                 outlier_model=None, extra_presses: int = 0, extend_classes=()):
        self.classes = list(dict.fromkeys(scene_classes))
        if not self.classes:
            raise ValueError("Evidence: the scene has no classes")
        if not 0.0 < confidence <= 1.0:
            raise ValueError(f"Evidence: confidence = {confidence} must be in (0, 1]")
        if max_presses < 1 or min_presses < 1 or min_presses > max_presses:
            raise ValueError(f"Evidence: need 1 <= min_presses ({min_presses}) <= max_presses ({max_presses})")
        if not 0.0 < weight <= 1.0:
            raise ValueError(f"Evidence: weight = {weight} must be in (0, 1]")
        for key, value in (("open_threshold", open_threshold), ("known_margin", known_margin)):
            if not value >= 0:  # -inf would switch the rule off below (it runs on a finite value only)
                raise ValueError(f"Evidence: {key} = {value} must be at least 0, or inf (the rule off)")
        if extra_presses < 0:
            raise ValueError(f"Evidence: extra_presses = {extra_presses} must be at least 0")
        self.confidence, self.max_presses, self.min_presses = confidence, max_presses, min_presses
        self.extra_presses = int(extra_presses)
        extend = set(extend_classes)
        self._extend = np.array([c in extend for c in self.classes])  # leaders that earn extra presses
        self.weight, self.open_threshold, self.known_margin = weight, open_threshold, known_margin
        self.refuse_early = bool(refuse_early)
        # the posterior that sorts into a class when it differs from ``confidence`` (the scene model
        # asks more of an untouched class, whose mean the generator synthesised, than of a touched one)
        self._needed = np.array([float((class_confidence or {}).get(c, confidence)) for c in self.classes])
        if not np.all((self._needed > 0) & (self._needed <= 1)):
            raise ValueError(f"Evidence: class_confidence {class_confidence} must be in (0, 1]")
        self._outside: dict[str, float] = {}  # weighted sums of log posteriors of bundle classes outside the scene
        # the offset rule's item scores of those classes, in item-model order (a dict of them per
        # press was a fifth of the evidence's time a press); ``_outside_values`` reads either
        self._outside_scores: np.ndarray | None = None
        self._inside = np.zeros(len(self.classes), dtype=np.float64)  # the same, unrenormalised, for scene classes
        self._open_sum, self._open_n = 0.0, 0
        # below this leading posterior the item is "unknown" even at the limit (default: confidence)
        self.unknown_floor = confidence if unknown_floor is None else unknown_floor
        self._floor_given = unknown_floor is not None
        self._acc = np.zeros(len(self.classes), dtype=np.float64)
        self.presses = 0
        self.outliers = 0  # presses ``outlier_model`` called no evidence (module doc)
        self.outlier_model = outlier_model
        self.item_model = item_model
        if item_model is not None:
            missing = [c for c in self.classes if c not in item_model.classes]
            if missing:
                raise ValueError(f"Evidence: the item model has no class {missing} of the scene")
            self._rows = np.array([item_model.classes.index(c) for c in self.classes])
            self._others = np.setdiff1d(np.arange(len(item_model.classes)), self._rows)
            self._z_sum = np.zeros(item_model.k, dtype=np.float64)
            self._z_all = np.zeros(item_model.k, dtype=np.float64)  # outlier presses too (``z_mean``)
        self._open_rows: np.ndarray | None = None  # item-model rows of the scene classes the open-set rule reads
        self._likeness: np.ndarray | None = None  # the scene classes' ``item_ratios`` when the rule is on

    def need_at_most_touched(self, classes) -> None:
        """From now on ``classes`` of the scene need at most the touched ``confidence``: operator
        labels made their means real presses, like a touched fabric's (runtime/feedback.py)."""
        for c in classes:
            i = self.classes.index(c)
            self._needed[i] = min(self._needed[i], self.confidence)

    def _posterior(self) -> np.ndarray:
        return self._acc - _logsumexp(self._acc)

    @property
    def used_presses(self) -> int:
        """The presses that were evidence (``presses`` less the outliers)."""
        return self.presses - self.outliers

    def _skip_outlier(self, score, z: np.ndarray | None = None) -> bool:
        """Count the press as an outlier when ``outlier_model`` calls it one (from its projection
        ``z`` when given, else its squared distances); False (count nothing) otherwise."""
        if self.outlier_model is None or not self.outlier_model.is_outlier_press(
                z, None if z is not None else getattr(score, "sq_distance", None)):
            return False
        self.presses += 1
        self.outliers += 1
        return True

    def add(self, score) -> ItemDecision | None:
        if self.item_model is not None:
            return self._add_projected(score)
        if self._skip_outlier(score):
            self._add_open(score)  # far from every fabric: evidence of a stranger all the same
            return self._check(final=False)
        lp = score.log_posterior
        missing = [c for c in self.classes if c not in lp]
        if missing:
            raise KeyError(f"Evidence: press score has no class {missing} of the scene")
        v = np.array([float(lp[c]) for c in self.classes], dtype=np.float64)
        if np.isnan(v).any():
            raise ValueError("Evidence: press score has NaN log posterior")
        if math.isfinite(self.known_margin):
            # before the zeroing below: a press no scene class can have made is evidence against
            # the job's fabrics here, not perfect evidence for them that hides a known outside one
            self._inside += self.weight * np.maximum(v, -1e300)
            for c, val in lp.items():
                if c not in self.classes:
                    if math.isnan(val := float(val)):  # max(NaN, x) is NaN: the known-class rule off for the piece
                        raise ValueError(f"Evidence: press score has NaN log posterior for {c} (outside the scene)")
                    self._outside[c] = self._outside.get(c, 0.0) + self.weight * max(val, -1e300)
        self._add_open(score)
        if not np.isfinite(v).any():  # no scene class possible from this press: uninformative for the posterior
            v = np.zeros_like(v)
        v = v - _logsumexp(v)
        self._acc = self._acc + self.weight * np.maximum(v, -1e300)  # keep -inf out of sums (inf - inf = NaN)
        self.presses += 1
        return self._check(final=False)

    def _add_open(self, score, z: np.ndarray | None = None) -> None:
        d2 = getattr(score, "sq_distance", None)
        if math.isfinite(self.open_threshold) and d2:
            # the scene's fabrics (a stranger the operator taught, runtime/feedback.py, has no press distance)
            if z is None:
                self._open_sum += float(np.min([float(d2[c]) for c in self.classes if c in d2]))  # NaN stays NaN
            else:
                # the item model's own means: where operator labels moved a class's mean to its real
                # presses, the distance to the learned mean, not to the bundle's synthesis the press
                # was scored against (which would refuse that fabric's pieces as off-scene for ever)
                if self._open_rows is None:
                    self._open_rows = np.array([self.item_model.classes.index(c) for c in self.classes if c in d2])
                own = self.item_model.sq_distances_projected(z[None, :])[0]
                self._open_sum += float(own[self._open_rows].min())
            if math.isnan(self._open_sum):  # NaN > threshold is False: the open-set rule off for the piece
                raise ValueError("Evidence: press score has a NaN squared distance")
            self._open_n += 1

    def _add_projected(self, score) -> ItemDecision | None:
        """The offset rule (module doc): item scores of the presses' mean projection."""
        z = getattr(score, "scene_z", None)
        if z is None:
            raise ValueError("Evidence: the scene model's offset rule needs the press's projection (scene_z), "
                             "and this press score has none")
        z = np.asarray(z, dtype=np.float64).reshape(-1)
        if z.shape != self._z_sum.shape or not np.isfinite(z).all():
            raise ValueError(f"Evidence: press projection of shape {z.shape} (finite: {bool(np.all(np.isfinite(z)))}), "
                             f"expected ({self._z_sum.shape[0]},) finite")
        self._z_all += z
        self._add_open(score, z)  # an outlier press too: far from every fabric is evidence of a stranger
        if self._skip_outlier(score, z):
            return self._check(final=False)
        self._z_sum += z
        self.presses += 1
        n = self.used_presses
        scores = self.item_model.item_log_lik(self._z_sum / n, n)
        self._acc = scores[self._rows]
        if math.isfinite(getattr(self.item_model, "likeness_ratio", math.inf)):
            self._likeness = self.item_model.item_ratios(self._z_sum / n, n)[self._rows]
        if math.isfinite(self.known_margin):
            self._inside = self._acc
            self._outside_scores = scores[self._others] if self._others.size else None
        return self._check(final=False)

    @property
    def z_mean(self) -> np.ndarray | None:
        """The mean projection of the presses that were evidence (the offset rule's), of every
        press when none was (what an operator's label of the piece teaches: a fabric whose every
        press lies far from every class is the one a label must be able to teach); None without
        presses or an item model. ``mean_presses`` says how many it averages."""
        if self.item_model is None or not self.presses:
            return None
        return self._z_sum / self.used_presses if self.used_presses else self._z_all / self.presses

    @property
    def mean_presses(self) -> int:
        """How many presses ``z_mean`` averages."""
        return self.used_presses or self.presses

    def decide(self) -> ItemDecision:
        return self._check(final=True)

    def peek(self) -> ItemDecision | None:
        """What ``add`` returned for the presses so far: a decision, or None (press on)."""
        return self._check(final=False)

    def off_scene(self) -> bool:
        """Whether the presses so far say the piece is none of the scene's fabrics (module doc)."""
        if self._open_n and self._open_sum / self._open_n > self.open_threshold:
            return True
        if self._likeness is not None and self._likeness[int(self._acc.argmax())] > self.item_model.likeness_ratio:
            return True
        outside = self._outside_values()
        if outside is not None:
            best_in = float(self._inside.max())
            return float(outside.max()) > best_in + self.known_margin
        return False

    def _outside_values(self) -> np.ndarray | None:
        """The scores of the bundle classes outside the scene (float64), or None before any or
        without any: the offset rule's item scores, or the sum rule's summed log posteriors."""
        if self._outside_scores is not None:
            return self._outside_scores
        return np.fromiter(self._outside.values(), np.float64, len(self._outside)) if self._outside else None

    def known_outsider(self) -> bool:
        """Whether a class the job leaves out leads every known class at ``confidence`` and beats
        the scene's best by ``known_margin`` (``refuse_early``; False when it is off)."""
        outside = self._outside_values() if self.refuse_early else None
        if outside is None:
            return False
        best_out = float(np.max(outside))
        if not best_out > float(np.max(self._inside)) + self.known_margin:
            return False
        every = np.concatenate([np.asarray(self._inside, np.float64), outside])
        return math.exp(best_out - _logsumexp(every)) >= self.confidence

    def _decisive(self, post: np.ndarray, i: int) -> bool:
        """Whether the presses can pick a bin at all: at least ``min_presses`` of them, and a
        leading class ahead of every other (a tie - a two-fabric scene at confidence 0.5 - would
        otherwise sort to whichever fabric the scene lists first)."""
        return self.used_presses >= self.min_presses and int((post == post[i]).sum()) == 1

    @property
    def press_limit(self) -> int:
        """The most presses an item may take: ``max_presses``, and ``extra_presses`` more for a
        piece that earns them (module doc)."""
        return self.max_presses + self.extra_presses

    def _extending(self, post: np.ndarray, i: int) -> bool:
        """Whether a piece at or past ``max_presses`` presses on: extra presses left, a leader of
        ``extend_classes`` ahead of every other class, and no off-scene rule refusing it."""
        return (self.presses < self.press_limit and bool(self._extend[i]) and bool(self.used_presses)
                and self._decisive(post, i) and not self.off_scene())

    def at_limit(self) -> bool:
        """Whether the item has taken every press it may (``max_presses``, or more while it earns
        ``extra_presses``)."""
        if self.presses < self.max_presses:
            return False
        post = self._posterior()
        return not self._extending(post, int(post.argmax()))

    def _check(self, final: bool) -> ItemDecision | None:
        post = self._posterior()
        i = int(post.argmax())
        confident = self._decisive(post, i) and math.exp(float(post[i])) >= self._needed[i]
        if confident and not self.off_scene():
            return self._make(post, "confident")
        if self.known_outsider():  # a fabric the job leaves out, surely: refused now (refuse_early)
            return self._make(post, "off_scene")
        if final or (self.presses >= self.max_presses and not self._extending(post, i)):
            return self._make(post, "off_scene" if self.off_scene() or not self.used_presses else "press_limit")
        return None

    def _make(self, post: np.ndarray, stopped_by: str) -> ItemDecision:
        i = int(np.argmax(post))
        conf = math.exp(float(post[i]))
        floor = self.unknown_floor if self._floor_given else float(self._needed[i])
        sure = stopped_by == "confident" or (stopped_by == "press_limit" and conf >= floor
                                             and self._decisive(post, i))
        label = self.classes[i] if sure else UNKNOWN
        return ItemDecision(label, conf, self.presses, {c: float(p) for c, p in zip(self.classes, post)}, stopped_by)

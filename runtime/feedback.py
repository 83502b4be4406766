"""The cell learns from its reject bin: operator labels re-estimate the untouched fabrics' means.

Zero-shot, an untouched fabric's class mean is the generator's synthesis from camera and
attributes, off its real mean by the generator's error on that fabric - the same on every piece
(runtime/scene_model.py, the offset item rule). That error, not the presses, is what keeps most
untouched pieces out of their bin (docs/results/zero_shot_limits_paper.md). A person already looks at
every piece in the reject bin; when they say what it was (``vs2t-edge label``), the piece's presses
are real tactile data of that fabric, and the next pieces of it are scored against a mean that
moves from the synthesis towards the fabric's real one.

The update is the offset model's own, no new knob: a synthesised mean m is the true mean mu
plus the generator's error, mu ~ N(m, s_u I); a labelled piece's press mean zbar_j of n_j presses
is mu plus the piece's own offset plus press noise, zbar_j ~ N(mu, (s_t + v / n_j) I). So

    precision  P = 1 / s_u + sum_j 1 / (s_t + v / n_j),
    mean       mu_post = (m / s_u + sum_j zbar_j / (s_t + v / n_j)) / P,

and a new piece's mean zbar ~ N(mu_post, (1 / P + s_t + v / n) I): the class's offset variance
becomes 1 / P + s_t (``SceneModel.class_offset_var``), and it is scored without the untouched
bias (``SceneModel.taught``): validation fitted that bias to price a synthesised mean against real
ones, and this mean is real presses now. (Kept, it let a touched fabric the job leaves out - a felt
of another colour - explain the demo's taught felt's pieces better than their own taught mean, and
refuse all of them.) s_u, s_t and v are the bundle's
(``offset_var_untouched``, ``offset_var_touched``, ``press_var``), chosen on validation fabrics in
training; so it needs an offset-rule setting: the bundle's own, or for a sum-rule bundle the offset
setting training searched on the same validation jobs (``SceneModel.for_labels``; the bundle's own
rule still decides until a label teaches something). Touched fabrics' means come from their training
presses and are left alone; a label naming one is recorded and not applied. A piece the operator
calls off-scene (none of the job's fabrics) teaches a stranger: a class ``off-scene:NAME`` at its
labelled pieces' mean (no prior: nothing synthesised it), decided like any class and sent, being
no fabric of the job, to the reject bin.

A taught class needs at most the touched confidence (``evidence.confidence``) and at most the
untouched one: its mean is real presses, known as well as a touched fabric's and better than a
synthesis. (Held at the untouched one alone, it went to reject where validation could not price
that one and training held it near 1.) Not so a taught class still guarded as a twin (below),
which keeps the untouched one, nor a learned stranger, whose pieces go to the reject bin anyway.

A class no label taught is guarded (``GuardedEvidence``): sorted only where the zero-shot model,
on the same presses, decides the same class - labels make the cell surer of what they taught,
never bolder about an untouched fabric they did not teach. (On a sum-rule bundle, whose labels
rule is another operating point than its own, what no label taught - touched classes too - is
decided by the bundle's own rule as zero-shot: ``ZeroShotUnlessTaught``.) On an offset-rule bundle
touched classes are not guarded: their means were real already (and the rule labels switch to
keeps every off-scene rule the bundle's own has, ``SceneModel.for_labels``: a sum-rule bundle's
stored offset setting may have had none). Nor is a taught class - unless an untouched fabric of the
job that no label taught may feel like it (``confusable``): the generator put the two syntheses
closer than its own error (within the 99 % region of the offset model's N(m, s_u I)), so it could
not tell the two fabrics apart, and the taught mean says nothing of where the other fabric's pieces
lie. The taught class is then guarded too (``stopped_by`` "confusable_guard") until a label teaches
the other fabric as well: found on the paper world, where one label of a jersey sent every piece of
its touch-twin (another colour of the same knit) into its bin.

So on an offset-rule bundle a label that moves an untouched fabric's mean off a touched one makes
the cell surer of that touched fabric too: of its own pieces, and of a piece of no job fabric that
lay between the two and was unconfident before, unless an off-scene rule refuses it.

This is a mode outside the zero-shot protocol, on only when the cell config names a labels file
(``evidence.operator_labels``), and measured as such (train/decision.py ``evaluate_scenes``,
"with operator labels"): the pure zero-shot numbers stay the product's headline.

The operator's labels file, the journal records of what the cell did with each label and the
state a restarted service rebuilds from them are runtime/labels.py (``OperatorFeedback``).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from vs2t_edge.runtime.evidence import UNKNOWN, Evidence, ItemDecision
from vs2t_edge.runtime.names import OFF_SCENE_PREFIX
from vs2t_edge.runtime.scene_model import SceneModel, SceneModelError


def _piece_weights(model: SceneModel, fabric: str, pieces) -> tuple[float, np.ndarray]:
    """(sum of the pieces' precisions, their precision-weighted sum of press means)."""
    s_t, v = model.offset_var_touched, model.press_var
    precision, weighted = 0.0, np.zeros(model.k)
    for zbar, n in pieces:
        if n < 1:
            raise SceneModelError(f"operator labels: a piece of {fabric!r} with {n} presses")
        w = 1.0 / (s_t + v / n)
        precision += w
        weighted = weighted + w * np.asarray(zbar, np.float64).reshape(-1)
    return precision, weighted


def labels_teach(model: SceneModel) -> bool:
    """Whether a label moves an untouched class's mean under ``model``'s offsets (``adapt``): with no
    offset for syntheses (``offset_var_untouched`` 0, a perfect synthesis) there is nothing to learn."""
    return model.offset_var_untouched > 0


def adapt(model: SceneModel, labelled: Mapping[str, Sequence[tuple[np.ndarray, int]]],
          strangers: Mapping[str, Sequence[tuple[np.ndarray, int]]] | None = None) -> SceneModel:
    """``model`` with each untouched class of ``labelled`` (class -> [(press mean, presses), ...])
    re-estimated from its labelled pieces, and one class ``off-scene:NAME`` per stranger the
    operator named (module doc). Classes without pieces are unchanged."""
    if model.item_rule != "offset":
        raise SceneModelError("operator labels need the scene model's offset item rule (its offset variances "
                              f"weigh a labelled piece against the synthesis); this bundle's rule is "
                              f"{model.item_rule!r}")
    means = np.array(model.means, np.float64, copy=True)
    is_u = np.array([c in model.untouched for c in model.classes])
    var = model.offset_vars()  # a fresh array: rows of labelled classes are replaced below
    s_u, s_t = model.offset_var_untouched, model.offset_var_touched
    taught = set(model.taught)
    for fabric, pieces in labelled.items():
        if fabric not in model.classes:
            raise SceneModelError(f"operator labels: the scene model has no class {fabric!r}")
        c = model.classes.index(fabric)
        if not is_u[c] or not pieces or not labels_teach(model):
            continue
        precision, weighted = _piece_weights(model, fabric, pieces)
        precision += 1.0 / s_u  # the synthesis is the prior: mu ~ N(m, s_u I)
        means[c] = (weighted + means[c] / s_u) / precision
        var[c] = 1.0 / precision + s_t
        taught.add(fabric)
    names, rows, extra_var = [], [], []
    for name, pieces in (strangers or {}).items():
        if not pieces:
            continue
        precision, weighted = _piece_weights(model, name, pieces)  # no prior: nothing synthesised it
        names.append(OFF_SCENE_PREFIX + name)
        rows.append(weighted / precision)
        extra_var.append(1.0 / precision + s_t)
    if names:
        means = np.concatenate([means, np.stack(rows)])
        var = np.concatenate([var, extra_var])
    return replace(model, classes=tuple(model.classes) + tuple(names), means=means, class_offset_var=var,
                   taught=frozenset(taught))


CONFUSABLE_Z = 2.326  # the 99 % quantile of the standard normal: ``confusable``'s region


def _chi2_quantile(k: int, z: float = CONFUSABLE_Z) -> float:
    """The chi-square quantile of ``k`` degrees of freedom at the normal quantile ``z``
    (Wilson-Hilferty; within 0.3 % of the exact value from k = 10 on)."""
    c = 2.0 / (9.0 * k)
    return k * (1.0 - c + z * c ** 0.5) ** 3


def confusable(model: SceneModel, offset_var_untouched: float, taught: Iterable[str],
               untaught: Iterable[str]) -> dict[str, list[str]]:
    """For each ``taught`` class, the ``untaught`` untouched classes whose synthesis in ``model``
    (the bundle's, before any label) lies within the generator's error of the taught class's
    synthesis: ||m_taught - m||^2 <= s_u chi2_0.99(k), s_u = ``offset_var_untouched`` (module doc)."""
    untaught = [c for c in untaught if c in model.classes]
    if offset_var_untouched <= 0 or not untaught:
        return {}
    radius2 = offset_var_untouched * _chi2_quantile(model.k)
    means = np.asarray(model.means, np.float64)
    rows_u = [model.classes.index(c) for c in untaught]
    out = {}
    for t in taught:
        if t not in model.classes:
            continue
        d2 = ((means[rows_u] - means[model.classes.index(t)]) ** 2).sum(axis=1)
        near = [c for c, v in zip(untaught, d2) if v <= radius2]
        if near:
            out[t] = near
    return out


class _PairedEvidence:
    """Two evidences that see every press of a piece: ``adapted`` (the labels' model) and
    ``zero_shot`` (the bundle's own). The piece's presses and press mean are the adapted one's,
    which sees every press: what its ``pre_sort`` record keeps and a later label reads."""

    def __init__(self, adapted: Evidence, zero_shot: Evidence) -> None:
        self.adapted, self.zero_shot = adapted, zero_shot

    @property
    def presses(self) -> int:
        return self.adapted.presses

    @property
    def mean_presses(self) -> int:
        return self.adapted.mean_presses

    @property
    def z_mean(self):
        return self.adapted.z_mean


class GuardedEvidence(_PairedEvidence):
    """The item evidence with labels, never bolder than zero-shot where no label taught it.

    Two evidences see every press: one scored with the adapted model, one with the bundle's own.
    A ``trusted`` class - one the labels taught (an untouched fabric with labelled pieces, a
    learned stranger) or a touched one (its mean was real already) - is decided by the adapted one
    alone. Any other class is sorted only when the zero-shot evidence decides the same class: a
    labelled class whose synthesis used to share a piece with
    another synthesised class stops sharing it once its mean is real, and that piece - a fabric
    the job does not list, between the two syntheses - would otherwise go to the other class's
    bin with a confidence the zero-shot operating point never gave it (measured on the demo's job:
    every piece of such a fabric mis-sorted). The cell keeps pressing while the two disagree, up to
    the press limit, where the piece goes to the reject bin (``stopped_by`` "unlabelled_guard")."""

    def __init__(self, adapted: Evidence, zero_shot: Evidence, trusted: Iterable[str],
                 confusable_with: Mapping[str, Sequence[str]] | None = None) -> None:
        super().__init__(adapted, zero_shot)
        self.trusted = frozenset(trusted)
        self.confusable_with = dict(confusable_with or {})  # taught, yet guarded (module doc)

    @property
    def press_limit(self) -> int:
        return self.adapted.press_limit  # the adapted evidence decides; the zero-shot one only agrees

    def _guarded(self, d, final: bool):
        if d is None or d.label == UNKNOWN or d.label in self.trusted:
            return d
        z = self.zero_shot.decide() if final or d.stopped_by != "confident" else self.zero_shot.peek()
        if z is not None and z.label == d.label:
            return d
        if final or self.adapted.at_limit():
            why = "confusable_guard" if d.label in self.confusable_with else "unlabelled_guard"
            return ItemDecision(UNKNOWN, d.confidence, d.presses, d.log_posterior, why)
        return None  # press on: the zero-shot evidence may yet agree

    def add(self, score):
        self.zero_shot.add(score)
        return self._guarded(self.adapted.add(score), final=False)

    def decide(self):
        return self._guarded(self.adapted.decide(), final=True)


class ZeroShotUnlessTaught(_PairedEvidence):
    """The item evidence with labels for a sum-rule bundle: its own rule decides every piece as it
    does zero-shot, except one the labels' rule puts into a class a label taught.

    A sum-rule bundle's labels rule is another operating point (its stored offset setting,
    ``SceneModel.for_labels``), which validation may have rated far below the bundle's own. Trusted
    with the touched classes (``GuardedEvidence``), one label - even a stranger's - moved every
    touched piece to that point: on a demo_visible job (docs/results/demo_visible_world.md) touched
    pieces went from 83 to 25 % right, and untouched pieces into a touched sibling's bin. Here what
    no label taught keeps the bundle's decision: the zero-shot evidence's, at the press it stops.
    Labels only add: while the labels' rule leads a taught class (``taught``: labelled untouched
    fabrics that are not guarded twins, learned strangers) the cell presses on, and the piece goes
    to that class once the labels' rule is confident of it; the zero-shot decision stands as soon as
    the labels' rule leads or decides any other class. A held decision keeps the zero-shot
    evidence's reason, confidence and posterior, with the presses the piece took."""

    def __init__(self, adapted: Evidence, zero_shot: Evidence, taught: Iterable[str]) -> None:
        super().__init__(adapted, zero_shot)
        self.taught = frozenset(taught)
        self._zero_shot_said: ItemDecision | None = None  # the bundle's decision, once its rule stopped
        self._adapted_done = False  # the labels' rule decided a class no label taught: it sorts nothing more

    @property
    def press_limit(self) -> int:
        # each rule stops at its own limit (their extra presses may differ); the piece at the later
        return max(self.adapted.press_limit, self.zero_shot.press_limit)

    def _sorts(self, d: ItemDecision | None) -> bool:
        """Whether the labels' rule's decision ``d`` sorts the piece: a taught class, and the rule
        decided no other class before."""
        return d is not None and not self._adapted_done and d.label in self.taught

    def _leads_taught(self) -> bool:
        post = self.adapted.decide().log_posterior
        return not self._adapted_done and max(post, key=post.get) in self.taught

    def add(self, score):
        a = self.adapted.add(score)
        if self._zero_shot_said is None:
            self._zero_shot_said = self.zero_shot.add(score)
        if self._sorts(a):
            return a
        if a is not None:
            self._adapted_done = True
        said = self._zero_shot_said
        if said is None or self._leads_taught():
            return None
        return self._as_pressed(said)

    def _as_pressed(self, said: ItemDecision) -> ItemDecision:
        """The bundle's decision, with the presses the piece took (the labels' rule may have held it)."""
        return replace(said, presses=self.adapted.presses)

    def decide(self):
        a = self.adapted.decide()
        if self._sorts(a):
            return a
        return self._as_pressed(self._zero_shot_said or self.zero_shot.decide())


class TrackedEvidence:
    """A sum-rule evidence that also keeps its presses' mean projection (``z_mean``), which a later
    label of the piece reads (the offset rule's evidence keeps it itself)."""

    def __init__(self, inner: Evidence, k: int) -> None:
        self.inner, self._z_sum, self._z_all = inner, np.zeros(k), np.zeros(k)

    @property
    def presses(self) -> int:
        return self.inner.presses

    @property
    def press_limit(self) -> int:
        return self.inner.press_limit

    @property
    def mean_presses(self) -> int:
        return self.inner.used_presses or self.inner.presses

    @property
    def z_mean(self):
        """As ``Evidence.z_mean``: the presses that were evidence, every press when none was."""
        if not self.inner.presses:
            return None
        return self._z_sum / self.inner.used_presses if self.inner.used_presses else self._z_all / self.inner.presses

    def add(self, score):
        z = getattr(score, "scene_z", None)
        if z is None:
            raise ValueError("operator labels need the press's projection (scene_z), and this press score has none")
        z = np.asarray(z, np.float64).reshape(-1)
        outliers = self.inner.outliers
        decision = self.inner.add(score)
        self._z_all = self._z_all + z
        if self.inner.outliers == outliers:  # an outlier press is no part of the piece's mean
            self._z_sum = self._z_sum + z
        return decision

    def decide(self):
        return self.inner.decide()

    def peek(self):
        return self.inner.peek()


def item_evidence(deployed: SceneModel, adapted: SceneModel, scene: Sequence[str], labelled: Iterable[str],
                  strangers: Iterable[str], make_evidence: Callable[[SceneModel, list[str]], Any]):
    """One piece's evidence: the bundle's own (``deployed``, zero-shot) while nothing was learned,
    else a pair over ``adapted`` (the offset-rule model the labels updated, over the scene's fabrics
    and the learned strangers) and the zero-shot one: ``GuardedEvidence`` for an offset-rule bundle,
    ``ZeroShotUnlessTaught`` for a sum-rule one (module doc)."""
    taught = [OFF_SCENE_PREFIX + name for name in strangers]
    # a labelled class is taught only where ``adapt`` moved its mean; else it is guarded like any other
    learned = [*(labelled if labels_teach(adapted) else ()), *taught]
    zero_shot = make_evidence(deployed, list(scene))
    if deployed.item_rule != "offset":
        zero_shot = TrackedEvidence(zero_shot, deployed.k)
    if not learned:
        return zero_shot
    labelled_taught = [c for c in learned if c not in taught]
    untaught = [c for c in scene if c in deployed.untouched and c not in labelled_taught]
    # taught, yet guarded: an untaught fabric of the job the generator could not tell from it
    near = confusable(deployed, adapted.offset_var_untouched, labelled_taught, untaught)
    trusted = [c for c in learned if c not in near] + [c for c in scene if c not in deployed.untouched]
    adapted_ev = make_evidence(adapted, [*scene, *taught])
    # a taught mean is real presses, as a touched one is, and no worse than a synthesis: it needs
    # at most the touched confidence, and at most the untouched one. Where validation cannot price
    # the untouched one the search holds it high (train/item_search.py), which would send taught
    # pieces to reject; where it priced it low, taught pieces sort there too
    adapted_ev.need_at_most_touched([c for c in labelled_taught if c in scene and c not in near])
    if math.isfinite(deployed.outlier_ratio):
        adapted_ev.outlier_model = FarFromBoth(deployed, adapted)
    if deployed.item_rule != "offset":  # the labels' rule is another operating point than the bundle's
        return ZeroShotUnlessTaught(adapted_ev, zero_shot, [c for c in learned if c not in near])
    return GuardedEvidence(adapted_ev, zero_shot, trusted, near)


class FarFromBoth:
    """The outlier-press test of the adapted evidence (runtime/scene_model.py ``outlier_ratio``): a
    press is an outlier only when it lies far from every class of the bundle's model and from every
    class of the adapted one at the bundle's spreads. A learned mean's own spread is narrower, and
    with it the adapted evidence would drop presses the zero-shot evidence keeps, deciding the
    classes it trusts on presses validation never priced; yet a knot press stays no evidence, and a
    fabric whose presses all lay far from the bundle's classes is evidence once a label taught it."""

    def __init__(self, deployed: SceneModel, adapted: SceneModel) -> None:
        self.deployed = deployed
        self.adapted = replace(adapted, class_offset_var=None, outlier_ratio=deployed.outlier_ratio)

    def is_outlier_press(self, z=None, sq_distance=None) -> bool:
        return self.deployed.is_outlier_press(z, sq_distance) and self.adapted.is_outlier_press(z, sq_distance)


__all__ = ["adapt", "item_evidence", "confusable", "GuardedEvidence", "ZeroShotUnlessTaught", "FarFromBoth",
           "OFF_SCENE_PREFIX", "TrackedEvidence", "labels_teach"]

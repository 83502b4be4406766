"""The cell learns from its reject bin: operator labels re-estimate the untouched fabrics' means.

Zero-shot, an untouched fabric's class mean is the generator's synthesis from camera and
attributes, off its real mean by the generator's error on that fabric - the same on every piece
(runtime/scene_model.py, the offset item rule). That error, not the presses, is what keeps most
untouched pieces out of their bin (docs/results/scene_decision_paper.md). A person already looks at
every piece in the reject bin; when they say what it was (``vs2t-edge label``), the piece's presses
are real tactile data of that fabric, and the next pieces of it are scored against a mean that
moves from the synthesis towards the fabric's real one.

The update is the offset model's own, no new knob: a synthesised mean m is the true mean mu
plus the generator's error, mu ~ N(m, s_u I); a labelled piece's press mean zbar_j of n_j presses
is mu plus the piece's own offset plus press noise, zbar_j ~ N(mu, (s_t + v / n_j) I). So

    precision  P = 1 / s_u + sum_j 1 / (s_t + v / n_j),
    mean       mu_post = (m / s_u + sum_j zbar_j / (s_t + v / n_j)) / P,

and a new piece's mean zbar ~ N(mu_post, (1 / P + s_t + v / n) I): the class's offset variance
becomes 1 / P + s_t (``SceneModel.class_offset_var``). s_u, s_t and v are the bundle's
(``offset_var_untouched``, ``offset_var_touched``, ``press_var``), chosen on validation fabrics in
training; so it needs an offset-rule setting: the bundle's own, or for a sum-rule bundle the offset
setting training searched on the same validation jobs (``SceneModel.for_labels``; the bundle's own
rule still decides until a label teaches something). Touched fabrics' means come from their training
presses and are left alone; a label naming one is recorded and not applied. A piece the operator
calls off-scene (none of the job's fabrics) teaches a stranger: a class ``off-scene:NAME`` at its
labelled pieces' mean (no prior: nothing synthesised it), decided like any class and sent, being
no fabric of the job, to the reject bin.

A class no label taught is guarded (``GuardedEvidence``): sorted only where the zero-shot model,
on the same presses, decides the same class - labels make the cell surer of what they taught,
never bolder elsewhere. Touched classes are not guarded: their means were real already (and the
rule labels switch to keeps every off-scene rule the bundle's own has, ``SceneModel.for_labels``:
a sum-rule bundle's stored offset setting may have had none). Nor is a
taught class - unless an untouched fabric of the job that no label taught may feel like it
(``confusable``): the generator put the two syntheses closer than its own error (within the 99 %
region of the offset model's N(m, s_u I)), so it could not tell the two fabrics apart, and the
taught mean says nothing of where the other fabric's pieces lie. The taught class is then guarded
too (``stopped_by`` "confusable_guard") until a label teaches the other fabric as well: found on
the paper world, where one label of a jersey sent every piece of its touch-twin (another colour of
the same knit) into its bin.

This is a mode outside the zero-shot protocol, on only when the cell config names a labels file
(``evidence.operator_labels``), and measured as such (train/decision.py ``evaluate_scenes``,
"with operator labels"): the pure zero-shot numbers stay the product's headline.

Files: the operator's labels are a JSON-lines file, one ``{"item_id": ..., "fabric": ...}`` a line,
appended with an fsync (``append_label``). A piece has at most one label that counts, its latest: a
second line for the same piece replaces the first (a correction; the same label again changes
nothing, so a piece is never counted twice), and ``{"item_id": ..., "retract": true}`` withdraws it -
a wrong label would otherwise pull its fabric's mean towards another fabric for the rest of the job,
and a restart, which rebuilds from the journal, would keep it. The cell reads new lines before each item
(``OperatorFeedback.poll``) and journals what it did with each (``{"type": "label", ...}``,
applied or not and why) before it presses the next piece; each decided item's pre_sort record
carries its presses' mean projection (``scene_z_mean``), so a restarted service rebuilds the same
state from the journal (``restore``) and reads on from the first line it has not journaled.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from vs2t_edge.runtime.bundle import SEAL_KEY
from vs2t_edge.runtime.evidence import UNKNOWN, Evidence, ItemDecision
from vs2t_edge.runtime.files import InputRefused, read_regular_file
from vs2t_edge.runtime.scene_model import SceneModel, SceneModelError

JOURNAL_DECIMALS = 5  # of a pre_sort record's scene_z_mean, what live and restarted cells learn from

MAX_LABEL_LINE_BYTES = 4096
MAX_LABELS_FILE_BYTES = 64 * 1024 * 1024  # ~500 000 labels; a new file per job (at a new path) long before
OFF_SCENE_PREFIX = "off-scene:"  # a learned stranger's class name (never a bundle class's)


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
    return replace(model, classes=tuple(model.classes) + tuple(names), means=means, class_offset_var=var)


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


class GuardedEvidence:
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
        self.adapted, self.zero_shot, self.trusted = adapted, zero_shot, frozenset(trusted)
        self.confusable_with = dict(confusable_with or {})  # taught, yet guarded (module doc)

    @property
    def presses(self) -> int:
        return self.adapted.presses

    @property
    def mean_presses(self) -> int:
        return self.adapted.mean_presses

    @property
    def z_mean(self):
        return self.adapted.z_mean

    def _guarded(self, d, final: bool):
        if d is None or d.label == UNKNOWN or d.label in self.trusted:
            return d
        z = self.zero_shot.decide() if final or d.stopped_by != "confident" else self.zero_shot.peek()
        if z is not None and z.label == d.label:
            return d
        if final or self.adapted.presses >= self.adapted.max_presses:
            why = "confusable_guard" if d.label in self.confusable_with else "unlabelled_guard"
            return ItemDecision(UNKNOWN, d.confidence, d.presses, d.log_posterior, why)
        return None  # press on: the zero-shot evidence may yet agree

    def add(self, score):
        self.zero_shot.add(score)
        return self._guarded(self.adapted.add(score), final=False)

    def decide(self):
        return self._guarded(self.adapted.decide(), final=True)


class TrackedEvidence:
    """A sum-rule evidence that also keeps its presses' mean projection (``z_mean``), which a later
    label of the piece reads (the offset rule's evidence keeps it itself)."""

    def __init__(self, inner: Evidence, k: int) -> None:
        self.inner, self._z_sum, self._z_all = inner, np.zeros(k), np.zeros(k)

    @property
    def presses(self) -> int:
        return self.inner.presses

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
    else the guarded pair (``GuardedEvidence``): ``adapted`` (the offset-rule model the labels
    updated, over the scene's fabrics and the learned strangers) checked by the zero-shot one."""
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
    if math.isfinite(deployed.outlier_ratio):
        adapted_ev.outlier_model = FarFromBoth(deployed, adapted)
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


def append_label(path: Path | str, item_id: str, fabric: str | None, off_scene: bool = False) -> dict:
    """Append one operator label, durably (fsync) - what ``vs2t-edge label`` does. ``off_scene``:
    ``fabric`` names a piece that is none of the job's fabrics (any name the operator uses);
    ``fabric`` None: withdraw the piece's label (module doc)."""
    if fabric is None:
        rec: dict = {"item_id": str(item_id), "retract": True}
    else:
        rec = {"item_id": str(item_id), "fabric": str(fabric), **({"off_scene": True} if off_scene else {})}
    line = (json.dumps(rec, sort_keys=True) + "\n").encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o640)
    try:
        os.write(fd, line)
        os.fsync(fd)
    finally:
        os.close(fd)
    return rec


def read_labels(path: Path | str, start: int = 0) -> list[tuple[int, dict | str]]:
    """(line number from 1, label or the reason it is unusable) for every whole line from line
    ``start`` + 1 on; a last line without its newline is being written and is left for later."""
    try:  # a regular file under a cap: a FIFO put there must not hang the cell (InputRefused, an error)
        data = read_regular_file(path, MAX_LABELS_FILE_BYTES, "labels file")
    except FileNotFoundError:
        return []
    return [(k, rec) for k, rec, _ in _parse_labels(data, start)[1]]


def _parse_labels(data: bytes, start: int = 0) -> tuple[int, list[tuple[int, dict | str, int]]]:
    """(the byte offset where line ``start`` + 1 begins, ``read_labels``'s lines of ``data`` from
    it, each with the byte offset just past its newline)."""
    lines = data.split(b"\n")[:-1]  # the part after the last newline is not a whole line yet
    begin = end = sum(len(raw) + 1 for raw in lines[:start])
    out: list[tuple[int, dict | str, int]] = []
    for k, raw in enumerate(lines[start:], start + 1):
        end += len(raw) + 1
        out.append((k, _parse_label(raw), end))
    return begin, out


def _parse_label(raw: bytes) -> dict | str:
    if not raw.strip():
        return "an empty line"
    if len(raw) > MAX_LABEL_LINE_BYTES:
        return f"a line of {len(raw)} bytes (at most {MAX_LABEL_LINE_BYTES})"
    try:
        rec = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        return f"not JSON ({exc})"
    retract = isinstance(rec, dict) and rec.get("retract") is True and "fabric" not in rec \
        and "off_scene" not in rec and isinstance(rec.get("item_id"), str)
    if not retract and (not isinstance(rec, dict) or not isinstance(rec.get("item_id"), str)
                        or not isinstance(rec.get("fabric"), str) or "retract" in rec
                        or not isinstance(rec.get("off_scene", False), bool)):
        return ('not {"item_id": "...", "fabric": "..."[, "off_scene": true]} '
                'nor {"item_id": "...", "retract": true}')
    return rec


_EMPTY_SHA256 = hashlib.sha256(b"").hexdigest()


class OperatorFeedback:
    """The cell's item rule with operator labels (module doc): an evidence factory the cell calls per
    item, which it also tells each decided item (``remember``) and lets read new labels (``poll``).
    ``model``: the bundle's scene model (its own rule decides until a label teaches something; a
    sum-rule model's stored offset setting is what labels update, ``SceneModel.for_labels``);
    ``make_evidence(model, classes)``: the item evidence over ``classes`` (the scene's, then the
    learned strangers', whose decisions go to the reject bin) at ``model``'s operating point."""

    def __init__(self, model: SceneModel, scene_classes: Iterable[str], labels_path: Path | str,
                 make_evidence: Callable[[SceneModel, list[str]], Evidence]) -> None:
        base = model.for_labels()
        if base is None:
            raise SceneModelError("operator labels need the scene model's offset item rule, and this sum-rule model "
                                  "carries no offset setting (a bundle exported before it did: re-export it)")
        self.deployed, self.base = model, base  # the zero-shot rule, and the offset-rule model labels update
        self.scene = list(scene_classes)
        self.path = Path(labels_path)
        self.make_evidence = make_evidence
        self.pieces: dict[str, tuple[list[float], int]] = {}  # item id -> (press mean, presses)
        self.item_labels: dict[str, tuple[str, bool]] = {}  # item id -> its label that counts (fabric, off-scene)
        self.labelled: dict[str, list[tuple[np.ndarray, int]]] = {}
        self.strangers: dict[str, list[tuple[np.ndarray, int]]] = {}
        self.lines_read = 0
        self.model = base
        self._unreadable = ""  # the last unreadable-file error journaled (said once, not per piece)
        self._seen: tuple | None = None  # the labels file's (device, inode, size, mtime) when last read
        # (bytes, SHA-256) of the file through line lines_read; None: unknown (a journal older than them)
        self._prefix: tuple[int, str] | None = (0, _EMPTY_SHA256)

    def __call__(self):
        return item_evidence(self.deployed, self.model, self.scene, self.labelled, self.strangers, self.make_evidence)

    @staticmethod
    def journal_z_mean(evidence: Any) -> list[float] | None:
        """The piece's press mean as its ``pre_sort`` record keeps it (``scene_z_mean``, 5 decimals),
        None when the evidence has none. The live cell learns from exactly these numbers
        (``remember``), as a restart does from the journal: the same state either way."""
        z = getattr(evidence, "z_mean", None)
        return None if z is None else [round(float(v), JOURNAL_DECIMALS) for v in np.asarray(z).reshape(-1)]

    @staticmethod
    def journal_z_presses(evidence: Any) -> int | None:
        """How many presses the piece's press mean averages when outlier presses were left out of
        it (its ``pre_sort`` record's ``scene_z_presses``), None when it averages all its presses."""
        n, presses = getattr(evidence, "mean_presses", None), getattr(evidence, "presses", 0)
        return None if n is None or n == presses else int(n)

    def remember(self, item_id: str, evidence: Any) -> None:
        z, n = self.journal_z_mean(evidence), getattr(evidence, "mean_presses", getattr(evidence, "presses", 0))
        if z is not None and n:
            self.pieces[str(item_id)] = (z, int(n))

    def _apply(self, item_id: str, fabric: str, off_scene: bool = False, rebuild: bool = True) -> str:
        """'' when the label moved the model (``rebuild`` False: is to move it once ``_relearn`` runs),
        else why not. A piece's earlier label is replaced (``item_labels``), never added to; by a
        touched fabric's (which teaches nothing) it is withdrawn; so it is by a label this job cannot
        apply - the piece's latest label says what it was, so the earlier one is wrong whatever job
        reads it (a restart into another job judges each journalled label again, ``restore``)."""
        if off_scene and fabric in self.scene:
            return self._withdraw_earlier(item_id, (fabric, off_scene), rebuild,
                                          f"{fabric!r} is a fabric of this job, not an off-scene one")
        if not off_scene and fabric not in self.scene:
            return self._withdraw_earlier(item_id, (fabric, off_scene), rebuild, f"{fabric!r} is not a fabric of "
                                          "this job (an off-scene piece is labelled with off_scene)")
        if not off_scene and fabric not in self.base.untouched:
            if item_id in self.item_labels:  # a correction: the piece was this touched fabric, its label is withdrawn
                return self._retract(item_id, rebuild)
            return f"{fabric!r} is a touched fabric: its mean comes from training presses"
        if item_id not in self.pieces:
            return f"no decided item {item_id!r} with presses in this journal"
        if self.item_labels.get(item_id) == (fabric, off_scene):
            return f"{item_id!r} is labelled {fabric!r} already (a piece counts once)"
        self.item_labels[item_id] = (fabric, off_scene)
        if rebuild:
            self._relearn()
        return ""

    def _withdraw_earlier(self, item_id: str, label: tuple[str, bool], rebuild: bool, why: str) -> str:
        """``why`` (the label is not applied), after withdrawing the piece's earlier, different
        label: left in force it would teach its class the presses of a piece the operator has
        since called something else - the next pieces of that fabric into the wrong bin."""
        earlier = self.item_labels.get(item_id)
        if earlier is None or earlier == label:
            return why
        self._retract(item_id, rebuild)
        return f"{why}; its earlier label {earlier[0]!r} is withdrawn (a piece's latest label counts)"

    def _retract(self, item_id: str, rebuild: bool = True) -> str:
        """'' when the piece's label was withdrawn, else why not."""
        if item_id not in self.item_labels:
            return f"{item_id!r} has no applied label to retract"
        del self.item_labels[item_id]
        if rebuild:
            self._relearn()
        return ""

    def _relearn(self) -> None:
        """The labelled pieces per class from each piece's label that counts, in the order labelled,
        and the model they teach."""
        self.labelled, self.strangers = {}, {}
        for item_id, (fabric, off_scene) in self.item_labels.items():
            z, n = self.pieces[item_id]
            (self.strangers if off_scene else self.labelled).setdefault(fabric, []).append((np.asarray(z), n))
        self.model = adapt(self.base, self.labelled, self.strangers)

    def poll(self, journal) -> list[dict]:
        """Read labels written since the last poll, apply them, journal each; the records written.
        A labels file that cannot be read (permissions, a folder in its place) stops no piece: the
        cell sorts on with what it learned, and the journal says so once per distinct error. A file
        that no longer begins with the lines read before (a new file in its place, truncated, edited)
        is read again from its first line, said in the journal: none of its lines is skipped, and a
        label already in force changes nothing when read again."""
        try:
            st = os.stat(self.path)
            seen = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
            if seen == self._seen:  # nothing written since the last read: no re-read per piece
                return []
            data = read_regular_file(self.path, MAX_LABELS_FILE_BYTES, "labels file")
        except FileNotFoundError:
            return []
        except (OSError, InputRefused) as exc:
            said = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            why = f"labels file {self.path} unreadable ({said}); sorting on without new labels"
            if why == self._unreadable:
                return []
            out = [journal.append({"type": "label", "file": str(self.path), "applied": False, "why": why})]
            self._unreadable = why  # said once it is in the journal
            return out
        self._unreadable = ""
        out = []
        if not self._begins_with_lines_read(data):
            why = (f"labels file {self.path} no longer begins with the {self.lines_read} line(s) read before (a new "
                   "file in its place, truncated or edited): read again from line 1. The labels in force stay (one "
                   "read again changes nothing); a line taken out withdraws nothing: `vs2t-edge label --retract` does")
            out.append(journal.append({"type": "label", "file": str(self.path), "applied": False, "reread": True,
                                       "why": why}))
            self.lines_read, self._prefix = 0, (0, _EMPTY_SHA256)
        start, lines = _parse_labels(data, self.lines_read)
        digest = hashlib.sha256(data[:start])
        for line, rec, end in lines:
            digest.update(data[start:end])
            start = end
            entry: dict[str, Any] = {"type": "label", "line": line, "file": str(self.path),
                                     "file_bytes": end, "file_sha256": digest.hexdigest()}
            before_line = dict(self.item_labels)  # what a label that cannot be journaled must leave
            if isinstance(rec, str):
                entry.update(applied=False, why=f"{self.path} line {line}: {rec}")
            elif rec.get("retract"):
                before = self.item_labels.get(rec["item_id"])
                why = self._retract(rec["item_id"])
                entry.update(item_id=rec["item_id"], retract=True, applied=not why, **({"why": why} if why else {}),
                             **({"withdrew": before[0]} if before and not why else {}))
            else:
                off = bool(rec.get("off_scene", False))
                before = self.item_labels.get(rec["item_id"])
                why = self._apply(rec["item_id"], rec["fabric"], off)
                twins = [] if why or off else self.twins_of(rec["fabric"])
                entry.update(item_id=rec["item_id"], fabric=rec["fabric"], **({"off_scene": True} if off else {}),
                             applied=not why, **({"why": why} if why else {}),
                             **({"replaces": before[0]} if before and not why else {}),
                             **({"withdrew": before[0]} if before and why and rec["item_id"] not in self.item_labels
                                else {}),
                             **({"guarded_while_untaught": twins} if twins else {}))
            try:
                out.append(journal.append(entry))
            except BaseException:
                # not in the journal, so not in the state: a restart could not rebuild it. The line
                # is read again at the next poll (lines_read, _seen not moved past it).
                if self.item_labels != before_line:
                    self.item_labels = before_line
                    self._relearn()
                raise
            self.lines_read, self._prefix = line, (end, entry["file_sha256"])
        self._seen = seen  # a line still being written grows the file, so it is read when whole
        return out

    def twins_of(self, fabric: str) -> list[str]:
        """The job's untaught untouched fabrics that keep ``fabric``'s label guarded (``confusable``):
        its pieces go to the reject bin unless zero-shot agrees, until one of each is labelled."""
        untaught = [c for c in self.scene if c in self.deployed.untouched and c not in self.labelled]
        return confusable(self.deployed, self.base.offset_var_untouched, [fabric], untaught).get(fabric, [])

    def _begins_with_lines_read(self, data: bytes) -> bool:
        """Whether ``data`` still begins with the lines read so far, byte for byte (their length and
        SHA-256, journaled with each line; a journal written before they were: at least as many lines)."""
        if self._prefix is None:
            return data.count(b"\n") >= self.lines_read
        n, sha = self._prefix
        return len(data) >= n and hashlib.sha256(data[:n]).hexdigest() == sha

    def restore(self, records: Iterable[Mapping[str, Any]], seal: str | None) -> None:
        """The state a restarted service resumes from: decided items' press means (pre_sort
        records' ``scene_z_mean``), the labels already journaled, applied again in their order -
        each judged by this job, whether its own session applied it or not (a label is what a piece
        was, whatever job it was given in).
        Records of sessions run on another bundle (their start record's ``seal``) are skipped:
        their projections are in another model's space."""
        current = True  # records before the first start record: this journal's own
        for rec in records:
            kind = rec.get("type")
            if kind == "start":
                current = rec.get(SEAL_KEY) == seal
            elif not current:
                continue
            elif kind == "pre_sort" and _projection(rec.get("scene_z_mean"), self.base.k) \
                    and rec.get("item_id") is not None and _press_count(rec.get("scene_z_presses", rec.get("presses"))):
                self.pieces[str(rec["item_id"])] = (rec["scene_z_mean"], rec.get("scene_z_presses", rec["presses"]))
            elif kind == "label" and rec.get("file") == str(self.path) and rec.get("reread") is True:
                self.lines_read, self._prefix = 0, (0, _EMPTY_SHA256)  # the file was read again from line 1
            elif kind == "label" and rec.get("file") == str(self.path) and isinstance(rec.get("line"), int):
                # every label the operator gave, applied in its session or not, judged again by this
                # job: a retraction or correction given while its fabric was out of the job (so not
                # applied then) must still withdraw the label when the fabric is back
                # (a line that was no label, unreadable, has no item_id: nothing to apply)
                item = rec.get("item_id")
                if item is not None and rec.get("retract"):
                    self._retract(str(item), rebuild=False)
                elif item is not None and isinstance(rec.get("fabric"), str):
                    self._apply(str(item), rec["fabric"], bool(rec.get("off_scene")), rebuild=False)
                n, sha = rec.get("file_bytes"), rec.get("file_sha256")
                self.lines_read = rec["line"]
                known = isinstance(n, int) and not isinstance(n, bool) and isinstance(sha, str)
                self._prefix = (n, sha) if known else None
        self._relearn()  # once, not once per label


def _press_count(n: Any) -> bool:
    """Whether a journal's press count is one a press mean can average (an int, at least 1)."""
    return isinstance(n, int) and not isinstance(n, bool) and n >= 1


def _projection(z: Any, k: int) -> bool:
    """Whether a journal's ``scene_z_mean`` is one this model can learn from (a hand-edited or
    damaged record is skipped at restore, not a crash at start)."""
    return isinstance(z, list) and len(z) == k and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in z)


__all__ = ["adapt", "append_label", "read_labels", "item_evidence", "confusable", "GuardedEvidence",
           "OperatorFeedback",
           "OFF_SCENE_PREFIX", "TrackedEvidence", "labels_teach"]

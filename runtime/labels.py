"""Operator labels as the cell reads, journals and restores them; what they teach is runtime/feedback.py.

The operator's labels are a JSON-lines file, one ``{"item_id": ..., "fabric": ...}`` a line,
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
import os
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from vs2t_edge.runtime.bundle import SEAL_KEY
from vs2t_edge.runtime.evidence import Evidence
from vs2t_edge.runtime.feedback import adapt, confusable, item_evidence
from vs2t_edge.runtime.files import InputRefused, read_regular_file
from vs2t_edge.runtime.names import name_key, typed_name
from vs2t_edge.runtime.scene_model import SceneModel, SceneModelError

JOURNAL_DECIMALS = 5  # of a pre_sort record's scene_z_mean, what live and restarted cells learn from

MAX_LABEL_LINE_BYTES = 4096
MAX_LABELS_FILE_BYTES = 64 * 1024 * 1024  # ~500 000 labels; a new file per job (at a new path) long before


def scene_fabric(name: str, scene: Iterable[str]) -> str | None:
    """The fabric of ``scene`` that ``name`` spells as Unicode text (``typed_name``), in the scene's own
    spelling; None when it names none."""
    typed = typed_name(name)
    return next((c for c in scene if typed_name(c) == typed), None)


def alike_fabric(name: str, scene: Iterable[str]) -> str | None:
    """The fabric of ``scene`` that ``name`` names but for case, width, spaces, '-' or '_' (``name_key``),
    or None."""
    key = name_key(name)
    return next((c for c in scene if name_key(c) == key), None)


def piece_digest(z_mean: Any, presses: Any) -> str | None:
    """The SHA-256 of a decided piece's press mean and press count as its ``pre_sort`` record keeps
    them (``scene_z_mean``, ``scene_z_presses`` or ``presses``), None for a record without them: what
    a label is bound to (``append_label``'s ``piece``)."""
    if not isinstance(z_mean, list) or not _press_count(presses):
        return None
    return hashlib.sha256(json.dumps([z_mean, presses], separators=(",", ":")).encode()).hexdigest()


def pre_sort_piece(rec: Mapping[str, Any]) -> tuple[list, int] | None:
    """(press mean, presses it averages) of a decided piece as its ``pre_sort`` record keeps them for
    a later label (``scene_z_mean``; ``scene_z_presses`` when outlier presses were left out of it,
    else ``presses``), None for a record without them."""
    z_mean, presses = rec.get("scene_z_mean"), rec.get("scene_z_presses", rec.get("presses"))
    return (z_mean, presses) if isinstance(z_mean, list) and _press_count(presses) else None


def bound_piece(rec: Mapping[str, Any]) -> str | None:
    """The ``piece_digest`` a label line or record is bound to (``piece_sha256``), None for an unbound one."""
    piece = rec.get("piece_sha256")
    return piece if isinstance(piece, str) else None


def append_label(path: Path | str, item_id: str, fabric: str | None, off_scene: bool = False,
                 piece: str | None = None) -> dict:
    """Append one operator label, durably (fsync) - what ``vs2t-edge label`` does. ``off_scene``:
    ``fabric`` names a piece that is none of the job's fabrics (any name the operator uses);
    ``fabric`` None: withdraw the piece's label (module doc). ``piece``: the ``piece_digest`` of the
    piece the label verb looked up; the cell applies the line to a piece of that id with those
    presses only (ids start again at piece-000001 in a new journal, and a kept labels file first
    read late - unreadable to the service until then - named the new journal's piece of that id)."""
    bound = {"piece_sha256": piece} if piece else {}
    if fabric is None:
        rec: dict = {"item_id": str(item_id), "retract": True, **bound}
    else:
        rec = {"item_id": str(item_id), "fabric": str(fabric), **({"off_scene": True} if off_scene else {}), **bound}
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
                        or not isinstance(rec.get("off_scene", False), bool)) \
            or not isinstance(rec.get("piece_sha256", ""), str):  # a dict by here: ``or`` stops at a non-dict
        return ('not {"item_id": "...", "fabric": "..."[, "off_scene": true]} '
                'nor {"item_id": "...", "retract": true} (either with a "piece_sha256": "..." or not)')
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
        self.path = Path(os.path.abspath(labels_path))  # absolute in the journal: a restart elsewhere finds it
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
        self._judged: set[tuple] = set()  # the labels file's lines judged so far (``_line_key``): a re-read skips them

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

    def _another_piece(self, item_id: str, piece: str | None) -> str:
        """Why a line bound to ``piece`` (``append_label``) names another piece than this journal's
        ``item_id``, '' when it names this one (or is bound to none, or no such piece is decided)."""
        if not piece or item_id not in self.pieces or piece == piece_digest(*self.pieces[item_id]):
            return ""
        return (f"names another piece than this journal's {item_id!r}: the label verb saw other presses for it "
                "(a label given before this journal began numbering its pieces again)")

    def _apply(self, item_id: str, fabric: str, off_scene: bool = False, rebuild: bool = True,
               piece: str | None = None) -> str:
        """'' when the label moved the model (``rebuild`` False: is to move it once ``_relearn`` runs),
        else why not. A piece's earlier label is replaced (``item_labels``), never added to; by a
        touched fabric's (which teaches nothing) it is withdrawn; so it is by a label this job cannot
        apply - the piece's latest label says what it was, so the earlier one is wrong whatever job
        reads it (a restart into another job judges each journalled label again, ``restore``). Names
        are Unicode text (``typed_name``): a job fabric spelt decomposed is that fabric; and an
        off-scene name that is a job fabric's but for case or spaces (``alike_fabric``) names that
        fabric, whose presses must not teach a stranger (its next pieces to the reject bin)."""
        if (other := self._another_piece(item_id, piece)):
            return other  # it says nothing of this piece: its label stands
        fabric = typed_name(fabric)
        if not off_scene:
            fabric = scene_fabric(fabric, self.scene) or fabric
        if off_scene and (alike := alike_fabric(fabric, self.scene)) is not None:
            return self._withdraw_earlier(item_id, (fabric, off_scene), rebuild,
                                          f"{fabric!r} is a fabric of this job"
                                          + (f" ({alike!r})" if alike != fabric else "") + ", not an off-scene one")
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
        """``why`` (the label is not applied), after withdrawing the piece's earlier label of another
        fabric (the same fabric labelled in two jobs - off-scene in one, a job fabric in the other -
        stays): left in force it would teach its class the presses of a piece the operator has
        since called something else - the next pieces of that fabric into the wrong bin."""
        earlier = self.item_labels.get(item_id)
        # the same fabric, named as this job or another needs
        if earlier is None or name_key(earlier[0]) == name_key(label[0]):
            return why
        self._retract(item_id, rebuild)
        return f"{why}; its earlier label {earlier[0]!r} is withdrawn (a piece's latest label counts)"

    def _retract(self, item_id: str, rebuild: bool = True, piece: str | None = None) -> str:
        """'' when the piece's label was withdrawn, else why not."""
        if (other := self._another_piece(item_id, piece)):
            return other
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
        is read again from its first line, said in the journal: none of its new lines is skipped, and
        a line judged before is not judged again (journaled ``read_before``): an editor's stale copy
        would bring a withdrawn label back into force, and a line that named no piece when it was
        read - the last journal's, whose ids a new journal gives again - would name a later piece."""
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
        judged_before: set[tuple] = set()  # a re-read: the lines judged so far stay judged
        if not self._begins_with_lines_read(data):
            why = (f"labels file {self.path} no longer begins with the {self.lines_read} line(s) read before (a new "
                   "file in its place, truncated or edited): read again from line 1. The labels in force stay (a line "
                   "judged before is not judged again); a line taken out withdraws nothing: `vs2t-edge label "
                   "--retract` does")
            out.append(journal.append({"type": "label", "file": str(self.path), "applied": False, "reread": True,
                                       "why": why}))
            self.lines_read, self._prefix, judged_before = 0, (0, _EMPTY_SHA256), set(self._judged)
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
            elif _line_key(rec) in judged_before:
                entry.update(item_id=rec["item_id"], **_said(rec), applied=False, read_before=True,
                             why="a line the cell judged before the file was read again: it changes nothing "
                                 "(a label given again after its withdrawal is appended anew)")
            elif rec.get("retract"):
                before = self.item_labels.get(rec["item_id"])
                why = self._retract(rec["item_id"], piece=rec.get("piece_sha256"))
                entry.update(item_id=rec["item_id"], **_said(rec), applied=not why, **({"why": why} if why else {}),
                             **({"withdrew": before[0]} if before and not why else {}))
            else:
                off = bool(rec.get("off_scene", False))
                before = self.item_labels.get(rec["item_id"])
                why = self._apply(rec["item_id"], rec["fabric"], off, piece=rec.get("piece_sha256"))
                twins = [] if why or off else self.twins_of(rec["fabric"])
                entry.update(item_id=rec["item_id"], **_said(rec), applied=not why, **({"why": why} if why else {}),
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
            if not isinstance(rec, str):
                self._judged.add(_line_key(rec))
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
        mine = _names_file(self.path)
        for rec in records:
            kind = rec.get("type")
            if kind == "start":
                current = rec.get(SEAL_KEY) == seal
            elif not current:
                continue
            elif kind == "pre_sort" and rec.get("item_id") is not None and (piece := pre_sort_piece(rec)) \
                    and _projection(piece[0], self.base.k):
                self.pieces[str(rec["item_id"])] = piece
            elif kind == "label" and mine(rec.get("file")) and rec.get("reread") is True:
                self.lines_read, self._prefix = 0, (0, _EMPTY_SHA256)  # the file was read again from line 1
            elif kind == "label" and mine(rec.get("file")) and isinstance(rec.get("line"), int):
                # every label the operator gave, applied in its session or not, judged again by this
                # job: a retraction or correction given while its fabric was out of the job (so not
                # applied then) must still withdraw the label when the fabric is back
                # (a line that was no label, unreadable, has no item_id: nothing to apply)
                item = rec.get("item_id")
                said = item is not None and (rec.get("retract") or isinstance(rec.get("fabric"), str))
                if said:
                    self._judged.add(_line_key(rec))
                # a line judged before its file was read again changed nothing live
                if said and judged_anew(rec):
                    piece = bound_piece(rec)
                    if rec.get("retract"):
                        self._retract(str(item), rebuild=False, piece=piece)
                    else:
                        self._apply(str(item), rec["fabric"], bool(rec.get("off_scene")), rebuild=False, piece=piece)
                n, sha = rec.get("file_bytes"), rec.get("file_sha256")
                self.lines_read = rec["line"]
                known = isinstance(n, int) and not isinstance(n, bool) and isinstance(sha, str)
                self._prefix = (n, sha) if known else None
        self._relearn()  # once, not once per label


def _names_file(path: Path) -> Callable[[Any], bool]:
    """Whether a ``label`` record's ``file`` is ``path``: the same string, or the same file by its real
    path. The string is the config's (relative to where a relative config was loaded: `run --config
    cell.yaml` from its folder writes `labels.jsonl`), so a restart may name the file otherwise, and
    one that found none of its records read the file again from line 1, judging again lines judged
    before (tests/test_label_reread.py). A relative string of an earlier run resolves against this
    process's folder, which may not be that run's: the cell keeps its own ``path`` absolute."""
    own, real = str(path), os.path.realpath(path)
    known: dict[str, bool] = {}

    def names(file: Any) -> bool:
        if not isinstance(file, str):
            return False
        if file not in known:
            known[file] = file == own or os.path.realpath(file) == real
        return known[file]
    return names


def judged_anew(rec: dict) -> bool:
    """Whether a journaled label line was judged when read, not skipped as one judged before its file
    was read again (``read_before``: an editor's stale copy, which changed nothing live). What the
    restore, `vs2t-edge label --list` and a replay count as the operator's word."""
    return rec.get("read_before") is not True


def _line_key(rec: Mapping[str, Any]) -> tuple:
    """What a labels-file line (or its ``label`` record) says, as a key: the same words, the same key."""
    return (str(rec.get("item_id")), *sorted(_said(rec).items()))


def _said(rec: Mapping[str, Any]) -> dict:
    """A label record's fields for what the line said (its fabric, or the withdrawal, and the piece
    it is bound to)."""
    bound = {"piece_sha256": piece} if (piece := bound_piece(rec)) is not None else {}
    if rec.get("retract"):
        return {"retract": True, **bound}
    return {"fabric": rec["fabric"], **({"off_scene": True} if rec.get("off_scene") else {}), **bound}


def _press_count(n: Any) -> bool:
    """Whether a journal's press count is one a press mean can average (an int, at least 1)."""
    return isinstance(n, int) and not isinstance(n, bool) and n >= 1


def _projection(z: Any, k: int) -> bool:
    """Whether a journal's ``scene_z_mean`` is one this model can learn from (a hand-edited or
    damaged record is skipped at restore, not a crash at start)."""
    return isinstance(z, list) and len(z) == k and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in z)


__all__ = ["append_label", "bound_piece", "piece_digest", "read_labels", "judged_anew", "typed_name", "name_key", "scene_fabric",
           "alike_fabric", "pre_sort_piece", "OperatorFeedback", "JOURNAL_DECIMALS", "MAX_LABEL_LINE_BYTES",
           "MAX_LABELS_FILE_BYTES"]

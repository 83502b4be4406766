"""An item's presses: press grid points, score each press, fold the scores into the evidence in
press order until it decides - with the scoring of one press overlapped with the arm's move on.

Sequential (``overlap_scoring`` off) the loop is press k -> score k -> evidence -> press k+1, so
the model's time adds to every press. Overlapped, press k's frame is handed to one worker thread
as soon as it is grabbed and passed the contact check, and is scored while the arm lifts the gel
(the lift happens whatever the score says):

* the score is ready when the gel is up -> it is folded in there; if the evidence decides, the
  arm stops exactly where it stops sequentially (the same device calls);
* it is not ready (a model slower than the lift) -> the arm does not wait: it presses the next
  point, and the late score is folded in once that press is done. If the late score decides, the
  extra press was *speculative*: its frame is never scored into the decision (the pre_sort record
  counts it as ``speculative_presses``), so the decision is the sequential one whatever the timing.

Before a press that the press limit (or the skipped-frame limit) could forbid once the late score
is in, the late score is waited for: the arm never presses beyond the limit.

The decision never depends on timing: the evidence sees the same scores in the same order as it
would sequentially. What may depend on timing is only whether a speculative press happens.

Faults keep the sequential rules. A ``FrameError`` from the model skips that frame when its score
is folded in (``frame_skipped`` record, in press order); any other exception from the model is
raised in the loop's thread when that score is folded in, and the cell latches it as before. An
item ends with no score running (``PressScorer.drain``), so the next item's ``set_reference``
never races a score of the last one. An item that ends in a fault while a late score is still
pending ends without it: its final record counts the presses the evidence saw.

A retryable device error (camera, press, arm link) of the press made while a late score was out
folds that score in before anything is journalled for the error (``PressLoop._before_retry``), so
the journal keeps press order (the late score's ``frame_skipped`` before this press's ``retry``).
If the score decides, the failed press was speculative - the sequential loop never made it - and
the piece keeps its decision: the gel is lifted, the error logged and kept in the pre_sort record
(``speculative_error``, not compared on replay, like ``speculative_presses``), no retry, no fault;
the device's next use is the next item's, under its own retry rules. A safety stop or a
non-retryable device error during that press still latches a fault on the piece (reject): the arm
is stopped where it is, and nothing is routed from under it.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable

from vs2t_edge.runtime.devices import CameraError
from vs2t_edge.runtime.preprocess import FrameError


class _Later:
    """A score computed in the caller's thread when asked for: the sequential loop's 'future'."""

    def __init__(self, fn: Callable[[], Any]) -> None:
        self._fn = fn

    def done(self) -> bool:
        return True  # computing it now costs the same as waiting: fold it in at once

    def result(self) -> Any:
        return self._fn()


def reduced_kw(frame: Any) -> dict:
    """``{"reduced_by": n}`` for a frame the camera decoded at 1/n scale (runtime/devices.py Frame),
    else nothing: the model's ``set_reference`` / ``score_press`` take it; models that never see
    such frames (the fakes, descriptor bundles) keep their one-argument form."""
    n = getattr(frame, "reduced_by", 1)
    return {"reduced_by": n} if n != 1 else {}


class PressScorer:
    """The model's score of a press in one worker thread (overlap) or in the caller (sequential).

    ``start(frame)`` is called by the press itself, before the gel lifts; ``claim()`` takes the
    score of the press that returned. A press that is retried calls ``start`` again: the earlier
    attempt's score is dropped unread, as sequentially that frame was never scored."""

    def __init__(self, score_press: Callable[[Any], Any], overlap: bool) -> None:
        self.score_press, self.overlap = score_press, overlap  # model.score_press(image) -> a score
        self._pool: ThreadPoolExecutor | None = None
        self._latest: Any = None  # the last started, not yet claimed score
        self._running: list[Future] = []  # every future of this item, for drain()

    def start(self, frame: Any) -> None:
        image, reduced = frame.image, reduced_kw(frame)
        if isinstance(self._latest, Future):
            self._latest.cancel()  # a retried press: the failed attempt's frame is not scored
        if not self.overlap:
            self._latest = _Later(lambda: self.score_press(image, **reduced))
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="score-press")
        future = self._pool.submit(self.score_press, image, **reduced)
        self._running.append(future)
        self._latest = future

    def claim(self) -> Any:
        latest, self._latest = self._latest, None
        if latest is None:
            raise RuntimeError("a press returned without starting its score")  # a bug, latched as one
        return latest

    def drain(self) -> None:
        """Wait for every score of this item to end (results and errors unread: the loop has
        read the ones it uses), so none runs into the next item."""
        running, self._running, self._latest = self._running, [], None
        for future in running:
            if not future.cancel():
                future.exception()  # waits; an error of a score nobody uses was never its concern

    def close(self) -> None:
        self.drain()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


@dataclass
class Tally:
    """What an item's presses have produced so far; the cell's fault paths read it too."""

    presses: int = 0  # scored presses the evidence saw
    skipped: int = 0  # frames the model could not score (FrameError)
    speculative: int = 0  # presses made while a late score was pending, that turned out not needed
    speculative_error: str = ""  # a speculative press's device error, which changed nothing
    latencies: list[float] = field(default_factory=list)  # model time per scored press
    scores: list[dict] = field(default_factory=list)  # per scored press, for the pre_sort record


@dataclass
class _Press:
    point: int
    x_mm: float
    y_mm: float
    force_n: float
    score: Any  # a Future (overlap) or _Later (sequential)


class _DecidedMeanwhile(Exception):
    """Raised out of a speculative press's failure once the late score it waited on decided."""

    def __init__(self, decision: Any) -> None:
        super().__init__("decided by a late score")
        self.decision = decision


class PressLoop:
    """One item's presses through ``cell``'s own press step and journal (runtime/cell.py)."""

    def __init__(self, cell: Any, number: int, evidence: Any, tally: Tally, t0: float) -> None:
        self.cell, self.number, self.evidence, self.tally, self.t0 = cell, number, evidence, tally, t0
        self._pending: _Press | None = None  # a press whose score came too late to fold in at its lift

    def run(self) -> Any:
        """Press until the evidence decides or a limit is reached; the decision or None."""
        cell, tally, scene = self.cell, self.tally, self.cell.scene
        for k, (x_mm, y_mm) in enumerate(scene.points_mm):
            if self._pending is not None and self._limit_near():
                decision = self._fold_pending()  # whether k may be pressed depends on it
                if decision is not None:
                    return decision
            # the evidence's own limit: extra presses past max_presses for a piece that earns them
            # (runtime/evidence.py); it decides at max_presses a piece that does not
            if tally.presses >= getattr(self.evidence, "press_limit", scene.max_presses):
                break
            if tally.skipped >= 2 * scene.max_presses:
                break  # the camera keeps giving bad frames: decide on what we have
            try:
                # a press's words count from 1, as the piece's press count does (its ``point`` stays 0-based)
                press, _frame = cell._step(f"press {k + 1} at ({x_mm}, {y_mm}) mm",
                                           lambda: cell._press_once(x_mm, y_mm, cell.scorer.start), self.t0,
                                           on_retryable=self._before_retry)
            except _DecidedMeanwhile as decided:
                return decided.decision  # press k failed, and sequentially it was never made
            current = _Press(k, x_mm, y_mm, float(press.force_n), cell.scorer.claim())
            if self._pending is not None:
                decision = self._fold_pending()
                if decision is not None:
                    tally.speculative += 1  # press k was made for nothing: never scored into the decision
                    return decision
            if current.score.done():
                decision = self._fold(current)
                if decision is not None:
                    return decision
            else:
                self._pending = current
        if self._pending is not None:
            return self._fold_pending()
        return None

    def _fold_pending(self) -> Any:
        pending, self._pending = self._pending, None
        return self._fold(pending)

    def _before_retry(self, exc: Exception) -> None:
        """A retryable failure of the press in hand, before the cell journals its retry (or
        latches its second failure): a late score still out is folded in first, so the journal
        keeps press order (that score's ``frame_skipped`` before this press's ``retry``). If it
        decides, this press was speculative - sequentially never made - and its failure must not
        change the decided piece: the gel is lifted, the error logged and kept in the pre_sort
        record (``speculative_error``), and the piece is sorted. The device is next used by the next
        item, whose own retry rules then apply to it (a camera still failing is reopened there)."""
        if self._pending is None:
            return
        decision = self._fold_pending()
        if decision is None:
            return  # as sequentially: this press was needed, its retry follows
        cell = self.cell
        if not isinstance(exc, CameraError):  # a failed grab has already been lifted by the press itself
            cell.lift_or_fault(exc)  # the gate never moves under a gel that is down
        self.tally.speculative += 1
        self.tally.speculative_error = f"{type(exc).__name__}: {exc}"
        cell.log(f"item {self.number}: a speculative press failed ({exc}); a late score had decided the piece, "
                 "which keeps its decision - the device is tried again by the next item")
        raise _DecidedMeanwhile(decision)

    def _limit_near(self) -> bool:
        """Could the pending score make the next press one too many? (From ``max_presses`` on, an
        evidence that may press on past it decides that from the pending score: it is folded in
        first, so extra presses are sequential.)"""
        scene, tally = self.cell.scene, self.tally
        return tally.presses + 1 >= scene.max_presses or tally.skipped + 1 >= 2 * scene.max_presses

    def _fold(self, p: _Press) -> Any:
        """Press ``p``'s score into the evidence (waiting for it if it is still running); the
        evidence's decision or None. A frame the model cannot score is skipped, as sequentially."""
        cell, tally = self.cell, self.tally
        try:
            score = p.score.result()
        except FrameError as exc:
            tally.skipped += 1
            cell.skipped_total += 1
            cell.journal.append({"type": "frame_skipped", "item": self.number, "point": p.point,
                                 "reason": exc.reason, "message": str(exc)})
            cell.log(f"item {self.number}: frame of press {p.point + 1} skipped ({exc.reason})")
            cell.notifier.ping_if_due()
            return None
        tally.presses += 1
        tally.latencies.append(float(getattr(score, "latency_ms", 0.0)))
        tally.scores.append({"point": p.point, "x_mm": p.x_mm, "y_mm": p.y_mm, "force_n": p.force_n,
                             **score_dict(score)})
        cell.notifier.ping_if_due()
        return self.evidence.add(score)


def score_dict(score: Any) -> dict:
    """A PressScore as plain JSON numbers (for the journal and replay comparisons)."""
    out: dict[str, Any] = {}
    for key in ("novelty", "untouched", "latency_ms"):
        v = getattr(score, key, None)
        if isinstance(v, (bool, int, float)):
            out[key] = v if isinstance(v, bool) else float(v)
    lp = getattr(score, "log_posterior", None)
    if isinstance(lp, dict):
        out["log_posterior"] = {str(k): float(v) for k, v in lp.items()}
    elif lp is not None:
        try:
            out["log_posterior"] = [float(v) for v in lp]
        except TypeError:
            pass
    return out

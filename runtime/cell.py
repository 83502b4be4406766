"""The one cell loop. The live daemon, replay and the demo all run this code.

Everything it touches is injected: camera, arm and gate (runtime/devices.py protocols), the
model (``set_reference`` / ``score_press``), an evidence factory (runtime/evidence.py), the
item source, the journal, the notifier and the clock. Per item::

    wait for item -> reference frame (gel in the air above the first point)
    -> for each grid point (config order): move_above, press, grab, retract, score
       -> evidence.add(score) until it decides (confident) or the press limit
       (runtime/press_pipeline.py; with ``overlap_scoring`` a press is scored in a worker thread
       while the arm lifts and moves on - the evidence sees the same scores in the same order)
    -> bin from the scene (a scene fabric -> its bin; "unknown" or off-scene -> reject bin)
    -> journal "pre_sort" record, fsynced  -> gate.sort(bin), ack awaited
    -> journal "final" record (exactly one per item)

Retry policy (one table, so the behaviour is reviewable):

* retryable device error (CameraError, PressFailed, ArmConnectionError): that press is tried
  once more; a second failure latches a fault. Before the retry of a CameraError the camera is
  reopened; if it does not reopen, the retry has failed. Reopened after the item's reference
  was taken, the retry's frame decides nothing: the piece goes to reject (``ReferenceStale``).
* with a ``contact_check``: a press frame that is still the no-contact reference is a
  CameraError of kind ``no_contact`` (retried, not reopened for).
* a bad frame from the camera (black, white, saturated, wrong size): every camera's frame guard
  (runtime/frame_guard.py) makes it a CameraError, so it is retried as above, then latched.
* a press the model cannot score (FrameError from inference: non-finite output): skipped,
  counted, journalled, never used; the next grid point is pressed. An item whose frames are all
  unusable is decided "unknown" -> reject.
* ArmSafetyStop, any other device error, a gate error, an item over its time budget: a
  latched fault.
* any other exception (an onnxruntime RuntimeError from the model, a device used while not
  connected, a bug): a latched fault of kind ``internal``, its type and text as the reason and
  its traceback in the log - sensor lifted, arm stopped, gate to reject, the item's final record
  ``rejected_fault`` (``unknown_outcome`` once a SORT went out), the fault file written. Only
  KeyboardInterrupt/SystemExit end the loop (the daemon shuts down safely and re-raises).

Latched fault (Klipper's shutdown): arm.stop(), gate.to_reject(), the reason in the journal,
in STATUS and in the fault file — each step guarded so one failing step does not skip the
rest. The item in hand gets its final record (``rejected_fault``). Nothing moves until an
operator clears the fault: the fault file is removed (``vs2t-edge run --clear-fault``), after
which the loop clears the gate and carries on. The fault file survives a restart, so a restart
does not clear a fault either. A fault file that could not be written is no clear: it is written
again while the fault stays latched, and a restart that finds none restores the journal's fault if
its record says so (runtime/fault_latch.py, which holds this part of the loop).

A journal write that fails (disk full, I/O error) latches a fault too: the journal has cut the
partial record back, the item in hand stays open in the journal (its ``item`` or ``pre_sort``
record is the last one), nothing moves. The operator's clear first resolves such open items
exactly as a restart would (``aborted`` before a decision, ``unknown_outcome`` after the
pre-sort record) - if the disk is still full that fails and the fault latches again.

Memory is bounded: ``results`` keeps the last ``RECENT_RESULTS`` items, ``items_done`` and
``outcomes`` count them all. A caller that needs every result (the demo's summary, replay) passes
``on_item``, which sees each result once as it is made; the journal file has every decision.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from typing import Any, Callable

import threading

from vs2t_edge.runtime.devices import (
    ArmSafetyStop,
    CameraError,
    DeviceError,
    GateError,
)
from vs2t_edge.runtime.fault_latch import (  # noqa: F401 - MAX_FAULT_FILE_BYTES, INTERNAL: importable from here
    INTERNAL, MAX_FAULT_FILE_BYTES, UNKNOWN, FaultLatch)
from vs2t_edge.runtime.items import Item, ItemResult, ItemSource
from vs2t_edge.runtime.journal import JournalError
from vs2t_edge.runtime.preprocess import FrameError
from vs2t_edge.runtime.press_pipeline import PressLoop, PressScorer, Tally, reduced_kw
from vs2t_edge.runtime.scene_spec import SceneSpec

NO_CONTACT = "no_contact"  # CameraError kind: the press frame shows the gel untouched
RECENT_RESULTS = 100  # ItemResults kept in memory (Cell.results); on_item sees every one
class CellFault(Exception):
    """Raised inside the loop to latch a fault; ``reason`` is what the operator reads.
    ``maybe_routed``: a SORT sent for this item may have been executed whatever ``kind`` says
    (an earlier try of it timed out)."""

    def __init__(self, reason: str, kind: str = "fault", maybe_routed: bool = False) -> None:
        super().__init__(reason)
        self.reason, self.kind, self.maybe_routed = reason, kind, maybe_routed


class StopRequested(Exception):
    pass


# Pieces in a row sent to reject by a camera reopened mid-piece (ReferenceStale) before a fault
# latches: one or two are glitches (the fault matrix's corrupt_frames row has two in a row); a camera
# that drops out on every press would otherwise send every piece to the reject bin without an alarm.
STALE_PIECES_TO_FAULT = 3


class ReferenceStale(Exception):
    """The camera was reopened after the item's no-contact reference was taken: the piece goes to
    the reject bin (docs/cell.md, retry policy)."""


class _Done(Exception):
    """Cell.run's own end (max_items, stop_when): not a fault."""



def _finite(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(float(x)) else None


class Cell(FaultLatch):
    def __init__(self, *, camera, arm, gate, model, journal, notifier, scene: SceneSpec,
                 evidence_factory: Callable[[], Any], items: ItemSource,
                 clock: Callable[[], float] = time.monotonic, stop_event: threading.Event | None = None,
                 on_item: Callable[[ItemResult], None] | None = None, log: Callable[[str], None] | None = None,
                 sleep: Callable[[float], None] = time.sleep, contact_check: Any = None) -> None:
        self.camera, self.arm, self.gate, self.model = camera, arm, gate, model
        # the model is looked up per press: a caller may swap cell.model between items
        self.scorer = PressScorer(lambda image, **reduced: self.model.score_press(image, **reduced),
                                  scene.overlap_scoring)
        # runtime/contact.py ContactCheck (or anything with its read()): each press frame against
        # the item's no-contact reference. None = not checked (see _require_contact).
        self.contact_check = contact_check
        self._reference_image = None
        self._stale_run = 0  # pieces in a row ended by a camera reopened mid-piece
        self.journal, self.notifier, self.scene = journal, notifier, scene
        self.evidence_factory, self.items, self.clock = evidence_factory, items, clock
        self.stop_event = stop_event or threading.Event()
        self.on_item = on_item
        self.log = log or (lambda msg: None)
        self.sleep = sleep
        self.fault: str | None = None
        self._fault_file_written = False  # FaultLatch: only a fault file that was there and is gone clears it
        self.results: deque[ItemResult] = deque(maxlen=RECENT_RESULTS)  # the most recent only
        self.items_done = 0  # items finished by this Cell (every outcome)
        self.outcomes: Counter = Counter()  # items finished by outcome
        self.skipped_total = 0
        self.next_number = journal.next_item_number()

    # --- start-up ----------------------------------------------------------------------

    # --- the loop ----------------------------------------------------------------------

    def run(self, max_items: int | None = None, stop_when: Callable[[], bool] | None = None) -> list[ItemResult]:
        """Sort until stopped (SIGTERM sets stop_event), ``max_items`` done by this Cell, or
        stop_when() is true. Returns the last (up to RECENT_RESULTS) results; ``on_item`` sees all."""
        while not self.stop_event.is_set():
            try:
                self._run_once(max_items, stop_when)
            except _Done:
                break
            except Exception as exc:  # noqa: BLE001 - outside an item (feeder, notifier, clear): latch too
                if self.fault is None:
                    self._latch_internal(exc, "")
                else:
                    # already latched: an error that repeats on every turn (a broken notifier, an
                    # unreadable fault file) must not append a fault record per turn in a tight loop
                    self.log(f"while latched ({self.fault}): {type(exc).__name__}: {exc}")
                    self.sleep(min(1.0, self.scene.wait_item_timeout_s))
        return list(self.results)

    def _run_once(self, max_items: int | None, stop_when: Callable[[], bool] | None) -> None:
        """One turn of the loop: wait out a latched fault, or take and sort one item."""
        self.notifier.ping_if_due()
        if max_items is not None and self.items_done >= max_items:
            raise _Done()
        if stop_when is not None and stop_when():
            raise _Done()
        if self.fault is not None:
            if not self.fault_cleared_by_operator():
                self.sleep(min(0.2, self.scene.wait_item_timeout_s))
                return
            if not self.clear_fault():
                return
        self.notifier.status(f"waiting for item ({self.outcomes['sorted']} sorted)")
        item = self.items.next_item(self.scene.wait_item_timeout_s)
        if item is None:
            return
        try:
            result = self.process_item(item)
        except JournalError as exc:
            # the record was cut back; the item stays open in the journal and is resolved
            # when the operator clears (or at restart). Nothing moves meanwhile.
            self.latch_fault(f"item {self._number} ({item.id}): journal write failed: {exc}", "journal")
            return
        if result is not None:
            self.results.append(result)
            self.items_done += 1
            self.outcomes[result.outcome] += 1
            if self.on_item is not None:
                self.on_item(result)

    def _check_time(self, t0: float) -> None:
        if self.clock() - t0 > self.scene.item_timeout_s:
            raise CellFault(f"item took longer than {self.scene.item_timeout_s} s", "item_timeout")
        if self.stop_event.is_set():
            raise StopRequested()

    def _reopen_camera(self, why: str, *, raise_on_failure: bool = False) -> str | None:
        """Disconnect + connect the camera, the close guarded so a failing one does not skip the
        open. Returns None once open again, else the open's error (raised if asked)."""
        try:
            self.camera.disconnect()
        except Exception as exc:  # noqa: BLE001 - a half-dead device may fail to close; open anyway
            self.log(f"camera disconnect before reopening failed ({exc}); opening anyway")
        try:
            self.camera.connect()
        except DeviceError as exc:
            self.log(f"camera did not reopen for {why}: {exc}")
            if raise_on_failure:
                raise
            return str(exc)
        self.log(f"camera reopened for {why}")
        return None

    def _lift_gel(self, after: str, failures: type[Exception] = DeviceError) -> bool:
        """Before latching a fault that is not a safety stop, lift the sensor off the piece: left
        at depth after 'force never reached', the tool sits where the fabric will be put back (the
        operator's fix then drives it into the piece and the controller protective-stops). A
        safety stop is never moved out of; a failing retract (``failures``: a device error, or
        any Exception after an internal fault) is logged and left for the operator. Whether the
        gel is up."""
        try:
            with self.notifier.bounded_wait(self.scene.bounds.lift_s if self.scene.bounds else None):
                self.arm.retract()
        except failures as lift_exc:
            self.log(f"could not lift the sensor after {after}: {lift_exc}")
            return False
        return True

    def lift_or_fault(self, exc: Exception) -> None:
        """Lift the gel after ``exc`` failed a press whose piece a late score decided meanwhile
        (runtime/press_pipeline.py); a gel that will not lift latches a fault - the piece to the
        reject bin, as sequentially - rather than the gate moving with the gel on the piece."""
        if not self._lift_gel(getattr(exc, "kind", type(exc).__name__)):
            raise CellFault(f"could not lift the sensor after a failed press ({exc})", "repeated_failure") from exc

    def _step(self, what: str, fn: Callable[[], Any], t0: float,
              on_retryable: Callable[[DeviceError], None] | None = None) -> Any:
        """One press step with the retry policy: a retryable error is retried once. Before the
        retry of a camera fault the camera is reopened (a UVC device that vanished and came back
        delivers nothing to the old handle); if it does not reopen, the retry has failed.
        ``on_retryable(exc)`` sees a retryable error first (the press pipeline folds a late score
        in there, and may end the step by raising). A camera reopened after the item's reference
        was taken: the retry still runs (it tests the camera: a second failure latches a fault),
        but ``ReferenceStale`` then ends the item to the reject bin, its retried frame unscored."""
        bounds = self.scene.bounds
        reopened = False
        for attempt in (1, 2):
            self._check_time(t0)
            try:
                with self.notifier.bounded_wait(bounds.press_try_s if bounds else None):
                    result = fn()
                if reopened and self._reference_image is not None:
                    raise ReferenceStale(f"camera reopened for the retry of {what}")
                return result
            except ArmSafetyStop as exc:
                raise CellFault(f"arm safety stop during {what}: {exc}", exc.kind) from exc
            except DeviceError as exc:
                if isinstance(exc, GateError):
                    raise CellFault(f"gate fault during {what}: {exc}", exc.kind) from exc
                if not exc.retryable:
                    self._lift_gel(exc.kind)
                    raise CellFault(f"{exc.device or 'device'} fault during {what}: {exc}", exc.kind) from exc
                if on_retryable is not None:
                    on_retryable(exc)
                if attempt == 2:
                    self._lift_gel(exc.kind)
                    raise CellFault(f"{what} failed twice: {exc}", "repeated_failure") from exc
                self.log(f"{what} failed ({exc}); retrying once")
                self.journal.append({"type": "retry", "item": self._number, "step": what, "error": str(exc),
                                     "kind": exc.kind})
                with self.notifier.bounded_wait(bounds.retry_prep_s if bounds else None):
                    try:
                        self.arm.retract()
                    except DeviceError:
                        pass  # the retried step starts from move_above again
                    not_open = None
                    if isinstance(exc, CameraError) and exc.kind != NO_CONTACT:  # no contact: the camera works
                        not_open = self._reopen_camera(f"the retry of {what}")
                        reopened = not_open is None
                if not_open is not None:
                    raise CellFault(f"{what} failed twice: {exc}; reopening the camera for the retry "
                                    f"failed: {not_open}", "repeated_failure") from exc
        raise AssertionError("unreachable")

    def _press_once(self, x_mm: float, y_mm: float, on_frame: Callable[[Any], None] | None = None):
        """Move, press, grab, lift. A frame that passed the contact check goes to ``on_frame``
        before the lift (the scorer: overlapped, the model works while the gel comes up)."""
        self.arm.move_above(x_mm, y_mm)
        press = self.arm.press()
        try:
            frame = self.camera.grab()
            self._require_contact(frame)
            if on_frame is not None:
                on_frame(frame)
        finally:
            self.arm.retract()  # always lift the gel, also when the grab or the check failed
        return press, frame

    def _require_contact(self, frame) -> None:
        """A press frame that looks like the no-contact reference is no tactile reading: the
        gel did not reach the piece (no piece, wrong height, a press that reported force on
        nothing) or the camera shows a stale frame. Raised as a retryable camera fault, so the
        press is retried once and a second one latches a fault naming it."""
        check, reference = self.contact_check, self._reference_image
        if check is None or reference is None:
            return
        image = getattr(frame, "image", None)
        if getattr(image, "shape", None) != reference.shape or getattr(image, "dtype", None) != reference.dtype:
            return  # a wrong-size or wrong-type frame is the frame check's to refuse (skipped, not retried)
        reading = check.read(image, reference)
        if not reading.pressed:
            seen = reading.model_area_fraction
            where = "" if seen is None else f" and in {seen:.2%} of the square the model reads"
            raise CameraError(
                f"no contact: the press frame differs from the no-contact reference in "
                f"{reading.area_fraction:.2%} of the image{where} (peak {reading.peak_levels:.1f} grey levels; "
                f"a press needs {check.min_area_fraction:.2%} over {check.threshold_levels:g}) - the gel "
                "did not touch the piece (piece missing, wrong height, an imprint beside the model's square?) "
                "or the frame is stale", device="camera", kind=NO_CONTACT)

    def process_item(self, item: Item) -> ItemResult | None:
        t0 = self.clock()
        self._number = number = self.next_number
        self.next_number += 1
        self.notifier.status(f"item {number} ({item.id}): pressing")
        self.journal.append({"type": "item", "item": number, "item_id": item.id, "t": time.time()})
        learns = hasattr(self.evidence_factory, "remember")  # operator labels (runtime/feedback.py)
        tally = Tally()  # presses, skipped frames, latencies and scores so far (fault paths read it)
        stale_before = getattr(self.camera, "stale_dropped", 0)  # a UVC camera's frames read past (runtime/camera.py)
        decision = None
        pre_written = False
        gate_told = False  # a SORT went out: from here a lost ack means the flap may have moved
        final_written = False
        label, bin_ = UNKNOWN, self.scene.reject_bin
        try:
            # inside the try: an exception here is this piece's fault, its final record says so
            if learns:
                self.evidence_factory.poll(self.journal)  # labels journaled before this piece is pressed
            evidence = self.evidence_factory()
            x0, y0 = self.scene.points_mm[0]

            def reference():
                self.arm.move_above(x0, y0)
                return self.camera.grab()

            self._reference_image = None  # never check a press against the last item's reference
            ref = self._step("reference frame", reference, t0)
            try:
                self.model.set_reference(ref.image, **reduced_kw(ref))
            except FrameError as exc:
                raise CellFault(f"no-contact reference frame unusable: {exc}", "reference") from exc
            self._reference_image = ref.image
            stale = ""  # a reset sensor may expose otherwise than for the reference: no decision on it
            try:
                decision = PressLoop(self, number, evidence, tally, t0).run()
            except ReferenceStale as exc:
                decision, stale = None, str(exc)
                self.log(f"item {number}: {exc} after its no-contact reference was taken: to the reject bin")
                self._stale_run += 1
                if self._stale_run >= STALE_PIECES_TO_FAULT:  # a camera that drops out on every press
                    self._stale_run = 0
                    raise CellFault(f"the camera had to be reopened mid-piece on {STALE_PIECES_TO_FAULT} pieces in "
                                    f"a row (last: {exc}); every such piece goes to reject - check the camera's "
                                    "cable and mount", "repeated_failure") from exc
            else:
                self._stale_run = 0
            if decision is None and not stale:
                decision = evidence.decide() if tally.presses else None
            label = decision.label if decision is not None else UNKNOWN
            confidence = float(decision.confidence) if decision is not None else 0.0
            stopped_by = decision.stopped_by if decision is not None else ("camera_reopened" if stale
                                                                           else "no_usable_frames")
            bin_ = self.scene.bin_for(label)
            pre = {"type": "pre_sort", "item": number, "item_id": item.id, "label": label, "bin": bin_,
                   "confidence": confidence, "presses": tally.presses,
                   "skipped_frames": tally.skipped, "stopped_by": stopped_by, "scores": tally.scores,
                   "log_posterior": _jsonable(getattr(decision, "log_posterior", None))}
            z_mean = self.evidence_factory.journal_z_mean(evidence) if learns else None
            if z_mean is not None:  # what a later label reads (live and after a restart alike)
                pre["scene_z_mean"] = z_mean
                if (n_mean := self.evidence_factory.journal_z_presses(evidence)) is not None:
                    pre["scene_z_presses"] = n_mean  # outlier presses left out of the mean (runtime/evidence.py)
            if (read_past := getattr(self.camera, "stale_dropped", 0) - stale_before) > 0:
                pre["stale_frames_read_past"] = read_past  # taken before a grab: a camera whose queue runs deep
            if tally.speculative:  # the arm pressed on while a late score decided (press_pipeline.py)
                pre["speculative_presses"] = tally.speculative
            if tally.speculative_error:  # ... and that press failed, which changed nothing
                pre["speculative_error"] = tally.speculative_error
            self.journal.append(pre)  # durable BEFORE the gate moves
            pre_written = True
            if "scene_z_mean" in pre:
                self.evidence_factory.remember(item.id, evidence)
            self.notifier.status(f"item {number}: {label} -> bin {bin_}")
            self._check_time(t0)
            gate_told = True
            self.notifier.ping_if_due()  # the sort and its retry are un-leased: budget.unleased_waits
            try:
                self.gate.sort(bin_)
            except GateError as exc:
                if exc.retryable:
                    self.log(f"gate did not answer ({exc}); one more try")
                    try:
                        self.gate.sort(bin_)
                    except GateError as exc2:
                        # the first SORT may have been executed with only its acks lost: a refused
                        # retry (latched meanwhile, jam, NAK) says nothing about where the piece went
                        raise CellFault(f"gate fault sorting to bin {bin_}: {exc2} (after a first try that "
                                        f"timed out: {exc})", exc2.kind, maybe_routed=True) from exc2
                else:  # a link lost after the SORT went out may have left the flap at the bin
                    raise CellFault(f"gate fault sorting to bin {bin_}: {exc}", exc.kind,
                                    maybe_routed=bool(getattr(exc, "maybe_executed", False))) from exc
            self._final(number, item.id, label=label, bin_=bin_, outcome="sorted", confidence=confidence,
                        presses=tally.presses)
            final_written = True
            result = ItemResult(item, label, bin_, "sorted", tally.presses, confidence, stopped_by,
                                tally.skipped, tally.latencies, self.clock() - t0)
        except CellFault as fault:
            # A SORT that timed out may have been executed with only its acks lost (docs/protocol.md):
            # the piece is in its bin or the reject bin, and the record says so instead of claiming
            # reject. A NAK of a gate that stays ready, or a reboot (the MCU boots to reject), did not
            # route it.
            # An ACK that contradicts the sort (bad_ack: another bin, a latched or moving gate) is no
            # more certain than a lost one: the flap is where the gate says, or nobody knows.
            # A SORT refused by a gate latched in fault (a jam) may have routed it too (the gate
            # driver's maybe_executed), and its reply names the last bin the flap reached.
            uncertain = gate_told and (fault.kind in ("timeout", "bad_ack") or fault.maybe_routed)
            reported = getattr(fault.__cause__, "reported_bin", None) if uncertain else None
            if fault.kind != "bad_ack" and reported == self.scene.reject_bin:
                reported = None  # the reject bin is named anyway
            where = ("where the gate says the flap is" if fault.kind == "bad_ack"
                     else "the last bin the latched gate reports its flap at")
            also = f", bin {reported} ({where})" if reported not in (None, bin_) else ""
            reason = fault.reason + (f"; the piece may be in bin {bin_}{also} or the reject bin - check "
                                     f"{'them' if also else 'both'}" if uncertain else "")
            outcome = "unknown_outcome" if uncertain else "rejected_fault"
            self.latch_fault(f"item {number} ({item.id}): {reason}", fault.kind)
            self._final(number, item.id, label=label if pre_written else UNKNOWN, bin_=self.scene.reject_bin,
                        outcome=outcome, reason=reason, presses=tally.presses,
                        **({"maybe_bin": bin_} if uncertain else {}),
                        **({"reported_bin": reported} if also else {}))
            result = ItemResult(item, UNKNOWN, self.scene.reject_bin, outcome, tally.presses, 0.0,
                                "fault", tally.skipped, tally.latencies, self.clock() - t0)
        except StopRequested:
            # SIGTERM mid-item: lift the gel, gate to reject, the item's final record says so.
            bounds = self.scene.bounds
            with self.notifier.bounded_wait(bounds.abort_s if bounds else None):
                for fn in (self.arm.retract, self.gate.to_reject):
                    try:
                        fn()
                    except Exception:  # noqa: BLE001 - stopping must reach the journal
                        pass
            self._final(number, item.id, label=UNKNOWN, bin_=self.scene.reject_bin, outcome="aborted",
                        reason="service stopping", presses=tally.presses)
            result = ItemResult(item, UNKNOWN, self.scene.reject_bin, "aborted", tally.presses, 0.0,
                                "stop", tally.skipped, tally.latencies, self.clock() - t0)
        except JournalError:
            # Cell.run latches it; the item stays open in the journal (see the module doc). The gel
            # first, as before any other fault: a write that failed between a failed press and its
            # retry would leave the tool at depth on the piece
            self._lift_gel("a journal write failed", Exception)
            raise
        except Exception as exc:  # noqa: BLE001 - no rule for it: latch like any other fault
            # The gate may have executed a SORT that was sent before the exception: the record says
            # the outcome is unknown instead of claiming reject. An item already finalised (the
            # exception came after its final record) keeps that record.
            self._lift_gel(type(exc).__name__, Exception)  # first, as _step does before a CellFault
            reason = self._latch_internal(exc, f"item {number} ({item.id}): ")
            uncertain = gate_told and not final_written
            outcome = "unknown_outcome" if uncertain else "rejected_fault"
            if not final_written:
                note = f"; the piece may be in bin {bin_} or the reject bin - check both" if uncertain else ""
                self._final(number, item.id, label=label if pre_written else UNKNOWN, bin_=self.scene.reject_bin,
                            outcome=outcome, reason=reason + note, presses=tally.presses,
                            **({"maybe_bin": bin_} if uncertain else {}))
            result = ItemResult(item, UNKNOWN, self.scene.reject_bin, outcome, tally.presses, 0.0,
                                "fault", tally.skipped, tally.latencies, self.clock() - t0)
        finally:
            # after the latch and the final record, never before them: no score of this item may
            # run into the next one's set_reference
            self.scorer.drain()
        return result

    def shutdown(self, reason: str = "stopped") -> None:
        """Gate to reject, arm stopped, scorer thread ended, journal closed; every step guarded."""
        for fn in (self.gate.to_reject, self.arm.stop, self.scorer.close):
            try:
                fn()
            except Exception:  # noqa: BLE001
                pass
        try:
            self.journal.append({"type": "stop", "reason": reason, "t": time.time(),
                                 "items": self.items_done, "outcomes": dict(self.outcomes)})
        except JournalError as exc:  # a full disk must not turn a clean stop into a crash
            self.log(f"stop record not written: {exc}")
        finally:
            self.journal.close()


def _jsonable(x: Any) -> Any:
    if x is None:
        return None
    if isinstance(x, dict):
        return {str(k): _finite(v) for k, v in x.items()}
    try:
        return [_finite(v) for v in x]
    except TypeError:
        return _finite(x) if isinstance(x, (int, float)) else str(x)

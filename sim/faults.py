"""The fault matrix: the simulated cell under every fault of issue 8, each row checked.

Every scenario builds a small cell (a few items), injects one fault at a known press, runs the
real loop (runtime/cell.py) or the real daemon (runtime/daemon.py, in a subprocess for the
signal rows) and then audits the journal with the same promises for every row:

* exactly one ``final`` record per ``item`` record, no item number or piece id twice;
* no piece sorted on a guess: a ``sorted`` piece is in its own fabric's bin or in the reject bin;
* the gate executed exactly one move per sorted piece (pty gate rows: counted in the MCU sim);
* the daemon either carried on (retry, skipped frame) or latched a fault with a reason, and after
  the operator's clear the remaining pieces were sorted.

Which boundary each row exercises is in its ``where`` column: ``loop`` rows use the in-process
fakes (FakeArm, FakeGate, SimulatedCamera) because the row is about the loop's logic; ``ursim``
rows use the real ur_rtde client (IsolatedURArm) against the loopback UR simulator; ``pty gate``
rows use the real host driver against the MCU simulator on a pty; ``daemon`` rows run the real
daemon as a subprocess and signal it; ``journal`` rows damage the journal file or its write path.

The model is a grey-level fake (a pressed frame's mean grey level votes for one fabric), as in the
cell tests: the rows check the loop's promises, not a bundle's accuracy. Run it all with
``vs2t-edge reliability`` (sim/faults_cli.py), which writes docs/reliability.md.
"""

from __future__ import annotations

import errno
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from vs2t_edge.runtime.cell import Cell, Item, SceneSpec
from vs2t_edge.runtime.journal import Journal, read_records
from vs2t_edge.runtime.notify import Notifier
from vs2t_edge.runtime.preprocess import check_frame

CLASSES = ["denim", "silk", "wool"]
BINS = {"denim": 1, "silk": 2, "wool": 3}
GREY = {"denim": 50, "silk": 60, "wool": 70, "tweed": 100}  # tweed: off-scene, votes for nothing
REFERENCE_GREY = 120
REJECT = 0


# --- the fake model and evidence (same rule as tests/cell_fakes.py; sim/ cannot import tests/) --

@dataclass(frozen=True)
class GreyScore:
    log_posterior: dict
    novelty: float
    untouched: bool
    latency_ms: float


@dataclass(frozen=True)
class GreyDecision:
    label: str
    confidence: float
    presses: int
    log_posterior: dict
    stopped_by: str


class GreyModel:
    """A pressed frame of mean grey level v votes for the fabric whose GREY is nearest (within 4)."""

    def __init__(self, classes=CLASSES, strength: float = 3.0) -> None:
        self.classes, self.strength = list(classes), strength
        self.votes = {GREY[c]: c for c in self.classes}

    def set_reference(self, frame) -> None:
        check_frame(frame, name="reference frame")

    def score_press(self, frame) -> GreyScore:
        t0 = time.perf_counter()
        check_frame(frame)
        v = float(frame[..., 0].mean())
        target = min(self.votes, key=lambda g: abs(g - v))
        target_name = self.votes[target] if abs(target - v) <= 4 else None
        lp = {c: (0.0 if c == target_name else -self.strength) for c in self.classes}
        return GreyScore(lp, novelty=v, untouched=False, latency_ms=(time.perf_counter() - t0) * 1000)


class GreyEvidence:
    """Sum of log posteriors; decides once the normalised posterior reaches ``confidence``."""

    def __init__(self, classes=CLASSES, confidence: float = 0.95, max_presses: int = 3) -> None:
        self.classes, self.confidence, self.max_presses = list(classes), confidence, max_presses
        self.total = {c: 0.0 for c in self.classes}
        self.n = 0

    def _posterior(self) -> dict:
        m = max(self.total.values())
        z = sum(math.exp(v - m) for v in self.total.values())
        return {c: math.exp(v - m) / z for c, v in self.total.items()}

    def add(self, score):
        self.n += 1
        for c in self.classes:
            self.total[c] += score.log_posterior.get(c, -30.0)
        post = self._posterior()
        best = max(post, key=post.get)
        if post[best] >= self.confidence:
            return GreyDecision(best, post[best], self.n, dict(self.total), "confident")
        return self.decide() if self.n >= self.max_presses else None

    def decide(self):
        post = self._posterior()
        best = max(post, key=post.get)
        label = best if post[best] >= self.confidence else "unknown"
        return GreyDecision(label, post[best], self.n, dict(self.total), "press_limit")


# --- the scene: items, an arm proxy that knows what is pressed, a camera fed from it ---------

class Pieces:
    """ItemSource over a fixed list of fabric names; ``current`` is the piece under the gel."""

    def __init__(self, truths: list[str]) -> None:
        self.items = [Item(f"piece-{i:04d}", t) for i, t in enumerate(truths)]
        self.index = -1

    @property
    def current(self) -> Item | None:
        return self.items[self.index] if 0 <= self.index < len(self.items) else None

    def next_item(self, timeout_s: float) -> Item | None:
        if self.index + 1 >= len(self.items):
            return None
        self.index += 1
        return self.items[self.index]

    def exhausted(self) -> bool:
        return self.index + 1 >= len(self.items)


class FaultArm:
    """Arm proxy: remembers whether the gel is pressed (for the camera) and fires scheduled faults.

    ``schedule[(item_index, press_number)] = fn``: ``fn()`` runs just before that press (1-based
    per item), so a fault lands mid-press at a known place.
    """

    def __init__(self, inner, pieces: Pieces) -> None:
        self.inner, self.pieces = inner, pieces
        self.pressed = False
        self.schedule: dict[tuple[int, int], Callable[[], None]] = {}
        self._item, self._press = -1, 0
        self.press_count = 0

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def connect(self) -> None:
        self.inner.connect()

    def disconnect(self) -> None:
        self.inner.disconnect()

    def move_above(self, x_mm: float, y_mm: float) -> None:
        self.pressed = False
        self.inner.move_above(x_mm, y_mm)

    def press(self):
        if self.pieces.index != self._item:
            self._item, self._press = self.pieces.index, 0
        self._press += 1
        fn = self.schedule.pop((self._item, self._press), None)
        if fn is not None:
            fn()
        result = self.inner.press()
        self.pressed = True
        self.press_count += 1
        return result

    def retract(self) -> None:
        self.pressed = False
        self.inner.retract()

    def stop(self) -> None:
        self.pressed = False
        self.inner.stop()


def grey_frames(arm: FaultArm, pieces: Pieces, hw=(48, 64)) -> Callable[[], np.ndarray]:
    def frame() -> np.ndarray:
        item = pieces.current
        grey = GREY.get(item.truth, 100) if (arm.pressed and item is not None) else REFERENCE_GREY
        return np.full(hw + (3,), grey, np.uint8)
    return frame


@dataclass
class Rig:
    cell: Cell
    arm: FaultArm
    camera: Any
    gate: Any
    pieces: Pieces
    journal_path: Path
    fault_file: Path
    operator: list = field(default_factory=list)  # what the operator did, in order


def build_rig(workdir: Path, truths: list[str], *, arm=None, gate=None, max_presses: int = 3,
              operator_fix: Callable[[], None] | None = None, item_timeout_s: float = 60.0,
              model=None, evidence_factory: Callable[[], Any] | None = None, bins: dict | None = None,
              frames: Callable[[FaultArm, Pieces], Callable[[], np.ndarray]] | None = None,
              camera=None) -> Rig:
    """A cell on the given (or fake) arm and gate; the operator clears a latched fault at once.

    ``operator_fix`` is what the operator does at the machine before removing the fault file
    (release a stop, free a jam); the loop's own ``clear_fault`` then clears the devices.
    ``model``, ``evidence_factory``, ``bins`` and ``frames`` replace the grey-level fake model,
    its evidence, its scene bins and its frames (the soak's real inference path).
    """
    from vs2t_edge.runtime.arm import FakeArm
    from vs2t_edge.runtime.camera import SimulatedCamera
    from vs2t_edge.runtime.gate import FakeGate
    from vs2t_edge.sim.scene import FAST_PRESS

    workdir.mkdir(parents=True, exist_ok=True)
    pieces = Pieces(truths)
    if arm is None:
        from vs2t_edge.runtime.arm import ArmConfig

        arm = FakeArm(config=ArmConfig(**FAST_PRESS))
    farm = FaultArm(arm, pieces)
    if camera is None:
        camera = SimulatedCamera((frames or grey_frames)(farm, pieces), noise_levels=1.0, seed=0,
                                 expected_hw=(48, 64))
    gate = gate if gate is not None else FakeGate()
    for dev in (gate, farm, camera):
        dev.connect()
    journal_path = workdir / "journal.jsonl"
    fault_file = workdir / "FAULT"
    points = farm.config.grid_points_mm()
    scene = SceneSpec(bins=dict(bins or BINS), reject_bin=REJECT, points_mm=points[:12], max_presses=max_presses,
                      confidence=0.95, item_timeout_s=item_timeout_s, wait_item_timeout_s=0.01,
                      fault_file=fault_file)
    operator: list = []

    def sleep(_s: float) -> None:
        # The loop sleeps only while a fault is latched: the operator fixes the machine and
        # removes the fault file, as `vs2t-edge run --clear-fault` does.
        if fault_file.exists():
            if operator_fix is not None:
                operator_fix()
            operator.append(fault_file.read_text().strip())
            fault_file.unlink()

    cell = Cell(camera=camera, arm=farm, gate=gate, model=model or GreyModel(), journal=Journal.open(journal_path),
                notifier=Notifier(address=""), scene=scene,
                evidence_factory=evidence_factory or (lambda: GreyEvidence(CLASSES, 0.95, max_presses)),
                items=pieces, sleep=sleep)
    cell.recover()
    return Rig(cell, farm, camera, gate, pieces, journal_path, fault_file, operator)


def run_rig(rig: Rig, limit_s: float = 120.0) -> None:
    t_end = time.monotonic() + limit_s
    try:
        rig.cell.run(stop_when=lambda: (rig.pieces.exhausted() and rig.cell.fault is None)
                     or time.monotonic() > t_end)
    finally:
        rig.cell.shutdown("scenario done")
        for dev in (rig.camera, rig.arm, rig.gate):
            try:
                dev.disconnect()
            except Exception:  # noqa: BLE001
                pass


# --- the audit: the same promises for every row ---------------------------------------------

def audit(journal_path: Path, truths: dict[str, str] | None = None) -> dict:
    """Check the journal's promises; ``problems`` lists every broken one in words."""
    recs = read_records(journal_path)
    problems: list[str] = []
    started = [r["item"] for r in recs if r.get("type") == "item"]
    finals = [r for r in recs if r.get("type") == "final"]
    final_items = Counter(r["item"] for r in finals)
    for n, c in final_items.items():
        if c != 1:
            problems.append(f"item {n} has {c} final records")
    if len(set(started)) != len(started):
        problems.append(f"an item number was started twice: {started}")
    missing = sorted(set(started) - set(final_items))
    if missing:
        problems.append(f"items without a final record: {missing}")
    ids = Counter(r.get("item_id") for r in finals)
    dup_ids = [i for i, c in ids.items() if c > 1]
    if dup_ids:
        problems.append(f"pieces with more than one final record: {dup_ids}")
    wrong = []
    for r in finals:
        if r.get("outcome") == "sorted" and truths is not None:
            truth = truths.get(r.get("item_id"))
            if r["bin"] not in (REJECT, BINS.get(truth, REJECT)):
                wrong.append(f"{r['item_id']} ({truth}) -> bin {r['bin']}")
        elif r.get("outcome") != "sorted" and r.get("bin") != REJECT:
            wrong.append(f"{r.get('item_id')} {r.get('outcome')} -> bin {r.get('bin')}")
    if wrong:
        problems.append("sorted on a guess / not rejected: " + ", ".join(wrong))
    return {"records": recs, "finals": finals, "outcomes": Counter(r.get("outcome") for r in finals),
            "faults": [r.get("reason", "") for r in recs if r.get("type") == "fault"],
            "retries": [r for r in recs if r.get("type") == "retry"],
            "skipped": [r for r in recs if r.get("type") == "frame_skipped"],
            "problems": problems}


@dataclass
class Row:
    name: str
    where: str
    fault: str
    expect: str
    outcome: str = ""
    passed: bool = False
    seconds: float = 0.0
    problems: list[str] = field(default_factory=list)
    pending: str = ""  # non-empty: the row cannot run yet, and why
    known_bug: str = ""  # the scenario's known bug (a failing row then reads KNOWN BUG, not FAIL)

    @property
    def result(self) -> str:
        if self.passed:
            return "PASS" + (" (known bug fixed? drop known_bug)" if self.known_bug else "")
        if self.pending:
            return "pending"
        return "KNOWN BUG" if self.known_bug else "FAIL"

    @property
    def blocking(self) -> bool:
        """A failure the command must report with exit 1 (known bugs are listed, not blocking)."""
        return not (self.passed or self.pending or self.known_bug)


def _outcome_words(a: dict, extra: str = "") -> str:
    o = a["outcomes"]
    parts = [f"{len(a['finals'])} finals ({', '.join(f'{k} {v}' for k, v in sorted(o.items()))})"]
    if a["retries"]:
        parts.append(f"{len(a['retries'])} retry")
    if a["skipped"]:
        parts.append(f"{len(a['skipped'])} frames skipped")
    if a["faults"]:
        parts.append("fault: " + "; ".join(f[:90] for f in a["faults"]))
    if extra:
        parts.append(extra)
    return "; ".join(parts)


def _check(problems: list[str], ok: bool, words: str) -> None:
    if not ok:
        problems.append(words)


TRUTHS = ["denim", "silk", "wool", "tweed"]


def _loop_row(workdir: Path, *, inject: Callable[[Rig], None], expect_outcomes: dict, fault_words: str | None,
              retries: int | None = None, skipped: int | None = None, truths=TRUTHS, arm=None, gate=None,
              operator_fix_for: Callable[[Rig], Callable[[], None]] | None = None, holder_out: dict | None = None,
              **kw) -> tuple[str, list[str]]:
    """Build, inject, run, audit; returns (outcome words, problems). ``holder_out`` (if given)
    receives the rig ("rig") and the audit ("audit")."""
    holder: dict = holder_out if holder_out is not None else {}

    def fix():
        if operator_fix_for is not None:
            operator_fix_for(holder["rig"])()

    rig = build_rig(workdir, list(truths), arm=arm, gate=gate, operator_fix=fix, **kw)
    holder["rig"] = rig
    inject(rig)
    run_rig(rig)
    a = audit(rig.journal_path, {it.id: it.truth for it in rig.pieces.items})
    problems = list(a["problems"])
    _check(problems, len(a["finals"]) == len(truths), f"{len(a['finals'])} finals for {len(truths)} pieces")
    for outcome, n in expect_outcomes.items():
        _check(problems, a["outcomes"].get(outcome, 0) == n,
               f"expected {n} {outcome}, got {a['outcomes'].get(outcome, 0)}")
    if fault_words is None:
        _check(problems, not a["faults"], f"unexpected fault: {a['faults']}")
    else:
        _check(problems, len(a["faults"]) == 1 and fault_words in a["faults"][0],
               f"expected one fault naming {fault_words!r}, got {a['faults']}")
        _check(problems, len(rig.operator) == 1, f"operator cleared {len(rig.operator)} times")
    if retries is not None:
        _check(problems, len(a["retries"]) == retries, f"expected {retries} retries, got {len(a['retries'])}")
    if skipped is not None:
        _check(problems, len(a["skipped"]) == skipped, f"expected {skipped} skipped frames, got {len(a['skipped'])}")
    holder["audit"] = a
    return _outcome_words(a), problems


# --- the scenarios ------------------------------------------------------------------------------

def _at(rig: Rig, item: int, press: int, fn: Callable[[], None]) -> None:
    rig.arm.schedule[(item, press)] = fn


def _unplug_camera(rig: Rig, item: int, press: int, *, for_good: bool) -> dict:
    """Pull the simulated camera's cable just before that press: a real disconnect, every grab
    fails until the camera is reopened. It is back for the first reopen, or (``for_good``) only
    once the operator has plugged it back in (``rig.camera.replug``). Returns a dict the row
    reads afterwards: ``connects`` = the camera's connect() calls when the cable came out."""
    seen: dict = {}

    def pull() -> None:
        seen["connects"] = rig.camera.connects
        rig.camera.unplug(failed_connects=None if for_good else 0)

    _at(rig, item, press, pull)
    return seen


def camera_unplugged_and_back(w: Path):
    # cable out mid-press, back at once: the loop reopens the camera before its one retry
    # (without the reopen the retry's grab finds it still disconnected and latches a fault)
    held: dict = {}

    def inject(r: Rig) -> None:
        held["rig"], held["seen"] = r, _unplug_camera(r, 1, 2, for_good=False)

    words, problems = _loop_row(w, inject=inject, expect_outcomes={"sorted": 4}, fault_words=None, retries=1)
    cam, seen = held["rig"].camera, held["seen"]
    _check(problems, "connects" in seen, "the cable was never pulled")
    _check(problems, cam.connects == seen.get("connects", 0) + 1 and not cam.cable_out,
           f"expected one reopen after the unplug, the camera saw {cam.connects - seen.get('connects', 0)}")
    return words + f"; camera reopened {cam.connected_count - 1}x", problems


def camera_unplugged_for_good(w: Path):
    # cable out mid-press and the retry's reopen fails: latched fault naming it, piece rejected;
    # the operator plugs it back in and clears, the clear reopens the camera, the rest are sorted
    # (without that reopen the next piece needs a retry of its own)
    held: dict = {}

    def inject(r: Rig) -> None:
        held["rig"], held["seen"] = r, _unplug_camera(r, 1, 2, for_good=True)

    def operator_fix(r: Rig):
        def fix() -> None:
            held["connects_at_fix"] = r.camera.connects
            r.camera.replug()
            grab = r.camera.grab

            def first_grab_after_the_clear():  # was the camera open again before the loop used it?
                held.setdefault("open_at_next_grab", r.camera.is_connected)
                return grab()
            r.camera.grab = first_grab_after_the_clear
        return fix

    words, problems = _loop_row(w, inject=inject, operator_fix_for=operator_fix,
                                expect_outcomes={"sorted": 3, "rejected_fault": 1},
                                fault_words="reopening the camera for the retry failed", retries=1)
    cam, seen = held["rig"].camera, held["seen"]
    _check(problems, "connects" in seen, "the cable was never pulled")
    _check(problems, cam.connects == seen.get("connects", 0) + 2,
           f"expected a failed reopen on the retry and one at the clear, got "
           f"{cam.connects - seen.get('connects', 0)} connect() calls")
    _check(problems, held.get("open_at_next_grab") is True and cam.connects == held.get("connects_at_fix", -9) + 1,
           "the operator's clear did not reopen the camera")
    return words + ("; camera reopened by the clear" if held.get("open_at_next_grab") else ""), problems


def _record_scores(rig: Rig, note: Callable[[np.ndarray], Any]) -> list:
    """Wrap the rig's model: ``note(frame)`` of every frame it scores, in order, in the list returned."""
    scored: list = []
    score = rig.cell.model.score_press

    def recording(frame):
        scored.append(note(frame))
        return score(frame)
    rig.cell.model.score_press = recording
    return scored


def camera_frozen(w: Path):
    # From press 1 of piece-0001 on, the driver hands out its last buffer (the piece's no-contact
    # frame) again, until the operator power-cycles the sensor. The first repeat is CameraFrozen
    # (frozen_after 2), the press is retried after a reopen, still frozen: the fault latches on
    # piece-0001 itself, which is rejected with no decision; the rest are sorted after the clear.
    # (With frozen_after 5 piece-0001 was decided on 3 frozen frames and the fault hit piece-0002.)
    held: dict = {}

    def inject(r: Rig) -> None:
        # (piece id, frame bytes) of every frame the model scored
        held["scored"] = _record_scores(r, lambda frame: (r.pieces.current.id, np.asarray(frame).tobytes()))
        _at(r, 1, 1, lambda: r.camera.inject("frozen", 1000))

    words, problems = _loop_row(w, inject=inject, operator_fix_for=lambda r: r.camera.clear_faults,
                                expect_outcomes={"rejected_fault": 1, "sorted": 3}, fault_words="same frame",
                                retries=1, holder_out=held)
    recs, faults = held["audit"]["records"], held["audit"]["faults"]
    _check(problems, len(faults) == 1 and "(piece-0001)" in faults[0],
           f"expected the fault on piece-0001, the first frozen piece, got {faults}")
    final = next((r for r in recs if r.get("type") == "final" and r.get("item_id") == "piece-0001"), {})
    _check(problems, final.get("outcome") == "rejected_fault" and final.get("presses") == 0,
           f"piece-0001: expected rejected_fault after 0 scored presses, got {final}")
    _check(problems, not any(r.get("type") == "pre_sort" and r.get("item_id") == "piece-0001" for r in recs),
           "piece-0001 was decided (a pre_sort record) from frozen frames")
    scored = held["scored"]
    _check(problems, not any(piece == "piece-0001" for piece, _ in scored),
           f"the model scored {sum(p == 'piece-0001' for p, _ in scored)} frame(s) of the frozen piece-0001")
    repeats = [p for (p, a), (_, b) in zip(scored, scored[1:]) if a == b]
    _check(problems, not repeats, f"a frame identical to the one before it was scored ({repeats})")
    return words + f"; {len(scored)} frames scored", problems


def corrupt_frames(w: Path):
    """A black and a truncated frame: the camera's frame guard refuses them (a retryable camera
    error), so the press is retried once each. Checked directly, not from the retry count: the
    guard refused exactly those two frames by reason, every frame the model scored has the
    camera's size and is not black, and the journal's scores are exactly the frames scored."""
    held: dict = {"refused": []}

    def inject(r: Rig):
        _at(r, 1, 1, lambda: r.camera.inject("black", 1))
        _at(r, 2, 1, lambda: r.camera.inject("truncated", 1))
        grab = r.camera.grab

        def watched_grab():
            try:
                return grab()
            except Exception as exc:  # noqa: BLE001 - recorded, then raised as the loop sees it
                held["refused"].append((r.pieces.index, getattr(exc, "kind", ""), getattr(exc, "reason", "")))
                raise
        r.camera.grab = watched_grab
        held["scored"] = _record_scores(r, lambda frame: (r.pieces.index, tuple(np.shape(frame)),
                                                          float(np.max(frame))))

    words, problems = _loop_row(w, inject=inject, expect_outcomes={"sorted": 4}, fault_words=None, retries=2,
                                holder_out=held)
    refused, scored = held["refused"], held["scored"]
    _check(problems, refused == [(1, "corrupt", "black"), (2, "corrupt", "size")],
           f"the frame guard refused {refused}, expected piece 1's black and piece 2's truncated frame")
    bad = [s for s in scored if s[1] != (48, 64, 3) or s[2] == 0.0]
    _check(problems, scored and not bad, f"frames scored that should not have been: {bad}")
    journal_scores = [sc for r in held["audit"]["records"] if r.get("type") == "pre_sort"
                      for sc in r.get("scores", [])]
    _check(problems, len(journal_scores) == len(scored),
           f"the journal holds {len(journal_scores)} scores for {len(scored)} frames scored")
    dark = [sc for sc in journal_scores if sc.get("novelty", 0.0) < 10.0]  # the grey model's novelty = mean level
    _check(problems, not dark, f"a black frame's score reached the evidence: {dark}")
    return words + (f"; guard refused {len(refused)} frames ({', '.join(f'piece {i} {why}' for i, _, why in refused)}),"
                    f" {len(scored)} frames scored, {len(bad)} of them corrupt"), problems


def all_frames_black(w: Path):
    # the gel is covered (black) for the press and its retry: a camera fault naming the cause
    return _loop_row(w, inject=lambda r: _at(r, 1, 1, lambda: r.camera.inject("black", 2)),
                     expect_outcomes={"sorted": 3, "rejected_fault": 1}, fault_words="all black", retries=1)


def replay_camera_bad_frames(w: Path):
    """The camera is a ReplayCamera (runtime/camera.py) on a folder of recorded frames, not the
    simulated one: frame 000004.png is corrupt (not a PNG) and 000008.png vanished from the disk
    after the camera listed the folder. Each must be refused naming the file, the press retried
    on the next recorded frame, and every other frame served once, in order: no frame of an
    earlier piece scored again, nothing lost, all three pieces sorted into their own bins.
    Every frame has its own grey level, so the journal's scores (the grey model's novelty is the
    frame's mean level) show which recorded frame each press was scored on."""
    import cv2

    from vs2t_edge.runtime.camera import ReplayCamera

    frames_dir = w / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    truths = ["denim", "silk", "wool"]
    # per piece: its no-contact reference, then two presses (the grey evidence decides on two);
    # a bad file sits where piece 1's and piece 2's first press would be
    levels: list[int | str] = [118, 48, 52, 119, "corrupt", 58, 62, 120, "missing", 68, 72]
    for i, v in enumerate(levels):
        path = frames_dir / f"{i:06d}.png"
        if v == "corrupt":
            path.write_bytes(b"\x89PNG\r\n\x1a\n not a picture")
        else:
            cv2.imwrite(str(path), np.full((48, 64, 3), 100 if v == "missing" else v, np.uint8))
    cam = ReplayCamera(frames_dir, expected_hw=(48, 64))
    held: dict = {}

    def inject(r: Rig) -> None:
        (frames_dir / "000008.png").unlink()  # gone after the camera listed the folder

    words, problems = _loop_row(w, inject=inject, truths=truths, camera=cam, expect_outcomes={"sorted": 3},
                                fault_words=None, retries=2, holder_out=held)
    retries = held["audit"]["retries"]
    for name, rec in zip(("000004.png", "000008.png"), retries):
        _check(problems, name in rec.get("error", ""), f"the refusal does not name {name}: {rec.get('error')!r}")
    scored = [round(sc["novelty"]) for r in held["audit"]["records"] if r.get("type") == "pre_sort"
              for sc in r["scores"]]
    want = [v for v in levels if isinstance(v, int) and v < 100]
    _check(problems, scored == want, f"press frames scored {scored}, the recording's press frames in order are "
                                     f"{want} (a frame scored twice or skipped: the camera lost its place)")
    return words + f"; both bad files refused by name, press frames scored in recorded order: {scored}", problems


def _fake_arm_fault(kind: str, count: int = 1):
    def inject(r: Rig):
        _at(r, 1, 2, lambda: r.arm.inner.fail_next.extend([kind] * count))
    return inject


def _release(r: Rig):
    return lambda: setattr(r.arm.inner, "latched", "")  # the operator releases the stop at the pendant


def protective_stop_fake(w: Path):
    return _loop_row(w, inject=_fake_arm_fault("protective_stop"), operator_fix_for=_release,
                     expect_outcomes={"sorted": 3, "rejected_fault": 1}, fault_words="protective_stop")


def emergency_stop_fake(w: Path):
    return _loop_row(w, inject=_fake_arm_fault("emergency_stop"), operator_fix_for=_release,
                     expect_outcomes={"sorted": 3, "rejected_fault": 1}, fault_words="emergency_stop")


def force_not_reached_once(w: Path):
    return _loop_row(w, inject=_fake_arm_fault("force_not_reached"), expect_outcomes={"sorted": 4},
                     fault_words=None, retries=1)


def force_never_reached(w: Path):
    return _loop_row(w, inject=_fake_arm_fault("force_not_reached", 2),
                     expect_outcomes={"sorted": 3, "rejected_fault": 1}, fault_words="failed twice", retries=1)


class LinkDrop:
    """The robot link drops in the middle of a press, and the arm really is disconnected.

    Wraps FakeArm the way IsolatedURArm behaves: ``press`` starts (the gel goes down), then the
    link drops - the inner arm is disconnected (any call on it now raises NotConnectedError), the
    press state (the target, force mode) is gone, and the press raises ArmConnectionError. The
    next motion call reconnects first (a new worker, a new link), as the real arm does; ``stop``
    and ``disconnect`` on a dead link do nothing. ``log`` records what happened, in order."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.drop_in_next_press = False
        self.down = False
        self.reconnects = 0
        self.log: list[str] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def _up(self) -> None:
        if self.down:
            self.inner.connect()
            self.down = False
            self.reconnects += 1
            self.log.append("reconnect")

    def connect(self) -> None:
        self.down = False
        self.inner.connect()

    def disconnect(self) -> None:
        if not self.down:
            self.inner.disconnect()

    def stop(self) -> None:
        if not self.down:
            self.inner.stop()

    def move_above(self, x_mm: float, y_mm: float) -> None:
        self._up()
        self.log.append("move_above")
        self.inner.move_above(x_mm, y_mm)

    def press(self):
        self._up()
        self.log.append("press")
        result = self.inner.press()  # the descent is under way ...
        if self.drop_in_next_press:
            from vs2t_edge.runtime.devices import ArmConnectionError

            self.drop_in_next_press = False
            self.inner.disconnect()  # ... and the link goes: really disconnected
            self.inner._target = None  # the controller's script restarted: no target, no force mode
            self.down = True
            self.log.append("drop")
            raise ArmConnectionError("link to the robot lost during press (injected mid-press)", device="arm",
                                     kind="connection_lost")
        return result

    def retract(self) -> None:
        self._up()
        self.log.append("retract")
        self.inner.retract()

    def clear_protective_stop(self) -> None:
        self._up()
        self.inner.clear_protective_stop()


def arm_connection_lost_fake(w: Path):
    """The link drops mid-press (FakeArm really disconnected, see LinkDrop): the arm reconnects on
    the next call and the cell retries the whole press (move_above first: the old target is gone,
    a bare re-press would be refused). One retry record, no fault, all sorted, nothing lost."""
    from vs2t_edge.runtime.arm import ArmConfig, FakeArm
    from vs2t_edge.sim.scene import FAST_PRESS

    link = LinkDrop(FakeArm(config=ArmConfig(**FAST_PRESS)))

    def inject(r: Rig) -> None:
        _at(r, 1, 2, lambda: setattr(link, "drop_in_next_press", True))

    held: dict = {}
    words, problems = _loop_row(w, inject=inject, arm=link, expect_outcomes={"sorted": 4}, fault_words=None,
                                retries=1, holder_out=held)
    log = link.log
    after = log[log.index("drop") + 1:] if "drop" in log else []
    _check(problems, "drop" in log, "the link never dropped")
    _check(problems, link.reconnects == 1 and after[:1] == ["reconnect"],
           f"expected one reconnect right after the drop, got {link.reconnects}: {after[:4]}")
    _check(problems, "press" in after and "move_above" in after and after.index("move_above") < after.index("press"),
           f"the press was not retried from move_above after the reconnect: {after[:6]}")
    retry = held["audit"]["retries"]
    _check(problems, len(retry) == 1 and retry[0].get("item") == 2 and retry[0].get("kind") == "connection_lost"
           and retry[0].get("step", "").startswith("press"),
           f"the retry record does not name piece 2's press and the lost link: {retry}")
    return words + f"; link dropped mid-press, {link.reconnects} reconnect, press redone from move_above", problems


def item_over_time_budget(w: Path):
    # a slow robot: the piece takes longer than item_timeout_s -> latched fault, piece rejected
    def inject(r: Rig):
        _at(r, 1, 1, lambda: r.cell.scene.__setattr__("item_timeout_s", 0.0))

    def restore(r: Rig):
        return lambda: r.cell.scene.__setattr__("item_timeout_s", 60.0)
    return _loop_row(w, inject=inject, operator_fix_for=restore,
                     expect_outcomes={"sorted": 3, "rejected_fault": 1}, fault_words="longer than")


# --- UR simulator rows (real ur_rtde client in a worker process, loopback simulator) ---------

@contextmanager
def _ursim_arm():
    """(the loopback UR simulator, an IsolatedURArm on it: the real ur_rtde client); the simulator
    is stopped on leaving."""
    from vs2t_edge.runtime.arm import ArmConfig
    from vs2t_edge.runtime.arm_isolated import IsolatedURArm
    from vs2t_edge.sim.scene import FAST_PRESS
    from vs2t_edge.sim.ursim import free_loopback_host
    from vs2t_edge.sim.ursim_model import PressScene
    from vs2t_edge.sim.ursim_process import URSimProcess

    sim = URSimProcess(PressScene(home_pose=(0.42, -0.08, 0.110, 0.0, math.pi, 0.0)),
                       host=free_loopback_host()).start()
    try:
        yield sim, IsolatedURArm(ArmConfig(host=sim.host, **FAST_PRESS))
    finally:
        sim.stop()


def _ursim_row(w: Path, trigger: str, expect_outcomes: dict, fault_words: str | None, retries=None):
    pytest_skip = _need_rtde()
    if pytest_skip:
        return pytest_skip, ["ur_rtde not installed"]
    with _ursim_arm() as (sim, arm):
        def inject(r: Rig):
            if trigger == "overforce_in_descent":
                # the controller's protective stop trips on the way down, once the gel is in contact
                _at(r, 1, 1, lambda: sim.set_faults(protective_stop_above_n=8.0))
            elif trigger == "trigger_emergency_stop":
                # the button is hit while the press is under way, not between commands
                _at(r, 1, 1, lambda: threading.Timer(0.12, sim.trigger_emergency_stop).start())
            else:
                raise ValueError(f"_ursim_row: unknown trigger {trigger!r}")

        def operator(r: Rig):
            def fix():
                if trigger == "trigger_emergency_stop":
                    sim.release_emergency_stop()
                sim.reset()
            return fix
        return _loop_row(w, inject=inject, operator_fix_for=operator, truths=["denim", "silk", "tweed"],
                         arm=arm, expect_outcomes=expect_outcomes, fault_words=fault_words,
                         retries=retries, max_presses=2)


def _need_rtde() -> str:
    try:
        import rtde_control  # noqa: F401
    except ImportError:
        return "skipped: ur_rtde missing"
    return ""


def protective_stop_ursim(w: Path):
    return _ursim_row(w, "overforce_in_descent", {"sorted": 2, "rejected_fault": 1}, "protective")


def emergency_stop_ursim(w: Path):
    return _ursim_row(w, "trigger_emergency_stop", {"sorted": 2, "rejected_fault": 1}, "emergency")


def connection_drop_ursim(w: Path):
    """The controller drops every connection while the arm is in force mode, pressing piece 1
    (refusing new ones for 1 s). The arm must reconnect (URArm's own link recovery, or a new
    worker if the ur_rtde client crashed its process) and the interrupted press must be done
    again (inside the arm, or by the cell's one retry); no fault, all sorted, nothing lost."""
    pytest_skip = _need_rtde()
    if pytest_skip:
        return pytest_skip, ["ur_rtde not installed"]
    from vs2t_edge.sim.ursim_model import CMD_ZERO_FT

    seen: dict = {}
    calls: list[dict] = []  # every press call on the arm: start, end, error, reconnects in its telemetry
    with _ursim_arm() as (sim, arm):
        real_press = arm.press

        def press():
            c = {"start": time.monotonic()}
            calls.append(c)
            try:
                res = real_press()
                c["reconnects"] = (res.telemetry or {}).get("reconnects", 0)
                return res
            except Exception as exc:  # noqa: BLE001 - recorded, raised as the cell sees it
                c["error"] = type(exc).__name__ + ": " + str(exc)[:120]
                raise
            finally:
                c["end"] = time.monotonic()
        arm.press = press

        def drop_in_force_mode() -> None:
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                snap = sim.snapshot()
                if snap["force_mode"] and snap["force_n"] >= 1.0:  # in force mode, the gel on the piece
                    sim.drop_connections()
                    seen.update(at=time.monotonic(), force_n=snap["force_n"], z=snap["pose"][2])
                    return
                time.sleep(0.002)

        def inject(r: Rig) -> None:
            _at(r, 1, 1, lambda: threading.Thread(target=drop_in_force_mode, daemon=True).start())

        words, problems = _loop_row(w, inject=inject, truths=["denim", "silk", "tweed"], arm=arm,
                                    expect_outcomes={"sorted": 3}, fault_words=None, max_presses=2,
                                    holder_out=seen)
        rig = seen["rig"]
        drops = len(sim.get_log().get("drops", []))
        zero_ft = sim.get_log().get("commands", []).count(CMD_ZERO_FT)
    at = seen.get("at")
    _check(problems, drops == 1 and at is not None, f"{drops} drops; the force-mode drop did not fire")
    hit = [c for c in calls if at is not None and c["start"] <= at <= c.get("end", 0.0)]
    _check(problems, len(hit) == 1, f"the drop did not land inside one press call: drop at {at}, calls {calls}")
    c = hit[0] if hit else {}
    restarts = arm.worker_restarts
    inside = "error" not in c and c.get("reconnects", 0) >= 1  # URArm reconnected and pressed again itself
    by_cell = "error" in c and restarts >= 1  # the worker died; the cell retried on a new one
    _check(problems, inside or by_cell,
           f"no reconnect seen for the interrupted press: {c}, worker restarts {restarts}")
    retries = len(seen["audit"]["retries"])
    _check(problems, retries == (1 if by_cell else 0), f"{retries} cell retries (press call {c})")
    # each press starts with zeroFtSensor: the interrupted one shows as one more than the presses done
    _check(problems, zero_ft == rig.arm.press_count + 1,
           f"{zero_ft} presses started for {rig.arm.press_count} done: the interrupted press was not redone")
    how = (f"arm reconnected itself (telemetry reconnects {c.get('reconnects')}) and pressed again" if inside
           else f"worker died ({c.get('error', '')[:60]}), cell retried on a new worker" if by_cell else "no reconnect")
    return words + (f"; link dropped in force mode ({seen.get('force_n', 0):.1f} N); {how}; "
                    f"{zero_ft} presses started for {rig.arm.press_count} done"), problems


def force_never_reached_ursim(w: Path):
    # nothing under the tool for piece 1: force not reached twice -> fault; fabric back, clear
    pytest_skip = _need_rtde()
    if pytest_skip:
        return pytest_skip, ["ur_rtde not installed"]
    with _ursim_arm() as (sim, arm):
        return _loop_row(w, inject=lambda r: _at(r, 1, 1, lambda: sim.set_faults(no_surface=True)),
                         # the operator puts the fabric back; the controller is not reset: the cell
                         # lifted the sensor before latching, so nothing is in the way
                         operator_fix_for=lambda r: (lambda: sim.set_faults(no_surface=False)),
                         truths=["denim", "silk", "tweed"], arm=arm, max_presses=2,
                         expect_outcomes={"sorted": 2, "rejected_fault": 1}, fault_words="twice", retries=1)


# --- pty gate rows (real host driver, MCU simulator on a pty) ---------------------------------

def _gate_row(w: Path, set_fault: Callable[[Any], None], expect_outcomes: dict, fault_words: str | None,
              fix: Callable[[Any], None] | None = None, timeout_s: float = 0.3,
              fired: Callable[[Any, Any], str] | None = None, seed: int = 1,
              exercise: Callable[[Any], None] | None = None):
    """``fired(gate, sim)``: why the injected fault did not happen ("" when it did), so a row
    cannot pass because the line stayed clean. ``exercise(gate)`` runs right after the fault is
    set (more traffic on the faulty line); ``seed`` seeds the line's noise."""
    from vs2t_edge.firmware_bridge.mcu_sim import LineFaults
    from vs2t_edge.runtime.gate import simulated_serial_gate

    faults = LineFaults(seed=seed)
    gate = simulated_serial_gate(faults=faults, timeout_s=timeout_s)
    sim = gate.simulator

    def at_fault() -> None:
        set_fault(sim)
        if exercise is not None:
            exercise(gate)

    def inject(r: Rig):
        _at(r, 1, 1, at_fault)

    words, problems = _loop_row(w, inject=inject, gate=gate, expect_outcomes=expect_outcomes,
                                fault_words=fault_words,
                                operator_fix_for=(lambda r: (lambda: fix(sim))) if fix else None)
    a = audit(w / "journal.jsonl")
    executed = list(sim.executed)
    why = _moves_match_journal(executed, a["finals"])
    _check(problems, not why, why)
    if fired is not None:
        why = fired(gate, sim)
        _check(problems, not why, f"the fault did not fire: {why}")
    return words + f"; gate executed {executed}", problems


def _moves_match_journal(executed: list[int], finals: list[dict]) -> str:
    """The MCU's non-reject moves are exactly the journal's sorted pieces, in order; a piece whose
    outcome is unknown (``unknown_outcome`` with ``maybe_bin``: ack lost, ack contradicted, killed
    after its pre_sort) may account for moves to that bin or to its ``reported_bin`` - none, one,
    or two if the cell retried the sort - and must account for them: a move the journal cannot
    explain is a piece in a bin nobody knows of. Every way of splitting the moves is tried, so an
    unknown piece whose SORT never got out does not swallow the next piece's move to the same bin."""
    moved = [b for b in executed if b != REJECT]
    steps: list[tuple[str, set, int]] = []
    for f in sorted(finals, key=lambda r: r["item"]):
        if f["outcome"] == "sorted" and f["bin"] != REJECT:
            steps.append(("sorted to", {f["bin"]}, f["item"]))
        elif f["outcome"] == "unknown_outcome":
            maybe = {f.get("maybe_bin"), f.get("reported_bin")} - {None, REJECT}
            if maybe:
                steps.append(("maybe in", maybe, f["item"]))
    # every count of moves the journal so far can account for (the matcher's states, no recursion)
    accounted = {0}
    for kind, bins, _item in steps:
        if kind == "sorted to":
            accounted = {j + 1 for j in accounted if j < len(moved) and moved[j] in bins}
        else:
            more = set(accounted)
            for j in accounted:
                while j < len(moved) and moved[j] in bins:
                    j += 1
                    more.add(j)
            accounted = more
    if len(moved) in accounted:
        return ""
    journal = ", ".join(f"item {item} {kind} bin {'/'.join(map(str, sorted(bins)))}" for kind, bins, item in steps)
    return f"gate moved to {moved} (non-reject) but the journal says: {journal or 'nothing sorted'}"


def _retransmitted(gate, sim) -> str:
    n = gate._client.retransmissions
    return "" if n >= 1 else "the host never retransmitted"


NOISE_SEEDS = (1, 2, 3)
NOISE_EXCHANGES = 100  # STATUS + HEARTBEAT pairs per seed on the noisy line, beside the cell's own traffic


def serial_noise(w: Path):
    """7 random bytes (sync bytes included) before every MCU frame, on several seeds and hundreds
    of frames: every frame the MCU sent must come out of the host's parser - none lost. A parser
    that drops a whole false frame (CRC mismatch) swallows the good frame starting inside it; the
    cell would still sort (a retransmission recovers), so only the count shows it. The stream is
    flushed with non-sync bytes at the end, as the next traffic would, so a frame still waiting
    behind an undisproved false start is counted, not lost."""
    from vs2t_edge.firmware_bridge.protocol import MAX_FRAME

    words, problems = [], []
    for seed in NOISE_SEEDS:
        counts: dict = {}

        def exercise(gate) -> None:
            for _ in range(NOISE_EXCHANGES):
                gate.client.status()
                gate.client.heartbeat()

        def fired(gate, sim, counts=counts) -> str:
            reader = gate.client._reader
            reader.feed(bytes(MAX_FRAME))  # the stream goes on: disproves any false start left
            counts.update(sent=sim.tx_frames, parsed=reader.frames, dropped=reader.dropped_bytes)
            if reader.dropped_bytes == 0:
                return "the host dropped no byte"
            if sim.tx_frames < 2 * NOISE_EXCHANGES:
                return f"only {sim.tx_frames} frames on the noisy line"
            return ""

        outcome, probs = _gate_row(w / f"seed{seed}", lambda s: setattr(s.faults, "noise_bytes", 7), {"sorted": 4},
                                   None, fired=fired, seed=seed, exercise=exercise)
        _check(probs, counts.get("parsed") == counts.get("sent"),
               f"the MCU sent {counts.get('sent')} frames, the host parsed {counts.get('parsed')}: "
               f"{(counts.get('sent') or 0) - (counts.get('parsed') or 0)} lost")
        words.append(f"seed {seed}: {outcome.split(';')[0]}, {counts.get('parsed')}/{counts.get('sent')} frames "
                     f"parsed, {counts.get('dropped')} noise bytes dropped")
        problems += [f"seed {seed}: {p}" for p in probs]
    return "; ".join(words), problems


def dropped_ack(w: Path):
    return _gate_row(w, lambda s: setattr(s.faults, "drop_tx", 1), {"sorted": 4}, None,
                     fired=lambda g, s: f"drop_tx left at {s.faults.drop_tx}" if s.faults.drop_tx else _retransmitted(g, s))


def dropped_request(w: Path):
    return _gate_row(w, lambda s: setattr(s.faults, "drop_rx", 1), {"sorted": 4}, None,
                     fired=lambda g, s: f"drop_rx left at {s.faults.drop_rx}" if s.faults.drop_rx else _retransmitted(g, s))


def duplicated_frames(w: Path):
    return _gate_row(w, lambda s: setattr(s.faults, "duplicate_tx", 3), {"sorted": 4}, None,
                     fired=lambda g, s: f"duplicate_tx left at {s.faults.duplicate_tx}" if s.faults.duplicate_tx else "")


def slow_ack_within_timeout(w: Path):
    return _gate_row(w, lambda s: setattr(s.faults, "ack_delay_s", 0.15), {"sorted": 4}, None, timeout_s=0.5,
                     fired=lambda g, s: "" if s.faults.ack_delay_s == 0.15 else "no delay set")


def ack_lost_past_timeout(w: Path):
    """The MCU answers 2 s late, past every retry of a 0.3 s timeout: the flap reached the bin but
    the host never heard. The piece's record must say unknown_outcome with the bin it may be in,
    not claim the reject bin; the operator (the MCU back to speed) clears and the rest are sorted."""
    return _gate_row(w, lambda s: setattr(s.faults, "ack_delay_s", 2.0), {"sorted": 3, "unknown_outcome": 1},
                     "may be in bin", fix=lambda s: setattr(s.faults, "ack_delay_s", 0.0))


def gate_jam(w: Path):
    return _gate_row(w, lambda s: s.jam(True), {"sorted": 3, "rejected_fault": 1}, "jam",
                     fix=lambda s: s.jam(False))


def gate_reboot(w: Path):
    return _gate_row(w, lambda s: s.reboot(), {"sorted": 3, "rejected_fault": 1}, "boot id")


def fault_flood(w: Path):
    """A stuck MCU (or the line) floods FAULT frames mid-run - 5000 JAM reports while the gate in
    fact works: the host keeps only the most recent few (the rest counted) and sorts on the
    honest ACKs."""
    from vs2t_edge.firmware_bridge import protocol as gp
    from vs2t_edge.firmware_bridge.gate_client import FAULT_REPORTS_KEPT

    def flood(sim) -> None:
        report = gp.FaultReport(gp.FAULT_JAM, gp.STATE_FAULT, 3, sim.firmware.boot_id).pack()
        frame = gp.encode_frame(1, gp.FAULT, report)
        for _ in range(20):
            sim.inject_noise(frame * 250)
            time.sleep(0.01)  # the heartbeats read in between, as from a real UART

    seen: dict = {}

    def fired(gate, sim) -> str:
        c = gate.client
        seen.update(kept=len(c.fault_reports), seen=c.fault_reports_seen)
        if c.fault_reports_seen <= 4 * FAULT_REPORTS_KEPT:  # a pty loses what the host does not read in time
            return f"only {c.fault_reports_seen} FAULT frames reached the host: no flood"
        if len(c.fault_reports) != FAULT_REPORTS_KEPT or c.fault_reports_dropped + FAULT_REPORTS_KEPT != seen["seen"]:
            return f"kept {len(c.fault_reports)} of {c.fault_reports_seen} FAULT frames (bound {FAULT_REPORTS_KEPT})"
        return ""

    words, problems = _gate_row(w, flood, {"sorted": 4}, None, fired=fired)
    return words + f"; host kept {seen.get('kept')} of {seen.get('seen')} FAULT frames", problems


# What a lying MCU's ACK of a SORT reports instead of "READY at the bin asked" (LineFaults fields).
ACK_LIES = {
    "another bin": {"lie_bin": 7},
    "jam": {"lie_state": 2, "lie_fault": 2},  # FAULT / JAM, at the bin asked
    "failsafe at reject": {"lie_state": 3, "lie_fault": 1, "lie_bin": 0},  # FAILSAFE / HEARTBEAT_LOST
    "busy": {"lie_state": 1},
}


def ack_contradicts_sort(w: Path):
    """The MCU acknowledges item 2's SORT with the right CRC, SEQ and type, but the ACK reports
    the flap at another bin, or the gate jammed, fail-safe or still moving. The piece must not be
    journalled sorted: a fault latches naming the contradiction, the record says unknown_outcome
    with the bin asked (and the bin reported), and after the operator's clear the rest are sorted."""
    words, problems = [], []
    for name, lie in ACK_LIES.items():
        def set_fault(sim, lie=lie):
            for field_, value in lie.items():
                setattr(sim.faults, field_, value)
            sim.faults.lie_acks = 1

        outcome, probs = _gate_row(w / name.replace(" ", "_"), set_fault, {"sorted": 3, "unknown_outcome": 1},
                                   "contradicts",
                                   fired=lambda g, s: "" if s.lies_told == 1 else f"{s.lies_told} lies told")
        finals = audit(w / name.replace(" ", "_") / "journal.jsonl")["finals"]
        odd = [f for f in finals if f["outcome"] != "sorted"]
        reported = lie.get("lie_bin", BINS["silk"])
        _check(probs, len(odd) == 1 and odd[0].get("maybe_bin") == BINS["silk"]
               and odd[0].get("reported_bin", BINS["silk"]) == reported,
               f"the piece's record does not name the bin asked ({BINS['silk']}) and reported ({reported}): {odd}")
        words.append(f"{name}: {outcome.split(';')[0]}")
        problems += [f"{name}: {p}" for p in probs]
    return "; ".join(words), problems


# --- journal rows ---------------------------------------------------------------------------

def power_loss_mid_write(w: Path):
    """The power goes while the pre_sort record is half written: the restarted cell (a new rig on
    the same state folder, as the service restarts) cuts the torn tail on open and keeps it aside,
    its recovery gives the open item exactly one final record (aborted, reject bin), and it sorts on."""
    from vs2t_edge.runtime.journal import _encode

    w.mkdir(parents=True, exist_ok=True)
    rig = build_rig(w, ["denim", "silk"])
    rig.cell.run(max_items=1)
    rig.cell.journal.close()  # every append was fsynced: what is on disk is what the power cut left
    # piece 2 started, then the power went mid pre_sort write
    line = _encode({"type": "item", "item": 2, "item_id": "piece-0001", "t": 0.0})
    torn = _encode({"type": "pre_sort", "item": 2, "item_id": "piece-0001", "label": "silk", "bin": 2})
    torn_part = torn[: len(torn) // 2]
    with open(rig.journal_path, "ab") as f:
        f.write(line + torn_part)
    good_size = rig.journal_path.stat().st_size - len(torn_part)
    problems: list[str] = []
    rig2 = _reopen_rig(rig.journal_path, ["wool"])  # the restart: same journal, recover() ran
    cut = rig2.cell.journal.torn_bytes
    recovered = [r for r in read_records(rig.journal_path) if r.get("type") == "final"]
    run_rig(rig2)
    a = audit(rig.journal_path, {"piece-0000": "denim", "piece-0001": "silk", "piece-0000b": "wool"})
    problems += a["problems"]
    kept = Path(str(rig.journal_path) + ".torn")
    _check(problems, cut == len(torn_part), f"the restart's journal cut {cut} bytes, the torn tail was {len(torn_part)}")
    _check(problems, kept.exists() and kept.read_bytes() == torn_part,
           f"the torn bytes are not kept aside in {kept.name}")
    data = rig.journal_path.read_bytes()
    _check(problems, data.endswith(b"\n") and len(a["records"]) == data.count(b"\n"),
           "the journal still holds a partial or corrupt line")
    _check(problems, not list(w.glob("run-*")), "the restart opened another journal")
    f2 = [r for r in a["finals"] if r["item"] == 2]
    _check(problems, len(f2) == 1 and f2[0]["outcome"] == "aborted" and f2[0]["bin"] == REJECT,
           f"open item 2 resolved as {f2}")
    _check(problems, [r["item"] for r in recovered] == [1, 2],
           f"the restart's recovery (before any new piece) closed items {[r['item'] for r in recovered]}, wanted [1, 2]")
    wool = [r for r in a["finals"] if r.get("item_id") == "piece-0000b"]
    _check(problems, len(wool) == 1 and wool[0]["item"] == 3 and wool[0]["outcome"] == "sorted",
           f"the piece after the restart: {wool}")
    _check(problems, rig.journal_path.stat().st_size > good_size, "nothing was written after the restart")
    return _outcome_words(a, f"restart cut {cut} torn bytes (kept aside), recovery aborted item 2 once, "
                             "then sorted on"), problems


def _reopen_rig(journal_path: Path, truths: list[str]) -> Rig:
    """The service restarted: a new cell on the same state folder (build_rig's journal.jsonl
    there), so the same journal file is reopened (its torn tail cut) and recover() runs in
    build_rig. Piece ids get a "b" so that they differ from the first run's."""
    rig = build_rig(journal_path.parent, truths)
    for it in rig.pieces.items:
        object.__setattr__(it, "id", it.id + "b")
    return rig


class _DiskFull:
    """os.write / os.fsync for the journal module that fail on the first record of a type once
    armed: ``write`` lands half the bytes, then ENOSPC on every write until ``freed`` (a filling
    disk); ``fsync`` raises EIO once (a dying disk). The journal must cut the half record back."""

    def __init__(self, fail_on_type: str, how: str = "write", real=os) -> None:
        self.fail_on_type, self.how, self.real = fail_on_type, how, real
        self.hit = 0
        self.freed = False
        self.armed = True
        self._full = False
        self._fsync_next = False

    def write(self, fd: int, data: bytes) -> int:
        if self.armed and not self.freed and f'"type":"{self.fail_on_type}"'.encode() in data:
            self.armed = False
            self.hit += 1
            if self.how == "fsync":
                self._fsync_next = True
                return self.real.write(fd, data)
            n = self.real.write(fd, data[: len(data) // 2])
            self._full = True
            return n
        if self._full and not self.freed:
            raise OSError(errno.ENOSPC, "No space left on device (injected)")
        return self.real.write(fd, data)

    def fsync(self, fd: int) -> None:
        if self._fsync_next:
            self._fsync_next = False
            raise OSError(errno.EIO, "Input/output error (injected)")
        return self.real.fsync(fd)


class _OsProxy:
    """What the journal module sees as ``os``: the injected write/fsync, the rest real."""

    def __init__(self, disk: _DiskFull) -> None:
        self._disk = disk

    def __getattr__(self, name):
        return getattr(self._disk, name) if name in ("write", "fsync") else getattr(os, name)


def _journal_clean(path: Path) -> str:
    """'' when the journal ends on a whole record and no torn bytes were ever cut, else why not."""
    torn = Path(str(path) + ".torn")
    data = path.read_bytes()
    if torn.exists():
        return f"{torn.stat().st_size} torn bytes were cut from the journal (a partial record was left)"
    if data and not data.endswith(b"\n"):
        return "the journal ends in a partial record"
    if len(read_records(path)) != data.count(b"\n"):
        return "the journal holds a corrupt line"
    return ""


def disk_failure(w: Path, *, mode: str):
    """The journal's disk fails mid-item (no tmpfs or loop device here without root, so the
    failure is injected into the journal module's ``os``). ``mode``:

    * ``clear``: ENOSPC while writing piece 1's pre_sort record (half the bytes land). The record
      is cut back, a fault latched naming the journal, the gate not moved for that piece. The
      operator's first clear while the disk is still full is refused (latched again); after space
      is freed the clear resolves the open piece (aborted, reject) and the rest are sorted.
    * ``restart``: the same, but the service is stopped while the disk is still full (the stop
      record cannot be written; the stop must not crash); space freed, a restart resolves it.
    * ``fsync_eio``: fsync of piece 1's final record fails with EIO after the gate moved it: cut
      back, fault latched; the clear resolves it as unknown_outcome (the gate may have moved).
    """
    import vs2t_edge.runtime.journal as jmod

    w.mkdir(parents=True, exist_ok=True)
    how = "fsync" if mode == "fsync_eio" else "write"
    disk = _DiskFull("final" if how == "fsync" else "pre_sort", how)
    clears = {"n": 0}

    def operator_fix():
        clears["n"] += 1
        if clears["n"] >= 2 or how == "fsync":
            disk.freed = True  # the operator made space (first try: not yet)

    truths = ["denim", "silk", "wool"]
    rig = build_rig(w, truths, operator_fix=operator_fix if mode != "restart" else None)
    problems: list[str] = []
    crashed = ""
    fault_reason = ""
    real_os = jmod.os

    def arm_on_second():
        disk.armed = True

    disk.armed = False
    _at(rig, 1, 1, arm_on_second)
    jmod.os = _OsProxy(disk)  # only the journal module sees the failing disk
    try:
        if mode == "restart":
            def stop_when():
                nonlocal fault_reason
                if rig.fault_file.exists():
                    fault_reason = rig.fault_file.read_text()
                    return True  # the operator stops the service instead of clearing
                return rig.pieces.exhausted()

            try:
                rig.cell.run(stop_when=stop_when)
                rig.cell.shutdown("SIGTERM")  # stop record fails on the full disk: logged, no crash
            except Exception as exc:  # noqa: BLE001 - that is the measured outcome
                crashed = repr(exc)
        else:
            try:
                run_rig(rig)
            except Exception as exc:  # noqa: BLE001
                crashed = repr(exc)
            fault_reason = rig.operator[0] if rig.operator else ""
    finally:
        jmod.os = real_os
    gate_sorted = list(rig.gate.sorted)
    _check(problems, not crashed, f"the loop crashed: {crashed}")
    _check(problems, disk.hit == 1, f"the failure was injected {disk.hit} times")
    want = "No space left" if how == "write" else "Input/output error"
    _check(problems, "journal write failed" in fault_reason and want in fault_reason,
           f"the latched fault does not name the journal and {want!r}: {fault_reason[:160]!r}")
    why = _journal_clean(rig.journal_path)
    _check(problems, not why, why)
    expect_gate = [BINS["denim"], BINS["silk"]] if how == "fsync" else [BINS["denim"]]
    if mode == "restart":
        _check(problems, gate_sorted == expect_gate, f"gate sorted {gate_sorted}; only piece 0 was decided on disk")
        rig2 = _reopen_rig(rig.journal_path, ["wool"])
        run_rig(rig2)
        truths_by_id = {"piece-0000": "denim", "piece-0001": "silk", "piece-0000b": "wool"}
        expect_finals = 3
    else:
        _check(problems, gate_sorted[: len(expect_gate)] == expect_gate and len(gate_sorted) == 2 + (how == "fsync"),
               f"gate sorted {gate_sorted}")
        truths_by_id = {it.id: it.truth for it in rig.pieces.items}
        expect_finals = 3
        n_clears = 1 if how == "fsync" else 2
        _check(problems, len(rig.operator) == n_clears, f"operator cleared {len(rig.operator)} times, "
                                                        f"expected {n_clears}")
    a = audit(rig.journal_path, truths_by_id)
    problems += a["problems"]
    _check(problems, len(a["finals"]) == expect_finals, f"{len(a['finals'])} finals")
    f2 = [r for r in a["finals"] if r["item"] == 2]
    want_outcome = "unknown_outcome" if how == "fsync" else "aborted"
    _check(problems, len(f2) == 1 and f2[0]["bin"] == REJECT and f2[0]["outcome"] == want_outcome,
           f"the piece whose record failed resolved as {f2}")
    _check(problems, a["outcomes"].get("sorted", 0) == 2, f"outcomes {dict(a['outcomes'])}")
    extra = {"clear": "record cut back, fault latched; clear refused while full, then resolved",
             "restart": "record cut back, fault latched, stopped while full; restart resolved it",
             "fsync_eio": "record cut back after the gate moved, fault latched; clear resolved it"}[mode]
    return _outcome_words(a, f"{extra}; gate sorted {gate_sorted}"), problems


def disk_full(w: Path):
    return disk_failure(w, mode="clear")


def disk_full_restart(w: Path):
    return disk_failure(w, mode="restart")


def fsync_eio(w: Path):
    return disk_failure(w, mode="fsync_eio")


# --- daemon subprocess rows -------------------------------------------------------------------

DAEMON_CONFIG = """\
bundle: bundle
threads: 1
devices:
  camera: {kind: replay, path: frames}
  arm: {kind: fake}
  gate: {kind: fake}
scene:
  reject_bin: 0
  fabrics:
    - {name: denim, kind: touched, bin: 1}
    - {name: silk, kind: touched, bin: 2}
    - {name: wool, kind: untouched, bin: 3}
evidence: {confidence: 0.95, max_presses: 3}
journal: state/journal.jsonl
fault_file: state/FAULT
watchdog: {wait_item_timeout_s: 0.05}
"""


def daemon_child(config: str, score_delay_s: float = 0.03, gate_travel_s: float = 0.08,
                 gate_url: str | None = None) -> int:
    """The real daemon with fake devices and the grey model (``python -m vs2t_edge.sim.faults
    daemon-child CONFIG [GATE_URL]``): signals, journal, recovery are the production code path.
    With ``gate_url`` the gate is the real host driver on that port (an MCU simulator in another
    process, so it outlives this one, as the real gate outlives a killed service)."""
    from vs2t_edge.runtime.arm import FakeArm
    from vs2t_edge.runtime.camera import SimulatedCamera
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.gate import FakeGate

    cfg = load_config(config)

    class Endless(Pieces):
        def next_item(self, timeout_s):
            self.items.append(Item(f"piece-{os.getpid()}-{len(self.items):05d}", TRUTHS[len(self.items) % 4]))
            self.index = len(self.items) - 1
            return self.items[-1]

    class SlowGrey(GreyModel):
        def score_press(self, frame):
            time.sleep(score_delay_s)  # a press takes time: signals land mid-item
            return super().score_press(frame)

    class MovingGate(FakeGate):
        def sort(self, bin_index):
            time.sleep(gate_travel_s)  # the flap takes time to move: a kill lands between pre_sort and ack
            return super().sort(bin_index)

    pieces = Endless([])
    arm = FaultArm(FakeArm(config=cfg.arm), pieces)
    camera = SimulatedCamera(grey_frames(arm, pieces), noise_levels=1.0, seed=0)
    if gate_url:
        from vs2t_edge.runtime.gate import SerialGate

        gate = SerialGate(gate_url, timeout_s=0.3)
    else:
        gate = MovingGate()
    return run_daemon(cfg, model=SlowGrey(), camera=camera, arm=arm, gate=gate, items=pieces,
                      evidence_factory=lambda: GreyEvidence(CLASSES, cfg.confidence, cfg.max_presses),
                      notifier=Notifier(address=""))


def start_daemon(w: Path, gate_url: str | None = None) -> tuple[subprocess.Popen, Path]:
    w.mkdir(parents=True, exist_ok=True)
    cfg = w / "cell.yaml"
    if not cfg.exists():
        cfg.write_text(DAEMON_CONFIG)
        cfg.chmod(0o640)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("NOTIFY_SOCKET", None)
    proc = subprocess.Popen([sys.executable, "-m", "vs2t_edge.sim.faults", "daemon-child", str(cfg),
                             *([gate_url] if gate_url else [])], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, w / "state" / "journal.jsonl"


def wait_for(journal: Path, pred: Callable[[list], bool], limit_s: float = 30.0, poll_s: float = 0.002) -> bool:
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        recs = read_records(journal)
        if recs and pred(recs):
            return True
        time.sleep(poll_s)
    return False


def _stop(proc: subprocess.Popen, sig=signal.SIGTERM) -> tuple[int, str]:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        _out, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        _out, err = proc.communicate()
    return proc.returncode, err


def _daemon_truths(recs: list[dict]) -> dict:
    return {r["item_id"]: TRUTHS[int(r["item_id"].rsplit("-", 1)[1]) % 4]
            for r in recs if r.get("type") == "item"}


def daemon_sigterm(w: Path):
    proc, journal = start_daemon(w)
    try:
        ok = wait_for(journal, lambda rs: sum(r["type"] == "final" for r in rs) >= 3 and rs[-1]["type"] == "item")
    finally:
        code, err = _stop(proc, signal.SIGTERM)
    problems: list[str] = []
    _check(problems, ok, "never saw three items and a fourth started")
    recs = read_records(journal)
    a = audit(journal, _daemon_truths(recs))
    problems += a["problems"]
    _check(problems, code == 0, f"exit code {code}: {err[-300:]}")
    _check(problems, recs[-1].get("type") == "stop" and recs[-1].get("reason") == "SIGTERM",
           f"last record {recs[-1]}")
    _check(problems, a["finals"][-1]["outcome"] == "aborted" and a["finals"][-1]["bin"] == REJECT,
           f"the item in hand ended as {a['finals'][-1]}")
    last_before = max(r["item"] for r in recs if r.get("type") == "item")

    def after_restart(rs: list) -> list:
        starts = [i for i, r in enumerate(rs) if r["type"] == "start"]
        return rs[starts[1] + 1:] if len(starts) >= 2 else []

    proc2, _ = start_daemon(w)  # restart: nothing open, carries on with new numbers
    ok2 = wait_for(journal, lambda rs: sum(r["type"] == "final" and r.get("outcome") == "sorted"
                                           for r in after_restart(rs)) >= 3)
    code2, err2 = _stop(proc2)
    recs2 = read_records(journal)
    a2 = audit(journal, _daemon_truths(recs2))
    problems += a2["problems"]
    _check(problems, code2 == 0, f"restart exit code {code2}: {err2[-300:]}")
    new = after_restart(recs2)
    sorted_new = [r for r in new if r["type"] == "final" and r.get("outcome") == "sorted"]
    _check(problems, ok2 and len(sorted_new) >= 3, f"the restarted daemon sorted {len(sorted_new)} pieces (wanted 3)")
    _check(problems, all(r["item"] > last_before for r in new if "item" in r),
           f"the restart reused item numbers <= {last_before}: {sorted({r['item'] for r in new if 'item' in r})}")
    _check(problems, not [r for r in new if r["type"] == "final" and r["item"] <= last_before],
           "the restart wrote a final record for an item the first run had closed")
    return _outcome_words(a2, f"exit {code}; restart sorted {len(sorted_new)} more (items {last_before + 1}+), "
                              f"exit {code2}"), problems


class GateProcess:
    """The MCU simulator in its own process (``python -m vs2t_edge.firmware_bridge.mcu_sim``): a
    gate that outlives a killed daemon, as the real one does. ``executed`` (the SORT moves it
    made) is known once ``stop()`` has run."""

    def __init__(self, move_ms: int = 80) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "vs2t_edge.firmware_bridge.mcu_sim",
                                      "--move-ms", str(move_ms)],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        first = self.proc.stdout.readline()  # "simulated gate on /dev/pts/N ..."
        if " on " not in first:
            self.proc.kill()
            raise RuntimeError(f"the MCU simulator did not start: {first!r} {self.proc.stderr.read()[-300:]}")
        self.path = first.split(" on ", 1)[1].split()[0]
        self.executed: list[int] | None = None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, _err = self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _err = self.proc.communicate()
        for line in out.splitlines():
            if line.startswith("executed "):
                self.executed = json.loads(line[len("executed "):])

    def __enter__(self) -> "GateProcess":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class Operator:
    """Clears a latched fault as soon as it appears (``vs2t-edge run --clear-fault``), for daemon rows."""

    def __init__(self, w: Path) -> None:
        self.fault_file = w / "state" / "FAULT"
        self.cleared: list[str] = []

    def waiting(self, pred: Callable[[list], bool]) -> Callable[[list], bool]:
        def check(recs: list) -> bool:
            if self.fault_file.exists():
                self.cleared.append(self.fault_file.read_text().strip())
                self.fault_file.unlink()
            return pred(recs)
        return check


def _after_start(recs: list, n: int) -> list:
    """The records after the ``n``-th start record (1-based), [] before it."""
    starts = [i for i, r in enumerate(recs) if r["type"] == "start"]
    return recs[starts[n - 1] + 1:] if len(starts) >= n else []


def _gate_reconciled(problems: list[str], gate: GateProcess, finals: list[dict]) -> str:
    _check(problems, gate.executed is not None, "the MCU simulator did not report its moves")
    executed = gate.executed or []
    why = _moves_match_journal(executed, finals)
    _check(problems, not why, why)
    return f"gate executed {executed}"


def daemon_sigkill(w: Path):
    """kill -9 mid-item (both right after a pre_sort and mid-press, alternately), restart: the open
    item gets exactly one final record (unknown_outcome with the bin it may be in after pre_sort,
    aborted before). The gate is the MCU simulator in its own process, so it outlives each kill as
    the real gate does and its moves must reconcile with the journal: one move per sorted piece, a
    killed sort's move (if the SORT got out) accounted by its unknown_outcome. Once the service
    stays down past the gate's heartbeat timeout: the restart finds the gate fail-safe and latches
    a fault before pressing, which the operator clears."""
    problems: list[str] = []
    seen = Counter()
    operator = Operator(w)
    journal = w / "state" / "journal.jsonl"
    with GateProcess() as gate:
        for round_, after in enumerate(["pre_sort", "item", "pre_sort", "item"]):
            proc, journal = start_daemon(w, gate_url=gate.path)
            starts = sum(r["type"] == "start" for r in read_records(journal))
            ok = wait_for(journal, operator.waiting(
                lambda rs: any(r["type"] == "final" for r in _after_start(rs, starts + 1)) and rs[-1]["type"] == after))
            if proc.poll() is None:
                proc.kill()  # SIGKILL: no handler, no shutdown record, the gate left where it was
            proc.wait(timeout=10)
            recs = read_records(journal)
            open_ = {r["item"] for r in recs if r["type"] == after} - {r["item"] for r in recs if r["type"] == "final"}
            if ok and open_:
                seen[after] += 1
            if round_ == 1:
                time.sleep(1.5)  # down longer than the gate's heartbeat timeout: it fails safe
        proc, journal = start_daemon(w, gate_url=gate.path)
        ok = wait_for(journal, operator.waiting(lambda rs: any(r.get("outcome") == "sorted" for r in _after_start(rs, 5))))
        code, err = _stop(proc)
    recs = read_records(journal)
    a = audit(journal, _daemon_truths(recs))
    problems += a["problems"]
    _check(problems, code == 0, f"final exit {code}: {err[-300:]}")
    _check(problems, ok, "the last restart sorted nothing")
    _check(problems, seen["pre_sort"] >= 1 and seen["item"] >= 1,
           f"kills that left an item open: {dict(seen)} (timing; rerun)")
    o = a["outcomes"]
    _check(problems, o.get("unknown_outcome", 0) == seen["pre_sort"],
           f"{o.get('unknown_outcome', 0)} unknown_outcome for {seen['pre_sort']} kills after pre_sort")
    _check(problems, all(r.get("maybe_bin") is not None for r in a["finals"] if r["outcome"] == "unknown_outcome"),
           "an unknown_outcome record does not name the bin the gate may have moved to")
    at_start = [f for f in a["faults"] if f.startswith("gate latched at start")]
    _check(problems, at_start and len(at_start) == len(a["faults"]),
           f"faults: {a['faults']} (wanted only 'gate latched at start', at least once)")
    _check(problems, len(operator.cleared) == len(a["faults"]), f"operator cleared {len(operator.cleared)} times")
    moves = _gate_reconciled(problems, gate, a["finals"])
    n_sorted = sum(f["outcome"] == "sorted" and f["bin"] != REJECT for f in a["finals"])
    n_killed_moves = sum(b != REJECT for b in gate.executed or []) - n_sorted
    return _outcome_words(a, f"{sum(seen.values())} kills left an item open; {len(at_start)} gate latched at "
                             f"start, cleared; {moves} ({n_killed_moves} made for a killed sort, "
                             "accounted by its unknown_outcome)"), problems


def gate_latched_at_start(w: Path):
    """The service is killed and stays down 1.5 s, past the gate's heartbeat timeout: the gate (its
    own process) fails safe. The restarted daemon must see the latch before pressing a piece - a
    fault record before any item record - and sort again once the operator has cleared it."""
    problems: list[str] = []
    operator = Operator(w)
    with GateProcess() as gate:
        proc, journal = start_daemon(w, gate_url=gate.path)
        ok = wait_for(journal, lambda rs: sum(r.get("outcome") == "sorted" for r in rs) >= 2)
        proc.kill()
        proc.wait(timeout=10)
        time.sleep(1.5)
        proc, journal = start_daemon(w, gate_url=gate.path)
        ok2 = wait_for(journal, lambda rs: any(r["type"] == "fault" for r in _after_start(rs, 2)))
        first_after = [r["type"] for r in _after_start(read_records(journal), 2) if r["type"] in ("fault", "item")][:1]
        ok3 = wait_for(journal, operator.waiting(
            lambda rs: sum(r.get("outcome") == "sorted" for r in _after_start(rs, 2)) >= 2))
        code, err = _stop(proc)
    recs = read_records(journal)
    a = audit(journal, _daemon_truths(recs))
    problems += a["problems"]
    _check(problems, ok and ok2 and ok3, f"never saw: 2 sorted {ok}, a fault after restart {ok2}, "
                                         f"2 sorted after the clear {ok3}")
    _check(problems, first_after == ["fault"], f"after the restart the first of fault/item was {first_after}")
    _check(problems, len(a["faults"]) == 1 and "heartbeat_lost" in a["faults"][0],
           f"expected one fault naming heartbeat_lost, got {a['faults']}")
    _check(problems, len(operator.cleared) == 1, f"operator cleared {len(operator.cleared)} times")
    _check(problems, code == 0, f"exit {code}: {err[-300:]}")
    moves = _gate_reconciled(problems, gate, a["finals"])
    return _outcome_words(a, moves), problems


# --- config rows ----------------------------------------------------------------------------

HOSTILE_CONFIGS = {
    "alias bomb": "a: &a [x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a]\n"
                  "c: &c [*b, *b, *b, *b, *b, *b, *b, *b]\nd: [*c, *c, *c, *c, *c, *c, *c, *c]\n",
    # @MARK@ becomes a file in the row's folder: if any loader ran the tag, the file would exist
    "python object tag": "bundle: !!python/object/apply:os.system ['touch @MARK@; echo pwned']\n",
    "not a mapping": "- 1\n- 2\n",
    "negative confidence": DAEMON_CONFIG.replace("confidence: 0.95", "confidence: -1"),
    "NaN press limit": DAEMON_CONFIG.replace("max_presses: 3", "max_presses: .nan"),
    "reject bin also a fabric bin": DAEMON_CONFIG.replace("bin: 1}", "bin: 0}"),
    "binary junk": "\x00\xff\xfe bundle: [",
    "huge number": DAEMON_CONFIG.replace("max_presses: 3", "max_presses: 1" + "0" * 400),
    # issue 17: a 5 MB file took 73 s and 1.6 GB to reach its error (now refused by size, unread)
    "five megabytes": DAEMON_CONFIG + "".join(f"k{i}: [1, 2, 3]\n" for i in range(400_000)),
    # issue 17: inside the documented 0.05 .. 10 but refused by the gate driver at `run`
    # (traceback, exit 1, restarted by systemd); validation now asks the driver's own rule
    "gate timeout the driver refuses": DAEMON_CONFIG.replace("gate: {kind: fake}",
                                                             "gate: {kind: serial, timeout_s: 0.9}"),
    # issue 17: no ping for 60 s against WatchdogSec=30 (runtime/budget.py)
    "wait for a piece past the watchdog": DAEMON_CONFIG.replace("wait_item_timeout_s: 0.05",
                                                                "wait_item_timeout_s: 60"),
}


def hostile_configs(w: Path):
    """Each hostile config is refused by `vs2t-edge run` with exit 2 and the file named, before any
    device is touched (a real subprocess per config, the real CLI)."""
    w.mkdir(parents=True, exist_ok=True)
    problems: list[str] = []
    codes = {}
    mark = w / "pwned"
    for name, text in HOSTILE_CONFIGS.items():
        path = w / (name.replace(" ", "_") + ".yaml")
        path.write_text(text.replace("@MARK@", str(mark)), encoding="utf-8", errors="surrogateescape")
        path.chmod(0o640)
        t0 = time.monotonic()
        p = subprocess.run([sys.executable, "-m", "vs2t_edge.cli", "run", "--config", str(path)],
                           capture_output=True, text=True, timeout=60)
        codes[name] = p.returncode
        _check(problems, p.returncode == 2, f"{name}: exit {p.returncode} ({p.stderr[-200:]!r})")
        _check(problems, path.name in p.stderr, f"{name}: the error does not name {path.name}")
        _check(problems, "Traceback" not in p.stderr, f"{name}: a traceback instead of words")
        _check(problems, time.monotonic() - t0 < 30, f"{name}: took {time.monotonic() - t0:.0f} s")
        _check(problems, "pwned" not in p.stdout, f"{name}: a tag ran a command (stdout {p.stdout[-80:]!r})")
    _check(problems, not mark.exists(), f"a tag ran a command: {mark} exists")
    return f"{sum(c == 2 for c in codes.values())}/{len(codes)} refused with exit 2, file named", problems


BUNDLE_CONFIG = """\
bundle: bundle
threads: 1
devices:
  camera: {kind: replay, path: frames}
  arm: {kind: fake}
  gate: {kind: fake}
scene:
  reject_bin: 0
  fabrics:
    - {name: f00, kind: touched, bin: 1}
    - {name: f02, kind: touched, bin: 2}
    - {name: f01, kind: untouched, bin: 3}
evidence: {confidence: 0.95, max_presses: 3}
journal: state/journal.jsonl
fault_file: state/FAULT
"""


def good_bundle() -> Path | None:
    """A small real bundle to tamper with: ``VS2T_GOOD_BUNDLE`` or the replay suite's committed one
    (tests/replays/bundle, 2.5 MB; sim never imports torch, so it does not export one itself)."""
    env = os.environ.get("VS2T_GOOD_BUNDLE")
    cand = Path(env) if env else Path(__file__).resolve().parents[1] / "tests" / "replays" / "bundle"
    return cand if (cand / "manifest.json").is_file() else None


def _manifest_edit(fn: Callable[[dict], None], rehash: tuple[str, ...] = (), seal: bool = False
                   ) -> Callable[[Path], None]:
    """Edit manifest.json; ``rehash``: files whose sha256 is updated first, and the manifest
    re-sealed (a change made as the exporter would have made it); ``seal``: re-seal only."""
    def edit(d: Path) -> None:
        from vs2t_edge.runtime.bundle import seal_manifest, sha256_file

        m = json.loads((d / "manifest.json").read_text())
        for name in rehash:
            m["files"][name] = sha256_file(d / name)
        fn(m)
        if rehash or seal:
            m = seal_manifest(m)
        (d / "manifest.json").write_text(json.dumps(m, indent=1))
    return edit


def _flip_byte(name: str) -> Callable[[Path], None]:
    def edit(d: Path) -> None:
        data = bytearray((d / name).read_bytes())
        data[len(data) // 2] ^= 0x40
        (d / name).write_bytes(bytes(data))
    return edit


def _truncate(name: str) -> Callable[[Path], None]:
    def edit(d: Path) -> None:
        data = (d / name).read_bytes()
        (d / name).write_bytes(data[: len(data) // 2])
    return edit


def _old_opset(d: Path) -> None:
    """trunk.onnx re-saved claiming opset 11 (older than this runtime runs), hash and manifest
    updated to match: only the opset check can refuse it."""
    import onnx

    model = onnx.load(str(d / "trunk.onnx"))
    for imp in model.opset_import:
        if imp.domain in ("", "ai.onnx"):
            imp.version = 11
    onnx.save(model, str(d / "trunk.onnx"))

    def declare(m: dict) -> None:
        m["graphs"]["trunk"]["opset"] = 11
    _manifest_edit(declare, rehash=("trunk.onnx",))(d)


def _probe_mismatch(d: Path) -> None:
    """probe_expected.npz no longer what the graphs give (as if trunk.onnx were swapped for another
    export and every hash updated): only the warm-up probe can refuse it."""
    with np.load(d / "probe_expected.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["feature"] = arrays["feature"] * 1.05 + 0.1
    np.savez(d / "probe_expected.npz", **arrays)
    _manifest_edit(lambda m: None, rehash=("probe_expected.npz",))(d)


def _beta_edit(m: dict) -> None:
    m["beta"] = float(m["beta"]) * 0.5


# (case, tamper, words the refusal must contain)
BUNDLE_TAMPERS: list[tuple[str, Callable[[Path], None], tuple[str, ...]]] = [
    ("graph byte flipped", _flip_byte("trunk.onnx"), ("trunk.onnx", "sha256")),
    ("graph truncated", _truncate("heads.onnx"), ("heads.onnx", "sha256")),
    ("router file missing", lambda d: (d / "router.npz").unlink(), ("router.npz", "missing")),
    ("manifest truncated", _truncate("manifest.json"), ("manifest.json", "not valid JSON")),
    ("format version 2", _manifest_edit(lambda m: m.update(format_version=2)), ("format version 2",)),
    ("opset 11 (hash updated)", _old_opset, ("trunk.onnx", "opset 11")),
    ("probe mismatch (hash updated)", _probe_mismatch, ("probe check failed",)),
]
# A hand-edited manifest value, the files' hashes untouched: only the manifest's own seal
# (manifest_sha256) can refuse it. Its own row: it was a known bug until the seal existed.
MANIFEST_EDITS = [("manifest beta edited, hashes untouched", _manifest_edit(_beta_edit),
                   ("manifest.json", "changed after export"))]


class _IdleCamera:
    """The control case reaches READY and stops at once: nothing is grabbed."""

    def connect(self) -> None:
        pass

    def disconnect(self) -> None:
        pass

    def grab(self):
        raise AssertionError("the bundle rows never press")


def _notify_socket():
    import socket

    sock_dir = Path(tempfile.mkdtemp(prefix="vs2t-n-"))  # short path: AF_UNIX names are < 108 bytes
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(str(sock_dir / "notify"))
    server.setblocking(False)
    return server, sock_dir / "notify"


def _drain(server) -> list[str]:
    msgs = []
    while True:
        try:
            msgs.append(server.recv(65536).decode(errors="replace"))
        except (BlockingIOError, OSError):
            return msgs


def _bundle_cell(case: Path, src: Path, tamper: Callable[[Path], None] | None = None):
    """Copy the good bundle to ``case``/bundle (then ``tamper`` it), write the cell.yaml that uses
    it, and load that config."""
    import shutil

    from vs2t_edge.runtime.config import load_config

    shutil.copytree(src, case / "bundle")
    (case / "cell.yaml").write_text(BUNDLE_CONFIG)
    (case / "cell.yaml").chmod(0o640)
    if tamper is not None:
        tamper(case / "bundle")
    return load_config(case / "cell.yaml")


def _run_bundle_daemon(cfg, gate=None) -> tuple[int, bool, str]:
    """The real daemon code (run_daemon) on ``cfg`` with a real sd_notify socket, nothing to sort:
    (exit code, whether it sent READY, what it logged)."""
    import shutil

    from vs2t_edge.runtime.arm import FakeArm
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.gate import FakeGate

    server, sock = _notify_socket()
    logged: list[str] = []
    try:
        code = run_daemon(cfg, camera=_IdleCamera(), arm=FakeArm(), gate=gate if gate is not None else FakeGate(),
                          notifier=Notifier(str(sock)), items=Pieces([]), max_items=0, install_signals=False,
                          log=logged.append)
        msgs = _drain(server)
    finally:
        server.close()
        shutil.rmtree(sock.parent, ignore_errors=True)
    ready = any(m.startswith("READY=1") or "\nREADY=1" in m for m in msgs)
    return code, ready, "\n".join(logged)


def _bundle_case(w: Path, src: Path, name: str, tamper: Callable[[Path], None] | None,
                 words: tuple[str, ...]) -> tuple[str, list[str]]:
    """Copy the good bundle, tamper it, start the real daemon code (run_daemon) on it with a real
    sd_notify socket: exit 2, the refusal names the file, never READY, the journal never opened."""
    import shutil

    case = w / name.split(" (")[0].replace(" ", "_")
    code, ready, text = _run_bundle_daemon(_bundle_cell(case, src, tamper))
    problems: list[str] = []
    journal = case / "state" / "journal.jsonl"
    if tamper is None:  # the control: the same copy untouched starts
        _check(problems, code == 0 and ready, f"untampered copy: exit {code}, READY {ready}: {text[-200:]}")
        return "control starts", problems
    _check(problems, code == 2, f"{name}: exit {code}, expected 2")
    _check(problems, not ready, f"{name}: the daemon sent READY")
    _check(problems, all(wd in text for wd in words), f"{name}: the refusal does not say {words}: {text[-240:]!r}")
    _check(problems, not journal.exists(), f"{name}: the journal was opened (something could have moved)")
    shutil.rmtree(case, ignore_errors=True)
    return _refusal_reason(text, case / "bundle"), problems


def _refusal_reason(text: str, bundle: Path) -> str:
    """The daemon's refusal in words without the temporary paths: 'bundle B refused: bundle B:
    WHY' -> 'WHY' (the row's folder is a fresh /tmp name on every run)."""
    first = text.splitlines()[0] if text else ""
    for prefix in (f"bundle {bundle} refused: ", f"bundle {bundle}: "):
        if first.startswith(prefix):
            first = first[len(prefix):]
    return first.replace(str(bundle), "<bundle>")


def bundle_tampered(w: Path):
    """Each tampered copy of a real bundle is refused by the daemon before anything starts.
    An untampered copy is the control (it must start), and one case goes through the real CLI."""
    src = good_bundle()
    if src is None:
        return "skipped: no bundle to tamper with (tests/replays/bundle absent; set VS2T_GOOD_BUNDLE)", []
    w.mkdir(parents=True, exist_ok=True)
    problems: list[str] = []
    _, p = _bundle_case(w, src, "control", None, ())
    problems += p
    if problems:
        return "the untampered bundle does not start: " + problems[0][:160], problems
    refused = 0
    cases = list(BUNDLE_TAMPERS)
    try:
        import onnx  # noqa: F401 - only to rewrite a graph's opset
    except ImportError:
        cases = [c for c in cases if not c[0].startswith("opset")]
    for name, tamper, words in cases:
        _, p = _bundle_case(w, src, name, tamper, words)
        problems += p
        refused += not p
    # the real CLI, end to end: exit code 2 and words on stderr, no traceback, no READY
    import shutil

    case = w / "cli"
    shutil.copytree(src, case / "bundle")
    (case / "cell.yaml").write_text(BUNDLE_CONFIG)
    (case / "cell.yaml").chmod(0o640)
    _flip_byte("heads.onnx")(case / "bundle")
    server, sock = _notify_socket()
    try:
        env = dict(os.environ, NOTIFY_SOCKET=str(sock))
        proc = subprocess.run([sys.executable, "-m", "vs2t_edge.cli", "run", "--config", str(case / "cell.yaml")],
                              capture_output=True, text=True, timeout=120, env=env)
        msgs = _drain(server)
    finally:
        server.close()
        shutil.rmtree(sock.parent, ignore_errors=True)
    _check(problems, proc.returncode == 2, f"CLI: exit {proc.returncode}")
    _check(problems, "heads.onnx" in proc.stderr and "Traceback" not in proc.stderr,
           f"CLI: stderr {proc.stderr[-240:]!r}")
    _check(problems, not any("READY=1" in m for m in msgs), "CLI: READY sent")
    _check(problems, not (case / "state").exists(), "CLI: state folder created")
    return (f"{refused}/{len(cases)} tampered copies refused (exit 2, file named, no READY, journal never "
            f"opened): {', '.join(c[0] for c in cases)}; CLI exit {proc.returncode}; untampered copy starts"), problems


def bundle_manifest_edited(w: Path):
    """A hand edit of a value in manifest.json (beta halved), the files' hashes untouched."""
    src = good_bundle()
    if src is None:
        return "skipped: no bundle to tamper with (tests/replays/bundle absent; set VS2T_GOOD_BUNDLE)", []
    w.mkdir(parents=True, exist_ok=True)
    name, tamper, words = MANIFEST_EDITS[0]
    outcome, problems = _bundle_case(w, src, name, tamper, words)
    if problems:
        return "NOT refused: the daemon starts on a manifest whose beta was edited (the seal did not catch it)", problems
    _check(problems, bool(outcome) and "/" not in outcome.split(" (")[0], f"the reason is not in words: {outcome!r}")
    return f"refused before READY, exit 2, journal never opened: {outcome[:240]}", problems


def disk_full_at_start(w: Path):
    """The state disk is full when the service starts: the journal cannot take its start record.
    The real daemon code (run_daemon, real bundle, real sd_notify socket) must exit 2 in words,
    never send READY, leave the gate at reject and sort nothing - and start once space is back."""
    import vs2t_edge.runtime.journal as jmod
    from vs2t_edge.runtime.gate import FakeGate

    src = good_bundle()
    if src is None:
        return "skipped: no bundle (tests/replays/bundle absent; set VS2T_GOOD_BUNDLE)", []
    w.mkdir(parents=True, exist_ok=True)
    cfg = _bundle_cell(w, src)
    problems: list[str] = []
    real_append = jmod.Journal.append

    def append(self, rec):
        if rec.get("type") == "start":
            raise jmod.JournalWriteError(f"journal {self.path}: write failed: [Errno 28] No space left on device",
                                         errno.ENOSPC, cut_back=True)
        return real_append(self, rec)

    gate = FakeGate()
    jmod.Journal.append = append  # the disk is full
    try:
        code, ready, text = _run_bundle_daemon(cfg, gate)
    finally:
        jmod.Journal.append = real_append
    outcomes = [f"full: exit {code}, READY {ready}"]
    _check(problems, code == 2, f"disk full: exit {code}, expected 2")
    _check(problems, not ready, "disk full: the daemon sent READY")
    _check(problems, "No space left" in text and "Traceback" not in text,
           f"disk full: the reason is not said in words: {text[-200:]!r}")
    _check(problems, gate.to_reject_calls >= 1 and gate.sorted == [], f"disk full: gate sorted {gate.sorted}")
    code, ready, text = _run_bundle_daemon(cfg)  # space freed
    outcomes.append(f"space freed: exit {code}, READY {ready}")
    _check(problems, code == 0 and ready, f"space freed: exit {code}, READY {ready}: {text[-200:]!r}")
    return "; ".join(outcomes), problems


# --- the matrix -----------------------------------------------------------------------------

@dataclass(frozen=True)
class Scenario:
    name: str
    where: str
    fault: str
    expect: str
    fn: Callable[[Path], tuple[str, list[str]]]
    slow: bool = False
    known_bug: str = ""  # non-empty: the row fails today because of this bug (owner named)


def _inputs_row(name: str, w: Path):
    from vs2t_edge.sim import faults_inputs  # issue 17's input rows, kept in their own module

    return getattr(faults_inputs, name)(w)


SCENARIOS = [
    Scenario("camera_unplugged_and_back", "loop", "camera unplugged mid-press, back for the retry",
             "press retried once, all pieces sorted", camera_unplugged_and_back),
    Scenario("camera_unplugged_for_good", "loop", "camera unplugged mid-press and stays out",
             "retry fails -> fault latched, piece rejected; rest sorted after clear", camera_unplugged_for_good),
    Scenario("camera_frozen", "loop", "frozen camera (same frame repeated)",
             "camera fault latched, piece rejected; rest sorted after clear", camera_frozen),
    Scenario("corrupt_frames", "loop", "one black frame, one truncated frame",
             "refused by the frame guard, press retried, never scored; all sorted", corrupt_frames),
    Scenario("replay_camera_bad_frames", "loop", "ReplayCamera: a corrupt and a missing frame file",
             "each refused naming the file, press retried on the next recorded frame, none scored twice; all sorted",
             replay_camera_bad_frames),
    Scenario("replay_camera_not_sensor_frames", "loop", "ReplayCamera: grey, RGBA, 16-bit, wrong-size, "
             "30000x30000 and FIFO frame files",
             "each refused naming the file and why, before decoding (size) or reading (FIFO); none scored; "
             "all sorted", lambda w: _inputs_row("replay_camera_not_sensor_frames", w)),
    Scenario("watchdog_hung_grab", "loop", "grab hangs to its timeout on a press and its retry (watchdog 1 s)",
             "camera fault latched before the watchdog: pings every < 0.5 s through the waits",
             lambda w: _inputs_row("watchdog_through_hung_grab", w)),
    Scenario("watchdog_gate_behind_heartbeat", "loop", "silent gate: a sort queued behind a heartbeat on the wire, "
             "then a failing gate-to-reject", "each wait within the bound the watchdog budget leases for it",
             lambda w: _inputs_row("watchdog_gate_behind_heartbeat", w)),
    Scenario("camera_covered", "loop", "black frames on a press and its retry",
             "camera fault latched naming 'all black', piece rejected; rest sorted", all_frames_black),
    Scenario("protective_stop", "loop", "protective stop mid-press (FakeArm)",
             "fault latched, piece rejected, resumes after operator clear", protective_stop_fake),
    Scenario("emergency_stop", "loop", "emergency stop mid-press (FakeArm)",
             "fault latched, piece rejected, resumes after operator clear", emergency_stop_fake),
    Scenario("force_not_reached_once", "loop", "force not reached once", "press retried, all sorted",
             force_not_reached_once),
    Scenario("force_never_reached", "loop", "force not reached twice", "fault latched, piece rejected",
             force_never_reached),
    Scenario("arm_connection_lost", "loop", "link lost mid-press, FakeArm really disconnected",
             "reconnect on the next call, press redone from move_above (one retry), all sorted",
             arm_connection_lost_fake),
    Scenario("item_over_time_budget", "loop", "piece exceeds item_timeout_s", "fault latched, piece rejected",
             item_over_time_budget),
    Scenario("ursim_protective_stop", "ursim", "protective stop in the force descent (limit 8 N, UR simulator)",
             "fault latched, piece rejected, resumes after clear", protective_stop_ursim),
    Scenario("ursim_emergency_stop", "ursim", "emergency stop 0.12 s into a press (UR simulator)",
             "fault latched, piece rejected, resumes after release + clear", emergency_stop_ursim),
    Scenario("ursim_connection_drop", "ursim", "controller drops every connection in force mode, gel on the "
             "piece (refused 1 s)", "reconnect, the interrupted press redone, all sorted", connection_drop_ursim),
    Scenario("ursim_force_never_reached", "ursim", "nothing under the tool (force never reached)",
             "retried once, then fault; piece rejected", force_never_reached_ursim),
    Scenario("gate_serial_noise", "pty gate", "7 noise bytes before every MCU frame; 3 seeds, 200+ frames each",
             "every MCU frame parsed by the host (none lost); all sorted, one move each", serial_noise),
    Scenario("gate_dropped_ack", "pty gate", "MCU's ack lost", "retransmitted, sorted once", dropped_ack),
    Scenario("gate_dropped_request", "pty gate", "host's sort frame lost", "retransmitted, sorted once",
             dropped_request),
    Scenario("gate_duplicated_frames", "pty gate", "MCU frames sent twice", "duplicates ignored, sorted once",
             duplicated_frames),
    Scenario("gate_slow_ack", "pty gate", "acks 0.15 s late (timeout 0.5 s)", "all sorted", slow_ack_within_timeout),
    Scenario("gate_ack_lost", "pty gate", "acks 2 s late, past all retries (timeout 0.3 s)",
             "fault latched, piece recorded unknown_outcome with the bin it may be in; resumes after clear",
             ack_lost_past_timeout),
    Scenario("gate_jam", "pty gate", "flap jammed", "fault latched, piece rejected, resumes once freed + cleared",
             gate_jam),
    Scenario("gate_reboot", "pty gate", "MCU reboots mid-run", "fault latched (boot id changed), cleared, resumes",
             gate_reboot),
    Scenario("gate_ack_contradicts", "pty gate", "ACK of a SORT reports another bin / jam / fail-safe / busy "
             "(right CRC, SEQ, type)", "never journalled sorted: fault latched, piece unknown_outcome with the bins "
             "asked and reported; resumes after clear", ack_contradicts_sort),
    Scenario("gate_fault_flood", "pty gate", "5000 FAULT frames (jam) sent mid-run, gate working",
             "host keeps the last 64 and counts the rest; all sorted", fault_flood),
    Scenario("daemon_sigterm", "daemon", "SIGTERM mid-item, restart",
             "item in hand aborted to reject, exit 0, restart carries on", daemon_sigterm),
    Scenario("daemon_sigkill", "daemon", "SIGKILL mid-item (after pre_sort / mid-press) x4, restart; the gate "
             "(MCU simulator, own process) survives, once past its heartbeat timeout",
             "open item resolved once: unknown_outcome (bin it may be in) / aborted; gate moves reconcile with the "
             "journal; a fail-safe gate latched at start and cleared", daemon_sigkill),
    Scenario("gate_latched_at_start", "daemon", "service down 1.5 s (past the gate's heartbeat timeout), restart",
             "fault latched before any piece is pressed, cleared by the operator, sorting resumes; moves reconcile",
             gate_latched_at_start),
    Scenario("power_loss_mid_write", "journal", "power lost mid pre_sort write (torn last line)",
             "torn tail cut and kept aside, open item aborted once", power_loss_mid_write),
    Scenario("disk_full", "journal", "ENOSPC mid pre_sort write (half lands; injected os.write)",
             "partial record cut back, fault latched naming the journal, gate not moved; clear refused while "
             "full, then the piece is aborted once and the rest sorted", disk_full),
    Scenario("disk_full_restart", "journal", "ENOSPC mid pre_sort write, service stopped while full",
             "cut back, no crash on stop; after space freed the restart resolves the piece", disk_full_restart),
    Scenario("disk_full_at_start", "journal", "ENOSPC on the journal's start record (disk full at service start)",
             "exit 2 in words, no READY, gate at reject, nothing sorted; starts once space is freed",
             disk_full_at_start),
    Scenario("fsync_eio", "journal", "EIO from fsync of a final record after the gate moved",
             "cut back, fault latched; the clear resolves the piece as unknown_outcome", fsync_eio),
    Scenario("restart_piece_ids", "daemon", "daemon restarted on its journal (run_daemon's own feed)",
             "piece ids go on (piece-000003 after piece-000002), none twice",
             lambda w: _inputs_row("restart_piece_ids", w)),
    Scenario("hostile_config", "config", "alias bomb, python tag, NaN, junk, 5 MB, a gate timeout the driver "
             "refuses, a piece wait past the watchdog, ...",
             "refused with exit 2 naming the file, no traceback", hostile_configs),
    Scenario("bundle_tampered", "bundle", "graph byte flipped / truncated, file missing, manifest truncated, "
             "format 2, opset 11, probe mismatch",
             "refused before READY, exit 2, file named, journal never opened", bundle_tampered),
    Scenario("bundle_manifest_edited", "bundle", "manifest.json beta edited by hand, hashes untouched",
             "refused before READY, exit 2, manifest.json named", bundle_manifest_edited),
]


def run_scenario(sc: Scenario, workdir: Path | None = None) -> Row:
    row = Row(sc.name, sc.where, sc.fault, sc.expect, known_bug=sc.known_bug)
    own = workdir is None
    tmp = Path(tempfile.mkdtemp(prefix=f"fault-{sc.name}-")) if own else workdir
    t0 = time.monotonic()
    try:
        outcome, problems = sc.fn(tmp)
    except Exception as exc:  # noqa: BLE001 - a crashing scenario is a failed row, in words
        import traceback

        outcome, problems = f"scenario crashed: {exc!r}", [traceback.format_exc(limit=6)]
    row.seconds = time.monotonic() - t0
    row.outcome, row.problems = outcome, problems
    row.passed = not problems and not outcome.startswith("skipped")
    if outcome.startswith("skipped"):
        row.pending = outcome
    if own:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
    return row


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["daemon-child"]:
        return daemon_child(argv[1], gate_url=argv[2] if len(argv) > 2 else None)
    names = set(argv)
    rows = [run_scenario(s) for s in SCENARIOS if not names or s.name in names]
    for r in rows:
        print(f"{r.result} {r.name} ({r.seconds:.1f} s): "
              f"{r.outcome}" + ("".join(f"\n    {p}" for p in r.problems)))
    return 0 if not any(r.blocking for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())

"""The fault matrix's rig: a small cell on fakes, and the audit every row shares.

* the scene - ``Pieces`` (the items), ``FaultArm`` (an arm proxy that knows whether the gel is
  down and fires a scheduled fault just before a given press), ``grey_frames`` (the camera's
  frames from it) - and ``build_rig`` / ``run_rig``: the real loop (runtime/cell.py) on them,
  with an operator who clears a latched fault at once;
* ``audit``: the journal's promises checked for every row (one final per item, nothing sorted on
  a guess, ...), ``_moves_match_journal`` for the gate's moves against the journal, and
  ``_loop_row``: build, inject, run, audit.

The rows themselves are in sim/faults_*.py by boundary; sim/faults.py lists them.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from vs2t_edge.runtime.cell import Cell, SceneSpec
from vs2t_edge.runtime.items import Item
from vs2t_edge.runtime.journal import Journal, read_records
from vs2t_edge.runtime.notify import Notifier
from vs2t_edge.sim.fake_devices import PressTrackingArm
from vs2t_edge.sim.fakes import BINS, CLASSES, GREY, REFERENCE_GREY, REJECT, GreyEvidence, GreyModel


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


class FaultArm(PressTrackingArm):
    """Arm proxy: remembers whether the gel is pressed (for the camera) and fires scheduled faults.

    ``schedule[(item_index, press_number)] = fn``: ``fn()`` runs just before that press (1-based
    per item), so a fault lands mid-press at a known place.
    """

    def __init__(self, inner, pieces: Pieces) -> None:
        super().__init__(inner, lambda: pieces.index)
        self.pieces = pieces
        self.schedule: dict[tuple[int, int], Callable[[], None]] = {}
        self.press_count = 0  # presses the arm finished

    def before_press(self, item: int, number: int) -> None:
        fn = self.schedule.pop((item, number), None)
        if fn is not None:
            fn()

    def press(self):
        result = super().press()
        self.press_count += 1
        return result


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
    from vs2t_edge.sim.fake_devices import FakeArm, FakeGate
    from vs2t_edge.sim.devices import SimulatedCamera
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


def _at(rig: Rig, item: int, press: int, fn: Callable[[], None]) -> None:
    rig.arm.schedule[(item, press)] = fn


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

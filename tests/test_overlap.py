"""Overlapped scoring (runtime/press_pipeline.py): a press is scored while the arm moves on.

The arm and the model here take real time (sleeps), since the overlap is two threads: a timed
FakeArm (``press_s`` per press, ``lift_s`` per retract) and a FakeModel that sleeps ``score_s``
per press. The same item is run with ``overlap_scoring`` on and off and compared: the decision and
the journal are the sequential ones (and, when a late score decides, one speculative press that is
journalled and never scored into the decision).

That the model's time is hidden is shown by order, not by a stopwatch: a rendezvous (``Meeting``)
lets the arm or the model wait, with a long timeout, for the other side to reach a point, and notes
whether it did. Overlapped, the other side gets there while the first waits; sequentially it cannot,
since it only runs after. The time this buys is the bench's to measure (runtime/sorting.py
``items_per_minute``), not a unit test's.
"""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import pytest

from cell_fakes import FakeEvidence, FakeModel, ScriptedCamera
from vs2t_edge.runtime.cell import Cell, SceneSpec
from vs2t_edge.runtime.devices import ArmConnectionError
from vs2t_edge.runtime.items import ContinuousFeed
from vs2t_edge.runtime.journal import Journal, read_records
from vs2t_edge.runtime.notify import Notifier
from vs2t_edge.runtime.preprocess import FrameError
from vs2t_edge.sim.fake_devices import FakeArm, FakeGate

CLASSES = ["denim", "silk", "wool"]
BINS = {"denim": 1, "silk": 2, "wool": 3}
VOTES = {50: "denim", 60: "silk", 70: "wool"}
AMBIGUOUS = [50, 60, 70, 50, 60, 70]  # never confident: the item goes to the press limit


class TimedArm(FakeArm):
    """A FakeArm whose press and lift take time; it notes when each press starts."""

    press_s = 0.0
    lift_s = 0.0

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.press_started: list[float] = []

    def press(self):
        self.press_started.append(time.monotonic())
        time.sleep(self.press_s)
        return super().press()

    def retract(self):
        time.sleep(self.lift_s)
        super().retract()


class Meeting:
    """A count that one thread raises and another waits on: ``wait_for(n)`` is True when the count
    reached ``n`` within ``timeout_s``. A long timeout cannot fail a slow machine that overlaps; a
    sequential loop never raises the count while the other side waits, so it is False there."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s, self.count = timeout_s, 0
        self._cond = threading.Condition()

    def arrive(self) -> None:
        with self._cond:
            self.count += 1
            self._cond.notify_all()

    def wait_for(self, n: int) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: self.count >= n, timeout=self.timeout_s)


class SlowModel(FakeModel):
    """FakeModel that takes ``score_s`` per press; ``fail_at`` (1-based call) raises ``error``."""

    def __init__(self, score_s, fail_at=None, error=None, on_score=None):
        super().__init__(VOTES, CLASSES)
        self.score_s, self.fail_at, self.error, self.on_score = score_s, fail_at, error, on_score
        self.calls = 0
        self.threads: set[str] = set()

    def score_press(self, frame):
        self.calls += 1
        self.threads.add(threading.current_thread().name)
        if self.on_score is not None:
            self.on_score(self.calls)
        time.sleep(self.score_s)
        if self.calls == self.fail_at:
            raise self.error
        return super().score_press(frame)


def make(tmp_path, script, *, overlap, press_s=0.0, lift_s=0.0, score_s=0.0, max_presses=4, confidence=0.95,
         model=None, name="cell"):
    folder = tmp_path / f"{name}-{'on' if overlap else 'off'}"
    folder.mkdir()
    arm = TimedArm()
    arm.press_s, arm.lift_s = press_s, lift_s
    arm.connect()
    camera = ScriptedCamera(arm, script)
    journal = Journal.open(folder / "journal.jsonl")
    gate = FakeGate()
    gate.connect()
    scene = SceneSpec(bins=dict(BINS), reject_bin=0, points_mm=arm.config.grid_points_mm()[:20],
                      max_presses=max_presses, confidence=confidence, fault_file=folder / "FAULT",
                      wait_item_timeout_s=0.01, overlap_scoring=overlap)
    cell = Cell(camera=camera, arm=arm, gate=gate, model=model or SlowModel(score_s), journal=journal,
                notifier=Notifier(address=""), scene=scene,
                evidence_factory=lambda: FakeEvidence(CLASSES, confidence, max_presses),
                items=ContinuousFeed(), sleep=lambda s: None)
    return cell


def records(cell):
    """The journal without its wall-clock times and where its fault file is (each cell's own folder)."""
    return [{k: v for k, v in r.items() if k not in ("t", "fault_file")} for r in read_records(cell.journal.path)]


def timed_run(cell, max_items=1):
    t0 = time.monotonic()
    results = cell.run(max_items=max_items, stop_when=lambda: cell.fault is not None)  # latched: no hang
    return results, time.monotonic() - t0


def test_a_slow_model_does_not_slow_the_arm(tmp_path):
    # each score (but the last) waits until the arm has begun the next press: overlapped, the arm
    # presses on while the model works; sequentially it waits for the score, so the next press
    # never begins during it
    n = 4  # AMBIGUOUS goes to the press limit

    class WaitsForTheNextPress(SlowModel):
        def __init__(self, arm_moved: Meeting):
            super().__init__(0.0)
            self.arm_moved, self.next_press_began = arm_moved, []

        def score_press(self, frame):
            k = self.calls + 1
            if k < n:
                self.next_press_began.append(self.arm_moved.wait_for(k + 1))
            return super().score_press(frame)

    def run(overlap, timeout_s):
        arm_moved = Meeting(timeout_s)
        cell = make(tmp_path, AMBIGUOUS, overlap=overlap, model=WaitsForTheNextPress(arm_moved))
        press = cell.arm.press

        def counted_press():
            arm_moved.arrive()
            return press()

        cell.arm.press = counted_press
        return cell, timed_run(cell)[0]

    on, r_on = run(True, timeout_s=5.0)
    off, r_off = run(False, timeout_s=0.05)
    assert r_on[0].presses == r_off[0].presses == n and r_on[0].label == r_off[0].label == "unknown"
    assert on.model.next_press_began == [True] * (n - 1)  # the arm never waited for a score
    assert off.model.next_press_began == [False] * (n - 1)  # the test can tell the two apart
    assert on.model.threads == {t for t in on.model.threads if t.startswith("score-press")}
    assert records(on) == records(off)  # same scores, same order, same decision


def test_a_late_deciding_score_makes_one_speculative_press_that_is_journalled_and_never_scored(tmp_path):
    # two silk presses decide (p = 0.995); the model is slower than the lift, so the arm is
    # already pressing point 2 when the second score comes in
    on = make(tmp_path, [60] * 6, overlap=True, press_s=0.05, score_s=0.15)
    off = make(tmp_path, [60] * 6, overlap=False, press_s=0.05, score_s=0.15)
    r_on, _ = timed_run(on)
    r_off, _ = timed_run(off)
    assert (r_on[0].label, r_on[0].presses, r_on[0].bin) == (r_off[0].label, r_off[0].presses, r_off[0].bin) \
        == ("silk", 2, 2)
    assert on.arm.calls.count("press") == 3 and off.arm.calls.count("press") == 2
    pre_on = [r for r in records(on) if r["type"] == "pre_sort"][0]
    pre_off = [r for r in records(off) if r["type"] == "pre_sort"][0]
    assert pre_on.pop("speculative_presses") == 1 and "speculative_presses" not in pre_off
    assert pre_on == pre_off  # the speculative frame is in no score and no posterior
    assert [s["point"] for s in pre_on["scores"]] == [0, 1]
    assert on.gate.sorted == off.gate.sorted == [2]
    assert on.scorer._running == []  # the speculative score ended with the item


def test_a_score_ready_when_the_gel_is_up_changes_no_device_call(tmp_path):
    # the model (10 ms) is quicker than the lift (80 ms): the decision is in before the arm moves
    # on, so the arm's calls are exactly the sequential loop's, over several items
    script = [60, 60, 70, 70, 50, 60, 70, 50]

    def run(overlap, timeout_s):
        # each lift waits until its press's score has begun: overlapped, the score runs during the
        # lift; sequentially it runs after the lift, so it never begins during one
        score_began = Meeting(timeout_s)
        cell = make(tmp_path, script, overlap=overlap, lift_s=0.08, score_s=0.01)
        score, retract = cell.model.score_press, cell.arm.retract
        lifts = []

        def counted_score(frame):
            score_began.arrive()
            return score(frame)

        def watching_retract():
            lifts.append(score_began.wait_for(len(lifts) + 1))
            retract()

        cell.model.score_press, cell.arm.retract = counted_score, watching_retract
        return cell, timed_run(cell, max_items=3)[0], lifts

    on, r_on, lifts_on = run(True, timeout_s=5.0)
    off, r_off, lifts_off = run(False, timeout_s=0.05)
    assert on.arm.calls == off.arm.calls
    assert records(on) == records(off)
    assert [r.label for r in r_on] == [r.label for r in r_off]
    assert on.arm.calls.count("retract") == on.model.calls == len(lifts_on) > 3  # one lift per scored press
    assert lifts_on == [True] * len(lifts_on)  # each press's scoring hidden behind its lift
    assert lifts_off == [False] * len(lifts_off)


def test_a_model_error_while_overlapped_latches_cleanly_with_nothing_lost(tmp_path):
    on = make(tmp_path, AMBIGUOUS, overlap=True, press_s=0.05,
              model=SlowModel(0.1, fail_at=2, error=RuntimeError("onnxruntime: session failed")))
    off = make(tmp_path, AMBIGUOUS, overlap=False, press_s=0.05,
               model=SlowModel(0.1, fail_at=2, error=RuntimeError("onnxruntime: session failed")))
    r_on, _ = timed_run(on)
    r_off, _ = timed_run(off)
    for cell, r in ((on, r_on), (off, r_off)):
        assert r[0].outcome == "rejected_fault" and r[0].bin == 0
        assert cell.fault and "RuntimeError: onnxruntime: session failed" in cell.fault
        assert cell.gate.to_reject_calls >= 1 and "stop" in cell.arm.calls
        recs = records(cell)
        assert [x["type"] for x in recs] == ["item", "fault", "final"]  # no pre_sort: the gate was never told
        assert recs[-1]["outcome"] == "rejected_fault" and recs[-1]["presses"] == 1
        assert cell.arm.calls[-2:] == ["retract", "stop"]  # gel lifted, then the arm stopped
    assert records(on) == records(off)
    assert on.scorer._running == []  # no score left running after the item


def test_a_frame_error_in_overlapped_scoring_is_skipped_as_before(tmp_path):
    class FailsOn13(SlowModel):
        def score_press(self, frame):
            if int(frame[..., 0].mean()) == 13:
                time.sleep(self.score_s)
                raise FrameError("non-finite model output", "model_output")
            return super().score_press(frame)

    on = make(tmp_path, [13, 70, 70, 70], overlap=True, press_s=0.05, model=FailsOn13(0.1))
    off = make(tmp_path, [13, 70, 70, 70], overlap=False, press_s=0.05, model=FailsOn13(0.1))
    r_on, _ = timed_run(on)
    r_off, _ = timed_run(off)
    assert (r_on[0].label, r_on[0].skipped_frames, r_on[0].presses) == ("wool", 1, 2)
    assert (r_off[0].label, r_off[0].skipped_frames, r_off[0].presses) == ("wool", 1, 2)
    assert not on.fault
    recs = records(on)
    assert [x["type"] for x in recs] == ["item", "frame_skipped", "pre_sort", "final"]
    assert recs[1]["point"] == 0 and recs[1]["reason"] == "model_output"
    pre = recs[2]
    assert pre.pop("speculative_presses") == 1  # the decision came in while point 3 was pressed
    assert pre == records(off)[2]


def test_a_stop_while_a_score_is_running_aborts_the_item_cleanly(tmp_path):
    holder = {}

    def stop_on_second(calls):
        if calls == 2:
            holder["cell"].stop_event.set()  # SIGTERM while press 1 is being scored

    on = make(tmp_path, AMBIGUOUS, overlap=True, press_s=0.05, model=SlowModel(0.1, on_score=stop_on_second))
    holder["cell"] = on
    results = on.run(max_items=1)
    assert results == [] or results[0].outcome == "aborted"
    recs = records(on)
    assert [x["type"] for x in recs] == ["item", "final"]
    assert recs[-1]["outcome"] == "aborted" and recs[-1]["bin"] == 0
    assert on.gate.to_reject_calls >= 1 and on.arm.calls[-1] == "retract"
    assert not on.fault
    assert on.scorer._running == []


def test_overlap_scoring_is_a_config_key_default_on_and_replay_runs_it_off(tmp_path):
    from vs2t_edge.runtime.config import ConfigError, load_config
    from vs2t_edge.runtime.replay import config_for_replay

    base = ("bundle: bundle\ndevices:\n  camera: {kind: sim, path: data}\n  arm: {kind: fake}\n"
            "  gate: {kind: fake}\nscene:\n  fabrics:\n    - {name: denim, kind: touched, bin: 1}\n"
            "journal: state/journal.jsonl\n")
    (tmp_path / "a.yaml").write_text(base)
    cfg = load_config(tmp_path / "a.yaml")
    assert cfg.overlap_scoring is True and SceneSpec.from_config(cfg).overlap_scoring is True
    (tmp_path / "b.yaml").write_text(base + "cell: {overlap_scoring: false}\n")
    assert SceneSpec.from_config(load_config(tmp_path / "b.yaml")).overlap_scoring is False
    (tmp_path / "c.yaml").write_text(base + "cell:\n  overlap_scoring: 'no'\n")
    with pytest.raises(ConfigError) as err:
        load_config(tmp_path / "c.yaml")
    assert "c.yaml:11: cell.overlap_scoring = 'no': must be true or false" in str(err.value)
    import yaml

    rf = SimpleNamespace(index={"config": yaml.safe_load(base), "meta": {}})
    work = tmp_path / "replay"
    work.mkdir()
    assert config_for_replay(rf, work, None).overlap_scoring is False


def test_a_session_recorded_overlapped_with_speculative_presses_replays(tmp_path):
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.recording import record_session
    from vs2t_edge.runtime.replay import ReplayFile, run_replay

    (tmp_path / "cell.yaml").write_text(
        "bundle: bundle\ndevices:\n  camera: {kind: replay, path: x}\n  arm: {kind: fake}\n  gate: {kind: fake}\n"
        "scene:\n  fabrics:\n    - {name: denim, kind: touched, bin: 1}\n    - {name: silk, kind: touched, bin: 2}\n"
        "    - {name: wool, kind: untouched, bin: 3}\nevidence: {confidence: 0.95, max_presses: 4}\n"
        "journal: j.jsonl\n")  # cell.overlap_scoring: the default, on
    cfg = load_config(tmp_path / "cell.yaml")
    assert cfg.overlap_scoring
    arm = FakeArm(config=cfg.arm)
    evidence = lambda: FakeEvidence(CLASSES, 0.95, 4)  # noqa: E731
    # every press votes silk, so the pieces do not depend on which frame a speculative press took;
    # the instant FakeArm is up before the 30 ms score: each decision comes in during the next press
    out = record_session(cfg, tmp_path / "s.replay", model=SlowModel(0.03), camera=ScriptedCamera(arm, [60] * 40),
                         arm=arm, gate=FakeGate(), items=ContinuousFeed(limit=3), evidence_factory=evidence,
                         operator_clear=lambda: True)
    decisions = ReplayFile.open(out).index["decisions"]
    assert [d["label"] for d in decisions if d["type"] == "final"] == ["silk"] * 3
    assert [d["presses"] for d in decisions if d["type"] == "pre_sort"] == [2] * 3
    presses = [e for e in ReplayFile.open(out).index["events"] if e["dev"] == "arm" and e["call"] == "press"]
    assert len(presses) == 3 * 3  # two scored and one speculative per piece
    report = run_replay(out, model=SlowModel(0.0), evidence_factory=evidence)  # replayed sequentially
    assert report.ok, report.mismatches + [report.diverged]


class HeldModel(SlowModel):
    """Overlapped, the score of call ``hold_call`` is held until ``release`` is set (the camera's
    first error): the deciding score is certainly still out while the next press fails. A frame of
    grey level 13 is one the model cannot score (FrameError)."""

    def __init__(self, hold_call=None):
        super().__init__(0.0)
        self.hold_call, self.release = hold_call, threading.Event()

    def score_press(self, frame):
        if self.calls + 1 == self.hold_call:
            assert self.release.wait(10), "the camera never failed"
        if int(frame[..., 0].mean()) == 13:
            self.calls += 1
            raise FrameError("non-finite model output", "model_output")
        return super().score_press(frame)


class ReleasingCamera(ScriptedCamera):
    """A ScriptedCamera that sets ``release`` when a grab fails."""

    release: threading.Event | None = None

    def grab(self):
        try:
            return super().grab()
        except Exception:
            if self.release is not None:
                self.release.set()
            raise


def _held_pair(tmp_path, script, hold_call):
    cells = []
    for overlap in (False, True):
        model = HeldModel(hold_call if overlap else None)
        cell = make(tmp_path, script, overlap=overlap, model=model)
        camera = ReleasingCamera(cell.arm, script)
        camera.release = model.release
        camera.connect()
        cell.camera = camera
        cells.append(cell)
    return cells


def _comparable(cell):
    return [{k: v for k, v in r.items() if k not in ("speculative_presses", "speculative_error")}
            for r in records(cell)]


def test_a_speculative_press_that_fails_twice_does_not_fault_a_piece_already_decided(tmp_path):
    # two silk presses decide; the second score is held until the camera fails on the next press,
    # which the overlapped arm made while that score was out - and whose retry fails too. The
    # sequential loop never made that press: the piece goes to silk's bin, so it must here too.
    off, on = _held_pair(tmp_path, [60, 60, "error", "error", 60, 60], hold_call=2)
    r_off, _ = timed_run(off)
    r_on, _ = timed_run(on)
    assert (r_off[0].label, r_off[0].outcome, r_off[0].bin) == ("silk", "sorted", 2)
    assert (r_on[0].label, r_on[0].outcome, r_on[0].bin) == ("silk", "sorted", 2)
    assert not on.fault and not on.scene.fault_file.exists()
    assert _comparable(on) == _comparable(off)  # no retry, no fault: the press never mattered
    pre = [r for r in records(on) if r["type"] == "pre_sort"][0]
    assert pre["speculative_presses"] == 1 and "no frame (injected)" in pre["speculative_error"]
    assert on.gate.sorted == [2] and on.arm.calls[-1] == "retract"  # the gel is up before the sort


def test_a_retry_comes_after_the_late_scores_records_as_sequentially(tmp_path):
    # press 1's frame cannot be scored (frame_skipped) and its score is held until press 2's camera
    # fault: sequentially frame_skipped (point 1) comes before press 2's retry, and so it must here
    off, on = _held_pair(tmp_path, [60, 13, "error", 60, 60, 60], hold_call=2)
    r_off, _ = timed_run(off)
    r_on, _ = timed_run(on)
    types = [r["type"] for r in records(off)]
    assert types == ["item", "frame_skipped", "retry", "pre_sort", "final"], types
    assert _comparable(on) == _comparable(off)
    assert (r_on[0].label, r_on[0].presses, r_on[0].skipped_frames) == (r_off[0].label, r_off[0].presses, 1)


def test_overlapped_and_sequential_journals_agree_under_camera_errors_and_bad_frames(tmp_path):
    """The seeded randomised comparison (runtime/press_pipeline.py's promise): for random scripts of
    votes, unscorable frames and camera errors, random model and lift times, and random press limits
    and confidences, the overlapped item's journal is the sequential one's record for record (the
    speculative press's own keys aside) and it never presses more than one press beyond it."""
    import random

    class RandomTimes(SlowModel):
        def __init__(self, rng):
            super().__init__(0.0)
            self.rng = rng

        def score_press(self, frame):
            time.sleep(self.rng.choice([0, 0, 0.002, 0.008]))
            if int(frame[..., 0].mean()) == 13:
                raise FrameError("non-finite model output", "model_output")
            return super().score_press(frame)

    for trial in range(40):
        rng = random.Random(trial)
        script = [rng.choice([50, 60, 70, 60, 13, "error"]) for _ in range(14)]
        max_presses, confidence = rng.randint(1, 5), rng.choice([0.6, 0.9, 0.99])
        runs = []
        for overlap in (False, True):
            cell = make(tmp_path, script, overlap=overlap, max_presses=max_presses, confidence=confidence,
                        lift_s=rng.choice([0, 0.001, 0.004]), model=RandomTimes(random.Random(trial)),
                        name=f"t{trial}")
            results, _ = timed_run(cell)
            runs.append((cell, results))
        (off, r_off), (on, r_on) = runs
        where = f"trial {trial}: script {script}, max_presses {max_presses}, confidence {confidence}"
        assert _comparable(on) == _comparable(off), where
        assert [(r.label, r.bin, r.outcome) for r in r_on] == [(r.label, r.bin, r.outcome) for r in r_off], where
        assert bool(on.fault) == bool(off.fault), where
        p_off, p_on = off.arm.calls.count("press"), on.arm.calls.count("press")
        assert p_off <= p_on <= p_off + 1, where


class _StuckLiftArm(TimedArm):
    """The lift after press ``stuck_at`` fails, and so does the next one (the link stays down a few
    ms); it tracks whether the gel is down and what it was when the gate sorted."""

    stuck_at = 3

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.down, self.presses, self.failing = False, 0, 0

    def press(self):
        result = super().press()
        self.presses += 1
        self.down = True
        if self.presses == self.stuck_at:
            self.failing = 2
        return result

    def retract(self):
        self.calls.append("retract")
        if self.failing:
            self.failing -= 1
            raise ArmConnectionError("link lost during retract", device="arm", kind="connection_lost")
        self.down = False


class _GelGate(FakeGate):
    def __init__(self, arm):
        super().__init__()
        self.arm, self.gel_at_sort = arm, []

    def sort(self, bin_):
        self.gel_at_sort.append("down" if self.arm.down else "up")
        return super().sort(bin_)


def test_a_speculative_press_whose_gel_will_not_lift_latches_a_fault_and_the_gate_never_moves_under_it(tmp_path):
    # score 2 decides silk, held until the arm has made press 3 (speculative); press 3's lift fails
    # twice. Sequentially press 3 is never made; overlapped, the gate must not sort with the gel down.
    cell = make(tmp_path, [60, 60, 60, 60], overlap=True)
    arm = _StuckLiftArm()
    arm.connect()
    cell.arm, cell.gate = arm, _GelGate(arm)
    cell.gate.connect()
    cell.camera = ScriptedCamera(arm, [60, 60, 60, 60])
    cell.camera.connect()

    def hold(call):
        if call == 2:
            deadline = time.monotonic() + 5
            while arm.presses < 3 and time.monotonic() < deadline:
                time.sleep(0.001)
            time.sleep(0.01)
    cell.model = SlowModel(0.0, on_score=hold)
    results, _ = timed_run(cell)
    assert "down" not in cell.gate.gel_at_sort
    assert cell.fault and "could not lift" in cell.fault
    assert (results[0].label, results[0].bin, results[0].outcome) == ("unknown", 0, "rejected_fault")

"""Record a session of the cell (fake devices, scripted model), replay it through the daemon.

The replays with the real bundle and the simulated cell are in tests/test_replay_sessions.py;
these check the machinery itself: identical decisions on a faithful replay, a mismatch caught
when the model changes, --update-refs, divergence, and a fault mid-item with the operator's
clear played back.
"""

from __future__ import annotations

import json

import pytest

from cell_fakes import LOOP_CONFIG, FakeEvidence, FakeModel, ScriptedCamera, latch_skipping
from vs2t_edge.sim.fake_devices import FakeArm
from vs2t_edge.runtime.items import ContinuousFeed
from vs2t_edge.runtime.config import load_config
from vs2t_edge.sim.fake_devices import FakeGate
from vs2t_edge.runtime.recording import record_session
from vs2t_edge.runtime.replay import ReplayError, ReplayFile, compare, run_replay


# overlap_scoring off: the ScriptedCamera hands out one script across items, so a speculative
# press (an instant FakeArm is always quicker than the model) would take the next item's frame
# here. A recording made overlapped is replayed in tests/test_overlap.py.
CONFIG = LOOP_CONFIG + "cell: {overlap_scoring: false}\n"
CLASSES = ["denim", "silk", "wool"]
VOTES = {50: "denim", 60: "silk", 70: "wool"}


def model(strength=3.0):
    return FakeModel(VOTES, CLASSES, strength=strength)


def evidence():
    return FakeEvidence(CLASSES, 0.95, 4)


def record(tmp_path, script, n_items, fail_next=(), clear=True):
    (tmp_path / "cell.yaml").write_text(CONFIG)
    cfg = load_config(tmp_path / "cell.yaml")
    arm = FakeArm(config=cfg.arm)
    cam = ScriptedCamera(arm, script)
    clears = []

    def operator_clear():
        arm.latched = ""  # the operator released the stop
        clears.append(1)
        return clear

    arm.fail_next = list(fail_next)
    out = record_session(cfg, tmp_path / "s.replay", model=model(), camera=cam, arm=arm, gate=FakeGate(),
                         items=ContinuousFeed(limit=n_items), evidence_factory=evidence,
                         operator_clear=operator_clear)
    return out, clears


def test_faithful_replay_reproduces_every_decision(tmp_path):
    out, _ = record(tmp_path, [50, 50, 60, 100, 100, 100, 60, 60, "black", 70, 70], 4)
    rf = ReplayFile.open(out)
    finals = [d for d in rf.index["decisions"] if d["type"] == "final"]
    assert [d["label"] for d in finals] == ["denim", "unknown", "silk", "wool"]
    assert len(list((out / "frames").glob("*.png"))) == sum(1 for e in rf.index["events"] if e.get("frame"))
    report = run_replay(out, model=model(), evidence_factory=evidence)
    assert report.ok, report.mismatches + [report.diverged]


def test_changed_model_is_caught_and_update_refs_accepts_it(tmp_path):
    out, _ = record(tmp_path, [50, 50, 60, 60], 2)
    report = run_replay(out, model=model(strength=3.5), evidence_factory=evidence)
    assert not report.ok and any("log_posterior" in m for m in report.mismatches)
    before = json.loads((out / "index.json").read_text())["events"]
    run_replay(out, model=model(strength=3.5), evidence_factory=evidence, update_refs=True)
    assert json.loads((out / "index.json").read_text())["events"] == before  # only references change
    assert run_replay(out, model=model(strength=3.5), evidence_factory=evidence).ok


def test_a_model_that_needs_more_presses_diverges(tmp_path):
    out, _ = record(tmp_path, [50, 50, 60, 60], 2)
    report = run_replay(out, model=model(strength=1.0), evidence_factory=evidence)
    assert report.diverged and "no more" in report.diverged


def test_fault_mid_item_with_operator_clear_replays(tmp_path):
    # first item: protective stop at its first move -> latched; the operator clears; two more items
    out, clears = record(tmp_path, [50, 50, 60, 60, 70, 70], 3, fail_next=["protective_stop"])
    rf = ReplayFile.open(out)
    types = [d["type"] for d in rf.index["decisions"]]
    assert "fault" in types and "fault_cleared" in types and clears
    finals = [d for d in rf.index["decisions"] if d["type"] == "final"]
    assert finals[0]["outcome"] == "rejected_fault" and finals[0]["bin"] == 0
    assert any(e["dev"] == "arm" and e.get("error", {}).get("type") == "ArmSafetyStop" for e in rf.index["events"])
    report = run_replay(out, model=model(), evidence_factory=evidence)
    assert report.ok, report.mismatches + [report.diverged]


def test_compare_is_exact_on_decisions_and_tolerant_on_scores():
    a = [{"type": "final", "item": 1, "label": "silk", "bin": 2, "confidence": 0.9500}]
    assert compare(a, [dict(a[0], confidence=0.9504)]) == []
    assert compare(a, [dict(a[0], confidence=0.96)])
    assert compare(a, [dict(a[0], bin=3)]) and compare(a, [dict(a[0], label="wool")])


def test_a_press_score_without_the_router_numbers_compares_on_the_rest():
    """A session recorded with a format-2 bundle replayed with the format-3 export of the same run:
    its presses have no router novelty (the scene decision never read it). The posterior is still
    compared, and a router number that both sides have still must agree."""
    press = {"point": 0, "novelty": 3.5, "untouched": False, "log_posterior": {"silk": -0.1, "wool": -2.4}}
    a = [{"type": "pre_sort", "item": 1, "scores": [press]}]
    lean = {k: v for k, v in press.items() if k not in ("novelty", "untouched")}
    assert compare(a, [{"type": "pre_sort", "item": 1, "scores": [lean]}]) == []
    moved = dict(lean, log_posterior={"silk": -0.2, "wool": -2.4})
    assert compare(a, [{"type": "pre_sort", "item": 1, "scores": [moved]}])
    assert compare(a, [{"type": "pre_sort", "item": 1, "scores": [dict(press, novelty=4.5)]}])
    assert compare(a, [{"type": "pre_sort", "item": 1, "scores": [dict(lean, point=1)]}])


def test_timings_are_not_decisions():
    """Model time per press and wall-clock stamps depend on the machine and its load (1.9 ms
    recorded beside the UR simulator, 0.6 ms replayed alone): never part of a reference, never
    compared - also for files whose references still carry them."""
    from vs2t_edge.runtime.replay import decisions_of

    rec = {"type": "pre_sort", "item": 1, "label": "silk", "bin": 2, "confidence": 0.97, "t": 1.7e9,
           "scores": [{"novelty": 3.0, "latency_ms": 1.9, "log_posterior": {"silk": -0.1}}]}
    (ref,) = decisions_of([rec, {"type": "item", "item": 1, "t": 1.7e9}])
    assert "t" not in ref and "latency_ms" not in ref["scores"][0] and ref["scores"][0]["novelty"] == 3.0
    now = dict(rec, t=1.8e9, scores=[dict(rec["scores"][0], latency_ms=0.6)])
    assert compare([rec], [now]) == [] and compare([rec], decisions_of([now])) == []
    assert compare([rec], [dict(now, scores=[dict(now["scores"][0], novelty=3.1)])])  # a score still counts


def test_a_fault_file_written_late_is_not_a_decision():
    """A fault file that could not be written when its fault latched, written at last by the loop's
    retry, is journalled (runtime/fault_latch.py): that day's disk, which a replay does not have."""
    from vs2t_edge.runtime.fault_latch import FILE_WRITTEN
    from vs2t_edge.runtime.replay import decisions_of

    fault = {"type": "fault", "reason": "jam", "kind": "jam", "steps_failed": ["fault file failed: EROFS"]}
    late = {"type": "fault", "reason": "jam", "kind": FILE_WRITTEN, "steps_failed": []}
    assert decisions_of([fault, late]) == [{"type": "fault", "reason": "jam", "kind": "jam"}]


def test_bad_replay_files_are_named(tmp_path):
    with pytest.raises(ReplayError, match="no index.json"):
        ReplayFile.open(tmp_path)
    (tmp_path / "index.json").write_text('{"format": "other"}')
    with pytest.raises(ReplayError, match="format 'other'"):
        ReplayFile.open(tmp_path)


def test_replay_cli_names_a_bad_file_once(tmp_path, capsys):
    """`replay /nonexistent.replay` said "/nonexistent.replay: /nonexistent.replay: not a replay
    file"; the path is said once, and a reason that does not name the file still gets it."""
    from vs2t_edge.cli import main

    missing = tmp_path / "nonexistent.replay"
    assert main(["replay", str(missing)]) == 2
    err = capsys.readouterr().err
    assert err.count(str(missing)) == 1 and "not a replay file (no such folder;" in err
    assert "`vs2t-edge record --config CONFIG --out NAME.replay`" in err  # and what writes one
    (tmp_path / "other.replay").mkdir()
    (tmp_path / "other.replay" / "index.json").write_text('{"format": "other"}')
    assert main(["replay", str(tmp_path / "other.replay")]) == 2
    err = capsys.readouterr().err
    assert err.count(str(tmp_path / "other.replay")) == 1 and "format 'other'" in err


def test_frame_names_cannot_leave_the_replay_folder(tmp_path):
    out, _ = record(tmp_path, [50, 50], 1)
    index = json.loads((out / "index.json").read_text())
    grab = next(e for e in index["events"] if e.get("frame"))
    grab["frame"] = "frames/../../../etc/passwd"
    (out / "index.json").write_text(json.dumps(index))
    with pytest.raises(ReplayError, match="is not frames/NNNNNN.png"):
        ReplayFile.open(out)


from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_json = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
                     lambda k: st.lists(k, max_size=3) | st.dictionaries(
                         st.sampled_from(["format", "version", "config", "items", "events", "decisions", "dev",
                                          "call", "item", "frame", "id", "type", "error", "args", "result"]),
                         k, max_size=5), max_leaves=20)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(body=_json)
def test_any_index_is_opened_or_refused_with_a_replay_error(tmp_path, body):
    if isinstance(body, dict):
        body = {"format": "vs2t-edge-replay", "version": 1, **body}
    (tmp_path / "index.json").write_text(json.dumps(body))
    try:
        ReplayFile.open(tmp_path)
    except ReplayError:
        pass


def test_record_cli_saves_what_was_recorded_on_sigint(tmp_path):
    """`vs2t-edge record` had no signal handlers: Ctrl-C raised KeyboardInterrupt before the save
    and the whole live recording was lost."""
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    from vs2t_edge.runtime.journal import read_records

    (tmp_path / "cell.yaml").write_text(CONFIG)
    out = tmp_path / "live.replay"
    journal = out.with_name(out.name + ".journal.jsonl")
    proc = subprocess.Popen([sys.executable, str(Path(__file__).parent / "daemon_fake_main.py"),
                             str(tmp_path / "cell.yaml"), "--record", str(out), "--score-delay-s", "0.02"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            if journal.exists() and sum(r["type"] == "final" for r in read_records(journal)) >= 2:
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert "stopped by SIGINT" in stdout and "SIGINT: finishing the item in hand safely" in stderr
    rf = ReplayFile.open(out)
    assert rf.index["meta"]["stopped_by"] == "SIGINT"
    finals = [d for d in rf.index["decisions"] if d["type"] == "final"]
    assert len(finals) >= 2 and len(finals) == len(rf.index["items"])  # every piece taken has its record
    assert all(d["outcome"] in ("sorted", "aborted") for d in finals)
    assert len(list((out / "frames").glob("*.png"))) == sum(1 for e in rf.index["events"] if e.get("frame")) > 0
    assert not journal.exists()


def test_an_exception_ending_a_recording_is_raised_after_the_save(tmp_path):
    class InterruptedModel(type(model())):
        def score_press(self, frame):
            if self.scored == 3:
                raise KeyboardInterrupt  # Ctrl-C where no handler catches it (a library call)
            return super().score_press(frame)

    (tmp_path / "cell.yaml").write_text(CONFIG)
    cfg = load_config(tmp_path / "cell.yaml")
    arm = FakeArm(config=cfg.arm)
    with pytest.raises(KeyboardInterrupt):
        record_session(cfg, tmp_path / "s.replay", model=InterruptedModel(VOTES, CLASSES),
                       camera=ScriptedCamera(arm, [50, 50, 60, 60, 70, 70]), arm=arm, gate=FakeGate(),
                       items=ContinuousFeed(limit=3), evidence_factory=evidence)
    rf = ReplayFile.open(tmp_path / "s.replay")
    assert rf.index["meta"]["crashed"].startswith("KeyboardInterrupt")
    assert [d["label"] for d in rf.index["decisions"] if d["type"] == "final"] == ["denim"]
    assert sum(1 for e in rf.index["events"] if e.get("frame")) >= 4


# --- the fault's safety steps (arm.stop, gate.to_reject) are recorded and compared -------------

def test_safety_steps_are_recorded_and_a_replay_that_skips_them_mismatches(tmp_path, monkeypatch):
    """arm.stop and gate.to_reject were not recorded and the replay devices stubbed them: a
    regression that stopped sending them replayed as identical."""
    out, _ = record(tmp_path, [50, 50, 60, 60, 70, 70], 3, fail_next=["protective_stop"])
    rf = ReplayFile.open(out)
    safety = [(e["item"], e["dev"], e["call"]) for e in rf.index["safety_steps"]]
    # start: gate to reject; item 0's protective stop: arm stopped, gate to reject; end: both again
    assert safety[0] == (-1, "gate", "to_reject") and (0, "arm", "stop") in safety and (0, "gate", "to_reject") in safety
    assert run_replay(out, model=model(), evidence_factory=evidence).ok

    latch_skipping(monkeypatch, "gate", "to_reject")  # the regression
    report = run_replay(out, model=model(), evidence_factory=evidence)
    assert not report.ok and any("gate.to_reject at item 0" in m for m in report.mismatches), report.mismatches
    # --update-refs cannot accept it: the recording itself would be wrong
    report = run_replay(out, model=model(), evidence_factory=evidence, update_refs=True)
    assert "re-record" in report.diverged


def test_replay_gate_goes_to_the_configured_reject_bin(tmp_path):
    from vs2t_edge.runtime.replay import ReplayGate, _Queues

    out, _ = record(tmp_path, [50, 50], 1)
    gate = ReplayGate(_Queues(ReplayFile.open(out)), reject_bin=5)
    gate.bin = 2
    gate.to_reject()
    assert gate.status().bin == 5


def test_a_file_recorded_before_safety_steps_still_replays(tmp_path, monkeypatch):
    out, _ = record(tmp_path, [50, 50, 60, 60, 70, 70], 3, fail_next=["protective_stop"])
    index = json.loads((out / "index.json").read_text())
    del index["safety_steps"]
    (out / "index.json").write_text(json.dumps(index))
    report = run_replay(out, model=model(), evidence_factory=evidence)
    assert report.ok, report.mismatches + [report.diverged]
    # nothing recorded to compare with: a latch without gate.to_reject is not (cannot be) flagged
    latch_skipping(monkeypatch, "gate", "to_reject")
    assert run_replay(out, model=model(), evidence_factory=evidence).ok


def test_malformed_safety_steps_are_refused_in_words(tmp_path):
    out, _ = record(tmp_path, [50, 50], 1)
    index = json.loads((out / "index.json").read_text())
    for bad in ({"item": 0, "dev": ["arm"], "call": "stop"}, {"item": True, "dev": "arm", "call": "stop"},
                {"item": 0, "dev": "arm", "call": "press"}, "stop"):
        (out / "index.json").write_text(json.dumps(dict(index, safety_steps=[bad])))
        with pytest.raises(ReplayError, match=r"safety_steps\[0\]"):
            ReplayFile.open(out)


def test_record_cli_gives_the_callers_signal_handlers_back(tmp_path):
    import signal

    from vs2t_edge.cli import main

    before = signal.getsignal(signal.SIGINT)
    (tmp_path / "cell.yaml").write_text(CONFIG.replace("bundle: bundle", f"bundle: {tmp_path / 'none'}"))
    assert main(["record", "--config", str(tmp_path / "cell.yaml"), "--out", str(tmp_path / "x.replay")]) == 2
    assert signal.getsignal(signal.SIGINT) is before

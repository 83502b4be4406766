"""The committed reference sessions of the simulated cell replay with identical decisions.

tests/replays/*.replay were recorded on the simulated cell (loopback UR simulator, pty gate,
camera fed from the tiny fabric world) with the bundle in tests/replays/bundle by

    python -m vs2t_edge.sim.scene record-references --dataset DS --bundle tests/replays/bundle --out tests/replays

(see tests/replays/README.md). Each replay runs the whole daemon again - the real bundle through
onnxruntime, the real evidence rule, the journal - and must reproduce every decision and bin
exactly and every score within 1e-3.
"""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).parent / "replays"
SESSIONS = sorted(HERE.glob("*.replay"))
BUNDLE = HERE / "bundle"

pytestmark = pytest.mark.skipif(not SESSIONS or not BUNDLE.is_dir(),
                                reason="no committed reference replays/bundle under tests/replays")


def test_the_four_kinds_of_session_are_committed():
    from vs2t_edge.runtime.replay import ReplayFile

    names = {p.stem for p in SESSIONS}
    assert {"touched", "untouched", "unknown", "fault"} <= names
    fault = ReplayFile.open(HERE / "fault.replay").index["decisions"]
    assert any(d["type"] == "fault" for d in fault) and any(d["type"] == "fault_cleared" for d in fault)
    assert any(d["type"] == "final" and d["outcome"] == "rejected_fault" for d in fault)
    total = sum(f.stat().st_size for f in HERE.rglob("*") if f.is_file())
    assert total < 3_000_000, f"tests/replays is {total / 1e6:.1f} MB; keep it small"


@pytest.mark.parametrize("session", SESSIONS, ids=[p.stem for p in SESSIONS])
def test_session_replays_with_identical_decisions(session):
    from vs2t_edge.runtime.replay import run_replay

    report = run_replay(session, bundle=BUNDLE)
    assert not report.diverged, report.diverged
    assert report.ok, "\n".join(report.mismatches)
    assert [d for d in report.decisions if d["type"] == "final"]


def test_replay_cli_reports_ok_and_catches_a_changed_beta(tmp_path, capsys):
    import json
    import shutil

    from vs2t_edge.cli import main

    assert main(["replay", str(HERE / "touched.replay"), "--bundle", str(BUNDLE)]) == 0
    assert "ok" in capsys.readouterr().out
    # the same session with a beta that routes everything untouched must not pass
    copy = tmp_path / "touched.replay"
    shutil.copytree(HERE / "touched.replay", copy)
    index = json.loads((copy / "index.json").read_text())
    index["meta"]["beta"] = -1e6
    (copy / "index.json").write_text(json.dumps(index))
    assert main(["replay", str(copy), "--bundle", str(BUNDLE)]) == 1

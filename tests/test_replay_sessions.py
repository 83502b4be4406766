"""The committed reference sessions of the simulated cell replay with identical decisions.

tests/replays/*.replay were recorded on the simulated cell (loopback UR simulator, pty gate,
camera fed from the tiny fabric world) with the bundle in tests/replays/bundle by

    python -m vs2t_edge.sim.scene record-references --dataset DS --bundle tests/replays/bundle --out tests/replays

(see tests/replays/README.md). Each replay runs the whole daemon again - the real bundle through
onnxruntime, the real evidence rule, the journal - and must reproduce every decision and bin
exactly and every score within 1e-3.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

HERE = Path(__file__).parent / "replays"
SESSIONS = sorted(HERE.glob("*.replay"))
BUNDLE = HERE / "bundle"

# No skip when they are missing: they are committed, and a replay test that silently skips is
# how the CI replays stayed unreal until they were.


def test_the_four_kinds_of_session_are_committed():
    from vs2t_edge.runtime.replay import ReplayFile

    assert BUNDLE.is_dir() and (BUNDLE / "manifest.json").is_file(), f"{BUNDLE} is missing (see README.md there)"
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


def test_committed_replays_name_no_machine_paths():
    """A clean clone has only the repo: the replays name the bundle and dataset relatively."""
    for session in SESSIONS:
        text = (session / "index.json").read_text()
        assert "/work/" not in text and "/tmp/" not in text and "/home/" not in text, session
        config = json.loads(text)["config"]
        assert config["bundle"] == "bundle" and config["devices"]["camera"]["path"] == "dataset"
        assert config["threads"] == 1, "references are recorded and replayed at 1 onnxruntime thread"


def test_reference_decisions_are_not_on_a_knife_edge():
    """A replay on another CPU differs in the last bits of a score; every recorded decision
    (stop/unknown rule, label, touched/untouched route of each press) must be farther from
    flipping than the replay's score tolerance, or the reference is fragile - re-record with
    another --seed."""
    import json
    import math

    from vs2t_edge.runtime.replay import SCORE_RTOL
    from vs2t_edge.sim.scene import decision_margins

    for session in SESSIONS:
        index = json.loads((session / "index.json").read_text())
        margins = decision_margins(index)
        assert all(math.isfinite(v) for v in margins.values()), (session.stem, margins)
        assert min(margins.values()) > SCORE_RTOL, (session.stem, margins)


def test_decision_margins_of_presses_without_a_router_have_no_route_margin():
    """A session recorded with a format-3 bundle: its presses carry no novelty, so there is no
    touched/untouched route to flip; the other margins are still measured."""
    from vs2t_edge.sim.scene import decision_margins

    index = {"config": {"evidence": {"confidence": 0.9}, "scene": {"fabrics": [{"name": "a"}, {"name": "b"}]}},
             "meta": {"beta": 2.0},
             "decisions": [{"type": "pre_sort", "scores": [{"log_posterior": {"a": -0.01, "b": -4.6}}]}]}
    m = decision_margins(index)
    assert "novelty_log_ratio" not in m and 0 < m["confidence"] < 0.1 and m["label_gap"] > 0.9
    index["decisions"][0]["scores"][0]["novelty"] = 4.0
    assert decision_margins(index)["novelty_log_ratio"] == pytest.approx(math.log(2.0))


def test_decision_margins_recompute_the_recorded_evidence():
    """decision_margins re-fuses the per-press posteriors over the scene; its fused posterior must
    be the one the cell journaled, or the margins above measure something else."""
    import json

    import numpy as np

    from vs2t_edge.sim.scene import decision_margins

    index = json.loads((HERE / "touched.replay" / "index.json").read_text())
    scene = [f["name"] for f in index["config"]["scene"]["fabrics"]]
    for d in (d for d in index["decisions"] if d["type"] == "pre_sort"):
        acc = sum(np.array([s["log_posterior"][c] for c in scene]) - np.logaddexp.reduce(
            [s["log_posterior"][c] for c in scene]) for s in d["scores"])
        fused = acc - np.logaddexp.reduce(acc)
        np.testing.assert_allclose(fused, [d["log_posterior"][c] for c in scene], atol=1e-9)
        assert abs(np.exp(fused.max()) - d["confidence"]) < 1e-9
    one = dict(index, decisions=[d for d in index["decisions"] if d["type"] == "pre_sort"][:1])
    assert decision_margins(one)["confidence"] == pytest.approx(
        min(abs(c - index["config"]["evidence"]["confidence"]) for c in _fused_maxima(one, scene)))


def _fused_maxima(index, scene):
    import numpy as np

    out = []
    for d in (d for d in index["decisions"] if d["type"] == "pre_sort"):
        acc = np.zeros(len(scene))
        for s in d["scores"]:
            v = np.array([s["log_posterior"][c] for c in scene])
            acc = acc + v - np.logaddexp.reduce(v)
            out.append(float(np.exp((acc - np.logaddexp.reduce(acc)).max())))
    return out


def test_the_readme_recipe_reproduces_the_committed_references(tmp_path):
    """tests/replays/README.md's recipe, steps 1 and 4 (the bundle is the committed one), with the
    in-process arm and gate for speed: the same world, the same device calls in the same order
    and the same decisions. Only what the simulated devices measure or say differs (the UR
    simulator's contact force, the wording of its protective stop). If this fails, the world
    generator or the simulated cell changed: the committed replays still replay, but the README
    no longer says how they were made - re-record them as it describes."""
    import json

    from vs2t_edge.runtime.replay import compare
    from vs2t_edge.sim.scene import make_reference_world, record_reference_sessions

    make_reference_world(tmp_path / "ds", seed=0, progress=False)
    written = record_reference_sessions(tmp_path / "ds", BUNDLE, tmp_path / "out", arm_kind="fake",
                                        gate_kind="fake", seed=1, log=lambda m: None)
    assert sorted(p.name for p in written) == sorted(p.name for p in SESSIONS)

    def device_independent(decisions):
        out = []
        for d in decisions:
            d = dict(d, scores=[{k: v for k, v in sc.items() if k != "force_n"} for sc in d.get("scores", [])])
            if isinstance(d.get("reason"), str):
                d["reason"] = d["reason"].split(" mm: ")[0]  # "... during press 1 at (x, y) mm: <the arm's words>"
            out.append(d)
        return out

    for new in written:
        ref = json.loads((HERE / new.name / "index.json").read_text())
        got = json.loads((new / "index.json").read_text())
        calls = [[(e["item"], e["dev"], e["call"], e.get("args")) for e in i["events"]] for i in (ref, got)]
        assert calls[0] == calls[1], f"{new.stem}: the simulated cell made other device calls"
        assert ref["items"] == got["items"]
        problems = compare(device_independent(ref["decisions"]), device_independent(got["decisions"]))
        assert not problems, f"{new.stem}: " + "\n".join(problems)


def test_the_bundle_is_found_beside_the_replays_or_asked_for(tmp_path):
    import shutil

    from vs2t_edge.runtime.replay import ReplayError, run_replay

    assert run_replay(HERE / "unknown.replay").ok  # tests/replays/bundle, next to the file
    shutil.copytree(HERE / "unknown.replay", tmp_path / "unknown.replay")
    with pytest.raises(ReplayError, match="give --bundle"):
        run_replay(tmp_path / "unknown.replay")


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


def _live_config(bundle, ref: dict, tmp_path) -> dict:
    """A cell config that records the touched session's frames live with ``bundle``: the reference
    session's scene and evidence, fake arm and gate. The committed bundle has no scene model, so
    recording it live needs the written opt-in."""
    return {"bundle": str(bundle), "threads": 1,
            "devices": {"camera": {"kind": "replay", "path": str((HERE / "touched.replay" / "frames").resolve())},
                        "arm": {"kind": "fake"}, "gate": {"kind": "fake"}},
            "scene": ref["config"]["scene"],
            "evidence": {**ref["config"]["evidence"], "without_scene_model": "allow"},
            "journal": str(tmp_path / "journal.jsonl")}


def test_record_cli_then_replay_cli_with_the_real_bundle(tmp_path, capsys):
    """`vs2t-edge record` on the live device path (the camera replaying touched.replay's frames,
    the in-process arm and gate) makes the same first two decisions as the reference, and
    `vs2t-edge replay` reproduces its own recording; a camera that cannot open ends in exit 3."""
    import json

    import yaml

    from vs2t_edge.cli import main

    ref = json.loads((HERE / "touched.replay" / "index.json").read_text())
    config = _live_config(BUNDLE.resolve(), ref, tmp_path)
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(config))
    out = tmp_path / "today.replay"
    assert main(["record", "--config", str(tmp_path / "cell.yaml"), "--out", str(out), "--max-items", "2"]) == 0
    assert "recorded 2 of 2 items" in capsys.readouterr().out
    got = [(d["label"], d["bin"], d["presses"]) for d in json.loads((out / "index.json").read_text())["decisions"]
           if d["type"] == "final"]
    want = [(d["label"], d["bin"], d["presses"]) for d in ref["decisions"] if d["type"] == "final"][:2]
    assert got == want
    assert main(["replay", str(out)]) == 0  # the absolute bundle path it recorded
    assert "ok, 2 items identical" in capsys.readouterr().out

    config["devices"]["camera"]["path"] = str(tmp_path / "no-such-frames")
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(config))
    assert main(["record", "--config", str(tmp_path / "cell.yaml"), "--out", str(tmp_path / "x.replay")]) == 3
    assert "exit 3" in capsys.readouterr().err


def test_the_fault_session_catches_a_latch_that_no_longer_stops_the_arm(monkeypatch):
    """fault.replay records the protective stop's safety steps (``safety_steps``): a cell that
    stopped sending arm.stop on a latched fault must not replay as identical."""
    from cell_fakes import latch_skipping
    from vs2t_edge.runtime.replay import ReplayFile, run_replay

    assert any(st["call"] == "stop" for st in ReplayFile.open(HERE / "fault.replay").index["safety_steps"])
    latch_skipping(monkeypatch, "arm", "stop")
    report = run_replay(HERE / "fault.replay", bundle=BUNDLE)
    assert not report.ok and any("safety steps" in m for m in report.mismatches), report.mismatches


def test_a_session_names_its_bundles_seal_and_replays_only_against_that_bundle(tmp_path, capsys):
    """The start record (and so the replay's meta) carries the bundle's manifest seal: a bundle
    swapped in the same folder is seen in the journal, and `vs2t-edge replay` refuses to compare a
    session with another bundle than the one it ran - unless told --allow-other-bundle."""
    import shutil

    import yaml

    from vs2t_edge.cli import main
    from vs2t_edge.runtime.bundle import SEAL_KEY, seal_manifest

    shutil.copytree(BUNDLE, tmp_path / "bundle")
    seal = json.loads((BUNDLE / "manifest.json").read_text())[SEAL_KEY]
    ref = json.loads((HERE / "touched.replay" / "index.json").read_text())
    config = _live_config(tmp_path / "bundle", ref, tmp_path)
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(config))
    out = tmp_path / "today.replay"
    assert main(["record", "--config", str(tmp_path / "cell.yaml"), "--out", str(out), "--max-items", "1"]) == 0
    assert json.loads((out / "index.json").read_text())["meta"][SEAL_KEY] == seal
    assert main(["replay", str(out)]) == 0
    # another export deployed to the same folder: the same graphs, another manifest
    manifest = json.loads((tmp_path / "bundle" / "manifest.json").read_text())
    manifest["provenance"] = dict(manifest["provenance"], note="another export")
    (tmp_path / "bundle" / "manifest.json").write_text(json.dumps(seal_manifest(manifest), indent=2))
    capsys.readouterr()
    assert main(["replay", str(out)]) == 2
    err = capsys.readouterr().err
    assert "another bundle than the session ran" in err and seal[:12] in err and "--allow-other-bundle" in err, err
    assert main(["replay", str(out), "--allow-other-bundle"]) == 0
    assert "ok, 1 items identical" in capsys.readouterr().out

"""The fault matrix (sim/faults.py): every row must pass in CI. One test per row, so a failing
row is named; the UR simulator rows need ur_rtde and take ~10 s each."""

from __future__ import annotations

import pytest

from vs2t_edge.sim import fault_rig, faults, faults_startup

ROWS = {s.name: s for s in faults.SCENARIOS}


def _param(sc):
    marks = [pytest.mark.slow] if sc.where == "ursim" else []  # ~10 s each against the UR simulator
    if sc.known_bug:  # fails today for a named reason; strict, so a fix shows up as XPASS
        marks.append(pytest.mark.xfail(strict=True, reason="BUG " + sc.known_bug))
    return pytest.param(sc.name, marks=marks)


@pytest.mark.parametrize("name", [_param(s) for s in faults.SCENARIOS])
def test_fault_matrix_row(name, tmp_path):
    sc = ROWS[name]
    if sc.where == "ursim":
        pytest.importorskip("rtde_control")
    row = faults.run_scenario(sc, tmp_path)
    if row.pending:
        pytest.skip(row.pending)
    assert row.passed, f"{name}: {row.outcome}\n" + "\n".join(row.problems)


def test_audit_catches_a_lost_a_duplicated_and_a_guessed_item(tmp_path):
    from vs2t_edge.runtime.journal import Journal

    j = Journal.open(tmp_path / "j.jsonl")
    for n, pid in ((1, "a"), (2, "b"), (3, "c"), (4, "d")):
        j.append({"type": "item", "item": n, "item_id": pid})
    j.append({"type": "final", "item": 1, "item_id": "a", "outcome": "sorted", "bin": 1})
    j.append({"type": "final", "item": 1, "item_id": "a", "outcome": "sorted", "bin": 1})  # duplicated
    j.append({"type": "final", "item": 3, "item_id": "c", "outcome": "sorted", "bin": 2})  # denim in silk's bin
    j.append({"type": "final", "item": 4, "item_id": "d", "outcome": "rejected_fault", "bin": 3})  # not rejected
    j.close()
    problems = fault_rig.audit(tmp_path / "j.jsonl", {"a": "denim", "b": "silk", "c": "denim", "d": "wool"})["problems"]
    text = "\n".join(problems)
    assert "item 1 has 2 final records" in text
    assert "items without a final record: [2]" in text
    assert "c (denim) -> bin 2" in text and "d rejected_fault -> bin 3" in text


def test_reliability_cli_writes_the_table(tmp_path, capsys):
    import argparse

    from vs2t_edge.sim import faults_cli

    p = argparse.ArgumentParser()
    faults_cli.add_arguments(p, "reliability")
    out = tmp_path / "rel.md"
    args = p.parse_args(["--only", "protective_stop", "bundle_tampered", "--out", str(out),
                         "--soak-json", str(tmp_path / "none.json")])
    assert faults_cli.run(args) == 0
    text = out.read_text()
    assert "| 1 | `protective_stop` | loop |" in text and "PASS" in text
    row2 = next(line for line in text.splitlines() if line.startswith("| 2 | `bundle_tampered` | bundle |"))
    assert row2.endswith(" |") and "| PASS |" in row2, row2  # really run, not pending
    # the template's hand-written sections survive regeneration, in their places
    assert (text.index("## Bugs found and fixed") < text.index("## Fault matrix") < text.index("## Fuzzing")
            < text.index("## Security"))
    assert "systemd-analyze security --offline=true" in text  # the command that measures the score
    assert "<!--" not in text
    assert faults_cli.run(p.parse_args(["--only", "no_such_row"])) == 2
    assert "unknown scenario" in capsys.readouterr().err


def test_bundle_rows_have_a_bundle_to_tamper_with():
    # the bundle rows skip (pending) without one: in this repository they must really run
    assert faults_startup.good_bundle() is not None


def test_known_bug_rows_are_listed_not_blocking(tmp_path, monkeypatch):
    """A row marked known_bug reads KNOWN BUG with its reason and does not fail the command; an
    ordinary failing row does. (No real row is a known bug today: both rows here are planted.)"""
    import argparse

    from vs2t_edge.sim import faults_cli

    def fails(w):
        return "did the wrong thing", ["planted failure"]

    monkeypatch.setattr(faults, "SCENARIOS", faults.SCENARIOS + [
        faults.Scenario("planted_known_bug", "loop", "a planted fault", "refused", fails, known_bug="owner: a planted bug"),
        faults.Scenario("planted_failure", "loop", "a planted fault", "refused", fails)])
    p = argparse.ArgumentParser()
    faults_cli.add_arguments(p, "reliability")
    out = tmp_path / "rel.md"

    def run(*names):
        return faults_cli.run(p.parse_args(["--only", *names, "--out", str(out), "--soak-json", str(tmp_path / "x")]))

    assert run("planted_known_bug") == 0  # listed as a known bug with its owner, the command does not fail on it
    text = out.read_text()
    assert "**KNOWN BUG**" in text and "owner: a planted bug" in text
    assert run("planted_failure") == 1


def test_no_row_is_a_known_bug():
    """Issue 8: every row of the matrix passes in CI. A known-bug row is a documented failure, not a pass."""
    assert [s.name for s in faults.SCENARIOS if s.known_bug] == []


def test_the_hostile_python_tag_would_be_caught(tmp_path):
    """The row's check can fail: the same text through PyYAML's unsafe loader does run the command
    and leaves the marker file the row looks for."""
    import yaml

    mark = tmp_path / "pwned"
    text = faults_startup.HOSTILE_CONFIGS["python object tag"].replace("@MARK@", str(mark))
    yaml.unsafe_load(text)
    assert mark.exists()


def test_the_security_section_names_tests_that_exist():
    """Every test the report's Security section cites as the check of a promise is a real test."""
    import re
    from pathlib import Path

    from vs2t_edge.sim import faults_cli

    text = Path(faults_cli.__file__).with_name("reliability_template.md").read_text()
    section = text[text.index("## Security"):]
    named = set(re.findall(r"\b(test_\w+)(?!\w|\.py)", section))  # not the module names
    assert len(named) >= 10, named
    tests = Path(__file__).parent
    defined = {m for f in tests.glob("test_*.py") for m in re.findall(r"^def (test_\w+)", f.read_text(), re.M)}
    assert named <= defined, sorted(named - defined)

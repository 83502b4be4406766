"""`vs2t-edge demo`'s sorting path, end to end on a tiny world: the CLI's run() with the world,
training and export stages cached (the committed tiny-trunk bundle tests/replays/bundle, trained
on the reference world that sim.scene.make_reference_world makes with seed 0), then the daemon
sorting a stream on the simulated cell (in-process arm and gate for speed; ~5 s on 2 cores).

What is asserted is structure and arithmetic, not a good accuracy: the bundle is a tiny test
model (GZSL H 53.8 on its split, no scene model: it decides with its router, so the demo is told
`--without-scene-model allow`) and its numbers on a
short stream are not robust. Every piece of the stream has exactly one final record in the journal,
its bin is the scene's bin of its label (the reject bin for unknown, off-scene labels and faults),
and the totals the demo prints and writes (right bin / mis-sort / reject per kind, presses per piece)
are recomputed from the journal and the stream.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import shutil
from pathlib import Path

import pytest
import yaml

from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.journal import read_records

HERE = Path(__file__).parent
BUNDLE = HERE / "replays" / "bundle"
N_ITEMS = 10


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    from vs2t_edge.cli import main
    from vs2t_edge.sim.scene import make_reference_world

    work = tmp_path_factory.mktemp("demo")
    make_reference_world(work / "dataset", seed=0, progress=False)
    shutil.copytree(BUNDLE, work / "bundle")
    (work / "run").mkdir()
    params = {"profile": "demo", "seed": 0}  # the demo's defaults: its stage markers say "cached"
    for stage in ("synth", "train", "export"):
        (work / f".stage-{stage}.json").write_text(json.dumps({"params": params}))
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["demo", "--workdir", str(work), "--items", str(N_ITEMS), "--arm", "fake", "--gate", "fake",
                     "--threads", "1", "--max-presses", "3", "--fault-at", "3:1",
                     "--without-scene-model", "allow"])  # the test bundle decides with its router
    return code, out.getvalue(), work


def test_the_demo_refuses_a_bundle_without_a_scene_model_unless_told(demo_run, capsys):
    """Without decision.npz nothing sends an off-scene piece to the reject bin: the demo says so
    and how to fix it, before the simulated cell comes up (the daemon would refuse it too)."""
    from vs2t_edge.cli import main

    _, _, work = demo_run
    code = main(["demo", "--workdir", str(work), "--items", "2", "--arm", "fake", "--gate", "fake", "--threads", "1"])
    err = capsys.readouterr().err
    assert code == 2 and "has no scene model (decision.npz)" in err and "vs2t-edge export RUN" in err, err


def test_the_demo_runs_from_cached_stages(demo_run):
    code, out, work = demo_run
    assert code == 0, out
    assert "[1/4] fabric world: cached" in out and "[3/4] export: cached" in out  # nothing was retrained
    assert (work / "demo_summary.json").is_file() and (work / "journal.jsonl").is_file()
    # the config the daemon ran is named, for the commands a user runs next (check-job, label, ...)
    assert f"the cell config the daemon ran: {work / 'cell.yaml'}" in out and (work / "cell.yaml").is_file()


def test_a_workdir_that_is_a_file_or_an_unknown_profile_is_bad_usage(tmp_path, capsys):
    from vs2t_edge.cli import main

    (tmp_path / "afile").write_text("")
    assert main(["demo", "--workdir", str(tmp_path / "afile")]) == 2
    err = capsys.readouterr().err
    assert "is a file, not a folder" in err and str(tmp_path / "afile") in err, err
    # an unknown --profile, before any stage (it was synth's ValueError traceback)
    assert main(["demo", "--workdir", str(tmp_path / "new"), "--profile", "papr"]) == 2
    err = capsys.readouterr().err
    assert "unknown --profile 'papr'; choose one of demo, demo_visible, paper" in err and not (tmp_path / "new").exists(), err


def test_every_piece_is_journalled_once_in_the_bin_of_its_label(demo_run):
    code, out, work = demo_run
    records = read_records(work / "journal.jsonl")
    items = [r for r in records if r["type"] == "item"]
    finals = [r for r in records if r["type"] == "final"]
    assert len(items) == N_ITEMS and [f["item"] for f in finals] == [i["item"] for i in items]
    scene = yaml.safe_load((work / "cell.yaml").read_text())["scene"]
    bins = {f["name"]: f["bin"] for f in scene["fabrics"]}
    for f in finals:
        if f["outcome"] == "sorted":
            assert f["bin"] == bins.get(f["label"], scene["reject_bin"]), f
        else:
            assert f["bin"] == scene["reject_bin"], f
    # the injected protective stop (--fault-at 3:1: item-0003's first press, as the printout numbers
    # them): latched, rejected, cleared, sorting went on
    assert finals[2]["outcome"] == "rejected_fault" and finals[2]["item_id"] == "item-0003"
    assert [r["type"] for r in records].count("fault_cleared") == 1
    assert all(f["outcome"] == "sorted" for i, f in enumerate(finals) if i != 2)
    # a pre_sort before every sorted final, with the same decision
    pre = {r["item"]: r for r in records if r["type"] == "pre_sort"}
    assert all((pre[f["item"]]["label"], pre[f["item"]]["bin"]) == (f["label"], f["bin"])
               for f in finals if f["outcome"] == "sorted")


def test_printed_and_written_totals_match_the_journal(demo_run):
    code, out, work = demo_run
    summary = json.loads((work / "demo_summary.json").read_text())
    finals = [r for r in read_records(work / "journal.jsonl") if r["type"] == "final"]
    cfg = yaml.safe_load((work / "cell.yaml").read_text())
    kinds = {f["name"]: f["kind"] for f in cfg["scene"]["fabrics"]}
    rows = summary["rows"]
    assert summary["items"] == len(rows) == len(finals) == N_ITEMS
    truth = {}
    for row, f in zip(rows, finals):
        assert (row["item"], row["label"], row["bin"], row["outcome"]) == (f["item_id"], f["label"], f["bin"],
                                                                           f["outcome"])
        truth[row["item"]] = row["truth"]
    # the line's rule, recomputed from the journal: a scene piece in its own bin is right, in another
    # scene bin a mis-sort, in the reject bin a reject; an off-scene piece is right only in the reject bin
    def result(f):
        t, sorted_ = truth[f["item_id"]], f["outcome"] == "sorted" and f["label"] in kinds
        if t not in kinds:
            return "mis-sort" if sorted_ else "right"
        return ("right" if f["label"] == t else "mis-sort") if sorted_ else "reject"

    results = [result(f) for f in finals]
    assert [r["result"] for r in rows] == results
    for o in ("right", "mis-sort", "reject"):
        assert summary["all"][o] == pytest.approx(results.count(o) / N_ITEMS)
    assert summary["all"]["presses"] == pytest.approx(sum(f["presses"] for f in finals) / N_ITEMS)
    for kind in set(kinds.get(t, "off-scene") for t in truth.values()):
        mine = [r for f, r in zip(finals, results) if kinds.get(truth[f["item_id"]], "off-scene") == kind]
        assert summary["by_kind"][kind]["right"] == pytest.approx(mine.count("right") / len(mine))
    # what is printed is what was computed
    m = re.search(r"(\d+) pieces: ([0-9.]+)% in the right bin, ([0-9.]+)% MIS-SORTED", out)
    assert m and int(m.group(1)) == N_ITEMS
    assert float(m.group(2)) == pytest.approx(100 * summary["all"]["right"], abs=0.05)
    assert float(m.group(3)) == pytest.approx(100 * summary["all"]["mis-sort"], abs=0.05)
    m = re.search(r"presses per piece ([0-9.]+);", out)
    assert m and float(m.group(1)) == pytest.approx(summary["all"]["presses"], abs=0.005)
    per_item = [line for line in out.splitlines() if re.match(r"\S+\s+\S+ .*-> .* bin \d+ ", line)]
    assert len(per_item) == N_ITEMS
    assert all(line.rstrip().split()[-1] in ("right", "rejected", "MIS-SORTED") or ":" in line or "(" in line
               for line in per_item)
    # a piece in the reject bin says why, as the journal has it; the totals count the off-scene rules' pieces
    why = {r["item_id"]: r["stopped_by"] for r in read_records(work / "journal.jsonl") if r["type"] == "pre_sort"}
    for line, f in zip(per_item, finals):
        in_reject = f["label"] not in kinds
        said = so.REASONS.get(why.get(f["item_id"], ""), why.get(f["item_id"], ""))
        assert (f": {said}" in line) == in_reject, line
    for kind, r in summary["by_kind"].items():
        mine = [f for f in finals if kinds.get(truth[f["item_id"]], "off-scene") == kind]
        by_rule = sum(why.get(f["item_id"]) == "off_scene" and f["label"] not in kinds for f in mine)
        assert round(summary["off_scene_rule"]["by_kind"][kind] * r["n"]) == by_rule
        assert re.search(rf"{kind}\s+{r['n']} pieces: .*; {by_rule} to the reject bin by the off-scene rules", out)
    assert all(1 <= f["presses"] <= 3 for f in finals if f["outcome"] == "sorted")  # --max-presses 3


def test_a_piece_line_says_press_for_one_and_presses_for_more(demo_run):
    """'1 presses' read wrong (this stream's first piece is decided after one press)."""
    code, out, work = demo_run
    said = re.findall(r" bin \d+\s+(\d+) (press(?:es)?)\b", out)
    assert len(said) == N_ITEMS and any(n == "1" for n, _ in said), out
    assert all((word == "press") == (n == "1") for n, word in said), said


def test_the_totals_count_the_pieces_the_off_scene_rules_refused():
    """The demo's own world may refuse no piece by the off-scene rules (its fixture bundle has no
    scene model): the count is checked here on hand-made records, one rule-refused piece of each kind
    and other rejects beside them that the rules did not send."""
    from vs2t_edge.sim.demo import report_lines
    scene = ["silk", "wool"]

    def rec(truth, kind, label, stopped_by):
        return so.record(truth, kind, type("D", (), {"label": label, "confidence": 0.5, "presses": 3,
                                                       "stopped_by": stopped_by, "log_posterior": {}})(), scene)
    recs = [rec("silk", "touched", "silk", "confident"), rec("silk", "touched", "unknown", "off_scene"),
            rec("silk", "touched", "unknown", "press_limit"), rec("wool", "untouched", "unknown", "press_limit"),
            rec("felt", "off-scene", "unknown", "off_scene"), rec("felt", "off-scene", "unknown", "off_scene"),
            rec("felt", "off-scene", "unknown", "press_limit")]
    summary = {**so.summarise(recs), "items_per_min": 20.0, "item_s_median": 3.0, "latency_ms_median": 5.0,
               "latency_ms_p95": 7.0}
    out = report_lines(summary)
    assert re.search(r"touched\s+3 pieces: right\s+33.3%.*; 1 to the reject bin by the off-scene rules", out), out
    assert re.search(r"untouched\s+1 pieces: .*; 0 to the reject bin by the off-scene rules", out), out
    assert re.search(r"off-scene\s+3 pieces: right\s+100.0%.*; 2 to the reject bin by the off-scene rules", out), out


def test_pieces_per_minute_count_the_job_pieces_over_the_time_teach_pieces_took_too():
    """Teach pieces are not counted (the totals are the job's pieces), but the arm pressed them: the
    pace is the job's pieces over the time of every piece. It counted the two teach pieces as pieces
    (32 where 30 were sorted) and put their 5-press times in the median time per piece."""
    from vs2t_edge.runtime.items import Item, ItemResult
    from vs2t_edge.sim.demo import TEACH_PREFIX, job_pace, report_lines

    def res(item_id, s):
        return ItemResult(Item(item_id), "silk", 1, "sorted", 1, 0.9, "confident", 0, [5.0], s)
    results = [res(f"{TEACH_PREFIX}01", 6.0), res(f"{TEACH_PREFIX}02", 6.0)] + [res(f"item-{i:04d}", 2.0)
                                                                               for i in range(1, 5)]
    pace = job_pace(results)
    assert pace["items_per_min"] == pytest.approx(60.0 * 4 / 20.0)  # 4 pieces in 20 s: 12 a minute, not 18
    assert pace["item_s_median"] == 2.0 and pace["teach_s"] == pytest.approx(12.0)
    assert job_pace(results[2:])["items_per_min"] == pytest.approx(30.0)  # no teach pieces: as before
    recs = [so.record("silk", "touched", r, ["silk"]) for r in results[2:]]
    out = report_lines({**so.summarise(recs), **pace, "teach_pieces": ["silk"]})
    assert "12.0 pieces per minute" in out and "their 12.0 s are in the pieces per minute" in out, out
    assert "(a piece's median 2.0 s)" in out, out  # a median, not 60 / pieces per minute: said so


def test_a_piece_of_unknown_outcome_is_counted_apart_not_as_a_reject(demo_run, tmp_path, monkeypatch):
    """A piece whose gate ack was lost twice is journalled ``unknown_outcome`` (the gate may have
    moved it into the bin it was asked for): the summary counted it as a reject - in the reject bin
    - which it may not be. It gets its own line, and the right / mis-sorted / rejected shares are
    of the pieces whose bin is known."""
    from vs2t_edge.cli import main
    from vs2t_edge.sim import fake_devices

    _, _, work = demo_run
    copy = tmp_path / "demo"
    shutil.copytree(work, copy, ignore=shutil.ignore_patterns("journal.jsonl*", "labels.jsonl", "FAULT"))

    class AckLostGate(fake_devices.FakeGate):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            self.time_out_next(2)  # the first SORT and its retry: the piece's outcome is unknown

    monkeypatch.setattr(fake_devices, "FakeGate", AckLostGate)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["demo", "--workdir", str(copy), "--items", "3", "--arm", "fake", "--gate", "fake",
                     "--threads", "1", "--max-presses", "3", "--without-scene-model", "allow"])
    out = out.getvalue()
    assert code == 0, out
    finals = [r for r in read_records(copy / "journal.jsonl") if r["type"] == "final"]
    unknown = [f["item_id"] for f in finals if f["outcome"] == "unknown_outcome"]
    assert len(unknown) == 1 and len(finals) == 3, finals
    summary = json.loads((copy / "demo_summary.json").read_text())
    assert summary["outcome_unknown"] == unknown and summary["items"] == 3
    assert summary["all"]["n"] == 2  # the shares: of the pieces whose bin is known
    m = re.search(r"(\d+) pieces?: ([0-9.]+)% in the right bin", out)
    assert m and int(m.group(1)) == 2, out
    assert re.search(rf"outcome unknown: 1 piece \({unknown[0]}\)", out), out


def test_a_recorded_demo_keeps_its_journal_for_its_totals_and_label(demo_run, tmp_path):
    """`demo --record` journalled into the recording's own journal and deleted it: the totals read
    the demo's journal, absent, and printed "0 label(s) taught the cell" under labels that had
    taught it, and the journal the last line named was not there for `vs2t-edge label --list`."""
    from vs2t_edge.cli import main

    _, _, cached = demo_run
    work = tmp_path / "work"
    shutil.copytree(cached, work)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["demo", "--workdir", str(work), "--items", "6", "--arm", "fake", "--gate", "fake",
                     "--threads", "1", "--max-presses", "3", "--without-scene-model", "allow",
                     "--record", str(tmp_path / "s.replay")])
    assert code == 0, out.getvalue()
    assert (tmp_path / "s.replay" / "index.json").is_file() and (work / "journal.jsonl").is_file()
    applied = sum(bool(r.get("applied")) for r in read_records(work / "journal.jsonl") if r["type"] == "label")
    summary = json.loads((work / "demo_summary.json").read_text())
    assert summary["labels_applied"] == applied
    assert sum(r["type"] == "final" for r in read_records(work / "journal.jsonl")) == 6


def test_the_fault_at_option_and_the_faults_words_number_as_the_printout(demo_run):
    """`--fault-at ITEM:PRESS` took ITEM 0-based while the printout names pieces item-0001 on, and the
    fault said "during press 0" of the press the option called 1 (the cell named a press by its
    0-based point): both are 1-based now, as the printout's pieces and press counts."""
    code, out, work = demo_run
    fault = next(r for r in read_records(work / "journal.jsonl") if r["type"] == "fault")
    assert "(item-0003): arm safety stop during press 1 at" in fault["reason"], fault["reason"]
    assert "item-0003" in next(line for line in out.splitlines() if "FAULT latched" in line)

"""int8 against fp32 over several training runs (bench/verdict.py ``over_runs``): one run's pair is
one split's noise, so a recipe benched on several runs is judged on the mean of their differences -
grouped by trunk, size and export recipe, never across them."""

from __future__ import annotations

import numpy as np
import pytest

from vs2t_edge.bench import verdict as bench
from vs2t_edge.bench.report import render_over_runs


def row(prec, run, press_h, extra="", arch="lite0", command=None):
    bins = {"all": {"right": 70.0, "mis-sort": 0.5}}
    cmd = command if command is not None else (
        f"vs2t-edge export {run} --out B/{run}_{prec}" + (" --trunk-precision int8" + extra if prec == "int8" else ""))
    made_by = {"command": cmd, "run": f"/data/runs/{run}"}
    return {"name": f"{run}_{prec}{extra.replace(' ', '')}{arch}", "precision": prec, "arch": arch, "size_px": 128,
            "run": run, "split": True, "made_by": made_by,
            "latency": {"2": {"p50_ms": 2.0 if prec == "fp32" else 1.0}},
            "accuracy": {"press": {"H": press_h, "zsl": 30.0, "acc_t": 80.0}, "items": {"5": {"H": 40.0}},
                         "sequential": {"H": 40.0}, "press_scene": {"H": 45.0},
                         "bins": {"scene_model": bins, "router": bins}}}


def test_the_recipe_is_the_export_command_less_run_and_out():
    r = bench.recipe
    assert r({"command": "/v/bin/vs2t-edge export runs/s1 --out B/s1_int8 --trunk-precision int8",
              "run": "/data/runs/s1"}) == "--trunk-precision int8"
    # the run anywhere (named by the manifest's run folder), --out=, a quoted path with a space
    assert r({"command": "vs2t-edge export --trunk-precision int8 runs/s0 --out=B/x --int8-float-auto 8",
              "run": "/data/runs/s0"}) == "--trunk-precision int8 --int8-float-auto 8"
    assert r({"command": "vs2t-edge export 'my runs/s2' --out B/y --trunk-precision int8 --size 128",
              "run": "/data/my runs/s2"}) == "--trunk-precision int8 --size 128"
    assert r({"command": "vs2t-edge export r --out B/z", "run": "/x/r"}) == ""  # fp32 at every default
    # the run named through a link (the manifest records the folder it points to): the bare word first
    assert r({"command": "vs2t-edge export paper --out B/p --trunk-precision int8", "run": "/x/paper90"}) \
        == "--trunk-precision int8"
    # recorded unquoted before 2026-11-29: an apostrophe in a path must not crash the bench
    assert r({"command": "vs2t-edge export bob's_run --out B/w --trunk-precision int8",
              "run": "/x/bob's_run"}) == "--trunk-precision int8"
    assert r({}) == "?" and r({"command": "python -m vs2t_edge.export.cli r --out B"}) == "?"
    assert r({"command": "vs2t-edge export r", "run": "/x/r"}) == "?"  # not a command export ran (no --out)


def test_int8_is_judged_on_the_mean_over_runs_when_a_recipe_was_benched_on_several():
    """Three runs, each exported fp32 and int8 with one recipe: one run's int8 loses 1.9 points of
    the router's H (that pair fails the target), the mean over the three loses 0.3 (the recipe meets
    it, and is recommended on the mean, said so). A second recipe benched on one run only gets no
    over-runs row and keeps its pair's verdict."""
    rows = [row("fp32", "s0", 40.0), row("int8", "s0", 38.1), row("fp32", "s1", 40.0), row("int8", "s1", 40.3),
            row("fp32", "s2", 40.0), row("int8", "s2", 40.6), row("int8", "s0", 37.0, " --int8-float-auto 8")]
    comps = bench.compare_pairs(rows)
    assert len(comps) == 4 and [c["within_1_point"] for c in comps] == [False, True, True, False]
    (o,) = bench.over_runs(comps)
    assert (o["recipe"], o["arch"], o["size_px"], o["runs"]) == ("--trunk-precision int8", "lite0", 128, 3)
    h = o["delta_points"]["press_H"]
    assert h["runs"] == pytest.approx([-1.9, 0.3, 0.6]) and h["mean"] == pytest.approx(-1 / 3)
    assert h["se"] == pytest.approx(np.std([-1.9, 0.3, 0.6], ddof=1) / np.sqrt(3))
    assert o["cost_points"]["press_H"] == pytest.approx(1 / 3) and o["within_1_point"] and o["cell_within_1_point"]
    result = {"machine": {}, "variants": [], "comparisons": comps, "int8_over_runs": [o]}
    over = [t for t in bench.targets(result) if "mean over runs" in t["target"]]
    assert len(over) == 1 and over[0]["met"] and "3 runs" in over[0]["variant"]
    rec = {r["int8"]: r for r in bench.recommend(result)}
    assert rec["s0_int8lite0"]["recommended"] == "s0_int8lite0" and "mean over 3 runs" in rec["s0_int8lite0"]["why"]
    # the one-run recipe: judged on its own pair, whose router loses 3 points (the scene model none)
    one = rec["s0_int8--int8-float-auto8lite0"]["why"]
    assert "loses 3.0 (press_H: -3.0)" in one and "mean over" not in one
    table = render_over_runs(result)
    assert "-0.3 ± 0.8" in table and "-1.9 / +0.3 / +0.6" in table and "within 1 point" in table
    # the mean fails when it loses more than 1
    rows[3]["accuracy"]["press"]["H"] = 37.0
    (o,) = bench.over_runs(bench.compare_pairs(rows))
    assert not o["within_1_point"] and o["cost_points"]["press_H"] == pytest.approx((1.9 + 3.0 - 0.6) / 3)


def test_runs_of_other_trunks_or_without_a_recipe_are_never_pooled():
    """A lite0 run and a resnet50 run exported the same way are two groups of one run (no row);
    bundles whose command says no export recipe join no group."""
    rows = [row("fp32", "s0", 40.0), row("int8", "s0", 38.1), row("fp32", "s1", 40.0, arch="resnet50"),
            row("int8", "s1", 40.3, arch="resnet50")]
    assert bench.over_runs(bench.compare_pairs(rows)) == []
    rows = [row("fp32", "s0", 40.0, command=""), row("int8", "s0", 38.1, command=""),
            row("fp32", "s1", 40.0, command=""), row("int8", "s1", 40.3, command="")]
    comps = bench.compare_pairs(rows)
    assert [c["recipe"] for c in comps] == ["?", "?"] and bench.over_runs(comps) == []

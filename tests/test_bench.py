"""`vs2t-edge bench` on two real (tiny) bundles of one run: the table, JSON and plot are written,
every number a user reads is there and sane, int8 is paired with its fp32, and the targets are
judged from the measurements."""

from __future__ import annotations

import json
import math

import pytest

pytest.importorskip("torch")
pytest.importorskip("onnx")

from test_export import tiny_run  # noqa: F401,E402  (the module-scoped run-folder fixture)


@pytest.fixture(scope="module")
def bench_result(tiny_run, tmp_path_factory):  # noqa: F811
    from vs2t_edge.export import export as ex
    from vs2t_edge.runtime import bench

    run, _ = tiny_run
    root = tmp_path_factory.mktemp("bench")
    bundles = []
    for prec in ("fp32", "int8"):
        ex.export_run(run, root / f"tiny_{prec}", trunk_precision=prec, calibration_frames=16)
        bundles.append(root / f"tiny_{prec}")
    out = root / "results"
    result = bench.run_bench(bundles, out, threads=(1, 2), budget_s=0.2, n_items=4, cap=3, log=lambda m: None)
    return result, out


def test_bench_writes_table_json_and_plot(bench_result):
    result, out = bench_result
    assert json.loads((out / "bench.json").read_text())["variants"][0]["name"] == "tiny_fp32"
    md = (out / "bench.md").read_text()
    for heading in ("## Variants", "## Outside the trunk", "## int8 against fp32", "## Against the targets"):
        assert heading in md
    assert (out / "pareto.png").stat().st_size > 1000
    assert "## How each bundle was made (from its manifest)" in md


def test_bench_rewrite_keeps_the_hand_written_tail_and_records_provenance(bench_result, tmp_path):
    from vs2t_edge.runtime import bench

    result, out = bench_result
    made = result["variants"][0]["made_by"]
    assert made["git_commit"] and made["router"] and "command" in made  # from the bundle's manifest
    md = tmp_path / "bench.md"
    md.write_text("old generated text\n" + bench.HAND_WRITTEN + "\n\n## Notes\n\nkept\n")
    md.write_text(bench.render_markdown(result) + bench.hand_written_tail(md))
    text = md.read_text()
    assert "old generated text" not in text and text.endswith("## Notes\n\nkept\n")
    assert text.count(bench.HAND_WRITTEN) == 1 and "## How each bundle was made" in text
    md.write_text("no marker here\n")
    assert bench.hand_written_tail(md) == ""  # nothing marked: nothing kept


def test_bench_numbers_are_measured_and_sane(bench_result):
    from vs2t_edge.runtime import bench

    result, _ = bench_result
    for r in result["variants"]:
        for t in ("1", "2"):
            lat = r["latency"][t]
            assert 0 < lat["p50_ms"] <= lat["p99_ms"] < 1000 and lat["runs"] >= 3
        o = r["overhead_ms"]
        assert o["cell"] == pytest.approx(sum(o[k] for k in ("preprocess", "heads", "router", "decision", "evidence")))
        assert o["decode"] > 0 and r["peak_rss_mb"] > result["baseline_rss_mb"] > 0
        assert 0 < r["fraction_of_peak"]["2"] and r["macs"] > 0
        a = r["accuracy"]
        for v in (a["press"]["zsl"], a["press"]["H"], a["sequential"]["H"], *(a["items"][str(k)]["H"] for k in bench.ITEM_PRESSES)):
            assert 0.0 <= v <= 100.0 or math.isnan(v)
        assert 1.0 <= a["sequential"]["presses_mean"] <= 9.0
    (pair,) = result["comparisons"]
    assert pair["int8"] == "tiny_int8" and pair["fp32"] == "tiny_fp32" and pair["speedup_2t"] > 0
    assert pair["within_1_point"] == all(abs(v) <= 1.0 for v in pair["delta_points"].values())


def test_targets_follow_the_measurements(bench_result):
    from vs2t_edge.runtime import bench

    result, _ = bench_result
    rows = bench.targets(result)
    cell = {t["variant"]: t for t in rows if "outside the trunk" in t["target"]}
    for r in result["variants"]:
        assert cell[r["name"]]["met"] == (r["overhead_ms"]["cell"] < bench.TARGET_CELL_MS)
    # a ResNet50 row is judged against its compute limit
    fake = json.loads(json.dumps(result))
    v = fake["variants"][0]
    v.update(arch="resnet50", limit_ms={"2": 10.0}, latency={**v["latency"], "2": {"p50_ms": 12.4, "p99_ms": 13.0, "runs": 5}})
    (limit_row,) = [t for t in bench.targets(fake) if "compute limit" in t["target"]]
    assert limit_row["met"] and "1.24x" in limit_row["measured"]
    v["latency"]["2"]["p50_ms"] = 12.6
    assert not [t for t in bench.targets(fake) if "compute limit" in t["target"]][0]["met"]

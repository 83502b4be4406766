"""The bench's verdict on what it measured (bench/measure.py): int8 against fp32 of the same run
(``compare_pairs``: speed-up, the difference on every accuracy, what each costs), the precision
it recommends on the machine it ran on (``recommend``), and where each variant stands against the
targets of issue 14 (``targets``). Pure functions of the measured rows: a bench.json can be
judged again without measuring (the committed one was, when the advice for format-3 pairs
changed)."""

from __future__ import annotations

import math
import shlex
from pathlib import Path

import numpy as np

from vs2t_edge.bench.press_timing import DECODE_LABEL, decode_key

MIN_INT8_SPEEDUP = 1.2  # below this, int8's accuracy cost buys too little time to recommend it
# what a format-3 bundle's cell decides with (its press runs no router): the scene model per press
# and per item by bins. The router's columns still count for the int8 target, not for the advice.
CELL_MEASURES = ("scene_press_H", "bins_right_scene_model", "bins_mis_sort_scene_model")


def recommend(result: dict) -> list[dict]:
    """Per fp32/int8 pair measured in this run: the precision to deploy on this machine. int8 when
    it is at least ``MIN_INT8_SPEEDUP`` x faster (2 threads) and loses at most ``TARGET_INT8_POINTS``
    against fp32 on every measure the bench took (``cost_points``); else fp32, saying why. For a
    pair of format-3 bundles (no router on the cell's press) "every measure" is every measure of
    what the cell decides with (``CELL_MEASURES``), and the advice says what the router loses.
    When the pair's recipe was benched on several runs (``result["int8_over_runs"]``), its accuracy
    is judged on the mean over those runs, which one split's noise does not decide."""
    out = []
    isa = result.get("machine", {}).get("instruction_sets", {})
    vnni = isa.get("avx512_vnni") or isa.get("avx_vnni")
    groups = result.get("int8_over_runs", [])
    for c in result.get("comparisons", []):
        o = next((g for g in groups if [c["int8"], c["fp32"]] in g["pairs"]), None)  # a group this pair is in
        judged = o or c
        over = f" (mean over {o['runs']} runs)" if o else ""
        fast = c["speedup_2t"] >= MIN_INT8_SPEEDUP
        cell_only = "cell_within_1_point" in judged and not judged.get("within_1_point")
        accurate = judged["cell_within_1_point"] if cell_only else judged.get("within_1_point")
        cost = judged.get("cost_points")
        worst = max(cost.items(), key=lambda kv: kv[1]) if cost else None
        delta = (lambda k: o["delta_points"][k]["mean"]) if o else (lambda k: c["delta_points"][k])
        if fast and accurate and cell_only:
            pick, why = c["int8"], (f"{c['speedup_2t']:.2f}x faster and within {TARGET_INT8_POINTS:g} point{over} on every "
                                    f"accuracy of what the cell decides with (the scene model: {', '.join(CELL_MEASURES)}); "
                                    f"the router, which a format-3 bundle's press never runs, loses {worst[1]:.1f} "
                                    f"({worst[0]}: {delta(worst[0]):+.1f})")
        elif fast and accurate:
            pick, why = c["int8"], (f"{c['speedup_2t']:.2f}x faster and within {TARGET_INT8_POINTS:g} point{over} on "
                                    "every accuracy")
        elif not fast:
            pick, why = c["fp32"], (f"int8 only {c['speedup_2t']:.2f}x faster here (< {MIN_INT8_SPEEDUP}x"
                                    f"{'' if vnni else '; this CPU has no VNNI'})")
        elif accurate is None:
            pick, why = c["fp32"], "int8's accuracy was not measured (trained bundles with --dataset measure it)"
        else:
            pick, why = c["fp32"], (f"int8 {c['speedup_2t']:.2f}x faster but costs {worst[1]:.1f} points{over} "
                                    f"({worst[0]}: {delta(worst[0]):+.1f}), more than {TARGET_INT8_POINTS:g}")
        out.append({"fp32": c["fp32"], "int8": c["int8"], "recommended": pick, "why": why})
    return out


def cost_points(delta_points: dict[str, float]) -> dict[str, float]:
    """What int8 costs on each measure, in points (int8 - fp32 signed so that a loss is positive):
    less accuracy, or more mis-sorts. A gain costs nothing: "int8 within 1 point of fp32" asks
    that it lose at most 1 point anywhere, not that it never do better."""
    return {k: (v if "mis_sort" in k else -v) for k, v in delta_points.items()}


def compare_pairs(rows: list[dict]) -> list[dict]:
    """int8 vs fp32 of the same trunk, size and run: speed-up and accuracy difference."""
    out = []
    for r8 in rows:
        if r8["precision"] != "int8":
            continue
        for r32 in rows:
            if (r32["precision"] == "fp32" and r32["arch"] == r8["arch"] and r32["size_px"] == r8["size_px"]
                    and r32.get("run") == r8.get("run")):
                t = max(set(r32["latency"]) & set(r8["latency"]), key=int)  # 2 threads unless --threads says
                c = {"int8": r8["name"], "fp32": r32["name"], "run": r8.get("run"), "arch": r8["arch"],
                     "size_px": r8["size_px"], "recipe": recipe(r8.get("made_by") or {}),
                     "speedup_2t": r32["latency"][t]["p50_ms"] / r8["latency"][t]["p50_ms"]}
                if "accuracy" in r8 and "accuracy" in r32:
                    a8, a32 = r8["accuracy"], r32["accuracy"]
                    c["delta_points"] = {"press_H": a8["press"]["H"] - a32["press"]["H"],
                                         "press_zsl": a8["press"]["zsl"] - a32["press"]["zsl"],
                                         "press_acc_t": a8["press"]["acc_t"] - a32["press"]["acc_t"],
                                         "item5_H": a8["items"]["5"]["H"] - a32["items"]["5"]["H"],
                                         "sequential_H": a8["sequential"]["H"] - a32["sequential"]["H"]}
                    if "press_scene" in a8 and "press_scene" in a32:  # the cell's own per-press decision
                        c["delta_points"]["scene_press_H"] = a8["press_scene"]["H"] - a32["press_scene"]["H"]
                    for name in ("scene_model", "router"):  # per item, by bins: right bin, and mis-sorts
                        b8, b32 = a8.get("bins", {}).get(name), a32.get("bins", {}).get(name)
                        if b8 and b32:
                            c["delta_points"][f"bins_right_{name}"] = b8["all"]["right"] - b32["all"]["right"]
                            c["delta_points"][f"bins_mis_sort_{name}"] = b8["all"]["mis-sort"] - b32["all"]["mis-sort"]
                    # format 3 on both sides: no router on the cell's press
                    c.update(_judge(c["delta_points"], bool(r8.get("split") and r32.get("split"))))
                out.append(c)
    return out


def _judge(delta: dict[str, float], format_3: bool) -> dict:
    """The int8 target on differences (int8 - fp32, points): what each costs (``cost_points``),
    ``within_1_point`` on every measure, and for format-3 bundles ``cell_within_1_point`` on what
    the cell decides with (``CELL_MEASURES``, when all were measured)."""
    cost = cost_points(delta)
    out = {"cost_points": cost, "within_1_point": all(v <= TARGET_INT8_POINTS for v in cost.values())}
    cell = {k: v for k, v in cost.items() if k in CELL_MEASURES}
    if format_3 and set(cell) == set(CELL_MEASURES):
        out["cell_within_1_point"] = all(v <= TARGET_INT8_POINTS for v in cell.values())
    return out


def recipe(made_by: dict) -> str:
    """How a bundle was exported, without the run it was made from: its export command's words
    after ``export``, less ``--out`` and its value and less the run folder (the word naming
    ``made_by["run"]``, wherever it stands): ``vs2t-edge export RUN --out B --trunk-precision int8``
    -> ``--trunk-precision int8``, so that bundles of several runs made the same way are one recipe.
    "?" when the command is not an export's (no ``export`` word, no ``--out``). Read from the words,
    not export's parser: the bench does not import export (docs/ARCHITECTURE.md)."""
    command = made_by.get("command") or ""
    try:
        words = shlex.split(command)
    except ValueError:  # an unbalanced quote in a path: commands were recorded unquoted until 2026-11-29
        words = command.split()
    if "export" not in words:
        return "?"
    words = words[words.index("export") + 1:]
    run = Path(str(made_by.get("run") or "")).name
    bare = [i for i, w in enumerate(words) if not w.startswith("-")]
    # the run folder: the word naming it, else the first bare word that is no option's value (a
    # link's name differs from the folder it points to); a word missed keeps its runs apart
    at = next((i for i in bare if run and Path(words[i]).name == run), None)
    if at is None:
        at = next((i for i in bare if i == 0 or not words[i - 1].startswith("-") or "=" in words[i - 1]), None)
    said, out, skip = [], False, False
    for i, w in enumerate(words):
        if skip:
            skip = False
        elif w == "--out":
            out = skip = True
        elif w.startswith("--out="):
            out = True
        elif i != at:
            said.append(w)
    return " ".join(said) if out else "?"


def over_runs(comparisons: list[dict]) -> list[dict]:
    """int8 against fp32 over several runs, one recipe at a time: one run's pair is one split's five
    untouched fabrics, whose noise is as large as the 1-point target (bench.md's paired intervals);
    the mean over runs, with its standard error, is the price a user pays on average. A recipe
    (``recipe``) benched on fewer than two runs gets no row. Per measure: the runs' deltas, their
    mean, sd and standard error; ``cost_points`` of the means; ``within_1_point`` judges the means."""
    groups: dict[tuple, dict[str, dict]] = {}
    for c in comparisons:  # one trunk, size and recipe a group; a bundle that says no recipe joins none
        if c.get("delta_points") and c.get("run") and c.get("recipe", "?") != "?":
            groups.setdefault((c.get("arch"), c.get("size_px"), c["recipe"]), {}).setdefault(c["run"], c)
    out = []
    for (arch, size_px, rec), by_run in groups.items():
        if len(by_run) < 2:
            continue
        cs = list(by_run.values())
        keys = [k for k in cs[0]["delta_points"] if all(k in c["delta_points"] for c in cs)]
        per = {}
        for k in keys:
            v = np.array([c["delta_points"][k] for c in cs], float)
            sd = float(v.std(ddof=1))
            per[k] = {"runs": [float(x) for x in v], "mean": float(v.mean()), "sd": sd, "se": sd / math.sqrt(len(v))}
        out.append({"recipe": rec, "arch": arch, "size_px": size_px, "runs": len(cs),
                    "pairs": [[c["int8"], c["fp32"]] for c in cs],
                    "speedup_2t": float(np.mean([c["speedup_2t"] for c in cs])), "delta_points": per,
                    **_judge({k: p["mean"] for k, p in per.items()}, all("cell_within_1_point" in c for c in cs))})
    return out


# The targets (benchmarked, not timed tests).
TARGET_OF_LIMIT = 1.25  # the ResNet50 trunk within 1.25x of this CPU's compute limit, batch 1, 2 threads
TARGET_CELL_MS = 1.0  # p50, everything per press outside the trunk: decode (MJPEG), frame checks, preprocess, heads,
TARGET_CELL_P99_MS = 2.0  # router, decision, evidence (issue 14: <= 1 ms p50, < 2 ms p99 at 2 threads)
TARGET_INT8_POINTS = 1.0  # int8 within 1 point of fp32 accuracy


def targets(result: dict) -> list[dict]:
    """Where each variant stands against the targets: one row per (variant, target)."""
    rows = []
    for r in result["variants"]:
        if r["arch"] == "resnet50" and r.get("limit_ms", {}).get("2"):
            ratio = r["latency"]["2"]["p50_ms"] / r["limit_ms"]["2"]
            rows.append({"variant": r["name"], "target": f"trunk p50 (2 threads) <= {TARGET_OF_LIMIT}x compute limit",
                         "measured": f"{r['latency']['2']['p50_ms']:.1f} ms = {ratio:.2f}x the {r['limit_ms']['2']:.1f} ms limit",
                         "met": ratio <= TARGET_OF_LIMIT})
        o = r["overhead_ms"]
        cell = o.get("cell")
        dk = decode_key(o)
        if cell is not None and dk is not None:
            t = max(r.get("press", {"2": None}), key=int)
            rest, p99 = cell - o[dk], r.get("overhead_p99_ms", {}).get("cell", math.nan)
            met = cell <= TARGET_CELL_MS and p99 < TARGET_CELL_P99_MS
            miss = "" if cell <= TARGET_CELL_MS else (
                f"; p50 misses by {cell - TARGET_CELL_MS:.2f} ms" + (
                    " (decode alone takes the budget)" if o[dk] >= TARGET_CELL_MS
                    else " even without decode" if rest >= TARGET_CELL_MS else ", met without decode"))
            if not p99 < TARGET_CELL_P99_MS:
                miss += f"; p99 over {TARGET_CELL_P99_MS:g} ms"
            # the target is on MJPEG frames: a YUYV run says which frames it met it on
            frames = " on uncompressed YUYV frames (the issue's target is on MJPEG)" if dk == "decode_yuyv" else ""
            rows.append({"variant": r["name"],
                         "target": f"per press outside the trunk, decode included, p50 <= {TARGET_CELL_MS:g} ms and "
                                   f"p99 < {TARGET_CELL_P99_MS:g} ms ({t} threads){frames}",
                         "measured": f"{cell:.2f} ms = {DECODE_LABEL[dk]} {o[dk]:.2f} + the rest {rest:.2f}"
                                     f" (p99 {p99:.2f}){miss}",
                         "met": met})
        elif cell is not None:  # a bench.json from before decode was timed: the rest only
            rows.append({"variant": r["name"], "target": f"per press outside the trunk, decode NOT included, "
                                                         f"<= {TARGET_CELL_MS:g} ms",
                         "measured": f"{cell:.2f} ms", "met": cell <= TARGET_CELL_MS})
    for c in result.get("comparisons", []):
        if c.get("cost_points"):
            worst = max(c["cost_points"].items(), key=lambda kv: kv[1])
            rows.append({"variant": c["int8"], "target": f"int8 loses at most {TARGET_INT8_POINTS:g} point against "
                                                         f"{c['fp32']} on every measure",
                         "measured": f"largest loss {worst[1]:.1f} points ({worst[0]}: {c['delta_points'][worst[0]]:+.1f})",
                         "met": c["within_1_point"]})
    for o in result.get("int8_over_runs", []):
        worst = max(o["cost_points"].items(), key=lambda kv: kv[1])
        d = o["delta_points"][worst[0]]
        rows.append({"variant": f"{o['arch']} {o['size_px']} px int8 `{o['recipe']}`, {o['runs']} runs",
                     "target": f"int8 loses at most {TARGET_INT8_POINTS:g} point against fp32 on every measure, "
                               "mean over runs",
                     "measured": f"largest mean loss {worst[1]:.1f} points ({worst[0]}: {d['mean']:+.1f} ± {d['se']:.1f} "
                                 "standard error)", "met": o["within_1_point"]})
    return rows

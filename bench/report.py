"""The bench's pages (`vs2t-edge bench --out`): the printed table, bench.md with its hand-written
tail kept, the per-item-by-bins table and the Pareto plot, from a result of runtime/bench.py."""

from __future__ import annotations

import math
from pathlib import Path

from vs2t_edge.bench.press_timing import DECODE_LABEL, DECODE_STAGE, decode_key
from vs2t_edge.bench.measure import (JPEG_QUALITY, SEQ_CONFIDENCE, SEQ_MAX_PRESSES, BIN_SCENES, BIN_MAX_PRESSES, ITEM_PRESSES, targets)
from vs2t_edge.runtime.files import portable


def _f(v, fmt="{:.1f}") -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v)


def render_table(result: dict) -> str:
    hdr = ("| variant | trunk | px | prec | MMAC | p50 1t | p99 1t | p50 2t | p99 2t | limit 2t | of peak 2t "
           "| press p50 1t | press p99 1t | press p50 2t | press p99 2t "
           "| outside trunk | RSS MB | bundle MB | ZSL/press | H/press | scene H/press | H 1 | H 3 | H 5 | H 9 | seq presses "
           "| seq H | seq unknown |")
    lines = [hdr, "|" + "---|" * (hdr.count("|") - 1)]
    for r in result["variants"]:
        a = r.get("accuracy")
        lat = r["latency"]
        acc = ["–"] * 10
        if a:
            acc = [_f(a["press"]["zsl"]), _f(a["press"]["H"]), _f(a.get("press_scene", {}).get("H"))] + [
                _f(a["items"][str(k)]["H"]) for k in ITEM_PRESSES] + [
                _f(a["sequential"]["presses_mean"], "{:.2f}"), _f(a["sequential"]["H"]), _f(a["sequential"]["unknown"])]
        elif not r["trained"]:
            acc = ["untrained"] + ["–"] * 9
        lines.append("| " + " | ".join([
            r["name"], r["arch"], str(r["size_px"]), r["precision"], _f((r["macs"] or math.nan) / 1e6, "{:.0f}"),
            _f(lat.get("1", {}).get("p50_ms"), "{:.2f}"), _f(lat.get("1", {}).get("p99_ms"), "{:.2f}"),
            _f(lat.get("2", {}).get("p50_ms"), "{:.2f}"), _f(lat.get("2", {}).get("p99_ms"), "{:.2f}"),
            _f(r.get("limit_ms", {}).get("2"), "{:.2f}"), _f(r.get("fraction_of_peak", {}).get("2"), "{:.0%}"),
            *(_f(r.get("press", {}).get(t, {}).get(q), "{:.2f}") for t in ("1", "2") for q in ("p50_ms", "p99_ms")),
            _f(r["overhead_ms"].get("cell", r["overhead_ms"].get("total")), "{:.2f}"), _f(r["peak_rss_mb"], "{:.0f}"),
            _f(r["bundle_mb"], "{:.1f}"),
            *acc]) + " |")
    return "\n".join(lines)


def render_bins(result: dict) -> str:
    """Per item, by bins (``by_bins``): one row per variant and decision; empty without accuracies."""
    rows = [(r["name"], name, {**b[name], "pieces_per_min": b.get("pieces_per_min", {}).get(name, {})})
            for r in result["variants"] for b in [r.get("accuracy", {}).get("bins", {})]
            for name in ("scene_model", "scene_model_labels", "scene_model_teach", "router") if name in b]
    if not rows:
        return ""
    lines = ["| variant | decision | right bin | mis-sort | reject | touched right | untouched right "
             "| off-scene rejected | presses | pieces/min, scored after each press | pieces/min, overlapped |",
             "|" + "---|" * 11]
    for name, decision, b in rows:
        kind = lambda k, o: _f(b.get(k, {}).get(o))  # noqa: E731
        ppm = b.get("pieces_per_min", {})
        said = {"scene_model": "scene decision", "scene_model_labels": "scene decision + operator labels (not zero-shot)",
                "scene_model_teach": "scene decision + operator labels + a teach piece of each untouched fabric "
                                     "(not zero-shot)",
                "router": "router, confidence 0.95"}[decision]
        lines.append(f"| {name} | {said} | "
                     f"{kind('all', 'right')} | {kind('all', 'mis-sort')} | {kind('all', 'reject')} | "
                     f"{kind('touched', 'right')} | {kind('untouched', 'right')} | {kind('off-scene', 'right')} | "
                     f"{_f(b['all'].get('presses'), '{:.2f}')} | {_f(ppm.get('sequential'), '{:.2f}')} | "
                     f"{_f(ppm.get('overlapped'), '{:.2f}')} |")
    return "\n".join(lines)


def arm_times_line(result: dict) -> str:
    """What the pieces-per-minute columns assumed of the arm, or how to get them."""
    arm = result.get("arm_times")
    if not arm:
        return ("Pieces per minute: not computed - give `--arm-times FILE`, the JSON of "
                "`python -m vs2t_edge.sim.ursim --bench 9 --json FILE` (the simulated UR5) or the same on a robot.")
    return (f"Pieces per minute with the arm's measured times per press (medians: to above the point "
            f"{arm['move_above_s']:.2f} s, press {arm['press_s']:.2f} s, lift {arm['retract_s']:.2f} s) and each "
            "variant's whole press (p50, most threads): scored after each press (the arm waits for the score), and "
            "overlapped with the lift (runtime/press_pipeline.py: the arm never waits; a score slower than the lift "
            "costs one speculative press per piece). A piece's own overheads (reference frame, gate) are left out.")


HAND_WRITTEN = "<!-- hand-written below: kept when `vs2t-edge bench --out` rewrites this file -->"


def hand_written_tail(md: Path) -> str:
    """The part of an existing bench.md below the marker (notes people added), to keep on rewrite."""
    try:
        text = md.read_text(encoding="utf-8")
    except OSError:
        return ""
    _, marker, tail = text.partition(HAND_WRITTEN)
    return f"\n{HAND_WRITTEN}{tail}" if marker else ""


def render_made_by(result: dict) -> list[str]:
    rows = [r for r in result["variants"] if r.get("made_by")]
    if not rows:
        return []
    lines = ["", "## How each bundle was made (from its manifest)", "",
             "| variant | command | commit | dataset | router |", "|---|---|---|---|---|"]
    for r in rows:
        mb = r["made_by"]
        lines.append(f"| {r['name']} | `{portable(str(mb.get('command', '?')))}` | {str(mb.get('git_commit', '?'))[:12]} | "
                     f"{portable(str(mb.get('dataset', '–')))} | {mb.get('router', '?')} |")
    return lines


def _isa_text(machine: dict) -> str:
    isa = machine.get("instruction_sets")
    if not isa:
        return "not recorded"
    return ", ".join(f"{k} {'yes' if v else 'no'}" for k, v in isa.items())


def _recommendation_lines(result: dict) -> list[str]:
    recs = result.get("recommendation") or []
    return ["", "**Recommended precision on this machine:** " + "; ".join(
        f"{r['recommended']} ({r['why']})" for r in recs)] if recs else []


def _decode_label(result: dict) -> str:
    """What the run's decode stage is called: the camera's format (``--camera-format``)."""
    return DECODE_LABEL[DECODE_STAGE.get(result.get("camera_format", "mjpeg"), "decode_mjpeg")]


# the int8-minus-fp32 measures the tables show, and their labels (verdict.compare_pairs' keys)
INT8_MEASURES = (("press_acc_t", "press acc_t"), ("press_H", "press H"), ("press_zsl", "press ZSL"),
                 ("scene_press_H", "scene press H"), ("item5_H", "item-5 H"), ("sequential_H", "seq H"),
                 ("bins_right_scene_model", "right bin (scene)"), ("bins_mis_sort_scene_model", "mis-sort (scene)"))


def render_markdown(result: dict) -> str:
    m, pk = result["machine"], result["peak"]
    lines = ["# Speed for accuracy: the bench", "",
             f"Measured {result['time_utc']} on {m['cpu']} ({m['cores']} cores; load average at start "
             f"{', '.join(f'{v:.2f}' for v in m['load_avg_at_start'])}"
             f"{'' if m['load_avg_at_start'][0] < 0.5 else ': the machine was busy, latencies are pessimistic'}"
             f"{'; at the end, with the bench itself, ' + ', '.join(f'{v:.2f}' for v in m['load_avg_at_end']) if 'load_avg_at_end' in m else ''}), onnxruntime "
             f"{m['onnxruntime']}, {result['seconds']:.0f} s. Latencies are medians (p50) and p99 of the trunk alone "
             f"at batch 1, and of the whole press (*press*: {_decode_label(result)} to evidence update, end to end); ratios below are from this one run. `vs2t-edge bench` wrote this file, bench.json and pareto.png.",
             "", f"Instruction sets: {_isa_text(m)}; onnxruntime build: {m.get('onnxruntime_build') or '?'} "
             f"({', '.join(m.get('onnxruntime_providers', [])) or '?'}).",
             *_recommendation_lines(result),
             "", "## Compute peak of this machine", "",
             "| precision | 1 thread | 2 threads | how |", "|---|---|---|---|"]
    for p in ("fp32", "int8"):  # the thread counts timed (--threads), '–' for the others
        gmacs = [_f(pk[p][t]["macs_per_s"] / 1e9) + " GMAC/s" if t in pk[p] else "–" for t in ("1", "2")]
        how = pk[p][max(pk[p], key=int)]["how"] if pk[p] else "–"
        lines.append(f"| {p} | {gmacs[0]} | {gmacs[1]} | {how}, fastest of 15 |")
    lines += ["", "limit = MACs per frame (counted from the graph) / peak; *of peak* = limit / measured p50.", "",
              "## Variants", "", render_table(result), "",
              *(["## Per item, by bins", "",
                 f"Scenes of 5 touched + 3 untouched bundle classes ({BIN_SCENES} per bundle), off-scene pieces of the "
                 f"classes a scene leaves out; items of at most {BIN_MAX_PRESSES} presses drawn from presses never "
                 "trained on, decided by the cell's own evidence (runtime/sorting.py, as the demo and training's report "
                 "count). *scene decision*: the bundle's scene model at its operating point; *+ operator labels*: "
                 "the same scenes as jobs of 4 pieces a fabric in a random order, every rejected piece labelled before "
                 "the next (runtime/feedback.py; not zero-shot); *+ a teach piece*: the same with one labelled piece of "
                 "each untouched fabric pressed before the job, not counted as a piece (its presses are in the pieces "
                 "per minute, not in *presses*); *router*: the GZSL "
                 "router's posterior, the cell's decision before it (the baseline). %.", "", render_bins(result), "",
                 arm_times_line(result), ""]
                if render_bins(result) else []),
              "Columns: *p50/p99 1t/2t* = trunk alone, ms, batch 1, 1 or 2 onnxruntime threads; *press p50/p99* = "
              "the whole press as the cell pays it, ms: decode of the camera's frame (" + (
                  "a UVC GelSight asked for uncompressed YUYV 4:2:2, devices.camera.pixel_format yuyv: the press frame "
                  "converted once to YUYV, its conversion to BGR at the bundle's scale timed"
                  if result.get("camera_format") == "yuyv" else
                  "a UVC GelSight streams MJPEG: the press frame encoded once as JPEG "
                  f"q={result.get('jpeg_quality', JPEG_QUALITY)}, cv2.imdecode timed") + ") + preprocess + trunk + heads + "
              "router + decision + evidence update, timed end to end per press; *outside trunk* = median over presses of "
              "(press - its own trunk run) at 2 threads, decode included: what the target (p50 <= 1 ms, p99 < 2 ms) is judged on (medians do "
              "not add: *press* p50 can exceed trunk p50 + outside p50, since a trunk run between other work wakes "
              "onnxruntime's thread pool instead of finding it spinning, as the trunk-alone loop does); RSS = "
              "peak resident memory of a process that "
              f"loaded the bundle and ran presses (a process importing the same modules and loading nothing peaks at "
              f"{result['baseline_rss_mb']:.0f} MB); accuracies in % on presses never used in training "
              f"(frames {result.get('accuracy_frames', 'lossless (the dataset PNG)')}); H = harmonic mean of "
              "acc_t and acc_u (per-class means) of the router's hard route at beta; *scene H/press* = the same for the "
              "bundle's scene model, one softmax over every bundle class (the cell's own per-press decision); "
              "*H k* = items of k presses, log posteriors summed; *seq* = sequential "
              f"rule (stop at posterior >= {SEQ_CONFIDENCE}, at most {SEQ_MAX_PRESSES} presses; unknown = reject bin, "
              "counted wrong).", "", "## Outside the trunk, per press (ms)", "",
              "Stage medians at 2 threads; *outside p50 / p99* = median / 99th percentile over presses of (press - its "
              "trunk run), decode included, at 1 and 2 threads (stage medians do not add up to it exactly). "
              f"*{_decode_label(result)}* at 1/reduce scale for a bundle on the reduced pixel path (runtime/preprocess.py); "
              "*frame checks* = the camera's frame guard and the press-frame contact check a UVC cell runs. "
              "*heads* = the second onnxruntime call of a two-graph bundle (format 1); *in graph* = what the heads and "
              "projections cost inside a fused bundle's one call (format 2; format 3's press graph of a scene decision "
              "has only the scene projection there, and no router stage: its heads run off the press path): that tail "
              "cut out of the press graph and "
              "timed right after each run of the trunk cut out of it (median; one session call more than the cell "
              "pays), added to its *outside* values, whose trunk is that cut-out trunk. "
              "*PNG decode* is what replays and the bench pay to read a recorded frame, not the camera: not in the totals.",
              "",
              f"| variant | frame px | {_decode_label(result)} | frame checks | preprocess | heads | in graph | router | decision "
              "| evidence "
              "| outside p50 1t | outside p99 1t | outside p50 2t | outside p99 2t | PNG decode (replays) |",
              "|" + "---|" * 15]
    for r in result["variants"]:
        o, pr = r["overhead_ms"], r.get("press", {})
        hw = r.get("frame_hw")
        scale = f" (decoded at 1/{r['decode_scale']})" if r.get("decode_scale", 1) != 1 else ""
        lines.append(f"| {r['name']} | {f'{hw[1]}x{hw[0]}{scale}' if hw else '–'} | " + " | ".join(
            [_f(o.get(k), "{:.3f}") for k in (decode_key(o) or "decode_mjpeg", "camera_checks", "preprocess", "heads",
                                              "in_graph", "router", "decision", "evidence")]
            + [_f(pr.get(t, {}).get(q), "{:.3f}") for t in ("1", "2") for q in ("outside_p50_ms", "outside_p99_ms")]
            + [_f(o.get("decode_png", o.get("decode")), "{:.3f}")]) + " |")
    tg = targets(result)
    if tg:
        lines += ["", "## Against the targets", "", "| variant | target | measured | met |", "|---|---|---|---|"]
        lines += [f"| {t['variant']} | {t['target']} | {t['measured']} | {'yes' if t['met'] else '**no**'} |" for t in tg]
    if result["comparisons"]:
        lines += ["", "## int8 against fp32", "",
                  "Δ = int8 - fp32, points. *largest loss*: the measure int8 loses most on (less accuracy, or more "
                  "mis-sorts by bins; a gain is no loss); *within 1 point*: it loses at most 1 point on every measure.", "",
                  "*press* columns: the router's hard route at beta (the paper's protocol); *scene press H*: the "
                  "bundle's scene model, one softmax over every bundle class, per press (what the cell decides with).", "",
                  "| int8 | fp32 | speed-up (2 threads) | " + " | ".join(f"Δ {label}" for _, label in INT8_MEASURES)
                  + " | largest loss | within 1 point |",
                  "|" + "---|" * 13]
        keys = tuple(k for k, _ in INT8_MEASURES)
        for c in result["comparisons"]:
            d, cost = c.get("delta_points"), c.get("cost_points") or {}
            worst = max(cost.items(), key=lambda kv: kv[1]) if cost else None
            lines.append(f"| {c['int8']} | {c['fp32']} | {c['speedup_2t']:.2f}x | " + (" | ".join(
                _f(d.get(k), "{:+.1f}") for k in keys) + f" | {f'{worst[1]:.1f} ({worst[0]})' if worst else '–'} | "
                f"{'yes' if c['within_1_point'] else 'no'} |" if d else " | ".join(["–"] * 10) + " |"))
        over = render_over_runs(result)
        if over:
            lines += ["", "### Over runs: int8 minus fp32, mean over each recipe's runs", "",
                      "One run's pair scores one split's held-out presses and five untouched fabrics; its noise is "
                      "about the size of the 1-point target (the paired intervals below). Each recipe benched on "
                      "several runs (bundles of several `train --seed S` runs, each exported fp32 and int8 the same "
                      "way) is judged on the mean of its runs' differences; ± is the standard error over runs.", "",
                      over]
        paired_lines = render_paired(result)
        if paired_lines:
            lines += ["", "### Paired: int8 minus fp32 on the same presses and items, with its noise", "", paired_lines]
    if render_pairs(result):
        lines += ["", "## Paired (--pair): B minus A on the same presses and items, with its noise", "",
                  "Bundles of different runs paired this way differ by their training too: the interval is the "
                  "held-out presses' and scenes' noise, not a retraining's.", "", render_pairs(result)]
    lines += render_made_by(result)
    return "\n".join(lines) + "\n"


def render_over_runs(result: dict) -> str:
    """``result["int8_over_runs"]`` as a table: per recipe and measure, the mean difference ± its
    standard error over runs, and each run's own."""
    rows = result.get("int8_over_runs") or []
    if not rows:
        return ""
    lines = ["| recipe | runs | speed-up (2 threads) | measure | Δ mean ± se | sd | each run | loss of the mean |",
             "|" + "---|" * 8]
    for o in rows:
        for k, label in INT8_MEASURES:
            d = o["delta_points"].get(k)
            if d is None:
                continue
            lines.append(f"| `{o['recipe']}` | {o['runs']} | {o['speedup_2t']:.2f}x | {label} | {d['mean']:+.1f} ± "
                         f"{d['se']:.1f} | {d['sd']:.1f} | {' / '.join(f'{v:+.1f}' for v in d['runs'])} | "
                         f"{max(o['cost_points'][k], 0.0):.1f} |")
        worst = max(o["cost_points"].items(), key=lambda kv: kv[1])
        lines.append(f"| `{o['recipe']}` | {o['runs']} | | **largest mean loss** | | | | {worst[1]:.1f} ({worst[0]}): "
                     f"{'within' if o['within_1_point'] else '**not** within'} 1 point |")
    return "\n".join(lines)


def render_paired(result: dict) -> str:
    """int8 minus fp32 per comparison (bench/paired.py): delta [95 % bootstrap], presses or items
    that flip worse / better, McNemar p. Empty when nothing was paired."""
    return _paired_rows([(c["int8"], c["fp32"], c.get("paired")) for c in result.get("comparisons", [])],
                        ("int8", "fp32"))


def render_pairs(result: dict) -> str:
    """The ``--pair A:B`` comparisons, B minus A, as ``render_paired`` shows int8 minus fp32."""
    return _paired_rows([(p["b"], p["a"], p.get("paired")) for p in result.get("pairs", [])], ("B", "A"))


def _paired_rows(comparisons: list, heads: tuple[str, str]) -> str:
    """(second, first, bench.paired result) per row: second minus first, as paired.py computes it
    (its "int8" is the second, its "fp32" the first)."""
    b_, a_ = heads
    rows = [f"| {b_} | {a_} | accuracy | {a_} | {b_} | Δ [95 % CI] | flips worse / better | McNemar p | n |",
            "|---|---|---|---:|---:|---|---|---:|---:|"]
    for second, first, p in comparisons:
        if not p:
            continue
        items = [(f"press {k}", p["press"][k], "presses") for k in ("acc_t", "zsl", "acc_u", "H")]
        items += [(f"item {k[:-2]} H", v, "items") for k, v in p.get("items", {}).items()]
        items += [(f"bins right ({k})", v, "items") for k, v in p.get("bins", {}).items()]
        for name, d, unit in items:
            flips = "–" if d.get("flips_worse") is None else f"{d['flips_worse']} / {d['flips_better']}"
            pv = "–" if d.get("mcnemar_p") is None else f"{d['mcnemar_p']:.3g}"
            rows.append(f"| {second} | {first} | {name} | {d['fp32']:.1f} | {d['int8']:.1f} | {d['delta']:+.1f} "
                        f"[{d['ci95'][0]:+.1f}, {d['ci95'][1]:+.1f}] | {flips} | {pv} | {d.get('presses', d.get('items'))} |")
    return "\n".join(rows) if len(rows) > 2 else ""


def plot_pareto(result: dict, path: Path) -> None:
    """Accuracy against trunk latency, one colour per training run: accuracies of bundles trained
    on different worlds (class counts) are not comparable, so each run gets its own Pareto front;
    an arrow joins each fp32 bundle to its int8 twin (the price of quantisation)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    # the trunk's latency at 2 threads, the cell's; at the most threads timed when 2 were not (--threads 1)
    counts = sorted({int(t) for r in result["variants"] for t in r["latency"]})
    t = "2" if 2 in counts else str(counts[-1])

    def ms(r: dict) -> float:
        return r["latency"][t]["p50_ms"]

    trained = [r for r in result["variants"] if "accuracy" in r]
    runs = sorted({r.get("run") or "?" for r in trained})
    colour = {run: f"C{i}" for i, run in enumerate(runs)}
    by_name = {r["name"]: r for r in trained}
    for ax, key, label in ((axes[0], lambda a: a["press"]["H"], "GZSL H per press (%)"),
                           (axes[1], lambda a: a["sequential"]["H"], "GZSL H per item, sequential rule (%)")):
        for run in runs:
            pts = sorted(((ms(r), key(r["accuracy"]), r) for r in trained
                          if (r.get("run") or "?") == run), key=lambda p: p[0])
            r0 = pts[0][2]
            ax.scatter([], [], color=colour[run], label=f"{Path(run).name} ({r0['classes'][0]} touched + "
                                                        f"{r0['classes'][1]} untouched)")
            for k, (x, y, r) in enumerate(pts):
                ax.scatter(x, y, marker="o" if r["precision"] == "fp32" else "s", color=colour[run], zorder=3)
                ax.annotate(f"{r['arch'].replace('efficientnet_lite0', 'effnet')} {r['size_px']} {r['precision']}",
                            (x, y), fontsize=6, xytext=(4, -9 if k % 2 else 3), textcoords="offset points")
            front, best = [], -1.0
            for x, y, _ in pts:  # Pareto front: faster and at least as accurate
                if y > best:
                    front.append((x, y))
                    best = y
            ax.step([p[0] for p in front], [p[1] for p in front], where="post", color=colour[run], lw=0.8, alpha=0.5)
        for c in result.get("comparisons", []):
            a, b = by_name.get(c["fp32"]), by_name.get(c["int8"])
            if a and b:
                ax.annotate("", xy=(ms(b), key(b["accuracy"])), xytext=(ms(a), key(a["accuracy"])),
                            arrowprops={"arrowstyle": "->", "color": "0.5", "lw": 0.6})
        for r in result["variants"]:
            if "accuracy" not in r:
                ax.axvline(ms(r), color="C3" if r["arch"] == "resnet50" else "C7", ls=":", lw=0.8)
                ax.annotate(f"{r['arch']} {r['size_px']} {r['precision']} (untrained)", (ms(r), 0),
                            rotation=90, fontsize=6, va="bottom")
        ax.set_xscale("log")
        ax.set_xlabel(f"trunk latency p50, batch 1, {t} thread{'s' if t != '1' else ''} (ms)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="center right", title="training run (colour)", title_fontsize=7)
    axes[0].set_title("circles fp32, squares int8, arrow fp32 -> int8; line = Pareto front of a run", fontsize=8)
    axes[1].set_title("dotted: latency of untrained trunks (no accuracy)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)

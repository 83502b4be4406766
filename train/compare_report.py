"""A comparison's pages: the markdown report, its figure, and a run's set of pages.

``render_markdown`` and ``plot`` draw one comparison result (train/compare.py); ``write_results``
writes the page, keeping the hand-written text below ``HAND_MARKER``; ``write_report_set`` writes a
run's main page and its extra pages with the recommendation pooled over all of them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from vs2t_edge.runtime.files import portable
from vs2t_edge.train.baselines import PAPER_GZSL_VS2T, PAPER_ZSL
from vs2t_edge.train.compare import (GAUSSIAN_ROUTER, ITEM_CONFIDENCE, ITEM_MAX_PRESSES, ITEM_SCENES,
                                     _evidence_strength, _lead, _pct, pool_into, summarise)


def _table4_row(name: str, ms: dict, paper_zsl, paper_g: dict | None) -> str:
    g = ms["routers"].get(GAUSSIAN_ROUTER) or next(iter(ms["routers"].values()))
    pg = f"{paper_g['acc_t']} / {paper_g['acc_u']} / {paper_g['H']}" if paper_g else "—"
    opt = lambda d, k: _pct(d[k]) if k in d else "—"  # noqa: E731
    return (f"| {name} | {paper_zsl if paper_zsl is not None else '—'} | {_pct(ms['zsl_acc'])} | "
            f"{opt(ms, 'val_zsl_acc')} | {pg} | {_pct(g['acc_t'])} | {_pct(g['acc_u'])} | {_pct(g['H'])} | "
            f"{opt(g, 'ausuc')} |")


def _test_numbers(ms: dict, router: str) -> str:
    return (f"ZSL {_pct(ms['zsl_acc'])}, GZSL H {_pct(ms['routers'][router]['H'])}, "
            f"AUSUC {_pct(ms['routers'][router]['ausuc'])}")


def _recommendation_section(result: dict) -> list[str]:
    """The page's recommendation: ``RECOMMENDATION_RULE`` over the pooled splits when the page
    pools several comparisons (``pool_into``), else over its own splits; a page pooled into
    another says so and points there."""
    pooled = result.get("pooled")
    meta = result.get("meta", {})
    if pooled is None:
        s, n = result["summary"], len(result["splits"])
        rec = s["recommendation"]
        if meta.get("pooled_in"):
            head = (f"## The rule on these {n} splits alone (validation only)", "",
                    f"The recommendation pools these splits with the others: see "
                    f"[{meta['pooled_in']}]({meta['pooled_in']}). On these splits alone the rule gives:")
        else:
            head = (f"## Recommendation (validation only, these {n} splits)",)
        lines = ["", *head, ""]
        if rec.get("model") is None:
            return lines + [f"No compared method runs on tactile features alone: nothing to recommend. "
                            f"Rule: {rec['rule']}.", ""]
        return lines + [f"Default model **{rec['model']}**, default router **{rec['router']}**. Rule: {rec['rule']}.",
                        f"On test (reported, not used to choose) this gives "
                        f"{_test_numbers(s['methods'][rec['model']], rec['router'])}.", "",
                        _evidence_strength(result), ""]
    s = pooled["summary"]
    rec, sm = s["recommendation"], s["methods"]
    lines = ["", f"## Recommendation (validation only, pooled over {pooled['n_splits']} splits: "
             f"{', '.join(pooled['sources'])})", ""]
    if rec.get("model") is None:
        return lines + [f"No compared method runs on tactile features alone: nothing to recommend. "
                        f"Rule: {rec['rule']}.", ""]
    rs = sm[rec["model"]]["routers"]
    lines += [f"Default model **{rec['model']}**, default router **{rec['router']}**.", "",
              f"The rule (stated once, as `compare.RECOMMENDATION_RULE`; applied by `compare.recommend`): "
              f"{rec['rule']}.", "",
              "| method | cell-side inputs per press | pooled val ZSL | its best val router (val AUSUC) |",
              "| --- | --- | --- | --- |"]
    for m in sorted(sm, key=lambda k: -sm[k]["val_zsl_acc"]["mean"]):
        br = max(sm[m]["routers"], key=lambda r: sm[m]["routers"][r]["val_ausuc"]["mean"])
        inputs = " + ".join(rec["excluded"][m]) + " (not eligible)" if m in rec["excluded"] else "tactile"
        name = f"**{m}**" if m == rec["model"] else m
        lines.append(f"| {name} | {inputs} | {_pct(sm[m]['val_zsl_acc'])} | {br} "
                     f"({100 * sm[m]['routers'][br]['val_ausuc']['mean']:.1f}) |")
    lines += ["", f"Validation AUSUC of {rec['model']} per router, pooled: "
              + ", ".join(f"{r} {100 * rs[r]['val_ausuc']['mean']:.1f}"
                          for r in sorted(rs, key=lambda r: -rs[r]['val_ausuc']['mean'])) + ".", "",
              pooled["evidence"], "",
              "The rule on each source alone (the pooled choice above is the recommendation):", "",
              "| source | splits | model | router |", "| --- | --- | --- | --- |"]
    for ps in pooled["per_source"]:
        lines.append(f"| {ps['source']} | {ps['n_splits']} | {ps['model']} | {ps['router']} |")
    lines += ["", f"On test (reported, not used to choose), pooled: {_test_numbers(sm[rec['model']], rec['router'])}.",
              ""]
    own = pooled.get("own_split") or {}
    if own:
        picks = ", ".join(f"{m} + {r}" for m, r in own["choices"])
        lines += [f"Each split choosing on its own validation fabrics only - the honest test number for the rule: "
                  f"the pooled choice reads fabrics that are another split's untouched ones; a split's own choice "
                  f"rests on its few validation fabrics, so it is also noisier: ZSL {_pct(own['zsl_acc'])}, "
                  f"GZSL H {_pct(own['H'])}, AUSUC {_pct(own['ausuc'])}; choices per split: {picks}.", ""]
    run_router = result.get("run_router") or {}
    ship = pooled.get("shipped_router")
    if run_router and ship:
        src = run_router.get("source", "the run's metrics.json")
        text = (f"**What the trained run ships.** `{src}` records router **{ship['router']}** for its VS2T-ZSL "
                f"(its rule: {run_router.get('rule') or 'not recorded'}, over its own "
                f"{len(result['splits'])} splits; this page's VS2T-ZSL row on those splits gives "
                f"{ship['run_splits_best_for_vs2t']}). ")
        if ship["router"] == rec["router"] and rec["model"] == "VS2T-ZSL":
            text += "That is the router the rule recommends."
        else:
            text += (f"Pooled over {pooled['n_splits']} splits the rule gives {ship['pooled_best_for_vs2t']} for "
                     f"VS2T-ZSL, {ship['lead']:.1f} validation AUSUC points ahead of {ship['router']} (standard error "
                     f"{ship['se']:.1f}, {_lead(ship['lead'], ship['se'])})")
            text += (f": the two differ because the run chose on its own splits' validation fabrics and this page on "
                     f"all {pooled['n_splits']} splits. A bundle exported from that run routes with "
                     f"{ship['router']}." if ship["pooled_best_for_vs2t"] != ship["router"] else ".")
            if rec["model"] != "VS2T-ZSL":
                text += f" The run's model is VS2T-ZSL; the rule recommends {rec['model']}."
        lines += [text, ""]
    elif result.get("run_vs2t") is not None:
        lines += ["**What the trained run ships.** Its metrics.json records no router choice (older runs ship "
                  "the paper's Gaussian).", ""]
    return lines


def _vs2t_condition_lines(result: dict) -> list[str]:
    """What VS2T-ZSL's condition was in this JSON, from the budget it records (``VS2TBudget``
    fields; ``train/vs2t.py`` ``VS2TZSL._visual``), not what today's default would be."""
    if not any("VS2T-ZSL" in sp["methods"] for sp in result.get("splits", [])):
        return []
    from vs2t_edge.train.vs2t import CLIP_SD

    b = result.get("budget", {})
    vc = b.get("visual_condition")
    clip = f"every channel clipped to ±{CLIP_SD:g} standard deviations of the touched training presses"
    if vc == "fabric":
        x_v = (f"each fabric's mean crop feature ({clip} first; `visual_condition: fabric`), the same for all "
               f"of a fabric's presses, so within-fabric variation must come from its latent")
    elif vc == "press":
        x_v = f"the crop feature at each press, {clip} (`visual_condition: press`)"
    else:
        x_v = ("the crop feature at each press as the other generators read it (this JSON's budget records no "
               "`visual_condition`: it predates the per-fabric condition and the clip)")
    extra = []
    if int(b.get("cond_pca", 0) or 0) > 0:
        extra.append(f"projected on its top {int(b['cond_pca'])} whitened principal components (touched presses)")
    if float(b.get("cond_noise", 0.0) or 0.0) > 0:
        extra.append(f"with Gaussian noise of std {b['cond_noise']} on the condition in training")
    tail = f", {'; '.join(extra)}" if extra else ""
    return [f"- VS2T-ZSL also conditions on [x_v, s] (through VS-F), but its x_v is {x_v}{tail}."]


def _bins_section(s: dict) -> list[str]:
    """Per item, by bins, per method at the router validation picks for it; empty for JSONs made
    before the comparison measured it."""
    rows = []
    for m, ms in s["methods"].items():
        rs = ms["routers"]
        br = max(rs, key=lambda r: rs[r]["val_ausuc"]["mean"])
        if "item_right" not in rs[br]:
            return []
        b = rs[br]
        rows.append(f"| {m} | {br} | {_pct(b['item_right'])} | {_pct(b['item_mis_sort'])} | {_pct(b['item_reject'])} "
                    f"| {b['item_presses']['mean']:.2f} |")
    return ["", "## Per item, by bins (test fabrics)", "",
            f"What a sorting line pays for (runtime/sorting.py, the evaluation the bench, the demo and training's "
            f"report use): each method's per-press posterior (its router at the validation beta, the gate's "
            f"temperature fitted on validation as export fits it) fed to the cell's evidence at confidence "
            f"{ITEM_CONFIDENCE} with at most {ITEM_MAX_PRESSES} presses, on {ITEM_SCENES} scenes per split of 5 "
            f"touched + 3 untouched test fabrics; off-scene pieces are the test fabrics a scene leaves out. A "
            f"mis-sort is a piece in a wrong bin; a reject goes to a person. The cell's own scene decision "
            f"(runtime/scene_model.py) is in training's report, not here: it needs synthesised features, which "
            f"only VS2T-ZSL's bundle carries.", "",
            "| method | router (best val AUSUC) | right bin | mis-sort | reject | presses |",
            "| --- | --- | --- | --- | --- | --- |", *rows, ""]


def render_markdown(result: dict, real_md: str | None = None) -> str:
    s = result["summary"]
    meta = result["meta"]
    lines = [
        f"# Comparison: baselines, modern generators and GZSL routers{meta.get('title_suffix', '')}",
        "",
    ]
    if meta.get("see_also"):
        lines += [meta["see_also"], ""]
    if meta.get("full_command"):
        lines += [f"Regenerate the whole comparison (the run's splits, new splits, the real-sensor check, the pooled "
                  f"recommendation and these pages) with one command: `{meta['full_command']}`. Rebuild the pages "
                  f"from the committed JSONs alone (no training): `{meta['rebuild_command']}`.", ""]
    lines += [
        f"{'These numbers were made by' if meta.get('full_command') else 'Regenerate:'} `{meta['command']}`. "
        f"Features: {meta['features']} ({meta['n_fabrics']} fabrics, "
        f"{meta['n_presses']} presses, d_t={meta['d_t']}, d_v={meta['d_v']}). {meta['n_splits']} splits "
        f"(touched/validation/untouched {meta['split_sizes']}{meta.get('splits_source', '')}). "
        f"Budget: {meta['budget']}. Wall time {meta['seconds']:.0f} s on {meta['host']}.",
        "",
        "Our numbers are mean ± std over splits (%). The paper's numbers are on FabricVST (real "
        "fabrics, not reachable here); ours are on the data named above, so the columns compare "
        "orderings, not values.",
        "",
        "## Table 4: ZSL and GZSL (paper's Gaussian router, beta tuned on validation fabrics)",
        "",
        "| method | paper ZSL | our ZSL | our val ZSL | paper acc_t / acc_u / H | acc_t | acc_u | H | AUSUC |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for m, ms in s["methods"].items():
        lines.append(_table4_row(m, ms, PAPER_ZSL.get(m), PAPER_GZSL_VS2T if m == "VS2T-ZSL" else None))
    own = result.get("run_vs2t")
    if own:
        lines.append(_table4_row("VS2T-ZSL, the run's own metrics.json", own, PAPER_ZSL["VS2T-ZSL"],
                                 PAPER_GZSL_VS2T))
    p = PAPER_GZSL_VS2T
    lines += ["", f"Paper, VS2T-ZSL GZSL: acc_t {p['acc_t']}, acc_u {p['acc_u']}, H {p['H']} (the paper gives "
              f"GZSL only for VS2T-ZSL). CLS_t touched accuracy (all methods share it): {_pct(s['cls_t_acc'])}.", ""]
    if own and own.get("reproduction"):
        rp = own["reproduction"]
        same = rp["max_abs_diff"] < 1e-9
        lines += [f"The VS2T-ZSL row is `train/vs2t.py`'s model trained here; its per-split ZSL accuracy "
                  f"differs from the run's own metrics.json by at most {100 * rp['max_abs_diff']:.2f} points "
                  f"({'identical: same model, features, splits, seeds and budget' if same else 'per split: ' + ', '.join(f'{100 * d:+.1f}' for d in rp['per_split_zsl_diff'])}).",
                  ""]
    routers = list(next(iter(s["methods"].values()))["routers"])
    lines += ["## AUSUC per router (test) — and validation AUSUC, which chooses", "",
              "| method | " + " | ".join(routers) + " |", "| --- | " + " | ".join("---" for _ in routers) + " |"]
    for m, ms in s["methods"].items():
        lines.append(f"| {m} | " + " | ".join(
            f"{100 * ms['routers'][r]['ausuc']['mean']:.1f} (val {100 * ms['routers'][r]['val_ausuc']['mean']:.1f})"
            for r in routers) + " |")
    lines += ["", "## H per router at the validation-tuned beta (test)", "",
              "| method | " + " | ".join(routers) + " |", "| --- | " + " | ".join("---" for _ in routers) + " |"]
    for m, ms in s["methods"].items():
        lines.append(f"| {m} | " + " | ".join(f"{100 * ms['routers'][r]['H']['mean']:.1f}" for r in routers) + " |")
    lines += _bins_section(s)
    lines += _recommendation_section(result)
    lines += [f"![comparison]({meta.get('png', 'comparison.png')})", ""]
    lines += ["## Methods and adaptations", "",
              "- All methods use the same features, splits, touched train/val/test presses and the same CLS_t. "
              "f-CLSWGAN, CADA-VAE and f-VAEGAN condition on the fused visual+semantic [x_v, s] with x_v the "
              "standardised visual feature of the camera crop at each press, as it is (for an untouched fabric: "
              "each of its crops). DAP uses tactile only; VT-FC-ZSL maps [x_t, x_v] to attributes; "
              "Abderrahmane 2019 conditions on attributes only; Lee 2019 on the per-press visual feature only.",
              *_vs2t_condition_lines(result),
              "- Lee 2019 is adapted to feature level: a pix2pix-style conditional GAN from the crop's "
              "visual feature to the tactile feature (BCE adversarial + 100 x L1), not image-to-image.",
              "- f-VAEGAN is the inductive f-VAEGAN-D2 without D2 (D2 needs unlabelled untouched "
              "tactile data).",
              "- VS2T-ZSL is `train/vs2t.py`'s `VS2TZSL` (the model `vs2t-edge train` fits), trained "
              "through the same split machinery as every other row.",
              "- Budgets are shortened for a shared 2-core CPU (see Budget above); GAN learning rates "
              "are 5e-4 instead of 1e-4 to compensate.", ""]
    for note in meta.get("notes", []):
        lines += [f"- {note}"]
    if meta.get("notes"):
        lines += [""]
    if meta.get("vs2t_note"):
        lines += [f"- VS2T-ZSL: {meta['vs2t_note']}", ""]
    if real_md:
        lines += [real_md]
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    """Test ZSL / GZSL per method and AUSUC per router; with a pooled recommendation (``pool_into``)
    a second row shows what chose it: pooled validation ZSL per method (not-eligible methods
    hatched) and the chosen model's pooled validation AUSUC per router."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = result["summary"]
    methods = list(s["methods"])
    routers = list(next(iter(s["methods"].values()))["routers"])
    pooled = result.get("pooled")
    fig, grid = plt.subplots(2 if pooled else 1, 2, figsize=(12, 8.4 if pooled else 4.2), squeeze=False)
    axes = grid[0]
    x = np.arange(len(methods))
    ours = [100 * s["methods"][m]["zsl_acc"]["mean"] for m in methods]
    err = [100 * s["methods"][m]["zsl_acc"]["std"] for m in methods]
    hs = [100 * (s["methods"][m]["routers"].get(GAUSSIAN_ROUTER) or {}).get("H", {"mean": 0})["mean"] for m in methods]
    paper = [PAPER_ZSL.get(m, np.nan) for m in methods]
    axes[0].bar(x - 0.27, ours, 0.27, yerr=err, label="our ZSL acc")
    axes[0].bar(x, hs, 0.27, label="our GZSL H (gaussian)")
    axes[0].bar(x + 0.27, paper, 0.27, label="paper ZSL acc (FabricVST)")
    axes[0].set_xticks(x, methods, rotation=30, ha="right")
    axes[0].set_ylabel("%")
    axes[0].set_title(f"ZSL / GZSL per method (test, {len(result['splits'])} splits)")
    axes[0].legend(fontsize=8)
    w = 0.8 / len(routers)
    for k, r in enumerate(routers):
        axes[1].bar(x + (k - len(routers) / 2 + 0.5) * w,
                    [100 * s["methods"][m]["routers"][r]["ausuc"]["mean"] for m in methods], w, label=r)
    axes[1].set_xticks(x, methods, rotation=30, ha="right")
    top = max(100 * s["methods"][m]["routers"][r]["ausuc"]["mean"] for m in methods for r in routers)
    axes[1].set_ylim(0, top * 1.35)  # room for the legend above the bars
    axes[1].set_ylabel("AUSUC %")
    axes[1].set_title("AUSUC per router (test)")
    axes[1].legend(fontsize=7, ncol=3, loc="upper center")
    if pooled:
        ps = pooled["summary"]
        rec = ps["recommendation"]
        order = sorted(ps["methods"], key=lambda m: -ps["methods"][m]["val_zsl_acc"]["mean"])
        ax = grid[1][0]
        xs = np.arange(len(order))
        for i, m in enumerate(order):
            ms = ps["methods"][m]["val_zsl_acc"]
            n = ms["n"]
            ax.bar(i, 100 * ms["mean"], 0.6, yerr=100 * ms["std"] / np.sqrt(max(n, 1)), capsize=3,
                   color="tab:green" if m == rec["model"] else "tab:gray",
                   hatch="//" if m in rec["excluded"] else None, edgecolor="black", linewidth=0.5)
        ax.set_xticks(xs, order, rotation=30, ha="right")
        ax.set_ylabel("validation ZSL %  (bar: mean, whisker: s.e.)")
        ax.set_title(f"what chose the model: validation, {pooled['n_splits']} splits pooled\n"
                     f"(green: chosen; hatched: needs the camera on the cell, not eligible)", fontsize=9)
        ax = grid[1][1]
        if rec["model"] is not None:
            rs = ps["methods"][rec["model"]]["routers"]
            rorder = sorted(rs, key=lambda r: -rs[r]["val_ausuc"]["mean"])
            ax.bar(np.arange(len(rorder)), [100 * rs[r]["val_ausuc"]["mean"] for r in rorder], 0.6,
                   yerr=[100 * rs[r]["val_ausuc"]["std"] / np.sqrt(max(rs[r]["val_ausuc"]["n"], 1)) for r in rorder],
                   capsize=3, color=["tab:green" if r == rec["router"] else "tab:gray" for r in rorder])
            ax.set_xticks(np.arange(len(rorder)), rorder, rotation=30, ha="right")
            ship = (pooled.get("shipped_router") or {}).get("router")
            note = f"; the trained run ships {ship}" if ship else ""
            ax.set_title(f"what chose the router: {rec['model']}'s validation AUSUC, pooled\n"
                         f"(green: chosen{note})", fontsize=9)
            ax.set_ylabel("validation AUSUC %")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# A report page is generated down to this line; everything from it on is hand-written (a reading
# of the numbers, caveats) and is carried over verbatim when the page is regenerated.
HAND_MARKER = "<!-- hand-written below: kept on regeneration -->"


class UnmarkedReportError(ValueError):
    """An existing report has no HAND_MARKER line, so which part is hand-written is unknown."""


def hand_written_tail(path: Path, unmarked: str = "refuse") -> str:
    """The hand-written part of the report at ``path``: from its first line that is exactly
    ``HAND_MARKER`` to the end, the marker line included; "" when the file does not exist.

    A file without the marker may hold hand text anywhere, so ``unmarked="refuse"`` (default)
    raises ``UnmarkedReportError`` naming the file, and ``unmarked="replace"`` returns "" (the
    file is then rewritten whole, its old text lost)."""
    if unmarked not in ("refuse", "replace"):
        raise ValueError(f"unmarked must be 'refuse' or 'replace', not {unmarked!r}")
    path = Path(path)
    if not path.is_file():
        return ""
    text = path.read_text()
    offset = 0
    for line in text.splitlines(keepends=True):
        if line.strip() == HAND_MARKER:
            return text[offset:]
        offset += len(line)
    if unmarked == "replace":
        return ""
    raise UnmarkedReportError(
        f"{path} has no line '{HAND_MARKER}': regenerating would erase any hand-written text in it. "
        f"Put that line above the hand-written part (everything from it on is kept), or replace the "
        f"whole file (vs2t-edge compare --replace-unmarked)")


def with_hand_text(generated: str, tail: str) -> str:
    """The generated page followed by the kept hand-written tail (or a bare marker line, so that
    text added below it later survives the next regeneration)."""
    return generated.rstrip("\n") + "\n\n" + (tail or HAND_MARKER + "\n")


def write_results(result: dict, out_dir: Path, real: dict | None = None, name: str = "comparison",
                  unmarked: str = "refuse") -> dict[str, Path]:
    """``out_dir/{name}.md|json|png``. The .md is generated down to ``HAND_MARKER``; the existing
    page's text from that line on is kept (see ``hand_written_tail`` for a page without it: by
    default nothing is written and ``UnmarkedReportError`` says why)."""
    from vs2t_edge.train.realdata_check import render_markdown as real_markdown

    paths = {"md": out_dir / f"{name}.md", "json": out_dir / f"{name}.json", "png": out_dir / f"{name}.png"}
    tail = hand_written_tail(paths["md"], unmarked)  # before writing anything: a refusal leaves the old files
    out_dir.mkdir(parents=True, exist_ok=True)
    result.setdefault("meta", {})["png"] = paths["png"].name
    # written as other machines read it: its paths without this machine's folders (the JSON and
    # the page alike, so a page rebuilt from the JSON is this page)
    result, real = portable(result), portable(real)
    payload = dict(result)
    if real is not None:
        payload["real_sensor_check"] = real
    paths["json"].write_text(json.dumps(payload, indent=1, default=float))
    plot(result, paths["png"])
    paths["md"].write_text(with_hand_text(render_markdown(result, real_markdown(real) if real else None), tail))
    return paths


def full_command(run: str | Path, out_dir: str | Path, name: str, n_extra: int, extra_seed: int) -> str:
    """The one command that regenerates a run's whole comparison (``vs2t-edge compare --full``)."""
    return (f"vs2t-edge compare --run {run} --full --splits {n_extra} --extra-seed {extra_seed} --threads 1 "
            f"--out {out_dir} --out-name {name}")


def rebuild_command(main_json: str | Path, extra_jsons: list) -> str:
    """The command that rebuilds a comparison's pages from its JSONs (``vs2t-edge compare --rebuild``)."""
    return f"vs2t-edge compare --rebuild {main_json}" + "".join(f" --pool {p}" for p in extra_jsons)


def write_report_set(main: tuple[str, dict], extra: list[tuple[str, dict]], out_dir: Path, real: dict | None = None,
                     unmarked: str = "refuse", meta: dict | None = None,
                     cell_inputs: dict[str, tuple[str, ...]] | None = None) -> dict[str, dict[str, Path]]:
    """The pages of one comparison, in ``out_dir``: ``main`` (name, result) gets the recommendation
    pooled over its splits and every ``extra`` (name, result)'s (``pool_into``) and the
    real-sensor check (``real``, else the one main's JSON holds); each extra gets its own page that
    points to main's. Every result is summarised again from its splits, so pages rebuilt from an
    older JSON apply today's rule. ``meta`` entries (e.g. the regenerate commands) go into every
    page's meta. Nothing is written when a page's hand-written text could not be kept."""
    for n in [main[0], *(n for n, _ in extra)]:
        hand_written_tail(out_dir / f"{n}.md", unmarked)
    main_name, main_result = main
    real = real if real is not None else main_result.pop("real_sensor_check", None)
    for _, r in [main, *extra]:
        r["summary"] = summarise(r["splits"], cell_inputs)
        r.setdefault("meta", {}).update(meta or {})
    pool_into(main_result, [(f"{n}.json", r) for n, r in extra], f"{main_name}.json", cell_inputs)
    paths = {}
    for n, r in extra:
        r.pop("pooled", None)
        r["meta"]["pooled_in"] = f"{main_name}.md"
        paths[n] = write_results(r, out_dir, r.pop("real_sensor_check", None), n, unmarked)
    main_result["meta"].pop("pooled_in", None)
    paths[main_name] = write_results(main_result, out_dir, real, main_name, unmarked)
    return paths

"""Figures (PNG) and the markdown report of a training run; paper numbers beside ours."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime import router_eval as reval
from vs2t_edge.train.baselines import predict_logits, train_classifier
from vs2t_edge.train.stats import sample_sd


# What the printout and the report's words mean, for someone who has not read the paper. One
# place: `vs2t-edge train` prints it after its result line, report.md carries it under its title.
LEGEND = (
    ("touched / untouched fabrics",
     "touched: the sensor felt them in training. untouched: never felt - the model knows only their camera "
     "photo and 24 yes/no attributes, and must still recognise them by touch (zero-shot)"),
    ("validation fabrics",
     "fabrics also never felt, kept aside to make choices on (router, beta); never the test"),
    ("ZSL", "accuracy (%) on presses of the untouched fabrics, choosing among the untouched fabrics only; "
            "val: the same on the validation fabrics"),
    ("GZSL t / u / H (acc_t / acc_u / H)",
     "the cell's real task, a press from any fabric: accuracy on touched presses (t), on untouched presses (u), "
     "and their harmonic mean H, high only when both are"),
    ("router, beta", "the rule that decides whether a press is from a touched fabric or an untouched one; "
                     "gaussian is the paper's (a density of touched fabrics' features). beta is its threshold, "
                     "tuned on the validation fabrics, on the router's own scale (a log density's can be in the thousands)"),
    ("AUSUC", "area under the touched-vs-untouched accuracy curve as beta sweeps every value (0-100, higher: the "
              "router separates better at any threshold); the run ships the router with the best validation AUSUC"),
    ("VS2T-ZSL, w/o E, w/o VS-F, w/o E, VS-F",
     "the full model, and the same without its encoder E (a VAE over real touched features), without the "
     "visual-semantic fusion VS-F (which merges the camera's features with the attributes), without both"),
    ("S2T / V2T", "tactile features made from the attributes alone / from the camera alone"),
    ("CLS_t / CLS_u", "the classifiers over touched fabrics (real presses) / untouched fabrics (synthesised "
                      "features)"),
    ("W1 / cos real-synth", "how close synthesised features of untouched fabrics are to their real ones "
                            "(Wasserstein distance: lower is closer; cosine of class means: higher is closer)"),
    ("right bin / mis-sort / reject", "per piece, as a sorting line counts: in its own bin; in another fabric's "
                                      "bin (found late, the costly error); in the reject bin (a person looks)"),
    ("scene, off-scene", "a job's list of fabrics, one bin each; an off-scene piece is of a fabric the job does "
                         "not list, and its right bin is the reject bin"),
)


def _full_decodes(prof: dict) -> bool:
    """Did a camera_jpeg run read its frames through full-size JPEG decodes? A descriptor's, and a
    float-path run's before --camera-decode (2026-11-29) or with ``full``; the reduced path decodes
    at 1/reduce."""
    if prof.get("tactile_feature", "cnn") != "cnn":
        return True
    return prof.get("preprocess_reduce", "off") == "off" and prof.get("camera_decode") != "auto"


def legend_lines(bullet: str = "  ") -> list[str]:
    """``LEGEND`` as lines, each ``<bullet><term>: <meaning>``."""
    return [f"{bullet}{term}: {meaning}" for term, meaning in LEGEND]


def _confusion(pred: np.ndarray, y: np.ndarray, n: int) -> np.ndarray:
    m = np.zeros((n, n))
    for a, b in zip(y, pred):
        m[a, b] += 1
    return m / np.maximum(m.sum(1, keepdims=True), 1)


def _cosine_matrix(x: np.ndarray) -> np.ndarray:
    x = x / (np.linalg.norm(x, axis=1, keepdims=True) + 1e-12)
    return x @ x.T


def figures(first: dict, fig_dir: Path, router: str = "gaussian", budget=None) -> dict:
    """Split 0's figures; returns the numbers drawn (also stored in metrics.json). The threshold
    curve is ``router``'s (the run's validation-chosen router) with the CLS_t ``compare.run_split``
    trains (same steps and seed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig_dir.mkdir(parents=True, exist_ok=True)
    views, fitted = first["views"], first["fitted"]
    x_up, _, y_up = views.test_presses
    names_u = views.train.names_u
    n_u = len(names_u)
    out: dict = {}
    # 1. normalised confusion matrices: multimodal (VS2T), visual (V2T), semantic (S2T)
    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    for ax, (key, title) in zip(axes, (("VS2T-ZSL", "multimodal (VS2T)"), ("V2T", "visual (V2T)"),
                                       ("S2T", "semantic (S2T)"))):
        cm = _confusion(predict_logits(fitted[key].cls_u, x_up).argmax(1), y_up, n_u)
        out[f"confusion_{key}"] = cm.round(3).tolist()
        ax.imshow(cm, vmin=0, vmax=1, cmap="Blues")
        ax.set_title(f"{title}\nmean diag {100 * np.mean(np.diag(cm)):.1f} %")
        ax.set_xticks(range(n_u), names_u, rotation=90, fontsize=7)
        ax.set_yticks(range(n_u), names_u, fontsize=7)
        for i in range(n_u):
            for j in range(n_u):
                ax.text(j, i, f"{cm[i, j]:.2f}", ha="center", va="center", fontsize=6)
    fig.tight_layout()
    fig.savefig(fig_dir / "confusion.png", dpi=80)
    plt.close(fig)
    # 2. PCA real vs synthesised untouched features (VS2T), fitted on the union
    xs, ys = fitted["VS2T-ZSL"].synthesise(views.train, _Budget(), 0)
    allx = np.concatenate([x_up, xs])
    mu = allx.mean(0)
    _, _, vt = np.linalg.svd(allx - mu, full_matrices=False)
    pr, ps = (x_up - mu) @ vt[:2].T, (xs - mu) @ vt[:2].T
    fig, ax = plt.subplots(figsize=(6, 5))
    cmap = plt.get_cmap("tab10")
    for k in range(n_u):
        ax.scatter(*pr[y_up == k].T, s=10, color=cmap(k % 10), marker="o", label=f"{names_u[k]} real")
        ax.scatter(*ps[ys == k].T, s=10, color=cmap(k % 10), marker="x", alpha=0.5, label=f"{names_u[k]} synth")
    ax.set_title("untouched tactile features: real (o) vs synthesised (x), PCA")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(fig_dir / "pca_real_vs_synth.png", dpi=80)
    plt.close(fig)
    # 3. cosine similarity between class inputs per modality (untouched classes)
    _, v_up, _ = views.test_presses
    mods = {"visual (class mean)": np.stack([v_up[y_up == k].mean(0) for k in range(n_u)]),
            "semantic (attributes)": views.train.attr_u.astype(float),
            "tactile real (class mean)": np.stack([x_up[y_up == k].mean(0) for k in range(n_u)])}
    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    for ax, (title, x) in zip(axes, mods.items()):
        c = _cosine_matrix(x)
        off = c[~np.eye(n_u, dtype=bool)]
        out[f"cosine_{title.split()[0]}_{title.split()[1]}"] = float(off.mean()) if off.size else 1.0
        ax.imshow(c, vmin=-1, vmax=1, cmap="RdBu_r")
        ax.set_title(f"{title}\nmean off-diagonal {off.mean() if off.size else 1:.2f}")
        ax.set_xticks(range(n_u), names_u, rotation=90, fontsize=7)
        ax.set_yticks(range(n_u), names_u, fontsize=7)
    fig.tight_layout()
    fig.savefig(fig_dir / "class_cosine.png", dpi=80)
    plt.close(fig)
    # 4. novelty threshold curve on validation (touched-val kept vs validation fabrics flagged)
    x_tv = views.touched_val[0]
    x_vp = views.val_presses[0]
    seed = int(first["result"]["split"]["seed"])
    cls_steps = 2 * int(getattr(budget, "cls_steps", 25))
    cls_t = train_classifier(views.train.x_t, views.train.y, views.train.n_t, hidden=[512, 512], steps=cls_steps,
                             seed=seed)
    opts = {"keep_covariance": False} if router in nv.GAUSSIAN_ROUTERS else {}
    rt = nv.fit_router(router, views.train.x_t, predict_logits(cls_t, views.train.x_t), touched_labels=views.train.y,
                       **opts)
    m = fitted["VS2T-ZSL"]
    cls_u_val = m.cls_u_by_classes.get(tuple(views.val.names_u), m.cls_u)  # CLS_u of the validation fabrics
    nov_tv = rt.novelty(x_tv, predict_logits(cls_t, x_tv), logits_u=predict_logits(cls_u_val, x_tv))
    nov_vp = rt.novelty(x_vp, predict_logits(cls_t, x_vp), logits_u=predict_logits(cls_u_val, x_vp))
    beta = reval.tune_threshold(nov_tv, nov_vp)
    lo, hi = np.percentile(np.concatenate([nov_tv, nov_vp]), [1, 99])
    betas = np.linspace(lo, hi, 200)
    kept, flagged = reval.threshold_rates(nov_tv, nov_vp, betas)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(betas, kept, label="touched (val presses) kept as touched")
    ax.plot(betas, flagged, label="validation fabrics flagged untouched")
    ax.plot(betas, (np.asarray(kept) + np.asarray(flagged)) / 2, "--", label="mean (maximised)")
    ax.axvline(beta, color="k", lw=0.8)
    ax.set_xlabel(f"beta ({router} novelty)")
    ax.set_ylim(0, 1.02)
    ax.legend(fontsize=7)
    ax.set_title(f"novelty threshold on validation, beta = {beta:.1f}")
    fig.tight_layout()
    fig.savefig(fig_dir / "threshold_curve.png", dpi=80)
    plt.close(fig)
    out["threshold_beta_split0"] = float(beta)
    return out


class _Budget:
    n_synth_per_class = 100


def render(m: dict) -> str:
    s = m["summary"]
    prof = m["profile"]
    n_t, n_v, n_u = m["split_sizes"]
    lines = [f"# VS2T-ZSL on {Path(m['dataset']).name} ({prof['name']} profile)", "",
             f"{m['n_fabrics']} fabrics, {len(m['splits'])} seeded split(s) {n_t}/{n_v}/{n_u} "
             f"(touched/validation/untouched); trunk {prof['trunk']} at {prof['size_px']} px, visual tail "
             f"{prof.get('visual_tail', 'frozen')}; "
             + (f"tactile tail fine-tuned to tell the touched fabrics apart and to say their attributes (weight "
                f"{prof['ft_attributes']:g}); " if prof.get("ft_attributes") else "")
             + (f"tactile frames through the camera's JPEG at q{prof['camera_jpeg']}, decoded "
                + ("at full size" if _full_decodes(prof) else "at the scale the cell's camera decodes this bundle's "
                   "frames at") + " (train, validation and test alike); " if prof.get("camera_jpeg") else "")
             + f"total {m['timing_s'].get('total', 0):.0f} s (features {m['timing_s']['features']:.0f} s, splits "
             f"{', '.join(f'{x:.0f}' for x in m['timing_s']['splits'])} s) on 2 shared CPU cores.", "",
             "Mean ± std over splits, %, test presses (per-class mean accuracy); ZSL val = the same model's "
             "accuracy on the validation fabrics (what choices may look at). GZSL: the paper's Gaussian router, "
             "and the router chosen by validation AUSUC (below), each with beta tuned on the validation fabrics "
             "(paper rule).", "", "How to read these numbers:", "", *legend_lines("- "), ""]
    rname = m.get("router", {}).get("chosen")
    head = "| model | ZSL ours | ZSL val | ZSL paper | Gaussian acc_t | acc_u | H |"
    if rname:
        per = m["router"].get("per_split")
        head += (f" {rname} acc_t | acc_u | H |" if not per or len(set(per)) == 1
                 else " val-chosen router (per split) acc_t | acc_u | H |")
    head += " W1 real-synth | cos real-synth |"
    lines += [head, "|" + " --- |" * (head.count("|") - 1)]
    for name, r in s.items():
        paper = f"{r['paper_zsl']:.2f}" if r["paper_zsl"] is not None else "—"
        val = f"{r['val_zsl']['mean']:.1f}" if "val_zsl" in r else "—"
        row = (f"| {name} | {r['zsl']['mean']:.1f} ± {r['zsl']['std']:.1f} | {val} | {paper} | {r['acc_t']['mean']:.1f} | "
               f"{r['acc_u']['mean']:.1f} | {r['H']['mean']:.1f} |")
        if rname:
            g = r["gzsl_router"]
            row += f" {g['acc_t']['mean']:.1f} | {g['acc_u']['mean']:.1f} | {g['H']['mean']:.1f} |"
        lines.append(row + f" {r['wasserstein']:.3f} | {r['cosine']:.3f} |")
    if rname and "routers" in s.get("VS2T-ZSL", {}):
        rs = s["VS2T-ZSL"]["routers"]
        per = m["router"].get("per_split")
        lines += ["", f"GZSL routers for VS2T-ZSL (beta of each tuned on validation; chosen: **{rname}**"
                      + (f", per split {', '.join(per)}" if per else "") + f"; rule: {m['router']['rule']}):", "",
                  "| router | val AUSUC | test AUSUC | acc_t | acc_u | H |", "| --- | --- | --- | --- | --- | --- |"]
        for k, v in rs.items():
            lines.append(f"| {k} | {v['val_ausuc']['mean']:.1f} | {v['ausuc']['mean']:.1f} | {v['acc_t']['mean']:.1f} ± "
                         f"{v['acc_t']['std']:.1f} | {v['acc_u']['mean']:.1f} ± {v['acc_u']['std']:.1f} | "
                         f"{v['H']['mean']:.1f} ± {v['H']['std']:.1f} |")
    pg = m["paper"]["gzsl"]
    lines += ["", f"Paper GZSL (VS2T-ZSL): acc_t {pg['acc_t']}, acc_u {pg['acc_u']}, H {pg['H']}.", "",
              "Orderings the paper shows (ZSL means): " + ", ".join(f"{k}: {'yes' if v else 'NO'}"
                                                                   for k, v in m["orderings"].items()), "",
              f"Wasserstein estimator: {m['wasserstein_estimator']}.", ""]
    if "orderings_paired" in m:
        lines += ["Paired over splits (difference of ZSL accuracy in points, mean ± standard error, splits won):", "",
                  "| ordering | test | validation |", "| --- | --- | --- |"]
        for k, t in m["orderings_paired"]["test"].items():
            v = m["orderings_paired"]["validation"][k]
            lines.append(f"| {k} | {t['mean_diff']:+.1f} ± {t['se']:.1f} ({t['wins']}/{t['n']}) | "
                         f"{v['mean_diff']:+.1f} ± {v['se']:.1f} ({v['wins']}/{v['n']}) |")
        lines.append("")
    lines += scene_lines(m.get("splits", []))
    if "risk_coverage" in m.get("figures", {}):
        lines += ["Risk-coverage per split, with the operating point and the knobs above on it "
                  "(`figures/risk_coverage.png`):", "", "![risk-coverage](figures/risk_coverage.png)", ""]
    if "figures" in m:
        lines += ["Figures (split 0): `figures/confusion.png` (multimodal / visual / semantic), "
                  "`figures/pca_real_vs_synth.png`, `figures/class_cosine.png`, `figures/threshold_curve.png`.", "",
                  "![confusion](figures/confusion.png)", "", "![pca](figures/pca_real_vs_synth.png)", "",
                  "![cosine](figures/class_cosine.png)", "", "![threshold](figures/threshold_curve.png)", ""]
    return "\n".join(lines) + "\n"


def _ms(values) -> str:
    """Mean ± spread over splits, %, NaN splits left out. The spread is the sample standard
    deviation (ddof 1): the splits are a sample of the ways the fabrics could be split, and the
    population one understated it by sqrt((n-1)/n), 11 % at 5 splits. One split: its value, no spread."""
    v = 100 * np.asarray([x for x in values if x == x], dtype=float)
    if v.size == 0:
        return "-"
    return f"{v.mean():.1f} ± {sample_sd(v):.1f}" if v.size > 1 else f"{v.mean():.1f}"


def _refused_share(summary: dict, kind: str) -> float:
    """The share of ``kind``'s pieces the off-scene rules sent to the reject bin (runtime/sorting.py
    ``summarise``); NaN for metrics written before it."""
    rule = summary.get("off_scene_rule") or {}
    share = rule.get("all") if kind == "all" else (rule.get("by_kind") or {}).get(kind)
    return math.nan if share is None else float(share)


def scene_lines(splits: list[dict]) -> list[str]:
    """Per item, as a sorting line counts (runtime/sorting.py): the scene decision on scenes of each
    split's test fabrics, mean ± std over splits."""
    sd = [s["scene_decision"] for s in splits if "scene_decision" in s]
    if not sd:
        return []
    n_sc = sd[0]["test"].get("n_scenes", "?")
    out = ["## Per item, by bins: the scene decision (train/decision.py)", "",
           f"Scenes of 5 touched + 3 untouched TEST fabrics ({n_sc} per split; touched pieces show only their "
           "test presses), off-scene pieces of the fabrics the model knows that a scene leaves out (the "
           "validation fabrics chose the operating point, so they are no test stranger: a stranger's "
           "rejection is measured on validation only); items decided by the cell's own evidence, at most 5 "
           "presses (and the extra presses validation chose, for a piece a touched fabric leads). "
           "Operating point chosen on validation jobs only (of the validation fabrics"
           + (", and of folds of touched fabrics, each held out of its own generator" if _fold_worlds(sd) else "")
           + "), for at most "
           f"{100 * sd[0]['validation']['target_mis_sort']:g} % mis-sorts. Mean ± std over {len(sd)} split(s), %.", "",
           "| pieces | right bin | mis-sort | reject | to the reject bin by the off-scene rules | presses |",
           "| --- | --- | --- | --- | --- | --- |"]
    kinds = ["all"] + [k for k in ("touched", "untouched", "off-scene") if k in sd[0]["test"]["by_kind"]]
    for kind in kinds:
        rs = [d["test"]["all"] if kind == "all" else d["test"]["by_kind"].get(kind, {}) for d in sd]
        pr = np.mean([r.get("presses", np.nan) for r in rs])
        refused = [_refused_share(d["test"], kind) for d in sd]
        out.append(f"| {kind} | {_ms([r.get('right') for r in rs])} | {_ms([r.get('mis-sort') for r in rs])} | "
                   f"{_ms([r.get('reject') for r in rs])} | {_ms(refused)} | {pr:.2f} |")
    val = [d["validation"]["validation"]["all"] for d in sd]
    kept = [d["test"]["all"]["mis-sort"] <= d["validation"]["target_mis_sort"] for d in sd]
    out += ["", f"Validation (what chose the operating point): right {_ms([v['right'] for v in val])}, mis-sort "
                f"{_ms([v['mis-sort'] for v in val])}, reject {_ms([v['reject'] for v in val])}; " + _worlds_text(sd)
                + f"the mis-sort target was met on validation in "
                f"{sum(d['validation']['meets_target_on_validation'] for d in sd)} of "
                f"{len(sd)} split(s); on the test jobs above in {sum(kept)} of {len(sd)}"
                + ("" if all(kept) else
                   " (**missed**: a split's test fabrics put that share of pieces in wrong bins, which its "
                   "validation jobs did not show)") + ".",
            *_extra_validation_lines(sd),
            f"Calibration: per-press expected calibration error {_ms([d['test']['press_ece']['before'] for d in sd])} "
            f"before, {_ms([d['test']['press_ece']['after'] for d in sd])} after temperature and bias (fitted on "
            f"validation); per item {_ms([d['test']['item_ece'] for d in sd])}. Area under the risk-coverage curve "
            f"(mis-sorts of all items against the share sorted) {_ms([d['test']['risk_coverage']['area'] for d in sd])}.",
            *([f"Per press over all bundle classes (the paper's protocol, no router: "
               f"the same one softmax over real touched and synthesised untouched means): acc_t "
               f"{_ms([d['test']['press_gzsl']['acc_t'] for d in sd])}, acc_u {_ms([d['test']['press_gzsl']['acc_u'] for d in sd])}, "
               f"H {_ms([d['test']['press_gzsl']['H'] for d in sd])} (paper: H 84.27)."]
              if all("press_gzsl" in d["test"] for d in sd) else []),
            *(["Item rules on validation per split (right / mis-sort, %; the better one by the target is kept): "
               + "; ".join(" ".join(f"{name} {100 * r['right']:.1f} / {100 * r['mis_sort']:.1f}"
                                    for name, r in d["validation"]["item_rules"].items()) for d in sd)]
              if all("item_rules" in d["validation"] for d in sd) else []),
            *knob_lines(sd),
            *job_check_lines(sd),
            *stranger_lines(sd),
            *label_lines(sd),
            "", "Chosen per split: " + "; ".join(
                f"k {c['k']}, T {c['temperature']:.3g}, untouched bias {c['untouched_bias']:g}, {_item_rule_text(c)}, "
                f"margin {c['known_margin']:g}{', refuse early' if c.get('refuse_early') else ''}, "
                f"{_outlier_text(c.get('outlier_ratio'))}{_likeness_text(c.get('likeness_ratio'))}"
                f"{_extra_text(c.get('extra_presses'))}confidence {c['confidence']:g}/{c['untouched_confidence']:g}"
                for c in (d["validation"]["chosen"] for d in sd)), ""]
    return out


def _extra_validation_lines(sd: list[dict]) -> list[str]:
    """Extra presses (evidence.extra_presses) on the validation jobs, beside the knob table's test
    prices, and how many each split chose ([] for runs before them; runs before the choice tried
    2, 4 and 8 without choosing)."""
    if not sd or not all(d["validation"].get("extra_presses") for d in sd):
        return []
    rows = zip(*(d["validation"]["extra_presses"] for d in sd))
    chosen = [d["validation"]["chosen"].get("extra_presses") for d in sd]
    said = ("the choice is made without" if None in chosen
            else "chosen per split: " + " / ".join(str(n) for n in chosen))
    return [f"Validation jobs with `evidence.extra_presses` ({said}; a touched fabric's validation pieces can "
            "only press as often as it has validation presses): "
            + "; ".join(f"{r[0]['extra_presses']}: right {_ms([x['right'] for x in r])}, mis-sort "
                        f"{_ms([x['mis_sort'] for x in r])}, {np.mean([x['presses'] for x in r]):.2f} presses"
                        for r in rows) + "."]


def _fold_worlds(sd: list[dict]) -> list[list[dict]]:
    """The validation worlds of each split whose choice had folds of touched fabrics (train/folds.py)."""
    return [w for w in (d["validation"].get("validation_worlds", []) for d in sd) if len(w) > 1]


def _worlds_text(sd: list[dict]) -> str:
    """How many fabrics the validation jobs were drawn from, when folds of touched fabrics joined the
    validation fabrics (train/folds.py; '' without them)."""
    worlds = _fold_worlds(sd)
    if not worlds:
        return ""
    own = [d["validation"]["validation_own_world"]["all"] for d in sd if "validation_own_world" in d["validation"]]
    alone = (f"; on the validation fabrics' jobs alone: right {_ms([v['right'] for v in own])}, mis-sort "
             f"{_ms([v['mis-sort'] for v in own])}, reject {_ms([v['reject'] for v in own])}") if own else ""
    return (f"drawn from {np.mean([sum(x['validation_fabrics'] for x in w) for w in worlds]):g} validation fabrics per "
            f"split on average (the split's {worlds[0][0]['validation_fabrics']} validation fabrics and {len(worlds[0]) - 1} "
            f"folds of touched fabrics, each held out of its own generator{alone}); ")


def _outlier_text(ratio) -> str:
    """The outlier-press rule of a chosen setting, for the report ('' for runs before it)."""
    if ratio is None:
        return ""
    return "outlier presses kept, " if not math.isfinite(float(ratio)) else \
        f"presses beyond {float(ratio):g} spreads no evidence, "


def _likeness_text(ratio) -> str:
    """The likeness rule of a chosen setting, for the report ('' for runs before it)."""
    if ratio is None:
        return ""
    return "likeness not asked, " if not math.isfinite(float(ratio)) else \
        f"sorted only within {float(ratio):g} times a class's own distance, "


def _extra_text(n) -> str:
    """The extra presses of a chosen setting, for the report ('' for runs before the choice)."""
    if n is None:
        return ""
    return "no extra presses, " if not n else f"up to {int(n)} extra presses, "


KNOB_KEYS = {"confidence": "evidence.confidence (touched)", "untouched_confidence": "evidence.untouched_confidence",
             "max_presses": "evidence.max_presses",
             "extra_presses": "evidence.extra_presses (past max_presses while a touched fabric leads, unrefused)",
             "outlier_ratio": "outlier ratio (training's choice, no config key)",
             "likeness_ratio": "likeness ratio (training's choice, offset rule only, no config key)",
             "mis_sort_target": "mis-sort target, % (`train --mis-sort-target`: the whole operating point chosen on "
                                "validation for it)",
             "twin_ratio": "evidence.twin_ratio (touched fabrics within this many times the generator's expected "
                           "error of an untouched fabric of the job held to confidence 0.9999; default off)",
             "validation_folds": "validation folds (`train --validation-folds`: the whole operating point chosen "
                                 "with that many folds of touched fabrics beside the validation fabrics)"}


def knob_lines(sd: list[dict]) -> list[str]:
    """The operator's knobs priced on the same test jobs (runtime/sorting.py ``knob_prices``): one
    row per setting, mean ± std over splits; the operating point first."""
    if not sd or not all("knobs" in d["test"] for d in sd):
        return []
    rows = list(zip(*(d["test"]["knobs"] for d in sd)))  # the same settings in the same order per split
    out = ["", "### What the operator's knobs cost (the same test jobs)", "",
           "One knob of the cell config moved at a time, the others at the operating point (the scene model's own "
           "confidences, at most 5 presses and its extra presses). A price list, measured on the test jobs; the "
           "operating point was chosen on validation, and so were the outlier ratio (inf: every press is evidence) "
           "and the likeness ratio (inf: not asked), priced here beside them, "
           "as is the mis-sort target the validation search chose for (each target a whole operating point). "
           "*own*: the value the operating point has in every split. Mean ± std over "
           f"{len(sd)} split(s), %.", "",
           "| knob | value | right bin | mis-sort | reject | untouched right | untouched mis-sort | presses |",
           "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for per_split in rows:
        r0 = per_split[0]
        name = KNOB_KEYS.get(r0["knob"], r0["knob"])
        value = "" if r0["value"] is None else f"{r0['value']:g}" + (" (own)" if all(r.get("own") for r in per_split) else "")
        u = [r["by_kind"].get("untouched", {}) for r in per_split]
        out.append(f"| {name} | {value} | {_ms([r['right'] for r in per_split])} | "
                   f"{_ms([r['mis-sort'] for r in per_split])} | {_ms([r['reject'] for r in per_split])} | "
                   f"{_ms([x.get('right') for x in u])} | {_ms([x.get('mis-sort') for x in u])} | "
                   f"{np.mean([r['presses'] for r in per_split]):.2f} |")
    return out + [""]


def risk_coverage_figure(sd: list[dict], path: Path) -> None:
    """Per split, the test jobs' risk-coverage curve (mis-sorted share of all pieces against the
    share sorted into a fabric's bin, as the confidence needed moves) and where the operating point
    and the confidence knobs put the jobs; the mis-sort target as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not sd:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 5))
    cmap = plt.get_cmap("tab10")
    marks = {"confidence": "^", "untouched_confidence": "s"}
    named: set[str] = set()

    def once(name: str) -> str | None:  # each kind of mark in the legend once
        if name in named:
            return None
        named.add(name)
        return name

    for i, d in enumerate(sd):
        t, colour = d["test"], cmap(i % 10)
        rc = t["risk_coverage"]
        ax.plot(100 * np.asarray(rc["coverage"]), 100 * np.asarray(rc["mis_sort"]), color=colour, lw=1,
                label=f"split {i}: confidence needed moves")
        for r in t.get("knobs", []):
            if r["knob"] == "operating point":
                ax.plot(100 * r["coverage"], 100 * r["mis-sort"], "o", color=colour, ms=8, mec="k",
                        label=once("operating point"))
            elif r["knob"] in marks:
                ax.plot(100 * r["coverage"], 100 * r["mis-sort"], marks[r["knob"]], color=colour, ms=4, alpha=0.7,
                        label=once(KNOB_KEYS[r["knob"]]))
    target = 100 * sd[0]["validation"]["target_mis_sort"]
    ax.axhline(target, color="k", ls="--", lw=0.8, label=f"mis-sort target {target:g} %")
    ax.set_xlabel("pieces sorted into a fabric's bin, % (the rest: reject bin)")
    ax.set_ylabel("pieces mis-sorted (wrong bin), % of all pieces")
    ax.set_title("risk-coverage on the test jobs, per split")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def job_check_lines(sd: list[dict]) -> list[str]:
    """How well the job check (runtime/job_check.py: before a job, from the model alone) foretold
    these test jobs' bins: per kind, the job fabrics it passed and flagged over all splits, with the
    share of their pieces in the right bin (a mean over job fabrics)."""
    if not all("job_check" in d["test"] for d in sd):
        return []
    parts = []
    for kind in ("touched", "untouched"):
        said = []
        for name in ("passed", "flagged"):
            rows = [d["test"]["job_check"].get(kind, {}).get(name) for d in sd]
            n = sum(r["fabrics"] for r in rows if r)
            right = sum(r["fabrics"] * r["right"] for r in rows if r) / n if n else float("nan")
            said.append(f"{name} {n}" + (f" ({100 * right:.1f} % of their pieces right)" if n else ""))
        parts.append(f"{kind} job fabrics {', '.join(said)}")
    return ["Job check (runtime/job_check.py: before each job, from the model alone, does each fabric's own "
            "picture sort?): " + "; ".join(parts) + "."]


def stranger_lines(sd: list[dict]) -> list[str]:
    """The deployed model knows the validation fabrics only to refuse them (train/decision.py
    ``with_known``): the same test jobs with their later presses among the off-scene pieces, decided
    without and with that knowledge."""
    ps = [d["test"]["pressed_strangers"] for d in sd if "pressed_strangers" in d["test"]]
    if not ps:
        return []

    def cell(name: str, kind: str) -> str:
        rs = [p[name]["all"] if kind == "all" else p[name]["by_kind"].get(kind, {}) for p in ps]
        return f"{_ms([r.get('right') for r in rs])} / {_ms([r.get('mis-sort') for r in rs])}"

    diff = [p["knowing"]["all"]["mis-sort"] - p["unaware"]["all"]["mis-sort"] for p in ps]
    return [f"Pieces of the validation fabrics among the off-scene ones (their later presses; fabrics the run "
            f"pressed, not never-seen ones - and every press of theirs also chose the operating point, so these "
            f"numbers flatter the rejection of a stranger; test.all above does not use them), right / mis-sort % "
            f"over {len(ps)} split(s): all pieces "
            f"{cell('unaware', 'all')} with a model that does not know them, {cell('knowing', 'all')} with the "
            f"deployed one, which knows them only to refuse them (mis-sorts {_ms(diff)} points paired by split, "
            f"fewer in {sum(d < 0 for d in diff)}, more in {sum(d > 0 for d in diff)}); off-scene pieces "
            f"{cell('unaware', 'off-scene')} → {cell('knowing', 'off-scene')}."]


def label_lines(sd: list[dict]) -> list[str]:
    """Learning from the reject bin (runtime/feedback.py): the same scenes as jobs, without and
    with operator labels, per job length, over the splits whose model can learn (``for_labels``)."""
    ol = [d["test"]["operator_labels"] for d in sd if "operator_labels" in d["test"]]
    if not ol:
        return []
    out = ["", "With operator labels (`evidence.operator_labels`, runtime/feedback.py; outside the zero-shot "
               "protocol): each scene as one job, its pieces in a random order, every rejected piece of a scene "
               "fabric labelled by the operator before the next piece; the same jobs, orders and presses without "
               "labels beside it, and the same with one known piece of each untouched fabric pressed and labelled "
               "before the job (a teach piece: not counted, its presses not shown again) "
               "(a split whose validation kept the sum rule learns with the offset setting its "
               "validation also searched). Right / mis-sort %, mean ± std over "
               f"{len(ol)} of {len(sd)} split(s) (a run before that setting was kept: the offset-rule ones):", "",
           "| pieces of each fabric per job | without labels | with labels | with labels and a teach piece of each "
           "untouched fabric first | untouched right without → with → with teach |",
           "| --- | --- | --- | --- | --- |"]
    for n in ol[0]:
        runs = [[o[n][k] for o in ol if k in o[n]] for k in ("without", "with", "teach")]
        u = lambda rs: _ms([r["by_kind"].get("untouched", {}).get("right") for r in rs])  # noqa: E731
        cell = lambda rs: f"{_ms([r['all']['right'] for r in rs])} / {_ms([r['all']['mis-sort'] for r in rs])}" \
            if rs else "-"  # noqa: E731
        out.append(f"| {n} | {cell(runs[0])} | {cell(runs[1])} | {cell(runs[2])} | "
                   f"{u(runs[0])} → {u(runs[1])} → {u(runs[2]) if runs[2] else '-'} |")
    flagged = {n: [o[n]["teach_flagged"] for o in ol if "teach_flagged" in o[n]] for n in ol[0]}
    if all(flagged.values()):
        out += ["", "With labels and a teach piece only of the untouched fabrics the job check flags (what the demo's "
                    "operator does; right / mis-sort %): " + "; ".join(
                        f"{n} pieces of each fabric {_ms([r['all']['right'] for r in rs])} / "
                        f"{_ms([r['all']['mis-sort'] for r in rs])}, "
                        f"{np.mean([r['teach_pieces_per_job'] for r in rs]):.1f} teach pieces a job"
                        for n, rs in flagged.items()) + "."]
    return out


def _item_rule_text(c: dict) -> str:
    if c.get("item_rule", "sum") == "sum":
        return f"sum rule, weight {c['evidence_weight']:g}"
    return (f"offset rule (press variance {c['press_var']:.3g}, offsets {c['offset_var_touched']:.3g} touched / "
            f"{c['offset_var_untouched']:.3g} synthesised, item temperature {c['item_temperature']:g}, "
            f"bias {c['item_bias']:g})")


__all__ = ["LEGEND", "figures", "legend_lines", "render", "scene_lines"]

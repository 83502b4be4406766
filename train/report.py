"""Figures (PNG) and the markdown report of a training run; paper numbers beside ours."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vs2t_edge.runtime import novelty as nv
from vs2t_edge.train.baselines import predict_logits, train_classifier


def _confusion(pred: np.ndarray, y: np.ndarray, n: int) -> np.ndarray:
    m = np.zeros((n, n))
    for a, b in zip(y, pred):
        m[a, b] += 1
    return m / np.maximum(m.sum(1, keepdims=True), 1)


def _cosine_matrix(x: np.ndarray) -> np.ndarray:
    x = x / (np.linalg.norm(x, axis=1, keepdims=True) + 1e-12)
    return x @ x.T


def figures(first: dict, fig_dir: Path) -> dict:
    """Split 0's figures; returns the numbers drawn (also stored in metrics.json)."""
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
    cls_t = train_classifier(views.train.x_t, views.train.y, views.train.n_t, hidden=[512, 512], steps=50, seed=0)
    router = nv.fit_router("gaussian", views.train.x_t, predict_logits(cls_t, views.train.x_t), keep_covariance=False)
    nov_tv, nov_vp = router.novelty(x_tv), router.novelty(x_vp)
    beta = nv.tune_threshold(nov_tv, nov_vp)
    lo, hi = np.percentile(np.concatenate([nov_tv, nov_vp]), [1, 99])
    betas = np.linspace(lo, hi, 200)
    kept, flagged = nv.threshold_rates(nov_tv, nov_vp, betas)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(betas, kept, label="touched (val presses) kept as touched")
    ax.plot(betas, flagged, label="validation fabrics flagged untouched")
    ax.plot(betas, (np.asarray(kept) + np.asarray(flagged)) / 2, "--", label="mean (maximised)")
    ax.axvline(beta, color="k", lw=0.8)
    ax.set_xlabel("beta (Gaussian novelty)")
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
             f"(touched/validation/untouched); trunk {prof['trunk']} at {prof['size_px']} px; "
             f"total {m['timing_s'].get('total', 0):.0f} s (features {m['timing_s']['features']:.0f} s, splits "
             f"{', '.join(f'{x:.0f}' for x in m['timing_s']['splits'])} s) on 2 shared CPU cores.", "",
             "Mean ± std over splits, %, test presses (per-class mean accuracy). GZSL uses the Gaussian router "
             "with beta tuned on the validation fabrics (paper rule).", "",
             "| model | ZSL ours | ZSL paper | GZSL acc_t | acc_u | H | W1 real-synth | cos real-synth |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, r in s.items():
        paper = f"{r['paper_zsl']:.2f}" if r["paper_zsl"] is not None else "—"
        lines.append(f"| {name} | {r['zsl']['mean']:.1f} ± {r['zsl']['std']:.1f} | {paper} | {r['acc_t']['mean']:.1f} | "
                     f"{r['acc_u']['mean']:.1f} | {r['H']['mean']:.1f} | {r['wasserstein']:.3f} | {r['cosine']:.3f} |")
    pg = m["paper"]["gzsl"]
    lines += ["", f"Paper GZSL (VS2T-ZSL): acc_t {pg['acc_t']}, acc_u {pg['acc_u']}, H {pg['H']}.", "",
              "Orderings the paper shows (ZSL means): " + ", ".join(f"{k}: {'yes' if v else 'NO'}"
                                                                   for k, v in m["orderings"].items()), "",
              f"Wasserstein estimator: {m['wasserstein_estimator']}.", ""]
    if "figures" in m:
        lines += ["Figures (split 0): `figures/confusion.png` (multimodal / visual / semantic), "
                  "`figures/pca_real_vs_synth.png`, `figures/class_cosine.png`, `figures/threshold_curve.png`.", "",
                  "![confusion](figures/confusion.png)", "", "![pca](figures/pca_real_vs_synth.png)", "",
                  "![cosine](figures/class_cosine.png)", "", "![threshold](figures/threshold_curve.png)", ""]
    return "\n".join(lines) + "\n"


__all__ = ["figures", "render"]

"""Is the fabric world's zero-shot problem honest? Neither trivial nor hopeless, measured.

    python -m vs2t_edge.sim.difficulty DATASET [--presses 40] [--out docs/difficulty.md]

Hand-made features only (numpy + OpenCV), so this judges the data, not a network:
- tactile: the reference-subtracted frame's radial power spectrum and gradient statistics;
- visual: colour statistics and the radial spectrum of the camera crop under the press.

It reports (1) a supervised tactile classifier over all fabrics, presses split in halves, with
its confusions: high but not perfect, mistakes between similar constructions; (2) identifying a
fabric from attributes alone: a second, independent panel of five annotators relabels every
fabric and the nearest of the dataset's attribute vectors names it. Coarseness alone caps this
at distinct vectors / fabrics (what the dataset's own labels would score, ties at random); the
measured number falls well below that cap, so it mostly measures label noise — two panels
labelling the same fabric disagree on enough attributes to land nearer another fabric — not
how coarse the 24 attributes are; (3) how much of a fabric's mean tactile feature is
predictable from vision, attributes, or both, across fabrics (leave one fabric out, ridge):
only in part, which is what makes the multimodal claim testable.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import yaml

from vs2t_edge.runtime.attributes import ATTRIBUTES
from vs2t_edge.runtime.dataset import load_dataset
from vs2t_edge.runtime.progress import Line

N_BANDS = 16
# The base rates the paper reports for FabricVST (out of 50 fabrics); the rest are not published.
FABRICVST_OF_50 = {"soft": 38, "rough": 30, "thick": 27, "warm": 26, "cool": 24, "thin": 23, "smooth": 20, "stiff": 11}


def radial_spectrum(gray: np.ndarray, n_bands: int = N_BANDS) -> np.ndarray:
    g = gray - gray.mean()
    power = np.abs(np.fft.fftshift(np.fft.fft2(g))) ** 2
    h, w = g.shape
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot((yy - h / 2) / (h / 2), (xx - w / 2) / (w / 2))
    bands = np.minimum((r * n_bands).astype(int), n_bands - 1)
    return np.log1p(np.bincount(bands.ravel(), power.ravel(), n_bands) / np.bincount(bands.ravel(), None, n_bands))


def tactile_features(frame: np.ndarray, reference: np.ndarray) -> np.ndarray:
    diff = frame.astype(np.float32) - reference.astype(np.float32)
    diff = cv2.resize(diff, (160, 120), interpolation=cv2.INTER_AREA)
    gray = diff.mean(axis=2)
    gx, gy = cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1)
    mag = np.hypot(gx, gy)
    ori = np.abs(np.mean(np.cos(2 * np.arctan2(gy, gx)) * mag)) / (mag.mean() + 1e-6)  # anisotropy
    stats = [diff.std(axis=(0, 1)), [np.percentile(mag, 50), np.percentile(mag, 95), ori, (np.abs(gray) > 6).mean()]]
    return np.concatenate([radial_spectrum(gray), np.log1p(np.abs(np.concatenate(stats)))]).astype(np.float64)


def visual_features(crop: np.ndarray) -> np.ndarray:
    hsv = cv2.cvtColor(crop, cv2.COLOR_BGR2HSV).reshape(-1, 3).astype(np.float64)
    gray = cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY).astype(np.float32)
    return np.concatenate([hsv.mean(0) / 255, hsv.std(0) / 255, radial_spectrum(gray, 8)])


def _standardise(train: np.ndarray, *others: np.ndarray):
    mu, sd = train.mean(0), train.std(0) + 1e-9
    return [(x - mu) / sd for x in (train, *others)]


def logistic_regression(x: np.ndarray, y: np.ndarray, n_classes: int, steps: int = 600, l2: float = 1e-3) -> np.ndarray:
    """Multinomial logistic regression by full-batch gradient descent (numpy only)."""
    xb = np.hstack([x, np.ones((len(x), 1))])
    w = np.zeros((xb.shape[1], n_classes))
    onehot = np.eye(n_classes)[y]
    lr = 0.5
    for _ in range(steps):
        z = xb @ w
        z -= z.max(1, keepdims=True)
        p = np.exp(z)
        p /= p.sum(1, keepdims=True)
        w -= lr * (xb.T @ (p - onehot) / len(x) + l2 * w)
    return w


def predict(w: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.argmax(np.hstack([x, np.ones((len(x), 1))]) @ w, axis=1)


def ridge_loo_r2(x: np.ndarray, y: np.ndarray, alpha: float = 1.0) -> float:
    """Leave-one-fabric-out R^2 of predicting y (fabrics x dims) from x (fabrics x dims)."""
    preds = np.zeros_like(y)
    for i in range(len(x)):
        keep = np.arange(len(x)) != i
        xs, xt = _standardise(x[keep], x[i:i + 1])
        ym = y[keep].mean(0)
        a = xs.T @ xs + alpha * np.eye(xs.shape[1])
        preds[i] = xt @ np.linalg.solve(a, xs.T @ (y[keep] - ym)) + ym
    ss_res = ((y - preds) ** 2).sum()
    ss_tot = ((y - y.mean(0)) ** 2).sum()
    return float(1 - ss_res / ss_tot)


def attribute_identification(params: list, attrs: np.ndarray, seed: int = 0, panels: int = 20) -> float:
    """Mean accuracy of naming each fabric from a second, independent annotator panel's labels:
    the nearest of the dataset's attribute vectors (Hamming, ties at random), over ``panels``
    panels. Same labelling rule as the world (sim/synth.py), fresh annotator noise; so it measures
    how reproducible a fabric's attribute vector is under label noise, on top of the ceiling that
    coarseness sets (distinct vectors / fabrics, what the dataset's own labels would score)."""
    from vs2t_edge.sim import synth  # the world's own labelling rule, with a different panel

    attrs = np.asarray(attrs).astype(int)
    n = len(attrs)
    hits = []
    for panel in range(panels):
        prng = np.random.default_rng([seed, 1000 + panel])
        relabelled = np.stack([synth.label_attributes(p, prng) for p in params]).astype(int)
        d = np.abs(relabelled[:, None, :] - attrs[None, :, :]).sum(-1)
        # ties broken at random: attributes cannot tell tied fabrics apart
        choice = [prng.choice(np.flatnonzero(row == row.min())) for row in d]
        hits.append(np.mean(np.array(choice) == np.arange(n)))
    return float(np.mean(hits))


def analyse(dataset: Path, presses: int = 40, seed: int = 0) -> dict:
    ds = load_dataset(dataset)
    rng = np.random.default_rng(seed)
    tac, vis, labels = [], [], []
    line = Line()
    for k, fabric in enumerate(ds.fabrics):
        ref = fabric.load_reference()
        camera = fabric.load_camera()
        idx = rng.permutation(len(fabric.presses))[:presses]
        for i in idx:
            tac.append(tactile_features(fabric.load_press(int(i)), ref))
            vis.append(visual_features(fabric.visual_crop(int(i), camera)))
            labels.append(k)
        line.draw(f"difficulty: features {k + 1}/{len(ds.fabrics)} fabrics", (k + 1) / len(ds.fabrics))
    line.keep()
    tac, vis, labels = np.array(tac), np.array(vis), np.array(labels)
    n = len(ds.fabrics)
    # (1) supervised tactile classifier: per fabric, half the presses train, half test
    train = np.zeros(len(labels), bool)
    for k in range(n):
        where = np.flatnonzero(labels == k)
        train[where[: len(where) // 2]] = True
    xs, xt = _standardise(tac[train], tac[~train])
    w = logistic_regression(xs, labels[train], n)
    pred = predict(w, xt)
    truth = labels[~train]
    acc = float((pred == truth).mean())
    constructions = [yaml.safe_load((f.folder / "fabric.yaml").read_text())["extra"]["params"]["construction"]
                     for f in ds.fabrics]
    confusions: dict[tuple[int, int], int] = {}
    for t, p in zip(truth, pred):
        if t != p:
            confusions[(int(t), int(p))] = confusions.get((int(t), int(p)), 0) + 1
    top = sorted(confusions.items(), key=lambda kv: -kv[1])[:8]
    same_kind = sum(c for (t, p), c in confusions.items() if constructions[t] == constructions[p])
    # nearest centroid too: a weaker, assumption-free reference
    cents = np.stack([xs[labels[train] == k].mean(0) for k in range(n)])
    nc_acc = float((np.argmin(((xt[:, None] - cents[None]) ** 2).sum(-1), 1) == truth).mean())
    # visual-only classifier on the same split, for contrast (colour makes this easy: it is not the ZSL task)
    vs_, vt_ = _standardise(vis[train], vis[~train])
    vis_acc = float((predict(logistic_regression(vs_, labels[train], n), vt_) == truth).mean())
    # (2) attributes alone: a fresh annotator panel relabels every fabric; nearest class by Hamming
    from vs2t_edge.sim import synth

    params = [synth.FabricParams(**{**yaml.safe_load((f.folder / "fabric.yaml").read_text())["extra"]["params"],
                                    "colour_hsv": (0.0, 0.0, 0.0)}) for f in ds.fabrics]
    attrs = ds.attribute_matrix().astype(int)
    unique_vectors = len({tuple(a) for a in attrs})
    attr_acc = attribute_identification(params, attrs, seed)
    # (3) cross-modal predictability of the fabric's mean tactile feature
    tac_mean = np.stack([tac[labels == k].mean(0) for k in range(n)])
    vis_mean = np.stack([vis[labels == k].mean(0) for k in range(n)])
    r2 = {"vision": ridge_loo_r2(vis_mean, tac_mean, 10.0),
          "attributes": ridge_loo_r2(attrs.astype(float), tac_mean, 10.0),
          "vision + attributes": ridge_loo_r2(np.hstack([vis_mean, attrs]), tac_mean, 10.0)}
    return {"dataset": str(dataset), "provenance": ds.meta.get("provenance") or {}, "fabrics": n, "presses_per_fabric_used": int(np.bincount(labels).min()),
            "tactile_logreg_acc": acc, "tactile_nearest_centroid_acc": nc_acc, "visual_logreg_acc": vis_acc,
            "chance": 1 / n, "errors_between_same_construction": same_kind,
            "errors_total": int((pred != truth).sum()),
            "top_confusions": [{"true": ds.fabrics[t].name, "predicted": ds.fabrics[p].name, "count": c}
                               for (t, p), c in top],
            "unique_attribute_vectors": unique_vectors, "attribute_nearest_class_acc": attr_acc,
            "tactile_r2_loo": r2,
            "attribute_counts": {a: int(c) for a, c in zip(ATTRIBUTES, np.asarray(attrs).sum(0))}}


def dataset_origin(dataset: str, provenance: dict) -> str:
    """How the analysed dataset was made: the synth command for the fabric world, else its provenance."""
    if str(provenance.get("generator", "")).startswith("vs2t-edge fabric world"):
        from vs2t_edge.sim.synth import PROFILES

        profile = provenance.get("profile")
        cmd = f"vs2t-edge synth {dataset} --profile {profile} --seed {provenance.get('seed')}"
        if profile in PROFILES and provenance.get("n_fabrics") not in (None, PROFILES[profile].n_fabrics):
            cmd += f" --fabrics {provenance['n_fabrics']}"
        if provenance.get("markers") is False:
            cmd += " --no-markers"
        return f"Dataset: `{cmd}`."
    if provenance:
        return f"Dataset: `{dataset}` (provenance in its dataset.yaml: {json.dumps(provenance, sort_keys=True)})."
    return f"Dataset: `{dataset}` (its dataset.yaml records no provenance)."


def write_report(res: dict, out: Path) -> None:
    r2 = res["tactile_r2_loo"]
    ceiling = res["unique_attribute_vectors"] / res["fabrics"]
    lines = [
        "# How hard is the fabric world?",
        "",
        f"{dataset_origin(res['dataset'], res.get('provenance') or {})} "
        f"Regenerate: `python -m vs2t_edge.sim.difficulty {res['dataset']} --out docs/difficulty.md` "
        f"({res['fabrics']} fabrics, {res['presses_per_fabric_used']} presses each; hand-made features, no network).",
        "",
        "| question | measure | value |",
        "| --- | --- | --- |",
        f"| can touch tell fabrics apart? | logistic regression on tactile features, held-out presses | {res['tactile_logreg_acc']:.1%} (chance {res['chance']:.1%}) |",
        f"| | nearest centroid, same features | {res['tactile_nearest_centroid_acc']:.1%} |",
        f"| are the mistakes between similar fabrics? | errors between fabrics of the same construction | {res['errors_between_same_construction']} of {res['errors_total']} |",
        f"| can attributes alone name a fabric? | fresh annotator panel, nearest attribute vector (ties at random), 20 panels | {res['attribute_nearest_class_acc']:.1%} |",
        f"| | distinct attribute vectors among {res['fabrics']} fabrics (the dataset's own labels, ties at random, would name {ceiling:.1%}: the cap set by coarseness) | {res['unique_attribute_vectors']} |",
        f"| is touch predictable from other modalities? | leave-one-fabric-out ridge R² of the fabric's mean tactile feature from vision | {r2['vision']:.2f} |",
        f"| | ... from attributes | {r2['attributes']:.2f} |",
        f"| | ... from vision + attributes | {r2['vision + attributes']:.2f} |",
        f"| (contrast) can the camera tell the same fabrics apart? | logistic regression on visual features | {res['visual_logreg_acc']:.1%} |",
        "",
        "Most frequent tactile confusions:",
        "",
        "| true | predicted | presses |",
        "| --- | --- | --- |",
    ] + [f"| {c['true']} | {c['predicted']} | {c['count']} |" for c in res["top_confusions"]] + [
        "",
        f"Attribute base rates in this dataset (of {res['fabrics']}) beside FabricVST's (of 50):",
        "",
        "| attribute | here | FabricVST |",
        "| --- | --- | --- |",
    ] + [f"| {a} | {res['attribute_counts'][a]} | {FABRICVST_OF_50.get(a, '')} |" for a in res["attribute_counts"]] + [
        "",
        "Reading: touch separates the touched fabrics well but not perfectly, and its mistakes fall",
        "between similar constructions. Attributes alone: a second annotator panel's labels name",
        f"the right fabric {res['attribute_nearest_class_acc']:.1%} of the time, while the {res['unique_attribute_vectors']} distinct vectors among",
        f"{res['fabrics']} fabrics would allow {ceiling:.1%}; " + (
            "the shortfall is mostly label noise (two panels disagree on the same fabric), not the"
            " coarseness of 24 yes/no attributes." if ceiling - res["attribute_nearest_class_acc"] >= 0.1 else
            "labels are reproducible here, so what limits attributes is their coarseness."),
        "A fabric's touch is only partly predictable from its look and its attributes — the gap the",
        "generative model has to bridge, and the reason the zero-shot numbers are not trivial.",
        "The camera separates *known* fabrics easily (colour and print); that is not the zero-shot",
        "task, where the untouched classes' touch must be synthesised.",
    ]
    out.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--presses", type=int, default=40)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    res = analyse(args.dataset, args.presses)
    print(json.dumps(res, indent=1))
    if args.out:
        write_report(res, args.out)
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

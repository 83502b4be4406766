"""World or model: how close could anyone get to an untouched fabric's touch in a synthetic world?

    python -m vs2t_edge.train.world_check RUN [--dataset DS] [--splits 0,1] [--k 128] [--out FILE.json]

A synthetic world's fabric.yaml carries each fabric's hidden physical parameters
(``sim/synth.py: FabricParams``), which no camera or annotator sees whole. Per split of a
`vs2t-edge train` run, with the run's own per-split features (its tails fine-tuned again, as
`compare --run` does) and in the space the cell decides in (the scene model's whitened k-subspace
of the touched training presses), each held-out fabric's (validation and untouched) real class
mean is set against:

- *generator*: VS2T-ZSL's synthesised class mean (fitted alone at the run's budget and split seed;
  the validation fabrics' after ``retarget``, as training chooses with them);
- *map from the physical parameters*: a ridge map, its penalty chosen by leave-one-fabric-out on
  the touched fabrics, from the hidden parameters to the touched fabrics' real means - what an
  observer who saw every parameter of the cloth would get from the touched fabrics;
- *kernel map from the physical parameters*: the same observer, non-linear (kernel ridge with a
  Gaussian kernel, its width and penalty chosen by leave-one-fabric-out): whether the parameters
  predict the touch better than a linear map can, from as many touched fabrics as the run has;
- *map from camera + attributes*: the same ridge map from what the model sees (the fabric's mean
  visual feature and its 24 attributes);
- *another realisation*: the fabric rendered again (``sim.synth.render_fabric``, at the grid points
  of the presses the run extracted) with the same parameters and another surface seed, through
  the split's tuned tactile trunk: the part of a fabric's touch that its parameters do not fix;
- *same surface*: the same, with its own surface seed (new press noise only): the measurement floor;
- *nearest touched fabric*: its real mean, the scale the decision works at.

Reported: rms distance over the held-out fabrics, and per-press accuracy of the nearest mean
among each role's fabrics (ZSL by prototypes), mean and spread over splits. Nothing here chooses
anything for the cell; held-out fabrics' tactile data only scores (their real means), never fits.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from vs2t_edge.runtime.files import portable
from vs2t_edge.train.stats import sample_sd

ROWS = ("generator", "map from the physical parameters", "kernel map from the physical parameters",
        "map from camera + attributes", "another realisation", "same surface", "nearest touched fabric")
ALPHAS = (0.1, 1.0, 10.0, 100.0, 1000.0)
# the Gaussian kernel's width, as multiples of 1 / (median squared distance between fitting rows)
KERNEL_GAMMAS = (0.1, 0.3, 1.0, 3.0, 10.0)
KERNEL_ALPHAS = (0.001, 0.01, 0.1, 1.0, 10.0)
OTHER_SURFACE = 7919  # added to a fabric's phase_seed for its other realisation


def hidden_parameters(fabric):
    """The FabricParams a synthetic world's fabric.yaml keeps (``extra.params``), or a ValueError
    naming the file."""
    import yaml

    from vs2t_edge.sim.synth import fabric_params

    path = fabric.folder / "fabric.yaml"
    extra = (yaml.safe_load(path.read_text()) or {}).get("extra") or {}
    if "params" not in extra:
        raise ValueError(f"{path}: no extra.params - the world check needs a synthetic world "
                         f"(`vs2t-edge synth`), whose fabric.yaml keeps each fabric's hidden parameters")
    return fabric_params(extra["params"], str(path))


def physical_parameters(dataset) -> tuple[np.ndarray, list]:
    """Every fabric's FabricParams of a synthetic world (its fabric.yaml read once), and their
    (F, P) numeric matrix, constructions one-hot; colour, print and the surface seed left out of it
    (they change no tactile frame, or are the realisation itself)."""
    from vs2t_edge.sim.fabrics import CONSTRUCTIONS

    hidden = [hidden_parameters(fab) for fab in dataset.fabrics]
    rows = []
    for p in hidden:
        rows.append([p.pitch_mm, p.yarn_fill, p.relief_mm, p.hairiness, p.stiffness, p.thickness_mm, p.stretch,
                     p.absorbency, p.hole_fraction, float(p.embroidery), float(p.jacquard),
                     *(float(p.construction == c) for c in CONSTRUCTIONS)])
    return np.asarray(rows, np.float64), hidden


def _standardised(cond_fit: np.ndarray, cond_new: np.ndarray, target_fit: np.ndarray) -> tuple:
    """(fitting conditions, new conditions) standardised by the fitting rows' mean and spread (a
    constant column left as it is), the targets centred, and their mean."""
    mu, sd = cond_fit.mean(0), cond_fit.std(0)
    sd[sd == 0] = 1.0
    t_mu = target_fit.mean(0)
    return (cond_fit - mu) / sd, (cond_new - mu) / sd, target_fit - t_mu, t_mu


def ridge_map(cond_fit: np.ndarray, target_fit: np.ndarray, cond_new: np.ndarray) -> tuple[np.ndarray, float]:
    """Ridge regression from standardised conditions to targets, its penalty the one of ALPHAS with
    the least leave-one-out error on the fitting rows (closed form); (predictions, penalty)."""
    a, b, y, t_mu = _standardised(cond_fit, cond_new, target_fit)
    best = None
    for alpha in ALPHAS:
        inv = np.linalg.inv(a @ a.T + alpha * np.eye(len(a)))  # dual form: fabrics, not features
        hat = a @ a.T @ inv
        loo = (y - hat @ y) / (1.0 - np.diag(hat))[:, None]
        err = float((loo ** 2).sum())
        if best is None or err < best[0]:
            best = (err, alpha, inv)
    _, alpha, inv = best
    return b @ a.T @ inv @ y + t_mu, alpha


def kernel_map(cond_fit: np.ndarray, target_fit: np.ndarray, cond_new: np.ndarray) -> tuple[np.ndarray, tuple]:
    """Kernel ridge regression with a Gaussian kernel from standardised conditions to targets, the
    kernel's width (KERNEL_GAMMAS over the median squared distance between fitting rows) and the
    penalty (KERNEL_ALPHAS) the pair with the least leave-one-out error on the fitting rows
    (closed form); (predictions, (gamma, penalty))."""
    a, b, y, t_mu = _standardised(cond_fit, cond_new, target_fit)
    d_fit = ((a[:, None, :] - a[None]) ** 2).sum(-1)
    d_new = ((b[:, None, :] - a[None]) ** 2).sum(-1)
    scale = float(np.median(d_fit[np.triu_indices(len(a), 1)])) or 1.0
    best = None
    for g in KERNEL_GAMMAS:
        kern = np.exp(-(g / scale) * d_fit)
        for alpha in KERNEL_ALPHAS:
            inv = np.linalg.inv(kern + alpha * np.eye(len(a)))
            hat = kern @ inv
            err = float((((y - hat @ y) / (1.0 - np.diag(hat))[:, None]) ** 2).sum())
            if best is None or err < best[0]:
                best = (err, g, alpha, inv)
    _, g, alpha, inv = best
    return np.exp(-(g / scale) * d_new) @ inv @ y + t_mu, (g, alpha)


def _nearest_mean_acc(z: np.ndarray, y: np.ndarray, means: np.ndarray) -> float:
    d = ((z[:, None, :] - means[None]) ** 2).sum(-1)
    pred = d.argmin(1)
    return float(np.mean([np.mean(pred[y == c] == c) for c in np.unique(y)]))


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def rerendered_features(dataset, fabric_id: str, p, presses: np.ndarray, phase_shift: int, trunk, spec,
                        camera_jpeg: int) -> np.ndarray:
    """The tuned tactile trunk's features of fabric ``fabric_id`` (its FabricParams ``p``) rendered
    again at the grid points ``presses`` with its phase_seed moved by ``phase_shift`` (0: its own
    surface)."""
    from vs2t_edge.runtime.preprocess import camera_press, camera_reference
    from vs2t_edge.sim.synth import render_fabric

    prov = dataset.meta.get("provenance") or {}
    p = replace(p, phase_seed=(p.phase_seed + phase_shift) % (2 ** 31 - 1))
    _, reference, out = render_fabric(p, str(prov["profile"]), dataset.ids.index(fabric_id), int(prov["seed"]),
                                      markers=prov.get("markers", True), presses=[int(i) for i in presses])
    ref = camera_reference(reference, spec, camera_jpeg, name=f"{fabric_id} re-rendered reference")
    x = np.stack([camera_press(frame, ref, spec, camera_jpeg, name=f"{fabric_id} re-rendered press {k}")
                  for k, (frame, *_rest) in enumerate(out)])
    with torch.no_grad():
        return trunk.eval()(torch.from_numpy(x)).numpy()


def check_split(dataset, params: np.ndarray, hidden: list, run, split, features_for, k: int, spec, camera_jpeg: int,
                max_presses: int | None, log=print) -> dict:
    from vs2t_edge.runtime.scene_model import SceneModel
    from vs2t_edge.train import compare as cmp
    from vs2t_edge.train import vs2t
    from vs2t_edge.train.compare_sources import run_budget
    from vs2t_edge.train.features import extracted_presses, touched_training_rows

    feats, cache, _ = features_for(split)
    table = cmp.FeatureTable(feats.x_t, feats.x_v, cache.fabric, cache.fabric_ids, cache.attributes)
    views = cmp.split_views(table, split)
    fit_rows = touched_training_rows(cache.fabric, cache.fabric_ids, split)[0]
    scaler, scaler_v = cmp.FeatureScaler.fit(feats.x_t[fit_rows]), cmp.FeatureScaler.fit(feats.x_v[fit_rows])
    budget = run_budget(run.profile, run.budget)
    t0 = time.time()
    gen = vs2t.variant_class("VS2T-ZSL")().fit(views.train, budget, split.seed)
    synth = {"untouched": gen.synthesise(views.train, budget, split.seed)}
    gen.retarget(views.val, budget, split.seed)
    synth["validation"] = gen.synthesise(views.val, budget, split.seed)
    log(f"  generator fitted ({time.time() - t0:.0f} s)")
    tr = views.train
    model = SceneModel.fit(tr.x_t, tr.y, list(tr.names_t), tr.x_t[:2], np.zeros(2, int), ["-"], k=k)

    def white(x):
        return (np.asarray(x, np.float64) - model.center) @ model.basis

    touched_means = np.stack([white(tr.x_t[tr.y == c]).mean(0) for c in range(tr.n_t)])
    index = {f: i for i, f in enumerate(cache.fabric_ids)}
    t_rows = [index[f] for f in split.touched]
    # a fabric's mean camera feature, scaled and clipped as the generator's condition is (train/vs2t.py)
    visual = np.stack([np.clip(scaler_v(feats.x_v[cache.fabric == i]), -vs2t.CLIP_SD, vs2t.CLIP_SD).mean(0)
                       for i in range(len(cache.fabric_ids))])
    seen = np.hstack([visual, cache.attributes])
    out = {"seed": split.seed}
    for role, names, (x, _, y) in (("validation", split.validation, views.val_presses),
                                   ("untouched", split.untouched, views.test_presses)):
        z = white(x)
        real = np.stack([z[y == c].mean(0) for c in range(len(names))])
        rows = [index[f] for f in names]
        xs, ys = synth[role]
        means = {"generator": np.stack([white(xs[ys == c]).mean(0) for c in range(len(names))])}
        means["map from the physical parameters"], a_p = ridge_map(params[t_rows], touched_means, params[rows])
        means["kernel map from the physical parameters"], a_k = kernel_map(params[t_rows], touched_means, params[rows])
        means["map from camera + attributes"], a_s = ridge_map(seen[t_rows], touched_means, seen[rows])
        for row, shift in (("another realisation", OTHER_SURFACE), ("same surface", 0)):
            t1 = time.time()
            means[row] = np.stack([white(scaler(rerendered_features(
                dataset, f, hidden[index[f]], extracted_presses(len(dataset.fabrics[index[f]].presses), max_presses),
                shift, feats.tactile_trunk, spec, camera_jpeg))).mean(0) for f in names])
            log(f"  {role}: {len(names)} fabrics rendered again ({row}, {time.time() - t1:.0f} s)")
        nearest = np.sqrt(((real[:, None] - touched_means[None]) ** 2).sum(-1)).min(1)
        r = {name: {"rms": _rms(m, real), "zsl": _nearest_mean_acc(z, y, m),
                    "per_fabric": [float(v) for v in np.sqrt(((m - real) ** 2).sum(1))]} for name, m in means.items()}
        r["nearest touched fabric"] = {"rms": float(np.sqrt(np.mean(nearest ** 2))), "zsl": None,
                                       "per_fabric": [float(v) for v in nearest]}
        r["real means"] = {"zsl": _nearest_mean_acc(z, y, real)}
        r["fabrics"], r["ridge_penalty"] = list(names), {"physical parameters": a_p, "camera + attributes": a_s,
                                                        "physical parameters, kernel (gamma, penalty)": list(a_k)}
        out[role] = r
    return out


def summarise(per_split: list[dict]) -> dict:
    out = {}
    for role in ("validation", "untouched"):
        out[role] = {}
        for row in (*ROWS, "real means"):
            vals = [s[role][row] for s in per_split]
            out[role][row] = {key: (None if vals[0].get(key) is None else
                                    {"mean": float(np.mean([v[key] for v in vals])),
                                     "std": sample_sd([v[key] for v in vals])})
                              for key in ("rms", "zsl") if key in vals[0]}
    return out


def render_table(summary: dict, k: int, n_splits: int) -> str:
    def cell(d, key, scale=1.0, fmt="{:.1f}"):
        v = d.get(key)
        return "-" if v is None else f"{fmt.format(scale * v['mean'])} ± {fmt.format(scale * v['std'])}"

    lines = [f"distance to a held-out fabric's real class mean (rms over fabrics, the scene model's whitened "
             f"{k}-subspace; mean ± std over {n_splits} splits) and per-press ZSL by nearest mean, %",
             "", "| class mean from | validation: distance | untouched: distance | validation: ZSL | untouched: ZSL |",
             "| --- | --- | --- | --- | --- |"]
    for row in (*ROWS, "real means"):
        v, u = summary["validation"][row], summary["untouched"][row]
        lines.append(f"| {row} | {cell(v, 'rms')} | {cell(u, 'rms')} | {cell(v, 'zsl', 100)} | {cell(u, 'zsl', 100)} |")
    return "\n".join(lines)


def world_check(run_dir: Path, dataset_dir: Path | None = None, splits: list[int] | None = None, k: int = 128,
                log=print) -> dict:
    import yaml

    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.train import run as tr
    from vs2t_edge.train.compare_sources import finetuned_features, load_run

    run = load_run(run_dir)
    if dataset_dir is None:
        cfg = yaml.safe_load((Path(run_dir) / "config.yaml").read_text()) or {}
        if not cfg.get("dataset"):
            raise ValueError(f"{Path(run_dir) / 'config.yaml'}: no 'dataset'; pass --dataset")
        dataset_dir = Path(cfg["dataset"])
    dataset = load_dataset(dataset_dir)
    if list(dataset.ids) != list(run.table.fabric_ids):
        raise ValueError(f"{dataset_dir}: its fabrics are not the run's ({run_dir})")
    if (run.profile.get("tactile_feature") or "cnn") != "cnn":
        raise ValueError(f"{run_dir}: tactile feature {run.profile['tactile_feature']!r}; the check needs a trunk")
    prov = dataset.meta.get("provenance") or {}
    if "profile" not in prov or "seed" not in prov:
        raise ValueError(f"{dataset_dir / 'dataset.yaml'}: no provenance profile/seed - not a synthetic world")
    params, hidden = physical_parameters(dataset)
    prof = tr.PROFILES[str(run.profile.get("name", "paper"))]
    prof = replace(prof, **{key: run.profile[key] for key in ("size_px", "preprocess_reduce", "camera_jpeg")
                            if run.profile.get(key) is not None},
                   camera_decode=run.profile.get("camera_decode", "full"))  # JPEG runs before it decoded full frames
    spec = tr.tactile_spec(prof, dataset_dir, dataset.geometry.frame_hw)
    max_presses = run.profile.get("max_presses")
    torch.set_num_threads(1)
    features_for = finetuned_features(run, log)
    chosen = list(range(len(run.splits))) if splits is None else splits
    per_split = []
    for i in chosen:
        t0 = time.time()
        log(f"split {i + 1}/{len(run.splits)}")
        per_split.append(check_split(dataset, params, hidden, run, run.splits[i], features_for, k, spec, prof.camera_jpeg,
                                     max_presses, log))
        log(f"split {i + 1}: {time.time() - t0:.0f} s")
    return {"run": str(run_dir), "dataset": str(dataset_dir), "k": k, "splits": chosen,
            "summary": summarise(per_split), "per_split": per_split}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m vs2t_edge.train.world_check", description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="a `vs2t-edge train` run folder on a synthetic world")
    p.add_argument("--dataset", type=Path, help="the world (default: the run's config.yaml dataset)")
    p.add_argument("--splits", help="comma-separated split indices (default: all)")
    p.add_argument("--k", type=int, default=128, help="scene model subspace (default 128, the paper runs' choice)")
    p.add_argument("--out", type=Path, help="write the JSON here")
    args = p.parse_args(argv)
    splits = None if not args.splits else [int(s) for s in args.splits.split(",")]
    from vs2t_edge.train.baselines import flush_denormals

    with flush_denormals():
        res = world_check(args.run, args.dataset, splits, args.k, log=lambda m: print(m, file=sys.stderr, flush=True))
    print(render_table(res["summary"], res["k"], len(res["splits"])))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(portable(res), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

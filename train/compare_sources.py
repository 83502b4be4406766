"""Where a comparison's features and splits come from (train/compare.py runs it).

- a `vs2t-edge train` run folder (``load_run``): its exact splits (metrics.json, order and seeds
  kept), its budget (config.yaml), its frozen feature table, or (``finetuned_tables``) per split the
  features its VS2T-ZSL saw; the run's own VS2T-ZSL numbers kept beside the comparison's
  (``compare_with_run``);
- a dataset folder (``extract_feature_table``: the frozen trunk over every press);
- a toy world for tests and a no-data smoke run (``toy_feature_table``).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from vs2t_edge.runtime.progress import Line
from vs2t_edge.train.baselines import Budget
from vs2t_edge.train.compare import GAUSSIAN_ROUTER, FabricSplit, FeatureTable, _ms, check_splits


RUN_FEATURE_TABLE = Path("features") / "feature_table.npz"


RUN_STEM_CACHE = Path("features") / "stem_cache.npz"


@dataclass
class RunSource:
    """What a comparison needs from a `vs2t-edge train` run folder."""

    run_dir: Path
    table: FeatureTable  # frozen-trunk features (features/feature_table.npz)
    splits: list[FabricSplit]  # exactly the run's splits, in its order (metrics.json)
    profile: dict  # config.yaml "profile" ({} when config.yaml is absent)
    vs2t_splits: list[dict]  # the run's own VS2T-ZSL record per split (metrics.json), fractions
    budget: dict = field(default_factory=dict)  # config.yaml "budget" (newer runs write the full VS2TBudget)
    router: dict = field(default_factory=dict)  # metrics.json "router": the router the run ships and its rule


def read_run_splits(path: Path) -> tuple[list[FabricSplit], list[dict]]:
    """The splits recorded by a training run: ``path`` is the run folder or its metrics.json.
    Returns (splits, per-split method records). Names the file and key on any problem."""
    path = Path(path)
    metrics = path / "metrics.json" if path.is_dir() else path
    if not metrics.is_file():
        partial = metrics.with_name("metrics_partial.json")
        hint = " (only metrics_partial.json: the run did not finish)" if partial.is_file() else ""
        raise FileNotFoundError(f"{metrics} does not exist{hint}")
    try:
        m = json.loads(metrics.read_text())
    except ValueError as exc:
        raise ValueError(f"{metrics}: not JSON ({exc})") from exc
    records = m.get("splits")
    if not isinstance(records, list) or not records:
        raise ValueError(f"{metrics}: no 'splits' list")
    splits = []
    for k, r in enumerate(records):
        sp = r.get("split") if isinstance(r, dict) else None
        if not isinstance(sp, dict):
            raise ValueError(f"{metrics}: splits[{k}] has no 'split' record")
        missing = {"touched", "validation", "untouched", "seed"} - set(sp)
        if missing:
            raise ValueError(f"{metrics}: splits[{k}].split lacks {sorted(missing)}")
        splits.append(FabricSplit(touched=[str(f) for f in sp["touched"]],
                                  validation=[str(f) for f in sp["validation"]],
                                  untouched=[str(f) for f in sp["untouched"]], seed=int(sp["seed"])))
    return splits, [r.get("methods", {}) for r in records]


def load_run(run_dir: Path) -> RunSource:
    """The run's cached frozen feature table, its exact splits, profile and VS2T numbers."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder {run_dir} does not exist")
    feats = run_dir / RUN_FEATURE_TABLE
    if not feats.is_file():
        raise FileNotFoundError(f"{feats} does not exist (written by `vs2t-edge train`)")
    table = FeatureTable.load(feats)
    splits, records = read_run_splits(run_dir)
    check_splits(table, splits)
    profile: dict = {}
    budget: dict = {}
    cfg = run_dir / "config.yaml"
    if cfg.is_file():
        import yaml

        try:
            conf = yaml.safe_load(cfg.read_text()) or {}
            profile = dict(conf.get("profile") or {})
            budget = dict(conf.get("budget") or {})
        except (yaml.YAMLError, AttributeError, TypeError, ValueError) as exc:
            raise ValueError(f"{cfg}: unreadable profile/budget ({exc})") from exc
    vs2t_splits = [r.get("VS2T-ZSL", {}) for r in records]
    return RunSource(run_dir, table, splits, profile, vs2t_splits, budget, read_run_router(run_dir))


def read_run_router(path: Path) -> dict:
    """The router a training run ships: metrics.json's "router" ({"chosen", "rule"}) with the file
    it came from under "source"; {} when the run does not record one (older runs: the Gaussian)."""
    path = Path(path)
    metrics = path / "metrics.json" if path.is_dir() else path
    try:
        router = json.loads(metrics.read_text()).get("router")
    except (OSError, ValueError, AttributeError):
        return {}
    if not isinstance(router, dict) or not router.get("chosen"):
        return {}
    return {"chosen": str(router["chosen"]), "rule": str(router.get("rule", "")), "source": str(metrics)}


def run_budget(profile: dict, budget: dict | None = None, **overrides) -> Budget:
    """The run's generator budget (``train/vs2t.py``'s ``VS2TBudget``) so that every row trains
    with the budget the VS2T run used: from its profile, then its config.yaml "budget" section
    (newer runs record every VS2TBudget field there; fields this VS2TBudget lacks are ignored),
    then ``overrides`` (not None). Fields the run did not record keep train/vs2t.py's defaults."""
    from vs2t_edge.train import vs2t

    known = {f.name for f in fields(vs2t.VS2TBudget)}
    keys = {"steps", "batch", "cls_steps", "n_synth_per_class", "lr_scale", "latent", "hidden"}
    kw = {k: profile[k] for k in keys if profile.get(k) is not None}
    kw.update({k: v for k, v in (budget or {}).items() if k in known and v is not None})
    kw.update({k: v for k, v in overrides.items() if v is not None})
    return vs2t.VS2TBudget(**kw)


def run_visual_tail(run: RunSource) -> str:
    """The visual tail the run's features went through: config.yaml ``profile.visual_tail``;
    runs written before that field existed were frozen."""
    vt = str(run.profile.get("visual_tail") or "frozen")
    if vt not in ("frozen", "finetuned"):
        raise ValueError(f"{run.run_dir / 'config.yaml'}: profile.visual_tail {vt!r} is neither 'frozen' nor "
                         f"'finetuned'")
    return vt


def finetuned_tables(run: RunSource, log: Callable[[str], None] = print,
                     weights: Path | None = None, tactile: bool = True) -> Callable[[FabricSplit], FeatureTable]:
    """Per split, the features the VS2T run's models saw: its cached stem activations through a
    copy of the trunk whose tail is fine-tuned on that split's touched-train presses, with the
    run's epochs, row cap and seed (``train/features.py``, as `vs2t-edge train` does) — the
    tactile tail (``tactile=False``: the cache's frozen tactile features instead) and, when the
    run's profile says ``visual_tail: finetuned``, the visual tail too (the camera crops at the
    same touched-train presses, seed split seed + 1, as train/run.py); otherwise the cache's
    frozen visual features. Every method of the comparison gets these visual features."""
    features_for = finetuned_features(run, log, weights, tactile)

    def table_for(split: FabricSplit) -> FeatureTable:
        feats, cache, source = features_for(split)
        return FeatureTable(feats.x_t, feats.x_v, cache.fabric, cache.fabric_ids, cache.attributes, source=source)

    return table_for


def finetuned_features(run: RunSource, log: Callable[[str], None] = print, weights: Path | None = None,
                       tactile: bool = True) -> Callable[[FabricSplit], tuple]:
    """``finetuned_tables``' work, with what it keeps: per split (``features.SplitFeatures`` - the
    features and the tuned tactile trunk -, the run's stem cache, a source line)."""
    from vs2t_edge.train import features as ft
    from vs2t_edge.train.trunks import build_trunk

    visual = run_visual_tail(run) == "finetuned"
    path = run.run_dir / RUN_STEM_CACHE
    cache = ft.StemCache.load(path)
    if cache is None:
        raise FileNotFoundError(f"{path} does not exist (fine-tuned features need the run's stem cache; "
                                f"use frozen tactile features instead)" if not visual else
                                f"{path} does not exist (the run fine-tuned its visual tail: its features "
                                f"need the run's stem cache)")
    if visual and cache.stem_v is None:
        raise ValueError(f"{path} has no visual stem, but config.yaml says the run fine-tuned its visual tail "
                         f"(profile.visual_tail: finetuned)")
    arch = str(run.profile.get("trunk", cache.meta.get("arch", "")))
    if cache.meta.get("arch") != arch:
        raise ValueError(f"{path}: stem cache of trunk {cache.meta.get('arch')!r}, config.yaml names {arch!r}")
    if list(cache.fabric_ids) != list(run.table.fabric_ids) or len(cache.fabric) != len(run.table.fabric):
        raise ValueError(f"{path}: fabrics/presses differ from {run.run_dir / RUN_FEATURE_TABLE}")
    # `vs2t-edge train` seeds torch with the profile seed just before building its trunk: the same
    # here, so that even a trunk without pretrained weights (tiny, resnet50) starts identical
    torch.manual_seed(int(run.profile.get("seed", 0)))
    trunk = build_trunk(arch, pretrained=True, weights_path=weights)
    made_by = cache.meta.get("trunk_sha256")  # caches written before the key have none
    if made_by is not None and made_by != ft.trunk_fingerprint(trunk):
        raise ValueError(f"{path}: stem cache made by another {arch} trunk (other weights or seed) than the one "
                         "built here; its tails would not be the run's (pass the run's --weights)")
    epochs = int(run.profile.get("ft_epochs", 2))
    max_rows = run.profile.get("ft_max_rows", None)
    attributes = float(run.profile.get("ft_attributes", 0.0))  # runs before it: the softmax alone
    what = " + ".join(w for w, on in (("tactile", tactile), ("visual", visual)) if on)

    def features_for(split: FabricSplit) -> tuple:
        t0 = time.time()
        # training's own per-split fine-tuning (run.run_split calls the same function)
        feats = ft.finetune_split(cache, trunk, split, epochs=epochs, max_rows=max_rows, tactile=tactile,
                                  visual=visual, progress=False, attributes=attributes)
        log(f"  {what} tail fine-tuned on {feats.n_rows} touched-train presses ({time.time() - t0:.0f} s)")
        return feats, cache, (f"{path} ({what} tail fine-tuned per split, seed = split seed"
                              + (f", visual {ft.visual_tail_seed(split.seed)}" if visual else "") + ")")

    return features_for


def run_vs2t_numbers(run: RunSource) -> dict | None:
    """The run's own VS2T-ZSL numbers (metrics.json, Gaussian router) in ``summarise``'s format,
    or None when the run has no VS2T-ZSL record."""
    recs = run.vs2t_splits
    if not recs or not all(r.get("routers", {}).get(GAUSSIAN_ROUTER) for r in recs):
        return None
    g = [r["routers"][GAUSSIAN_ROUTER] for r in recs]
    out = {"zsl_acc": _ms([r["zsl_acc"] for r in recs]), "per_split_zsl": [float(r["zsl_acc"]) for r in recs],
           "routers": {GAUSSIAN_ROUTER: {k: _ms([x[k] for x in g]) for k in ("acc_t", "acc_u", "H")}}}
    if all("val_zsl_acc" in r for r in recs):
        out["val_zsl_acc"] = _ms([r["val_zsl_acc"] for r in recs])
    for k in ("ausuc", "val_ausuc"):
        if all(k in x for x in g):
            out["routers"][GAUSSIAN_ROUTER][k] = _ms([x[k] for x in g])
    return out


def compare_with_run(result: dict, run: RunSource) -> dict | None:
    """The run's own VS2T-ZSL numbers and, per split, how far this comparison's VS2T-ZSL row
    (same class, features, splits, seeds and budget when run on fine-tuned features) is from
    them. Stored in ``result["run_vs2t"]``; None when the run has no VS2T-ZSL record."""
    own = run_vs2t_numbers(run)
    if own is None:
        return None
    ours = [r["methods"].get("VS2T-ZSL", {}).get("zsl_acc") for r in result["splits"]]
    if len(ours) == len(own["per_split_zsl"]) and all(o is not None for o in ours):
        diffs = [float(a - b) for a, b in zip(ours, own["per_split_zsl"])]
        own["reproduction"] = {"per_split_zsl_diff": diffs, "max_abs_diff": float(np.max(np.abs(diffs)))}
    result["run_vs2t"] = own
    return own


def toy_feature_table(n_fabrics: int = 30, presses: int = 40, d_t: int = 128, d_v: int = 64, seed: int = 0,
                      noise: float = 0.8, private: float = 0.0) -> FeatureTable:
    """A synthetic feature world for tests and a no-data smoke run: tactile and visual features are
    ReLU maps of the fabric's attributes and a hidden per-fabric 'structure' that both camera and
    touch partly see (so vision adds information beyond the 24 attributes), plus press noise of
    std ``noise`` and a touch-only per-fabric part of scale ``private`` that neither attributes
    nor camera reveal (what makes zero-shot recognition hard)."""
    rng = np.random.default_rng(seed)
    attrs = rng.integers(0, 2, (n_fabrics, 24)).astype(np.float64)
    hidden = rng.normal(size=(n_fabrics, 8))
    secret = rng.normal(size=(n_fabrics, 8)) * private
    w_ta, w_th, w_ts = rng.normal(size=(24, d_t)) / 3, rng.normal(size=(8, d_t)) / 2, rng.normal(size=(8, d_t)) / 2
    w_va, w_vh = rng.normal(size=(24, d_v)) / 3, rng.normal(size=(8, d_v)) / 2
    xt, xv, fab = [], [], []
    for f in range(n_fabrics):
        xt.append(np.maximum(attrs[f] @ w_ta + hidden[f] @ w_th + secret[f] @ w_ts
                             + rng.normal(size=(presses, d_t)) * noise, 0))
        xv.append(np.maximum(attrs[f] @ w_va + hidden[f] @ w_vh + rng.normal(size=(presses, d_v)) * noise, 0))
        fab.append(np.full(presses, f))
    xt, xv = np.concatenate(xt), np.concatenate(xv)
    xt[:, :5] = 0.0  # dead channels, as a ReLU trunk has
    return FeatureTable(xt.astype(np.float32), xv.astype(np.float32), np.concatenate(fab),
                        [f"toy{f:02d}" for f in range(n_fabrics)], attrs, source=f"toy world seed {seed}")


def extract_feature_table(dataset_root: Path, size_px: int = 224, log: Callable[[str], None] = print,
                          max_presses: int | None = None) -> FeatureTable:
    """PRIVATE MINIMAL feature extraction (used only when no training-run feature cache is given):
    frozen ImageNet EfficientNet-Lite0 features of each preprocessed tactile frame (the one
    ``preprocess_tactile`` with the fabric's reference frame) and of the camera crop at each press
    (ImageNet normalisation). The VS2T run fine-tunes its tactile trunk on touched fabrics; this
    extractor does not, so all methods here see the same frozen features."""
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import TactilePreprocess, preprocess_tactile
    from vs2t_edge.train.realdata_check import IMAGENET_MEAN, IMAGENET_STD, make_trunk

    import cv2

    ds = load_dataset(dataset_root)
    trunk, _ = make_trunk(pretrained=True)
    trunk.eval()
    spec = TactilePreprocess(size=size_px)
    mean, std = np.asarray(IMAGENET_MEAN, np.float32), np.asarray(IMAGENET_STD, np.float32)
    xt, xv, fab = [], [], []
    t0 = time.time()
    line = Line()
    for k, fabric in enumerate(ds.fabrics):
        ref = fabric.load_reference()
        camera = fabric.load_camera()
        n = len(fabric.presses) if max_presses is None else min(max_presses, len(fabric.presses))
        tac = np.stack([preprocess_tactile(fabric.load_press(i), ref, spec) for i in range(n)])
        vis = []
        for i in range(n):
            crop = cv2.resize(fabric.visual_crop(i, camera), (size_px, size_px), interpolation=cv2.INTER_AREA)
            vis.append(((crop[..., ::-1] / 255.0 - mean) / std).transpose(2, 0, 1).astype(np.float32))
        with torch.no_grad():
            xt.append(torch.cat([trunk(torch.from_numpy(tac[i:i + 32])) for i in range(0, n, 32)]).numpy())
            xv.append(torch.cat([trunk(torch.from_numpy(np.stack(vis[i:i + 32]))) for i in range(0, n, 32)]).numpy())
        fab.append(np.full(n, k))
        line.draw(f"features: fabric {k + 1}/{len(ds.fabrics)} ({time.time() - t0:.0f} s)", (k + 1) / len(ds.fabrics))
    line.keep()
    return FeatureTable(np.concatenate(xt), np.concatenate(xv), np.concatenate(fab), [f.id for f in ds.fabrics],
                        ds.attribute_matrix().astype(np.float64), source=f"{dataset_root} (frozen EfficientNet-Lite0)")

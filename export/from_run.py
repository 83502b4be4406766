"""A training run folder (train/artifacts.py) -> a bundle, through ``export.write_bundle``.

``export_run`` reads a run folder and its dataset, and ships the run's stored router or, with
``router=NAME``, that router refitted on the run's touched training presses with beta retuned as
training tunes it (``refit_router``); frames for parity, calibration and the probe are touched
presses only (``check_zero_shot``). ``export_random_trunk`` makes a latency-only bundle of an
untrained trunk (ResNet50 latency without a trained run).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from torch import nn

from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime import router_eval as reval
from vs2t_edge.runtime.preprocess import TactilePreprocess, camera_press, camera_reference, camera_scale

from vs2t_edge.export.calibration import calibration_presses, sensitivity_presses
from vs2t_edge.export.export import ExportError, _novelty, write_bundle
from vs2t_edge.export.int8_scene import real_mean_presses


def grid_presses(n_presses: int, max_presses: int | None) -> np.ndarray:
    """The presses of one fabric that training's feature cache holds: training's own rule
    (``train.features.extracted_presses``: ``max_presses`` evenly spaced over the grid, or all)."""
    from vs2t_edge.train.features import extracted_presses

    return extracted_presses(n_presses, max_presses)


def press_partition(n_presses: dict[str, int], touched: Sequence[str], seed: int,
                    max_presses: int | None) -> dict[str, dict[str, list[int]]]:
    """Which presses of each touched fabric trained the model (train/features.py
    ``extract_cache`` + ``touched_training_rows``: evenly spaced ``max_presses`` of the grid, then
    ``runtime.dataset.press_partition`` in press order: earlier presses train, later ones validate
    and test). ``seed`` is kept for callers; the partition no longer draws. Returns
    {fabric: {"train": [...], "val": [...], "test": [...], "unused": [...]}} in press indices."""
    from vs2t_edge.runtime.dataset import press_partition as by_order

    out = {}
    for fid in touched:
        p = n_presses[fid]
        chosen = grid_presses(p, max_presses)
        tr, va, te = by_order(len(chosen))
        out[fid] = {"val": chosen[va].tolist(), "test": chosen[te].tolist(), "train": chosen[tr].tolist(),
                    "unused": sorted(set(range(p)) - set(chosen.tolist()))}
    return out


def _frames(ds, fid: str, indices: Sequence[int], spec: TactilePreprocess, camera_jpeg: int = 0) -> np.ndarray:
    """Those presses of one fabric as the trunk takes them; with ``camera_jpeg`` Q > 0 each frame and
    the no-contact frame through the camera's JPEG at Q, decoded at the bundle's scale, as the run
    trained (runtime.preprocess.camera_press)."""
    fab = ds.by_id(fid)
    ref = camera_reference(fab.load_reference(), spec, camera_jpeg, f"{fid} reference frame")
    return np.stack([camera_press(fab.load_press(i), ref, spec, camera_jpeg, f"{fid} press {i}")
                     for i in indices]).astype(np.float32)


def _spread(indices: Sequence[int], k: int) -> list[int]:
    idx = list(indices)
    if len(idx) <= k:
        return idx
    return [idx[int(j)] for j in np.linspace(0, len(idx) - 1, k).round().astype(int)]


def _run_profile(run_dir: Path) -> dict:
    cfg = run_dir / "config.yaml"
    if not cfg.is_file():
        return {}
    import yaml

    data = yaml.safe_load(cfg.read_text()) or {}
    return data.get("profile", {}) or {}


def check_zero_shot(sources: dict[str, Sequence[int]], untouched: Sequence[str], what: str) -> None:
    """Zero-shot guard: no tactile press of an untouched fabric may shape what the bundle ships
    (router, beta, gating). ``sources`` = {fabric id: press indices} about to be read for ``what``."""
    leaked = sorted(fid for fid, idx in sources.items() if fid in set(untouched) and len(idx))
    if leaked:
        raise ExportError(f"zero-shot violated: {what} would read tactile presses of untouched fabric(s) "
                          f"{', '.join(leaked)}; only touched and validation fabrics may be touched at export")


def _outputs(trunk: nn.Module, cls_t: nn.Module, cls_u: nn.Module, x: np.ndarray, chunk: int = 32):
    """(feature, logits_t, logits_u) of the torch modules the bundle's fp32 graphs are exported
    from (they agree with onnxruntime to PARITY_TOLERANCE, which export checks)."""
    with torch.no_grad():
        outs = []
        for i in range(0, len(x), chunk):
            f = trunk(torch.from_numpy(np.ascontiguousarray(x[i:i + chunk])))
            outs.append((f.numpy(), cls_t(f).numpy(), cls_u(f).numpy()))
    return tuple(np.concatenate([o[k] for o in outs]) for k in range(3))


def refit_router(name: str, *, ds, spec: TactilePreprocess, trunk: nn.Module, cls_t: nn.Module, cls_u: nn.Module,
                 touched: Sequence[str], untouched: Sequence[str], validation: Sequence[str],
                 part: dict[str, dict[str, list[int]]], max_presses: int | None,
                 log: Callable[[str], None] = lambda m: None, camera_jpeg: int = 0) -> dict:
    """Router ``name`` fitted and its beta tuned the way `vs2t-edge train` does it, on this run.

    - fit: ``train.run.fit_router`` (the trainer's own call) on the trunk features, CLS_t logits
      and touched classes of the touched fabrics' TRAINING presses (``part[fid]["train"]``);
    - beta: ``novelty.tune_threshold(..., "balanced")`` between the held-out touched presses
      (``part[fid]["val"]``) and every cached press of the validation fabrics (``grid_presses``),
      as ``train.compare`` tunes it (its touched_val vs val_presses).
    Untouched fabrics are never read (``check_zero_shot``); ``camera_jpeg``: the run's camera JPEG
    quality, every frame read through it (``_frames``). Calibrated stacking scores the
    validation presses with the bundle's CLS_u (the untouched classes): training scored them
    with CLS_u retargeted to the validation fabrics, which the run does not keep.
    Returns {"router", "beta", "heldout", "validation" (preprocessed frames, for the gating fit),
    "provenance"}."""
    from vs2t_edge.train.run import fit_router as trainer_fit_router  # train may not import export

    if name not in nv.ROUTERS:
        raise ExportError(f"unknown router '{name}'; known: {', '.join(nv.ROUTERS)}")
    if not validation:
        raise ExportError(f"router '{name}' needs the run's validation fabrics to tune beta; this run names none")
    if set(validation) & set(touched) or set(validation) & set(untouched) or set(touched) & set(untouched):
        raise ExportError("touched, validation and untouched fabrics must be disjoint")
    fit_src = {fid: part[fid]["train"] for fid in touched}
    held_src = {fid: part[fid]["val"] for fid in touched}
    val_src = {fid: grid_presses(len(ds.by_id(fid).presses), max_presses).tolist() for fid in validation}
    for what, src in (("the router fit", fit_src), ("beta (held-out touched presses)", held_src),
                      ("beta (validation presses)", val_src)):
        check_zero_shot(src, untouched, what)

    def read(src: dict[str, list[int]], keep_frames: bool):
        frames, outs = [], []
        for fid, idx in src.items():  # per fabric: the paper run's ~1280 training frames are never all in memory
            if idx:
                x = _frames(ds, fid, idx, spec, camera_jpeg)
                outs.append(_outputs(trunk, cls_t, cls_u, x))
                if keep_frames:
                    frames.append(x)
        f, lt, lu = (np.concatenate([o[k] for o in outs]) for k in range(3))
        return (np.concatenate(frames) if keep_frames else None), f, lt, lu

    n_fit = sum(len(v) for v in fit_src.values())
    log(f"refitting router {name} on {n_fit} training presses of {len(touched)} touched fabrics")
    _, f, lt, _ = read(fit_src, keep_frames=False)
    # each fit press's touched class, in read's order (fit_src follows ``touched``; a fabric without presses adds none)
    labels = np.concatenate([np.full(len(idx), k) for k, idx in enumerate(fit_src.values())])
    router = trainer_fit_router(name, f, lt, labels)
    x_held, *held = read(held_src, keep_frames=True)
    x_val, *val = read(val_src, keep_frames=True)
    nov_held, nov_val = _novelty(router, *held), _novelty(router, *val)
    beta = reval.tune_threshold(nov_held, nov_val, "balanced")
    kept, flagged = (float(r[0]) for r in reval.threshold_rates(nov_held, nov_val, [beta]))
    log(f"beta {beta:.6g} balanced on {len(nov_held)} held-out touched vs {len(nov_val)} validation presses "
        f"(touched kept {kept:.0%}, validation flagged {flagged:.0%})")
    prov = {"name": name, "refitted_at_export": True,
            "fit": "train.run.fit_router (as `vs2t-edge train` fits it) on the torch trunk's features and CLS_t "
                   f"logits at {spec.size} px" + (f", frames through the camera's JPEG at q{camera_jpeg}"
                                                  if camera_jpeg else ""),
            "fitted_on": {"presses": "data.touched_presses[fabric].train", "fabrics": list(touched), "count": n_fit},
            "beta_rule": "runtime.novelty.tune_threshold balanced (mean of touched kept and validation flagged)",
            "beta_tuned_on": {"touched_heldout": "data.touched_presses[fabric].val", "touched_heldout_count":
                              len(nov_held), "validation_presses": val_src, "validation_count": len(nov_val)},
            "beta_rates": {"touched_kept": kept, "validation_flagged": flagged}}
    if name == "calibrated_stacking":
        prov["note"] = ("validation presses scored with the bundle's CLS_u (untouched classes); training used CLS_u "
                        "retargeted to the validation fabrics, which the run does not store")
    return {"router": router, "beta": float(beta), "heldout": x_held, "validation": x_val, "provenance": prov}


def export_run(run_dir: Path | str, out_dir: Path | str, *, trunk_precision: str = "fp32", size: int | None = None,
               calibration_frames: int = 64, dataset: Path | str | None = None, calibration_method: str = "minmax",
               float_convs: int = 0, router: str | None = None, log: Callable[[str], None] = lambda m: None,
               threads: int = 2, fuse: bool = True, float_nodes: Sequence[str] = (), float_auto: int = 0,
               percentile: float | None = None, int8_keep_operating_point: bool = False,
               heads_precision: str = "fp32", heads_in_press_graph: bool = False,
               int8_scene_means: bool = False) -> dict:
    """Bundle of a training run (RUN/artifacts/model.pt and its dataset).

    ``router``: None ships the run's stored router and beta; a name from ``novelty.ROUTERS``
    refits that router and retunes beta on this run's touched and validation presses
    (``refit_router``), e.g. the comparison's pooled recommendation instead of the run's own pick.

    int8: ``calibration_frames`` training presses of touched fabrics set the ranges (0: all of
    them, export/calibration.py); ``float_nodes`` keeps those trunk nodes in float; ``float_auto=K``
    keeps the K that buy back the most on held-out touched and validation presses
    (export/quantize.py ``layer_sensitivity``); ``percentile`` for the percentile calibration;
    ``int8_keep_operating_point`` moves beta so the int8 graph keeps as many held-out touched
    presses touched as fp32 does at the run's beta (``matched_beta``, on the graph being written);
    ``int8_scene_means`` moves the scene model's real class means (touched and known-only fabrics)
    by the int8 trunk's shift of the training presses they were fitted on (export/int8_scene.py)."""
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.train.artifacts import build_modules, load_run_artifacts, load_router

    if router is not None and router not in nv.ROUTERS:
        raise ExportError(f"unknown router '{router}'; known: {', '.join(nv.ROUTERS)}")
    run_dir = Path(run_dir)
    art = load_run_artifacts(run_dir)
    if art.tactile_feature != "cnn":
        from vs2t_edge.export.descriptor import export_descriptor_run

        asked = [opt for opt, on in (("--router", router is not None), ("--trunk-precision int8", trunk_precision != "fp32"),
                                     ("--size", size is not None), ("--heads-precision int8", heads_precision != "fp32"),
                                     ("--two-graphs", not fuse), ("--heads-in-press-graph", heads_in_press_graph)) if on]
        if asked:  # a descriptor bundle has no trunk or press graph: what is asked would not ship
            raise ExportError(f"run {run_dir} has the {art.tactile_feature} descriptor as its tactile feature: "
                              f"{', '.join(asked)} apply to a trunk and its press graph (not to a descriptor)")
        return export_descriptor_run(run_dir, art, out_dir, dataset=dataset, calibration_frames=calibration_frames,
                                     log=log, threads=threads)
    trunk, cls_t, cls_u = build_modules(art)
    stored = load_router(art)
    spec = art.tactile_preprocess
    trained_size = spec.size
    if size is not None and int(size) != trained_size and art.scene_model is not None and router is None:
        # the scene model and its operating point were fitted on features of the trained size: at
        # another size they decide on other features (the paper run at 96 px: mis-sorts 0.9 -> 3.8 %)
        raise ExportError(f"--size {size}: run {run_dir} was trained at {trained_size} px, and its scene model "
                          "(the cell's decision) and operating point were fitted on features of that size; a "
                          f"bundle at {size} px would decide with them on other features (on the paper run at "
                          "96 px: mis-sorts 0.9 -> 3.8 %). Train at the size you want (the profile's size), or "
                          "export without --size")
    if size is not None:
        spec = replace(spec, size=int(size))
    ds_root = Path(dataset or art.dataset)
    if not ds_root.is_dir():
        raise ExportError(f"the run's dataset {ds_root} is not there (int8 calibration, parity and the probe "
                          "need its touched presses); pass --dataset")
    ds = load_dataset(ds_root)
    prof = _run_profile(run_dir)
    seed = int(art.info.get("split_seed", 0))
    max_presses = prof.get("max_presses")
    part = press_partition({f.id: len(f.presses) for f in ds.fabrics}, art.touched, seed, max_presses)
    calib_ids = [fid for fid in (art.touched_fabric_ids or art.touched) if fid in part]
    if set(calib_ids) - set(art.touched):
        raise ExportError("calibration fabrics must be touched fabrics")
    calib_src = calibration_presses(part, calib_ids, calibration_frames, untouched=art.untouched)
    log(f"reading {sum(map(len, calib_src.values()))} training presses of {len(calib_src)} touched fabrics "
        "(calibration)")
    q = art.camera_jpeg  # the camera JPEG the run trained through: every frame read here goes through it too
    if q:
        log(f"frames through the camera's JPEG at q{q}, decoded at 1/{camera_scale(spec)}, as the run trained")
    calib = np.concatenate([_frames(ds, fid, idx, spec, q) for fid, idx in calib_src.items()])
    for what, fids in (("int8 calibration, parity and the probe", calib_ids),
                       ("the gating fit (held-out touched presses)", art.touched),
                       ("the gating fit (validation presses)", art.validation)):
        check_zero_shot({fid: [0] for fid in fids}, art.untouched, what)
    if router is None:
        heldout = np.concatenate([_frames(ds, fid, part[fid]["val"], spec, q) for fid in art.touched])
        validation = np.concatenate([_frames(ds, fid, _spread(range(len(ds.by_id(fid).presses)), 12), spec, q)
                                     for fid in art.validation]) if art.validation else None
        chosen, beta = stored, art.beta
        operating_point = f"{art.router_name} router, beta balanced on validation fabrics {', '.join(art.validation)}"
        router_prov = {"name": art.router_name, "refitted_at_export": False,
                       "source": "the run's stored router and beta (artifacts/model.pt)"}
    else:
        refit = refit_router(router, ds=ds, spec=spec, trunk=trunk, cls_t=cls_t, cls_u=cls_u, touched=art.touched,
                             untouched=art.untouched, validation=art.validation, part=part, max_presses=max_presses,
                             log=log, camera_jpeg=q)
        chosen, beta, heldout, validation = refit["router"], refit["beta"], refit["heldout"], refit["validation"]
        operating_point = (f"{router} router (refitted at export on touched training presses), beta balanced on "
                           f"validation fabrics {', '.join(art.validation)} against held-out touched presses")
        router_prov = {**refit["provenance"], "run_router": art.router_name, "run_beta": float(art.beta)}
    quant_options: dict = {"float_nodes": list(float_nodes), "float_auto": int(float_auto)}
    if percentile is not None:
        quant_options["percentile"] = float(percentile)
    if trunk_precision == "int8" and float_auto:
        val_n = {fid: len(ds.by_id(fid).presses) for fid in art.validation}
        sens_src = sensitivity_presses(part, art.touched, val_n, untouched=art.untouched)
        quant_options["sensitivity_frames"] = np.concatenate([_frames(ds, fid, idx, spec, q)
                                                              for fid, idx in sens_src.items()])
        log(f"sensitivity scan on {len(quant_options['sensitivity_frames'])} held-out touched and validation presses")
        quant_options.update(score=_logit_score(cls_t, cls_u), rank_by="logit_error")
    prov = {"run": str(run_dir.resolve()), "trained": True, "trained_size_px": trained_size,
            "data": {"dataset": str(ds_root.resolve()), "split_seed": seed, "max_presses": max_presses,
                     "validation": list(art.validation), "touched_presses": part,
                     "calibration_fabrics": calib_ids, "calibration_presses": calib_src},
            "router": router_prov, "run_info": art.info}
    mean_frames = None
    if trunk_precision == "int8" and int8_scene_means and (router is not None or art.scene_model is None):
        log("the scene model's means stay as trained: " + ("--router ships no scene model" if router is not None
                                                          else "the run has no scene model"))
    elif trunk_precision == "int8" and int8_scene_means:
        known = [str(c) for c in art.scene_model.get("known_only", ())]
        known_part = press_partition({fid: len(ds.by_id(fid).presses) for fid in known}, known, seed, max_presses)
        mean_src = real_mean_presses(part, art.touched, known_part)
        check_zero_shot(mean_src, art.untouched, "the int8 scene model's real class means")
        log(f"reading {sum(map(len, mean_src.values()))} training presses of {len(mean_src)} touched and known-only "
            "fabrics (the int8 scene model's real class means)")

        def read_mean_presses():
            for fid, idx in mean_src.items():
                yield fid, _frames(ds, fid, idx, spec, q)
        mean_frames = read_mean_presses
        prov["data"]["int8_scene_mean_presses"] = mean_src
    keep_op = trunk_precision == "int8" and int8_keep_operating_point
    nov32 = _novelty(chosen, *_outputs(trunk, cls_t, cls_u, heldout)) if keep_op else None

    def int8_beta(nov8: np.ndarray) -> tuple[float, str, dict]:
        beta8, kept = matched_beta(nov32, nov8, beta)
        log(f"int8 operating point: beta {beta:.6g} -> {beta8:.6g} keeps {kept:.1%} of {len(heldout)} held-out "
            "touched presses touched, as fp32 does at the run's beta")
        return beta8, f"; moved for int8 to keep fp32's touched kept rate ({kept:.1%})", {"int8_operating_point": {
            "rule": "beta moved so the int8 graph routes as many held-out touched presses "
                    "(data.touched_presses[*].val) touched as the fp32 graph does at the run's beta",
            "run_beta": float(beta), "beta": float(beta8), "touched_kept": kept, "presses": int(len(heldout))}}

    return write_bundle(out_dir, trunk=trunk, cls_t=cls_t, cls_u=cls_u, router=chosen, touched=art.touched,
                        untouched=art.untouched, preprocess=spec, beta=beta, calibration=calib,
                        trunk_precision=trunk_precision, trunk_arch=art.trunk_arch, validation=validation,
                        touched_heldout=heldout, provenance=prov, log=log, threads=threads,
                        calibration_method=calibration_method, float_convs=float_convs,
                        quant_options=quant_options if trunk_precision == "int8" else None,
                        operating_point=operating_point, scene_model=art.scene_model if router is None else None,
                        fuse=fuse, int8_beta=int8_beta if keep_op else None, heads_precision=heads_precision,
                        camera_jpeg=q, heads_in_press_graph=heads_in_press_graph, real_mean_presses=mean_frames)


def matched_beta(nov32: np.ndarray, nov8: np.ndarray, beta: float) -> tuple[float, float]:
    """beta for the int8 graph that keeps the same share of touched presses touched (novelty <=
    beta) as fp32 keeps at ``beta``, midway between two observed int8 scores. Returns (beta, share)."""
    nov32, nov8 = np.asarray(nov32, np.float64), np.sort(np.asarray(nov8, np.float64))
    kept = float(np.mean(nov32 <= beta))
    k = int(round(kept * len(nov8)))  # presses to keep
    if k <= 0:
        return float(nov8[0] - 1.0 - abs(nov8[0])), kept
    if k >= len(nov8):
        return float(nov8[-1] + 1.0 + abs(nov8[-1])), kept
    return float((nov8[k - 1] + nov8[k]) / 2), kept


def _logit_score(cls_t: nn.Module, cls_u: nn.Module):
    """The sensitivity scan's measure at export: the heads' logit error (export/quantize.py)."""
    from vs2t_edge.export.quantize import logit_error

    def score(f8: np.ndarray, f32: np.ndarray) -> dict:
        with torch.no_grad():
            a = [m(torch.from_numpy(np.ascontiguousarray(f8))).numpy() for m in (cls_t, cls_u)]
            b = [m(torch.from_numpy(np.ascontiguousarray(f32))).numpy() for m in (cls_t, cls_u)]
        return {"logit_error": logit_error(a, b)}
    return score


def export_random_trunk(arch: str, out_dir: Path | str, *, size: int, dataset: Path | str,
                        trunk_precision: str = "fp32", calibration_frames: int = 32, seed: int = 0,
                        log: Callable[[str], None] = lambda m: None, threads: int = 2, fuse: bool = True,
                        reduce: int = 0, heads_precision: str = "fp32", heads_in_press_graph: bool = False) -> dict:
    """A latency-only bundle: an UNTRAINED trunk (random init, or the offline ImageNet weights for
    efficientnet_lite0) with random heads over the dataset's fabrics and a Gaussian router on its
    own features, and a scene model of the trained runs' width (``latency_scene_model``), so that
    its press path is a deployed bundle's. Its accuracy means nothing (the manifest says trained:
    false); its latency, memory and int8 behaviour on real-looking frames are those of the
    architecture. ``reduce``: the pixel path (runtime/preprocess.py; 0 the float path)."""
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.train.models import Classifier
    from vs2t_edge.train.trunks import build_trunk

    torch.manual_seed(seed)
    trunk = build_trunk(arch, pretrained=False).eval()
    spec = TactilePreprocess(size=int(size), reduce=int(reduce))
    ds = load_dataset(dataset)
    ids = ds.ids
    touched, untouched = ids[: max(1, len(ids) - 3)], ids[max(1, len(ids) - 3):]
    per = max(1, math.ceil(calibration_frames / len(touched)))
    parts = [_frames(ds, fid, _spread(range(len(ds.by_id(fid).presses)), per), spec) for fid in touched]
    keep = _spread(range(sum(len(p) for p in parts)), calibration_frames)
    calib = np.concatenate(parts)[keep]
    labels = np.concatenate([np.full(len(p), c) for c, p in enumerate(parts)])[keep]
    with torch.no_grad():
        feats = torch.cat([trunk(torch.from_numpy(calib[i:i + 8])) for i in range(0, len(calib), 8)]).numpy()
    mean, std = feats.mean(0), feats.std(0) + 1e-6

    class _Std(nn.Module):
        def __init__(self):
            super().__init__()
            self.t = trunk
            self.register_buffer("m", torch.from_numpy(mean))
            self.register_buffer("s", torch.from_numpy(std))

        def forward(self, x):
            return (self.t(x) - self.m) / self.s

    deploy = _Std().eval()
    d = feats.shape[1]
    router = nv.fit_router("gaussian", (feats - mean) / std, keep_covariance=False)
    nov = router.novelty((feats - mean) / std)
    scene = latency_scene_model((feats - mean) / std, labels, touched, untouched, seed)
    return write_bundle(out_dir, trunk=deploy, cls_t=Classifier(d, len(touched)), cls_u=Classifier(d, len(untouched)),
                        router=router, touched=touched, untouched=untouched, preprocess=spec,
                        beta=float(np.quantile(nov, 0.95)), calibration=calib, trunk_precision=trunk_precision,
                        trunk_arch=arch, operating_point="none (untrained, latency only)", scene_model=scene,
                        provenance={"trained": False, "dataset": str(Path(dataset).resolve()), "seed": seed},
                        log=log, threads=threads, fuse=fuse, heads_precision=heads_precision,
                        heads_in_press_graph=heads_in_press_graph)


LATENCY_SCENE_K = 128  # the scene model's width in the paper profile's runs (train/decision.py)


def latency_scene_model(features: np.ndarray, labels: np.ndarray, touched: Sequence[str], untouched: Sequence[str],
                        seed: int = 0) -> dict:
    """A latency-only bundle's scene model (``SceneModel.to_params()``): ``LATENCY_SCENE_K`` random
    orthonormal directions (an untrained trunk's few calibration presses span fewer), the touched
    classes at their presses' mean there, the untouched ones at random points of the same spread.
    Its decisions mean nothing; its shapes, and so the press's cost, are a trained bundle's."""
    from vs2t_edge.runtime.scene_model import SceneModel

    rng = np.random.default_rng(seed)
    x = np.asarray(features, np.float64)
    k = min(LATENCY_SCENE_K, x.shape[1])
    basis = np.linalg.qr(rng.standard_normal((x.shape[1], k)))[0]
    center = x.mean(axis=0)
    z = (x - center) @ basis
    means_t = np.stack([z[labels == c].mean(axis=0) if np.any(labels == c) else z.mean(axis=0)
                        for c in range(len(touched))])
    means_u = rng.standard_normal((len(untouched), k)) * z.std(axis=0)
    return SceneModel(tuple(touched) + tuple(untouched), frozenset(untouched), center, basis,
                      np.concatenate([means_t, means_u]), info={"k": k, "latency_only": True}).to_params()


__all__ = ["export_run", "export_random_trunk", "latency_scene_model", "matched_beta", "press_partition", "grid_presses", "refit_router", "check_zero_shot"]

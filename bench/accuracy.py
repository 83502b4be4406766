"""The bench's accuracy half (`vs2t-edge bench`, runtime/bench.py): on presses a bundle never
trained on (the manifest records which presses trained it), per press ZSL and GZSL acc_t / acc_u /
H at the bundle's beta (the paper's protocol); per item (random presses of one fabric) for 1, 3,
5, 9 presses and the sequential rule; and per item, by bins (runtime/sorting.py) on scenes of 5
touched + 3 untouched bundle classes, for the bundle's scene decision and the router's posterior.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

from vs2t_edge.runtime.progress import Line

ITEM_PRESSES = (1, 3, 5, 9)
SEQ_CONFIDENCE, SEQ_MAX_PRESSES = 0.95, 9
BIN_SCENES, BIN_MAX_PRESSES = 12, 5  # by-bins scenes (runtime/sorting.py), as training's report draws them


def _log(msg: str) -> None:
    print(f"bench: {msg}", file=sys.stderr, flush=True)

# ------------------------------------------------------------------ data


def _dataset_of(manifest: dict, override: str | None) -> Path | None:
    prov = manifest.get("provenance", {})
    for cand in (override, prov.get("data", {}).get("dataset"), prov.get("dataset")):
        if cand and Path(cand).is_dir():
            return Path(cand)
    return None


def eval_presses(manifest: dict, ds, cap: int) -> dict[str, list[int]]:
    """Presses the bundle never trained on, per fabric: touched = its test presses and the presses
    training did not extract that come after its last training or validation press (fit on earlier
    presses, test on later ones: an unextracted press between two training presses is not a later
    one); untouched = all; at most ``cap`` each, evenly spread over the grid (``cap`` <= 0: no cap)."""
    part = manifest["provenance"]["data"]["touched_presses"]
    out = {}
    for fid in manifest["classes"]["touched"]:
        last_fit = max(part[fid]["train"] + part[fid]["val"], default=-1)
        idx = sorted(part[fid]["test"] + [i for i in part[fid]["unused"] if i > last_fit])
        out[fid] = _spread(idx, cap)
    for fid in manifest["classes"]["untouched"]:
        out[fid] = _spread(list(range(len(ds.by_id(fid).presses))), cap)
    return out


def _spread(idx: list[int], k: int) -> list[int]:
    if k <= 0 or len(idx) <= k:
        return list(idx)
    return [idx[int(j)] for j in np.linspace(0, len(idx) - 1, k).round().astype(int)]



# ------------------------------------------------------------------ accuracy


def press_outputs(model, ds, presses: dict[str, list[int]], log: Callable[[str], None] = _log,
                  jpeg_quality: int | None = None, scale: int | None = None) -> dict:
    """Per press: label (class index in model.classes), soft log posterior, novelty, logits_u.
    ``jpeg_quality``: each frame (and the no-contact frame) goes through the camera's JPEG at that
    quality and is decoded at the bundle's scale, as a UVC camera hands it (runtime.preprocess
    ``camera_press``, what training with ``camera_jpeg`` reads); None: lossless frames. ``scale``:
    the camera's decode scale for those frames (bench/press_timing.py ``decode_scale``, the cell's
    ``devices.camera.decode_scale``); None: the bundle's own (``camera_scale``)."""
    from vs2t_edge.runtime.novelty import log_softmax
    from vs2t_edge.runtime.preprocess import camera_press, camera_reference, camera_scale

    q, spec = jpeg_quality or 0, model.preprocess_spec
    scale = camera_scale(spec) if scale is None else scale
    cls_index = {c: i for i, c in enumerate(model.classes)}
    lp, nov, lsu, lab, feat = [], [], [], [], []
    line = Line()
    for j, (fid, idx) in enumerate(presses.items()):
        fab = ds.by_id(fid)
        if q == YUYV:
            ref, x = _through_yuyv(fab, idx, spec, scale)
        else:
            # through the JPEG, the no-contact frame is decoded reduced like the frames and prepared at that scale
            ref = camera_reference(fab.load_reference(), spec, q, f"{fid} reference frame", scale)
            x = np.stack([camera_press(fab.load_press(i), ref, spec, q, f"{fid} press {i}", scale) for i in idx])
        for a in range(0, len(x), 32):
            o = model.forward(x[a:a + 32])
            lp.append(model.log_posterior(o))
            nov.append(o.novelty)
            lsu.append(log_softmax(o.logits_u, axis=1))
            feat.append(np.asarray(o.feature, np.float32))
        lab.append(np.full(len(idx), cls_index[fid]))
        line.draw(f"bench: scoring presses, fabric {j + 1}/{len(presses)}", (j + 1) / len(presses))
    line.keep()
    return {"lp": np.concatenate(lp), "novelty": np.concatenate(nov), "lsu": np.concatenate(lsu),
            "label": np.concatenate(lab), "feature": np.concatenate(feat)}


YUYV = "yuyv"  # press_outputs' frames through an uncompressed YUYV camera instead of a JPEG quality


def _through_yuyv(fab, idx: list[int], spec, scale: int):
    """A fabric's no-contact frame and presses as a UVC camera streaming YUYV hands them to the
    cell (runtime/yuyv.py, at the camera's ``scale``): (prepared reference, (n, 3, S, S) inputs)."""
    from vs2t_edge.runtime.preprocess import prepare_reference, preprocess_tactile
    from vs2t_edge.runtime.yuyv import through_camera_yuyv

    ref = prepare_reference(through_camera_yuyv(fab.load_reference(), scale, f"{fab.id} reference frame"), spec, scale)
    x = np.stack([preprocess_tactile(through_camera_yuyv(fab.load_press(i), scale, f"{fab.id} press {i}"), ref, spec,
                                     scale) for i in idx])
    return ref, x


def through_jpeg(frame: np.ndarray, quality: int, scale: int = 1) -> np.ndarray:
    """``frame`` as a camera streaming MJPEG at ``quality`` hands it: the runtime's
    ``through_camera_jpeg`` (encoded, then decoded at 1/``scale`` by the cell's own decode)."""
    from vs2t_edge.runtime.preprocess import through_camera_jpeg

    return through_camera_jpeg(frame, quality, scale)


def accuracy_frames(model, jpeg_quality: int, through_jpeg: bool, lossless: bool = False,
                    through_yuyv: bool = False) -> tuple[int | str | None, str]:
    """(quality the held-out frames go through, ``YUYV``, or None for lossless; what the report says):
    ``--accuracy-through-jpeg``'s ``jpeg_quality`` when asked; YUYV when asked
    (``--accuracy-through-yuyv``); lossless when asked (``--accuracy-lossless``); else the bundle's
    own camera JPEG (manifest ``camera_jpeg``: trained on frames through it) when it records one;
    else lossless."""
    if through_jpeg + lossless + through_yuyv > 1:
        raise ValueError("frames through JPEG, through YUYV or lossless: one of them")
    if lossless:
        return None, "lossless (the dataset's PNG)"
    if through_yuyv:
        return YUYV, "through YUYV 4:2:2 (BT.601 video range), made BGR at the cell camera's scale"
    if through_jpeg:
        return int(jpeg_quality), f"through JPEG q={int(jpeg_quality)}, decoded at the cell camera's scale"
    own = int(getattr(model, "camera_jpeg", 0) or 0)
    if own:
        return own, f"through JPEG q={own} (the bundle's camera_jpeg: it trained on such frames), decoded at its scale"
    return None, "lossless (the dataset's PNG)"


def _per_class_mean(correct: np.ndarray, labels: np.ndarray) -> float:
    if correct.size == 0:
        return math.nan
    return float(np.mean([np.mean(correct[labels == c]) for c in np.unique(labels)]))


def _h(a: float, b: float) -> float:
    return 0.0 if a + b == 0 or math.isnan(a) or math.isnan(b) else 2 * a * b / (a + b)


def accuracy(model, out: dict, n_items: int = 100, seed: int = 0) -> dict:
    """Per press and per item accuracies (module doc); all in percent."""
    from vs2t_edge.runtime.router_eval import gzsl_accuracies

    ct = len(model.touched)
    lab, lp, lsu, nov = out["label"], out["lp"], out["lsu"], out["novelty"]
    is_t = lab < ct
    res: dict[str, Any] = {"eval_presses": {"touched": int(is_t.sum()), "untouched": int((~is_t).sum())}}
    # per press: the paper's protocol (hard route at beta)
    routed_u = nov > model.beta
    pred_t = np.argmax(lp[:, :ct], axis=1)  # = argmax logits_t (the gate is a constant per press)
    pred_u = ct + np.argmax(lsu, axis=1)
    g = gzsl_accuracies(routed_u[is_t], pred_t[is_t] == lab[is_t], routed_u[~is_t], pred_u[~is_t] == lab[~is_t],
                        lab[is_t], lab[~is_t])
    res["press"] = {"zsl": 100 * _per_class_mean(pred_u[~is_t] == lab[~is_t], lab[~is_t]),
                    "acc_t": 100 * g["acc_t"], "acc_u": 100 * g["acc_u"], "H": 100 * g["H"],
                    "touched_routed_untouched": 100 * float(np.mean(routed_u[is_t])),
                    "untouched_routed_untouched": 100 * float(np.mean(routed_u[~is_t]))}
    if getattr(model, "scene_model", None) is not None:
        res["press_scene"] = scene_press_accuracy(model, out)
    # per item
    items, item_lab, replaced = draw_items(lab, n_items, seed)
    it_t = item_lab < ct
    res["items"] = {"per_class": n_items, "drawn_with_replacement": replaced,
                    "note": "presses of one fabric drawn at random; scene = all bundle classes"}
    for k in ITEM_PRESSES:
        acc_lp = lp[items[:, :k]].sum(axis=1)  # (items, C): log posteriors summed over k presses
        pred = np.argmax(acc_lp, axis=1)
        zs = ct + np.argmax(lsu[items[:, :k]].sum(axis=1), axis=1)
        at = _per_class_mean(pred[it_t] == item_lab[it_t], item_lab[it_t])
        au = _per_class_mean(pred[~it_t] == item_lab[~it_t], item_lab[~it_t])
        res["items"][str(k)] = {"zsl": 100 * _per_class_mean(zs[~it_t] == item_lab[~it_t], item_lab[~it_t]),
                                "acc_t": 100 * at, "acc_u": 100 * au, "H": 100 * _h(at, au)}
    # the sequential rule
    correct, used, unknown = sequential_items(list(model.classes), lp, items, item_lab)
    at = _per_class_mean(correct[it_t], item_lab[it_t])
    au = _per_class_mean(correct[~it_t], item_lab[~it_t])
    res["sequential"] = {"confidence": SEQ_CONFIDENCE, "max_presses": SEQ_MAX_PRESSES,
                         "presses_mean": float(used.mean()), "presses_touched": float(used[it_t].mean()),
                         "presses_untouched": float(used[~it_t].mean()), "acc_t": 100 * at, "acc_u": 100 * au,
                         "H": 100 * _h(at, au), "unknown": 100 * float(unknown.mean())}
    res["bins"] = by_bins(model, out, seed=seed)
    return res


def draw_items(lab: np.ndarray, n_items: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, int]:
    """``n_items`` items per class, each ``max(ITEM_PRESSES, SEQ_MAX_PRESSES)`` random presses of
    that class (with replacement when it has fewer): (items, item labels, items drawn with
    replacement). The draw depends only on the labels and the seed: two bundles scored on the
    same presses get the same items."""
    rng = np.random.default_rng(seed)
    kmax = max(max(ITEM_PRESSES), SEQ_MAX_PRESSES)
    items, item_lab, replaced = [], [], 0
    for c in np.unique(lab):
        rows = np.flatnonzero(lab == c)
        for _ in range(n_items):
            if len(rows) >= kmax:
                items.append(rng.choice(rows, kmax, replace=False))
            else:
                items.append(rng.choice(rows, kmax, replace=True))
                replaced += 1
        item_lab += [c] * n_items
    return np.stack(items), np.asarray(item_lab), replaced


def sequential_items(classes: list, lp: np.ndarray, items: np.ndarray, item_lab: np.ndarray):
    """The sequential rule (runtime.evidence, SEQ_CONFIDENCE, at most SEQ_MAX_PRESSES) on each
    item: (right, presses used, decided unknown), one entry per item."""
    from vs2t_edge.runtime.evidence import UNKNOWN, Evidence

    used, correct, unknown = [], [], []
    for row, c in zip(items, item_lab):
        ev = Evidence(classes, SEQ_CONFIDENCE, SEQ_MAX_PRESSES)
        d = None
        for r in row[:SEQ_MAX_PRESSES]:
            d = ev.add(_Score(dict(zip(classes, lp[r]))))
            if d is not None:
                break
        used.append(d.presses)
        correct.append(d.label == classes[c])
        unknown.append(d.label == UNKNOWN)
    return np.asarray(correct), np.asarray(used), np.asarray(unknown)


def scene_press_accuracy(model, out: dict) -> dict:
    """The paper's per-press protocol for the decision the cell makes per press: the bundle's scene
    model, one softmax over every bundle class (not the fabrics it knows only to refuse), on the
    same presses as the router's columns - acc_t, acc_u (per-class means), H, and ZSL (untouched
    presses among the untouched classes). Percent. As training's report computes it
    (train/decision.py ``evaluate_scenes`` "press_gzsl"), on the graph's float32 feature."""
    sm = model.scene_model
    pm = sm.subset([c for c in sm.classes if c not in sm.known_only])
    lab, ct = out["label"], len(model.touched)
    scores = pm.scores(pm.sq_distances(out["feature"]))
    pred = np.argmax(scores, axis=1)
    is_t = lab < ct
    at = _per_class_mean(pred[is_t] == lab[is_t], lab[is_t])
    au = _per_class_mean(pred[~is_t] == lab[~is_t], lab[~is_t])
    zs = ct + np.argmax(scores[:, ct:], axis=1)
    return {"acc_t": 100 * at, "acc_u": 100 * au, "H": 100 * _h(at, au),
            "zsl": 100 * _per_class_mean(zs[~is_t] == lab[~is_t], lab[~is_t])}


def by_bins(model, out: dict, n_scenes: int = BIN_SCENES, seed: int = 0) -> dict:
    """Per item, by bins (runtime/sorting.py), on scenes of 5 touched + 3 untouched bundle classes
    with off-scene pieces of the classes a scene leaves out: the bundle's scene decision (when it
    carries one) and the router's posterior with the fixed confidence (the baseline), on the same
    scenes and presses; for a scene model that can learn also the same scenes as jobs with operator
    labels (``scene_model_labels``, runtime/feedback.py), and with a labelled teach piece of each
    untouched fabric first (``scene_model_teach``). Percent; presses per item."""
    from vs2t_edge.runtime import sorting as so

    classes = list(model.classes)
    lab = out["label"]
    touched, untouched = list(model.touched), list(model.untouched)
    if len(touched) < 2 or not untouched:
        return {}
    scenes = so.draw_scenes(touched, untouched, (), n_scenes, seed=seed)
    tables = {"router": {classes[c]: so.posterior_presses(classes, out["lp"][lab == c]) for c in np.unique(lab)}}
    rules = {"router": so.plain_evidence(SEQ_CONFIDENCE, BIN_MAX_PRESSES)}
    if getattr(model, "scene_model", None) is not None:
        tables["scene_model"] = {classes[c]: so.scene_model_presses(model.scene_model, out["feature"][lab == c],
                                                                    np.float32) for c in np.unique(lab)}
        rules["scene_model"] = so.scene_evidence(model.scene_model, BIN_MAX_PRESSES)
    res = {"scenes": n_scenes, "max_presses": BIN_MAX_PRESSES}
    runs = {name: so.simulate_scenes(scenes, table, rules[name], max_presses=BIN_MAX_PRESSES, seed=seed + 1)
            for name, table in tables.items()}
    if getattr(model, "scene_model", None) is not None and model.scene_model.for_labels() is not None:
        # the same scenes as jobs, every rejected piece labelled by the operator (runtime/feedback.py)
        runs["scene_model_labels"] = so.simulate_with_labels(scenes, tables["scene_model"], model.scene_model,
                                                             max_presses=BIN_MAX_PRESSES, seed=seed + 2)
        # and with a labelled teach piece of each untouched fabric before each job (docs/cell.md)
        runs["scene_model_teach"] = so.simulate_with_labels(scenes, tables["scene_model"], model.scene_model,
                                                            max_presses=BIN_MAX_PRESSES, seed=seed + 2, teach=True)
    for name, recs in runs.items():
        summary = so.summarise(recs)
        res[name] = {kind: {k: (100 * v if k in so.OUTCOMES else v) for k, v in r.items()}
                     for kind, r in [("all", summary["all"]), *summary["by_kind"].items()]}
    if "scene_model_teach" in res and runs["scene_model_teach"]:
        # the teach pieces are no pieces of the table, but the arm pressed them: per counted piece
        n = len(runs["scene_model_teach"])
        res["scene_model_teach"]["all"]["teach_presses"] = so.teach_presses(
            scenes, tables["scene_model"], True, BIN_MAX_PRESSES) / n
    return res


def pieces_per_minute(row: dict, arm) -> None:
    """Adds ``pieces_per_min`` (per decision: scored sequentially / overlapped) to ``row``'s by-bins
    table, from the decision's presses per piece (its teach pieces' presses spread over them),
    ``arm`` (runtime.sorting.ArmTimes) and this variant's whole press as the cell pays it (p50 at
    the most threads timed)."""
    from vs2t_edge.runtime import sorting as so

    press = row.get("press", {})
    if not press:
        return
    score_s = press[max(press, key=int)]["p50_ms"] / 1e3
    bins = row.get("accuracy", {}).get("bins", {})
    # a decision whose jobs start with teach pieces pays their presses too (``teach_presses``, per piece)
    bins["pieces_per_min"] = {
        name: {mode: so.items_per_minute(b["all"]["presses"] + b["all"].get("teach_presses", 0.0), arm, score_s,
                                         overlap)
               for mode, overlap in (("sequential", False), ("overlapped", True))}
        for name, b in bins.items() if isinstance(b, dict) and "all" in b}


class _Score:
    __slots__ = ("log_posterior",)

    def __init__(self, lp: dict) -> None:
        self.log_posterior = lp

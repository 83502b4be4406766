"""A bundle whose tactile feature is a numpy descriptor (runtime/tactile_descriptor.py), not an
ONNX trunk: ``write_bundle(..., descriptor=Descriptor(...))`` comes here (docs/bundle.md,
"A descriptor instead of a trunk").

What differs from a trunk bundle: no ``trunk.onnx``; the manifest's ``"trunk": {"kind":
"descriptor", "name", "dim", "file": "descriptor.npz"}`` names the function and holds the
per-dimension standardisation an ONNX trunk folds in; the probe adds ``probe_frames.npy`` (the
reference and press it was computed from), so the cell checks its own descriptor function as well
as the heads and router. Everything else - heads graph, router, gating fit, scene model, hashes,
seal, the runtime's own verification before anything is left in place - is ``write_bundle``'s.
"""

from __future__ import annotations

import datetime as _dt
import math
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import nn

from vs2t_edge.runtime import bundle as rb
from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime import tactile_descriptor as td
from vs2t_edge.runtime.preprocess import TactilePreprocess, camera_frame

from vs2t_edge.export import export as ex

# the descriptor is computed by the same numpy/OpenCV code at export and on the cell; float32
# rounding and an OpenCV of another build are all that can differ
PROBE_TOLERANCE = {"feature": 1e-4, "logits": 1e-4, "novelty": 1e-4}


@dataclass(frozen=True)
class Descriptor:
    """The tactile feature of a descriptor bundle: ``name`` (``tactile_descriptor.NAMES``), the
    standardisation fitted on touched training presses, and the [reference, press] frames of one
    touched training press for the probe."""

    name: str
    mean: np.ndarray  # (D,)
    std: np.ndarray  # (D,) > 0
    probe_frames: np.ndarray  # (2, H, W, 3) uint8: the no-contact reference, then the press


def write_descriptor_bundle(out_dir: Path | str, *, descriptor: Descriptor, cls_t: nn.Module, cls_u: nn.Module,
                            router: nv.Router, touched: Sequence[str], untouched: Sequence[str], beta: float,
                            calibration: np.ndarray, validation: np.ndarray | None = None,
                            touched_heldout: np.ndarray | None = None, gating_temperature: float | None = None,
                            operating_point: str = "balanced on validation fabrics", provenance: dict | None = None,
                            opset: int = ex.OPSET, scene_model: dict | None = None, threads: int = 2,
                            log: Callable[[str], None] = lambda m: None, camera_jpeg: int = 0, **_unused: Any) -> dict:
    """Write and verify a descriptor bundle; returns the manifest. ``calibration``, ``validation``,
    ``touched_heldout``: RAW descriptors (N, D) (of touched presses, validation-fabric presses and
    held-out touched presses: the gating fit, as ``write_bundle``)."""
    name = descriptor.name
    if name not in td.NAMES:
        raise ex.ExportError(f"descriptor {name!r}: this runtime computes {list(td.NAMES)}")
    dim = td.DIM[name]
    touched, untouched = [str(c) for c in touched], [str(c) for c in untouched]
    if not touched or not untouched:
        raise ex.ExportError("a bundle needs at least one touched and one untouched class")
    calibration = np.asarray(calibration, np.float32)
    if calibration.ndim != 2 or calibration.shape[1] != dim or len(calibration) < 1:
        raise ex.ExportError(f"calibration descriptors are {calibration.shape}, expected (N>=1, {dim})")
    feature = td.DescriptorFeature(name, np.asarray(descriptor.mean, np.float32),
                                   np.asarray(descriptor.std, np.float32))
    frames = np.ascontiguousarray(descriptor.probe_frames, np.uint8)
    out = Path(out_dir)
    ex._prepare_out(out)
    heads = ex._Heads(cls_t.eval(), cls_u.eval()).eval()
    with tempfile.TemporaryDirectory(dir=out.parent if out.parent.exists() else None) as tmp_s:
        tmp = Path(tmp_s)
        log(f"descriptor {name} ({dim} numbers, no trunk graph); exporting the heads (opset {opset})")
        ex.export_onnx(heads, torch.zeros(1, dim), tmp / "heads.onnx", "feature", ["logits_t", "logits_u"], opset)
        sess_h = rb.open_session(tmp / "heads.onnx", threads)
        parity_f = feature.standardise(calibration[:8])
        with torch.no_grad():
            lt_torch, lu_torch = (t.numpy() for t in heads(torch.from_numpy(parity_f)))
        lt_ort, lu_ort = sess_h.run(None, {"feature": parity_f})
        checks: dict[str, Any] = {"parity_torch_vs_onnxruntime": {
            "frames": int(len(parity_f)), "logits_t": ex._rel(lt_ort, lt_torch), "logits_u": ex._rel(lu_ort, lu_torch),
            "tolerance": ex.PARITY_TOLERANCE}}
        bad = {k: v for k, v in checks["parity_torch_vs_onnxruntime"].items()
               if k in ("logits_t", "logits_u") and not v <= ex.PARITY_TOLERANCE}
        if bad:
            raise ex.ExportError(f"torch and onnxruntime disagree beyond {ex.PARITY_TOLERANCE}: {bad}")

        def score(raw: np.ndarray):
            f = feature.standardise(raw)
            lt, lu = sess_h.run(None, {"feature": f})
            return f, lt, lu, ex._novelty(router, f, lt, lu)

        how = "given"
        have_val = validation is not None and len(validation) and touched_heldout is not None and len(touched_heldout)
        nt = score(touched_heldout if have_val else calibration)[3]
        scale = ex.gating_scale(nt)
        if gating_temperature is None:
            if have_val:
                nu = score(validation)[3]
                gating_temperature = ex.fit_gating_temperature(nt, nu, beta, scale)
                how = (f"maximum likelihood of the route on {len(nt)} held-out touched and {len(nu)} "
                       "validation-fabric presses, offset fixed at beta")
            else:
                gating_temperature = ex.robust_temperature(nt, scale)
                how = "1.4826 x MAD of the calibration presses' asinh novelty (no validation presses given)"
        if not (gating_temperature > 0 and math.isfinite(gating_temperature)):
            raise ex.ExportError(f"gating temperature {gating_temperature} must be finite and > 0")

        # the probe: computed here from its frames by the cell's own function, so the cell checks
        # that function too (runtime.inference.TactileModel._warm_and_probe)
        probe = td.describe(name, frames[1], frames[0])[None]
        f, lt, lu, nov = score(probe)
        np.save(tmp / "probe_input.npy", probe)
        np.save(tmp / "probe_frames.npy", frames)
        np.savez(tmp / "probe_expected.npz", feature=f, logits_t=lt, logits_u=lu, novelty=np.asarray(nov, np.float64))
        np.savez(tmp / "descriptor.npz", mean=feature.mean, std=feature.std)
        np.savez(tmp / "router.npz", **{k: np.asarray(v) for k, v in router.to_params().items()})
        if scene_model is not None:
            np.savez(tmp / "decision.npz", **{k: np.asarray(v) for k, v in scene_model.items()})
        heads_graph = {"file": "heads.onnx", "opset": rb.read_onnx_opsets(tmp / "heads.onnx")[""],
                       **ex.graph_io(tmp / "heads.onnx"), "precision": "fp32"}
        files = sorted(p.name for p in tmp.iterdir())
        manifest = {
            "format": rb.FORMAT,
            "format_version": rb.FORMAT_VERSION,
            "classes": {"touched": touched, "untouched": untouched},
            # kept for the loader's checks and use_reference; size, crop and scaling do not apply
            "preprocess": TactilePreprocess().to_dict(),
            **ex.camera_jpeg_entry(camera_jpeg),
            "feature_dim": dim,
            "trunk": {"kind": td.KIND, "name": name, "dim": dim, "file": "descriptor.npz",
                      "rule": "feature = (runtime.tactile_descriptor.<name>(press, item's no-contact frame) - mean) "
                              "/ std; mean and std of touched training presses"},
            "graphs": {"heads": heads_graph},
            "router": {"name": router.name, "file": "router.npz"},
            **({"decision": {"kind": str(scene_model["kind"]), "file": "decision.npz",
                             "rule": "as a trunk bundle's (docs/bundle.md)"}} if scene_model is not None else {}),
            "beta": float(beta),
            "operating_point": operating_point,
            "gating": {"transform": "asinh", "scale": scale, "temperature": float(gating_temperature), "how": how,
                       "rule": "P(untouched|x) = sigmoid((asinh(novelty/scale) - asinh(beta/scale)) / temperature)",
                       "scale_is": "median |novelty| of held-out touched presses"},
            "probe": {"input": "probe_input.npy", "frames": "probe_frames.npy", "expected": "probe_expected.npz",
                      "tolerance": PROBE_TOLERANCE,
                      "note": "a touched training press and its item's no-contact frame; input = the raw descriptor of "
                              "frames [reference, press]; expected = at export, max|diff|/max|expected|"},
            "checks": checks,
            "files": {n: rb.sha256_file(tmp / n) for n in files},
            "provenance": {"time_utc": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                           "git_commit": ex._git_commit(), "versions": ex._versions(), "command": " ".join(sys.argv),
                           **(provenance or {})},
        }
        manifest = ex.seal_verify_and_place(manifest, tmp, out, threads)
    log(f"bundle written to {out} and verified")
    return manifest


def _descriptors(ds, name: str, fid: str, indices: Sequence[int], camera_jpeg: int = 0) -> np.ndarray:
    """Raw descriptors of those presses, each frame through the camera's JPEG at ``camera_jpeg``
    (full size; 0: lossless) as training read them (train.features.descriptor_table)."""
    fab = ds.by_id(fid)
    ref = td.prepare_reference(camera_frame(fab.load_reference(), camera_jpeg, 1, f"{fid} reference frame"))
    return np.stack([td.describe(name, camera_frame(fab.load_press(i), camera_jpeg, 1, f"{fid} press {i}"), ref)
                     for i in indices]).astype(np.float32)


def export_descriptor_run(run_dir: Path, art, out_dir: Path | str, *, dataset: Path | str | None = None,
                          calibration_frames: int = 64, log: Callable[[str], None] = lambda m: None,
                          threads: int = 2) -> dict:
    """``from_run.export_run`` of a run trained with a descriptor as its tactile feature: the run's
    heads, stored router, beta and scene model; the standardisation it trained with; the gating fit
    on held-out touched and validation-fabric presses, the probe on a touched training press.
    Untouched fabrics are never read (``check_zero_shot``)."""
    from vs2t_edge.export.from_run import _run_profile, _spread, check_zero_shot, press_partition
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.train.artifacts import build_modules, load_router

    name = art.tactile_feature
    ds_root = Path(dataset or art.dataset)
    if not ds_root.is_dir():
        raise ex.ExportError(f"the run's dataset {ds_root} is not there (the probe and the gating fit need its "
                             "touched presses); pass --dataset")
    ds = load_dataset(ds_root)
    _, cls_t, cls_u = build_modules(art)
    max_presses = _run_profile(Path(run_dir)).get("max_presses")
    seed = int(art.info.get("split_seed", 0))
    part = press_partition({f.id: len(f.presses) for f in ds.fabrics}, art.touched, seed, max_presses)
    calib_ids = [fid for fid in (art.touched_fabric_ids or art.touched) if fid in part]
    for what, fids in (("the probe and calibration", calib_ids), ("the gating fit (held-out touched presses)",
                                                                  art.touched),
                       ("the gating fit (validation presses)", art.validation)):
        check_zero_shot({fid: [0] for fid in fids}, art.untouched, what)
    per = max(1, math.ceil(calibration_frames / len(calib_ids)))
    q = art.camera_jpeg
    log(f"{name}: descriptors of {per} training presses of each of {len(calib_ids)} touched fabrics"
        + (f" (frames through the camera's JPEG at q{q}, as the run trained)" if q else ""))
    calib = np.concatenate([_descriptors(ds, name, fid, _spread(part[fid]["train"], per), q) for fid in calib_ids])
    heldout = np.concatenate([_descriptors(ds, name, fid, part[fid]["val"], q) for fid in art.touched])
    validation = np.concatenate([_descriptors(ds, name, fid, _spread(range(len(ds.by_id(fid).presses)), 12), q)
                                 for fid in art.validation]) if art.validation else None
    probe_fab = ds.by_id(calib_ids[0])
    frames = np.stack([probe_fab.load_reference(), probe_fab.load_press(part[calib_ids[0]]["train"][0])])
    prov = {"run": str(Path(run_dir).resolve()), "trained": True, "tactile_feature": name,
            "data": {"dataset": str(ds_root.resolve()), "split_seed": seed, "max_presses": max_presses,
                     "validation": list(art.validation), "touched_presses": part, "calibration_fabrics": calib_ids},
            "router": {"name": art.router_name, "refitted_at_export": False,
                       "source": "the run's stored router and beta (artifacts/model.pt)"}, "run_info": art.info}
    return ex.write_bundle(out_dir, trunk=None, cls_t=cls_t, cls_u=cls_u, router=load_router(art), touched=art.touched,
                           untouched=art.untouched, preprocess=art.tactile_preprocess, beta=art.beta,
                           calibration=calib, validation=validation, touched_heldout=heldout, provenance=prov,
                           operating_point=f"{art.router_name} router, beta balanced on validation fabrics "
                                           f"{', '.join(art.validation)}",
                           scene_model=art.scene_model, threads=threads, log=log, camera_jpeg=q,
                           descriptor=Descriptor(name, art.feature_mean, art.feature_std, frames))


__all__ = ["Descriptor", "write_descriptor_bundle", "export_descriptor_run", "PROBE_TOLERANCE"]

"""Training run -> verified ONNX bundle (docs/bundle.md).

``write_bundle`` is the core: torch modules + router + class names + preprocessing + frames in,
bundle folder out. It exports the trunk and the heads (opset ``OPSET``), checks torch against
onnxruntime on real frames (train/serve parity, recorded in the manifest), quantises the trunk
statically to int8 when asked (export/quantize.py; calibrated on touched presses only), fits the
gating temperature, records a probe press with the outputs onnxruntime gives for it, hashes
every file and finally loads the folder with the cell's own ``TactileModel.load`` - a bundle
that does not pass the runtime's verification is never left behind.

A run folder becomes a bundle through export/from_run.py (``export_run``, ``export_random_trunk``).
"""

from __future__ import annotations

import datetime as _dt
import io
import json
import math
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import torch
from torch import nn

from vs2t_edge.export import fuse as fz
from vs2t_edge.export.int8_scene import shift_real_means
from vs2t_edge.runtime import bundle as rb
from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime.inference import fused_novelty
from vs2t_edge.runtime.router_eval import fit_gating_temperature, gating_scale, robust_temperature
from vs2t_edge.runtime.preprocess import TactilePreprocess

# The newest opset torch 2.13's TorchScript exporter writes (21+ warns 'not supported'); onnxruntime
# >= 1.17 (pyproject's floor) implements it; runtime.bundle accepts MIN_OPSET..MAX_OPSET (docs/bundle.md).
OPSET = 20
# torch (float32, its own kernels) vs onnxruntime (fused BN/conv, other summation order) on the
# same frames: max |diff| / max |torch output|. Measured ~1e-6 on the tiny and EfficientNet trunks.
PARITY_TOLERANCE = 1e-4
HEADS_INT8_TOLERANCE = 2e-2  # int8 heads' logits against the float heads' (0.5-1 % on the paper profile's runs)
PROBE_TOLERANCE = {"fp32": {"feature": 1e-4, "logits": 1e-4, "novelty": 1e-4},
                   # int8 kernels may pick other accumulation orders per thread count / CPU
                   "int8": {"feature": 2e-2, "logits": 2e-2, "novelty": 2e-2}}


class ExportError(RuntimeError):
    pass


class _Heads(nn.Module):
    def __init__(self, cls_t: nn.Module, cls_u: nn.Module) -> None:
        super().__init__()
        self.cls_t, self.cls_u = cls_t, cls_u

    def forward(self, f):
        return self.cls_t(f), self.cls_u(f)


def export_onnx(module: nn.Module, example: torch.Tensor, path: Path, input_name: str,
                output_names: Sequence[str], opset: int = OPSET) -> None:
    """TorchScript-based exporter (no onnxscript needed), dynamic batch axis, BN folded."""
    module = module.eval()
    axes = {input_name: {0: "batch"}, **{n: {0: "batch"} for n in output_names}}
    buf = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, example, buf, opset_version=opset, input_names=[input_name],
                          output_names=list(output_names), dynamic_axes=axes, do_constant_folding=True,
                          dynamo=False)
    Path(path).write_bytes(buf.getvalue())


def graph_io(path: Path) -> dict[str, dict[str, list]]:
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    init = {i.name for i in model.graph.initializer}

    def dims(v):
        return [d.dim_value if d.HasField("dim_value") else None for d in v.type.tensor_type.shape.dim]

    return {"inputs": {v.name: dims(v) for v in model.graph.input if v.name not in init},
            "outputs": {v.name: dims(v) for v in model.graph.output}}


def count_macs(path: Path) -> dict[str, int]:
    """Multiply-accumulates of one frame (batch 1) by op type, from the graph itself: Conv =
    C_out x H_out x W_out x (C_in / group) x kH x kW, MatMul/Gemm = M x K x N. Shapes are
    observed, not inferred: every Conv/MatMul/Gemm tensor is made a graph output and the graph
    is run once on zeros (static shape inference cannot see through EfficientNet's computed
    "same" padding). Element-wise ops are not counted (memory-bound, < 1 % of these trunks' MACs)."""
    import onnx
    import onnxruntime as ort
    from onnx import numpy_helper

    model = onnx.load(str(path))
    init = {i.name: list(numpy_helper.to_array(i).shape) for i in model.graph.initializer}
    nodes = [n for n in model.graph.node if n.op_type in ("Conv", "MatMul", "Gemm")]
    present = {o.name for o in model.graph.output}
    wanted = sorted({t for n in nodes for t in list(n.input[:2]) + [n.output[0]] if t and t not in init} - present)
    model.graph.output.extend([onnx.ValueInfoProto(name=t) for t in wanted])
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    inp = sess.get_inputs()[0]
    x = np.zeros([d if isinstance(d, int) else 1 for d in inp.shape], np.float32)
    names = [o.name for o in sess.get_outputs()]
    shapes = {n: list(v.shape) for n, v in zip(names, sess.run(None, {inp.name: x}))}
    shapes.update(init)
    out: dict[str, int] = {}
    for node in nodes:
        macs = 0
        if node.op_type == "Conv":
            w, y = shapes.get(node.input[1]), shapes.get(node.output[0])
            if w and y and len(y) == 4:
                macs = int(np.prod(y[1:])) * int(np.prod(w[1:]))  # w: (C_out, C_in/group, kH, kW)
        else:
            a, b = shapes.get(node.input[0]), shapes.get(node.input[1])
            if a and b:
                trans_b = any(at.name == "transB" and at.i for at in node.attribute)
                k, n = (b[-1], b[-2]) if trans_b else (b[-2], b[-1])
                macs = int(np.prod(a[:-1])) * k * n
        if macs:
            out[node.op_type] = out.get(node.op_type, 0) + macs
    out["total"] = sum(out.values())
    return out


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-6))


def _run_batches(session, x: np.ndarray, chunk: int = 16) -> list[np.ndarray]:
    name = session.get_inputs()[0].name
    outs = [session.run(None, {name: np.ascontiguousarray(x[i:i + chunk], np.float32)}) for i in range(0, len(x), chunk)]
    return [np.concatenate([o[k] for o in outs]) for k in range(len(outs[0]))]


def _novelty(router: nv.Router, feature, logits_t, logits_u) -> np.ndarray:
    """The novelty exactly as runtime.inference computes it (float32 path for Gaussians)."""
    if isinstance(router, nv.GaussianRouter):
        return router.novelty(feature, logits_t, logits_u=logits_u, dtype=np.float32)
    return router.novelty(feature, logits_t, logits_u=logits_u)


def _git_commit() -> str:
    try:
        root = Path(__file__).resolve().parents[1]
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=5)
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "export", "runtime", "train"], cwd=root,
                               capture_output=True, text=True, timeout=5)
        return sha.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "") if sha.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _versions() -> dict[str, str]:
    import onnx
    import onnxruntime

    from vs2t_edge import __version__

    return {"vs2t_edge": __version__, "python": platform.python_version(), "torch": torch.__version__,
            "onnx": onnx.__version__, "onnxruntime": onnxruntime.__version__, "numpy": np.__version__}


def _prepare_out(out: Path) -> None:
    if out.exists():
        if not out.is_dir():
            raise ExportError(f"{out} exists and is not a folder")
        if any(out.iterdir()) and not (out / rb.MANIFEST).is_file():
            raise ExportError(f"{out} is a non-empty folder that is not a bundle; refusing to overwrite it")


def camera_jpeg_entry(camera_jpeg: int) -> dict:
    """The manifest's ``camera_jpeg`` (docs/bundle.md): present only when the model was trained on
    frames through the camera's JPEG, so every lossless bundle's manifest stays what it was."""
    from vs2t_edge.runtime.preprocess import check_camera_jpeg

    q = check_camera_jpeg(camera_jpeg)
    return {"camera_jpeg": q} if q else {}


def write_bundle(out_dir: Path | str, *, trunk: nn.Module | None, cls_t: nn.Module, cls_u: nn.Module, router: nv.Router,
                 touched: Sequence[str], untouched: Sequence[str], preprocess: TactilePreprocess, beta: float,
                 calibration: np.ndarray, trunk_precision: str = "fp32", trunk_arch: str = "custom",
                 validation: np.ndarray | None = None, touched_heldout: np.ndarray | None = None,
                 gating_temperature: float | None = None, operating_point: str = "balanced on validation fabrics",
                 provenance: dict | None = None, calibration_method: str = "minmax", float_convs: int = 0,
                 quant_options: dict | None = None, opset: int = OPSET, scene_model: dict | None = None,
                 threads: int = 2, log: Callable[[str], None] = lambda m: None, descriptor=None,
                 fuse: bool = True, int8_beta: Callable[[np.ndarray], tuple[float, str, dict]] | None = None,
                 heads_precision: str = "fp32", camera_jpeg: int = 0, heads_in_press_graph: bool = False,
                 real_mean_presses: Callable[[], Iterable[tuple[str, np.ndarray]]] | None = None) -> dict:
    """Write and verify a bundle; returns the manifest. ``calibration``: (N, 3, S, S) float32
    preprocessed presses of TOUCHED fabrics (int8 ranges, parity, probe = calibration[0]);
    ``validation`` / ``touched_heldout``: preprocessed presses of validation fabrics and held-out
    touched presses for the gating temperature; ``scene_model``: ``runtime.scene_model.SceneModel``
    parameters (train/decision.py) - the bundle then decides per scene with it (docs/bundle.md).
    ``quant_options``: more keywords of ``export.quantize.quantize_trunk_static`` (float nodes,
    the sensitivity scan and its frames, the percentile).
    ``descriptor``: an ``export.descriptor.Descriptor``; the tactile feature is then that numpy
    descriptor, no trunk graph (``trunk`` None; calibration, validation, held-out: raw descriptors).
    ``fuse``: one press graph (format 2, export/fuse.py: heads and projections folded into
    trunk.onnx; with ``scene_model``, format 3: the scene projection alone folded in, the heads and
    the router's outputs in heads.onnx, off the cell's press path; ``heads_in_press_graph`` writes
    format 2 for it, as before that split: to price it); False writes the two-graph format 1 of
    earlier releases (comparisons, tests).
    ``int8_beta``: for an int8 trunk, maps the deployed graph's novelty of ``touched_heldout`` to
    (beta, what to add to ``operating_point``, what to add to ``provenance``) - the operating point
    set on the graph the cell will run, in the one write.
    ``heads_precision`` int8: the fused graph's CLS_t / CLS_u weights in int8 (``fuse.quantize_heads``;
    beta stays the run's, the gating is fitted on the graph written, as for an int8 trunk).
    ``camera_jpeg``: the tactile camera's MJPEG quality the model was trained on and the given frames
    were read through (train --camera-jpeg), recorded as the manifest's ``camera_jpeg`` (absent for 0).
    ``real_mean_presses``: for an int8 trunk with ``scene_model``, yields (class, preprocessed frames)
    of the presses each real class mean was fitted on; each mean is moved by the int8 trunk's shift
    of them (export/int8_scene.py). None keeps the fp32 trunk's means."""
    if descriptor is not None:
        from vs2t_edge.export.descriptor import write_descriptor_bundle

        return write_descriptor_bundle(out_dir, descriptor=descriptor, cls_t=cls_t, cls_u=cls_u, router=router,
                                       touched=touched, untouched=untouched, beta=beta, calibration=calibration,
                                       validation=validation, touched_heldout=touched_heldout,
                                       gating_temperature=gating_temperature, operating_point=operating_point,
                                       provenance=provenance, opset=opset, scene_model=scene_model, threads=threads,
                                       log=log, camera_jpeg=camera_jpeg)

    if trunk_precision not in ("fp32", "int8"):
        raise ExportError(f"trunk precision {trunk_precision!r}: choose fp32 or int8")
    if heads_precision not in ("fp32", "int8") or (heads_precision == "int8" and not fuse):
        raise ExportError(f"heads precision {heads_precision!r}: fp32, or int8 in the fused press graph")
    touched, untouched = [str(c) for c in touched], [str(c) for c in untouched]
    if not touched or not untouched:
        raise ExportError("a bundle needs at least one touched and one untouched class")
    s = preprocess.size
    calibration = np.ascontiguousarray(calibration, dtype=np.float32)
    if calibration.ndim != 4 or calibration.shape[1:] != (3, s, s) or len(calibration) < 1:
        raise ExportError(f"calibration frames are {calibration.shape}, expected (N>=1, 3, {s}, {s})")
    out = Path(out_dir)
    _prepare_out(out)
    trunk, cls_t, cls_u = trunk.eval(), cls_t.eval(), cls_u.eval()
    heads = _Heads(cls_t, cls_u).eval()
    with torch.no_grad():
        dim = int(trunk(torch.from_numpy(calibration[:1])).shape[1])
    checks: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(dir=out.parent if out.parent.exists() else None) as tmp_s:
        tmp = Path(tmp_s)
        fp32 = tmp / "trunk_fp32.onnx"
        log(f"exporting the {trunk_arch} trunk at {s} px (opset {opset})")
        export_onnx(trunk, torch.from_numpy(calibration[:1]), fp32, "image", ["feature"], opset)
        export_onnx(heads, torch.zeros(1, dim), tmp / "heads.onnx", "feature", ["logits_t", "logits_u"], opset)

        # train/serve parity: torch vs onnxruntime (fp32 graphs) on real frames
        parity_x = calibration[: min(8, len(calibration))]
        with torch.no_grad():
            f_torch = trunk(torch.from_numpy(parity_x)).numpy()
            lt_torch, lu_torch = (t.numpy() for t in heads(torch.from_numpy(f_torch)))
        (f_ort,) = _run_batches(rb.open_session(fp32, threads), parity_x)
        lt_ort, lu_ort = rb.open_session(tmp / "heads.onnx", threads).run(None, {"feature": f_torch})
        checks["parity_torch_vs_onnxruntime"] = {"frames": int(len(parity_x)), "feature": _rel(f_ort, f_torch),
                                                 "logits_t": _rel(lt_ort, lt_torch), "logits_u": _rel(lu_ort, lu_torch),
                                                 "tolerance": PARITY_TOLERANCE}
        bad = {k: v for k, v in checks["parity_torch_vs_onnxruntime"].items()
               if k in ("feature", "logits_t", "logits_u") and not v <= PARITY_TOLERANCE}
        if bad:
            raise ExportError(f"torch and onnxruntime disagree beyond {PARITY_TOLERANCE}: {bad}")

        macs = count_macs(fp32)
        trunk_file = tmp / "trunk.onnx"
        quant: dict | None = None
        if trunk_precision == "int8":
            log(f"static int8 quantisation (QDQ, per-channel) calibrated on {len(calibration)} touched presses")
            from vs2t_edge.export.quantize import quantize_trunk_static

            quant = quantize_trunk_static(fp32, trunk_file, calibration, method=calibration_method,
                                          float_convs=float_convs, log=log, **(quant_options or {}))
            sess32, sess8 = rb.open_session(fp32, threads), rb.open_session(trunk_file, threads)
            (f32,) = _run_batches(sess32, calibration)
            (f8,) = _run_batches(sess8, calibration)
            sess_h = rb.open_session(tmp / "heads.onnx", threads)
            top32 = np.argmax(sess_h.run(None, {"feature": f32})[0], axis=1)
            top8 = np.argmax(sess_h.run(None, {"feature": f8})[0], axis=1)
            cos = np.sum(f32 * f8, 1) / np.maximum(np.linalg.norm(f32, axis=1) * np.linalg.norm(f8, axis=1), 1e-12)
            checks["int8_vs_fp32_on_calibration"] = {"frames": int(len(calibration)), "feature_rel": _rel(f8, f32),
                                                     "feature_cosine_min": float(np.min(cos)),
                                                     "cls_t_top1_agreement": float(np.mean(top32 == top8))}
            scene32 = scene_model
            if scene_model is not None and real_mean_presses is not None:
                try:
                    scene_model, checks["int8_scene_means"] = shift_real_means(
                        scene_model, real_mean_presses(), lambda x: _run_batches(sess32, x)[0],
                        lambda x: _run_batches(sess8, x)[0])
                except ValueError as exc:
                    raise ExportError(str(exc)) from None
                log("the scene model's real class means moved to the int8 trunk's: {classes} classes, {presses} "
                    "training presses, median shift {shift_rms_per_dim_median:.3f} rms a dimension"
                    .format(**checks["int8_scene_means"]))
            if scene_model is not None:
                val = [x for x in (touched_heldout, validation) if x is not None and len(x)]
                if val:
                    checks["int8_scene_decision_on_validation"] = _int8_scene_check(
                        scene32, np.concatenate(val), sess32, sess8, scene_model if scene_model is not scene32 else None)
                    log("int8 against fp32, the scene model's per-press decision on {presses} validation presses: "
                        "{argmax_agreement:.1%} the same class".format(**checks["int8_scene_decision_on_validation"]))
        else:
            shutil.copyfile(fp32, trunk_file)
        fp32.unlink()

        sess_t, sess_h = rb.open_session(trunk_file, threads), rb.open_session(tmp / "heads.onnx", threads)
        fused: dict | None = None
        split = fuse and scene_model is not None and not heads_in_press_graph  # format 3
        if fuse:
            log("folding the scene model's projection into the trunk graph (the heads and the router's apart)"
                if split else "folding the heads and the router's / scene model's projections into the trunk graph")
            fused = fuse_press_graph(trunk_file, tmp / "heads.onnx", cls_t, cls_u, router, scene_model, dim, opset,
                                     calibration, threads, heads_int8=heads_precision == "int8", split=split)
            checks["fused_vs_two_graphs"] = fused["check"]
            if split:  # heads.onnx now holds the heads and the router's outputs
                sess_h = rb.open_session(tmp / "heads.onnx", threads)
            else:
                (tmp / "heads.onnx").unlink()
            sess_t = rb.open_session(trunk_file, threads)

        def score(x: np.ndarray):
            if fused is not None:
                got = dict(zip(fused["outputs"], _run_batches(sess_t, x)))
                if split:
                    got.update(zip(fused["heads_outputs"], _run_batches(sess_h, got["feature"])))
                f, lt, lu = got["feature"], got["logits_t"], got["logits_u"]
                nov = fused_novelty(router, f, lt, lu, got.get(fz.ROUTER_OUT), got.get(fz.NOVELTY_OUT))
                return f, lt, lu, nov, {k: got[k] for k in (fz.ROUTER_OUT, fz.NOVELTY_OUT, fz.SCENE_OUT) if k in got}
            (f,) = _run_batches(sess_t, x)
            lt, lu = sess_h.run(None, {"feature": f})
            return f, lt, lu, _novelty(router, f, lt, lu), {}

        have_val = validation is not None and len(validation) and touched_heldout is not None and len(touched_heldout)
        nt = score(touched_heldout if have_val else calibration)[3]
        if int8_beta is not None and trunk_precision == "int8":
            if touched_heldout is None or not len(touched_heldout):
                raise ExportError("moving beta for the int8 graph needs held-out touched presses")
            beta, note, prov_more = int8_beta(nt if have_val else score(touched_heldout)[3])
            operating_point, provenance = operating_point + note, {**(provenance or {}), **prov_more}
        # gate scale and temperature on the deployed graph's own scores
        how = "given"
        scale = gating_scale(nt)
        if gating_temperature is None:
            if have_val:
                nu = score(validation)[3]
                gating_temperature = fit_gating_temperature(nt, nu, beta, scale)
                how = (f"maximum likelihood of the route on {len(nt)} held-out touched and {len(nu)} "
                       "validation-fabric presses, offset fixed at beta")
            else:
                gating_temperature = robust_temperature(nt, scale)
                how = "1.4826 x MAD of the calibration presses' asinh novelty (no validation presses given)"
        if not (gating_temperature > 0 and math.isfinite(gating_temperature)):
            raise ExportError(f"gating temperature {gating_temperature} must be finite and > 0")

        probe = calibration[:1]
        f, lt, lu, nov, proj = score(probe)
        np.save(tmp / "probe_input.npy", probe)
        np.savez(tmp / "probe_expected.npz", feature=f, logits_t=lt, logits_u=lu, novelty=np.asarray(nov, np.float64),
                 **proj)
        np.savez(tmp / "router.npz", **{k: np.asarray(v) for k, v in router.to_params().items()})
        if scene_model is not None:
            np.savez(tmp / "decision.npz", **{k: np.asarray(v) for k, v in scene_model.items()})

        graphs = {}
        for key, path in (("trunk", trunk_file), *(() if fused and not split else (("heads", tmp / "heads.onnx"),))):
            graphs[key] = {"file": path.name, "opset": rb.read_onnx_opsets(path)[""], **graph_io(path)}
        graphs["trunk"].update(arch=trunk_arch, precision=trunk_precision, input_size_px=s, macs_per_frame=macs)
        if quant:
            graphs["trunk"]["quantisation"] = quant
        if fused:
            graphs["trunk"]["fused"] = fused["manifest"]
        if split:
            graphs["heads"].update(precision=heads_precision, fused=fused["heads_manifest"])
        elif not fused:
            graphs["heads"]["precision"] = "fp32"
        tolerance = dict(PROBE_TOLERANCE[trunk_precision])
        if fused:  # the projections are linear in the feature, amplified like the novelty
            tolerance["projection"] = tolerance["novelty"]
        if heads_precision == "int8":  # the logits (and a novelty made of them) from integer kernels
            tolerance.update(logits=PROBE_TOLERANCE["int8"]["logits"], novelty=PROBE_TOLERANCE["int8"]["novelty"])
        files = sorted(p.name for p in tmp.iterdir())
        manifest = {
            "format": rb.FORMAT,
            "format_version": 3 if split else 2 if fused else 1,
            "classes": {"touched": touched, "untouched": untouched},
            "preprocess": preprocess.to_dict(),
            **camera_jpeg_entry(camera_jpeg),
            "feature_dim": dim,
            "graphs": graphs,
            "router": {"name": router.name, "file": "router.npz"},
            **({"decision": {"kind": str(scene_model["kind"]), "file": "decision.npz",
                             "rule": "per press: softmax over the scene's classes of -d2/(2 T) + b [untouched] "
                                     "(runtime/scene_model.py); per item: weighted evidence, off-scene checks, "
                                     "confidence per kind (runtime/evidence.py); fitted on validation fabrics"
                                     + ("; fitted on the fp32 trunk's features and applied to the int8 trunk's "
                                        "features" + (", its real class means moved to where the int8 trunk puts their "
                                                      "training presses (checks.int8_scene_means)"
                                                      if "int8_scene_means" in checks else "")
                                        + " (checks.int8_scene_decision_on_validation)" if trunk_precision == "int8" else "")}}
               if scene_model is not None else {}),
            "beta": float(beta),
            "operating_point": operating_point,
            "gating": {"transform": "asinh", "scale": scale, "temperature": float(gating_temperature), "how": how,
                       "rule": "P(untouched|x) = sigmoid((asinh(novelty/scale) - asinh(beta/scale)) / temperature)",
                       "scale_is": "median |novelty| of held-out touched presses"},
            "probe": {"input": "probe_input.npy", "expected": "probe_expected.npz",
                      "tolerance": tolerance,
                      "note": "a touched calibration press; expected = onnxruntime at export, max|diff|/max|expected|"},
            "checks": checks,
            "files": {name: rb.sha256_file(tmp / name) for name in files},
            "provenance": {"time_utc": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                           "git_commit": _git_commit(), "versions": _versions(), "command": shlex.join(sys.argv),
                           **(provenance or {})},
        }
        manifest = seal_verify_and_place(manifest, tmp, out, threads)
    log(f"bundle written to {out} and verified")
    return manifest


def _int8_scene_check(scene_model: dict, x: np.ndarray, sess32, sess8, scene_model8: dict | None = None) -> dict:
    """The scene model (fitted on the fp32 trunk's features) on the int8 trunk's - ``scene_model8``
    when the int8 bundle ships other means (export/int8_scene.py) -: per press, how often its most
    likely class over every class it knows is the same, and how far the projection moves against
    the spread of a press around its class mean - on validation presses only (touched fabrics'
    held-out presses and the validation fabrics'; never an untouched fabric's)."""
    from vs2t_edge.runtime.scene_model import SceneModel

    sm = SceneModel.from_params(scene_model)
    sm8 = sm if scene_model8 is None else SceneModel.from_params(scene_model8)
    (f32,) = _run_batches(sess32, x)
    (f8,) = _run_batches(sess8, x)
    z32, z8 = sm.project(f32), sm8.project(f8)
    lp32, d32 = sm.log_posterior_projected(z32)
    lp8, _ = sm8.log_posterior_projected(z8)
    shift = np.sum((z8 - z32) ** 2, axis=1)
    return {"presses": int(len(x)), "means_moved": scene_model8 is not None,
            "argmax_agreement": float(np.mean(lp32.argmax(1) == lp8.argmax(1))),
            "projection_shift_sq_median": float(np.median(shift)), "projection_shift_sq_max": float(np.max(shift)),
            "nearest_class_sq_median_fp32": float(np.median(d32.min(1))),
            "note": "squared distances in the scene model's whitened space; a press sits about "
                    "nearest_class_sq_median_fp32 from its nearest class mean"}


def fuse_press_graph(trunk_file: Path, heads_file: Path, cls_t: nn.Module, cls_u: nn.Module, router: nv.Router,
                     scene_model: dict | None, dim: int, opset: int, frames: np.ndarray, threads: int,
                     heads_int8: bool = False, split: bool = False) -> dict:
    """Replace ``trunk_file`` by the fused press graph (export/fuse.py) after checking it on
    ``frames`` against the two-graph path: feature and logits against trunk + heads sessions, the
    novelty against the router's own float64 novelty and scene_z against the scene model's float64
    projection of the same feature, each max|diff| / max|reference| <= PARITY_TOLERANCE. A low-rank
    router projection that misses it is replaced by the full whitening; a full one that misses it
    refuses the export. ``heads_int8``: the heads' weights in int8 (``fuse.quantize_heads``); their
    logits are then held to the int8 probe tolerance (HEADS_INT8_TOLERANCE), the rest as before.

    ``split`` (format 3, a scene model needed): the press graph is the trunk and the scene projection only, and
    ``heads_file`` is replaced by the heads with the router's outputs on the feature (fuse.py's
    module doc); the same checks, the logits and novelty read from that graph on the press graph's
    feature. Returns {"outputs", "manifest", "check"} and, for format 3, "heads_outputs" and
    "heads_manifest"."""
    from vs2t_edge.runtime.scene_model import SceneModel

    scene = SceneModel.from_params(scene_model) if scene_model is not None else None
    scene_params = {"center": scene.center, "basis": scene.basis} if scene is not None else None
    if split and scene is None:
        raise ExportError("a press graph without the heads (format 3) is a scene model's: this bundle has none")
    (f_ref,) = _run_batches(rb.open_session(trunk_file, threads), frames)
    lt_ref, lu_ref = _run_batches(rb.open_session(heads_file, threads), f_ref)
    last: dict = {}
    rule = fz.logit_router_rule(router)
    for force_full in (False, True):
        proj = fz.router_projection(router, force_full=force_full)
        with tempfile.TemporaryDirectory() as work_s:
            work = Path(work_s)
            # the heads (and the router's outputs): in the press graph's tail, or apart (format 3)
            head_names = fz.export_tail(work / "tail.onnx", cls_t, cls_u, dim, proj, None if split else scene_params,
                                        opset, rule)
            tail = work / "tail.onnx"
            if heads_int8:
                fz.quantize_heads(tail, work / "tail_int8.onnx")
                tail = work / "tail_int8.onnx"
            if split:
                heads_tail, tail = tail, work / "scene_tail.onnx"
                fz.export_tail(tail, cls_t, cls_u, dim, None, scene_params, opset, heads=False)
            names = fz.merge_into_trunk(trunk_file, tail, work / "press.onnx")
            got = dict(zip(names, _run_batches(rb.open_session(work / "press.onnx", threads), frames)))
            f = got["feature"]
            if split:
                got.update(zip(head_names, _run_batches(rb.open_session(heads_tail, threads), f)))
            check = {"frames": int(len(frames)), "feature": _rel(f, f_ref), "logits_t": _rel(got["logits_t"], lt_ref),
                     "logits_u": _rel(got["logits_u"], lu_ref), "tolerance": PARITY_TOLERANCE}
            if proj is not None:
                ref = router.novelty(f.astype(np.float64))
                check["novelty_vs_router_float64"] = _rel(fused_novelty(router, f, got["logits_t"], got["logits_u"],
                                                                        got[fz.ROUTER_OUT]), ref)
                check["router_form"] = proj["form"]
            if rule is not None:  # the graph's float32 novelty against the router's float64 one on the same logits
                lt64, lu64 = got["logits_t"].astype(np.float64), got["logits_u"].astype(np.float64)
                check["novelty_vs_router_float64"] = _rel(got[fz.NOVELTY_OUT][:, 0],
                                                          router.novelty(f, lt64, logits_u=lu64))
            if scene is not None:
                check["scene_z_vs_float64"] = _rel(got[fz.SCENE_OUT], scene.project(f.astype(np.float64)))
            if heads_int8:
                check["logits_tolerance"] = HEADS_INT8_TOLERANCE
            bad = {k: v for k, v in check.items() if isinstance(v, float) and not k.endswith("tolerance") and not v <= (
                HEADS_INT8_TOLERANCE if heads_int8 and k in ("logits_t", "logits_u") else PARITY_TOLERANCE)}
            if not bad:
                shutil.copyfile(work / "press.onnx", trunk_file)
                if not split:
                    return {"outputs": names, "check": check,
                            "manifest": fz.projection_manifest(proj, scene_params, dim, rule, heads_int8)}
                shutil.copyfile(heads_tail, heads_file)
                return {"outputs": names, "check": check, "heads_outputs": head_names,
                        "manifest": fz.projection_manifest(None, scene_params, dim, heads=False),
                        "heads_manifest": fz.projection_manifest(proj, None, dim, rule, heads_int8)}
            last = bad
            if proj is None or proj["form"] == "whitened":
                break
    raise ExportError(f"the fused press graph disagrees with the two-graph path beyond {PARITY_TOLERANCE}: {last}")


def seal_verify_and_place(manifest: dict, tmp: Path, out: Path, threads: int) -> dict:
    """Seal the manifest into the staged bundle ``tmp``, load it with the cell's own verification
    (``TactileModel.load``: a bundle that fails it is never left behind), then move it to ``out``
    (replacing what was there). Returns the manifest with the probe errors the cell measured."""
    from vs2t_edge.runtime.inference import TactileModel

    manifest = rb.seal_manifest(manifest)
    (tmp / rb.MANIFEST).write_text(json.dumps(manifest, indent=1, allow_nan=True) + "\n")
    model = TactileModel.load(tmp, threads=threads)
    manifest["checks"]["probe_errors_at_export"] = model.probe_errors
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for p in tmp.iterdir():
        shutil.move(str(p), out / p.name)
    return manifest


__all__ = ["OPSET", "ExportError", "write_bundle", "fuse_press_graph", "seal_verify_and_place", "count_macs", "export_onnx", "graph_io"]

"""`vs2t-edge int8-sensitivity BUNDLE`: what each trunk layer kept in float buys back under int8.

Takes an fp32 bundle (its trunk graph, heads, preprocessing and the record of which presses
trained it), calibrates int8 ranges on touched TRAINING presses (as `export --trunk-precision
int8` does, export/calibration.py), then quantises the trunk once per candidate node with that
node left in float and measures, on held-out presses only (touched fabrics' val presses and the
validation fabrics' presses; never test, never an untouched fabric):

- the feature error against fp32 (mse of the standardised feature, cosine);
- CLS_t on the touched held-out presses: top-1 agreement with fp32 and accuracy;
- CLS_u on the validation fabrics' presses: top-1 agreement with fp32 (their zero-shot route);
- the node's share of the trunk's multiply-accumulates (what keeping it float costs in time).

Frames are read as the bundle's run trained: through the camera's JPEG at the manifest's
``camera_jpeg`` when it records one (runtime.preprocess.camera_press), lossless otherwise.

Prints the ranking and, with ``--out FILE``, writes JSON whose ``recommended`` list (the ``--top``
nodes that buy back error) `vs2t-edge export RUN --trunk-precision int8 --int8-float-nodes @FILE`
keeps in float. No torch.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("bundle", help="an fp32 bundle of a trained run (vs2t-edge export RUN --out B)")
    parser.add_argument("--dataset", default=None, help="dataset folder (default: the bundle's)")
    parser.add_argument("--calibration-frames", type=int, default=64,
                        help="touched training presses for the int8 ranges (default 64, as export; 0: all)")
    parser.add_argument("--int8-calibration", choices=("minmax", "percentile", "entropy"), default="minmax")
    parser.add_argument("--int8-percentile", type=float, default=99.999)
    parser.add_argument("--float-nodes", default=None, metavar="NAMES",
                        help="nodes already kept in float (comma-separated): rank what ELSE buys back")
    parser.add_argument("--validation-presses", type=int, default=12,
                        help="presses per validation fabric in the scan (default 12)")
    parser.add_argument("--top", type=int, default=5, help="nodes in the 'recommended' list (default 5)")
    parser.add_argument("--ops", default="Conv,Add,Mul,Concat,GlobalAveragePool,AveragePool",
                        help="node types to scan (default Conv,Add,Mul,Concat,GlobalAveragePool,AveragePool)")
    parser.add_argument("--rank-by", default="logit_error", choices=("logit_error", "mse"),
                        help="what a node in float must reduce: the heads' logit error relative to fp32's spread "
                             "(default) or the standardised feature's mse")
    parser.add_argument("--out", default=None, help="JSON file to write")
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime threads (default 1)")


def _macs(model) -> dict[str, int]:
    """Multiply-accumulates per Conv node, from the shapes the pre-processing inferred."""
    from onnx import numpy_helper

    shapes = {v.name: [d.dim_value for d in v.type.tensor_type.shape.dim]
              for v in list(model.graph.value_info) + list(model.graph.output)}
    init = {i.name: list(numpy_helper.to_array(i).shape) for i in model.graph.initializer}
    out = {}
    for n in model.graph.node:
        if n.op_type == "Conv" and n.input[1] in init and shapes.get(n.output[0]):
            y, w = shapes[n.output[0]], init[n.input[1]]
            if len(y) == 4 and all(d > 0 for d in y[1:]):
                out[n.name] = int(y[1] * y[2] * y[3]) * int(w[1] * w[2] * w[3])
    return out


def scan(bundle: Path, *, dataset: str | None = None, calibration_frames: int = 64, method: str = "minmax",
         percentile: float = 99.999, float_nodes=(), validation_presses: int = 12, ops=None, top: int = 5,
         threads: int = 1, rank_by: str = "logit_error", log=lambda m: None) -> dict:
    import numpy as np

    from vs2t_edge.bench.accuracy import _dataset_of
    from vs2t_edge.export.calibration import calibration_presses, sensitivity_presses
    from vs2t_edge.export.quantize import Quantiser, _float_tail_nodes, layer_sensitivity, logit_error
    from vs2t_edge.runtime.bundle import load_bundle, read_manifest
    from vs2t_edge.runtime.novelty import GaussianRouter
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import TactilePreprocess, camera_press, camera_reference, check_camera_jpeg

    m = read_manifest(bundle)
    if "heads" not in m.get("graphs", {}):
        raise ValueError(f"{bundle}: its heads are inside its press graph (format {m.get('format_version')}); the scan "
                         "quantises the trunk alone and reads the heads from heads.onnx: give a bundle with a scene "
                         "model as `export` writes it (format 3), or one exported with --two-graphs (format 1)")
    if m.get("graphs", {}).get("trunk", {}).get("precision") != "fp32":
        raise ValueError(f"{bundle}: give an fp32 bundle (its trunk graph is what int8 is made from)")
    data = m.get("provenance", {}).get("data")
    if not data or "touched_presses" not in data:
        raise ValueError(f"{bundle}: its manifest does not record which presses trained it (a trained run's bundle)")
    ds_root = _dataset_of(m, dataset)
    if ds_root is None:
        raise FileNotFoundError(f"{bundle}: its dataset is not here; pass --dataset")
    ds = load_dataset(ds_root)
    spec = TactilePreprocess.from_dict(m["preprocess"])
    # a bundle trained through the camera's JPEG (manifest camera_jpeg) is scanned on frames read the same way
    q = check_camera_jpeg(m.get("camera_jpeg", 0), f"{bundle}: manifest.json 'camera_jpeg'")
    touched, untouched = list(m["classes"]["touched"]), list(m["classes"]["untouched"])
    part = data["touched_presses"]
    validation = {f: len(ds.by_id(f).presses) for f in data.get("validation", [])}
    calib_src = calibration_presses(part, touched, calibration_frames, untouched=untouched)
    sens_src = sensitivity_presses(part, touched, validation, untouched=untouched, per_fabric=validation_presses)

    def frames(src):
        xs = []
        for fid, idx in src.items():
            fab = ds.by_id(fid)
            ref = camera_reference(fab.load_reference(), spec, q, f"{fid} reference frame")
            xs.append(np.stack([camera_press(fab.load_press(i), ref, spec, q, f"{fid} press {i}") for i in idx]))
        return np.concatenate(xs).astype(np.float32)

    log(f"reading {sum(map(len, calib_src.values()))} calibration and {sum(map(len, sens_src.values()))} "
        "held-out presses")
    calib, held = frames(calib_src), frames(sens_src)
    t_index = {f: i for i, f in enumerate(touched)}
    label = np.concatenate([np.full(len(idx), t_index.get(f, -1)) for f, idx in sens_src.items()])
    is_t = label >= 0
    heads = _heads(bundle / m["graphs"]["heads"]["file"], threads)
    b = load_bundle(bundle)

    def novelty(f, lt, lu):
        if isinstance(b.router, GaussianRouter):
            return b.router.novelty(f, lt, logits_u=lu, dtype=np.float32)
        return b.router.novelty(f, lt, logits_u=lu)

    def score(f8, f32):
        (lt8, lu8), (lt32, lu32) = heads(f8), heads(f32)
        p8, p32 = lt8.argmax(1), lt32.argmax(1)
        r8, r32 = novelty(f8, lt8, lu8) > b.beta, novelty(f32, lt32, lu32) > b.beta
        out = {"cls_t_agreement": float(np.mean(p8[is_t] == p32[is_t])) if is_t.any() else float("nan"),
               "cls_t_acc": float(np.mean(p8[is_t] == label[is_t])) if is_t.any() else float("nan"),
               # the GZSL touched accuracy at beta: right class and routed touched
               "acc_t": float(np.mean((p8 == label)[is_t] & ~r8[is_t])) if is_t.any() else float("nan"),
               "route_agreement": float(np.mean(r8 == r32)), "logit_error": logit_error((lt8, lu8), (lt32, lu32))}
        if (~is_t).any():
            out["cls_u_agreement"] = float(np.mean(lu8[~is_t].argmax(1) == lu32[~is_t].argmax(1)))
        return out

    t0 = time.time()
    # ``quant``, not ``q``: q is the camera JPEG quality the result reports
    with Quantiser(bundle / m["graphs"]["trunk"]["file"], calib, method=method, percentile=percentile) as quant:
        tail = _float_tail_nodes(quant.model)
        quant.check_names(list(float_nodes))
        ops = tuple(ops) if ops else None
        cands = [n for n in quant.candidates(tail)
                 if (ops is None or quant.nodes[n] in ops) and n not in set(float_nodes)]
        f32 = _run_fp32(quant.pre, held, threads)
        fp32_scores = score(f32, f32)
        sens = layer_sensitivity(quant, held, tail=tail, base_float=list(float_nodes), candidates=cands,
                                 threads=threads, score=score, rank_by=rank_by, log=log)
        macs = _macs(quant.model)
    total = sum(macs.values()) or 1
    for r in sens["rows"]:
        r["macs_share"] = macs.get(r["node"], 0) / total
    rec = [r["node"] for r in sens["rows"] if r["buys_back"] > 0][:top]
    return {"bundle": str(bundle), "dataset": str(ds_root), "camera_jpeg": q,
            "calibration": {"method": method, "presses": calib_src,
            **({"percentile": percentile} if method == "percentile" else {})},
            "held_out_presses": sens_src, "fp32": fp32_scores, "float_tail": tail, **sens,
            "recommended": list(float_nodes) + rec, "seconds": round(time.time() - t0, 1)}


def _heads(path: Path, threads: int):
    from vs2t_edge.export.quantize import _session

    sess = _session(path, threads)
    name = sess.get_inputs()[0].name
    return lambda f: sess.run(["logits_t", "logits_u"], {name: f.astype("float32")})  # format 3's also gives the router's


def _run_fp32(path, frames, threads):
    from vs2t_edge.export.quantize import run_graph

    return run_graph(path, frames, threads)


def render(res: dict, rows: int = 15) -> str:
    a = res["all_int8"]
    f = res["fp32"]
    lines = [f"{res['frames']} held-out presses (touched val + validation fabrics); fp32: CLS_t accuracy "
             f"{100 * f['cls_t_acc']:.1f} %, GZSL acc_t at beta {100 * f['acc_t']:.1f} %",
             f"all int8 (float tail only{' + ' + ', '.join(res['base_float']) if res['base_float'] else ''}): "
             f"{res['metric']} {a[res['metric']]:.4g}, mse {a['mse']:.4g}, CLS_t acc {100 * a['cls_t_acc']:.1f} %, acc_t {100 * a['acc_t']:.1f} %, "
             f"route agreement {100 * a['route_agreement']:.1f} %"
             + (f", CLS_u agreement {100 * a['cls_u_agreement']:.1f} %" if "cls_u_agreement" in a else ""),
             "", f"| node | op | MACs % | {res['metric']} | buys back (% of error) | CLS_t acc % | acc_t % | route agree % | "
             "CLS_u agree % |", "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in res["rows"][:rows]:
        lines.append(f"| {r['node']} | {r['op']} | {100 * r['macs_share']:.1f} | {r[res['metric']]:.4g} | "
                     f"{100 * r['buys_back_share']:+.1f} | {100 * r['cls_t_acc']:.1f} | {100 * r['acc_t']:.1f} | "
                     f"{100 * r['route_agreement']:.1f} | {100 * r.get('cls_u_agreement', float('nan')):.1f} |")
    lines.append(f"\nrecommended to keep in float: {', '.join(res['recommended']) or '(none buys back error)'}")
    return "\n".join(lines)


def run(args) -> int:
    def log(msg: str) -> None:
        print(f"int8-sensitivity: {msg}", file=sys.stderr, flush=True)

    from vs2t_edge.runtime.bundle import BundleError

    float_nodes = [n.strip() for n in (args.float_nodes or "").split(",") if n.strip()]
    try:
        res = scan(Path(args.bundle), dataset=args.dataset, calibration_frames=args.calibration_frames,
                   method=args.int8_calibration, percentile=args.int8_percentile, float_nodes=float_nodes,
                   validation_presses=args.validation_presses, ops=[o for o in args.ops.split(",") if o],
                   top=args.top, threads=args.threads, rank_by=args.rank_by, log=log)
    except (ValueError, FileNotFoundError, BundleError) as exc:
        print(f"int8-sensitivity: {exc}", file=sys.stderr)
        return 2
    print(render(res))
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
        print(f"int8-sensitivity: wrote {args.out}", file=sys.stderr)
    return 0

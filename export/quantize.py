"""Static int8 quantisation of the tactile trunk (QDQ, per-channel weights), calibrated on
preprocessed presses of TOUCHED fabrics only (the untouched ones must stay unseen).

Why static and QDQ: onnxruntime fuses DequantizeLinear -> Conv -> QuantizeLinear into integer
QLinearConv kernels (VNNI on this CPU). Dynamic quantisation of a conv trunk becomes ConvInteger,
which onnxruntime does not optimise: measured here 4-6x SLOWER than fp32, so it is never shipped.

Activations are uint8 (asymmetric: ReLU/ReLU6 outputs are non-negative), weights int8 symmetric
per output channel. The feature tail (global mean pool and the standardisation Sub/Div) stays
float: it is a few thousand operations and the router's Gaussian is sensitive to its scale.

Mixed precision: ``float_nodes`` names graph nodes to keep in float (their inputs and outputs
are dequantised around them); ``float_auto=K`` keeps the K nodes whose float copy buys back the
most, measured by ``layer_sensitivity`` on ``sensitivity_frames`` (held-out touched presses and
validation fabrics' presses - never calibration, never test). The activation ranges are
calibrated once and reused for every variant (onnxruntime's calibration cache when it has one).
"""

from __future__ import annotations

import inspect
import tempfile
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

METHODS = ("minmax", "percentile", "entropy")
HISTOGRAM_CHUNK = 32  # frames between histogram updates (percentile, entropy): bounds calibration memory
# node types the QDQ quantiser turns to integer kernels here; the candidates of the sensitivity scan
# nodes onnxruntime would turn back to integer kernels after the quantiser left them in float
FLOAT_KERNEL_OPS = ("Conv", "ConvTranspose", "Gemm", "MatMul", "Add", "Mul", "Concat", "AveragePool",
                    "GlobalAveragePool", "Sigmoid")
CANDIDATE_OPS = ("Conv", "Add", "Mul", "MatMul", "Gemm", "Concat", "AveragePool", "GlobalAveragePool", "Sigmoid")


class _Reader:
    """onnxruntime CalibrationDataReader over an (N, 3, S, S) float32 array, one frame a batch."""

    def __init__(self, input_name: str, frames: np.ndarray) -> None:
        self.input_name, self.frames, self.i, self.end = input_name, frames, 0, None

    def get_next(self):
        if self.i >= (len(self.frames) if self.end is None else min(self.end, len(self.frames))):
            return None
        x = self.frames[self.i:self.i + 1]
        self.i += 1
        return {self.input_name: np.ascontiguousarray(x, dtype=np.float32)}

    def __len__(self) -> int:
        return len(self.frames)

    def set_range(self, start_index: int, end_index: int) -> None:
        """onnxruntime's strided calibration: read frames [start, end) next."""
        self.i, self.end = start_index, end_index

    def rewind(self) -> None:
        self.i, self.end = 0, None


def one_opset_per_domain(model) -> bool:
    """Drop repeated opset imports of a domain (``onnx.compose.merge_models`` lists the trunk's and
    the tail's both: onnxruntime runs such a graph, its quantiser refuses it). True if it changed."""
    seen: dict[str, int] = {}
    for o in model.opset_import:
        if seen.setdefault(o.domain or "", o.version) != o.version:
            raise ValueError(f"the graph imports domain {o.domain or 'ai.onnx'!r} at opsets {seen[o.domain or '']} "
                             f"and {o.version}")
    if len(seen) == len(model.opset_import):
        return False
    del model.opset_import[:]
    for domain, version in seen.items():
        model.opset_import.add(domain=domain, version=version)
    return True


def _float_tail_nodes(model, float_convs: int = 0) -> list[str]:
    """Names of the nodes after the last ``float_convs + 1``-th Conv from the end (pooling,
    standardisation, and the last ``float_convs`` convolutions): kept in float."""
    nodes = list(model.graph.node)
    convs = [i for i, n in enumerate(nodes) if n.op_type == "Conv"]
    if not convs:
        return [n.name for n in nodes if n.name]
    if float_convs <= 0:
        start = convs[-1] + 1
    elif float_convs >= len(convs):
        start = 0
    else:
        start = convs[-float_convs]
    return [n.name for n in nodes[start:] if n.name]


def _check_frames(frames: np.ndarray, what: str) -> np.ndarray:
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim != 4 or len(frames) < 1:
        raise ValueError(f"{what} frames must be (N, 3, S, S) with N >= 1, got {frames.shape}")
    if not np.all(np.isfinite(frames)):
        raise ValueError(f"{what} frames contain NaN or Inf")
    return np.ascontiguousarray(frames)


class Quantiser:
    """One fp32 trunk, pre-processed and calibrated once; ``write(out, exclude)`` writes a QDQ
    int8 copy keeping the nodes ``exclude`` in float. Use as a context manager (a temp folder)."""

    def __init__(self, fp32_path: Path | str, calibration: np.ndarray, *, method: str = "minmax",
                 per_channel: bool = True, percentile: float = 99.999, symmetric_ranges: bool | None = None) -> None:
        if method not in METHODS:
            raise ValueError(f"calibration method {method!r}: choose one of {', '.join(METHODS)}")
        self.calibration = _check_frames(calibration, "calibration")
        self.method, self.per_channel, self.percentile = method, per_channel, float(percentile)
        # onnxruntime's percentile calibrator is symmetric by default: half of a ReLU6 output's
        # uint8 codes would go to negative values it never takes. Asymmetric unless asked.
        self.symmetric_ranges = bool(symmetric_ranges) if symmetric_ranges is not None else False
        self._tmp = tempfile.TemporaryDirectory()
        self.tmp = Path(self._tmp.name)
        self.fp32 = Path(fp32_path)
        self._prepare()

    def __enter__(self) -> "Quantiser":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._tmp.cleanup()

    def _prepare(self) -> None:
        import onnx
        from onnxruntime.quantization import quantize_static
        from onnxruntime.quantization.shape_inference import quant_pre_process

        self.pre = self.tmp / "pre.onnx"
        # symbolic shape inference + constant folding (BatchNorm already folded by the exporter)
        quant_pre_process(str(self.fp32), str(self.pre), skip_symbolic_shape=False)
        self.model = onnx.load(str(self.pre))
        if one_opset_per_domain(self.model):  # a press graph fused before merge_into_trunk said each domain once
            onnx.save(self.model, str(self.pre))
        self.input_name = self.model.graph.input[0].name
        self.nodes = {n.name: n.op_type for n in self.model.graph.node if n.name}
        self.order = [n.name for n in self.model.graph.node if n.name]
        self._cache = (self.tmp / "ranges.json"
                       if "calibration_cache_path" in inspect.signature(quantize_static).parameters else None)

    def check_names(self, names: Sequence[str]) -> None:
        unknown = [n for n in names if n not in self.nodes]
        if unknown:
            raise ValueError(f"float node(s) not in the trunk graph: {', '.join(unknown[:5])}"
                             f"{' ...' if len(unknown) > 5 else ''} (`vs2t-edge int8-sensitivity` lists the names)")

    def candidates(self, tail: Sequence[str]) -> list[str]:
        """Nodes the quantiser would make integer and the sensitivity scan may keep in float."""
        skip = set(tail)
        return [n for n in self.order if self.nodes[n] in CANDIDATE_OPS and n not in skip]

    def write(self, out_path: Path | str, exclude: Sequence[str]) -> None:
        from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

        methods = {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile,
                   "entropy": CalibrationMethod.Entropy}
        extra = {"ActivationSymmetric": False, "WeightSymmetric": True,
                 "CalibTensorRangeSymmetric": self.symmetric_ranges}
        if self.method == "percentile":
            extra["CalibPercentile"] = self.percentile
        if self.method in ("percentile", "entropy"):
            # histogram calibrators keep every frame's activations until they fold them into the
            # histograms (1280 presses of EfficientNet-Lite0 at 128 px took 24 GB and were
            # OOM-killed): feed them in strides, each folded in before the next is read
            n = len(self.calibration)
            extra["CalibStridedMinMax"] = max(d for d in range(1, HISTOGRAM_CHUNK + 1) if n % d == 0)
        kwargs = {}
        if self._cache is not None:
            kwargs["calibration_cache_path"] = str(self._cache)
        quantize_static(str(self.pre), str(out_path), _Reader(self.input_name, self.calibration),
                        quant_format=QuantFormat.QDQ, per_channel=self.per_channel,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        nodes_to_exclude=list(exclude), calibrate_method=methods[self.method],
                        extra_options=extra, **kwargs)
        float_ops = [n for n in exclude if self.nodes.get(n) in FLOAT_KERNEL_OPS]
        if float_ops:
            keep_float(out_path, float_ops, _shapes(self.model))


def _shapes(model) -> dict[str, list[int]]:
    g = model.graph
    return {v.name: [d.dim_value for d in v.type.tensor_type.shape.dim]
            for v in list(g.value_info) + list(g.input) + list(g.output)}


def keep_float(path: Path | str, names: Sequence[str], shapes: dict[str, list[int]] | None = None) -> int:
    """Make the nodes ``names`` of a QDQ graph really run in float; returns how many inputs it rewired.

    Leaving a node out of quantisation is not enough: onnxruntime's WeightBiasQuantization
    optimiser quantises the float weights of any Conv/Gemm whose input comes from a
    DequantizeLinear with a per-tensor scale (symmetric per-TENSOR int8, worse than the exporter's
    per-channel), and the QDQ fusions then run it as an integer kernel. Each activation input of
    those nodes is therefore read through its own DequantizeLinear with the same scale and zero
    point repeated per channel (axis 1): the same numbers, but no longer the per-tensor pattern
    those optimisers match, so the node computes in float on float weights."""
    import onnx
    from onnx import helper, numpy_helper

    model = onnx.load(str(path))
    g = model.graph
    init = {i.name: i for i in g.initializer}
    producer = {o: n for n in g.node for o in n.output}
    shapes = {**_shapes(model), **(shapes or {})}  # the float graph's shapes: the quantiser's tensors have none
    by_name = {n.name: n for n in g.node}
    new_nodes, rewired = [], 0
    for name in names:
        node = by_name.get(name)
        if node is None:
            raise ValueError(f"float node {name!r} is not in the quantised graph")
        for k, x in enumerate(node.input):
            dq = producer.get(x)
            if dq is None or dq.op_type != "DequantizeLinear" or dq.input[0] in init:
                continue  # not an activation read through a DequantizeLinear
            scale, zp = (numpy_helper.to_array(init[t]) if t in init else None for t in (dq.input[1], dq.input[2]))
            if scale is None or zp is None or scale.size != 1:
                continue
            channels = None
            if node.op_type in ("Conv", "ConvTranspose") and k == 0 and node.input[1] in init:
                w = init[node.input[1]].dims
                group = next((a.i for a in node.attribute if a.name == "group"), 1)
                channels = int(w[1] * group) if node.op_type == "Conv" else int(w[0])
            else:  # the float tensor the Q -> DQ pair stands for
                q = producer.get(dq.input[0])
                src = q.input[0] if q is not None and q.op_type == "QuantizeLinear" else x
                if len(shapes.get(src, [])) >= 2 and shapes[src][1] > 0:
                    channels = shapes[src][1]
            if not channels:
                raise ValueError(f"cannot keep {name!r} in float: the channel count of its input {x!r} is unknown")
            tag = f"{x}_float_for_{name}"
            g.initializer.extend([numpy_helper.from_array(np.full(channels, scale.reshape(-1)[0], scale.dtype), tag + "_scale"),
                                  numpy_helper.from_array(np.full(channels, zp.reshape(-1)[0], zp.dtype), tag + "_zero_point")])
            new_nodes.append(helper.make_node("DequantizeLinear", [dq.input[0], tag + "_scale", tag + "_zero_point"],
                                              [tag], name=tag + "_DequantizeLinear", axis=1))
            node.input[k] = tag
            rewired += 1
    if new_nodes:
        # each new DequantizeLinear right before the first node that reads it (topological order);
        # a shared DequantizeLinear nobody reads any more is dropped
        reads = {n.output[0]: n for n in new_nodes}
        read = {i for n in g.node for i in n.input} | {o.name for o in g.output}
        order = []
        for n in g.node:
            if n.op_type == "DequantizeLinear" and n.output[0] not in read:
                continue
            order += [reads.pop(i) for i in n.input if i in reads] + [n]
        del g.node[:]
        g.node.extend(order)
        onnx.save(model, str(path))
    return rewired


def _session(path: Path | str, threads: int):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads = threads, 1
    return ort.InferenceSession(str(path), sess_options=so, providers=["CPUExecutionProvider"])


def run_graph(path: Path | str, frames: np.ndarray, threads: int = 1, chunk: int = 32) -> np.ndarray:
    """The graph's first output on ``frames`` (batched; one at a time if the graph is batch 1)."""
    sess = _session(path, threads)
    name = sess.get_inputs()[0].name
    fixed = sess.get_inputs()[0].shape[0]
    step = 1 if isinstance(fixed, int) and fixed == 1 else chunk
    return np.concatenate([sess.run(None, {name: frames[i:i + step]})[0] for i in range(0, len(frames), step)])


def feature_error(f8: np.ndarray, f32: np.ndarray) -> dict:
    """How far int8 features are from fp32: mean squared error (the trunk's output is standardised,
    so in units of the feature's own spread), and the worst and mean cosine."""
    cos = np.sum(f32 * f8, 1) / np.maximum(np.linalg.norm(f32, axis=1) * np.linalg.norm(f8, axis=1), 1e-12)
    return {"mse": float(np.mean((f8 - f32) ** 2)), "cosine_mean": float(np.mean(cos)),
            "cosine_min": float(np.min(cos))}


def logit_error(logits8: Sequence[np.ndarray], logits32: Sequence[np.ndarray]) -> float:
    """Squared error of the heads' logits (CLS_t and CLS_u side by side) relative to the fp32
    logits' own spread: what reaches the decision, each feature dimension weighted by the heads."""
    a, b = np.concatenate(list(logits8), 1), np.concatenate(list(logits32), 1)
    return float(np.mean((a - b) ** 2) / max(float(np.var(b)), 1e-12))


def layer_sensitivity(q: Quantiser, frames: np.ndarray, *, tail: Sequence[str], base_float: Sequence[str] = (),
                      candidates: Sequence[str] | None = None, threads: int = 1,
                      score: Callable[[np.ndarray, np.ndarray], dict] | None = None, rank_by: str = "mse",
                      log: Callable[[str], None] = lambda m: None) -> dict:
    """What keeping each node in float buys back, one node at a time on top of the all-int8 trunk
    (``tail`` and ``base_float`` already float): the feature error on ``frames`` against fp32
    (``feature_error``; ``score(f8, f32)`` adds numbers, e.g. head agreement). Rows sorted by
    ``buys_back`` = error ``rank_by`` (a key of those numbers, lower is better) of the all-int8
    trunk minus that error with the node in float (larger is better).
    ``frames`` must be held-out presses (never the calibration presses, never test)."""
    frames = _check_frames(frames, "sensitivity")
    f32 = run_graph(q.pre, frames, threads)
    base_ex = list(tail) + [n for n in base_float if n not in set(tail)]

    def measure(exclude: list[str]) -> dict:
        path = q.tmp / "variant.onnx"
        q.write(path, exclude)
        f8 = run_graph(path, frames, threads)
        return {**feature_error(f8, f32), **(score(f8, f32) if score else {})}

    base = measure(base_ex)
    if rank_by not in base:
        raise ValueError(f"rank_by {rank_by!r}: not one of the measured numbers {', '.join(base)}")
    cands = list(candidates) if candidates is not None else q.candidates(base_ex)
    q.check_names(cands)
    rows = []
    for i, name in enumerate(cands):
        m = measure(base_ex + [name])
        e0, e1 = base[rank_by], m[rank_by]
        rows.append({"node": name, "op": q.nodes[name], **m, "buys_back": e0 - e1,
                     "buys_back_share": (e0 - e1) / e0 if e0 > 0 else 0.0})
        log(f"sensitivity {i + 1}/{len(cands)}: {name} ({q.nodes[name]}) {rank_by} {e1:.3g} (all int8 {e0:.3g})")
    rows.sort(key=lambda r: -r["buys_back"])
    return {"frames": int(len(frames)), "metric": rank_by, "all_int8": base, "base_float": list(base_float),
            "rows": rows}


def quantize_trunk_static(fp32_path: Path | str, out_path: Path | str, calibration: np.ndarray, *,
                          method: str = "minmax", per_channel: bool = True, float_convs: int = 0,
                          float_nodes: Sequence[str] = (), float_auto: int = 0,
                          sensitivity_frames: np.ndarray | None = None, percentile: float = 99.999,
                          score: Callable[[np.ndarray, np.ndarray], dict] | None = None, rank_by: str = "mse",
                          log: Callable[[str], None] = lambda m: None) -> dict:
    """Write the QDQ int8 trunk; returns what was done (for the manifest).

    ``float_nodes``: node names kept in float; ``float_auto``: also keep the ``float_auto`` nodes
    the sensitivity scan on ``sensitivity_frames`` ranks first (only those that buy back error)."""
    calibration = _check_frames(calibration, "calibration")
    if float_auto < 0 or float_convs < 0:
        raise ValueError("float_auto and float_convs must be >= 0")
    if float_auto and sensitivity_frames is None:
        raise ValueError("float_auto needs sensitivity frames (held-out touched / validation presses)")
    out_path = Path(out_path)
    with Quantiser(fp32_path, calibration, method=method, per_channel=per_channel, percentile=percentile) as q:
        tail = _float_tail_nodes(q.model, float_convs)
        q.check_names(float_nodes)
        chosen = [n for n in float_nodes if n not in set(tail)]
        sens = None
        if float_auto:
            sens = layer_sensitivity(q, sensitivity_frames, tail=tail, base_float=chosen, score=score,
                                     rank_by=rank_by, log=log)
            picked = [r["node"] for r in sens["rows"] if r["buys_back"] > 0][:float_auto]
            log(f"keeping in float the {len(picked)} nodes that buy back the most: {', '.join(picked)}")
            chosen += picked
        q.write(out_path, tail + chosen)
    rep = {"method": "static QDQ", "activations": "uint8 asymmetric", "weights": "int8 symmetric per-channel"
           if per_channel else "int8 symmetric per-tensor", "calibration": method, "calibration_frames": int(len(calibration)),
           "float_convs_at_end": int(float_convs), "float_nodes": len(tail) + len(chosen),
           "float_nodes_chosen": chosen}
    if method == "percentile":
        rep["percentile"] = percentile
    if sens is not None:
        rep["sensitivity"] = {"frames": sens["frames"], "metric": sens["metric"],
                              "all_int8": sens["all_int8"][rank_by],
                              "top": [{k: r[k] for k in ("node", "op", rank_by, "buys_back")} for r in sens["rows"][:10]]}
    return rep


__all__ = ["quantize_trunk_static", "layer_sensitivity", "logit_error", "keep_float", "Quantiser", "feature_error", "run_graph", "METHODS"]

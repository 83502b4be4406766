"""Static int8 quantisation of the tactile trunk (QDQ, per-channel weights), calibrated on
preprocessed presses of TOUCHED fabrics only (the untouched ones must stay unseen).

Why static and QDQ: onnxruntime fuses DequantizeLinear -> Conv -> QuantizeLinear into integer
QLinearConv kernels (VNNI on this CPU). Dynamic quantisation of a conv trunk becomes ConvInteger,
which onnxruntime does not optimise: measured here 4-6x SLOWER than fp32, so it is never shipped.

Activations are uint8 (asymmetric: ReLU/ReLU6 outputs are non-negative), weights int8 symmetric
per output channel. The feature tail (global mean pool and the standardisation Sub/Div) stays
float: it is a few thousand operations and the router's Gaussian is sensitive to its scale.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np


class _Reader:
    """onnxruntime CalibrationDataReader over an (N, 3, S, S) float32 array, one frame a batch."""

    def __init__(self, input_name: str, frames: np.ndarray) -> None:
        self.input_name, self.frames, self.i = input_name, frames, 0

    def get_next(self):
        if self.i >= len(self.frames):
            return None
        x = self.frames[self.i:self.i + 1]
        self.i += 1
        return {self.input_name: np.ascontiguousarray(x, dtype=np.float32)}

    def rewind(self) -> None:
        self.i = 0


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


def quantize_trunk_static(fp32_path: Path | str, out_path: Path | str, calibration: np.ndarray, *,
                          method: str = "minmax", per_channel: bool = True, float_convs: int = 0) -> dict:
    """Write the QDQ int8 trunk; returns what was done (for the manifest)."""
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    calibration = np.asarray(calibration, dtype=np.float32)
    if calibration.ndim != 4 or len(calibration) < 1:
        raise ValueError(f"calibration frames must be (N, 3, S, S) with N >= 1, got {calibration.shape}")
    if not np.all(np.isfinite(calibration)):
        raise ValueError("calibration frames contain NaN or Inf")
    methods = {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile,
               "entropy": CalibrationMethod.Entropy}
    if method not in methods:
        raise ValueError(f"calibration method {method!r}: choose one of {', '.join(methods)}")
    out_path = Path(out_path)
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        # symbolic shape inference + constant folding (BatchNorm already folded by the exporter)
        quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=False)
        model = onnx.load(str(pre))
        input_name = model.graph.input[0].name
        exclude = _float_tail_nodes(model, float_convs)
        extra = {"ActivationSymmetric": False, "WeightSymmetric": True}
        if method == "percentile":
            extra["CalibPercentile"] = 99.99
        quantize_static(str(pre), str(out_path), _Reader(input_name, calibration), quant_format=QuantFormat.QDQ,
                        per_channel=per_channel, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        nodes_to_exclude=exclude, calibrate_method=methods[method], extra_options=extra)
    return {"method": "static QDQ", "activations": "uint8 asymmetric", "weights": "int8 symmetric per-channel"
            if per_channel else "int8 symmetric per-tensor", "calibration": method, "calibration_frames": int(len(calibration)),
            "float_convs_at_end": int(float_convs), "float_nodes": len(exclude)}


__all__ = ["quantize_trunk_static"]

"""One onnxruntime call per press: the heads and the per-press projections folded into the trunk
graph at export (docs/bundle.md "The fused press graph", format_version 2), or, for a bundle that
decides with a scene model, only the scene projection (format_version 3, ``heads=False`` below).

A two-graph bundle (format 1) pays per press a second ``session.run`` for the heads, the Gaussian
router's D x D whitening matvec in numpy (2048 x 2048 for ResNet50: 16 MB read per press) and the
scene model's D x k projection in numpy. Here they become one graph, written by the exporter with
``onnx`` (an export-time dependency; the cell never imports it):

    image -> trunk -> feature --+-> CLS_t -> logits_t
                                +-> CLS_u -> logits_u
                                +-> router_z   (Gaussian routers only)
                                +-> router_novelty (routers on the logits only)
                                +-> scene_z    (bundles with a scene model only)

- ``router_z`` is a vector whose squared norm is the squared Mahalanobis distance the router's
  novelty is made of (the cell sums its squares in float64 and adds the log-density constant,
  ``GaussianRouter.novelty_from_squared``). ``form: whitened``: (x - mean) @ W, D numbers, as the
  numpy router computes it. ``form: low_rank``: when the covariance's spectrum ends in a flat floor
  - always when the router was fitted on fewer presses than dimensions: the floored (or shrunk)
  eigenvalues are all equal - only the r eigen-directions above the floor need their own scale:
  z = [ (x - mean) @ V_r / sqrt(lambda_r),  ((x - mean) - ((x - mean) @ V_r) V_r^T) / sqrt(floor) ],
  2 r D multiply-adds instead of D^2 (ResNet50's untrained latency bundle: r = 31 instead of 2048).
  Used when 2 r < D and the spectrum's floor is flat within ``FLAT_RTOL``; the exporter checks the
  novelty it gives against the router's own float64 novelty on the calibration presses either way.
- ``router_novelty`` (N, 1): the novelty of a router that reads only the heads' logits (energy,
  max_softmax, calibrated_stacking), its formula in float32 on the graph's own logits; the numpy
  form cost about 0.1 ms of a press on the bench's 2-core CPU (some ten small numpy calls, cold
  after the trunk's run), the graph's nodes a few microseconds.
- ``scene_z`` = (x - center) @ basis, the scene model's k-dimensional whitened projection; the cell
  computes the class distances from it (k x C, float64).

The heads and projections stay float32 behind an int8 trunk; ``quantize_heads`` (export
``--heads-precision int8``) puts the heads' weights in int8, the projections stay float32.

Format 3: a bundle with a scene model decides every piece from ``scene_z`` alone; the logits and
the router's novelty are never read on the cell's press path. onnxruntime runs every node of a
graph whatever outputs are fetched (measured: fetching only ``feature`` and ``scene_z`` from the
format-2 graph cost the same as fetching all), so there the press graph is only

    image -> trunk -> feature --+-> scene_z

and the heads with the router's outputs go to ``heads.onnx`` (input ``feature``), which the probe,
the bench's accuracy and calibration run on the feature when they need the logits.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime.bundle import NOVELTY_OUT

ROUTER_OUT, SCENE_OUT = "router_z", "scene_z"
HEAD_OUTS = ("logits_t", "logits_u")
FLAT_RTOL = 1e-6  # eigenvalues within this of the smallest count as the flat floor
TAIL_PREFIX = "press_tail/"


class FuseError(RuntimeError):
    pass


def router_projection(router: nv.Router, force_full: bool = False) -> dict[str, Any] | None:
    """What the graph computes for the router (module doc), float64; None for routers that need only
    the logits (energy, max_softmax, calibrated_stacking: numpy on C numbers, nothing to fold) and
    for the discriminant router (its novelty is a minimum over classes, not a squared norm: the cell
    computes it in numpy from the graph's feature, a D x (C - 1) matmul and C x (C - 1) numbers)."""
    if not isinstance(router, nv.GaussianRouter):
        return None
    w = np.asarray(router.whitening, np.float64)
    mean = np.asarray(router.mean, np.float64)
    d = w.shape[0]
    full = {"form": "whitened", "mean": mean, "weight": w, "rank": d}
    if force_full:
        return full
    inv_sqrt = np.linalg.norm(w, axis=0)  # W = V diag(lambda^-1/2) with V orthonormal: column norms
    if not np.all(inv_sqrt > 0):
        return full
    v = w / inv_sqrt[None, :]
    if not np.allclose(v.T @ v, np.eye(d), atol=1e-6):  # a whitening not of that form: keep it whole
        return full
    lam = 1.0 / inv_sqrt ** 2
    flat = lam <= lam.min() * (1.0 + FLAT_RTOL)
    r = int(d - flat.sum())
    if 2 * r >= d:
        return full
    return {"form": "low_rank", "mean": mean, "basis": v[:, ~flat], "scale": inv_sqrt[~flat],
            "floor_scale": float(1.0 / np.sqrt(np.mean(lam[flat]))), "rank": r}


def logit_router_rule(router: nv.Router) -> dict[str, Any] | None:
    """What the graph computes as ``router_novelty`` for a router on the logits (module doc); None
    for the routers on the feature (Gaussian: ``router_projection``; discriminant: numpy)."""
    if isinstance(router, (nv.EnergyRouter, nv.MaxSoftmaxRouter)):
        return {"name": router.name, "temperature": float(router.temperature)}
    if isinstance(router, nv.CalibratedStackingRouter):
        return {"name": router.name, "scores": router.scores}
    return None


class _Tail(nn.Module):
    """feature -> logits_t, logits_u [, router_z] [, router_novelty] [, scene_z] (module doc), float32;
    ``heads`` False: feature -> scene_z alone (format 3's press tail)."""

    def __init__(self, cls_t: nn.Module, cls_u: nn.Module, router: dict | None, scene: dict | None,
                 novelty: dict | None = None, heads: bool = True) -> None:
        super().__init__()
        if not heads and (router or novelty or not scene):
            raise FuseError("a tail without the heads carries the scene projection alone")
        self.heads = heads
        self.cls_t, self.cls_u = cls_t, cls_u
        self.novelty_rule = dict(novelty) if novelty else None
        self.router_form = router["form"] if router else None
        f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
        if router:
            self.register_buffer("r_mean", f32(router["mean"]))
            if router["form"] == "whitened":
                self.register_buffer("r_weight", f32(router["weight"]))
            else:
                self.register_buffer("r_basis", f32(router["basis"]))
                self.register_buffer("r_basis_t", f32(np.asarray(router["basis"]).T))
                self.register_buffer("r_scale", f32(router["scale"]))
                self.register_buffer("r_floor", f32(np.float64(router["floor_scale"])))
        self.has_scene = scene is not None
        if scene:
            self.register_buffer("s_center", f32(scene["center"]))
            self.register_buffer("s_basis", f32(scene["basis"]))

    def forward(self, f):
        outs = [self.cls_t(f), self.cls_u(f)] if self.heads else []
        if self.router_form is not None:
            c = f - self.r_mean
            if self.router_form == "whitened":
                outs.append(c @ self.r_weight)
            else:
                a = c @ self.r_basis
                outs.append(torch.cat([a * self.r_scale, (c - a @ self.r_basis_t) * self.r_floor], dim=1))
        if self.novelty_rule is not None:
            outs.append(self._novelty(outs[0], outs[1]))
        if self.has_scene:
            outs.append((f - self.s_center) @ self.s_basis)
        return tuple(outs)


    def _novelty(self, lt, lu):
        """(N, 1): the numpy router's formula (runtime/novelty.py) on the logits, in float32."""
        rule = self.novelty_rule
        if rule["name"] == "energy":
            t = rule["temperature"]
            return -t * torch.logsumexp(lt / t, dim=1, keepdim=True)
        if rule["name"] == "max_softmax":
            return -torch.amax(torch.softmax(lt / rule["temperature"], dim=1), dim=1, keepdim=True)
        if rule["scores"] == "log_softmax":
            lt, lu = torch.log_softmax(lt, dim=1), torch.log_softmax(lu, dim=1)
        return torch.amax(lu, dim=1, keepdim=True) - torch.amax(lt, dim=1, keepdim=True)


def tail_outputs(router: dict | None, scene: dict | None, novelty: dict | None = None,
                 heads: bool = True) -> list[str]:
    return [*(HEAD_OUTS if heads else ()), *([ROUTER_OUT] if router else []), *([NOVELTY_OUT] if novelty else []),
            *([SCENE_OUT] if scene else [])]


def export_tail(path: Path, cls_t: nn.Module, cls_u: nn.Module, dim: int, router: dict | None,
                scene: dict | None, opset: int, novelty: dict | None = None, heads: bool = True) -> list[str]:
    """Write the tail graph (input ``feature``); returns its output names. ``novelty``:
    ``logit_router_rule`` of a router on the logits, folded in as ``router_novelty``. ``heads``
    False: the scene projection alone (format 3's press tail; ``router`` and ``novelty`` None)."""
    from vs2t_edge.export.export import export_onnx

    names = tail_outputs(router, scene, novelty, heads)
    export_onnx(_Tail(cls_t.eval(), cls_u.eval(), router, scene, novelty, heads).eval(), torch.zeros(1, dim), path,
                "feature", names, opset)
    return names


def quantize_heads(tail_path: Path, out_path: Path) -> None:
    """The tail with CLS_t's and CLS_u's Gemm weights in int8 (per output channel; activations
    quantised per press by onnxruntime's dynamic quantisation: DynamicQuantizeLinear +
    MatMulInteger, standard ONNX ops). The projections (MatMul: router_z, scene_z) stay float32.
    The heads' float32 weights are 7.3 MB on EfficientNet-Lite0's 1280-d feature: read once per
    press, cold after the trunk's run, they are most of the tail's time (int8: 1.8 MB)."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    # the quantiser rewrites each Gemm as MatMul + Add before it quantises MatMuls: name the
    # projections' own MatMuls to keep them float
    projections = [n.name for n in onnx.load(str(tail_path)).graph.node if n.op_type == "MatMul"]
    quantize_dynamic(str(tail_path), str(out_path), weight_type=QuantType.QInt8, per_channel=True,
                     op_types_to_quantize=["Gemm", "MatMul"], nodes_to_exclude=projections)
    model = onnx.load(str(out_path))
    ops = {(n.domain or "", n.op_type) for n in model.graph.node}
    if any(d for d, _ in ops):
        raise FuseError(f"dynamic quantisation of the heads wrote non-standard ops {sorted(ops)}")
    if not any(op == "MatMulInteger" for _, op in ops):
        raise FuseError("dynamic quantisation of the heads quantised nothing")


def _prefix_internal(graph, prefix: str, keep: set[str]) -> None:
    """Rename every tensor and node of ``graph`` except ``keep`` (its inputs/outputs), so that
    nothing collides with the trunk's names when the two are merged."""
    def ren(name: str) -> str:
        return name if not name or name in keep else prefix + name

    for node in graph.node:
        node.name = prefix + node.name if node.name else node.name
        node.input[:] = [ren(n) for n in node.input]
        node.output[:] = [ren(n) for n in node.output]
    for init in graph.initializer:
        init.name = ren(init.name)
    for vi in graph.value_info:
        vi.name = ren(vi.name)


def merge_into_trunk(trunk_path: Path, tail_path: Path, out_path: Path) -> list[str]:
    """The trunk graph (fp32 or int8 QDQ) with the tail appended on its ``feature`` output, written
    to ``out_path``; returns the fused graph's output names (``feature`` first)."""
    import onnx
    from onnx import compose

    from vs2t_edge.export.quantize import one_opset_per_domain

    trunk, tail = onnx.load(str(trunk_path)), onnx.load(str(tail_path))
    t_outs = [o.name for o in trunk.graph.output]
    if t_outs != ["feature"]:
        raise FuseError(f"{trunk_path.name}: outputs {t_outs}, expected ['feature']")
    tail_outs = [o.name for o in tail.graph.output]
    _prefix_internal(tail.graph, TAIL_PREFIX, {"feature", *tail_outs})
    tail.ir_version = trunk.ir_version
    ops_t = {o.domain or "": o.version for o in trunk.opset_import}
    for o in tail.opset_import:
        if ops_t.get(o.domain or "", o.version) != o.version:
            raise FuseError(f"opset of domain {o.domain or 'ai.onnx'}: trunk {ops_t[o.domain or '']}, tail {o.version}")
    merged = compose.merge_models(trunk, tail, io_map=[("feature", "feature")], outputs=["feature", *tail_outs],
                                  producer_name="vs2t-edge export (fused press graph)")
    one_opset_per_domain(merged)  # merge_models lists the ai.onnx import of both graphs
    onnx.checker.check_model(merged)
    onnx.save(merged, str(out_path))
    return ["feature", *tail_outs]


HEADS_INT8 = "CLS_t -> logits_t, CLS_u -> logits_u, int8 weights per channel, activations quantised per press"


def projection_manifest(router: dict | None, scene: dict | None, dim: int, novelty: dict | None = None,
                        heads_int8: bool = False, heads: bool = True) -> dict:
    """What ``graphs.trunk.fused`` (or a descriptor bundle's or a format-3 bundle's
    ``graphs.heads.fused``) says the extra outputs are (docs/bundle.md); ``heads`` False: a graph
    without the heads (format 3's press graph)."""
    out: dict[str, Any] = {}
    if heads:
        out["heads"] = HEADS_INT8 if heads_int8 else "CLS_t -> logits_t, CLS_u -> logits_u, float32"
    if novelty:
        out[NOVELTY_OUT] = {**novelty, "rule": "the router's novelty on the graph's logits, float32 (runtime/novelty.py)"}
    if router:
        out[ROUTER_OUT] = {"form": router["form"], "rank": int(router["rank"]), "width": int(
            dim if router["form"] == "whitened" else router["rank"] + dim),
            "macs": int(dim * dim if router["form"] == "whitened" else 2 * router["rank"] * dim),
            "rule": "novelty from sum(router_z^2) in float64 (GaussianRouter.novelty_from_squared)"}
    if scene:
        out[SCENE_OUT] = {"k": int(np.asarray(scene["basis"]).shape[1]), "rule": "(feature - center) @ basis"}
    return out


__all__ = ["FuseError", "NOVELTY_OUT", "ROUTER_OUT", "SCENE_OUT", "logit_router_rule", "router_projection", "export_tail",
           "merge_into_trunk", "projection_manifest", "quantize_heads", "tail_outputs"]

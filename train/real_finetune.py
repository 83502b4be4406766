"""The ``finetuned`` pipeline of `vs2t-edge real-check`: the frozen pipeline's trunk and input
(ImageNet EfficientNet-Lite0, the whole frame resized to 224 px), its tail fine-tuned per fold on
that fold's fit presses only, with the augmentations the sensor allows.

Why these pieces:

- only the tail (the last MBConv block and the 1x1 head, ``train.trunks``' own split, the one the
  cell's training tunes) is trained; the stem is frozen, so its activations of a few augmented
  views per fit press are computed once and the epochs cost only the tail - minutes on 2 cores;
- augmentations: shifts of up to ``SHIFT_PX`` on the native frame (the press lands a little off
  each time) and brightness / contrast jitter of a few % (these recordings have a 3-4 % exposure
  step between presses 1-5 and 6-20). No flips, no turns: they move the LED colour layout, which a
  real press never does;
- recipe: a linear head on the fit materials, first fitted on the frozen features (a linear probe),
  then tail and head tuned together with a small learning rate and the BatchNorm statistics kept
  (a few presses per class cannot re-estimate them). Starting from a fitted head keeps the first
  gradients from wrecking the pretrained features;
- the number of epochs (0 allowed: the frozen trunk) is chosen inside the fit presses: per
  material the first ``SELECT_SHARE`` of them in press order tune, the rest score the tuned
  features by the check's own shrunk-LDA accuracy; then the tail is tuned afresh on all fit presses
  for that many epochs. The fold's test presses are never read (``finetune`` never indexes them).

Seeded (``SEED``) and deterministic on CPU with a fixed thread count.
"""

from __future__ import annotations

import copy

import numpy as np

SHIFT_PX = 20
BRIGHTNESS = 0.06
CONTRAST = 0.06
VIEWS = 4  # augmented views per fit press, besides the clean one
EPOCH_CHOICES = (0, 2, 4, 8)
LR = 1e-4
HEAD_LR = 1e-2
PROBE_STEPS = 200
BATCH = 32
SELECT_SHARE = 0.7
SEED = 0


def augment(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A sensor-plausible variant of an HxWx3 uint8 BGR press as float RGB in [0, 1]: shifted by up
    to SHIFT_PX (border replicated), brightness and contrast jittered; never flipped or turned."""
    import cv2

    h, w = image.shape[:2]
    dx, dy = rng.integers(-SHIFT_PX, SHIFT_PX + 1, size=2)
    moved = cv2.warpAffine(image, np.float32([[1, 0, dx], [0, 1, dy]]), (w, h), borderMode=cv2.BORDER_REPLICATE)
    x = moved[..., ::-1].astype(np.float64) / 255
    mean = x.mean()
    x = (x - mean) * (1 + rng.uniform(-CONTRAST, CONTRAST)) + mean
    return np.clip(x * (1 + rng.uniform(-BRIGHTNESS, BRIGHTNESS)), 0.0, 1.0)


def clean(image: np.ndarray) -> np.ndarray:
    """The frozen pipeline's input: the frame as float RGB in [0, 1]."""
    return image[..., ::-1].astype(np.float64) / 255


class TunedTrunk:
    """EfficientNet-Lite0 of ``train.trunks`` (offline ImageNet weights) split into a frozen stem,
    whose activations are cached, and a tail tuned per fold. ``arch="tiny"`` is for tests."""

    def __init__(self, arch: str = "efficientnet_lite0", pretrained: bool = True) -> None:
        import torch

        from vs2t_edge.train.trunks import build_trunk

        torch.set_num_threads(1)
        self.torch = torch
        torch.manual_seed(SEED)  # the tiny test trunk's random init
        self.trunk = build_trunk(arch, pretrained=pretrained).eval()
        self.pretrained_tail = copy.deepcopy(self.trunk.tail.state_dict())

    def stem(self, rgb01: list[np.ndarray], chunk: int = 16) -> "torch.Tensor":
        from vs2t_edge.train.real_check import trunk_input

        torch = self.torch
        with torch.no_grad():
            return torch.cat([self.trunk.stem(torch.from_numpy(trunk_input(rgb01[i:i + chunk])))
                              for i in range(0, len(rgb01), chunk)])

    def features(self, acts: "torch.Tensor", chunk: int = 64) -> np.ndarray:
        torch = self.torch
        with torch.no_grad():
            return torch.cat([self.trunk.features_from_stem(acts[i:i + chunk])
                              for i in range(0, len(acts), chunk)]).numpy().astype(np.float64)

    def reset(self) -> None:
        self.trunk.tail.load_state_dict(self.pretrained_tail)

    def tune(self, views: "torch.Tensor", labels: np.ndarray, n_classes: int, epochs: int,
             on_epoch=lambda e: None) -> None:
        """From the pretrained tail: a linear probe on the frozen features of ``views`` (stem
        activations, one row per augmented view), then tail + head for ``epochs`` epochs. BatchNorm
        stays in eval mode. ``on_epoch(e)`` is called after epochs 0 (probe only) .. ``epochs``."""
        torch = self.torch
        self.reset()
        torch.manual_seed(SEED)
        y = torch.from_numpy(labels.astype(np.int64))
        head = torch.nn.Linear(self.trunk.feature_dim, n_classes).double()
        feats = torch.from_numpy(self.features(views))
        opt = torch.optim.Adam(head.parameters(), lr=HEAD_LR)
        for _ in range(PROBE_STEPS):  # full batch: the probe on the frozen features
            opt.zero_grad()
            torch.nn.functional.cross_entropy(head(feats), y).backward()
            opt.step()
        head = head.float()
        on_epoch(0)
        params = [p for p in self.trunk.tail.parameters()] + list(head.parameters())
        opt = torch.optim.Adam(params, lr=LR)
        gen = torch.Generator().manual_seed(SEED)
        for e in range(1, epochs + 1):
            order = torch.randperm(len(views), generator=gen)
            for i in range(0, len(order), BATCH):
                b = order[i:i + BATCH]
                opt.zero_grad()
                loss = torch.nn.functional.cross_entropy(head(self.trunk.features_from_stem(views[b])), y[b])
                loss.backward()
                opt.step()
            on_epoch(e)


def _view_set(frames: list[list[np.ndarray]], idx: list[np.ndarray], seed: int) -> tuple[list, np.ndarray]:
    """The clean frame and VIEWS augmented variants of every press ``idx`` names, with labels."""
    rng = np.random.default_rng(seed)
    images, labels = [], []
    for c, (fs, ii) in enumerate(zip(frames, idx)):
        for i in ii:
            images += [clean(fs[i])] + [augment(fs[i], rng) for _ in range(VIEWS)]
            labels += [c] * (1 + VIEWS)
    return images, np.array(labels)


def _inner_accuracy(fit_x: np.ndarray, fit_y: np.ndarray, val_x: np.ndarray, val_y: np.ndarray) -> float:
    from vs2t_edge.train.real_check import _standardise, shrunk_lda_sq_distances

    fx, vx = _standardise(fit_x, val_x)
    return float(np.mean(shrunk_lda_sq_distances(fx, fit_y, int(fit_y.max()) + 1, vx).argmin(1) == val_y))


def choose_epochs(net: TunedTrunk, frames: list[list[np.ndarray]], fit: list[np.ndarray]) -> dict:
    """Epochs from EPOCH_CHOICES by shrunk-LDA accuracy inside the fit presses: the first
    SELECT_SHARE of each material's fit presses (press order) tune, the rest score."""
    inner = [ii[:max(1, min(len(ii) - 1, round(SELECT_SHARE * len(ii))))] for ii in fit]
    held = [ii[len(a):] for ii, a in zip(fit, inner)]
    if min(map(len, held)) == 0:
        return {"epochs": 0, "inner_accuracy": {}}
    images, labels = _view_set(frames, inner, SEED)
    views = net.stem(images)
    clean_rows = np.arange(0, len(images), 1 + VIEWS)
    held_acts = net.stem([clean(fs[i]) for fs, ii in zip(frames, held) for i in ii])
    held_y = np.concatenate([np.full(len(ii), c) for c, ii in enumerate(held)])
    scores = {}

    def score(e: int) -> None:
        if e in EPOCH_CHOICES:
            scores[e] = _inner_accuracy(net.features(views[clean_rows]), labels[clean_rows],
                                        net.features(held_acts), held_y)

    net.tune(views, labels, len(frames), max(EPOCH_CHOICES), on_epoch=score)
    best = max(EPOCH_CHOICES, key=lambda e: (scores[e], -e))  # ties: fewer epochs
    return {"epochs": int(best), "inner_accuracy": {str(k): v for k, v in scores.items()}}


def finetune(net: TunedTrunk, frames: list[list[np.ndarray]], fit: list[np.ndarray]) -> dict:
    """Tune ``net``'s tail on the fit presses ``fit`` of ``frames`` (per material, press indices),
    epochs chosen inside them; reads no other press. Returns what was chosen."""
    chosen = choose_epochs(net, frames, fit)
    images, labels = _view_set(frames, fit, SEED + 1)
    net.tune(net.stem(images), labels, len(frames), chosen["epochs"])
    return chosen


def finetuned_features(frames: list[list[np.ndarray]], fit: list[np.ndarray], net: TunedTrunk | None = None,
                       log=lambda m: None) -> list[np.ndarray]:
    """Per material, (presses, 1280) features of every press from the trunk tuned on ``fit``."""
    net = net or TunedTrunk()
    chosen = finetune(net, frames, fit)
    log(f"real-check: finetuned: {chosen['epochs']} epochs chosen inside the fit presses "
        f"(shrunk LDA accuracy by epochs {chosen['inner_accuracy']})")
    return [net.features(net.stem([clean(im) for im in fs])) for fs in frames]


__all__ = ["TunedTrunk", "augment", "finetune", "finetuned_features"]

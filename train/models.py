"""VS2T-ZSL's networks (paper section 4), sized from the feature dimensions.

- ``Encoder`` E: x_t -> (mu, logvar); hidden widths = d_t (the paper's 2048-2048-2048 for
  2048-d ResNet50 features, scaled with the trunk: 1280 for EfficientNet-Lite0).
- ``VSFusion`` VS-F: f = concat(v, s); m = f * sigmoid(W3 relu(W2 relu(W1 f))), 512-256-(d_v+d_s).
- ``Generator`` G: concat(z, m) -> hidden d_t (LeakyReLU 0.2) -> d_t (the paper's 2048-2048).
- ``Discriminator`` D: x -> hidden 512 (LeakyReLU) -> 1 logit; returns (logit, hidden) because
  L_rec and L_GD match D's last hidden layer.
- ``Classifier`` CLS: in -> 512 -> 512 -> n (LeakyReLU 0.2), CLS_t and CLS_u.
"""

from __future__ import annotations

import torch
from torch import nn


class Classifier(nn.Module):
    def __init__(self, in_dim: int, n_classes: int, hidden: tuple[int, ...] = (512, 512)) -> None:
        super().__init__()
        sizes = [in_dim, *hidden, n_classes]
        layers: list[nn.Module] = []
        for i in range(len(sizes) - 1):
            layers.append(nn.Linear(sizes[i], sizes[i + 1]))
            if i < len(sizes) - 2:
                layers.append(nn.LeakyReLU(0.2))  # same layout as baselines.SoftmaxClassifier: state dicts interchange
        self.net = nn.Sequential(*layers)
        self.in_dim, self.n_classes, self.hidden = in_dim, n_classes, tuple(hidden)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class Encoder(nn.Module):
    def __init__(self, d_x: int, latent: int, hidden: int | None = None) -> None:
        super().__init__()
        h = hidden or d_x
        self.body = nn.Sequential(nn.Linear(d_x, h), nn.LeakyReLU(0.2), nn.Linear(h, h), nn.LeakyReLU(0.2))
        self.mu = nn.Linear(h, latent)
        self.logvar = nn.Linear(h, latent)

    def forward(self, x):
        h = self.body(x)
        return self.mu(h), self.logvar(h).clamp(-10.0, 10.0)  # clamp: exp() stays finite


class VSFusion(nn.Module):
    def __init__(self, d_in: int, gate_bias: float = 0.0) -> None:
        super().__init__()
        self.gate = nn.Sequential(nn.Linear(d_in, 512), nn.ReLU(), nn.Linear(512, 256), nn.ReLU(),
                                  nn.Linear(256, d_in))
        if gate_bias:
            nn.init.constant_(self.gate[-1].bias, float(gate_bias))

    def forward(self, f):
        return f * torch.sigmoid(self.gate(f))


class Generator(nn.Module):
    def __init__(self, d_in: int, d_out: int, hidden: int | None = None) -> None:
        super().__init__()
        h = hidden or d_out
        self.net = nn.Sequential(nn.Linear(d_in, h), nn.LeakyReLU(0.2), nn.Linear(h, d_out))

    def forward(self, zm):
        return self.net(zm)


class Discriminator(nn.Module):
    def __init__(self, d_x: int, hidden: int = 512) -> None:
        super().__init__()
        self.hidden = nn.Sequential(nn.Linear(d_x, hidden), nn.LeakyReLU(0.2))
        self.out = nn.Linear(hidden, 1)

    def forward(self, x):
        h = self.hidden(x)
        return self.out(h).squeeze(1), h


__all__ = ["Classifier", "Encoder", "VSFusion", "Generator", "Discriminator"]

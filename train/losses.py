"""VS2T-ZSL's losses (paper section 4), batch means, numerically safe (logits, never log(sigmoid)).

Given D's (logit, last hidden h) on real x_t, on x_e = G(E(x_t), m) and on x_r = G(z ~ N(0, I), m):
- KL(N(mu, exp(logvar)) || N(0, I)), summed over latent dims;
- L_rec = ||x - x_e||^2 + ||h(x) - h(x_e)||^2 (squared L2 summed over dims, pairwise);
- L_D (eq. 3) = BCE(D(x), 1) + BCE(D(x_e), 0) + BCE(D(x_r), 0) with BCEWithLogits;
- L_GD = ||mean h(x_e) - mean h(x)||^2 + ||mean h(x_r) - mean h(x)||^2 (mean feature matching);
- L_E = KL + L_rec;  L_G = 1 * L_rec + 20 * L_GD.
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

GD_WEIGHT = 20.0


def kl_loss(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    return (-0.5 * torch.sum(1 + logvar - mu.pow(2) - logvar.exp(), dim=1)).mean()


def rec_loss(x, x_e, h_x, h_e) -> torch.Tensor:
    return ((x - x_e) ** 2).sum(1).mean() + ((h_x - h_e) ** 2).sum(1).mean()


def d_loss(logit_real, logit_e, logit_r) -> torch.Tensor:
    bce = F.binary_cross_entropy_with_logits
    loss = bce(logit_real, torch.ones_like(logit_real))
    if logit_e is not None:
        loss = loss + bce(logit_e, torch.zeros_like(logit_e))
    if logit_r is not None:
        loss = loss + bce(logit_r, torch.zeros_like(logit_r))
    return loss


def gd_loss(h_real, h_e, h_r) -> torch.Tensor:
    m = h_real.mean(0)
    loss = torch.zeros((), dtype=h_real.dtype)
    for h in (h_e, h_r):
        if h is not None:
            loss = loss + ((h.mean(0) - m) ** 2).sum()
    return loss


def g_loss(l_rec, l_gd, gd_weight: float = GD_WEIGHT) -> torch.Tensor:
    return l_rec + gd_weight * l_gd


__all__ = ["kl_loss", "rec_loss", "d_loss", "gd_loss", "g_loss", "GD_WEIGHT"]

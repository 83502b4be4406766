"""Modern feature generators after the paper, on the SAME fused visual+semantic condition
c = [x_v, s] (visual feature of a camera crop, 24 attributes) as VS2T-ZSL. Written from:

- f-CLSWGAN: Xian, Lorenz, Schiele, Akata, "Feature generating networks for zero-shot
  learning", CVPR 2018. Conditional WGAN-GP (lambda = 10, 5 critic steps per generator step)
  plus a classification loss of the generated features under a softmax classifier pretrained
  on real touched features (beta = 0.01).
- CADA-VAE: Schoenfeld, Ebrahimi, Sinha, Darrell, Akata, "Generalized zero- and few-shot
  learning via aligned variational autoencoders", CVPR 2019. One VAE per modality (tactile
  feature, condition), L1 reconstructions, cross-alignment (decode each modality from the other
  one's latent) and distribution alignment (2-Wasserstein distance between the two diagonal
  Gaussian posteriors), with the paper's warm-up schedules; CLS_u lives in the latent space.
- f-VAEGAN (the inductive f-VAEGAN-D2 of Xian, Sharma, Schiele, Akata, CVPR 2019, without the
  transductive D2, which needs unlabelled untouched tactile data the cell never has in
  training): a conditional VAE whose decoder is also the generator of a conditional WGAN-GP.

All methods are ``ZSLMethod``s (see ``baselines.py``): fit on one split's ``ZSLData``, give
``untouched_logits``. Loss functions are separate pure functions so tests can check them on
tiny tensors against hand-computed values.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from vs2t_edge.train.baselines import (
    Budget,
    ZSLData,
    ZSLMethod,
    _GenerativeZSL,
    _t,
    batches,
    gaussian_kl,
    mlp,
    predict_logits,
    train_classifier,
)

# --------------------------------------------------------------------------------------------
# losses
# --------------------------------------------------------------------------------------------


def gradient_penalty(critic, real: torch.Tensor, fake: torch.Tensor, cond: torch.Tensor,
                     alpha: torch.Tensor | None = None) -> torch.Tensor:
    """WGAN-GP (Gulrajani et al. 2017): E[(||grad_x D(x_hat, c)||_2 - 1)^2] on x_hat = a x + (1-a) x~."""
    if alpha is None:
        alpha = torch.rand(real.shape[0], 1)
    x_hat = (alpha * real + (1 - alpha) * fake).requires_grad_(True)
    out = critic(x_hat, cond)
    (grad,) = torch.autograd.grad(out.sum(), x_hat, create_graph=True)
    return ((grad.norm(2, dim=1) - 1.0) ** 2).mean()


def wgan_critic_loss(critic, real, fake, cond, gp_weight: float = 10.0, alpha=None) -> torch.Tensor:
    """f-CLSWGAN eq. 1, as minimised by the critic: E[D(x~,c)] - E[D(x,c)] + lambda * GP."""
    return (critic(fake, cond).mean() - critic(real, cond).mean()
            + gp_weight * gradient_penalty(critic, real, fake, cond, alpha))


def clswgan_generator_loss(d_fake: torch.Tensor, cls_logits_fake: torch.Tensor, labels: torch.Tensor,
                           cls_weight: float = 0.01) -> torch.Tensor:
    """f-CLSWGAN eq. 3 for G: -E[D(x~, c)] + beta * E[-log P(y | x~; theta)]."""
    return -d_fake.mean() + cls_weight * F.cross_entropy(cls_logits_fake, labels)


def diag_gaussian_w2(mu1: torch.Tensor, logvar1: torch.Tensor, mu2: torch.Tensor, logvar2: torch.Tensor) -> torch.Tensor:
    """CADA-VAE distribution alignment: 2-Wasserstein distance between diagonal Gaussians,
    sqrt(||mu1 - mu2||^2 + ||sigma1 - sigma2||^2) per sample, batch mean."""
    s1, s2 = torch.exp(0.5 * logvar1), torch.exp(0.5 * logvar2)
    return torch.sqrt(((mu1 - mu2) ** 2).sum(1) + ((s1 - s2) ** 2).sum(1) + 1e-12).mean()


def cada_vae_loss(x: torch.Tensor, c: torch.Tensor, out: dict[str, torch.Tensor], beta: float, gamma: float,
                  delta: float) -> dict[str, torch.Tensor]:
    """CADA-VAE objective: L_VAE + gamma L_CA + delta L_DA (all sums over dims, batch means).

    out holds x_rec (D_x(E_x(x))), c_rec (D_c(E_c(c))), x_from_c (D_x(E_c(c))), c_from_x
    (D_c(E_x(x))) and the posteriors mu_x, logvar_x, mu_c, logvar_c.
    """
    l1 = lambda a, b: torch.abs(a - b).sum(1).mean()  # noqa: E731
    rec = l1(out["x_rec"], x) + l1(out["c_rec"], c)
    kl = gaussian_kl(out["mu_x"], out["logvar_x"]) + gaussian_kl(out["mu_c"], out["logvar_c"])
    ca = l1(out["x_from_c"], x) + l1(out["c_from_x"], c)
    da = diag_gaussian_w2(out["mu_x"], out["logvar_x"], out["mu_c"], out["logvar_c"])
    total = rec + beta * kl + gamma * ca + delta * da
    return {"total": total, "rec": rec, "kl": kl, "ca": ca, "da": da}


def warmup(step: int, start: int, end: int, final: float) -> float:
    """CADA-VAE's linear warm-up: 0 before ``start``, ``final`` after ``end``."""
    if step <= start:
        return 0.0
    if step >= end:
        return final
    return final * (step - start) / (end - start)


def fvaegan_vae_loss(x: torch.Tensor, x_rec: torch.Tensor, mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """f-VAEGAN L_VAE: reconstruction (squared error summed over dims; the paper uses BCE on
    [0,1] features, ours are standardised) + KL, batch mean."""
    return ((x_rec - x) ** 2).sum(1).mean() + gaussian_kl(mu, logvar)


def fvaegan_generator_loss(x: torch.Tensor, x_rec: torch.Tensor, mu: torch.Tensor, logvar: torch.Tensor,
                           d_rec: torch.Tensor, d_fake: torch.Tensor, gan_weight: float = 10.0) -> torch.Tensor:
    """f-VAEGAN objective of E and G (the shared decoder/generator): L_VAE + gamma * the WGAN
    generator term on both reconstructions G(E(x, c), c) and prior samples G(z, c) (f-VAEGAN
    fig. 2): -(E[D(x_rec, c)] + E[D(x~, c)]) / 2."""
    return fvaegan_vae_loss(x, x_rec, mu, logvar) - gan_weight * (d_rec.mean() + d_fake.mean()) / 2


# --------------------------------------------------------------------------------------------
# networks
# --------------------------------------------------------------------------------------------


class ConditionalCritic(nn.Module):
    def __init__(self, d_x: int, d_c: int, hidden: int) -> None:
        super().__init__()
        self.net = mlp([d_x + d_c, hidden, 1])

    def forward(self, x, c):
        return self.net(torch.cat([x, c], 1)).squeeze(1)


class ConditionalGenerator(nn.Module):
    def __init__(self, d_z: int, d_c: int, hidden: int, d_x: int) -> None:
        super().__init__()
        self.d_z = d_z
        self.net = mlp([d_z + d_c, hidden, d_x])

    def forward(self, z, c):
        return self.net(torch.cat([z, c], 1))


# --------------------------------------------------------------------------------------------
# methods
# --------------------------------------------------------------------------------------------


class _FusedConditionGenerator(_GenerativeZSL):
    def _conditions_u(self, data):
        return data.condition_u()

    def _sample(self, c, gen):
        z = torch.randn(c.shape[0], self.G.d_z, generator=gen)
        with torch.no_grad():
            return self.G(z, c)


class FCLSWGAN(_FusedConditionGenerator):
    name = "f-CLSWGAN"
    n_critic = 5
    cls_weight = 0.01

    def fit(self, data: ZSLData, budget: Budget, seed: int):
        torch.manual_seed(seed)
        gen = torch.Generator().manual_seed(seed)
        cond = data.condition_t()
        d_c = cond.shape[1]
        # the classifier whose loss steers G is trained on real touched features and frozen
        self.cls_t = train_classifier(data.x_t, data.y, data.n_t, steps=budget.cls_steps, seed=seed,
                                      label=f"{self.name} CLS_t")
        for p in self.cls_t.parameters():
            p.requires_grad_(False)
        self.G = ConditionalGenerator(budget.latent, d_c, budget.hidden, data.d_t)
        self.D = ConditionalCritic(data.d_t, d_c, budget.hidden)
        opt_g = torch.optim.Adam(self.G.parameters(), lr=budget.lr, betas=(0.5, 0.999))
        opt_d = torch.optim.Adam(self.D.parameters(), lr=budget.lr, betas=(0.5, 0.999))
        x, c, y = _t(data.x_t), _t(cond), torch.as_tensor(data.y, dtype=torch.long)
        # budget.steps counts generator steps; critic steps are n_critic times as many but
        # cheaper; to keep methods comparable in wall time we divide the generator steps.
        g_steps = max(1, budget.steps // 2)
        it = batches(len(x), budget.batch, g_steps * (self.n_critic + 1), gen, label=f"{self.name} generator")
        for _ in range(g_steps):
            for _ in range(self.n_critic):
                idx = next(it)
                fake = self.G(torch.randn(len(idx), budget.latent), c[idx]).detach()
                d_loss = wgan_critic_loss(self.D, x[idx], fake, c[idx])
                opt_d.zero_grad()
                d_loss.backward()
                opt_d.step()
            idx = next(it)
            fake = self.G(torch.randn(len(idx), budget.latent), c[idx])
            g_loss = clswgan_generator_loss(self.D(fake, c[idx]), self.cls_t(fake), y[idx], self.cls_weight)
            opt_g.zero_grad()
            g_loss.backward()
            opt_g.step()
        self.G.eval()
        self._fit_cls_u(data, budget, seed)
        return self


class FVAEGAN(_FusedConditionGenerator):
    """Inductive f-VAEGAN-D2 (no D2): E(x, c) -> z, G(z, c) shared by the VAE and the WGAN."""

    name = "f-VAEGAN"
    n_critic = 5
    gan_weight = 10.0  # gamma_G of the authors' code

    def fit(self, data: ZSLData, budget: Budget, seed: int):
        torch.manual_seed(seed)
        gen = torch.Generator().manual_seed(seed)
        cond = data.condition_t()
        d_c = cond.shape[1]
        self.E = mlp([data.d_t + d_c, budget.hidden, 2 * budget.latent])
        self.G = ConditionalGenerator(budget.latent, d_c, budget.hidden, data.d_t)
        self.D = ConditionalCritic(data.d_t, d_c, budget.hidden)
        opt_ge = torch.optim.Adam(list(self.G.parameters()) + list(self.E.parameters()), lr=budget.lr,
                                  betas=(0.5, 0.999))
        opt_d = torch.optim.Adam(self.D.parameters(), lr=budget.lr, betas=(0.5, 0.999))
        x, c = _t(data.x_t), _t(cond)
        g_steps = max(1, budget.steps // 2)
        it = batches(len(x), budget.batch, g_steps * (self.n_critic + 1), gen, label=f"{self.name} generator")
        for _ in range(g_steps):
            for _ in range(self.n_critic):
                idx = next(it)
                fake = self.G(torch.randn(len(idx), budget.latent), c[idx]).detach()
                d_loss = wgan_critic_loss(self.D, x[idx], fake, c[idx])
                opt_d.zero_grad()
                d_loss.backward()
                opt_d.step()
            idx = next(it)
            mu, logvar = self.E(torch.cat([x[idx], c[idx]], 1)).chunk(2, dim=1)
            logvar = logvar.clamp(-10, 10)
            z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
            x_rec = self.G(z, c[idx])
            fake = self.G(torch.randn(len(idx), budget.latent), c[idx])
            loss = fvaegan_generator_loss(x[idx], x_rec, mu, logvar, self.D(x_rec, c[idx]), self.D(fake, c[idx]),
                                          self.gan_weight)
            opt_ge.zero_grad()
            loss.backward()
            opt_ge.step()
        self.G.eval()
        self._fit_cls_u(data, budget, seed)
        return self


class _CADANet(nn.Module):
    def __init__(self, d_x: int, d_c: int, latent: int, h_x: int, h_c: int) -> None:
        super().__init__()
        self.enc_x = mlp([d_x, h_x, 2 * latent])
        self.enc_c = mlp([d_c, h_c, 2 * latent])
        self.dec_x = mlp([latent, h_x, d_x])
        self.dec_c = mlp([latent, h_c, d_c])

    @staticmethod
    def _split(h):
        mu, logvar = h.chunk(2, dim=1)
        return mu, logvar.clamp(-10, 10)

    def encode_x(self, x):
        return self._split(self.enc_x(x))

    def encode_c(self, c):
        return self._split(self.enc_c(c))

    def forward(self, x, c):
        mu_x, lv_x = self.encode_x(x)
        mu_c, lv_c = self.encode_c(c)
        z_x = mu_x + torch.randn_like(mu_x) * torch.exp(0.5 * lv_x)
        z_c = mu_c + torch.randn_like(mu_c) * torch.exp(0.5 * lv_c)
        return {
            "x_rec": self.dec_x(z_x), "c_rec": self.dec_c(z_c),
            "x_from_c": self.dec_x(z_c), "c_from_x": self.dec_c(z_x),
            "mu_x": mu_x, "logvar_x": lv_x, "mu_c": mu_c, "logvar_c": lv_c,
        }


class CADAVAE(ZSLMethod):
    name = "CADA-VAE"
    # final weights of the paper (CUB): beta 0.25, gamma 2.37, delta 8.13; warm-ups as fractions
    # of training (paper: epochs 0-93 for beta, 21-75 for gamma, 6-22 for delta of 100).
    beta, gamma, delta = 0.25, 2.37, 8.13

    def fit(self, data: ZSLData, budget: Budget, seed: int):
        torch.manual_seed(seed)
        gen = torch.Generator().manual_seed(seed)
        cond = data.condition_t()
        self.net = _CADANet(data.d_t, cond.shape[1], budget.latent, min(1560, budget.hidden), min(1450, budget.hidden))
        opt = torch.optim.Adam(self.net.parameters(), lr=1.5e-4, amsgrad=True)
        x, c = _t(data.x_t), _t(cond)
        n = budget.steps
        for step, idx in enumerate(batches(len(x), budget.batch, n, gen, label=f"{self.name} generator")):
            out = self.net(x[idx], c[idx])
            losses = cada_vae_loss(
                x[idx], c[idx], out,
                beta=warmup(step, 0, int(0.93 * n), self.beta),
                gamma=warmup(step, int(0.21 * n), int(0.75 * n), self.gamma),
                delta=warmup(step, int(0.06 * n), int(0.22 * n), self.delta),
            )
            opt.zero_grad()
            losses["total"].backward()
            opt.step()
        self.net.eval()
        return self.retarget(data, budget, seed)

    def retarget(self, data: ZSLData, budget: Budget, seed: int):
        # CLS_u on latent samples drawn from the condition encoder of untouched crops
        cond_u, cls_u = data.condition_u()
        gen_s = torch.Generator().manual_seed(seed + 7)
        zs, ys = [], []
        with torch.no_grad():
            for k in range(data.n_u):
                rows = np.flatnonzero(cls_u == k)
                pick = rows[torch.randint(0, len(rows), (budget.n_synth_per_class,), generator=gen_s).numpy()]
                mu, lv = self.net.encode_c(_t(cond_u[pick]))
                zs.append((mu + torch.randn(mu.shape, generator=gen_s) * torch.exp(0.5 * lv)).numpy())
                ys.append(np.full(len(pick), k))
        self.cls_u = train_classifier(np.concatenate(zs), np.concatenate(ys), data.n_u, steps=budget.cls_steps,
                                      lr=1e-3, seed=seed, label=f"{self.name} CLS_u")
        return self

    def embed(self, x_t: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self.net.encode_x(_t(x_t))[0].numpy()

    def untouched_logits(self, x_t, x_v):
        return predict_logits(self.cls_u, self.embed(x_t))


MODERN: dict[str, type[ZSLMethod]] = {
    "f-CLSWGAN": FCLSWGAN,
    "CADA-VAE": CADAVAE,
    "f-VAEGAN": FVAEGAN,
}

"""VS2T-ZSL on cached features: the generative model (E, VS-F, G, D), its ablations and the
unimodal variants, as ``baselines.ZSLMethod`` rows so the shared split / GZSL machinery of
``compare.py`` evaluates them exactly like every baseline.

Algorithm 1's update order per mini-batch (x_t real tactile, v visual, s attributes):
  1. m = VS-F([v, s]); z ~ E(x_t) (reparameterised); x_e = G(z, m); x_r = G(n ~ N(0, I), m)
  2. D step: L_D (eq. 3) on x_t (real) vs x_e and x_r (detached), Adam lr 1e-5 x lr_scale
  3. E step: L_E = KL + L_rec, Adam lr 1e-4 x lr_scale
  4. G + VS-F step: L_G = L_rec + 20 L_GD, Adam lr 1e-4 x lr_scale
  (E and G gradients are taken from one forward pass, each for its own loss.)

Variants (``Variant``): ``no_e`` drops E: x_e does not exist, L_rec is taken between x_r and x_t
(the only paired output), KL is gone; ``no_vsf`` replaces m by the plain concatenation f;
``modality`` "vs" (VS2T), "v" (V2T: condition = visual only), "s" (S2T: attributes only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vs2t_edge.train import losses as L
from vs2t_edge.train.baselines import Budget, ZSLData, ZSLMethod, _GenerativeZSL, _t, batches, predict_logits
from vs2t_edge.train.models import Classifier, Discriminator, Encoder, Generator, VSFusion

# Paper rates; lr_scale multiplies all three (ratios kept) because our CPU schedule is far shorter.
LR_E, LR_G, LR_D = 1e-4, 1e-4, 1e-5
CLIP_SD = 4.0


@dataclass(frozen=True)
class Variant:
    name: str
    use_e: bool = True
    use_vsf: bool = True
    modality: str = "vs"


VARIANTS = {
    "VS2T-ZSL": Variant("VS2T-ZSL"),
    "w/o E": Variant("w/o E", use_e=False),
    "w/o VS-F": Variant("w/o VS-F", use_vsf=False),
    "w/o E, VS-F": Variant("w/o E, VS-F", use_e=False, use_vsf=False),
    "S2T": Variant("S2T", modality="s"),
    "V2T": Variant("V2T", modality="v"),
}
PAPER = {"VS2T-ZSL": 83.06, "w/o E": 79.50, "w/o VS-F": 78.21, "w/o E, VS-F": 74.61, "S2T": 55.07, "V2T": 72.71}
PAPER_GZSL = {"acc_t": 94.56, "acc_u": 76.00, "H": 84.27}


@dataclass
class VS2TBudget(Budget):
    lr_scale: float = 5.0
    latent: int = 64
    hidden: int | None = None  # E / G hidden width; None: the feature size (paper: 2048 for 2048-d)
    kl_weight: float = 1.0  # weight of KL in L_E (paper: 1)
    # VS-F's gate starts at sigmoid(gate_bias): 0 (PyTorch's default, run 1) halved the condition at
    # the start; 3 (0.95) starts VS-F as the plain concatenation and lets it learn to down-weight
    # (validation ZSL, paper profile, 5 splits: 54.9 -> 56.8 %)
    gate_bias: float = 3.0
    lr_decay: str = "none"  # "none" or "cosine" (to 0 over the run's steps)
    weight_decay: float = 0.0  # Adam weight decay of G and VS-F
    cond_noise: float = 0.0  # std of Gaussian noise added to the condition in training (not at synthesis)
    # "press": the crop at each press (run 1): G learnt press-level detail from 40 fabrics and
    # generalised worse to new fabrics; "fabric": the fabric's mean crop feature, so within-fabric
    # variation must come from z (validation ZSL 54.9 -> 58.3 %; with gate_bias 3: see docs/training.md)
    visual_condition: str = "fabric"
    cond_pca: int = 0  # > 0: visual condition = its top-k principal components (fitted on touched presses), whitened
    # True: E is q(z | x, v, s) as in the paper (the press's feature and its condition); False: q(z | x)
    encoder_condition: bool = False
    # > 1: that many generators (E, VS-F, G, D), each trained as above from its own seed (the first
    # from the split's seed, so member 0 is the single generator), their synthesised samples pooled
    # per class (n_synth_per_class from each) for CLS_u and the scene decision's class means
    ensemble: int = 1


ENSEMBLE_SEED_STEP = 100  # member j trains from seed + 100 j (split seeds are 1000 s + k)


class VS2TZSL(_GenerativeZSL):
    """One variant of VS2T-ZSL. ``fit`` reads only ``ZSLData``: touched training presses' real
    tactile features and, for untouched classes, visual features and attributes — never their
    tactile features (``ZSLData`` has none)."""

    variant = VARIANTS["VS2T-ZSL"]
    instances: list = []

    def __init__(self) -> None:
        self.name = self.variant.name
        self.cls_u_by_classes: dict[tuple[str, ...], Classifier] = {}
        self.history: list[dict] = []
        type(self).instances.append(self)  # compare.run_split discards its instances; the run keeps them

    # conditions -------------------------------------------------------------------------
    def _cond(self, v: np.ndarray, s: np.ndarray) -> np.ndarray:
        # Visual features are standardised on touched presses; a channel almost constant there
        # gets values in the hundreds for an unseen fabric and G extrapolates wildly (measured:
        # W1 real-synth ~500 vs 0.6 without vision). Clip to +-CLIP_SD standard deviations.
        v = np.clip(v, -CLIP_SD, CLIP_SD)
        parts = {"vs": [v, s], "v": [v], "s": [s]}[self.variant.modality]
        return np.concatenate(parts, axis=1).astype(np.float32)

    def _visual(self, v: np.ndarray, cls: np.ndarray) -> np.ndarray:
        """Per-press visual features, or (``visual_condition`` "fabric") each row replaced by its
        fabric's mean clipped visual feature."""
        v = np.clip(v, -CLIP_SD, CLIP_SD)
        basis = getattr(self, "pca_basis", None)
        if basis is not None:
            v = ((v - self.pca_mean) @ basis).astype(np.float32)
        if getattr(self, "visual_condition", "press") != "fabric":
            return v
        out = np.empty_like(v)
        for k in np.unique(cls):
            out[cls == k] = v[cls == k].mean(0)
        return out

    def _conditions_u(self, data: ZSLData):
        return self._cond(self._visual(data.v_u, data.v_u_class), data.attr_u[data.v_u_class]), data.v_u_class

    def _fuse(self, c: torch.Tensor) -> torch.Tensor:
        return self.vsf(c) if self.vsf is not None else c

    def _sample(self, c: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        with torch.no_grad():
            z = torch.randn(c.shape[0], self.latent, generator=gen)
            return self.G(torch.cat([z, self._fuse(c)], 1))

    # training ---------------------------------------------------------------------------
    def build(self, d_t: int, d_c: int, budget: Budget) -> None:
        h = getattr(budget, "hidden", None) or d_t
        h = h if isinstance(h, int) and h > 0 else d_t
        self.latent = int(budget.latent)
        self.encoder_condition = bool(getattr(budget, "encoder_condition", False))
        self.E = Encoder(d_t + (d_c if self.encoder_condition else 0), self.latent, h) if self.variant.use_e else None
        self.vsf = VSFusion(d_c, gate_bias=float(getattr(budget, "gate_bias", 0.0))) if self.variant.use_vsf else None
        self.G = Generator(self.latent + d_c, d_t, h)
        self.D = Discriminator(d_t)

    @classmethod
    def unregistered(cls) -> "VS2TZSL":
        """A method not in ``instances`` (an ensemble's member, a validation fold's generator):
        only what a run fits as its method is one."""
        method = object.__new__(cls)
        method.name, method.history = cls.variant.name, []
        return method

    def fit(self, data: ZSLData, budget: Budget, seed: int, steps: int | None = None) -> "VS2TZSL":
        self.fit_generators(data, budget, seed, steps)
        self._fit_cls_u(data, budget, seed)
        return self

    def fit_generators(self, data: ZSLData, budget: Budget, seed: int, steps: int | None = None) -> "VS2TZSL":
        """The generator (``budget.ensemble`` of them, pooled by ``synthesise``), without CLS_u."""
        n = int(getattr(budget, "ensemble", 1))
        if n < 1:
            raise ValueError(f"VS2TBudget.ensemble {n}: need at least 1 generator")
        self._fit_generator(data, budget, seed, steps)
        self.members = [self]
        for j in range(1, n):
            member = self.unregistered()
            member._fit_generator(data, budget, seed + ENSEMBLE_SEED_STEP * j, steps)
            self.members.append(member)
        return self

    def synthesise(self, data: ZSLData, budget: Budget, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """``n_synth_per_class`` samples per untouched class from each member, pooled (grouped by
        member; every member draws with the same seed)."""
        members = getattr(self, "members", [self])
        if len(members) == 1:
            return super().synthesise(data, budget, seed)
        parts = [_GenerativeZSL.synthesise(m, data, budget, seed) for m in members]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    def _fit_generator(self, data: ZSLData, budget: Budget, seed: int, steps: int | None = None) -> None:
        torch.manual_seed(seed)
        gen = torch.Generator().manual_seed(seed)
        self.visual_condition = getattr(budget, "visual_condition", "press")
        self.pca_basis = None
        k = int(getattr(budget, "cond_pca", 0) or 0)
        if k > 0 and self.variant.modality != "s":
            # principal axes of the touched training presses' clipped visual features only
            v = np.clip(data.x_v, -CLIP_SD, CLIP_SD).astype(np.float64)
            mean = v.mean(0)
            _, sv, vt = np.linalg.svd(v - mean, full_matrices=False)
            k = min(k, len(sv))
            scale = sv[:k] / np.sqrt(max(len(v) - 1, 1))
            self.pca_mean = mean.astype(np.float32)
            self.pca_basis = (vt[:k].T / np.maximum(scale, 1e-8)).astype(np.float32)
        cond = self._cond(self._visual(data.x_v, data.y), data.attr_t[data.y])
        self.build(data.d_t, cond.shape[1], budget)
        self.train_generator(data.x_t, cond, budget, gen, steps)

    def train_generator(self, x_np, c_np, budget: Budget, gen: torch.Generator, steps: int | None = None) -> None:
        scale = float(getattr(budget, "lr_scale", 5.0))
        opt_e = torch.optim.Adam(self.E.parameters(), lr=LR_E * scale) if self.E is not None else None
        g_params = list(self.G.parameters()) + (list(self.vsf.parameters()) if self.vsf is not None else [])
        opt_g = torch.optim.Adam(g_params, lr=LR_G * scale, weight_decay=float(getattr(budget, "weight_decay", 0.0)))
        cond_noise = float(getattr(budget, "cond_noise", 0.0))
        opt_d = torch.optim.Adam(self.D.parameters(), lr=LR_D * scale)
        x_all, c_all = _t(x_np), _t(c_np)
        n_steps = budget.steps if steps is None else steps
        kl_w = float(getattr(budget, "kl_weight", 1.0))
        opts = [o for o in (opt_e, opt_g, opt_d) if o is not None]
        scheds = ([torch.optim.lr_scheduler.CosineAnnealingLR(o, max(1, n_steps)) for o in opts]
                  if getattr(budget, "lr_decay", "none") == "cosine" else [])
        for step, idx in enumerate(batches(len(x_all), budget.batch, n_steps, gen, label=f"{self.name} generator")):
            x, c = x_all[idx], c_all[idx]
            if cond_noise > 0:
                c = c + cond_noise * torch.randn(c.shape, generator=gen)
            m = self._fuse(c)
            noise = torch.randn(len(idx), self.latent, generator=gen)
            x_r = self.G(torch.cat([noise, m], 1))
            if self.E is not None:
                mu, logvar = self.E(torch.cat([x, c], 1) if self.encoder_condition else x)
                z = mu + torch.randn(mu.shape, generator=gen) * torch.exp(0.5 * logvar)
                x_e = self.G(torch.cat([z, m], 1))
            else:
                mu = logvar = x_e = None
            # 2. D on detached fakes
            l_d = L.d_loss(self.D(x)[0], self.D(x_e.detach())[0] if x_e is not None else None,
                           self.D(x_r.detach())[0])
            opt_d.zero_grad()
            l_d.backward()
            opt_d.step()
            # 3./4. E and G(+VS-F) through the updated D; D's own parameters are not stepped
            _, h_x = self.D(x)
            h_x = h_x.detach()
            _, h_r = self.D(x_r)
            if x_e is not None:
                _, h_e = self.D(x_e)
                l_rec = L.rec_loss(x, x_e, h_x, h_e)
                l_kl = L.kl_loss(mu, logvar)
            else:
                h_e = None
                l_rec = L.rec_loss(x, x_r, h_x, h_r)  # without E the only paired output is x_r
                l_kl = torch.zeros(())
            l_gd = L.gd_loss(h_x, h_e, h_r)
            l_g = L.g_loss(l_rec, l_gd)
            grads_g = torch.autograd.grad(l_g, g_params, retain_graph=self.E is not None, allow_unused=True)
            if self.E is not None:
                e_params = list(self.E.parameters())
                grads_e = torch.autograd.grad(kl_w * l_kl + l_rec, e_params)
                for p, g in zip(e_params, grads_e):
                    p.grad = g
                opt_e.step()
            for p, g in zip(g_params, grads_g):
                p.grad = g
            opt_g.step()
            for sc in scheds:
                sc.step()
            if step % 50 == 0 or step == n_steps - 1:
                self.history.append({"step": step, "D": l_d.item(), "rec": l_rec.item(), "GD": l_gd.item(),
                                     "KL": l_kl.item()})
        self.G.eval()

    def _fit_cls_u(self, data: ZSLData, budget: Budget, seed: int) -> None:
        xs, ys = self.synthesise(data, budget, seed)
        self.cls_u = train_cls(xs, ys, data.n_u, steps=budget.cls_steps, seed=seed, label=f"{self.name} CLS_u")
        self.cls_u_by_classes[tuple(data.names_u)] = self.cls_u

    def untouched_logits(self, x_t, x_v):
        return predict_logits(self.cls_u, x_t)


def train_cls(x: np.ndarray, y: np.ndarray, n_classes: int, *, steps: int = 600, batch: int = 128, lr: float = 1e-3,
              seed: int = 0, weight_decay: float = 1e-4, label: str = "CLS") -> Classifier:
    """CLS (512-512-n) with softmax cross-entropy, seeded."""
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    clf = Classifier(x.shape[1], n_classes)
    opt = torch.optim.Adam(clf.parameters(), lr=lr, weight_decay=weight_decay)
    xt, yt = _t(x), torch.as_tensor(np.asarray(y), dtype=torch.long)
    for idx in batches(len(xt), batch, steps, gen, label=label):
        loss = torch.nn.functional.cross_entropy(clf(xt[idx]), yt[idx])
        opt.zero_grad()
        loss.backward()
        opt.step()
    clf.eval()
    return clf


def variant_class(name: str) -> type[VS2TZSL]:
    return type(f"VS2T_{abs(hash(name)) % 10**6}", (VS2TZSL,), {"variant": VARIANTS[name], "name": name,
                                                                  "instances": []})


def all_variants() -> dict[str, type[ZSLMethod]]:
    return {k: variant_class(k) for k in VARIANTS}


__all__ = ["VS2TZSL", "VS2TBudget", "Variant", "VARIANTS", "PAPER", "PAPER_GZSL", "train_cls", "all_variants",
           "variant_class"]

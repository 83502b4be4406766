"""Losses of every comparison method on tiny tensors against hand-computed values, and a quick
end-to-end check that each method learns a separable toy split better than chance."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from vs2t_edge.train import baselines as bl
from vs2t_edge.train import generators_modern as gm


def test_dap_posterior_by_hand():
    # one press, two attributes with p(a=1|x) = (0.9, 0.2); class A = (1, 0), class B = (0, 1)
    p = np.array([[0.9, 0.2]])
    attrs = np.array([[1, 0], [0, 1]])
    out = bl.dap_class_log_posterior(p, attrs)
    assert out[0, 0] == pytest.approx(math.log(0.9) + math.log(0.8))
    assert out[0, 1] == pytest.approx(math.log(0.1) + math.log(0.2))
    # with prior p(a=1) = (0.5, 0.25): subtract log p(a^z) per class
    out = bl.dap_class_log_posterior(p, attrs, prior=np.array([0.5, 0.25]))
    assert out[0, 0] == pytest.approx(math.log(0.9) + math.log(0.8) - math.log(0.5) - math.log(0.75))
    assert out[0, 1] == pytest.approx(math.log(0.1) + math.log(0.2) - math.log(0.5) - math.log(0.25))


def test_attribute_bce_by_hand():
    logits = torch.tensor([[0.0, 2.0]])
    target = torch.tensor([[1.0, 0.0]])
    expected = (math.log(2) + math.log1p(math.exp(2))) / 2
    assert bl.attribute_bce_loss(logits, target).item() == pytest.approx(expected, rel=1e-6)


def test_kl_and_cvae_loss_by_hand():
    mu = torch.tensor([[1.0, 0.0]])
    logvar = torch.tensor([[0.0, math.log(4.0)]])
    # KL = 0.5 * sum(var + mu^2 - 1 - logvar) = 0.5 * ((1 + 1 - 1 - 0) + (4 + 0 - 1 - log 4))
    kl = 0.5 * (1 + 3 - math.log(4))
    assert bl.gaussian_kl(mu, logvar).item() == pytest.approx(kl, rel=1e-6)
    x = torch.tensor([[1.0, 2.0, 3.0]])
    x_rec = torch.tensor([[1.5, 2.0, 1.0]])
    assert bl.cvae_loss(x, x_rec, mu, logvar).item() == pytest.approx(0.25 + 4.0 + kl, rel=1e-6)
    assert bl.cvae_loss(x, x_rec, mu, logvar, kl_weight=0.0).item() == pytest.approx(4.25, rel=1e-6)


def test_pix2pix_losses_by_hand():
    d_fake = torch.tensor([0.0])
    d_real = torch.tensor([math.log(3.0)])  # sigmoid = 0.75
    fake = torch.tensor([[1.0, 2.0]])
    real = torch.tensor([[0.0, 2.5]])
    g = bl.pix2pix_generator_loss(d_fake, fake, real, l1_weight=100.0)
    assert g.item() == pytest.approx(math.log(2) + 100 * 0.75, rel=1e-6)
    d = bl.pix2pix_discriminator_loss(d_real, d_fake)
    assert d.item() == pytest.approx(0.5 * (-math.log(0.75) + math.log(2)), rel=1e-6)


class _LinearCritic(torch.nn.Module):
    """D(x, c) = w.x + u.c: its gradient in x is w everywhere, so GP = (||w|| - 1)^2."""

    def __init__(self, w, u):
        super().__init__()
        self.w, self.u = torch.tensor(w), torch.tensor(u)

    def forward(self, x, c):
        return x @ self.w + c @ self.u


def test_wgan_gp_critic_loss_by_hand():
    critic = _LinearCritic([3.0, 4.0], [1.0])  # ||w|| = 5 -> GP = 16
    real = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    fake = torch.tensor([[0.0, 0.0], [1.0, 1.0]])
    cond = torch.tensor([[1.0], [2.0]])
    # E D(fake) = mean(0 + 1, 7 + 2) = 5 ; E D(real) = mean(3 + 1, 4 + 2) = 5
    assert gm.gradient_penalty(critic, real, fake, cond).item() == pytest.approx(16.0, rel=1e-6)
    loss = gm.wgan_critic_loss(critic, real, fake, cond, gp_weight=10.0)
    assert loss.item() == pytest.approx(5 - 5 + 160.0, rel=1e-6)


def test_gradient_penalty_is_zero_for_unit_gradient():
    critic = _LinearCritic([0.6, 0.8], [0.0])
    x = torch.randn(4, 2)
    assert gm.gradient_penalty(critic, x, x + 1, torch.zeros(4, 1)).item() == pytest.approx(0.0, abs=1e-10)


def test_clswgan_generator_loss_by_hand():
    d_fake = torch.tensor([1.0, 3.0])
    logits = torch.tensor([[0.0, 0.0], [math.log(3.0), 0.0]])  # p(y=0) = 0.5 and 0.75
    labels = torch.tensor([0, 0])
    ce = (math.log(2) - math.log(0.75)) / 2
    loss = gm.clswgan_generator_loss(d_fake, logits, labels, cls_weight=0.01)
    assert loss.item() == pytest.approx(-2.0 + 0.01 * ce, rel=1e-6)


def test_w2_between_diagonal_gaussians_by_hand():
    mu1, mu2 = torch.tensor([[0.0, 0.0]]), torch.tensor([[3.0, 0.0]])
    lv1 = torch.tensor([[0.0, 0.0]])  # sigma 1, 1
    lv2 = torch.tensor([[math.log(4.0), 0.0]])  # sigma 2, 1
    assert gm.diag_gaussian_w2(mu1, lv1, mu2, lv2).item() == pytest.approx(math.sqrt(9 + 1), rel=1e-5)
    assert gm.diag_gaussian_w2(mu1, lv1, mu1, lv1).item() == pytest.approx(0.0, abs=1e-5)


def test_cada_vae_loss_by_hand():
    x = torch.tensor([[1.0, 2.0]])
    c = torch.tensor([[0.0]])
    out = {
        "x_rec": torch.tensor([[1.0, 1.0]]),  # L1 = 1
        "c_rec": torch.tensor([[0.5]]),  # L1 = 0.5
        "x_from_c": torch.tensor([[0.0, 2.0]]),  # L1 = 1
        "c_from_x": torch.tensor([[-2.0]]),  # L1 = 2
        "mu_x": torch.tensor([[0.0]]), "logvar_x": torch.tensor([[0.0]]),  # KL 0
        "mu_c": torch.tensor([[2.0]]), "logvar_c": torch.tensor([[0.0]]),  # KL 2, W2 = 2
    }
    losses = gm.cada_vae_loss(x, c, out, beta=0.5, gamma=2.0, delta=3.0)
    assert losses["rec"].item() == pytest.approx(1.5)
    assert losses["kl"].item() == pytest.approx(2.0)
    assert losses["ca"].item() == pytest.approx(3.0)
    assert losses["da"].item() == pytest.approx(2.0, rel=1e-5)
    assert losses["total"].item() == pytest.approx(1.5 + 0.5 * 2 + 2 * 3 + 3 * 2, rel=1e-5)


def test_cada_warmup_schedule():
    assert gm.warmup(0, 10, 20, 8.0) == 0.0
    assert gm.warmup(15, 10, 20, 8.0) == pytest.approx(4.0)
    assert gm.warmup(25, 10, 20, 8.0) == 8.0


def test_fvaegan_vae_loss_by_hand():
    x = torch.tensor([[0.0, 1.0]])
    x_rec = torch.tensor([[1.0, 1.0]])
    mu, lv = torch.tensor([[1.0]]), torch.tensor([[0.0]])
    assert gm.fvaegan_vae_loss(x, x_rec, mu, lv).item() == pytest.approx(1.0 + 0.5)


def test_fvaegan_generator_loss_by_hand():
    x, x_rec = torch.tensor([[0.0, 1.0]]), torch.tensor([[1.0, 1.0]])
    mu, lv = torch.tensor([[1.0]]), torch.tensor([[0.0]])
    d_rec, d_fake = torch.tensor([2.0, 4.0]), torch.tensor([-1.0, 1.0])
    # L_VAE 1.5; WGAN term -(mean 3 + mean 0) / 2 = -1.5, times gamma 10
    assert gm.fvaegan_generator_loss(x, x_rec, mu, lv, d_rec, d_fake, 10.0).item() == pytest.approx(1.5 - 15.0)
    assert gm.fvaegan_generator_loss(x, x_rec, mu, lv, d_rec, d_fake, 0.0).item() == pytest.approx(1.5)


def test_feature_scaler_keeps_dead_channels_at_zero():
    x = np.c_[np.zeros(5), np.arange(5.0)]
    s = bl.FeatureScaler.fit(x)
    out = s(x)
    assert np.all(out[:, 0] == 0) and out[:, 1].std() == pytest.approx(1.0, rel=1e-6)


def _toy_split(seed=0, n_t=8, n_u=3, d_t=32, d_v=16, per=30):
    """Classes whose tactile and visual features are linear in their attributes plus noise."""
    rng = np.random.default_rng(seed)
    a = rng.integers(0, 2, (n_t + n_u, 24)).astype(float)
    wa, wv = rng.normal(size=(24, d_t)), rng.normal(size=(24, d_v))

    def make(c, k):
        return a[c] @ wa + rng.normal(size=(k, d_t)) * 0.7, a[c] @ wv + rng.normal(size=(k, d_v)) * 0.7

    tr = [make(c, per) for c in range(n_t)]
    cond_u = [make(n_t + k, per) for k in range(n_u)]
    test_u = [make(n_t + k, per) for k in range(n_u)]
    sx = bl.FeatureScaler.fit(np.concatenate([t[0] for t in tr]))
    sv = bl.FeatureScaler.fit(np.concatenate([t[1] for t in tr]))
    data = bl.ZSLData(
        x_t=sx(np.concatenate([t[0] for t in tr])), x_v=sv(np.concatenate([t[1] for t in tr])),
        y=np.repeat(np.arange(n_t), per), attr_t=a[:n_t], attr_u=a[n_t:],
        v_u=sv(np.concatenate([c[1] for c in cond_u])), v_u_class=np.repeat(np.arange(n_u), per),
    )
    test = (sx(np.concatenate([t[0] for t in test_u])), sv(np.concatenate([t[1] for t in test_u])),
            np.repeat(np.arange(n_u), per))
    return data, test


@pytest.mark.parametrize("name", [*bl.BASELINES, *gm.MODERN])
def test_each_method_beats_chance_on_a_separable_toy_split(name):
    torch.set_num_threads(1)
    data, (x_te, v_te, y_te) = _toy_split()
    budget = bl.Budget(steps=240, batch=32, hidden=64, latent=8, cls_steps=150, n_synth_per_class=60, lr=1e-3)
    method = {**bl.BASELINES, **gm.MODERN}[name]().fit(data, budget, seed=0)
    logits = method.untouched_logits(x_te, v_te)
    assert logits.shape == (len(y_te), data.n_u) and np.all(np.isfinite(logits))
    acc = float(np.mean(logits.argmax(1) == y_te))
    assert acc > 1.0 / data.n_u + 0.15, f"{name}: accuracy {acc:.2f} on a separable toy split"


def test_vs2t_row_is_the_training_rooms_model_and_beats_chance():
    """The comparison's VS2T-ZSL row is train/vs2t.py's VS2TZSL (no private copy)."""
    from vs2t_edge.train import compare as cmp
    from vs2t_edge.train import vs2t

    torch.set_num_threads(1)
    cls = cmp.all_methods()["VS2T-ZSL"]
    assert issubclass(cls, vs2t.VS2TZSL) and cls.variant == vs2t.VARIANTS["VS2T-ZSL"]
    assert not hasattr(gm, "VS2TPrivate")
    data, (x_te, v_te, y_te) = _toy_split()
    budget = vs2t.VS2TBudget(steps=240, batch=32, hidden=64, latent=8, cls_steps=150, n_synth_per_class=60)
    m = cls().fit(data, budget, seed=0)
    assert float(np.mean(m.untouched_logits(x_te, v_te).argmax(1) == y_te)) > 1 / 3 + 0.15

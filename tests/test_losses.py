"""VS2T-ZSL losses against values computed by hand on tiny tensors."""

import math

import torch

from vs2t_edge.train import losses as L


def test_kl_zero_for_standard_normal_and_hand_value():
    assert float(L.kl_loss(torch.zeros(3, 2), torch.zeros(3, 2))) == 0.0
    # one sample, one dim: mu = 1, logvar = log 2 -> -0.5 (1 + log2 - 1 - 2) = 0.5 (2 - log 2)
    got = float(L.kl_loss(torch.tensor([[1.0]]), torch.tensor([[math.log(2.0)]])))
    assert abs(got - 0.5 * (2 - math.log(2.0))) < 1e-6


def test_rec_loss_is_summed_squares_plus_feature_matching():
    x = torch.tensor([[1.0, 2.0], [0.0, 0.0]])
    x_e = torch.tensor([[0.0, 0.0], [1.0, 1.0]])
    h_x = torch.tensor([[1.0], [1.0]])
    h_e = torch.tensor([[3.0], [1.0]])
    # L2: (1 + 4) and (1 + 1) -> mean 3.5; FM: (4) and (0) -> mean 2
    assert abs(float(L.rec_loss(x, x_e, h_x, h_e)) - 5.5) < 1e-6


def test_d_loss_is_bce_with_logits_real_one_fakes_zero():
    zero = torch.zeros(4)
    # logit 0 -> BCE log 2 for each term, three terms
    assert abs(float(L.d_loss(zero, zero, zero)) - 3 * math.log(2.0)) < 1e-6
    # very confident correct D: loss ~ 0 and finite (no log of a saturated sigmoid)
    big = torch.full((4,), 100.0)
    v = float(L.d_loss(big, -big, -big))
    assert math.isfinite(v) and v < 1e-6
    # very confident wrong D: ~ 3 * 100, still finite
    assert abs(float(L.d_loss(-big, big, big)) - 300.0) < 1e-3


def test_gd_loss_mean_feature_matching_and_g_weight():
    h = torch.tensor([[0.0, 0.0], [2.0, 2.0]])  # mean (1, 1)
    h_e = torch.tensor([[1.0, 1.0], [1.0, 1.0]])  # mean equal -> 0
    h_r = torch.tensor([[3.0, 1.0], [3.0, 1.0]])  # mean (3, 1) -> 4
    assert abs(float(L.gd_loss(h, h_e, h_r)) - 4.0) < 1e-6
    assert abs(float(L.g_loss(torch.tensor(1.5), torch.tensor(0.25))) - (1.5 + 20 * 0.25)) < 1e-6

"""The tactile tail's attribute task (``Profile.ft_attributes``, train/features.py): beside the
softmax over touched fabrics, a linear head regresses each touched-train press's fabric attributes,
so the features carry what attributes can predict - where a generator conditioned on attributes
can reach an untouched fabric. Its zero-shot guard is in tests/test_zsl_guard.py (the run with the
task on, untouched attributes flipped, every touched-side artefact bit-identical)."""

import numpy as np
import pytest
import torch

from vs2t_edge.train import features as ft
from vs2t_edge.train.trunks import build_trunk


def _trunk(c_in: int, width: int = 32):
    torch.manual_seed(0)
    trunk = build_trunk("tiny")
    trunk.stem = torch.nn.Identity()  # the rows below are the stem's output
    trunk.tail = torch.nn.Sequential(torch.nn.Conv2d(c_in, width, 1), torch.nn.BatchNorm2d(width), torch.nn.ReLU())
    trunk.feature_dim = width
    return trunk


def test_targets_are_the_rows_fabrics_attributes_standardised_over_those_fabrics_only():
    attrs = np.array([[1, 0, 1], [0, 0, 1], [1, 1, 1], [np.nan, 7, -3]], float)  # fabric 3 is no row's
    fabric = np.array([0, 0, 1, 2, 2, 2, 3, 3])
    rows = np.array([0, 1, 2, 3, 5])
    z = ft.attribute_targets(attrs, fabric, rows)
    assert z.shape == (5, 3) and z.dtype == np.float32 and np.isfinite(z).all()
    seen = attrs[:3]
    want = (seen[fabric[rows]] - seen.mean(0)) / (seen.std(0) + 1e-6)
    np.testing.assert_allclose(z, want, rtol=1e-6)
    assert np.all(z[:, 2] == 0)  # constant over the touched fabrics: nothing to learn
    # each fabric weighs once, whatever its number of rows
    np.testing.assert_allclose(z[[0, 2, 3]].mean(0), 0, atol=1e-6)


def test_weight_zero_is_the_softmax_alone_and_a_weight_changes_the_tail():
    rng = np.random.default_rng(0)
    y = np.repeat(np.arange(4), 12)
    stem = (rng.normal(size=(len(y), 8, 3, 3)) + y[:, None, None, None]).astype(np.float32)
    aux = rng.normal(size=(len(y), 5)).astype(np.float32)
    kw = dict(epochs=1, max_rows=40, seed=3, progress=False)
    plain = ft.finetune_tail(_trunk(8), stem, y, 4, **kw)
    zero = ft.finetune_tail(_trunk(8), stem, y, 4, aux=aux, aux_weight=0.0, **kw)
    on = ft.finetune_tail(_trunk(8), stem, y, 4, aux=aux, aux_weight=1.0, **kw)
    for k, v in plain.state_dict().items():
        assert torch.equal(v, zero.state_dict()[k]), k
    assert any(not torch.equal(v, on.state_dict()[k]) for k, v in plain.state_dict().items())
    with pytest.raises(ValueError, match="3 auxiliary targets for 48 rows"):
        ft.finetune_tail(_trunk(8), stem, y, 4, aux=aux[:3], aux_weight=1.0, **kw)


def _attribute_world(seed: int):
    """24 fabrics whose stem activations mix what their attributes say (a fixed map of 6 binary
    attributes) with a stronger per-fabric nuisance no attribute predicts (where a real piece's
    loops and slubs fall)."""
    rng = np.random.default_rng(seed)
    n_f, presses, c = 24, 12, 24
    attrs = rng.integers(0, 2, size=(n_f, 6)).astype(np.float64)
    centre = attrs @ rng.normal(size=(6, c)) + 2.0 * rng.normal(size=(n_f, c))
    fabric = np.repeat(np.arange(n_f), presses)
    stem = centre[fabric][:, :, None, None] + 0.3 * rng.normal(size=(len(fabric), c, 2, 2))
    return stem.astype(np.float32), fabric, attrs


def _attribute_error(feats: np.ndarray, targets: np.ndarray) -> float:
    """Mean squared error of the best ridge map from the (standardised) features to the targets."""
    x = np.c_[(feats - feats.mean(0)) / (feats.std(0) + 1e-6), np.ones(len(feats))]
    w = np.linalg.solve(x.T @ x + np.eye(x.shape[1]), x.T @ targets)
    return float(((x @ w - targets) ** 2).mean())


@pytest.mark.parametrize("seed", [0, 1])
def test_the_attribute_task_puts_the_presses_attributes_into_the_feature(seed):
    """A 4-wide tail on a world where touch mixes attributes with a stronger per-fabric nuisance:
    the softmax alone keeps whatever tells the fabrics apart; with the task the features say
    clearly more of each press's attributes (measured: error 0.42-0.61 against 0.56-0.75 over six
    seeds). The same task on targets shuffled across presses buys nothing: the targets must stay
    the rows' own through the subsample of ``max_rows``."""
    stem, fabric, attrs = _attribute_world(seed)
    rows = np.arange(len(fabric))
    aux = ft.attribute_targets(attrs, fabric, rows)
    shuffled = aux[np.random.default_rng(9).permutation(len(aux))]
    kw = dict(epochs=20, max_rows=200, seed=seed, progress=False, lr=1e-2)
    err = {}
    for name, w, targets in (("off", 0.0, aux), ("on", 1.0, aux), ("shuffled", 1.0, shuffled)):
        tuned = ft.finetune_tail(_trunk(stem.shape[1], width=4), stem, fabric, 24, aux=targets, aux_weight=w, **kw)
        err[name] = _attribute_error(ft.features_from_stem(tuned, stem), aux)
    assert err["on"] < err["off"] - 0.08, err
    assert err["on"] < err["shuffled"] - 0.08, err


def test_train_refuses_an_attribute_weight_that_is_no_weight(tmp_path, capsys):
    from test_bundle_fixtures import tiny_world

    from vs2t_edge.cli import main
    from vs2t_edge.train.run import train

    for bad in ("-1", "nan", "inf"):
        assert main(["train", str(tiny_world()), "--profile", "tiny", "--out", str(tmp_path / "r"),
                     "--ft-attributes", bad]) == 2
        assert f"--ft-attributes {float(bad)}: a finite weight of 0 or more" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
    with pytest.raises(ValueError, match="ft_attributes -0.5"):
        train(tiny_world(), tmp_path / "r", "tiny", ft_attributes=-0.5)


def test_the_small_and_paper_profiles_train_with_the_attribute_task():
    """The profiles the demo and the paper world train with (chosen on both worlds' validation jobs,
    docs/training.md); the tiny test profile keeps the softmax alone."""
    from vs2t_edge.train.profile import PROFILES

    assert PROFILES["small"].ft_attributes == PROFILES["paper"].ft_attributes == 1.0
    assert PROFILES["tiny"].ft_attributes == 0.0

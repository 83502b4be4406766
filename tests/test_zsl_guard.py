"""Zero-shot is sacred: untouched fabrics' tactile data never reaches a training step.

The test poisons every tactile value of the untouched (and validation) fabrics with NaN. NaN
spreads through any arithmetic (BatchNorm statistics, Adam moments, means), so if any training
step — tactile tail fine-tuning, E/G/D/VS-F, CLS_u, CLS_t, the Gaussian — read one of those
values, a trained parameter would become NaN and the test fails.
"""

import numpy as np
import pytest
import torch

from vs2t_edge.train import compare as cmp
from vs2t_edge.train import features as ft
from vs2t_edge.train import vs2t
from vs2t_edge.train.trunks import build_trunk


def _world(n_fabrics=10, presses=20, seed=0):
    rng = np.random.default_rng(seed)
    fabric = np.repeat(np.arange(n_fabrics), presses)
    stem = rng.normal(size=(len(fabric), 32, 4, 4)).astype(np.float32) + fabric[:, None, None, None] * 0.1
    x_v = rng.normal(size=(len(fabric), 16)).astype(np.float32) + fabric[:, None]
    attrs = rng.integers(0, 2, size=(n_fabrics, 24)).astype(np.float64)
    return stem, x_v, fabric, [f"f{i:02d}" for i in range(n_fabrics)], attrs


def _finite(module) -> bool:
    return all(torch.isfinite(p).all() for p in module.parameters()) and \
        all(torch.isfinite(b).all() for b in module.buffers() if b.is_floating_point())


def test_no_untouched_tactile_value_reaches_training():
    stem, x_v, fabric, ids, attrs = _world()
    split = cmp.make_splits(ids, 1, 2, 2, seed=3)[0]
    unseen = [ids.index(f) for f in split.untouched + split.validation]
    poisoned = np.isin(fabric, unseen)
    stem[poisoned] = np.nan
    trunk = build_trunk("tiny")
    trunk.tail = torch.nn.Sequential(torch.nn.Conv2d(32, 64, 1), torch.nn.BatchNorm2d(64), torch.nn.ReLU())
    rows, y = ft.touched_training_rows(fabric, ids, split)
    assert not np.isin(fabric[rows], unseen).any()
    tuned = ft.finetune_tail(trunk, stem[rows], y, len(split.touched), epochs=1, progress=False)
    assert _finite(tuned), "tail fine-tuning read an untouched fabric's tactile data"
    x_t = ft.features_from_stem(tuned, stem)
    assert np.isnan(x_t[poisoned]).all() and np.isfinite(x_t[~poisoned]).all()
    table = cmp.FeatureTable(x_t, x_v, fabric, ids, attrs)
    views = cmp.split_views(table, split)
    assert np.isfinite(views.train.x_t).all() and np.isfinite(views.train.v_u).all()
    budget = vs2t.VS2TBudget(steps=20, cls_steps=10, n_synth_per_class=10, hidden=32, latent=8)
    m = vs2t.VS2TZSL().fit(views.train, budget, seed=0)
    for mod in (m.E, m.G, m.D, m.vsf, m.cls_u):
        assert _finite(mod), f"{type(mod).__name__} saw an untouched fabric's tactile data"
    assert np.isnan(views.test_presses[0]).all()  # the untouched tactile data exists only for testing


def test_fine_tuning_rows_refuse_a_fabric_outside_touched(monkeypatch):
    stem, x_v, fabric, ids, attrs = _world()
    split = cmp.make_splits(ids, 1, 2, 2, seed=3)[0]
    # a refactor that hands fine-tuning an untouched fabric's rows must fail loudly
    leaky = cmp.FabricSplit(touched=split.touched + [split.untouched[0]], validation=split.validation,
                            untouched=split.untouched, seed=split.seed)
    rows, _ = ft.touched_training_rows(fabric, ids, leaky)  # by itself it just follows the list ...
    assert np.isin(fabric[rows], [ids.index(split.untouched[0])]).any()
    # ... so the run builds fine-tuning rows from the split's touched list only, never another list
    from vs2t_edge.train import run

    seen = {}
    real = ft.finetune_tail

    def spy(trunk, stem_rows, y, n_classes, **kw):
        seen["n"] = n_classes
        seen["rows"] = len(stem_rows)
        raise RuntimeError("stop")

    monkeypatch.setattr(ft, "finetune_tail", spy)
    cache = ft.StemCache(stem.astype(np.float16), x_v, x_v, fabric, ids, attrs, {})
    with pytest.raises(RuntimeError, match="stop"):
        run.run_split(cache, build_trunk("tiny"), split, run.PROFILES["tiny"], vs2t.VS2TBudget())
    assert seen["n"] == len(split.touched)
    assert seen["rows"] == len(ft.touched_training_rows(fabric, ids, split)[0])
    del real

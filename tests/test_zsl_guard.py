"""Zero-shot is sacred: untouched fabrics' tactile data never reaches a training step.

The test poisons every tactile value of the untouched (and validation) fabrics with NaN. NaN
spreads through any arithmetic (BatchNorm statistics, Adam moments, means), so if any training
step — tactile tail fine-tuning, E/G/D/VS-F, CLS_u, CLS_t, the Gaussian — read one of those
values, a trained parameter would become NaN and the test fails. The visual tail, when it is
fine-tuned, may learn from touched training fabrics' camera crops only: the same poisoning of
the untouched and validation fabrics' crop activations must leave it finite.
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


def test_visual_fine_tuning_sees_touched_training_crops_only(monkeypatch):
    """`vs2t-edge train` with the visual tail fine-tuned (run.run_split, the real code path): every
    camera crop (visual stem activation) and tactile value of a validation or untouched fabric is
    NaN, and so are the crops of the touched fabrics' held-out (val/test) presses; both tails must
    come out finite, and the visual tail must have been trained on exactly the touched-train rows."""
    from vs2t_edge.train import run

    stem, x_v, fabric, ids, attrs = _world()
    split = cmp.make_splits(ids, 1, 2, 2, seed=3)[0]
    rows, _ = ft.touched_training_rows(fabric, ids, split)
    unseen = np.isin(fabric, [ids.index(f) for f in split.untouched + split.validation])
    held_out = ~np.isin(np.arange(len(fabric)), rows)  # unseen fabrics + touched val/test presses
    assert unseen[held_out].sum() == unseen.sum() and (held_out & ~unseen).any()
    stem_v = np.random.default_rng(1).normal(size=(len(fabric), 32, 4, 4)).astype(np.float16)
    stem_v[held_out] = np.nan
    stem_t = stem.astype(np.float16)
    stem_t[unseen] = np.nan
    cache = ft.StemCache(stem_t, x_v, x_v, fabric, ids, attrs, {}, stem_v)

    tuned, real = {}, ft.finetune_tail

    def spy(trunk, stem_rows, y, n_classes, **kw):
        what = kw.get("what", "tactile")
        assert np.isfinite(np.asarray(stem_rows, dtype=np.float32)).all(), f"{what} fine-tuning got a held-out row"
        assert n_classes == len(split.touched) and len(stem_rows) == len(rows)
        tuned[what] = real(trunk, stem_rows, y, n_classes, **{**kw, "progress": False})
        if what == "visual":
            raise RuntimeError("stop")  # the generative part is covered by the test above
        return tuned[what]

    monkeypatch.setattr(ft, "finetune_tail", spy)
    prof = run.PROFILES["tiny"]
    prof = type(prof)(**{**prof.__dict__, "visual_tail": "finetuned", "ft_epochs": 1})
    trunk = build_trunk("tiny")
    trunk.stem = torch.nn.Identity()  # the cached activations are the stem's output
    with pytest.raises(RuntimeError, match="stop"):
        run.run_split(cache, trunk, split, prof, vs2t.VS2TBudget())
    assert set(tuned) == {"tactile", "visual"}
    for what, t in tuned.items():
        assert _finite(t), f"{what} tail fine-tuning read a held-out crop or frame"
    # and the poison is really there: the tuned visual tail turns an unseen fabric's crop into NaN
    x = ft.features_from_stem(tuned["visual"], stem_v)
    assert np.isnan(x[unseen]).all() and np.isfinite(x[~held_out]).all()


def test_visual_fine_tuning_guard_catches_a_leak():
    """The check above is not vacuous: handing the visual tail every crop poisons it."""
    stem, x_v, fabric, ids, attrs = _world()
    split = cmp.make_splits(ids, 1, 2, 2, seed=3)[0]
    unseen = np.isin(fabric, [ids.index(f) for f in split.untouched + split.validation])
    stem_v = np.random.default_rng(1).normal(size=(len(fabric), 32, 4, 4)).astype(np.float32)
    stem_v[unseen] = np.nan
    trunk = build_trunk("tiny")
    y = np.arange(len(fabric)) % len(split.touched)
    leaky = ft.finetune_tail(trunk, stem_v, y, len(split.touched), epochs=1, progress=False, what="visual")
    assert not _finite(leaky)

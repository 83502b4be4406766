"""Zero-shot is sacred: untouched fabrics' tactile data never reaches a training step.

The test poisons every tactile value of the untouched (and validation) fabrics with NaN. NaN
spreads through any arithmetic (BatchNorm statistics, Adam moments, means), so if any training
step — tactile tail fine-tuning, E/G/D/VS-F, CLS_u, CLS_t, the Gaussian — read one of those
values, a trained parameter would become NaN and the test fails. The visual tail, when it is
fine-tuned, may learn from touched training fabrics' camera crops only: the same poisoning of
the untouched and validation fabrics' crop activations must leave it finite.

End to end, ``run.run_split`` (with the deployed artefacts) and ``compare.run_split`` run twice,
clean and with every input of the untouched fabrics poisoned (frames, crops, features, attributes):
every touched- and validation-side artefact must be bit-identical, only untouched test outputs move.
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


def test_a_split_calling_an_untouched_fabric_touched_is_refused_before_fine_tuning(monkeypatch):
    """Fine-tuning rows follow the split's touched list; a split (a refactor, a hand-edited
    metrics.json) that also lists an untouched or validation fabric as touched is refused with
    ZeroShotViolation by ``touched_training_rows`` — before `vs2t-edge train` fine-tunes anything."""
    from vs2t_edge.train import run

    stem, x_v, fabric, ids, attrs = _world()
    split = cmp.make_splits(ids, 1, 2, 2, seed=3)[0]

    def spy(*a, **kw):
        raise AssertionError("fine-tuning ran on a leaky split")

    monkeypatch.setattr(ft, "finetune_tail", spy)
    cache = ft.StemCache(stem.astype(np.float16), x_v, x_v, fabric, ids, attrs, {})
    for other in (split.untouched[0], split.validation[0]):
        leaky = cmp.FabricSplit(touched=split.touched + [other], validation=split.validation,
                                untouched=split.untouched, seed=split.seed)
        with pytest.raises(ft.ZeroShotViolation, match=other):
            ft.touched_training_rows(fabric, ids, leaky)
        with pytest.raises(ft.ZeroShotViolation):
            run.run_split(cache, build_trunk("tiny"), leaky, run.PROFILES["tiny"], vs2t.VS2TBudget())


def test_run_fine_tunes_on_the_splits_touched_training_rows_only(monkeypatch):
    """run.run_split hands the tactile tail exactly the split's touched-train rows (count and classes)."""
    from vs2t_edge.train import run

    stem, x_v, fabric, ids, attrs = _world()
    split = cmp.make_splits(ids, 1, 2, 2, seed=3)[0]
    seen = {}

    def spy(trunk, stem_rows, y, n_classes, **kw):
        seen["n"] = n_classes
        seen["rows"] = np.asarray(stem_rows, dtype=np.float32)
        raise RuntimeError("stop")

    monkeypatch.setattr(ft, "finetune_tail", spy)
    cache = ft.StemCache(stem.astype(np.float16), x_v, x_v, fabric, ids, attrs, {})
    with pytest.raises(RuntimeError, match="stop"):
        run.run_split(cache, build_trunk("tiny"), split, run.PROFILES["tiny"], vs2t.VS2TBudget())
    rows, _ = ft.touched_training_rows(fabric, ids, split)
    assert seen["n"] == len(split.touched)
    assert np.array_equal(seen["rows"], stem[rows].astype(np.float16).astype(np.float32))
    assert set(fabric[rows]) == {ids.index(f) for f in split.touched}


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


# --------------------------------------------------------------------------------------------
# end to end: run.run_split and compare.run_split, clean vs every untouched input poisoned
# --------------------------------------------------------------------------------------------

# What may differ between the clean and the poisoned run: numbers measured on the untouched
# (test) fabrics' presses, and timings. Everything else is touched- or validation-side.
TEST_SIDE_KEYS = {"zsl_acc", "acc_u", "H", "ausuc", "auroc", "wasserstein", "cosine"}
TIMING_KEYS = {"seconds", "finetune_s", "finetune_visual_s"}
# calibrated stacking scores touched test presses with CLS_u of the untouched classes too, so its
# touched-test GZSL accuracy is a test-side number; every other router's acc_t reads CLS_t only
READS_CLS_U = {"calibrated_stacking"}


def _poisonable_world(poison: bool):
    """The tiny stem world with, when ``poison``, every input of the untouched (test) fabrics
    replaced: tactile frames (stem activations and frozen tactile features), camera crops (visual
    stem and frozen visual features) by large finite noise — the routers refuse NaN when they score
    a press, and bit-identity with the clean run below catches any leak a NaN would — and their
    attribute rows flipped (CLS_u legitimately reads them)."""
    stem, x_v, fabric, ids, attrs = _world()
    rng = np.random.default_rng(7)
    stem_v = rng.normal(size=stem.shape).astype(np.float32)
    x_t0 = rng.normal(size=(len(fabric), 16)).astype(np.float32)
    split = cmp.make_splits(ids, 1, 2, 2, seed=3)[0]
    if poison:
        bad = np.isin(fabric, [ids.index(f) for f in split.untouched])
        noise = np.random.default_rng(99)
        for a in (stem, stem_v, x_v, x_t0):
            a[bad] = (50 * noise.normal(size=a[bad].shape) + 20).astype(np.float32)
        u = [ids.index(f) for f in split.untouched]
        attrs[u] = 1 - attrs[u]
    cache = ft.StemCache(stem.astype(np.float16), x_v, x_t0, fabric, ids, attrs, {}, stem_v.astype(np.float16))
    return cache, split


def _differing_leaves(a, b, path=()):
    if isinstance(a, dict):
        assert set(a) == set(b), path
        return [p for k in a for p in _differing_leaves(a[k], b[k], path + (k,))]
    if isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        return [p for i, (x, y) in enumerate(zip(a, b)) for p in _differing_leaves(x, y, path + (i,))]
    same = a == b or (isinstance(a, float) and np.isnan(a) and isinstance(b, float) and np.isnan(b))
    return [] if same else [path]


def _per_item(path: tuple) -> bool:
    """compare's per item by bins: scenes of test fabrics, untouched pieces included, scored with
    the untouched classes' CLS_u (touched pieces too): all test side."""
    return any(isinstance(k, str) and k.startswith("item_") for k in path)


def _only_test_side_changed(clean: dict, poisoned: dict) -> list:
    # the scene decision's test scenes are made of the untouched fabrics' presses: all test side,
    # structure included (the risk-coverage curve has one point per distinct confidence)
    clean, poisoned = dict(clean), dict(poisoned)
    scene_test = []
    if "scene_decision" in clean:
        a, b = dict(clean["scene_decision"]), dict(poisoned["scene_decision"])
        if a.pop("test") != b.pop("test"):
            scene_test = [("scene_decision", "test")]
        clean["scene_decision"], poisoned["scene_decision"] = a, b
    diff = _differing_leaves(clean, poisoned)
    touched = [p for p in diff if p[-1] not in TEST_SIDE_KEYS | TIMING_KEYS
               and not (p[-1] == "acc_t" and len(p) >= 2 and p[-2] in READS_CLS_U) and not _per_item(p)]
    assert not touched, f"a touched- or validation-side number moved when only untouched inputs changed: {touched}"
    test_side = [p for p in diff if p[-1] in TEST_SIDE_KEYS] + scene_test
    assert test_side, "the poison did not reach the untouched test outputs (the check would be vacuous)"
    return test_side


def _plain(o):
    """Arrays as nested lists, so ``_differing_leaves`` compares them element by element."""
    if isinstance(o, dict):
        return {k: _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    return np.asarray(o).tolist() if isinstance(o, np.ndarray) else o


def _state(module) -> dict:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def _same_state(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _method_states(m) -> dict:
    """Every trained module of a fitted method (after ``retarget`` to the validation fabrics, as
    compare.run_split leaves it), and its CLS_u per class set."""
    out = {k: _state(v) for k, v in vars(m).items() if isinstance(v, torch.nn.Module)}
    for classes, clf in getattr(m, "cls_u_by_classes", {}).items():
        out[("cls_u",) + classes] = _state(clf)
    return out


@pytest.mark.parametrize("visual_tail,ft_attributes", [("frozen", 0.0), ("finetuned", 0.0), ("frozen", 1.0)])
def test_training_run_split_is_blind_to_every_untouched_input(visual_tail, ft_attributes):
    """`vs2t-edge train`'s own split runner (run.run_split: tail fine-tuning, every VS2T variant and
    ablation, CLS_t, every router and its validation beta) and the deployed artefacts, run twice:
    once clean, once with the untouched fabrics' frames, crops, features and attributes poisoned.
    Every touched-side artefact must be bit-identical; only untouched test outputs may move. With
    the tactile tail's attribute task on (``ft_attributes``) the flipped untouched attributes must
    not reach it either (its targets are standardised over the touched fabrics alone)."""
    from vs2t_edge.train import run

    prof = run.PROFILES["tiny"]
    prof = type(prof)(**{**prof.__dict__, "visual_tail": visual_tail, "ft_epochs": 1, "ft_attributes": ft_attributes})
    budget = vs2t.VS2TBudget(steps=15, cls_steps=10, n_synth_per_class=10, hidden=32, latent=8)
    outs = {}
    for poison in (False, True):
        cache, split = _poisonable_world(poison)
        torch.manual_seed(0)  # the tiny trunk's random init, as `vs2t-edge train` seeds it
        trunk = build_trunk("tiny")
        trunk.stem = torch.nn.Identity()  # the cached activations are the stem's output
        o = run.run_split(cache, trunk, split, prof, budget)
        arts = {r: run._deploy_artifacts("world", prof, split, o, budget, r) for r in prof.routers}
        outs[poison] = (o, arts, split)
    (clean, arts_c, split), (pois, arts_p, _) = outs[False], outs[True]
    changed = _only_test_side_changed(clean["result"], pois["result"])
    assert any(p[:2] == ("methods", "VS2T-ZSL") for p in changed)
    # the trained parts: tactile tail, every variant's E / G / D / VS-F and its validation CLS_u
    assert _same_state(_state(clean["trunk"]), _state(pois["trunk"]))
    assert set(clean["fitted"]) == set(vs2t.VARIANTS)
    for name, m in clean["fitted"].items():
        a, b = _method_states(m), _method_states(pois["fitted"][name])
        u = ("cls_u",) + tuple(split.untouched)
        for k in a:
            if k in (u, "cls_u"):  # run.run_split points cls_u at the untouched CLS_u afterwards
                assert not _same_state(a[k], b[k]), (name, k)  # the untouched CLS_u did read the poison
            else:
                assert _same_state(a[k], b[k]), f"{name}: {k} changed with untouched inputs only"
    # the deployed bundle: all but the untouched CLS_u identical, for every router it can ship
    for r in prof.routers:
        ac, ap = arts_c[r], arts_p[r]
        assert _same_state(ac.trunk_state, ap.trunk_state) and _same_state(ac.cls_t_state, ap.cls_t_state)
        assert np.array_equal(ac.feature_mean, ap.feature_mean) and np.array_equal(ac.feature_std, ap.feature_std)
        assert not _differing_leaves(_plain(ac.router_params), _plain(ap.router_params)) and ac.beta == ap.beta, r
        assert (ac.touched, ac.validation, ac.untouched) == (ap.touched, ap.validation, ap.untouched)
        assert not _same_state(ac.cls_u_state, ap.cls_u_state)
        # the scene decision (train/decision.py): subspace, whitening, touched means and every
        # scalar chosen on validation are blind to the untouched fabrics; only their synthesised
        # means (from their camera crops and attributes, poisoned here) move
        sc, sp = ac.scene_model, ap.scene_model
        n_t = len(ac.touched)
        for key in set(sc) - {"means"}:
            assert np.array_equal(np.asarray(sc[key]), np.asarray(sp[key])), f"scene model '{key}' read untouched data"
        assert np.array_equal(sc["means"][:n_t], sp["means"][:n_t])
        assert not np.array_equal(sc["means"][n_t:], sp["means"][n_t:])
    assert any(p[:2] == ("scene_decision", "test") for p in changed)  # the test scenes did read them


def test_compare_run_split_is_blind_to_every_untouched_input():
    """The comparison's split runner (compare.run_split, every row of compare.all_methods: DAP,
    VT-FC-ZSL, Abderrahmane, Lee, f-CLSWGAN, CADA-VAE, f-VAEGAN, VS2T-ZSL), clean vs untouched
    tactile features, visual features and attributes poisoned: CLS_t, each method's trained
    weights (left retargeted to the validation fabrics), every router's beta and validation
    numbers are bit-identical; only the untouched test outputs move."""
    from vs2t_edge.train.baselines import Budget

    budget = Budget(steps=12, batch=16, hidden=32, latent=4, cls_steps=8, n_synth_per_class=8)
    made, results = {}, {}
    for poison in (False, True):
        cache, split = _poisonable_world(poison)
        table = cmp.FeatureTable(cache.x_t0, cache.x_v, cache.fabric, cache.fabric_ids, cache.attributes)
        fitted = {}

        def recording(name, cls, fitted=fitted):
            def fit(self, *a, **k):
                fitted[name] = self
                return cls.fit(self, *a, **k)
            return type(cls.__name__, (cls,), {"fit": fit})

        methods = {n: recording(n, c) for n, c in cmp.all_methods().items()}
        results[poison] = cmp.run_split(table, split, methods, budget, log=lambda *_: None)
        made[poison] = fitted
    changed = _only_test_side_changed(results[False], results[True])
    assert {p[1] for p in changed if p[0] == "methods"} == set(made[False])  # every row read its poison
    for name, m in made[False].items():
        a, b = _method_states(m), _method_states(made[True][name])
        assert a, name
        u = ("cls_u",) + tuple(split.untouched)
        for k in a:
            if k != u:
                assert _same_state(a[k], b[k]), f"{name}: {k} changed with untouched inputs only"


def test_descriptor_feature_run_is_blind_to_untouched_descriptors():
    """`train --tactile-feature shading_markers`: the tactile feature is a fixed descriptor of every
    press (runtime/tactile_descriptor.py, nothing fitted), nothing is fine-tuned, and the only
    statistic of it - the standardisation - comes from touched training rows. Clean vs the untouched
    fabrics' descriptors, crops and attributes poisoned: every touched-side artefact is
    bit-identical, the deployed feature standardisation included; only untouched test outputs move."""
    from vs2t_edge.train import run

    prof = run.PROFILES["tiny"]
    prof = type(prof)(**{**prof.__dict__, "tactile_feature": "shading_markers", "ft_epochs": 1})
    budget = vs2t.VS2TBudget(steps=15, cls_steps=10, n_synth_per_class=10, hidden=32, latent=8)
    outs = {}
    for poison in (False, True):
        cache, split = _poisonable_world(poison)
        desc = np.random.default_rng(5).normal(size=(len(cache.fabric), 240)).astype(np.float32)
        desc += cache.fabric[:, None] * 0.3
        if poison:
            bad = np.isin(cache.fabric, [cache.fabric_ids.index(f) for f in split.untouched])
            desc[bad] = 50 * np.random.default_rng(98).normal(size=desc[bad].shape) + 20
        torch.manual_seed(0)
        trunk = build_trunk("tiny")
        trunk.stem = torch.nn.Identity()
        o = run.run_split(cache, trunk, split, prof, budget, desc)
        outs[poison] = (o, run._deploy_artifacts("world", prof, split, o, budget, "gaussian"), desc)
    (clean, ac, desc), (pois, ap, _) = outs[False], outs[True]
    assert clean["trunk"] is None and ac.trunk_state == {} and ac.tactile_feature == "shading_markers"
    assert ac.feature_dim == 240 and np.array_equal(clean["table"].x_t, desc)  # the descriptor, not the trunk
    changed = _only_test_side_changed(clean["result"], pois["result"])
    assert any(p[:2] == ("methods", "VS2T-ZSL") for p in changed)
    assert np.array_equal(ac.feature_mean, ap.feature_mean) and np.array_equal(ac.feature_std, ap.feature_std)
    assert _same_state(ac.cls_t_state, ap.cls_t_state) and ac.beta == ap.beta
    assert not _differing_leaves(_plain(ac.router_params), _plain(ap.router_params))
    assert not _same_state(ac.cls_u_state, ap.cls_u_state)  # CLS_u does read the untouched attributes


def test_descriptor_feature_needs_its_descriptors():
    from vs2t_edge.train import run

    cache, split = _poisonable_world(False)
    prof = run.PROFILES["tiny"]
    prof = type(prof)(**{**prof.__dict__, "tactile_feature": "shading_markers"})
    with pytest.raises(ValueError, match="needs its descriptor"):
        run.run_split(cache, build_trunk("tiny"), split, prof, vs2t.VS2TBudget(steps=1), None)

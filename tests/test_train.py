"""VS2T-ZSL training: trunks, reproducibility, a trained generator beats an untrained one (toy
features, the tiny fabric world, and the small profile (marked slow), and `vs2t-edge train`
end to end on the tiny fabric world (run folder, artefacts round trip). Progress lines:
tests/test_train_progress.py."""

import json
import time
from dataclasses import replace

import numpy as np
import pytest
import torch

from vs2t_edge.train import compare as cmp, compare_sources as sources, splits as fabric_splits
from vs2t_edge.train import vs2t
from vs2t_edge.train.run import wasserstein_mean_1d
from vs2t_edge.train.trunks import ResNet50, build_trunk, resnet50_state_for_torchvision


def _views(seed=0):
    table = sources.toy_feature_table(n_fabrics=16, presses=30, d_t=48, d_v=24, seed=seed)
    split = cmp.make_splits(table.fabric_ids, 1, 3, 3, seed=seed)[0]
    return cmp.split_views(table, split)


BUDGET = vs2t.VS2TBudget(steps=250, cls_steps=150, n_synth_per_class=60, hidden=128, latent=16)


def _zsl(m, views):
    x, v, y = views.test_presses
    return float(np.mean(m.untouched_logits(x, v).argmax(1) == y))


def test_seeded_training_is_reproducible():
    views = _views()
    a = vs2t.VS2TZSL().fit(views.train, BUDGET, seed=5, steps=30)
    b = vs2t.VS2TZSL().fit(views.train, BUDGET, seed=5, steps=30)
    for pa, pb in zip(list(a.G.parameters()) + list(a.cls_u.parameters()),
                      list(b.G.parameters()) + list(b.cls_u.parameters())):
        assert torch.equal(pa, pb)
    c = vs2t.VS2TZSL().fit(views.train, BUDGET, seed=6, steps=30)
    assert not torch.equal(next(a.G.parameters()), next(c.G.parameters()))


def test_ensemble_pools_its_members_samples_deterministically():
    """``ensemble`` 3: n_synth_per_class samples per class from each of 3 generators, member 0 the
    single generator of the same seed, the others different; the same seed gives the same pool
    and the same CLS_u."""
    views = _views()
    one = replace(BUDGET, n_synth_per_class=20)
    three = replace(one, ensemble=3)
    single = vs2t.VS2TZSL().fit(views.train, one, seed=5, steps=30)
    a = vs2t.VS2TZSL().fit(views.train, three, seed=5, steps=30)
    b = vs2t.VS2TZSL().fit(views.train, three, seed=5, steps=30)
    xa, ya = a.synthesise(views.train, three, 5)
    xb, yb = b.synthesise(views.train, three, 5)
    n_u, block = views.train.n_u, views.train.n_u * 20
    assert xa.shape == (3 * block, views.train.d_t) and np.bincount(ya).tolist() == [60] * n_u
    assert np.array_equal(xa, xb) and np.array_equal(ya, yb)
    assert all(torch.equal(p, q) for p, q in zip(a.cls_u.parameters(), b.cls_u.parameters()))
    x1, y1 = single.synthesise(views.train, one, 5)
    assert np.array_equal(xa[:block], x1) and np.array_equal(ya[:block], y1)
    assert not np.allclose(xa[:block], xa[block:2 * block]) and not np.allclose(xa[block:2 * block], xa[2 * block:])
    assert len(a.members) == 3 and a.members[1] not in type(a).instances
    with pytest.raises(ValueError, match="ensemble"):
        vs2t.VS2TZSL().fit(views.train, replace(one, ensemble=0), seed=5, steps=1)


def test_trained_generator_beats_untrained():
    views = _views()
    trained = vs2t.VS2TZSL().fit(views.train, BUDGET, seed=0)
    untrained = vs2t.VS2TZSL().fit(views.train, BUDGET, seed=0, steps=0)
    xr, _, yr = views.test_presses

    def w1(m):
        xs, ys = m.synthesise(views.train, BUDGET, 0)
        return np.mean([wasserstein_mean_1d(xr[yr == k], xs[ys == k]) for k in np.unique(yr)])

    assert w1(trained) < w1(untrained)
    assert _zsl(trained, views) > _zsl(untrained, views) + 0.1
    assert _zsl(trained, views) > 1.5 / views.train.n_u  # well above chance


def test_ablation_variants_build_the_right_parts():
    views = _views()
    for name, cls in vs2t.all_variants().items():
        m = cls().fit(views.train, BUDGET, seed=0, steps=3)
        assert (m.E is None) == (not vs2t.VARIANTS[name].use_e)
        assert (m.vsf is None) == (not vs2t.VARIANTS[name].use_vsf)
        d_c = {"vs": views.train.d_v + 24, "v": views.train.d_v, "s": 24}[vs2t.VARIANTS[name].modality]
        assert m.G.net[0].in_features == BUDGET.latent + d_c


@pytest.mark.parametrize("arch,dim", [("tiny", 64), ("efficientnet_lite0", 1280), ("resnet50", 2048)])
def test_trunks_shapes_and_stem_tail_split(arch, dim):
    t = build_trunk(arch, pretrained=(arch == "efficientnet_lite0")).eval()
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        f = t(x)
        assert f.shape == (2, dim) and t.feature_dim == dim
        assert torch.allclose(f, t.features_from_stem(t.stem(x)), atol=1e-5)


def test_resnet50_loads_a_torchvision_named_state_dict(tmp_path):
    src = ResNet50()
    state = {k: v for k, v in src.state_dict().items()}
    state["fc.weight"], state["fc.bias"] = torch.zeros(1000, 2048), torch.zeros(1000)  # torchvision has fc
    torch.save(state, tmp_path / "r50.pth")
    t = build_trunk("resnet50", weights_path=tmp_path / "r50.pth")
    got = resnet50_state_for_torchvision(t)
    assert torch.equal(got["layer4.2.conv3.weight"], state["layer4.2.conv3.weight"])
    torch.save({"conv1.weight": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(Exception):
        build_trunk("resnet50", weights_path=tmp_path / "bad.pth")


@pytest.fixture(scope="module")
def tiny_world():
    """The tiny synthetic fabric world (10 fabrics x 9 presses): the one test_bundle_fixtures
    generates once per test session for the bundle and export tests (same profile, same seed);
    tests only read it."""
    from test_bundle_fixtures import tiny_world as shared_tiny_world

    return shared_tiny_world()


def _generator_vs_untrained(dataset, profile: str, split_seeds) -> list[dict]:
    """Per split: the full VS2T-ZSL trained with the profile's budget, and the same model with 0
    generator steps (random E/G/D/VS-F; CLS_u still fitted on its output), on the fabric world's
    features as `vs2t-edge train` makes them (trunk seeded like the run, frozen stem, tactile tail
    fine-tuned on the split's touched-train presses) but for the tail's attribute task, left out
    (softmax alone, as every run before 2026-11-30): this measures the generator, and its thresholds
    were measured on that tail. Metrics (standardised units):
    ``seen_*``: synthesised from the crops and attributes of touched fabrics' HELD-OUT presses,
    against their real features — does G learn the world's tactile distribution; ``unseen_*``:
    untouched (test) fabrics, against their real features — does it transfer (zero-shot);
    ``w1``: per-class mean 1-D Wasserstein (``run.synth_quality``'s estimator); ``cos``: cosine of
    real vs synthesised class means; ``zsl``: CLS_u accuracy on the untouched presses."""
    from vs2t_edge.train.run import PROFILES

    prof = PROFILES[profile]
    budget = vs2t.VS2TBudget(steps=prof.steps, batch=prof.batch, cls_steps=prof.cls_steps,
                             n_synth_per_class=prof.n_synth_per_class, lr_scale=prof.lr_scale, latent=prof.latent,
                             hidden=prof.hidden)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as `vs2t-edge train` runs: 2 threads on the 2 shared cores were ~2x slower
    try:
        return _compare_generators(dataset, prof, budget, split_seeds)
    finally:
        torch.set_num_threads(threads)


def _compare_generators(dataset, prof, budget, split_seeds) -> list[dict]:
    from vs2t_edge.train import features as ft
    from vs2t_edge.train.baselines import ZSLData
    from vs2t_edge.train.run import n_holdout, synth_quality

    torch.manual_seed(prof.seed)
    trunk = build_trunk(prof.trunk, pretrained=True)
    cache = ft.extract_cache(dataset, trunk, prof.size_px, prof.max_presses, progress=False)
    k = n_holdout(len(cache.fabric_ids))
    out = []
    for seed in split_seeds:
        split = cmp.make_splits(cache.fabric_ids, 1, k, k, seed=seed)[0]
        rows, y = ft.touched_training_rows(cache.fabric, cache.fabric_ids, split)
        tuned = ft.finetune_tail(trunk, cache.stem_t[rows], y, len(split.touched), epochs=prof.ft_epochs,
                                 max_rows=prof.ft_max_rows, seed=split.seed, progress=False)
        table = cmp.FeatureTable(ft.features_from_stem(tuned, cache.stem_t), cache.x_v, cache.fabric,
                                 cache.fabric_ids, cache.attributes)
        views = cmp.split_views(table, split)
        x_s, v_s, y_s = views.touched_test
        seen = cmp.SplitViews(**{**views.__dict__, "test_presses": (x_s, v_s, y_s),
                                 "train": ZSLData(**{**views.train.__dict__, "attr_u": views.train.attr_t, "v_u": v_s,
                                                     "v_u_class": y_s, "names_u": views.train.names_t})})
        row = {}
        for name, steps in (("trained", None), ("untrained", 0)):
            m = vs2t.VS2TZSL().fit(views.train, budget, seed=split.seed, steps=steps)
            q_seen = synth_quality(m, seen, budget, split.seed)
            q_unseen = synth_quality(m, views, budget, split.seed)
            row[name] = {"seen_w1": q_seen["wasserstein"], "seen_cos": q_seen["cosine"],
                         "unseen_w1": q_unseen["wasserstein"], "unseen_cos": q_unseen["cosine"],
                         "zsl": _zsl(m, views)}
        out.append(row)
    return out


def test_trained_generator_beats_untrained_on_the_tiny_fabric_world(tiny_world):
    """On the tiny world (6 touched fabrics, a random-weight tiny trunk) the trained generator
    reproduces touched fabrics' held-out presses far better than an untrained one: measured over
    3 worlds x 4 splits, W1 0.22-0.46 vs 0.60-0.85 and class-mean cosine 0.76-0.95 vs -0.09-0.09,
    every time. What it does NOT show is zero-shot transfer: on the 2 untouched fabrics W1, cosine
    and ZSL did not separate trained from untrained (trained better in 5, 6 and 7 of those 12) —
    the small-profile test below is the zero-shot claim. ~10 s after the world is built."""
    for r in _generator_vs_untrained(tiny_world, "tiny", (0, 1, 2)):
        t, u = r["trained"], r["untrained"]
        assert t["seen_w1"] < 0.75 * u["seen_w1"], r
        assert t["seen_cos"] > u["seen_cos"] + 0.4, r


@pytest.mark.slow
def test_trained_generator_beats_untrained_on_the_small_profile(tmp_path):
    """Issue 3's claim on the small profile (20 fabrics, split 0 = the run's 14/3/3, EfficientNet-
    Lite0 at 128 px). Measured on 6 splits before writing this: the class means the trained
    generator synthesises for UNTOUCHED fabrics point more towards the real ones than an untrained
    generator's (cosine, trained higher in all 6; split 0: 0.22 vs -0.02) and it reproduces
    touched held-out presses better (W1 0.34-0.45 vs 0.45-0.58, cosine 0.61-0.76 vs ~0). Not
    asserted, because they did not separate: untouched ZSL (3 classes; trained higher in 3 of 6
    splits on test, 5 of 6 on validation, one tie) and untouched W1, which was LOWER for the
    untrained generator in every split — its output is nearly constant near the touched mean, the
    trained class means are no closer to the real ones (split 0: rms error 1.16 vs 1.15), and the
    trained spread only adds W1 (docs/training.md). ~1-2 min (world 30 s, features 15 s, one split);
    it runs in CI, since the issue's "done when" names this profile; `-m "not slow"` leaves it out."""
    from vs2t_edge.sim.synth import generate

    data = generate(tmp_path / "small", "small", 0, progress=False, workers=1)
    (r,) = _generator_vs_untrained(data, "small", (0,))
    t, u = r["trained"], r["untrained"]
    assert t["unseen_cos"] > u["unseen_cos"] + 0.1, r
    assert t["seen_w1"] < u["seen_w1"] and t["seen_cos"] > u["seen_cos"] + 0.4, r


def test_tiny_profile_end_to_end(tmp_path, tiny_world, capsys):
    from vs2t_edge.train.artifacts import build_modules, load_router, load_run_artifacts
    from vs2t_edge.train.cli import add_arguments, run
    import argparse

    data = tiny_world
    out = tmp_path / "run"
    p = argparse.ArgumentParser()
    add_arguments(p, "train")
    t0 = time.time()
    assert run(p.parse_args([str(data), "--profile", "tiny", "--out", str(out)])) == 0
    assert time.time() - t0 < 60
    # its words are explained, in the printout and in the report (a new user met "w/o E, VS-F",
    # "AUSUC", "beta" with no word of what they are)
    from vs2t_edge.train.report import LEGEND

    said = capsys.readouterr().out
    assert "How to read these numbers:" in said and "How to read these numbers:" in (out / "report.md").read_text()
    for term, meaning in LEGEND:
        assert f"  {term}: {meaning}" in said and f"- {term}: {meaning}" in (out / "report.md").read_text()
    assert all(t in said for t in ("ZSL:", "AUSUC:", "w/o E, w/o VS-F, w/o E, VS-F:", "router, beta:"))
    for f in ("config.yaml", "metrics.json", "report.md", "artifacts/model.pt", "features/feature_table.npz",
              "figures/confusion.png", "figures/pca_real_vs_synth.png", "figures/class_cosine.png",
              "figures/threshold_curve.png"):
        assert (out / f).is_file(), f
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["summary"]) == set(vs2t.VARIANTS)
    # the summary is the splits' numbers, and the report prints exactly the summary
    (split,) = m["splits"]
    report = (out / "report.md").read_text()
    for name, r in m["summary"].items():
        assert r["zsl"]["mean"] == pytest.approx(100 * split["methods"][name]["zsl_acc"]), name
        g = split["methods"][name]["routers"]["gaussian"]
        assert r["H"]["mean"] == pytest.approx(100 * g["H"]), name
        paper = f"{vs2t.PAPER[name]:.2f}"
        row = (f"| {name} | {r['zsl']['mean']:.1f} ± {r['zsl']['std']:.1f} | {r['val_zsl']['mean']:.1f} | {paper} | "
               f"{r['acc_t']['mean']:.1f} | {r['acc_u']['mean']:.1f} | {r['H']['mean']:.1f} |")
        assert row in report, (row, report)
    chosen = m["router"]["chosen"]
    v = m["summary"]["VS2T-ZSL"]["routers"][chosen]
    assert f"| {chosen} | {v['val_ausuc']['mean']:.1f} | {v['ausuc']['mean']:.1f} |" in report
    # the scene decision: per item by bins on test scenes, every item in exactly one outcome, and
    # the same one-softmax model's per-press GZSL beside it; the report prints those numbers
    sd = split["scene_decision"]["test"]
    for kind in ("touched", "untouched", "off-scene"):
        r = sd["by_kind"][kind]
        assert r["n"] > 0 and r["right"] + r["mis-sort"] + r["reject"] == pytest.approx(1.0), kind
    g = sd["press_gzsl"]
    assert 0 <= g["acc_t"] <= 1 and 0 <= g["acc_u"] <= 1
    assert g["H"] == pytest.approx(2 * g["acc_t"] * g["acc_u"] / (g["acc_t"] + g["acc_u"]) if g["acc_t"] + g["acc_u"] else 0)
    a = sd["all"]
    refused = sd["off_scene_rule"]
    # one split: its values, no spread (train/report.py ``_ms``)
    assert f"| all | {100 * a['right']:.1f} | {100 * a['mis-sort']:.1f} | {100 * a['reject']:.1f} | " \
           f"{100 * refused['all']:.1f} |" in report
    # the off-scene rules' share of a kind is inside what the kind's pieces have in the reject bin
    for kind in ("touched", "untouched"):
        assert 0 <= refused["by_kind"][kind] <= sd["by_kind"][kind]["reject"] + 1e-12, kind
    assert refused["by_kind"]["off-scene"] <= sd["by_kind"]["off-scene"]["right"] + 1e-12
    assert f"H {100 * g['H']:.1f} (paper: H 84.27)" in report
    # the job check (runtime/job_check.py) is scored on every job fabric of every test job
    jc = sd["job_check"]
    n_fabrics = sum(g["fabrics"] for kind in jc.values() for g in kind.values())
    assert n_fabrics == sd["n_scenes"] * (5 + 2)  # jobs of 5 touched + the tiny split's 2 untouched fabrics
    assert "Job check (runtime/job_check.py: before each job" in report
    if "operator_labels" in sd:  # an offset-rule model also prices teaching only what the check flags
        assert "With labels and a teach piece only of the untouched fabrics the job check flags" in report
    # each mis-sort target a whole operating point chosen on validation, priced on the same test jobs;
    # the run's own (1 %) is the operating point's row
    targets = [r for r in sd["knobs"] if r["knob"] == "mis_sort_target"]
    assert [r["value"] for r in targets] == [0.5, 1.0, 2.0] and [r["own"] for r in targets] == [False, True, False]
    outcomes = ("right", "mis-sort", "reject")
    assert {k: targets[1][k] for k in outcomes} == {k: sd["knobs"][0][k] for k in outcomes}
    assert "| mis-sort target, % (`train --mis-sort-target`" in report and "| 1 (own) |" in report
    # extra presses: chosen on validation jobs (one row per number tried, the choice flagged), the
    # operating point's own row on the test jobs the knob table's
    chosen_extra = split["scene_decision"]["validation"]["chosen"]["extra_presses"]
    val_extra = split["scene_decision"]["validation"]["extra_presses"]
    assert [r["extra_presses"] for r in val_extra] == [0, 2, 4, 8]
    assert [r["extra_presses"] for r in val_extra if r["chosen"]] == [chosen_extra]
    extra = [r for r in sd["knobs"] if r["knob"] == "extra_presses"]
    assert [r["value"] for r in extra] == [0, 2, 4, 8]
    assert [r["value"] for r in extra if r["own"]] == [chosen_extra]
    presses = [r["presses"] for r in extra]
    assert presses == sorted(presses)  # more extra presses only ever add presses
    assert "| evidence.extra_presses (past max_presses" in report
    assert "Validation jobs with `evidence.extra_presses`" in report
    # a test miss of the mis-sort target is said where the user looks: the report and the printout
    missed = a["mis-sort"] > split["scene_decision"]["validation"]["target_mis_sort"]
    assert f"on the test jobs above in {0 if missed else 1} of 1" in report
    assert ("**missed**" in report) == missed and ("WARNING: the test jobs mis-sorted" in said) == missed
    # CLS_t learnt the touched fabrics of the tiny world: 6 classes, chance 16.7 %; measured 91.7 %
    n_t = m["split_sizes"][0]
    assert n_t == 6 and split["cls_t_acc"] >= 3.0 / n_t, split["cls_t_acc"]
    art = load_run_artifacts(out)
    assert not set(art.untouched) & set(art.touched) and not set(art.validation) & set(art.touched)
    trunk, cls_t, cls_u = build_modules(art)
    x = torch.randn(3, 3, art.tactile_preprocess.size, art.tactile_preprocess.size)
    with torch.no_grad():
        f = trunk(x)
        assert cls_t(f).shape == (3, len(art.touched)) and cls_u(f).shape == (3, len(art.untouched))
        lt, lu = cls_t(f).numpy(), cls_u(f).numpy()
    # the deployed router is the one chosen on validation (it may need the heads' logits)
    m_router = m["router"]["chosen"]
    assert art.router_name == m_router and m_router in m["summary"]["VS2T-ZSL"]["routers"]
    assert load_router(art).novelty(f.numpy().astype(np.float64), lt, logits_u=lu).shape == (3,)
    # the cached features are reused by a second run (no frame is read again)
    assert cmp.FeatureTable.load(out / "features" / "feature_table.npz").x_t.shape[1] == 64


def _same(a, b, where: str = "") -> list[str]:
    """Where two loaded runs differ: nested dicts/lists, tensors and arrays bit for bit, NaN equal
    to NaN (a one-split run's standard errors)."""
    if isinstance(a, dict):
        keys = set(a) | set(b)
        return [d for k in sorted(keys, key=str) for d in (_same(a.get(k), b.get(k), f"{where}/{k}")
                                                            if k in a and k in b else [f"{where}/{k}: only one"])]
    if isinstance(a, (list, tuple)):
        if len(a) != len(b):
            return [f"{where}: length {len(a)} vs {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _same(x, y, f"{where}[{i}]")]
    if isinstance(a, torch.Tensor):
        return [] if torch.equal(a, b) else [f"{where}: tensors differ"]
    if isinstance(a, np.ndarray):
        return [] if np.array_equal(a, b, equal_nan=a.dtype.kind == "f") else [f"{where}: arrays differ"]
    if isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b):
        return []
    return [] if a == b else [f"{where}: {a!r} vs {b!r}"]


def test_training_twice_with_one_seed_gives_the_same_run(tmp_path, tiny_world, monkeypatch):
    """A new user's demo numbers must be the README's: `train` with a fixed seed, twice, gives the
    same metrics.json (timings aside) and the same artifacts/model.pt tensors, bit for bit - the
    features extracted, the tail fine-tuned, every method fitted and the router chosen again from
    scratch. (Checked by hand on the tiny profile from the CLI, two processes, and on the small
    profile; here a shortened tiny budget keeps it to seconds, with the tactile tail's attribute
    task on as the demo's small profile has it.)"""
    from vs2t_edge.train import run as tr

    monkeypatch.setitem(tr.PROFILES, "tiny", replace(tr.PROFILES["tiny"], steps=20, cls_steps=20,
                                                     n_synth_per_class=20, ft_epochs=1, ft_attributes=1.0))
    runs = [tmp_path / "a", tmp_path / "b"]
    for out in runs:
        tr.train(tiny_world, out, profile="tiny", seed=3, figures=False)

    def loaded(out):
        m = json.loads((out / "metrics.json").read_text())
        m.pop("timing_s")
        for split in m["splits"]:
            for key in ("seconds", "finetune_s", "finetune_visual_s"):
                split.pop(key, None)
            for method in split["methods"].values():
                method.pop("seconds", None)
        return m, torch.load(out / "artifacts" / "model.pt", weights_only=False)

    (m_a, art_a), (m_b, art_b) = map(loaded, runs)
    assert _same(m_a, m_b) == []
    assert _same(art_a, art_b) == []


def test_a_fine_tuned_tail_does_not_depend_on_the_memory_layout_of_its_stems():
    """A fresh `train` fine-tuned its visual tail on the stems as the conv left them (channels-last
    in memory), its reruns on the same values read back from the cache in C order - and got other
    features (the small world: validation ZSL 72 against 56 for the same seed). Same values, same
    features now, and a fresh cache is in C order as a read-back one is."""
    from vs2t_edge.train import features as ft
    from vs2t_edge.train.trunks import build_trunk

    torch.set_num_threads(1)
    trunk = build_trunk("tiny", pretrained=False)
    stem = np.random.default_rng(0).standard_normal((64, 32, 8, 8)).astype(np.float16)
    channels_last = np.ascontiguousarray(stem.transpose(0, 2, 3, 1)).transpose(0, 3, 1, 2)
    assert np.array_equal(stem, channels_last) and not channels_last.flags.c_contiguous
    y = np.arange(64) % 4
    feats = [ft.features_from_stem(ft.finetune_tail(trunk, s, y, 4, epochs=1, progress=False), s)
             for s in (stem, channels_last)]
    assert np.array_equal(*feats)


def test_train_on_fewer_touched_fabrics(tmp_path, tiny_world, monkeypatch, capsys):
    """`train --touched N` trains each split on N of its touched fabrics and says so in
    metrics.json and config.yaml; a count a split cannot give is refused before any work."""
    from vs2t_edge.cli import main
    from vs2t_edge.train import run as tr

    code = main(["train", str(tiny_world), "--profile", "tiny", "--touched", "7", "--out", str(tmp_path / "no")])
    assert code == 2 and "has 6 touched ones; give 2 to 6" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()
    with pytest.raises(ValueError, match="has 6 touched ones; give 2 to 6"):  # the API refuses it before work too
        tr.train(tiny_world, tmp_path / "no", profile="tiny", touched=1)
    assert not (tmp_path / "no").exists()
    monkeypatch.setitem(tr.PROFILES, "tiny", replace(tr.PROFILES["tiny"], steps=20, cls_steps=20,
                                                     n_synth_per_class=20, ft_epochs=1))
    m = tr.train(tiny_world, tmp_path / "run", profile="tiny", seed=3, figures=False, touched=4)
    import yaml

    from vs2t_edge.runtime.dataset import load_dataset

    full = cmp.make_splits(load_dataset(tiny_world).ids, 1, 2, 2, seed=3)[0]  # what the run drew from
    sp = m["splits"][0]["split"]
    assert sp["touched"] == fabric_splits.fewer_touched(full, 4).touched and len(full.touched) == 6
    assert (sp["validation"], sp["untouched"]) == (full.validation, full.untouched)
    assert m["split_sizes"] == [4, 2, 2] and m["profile"]["touched"] == 4
    assert yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())["profile"]["touched"] == 4


def test_visual_condition_is_clipped_for_unseen_fabrics():
    # a channel nearly constant on touched fabrics standardises to huge values for an unseen one;
    # unclipped, G extrapolated (W1 real-synth ~500 on the small world)
    m = vs2t.VS2TZSL()
    c = m._cond(np.array([[3.7e5, -2.0]]), np.array([[1.0, 0.0]]))
    assert c.tolist() == [[vs2t.CLIP_SD, -2.0, 1.0, 0.0]]


def test_router_is_chosen_on_validation_ausuc_only():
    from vs2t_edge.train.run import choose_router

    def split(val_a, val_b, test_a, test_b):
        block = {"a": {"val_ausuc": val_a, "ausuc": test_a}, "b": {"val_ausuc": val_b, "ausuc": test_b}}
        return {"methods": {"VS2T-ZSL": {"routers": block}, "S2T": {"routers": {
            "a": {"val_ausuc": 0.0, "ausuc": 1.0}, "b": {"val_ausuc": 1.0, "ausuc": 0.0}}}}}

    # b is better on test in every split, a on validation on average: a wins, whatever test says
    results = [split(0.6, 0.5, 0.1, 0.9), split(0.7, 0.75, 0.1, 0.9)]
    assert choose_router(results) == "a"
    assert choose_router([split(0.5, 0.5, 0.0, 0.0)]) == "a"  # tie: the first evaluated (the paper's Gaussian)


def test_each_splits_router_is_chosen_on_its_own_validation_fabrics():
    """Splits are drawn independently: split 1's validation fabric can be split 0's untouched one.
    A choice averaged over splits read it; each split's (and the shipped split 0's) must not."""
    from vs2t_edge.train.run import routers_by_split, summarise

    def split(val_a, val_b, h_a, h_b):
        r = lambda v, h: {"val_ausuc": v, "ausuc": 0.5, "acc_t": 0.5, "acc_u": 0.5, "H": h}  # noqa: E731
        block = {"gaussian": r(0.1, 0.0), "a": r(val_a, h_a), "b": r(val_b, h_b)}
        return {"methods": {"VS2T-ZSL": {"routers": block, "zsl_acc": 0.5, "val_zsl_acc": 0.5,
                                          "synthesis": {"wasserstein": 0.0, "cosine": 1.0}}}}

    # split 0's validation prefers a; split 1's validation (which may hold split 0's untouched
    # fabrics) prefers b strongly enough to win the mean over both
    results = [split(0.6, 0.5, 0.2, 0.9), split(0.1, 0.9, 0.4, 0.8)]
    assert routers_by_split(results) == ["a", "b"]
    g = summarise(results)["VS2T-ZSL"]["gzsl_router"]
    assert g["per_split"] == ["a", "b"] and g["name"] == "per split"
    assert abs(g["H"]["mean"] - 100 * (0.2 + 0.8) / 2) < 1e-9  # each split's own choice, not b everywhere


def test_vsf_gate_starts_where_gate_bias_puts_it():
    from vs2t_edge.train.models import VSFusion

    torch.manual_seed(0)
    f = torch.randn(256, 40)
    for bias, lo, hi in ((0.0, 0.4, 0.6), (3.0, 0.9, 1.0)):
        with torch.no_grad():
            gate = torch.sigmoid(VSFusion(40, gate_bias=bias).gate(f))
        assert lo < float(gate.mean()) < hi, (bias, float(gate.mean()))  # 0: halves the condition; 3: passes it


def test_condition_options_see_only_touched_visual_features():
    views = _views()
    budget = vs2t.VS2TBudget(steps=3, cls_steps=3, n_synth_per_class=5, hidden=16, latent=4, cond_pca=6,
                             visual_condition="fabric", cond_noise=0.5)
    m = vs2t.VS2TZSL().fit(views.train, budget, seed=0)
    assert m.G.net[0].in_features == 4 + 6 + 24  # latent + principal components + attributes
    basis = m.pca_basis.copy()
    # the principal axes come from touched training presses: other untouched crops change nothing
    data2 = cmp.ZSLData(**{**views.train.__dict__, "v_u": views.train.v_u * 3 + 1})
    m2 = vs2t.VS2TZSL().fit(data2, budget, seed=0)
    assert np.array_equal(m2.pca_basis, basis)
    # "fabric": one visual condition per fabric (the mean over its crops)
    c, cls = m._conditions_u(views.train)
    for k in np.unique(cls):
        assert np.allclose(c[cls == k], c[cls == k][0])
    # whitened: unit variance on the presses it was fitted on
    z = (np.clip(views.train.x_v, -vs2t.CLIP_SD, vs2t.CLIP_SD) - m.pca_mean) @ m.pca_basis
    assert np.allclose(z.std(0, ddof=1), 1.0, atol=1e-3)


def test_the_papers_encoder_conditioning_is_an_option_that_reads_the_condition():
    """encoder_condition: E is q(z | x, v, s) as the paper's (its input is the press feature and
    the condition) instead of q(z | x); the generator is the same."""
    views = _views()
    budget = vs2t.VS2TBudget(steps=3, cls_steps=3, n_synth_per_class=5, hidden=16, latent=4, cond_pca=6,
                             visual_condition="fabric")
    plain = vs2t.VS2TZSL().fit(views.train, budget, seed=0)
    paper = vs2t.VS2TZSL().fit(views.train, replace(budget, encoder_condition=True), seed=0)
    d_t = views.train.x_t.shape[1]
    assert plain.E.body[0].in_features == d_t and paper.E.body[0].in_features == d_t + 6 + 24
    assert paper.G.net[0].in_features == plain.G.net[0].in_features


def test_the_runs_pixel_path_is_chosen_once_and_keys_the_feature_cache(tiny_world, tmp_path):
    """``--preprocess-reduce``: off keeps the float path (no ``reduce`` in the run's preprocessing,
    the cache key as before); auto picks the largest factor that leaves the input size; the
    extracted tactile stems are those of the cell's own function on the chosen path."""
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import TactilePreprocess, preprocess_tactile
    from vs2t_edge.train import features as ft
    from vs2t_edge.train.run import PROFILES, get_cache, tactile_spec

    tiny = PROFILES["tiny"]  # 64 px on 160x120 frames: the crop is 120 px, 60 at 1/2
    assert tactile_spec(tiny, tiny_world) == TactilePreprocess(size=64)
    assert tactile_spec(replace(tiny, preprocess_reduce="auto"), tiny_world).reduce == 1
    assert tactile_spec(replace(tiny, preprocess_reduce="2"), tiny_world).reduce == 2
    assert tactile_spec(replace(tiny, preprocess_reduce="2", tactile_feature="shading_markers"), tiny_world).reduce == 0
    with pytest.raises(ValueError, match="preprocess_reduce"):
        tactile_spec(replace(tiny, preprocess_reduce="3"), tiny_world)
    prof = replace(tiny, preprocess_reduce="2", max_presses=5)
    trunk = build_trunk("tiny", pretrained=False).eval()
    cache = get_cache(tiny_world, prof, tmp_path, trunk)
    assert cache.meta["reduce"] == 2
    assert ft.StemCache.load(tmp_path / "stem_cache.npz", {k: v for k, v in cache.meta.items() if k != "reduce"}) is None
    fab = load_dataset(tiny_world).fabrics[0]
    with torch.no_grad():
        stem = {r: trunk.stem(torch.from_numpy(preprocess_tactile(fab.load_press(0), fab.load_reference(),
                                                                  TactilePreprocess(size=64, reduce=r))[None]))
                .half().float().numpy()[0] for r in (0, 2)}
    got = cache.stem_t[0].astype(np.float32)
    # batch against single-frame convolution rounds differently in the last bits, then to float16
    np.testing.assert_allclose(got, stem[2], rtol=3e-3, atol=2e-5)
    assert np.abs(got - stem[0]).max() > 100 * np.abs(got - stem[2]).max()  # not the float path's


def test_training_warns_when_test_jobs_miss_the_mis_sort_target():
    """Validation chose the operating point for the target; when the test jobs mis-sort more, the
    trainer says so (the demo's world with seed 1: 0.2 % on validation, 11 % on test)."""
    from vs2t_edge.train.run import test_target_warning

    assert test_target_warning(0.01, 0.01, 4) is None and test_target_warning(0.0, 0.01, 4) is None
    said = test_target_warning(0.11, 0.01, 4)
    assert said.startswith("WARNING: the test jobs mis-sorted 11.0% of their pieces, above the 1% target")
    assert "4 validation fabrics" in said

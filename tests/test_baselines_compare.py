"""The comparison pipeline: splits, validation-only choices, the written report; and the
real-sensor check (skips when ../shared/real is absent)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch

from vs2t_edge.runtime import novelty as nv
from vs2t_edge.runtime import router_eval as reval
from vs2t_edge.train import compare as cmp, compare_report as report, compare_sources as sources, splits as fabric_splits
from vs2t_edge.train.baselines import DAP, Budget
from vs2t_edge.train.generators_modern import CADAVAE

REAL = Path(__file__).resolve().parents[2] / "shared" / "real" / "gelsight_mini_materials"


def test_splits_are_disjoint_reproducible_and_different():
    ids = [f"f{i:02d}" for i in range(50)]
    a = cmp.make_splits(ids, 5, seed=0)
    b = cmp.make_splits(ids, 5, seed=0)
    assert [asdict_(s) for s in a] == [asdict_(s) for s in b]
    for s in a:
        assert (len(s.touched), len(s.validation), len(s.untouched)) == (40, 5, 5)  # the paper's 40/5/5
        assert not (set(s.touched) & set(s.validation) or set(s.touched) & set(s.untouched)
                    or set(s.validation) & set(s.untouched))
    assert len({tuple(s.untouched) for s in a}) == 5
    with pytest.raises(ValueError, match="too few"):
        cmp.make_splits(ids[:4], 1)


def test_fewer_touched_nests_its_draws_and_keeps_the_held_out_fabrics():
    """`train --touched N`: N of a split's touched fabrics, the same validation and untouched ones,
    a draw that nests (fewer touched fabrics are a subset of more) and differs between splits."""
    ids = [f"f{i:03d}" for i in range(150)]
    splits = cmp.make_splits(ids, 3, 5, 5, seed=0)
    for sp in splits:
        by_n = {n: fabric_splits.fewer_touched(sp, n) for n in (2, 40, 80, 140)}
        assert all((f.validation, f.untouched, f.seed) == (sp.validation, sp.untouched, sp.seed) for f in by_n.values())
        assert [len(by_n[n].touched) for n in (2, 40, 80, 140)] == [2, 40, 80, 140]
        assert set(by_n[2].touched) < set(by_n[40].touched) < set(by_n[80].touched) < set(sp.touched)
        assert by_n[140].touched == sp.touched and by_n[40] == fabric_splits.fewer_touched(sp, 40)
        assert by_n[40].touched != sorted(sp.touched)[:40]  # a draw, not the first ids
    assert fabric_splits.fewer_touched(splits[0], 40).touched != fabric_splits.fewer_touched(splits[1], 40).touched
    for n in (1, 141):
        with pytest.raises(ValueError, match=f"{n} asked, the split has 140"):
            fabric_splits.fewer_touched(splits[0], n)


def asdict_(s):
    return (s.touched, s.validation, s.untouched, s.seed)


def test_split_views_keep_untouched_tactile_out_of_training():
    table = sources.toy_feature_table(n_fabrics=12, presses=20, d_t=16, d_v=8)
    split = cmp.make_splits(table.fabric_ids, 1, n_val=2, n_untouched=2)[0]
    v = cmp.split_views(table, split)
    assert v.train.n_t == 8 and v.train.n_u == 2 and v.val.n_u == 2
    # touched presses: train + val + test = all presses of touched fabrics, no overlap in count
    assert len(v.train.y) + len(v.touched_val[2]) + len(v.touched_test[2]) == 8 * 20
    assert len(v.test_presses[2]) == 2 * 20 and len(v.val_presses[2]) == 2 * 20
    # the scaler is fitted on touched train presses only: their mean is ~0, untouched not
    assert np.allclose(v.train.x_t.mean(0), 0, atol=1e-4)


TACTILE_ONLY = {"A": ("tactile",), "B": ("tactile",)}  # cell-side inputs of the fake methods


def _fake_split_result(val_zsl, test_zsl, val_ausuc, test_ausuc, seed=0):
    methods = {}
    for m in val_zsl:
        routers = {r: {"acc_t": 0.9, "acc_u": 0.5, "H": 0.6, "auroc": 0.8, "beta": 0.0,
                       "ausuc": test_ausuc[m][r], "val_ausuc": val_ausuc[m][r]} for r in val_ausuc[m]}
        methods[m] = {"zsl_acc": test_zsl[m], "val_zsl_acc": val_zsl[m], "routers": routers, "seconds": 1.0}
    return {"split": {"touched": [], "validation": [], "untouched": [], "seed": seed}, "cls_t_acc": 0.9,
            "methods": methods}


def test_recommendation_uses_validation_not_test():
    r = _fake_split_result(
        val_zsl={"A": 0.9, "B": 0.5}, test_zsl={"A": 0.4, "B": 0.99},
        val_ausuc={"A": {"gaussian": 0.3, "energy": 0.7}, "B": {"gaussian": 0.9, "energy": 0.1}},
        test_ausuc={"A": {"gaussian": 0.9, "energy": 0.2}, "B": {"gaussian": 0.9, "energy": 0.9}},
    )
    s = cmp.summarise([r, r], TACTILE_ONLY)
    assert s["recommendation"]["model"] == "A" and s["recommendation"]["router"] == "energy"
    assert s["methods"]["B"]["zsl_acc"]["mean"] == pytest.approx(0.99)
    assert s["recommendation"]["rule"] == cmp.RECOMMENDATION_RULE


def test_the_rule_skips_methods_that_need_the_camera_on_the_cell():
    r = _fake_split_result(
        val_zsl={"A": 0.9, "B": 0.5}, test_zsl={"A": 0.4, "B": 0.99},
        val_ausuc={"A": {"gaussian": 0.3, "energy": 0.7}, "B": {"gaussian": 0.9, "energy": 0.1}},
        test_ausuc={"A": {"gaussian": 0.9, "energy": 0.2}, "B": {"gaussian": 0.9, "energy": 0.9}})
    rec = cmp.summarise([r], {"A": ("tactile", "visual"), "B": ("tactile",)})["recommendation"]
    assert (rec["model"], rec["router"]) == ("B", "gaussian")  # A is better on validation but not deployable
    assert rec["excluded"] == {"A": ["tactile", "visual"]} and rec["best_any_inputs"] == "A"
    nobody = cmp.summarise([r], {"A": ("visual",), "B": ("tactile", "visual")})["recommendation"]
    assert nobody["model"] is None and nobody["router"] is None
    with pytest.raises(ValueError, match=r"no cell-side inputs recorded for \['A', 'B'\]"):
        cmp.summarise([r])  # a method whose inputs nobody wrote down cannot be recommended
    assert set(cmp.CELL_INPUTS) == set(cmp.all_methods())


def test_cell_inputs_say_what_each_method_reads_per_press():
    """CELL_INPUTS is data the rule trusts: a method listed as tactile-only must score untouched
    classes without the camera (its logits ignore x_v), and one listed with visual must use it."""
    torch.set_num_threads(1)
    table = sources.toy_feature_table(n_fabrics=10, presses=10, d_t=16, d_v=8, noise=0.5)
    views = cmp.split_views(table, cmp.make_splits(table.fabric_ids, 1, n_val=2, n_untouched=2)[0])
    budget = Budget(steps=5, batch=16, hidden=16, latent=4, cls_steps=5, n_synth_per_class=5)
    x_t, x_v, _ = views.test_presses
    other_v = np.random.default_rng(1).normal(size=x_v.shape).astype(x_v.dtype)
    for name, cls in cmp.all_methods().items():
        method = cls().fit(views.train, budget, 0)
        reads_visual = not np.allclose(method.untouched_logits(x_t, x_v), method.untouched_logits(x_t, other_v))
        assert reads_visual == ("visual" in cmp.CELL_INPUTS[name]), name


def _fake_comparison(val_a=0.9, val_b=0.5):
    """A comparison result as run_comparison returns it (two splits, methods A and B), no training."""
    r = _fake_split_result(
        val_zsl={"A": val_a, "B": val_b}, test_zsl={"A": 0.4, "B": 0.6},
        val_ausuc={"A": {"gaussian": 0.3, "energy": 0.7}, "B": {"gaussian": 0.5, "energy": 0.4}},
        test_ausuc={"A": {"gaussian": 0.3, "energy": 0.6}, "B": {"gaussian": 0.5, "energy": 0.4}})
    r2 = json.loads(json.dumps(r))
    r2["methods"]["A"]["val_zsl_acc"] -= 0.1
    r2["split"]["seed"] = 1
    splits = [r, r2]
    return {"splits": splits, "summary": cmp.summarise(splits, TACTILE_ONLY),
            "meta": {"command": "test", "features": "fake", "n_fabrics": 10, "n_presses": 100, "d_t": 4, "d_v": 4,
                     "n_splits": 2, "split_sizes": "6/2/2", "budget": "none", "host": "test", "seconds": 0.0}}


def test_regeneration_keeps_hand_written_text_below_the_marker(tmp_path):
    out = tmp_path / "out"
    paths = report.write_results(_fake_comparison(), out, name="page")
    first = paths["md"].read_text()
    assert first.rstrip("\n").endswith(report.HAND_MARKER) and first.count(report.HAND_MARKER) == 1
    hand = "\n## Reading (hand-written)\n\nA wins on validation; the router choice is weak.\n"
    paths["md"].write_text(first + hand)
    # new numbers: the generated part changes, the hand text stays, once, at the end
    report.write_results(_fake_comparison(val_a=0.2, val_b=0.8), out, name="page")
    second = paths["md"].read_text()
    assert second.endswith(report.HAND_MARKER + "\n" + hand) and second.count("A wins on validation") == 1
    assert second.count(report.HAND_MARKER) == 1 and second.split(report.HAND_MARKER)[0] != first.split(report.HAND_MARKER)[0]
    report.write_results(_fake_comparison(val_a=0.2, val_b=0.8), out, name="page")
    assert paths["md"].read_text() == second  # regenerating is idempotent

    # a page without the marker: refused by default, nothing written; replaced whole on request
    paths["md"].write_text("# my page\n\nhand text with no marker\n")
    json_before = paths["json"].read_text()
    with pytest.raises(report.UnmarkedReportError, match=r"page\.md has no line"):
        report.write_results(_fake_comparison(), out, name="page")
    assert paths["md"].read_text() == "# my page\n\nhand text with no marker\n"
    assert paths["json"].read_text() == json_before
    report.write_results(_fake_comparison(), out, name="page", unmarked="replace")
    replaced = paths["md"].read_text()
    assert "hand text with no marker" not in replaced and replaced.rstrip("\n").endswith(report.HAND_MARKER)


def test_compare_verb_refuses_an_unmarked_page_before_running(tmp_path, capsys):
    from vs2t_edge.cli import main

    (tmp_path / "comparison.md").write_text("# hand-made\n")
    code = main(["compare", "--toy", "--methods", "DAP", "--skip-real", "--out", str(tmp_path)])
    assert code == 2 and "--replace-unmarked" in capsys.readouterr().err
    assert not (tmp_path / "comparison.json").exists()


def test_end_to_end_on_the_toy_world_writes_report(tmp_path):
    torch.set_num_threads(1)
    table = sources.toy_feature_table(n_fabrics=32, presses=15, d_t=32, d_v=16, noise=0.5)
    cache = tmp_path / "features.npz"
    table.save(cache)
    table = cmp.FeatureTable.load(cache)
    splits = cmp.make_splits(table.fabric_ids, 1, n_val=3, n_untouched=3)
    budget = Budget(steps=100, batch=32, hidden=32, latent=8, cls_steps=150, n_synth_per_class=30)
    result = cmp.run_comparison(table, splits, budget, {"DAP": DAP, "CADA-VAE": CADAVAE}, log=lambda m: None)
    result["meta"] = {"command": "test", "features": "toy", "n_fabrics": 14, "n_presses": 280, "d_t": 24,
                      "d_v": 16, "n_splits": 1, "split_sizes": "26/3/3", "budget": "tiny", "host": "test",
                      "seconds": 1.0}
    m = result["summary"]["methods"]["DAP"]
    assert set(m["routers"]) == set(nv.ROUTERS)
    for r in nv.ROUTERS:
        for key in ("acc_t", "acc_u", "H", "ausuc", "val_ausuc"):
            assert 0.0 <= m["routers"][r][key]["mean"] <= 1.0
    # 24 touched fabrics teach DAP the attributes well enough to beat chance (1/3) clearly
    assert m["zsl_acc"]["mean"] > 0.5
    for r in nv.ROUTERS:  # per item, by bins: shares of every piece, at most 5 presses each
        b = {k: m["routers"][r][k]["mean"] for k in cmp.ITEM_KEYS}
        assert abs(b["item_right"] + b["item_mis_sort"] + b["item_reject"] - 1) < 1e-9 and 1 <= b["item_presses"] <= 5
    paths = report.write_results(result, tmp_path / "out")
    md = paths["md"].read_text()
    assert "| DAP | 43.56 |" in md and "Recommendation" in md
    assert "## Per item, by bins (test fabrics)" in md and "| DAP |" in md.split("## Per item, by bins")[1]
    assert json.loads(paths["json"].read_text())["summary"]["recommendation"]["model"] in ("DAP", "CADA-VAE")
    assert paths["png"].stat().st_size > 5000


def test_feature_cache_names_missing_keys(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, x_t=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="lacks"):
        cmp.FeatureTable.load(bad)


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/real/gelsight_mini_materials absent")
def test_real_materials_frozen_trunk_separates_touched_from_untouched():
    """Real GelSight Mini frames: the frozen ImageNet trunk + Gaussian router flags unseen
    materials better than chance (a weak but real bar; the benchmark fine-tunes)."""
    from vs2t_edge.train import realdata_check as rc

    torch.set_num_threads(1)
    names, frames = rc.load_materials(REAL)
    assert len(names) == 10 and all(len(f) == 20 for f in frames)
    spec = rc.TactilePreprocess(size=96, mean=rc.IMAGENET_MEAN, std=rc.IMAGENET_STD, use_reference=False)
    x = {m: torch.from_numpy(np.stack([rc.preprocess_tactile(f, None, spec) for f in frames[m]])) for m in range(10)}
    trunk, _ = rc.make_trunk()
    feats = {m: rc._features(trunk, x[m]) for m in range(10)}
    touched, untouched = range(0, 5), range(5, 10)
    train = np.concatenate([feats[m][:14] for m in touched])
    held = np.concatenate([feats[m][14:] for m in touched])
    unseen = np.concatenate([feats[m] for m in untouched])
    router = nv.fit_router("mahalanobis_lw", train)
    assert reval.auroc(router.novelty(held), router.novelty(unseen)) > 0.6


def test_compare_verb_refuses_bad_input_with_exit_2(tmp_path, capsys):
    from vs2t_edge.cli import main

    assert main(["compare"]) == 2
    assert "--features" in capsys.readouterr().err
    assert main(["compare", "--features", str(tmp_path / "nope.npz")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["compare", "--toy", "--methods", "DAP,Nope", "--skip-real"]) == 2
    assert "unknown method" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# a training run as the source: its features, its exact splits, its VS2T numbers
# --------------------------------------------------------------------------------------------


def _fake_run(tmp_path, with_stems=False, seeds=(7, 11)):
    """A run folder as `vs2t-edge train` writes it (features, config.yaml, metrics.json), with
    splits drawn by other seeds than `make_splits(..., seed=0)` would, and VS2T-ZSL numbers
    computed the way the run computes them (compare.run_split with train/vs2t.py's class)."""
    import yaml

    from vs2t_edge.train import vs2t

    run = tmp_path / "run"
    (run / "features").mkdir(parents=True)
    table = sources.toy_feature_table(n_fabrics=14, presses=12, d_t=24, d_v=12, noise=0.5, seed=3)
    table.save(run / "features" / "feature_table.npz")
    splits = [cmp.make_splits(table.fabric_ids, 1, n_val=2, n_untouched=3, seed=s)[0] for s in seeds]
    profile = {"name": "tiny", "trunk": "tiny", "size_px": 32, "splits": len(splits), "ft_epochs": 1,
               "ft_max_rows": None, "steps": 20, "batch": 32, "cls_steps": 30, "n_synth_per_class": 20,
               "lr_scale": 5.0, "latent": 8, "hidden": 32, "seed": 0}
    budget = sources.run_budget(profile)
    (run / "config.yaml").write_text(yaml.safe_dump({"dataset": "toy", "profile": profile,
                                                     "budget": {"steps": 20, "not_a_field": 1}}, sort_keys=False))
    records = []
    for sp in splits:
        r = cmp.run_split(table, sp, {"VS2T-ZSL": vs2t.variant_class("VS2T-ZSL")}, budget, routers=("gaussian",),
                          log=lambda m: None)
        records.append(r)
    (run / "metrics.json").write_text(json.dumps({"splits": records, "summary": {}}, default=float))
    if with_stems:
        from vs2t_edge.train import features as ft
        from vs2t_edge.train.trunks import build_trunk

        torch.manual_seed(0)
        trunk = build_trunk("tiny").eval()
        images = torch.from_numpy(np.random.default_rng(0).normal(size=(len(table.fabric), 3, 32, 32))
                                  .astype(np.float32) + table.fabric[:, None, None, None].astype(np.float32) * 0.1)
        with torch.no_grad():
            stem = trunk.stem(images)
            x_t0 = trunk.features_from_stem(stem).numpy()
        ft.StemCache(stem.half().numpy(), table.x_v, x_t0, table.fabric, table.fabric_ids, table.attributes,
                     {"arch": "tiny", "size": 32}).save(run / "features" / "stem_cache.npz")
    return run, table, splits


def test_load_run_reads_exactly_the_runs_splits_and_budget(tmp_path):
    torch.set_num_threads(1)
    run, table, splits = _fake_run(tmp_path)
    src = sources.load_run(run)
    assert [asdict_(s) for s in src.splits] == [asdict_(s) for s in splits]  # order and seeds kept
    assert [asdict_(s) for s in src.splits] != [asdict_(s) for s in cmp.make_splits(table.fabric_ids, 2, 2, 3)]
    assert np.array_equal(src.table.x_t, table.x_t) and src.table.fabric_ids == table.fabric_ids
    b = sources.run_budget(src.profile, src.budget, steps=5)
    assert (b.steps, b.hidden, b.latent, b.cls_steps, b.lr_scale) == (5, 32, 8, 30, 5.0)
    assert src.budget["steps"] == 20 and sources.run_budget(src.profile, {"steps": 25, "not_a_field": 1}).steps == 25
    own = sources.run_vs2t_numbers(src)
    assert own["per_split_zsl"] == [r["zsl_acc"] for r in src.vs2t_splits] and len(src.vs2t_splits) == 2
    # a split naming a fabric the table lacks is refused by name
    m = json.loads((run / "metrics.json").read_text())
    m["splits"][1]["split"]["untouched"][0] = "nope"
    (run / "metrics.json").write_text(json.dumps(m))
    with pytest.raises(ValueError, match=r"split 1 .*\['nope'\]"):
        sources.load_run(run)
    del m["splits"][0]["split"]["seed"]
    (run / "metrics.json").write_text(json.dumps(m))
    with pytest.raises(ValueError, match=r"splits\[0\]\.split lacks \['seed'\]"):
        sources.read_run_splits(run / "metrics.json")


def test_compare_verb_on_a_run_uses_its_splits_and_reproduces_its_vs2t(tmp_path, capsys):
    from vs2t_edge.cli import main

    torch.set_num_threads(1)
    run, table, splits = _fake_run(tmp_path)
    out = tmp_path / "out"
    code = main(["compare", "--run", str(run), "--tactile", "frozen", "--methods", "DAP,VS2T-ZSL", "--skip-real",
                 "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    res = json.loads((out / "comparison_tiny.json").read_text())
    assert [tuple(r["split"][k] for k in ("touched", "validation", "untouched", "seed")) for r in res["splits"]] \
        == [asdict_(s) for s in splits]
    # same class, features, splits, seeds and budget as the "run": identical VS2T-ZSL numbers
    assert res["run_vs2t"]["reproduction"]["max_abs_diff"] == 0.0
    md = (out / "comparison_tiny.md").read_text()
    assert "VS2T-ZSL, the run's own metrics.json | 76.36" in md and "exactly the splits of" in md
    assert (out / "comparison_tiny.png").is_file() and not (out / "comparison_tiny.partial.json").exists()
    # the same splits through --features + --splits-from
    code = main(["compare", "--features", str(run / "features" / "feature_table.npz"), "--splits-from", str(run),
                 "--methods", "DAP", "--skip-real", "--steps", "20", "--cls-steps", "30", "--hidden", "32",
                 "--out", str(out), "--out-name", "sf"])
    assert code == 0
    res2 = json.loads((out / "sf.json").read_text())
    assert [r["split"] for r in res2["splits"]] == [r["split"] for r in res["splits"]]
    # --new-splits: the run's features, fresh random splits, no run VS2T numbers to compare with
    code = main(["compare", "--run", str(run), "--tactile", "frozen", "--new-splits", "--splits", "1", "--seed", "4",
                 "--n-val", "2", "--n-untouched", "2", "--methods", "DAP", "--skip-real", "--out", str(out),
                 "--out-name", "ns"])
    assert code == 0
    res3 = json.loads((out / "ns.json").read_text())
    assert [r["split"]["seed"] for r in res3["splits"]] == [4000] and "run_vs2t" not in res3
    assert main(["compare", "--run", str(tmp_path / "absent"), "--skip-real"]) == 2
    assert "does not exist" in capsys.readouterr().err


def _trained_run(tmp_path, visual_tail, seeds=(7, 11), ft_attributes=0.0):
    """A tiny run made by training's own code (``run.run_split``: tactile tail, and with
    ``visual_tail="finetuned"`` the visual tail, fine-tuned per split from the stem cache) on a
    stem cache of a tiny trunk, written as `vs2t-edge train` writes it."""
    import yaml

    from vs2t_edge.train import features as ft
    from vs2t_edge.train import run as tr
    from vs2t_edge.train import vs2t
    from vs2t_edge.train.trunks import build_trunk

    run = tmp_path / f"run_{visual_tail}_{ft_attributes:g}"
    (run / "features").mkdir(parents=True)
    toy = sources.toy_feature_table(n_fabrics=14, presses=12, d_t=8, d_v=8, seed=3)
    prof = tr.Profile("tiny", trunk="tiny", size_px=32, splits=len(seeds), ft_epochs=1, ft_max_rows=None, steps=20,
                      batch=32, cls_steps=30, n_synth_per_class=20, latent=8, hidden=32, seed=0,
                      routers=("gaussian",), visual_tail=visual_tail, ft_attributes=ft_attributes)
    budget = vs2t.VS2TBudget(steps=prof.steps, batch=prof.batch, cls_steps=prof.cls_steps,
                             n_synth_per_class=prof.n_synth_per_class, lr_scale=prof.lr_scale, latent=prof.latent,
                             hidden=prof.hidden)
    torch.manual_seed(prof.seed)  # as `train` does before building its trunk
    trunk = build_trunk(prof.trunk, pretrained=True)
    rng = np.random.default_rng(0)
    # each fabric's texture (tactile, camera) a map of its attributes, plus press noise
    basis = rng.normal(size=(2, toy.attributes.shape[1], 3, 32, 32)) / 3
    tex_t, tex_v = np.einsum("fa,kachw->kfchw", toy.attributes, basis)
    noise = rng.normal(size=(2, len(toy.fabric), 3, 32, 32))
    tac = torch.from_numpy((tex_t[toy.fabric] + 0.7 * noise[0]).astype(np.float32))
    vis = torch.from_numpy((tex_v[toy.fabric] + 0.7 * noise[1]).astype(np.float32))
    trunk.eval()
    with torch.no_grad():
        stem_t, stem_v = trunk.stem(tac), trunk.stem(vis)
        x_t0, x_v = trunk.features_from_stem(stem_t).numpy(), trunk.features_from_stem(stem_v).numpy()
    cache = ft.StemCache(stem_t.half().numpy(), x_v, x_t0, toy.fabric, toy.fabric_ids, toy.attributes,
                         {"arch": "tiny", "size": 32}, stem_v.half().numpy())
    cache.save(run / "features" / "stem_cache.npz")
    cmp.FeatureTable(x_t0, x_v, toy.fabric, toy.fabric_ids, toy.attributes).save(run / "features" / "feature_table.npz")
    plain = json.loads(json.dumps({"profile": asdict(prof), "budget": asdict(budget)}))
    (run / "config.yaml").write_text(yaml.safe_dump({"dataset": "toy", **plain}, sort_keys=False))
    splits = [cmp.make_splits(toy.fabric_ids, 1, n_val=2, n_untouched=3, seed=s)[0] for s in seeds]
    records = [tr.run_split(cache, trunk, sp, prof, budget)["result"] for sp in splits]
    (run / "metrics.json").write_text(json.dumps({"splits": records, "summary": {}}, default=float))
    return run, cache, splits


@pytest.mark.parametrize("visual_tail,ft_attributes", [("finetuned", 0.0), ("frozen", 0.0), ("frozen", 1.0)])
def test_compare_run_reproduces_a_run_trained_with_its_visual_tail(tmp_path, capsys, visual_tail, ft_attributes):
    """`compare --run` follows the run's profile.visual_tail: a run whose visual tail was
    fine-tuned per split is reproduced (same per-split VS2T-ZSL as its metrics.json), every
    method reads those tuned visual features, and a frozen run still is reproduced. It follows
    the tactile tail's attribute task too (``ft_attributes``), which a run without it lacks."""
    from vs2t_edge.cli import main

    torch.set_num_threads(1)
    run, cache, splits = _trained_run(tmp_path, visual_tail, ft_attributes=ft_attributes)
    src = sources.load_run(run)
    assert sources.run_visual_tail(src) == visual_tail
    table = sources.finetuned_tables(src, log=lambda m: None)(splits[0])
    assert np.array_equal(table.x_v, cache.x_v) == (visual_tail == "frozen")
    out = tmp_path / "out"
    code = main(["compare", "--run", str(run), "--methods", "DAP,VT-FC-ZSL,VS2T-ZSL", "--skip-real",
                 "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    res = json.loads((out / "comparison_tiny.json").read_text())
    rep = res["run_vs2t"]["reproduction"]
    assert len(rep["per_split_zsl_diff"]) == len(splits) and rep["max_abs_diff"] == 0.0, rep
    assert ("visual_tail finetuned" in res["meta"]["features"]) == (visual_tail == "finetuned")
    assert ("tactile + visual tail fine-tuned" in err) == (visual_tail == "finetuned")
    for ours, own in zip(res["splits"], src.vs2t_splits):  # validation and GZSL numbers too
        m = ours["methods"]["VS2T-ZSL"]
        assert (m["val_zsl_acc"], m["routers"]["gaussian"]) == (own["val_zsl_acc"], own["routers"]["gaussian"])
    if ft_attributes:  # the test can fail: the tail without the task is another tail
        from vs2t_edge.train import features as ft
        from vs2t_edge.train.trunks import build_trunk

        torch.manual_seed(0)  # the run's trunk, as compare builds it
        plain = ft.finetune_split(cache, build_trunk("tiny", pretrained=True), splits[0], epochs=1, max_rows=None,
                                  progress=False)
        assert not np.array_equal(plain.x_t, table.x_t)
    if visual_tail == "finetuned":  # the test can fail: frozen visual features (compare's old way) do not reproduce
        from vs2t_edge.train import vs2t

        old = cmp.FeatureTable(table.x_t, cache.x_v, table.fabric, table.fabric_ids, table.attributes)
        r = cmp.run_split(old, splits[0], {"VS2T-ZSL": vs2t.variant_class("VS2T-ZSL")},
                          sources.run_budget(src.profile, src.budget), routers=("gaussian",), log=lambda m: None)
        assert r["methods"]["VS2T-ZSL"]["zsl_acc"] != src.vs2t_splits[0]["zsl_acc"]


def test_one_command_runs_the_whole_comparison_and_the_pages_rebuild_from_its_jsons(tmp_path, capsys):
    """Issue 4's chain on a tiny run: `compare --run RUN --full` = the run's splits (fine-tuned
    tactile features, the default), new splits, the real-sensor check (its folder absent here:
    skipped), the recommendation pooled over every split, and both pages; then `--rebuild` from
    the two JSONs alone gives the same pages and keeps hand-written text."""
    from vs2t_edge.cli import main

    torch.set_num_threads(1)
    run, table, splits = _fake_run(tmp_path, with_stems=True)
    metrics = json.loads((run / "metrics.json").read_text())
    metrics["router"] = {"chosen": "energy", "rule": "highest mean validation AUSUC of VS2T-ZSL over splits"}
    (run / "metrics.json").write_text(json.dumps(metrics))
    out = tmp_path / "results"
    code = main(["compare", "--run", str(run), "--full", "--splits", "2", "--extra-seed", "5", "--n-val", "2",
                 "--n-untouched", "3", "--methods", "DAP,VT-FC-ZSL,VS2T-ZSL", "--real", str(tmp_path / "no_real"),
                 "--out", str(out)])
    io = capsys.readouterr()
    assert code == 0, io.err
    for stage in ("[stage 1/4: the run's 2 splits]", "[stage 2/4: 2 new random splits, seed 5]",
                  "[stage 3/4: real-sensor check]", "real-sensor check skipped", "[stage 4/4:", "[2/2] split seed"):
        assert stage in io.err
    main_json, extra_json = json.loads((out / "comparison_tiny.json").read_text()), \
        json.loads((out / "comparison_tiny_newsplits.json").read_text())
    assert [r["split"]["seed"] for r in main_json["splits"]] == [s.seed for s in splits]
    assert [r["split"]["seed"] for r in extra_json["splits"]] == [5000, 5001]
    # the page's recommendation is the one rule over every split of both JSONs
    rec = cmp.pool_results([main_json, extra_json])["summary"]["recommendation"]
    assert main_json["pooled"]["summary"]["recommendation"] == rec and main_json["pooled"]["n_splits"] == 4
    assert (main_json["recommendation"]["model"], main_json["recommendation"]["router"]) == (rec["model"], rec["router"])
    assert rec["model"] in ("DAP", "VS2T-ZSL") and rec["excluded"] == {"VT-FC-ZSL": ["tactile", "visual"]}
    md = (out / "comparison_tiny.md").read_text()
    assert f"Default model **{rec['model']}**, default router **{rec['router']}**." in md
    assert cmp.RECOMMENDATION_RULE in md and "| VT-FC-ZSL | tactile + visual (not eligible) |" in md
    assert "records router **energy** for its VS2T-ZSL" in md and "vs2t-edge compare --run" in md
    extra_md = (out / "comparison_tiny_newsplits.md").read_text()
    assert "see [comparison_tiny.md](comparison_tiny.md)" in extra_md and "Default model" in extra_md
    assert f"recommended default: model {rec['model']}, router {rec['router']}" in io.out
    for page in ("comparison_tiny", "comparison_tiny_newsplits"):
        assert (out / f"{page}.png").stat().st_size > 5000 and not (out / f"{page}.partial.json").exists()
        assert (out / f"{page}.md").read_text().rstrip("\n").endswith(report.HAND_MARKER)

    hand = "\n## Reading (hand-written)\n\nThe tiny world says nothing about fabrics.\n"
    (out / "comparison_tiny.md").write_text(md + hand)
    code = main(["compare", "--rebuild", str(out / "comparison_tiny.json"),
                 "--pool", str(out / "comparison_tiny_newsplits.json")])
    assert code == 0, capsys.readouterr().err
    assert (out / "comparison_tiny.md").read_text() == md + hand  # same generated part, hand text kept
    assert (out / "comparison_tiny_newsplits.md").read_text() == extra_md
    # pooling a JSON with itself would count its splits twice: refused, in words
    assert main(["compare", "--rebuild", str(out / "comparison_tiny.json"),
                 "--pool", str(out / "comparison_tiny.json")]) == 2
    assert "more than once" in capsys.readouterr().err
    # the router a run ships is only read from that run: another run's metrics.json is refused
    assert main(["compare", "--rebuild", str(out / "comparison_tiny_newsplits.json"),
                 "--run-metrics", str(run / "metrics.json")]) == 2
    assert "is another run" in capsys.readouterr().err


def test_finetuned_run_features_follow_the_run_recipe(tmp_path):
    torch.set_num_threads(1)
    run, table, splits = _fake_run(tmp_path, with_stems=True)
    src = sources.load_run(run)
    for_split = sources.finetuned_tables(src, log=lambda m: None)
    a, b = for_split(splits[0]), for_split(splits[0])
    assert np.array_equal(a.x_t, b.x_t)  # seeded by the split, like the run
    assert np.array_equal(a.x_v, table.x_v) and a.fabric_ids == table.fabric_ids
    assert a.x_t.shape == (len(table.fabric), 64)
    from vs2t_edge.train import features as ft

    frozen = ft.StemCache.load(run / "features" / "stem_cache.npz").x_t0
    assert not np.allclose(a.x_t, frozen)  # the tail was fine-tuned
    assert not np.array_equal(for_split(splits[1]).x_t, a.x_t)  # per split: other touched fabrics, other seed
    (run / "features" / "stem_cache.npz").unlink()
    with pytest.raises(FileNotFoundError, match="stem_cache"):
        sources.finetuned_tables(src)


def test_pooling_concatenates_splits_and_keeps_the_validation_rule(capsys):
    a = _fake_split_result(
        val_zsl={"A": 0.9, "B": 0.5}, test_zsl={"A": 0.1, "B": 0.9},
        val_ausuc={"A": {"gaussian": 0.2, "energy": 0.6}, "B": {"gaussian": 0.3, "energy": 0.4}},
        test_ausuc={"A": {"gaussian": 0.9, "energy": 0.1}, "B": {"gaussian": 0.9, "energy": 0.9}})
    a2 = {**a, "split": {**a["split"], "seed": 1}}
    b = _fake_split_result(
        val_zsl={"A": 0.7, "B": 0.6}, test_zsl={"A": 0.1, "B": 0.9},
        val_ausuc={"A": {"gaussian": 0.25, "energy": 0.5}, "B": {"gaussian": 0.3, "energy": 0.4}},
        test_ausuc={"A": {"gaussian": 0.9, "energy": 0.1}, "B": {"gaussian": 0.9, "energy": 0.9}}, seed=1000)
    pooled = cmp.pool_results([{"splits": [a, a2]}, {"splits": [b]}], TACTILE_ONLY)
    assert len(pooled["splits"]) == 3
    assert pooled["summary"]["methods"]["A"]["val_zsl_acc"]["mean"] == pytest.approx((0.9 + 0.9 + 0.7) / 3)
    assert pooled["summary"]["recommendation"] == {**pooled["summary"]["recommendation"], "model": "A",
                                                   "router": "energy"}
    assert "Against the paper's Gaussian router it leads by" in pooled["evidence"]
    c = _fake_split_result(val_zsl={"A": 0.9}, test_zsl={"A": 0.1}, val_ausuc={"A": {"gaussian": 0.2}},
                           test_ausuc={"A": {"gaussian": 0.9}})
    with pytest.raises(ValueError, match="different methods"):
        cmp.pool_results([{"splits": [a]}, {"splits": [c]}], TACTILE_ONLY)
    older = _fake_split_result(val_zsl={"A": 0.9, "B": 0.5}, test_zsl={"A": 0.1, "B": 0.9},
                               val_ausuc={"A": {"gaussian": 0.2}, "B": {"gaussian": 0.3}},
                               test_ausuc={"A": {"gaussian": 0.9}, "B": {"gaussian": 0.9}}, seed=2000)
    with pytest.raises(ValueError, match="different routers .*energy"):  # a comparison from before a router
        cmp.pool_results([{"splits": [a]}, {"splits": [older]}], TACTILE_ONLY)
    with pytest.raises(ValueError, match=r"same fabric split \(seed \[0\]\)"):
        cmp.pool_results([{"splits": [a, a2]}, {"splits": [a]}], TACTILE_ONLY)  # would count split 0 twice


def test_methods_section_says_what_vs2t_conditions_on():
    """The generated "Methods and adaptations" text follows the budget the JSON records: VS2T-ZSL's
    visual condition is each fabric's clipped mean crop feature (``visual_condition: fabric``) or
    the clipped per-press feature, while f-CLSWGAN / CADA-VAE / f-VAEGAN read the raw per-press
    one — never "all share the same [x_v, s]"."""
    import copy

    from vs2t_edge.train import vs2t

    base = json.loads((Path(__file__).parents[1] / "docs/results/comparison_paper_v3.json").read_text())
    assert base["budget"]["visual_condition"] == "fabric"

    def methods_text(budget):
        r = copy.deepcopy(base)
        r["budget"] = budget
        md = report.render_markdown(r)
        return md[md.index("## Methods and adaptations"):]

    fabric = methods_text(base["budget"])
    assert "same fused visual+semantic condition" not in fabric
    assert "f-CLSWGAN, CADA-VAE and f-VAEGAN condition on the fused" in fabric and "at each press, as it is" in fabric
    assert "VS2T-ZSL also conditions on [x_v, s] (through VS-F), but its x_v is each fabric's mean crop feature" in fabric
    assert f"±{vs2t.CLIP_SD:g} standard deviations" in fabric
    press = methods_text({**base["budget"], "visual_condition": "press"})
    assert "its x_v is the crop feature at each press, every channel clipped" in press and "mean crop" not in press
    old = methods_text({k: v for k, v in base["budget"].items() if k != "visual_condition"})
    assert "records no `visual_condition`" in old and "clipped" not in old
    pca = methods_text({**base["budget"], "cond_pca": 8})
    assert "top 8 whitened principal components" in pca
    no_vs2t = copy.deepcopy(base)
    for sp in no_vs2t["splits"]:
        sp["methods"].pop("VS2T-ZSL")
    assert "VS2T-ZSL also conditions" not in report.render_markdown(no_vs2t)


def _posteriors(names, truth_of_row, confidence):
    """Log posteriors over ``names``: ``confidence`` on the class each row names, the rest spread."""
    lp = np.full((len(truth_of_row), len(names)), np.log((1 - confidence) / (len(names) - 1)))
    lp[np.arange(len(truth_of_row)), truth_of_row] = np.log(confidence)
    return lp


def test_by_bins_counts_right_bins_and_mis_sorts_on_a_hand_made_case():
    names_t, names_u = [f"t{i}" for i in range(6)], ["u0", "u1", "u2"]
    y_t, y_u = np.repeat(np.arange(6), 5), np.repeat(np.arange(3), 5)
    lp_t = _posteriors(names_t + names_u, y_t, 0.99)
    right = cmp.by_bins(names_t, names_u, lp_t, y_t, _posteriors(names_t + names_u, 6 + y_u, 0.99), y_u)
    assert right["item_right"] == 1.0 and right["item_mis_sort"] == 0.0
    assert right["item_by_kind"]["touched"]["presses"] == right["item_by_kind"]["untouched"]["presses"] == 1.0
    assert right["item_by_kind"]["off-scene"]["right"] == 1.0  # no scene class explains them: rejected
    # every untouched press sure it is t0: an untouched piece in a scene listing t0 goes to t0's bin
    wrong = cmp.by_bins(names_t, names_u, lp_t, y_t, _posteriors(names_t + names_u, 0 * y_u, 0.99), y_u)
    assert wrong["item_by_kind"]["untouched"]["mis-sort"] > 0 and wrong["item_by_kind"]["touched"]["right"] == 1.0
    assert wrong["item_right"] < 1.0


def test_each_split_choosing_alone_reads_only_its_own_validation():
    """The pooled rule can pick what no single split's validation picks; a split's own choice and
    its test numbers come from that split alone."""
    def split(val_a, val_b, zsl_a, zsl_b):
        r = lambda v, h: {"val_ausuc": v, "H": h, "ausuc": h}  # noqa: E731
        return {"methods": {"DAP": {"val_zsl_acc": val_a, "zsl_acc": zsl_a, "routers": {"gaussian": r(0.5, zsl_a)}},
                            "CADA-VAE": {"val_zsl_acc": val_b, "zsl_acc": zsl_b,
                                         "routers": {"gaussian": r(0.4, 0.1), "energy": r(0.6, zsl_b)}}}}

    own = cmp.own_split_choices([split(0.9, 0.1, 0.3, 0.8), split(0.2, 0.8, 0.4, 0.6)])
    assert own["choices"] == [("DAP", "gaussian"), ("CADA-VAE", "energy")]
    assert abs(own["zsl_acc"]["mean"] - (0.3 + 0.6) / 2) < 1e-12 and abs(own["H"]["mean"] - 0.45) < 1e-12

"""More validation fabrics for the scene decision (train/folds.py): folds of the touched fabrics,
each held out of a generator trained on the others, play validation fabrics beside the split's own."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from vs2t_edge.runtime.scene_model import SceneModel
from vs2t_edge.train import decision as dc
from vs2t_edge.train.baselines import ZSLData
from vs2t_edge.train.folds import fold_assignment, fold_data

N_T, TRAIN, VAL = 9, 6, 2  # touched fabrics; training and validation presses of each


def _split_data() -> tuple[ZSLData, tuple]:
    """Touched training and validation presses whose features say which fabric and press they are
    (column 0: fabric, column 1: press number; tests stop at the validation presses: the test
    presses are never handed over)."""
    rows = [(f, p) for f in range(N_T) for p in range(TRAIN)]
    x = np.array([[f, p, 0.0] for f, p in rows])
    train = ZSLData(x_t=x, x_v=x + 100, y=np.array([f for f, _ in rows]), attr_t=np.arange(N_T)[:, None] * np.ones((1, 4)),
                    attr_u=np.zeros((0, 4)), v_u=np.zeros((0, 3)), v_u_class=np.zeros(0, int),
                    names_t=[f"t{f}" for f in range(N_T)])
    val = [(f, p) for f in range(N_T) for p in range(TRAIN, TRAIN + VAL)]
    xv = np.array([[f, p, 0.0] for f, p in val])
    return train, (xv, xv + 100, np.array([f for f, _ in val]))


def test_every_touched_fabric_is_held_out_once():
    parts = fold_assignment(N_T, 3, seed=5)
    assert sorted(np.concatenate(parts).tolist()) == list(range(N_T)) and all(len(p) == 3 for p in parts)
    assert [p.tolist() for p in parts] == [p.tolist() for p in fold_assignment(N_T, 3, seed=5)]  # drawn from the seed
    assert [p.tolist() for p in parts] != [p.tolist() for p in fold_assignment(N_T, 3, seed=6)]
    for bad in (1, 5):  # one fold holds out everything; five cannot hold 2 each
        with pytest.raises(ValueError, match="validation folds"):
            fold_assignment(N_T, bad, seed=5)


def test_a_fold_generator_never_reads_its_held_out_fabrics_touch():
    train, touched_val = _split_data()
    held = np.array([1, 4, 7])
    data, (x, y), (xk, yk) = fold_data(train, touched_val, held)
    keep = np.array([0, 2, 3, 5, 6, 8])
    # the generator's tactile rows: only kept fabrics, relabelled 0..5 in their order
    assert set(data.x_t[:, 0].astype(int)) == set(keep.tolist())
    assert np.array_equal(keep[data.y], data.x_t[:, 0].astype(int))
    assert data.names_t == [f"t{f}" for f in keep] and data.names_u == ["t1", "t4", "t7"]
    assert np.array_equal(data.attr_u[:, 0], held)
    # the held fabrics play validation fabrics: their training then validation presses, in press order
    for j, f in enumerate(held):
        mine = x[y == j]
        assert mine[:, 0].tolist() == [f] * (TRAIN + VAL) and mine[:, 1].tolist() == list(range(TRAIN + VAL))
    # their camera crops are the generator's conditions, the same presses as the pieces
    assert np.array_equal(data.v_u, x + 100) and np.array_equal(data.v_u_class, y)
    # the kept fabrics' validation presses are the fold's touched pieces, relabelled as the generator's
    assert np.array_equal(keep[yk], xk[:, 0].astype(int)) and set(xk[:, 1].astype(int)) == {TRAIN, TRAIN + 1}
    assert len(xk) == len(keep) * VAL


def _world(rng, n_t: int, n_v: int, misnamed: int = 0, per: int = 30, d: int = 16):
    """A validation world whose generator synthesises each validation fabric's mean near its
    presses, except the first ``misnamed``, whose means it puts on the next fabric's presses."""
    centres = rng.normal(0, 3.0, (n_t + n_v, d))
    presses = [c + rng.normal(0, 1, (per, d)) for c in centres]
    at = [n_t + ((j + 1) % n_v if j < misnamed else j) for j in range(n_v)]
    synth = np.concatenate([centres[at[j]] + 0.3 * rng.normal(0, 1, d) + rng.normal(0, 1, (40, d))
                            for j in range(n_v)]), np.repeat(np.arange(n_v), 40)
    return dc.ValidationWorld(np.concatenate([p[:20] for p in presses[:n_t]]), np.repeat(np.arange(n_t), 20),
                              [f"t{j}" for j in range(n_t)],
                              (np.concatenate([p[20:25] for p in presses[:n_t]]), np.repeat(np.arange(n_t), 5)),
                              [f"v{j}" for j in range(n_v)],
                              (np.concatenate(presses[n_t:]), np.repeat(np.arange(n_v), per)), synth)


def _on(model, world: dc.ValidationWorld, seed: int) -> dict:
    """``model``'s operating point on ``world``'s validation jobs (its means, the same scalars)."""
    jobs = dc._Jobs.of(world, seed)
    vm = jobs.model(model.k)
    cand = replace(model, classes=vm.classes, untouched=vm.untouched, center=vm.center, basis=vm.basis, means=vm.means)
    return dc._simulate([cand], [jobs])["all"]


def test_the_operating_point_is_chosen_on_every_worlds_jobs():
    """Four validation fabrics the generator names well say untouched pieces are safe to sort; a
    fold of touched fabrics of which it names some as others says they are not. Chosen on both,
    the operating point keeps the fold's misnamed fabrics out of wrong bins, which the point the
    validation fabrics alone choose puts there."""
    rng = np.random.default_rng(3)
    own, fold = _world(rng, 8, 4), _world(rng, 8, 9, misnamed=4)
    untouched = ["u0", "u1"]
    synth_u = rng.normal(0, 3.0, (80, 16)), np.repeat(np.arange(2), 40)
    args = (own.train_x, own.train_y, own.touched, own.touched_val, own.val_fabrics, own.val_presses, own.synth_val,
            untouched, synth_u)
    alone, rep_alone = dc.fit_scene_decision(*args, seed=2)
    both, rep_both = dc.fit_scene_decision(*args, seed=2, folds=[fold])
    assert [w["validation_fabrics"] for w in rep_both["validation_worlds"]] == [4, 9]
    assert "validation_own_world" not in rep_alone  # without folds the validation jobs are the own ones
    pooled, own_jobs = rep_both["validation"], rep_both["validation_own_world"]
    assert pooled["all"]["n"] == 2 * own_jobs["all"]["n"] == 2 * rep_alone["validation"]["all"]["n"]  # both worlds' jobs
    assert pooled["all"]["mis-sort"] <= 0.01 and pooled["by_kind"]["untouched"]["reject"] > 0.3
    # the validation fabrics alone chose a sum rule: its scalars (the open-set threshold in the same
    # whitened units) on the fold's jobs are what that choice does there - misnamed fabrics into wrong bins
    assert alone.item_rule == "sum"
    assert _on(alone, fold, 2 + dc.WORLD_SEED_STEP)["mis-sort"] > 0.05
    assert both.classes == tuple(own.touched + untouched)  # deployed on the split's own touched means


@pytest.fixture(scope="module")
def tiny_world():
    from test_bundle_fixtures import tiny_world as shared_tiny_world

    return shared_tiny_world()


def test_train_refuses_folds_a_split_cannot_give(tmp_path, tiny_world, capsys):
    from vs2t_edge.cli import main
    from vs2t_edge.train import run as tr

    for bad in ("1", "4", "-2"):  # the tiny world's splits train on 6 touched fabrics: 2 or 3 folds
        assert main(["train", str(tiny_world), "--profile", "tiny", "--validation-folds", bad,
                     "--out", str(tmp_path / "no")]) == 2
        assert "give 0 (none) or 2 to 3" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--validation-folds 4"):
        tr.train(tiny_world, tmp_path / "no", profile="tiny", validation_folds=4)
    assert not (tmp_path / "no").exists()


def test_a_profiles_own_folds_shrink_to_what_a_split_can_give():
    """The paper profile's 4 folds are no request: with ``--touched 5`` a split makes 2 folds, with 3
    none; a world of 20 fabrics (14 touched) keeps 4. A count given on the command line is refused."""
    from vs2t_edge.train.run import PROFILES, folds_problem, profile_folds

    paper = PROFILES["paper"]
    assert paper.validation_folds == 4 and profile_folds(50, paper) == 4
    assert [profile_folds(50, replace(paper, touched=t)) for t in (3, 5, 7, 8)] == [0, 2, 3, 4]
    assert profile_folds(20, paper) == 4 and profile_folds(10, paper) == 3
    assert "give 0 (none) or 2 to 2" in folds_problem(50, replace(paper, touched=5), "DS")


def test_training_chooses_on_its_folds_and_says_so(tmp_path, tiny_world, monkeypatch, capsys):
    from vs2t_edge.train import run as tr

    monkeypatch.setitem(tr.PROFILES, "tiny", replace(tr.PROFILES["tiny"], steps=20, cls_steps=20,
                                                     n_synth_per_class=20, ft_epochs=1))
    tuned_on = []  # the touched fabrics each tail fine-tuning read

    def finetune_split(cache, trunk, split, **kw):
        tuned_on.append((list(split.touched), kw.get("tactile"), split.seed))
        weights.append(kw.get("attributes"))
        return real_finetune_split(cache, trunk, split, **kw)

    weights = []  # the attribute task's weight each fine-tuning got: the run's, in every fold too
    real_finetune_split = tr.ft.finetune_split
    monkeypatch.setattr(tr.ft, "finetune_split", finetune_split)
    m = tr.train(tiny_world, tmp_path / "run", profile="tiny", seed=3, figures=False, validation_folds=3,
                 ft_attributes=0.5)
    assert weights == [0.5] * 4 and m["profile"]["ft_attributes"] == 0.5
    chosen = m["splits"][0]["scene_decision"]["validation"]
    # the split's tail, then one per fold on the kept touched fabrics alone: no fold's held-out fabric
    # was told apart from its siblings by a tail that read its label (train/folds.py)
    split_touched, seed = m["splits"][0]["split"]["touched"], m["splits"][0]["split"]["seed"]
    assert tuned_on[0][0] == split_touched and len(tuned_on) == 4
    # fold i's tail left out exactly fold i's held-out fabrics (fold_worlds' own assignment)
    held = [sorted(set(split_touched) - set(kept)) for kept, _, _ in tuned_on[1:]]
    assert held == [sorted(split_touched[j] for j in fold) for fold in fold_assignment(len(split_touched), 3, seed)]
    assert all(tactile and s == seed for _, tactile, s in tuned_on)
    # the split's own 2 validation fabrics, then 3 folds of its 6 touched fabrics, 2 held out each
    assert chosen["validation_worlds"] == [{"touched": 6, "validation_fabrics": 2}] + \
        [{"touched": 4, "validation_fabrics": 2}] * 3
    assert m["profile"]["validation_folds"] == 3
    err = capsys.readouterr().err
    assert "validation fold 3/3: own fine-tuning and generator on 4 touched fabrics, 2 held out" in err
    assert "(4 world(s), 8 validation fabrics)" in err
    # the operating point the validation fabrics alone choose is priced beside it, on the same test jobs
    rows = {r["value"]: r for r in m["splits"][0]["scene_decision"]["test"]["knobs"] if r["knob"] == "validation_folds"}
    assert set(rows) == {0.0, 3.0} and rows[3.0]["own"] and not rows[0.0]["own"]
    assert rows[3.0]["right"] == m["splits"][0]["scene_decision"]["test"]["all"]["right"]
    report = (tmp_path / "run" / "report.md").read_text()
    assert "| validation folds (`train --validation-folds`" in report and "| 3 (own) |" in report
    assert "8 validation fabrics per split on average (the split's 2 validation fabrics and 3 folds" in report


def test_the_own_worlds_summary_is_the_deployed_rule_on_its_jobs(monkeypatch):
    """With folds the report says what the choice does on the split's own validation jobs: the
    deployed rule there, a sum rule's outlier presses judged by its labels rule's press spread as
    the search judged them (the first version priced it without, and reported another rule)."""
    monkeypatch.setattr(dc, "OUTLIER_RATIOS", (3.0, 1.5))  # so that the chosen sum rule leaves presses out
    rng = np.random.default_rng(3)
    own, fold = _world(rng, 8, 4), _world(rng, 8, 5)
    synth_u = rng.normal(0, 3.0, (80, 16)), np.repeat(np.arange(2), 40)
    model, rep = dc.fit_scene_decision(own.train_x, own.train_y, own.touched, own.touched_val, own.val_fabrics,
                                       own.val_presses, own.synth_val, ["u0", "u1"], synth_u, seed=2, folds=[fold])
    assert model.item_rule == "sum" and model.outlier_ratio == 3.0 and model.labels_rule
    assert rep["validation_own_world"]["all"] == pytest.approx(_on(model, own, 2))


def test_a_folds_generator_is_the_methods_kind_ensemble_and_all():
    import torch

    from vs2t_edge.train import vs2t
    from vs2t_edge.train.folds import fold_worlds

    rng = np.random.default_rng(0)
    n_t, d = 6, 8
    x = rng.normal(size=(n_t * 12, d)).astype(np.float32)
    train = ZSLData(x_t=x, x_v=x[::-1].copy(), y=np.repeat(np.arange(n_t), 12),
                    attr_t=rng.integers(0, 2, (n_t, 4)).astype(float), attr_u=np.ones((2, 4)),
                    v_u=rng.normal(size=(10, d)).astype(np.float32), v_u_class=np.repeat(np.arange(2), 5),
                    names_t=[f"t{i}" for i in range(n_t)], names_u=["u0", "u1"])
    touched_val = (x[:18] + 0.1, x[:18] - 0.1, np.repeat(np.arange(n_t), 3))
    budget = vs2t.VS2TBudget(steps=2, batch=8, cls_steps=2, n_synth_per_class=5, hidden=16, latent=4, ensemble=3)
    cls = vs2t.variant_class("VS2T-ZSL")
    torch.manual_seed(0)
    method = cls().fit(train, budget, seed=1000)
    before = len(cls.instances)
    worlds = fold_worlds(method, train, touched_val, budget, n_folds=2, seed=1000)
    assert len(cls.instances) == before  # the split's fitted method stays the one the run keeps
    for w in worlds:  # three members' samples per held-out fabric, as the split's own syntheses pool
        assert np.bincount(w.synth_val[1]).tolist() == [3 * budget.n_synth_per_class] * len(w.val_fabrics)

    # with ``features``, fold i asks for features without its own held-out fabrics, and its world's
    # pieces and touched part are those features, not the split's
    asked = []

    def features(held_names):
        asked.append(held_names)
        shift = 100.0 * len(asked)  # each fold's features told apart from the split's and each other's
        return replace(train, x_t=train.x_t + shift), (touched_val[0] + shift, touched_val[1], touched_val[2])

    worlds = fold_worlds(method, train, touched_val, budget, n_folds=2, seed=1000, features=features)
    folds = fold_assignment(n_t, 2, 1000)
    assert asked == [[train.names_t[j] for j in fold] for fold in folds]
    for i, (w, fold) in enumerate(zip(worlds, folds)):
        kept = np.setdiff1d(np.arange(n_t), fold)
        assert w.val_fabrics == [train.names_t[j] for j in fold] and w.touched == [train.names_t[j] for j in kept]
        assert np.array_equal(w.train_x, train.x_t[np.isin(train.y, kept)] + 100.0 * (i + 1))
        assert np.all(w.val_presses[0] >= 50.0) and np.all(w.touched_val[0] >= 50.0)
    with pytest.raises(ValueError, match="other touched fabrics or rows"):
        fold_worlds(method, train, touched_val, budget, n_folds=2, seed=1000,
                    features=lambda held: (replace(train, y=train.y[::-1].copy()), touched_val))


def test_both_item_rules_searches_break_ties_towards_fewer_mis_sorts(monkeypatch):
    """``item_search.fewer_mis_sorts`` after the sum rule's search and after the offset rule's: on a
    world where each search meets its score at more than one setting, each rule's point mis-sorts
    fewer validation pieces than the one the search alone keeps, at a score no lower."""
    from vs2t_edge.train import item_search as ns

    # on this world the likeness rule's knob (added later) gives the offset search a point without
    # mis-sorts by itself; held off, the world still shows what the tie-break pass is for
    monkeypatch.setitem(ns.OFFSET_GRID, "likeness_ratio", (math.inf,))
    rng = np.random.default_rng(4)
    own, fold = _world(rng, 8, 4), _world(rng, 8, 9, misnamed=4)
    synth_u = rng.normal(0, 3.0, (80, 16)), np.repeat(np.arange(2), 40)
    args = (own.train_x, own.train_y, own.touched, own.touched_val, own.val_fabrics, own.val_presses, own.synth_val,
            ["u0", "u1"], synth_u)
    _, with_pass = dc.fit_scene_decision(*args, seed=2, folds=[fold])
    monkeypatch.setattr(ns, "fewer_mis_sorts", lambda point, grid, rank: dict(point))
    _, without = dc.fit_scene_decision(*args, seed=2, folds=[fold])
    for rule in ("sum", "offset"):
        a, b = with_pass["item_rules"][rule], without["item_rules"][rule]
        assert a["mis_sort"] < b["mis_sort"], (rule, a, b)
        score = {name: dc._score({"all": {"mis-sort": r["mis_sort"], "right": r["right"]}}, 0.01)
                 for name, r in (("with", a), ("without", b))}
        assert score["with"] >= score["without"], (rule, a, b)


def test_the_outlier_ratio_breaks_ties_towards_fewer_mis_sorts(monkeypatch):
    """Of the outlier ratios that sort as many validation pieces right, the one with the fewest
    mis-sorts (the first of those: a full tie leaves the rule off)."""
    rng = np.random.default_rng(0)
    x = rng.normal(0, 1, (60, 8))
    model = replace(SceneModel.fit(x, np.repeat(np.arange(3), 20), ["a", "b", "c"], x[:20], np.zeros(20, int), ["u"],
                                   k=4), item_rule="offset")
    by_ratio = {50.0: 0.004, 20.0: 0.004}  # mis-sorts; every other ratio 0.008, all at 70 % right

    def summary(ratio):
        return {"all": {"right": 0.7, "mis-sort": by_ratio.get(ratio, 0.008), "reject": 0.3 - by_ratio.get(ratio, 0.008),
                        "presses": 3.0}}
    monkeypatch.setattr(dc, "press_tables", lambda m, rows: None)
    monkeypatch.setattr(dc, "_simulate", lambda models, jobs, tables=None: summary(models[0].outlier_ratio))
    jobs = [type("Jobs", (), {"rows": {}})()]
    best, _, rows = dc._outlier_rule([model], summary(math.inf), [model], jobs, 0.01)
    assert best[0].outlier_ratio == 50.0 and len(rows) == len(dc.OUTLIER_RATIOS)
    by_ratio.clear()  # a full tie: the rule stays off
    assert math.isinf(dc._outlier_rule([model], summary(math.inf), [model], jobs, 0.01)[0][0].outlier_ratio)

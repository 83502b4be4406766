"""int8 (issue 14): trunk nodes kept in float really stay float in the graph onnxruntime runs;
the sensitivity scan measures what each buys back; calibration reads only training presses of
touched fabrics and the scan only held-out ones (never test, never untouched); the bench pairs
int8 with fp32 on the same presses and states the noise."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from test_bundle_fixtures import world_frames
from test_export import tiny_run  # noqa: F401  (the module fixture: a run folder on the tiny world)
from vs2t_edge.bench import paired as pr
from vs2t_edge.export import export as ex, from_run as fr
from vs2t_edge.export.calibration import PressLeak, calibration_presses, sensitivity_presses
from vs2t_edge.export.quantize import Quantiser, _float_tail_nodes, layer_sensitivity, quantize_trunk_static, run_graph


@pytest.fixture(scope="module")
def tiny_fp32(tmp_path_factory):
    """The tiny trunk (3 convs) as an fp32 ONNX graph, and world frames."""
    from vs2t_edge.train.trunks import build_trunk

    torch.manual_seed(0)
    trunk = build_trunk("tiny").eval()
    x, _, _ = world_frames(64)
    path = tmp_path_factory.mktemp("q") / "trunk_fp32.onnx"
    ex.export_onnx(trunk, torch.from_numpy(x[:1]), path, "image", ["feature"])
    return path, x


def _float_convs_after_ort(path: Path, tmp: Path) -> tuple[int, int]:
    """(Conv on float weights, integer QLinearConv) nodes in the graph onnxruntime actually runs
    (its optimisers applied, as the cell's session applies them); no Conv on dequantised weights."""
    import onnx
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    so.optimized_model_filepath = str(tmp / "optimised.onnx")
    ort.InferenceSession(str(path), sess_options=so, providers=["CPUExecutionProvider"])
    g = onnx.load(str(tmp / "optimised.onnx")).graph
    floats = {i.name for i in g.initializer if i.data_type == onnx.TensorProto.FLOAT}
    convs = [n for n in g.node if n.op_type in ("Conv", "FusedConv")]
    assert all(n.input[1] in floats for n in convs), "a Conv runs on weights onnxruntime quantised"
    assert not [n for n in g.node if n.op_type == "DequantizeLinear" and not any(
        n.output[0] in m.input for m in g.node) and n.output[0] not in {o.name for o in g.output}], "a dangling DQ"
    return len(convs), sum(n.op_type == "QLinearConv" for n in g.node)


def _weight_is_dequantised(model, node_name: str) -> bool:
    producers = {o: n for n in model.graph.node for o in n.output}
    node = next(n for n in model.graph.node if n.name == node_name)
    src = producers.get(node.input[1])
    return src is not None and src.op_type == "DequantizeLinear"


def test_float_nodes_stay_float_in_the_graph_onnxruntime_runs(tiny_fp32, tmp_path):
    import onnx

    path, x = tiny_fp32
    cal = x[:24]
    all8, mixed = tmp_path / "all8.onnx", tmp_path / "mixed.onnx"
    rep0 = quantize_trunk_static(path, all8, cal)
    with Quantiser(path, cal) as q:
        convs = [n for n in q.order if q.nodes[n] == "Conv"]
    assert len(convs) == 3
    keep = [convs[1]]
    rep = quantize_trunk_static(path, mixed, cal, float_nodes=keep)
    assert rep["float_nodes_chosen"] == keep and rep["float_nodes"] == rep0["float_nodes"] + 1
    m8, mm = onnx.load(str(all8)), onnx.load(str(mixed))
    assert all(_weight_is_dequantised(m8, c) for c in convs)
    assert not _weight_is_dequantised(mm, convs[1])  # float weights, float kernel
    assert _weight_is_dequantised(mm, convs[0]) and _weight_is_dequantised(mm, convs[2])
    # what onnxruntime runs: all three convs integer, or two integer and the kept one float
    assert _float_convs_after_ort(all8, tmp_path) == (0, 3)
    assert _float_convs_after_ort(mixed, tmp_path) == (1, 2)


def test_a_residual_add_kept_in_float_is_not_fused_back(tmp_path):
    """A residual Add left out of quantisation runs as a float Add, not QLinearAdd (its inputs'
    channel counts come from the float graph: the quantiser's tensors carry no shapes)."""
    import onnx
    import onnxruntime as ort

    class Res(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.a = torch.nn.Conv2d(3, 8, 3, padding=1)
            self.b = torch.nn.Conv2d(8, 8, 1)
            self.c = torch.nn.Conv2d(8, 8, 1)

        def forward(self, x):
            y = torch.relu(self.a(x))
            return self.c(y + self.b(y)).mean((2, 3))

    torch.manual_seed(0)
    x = np.random.default_rng(0).standard_normal((16, 3, 16, 16)).astype(np.float32)
    ex.export_onnx(Res().eval(), torch.from_numpy(x[:1]), tmp_path / "r.onnx", "image", ["feature"])
    with Quantiser(tmp_path / "r.onnx", x) as q:
        (add,) = [n for n in q.order if q.nodes[n] == "Add"]

    def ops(path):
        so = ort.SessionOptions()
        so.optimized_model_filepath = str(tmp_path / "opt.onnx")
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
        ort.InferenceSession(str(path), sess_options=so, providers=["CPUExecutionProvider"])
        return [n.op_type for n in onnx.load(str(tmp_path / "opt.onnx")).graph.node]

    quantize_trunk_static(tmp_path / "r.onnx", tmp_path / "all8.onnx", x)
    quantize_trunk_static(tmp_path / "r.onnx", tmp_path / "mixed.onnx", x, float_nodes=[add])
    assert "QLinearAdd" in ops(tmp_path / "all8.onnx")
    mixed = ops(tmp_path / "mixed.onnx")
    assert "QLinearAdd" not in mixed and "Add" in mixed and mixed.count("QLinearConv") >= 2


def test_unknown_float_node_is_refused_by_name(tiny_fp32, tmp_path):
    path, x = tiny_fp32
    with pytest.raises(ValueError, match="not in the trunk graph: /no/such/Conv"):
        quantize_trunk_static(path, tmp_path / "q.onnx", x[:8], float_nodes=["/no/such/Conv"])
    with pytest.raises(ValueError, match="sensitivity frames"):
        quantize_trunk_static(path, tmp_path / "q.onnx", x[:8], float_auto=1)


def test_sensitivity_scan_measures_what_each_node_buys_back(tiny_fp32):
    """Every candidate is measured against the all-int8 trunk; everything float is fp32 again;
    the scan ranks by what it was asked to reduce."""
    path, x = tiny_fp32
    cal, held = x[:24], x[24:]
    with Quantiser(path, cal) as q:
        tail = _float_tail_nodes(q.model)
        res = layer_sensitivity(q, held, tail=tail)
        cands = q.candidates(tail)
        assert {r["node"] for r in res["rows"]} == set(cands) and res["frames"] == len(held)
        assert res["all_int8"]["mse"] > 0
        gains = [r["buys_back"] for r in res["rows"]]
        assert gains == sorted(gains, reverse=True)
        for r in res["rows"]:
            assert r["buys_back"] == pytest.approx(res["all_int8"]["mse"] - r["mse"])
        q.write(q.tmp / "none.onnx", tail + cands)  # nothing left to quantise: the fp32 features
        f32, f = run_graph(q.pre, held), run_graph(q.tmp / "none.onnx", held)
        assert np.max(np.abs(f - f32)) <= 1e-4 * np.max(np.abs(f32))
        ranked = layer_sensitivity(q, held, tail=tail, score=lambda a, b: {"neg": -float(np.mean((a - b) ** 2))},
                                   rank_by="neg")
        negs = [r["neg"] for r in ranked["rows"]]  # lower is better: ranked by what it reduces
        assert ranked["metric"] == "neg" and negs == sorted(negs)
        with pytest.raises(ValueError, match="rank_by"):
            layer_sensitivity(q, held, tail=tail, candidates=cands[:1], rank_by="nope")


PART = {"a": {"train": [0, 1, 2, 3, 4, 5], "val": [6, 7], "test": [8, 9], "unused": [10]},
        "b": {"train": [0, 2, 4], "val": [5], "test": [6], "unused": []}}


@pytest.mark.parametrize("n", [0, 1, 2, 4, 5, 9, 100])
def test_calibration_presses_are_training_presses_of_touched_fabrics(n):
    got = calibration_presses(PART, ["a", "b"], n, untouched=["u"])
    for f, idx in got.items():
        assert set(idx) <= set(PART[f]["train"]) and len(set(idx)) == len(idx)
    total = sum(map(len, got.values()))
    assert total == (9 if n <= 0 or n >= 9 else n)
    with pytest.raises(PressLeak, match="untouched fabric"):
        calibration_presses(PART, ["a", "u"], n, untouched=["u"])
    with pytest.raises(PressLeak, match="no training presses"):
        calibration_presses(PART, ["a", "v"], n)


def test_sensitivity_presses_are_held_out_never_train_or_test():
    got = sensitivity_presses(PART, ["a", "b"], {"v": 30}, untouched=["u"], per_fabric=5)
    assert got["a"] == [6, 7] and got["b"] == [5] and len(got["v"]) == 5
    with pytest.raises(PressLeak, match="untouched"):
        sensitivity_presses(PART, ["a"], {"u": 10}, untouched=["u"])
    with pytest.raises(PressLeak, match="also a touched"):
        sensitivity_presses(PART, ["a"], {"b": 10})


def test_export_reads_no_untouched_or_test_press_and_ships_the_chosen_float_nodes(tiny_run, tmp_path, monkeypatch):  # noqa: F811
    """int8 export with the sensitivity scan: every press it reads is a touched fabric's training
    or held-out press or a validation fabric's press; the calibration set recorded in the
    manifest is training presses only; the nodes it picked are float in the shipped graph."""
    import onnx

    from vs2t_edge.runtime import dataset as dsm

    run, art = tiny_run
    reads: list[tuple[str, int]] = []
    orig = dsm.Fabric.load_press

    def spy(self, i, *a, **k):
        reads.append((self.id, int(i)))
        return orig(self, i, *a, **k)

    monkeypatch.setattr(dsm.Fabric, "load_press", spy)
    out = tmp_path / "b8"
    m = fr.export_run(run, out, trunk_precision="int8", calibration_frames=12, float_auto=1)
    part = m["provenance"]["data"]["touched_presses"]
    assert reads and not {f for f, _ in reads} & set(art.untouched)
    for f, i in reads:
        if f in part:
            assert i not in part[f]["test"] and i not in part[f]["unused"], (f, i)
        else:
            assert f in art.validation
    cal = m["provenance"]["data"]["calibration_presses"]
    assert sum(map(len, cal.values())) == 12
    assert all(set(idx) <= set(part[f]["train"]) for f, idx in cal.items())
    q = m["graphs"]["trunk"]["quantisation"]
    (kept,) = q["float_nodes_chosen"]
    assert q["sensitivity"]["metric"] == "logit_error" and q["sensitivity"]["top"][0]["node"] == kept
    assert not _weight_is_dequantised(onnx.load(str(out / "trunk.onnx")), kept)


def test_export_cli_float_node_options(tiny_run, tmp_path, capsys):  # noqa: F811
    from vs2t_edge.cli import main
    from vs2t_edge.export.cli import parse_float_nodes

    run, _ = tiny_run
    assert main(["export", str(run), "--out", str(tmp_path / "b"), "--int8-float-auto", "2"]) == 2
    assert "need --trunk-precision int8" in capsys.readouterr().err
    assert main(["export", str(run), "--out", str(tmp_path / "b"), "--trunk-precision", "int8",
                 "--int8-float-nodes", "/no/such/Conv", "--calibration-frames", "8"]) == 2
    assert "not in the trunk graph" in capsys.readouterr().err
    (tmp_path / "s.json").write_text(json.dumps({"recommended": ["x", "y"]}))
    assert parse_float_nodes(f"@{tmp_path / 's.json'}") == ["x", "y"]
    assert parse_float_nodes(" a, b ,") == ["a", "b"]
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match="recommended"):
        parse_float_nodes(f"@{tmp_path / 'bad.json'}")


def test_export_cli_int8_recipe_fills_what_is_left_out(faithful_run, tmp_path, capsys):
    """`--trunk-precision int8` alone exports with INT8_RECIPE (percentile ranges, the float nodes the
    sensitivity scan picks, fp32's operating point kept); each option given wins over the recipe."""
    import argparse

    from vs2t_edge.cli import main
    from vs2t_edge.export import cli as ec

    p = argparse.ArgumentParser()
    ec.add_arguments(p, "export")
    assert ec.run_options(p.parse_args(["r", "--out", "o"])) == {
        "calibration_frames": ec.FP32_CALIBRATION_FRAMES, "int8_calibration": "minmax", "int8_float_auto": 0,
        "int8_keep_operating_point": False, "int8_scene_means": False}
    assert ec.run_options(p.parse_args(["r", "--out", "o", "--trunk-precision", "int8"])) == ec.INT8_RECIPE
    given = ec.run_options(p.parse_args(["r", "--out", "o", "--trunk-precision", "int8", "--int8-calibration", "minmax",
                                         "--no-int8-keep-operating-point", "--int8-float-auto", "0",
                                         "--no-int8-scene-means"]))
    assert given["int8_calibration"] == "minmax" and given["int8_float_auto"] == 0
    assert given["int8_keep_operating_point"] is False and given["int8_scene_means"] is False
    assert given["calibration_frames"] == ec.INT8_RECIPE["calibration_frames"]
    assert main(["export", "r", "--out", str(tmp_path / "x"), "--int8-calibration", "percentile"]) == 2
    assert "need --trunk-precision int8" in capsys.readouterr().err

    run, _ = faithful_run
    out = tmp_path / "b8"
    assert main(["export", str(run), "--out", str(out), "--trunk-precision", "int8", "--calibration-frames", "12"]) == 0
    m = json.loads((out / "manifest.json").read_text())
    q = m["graphs"]["trunk"]["quantisation"]
    assert q["calibration"] == "percentile" and "sensitivity" in q
    assert 0 < len(q["float_nodes_chosen"]) <= ec.INT8_RECIPE["int8_float_auto"]
    assert "moved for int8" in m["operating_point"]
    assert m["checks"]["int8_scene_means"]["classes"] == len(m["classes"]["touched"]) + 2  # and 2 known-only


# ------------------------------------------------ the bench: int8 and fp32 paired


def test_mcnemar_exact():
    assert pr.mcnemar_p(0, 0) == 1.0
    assert pr.mcnemar_p(0, 10) == pytest.approx(2 / 1024)
    assert pr.mcnemar_p(5, 5) == 1.0
    assert pr.mcnemar_p(3, 9) == pytest.approx(pr.mcnemar_p(9, 3))


def _view(lp_shift: np.ndarray | None = None, beta: float = 0.0) -> dict:
    """3 touched + 2 untouched classes, 10 presses each; every press right and routed right."""
    rng = np.random.default_rng(0)
    lab = np.repeat(np.arange(5), 10)
    lp = np.full((50, 5), -10.0)
    lp[np.arange(50), lab] = 0.0
    lsu = np.full((50, 2), -5.0)
    lsu[lab >= 3, lab[lab >= 3] - 3] = 0.0
    nov = np.where(lab < 3, -1.0, 1.0) + 0.01 * rng.standard_normal(50)
    if lp_shift is not None:
        lp = lp + lp_shift
    out = {"label": lab, "lp": lp, "lsu": lsu, "novelty": nov, "feature": np.zeros((50, 4), np.float32)}
    return {"beta": beta, "ct": 3, "classes": list("abcde"), "touched": list("abc"), "untouched": list("de"),
            "scene_model": None, "out": out}


def test_paired_press_counts_flips_and_its_interval_holds_the_truth():
    same = pr.paired_press(_view(), _view(), n_boot=200)
    for k in ("acc_t", "zsl", "acc_u", "H"):
        assert same[k]["delta"] == 0 and same[k]["ci95"] == [0.0, 0.0]
    assert same["acc_t"]["flips_worse"] == same["acc_t"]["flips_better"] == 0
    shift = np.zeros((50, 5))
    shift[[0, 1, 2], 1] = 20.0  # int8 moves 3 presses of class a to class b
    d = pr.paired_press(_view(), _view(shift), n_boot=200)["acc_t"]
    assert d["flips_worse"] == 3 and d["flips_better"] == 0 and d["presses"] == 30
    assert d["delta"] == pytest.approx(-100 * (3 / 10) / 3)  # per-class mean over 3 touched classes
    assert d["ci95"][0] < d["delta"] <= d["ci95"][1] <= 0
    assert d["mcnemar_p"] == pytest.approx(0.25)
    other = _view()
    other["out"] = dict(other["out"], label=np.roll(other["out"]["label"], 1))
    with pytest.raises(ValueError, match="same presses"):
        pr.paired_press(_view(), other)


def test_paired_items_mcnemar_counts_one_flipped_press_once():
    """The bench's items share their fabric's presses: one press that flips flips every item showing
    it. The exact McNemar test on items counted it once per item (49 items, p 4e-15, where the press
    itself has p 1.0); clustered by fabric it is one cluster's evidence."""
    shift = np.zeros((50, 5))
    shift[0, 1] = 60.0  # int8 moves ONE press of class a to class b
    assert pr.paired_press(_view(), _view(shift), n_boot=50)["acc_t"]["mcnemar_p"] == 1.0
    d = pr.paired_items(_view(), _view(shift), n_items=100, n_boot=50)["item5_H"]
    assert d["flips_worse"] > 20 and d["flips_better"] == 0
    assert d["mcnemar_p"] > 0.3
    # and its interval: one press apart is inside the noise (items resampled within the fabric
    # gave -8.9 [-11.1, -7.1]; fabrics, each with all its items, hold 0)
    lo, hi = d["ci95"]
    assert d["delta"] < 0 and lo < d["delta"] <= hi and hi >= 0
    # clusters of one pair each: the classic McNemar, (b - c)^2 / (b + c)
    assert pr.mcnemar_clustered_p(np.r_[np.ones(9), np.zeros(3)], np.r_[np.zeros(9), np.ones(3)],
                                  np.arange(12)) == pytest.approx(math.erfc(math.sqrt(3.0 / 2)))
    assert pr.mcnemar_clustered_p(np.zeros(4), np.zeros(4), np.arange(4)) == 1.0


def test_paired_numbers_are_the_bench_accuracy_numbers():
    """The paired comparison recomputes the bench's own per-press and per-item numbers (same
    presses, same items): its fp32 and int8 columns must equal accuracy()'s for each bundle."""
    from types import SimpleNamespace

    from vs2t_edge.bench.accuracy import accuracy

    rng = np.random.default_rng(1)
    views = []
    for noise in (0.0, 3.0):
        v = _view(rng.normal(0, 1 + noise, (50, 5)))
        v["out"]["lsu"] = v["out"]["lsu"] + rng.normal(0, 4, (50, 2))
        v["out"]["novelty"] = v["out"]["novelty"] + rng.normal(0, 0.8, 50)
        views.append(v)
    got = pr.paired(*views, n_boot=50, n_items=20)
    for v, col in zip(views, ("fp32", "int8")):
        model = SimpleNamespace(touched=v["touched"], untouched=v["untouched"], classes=v["classes"],
                                beta=v["beta"], scene_model=None)
        acc = accuracy(model, v["out"], n_items=20)
        for k in ("zsl", "acc_t", "acc_u", "H"):
            assert got["press"][k][col] == pytest.approx(acc["press"][k])
        assert got["items"]["item5_H"][col] == pytest.approx(acc["items"]["5"]["H"])
        assert got["items"]["sequential_H"][col] == pytest.approx(acc["sequential"]["H"])


def test_matched_beta_keeps_fp32s_touched_kept_rate():
    """int8 noise shifts the router's scores; the moved beta keeps the same share of held-out
    touched presses touched on the int8 graph as fp32 keeps at the run's beta."""
    rng = np.random.default_rng(0)
    nov32 = rng.normal(0, 1, 160)
    beta = 0.7
    nov8 = nov32 * 1.5 + 0.4 + rng.normal(0, 0.05, 160)  # wider and shifted, as int8 makes them
    b8, kept = fr.matched_beta(nov32, nov8, beta)
    assert kept == pytest.approx(np.mean(nov32 <= beta))
    assert np.mean(nov8 <= b8) == pytest.approx(kept, abs=1 / 160)
    assert not np.any(nov8 == b8)  # midway between two scores, never on one
    assert np.mean(nov8 <= beta) < kept  # the run's beta would flag more touched presses
    lo, _ = fr.matched_beta(np.ones(5), np.arange(5.0), 0.0)  # fp32 keeps none: int8 keeps none
    assert np.all(np.arange(5.0) > lo)
    hi, _ = fr.matched_beta(np.zeros(5), np.arange(5.0), 1.0)  # fp32 keeps all: int8 keeps all
    assert np.all(np.arange(5.0) <= hi)


def test_export_int8_keeps_the_operating_point(tiny_run, tmp_path):  # noqa: F811
    run, art = tiny_run
    m = fr.export_run(run, tmp_path / "b8", trunk_precision="int8", calibration_frames=12,
                      int8_keep_operating_point=True)
    op = m["provenance"]["int8_operating_point"]
    assert op["run_beta"] == art.beta and m["beta"] == op["beta"] and 0 <= op["touched_kept"] <= 1
    assert "moved for int8" in m["operating_point"]


# ------------------------------------------------ the scene model's real means on the int8 trunk


@pytest.fixture(scope="module")
def faithful_run(tiny_run, tmp_path_factory):  # noqa: F811
    """``tiny_run`` with a scene model fitted as training fits one: touched means from each touched
    fabric's training presses (through the run's own trunk), two synthesised classes drawn near two
    of them, and the validation fabrics known only to refuse (train/decision.py ``with_known``)."""
    from dataclasses import replace

    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.scene_model import SceneModel
    from vs2t_edge.train.artifacts import build_modules, save_run_artifacts
    from vs2t_edge.train.decision import with_known

    _, art = tiny_run
    ds = load_dataset(art.dataset)
    trunk, _, _ = build_modules(art)
    part = fr.press_partition({f.id: len(f.presses) for f in ds.fabrics}, art.touched, 0, None)

    def feats(fid, idx):
        with torch.no_grad():
            return trunk(torch.from_numpy(fr._frames(ds, fid, idx, art.tactile_preprocess))).numpy()

    z = np.concatenate([feats(f, part[f]["train"]) for f in art.touched])
    y = np.concatenate([np.full(len(part[f]["train"]), i) for i, f in enumerate(art.touched)])
    rng = np.random.default_rng(0)
    synth = np.concatenate([z[y == c].mean(0) + rng.normal(0, 0.5, (20, z.shape[1])) for c in (0, 3)])
    scene = replace(SceneModel.fit(z, y, art.touched, synth, np.repeat([0, 1], 20), art.untouched, k=16),
                    temperature=2.0, untouched_bias=0.5, confidence=0.9, untouched_confidence=0.9)
    xv = [feats(f, range(len(ds.by_id(f).presses))) for f in art.validation]
    scene, _ = with_known(scene, np.concatenate(xv), np.concatenate([np.full(len(x), i) for i, x in enumerate(xv)]),
                          list(art.validation))
    art = replace(art, scene_model=scene.to_params())
    run = tmp_path_factory.mktemp("faithful_run")
    save_run_artifacts(run, art)
    return run, art


def test_int8_export_moves_real_scene_means_by_the_int8_shift_of_their_own_training_presses(faithful_run, tmp_path,
                                                                                             monkeypatch):
    """With int8_scene_means each real class mean - touched and known-only - moves by mean(int8) -
    mean(fp32) of the training presses it was fitted on, projected; the synthesised means stay the
    generator's; every press read is such a training press; without it the means are training's."""
    from vs2t_edge.runtime import dataset as dsm
    from vs2t_edge.runtime.dataset import load_dataset, press_partition
    from vs2t_edge.runtime.inference import TactileModel
    from vs2t_edge.runtime.scene_model import SceneModel

    run, art = faithful_run
    stored = SceneModel.from_params(art.scene_model)
    assert stored.known_only == tuple(art.validation)
    plain = fr.export_run(run, tmp_path / "plain", trunk_precision="int8", calibration_frames=12)
    assert "int8_scene_means" not in plain["checks"]
    assert plain["checks"]["int8_scene_decision_on_validation"]["means_moved"] is False
    reads: list[tuple[str, int]] = []
    orig = dsm.Fabric.load_press
    monkeypatch.setattr(dsm.Fabric, "load_press", lambda self, i, *a, **k: reads.append((self.id, int(i))) or
                        orig(self, i, *a, **k))
    m = fr.export_run(run, tmp_path / "moved", trunk_precision="int8", calibration_frames=12, int8_scene_means=True)
    monkeypatch.undo()
    ds = load_dataset(art.dataset)
    part = m["provenance"]["data"]["touched_presses"]
    src = m["provenance"]["data"]["int8_scene_mean_presses"]
    assert set(src) == set(art.touched) | set(art.validation)
    assert all(src[f] == part[f]["train"] for f in art.touched)
    for f in art.validation:  # with_known's presses: the first part of each fabric's presses in press order
        assert src[f] == list(press_partition(len(ds.by_id(f).presses))[0])
    assert not {f for f, _ in reads} & set(art.untouched)
    assert all(i not in part[f]["test"] and i not in part[f]["unused"] for f, i in reads if f in part)
    check = m["checks"]["int8_scene_means"]
    assert check["classes"] == len(src) and check["presses"] == sum(map(len, src.values()))
    assert check["fp32_reread_rms_per_dim_max"] < 1e-3  # the presses training fitted the means on
    assert "moved to where the int8 trunk puts" in m["decision"]["rule"]
    assert m["checks"]["int8_scene_decision_on_validation"]["means_moved"] is True

    b32 = tmp_path / "b32"
    fr.export_run(run, b32, trunk_precision="fp32", calibration_frames=12)
    m32, m8 = TactileModel.load(b32, threads=1), TactileModel.load(tmp_path / "moved", threads=1)
    np.testing.assert_allclose(TactileModel.load(tmp_path / "plain", threads=1).scene_model.means, stored.means,
                               atol=1e-12)
    moved = m8.scene_model.means
    for fid, idx in src.items():
        x = fr._frames(ds, fid, idx, m8.preprocess_spec)
        z8, z32 = (stored.project(mm.forward(x).feature).mean(0) for mm in (m8, m32))
        row = stored.classes.index(fid)
        np.testing.assert_allclose(moved[row], stored.means[row] + z8 - z32, atol=1e-4)
        assert np.abs(z8 - z32).max() > 1e-3  # int8 did move this fabric's presses
    for fid in art.untouched:
        row = stored.classes.index(fid)
        np.testing.assert_array_equal(moved[row], stored.means[row])


def test_int8_export_refuses_to_move_means_its_presses_do_not_give_back(tiny_run, tmp_path):  # noqa: F811
    """tiny_run's scene model was fitted on other frames than the run's training presses: moving
    its means would be a guess, so the export says which class and how to go on."""
    run, art = tiny_run
    with pytest.raises(ex.ExportError, match=r"re-read through the fp32 graph.*--no-int8-scene-means"):
        fr.export_run(run, tmp_path / "b", trunk_precision="int8", calibration_frames=12, int8_scene_means=True)
    assert not (tmp_path / "b").exists()


def test_shift_real_means_moves_by_the_shift_and_refuses_what_it_cannot_move(tiny_run):  # noqa: F811
    from vs2t_edge.export.int8_scene import shift_real_means
    from vs2t_edge.runtime.scene_model import SceneModel

    _, art = tiny_run
    sm = SceneModel.from_params(art.scene_model)
    c = art.touched[2]
    row = sm.classes.index(c)
    # presses whose fp32 features give back the stored mean exactly: the mean's preimage, repeated
    x = np.repeat(np.linalg.lstsq(sm.basis.T, sm.means[row], rcond=None)[0][None] + sm.center[None], 3, axis=0)
    offset = np.linspace(-0.05, 0.05, sm.dim)
    params, check = shift_real_means(art.scene_model, [(c, x)], lambda f: f, lambda f: f + offset)
    want = sm.means.copy()
    want[row] += offset @ sm.basis  # the projection is linear: the shift of the means is the offset's
    np.testing.assert_allclose(params["means"], want, atol=1e-9)
    assert check["classes"] == 1 and check["presses"] == 3 and check["fp32_reread_rms_per_dim_max"] < 1e-9
    same = lambda f: f  # noqa: E731
    with pytest.raises(ValueError, match="synthesised"):
        shift_real_means(art.scene_model, [(art.untouched[0], x)], same, same)
    with pytest.raises(ValueError, match="no class"):
        shift_real_means(art.scene_model, [("nope", x)], same, same)
    with pytest.raises(ValueError, match="no presses"):
        shift_real_means(art.scene_model, [(c, x[:0])], same, same)
    with pytest.raises(ValueError, match="no real class means"):
        shift_real_means(art.scene_model, [], same, same)
    with pytest.raises(ValueError, match="not the presses training fitted"):
        shift_real_means(art.scene_model, [(c, x + 1.0)], same, same)

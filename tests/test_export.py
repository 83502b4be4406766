"""export/: a run folder -> a bundle the runtime verifies; train/serve parity (torch vs
onnxruntime) within a stated tolerance; int8 calibrated on touched fabrics only; MACs counted."""
from __future__ import annotations

import json
import sys
from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from test_bundle_fixtures import tiny_world, world_frames
from vs2t_edge.export import export as ex, from_run as fr
from vs2t_edge.runtime import router_eval as reval
from vs2t_edge.runtime.inference import TactileModel


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A run folder as train/ writes it, with the tiny trunk on the tiny fabric world."""
    from vs2t_edge.runtime import novelty as nv
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import TactilePreprocess
    from vs2t_edge.runtime.scene_model import SceneModel
    from vs2t_edge.train.artifacts import RunArtifacts, save_run_artifacts
    from vs2t_edge.train.models import Classifier
    from vs2t_edge.train.trunks import build_trunk

    torch.manual_seed(0)
    ds = load_dataset(tiny_world())
    ids = ds.ids
    touched, untouched, validation = ids[:6], ids[6:8], ids[8:10]
    trunk = build_trunk("tiny").eval()
    x, _, _ = world_frames(64)
    with torch.no_grad():
        f = trunk(torch.from_numpy(x[: 6 * 9])).numpy()
    mean, std = f.mean(0), f.std(0) + 1e-3
    router = nv.fit_router("gaussian", (f - mean) / std, keep_covariance=False)
    # a scene model as train/decision.py deploys one: touched means from the touched presses above,
    # the untouched "synthesised" samples drawn near two of them (never an untouched press)
    z = (f - mean) / std
    y = np.repeat(np.arange(6), 9)
    rng = np.random.default_rng(0)
    synth = np.concatenate([z[y == c].mean(0) + rng.normal(0, 0.5, (20, 64)) for c in (0, 3)])
    scene = SceneModel.fit(z, y, touched, synth, np.repeat([0, 1], 20), untouched, k=16)
    scene = replace(scene, temperature=2.0, untouched_bias=0.5, evidence_weight=0.5, confidence=0.9,
                    untouched_confidence=0.9)
    art = RunArtifacts(trunk_arch="tiny", trunk_state=trunk.state_dict(), feature_dim=64,
                       preprocess=TactilePreprocess(size=64).to_dict(), feature_mean=mean, feature_std=std,
                       cls_t_state=Classifier(64, 6).state_dict(), touched=touched,
                       cls_u_state=Classifier(64, 2).state_dict(), untouched=untouched, router_name="gaussian",
                       router_params=router.to_params(), beta=float(np.median(router.novelty((f - mean) / std))),
                       validation=validation, dataset=str(tiny_world()), touched_fabric_ids=touched,
                       info={"split_seed": 0}, scene_model=scene.to_params())
    run = tmp_path_factory.mktemp("run")
    save_run_artifacts(run, art)
    return run, art


def test_export_run_fp32_and_int8_verify(tiny_run, tmp_path):
    run, art = tiny_run
    for prec in ("fp32", "int8"):
        out = tmp_path / f"b_{prec}"
        m = fr.export_run(run, out, trunk_precision=prec, calibration_frames=24)
        model = TactileModel.load(out, threads=1)
        assert list(model.touched) == art.touched and list(model.untouched) == art.untouched
        assert m["graphs"]["trunk"]["precision"] == prec and m["graphs"]["trunk"]["opset"] >= 17
        assert m["provenance"]["run"] == str(run.resolve()) and m["provenance"]["trained"] is True
        # calibration presses come only from touched fabrics, and only from their training presses
        data = m["provenance"]["data"]
        assert set(data["calibration_fabrics"]) <= set(art.touched)
        assert not set(data["calibration_fabrics"]) & set(art.untouched + art.validation)
        assert m["gating"]["temperature"] > 0 and m["gating"]["scale"] > 0
        # without --router: the run's stored router and beta, as before
        assert m["router"]["name"] == art.router_name and m["beta"] == art.beta
        assert m["provenance"]["router"]["refitted_at_export"] is False
        if prec == "int8":
            q = m["graphs"]["trunk"]["quantisation"]
            assert q["method"] == "static QDQ" and "per-channel" in q["weights"]
            import onnx

            ops = {n.op_type for n in onnx.load(str(out / "trunk.onnx")).graph.node}
            assert {"QuantizeLinear", "DequantizeLinear"} <= ops and "ConvInteger" not in ops
            assert m["checks"]["int8_vs_fp32_on_calibration"]["cls_t_top1_agreement"] >= 0.9
            # the scene model was fitted on fp32 features: export says so and checks it on int8's,
            # on validation presses only (touched held-out and validation fabrics')
            sc = m["checks"]["int8_scene_decision_on_validation"]
            assert sc["presses"] > 0 and 0.5 <= sc["argmax_agreement"] <= 1.0
            assert sc["projection_shift_sq_median"] >= 0.0 and "int8" in m["decision"]["rule"]
        else:
            assert "int8_scene_decision_on_validation" not in m["checks"] and "int8" not in m["decision"]["rule"]


def test_press_partition_is_the_trainers(tiny_run):
    """The manifest's 'which presses trained it' must be train/features.py's partition."""
    from types import SimpleNamespace

    from vs2t_edge.train.features import touched_training_rows

    ids = [f"f{i:02d}" for i in range(7)]
    counts = {f: 20 + 3 * i for i, f in enumerate(ids)}
    touched = ids[1:5]
    fabric = np.concatenate([np.full(counts[f], i) for i, f in enumerate(ids)])
    rows, _ = touched_training_rows(fabric, ids, SimpleNamespace(touched=touched, untouched=ids[5:6],
                                                                 validation=ids[6:], seed=3))
    start = {f: int(np.flatnonzero(fabric == i)[0]) for i, f in enumerate(ids)}
    part = fr.press_partition(counts, touched, seed=3, max_presses=None)
    want = sorted(start[f] + p for f in touched for p in part[f]["train"])
    assert sorted(rows.tolist()) == want
    # with max_presses, presses off the evenly spaced subset are 'unused' and never train
    part45 = fr.press_partition({"a": 225}, ["a"], seed=0, max_presses=45)["a"]
    assert len(part45["unused"]) == 180 and not set(part45["unused"]) & set(part45["train"])


def test_parity_efficientnet_trunk_torch_vs_onnxruntime(tmp_path):
    """Train/serve parity on the real architecture (random init, 64 px, world frames):
    max |ort - torch| / max |torch| <= PARITY_TOLERANCE."""
    from vs2t_edge.runtime.bundle import open_session
    from vs2t_edge.train.trunks import build_trunk

    trunk = build_trunk("efficientnet_lite0", pretrained=False).eval()
    x, _, _ = world_frames(64)
    x = x[:6]
    ex.export_onnx(trunk, torch.from_numpy(x[:1]), tmp_path / "t.onnx", "image", ["feature"])
    with torch.no_grad():
        ref = trunk(torch.from_numpy(x)).numpy()
    (got,) = open_session(tmp_path / "t.onnx", 1).run(None, {"image": x})
    assert got.shape == ref.shape == (6, 1280)
    assert np.max(np.abs(got - ref)) / np.max(np.abs(ref)) <= ex.PARITY_TOLERANCE


@given(st.integers(1, 5), st.floats(1e-3, 1e3))
@settings(max_examples=15, deadline=None)
def test_parity_heads_property(batch, scale):
    from vs2t_edge.runtime.bundle import open_session
    from vs2t_edge.train.models import Classifier

    import tempfile
    from pathlib import Path

    torch.manual_seed(batch)
    heads = ex._Heads(Classifier(16, 4, (32, 32)), Classifier(16, 3, (32, 32))).eval()
    f = (torch.randn(batch, 16) * scale).float()
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "h.onnx"
        ex.export_onnx(heads, torch.zeros(1, 16), p, "feature", ["logits_t", "logits_u"])
        lt, lu = open_session(p, 1).run(None, {"feature": f.numpy()})
    with torch.no_grad():
        rt, ru = heads(f)
    for a, b in ((lt, rt.numpy()), (lu, ru.numpy())):
        assert np.max(np.abs(a - b)) <= ex.PARITY_TOLERANCE * max(1.0, float(np.max(np.abs(b))))


def test_count_macs_by_hand(tmp_path):
    from torch import nn

    m = nn.Sequential(nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.ReLU(), nn.Conv2d(8, 8, 3, padding=1, groups=8),
                      nn.Flatten(), nn.Linear(8 * 16 * 16, 5)).eval()
    ex.export_onnx(m, torch.zeros(1, 3, 32, 32), tmp_path / "m.onnx", "image", ["y"])
    macs = ex.count_macs(tmp_path / "m.onnx")
    conv = 8 * 16 * 16 * 3 * 9 + 8 * 16 * 16 * 1 * 9  # C_out*H*W*(C_in/group)*k*k
    assert macs["Conv"] == conv and macs.get("Gemm", 0) + macs.get("MatMul", 0) == 8 * 16 * 16 * 5
    assert macs["total"] == conv + 8 * 16 * 16 * 5


def test_gating_temperature_recovers_a_known_logistic():
    rng = np.random.default_rng(0)
    nov = rng.uniform(-10, 10, 20000)
    y = rng.random(nov.size) < 1 / (1 + np.exp(-(nov - 1.0) / 2.5))
    t = reval.fit_gating_temperature(nov[~y], nov[y], beta=1.0)
    assert t == pytest.approx(2.5, rel=0.1)


def test_export_cli_usage_errors(tmp_path, capsys):
    from vs2t_edge.cli import main

    assert main(["export", str(tmp_path / "norun"), "--out", str(tmp_path / "b")]) == 2
    assert "no artifacts/model.pt" in capsys.readouterr().err
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "keep.txt").write_text("x")
    assert main(["export", "--random-trunk", "tiny", "--dataset", str(tiny_world()), "--size", "32",
                 "--out", str(tmp_path / "junk")]) == 2
    assert "not a bundle; refusing" in capsys.readouterr().err
    assert (tmp_path / "junk" / "keep.txt").exists()


def test_export_cli_random_trunk_writes_latency_bundle(tmp_path, capsys):
    from vs2t_edge.cli import main

    out = tmp_path / "b"
    assert main(["export", "--random-trunk", "tiny", "--dataset", str(tiny_world()), "--size", "32",
                 "--trunk-precision", "int8", "--out", str(out)]) == 0
    m = json.loads((out / "manifest.json").read_text())
    assert m["provenance"]["trained"] is False and m["graphs"]["trunk"]["macs_per_frame"]["total"] > 0
    assert "verified" in capsys.readouterr().out
    # its classes carry the dataset's real fabric names, its decisions mean nothing: no cell sorts with it
    from types import SimpleNamespace

    from vs2t_edge.runtime.config import SceneFabric
    from vs2t_edge.runtime.inference import TactileModel
    from vs2t_edge.runtime.wiring import check_scene_against_bundle

    model = TactileModel.load(out)
    cfg = SimpleNamespace(bundle=out, path=tmp_path / "cell.yaml",
                          fabrics=(SceneFabric(model.touched[0], "touched", 1), SceneFabric(model.untouched[0], "untouched", 2)))
    with pytest.raises(ValueError, match=r"never trained \(manifest provenance.trained: false"):
        check_scene_against_bundle(cfg, model)


# ------------------------------------------------ export --router NAME (issue 4: ship any router)


def _balanced_separation(model, ds, spec, touched_heldout, validation_presses):
    """Mean of (held-out touched presses kept touched, validation presses flagged untouched) at
    the bundle's beta, scored by the loaded bundle itself: 0.5 is chance (beta = +-inf)."""
    x_t = np.concatenate([fr._frames(ds, fid, idx, spec) for fid, idx in touched_heldout.items() if idx])
    x_v = np.concatenate([fr._frames(ds, fid, idx, spec) for fid, idx in validation_presses.items() if idx])
    nt, nv_ = model.forward(x_t).novelty, model.forward(x_v).novelty
    return 0.5 * (float(np.mean(nt <= model.beta)) + float(np.mean(nv_ > model.beta)))


@pytest.mark.parametrize("name", ["max_softmax", "gaussian"])
def test_export_router_refits_and_tunes_beta(tiny_run, tmp_path, monkeypatch, capsys, name):
    """`export RUN --router NAME`: the bundle names NAME, loads with the cell's verification, its
    beta separates held-out touched from validation presses at least as well as chance, the
    provenance says it was refitted (and on which presses), and no untouched fabric's tactile data
    is read anywhere in the export (zero-shot)."""
    from vs2t_edge.cli import main
    from vs2t_edge.runtime import dataset as rd
    from vs2t_edge.runtime.dataset import load_dataset

    run, art = tiny_run
    read: set[str] = set()
    for meth in ("load_press", "load_reference"):
        orig = getattr(rd.Fabric, meth)
        monkeypatch.setattr(rd.Fabric, meth, lambda self, *a, _o=orig, **k: (read.add(self.id), _o(self, *a, **k))[1])
    out = tmp_path / name
    assert main(["export", str(run), "--out", str(out), "--router", name, "--calibration-frames", "8",
                 "--threads", "1"]) == 0
    said = capsys.readouterr().out
    assert f"router {name} (tells touched from untouched presses), beta " in said  # beta says what it is
    assert "(its threshold, on the router's own scale)" in said
    assert read and not read & set(art.untouched), f"untouched fabrics read: {sorted(read & set(art.untouched))}"
    assert read <= set(art.touched) | set(art.validation)

    m = json.loads((out / "manifest.json").read_text())
    assert m["router"]["name"] == name
    model = TactileModel.load(out, threads=1)
    assert model.router.name == name and model.beta == m["beta"]
    assert name in m["operating_point"] and "balanced" in m["operating_point"]
    assert all(v in m["operating_point"] for v in art.validation)
    rp, data = m["provenance"]["router"], m["provenance"]["data"]
    assert rp["refitted_at_export"] is True and rp["name"] == name and rp["run_router"] == art.router_name
    assert rp["fitted_on"]["count"] == sum(len(data["touched_presses"][f]["train"]) for f in art.touched)
    assert set(rp["beta_tuned_on"]["validation_presses"]) == set(art.validation)
    assert m["checks"]["parity_torch_vs_onnxruntime"]["feature"] <= ex.PARITY_TOLERANCE
    ds = load_dataset(tiny_world())
    held = {f: data["touched_presses"][f]["val"] for f in art.touched}
    sep = _balanced_separation(model, ds, model.preprocess_spec, held, rp["beta_tuned_on"]["validation_presses"])
    assert sep >= 0.5


def test_export_router_unknown_name_is_refused(tiny_run, tmp_path, capsys):
    from vs2t_edge.cli import main
    from vs2t_edge.runtime.novelty import ROUTERS

    run, _ = tiny_run
    assert main(["export", str(run), "--out", str(tmp_path / "b"), "--router", "softmax"]) == 2
    err = capsys.readouterr().err
    assert "unknown router 'softmax'" in err and all(r in err for r in ROUTERS)
    assert not (tmp_path / "b").exists()
    with pytest.raises(ex.ExportError, match="known: " + ", ".join(ROUTERS)):
        fr.export_run(run, tmp_path / "b", router="softmax")


def test_zero_shot_guard_refuses_untouched_presses(tiny_run):
    """The guard itself: a press of an untouched fabric among the presses the router, beta or
    gating would read is refused, and refit_router refuses validation fabrics that are untouched."""
    from vs2t_edge.runtime.dataset import load_dataset

    _, art = tiny_run
    fr.check_zero_shot({art.touched[0]: [1, 2], art.validation[0]: [0]}, art.untouched, "x")  # allowed
    with pytest.raises(ex.ExportError, match="zero-shot violated: beta .* " + art.untouched[0]):
        fr.check_zero_shot({art.untouched[0]: [3]}, art.untouched, "beta")
    ds = load_dataset(tiny_world())
    part = fr.press_partition({f.id: len(f.presses) for f in ds.fabrics}, art.touched, 0, None)
    with pytest.raises(ex.ExportError, match="disjoint"):
        fr.refit_router("gaussian", ds=ds, spec=art.tactile_preprocess, trunk=None, cls_t=None, cls_u=None,
                        touched=art.touched, untouched=art.untouched, validation=art.untouched, part=part,
                        max_presses=None)


# ------------------------------------------------ a bundle from a real training run (issue 5's "done when")


@pytest.mark.slow
def test_bundle_from_a_real_tiny_training_run_passes_runtime_verification(tmp_path, capsys):
    """`train` on the tiny profile (the real trainer: trunk, tactile tail, VS2T-ZSL, router chosen
    on validation), then `export` of that run folder, fp32 and int8: each bundle passes the cell's
    verification (TactileModel.load and `verify-bundle`), names the run's classes, router and beta,
    records which presses trained it, and scores a press of an untouched fabric finitely."""
    from vs2t_edge.cli import main
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.train.artifacts import load_run_artifacts
    from vs2t_edge.train.run import train

    world = tiny_world()
    run = tmp_path / "run"
    train(world, run, profile="tiny", figures=False)
    # training flushes denormals while it runs; the process-wide flag must not outlive it
    # (left on, it broke every later hypothesis test in the same pytest process)
    assert sys.float_info.min / 2 != 0.0
    art = load_run_artifacts(run)
    ds = load_dataset(world)
    for prec in ("fp32", "int8"):
        out = tmp_path / f"bundle_{prec}"
        m = fr.export_run(run, out, trunk_precision=prec, calibration_frames=16)
        assert main(["verify-bundle", str(out), "--threads", "1"]) == 0
        assert f"bundle {out}: ok" in capsys.readouterr().out
        model = TactileModel.load(out, threads=1)
        assert list(model.touched) == list(art.touched) and list(model.untouched) == list(art.untouched)
        assert m["router"]["name"] == art.router_name and model.beta == pytest.approx(art.beta)
        assert m["provenance"]["trained"] is True and m["provenance"]["run"] == str(run.resolve())
        assert m["graphs"]["trunk"]["opset"] == ex.OPSET and m["graphs"]["trunk"]["precision"] == prec
        part = m["provenance"]["data"]["touched_presses"]
        assert set(part) == set(art.touched) and all(part[f]["train"] for f in art.touched)
        fab = ds.by_id(art.untouched[0])
        model.set_reference(fab.load_reference())
        s = model.score_press(fab.load_press(0))
        # the deployed scene model knows the run's validation fabrics too, only to refuse them
        assert model.scene_model.known_only == tuple(art.validation) and art.validation
        assert set(s.log_posterior) == set(model.classes) | set(art.validation)
        assert all(np.isfinite(v) for v in s.log_posterior.values())
        # format 3: the press ran no router; the heads' graph still gives one off the press path
        assert m["format_version"] == 3 and s.novelty is None and np.isfinite(model.press_novelty(fab.load_press(0)))


def test_size_other_than_trained_is_refused_with_a_scene_model(tiny_run, tmp_path, capsys):
    """The scene model and its operating point were fitted on features of the trained size: a
    bundle at another size would decide with them on other features (the paper run at 96 px:
    mis-sorts 0.9 -> 3.8 %). Export refuses it, and a bundle made so before is refused at load."""
    import json

    from vs2t_edge.cli import main
    from vs2t_edge.runtime.bundle import BundleError, load_bundle

    run, _ = tiny_run
    with pytest.raises(ex.ExportError, match="trained at 64 px.*scene model"):
        fr.export_run(run, tmp_path / "b32", size=32)
    assert not (tmp_path / "b32").exists()
    assert main(["export", str(run), "--out", str(tmp_path / "b32"), "--size", "32"]) == 2
    assert "scene model" in capsys.readouterr().err
    # its own size is fine, said or not
    fr.export_run(run, tmp_path / "b64", size=64, calibration_frames=8)
    assert load_bundle(tmp_path / "b64").scene_model is not None
    # a bundle whose manifest says it was trained at another size than its trunk takes: refused at load
    m = json.loads((tmp_path / "b64" / "manifest.json").read_text())
    m["provenance"]["trained_size_px"] = 128
    from vs2t_edge.runtime.bundle import seal_manifest

    (tmp_path / "b64" / "manifest.json").write_text(json.dumps(seal_manifest(m)))
    with pytest.raises(BundleError, match="trained at 128 px"):
        load_bundle(tmp_path / "b64")

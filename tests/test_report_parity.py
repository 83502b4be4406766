"""Train/serve parity end to end: the bundle, scoring the frames of training's test jobs as the cell
scores a camera's frames, decides every piece as training's report decided it.

Training's report counts its test jobs with ``runtime.sorting.simulate_scenes`` on features the
run computed itself (the float16 stem cache through the tuned tail, standardised in float64, the
scene model's float64 projection). The cell scores a frame with the exported graph (float32, no
stem cache) and the bundle's ``decision.npz``. Measured on the demo world (2026-11-29, one split,
528 pieces): per press the log posteriors agree to 4.4e-3 (the float16 stems; 4e-5 between the
torch modules and onnxruntime), and not one piece is decided otherwise, on the float path, the
reduced path, through the camera's JPEG and with a descriptor (the audit's script, 2026-11-29).
Kept here: the float path, on a tiny world."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from test_bundle_fixtures import tiny_world


@pytest.mark.slow
def test_the_bundle_decides_the_reports_test_jobs_as_the_report_did(tmp_path):
    from vs2t_edge.export.from_run import export_run
    from vs2t_edge.runtime import sorting as so
    from vs2t_edge.runtime.dataset import load_dataset, press_partition
    from vs2t_edge.runtime.inference import TactileModel
    from vs2t_edge.runtime.scene_model import SceneModel
    from vs2t_edge.train import decision as dc
    from vs2t_edge.train.artifacts import build_modules, load_run_artifacts
    from vs2t_edge.train.features import StemCache, extracted_presses, features_from_stem
    from vs2t_edge.train.run import train

    world, run = tiny_world(), tmp_path / "run"
    train(world, run, profile="tiny", figures=False)
    export_run(run, tmp_path / "bundle", calibration_frames=8, threads=1)
    art = load_run_artifacts(run)
    cell = TactileModel.load(tmp_path / "bundle", threads=1)
    trained_model = SceneModel.from_params(art.scene_model)
    assert cell.scene_model.classes == trained_model.classes

    # what the report scored: the run's own features of each fabric's test-job presses
    cache = StemCache.load(run / "features" / "stem_cache.npz")
    deploy, _, _ = build_modules(art)
    with torch.no_grad():
        raw = features_from_stem(deploy.trunk, cache.stem_t)
    x = ((raw.astype(np.float64) - art.feature_mean) / art.feature_std).astype(np.float32)
    ds = load_dataset(world)
    trained_rows, served = {}, {}
    for fid in list(art.touched) + list(art.untouched):
        rows = np.flatnonzero(cache.fabric == cache.fabric_ids.index(fid))
        presses = extracted_presses(len(ds.by_id(fid).presses), None)
        pick = np.arange(len(rows))[press_partition(len(rows))[2]] if fid in art.touched else np.arange(len(rows))
        trained_rows[fid] = x[rows[pick]]
        fabric = ds.by_id(fid)
        cell.set_reference(fabric.load_reference())  # as the cell: the item's no-contact frame, then each press
        scores = [cell.score_press(fabric.load_press(int(presses[j]))) for j in pick]
        served[fid] = [so.Press(s.log_posterior, s.sq_distance, s.scene_z) for s in scores]
    trained = dc.press_tables(trained_model, trained_rows)
    for fid in trained:
        for a, b in zip(trained[fid], served[fid]):
            assert max(abs(a.log_posterior[c] - b.log_posterior[c]) for c in trained_model.classes) < 0.05, fid

    seed = int(art.info.get("split_seed", 0))
    scenes = so.draw_scenes(list(art.touched), list(art.untouched), (), dc.N_SCENES,
                            n_untouched=min(3, len(art.untouched)), seed=seed + 1)
    report = so.simulate_scenes(scenes, trained, dc.evidence_for(trained_model), seed=seed + 1, items_per_fabric=4)
    on_cell = so.simulate_scenes(scenes, served, dc.evidence_for(cell.scene_model), seed=seed + 1, items_per_fabric=4)
    assert [(r.truth, r.label, r.presses) for r in on_cell] == [(r.truth, r.label, r.presses) for r in report]
    # and those are the report's own numbers
    test = json.loads((run / "metrics.json").read_text())["splits"][0]["scene_decision"]["test"]["all"]
    mine = so.summarise(report)["all"]
    for key in ("right", "mis-sort", "reject", "presses"):
        assert mine[key] == pytest.approx(test[key]), key

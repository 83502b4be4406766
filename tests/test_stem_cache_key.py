"""The stem cache is keyed by the trunk that made it, weights included: the exported trunk is the
run's own (its stem too), so tails fine-tuned on another trunk's cached stems would give a scene
model, scaler and heads fitted on features the shipped graph never computes.

Before the key held the weights, `train --seed 1` (or `--weights`) into a folder that had trained
with seed 0 reused seed 0's stems under a tiny (random) trunk of seed 1: the bundle's feature of a
touched training press was ~20x its size away from training's, and its scene model's most likely
class agreed with training's on none of them."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from test_bundle_fixtures import tiny_world


def _stems_through_tail(trunk, stems: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return trunk.features_from_stem(torch.from_numpy(stems.astype(np.float32))).numpy()


def test_a_cache_made_by_another_trunks_weights_is_not_reused(tmp_path):
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import TactilePreprocess, preprocess_tactile
    from vs2t_edge.train import features as ft
    from vs2t_edge.train.run import PROFILES, get_cache
    from vs2t_edge.train.trunks import build_trunk

    world = tiny_world()
    prof = replace(PROFILES["tiny"], max_presses=3)
    torch.manual_seed(0)
    seed0 = build_trunk("tiny").eval()
    torch.manual_seed(1)
    seed1 = build_trunk("tiny").eval()
    assert ft.trunk_fingerprint(seed0) != ft.trunk_fingerprint(seed1)
    first = get_cache(world, prof, tmp_path, seed0)
    again = get_cache(world, prof, tmp_path, seed0)  # the same trunk: the cache serves
    assert np.array_equal(again.stem_t, first.stem_t)
    other = get_cache(world, prof, tmp_path, seed1)  # another trunk's weights: extracted again
    assert other.meta["trunk_sha256"] == ft.trunk_fingerprint(seed1) != first.meta["trunk_sha256"]
    # what the run fine-tunes on is what the exported trunk computes: its own stem, then the tail
    fab = load_dataset(world).fabrics[0]
    x = preprocess_tactile(fab.load_press(0), fab.load_reference(), TactilePreprocess(size=prof.size_px))[None]
    with torch.no_grad():
        exported = seed1(torch.from_numpy(x)).numpy()
    trained = _stems_through_tail(seed1, other.stem_t[:1])
    assert np.abs(trained - exported).max() <= 1e-2 * np.abs(exported).max()


@pytest.mark.slow
def test_a_rerun_with_another_seed_into_the_same_folder_exports_what_it_trained(tmp_path):
    """`train` tiny with seed 0, then with seed 1 into the same run folder, then `export`: the
    bundle's feature of a touched training press is the one training fitted on (the run's stem
    cache through the run's tuned tail and standardisation), and the scene model decides alike."""
    from vs2t_edge.export.from_run import _frames, export_run
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.inference import TactileModel
    from vs2t_edge.train import features as ft
    from vs2t_edge.train.artifacts import build_modules, load_run_artifacts
    from vs2t_edge.train.run import train

    world, run = tiny_world(), tmp_path / "run"
    train(world, run, profile="tiny", figures=False)
    train(world, run, profile="tiny", seed=1, figures=False)
    art = load_run_artifacts(run)
    export_run(run, tmp_path / "bundle", calibration_frames=8, threads=1)
    model = TactileModel.load(tmp_path / "bundle", threads=1)
    deploy, _, _ = build_modules(art)
    cache = ft.StemCache.load(run / "features" / "stem_cache.npz")
    ds = load_dataset(world)
    for fid in art.touched[:2]:
        rows = np.flatnonzero(cache.fabric == cache.fabric_ids.index(fid))
        shipped = model.forward(_frames(ds, fid, range(len(rows)), art.tactile_preprocess)).feature
        with torch.no_grad():
            trained = deploy.scale(torch.from_numpy(_stems_through_tail(deploy.trunk, cache.stem_t[rows]))).numpy()
        assert np.abs(shipped - trained).max() <= 1e-2 * np.abs(trained).max(), fid
        sm = model.scene_model
        agree = sm.log_posterior(shipped)[0].argmax(1) == sm.log_posterior(trained)[0].argmax(1)
        assert agree.all(), fid


def test_a_cache_of_frames_since_replaced_in_the_same_folder_is_not_reused(tmp_path):
    """A world drawn again into the same folder (`vs2t-edge demo --seed 1` in a work folder of seed
    0) keeps the dataset's path: the cache keyed by the path fed the old frames' stems to the new
    run, while export, the probe and the cell read the new frames."""
    import shutil

    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import TactilePreprocess, preprocess_tactile
    from vs2t_edge.train.run import PROFILES, get_cache
    from vs2t_edge.train.trunks import build_trunk

    world = tmp_path / "world"
    shutil.copytree(tiny_world(), world)
    prof = replace(PROFILES["tiny"], max_presses=3)
    torch.manual_seed(0)
    trunk = build_trunk("tiny").eval()
    first = get_cache(world, prof, tmp_path / "features", trunk)
    ds = load_dataset(world)
    a, b = ds.fabrics[0], ds.fabrics[5]
    shutil.copyfile(b.presses[0].path, a.presses[0].path)  # f00's first press is now another fabric's frame
    again = get_cache(world, prof, tmp_path / "features", trunk)
    x = preprocess_tactile(load_dataset(world).fabrics[0].load_press(0), a.load_reference(),
                           TactilePreprocess(size=prof.size_px))[None]
    with torch.no_grad():
        exported = trunk(torch.from_numpy(x)).numpy()
    assert not np.array_equal(again.stem_t[0], first.stem_t[0])
    trained = _stems_through_tail(trunk, again.stem_t[:1])
    assert np.abs(trained - exported).max() <= 1e-2 * np.abs(exported).max()


def test_a_cache_of_another_preprocessing_is_not_reused(tmp_path):
    """The key held the pixel path (reduce, camera JPEG, its scale) but not the rest of the
    preprocessing the bundle ships and the cell runs: a run whose crop, normalisation, reference use
    or sensor corrections differ from the cache's (a TactilePreprocess default changed, a profile
    that sets one) fine-tuned its tails and fitted its scene model on stems of the old frames' input.
    A cache of the preprocessing every run so far used keeps its key (no extraction again)."""
    from vs2t_edge.runtime.preprocess import TactilePreprocess
    from vs2t_edge.train import features as ft
    from vs2t_edge.train.run import PROFILES, get_cache
    from vs2t_edge.train.trunks import build_trunk

    world = tiny_world()
    prof = replace(PROFILES["tiny"], max_presses=3)
    torch.manual_seed(0)
    trunk = build_trunk("tiny").eval()
    plain = TactilePreprocess(size=prof.size_px)
    first = get_cache(world, prof, tmp_path, trunk, plain)
    assert set(first.meta) == {"size", "arch", "max_presses", "version", "dataset", "trunk_sha256",
                               "dataset_files_sha256"}  # the key every float-path, lossless cache has had
    for other in (replace(plain, std=(0.1, 0.1, 0.1)), replace(plain, crop_fraction=0.8),
                  replace(plain, use_reference=False), replace(plain, mean=(0.01, 0.0, 0.0)),
                  replace(plain, normalise_exposure=True)):
        again = get_cache(world, prof, tmp_path, trunk, other)
        assert again.meta != first.meta, other
        assert not np.array_equal(again.stem_t, first.stem_t), other
        assert again.meta == ft.stem_cache_key(world, trunk, prof.size_px, prof.max_presses, other, 0)


def test_every_preprocessing_field_is_in_the_cache_key():
    """A field TactilePreprocess gains later must join the key (train/features.py ``_KEYED_AS_BEFORE``,
    or the size, pixel path and decode scale keyed on their own): else a run of another input would
    reuse these stems silently (review, 2026-11-29)."""
    from dataclasses import fields

    from vs2t_edge.runtime.preprocess import TactilePreprocess
    from vs2t_edge.train.features import _KEYED_AS_BEFORE

    assert {f.name for f in fields(TactilePreprocess)} == set(_KEYED_AS_BEFORE) | {"size", "reduce", "jpeg_scale"}

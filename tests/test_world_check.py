"""train/world_check.py: how close anyone could get to an untouched fabric's touch in a synthetic
world (docs/results/zero_shot_limits_paper.md, "World or model")."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import yaml

torch = pytest.importorskip("torch")

from test_bundle_fixtures import tiny_world  # noqa: E402
from vs2t_edge.runtime.dataset import load_dataset  # noqa: E402
from vs2t_edge.sim import synth  # noqa: E402
from vs2t_edge.train import world_check as wc  # noqa: E402


def test_a_fabric_rendered_again_from_its_yaml_is_the_datasets_fabric():
    """The check re-renders held-out fabrics from the parameters fabric.yaml keeps: with its own
    surface and every grid point, render_fabric gives the dataset's frames bit for bit; at a
    subset of points, other presses of the same surface; with another surface seed, other frames."""
    ds = load_dataset(tiny_world())
    fab = ds.fabrics[3]
    params = synth.fabric_params(yaml.safe_load((fab.folder / "fabric.yaml").read_text())["extra"]["params"])
    camera, reference, presses = synth.render_fabric(params, "tiny", 3, 0)
    assert np.array_equal(camera, fab.load_camera()) and np.array_equal(reference, fab.load_reference())
    assert len(presses) == len(fab.presses)
    assert all(np.array_equal(frame, fab.load_press(i)) for i, (frame, *_) in enumerate(presses))
    _, _, some = synth.render_fabric(params, "tiny", 3, 0, presses=[0, 4])
    assert [(x, y) for _, x, y, _ in some] == [(presses[i][1], presses[i][2]) for i in (0, 4)]
    assert not np.array_equal(some[0][0], presses[0][0])  # its own press noise
    _, _, other = synth.render_fabric(replace(params, phase_seed=params.phase_seed + 1), "tiny", 3, 0)
    assert not np.array_equal(other[0][0], presses[0][0])


def test_fabric_params_names_what_is_wrong():
    ds = load_dataset(tiny_world())
    raw = yaml.safe_load((ds.fabrics[0].folder / "fabric.yaml").read_text())["extra"]["params"]
    with pytest.raises(ValueError, match=r"f00.yaml: extra.params lacks \['stiffness'\]"):
        synth.fabric_params({k: v for k, v in raw.items() if k != "stiffness"}, "f00.yaml")
    with pytest.raises(ValueError, match=r"has unknown \['softness'\]"):
        synth.fabric_params({**raw, "softness": 1}, "f00.yaml")
    with pytest.raises(ValueError, match="only a synthetic world"):
        synth.fabric_params(None, "f00.yaml")


def test_a_world_without_hidden_parameters_is_refused_by_file(tmp_path):
    import shutil

    root = tmp_path / "world"
    shutil.copytree(tiny_world(), root)
    path = root / "f02" / "fabric.yaml"
    doc = yaml.safe_load(path.read_text())
    del doc["extra"]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValueError, match=r"f02/fabric.yaml: no extra.params"):
        wc.physical_parameters(load_dataset(root))


def test_ridge_map_chooses_its_penalty_by_leave_one_fabric_out():
    """Targets linear in the conditions: the least penalty, predictions close to the truth;
    targets unrelated to them: the largest penalty, predictions close to the fitting mean."""
    rng = np.random.default_rng(0)
    cond = rng.normal(size=(40, 6))
    new = rng.normal(size=(5, 6))
    w = rng.normal(size=(6, 3))
    pred, alpha = wc.ridge_map(cond, cond @ w + 2.0, new)
    assert alpha == min(wc.ALPHAS)
    assert np.abs(pred - (new @ w + 2.0)).max() < 0.1
    noise = rng.normal(size=(40, 3))
    pred, alpha = wc.ridge_map(cond, noise, new)
    assert alpha == max(wc.ALPHAS)
    assert np.abs(pred - noise.mean(0)).max() < 0.1


def test_kernel_map_follows_what_a_linear_map_cannot():
    """Targets a smooth non-linear function of the conditions: the kernel map predicts new rows
    far better than the ridge map; targets unrelated to them: close to the fitting mean."""
    rng = np.random.default_rng(1)
    cond = rng.uniform(-2.0, 2.0, size=(60, 2))
    new = rng.uniform(-1.5, 1.5, size=(10, 2))
    f = lambda c: np.stack([c[:, 0] ** 2, np.sin(2.0 * c[:, 1])], axis=1)  # noqa: E731
    kern, (gamma, alpha) = wc.kernel_map(cond, f(cond), new)
    ridge, _ = wc.ridge_map(cond, f(cond), new)
    assert gamma in wc.KERNEL_GAMMAS and alpha in wc.KERNEL_ALPHAS
    assert np.abs(kern - f(new)).max() < 0.25 < np.abs(ridge - f(new)).max()
    noise = rng.normal(size=(60, 2))
    pred, _ = wc.kernel_map(cond, noise, new)
    assert np.abs(pred - noise.mean(0)).max() < 0.3


def test_world_check_on_a_trained_tiny_run(tmp_path, monkeypatch):
    """The check end to end on a real (shortened) tiny run: every row for both roles, distances
    and accuracies in range, the real means the best prototypes, and the printed table."""
    from vs2t_edge.train import run as tr

    monkeypatch.setitem(tr.PROFILES, "tiny", replace(tr.PROFILES["tiny"], steps=20, cls_steps=20,
                                                     n_synth_per_class=20, ft_epochs=1))
    run = tmp_path / "run"
    tr.train(tiny_world(), run, profile="tiny", seed=1, figures=False)
    res = wc.world_check(run, k=8, log=lambda m: None)
    one = res["per_split"][0]
    for role in ("validation", "untouched"):
        r = one[role]
        assert len(r["fabrics"]) == 2
        for row in wc.ROWS:
            assert len(r[row]["per_fabric"]) == 2 and all(np.isfinite(v) and v >= 0 for v in r[row]["per_fabric"])
            assert r[row]["zsl"] is None or 0.0 <= r[row]["zsl"] <= 1.0
        assert r["real means"]["zsl"] >= max(r[row]["zsl"] or 0.0 for row in wc.ROWS[:4])
    table = wc.render_table(res["summary"], 8, 1)
    assert all(f"| {row} |" in table for row in wc.ROWS)

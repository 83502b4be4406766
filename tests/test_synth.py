"""The fabric world: deterministic, loadable, and honest about what touch and vision can see."""

from __future__ import annotations

import os
import hashlib
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from vs2t_edge.cli import main
from vs2t_edge.runtime.attributes import ATTRIBUTES, EXCLUSIVE_PAIRS
from vs2t_edge.runtime.dataset import load_dataset, validate_dataset
from vs2t_edge.sim import fabrics, synth
from vs2t_edge.sim.gelsight import GelSight, marker_mask


def _digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(p.relative_to(root).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return synth.generate(tmp_path_factory.mktemp("w") / "tiny", "tiny", seed=3, progress=False, n_fabrics=4)


def test_tiny_world_validates_deeply(tiny):
    ds = validate_dataset(tiny, deep=True)
    assert len(ds.fabrics) == 4 and all(len(f.presses) == 9 for f in ds.fabrics)
    assert ds.geometry.frame_width_px == 160
    f = ds.fabrics[0]
    assert f.load_press(0).shape == (120, 160, 3)
    assert "params" in (f.folder / "fabric.yaml").read_text()


def test_same_seed_same_bytes_other_seed_other_bytes(tiny, tmp_path):
    again = synth.generate(tmp_path / "again", "tiny", seed=3, progress=False, n_fabrics=4, workers=1)
    other = synth.generate(tmp_path / "other", "tiny", seed=4, progress=False, n_fabrics=4, workers=1)
    assert _digest(again) == _digest(tiny)
    assert _digest(other) != _digest(tiny)


def test_progress_into_a_log_is_plain_lines(tmp_path, capsys):
    """stderr that is not a terminal (a log file, the demo's captured output) gets a plain line
    per fabric done here, not carriage returns that pile up into one very long line."""
    synth.generate(tmp_path / "w", "tiny", seed=3, n_fabrics=2, workers=1)
    err = capsys.readouterr().err
    assert "\r" not in err
    assert [ln.split(",")[0] for ln in err.splitlines()] == ["synth tiny: 1/2 fabrics", "synth tiny: 2/2 fabrics"]


def _dark_dots(image: np.ndarray) -> int:
    """Marker-sized dark blobs: pixels 20 % darker than their 11-px median neighbourhood."""
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    dark = (gray < 0.8 * cv2.medianBlur(gray, 11).astype(np.float32)).astype(np.uint8)
    return cv2.connectedComponents(dark)[0] - 1


def test_no_markers_renders_the_same_world_without_dots(tiny, tmp_path, capsys):
    """`vs2t-edge synth --no-markers`: the reference frames have no marker dots, and every pixel
    away from the markers is the same as in the default world of the same seed (which keeps its
    dots and its dataset.yaml without a 'markers' key)."""
    out = tmp_path / "plain"
    assert main(["synth", str(out), "--profile", "tiny", "--fabrics", "4", "--seed", "3", "--workers", "1",
                 "--no-markers"]) == 0
    assert "no markers" in capsys.readouterr().out
    with_dots, without = load_dataset(tiny), validate_dataset(out, deep=True)
    assert without.meta["provenance"]["markers"] is False and "markers" not in with_dots.meta["provenance"]
    g = with_dots.geometry
    mask = marker_mask(GelSight(width_px=g.frame_width_px, height_px=g.frame_height_px,
                                mm_per_px=15.0 / g.frame_width_px), np.random.default_rng(0))
    expected_dots = len(np.arange(0.9, 15.0, 1.8)) * len(np.arange(0.9, 15.0 * 120 / 160, 1.8))  # 1.8 mm pitch
    for a, b in zip(with_dots.fabrics, without.fabrics):
        ref_a, ref_b = a.load_reference(), b.load_reference()
        assert _dark_dots(ref_a) == expected_dots and _dark_dots(ref_b) == 0, a.name
        changed = np.any(ref_a != ref_b, axis=-1)
        assert changed.any() and np.all(mask[changed] > 0), a.name  # only marker pixels differ
        centres = mask > 0.5
        assert ref_a[centres].mean() < 0.8 * ref_b[centres].mean()  # where the dots were, now plain gel
        for k in range(len(a.presses)):
            same = np.all(a.load_press(k) == b.load_press(k), axis=-1).mean()
            assert same > 0.75, (a.name, k, same)  # the presses are the same fabric, markers aside
        assert np.array_equal(a.load_camera(), b.load_camera())


def _press(p: synth.FabricParams, force_n: float = 15.0) -> np.ndarray:
    sensor = GelSight(width_px=160, height_px=120, mm_per_px=15 / 160)
    return synth.pressed_deformation(p, synth.Surface(p), 40.0, 40.0, force_n, 0.0, sensor, 1.0)


def test_colour_and_print_never_change_touch():
    p = fabrics.draw_fabric(np.random.default_rng(0), "twill")
    recoloured = replace(p, colour_hsv=(10.0, 0.9, 0.3), print_kind="dots", stripes=not p.stripes)
    assert np.array_equal(_press(p), _press(recoloured))
    cam_a = synth.camera_image(p, synth.Surface(p), 100)
    cam_b = synth.camera_image(recoloured, synth.Surface(recoloured), 100)
    assert np.abs(cam_a.astype(int) - cam_b).mean() > 10  # ... while the camera sees it


def test_stiffer_fabric_lets_less_of_its_surface_touch_the_gel():
    p = fabrics.draw_fabric(np.random.default_rng(1), "jersey")
    soft, stiff = replace(p, stiffness=0.05), replace(p, stiffness=0.95)
    assert (_press(soft) > 1e-4).mean() > (_press(stiff) > 1e-4).mean() + 0.1


def test_more_force_more_contact():
    p = fabrics.draw_fabric(np.random.default_rng(2), "felt")
    assert (_press(p, 19.0) > 1e-4).mean() > (_press(p, 11.0) > 1e-4).mean()


def test_hairiness_shows_more_in_touch_than_in_sight():
    p = fabrics.draw_fabric(np.random.default_rng(5), "plain")
    bald, hairy = replace(p, hairiness=0.0), replace(p, hairiness=1.0)
    touch = np.abs(_press(hairy) - _press(bald)).mean() / (np.abs(_press(bald)).mean() + 1e-9)
    cam = lambda q: synth.camera_image(q, synth.Surface(q), 200).astype(float)
    sight = np.abs(cam(hairy) - cam(bald)).mean() / cam(bald).mean()
    assert touch > 3 * sight


def test_attributes_respect_exclusive_pairs_and_fabricvst_base_rates():
    """Base rates over many worlds of 50 (labels only, no rendering) sit near FabricVST's."""
    rates = {a: [] for a in synth.TARGET_RATES}
    for seed in range(12):
        world = fabrics.draw_world(50, seed)
        rng = np.random.default_rng([seed, 99])
        attrs = np.stack([synth.label_attributes(p, rng) for p in world])
        for x, y in EXCLUSIVE_PAIRS:
            assert not np.any(attrs[:, ATTRIBUTES.index(x)] & attrs[:, ATTRIBUTES.index(y)])
        for a in rates:
            rates[a].append(attrs[:, ATTRIBUTES.index(a)].mean())
    for a, target in synth.TARGET_RATES.items():
        assert abs(np.mean(rates[a]) - target) < 0.08, (a, np.mean(rates[a]), target)


def test_every_construction_appears_in_a_paper_sized_world():
    kinds = {p.construction for p in fabrics.draw_world(50, 0)}
    assert kinds == set(fabrics.CONSTRUCTIONS)


def test_unknown_profile_is_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown profile"):
        synth.generate(tmp_path, "huge")


def test_difficulty_report_runs_and_touch_beats_chance(tiny, tmp_path):
    from vs2t_edge.sim import difficulty

    res = difficulty.analyse(tiny, presses=9)
    assert res["tactile_logreg_acc"] > 2 * res["chance"]
    assert res["provenance"]["seed"] == 3
    difficulty.write_report(res, tmp_path / "d.md")
    text = (tmp_path / "d.md").read_text()
    # the report says which world it measured (a regenerated docs/difficulty.md keeps that line)
    assert text.splitlines()[2].startswith(f"Dataset: `vs2t-edge synth {tiny} --profile tiny --seed 3 --fabrics 4`. ")
    assert f"| {res['tactile_logreg_acc']:.1%} (chance {res['chance']:.1%}) |" in text
    assert f"| {res['attribute_nearest_class_acc']:.1%} |" in text
    assert f"would allow {res['unique_attribute_vectors'] / res['fabrics']:.1%}" in text


def test_attributes_alone_number_measures_label_noise_below_the_coarseness_cap(monkeypatch):
    """docs/difficulty.md's "attributes alone" number relabels each fabric with a fresh panel. On
    worlds of 50 (labels only, no rendering) it is far above chance, far from perfect, and well
    below what the distinct attribute vectors allow; with the annotators' noise switched off it
    reaches that cap, so the shortfall is label noise, not coarseness."""
    from vs2t_edge.sim import difficulty

    def world(seed: int):
        params = fabrics.draw_world(50, seed)
        rng = np.random.default_rng([seed, 99])
        attrs = np.stack([synth.label_attributes(p, rng) for p in params])
        return params, attrs, len({tuple(a) for a in attrs}) / len(attrs)

    for seed in range(4):
        params, attrs, cap = world(seed)
        acc = difficulty.attribute_identification(params, attrs, seed=0)
        assert 10 * (1 / 50) < acc < 0.8 and cap - acc > 0.2, (seed, acc, cap)
    monkeypatch.setattr(synth, "ANNOTATOR_NOISE", 0.0)
    for seed in range(2):
        params, attrs, cap = world(seed)
        assert abs(difficulty.attribute_identification(params, attrs, seed=0) - cap) < 0.03, seed


def test_sample_sheet_is_written_losslessly(tiny, tmp_path):
    """The PNG holds the sheet's exact pixels: no rounding to coarse grey steps (which showed as
    blotches in the flat parts of the GelSight frames)."""
    from vs2t_edge.sim import sample_sheet

    out = tmp_path / "sheet.png"
    assert sample_sheet.main([str(tiny), "--out", str(out)]) == 0
    drawn = sample_sheet.sheet(tiny)
    assert drawn.shape[0] > 28 + 3 * sample_sheet.TILE_H  # a header and a row per fabric (4 here)
    assert np.array_equal(cv2.imread(str(out)), drawn)


# --- the `vs2t-edge synth` verb end to end (issue 2: "Done when `vs2t-edge synth` with the small
# profile writes a dataset the loader accepts"), in-process through the CLI's main(argv)

def _synth_and_validate(out: Path, capsys, *flags: str) -> tuple[str, str]:
    assert main(["synth", str(out), *flags]) == 0, capsys.readouterr().err[-2000:]
    made = capsys.readouterr().out
    assert main(["validate-data", str(out)]) == 0, capsys.readouterr().err[-2000:]  # deep: decodes every image
    return made, capsys.readouterr().out


def test_synth_cli_tiny_writes_a_dataset_validate_data_accepts(tmp_path, capsys):
    out = tmp_path / "ds"
    made, checked = _synth_and_validate(out, capsys, "--profile", "tiny", "--fabrics", "3", "--seed", "5",
                                        "--workers", "1")
    assert "3 fabrics, 27 presses (tiny, seed 5)" in made
    assert "ok — 3 fabrics, 27 presses, frames 160x120, camera 200 px" in checked
    prov = load_dataset(out).meta["provenance"]
    assert (prov["profile"], prov["seed"], prov["n_fabrics"]) == ("tiny", 5, 3)
    # the verb refuses to write over a dataset...
    assert main(["synth", str(out), "--profile", "tiny", "--fabrics", "1"]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    # ... and validate-data is a real check: a press frame gone is exit 2 naming the fabric
    victim = sorted((out / "f01" / "tactile").glob("press_*.png"))[0]
    victim.unlink()
    assert main(["validate-data", str(out)]) == 2
    err = capsys.readouterr().err
    assert "f01" in err and victim.name in err


@pytest.mark.slow
def test_synth_cli_small_profile_writes_a_dataset_validate_data_accepts(tmp_path, capsys):
    """The issue's own words, on the small profile with one worker: measured 19-33 s on the shared
    2-core dev machine (under 90 s, so the whole profile, not a reduced number of fabrics). It runs
    in CI: the issue's "done when" is about this profile; `-m "not slow"` leaves it out locally."""
    t0 = time.monotonic()
    made, checked = _synth_and_validate(tmp_path / "small", capsys, "--profile", "small", "--workers", "1")
    assert "20 fabrics, 500 presses (small, seed 0)" in made
    assert "ok — 20 fabrics, 500 presses, frames 320x240, camera 500 px" in checked
    print(f"synth + validate-data, small profile, one worker: {time.monotonic() - t0:.1f} s")


def test_synth_defaults_to_the_fabricvst_sized_world():
    """Issue 2: frames 640x480 and a 1000 px camera image by default (smaller worlds by name)."""
    import argparse

    from vs2t_edge.sim import synth_cli
    from vs2t_edge.sim.synth import PROFILES

    parser = argparse.ArgumentParser()
    synth_cli.add_arguments(parser, "synth")
    prof = PROFILES[parser.parse_args(["out"]).profile]
    assert (prof.frame_px, prof.camera_px, prof.n_fabrics) == ((640, 480), 1000, 50)


def test_the_visible_world_spreads_each_kinds_pitch_and_shares_what_the_camera_cannot_see():
    """The demo_visible world: a kind's fabrics differ in yarn pitch, one in each quarter of the
    kind's range (so none is another's twin), and sit near the kind's middle in what no camera sees;
    the same world in every process (a set's order once depended on the string hash seed)."""
    import subprocess
    import sys

    from vs2t_edge.sim.fabrics import _FAMILY, draw_world
    from vs2t_edge.sim.synth import PROFILES

    prof = PROFILES["demo_visible"]
    world = draw_world(prof.n_fabrics, 0, prof.constructions, prof.kind_spread)
    for kind in prof.constructions:
        mine = [p for p in world if p.construction == kind]
        (lo, hi), (h_lo, h_hi) = _FAMILY[kind][0], _FAMILY[kind][2]
        quarters = sorted(int((p.pitch_mm - lo) / (hi - lo) * len(mine)) for p in mine)
        assert quarters == list(range(len(mine))), (kind, [p.pitch_mm for p in mine])
        assert all(abs(p.hairiness - (h_lo + h_hi) / 2) < 0.25 * (h_hi - h_lo) + 0.01 for p in mine), kind
        assert not any(p.embroidery or p.jacquard for p in mine)
    code = ("from vs2t_edge.sim.synth import PROFILES, draw_world; p = PROFILES['demo_visible']; "
            "print([f.pitch_mm for f in draw_world(p.n_fabrics, 0, p.constructions, p.kind_spread)])")
    outs = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                           env={**os.environ, "PYTHONHASHSEED": str(seed)}).stdout for seed in (1, 2)}
    assert outs == {str([p.pitch_mm for p in world]) + "\n"}

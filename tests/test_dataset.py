"""The dataset loader accepts a well-formed folder and names fabric, file and problem otherwise."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from vs2t_edge.cli import main
from vs2t_edge.runtime.attributes import ATTRIBUTES, EXCLUSIVE_PAIRS
from vs2t_edge.runtime.dataset import (DatasetError, SensorGeometry, load_dataset, press_grid_mm,
                                        validate_dataset, write_dataset_meta, write_fabric,
                                        write_fabric_index)

GEOM = SensorGeometry(frame_width_px=64, frame_height_px=48, camera_image_px=100)


def _attrs(seed: int) -> list[int]:
    rng = np.random.default_rng(seed)
    a = rng.integers(0, 2, len(ATTRIBUTES))
    for x, y in EXCLUSIVE_PAIRS:  # respect the exclusive pairs
        if a[ATTRIBUTES.index(x)] and a[ATTRIBUTES.index(y)]:
            a[ATTRIBUTES.index(y)] = 0
    return a.tolist()


def _build(root: Path, n_fabrics: int = 3, n_presses: int = 2) -> Path:
    rng = np.random.default_rng(0)
    write_dataset_meta(root, GEOM, {"generator": "test"})
    index = []
    grid = press_grid_mm(n_presses, 1)
    for k in range(n_fabrics):
        fid, attrs = f"f{k:02d}", _attrs(k)
        img = lambda: rng.integers(40, 200, (48, 64, 3), dtype=np.uint8)
        presses = [(img(), x, y, 15.0) for x, y in grid]
        write_fabric(root, fid, f"fabric {k}", attrs, rng.integers(0, 255, (100, 100, 3), dtype=np.uint8),
                     img(), presses)
        index.append((fid, f"fabric {k}", attrs))
    write_fabric_index(root, index)
    return root


@pytest.fixture()
def good(tmp_path):
    return _build(tmp_path / "ds")


def _problems(root: Path) -> str:
    with pytest.raises(DatasetError) as info:
        validate_dataset(root, deep=True)
    return "\n".join(info.value.problems)


def _edit_yaml(path: Path, fn) -> None:
    doc = yaml.safe_load(path.read_text())
    fn(doc)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def _rewrite_csv(root: Path, fn) -> None:
    rows = list(csv.reader(open(root / "fabrics.csv")))
    fn(rows)
    with open(root / "fabrics.csv", "w", newline="") as fh:
        csv.writer(fh).writerows(rows)


def test_well_formed_dataset_loads(good):
    ds = validate_dataset(good, deep=True)
    assert ds.ids == ["f00", "f01", "f02"]
    assert ds.attribute_matrix().shape == (3, 24)
    f = ds.fabrics[0]
    assert f.load_press(1).shape == (48, 64, 3)
    crop = f.visual_crop(0)
    assert crop.shape[:2] == (round(11 * 100 / 80), round(15 * 100 / 80))


def test_missing_frame_is_named(good):
    (good / "f01" / "tactile" / "press_001.png").unlink()
    msg = _problems(good)
    assert "fabric 'f01' press 1" in msg and "press_001.png missing" in msg


def test_unreadable_frame_is_named(good):
    (good / "f02" / "tactile" / "press_000.png").write_bytes(b"not a png")
    msg = _problems(good)
    assert "fabric 'f02' press 0" in msg and "not a readable image" in msg


def test_wrong_size_frame_is_named(good):
    cv2.imwrite(str(good / "f00" / "tactile" / "press_001.png"), np.full((40, 50, 3), 99, np.uint8))
    msg = _problems(good)
    assert "fabric 'f00' press 1" in msg and "50x40" in msg and "64x48" in msg


def test_missing_reference_is_named(good):
    (good / "f00" / "reference.png").unlink()
    assert "fabric 'f00': no-contact reference frame f00/reference.png missing" in _problems(good)


def test_unknown_and_missing_attributes_are_named(good):
    def swap(doc):
        doc["attributes"]["sparkly"] = doc["attributes"].pop("hairy")
    _edit_yaml(good / "f01" / "fabric.yaml", swap)
    msg = _problems(good)
    assert "fabric 'f01'" in msg and "unknown attribute(s) ['sparkly']" in msg
    assert "missing attribute(s) ['hairy']" in msg


def test_unknown_attribute_column_in_index(good):
    _rewrite_csv(good, lambda rows: rows[0].__setitem__(10, "sparkly"))
    msg = _problems(good)
    assert "fabrics.csv" in msg and "sparkly" in msg and "fluffy" in msg


def test_exclusive_pair_both_true_is_named(good):
    def both(rows):
        rows[2][2 + ATTRIBUTES.index("stiff")] = "1"
        rows[2][2 + ATTRIBUTES.index("soft")] = "1"
    _rewrite_csv(good, both)
    msg = _problems(good)
    assert "fabric 'f01'" in msg and "'stiff' and 'soft' are both true" in msg


def test_duplicate_ids_are_named(good):
    _rewrite_csv(good, lambda rows: rows.append(list(rows[1])))
    assert "duplicate fabric id 'f00'" in _problems(good)


def test_press_off_the_piece_is_named(good):
    _edit_yaml(good / "f02" / "fabric.yaml", lambda d: d["presses"][1].__setitem__("x_mm", 95.0))
    msg = _problems(good)
    assert "fabric 'f02' press 1" in msg and "(95.0" in msg and "off the 80 mm x 80 mm piece" in msg


def test_attribute_disagreement_between_index_and_folder(good):
    def flip(doc):
        doc["attributes"]["shiny"] = 1 - doc["attributes"]["shiny"]
    _edit_yaml(good / "f00" / "fabric.yaml", flip)
    assert "disagree on ['shiny']" in _problems(good)


def test_all_problems_reported_at_once(good):
    (good / "f00" / "reference.png").unlink()
    (good / "f01" / "tactile" / "press_000.png").unlink()
    with pytest.raises(DatasetError) as info:
        load_dataset(good)
    assert len(info.value.problems) == 2


def test_validate_data_cli(good, capsys):
    assert main(["validate-data", str(good)]) == 0
    assert "3 fabrics, 6 presses" in capsys.readouterr().out
    shutil.rmtree(good / "f01")
    assert main(["validate-data", str(good)]) == 2
    assert "f01/fabric.yaml missing" in capsys.readouterr().err


REAL = Path(__file__).resolve().parents[2] / "shared" / "real" / "vitac_cloth11"


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/real absent (fresh machine)")
def test_real_visual_tactile_pair_loads_through_the_layout(tmp_path):
    """A real cloth (ViTac #11) converted into our layout loads and validates."""
    tactile = sorted((REAL / "11t").glob("*.jpg"))[:5]
    visual = sorted((REAL / "11v").glob("*.jpg"))[:1]
    assert tactile and visual, "expected JPEGs in vitac_cloth11/11t and 11v"
    frames = [cv2.imread(str(p)) for p in tactile]
    h, w = frames[0].shape[:2]
    geom = SensorGeometry(frame_width_px=w, frame_height_px=h, camera_image_px=cv2.imread(str(visual[0])).shape[1])
    root = tmp_path / "real"
    write_dataset_meta(root, geom, {"source": "vitac_cloth11 (test conversion)"})
    attrs = [0] * 24
    grid = press_grid_mm(len(frames) - 1, 1)
    write_fabric(root, "cloth11", "ViTac cloth 11", attrs, cv2.imread(str(visual[0])), frames[0],
                 [(f, x, y, 15.0) for f, (x, y) in zip(frames[1:], grid)])
    write_fabric_index(root, [("cloth11", "ViTac cloth 11", attrs)])
    ds = validate_dataset(root, deep=True)
    assert ds.fabrics[0].load_press(0).shape == (h, w, 3)

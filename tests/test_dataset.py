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


def test_wrong_size_or_non_square_camera_image_is_named(good):
    """dataset.yaml's camera.image_px is checked, not only that camera.png decodes."""
    cv2.imwrite(str(good / "f01" / "camera.png"), np.full((90, 100, 3), 99, np.uint8))  # not square
    cv2.imwrite(str(good / "f02" / "camera.png"), np.full((80, 80, 3), 99, np.uint8))  # square, wrong size
    msg = _problems(good)
    assert "fabric 'f01' camera image: f01/camera.png is 100x90, dataset.yaml says 100x100" in msg
    assert "fabric 'f02' camera image: f02/camera.png is 80x80, dataset.yaml says 100x100" in msg
    assert "f00/camera.png" not in msg


def test_bad_frames_raise_the_dataset_error_where_they_are_read(good):
    """load_dataset reads metadata only; the frame readers that train, export, calibrate and the
    simulated cell use raise DatasetError naming fabric, file and problem, not a cv2/numpy error."""
    cv2.imwrite(str(good / "f00" / "tactile" / "press_001.png"), np.full((40, 50, 3), 99, np.uint8))
    (good / "f01" / "reference.png").write_bytes(b"not a png")
    cv2.imwrite(str(good / "f02" / "camera.png"), np.full((90, 100, 3), 99, np.uint8))
    ds = load_dataset(good)  # metadata only: still loads
    f00, f01, f02 = ds.fabrics
    assert f00.load_press(0).shape == (48, 64, 3)  # good frames still read
    cases = [(lambda: f00.load_press(1), "fabric 'f00' press 1: f00/tactile/press_001.png is 50x40, "
                                         "dataset.yaml says 64x48"),
             (f01.load_reference, "fabric 'f01' no-contact reference frame: f01/reference.png is not a readable image"),
             (f02.load_camera, "fabric 'f02' camera image: f02/camera.png is 100x90, dataset.yaml says 100x100"),
             (lambda: f02.visual_crop(0), "f02/camera.png is 100x90")]
    for read, message in cases:
        with pytest.raises(DatasetError) as info:
            read()
        assert message in str(info.value)
    (good / "f00" / "tactile" / "press_000.png").unlink()
    with pytest.raises(DatasetError, match=r"fabric 'f00' press 0: f00/tactile/press_000.png missing"):
        f00.load_press(0)


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


def test_exclusive_pair_both_true_in_fabric_yaml_is_named(good):
    """Both sources are checked: a pair true in fabric.yaml is named as such, not only as a
    disagreement with fabrics.csv."""
    def both(doc):
        doc["attributes"]["cool"], doc["attributes"]["warm"] = 1, 1
    _edit_yaml(good / "f02" / "fabric.yaml", both)
    msg = _problems(good)
    assert "fabric 'f02' (f02/fabric.yaml): exclusive attributes 'cool' and 'warm' are both true" in msg
    assert "(fabrics.csv)" not in msg  # the index is consistent


def test_attribute_value_not_0_or_1_in_fabric_yaml_is_named(good):
    _edit_yaml(good / "f01" / "fabric.yaml", lambda d: d["attributes"].__setitem__("shiny", "maybe"))
    assert "fabric 'f01': f01/fabric.yaml attribute(s) ['shiny'] must be 0 or 1" in _problems(good)


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
    camera = _square(cv2.imread(str(visual[0])))  # the layout's camera image is square (camera.image_px)
    geom = SensorGeometry(frame_width_px=w, frame_height_px=h, camera_image_px=camera.shape[0])
    root = tmp_path / "real"
    write_dataset_meta(root, geom, {"source": "vitac_cloth11 (test conversion)"})
    attrs = [0] * 24
    grid = press_grid_mm(len(frames) - 1, 1)
    write_fabric(root, "cloth11", "ViTac cloth 11", attrs, camera, frames[0],
                 [(f, x, y, 15.0) for f, (x, y) in zip(frames[1:], grid)])
    write_fabric_index(root, [("cloth11", "ViTac cloth 11", attrs)])
    ds = validate_dataset(root, deep=True)
    assert ds.fabrics[0].load_press(0).shape == (h, w, 3)


def _square(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    side = min(h, w)
    return image[(h - side) // 2:(h - side) // 2 + side, (w - side) // 2:(w - side) // 2 + side]


def _jpeg_sources(kind: str) -> tuple[list[bytes], bytes, str]:
    """JPEG bytes of tactile frames (the first one serves as reference) and of a camera image.

    "real": ViTac cloth 11's own JPEG files from ../shared/real, byte for byte (it has no
    no-contact frame, so its first frame stands in). "synthetic": GelSight frames and a camera
    image of the fabric world encoded as JPEG, as a sensor that writes JPEG would store them."""
    if kind == "real":
        if not REAL.is_dir():
            pytest.skip("../shared/real absent (fresh machine)")
        tactile = sorted((REAL / "11t").glob("*.jpg"))[:4]
        visual = sorted((REAL / "11v").glob("*.jpg"))[:1]
        assert len(tactile) == 4 and visual, "expected JPEGs in vitac_cloth11/11t and 11v"
        cam = visual[0].read_bytes()
        image = cv2.imdecode(np.frombuffer(cam, np.uint8), cv2.IMREAD_COLOR)
        if image.shape[0] != image.shape[1]:  # 256x256 as published; crop if a copy is not square
            cam = cv2.imencode(".jpg", _square(image), [cv2.IMWRITE_JPEG_QUALITY, 92])[1].tobytes()
        return [p.read_bytes() for p in tactile], cam, "vitac_cloth11"
    from vs2t_edge.sim import fabrics, synth
    from vs2t_edge.sim.gelsight import GelSight, background, reference_frame, render_press

    sensor = GelSight(width_px=160, height_px=120, mm_per_px=15 / 160)
    rng = np.random.default_rng(0)
    bg = background(sensor, seed=1)
    fabric = fabrics.draw_fabric(rng, "corduroy")
    surface = synth.Surface(fabric)
    frames = [reference_frame(bg, sensor, rng)] + [
        render_press(synth.pressed_deformation(fabric, surface, 20.0 + 10 * k, 40.0, 15.0, 0.0, sensor, 1.0),
                     bg, sensor, rng) for k in range(3)]
    enc = [cv2.imencode(".jpg", f, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes() for f in frames]
    cam = cv2.imencode(".jpg", synth.camera_image(fabric, surface, 120), [cv2.IMWRITE_JPEG_QUALITY, 90])[1]
    return enc, cam.tobytes(), "fabric world, JPEG-encoded"


@pytest.mark.parametrize("kind", ["real", "synthetic"])
def test_dataset_with_jpeg_frames_loads_and_validates_as_jpeg(tmp_path, kind):
    """docs/dataset.md says frames are PNG or JPEG: a dataset whose camera image, reference and
    presses are .jpg files (not re-encoded as PNG) loads, validates deeply, and reads back the
    very pixels of those files; a wrong-size JPEG is named like a PNG would be."""
    tactile, camera, source = _jpeg_sources(kind)
    first = cv2.imdecode(np.frombuffer(tactile[0], np.uint8), cv2.IMREAD_COLOR)
    side = cv2.imdecode(np.frombuffer(camera, np.uint8), cv2.IMREAD_COLOR).shape[0]
    root = tmp_path / "jpeg"
    write_dataset_meta(root, SensorGeometry(frame_width_px=first.shape[1], frame_height_px=first.shape[0],
                                            camera_image_px=side), {"source": source})
    folder = root / "c0"
    (folder / "tactile").mkdir(parents=True)
    (folder / "camera.jpg").write_bytes(camera)
    (folder / "reference.jpg").write_bytes(tactile[0])
    presses = []
    for i, (data, (x, y)) in enumerate(zip(tactile[1:], press_grid_mm(len(tactile) - 1, 1))):
        (folder / "tactile" / f"press_{i:03d}.jpg").write_bytes(data)
        presses.append({"file": f"tactile/press_{i:03d}.jpg", "x_mm": x, "y_mm": y, "force_n": 15.0})
    attrs = _attrs(7)
    (folder / "fabric.yaml").write_text(yaml.safe_dump({
        "id": "c0", "name": "jpeg cloth", "camera": "camera.jpg", "reference": "reference.jpg",
        "attributes": dict(zip(ATTRIBUTES, attrs)), "presses": presses}, sort_keys=False))
    write_fabric_index(root, [("c0", "jpeg cloth", attrs)])

    ds = validate_dataset(root, deep=True)
    fab = load_dataset(root).fabrics[0]
    assert [p.path.suffix for p in fab.presses] == [".jpg"] * (len(tactile) - 1)
    assert all(p.path.read_bytes()[:2] == b"\xff\xd8" for p in fab.presses)  # still JPEG on disk
    for i, data in enumerate(tactile[1:]):
        assert np.array_equal(fab.load_press(i), cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR))
    assert np.array_equal(fab.load_reference(), first)
    assert fab.load_camera().shape == (side, side, 3) and fab.visual_crop(0).size > 0
    assert ds.attribute_matrix()[0].tolist() == attrs

    small = cv2.imencode(".jpg", first[: first.shape[0] // 2], [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
    (folder / "tactile" / "press_001.jpg").write_bytes(small)
    msg = _problems(root)
    assert f"fabric 'c0' press 1: c0/tactile/press_001.jpg is {first.shape[1]}x{first.shape[0] // 2}" in msg

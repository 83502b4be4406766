"""The dataset layout shared by the fabric world and real data (docs/dataset.md).

    ROOT/dataset.yaml           format, version, sensor and camera geometry, provenance
    ROOT/fabrics.csv            id, name, the 24 attributes (0/1) in the paper's order
    ROOT/<id>/fabric.yaml       name, attributes by name, files, presses (x_mm, y_mm, force_n)
    ROOT/<id>/camera.png        the camera image of the whole piece
    ROOT/<id>/reference.png     the no-contact GelSight frame
    ROOT/<id>/tactile/*.png     one GelSight frame per press

``load_dataset`` reads and cross-checks the metadata; ``validate_dataset(deep=True)`` also
decodes every image. Every problem is reported at once, each naming fabric, file and what is
wrong, so a person fixes a malformed dataset in one pass.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import cv2
import numpy as np
import yaml

from vs2t_edge.runtime.attributes import ATTRIBUTES, EXCLUSIVE_PAIRS, N_ATTRIBUTES
from vs2t_edge.runtime.files import MAX_CONFIG_BYTES, MAX_JSON_BYTES, InputRefused, read_image_file, read_regular_file

FORMAT_NAME = "vs2t-dataset"
FORMAT_VERSION = 1
PIECE_MM = 80.0  # the fabric piece is 8 cm x 8 cm
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")


class DatasetError(ValueError):
    """A malformed dataset. ``problems`` lists every problem found, one line each."""

    def __init__(self, root: Path | str, problems: Sequence[str]) -> None:
        self.root = Path(root)
        self.problems = list(problems)
        lines = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"dataset {self.root}: {len(self.problems)} problem(s)\n{lines}")


@dataclass(frozen=True)
class SensorGeometry:
    frame_width_px: int = 640
    frame_height_px: int = 480
    field_width_mm: float = 15.0  # the gel's field of view along x
    field_height_mm: float = 11.0
    camera_image_px: int = 1000  # the camera image of the 80 mm piece is square
    piece_mm: float = PIECE_MM

    @property
    def camera_px_per_mm(self) -> float:
        return self.camera_image_px / self.piece_mm

    @property
    def frame_hw(self) -> tuple[int, int]:
        """(height, width) of the tactile frames, px."""
        return self.frame_height_px, self.frame_width_px


@dataclass(frozen=True)
class Press:
    index: int
    path: Path
    x_mm: float  # press centre on the piece, origin at its top-left corner
    y_mm: float
    force_n: float


@dataclass(frozen=True)
class Fabric:
    id: str
    name: str
    folder: Path
    attributes: np.ndarray  # (24,) uint8, paper order
    camera_path: Path
    reference_path: Path
    presses: tuple[Press, ...]
    geometry: SensorGeometry

    # The readers every consumer goes through (train, export, calibrate, the simulated cell):
    # a frame that cannot be decoded or has the wrong size raises DatasetError naming fabric,
    # file and problem, the same message validate_dataset(deep=True) gives.

    def load_camera(self) -> np.ndarray:
        side = self.geometry.camera_image_px
        return self._load_checked("camera image", self.camera_path, (side, side), _CAMERA_KEY)

    def load_reference(self) -> np.ndarray:
        return self._load_checked("no-contact reference frame", self.reference_path, self.geometry.frame_hw)

    def load_press(self, i: int) -> np.ndarray:
        p = self.presses[i]
        return self._load_checked(f"press {p.index}", p.path, self.geometry.frame_hw)

    def _load_checked(self, label: str, path: Path, want_hw: tuple[int, int],
                      key: str = "") -> np.ndarray:
        image, problem = _read_checked(self, label, path, want_hw, key)
        if problem is not None:
            raise DatasetError(self.folder.parent, [problem])
        return image

    def visual_crop(self, i: int, camera: np.ndarray | None = None) -> np.ndarray:
        """The camera image's view of the patch under press ``i`` (same field as the gel)."""
        image = self.load_camera() if camera is None else camera
        p = self.presses[i]
        return crop_at(image, p.x_mm, p.y_mm, self.geometry)


@dataclass(frozen=True)
class Dataset:
    root: Path
    meta: dict
    geometry: SensorGeometry
    fabrics: tuple[Fabric, ...]

    def by_id(self, fabric_id: str) -> Fabric:
        for f in self.fabrics:
            if f.id == fabric_id:
                return f
        raise KeyError(f"dataset {self.root}: no fabric '{fabric_id}'")

    @property
    def ids(self) -> list[str]:
        return [f.id for f in self.fabrics]

    def attribute_matrix(self) -> np.ndarray:
        return np.stack([f.attributes for f in self.fabrics]).astype(np.uint8)


def read_image(path: Path | str, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Decode an image file as HxWx3 uint8 BGR; raise ValueError naming the file otherwise.

    The file must be a regular file (a FIFO would block the read forever); its size is read from
    the header and refused before decoding when it is over runtime/files.py's caps or not
    ``expected_hw`` (height, width). It is decoded as stored: a grey, RGBA or 16-bit image is
    refused, not converted - a GelSight sends 8-bit BGR, and a converted grey frame was scored
    with full confidence into a wrong bin.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file missing")
    try:
        image = read_image_file(path, expected_hw)
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    # InputRefused is a ValueError naming the file and the problem: it passes through
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        channels = 1 if image.ndim == 2 else image.shape[2]
        raise InputRefused(f"{path}: {channels} channel(s) of {image.dtype}, expected 3 channels of uint8 "
                           "(8-bit colour, as the sensor sends)", "format")
    return image


def _bounded_text(path: Path, max_bytes: int) -> str:
    """A dataset's text file (dataset.yaml, fabrics.csv, fabric.yaml): a regular file under a byte
    cap (a FIFO would block the read, a huge YAML takes minutes to parse), as UTF-8 text."""
    return read_regular_file(path, max_bytes, "dataset text file").decode("utf-8")


def crop_at(image: np.ndarray, x_mm: float, y_mm: float, geometry: SensorGeometry) -> np.ndarray:
    """Crop the camera image around (x_mm, y_mm) with the gel's field size; edge-padded."""
    scale = image.shape[1] / geometry.piece_mm
    w = max(1, int(round(geometry.field_width_mm * scale)))
    h = max(1, int(round(geometry.field_height_mm * scale)))
    cx, cy = x_mm * scale, y_mm * scale
    x0, y0 = int(round(cx - w / 2)), int(round(cy - h / 2))
    pad = max(w, h)
    padded = cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_REFLECT)
    return padded[y0 + pad:y0 + pad + h, x0 + pad:x0 + pad + w].copy()


PRESS_FRACTIONS = (0.7, 0.1, 0.2)  # training, validation, test presses of a touched fabric


def press_partition(n: int) -> tuple[range, range, range]:
    """Which of a touched fabric's ``n`` presses (in press order) fit, validate and test: earlier
    presses fit, later ones test - the cell is trained on what it touched before and meets the
    piece again afterwards, so a random permutation (neighbouring presses on both sides) flatters.
    At least one validation and one test press."""
    if n < 3:
        raise ValueError(f"{n} presses: need at least 3 to fit, validate and test")
    n_va, n_te = max(1, round(PRESS_FRACTIONS[1] * n)), max(1, round(PRESS_FRACTIONS[2] * n))
    n_tr = n - n_va - n_te
    return range(0, n_tr), range(n_tr, n_tr + n_va), range(n_tr + n_va, n)


def press_grid_mm(n_x: int = 15, n_y: int = 15, step_x_mm: float = 4.9, step_y_mm: float = 4.6,
                  piece_mm: float = PIECE_MM) -> list[tuple[float, float]]:
    """Press centres of an n_x x n_y grid centred on the piece, row by row."""
    span_x, span_y = (n_x - 1) * step_x_mm, (n_y - 1) * step_y_mm
    if span_x > piece_mm or span_y > piece_mm:
        raise ValueError(f"press grid {n_x}x{n_y} at {step_x_mm}x{step_y_mm} mm exceeds the {piece_mm} mm piece")
    x0, y0 = (piece_mm - span_x) / 2, (piece_mm - span_y) / 2
    return [(round(x0 + i * step_x_mm, 3), round(y0 + j * step_y_mm, 3))
            for j in range(n_y) for i in range(n_x)]


# --- writing (the fabric world and converters use this, so both sides share one layout) ---

def write_dataset_meta(root: Path, geometry: SensorGeometry, provenance: dict) -> None:
    root.mkdir(parents=True, exist_ok=True)
    meta = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "sensor": {
            "frame_width_px": geometry.frame_width_px,
            "frame_height_px": geometry.frame_height_px,
            "field_width_mm": geometry.field_width_mm,
            "field_height_mm": geometry.field_height_mm,
        },
        "camera": {"image_px": geometry.camera_image_px, "piece_mm": geometry.piece_mm},
        "provenance": provenance,
    }
    (root / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))


def write_fabric_index(root: Path, fabrics: Iterable[tuple[str, str, Sequence[int]]]) -> None:
    with open(root / "fabrics.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "name", *ATTRIBUTES])
        for fid, name, attrs in fabrics:
            w.writerow([fid, name, *[int(a) for a in attrs]])


def write_fabric(root: Path, fabric_id: str, name: str, attributes: Sequence[int], camera: np.ndarray,
                 reference: np.ndarray, presses: Sequence[tuple[np.ndarray, float, float, float]],
                 extra: dict | None = None) -> Path:
    """Write one fabric folder. ``presses``: (frame, x_mm, y_mm, force_n) in press order."""
    folder = root / fabric_id
    (folder / "tactile").mkdir(parents=True, exist_ok=True)
    _write_png(folder / "camera.png", camera)
    _write_png(folder / "reference.png", reference)
    entries = []
    for i, (frame, x_mm, y_mm, force_n) in enumerate(presses):
        rel = f"tactile/press_{i:03d}.png"
        _write_png(folder / rel, frame)
        entries.append({"file": rel, "x_mm": float(round(x_mm, 3)), "y_mm": float(round(y_mm, 3)),
                        "force_n": float(round(force_n, 3))})
    doc = {
        "id": fabric_id,
        "name": name,
        "camera": "camera.png",
        "reference": "reference.png",
        "attributes": {a: int(v) for a, v in zip(ATTRIBUTES, attributes)},
        "presses": entries,
    }
    if extra:
        doc["extra"] = extra
    (folder / "fabric.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return folder


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError(f"{path}: could not encode image")
    path.write_bytes(buf.tobytes())


# --- reading and validation --------------------------------------------------------------

def load_dataset(root: Path | str) -> Dataset:
    """Read and cross-check a dataset's metadata; raises DatasetError listing every problem."""
    return _load(Path(root), deep=False)


def validate_dataset(root: Path | str, deep: bool = True) -> Dataset:
    """As load_dataset, and with ``deep`` decode every image and check its size."""
    return _load(Path(root), deep=deep)


def _load(root: Path, deep: bool) -> Dataset:
    problems: list[str] = []
    if not root.is_dir():
        raise DatasetError(root, [f"{root}: not a folder"])
    meta, geometry = _read_meta(root, problems)
    index = _read_index(root, problems)
    fabrics: list[Fabric] = []
    for fid, name, attrs in index:
        fabric = _read_fabric(root, fid, name, attrs, geometry, problems)
        if fabric is not None:
            fabrics.append(fabric)
            if deep:
                _check_images(fabric, problems)
    if problems:
        raise DatasetError(root, problems)
    return Dataset(root=root, meta=meta, geometry=geometry, fabrics=tuple(fabrics))


def _read_meta(root: Path, problems: list[str]) -> tuple[dict, SensorGeometry]:
    path = root / "dataset.yaml"
    if not path.is_file():
        problems.append(f"{path.name}: missing (the dataset's format, sensor and camera geometry)")
        return {}, SensorGeometry()
    try:
        meta = yaml.safe_load(_bounded_text(path, MAX_CONFIG_BYTES)) or {}
    except (InputRefused, UnicodeDecodeError) as exc:
        problems.append(f"{path.name}: {str(exc).split(': ', 1)[-1]}")
        return {}, SensorGeometry()
    except yaml.YAMLError as exc:
        problems.append(f"{path.name}: not valid YAML: {exc}")
        return {}, SensorGeometry()
    if not isinstance(meta, dict):
        problems.append(f"{path.name}: must be a mapping")
        return {}, SensorGeometry()
    if meta.get("format") != FORMAT_NAME:
        problems.append(f"{path.name}: key 'format' must be '{FORMAT_NAME}', found {meta.get('format')!r}")
    if meta.get("version") != FORMAT_VERSION:
        problems.append(f"{path.name}: key 'version' must be {FORMAT_VERSION}, found {meta.get('version')!r}")
    sensor, camera = meta.get("sensor") or {}, meta.get("camera") or {}
    try:
        geometry = SensorGeometry(
            frame_width_px=int(sensor["frame_width_px"]),
            frame_height_px=int(sensor["frame_height_px"]),
            field_width_mm=float(sensor.get("field_width_mm", 15.0)),
            field_height_mm=float(sensor.get("field_height_mm", 11.0)),
            camera_image_px=int(camera.get("image_px", 1000)),
            piece_mm=float(camera.get("piece_mm", PIECE_MM)),
        )
    except (KeyError, TypeError, ValueError) as exc:
        problems.append(f"{path.name}: key 'sensor' needs frame_width_px and frame_height_px ({exc})")
        geometry = SensorGeometry()
    return meta, geometry


def _read_index(root: Path, problems: list[str]) -> list[tuple[str, str, np.ndarray]]:
    path = root / "fabrics.csv"
    if not path.is_file():
        problems.append("fabrics.csv: missing (the list of fabrics with their 24 attributes)")
        return []
    try:
        rows = list(csv.reader(io.StringIO(_bounded_text(path, MAX_JSON_BYTES), newline="")))
    except (InputRefused, UnicodeDecodeError) as exc:
        problems.append(f"fabrics.csv: {str(exc).split(': ', 1)[-1]}")
        return []
    if not rows:
        problems.append("fabrics.csv: empty")
        return []
    header = [h.strip() for h in rows[0]]
    expected = ["id", "name", *ATTRIBUTES]
    if header != expected:
        unknown = [h for h in header[2:] if h not in ATTRIBUTES]
        missing = [a for a in ATTRIBUTES if a not in header]
        detail = []
        if unknown:
            detail.append(f"unknown attribute(s) {unknown}")
        if missing:
            detail.append(f"missing attribute(s) {missing}")
        if not detail:
            detail.append("columns out of the paper's order")
        problems.append(f"fabrics.csv: header must be id, name and the 24 attributes in order: {'; '.join(detail)}")
        return []
    out: list[tuple[str, str, np.ndarray]] = []
    seen: set[str] = set()
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        where = f"fabrics.csv line {lineno}"
        if len(row) != len(expected):
            problems.append(f"{where}: {len(row)} columns, expected {len(expected)}")
            continue
        fid, name = row[0].strip(), row[1].strip()
        if not fid or "/" in fid or fid.startswith("."):
            problems.append(f"{where}: bad fabric id {fid!r}")
            continue
        if fid in seen:
            problems.append(f"{where}: duplicate fabric id '{fid}'")
            continue
        seen.add(fid)
        try:
            attrs = np.array([int(c) for c in row[2:]], dtype=np.int64)
        except ValueError:
            problems.append(f"fabric '{fid}' ({where}): attributes must be 0 or 1")
            continue
        if np.any((attrs != 0) & (attrs != 1)):
            bad = [ATTRIBUTES[i] for i in np.flatnonzero((attrs != 0) & (attrs != 1))]
            problems.append(f"fabric '{fid}' ({where}): attribute(s) {bad} must be 0 or 1")
            continue
        out.append((fid, name, attrs.astype(np.uint8)))
    return out


def _read_fabric(root: Path, fid: str, name: str, index_attrs: np.ndarray, geometry: SensorGeometry,
                 problems: list[str]) -> Fabric | None:
    folder = root / fid
    where = f"fabric '{fid}'"
    problems.extend(f"{where} (fabrics.csv): {p}" for p in _pair_conflicts(index_attrs))
    doc_path = folder / "fabric.yaml"
    if not doc_path.is_file():
        problems.append(f"{where}: {fid}/fabric.yaml missing")
        return None
    try:
        doc = yaml.safe_load(_bounded_text(doc_path, MAX_CONFIG_BYTES)) or {}
    except (InputRefused, UnicodeDecodeError) as exc:
        problems.append(f"{where}: {fid}/fabric.yaml: {str(exc).split(': ', 1)[-1]}")
        return None
    except yaml.YAMLError as exc:
        problems.append(f"{where}: {fid}/fabric.yaml is not valid YAML: {exc}")
        return None
    if not isinstance(doc, dict):
        problems.append(f"{where}: {fid}/fabric.yaml must be a mapping")
        return None
    if str(doc.get("id", fid)) != fid:
        problems.append(f"{where}: {fid}/fabric.yaml says id '{doc.get('id')}'")
    attrs_doc = doc.get("attributes")
    if not isinstance(attrs_doc, dict):
        problems.append(f"{where}: {fid}/fabric.yaml key 'attributes' must map each attribute name to 0 or 1")
    else:
        unknown = [k for k in attrs_doc if k not in ATTRIBUTES]
        missing = [a for a in ATTRIBUTES if a not in attrs_doc]
        if unknown:
            problems.append(f"{where}: {fid}/fabric.yaml unknown attribute(s) {unknown}")
        if missing:
            problems.append(f"{where}: {fid}/fabric.yaml missing attribute(s) {missing}")
        bad = [a for a in ATTRIBUTES if a in attrs_doc and attrs_doc[a] not in (0, 1)]
        if bad:
            problems.append(f"{where}: {fid}/fabric.yaml attribute(s) {bad} must be 0 or 1")
        if not unknown and not missing and not bad:
            by_name = np.array([int(attrs_doc[a]) for a in ATTRIBUTES])
            # each source is checked for exclusive pairs on its own, so the message names the pair
            # and the file instead of only saying that the two files disagree
            problems.extend(f"{where} ({fid}/fabric.yaml): {p}" for p in _pair_conflicts(by_name))
            if not np.array_equal(by_name, index_attrs):
                diff = [ATTRIBUTES[i] for i in np.flatnonzero(by_name != index_attrs)]
                problems.append(f"{where}: attributes in {fid}/fabric.yaml and fabrics.csv disagree on {diff}")
    camera = folder / str(doc.get("camera", "camera.png"))
    reference = folder / str(doc.get("reference", "reference.png"))
    for label, p in (("camera image", camera), ("no-contact reference frame", reference)):
        if not p.is_file():
            problems.append(f"{where}: {label} {p.relative_to(root)} missing")
    presses: list[Press] = []
    raw = doc.get("presses")
    if not isinstance(raw, list) or not raw:
        problems.append(f"{where}: {fid}/fabric.yaml key 'presses' must list at least one press")
        raw = []
    for i, entry in enumerate(raw):
        pw = f"{where} press {i}"
        try:
            rel = str(entry["file"])
            x, y, force = float(entry["x_mm"]), float(entry["y_mm"]), float(entry["force_n"])
        except (KeyError, TypeError, ValueError):
            problems.append(f"{pw}: needs file, x_mm, y_mm and force_n")
            continue
        path = folder / rel
        if not path.is_file():
            problems.append(f"{pw}: frame {path.relative_to(root)} missing")
        if not all(math.isfinite(v) for v in (x, y, force)):
            problems.append(f"{pw}: position or force not finite")
            continue
        # Press centres lie on the piece (the 15 x 15 grid spans 68.6 x 64.4 mm of its 80 mm).
        if not (0.0 <= x <= geometry.piece_mm and 0.0 <= y <= geometry.piece_mm):
            problems.append(f"{pw} ({rel}): grid position ({x}, {y}) mm is off the "
                            f"{geometry.piece_mm:g} mm x {geometry.piece_mm:g} mm piece")
        if not 0.0 < force <= 100.0:
            problems.append(f"{pw} ({rel}): force {force} N outside (0, 100]")
        presses.append(Press(index=i, path=path, x_mm=x, y_mm=y, force_n=force))
    return Fabric(id=fid, name=str(doc.get("name", name)), folder=folder, attributes=index_attrs,
                  camera_path=camera, reference_path=reference, presses=tuple(presses), geometry=geometry)


def _pair_conflicts(attrs: np.ndarray) -> list[str]:
    """One message per exclusive pair whose both sides are true in ``attrs`` (paper order)."""
    return [f"exclusive attributes '{a}' and '{b}' are both true" for a, b in EXCLUSIVE_PAIRS
            if attrs[ATTRIBUTES.index(a)] and attrs[ATTRIBUTES.index(b)]]


_CAMERA_KEY = " (camera.image_px: the 80 mm piece is square)"


def _read_checked(fabric: Fabric, label: str, path: Path, want_hw: tuple[int, int],
                  key: str) -> tuple[np.ndarray | None, str | None]:
    """Decode one image of ``fabric`` and check its size: (image, None) or (None, problem)."""
    where = f"fabric '{fabric.id}' {label}"
    try:
        rel = path.relative_to(fabric.folder.parent).as_posix()
    except ValueError:
        rel = str(path)
    try:
        image = read_image(path, want_hw)
    except InputRefused as exc:
        if exc.reason == "size":  # from the header, before decoding
            head = exc.header
            got = f"{head.width}x{head.height}" if head else "another size"
            return None, f"{where}: {rel} is {got}, dataset.yaml says {want_hw[1]}x{want_hw[0]}{key}"
        detail = str(exc).split(": ", 1)[-1]
        if exc.reason in ("format", "corrupt"):
            return None, f"{where}: {rel} is not a readable image ({detail})"
        return None, f"{where}: {rel} refused: {detail}"
    except ValueError:  # read_image says which; the file is looked for again only then
        return None, f"{where}: {rel} {'is not a readable image' if path.is_file() else 'missing'}"
    return image, None


def _check_images(fabric: Fabric, problems: list[str]) -> None:
    frame_hw = fabric.geometry.frame_hw
    side = fabric.geometry.camera_image_px
    paths = [("no-contact reference frame", fabric.reference_path, frame_hw, "")] + [
        (f"press {p.index}", p.path, frame_hw, "") for p in fabric.presses] + [
        ("camera image", fabric.camera_path, (side, side), _CAMERA_KEY)]
    for label, path, want, key in paths:
        if not path.is_file():
            continue  # already reported by _read_fabric
        _, problem = _read_checked(fabric, label, path, want, key)
        if problem is not None:
            problems.append(problem)

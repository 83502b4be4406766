"""A sample sheet so a person can judge the fabric world by eye.

    python -m vs2t_edge.sim.sample_sheet DATASET --out docs/sample_sheet.png [--fabrics 6]

One row per fabric: the camera image of the piece, the camera's crop under one press, the
GelSight frame of that press, the same frame minus the no-contact reference (contrast x3),
and the fabric's true attributes. Drawn with OpenCV only (the lean install has no matplotlib).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from vs2t_edge.runtime.attributes import ATTRIBUTES
from vs2t_edge.runtime.dataset import load_dataset

TILE_W, TILE_H = 176, 132
TEXT_W = 230
# The sheet is written losslessly (~1 MB for six paper-profile fabrics). It used to round pixel
# values to steps of up to 24 DN to stay under 300 KB, which painted blotches into the smooth
# parts of the frames — exactly where a person judges the realism.


def _fit(image: np.ndarray, w: int = TILE_W, h: int = TILE_H) -> np.ndarray:
    ih, iw = image.shape[:2]
    s = min(w / iw, h / ih)
    small = cv2.resize(image, (max(1, int(iw * s)), max(1, int(ih * s))), interpolation=cv2.INTER_AREA)
    tile = np.full((h, w, 3), 255, np.uint8)
    y0, x0 = (h - small.shape[0]) // 2, (w - small.shape[1]) // 2
    tile[y0:y0 + small.shape[0], x0:x0 + small.shape[1]] = small
    return tile


# Constructions that look different under a GelSight, shown first so one sheet spans the world;
# the construction is the first word(s) of a synthetic fabric's name. Real data falls back to order.
SHOWCASE = ("twill", "terry", "corduroy", "lace", "rib-knit", "hessian", "fleece", "denim", "satin", "felt")


def _pick(fabrics: list, n: int) -> list:
    chosen = []
    for kind in SHOWCASE:
        match = next((f for f in fabrics if f.name.startswith(kind + "-") and f not in chosen), None)
        if match is not None and len(chosen) < n:
            chosen.append(match)
    chosen += [f for f in fabrics if f not in chosen][:n - len(chosen)]
    return chosen


def sheet(dataset: Path, n_fabrics: int = 6) -> np.ndarray:
    ds = load_dataset(dataset)
    rows = []
    header = np.full((28, TILE_W * 4 + TEXT_W, 3), 255, np.uint8)
    for i, title in enumerate(("camera, 8 x 8 cm", "camera crop under the press", "GelSight frame",
                               "frame - reference (gain)")):
        cv2.putText(header, title, (i * TILE_W + 6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(header, "attributes", (4 * TILE_W + 6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    rows.append(header)
    for fabric in _pick(ds.fabrics, n_fabrics):
        k = len(fabric.presses) // 2
        camera = fabric.load_camera()
        frame, ref = fabric.load_press(k), fabric.load_reference()
        delta = frame.astype(np.float32) - ref
        # per-row gain so faint fabrics (velvet, felt) are visible too; the gain is printed
        gain = float(np.clip(60.0 / max(np.percentile(np.abs(delta), 99), 1e-3), 1.0, 12.0))
        diff = np.clip(delta * gain + 128, 0, 255).astype(np.uint8)
        text = np.full((TILE_H, TEXT_W, 3), 255, np.uint8)
        on = [a for a, v in zip(ATTRIBUTES, fabric.attributes) if v]
        lines = [fabric.name, ""] + [", ".join(on[j:j + 3]) for j in range(0, len(on), 3)]
        for j, line in enumerate(lines[:11]):
            cv2.putText(text, line, (6, 18 + 15 * j), cv2.FONT_HERSHEY_SIMPLEX, 0.4 if j else 0.45,
                        (0, 0, 0), 1, cv2.LINE_AA)
        diff_tile = _fit(diff)
        cv2.putText(diff_tile, f"x{gain:.1f}", (6, TILE_H - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                    cv2.LINE_AA)
        row = np.hstack([_fit(camera), _fit(fabric.visual_crop(k, camera)), _fit(frame), diff_tile, text])
        rows.append(np.vstack([row, np.full((4, row.shape[1], 3), 255, np.uint8)]))
    return np.vstack(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--out", type=Path, default=Path("docs/sample_sheet.png"))
    ap.add_argument("--fabrics", type=int, default=6)
    args = ap.parse_args(argv)
    image = sheet(args.dataset, args.fabrics)
    ok, png = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        print(f"sample_sheet: could not encode the {image.shape[1]}x{image.shape[0]} sheet as PNG", file=sys.stderr)
        return 2
    try:
        args.out.write_bytes(png.tobytes())
    except OSError as exc:
        print(f"sample_sheet: could not write {args.out}: {exc}", file=sys.stderr)
        return 2
    print(f"{args.out}: {image.shape[1]}x{image.shape[0]}, {len(png) // 1024} KB, lossless")
    return 0


if __name__ == "__main__":
    sys.exit(main())

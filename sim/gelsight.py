"""A GelSight as the fabric world needs it: a height map pressed into a gel, lit photometrically.

The sensor is a camera behind a painted elastomer lit by coloured lights from several sides.
A press deforms the gel; each pixel's colour change is a function of the local surface slope
(gx, gy). We model that function per channel as a quadratic in the slopes,

    I_c = bg_c + a_c * gx + b_c * gy + q_c * (gx^2 + gy^2)

(the first terms of the polynomial lookup a real GelSight is calibrated with; Taxim, Si & Yuan
2022). The coefficients below were fitted by least squares to 49 real presses of a ball on a real
GelSight (the MIT-licensed Taxim calibration pack, 120x160 at 0.1245 mm/px, kept outside the
repository in ../shared/real/taxim_calib); sim/realism.py refits them and reports the error.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

# Fitted on ../shared/real/taxim_calib by `python -m vs2t_edge.sim.realism` (least squares on 25
# real ball presses, scored on the other 24: contact-disc MAE 40.70 -> 15.75 DN; docs/realism.md).
# Rows: B, G, R (OpenCV order); columns: a (d/d gx), b (d/d gy), q (slope^2); slopes in mm/mm.
# UNFITTED_LIGHTS is the symmetric three-LED guess we started from, kept for the report.
FITTED_LIGHTS = np.array([
    [80.6, -145.8, -10.3],
    [36.5, 64.0, -75.5],
    [-132.3, -1.9, -66.6],
])
UNFITTED_LIGHTS = np.array([
    [-60.0, 35.0, 0.0],
    [0.0, -70.0, 0.0],
    [60.0, 35.0, 0.0],
])
# The mean no-contact colour of that real sensor (B, G, R), from its reference frame.
REAL_BG_BGR = (156.0, 145.6, 150.0)


@dataclass(frozen=True)
class GelSight:
    width_px: int = 640
    height_px: int = 480
    mm_per_px: float = 15.0 / 640
    lights: tuple = tuple(map(tuple, FITTED_LIGHTS))
    bg_bgr: tuple = REAL_BG_BGR
    gel_blur_mm: float = 0.06  # the elastomer low-pass: it cannot follow detail finer than this
    noise_dn: float = 1.2  # sensor read noise, digital numbers
    vignetting: float = 0.18  # fractional darkening at the corners
    markers: bool = True
    marker_pitch_mm: float = 1.8

    @property
    def field_mm(self) -> tuple[float, float]:
        return self.width_px * self.mm_per_px, self.height_px * self.mm_per_px


def background(sensor: GelSight, seed: int) -> np.ndarray:
    """The no-contact frame (float32 BGR): lit gel with vignetting, a colour gradient and markers."""
    rng = np.random.default_rng(seed)
    h, w = sensor.height_px, sensor.width_px
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    rx, ry = (xx - w / 2) / (w / 2), (yy - h / 2) / (h / 2)
    vign = 1.0 - sensor.vignetting * (rx ** 2 + ry ** 2) / 2
    bg = np.empty((h, w, 3), np.float32)
    tilt = rng.normal(0, 6, size=(3, 2))  # each LED brightens its own side a little
    for c in range(3):
        bg[..., c] = (sensor.bg_bgr[c] + tilt[c, 0] * rx + tilt[c, 1] * ry) * vign
    if sensor.markers:
        mask = marker_mask(sensor, rng)
        bg *= (1.0 - 0.55 * mask)[..., None]
    return bg


def marker_mask(sensor: GelSight, rng: np.random.Generator, shift_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    h, w = sensor.height_px, sensor.width_px
    pitch = sensor.marker_pitch_mm / sensor.mm_per_px
    radius = max(1.0, 0.18 / sensor.mm_per_px)
    mask = np.zeros((h, w), np.float32)
    for y in np.arange(pitch / 2, h, pitch):
        for x in np.arange(pitch / 2, w, pitch):
            cv2.circle(mask, (int(round(x + shift_px[0])), int(round(y + shift_px[1]))), int(round(radius)), 1.0, -1,
                       lineType=cv2.LINE_AA)
    return cv2.GaussianBlur(mask, (0, 0), radius / 2)


@lru_cache(maxsize=4)
def _marker_base(sensor: GelSight) -> np.ndarray:
    return marker_mask(sensor, np.random.default_rng(0))


def shade(deformation_mm: np.ndarray, sensor: GelSight, lights: np.ndarray | None = None) -> np.ndarray:
    """Colour change (float32 HxWx3 BGR) of the gel for a deformation map in mm."""
    lights = np.asarray(sensor.lights if lights is None else lights, np.float32)
    gy, gx = np.gradient(deformation_mm.astype(np.float32), sensor.mm_per_px)
    slope2 = gx * gx + gy * gy
    out = np.empty(deformation_mm.shape + (3,), np.float32)
    for c in range(3):
        out[..., c] = lights[c, 0] * gx + lights[c, 1] * gy + lights[c, 2] * slope2
    return out


def render_press(deformation_mm: np.ndarray, bg: np.ndarray, sensor: GelSight, rng: np.random.Generator,
                 marker_shift_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """One pressed frame (uint8 BGR): gel low-pass, photometric shading, markers, noise."""
    sigma = sensor.gel_blur_mm / sensor.mm_per_px
    gel = cv2.GaussianBlur(deformation_mm.astype(np.float32), (0, 0), sigma) if sigma > 0.3 else deformation_mm
    image = bg + shade(gel, sensor)
    if sensor.markers and any(marker_shift_px):
        # markers ride on the gel: the press shears them a little relative to the reference
        base = _marker_base(sensor)
        shift = np.float32([[1, 0, marker_shift_px[0]], [0, 1, marker_shift_px[1]]])
        moved = cv2.warpAffine(base, shift, (sensor.width_px, sensor.height_px), borderMode=cv2.BORDER_REFLECT)
        image *= ((1.0 - 0.55 * moved) / (1.0 - 0.55 * base))[..., None]
    image += rng.standard_normal(image.shape, dtype=np.float32) * np.float32(sensor.noise_dn)
    return np.clip(image, 0, 255).astype(np.uint8)


def reference_frame(bg: np.ndarray, sensor: GelSight, rng: np.random.Generator) -> np.ndarray:
    noisy = bg + rng.standard_normal(bg.shape, dtype=np.float32) * np.float32(sensor.noise_dn)
    return np.clip(noisy, 0, 255).astype(np.uint8)

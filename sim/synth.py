"""The synthetic fabric world: the stand-in for FabricVST that the project can reach.

Each fabric is drawn from hidden physical parameters (construction, yarn pitch and diameter,
hairiness, stiffness, thickness, relief, colour, print, stripes). Everything observable follows
from them: the 24 attributes as five simulated annotators would label them (majority vote), a
camera image of the 8 cm x 8 cm piece, and GelSight frames of presses on the grid.

Two rules keep the zero-shot problem honest:
- colour and print live only in the camera image: they never change a tactile frame;
- touch sees what vision sees only coarsely: the camera averages the weave over its 0.08 mm
  pixels, hairiness barely shows in it, stiffness not at all; the gel sees fibres and the
  indentation that stiffness and force decide.

The surface is a deterministic function of position on the piece (a procedural weave plus
sums of sinusoids with per-fabric random phases), so the camera, every press and a re-run
with the same seed agree exactly.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import sys
import time
from dataclasses import asdict, dataclass, fields, replace
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from vs2t_edge.runtime.attributes import ATTRIBUTES, EXCLUSIVE_PAIRS
from vs2t_edge.runtime.dataset import (SensorGeometry, press_grid_mm, write_dataset_meta, write_fabric,
                                        write_fabric_index)
from vs2t_edge.runtime.progress import Line
from vs2t_edge.sim.fabrics import FabricParams, draw_world
from vs2t_edge.sim.gelsight import GelSight, background, reference_frame, render_press

PIECE_MM = 80.0


@dataclass(frozen=True)
class SynthProfile:
    n_fabrics: int
    grid: tuple[int, int]  # presses per row, rows (a centred sub-grid of the paper's 15x15)
    frame_px: tuple[int, int]  # width, height of the GelSight frames
    camera_px: int
    markers: bool = True
    # None: every construction, drawn as ``draw_world`` always has; a tuple: only these, each as
    # often as the others (the demo's world, where each family is touched several times over)
    constructions: tuple[str, ...] | None = None
    # "drawn": every parameter drawn at random within its kind's ranges (what the camera cannot see
    # varies as much as what it can); "visible": the fabrics of a kind differ in yarn pitch, spread
    # evenly over the kind's range (relief follows it), and share the rest, near the kind's middle
    kind_spread: str = "drawn"


PROFILES: dict[str, SynthProfile] = {
    "tiny": SynthProfile(n_fabrics=10, grid=(3, 3), frame_px=(160, 120), camera_px=200),
    "small": SynthProfile(n_fabrics=20, grid=(5, 5), frame_px=(320, 240), camera_px=500),
    "paper": SynthProfile(n_fabrics=50, grid=(15, 15), frame_px=(640, 480), camera_px=1000),
    # The demo's world: 24 fabrics of 6 constructions that feel different (4 of each), so every
    # fabric the cell never touched has touched siblings of its kind, as in FabricVST; the small
    # profile's 20 fabrics of 14 constructions leave most kinds touched once or not at all, and its
    # zero-shot is at chance (docs/training.md). 7 x 7 presses: the last 10 of each touched fabric
    # are never trained on (runtime.dataset.press_partition), enough for a 5-press item.
    "demo": SynthProfile(n_fabrics=24, grid=(7, 7), frame_px=(320, 240), camera_px=500,
                         constructions=("plain", "rib_knit", "terry", "felt", "lace", "corduroy")),
    "demo_visible": SynthProfile(n_fabrics=24, grid=(7, 7), frame_px=(320, 240), camera_px=500,
                                 constructions=("rib_knit", "terry", "lace", "corduroy", "hessian", "felt"),
                                 kind_spread="visible"),
    # A paper-like world three times as wide (another draw, not the paper world's 50 plus 100), at
    # the 45 presses a fabric the paper profile trains on
    # (a 9 x 5 sub-grid): how zero-shot grows with the fabrics a cell has touched
    # (`vs2t-edge train DS --profile paper --touched N`, docs/results/zero_shot_limits_paper.md).
    "wide": SynthProfile(n_fabrics=150, grid=(9, 5), frame_px=(640, 480), camera_px=1000),
}


# --- attributes: five annotators and a majority vote -------------------------------------

def _attribute_scores(p: FabricParams) -> dict[str, float]:
    """What an annotator perceives, before noise: a score per attribute, 0 at the boundary."""
    rough = 2.2 * p.relief_mm / max(p.pitch_mm, 0.1) + 0.9 * p.hairiness * (p.construction != "velvet") \
        + 0.4 * (p.construction in ("hessian", "terry", "corduroy")) - 0.55
    thick = p.thickness_mm - 0.95
    warm = 0.9 * p.hairiness + 0.35 * p.thickness_mm - 0.5 * p.shininess - 0.55
    soft = 0.62 - p.stiffness + 0.25 * p.hairiness
    fluffy_heavy = p.hairiness - 0.45 * p.density / 2.0 - 0.25
    delicate = 0.35 * (p.construction in ("lace", "satin")) + 0.4 * (0.6 - p.thickness_mm) - 0.2 * p.stiffness
    return {
        "stiff/soft": -soft, "rough/smooth": rough, "thick/thin": thick, "cool/warm": -warm,
        "fluffy/heavy": fluffy_heavy, "delicate/durable": delicate,
        "stretchable": p.stretch - 0.5,
        "absorbent": p.absorbency - 0.55,
        "holey": p.hole_fraction - 0.12,
        "flat": 0.06 - p.relief_mm - 0.2 * p.embroidery,
        "bumpy": p.relief_mm + 0.2 * p.embroidery + 0.1 * p.jacquard - 0.17,
        "patterned": (p.print_kind != "none") * 1.0 + p.jacquard * 1.0 - 0.5,
        "striped": p.stripes - 0.5,
        "shiny": p.shininess - 0.5,
        "hairy": p.hairiness - 0.5,
        "embroidered": p.embroidery - 0.5,
        "jacquard": p.jacquard - 0.5,
        "pigment printed": (p.print_kind != "none") - 0.5,
    }


# Paired attributes: FabricVST's pairs nearly partition the 50 fabrics (soft 38 + stiff 11 = 49,
# rough 30 + smooth 20 ...). Each annotator picks a side or, near the boundary, neither.
_PAIR_NEITHER_BAND = {"stiff/soft": 0.03, "rough/smooth": 0.0, "thick/thin": 0.0, "cool/warm": 0.0,
                      "fluffy/heavy": 0.25, "delicate/durable": 0.12}
# Base rates out of 50 in FabricVST for the first side of each pair we can check (DESIGN/issue).
TARGET_RATES = {"soft": 38 / 50, "rough": 30 / 50, "thick": 27 / 50, "warm": 26 / 50, "cool": 24 / 50,
                "thin": 23 / 50, "smooth": 20 / 50, "stiff": 11 / 50}
N_ANNOTATORS = 5
ANNOTATOR_NOISE = 0.12  # in score units: how much two people disagree


@lru_cache(maxsize=1)
def _pair_offsets() -> dict[str, float]:
    """Shift each pair's boundary so that the population's rates match FabricVST's.

    Calibrated once on a fixed population of 6000 drawn fabrics (seed 12345), so every world
    shares the same labelling rule."""
    pop = draw_world(6000, seed=12345)
    scores = {k: np.array([_attribute_scores(p)[k] for p in pop]) for k in _PAIR_NEITHER_BAND}
    first_rate = {"stiff/soft": 1 - TARGET_RATES["soft"], "rough/smooth": TARGET_RATES["rough"],
                  "thick/thin": TARGET_RATES["thick"], "cool/warm": TARGET_RATES["cool"]}
    offsets = {}
    for key, s in scores.items():
        rate = first_rate.get(key, 0.4)
        if key == "stiff/soft":  # stiff is the score's positive side; soft its negative side
            offsets[key] = float(np.quantile(s, 1 - TARGET_RATES["stiff"]))
            offsets["stiff/soft:soft"] = float(np.quantile(s, TARGET_RATES["soft"]))
        else:
            offsets[key] = float(np.quantile(s, 1 - rate))
    return offsets


def label_attributes(p: FabricParams, rng: np.random.Generator) -> np.ndarray:
    scores = _attribute_scores(p)
    off = _pair_offsets()
    votes = np.zeros((N_ANNOTATORS, len(ATTRIBUTES)), np.int8)
    for a in range(N_ANNOTATORS):
        noise = rng.normal(0, ANNOTATOR_NOISE, size=len(scores))
        for (key, s), n in zip(scores.items(), noise):
            if "/" in key:
                first, second = key.split("/")
                v = s + n
                if key == "stiff/soft":
                    if v > off[key]:
                        votes[a, ATTRIBUTES.index(first)] = 1
                    elif v < off["stiff/soft:soft"]:
                        votes[a, ATTRIBUTES.index(second)] = 1
                    continue
                band = _PAIR_NEITHER_BAND[key]
                if v > off[key] + band / 2:
                    votes[a, ATTRIBUTES.index(first)] = 1
                elif v < off[key] - band / 2:
                    votes[a, ATTRIBUTES.index(second)] = 1
            else:
                votes[a, ATTRIBUTES.index(key)] = int(s + n > 0)
    attrs = (votes.sum(axis=0) * 2 > N_ANNOTATORS).astype(np.uint8)
    for x, y in EXCLUSIVE_PAIRS:  # a majority can never hold both sides, but make it explicit
        assert not (attrs[ATTRIBUTES.index(x)] and attrs[ATTRIBUTES.index(y)])
    return attrs


# --- the surface --------------------------------------------------------------------------

def _profile(t: np.ndarray, fill: float) -> np.ndarray:
    """Cross-section of a yarn centred on integers of t: a rounded bump of width `fill`."""
    d = np.abs(t - np.round(t)) / max(fill / 2, 1e-3)
    return np.sqrt(np.clip(1.0 - d * d, 0.0, 1.0))


class Surface:
    """Height (mm) of one fabric's top surface at any point of the piece, before pressing."""

    def __init__(self, p: FabricParams) -> None:
        self.p = p
        rng = np.random.default_rng(p.phase_seed)
        self._hair = self._sinusoids(rng, 48, 2.5, 9.0)  # fibres: fine, random
        self._slub = self._sinusoids(rng, 16, 0.15, 0.6)  # yarn thickness irregularity, low-frequency
        self._pile = self._sinusoids(rng, 40, 0.8 / max(p.pitch_mm, 0.2), 2.5 / max(p.pitch_mm, 0.2))
        self._motif = self._sinusoids(rng, 6, 0.06, 0.16)  # embroidery / jacquard / lace motif scale
        self._defects = rng.uniform(0, PIECE_MM, size=(4, 2))  # a few pulled threads / knots

    @staticmethod
    def _sinusoids(rng: np.random.Generator, k: int, f_lo: float, f_hi: float) -> tuple[np.ndarray, ...]:
        f = rng.uniform(f_lo, f_hi, k) * 2 * np.pi  # radians per mm
        theta = rng.uniform(0, np.pi, k)
        amp = rng.uniform(0.5, 1.0, k) / np.sqrt(k / 2)
        return f * np.cos(theta), f * np.sin(theta), rng.uniform(0, 2 * np.pi, k), amp

    @staticmethod
    def _field(comp: tuple[np.ndarray, ...], x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Sum of sinusoids on the grid x (W,) by y (H,), as two matrix products (separable)."""
        a, b, phi, amp = comp
        ax, by = np.outer(x, a), np.outer(y, b) + phi  # (W,k), (H,k)
        return (np.cos(by) * amp) @ np.sin(ax).T + (np.sin(by) * amp) @ np.cos(ax).T

    def height(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Heights (H, W) on the axis-aligned grid x_mm (W,) by y_mm (H,)."""
        p = self.p
        X, Y = np.meshgrid(x_mm, y_mm)
        ang = math.radians(p.weave_angle_deg)
        U = (X * math.cos(ang) + Y * math.sin(ang)) / p.pitch_mm
        V = (-X * math.sin(ang) + Y * math.cos(ang)) / p.pitch_mm
        slub = 1.0 + 0.25 * self._field(self._slub, x_mm, y_mm) * (1.5 if p.construction == "hessian" else 0.6)
        h = self._structure(U, V, x_mm, y_mm, p) * p.relief_mm * slub
        if p.jacquard:  # the motif swaps the float direction: a woven figure in relief
            figure = self._field(self._motif, x_mm, y_mm) > 0.2
            h = np.where(figure, self._weave(V, U, 5, 2, 4, p.yarn_fill) * p.relief_mm * 1.2, h)
        if p.embroidery:  # raised satin-stitch lines along a motif contour
            m = self._field(self._motif, x_mm, y_mm)
            h = h + 0.22 * np.exp(-(m / 0.12) ** 2) * (0.6 + 0.4 * _profile(U * 3, 0.8))
        if p.hole_fraction > 0:
            m = self._field(self._motif, x_mm * 3.0, y_mm * 3.0)
            holes = m > np.quantile(m, 1.0 - p.hole_fraction) if m.size > 64 else m > 0.8
            h = np.where(holes, -p.thickness_mm, h)
        if p.hairiness > 0:
            fibres = np.abs(self._field(self._hair, x_mm, y_mm))
            h = h + p.hairiness * 0.035 * np.minimum(fibres, 1.5) ** 2  # fibres stand off <= ~0.08 mm
        for dx, dy in self._defects:  # a knot or slub: a local bump of one yarn's height
            r2 = (X - dx) ** 2 + (Y - dy) ** 2
            h = h + 0.6 * p.relief_mm * np.exp(-r2 / (2 * (1.5 * p.pitch_mm) ** 2))
        return h.astype(np.float32)

    def _structure(self, U: np.ndarray, V: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray,
                   p: FabricParams) -> np.ndarray:
        c, fill = p.construction, p.yarn_fill
        if c in ("plain", "hessian", "lace"):
            return self._weave(U, V, 2, 1, 1, fill)
        if c in ("twill", "denim"):
            return self._weave(U, V, 4 if c == "denim" else 3, 1, 2 if c == "twill" else 3, fill)
        if c == "satin":
            return self._weave(U, V, 5, 2, 4, fill) * 0.7
        if c == "herringbone":
            flip = (np.floor(U / 6) % 2) * 2 - 1  # the twill's direction reverses every 6 yarns
            return self._weave(U, V * flip, 3, 1, 2, fill)
        if c == "rib_knit":
            return _profile(U / 2, 0.9) ** 0.7 * (0.75 + 0.25 * _profile(V * 2, 0.9))
        if c == "jersey":  # columns of V-shaped loops
            row = V - np.floor(V)
            return _profile(U * 2 + (np.abs(row - 0.5) - 0.25) * np.sign(np.sin(np.pi * U * 2)), fill)
        if c == "terry":  # upright loops: a dense, tall, irregular pile
            return 0.5 + 0.5 * np.tanh(1.5 * self._field(self._pile, x_mm, y_mm))
        if c in ("fleece", "velvet"):
            return 0.5 + 0.35 * self._field(self._pile, x_mm, y_mm)
        if c == "felt":
            return 0.5 + 0.3 * self._field(self._pile, x_mm, y_mm)
        if c == "corduroy":  # wide wales with a cut pile on top
            return _profile(U, 0.85) ** 0.5 * (0.85 + 0.15 * self._field(self._pile, x_mm * 6, y_mm * 6))
        raise ValueError(f"unknown construction {c}")

    @staticmethod
    def _weave(U: np.ndarray, V: np.ndarray, repeat: int, shift: int, float_len: int, fill: float) -> np.ndarray:
        """Warp along V, weft along U; at each crossing the warp is on top for `float_len` of `repeat`."""
        i, j = np.floor(U), np.floor(V)
        warp_top = ((i + shift * j) % repeat) < float_len
        warp = _profile(U - 0.5, fill)  # warp yarns centred in each column
        weft = _profile(V - 0.5, fill)
        along_warp = 0.55 + 0.45 * np.cos(np.pi * (V - j - 0.5))  # yarns dip where they pass under
        along_weft = 0.55 + 0.45 * np.cos(np.pi * (U - i - 0.5))
        return np.where(warp_top, np.maximum(warp * along_warp, 0.45 * weft), np.maximum(weft * along_weft, 0.45 * warp))


# --- camera ---------------------------------------------------------------------------------

def camera_image(p: FabricParams, surface: Surface, size_px: int) -> np.ndarray:
    """The piece as the camera sees it (BGR uint8): colour, print, stripes, coarse weave shading."""
    coords = (np.arange(size_px) + 0.5) * PIECE_MM / size_px
    # The camera resolves structure only at its own pixel scale: sample the surface 2x finer and
    # average down, which is what the lens and sensor do (and hides fibres and fine yarns).
    fine = (np.arange(size_px * 2) + 0.5) * PIECE_MM / (size_px * 2)
    h = cv2.resize(surface.height(fine, fine), (size_px, size_px), interpolation=cv2.INTER_AREA)
    gy, gx = np.gradient(h, PIECE_MM / size_px)
    shading = 0.78 + 0.22 * np.tanh(-(gx + 0.6 * gy) * 1.2) + 0.15 * np.tanh(h / max(p.relief_mm, 0.05) - 0.5)
    hue, sat, val = p.colour_hsv
    hsv = np.zeros((size_px, size_px, 3), np.float32)
    hsv[..., 0], hsv[..., 1], hsv[..., 2] = hue, sat, val
    rng = np.random.default_rng(p.phase_seed + 1)
    X, Y = np.meshgrid(coords, coords)
    if p.stripes:
        width = rng.uniform(3, 10)
        band = (np.floor(Y / width) % 2 == 1) if rng.random() < 0.5 else (np.floor(X / width) % 2 == 1)
        hsv[..., 0] = np.where(band, (hue + 90) % 180, hue)
        hsv[..., 2] = np.where(band, np.clip(val * 0.6 + 0.3, 0, 1), val)
    if p.print_kind != "none":
        ink_hue = (hue + rng.uniform(40, 140)) % 180
        if p.print_kind == "dots":
            pitch = rng.uniform(4, 9)
            ink = ((X % pitch - pitch / 2) ** 2 + (Y % pitch - pitch / 2) ** 2) < (pitch * 0.22) ** 2
        elif p.print_kind == "geometric":
            pitch = rng.uniform(6, 14)
            ink = (np.abs((X + Y) % pitch - pitch / 2) < pitch * 0.12) | (np.abs((X - Y) % pitch - pitch / 2) < pitch * 0.08)
        else:  # floral: blobs from a low-frequency field
            field = Surface._field(Surface._sinusoids(rng, 10, 0.05, 0.2), coords, coords)
            ink = field > 0.55
        hsv[..., 0] = np.where(ink, ink_hue, hsv[..., 0])
        hsv[..., 1] = np.where(ink, np.clip(sat + 0.3, 0, 1), hsv[..., 1])
        hsv[..., 2] = np.where(ink, np.clip(val * 0.8, 0, 1), hsv[..., 2])
    hsv[..., 2] = np.clip(hsv[..., 2] * shading + p.shininess * 0.25 * np.clip(-gx, 0, 1), 0, 1)
    # hairiness: a faint haze that lowers contrast a little; colour is untouched by touch
    hsv[..., 1] *= 1.0 - 0.2 * p.hairiness
    holes = h < -0.5 * p.thickness_mm
    bgr = cv2.cvtColor(np.dstack([hsv[..., 0] * 2, hsv[..., 1], hsv[..., 2]]).astype(np.float32), cv2.COLOR_HSV2BGR)
    bgr[holes] = (0.12, 0.12, 0.13)  # the dark table shows through the holes
    bgr += rng.normal(0, 0.01, bgr.shape).astype(np.float32)
    return np.clip(bgr * 255, 0, 255).astype(np.uint8)


# --- pressing ------------------------------------------------------------------------------

def pressed_deformation(p: FabricParams, surface: Surface, x_mm: float, y_mm: float, force_n: float,
                        rot_deg: float, sensor: GelSight, work_scale: float) -> np.ndarray:
    """How far the gel is pushed in (mm) at each pixel for one press at (x_mm, y_mm)."""
    w_mm, h_mm = sensor.field_mm
    wp, hp = max(8, int(sensor.width_px * work_scale)), max(8, int(sensor.height_px * work_scale))
    # Sample a margin around the field so the small per-press rotation stays filled
    # (|rot| <= ~6 deg needs sin(6 deg) * width of margin; a rectangle, not the diagonal's square).
    margin = int(math.ceil(abs(math.sin(math.radians(min(abs(rot_deg), 8.0) + 1.0))) * max(wp, hp))) + 2
    nw, nh = wp + 2 * margin, hp + 2 * margin
    px_mm = w_mm / wp
    xs = (np.arange(nw) - nw / 2 + 0.5) * px_mm
    ys = (np.arange(nh) - nh / 2 + 0.5) * px_mm
    h = surface.height(x_mm + xs, y_mm + ys)
    rot = cv2.getRotationMatrix2D((nw / 2, nh / 2), rot_deg, 1.0)
    h = cv2.warpAffine(h, rot, (nw, nh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    h = h[margin:margin + hp, margin:margin + wp]
    # Indentation: the gel sinks until the fabric carries the force. A compliant fabric lets
    # more of its surface touch (and is itself squashed, flattening its relief); a stiff one
    # carries the load on its peaks alone.
    compliance = (1.0 - 0.8 * p.stiffness) * (0.5 + 0.5 * min(p.thickness_mm, 3.0) / 3.0)
    contact = float(np.clip(0.2 + 0.55 * compliance * force_n / 15.0, 0.05, 0.95))
    level = float(np.quantile(h, 1.0 - contact))
    squash = 1.0 - 0.45 * compliance
    deform = np.clip(h - level, 0.0, None) * squash
    deform = cv2.resize(deform, (sensor.width_px, sensor.height_px), interpolation=cv2.INTER_CUBIC)
    return deform


def fabric_params(params: object, where: str = "fabric.yaml") -> FabricParams:
    """A fabric's hidden parameters as ``generate`` stores them (fabric.yaml ``extra.params``),
    back as FabricParams; a missing or unknown key is named."""
    names = [f.name for f in fields(FabricParams)]
    if not isinstance(params, dict):
        raise ValueError(f"{where}: extra.params is not a mapping (only a synthetic world's fabric.yaml has one)")
    missing, unknown = sorted(set(names) - set(params)), sorted(set(params) - set(names))
    if missing or unknown:
        raise ValueError(f"{where}: extra.params" + (f" lacks {missing}" if missing else "")
                         + (f" has unknown {unknown}" if unknown else ""))
    d = dict(params)
    d["colour_hsv"] = tuple(float(v) for v in d["colour_hsv"])
    return FabricParams(**d)


def render_fabric(p: FabricParams, profile: str, index: int, seed: int, *, markers: bool = True,
                  presses: list[int] | None = None) -> tuple[np.ndarray, np.ndarray, list[tuple]]:
    """(camera image, no-contact frame, [(frame, x_mm, y_mm, force_n)]) of fabric ``index`` of the
    world ``generate(..., profile, seed)`` draws: with ``presses`` None, every grid point, the
    dataset's own frames bit for bit. ``presses`` (grid indices) renders only those, with press noise
    from a stream of its own: other presses at the same points (``train/world_check.py`` re-renders
    a fabric so, with its parameters or another ``phase_seed``)."""
    prof = PROFILES[profile]
    surface = Surface(p)
    # Markers only darken the gel (no random draws), so switching them off leaves every other
    # pixel of the world as it was: same seed, same fabrics, same presses, no dots.
    sensor = GelSight(width_px=prof.frame_px[0], height_px=prof.frame_px[1], mm_per_px=15.0 / prof.frame_px[0],
                      markers=markers)
    rng = np.random.default_rng([seed, index, 7])
    bg = background(sensor, seed=seed * 1000 + index)
    reference = reference_frame(bg, sensor, rng)
    camera = camera_image(p, surface, prof.camera_px)
    work_scale = 0.5 if prof.frame_px[0] >= 480 else 1.0  # the gel blurs finer detail anyway
    grid = _grid(prof)
    if presses is not None:
        rng = np.random.default_rng([seed, index, 7, 1])
        grid = [grid[i] for i in presses]
    out = []
    for x, y in grid:
        force = float(np.clip(rng.normal(15.0, 1.0), 11.0, 19.0))
        rot = float(rng.normal(0, 2.0))
        jx, jy = rng.normal(0, 0.15, 2)  # the arm's placement repeatability
        deform = pressed_deformation(p, surface, x + jx, y + jy, force, rot, sensor, work_scale)
        shift = tuple(rng.normal(0, 0.3, 2) * prof.frame_px[0] / 640)  # press shear moves markers slightly
        frame = render_press(deform, bg, sensor, rng, marker_shift_px=shift)
        out.append((frame, x, y, force))
    return camera, reference, out


def _render_fabric(args: tuple) -> tuple:
    index, params, attrs, profile_name, seed, markers = args
    return (index, *render_fabric(params, profile_name, index, seed, markers=markers))


def _grid(prof: SynthProfile) -> list[tuple[float, float]]:
    full = press_grid_mm()  # the paper's 15 x 15 grid, row by row
    nx, ny = prof.grid
    cols = np.round(np.linspace(0, 14, nx)).astype(int)
    rows = np.round(np.linspace(0, 14, ny)).astype(int)
    return [full[r * 15 + c] for r in rows for c in cols]


def fabric_name(i: int, p: FabricParams) -> str:
    colour = ("red", "orange", "yellow", "lime", "green", "teal", "cyan", "blue", "indigo", "violet", "purple",
              "pink")[int(p.colour_hsv[0] / 15) % 12]
    if p.colour_hsv[1] < 0.2:
        colour = "grey" if p.colour_hsv[2] > 0.35 else "black"
    return f"{p.construction.replace('_', '-')}-{colour}-{i:02d}"


def generate(root: str | Path, profile: str = "small", seed: int = 0, progress: bool = True,
             n_fabrics: int | None = None, workers: int | None = None, markers: bool = True) -> Path:
    """Write a fabric-world dataset (docs/dataset.md) to ``root``; deterministic from ``seed``.

    ``markers=False`` renders the GelSight frames without marker dots (a sensor with an unmarked
    gel); everything else is the same world as with markers."""
    if profile not in PROFILES:
        raise ValueError(f"unknown profile '{profile}'; choose one of {sorted(PROFILES)}")
    prof = PROFILES[profile]
    if n_fabrics is not None:
        prof = replace(prof, n_fabrics=int(n_fabrics))
    markers = bool(markers and prof.markers)
    root = Path(root)
    world = draw_world(prof.n_fabrics, seed, prof.constructions, prof.kind_spread)
    label_rng = np.random.default_rng([seed, 99])
    attrs = [label_attributes(p, label_rng) for p in world]
    w, h = prof.frame_px
    geometry = SensorGeometry(frame_width_px=w, frame_height_px=h, field_width_mm=15.0,
                              field_height_mm=round(15.0 * h / w, 4), camera_image_px=prof.camera_px)
    provenance = {"generator": "vs2t-edge fabric world (sim/synth.py)", "profile": profile,
                  "seed": seed, "n_fabrics": prof.n_fabrics, "grid": list(prof.grid)}
    if not markers:  # recorded only when off, so a default world's dataset.yaml stays byte-identical
        provenance["markers"] = False
    write_dataset_meta(root, geometry, provenance)
    ids = [f"f{i:02d}" for i in range(len(world))]
    names = [fabric_name(i, p) for i, p in enumerate(world)]
    jobs = [(i, p, a, profile, seed, markers) for i, (p, a) in enumerate(zip(world, attrs))]
    start = time.monotonic()
    line = Line()
    n_workers = workers if workers is not None else min(2, len(jobs))
    done = 0

    def _write(result: tuple) -> None:
        nonlocal done
        i, camera, reference, presses = result
        write_fabric(root, ids[i], names[i], attrs[i], camera, reference, presses,
                     extra={"params": _plain(asdict(world[i]))})
        done += 1
        if progress:
            el = time.monotonic() - start
            eta = el / done * (len(jobs) - done)
            line.draw(f"synth {profile}: {done}/{len(jobs)} fabrics, {el:5.1f}s elapsed, ~{eta:5.1f}s left",
                      done / len(jobs))

    if n_workers > 1:
        ctx = mp.get_context("fork" if sys.platform != "win32" else "spawn")
        with ctx.Pool(n_workers) as pool:
            for result in pool.imap_unordered(_render_fabric, jobs):
                _write(result)
    else:
        for job in jobs:
            _write(_render_fabric(job))
    # The index is written last: a folder without fabrics.csv is visibly unfinished.
    write_fabric_index(root, [(ids[i], names[i], attrs[i]) for i in range(len(world))])
    if progress:
        line.keep()
    return root


def _plain(d: dict) -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, tuple):
            v = [float(x) for x in v]
        elif isinstance(v, (np.floating, np.integer)):
            v = v.item()
        out[k] = v
    return out

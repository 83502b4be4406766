"""Drawing the synthetic world's fabrics: each construction's ranges of hidden physical parameters,
and a world of fabrics drawn from them (sim/synth.py renders what is observable of each).

``kind_spread`` "drawn" (every profile but one): every parameter drawn at random within its kind's
ranges, what no camera sees varying as much as what it does. "visible" (the demo_visible profile,
docs/results/demo_visible_world.md): a kind's fabrics differ in yarn pitch, spread one per equal
part of the kind's range (relief follows it), and share the rest near the kind's middle."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

KIND_SPREADS = ("drawn", "visible")

CONSTRUCTIONS = ("plain", "twill", "satin", "herringbone", "rib_knit", "jersey", "terry", "fleece",
                 "felt", "lace", "corduroy", "hessian", "denim", "velvet")

# construction -> (pitch mm range, relief mm range, hairiness range, stiffness range,
#                  thickness mm range, stretch, absorbency)
_FAMILY = {
    "plain":       ((0.20, 0.55), (0.04, 0.10), (0.05, 0.35), (0.25, 0.65), (0.25, 0.7), 0.1, 0.5),
    "twill":       ((0.25, 0.60), (0.05, 0.12), (0.05, 0.30), (0.35, 0.75), (0.45, 1.0), 0.1, 0.5),
    "satin":       ((0.15, 0.35), (0.02, 0.05), (0.00, 0.10), (0.20, 0.50), (0.20, 0.5), 0.1, 0.2),
    "herringbone": ((0.35, 0.70), (0.06, 0.13), (0.10, 0.40), (0.40, 0.75), (0.6, 1.3), 0.1, 0.5),
    "rib_knit":    ((0.60, 1.30), (0.10, 0.22), (0.10, 0.40), (0.10, 0.35), (0.8, 1.8), 0.9, 0.6),
    "jersey":      ((0.35, 0.70), (0.04, 0.10), (0.05, 0.35), (0.05, 0.30), (0.3, 0.8), 0.8, 0.6),
    "terry":       ((0.80, 1.60), (0.20, 0.40), (0.45, 0.80), (0.10, 0.35), (1.8, 3.5), 0.2, 0.95),
    "fleece":      ((0.50, 1.00), (0.06, 0.15), (0.70, 1.00), (0.05, 0.25), (1.5, 3.5), 0.5, 0.6),
    "felt":        ((0.40, 0.90), (0.03, 0.08), (0.40, 0.75), (0.50, 0.90), (1.2, 3.5), 0.0, 0.6),
    "lace":        ((1.50, 3.50), (0.10, 0.25), (0.00, 0.15), (0.20, 0.50), (0.2, 0.5), 0.3, 0.2),
    "corduroy":    ((1.50, 3.50), (0.25, 0.50), (0.30, 0.60), (0.45, 0.80), (1.2, 2.5), 0.1, 0.6),
    "hessian":     ((1.00, 2.20), (0.15, 0.35), (0.45, 0.80), (0.65, 0.95), (0.8, 1.6), 0.0, 0.7),
    "denim":       ((0.35, 0.70), (0.07, 0.14), (0.10, 0.35), (0.60, 0.90), (0.7, 1.3), 0.1, 0.6),
    "velvet":      ((0.15, 0.30), (0.02, 0.05), (0.55, 0.85), (0.15, 0.40), (0.9, 2.0), 0.2, 0.5),
}


@dataclass(frozen=True)
class FabricParams:
    """The hidden physical truth of one fabric; stored in fabric.yaml under `extra`."""

    construction: str
    pitch_mm: float  # yarn spacing (wale spacing for corduroy, loop spacing for knits/terry)
    yarn_fill: float  # yarn diameter / pitch
    relief_mm: float  # peak-to-valley height of the structure
    hairiness: float  # 0..1 loose fibres standing off the surface
    stiffness: float  # 0..1 bending/compression stiffness
    thickness_mm: float
    stretch: float  # 0..1
    absorbency: float  # 0..1
    weave_angle_deg: float  # orientation of the structure on the piece
    embroidery: bool
    jacquard: bool
    hole_fraction: float  # lace/open weaves: fraction of area that is hole
    colour_hsv: tuple[float, float, float]
    print_kind: str  # none, dots, floral, geometric
    stripes: bool
    shininess: float
    phase_seed: int  # the fabric's own randomness for its noise fields

    @property
    def density(self) -> float:
        return self.thickness_mm * (0.6 + 0.8 * self.stiffness) * (1.0 - self.hole_fraction)


def _u(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(*lo_hi))


def draw_fabric(rng: np.random.Generator, construction: str) -> FabricParams:
    pitch, relief, hair, stiff, thick, stretch, absorb = _FAMILY[construction]
    decorated = construction in ("plain", "twill", "satin", "jersey", "denim", "felt")
    print_kind = str(rng.choice(["none", "dots", "floral", "geometric"], p=[0.6, 0.13, 0.14, 0.13]))
    return FabricParams(
        construction=construction,
        pitch_mm=round(_u(rng, pitch), 4),
        yarn_fill=round(float(rng.uniform(0.6, 0.95)), 3),
        relief_mm=round(_u(rng, relief), 4),
        hairiness=round(float(np.clip(_u(rng, hair) + rng.normal(0, 0.05), 0, 1)), 3),
        stiffness=round(float(np.clip(_u(rng, stiff) + rng.normal(0, 0.05), 0, 1)), 3),
        thickness_mm=round(_u(rng, thick), 3),
        stretch=round(float(np.clip(stretch + rng.normal(0, 0.1), 0, 1)), 3),
        absorbency=round(float(np.clip(absorb + rng.normal(0, 0.1), 0, 1)), 3),
        weave_angle_deg=round(float(rng.choice([0.0, 90.0]) + rng.normal(0, 4)), 2),
        embroidery=bool(decorated and rng.random() < 0.18),
        jacquard=bool(construction in ("plain", "twill", "satin") and rng.random() < 0.25),
        hole_fraction=round(float(rng.uniform(0.25, 0.5)) if construction == "lace"
                            else (float(rng.uniform(0.05, 0.15)) if construction == "hessian" else 0.0), 3),
        colour_hsv=(round(float(rng.uniform(0, 180)), 1), round(float(rng.uniform(0.1, 0.9)), 3),
                    round(float(rng.uniform(0.25, 0.95)), 3)),
        print_kind=print_kind if construction not in ("lace", "terry", "velvet") else "none",
        stripes=bool(rng.random() < 0.2),
        shininess=round(float(np.clip((0.8 if construction in ("satin", "velvet") else 0.15) + rng.normal(0, 0.1),
                                      0, 1)), 3),
        phase_seed=int(rng.integers(0, 2**31 - 1)),
    )


def _visible_fabric(rng: np.random.Generator, construction: str, q: float) -> FabricParams:
    """One fabric of a kind whose pitch and relief sit at ``q`` (0..1) of the kind's ranges, and
    what the camera cannot see (hairiness, stiffness, thickness, yarn fill) near the kind's middle,
    without decoration."""
    pitch, relief, hair, stiff, thick, stretch, absorb = _FAMILY[construction]

    def middle(lo_hi: tuple[float, float], spread: float = 0.05) -> float:
        return float(np.mean(lo_hi) + rng.normal(0, spread * (lo_hi[1] - lo_hi[0])))

    drawn = draw_fabric(rng, construction)  # colour, print, stripes, angle, phases: as any fabric
    return replace(drawn, pitch_mm=round(pitch[0] + q * (pitch[1] - pitch[0]), 4),
                   relief_mm=round(relief[0] + q * (relief[1] - relief[0]), 4), yarn_fill=0.8,
                   hairiness=round(float(np.clip(middle(hair), 0, 1)), 3),
                   stiffness=round(float(np.clip(middle(stiff), 0, 1)), 3),
                   thickness_mm=round(middle(thick), 3), stretch=stretch, absorbency=absorb,
                   embroidery=False, jacquard=False)


def draw_world(n_fabrics: int, seed: int, constructions: tuple[str, ...] | None = None,
               kind_spread: str = "drawn") -> list[FabricParams]:
    """n fabrics covering the constructions (each at least once when n allows), shuffled; with
    ``constructions``, only those, in equal numbers (up to one). ``kind_spread="visible"`` (with
    ``constructions``): a kind's fabrics differ in pitch, spread evenly over the kind's range."""
    if kind_spread not in KIND_SPREADS or (kind_spread != "drawn" and constructions is None):
        raise ValueError(f"kind_spread {kind_spread!r}: one of {', '.join(KIND_SPREADS)}, and 'visible' only "
                         "with the constructions to spread")
    rng = np.random.default_rng(seed)
    if constructions is not None:
        unknown = sorted(set(constructions) - set(CONSTRUCTIONS))
        if unknown:
            raise ValueError(f"unknown construction(s) {unknown}; known: {', '.join(CONSTRUCTIONS)}")
        kinds = [constructions[i % len(constructions)] for i in range(n_fabrics)]
        if kind_spread == "visible":
            order = [str(k) for k in rng.permutation(kinds)]
            quantile = {}
            for kind in sorted(set(order)):
                slots = [i for i, k in enumerate(order) if k == kind]
                for rank, i in enumerate(rng.permutation(len(slots))):
                    quantile[slots[i]] = (rank + rng.uniform(0.3, 0.7)) / len(slots)
            return [_visible_fabric(rng, k, quantile[i]) for i, k in enumerate(order)]
        return [draw_fabric(rng, str(k)) for k in rng.permutation(kinds)]
    order = list(CONSTRUCTIONS) * (n_fabrics // len(CONSTRUCTIONS) + 1)
    head = list(rng.permutation(CONSTRUCTIONS))
    kinds = (head + list(rng.choice(order, size=max(0, n_fabrics - len(head)))))[:n_fabrics]
    return [draw_fabric(rng, str(k)) for k in kinds]

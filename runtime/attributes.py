"""The 24 semantic attributes of a fabric, in the paper's order (FabricVST, VS2T-ZSL)."""

from __future__ import annotations

ATTRIBUTES: tuple[str, ...] = (
    "stiff", "soft", "rough", "smooth", "thick", "thin", "cool", "warm",
    "fluffy", "heavy", "delicate", "durable", "stretchable", "absorbent", "holey", "flat",
    "bumpy", "patterned", "striped", "shiny", "hairy", "embroidered", "jacquard",
    "pigment printed",
)
N_ATTRIBUTES = len(ATTRIBUTES)
ATTRIBUTE_INDEX = {name: i for i, name in enumerate(ATTRIBUTES)}

# The first six pairs are mutually exclusive: a fabric is never labelled both.
EXCLUSIVE_PAIRS: tuple[tuple[str, str], ...] = tuple(
    (ATTRIBUTES[2 * i], ATTRIBUTES[2 * i + 1]) for i in range(6)
)

"""Fabric names as people type them, and the one name no fabric may have: the leaf module the
config check, operator labels and their learned strangers share (stdlib only, no model).

``typed_name``: a name as typed, composed (Unicode NFC). ``name_key``: a name with case, letter
width, spaces, '-' and '_' set aside - two names with one key are one fabric to a person, so the
config refuses a job listing both (runtime/config.py) and a label names either (runtime/labels.py).
``OFF_SCENE_PREFIX``: the class name of a stranger operator labels teach (runtime/feedback.py)."""

from __future__ import annotations

import unicodedata

OFF_SCENE_PREFIX = "off-scene:"  # a learned stranger's class name (never a bundle class's)


def typed_name(name: str) -> str:
    """A name as typed, composed (Unicode NFC): 'é' sent decomposed by another keyboard or system
    (e + a combining accent, NFD) is the same name, byte for byte, as the config's."""
    return unicodedata.normalize("NFC", name)


def name_key(name: str) -> str:
    """A fabric name with case, letter width, spaces, '-' and '_' set aside: two names with one key are
    one fabric to a person ('WOOL', 'wool ', 'Ｗｏｏｌ' for wool)."""
    folded = unicodedata.normalize("NFKC", unicodedata.normalize("NFKC", name).casefold())
    return "".join(c for c in folded if c not in "-_" and not c.isspace())


__all__ = ["OFF_SCENE_PREFIX", "typed_name", "name_key"]

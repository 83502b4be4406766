"""Reading a bundle manifest's fields: each refusal a ``BundleError`` that names the key (or the
file) and shows the offending value, shortened. runtime/bundle.py reads a manifest with these;
descriptor bundles (runtime/tactile_descriptor.py) too."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any


class BundleError(ValueError):
    """The bundle is not the one its manifest describes (or no bundle at all)."""

    def __init__(self, bundle: Path | str, message: str) -> None:
        super().__init__(f"bundle {bundle}: {message}")
        self.bundle = str(bundle)
        self.detail = message


def _need(manifest: dict, root: Path, *keys: str):
    node: Any = manifest
    for depth, k in enumerate(keys):
        if not isinstance(node, dict) or k not in node:
            raise BundleError(root, f"manifest.json lacks '{'.'.join(keys[:depth + 1])}'")
        node = node[k]
    return node


def _get(manifest: Any, *keys: str) -> Any:
    """The value at keys, or None when any level is missing or not an object (no error)."""
    node = manifest
    for k in keys:
        if not isinstance(node, dict):
            return None
        node = node.get(k)
    return node


def _float(v: Any, root: Path, key: str, allow_inf: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise BundleError(root, f"manifest.json '{key}' = {_short(v)} is not a number")
    try:
        x = float(v)
    except OverflowError:  # an integer beyond float range
        raise BundleError(root, f"manifest.json '{key}' = {_short(v)} is not a finite number") from None
    if math.isnan(x) or (math.isinf(x) and not allow_inf):
        raise BundleError(root, f"manifest.json '{key}' = {x} is not a finite number")
    return x


def _int(v: Any, root: Path, key: str, lo: int, hi: int) -> int:
    # bool is an int in Python and 16.7 would truncate silently: both refused.
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise BundleError(root, f"manifest.json '{key}' = {_short(v)} must be a whole number in {lo}..{hi}")
    return v


def _short(v: Any) -> str:
    text = repr(v) if not isinstance(v, int) or abs(v) < 10 ** 30 else f"<{v.bit_length()}-bit integer>"
    return text if len(text) <= 80 else text[:77] + "..."


def _names(v: Any, root: Path, key: str) -> tuple[str, ...]:
    if not isinstance(v, list) or not all(isinstance(c, str) and c for c in v):
        raise BundleError(root, f"manifest.json '{key}' must be a list of class names (non-empty texts)")
    return tuple(v)


def _inside(root: Path, name: Any, key: str) -> Path:
    """root / name, refused unless it is a plain relative name that stays in the folder (links
    resolved: a link inside the bundle pointing out of it is outside)."""
    if not isinstance(name, str) or not name or "\x00" in name:
        raise BundleError(root, f"manifest.json '{key}' = {_short(name)} is not a file name")
    if Path(name).is_absolute() or ".." in Path(name).parts:
        raise BundleError(root, f"file name {name!r} ('{key}') leaves the bundle folder")
    path = root / name
    try:
        real, base = path.resolve(), root.resolve()
    except (OSError, RuntimeError) as exc:  # RuntimeError: a symlink loop
        raise BundleError(root, f"{name} ('{key}'): cannot resolve ({exc})") from None
    if real != base and base not in real.parents:
        raise BundleError(root, f"file name {name!r} ('{key}') leaves the bundle folder (links to {real})")
    return path


def _shapes(v: Any, root: Path, key: str) -> dict:
    """{tensor name: [dim or null, ...]} as the exporter writes it."""
    if not isinstance(v, dict) or not v:
        raise BundleError(root, f"manifest.json '{key}' missing")
    for name, shape in v.items():
        if not (isinstance(shape, list) and 1 <= len(shape) <= 8 and all(
                d is None or (isinstance(d, int) and not isinstance(d, bool) and 0 < d < 1 << 31) for d in shape)):
            raise BundleError(root, f"manifest.json '{key}.{name}' = {_short(shape)} is not a shape "
                                    "(a list of positive sizes or null)")
    return v


def _no_duplicate_keys(pairs: list) -> dict:
    out: dict = {}
    for k, v in pairs:
        if k in out:  # json keeps the last silently: a tampered manifest could hide a second 'files'
            raise ValueError(f"key {k!r} appears twice in one object")
        out[k] = v
    return out

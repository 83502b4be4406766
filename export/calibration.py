"""Which presses int8 may read, torch-free (the export and `vs2t-edge int8-sensitivity` share it).

- calibration (the activation ranges): TRAINING presses of touched fabrics only
  (``part[fabric]["train"]``, the presses that fitted the model) - never a held-out, test or
  unused press, never an untouched fabric;
- the sensitivity scan (which layers stay float): held-out touched presses (``part[fabric]["val"]``)
  and presses of the validation fabrics - what the run tunes its choices on - never test presses,
  never an untouched fabric.

``part`` is the manifest's ``provenance.data.touched_presses`` ({fabric: {"train", "val", "test",
"unused"}}, export/from_run.py ``press_partition``).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np


class PressLeak(ValueError):
    """A press selection would read presses int8 may not see."""


def spread(indices: Sequence[int], k: int) -> list[int]:
    """``k`` of ``indices`` evenly spaced (all of them when there are no more than ``k``)."""
    idx = list(indices)
    if k <= 0 or len(idx) <= k:
        return idx
    return [idx[int(j)] for j in np.linspace(0, len(idx) - 1, k).round().astype(int)]


def _guard(fabrics: Sequence[str], untouched: Sequence[str], what: str) -> None:
    leaked = sorted(set(fabrics) & set(untouched))
    if leaked:
        raise PressLeak(f"{what} would read presses of untouched fabric(s) {', '.join(leaked)}")


def calibration_presses(part: dict[str, dict[str, list[int]]], fabrics: Sequence[str], n: int,
                        untouched: Sequence[str] = ()) -> dict[str, list[int]]:
    """``n`` training presses (0: all of them; fewer when there are fewer) over ``fabrics``
    (touched), about the same number from each fabric, evenly spread in press order; {fabric: press
    indices}."""
    fabrics = list(fabrics)
    if not fabrics:
        raise PressLeak("calibration needs at least one touched fabric")
    _guard(fabrics, untouched, "int8 calibration")
    missing = [f for f in fabrics if f not in part]
    if missing:
        raise PressLeak(f"calibration fabric(s) {', '.join(missing)} have no training presses (not touched)")
    if n <= 0:
        return {f: list(part[f]["train"]) for f in fabrics if part[f]["train"]}
    per = max(1, math.ceil(n / len(fabrics)))
    longest = max(len(part[f]["train"]) for f in fabrics)
    pairs = [(f, i) for f in fabrics for i in spread(part[f]["train"], per)]
    while len(pairs) < n and per < longest:  # fabrics with few training presses: take more of the others
        per += 1
        pairs = [(f, i) for f in fabrics for i in spread(part[f]["train"], per)]
    out: dict[str, list[int]] = {}
    for f, i in (pairs[j] for j in spread(range(len(pairs)), n)):
        out.setdefault(f, []).append(i)
    return out


def sensitivity_presses(part: dict[str, dict[str, list[int]]], touched: Sequence[str],
                        validation: dict[str, int], untouched: Sequence[str] = (), per_fabric: int = 12,
                        ) -> dict[str, list[int]]:
    """Held-out presses for the sensitivity scan: every ``val`` press of the touched fabrics and
    ``per_fabric`` presses (evenly spread) of each validation fabric (``validation`` = {fabric:
    its number of presses}). Never a training (calibration) or test press."""
    _guard(list(touched) + list(validation), untouched, "the int8 sensitivity scan")
    out = {f: list(part[f]["val"]) for f in touched if part[f]["val"]}
    for f, n in validation.items():
        if f in part:
            raise PressLeak(f"validation fabric {f} is also a touched fabric")
        out[f] = spread(range(n), per_fabric)
    return out


__all__ = ["calibration_presses", "sensitivity_presses", "spread", "PressLeak"]

"""Fabric splits: which fabrics a run touches, validates on and never touches.

``make_splits`` draws the paper's 40/5/5 protocol (seeded, one permutation per split);
``fewer_touched`` keeps a nested draw of a split's touched fabrics (`train --touched N`). The
comparison (``compare.py``), training (``run.py``) and the world check read splits from here.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass
class FabricSplit:
    touched: list[str]
    validation: list[str]
    untouched: list[str]
    seed: int = 0


def make_splits(fabric_ids: list[str], n_splits: int = 5, n_val: int | None = None, n_untouched: int | None = None,
                seed: int = 0) -> list[FabricSplit]:
    """Random splits like the paper's 40/5/5 (10 % validation, 10 % untouched by default)."""
    n = len(fabric_ids)
    n_val = n_val if n_val is not None else max(2, round(0.1 * n))
    n_untouched = n_untouched if n_untouched is not None else max(2, round(0.1 * n))
    if n - n_val - n_untouched < 2:
        raise ValueError(f"{n} fabrics are too few for {n_val} validation and {n_untouched} untouched")
    out = []
    for k in range(n_splits):
        perm = np.random.default_rng(seed * 1000 + k).permutation(n)
        ids = [fabric_ids[i] for i in perm]
        out.append(FabricSplit(touched=sorted(ids[n_val + n_untouched:]), validation=sorted(ids[:n_val]),
                               untouched=sorted(ids[n_val:n_val + n_untouched]), seed=seed * 1000 + k))
    return out


def fewer_touched(split: FabricSplit, n: int) -> FabricSplit:
    """``split`` with only ``n`` of its touched fabrics, drawn with the split's seed. The draws
    nest (the fabrics kept at n are among those kept at any larger n), so runs that differ only in
    n set the same validation and untouched fabrics against more or fewer touched ones; the
    fabrics left out take no part (not trained on, not scored)."""
    if not 2 <= n <= len(split.touched):
        raise ValueError(f"touched fabrics: {n} asked, the split has {len(split.touched)} (at least 2)")
    order = np.random.default_rng(split.seed + 77).permutation(len(split.touched))
    return replace(split, touched=sorted(split.touched[i] for i in order[:n]))


__all__ = ["FabricSplit", "make_splits", "fewer_touched"]

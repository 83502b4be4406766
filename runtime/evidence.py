"""Evidence over several presses of one item, in log space, with a sequential stopping rule.

Each press gives a normalised log posterior over the bundle's classes (runtime/inference.py).
Only the scene's classes count: the per-press posterior is restricted to them and renormalised,
then log posteriors are summed (independent presses, uniform prior) and renormalised with a
stable logsumexp, so 225 presses never underflow. Stop when the leading class reaches
``confidence`` (after ``min_presses``) or at ``max_presses``; at the limit an unconfident item
is "unknown" (the reject bin).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

UNKNOWN = "unknown"


@dataclass(frozen=True)
class ItemDecision:
    label: str
    confidence: float
    presses: int
    log_posterior: dict[str, float]
    stopped_by: str  # "confident" | "press_limit"


def _logsumexp(x: np.ndarray) -> float:
    m = float(np.max(x))
    if not math.isfinite(m):
        return m
    return m + math.log(float(np.sum(np.exp(x - m))))


class Evidence:
    def __init__(self, scene_classes, confidence: float = 0.95, max_presses: int = 9,
                 min_presses: int = 1, unknown_floor: float | None = None):
        self.classes = list(dict.fromkeys(scene_classes))
        if not self.classes:
            raise ValueError("Evidence: the scene has no classes")
        if not 0.0 < confidence <= 1.0:
            raise ValueError(f"Evidence: confidence = {confidence} must be in (0, 1]")
        if max_presses < 1 or min_presses < 1 or min_presses > max_presses:
            raise ValueError(f"Evidence: need 1 <= min_presses ({min_presses}) <= max_presses ({max_presses})")
        self.confidence, self.max_presses, self.min_presses = confidence, max_presses, min_presses
        # below this leading posterior the item is "unknown" even at the limit (default: confidence)
        self.unknown_floor = confidence if unknown_floor is None else unknown_floor
        self._acc = np.zeros(len(self.classes), dtype=np.float64)
        self.presses = 0

    def _posterior(self) -> np.ndarray:
        return self._acc - _logsumexp(self._acc)

    def add(self, score) -> ItemDecision | None:
        lp = score.log_posterior
        missing = [c for c in self.classes if c not in lp]
        if missing:
            raise KeyError(f"Evidence: press score has no class {missing} of the scene")
        v = np.array([float(lp[c]) for c in self.classes], dtype=np.float64)
        if np.any(np.isnan(v)):
            raise ValueError("Evidence: press score has NaN log posterior")
        if not np.any(np.isfinite(v)):  # no scene class possible from this press: uninformative
            v = np.zeros_like(v)
        v = v - _logsumexp(v)
        self._acc = self._acc + np.maximum(v, -1e300)  # keep -inf out of sums (inf - inf = NaN)
        self.presses += 1
        post = self._posterior()
        i = int(np.argmax(post))
        if self.presses >= self.min_presses and math.exp(post[i]) >= self.confidence:
            return self._make(post, "confident")
        if self.presses >= self.max_presses:
            return self._make(post, "press_limit")
        return None

    def decide(self) -> ItemDecision:
        post = self._posterior()
        i = int(np.argmax(post))
        if self.presses >= self.min_presses and math.exp(post[i]) >= self.confidence:
            return self._make(post, "confident")
        return self._make(post, "press_limit")

    def _make(self, post: np.ndarray, stopped_by: str) -> ItemDecision:
        i = int(np.argmax(post))
        conf = math.exp(float(post[i]))
        label = self.classes[i] if (stopped_by == "confident" or conf >= self.unknown_floor) else UNKNOWN
        return ItemDecision(label, conf, self.presses, {c: float(p) for c, p in zip(self.classes, post)}, stopped_by)

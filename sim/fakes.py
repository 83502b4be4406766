"""The grey-level fake model and its evidence: one copy for the fault matrix, the soak and the tests.

A pressed frame's mean grey level votes for one fabric (``GREY``), so the cell loop can be
exercised - by the fault matrix (sim/faults.py), the soak and the loop's tests - without waiting
for, or depending on the numbers of, a trained bundle. They satisfy the protocols the real
runtime/inference.py and runtime/evidence.py do. tests/cell_fakes.py uses the score, decision and
evidence from here (sim/ is shipped and may not import tests/); its FakeModel keeps its own rule
(a frame votes only at its exact grey level, and counts what it scored).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from vs2t_edge.runtime.preprocess import check_frame

# the rig's scene: three fabrics in bins 1-3, tweed off the scene, the no-contact frame's grey
CLASSES = ["denim", "silk", "wool"]
BINS = {"denim": 1, "silk": 2, "wool": 3}
GREY = {"denim": 50, "silk": 60, "wool": 70, "tweed": 100}  # tweed: off-scene, votes for nothing
REFERENCE_GREY = 120
REJECT = 0


@dataclass(frozen=True)
class GreyScore:
    log_posterior: dict
    novelty: float
    untouched: bool
    latency_ms: float = 1.0  # GreyModel measures it; the tests' FakeModel leaves this stand-in


@dataclass(frozen=True)
class GreyDecision:
    label: str
    confidence: float
    presses: int
    log_posterior: dict
    stopped_by: str


class GreyModel:
    """A pressed frame of mean grey level v votes for the fabric whose GREY is nearest (within 4)."""

    def __init__(self, classes=CLASSES, strength: float = 3.0) -> None:
        self.classes, self.strength = list(classes), strength
        self.votes = {GREY[c]: c for c in self.classes}

    def set_reference(self, frame) -> None:
        check_frame(frame, name="reference frame")

    def score_press(self, frame) -> GreyScore:
        t0 = time.perf_counter()
        check_frame(frame)
        v = float(frame[..., 0].mean())
        target = min(self.votes, key=lambda g: abs(g - v))
        target_name = self.votes[target] if abs(target - v) <= 4 else None
        lp = {c: (0.0 if c == target_name else -self.strength) for c in self.classes}
        return GreyScore(lp, novelty=v, untouched=False, latency_ms=(time.perf_counter() - t0) * 1000)


class GreyEvidence:
    """Sum of log posteriors; decides once the normalised posterior reaches ``confidence``."""

    def __init__(self, classes=CLASSES, confidence: float = 0.95, max_presses: int = 3) -> None:
        self.classes, self.confidence, self.max_presses = list(classes), confidence, max_presses
        self.total = {c: 0.0 for c in self.classes}
        self.n = 0

    def _posterior(self) -> dict:
        m = max(self.total.values())
        z = sum(math.exp(v - m) for v in self.total.values())
        return {c: math.exp(v - m) / z for c, v in self.total.items()}

    def add(self, score):
        self.n += 1
        for c in self.classes:
            self.total[c] += score.log_posterior.get(c, -30.0)
        post = self._posterior()
        best = max(post, key=post.get)
        if post[best] >= self.confidence:
            return GreyDecision(best, post[best], self.n, dict(self.total), "confident")
        return self.decide() if self.n >= self.max_presses else None

    def decide(self):
        post = self._posterior()
        best = max(post, key=post.get)
        label = best if post[best] >= self.confidence else "unknown"
        return GreyDecision(label, post[best], self.n, dict(self.total), "press_limit")

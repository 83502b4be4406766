import math
from dataclasses import dataclass

from vs2t_edge.runtime.evidence import Evidence


@dataclass(frozen=True)
class S:
    log_posterior: dict


def test_confident_stop_and_restriction():
    ev = Evidence(["a", "b"], 0.95, 9)
    d = None
    for _ in range(9):
        d = ev.add(S({"a": math.log(0.7), "b": math.log(0.2), "z": math.log(0.1)}))
        if d:
            break
    assert d.label == "a" and d.stopped_by == "confident" and 1 < d.presses < 9


def test_unknown_at_limit_and_225_presses_no_underflow():
    ev = Evidence(["a", "b"], 0.95, 225)
    d = None
    for k in range(225):
        d = ev.add(S({"a": -1e4 if k % 2 else 0.0, "b": 0.0 if k % 2 else -1e4}))
        if d:
            break
    assert d is not None and all(math.isfinite(v) for v in d.log_posterior.values())
    ev2 = Evidence(["a", "b"], 0.95, 3)
    for _ in range(3):
        d = ev2.add(S({"a": math.log(0.5), "b": math.log(0.5)}))
    assert d.label == "unknown" and d.stopped_by == "press_limit" and d.presses == 3

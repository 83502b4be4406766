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


def test_no_presses_or_a_tie_is_never_a_sort():
    """An item the evidence has no press of (a one-fabric scene's posterior is 1 before any press),
    or whose leading classes are tied (a two-fabric scene at confidence 0.5, presses that tell the
    two apart not at all), carries nothing that picks its bin: unknown, the reject bin - not the
    scene's first-listed fabric."""
    d = Evidence(["a"], 0.9, 3).decide()
    assert (d.label, d.presses) == ("unknown", 0)
    ev = Evidence(["a", "b"], 0.5, 3)
    d = ev.add(S({"a": -1e30, "b": -1e30, "z": 0.0}))  # both scene fabrics impossible by this press
    assert d is None and ev.decide().label == "unknown"
    for _ in range(2):
        d = ev.add(S({"a": math.log(0.4), "b": math.log(0.4), "z": math.log(0.2)}))
    assert d.label == "unknown" and d.stopped_by == "press_limit" and d.presses == 3
    d = Evidence(["a", "b"], 0.5, 3).add(S({"a": math.log(0.51), "b": math.log(0.49)}))
    assert d.label == "a" and d.stopped_by == "confident"  # a lead, however small, is still a lead


def test_refuse_early_stops_at_the_press_that_makes_a_left_out_fabric_sure():
    """A known fabric the job leaves out ("z") leads every class: with ``refuse_early`` the piece
    goes to the reject bin at the first press where z holds the confidence over all classes;
    without it the cell presses to the limit for the same reject bin. A z that only leads (below
    the confidence) presses on either way."""
    sure = S({"a": math.log(0.02), "b": math.log(0.01), "z": math.log(0.97)})
    early = Evidence(["a", "b"], 0.9, 5, known_margin=0.0, refuse_early=True)
    d = early.add(sure)
    assert d is not None and d.label == "unknown" and d.stopped_by == "off_scene" and d.presses == 1
    late = Evidence(["a", "b"], 0.9, 5, known_margin=0.0)
    ds = [late.add(sure) for _ in range(5)]
    assert ds[:4] == [None] * 4 and ds[4].label == "unknown" and ds[4].presses == 5
    leads = S({"a": math.log(0.3), "b": math.log(0.1), "z": math.log(0.6)})
    ev = Evidence(["a", "b"], 0.99, 5, known_margin=0.0, refuse_early=True, weight=0.1)
    assert ev.add(leads) is None  # 0.6 share < 0.99: not sure yet
    # off without the known-class rule: nothing to compare with
    assert Evidence(["a", "b"], 0.9, 5, refuse_early=True).add(sure) is None


def test_a_nan_in_a_refusal_rule_is_refused_not_a_rule_switched_off():
    """A NaN for a class outside the job, or in a press's squared distances, made every comparison
    of the known-class or open-set rule False: the rule silently off for that piece, which could
    then sort a stranger. Like a NaN of the job's own classes, it is refused (the cell latches)."""
    import pytest

    @dataclass(frozen=True)
    class D:
        log_posterior: dict
        sq_distance: dict

    known = Evidence(["a", "b"], 0.95, 5, known_margin=0.0)
    with pytest.raises(ValueError, match="outside the scene"):
        known.add(S({"a": 0.0, "b": -3.0, "z": math.nan}))
    opened = Evidence(["a", "b"], 0.95, 5, open_threshold=10.0)
    with pytest.raises(ValueError, match="NaN squared distance"):
        opened.add(D({"a": 0.0, "b": -3.0}, {"a": 1.0, "b": math.nan}))  # min(1.0, NaN) is 1.0: one is enough
    fine = Evidence(["a", "b"], 0.95, 5, known_margin=0.0, open_threshold=10.0)
    fine.add(D({"a": 0.0, "b": -3.0, "z": -9.0}, {"a": 1.0, "b": 4.0}))


def test_press_no_scene_class_can_explain_counts_against_the_job():
    """A press on which every class of the job is impossible (log posterior -inf) is no evidence for
    the posterior among them, but it is for the known-class rule: two presses surely of the outside
    fabric k and one that leans to a must send the piece to the reject bin, not into a's bin (they
    once did: the zeroed press entered the rule's inside sum as perfect evidence for the job)."""
    ev = Evidence(["a", "b"], 0.9, 3, known_margin=1.0)
    d = None
    for lp in ({"a": -math.inf, "b": -math.inf, "k": 0.0},) * 2 + ({"a": -0.05, "b": -5.0, "k": -3.2},):
        d = ev.add(S(lp))
    assert d is not None and d.label == "unknown" and d.stopped_by == "off_scene"
    # without an outside fabric to prefer, the same presses still decide among the job's classes
    alone = Evidence(["a", "b"], 0.9, 3)
    for lp in ({"a": -math.inf, "b": -math.inf},) * 2 + ({"a": -0.05, "b": -5.0},):
        d = alone.add(S(lp))
    assert d is not None and d.label == "a"

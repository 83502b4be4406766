"""Before a job: which of its fabrics can the cell sort at all?

The scene model holds one picture of each fabric: its class mean, real presses' for a touched
fabric, the generator's synthesis for an untouched one (runtime/scene_model.py). A piece that
feels exactly like that picture is the easiest piece of the fabric the cell could meet.
``check_job`` presses it ``max_presses`` times through the cell's own evidence for the job and
says where it goes. When even the picture goes to the reject bin - a fabric of the job lies too
close to it, or a fabric the cell knows that the job leaves out does and the off-scene rule
refuses it - the fabric's real pieces go there too, whatever they press: the operator learns it
before the first piece, not from the reject bin, and can start the job with a teach piece of it
(docs/operator_labels.md, "Starting a job with teach pieces") or leave its rival out of the job.

Training's report measures how well the check foretells the bins of its test jobs
(train/decision.py ``job_check_outcomes``). Paper world, the 5 splits' test jobs (`vs2t-edge train DS
--profile paper --out RUN`, 2026-11-27, RUN/report.md "Job check"): of 300 touched job fabrics the check flagged 23,
none of whose pieces went to their bin, against 93.7 % of the others' pieces; of 180 untouched ones
it flagged 93, 5.1 % of whose pieces went to their bin, against 48.3 %. It is no promise for a
fabric it passes: an untouched fabric's real presses lie off its synthesis by the generator's
error, which the model cannot see, and a touched fabric's later presses drift from its training
ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from vs2t_edge.runtime.evidence import UNKNOWN
from vs2t_edge.runtime.sorting import REASONS, Press


@dataclass(frozen=True)
class FabricCheck:
    fabric: str
    kind: str  # "touched" | "untouched"
    label: str  # where the fabric's own picture goes: the fabric itself, UNKNOWN (reject bin) or another fabric
    stopped_by: str  # the evidence's reason ("confident", "off_scene", "press_limit", ...)
    confidence: float
    rival: str  # the bundle class nearest the picture after the fabric itself (the model's per-press posterior)
    rival_in_job: bool
    # the rival is a fabric the model knows only to refuse (a validation fabric of its training run,
    # runtime/scene_model.py known_only): no job can list it, so leaving it out changes nothing
    rival_refuse_only: bool = False

    @property
    def sorts(self) -> bool:
        return self.label == self.fabric

    def describe(self) -> str:
        where = "its bin" if self.sorts else "the reject bin" if self.label == UNKNOWN else f"{self.label}'s bin"
        if self.sorts:
            return f"{self.fabric} ({self.kind}): its own picture goes to {where} (confidence {self.confidence:.2f})"
        why = REASONS.get(self.stopped_by, self.stopped_by)
        rival = f"{self.rival}, " + ("in this job" if self.rival_in_job else
                                     "a fabric the cell knows only to refuse, pressed in training and in no classifier"
                                     if self.rival_refuse_only else "a fabric the cell knows that this job leaves out")
        advice = "start the job with a teach piece of it" if self.kind == "untouched" else \
            "no job can list that rival, so leaving it out changes nothing" if self.rival_refuse_only else \
            "leave its rival out of the job, or teach the rival if it is untouched"
        return (f"{self.fabric} ({self.kind}): even its own picture goes to {where} ({why}; nearest {rival}): "
                f"expect its pieces there - {advice}")


def picture_presses(model: Any, fabric: str, n: int) -> list[Press]:
    """``n`` presses exactly at ``fabric``'s class mean, scored as the cell scores a press."""
    z = np.asarray(model.means[list(model.classes).index(fabric)], np.float64)[None, :]
    lp, d2 = model.log_posterior_projected(z)
    classes = model.classes
    press = Press(dict(zip(classes, lp[0].tolist())), dict(zip(classes, d2[0].tolist())), z[0])
    return [press] * n


def check_job(model: Any, scene: Sequence[str], make_evidence: Callable[[], Any], max_presses: int) -> list[FabricCheck]:
    """One ``FabricCheck`` per fabric of ``scene``: the fabric's picture pressed ``max_presses``
    times through a fresh evidence from ``make_evidence`` (the cell's own, for this job), or as many
    as that evidence may take (its ``press_limit``: the scene model's extra presses, or the
    config's ``evidence.extra_presses``)."""
    out = []
    for fabric in scene:
        if fabric not in model.classes:
            raise ValueError(f"job check: the scene model has no class {fabric!r}")
        ev = make_evidence()
        presses = picture_presses(model, fabric, max(max_presses, int(getattr(ev, "press_limit", max_presses))))
        decision = None
        for press in presses:
            decision = ev.add(press)
            if decision is not None:
                break
        if decision is None:
            decision = ev.decide()
        lp = presses[0].log_posterior
        rival = max((c for c in model.classes if c != fabric), key=lambda c: lp[c], default="")
        out.append(FabricCheck(fabric, "untouched" if fabric in model.untouched else "touched", decision.label,
                               decision.stopped_by, float(decision.confidence), rival, rival in scene,
                               rival in model.known_only))
    return out


def summary_lines(checks: Sequence[FabricCheck]) -> list[str]:
    """What the cell says before a job: the fabrics whose own picture it cannot sort, or that all pass."""
    flagged = [c for c in checks if not c.sorts]
    if not flagged:
        return [f"job check: every fabric of the job sorts at its own picture ({len(checks)} fabrics)"]
    return [f"job check: {len(flagged)} of {len(checks)} fabrics cannot be sorted even at their own picture "
            "(the scene model's mean of them; runtime/job_check.py):"] + [f"  {c.describe()}" for c in flagged]


__all__ = ["FabricCheck", "picture_presses", "check_job", "summary_lines"]

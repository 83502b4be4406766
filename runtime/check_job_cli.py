"""`vs2t-edge check-job CONFIG`: before starting the service on a job, which of its fabrics the cell
cannot sort even when a piece feels exactly like the bundle's picture of it (runtime/job_check.py) -
the same check the service logs at start, with the item rule it will use. Every fabric of the job
is listed with where its picture goes; exit 0 when all sort, 1 when any cannot (start the job with a
teach piece of an untouched one, docs/cell.md), 2 for a config or bundle that cannot be used."""

from __future__ import annotations

import sys

from vs2t_edge.runtime import job_check
from vs2t_edge.runtime.bundle import BundleError
from vs2t_edge.runtime.config import load_config_or_say
from vs2t_edge.runtime.wiring import SceneModelMissing, evidence_factory_for, load_model


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("config", help="the cell config of the job (its scene's fabrics and the bundle)")


def run(args) -> int:
    if (cfg := load_config_or_say(args.config)) is None:
        return 2
    try:
        model = load_model(cfg)
        factory = evidence_factory_for(cfg, model)
    except (BundleError, SceneModelMissing, ValueError) as exc:
        print(f"check-job: {exc}", file=sys.stderr)
        return 2
    if getattr(model, "scene_model", None) is None:  # allowed by the config: nothing to check with
        print(f"check-job: bundle {cfg.bundle} has no scene model (decision.npz); nothing to check", file=sys.stderr)
        return 2
    checks = job_check.check_job(model.scene_model, cfg.scene_classes, factory, cfg.max_presses)
    for c in checks:
        print(c.describe())
    flagged = sum(not c.sorts for c in checks)
    print(f"{flagged} of {len(checks)} fabrics of the job cannot be sorted even at their own picture" if flagged
          else f"every fabric of the job ({len(checks)}) sorts at its own picture")
    return 1 if flagged else 0

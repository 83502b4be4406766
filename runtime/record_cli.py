"""`vs2t-edge record --config FILE --out NAME.replay`: record a live session into a replay file.

Runs the daemon on the config's devices and bundle (not as the service: stop the service
first, the devices are single-user), for ``--max-items`` pieces, recording every frame, arm
telemetry, gate call and decision. The session journals beside the replay, not into the
service's journal. A latched fault ends the recording (the fault is part of it). The simulated
cell records through `vs2t-edge demo --record DIR`.
"""

from __future__ import annotations

import sys
from pathlib import Path


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("--config", required=True, help="cell config (YAML)")
    parser.add_argument("--out", required=True, help="replay folder to write (NAME.replay)")
    parser.add_argument("--max-items", type=int, default=5, help="pieces to record (default 5)")


def run(args) -> int:
    from vs2t_edge.runtime.cell import ContinuousFeed
    from vs2t_edge.runtime.config import ConfigError, load_config
    from vs2t_edge.runtime.daemon import build_live_devices, default_evidence_factory, load_model
    from vs2t_edge.runtime.replay import record_session

    try:
        cfg = load_config(args.config)
        camera, arm, gate = build_live_devices(cfg)
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    try:
        model = load_model(cfg)
    except Exception as exc:  # noqa: BLE001
        print(f"record: bundle {cfg.bundle} refused: {exc}", file=sys.stderr)
        return 2
    from vs2t_edge.runtime.replay import ReplayFile

    out = record_session(cfg, Path(args.out), model=model, camera=camera, arm=arm, gate=gate,
                         items=ContinuousFeed(limit=args.max_items), evidence_factory=default_evidence_factory(cfg),
                         log=lambda m: print(m, file=sys.stderr))
    index = ReplayFile.open(out).index
    finals = [d for d in index["decisions"] if d["type"] == "final"]
    faults = [d for d in index["decisions"] if d["type"] == "fault"]
    code = int(index["meta"].get("daemon_exit") or 0)
    print(f"recorded {len(finals)} of {args.max_items} items into {out}"
          + (f"; ended latched: {faults[-1]['reason']}" if faults and len(finals) < args.max_items else ""))
    if code != 0:
        print(f"record: the daemon stopped with exit {code} (see the messages above); the replay holds what "
              "happened until then", file=sys.stderr)
    return code

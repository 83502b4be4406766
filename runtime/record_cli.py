"""`vs2t-edge record --config FILE --out NAME.replay`: record a live session into a replay file.

Runs the daemon on the config's devices and bundle (not as the service: stop the service
first, the devices are single-user), for ``--max-items`` pieces, recording every frame, arm
telemetry, gate call and decision. The session journals beside the replay, not into the
service's journal. A latched fault ends the recording (the fault is part of it). The simulated
cell records through `vs2t-edge demo --record DIR`.

Ctrl-C (SIGINT) or SIGTERM ends the recording as SIGTERM ends the service - the item in hand is
aborted to the reject bin at the next press boundary, gate to reject, arm stopped - and what was
recorded until then is saved (exit 0, ``meta.stopped_by`` names the signal); an exception is
re-raised only after the save. Exit codes: 0 recorded (all items, or until a signal), 2 config or
bundle refused, 3 a device fault at start.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from pathlib import Path

from vs2t_edge.runtime import wiring
from vs2t_edge.runtime.items import ContinuousFeed
from vs2t_edge.runtime.config import ConfigError, load_config
from vs2t_edge.runtime.recording import record_session
from vs2t_edge.runtime.replay import ReplayFile


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("--config", required=True, help="cell config (YAML)")
    parser.add_argument("--out", required=True, help="replay folder to write (NAME.replay)")
    parser.add_argument("--max-items", type=int, default=5, help="pieces to record (default 5)")


def run(args) -> int:
    return record(args.config, args.out, args.max_items)


def record(config: Path | str, out: Path | str, max_items: int) -> int:
    """Record ``max_items`` pieces on the devices and bundle of the cell config ``config`` into
    the replay folder ``out``; the exit code of `vs2t-edge record`. `calibrate-threshold`'s live
    presses call this too."""
    # Handlers first: a signal during the bundle check stops the session before it starts; from
    # then on the daemon's loop sees stop_event at its next press boundary.
    stop_event = threading.Event()

    def on_signal(signum, _frame) -> None:
        name = signal.Signals(signum).name
        if not stop_event.is_set():
            print(f"record: {name}: finishing the item in hand safely, then saving what was recorded",
                  file=sys.stderr, flush=True)
        stop_event.signal_name = name  # type: ignore[attr-defined] - read by record_session's meta
        stop_event.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _record(Path(config), Path(out), max_items, stop_event)
    finally:  # a caller in the same process (tests, a shell) gets its own handlers back
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def recording_feed(max_items: int) -> ContinuousFeed:
    """The pieces of a recording, named ``rec<UTC time>-000001``...: never a live journal's
    ``piece-...`` nor another recording's. The recording reads the config's operator-labels file,
    and so does the live service: a label given a recorded piece (`vs2t-edge label CONFIG ITEM
    FABRIC --recording OUT`) is then applied by that recording alone - by the live service, or a
    later recording, it is journaled as naming no piece of theirs."""
    return ContinuousFeed(limit=max_items, prefix="rec" + time.strftime("%Y%m%dT%H%M%S", time.gmtime()))


def _record(config: Path, out: Path, max_items: int, stop_event: threading.Event) -> int:
    # wiring's builders looked up when called: a test replaces one (fake devices, a fake model) in one place
    try:
        cfg = load_config(config)
        camera, arm, gate = wiring.build_live_devices(cfg)
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    try:
        model = wiring.load_model(cfg)
    except Exception as exc:  # noqa: BLE001
        print(f"record: bundle {cfg.bundle} refused: {exc}", file=sys.stderr)
        return 2
    wiring.match_camera(camera, model, cfg.camera["decode_scale"])  # a UVC camera decodes at the bundle's scale
    # the item rule is the daemon's own (wiring.build_cell): what `run` would decide is recorded
    out = record_session(cfg, out, model=model, camera=camera, arm=arm, gate=gate,
                         items=recording_feed(max_items), log=lambda m: print(m, file=sys.stderr),
                         stop_event=stop_event)
    index = ReplayFile.open(out).index
    finals = [d for d in index["decisions"] if d["type"] == "final"]
    faults = [d for d in index["decisions"] if d["type"] == "fault"]
    code = int(index["meta"].get("daemon_exit") or 0)
    print(f"recorded {len(finals)} of {max_items} items into {out}"
          + (f"; stopped by {index['meta']['stopped_by']}" if index["meta"].get("stopped_by") else "")
          + (f"; ended latched: {faults[-1]['reason']}" if faults and len(finals) < max_items else ""))
    if code != 0:
        print(f"record: the daemon stopped with exit {code} (see the messages above); the replay holds what "
              "happened until then", file=sys.stderr)
    return code

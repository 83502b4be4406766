"""`vs2t-edge run --config FILE`: the sorting cell as a systemd service (Type=notify).

Start-up order (each step says what it is doing in STATUS=):

1. load and validate the config (exit 2 on any problem; ExecStartPre has checked it already);
2. load the bundle: hashes, shapes, versions verified, sessions warmed, probe input checked
   against the manifest (runtime/inference.py) - exit 2 if the bundle is not the one it says,
   and exit 2 for a bundle without a scene model unless the config opts in
   (``evidence.without_scene_model: allow``: nothing would send an off-scene piece to reject);
   once all passed, a log and STATUS line "... probe check passed ..." (READY=1 comes after it);
3. open the journal (a torn last record is cut and kept aside), resolve an item the last run
   left between its pre-sort and final records, restore a latched fault from the fault file;
4. connect camera, arm and gate - exit 3 on a device fault (systemd restarts, within limits);
   a gate found latched (fault or fail-safe, e.g. after a stop longer than its heartbeat
   timeout) latches a fault before the first piece is pressed;
5. READY=1, then the loop (runtime/cell.py) with WATCHDOG=1 pings and STATUS= lines.

SIGTERM/SIGINT: the current item is aborted at the next press boundary (gel lifted, gate to
reject, its final record ``aborted``), then gate to reject, arm stopped, ``stop`` record,
journal closed, STOPPING=1, exit 0.

``--clear-fault``: the operator's command after fixing the cause of a latched fault: prints
the reason and removes the fault file - the config's, or, when that is absent, the one the
journal's latched fault names (found as a start finds it, ``fault_latch.find_latched_fault``);
the running service sees it, clears the gate and arm and resumes (a stopped service starts clean).

This module is the service around the cell: start-up order, signals, watchdog and the fault
clear. The parts - model, devices, item rule, the Cell itself - are built by runtime/wiring.py,
which `record`, `replay`, `calibrate-threshold` and the demo share. Devices of kind ``sim`` are
built by the simulated cell (vs2t_edge.sim.scene, the demo), which calls :func:`run_daemon` with
them: the cell runtime never imports the simulators, but for a gate of kind ``sim``, looked up by
name when the config asks for it (runtime/devices.py).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Any, Callable

from vs2t_edge.runtime.bundle import SEAL_KEY
from vs2t_edge.runtime.config import CellConfig, ConfigError, load_config_or_say
from vs2t_edge.runtime.devices import DeviceError
from vs2t_edge.runtime.fault_latch import find_latched_fault
from vs2t_edge.runtime.journal import Journal, JournalError, iter_records, latched_fault_in
from vs2t_edge.runtime.jpeg_quality import quality_note, trained_quality
from vs2t_edge.runtime.notify import Notifier
from vs2t_edge.runtime.operating_point import confidence_override_note
from vs2t_edge.runtime import job_check, wiring
from vs2t_edge.runtime.wiring import SceneModelMissing, build_cell, build_live_devices, load_model, match_camera

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_DEVICE = 0, 1, 2, 3


def _log(msg: str) -> None:
    print(f"vs2t-edge: {msg}", file=sys.stderr, flush=True)


def clear_fault(cfg: CellConfig) -> int:
    """The operator's clear: the latched fault found as the service's start finds it
    (``find_latched_fault``: the config's fault file, else the one the journal's last fault record
    names), its file removed; a fault whose file was never written is only in the journal, and is
    said so (exit 1) - the service's next start writes its file, which the operator then removes."""
    ff = cfg.fault_file
    found = find_latched_fault(ff, lambda: latched_fault_in(cfg.journal))
    if found is None:
        print(f"no latched fault ({ff} absent, and the journal {cfg.journal} names no other fault file still there)")
        return EXIT_OK
    if found.file is None:
        print(f"fault NOT cleared: {found.reason}\nits fault file {ff} was never written (the journal {cfg.journal} "
              "says so): the service writes it as soon as it can - a running one retries every turn, a stopped "
              "one at its next start - and then `vs2t-edge run --clear-fault` clears it")
        return EXIT_FAILED
    found.file.unlink(missing_ok=True)  # a running service may have cleared it meanwhile
    if found.moved:
        print(f"fault cleared: {found.reason}\nit was latched under an earlier config's fault file {found.file} "
              f"(removed; this config's is {ff}): the service starts clean")
    else:
        print(f"fault cleared: {found.reason}\nthe running service clears the gate and arm and resumes sorting")
    return EXIT_OK


def job_check_lines(cfg: CellConfig, model, evidence_factory) -> list[str]:
    """Before the first piece: the job's fabrics whose own picture the cell cannot sort
    (runtime/job_check.py), with the item rule the cell will use; nothing for a bundle without a
    scene model. Advice in the log, never a reason not to start. It reads the bundle's model as it
    came: with operator labels, what earlier labels taught (restored from the journal when the cell
    is built) is not in it, so a restarted job may hear of a fabric it has taught already."""
    scene_model = getattr(model, "scene_model", None)
    if scene_model is None:
        return []
    try:
        return job_check.summary_lines(job_check.check_job(scene_model, cfg.scene_classes, evidence_factory,
                                                           cfg.max_presses))
    except ValueError as exc:  # a scene class the scene model lacks: the start refuses that elsewhere
        return [f"job check skipped: {exc}"]


def camera_runs(camera) -> dict:
    """What a live camera's driver accepted (``UVCCamera.settings_applied``: pixel format, size,
    rate, exposure, queue, frames flushed), as JSON values for the start record; {} for cameras
    that say nothing (replay, simulated)."""
    applied = getattr(camera, "settings_applied", None)
    if not isinstance(applied, dict):
        return {}
    return {str(k): v for k, v in applied.items() if v is None or isinstance(v, (bool, int, float, str))}


def stream_quality_teller(camera_jpeg: int, log: Callable[[str], None]) -> Callable[[int | None], None]:
    """What a UVC camera calls with the MJPEG quality of its first frame (``on_stream_quality``):
    the log says, once a service run, when the bundle was trained for other frames
    (runtime/jpeg_quality.py ``quality_note``; said, never refused)."""
    told = False

    def tell(quality: int | None) -> None:
        nonlocal told
        note = quality_note(quality, camera_jpeg)
        if note and not told:
            told = True
            log(note)
    return tell


def run_daemon(cfg: CellConfig, *, model=None, camera=None, arm=None, gate=None, items=None,
               evidence_factory=None, notifier=None, stop_event: threading.Event | None = None,
               on_item=None, max_items: int | None = None, stop_when=None, install_signals: bool = True,
               log: Callable[[str], None] = _log) -> int:
    notifier = notifier or Notifier()
    stop_event = stop_event or threading.Event()
    if install_signals:
        def on_signal(signum, _frame):
            log(f"{signal.Signals(signum).name}: finishing safely")
            notifier.stopping(f"stopping ({signal.Signals(signum).name}): current item aborted to reject")
            stop_event.set()

        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)

    notifier.status(f"loading bundle {cfg.bundle}")
    t0 = time.monotonic()
    try:
        if model is None:
            model = load_model(cfg)
        elif getattr(model, "manifest", None) is not None:
            # a bundle loaded by the caller (replay, recording, the demo): load_model's check of the
            # scene - a fabric the bundle lacks, or of the other kind, is a wrong config or bundle
            wiring.check_scene_against_bundle(cfg, model)
    except Exception as exc:  # noqa: BLE001 - any bundle problem stops the start, in words
        notifier.status(f"bundle refused: {exc}")
        log(f"bundle {cfg.bundle} refused: {exc}")
        return EXIT_USAGE
    load_s = time.monotonic() - t0
    if evidence_factory is None:  # the config's item rule for this bundle (a caller may bring its own)
        try:
            evidence_factory = wiring.evidence_factory_for(cfg, model)
        except SceneModelMissing as exc:  # also: operator labels on a bundle that cannot learn
            notifier.status(f"bundle refused: {exc}")
            log(str(exc))
            return EXIT_USAGE
    probe = getattr(model, "probe_errors", None)
    if probe:  # TactileModel.load returned: hashes, shapes, warm-up and probe check all passed
        said = (f"bundle {cfg.bundle} verified (hashes, shapes), warmed up, probe check passed "
                f"(max relative error {max(probe.values()):.2g}) in {load_s:.1f} s")
        log(said)
        notifier.status(said)
    note = confidence_override_note(cfg, getattr(model, "scene_model", None))
    if note:  # the config moves the operating point training chose for the mis-sort target
        log(note)
    for line in job_check_lines(cfg, model, evidence_factory):
        log(line)
    try:
        journal = Journal.open(cfg.journal)
    except (JournalError, OSError) as exc:
        log(f"journal: {exc}")
        notifier.status(f"journal unusable: {exc}")
        return EXIT_USAGE
    folder = cfg.fault_file.parent
    if not (folder.is_dir() and os.access(folder, os.W_OK | os.X_OK)):
        # a fault the service could not latch durably: refused before anything moves (the loop
        # would hold such a fault anyway, runtime/fault_latch.py, but no operator could clear it)
        log(f"fault file {cfg.fault_file}: its folder {folder} is not a folder this service may write "
            "(the unit's ReadWritePaths, permissions); set fault_file to a writable place")
        notifier.status(f"fault file unwritable: {cfg.fault_file}")
        journal.close()
        return EXIT_USAGE
    if journal.torn_bytes:
        log(f"journal {cfg.journal}: torn last record ({journal.torn_bytes} bytes) cut, kept in "
            f"{cfg.journal}.torn")
    if camera is None or arm is None or gate is None:
        try:
            camera, arm, gate = build_live_devices(cfg)
            match_camera(camera, model, cfg.camera["decode_scale"])  # a UVC camera decodes at the bundle's scale
            note = wiring.decode_scale_note(model, cfg.camera["decode_scale"])
            if note:
                log(f"{cfg.path}: {note}")
        except (ConfigError, ValueError) as exc:  # ValueError: a driver refusing its settings
            # (validation checks the drivers' constraints, so this is a gap to report, in words)
            log(str(exc) if isinstance(exc, ConfigError) else f"{cfg.path}: a device refused its settings: {exc}")
            journal.close()
            return EXIT_USAGE
    connected: list[Any] = []
    try:
        for name, dev in (("gate", gate), ("arm", arm), ("camera", camera)):
            notifier.status(f"connecting {name}")
            dev.connect()
            connected.append(dev)
    except DeviceError as exc:
        log(f"cannot start: {exc}")
        notifier.status(f"device fault at start: {exc}")
        for dev in connected:
            try:
                dev.disconnect()
            except Exception:  # noqa: BLE001
                pass
        try:
            journal.append({"type": "start_failed", "reason": str(exc), "t": time.time()})
        except JournalError as jexc:
            log(f"journal {cfg.journal}: start_failed not recorded ({jexc})")
        journal.close()
        return EXIT_DEVICE
    missing = scene_bins_missing(cfg, gate)
    if missing:  # every piece of those fabrics would latch a fault at its sort, mid-job
        log(f"cannot start: {missing}")
        notifier.status(f"gate has too few bins: {missing}")
        _disconnect_all(camera, arm, gate)
        try:
            journal.append({"type": "start_failed", "reason": missing, "t": time.time()})
        except JournalError as jexc:
            log(f"journal {cfg.journal}: start_failed not recorded ({jexc})")
        journal.close()
        return EXIT_USAGE
    try:
        gate.to_reject()  # a fresh start routes nothing until a decision says so
    except Exception:  # noqa: BLE001
        pass
    cell = build_cell(cfg, model=model, camera=camera, arm=arm, gate=gate, journal=journal, notifier=notifier,
                      items=items, evidence_factory=evidence_factory, stop_event=stop_event, on_item=on_item, log=log)
    try:
        seal = bundle_seal(model)  # which bundle, not only which folder: a swapped bundle is auditable
        runs = camera_runs(camera)  # what the driver accepted (format, size, rate, queue, flush)
        journal.append({"type": "start", "t": time.time(), "config": str(cfg.path), "bundle": str(cfg.bundle),
                        **({SEAL_KEY: seal} if seal else {}), **({"camera": runs} if runs else {}),
                        "beta": _float_or_none(getattr(model, "beta", None)), "load_s": round(load_s, 3)})
        if runs:
            log("camera runs: " + ", ".join(f"{k} {v}" for k, v in runs.items()))
        if note := wiring.decode_fallback_note(model, camera):  # a backend that decodes what the bundle trained on
            log(f"{cfg.path}: {note}")
    except JournalError as exc:  # e.g. the disk is full: nothing may move without a journal
        log(f"journal {cfg.journal}: cannot write the start record ({exc}); free space or fix the state "
            "folder, then start again")
        notifier.status(f"journal unwritable: {exc}")
        _disconnect_all(camera, arm, gate)
        journal.close()
        return EXIT_USAGE
    if hasattr(camera, "on_stream_quality"):  # a UVC camera taking MJPEG undecoded reads its quality from a frame
        camera.on_stream_quality = stream_quality_teller(trained_quality(model), log)
    if hasattr(evidence_factory, "restore"):  # operator labels: the pieces and labels of this bundle so far
        evidence_factory.restore(iter_records(cfg.journal), seal)
    cell.recover()
    if cell.fault is None:
        latched = gate_latched_at_start(gate)
        if latched:
            cell.latch_fault(*latched)
    beta = getattr(model, "beta", None)
    notifier.ready(f"ready: bundle {cfg.bundle} verified and warm in {load_s:.1f} s"
                   + (f", beta {beta:.4g}" if isinstance(beta, (int, float)) else "")
                   + (f"; FAULT latched: {cell.fault}" if cell.fault else ""))
    notifier.watchdog()
    reason = "stopped"
    try:
        cell.run(max_items=max_items, stop_when=stop_when)
        reason = "SIGTERM" if stop_event.is_set() else "done"
    except BaseException as exc:  # noqa: BLE001 - the journal must close, the gate must go to reject
        reason = f"crashed: {exc!r}"
        log(reason)
        cell.shutdown(reason)
        _disconnect_all(camera, arm, gate)
        raise
    cell.shutdown(reason)
    _disconnect_all(camera, arm, gate)
    notifier.stopping(f"stopped ({reason}); {cell.items_done} items")
    notifier.close()
    return EXIT_OK


def scene_bins_missing(cfg: CellConfig, gate) -> str:
    """'' when the gate has every bin the scene names, else which fabrics' bins it lacks. A gate
    that cannot say now (status fails, or a gate that reports no bin count) is not refused here:
    ``gate_latched_at_start`` deals with a gate that does not answer."""
    try:
        n_bins = gate.status().n_bins
    except DeviceError:
        return ""
    if not isinstance(n_bins, int):
        return ""
    beyond = [f"{f.name} (bin {f.bin})" for f in cfg.fabrics if f.bin >= n_bins]
    if not beyond:
        return ""
    return (f"{cfg.path}: the gate has bins 0..{n_bins - 1}, and the scene sends {', '.join(beyond)} beyond them; "
            "every such piece would latch a fault at its sort - give those fabrics bins the gate has")


def gate_latched_at_start(gate) -> tuple[str, str] | None:
    """(reason, kind) when the gate refuses to route right now, else None. A gate that latched while
    no service fed it (down longer than its heartbeat timeout, a jam, a reboot) is seen here, before
    the first piece is pressed - not by the sort after the piece's presses - and latched as any gate
    fault: nothing moves until the operator's clear, which clears the gate too. So is a gate whose
    start-up ``to_reject`` failed while its status says ready (``failing_safe``): its heartbeats
    were stopped so that it fails safe on its own, and the first piece would have been pressed and
    its decision refused at the sort a second later. (A latched gate refuses that ``to_reject`` too;
    its status says why, first.)"""
    try:
        status = gate.status()
    except DeviceError as exc:
        return f"gate status at start failed: {exc}", exc.kind
    if status.state in ("fault", "failsafe"):
        return (f"gate latched at start: {status.state} ({status.fault or 'no reason given'}), flap at bin "
                f"{status.bin} - it routes nothing until cleared; check the gate, then clear", "fault_latched")
    if getattr(gate, "failing_safe", False) is True:
        return ("gate to reject at start failed: its heartbeats are stopped so that it fails safe on its own, "
                "and it routes nothing until cleared; check the gate's link, then clear", "link")
    return None


def bundle_seal(model) -> str | None:
    """The manifest seal (``manifest_sha256``) of the bundle ``model`` was loaded from; None for a
    model that names none (an injected fake)."""
    manifest = getattr(model, "manifest", None)
    seal = manifest.get(SEAL_KEY) if isinstance(manifest, dict) else None
    return seal if isinstance(seal, str) and seal else None


def _float_or_none(x) -> float | None:
    return float(x) if isinstance(x, (int, float)) else None


def _disconnect_all(*devices) -> None:
    for dev in devices:
        try:
            dev.disconnect()
        except Exception:  # noqa: BLE001
            pass


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("--config", required=True, help="cell config (YAML); see docs/cell.md")
    parser.add_argument("--clear-fault", action="store_true",
                        help="clear a latched fault (after fixing its cause) and exit")
    parser.add_argument("--max-items", type=int, default=None, help="stop after this many items (commissioning)")


def run(args) -> int:
    if (cfg := load_config_or_say(args.config)) is None:
        return EXIT_USAGE
    if args.clear_fault:
        return clear_fault(cfg)
    return run_daemon(cfg, max_items=args.max_items)

"""`vs2t-edge demo [--workdir DIR]`: the embedded default, end to end, on the simulated cell.

Stages (each cached in the work folder and skipped when re-run with the same settings):

1. the fabric world: ``vs2t_edge.sim.synth.generate`` (profile ``small``) -> ``DIR/dataset``;
2. training: ``vs2t-edge train DIR/dataset --profile small --out DIR/run`` (a child process:
   torch stays out of this one);
3. export: ``vs2t-edge export DIR/run --out DIR/bundle`` (verified ONNX bundle);
4. sorting: the daemon (runtime/daemon.py, the service's code) on the simulated cell - the real
   ur_rtde client against the loopback UR simulator, the gate host driver against the MCU
   simulator on a pty, the camera fed from the dataset - over a stream of pieces: the bundle's
   touched and untouched fabrics (the scene) and the dataset's other fabrics (off-scene: they
   must go to the reject bin).

Prints a line per item (truth, decision, bin, presses, confidence, model latency) and the
totals: accuracy, presses per item, latency, time per item, time per stage; writes them to
``DIR/demo_summary.json``. ``--record FILE`` also records the sorting session as a replay.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path


def _stage_done(marker: Path, params: dict) -> bool:
    try:
        return json.loads(marker.read_text()).get("params") == params
    except (OSError, ValueError):
        return False


def _mark(marker: Path, params: dict, seconds: float) -> None:
    marker.write_text(json.dumps({"params": params, "seconds": round(seconds, 1),
                                  "at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}))


def _child(argv: list[str], what: str) -> None:
    env = dict(os.environ)
    proc = subprocess.run([sys.executable, "-m", "vs2t_edge", *argv], env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"{what} failed (exit {proc.returncode}): vs2t-edge {' '.join(argv)}")


def prepare(workdir: Path, *, profile: str, seed: int, force: bool, log) -> tuple[Path, Path, dict]:
    """Dataset, run and bundle in workdir, each stage skipped when cached. Returns stage times."""
    workdir.mkdir(parents=True, exist_ok=True)
    times: dict[str, float] = {}
    dataset, run, bundle = workdir / "dataset", workdir / "run", workdir / "bundle"

    params = {"profile": profile, "seed": seed}
    marker = workdir / ".stage-synth.json"
    if force or not _stage_done(marker, params) or not dataset.is_dir():
        log(f"[1/4] fabric world ({profile}) -> {dataset}")
        t0 = time.monotonic()
        from vs2t_edge.sim.synth import generate

        if dataset.exists():
            import shutil

            shutil.rmtree(dataset)
        generate(dataset, profile=profile, seed=seed)
        times["synth_s"] = time.monotonic() - t0
        _mark(marker, params, times["synth_s"])
        force = True  # everything downstream is stale
    else:
        log(f"[1/4] fabric world: cached ({dataset})")

    marker = workdir / ".stage-train.json"
    if force or not _stage_done(marker, params) or not run.is_dir():
        log(f"[2/4] training ({profile}) -> {run}")
        t0 = time.monotonic()
        _child(["train", str(dataset), "--profile", profile, "--out", str(run)], "training")
        times["train_s"] = time.monotonic() - t0
        _mark(marker, params, times["train_s"])
        force = True
    else:
        log(f"[2/4] training: cached ({run})")

    marker = workdir / ".stage-export.json"
    if force or not _stage_done(marker, params) or not bundle.is_dir():
        log(f"[3/4] export -> {bundle}")
        t0 = time.monotonic()
        _child(["export", str(run), "--out", str(bundle)], "export")
        times["export_s"] = time.monotonic() - t0
        _mark(marker, params, times["export_s"])
    else:
        log(f"[3/4] export: cached ({bundle})")
    return dataset, bundle, times


def sort_stream(workdir: Path, dataset: Path, bundle: Path, *, n_items: int, seed: int, arm_kind: str,
                gate_kind: str, max_presses: int, confidence: float, threads: int, record: Path | None,
                fault_at: tuple[int, int] | None, log) -> dict:
    from vs2t_edge.runtime.daemon import default_evidence_factory, run_daemon
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.inference import TactileModel
    from vs2t_edge.sim.scene import (
        SimulatedCell,
        assign_bins,
        item_stream,
        scene_config_yaml,
        score_run,
        write_scene_config,
    )

    model = TactileModel.load(bundle, threads=threads, beta_override=None)
    touched, untouched = list(model.touched), list(model.untouched)
    ds = load_dataset(dataset)
    scene_names = set(touched) | set(untouched)
    off_scene = [f.id for f in ds.fabrics if f.id not in scene_names][:max(1, len(scene_names) // 4)]
    # Bundle classes are dataset ids; the printout adds the fabric's name for the operator.
    names_of = {f.id: f.name for f in ds.fabrics}
    # Scene pieces are the touched and untouched fabrics; a few off-scene pieces test the reject path.
    names = touched + untouched + off_scene
    items = item_stream(ds, names, n_items, seed=seed)
    fabrics = assign_bins(touched, untouched)
    journal = workdir / "journal.jsonl"
    if journal.exists():
        journal.unlink()
    kinds = {n: k for n, k, _ in fabrics}
    rows_printed = []

    def on_item(r) -> None:
        truth = r.item.truth
        tk = kinds.get(truth, "off-scene")
        ok = (r.label == truth) if truth in scene_names else (r.label not in scene_names)
        lat = sum(r.latency_ms) / len(r.latency_ms) if r.latency_ms else float("nan")
        said = f"{r.label} {names_of.get(r.label, '')}".strip()
        line = (f"{r.item.id}  {truth} {names_of.get(truth, ''):>22s} ({tk:9s}) -> {said:>26s}  bin {r.bin}  "
                f"{r.presses} {'press' if r.presses == 1 else 'presses':7s}  "
                f"conf {r.confidence:.2f}  {lat:6.1f} ms/press  {r.item_s:5.1f} s  "
                f"{'ok' if ok and r.outcome == 'sorted' else 'WRONG' if r.outcome == 'sorted' else r.outcome}")
        rows_printed.append(line)
        log(line)

    with SimulatedCell(dataset, items, arm_kind=arm_kind, gate_kind=gate_kind) as cell:
        data = scene_config_yaml(bundle=bundle, dataset=dataset, journal=journal, fabrics=fabrics,
                                 arm_host=cell.arm_host, confidence=confidence, max_presses=max_presses,
                                 threads=threads)
        cfg = write_scene_config(workdir / "cell.yaml", data)
        if fault_at is not None:
            cell.schedule_fault(fault_at[0], fault_at[1], "protective_stop")
        t0 = time.monotonic()
        results_holder: list = []

        def capture(r):
            results_holder.append(r)
            on_item(r)

        log(f"[4/4] sorting {n_items} pieces: scene {len(touched)} touched + {len(untouched)} untouched fabrics, "
            f"{len(off_scene)} off-scene; arm {arm_kind}, gate {gate_kind}")
        if record is not None:
            from vs2t_edge.runtime.replay import record_session

            record_session(cfg, record, model=model, camera=cell.camera, arm=cell.arm, gate=cell.gate,
                           items=cell.source, evidence_factory=default_evidence_factory(cfg),
                           operator_clear=cell.operator_clear, on_item=capture,
                           meta={"made_by": "vs2t-edge demo", "seed": seed})
        else:
            def stop_when() -> bool:
                if cfg.fault_file.exists():
                    log("operator: protective stop released, fault cleared")
                    cell.operator_clear()
                    cfg.fault_file.unlink()
                    return False
                return cell.source.exhausted()

            run_daemon(cfg, model=model, camera=cell.camera, arm=cell.arm, gate=cell.gate, items=cell.source,
                       evidence_factory=default_evidence_factory(cfg), on_item=capture, stop_when=stop_when,
                       install_signals=False, log=lambda m: log(f"  daemon: {m}"))
        sort_s = time.monotonic() - t0
    summary = score_run(results_holder, items, scene_names)
    summary["sort_s"] = sort_s
    by_kind: dict[str, list[bool]] = {}
    for row in summary["rows"]:
        by_kind.setdefault(kinds.get(row["truth"], "off-scene"), []).append(row["correct"])
    summary["accuracy_by_kind"] = {k: sum(v) / len(v) for k, v in by_kind.items()}
    return summary


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("--workdir", default="vs2t-demo", help="work folder; stages are cached there")
    parser.add_argument("--items", type=int, default=24, help="pieces in the stream (default 24)")
    parser.add_argument("--profile", default="small", help="world and training profile (default small)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--arm", choices=("ursim", "fake"), default="ursim",
                        help="ursim: real ur_rtde client against the loopback simulator (default)")
    parser.add_argument("--gate", choices=("pty", "fake"), default="pty",
                        help="pty: gate host driver against the MCU simulator (default)")
    parser.add_argument("--max-presses", type=int, default=5)
    parser.add_argument("--confidence", type=float, default=0.95)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--fault-at", default=None, metavar="ITEM:PRESS",
                        help="inject a protective stop at that press of that item (0-based item)")
    parser.add_argument("--record", default=None, help="also record the session into this replay folder")
    parser.add_argument("--force", action="store_true", help="redo every stage")


def run(args) -> int:
    def log(msg: str) -> None:
        print(msg, flush=True)

    workdir = Path(args.workdir).resolve()
    t0 = time.monotonic()
    fault_at = None
    if args.fault_at:
        try:
            a, b = args.fault_at.split(":")
            fault_at = (int(a), int(b))
        except ValueError:
            print("demo: --fault-at wants ITEM:PRESS, e.g. 3:2", file=sys.stderr)
            return 2
    try:
        dataset, bundle, times = prepare(workdir, profile=args.profile, seed=args.seed, force=args.force, log=log)
    except ModuleNotFoundError as exc:
        print(f"demo: a stage is not available in this build ({exc.name})", file=sys.stderr)
        return 4 if (exc.name or "").split(".")[0] in {"torch", "onnx"} else 2
    except RuntimeError as exc:
        print(f"demo: {exc}", file=sys.stderr)
        return 1
    summary = sort_stream(workdir, dataset, bundle, n_items=args.items, seed=args.seed, arm_kind=args.arm,
                          gate_kind=args.gate, max_presses=args.max_presses, confidence=args.confidence,
                          threads=args.threads, record=Path(args.record) if args.record else None,
                          fault_at=fault_at, log=log)
    summary["stage_s"] = {k: round(v, 1) for k, v in times.items()}
    summary["total_s"] = time.monotonic() - t0
    by_kind = ", ".join(f"{k} {v:.0%}" for k, v in sorted(summary["accuracy_by_kind"].items()))
    log("")
    log(f"accuracy {summary['accuracy']:.1%} over {summary['items']} pieces ({by_kind})")
    log(f"presses per piece {summary['presses_per_item']:.2f}; model latency median "
        f"{summary['latency_ms_median']:.1f} ms, p95 {summary['latency_ms_p95']:.1f} ms per press; "
        f"{summary['item_s_median']:.1f} s per piece (simulated arm in real time)")
    stages = ", ".join(f"{k.removesuffix('_s')} {v:.0f} s" for k, v in summary["stage_s"].items()) or "all stages cached"
    log(f"time: {stages}; sorting {summary['sort_s']:.0f} s; total {summary['total_s']:.0f} s")
    (workdir / "demo_summary.json").write_text(json.dumps(summary, indent=1, default=float))
    log(f"summary: {workdir / 'demo_summary.json'}; journal: {workdir / 'journal.jsonl'}")
    return 0

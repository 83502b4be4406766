"""`vs2t-edge demo [--workdir DIR]`: the embedded default, end to end, on the simulated cell.

Stages (each cached in the work folder and skipped when re-run with the same settings):

1. the fabric world: ``vs2t_edge.sim.synth.generate`` (profile ``demo``: 24 fabrics of 6 kinds, 4 of
   each, so every fabric the cell never touches has touched siblings) -> ``DIR/dataset``;
2. training: ``vs2t-edge train DIR/dataset --profile small --out DIR/run`` (a child process:
   torch stays out of this one);
3. export: ``vs2t-edge export DIR/run --out DIR/bundle`` (verified ONNX bundle);
4. sorting: the daemon (runtime/daemon.py, the service's code) on the simulated cell - the real
   ur_rtde client against the loopback UR simulator, the gate host driver against the MCU
   simulator on a pty, the camera fed from the dataset - over a stream of pieces: the bundle's
   touched and untouched fabrics (the scene) and the dataset's other fabrics (off-scene: they
   must go to the reject bin).

The job (the scene) is 4 of the bundle's touched and 3 of its untouched fabrics, one bin each; the
stream adds off-scene pieces of a touched fabric the job leaves out and of a fabric the bundle has
never seen. Touched pieces show only presses no training step saw. Prints a line per item (truth,
its bin, decision, bin, presses, confidence, latency: right / rejected / MIS-SORTED) and the totals
as a sorting line counts them (runtime/sorting.py): per kind, right bin, mis-sort, reject - of the
pieces whose bin is known: a piece journalled ``unknown_outcome`` (the gate may have moved it) is
counted on its own line, "outcome unknown", in no share; presses per piece, pieces per minute, latency, time per stage; writes them to
``DIR/demo_summary.json``. ``--record FILE`` also records the sorting session as a replay.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from vs2t_edge.runtime import sorting as so
from vs2t_edge.runtime.daemon import run_daemon
from vs2t_edge.runtime.dataset import load_dataset, press_partition
from vs2t_edge.runtime.labels import append_label
from vs2t_edge.runtime.inference import TactileModel
from vs2t_edge.runtime.recording import record_session
from vs2t_edge.runtime.wiring import SceneModelMissing, require_scene_model
from vs2t_edge.sim.scene import SimItem, SimulatedCell, assign_bins, item_stream, scene_config_yaml, write_scene_config

TEACH_PREFIX = "teach-"  # a teach piece's item id: pressed and labelled before the job, not counted
UNKNOWN_OUTCOME = "unknown_outcome"  # a final record's outcome: the gate may or may not have moved the piece
OUTCOME_UNKNOWN = "outcome unknown"  # such a piece's result: counted apart from right / mis-sort / reject
# world profile -> training profile (the demo's world trains with the small profile's budget)
TRAIN_PROFILE = {"demo": "small", "demo_visible": "small"}


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
        _child(["train", str(dataset), "--profile", TRAIN_PROFILE.get(profile, profile), "--out", str(run)], "training")
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


def choose_scene(touched: list[str], untouched: list[str], others: list[str], seed: int,
                 n_touched: int = 4, n_untouched: int = 3) -> tuple[list[str], list[str], list[str]]:
    """The demo's sorting job: ``n_touched`` of the bundle's touched fabrics and ``n_untouched`` of
    its untouched ones (one bin each on the 8-bin gate, bin 0 rejects), drawn with the seed; the
    off-scene pieces are one touched fabric the job leaves out (the cell knows it) and one of the
    ``others`` (the validation fabrics: no bundle class, known to its scene model only to refuse)."""
    rng = np.random.default_rng(seed)
    st = sorted(rng.choice(touched, min(n_touched, len(touched)), replace=False).tolist())
    su = sorted(rng.choice(untouched, min(n_untouched, len(untouched)), replace=False).tolist())
    left = [f for f in touched if f not in st]
    off = ([str(rng.choice(left))] if left else []) + ([str(rng.choice(others))] if others else [])
    return st, su, off


def held_out_presses(ds, bundle_touched: list[str]) -> dict[str, list[int]]:
    """The touched fabrics' presses that no training step saw (the test part of
    ``runtime.dataset.press_partition``): a touched piece in the demo shows only these."""
    out = {}
    for fid in bundle_touched:
        n = len(ds.by_id(fid).presses)
        out[fid] = list(press_partition(n)[2])
    return out


def sort_stream(workdir: Path, dataset: Path, bundle: Path, *, n_items: int, seed: int, arm_kind: str,
                gate_kind: str, max_presses: int, confidence: float | None, threads: int, record: Path | None,
                fault_at: tuple[int, int] | None, log, overlap_scoring: bool = True,
                without_scene_model: str | None = None, operator_labels: bool = False, teach: bool = False,
                extra_presses: int | None = None) -> dict:
    model = TactileModel.load(bundle, threads=threads, beta_override=None)
    # the daemon would refuse it too (runtime/wiring.py), after the simulated cell came up
    require_scene_model(model, bundle, without_scene_model,
                        "give --without-scene-model allow (`--force` redoes the demo's stages)")
    if operator_labels and (getattr(model, "scene_model", None) is None or model.scene_model.for_labels() is None):
        log("operator labels need a scene model with an offset item rule setting; this bundle sorts zero-shot only")
        operator_labels = False
    ds = load_dataset(dataset)
    known = set(model.touched) | set(model.untouched)
    strangers = [f.id for f in ds.fabrics if f.id not in known]
    touched, untouched, off_scene = choose_scene(list(model.touched), list(model.untouched), strangers, seed)
    scene_names = set(touched) | set(untouched)
    names_of = {f.id: f.name for f in ds.fabrics}
    # Mostly the job's own fabrics, as on a line; each off-scene fabric as often as one scene fabric.
    items = item_stream(ds, touched + untouched + off_scene, n_items, seed=seed)
    taught = (teach_fabrics(model, touched + untouched, confidence, max_presses, extra_presses)
              if teach and operator_labels else [])
    items = [SimItem(f"{TEACH_PREFIX}{i + 1:02d}", f, f) for i, f in enumerate(taught)] + items
    fabrics = assign_bins(touched, untouched)
    journal = workdir / "journal.jsonl"
    labels = workdir / "labels.jsonl"  # the simulated operator's (runtime/feedback.py)
    for old in (journal, labels):
        if old.exists():
            old.unlink()
    kinds = {n: k for n, k, _ in fabrics}
    bins = {n: b for n, _, b in fabrics}
    records: list = []  # the pieces whose bin is known: the right / mis-sort / reject shares
    unknown: list[str] = []  # pieces recorded unknown_outcome: counted apart
    rows: list[dict] = []

    def on_item(r) -> None:
        truth = r.item.truth
        if r.item.id.startswith(TEACH_PREFIX):  # the operator labels it whatever bin it went to; not counted
            append_label(labels, r.item.id, truth)
            log(f"{r.item.id}  {truth} {names_of.get(truth, ''):>22s} (teach piece: {r.presses} press"
                f"{'es' if r.presses != 1 else ''}, the cell said {r.label}; operator: {truth}) - not counted")
            return
        kind = kinds.get(truth, "off-scene")
        if r.outcome == UNKNOWN_OUTCOME:  # the gate may have moved it: in no share (``report_lines``)
            unknown.append(r.item.id)
            o = OUTCOME_UNKNOWN
        else:
            rec = so.record(truth, kind, r, tuple(scene_names), sorted_=r.outcome == "sorted")
            records.append(rec)
            o = rec.outcome
        rows.append({"item": r.item.id, "truth": truth, "kind": kind, "label": r.label, "bin": r.bin,
                     "outcome": r.outcome, "result": o, "presses": r.presses, "confidence": float(r.confidence),
                     "stopped_by": r.stopped_by})
        lat = sum(r.latency_ms) / len(r.latency_ms) if r.latency_ms else float("nan")
        said = "reject" if r.label not in scene_names else f"{r.label} {names_of.get(r.label, '')}"
        mark = {so.RIGHT: "right", so.REJECT: "rejected", so.MIS_SORT: "MIS-SORTED",
                OUTCOME_UNKNOWN: "OUTCOME UNKNOWN: the gate may have moved it, a person checks the bins"}[o]
        if r.label not in scene_names and o != OUTCOME_UNKNOWN:  # the reject bin: say why ("conf" is the leading job fabric's)
            mark += f": {so.reject_reason(r.label, r.stopped_by)}"
        if r.outcome != "sorted":
            mark += f" ({r.outcome})"
        elif operator_labels and r.label not in scene_names:  # a person at the reject bin says what it was
            append_label(labels, r.item.id, truth, off_scene=truth not in scene_names)
            mark += f" (operator: {truth}" + (")" if truth in scene_names else ", off-scene)")
        own = f"bin {bins[truth]}" if truth in bins else "reject"
        log(f"{r.item.id}  {truth} {names_of.get(truth, ''):>22s} ({kind:9s}, its bin: {own:6s}) -> "
            f"{said:>26s}  bin {r.bin}  {r.presses} press{'es' if r.presses != 1 else '  '}  "
            f"conf {r.confidence:.2f}  {lat:5.1f} ms/press  {r.item_s:4.1f} s  {mark}")

    allowed = held_out_presses(ds, list(model.touched))
    with SimulatedCell(dataset, items, arm_kind=arm_kind, gate_kind=gate_kind, allowed_presses=allowed) as cell:
        data = scene_config_yaml(bundle=bundle, dataset=dataset, journal=journal, fabrics=fabrics,
                                 arm_host=cell.arm_host, confidence=confidence or 0.9, max_presses=max_presses,
                                 threads=threads)
        if confidence is None:  # the bundle's operating point decides (runtime/operating_point.py)
            del data["evidence"]["confidence"]
        if extra_presses is not None:  # else the bundle's scene model's (runtime/operating_point.py)
            data["evidence"]["extra_presses"] = extra_presses
        data["cell"] = {"overlap_scoring": overlap_scoring}
        if without_scene_model:
            data["evidence"]["without_scene_model"] = without_scene_model
        if operator_labels:
            data["evidence"]["operator_labels"] = str(labels)
        cfg = write_scene_config(workdir / "cell.yaml", data)
        if fault_at is not None:  # item-000N as printed (teach pieces are pressed first, named apart)
            cell.schedule_fault(len(taught) + fault_at[0] - 1, fault_at[1], "protective_stop")
        t0 = time.monotonic()
        results_holder: list = []

        def capture(r):
            results_holder.append(r)
            on_item(r)

        if taught:
            log(f"the operator starts the job with a teach piece of {', '.join(taught)}: the fabrics the job check "
                "(below) says the cell cannot sort at their synthesised picture (docs/cell.md; not zero-shot)")
        log(f"[4/4] sorting {n_items} pieces: the job is {len(touched)} touched + {len(untouched)} untouched "
            f"fabrics ({', '.join(f'{f} bin {bins[f]}' for f in touched + untouched)}); off-scene pieces of "
            f"{', '.join(off_scene)} must go to the reject bin 0; arm {arm_kind}, gate {gate_kind}; touched pieces "
            "show only presses no training step saw")
        # the item rule is the daemon's own (runtime/wiring.py), as `run` would build it for this config
        if record is not None:
            record_session(cfg, record, model=model, camera=cell.camera, arm=cell.arm, gate=cell.gate,
                           items=cell.source, operator_clear=cell.operator_clear, on_item=capture,
                           meta={"made_by": "vs2t-edge demo", "seed": seed},
                           keep_journal=journal)  # the totals below read it (labels applied, speculative presses)
        else:
            def stop_when() -> bool:
                if cfg.fault_file.exists():
                    log("operator: protective stop released, fault cleared")
                    cell.operator_clear()
                    cfg.fault_file.unlink()
                    return False
                return cell.source.exhausted()

            run_daemon(cfg, model=model, camera=cell.camera, arm=cell.arm, gate=cell.gate, items=cell.source,
                       on_item=capture, stop_when=stop_when,
                       install_signals=False, log=lambda m: log(f"  daemon: {m}"))
        sort_s = time.monotonic() - t0
    summary = so.summarise(records)
    from vs2t_edge.runtime.journal import read_records

    speculative = sum(r.get("speculative_presses", 0) for r in read_records(journal) if r["type"] == "pre_sort")
    summary.update(scene={"touched": touched, "untouched": untouched, "off_scene": off_scene, "bins": bins},
                   items=len(records) + len(unknown), outcome_unknown=unknown, sort_s=sort_s, rows=rows, overlap_scoring=overlap_scoring,
                   speculative_presses=speculative, operator_labels=operator_labels, teach_pieces=taught,
                   labels_applied=sum(bool(r.get("applied")) for r in read_records(journal) if r["type"] == "label"),
                   **job_pace(results_holder))
    return summary


def job_pace(results) -> dict:
    """The job's pace from the cell's results (``ItemResult``, teach pieces among them): pieces per
    minute are the counted pieces over the time of every piece pressed - a teach piece is not
    counted, but the job spent its presses (counting it a piece made the default's pace look
    faster: 32 pieces where 30 were sorted); the median time per piece is the counted pieces';
    the model's latency is every press's."""
    counted = [r.item_s for r in results if not r.item.id.startswith(TEACH_PREFIX)]
    total_s = sum(r.item_s for r in results)
    lat = [x for r in results for x in r.latency_ms]
    return {"latency_ms_median": float(np.median(lat)) if lat else float("nan"),
            "latency_ms_p95": float(np.percentile(lat, 95)) if lat else float("nan"),
            "item_s_median": float(np.median(counted)) if counted else float("nan"),
            "items_per_min": 60.0 * len(counted) / total_s if counted and total_s > 0 else float("nan"),
            "teach_s": total_s - sum(counted)}


def teach_fabrics(model, scene: list[str], confidence: float | None, max_presses: int,
                  extra_presses: int | None = None) -> list[str]:
    """The untouched fabrics of the job that the job check (runtime/job_check.py) flags: the ones
    a line would start the job with a teach piece of (docs/cell.md). The evidence is the one the
    demo's config gives the daemon (the bundle's operating point, or ``--confidence`` and
    ``--extra-presses`` over it)."""
    from vs2t_edge.runtime.evidence import Evidence
    from vs2t_edge.runtime.job_check import check_job
    from vs2t_edge.runtime.operating_point import scene_model_settings

    sm = getattr(model, "scene_model", None)
    if sm is None:
        return []
    # the config the demo writes for the daemon (``sort_stream``), through the daemon's own rule
    written = SimpleNamespace(confidence=confidence, extra_presses=extra_presses, untouched_confidence=None,
                              raw={"evidence": {"confidence": confidence}})
    conf, opts = scene_model_settings(written, sm)
    checks = check_job(sm, scene, lambda: Evidence(scene, conf, max_presses, **opts), max_presses)
    return [c.fabric for c in checks if c.kind == "untouched" and not c.sorts]


def report_lines(summary: dict) -> str:
    """The totals a sorting line reads: per kind, right bin / mis-sorted / rejected; presses; speed."""
    a = summary["all"]
    lines = [f"{a['n']} pieces: {a['right']:.1%} in the right bin, {a['mis-sort']:.1%} MIS-SORTED (wrong bin), "
             f"{a['reject']:.1%} rejected (reject bin, a person looks)"]
    if unknown := summary.get("outcome_unknown"):
        # recorded unknown_outcome: the gate may or may not have moved the piece (docs/cell.md), so it
        # is neither rejected nor in a bin - in none of the shares, which are of the pieces above
        lines.append(f"outcome unknown: {len(unknown)} piece{'s' if len(unknown) != 1 else ''} ({', '.join(unknown)}) - "
                     "the gate may have moved it into the bin it was asked for; a person checks the bins. Not in "
                     "the shares above, which are of the pieces whose bin is known")
    for kind, r in summary["by_kind"].items():
        refused = round(summary["off_scene_rule"]["by_kind"][kind] * r["n"])
        lines.append(f"  {kind:9s} {r['n']:3d} pieces: right {r['right']:6.1%}  mis-sorted {r['mis-sort']:6.1%}  "
                     f"rejected {r['reject']:6.1%}  ({r['presses']:.1f} presses each; "
                     f"{refused} to the reject bin by the off-scene rules)")
    lines.append(f"presses per piece {a['presses']:.2f}; {summary['items_per_min']:.1f} pieces per minute with the "
                 f"simulated arm in real time (a piece's median {summary['item_s_median']:.1f} s); model latency median "
                 f"{summary['latency_ms_median']:.1f} ms, p95 {summary['latency_ms_p95']:.1f} ms per press")
    if summary.get("operator_labels"):
        lines.append(f"learning from the reject bin (evidence.operator_labels, outside the zero-shot protocol): the "
                     f"simulated operator labelled every rejected piece, {summary['labels_applied']} label(s) taught the "
                     "cell (an untouched fabric's real mean, or an off-scene fabric to refuse); `--operator-labels off` "
                     "sorts zero-shot only")
    if summary.get("teach_pieces"):
        lines.append(f"teach pieces (not counted as pieces; their {summary.get('teach_s', 0.0):.1f} s are in the "
                     f"pieces per minute): {', '.join(summary['teach_pieces'])} - the job check's flagged "
                     "untouched fabrics, one labelled piece each before the job; `--teach off` leaves them out")
    if "overlap_scoring" in summary:
        spec = summary.get("speculative_presses", 0)
        lines.append(f"scoring overlapped with the arm's moves: {'on' if summary['overlap_scoring'] else 'off'}"
                     f" (cell.overlap_scoring; {spec} speculative press{'es' if spec != 1 else ''})")
    return "\n".join(lines)


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("--workdir", default="vs2t-demo", help="work folder (default ./vs2t-demo); stages are cached there, and the daemon's "
                             "cell.yaml, journal and labels are left there")
    parser.add_argument("--items", type=int, default=30, help="pieces in the stream (default 30)")
    parser.add_argument("--profile", default="demo",
                        help="fabric world (sim/synth.py PROFILES; default demo: 24 fabrics of 6 kinds, 7 x 7 presses); "
                             "training uses the small profile for the demo world and the world's own otherwise")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--arm", choices=("ursim", "fake"), default="ursim",
                        help="ursim: real ur_rtde client against the loopback simulator (default)")
    parser.add_argument("--gate", choices=("pty", "fake"), default="pty",
                        help="pty: gate host driver against the MCU simulator (default)")
    parser.add_argument("--max-presses", type=int, default=5)
    parser.add_argument("--extra-presses", type=int, default=None,
                        help="evidence.extra_presses: presses past --max-presses for a piece a touched fabric leads, "
                             "not yet confident and refused by no off-scene rule (default: the bundle's, chosen "
                             "on validation; 0: off)")
    parser.add_argument("--confidence", type=float, default=None,
                        help="evidence.confidence: the posterior that sorts a piece of a touched fabric (default: "
                             "the bundle's operating point, chosen on validation fabrics for at most 1 %% mis-sorts; "
                             "with a scene model untouched fabrics keep the bundle's own confidence)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--fault-at", default=None, metavar="ITEM:PRESS",
                        help="inject a protective stop just before that press of that piece, both numbered as the "
                             "printout and the fault's words do: 3:2 is item-0003's second press (teach pieces, "
                             "named teach-NN, are not counted)")
    parser.add_argument("--record", default=None, metavar="NAME.replay",
                        help="also record the session into this replay folder (`vs2t-edge replay NAME.replay` "
                             "replays it)")
    parser.add_argument("--force", action="store_true", help="redo every stage")
    parser.add_argument("--without-scene-model", choices=("refuse", "allow"), default=None,
                        help="evidence.without_scene_model for a bundle without a scene model (decision.npz): "
                             "refused by default; allow sorts with the router's posterior, which has no "
                             "off-scene rule (off-scene pieces go to a scene fabric's bin)")
    parser.add_argument("--operator-labels", choices=("on", "off"), default="on",
                        help="evidence.operator_labels: a simulated operator labels every piece in the reject bin "
                             "with what it was, and the cell learns from it - an untouched fabric's real mean, an "
                             "off-scene fabric to refuse (runtime/feedback.py; outside the zero-shot protocol; "
                             "default on, as a line with a person at the reject bin would run; off: zero-shot only)")
    parser.add_argument("--teach", choices=("on", "off"), default="on",
                        help="with operator labels: start the job with one labelled teach piece of each untouched "
                             "fabric the job check (runtime/job_check.py) says the cell cannot sort at its synthesised "
                             "picture, as docs/cell.md advises (default on; not counted; off: labels only)")
    parser.add_argument("--overlap-scoring", choices=("on", "off"), default="on",
                        help="cell.overlap_scoring: score a press while the arm moves on (default on); off: "
                             "each press scored before the arm moves again, to compare pieces per minute")


def run(args) -> int:
    def log(msg: str) -> None:
        print(msg, flush=True)

    workdir = Path(args.workdir).resolve()
    if workdir.exists() and not workdir.is_dir():
        print(f"demo: --workdir {workdir} is a file, not a folder; give a new or an earlier demo's folder", file=sys.stderr)
        return 2
    from vs2t_edge.sim.synth import PROFILES

    if args.profile not in PROFILES:  # before any stage: synth raised it as a traceback
        print(f"demo: unknown --profile {args.profile!r}; choose one of {', '.join(sorted(PROFILES))}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    fault_at = None
    if args.fault_at:
        try:
            a, b = args.fault_at.split(":")
            fault_at = (int(a), int(b))
        except ValueError:
            print("demo: --fault-at wants ITEM:PRESS, e.g. 3:2", file=sys.stderr)
            return 2
        if not (1 <= fault_at[0] <= args.items and fault_at[1] >= 1):
            print(f"demo: --fault-at {args.fault_at}: ITEM is a piece of the stream as printed (item-0001 .. "
                  f"item-{args.items:04d}: 1 .. {args.items}) and PRESS counts from 1", file=sys.stderr)
            return 2
    try:
        dataset, bundle, times = prepare(workdir, profile=args.profile, seed=args.seed, force=args.force, log=log)
    except ModuleNotFoundError as exc:
        print(f"demo: a stage is not available in this build ({exc.name})", file=sys.stderr)
        return 4 if (exc.name or "").split(".")[0] in {"torch", "onnx"} else 2
    except RuntimeError as exc:
        print(f"demo: {exc}", file=sys.stderr)
        return 1
    try:
        summary = sort_stream(workdir, dataset, bundle, n_items=args.items, seed=args.seed, arm_kind=args.arm,
                              gate_kind=args.gate, max_presses=args.max_presses, confidence=args.confidence,
                              threads=args.threads, record=Path(args.record) if args.record else None,
                              fault_at=fault_at, log=log, overlap_scoring=args.overlap_scoring == "on",
                              without_scene_model=args.without_scene_model,
                              operator_labels=args.operator_labels == "on", teach=args.teach == "on",
                              extra_presses=args.extra_presses)
    except SceneModelMissing as exc:
        print(f"demo: {exc}", file=sys.stderr)
        return 2
    summary["stage_s"] = {k: round(v, 1) for k, v in times.items()}
    summary["total_s"] = time.monotonic() - t0
    log("")
    log(report_lines(summary))
    stages = ", ".join(f"{k.removesuffix('_s')} {v:.0f} s" for k, v in summary["stage_s"].items()) or "all stages cached"
    log(f"time: {stages}; sorting {summary['sort_s']:.0f} s; total {summary['total_s']:.0f} s")
    (workdir / "demo_summary.json").write_text(json.dumps(summary, indent=1, default=float))
    log(f"summary: {workdir / 'demo_summary.json'}; journal: {workdir / 'journal.jsonl'}; the cell config the daemon "
        f"ran: {workdir / 'cell.yaml'} (`vs2t-edge check-job`, `vs2t-edge label CONFIG --list` and "
        "`vs2t-edge validate-config` take it)")
    return 0

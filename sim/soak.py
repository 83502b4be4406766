"""Soak: the simulated cell sorting for a long bounded run, memory and latency tracked.

    python -m vs2t_edge.sim.soak --presses 5000 [--gate pty|fake] [--model onnx|grey] [--json docs/results/soak.json]

The cell is the fault matrix's rig (sim/fault_rig.py): the real loop, journal (fsynced), the gate
host driver against the MCU simulator on a pty (default), FakeArm and the simulated camera with
sensor noise. The model (``--model onnx``, the default) is the real inference path on the
committed bundle tests/replays/bundle (or ``--bundle``): TactileModel's preprocessing,
onnxruntime at 1 thread and router, the real Evidence rule, fed the real 64 x 48 frames the
reference replays recorded (per piece its no-contact reference and its press frames in turn);
``--model grey`` is the fault matrix's grey-level fake (loop, journal and gate only). Every
``--sample`` presses it records the process RSS (/proc/self/statm), the press cycle times and
the model's scoring times since the last sample. It reports, over the run after a 10 % warm-up,
the least-squares slope of RSS, of the median press cycle and of the median scoring time per
1000 presses, and the first and last 10 % levels. Verdicts: RSS "no growth" when the slope is
under ``--rss-limit-mib`` per 1000 presses; latency and scoring "no drift" when the last 10 %
median is within 20 % of the first 10 %. With the real model a sorted piece may be in the wrong
bin (a tiny test model): the journal audit checks the loop's promises (one final per piece,
nothing lost, faults to reject) and the bins right are counted, not required.

What is measured is the daemon's own state (loop, journal, notifier, gate host driver). The
test doubles' logs that a real cell does not have - FakeArm.calls, FakeGate.sorted, the MCU
simulator's frame and move lists (the real MCU is another machine) - are trimmed to their last
``KEEP_LOG`` entries at every sample, and the soak's own press stamps are kept per sample window,
so they do not show up as growth.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        resident_pages = int(f.read().split()[1])
    return resident_pages * os.sysconf("SC_PAGE_SIZE") / 2**20


KEEP_LOG = 100
_DOUBLE_LOGS = ("calls", "sorted", "rx_frames", "executed")


def _trim_test_doubles(*objs) -> None:
    """Cut the test doubles' every-call logs to their last KEEP_LOG entries (see the docstring)."""
    seen: set[int] = set()
    todo = [o for o in objs if o is not None]
    while todo:
        o = todo.pop()
        if id(o) in seen:
            continue
        seen.add(id(o))
        for name in _DOUBLE_LOGS:
            lst = getattr(o, name, None)
            if isinstance(lst, list) and len(lst) > KEEP_LOG:
                del lst[:-KEEP_LOG]
        for child in ("simulator", "firmware", "inner", "fw"):
            c = getattr(o, child, None)
            if c is not None and not isinstance(c, (int, float, str, bytes)):
                todo.append(c)


def slope_per_k(x: list[float], y: list[float]) -> float:
    if len(x) < 2:
        return 0.0
    a = np.polyfit(np.asarray(x, float), np.asarray(y, float), 1)[0]
    return float(a * 1000.0)


def drift_verdict(first: float, last: float) -> str:
    """"no drift" when ``last`` is within 20 % of ``first``."""
    drift = last / max(first, 1e-9) - 1.0
    return "no drift" if abs(drift) < 0.2 else f"DRIFT ({drift:+.0%})"


REPLAYS = ("touched", "untouched", "unknown", "fault")


def default_bundle() -> Path:
    return Path(__file__).resolve().parents[1] / "tests" / "replays" / "bundle"


def onnx_path(bundle: Path, max_presses: int = 3, confidence: float = 0.95):
    """The real inference path for the rig: the bundle's TactileModel (preprocess, onnxruntime at
    1 thread, router), the real Evidence rule over the reference replays' scene, and the real
    frames those replays recorded (64 x 48 px; per piece its no-contact reference and its press
    frames in turn, the camera adds its sensor noise). Returns build_rig keywords and the
    recorded truths to cycle through."""
    from vs2t_edge.runtime.evidence import Evidence
    from vs2t_edge.runtime.inference import TactileModel
    from vs2t_edge.runtime.replay import ReplayFile

    replays = bundle.parent if (bundle.parent / "touched.replay").is_dir() else default_bundle().parent
    recorded: list[tuple[str, np.ndarray, list[np.ndarray]]] = []  # (truth, reference, presses)
    scene_fabrics = None
    for name in REPLAYS:
        rf = ReplayFile.open(replays / f"{name}.replay")
        scene_fabrics = scene_fabrics or rf.index["config"]["scene"]["fabrics"]
        for i, ref, pressed in rf.frames_by_item():  # paired by item index: a piece without a grab is skipped
            if pressed:
                recorded.append((rf.index["items"][i]["truth"], ref, pressed))
    model = TactileModel.load(bundle, threads=1)
    bins = {f["name"]: int(f["bin"]) for f in scene_fabrics}
    classes = list(bins)

    def frames(arm, pieces):
        state = {"piece": -1, "k": 0, "was_pressed": False}

        def frame() -> np.ndarray:
            i = pieces.index
            _, ref, pressed = recorded[i % len(recorded)]
            if i != state["piece"]:
                state.update(piece=i, k=0, was_pressed=False)
            if not arm.pressed:
                state["was_pressed"] = False
                return ref
            if not state["was_pressed"]:  # a new press: the next recorded press frame
                state["was_pressed"] = True
                state["k"] += 1
            return pressed[(state["k"] - 1) % len(pressed)]
        return frame

    rig_kw = {"model": model, "bins": bins, "frames": frames, "max_presses": max_presses,
              "evidence_factory": lambda: Evidence(classes, confidence, max_presses)}
    return rig_kw, [t for t, _, _ in recorded]


def _shown(path: Path) -> str:
    root = Path(__file__).resolve().parents[1]
    try:
        return str(Path(path).resolve().relative_to(root))
    except ValueError:
        return str(path)


def soak(presses: int, *, gate_kind: str = "pty", sample: int = 100, workdir: Path | None = None,
         rss_limit_mib: float = 0.5, progress: bool = True, model: str = "onnx",
         bundle: Path | None = None) -> dict:
    """``model``: "onnx" (default) runs the real inference path on ``bundle`` (default: the
    committed tests/replays/bundle) with the reference replays' frames; "grey" the fault
    matrix's grey-level fake model (the loop, journal and gate only)."""
    from vs2t_edge.sim.fault_rig import TRUTHS, build_rig

    own = workdir is None
    workdir = Path(tempfile.mkdtemp(prefix="soak-")) if own else workdir
    gate = None
    if gate_kind == "pty":
        from vs2t_edge.sim.devices import simulated_serial_gate

        gate = simulated_serial_gate(timeout_s=0.5)
    if model == "onnx":
        bundle = Path(bundle) if bundle is not None else default_bundle()
        rig_kw, cycle = onnx_path(bundle)
    elif model == "grey":
        rig_kw, cycle = {}, TRUTHS
    else:
        raise ValueError(f"soak: model {model!r}, expected 'onnx' or 'grey'")
    truths = [cycle[i % len(cycle)] for i in range(presses)]  # at least one press per piece
    rig = build_rig(workdir, truths, gate=gate, **rig_kw)
    inner_press = rig.arm.inner.press
    stamps: list[float] = []  # press start times of the current sample window only
    n_pressed = 0

    def timed_press():
        nonlocal n_pressed
        stamps.append(time.perf_counter())
        n_pressed += 1
        return inner_press()

    rig.arm.inner.press = timed_press
    score_ms: list[float] = []  # model.score_press wall time of the current sample window only
    real_score = rig.cell.model.score_press

    def timed_score(frame):
        t = time.perf_counter()
        try:
            return real_score(frame)
        finally:
            score_ms.append((time.perf_counter() - t) * 1000.0)

    rig.cell.model.score_press = timed_score
    samples: list[dict] = []
    last_n = 0
    t0 = time.monotonic()

    def tick() -> bool:
        nonlocal last_n
        n = n_pressed
        if n - last_n >= sample:
            cycles = np.diff(np.asarray(stamps, float)) * 1000.0
            del stamps[:-1]  # the window's last press starts the next window's first cycle
            _trim_test_doubles(rig.arm, rig.gate, rig.camera)
            samples.append({"presses": n, "rss_mib": rss_mib(), "press_ms_median": float(np.median(cycles)),
                            "press_ms_p95": float(np.percentile(cycles, 95)), "t_s": time.monotonic() - t0,
                            "score_ms_median": float(np.median(score_ms)) if score_ms else 0.0,
                            "notifier_messages": len(rig.cell.notifier.sent)})
            score_ms.clear()
            last_n = n
            if progress:
                s = samples[-1]
                print(f"\rsoak: {n}/{presses} presses, RSS {s['rss_mib']:.1f} MiB, press cycle "
                      f"{s['press_ms_median']:.2f} ms, scoring {s['score_ms_median']:.2f} ms", end="",
                      file=sys.stderr, flush=True)
        return n >= presses

    try:
        rig.cell.run(stop_when=tick)
    finally:
        rig.cell.shutdown("soak done")
        for dev in (rig.camera, rig.arm, rig.gate):
            try:
                dev.disconnect()
            except Exception:  # noqa: BLE001
                pass
    if progress:
        print(file=sys.stderr)
    seconds = time.monotonic() - t0
    from vs2t_edge.sim.fault_rig import audit

    # the grey model is exact, so every sorted piece must be in its own bin; the real model may be
    # wrong (a tiny test model): its bins are counted below, the audit checks the loop's promises
    truth_of = {it.id: it.truth for it in rig.pieces.items}
    a = audit(rig.journal_path, truth_of if model == "grey" else None)
    bins = rig.cell.scene.bins
    sorted_right = sum(f.get("outcome") == "sorted" and f["bin"] == bins.get(truth_of.get(f.get("item_id")), -1)
                       for f in a["finals"])
    to_reject = sum(f["bin"] == rig.cell.scene.reject_bin for f in a["finals"])
    journal_mib = rig.journal_path.stat().st_size / 2**20
    warm = samples[max(1, len(samples) // 10):]
    k = max(1, len(samples) // 10)
    first, last = samples[:k], samples[-k:]
    x = [s["presses"] for s in warm]
    res = {
        "command": f"python -m vs2t_edge.sim.soak --presses {presses} --gate {gate_kind} --model {model}",
        "presses": n_pressed, "items": len(a["finals"]), "seconds": seconds, "arm": "FakeArm",
        "model": (f"real inference path: bundle {_shown(bundle)} (TactileModel: preprocess, onnxruntime 1 thread, "
                  "router) + Evidence, the reference replays' frames" if model == "onnx"
                  else "grey-level fake model"),
        "score_ms_first": float(np.median([s["score_ms_median"] for s in first])),
        "score_ms_last": float(np.median([s["score_ms_median"] for s in last])),
        "score_ms_slope_per_kpress": slope_per_k(x, [s["score_ms_median"] for s in warm]),
        "sorted_to_truth_bin": int(sorted_right), "to_reject_bin": int(to_reject),
        "gate": "MCU simulator (pty)" if gate_kind == "pty" else "FakeGate",
        "rss_first_mib": float(np.mean([s["rss_mib"] for s in first])),
        "rss_last_mib": float(np.mean([s["rss_mib"] for s in last])),
        "rss_slope_mib_per_kpress": slope_per_k(x, [s["rss_mib"] for s in warm]),
        "press_ms_first": float(np.median([s["press_ms_median"] for s in first])),
        "press_ms_last": float(np.median([s["press_ms_median"] for s in last])),
        "press_ms_slope_per_kpress": slope_per_k(x, [s["press_ms_median"] for s in warm]),
        "journal_mib": journal_mib, "journal_records": len(a["records"]),
        "in_memory_journal_records": len(rig.cell.journal.records), "in_memory_results": len(rig.cell.results),
        "items_done": rig.cell.items_done, "notifier_messages_held": len(rig.cell.notifier.sent),
        "outcomes": dict(a["outcomes"]), "problems": a["problems"], "samples": samples,
    }
    res["rss_verdict"] = ("no growth" if res["rss_slope_mib_per_kpress"] < rss_limit_mib
                          else f"GROWS ({res['rss_slope_mib_per_kpress']:.2f} MiB / 1000 presses)")
    res["latency_verdict"] = drift_verdict(res["press_ms_first"], res["press_ms_last"])
    res["score_verdict"] = drift_verdict(res["score_ms_first"], res["score_ms_last"])
    res["journal_verdict"] = (f"{1024 * journal_mib / max(res['items'], 1):.2f} KiB per piece, "
                              + ("one final per piece" if not a["problems"] else "; ".join(a["problems"])))
    if own:
        import shutil

        shutil.rmtree(workdir, ignore_errors=True)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vs2t_edge.sim.soak", description=__doc__.split("\n\n")[0])
    ap.add_argument("--presses", type=int, default=5000)
    ap.add_argument("--gate", choices=["pty", "fake"], default="pty")
    ap.add_argument("--sample", type=int, default=100, help="presses per sample")
    ap.add_argument("--rss-limit-mib", type=float, default=0.5, help="largest acceptable RSS slope per 1000 presses")
    ap.add_argument("--json", type=Path, default=None, help="write the result (with every sample) here")
    ap.add_argument("--model", choices=["onnx", "grey"], default="onnx",
                    help="onnx: the real inference path on --bundle (default); grey: the fake grey-level model")
    ap.add_argument("--bundle", type=Path, default=None, help="bundle for --model onnx (default: tests/replays/bundle)")
    a = ap.parse_args(argv)
    if a.presses < 10 * a.sample:
        print(f"--presses must be at least 10 x --sample ({10 * a.sample})", file=sys.stderr)
        return 2
    res = soak(a.presses, gate_kind=a.gate, sample=a.sample, rss_limit_mib=a.rss_limit_mib, model=a.model,
               bundle=a.bundle)
    print(f"{res['presses']} presses, {res['items']} pieces, {res['seconds']:.0f} s; {res['model']}")
    print(f"scoring (model.score_press) median {res['score_ms_first']:.2f} -> {res['score_ms_last']:.2f} ms, slope "
          f"{res['score_ms_slope_per_kpress']:+.3f} ms/1000 presses; {res['sorted_to_truth_bin']} pieces in their "
          f"fabric's bin, {res['to_reject_bin']} to reject")
    print(f"RSS {res['rss_first_mib']:.1f} -> {res['rss_last_mib']:.1f} MiB, slope "
          f"{res['rss_slope_mib_per_kpress']:+.3f} MiB/1000 presses: {res['rss_verdict']}")
    print(f"press cycle median {res['press_ms_first']:.2f} -> {res['press_ms_last']:.2f} ms, slope "
          f"{res['press_ms_slope_per_kpress']:+.3f} ms/1000 presses: {res['latency_verdict']}")
    print(f"journal {res['journal_mib']:.2f} MiB ({res['journal_records']} records; {res['in_memory_journal_records']} "
          f"held in memory, {res['in_memory_results']} results); {res['journal_verdict']}")
    print(f"notifier messages held in memory: {res['notifier_messages_held']}")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(res, indent=1))
    ok = (not res["problems"] and res["rss_verdict"] == "no growth" and res["latency_verdict"] == "no drift"
          and res["score_verdict"] == "no drift")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""The measured speed-for-accuracy trade of bundles (`vs2t-edge bench`, docs/results/bench/).

Per bundle (a variant: trunk, input size, fp32/int8):

- speed, in a fresh subprocess per bundle so peak memory is the bundle's own, with 1 and 2
  onnxruntime threads: the trunk alone at batch 1 (p50/p99 over timed runs on real preprocessed
  presses), and the whole press as the cell pays it, end to end (decode of the camera's MJPEG
  frame - the press frame encoded once as JPEG q=95, cv2.imdecode timed - preprocess, trunk,
  heads, router, decision, evidence update): p50/p99 of the press and of the press minus its own
  trunk run ("outside the trunk", decode included, what the < 2 ms target is judged on), stage
  medians; PNG decode (replays and the bench only) apart; peak RSS (VmHWM) next to a baseline
  process that imports the same modules and loads nothing;
- the compute limit: MACs per frame (counted from the graph at export, manifest
  ``graphs.trunk.macs_per_frame``) / this machine's measured GEMM peak (``measure_peak``), and
  the fraction of it the trunk reaches;
- accuracy, for trained bundles, on presses the model never trained on (the manifest records
  which presses trained it): per press ZSL accuracy and GZSL acc_t / acc_u / H at the bundle's
  beta (hard route, the paper's protocol); per item (random presses of one fabric) for 1, 3, 5, 9
  presses with the soft-gated posterior summed in log space, and the sequential rule
  (runtime.evidence, confidence 0.95, at most 9 presses): presses used, accuracy, unknown rate.
  The scene is every class of the bundle (the hardest scene the cell can be given). Per item, by
  bins (runtime/sorting.py, as the demo and training's report count): right bin / mis-sort /
  reject on scenes of 5 touched + 3 untouched bundle classes with off-scene pieces, for the
  bundle's scene decision and for the router's posterior at confidence 0.95 (the baseline).

The machine is recorded with its instruction sets (AVX2, AVX-512, VNNI, AMX: int8's gain
depends on them) and the onnxruntime build, and for every fp32/int8 pair the bench says which
precision it recommends on the machine it ran on (``recommend``; the verdict: bench/verdict.py).

No torch here (runtime/). ``onnx`` (train extra) is used only to build the GEMM graphs of the
peak measurement; without it the fp32 peak comes from numpy and the int8 peak is not measured.
matplotlib (train extra) draws the Pareto plot when importable.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

# the accuracy half lives in runtime/bench_accuracy.py; its names stay importable from here
from vs2t_edge.bench.press_timing import (  # noqa: F401 - press_stages & co. stay importable from here
    CAMERA_FORMATS, DECODE_SCALES, JPEG_QUALITY, OUTSIDE_STAGES, STAGES, CameraChecks, _time_runs, _time_split, camera_payload,
    decode_payload, decode_scale, press_stages, split_press_graph, stages_of)
from vs2t_edge.bench.verdict import (  # noqa: F401 - the verdict's names stay importable from here
    CELL_MEASURES, MIN_INT8_SPEEDUP, TARGET_CELL_MS, TARGET_CELL_P99_MS, TARGET_INT8_POINTS, TARGET_OF_LIMIT,
    compare_pairs, cost_points, over_runs, recommend, targets)
from vs2t_edge.bench.accuracy import (  # noqa: F401
    BIN_MAX_PRESSES, BIN_SCENES, ITEM_PRESSES, SEQ_CONFIDENCE, SEQ_MAX_PRESSES, YUYV, _dataset_of, _spread, accuracy,
    accuracy_frames, by_bins, eval_presses, pieces_per_minute, press_outputs)


def _log(msg: str) -> None:
    print(f"bench: {msg}", file=sys.stderr, flush=True)


def _pct(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, np.float64), q)) if len(values) else math.nan


# ------------------------------------------------------------------ compute peak


def _gemm_graph(n: int, int8: bool) -> bytes:
    import onnx
    from onnx import TensorProto, helper

    if int8:
        a = helper.make_tensor_value_info("a", TensorProto.UINT8, [n, n])
        b = helper.make_tensor_value_info("b", TensorProto.INT8, [n, n])
        y = helper.make_tensor_value_info("y", TensorProto.INT32, [n, n])
        node = helper.make_node("MatMulInteger", ["a", "b"], ["y"])
    else:
        a = helper.make_tensor_value_info("a", TensorProto.FLOAT, [n, n])
        b = helper.make_tensor_value_info("b", TensorProto.FLOAT, [n, n])
        y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [n, n])
        node = helper.make_node("MatMul", ["a", "b"], ["y"])
    g = helper.make_graph([node], "gemm", [a, b], [y])
    return helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString()


def measure_peak(threads: int, precision: str, n: int = 1024, repeats: int = 15) -> dict:
    """GEMM throughput (MAC/s) of an n x n x n matrix product through onnxruntime's own kernels
    (MLAS; MatMul for fp32, MatMulInteger u8 x s8 for int8 - the VNNI path the QDQ convs use),
    ``threads`` intra-op threads; the fastest of ``repeats`` runs after 3 warm-ups, i.e. a
    practical peak, not the datasheet's."""
    try:
        import onnxruntime as ort

        model = _gemm_graph(n, precision == "int8")
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        sess = ort.InferenceSession(model, sess_options=so, providers=["CPUExecutionProvider"])
        rng = np.random.default_rng(0)
        if precision == "int8":
            feeds = {"a": rng.integers(0, 255, (n, n), dtype=np.uint8), "b": rng.integers(-127, 127, (n, n), dtype=np.int8)}
        else:
            feeds = {"a": rng.standard_normal((n, n), dtype=np.float32), "b": rng.standard_normal((n, n), dtype=np.float32)}
        run = lambda: sess.run(None, feeds)  # noqa: E731
        how = f"onnxruntime {'MatMulInteger u8xs8' if precision == 'int8' else 'MatMul fp32'} {n}^3, {threads} thread(s)"
    except ImportError:
        if precision == "int8":
            return {"macs_per_s": math.nan, "how": "not measured (needs the onnx package to build the GEMM graph)"}
        a = np.random.default_rng(0).standard_normal((n, n), dtype=np.float32)
        run = lambda: a @ a  # noqa: E731
        how = f"numpy matmul fp32 {n}^3 (its BLAS's own thread count)"
    for _ in range(3):
        run()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - t0)
    return {"macs_per_s": n ** 3 / best, "how": how}


# ------------------------------------------------------------------ speed (worker process)


def _vm_hwm_mb() -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _import_runtime() -> None:
    import cv2  # noqa: F401
    import onnxruntime  # noqa: F401

    from vs2t_edge.runtime import evidence, inference  # noqa: F401


def cell_evidence(model) -> tuple[Callable[[], Any], int]:
    """(a new item's evidence, presses per item) as the cell builds them: for a bundle with a scene
    model, its item rule and operating point over a job of 5 touched and 3 untouched fabrics with
    the bench's frames' fabric among them (runtime/sorting.py ``scene_evidence``) at the bins'
    press limit; without one, the router's posterior at the sequential rule's confidence over every
    class."""
    from vs2t_edge.runtime import sorting as so
    from vs2t_edge.runtime.evidence import Evidence

    if getattr(model, "scene_model", None) is None:
        return (lambda: Evidence(model.classes, SEQ_CONFIDENCE, SEQ_MAX_PRESSES)), SEQ_MAX_PRESSES
    scene = so.Scene(tuple(model.touched[:5]), tuple(model.untouched[:3]), ())
    make = so.scene_evidence(model.scene_model, BIN_MAX_PRESSES)
    return (lambda: make(scene)), BIN_MAX_PRESSES


def speed_worker(bundle: str, dataset: str | None, threads_list: Sequence[int], budget_s: float,
                 n_frames: int = 16, jpeg_quality: int = JPEG_QUALITY, camera_format: str = "mjpeg",
                 camera_decode: str = "auto") -> dict:
    """Runs in its own process (see module doc). Returns latencies, overheads and peak RSS.

    Per thread count: the trunk alone (``latency``) and the whole press (``press``: MJPEG decode +
    the camera's frame checks + preprocess + trunk + heads + router + decision + evidence, timed
    end to end per press; its ``outside`` = that press minus its own trunk run), each as p50/p99
    over the timed presses. For a fused bundle (one graph per press) ``latency`` is the trunk cut
    out of the graph, and the tail's share of the press's one call (``in_graph_ms``) is counted in
    ``outside``.
    ``overhead_ms`` / ``overhead_p99_ms`` are the stage medians / p99 at the largest thread count;
    PNG decode (what replays and the bench pay, not the camera) is timed apart. ``camera_format``
    yuyv: the camera streams uncompressed YUYV (runtime/yuyv.py) instead of MJPEG at ``jpeg_quality``;
    ``camera_decode``: the cell's ``devices.camera.decode_scale`` (auto or full)."""
    import cv2

    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.inference import TactileModel

    _import_runtime()
    out: dict[str, Any] = {"latency": {}, "press": {}, "overhead_ms": {}, "jpeg_quality": jpeg_quality,
                           "camera_format": camera_format}
    all_stages = stages_of(camera_format)
    outside_stages = tuple(k for k in all_stages if k != "trunk")
    raw_png: list[bytes] = []
    jpegs: list[bytes] = []
    ref = None
    model = None
    stages: dict[str, list[float]] = {}
    frames: list[np.ndarray] = []
    runs: dict[int, tuple] = {}
    per_press: dict[int, tuple] = {}
    for t in sorted(threads_list):  # ascending: the stages left at the end are the largest count's
        model = TactileModel.load(bundle, threads=t)
        if ref is None:
            ds_root = _dataset_of(model.manifest, dataset)
            if ds_root is None:
                raise FileNotFoundError(f"{bundle}: its dataset is not here; pass --dataset")
            ds = load_dataset(ds_root)
            fab = ds.by_id(model.touched[0])
            ref = fab.load_reference()
            for i in _spread(list(range(len(fab.presses))), n_frames):
                raw_png.append(fab.presses[i].path.read_bytes())
            for b in raw_png:  # encoded once: the camera's work, not the cell's
                jpegs.append(camera_payload(cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR),
                                            camera_format, jpeg_quality))
            # as the cell's camera hands them: decoded at the bundle's scale, the reference too
            scale, sensor_hw = decode_scale(model, ref.shape[:2], camera_decode, camera_format), list(ref.shape[:2])
            frames = [decode_payload(b, scale) for b in jpegs]
            ref = decode_payload(camera_payload(ref, camera_format, jpeg_quality), scale)
        model.set_reference(ref, scale)
        checks = CameraChecks(ref, model)
        xs = [model.preprocess(f, scale) for f in frames]
        sess, name = model._trunk, model._trunk_in  # a fused bundle's: the whole press graph (see below)
        t0 = time.perf_counter()
        sess.run(None, {name: xs[0]})
        est = time.perf_counter() - t0
        n = int(min(400, max(30, budget_s / max(est, 1e-4))))
        times = _time_runs(sess, name, xs, n)
        out["latency"][str(t)] = {"p50_ms": _pct(times, 50), "p99_ms": _pct(times, 99), "runs": n}
        runs[t] = (xs, n)
        # the whole press, as the cell runs it with t threads
        stages = {k: [] for k in (*all_stages, "press")}
        png: list[float] = []
        new_item, item_presses = cell_evidence(model)
        ev = new_item()
        for k in range(3):
            press_stages(model, jpegs[k % len(jpegs)], ev, checks, scale)
        n_press = int(min(400, max(60, 4 * len(jpegs), budget_s / max(est + 1e-3, 1e-4))))
        for k in range(n_press):
            if k % item_presses == 0:  # a new item at the press limit, as the cell's evidence would
                ev = new_item()
            for key, v in press_stages(model, jpegs[k % len(jpegs)], ev, checks, scale).items():
                stages[key].append(v)
            t0 = time.perf_counter()  # beside each press (same process state), not in its total
            cv2.imdecode(np.frombuffer(raw_png[k % len(raw_png)], np.uint8), cv2.IMREAD_COLOR)
            png.append(1e3 * (time.perf_counter() - t0))
        press = np.asarray(stages["press"])
        per_press[t] = (press, np.asarray(stages["trunk"]))
        out["press"][str(t)] = {"p50_ms": _pct(press, 50), "p99_ms": _pct(press, 99), "runs": n_press,
                                "stages_p50_ms": {k: _pct(v, 50) for k, v in stages.items()}}
    out["peak_rss_mb"] = _vm_hwm_mb()  # before the trunk-only sessions below, which the cell never opens
    # A fused bundle's one call holds the trunk AND its tail (heads, projections): "trunk" is made to
    # mean the trunk alone in both formats (cut out of the graph) and the tail (cut out too, timed
    # right after each trunk run) is counted outside it.
    in_graph = {t: 0.0 for t in threads_list}
    if model.fused:
        for t in sorted(threads_list):
            xs, n = runs[t]
            lat = out["latency"][str(t)]
            lat.update(press_graph_p50_ms=lat["p50_ms"], press_graph_p99_ms=lat["p99_ms"])
            cut = split_press_graph(model, t)
            if cut is None:  # no onnx to cut the trunk out: the tail stays inside "trunk", said so
                lat.update(includes_tail=True)
                continue
            alone, tail = _time_split(*cut, model._trunk_in, xs, n)
            in_graph[t] = _pct(tail, 50)
            lat.update(p50_ms=_pct(alone, 50), p99_ms=_pct(alone, 99), in_graph_ms=in_graph[t],
                       in_graph_p99_ms=_pct(tail, 99))
            del cut
    for t, (press, trunk) in per_press.items():
        outside = press - trunk + in_graph[t]  # fused: minus the one call, plus its tail's share
        out["press"][str(t)].update(outside_p50_ms=_pct(outside, 50), outside_p99_ms=_pct(outside, 99))
    tmax = str(max(threads_list))
    out["overhead_ms"] = {k: _pct(stages[k], 50) for k in outside_stages}
    out["overhead_ms"]["heads" if model.fused else "in_graph"] = math.nan  # the stage the format does not have
    if model.fused:
        out["overhead_ms"]["in_graph"] = in_graph[max(threads_list)]
    out["fused"] = bool(model.fused)
    out["split"] = bool(getattr(model, "split", False))  # format 3: no heads, no router on the press path
    out["overhead_ms"]["decode_png"] = _pct(png, 50)
    # what the target is judged on: everything per press outside the trunk, decode included (the
    # median of (press - its trunk), measured end to end, not a sum of stage medians)
    out["overhead_ms"]["cell"] = out["press"][tmax]["outside_p50_ms"]
    out["overhead_p99_ms"] = {k: _pct(stages[k], 99) for k in outside_stages}
    out["overhead_p99_ms"]["decode_png"] = _pct(png, 99)
    out["overhead_p99_ms"]["cell"] = out["press"][tmax]["outside_p99_ms"]
    out["frame_hw"] = sensor_hw  # the camera's frames; decoded at 1/decode_scale
    out["decode_scale"] = scale
    return out


def baseline_worker() -> dict:
    _import_runtime()
    return {"peak_rss_mb": _vm_hwm_mb()}


def _run_worker(args: list[str], timeout_s: float = 900) -> dict:
    cmd = [sys.executable, "-m", "vs2t_edge.bench.measure", *args]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env)
    if res.returncode != 0:
        raise RuntimeError(f"bench worker failed ({' '.join(args[:2])}): {res.stderr.strip()[-800:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])



# ------------------------------------------------------------------ the bench


def describe(bundle: Path) -> dict:
    from vs2t_edge.runtime.bundle import read_manifest

    m = read_manifest(bundle)
    tr = m["graphs"]["trunk"]
    size_b = sum((bundle / f).stat().st_size for f in m["files"])
    return {"bundle": str(bundle), "name": bundle.name, "arch": tr.get("arch", "?"), "precision": tr.get("precision", "?"),
            "size_px": int(m["preprocess"]["size"]), "trained": bool(m.get("provenance", {}).get("trained", True)),
            "macs": int(tr.get("macs_per_frame", {}).get("total", 0)) or None,
            "bundle_mb": size_b / 1e6, "trunk_mb": (bundle / tr["file"]).stat().st_size / 1e6,
            "classes": [len(m["classes"]["touched"]), len(m["classes"]["untouched"])],
            "run": m.get("provenance", {}).get("run"), "made_by": _made_by(m)}


def frames_said(rows: list[dict], jpeg_quality: int, through_jpeg: bool) -> str:
    """Which frames the accuracies read, for the report: one phrase when every scored variant read
    the same kind, else each variant's (a bundle trained through the camera's JPEG reads its own)."""
    said = {r["name"]: r["accuracy_frames"] for r in rows if "accuracy_frames" in r}
    if through_jpeg:
        scales = sorted({r["decode_scale_accuracy"] for r in rows if "decode_scale_accuracy" in r})
        at = (" (" + " or ".join(f"1/{n}" for n in scales) + ")") if scales else ""
        return f"through JPEG q={jpeg_quality}, decoded at the scale the cell's camera decodes each bundle's{at}"
    if len(set(said.values())) <= 1:
        return next(iter(said.values()), "lossless (the dataset's PNG)")
    return "per variant - " + "; ".join(f"{name}: {what}" for name, what in said.items())


def _made_by(manifest: dict) -> dict:
    """What the bundle says produced it, so the bench page can say how to make it again."""
    prov = manifest.get("provenance", {}) if isinstance(manifest.get("provenance"), dict) else {}
    data = prov.get("data", {}) if isinstance(prov.get("data"), dict) else {}
    out = {"command": prov.get("command"), "git_commit": prov.get("git_commit"), "time_utc": prov.get("time_utc"),
           "run": prov.get("run"), "dataset": data.get("dataset"), "split_seed": data.get("split_seed"),
           "router": (manifest.get("router") or {}).get("name"), "operating_point": manifest.get("operating_point")}
    return {k: v for k, v in out.items() if v is not None}


def run_bench(bundles: Sequence[Path], out_dir: Path | None, *, dataset: str | None = None,
              threads: Sequence[int] = (1, 2), budget_s: float = 4.0, n_items: int = 100, cap: int = 0,
              accuracy_on: bool = True, arm=None, jpeg_quality: int = JPEG_QUALITY, accuracy_through_jpeg: bool = False,
              accuracy_lossless: bool = False, pairs: Sequence[tuple[str, str]] = (),
              camera_format: str = "mjpeg", accuracy_through_yuyv: bool = False, camera_decode: str = "auto",
              log: Callable[[str], None] = _log) -> dict:
    """The bench (module doc). ``arm``: runtime.sorting.ArmTimes, for pieces per minute.
    ``jpeg_quality``: what the camera's MJPEG frames are encoded at (timing); with
    ``accuracy_through_jpeg`` the held-out presses are scored through that JPEG too, decoded at the
    bundle's scale as the camera hands them; else a bundle trained through the camera's JPEG (manifest
    ``camera_jpeg``) is scored through its own, the others on the dataset's lossless frames
    (``accuracy_lossless``: every bundle on the lossless frames). ``pairs``: (A, B) variant names
    whose difference B - A is paired on the same presses and items (bench/paired.py), as every
    int8 bundle is with its fp32 twin. ``camera_format`` yuyv: the press is timed on uncompressed
    YUYV frames (runtime/yuyv.py) instead of MJPEG; ``accuracy_through_yuyv`` scores through them.
    ``camera_decode``: the cell's ``devices.camera.decode_scale`` - the scale the camera's frames are
    decoded at, for the timing and for accuracy through the camera's JPEG or YUYV (auto: a
    float-path bundle's frames at 1/2 of 640x480, runtime/wiring.py ``model_decode_scale``)."""
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.inference import TactileModel

    t_start = time.time()
    machine = _machine()  # the load average before the bench's own work raises it
    log("measuring this machine's GEMM peak (1 and 2 threads, fp32 and int8)")
    peak = {p: {str(t): measure_peak(t, p) for t in threads} for p in ("fp32", "int8")}
    base = _run_worker(["--baseline"])
    from vs2t_edge.bench.paired import paired, view as paired_view

    rows, views = [], {}
    for i, b in enumerate(bundles):
        b = Path(b)
        row = describe(b)
        log(f"[{i + 1}/{len(bundles)}] {b.name}: speed ({row['arch']} {row['precision']} {row['size_px']} px)")
        args = ["--worker", str(b), "--threads", ",".join(map(str, threads)), "--budget", str(budget_s),
                "--jpeg-quality", str(jpeg_quality), "--camera-format", camera_format, "--camera-decode", camera_decode]
        if dataset:
            args += ["--dataset", dataset]
        row.update(_run_worker(args))
        row["rss_over_baseline_mb"] = row["peak_rss_mb"] - base["peak_rss_mb"]
        if row["macs"]:
            row["limit_ms"], row["fraction_of_peak"] = {}, {}
            for t in map(str, threads):
                pk = peak[row["precision"]][t]["macs_per_s"]
                if pk and math.isfinite(pk):
                    row["limit_ms"][t] = 1e3 * row["macs"] / pk
                    row["fraction_of_peak"][t] = row["limit_ms"][t] / row["latency"][t]["p50_ms"]
        if accuracy_on and row["trained"]:
            model = TactileModel.load(b, threads=max(threads))
            ds_root = _dataset_of(model.manifest, dataset)
            if ds_root is not None and "data" in model.manifest.get("provenance", {}):
                quality, row["accuracy_frames"] = accuracy_frames(model, jpeg_quality, accuracy_through_jpeg,
                                                                  accuracy_lossless, accuracy_through_yuyv)
                log(f"[{i + 1}/{len(bundles)}] {b.name}: accuracy on held-out presses, frames {row['accuracy_frames']}")
                ds = load_dataset(ds_root)
                row["decode_scale_accuracy"] = 1  # lossless frames: the dataset's, whole
                if quality:  # as the cell's camera hands them, at the frame size of the dataset's geometry
                    row["decode_scale_accuracy"] = decode_scale(model, ds.geometry.frame_hw, camera_decode,
                                                                "yuyv" if quality == YUYV else "mjpeg")
                    row["accuracy_frames"] += f" (1/{row['decode_scale_accuracy']})"
                outs = press_outputs(model, ds, eval_presses(model.manifest, ds, cap), jpeg_quality=quality,
                                     scale=row["decode_scale_accuracy"])
                row["accuracy"] = accuracy(model, outs, n_items=n_items)
                views[row["name"]] = paired_view(model, outs)  # for the paired int8-fp32 comparison
                if arm is not None:
                    pieces_per_minute(row, arm)
            del model
        rows.append(row)
    machine["load_avg_at_end"] = list(os.getloadavg())  # includes the bench itself
    result = {"machine": machine, "peak": peak, "baseline_rss_mb": base["peak_rss_mb"], "variants": rows,
              "seconds": round(time.time() - t_start, 1), "arm_times": asdict(arm) if arm is not None else None,
              "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "jpeg_quality": jpeg_quality,
              "camera_format": camera_format, "camera_decode": camera_decode,
              "accuracy_frames": frames_said(rows, jpeg_quality, accuracy_through_jpeg)}
    result["pairs"] = [{"a": a, "b": b, "paired": paired(views[a], views[b], n_items=n_items)}
                       for a, b in pairs if a in views and b in views]
    for a, b in pairs:
        if a not in views or b not in views:
            log(f"--pair {a}:{b}: {'both were' if a not in views and b not in views else 'one was'} not scored "
                "(no accuracy); not paired")
    result["comparisons"] = compare_pairs(rows)
    for c in result["comparisons"]:  # the same presses and items: the difference with its noise
        if c["fp32"] in views and c["int8"] in views:
            c["paired"] = paired(views[c["fp32"]], views[c["int8"]], n_items=n_items)
    result["int8_over_runs"] = over_runs(result["comparisons"])
    result["targets"] = targets(result)
    result["recommendation"] = recommend(result)
    if out_dir is not None:
        from vs2t_edge.bench.report import hand_written_tail, plot_pareto, render_markdown

        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        from vs2t_edge.runtime.files import portable

        (out_dir / "bench.json").write_text(json.dumps(portable(result), indent=1, default=float) + "\n")
        md = out_dir / "bench.md"
        md.write_text(render_markdown(result) + hand_written_tail(md))
        try:
            plot_pareto(result, out_dir / "pareto.png")
        except ImportError:
            log("matplotlib not installed: no pareto.png (install the [train] extra)")
    return result


def _machine() -> dict:
    import platform

    import onnxruntime

    cpu = "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    build = onnxruntime.get_build_info() if hasattr(onnxruntime, "get_build_info") else ""
    return {"cpu": cpu, "cores": os.cpu_count(), "instruction_sets": cpu_features(), "onnxruntime": onnxruntime.__version__,
            "onnxruntime_build": build, "onnxruntime_providers": onnxruntime.get_available_providers(),
            "python": platform.python_version(), "load_avg_at_start": list(os.getloadavg())}


# int8's gain depends on the CPU: ~1.8x without VNNI, ~3.3x with it (issue 14, measured on two machines)
INSTRUCTION_SETS = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8")


def cpu_features(cpuinfo: str | None = None) -> dict[str, bool]:
    """Which of ``INSTRUCTION_SETS`` this CPU has (Linux /proc/cpuinfo flags; all False elsewhere)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        if line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
            break
    return {name: name in flags for name in INSTRUCTION_SETS}


def _main(argv: list[str]) -> int:
    import argparse

    p = argparse.ArgumentParser()
    p.add_argument("--worker")
    p.add_argument("--baseline", action="store_true")
    p.add_argument("--threads", default="1,2")
    p.add_argument("--budget", type=float, default=4.0)
    p.add_argument("--jpeg-quality", type=int, default=JPEG_QUALITY)
    p.add_argument("--camera-format", default="mjpeg", choices=CAMERA_FORMATS)
    p.add_argument("--camera-decode", default="auto", choices=DECODE_SCALES)
    p.add_argument("--dataset")
    a = p.parse_args(argv)
    if a.baseline:
        print(json.dumps(baseline_worker()))
    else:
        print(json.dumps(speed_worker(a.worker, a.dataset, [int(t) for t in a.threads.split(",")], a.budget,
                                      jpeg_quality=a.jpeg_quality, camera_format=a.camera_format,
                                      camera_decode=a.camera_decode)))
    return 0


if __name__ == "__main__":  # the speed worker process
    sys.exit(_main(sys.argv[1:]))

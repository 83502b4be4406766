"""`vs2t-edge export RUN --out BUNDLE`: a training run -> a verified ONNX bundle (docs/bundle.md).

The bundle is written to a temporary folder, loaded with the cell's own verification
(runtime.inference.TactileModel.load) and only then moved to --out.
``--random-trunk ARCH --dataset D`` makes a latency-only bundle of an untrained trunk instead
(used by the bench for ResNet50 when no trained run exists; its manifest says trained: false).
``--router NAME`` ships router NAME (runtime.novelty.ROUTERS) instead of the run's own pick, refitted
on the run's touched training presses with beta retuned on its validation fabrics (e.g.
``--router max_softmax``, the recommendation of docs/results/comparison_paper.md).

``--trunk-precision int8`` of a trained run uses ``INT8_RECIPE`` for every int8 option not given:
the recipe the bench prices against fp32 (docs/bundle.md, "int8"; docs/results/bench/).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

# What `--trunk-precision int8` of a trained run does for each int8 option left out. Measured on the
# paper world (bench, paired on the same presses, docs/bundle.md "int8"): minmax ranges on 64
# presses with fp32's beta lost 2.9 points of touched accuracy per press; this recipe lost at most
# 0.6 on every measure for a 2.1x faster trunk (2026-11-26, before the attribute task; what it loses
# now is in docs/results/bench/). The float nodes are chosen at export from held-out
# touched and validation presses, never from untouched fabrics. The scene model's real class means
# moved to the int8 trunk's (since 2026-11-30): without it, int8 put 4.9 points fewer of the
# attribute-task run's pieces in the right bin in the bench (touched pieces 10.8 points fewer;
# -2.4 +- 0.7 over five draws of its scenes); with it -0.2, at a per-press cost on untouched
# presses (docs/bundle.md "int8").
INT8_RECIPE = {"calibration_frames": 256, "int8_calibration": "percentile", "int8_float_auto": 4,
               "int8_keep_operating_point": True, "int8_scene_means": True}
FP32_CALIBRATION_FRAMES = 64


def add_arguments(parser, verb: str) -> None:
    from vs2t_edge.runtime.novelty import ROUTERS

    parser.add_argument("run", nargs="?", help="training run folder (RUN/artifacts/model.pt)")
    parser.add_argument("--out", required=True, help="bundle folder to write (replaced if it is a bundle)")
    parser.add_argument("--trunk-precision", choices=("fp32", "int8"), default="fp32",
                        help="int8 = static QDQ quantisation calibrated on touched presses (default fp32)")
    parser.add_argument("--size", type=int, default=None,
                        help="input side in px (default: the run's); other sizes trade accuracy for speed. Refused for a "
                             "run with a scene model (fitted at the trained size) unless --router drops it")
    parser.add_argument("--calibration-frames", type=int, default=None,
                        help="touched training presses for int8 ranges, parity and the probe, the same number "
                             f"from each touched fabric (default {FP32_CALIBRATION_FRAMES}, int8 "
                             f"{INT8_RECIPE['calibration_frames']}; 0: every training press)")
    parser.add_argument("--int8-calibration", choices=("minmax", "percentile", "entropy"), default=None,
                        help="how int8 activation ranges are set from the calibration presses (default "
                             f"{INT8_RECIPE['int8_calibration']})")
    parser.add_argument("--int8-percentile", type=float, default=None, metavar="P",
                        help="percentile of each activation kept by --int8-calibration percentile (default 99.999; "
                             "ranges asymmetric)")
    parser.add_argument("--float-convs", type=int, default=0,
                        help="keep the last N convolutions of the trunk in float when quantising (default 0)")
    parser.add_argument("--int8-float-nodes", default=None, metavar="NAMES",
                        help="trunk graph nodes to keep in float, comma-separated, or @FILE: the JSON "
                             "`vs2t-edge int8-sensitivity --out FILE` writes (its 'recommended' list)")
    parser.add_argument("--int8-keep-operating-point", action=argparse.BooleanOptionalAction, default=None,
                        help="move beta so the int8 graph keeps as many held-out touched presses touched as fp32 "
                             "does at the run's beta (int8 noise otherwise routes more presses to untouched; "
                             "default on)")
    parser.add_argument("--int8-scene-means", action=argparse.BooleanOptionalAction, default=None,
                        help="move the scene model's real class means (touched and known-only fabrics) by the int8 "
                             "trunk's shift of the training presses they were fitted on (part of the int8 shift is "
                             "the same on every press of a fabric; default on)")
    parser.add_argument("--int8-float-auto", type=int, default=None, metavar="K",
                        help="keep in float the K trunk nodes whose float copy buys back the most feature error "
                             "on held-out touched and validation presses (a sensitivity scan at export; default "
                             f"{INT8_RECIPE['int8_float_auto']})")
    parser.add_argument("--router", default=None, metavar="NAME",
                        help="GZSL router to ship, refitted on the run's touched training presses with beta tuned "
                             "balanced on its validation fabrics (default: the run's stored router and beta); one of "
                             + ", ".join(ROUTERS))
    parser.add_argument("--dataset", default=None, help="dataset folder (default: the run's)")
    parser.add_argument("--random-trunk", choices=("efficientnet_lite0", "resnet50", "tiny"), default=None,
                        help="latency-only bundle of an UNTRAINED trunk (needs --dataset and --size, no RUN)")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads for the checks (default 2)")
    parser.add_argument("--two-graphs", action="store_true",
                        help="write the format-1 bundle of earlier releases (trunk.onnx + heads.onnx, router and scene "
                             "projection in numpy) instead of one press graph (format 2; format 3 for a bundle with a "
                             "scene model, the default export since 2026-11-27); for comparisons")
    parser.add_argument("--heads-in-press-graph", action="store_true",
                        help="for a bundle with a scene model: keep the heads and the router in the press graph "
                             "(format 2, as exported before 2026-11-27) instead of heads.onnx beside it (format 3, "
                             "the cell's press graph ends at the scene projection); to price it (docs/bundle.md)")
    parser.add_argument("--heads-precision", choices=("fp32", "int8"), default="fp32",
                        help="CLS_t / CLS_u weights in the fused press graph: fp32 (default) or int8 (dynamic "
                             "quantisation, per channel; docs/bundle.md prices it)")
    parser.add_argument("--preprocess-reduce", choices=("off", "auto", "1", "2", "4", "8"), default="off",
                        help="with --random-trunk: the tactile pixel path (runtime/preprocess.py; a trained run's "
                             "bundle keeps the run's own, as `train --preprocess-reduce` chose it)")


def _reduce(choice: str, dataset, size: int) -> int:
    if choice == "off":
        return 0
    if choice != "auto":
        return int(choice)
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import auto_reduce

    return auto_reduce(load_dataset(dataset).geometry.frame_hw, size)


def parse_float_nodes(value: str | None) -> list[str]:
    """``a,b,c`` or ``@FILE`` (int8-sensitivity's JSON: its ``recommended`` list) -> node names."""
    if not value:
        return []
    if value.startswith("@"):
        import json

        path = Path(value[1:])
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path} is not JSON: {exc}") from None
        names = data.get("recommended") if isinstance(data, dict) else None
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ValueError(f"{path}: no 'recommended' list of node names (write it with `vs2t-edge int8-sensitivity`)")
        return names
    return [n.strip() for n in value.split(",") if n.strip()]


def run_options(args) -> dict:
    """The calibration and int8 options of a trained run's export: each one given on the command line
    as given, each one left out from ``INT8_RECIPE`` (int8) or the fp32 defaults (no int8 work)."""
    int8 = args.trunk_precision == "int8"
    fallback = INT8_RECIPE if int8 else {"calibration_frames": FP32_CALIBRATION_FRAMES, "int8_calibration": "minmax",
                                         "int8_float_auto": 0, "int8_keep_operating_point": False,
                                         "int8_scene_means": False}
    return {key: fallback[key] if getattr(args, key) is None else getattr(args, key) for key in INT8_RECIPE}


def run(args) -> int:
    from vs2t_edge.export.export import ExportError
    from vs2t_edge.export.from_run import export_random_trunk, export_run
    from vs2t_edge.runtime.bundle import BundleError
    from vs2t_edge.runtime.novelty import ROUTERS

    def log(msg: str) -> None:
        print(f"export: {msg}", file=sys.stderr, flush=True)

    if args.router is not None and args.router not in ROUTERS:
        print(f"export: unknown router '{args.router}'; known: {', '.join(ROUTERS)}", file=sys.stderr)
        return 2
    t0 = time.time()
    try:
        float_nodes = parse_float_nodes(args.int8_float_nodes)
    except (OSError, ValueError) as exc:
        print(f"export: --int8-float-nodes: {exc}", file=sys.stderr)
        return 2
    if ((float_nodes or args.int8_float_auto or args.int8_percentile is not None or args.int8_keep_operating_point
         or args.int8_scene_means or args.int8_calibration is not None) and args.trunk_precision != "int8"):
        print("export: --int8-float-nodes, --int8-float-auto, --int8-calibration, --int8-percentile, "
              "--int8-keep-operating-point and --int8-scene-means need --trunk-precision int8",
              file=sys.stderr)
        return 2
    if args.heads_precision == "int8" and args.two_graphs:
        print("export: --heads-precision int8 is for the fused press graph, not --two-graphs", file=sys.stderr)
        return 2
    if args.heads_in_press_graph and args.two_graphs:
        print("export: --heads-in-press-graph is for the fused press graph, not --two-graphs", file=sys.stderr)
        return 2
    try:
        if args.random_trunk:
            if args.run or not args.dataset or not args.size:
                print("export: --random-trunk needs --dataset and --size and no RUN", file=sys.stderr)
                return 2
            if args.router is not None:
                print("export: --router refits a trained run's router; a --random-trunk bundle has no run",
                      file=sys.stderr)
                return 2
            m = export_random_trunk(args.random_trunk, args.out, size=args.size, dataset=args.dataset,
                                    trunk_precision=args.trunk_precision,
                                    calibration_frames=min(FP32_CALIBRATION_FRAMES if args.calibration_frames is None
                                                           else args.calibration_frames, 32),
                                    log=log, threads=args.threads,
                                    fuse=not args.two_graphs, heads_precision=args.heads_precision,
                                    heads_in_press_graph=args.heads_in_press_graph, reduce=_reduce(args.preprocess_reduce, args.dataset, args.size))
        else:
            if args.preprocess_reduce != "off":
                print("export: --preprocess-reduce is for --random-trunk; a trained run's bundle takes the pixel "
                      "path it was trained on (train --preprocess-reduce)", file=sys.stderr)
                return 2
            if not args.run:
                print("export: give a training run folder (or --random-trunk)", file=sys.stderr)
                return 2
            if not (Path(args.run) / "artifacts" / "model.pt").is_file():
                print(f"export: {args.run} has no artifacts/model.pt (run `vs2t-edge train` first)", file=sys.stderr)
                return 2
            opt = run_options(args)
            m = export_run(args.run, args.out, trunk_precision=args.trunk_precision, size=args.size,
                           calibration_frames=opt["calibration_frames"], dataset=args.dataset, log=log,
                           calibration_method=opt["int8_calibration"], float_convs=args.float_convs,
                           router=args.router, threads=args.threads, fuse=not args.two_graphs,
                           float_nodes=float_nodes, float_auto=opt["int8_float_auto"], percentile=args.int8_percentile,
                           int8_keep_operating_point=opt["int8_keep_operating_point"],
                           int8_scene_means=opt["int8_scene_means"],
                           heads_precision=args.heads_precision, heads_in_press_graph=args.heads_in_press_graph)
    except (ExportError, FileNotFoundError, ValueError) as exc:
        print(f"export: {exc}", file=sys.stderr)
        return 2
    except BundleError as exc:  # the written bundle failed the runtime's own verification
        print(f"export: the exported bundle fails verification: {exc}", file=sys.stderr)
        return 1
    checks = m["checks"]
    par = checks["parity_torch_vs_onnxruntime"]
    feature = (f"the {m['trunk']['name']} descriptor (no trunk graph)" if "trunk" in m else
               f"{m['graphs']['trunk']['arch']} {m['graphs']['trunk']['precision']} at {m['preprocess']['size']} px")
    print(f"bundle {args.out}: {feature}, {len(m['classes']['touched'])} touched + "
          f"{len(m['classes']['untouched'])} untouched classes, verified ({time.time() - t0:.1f} s)")
    trunk_parity = f"feature {par['feature']:.1e}, " if "feature" in par else ""  # a descriptor has no graph
    print(f"  torch vs onnxruntime: {trunk_parity}logits_t {par['logits_t']:.1e} (tolerance {par['tolerance']:.0e})")
    if "int8_vs_fp32_on_calibration" in checks:
        q = checks["int8_vs_fp32_on_calibration"]
        print(f"  int8 vs fp32 on {q['frames']} touched presses: min feature cosine {q['feature_cosine_min']:.4f}, "
              f"CLS_t top-1 agreement {q['cls_t_top1_agreement']:.1%}")
        kept = m["graphs"]["trunk"].get("quantisation", {}).get("float_nodes_chosen") or []
        if kept:
            print(f"  kept in float: {', '.join(kept)}")
        if "int8_scene_means" in checks:
            sm = checks["int8_scene_means"]
            print(f"  scene model: {sm['classes']} real class means moved to the int8 trunk's ({sm['presses']} training "
                  f"presses; median {sm['shift_rms_per_dim_median']:.3f}, largest {sm['shift_rms_per_dim_max']:.3f} "
                  "rms a dimension)")
    print(f"  router {m['router']['name']} (tells touched from untouched presses), beta {m['beta']:.6g} "
          f"(its threshold, on the router's own scale): {m['operating_point']}")
    print(f"  gating temperature {m['gating']['temperature']:.4g} ({m['gating']['how']})")
    if "fused_vs_two_graphs" in checks:
        fc = checks["fused_vs_two_graphs"]
        worst = max((v for k, v in fc.items() if isinstance(v, float) and not k.endswith("tolerance")), default=0.0)
        heads = (f"; heads.onnx apart ({', '.join(m['graphs']['heads']['outputs'])}), off the press path"
                 if m["format_version"] == 3 else "")
        print(f"  one press graph (format {m['format_version']}): {', '.join(m['graphs']['trunk']['outputs'])}{heads}; "
              f"against the two-graph path "
              f"max rel. diff {worst:.1e}" + (f", router projection {fc['router_form']}" if "router_form" in fc else ""))
    return 0

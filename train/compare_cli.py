"""`vs2t-edge compare`: regenerate the whole comparison (Table 4 rows, modern generators, GZSL
routers with AUSUC, the real-sensor check) into docs/results/comparison.{md,json,png}.

Feature sources, first match wins: ``--features CACHE.npz`` (a FeatureTable cache, e.g. written
by a previous ``--data`` run with ``--cache``), ``--data DATASET`` (features extracted here with
a frozen ImageNet EfficientNet-Lite0), ``--toy`` (a synthetic feature world, for smoke runs).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

EXIT_OK, EXIT_USAGE = 0, 2


def add_arguments(parser: argparse.ArgumentParser, verb: str) -> None:
    src = parser.add_argument_group("features (one of)")
    src.add_argument("--features", type=Path, help="FeatureTable cache (.npz)")
    src.add_argument("--data", type=Path, help="dataset folder: extract frozen-trunk features here")
    src.add_argument("--toy", action="store_true", help="synthetic feature world (smoke run)")
    parser.add_argument("--cache", type=Path, help="with --data: write/read the extracted features here")
    parser.add_argument("--max-presses", type=int, default=None, help="with --data: presses per fabric")
    parser.add_argument("--splits", type=int, default=5, help="random fabric splits (paper: 5)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-val", type=int, default=None, help="validation fabrics per split (default 10%%)")
    parser.add_argument("--n-untouched", type=int, default=None, help="untouched fabrics per split (default 10%%)")
    parser.add_argument("--methods", default="all", help="comma list of method names, or 'all'")
    parser.add_argument("--steps", type=int, default=1500, help="optimiser steps per generative model")
    parser.add_argument("--hidden", type=int, default=1024)
    parser.add_argument("--cls-steps", type=int, default=600)
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (1: the machine is shared; 2 threads measured 6x slower under load)")
    parser.add_argument("--out", type=Path, default=Path("docs/results"), help="folder for comparison.*")
    parser.add_argument("--real", type=Path, default=None,
                        help="GelSight Mini materials folder (default ../shared/real/gelsight_mini_materials)")
    parser.add_argument("--skip-real", action="store_true", help="do not run the real-sensor check")
    parser.add_argument("--real-result", type=Path, default=None,
                        help="reuse a real-sensor check JSON written by `python -m vs2t_edge.train.realdata_check --out`")
    parser.add_argument("--real-splits", type=int, default=5)
    parser.add_argument("--real-epochs", type=int, default=8)


def run(args: argparse.Namespace) -> int:
    try:
        import torch
    except ModuleNotFoundError:
        print("vs2t-edge compare: needs the [train] extra (torch)", file=sys.stderr)
        return 4
    from vs2t_edge.train import compare as cmp
    from vs2t_edge.train.baselines import Budget
    from vs2t_edge.train.realdata_check import DEFAULT_ROOT, RealCheckConfig, run_check

    torch.set_num_threads(max(1, args.threads))
    t0 = time.time()
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    try:
        if args.features:
            if not args.features.is_file():
                print(f"vs2t-edge compare: feature cache {args.features} does not exist", file=sys.stderr)
                return EXIT_USAGE
            table = cmp.FeatureTable.load(args.features)
            source = f"cache {args.features} ({table.source})"
        elif args.data:
            if args.cache and args.cache.is_file():
                table = cmp.FeatureTable.load(args.cache)
                source = f"cache {args.cache} ({table.source})"
            else:
                table = cmp.extract_feature_table(args.data, log=log, max_presses=args.max_presses)
                if args.cache:
                    args.cache.parent.mkdir(parents=True, exist_ok=True)
                    table.save(args.cache)
                source = table.source
        elif args.toy:
            # sized like the paper (50 fabrics) but with 60 presses each, 256-d features, and a
            # touch-only part per fabric so that zero-shot is not trivially solvable
            table = cmp.toy_feature_table(n_fabrics=50, presses=60, d_t=256, d_v=256, seed=args.seed, noise=3.0,
                                          private=1.5)
            source = table.source
        else:
            print("vs2t-edge compare: give --features CACHE.npz, --data DATASET or --toy", file=sys.stderr)
            return EXIT_USAGE
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"vs2t-edge compare: cannot read features: {exc}", file=sys.stderr)
        return EXIT_USAGE

    methods = cmp.all_methods()
    if args.methods != "all":
        wanted = [m.strip() for m in args.methods.split(",") if m.strip()]
        unknown = [m for m in wanted if m not in methods]
        if unknown:
            print(f"vs2t-edge compare: unknown method(s) {unknown}; known: {list(methods)}", file=sys.stderr)
            return EXIT_USAGE
        methods = {m: methods[m] for m in wanted}
    try:
        splits = cmp.make_splits(table.fabric_ids, args.splits, args.n_val, args.n_untouched, args.seed)
    except ValueError as exc:
        print(f"vs2t-edge compare: {exc}", file=sys.stderr)
        return EXIT_USAGE
    budget = Budget(steps=args.steps, hidden=args.hidden, cls_steps=args.cls_steps)
    result = cmp.run_comparison(table, splits, budget, methods, log=log)
    s0 = splits[0]
    result["meta"] = {
        "command": "vs2t-edge compare " + " ".join(sys.argv[2:] if len(sys.argv) > 2 else []),
        "features": source, "n_fabrics": len(table.fabric_ids), "n_presses": int(len(table.fabric)),
        "d_t": int(table.x_t.shape[1]), "d_v": int(table.x_v.shape[1]), "n_splits": len(splits),
        "split_sizes": f"{len(s0.touched)}/{len(s0.validation)}/{len(s0.untouched)}",
        "budget": f"steps {budget.steps}, hidden {budget.hidden}, batch {budget.batch}, latent {budget.latent}, "
                  f"cls steps {budget.cls_steps}, {budget.n_synth_per_class} synthetic/class, GAN lr {budget.lr}",
        "host": f"{platform.machine()} {torch.get_num_threads()} torch threads",
        "seconds": 0.0,
    }
    real = None
    if args.real_result is not None:
        try:
            real = json.loads(args.real_result.read_text())
            real["summary"]
        except (OSError, ValueError, KeyError) as exc:
            print(f"vs2t-edge compare: cannot read real-sensor result {args.real_result}: {exc}", file=sys.stderr)
            return EXIT_USAGE
    elif not args.skip_real:
        root = args.real or DEFAULT_ROOT
        if root.is_dir():
            log(f"real-sensor check on {root}")
            real = run_check(root, RealCheckConfig(n_splits=args.real_splits, epochs=args.real_epochs))
        else:
            log(f"real-sensor check skipped: {root} is absent")
    result["meta"]["seconds"] = time.time() - t0
    paths = cmp.write_results(result, args.out, real)
    rec = result["summary"]["recommendation"]
    print(f"recommended default: model {rec['model']}, router {rec['router']} (chosen on validation)")
    for p in paths.values():
        print(f"wrote {p}")
    return EXIT_OK

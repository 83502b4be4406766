"""`vs2t-edge compare`: regenerate the whole comparison (Table 4 rows, modern generators, GZSL
routers with AUSUC, the real-sensor check) into docs/results/comparison.{md,json,png}.

Feature sources, first match wins:

- ``--run RUN``: a `vs2t-edge train` run folder. Its exact splits (metrics.json, in order, with
  their seeds), its budget (config.yaml; --steps/--hidden/--cls-steps override), and its tactile
  features: ``--tactile finetuned`` (default) re-runs the run's per-split tail fine-tuning from
  its stem cache, so every row sees the features the run's VS2T-ZSL saw; ``--tactile frozen``
  uses features/feature_table.npz. The run's own VS2T-ZSL numbers are shown beside ours and the
  report goes to ``{--out}/comparison_{profile}.*``.
- ``--features CACHE.npz`` (a FeatureTable cache, e.g. a run's features/feature_table.npz or a
  previous ``--data`` run's ``--cache``), ``--data DATASET`` (features extracted here with a
  frozen ImageNet EfficientNet-Lite0), ``--toy`` (a synthetic feature world, for smoke runs);
  with these, ``--splits-from RUN_OR_METRICS_JSON`` takes the splits of a run instead of drawing
  ``--splits`` random ones.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from dataclasses import asdict
from pathlib import Path

EXIT_OK, EXIT_USAGE = 0, 2


def add_arguments(parser: argparse.ArgumentParser, verb: str) -> None:
    src = parser.add_argument_group("features (one of)")
    src.add_argument("--run", type=Path,
                     help="`vs2t-edge train` run folder: its splits, budget, features and VS2T numbers")
    src.add_argument("--features", type=Path, help="FeatureTable cache (.npz)")
    src.add_argument("--data", type=Path, help="dataset folder: extract frozen-trunk features here")
    src.add_argument("--toy", action="store_true", help="synthetic feature world (smoke run)")
    parser.add_argument("--tactile", choices=("finetuned", "frozen"), default="finetuned",
                        help="with --run: the run's per-split fine-tuned tactile features (default) or frozen ones")
    parser.add_argument("--new-splits", action="store_true",
                        help="with --run: draw --splits random splits (--seed, --n-val, --n-untouched) instead of the "
                             "run's, e.g. more validation evidence on the run's features (no run VS2T numbers then)")
    parser.add_argument("--splits-from", type=Path, default=None,
                        help="take the splits of this run folder (or its metrics.json) instead of random ones")
    parser.add_argument("--out-name", default=None,
                        help="report file stem (default comparison, with --run comparison_<profile>)")
    parser.add_argument("--cache", type=Path, help="with --data: write/read the extracted features here")
    parser.add_argument("--max-presses", type=int, default=None, help="with --data: presses per fabric")
    parser.add_argument("--splits", type=int, default=5, help="random fabric splits (paper: 5)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-val", type=int, default=None, help="validation fabrics per split (default 10%%)")
    parser.add_argument("--n-untouched", type=int, default=None, help="untouched fabrics per split (default 10%%)")
    parser.add_argument("--methods", default="all", help="comma list of method names, or 'all'")
    parser.add_argument("--steps", type=int, default=None,
                        help="optimiser steps per generative model (default: the run's, else 1500)")
    parser.add_argument("--hidden", type=int, default=None, help="hidden width (default: the run's, else 1024)")
    parser.add_argument("--cls-steps", type=int, default=None, help="classifier steps (default: the run's, else 600)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (1: the machine is shared; 2 threads measured 6x slower under load)")
    parser.add_argument("--out", type=Path, default=Path("docs/results"), help="folder for comparison.*")
    parser.add_argument("--real", type=Path, default=None,
                        help="GelSight Mini materials folder (default ../shared/real/gelsight_mini_materials)")
    parser.add_argument("--skip-real", action="store_true", help="do not run the real-sensor check")
    parser.add_argument("--real-result", type=Path, default=None,
                        help="reuse a real-sensor check JSON written by `python -m vs2t_edge.train.realdata_check --out`, "
                             "or the real_sensor_check of an earlier comparison JSON")
    parser.add_argument("--replace-unmarked", action="store_true",
                        help="rewrite a report page that has no hand-written marker line whole (default: refuse, "
                             "since its hand-written text cannot be told from the generated part)")
    parser.add_argument("--real-splits", type=int, default=5)
    parser.add_argument("--real-epochs", type=int, default=8)


def run(args: argparse.Namespace) -> int:
    try:
        import torch
    except ModuleNotFoundError:
        print("vs2t-edge compare: needs the [train] extra (torch)", file=sys.stderr)
        return 4

    torch.set_num_threads(max(1, args.threads))
    # as `vs2t-edge train` (same numerics; denormals can slow CPU steps many-fold), and only for
    # this verb: the flag is process-wide and would break IEEE subnormals for later code
    torch.set_flush_denormal(True)
    try:
        return _run(args, torch)
    finally:
        torch.set_flush_denormal(False)


def _run(args: argparse.Namespace, torch) -> int:
    from vs2t_edge.train import compare as cmp
    from vs2t_edge.train.baselines import Budget
    from vs2t_edge.train.realdata_check import DEFAULT_ROOT, RealCheckConfig, run_check

    t0 = time.time()
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    run_src, table_for_split, notes = None, None, []
    try:
        if args.run:
            run_src = cmp.load_run(args.run)
            table = run_src.table
            source = f"run {args.run}: {cmp.RUN_FEATURE_TABLE} ({table.source})"
            if args.tactile == "finetuned":
                table_for_split = cmp.finetuned_tables(run_src, log=log)
                source = (f"run {args.run}: tactile features of the run's stem cache through the trunk tail "
                          f"fine-tuned per split on touched-train presses (as `vs2t-edge train` does, same seeds); "
                          f"visual features frozen ({table.source})")
        elif args.features:
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
            print("vs2t-edge compare: give --run RUN, --features CACHE.npz, --data DATASET or --toy", file=sys.stderr)
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
        if run_src is not None and not args.new_splits:
            splits, splits_source = run_src.splits, f"; exactly the splits of {args.run / 'metrics.json'}"
        elif args.splits_from is not None:
            splits, _ = cmp.read_run_splits(args.splits_from)
            splits_source = f"; exactly the splits of {args.splits_from}"
        else:
            splits = cmp.make_splits(table.fabric_ids, args.splits, args.n_val, args.n_untouched, args.seed)
            splits_source = f"; random, seed {args.seed}"
        cmp.check_splits(table, splits)
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"vs2t-edge compare: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if run_src is not None:
        budget = cmp.run_budget(run_src.profile, run_src.budget, steps=args.steps, hidden=args.hidden,
                                cls_steps=args.cls_steps)
        notes.append(f"Budget: the VS2T run's profile ({args.run / 'config.yaml'}) for every row"
                     + (" with command-line overrides" if any(v is not None for v in (args.steps, args.hidden,
                                                                                       args.cls_steps)) else "")
                     + f"; VS2T-ZSL lr scale {budget.lr_scale} (its paper rates x {budget.lr_scale}); full budget: "
                     + ", ".join(f"{k} {v}" for k, v in asdict(budget).items()) + ".")
    else:
        budget = Budget(steps=args.steps or 1500, hidden=args.hidden or 1024, cls_steps=args.cls_steps or 600)
    real = None  # read before the long run: a bad path fails now
    if args.real_result is not None:
        try:
            real = json.loads(args.real_result.read_text())
            real = real.get("real_sensor_check", real)  # an earlier comparison JSON holds it under this key
            real["summary"]
        except (OSError, ValueError, KeyError) as exc:
            print(f"vs2t-edge compare: cannot read real-sensor result {args.real_result}: {exc}", file=sys.stderr)
            return EXIT_USAGE
        notes.append(f"Real-sensor check: reused from {args.real_result}, not re-run (it does not depend on the "
                     f"fabric splits).")
    n_jobs = len(splits) * len(methods)
    log(f"compare: {len(methods)} methods x {len(splits)} splits = {n_jobs} fits; features: {source}")
    name = args.out_name or (f"comparison_{run_src.profile.get('name', 'run')}" if run_src is not None
                             else "comparison")
    unmarked = "replace" if args.replace_unmarked else "refuse"
    try:  # now, not after the long run: a page whose hand-written text cannot be kept is refused up front
        cmp.hand_written_tail(args.out / f"{name}.md", unmarked)
    except cmp.UnmarkedReportError as exc:
        print(f"vs2t-edge compare: {exc}", file=sys.stderr)
        return EXIT_USAGE
    partial = args.out / f"{name}.partial.json"  # per-split results so far; removed when the report is written

    def on_split(done: list[dict]) -> None:
        args.out.mkdir(parents=True, exist_ok=True)
        partial.write_text(json.dumps({"splits_done": len(done), "splits": done}, indent=1, default=float))

    result = cmp.run_comparison(table, splits, budget, methods, log=log, table_for_split=table_for_split,
                                on_split=on_split)
    s0 = splits[0]
    result["meta"] = {
        "command": "vs2t-edge compare " + " ".join(sys.argv[2:] if len(sys.argv) > 2 else []),
        "features": source, "n_fabrics": len(table.fabric_ids), "n_presses": int(len(table.fabric)),
        "d_t": int(table.x_t.shape[1]), "d_v": int(table.x_v.shape[1]), "n_splits": len(splits),
        "split_sizes": f"{len(s0.touched)}/{len(s0.validation)}/{len(s0.untouched)}",
        "splits_source": splits_source,
        "budget": f"steps {budget.steps}, hidden {budget.hidden}, batch {budget.batch}, latent {budget.latent}, "
                  f"cls steps {budget.cls_steps}, {budget.n_synth_per_class} synthetic/class, GAN lr {budget.lr}",
        "host": f"{platform.machine()} {torch.get_num_threads()} torch threads",
        "seconds": 0.0, "notes": notes,
    }
    if name != "comparison" and (args.out / "comparison.md").is_file():
        result["meta"]["see_also"] = ("The earlier comparison on its own random splits and frozen features is "
                                      "[comparison.md](comparison.md) (with the real-sensor check).")
    if run_src is not None and args.new_splits:
        result["meta"]["title_suffix"] = (f" — {run_src.profile.get('name', 'run')} profile, the run's features, "
                                          f"new random splits (seed {args.seed})")
    elif run_src is not None:
        result["meta"]["title_suffix"] = f" — {run_src.profile.get('name', 'run')} profile (the VS2T run's splits)"
        own = cmp.compare_with_run(result, run_src)
        if own is None:
            log(f"note: {args.run / 'metrics.json'} has no VS2T-ZSL record to show beside ours")
    if real is None and not args.skip_real:
        root = args.real or DEFAULT_ROOT
        if root.is_dir():
            log(f"real-sensor check on {root}")
            real = run_check(root, RealCheckConfig(n_splits=args.real_splits, epochs=args.real_epochs))
        else:
            log(f"real-sensor check skipped: {root} is absent")
    result["meta"]["seconds"] = time.time() - t0
    paths = cmp.write_results(result, args.out, real, name=name, unmarked=unmarked)
    partial.unlink(missing_ok=True)
    rec = result["summary"]["recommendation"]
    print(f"recommended default: model {rec['model']}, router {rec['router']} (chosen on validation)")
    for p in paths.values():
        print(f"wrote {p}")
    return EXIT_OK

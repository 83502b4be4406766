"""`vs2t-edge replay FILE...`: run the whole daemon from replay files and compare decisions.

Exit 0 when every file reproduces its recorded decisions (exact on labels, bins, outcomes,
presses and faults; scores within 1e-3), 1 on any mismatch or divergence (each printed), 2 on
an unreadable file or a refused bundle (also another bundle than the session ran, by its seal,
unless ``--allow-other-bundle``). ``--update-refs`` rewrites the reference decisions of
each file from this run (the recorded frames and device events never change).
"""

from __future__ import annotations

import sys
from pathlib import Path


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("files", nargs="+", help="replay folders (NAME.replay)")
    parser.add_argument("--bundle", default=None, help="bundle to replay with (default: the recorded one)")
    parser.add_argument("--allow-other-bundle", action="store_true",
                        help="replay against a bundle other than the one the session ran (its recorded seal, "
                             "manifest_sha256, differs): refused without this flag")
    parser.add_argument("--update-refs", action="store_true",
                        help="regenerate the reference decisions from this run (review the diff!)")


def run(args) -> int:
    from vs2t_edge.runtime.replay import ReplayError, run_replay

    worst = 0
    for f in args.files:
        try:
            report = run_replay(Path(f), bundle=Path(args.bundle) if args.bundle else None,
                                update_refs=args.update_refs, allow_other_bundle=args.allow_other_bundle)
        except ReplayError as exc:
            said = str(exc)  # most reasons already begin with the file or a path inside it
            print(said if said.startswith(str(Path(f))) else f"{f}: {said}", file=sys.stderr)
            worst = max(worst, 2)
            continue
        finals = [d for d in report.decisions if d["type"] == "final"]
        if report.diverged:
            print(f"{f}: DIVERGED: {report.diverged}")
            worst = max(worst, 2 if "exited with 2" in report.diverged else 1)
        elif args.update_refs:
            print(f"{f}: references updated ({len(finals)} items)")
        elif report.mismatches:
            print(f"{f}: MISMATCH ({len(report.mismatches)})")
            for m in report.mismatches[:50]:
                print(f"  {m}")
            worst = max(worst, 1)
        else:
            labels = ", ".join(f"{d['label']}->{d['bin']}" for d in finals)
            print(f"{f}: ok, {len(finals)} items identical [{labels}]")
    return worst

"""`vs2t-edge reliability`: run the fault matrix (sim/faults.py) and write docs/reliability.md.

The table's numbers are measured on this run; the soak section is read from the last soak JSON
(``--soak-json``, written by ``python -m vs2t_edge.sim.soak``); the hand-written prose (what the
rows do, bugs found, fuzzing, security: what is enforced and which test checks it) comes from
sim/reliability_template.md.
"""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("--out", type=Path, default=None, help="write the markdown report here "
                        "(e.g. docs/reliability.md); without it only the table is printed")
    parser.add_argument("--only", nargs="*", default=None, help="run only these scenario names")
    parser.add_argument("--skip-slow", action="store_true", help="leave out the UR simulator rows")
    parser.add_argument("--soak-json", type=Path, default=Path("docs/results/soak.json"),
                        help="soak result to quote in the report (from `python -m vs2t_edge.sim.soak`)")


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def table(rows) -> str:
    lines = ["| # | scenario | where | fault | expected | measured outcome | result | s |",
             "|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(rows, 1):
        result = {"FAIL": "**FAIL**", "KNOWN BUG": "**KNOWN BUG**"}.get(r.result, r.result)
        outcome = r.outcome if not r.problems else r.outcome + " — " + "; ".join(p.splitlines()[-1] for p in r.problems)
        lines.append(f"| {i} | `{r.name}` | {r.where} | {_cell(r.fault)} | {_cell(r.expect)} | "
                     f"{_cell(outcome[:400])} | {result} | {r.seconds:.1f} |")
    return "\n".join(lines)


TEMPLATE_MARKER = "<!-- generated sections (fault matrix, soak) go here; what follows is kept after them -->"


def report(rows, soak: dict | None, seconds: float) -> str:
    here = Path(__file__).with_name("reliability_template.md")
    text = here.read_text(encoding="utf-8") if here.exists() else ""
    # the template's hand-written text: above the marker before the generated sections, below it after
    head, _, tail = text.partition(TEMPLATE_MARKER)
    n_pass = sum(r.passed for r in rows)
    n_pending = sum(bool(r.pending) for r in rows)
    known = [r for r in rows if r.result == "KNOWN BUG"]
    out = [head.rstrip() + "\n" if head else "",
           f"## Fault matrix\n\nRegenerate: `vs2t-edge reliability --out docs/reliability.md`. "
           f"Last run: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {platform.machine()} "
           f"(Python {platform.python_version()}), {len(rows)} rows, {n_pass} pass, {n_pending} pending, "
           f"{len(known)} known bug, {len(rows) - n_pass - n_pending - len(known)} fail, {seconds:.0f} s.\n",
           table(rows), ""]
    if known:
        out.append("Known bugs (rows that fail today; the test is a strict xfail naming the owner):\n\n"
                   + "\n".join(f"* `{r.name}`: {r.known_bug}" for r in known) + "\n")
    if soak:
        out.append(soak_section(soak))
    if tail.strip():
        out.append(tail.strip() + "\n")
    return "\n".join(out) + "\n"


def soak_section(s: dict) -> str:
    return ("## Soak (last run)\n\n"
            f"`{s.get('command', 'python -m vs2t_edge.sim.soak')}`: {s['presses']} presses, {s['items']} pieces in "
            f"{s['seconds']:.0f} s ({s.get('arm', '?')} arm, {s.get('gate', '?')} gate; model: "
            f"{s.get('model', 'grey-level fake model')}).\n\n"
            "| measure | first 10 % | last 10 % | slope (per 1000 presses) | verdict |\n|---|---|---|---|---|\n"
            f"| RSS (MiB) | {s['rss_first_mib']:.1f} | {s['rss_last_mib']:.1f} | {s['rss_slope_mib_per_kpress']:+.3f} MiB | "
            f"{s['rss_verdict']} |\n"
            f"| press cycle (ms, median) | {s['press_ms_first']:.2f} | {s['press_ms_last']:.2f} | "
            f"{s['press_ms_slope_per_kpress']:+.3f} ms | {s['latency_verdict']} |\n"
            + (f"| scoring (model.score_press, ms, median) | {s['score_ms_first']:.2f} | {s['score_ms_last']:.2f} | "
               f"{s['score_ms_slope_per_kpress']:+.3f} ms | {s['score_verdict']} |\n" if "score_verdict" in s else "")
            + f"| journal | | {s['journal_mib']:.1f} MiB | | {s['journal_verdict']} |\n"
            + (f"\nHeld in memory at the end: {s['in_memory_journal_records']} journal records and "
               f"{s['in_memory_results']} item results (bounded windows; {s.get('items_done', s['items'])} items "
               f"counted), {s['notifier_messages_held']} sd_notify messages (a window of the last "
               "ones).\n" if "notifier_messages_held" in s else ""))


def run(args) -> int:
    from vs2t_edge.sim import faults

    chosen = [s for s in faults.SCENARIOS
              if (args.only is None or s.name in args.only) and not (args.skip_slow and s.where == "ursim")]
    if args.only:
        unknown = set(args.only) - {s.name for s in faults.SCENARIOS}
        if unknown:
            print(f"unknown scenario(s): {', '.join(sorted(unknown))}; known: "
                  f"{', '.join(s.name for s in faults.SCENARIOS)}", file=sys.stderr)
            return 2
    t0 = time.monotonic()
    rows = []
    for i, sc in enumerate(chosen, 1):
        print(f"[{i}/{len(chosen)}] {sc.name} ...", file=sys.stderr, flush=True)
        rows.append(faults.run_scenario(sc))
        r = rows[-1]
        print(f"    {r.result} ({r.seconds:.1f} s) {r.outcome[:160]}",
              file=sys.stderr, flush=True)
    seconds = time.monotonic() - t0
    print(table(rows))
    if args.out is not None:
        soak = None
        if args.soak_json and Path(args.soak_json).exists():
            soak = json.loads(Path(args.soak_json).read_text())
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report(rows, soak, seconds), encoding="utf-8")
        print(f"wrote {args.out}", file=sys.stderr)
    return 0 if not any(r.blocking for r in rows) else 1

"""Soak: the simulated cell sorting for a long bounded run, memory and latency tracked.

    python -m vs2t_edge.sim.soak --presses 5000 [--gate pty|fake] [--json docs/results/soak.json]

The cell is the fault matrix's rig (sim/faults.py): the real loop, journal (fsynced), the gate
host driver against the MCU simulator on a pty (default), FakeArm and the simulated camera with
sensor noise, the grey-level fake model. Every ``--sample`` presses it records the process RSS
(/proc/self/statm) and the press cycle times since the last sample. It reports, over the run
after a 10 % warm-up, the least-squares slope of RSS and of the median press cycle per 1000
presses, and the first and last 10 % levels. Verdicts: RSS "no growth" when the slope is under
``--rss-limit-mib`` per 1000 presses; latency "no drift" when the last 10 % median is within 20 %
of the first 10 %.

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


def soak(presses: int, *, gate_kind: str = "pty", sample: int = 100, workdir: Path | None = None,
         rss_limit_mib: float = 0.5, progress: bool = True) -> dict:
    from vs2t_edge.sim.faults import TRUTHS, build_rig

    own = workdir is None
    workdir = Path(tempfile.mkdtemp(prefix="soak-")) if own else workdir
    gate = None
    if gate_kind == "pty":
        from vs2t_edge.runtime.gate import simulated_serial_gate

        gate = simulated_serial_gate(timeout_s=0.5)
    truths = [TRUTHS[i % len(TRUTHS)] for i in range(presses)]  # at least one press per piece
    rig = build_rig(workdir, truths, gate=gate)
    inner_press = rig.arm.inner.press
    stamps: list[float] = []  # press start times of the current sample window only
    n_pressed = 0

    def timed_press():
        nonlocal n_pressed
        stamps.append(time.perf_counter())
        n_pressed += 1
        return inner_press()

    rig.arm.inner.press = timed_press
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
                            "notifier_messages": len(rig.cell.notifier.sent)})
            last_n = n
            if progress:
                s = samples[-1]
                print(f"\rsoak: {n}/{presses} presses, RSS {s['rss_mib']:.1f} MiB, press cycle "
                      f"{s['press_ms_median']:.2f} ms", end="", file=sys.stderr, flush=True)
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
    from vs2t_edge.sim.faults import audit

    a = audit(rig.journal_path, {it.id: it.truth for it in rig.pieces.items})
    journal_mib = rig.journal_path.stat().st_size / 2**20
    warm = samples[max(1, len(samples) // 10):]
    k = max(1, len(samples) // 10)
    first, last = samples[:k], samples[-k:]
    x = [s["presses"] for s in warm]
    res = {
        "command": f"python -m vs2t_edge.sim.soak --presses {presses} --gate {gate_kind}",
        "presses": n_pressed, "items": len(a["finals"]), "seconds": seconds, "arm": "FakeArm",
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
    drift = res["press_ms_last"] / max(res["press_ms_first"], 1e-9) - 1.0
    res["latency_verdict"] = "no drift" if abs(drift) < 0.2 else f"DRIFT ({drift:+.0%})"
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
    a = ap.parse_args(argv)
    if a.presses < 10 * a.sample:
        print(f"--presses must be at least 10 x --sample ({10 * a.sample})", file=sys.stderr)
        return 2
    res = soak(a.presses, gate_kind=a.gate, sample=a.sample, rss_limit_mib=a.rss_limit_mib)
    print(f"{res['presses']} presses, {res['items']} pieces, {res['seconds']:.0f} s")
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
    ok = not res["problems"] and res["rss_verdict"] == "no growth" and res["latency_verdict"] == "no drift"
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

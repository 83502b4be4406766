"""Time the press with the real ur_rtde client against the loopback simulator:
``python -m vs2t_edge.sim.ursim --bench 9 --json FILE`` (docs/arm.md, "Measured")."""

from __future__ import annotations

import time

from vs2t_edge.sim.ursim import free_loopback_host
from vs2t_edge.sim.ursim_model import PressScene
from vs2t_edge.sim.ursim_process import URSimProcess


def bench_press(n_points: int = 9, json_path: str | None = None, **arm_overrides) -> dict:
    """Time move_above / press / retract with the real ur_rtde client against the simulator.

    Uses the default ArmConfig (the cell's settings) unless overridden; the points are spread
    over the 15 x 15 grid. Prints a table; writes the numbers as JSON when json_path is given.
    """
    import json
    import statistics
    import sys

    from vs2t_edge.runtime.arm import ArmConfig
    from vs2t_edge.runtime.arm_ur import URArm

    host = free_loopback_host()
    config = ArmConfig(host=host, **arm_overrides)
    grid = config.grid_points_mm()
    points = [grid[round(i * (len(grid) - 1) / max(n_points - 1, 1))] for i in range(n_points)]
    rows = []
    with URSimProcess(PressScene(), host=host) as sim:
        arm = URArm(config)
        t0 = time.monotonic()
        arm.connect()
        connect_s = time.monotonic() - t0
        try:
            for k, (x, y) in enumerate(points):
                t0 = time.monotonic()
                arm.move_above(x, y)
                t1 = time.monotonic()
                result = arm.press()
                t2 = time.monotonic()
                arm.retract()
                t3 = time.monotonic()
                rows.append({"x_mm": x, "y_mm": y, "move_above_s": t1 - t0, "press_s": t2 - t1,
                             "retract_s": t3 - t2, "force_n": result.force_n, "depth_mm": result.depth_mm,
                             "contact_after_s": result.telemetry["contact_after_s"]})
                print(f"\rpress {k + 1}/{len(points)}", end="", file=sys.stderr)
            print(file=sys.stderr)
        finally:
            arm.disconnect()
        unsupported = sim.get_log().get("unsupported", [])

    def stats(key: str) -> dict:
        values = [r[key] for r in rows[1:] or rows]  # the first move starts from home, far away
        return {"median": statistics.median(values), "max": max(values)}

    summary = {
        "client": "ur_rtde (real) " + _ur_rtde_version(),
        "config": {k: v for k, v in config.to_dict().items() if k != "host"},
        "connect_s": connect_s,
        "presses": rows,
        "move_above_s": stats("move_above_s"), "press_s": stats("press_s"),
        "retract_s": stats("retract_s"), "force_n": stats("force_n"),
        "force_error_n_max": max(abs(r["force_n"] - config.force_n) for r in rows),
        "unsupported_commands": unsupported,
    }
    print(f"{'step':<12}{'median s':>10}{'max s':>10}")
    for key in ("move_above_s", "press_s", "retract_s"):
        print(f"{key[:-2]:<12}{summary[key]['median']:>10.3f}{summary[key]['max']:>10.3f}")
    print(f"force at grab: median {summary['force_n']['median']:.2f} N, worst error "
          f"{summary['force_error_n_max']:.2f} N (target {config.force_n} N); connect {connect_s:.2f} s")
    if json_path:
        with open(json_path, "w") as f:
            json.dump(summary, f, indent=1, default=float)
    return summary


def _ur_rtde_version() -> str:
    try:
        from importlib.metadata import version

        return version("ur_rtde")
    except Exception:
        return "?"

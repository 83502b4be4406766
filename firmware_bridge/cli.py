"""Hand commands for the gate: ``vs2t-edge sort BIN``, ``sort status``, ``sort clear``.

``gate-status`` and ``gate-clear`` are the older names of ``sort status`` and ``sort clear``
and stay as aliases (scripts and docs use them).

For commissioning and tests. Each command is its own host session: it connects, does one
thing and disconnects. Between hand commands nobody sends heartbeats, so a gate left alone
for more than a second fails safe (reject, HEARTBEAT_LOST latched) — that is the fail-safe
working. ``sort`` therefore arms a gate latched by BOOT or HEARTBEAT_LOST before routing
(``--no-arm`` refuses instead); a JAM latch always needs ``sort clear`` after someone freed
the flap. ``--simulate`` runs the command against the MCU simulator on a fresh pty.

Exit codes: 0 ok, 2 bad usage (no port, bad bin), 3 gate fault (timeout, NAK, jam, latched,
link), as in vs2t_edge/cli.py.
"""

from __future__ import annotations

import argparse
import os
import sys

from vs2t_edge.firmware_bridge import protocol as p
from vs2t_edge.firmware_bridge.gate_client import GateClient, GateClientError, GateReport

EXIT_OK, EXIT_USAGE, EXIT_DEVICE = 0, 2, 3  # the values of vs2t_edge.cli (this room imports none of ours)
PORT_ENV = "VS2T_GATE_PORT"


ARMED_LATCHES = ("boot", "heartbeat_lost")  # latches `sort BIN` clears before routing (not --no-arm)
SUBCOMMANDS = {"status": "gate-status", "clear": "gate-clear"}  # `sort WORD` -> the verb it stands for


def add_arguments(parser: argparse.ArgumentParser, verb: str) -> None:
    if verb == "sort":
        parser.usage = "vs2t-edge sort {BIN,status,clear} [options]"
        parser.add_argument("bin", metavar="BIN|status|clear",
                            help="a bin to route to (0 is the reject bin); `status`: ask the gate for its "
                                 "state (exits 3 when latched: fault or failsafe); `clear`: clear a latched "
                                 "fault (after freeing a jammed flap)")
        parser.add_argument("--no-arm", action="store_true",
                            help="sort BIN: do not clear a boot or heartbeat-lost latch before sorting")
        parser.epilog = "`vs2t-edge gate-status` and `vs2t-edge gate-clear` are aliases of `sort status` / `sort clear`"
    if verb == "gate-status":
        parser.epilog = "exits 3 when the gate is latched (fault or failsafe); alias: vs2t-edge sort status"
    if verb == "gate-clear":
        parser.epilog = "alias: vs2t-edge sort clear"
    parser.add_argument("--port", default=os.environ.get(PORT_ENV),
                        help=f"serial port or pyserial URL of the gate (default: ${PORT_ENV})")
    parser.add_argument("--timeout-s", type=float, default=0.5, help="reply timeout per attempt, seconds")
    parser.add_argument("--retries", type=int, default=3, help="retransmissions before giving up")
    parser.add_argument("--simulate", action="store_true",
                        help="talk to a simulated gate MCU on a new pseudo-terminal (commissioning practice)")


def _describe(report: GateReport) -> str:
    fault = f" ({report.fault})" if report.fault else ""
    return (f"gate {report.state}{fault}, flap at bin {report.bin} of {report.n_bins}, "
            f"boot {report.boot_id}, up {report.uptime_ms / 1000:.1f} s, {report.sorts_done} sorts since boot")


def _resolve(args: argparse.Namespace) -> tuple[str, str] | int:
    """(the verb to run, the name to say in messages), or EXIT_USAGE after saying why."""
    if args.verb != "sort":
        return args.verb, args.verb
    word = str(args.bin).strip()
    sub = word.lower()
    if sub in SUBCOMMANDS:
        if args.no_arm:
            print(f"vs2t-edge sort {sub}: --no-arm applies to sort BIN only", file=sys.stderr)
            return EXIT_USAGE
        return SUBCOMMANDS[sub], f"sort {sub}"
    try:
        args.bin = int(word)
    except ValueError:
        print(f"vs2t-edge sort: {word!r} is neither a bin number nor status or clear", file=sys.stderr)
        return EXIT_USAGE
    return "sort", "sort"


def run(args: argparse.Namespace) -> int:
    resolved = _resolve(args)
    if isinstance(resolved, int):
        return resolved
    action, verb = resolved
    if args.timeout_s <= 0 or args.retries < 0:
        print(f"vs2t-edge {verb}: --timeout-s must be > 0 and --retries >= 0", file=sys.stderr)
        return EXIT_USAGE
    if action == "sort" and not 0 <= args.bin <= 255:
        print(f"vs2t-edge sort: bin {args.bin} is out of range (0..255; 0 is reject)", file=sys.stderr)
        return EXIT_USAGE
    simulator = None
    port = args.port
    if args.simulate:
        from vs2t_edge.firmware_bridge.mcu_sim import start_simulated_gate

        port, simulator = start_simulated_gate()
        print(f"simulated gate on {port}", file=sys.stderr)
    if not port:
        print(f"vs2t-edge {verb}: no gate port; pass --port /dev/ttyACM0 (or any pyserial URL), "
              f"set {PORT_ENV}, or use --simulate", file=sys.stderr)
        return EXIT_USAGE
    # No heartbeat thread: a hand command is one short exchange. connect() only asks the gate's
    # STATUS (no latch armed): how many bins it has is known only then, and a bin it does not have
    # is bad input, refused before anything is cleared or moved.
    client = GateClient(port, timeout_s=args.timeout_s, retries=args.retries, heartbeat_period_s=None,
                        arm_latches=())
    try:
        report = client.connect()
        if action == "sort" and args.bin >= report.n_bins:
            print(f"vs2t-edge sort: no such bin {args.bin}: this gate has bins 0..{report.n_bins - 1} "
                  "(0 is reject); nothing was moved", file=sys.stderr)
            return EXIT_USAGE
        if action == "sort" and not args.no_arm and report.state in ("fault", "failsafe") \
                and report.fault in ARMED_LATCHES:
            client.clear()
            print(f"note: the gate was latched ({report.fault}); armed it", file=sys.stderr)
        if action == "sort":
            client.sort(args.bin)
            print(f"sorted to bin {args.bin}" + (" (reject)" if args.bin == p.REJECT_BIN else ""))
        elif action == "gate-clear":
            client.clear()
            print("gate cleared: " + _describe(client.status()))
        else:
            print(_describe(report))
            if report.state in ("fault", "failsafe"):
                return EXIT_DEVICE  # a latched gate is a device fault to a script asking

        return EXIT_OK
    except GateClientError as exc:
        print(f"vs2t-edge {verb}: {exc} [{exc.kind}]", file=sys.stderr)
        return EXIT_DEVICE
    finally:
        client.disconnect()
        if simulator is not None:
            simulator.stop()

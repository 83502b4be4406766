"""Fault-matrix rows of issue 17's inputs part (registered in sim/faults.py SCENARIOS).

Built from the matrix's helpers: the rig and the audit (sim/fault_rig.py), the grey-level fake
model (sim/fakes.py).
"""

from __future__ import annotations

import os
import socket
import struct
import threading
import time
import zlib
from pathlib import Path

import numpy as np


def _huge_png_header(side: int = 30000) -> bytes:
    """All a header check reads of a side x side PNG (the real file is < 3 MB and decodes to 2.7 GB)."""
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr
            + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr)) + b"\x00" * 64)


def replay_camera_not_sensor_frames(w: Path):
    """A ReplayCamera folder where a press frame is not what a GelSight sends: grey (1 channel),
    RGBA, 16-bit, another size, a 30000 x 30000 PNG and a FIFO. IMREAD_COLOR made the first three
    a BGR frame that was scored (a grey press decided with confidence 1.0 into a wrong bin); the
    big one decoded to 5.2 GB; the FIFO blocked the grab for ever. Each must be refused naming the
    file and why, the press retried on the next recorded frame, nothing of them scored. The retry
    reopened the camera after the piece's reference was taken, so those pieces go to the reject
    bin with their retried frame unscored (docs/cell.md, retry policy); the good pieces between them
    are sorted."""
    import cv2

    from vs2t_edge.runtime.camera import ReplayCamera
    from vs2t_edge.sim.fault_rig import _check, _loop_row
    from vs2t_edge.sim.faults_camera import _serving

    frames_dir = w / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    grey = {"denim": 50, "silk": 60, "wool": 70}
    bad = ["grey", "rgba", "16bit", "size", "huge", "fifo"]
    # a good piece, then each bad frame in a piece of its own followed by a good piece (three pieces in
    # a row ended by a reopen would latch a fault: runtime/cell.py STALE_PIECES_TO_FAULT)
    truths = ["denim", "silk", "wool", "denim", "silk", "wool", "denim", "silk", "wool", "denim", "silk", "wool",
              "denim"]
    bad_piece = {2 * i + 1: b for i, b in enumerate(bad)}
    levels: list = []
    for k, truth in enumerate(truths):  # per piece: its reference, then two presses or a bad frame and its retry
        levels.append(118 + k % 3)
        levels += [bad_piece[k], grey[truth]] if k in bad_piece else [grey[truth] - 2, grey[truth] + 2]
    for i, v in enumerate(levels):
        path = frames_dir / f"{i:06d}.png"
        if v == "grey":
            cv2.imwrite(str(path), np.full((48, 64), 55, np.uint8))
        elif v == "rgba":
            cv2.imwrite(str(path), np.full((48, 64, 4), 65, np.uint8))
        elif v == "16bit":
            cv2.imwrite(str(path), np.full((48, 64, 3), 75 * 257, np.uint16))
        elif v == "size":
            cv2.imwrite(str(path), np.full((24, 64, 3), 55, np.uint8))
        elif v == "huge":
            path.write_bytes(_huge_png_header())
        elif v == "fifo":
            os.mkfifo(path)
        else:
            cv2.imwrite(str(path), np.full((48, 64, 3), v, np.uint8))
    cam = ReplayCamera(frames_dir, expected_hw=(48, 64))
    served = _serving(cam)
    held: dict = {}
    words, problems = _loop_row(w, inject=lambda r: None, truths=truths, camera=cam,
                                expect_outcomes={"sorted": len(truths)}, fault_words=None, retries=len(bad),
                                holder_out=held)
    retries = held["audit"]["retries"]
    names = [f"{i:06d}.png" for i, v in enumerate(levels) if v in bad]
    for name, why, rec in zip(names, ("shape", "shape", "dtype", "size", "30000x30000", "FIFO"), retries):
        err = rec.get("error", "")
        _check(problems, name in err and why in err, f"the refusal of {name} does not say {name} / {why}: {err!r}")
    pre = [r for r in held["audit"]["records"] if r.get("type") == "pre_sort"]
    scored = [round(sc["novelty"]) for r in pre for sc in r["scores"]]
    good = [v for k in range(len(truths)) if k not in bad_piece for v in levels[3 * k + 1:3 * k + 3]]
    _check(problems, scored == good, f"press frames scored {scored}, expected the good pieces' {good}")
    reopened = [(r["bin"], r["stopped_by"]) for k, r in enumerate(pre) if k in bad_piece]
    _check(problems, reopened == [(0, "camera_reopened")] * len(bad),
           f"pieces after a reopen: {reopened}, expected reject, camera_reopened")
    want = [v for v in levels if isinstance(v, int)]
    _check(problems, served == want, f"frames served {served}, the good frames in order are {want}")
    return words + f"; {len(retries)} frames refused by name ({', '.join(bad)}), none scored", problems


def restart_piece_ids(w: Path):
    """The daemon (runtime/daemon.py run_daemon, its own ContinuousFeed) sorts two pieces, is
    restarted on the same journal and sorts two more: the piece ids must not start again at
    piece-000001 (every restart reused them, so the journal held two pieces of each id)."""
    from vs2t_edge.runtime.arm import ArmConfig
    from vs2t_edge.sim.fake_devices import FakeArm
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.sim.fake_devices import FakeGate
    from vs2t_edge.sim.devices import SimulatedCamera
    from vs2t_edge.sim.fakes import GREY, REFERENCE_GREY, GreyEvidence, GreyModel
    from vs2t_edge.sim.fault_rig import _check, audit
    from vs2t_edge.sim.faults_process import DAEMON_CONFIG
    from vs2t_edge.sim.scene import FAST_PRESS

    w.mkdir(parents=True, exist_ok=True)
    (w / "cell.yaml").write_text(DAEMON_CONFIG)
    (w / "cell.yaml").chmod(0o640)
    cfg = load_config(w / "cell.yaml")
    problems: list[str] = []
    class PressingArm(FakeArm):  # remembers whether the gel is down, for the camera
        pressed = False

        def press(self):
            result = super().press()
            self.pressed = True
            return result

        def retract(self):
            self.pressed = False
            return super().retract()

    for run in range(2):
        arm = PressingArm(config=ArmConfig(**FAST_PRESS))
        cam = SimulatedCamera(lambda: np.full((48, 64, 3), GREY["denim"] if arm.pressed else REFERENCE_GREY,
                                              np.uint8), expected_hw=(48, 64))
        code = run_daemon(cfg, model=GreyModel(), camera=cam, arm=arm, gate=FakeGate(),
                          evidence_factory=lambda: GreyEvidence(max_presses=3), max_items=2, install_signals=False,
                          log=lambda m: None)
        _check(problems, code == 0, f"run {run + 1}: exit {code}")
    a = audit(cfg.journal, {f"piece-{n:06d}": "denim" for n in range(1, 5)})
    problems += a["problems"]
    ids = [r["item_id"] for r in a["finals"]]
    _check(problems, ids == [f"piece-{n:06d}" for n in range(1, 5)], f"piece ids over two runs: {ids}")
    return f"two runs on one journal: pieces {', '.join(ids)}", problems


def watchdog_through_hung_grab(w: Path):
    """Scaled to a 1 s watchdog: arm moves of 0.15 s and a grab that hangs 0.5 s (its timeout),
    on a press and its retry. The loop pinged at half the watchdog, only between presses: the gap
    reached 1.10 s, past the watchdog - systemd would kill the service instead of the cell
    latching a camera fault with the piece in the reject bin. The fault must latch with every gap
    between pings under half the watchdog (runtime/budget.py: leased device waits)."""
    from vs2t_edge.runtime.arm import ArmConfig
    from vs2t_edge.sim.fake_devices import FakeArm
    from vs2t_edge.runtime.budget import StepBounds
    from vs2t_edge.runtime.cell import Cell, SceneSpec
    from vs2t_edge.runtime.devices import CameraError, Frame
    from vs2t_edge.sim.fake_devices import FakeGate
    from vs2t_edge.runtime.journal import Journal
    from vs2t_edge.runtime.notify import Notifier
    from vs2t_edge.sim.fakes import GreyEvidence, GreyModel
    from vs2t_edge.sim.fault_rig import Pieces, _check, audit
    from vs2t_edge.sim.scene import FAST_PRESS

    w.mkdir(parents=True, exist_ok=True)
    watchdog_s = 1.0

    class SlowArm(FakeArm):
        def move_above(self, x_mm, y_mm):
            time.sleep(0.15)
            return super().move_above(x_mm, y_mm)

        def retract(self):
            time.sleep(0.15)
            return super().retract()

    class HungCamera:
        grabs = 0

        def connect(self):
            pass

        def disconnect(self):
            pass

        def grab(self):
            self.grabs += 1
            if self.grabs == 1:
                return Frame(np.full((48, 64, 3), 120, np.uint8), time.monotonic(), 0)
            time.sleep(0.5)
            raise CameraError("no frame within 0.5 s", device="camera", kind="timeout")

    sock_path = str(w / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(sock_path)
    server.settimeout(0.01)
    old = os.environ.get("WATCHDOG_USEC"), os.environ.pop("WATCHDOG_PID", None)
    os.environ["WATCHDOG_USEC"] = str(int(watchdog_s * 1e6))
    try:
        notifier = Notifier(address=sock_path)
    finally:
        os.environ.pop("WATCHDOG_USEC")
        if old[0] is not None:
            os.environ["WATCHDOG_USEC"] = old[0]
        if old[1] is not None:
            os.environ["WATCHDOG_PID"] = old[1]
    arm = SlowArm(config=ArmConfig(**FAST_PRESS))
    arm.connect()
    pieces = Pieces(["denim"])
    scene = SceneSpec(bins={"denim": 1}, reject_bin=0, points_mm=arm.config.grid_points_mm()[:4], max_presses=2,
                      confidence=0.95, wait_item_timeout_s=0.01, fault_file=w / "FAULT",
                      bounds=StepBounds(arm_call_s=0.3, grab_s=0.6, gate_request_s=0.1))
    journal = Journal.open(w / "journal.jsonl")
    cell = Cell(camera=HungCamera(), arm=arm, gate=FakeGate(), model=GreyModel(), journal=journal,
                notifier=notifier, scene=scene, evidence_factory=lambda: GreyEvidence(max_presses=2), items=pieces,
                log=lambda m: None)
    pings: list[float] = []
    done = threading.Event()

    def listen():
        while not done.is_set():
            try:
                if server.recv(64) == b"WATCHDOG=1":
                    pings.append(time.monotonic())
            except socket.timeout:
                pass

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    notifier.watchdog()
    cell.run(max_items=1, stop_when=lambda: cell.fault is not None)
    notifier.watchdog()
    time.sleep(0.05)
    done.set()
    listener.join()
    journal.close()
    server.close()
    problems: list[str] = []
    a = audit(w / "journal.jsonl", {"piece-0000": "denim"})
    problems += a["problems"]
    _check(problems, cell.fault is not None and "failed twice" in cell.fault, f"fault: {cell.fault!r}")
    _check(problems, a["outcomes"].get("rejected_fault") == 1, f"outcomes {dict(a['outcomes'])}")
    gaps = [b - a_ for a_, b in zip(pings, pings[1:])]
    largest = max(gaps) if gaps else float("inf")
    _check(problems, largest < watchdog_s / 2, f"largest gap between watchdog pings {largest:.2f} s "
                                               f"(watchdog {watchdog_s} s)")
    return f"camera fault latched, piece rejected; {len(pings)} pings, largest gap {largest:.2f} s", problems


def watchdog_gate_behind_heartbeat(w: Path):
    """A silent gate (every frame the host sends is lost) with a heartbeat on the wire when the
    sort goes out. The budget counted a request as (retries + 1) x timeout_s, but stop-and-wait
    puts the sort behind the heartbeat's try first, and a failed to-reject then waits for the
    heartbeat thread: both must stay within the bounds the watchdog budget leases
    (gate_client.request_worst_case_s / to_reject_worst_case_s)."""
    import time

    from vs2t_edge.firmware_bridge.gate_client import (GateClient, GateClientError, request_worst_case_s,
                                                      to_reject_worst_case_s)
    from vs2t_edge.firmware_bridge.mcu_sim import start_simulated_gate
    from vs2t_edge.sim.fault_rig import _check

    timeout_s, retries, heartbeat_s = 0.3, 1, 0.1
    problems: list[str] = []
    _, sim = start_simulated_gate(move_time_ms=20)
    client = GateClient(sim.device_path, timeout_s=timeout_s, retries=retries, heartbeat_period_s=heartbeat_s)
    try:
        client.connect()
        sim.faults.drop_rx = 10**9
        waits = {}
        for what, call in (("sort", lambda: client.sort(3)), ("to_reject", client.to_reject)):
            deadline = time.monotonic() + 2
            while client._lock.acquire(blocking=False) and time.monotonic() < deadline:
                client._lock.release()  # not yet: wait until the heartbeat holds the line
                time.sleep(0.001)
            start = time.monotonic()
            try:
                call()
            except GateClientError:
                pass
            waits[what] = time.monotonic() - start
    finally:
        client.disconnect()
        sim.stop()
    bound = {"sort": request_worst_case_s(timeout_s, retries, heartbeat_s),
             "to_reject": to_reject_worst_case_s(timeout_s, retries, heartbeat_s)}
    for what, took in waits.items():
        _check(problems, took <= bound[what], f"{what} waited {took:.2f} s, past its bound {bound[what]:.2f} s")
    _check(problems, waits["sort"] > (retries + 1) * timeout_s,
           f"the sort did not wait behind the heartbeat ({waits['sort']:.2f} s): the row proves nothing")
    return (f"sort behind a heartbeat {waits['sort']:.2f} s (bound {bound['sort']:.2f} s, the old count "
            f"{(retries + 1) * timeout_s:.2f} s); failed to-reject {waits['to_reject']:.2f} s "
            f"(bound {bound['to_reject']:.2f} s)"), problems

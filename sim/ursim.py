"""A loopback UR controller that the real ``ur_rtde`` client talks to, for the press scene only.

What it speaks (see docs/arm.md for the full list and what is *not* emulated):

* RTDE protocol v2 on ``rtde_port`` (30004), one session per client (``sim/ursim_rtde.py``).
* The dashboard server on ``dashboard_port`` (29999): the line commands ur_rtde and our arm
  backend send (version, serial number, robot/safety mode, program state, stop, unlock
  protective stop, close safety popup, power on, brake release, quit).
* The script ports (30001-30003): ur_rtde uploads its control script there. The script is
  accepted and *not interpreted*: :class:`vs2t_edge.sim.ursim_model.ControllerModel`, which
  URSim is, plays its role (the register handshake) and holds the press physics.

This module is the sockets, the threads and the lifecycle. The real ur_rtde client needs the
simulator in another process: ``sim/ursim_process.py`` (URSimProcess); timing presses with that
client is ``sim/ursim_bench.py``.

ur_rtde hardcodes the RTDE port (30004) and the script port (30003) of RTDEControlInterface and
RTDEReceiveInterface, so a simulator always listens on those ports; to let several simulators
(or test processes) coexist, each one may bind its own loopback address (127.x.y.z, the whole
127/8 is loopback on Linux) - see :func:`free_loopback_host` - and a lock file per address
serialises two simulators that want the same address.
"""

from __future__ import annotations

import fcntl
import ipaddress
import os
import random
import socket
import tempfile
import threading
import time
from typing import Callable

from vs2t_edge.sim.ursim_model import (
    ROBOT_MODE,
    RUNTIME_PLAYING,
    RUNTIME_STOPPED,
    SAFETY_MODE,
    ControllerModel,
    PressScene,
)
from vs2t_edge.sim.ursim_rtde import RTDESession, close_socket

SCRIPT_PORTS = (30001, 30002, 30003)


def check_loopback(host: str) -> None:
    if not ipaddress.ip_address(host).is_loopback:
        raise ValueError(f"URSim serves loopback only, not {host}")


def free_loopback_host() -> str:
    """A 127.x.y.z address whose RTDE port is free, so a simulator can run beside others."""
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    for _ in range(200):
        host = f"127.{rng.randint(1, 254)}.{rng.randint(0, 254)}.{rng.randint(1, 254)}"
        probe = socket.socket()
        try:
            probe.bind((host, 30004))
            return host
        except OSError:
            continue
        finally:
            probe.close()
    raise RuntimeError("no free loopback address for a UR simulator")


class URSim(ControllerModel):
    """The simulated controller on the wire (its state and physics are the ControllerModel it
    is). Use as a context manager; ``host`` must be a loopback address."""

    def __init__(self, scene: PressScene | None = None, *, host: str = "127.0.0.1",
                 rtde_port: int = 30004, dashboard_port: int = 29999,
                 script_ports: tuple[int, ...] = SCRIPT_PORTS,
                 controller_version: tuple[int, int, int, int] = (5, 11, 6, 108549),
                 tick_hz: float = 250.0, lock_timeout_s: float = 120.0,
                 unlock_delay_s: float = 0.0) -> None:
        check_loopback(host)
        super().__init__(scene)
        self.host = host
        self.rtde_port, self.dashboard_port, self.script_ports = rtde_port, dashboard_port, script_ports
        self.controller_version = controller_version
        self.tick_s = 1.0 / tick_hz
        self.lock_timeout_s = lock_timeout_s
        self.unlock_delay_s = unlock_delay_s  # the real robot wants 5 s before unlocking
        self._threads: list[threading.Thread] = []
        self._listeners: dict[int, socket.socket] = {}
        self._conns: set[socket.socket] = set()
        self._running = threading.Event()
        self._lockfile = None

    # --- fault injection on the wire ------------------------------------------------------

    def drop_connections(self, refuse_s: float = 1.0) -> None:
        """Cut every client connection and refuse new ones for ``refuse_s``.

        With refuse_s = 0 the real ur_rtde 1.6.5 client's own reconnect succeeds at once and
        then loops (reconnecting again after every success) until it crashes its process with a
        segfault - a client bug, see docs/arm.md. Keep a refusal window unless that is the test.
        """
        if refuse_s > 0:
            self._close_listeners()
            timer = threading.Timer(refuse_s, self._open_listeners)
            timer.daemon = True
            timer.start()
        with self._lock:
            conns = list(self._conns)
            self._conns.clear()
        for conn in conns:
            close_socket(conn)
        self._record("drops", time.monotonic())

    # --- the physics clock -----------------------------------------------------------------

    def _tick_loop(self) -> None:
        last = time.monotonic()
        while self._running.is_set():
            time.sleep(self.tick_s)
            now = time.monotonic()
            with self._lock:
                self._physics_step(now - last)
                self._controller_step(now)
            last = now

    # --- servers -------------------------------------------------------------------------

    def _open_listeners(self) -> None:
        if not self._running.is_set():
            return
        for port, handler in self._port_handlers().items():
            if port in self._listeners:
                continue
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host, port))
            sock.listen(8)
            self._listeners[port] = sock
            self._spawn(self._accept_loop, sock, handler, name=f"ursim-accept-{port}")

    def _close_listeners(self) -> None:
        listeners, self._listeners = self._listeners, {}
        for sock in listeners.values():
            close_socket(sock)

    def _port_handlers(self) -> dict[int, Callable[[socket.socket], None]]:
        handlers: dict[int, Callable[[socket.socket], None]] = {
            self.rtde_port: self._serve_rtde, self.dashboard_port: self._serve_dashboard}
        for port in self.script_ports:
            handlers[port] = self._serve_script
        return handlers

    def _spawn(self, target, *args, name: str) -> None:
        t = threading.Thread(target=target, args=args, daemon=True, name=name)
        t.start()
        self._threads.append(t)

    def _accept_loop(self, sock: socket.socket, handler) -> None:
        while self._running.is_set():
            try:
                conn, _ = sock.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._conns.add(conn)
            self._spawn(self._serve_and_forget, handler, conn, name="ursim-conn")

    def _serve_and_forget(self, handler, conn: socket.socket) -> None:
        try:
            handler(conn)
        finally:
            with self._lock:
                self._conns.discard(conn)
            close_socket(conn)

    def _serve_rtde(self, conn: socket.socket) -> None:
        self._record("rtde_connections", time.monotonic())
        RTDESession(self, conn).serve()

    def _serve_script(self, conn: socket.socket) -> None:
        """Accept a URScript program: not interpreted, only 'a program is now running'."""
        conn.settimeout(0.05)
        buf = b""
        while self._running.is_set():
            try:
                chunk = conn.recv(65536)
                if not chunk:
                    break
                buf += chunk
                continue
            except socket.timeout:
                pass
            except OSError:
                break
            if buf:
                # A quiet gap after data: one program (or one line of script) has arrived.
                self._record("scripts", buf.decode(errors="replace"))
                if b"def " in buf:  # a program; a secondary one ("sec") or a single line is not
                    self._program_started()
                buf = b""
        if buf:
            self._record("scripts", buf.decode(errors="replace"))
            if b"def " in buf:
                self._program_started()

    def _dashboard_answer(self, line: str) -> str | None:
        cmd = line.strip()
        low = cmd.lower()
        with self._lock:
            safety = {v: k for k, v in SAFETY_MODE.items()}[self.safety_mode]
            robot = {v: k for k, v in ROBOT_MODE.items()}[self.robot_mode]
            playing = self.runtime_state == RUNTIME_PLAYING
            if low == "polyscopeversion":
                major, minor, bugfix, build = self.controller_version
                return f"URSoftware {major}.{minor}.{bugfix}.{build} (simulated)"
            if low == "get serial number":
                return "20185500001"
            if low == "get robot model":
                return "UR5"
            if low == "robotmode":
                return f"Robotmode: {robot}"
            if low == "safetymode":
                return f"Safetymode: {safety}"
            if low == "safetystatus":
                return f"Safetystatus: {safety}"
            if low == "programstate":
                return ("PLAYING" if playing else "STOPPED") + " <unnamed>"
            if low == "running":
                return f"Program running: {'true' if playing else 'false'}"
            if low == "is in remote control":
                return "true"
            if low == "stop":
                self.runtime_state = RUNTIME_STOPPED
                self._force_mode = None
                self._motion = None
                return "Stopped"
            if low == "unlock protective stop":
                if self.safety_mode != SAFETY_MODE["PROTECTIVE_STOP"]:
                    return "Protective stop releasing"
                if time.monotonic() - self.safety_stop_at < self.unlock_delay_s:
                    return ("Cannot unlock protective stop until 5s after occurrence. "
                            "Always inspect cause of protective stop before unlocking")
                self.safety_mode = SAFETY_MODE["NORMAL"]
                return "Protective stop releasing"
            if low == "close safety popup":
                return "closing safety popup"
            if low == "close popup":
                return "closing popup"
            if low == "power on":
                if self.safety_mode == SAFETY_MODE["NORMAL"]:
                    self.robot_mode = ROBOT_MODE["IDLE"]
                return "Powering on"
            if low == "brake release":
                if self.safety_mode == SAFETY_MODE["NORMAL"] and self.robot_mode >= ROBOT_MODE["POWER_ON"]:
                    self.robot_mode = ROBOT_MODE["RUNNING"]
                return "Brake releasing"
            if low == "power off":
                self.robot_mode = ROBOT_MODE["POWER_OFF"]
                self.runtime_state = RUNTIME_STOPPED
                return "Powering off"
            if low.startswith("addtolog"):
                return "Added log message"
            if low == "quit":
                return None
        return f"could not understand: '{cmd}'"

    def _serve_dashboard(self, conn: socket.socket) -> None:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        buf = b""
        while self._running.is_set():
            try:
                chunk = conn.recv(4096)
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                self._record("dashboard", line.decode(errors="replace"))
                answer = self._dashboard_answer(line.decode(errors="replace"))
                if answer is None:
                    conn.sendall(b"Disconnected\n")
                    return
                conn.sendall(answer.encode() + b"\n")

    # --- lifecycle -----------------------------------------------------------------------

    def start(self) -> "URSim":
        lock_path = os.path.join(tempfile.gettempdir(), f"vs2t-ursim-{self.host}.lock")
        self._lockfile = open(lock_path, "w")
        deadline = time.monotonic() + self.lock_timeout_s
        while True:
            try:
                fcntl.flock(self._lockfile, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    self._lockfile.close()
                    raise RuntimeError(f"another UR simulator holds {self.host} (lock {lock_path})")
                time.sleep(0.1)
        self._running.set()
        try:
            self._open_listeners()
        except OSError as exc:
            self.stop()
            raise RuntimeError(f"UR simulator cannot listen on {self.host}: {exc}") from exc
        self._spawn(self._tick_loop, name="ursim-tick")
        return self

    def stop(self) -> None:
        self._running.clear()
        self._close_listeners()
        with self._lock:
            conns = list(self._conns)
            self._conns.clear()
        for conn in conns:
            close_socket(conn)
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()
        if self._lockfile is not None:
            if self.host != "127.0.0.1":
                # Per-simulator addresses are used once; do not leave a lock file per test run.
                try:
                    os.unlink(self._lockfile.name)
                except OSError:
                    pass
            fcntl.flock(self._lockfile, fcntl.LOCK_UN)
            self._lockfile.close()
            self._lockfile = None

    def __enter__(self) -> "URSim":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _main() -> None:  # pragma: no cover - manual use: python -m vs2t_edge.sim.ursim
    import argparse

    parser = argparse.ArgumentParser(description="loopback UR simulator for the press scene")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--bench", type=int, metavar="N", help="time N presses with the real ur_rtde client")
    parser.add_argument("--json", help="with --bench: write the numbers here")
    args = parser.parse_args()
    if args.bench:
        from vs2t_edge.sim.ursim_bench import bench_press

        bench_press(args.bench, args.json)
        return
    with URSim(host=args.host) as sim:
        print(f"UR simulator on {sim.host} (RTDE {sim.rtde_port}, dashboard {sim.dashboard_port}); Ctrl-C stops")
        try:
            while True:
                time.sleep(1)
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":  # pragma: no cover
    _main()

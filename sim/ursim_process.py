"""The loopback UR simulator in its own process, for the real ur_rtde client.

:class:`URSimProcess` starts ``python -m vs2t_edge.sim.ursim_process --serve-stdio SPEC`` and
forwards fault injection to the :class:`vs2t_edge.sim.ursim.URSim` running there
(:func:`_serve_stdio`), as JSON lines on the child's stdin and stdout.
"""

from __future__ import annotations

import tempfile
import threading
from dataclasses import asdict

from vs2t_edge.sim.ursim import URSim, check_loopback
from vs2t_edge.sim.ursim_model import PressScene


class URSimProcess:
    """Runs :class:`URSim` in a child interpreter and forwards fault injection to it.

    The real ur_rtde client must not share a process with the simulator: its pybind11
    constructors (RTDEControlInterface, RTDEReceiveInterface) keep the GIL while they block on
    the handshake, so an in-process simulator thread could never answer them. The child is
    ``python -m vs2t_edge.sim.ursim_process --serve-stdio``; calls travel as JSON lines on its stdin and
    stdout, so any script can use this without a ``__main__`` guard.
    """

    _ALLOWED = {"trigger_protective_stop", "trigger_emergency_stop", "release_emergency_stop",
                "drop_connections", "snapshot", "set_faults", "set_scene", "get_log", "clear_log", "reset",
                "contact_force_at"}

    def __init__(self, scene: PressScene | None = None, *, host: str = "127.0.0.1",
                 start_timeout_s: float = 140.0, **kwargs) -> None:
        check_loopback(host)
        self.scene = scene or PressScene()
        self.host = host
        self._kwargs = kwargs
        # Longer than the child's wait for another simulator's lock on the same address.
        self._start_timeout_s = start_timeout_s
        self._proc = None
        self._call_lock = threading.Lock()

    def start(self) -> "URSimProcess":
        import json
        import subprocess
        import sys

        spec = {"scene": asdict(self.scene), "host": self.host, "kwargs": self._kwargs}
        # The child's stderr goes to a file, not a pipe nobody drains (a full pipe would stall it).
        self._stderr = tempfile.TemporaryFile(mode="w+")
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "vs2t_edge.sim.ursim_process", "--serve-stdio", json.dumps(spec)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._stderr, text=True, bufsize=1)
        status, detail = self._read_reply(self._start_timeout_s)
        if status != "ready":
            self.stop()
            raise RuntimeError(f"UR simulator process failed to start: {detail}")
        return self

    def _read_reply(self, timeout_s: float):
        import json
        import select

        ready, _, _ = select.select([self._proc.stdout], [], [], timeout_s)
        line = self._proc.stdout.readline() if ready else ""
        if not line:
            return "error", f"no answer from the simulator process {self.stderr_text()[-2000:]}".strip()
        reply = json.loads(line)
        return reply["status"], reply.get("value")

    def call(self, method: str, *args, **kwargs):
        import json

        if method not in self._ALLOWED:
            raise AttributeError(method)
        with self._call_lock:
            if self._proc is None or self._proc.poll() is not None:
                raise RuntimeError("UR simulator is not running")
            self._proc.stdin.write(json.dumps({"method": method, "args": args, "kwargs": kwargs}) + "\n")
            self._proc.stdin.flush()
            status, value = self._read_reply(10.0)
        if status != "ok":
            raise RuntimeError(f"UR simulator {method}: {value}")
        return value

    def stderr_text(self) -> str:
        """What the child wrote on stderr (tracebacks of simulator threads end up here)."""
        if getattr(self, "_stderr", None) is None:
            return ""
        self._stderr.flush()
        self._stderr.seek(0)
        return self._stderr.read()

    def __getattr__(self, name: str):
        if name in URSimProcess._ALLOWED:
            return lambda *a, **k: self.call(name, *a, **k)
        raise AttributeError(name)

    def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()  # EOF: the child stops its servers and exits
        except OSError:
            pass
        try:
            proc.wait(timeout=5.0)
        except Exception:
            proc.terminate()
            try:
                proc.wait(timeout=2.0)
            except Exception:
                proc.kill()
                proc.wait()
        try:
            proc.stdout.close()
        except OSError:
            pass

    def __enter__(self) -> "URSimProcess":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _serve_stdio(spec_json: str) -> None:
    """The child side of URSimProcess: one JSON request per stdin line, one reply per line."""
    import json
    import sys

    spec = json.loads(spec_json)
    scene = PressScene(**{k: tuple(v) if isinstance(v, list) else v for k, v in spec["scene"].items()})
    out = sys.stdout
    sys.stdout = sys.stderr  # nothing else may write on the reply channel

    def reply(status: str, value=None) -> None:
        out.write(json.dumps({"status": status, "value": value}) + "\n")
        out.flush()

    try:
        sim = URSim(scene, host=spec["host"], **spec["kwargs"]).start()
    except Exception as exc:
        reply("error", f"{type(exc).__name__}: {exc}")
        return
    reply("ready", sim.host)
    try:
        for line in sys.stdin:
            request = json.loads(line)
            method = request["method"]
            if method not in URSimProcess._ALLOWED:
                reply("error", f"unknown method {method}")
                continue
            try:
                reply("ok", getattr(sim, method)(*request["args"], **request["kwargs"]))
            except Exception as exc:
                reply("error", f"{type(exc).__name__}: {exc}")
    finally:
        sim.stop()


if __name__ == "__main__":  # pragma: no cover - the child of URSimProcess
    import sys

    if len(sys.argv) == 3 and sys.argv[1] == "--serve-stdio":
        _serve_stdio(sys.argv[2])
    else:
        print("usage: python -m vs2t_edge.sim.ursim_process --serve-stdio SPEC_JSON", file=sys.stderr)
        sys.exit(2)

"""The live arm in a supervised worker process: :class:`IsolatedURArm`, as the service runs it.

ur_rtde 1.6.5 can crash its own process (docs/arm.md); here that process is a worker
(``python -m vs2t_edge.runtime.arm_isolated --worker``) running :class:`URArm`, and the cell
loses one step, not itself. :func:`isolated_call_bound_s` is the longest one call may take;
runtime/budget.py counts it in the watchdog budget.
"""

from __future__ import annotations

from dataclasses import asdict

from vs2t_edge.runtime.arm import ArmConfig, ArmConfigError
from vs2t_edge.runtime.arm_ur import URArm
from vs2t_edge.runtime.devices import (
    ArmConnectionError,
    ArmError,
    ArmSafetyStop,
    NotConnectedError,
    PressFailed,
    PressResult,
)

_WORKER_METHODS = ("connect", "disconnect", "move_above", "press", "retract", "stop", "clear_protective_stop")
_ERRORS = {cls.__name__: cls for cls in (ArmError, ArmConnectionError, ArmSafetyStop, PressFailed,
                                         NotConnectedError, ArmConfigError, ValueError)}


WORKER_START_TIMEOUT_S = 30.0  # IsolatedURArm: a new worker process starting (runtime/budget.py counts it)


def isolated_call_bound_s(c: ArmConfig) -> float:
    """The longest one IsolatedURArm call may take before the worker is ended and the call fails:
    a move or press plus every reconnect it may do. runtime/budget.py's watchdog budget uses it."""
    backoff = sum(c.reconnect_backoff_s * 2 ** i for i in range(c.reconnect_attempts))
    return (c.move_timeout_s + c.press_timeout_s + 3 * c.command_timeout_s + backoff
            + c.client_reconnect_grace_s + 15.0 * (c.reconnect_attempts + 1))


class IsolatedURArm:
    """:class:`URArm` in a worker process, so that a crash of the ur_rtde client costs one
    step and not the cell.

    ur_rtde 1.6.5 segfaults its process when the robot drops the link and accepts it again at
    once (its own reconnect loops; docs/arm.md). Here the worker dies instead: the call raises
    ``ArmConnectionError(kind="connection_lost")`` naming the exit code, and the next call starts
    a new worker and connects it (``worker_restarts`` counts them). Calls travel as JSON lines
    over two private pipes; the client's own stdout chatter goes to a log file.
    """

    def __init__(self, config: ArmConfig | None = None, *, start_timeout_s: float = WORKER_START_TIMEOUT_S) -> None:
        self.config = (config or ArmConfig()).validate()
        self.start_timeout_s = start_timeout_s
        self.worker_restarts = 0
        self.worker_exit_codes: list[int] = []
        self._proc = None
        self._req = None
        self._rep = None
        self._log = None
        self._wanted = False  # connect() was called and disconnect() not yet

    def _call_bound_s(self) -> float:
        return isolated_call_bound_s(self.config)

    def _spawn(self) -> None:
        import json
        import os
        import subprocess
        import sys
        import tempfile

        req_r, req_w = os.pipe()
        rep_r, rep_w = os.pipe()
        self._log = tempfile.TemporaryFile(mode="w+")
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "vs2t_edge.runtime.arm_isolated", "--worker", str(req_r), str(rep_w),
             json.dumps(self.config.to_dict())],
            pass_fds=(req_r, rep_w), stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log)
        os.close(req_r)
        os.close(rep_w)
        self._req = os.fdopen(req_w, "w", buffering=1)
        self._rep = os.fdopen(rep_r, "r")

    def _reap(self) -> None:
        proc, self._proc = self._proc, None
        for stream in (self._req, self._rep):
            try:
                if stream is not None:
                    stream.close()
            except OSError:
                pass
        self._req = self._rep = None
        if proc is not None:
            try:
                proc.wait(timeout=5.0)
            except Exception:
                proc.kill()
                proc.wait()
            self.worker_exit_codes.append(proc.returncode)

    def worker_log(self) -> str:
        if self._log is None:
            return ""
        self._log.flush()
        self._log.seek(0)
        return self._log.read()

    def _send(self, method: str, args: tuple, timeout_s: float):
        import json
        import select

        hung = False
        try:
            self._req.write(json.dumps({"method": method, "args": list(args)}) + "\n")
            self._req.flush()
            ready, _, _ = select.select([self._rep], [], [], timeout_s)
            hung = not ready
            line = self._rep.readline() if ready else ""
        except (OSError, ValueError):
            line = ""
        if not line:
            if hung and self._proc is not None:
                self._proc.kill()  # past every bound of its own: end it
            self._reap()  # waits for the exit (a crash closes the pipe a moment before it ends)
            code = self.worker_exit_codes[-1] if self.worker_exit_codes else None
            raise ArmConnectionError(f"arm worker {'hung' if hung else 'died'} during {method} "
                                     f"(exit code {code}); it is restarted on the next call",
                                     device="arm", kind="connection_lost")
        reply = json.loads(line)
        if reply["status"] == "ok":
            return reply.get("value")
        cls = _ERRORS.get(reply["type"], ArmError)
        if issubclass(cls, ArmError) or cls is NotConnectedError:
            err = cls(reply["message"], device="arm", kind=reply.get("kind", ""))
            if reply.get("reconnected"):
                err.reconnected = True
        else:
            err = cls(reply["message"])
        raise err

    def _call(self, method: str, *args):
        if self._proc is None or self._proc.poll() is not None:
            if self._proc is not None:
                self._reap()
            if method in ("stop", "disconnect"):
                return None  # nothing to stop: the worker is gone and its robot link with it
            if not self._wanted and method != "connect":
                raise NotConnectedError("arm used before connect()", device="arm")
            self._spawn()
            if self.worker_exit_codes:
                self.worker_restarts += 1
            self._send("connect", (), self.start_timeout_s + self._call_bound_s())
            if method == "connect":
                return None
        return self._send(method, args, self._call_bound_s())

    def connect(self) -> None:
        self._wanted = True
        self._call("connect")

    def disconnect(self) -> None:
        self._wanted = False
        try:
            self._call("disconnect")
        except ArmError:
            pass
        if self._proc is not None:
            try:
                self._req.close()  # EOF: the worker leaves its loop and exits
            except OSError:
                pass
            self._reap()

    def move_above(self, x_mm: float, y_mm: float) -> None:
        self.config.surface_pose(x_mm, y_mm)  # off the piece: refused here, no worker needed
        self._call("move_above", x_mm, y_mm)

    def press(self) -> PressResult:
        d = self._call("press")
        d["tcp_pose"] = tuple(d["tcp_pose"])
        return PressResult(**d)

    def retract(self) -> None:
        self._call("retract")

    def stop(self) -> None:
        if self._proc is None or self._proc.poll() is not None:
            return  # no worker, no link: nothing to command
        try:
            self._send("stop", (), 5.0)  # stop is quick or the worker is hung (then it is ended)
        except Exception:  # must not raise: the fault paths call it
            pass

    def clear_protective_stop(self) -> None:
        self._call("clear_protective_stop")

    def __enter__(self) -> "IsolatedURArm":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self.disconnect()


def _worker_main(req_fd: int, rep_fd: int, config_json: str) -> None:
    import json
    import os

    rep = os.fdopen(rep_fd, "w", buffering=1)
    arm = URArm(ArmConfig.from_dict(json.loads(config_json)))

    def reply(payload: dict) -> None:
        rep.write(json.dumps(payload, default=float) + "\n")
        rep.flush()

    try:
        with os.fdopen(req_fd, "r") as req:
            for line in req:
                request = json.loads(line)
                method = request["method"]
                if method not in _WORKER_METHODS:
                    reply({"status": "error", "type": "ArmError", "message": f"unknown method {method}"})
                    continue
                try:
                    value = getattr(arm, method)(*request["args"])
                    if isinstance(value, PressResult):
                        value = asdict(value)
                    reply({"status": "ok", "value": value})
                except Exception as exc:
                    reply({"status": "error", "type": type(exc).__name__, "message": str(exc),
                           "kind": getattr(exc, "kind", ""), "reconnected": getattr(exc, "reconnected", False)})
    finally:
        arm.stop()
        arm.disconnect()


if __name__ == "__main__":  # the worker of IsolatedURArm: python -m vs2t_edge.runtime.arm_isolated --worker R W CONFIG
    import sys

    if len(sys.argv) == 5 and sys.argv[1] == "--worker":
        _worker_main(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])
    else:
        print("usage: python -m vs2t_edge.runtime.arm_isolated --worker REQ_FD REP_FD CONFIG_JSON", file=sys.stderr)
        sys.exit(2)

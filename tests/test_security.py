"""Security checks: no shell built from input, no listening socket, safe file permissions."""

from __future__ import annotations

import ast
import json
import os
import re
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vs2t_edge.sim import faults_process

PKG = Path(faults_process.__file__).resolve().parents[1]
HERE = Path(__file__).parent

# --- no shell built from input ------------------------------------------------------------------

SCANNED_FOLDERS = ("runtime", "firmware_bridge", "sim", "train", "export", "vs2t_edge")
SHELLS = {"sh", "bash", "dash", "zsh", "ksh", "ash", "busybox"}  # argv[0] of a `SHELL -c TEXT` list
ALWAYS_A_SHELL = {"os.system", "os.popen", "subprocess.getoutput", "subprocess.getstatusoutput",
                  "asyncio.create_subprocess_shell", "platform.popen"}
SUBPROCESS_CALLS = {f"subprocess.{name}" for name in ("run", "call", "check_call", "check_output", "Popen")}


def _import_names(tree: ast.AST) -> dict[str, str]:
    """Local name -> what it was imported as (`import subprocess as sp`, `from os import system`)."""
    names: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                names[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for a in node.names:
                names[a.asname or a.name] = f"{node.module}.{a.name}"
    return names


def _assignments(scope: ast.AST) -> dict[str, list[ast.expr]]:
    out: dict[str, list[ast.expr]] = {}
    for node in ast.walk(scope):
        if isinstance(node, ast.Assign):
            for target in node.targets:
                if isinstance(target, ast.Name):
                    out.setdefault(target.id, []).append(node.value)
        elif isinstance(node, (ast.AnnAssign, ast.AugAssign)) and isinstance(node.target, ast.Name) and node.value:
            out.setdefault(node.target.id, []).append(node.value)  # `cmd += " --x"` is text too
    return out


class _ShellFinder(ast.NodeVisitor):
    """Every call that runs a shell, or a subprocess whose command is (or may be) one string."""

    def __init__(self, tree: ast.AST) -> None:
        self.imports = _import_names(tree)
        self.scopes = [_assignments(tree)]
        self.hits: list[tuple[int, str]] = []

    def dotted(self, node: ast.AST) -> str:
        parts = []
        while isinstance(node, ast.Attribute):
            parts.append(node.attr)
            node = node.value
        if not isinstance(node, ast.Name):
            return ""
        parts.append(self.imports.get(node.id, node.id))
        return ".".join(reversed(parts))

    def is_text(self, node: ast.AST) -> bool:
        if isinstance(node, ast.Constant):
            return isinstance(node.value, (str, bytes))
        if isinstance(node, ast.JoinedStr):
            return True
        if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Mod)):
            return self.is_text(node.left) or self.is_text(node.right)
        if isinstance(node, ast.Call):
            func = node.func
            if isinstance(func, ast.Attribute) and func.attr in ("format", "join") and self.is_text(func.value):
                return True  # "...".format(...), " ".join(argv)
            return self.dotted(func) in ("str", "shlex.join", "shlex.quote")
        return False

    def command_problem(self, cmd: ast.AST | None) -> str | None:
        """None when `cmd` is visibly an argument list (the only form allowed)."""
        if isinstance(cmd, (ast.List, ast.Tuple, ast.ListComp)):
            return None
        if cmd is None or isinstance(cmd, ast.Starred):
            return "cannot tell the command is an argument list"
        if self.is_text(cmd):
            return "the command is one string"
        if isinstance(cmd, ast.Name):
            values = next((s[cmd.id] for s in reversed(self.scopes) if cmd.id in s), None)
            if values is None:
                return f"cannot tell `{cmd.id}` is an argument list (a parameter or a global from elsewhere)"
            if any(self.is_text(v) for v in values):
                return f"`{cmd.id}` is assigned a string"
            if all(isinstance(v, (ast.List, ast.Tuple, ast.ListComp)) or
                   (isinstance(v, ast.BinOp) and isinstance(v.op, ast.Add)) for v in values):
                return None
            return f"cannot tell `{cmd.id}` is an argument list"
        return "cannot tell the command is an argument list"

    def visit_FunctionDef(self, node: ast.AST) -> None:
        self.scopes.append(_assignments(node))
        self.generic_visit(node)
        self.scopes.pop()

    visit_AsyncFunctionDef = visit_FunctionDef
    visit_Lambda = visit_FunctionDef

    def visit_List(self, node: ast.List | ast.Tuple) -> None:
        words = [e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
        if words and node.elts and isinstance(node.elts[0], ast.Constant) and "-c" in words[1:] \
                and Path(str(node.elts[0].value)).name in SHELLS:
            self.hits.append((node.lineno, f"[{words[0]!r}, '-c', ...]: a shell running a text"))
        self.generic_visit(node)

    visit_Tuple = visit_List

    def visit_Call(self, node: ast.Call) -> None:
        name = self.dotted(node.func)
        for kw in node.keywords:
            if kw.arg == "shell" and not (isinstance(kw.value, ast.Constant) and not kw.value.value):
                self.hits.append((node.lineno, f"{name or 'call'}(shell={ast.unparse(kw.value)})"))
        if name in ALWAYS_A_SHELL:
            self.hits.append((node.lineno, f"{name}(): always a shell"))
        elif name.startswith(("os.exec", "os.spawn")):
            self.hits.append((node.lineno, f"{name}(): the daemon has no reason to exec or spawn by hand"))
        elif name in SUBPROCESS_CALLS:
            cmd = node.args[0] if node.args else next((k.value for k in node.keywords if k.arg == "args"), None)
            problem = self.command_problem(cmd)
            if problem:
                self.hits.append((node.lineno, f"{name}(): {problem}"))
        self.generic_visit(node)


def shell_invocations(source: str, name: str = "<source>") -> list[str]:
    """`name:line: what` for every shell invocation in a Python source (calls, not text in strings)."""
    try:
        tree = ast.parse(source, filename=name)
    except SyntaxError as exc:
        return [f"{name}:{exc.lineno}: cannot parse, so cannot be checked"]
    finder = _ShellFinder(tree)
    finder.visit(tree)
    return [f"{name}:{line}: {what}" for line, what in sorted(finder.hits)]


def test_no_shell_invocation_in_any_package_folder():
    files = sorted(p for d in SCANNED_FOLDERS for p in (PKG / d).rglob("*.py"))
    assert {p.relative_to(PKG).parts[0] for p in files} == set(SCANNED_FOLDERS)  # every folder was found
    hits = [h for p in files for h in shell_invocations(p.read_text(encoding="utf-8"), str(p.relative_to(PKG)))]
    assert not hits, "\n".join(hits)


@pytest.mark.parametrize("source", [
    "import os\nos.system('ls ' + name)",
    "import os\nos.popen(f'cat {path}')",
    "from os import system\nsystem(cmd)",
    "import subprocess\nsubprocess.run(cmd, shell=True)",
    "import subprocess as sp\nsp.Popen(['ls'], shell=use_shell)",
    "import subprocess\nsubprocess.run(['sh', '-c', 'ls ' + name])",
    "import subprocess\nsubprocess.check_call(('/bin/bash', '-c', text))",
    "import subprocess\nsubprocess.check_output('ls -l')",
    "import subprocess\nsubprocess.call(f'ls {name}')",
    "import subprocess\nsubprocess.run('git {}'.format(arg))",
    "import subprocess\ndef f(path):\n    cmd = 'cat ' + path\n    return subprocess.run(cmd)",
    "import subprocess\ndef f(cmd):\n    return subprocess.run(cmd)",
    "from subprocess import run\nrun(args=' '.join(argv))",
    "import subprocess\nsubprocess.getoutput('ls')",
    "import os\nos.execvp('vi', ['vi', name])",
    "import os\nos.spawnlp(os.P_WAIT, 'ls', 'ls')",
    "import asyncio\nasyncio.create_subprocess_shell(text)",
])
def test_shell_scan_flags_each_pattern(source):
    assert shell_invocations(source), source


def test_shell_scan_lets_argument_lists_and_text_pass():
    ok = (
        "import subprocess, sys\n"
        "subprocess.run([sys.executable, '-m', 'vs2t_edge.cli', 'run'], shell=False)\n"
        "def worker(args):\n"
        "    cmd = [sys.executable, '-m', 'x', *args]\n"
        "    return subprocess.run(cmd, capture_output=True)\n"
        "subprocess.Popen(args=['git', 'rev-parse', 'HEAD'])\n"
        "PAYLOAD = \"bundle: !!python/object/apply:os.system ['touch x']\"  # text, not a call\n"
        "PY = [sys.executable, '-c', 'print(1)']  # python -c is not a shell\n"
    )
    assert shell_invocations(ok) == []


# --- no listening socket ------------------------------------------------------------------------

SO_ACCEPTCON = 0x10000  # __SO_ACCEPTCON in /proc/net/unix Flags: a listen()ing socket
TCP_LISTEN, UDP_UNCONNECTED = "0A", "07"  # st column of /proc/net/{tcp,udp}; a connected UDP socket is 01
UNIX_DGRAM = 2


def _socket_inodes(pid: int) -> set[str]:
    fd_dir = Path(f"/proc/{pid}/fd")
    inodes = set()
    for fd in fd_dir.iterdir():
        try:
            m = re.fullmatch(r"socket:\[(\d+)\]", os.readlink(fd))
        except OSError:
            continue  # closed meanwhile
        if m:
            inodes.add(m.group(1))
    return inodes


def receiving_sockets(pid: int) -> dict[str, str]:
    """The sockets of process `pid` that others can reach, inode -> what it is: TCP in LISTEN, UDP
    bound to a port and not connected (IPv4 and IPv6), Unix sockets in listen() (__SO_ACCEPTCON) and
    Unix datagram sockets bound to a name. Outgoing connections (TCP or UDP connected to a peer,
    a Unix client) and the unbound datagram socket sd_notify sends from are not listed."""
    mine = _socket_inodes(pid)
    net = Path(f"/proc/{pid}/net")  # the process's own network namespace
    found: dict[str, str] = {}
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        table = net / proto
        if not table.exists():
            continue
        for line in table.read_text().splitlines()[1:]:
            f = line.split()
            local, st, inode = f[1], f[3], f[9]
            if inode not in mine:
                continue
            if proto.startswith("tcp") and st == TCP_LISTEN:
                found[inode] = f"{proto} listening on {local}"
            elif proto.startswith("udp") and st == UDP_UNCONNECTED and not local.endswith(":0000"):
                found[inode] = f"{proto} bound to {local}"
    for line in (net / "unix").read_text().splitlines()[1:]:
        f = line.split()  # Num RefCount Protocol Flags Type St Inode [Path]
        flags, kind, inode = int(f[3], 16), int(f[4], 16), f[6]
        name = f[7] if len(f) > 7 else ""
        if inode not in mine:
            continue
        if flags & SO_ACCEPTCON:
            found[inode] = f"unix listening on {name or '(unnamed)'}"
        elif kind == UNIX_DGRAM and name:
            found[inode] = f"unix datagram bound to {name}"
    return found


def _notify_server(tmp_path: Path) -> tuple[socket.socket, str]:
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp_path / "notify.sock")
    server.bind(path)
    server.settimeout(20)
    return server, path


def test_daemon_opens_no_listening_socket(tmp_path):
    """The real daemon (tests/daemon_fake_main.py: production loop, sd_notify, journal) with a
    NOTIFY_SOCKET, so its notify socket exists while it sorts: that one is allowed, nothing else."""
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(faults_process.DAEMON_CONFIG)
    cfg.chmod(0o640)
    server, notify = _notify_server(tmp_path)
    env = dict(os.environ, NOTIFY_SOCKET=notify, PYTHONUNBUFFERED="1")
    env.pop("WATCHDOG_PID", None)
    proc = subprocess.Popen([sys.executable, str(HERE / "daemon_fake_main.py"), str(cfg)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 20
        while not server.recv(4096).startswith(b"READY=1"):
            assert time.monotonic() < deadline, "no READY=1"
        journal = tmp_path / "state" / "journal.jsonl"
        assert faults_process.wait_for(journal, lambda rs: sum(r["type"] == "final" for r in rs) >= 2)
        assert _socket_inodes(proc.pid), "the daemon holds no socket: its sd_notify socket was not seen"
        listening = receiving_sockets(proc.pid)
        assert not listening, f"the daemon listens: {listening}"
    finally:
        faults_process._stop(proc)
        server.close()


HELPER = r"""
import json, socket, sys
notify, tcp_port, udp_port, folder = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
S = socket.socket
s = {}
s["udp bound"] = S(socket.AF_INET, socket.SOCK_DGRAM)
s["udp bound"].bind(("127.0.0.1", 0))
try:
    s["udp6 bound"] = S(socket.AF_INET6, socket.SOCK_DGRAM)
    s["udp6 bound"].bind(("::1", 0))
except OSError:
    s.pop("udp6 bound").close()  # no IPv6 here
s["tcp listening"] = S(socket.AF_INET, socket.SOCK_STREAM)
s["tcp listening"].bind(("127.0.0.1", 0))
s["tcp listening"].listen()
s["unix listening"] = S(socket.AF_UNIX, socket.SOCK_STREAM)
s["unix listening"].bind(folder + "/l.sock")
s["unix listening"].listen()
s["unix abstract listening"] = S(socket.AF_UNIX, socket.SOCK_SEQPACKET)
s["unix abstract listening"].bind("\0vs2t-test-%d" % tcp_port)
s["unix abstract listening"].listen()
s["unix datagram bound"] = S(socket.AF_UNIX, socket.SOCK_DGRAM)
s["unix datagram bound"].bind(folder + "/d.sock")
# what the daemon legitimately holds: the sd_notify sender, outgoing connections
s["ok: sd_notify sender"] = S(socket.AF_UNIX, socket.SOCK_DGRAM)
s["ok: sd_notify sender"].sendto(b"READY=1", notify)
s["ok: tcp client"] = socket.create_connection(("127.0.0.1", tcp_port))
s["ok: udp client"] = S(socket.AF_INET, socket.SOCK_DGRAM)
s["ok: udp client"].connect(("127.0.0.1", udp_port))
s["ok: udp client"].send(b"x")
s["ok: unix client"] = S(socket.AF_UNIX, socket.SOCK_STREAM)
s["ok: unix client"].connect(folder + "/l.sock")
s["ok: unbound udp"] = S(socket.AF_INET, socket.SOCK_DGRAM)
print(json.dumps({k: v.fileno() for k, v in s.items()}), flush=True)
sys.stdin.read()
"""


def test_listening_check_flags_bound_and_listening_sockets_only(tmp_path):
    """The same check on a helper that listens every way it could: each is flagged, while its
    sd_notify sender and its outgoing TCP / UDP / Unix connections are not."""
    server, notify = _notify_server(tmp_path)
    tcp_server = socket.create_server(("127.0.0.1", 0))
    udp_peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp_peer.bind(("127.0.0.1", 0))
    proc = subprocess.Popen([sys.executable, "-c", HELPER, notify, str(tcp_server.getsockname()[1]),
                             str(udp_peer.getsockname()[1]), str(tmp_path)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        fds = json.loads(proc.stdout.readline())
        assert server.recv(64) == b"READY=1"
        inode = {name: re.fullmatch(r"socket:\[(\d+)\]", os.readlink(f"/proc/{proc.pid}/fd/{fd}")).group(1)
                 for name, fd in fds.items()}
        flagged = receiving_sockets(proc.pid)
        for name, ino in inode.items():
            assert (ino in flagged) == (not name.startswith("ok:")), (name, flagged.get(ino))
        assert set(flagged) == {ino for name, ino in inode.items() if not name.startswith("ok:")}, flagged
    finally:
        proc.stdin.close()
        proc.wait(timeout=20)
        for s in (server, tcp_server, udp_peer):
            s.close()


# --- safe file permissions -----------------------------------------------------------------------

def test_journal_is_not_world_writable_or_readable(tmp_path):
    from vs2t_edge.runtime.journal import Journal

    j = Journal.open(tmp_path / "state" / "journal.jsonl")
    j.append({"type": "start"})
    j.close()
    mode = stat.S_IMODE((tmp_path / "state" / "journal.jsonl").stat().st_mode)
    assert not mode & (stat.S_IWOTH | stat.S_IROTH), oct(mode)


@pytest.fixture(params=[0o000, 0o077], ids=["umask000", "umask077"])
def umask(request):
    """The daemon's modes must not depend on the umask it was started with (a hand start, a
    service manager without UMask=): the permissive one would leave FAULT deletable by anyone."""
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def _modes(*paths: Path) -> dict[str, str]:
    return {p.name: oct(stat.S_IMODE(p.stat().st_mode)) for p in paths}


def test_state_files_and_folders_are_created_0640_and_0750_whatever_the_umask(tmp_path, umask):
    from vs2t_edge.runtime.files import atomic_write as _atomic_write
    from vs2t_edge.runtime.journal import Journal

    state = tmp_path / "var" / "state"
    journal = state / "journal.jsonl"
    j = Journal.open(journal)
    j.append({"type": "start"})
    j.close()
    with open(journal, "ab") as f:
        f.write(b'{"crc":1,"rec":{"type":"pre')  # power lost mid-write: the next open keeps it aside
    j = Journal.open(journal)
    assert j.torn_bytes > 0
    j.close()
    fault = state / "FAULT"
    _atomic_write(fault, "item 3: gate jam\n")
    elsewhere = tmp_path / "run" / "cell" / "STATUS"  # a file in a folder the journal did not make
    (tmp_path / "run").mkdir(mode=0o700)
    os.chmod(tmp_path / "run", 0o700)
    _atomic_write(elsewhere, "sorting\n")
    assert _modes(state.parent, state, elsewhere.parent) == {"var": "0o750", "state": "0o750", "cell": "0o750"}
    assert _modes(journal, Path(f"{journal}.torn"), fault, elsewhere) == {
        "journal.jsonl": "0o640", "journal.jsonl.torn": "0o640", "FAULT": "0o640", "STATUS": "0o640"}
    assert oct(stat.S_IMODE((tmp_path / "run").stat().st_mode)) == "0o700"  # an existing folder is left alone


def test_a_stale_fault_tmp_does_not_pass_its_mode_on(tmp_path, umask):
    """A crash between writing FAULT.tmp and renaming it leaves the .tmp behind; the next latch
    reuses the name and must not inherit a world-writable mode from it."""
    from vs2t_edge.runtime.files import atomic_write as _atomic_write

    stale = tmp_path / "FAULT.tmp"
    stale.write_text("old\n")
    stale.chmod(0o666)
    _atomic_write(tmp_path / "FAULT", "item 4: arm stopped\n")
    assert _modes(tmp_path / "FAULT") == {"FAULT": "0o640"} and not stale.exists()


def test_world_writable_config_is_refused(tmp_path):
    from vs2t_edge.runtime.config import ConfigError, load_config

    cfg = tmp_path / "cell.yaml"
    cfg.write_text(faults_process.DAEMON_CONFIG)
    cfg.chmod(0o666)
    # anyone on the machine could point the daemon at another bundle or journal: refused, in words
    with pytest.raises(ConfigError) as err:
        load_config(cfg)
    assert "world-writable" in str(err.value) and f"chmod o-w {cfg}" in str(err.value)
    cfg.chmod(0o664)  # group-writable (an operators' group) stays allowed
    assert load_config(cfg).path == cfg


def test_world_writable_config_refused_by_the_daemon_with_exit_2(tmp_path):
    import subprocess
    import sys

    cfg = tmp_path / "cell.yaml"
    cfg.write_text(faults_process.DAEMON_CONFIG)
    cfg.chmod(0o646)
    p = subprocess.run([sys.executable, "-m", "vs2t_edge.cli", "run", "--config", str(cfg)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "chmod o-w" in p.stderr and "Traceback" not in p.stderr, p.stderr


def test_non_utf8_config_is_refused_in_words(tmp_path):
    from vs2t_edge.runtime.config import ConfigError, load_config

    cfg = tmp_path / "cell.yaml"
    cfg.write_bytes(b"bundle: \xff\xfe\n")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_config(cfg)


# --- bounded inputs: size caps and regular files only (issue 17, item 2) ---------------------------

def _in_thread(fn, timeout_s: float = 10.0, fifo: Path | None = None):
    """fn()'s exception, or "hung" if it does not return (a reader blocked on a FIFO is released
    by opening and closing a writer, so the test process can still end)."""
    import threading

    box: dict = {}

    def run():
        try:
            fn()
            box["exc"] = None
        except BaseException as exc:  # noqa: BLE001
            box["exc"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        if fifo is not None:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        return "hung"
    return box["exc"]


def test_a_fifo_config_is_refused_instead_of_hanging(tmp_path):
    from vs2t_edge.runtime.config import ConfigError, load_config

    cfg = tmp_path / "cell.yaml"
    os.mkfifo(cfg, 0o640)
    exc = _in_thread(lambda: load_config(cfg), fifo=cfg)
    assert isinstance(exc, ConfigError) and "not a regular file" in str(exc), exc


def test_a_huge_config_is_refused_before_it_is_parsed(tmp_path):
    from vs2t_edge.runtime.config import ConfigError, load_config

    cfg = tmp_path / "cell.yaml"
    # 5 MB of keys: took 73 s and 1.6 GB to reach its error; 50 MB ended in a MemoryError traceback
    cfg.write_text(faults_process.DAEMON_CONFIG + "".join(f"k{i}: [1, 2, 3]\n" for i in range(400_000)))
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match="a cell config is a few KB"):
        load_config(cfg)
    assert time.monotonic() - t0 < 1.0


def test_a_fifo_or_huge_manifest_is_refused(tmp_path):
    from vs2t_edge.runtime.bundle import BundleError, read_manifest

    manifest = tmp_path / "manifest.json"
    os.mkfifo(manifest)
    exc = _in_thread(lambda: read_manifest(tmp_path), fifo=manifest)
    assert isinstance(exc, BundleError), exc
    manifest.unlink()
    with open(manifest, "wb") as f:
        f.truncate(200 * 1024 * 1024)  # sparse
    with pytest.raises(BundleError, match="bytes, more than"):
        read_manifest(tmp_path)


def test_a_fifo_beta_override_or_fault_file_does_not_hang_the_start(tmp_path):
    from vs2t_edge.runtime.operating_point import OverrideFileError, read_beta_override
    from vs2t_edge.runtime.cell import Cell

    override = tmp_path / "b.beta_override.json"
    os.mkfifo(override)
    exc = _in_thread(lambda: read_beta_override(override), fifo=override)
    assert isinstance(exc, OverrideFileError) and "FIFO" in str(exc), exc

    fault = tmp_path / "FAULT"
    os.mkfifo(fault)

    class Scene:
        fault_file = fault

    cell = Cell.__new__(Cell)  # recover() needs only these
    cell.scene, cell.fault = Scene(), None
    cell._resolve_open_items = lambda: []
    cell.notifier = type("N", (), {"status": lambda self, s: None})()
    assert _in_thread(cell.recover, fifo=fault) is None
    assert cell.fault and "unreadable" in cell.fault  # still latched: an operator looks

"""Security checks: no shell built from input, no listening socket, safe file permissions."""

from __future__ import annotations

import os
import re
import stat
import time
from pathlib import Path

import pytest

from vs2t_edge.sim import faults

PKG = Path(faults.__file__).resolve().parents[1]


def test_no_shell_invocation_in_runtime_bridge_sim():
    bad = re.compile(r"shell\s*=\s*True|os\.system\(|os\.popen\(")
    hits = [f"{p.relative_to(PKG)}:{i}" for d in ("runtime", "firmware_bridge", "sim")
            for p in sorted((PKG / d).glob("*.py")) if p.name != "test_security.py"
            for i, line in enumerate(p.read_text().splitlines(), 1) if bad.search(line)]
    assert not hits, hits


def _listening_inodes() -> set[str]:
    out = set()
    for name in ("tcp", "tcp6", "udp", "udp6"):
        path = Path("/proc/net") / name
        if path.exists():
            for line in path.read_text().splitlines()[1:]:
                f = line.split()
                if name.startswith("tcp") and f[3] == "0A":  # LISTEN
                    out.add(f[9])
                elif name.startswith("udp") and f[2].endswith(":0000") is False:
                    pass
    return out


def test_daemon_opens_no_listening_socket(tmp_path):
    proc, journal = faults.start_daemon(tmp_path)
    try:
        assert faults.wait_for(journal, lambda rs: sum(r["type"] == "final" for r in rs) >= 2)
        fd_dir = Path(f"/proc/{proc.pid}/fd")
        inodes = set()
        for fd in fd_dir.iterdir():
            try:
                target = (fd_dir / fd.name).readlink()
            except OSError:
                continue
            m = re.match(r"socket:\[(\d+)\]", str(target))
            if m:
                inodes.add(m.group(1))
        listening = inodes & _listening_inodes()
        assert not listening, f"daemon listens on socket inodes {listening}"
    finally:
        faults._stop(proc)


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
    from vs2t_edge.runtime.cell import _atomic_write
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
    from vs2t_edge.runtime.cell import _atomic_write

    stale = tmp_path / "FAULT.tmp"
    stale.write_text("old\n")
    stale.chmod(0o666)
    _atomic_write(tmp_path / "FAULT", "item 4: arm stopped\n")
    assert _modes(tmp_path / "FAULT") == {"FAULT": "0o640"} and not stale.exists()


def test_world_writable_config_is_refused(tmp_path):
    from vs2t_edge.runtime.config import ConfigError, load_config

    cfg = tmp_path / "cell.yaml"
    cfg.write_text(faults.DAEMON_CONFIG)
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
    cfg.write_text(faults.DAEMON_CONFIG)
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

"""The unit file: `systemd-analyze verify` clean, hardening exposure low, the example config valid.

`systemd-analyze` comes with the systemd package (Debian: `apt-get install systemd`); where it
is absent the verify tests skip with that message, the static checks still run.
"""

from __future__ import annotations

import configparser
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
UNIT = ROOT / "systemd" / "vs2t-edge.service"
ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze not installed "
                                   "(apt-get install systemd); unit not verified")


def unit_for_this_machine(tmp_path: Path) -> Path:
    """The unit with ExecStart pointing at this venv's entry point (verify checks it exists)."""
    exe = Path(sys.executable).with_name("vs2t-edge")
    text = UNIT.read_text().replace("/usr/local/bin/vs2t-edge", str(exe))
    out = tmp_path / "vs2t-edge.service"
    out.write_text(text)
    return out


def directives() -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        m = re.match(r"^([A-Za-z]+)=(.*)$", line.strip())
        if m:
            found.setdefault(m.group(1), []).append(m.group(2))
    return found


@needs_analyze
def test_systemd_analyze_verify_is_clean(tmp_path):
    unit = unit_for_this_machine(tmp_path)
    proc = subprocess.run([ANALYZE, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    # verify exits 0 on unknown keys too; any line about our file is a problem.
    ours = [ln for ln in (proc.stdout + proc.stderr).splitlines() if unit.name in ln]
    assert proc.returncode == 0 and not ours, proc.stdout + proc.stderr


@needs_analyze
def test_verify_would_catch_a_typo(tmp_path):
    unit = unit_for_this_machine(tmp_path)
    unit.write_text(unit.read_text().replace("PrivateTmp=yes", "PrivateTmp=yes\nPrivateTmpp=yes"))
    proc = subprocess.run([ANALYZE, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert "PrivateTmpp" in proc.stdout + proc.stderr


@needs_analyze
def test_security_exposure_is_low(tmp_path):
    unit = unit_for_this_machine(tmp_path)
    proc = subprocess.run([ANALYZE, "security", "--offline=true", str(unit)], capture_output=True, text=True,
                          timeout=60)
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", proc.stdout + proc.stderr)
    if m is None:
        pytest.skip(f"this systemd-analyze has no offline security report: {proc.stderr.strip()[:200]}")
    assert float(m.group(1)) <= 2.5, proc.stdout[-2000:]


def test_unit_has_the_contract():
    d = directives()
    assert d["Type"] == ["notify"] and d["NotifyAccess"] == ["main"]
    assert any("validate-config" in v for v in d["ExecStartPre"])
    assert d["Restart"] == ["on-failure"] and int(d["StartLimitBurst"][0]) >= 1
    assert int(d["WatchdogSec"][0]) > 0
    for key, value in [("ProtectSystem", "strict"), ("PrivateTmp", "yes"), ("NoNewPrivileges", "yes"),
                       ("DevicePolicy", "closed"), ("DynamicUser", "yes"), ("IPAddressDeny", "any")]:
        assert d[key] == [value], key
    assert d["StateDirectory"] == ["vs2t-edge"] and d["ReadWritePaths"] == ["/var/lib/vs2t-edge"]
    allowed = [v.split()[0] for v in d["DeviceAllow"]]
    assert allowed == ["char-video4linux", "/dev/ttyACM0"]  # the camera and the gate, nothing else
    assert set(d["RestrictAddressFamilies"][0].split()) == {"AF_UNIX", "AF_INET"}
    assert "localhost" in d["IPAddressAllow"] and len(d["IPAddressAllow"]) == 2


def test_example_config_validates_and_matches_the_unit():
    from vs2t_edge.runtime.config import load_config

    cfg = load_config(ROOT / "systemd" / "cell.yaml")
    d = directives()
    assert cfg.arm.host in d["IPAddressAllow"]
    assert any(v.startswith(cfg.gate["url"]) for v in d["DeviceAllow"])
    assert str(cfg.journal).startswith(d["ReadWritePaths"][0])


def test_drop_in_example_parses():
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str
    cp.read_string((ROOT / "systemd" / "site.conf.example").read_text())
    assert "Service" in cp

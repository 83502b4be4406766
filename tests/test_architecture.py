"""docs/ARCHITECTURE.md lists every module of the cell (runtime/, firmware_bridge/), so a newcomer
can trust it: a module added without a line there fails here."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_cell_module_has_its_line_in_architecture_md():
    doc = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    modules = [p for room in ("runtime", "firmware_bridge") for p in sorted((ROOT / room).glob("*.py"))
               if p.name != "__init__.py"]
    assert len(modules) > 20
    missing = [f"{p.parent.name}/{p.name}" for p in modules if f"| `{p.parent.name}/{p.name}` |" not in doc]
    assert not missing, f"docs/ARCHITECTURE.md has no line for {missing}"


def test_the_hardware_skip_says_what_to_set():
    """One rule for every hardware test (tests/conftest.py): skipped off the cell, with the
    variables to set named; run when they are set."""
    import pytest

    from conftest import hardware_skip_reason

    marker = pytest.mark.hardware(needs="the real gate", env=("VS2T_GATE_PORT",)).mark
    assert hardware_skip_reason(marker, {}) == "needs the real gate: set VS2T_HARDWARE=1 and VS2T_GATE_PORT"
    assert hardware_skip_reason(marker, {"VS2T_HARDWARE": "1"}) == "needs the real gate: set VS2T_GATE_PORT"
    assert hardware_skip_reason(marker, {"VS2T_HARDWARE": "1", "VS2T_GATE_PORT": "/dev/ttyACM0"}) is None
    assert hardware_skip_reason(pytest.mark.hardware.mark, {}) == "needs the real cell: set VS2T_HARDWARE=1"


def _imported_modules(path: Path) -> list[str]:
    """Every module a file imports, at any depth (a lazy import inside a function counts too)."""
    import ast

    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.append(node.module)
    return names


def test_the_cell_code_never_imports_the_simulators():
    """runtime/ and firmware_bridge/ never import vs2t_edge.sim (the simulated camera and gate were
    in runtime/camera.py and runtime/gate.py); a config's simulated gate is reached only by name,
    through runtime/devices.py's SIMULATORS, which must name factories that exist."""
    from vs2t_edge.runtime.devices import SIMULATORS, simulator

    offenders = [f"{p.parent.name}/{p.name} imports {m}"
                 for room in ("runtime", "firmware_bridge") for p in sorted((ROOT / room).glob("*.py"))
                 for m in _imported_modules(p) if m == "vs2t_edge.sim" or m.startswith("vs2t_edge.sim.")]
    assert not offenders, offenders
    assert SIMULATORS and all(v.startswith("vs2t_edge.sim.") for v in SIMULATORS.values())
    assert all(callable(simulator(device)) for device in SIMULATORS)

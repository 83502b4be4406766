"""Fuzz the config loader beyond tests/test_config.py's random documents (issue 8): mutations of
the shipped systemd/cell.yaml (every key set to hostile values or removed), line edits with YAML
tokens (anchors, tags, merges, huge numbers, home-relative paths) and raw bytes. Property (in
sim/fuzz.py, shared with the atheris harness): a CellConfig or a ConfigError whose every problem
starts with FILE: - never another exception, never a hang. Seeds: tests/fuzz_seeds/config/."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vs2t_edge.sim import fuzz

BASE = Path(__file__).parents[1] / "systemd" / "cell.yaml"
SEEDS = fuzz.load_seeds("config")
_slow_ok = settings(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                                           HealthCheck.function_scoped_fixture])
YAML_VALUES = [None, True, 0, -1, 1, 7, 8, 64, 65, 10 ** 30, 10 ** 400, 1e308, float("nan"), float("inf"), -0.0,
               0.5, "", "x", "~", "~nobody-here/bundle", "/dev/null", "a\x00b", "\u00e9\u202e", "spread", "list",
               "touched", "untouched", "unknown", "sim", "fake", [], {}, [None], [0, 224], [225], [True],
               {"name": "f", "kind": "touched", "bin": 1}, [{"name": "f", "kind": "touched", "bin": 0}],
               list(range(300)), {"a": {"b": {"c": {}}}}]
LINE_TOKENS = ["&a ", "*a", "*nope", "<<: *a", "!!python/object:os.system ", "!!binary ", "!!timestamp ",
               "2001-12-14", "0x1F", "0o17", "1_000", ".nan", ".inf", "-.inf", "9" * 5000, "9" * 400,
               "1e400", "~nobody-here/x", "? [a, b]\n: c", "\t", "{", "[", "'", '"', "- ", ": ", "%YAML 1.1\n---\n",
               "--- ", "...", "\u2028", "\x00", "\ufeff"]


@pytest.fixture(scope="module")
def target():
    work = Path(tempfile.mkdtemp(prefix="vs2t_fuzz_config_"))
    yield fuzz.ConfigTarget(BASE, work)
    shutil.rmtree(work, ignore_errors=True)


def test_the_shipped_config_passes_the_property(target):
    # It names a bundle and devices this machine lacks: loads or is refused, both are fine here.
    target.run(BASE.read_bytes())


@pytest.mark.parametrize("seed", [s for _, s in SEEDS], ids=[p.stem for p, _ in SEEDS])
def test_committed_seed(target, seed):
    fuzz.check_seed(target, seed, target.run(target.seed_bytes(seed)))


@settings(_slow_ok, max_examples=100)
@given(data=st.data())
def test_mutated_configs_load_or_are_refused(target, data):
    base = yaml.safe_load(target.base_text)
    paths = [list(p) for p in fuzz.paths_of(base)]
    # the hand-picked values twice as often as random ones: they are where loaders break
    value_st = st.sampled_from(YAML_VALUES) | st.sampled_from(YAML_VALUES) | st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
        lambda kids: st.lists(kids, max_size=3) | st.dictionaries(st.text(max_size=6), kids, max_size=3),
        max_leaves=8)
    ops = data.draw(st.lists(st.tuples(st.just("set"), st.sampled_from(paths), value_st)
                             | st.tuples(st.just("del"), st.sampled_from(paths)), min_size=1, max_size=4))
    doc = fuzz.apply_ops(base, ops)
    target.run(yaml.safe_dump(doc, allow_unicode=True).encode("utf-8", "surrogatepass"))


@settings(_slow_ok, max_examples=120)
@given(data=st.data())
def test_line_edits_with_yaml_tokens(target, data):
    lines = target.base_text.splitlines(keepends=True)
    for _ in range(data.draw(st.integers(1, 3))):
        i = data.draw(st.integers(0, len(lines) - 1))
        line = lines[i]
        cut = data.draw(st.integers(0, len(line)))
        token = data.draw(st.sampled_from(LINE_TOKENS))
        lines[i] = line[:cut] + token + line[cut:] if data.draw(st.booleans()) else line[:cut] + token + "\n"
    target.run("".join(lines).encode("utf-8", "surrogatepass"))


@settings(_slow_ok, max_examples=100)
@given(raw=st.binary(max_size=200))
def test_any_bytes_as_config(target, raw):
    target.run(raw)


def test_harness_replays_every_committed_corpus(tmp_path, capsys):
    """`python -m vs2t_edge.sim.fuzz TARGET --seeds-only` (no atheris needed): the committed
    seeds hold on the default bases (the tests/replays bundle, touched.replay, systemd/cell.yaml)."""
    for name in fuzz.TARGETS:
        assert fuzz.main([name, "--seeds-only", "--work", str(tmp_path / name)]) == 0, capsys.readouterr().out
    out = capsys.readouterr().out
    assert "FAIL" not in out and out.count("ok ") >= sum(len(fuzz.load_seeds(t)) for t in fuzz.TARGETS)

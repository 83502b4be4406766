"""Fuzz the bundle manifest loader (issue 8): any manifest.json beside the files of a real bundle
loads or is refused with a BundleError naming the bundle - never another exception, never a
hang, never a file opened outside the bundle folder. The property lives in sim/fuzz.py (shared
with the atheris harness); the committed seeds in tests/fuzz_seeds/manifest/ replay here."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from test_bundle_fixtures import shared_bundle
from vs2t_edge.sim import fuzz

SEEDS = fuzz.load_seeds("manifest")


@pytest.fixture(scope="module")
def target():
    work = Path(tempfile.mkdtemp(prefix="vs2t_fuzz_manifest_"))
    # a two-graph (format 1) bundle: the committed seeds name heads.onnx, and the harness's CLI
    # default is tests/replays/bundle, also format 1
    yield fuzz.ManifestTarget(shared_bundle(fuse=False), work)
    shutil.rmtree(work, ignore_errors=True)


def test_the_base_manifest_loads_and_the_model_opens(target):
    assert target.run(target.base_bytes) == "ok"
    assert target.run(target.base_bytes, open_model=True) == "ok"


@pytest.mark.parametrize("seed", [s for _, s in SEEDS], ids=[p.stem for p, _ in SEEDS])
def test_committed_seed(target, seed):
    outcome = fuzz.run_seed(target, seed, target.seed_bytes(seed))
    fuzz.check_seed(target, seed, outcome)


def _ops(target, values):
    paths = fuzz.paths_of(target.base)
    path_st = st.sampled_from(paths).map(list) | st.lists(
        st.sampled_from(["files", "graphs", "trunk", "heads", "file", "opset", "inputs", "outputs", "classes",
                         "touched", "untouched", "router", "probe", "tolerance", "gating", "transform", "x", 0, 1]),
        min_size=1, max_size=4)
    value_st = st.sampled_from(values) | st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
        lambda kids: st.lists(kids, max_size=3) | st.dictionaries(st.text(max_size=6), kids, max_size=3),
        max_leaves=8)
    op_st = st.tuples(st.just("set"), path_st, value_st) | st.tuples(st.just("del"), path_st)
    return st.lists(op_st, min_size=1, max_size=4)


_slow_ok = settings(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                                           HealthCheck.function_scoped_fixture])


@settings(_slow_ok, max_examples=150)
@given(data=st.data())
def test_mutated_manifests_load_or_are_refused(target, data):
    ops = data.draw(_ops(target, fuzz.interesting_values(str(target.outside))))
    target.run(fuzz.dump_json(fuzz.apply_ops(target.base, ops)))


@settings(_slow_ok, max_examples=25)
@given(data=st.data())
def test_mutated_graph_shapes_through_onnxruntime(target, data):
    """Shapes and names only matter once onnxruntime has the graphs open: TactileModel.load."""
    paths = [list(p) for p in fuzz.paths_of(target.base) if p[0] in ("graphs", "classes", "feature_dim", "probe")]
    vals = [None, 0, 1, 3, 16, 32, -1, 10 ** 20, "16", [None, 16], [None, 3], [16], [None, 3, 32, 32],
            [None, 3, 16, 16], {"x": [None, 16]}, {"feature": [None, 16], "y": [1]}, [], {}, 1e-300, float("nan")]
    ops = data.draw(st.lists(st.tuples(st.just("set"), st.sampled_from(paths), st.sampled_from(vals)),
                             min_size=1, max_size=3))
    target.run(fuzz.dump_json(fuzz.apply_ops(target.base, ops)), open_model=True)


@settings(_slow_ok, max_examples=80)
@given(raw=st.binary(max_size=300) | st.text(max_size=200).map(lambda t: t.encode("utf-8", "surrogatepass")))
def test_any_bytes_as_manifest(target, raw):
    target.run(raw)


@settings(_slow_ok, max_examples=80)
@given(data=st.data())
def test_byte_edits_of_the_real_manifest(target, data):
    raw = bytearray(target.base_bytes)
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(raw) - 1))
        edit = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        if edit == "flip":
            raw[i] = data.draw(st.integers(0, 255))
        elif edit == "cut":
            del raw[i:i + data.draw(st.integers(1, 40))]
        else:
            raw[i:i] = data.draw(st.sampled_from([b"[", b"{", b"\"", b"NaN", b"1e999", b"9" * 5000, b"\xff",
                                                   b",", b"null", b"\"../outside/trunk.onnx\""]))
        if not raw:
            break
    target.run(bytes(raw))


def test_symlink_to_outside_listed_with_its_true_hash_is_refused(target, tmp_path):
    """A file inside the folder that is a link out is still outside: never read."""
    link = target.root / "linked.onnx"
    try:
        os.symlink(target.outside / "trunk.onnx", link)
        m = json.loads(target.base_bytes)
        m["files"]["linked.onnx"] = target.subs["@sha:trunk.onnx@"]
        m["graphs"]["trunk"]["file"] = "linked.onnx"
        outcome = target.run(fuzz.dump_json(m))
        assert outcome.startswith("refused") and "linked.onnx" in outcome and "leaves the bundle folder" in outcome
    finally:
        link.unlink(missing_ok=True)


def test_a_property_violation_is_reported(target, monkeypatch):
    """The harness itself can fail: a loader raising KeyError is caught as a FuzzFailure."""
    from vs2t_edge.runtime import bundle

    def broken(root, beta_override=None):
        raise KeyError("graphs")

    monkeypatch.setattr(bundle, "load_bundle", broken)
    with pytest.raises(fuzz.FuzzFailure, match="KeyError"):
        target.run(target.base_bytes)


def test_a_huge_class_list_is_handled_in_linear_time(target):
    """20000 names: the duplicate check was list.count per name (4e8 steps, a hang at start)."""
    import time

    m = json.loads(target.base_bytes)
    m["classes"]["untouched"] = [f"c{i}" for i in range(20000)]
    t0 = time.monotonic()
    assert target.run(fuzz.dump_json(m)) == "ok"  # the heads' shape check (onnxruntime) refuses it later
    assert time.monotonic() - t0 < 2.0
    assert "logits_u" in target.run(fuzz.dump_json(m), open_model=True)

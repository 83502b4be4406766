"""Fuzz the replay file reader (issue 8): any index.json beside real frames opens or is refused
with a ReplayError naming the file - never another exception, never a hang, never a frame read
from outside the replay folder; a file that opens also survives everything `vs2t-edge replay`
does before the daemon runs (frames, queues, bundle lookup, config). Property in sim/fuzz.py;
the committed seeds in tests/fuzz_seeds/replay/ replay here."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vs2t_edge.sim import fuzz

BASE = Path(__file__).parent / "replays" / "touched.replay"
SEEDS = fuzz.load_seeds("replay")
_slow_ok = settings(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                                           HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def target():
    work = Path(tempfile.mkdtemp(prefix="vs2t_fuzz_replay_"))
    yield fuzz.ReplayTarget(BASE, work)
    shutil.rmtree(work, ignore_errors=True)


def test_the_recorded_index_opens(target):
    assert target.run(target.base_bytes).startswith(("ok", "opened"))


@pytest.mark.parametrize("seed", [s for _, s in SEEDS], ids=[p.stem for p, _ in SEEDS])
def test_committed_seed(target, seed):
    fuzz.check_seed(target, seed, target.run(target.seed_bytes(seed)))


def _paths(target):
    # The index has hundreds of events alike and big decision records: mutate the top levels and
    # the first few entries of each list, where every key the reader looks at appears.
    return [list(p) for p in fuzz.paths_of(target.base, limit=3000)
            if len(p) <= 3 and not (len(p) > 1 and isinstance(p[1], int) and p[1] > 6)]


@settings(_slow_ok, max_examples=120)
@given(data=st.data())
def test_mutated_indexes_open_or_are_refused(target, data):
    paths = _paths(target)
    path_st = st.sampled_from(paths) | st.lists(
        st.sampled_from(["events", "items", "decisions", "config", "meta", "beta", "frame", "dev", "call", "item",
                         "args", "result", "error", "type", "message", "id", "bundle", "x", 0, 1, -1]),
        min_size=1, max_size=4)
    value_st = st.sampled_from(fuzz.interesting_values(str(target.outside))) | st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
        lambda kids: st.lists(kids, max_size=3) | st.dictionaries(st.text(max_size=6), kids, max_size=3),
        max_leaves=8)
    ops = data.draw(st.lists(st.tuples(st.just("set"), path_st, value_st) | st.tuples(st.just("del"), path_st),
                             min_size=1, max_size=4))
    target.run(fuzz.dump_json(fuzz.apply_ops(target.base, ops)))


@settings(_slow_ok, max_examples=80)
@given(raw=st.binary(max_size=300) | st.text(max_size=200).map(lambda t: t.encode("utf-8", "surrogatepass")))
def test_any_bytes_as_index(target, raw):
    target.run(raw)


@settings(_slow_ok, max_examples=60)
@given(data=st.data())
def test_byte_edits_of_the_recorded_index(target, data):
    raw = bytearray(target.base_bytes)
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(raw) - 1))
        edit = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        if edit == "flip":
            raw[i] = data.draw(st.integers(0, 255))
        elif edit == "cut":
            del raw[i:i + data.draw(st.integers(1, 40))]
        else:
            raw[i:i] = data.draw(st.sampled_from([b"[", b"{", b"\"", b"NaN", b"1e999", b"9" * 5000, b"\xff", b",",
                                                   b"null", b"\"frames/../../outside/000001.png\""]))
        if not raw:
            break
    target.run(bytes(raw))

"""Fuzz targets for everything the cell reads from disk or the wire (issue 8; docs/reliability.md).

Four targets, each one property, used by three drivers (the hypothesis tests, the committed
seed corpora under tests/fuzz_seeds/, and the atheris harness below):

* ``manifest`` - bytes as a bundle's ``manifest.json`` beside the real files of a valid bundle:
  ``load_bundle`` (and, when asked, ``TactileModel.load``) loads or raises ``BundleError``
  "bundle PATH: ..." - never another exception, never a hang, never a file opened outside the
  bundle folder (a valid copy of ``trunk.onnx`` waits outside it as bait).
* ``replay`` - bytes as a replay file's ``index.json`` beside real frames: ``ReplayFile.open``
  opens or raises ``ReplayError`` naming the index file; an opened file then also survives
  ``frames_by_item``, the replay queues, ``recorded_bundle`` and ``config_for_replay``
  (``ReplayError`` / ``ConfigError`` only); no frame is read from outside the replay folder.
* ``config`` - bytes as a cell config: ``load_config`` gives a ``CellConfig`` or a
  ``ConfigError`` whose every problem starts with ``FILE:``.
* ``gate`` - bytes as a serial stream, fed to the ``FrameReader`` in chunks: never raises, every
  byte is a frame, dropped or pending, and every frame it yields is CRC-valid.

Coverage-guided byte fuzzing (atheris, libFuzzer) over the same properties::

    python -m vs2t_edge.sim.fuzz manifest|replay|config|gate --seconds 60

starts from the committed seeds (turned into raw files), keeps its growing corpus and any crash
input in ``/tmp/vs2t-fuzz-TARGET/`` (never in the repository), and prints runs, new corpus
entries and crashes. Exit 0 no failure, 1 a property failed (input saved), 4 atheris missing.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import hashlib
import json
import os
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
SEEDS = REPO / "tests" / "fuzz_seeds"
TARGETS = ("manifest", "replay", "config", "gate")
HANG_S = 10.0  # one input taking longer than this is a hang (a real load is ~10 ms)


class FuzzFailure(AssertionError):
    """The property does not hold for this input (the message says how)."""


# --- watching what is opened and how long it takes ----------------------------------------

_WATCH: dict[str, Any] = {"forbidden": None, "hits": []}
_HOOKED = False


def _audit(event: str, args: tuple) -> None:
    # Every open() / io.open / os.open in this process raises the "open" audit event; numpy's
    # np.load and Path.read_bytes go through it, so a loader reading outside its folder is seen.
    if event != "open" or _WATCH["forbidden"] is None:
        return
    target = args[0] if args else None
    if isinstance(target, (str, bytes, os.PathLike)):
        try:
            real = os.path.realpath(os.fsdecode(target))
        except (ValueError, OSError):
            return
        if real == _WATCH["forbidden"] or real.startswith(_WATCH["forbidden"] + os.sep):
            _WATCH["hits"].append(real)


@contextlib.contextmanager
def watch_opens(forbidden: Path):
    """Record every file opened under ``forbidden`` (a folder) while the block runs."""
    global _HOOKED
    if not _HOOKED:
        sys.addaudithook(_audit)  # cannot be removed; inert while nothing is watched
        _HOOKED = True
    _WATCH["forbidden"], _WATCH["hits"] = os.path.realpath(forbidden), []
    try:
        yield _WATCH["hits"]
    finally:
        _WATCH["forbidden"] = None


class _Hang(BaseException):
    pass  # BaseException: a loader's broad `except Exception` must not swallow it


@contextlib.contextmanager
def time_limit(seconds: float):
    """Raise FuzzFailure if the block runs longer (SIGALRM; a no-op off the main thread)."""
    import threading

    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "setitimer"):
        yield
        return

    def on_alarm(signum, frame):
        raise _Hang()

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    except _Hang:
        raise FuzzFailure(f"hang: more than {seconds} s on one input") from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _unexpected(exc: BaseException, what: str) -> FuzzFailure:
    return FuzzFailure(f"{what} raised {type(exc).__name__}: {exc}"[:2000])


# --- mutations of a JSON document (hypothesis and the seeds) -------------------------------

def substitute(x: Any, subs: dict[str, str]) -> Any:
    """Replace @NAME@ placeholders in strings (seeds name the bait folder and real hashes)."""
    if isinstance(x, str):
        for k, v in subs.items():
            x = x.replace(k, v)
        return x
    if isinstance(x, list):
        return [substitute(v, subs) for v in x]
    if isinstance(x, dict):
        return {substitute(k, subs): substitute(v, subs) for k, v in x.items()}
    return x


def apply_ops(doc: Any, ops: list) -> Any:
    """A copy of ``doc`` with each op applied: ["set", path, value] | ["del", path].

    A path is a list of keys / list indices; a missing parent or a non-container on the way
    makes the op a no-op (mutations are drawn blindly)."""
    doc = copy.deepcopy(doc)
    for op in ops:
        kind, path = op[0], list(op[1])
        if not path:
            if kind == "set":
                doc = copy.deepcopy(op[2])
            continue
        node = doc
        for k in path[:-1]:
            if isinstance(node, dict) and k in node:
                node = node[k]
            elif isinstance(node, list) and isinstance(k, int) and -len(node) <= k < len(node):
                node = node[k]
            else:
                node = None
                break
        last = path[-1]
        if isinstance(node, dict):
            if kind == "set":
                node[last] = copy.deepcopy(op[2])
            elif last in node:
                del node[last]
        elif isinstance(node, list) and isinstance(last, int) and -len(node) <= last < len(node):
            if kind == "set":
                node[last] = copy.deepcopy(op[2])
            else:
                del node[last]
    return doc


def paths_of(doc: Any, prefix: tuple = (), limit: int = 400) -> list[tuple]:
    """Every key path in a JSON document (depth first, capped), the root excluded."""
    out: list[tuple] = []

    def walk(node: Any, pre: tuple) -> None:
        if len(out) >= limit:
            return
        items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
        for k, v in items:
            out.append(pre + (k,))
            walk(v, pre + (k,))

    walk(doc, prefix)
    return out


def dump_json(doc: Any) -> bytes:
    """JSON text as a writer would produce it; NaN/Infinity kept (Python's json reads them)."""
    return json.dumps(doc, indent=1, allow_nan=True).encode()  # \uXXXX escapes: lone surrogates too


def interesting_values(bait: str) -> list:
    """Values that broke loaders elsewhere: wrong types, non-finite and huge numbers, paths out."""
    return [None, True, False, 0, -1, 1, 16, 17, 21, 22, 255, 2 ** 31, 2 ** 63, 10 ** 30, -(10 ** 30),
            1e308, -1e308, float("nan"), float("inf"), float("-inf"), 0.5, -0.0, 1e-320,
            "", "x", "t0", "u0", "\u00e9\u202e\U0001F600", "a\x00b", "1", "17", "NaN", "asinh", "linear", "gaussian",
            "vs2t-bundle", "vs2t-edge-replay", "trunk.onnx", "heads.onnx", "router.npz", "probe_input.npy",
            "probe_expected.npz", "manifest.json", "index.json", ".", "..", "../", "../outside/trunk.onnx",
            f"{bait}/trunk.onnx", "/etc/passwd", "sub/../trunk.onnx", "./trunk.onnx", "trunk.onnx/",
            "frames/000001.png", "frames/../../outside/000001.png", "~nobody-here/x", "a" * 3000,
            [], {}, [None], [3, 32, 32], [None, 3, 32, 32], [None, 16], [None, "16"], ["t0", "t0"], ["t0", 1],
            {"a": 1}, [[[[[]]]]], list(range(300)), {"": None}, {"trunk.onnx": "0" * 64}]


def json_seed_bytes(base: Any, seed: dict, subs: dict[str, str]) -> bytes:
    """A JSON seed's file: "raw" text, "raw_hex" bytes, "replace" [old, new] once in the base's
    text, or "ops" applied to the base document."""
    if "raw_hex" in seed:
        return bytes.fromhex(seed["raw_hex"])
    if "raw" in seed:
        return substitute(seed["raw"], subs).encode("utf-8", "surrogatepass")
    if "replace" in seed:
        old, new = substitute(seed["replace"], subs)
        text = dump_json(base).decode("utf-8", "surrogatepass")
        if old not in text:
            raise ValueError(f"seed replaces {old!r}, which the base does not contain")
        return text.replace(old, new, 1).encode("utf-8", "surrogatepass")
    return dump_json(apply_ops(base, substitute(seed["ops"], subs)))


# --- the bundle manifest ------------------------------------------------------------------

def _refuse_duplicates(pairs: list) -> dict:
    out = dict(pairs)
    if len(out) != len(pairs):
        raise ValueError("duplicate key")
    return out


class ManifestTarget:
    """A valid bundle copied to ``work/bundle`` (files fixed), a bait copy of trunk.onnx in
    ``work/outside``; ``run(bytes)`` writes them as manifest.json and loads."""

    name = "manifest"

    def __init__(self, base_bundle: Path, work: Path) -> None:
        self.work = Path(work)
        self.root = self.work / "bundle"
        self.outside = self.work / "outside"
        if self.root.exists():
            shutil.rmtree(self.root)
        shutil.copytree(base_bundle, self.root)
        self.outside.mkdir(parents=True, exist_ok=True)
        shutil.copy2(self.root / "trunk.onnx", self.outside / "trunk.onnx")
        self.base_bytes = (self.root / "manifest.json").read_bytes()
        self.base = json.loads(self.base_bytes)
        self.subs = {"@outside@": str(self.outside)}
        for f in sorted(p.name for p in self.root.iterdir() if p.is_file() and p.name != "manifest.json"):
            self.subs[f"@sha:{f}@"] = hashlib.sha256((self.root / f).read_bytes()).hexdigest()

    @staticmethod
    def sealed(data: bytes) -> bytes:
        """The document re-sealed as the exporter would have (so the fuzz reaches the checks behind
        the seal); bytes that are no JSON object, or that the loader refuses to parse, as they are."""
        from vs2t_edge.runtime.bundle import seal_manifest

        try:
            doc = json.loads(data, object_pairs_hook=_refuse_duplicates)
            return dump_json(seal_manifest(doc)) if isinstance(doc, dict) else data
        except (ValueError, TypeError, RecursionError):  # the loader refuses these before the seal
            return data

    def run(self, data: bytes, open_model: bool = False, seal: bool = True) -> str:
        from vs2t_edge.runtime.bundle import BundleError, load_bundle

        (self.root / "manifest.json").write_bytes(self.sealed(data) if seal else data)
        what = "TactileModel.load" if open_model else "load_bundle"
        try:
            with watch_opens(self.outside) as opened, time_limit(HANG_S):
                try:
                    if open_model:
                        from vs2t_edge.runtime.inference import TactileModel

                        TactileModel.load(self.root, threads=1)
                    else:
                        load_bundle(self.root)
                    outcome = "ok"
                except BundleError as exc:
                    if not str(exc).startswith(f"bundle {self.root}: ") or not exc.detail.strip():
                        raise FuzzFailure(f"BundleError does not name the bundle: {exc}") from None
                    outcome = f"refused: {exc.detail}"
                except FuzzFailure:
                    raise
                except Exception as exc:  # noqa: BLE001 - exactly what the property forbids
                    raise _unexpected(exc, what) from exc
        finally:
            (self.root / "manifest.json").write_bytes(self.base_bytes)
        if opened:
            raise FuzzFailure(f"{what} opened {opened[0]}, outside the bundle folder ({outcome[:200]})")
        return outcome

    def seed_bytes(self, seed: dict) -> bytes:
        return json_seed_bytes(self.base, seed, self.subs)


# --- the replay file ----------------------------------------------------------------------

class ReplayTarget:
    """A recorded replay copied to ``work/session.replay`` (frames fixed), a bait PNG in
    ``work/outside``; ``run(bytes)`` writes them as index.json and opens and walks it."""

    name = "replay"

    def __init__(self, base_replay: Path, work: Path) -> None:
        self.work = Path(work)
        self.folder = self.work / "session.replay"
        self.outside = self.work / "outside"
        self.scratch = self.work / "scratch"
        if self.folder.exists():
            shutil.rmtree(self.folder)
        shutil.copytree(base_replay, self.folder)
        self.outside.mkdir(parents=True, exist_ok=True)
        self.scratch.mkdir(parents=True, exist_ok=True)
        first = sorted((self.folder / "frames").glob("*.png"))[0]
        shutil.copy2(first, self.outside / "000001.png")
        self.base_bytes = (self.folder / "index.json").read_bytes()
        self.base = json.loads(self.base_bytes)
        self.subs = {"@outside@": str(self.outside)}

    def run(self, data: bytes) -> str:
        from vs2t_edge.runtime.config import ConfigError
        from vs2t_edge.runtime import replay as rp

        index = self.folder / "index.json"
        index.write_bytes(data)
        step = "ReplayFile.open"
        try:
            with watch_opens(self.outside) as opened, time_limit(HANG_S):
                try:
                    rf = rp.ReplayFile.open(self.folder)
                except rp.ReplayError as exc:
                    if str(self.folder) not in str(exc):
                        raise FuzzFailure(f"ReplayError does not name the file: {exc}") from None
                    outcome = f"refused: {exc}"
                except Exception as exc:  # noqa: BLE001
                    raise _unexpected(exc, step) from exc
                else:
                    outcome = "opened"
                    # An opened file must survive everything `replay` does before the daemon runs.
                    for step, fn in (("frames_by_item", lambda: [None for _ in rf.frames_by_item()]),
                                     ("replay queues", lambda: rp.ReplayItems(rp._Queues(rf))),
                                     ("recorded_bundle", lambda: rp.recorded_bundle(rf)),
                                     ("config_for_replay",
                                      lambda: rp.config_for_replay(rf, self.scratch, self.work / "bundle"))):
                        try:
                            fn()
                        except (rp.ReplayError, ConfigError) as exc:
                            outcome = f"{outcome}; {step} refused: {str(exc)[:800]}"
                        except Exception as exc:  # noqa: BLE001
                            raise _unexpected(exc, step) from exc
        finally:
            index.write_bytes(self.base_bytes)
        if opened:
            raise FuzzFailure(f"{step} opened {opened[0]}, outside the replay folder")
        return outcome

    def seed_bytes(self, seed: dict) -> bytes:
        return json_seed_bytes(self.base, seed, self.subs)


# --- the cell config ----------------------------------------------------------------------

class ConfigTarget:
    name = "config"

    def __init__(self, base_config: Path, work: Path) -> None:
        self.work = Path(work)
        self.work.mkdir(parents=True, exist_ok=True)
        self.path = self.work / "cell.yaml"
        self.base_text = Path(base_config).read_text()

    def run(self, data: bytes) -> str:
        from vs2t_edge.runtime.config import ConfigError, load_config

        self.path.write_bytes(data)
        with time_limit(HANG_S):
            try:
                load_config(self.path)
                return "ok"
            except ConfigError as exc:
                bad = [p for p in exc.problems if not p.startswith(f"{self.path}:")]
                if bad or not exc.problems:
                    raise FuzzFailure(f"ConfigError problem without FILE: prefix: {bad or exc.problems}") from None
                return f"refused: {exc.problems[0]}"
            except Exception as exc:  # noqa: BLE001
                raise _unexpected(exc, "load_config") from exc

    def seed_bytes(self, seed: dict) -> bytes:
        return seed["yaml"].encode("utf-8", "surrogatepass")


# --- the gate's serial stream -------------------------------------------------------------

class GateTarget:
    name = "gate"

    def run(self, data: bytes) -> str:
        from vs2t_edge.firmware_bridge import protocol as p

        reader = p.FrameReader()
        found = []
        chunk = 1 + (data[0] % 16 if data else 0)  # the chunking is part of the input
        try:
            with time_limit(HANG_S):
                for i in range(0, len(data), chunk):
                    found += reader.feed(data[i:i + chunk])
        except FuzzFailure:
            raise
        except Exception as exc:  # noqa: BLE001
            raise _unexpected(exc, "FrameReader.feed") from exc
        encoded = [f.encode() for f in found]
        if reader.dropped_bytes + sum(map(len, encoded)) + reader.pending != len(data):
            raise FuzzFailure("bytes unaccounted for (frames + dropped + pending != input)")
        if reader.pending >= p.MAX_FRAME:
            raise FuzzFailure(f"reader hoards {reader.pending} bytes")
        for fr in encoded:
            if p.check_frame(fr) != (p.FRAME, len(fr)):
                raise FuzzFailure(f"yielded a frame that does not check: {fr.hex()}")
        return f"{len(encoded)} frame(s)"

    def seed_bytes(self, seed: dict) -> bytes:
        return bytes.fromhex(seed["stream"])


# --- seeds --------------------------------------------------------------------------------

def load_seeds(target: str, root: Path = SEEDS) -> list[tuple[Path, dict]]:
    return [(p, json.loads(p.read_text())) for p in sorted((root / target).glob("*.json"))]


def run_seed(target, seed: dict, data: bytes) -> str:
    """A seed's run; manifest seeds may say ``"open_model": true`` or ``"seal": false`` (left as a
    hand edit would leave it, so the seal itself is what refuses it)."""
    kw = {}
    if seed.get("open_model"):
        kw["open_model"] = True
    if "seal" in seed:
        kw["seal"] = bool(seed["seal"])
    return target.run(data, **kw)


def check_seed(target_obj, seed: dict, outcome: str) -> None:
    """A seed's recorded expectation: "ok" or "refused" (with `match` in the message)."""
    want = seed.get("expect")
    if want == "ok" and not outcome.startswith(("ok", "opened")):
        raise FuzzFailure(f"expected to load, got {outcome}")
    if want == "refused" and not outcome.startswith("refused"):
        raise FuzzFailure(f"expected a refusal, got {outcome}")
    if seed.get("match") and seed["match"] not in outcome:
        raise FuzzFailure(f"expected {seed['match']!r} in the outcome, got {outcome}")


def default_bases() -> dict[str, Path]:
    return {"manifest": REPO / "tests" / "replays" / "bundle",
            "replay": REPO / "tests" / "replays" / "touched.replay",
            "config": REPO / "systemd" / "cell.yaml"}


def make_target(name: str, work: Path, base: Path | None = None):
    base = base or default_bases().get(name)
    if name == "manifest":
        return ManifestTarget(base, work)
    if name == "replay":
        return ReplayTarget(base, work)
    if name == "config":
        return ConfigTarget(base, work)
    if name == "gate":
        return GateTarget()
    raise ValueError(f"unknown fuzz target {name!r}; known: {', '.join(TARGETS)}")


# --- the atheris harness ------------------------------------------------------------------

# libFuzzer dictionary entries: the tokens byte mutation cannot guess.
_DICT = {
    "manifest": ['"format"', '"vs2t-bundle"', '"format_version"', '"files"', '"graphs"', '"trunk"', '"heads"',
                 '"file"', '"opset"', '"inputs"', '"outputs"', '"classes"', '"touched"', '"untouched"',
                 '"router"', '"probe"', '"tolerance"', '"gating"', '"asinh"', '"beta"', '"feature_dim"',
                 '"../outside/trunk.onnx"', 'NaN', 'Infinity', '-Infinity', '1e999', 'null', 'true', '[]', '{}'],
    "replay": ['"format"', '"vs2t-edge-replay"', '"version"', '"events"', '"items"', '"decisions"', '"config"',
               '"meta"', '"frame"', '"frames/000001.png"', '"dev"', '"call"', '"press"', '"camera"', '"error"',
               '"args"', '"result"', '"beta"', 'NaN', 'Infinity', 'null', '[]', '{}'],
    "config": ['bundle:', 'devices:', 'camera:', 'arm:', 'gate:', 'scene:', 'fabrics:', 'evidence:', 'kind:',
               'journal:', 'watchdog:', '&a', '*a', '<<:', '!!python/object', '~', '.nan', '.inf', '- ', ': ', '{', '['],
    "gate": ['\xa5'],
}


def _escape_dict_entry(token: str) -> str:
    return "".join(c if 32 <= ord(c) < 127 and c not in '"\\' else f"\\x{ord(c):02x}" for c in token)


def run_atheris(name: str, seconds: int, work: Path, base: Path | None = None, max_len: int = 16384) -> int:
    try:
        import atheris
    except ImportError as exc:
        print(f"atheris is not installed ({exc}); pip install atheris (wheels for Linux x86_64)", file=sys.stderr)
        return 4
    work.mkdir(parents=True, exist_ok=True)
    target = make_target(name, work / "target", base)
    corpus = work / "corpus"
    corpus.mkdir(exist_ok=True)
    seeds = load_seeds(name)
    for path, seed in seeds:  # committed seeds -> raw inputs
        (corpus / f"seed-{path.stem}").write_bytes(target.seed_bytes(seed))
    if name in ("manifest", "replay"):
        (corpus / "seed-base").write_bytes(target.base_bytes)
    elif name == "config":
        (corpus / "seed-base").write_bytes(target.base_text.encode())
    dict_file = work / "tokens.dict"
    dict_file.write_text("".join(f'"{_escape_dict_entry(t)}"\n' for t in _DICT[name]))
    n_corpus_before = len(list(corpus.iterdir()))
    stats = {"runs": 0, "ok": 0, "refused": 0}
    t0 = time.monotonic()
    last = [t0]

    def report(final: bool = False) -> None:
        dt = time.monotonic() - t0
        crashes = sorted(p.name for p in work.glob("crash-*")) + sorted(p.name for p in work.glob("timeout-*"))
        print(f"fuzz {name}: {stats['runs']} runs in {dt:.0f} s ({stats['runs'] / max(dt, 1e-9):.0f}/s), "
              f"{stats['ok']} loaded, {stats['refused']} refused, corpus {n_corpus_before} -> "
              f"{len(list(corpus.iterdir()))}, failures saved {len(crashes)}{' (in ' + str(work) + ')' if final else ''}",
              file=sys.stderr, flush=True)

    def one(data: bytes) -> None:
        stats["runs"] += 1
        try:
            outcome = target.run(data)
        except FuzzFailure:
            report(final=True)
            raise  # libFuzzer saves the input as crash-<sha1> in the work folder and stops
        stats["ok" if outcome.startswith(("ok", "opened")) or name == "gate" else "refused"] += 1
        now = time.monotonic()
        # libFuzzer ends the process from C at -max_total_time (no atexit): report as we go.
        if now - last[0] >= 10 or now - t0 >= seconds - 0.5 and last[0] < t0 + seconds - 0.5:
            last[0] = now
            report(final=now - t0 >= seconds - 0.5)

    import numpy  # noqa: F401 - third-party code imported first stays uninstrumented (speed):
    import yaml  # noqa: F401   coverage is wanted in this project's parsers only
    with atheris.instrument_imports():
        # Coverage-guide the code under test (imported here, after instrumentation is on).
        import vs2t_edge.firmware_bridge.protocol  # noqa: F401
        import vs2t_edge.runtime.bundle  # noqa: F401
        import vs2t_edge.runtime.config  # noqa: F401
        import vs2t_edge.runtime.replay  # noqa: F401
    args = [sys.argv[0], f"-max_total_time={seconds}", f"-timeout={int(HANG_S) + 5}", f"-max_len={max_len}",
            "-rss_limit_mb=3072", "-error_exitcode=1", "-timeout_exitcode=1", f"-artifact_prefix={work}/",
            f"-dict={dict_file}", "-print_final_stats=1",
            str(corpus)]
    atheris.Setup(args, one)
    atheris.Fuzz()
    return 0  # atheris.Fuzz exits the process itself


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vs2t_edge.sim.fuzz", description=__doc__.split("\n\n")[0])
    ap.add_argument("target", choices=TARGETS)
    ap.add_argument("--seconds", type=int, default=60, help="fuzzing time (default 60)")
    ap.add_argument("--base", type=Path, default=None,
                    help="the valid bundle / replay folder / config file to start from (default: tests/replays "
                         "bundle, tests/replays/touched.replay, systemd/cell.yaml)")
    ap.add_argument("--work", type=Path, default=None, help="corpus and crash folder (default /tmp/vs2t-fuzz-TARGET)")
    ap.add_argument("--seeds-only", action="store_true", help="only replay the committed seeds, no atheris")
    args = ap.parse_args(argv)
    work = args.work or Path(tempfile.gettempdir()) / f"vs2t-fuzz-{args.target}"
    if args.seeds_only:
        target = make_target(args.target, work / "target", args.base)
        failed = 0
        for path, seed in load_seeds(args.target):
            try:
                data = target.seed_bytes(seed)
                outcome = run_seed(target, seed, data)
                check_seed(target, seed, outcome)
                print(f"ok    {path.name}: {outcome[:120]}")
            except FuzzFailure as exc:
                failed += 1
                print(f"FAIL  {path.name}: {exc}")
        return 1 if failed else 0
    return run_atheris(args.target, args.seconds, work, args.base)


if __name__ == "__main__":
    sys.exit(main())

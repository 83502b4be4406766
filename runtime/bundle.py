"""The model bundle: the one thing that crosses from training to the cell (docs/bundle.md).

A bundle is a folder::

    manifest.json        format, classes, preprocessing, beta, gating, router, files + sha256, probe
    trunk.onnx           image (N, 3, S, S) float32 -> feature (N, D), standardised (fp32 or QDQ int8)
    heads.onnx           feature (N, D) -> logits_t (N, C_t), logits_u (N, C_u)  (always fp32)
                         format 2 (the fused press graph): no heads.onnx; trunk.onnx also outputs
                         logits_t, logits_u and the router's / scene model's projections
                         (router_z, scene_z; export/fuse.py), one onnxruntime call per press
    router.npz           runtime.novelty Router.to_params()
    probe_input.npy      one preprocessed press (1, 3, S, S) float32
    probe_expected.npz   feature, logits_t, logits_u, novelty the exporter's onnxruntime gave for it

``load_bundle`` reads and checks everything that can be checked without running a graph:
format and version, the manifest's own seal (``manifest_sha256``: the sha256 of its canonical
JSON without that key, so a hand-edited or bit-flipped beta, class list or preprocessing is
refused like a changed graph), every file's presence and sha256, each graph's opset (read from the ONNX
protobuf itself, so the cell needs no ``onnx`` package), the router's parameters and dimension,
the class lists. ``check_session_shapes`` compares the sessions' inputs/outputs with the manifest
once the graphs are open; ``runtime.inference.TactileModel.load`` then warms up and checks the
probe. Every refusal is a ``BundleError`` whose message names the file or key that mismatches.
"""

from __future__ import annotations

import hashlib
import json
import math
import zipfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vs2t_edge.runtime.files import MAX_JSON_BYTES, InputRefused, read_regular_file
from vs2t_edge.runtime.manifest_fields import (BundleError, _float, _get, _inside, _int, _names,  # noqa: F401
                                              _need, _no_duplicate_keys, _shapes, _short)
from vs2t_edge.runtime.onnx_opsets import read_onnx_opsets  # noqa: F401 - re-exported (runtime.bundle API)
from vs2t_edge.runtime.preprocess import TactilePreprocess

FORMAT = "vs2t-bundle"
FORMAT_VERSION = 2  # what the exporter writes: a trunk bundle is one fused press graph (docs/bundle.md)
SPLIT_VERSION = 3  # ... and for a bundle with a scene model: the press graph ends at scene_z, heads.onnx apart
READ_VERSIONS = (1, 2, 3)  # 1: trunk.onnx + heads.onnx, router and scene projection in numpy; still loaded
# Opsets this runtime accepts for the default ONNX domain (ai.onnx).
# MIN_OPSET: the oldest any exporter of this project wrote (17, before the move to 20; those
# bundles still load). MAX_OPSET: the newest opset the INSTALLED onnxruntime implements. ONNX
# Runtime's compatibility docs (onnxruntime.ai/docs/reference/compatibility.html and
# docs/Versioning.md, "Version matrix") say a release implements the opsets of the ONNX release it
# is built on, and runs every model stamped with an opset from 7 up to that one; the release's
# CPU kernel registry (get_all_opkernel_def) lists each kernel from the opset that introduced its
# current version, so its highest default-domain version is that opset (28 for onnxruntime 1.32;
# never above it, so never too generous). Without the registry: 20, what onnxruntime 1.17 - the
# oldest pyproject.toml allows - implements per that matrix.
MIN_OPSET = 17
ORT_FLOOR_OPSET = 20


def onnxruntime_max_opset() -> int:
    """The newest ai.onnx opset the installed onnxruntime implements (see MAX_OPSET above)."""
    try:
        from onnxruntime.capi import onnxruntime_pybind11_state as _ort

        versions = [int(k.version_range[0]) for k in _ort.get_all_opkernel_def()
                    if k.domain in ("", "ai.onnx") and k.provider == "CPUExecutionProvider"]
    except Exception:  # no onnxruntime here, or a build without the registry call: the documented floor
        return ORT_FLOOR_OPSET
    return max([ORT_FLOOR_OPSET, *versions])


MAX_OPSET = onnxruntime_max_opset()


def _ort_version() -> str:
    try:
        import onnxruntime

        return onnxruntime.__version__
    except ImportError:
        return "(not installed)"
MANIFEST = "manifest.json"
# The manifest's own digest, kept inside it. It catches corruption and hand edits; it is not a
# signature - whoever can rewrite the folder can recompute it (docs/bundle.md, "What the hashes prove").
SEAL_KEY = "manifest_sha256"
GRAPH_KEYS = ("trunk", "heads")
# the fused press graph's outputs beyond feature / logits_t / logits_u (export/fuse.py)
ROUTER_OUT, SCENE_OUT = "router_z", "scene_z"
NOVELTY_OUT = "router_novelty"  # (N, 1): a router on the logits, folded into the press graph (export/fuse.py)
LOGIT_ROUTERS = ("energy", "max_softmax", "calibrated_stacking")


def sha256_file(path: Path | str, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            block = f.read(chunk)
            if not block:
                break
            h.update(block)
    return h.hexdigest()


# ------------------------------------------------------------------ the bundle


@dataclass(frozen=True)
class Bundle:
    root: Path
    manifest: dict
    touched: tuple[str, ...]
    untouched: tuple[str, ...]
    preprocess: TactilePreprocess
    feature_dim: int
    beta: float
    gating_temperature: float
    gating_scale: float | None  # None = linear gate (manifest gating.transform = "linear")
    router: Any  # runtime.novelty.Router
    probe_input: np.ndarray
    probe_expected: dict[str, np.ndarray]
    probe_tolerance: dict[str, float]
    opsets: dict[str, dict[str, int]] = field(default_factory=dict)
    scene_model: Any = None  # runtime.scene_model.SceneModel, or None for a bundle without one (router path)
    # the tactile feature: None = the ONNX trunk (graphs.trunk); else runtime.tactile_descriptor's
    # DescriptorFeature (manifest "trunk": {"kind": "descriptor", ...}), numpy, no graph
    descriptor: Any = None
    probe_frames: np.ndarray | None = None  # descriptor bundles: (2, H, W, 3) uint8, [reference, press]
    # the tactile camera's MJPEG quality the model was trained and exported on (manifest "camera_jpeg",
    # train --camera-jpeg); 0 = lossless frames, and every bundle without the key
    camera_jpeg: int = 0

    def path(self, key: str) -> Path:
        return self.root / self.manifest["graphs"][key]["file"]

    @property
    def classes(self) -> tuple[str, ...]:
        return self.touched + self.untouched


def not_a_bundle_hint(root: Path) -> str:
    """What to do with a folder given as a bundle that has no manifest: the usual mix-ups (a training
    run, a dataset) named, and where a bundle comes from."""
    if (root / "metrics.json").is_file() and (root / "config.yaml").is_file():
        return f"it is a training run: export it first, `vs2t-edge export {root} --out BUNDLE`, and give BUNDLE"
    if (root / "dataset.yaml").is_file():
        return ("it is a dataset: train on it (`vs2t-edge train DS --out RUN`), export the run "
                "(`vs2t-edge export RUN --out BUNDLE`) and give BUNDLE")
    return "a bundle is the folder `vs2t-edge export RUN --out BUNDLE` writes"


def read_manifest(root: Path | str) -> dict:
    root = Path(root)
    if not root.is_dir():
        raise BundleError(root, "not a folder")
    path = root / MANIFEST
    if not path.is_file():
        raise BundleError(root, f"no {MANIFEST}; {not_a_bundle_hint(root)}")
    try:
        manifest = json.loads(read_regular_file(path, MAX_JSON_BYTES, MANIFEST), object_pairs_hook=_no_duplicate_keys)
    except InputRefused as exc:  # a FIFO (would block for ever), a device, or far too large
        raise BundleError(root, f"{MANIFEST} refused: {str(exc).split(': ', 1)[-1]}") from None
    except OSError as exc:
        raise BundleError(root, f"{MANIFEST} cannot be read ({exc.strerror or exc})") from None
    except RecursionError:
        raise BundleError(root, f"{MANIFEST} is nested too deeply to be a manifest") from None
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, integers past 4300 digits, duplicates
        raise BundleError(root, f"{MANIFEST} is not valid JSON ({str(exc)[:200]})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        found = manifest.get("format") if isinstance(manifest, dict) else "?"
        raise BundleError(root, f"{MANIFEST} format is {_short(found)}, expected {FORMAT!r}")
    version = manifest.get("format_version")
    if version not in READ_VERSIONS or isinstance(version, bool):
        raise BundleError(root, f"format version {_short(version)}, this runtime reads versions "
                                f"{', '.join(map(str, READ_VERSIONS))} (re-export the bundle with this release)")
    return manifest


def manifest_digest(manifest: dict) -> str:
    """sha256 of the manifest's canonical JSON (sorted keys, no spaces, ASCII escapes, NaN and
    Infinity as Python writes them) without its own seal: independent of indentation and key order."""
    body = {k: v for k, v in manifest.items() if k != SEAL_KEY}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=True)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def seal_manifest(manifest: dict) -> dict:
    """The manifest with its seal set: what the exporter writes (and nothing on the cell does)."""
    return {**{k: v for k, v in manifest.items() if k != SEAL_KEY}, SEAL_KEY: manifest_digest(manifest)}


def verify_seal(root: Path, manifest: dict) -> None:
    seal = manifest.get(SEAL_KEY)
    if not isinstance(seal, str):
        raise BundleError(root, f"{MANIFEST} carries no '{SEAL_KEY}' (written by hand or by an older exporter): "
                                "re-export the bundle")
    try:
        actual = manifest_digest(manifest)
    except (ValueError, TypeError, RecursionError) as exc:  # not re-serialisable: cannot be what was sealed
        raise BundleError(root, f"{MANIFEST} cannot be re-serialised to check its seal ({str(exc)[:120]})") from None
    if actual != seal:
        raise BundleError(root, f"{MANIFEST} was changed after export: its content hashes to {actual[:12]}..., "
                                f"'{SEAL_KEY}' says {seal[:12] if isinstance(seal, str) else _short(seal)}... (set beta with calibrate-threshold's "
                                "override, never by editing the manifest)")


def is_descriptor(manifest: dict) -> bool:
    """The bundle's tactile feature is a numpy descriptor, not an ONNX trunk (docs/bundle.md)."""
    return "trunk" in manifest


def is_fused(manifest: dict) -> bool:
    """A format-2 or -3 trunk bundle: trunk.onnx is the press graph (format 2: the heads and every
    projection in it; format 3: ``is_split``)."""
    return manifest.get("format_version") in (FORMAT_VERSION, SPLIT_VERSION) and not is_descriptor(manifest)


def is_split(manifest: dict) -> bool:
    """A format-3 trunk bundle: trunk.onnx is the press graph of a scene decision (feature,
    scene_z) and heads.onnx the heads with the router's outputs on the feature, which the cell's
    press path never runs (export/fuse.py)."""
    return manifest.get("format_version") == SPLIT_VERSION and not is_descriptor(manifest)


def graph_keys(manifest: dict) -> tuple[str, ...]:
    """The ONNX graphs a bundle holds: trunk and heads (formats 1 and 3), the fused trunk alone
    (format 2), or the heads alone behind a descriptor."""
    if is_descriptor(manifest):
        return ("heads",)
    return ("trunk",) if is_fused(manifest) and not is_split(manifest) else GRAPH_KEYS


def _used_files(manifest: dict) -> dict[str, Any]:
    """{manifest key: file name} of every file the loader opens (names unchecked here)."""
    used = {f"graphs.{k}.file": _get(manifest, "graphs", k, "file") for k in graph_keys(manifest)}
    if is_descriptor(manifest):
        used.update({"trunk.file": _get(manifest, "trunk", "file"), "probe.frames": _get(manifest, "probe", "frames")})
    used.update({"router.file": _get(manifest, "router", "file"), "probe.input": _get(manifest, "probe", "input"),
                 "probe.expected": _get(manifest, "probe", "expected")})
    if "decision" in manifest:
        used["decision.file"] = _get(manifest, "decision", "file")
    return used


def verify_hashes(root: Path, manifest: dict) -> None:
    files = _need(manifest, root, "files")
    if not isinstance(files, dict) or not files:
        raise BundleError(root, "manifest.json 'files' is empty")
    for key, name in _used_files(manifest).items():
        if name is None:
            raise BundleError(root, f"manifest.json lacks '{key}'")
        _inside(root, name, key)
        if name not in files:
            raise BundleError(root, f"file {name!r} ('{key}') is used but not listed with a sha256 in 'files'")
    for name, digest in files.items():
        p = _inside(root, name, f"files.{name}")
        if not p.is_file():
            raise BundleError(root, f"{name} is missing")
        if not isinstance(digest, str):
            raise BundleError(root, f"manifest.json 'files.{name}' = {_short(digest)} is not a sha256 text")
        try:
            actual = sha256_file(p)
        except OSError as exc:
            raise BundleError(root, f"{name} cannot be read ({exc.strerror or exc})") from None
        if actual != digest:
            raise BundleError(root, f"{name}: sha256 {actual[:12]}... does not match the manifest's "
                                    f"{digest[:12]!r}... (file changed or corrupted)")


def manifest_classes(root: Path, manifest: dict) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The manifest's (touched, untouched) class names, checked: names, at least one touched, each
    once. Raises BundleError."""
    touched = _names(_need(manifest, root, "classes", "touched"), root, "classes.touched")
    untouched = _names(_need(manifest, root, "classes", "untouched"), root, "classes.untouched")
    if not touched:
        raise BundleError(root, "manifest.json 'classes.touched' is empty")
    counts = Counter(touched + untouched)  # not list.count per name: O(n^2) on a hostile list
    dup = sorted(c for c, n in counts.items() if n > 1)
    if dup:
        raise BundleError(root, f"class name(s) {dup[:10]} appear more than once in 'classes'")
    return touched, untouched


def load_bundle(root: Path | str, beta_override: float | None = None) -> Bundle:
    """Read and statically verify a bundle (no graph is run here). Raises BundleError."""
    from vs2t_edge.runtime import novelty as nv

    root = Path(root)
    manifest = read_manifest(root)
    verify_seal(root, manifest)
    verify_hashes(root, manifest)
    touched, untouched = manifest_classes(root, manifest)
    pre = _need(manifest, root, "preprocess")
    if not isinstance(pre, dict):
        raise BundleError(root, "manifest.json 'preprocess' must be an object")
    try:
        spec = TactilePreprocess.from_dict(pre)
    except (TypeError, ValueError, OverflowError) as exc:
        raise BundleError(root, f"manifest.json 'preprocess': {exc}") from None
    _check_preprocess(spec, root)
    camera_jpeg = _int(manifest.get("camera_jpeg", 0), root, "camera_jpeg", 0, 100)
    if spec.jpeg_scale > 1 and not camera_jpeg:
        raise BundleError(root, f"manifest.json 'preprocess' has jpeg_scale {spec.jpeg_scale} (frames decoded from "
                                "the camera's JPEG at that scale in training) but no 'camera_jpeg' quality")
    dim = _int(_need(manifest, root, "feature_dim"), root, "feature_dim", 1, 1 << 20)
    beta = _float(_need(manifest, root, "beta"), root, "beta", allow_inf=True)
    if beta_override is not None:
        beta = float(beta_override)
        if math.isnan(beta):
            raise BundleError(root, "beta override is NaN")
    temp = _float(_need(manifest, root, "gating", "temperature"), root, "gating.temperature")
    if temp <= 0:
        raise BundleError(root, f"manifest.json 'gating.temperature' = {temp} must be > 0")
    transform = manifest["gating"].get("transform", "linear")
    if transform == "asinh":
        gscale = _float(_need(manifest, root, "gating", "scale"), root, "gating.scale")
        if gscale <= 0:
            raise BundleError(root, f"manifest.json 'gating.scale' = {gscale} must be > 0")
    elif transform == "linear":
        gscale = None
    else:
        raise BundleError(root, f"manifest.json 'gating.transform' = {_short(transform)}: expected 'asinh' or 'linear'")

    opsets: dict[str, dict[str, int]] = {}
    for key in graph_keys(manifest):
        g = _need(manifest, root, "graphs", key)
        path = _inside(root, _need(manifest, root, "graphs", key, "file"), f"graphs.{key}.file")
        try:
            ops = read_onnx_opsets(path)
        except (ValueError, OSError) as exc:
            raise BundleError(root, f"{path.name} ('graphs.{key}.file'): {exc}") from None
        declared = _int(_need(manifest, root, "graphs", key, "opset"), root, f"graphs.{key}.opset", 1, 1000)
        if ops[""] != declared:
            raise BundleError(root, f"{path.name}: opset {ops['']}, the manifest says {declared}")
        if ops[""] < MIN_OPSET:
            raise BundleError(root, f"{path.name}: opset {ops['']} is older than this runtime accepts "
                                    f"({MIN_OPSET}..{MAX_OPSET}); re-export the run with this version's exporter")
        if ops[""] > MAX_OPSET:
            raise BundleError(root, f"{path.name}: opset {ops['']} is newer than the installed onnxruntime "
                                    f"{_ort_version()} implements (up to {MAX_OPSET}); upgrade onnxruntime "
                                    "or re-export with an older opset")
        for section in ("inputs", "outputs"):
            _shapes(g.get(section), root, f"graphs.{key}.{section}")
        opsets[key] = ops

    router_file = _inside(root, _need(manifest, root, "router", "file"), "router.file")
    router_name = _need(manifest, root, "router", "name")
    try:
        with _npz(router_file, root, "router.file") as z:
            router = nv.Router.from_params({k: z[k] for k in z.files})
    except _DATA_ERRORS as exc:
        raise BundleError(root, f"{router_file.name} ('router.file'): {exc}") from None
    if router.name != router_name:
        raise BundleError(root, f"{router_file.name} holds router '{router.name}', the manifest says "
                                f"{_short(router_name)}")
    rdim = getattr(router, "dim", None)
    if rdim is not None and rdim != dim:
        raise BundleError(root, f"{router_file.name}: router fitted on {rdim}-d features, feature_dim is {dim}")
    r_classes = getattr(router, "n_classes", None)  # a class-conditional router models every touched class
    if r_classes is not None and r_classes != len(touched):
        raise BundleError(root, f"{router_file.name}: router '{router.name}' models {r_classes} touched classes, "
                                f"the manifest's classes.touched names {len(touched)}")

    scene_model = _load_scene_model(root, manifest, touched + untouched, dim, spec.size)

    probe_in = _inside(root, _need(manifest, root, "probe", "input"), "probe.input")
    probe_exp = _inside(root, _need(manifest, root, "probe", "expected"), "probe.expected")
    try:
        x = np.load(probe_in, allow_pickle=False)
        if not isinstance(x, np.ndarray):
            if hasattr(x, "close"):
                x.close()
            raise ValueError("not a single .npy array")
        with _npz(probe_exp, root, "probe.expected") as z:
            expected = {k: np.asarray(z[k]) for k in z.files}
    except _DATA_ERRORS as exc:
        raise BundleError(root, f"probe files unreadable ({exc})") from None
    descriptor, frames = None, None
    if is_descriptor(manifest):
        from vs2t_edge.runtime.tactile_descriptor import load_descriptor_feature

        descriptor, frames = load_descriptor_feature(root, manifest, dim)
    want = (1, dim) if descriptor is not None else (1, 3, spec.size, spec.size)
    if x.shape != want or x.dtype != np.float32:
        raise BundleError(root, f"{probe_in.name}: {x.dtype} {x.shape}, expected float32 {want}")
    fused = is_fused(manifest)
    outputs = {**(_get(manifest, "graphs", "trunk", "outputs") or {}),
               **((_get(manifest, "graphs", "heads", "outputs") or {}) if is_split(manifest) else {})}
    extra = [k for k in (ROUTER_OUT, NOVELTY_OUT, SCENE_OUT) if fused and k in outputs]
    for k in ("feature", "logits_t", "logits_u", "novelty", *extra):
        if k not in expected:
            raise BundleError(root, f"{probe_exp.name} lacks '{k}'")
    tol = _need(manifest, root, "probe", "tolerance")
    tolerance = {k: _float(tol.get(k) if isinstance(tol, dict) else None, root, f"probe.tolerance.{k}")
                 for k in ("feature", "logits", "novelty", *(("projection",) if fused else ()))}
    return Bundle(root=root, manifest=manifest, touched=touched, untouched=untouched, preprocess=spec,
                  feature_dim=dim, beta=beta, gating_temperature=temp, gating_scale=gscale, router=router, probe_input=x,
                  probe_expected=expected, probe_tolerance=tolerance, opsets=opsets, scene_model=scene_model,
                  descriptor=descriptor, probe_frames=frames, camera_jpeg=camera_jpeg)


def _load_scene_model(root: Path, manifest: dict, classes: tuple[str, ...], dim: int, size: int):
    """The optional scene decision model (runtime/scene_model.py); None when the manifest has none.
    Refused when the trunk runs at another input size than the run was trained at: the scene
    model and its operating point were fitted on that size's features (docs/bundle.md)."""
    if "decision" not in manifest:
        return None
    trained = (manifest.get("provenance") or {}).get("trained_size_px")
    if isinstance(trained, int) and not isinstance(trained, bool) and trained != size:
        raise BundleError(root, f"the trunk takes {size} px input (manifest.json 'preprocess.size'), but the run was "
                                f"trained at {trained} px (provenance.trained_size_px), and its scene model "
                                "(decision.npz) and operating point were fitted on features of that size: they would "
                                "decide on other features (on the paper run at 96 px: mis-sorts 0.9 -> 3.8 %). "
                                "Export the run at its own size, or train at the size you want")
    from vs2t_edge.runtime.scene_model import KIND, SceneModel, SceneModelError

    kind = _need(manifest, root, "decision", "kind")
    if kind != KIND:
        raise BundleError(root, f"manifest.json 'decision.kind' = {_short(kind)}: this runtime knows {KIND!r}")
    path = _inside(root, _need(manifest, root, "decision", "file"), "decision.file")
    try:
        with _npz(path, root, "decision.file") as z:
            model = SceneModel.from_params({k: z[k] for k in z.files})
    except (*_DATA_ERRORS, SceneModelError) as exc:
        raise BundleError(root, f"{path.name} ('decision.file'): {exc}") from None
    # the manifest's classes in order, then the fabrics the model knows only to refuse (scene_model.py)
    if model.classes != classes + model.known_only or set(model.known_only) & set(classes):
        raise BundleError(root, f"{path.name}: scene model classes {list(model.classes)[:6]}... are not the "
                                f"manifest's classes in order" + (f" then its known_only {list(model.known_only)}"
                                                                    if model.known_only else ""))
    if set(model.untouched) != set(classes[len(classes) - len(model.untouched):]) or \
            len(model.untouched) != len(_get(manifest, "classes", "untouched") or []):
        raise BundleError(root, f"{path.name}: scene model's untouched classes are not the manifest's")
    if model.dim != dim:
        raise BundleError(root, f"{path.name}: scene model fitted on {model.dim}-d features, feature_dim is {dim}")
    return model


# What reading a listed data file may raise when the manifest points a key at the wrong kind of
# file (router.file = "probe_input.npy") or the parameters inside are not what the key needs.
_DATA_ERRORS = (ValueError, OSError, EOFError, KeyError, IndexError, TypeError, zipfile.BadZipFile)


def _npz(path: Path, root: Path, key: str):
    z = np.load(path, allow_pickle=False)
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError(f"'{key}' names {path.name}, which is not an .npz archive")
    return z


def _check_preprocess(spec: TactilePreprocess, root: Path) -> None:
    """TactilePreprocess does not check its fields; the cell resizes and divides with them."""
    ok = (isinstance(spec.size, int) and not isinstance(spec.size, bool) and 8 <= spec.size <= 4096
          and isinstance(spec.crop_fraction, (int, float)) and not isinstance(spec.crop_fraction, bool)
          and 0 < spec.crop_fraction <= 1
          and len(spec.mean) == 3 and len(spec.std) == 3
          and all(math.isfinite(m) for m in spec.mean) and all(math.isfinite(s) and s > 0 for s in spec.std)
          and isinstance(spec.use_reference, bool) and isinstance(spec.inpaint_markers, bool)
          and isinstance(spec.normalise_exposure, bool)
          and (spec.reduce == 0 or spec.size <= 4096 // spec.reduce))  # reduce itself: TactilePreprocess
    if not ok:
        raise BundleError(root, f"manifest.json 'preprocess' = {_short(spec.to_dict())}: size 8..4096 px "
                                "(8..4096 / reduce with reduce), crop_fraction in (0, 1], 3 finite means, "
                                "3 positive stds, use_reference, inpaint_markers and normalise_exposure true/false")


# ------------------------------------------------------------------ sessions


def session_options(threads: int = 2):
    """onnxruntime options for a small dedicated CPU: see docs/bundle.md "Session"."""
    import onnxruntime as ort

    if threads < 1:
        raise ValueError(f"threads = {threads} must be >= 1")
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)  # the trunk's convolutions split over the cores
    so.inter_op_num_threads = 1  # the graphs are a chain: no parallel branches worth a pool
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL  # fusions, QDQ -> QLinear
    so.enable_cpu_mem_arena = True  # one arena, reused press after press (no malloc per run)
    so.enable_mem_pattern = True  # static shapes at batch 1: plan buffers once
    # No busy-waiting after a run: on 2 cores a spinning pool thread steals the core the next
    # numpy step (router, preprocessing) needs. Measured here: router 7.2 -> 1.1 ms per press,
    # trunk 2.9 -> 2.5 ms (EfficientNet-Lite0 128 px) with spinning off.
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    so.log_severity_level = 3
    return so


def open_session(path: Path, threads: int = 2):
    import onnxruntime as ort

    return ort.InferenceSession(str(path), sess_options=session_options(threads), providers=["CPUExecutionProvider"])


def _dims(shape) -> list:
    return [d if isinstance(d, int) else None for d in shape]


def check_session_shapes(bundle: Bundle, key: str, session) -> None:
    """The open graph's input/output names and fixed dimensions are the manifest's."""
    g = bundle.manifest["graphs"][key]
    for section, actual in (("inputs", session.get_inputs()), ("outputs", session.get_outputs())):
        declared = g[section]
        got = {a.name: _dims(a.shape) for a in actual}
        if set(got) != set(declared):
            raise BundleError(bundle.root, f"{g['file']}: {section} {sorted(got)}, the manifest says {sorted(declared)}")
        for name, shape in declared.items():
            if len(shape) != len(got[name]) or any(d is not None and d != a for d, a in zip(shape, got[name])):
                raise BundleError(bundle.root, f"{g['file']}: {section[:-1]} '{name}' has shape {got[name]}, "
                                               f"the manifest says {shape}")
    # and the manifest agrees with the rest of the bundle
    s = bundle.preprocess.size
    if is_fused(bundle.manifest) and (key == "trunk" or is_split(bundle.manifest)):
        _check_press_outputs(bundle, key, g)
    if key == "trunk":
        if len(g["inputs"]) != 1 or (len(g["outputs"]) != 1 and not is_fused(bundle.manifest)):
            raise BundleError(bundle.root, f"{g['file']}: inputs {sorted(g['inputs'])}, outputs {sorted(g['outputs'])}: "
                                           "a trunk graph takes one image and gives one feature")
        (shape_in,) = g["inputs"].values()
        shape_out = g["outputs"].get("feature") if is_fused(bundle.manifest) else next(iter(g["outputs"].values()))
        if shape_out is None:
            raise BundleError(bundle.root, f"{g['file']}: no output 'feature'")
        if list(shape_in[1:]) != [3, s, s]:
            raise BundleError(bundle.root, f"{g['file']}: input {shape_in}, preprocessing makes (N, 3, {s}, {s})")
        if shape_out[-1] != bundle.feature_dim:
            raise BundleError(bundle.root, f"{g['file']}: feature dim {shape_out[-1]}, feature_dim is {bundle.feature_dim}")
    else:
        inputs = list(g["inputs"].values())
        if len(inputs) != 1 or inputs[0][-1] != bundle.feature_dim:
            # else onnxruntime's own error at the probe, not a refusal naming the file
            raise BundleError(bundle.root, f"{g['file']}: inputs {g['inputs']}, the heads take one "
                                           f"(N, {bundle.feature_dim}) feature")
        want = {"logits_t": len(bundle.touched), "logits_u": len(bundle.untouched)}
        for name, n in want.items():
            if name not in g["outputs"] or g["outputs"][name][-1] != n:
                raise BundleError(bundle.root, f"{g['file']}: output '{name}' is not (N, {n}) for the "
                                               f"{n} class names in the manifest")


def _check_press_outputs(bundle: Bundle, key: str, g: dict) -> None:
    """A fused press graph (format 2) outputs exactly what this bundle's router and scene model read:
    feature and logits, a Gaussian router's router_z (the manifest's width), a scene model's scene_z;
    and may output a router on the logits' novelty (router_novelty, N x 1; bundles exported before
    it was folded in leave it to numpy). Format 3 (``is_split``) shares them out: trunk.onnx gives
    feature and scene_z (it needs a scene model), heads.onnx the rest (``key``: which graph)."""
    from vs2t_edge.runtime.novelty import GaussianRouter

    d = bundle.feature_dim
    split = is_split(bundle.manifest)
    if split and bundle.scene_model is None:
        raise BundleError(bundle.root, f"format version {SPLIT_VERSION} is a scene decision's press graph, and "
                                       "this bundle has no scene model (manifest.json 'decision')")
    want = {"feature": d, "logits_t": len(bundle.touched), "logits_u": len(bundle.untouched)}
    if isinstance(bundle.router, GaussianRouter):
        where = "heads" if split else "trunk"  # the graph that outputs router_z
        width = _get(bundle.manifest, "graphs", where, "fused", ROUTER_OUT, "width")
        if isinstance(width, bool) or not isinstance(width, int) or not d <= width <= 2 * d:
            raise BundleError(bundle.root, f"manifest.json 'graphs.{where}.fused.{ROUTER_OUT}.width' = {_short(width)}: "
                                           f"the Gaussian router's projection is {d}..{2 * d} wide")
        want[ROUTER_OUT] = width
    if bundle.scene_model is not None:
        want[SCENE_OUT] = bundle.scene_model.k
    if NOVELTY_OUT in g["outputs"] and bundle.router.name in LOGIT_ROUTERS:
        want[NOVELTY_OUT] = 1
    if split:  # the press graph ends at the scene projection; the heads' graph takes the feature
        press = ("feature", SCENE_OUT)
        want = {k: v for k, v in want.items() if (k in press) == (key == "trunk")}
    if set(g["outputs"]) != set(want):
        raise BundleError(bundle.root, f"{g['file']}: outputs {sorted(g['outputs'])}, this bundle's router "
                                       f"'{bundle.router.name}'{' and scene model' if bundle.scene_model else ''} "
                                       f"need {sorted(want)}")
    for name, width in want.items():
        if g["outputs"][name][-1] != width:
            raise BundleError(bundle.root, f"{g['file']}: output '{name}' is not (N, {width})")


__all__ = ["FORMAT", "FORMAT_VERSION", "READ_VERSIONS", "is_fused", "MIN_OPSET", "MAX_OPSET", "ORT_FLOOR_OPSET", "onnxruntime_max_opset", "SEAL_KEY", "Bundle", "BundleError", "load_bundle",
           "manifest_classes", "read_manifest", "graph_keys", "is_descriptor", "manifest_digest", "seal_manifest", "verify_seal", "verify_hashes", "read_onnx_opsets",
           "sha256_file", "session_options", "open_session", "check_session_shapes"]

"""`vs2t-edge verify-bundle BUNDLE`: the cell's own verification, run by hand (or in CI).

Exit 0 when the bundle loads, warms up and passes its probe; 1 when a bundle (a folder with a
manifest.json) is refused (the reason, naming the file or key, on stderr); 2 when the path is no
folder or a folder without a manifest: bad input, not a bundle that failed its check.
"""

from __future__ import annotations

import sys
from pathlib import Path


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("bundle", help="bundle folder (manifest.json + graphs)")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads (default 2)")


def run(args) -> int:
    from vs2t_edge.runtime.bundle import MANIFEST, BundleError, not_a_bundle_hint
    from vs2t_edge.runtime.inference import TactileModel

    path = Path(args.bundle)
    if not path.is_dir():
        print(f"verify-bundle: {path} is not a folder", file=sys.stderr)
        return 2
    if not (path / MANIFEST).is_file():
        print(f"verify-bundle: {path} is not a bundle (no {MANIFEST}): {not_a_bundle_hint(path)}", file=sys.stderr)
        return 2
    try:
        model = TactileModel.load(path, threads=args.threads)
    except BundleError as exc:
        print(f"verify-bundle: REFUSED - {exc}", file=sys.stderr)
        return 1
    m = model.manifest
    worst = max(model.probe_errors.values())
    print(f"bundle {path}: ok")
    if model.descriptor is not None:
        print(f"  tactile feature: the {model.descriptor.name} descriptor (no trunk graph), {m['feature_dim']}-d")
    else:
        trunk = m["graphs"]["trunk"]
        print(f"  trunk {trunk.get('arch', '?')} {trunk.get('precision', '?')} at {model.preprocess_spec.size} px, "
              f"opset {trunk['opset']}, feature {m['feature_dim']}-d")
        heads = (f"; the heads apart, off the press path ({', '.join(m['graphs']['heads']['outputs'])})"
                 if model.split else "")
        print(f"  format {m['format_version']}: " + (f"one press graph per press ({', '.join(trunk['outputs'])}){heads}"
                                                     if model.fused else "two graphs (trunk.onnx, heads.onnx)"))
    print(f"  frames: {frames_trained_on(model)}")
    print(f"  classes: {len(model.touched)} touched, {len(model.untouched)} untouched; router {m['router']['name']}, "
          f"beta {model.beta:.6g}, gating T {model.temperature:.6g}")
    print(f"  {len(m['files'])} files, sha256 verified; probe max relative error {worst:.2e} "
          f"(tolerance {min(model.bundle.probe_tolerance.values()):.0e})")
    prov = m.get("provenance", {})
    print(f"  made {prov.get('time_utc', '?')} from {prov.get('run', 'no run (untrained)')} at commit "
          f"{prov.get('git_commit', '?')}")
    return 0


def frames_trained_on(model) -> str:
    """The tactile frames a bundle was trained on, in words: what its camera should hand it
    (docs/training.md "The camera's JPEG"; the cell says at its first piece when the camera's
    MJPEG quality is another, runtime/jpeg_quality.py)."""
    from vs2t_edge.runtime.preprocess import camera_scale
    from vs2t_edge.runtime.jpeg_quality import trained_quality

    q = trained_quality(model)
    spec = model.preprocess_spec
    if not q:
        return ("lossless (a camera streaming MJPEG costs it accuracy: train with --camera-jpeg at the camera's "
                "quality)")
    scale = camera_scale(spec) if model.descriptor is None else 1
    return f"through the camera's JPEG at q{q}, decoded at " + (f"1/{scale}" if scale > 1 else "full size")


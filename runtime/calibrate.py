"""`vs2t-edge calibrate-threshold`: choose the novelty threshold beta from presses on the cell.

Inputs: presses of fabrics the model was trained on ("touched") and of validation fabrics it
never saw, either from a dataset folder (fabrics named as bundle classes count as touched,
the rest - or those given by ``--validation`` - as validation) or from replay files
(``--touched-replay`` / ``--validation-replay``: every press in the file is of that group), or
live on the cell (``--config`` with ``--live-touched N --live-validation M``: two `vs2t-edge
record` sessions on the config's devices, kept as replay files, then read as above).
Each press is scored by the deployed bundle (same preprocessing, same model) to its novelty.

beta is chosen as the paper does - maximise the mean of the two accuracies (touched kept as
touched, validation flagged untouched) - or, with ``--target-false-untouched R``, flagging as
many validation presses as possible with at most a fraction R of touched presses flagged.
The curve (both rates and their mean against beta) goes to a PNG (matplotlib when importable,
else drawn with OpenCV: the cell has no matplotlib) and a CSV beside it.

The new beta is written atomically (temp file, fsync, rename) to
``<bundle>.beta_override.json`` next to the bundle - the bundle itself stays as its hashes say
- with the previous override kept as ``...json.prev`` and the history inside the file.

Which beta the daemon uses is the service config's to say (runtime/operating_point.py):
its ``beta_override`` number first, then the file its ``beta_override_file`` names, then the
default file above. So with ``--config CELL.yaml`` (the service's config; its bundle is the one
calibrated unless ``--bundle`` is given too, and then they must agree) the override goes where
that daemon reads it: the file ``beta_override_file`` names, else the default file; and a config
with a ``beta_override`` number is refused (exit 2, nothing written) - that number would shadow any
file, the new beta would be silently ignored. Without ``--config`` the default file is written and
the message says it is used only if the service's config sets neither key.

Refuses (exit 2, in words) with fewer than ``--min-presses`` per group, non-finite scores, all
scores equal, or a best balanced accuracy no better than chance.
"""

from __future__ import annotations

import csv
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vs2t_edge.runtime.bundle import SEAL_KEY
from vs2t_edge.runtime.config import ConfigError, load_config
from vs2t_edge.runtime.dataset import load_dataset
from vs2t_edge.runtime.inference import TactileModel
from vs2t_edge.runtime.jpeg_quality import trained_quality
from vs2t_edge.runtime.router_eval import threshold_rates, tune_threshold
from vs2t_edge.runtime.operating_point import (  # noqa: F401 - re-exported for callers of calibrate
    OverrideFileError, override_file_for, override_path_for, read_beta_override, write_beta_override)
from vs2t_edge.runtime.preprocess import FrameError, camera_frame, camera_scale
from vs2t_edge.runtime.progress import Line
from vs2t_edge.runtime.record_cli import record
from vs2t_edge.runtime.replay import ReplayFile


class CalibrationError(ValueError):
    pass


@dataclass(frozen=True)
class Calibration:
    beta: float
    objective: str
    target_false_untouched: float | None
    kept_touched: float  # fraction of touched presses routed to touched at beta
    flagged_validation: float  # fraction of validation presses flagged untouched at beta
    balanced: float
    n_touched: int
    n_validation: int


def choose_beta(novelty_touched, novelty_validation, *, target_false_untouched: float | None = None,
                min_presses: int = 20) -> Calibration:
    t = np.asarray(novelty_touched, dtype=np.float64).ravel()
    v = np.asarray(novelty_validation, dtype=np.float64).ravel()
    for name, a in (("touched", t), ("validation", v)):
        if a.size < min_presses:
            raise CalibrationError(f"only {a.size} {name} presses; at least {min_presses} are needed "
                                   "(press more pieces, or lower --min-presses knowingly)")
        if not np.all(np.isfinite(a)):
            raise CalibrationError(f"{int(np.sum(~np.isfinite(a)))} {name} novelty scores are not finite; "
                                   "the bundle or the frames are broken")
    both = np.concatenate([t, v])
    if np.ptp(both) == 0.0:
        raise CalibrationError(f"every press scored the same novelty ({both[0]:.6g}); nothing to separate - "
                               "are the frames all the same (camera frozen, no contact)?")
    objective = "target" if target_false_untouched is not None else "balanced"
    beta = tune_threshold(t, v, objective=objective, target_false_untouched=target_false_untouched)
    kept, flagged = threshold_rates(t, v, np.array([beta]))
    balanced = 0.5 * (float(kept[0]) + float(flagged[0]))
    # Under a target rate an infinite beta means "flag nothing to keep the rate": not the same
    # refusal as "nothing separates the groups" (the balanced rule's infinite beta), nor the same remedy.
    if objective == "target" and not math.isfinite(beta):
        raise CalibrationError(f"the chosen beta is {beta}: with at most {target_false_untouched:.1%} of touched "
                               "presses flagged, no validation press can be flagged; loosen "
                               "--target-false-untouched or add presses")
    if balanced <= 0.5 + 1e-9 or not math.isfinite(beta):
        raise CalibrationError(f"no threshold separates touched from validation presses better than chance "
                               f"(best balanced accuracy {balanced:.1%}); the validation fabrics look touched "
                               "to this model - check the scene and the bundle")
    return Calibration(beta, objective, target_false_untouched, float(kept[0]), float(flagged[0]), balanced,
                       int(t.size), int(v.size))


def curve(novelty_touched, novelty_validation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Both rates at every threshold where one of them changes (the midpoints between observed
    scores, as ``tune_threshold`` searches) and just outside the observed range.

    Exact, not sampled: novelty scores are heavy-tailed (1e3 .. 1e7 on one bundle), and an even
    grid over that range stepped over the one gap where the paper's rule peaks.
    """
    t, v = np.ravel(novelty_touched).astype(np.float64), np.ravel(novelty_validation).astype(np.float64)
    u = np.unique(np.concatenate([t, v]))
    mids = u[:-1] + 0.5 * (u[1:] - u[:-1])
    lo, hi = float(u[0]), float(u[-1])
    if lo > 0:  # room on a log axis
        ends = [lo / 1.5, hi * 1.5]
    else:
        pad = 0.05 * (hi - lo or 1.0)
        ends = [lo - pad, hi + pad]
    betas = np.concatenate([[ends[0]], mids, [ends[1]]])
    kept, flagged = threshold_rates(t, v, betas)
    return betas, kept, flagged


def write_curve(out_png: Path, novelty_touched, novelty_validation, cal: Calibration,
                old_beta: float | None = None) -> list[Path]:
    """The curve as a PNG (log beta axis when every score is positive) and the same numbers as
    CSV; the chosen beta and the one it replaces are marked."""
    betas, kept, flagged = curve(novelty_touched, novelty_validation)
    log_x = bool(betas[0] > 0)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    csv_path = out_png.with_suffix(".csv")
    with open(csv_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["beta", "touched_kept", "validation_flagged", "mean"])
        for b, k, g in zip(betas, kept, flagged):
            w.writerow([f"{b:.9g}", f"{k:.4f}", f"{g:.4f}", f"{(k + g) / 2:.4f}"])
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 3.6), dpi=100)
        ax.step(betas, kept, where="post", label="touched kept as touched")
        ax.step(betas, flagged, where="post", label="validation flagged untouched")
        ax.step(betas, (kept + flagged) / 2, "k--", where="post", label="mean (paper's rule)")
        ax.axvline(cal.beta, color="r", lw=1, label=f"new beta = {cal.beta:.4g} ({cal.objective})")
        if old_beta is not None and math.isfinite(old_beta) and (not log_x or old_beta > 0):
            ax.axvline(old_beta, color="grey", lw=1, ls=":", label=f"old beta = {old_beta:.4g}")
        if log_x:
            ax.set_xscale("log")
        ax.set_xlabel("novelty threshold beta" + (" (log scale)" if log_x else ""))
        ax.set_ylabel("fraction of presses")
        ax.set_ylim(-0.02, 1.02)
        ax.set_title(f"{cal.n_touched} touched + {cal.n_validation} validation presses", fontsize=9)
        ax.legend(fontsize=7, loc="lower left")
        fig.tight_layout()
        fig.savefig(out_png)
        plt.close(fig)
    except ImportError:
        _draw_curve_cv2(out_png, betas, kept, flagged, cal.beta, log_x)
    return [out_png, csv_path]


def _draw_curve_cv2(out_png: Path, betas, kept, flagged, beta: float, log_x: bool = False) -> None:
    w, h, m = 640, 360, 40
    img = np.full((h, w, 3), 255, np.uint8)
    cv2.rectangle(img, (m, m // 2), (w - m // 2, h - m), (0, 0, 0), 1)
    axis = np.log10 if log_x else (lambda b: b)
    lo, hi = float(axis(betas[0])), float(axis(betas[-1]))

    def px(b, r):
        x = m + (float(axis(b)) - lo) / (hi - lo or 1.0) * (w - 1.5 * m)
        y = (h - m) - r * (h - 1.5 * m)
        return int(round(x)), int(round(y))

    for series, colour in ((kept, (200, 80, 0)), (flagged, (0, 140, 0)), ((kept + flagged) / 2, (0, 0, 0))):
        pts = np.array([px(b, r) for b, r in zip(betas, series)], np.int32)
        cv2.polylines(img, [pts], False, colour, 2)
    x, _ = px(beta, 0)
    cv2.line(img, (x, m // 2), (x, h - m), (0, 0, 255), 1)
    cv2.putText(img, f"beta={beta:.4g}{' (log axis)' if log_x else ''}  blue: touched kept, green: validation "
                "flagged, black: mean",
                (m, h - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.imwrite(str(out_png), img)


# --- the override file: runtime/operating_point.py owns it (names kept importable here) --------

# --- scoring presses ---------------------------------------------------------------------

def novelty_from_dataset(model, dataset_root: Path, validation: list[str] | None = None,
                         progress=None) -> tuple[list[float], list[float]]:
    """Novelty of every press of the dataset, split into touched (bundle classes) and validation.
    A bundle trained through the camera's JPEG (manifest ``camera_jpeg``) scores the dataset's
    frames through it, decoded at its scale, as its camera hands them (``camera_frame``)."""
    q = trained_quality(model)
    scale = camera_scale(model.preprocess_spec) if q else 1
    by = {"reduced_by": scale} if scale != 1 else {}
    ds = load_dataset(dataset_root)
    touched_names = set(model.touched)
    touched, val = [], []
    fabrics = list(ds.fabrics)
    for i, fab in enumerate(fabrics):
        if fab.name in touched_names or fab.id in touched_names:
            group = touched
        elif validation is None or fab.name in validation or fab.id in validation:
            group = val
        else:
            continue
        model.set_reference(camera_frame(fab.load_reference(), q, scale, f"{fab.id} reference frame"), **by)
        for k in range(len(fab.presses)):
            try:
                group.append(model.press_novelty(camera_frame(fab.load_press(k), q, scale, f"{fab.id} press {k}"), **by))
            except FrameError:
                continue  # a bad frame says nothing about beta
        if progress:
            progress(i + 1, len(fabrics))
    return touched, val


def novelty_from_replays(model, files: list[Path]) -> list[float]:
    out = []
    for f in files:
        rf = ReplayFile.open(f)
        # a session recorded from a camera that decoded at 1/n: the model is told, as the cell was
        reduced = {"reduced_by": rf.frame_scale()} if rf.frame_scale() != 1 else {}
        for _, ref, frames in rf.frames_by_item():
            model.set_reference(ref, **reduced)
            for frame in frames:
                try:
                    out.append(model.press_novelty(frame, **reduced))
                except FrameError:
                    continue
    return out


def add_arguments(parser, verb: str) -> None:
    parser.add_argument("--bundle", default=None, help="the deployed bundle folder (default: the --config's)")
    parser.add_argument("--config", default=None,
                        help="the service's cell config: write the override where that daemon reads it, refuse "
                             "if its beta_override would shadow it")
    parser.add_argument("--dataset", help="dataset folder: bundle classes = touched, others = validation")
    parser.add_argument("--validation", nargs="*", help="with --dataset: only these fabrics (names or ids) "
                                                        "are validation fabrics")
    parser.add_argument("--touched-replay", nargs="*", default=[], help="replay files of touched fabrics")
    parser.add_argument("--validation-replay", nargs="*", default=[], help="replay files of validation fabrics")
    parser.add_argument("--live-touched", type=int, default=0, metavar="N",
                        help="with --config and --live-validation: press N pieces of touched fabrics live on the "
                             "cell (recorded as `vs2t-edge record` does), then M validation pieces, and calibrate "
                             "on those presses (stop the service first: the devices are single-user)")
    parser.add_argument("--live-validation", type=int, default=0, metavar="M",
                        help="pieces of validation fabrics to press live after the touched ones")
    parser.add_argument("--live-dir", default=None,
                        help="where the live sessions are kept (default: calibration/ beside the bundle)")
    parser.add_argument("--target-false-untouched", type=float, default=None,
                        help="max fraction of touched presses flagged untouched (default: the paper's rule)")
    parser.add_argument("--min-presses", type=int, default=20, help="refuse with fewer presses per group")
    parser.add_argument("--curve", default=None, help="curve PNG (default: next to the bundle)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--dry-run", action="store_true", help="print the beta, write nothing")
    parser.add_argument("--for-router", action="store_true",
                        help="calibrate a bundle that decides with its scene model anyway: its beta moves no piece "
                             "there, only the router's columns of the bench (refused without this flag)")


def _override_target(args) -> tuple[Path | None, Path | None, str]:
    """(bundle, override file to write, problem): where the daemon of ``--config`` reads beta."""
    if args.config is None:
        if args.bundle is None:
            return None, None, "give --bundle (the deployed bundle) or --config (the service's config)"
        bundle = Path(args.bundle)
        return bundle, override_path_for(bundle), ""
    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        return None, None, str(exc)
    bundle = Path(cfg.bundle)
    if args.bundle is not None and Path(args.bundle).resolve() != bundle.resolve():
        return None, None, (f"--bundle {args.bundle} is not the bundle {args.config} deploys ({bundle}); "
                            "calibrate the bundle the service runs")
    path, problem = override_file_for(cfg)
    return bundle, path, problem


def decides_with_scene_model(bundle: Path) -> bool:
    """Whether ``bundle``'s manifest lists a scene model (the cell then decides with it, and beta
    moves no piece); False when the manifest cannot be read (the load says why, later)."""
    from vs2t_edge.runtime.bundle import BundleError, read_manifest

    try:
        manifest = read_manifest(bundle)
    except (BundleError, OSError, ValueError):
        return False
    return isinstance(manifest, dict) and isinstance(manifest.get("decision"), dict)


def _record_live(args, bundle: Path) -> int:
    """Live presses: one `vs2t-edge record` session per group on the config's devices, kept as
    replay files (the evidence behind the new beta) and then read like --touched-replay /
    --validation-replay. Returns an exit code, 0 when both sessions were recorded."""
    if args.config is None or args.live_touched < 1 or args.live_validation < 1:
        print("calibrate-threshold: live presses need --config (the cell's devices) and both "
              "--live-touched N and --live-validation M (pieces, at least 1 each)", file=sys.stderr)
        return 2
    folder = Path(args.live_dir) if args.live_dir else bundle.parent / "calibration"
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    for group, pieces, into in (("touched", args.live_touched, args.touched_replay),
                                ("validation", args.live_validation, args.validation_replay)):
        out = folder / f"{group}-{stamp}.replay"
        print(f"calibrate-threshold: feed {pieces} piece(s) of {group} fabrics; recording into {out}",
              file=sys.stderr, flush=True)
        code = record(args.config, out, pieces)
        if code:
            print(f"calibrate-threshold: the {group} session ended with exit {code}; nothing calibrated "
                  f"(what was recorded is in {folder})", file=sys.stderr)
            return code
        into.append(str(out))
    return 0


def run(args) -> int:
    bundle, override, problem = _override_target(args)
    if problem and not (args.dry_run and bundle is not None):
        print(f"calibrate-threshold: {problem}", file=sys.stderr)
        return 2
    if problem:  # --dry-run: say it, write nothing anyway
        print(f"calibrate-threshold: note: {problem}", file=sys.stderr)
        override = override_path_for(bundle)
    if not args.for_router and decides_with_scene_model(bundle):
        # said before any live session: the presses would be pressed for nothing
        print(f"calibrate-threshold: bundle {bundle} decides every piece with its scene model (decision.npz); beta, "
              "the router's threshold, moves no piece there, so calibrating it would change nothing the cell sorts. "
              "The scene model's operating point (its confidences and off-scene rules) was chosen in training on "
              "validation fabrics (docs/decision.md). Give --for-router to calibrate the router's beta anyway (the "
              "bench's router columns read it)", file=sys.stderr)
        return 2
    if args.live_touched or args.live_validation:
        code = _record_live(args, bundle)
        if code:
            return code
    if not args.dataset and not (args.touched_replay and args.validation_replay):
        print("calibrate-threshold: give --dataset, both --touched-replay and --validation-replay, or "
              "--config with --live-touched N and --live-validation M", file=sys.stderr)
        return 2
    if args.target_false_untouched is not None and not 0.0 <= args.target_false_untouched <= 1.0:
        print("calibrate-threshold: --target-false-untouched must be between 0 and 1", file=sys.stderr)
        return 2
    try:
        model = TactileModel.load(bundle, threads=args.threads, beta_override=None)
    except Exception as exc:  # noqa: BLE001
        print(f"calibrate-threshold: bundle {bundle} refused: {exc}", file=sys.stderr)
        return 2
    try:
        if args.dataset:
            line = Line()
            touched, val = novelty_from_dataset(model, Path(args.dataset), args.validation,
                                                lambda i, n: line.draw(f"scoring fabric {i}/{n}", i / n))
            line.keep()
        else:
            touched = novelty_from_replays(model, [Path(p) for p in args.touched_replay])
            val = novelty_from_replays(model, [Path(p) for p in args.validation_replay])
        cal = choose_beta(touched, val, target_false_untouched=args.target_false_untouched,
                          min_presses=args.min_presses)
    except (CalibrationError, ValueError) as exc:
        print(f"calibrate-threshold: refused: {exc}", file=sys.stderr)
        return 2
    png = Path(args.curve) if args.curve else bundle.parent / f"{bundle.name}.beta_curve.png"
    old = float(model.beta) if getattr(model, "beta", None) is not None else None
    try:
        in_force = read_beta_override(override)
    except OverrideFileError:
        in_force = None  # a damaged override is replaced (and kept as .prev)
    written = write_curve(png, touched, val, cal, old_beta=in_force if in_force is not None else old)
    print(f"beta {cal.beta:.6g} ({cal.objective}): touched kept {cal.kept_touched:.1%}, validation flagged "
          f"{cal.flagged_validation:.1%}, mean {cal.balanced:.1%} on {cal.n_touched}+{cal.n_validation} presses"
          f" (bundle's beta {old:.6g}" + (f", override in force {in_force:.6g})" if in_force is not None else ")")
          if old is not None else ")")
    print("curve: " + ", ".join(str(p) for p in written))
    if args.dry_run:
        return 0
    had_old = override.exists()
    override.parent.mkdir(parents=True, exist_ok=True)  # a beta_override_file in a folder not made yet
    sources = args.dataset or " ".join(["touched:", *args.touched_replay, "validation:", *args.validation_replay])
    seal = (getattr(model, "manifest", None) or {}).get(SEAL_KEY)  # the daemon refuses the file for another bundle
    path = write_beta_override(override, cal, bundle_beta=old, source=sources, bundle_seal=seal)
    print(f"written {path}" + (f" (previous kept as {path.name}.prev)" if had_old else "")
          + ("; restart the service to use it" if args.config else
             "; the service uses it after a restart if its config sets neither beta_override nor "
             "beta_override_file (give --config to check and to write where the config points)"))
    return 0

"""An int8 bundle's scene model, its real class means moved to where the int8 trunk puts them.

Training fits the scene model (runtime/scene_model.py) on the fp32 trunk's features. A touched
class's mean is the mean of its training presses in the model's whitened space. A fabric known only
to be refused (a validation fabric, ``known_only``) sits at the mean of its own training presses
in the same way. Quantisation does not only add noise from press to press: part of its shift is
the same on every press of a fabric. On the paper world's deployment bundle that part is half of
the shift. So the int8 trunk's presses of a touched fabric sit off the mean the model keeps for
it, and its pieces are less often confident.

``shift_real_means`` reads each such fabric's training presses through both graphs. It moves the
fabric's mean by the difference of the two means, in the model's own space. The untouched classes
keep the generator's means, so no untouched fabric's tactile data reaches this step. Nothing else
of the model moves: the projection, the operating point and the synthesised means stay as training
chose them. docs/bundle.md, "int8", has what it buys.
"""

from __future__ import annotations

from typing import Callable, Iterable, Sequence

import numpy as np

# the stored mean against the same presses re-read through the fp32 graph, rms a dimension of the
# whitened space (where a press spreads about 1): above it, they are not the presses training
# fitted the mean on (another dataset, another max_presses), and moving the mean would be a guess
REREAD_TOLERANCE = 1e-2


def real_mean_presses(part: dict[str, dict[str, list[int]]], touched: Sequence[str],
                      known_only_part: dict[str, dict[str, list[int]]]) -> dict[str, list[int]]:
    """{class: press indices} of the presses whose mean is each real class mean: a touched
    fabric's training presses (``part``, export/from_run.py ``press_partition``), and the same
    partition of each known-only fabric's extracted presses (train/decision.py ``with_known``)."""
    out = {fid: list(part[fid]["train"]) for fid in touched}
    out.update({fid: list(p["train"]) for fid, p in known_only_part.items()})
    return out


def shift_real_means(scene_model: dict, presses: Iterable[tuple[str, np.ndarray]],
                     fp32: Callable[[np.ndarray], np.ndarray],
                     int8: Callable[[np.ndarray], np.ndarray]) -> tuple[dict, dict]:
    """``scene_model``'s parameters with the mean of every class in ``presses`` moved by the int8
    trunk's shift of that class's presses: stored mean + mean(int8 presses) - mean(fp32 presses),
    projected. ``presses`` yields (class, preprocessed frames); ``fp32`` / ``int8`` map frames to
    features. A synthesised class is refused: its mean is the generator's. So is a class whose
    presses, re-read through the fp32 graph, do not give back its stored mean (``REREAD_TOLERANCE``).
    Returns (parameters, what the manifest records: the presses read, how far the means moved, and
    how well the fp32 presses re-read give the stored means)."""
    from vs2t_edge.runtime.scene_model import SceneModel

    model = SceneModel.from_params(scene_model)
    means = np.array(model.means, dtype=np.float64, copy=True)
    moved, reread, n = {}, [], 0
    for cls, x in presses:
        if cls not in model.classes:
            raise ValueError(f"scene model: no class {cls!r} to move")
        if cls in model.untouched:
            raise ValueError(f"scene model: {cls!r} is a synthesised class; its mean is the generator's")
        if not len(x):
            raise ValueError(f"scene model: no presses of {cls!r} to re-read")
        row = model.classes.index(cls)
        m32, m8 = model.project(fp32(x)).mean(axis=0), model.project(int8(x)).mean(axis=0)
        reread.append(float(np.sqrt(np.mean((m32 - model.means[row]) ** 2))))
        if not reread[-1] <= REREAD_TOLERANCE:
            raise ValueError(f"scene model: the {len(x)} presses of {cls!r} re-read through the fp32 graph lie "
                             f"{reread[-1]:.3g} rms a dimension from its stored mean (tolerance {REREAD_TOLERANCE}): "
                             "they are not the presses training fitted it on (the run's dataset and max_presses?); "
                             "export with --no-int8-scene-means to keep the means as trained")
        moved[cls] = float(np.sqrt(np.mean((m8 - m32) ** 2)))
        means[row] = model.means[row] + (m8 - m32)
        n += len(x)
    if not moved:
        raise ValueError("scene model: no real class means to move")
    shifts = np.array(list(moved.values()))
    check = {"classes": len(moved), "presses": n,
             "shift_rms_per_dim_median": float(np.median(shifts)), "shift_rms_per_dim_max": float(shifts.max()),
             "fp32_reread_rms_per_dim_max": float(max(reread)),
             "rule": "each real class mean (touched and known-only fabrics) moved by mean(int8) - mean(fp32) of "
                     "its training presses in the scene model's whitened space; synthesised means unchanged",
             "note": "fp32_reread: the stored means against the same presses re-read through the fp32 graph "
                     "(about 0 when they are the presses training fitted the means on)"}
    return {**scene_model, "means": means}, check


__all__ = ["REREAD_TOLERANCE", "real_mean_presses", "shift_real_means"]

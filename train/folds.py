"""More validation fabrics for the scene decision: folds of the touched fabrics held out of a
generator trained on the others.

The scene decision (train/decision.py) chooses its operating point on validation jobs whose
untouched part is played by fabrics the generator never read: the split's few validation fabrics
(5 of 50 on the paper-sized world). Five fabrics are too few. One split's five looked easy to the
generator (validation ZSL 94 %, test 40 %) and chose a caution that left half of its touched test
pieces in the reject bin; two others met 1 % mis-sorts on validation and mis-sorted 1.5 and 2.8 %
of their test jobs' pieces. ``fold_worlds`` adds worlds of the same kind from the touched fabrics
themselves: split them into ``n_folds`` folds; for each, train the generator (the split's own
method and budget) on the other touched fabrics' training presses, synthesise the held-out fold's
fabrics from their camera crops and attributes, and let them play validation fabrics - their
training and validation presses the pieces, the other touched fabrics the touched part. Every
touched fabric so serves once as a fabric the generator never read.

What no fold reads: the split's untouched (test) fabrics and the touched fabrics' test presses.
Nor do a fold's features, where training makes them (``features``; train/run.py
``fold_features``): its tactile tail and, where the run fine-tunes one (the paper profile), its
visual tail are fine-tuned afresh on the kept fabrics alone. A tail fine-tuned on every touched
fabric's label has learnt to tell a held-out fabric from its touched siblings, which no tail does
for a real untouched fabric. On the demo world without folds, in split 3's test jobs that listed
both, 17 of an untouched felt's 24 pieces went into its touched sibling's bin (docs/decision.md,
"More validation fabrics"). What the folds still share with the split's own world: the feature
scaling (per-dimension mean and spread of every touched fabric's training presses, the held-out
ones' too; no label). Each fold's generator sees fewer fabrics than the deployed one (a quarter
fewer with 4 folds). All of that is said where the numbers are
(docs/results/scene_decision_rules_paper.md).
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from vs2t_edge.train.baselines import ZSLData
from vs2t_edge.train.decision import ValidationWorld

FOLD_SEED = 104729  # the folds of split seed s are drawn with s + this


def folds_fit(n_folds: int, n_touched: int) -> bool:
    """Whether ``n_touched`` fabrics make ``n_folds`` folds: at least 2, each holding out at least 2."""
    return 2 <= n_folds <= n_touched // 2


def fold_assignment(n_touched: int, n_folds: int, seed: int) -> list[np.ndarray]:
    """``n_folds`` disjoint sorted index sets covering ``range(n_touched)``, drawn from ``seed``."""
    if not folds_fit(n_folds, n_touched):
        raise ValueError(f"validation folds: {n_folds} folds of {n_touched} touched fabrics; "
                         "need at least 2 folds and 2 fabrics in each")
    order = np.random.default_rng(seed + FOLD_SEED).permutation(n_touched)
    return [np.sort(part) for part in np.array_split(order, n_folds)]


def fold_data(train: ZSLData, touched_val: tuple, held: np.ndarray) -> tuple[ZSLData, tuple, tuple]:
    """(the generator's data without the ``held`` touched fabrics, those fabrics as untouched ones;
    the held fabrics' presses - training then validation, in press order - with their index into
    ``held``; the kept fabrics' validation presses with their index into the kept ones).
    ``train``: the split's touched training data; ``touched_val``: (x_t, x_v, y) of its touched
    validation presses."""
    n_t = train.n_t
    keep = np.setdiff1d(np.arange(n_t), held)
    new_kept = np.full(n_t, -1)
    new_kept[keep] = np.arange(len(keep))
    new_held = np.full(n_t, -1)
    new_held[held] = np.arange(len(held))
    x_tv, v_tv, y_tv = touched_val
    tr_keep, tr_held = np.isin(train.y, keep), np.isin(train.y, held)
    va_keep, va_held = np.isin(y_tv, keep), np.isin(y_tv, held)
    # each held fabric's presses in press order: its training presses, then its validation ones
    order = np.argsort(np.concatenate([new_held[train.y[tr_held]], new_held[y_tv[va_held]]]), kind="stable")
    x_t = np.concatenate([train.x_t[tr_held], x_tv[va_held]])[order]
    x_v = np.concatenate([train.x_v[tr_held], v_tv[va_held]])[order]
    y = np.concatenate([new_held[train.y[tr_held]], new_held[y_tv[va_held]]])[order]
    names = list(train.names_t)
    data = ZSLData(x_t=train.x_t[tr_keep], x_v=train.x_v[tr_keep], y=new_kept[train.y[tr_keep]],
                   attr_t=train.attr_t[keep], attr_u=train.attr_t[held], v_u=x_v, v_u_class=y,
                   names_t=[names[i] for i in keep], names_u=[names[i] for i in held])
    return data, (x_t, y), (x_tv[va_keep], new_kept[y_tv[va_keep]])


def fold_worlds(method, train: ZSLData, touched_val: tuple, budget, *, n_folds: int, seed: int,
                features: Callable[[list[str]], tuple[ZSLData, tuple]] | None = None,
                log=lambda m: None) -> list[ValidationWorld]:
    """One ``ValidationWorld`` per fold of the touched fabrics (module doc). ``method``: the split's
    fitted generative method (VS2T-ZSL); a fresh generator of its kind (``unregistered``) is trained
    per fold with the same ``budget``, its ensemble too. ``features``: the held-out fabrics' names ->
    ``train`` and ``touched_val`` of the same split (same fabrics, rows and order) in features from
    tails that never read those fabrics (train/run.py ``fold_features``); None: ``train``'s own."""
    worlds = []
    for i, held in enumerate(fold_assignment(train.n_t, n_folds, seed)):
        t0 = time.time()
        fold_train, fold_val = (train, touched_val) if features is None else \
            features([train.names_t[j] for j in held])
        if list(fold_train.names_t) != list(train.names_t) or not np.array_equal(fold_train.y, train.y) \
                or not np.array_equal(fold_val[-1], touched_val[-1]):
            raise ValueError(f"validation fold {i + 1}: its features name other touched fabrics or rows than the split's")
        data, presses, kept_val = fold_data(fold_train, fold_val, held)
        gen = type(method).unregistered().fit_generators(data, budget, seed + 1 + i)
        worlds.append(ValidationWorld(data.x_t, data.y, list(data.names_t), kept_val, list(data.names_u), presses,
                                      gen.synthesise(data, budget, seed)))
        log(f"validation fold {i + 1}/{n_folds}: {'own fine-tuning and ' if features is not None else ''}generator on "
            f"{data.n_t} touched fabrics, {len(held)} held out as validation fabrics ({time.time() - t0:.0f} s)")
    return worlds


__all__ = ["FOLD_SEED", "folds_fit", "fold_assignment", "fold_data", "fold_worlds"]

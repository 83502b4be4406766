"""More validation fabrics for the scene decision: folds of the touched fabrics held out of a
generator trained on the others.

The scene decision (train/decision.py) chooses its operating point on validation jobs whose
untouched part is played by fabrics the generator never read: the split's few validation fabrics
(5 of 50 on the paper-sized world). Five fabrics are too few. One split's five looked easy to the
generator (validation ZSL 94 %, test 40 %) and chose a caution that left half of its touched test
pieces in the reject bin; another's looked hard (33 %, test 75 %) and chose too little, so its test
jobs mis-sorted 2.8 %. ``fold_worlds`` adds worlds of the same kind from the touched fabrics
themselves: split them into ``n_folds`` folds; for each, train the generator (the split's own
method and budget) on the other touched fabrics' training presses, synthesise the held-out fold's
fabrics from their camera crops and attributes, and let them play validation fabrics - their
training and validation presses the pieces, the other touched fabrics the touched part. Every
touched fabric so serves once as a fabric the generator never read.

What no fold reads: the split's untouched (test) fabrics and the touched fabrics' test presses.
What the folds share with the split's own world: the fine-tuned tactile tail, trained on every
touched fabric's training presses, so a held-out fabric's presses are features the tail learnt to
tell apart (a real untouched fabric's are not), and the feature scaling. Each fold's generator
sees a quarter fewer fabrics than the deployed one. Both are said where the numbers are
(docs/results/scene_decision_paper.md).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from vs2t_edge.train.baselines import ZSLData
from vs2t_edge.train.decision import ValidationWorld

FOLD_SEED = 104729  # the folds of split seed s are drawn with s + this


def fold_assignment(n_touched: int, n_folds: int, seed: int) -> list[np.ndarray]:
    """``n_folds`` disjoint sorted index sets covering ``range(n_touched)``, drawn from ``seed``."""
    if not 2 <= n_folds <= n_touched // 2:
        raise ValueError(f"validation folds: {n_folds} folds of {n_touched} touched fabrics; "
                         "need at least 2 folds and 2 fabrics in each")
    order = np.random.default_rng(seed + FOLD_SEED).permutation(n_touched)
    return [np.sort(part) for part in np.array_split(order, n_folds)]


def fold_data(train: ZSLData, touched_val: tuple, held: np.ndarray) -> tuple[ZSLData, tuple, np.ndarray]:
    """(the generator's data without the ``held`` touched fabrics, those fabrics as untouched ones;
    the held fabrics' presses - training then validation, in press order - with their index into
    ``held``; the kept fabrics' indices). ``train``: the split's touched training data; ``touched_val``:
    (x_t, x_v, y) of its touched validation presses."""
    n_t = train.n_t
    keep = np.setdiff1d(np.arange(n_t), held)
    new_kept = np.full(n_t, -1)
    new_kept[keep] = np.arange(len(keep))
    new_held = np.full(n_t, -1)
    new_held[held] = np.arange(len(held))
    x_tv, v_tv, y_tv = touched_val
    tr_keep, tr_held, va_held = np.isin(train.y, keep), np.isin(train.y, held), np.isin(y_tv, held)
    # each held fabric's presses in press order: its training presses, then its validation ones
    order = np.argsort(np.concatenate([new_held[train.y[tr_held]], new_held[y_tv[va_held]]]), kind="stable")
    x_t = np.concatenate([train.x_t[tr_held], x_tv[va_held]])[order]
    x_v = np.concatenate([train.x_v[tr_held], v_tv[va_held]])[order]
    y = np.concatenate([new_held[train.y[tr_held]], new_held[y_tv[va_held]]])[order]
    names = list(train.names_t)
    data = ZSLData(x_t=train.x_t[tr_keep], x_v=train.x_v[tr_keep], y=new_kept[train.y[tr_keep]],
                   attr_t=train.attr_t[keep], attr_u=train.attr_t[held], v_u=x_v, v_u_class=y,
                   names_t=[names[i] for i in keep], names_u=[names[i] for i in held])
    return data, (x_t, y), keep


def fold_worlds(method, train: ZSLData, touched_val: tuple, budget, *, n_folds: int, seed: int,
                log=lambda m: None) -> list[ValidationWorld]:
    """One ``ValidationWorld`` per fold of the touched fabrics (module doc). ``method``: the split's
    fitted generative method (VS2T-ZSL); a fresh generator of its kind is trained per fold with the
    same ``budget``."""
    worlds = []
    x_tv, _, y_tv = touched_val
    for i, held in enumerate(fold_assignment(train.n_t, n_folds, seed)):
        t0 = time.time()
        data, presses, keep = fold_data(train, touched_val, held)
        gen = object.__new__(type(method))  # not in the class's ``instances``: the split's method stays the fitted one
        gen.name, gen.history = method.name, []
        gen._fit_generator(data, replace(budget, ensemble=1) if hasattr(budget, "ensemble") else budget, seed + 1 + i)
        synth = gen.synthesise(data, budget, seed)
        kept_val = np.isin(y_tv, keep)
        remap = np.full(train.n_t, -1)
        remap[keep] = np.arange(len(keep))
        worlds.append(ValidationWorld(data.x_t, data.y, list(data.names_t), (x_tv[kept_val], remap[y_tv[kept_val]]),
                                      list(data.names_u), presses, synth))
        log(f"validation fold {i + 1}/{n_folds}: generator on {len(keep)} touched fabrics, "
            f"{len(held)} held out as validation fabrics ({time.time() - t0:.0f} s)")
    return worlds


__all__ = ["FOLD_SEED", "fold_assignment", "fold_data", "fold_worlds"]

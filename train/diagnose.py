"""World or model? A linear check on the same features the run used.

For each split: ridge regression (fitted on TOUCHED fabrics only) from a fabric's condition
(mean visual feature + attributes, or either alone) to its mean tactile feature; untouched
fabrics' predicted means are class prototypes; a test press goes to the nearest prototype
(cosine). If this linear map already reaches the generator's ZSL accuracy, the features/world
bound the result; if it is far above, the generator is at fault.

    python -m vs2t_edge.train.diagnose RUN/features/feature_table.npz --splits 5 --holdout 5
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from vs2t_edge.train import compare as cmp


def linear_zsl(table: cmp.FeatureTable, split: cmp.FabricSplit, parts: str, alpha: float = 10.0) -> dict:
    v = cmp.split_views(table, split)
    tr = v.train
    k_t = tr.n_t
    mean_t = np.stack([tr.x_t[tr.y == k].mean(0) for k in range(k_t)])
    mean_v = np.stack([np.clip(tr.x_v[tr.y == k], -4, 4).mean(0) for k in range(k_t)])
    vu = np.clip(tr.v_u, -4, 4)
    mean_vu = np.stack([vu[tr.v_u_class == k].mean(0) for k in range(tr.n_u)])

    def cond(mv, a):
        return np.concatenate({"vs": [mv, a], "v": [mv], "s": [a]}[parts], axis=1)

    a, b = cond(mean_v, tr.attr_t), cond(mean_vu, tr.attr_u)
    mu_a, mu_t = a.mean(0), mean_t.mean(0)
    w = np.linalg.solve((a - mu_a).T @ (a - mu_a) + alpha * np.eye(a.shape[1]), (a - mu_a).T @ (mean_t - mu_t))
    proto = (b - mu_a) @ w + mu_t
    x, _, y = v.test_presses
    xn = x / np.linalg.norm(x, axis=1, keepdims=True)
    pn = proto / np.linalg.norm(proto, axis=1, keepdims=True)
    pred = (xn @ pn.T).argmax(1)
    real = np.stack([x[y == k].mean(0) for k in range(tr.n_u)])
    ss_res = ((real - proto) ** 2).sum()
    ss_tot = ((real - real.mean(0)) ** 2).sum()
    oracle = (xn @ (real / np.linalg.norm(real, axis=1, keepdims=True)).T).argmax(1)
    acc = float(np.mean([np.mean(pred[y == k] == k) for k in range(tr.n_u)]))
    acc_oracle = float(np.mean([np.mean(oracle[y == k] == k) for k in range(tr.n_u)]))
    return {"zsl": acc, "r2_class_means": float(1 - ss_res / ss_tot), "oracle_real_means": acc_oracle}


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("features", help="FeatureTable .npz")
    p.add_argument("--splits", type=int, default=5)
    p.add_argument("--holdout", type=int, default=5)
    args = p.parse_args(argv)
    t = cmp.FeatureTable.load(args.features)
    splits = cmp.make_splits(t.fabric_ids, args.splits, args.holdout, args.holdout)
    out = {}
    for parts in ("vs", "v", "s"):
        r = [linear_zsl(t, s, parts) for s in splits]
        out[parts] = {k: float(np.mean([x[k] for x in r])) for k in r[0]}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

import os
EXP = os.environ.get("VS2T_EXP", "exp")  # the folder of the feature tables ftables.py writes
import sys, numpy as np
from vs2t_edge.train import compare as cmp
def ridge_val(profile, i, parts="vs", alpha=10.0):
    t = cmp.FeatureTable.load(f"{EXP}/{profile}_split{i}.npz")
    k = 5 if len(t.fabric_ids) >= 50 else 3
    sp = cmp.make_splits(t.fabric_ids, i + 1, k, k, seed=0)[i]
    v = cmp.split_views(t, sp); tr = v.val
    mean_t = np.stack([tr.x_t[tr.y == c].mean(0) for c in range(tr.n_t)])
    mean_v = np.stack([np.clip(tr.x_v[tr.y == c], -4, 4).mean(0) for c in range(tr.n_t)])
    vu = np.clip(tr.v_u, -4, 4); mean_vu = np.stack([vu[tr.v_u_class == c].mean(0) for c in range(tr.n_u)])
    cond = lambda mv, a: np.concatenate({"vs": [mv, a], "v": [mv], "s": [a]}[parts], axis=1)
    a, b = cond(mean_v, tr.attr_t), cond(mean_vu, tr.attr_u)
    mu_a, mu_t = a.mean(0), mean_t.mean(0)
    w = np.linalg.solve((a - mu_a).T @ (a - mu_a) + alpha * np.eye(a.shape[1]), (a - mu_a).T @ (mean_t - mu_t))
    proto = (b - mu_a) @ w + mu_t
    x, _, y = v.val_presses
    xn = x / np.linalg.norm(x, axis=1, keepdims=True); pn = proto / np.linalg.norm(proto, axis=1, keepdims=True)
    pred = (xn @ pn.T).argmax(1)
    real = np.stack([x[y == c].mean(0) for c in range(tr.n_u)]); rn = real/np.linalg.norm(real,axis=1,keepdims=True)
    o = (xn @ rn.T).argmax(1)
    f = lambda p: float(np.mean([np.mean(p[y == c] == c) for c in range(tr.n_u)]))
    return f(pred), f(o)
prof = sys.argv[1]; n = int(sys.argv[2])
for parts in ("vs", "v", "s"):
    r = [ridge_val(prof, i, parts) for i in range(n)]
    print(prof, parts, "ridge val", [round(100*a,1) for a,_ in r], round(100*np.mean([a for a,_ in r]),1), "oracle", round(100*np.mean([o for _,o in r]),1))

import os
EXP = os.environ.get("VS2T_EXP", "exp")  # the folder of the feature tables ftables.py writes
import numpy as np, sys
from vs2t_edge.runtime import novelty as nv
from vs2t_edge.train import compare as cmp
from vs2t_edge.train.baselines import train_classifier, predict_logits
import torch; torch.set_num_threads(1)
prof = sys.argv[1]; res = {}
for i in range(5):
    t = cmp.FeatureTable.load(f"{EXP}/{prof}_split{i}.npz")
    k = 5 if len(t.fabric_ids) >= 50 else 3
    sp = cmp.make_splits(t.fabric_ids, i + 1, k, k, seed=0)[i]
    v = cmp.split_views(t, sp)
    x_tr, y_tr = v.train.x_t, v.train.y; x_tv = v.touched_val[0]; x_vp = v.val_presses[0]
    cls_t = train_classifier(x_tr, y_tr, v.train.n_t, hidden=[512, 512], steps=400, seed=sp.seed)
    lt_tv, lt_vp = predict_logits(cls_t, x_tv), predict_logits(cls_t, x_vp)
    for name in ("energy", "max_softmax"):
        r = nv.fit_router(name, None)
        res.setdefault(name, []).append(nv.auroc(r.novelty(x_tv, lt_tv), r.novelty(x_vp, lt_vp)))
    # class-conditional: residuals from class means, shared shrunk covariance, min distance
    means = np.stack([x_tr[y_tr == c].mean(0) for c in range(v.train.n_t)])
    resid = x_tr - means[y_tr]
    r = nv.fit_router("mahalanobis_lw", resid, keep_covariance=False)
    def cm(x):
        return np.min(np.stack([r.novelty(x - mu + r.mean) for mu in means], 1), 1)
    res.setdefault("class_maha_lw", []).append(nv.auroc(cm(x_tv), cm(x_vp)))
    # nearest class mean, euclidean
    def ce(x): return np.min(((x[:, None, :] - means[None]) ** 2).sum(-1), 1)
    res.setdefault("class_euclid", []).append(nv.auroc(ce(x_tv), ce(x_vp)))
for name, rs in res.items():
    print(prof, name, "val AUROC", np.round(100*np.array(rs),1), "mean", round(100*np.mean(rs),1))

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
    x_tr = v.train.x_t; x_tv = v.touched_val[0]; x_vp = v.val_presses[0]
    for name in ("gaussian", "mahalanobis_lw", "mahalanobis_oas"):
        r = nv.fit_router(name, x_tr, keep_covariance=False)
        a, b = r.novelty(x_tv), r.novelty(x_vp)
        beta = nv.tune_threshold(a, b)
        kept, flagged = nv.threshold_rates(a, b, [beta])
        res.setdefault(name, []).append((nv.auroc(a, b), float(kept[0]), float(flagged[0]), getattr(r, "shrinkage", 0)))
for name, rs in res.items():
    rs = np.array(rs)
    print(prof, name, "val AUROC", np.round(100*rs[:,0],1), "mean", round(100*rs[:,0].mean(),1), "shrink", np.round(rs[:,3],3))

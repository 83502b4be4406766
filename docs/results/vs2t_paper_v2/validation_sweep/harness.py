"""Validation-only measurements: fit a VS2T variant on touched training presses, build CLS_u for the
VALIDATION fabrics (views.val), score ZSL on validation presses. Test (untouched) fabrics: never read."""
import os
EXP = os.environ.get("VS2T_EXP", "exp")  # the folder of the feature tables ftables.py writes
import json, sys, time
from dataclasses import replace
import numpy as np, torch
from vs2t_edge.train import compare as cmp, vs2t
from vs2t_edge.train.baselines import predict_logits

torch.set_num_threads(1); torch.set_flush_denormal(True)

def acc(pred, y):
    return float(np.mean([np.mean(pred[y == k] == k) for k in np.unique(y)]))

def measure(profile, splits, budget, variant="VS2T-ZSL", extra=None):
    out = []
    for i in splits:
        t = cmp.FeatureTable.load(f"{EXP}/{profile}_split{i}.npz")
        k = 5 if len(t.fabric_ids) >= 50 else 3
        sp = cmp.make_splits(t.fabric_ids, i + 1, k, k, seed=0)[i]
        views = cmp.split_views(t, sp)
        cls = vs2t.variant_class(variant)
        t0 = time.time()
        m = cls().fit(views.val, budget, sp.seed)   # untouched := validation fabrics
        x, _, y = views.val_presses
        r = {"split": i, "val_zsl": acc(predict_logits(m.cls_u, x).argmax(1), y)}
        xs, ys = m.synthesise(views.val, budget, sp.seed)
        proto = np.stack([xs[ys == c].mean(0) for c in range(views.val.n_u)])
        xn = x / np.linalg.norm(x, axis=1, keepdims=True); pn = proto / np.linalg.norm(proto, axis=1, keepdims=True)
        r["val_proto"] = acc((xn @ pn.T).argmax(1), y)
        r["synth_std"] = float(np.mean([xs[ys == c].std(0).mean() for c in range(views.val.n_u)]))
        r["real_std"] = float(np.mean([x[y == c].std(0).mean() for c in range(views.val.n_u)]))
        r["hist_last"] = m.history[-1]
        r["s"] = round(time.time() - t0, 1)
        out.append(r)
    return {"val_zsl": float(np.mean([r["val_zsl"] for r in out])), "val_proto": float(np.mean([r["val_proto"] for r in out])),
            "per_split": out}

if __name__ == "__main__":
    profile = sys.argv[1]; splits = [int(s) for s in sys.argv[2].split(",")]
    variant = sys.argv[3]
    kw = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
    base = dict(steps=400, batch=64, cls_steps=200, n_synth_per_class=150, lr_scale=5.0, latent=64, hidden=512)
    base.update(kw)
    b = vs2t.VS2TBudget(**base)
    r = measure(profile, splits, b, variant)
    line = {"profile": profile, "splits": splits, "variant": variant, "kw": kw, "val_zsl": round(100*r["val_zsl"],1),
            "val_proto": round(100*r["val_proto"],1),
            "synth_std": round(np.mean([x["synth_std"] for x in r["per_split"]]),3),
            "real_std": round(np.mean([x["real_std"] for x in r["per_split"]]),3),
            "per_split": [round(100*x["val_zsl"],1) for x in r["per_split"]],
            "hist": r["per_split"][0]["hist_last"], "s": sum(x["s"] for x in r["per_split"])}
    print(json.dumps(line))
    with open(f"{EXP}/log.jsonl", "a") as f:
        f.write(json.dumps(line) + "\n")

"""Per-split fine-tuned tactile feature tables (exactly what `vs2t-edge train` feeds the model), cached."""
import os
EXP = os.environ.get("VS2T_EXP", "exp")  # the folder of the feature tables ftables.py writes
import sys, time
from pathlib import Path
import numpy as np, torch
from vs2t_edge.train import compare as cmp, features as ft, run
from vs2t_edge.train.trunks import build_trunk

def tables(run_dir, profile, n_splits, out):
    prof = run.PROFILES[profile]
    torch.set_num_threads(1); torch.set_flush_denormal(True)
    cache = ft.StemCache.load(Path(run_dir) / "features/stem_cache.npz")
    k = run.n_holdout(len(cache.fabric_ids))
    splits = cmp.make_splits(cache.fabric_ids, n_splits, k, k, seed=0)
    torch.manual_seed(0)
    trunk = build_trunk(prof.trunk, pretrained=True)
    for i, sp in enumerate(splits):
        p = Path(out) / f"{profile}_split{i}.npz"
        if p.exists():
            continue
        t0 = time.time()
        rows, y = ft.touched_training_rows(cache.fabric, cache.fabric_ids, sp)
        tuned = ft.finetune_tail(trunk, cache.stem_t[rows], y, len(sp.touched), epochs=prof.ft_epochs,
                                 max_rows=prof.ft_max_rows, seed=sp.seed, progress=False)
        x_t = ft.features_from_stem(tuned, cache.stem_t)
        cmp.FeatureTable(x_t, cache.x_v, cache.fabric, cache.fabric_ids, cache.attributes).save(p)
        print(profile, i, sp.seed, f"{time.time()-t0:.1f}s", file=sys.stderr)

if __name__ == "__main__":
    tables(sys.argv[1], sys.argv[2], int(sys.argv[3]), EXP)

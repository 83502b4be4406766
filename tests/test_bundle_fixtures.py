"""Shared builders for the bundle/inference/export tests (no tests here).

A tiny trunk (2 convs + BN + mean pool, like train/trunks.py's 'tiny') and heads, exported
through the real exporter on frames of the synthetic fabric world (tiny profile, generated once
per test session into a temp folder) so the numbers are those of real-looking presses.
"""
from __future__ import annotations

import functools
import tempfile
from pathlib import Path

import numpy as np

SIZE = 32
TOUCHED = ("t0", "t1", "t2")
UNTOUCHED = ("u0", "u1")


def tiny_modules(seed: int = 0, dim: int = 16):
    import torch
    from torch import nn

    torch.manual_seed(seed)

    class Trunk(nn.Module):
        def __init__(self):
            super().__init__()
            self.body = nn.Sequential(nn.Conv2d(3, 8, 3, 2, 1), nn.BatchNorm2d(8), nn.ReLU(),
                                      nn.Conv2d(8, dim, 3, 2, 1), nn.BatchNorm2d(dim), nn.ReLU())

        def forward(self, x):
            return self.body(x).mean(dim=(2, 3))

    trunk = Trunk()
    with torch.no_grad():  # non-trivial BN statistics so folding them is actually exercised
        for m in trunk.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
    cls_t = nn.Sequential(nn.Linear(dim, 32), nn.LeakyReLU(0.2), nn.Linear(32, len(TOUCHED)))
    cls_u = nn.Sequential(nn.Linear(dim, 32), nn.LeakyReLU(0.2), nn.Linear(32, len(UNTOUCHED)))
    return trunk.eval(), cls_t.eval(), cls_u.eval()


@functools.lru_cache(maxsize=1)
def tiny_world() -> Path:
    from vs2t_edge.sim.synth import generate

    root = Path(tempfile.mkdtemp(prefix="vs2t_tinyworld_"))
    return Path(generate(root / "world", "tiny", 0, progress=False))


@functools.lru_cache(maxsize=4)
def world_frames(size: int = SIZE) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """(preprocessed presses (N, 3, S, S), raw press frames, the reference of fabric 0)."""
    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.runtime.preprocess import TactilePreprocess, preprocess_tactile

    ds = load_dataset(tiny_world())
    spec = TactilePreprocess(size=size)
    xs, raws = [], []
    for fab in ds.fabrics:
        ref = fab.load_reference()
        for i in range(len(fab.presses)):
            f = fab.load_press(i)
            raws.append(f)
            xs.append(preprocess_tactile(f, ref, spec))
    return np.stack(xs).astype(np.float32), raws, ds.fabrics[0].load_reference()


def fit_fixture_router(name: str = "gaussian", seed: int = 0):
    """(router ``name`` fitted as make_bundle fits it, its beta, the torch outputs it was fitted on).

    Feature routers (gaussian, mahalanobis_*, discriminant) are fitted on the tiny trunk's features
    of the first 40 presses (the discriminant router's classes: TOUCHED, a third of them each, in
    press order); the logit routers (energy, max_softmax, calibrated_stacking) have nothing to fit.
    beta is the 0.9 quantile of the router's novelty on those presses."""
    import torch

    from vs2t_edge.runtime import novelty as nv

    trunk, cls_t, cls_u = tiny_modules(seed)
    x, _, _ = world_frames(SIZE)
    with torch.no_grad():
        f = trunk(torch.from_numpy(x[:40]))
        lt, lu = (t.numpy() for t in (cls_t(f), cls_u(f)))
        f = f.numpy()
    if name in nv.GAUSSIAN_ROUTERS:
        router = nv.fit_router(name, f, keep_covariance=False)
    elif name == "discriminant":
        router = nv.fit_router(name, f, touched_labels=np.arange(len(f)) * len(TOUCHED) // len(f))
    else:
        router = nv.fit_router(name, None)
    beta = float(np.quantile(router.novelty(f, lt, logits_u=lu), 0.9))
    return router, beta, (f, lt, lu)


def make_bundle(out: Path, precision: str = "fp32", seed: int = 0, router: str = "gaussian", **kw) -> dict:
    """Export the tiny modules through the real exporter with router ``router`` (any of
    runtime.novelty.ROUTERS); returns the manifest."""
    from vs2t_edge.export.export import write_bundle
    from vs2t_edge.runtime.preprocess import TactilePreprocess

    trunk, cls_t, cls_u = tiny_modules(seed)
    x, _, _ = world_frames(SIZE)
    calib, held, val = x[:40], x[40:60], x[60:]
    fitted, beta, _ = fit_fixture_router(router, seed)
    args = dict(trunk=trunk, cls_t=cls_t, cls_u=cls_u, router=fitted, touched=TOUCHED, untouched=UNTOUCHED,
                preprocess=TactilePreprocess(size=SIZE), beta=beta, calibration=calib, trunk_precision=precision,
                trunk_arch="tiny-test", validation=val, touched_heldout=held)
    args.update(kw)
    return write_bundle(out, **args)


@functools.lru_cache(maxsize=3)
def shared_bundle(precision: str = "fp32", fuse: bool = True) -> Path:
    """One bundle per precision (and format: fused press graph, or ``fuse=False`` the two-graph
    format 1) per test session (export is the slow part)."""
    out = Path(tempfile.mkdtemp(prefix=f"vs2t_bundle_{precision}_")) / "bundle"
    make_bundle(out, precision, fuse=fuse)
    return out

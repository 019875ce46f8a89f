"""Offline check of accumulating OIDN's noisy *input* over frames (docs/notes/flicker.md).
Inputs: /tmp/w/rec.pkl from record_oidn_blend_inputs.py; the 1024-spp animated references in /work/refs.
History: the accumulated colour warped by core.history.warp (same-surface taps), change test on the pooled
variances (floored per pixel), a bias term from the pooled squared difference, at most (max_frames - 1)
frames' samples; OIDN (albedo, normal of this frame) on the accumulated colour."""
import sys, pickle; sys.path.insert(0, "tests"); sys.path.insert(0, "."); import conftest
import numpy as np
from cycles_adaptive.core import history as hi, oidn, io
from cycles_adaptive.core.filters import box_mean_finite
rec = pickle.load(open("/tmp/w/rec.pkl", "rb"))
R = [io.read_reference(f"/work/refs/animated.f{f:04d}.r100.s1024.exr")[..., :3].astype(np.float64) for f in range(1, 9)]
def te(X):
    return float(np.mean([np.mean(((X[k] - X[k - 1]) - (R[k] - R[k - 1])) ** 2 / (R[k] ** 2 + 0.01))
                          for k in range(1, len(X))]))
rel = lambda x, r: float(np.mean((x - r) ** 2 / (r ** 2 + 0.01)))
def run(max_frames, z, resample, pool):
    p = hi.Params(resample=resample, pool_radius=0)
    state = None
    out = []
    for t, d in enumerate(rec):
        C, n = d["color"], d["n"].astype(np.float64)
        var = d["var"]; var = var.mean(-1) if var.ndim == 3 else var
        if state is not None and d["coords"] is not None:
            W, e, L, valid, _ = hi.warp(state, d["coords"], d["surface"], d["cam"], p)
            vp = box_mean_finite(var, pool) if pool else var
            ep = box_mean_finite(np.where(valid, e, np.nan), pool) if pool else e
            ep = np.where(np.isfinite(ep), ep, e)
            d2 = np.mean((C - W) ** 2, -1)
            use = valid & (d2 <= z ** 2 * (np.maximum(vp, var) + np.maximum(ep, e)))
            m = np.where(use, np.minimum(L, (max_frames - 1) * n), 0.0)  # history's samples
            d2p = box_mean_finite(np.where(use, d2, np.nan), pool)
            d2p = np.where(np.isfinite(d2p), d2p, d2)
            b2 = np.maximum(d2p - np.maximum(vp, var) - np.maximum(ep, e), 0.0)
            e = e + b2
            eh = np.maximum(ep, e) + b2
            wc = np.where(use, np.maximum(eh / np.maximum(np.maximum(vp, var) + eh, 1e-30), n / np.maximum(n + m, 1e-9)), 1.0)
            A = wc[..., None] * C + (1 - wc[..., None]) * np.where(use[..., None], W, 0)
            Av = wc ** 2 * var + (1 - wc) ** 2 * np.where(use, e, 0)
            N = n + m
        else:
            A, Av, N = C, var, n
        state = hi.History(A, Av, N, d["surface"])
        out.append(oidn.oidn_filter(A, d["albedo"], d["normal"]))
    return np.array([rel(o, r) for o, r in zip(out, R)]), te(out)
alone = [oidn.oidn_filter(d["color"], d["albedo"], d["normal"]) for d in rec]
base = np.array([rel(o, r) for o, r in zip(alone, R)])
blend = np.array([rel(d["blend"], r) for d, r in zip(rec, R)])
print("oidn on this frame's mean   ", base.mean(), "TE", te(alone), np.round(base, 5))
print("oidn+blend (output blend)   ", blend.mean(), "TE", te([d["blend"] for d in rec]), np.round(blend, 5))
for mf, z, rs, pool in [(2, 3, "catmull-rom", 1), (2, 3, "bilinear", 1), (3, 3, "catmull-rom", 1), (8, 3, "catmull-rom", 1)]:
    a, t = run(mf, z, rs, pool)
    print(f"input accumulation mf={mf} z={z} {rs} pool={pool}", a.mean(), "TE", t, np.round(a, 5), "worse frames", int(np.sum(a > base * 1.0001)))

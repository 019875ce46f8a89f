"""Where courtyard's temporal error comes from (docs/notes/flicker.md). Inputs:
./cycles-adaptive render sample_blends/courtyard.blend --method uniform --spp 8 --frames 1-8 --temporal {none,blend}
  --seed-mode animated --resolution-percentage 25 --out /tmp/w/cu/{none,blend}.####.exr
and the 1024-spp references of bench-sequence in /work/refs.  Run: .venv/bin/python docs/notes/flicker_data/courtyard_te_share.py"""
import sys; sys.path.insert(0, "tests"); sys.path.insert(0, "."); import conftest
import numpy as np
from cycles_adaptive.core import io
R = [io.read_reference(f"/work/refs/courtyard.f{f:04d}.r25.s1024.exr")[..., :3].astype(np.float64) for f in range(1, 9)]
for t in ("none", "blend"):
    X = [io.read_rgb(f"/tmp/w/cu/{t}.{f:04d}.exr")[..., :3].astype(np.float64) for f in range(1, 9)]
    te = []
    for k in range(1, 8):
        d = ((X[k] - X[k-1]) - (R[k] - R[k-1])) ** 2 / (R[k] ** 2 + 0.01)
        te.append(d.mean(-1))
    te = np.stack(te)
    flat = np.sort(te.ravel())[::-1]
    tot = flat.sum()
    print(t, "TE", te.mean(), "share of top 0.1%:", flat[:len(flat)//1000].sum()/tot, "top 1%:", flat[:len(flat)//100].sum()/tot)
    k, y, x = np.unravel_index(np.argmax(te), te.shape)
    print("  worst", k+2, y, x, "X", X[k+1][y, x], X[k][y, x], "R", R[k+1][y, x], R[k][y, x])
    rel = np.mean([((X[k]-R[k])**2/(R[k]**2+0.01)).mean() for k in range(8)])
    print("  relMSE", rel)
print("excluding pixels where the reference exceeds 4 in either frame (the sun glint on the ball):")
for t in ("none", "blend"):
    X = [io.read_rgb(f"/tmp/w/cu/{t}.{f:04d}.exr")[..., :3].astype(np.float64) for f in range(1, 9)]
    s, n = 0.0, 0
    for k in range(1, 8):
        m = (R[k].max(-1) < 4) & (R[k-1].max(-1) < 4)
        d = (((X[k] - X[k-1]) - (R[k] - R[k-1])) ** 2 / (R[k] ** 2 + 0.01)).mean(-1)
        s += d[m].sum(); n += m.sum()
    print(t, "TE", s / n, "share of pixels kept", n / (7 * R[0].shape[0] * R[0].shape[1]))

"""Sample maps the planner keeps: pooling by confidence and to the planner's scale.

A method's sample map (new samples per pixel) follows per-pixel estimates made
from a few sample groups: after the initial pass each pixel's variance has
``k - 1 = 3`` degrees of freedom, so the map is heavy-tailed noise around the
true need (a pixel that drew one firefly asks for hundreds of samples, its
equally noisy neighbours for none).  Two steps between the method and the
planner (:func:`core.regions.plan`) make the map one that region renders can
follow and that is worth following:

1. :func:`confidence_pool`: each pixel's count becomes an inverse-variance
   weighted mean of its 3x3 neighbourhood, the weights following the degrees of
   freedom ``nu = k - 1`` of each estimate: a pixel estimated from few groups
   among well-sampled neighbours gets a bounded share (their value), one with
   many groups keeps its own.  (The loop's cap of twice the iteration's
   mean, ``Options.max_pixel_share``, still applies after both steps.)
2. :func:`pool_to_blocks`: the mean over the planner's aligned ``min_size``
   blocks, so the planner's rectangles cover whole blocks of equal count and
   the samples it adds beyond the map come only from merging blocks to save
   renders.

Both keep the map's total (largest-remainder rounding, :func:`core.method.allocate`).
The pooling runs over row bands on the controller's threads (each band reads
``r`` rows beyond its own); the bits do not depend on the bands or the thread
count.  The total and the rounding stay whole-frame and serial.
Measurements (tools/planner_curve.py): docs/notes/planner.md.
"""
from __future__ import annotations

import numpy as np

from .method import allocate


def confidence_pool(counts: np.ndarray, dof: np.ndarray, radius: int = 1) -> np.ndarray:
    """Confidence-weighted (2r+1)^2 neighbourhood mean of a sample map, same total.

    Each neighbour ``q`` of pixel ``p`` is an estimate of ``p``'s need with its
    own noise (variance ~ 1/nu_q) plus the difference between the two pixels,
    taken as uncertain as ``p``'s own estimate (~ 1/nu_p); inverse-variance
    weights are then ``w_pp = nu_p`` and ``w_pq = nu_p nu_q / (nu_p + nu_q)``.
    So a pixel never trusts a neighbour more than itself, a low-dof pixel among
    well-sampled ones takes their value, and a well-sampled one keeps its own.

    counts : (H, W) non-negative map; dof : (H, W) degrees of freedom of each
    pixel's estimate (``k - 1``; <= 0 or non-finite: none, the pixel takes the
    plain mean of its neighbourhood).  Returns (H, W) int64 summing to
    ``counts.sum()`` (the pooled map is rescaled to the total, then rounded).
    """
    c = np.asarray(counts, np.float64)
    c = np.where(np.isfinite(c) & (c > 0), c, 0.0)
    total = int(round(c.sum()))
    if total <= 0 or c.size == 0:
        return np.zeros(c.shape, np.int64)
    nu = np.broadcast_to(np.asarray(dof, np.float64), c.shape)
    h, w = c.shape
    r = int(radius)
    pooled = np.empty((h, w))

    def band(rows):
        y0, y1 = rows
        _pool_rows(c, nu, r, y0, y1, pooled)

    _run_bands(band, h, w)
    return allocate(pooled, total)


#: pixels per row band of the pooling (rows = BAND_PIXELS // width) and the
#: size below which it runs inline: shape only, never the thread count
BAND_PIXELS = 32768
INLINE_PIXELS = 65536


def _run_bands(fn, h: int, w: int) -> None:
    """``fn((y0, y1))`` over row bands of about :data:`BAND_PIXELS` pixels on
    the controller's threads (:mod:`core.parallel`), inline below
    :data:`INLINE_PIXELS` pixels."""
    from . import parallel
    if h * w == 0:
        return
    rows = max(1, BAND_PIXELS // max(1, w))
    if h * w < INLINE_PIXELS:
        fn((0, h))
        return
    parallel.run_bands(fn, h, rows)


def _pool_rows(c, dof, r, y0, y1, out) -> None:
    """Rows ``y0:y1`` of :func:`confidence_pool`'s pooled (unrounded) map into
    ``out[y0:y1]``, from rows ``y0 - r : y1 + r`` of the cleaned counts ``c``
    and the raw ``dof``, zero-padded outside the image.  Per pixel the same
    operations in the same order as over the whole frame, so the band's
    values are the whole frame's bits."""
    from .buffers import _tmp
    h, w = c.shape
    bh, pw = y1 - y0, w + 2 * r
    a0, a1 = max(0, y0 - r), min(h, y1 + r)
    cp = _tmp("cpool_c", (bh + 2 * r, pw))
    nup = _tmp("cpool_nu", (bh + 2 * r, pw))
    inside = _tmp("cpool_in", (bh + 2 * r, pw))
    for a in (cp, nup, inside):
        a.fill(0.0)
    t0, t1 = a0 - (y0 - r), a1 - (y0 - r)
    cp[t0:t1, r:r + w] = c[a0:a1]
    d = dof[a0:a1]
    nup[t0:t1, r:r + w] = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    inside[t0:t1, r:r + w] = 1.0
    nu = nup[r:r + bh, r:r + w]
    shape = (bh, w)
    num = _tmp("cpool_num", shape)
    den = _tmp("cpool_den", shape)
    plain = _tmp("cpool_plain", shape)
    area = _tmp("cpool_area", shape)
    for a in (num, den, plain, area):
        a.fill(0.0)
    prod = _tmp("cpool_prod", shape)
    s = _tmp("cpool_s", shape)
    wq = _tmp("cpool_w", shape)
    pos = _tmp("cpool_pos", shape, bool)
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            cq, nq, iq = cp[dy:dy + bh, dx:dx + w], nup[dy:dy + bh, dx:dx + w], inside[dy:dy + bh, dx:dx + w]
            if dy == r and dx == r:
                wt = nu
            else:
                np.add(nu, nq, out=s)
                np.multiply(nu, nq, out=prod)
                wq.fill(0.0)
                np.divide(prod, s, out=wq, where=np.greater(s, 0.0, out=pos))
                wt = wq
            np.add(num, np.multiply(wt, cq, out=prod), out=num)
            np.add(den, wt, out=den)
            np.add(plain, np.multiply(cq, iq, out=prod), out=plain)
            np.add(area, iq, out=area)
    ok = np.greater(den, 0.0, out=pos)
    safe = np.where(ok, den, 1.0)
    out[y0:y1] = np.where(ok, num / safe, plain / np.maximum(area, 1.0))


def pool_to_blocks(counts: np.ndarray, size: int) -> np.ndarray:
    """Mean of a sample map over aligned ``size`` x ``size`` blocks (edge
    blocks are smaller), one whole count per block: each block gets the floor
    of its mean, then the blocks with the largest remainders one more, in that
    order, while the total stays within ``counts.sum()``; what is then left
    (less than one block's area) goes as single samples to the pixels of the
    blocks with the largest remainders.  Same total; ``size <= 1`` returns the
    map.  (H, W) int64."""
    c = np.asarray(counts, np.int64)
    size = int(size)
    if size <= 1 or c.size == 0:
        return c.copy()
    h, w = c.shape
    gh, gw = -(-h // size), -(-w // size)
    pad = np.zeros((gh * size, gw * size), np.int64)
    pad[:h, :w] = c
    ones = np.zeros_like(pad)
    ones[:h, :w] = 1
    s = pad.reshape(gh, size, gw, size).sum(axis=(1, 3)).ravel()
    a = ones.reshape(gh, size, gw, size).sum(axis=(1, 3)).ravel()
    base = s // a
    left = int(c.sum() - (base * a).sum())
    frac = s / a - base
    order = np.argsort(-frac, kind="stable")
    take = order[(np.cumsum(a[order]) <= left) & (frac[order] > 0)]
    base[take] += 1
    left -= int(a[take].sum())
    up = lambda g: np.repeat(np.repeat(g.reshape(gh, gw), size, axis=0), size, axis=1)[:h, :w]
    out = up(base).astype(np.int64)
    if left > 0:  # less than a block's worth: single samples where the remainders are largest
        rest = up(np.where((frac > 0) & (base == s // a), frac, 0.0))  # per block, then to pixels
        out += allocate(rest, left)
    return out


def cap_share(counts: np.ndarray, share: float) -> np.ndarray:
    """A map with no pixel above ``share`` times its mean (at least 1), the
    excess spread over the other pixels in proportion to the map (same total
    when possible); ``share <= 0`` or an empty map returns it unchanged."""
    total = int(counts.sum())
    if share <= 0 or total <= 0:
        return counts
    cap = max(1, int(np.ceil(share * total / counts.size)))
    if counts.max() <= cap:
        return counts
    return allocate(counts.astype(np.float64), total, cap=np.full(counts.shape, cap, np.int64))

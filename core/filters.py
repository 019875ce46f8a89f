"""Reusable image filters: box sums, the guided image filter, NL-means with the
variance-cancelling distance of Rousselle et al. 2013, and the Sobel gradient.

All functions are pure numpy, vectorised across pixels (Python loops run only
over window offsets, patch offsets, row chunks or image axes), work on
``(H, W)`` or ``(H, W, C)`` arrays and return float64.  Borders are handled by
*clipping*: a window or patch that leaves the image uses only the pixels inside
it (and, for NL-means, only the pixel pairs whose both members lie inside).

Used by ``core/rhf.py`` (Liu, Zheng, Yuan 2018) and usable by other methods.
"""
from __future__ import annotations

import numpy as np

from . import parallel

__all__ = [
    "box_count",
    "box_sum",
    "box_mean",
    "box_mean_finite",
    "guided_filter",
    "guided_filter_mean",
    "nlm_pixel_distance",
    "nlm_filter",
    "nlm_center_weights",
    "window_offsets",
    "sobel_gradient",
]

#: Largest magnitude any filter lets through (inputs are clipped to it), so
#: squares and sums of squares of inputs stay finite in float64.
VALUE_LIMIT = 1e30
#: Largest variance accepted (VALUE_LIMIT ** 2).
VAR_LIMIT = 1e60
#: Frames below this many pixels run the row strips of ``nlm_filter`` and
#: ``guided_filter_mean`` on the calling thread; larger ones on
#: :mod:`core.parallel`'s pool (strips are cut by the shape only and each
#: writes only its own rows: the same bits for any thread count).
THREAD_MIN_PIXELS = 1 << 16


def _finite(x, limit=VALUE_LIMIT, fill=0.0, dtype=np.float64):
    """Copy (one allocation) with NaN -> ``fill`` and values clipped to
    [-limit, limit] (so +-inf -> +-limit)."""
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.array(x, dtype=dtype, copy=True)
    np.nan_to_num(out, copy=False, nan=fill, posinf=limit, neginf=-limit)
    np.clip(out, -limit, limit, out=out)
    return out


def _finite_or_self(x, limit=VALUE_LIMIT):
    """``_finite(x)`` without the copy when x is float64 and already finite
    within [-limit, limit] (the common case; the caller must not modify it)."""
    x = np.asarray(x)
    if x.dtype == np.float64 and np.isfinite(x).all() and (
            x.size == 0 or (x.max() <= limit and x.min() >= -limit)):
        return x
    return _finite(x, limit)


def _finite_var(v, limit=VAR_LIMIT, dtype=np.float64):
    """Variances (copy): NaN/negative -> 0, +inf and huge -> ``limit``."""
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.array(v, dtype=dtype, copy=True)
    np.nan_to_num(out, copy=False, nan=0.0, posinf=limit, neginf=0.0)
    np.clip(out, 0.0, limit, out=out)
    return out


# --------------------------------------------------------------------------- box
def box_count(n: int, r: int) -> np.ndarray:
    """(n,) number of positions of a length-n axis within distance r of each index."""
    i = np.arange(n)
    return (np.minimum(n - 1, i + r) - np.maximum(0, i - r) + 1).astype(np.float64)


def _box_sum_axis_blocked(x: np.ndarray, r: int, axis: int) -> np.ndarray:
    """Clipped window sum along ``axis`` in O(1) per element for any r.

    Block-wise prefix/suffix sums (the van Herk / Gil-Werman decomposition used
    for running sums): the axis, zero-padded by r, is cut into blocks of length
    L = 2r + 1; any window of length L is the suffix of one block plus the
    prefix of the next.  Unlike a global cumulative sum this never subtracts
    two large partial sums, so one huge value (1e30) does not destroy the
    precision of windows that do not contain it.
    """
    x = np.moveaxis(x, axis, 0)
    n = x.shape[0]
    L = 2 * r + 1
    m = n + 2 * r
    nb = -(-m // L) + 1
    z = np.zeros((nb * L,) + x.shape[1:], x.dtype)
    z[r:r + n] = x
    zb = z.reshape((nb, L) + x.shape[1:])
    pre = np.cumsum(zb, axis=1).reshape(z.shape)
    suf = np.cumsum(zb[:, ::-1], axis=1)[:, ::-1].reshape(z.shape)
    out = suf[:n] + pre[L - 1:L - 1 + n]
    out[::L] = suf[:n:L]          # windows starting on a block boundary: one block
    return np.moveaxis(out, 0, axis)


def _window_sums(z: np.ndarray, L: int, axis: int, start: int, stop: int) -> np.ndarray:
    """Sums of ``L`` consecutive elements of ``z`` along ``axis``, for window
    starts ``start .. stop - 1`` (z already zero-padded as needed).

    Binary doubling: sums over 1, 2, 4, ... consecutive elements are built by
    one addition each and a window of L is the sum of the powers of two in L's
    binary expansion -- about 2 log2(L) additions per element, no subtraction.
    """
    nd = z.ndim

    def sl(a, b):
        idx = [slice(None)] * nd
        idx[axis] = slice(a, b)
        return tuple(idx)

    n = stop - start
    sums = {1: z}
    p = 1
    lo, hi = start, start + n + L - 1          # range of z that matters
    while 2 * p <= L:
        s = sums[p]
        m = s.shape[axis]
        if p == 1:
            s = s[sl(lo, hi)]
            m = s.shape[axis]
            sums[1] = s
        sums[2 * p] = s[sl(0, m - p)] + s[sl(p, m)]
        p *= 2
    if L == 1:
        sums[1] = z[sl(lo, hi)]
    parts = []
    off = 0
    while p >= 1:
        if L & p:
            parts.append(sums[p][sl(off, off + n)])
            off += p
        p //= 2
    if len(parts) == 1:
        return parts[0].copy()
    out = np.add(parts[0], parts[1])           # the first two added into a new array
    for part in parts[2:]:
        np.add(out, part, out=out)
    return out


def _box_sum_axis_doubling(x: np.ndarray, r: int, axis: int) -> np.ndarray:
    """Clipped window sum along ``axis`` (zero padding + ``_window_sums``)."""
    n = x.shape[axis]
    shape = list(x.shape)
    shape[axis] = n + 2 * r
    z = np.zeros(shape, x.dtype)
    idx = [slice(None)] * x.ndim
    idx[axis] = slice(r, r + n)
    z[tuple(idx)] = x
    return _window_sums(z, 2 * r + 1, axis, 0, n)


def _box_sum_axis(x: np.ndarray, r: int, axis: int) -> np.ndarray:
    if r <= 0:
        return x.copy()
    if r <= 16:
        return _box_sum_axis_doubling(x, r, axis)
    return _box_sum_axis_blocked(x, r, axis)


def box_sum(x: np.ndarray, r: int, dtype=np.float64) -> np.ndarray:
    """Sum of ``x`` over the (2r+1) x (2r+1) window around each pixel, clipped.

    Parameters
    ----------
    x : (H, W) or (H, W, C) array
    r : int, window radius (0 returns a copy)
    dtype : float dtype of the computation (float64 by default).

    Returns
    -------
    (H, W[, C]) array.  Separable; each axis costs O(log r) additions per
    element for r <= 16 (binary doubling) and O(1) for larger r (block
    prefix/suffix sums), with no subtraction of partial sums, so a huge value
    never spoils the precision of windows that do not contain it (He et al.
    2010, Sec. 4: the box filter behind the O(N) guided filter).
    """
    x = np.asarray(x, dtype)
    r = int(r)
    return _box_sum_axis(_box_sum_axis(x, r, 0), r, 1)


def box_mean(x: np.ndarray, r: int) -> np.ndarray:
    """Mean over the clipped (2r+1)^2 window: ``box_sum(x, r) / count``."""
    x = np.asarray(x, np.float64)
    h, w = x.shape[:2]
    cnt = np.outer(box_count(h, r), box_count(w, r))
    if x.ndim == 3:
        cnt = cnt[..., None]
    return box_sum(x, r) / cnt


def box_mean_finite(x: np.ndarray, r: int) -> np.ndarray:
    """Mean over the finite entries of each clipped (2r+1)^2 window.

    ``box_sum`` of the finite values over ``box_sum`` of their count; NaN
    where a window holds no finite entry.  For maps with unknown pixels (NaN),
    e.g. the oracle's pooled true error.

    x : (H, W) or (H, W, C) -> same shape, float64
    """
    x = np.asarray(x, np.float64)
    ok = np.isfinite(x)
    num = box_sum(np.where(ok, x, 0.0), r)
    den = box_sum(ok.astype(np.float64), r)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


# ----------------------------------------------------------------- guided filter
def guided_filter(p: np.ndarray, guide: np.ndarray, radius: int, eps: float = 1e-3) -> np.ndarray:
    """Guided image filter with a grey guide, O(1) per pixel (He et al. 2010).

    For each window w_k of radius ``radius`` the linear model q = a_k I + b_k
    (Eq. 6 of Liu et al. 2018; He et al. Eq. 1) minimises
    ``sum_{i in w_k} (a_k I_i + b_k - p_i)^2 + eps a_k^2`` (He et al. Eq. 3):

        a_k = cov_k(I, p) / (var_k(I) + eps),   b_k = mean_k(p) - a_k mean_k(I)

    and every pixel averages the models of the windows that contain it:
    q_i = mean_{k: i in w_k}(a_k) I_i + mean_{k: i in w_k}(b_k).  Windows are
    clipped at the border (their statistics use the pixels inside).

    Parameters
    ----------
    p : (H, W) or (H, W, C) image to filter (each channel uses the same guide).
    guide : (H, W) guidance image I.
    radius : int >= 0, window radius r.
    eps : float > 0, regularisation (paper: 0.001).  Values below 1e-12 are
        raised to 1e-12 so the division is always defined.

    Returns
    -------
    q : same shape as ``p``, float64.  Non-finite inputs are replaced by 0 and
    magnitudes clipped to 1e30 first; variances use a per-image centring of the
    guide and are clamped at 0 to avoid cancellation.
    """
    p = _finite(p)
    I = _finite(guide)
    if I.ndim == 3:
        I = I[..., 0]
    squeeze = p.ndim == 2
    if squeeze:
        p = p[..., None]
    eps = max(float(eps), 1e-12)
    r = int(radius)
    I = I - (I.mean() if I.size else 0.0)           # centring: less cancellation
    pc = p.mean(axis=(0, 1), keepdims=True) if p.size else 0.0
    p0 = p - pc
    mean_I = box_mean(I, r)
    mean_p = box_mean(p0, r)
    var_I = np.maximum(box_mean(I * I, r) - mean_I * mean_I, 0.0)
    cov = box_mean(I[..., None] * p0, r) - mean_I[..., None] * mean_p
    a = cov / (var_I + eps)[..., None]
    b = mean_p - a * mean_I[..., None]
    q = box_mean(a, r) * I[..., None] + box_mean(b, r) + pc
    q = np.clip(q, -VALUE_LIMIT, VALUE_LIMIT)
    return q[..., 0] if squeeze else q


def guided_filter_mean(p: np.ndarray, guides: np.ndarray, radius: int, eps: float = 1e-3,
                       chunk_pixels: int = 1 << 13) -> np.ndarray:
    """Mean over G grey guides of ``guided_filter(p, guides[..., m], radius, eps)``.

    Same result as the explicit mean (Eq. 8 of Liu et al. 2018 with the 7
    feature channels as guides), with the shared work done once: the box mean
    of p, and the b terms summed before their box filter (the filter is
    linear in b).  Processed in row strips with a 2r halo (exact).

    p : (H, W, C); guides : (H, W, G) -> (H, W, C) float64.  Inputs that are
    already finite float64 are not copied (only the strips' temporaries and
    the output are allocated).
    """
    p = _finite_or_self(p)
    g = _finite_or_self(guides)
    if g.ndim == 2:
        g = g[..., None]
    h, w, c = p.shape
    G = g.shape[2]
    eps = max(float(eps), 1e-12)
    r = int(radius)
    gc = g.mean(axis=(0, 1)) if g.size else np.zeros(G)
    pc = p.mean(axis=(0, 1)) if p.size else np.zeros(c)
    out = np.empty_like(p)
    rows = max(1, int(chunk_pixels) // max(1, w))

    def strip(y0):
        # one strip, written to its own output rows (strips run on
        # core.parallel's threads; cut by the shape only: same bits)
        y1 = min(h, y0 + rows)
        a0, b0 = max(0, y0 - 2 * r), min(h, y1 + 2 * r)
        I = g[a0:b0] - gc
        p0 = p[a0:b0] - pc
        hh = b0 - a0
        mI = box_mean(I, r)
        vI = np.maximum(box_mean(I * I, r) - mI * mI, 0.0)
        mp = box_mean(p0, r)
        mIp = box_mean((I[..., :, None] * p0[..., None, :]).reshape(hh, w, G * c), r)
        a = (mIp.reshape(hh, w, G, c) - mI[..., None] * mp[..., None, :]) \
            / (vI + eps)[..., None]
        bsum = G * mp - (a * mI[..., None]).sum(axis=2)
        ma = box_mean(a.reshape(hh, w, G * c), r).reshape(hh, w, G, c)
        q = ((ma * I[..., None]).sum(axis=2) + box_mean(bsum, r)) / G + pc
        out[y0:y1] = q[y0 - a0:y1 - a0]

    parallel.run_bands(lambda band: strip(band[0]), h, rows, THREAD_MIN_PIXELS, w)
    return np.clip(out, -VALUE_LIMIT, VALUE_LIMIT, out=out)


# ----------------------------------------------------------------------- NL-means
def nlm_pixel_distance(y_i, y_j, var_i, var_j, k: float, eps: float = 1e-10) -> np.ndarray:
    """Variance-cancelling per-pixel distance (Eq. 5 of Liu et al. 2018,
    from Rousselle, Manzi, Zwicker 2013):

        d(i, j) = (|y_i - y_j|^2 - (var_i + min(var_i, var_j))) / (eps + k^2 (var_i + var_j))

    evaluated per channel (arrays broadcast together, last axis = channel).
    Multi-channel distances are the channel mean of this (Rousselle et al.),
    which callers take.  ``var`` is the variance of the pixel mean.
    """
    y_i = np.asarray(y_i, np.float64)
    y_j = np.asarray(y_j, np.float64)
    var_i = np.asarray(var_i, np.float64)
    var_j = np.asarray(var_j, np.float64)
    diff = y_i - y_j
    num = diff * diff - (var_i + np.minimum(var_i, var_j))
    return num / (eps + (k * k) * (var_i + var_j))


def window_offsets(radius: int):
    """Row-major offsets (dy, dx) of a (2r+1)^2 square window: two (n,) int arrays."""
    r = int(radius)
    dy, dx = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
    return dy.ravel(), dx.ravel()


#: Per-pixel NL-means distances (channel means for colour) are clipped to this
#: before the patch sum.  A single pixel pair at the clip already makes the
#: patch weight exp(-D_CLIP / ((2r+1)^2 2 sigma_r^2)) < e^-1000 for patch radius
#: r <= 10 and sigma_r = 1, so weights do not change; it keeps sums finite and
#: float32-safe (zero-variance pixels give d ~ diff^2 / 1e-10).
D_CLIP = 1e6


def nlm_filter(values, variances, k: float, radius: int, patch_radius: int,
               sigma_r: float = 1.0, sigma_s: float = 0.0, guides=None, guide_sigmas=None,
               channelwise: bool = False, eps: float = 1e-10, chunk_pixels: int = 1 << 15,
               dtype=np.float64):
    """(Joint) NL-means filter ``NLM(Y, k, UF)`` of Liu et al. 2018, Eq. 3-5.

    Weight between pixel i and j (|i - j|_inf <= radius):

        w(i, j) = exp(-|i-j|^2 / (2 sigma_s^2))                       spatial
                * exp(-|P_i - P_j|^2 / (2 sigma_r^2))                   patch range
                * prod_m exp(-|f_i,m - f_j,m|^2 / (2 sigma_m^2))         joint features (UF)

    with the patch distance of Eq. 4,
    ``|P_i - P_j|^2 = max(0, mean_{l in patch} d(i + l, j + l))``, and d the
    per-pixel distance of Eq. 5 (``nlm_pixel_distance``; channel mean unless
    ``channelwise``), clipped above at ``D_CLIP`` (no effect on the weights).  Eq. 4 normalises by
    (2r+1)^2; at the border only pixel pairs with both members inside the image
    exist, so the mean runs over those (identical to Eq. 4 away from borders).
    The output is the weight-normalised average ``sum_j w(i,j) y_j / sum_j w(i,j)``.

    Parameters
    ----------
    values : (H, W) or (H, W, C) image Y.
    variances : same shape, variance of each pixel mean (finite, >= 0; NaN ->
        0, inf -> 1e60).
    k : float > 0, filter strength of Eq. 5 (paper: 0.25 for features).
    radius : int, search window radius (the paper leaves it open; RHF uses 2 sigma_s).
    patch_radius : int, patch radius r of Eq. 4 (paper: 3).
    sigma_r : float, range sigma (paper: 1).
    sigma_s : float, spatial sigma (paper: 2); 0 disables the spatial term
        (uniform weights in the window).
    guides : optional (H, W, G) joint features f (UF = true); None = UF false.
    guide_sigmas : (G,) sigma_m for each guide channel.
    channelwise : bool.  False (colour): one weight per pixel pair from the
        channel-mean distance.  True: each channel is filtered independently
        with its own patch distance (Liu et al. Sec. 3.2, features).
    eps : float, epsilon of Eq. 5 (Rousselle et al. 2013: 1e-10).
    chunk_pixels : int, rows are processed in strips of about this many pixels
        (bounds temporaries and keeps them in cache; results do not depend on
        it); frames of ``THREAD_MIN_PIXELS`` or more run the strips on
        :mod:`core.parallel`'s pool (same bits for any thread count).
    dtype : float64 (default) or float32 for the distances and weights (about
        twice as fast; the caller must keep values within float32 range --
        inputs are clipped to +-1e15 and variances to 1e30 in that case, and
        the averaged values are rounded to float32).  The weighted sums are
        always accumulated in float64.

    Returns
    -------
    (H, W[, C]) float64.  The self weight is 1 (d(i, i) <= 0), so the
    normaliser is >= 1 and the output is always finite; zero-variance pixels
    whose patch differs from every neighbour's come back unchanged.
    """
    dtype = np.dtype(dtype)
    lim, vlim = (VALUE_LIMIT, VAR_LIMIT) if dtype == np.float64 else (1e15, 1e30)
    y = _finite(values, lim, dtype=dtype)
    squeeze = y.ndim == 2
    if squeeze:
        y = y[..., None]
    h, w, c = y.shape
    v = _finite_var(np.broadcast_to(np.asarray(variances).reshape(h, w, -1), y.shape), vlim,
                    dtype=dtype)
    g = None
    if guides is not None:
        g = y if guides is values else _finite(guides, lim, dtype=dtype)
        if g.ndim == 2:
            g = g[..., None]
        gs = np.broadcast_to(np.asarray(guide_sigmas, np.float64), (g.shape[2],))
        ginv = (1.0 / (2.0 * np.maximum(gs, 1e-12) ** 2)).astype(dtype)
    r = int(radius)
    pr = int(patch_radius)
    k2 = dtype.type(float(k) ** 2)
    epsd = dtype.type(max(float(eps), 1e-300) if dtype == np.float64 else max(float(eps), 1e-30))
    inv2sr = 1.0 / (2.0 * max(float(sigma_r), 1e-12) ** 2)
    mean_w = np.full(c, 1.0 / c, dtype)
    cw = c if channelwise else 1
    out = np.empty((h, w, c))
    rows = max(1, int(chunk_pixels) // max(1, w))

    with np.errstate(over="ignore", invalid="ignore"):
        vk = v * k2                             # Eq. 5's k^2 Var, once per image, and
        vke = vk + epsd                         # k^2 Var + eps: the denominator's halves

    def strip(y0):
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            _nlm_strip(y, v, vk, vke, g, ginv if g is not None else None, out, r, pr, inv2sr,
                       sigma_s, mean_w, channelwise, cw, dtype, rows, y0)

    # strips are independent (each writes only its own output rows) and cut
    # by the shape only: same bits on any number of threads
    parallel.run_bands(lambda band: strip(band[0]), h, rows, THREAD_MIN_PIXELS, w)
    return out[..., 0] if squeeze else out


def _nlm_strip(y, v, vk, vke, g, ginv, out, r, pr, inv2sr, sigma_s, mean_w, channelwise, cw,
               dtype, rows, y0):
    """One row strip [y0, y0 + rows) of ``nlm_filter`` (loops over offsets
    only), written to ``out``; its own scratch buffer, so strips can run on
    :mod:`core.parallel`'s threads.  ``vk`` = k^2 v and ``vke`` = k^2 v + eps
    (Eq. 5's denominator is vk_p + vke_q).

    Weighted sums are accumulated in float64 for float64 input and in float32
    for float32 input (at most (2r+1)^2 terms in [0, 1]: relative error < 1e-5).
    """
    h, w, c = y.shape
    L = 2 * pr + 1
    buf_full = np.zeros((min(h, rows + 2 * pr) + 2 * pr, w + 2 * pr, cw), dtype)
    y1 = min(h, y0 + rows)
    ea, eb = max(0, y0 - pr), min(h, y1 + pr)
    num = np.zeros((y1 - y0, w, c), dtype)
    den = np.zeros((y1 - y0, w, cw), dtype)
    scales = {}                                 # 1 / pair counts of Eq. 4's mean, by rectangle
    for dy in range(-r, r + 1):
        ra, rb = max(ea, -dy), min(eb, h - dy)
        oa, ob = max(y0, ra), min(y1, rb)
        if ra >= rb or oa >= ob:
            continue
        R = rb - ra
        cnt_y = box_count(R, pr)[oa - ra:ob - ra]
        for dx in range(-r, r + 1):
            ca, cb = max(0, -dx), min(w, w - dx)
            if ca >= cb:
                continue
            Wc = cb - ca
            # zero-bordered buffer holding d over the rectangle (Eq. 5)
            buf = buf_full[:R + 2 * pr, :Wc + 2 * pr]
            if pr:
                buf[:pr] = 0
                buf[R + pr:] = 0
                buf[:, :pr] = 0
                buf[:, Wc + pr:] = 0
            yq = y[ra + dy:rb + dy, ca + dx:cb + dx]
            vp, vq = v[ra:rb, ca:cb], v[ra + dy:rb + dy, ca + dx:cb + dx]
            d = y[ra:rb, ca:cb] - yq
            d *= d
            m = np.minimum(vp, vq)
            m += vp
            d -= m
            m = np.add(vk[ra:rb, ca:cb], vke[ra + dy:rb + dy, ca + dx:cb + dx], out=m)
            d /= m
            if channelwise:
                np.minimum(d, D_CLIP, out=buf[pr:pr + R, pr:pr + Wc])
            else:
                np.matmul(d, mean_w, out=buf[pr:pr + R, pr:pr + Wc, 0])
                np.minimum(buf, D_CLIP, out=buf)
            # Eq. 4: patch sums (box filter) for the output rows only
            ps = _window_sums(buf, L, 0, oa - ra, ob - ra)
            ps = _window_sums(ps, L, 1, 0, Wc)
            # -max(P, 0) / (2 sigma_r^2) = min(P * scale, 0) with scale < 0
            key = (oa - ra, ob - ra, R, Wc)                      # repeats across dy
            scale = scales.get(key)
            if scale is None:
                scale = scales[key] = (-inv2sr / np.outer(cnt_y, box_count(Wc, pr))).astype(dtype)
            ps *= scale[..., None]
            np.minimum(ps, 0, out=ps)
            # spatial and joint-feature terms: one channel, shared by all
            lj = None
            if g is not None:
                gd = g[oa:ob, ca:cb] - g[oa + dy:ob + dy, ca + dx:cb + dx]
                gd *= gd
                lj = gd @ ginv
            if sigma_s > 0:
                sp = dtype.type((dy * dy + dx * dx) / (2.0 * sigma_s * sigma_s))
                lj = sp if lj is None else np.add(lj, sp, out=lj)
            if lj is not None:
                ps -= lj[..., None] if np.ndim(lj) else lj
            wgt = np.exp(ps, out=ps)
            den[oa - y0:ob - y0, ca:cb] += wgt
            if cw == c:
                wgt *= yq[oa - ra:ob - ra]
                num[oa - y0:ob - y0, ca:cb] += wgt
            else:
                num[oa - y0:ob - y0, ca:cb] += wgt * yq[oa - ra:ob - ra]
    out[y0:y1] = num / np.maximum(den, 1e-30 if dtype == np.float32 else 1e-300)


def nlm_center_weights(values, variances, cy, cx, radius: int, patch_radius: int, ks,
                       sigma_r: float = 1.0, sigma_s: float = 0.0, eps: float = 1e-10,
                       dtype=np.float64):
    """NL-means weights ``w_k(i, j)`` (Eq. 3-5, UF = false) between centre
    pixels i and every pixel j of their (2 radius + 1)^2 window, for several k.

    Used for RHF's colour regression weights ``w(i, j) = NLM(M, k, false)``
    (Liu et al. 2018, Sec. 3.3) at sparse centres only.  The distance is the
    channel mean of Eq. 5 (Rousselle et al. 2013), clipped at ``D_CLIP`` and
    averaged over the patch pairs that lie inside the image (Eq. 4), computed
    once at k = 1; at strength k it is that over k^2, which is Eq. 5 with
    eps taken as k^2 eps (``_center_patch_sums``: one patch sum for all k).

    Parameters
    ----------
    values, variances : (H, W, C) image and variance of its pixel means.
    cy, cx : (N,) int centre coordinates (inside the image).
    radius : int, window radius.
    patch_radius : int, Eq. 4 patch radius.
    ks : (K,) filter strengths k (Eq. 5).
    sigma_r, sigma_s, eps : as in ``nlm_filter`` (sigma_s = 0: no spatial term).
    dtype : float64 (default) or float32 for the distances (about twice as
        fast; values are then clipped to +-1e15 and variances to 1e30).

    Returns
    -------
    (N, K, (2 radius + 1)^2) float64 weights in [0, 1], window offsets in
    ``window_offsets(radius)`` order; 0 for window pixels outside the image.
    The centre's own weight is 1.
    """
    dtype = np.dtype(dtype)
    lim, vlim = (VALUE_LIMIT, VAR_LIMIT) if dtype == np.float64 else (1e15, 1e30)
    yv = np.asarray(values)
    if yv.ndim == 2:
        yv = yv[..., None]
    h, w, c = yv.shape
    vv = np.broadcast_to(np.asarray(variances).reshape(h, w, -1), (h, w, c))
    cy = np.asarray(cy, np.int64)
    cx = np.asarray(cx, np.int64)
    ks = np.asarray(ks, np.float64).ravel()
    r, pr = int(radius), int(patch_radius)
    R = r + pr
    n = cy.size
    s = 2 * r + 1
    K = ks.size
    # extended windows (radius r + pr) gathered once per centre, channel first;
    # non-finite values are sanitised on the gathered windows only
    e = np.arange(-R, R + 1)
    yy = cy[:, None, None] + e[None, :, None]
    xx = cx[:, None, None] + e[None, None, :]
    inside = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
    idx = np.clip(yy, 0, h - 1) * w + np.clip(xx, 0, w - 1)
    ye = _finite(np.moveaxis(yv.reshape(-1, c)[idx], -1, 0), lim, dtype=dtype)  # (C,N,E,E)
    ve = _finite_var(np.moveaxis(vv.reshape(-1, c)[idx], -1, 0), vlim, dtype=dtype)
    epsd = dtype.type(max(float(eps), 1e-300 if dtype == np.float64 else 1e-30))
    acc = np.zeros((n, s, s))
    cnt = np.zeros((n, s, s))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        _center_patch_sums(ye, ve, inside, acc, cnt, epsd, r, pr, c)
    pdist = np.maximum(acc / np.maximum(cnt, 1.0), 0.0)                # (N, s, s) at k = 1
    scale = 1.0 / (2.0 * max(float(sigma_r), 1e-12) ** 2 * np.maximum(ks * ks, 1e-300))
    logw = pdist[None] * -scale.reshape(K, 1, 1, 1)                    # (K, N, s, s): d_k = d_1 / k^2
    if sigma_s > 0:
        oy, ox = window_offsets(r)
        logw = logw - ((oy * oy + ox * ox) / (2.0 * sigma_s * sigma_s)).reshape(1, 1, s, s)
    wgt = np.exp(logw)
    wgt = np.where(inside[:, pr:pr + s, pr:pr + s][None], wgt, 0.0)
    return np.ascontiguousarray(np.moveaxis(wgt, 0, 1)).reshape(n, K, s * s)


def _center_patch_sums(ye, ve, inside, acc, cnt, epsd, r, pr, c):
    """Patch sums of the clipped channel-mean Eq. 5 distance at k = 1, added
    to ``acc`` (N, s, s) float64, and the pair counts to ``cnt``.

    One pass per patch offset (ly, lx), all channels at once:
    ``min(mean_c (|y_a - y_b|^2 - (va + min(va, vb))) / (va + vb + eps), D_CLIP)``.
    The distance at strength k is this over k^2 (``nlm_center_weights``):
    Eq. 5's eps then enters as k^2 eps, and the clip as D_CLIP / k^2; both
    differ from the per-k formula only where a pair's distance is beyond
    D_CLIP / 16 (patch weights below e^-600: zero once quantised) or where
    the variances are ~eps (zero-variance pixels, returned unchanged by RHF).
    One division per pixel pair and channel instead of one per k.  The
    channel mean's 1/C is applied once to ``acc`` at the end (the clip is
    then at C D_CLIP), and eps is added to the gathered variances once.
    ye, ve : (C, N, E, E) gathered values / variances, E = s + 2 pr.
    """
    R = r + pr
    s = 2 * r + 1
    n = ye.shape[1]
    dt = ye.dtype
    num = np.empty((c, n, s, s), dt)
    sv = np.empty((c, n, s, s), dt)
    dsum = np.empty((n, s, s), dt)
    ok = np.empty((n, s, s), bool)
    clip = dt.type(D_CLIP * c)
    ve_eps = ve + epsd                                               # vb + eps, once
    part = np.zeros_like(acc)
    for ly in range(-pr, pr + 1):
        for lx in range(-pr, pr + 1):
            sl = (slice(None), slice(pr + ly, pr + ly + s), slice(pr + lx, pr + lx + s))
            np.logical_and(inside[:, R + ly, R + lx][:, None, None], inside[sl], out=ok)
            cnt += ok
            a = ye[:, :, R + ly, R + lx][..., None, None]            # centre-patch pixel
            va = ve[:, :, R + ly, R + lx][..., None, None]
            b, vb = ye[(slice(None),) + sl], ve[(slice(None),) + sl]
            np.subtract(a, b, out=num)
            num *= num
            np.minimum(va, vb, out=sv)
            np.add(va, sv, out=sv)
            num -= sv                                                # |y_a - y_b|^2 - (va + min)
            np.add(va, ve_eps[(slice(None),) + sl], out=sv)         # va + vb + eps
            np.divide(num, sv, out=num)
            if c == 1:
                dsum[...] = num[0]
            else:
                np.add(num[0], num[1], out=dsum)
                for ch in range(2, c):
                    dsum += num[ch]
            np.minimum(dsum, clip, out=dsum)                         # C x the clipped mean
            if ok.all():
                part += dsum
            else:
                np.add(part, dsum, out=part, where=ok)
    part *= 1.0 / c
    acc += part


# ------------------------------------------------------------------------- Sobel
_SOBEL_X = np.array([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]])


def sobel_gradient(img: np.ndarray, reduce_max: bool = False) -> np.ndarray:
    """Sobel gradient magnitude per channel (Eq. 14 of Liu et al. 2018):
    ``gra = sqrt((G_x * f)^2 + (G_y * f)^2)`` with the unnormalised 3x3 Sobel
    kernels G_x = [[-1,0,1],[-2,0,2],[-1,0,1]], G_y = G_x^T.

    Border pixels replicate their neighbour (edge padding), so the image
    border itself is not an edge.  A unit step gives a response of 4.

    img : (H, W) or (H, W, C) -> same shape, float64, >= 0, finite; with
    ``reduce_max`` the (H, W) maximum over channels (Eq. 14's
    gra = max_m gra_m), computed one channel at a time.
    """
    f = np.asarray(img)
    squeeze = f.ndim == 2
    if squeeze:
        f = f[..., None]
    h, w, nc = f.shape
    out = np.zeros((h, w)) if reduce_max else np.empty((h, w, nc))
    for ch in range(nc):
        pad = np.pad(_finite(f[..., ch]), 1, mode="edge")
        # separable: G_x = [1,2,1]^T [-1,0,1], G_y = [-1,0,1]^T [1,2,1]
        sm_r = pad[:-2] + 2.0 * pad[1:-1] + pad[2:]             # vertical smoothing
        gx = sm_r[:, 2:] - sm_r[:, :-2]
        sm_c = pad[:, :-2] + 2.0 * pad[:, 1:-1] + pad[:, 2:]    # horizontal smoothing
        gy = sm_c[2:] - sm_c[:-2]
        g = np.minimum(np.sqrt(gx * gx + gy * gy), VALUE_LIMIT)
        if reduce_max:
            np.maximum(out, g, out=out)
        else:
            out[..., ch] = g
    if reduce_max or not squeeze:
        return out
    return out[..., 0]

"""Calibrated per-pixel variance of the mean: QMC stratification correction and
edge-aware pooling.  Measurements: docs/notes/variance.md.

``Buffers.variance_of_mean`` is ``M2 / ((k - 1) n)``, exact for i.i.d. samples.
Cycles' sample sequence (Tabulated Sobol) is stratified: the error of a mean of
``x`` consecutive samples decays as ``v(x) = C x^-beta`` with ``beta > 1``, and
the raw estimate, built from the spread of ``k`` subset means of ``m = n / k``
samples, sees ``v(m)`` and not the smaller ``v(n)``.

Model (exact identity, then one assumption).  For ``k`` consecutive groups of
``m`` samples with errors ``e_i`` and full-mean error ``e = mean(e_i)``,
``sum_i (e_i - e)^2 = sum_i e_i^2 - k e^2``, so with ``E[e_i^2] = v(m)``::

    E[M2] = m E[sum_i (mu_i - mu)^2] = n (v(m) - v(n))                  (1)

With the power law ``v(x) = C x^-beta`` (the assumption) this is
``E[M2] = C n^(1-beta) (k^beta - 1)``, hence the calibrated variance of the mean

    v(n) = C n^-beta = M2 / (n (k^beta - 1))                            (2)

which is the raw ``M2 / (n (k - 1))`` at ``beta = 1`` (i.i.d.).  ``beta`` is
measured per scene from the data (:func:`stratification_exponent`): the same
identity (1) for the ``k / 2`` consecutive *pairs* of subsets gives
``E[S_k] / E[S_k/2] = 2 (k^beta - 1) / ((k/2)^beta - 1)`` (``S`` the sums of
squared deviations of the group means), solved for ``beta``.  The Buffers'
halves cannot serve: they interleave the subsets ({0, 2} and {1, 3}), whose
union is not a stratified block (measured ratio ~5.7, i.i.d.-like).

Pooling (:func:`pool_m2`): ``C`` is estimated per pixel as the ratio of the
feature-weighted sums of ``M2`` and of its expectation factor
``n^(1-beta) (k^beta - 1)`` over a (2r+1)^2 window (a joint-bilateral average
guided by albedo, normal and log depth, each widened by the feature's own
noise).  A ratio of sums pools the degrees of freedom (each pixel weighs by its
own dof) and stays unbiased where the neighbours share ``C``; averaging in the
log domain would be biased by ``E[log chi^2]``.  The colour mean is not a guide
by default: its noise is correlated with the ``M2`` being pooled (a pixel with
an outlier sample has both), which biases the pool low (cornell, 4 spp: ratio
0.82 -> 0.75); ``color_guide=True`` offers it.  :func:`calibrated_variance_and_dof`
also gives the pool's effective dof (for Student-t tests on it).

Limit: ``v(n)`` is the one direction of the subsets' covariance that no
within-render contrast sees, so (2) extrapolates the first octave's slope to
the last; real slopes differ by 0.1-0.2 between octaves, which is the 20-60 %
error left on some scenes (docs/notes/variance.md).

Calibration ratio (:func:`calibration_ratio`): a single pixel's squared error
is one chi-square-like draw, so per-pixel ratios est / true are heavy-tailed.
We sum both (relMSE weights ``1 / (ref^2 + 0.01)``) over 8x8 tiles and report
the median over tiles of sum(est) / sum(true), ``true = (mean - ref)^2 -
var_ref``.  A perfect estimate gives ~1 (each tile sums 192 draws).
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "EXPONENT_RANGE",
    "GUIDE_FEATURES",
    "calibrated_variance_and_dof",
    "calibrated_variance_of_mean",
    "calibration_ratio",
    "ExponentMeter",
    "expected_m2_factor",
    "group_spread",
    "pool_m2",
    "spread_ratio",
    "stratification_exponent",
]

#: beta is searched in this range (a ratio outside it is clamped): 1 is i.i.d.,
#: 3 would be a smooth 2-D integrand under a (0, 2)-sequence (Owen: n^-3).
EXPONENT_RANGE = (0.5, 3.0)
#: feature passes that guide the pooling, and each one's tolerance (the
#: distance at which the weight falls to exp(-1/2) on top of the feature's
#: own noise): albedo and normal in their units, depth as log depth (relative).
#: Set a priori (a 5 % albedo step, ~6 degrees of normal, 5 % of depth are
#: different surfaces), not tuned on the sample scenes.
GUIDE_FEATURES = {"albedo": 0.05, "normal": 0.1, "depth": 0.05}
#: tolerance of the colour guide (log of the mean + 0.01, i.e. relative)
COLOR_TOLERANCE = 0.2
#: rows per band of the pooling (bounded memory: the guides, weights and sums
#: exist for one band and its halo at a time); the bands run on the
#: controller's threads, and their size does not change the result
CHUNK_ROWS = 64


# ----------------------------------------------------------- stratification
def group_spread(group_means, weights=None) -> float:
    """Weighted sum over pixels and channels of ``sum_i (mu_i - mu)^2`` for a
    list of equal-size group means (each (H, W, C)); non-finite pixels skipped."""
    g = np.asarray(group_means, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        s = ((g - g.mean(axis=0)) ** 2).sum(axis=0)
        if weights is not None:
            s = s * weights
    return float(np.sum(s[np.isfinite(s)]))


def spread_ratio(exponent, k: int) -> np.ndarray:
    """``E[S_k] / E[S_k/2]`` under the power law, ``2 (k^b - 1) / ((k/2)^b - 1)``
    (identity (1) of the module notes for k groups and k/2 pairs)."""
    b = np.asarray(exponent, np.float64)
    return 2.0 * (np.power(float(k), b) - 1.0) / (np.power(k / 2.0, b) - 1.0)


def stratification_exponent(subset_means, mean=None, radius=None):
    """Convergence exponent ``beta`` of the error of a mean, ``v(x) ~ x^-beta``,
    measured from ``k`` consecutive equal-size subset means of one render.

    subset_means : sequence of k (H, W, C) means of consecutive sample subsets
        of equal size (the loop's initial pass), k even and >= 4.
    mean : optional (H, W, C) image for the relMSE weights ``1 / (mean^2 +
        0.01)`` (default: the mean of the subsets), so bright pixels do not
        decide the exponent alone.
    radius : None for one exponent for the scene (float); an int for an
        (H, W) map measured over each pixel's (2r+1)^2 window (the exponent
        differs between regions: smooth ones converge faster).

    The spread of single subsets (``S_k``) and of consecutive pairs
    (``S_k/2``) are summed over pixels and their ratio inverted through
    :func:`spread_ratio` (bisection; monotone in beta).  1.0 (i.i.d., no
    correction) with fewer than 4 or an odd number of subsets, or no spread.
    """
    g = [np.asarray(s, np.float64) for s in subset_means]
    k = len(g)
    shape = g[0].shape[:2] if g else (0, 0)
    if k < 4 or k % 2:
        return 1.0 if radius is None else np.ones(shape)
    m = np.mean(g, axis=0) if mean is None else np.asarray(mean, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        w = 1.0 / (np.where(np.isfinite(m), m, 0.0) ** 2 + 0.01)
    pairs = [0.5 * (g[i] + g[i + 1]) for i in range(0, k, 2)]
    if radius is None:
        s_k, s_pairs = group_spread(g, w), group_spread(pairs, w)
        if not (s_k > 0 and s_pairs > 0 and np.isfinite(s_k) and np.isfinite(s_pairs)):
            return 1.0
        return _invert_ratio(s_k / s_pairs, k)
    from .filters import box_sum
    a = box_sum(_spread_map(g, w), int(radius))
    b = box_sum(_spread_map(pairs, w), int(radius))
    ok = (a > 0) & (b > 0) & np.isfinite(a) & np.isfinite(b)
    rho = np.where(ok, a / np.where(ok, b, 1.0), spread_ratio(1.0, k))
    return np.where(ok, _invert_ratio(rho, k), 1.0)


def _spread_map(group_means, weights) -> np.ndarray:
    """(H, W) weighted ``sum_i (mu_i - mu)^2`` summed over channels, 0 where
    not finite."""
    g = np.asarray(group_means, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        s = (((g - g.mean(axis=0)) ** 2).sum(axis=0) * weights).sum(axis=-1)
    return np.where(np.isfinite(s), s, 0.0)


def _invert_ratio(rho, k: int):
    """beta with ``spread_ratio(beta, k) = rho`` (scalar or array), clamped
    to ``EXPONENT_RANGE``; vectorised bisection."""
    r = np.asarray(rho, np.float64)
    lo = np.full(r.shape, EXPONENT_RANGE[0])
    hi = np.full(r.shape, EXPONENT_RANGE[1])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = spread_ratio(mid, k) < r
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    out = np.clip(0.5 * (lo + hi), *EXPONENT_RANGE)
    return float(out) if out.ndim == 0 else out


class ExponentMeter:
    """:func:`stratification_exponent` of a render's consecutive, equal-size
    subsets, fed one subset at a time so the loop keeps two frame-sized arrays
    instead of every subset: the running sum and sum of squares of the pair
    means, and the current pair's first subset.  ``S_k`` comes from the
    merged Buffers' ``M2`` (``M2 = m sum_i (mu_i - mu)^2`` for equal groups of
    ``m`` samples), ``S_k/2 = sum_j p_j^2 - (k/2) mu^2``.
    """

    def __init__(self):
        self.k = 0
        self.size = None
        self.equal = True
        self._first = None
        self._sq = None

    def add(self, color, samples: int) -> None:
        """One subset's (H, W, 3) mean of ``samples`` samples, in sequence order."""
        c = np.asarray(color, np.float64)[..., :3]
        if self.size is None:
            self.size = int(samples)
        self.equal &= int(samples) == self.size
        if self.k % 2 == 0:
            self._first = c.copy()
        else:
            p = 0.5 * (self._first + c)
            self._sq = p * p if self._sq is None else self._sq + p * p
            self._first = None
        self.k += 1

    def exponent(self, buf) -> float:
        """beta for the Buffers the subsets were merged into (1.0 when the
        subsets were too few, odd in number, unequal, or show no spread)."""
        k = self.k
        if k < 4 or k % 2 or not self.equal or self._sq is None:
            return 1.0
        mu = np.asarray(buf.color.mean, np.float64)
        with np.errstate(invalid="ignore", over="ignore"):
            w = 1.0 / (np.where(np.isfinite(mu), mu, 0.0) ** 2 + 0.01)
            s_k = buf.color.m2 / self.size * w
            s_pairs = (self._sq - (k / 2.0) * mu * mu) * w
        s_k = float(np.sum(s_k[np.isfinite(s_k)]))
        s_pairs = float(np.sum(s_pairs[np.isfinite(s_pairs)]))
        if not (s_k > 0 and s_pairs > 0):
            return 1.0
        return _invert_ratio(s_k / s_pairs, k)


def expected_m2_factor(n, k, exponent: float = 1.0, gsum=None) -> np.ndarray:
    """``E[M2] / C`` for a pixel's groups under ``v(x) = C x^-beta``: with
    the groups' sizes ``n_i``, identity (1) of the module notes gives
    ``E[M2] = sum_i n_i v(n_i) - n v(n) = C (sum_i n_i^(1-beta) - n^(1-beta))``
    (``gsum`` = that sum, :attr:`core.buffers.Buffers.gsum`); without it the
    groups are taken as equal, ``m = n / k``, which is Eq. 2,
    ``n^(1-beta) (k^beta - 1)``.  0 where k < 2 or n <= 0 (no estimate)."""
    n = np.asarray(n, np.float64)
    k = np.asarray(k, np.float64)
    ok = (k >= 2) & (n > 0) & np.isfinite(n) & np.isfinite(k)
    b = np.asarray(exponent, np.float64)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        if gsum is None:
            f = np.power(np.where(ok, n, 1.0), 1.0 - b) * (np.power(np.where(ok, k, 2.0), b) - 1.0)
        else:
            f = np.asarray(gsum, np.float64) - np.power(np.where(ok, n, 1.0), 1.0 - b)
    return np.where(ok & np.isfinite(f) & (f > 0), f, 0.0)


# ------------------------------------------------------------------ pooling
def _guides(buf, names, color=True, rows=None):
    """[(values (H, W, C), noise variance (H, W, C), tolerance)] of the guide
    features present in ``buf``, finite (depth as log depth), and of the
    colour mean as log(mean + 0.01) when ``color``.  ``rows`` ``(r0, r1)``:
    those rows only (the same values; per-pixel arithmetic)."""
    out = []
    r = slice(None) if rows is None else slice(int(rows[0]), int(rows[1]))
    if color:
        mu = np.nan_to_num(np.asarray(buf.color.mean[r], np.float64), nan=0.0, posinf=1e30, neginf=0.0)
        mu = np.clip(mu, 0.0, 1e30) + 0.01
        var = buf.variance_of_mean(rows=rows)
        var = np.clip(np.where(np.isfinite(var), var, 0.0) / (mu * mu), 0.0, 1e6)
        out.append((np.log(mu), var, COLOR_TOLERANCE))
    for name in names:
        st = buf.features.get(name)
        if st is None:
            continue
        v = np.nan_to_num(np.asarray(st.mean[r], np.float64), nan=0.0, posinf=1e30, neginf=-1e30)
        var = buf.variance_of_mean(st, rows=rows)
        var = np.where(np.isfinite(var), var, 0.0)
        if name == "depth":
            safe = np.clip(np.abs(v), 1e-6, 1e30)
            var = var / (safe * safe)  # delta method: Var[log d] ~ Var[d] / d^2
            v = np.log(safe)
        out.append((v, np.clip(var, 0.0, 1e6), float(GUIDE_FEATURES.get(name, 0.1))))
    return out


def pool_m2(m2, factor, guides=(), radius: int = 2, dof=None):
    """Edge-aware estimate of ``C`` per pixel: ``sum_q w_pq M2_q / sum_q w_pq
    factor_q`` over the (2r+1)^2 window clipped to the image, ``w_pq =
    exp(-sum_g sum_c |f_p - f_q|^2 / (2 (var_p + var_q + tol_g^2)))`` over
    the guides (1 at q = p); a guide's own noise widens its tolerance, so
    noisy features (DoF, motion blur) do not split a flat region.

    m2 : (H, W, C) between-group sums of squares (non-finite: pixel skipped)
    factor : (H, W) ``expected_m2_factor`` (0: pixel skipped)
    guides : from ``_guides``
    dof : optional (H, W) degrees of freedom of each pixel's M2 (k - 1): then
        also returns the effective dof of the pooled ratio, ``(sum w f)^2 /
        sum (w f)^2 / dof_q`` (each ``M2_q ~ C f_q chi2_d / d``: the dof of a
        chi-square with the pool's relative variance), 0 where no estimate.
    Returns (H, W, C) float64, +inf where no pixel of the window has an
    estimate; with ``dof``, ``(C, effective dof)``.
    """
    m2 = np.asarray(m2, np.float64)
    factor = np.asarray(factor, np.float64)
    d = None if dof is None else np.asarray(dof, np.float64)
    guides = list(guides)

    def region(a0, a1):
        L = slice(a0, a1)
        return (m2[L], factor[L], None if d is None else d[L],
                [(f[L], v[L], t) for f, v, t in guides])

    out = np.empty(m2.shape)
    dof_out = np.zeros(m2.shape) if dof is not None else None
    _pool_bands(region, m2.shape, radius, out, dof_out)
    return out if dof is None else (out, dof_out)


#: pixels below which the pooling runs inline (threads do not pay)
INLINE_PIXELS = 65536


def _pool_bands(region, shape, radius, out, dof_out=None, finish=None) -> None:
    """:func:`pool_m2` over row bands of ``CHUNK_ROWS`` rows on the controller's
    threads, each band with a halo of ``r`` rows.  ``region(a0, a1)`` gives
    rows ``a0:a1`` of ``(m2, factor, dof or None, guides)``; each band writes
    rows ``y0:y1`` of ``out`` (and ``dof_out``) only, then ``finish(y0, y1)``.
    A pixel's sums run over the same pairs in the same order whatever the band
    (only the image's edges clip its window), so the result has the same bits
    for any band size and thread count."""
    from . import parallel
    h, w = int(shape[0]), int(shape[1]) if len(shape) > 1 else 1
    r = int(max(0, radius))

    def band(rows):
        y0, y1 = rows
        a0, a1 = max(0, y0 - r), min(h, y1 + r)  # the band and its halo
        m2, factor, d, guides = region(a0, a1)
        valid = (factor > 0)[..., None] & np.isfinite(m2) & (m2 >= 0)
        m2c = np.where(valid, np.minimum(m2, 1e300), 0.0)
        fac = np.where(valid, factor[..., None], 0.0)
        inv_d = None
        if d is not None:
            inv_d = np.where(valid, 1.0 / np.where(d > 0, d, 1.0)[..., None], 0.0)
        num, den, den2 = _pool_region(m2c, fac, inv_d, guides, r)
        k0, k1 = y0 - a0, y1 - a0
        num, den = num[k0:k1], den[k0:k1]
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            c = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.inf)
            if den2 is not None:
                den2 = den2[k0:k1]
                dof_out[y0:y1] = np.where(den2 > 0, den * den / np.where(den2 > 0, den2, 1.0), 0.0)
        out[y0:y1] = np.where(np.isnan(c), np.inf, c)
        if finish is not None:
            finish(y0, y1)

    if h == 0:
        return
    parallel.run_bands(band, h, max(1, int(CHUNK_ROWS)), min_work=INLINE_PIXELS, work_per_row=w)


def _pool_region(m2c, fac, inv_d, guides, r):
    """Weighted sums of one row block over all pixel pairs within ``r``:
    ``sum_q w M2_q``, ``sum_q w f_q`` and (``inv_d`` given) ``sum_q (w f_q)^2
    / d_q``.  The weight is symmetric, so each pair's weight is computed
    once (half the offsets) and added to both pixels.  Without guides every
    weight is 1: clipped box sums (:func:`core.filters.box_sum`, which adds
    the same elements in the same order in any row band).

    With guides the block is laid out channel-first (every array operation
    runs over whole planes) and the weights' exponent is computed in float32:
    a weight is a factor in [0, 1] needing no more than ~1e-6 relative
    precision, while the sums stay float64.  This cut the pooling of a
    0.6-megapixel frame ~2x (docs/notes/loop-speed.md)."""
    h, w = m2c.shape[:2]
    if not guides:
        from .filters import box_sum
        den2 = None if inv_d is None else box_sum(fac * fac * inv_d, r)
        return box_sum(m2c, r), box_sum(fac, r), den2
    cf = lambda a: np.ascontiguousarray(np.moveaxis(np.asarray(a, np.float64), -1, 0))
    m2t, fct = cf(m2c), cf(fac)
    idt = None if inv_d is None else cf(inv_d)
    # where every channel has the same factor and dof (the usual case) the
    # denominators are the same per channel: sum one plane (the same bits)
    nc = fct.shape[0]
    if nc > 1 and (fct == fct[:1]).all() and (idt is None or (idt == idt[:1]).all()):
        fct = fct[:1]
        idt = None if idt is None else idt[:1]
    num, den = m2t.copy(), fct.copy()
    den2 = fct * fct * idt if idt is not None else None
    # every guide's channels as planes, each variance with half its tolerance^2
    # added and doubled, so one pass per offset gives the weight exponent of
    # :func:`pool_m2` summed over the guides: 2 (vp + vq + t^2)
    g = np.concatenate([np.moveaxis(np.asarray(f, np.float32), -1, 0) for f, _, _ in guides])
    u = np.concatenate([np.moveaxis(np.asarray(v, np.float64) + 0.5 * float(t) * float(t), -1, 0)
                        for _, v, t in guides]).astype(np.float32)
    np.maximum(u, 1e-30, out=u)  # a zero tolerance on a noiseless guide: no division by zero
    u *= 2.0
    with np.errstate(over="ignore", invalid="ignore"):
        for dy in range(0, r + 1):
            for dx in range(-r, r + 1):
                if dy == 0 and dx <= 0:
                    continue
                if dy >= h or abs(dx) >= w:
                    continue
                px0, px1 = max(0, -dx), min(w, w - dx)
                P = (slice(None), slice(0, h - dy), slice(px0, px1))
                Q = (slice(None), slice(dy, h), slice(px0 + dx, px1 + dx))
                d = np.subtract(g[P], g[Q])
                np.square(d, out=d)
                np.divide(d, np.add(u[P], u[Q]), out=d)
                e = d.sum(axis=0)
                np.fmin(e, 700.0, out=e)  # NaN (none expected: finite guides) -> weight ~0
                np.negative(e, out=e)
                wt = np.exp(e, out=e).astype(np.float64)
                t = np.multiply(wt, fct[Q])
                den[P] += t
                if den2 is not None:
                    den2[P] += t * t * idt[Q]
                np.multiply(wt, fct[P], out=t)
                den[Q] += t
                if den2 is not None:
                    den2[Q] += t * t * idt[P]
                num[P] += wt * m2t[Q]
                num[Q] += wt * m2t[P]
    back = lambda a: np.moveaxis(np.broadcast_to(a, (nc,) + a.shape[1:]), 0, -1)
    return back(num), back(den), None if den2 is None else back(den2)


# ------------------------------------------------------------------- public
def calibrated_variance_of_mean(buf, exponent: float = 1.0, radius: int = 2,
                                features=tuple(GUIDE_FEATURES), stat=None, color_guide: bool = False
                                ) -> np.ndarray:
    """Calibrated variance of the pixel mean, (H, W, C) float64.

    ``v(n) = C n^-beta`` (Eq. 2 of the module notes) with ``C`` pooled over a
    (2r+1)^2 feature-guided window (:func:`pool_m2`) and ``beta`` the scene's
    stratification exponent (:func:`stratification_exponent`; 1 = i.i.d.,
    no correction; a scalar or an (H, W) map).  +inf where no estimate exists
    (k < 2 or n = 0 in the whole window); never NaN.  ``radius=0`` is the
    unpooled per-pixel estimate; ``stat`` another pass's Stat (default colour).
    """
    return calibrated_variance_and_dof(buf, exponent, radius, features, stat, color_guide)[0]


def calibrated_variance_and_dof(buf, exponent: float = 1.0, radius: int = 2,
                                features=tuple(GUIDE_FEATURES), stat=None, color_guide: bool = False):
    """:func:`calibrated_variance_of_mean` and its effective degrees of freedom
    (H, W, C) (:func:`pool_m2`; ``k - 1`` unpooled, 0 where no estimate), for
    tests that need a Student-t quantile (the consistency guard)."""
    stat = buf.color if stat is None else stat
    b = np.clip(np.nan_to_num(np.asarray(exponent, np.float64), nan=1.0), *EXPONENT_RANGE)
    m2 = np.asarray(stat.m2, np.float64)
    n_all = np.asarray(buf.n, np.float64)
    k_all = np.asarray(buf.k, np.float64)
    b_rows = (lambda L: b[L]) if b.ndim >= 1 else (lambda L: b)
    names = features if radius > 0 else ()
    colour = color_guide if radius > 0 else False

    # the buffers' record of their group sizes holds for their own exponent only
    gsum = getattr(buf, "gsum", None)
    if gsum is not None and not (b.ndim == 0 and float(b) == float(buf.exponent)):
        gsum = None

    def region(a0, a1):
        L = slice(a0, a1)
        factor = expected_m2_factor(n_all[L], k_all[L], b_rows(L), None if gsum is None else gsum[L])
        return m2[L], factor, k_all[L] - 1.0, _guides(buf, names, colour, rows=(a0, a1))

    v = np.empty(m2.shape)
    dof = np.zeros(m2.shape)

    def finish(y0, y1):
        L = slice(y0, y1)
        n = n_all[L]
        ok = (n > 0) & np.isfinite(n)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            scale = np.where(ok, np.power(np.where(ok, n, 1.0), -b_rows(L)), np.inf)[..., None]
            vb = v[L] * scale
        vb = np.where(np.isnan(vb), np.inf, vb)
        vb = np.where(ok[..., None], vb, np.inf)
        v[L] = vb
        dof[L] = np.where(np.isfinite(vb), dof[L], 0.0)

    _pool_bands(region, m2.shape, radius, v, dof, finish)
    return v, dof


def calibration_ratio(est_var, mean, reference, reference_variance=None, tile: int = 8) -> float:
    """Median over ``tile`` x ``tile`` tiles of ``sum w est / sum w true``,
    ``true = (mean - reference)^2 - reference_variance``, ``w = 1 / (ref^2 +
    0.01)`` (relMSE weights), summed over the tile's pixels and channels.

    1 for a calibrated estimate (module notes), > 1 an over-estimate.  Tiles
    with a non-finite entry or ``sum w true <= 0`` are skipped; with none left,
    1.0 if the estimate is 0 everywhere (exact: no error, none estimated),
    else +inf.
    """
    est = np.asarray(est_var, np.float64)
    x = np.asarray(mean, np.float64)
    r = np.asarray(reference, np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        true = (x - r) ** 2
        if reference_variance is not None:
            true = true - np.asarray(reference_variance, np.float64)
        wgt = 1.0 / (r * r + 0.01)
        a, b = est * wgt, true * wgt
    h, w = est.shape[:2]
    t = max(1, int(tile))
    ht, wt = h // t, w // t
    if ht == 0 or wt == 0:
        ht, wt, t = 1, 1, min(h, w)
    crop = lambda z: z[:ht * t, :wt * t].reshape(ht, t, wt, t, -1)
    with np.errstate(over="ignore", invalid="ignore"):
        sa = crop(a).sum(axis=(1, 3, 4))
        sb = crop(b).sum(axis=(1, 3, 4))
        ok = np.isfinite(sa) & np.isfinite(sb) & (sb > 0)
        if not ok.any():
            return 1.0 if np.all(np.nan_to_num(est, nan=1.0) == 0) else float("inf")
        return float(np.median(sa[ok] / sb[ok]))

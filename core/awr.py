"""``awr``: adaptive wavelet rendering (Overbeck, Donner, Ramamoorthi 2009,
"Adaptive Wavelet Rendering").

The wavelet machinery (Appendix A filter banks, non-standard DWT, the
squared-filter variance propagation of Eq. 9-10) lives in ``core/wavelets.py``.
Measurements and design notes: docs/notes/awr.md.

Reconstruction (Sec. 4.2)
-------------------------
DWT of the pixel means (Eq. 7); the error of every wavelet coefficient,
``Delta = sqrt(<sigma^2(B), Psi^2>)`` (Eq. 10), by a DWT of the per-pixel
variance with the squared filters renormalised to sum to ``2**-1/2``
(``recon_filter_sum``); the soft threshold
``W = sign(W~) max(0, |W~| - c_s Delta)`` (Eq. 11, ``c_s = smoothing = 1``);
synthesis.  The coarsest scale coefficients are kept as they are.

Cycle spinning (``shifts``, our addition; ``shifts = 1`` is the paper)
----------------------------------------------------------------------
A decimated DWT is not translation invariant, so the thresholding error
(edge blur, ringing) changes with a one-pixel shift of the image.  As in
Coifman and Donoho 1995 ("Translation-invariant de-noising") the paper's
reconstruction runs unchanged on copies translated by ``shifts`` offsets
``(dy, dx)`` (rows and columns of half-sample symmetric extension prepended,
cropped after synthesis) and the results are averaged.  The offsets
(:func:`shift_set`) come in groups of four with every level-1 grid parity
once and every level-2 residue once per axis.  Default 4.

Functional variance from sample subsets (Eq. 5, 6, 10)
------------------------------------------------------
The paper keeps each pixel's min and max sample; Cycles gives only ``K``
subset means, hence the per-sample variance ``s^2`` and the count ``N``.

* Eq. 5 (sampler): the range is its expectation for ``N`` normal samples,
  ``I_max - I_min ~ d2(N) s`` (:func:`expected_range`), spread symmetrically
  about the mean ``mu``: the squared Mitchell contrast is
  ``min(1, d2(N)^2 s^2 / (2 mu)^2)``, the largest over R, G, B (Mitchell
  refines when any channel exceeds its threshold); the cap 1 is the contrast
  of samples reaching 0.  Eq. 6 divides by ``N``.
* Eq. 10 (reconstruction, ``recon_variance``): the paper uses the range as
  "an upper bound estimate of the pixel variance"; our subsets estimate the
  functional variance itself, so by default (``"sample"``)
  ``sigma^2(F) = s^2`` and ``sigma^2(B) = Var(mean)``: the threshold is
  ``c_s`` standard deviations of each coefficient, Sec. 4.2's "range of
  statistically valid values" read literally.  ``"range"`` is the paper's
  bound ``d2(N)^2 s^2``, which erased texture in our measurements.

Unknown variance (``k < 2``, ``+inf``, non-finite) is replaced by Donoho's
median estimate ``(median |W2_1| / 0.6745)^2`` of the finest diagonal wavelets
per channel, over the squared high-pass gain (``info["unknown_variance_pixels"]``).
Pixels without samples or with non-finite means are filled by pull-push
(``info["missing_pixels"]``).  Values are clamped to ``1e100`` and variances
to ``1e200`` so that squares of coefficients stay finite.

Error estimate (``MethodResult.error``)
---------------------------------------
Stein's unbiased risk estimate of each soft-thresholded coefficient of the
untranslated transform, ``sigma_w^2 - 2 sigma_w^2 [|w| <= t] + min(w^2, t^2)``
with ``t = c_s Delta`` and ``sigma_w^2 = <Var(mean), Psi^2>`` (natural squared
filters: ``Delta^2`` with the renormalisation and, for ``"range"``, the
``Psi^2``-weighted mean of ``d2(N)^2`` divided out), plus the variance of the
untouched coarse coefficients, synthesised with squared synthesis filters
(coefficients taken as uncorrelated), clamped at 0, averaged over RGB.  With
``shifts > 1`` it is conservative: squared error is convex, so the average's
is at most the copies' mean, and every copy has the untranslated one's
expected error up to the borders.  Where the per-pixel consistency below
moves a pixel by ``d`` (RMS over RGB), the estimate becomes
``(sqrt(SURE) + d)^2`` (Minkowski's inequality, conservative again): the
pixels that got a firefly's mass back carry its error.  Measured in
docs/notes/awr.md: 8 x 8 pooled correlation with the true error on glossy
0.31-0.78 -> 0.59-0.93, animated 0.67-0.81 -> 0.77-0.90, other scenes
unchanged (0.74-0.95).

Per-pixel consistency (``consistency``, our addition; 0 = the paper)
--------------------------------------------------------------------
Eq. 10 pools the variance over each coefficient's support, so the soft
threshold moves low-variance pixels beside a firefly, a highlight or a noisy
region by many of their own standard errors (a noise-free region beside a
noisy one: every pixel), and rings negative around bright highlights.  The
pixels are the level-0 scale coefficients of the same basis: we keep them,
too, in their "range of statistically valid values" (Sec. 4.2), clipping each
to ``mean +- t sd`` (the test of ``core.method.consistency_guard``, which then
finds nothing) and to ``>= 0`` where its mean is; the clipped mass goes back
to the uncertain pixels it came from, and the image total to that of the
sample means (:func:`pixel_consistency`).  Measured (docs/notes/awr.md): the
guard's share on the sample scenes 0-10 % -> 0, mean brightness equal to the
sample mean's to 1e-13 (the paper: up to +0.07 %; with the guard's fallback
down to -1.48 %), no negative pixel (before: up to 73, min -1.31), relMSE
within 2 % of paper + guard on four scenes, +7-11 % on glossy (2.6x below
the paper alone) and +1-10 % on animated: the guard's fallback drops the
spread mass of highlights; we keep it (the brightness).

Adaptive sampling (Sec. 4.1, Steps 2-4 of Fig. 4 per render iteration)
----------------------------------------------------------------------
1. ``sigma^2(B) = sigma^2_Mitchell(F) / N`` (Eq. 5, 6); the intensity image is
   the luminance scaled to median ``sampler_intensity``, since Eq. 8 subtracts
   squared intensities from a unit-free variance (exposure invariance).
2. ``P(S_k) = sigma^2(S_k) - (W~_k)^2`` (Eq. 8) for levels
   ``0..sample_levels``; ``sigma^2(S_k)`` by Eq. 9 renormalised to 1.05,
   ``(W~_k)^2`` the mean of the three squared level-k wavelets.  Pixels have
   no wavelets (the paper defines them for ``k >= 1``): their priority is
   their variance.
3. The highest priorities get ``batch_base * 2**k`` samples each, spread as
   expected per-pixel counts over the support with ``|phi_k(x)| |phi_k(y)|``
   (Fig. 5; Cycles cannot place single samples), renormalised inside the
   image.
4. Priorities are updated ``rounds`` times per iteration with the predicted
   variance ``sigma^2(F) / (N + planned)`` (the paper: after every pop).
5. Ordered dithering (8 x 8 pattern, shifted per iteration) makes integer
   counts summing exactly to ``budget``: stratified, where the paper's random
   positions would leave Poisson holes.  Equal priorities give a uniform map.

Precision (``precision``, our addition)
---------------------------------------
Transforms run in float32 by default (about half the memory traffic, and
blocked sgemm filters along x in ``core.wavelets``); input, shift average
and output stay float64, and values above ``1e25`` or variances above
``1e30`` switch to float64.  The soft threshold is applied as a correction,
``soft(w, t) = w - clip(w, -t, t)``, so each plane is
``img - synthesis(clip(W, -t, t))``: the float64 input is exact where nothing
is clipped, and a coefficient's rounding error is at most twice its
threshold (the variance transform sums positive terms: a few ulp).

Cost: 3 transforms per channel and shift plus one squared synthesis for the
error, linear in pixels and ``shifts``; channels and shifts run in threads
(``threads``), at most ``threads + 3`` jobs ahead, so memory does not grow
with ``shifts``.
"""
from __future__ import annotations

import math
import os
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from . import wavelets as wv
from .buffers import Buffers, luminance
from .filters import box_sum
from .method import MethodResult, allocate, median3x3, param, params_from_dict, t_quantile

NAME = "awr"
PASSES: tuple = ()
ADAPTIVE = True
#: ``sample_map`` does not read the reconstruction (Eq. 8 uses the noisy pixel
#: means), so the render loop skips the per-iteration reconstruction
SAMPLER_USES_RESULT = False

_BIG_VALUE = 1e100
_BIG_VAR = 1e200
_MAD_SCALE = 0.6744897501960817  # Phi^-1(3/4)
#: largest pixel value and variance for float32 transforms (float32 overflows
#: at 3.4e38; level-k scale coefficients are 2^k times the pixels)
_F32_MAX_VALUE = 1e25
_F32_MAX_VAR = 1e30


#: Grid translations (dy, dx) for ``Params.shifts``: four Latin transversals of
#: the 4 x 4 grid, in this order.  Each group of four contains every 2 x 2
#: parity once (the level-1 grid positions) and every residue mod 4 once per
#: axis (the level-2 positions along each axis); all sixteen are the whole grid.
_SHIFT_ORDER = ((0, 0), (1, 2), (2, 1), (3, 3),
                (0, 2), (1, 0), (2, 3), (3, 1),
                (0, 1), (1, 3), (2, 0), (3, 2),
                (0, 3), (1, 1), (2, 2), (3, 0))


def shift_set(count: int) -> tuple:
    """The first ``count`` grid translations ``(dy, dx)`` of the cycle spinning
    (``_SHIFT_ORDER``; 1 gives the paper's untranslated transform only)."""
    count = int(count)
    if not 1 <= count <= len(_SHIFT_ORDER):
        raise ValueError(f"shifts must be in 1..{len(_SHIFT_ORDER)}, not {count}")
    return _SHIFT_ORDER[:count]


@dataclass
class Params:
    """AWR parameters with the paper's defaults (Sec. 5.3: "we use the
    Daubechies 9/7 filter bank, 64 x 2^k rays per adaptive iteration, c_s = 1,
    sampling variance filters renormalised to 1.05 and reconstruction variance
    filters to 2^-1/2")."""

    wavelet: str = param(
        "cdf97", "Filter bank: cdf97 (paper default, smoothest), legall53 (faster, some "
        "artifacts) or haar (fastest, blocky); speed vs smoothness (Fig. 8)",
        choices=("cdf97", "legall53", "haar"), label="Wavelet")
    smoothing: float = param(
        1.0, "c_s of Eq. 11: threshold = c_s x coefficient error; larger removes more "
        "noise but may ring or blur edges", 0.0, 10.0, label="Smoothing")
    recon_filter_sum: float = param(
        2.0 ** -0.5, "Sum of the squared reconstruction filters (paper 2^-1/2); lower damps "
        "smoothing at coarse levels (fewer artifacts, more low-frequency noise)", 0.01, 2.0, label="Reconstruction Filter Energy")
    sample_filter_sum: float = param(
        1.05, "Sum of the squared sampler low-pass filter (Eq. 9, paper 1.05); above 1 "
        "sends samples to coarser levels", 0.5, 2.0, label="Sampling Filter Energy")
    levels: int = param(
        0, "Wavelet levels for reconstruction, 0 = full depth (paper); fewer levels are "
        "slightly faster but leave low-frequency noise", 0, 30, label="Levels")
    sample_levels: int = param(
        5, "Coarsest scale-coefficient level the sampler considers (paper 0..5); more "
        "levels allow coarser, smoother sampling", 0, 12, label="Sampling Levels")
    batch_base: int = param(
        64, "Samples per chosen coefficient are batch_base x 2^level (paper 64); larger "
        "batches adapt less finely but plan faster", 1, 1 << 20, label="Samples per Coefficient")
    rounds: int = param(
        16, "Priority updates per render iteration (paper: after every coefficient); "
        "more rounds follow the paper more closely at O(pixels) cost each", 1, 4096, label="Priority Updates")
    recon_variance: str = param(
        "sample", "sigma^2(F) of Eq. 10 (reconstruction thresholds): sample (the per-sample "
        "variance from the sample subsets, default: threshold = c_s standard deviations) or "
        "range (the paper's (I_max - I_min)^2 bound, d2(N)^2 x larger: much smoother, "
        "erases texture)", choices=("sample", "range"), label="Reconstruction Variance")
    sampler_intensity: float = param(
        0.5, "Median luminance the sampler maps the image to before Eq. 8; higher weighs "
        "edges (wavelet magnitude) more against variance", 1e-3, 1e3, label="Sampler Brightness")
    seed: int = param(0, "Seed for breaking ties between equal priorities (reproducibility only)",
                      0, 2 ** 31 - 1, label="Seed")
    shifts: int = param(
        4, "Translations of the wavelet grid averaged in the reconstruction (cycle spinning; "
        "1 = the paper's single transform); more remove more grid artifacts, cost grows "
        "linearly", 1, len(_SHIFT_ORDER), label="Grid Shifts")
    threads: int = param(
        0, "Worker threads for the transforms (one job per channel and grid shift; 0 = one "
        "per core from 0.5 megapixel, one below)", 0, 64, label="Threads")
    consistency: float = param(
        3.0, "Per-pixel consistency (our addition; 0 = the paper's Eq. 11 alone): every pixel is "
        "kept within this many standard errors of its own sample mean (Student-t for its "
        "subsets); stops the pooled thresholds from spreading fireflies and noisy regions into "
        "low-variance neighbours", 0.0, 100.0, label="Pixel Consistency")
    precision: str = param(
        "float32", "Arithmetic of the reconstruction's transforms: float32 (default, about 2x "
        "faster; each coefficient's correction errs by at most ~1e-7 of the local signal "
        "and never by more than twice its threshold) or float64 (exact to ~1e-15)",
        choices=("float32", "float64"), label="Precision")


# ----------------------------------------------------------------------------
# Functional variance from sample subsets
# ----------------------------------------------------------------------------
_ACK_A = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02,
          1.383577518672690e+02, -3.066479806614716e+01, 2.506628277459239e+00)
_ACK_B = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02,
          6.680131188771972e+01, -1.328068155288572e+01)
_ACK_C = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00,
          -2.549671010135738e+00, 4.374664141464968e+00, 2.938163982698783e+00)
_ACK_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00,
          3.754408661907416e+00)


def _norm_ppf_upper(p: np.ndarray) -> np.ndarray:
    """Standard normal quantile for ``0.5 <= p < 1`` (Acklam's rational
    approximation, relative error < 1.2e-9)."""
    p = np.clip(np.asarray(p, np.float64), 0.5, 1.0 - 1e-300)
    out = np.empty_like(p)
    central = p <= 0.97575
    q = p[central] - 0.5
    r = q * q
    a, b = _ACK_A, _ACK_B
    out[central] = ((((((a[0] * r + a[1]) * r + a[2]) * r + a[3]) * r + a[4]) * r + a[5]) * q
                    / (((((b[0] * r + b[1]) * r + b[2]) * r + b[3]) * r + b[4]) * r + 1.0))
    q = np.sqrt(-2.0 * np.log1p(-p[~central]))
    c, d = _ACK_C, _ACK_D
    out[~central] = -((((((c[0] * q + c[1]) * q + c[2]) * q + c[3]) * q + c[4]) * q + c[5])
                      / ((((d[0] * q + d[1]) * q + d[2]) * q + d[3]) * q + 1.0))
    return out


@lru_cache(maxsize=1)
def _range_table(nmax: int = 64) -> np.ndarray:
    """Exact ``d2(N)`` for ``N = 0..nmax`` by quadrature of
    ``E[R] = int 1 - Phi(x)^N - (1 - Phi(x))^N dx`` (entries 0, 1 unused)."""
    x = np.linspace(-9.0, 9.0, 3601)
    cdf = 0.5 * (1.0 + np.vectorize(math.erf)(x / math.sqrt(2.0)))
    ns = np.arange(nmax + 1, dtype=np.float64)[:, None]
    f = 1.0 - cdf[None, :] ** ns - (1.0 - cdf[None, :]) ** ns
    return np.trapz(f, x, axis=1)


def expected_range(n) -> np.ndarray:
    """``d2(N)``: expected range ``E[max - min]`` of ``N`` standard normal samples.

    Exact (quadrature) for integer ``N <= 64``, otherwise Blom's approximation
    ``2 Phi^-1((N - 0.375) / (N + 0.25))`` scaled by 1.003 to join the exact
    value at 64;
    ``N < 2`` (and non-finite ``N``) use ``N = 2``.  Stands in for Eq. 5 and
    10's ``I_max - I_min`` as ``d2(N) s`` (module docstring).

    n : array_like of sample counts -> same shape, float64 >= 1.128
    """
    n = np.asarray(n, np.float64)
    n = np.where(np.isfinite(n), np.clip(n, 2.0, 1e15), 2.0)
    table = _range_table()

    blom = lambda v: 2.0 * _norm_ppf_upper((v - 0.375) / (v + 0.25))
    top = len(table) - 1
    join = table[top] / float(blom(np.array([float(top)]))[0])

    def direct(v):
        out = join * blom(v)  # continuous (and monotone) at N = 64
        small = (v <= 64) & (v == np.floor(v))
        if small.any():
            out[small] = table[v[small].astype(np.int64)]
        return out

    if n.size > 64:  # few distinct counts: evaluate once per count
        lo, hi = float(n.min()), float(n.max())
        if lo == hi:
            return np.full(n.shape, float(direct(np.array([lo]))[0]))
        if hi - lo <= 1 << 20 and np.array_equal(n, np.floor(n)):
            tab = direct(np.arange(int(lo), int(hi) + 1, dtype=np.float64))
            return tab[n.astype(np.int64) - int(lo)]
    return direct(np.atleast_1d(n)).reshape(n.shape)


def spread_factor(n, mode: str = "sample") -> np.ndarray:
    """Squared spread ``sigma^2(F) / s^2`` of the functional-variance estimator.

    ``"range"``: ``d2(N)^2``, so that ``sigma^2(F) = (I_max - I_min)^2`` in
    expectation (the paper's upper bound); ``"sample"``: 1, ``sigma^2(F) = s^2``.
    n : array of sample counts -> float64 array of the same shape.
    """
    if mode == "range":
        d2 = expected_range(n)
        return d2 * d2
    if mode != "sample":
        raise ValueError(f"recon_variance must be 'sample' or 'range', not {mode!r}")
    return np.ones(np.shape(n))


def mitchell_variance(mean: np.ndarray, sample_var: np.ndarray, n) -> np.ndarray:
    """Squared Mitchell contrast ``(I_max - I_min)^2 / (I_max + I_min)^2`` (Eq. 5).

    Numerator ``(d2(N) s)^2``, the expected squared range
    (``spread_factor(N, "range") s^2``), ``I_max + I_min = 2 |mu|``; capped at 1.

    mean, sample_var : (H, W, C) per-channel pixel mean and per-sample variance
    n : (H, W) sample counts
    Returns (H, W) float64 in [0, 1], the largest over channels.
    """
    num = spread_factor(n, "range")[..., None] * np.maximum(sample_var, 0.0)
    den = 4.0 * mean * mean
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        c2 = np.where(num >= den, (num > 0).astype(np.float64), num / np.where(den > 0, den, 1.0))
    c2 = np.where(np.isfinite(c2), c2, 1.0)
    return c2.max(axis=-1)


# ----------------------------------------------------------------------------
# Input hygiene
# ----------------------------------------------------------------------------
def _pull_push(x: np.ndarray, valid: np.ndarray, default: float = 0.0) -> np.ndarray:
    """Fill ``x`` where ``valid`` is False from valid neighbours (pull-push over a
    2 x 2 box pyramid).  x, valid : (H, W, C)."""
    if valid.all():
        return x
    vals = [np.where(valid, x, 0.0)]
    wts = [valid.astype(np.float64)]
    while (vals[-1].shape[0] > 1 or vals[-1].shape[1] > 1) and not (wts[-1] > 0).all():
        v, w = vals[-1], wts[-1]
        h, wd = v.shape[:2]
        ph, pw = h % 2, wd % 2
        if ph or pw:
            v = np.pad(v, ((0, ph), (0, pw), (0, 0)))
            w = np.pad(w, ((0, ph), (0, pw), (0, 0)))
        v = v[0::2, 0::2] + v[1::2, 0::2] + v[0::2, 1::2] + v[1::2, 1::2]
        w = w[0::2, 0::2] + w[1::2, 0::2] + w[0::2, 1::2] + w[1::2, 1::2]
        vals.append(v)
        wts.append(w)
    est = np.where(wts[-1] > 0, vals[-1] / np.where(wts[-1] > 0, wts[-1], 1.0), default)
    for v, w in zip(reversed(vals[:-1]), reversed(wts[:-1])):
        h, wd = v.shape[:2]
        up = np.repeat(np.repeat(est, 2, axis=0), 2, axis=1)[:h, :wd]
        est = np.where(w > 0, v / np.where(w > 0, w, 1.0), up)
    return np.where(valid, x, est)


def _mad_pixel_variance(img: np.ndarray, bank: wv.FilterBank) -> np.ndarray:
    """Per-channel pixel noise variance from the finest wavelets (Donoho's MAD).

    img : (H, W, C) -> (C,) float64 >= 0; 0 for a 1 x 1 image.
    """
    c = img.shape[-1]
    pyr = wv.dwt2(img, bank, levels=1)
    if not pyr.details:
        return np.zeros(c)
    w0, w1, w2 = pyr.details[0]
    hi2 = float(np.sum(wv.squared_bank(bank).full("hi_a")[1]))
    if w2.size:
        coef, gain = w2, hi2 * hi2
    else:
        coef, gain = (w0 if w0.size else w1), hi2
    med = np.median(np.abs(coef.reshape(-1, c)), axis=0)
    return (med / _MAD_SCALE) ** 2 / gain


@dataclass
class _Prepared:
    mean: np.ndarray        # (H, W, 3) finite, clamped, missing pixels filled
    var: np.ndarray         # (H, W, 3) finite >= 0 variance of the mean
    n: np.ndarray           # (H, W) sample counts (0 where none)
    missing: np.ndarray     # (H, W) bool: no samples or non-finite mean
    unknown: np.ndarray     # (H, W) bool: variance estimated by the MAD fallback


def _prepare(mean, var, n, bank) -> _Prepared:
    mean = np.asarray(mean, np.float64)
    if mean.ndim == 2:
        mean = mean[..., None]
    h, w, c = mean.shape
    n = np.broadcast_to(np.asarray(n, np.float64), (h, w))
    n = np.where(np.isfinite(n) & (n > 0), n, 0.0)
    var = np.broadcast_to(np.asarray(var, np.float64).reshape(h, w, -1), (h, w, c))
    # ranges by reductions (no temporaries): NaN propagates to min/max, so
    # finite extremes mean every value is finite
    m_lo, m_hi = float(mean.min(initial=0.0)), float(mean.max(initial=0.0))
    v_lo, v_hi = float(var.min(initial=0.0)), float(var.max(initial=0.0))
    if (np.isfinite(m_lo) and np.isfinite(m_hi) and np.isfinite(v_lo) and np.isfinite(v_hi)
            and bool(n.min(initial=1.0) > 0)
            and max(m_hi, -m_lo) <= _BIG_VALUE and v_lo >= 0.0 and v_hi <= _BIG_VAR):
        none = np.zeros((h, w), bool)
        return _Prepared(mean, var, n, none, none)
    missing = ~np.isfinite(mean).all(axis=-1) | (n <= 0)
    m = np.clip(np.where(np.isfinite(mean), mean, 0.0), -_BIG_VALUE, _BIG_VALUE)
    valid3 = np.broadcast_to(~missing[..., None], m.shape)
    if missing.any():
        m = _pull_push(m, valid3)
    known = np.isfinite(var) & (var >= 0) & valid3
    v = np.where(known, np.minimum(np.where(known, var, 0.0), _BIG_VAR), 0.0)
    unknown = ~missing & ~known.all(axis=-1)
    if unknown.any() or (missing.any() and not known.any()):
        mad = np.minimum(_mad_pixel_variance(m, bank), _BIG_VAR)
        v = np.where(~known & valid3, mad, v)
        known = known | valid3
    if missing.any():
        v = _pull_push(v, known, default=0.0)
    return _Prepared(m, v, n, missing, unknown)


# ----------------------------------------------------------------------------
# Reconstruction (Sec. 4.2)
# ----------------------------------------------------------------------------
def soft_threshold(w: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``sign(w) max(0, |w| - t)`` (Eq. 11 with ``t = c_s Delta``), computed as
    ``w - clip(w, -t, t)`` (the same values, two passes instead of five)."""
    return w - np.clip(w, -t, t)


def sure_soft(w: np.ndarray, t: np.ndarray, var: np.ndarray) -> np.ndarray:
    """Stein's unbiased estimate of ``E[(soft(w, t) - w_true)^2]`` for Gaussian
    noise of variance ``var``: ``var - 2 var [|w| <= t] + min(w^2, t^2)``."""
    aw = np.abs(w)
    out = np.minimum(aw, t)
    out *= out
    out += np.where(aw <= t, -var, var)
    return out


def _subband_gains(shape, levels, r_lo, r_hi) -> tuple:
    """Per-subband factors turning natural squared-filter variances into
    renormalised ones (each 1D application multiplies by ``r`` = target /
    natural sum; axes of length 1 are not filtered)."""
    ty, tx = wv.axis_levels(shape[0]), wv.axis_levels(shape[1])
    acc = 1.0
    out = []
    for k in range(1, levels + 1):
        fy_lo = r_lo if k <= ty else 1.0
        fx_lo = r_lo if k <= tx else 1.0
        out.append((acc * fy_lo * r_hi, acc * r_hi * fx_lo, acc * r_hi * r_hi))
        acc *= fy_lo * fx_lo
    return out, acc


def _plane_correction(img, rvar, nat_ratio, bank, levels, params):
    """Eq. 7, 10, 11 for one channel, as the correction the threshold makes.

    img : (H, W) pixel means and rvar : (H, W) ``sigma^2(B)`` of Eq. 10, both
    in the precision of the transforms (module docstring, "Precision");
    nat_ratio : per level (r0, r1, r2) factors (scalars or arrays) that turn the
    renormalised ``Delta^2`` into the coefficient's actual variance, plus the
    factor for the coarsest scale coefficients; ``None``: no error estimate
    and no counts (the translated copies of the cycle spinning).

    The soft threshold is ``soft(w, t) = w - clip(w, -t, t)``, so synthesising
    the thresholded pyramid gives ``img - synthesis(clip(W, -t, t))`` (perfect
    reconstruction; the coarsest scale coefficients are kept, so they are not
    in the correction).  Returning only the correction keeps the input exact
    where nothing is clipped, and bounds each coefficient's rounding error by twice
    its threshold ``t``.

    Returns (correction (H, W) or ``None`` when no threshold is positive, SURE
    pyramid or None, (zero coefficients after thresholding, coefficients)).
    """
    dtype = img.dtype
    pyr = wv.dwt2(img, bank, levels, dtype=dtype)
    r = float(params.recon_filter_sum)
    dpyr = wv.dwt2_variance(rvar, bank, levels, lo_sum=r, hi_sum=r, dtype=dtype)
    cs = float(params.smoothing)
    shrunk = False
    zeroed = total = 0
    sure_details = []
    clipped = []
    for k, (det, dv) in enumerate(zip(pyr.details, dpyr.details)):
        cd, sd = [], []
        for alpha, (w, d2b) in enumerate(zip(det, dv)):
            t = np.sqrt(d2b)
            t *= cs
            shrunk = shrunk or bool(t.any())
            cd.append(np.clip(w, -t, t))
            if nat_ratio is not None:
                zeroed += int(np.count_nonzero(np.abs(w) <= t))
                total += w.size
                sd.append(sure_soft(w, t, d2b * nat_ratio[0][k][alpha]))
        clipped.append(tuple(cd))
        sure_details.append(tuple(sd))
    sure = (None if nat_ratio is None
            else wv.Pyramid(dpyr.approx * nat_ratio[1], sure_details, dpyr.axes))
    if not shrunk:
        return None, sure, (zeroed, total)
    corr = wv.idwt2(wv.Pyramid(np.zeros(pyr.approx.shape, dtype), clipped, pyr.axes), bank)
    return corr, sure, (zeroed, total)


def _precision(params, mean: np.ndarray, rvar: np.ndarray):
    """dtype of the transforms: ``params.precision``, float64 where values or
    variances approach float32's range (module docstring, "Precision")."""
    if str(params.precision) == "float64":
        return np.float64
    if (max(float(mean.max(initial=0.0)), -float(mean.min(initial=0.0))) > _F32_MAX_VALUE
            or float(rvar.max(initial=0.0)) > _F32_MAX_VAR):
        return np.float64
    return np.float32


def _bounded_map(pool, fn, jobs, ahead: int):
    """``pool.map(fn, jobs)`` in order, with at most ``ahead`` jobs submitted
    and not yet consumed (bounded memory for large job lists)."""
    pending = deque()
    it = iter(jobs)
    for job in it:
        pending.append(pool.submit(fn, job))
        if len(pending) >= ahead:
            break
    while pending:
        fut = pending.popleft()
        nxt = next(it, None)
        if nxt is not None:
            pending.append(pool.submit(fn, nxt))
        yield fut.result()


#: below this many pixels ``threads = 0`` runs the transforms in one thread:
#: per-call overhead dominates small transforms and threads contend for the
#: GIL (timings: docs/notes/awr.md)
_THREAD_MIN_PIXELS = 1 << 19


def _n_threads(params, c, pixels):
    if params.threads:
        t = int(params.threads)
    elif pixels < _THREAD_MIN_PIXELS:
        t = 1
    else:
        t = os.cpu_count() or 1
    return max(1, min(t, c))


def _natural_ratios(shape, levels, bank, r, d2sq):
    """Factors from the renormalised range-based ``Delta^2`` to each coefficient's
    actual variance ``<Var(mean), Psi^2>`` (natural squared filters).

    Renormalising a squared 1D filter multiplies it by ``r / natural sum``, so
    per subband ``Delta^2 = g * <d2^2 Var, Psi^2_nat>`` with a constant ``g``.
    The range factor ``d2(N)^2`` is divided out as its ``Psi^2``-weighted mean
    over the coefficient's support (exact where ``N`` is locally constant; the
    reconstruction itself uses the exact Eq. 10, only the error estimate uses
    this ratio).
    """
    sq = wv.squared_bank(bank)
    a = float(np.sum(sq.full("lo_a")[1]))
    b = float(np.sum(sq.full("hi_a")[1]))
    g, g_app = _subband_gains(shape, levels, r / a, r / b)
    if np.ptp(d2sq) == 0:
        c = float(d2sq.flat[0])
        return [tuple(1.0 / (c * gi) for gi in gk) for gk in g], 1.0 / (c * g_app)
    ones, ones_app = _subband_gains(shape, levels, a, b)
    dp = wv.dwt2_variance(d2sq, bank, levels)
    det = [tuple(o / (gi * np.maximum(band, 1e-300)) for band, gi, o in zip(db, gk, ok))
           for db, gk, ok in zip(dp.details, g, ones)]
    return det, ones_app / (g_app * np.maximum(dp.approx, 1e-300))


def _shifted(x: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``x`` (H, W) translated by ``(dy, dx)`` against the wavelet grid: ``dy``
    rows and ``dx`` columns of half-sample symmetric extension prepended
    (cropped off again after synthesis), as a new C-contiguous array; ``x``
    itself when there is nothing to prepend."""
    h, w = x.shape
    if not dy and not dx:
        return x
    if dy > h or dx > w:  # extension longer than the image: repeated mirroring
        return np.pad(x, ((dy, 0), (dx, 0)), mode="symmetric")
    out = np.empty((h + dy, w + dx), x.dtype)
    out[dy:, dx:] = x
    if dy:
        out[:dy, dx:] = x[dy - 1::-1]
    if dx:
        out[:, :dx] = out[:, 2 * dx - 1:dx - 1:-1] if dx > 1 else out[:, 1:2]
    return out


def pixel_consistency(image: np.ndarray, mean: np.ndarray, var: np.ndarray, z: float,
                      dof=None, known: np.ndarray | None = None) -> tuple:
    """Project the reconstruction onto each pixel's own confidence interval.

    Eq. 11 keeps every wavelet coefficient within ``c_s Delta`` of its measured
    value, but ``Delta`` (Eq. 10) pools the variance over the coefficient's
    support: next to a firefly or a noisy region, pixels of small variance are
    moved by many of their own standard errors (on a noise-free region beside
    a noisy one, every pixel).  The pixels are the level-0 scale coefficients
    of the same basis, so we apply the paper's "range of statistically valid
    values" (Sec. 4.2) to them too: each channel is clipped to
    ``mean +- t sd``, ``t`` the Student-t value of two-sided tail ``z`` for
    ``dof`` degrees of freedom (the normal ``z`` where ``dof`` is None) and
    ``sd`` the pixel's standard error, at least the 3 x 3 median of its
    neighbours' (a pixel whose few subsets agreed by chance is not pinned),
    the same test as ``core.method.consistency_guard``, which then finds
    nothing to reject.  A clip rather than a fallback keeps the smoothing that
    the interval allows; the clipped mass is handed back (``_give_back``), so
    the mean brightness stays that of the samples.  Channels whose mean is
    >= 0 are also kept >= 0 (no negative radiance from ringing).  ``z <= 0``
    returns the image unchanged (the paper).  Our addition, not in the paper.

    image, mean, var : (H, W, C); dof : (H, W) or None; known : (H, W) bool,
    pixels whose variance is measured (the others get the positivity clip only).
    Returns (image, (H, W) bool of pixels changed).
    """
    if not z > 0:
        return image, np.zeros(image.shape[:2], bool)
    ok = np.isfinite(var) & (var >= 0)
    if known is not None:
        ok &= known[..., None]
    sd = np.sqrt(np.where(ok, var, 0.0))
    sd = np.maximum(sd, median3x3(sd))
    thr = (np.full(mean.shape[:2], float(z)) if dof is None
           else t_quantile(float(z), np.maximum(np.asarray(dof, np.float64) - 1.0, 1.0)))
    half = thr[..., None] * sd
    # a few ulp inside, so that |x - mean| <= half holds when recomputed
    half -= 1e-15 * (np.abs(mean) + half)
    np.maximum(half, 0.0, out=half)
    half[~ok] = np.inf
    lo, hi = mean - half, mean + half
    lo = np.where(mean >= 0, np.maximum(lo, 0.0), lo)
    out = np.clip(image, lo, hi)
    changed = (out != image).any(axis=-1)
    out = _give_back(image, out, lo, hi, np.where(ok, sd * sd, 0.0), mean)
    return out, changed


#: local passes that give clipped mass back (``_give_back``): (block size,
#: radius in blocks).  One pass on 8 x 8 pixel blocks, 7 x 7 blocks wide:
#: the mass stays within ~28 px of where the clip removed it, at 1/64 of
#: the cost of a pixel pass; an added pixel-exact pass (7 x 7 px) first,
#: which hands a firefly's halo back to the firefly, cost 3-5 % relMSE on
#: glossy, 1 % on animated, nothing elsewhere (docs/notes/awr.md)
_GIVE_BACK_PASSES = ((8, 3),)


def _block_sums(x, b):
    """Sums over ``b x b`` blocks (the last ones partial): (H, W, C) -> (ceil(H/b), ceil(W/b), C)."""
    if b == 1:
        return x
    h, w = x.shape[:2]
    ph, pw = -h % b, -w % b
    if ph or pw:
        x = np.pad(x, ((0, ph), (0, pw), (0, 0)))
    return x.reshape(x.shape[0] // b, b, x.shape[1] // b, b, -1).sum(axis=(1, 3))


def _scatter(amount, weight, block, r):
    """``weight_p * sum_{q in window(p)} amount_q / box_sum(weight)_q``: each
    ``amount_q`` split over its (2r+1)^2 window in proportion to ``weight``,
    exactly (up to float32 rounding) where that window holds any weight.
    With ``block > 1`` the windows are made of ``block x block`` pixel blocks
    (amounts and weights summed per block), and a block's share is split over
    its pixels in proportion to their weight, which is still exact."""
    a, wgt = _block_sums(amount, block), _block_sums(weight, block)
    den = box_sum(wgt, r, dtype=np.float32)
    share = np.divide(a, den, out=np.zeros(a.shape, np.float32), where=den > 0, dtype=np.float32)
    per_weight = box_sum(share, r, dtype=np.float32)
    if block > 1:
        h, w = amount.shape[:2]
        per_weight = np.repeat(np.repeat(per_weight, block, axis=0), block, axis=1)[:h, :w]
    return weight * per_weight


def _give_back(image, out, lo, hi, weight, mean):
    """Return the mass the clip removed to the pixels that can hold it.

    The soft threshold moved the mass of a firefly (or of a noisy region) into
    its low-variance neighbours; clipping those neighbours alone would darken
    the image (by 25-30 % on ``tests/core/test_awr.py``'s highlights).  Each
    removed amount ``r_q = image_q - out_q`` is split over the window around
    ``q`` in proportion to the variance ``w_p`` (the uncertain pixels the mass
    came from), then clipped again (``_GIVE_BACK_PASSES``).  Two
    last passes give the whole image, per channel, the total of its sample
    means, spread in proportion to ``w`` over the pixels with room: Eq. 11
    keeps the coarsest scale coefficients, but with symmetric boundaries the
    coarse wavelets are not zero-sum, so the paper's reconstruction itself can
    drift by a few percent where bright, uncertain highlights dominate (the
    mean of many pixels is known far better than any pixel).
    """
    for block, r in _GIVE_BACK_PASSES:
        resid = image - out
        if not resid.any():
            break
        image = out + _scatter(resid, weight, block, r)
        out = np.clip(image, lo, hi)
    c = out.shape[-1]
    total = mean.reshape(-1, c).sum(axis=0)
    for _ in range(2):
        d = total - out.reshape(-1, c).sum(axis=0)  # per channel
        room = np.where(d > 0, out < hi, out > lo)
        wr = np.where(room, weight, 0.0)
        tot = wr.reshape(-1, c).sum(axis=0)
        q = np.divide(d, tot, out=np.zeros_like(tot), where=tot > 0)
        with np.errstate(over="ignore", invalid="ignore"):
            # where a pixel has no room its share is 0 even when d / tot
            # overflowed (a 1e30 total over weights of 1e-300): never 0 * inf
            add = np.where(wr > 0, wr * q, 0.0)
            out = np.clip(out + np.where(np.isnan(add), 0.0, add), lo, hi)
    return out


def wavelet_reconstruct(mean: np.ndarray, var: np.ndarray, n, params: Params | None = None,
                        k=None) -> MethodResult:
    """Adaptive wavelet reconstruction (Sec. 4.2) from arrays.

    With ``params.shifts = S > 1`` the reconstruction of Eq. 7, 10, 11 is run on
    the image translated by each of the ``S`` offsets of :func:`shift_set`
    against the dyadic grid and the ``S`` results are averaged (cycle spinning;
    module docstring).  ``shifts = 1`` is the paper's single transform.

    Parameters
    ----------
    mean : (H, W, 3) pixel means (NaN/Inf allowed: treated as missing)
    var : (H, W, 3) variance of each pixel mean (``+inf``/NaN: unknown, see the
        module docstring)
    n : (H, W) or scalar, samples per pixel (0: missing pixel)
    params : Params (paper defaults)
    k : (H, W) sample subsets per pixel (the degrees of freedom of ``var``
        for :func:`pixel_consistency`); None: the normal quantile

    Returns
    -------
    MethodResult(image (H, W, 3), error (H, W) estimated squared error, info)
    """
    params = params or Params()
    bank = wv.get_bank(params.wavelet)
    prep = _prepare(mean, var, n, bank)
    h, w, c = prep.mean.shape
    shifts = shift_set(params.shifts)
    d2sq = spread_factor(prep.n, params.recon_variance)
    if np.ptp(d2sq) == 0 and float(d2sq.flat[0]) == 1.0:
        rvar = prep.var  # "sample": sigma^2(F) = s^2, already clamped by _prepare
    else:
        rvar = np.minimum(d2sq[..., None] * prep.var, _BIG_VAR)
    dtype = _precision(params, prep.mean, rvar)
    per_shift = []
    for dy, dx in shifts:
        shape = (h + dy, w + dx)
        full = wv.max_levels(shape)
        levels = full if int(params.levels) <= 0 else min(int(params.levels), full)
        # factors for the error estimate, which only the untranslated transform
        # gives (None: _plane_correction skips it)
        ratios = (_natural_ratios(shape, levels, bank, float(params.recon_filter_sum), d2sq)
                  if not per_shift else None)
        per_shift.append((dy, dx, levels, ratios))

    # contiguous planes in the transforms' precision, once (each shift copies
    # them again with its extension)
    mean_planes = [np.ascontiguousarray(prep.mean[..., ch], dtype) for ch in range(c)]
    var_planes = [np.ascontiguousarray(rvar[..., ch], dtype) for ch in range(c)]

    def work(job):
        si, ch = job
        dy, dx, levels, ratios = per_shift[si]
        return _plane_correction(_shifted(mean_planes[ch], dy, dx), _shifted(var_planes[ch], dy, dx),
                                 ratios, bank, levels, params)

    jobs = [(si, ch) for si in range(len(shifts)) for ch in range(c)]
    nt = _n_threads(params, len(jobs), h * w)
    pool = ThreadPoolExecutor(nt) if nt > 1 else None
    # the image is the input minus the mean correction over the shifts (float64
    # sums): exactly the input where no coefficient is clipped
    total_corr = [None] * c
    sure = None
    zeroed = total = 0
    try:
        # consumed in job order (shift 0's channels first); the pool runs at
        # most nt + c jobs ahead, so memory does not grow with the shifts
        results = _bounded_map(pool, work, jobs, nt + c) if pool else map(work, jobs)
        for (si, ch), (corr, pyr, (z, t)) in zip(jobs, results):
            if corr is not None:
                dy, dx = per_shift[si][:2]
                if total_corr[ch] is None:
                    total_corr[ch] = np.zeros((h, w))
                total_corr[ch] += corr[dy:, dx:]
            if si == 0:
                zeroed, total = zeroed + z, total + t
                if sure is None:
                    sure = pyr
                else:
                    sure.approx = sure.approx + pyr.approx
                    sure.details = [tuple(a + b for a, b in zip(da, db))
                                    for da, db in zip(sure.details, pyr.details)]
    finally:
        if pool:
            pool.shutdown()
    image = np.empty(prep.mean.shape)
    for ch, tc in enumerate(total_corr):
        if tc is None:
            image[..., ch] = prep.mean[..., ch]
        else:
            tc *= 1.0 / len(shifts)
            np.subtract(prep.mean[..., ch], tc, out=image[..., ch])
    # Error: SURE per coefficient of the untranslated transform, averaged over
    # channels, squared synthesis (module docstring: conservative for the
    # averaged image, squared error being convex)
    sure.approx = sure.approx / c
    sure.details = [tuple(b / c for b in d) for d in sure.details]
    err = wv.idwt2_variance(sure, bank)
    err = np.where(np.isfinite(err), np.maximum(err, 0.0), _BIG_VAR)
    if not (np.isfinite(image.min(initial=0.0)) and np.isfinite(image.max(initial=0.0))):
        image = np.where(np.isfinite(image), image, 0.0)
    kk = None if k is None else np.broadcast_to(np.asarray(k, np.float64), (h, w))
    paper = image
    image, clipped = pixel_consistency(image, prep.mean, prep.var, float(params.consistency), kk,
                                       known=~(prep.missing | prep.unknown))
    if image is not paper:
        # Minkowski: ||x' - truth|| <= ||x - truth|| + |x' - x| (module docstring)
        moved = np.sqrt(np.mean((image - paper) ** 2, axis=-1))
        err = np.minimum((np.sqrt(err) + moved) ** 2, _BIG_VAR)
    info = {
        "wavelet": bank.name,
        "levels": int(per_shift[0][2]),
        "shifts": len(shifts),
        "zeroed_fraction": zeroed / total if total else 0.0,
        "missing_pixels": int(prep.missing.sum()),
        "unknown_variance_pixels": int(prep.unknown.sum()),
        "consistency_fraction": float(clipped.mean()) if clipped.size else 0.0,
    }
    return MethodResult(image, err, info)


def reconstruct(buf: Buffers, params: Params | None = None) -> MethodResult:
    """AWR reconstruction of the accumulated samples (Sec. 4.2, Eq. 7, 10, 11).

    Uses ``buf.color.mean``, :func:`variance_of_mean`, ``buf.n`` and ``buf.k``; the
    functional variance of Eq. 10 is ``s^2`` (``recon_variance = "sample"``) or
    ``d2(N)^2 s^2`` (``"range"``, the paper's bound; module docstring).
    Pixels with fewer than 2 subsets (variance ``+inf``) get the image's own
    MAD noise estimate; pixels without samples are filled from neighbours.

    Returns
    -------
    MethodResult: image (H, W, 3), error (H, W) estimated squared error
    (SURE, averaged over RGB), info (wavelet, levels, ``zeroed_fraction`` of
    the untranslated transform's wavelet coefficients that are zero after
    Eq. 11, ``missing_pixels``,
    ``unknown_variance_pixels``).
    """
    return wavelet_reconstruct(buf.color.mean, variance_of_mean(buf), buf.n, params, k=buf.k)


def variance_of_mean(buf: Buffers) -> np.ndarray:
    """The variance of each pixel mean that AWR uses (Eq. 6, 10 and the
    per-pixel consistency): the one place it enters, for reconstruction and
    sampler alike.  Today ``buf.variance_of_mean()`` (between-subset estimate)."""
    return buf.variance_of_mean()


def denoise(color: np.ndarray, color_var: np.ndarray, features: dict | None = None,
            feature_var: dict | None = None, n=None,
            params: Params | dict | None = None) -> MethodResult:
    """Wavelet reconstruction of a uniform render alone (the paper's Fig. 10b).

    Parameters
    ----------
    color : (H, W, 3) pixel means
    color_var : (H, W, 3) variance of the pixel means (``+inf``: unknown)
    features, feature_var : ignored (AWR uses no feature passes)
    n : samples per pixel of the render (scalar or (H, W)); sets ``d2(N)`` of
        the range estimate (``recon_variance = "range"``).  None: 16.
    params : Params or dict of its fields
    """
    if isinstance(params, dict):
        params = params_from_dict(Params, params)
    color = np.asarray(color, np.float64)
    return wavelet_reconstruct(color, color_var, np.broadcast_to(
        np.asarray(16 if n is None else n, np.float64), color.shape[:2]), params)


# ----------------------------------------------------------------------------
# Adaptive sampling (Sec. 4.1)
# ----------------------------------------------------------------------------
@dataclass
class _SamplerInputs:
    sigma_f: np.ndarray      # (H, W) Eq. 5 functional variance (per sample)
    n: np.ndarray            # (H, W) samples so far
    wbar2: list              # level 0..K: mean squared wavelets at S_k positions
    levels: int


def _sampler_inputs(buf: Buffers, params: Params) -> _SamplerInputs:
    bank = wv.get_bank(params.wavelet)
    prep = _prepare(buf.color.mean, variance_of_mean(buf), buf.n, bank)
    h, w = prep.n.shape
    levels = min(int(params.sample_levels), wv.max_levels((h, w)))
    s2 = np.minimum(prep.var * np.maximum(prep.n, 1.0)[..., None], _BIG_VAR)
    sigma_f = np.where(prep.missing, 1.0, mitchell_variance(prep.mean, s2, prep.n))
    lum = luminance(prep.mean)
    pos = lum[lum > 0]
    med = float(np.median(pos)) if pos.size else 0.0
    scale = float(params.sampler_intensity) / med if med > 0 and np.isfinite(med) else 1.0
    lum = np.clip(lum * scale, -_BIG_VALUE, _BIG_VALUE)
    pyr = wv.dwt2(lum, bank, levels)
    shapes = wv.level_shapes((h, w), levels)
    wbar2 = [np.zeros(shapes[0])]
    for k in range(1, levels + 1):
        acc = np.zeros(shapes[k])
        cnt = np.zeros(shapes[k])
        for band in pyr.details[k - 1]:
            if band.size:
                bh, bw = band.shape
                acc[:bh, :bw] += np.minimum(band * band, _BIG_VAR)
                cnt[:bh, :bw] += 1.0
        wbar2.append(acc / np.maximum(cnt, 1.0))
    return _SamplerInputs(sigma_f, prep.n, wbar2, levels)


def _pixel_variance(inp: _SamplerInputs, extra: np.ndarray | None) -> np.ndarray:
    """Eq. 6: ``sigma^2(B) = sigma^2(F) / N`` with the predicted count ``N``
    (samples so far plus those planned); a pixel without samples counts as half
    a sample of maximal contrast."""
    n = inp.n if extra is None else inp.n + extra
    return inp.sigma_f / np.maximum(n, 0.5)


def priorities(buf: Buffers, params: Params | None = None, planned: np.ndarray | None = None,
               _inputs: _SamplerInputs | None = None) -> list:
    """Priority ``P(S_k) = sigma^2(S_k) - (W~_k)^2`` of every scale coefficient
    (Eq. 8), levels ``k = 0..min(sample_levels, full depth)``.

    ``sigma^2(S_k)`` is Eq. 9 (squared low-pass DWT of the Eq. 5-6 per-pixel
    variance, renormalised to ``sample_filter_sum``); ``(W~_k)^2`` is the mean of
    the three squared level-k wavelets of the normalised luminance (0 for
    pixels).  ``planned`` (H, W) are samples already planned but not rendered;
    they lower the predicted variance.

    Returns list of (h_k, w_k) float64 arrays.
    """
    params = params or Params()
    inp = _inputs or _sampler_inputs(buf, params)
    v = _pixel_variance(inp, planned)
    s2 = wv.scale_variance(v, params.wavelet, inp.levels, lo_sum=float(params.sample_filter_sum))
    return [s - wb for s, wb in zip(s2, inp.wbar2)]


def _profile(bank, k_eff: int):
    """Importance density of a level-``k_eff`` scale coefficient along one axis:
    ``|phi_k|`` normalised to sum 1 (Fig. 5).  Returns (start offset, taps)."""
    if k_eff <= 0:
        return 0, np.ones(1)
    start, phi = wv.scale_function(bank, k_eff)
    p = np.abs(phi)
    return start, p / p.sum()


def _inside_mass(centres: np.ndarray, start: int, prof: np.ndarray, size: int) -> np.ndarray:
    """Profile mass of each coefficient that falls inside ``[0, size)``."""
    cum = np.concatenate([[0.0], np.cumsum(prof)])
    lo = np.clip(-(centres + start), 0, len(prof))
    hi = np.clip(size - (centres + start), 0, len(prof))
    return np.where(hi > lo, cum[hi] - cum[np.minimum(lo, hi)], 0.0)


@lru_cache(maxsize=32)
def _spread_matrix(name: str, k_eff: int, n_coef: int, size: int) -> np.ndarray:
    """Dense (n_coef, size) matrix: row i is coefficient i's density over the
    axis (profile clipped to the image and renormalised to sum 1)."""
    start, prof = _profile(name, k_eff)
    centres = (2 ** k_eff) * np.arange(n_coef)
    mass = _inside_mass(centres, start, prof, size)
    mat = np.zeros((n_coef, size))
    pos = centres[:, None] + start + np.arange(len(prof))[None, :]
    ok = (pos >= 0) & (pos < size)
    rows = np.broadcast_to(np.arange(n_coef)[:, None], pos.shape)
    vals = np.broadcast_to(prof[None, :], pos.shape) / np.where(mass > 0, mass, 1.0)[:, None]
    mat[rows[ok], pos[ok]] = vals[ok]
    return mat


_DENSE_LIMIT = 1 << 22


def _spread_axis(vals: np.ndarray, centres_idx: np.ndarray, k_eff: int, size: int,
                 bank: wv.FilterBank, n_coef: int) -> np.ndarray:
    """Spread ``vals`` (rows = coefficients ``centres_idx`` along this axis, any
    trailing columns) over ``size`` samples: (len(idx), m) -> (size, m)."""
    if k_eff <= 0:
        out = np.zeros((size,) + vals.shape[1:])
        out[centres_idx] = vals
        return out
    if n_coef * size <= _DENSE_LIMIT:
        mat = _spread_matrix(bank.name, k_eff, n_coef, size)[centres_idx]
        return mat.T @ vals
    start, prof = _profile(bank, k_eff)
    centres = (2 ** k_eff) * centres_idx
    mass = _inside_mass(centres, start, prof, size)
    v = vals / np.where(mass > 0, mass, 1.0).reshape((-1,) + (1,) * (vals.ndim - 1))
    out = np.zeros((size,) + vals.shape[1:])
    for t in range(len(prof)):
        pos = centres + start + t
        ok = (pos >= 0) & (pos < size)
        out[pos[ok]] += prof[t] * v[ok]
    return out


def spread_batches(grid: np.ndarray, level: int, shape, bank="cdf97") -> np.ndarray:
    """Expected per-pixel counts of level-``level`` coefficient batches.

    Each entry ``grid[i, j]`` (samples for ``S_{k,ij}``) is spread over the
    coefficient's support with the separable density ``|phi_k(y)| |phi_k(x)|``
    (Fig. 5), renormalised over the pixels inside the image, so the output sums
    to ``grid.sum()``.  Axes of length 1 are not spread (``k`` is capped per
    axis at the levels that axis was actually halved).

    grid : (h_k, w_k) non-negative; shape : (H, W) -> (H, W) float64
    """
    bank = wv.get_bank(bank)
    h, w = int(shape[0]), int(shape[1])
    grid = np.asarray(grid, np.float64)
    rows = np.nonzero(grid.any(axis=1))[0]
    if rows.size == 0:
        return np.zeros((h, w))
    ky = min(int(level), wv.axis_levels(h))
    kx = min(int(level), wv.axis_levels(w))
    cols = np.arange(grid.shape[1])
    # along x: (w_k, rows) -> (w, rows), then along y: (rows, w) -> (h, w)
    tmp = _spread_axis(grid[rows].T, cols, kx, w, bank, grid.shape[1])
    return _spread_axis(tmp.T, rows, ky, h, bank, grid.shape[0])


def plan_samples(buf: Buffers, budget: int, params: Params | None = None,
                 state: dict | None = None) -> tuple:
    """Steps 2-4 of Fig. 4 for one iteration: expected counts and the chosen
    coefficients.

    Returns
    -------
    expected : (H, W) float64 expected new samples per pixel, sums to ``budget``
    chosen : dict of int64/float64 arrays ``level``, ``i``, ``j``, ``samples``
        (one entry per popped coefficient, grouped by round then level; the
        coefficient ``S_{level, ij}`` is centred on pixel ``(2^level i,
        2^level j)``)

    Batches are ``batch_base * 2**level``; the last one of each round is cut to
    the round's share.  If the image has too few coefficients to absorb the
    budget (tiny images), the plan is scaled up to sum to ``budget``.
    """
    params = params or Params()
    state = {} if state is None else state
    rng = state.get("rng")
    if rng is None:  # the render loop may put its --seed in the state
        rng = state["rng"] = np.random.default_rng(int(state.get("seed", params.seed) or 0))
    bank = wv.get_bank(params.wavelet)
    h, w = buf.shape
    budget = int(max(budget, 0))
    planned = np.zeros((h, w))
    chosen = {"level": [], "i": [], "j": [], "samples": []}
    empty = {k: np.zeros(0, np.int64 if k != "samples" else np.float64) for k in chosen}
    if budget == 0 or h * w == 0:
        return planned, empty
    inp = _sampler_inputs(buf, params)
    shapes = wv.level_shapes((h, w), inp.levels)
    sizes = [a * b for a, b in shapes]
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    level_of = np.repeat(np.arange(inp.levels + 1), sizes)
    batch_of = float(params.batch_base) * np.exp2(level_of)
    rounds = max(1, min(int(params.rounds), budget))
    remaining = float(budget)
    for r in range(rounds):
        share = remaining / (rounds - r)
        if share <= 0:
            break
        pr = priorities(buf, params, planned, _inputs=inp)
        flat = np.concatenate([p.ravel() for p in pr])
        flat = np.where(np.isfinite(flat), flat, -np.inf)
        if r == 0 and (flat.max() == flat.min()):
            planned = allocate(np.ones((h, w)), budget).astype(np.float64)
            return planned, empty
        m = int(min(flat.size, np.ceil(share / float(params.batch_base)) + 1))
        cand = np.argpartition(-flat, m - 1)[:m] if m < flat.size else np.arange(flat.size)
        order = np.lexsort((rng.random(cand.size), -flat[cand]))
        cand = cand[order]
        b = batch_of[cand]
        before = np.concatenate([[0.0], np.cumsum(b)[:-1]])
        take = before < share
        cand, b, before = cand[take], b[take], before[take]
        b = np.minimum(b, share - before)
        grids = {}
        lv = level_of[cand]
        for k in np.unique(lv):
            sel = lv == k
            local = cand[sel] - offsets[k]
            g = np.zeros(shapes[k])
            np.add.at(g.ravel(), local, b[sel])
            grids[int(k)] = g
            ii, jj = np.divmod(local, shapes[k][1])
            chosen["level"].append(np.full(ii.size, k, np.int64))
            chosen["i"].append(ii.astype(np.int64))
            chosen["j"].append(jj.astype(np.int64))
            chosen["samples"].append(b[sel])
        for k, g in grids.items():
            planned += spread_batches(g, k, (h, w), bank)
        remaining -= float(b.sum())
    out = {k: (np.concatenate(v) if v else empty[k]) for k, v in chosen.items()}
    # Exact budget despite float round-off.
    tot = planned.sum()
    if tot > 0:
        planned *= budget / tot
    return planned, out


def _bayer(order: int = 3) -> np.ndarray:
    """Ordered-dither threshold matrix (2^order square) with values (i + 0.5) / n."""
    m = np.zeros((1, 1))
    for _ in range(order):
        m = np.block([[4 * m, 4 * m + 2], [4 * m + 3, 4 * m + 1]])
    return (m + 0.5) / m.size


def _round_counts(expected: np.ndarray, budget: int, offset=(0, 0)) -> np.ndarray:
    """Integer counts from expected counts: ordered dithering (each pixel gets
    ``floor`` or ``ceil`` of its expectation, the extra samples stratified over
    8 x 8 blocks; ``offset`` shifts the pattern between iterations), then
    corrected to sum to ``budget`` exactly."""
    e = np.maximum(np.where(np.isfinite(expected), expected, 0.0), 0.0)
    h, w = e.shape
    b = _bayer()
    oy, ox = int(offset[0]) % b.shape[0], int(offset[1]) % b.shape[1]
    thr = np.tile(np.roll(b, (oy, ox), axis=(0, 1)),
                  (h // b.shape[0] + 1, w // b.shape[1] + 1))[:h, :w]
    base = np.floor(e)
    counts = (base + ((e - base) > thr)).astype(np.int64)
    diff = int(budget - counts.sum())
    if diff != 0:
        resid = (e - counts).ravel()
        flat = counts.ravel()
        if diff > 0:
            idx = np.argpartition(-resid, diff - 1)[:diff] if diff < resid.size else np.arange(resid.size)
            flat[idx] += 1
            left = budget - int(flat.sum())
            if left > 0:
                flat += allocate(np.maximum(e.ravel(), 1e-12), left)
        else:
            need = -diff
            while need > 0:
                cand = np.nonzero(flat > 0)[0]
                take = cand[np.argsort(resid[cand], kind="stable")[:need]]
                flat[take] -= 1
                resid[take] += 1.0
                need -= take.size
        counts = flat.reshape(e.shape)
    return counts


def sample_map(buf: Buffers, result: MethodResult | None, budget: int,
               params: Params | None = None, state: dict | None = None) -> np.ndarray:
    """New samples per pixel for the next render iteration (Sec. 4.1, Fig. 4).

    Priorities (Eq. 8) choose scale coefficients, each gets a 64 x 2^k batch
    spread over its support by the scale-function profile (Fig. 5), priorities
    are updated ``rounds`` times, and the expected counts are dithered to
    integers (module docstring).  ``result`` is not used: the priorities come
    from the noisy pixel means (Eq. 7), as in the paper.  ``state`` keeps the
    tie-breaking generator (seeded from ``params.seed``), the iteration count
    (it shifts the dither pattern) and, for diagnostics, ``state["chosen"]``
    (the popped coefficients of the last call, see ``plan_samples``).

    Returns
    -------
    (H, W) int64 >= 0 summing exactly to ``budget``.
    """
    params = params or Params()
    state = {} if state is None else state
    budget = int(max(budget, 0))
    expected, chosen = plan_samples(buf, budget, params, state)
    state["chosen"] = chosen
    state["iteration"] = int(state.get("iteration", 0)) + 1
    if budget == 0:
        return np.zeros(buf.shape, np.int64)
    it = state["iteration"]
    return _round_counts(expected, budget, offset=(3 * it, 5 * it))

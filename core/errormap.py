"""The noise a reconstruction keeps: an error term its own estimate cannot see.

LP (Moon et al. 2015, Eq. 4-7) and RHF (Liu et al. 2018, Eq. 11-12) estimate
their error from their regression models, with the features taken as exact.
Features rendered with the same few samples as the colour (defocus, motion
blur, soft shadows) carry noise correlated with the colour's: a model fitted
on them follows part of the colour noise, its held-out residuals stay small,
and the estimate misses that part (it saw a tenth to a third of the true error
on the defocus and soft-shadow scenes, docs/notes/error-maps.md).

:func:`retained_noise` estimates it from what the reconstruction left behind.
For a linear smoother ``f = H y`` of ``y = t + n`` (independent noise of
variance ``v_j``), Stein's unbiased risk estimate is::

    E[(f - t)_i^2] = E[(f - y)_i^2] - v_i + 2 H_ii v_i                  (1)

with the self-weight ``H_ii`` unknown for a data-dependent smoother.  Model:
``H = rho I + (1 - rho) S`` with ``S`` a wide smoother (``S_ii ~ 0``, its
output variance ``~ 0``), i.e. the reconstruction keeps a fraction ``rho`` of
each pixel's own noise.  Then ``E[(f - y)^2] = (1 - rho)^2 v`` and the noise
part of (1) is ``rho^2 v``.  ``rho`` is estimated over a (2r+1)^2 window from
the pooled ``V = mean v`` and ``R = mean (f - y)^2``, clamped to [0, 1]::

    rho = 1 - sqrt(R / V),    N_i = rho^2 v_i                           (2)

(0 for a perfect denoiser, ``R = V``; ``v_i`` for the identity, ``R = 0``).
Where ``R > V`` the residual holds bias, which (2) leaves to the method's
own estimate.  Choices: the window radius 2 (the 5x5 of the calibrated
variance; 1-5 measured within 0.03 of each other in 8x8 correlation); the
pixel's own ``v_i``, not the window's ``V`` (``rho^2 V`` correlated as well but
lent a highlight's variance to the dim pixels around it: estimated relMSE up
to 12x the true on the glossy scene, against 4x); ``v`` the calibrated
variance of the mean (``Buffers.calibrated_variance``: stratification-corrected,
feature-pooled); the channel mean of (2).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from . import parallel
from .filters import box_sum
from .method import params_from_dict

__all__ = ["RADIUS", "retained_noise"]

#: window radius of the pooled variance and residual in (2)
RADIUS = 2

#: squared radiance and variances are clipped at this over the window's pixel
#: count before pooling, so the window sums stay finite in float64
_LIMIT = 1e300

_BAND_ROWS = 128
_THREAD_MIN_PIXELS = 1 << 16


def retained_noise(image, mean, var, radius: int = RADIUS, rows: int = _BAND_ROWS) -> np.ndarray:
    """Kept noise N (Eq. 2) of a reconstruction, (H, W) float64, >= 0, finite.

    image : (H, W, C) the reconstruction f; mean : (H, W, C) its input y (the
    pixel means); var : (H, W, C) the variance of the means (+inf / NaN:
    unknown).  Pixels where any of the three is non-finite (or var < 0) are
    left out of the window sums and get 0; a window with none left gives 0.  Computed
    in row bands with a ``radius`` halo (the same values as one whole-frame
    pass), on :mod:`core.parallel`'s pool for large frames.
    """
    f = np.asarray(image, np.float64)
    y = np.asarray(mean, np.float64)
    v = np.asarray(var, np.float64)
    if f.ndim == 2:
        f, y = f[..., None], y[..., None]
    if v.ndim == 2:
        v = v[..., None]
    v = np.broadcast_to(v, f.shape)
    if y.shape != f.shape:
        raise ValueError(f"image {f.shape} and mean {y.shape} differ in shape")
    h, w = f.shape[:2]
    r = max(int(radius), 0)
    lim = _LIMIT / (2 * r + 1) ** 2
    out = np.zeros((h, w))

    def band(span):
        y0, y1 = span
        a, b = max(0, y0 - r), min(h, y1 + r)
        fs, ys, vs = f[a:b], y[a:b], v[a:b]
        with np.errstate(over="ignore", invalid="ignore"):
            d = fs - ys
            d *= d
            ok = np.isfinite(d) & np.isfinite(vs) & (vs >= 0)
        R = box_sum(np.where(ok, np.minimum(d, lim), 0.0), r)
        V = box_sum(np.where(ok, np.minimum(vs, lim), 0.0), r)
        lo, hi = y0 - a, y1 - a
        R, V = R[lo:hi], V[lo:hi]
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = 1.0 - np.sqrt(R / V)                                  # Eq. 2 (the counts cancel)
        rho = np.where(V > 0, np.clip(rho, 0.0, 1.0), 0.0)
        rho *= rho
        rho *= np.where(ok[lo:hi], np.minimum(vs[lo:hi], lim), 0.0)  # rho^2 v_i
        out[y0:y1] = rho.mean(axis=-1)

    parallel.run_bands(band, h, max(int(rows), 1), _THREAD_MIN_PIXELS, w)
    return out


def without_kept_noise(reconstruct, params_cls, buf, params=None):
    """``reconstruct(buf, params)`` with ``kept_noise`` off: what a method
    whose error map adds :func:`retained_noise` hands its sampler between
    iterations (``map_result``; the image and the sampler's estimate are the
    same, without the calibrated variance the kept noise needs).
    ``params``: a ``params_cls`` instance, a dict or None."""
    p = params if isinstance(params, params_cls) else params_from_dict(params_cls, params)
    return reconstruct(buf, replace(p, kept_noise=False) if p.kept_noise else p)

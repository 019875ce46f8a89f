"""Error metrics, stated exactly as the README and every report use them:
relMSE = mean over pixels and RGB of (x - r)^2 / (r^2 + 0.01)."""
from __future__ import annotations

import numpy as np

#: the relMSE denominator's epsilon
REL_EPS = 0.01


def relmse(x: np.ndarray, ref: np.ndarray) -> float:
    """relMSE = mean over pixels and RGB channels of (x - r)^2 / (r^2 + 0.01).

    x, ref : (H, W, 3+) arrays (only RGB is used).  Non-finite values in ``x``
    count as an error of ``r^2 + 0.01`` times 1e6 (never silently ignored).
    """
    x = np.asarray(x, np.float64)[..., :3]
    r = np.asarray(ref, np.float64)[..., :3]
    _check(x, r)
    e = relative_squared_error(x, r)
    e = np.where(np.isfinite(e), e, 1e6)
    return float(e.mean())


def relative_squared_error(x: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Per channel ``(x - r)^2 / (r^2 + 0.01)``, the term relMSE averages
    (no checks: callers validate shapes and decide what non-finite means)."""
    return (x - r) ** 2 / (r * r + REL_EPS)


def per_pixel_relmse(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(H, W) relative squared error averaged over RGB (the quantity relMSE averages)."""
    x = np.asarray(x, np.float64)[..., :3]
    r = np.asarray(ref, np.float64)[..., :3]
    _check(x, r)
    return np.where(np.isfinite(e := relative_squared_error(x, r)), e, 1e6).mean(axis=-1)


def smape(x: np.ndarray, ref: np.ndarray) -> float:
    """SMAPE = mean of |x - r| / (|x| + |r| + 0.01) over pixels and RGB."""
    x = np.asarray(x, np.float64)[..., :3]
    r = np.asarray(ref, np.float64)[..., :3]
    _check(x, r)
    e = np.abs(x - r) / (np.abs(x) + np.abs(r) + 0.01)
    return float(np.where(np.isfinite(e), e, 1.0).mean())


def error_correlation(estimated: np.ndarray, x: np.ndarray, ref: np.ndarray) -> float:
    """Pearson correlation between an estimated per-pixel squared error (H, W)
    and the true squared error of ``x`` against ``ref`` (averaged over RGB).
    Returns 0.0 when either has no variation."""
    x = np.asarray(x, np.float64)[..., :3]
    r = np.asarray(ref, np.float64)[..., :3]
    _check(x, r)
    true = ((x - r) ** 2).mean(axis=-1).ravel()
    est = np.asarray(estimated, np.float64).ravel()
    ok = np.isfinite(true) & np.isfinite(est)
    if ok.sum() < 2:
        return 0.0
    a, b = true[ok] - true[ok].mean(), est[ok] - est[ok].mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else 0.0


def summary(image: np.ndarray, error: np.ndarray, reference: np.ndarray) -> dict:
    """The figures every run reports against a reference: ``relmse``, ``smape``
    and ``error_correlation`` (of the estimated squared error ``error``)."""
    return {"relmse": relmse(image, reference), "smape": smape(image, reference),
            "error_correlation": error_correlation(error, image, reference)}


def _check(x, r):
    if x.shape != r.shape:
        raise ValueError(f"image is {x.shape[:2]} but the reference is {r.shape[:2]}")


def relative_error_map(image: np.ndarray, error: np.ndarray) -> np.ndarray:
    """(H, W) ``mean_c error / (image_c^2 + 0.01)``: the per-pixel term of
    :func:`estimated_relmse` (the image stands in for the reference, the
    estimated squared error is shared by the RGB channels).  Non-finite terms
    are 0 (pixels without an estimate), negative ones 0."""
    img = np.asarray(image, np.float64)[..., :3]
    err = np.asarray(error, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        e = err[..., None] / (img * img + REL_EPS)
    e = np.where(np.isfinite(e), e, 0.0)
    return np.maximum(e, 0.0).mean(axis=-1) if e.size else np.zeros(img.shape[:2])


def estimated_relmse(image: np.ndarray, error: np.ndarray) -> float:
    """The relMSE a run's own error estimate predicts (no reference needed):
    mean over pixels and RGB of ``error / (image^2 + 0.01)``, i.e.
    :func:`relmse` with the image standing in for the reference and the
    estimated squared error (averaged over RGB) for every channel's.
    Non-finite terms count as 0 (pixels without an estimate); 0.0 for an
    empty image."""
    img = np.asarray(image, np.float64)[..., :3]
    err = np.asarray(error, np.float64)
    if img.size == 0:
        return 0.0
    with np.errstate(invalid="ignore", over="ignore"):
        e = err[..., None] / (img * img + REL_EPS)
    return float(np.where(np.isfinite(e), e, 0.0).mean())


#: robust_relmse: the bulk's spread is read between these quantiles of the
#: positive per-pixel terms (structures covering more than 1 - 0.95 of the
#: frame lie inside the bulk and are never capped) ...
ROBUST_QUANTILES = (0.5, 0.95)
#: ... and terms more than this many (log-normal) standard deviations above
#: the median count at that bound (4: a log-normal bulk is clipped beyond its
#: 99.997th percentile only; 3 clipped the highlights' real error too, see
#: docs/notes/target-error.md)
ROBUST_SIGMAS = 4.0
#: fewer positive terms than this: no statistics, the plain mean
ROBUST_MIN_PIXELS = 64
#: z-score distance of ROBUST_QUANTILES under a normal law (Phi^-1(0.95))
_Z_SPREAD = 1.6448536269514722


def robust_relmse(image: np.ndarray, error: np.ndarray, sigmas: float = ROBUST_SIGMAS) -> float:
    """A firefly-robust :func:`estimated_relmse`: the mean of the per-pixel
    terms ``e_p`` (:func:`relative_error_map`) winsorised in log space,

        m = median log e,  s = (q95(log e) - m) / 1.645,
        estimate = mean_p min(e_p, exp(m + sigmas s))     (quantiles of e_p > 0)

    Why: a pixel's error estimate is a statistic of samples, its own and
    (pooled estimates) its alike neighbours'.  A small, very bright spot (a
    highlight or caustic, heavy-tailed) lends its large absolute variance to
    dim neighbours whose realised error stays small; divided by their small
    values, those terms are 1e2-1e4 times the bulk's.  On the glossy sample
    scene 1 % of the pixels held 98 % of the plain mean, 15-80x the true
    relMSE (docs/notes/target-error.md).  The bulk of the terms is near
    log-normal (smooth error over a smooth image): terms beyond ``sigmas`` of
    its spreads count at that bound (a winsorised mean; the trimmed mass
    estimated by the bound).  Where no term lies beyond it (the normal sample
    scenes) the value is the plain mean exactly; it never exceeds the plain
    mean of a non-negative error map.  The spread is read at the 95th
    percentile, so an error concentrated on a structure over more than 5 %
    of the frame shapes the bulk and is kept; a larger error on less than
    that is under-counted (the price of the robustness).  Neither estimate
    sees a firefly realised in the image (the image, not the reference, is
    in the denominator).  Fewer than ``ROBUST_MIN_PIXELS`` positive terms:
    the plain mean.  Finite, >= 0."""
    e = relative_error_map(image, error)
    if e.size == 0:
        return 0.0
    pos = e[e > 0]
    if pos.size < ROBUST_MIN_PIXELS:
        return float(e.mean())
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        lo, hi = np.log(np.quantile(pos, ROBUST_QUANTILES))
        bound = np.exp(lo + float(sigmas) * max(hi - lo, 0.0) / _Z_SPREAD)
    if not np.isfinite(bound):
        return float(e.mean())
    return float(np.minimum(e, bound).mean())

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

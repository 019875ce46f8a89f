"""RHF: denoising Monte Carlo renderings with a robust high-order function
(Liu, Zheng, Yuan 2018, GRAPP; ``../shared/papers/rhf-liu2018-robust-high-order-function.txt``).

Pipeline (section / equation of the paper):

1. Collaborative feature prefiltering (Sec. 3.2, Eq. 3-7): every feature
   channel (normal xyz, albedo rgb, depth) is filtered by a joint NL-means
   (``NLM(f_m, 0.25, true)``: spatial sigma_s = 2, patch range sigma_r = 1 with
   the variance-cancelling distance of Rousselle et al. 2013, feature terms
   sigma_m = 0.8 / 0.25 / 0.6), then by a self-guided image filter
   ``GUID(f_m, f_m)`` with regularisation 0.001.
2. Colour guidance (Sec. 3.3, Eq. 8): ``M = mean_m GUID(y, f^_m)`` over the 7
   prefiltered feature channels.
3. Centre and window selection (Sec. 3.5, Eq. 14): Sobel gradient of the
   prefiltered features, patches of radius r_l, small windows (r_s) for
   patches with high-frequency pixels, large (r_l) otherwise, medium (r_m)
   models for pixels no window covers.
4. First-order regression (Sec. 3.1, Eq. 1-2) per centre with D = 9 features
   (pixel position 2, depth 1, normal 3, albedo 3), predicting every pixel of
   its window; regression weights ``w(i, j) = NLM(M, k, false)`` (Sec. 3.3).
5. Bandwidth selection (Sec. 3.4, Eq. 9-12): candidates k = {1, 1.5, 2, 3.5,
   4}; bias and variance through the hat matrix (Eq. 11), T = 2 iterations
   weighted by 1 - 1/(t+1)^2 (Eq. 12), block error (Eq. 9-10).
6. Overlapping models averaged with their weights (Eq. 13).

Choices where the paper is silent or ambiguous are documented in the
docstrings of the functions that make them (search "Choice"), the main ones in
``rhf_reconstruct``.  The per-pixel error estimate (Eq. 12 at the chosen k,
merged by Eq. 13) is returned as ``MethodResult.error`` and drives
``sample_map`` (LP Sec. 5.2 style).

Special inputs
--------------
* Non-finite colour (NaN / +-Inf) or pixels with no samples are *missing*:
  they are filled from their neighbours for the guides and the NL-means
  distances, excluded from every regression fit, and still predicted.
* Variance +inf (fewer than 2 subsets, k < 2): the per-sample variance
  s^2 = n Var(mean) is filled from the nearest pixels that have one; with no
  variance anywhere, a robust (median) form of Immerkaer's (1996) Laplacian
  noise estimate of the image is used (``noise_variance_estimate``).
* Zero variance (k >= 2 and M2 = 0): the pixel mean is exact, so such channels
  are returned unchanged (their error is 0); any smoothing could only add bias.
* A pixel that every model ignores (all regression weights ~0) keeps its input
  value rather than an extrapolated prediction, and weakly weighted pixels
  lean on it (``Params.input_weight``, ``rhf_reconstruct``).
* Magnitudes are clipped to 1e30 (features to 1e6) so squares stay finite; the
  output is always finite.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .buffers import Buffers
from .filters import (VALUE_LIMIT, VAR_LIMIT, box_sum, guided_filter, guided_filter_mean,
                      nlm_center_weights, nlm_filter, sobel_gradient, window_offsets)
from .method import MethodResult, allocate, param, relative_error

PASSES = ("normal", "albedo", "depth")

#: Feature values are clipped to +-this (normals, albedo and normalised depth
#: are O(1); larger values are corrupt input), their variances to its square.
FEATURE_LIMIT = 1e6

#: The 7 feature channels (D - 2 of the paper) in the order used everywhere.
FEATURE_ORDER = (("normal", 3), ("albedo", 3), ("depth", 1))


@dataclass
class Params:
    """RHF parameters; defaults are the paper's (Liu et al. 2018, Sec. 3-4)
    where it gives them, otherwise the documented choices."""

    bandwidths: str = param("1.0,1.5,2.0,3.5,4.0",
                           "candidate NL-means strengths k (Sec. 3.4, comma list); more candidates "
                           "= finer bias/variance choice, proportionally slower")
    iterations: int = param(2, "T, iterations of the bias/variance estimate (Eq. 12); 3 gives slightly "
                              "less noisy error estimates, each costs one more regression pass", 1, 5)
    radius_small: int = param(5, "r_s, window radius for patches with fine detail (Sec. 3.5); smaller "
                                "keeps detail, more models = slower", 1, 64)
    radius_medium: int = param(10, "r_m, window radius of models filling uncovered pixels (Sec. 3.5)",
                              1, 64)
    radius_large: int = param(15, "r_l, patch radius and window radius of smooth patches (Sec. 3.5); "
                                 "larger = fewer models (faster), more smoothing", 1, 64)
    edge_threshold: float = param(0.4, "tau: a pixel whose feature Sobel gradient (Eq. 14) exceeds it "
                                      "is high-frequency; lower = more small windows (slower, sharper)",
                                 0.0, 1e6)
    detail_min_pixels: int = param(1, "a patch with at least this many high-frequency pixels gets the "
                                     "small radius r_s (num > tau, Sec. 3.5)", 1, 1 << 20)
    patch_radius: int = param(3, "r, NL-means patch radius (Eq. 4); larger = more robust distances, "
                                "cost grows with (2r+1)^2", 0, 10)
    sigma_s: float = param(2.0, "spatial sigma of the feature NL-means (Eq. 3)", 0.0, 100.0)
    sigma_r: float = param(1.0, "patch-range sigma of the NL-means kernels (Eq. 3)", 1e-6, 100.0)
    sigma_normal: float = param(0.8, "sigma_m of the normal term of the joint feature kernel (Eq. 3)",
                               1e-6, 100.0)
    sigma_albedo: float = param(0.25, "sigma_m of the albedo term of the joint feature kernel (Eq. 3)",
                               1e-6, 100.0)
    sigma_depth: float = param(0.6, "sigma_m of the depth term (depth scaled to the scene's 99th "
                                   "percentile, Eq. 3)", 1e-6, 100.0)
    feature_k: float = param(0.25, "k of the feature NL-means (Eq. 7); larger = smoother features",
                            1e-3, 100.0)
    feature_radius: int = param(4, "search radius of the feature NL-means (2 sigma_s; the paper does "
                                  "not say); larger = smoother features, cost ~ (2r+1)^2", 0, 16)
    guided_radius: int = param(1, "window radius of the guided filters (Eq. 6-8; not given in the "
                                 "paper); larger = smoother guide colour M, more bias", 0, 32)
    guided_eps: float = param(0.001, "regularisation of the guided filter (Eq. 6, paper 0.001); larger "
                                    "= flatter a, more smoothing", 1e-12, 1e3)
    regression_sigma_s: float = param(0.0, "spatial sigma of the regression weights NLM(M,k,false); 0 "
                                          "= none (the window bounds the support)", 0.0, 100.0)
    regress_guide: bool = param(False, "fit the guide colour M (Eq. 8) instead of the input colour "
                                      "(Eq. 2); less variance, but M's blur at colour-only edges is "
                                      "bias the error estimate cannot see")
    bias_noise_correction: bool = param(False, "subtract the pilot's noise from the Eq. 11 bias "
                                              "estimate (not in the paper): flat noisy regions then "
                                              "choose large k", None, None)
    ridge: float = param(1e-3, "Tikhonov regularisation of the gradient terms relative to the total "
                              "weight (guards singular systems); larger = more stable, more bias",
                        1e-9, 1.0)
    nlm_eps: float = param(1e-10, "epsilon of the NL-means distance (Eq. 5)", 1e-300, 1.0)
    coverage_weight: float = param(0.01, "a pixel counts as covered when some model's regression "
                                        "weight for it at the smallest k reaches this; uncovered "
                                        "pixels get r_m models (Sec. 3.5). Higher = more models, "
                                        "slower, fewer extrapolated predictions", 0.0, 1.0)
    fill_rounds: int = param(4, "rounds of r_m models for uncovered pixels (Sec. 3.5); 0 = only the "
                               "geometric cover", 0, 16)
    input_weight: float = param(0.02, "weight of each pixel's own input colour in the Eq. 13 average "
                                     "(not in the paper): pixels that the models weight weakly (their "
                                     "predictions there are extrapolations) lean on their unbiased "
                                     "input; 0 = pure Eq. 13, higher = closer to the input", 0.0, 1.0)
    chunk_centers: int = param(32, "model centres processed together (at most CHUNK_PIXELS window "
                                  "pixels per chunk); larger = faster, more memory; results do "
                                  "not depend on it",
                              1, 4096)


def parse_bandwidths(text) -> np.ndarray:
    """Candidate k values from ``Params.bandwidths`` ("1.0,1.5,...") -> (K,)
    float64 > 0, sorted ascending without duplicates."""
    if isinstance(text, (int, float)):
        vals = [float(text)]
    elif isinstance(text, str):
        vals = [float(t) for t in text.replace(";", ",").split(",") if t.strip()]
    else:
        vals = [float(t) for t in text]
    ks = np.asarray(vals, np.float64)
    if ks.size == 0 or not np.all(np.isfinite(ks)) or np.any(ks <= 0):
        raise ValueError(f"rhf bandwidths must be positive numbers, got {text!r}")
    return np.unique(ks)


def iteration_weights(T: int) -> np.ndarray:
    """Eq. 12 of Liu et al. 2018: wei_t = 1 - 1/(t+1)^2 for t = 1..T -> (T,)."""
    t = np.arange(1, int(T) + 1, dtype=np.float64)
    return 1.0 - 1.0 / (t + 1.0) ** 2


# ------------------------------------------------------------------ input fixes
def _fill_missing(values: np.ndarray, missing: np.ndarray) -> np.ndarray:
    """Replace ``values[missing]`` ((H, W, C), mask (H, W)) by the mean of the
    known pixels in the smallest window (radius 1, 2, 4, ...) that has any;
    with no known pixel at all, by 0."""
    out = np.where(missing[..., None], 0.0, values)
    if not missing.any():
        return out
    known = (~missing).astype(np.float64)
    if not known.any():
        return out
    todo = missing.copy()
    r = 1
    while todo.any():
        s = box_sum(out * known[..., None], r)
        c = box_sum(known, r)
        fill = todo & (c > 0)
        out[fill] = s[fill] / c[fill][:, None]
        todo &= ~fill
        if r > max(missing.shape):
            break
        r *= 2
    return out


def noise_variance_estimate(img: np.ndarray) -> np.ndarray:
    """Per-channel noise variance of an image from its Laplacian residual
    (Immerkaer 1996): L = I * N with N = [[1,-2,1],[-2,4,-2],[1,-2,1]] has
    variance 36 sigma^2 for white noise.  Choice: the robust form
    sigma = median|L| / (0.6745 * 6) replaces Immerkaer's mean |L| so that
    edges (sparse, large |L|) do not inflate the estimate.  Images smaller
    than 3x3 use the variance of their pixels (conservative).  (H, W, C) -> (C,)."""
    img = np.asarray(img, np.float64)
    h, w = img.shape[:2]
    if h < 3 or w < 3:
        return img.reshape(-1, img.shape[2]).var(axis=0) if img.size else np.zeros(img.shape[2])
    i = img
    lap = (i[:-2, :-2] - 2 * i[:-2, 1:-1] + i[:-2, 2:] - 2 * i[1:-1, :-2] + 4 * i[1:-1, 1:-1]
           - 2 * i[1:-1, 2:] + i[2:, :-2] - 2 * i[2:, 1:-1] + i[2:, 2:])
    sigma = np.median(np.abs(lap).reshape(-1, img.shape[2]), axis=0) / (0.6745 * 6.0)
    return np.minimum(sigma * sigma, VAR_LIMIT)


def _fill_variance(var_mean: np.ndarray, n: np.ndarray, values: np.ndarray, bad: np.ndarray):
    """Variance of the pixel mean with every missing entry filled.

    Missing = non-finite (k < 2: +inf), negative, or at a missing pixel.  The
    per-sample variance s^2 = n Var(mean) is taken from the nearest window of
    pixels that have one (``_fill_missing``), then Var(mean) = s^2 / max(n, 1);
    with no variance anywhere, Immerkaer's estimate of ``values`` is used as
    Var(mean) directly.  Returns (filled (H, W, C), filled-mask (H, W)).
    """
    v = np.asarray(var_mean, np.float64)
    nn = np.maximum(np.asarray(n, np.float64), 1.0)
    ok = np.isfinite(v).all(-1) & (v >= 0).all(-1) & ~bad
    if ok.all():
        return np.minimum(v, VAR_LIMIT), ~ok
    if ok.any():
        s2 = np.where(ok[..., None], np.minimum(v, VAR_LIMIT) * nn[..., None], 0.0)
        s2 = _fill_missing(s2, ~ok)
        out = np.where(ok[..., None], v, s2 / nn[..., None])
    else:
        out = np.broadcast_to(noise_variance_estimate(values), v.shape).copy()
    return np.clip(out, 0.0, VAR_LIMIT), ~ok


def _normalise_depth(depth: np.ndarray, var: np.ndarray):
    """Choice: depth is divided by the 99th percentile of |depth| (1 if that is
    0), then clipped to [-4, 4].  Cycles depth is in scene units, so sigma_depth
    = 0.6, the Sobel threshold and the guided-filter eps (all absolute in the
    paper) would otherwise depend on the scene's scale; the percentile keeps
    far background values (1e10) from squashing the scene to 0."""
    a = np.abs(depth[np.isfinite(depth)])
    scale = float(np.percentile(a, 99)) if a.size else 1.0
    if not np.isfinite(scale) or scale <= 0:
        scale = 1.0
    return np.clip(depth / scale, -4.0, 4.0), var / (scale * scale)


# ------------------------------------------------------------------- prefiltering
def _guided_rows(p, guide, radius, eps, rows=256):
    """``guided_filter`` in row strips with a 2r halo (exact; bounds memory)."""
    h = p.shape[0]
    r = int(radius)
    if h <= rows + 4 * r:
        return guided_filter(p, guide, r, eps)
    out = np.empty(p.shape, np.float64)
    for y0 in range(0, h, rows):
        y1 = min(h, y0 + rows)
        a, b = max(0, y0 - 2 * r), min(h, y1 + 2 * r)
        out[y0:y1] = guided_filter(p[a:b], guide[a:b], r, eps)[y0 - a:y1 - a]
    return out


def prefilter_features(feats: np.ndarray, feat_var: np.ndarray, params: Params) -> np.ndarray:
    """Collaborative feature prefiltering, Eq. 7 of Liu et al. 2018.

    ``f_m = NLM(f_m, 0.25, true)`` (joint NL-means, Eq. 3-5, each channel with
    its own patch distance, the joint term over all 7 input channels with
    sigma_m = 0.8 normal / 0.25 albedo / 0.6 depth, sigma_s = 2, sigma_r = 1),
    then ``f^_m = GUID(f_m, f_m)`` (self-guided filter, eps = 0.001).

    feats, feat_var : (H, W, 7) normal xyz, albedo rgb, depth (normalised) and
        the variances of their means.
    Returns (H, W, 7) prefiltered features f^.

    Choice: the search window of the NL-means has radius ``feature_radius`` =
    4 = 2 sigma_s (the paper gives none; the spatial weight beyond it is below
    e^-2); the guided filter radius ``guided_radius`` = 1 (not given either:
    the filter's support is 2r + 2r + 1 = 5 pixels, and on our synthetic scenes
    r = 1 gave lower error than r = 2 because it blurs colour-only edges of M
    less).  The NL-means runs in float32 (features are O(1)).
    """
    sig = np.array([params.sigma_normal] * 3 + [params.sigma_albedo] * 3 + [params.sigma_depth])
    f = nlm_filter(feats, feat_var, params.feature_k, params.feature_radius, params.patch_radius,
                   sigma_r=params.sigma_r, sigma_s=params.sigma_s, guides=feats,
                   guide_sigmas=sig[:feats.shape[2]], channelwise=True, eps=params.nlm_eps,
                   dtype=np.float32)
    for m in range(f.shape[2]):                 # channel by channel, in place
        f[..., m] = _guided_rows(f[..., m], f[..., m], params.guided_radius, params.guided_eps)
    return f


def prefilter_color(color: np.ndarray, fhat: np.ndarray, params: Params) -> np.ndarray:
    """Colour guide M of Eq. 8: ``M = (1/(D-2)) sum_m GUID(y, f^_m)`` -- the
    noisy colour y guided-filtered with each prefiltered feature channel as
    the guide, averaged over the D - 2 = 7 channels.  (H, W, 3) -> (H, W, 3)."""
    return guided_filter_mean(color, fhat, params.guided_radius, params.guided_eps)


def _box2_band(n: int, r: int) -> np.ndarray:
    """Band of the 1-D operator ``box_mean(box_mean(., r), r)`` (clipped
    windows): (4r+1, n) array, row d + 2r holding W[i, i + d] (0 outside)."""
    i = np.arange(n)
    inv = 1.0 / (np.minimum(n - 1, i + r) - np.maximum(0, i - r) + 1)
    band = np.zeros((4 * r + 1, n))
    for d in range(-2 * r, 2 * r + 1):
        j = i + d
        okj = (j >= 0) & (j < n)
        acc = np.zeros(n)
        for o in range(-r, r + 1):             # window centres k = i + o
            k = i + o
            ok = okj & (k >= 0) & (k < n) & (np.abs(k - j) <= r)
            acc[ok] += inv[k[ok]]
        band[d + 2 * r] = np.where(okj, acc * inv, 0.0)
    return band


def guide_variance(var: np.ndarray, radius: int) -> np.ndarray:
    """Variance of the guide colour M (Eq. 8) from the variance of the input
    means, ``sum_j W_ij^2 Var(y_j)`` with W the guided filter's weights where
    the guide is flat (a = 0): W = box_mean o box_mean, separable, so the
    squared weights are applied per axis.  (H, W, C) -> (H, W, C).

    Choice: the paper runs the Eq. 5 distance on M without saying which
    variance; the input's variance would make M's smoothed values look
    noise-free, and a firefly spread by the guided filter would look like
    structure (Var(M) spreads with it, so Eq. 5 cancels it).  Guides with
    edges smooth less, so this underestimates Var(M) there, which only makes
    the weights more selective across those edges.
    """
    v = np.asarray(var, np.float64)
    r = int(radius)
    if r <= 0:
        return v.copy()
    out = v
    for axis in (0, 1):
        n = out.shape[axis]
        band = _box2_band(n, r) ** 2
        res = np.zeros_like(out)
        for d in range(-2 * r, 2 * r + 1):
            lo, hi = max(0, -d), min(n, n - d)
            if lo >= hi:
                continue
            c = band[d + 2 * r, lo:hi]
            if axis == 0:
                res[lo:hi] += c[:, None, None] * out[lo + d:hi + d]
            else:
                res[:, lo:hi] += c[None, :, None] * out[:, lo + d:hi + d]
        out = res
    return np.minimum(out, VAR_LIMIT)


def feature_gradient(fhat: np.ndarray) -> np.ndarray:
    """Eq. 14: gra = max_m sqrt((G_x * f^_m)^2 + (G_y * f^_m)^2), the maximum
    over feature channels of their Sobel gradient magnitude.  (H, W, C) -> (H, W)."""
    return sobel_gradient(fhat, reduce_max=True)


# ------------------------------------------------------------------ centre choice
def select_centers(gra: np.ndarray, params: Params):
    """Model centres and window radii (Sec. 3.5 of Liu et al. 2018).

    The image is divided into patches of radius r_l (side 2 r_l + 1, from the
    top-left corner).  num = number of pixels with gra > tau in the patch;
    if num >= ``detail_min_pixels`` (num > tau with num a count and tau = 0.4
    means at least one pixel) the patch gets a window of radius r_s at its
    centre, otherwise one of radius r_l.  Every pixel that no window covers
    then gets a model of radius r_m.

    Choice: tau = 0.4 thresholds the gradient gra of each pixel ("pixels
    recognized by gra"), since a count num compared with 0.4 only says
    "num >= 1".  Patches whose centre lies outside the image (partial patches
    at the right / bottom border) get no patch window.  The paper builds r_m
    models by a sequential pixel scan; vectorised, we cut the image into cells
    of side 2 r_m + 1 and centre one r_m model on the middle of the bounding
    box of each cell's uncovered pixels, which covers all of them in one pass.
    Sec. 4's "patch size r = 3" is the Eq. 4 NL-means patch radius (Eq. 4
    names it r); the detail patches here have radius r_l as Sec. 3.5 says.
    The three radii are used sorted (r_s <= r_m <= r_l).

    Returns
    -------
    cy, cx, cr : (N,) int64 centre rows, columns and radii, every pixel of the
        image lies in at least one window |q - c|_inf <= r.
    detailed : (ny, nx) bool per patch.
    """
    rs, rm, rl = sorted((int(params.radius_small), int(params.radius_medium),
                         int(params.radius_large)))
    h, w = gra.shape
    side = 2 * rl + 1
    ny, nx = -(-h // side), -(-w // side)
    edge = np.zeros((ny * side, nx * side), bool)
    edge[:h, :w] = gra > params.edge_threshold
    num = edge.reshape(ny, side, nx, side).sum(axis=(1, 3))
    detailed = num >= max(int(params.detail_min_pixels), 1)
    ty, tx = np.meshgrid(np.arange(ny) * side + rl, np.arange(nx) * side + rl, indexing="ij")
    keep = (ty < h) & (tx < w)
    cy = [ty[keep]]
    cx = [tx[keep]]
    cr = [np.where(detailed[keep], rs, rl)]
    covered = np.zeros((h, w), bool)
    for r in (rs, rl):
        ind = np.zeros((h, w))
        sel = cr[0] == r
        ind[cy[0][sel], cx[0][sel]] = 1.0
        covered |= box_sum(ind, r) > 0.5
    if not covered.all():
        side_m = 2 * rm + 1
        my, mx = -(-h // side_m), -(-w // side_m)
        unc = np.zeros((my * side_m, mx * side_m), bool)
        unc[:h, :w] = ~covered
        cells = unc.reshape(my, side_m, mx, side_m)
        rows_any = cells.any(axis=3)                  # (my, side_m, mx)
        cols_any = cells.any(axis=1)                  # (my, mx, side_m)
        has = rows_any.any(axis=1)                    # (my, mx)
        ar = np.arange(side_m)
        big = side_m + 1
        ymin = np.where(rows_any, ar[None, :, None], big).min(axis=1)
        ymax = np.where(rows_any, ar[None, :, None], -1).max(axis=1)
        xmin = np.where(cols_any, ar[None, None, :], big).min(axis=2)
        xmax = np.where(cols_any, ar[None, None, :], -1).max(axis=2)
        gy = np.arange(my)[:, None] * side_m + (ymin + ymax) // 2
        gx = np.arange(mx)[None, :] * side_m + (xmin + xmax) // 2
        cy.append(gy[has])
        cx.append(gx[has])
        cr.append(np.full(int(has.sum()), rm))
    cy = np.concatenate(cy).astype(np.int64)
    cx = np.concatenate(cx).astype(np.int64)
    cr = np.concatenate(cr).astype(np.int64)
    return cy, cx, cr, detailed


# ---------------------------------------------------------------- hat matrix core
def regularizer(weight_sum: np.ndarray, P: int, ridge: float) -> np.ndarray:
    """Diagonal Tikhonov term added to X^T W X: ``diag(1e-6 ridge, ridge, ...,
    ridge) * sum_j w_j`` -> (..., P, P).  Relative to the total weight, so it
    does not depend on how W is scaled; the intercept gets a tiny term only so
    the system is always positive definite.  Choice: the paper does not
    regularise Eq. 2; without it constant features (a flat wall) make X^T W X
    singular.  A feature with no variation in the window gets gradient 0."""
    d = np.full(P, float(ridge))
    d[0] = 1e-6 * float(ridge)
    return weight_sum[..., None, None] * np.eye(P) * d


def hat_bias_variance(X, w, Y, y_prev, var_prev, ridge: float = 1e-3, pilot_var=None,
                      cache: dict | None = None, lean: bool = False):
    """Weighted first-order regression and its hat-matrix bias / variance,
    batched over B windows and K weightings (candidate bandwidths).

    With H = X (X^T W X + Lambda)^-1 X^T W (Eq. 2 of Liu et al. 2018;
    Lambda = ``regularizer``):

    * prediction      y^ = H Y                               (Eq. 2)
    * bias_t(j)       = sum_s H_js y_{s,t-1} - y_{j,t-1}      (Eq. 11)
    * Var_t(j)        = sum_s H_js^2 Var_{t-1}(s)             (Eq. 11)

    computed without forming the n x n matrix H: Var(j) = x_j^T A^-1 B A^-1 x_j
    with A = X^T W X + Lambda and B = X^T W diag(Var) W X.  The products run
    one weighting k at a time, so the temporaries are (B, n, P), not
    (B, n, K P) (bounds the peak memory of ``rhf_reconstruct``).

    Parameters
    ----------
    X : (B, n, P) design rows [1, x_j - x_i] (scaled).
    w : (B, K, n) weights w(i, j) >= 0.  A window whose weights are all zero
        falls back to uniform weights.  H does not change when w is scaled.
    Y : (B, n, C) regression target (input colours).
    y_prev : (B, n, C) y_{t-1} for the bias.
    var_prev : (B, n) or (B, K, n) Var_{t-1} (channel mean; the formula is
        linear, so the channel mean of Var_t equals it for the channel-mean input).
    ridge : float, see ``regularizer``.
    pilot_var : optional (B, n) or (B, K, n) variance u of y_prev (channel
        mean).  If given, a fourth output is returned: the part of E[bias^2]
        that is pilot noise, ``sum_s (H_js - delta_js)^2 u_s``
        = sum_s H_js^2 u_s - 2 H_jj u_j + u_j.
    cache : optional dict kept by the caller between calls with the same X
        and w: (X^T W X + Lambda)^-1 is stored there (key "Ainv", (B, K, P, P))
        and reused.
    lean : if True, return ``beta`` (B, K, P, C), the coefficients of the fit
        of Y (pred = X @ beta[:, k]), instead of pred, and the channel mean of
        bias^2 (B, K, n) instead of bias (what ``rhf_reconstruct`` needs).

    Returns
    -------
    pred (B, K, n, C), bias (B, K, n, C), var (B, K, n) [, noise (B, K, n)],
    all finite; with ``lean``: beta, bias^2 (B, K, n), var [, noise].
    """
    X = np.asarray(X, np.float64)
    w = np.asarray(w, np.float64)
    Bn, n, P = X.shape
    K = w.shape[1]
    C = Y.shape[-1]
    wmax = w.max(axis=-1, keepdims=True)
    w = np.where(wmax > 0, w / np.where(wmax > 0, wmax, 1.0), 1.0)
    Z = np.concatenate([Y, y_prev], axis=-1)                      # (B, n, 2C)
    v = np.asarray(var_prev, np.float64)
    u = None
    if pilot_var is not None:
        u = np.asarray(pilot_var, np.float64)
        u = np.broadcast_to(u[:, None, :] if u.ndim == 2 else u, w.shape)
        u_is_v = np.array_equal(u, np.broadcast_to(v[:, None, :] if v.ndim == 2 else v,
                                                   w.shape))
    Ainv = None if cache is None else cache.get("Ainv")
    need_a = Ainv is None or Ainv.shape != (Bn, K, P, P)
    rhs = np.empty((Bn, K, P, 2 * C))
    Bm = np.empty((Bn, K, P, P))
    Bu = np.empty((Bn, K, P, P)) if u is not None and not u_is_v else None
    A = np.empty((Bn, K, P, P)) if need_a else None
    for k in range(K):                                            # X^T W Z, A, B per k
        wk = w[:, k, :, None]                                     # (B, n, 1)
        Xw = wk * X                                               # (B, n, P)
        XwT = Xw.transpose(0, 2, 1)
        rhs[:, k] = XwT @ Z
        if need_a:
            A[:, k] = XwT @ X
        vk = v if v.ndim == 2 else v[:, k]
        Bm[:, k] = (Xw * (wk * vk[..., None])).transpose(0, 2, 1) @ X
        if Bu is not None:
            Bu[:, k] = (Xw * (wk * u[:, k, :, None])).transpose(0, 2, 1) @ X
        del Xw, XwT
    if need_a:
        A += regularizer(w.sum(-1), P, ridge)
        try:
            Ainv = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            Ainv = np.linalg.pinv(A)
        if not np.all(np.isfinite(Ainv)):
            Ainv = np.where(np.isfinite(Ainv), Ainv, 0.0)
        if cache is not None:
            cache["Ainv"] = Ainv
        del A
    beta = Ainv @ rhs                                             # (B, K, P, 2C)
    Cm = Ainv @ Bm @ Ainv                                         # (B, K, P, P)
    del Bm
    Cu = None if Bu is None else Ainv @ Bu @ Ainv
    var = np.empty((Bn, K, n))
    bias = np.empty((Bn, K, n) if lean else (Bn, K, n, C))
    pred = None if lean else np.empty((Bn, K, n, C))
    hjj = hu = None
    if u is not None:
        hjj = np.empty((Bn, K, n))
        hu = var if Cu is None else np.empty((Bn, K, n))
    for k in range(K):                                            # per-pixel terms per k
        pz = X @ beta[:, k]                                       # (B, n, 2C)
        b = np.subtract(pz[..., C:], y_prev, out=pz[..., C:])
        if lean:
            bias[:, k] = _channel_mean_sq(b)
        else:
            pred[:, k] = pz[..., :C]
            bias[:, k] = b
        var[:, k] = np.einsum("bnp,bnp->bn", X @ Cm[:, k], X)
        if u is not None:
            hjj[:, k] = w[:, k] * np.einsum("bnp,bnp->bn", X @ Ainv[:, k], X)
            if Cu is not None:
                hu[:, k] = np.einsum("bnp,bnp->bn", X @ Cu[:, k], X)
        del pz, b
    np.maximum(var, 0.0, out=var)
    first = beta[..., :C] if lean else pred
    if u is None:
        return first, bias, var
    if Cu is not None:
        np.maximum(hu, 0.0, out=hu)
    noise = np.maximum(hu - 2.0 * hjj * u + u, 0.0)
    return first, bias, var, noise


def choose_bandwidth(errors: np.ndarray) -> np.ndarray:
    """Index of k_opt = argmin_k of the block errors (Eq. 10), (N, K) -> (N,).

    Candidates are sorted ascending.  Ties (within 1e-9 relative, e.g. a flat
    region where every k gives weights ~1 and so the same fit) go to the
    largest k: the fits are identical, and the larger k is the one that keeps
    smoothing as the image gets flatter."""
    e = np.asarray(errors, np.float64)
    best = e.min(axis=1, keepdims=True)
    near = e <= best + 1e-9 * np.abs(best) + 1e-300
    return e.shape[1] - 1 - np.argmax(near[:, ::-1], axis=1)


def block_error(w: np.ndarray, err: np.ndarray) -> np.ndarray:
    """Block-wise reconstruction error of Eq. 9-10 (Liu et al. 2018):
    ``sum_j w(i,j) err_j / sum_j w(i,j)`` over the window, last axis.

    Choice: Eq. 10 writes the unnormalised sum.  Its variance part is then
    ~ sum_j w_j (D+1) sigma^2 / sum_j w_j, the same for every k, while its bias
    part grows with the weights, so the unnormalised sum always picks the
    smallest k.  The weighted mean is the block's mean squared error, which
    trades bias against variance as Sec. 3.4 intends.  All-zero weights give 0.
    """
    w = np.asarray(w, np.float64)
    sw = w.sum(-1)
    return (w * err).sum(-1) / np.where(sw > 0, sw, 1.0)


# -------------------------------------------------------------------- regression
@dataclass
class RHFOutput:
    """Everything ``rhf_reconstruct`` computes (for tests and diagnostics).

    image (H, W, 3); error (H, W) estimated squared error (RGB mean);
    features (H, W, 7) prefiltered f^; guide (H, W, 3) colour guide M;
    gradient (H, W) Eq. 14; cy, cx, cr (N,) model centres and radii;
    k_opt (N,) chosen bandwidth per model; block_error (N, K) Eq. 10 per
    candidate (Eq. 12-combined); detailed (ny, nx) patch flags; info dict.
    """

    image: np.ndarray
    error: np.ndarray
    features: np.ndarray
    guide: np.ndarray
    gradient: np.ndarray
    cy: np.ndarray
    cx: np.ndarray
    cr: np.ndarray
    k_opt: np.ndarray
    block_error: np.ndarray
    detailed: np.ndarray
    info: dict


def _design_rows(feat, idx, inside, cidx, width):
    """Design rows of Eq. 2, [1, (x_j - x_i) / s], for the windows of a chunk
    of centres: x = (column, row, 7 prefiltered feature channels), D = 9
    (pixel position 2, normal 3, albedo 3, depth 1 -- the paper's set).

    feat : (H, W, 7) prefiltered features (any float dtype); idx, inside :
    (c, n) window pixel indices and mask; cidx : (c,) centre indices.
    Returns (c, n, 10) float64.

    Choice: each feature column is divided by its largest |x_j - x_i| in the
    window (columns with no variation become 0).  Least squares is invariant to
    this; it only makes the relative ridge act alike on every feature.
    """
    F = feat.reshape(-1, feat.shape[2])
    c, n = idx.shape
    diff = np.empty((c, n, 2 + F.shape[1]))
    qy, qx = np.divmod(idx, width)
    cy, cx = np.divmod(cidx, width)
    diff[..., 0] = qx - cx[:, None]
    diff[..., 1] = qy - cy[:, None]
    diff[..., 2:] = F[idx]
    diff[..., 2:] -= F[cidx][:, None, :]
    diff[~inside] = 0.0
    s = np.abs(diff).max(axis=1, keepdims=True)
    diff = np.where(s > 1e-12, diff / np.where(s > 1e-12, s, 1.0), 0.0)
    return np.concatenate([np.ones((c, n, 1)), diff], axis=2)


#: Most window pixels (centres x (2r+1)^2) regressed together: the per-chunk
#: temporaries of ``rhf_reconstruct`` (design rows, weights, the per-k
#: products of ``hat_bias_variance``) take ~0.5 kB per window pixel, so this
#: bounds them to ~4 MB whatever the window radius.
CHUNK_PIXELS = 1 << 13

#: Regression weights of every model are kept over the T iterations as
#: 16-bit fixed point in [0, 1] (``round(w * WEIGHT_SCALE)``): half the memory
#: of float32 (they were ~107 of ~365 bytes per pixel on a textured scene),
#: absolute error <= 7.6e-6 per weight, output changes ~1e-6 relative.
WEIGHT_SCALE = 65535.0

#: Smallest weight of the input colour y in Eq. 13 (failure guard, used even
#: with ``Params.input_weight = 0``): a pixel that every model ignores keeps
#: its input value instead of 0 / 0.
FALLBACK_WEIGHT = 1e-12


def _window_index(cy, cx, r, h, w):
    """Flat pixel indices (c, (2r+1)^2) of the windows of centres (clipped) and
    the mask of window pixels inside the image."""
    oy, ox = window_offsets(r)
    qy = cy[:, None] + oy[None, :]
    qx = cx[:, None] + ox[None, :]
    inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
    return np.clip(qy, 0, h - 1) * w + np.clip(qx, 0, w - 1), inside


def _fill_centers(uncovered: np.ndarray, rm: int):
    """One r_m model per cell of side 2 r_m + 1 that holds uncovered pixels,
    centred on the uncovered pixel nearest the centroid of the cell's
    uncovered pixels (a vectorised form of the paper's pixel scan).
    uncovered (H, W) bool -> (cy, cx) int64 arrays."""
    h, w = uncovered.shape
    s = 2 * rm + 1
    my, mx = -(-h // s), -(-w // s)
    u = np.zeros((my * s, mx * s), bool)
    u[:h, :w] = uncovered
    cells = u.reshape(my, s, mx, s).transpose(0, 2, 1, 3).reshape(my, mx, s * s)
    cnt = cells.sum(-1)
    ly, lx = np.divmod(np.arange(s * s), s)
    with np.errstate(invalid="ignore", divide="ignore"):
        my_c = (cells * ly).sum(-1) / np.maximum(cnt, 1)
        mx_c = (cells * lx).sum(-1) / np.maximum(cnt, 1)
    dist = (ly[None, None] - my_c[..., None]) ** 2 + (lx[None, None] - mx_c[..., None]) ** 2
    dist = np.where(cells, dist, np.inf)
    best = dist.argmin(-1)
    has = cnt > 0
    gy = np.arange(my)[:, None] * s + ly[best]
    gx = np.arange(mx)[None, :] * s + lx[best]
    return gy[has].astype(np.int64), gx[has].astype(np.int64)


def _channel_mean_sq(x: np.ndarray) -> np.ndarray:
    """mean over the last axis of x^2 (few channels: explicit sum, faster)."""
    acc = x[..., 0] * x[..., 0]
    for ch in range(1, x.shape[-1]):
        acc += x[..., ch] * x[..., ch]
    return acc / x.shape[-1]


def _bincount_add(acc, flat, vals, lo, hi):
    """acc[flat] += vals (duplicates summed), within the index range [lo, hi)."""
    acc[lo:hi] += np.bincount(flat - lo, weights=vals, minlength=hi - lo)


def rhf_reconstruct(color, color_var, feats, feat_var, n=None, params: Params | None = None,
                    zero_var=None) -> RHFOutput:
    """Full RHF reconstruction (Liu et al. 2018, Eq. 1-14) from arrays.

    Parameters
    ----------
    color : (H, W, 3) pixel means y (may hold NaN/Inf: treated as missing).
    color_var : (H, W, 3) variance of the means (+inf where unknown), or a
        zero-argument callable returning it (called once; the array is then
        released as soon as the variance is prepared, which bounds peak memory).
    feats : dict 'normal' (H, W, 3), 'albedo' (H, W, 3), 'depth' (H, W[, 1]);
        a missing pass is a constant 0 feature.
    feat_var : dict of their variances (missing entries: 0, noise-free); a
        value may be a zero-argument callable returning the array, evaluated
        when that feature is prepared (bounds peak memory).
    n : (H, W) samples per pixel (default 1; pixels with n <= 0 are missing).
    params : Params (paper defaults).
    zero_var : optional (H, W, 3) bool, channels known to be noise-free
        (default: ``color_var == 0``); they are returned unchanged.

    Returns
    -------
    RHFOutput.

    Choices (where the paper is silent or ambiguous)
    ------------------------------------------------
    * Regression target: Eq. 2 fits the *input* colours Y ("Y = [y_1..y_n]
      are the input colors"); the guide colour M (Eq. 8) gives the regression
      weights ``NLM(M, k, false)`` and the first pilot y_0 of Eq. 11, as Sec.
      3.3-3.4 state.  (``regress_guide`` fits M instead: on our synthetic
      scenes that is several times worse, because M's blur at colour-only
      edges is bias that Eq. 11 cannot see.)
    * The Eq. 5 distance on M uses the variance of M (``guide_variance``);
      Var_0 of Eq. 11 is the variance of the input mean, as the paper says.
    * Regression weights have no spatial term (``regression_sigma_s`` = 0):
      with sigma_s = 2 a radius-15 window would be fitted from ~5 pixels and
      extrapolated to the rest.
    * Eq. 9-10 use the weighted *mean* error of the block (``block_error``);
      ties between candidates go to the larger k (``choose_bandwidth``).
    * Iterations (Eq. 11-12): y_{t-1} is the full image reconstructed in
      iteration t-1 (Eq. 13 over all models, each with the k minimising the
      Eq. 12 error accumulated so far) and Var_{t-1}(s, k) the per-k variance
      maps of iteration t-1 merged with the same Eq. 13 weights.  (Using each
      window's own H y would make bias_2 = H H y - H y = 0.)  The regression
      itself always fits Y; only the error estimate and k_opt are iterated.
      Eq. 11 is used as written; ``bias_noise_correction`` (off by default)
      subtracts the pilot's noise, sum_s (H_js - delta_js)^2 Var(y_s), from
      the block's bias^2, which the raw estimate counts as bias.
    * Coverage (Sec. 3.5, "not covered by any existing window"): a window pixel
      whose weight is ~0 in its model is extrapolated, not fitted.  A pixel
      therefore counts as covered when some model weights it >=
      ``coverage_weight`` at the smallest k (weights grow with k, so it keeps
      that weight at the chosen k); uncovered pixels get r_m models for
      ``fill_rounds`` rounds (``_fill_centers``).  Pixels still ignored by every
      model keep their input value in Eq. 13.
    * Input weight (``input_weight``, 0.02; not in the paper): Eq. 13 also
      averages in the pixel's own input colour with that weight.  The models
      are sparse (one per 31 x 31 patch plus r_m fill models), so most pixels
      are predicted far from a model centre, and a pixel whose features or
      guide colour differ from the model's data gets a small weight *and* an
      extrapolated prediction; when every covering model weights it weakly
      the normalised average still trusts those extrapolations fully (the
      paper's method as written, ``input_weight = 0``, came out worse than its
      input on our synthetic test scene: MSE 1.25x).  On the
      soft_shadows scene (16 spp, uniform) that put 0.42 on contact-shadow
      pixels whose reference is 0.04 (the input mean said 0.09), and choosing
      k per model made it worse than either fixed k (relMSE 1.7e-2 for
      k in {1, 4} against 7.1e-3 / 7.5e-3 for k = 1 / k = 4 alone).  With
      the input at weight 0.02, pixels any model weights >= 0.2 move < 10 %
      toward their input.  Measured on the six sample scenes at 16 spp
      (uniform samples, after the loop's consistency guard; weights 0.001 /
      0.003 / 0.01 / 0.02 / 0.03 / 0.1): from 0.01 up every scene is below
      the input's relMSE (0.02: cornell 5.8e-3 vs 3.5e-2, soft_shadows 6.4e-3
      vs 7.3e-3, animated 8.3e-3 vs 1.0e-2) where 0.001 lost on soft_shadows
      (1.07e-2) and animated (1.25e-2); above 0.03 cornell and the synthetic
      tests lose smoothing (MSE ratio to the input 0.12 / 0.17 / 0.21 / 0.26
      for 0.001 / 0.01 / 0.02 / 0.03).
    * Design features are pixel position, depth, normal, albedo (D = 9),
      prefiltered; each column is scaled by its largest |x_j - x_i| in the
      window and the gradient terms get a small relative ridge
      (``regularizer``) so constant features and singular systems are safe.
    * The error map (``RHFOutput.error``) is the Eq. 12 error (bias^2 +
      variance, RGB mean) at each model's chosen k, averaged with the Eq. 13
      weights; 0 for zero-variance pixels.
    * Memory: per model only the float32 weights (K, n) and (X^T W X +
      Lambda)^-1 (K, P, P) are kept over the T iterations; the Eq. 12 terms
      of the earlier iterations are recomputed in the last one for k_opt only
      (from the kept pilots), and models are regressed in chunks of at most
      ``CHUNK_PIXELS`` window pixels.  Peak traced memory (inputs excluded)
      measured on synthetic 512x512 scenes: ~280-370 B/px (~380-430 B/px at
      256x256, where the fixed-size chunk temporaries weigh more).
    """
    params = params or Params()
    t0 = time.perf_counter()
    ks = parse_bandwidths(params.bandwidths)
    K = ks.size
    T = max(1, int(params.iterations))
    y_in = np.asarray(color, np.float64)
    if y_in.ndim == 2:
        y_in = y_in[..., None]
    h, w = y_in.shape[:2]
    if y_in.shape[2] != 3:
        y_in = np.broadcast_to(y_in[..., :1], (h, w, 3))
    if callable(color_var):
        color_var = color_var()
    cvar = np.broadcast_to(np.asarray(color_var, np.float64).reshape(h, w, -1), (h, w, 3))
    nn = np.ones((h, w)) if n is None else np.asarray(n, np.float64).reshape(h, w)
    nn = np.where(np.isfinite(nn), nn, 0.0)

    # ---- missing colour and variance
    bad = ~np.isfinite(y_in).all(-1) | (nn <= 0)
    y = np.clip(np.where(np.isfinite(y_in), y_in, 0.0), -VALUE_LIMIT, VALUE_LIMIT)
    y = _fill_missing(y, bad)
    if zero_var is None:
        zero_var = np.isfinite(cvar) & (cvar == 0) & ~bad[..., None]
    vy, vy_filled = _fill_variance(cvar, nn, y, bad)
    del cvar, color_var
    vy_filled = float(vy_filled.mean())

    # ---- features: normal, albedo, depth (7 channels), float32 (NL-means input)
    F7 = np.empty((h, w, 7), np.float32)
    V7 = np.empty((h, w, 7), np.float32)
    c0 = 0
    for name, c in FEATURE_ORDER:
        f = feats.get(name) if feats else None
        if f is None:
            f = np.zeros((h, w, c))
            fv = np.zeros((h, w, c))
        else:
            f = np.asarray(f, np.float64).reshape(h, w, -1)[..., :c]
            fv = (feat_var or {}).get(name)
            fv = fv() if callable(fv) else fv
            fv = np.zeros_like(f) if fv is None else np.broadcast_to(
                np.asarray(fv, np.float64).reshape(h, w, -1)[..., :c], f.shape)
        fbad = ~np.isfinite(f).all(-1)
        f = _fill_missing(np.clip(np.where(np.isfinite(f), f, 0.0), -FEATURE_LIMIT,
                                  FEATURE_LIMIT), fbad)
        fv, _ = _fill_variance(fv, nn, f, fbad | bad)
        if name == "depth":
            f, fv = _normalise_depth(f, fv)
        F7[..., c0:c0 + c] = f
        V7[..., c0:c0 + c] = np.minimum(fv, FEATURE_LIMIT ** 2)
        c0 += c
    del f, fv, nn
    t_prep = time.perf_counter()

    # ---- Sec. 3.2 / 3.3 prefiltering
    fhat = prefilter_features(F7, V7, params)
    del F7, V7
    t_feat = time.perf_counter()
    # stored as float32 (they only feed the NL-means weights and the pilot y_0;
    # variances capped at 1e30, the float32 NL-means limit)
    M = prefilter_color(y, fhat, params).astype(np.float32)
    vM = np.minimum(guide_variance(vy, params.guided_radius), 1e30).astype(np.float32)
    gra = feature_gradient(fhat)
    cy, cx, cr, detailed = select_centers(gra, params)
    t_guide = time.perf_counter()

    # ---- Sec. 3.1 / 3.4 regression with bandwidth selection
    fhat = fhat.astype(np.float32)            # design features (Eq. 2); halves memory
    target = M if params.regress_guide else y
    var0 = vy.mean(axis=2)                                       # Var_0: variance of the mean
    del vy
    valid = (~bad).ravel()
    npx = h * w
    chunk = max(1, int(params.chunk_centers))

    def weights_of(ids, r):
        wk = nlm_center_weights(M, vM, cy[ids], cx[ids], r, params.patch_radius, ks,
                                sigma_r=params.sigma_r, sigma_s=params.regression_sigma_s,
                                eps=params.nlm_eps, dtype=np.float32)
        return wk.astype(np.float32)

    def add_chunks(ids_all):
        """Chunks (radius, ids, weights) for new models; updates coverage.
        Weights are computed for ``chunk_centers`` centres at a time, the
        regression runs on sub-chunks of at most CHUNK_PIXELS window pixels."""
        out = []
        order = ids_all[np.lexsort((cx[ids_all], cy[ids_all], cr[ids_all]))]
        for r in np.unique(cr[order]):
            ids_r = order[cr[order] == r]
            step = max(1, CHUNK_PIXELS // (2 * int(r) + 1) ** 2)
            for s0 in range(0, ids_r.size, chunk):
                ids = ids_r[s0:s0 + chunk]
                wk = weights_of(ids, int(r))
                idx, inside = _window_index(cy[ids], cx[ids], int(r), h, w)
                np.maximum.at(cover, idx[inside], wk[:, 0][inside])
                # kept for all T iterations: 16-bit fixed point (weights are
                # in [0, 1]; step 1.5e-5, the centre's 1 stays exactly 1)
                wq = np.rint(wk * WEIGHT_SCALE).astype(np.uint16)
                del wk
                for a in range(0, ids.size, step):
                    out.append((int(r), ids[a:a + step], wq[a:a + step]))
        return out

    # coverage: best weight at the smallest k (weights grow with k)
    cover = np.zeros(npx)
    chunks = add_chunks(np.arange(cy.size))
    rm = sorted((params.radius_small, params.radius_medium, params.radius_large))[1]
    fill_models = 0
    for _ in range(int(params.fill_rounds)):
        unc = (cover < params.coverage_weight).reshape(h, w)
        if not unc.any():
            break
        ny_, nx_ = _fill_centers(unc, int(rm))
        first = cy.size
        cy = np.concatenate([cy, ny_])
        cx = np.concatenate([cx, nx_])
        cr = np.concatenate([cr, np.full(ny_.size, int(rm), np.int64)])
        fill_models += ny_.size
        chunks += add_chunks(np.arange(first, cy.size))
    uncovered_frac = float((cover < params.coverage_weight).mean())
    del cover

    weis = iteration_weights(T)
    n_models = cy.size
    Ecum = np.zeros((n_models, K))
    k_idx = np.zeros(n_models, np.int64)
    vM_mean = vM.mean(axis=2, dtype=np.float64).ravel() if params.bias_noise_correction else None
    var0_flat = var0.ravel()
    target_flat = target.reshape(npx, 3)
    # pilots (y_{t-1}, Var_{t-1}) of Eq. 11 for t = 0..T-1; Var None = Var_0 (t = 0)
    pilots = [(M, None)]
    a_cache = [None] * len(chunks)
    tiny = 1e-12

    def chunk_terms(X, wfit, Yq, idx, pilot, cache, kk=None):
        """Eq. 11 terms of a chunk of models against the pilot (y_{t-1},
        Var_{t-1}): beta (c, K, P, 3) of the fit of Y, err_t = bias^2 + var
        (c, K, n), the Eq. 9-10 block error (c, K) and var (c, K, n).  With
        ``kk`` (c,) only that weighting of each model is evaluated (wfit is
        then (c, 1, n) and Var_{t-1} is taken at kk)."""
        y_p, v_p = pilot
        if v_p is None:
            vq = var0_flat[idx]                                 # (c, n)
        elif kk is None:
            vq = np.moveaxis(v_p.reshape(npx, K)[idx], 2, 1).astype(np.float64)
        else:
            vq = v_p.reshape(npx, K)[idx, kk[:, None]].astype(np.float64)
        Pq = y_p.reshape(npx, 3)[idx]
        if params.bias_noise_correction:
            uq = vM_mean[idx] if v_p is None else vq
            beta, b2, var, noise = hat_bias_variance(X, wfit, Yq, Pq, vq, params.ridge,
                                                     pilot_var=uq, cache=cache, lean=True)
            err_t = np.maximum(b2 - noise, 0.0) + var
            # block level: subtract the pilot noise from the block's bias
            # before clamping (per-pixel clamping keeps noise's positive part)
            blk = np.maximum(block_error(wfit, b2 - noise), 0.0) + block_error(wfit, var)
        else:
            beta, b2, var = hat_bias_variance(X, wfit, Yq, Pq, vq, params.ridge, cache=cache,
                                              lean=True)
            err_t = b2 + var                                    # (c, K, n)
            blk = None
        err_t = np.where(np.isfinite(err_t), np.minimum(err_t, VAR_LIMIT), VAR_LIMIT)
        if blk is None:
            blk = block_error(wfit, err_t)                      # Eq. 9-10
        blk = np.where(np.isfinite(blk), np.minimum(blk, VAR_LIMIT), VAR_LIMIT)
        return beta, err_t, blk, var

    for t in range(T):
        last = t == T - 1
        img_num = np.zeros((npx, 3))
        den = np.zeros(npx)
        if last:
            err_num = np.zeros(npx)
        else:
            v_num = np.zeros((npx, K), np.float32)
            v_den = np.zeros((npx, K), np.float32)
        for gi, (r, ids, wq) in enumerate(chunks):
            idx, inside = _window_index(cy[ids], cx[ids], r, h, w)
            cidx = cy[ids] * w + cx[ids]
            wk = wq * (1.0 / WEIGHT_SCALE)                      # (c, K, n) float64
            X = _design_rows(fhat, idx, inside, cidx, w)        # (c, n, 10)
            wfit = wk * (valid[idx] & inside)[:, None, :]
            Yq = target_flat[idx]                               # (c, n, 3)
            # (X^T W X + Lambda)^-1 of this chunk, reused over the T iterations
            cache = {} if a_cache[gi] is None else {"Ainv": a_cache[gi]}
            beta, err_t, blk, var = chunk_terms(X, wfit, Yq, idx, pilots[t], cache)
            a_cache[gi] = None if last else cache["Ainv"]
            Ecum[ids] += weis[t] * blk                          # Eq. 12
            kk = choose_bandwidth(Ecum[ids])
            k_idx[ids] = kk
            ar = np.arange(ids.size)
            wm = wk[ar, kk] + tiny                               # (c, n)  Eq. 13 weights
            yk = X @ beta[ar, kk]                                # (c, n, 3) prediction at k
            flat = idx[inside]
            lo, hi = int(flat.min()), int(flat.max()) + 1
            wsel = wm[inside]
            for ch in range(3):
                _bincount_add(img_num[:, ch], flat, wsel * yk[..., ch][inside], lo, hi)
            _bincount_add(den, flat, wsel, lo, hi)
            if last:
                # Eq. 12 error at the chosen k.  The terms of the earlier
                # iterations are recomputed for k_opt only (pilots kept, the
                # same Ainv) instead of keeping every model's (K, n) errors.
                ek = np.zeros(wm.shape)
                if t > 0:
                    sub = {"Ainv": cache["Ainv"][ar, kk][:, None]}
                    wsub = wfit[ar, kk][:, None]
                    for t2 in range(t):
                        e2 = chunk_terms(X, wsub, Yq, idx, pilots[t2], sub, kk)[1]
                        ek += weis[t2] * e2[:, 0]
                ek += weis[t] * err_t[ar, kk]
                ek /= weis.sum()
                _bincount_add(err_num, flat, wsel * ek[inside], lo, hi)
            else:
                wv = wk + tiny
                for kq in range(K):
                    wsk = wv[:, kq][inside]
                    # float32 maps: variances above 1e30 (inputs ~1e15) are capped
                    _bincount_add(v_num[:, kq], flat,
                                  wsk * np.minimum(var[:, kq][inside], 1e30), lo, hi)
                    _bincount_add(v_den[:, kq], flat, wsk, lo, hi)
                del wv, wsk
            # free this chunk's temporaries before the next one is built
            del X, wk, wfit, Yq, cache, beta, err_t, blk, var, wm, yk, flat, wsel
        # Eq. 13, with the input colour at weight input_weight (at least
        # FALLBACK_WEIGHT, for pixels that every model ignores)
        # (in place, one channel at a time: no full-size temporaries)
        fw = max(float(params.input_weight), FALLBACK_WEIGHT)
        dd = np.add(den, fw, out=den)
        for ch in range(3):
            img_num[:, ch] += fw * y[..., ch].ravel()
            img_num[:, ch] /= dd
        img = img_num.reshape(h, w, 3)
        del img_num
        if last:
            err_map = (err_num + fw * var0_flat) / dd
            del err_num
        else:
            # Var_t = v_num / v_den where v_den > 0 (float32, in place)
            np.divide(v_num, v_den, out=v_num, where=v_den > 0)
            del v_den
            v_prev = v_num.reshape(h, w, K)
            del v_num
            pilots.append((img, v_prev))
            del v_prev
    del chunks, pilots, a_cache
    t_reg = time.perf_counter()

    # ---- special cases and final guards
    out = np.where(zero_var, y_in, img)
    out = np.clip(np.where(np.isfinite(out), out, 0.0), -VALUE_LIMIT, VALUE_LIMIT)
    err = err_map.reshape(h, w) * (1.0 - zero_var.mean(axis=2))
    err = np.clip(np.where(np.isfinite(err), err, VAR_LIMIT), 0.0, VAR_LIMIT)
    active = 2 + int(sum(np.ptp(fhat[..., c]) > 1e-6 for c in range(fhat.shape[2]))) \
        if npx else 0
    info = {
        "models": int(n_models),
        "models_small": int((cr == min(params.radius_small, params.radius_medium,
                                       params.radius_large)).sum()),
        "models_fill": int(fill_models),
        "uncovered_fraction": uncovered_frac,
        "detailed_patch_fraction": float(detailed.mean()) if detailed.size else 0.0,
        "pixels_per_model": float(npx / max(n_models, 1)),
        "mean_k": float(ks[k_idx].mean()) if n_models else 0.0,
        "missing_pixels": int(bad.sum()),
        "variance_filled_fraction": vy_filled,
        "active_features": int(active),
        "seconds_prepare": t_prep - t0,
        "seconds_features": t_feat - t_prep,
        "seconds_guide": t_guide - t_feat,
        "seconds_regression": t_reg - t_guide,
    }
    return RHFOutput(out, err, fhat, M, gra, cy, cx, cr, ks[k_idx], Ecum / weis.sum(),
                     detailed, info)


# ------------------------------------------------------------- method interface
def _feature_arrays(buf: Buffers):
    feats, fvars = {}, {}
    for name, _ in FEATURE_ORDER:
        if name in buf.features:
            feats[name] = buf.feature(name)
            fvars[name] = (lambda st=buf.features[name]: buf.variance_of_mean(st))
    return feats, fvars


def reconstruct(buf: Buffers, params: Params | None = None) -> MethodResult:
    """RHF reconstruction of the accumulated buffers (Liu et al. 2018).

    Reads the colour mean and variance of the mean, the ``PASSES`` features
    and their variances, and n.  See ``rhf_reconstruct``; the error is the
    Eq. 12 estimate (bias^2 + variance) at each pixel's chosen k, averaged over
    the overlapping models with the Eq. 13 weights.
    """
    params = params or Params()
    feats, fvars = _feature_arrays(buf)
    cvar = [buf.variance_of_mean()]
    zero = np.isfinite(buf.color.mean)
    zero &= cvar[0] == 0                   # k >= 2, n > 0 and M2 = 0 (cvar is inf otherwise)
    # handed over as a callable (list.pop) so that rhf_reconstruct holds the
    # only reference and frees it once the variance is prepared
    res = rhf_reconstruct(buf.color.mean, cvar.pop, feats, fvars, buf.n, params, zero_var=zero)
    return MethodResult(res.image, res.error, res.info)


def sample_map(buf: Buffers, result: MethodResult, budget: int, params: Params | None,
               state: dict) -> np.ndarray:
    """New samples per pixel for the next iteration, summing to ``budget``.

    The paper stops at reconstruction; sampling follows LP (Moon et al. 2015,
    Sec. 5.2): the expected error reduction of one more sample at pixel i is
    ``err_i * n_i^(-4/(d+4))`` (Moon et al. 2014) with d the number of active
    regression features (``info['active_features']``, at most D = 9), made
    relative by ``/(lum(image_i)^2 + 0.001)``; samples are allocated in
    proportion (largest-remainder rounding, exact sum).  Pixels with no samples
    yet use n = 1.  ``state`` is unused (kept for the interface).
    """
    d = float(result.info.get("active_features", 9)) if result.info else 9.0
    n = np.maximum(np.asarray(buf.n, np.float64), 1.0)
    gain = np.asarray(result.error, np.float64) * n ** (-4.0 / (d + 4.0))
    rho = relative_error(gain, result.image, 1e-3)
    return allocate(rho, int(budget))


def denoise(color, color_var, features: dict, params: Params | None = None,
            feature_vars: dict | None = None, n=None) -> MethodResult:
    """Convenience: RHF on plain arrays.

    color, color_var : (H, W, 3) pixel means and variance of the means (+inf =
        unknown, see module notes); features : dict name -> (H, W, C) of
        'normal', 'albedo', 'depth'; feature_vars : their variances (default
        0, i.e. noise-free features); n : (H, W) samples per pixel (default 1).
    """
    res = rhf_reconstruct(color, color_var, features, feature_vars, n, params)
    return MethodResult(res.image, res.error, res.info)

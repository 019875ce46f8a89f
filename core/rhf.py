"""RHF: denoising Monte Carlo renderings with a robust high-order function
(Liu, Zheng, Yuan 2018, "Denoising Monte Carlo renderings based on a robust
high-order function", GRAPP).

What: sparse first-order regressions (Eq. 1-2) on prefiltered features, one
per model centre, each predicting every pixel of its window, with the NL-means
bandwidth k of its weights chosen per model from a hat-matrix estimate of bias
and variance; overlapping predictions are averaged (Eq. 13).  Why: the
per-model bandwidth trades noise against detail locally, and sparse models
make a regression per pixel unnecessary.  The per-pixel error estimate (Eq. 12
at the chosen k, merged by Eq. 13) and the active feature count
(``MethodResult.dimension``) drive ``sample_map`` (LP, Moon et al. 2015,
Sec. 5.2).

Pipeline (section / equation of the paper -> function):

1. Input fixes (missing colour, variance, features) -> ``prepare_color``,
   ``prepare_features``.
2. Collaborative feature prefiltering, Sec. 3.2, Eq. 3-7: joint NL-means
   ``NLM(f_m, 0.25, true)`` then ``GUID(f_m, f_m)`` -> ``prefilter_features``.
3. Colour guide, Sec. 3.3, Eq. 8: ``M = mean_m GUID(y, f^_m)`` and its
   variance -> ``colour_guide`` (``prefilter_color``, ``guide_variance``).
4. Centres and windows, Sec. 3.5, Eq. 14 -> ``feature_gradient``,
   ``select_centers``; regression weights ``w(i, j) = NLM(M, k, false)``
   (Sec. 3.3) and the r_m fill models -> ``regression_weights``,
   ``weight_chunks``, ``place_models``.
5. Per-window regression and its hat-matrix bias / variance, Eq. 2, 9-12 ->
   ``window_inputs``, ``window_error_terms`` (``hat_bias_variance``,
   ``block_error``).
6. Bandwidth selection, Eq. 10, 12 -> ``choose_bandwidth``,
   ``predict_at_bandwidth`` (``clamp_to_support``), ``error_at_bandwidth``.
7. Accumulation of the window predictions and their combination, Eq. 13 ->
   ``accumulate_predictions``, ``accumulate_variances``, ``blend_input``
   (``combine_models`` with a fixed input weight);
   one iteration over all models -> ``regression_pass``; the T iterations of
   Eq. 11-12 -> ``fit_models``; the driver -> ``rhf_reconstruct``.

Choices where the paper is silent or ambiguous (details in each function):

* Eq. 2 fits the input colours Y; M gives the weights and the first pilot
  y_0 of Eq. 11 (``Params.regress_guide`` fits M instead).  The Eq. 5
  distance on M uses the variance of M (``guide_variance``).
* Regression weights have no spatial term (``regression_sigma_s = 0``).
* Eq. 9-10 use the weighted *mean* error of the block (``block_error``); ties
  go to the larger k (``choose_bandwidth``).
* Iterations: y_{t-1} is the whole Eq. 13 image of iteration t-1 and
  Var_{t-1}(s, k) its per-k variance maps merged with the same weights; only
  the error estimate and k_opt are iterated, the fit always targets Y.
  ``bias_noise_correction`` (off) subtracts the pilot's noise from bias^2.
* tau thresholds each pixel's gradient; a detailed patch gets r_s windows on
  its detail pixels (Fig. 4), not one at its centre; r_m models go to pixels
  that no model weights >= ``coverage_weight`` (``select_centers``,
  ``place_models``).
* Each model's predictions are clipped to the range of the input colours it
  fitted (``clamp_to_support``): no extrapolated overshoot, and non-negative
  input gives non-negative output.
* The Eq. 13 average is blended with each pixel's own input by inverse MSE:
  weight E / (E + V) for the input, E the models' Eq. 12 error and V the
  input's variance (``blend_input``, ``blend_variance``); the former fixed
  input weight (0.02) is ``input_blend = "fixed"``.
* Design features are position, depth, normal, albedo (D = 9), each column
  scaled per window, with a small relative ridge (``regularizer``); depth is
  normalised by its 99th percentile (``_normalise_depth``).
* Unstated radii: feature NL-means search 4 = 2 sigma_s, guided filter 1.

Special inputs: non-finite colour or n <= 0 is *missing* (filled for the
guides, excluded from every fit, still predicted); variance +inf is filled
from neighbours or, with none anywhere, from a robust Immerkaer estimate
(``noise_variance_estimate``); zero-variance channels are returned unchanged
with error 0; magnitudes are clipped (1e30, features 1e6), the output is
always finite.

Threads (:mod:`core.parallel`): the regression weights of each group of
centres (``weight_chunks``) and the model chunks of every iteration
(``regression_pass``, ``chunk_terms``) run as pieces on the shared pool; the
pieces are cut by the data only, each writes only its own models' rows and
returns its Eq. 13 sums, and the sums (and the coverage maximum) are added
one piece at a time in piece order (``parallel.ordered_reduce``): the output is
bit-identical for any thread count.  Frames below ``THREAD_MIN_PIXELS`` run
inline.  The feature prefilter (``core.filters.nlm_filter``'s row strips, then
one guided filter per channel) and the colour guide (``guided_filter_mean``'s
row strips) run on the same pool, each piece writing only its own rows or
channel.

Measurements and design notes: docs/notes/rhf.md
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from . import parallel
from .buffers import Buffers
from .errormap import retained_noise, without_kept_noise
from .filters import (VALUE_LIMIT, VAR_LIMIT, box_mean, box_sum, guided_filter, guided_filter_mean,
                      nlm_center_weights, nlm_filter, sobel_gradient, window_offsets)
from .method import (MethodResult, allocate, param, params_from_dict, relative_error,
                     sampling_gain)

NAME = "rhf"
PASSES = ("normal", "albedo", "depth")
ADAPTIVE = True
SAMPLER_USES_RESULT = True

#: Model dimension assumed by ``sample_map`` when a result carries none (D = 9).
DEFAULT_DIMENSION = 9.0

#: Feature values are clipped to +-this (normals, albedo and normalised depth
#: are O(1); larger values are corrupt input), their variances to its square.
FEATURE_LIMIT = 1e6

#: The 7 feature channels (D - 2 of the paper) in the order used everywhere.
FEATURE_ORDER = (("normal", 3), ("albedo", 3), ("depth", 1))

#: Most window pixels (centres x (2r+1)^2) regressed together: the per-chunk
#: temporaries (design rows, weights, the per-k products of
#: ``hat_bias_variance``) take ~0.5 kB per window pixel, so this bounds them
#: to ~8 MB whatever the window radius; smaller chunks spend their time in
#: per-call costs of small batched products (docs/notes/rhf.md, "Chunk sizes").
CHUNK_PIXELS = 1 << 14
#: frames below this many pixels run their model chunks on the calling thread
#: only (measured: docs/notes/rhf.md, "Threads")
THREAD_MIN_PIXELS = 1 << 16

#: Regression weights of every model are kept over the T iterations as
#: 16-bit fixed point in [0, 1] (``round(w * WEIGHT_SCALE)``): half the memory
#: of float32, absolute error <= 7.6e-6 per weight.
WEIGHT_SCALE = 65535.0

#: Smallest weight of the input colour y in Eq. 13 (failure guard, used even
#: with ``Params.input_weight = 0``): a pixel that every model ignores keeps
#: its input value instead of 0 / 0.
FALLBACK_WEIGHT = 1e-12

#: Added to every model weight in the Eq. 13 sums (and the Var_t maps), so a
#: window pixel weighted 0 still contributes a defined average.
MODEL_WEIGHT_FLOOR = 1e-12


@dataclass
class Params:
    """RHF parameters; defaults are the paper's (Liu et al. 2018, Sec. 3-4)
    where it gives them, otherwise the documented choices."""

    bandwidths: str = param("1.0,1.5,2.0,3.5,4.0",
                           "candidate NL-means strengths k (Sec. 3.4, comma list); more candidates "
                           "= finer bias/variance choice, proportionally slower", label="Bandwidths")
    iterations: int = param(2, "T, iterations of the bias/variance estimate (Eq. 12); 3 gives slightly "
                              "less noisy error estimates, each costs one more regression pass", 1, 5, label="Iterations")
    radius_small: int = param(5, "r_s, window radius for patches with fine detail (Sec. 3.5); smaller "
                                "keeps detail, more models = slower", 1, 64, label="Detail Radius")
    radius_medium: int = param(10, "r_m, window radius of models filling uncovered pixels (Sec. 3.5)",
                              1, 64, label="Fill Radius")
    radius_large: int = param(15, "r_l, patch radius and window radius of smooth patches (Sec. 3.5); "
                                 "larger = fewer models (faster), more smoothing", 1, 64, label="Smooth Radius")
    edge_threshold: float = param(0.4, "tau: a pixel whose feature Sobel gradient (Eq. 14) exceeds it "
                                      "is high-frequency; lower = more small windows (slower, sharper)",
                                 0.0, 1e6, label="Edge Threshold")
    detail_min_pixels: int = param(1, "a patch with at least this many high-frequency pixels gets the "
                                     "small radius r_s (num > tau, Sec. 3.5)", 1, 1 << 20, label="Detail Pixels")
    patch_radius: int = param(3, "r, NL-means patch radius (Eq. 4); larger = more robust distances, "
                                "cost grows with (2r+1)^2", 0, 10, label="Patch Radius")
    sigma_s: float = param(2.0, "spatial sigma of the feature NL-means (Eq. 3)", 0.0, 100.0, label="Spatial Sigma")
    sigma_r: float = param(1.0, "patch-range sigma of the NL-means kernels (Eq. 3)", 1e-6, 100.0, label="Range Sigma")
    sigma_normal: float = param(0.8, "sigma_m of the normal term of the joint feature kernel (Eq. 3)",
                               1e-6, 100.0, label="Normal Sigma")
    sigma_albedo: float = param(0.25, "sigma_m of the albedo term of the joint feature kernel (Eq. 3)",
                               1e-6, 100.0, label="Albedo Sigma")
    sigma_depth: float = param(0.6, "sigma_m of the depth term (depth scaled to the scene's 99th "
                                   "percentile, Eq. 3)", 1e-6, 100.0, label="Depth Sigma")
    feature_k: float = param(0.25, "k of the feature NL-means (Eq. 7); larger = smoother features",
                            1e-3, 100.0, label="Feature Smoothing")
    feature_radius: int = param(4, "search radius of the feature NL-means (2 sigma_s; the paper does "
                                  "not say); larger = smoother features, cost ~ (2r+1)^2", 0, 16, label="Search Radius")
    guided_radius: int = param(1, "window radius of the guided filters (Eq. 6-8; not given in the "
                                 "paper); larger = smoother guide colour M, more bias", 0, 32, label="Guided Filter Radius")
    guided_eps: float = param(0.001, "regularisation of the guided filter (Eq. 6, paper 0.001); larger "
                                    "= flatter a, more smoothing", 1e-12, 1e3, label="Guided Filter Epsilon")
    regression_sigma_s: float = param(0.0, "spatial sigma of the regression weights NLM(M,k,false); 0 "
                                          "= none (the window bounds the support)", 0.0, 100.0, label="Regression Spatial Sigma")
    regress_guide: bool = param(False, "fit the guide colour M (Eq. 8) instead of the input colour "
                                      "(Eq. 2); less variance, but M's blur at colour-only edges is "
                                      "bias the error estimate cannot see", label="Fit Guide Colour")
    bias_noise_correction: bool = param(False, "subtract the pilot's noise from the Eq. 11 bias "
                                              "estimate (not in the paper): flat noisy regions then "
                                              "choose large k", None, None, label="Bias Noise Correction")
    ridge: float = param(1e-3, "Tikhonov regularisation of the gradient terms relative to the total "
                              "weight (guards singular systems); larger = more stable, more bias",
                        1e-9, 1.0, label="Ridge")
    nlm_eps: float = param(1e-10, "epsilon of the NL-means distance (Eq. 5)", 1e-300, 1.0, label="Distance Epsilon")
    coverage_weight: float = param(0.01, "a pixel counts as covered when some model's regression "
                                        "weight for it at the smallest k reaches this; uncovered "
                                        "pixels get r_m models (Sec. 3.5). Higher = more models, "
                                        "slower, fewer extrapolated predictions", 0.0, 1.0, label="Coverage Weight")
    clamp_predictions: bool = param(True, "clip each model's predictions to the range of the input "
                                          "colours it fitted (weight >= coverage_weight): no "
                                          "extrapolated overshoot, no negative output from "
                                          "non-negative input; off = the paper's fit as is", label="Clamp Predictions")
    detail_cover: bool = param(True, "detailed patches get r_s windows on every detail pixel (Sec. "
                                     "3.5, Fig. 4); off: one r_s window at the patch centre (fewer "
                                     "models, faster, edges off the centre get r_m windows)", label="Detail Coverage")
    fill_rounds: int = param(4, "rounds of r_m models for uncovered pixels (Sec. 3.5); 0 = only the "
                               "geometric cover", 0, 16, label="Fill Rounds")
    input_blend: str = param("mse", "how each pixel's own input enters Eq. 13: mse = inverse-MSE "
                                    "blend of the models' average (its Eq. 12 error) and the "
                                    "input (its variance), derived, no constant; fixed = the "
                                    "input as one more model at weight input_weight",
                            choices=("mse", "fixed"), label="Input Blend")
    input_weight: float = param(0.02, "with input_blend = fixed: weight of each pixel's own input "
                                     "colour in the Eq. 13 average (not in the paper): pixels that the models weight weakly (their "
                                     "predictions there are extrapolations) lean on their unbiased "
                                     "input; 0 = pure Eq. 13, higher = closer to the input", 0.0, 1.0, label="Input Weight")
    chunk_centers: int = param(128, "model centres processed together (at most CHUNK_PIXELS window "
                                  "pixels per chunk); larger = fewer, larger batched products "
                                  "(faster up to ~128), more memory, fewer pieces for threads; "
                                  "results equal up to float rounding",
                              1, 4096, label="Batch Size")
    kept_noise: bool = param(True, "add to the error map the noise the models keep from noisy "
                                   "features (defocus, motion), which Eq. 11-12 cannot see "
                                   "(core/errormap.py); off = the Eq. 12 estimate alone. The image "
                                   "and the sampling do not change", 0, 1, label="Kept Noise in Error")


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


def prepare_color(color, color_var, n=None, zero_var=None):
    """Input colour, its variance and the missing-pixel mask, made usable.

    color : (H, W, 3) pixel means y (a single channel is broadcast to RGB);
        NaN / +-Inf or n <= 0 mark a *missing* pixel, filled from its
        neighbours (``_fill_missing``) for the guides and the distances.
    color_var : (H, W, 3) variance of the means (+inf unknown) or a
        zero-argument callable returning it (called here, so the caller can
        hand over the only reference); unknown entries are filled
        (``_fill_variance``).
    n : (H, W) samples per pixel, default 1.
    zero_var : optional (H, W, 3) bool noise-free channels; default
        ``color_var == 0`` at non-missing pixels.

    Returns
    -------
    y_in (H, W, 3) the input as given (float64), y (H, W, 3) finite filled
    colour, var (H, W, 3) filled variance of the mean, n (H, W) finite sample
    counts, bad (H, W) missing mask, zero_var (H, W, 3), and the fraction of
    pixels whose variance was filled (float).
    """
    y_in = np.asarray(color, np.float64)
    if y_in.ndim == 2:
        y_in = y_in[..., None]
    h, w = y_in.shape[:2]
    if y_in.shape[2] != 3:
        y_in = np.broadcast_to(y_in[..., :1], (h, w, 3))
    if callable(color_var):
        color_var = color_var()
    cvar = np.broadcast_to(np.asarray(color_var, np.float64).reshape(h, w, -1), (h, w, 3))
    del color_var
    nn = np.ones((h, w)) if n is None else np.asarray(n, np.float64).reshape(h, w)
    nn = np.where(np.isfinite(nn), nn, 0.0)
    bad = ~np.isfinite(y_in).all(-1) | (nn <= 0)
    y = np.clip(np.where(np.isfinite(y_in), y_in, 0.0), -VALUE_LIMIT, VALUE_LIMIT)
    y = _fill_missing(y, bad)
    if zero_var is None:
        zero_var = np.isfinite(cvar) & (cvar == 0) & ~bad[..., None]
    vy, vy_filled = _fill_variance(cvar, nn, y, bad)
    return y_in, y, vy, nn, bad, zero_var, float(vy_filled.mean())


def prepare_features(feats, feat_var, n: np.ndarray, bad: np.ndarray):
    """The 7 feature channels of ``FEATURE_ORDER`` (normal xyz, albedo rgb,
    depth) and the variances of their means, as the NL-means input.

    feats : dict 'normal' (H, W, 3), 'albedo' (H, W, 3), 'depth' (H, W[, 1]);
        a missing pass is a constant 0 feature (variance 0).
    feat_var : dict of their variances (missing entries: 0, noise-free); a
        value may be a zero-argument callable, evaluated when that feature is
        prepared (bounds peak memory).
    n, bad : (H, W) sample counts and missing-pixel mask (``prepare_color``).

    Non-finite feature values are filled from their neighbours, magnitudes
    clipped to ``FEATURE_LIMIT``, variances filled like the colour's and depth
    normalised (``_normalise_depth``).  Returns (F, V), both (H, W, 7) float32.
    """
    h, w = n.shape
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
        fv, _ = _fill_variance(fv, n, f, fbad | bad)
        if name == "depth":
            f, fv = _normalise_depth(f, fv)
        F7[..., c0:c0 + c] = f
        V7[..., c0:c0 + c] = np.minimum(fv, FEATURE_LIMIT ** 2)
        c0 += c
    return F7, V7


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
    the filter's support is 2r + 2r + 1 = 5 pixels; a smaller radius blurs the
    colour-only edges of M less).  The NL-means runs in float32 (features are
    O(1)).
    """
    sig = np.array([params.sigma_normal] * 3 + [params.sigma_albedo] * 3 + [params.sigma_depth])
    f = nlm_filter(feats, feat_var, params.feature_k, params.feature_radius, params.patch_radius,
                   sigma_r=params.sigma_r, sigma_s=params.sigma_s, guides=feats,
                   guide_sigmas=sig[:feats.shape[2]], channelwise=True, eps=params.nlm_eps,
                   dtype=np.float32)

    def channel(m):                             # channel by channel, in place
        f[..., m] = _guided_rows(f[..., m], f[..., m], params.guided_radius, params.guided_eps)

    # channels are independent (each reads and writes only its own): on the
    # pool, same bits for any thread count; inline for small frames
    if f.shape[0] * f.shape[1] < THREAD_MIN_PIXELS:
        for m in range(f.shape[2]):
            channel(m)
    else:
        parallel.map_ordered(channel, range(f.shape[2]))
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


def colour_guide(y: np.ndarray, var: np.ndarray, fhat: np.ndarray, params: Params):
    """Colour guide M of Eq. 8 (``prefilter_color``) and its variance
    (``guide_variance``), the inputs of the regression weights
    ``NLM(M, k, false)`` (Sec. 3.3) and the first pilot y_0 of Eq. 11.

    y, var : (H, W, 3) filled colour and variance of its mean; fhat : (H, W, 7)
    prefiltered features.  Returns (M, Var(M)), both (H, W, 3) float32 (they
    only feed the NL-means weights and the pilot; variances capped at 1e30, the
    float32 NL-means limit).
    """
    M = prefilter_color(y, fhat, params).astype(np.float32)
    vM = np.minimum(guide_variance(var, params.guided_radius), 1e30).astype(np.float32)
    return M, vM


# ------------------------------------------------------------------ centre choice
def select_centers(gra: np.ndarray, params: Params):
    """Model centres and window radii (Sec. 3.5 of Liu et al. 2018).

    The image is divided into patches of radius r_l (side 2 r_l + 1, from the
    top-left corner).  num = number of pixels with gra > tau in the patch;
    if num >= ``detail_min_pixels`` (num > tau with num a count and tau = 0.4
    means at least one pixel) the patch has fine detail and is reconstructed
    with windows of radius r_s placed on its detail pixels, otherwise with one
    window of radius r_l at its centre.  Every pixel that no window covers
    then gets a model of radius r_m.

    Choices: tau = 0.4 thresholds the gradient gra of each pixel ("pixels
    recognized by gra"), since a count num compared with 0.4 only says
    "num >= 1".  The paper's Fig. 4 reconstructs the *detail pixels* ("the red
    pixels") with r_s windows and the rest with larger ones, so a detailed
    patch gets r_s windows wherever it has detail pixels, not one r_s window
    at its centre (which leaves an edge off the centre to the r_m fill): the
    detail pixels are cut into cells of side 2 r_s + 1 and one r_s window is
    centred on the bounding box of each cell's detail pixels
    (``_cell_box_centers``), which covers all of them.  With
    ``Params.detail_cover`` off, the former placement (one r_s window at each
    detailed patch centre) is used.  Patches whose centre lies outside the
    image (partial patches at the right / bottom border) get no r_l window.
    The paper builds r_m models by a sequential pixel scan; vectorised, the
    uncovered pixels are cut into cells of side 2 r_m + 1 and one r_m model
    is centred on each cell's bounding box, which covers all of them in one
    pass.  Sec. 4's "patch size r = 3" is the Eq. 4 NL-means patch radius
    (Eq. 4 names it r); the detail patches here have radius r_l as Sec. 3.5
    says.  The three radii are used sorted (r_s <= r_m <= r_l).

    Returns
    -------
    cy, cx, cr : (N,) int64 centre rows, columns and radii, every pixel of the
        image lies in at least one window |q - c|_inf <= r; every detail
        pixel of a detailed patch lies in an r_s window.
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
    if params.detail_cover:
        big = keep & ~detailed
        detail_px = (edge & np.repeat(np.repeat(detailed, side, 0), side, 1))[:h, :w]
        sy, sx = _cell_box_centers(detail_px, rs)
        cy = [ty[big], sy]
        cx = [tx[big], sx]
        cr = [np.full(int(big.sum()), rl), np.full(sy.size, rs)]
    else:
        cy = [ty[keep]]
        cx = [tx[keep]]
        cr = [np.where(detailed[keep], rs, rl)]
    covered = np.zeros((h, w), bool)
    for yy, xx, rr in zip(cy, cx, cr):
        for r in np.unique(rr):
            ind = np.zeros((h, w))
            sel = rr == r
            ind[yy[sel], xx[sel]] = 1.0
            covered |= box_sum(ind, int(r)) > 0.5
    if not covered.all():
        gy, gx = _cell_box_centers(~covered, rm)
        cy.append(gy)
        cx.append(gx)
        cr.append(np.full(gy.size, rm))
    cy = np.concatenate(cy).astype(np.int64)
    cx = np.concatenate(cx).astype(np.int64)
    cr = np.concatenate(cr).astype(np.int64)
    return cy, cx, cr, detailed


def _cell_box_centers(mask: np.ndarray, r: int):
    """Centres of windows of radius r that cover every True pixel of ``mask``:
    the image is cut into cells of side 2 r + 1 (from the top-left corner)
    and each cell holding mask pixels gets one centre at the middle of their
    bounding box (its extent is <= 2 r, so the window covers it).
    mask (H, W) bool -> (cy, cx) int64, in cell row-major order."""
    h, w = mask.shape
    side_m = 2 * int(r) + 1
    my, mx = -(-h // side_m), -(-w // side_m)
    unc = np.zeros((my * side_m, mx * side_m), bool)
    unc[:h, :w] = mask
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
    return gy[has].astype(np.int64), gx[has].astype(np.int64)


def _window_index(cy, cx, r, h, w):
    """Flat pixel indices (c, (2r+1)^2) of the windows of centres (clipped) and
    the mask of window pixels inside the image."""
    oy, ox = window_offsets(r)
    qy = cy[:, None] + oy[None, :]
    qx = cx[:, None] + ox[None, :]
    inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
    qy = np.minimum(np.maximum(qy, 0, out=qy), h - 1, out=qy)   # np.clip without its wrapper
    qx = np.minimum(np.maximum(qx, 0, out=qx), w - 1, out=qx)
    qy *= w
    qy += qx
    return qy, inside


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



# ------------------------------------------------------------ regression weights
class ModelChunk(NamedTuple):
    """Models regressed together: window radius, model ids (c,) into the
    centre arrays, and their regression weights (c, K, (2r+1)^2) as uint16
    fixed point (``WEIGHT_SCALE``)."""

    radius: int
    ids: np.ndarray
    weights: np.ndarray


class ModelSet(NamedTuple):
    """All models of an image (``place_models``): centres cy, cx and radii cr
    (N,) int64, their weight chunks, the number of r_m fill models and the
    fraction of pixels still uncovered after the fill rounds."""

    cy: np.ndarray
    cx: np.ndarray
    cr: np.ndarray
    chunks: list
    fill_models: int
    uncovered_fraction: float


def regression_weights(M, vM, cy, cx, radius: int, ks, params: Params) -> np.ndarray:
    """Regression weights ``w(i, j) = NLM(M, k, false)`` (Sec. 3.3, Eq. 3-5
    with UF = false) between centres i and every pixel j of their window,
    for every candidate k.

    M, vM : (H, W, 3) colour guide and its variance; cy, cx : (c,) centres;
    ks : (K,) candidates.  Returns (c, K, (2 radius + 1)^2) float32 in [0, 1]
    (``window_offsets`` order, 0 outside the image, 1 at the centre).

    Choice: no spatial term by default (``regression_sigma_s = 0``): with
    sigma_s = 2 a radius-15 window would be fitted from ~5 pixels and
    extrapolated to the rest; the window bounds the support.
    """
    wk = nlm_center_weights(M, vM, cy, cx, radius, params.patch_radius, ks,
                            sigma_r=params.sigma_r, sigma_s=params.regression_sigma_s,
                            eps=params.nlm_eps, dtype=np.float32)
    return wk.astype(np.float32)


def weight_chunks(M, vM, cy, cx, cr, ids_all, ks, params: Params, cover: np.ndarray) -> list:
    """Regression weights of the models ``ids_all``, grouped into chunks.

    Models are sorted by (radius, row, column); weights are computed for
    ``Params.chunk_centers`` centres at a time, and each chunk regressed later
    holds at most ``CHUNK_PIXELS`` window pixels.  ``cover`` (H W,) is updated
    in place to the best weight at the smallest k of any model for each pixel
    (the coverage test of Sec. 3.5; weights grow with k).

    Returns a list of ``ModelChunk``.
    """
    h, w = M.shape[:2]
    chunk = max(1, int(params.chunk_centers))
    order = ids_all[np.lexsort((cx[ids_all], cy[ids_all], cr[ids_all]))]
    # the pieces: chunk_centers centres of one radius, cut by the data only
    pieces = []
    for r in np.unique(cr[order]):
        ids_r = order[cr[order] == r]
        pieces += [(int(r), ids_r[s0:s0 + chunk]) for s0 in range(0, ids_r.size, chunk)]

    def compute(piece):
        # on a pool thread: the weights of one piece (reads M and vM only)
        r, ids = piece
        wk = regression_weights(M, vM, cy[ids], cx[ids], r, ks, params)
        idx, inside = _window_index(cy[ids], cx[ids], r, h, w)
        # kept for all T iterations: 16-bit fixed point (weights are
        # in [0, 1]; step 1.5e-5, the centre's 1 stays exactly 1)
        return r, ids, idx[inside], wk[:, 0][inside], np.rint(wk * WEIGHT_SCALE).astype(np.uint16)

    def reduce(out):
        r, ids, flat, w0, wq = out
        np.maximum.at(cover, flat, w0)                          # one piece at a time
        step = max(1, CHUNK_PIXELS // (2 * r + 1) ** 2)
        return [ModelChunk(r, ids[a:a + step], wq[a:a + step]) for a in range(0, ids.size, step)]

    return [c for part in parallel.ordered_reduce(compute, reduce, pieces, h * w < THREAD_MIN_PIXELS) for c in part]


def place_models(M, vM, cy, cx, cr, ks, params: Params) -> ModelSet:
    """The models of Sec. 3.5: the patch models of ``select_centers`` plus
    rounds of r_m models for pixels "not covered by any existing window".

    Choice: a window pixel whose weight is ~0 in its model is extrapolated,
    not fitted, so a pixel counts as covered when some model weights it >=
    ``coverage_weight`` at the smallest k; uncovered pixels get r_m models
    (``_fill_centers``) for up to ``fill_rounds`` rounds.

    M, vM : (H, W, 3) colour guide and its variance; cy, cx, cr : (N0,) the
    patch models; ks : (K,) candidates.  Returns a ``ModelSet``.
    """
    h, w = M.shape[:2]
    cover = np.zeros(h * w)
    chunks = weight_chunks(M, vM, cy, cx, cr, np.arange(cy.size), ks, params, cover)
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
        chunks += weight_chunks(M, vM, cy, cx, cr, np.arange(first, cy.size), ks, params, cover)
    uncovered = float((cover < params.coverage_weight).mean())
    return ModelSet(cy, cx, cr, chunks, int(fill_models), uncovered)


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
    (B, n, K P) (bounds the peak memory of the regression).

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
        bias^2 (B, K, n) instead of bias (what ``window_error_terms`` needs).

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
        with parallel.lapack_lock():            # one LAPACK call at a time, if BLAS threads
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
    # lean: the channels of y_prev as (B, n) planes, so the bias^2 sums run
    # along n, not along a 3-long strided last axis (same operations)
    yp_ch = [y_prev[..., ch] for ch in range(C)] if lean else None
    for k in range(K):                                            # per-pixel terms per k
        if lean:
            pz = X @ beta[:, k, :, C:]                            # (B, n, C): H y_prev only
            bk = bias[:, k]                                       # mean_c (H y_prev - y_prev)^2
            for ch in range(C):
                d = np.subtract(pz[..., ch], yp_ch[ch])
                d *= d
                if ch == 0:
                    bk[...] = d
                else:
                    bk += d
            bk /= C
        else:
            pz = X @ beta[:, k]                                   # (B, n, 2C)
            b = np.subtract(pz[..., C:], y_prev, out=pz[..., C:])
            pred[:, k] = pz[..., :C]
            bias[:, k] = b
        var[:, k] = np.einsum("bnp,bnp->bn", X @ Cm[:, k], X)
        if u is not None:
            hjj[:, k] = w[:, k] * np.einsum("bnp,bnp->bn", X @ Ainv[:, k], X)
            if Cu is not None:
                hu[:, k] = np.einsum("bnp,bnp->bn", X @ Cu[:, k], X)
        del pz
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
    out = np.empty((c, n, 3 + F.shape[1]))
    out[..., 0] = 1.0
    diff = out[..., 1:]                                     # written in place
    qy, qx = np.divmod(idx, width)
    cy, cx = np.divmod(cidx, width)
    diff[..., 0] = qx - cx[:, None]
    diff[..., 1] = qy - cy[:, None]
    diff[..., 2:] = F[idx]
    diff[..., 2:] -= F[cidx][:, None, :]
    np.copyto(diff, 0.0, where=~inside[..., None])
    s = np.abs(diff).max(axis=1, keepdims=True)
    ok = s > 1e-12
    np.divide(diff, np.where(ok, s, 1.0), out=diff)
    np.copyto(diff, 0.0, where=~ok)
    return out


@dataclass
class RegressionData:
    """Per-image inputs shared by every model chunk of the regression.

    fhat : (H, W, 7) float32 prefiltered features (design rows, Eq. 2).
    target : (H W, 3) regression target Y (input colours, or M with
        ``regress_guide``).
    y : (H, W, 3) filled input colour (the input term of Eq. 13).
    valid : (H W,) bool, pixels that enter the fits (not missing).
    var0 : (H W,) Var_0 of Eq. 11, the channel mean of the variance of the mean.
    guide_var : (H W,) channel mean of Var(M), the pilot noise of y_0, or None
        (no ``bias_noise_correction``).
    cy, cx : (N,) model centres.
    weis : (T,) Eq. 12 iteration weights.
    ridge : ``Params.ridge``; input_weight : Eq. 13 weight of the input
        (``Params.input_weight``, at least ``FALLBACK_WEIGHT``), used when
        ``blend`` is "fixed"; blend : ``Params.input_blend``; var_blend :
        (H W,) the input variance of the "mse" blend (``blend_variance``).
    """

    fhat: np.ndarray
    target: np.ndarray
    y: np.ndarray
    valid: np.ndarray
    var0: np.ndarray
    guide_var: np.ndarray | None
    cy: np.ndarray
    cx: np.ndarray
    weis: np.ndarray
    ridge: float
    input_weight: float
    blend: str = "mse"
    var_blend: np.ndarray | None = None
    clamp_weight: float | None = None


@dataclass
class WindowSums:
    """Eq. 13 sums over the models of one iteration, (H W,) per pixel:
    img_num (H W, 3) sum_i w(i, j) y_ij and den sum_i w(i, j); in the last
    iteration err_num, the same average of the Eq. 12 error (in the earlier
    ones, of the iteration's own error term at k_opt); otherwise v_num,
    v_den (H W, K) float32, the per-k variance maps Var_t(s, k) of Eq. 11."""

    img_num: np.ndarray
    den: np.ndarray
    err_num: np.ndarray | None = None
    v_num: np.ndarray | None = None
    v_den: np.ndarray | None = None

    @classmethod
    def zeros(cls, npx: int, K: int, last: bool) -> "WindowSums":
        if last:
            return cls(np.zeros((npx, 3)), np.zeros(npx), err_num=np.zeros(npx))
        return cls(np.zeros((npx, 3)), np.zeros(npx), err_num=np.zeros(npx),
                   v_num=np.zeros((npx, K), np.float32), v_den=np.zeros((npx, K), np.float32))


def window_inputs(data: RegressionData, chunk: ModelChunk):
    """Eq. 2 inputs of a chunk of c models with n = (2r+1)^2 window pixels.

    Returns idx, inside (c, n) flat window pixel indices and in-image mask,
    X (c, n, 10) design rows (``_design_rows``), wk (c, K, n) float64
    regression weights w(i, j), wfit (c, K, n) the weights of the fit (0 at
    missing and outside pixels) and Yq (c, n, 3) the target.
    """
    h, w = data.fhat.shape[:2]
    r, ids, wq = chunk
    idx, inside = _window_index(data.cy[ids], data.cx[ids], r, h, w)
    cidx = data.cy[ids] * w + data.cx[ids]
    wk = wq * (1.0 / WEIGHT_SCALE)                              # (c, K, n) float64
    X = _design_rows(data.fhat, idx, inside, cidx, w)           # (c, n, 10)
    wfit = wk * (data.valid[idx] & inside)[:, None, :]
    Yq = data.target[idx]                                       # (c, n, 3)
    return idx, inside, X, wk, wfit, Yq


def gather_pilot(pilot, idx, var0, guide_var, kk=None):
    """The pilot (y_{t-1}, Var_{t-1}) of Eq. 11 on a chunk's windows.

    pilot : (y (H, W, 3), Var (H, W, K) float32 or None = Var_0, t = 1).
    idx : (c, n) window pixels; var0, guide_var : as in ``RegressionData``.
    kk : optional (c,) chosen candidate per model; Var_{t-1} is then taken
        at kk only.

    Returns Pq (c, n, 3) y_{t-1}; vq (c, n), (c, K, n) or, with kk, (c, n)
    Var_{t-1}; uq the variance of y_{t-1} for ``bias_noise_correction``
    (Var(M) at t = 1, Var_{t-1} after) or None when it is off.
    """
    y_p, v_p = pilot
    npx = var0.size
    if v_p is None:
        vq = var0[idx]                                          # (c, n)
    elif kk is None:
        vq = np.moveaxis(v_p.reshape(npx, v_p.shape[-1])[idx], 2, 1).astype(np.float64)
    else:
        vq = v_p.reshape(npx, v_p.shape[-1])[idx, kk[:, None]].astype(np.float64)
    Pq = y_p.reshape(npx, 3)[idx]
    uq = None
    if guide_var is not None:
        uq = guide_var[idx] if v_p is None else vq
    return Pq, vq, uq


def window_error_terms(X, wfit, Yq, Pq, vq, uq, ridge: float, cache: dict):
    """Per-window regression and its error terms for one iteration t.

    Eq. 2 fit of Y with the hat matrix H (``hat_bias_variance``), Eq. 11
    bias_t^2 + Var_t per window pixel (err_t, the term of Eq. 12) and the
    Eq. 9-10 block error (``block_error``) per candidate k.  With ``uq``
    (``bias_noise_correction``) the pilot's noise is subtracted from bias^2,
    at block level before clamping (per-pixel clamping would keep the
    noise's positive part).

    X (c, n, P), wfit (c, K, n), Yq, Pq (c, n, 3), vq (c, n) or (c, K, n),
    uq like vq or None; cache : dict holding or receiving (X^T W X +
    Lambda)^-1 ("Ainv", (c, K, P, P)).

    Returns beta (c, K, P, 3) coefficients of the fit (prediction X @ beta),
    err_t (c, K, n), block errors (c, K) and Var_t (c, K, n); err_t and the
    block errors are finite, <= VAR_LIMIT.
    """
    if uq is not None:
        beta, b2, var, noise = hat_bias_variance(X, wfit, Yq, Pq, vq, ridge, pilot_var=uq,
                                                 cache=cache, lean=True)
        err_t = np.maximum(b2 - noise, 0.0) + var
        blk = np.maximum(block_error(wfit, b2 - noise), 0.0) + block_error(wfit, var)
    else:
        beta, b2, var = hat_bias_variance(X, wfit, Yq, Pq, vq, ridge, cache=cache, lean=True)
        err_t = b2 + var                                        # (c, K, n)
        blk = None
    err_t = np.where(np.isfinite(err_t), np.minimum(err_t, VAR_LIMIT), VAR_LIMIT)
    if blk is None:
        blk = block_error(wfit, err_t)                          # Eq. 9-10
    blk = np.where(np.isfinite(blk), np.minimum(blk, VAR_LIMIT), VAR_LIMIT)
    return beta, err_t, blk, var


def clamp_to_support(yk, wsel, Yq, min_weight: float):
    """Clip each model's predictions to the range of the data it fitted.

    A first-order model evaluated at window pixels whose features lie outside
    those of its fitted pixels extrapolates, and a line through noisy data can
    leave the data's range far from it (measured: -3.2 on glossy where the
    reference is >= 0).  The fitted pixels are those the model weights >=
    ``min_weight`` (``Params.coverage_weight``: the same notion of "fitted,
    not extrapolated" as the coverage test of Sec. 3.5); each prediction is
    clipped per channel to [min, max] of their input colours.  Radiance
    inside the data's range is unchanged, so the paper's fit is kept wherever
    it interpolates; with non-negative input, every prediction is >= 0.
    Not in the paper.  A model with no fitted pixel is left unclipped.

    yk (c, n, 3) predictions, wsel (c, n) fit weights at k_opt, Yq (c, n, 3)
    the fitted colours.  Returns (c, n, 3).
    """
    sel = (wsel >= min_weight)[..., None]
    lo = np.where(sel, Yq, np.inf).min(axis=1, keepdims=True)
    hi = np.where(sel, Yq, -np.inf).max(axis=1, keepdims=True)
    ok = lo <= hi                                # else no fitted pixel: no bounds
    out = np.maximum(yk, np.where(ok, lo, -np.inf))
    return np.minimum(out, np.where(ok, hi, np.inf), out=out)


def predict_at_bandwidth(wk, X, beta, kk):
    """Each model's prediction and Eq. 13 weight at its chosen k_opt (Eq. 10).

    wk (c, K, n) regression weights, X (c, n, P), beta (c, K, P, 3), kk (c,)
    indices of k_opt (``choose_bandwidth``).  Returns the Eq. 13 weights
    w(i, j) + ``MODEL_WEIGHT_FLOOR`` (c, n) and the predictions y_ij (c, n, 3).
    """
    ar = np.arange(kk.size)
    wm = wk[ar, kk] + MODEL_WEIGHT_FLOOR
    yk = X @ beta[ar, kk]
    return wm, yk


def error_at_bandwidth(X, wfit, Yq, idx, pilots, Ainv, kk, err_t, data: RegressionData):
    """Eq. 12 error at k_opt, sum_t wei_t (bias_t^2 + Var_t) / sum_t wei_t,
    per window pixel, in the last iteration t = T.

    The terms of the earlier iterations are recomputed for k_opt only from
    the kept pilots (``pilots``, T entries) and the same (X^T W X +
    Lambda)^-1 (``Ainv`` (c, K, P, P)) instead of keeping every model's
    (K, n) errors.  X, wfit, Yq, idx as in ``window_inputs``; kk (c,);
    err_t (c, K, n) the last iteration's term.  Returns (c, n).
    """
    t = len(pilots) - 1
    weis = data.weis
    ar = np.arange(kk.size)
    ek = np.zeros((kk.size, X.shape[1]))
    if t > 0:
        sub = {"Ainv": Ainv[ar, kk][:, None]}
        wsub = wfit[ar, kk][:, None]
        for t2 in range(t):
            Pq, vq, uq = gather_pilot(pilots[t2], idx, data.var0, data.guide_var, kk)
            e2 = window_error_terms(X, wsub, Yq, Pq, vq, uq, data.ridge, sub)[1]
            ek += weis[t2] * e2[:, 0]
    ek += weis[t] * err_t[ar, kk]
    ek /= weis.sum()
    return ek


def prediction_parts(flat, wsel, yk, inside, lo: int, hi: int) -> list:
    """The Eq. 13 sums of a chunk's window predictions over the pixel range
    [lo, hi): ``[(("img_num", ch), part), ..., (("den", None), part)]`` with
    each part the bincount ``accumulate_predictions`` adds (see there for the
    arguments); :func:`apply_parts` adds them."""
    parts = [(("img_num", ch), np.bincount(flat - lo, weights=wsel * yk[..., ch][inside], minlength=hi - lo))
             for ch in range(3)]
    parts.append((("den", None), np.bincount(flat - lo, weights=wsel, minlength=hi - lo)))
    return parts


def variance_parts(flat, wk, var, inside, lo: int, hi: int) -> list:
    """The per-k variance sums of a chunk (``accumulate_variances``) as
    ``[(("v_num", kq), part), (("v_den", kq), part), ...]`` over [lo, hi)."""
    wv = wk + MODEL_WEIGHT_FLOOR
    parts = []
    for kq in range(wk.shape[1]):
        wsk = wv[:, kq][inside]
        parts.append((("v_num", kq), np.bincount(flat - lo, weights=wsk * np.minimum(var[:, kq][inside], 1e30),
                                                 minlength=hi - lo)))
        parts.append((("v_den", kq), np.bincount(flat - lo, weights=wsk, minlength=hi - lo)))
    return parts


def apply_parts(arrays, parts: list, lo: int) -> None:
    """``arrays[name][lo:lo + len(part), column] += part`` for every part
    (column None: a (H W,) array), in list order; ``arrays`` a dict or a
    :class:`WindowSums`.  Replaying a chunk's parts in chunk order gives the
    sums of a serial accumulation bit for bit."""
    for (name, col), part in parts:
        arr = arrays[name] if isinstance(arrays, dict) else getattr(arrays, name)
        target = arr if col is None else arr[:, col]
        target[lo:lo + part.size] += part


def accumulate_predictions(img_num, den, flat, wsel, yk, inside, lo: int, hi: int) -> None:
    """Add a chunk's window predictions to the Eq. 13 sums, in place:
    ``img_num[j] += w(i, j) y_ij`` and ``den[j] += w(i, j)`` over its models.

    img_num (H W, 3), den (H W,); flat (m,) pixel indices of the in-image
    window pixels, wsel (m,) their weights; yk (c, n, 3) predictions and
    inside (c, n) the mask that selects the m entries; [lo, hi) bounds flat.
    """
    apply_parts({"img_num": img_num, "den": den}, prediction_parts(flat, wsel, yk, inside, lo, hi), lo)


def accumulate_variances(v_num, v_den, flat, wk, var, inside, lo: int, hi: int) -> None:
    """Add a chunk's Var_t(j, k) (Eq. 11) to the per-k variance maps with the
    Eq. 13 weights of every candidate, in place (the Var_{t-1}(s, k) of the
    next iteration is v_num / v_den).

    v_num, v_den (H W, K) float32; wk, var (c, K, n); flat, inside, lo, hi as
    in ``accumulate_predictions``.  Variances are capped at 1e30 (float32).
    """
    apply_parts({"v_num": v_num, "v_den": v_den}, variance_parts(flat, wk, var, inside, lo, hi), lo)


def combine_models(img_num, den, y, input_weight: float):
    """Eq. 13, ``out_j = sum_i w(i, j) y_ij / sum_i w(i, j)``, with the pixel's
    own input y_j added at weight ``input_weight`` (at least
    ``FALLBACK_WEIGHT``, so pixels every model ignores keep their input).

    Choice (not in the paper): the models are sparse, so most pixels are
    predicted far from a centre; a pixel every covering model weights weakly
    would otherwise trust their extrapolations fully.  At 0.02, pixels some
    model weights >= 0.2 move < 10 % toward their input.

    img_num (H W, 3), den (H W,) sums of ``accumulate_predictions``, both
    overwritten (in place: no full-size temporaries); y (H, W, 3).  Returns
    out (H, W, 3) (a view of img_num) and the normaliser den + input_weight
    (H W,) (den itself).
    """
    dd = np.add(den, input_weight, out=den)
    for ch in range(3):
        img_num[:, ch] += input_weight * y[..., ch].ravel()
        img_num[:, ch] /= dd
    return img_num.reshape(y.shape), dd


def blend_variance(var0: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Variance of the input y_j for ``blend_input``: the larger of the
    pixel's own per-sample variance n Var_0 and its median over the 3 x 3
    neighbourhood (edge-replicated), divided by the pixel's n.  Why: a pixel's own sample variance is
    correlated with its own mean (a pixel that drew a bright sample has a
    large one), so weighting the input by it pulls bright pixels to the models
    and keeps dark ones: the image darkens (measured -2.2 % on cornell at
    8 spp, -5 % on glossy; docs/notes/rhf.md).  A mean over the neighbours
    would spread a firefly's huge variance onto them (they then trust models
    the firefly broke); the median of 9 ignores up to 4 such pixels.  The
    pixel's own estimate is kept where it is larger (the max), so a firefly
    itself is still known to be uncertain and goes to the models; only a
    pixel whose own samples happen to agree (an underestimated variance) is
    corrected.  var0, n (H, W) -> (H, W)."""
    nn = np.maximum(np.asarray(n, np.float64), 1.0)
    s2 = np.minimum(np.asarray(var0, np.float64) * nn, VAR_LIMIT)
    h, w = s2.shape
    p = np.pad(s2, 1, mode="edge")
    stack = np.stack([p[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)], axis=-1)
    return np.maximum(np.median(stack, axis=-1), s2) / nn


def blend_input(img_num, den, err_num, y, var0):
    """Eq. 13 output blended with the pixel's own input by inverse MSE.

    m_j = sum_i w(i, j) y_ij / sum_i w(i, j) (Eq. 13) has the estimated squared
    error E_j = sum_i w(i, j) e_ij / sum_i w(i, j) (Eq. 12 at k_opt, merged
    like Eq. 13); the input y_j is unbiased with variance V_j (Var_0 of
    Eq. 11).  The convex combination of two estimates with the least expected
    squared error, taking their errors as uncorrelated, is
    ``out = (1 - a) m + a y`` with ``a = E / (E + V)`` (inverse-MSE weights),
    and its error ``(1 - a)^2 E + a^2 V = E V / (E + V)``.

    Why (not in the paper): the models are sparse, so most pixels are
    predicted far from a centre; where the covering models fit the pixel
    badly (extrapolation, an edge the features miss) their bias makes E large
    and the pixel leans on its input; where they fit, E ~ the model variance
    << V and the input barely enters.  This replaces a fixed input weight
    (``input_blend = "fixed"``) with the method's own error estimate.  Where
    no model weights the pixel (den = 0) a = 1 (FALLBACK_WEIGHT); where E = V
    = 0 a = 0.

    img_num (H W, 3), den (H W,), err_num (H W,) sums of
    ``accumulate_predictions`` and of the weighted errors (overwritten);
    y (H, W, 3); var0 (H W,).  Returns out (H, W, 3) (a view of img_num) and
    the blended error (H W,).
    """
    eps = FALLBACK_WEIGHT
    dd = np.add(den, eps, out=den)
    E = np.add(err_num, eps * var0, out=err_num)
    E /= dd
    tot = E + var0
    a = np.divide(E, tot, out=np.zeros_like(E), where=tot > 0)
    a = np.where(den > eps, a, 1.0)                 # den was overwritten: den + eps
    for ch in range(3):
        yc = y[..., ch].ravel()
        m = img_num[:, ch]
        m += eps * yc
        m /= dd
        m += a * (yc - m)
    err = (1.0 - a) ** 2 * E + a * a * var0
    return img_num.reshape(y.shape), err


def regress_chunk(data: RegressionData, chunk: ModelChunk, pilots, Ainv, Ecum, k_idx,
                  sums: WindowSums, last: bool):
    """One chunk of models in iteration t = len(pilots): Eq. 2 fit, Eq. 11
    terms against ``pilots[-1]``, Eq. 12 accumulation into ``Ecum`` (N, K),
    Eq. 10 choice into ``k_idx`` (N,), and the Eq. 13 sums into ``sums``
    (all in place).  ``Ainv`` : the chunk's (X^T W X + Lambda)^-1 from an
    earlier iteration or None.  Returns Ainv to keep for the next iteration
    (None in the last).
    """
    Ainv, lo, parts = chunk_terms(data, chunk, pilots, Ainv, Ecum, k_idx, last)
    apply_parts(sums, parts, lo)
    return Ainv


def chunk_terms(data: RegressionData, chunk: ModelChunk, pilots, Ainv, Ecum, k_idx, last: bool):
    """:func:`regress_chunk` without the Eq. 13 sums: writes only the chunk's
    own rows of ``Ecum`` and ``k_idx`` and returns ``(Ainv, lo, parts)``, the
    sums as :func:`apply_parts` adds them, so chunks can run on several
    threads and be added in chunk order."""
    t = len(pilots) - 1
    idx, inside, X, wk, wfit, Yq = window_inputs(data, chunk)
    cache = {} if Ainv is None else {"Ainv": Ainv}
    Pq, vq, uq = gather_pilot(pilots[t], idx, data.var0, data.guide_var)
    beta, err_t, blk, var = window_error_terms(X, wfit, Yq, Pq, vq, uq, data.ridge, cache)
    del Pq, vq, uq
    ids = chunk.ids
    Ecum[ids] += data.weis[t] * blk                             # Eq. 12
    kk = choose_bandwidth(Ecum[ids])                            # Eq. 10
    k_idx[ids] = kk
    wm, yk = predict_at_bandwidth(wk, X, beta, kk)
    if data.clamp_weight is not None:
        yk = clamp_to_support(yk, wfit[np.arange(kk.size), kk], Yq, data.clamp_weight)
    flat = idx[inside]
    lo, hi = int(flat.min()), int(flat.max()) + 1
    wsel = wm[inside]
    parts = prediction_parts(flat, wsel, yk, inside, lo, hi)
    if not last and data.blend == "mse":
        parts.append((("err_num", None), np.bincount(flat - lo, weights=wsel * err_t[np.arange(kk.size), kk][inside],
                                                     minlength=hi - lo)))
    if last:
        ek = error_at_bandwidth(X, wfit, Yq, idx, pilots, cache["Ainv"], kk, err_t, data)
        parts.append((("err_num", None), np.bincount(flat - lo, weights=wsel * ek[inside], minlength=hi - lo)))
        return None, lo, parts
    parts += variance_parts(flat, wk, var, inside, lo, hi)
    return cache["Ainv"], lo, parts


def regression_pass(data: RegressionData, chunks: list, pilots: list, a_cache: list, Ecum,
                    k_idx, last: bool):
    """Iteration t = len(pilots) of Eq. 11-13 over every model chunk.

    pilots : the (y_{s-1}, Var_{s-1}) of iterations s = 1..t (``gather_pilot``);
    a_cache : per chunk (X^T W X + Lambda)^-1 or None, updated in place;
    Ecum (N, K) and k_idx (N,) updated in place (``regress_chunk``).
    The chunks run on :mod:`core.parallel`'s pool (:func:`chunk_terms`: each
    writes only its own models' rows) and their sums are added in chunk
    order, so the result is the same bits for any thread count.

    Returns the Eq. 13 image (H, W, 3) and, in the last iteration, the error
    map (H W,) (Eq. 12 at k_opt, merged with the Eq. 13 weights, the input's
    Var_0 at the input weight), otherwise the per-k variance maps Var_t
    (H, W, K) float32 (v_num / v_den where v_den > 0, else 0).
    """
    h, w = data.fhat.shape[:2]
    K = Ecum.shape[1]
    sums = WindowSums.zeros(h * w, K, last)

    def compute(gi):
        return gi, chunk_terms(data, chunks[gi], pilots, a_cache[gi], Ecum, k_idx, last)

    def reduce(out):
        gi, (ainv, lo, parts) = out
        apply_parts(sums, parts, lo)                            # in chunk order: the serial sums
        a_cache[gi] = ainv

    parallel.ordered_reduce(compute, reduce, range(len(chunks)), h * w < THREAD_MIN_PIXELS)
    if data.blend == "mse":
        img, err = blend_input(sums.img_num, sums.den, sums.err_num, data.y, data.var_blend)
        if last:
            return img, err
    else:
        img, dd = combine_models(sums.img_num, sums.den, data.y, data.input_weight)
        if last:
            return img, (sums.err_num + data.input_weight * data.var0) / dd
    np.divide(sums.v_num, sums.v_den, out=sums.v_num, where=sums.v_den > 0)
    return img, sums.v_num.reshape(h, w, K)


def fit_models(data: RegressionData, chunks: list, guide: np.ndarray, K: int):
    """The T iterations of the bandwidth selection (Eq. 11-12, T =
    ``data.weis.size``), each a ``regression_pass``; the first pilot y_0 is
    the colour guide M with Var_0, the next ones the previous pass's output
    and variance maps.  Only the error estimate and k_opt are iterated: every
    pass fits Y.

    Choice: y_{t-1} is the whole Eq. 13 image of the previous pass (each
    model with the k minimising the Eq. 12 error so far), not the window's
    own H y, which would make bias_2 = H H y - H y = 0.

    Returns image (H, W, 3), error map (H W,), Ecum (N, K) the
    wei-weighted sum of the Eq. 10 block errors and k_idx (N,) the chosen
    candidate per model.
    """
    n_models = data.cy.size
    T = data.weis.size
    Ecum = np.zeros((n_models, K))
    k_idx = np.zeros(n_models, np.int64)
    pilots = [(guide, None)]
    a_cache = [None] * len(chunks)
    for t in range(T):
        last = t == T - 1
        img, second = regression_pass(data, chunks, pilots, a_cache, Ecum, k_idx, last)
        if not last:
            pilots.append((img, second))
    return img, second, Ecum, k_idx


def finalize_output(y_in, img, err_map, zero_var):
    """Final guards: zero-variance channels return their input unchanged
    (error 0 there), non-finite values become 0 (image) or VAR_LIMIT
    (error), magnitudes are clipped.  y_in, img (H, W, 3), err_map (H W,),
    zero_var (H, W, 3) bool -> image (H, W, 3), error (H, W)."""
    h, w = img.shape[:2]
    out = np.where(zero_var, y_in, img)
    out = np.clip(np.where(np.isfinite(out), out, 0.0), -VALUE_LIMIT, VALUE_LIMIT)
    err = err_map.reshape(h, w) * (1.0 - zero_var.mean(axis=2))
    err = np.clip(np.where(np.isfinite(err), err, VAR_LIMIT), 0.0, VAR_LIMIT)
    return out, err


def active_features(fhat: np.ndarray) -> int:
    """Model dimension d: the 2 pixel coordinates plus the prefiltered feature
    channels that vary over the image (range > 1e-6), at most D = 9; 0 for an
    empty image.  (H, W, 7) -> int."""
    if not fhat.shape[0] * fhat.shape[1]:
        return 0
    return 2 + int(sum(np.ptp(fhat[..., c]) > 1e-6 for c in range(fhat.shape[2])))


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
    RHFOutput; its error is the Eq. 12 error (bias^2 + variance, RGB mean)
    at each model's chosen k, averaged with the Eq. 13 weights.
    """
    params = params or Params()
    t0 = time.perf_counter()
    ks = parse_bandwidths(params.bandwidths)
    y_in, y, vy, nn, bad, zero_var, vy_filled = prepare_color(color, color_var, n, zero_var)
    del color_var
    F7, V7 = prepare_features(feats, feat_var, nn, bad)
    t_prep = time.perf_counter()

    fhat = prefilter_features(F7, V7, params)                   # Sec. 3.2, Eq. 3-7
    del F7, V7
    t_feat = time.perf_counter()
    M, vM = colour_guide(y, vy, fhat, params)                   # Sec. 3.3, Eq. 8
    var0 = vy.mean(axis=2).ravel()                              # Var_0 of Eq. 11
    var_blend = (blend_variance(var0.reshape(nn.shape), nn).ravel()
                 if params.input_blend == "mse" else None)
    del nn
    del vy
    gra = feature_gradient(fhat)                                # Eq. 14
    cy, cx, cr, detailed = select_centers(gra, params)          # Sec. 3.5
    t_guide = time.perf_counter()

    fhat = fhat.astype(np.float32)            # design features (Eq. 2); halves memory
    models = place_models(M, vM, cy, cx, cr, ks, params)        # Sec. 3.3, 3.5
    data = RegressionData(
        fhat=fhat, target=(M if params.regress_guide else y).reshape(-1, 3), y=y,
        valid=(~bad).ravel(), var0=var0,
        guide_var=(vM.mean(axis=2, dtype=np.float64).ravel()
                   if params.bias_noise_correction else None),
        cy=models.cy, cx=models.cx, weis=iteration_weights(max(1, int(params.iterations))),
        ridge=params.ridge, input_weight=max(float(params.input_weight), FALLBACK_WEIGHT),
        blend=str(params.input_blend), var_blend=var_blend,
        clamp_weight=float(params.coverage_weight) if params.clamp_predictions else None)
    del vM
    img, err_map, Ecum, k_idx = fit_models(data, models.chunks, M, ks.size)  # Eq. 9-13
    t_reg = time.perf_counter()

    out, err = finalize_output(y_in, img, err_map, zero_var)
    info = _diagnostics(models, detailed, ks[k_idx], bad, vy_filled, active_features(fhat),
                        params)
    info.update(seconds_prepare=t_prep - t0, seconds_features=t_feat - t_prep,
                seconds_guide=t_guide - t_feat, seconds_regression=t_reg - t_guide)
    return RHFOutput(out, err, fhat, M, gra, models.cy, models.cx, models.cr, ks[k_idx],
                     Ecum / data.weis.sum(), detailed, info)


def _diagnostics(models: ModelSet, detailed, k_opt, bad, vy_filled: float, active: int,
                 params: Params) -> dict:
    """Scalar diagnostics of a reconstruction (``RHFOutput.info``)."""
    n_models = models.cy.size
    return {
        "models": int(n_models),
        "models_small": int((models.cr == min(params.radius_small, params.radius_medium,
                                              params.radius_large)).sum()),
        "models_fill": int(models.fill_models),
        "uncovered_fraction": models.uncovered_fraction,
        "detailed_patch_fraction": float(detailed.mean()) if detailed.size else 0.0,
        "pixels_per_model": float(bad.size / max(n_models, 1)),
        "mean_k": float(k_opt.mean()) if n_models else 0.0,
        "missing_pixels": int(bad.sum()),
        "variance_filled_fraction": vy_filled,
        "active_features": int(active),
    }


# ------------------------------------------------------------- method interface
def _feature_arrays(buf: Buffers):
    feats, fvars = {}, {}
    for name, _ in FEATURE_ORDER:
        if name in buf.features:
            feats[name] = buf.feature(name)
            fvars[name] = (lambda st=buf.features[name]: buf.variance_of_mean(st))
    return feats, fvars


def _result(res: RHFOutput, kept: np.ndarray | None = None) -> MethodResult:
    """MethodResult of a reconstruction; ``dimension`` is the active feature
    count (the model dimension d of ``sample_map``).  ``kept`` (H, W), the
    kept noise (:func:`core.errormap.retained_noise`), is added to the error
    map only; ``fit`` holds the Eq. 12 error (H, W), which the sampler reads."""
    error = res.error if kept is None else res.error + kept
    return MethodResult(res.image, error, res.info,
                        dimension=float(res.info["active_features"]), fit=res.error)


def reconstruct(buf: Buffers, params: Params | None = None) -> MethodResult:
    """RHF reconstruction of the accumulated buffers (Liu et al. 2018).

    Reads the colour mean and variance of the mean, the ``PASSES`` features
    and their variances, and n.  See ``rhf_reconstruct``; the error is the
    Eq. 12 estimate (bias^2 + variance) at each pixel's chosen k, averaged over
    the overlapping models with the Eq. 13 weights, plus the kept noise
    (``Params.kept_noise``); ``dimension`` is the number of active regression
    features.
    """
    params = params or Params()
    feats, fvars = _feature_arrays(buf)
    cvar = [buf.variance_of_mean()]
    zero = np.isfinite(buf.color.mean)
    zero &= cvar[0] == 0                   # k >= 2, n > 0 and M2 = 0 (cvar is inf otherwise)
    # handed over as a callable (list.pop) so that rhf_reconstruct holds the
    # only reference and frees it once the variance is prepared
    res = rhf_reconstruct(buf.color.mean, cvar.pop, feats, fvars, buf.n, params, zero_var=zero)
    kept = retained_noise(res.image, buf.color.mean, buf.calibrated_variance()) if params.kept_noise else None
    return _result(res, kept)


def map_result(buf: Buffers, params: Params | None = None) -> MethodResult:
    """The reconstruction the loop hands :func:`sample_map` between
    iterations (the optional member of ``core.method.Method``):
    :func:`reconstruct` without the kept noise, which only the error map
    shown and stored at the end reads (the sampler reads the Eq. 12
    estimate); the same image and the same sample map, without the
    calibrated variance the kept noise needs."""
    return without_kept_noise(reconstruct, Params, buf, params)


def sample_map(buf: Buffers, result: MethodResult, budget: int, params: Params | None,
               state: dict) -> np.ndarray:
    """New samples per pixel for the next iteration, summing to ``budget``.

    The paper stops at reconstruction; sampling follows LP (Moon et al. 2015,
    Sec. 5.2): the expected error reduction of one more sample at pixel i is
    ``err_i * n_i^(-4/(d+4))`` (``core.method.sampling_gain``), err the Eq. 12
    error (``result.fit``; the error map, kept noise included, otherwise), d =
    ``result.dimension``, the number of active regression features
    (``DEFAULT_DIMENSION`` = D = 9 when None), made relative by
    ``/(lum(image_i)^2 + 0.001)``; samples are allocated in proportion
    (largest-remainder rounding, exact sum).  Pixels with no samples yet use
    n = 1.  ``state`` is unused (kept for the interface).
    """
    d = DEFAULT_DIMENSION if result.dimension is None else float(result.dimension)
    err = result.fit if isinstance(result.fit, np.ndarray) and result.fit.shape == result.error.shape \
        else result.error
    gain = sampling_gain(err, buf.n, d)
    rho = relative_error(gain, result.image, 1e-3)
    return allocate(rho, int(budget))


def denoise(color, color_var, features=None, feature_var=None, n=None,
            params=None) -> MethodResult:
    """RHF on plain arrays.

    color, color_var : (H, W, 3) pixel means and variance of the means (+inf =
        unknown, see the module notes); features : dict name -> (H, W, C) of
        'normal', 'albedo', 'depth' (a missing one is a constant feature);
        feature_var : their variances (default 0, i.e. noise-free features);
        n : (H, W) or scalar samples per pixel (default 1); params : Params or
        dict (``params_from_dict``).
    """
    if isinstance(params, dict):
        params = params_from_dict(Params, params)
    if n is not None and np.ndim(n) == 0:
        n = np.full(np.shape(color)[:2], float(n))
    res = rhf_reconstruct(color, color_var, features, feature_var, n, params)
    kept = None
    if (params or Params()).kept_noise:
        kept = retained_noise(res.image, color, color_var)
    return _result(res, kept)

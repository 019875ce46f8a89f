"""LP: adaptive rendering with linear predictions (Moon, Iglesias-Guitian, Yoon, Mitchell 2015).

What: a first-order model ``f(x_i) ~ f(x_c) + grad f(x_c)^T (x_i - x_c)``
(Eq. 1) in the features x = (pixel position, depth, normal, albedo) (Table 1)
is fitted by least squares at a sparse set of *centre* pixels c, inside a
prediction window ``k(r) = (2r+1)^2`` whose size is chosen per centre by a
recursive estimate of the prediction error, and it predicts every pixel of
that window.  Why: one model predicts up to (2R+1)^2 pixels, so the expensive
fit and error estimate run at a few percent of the pixels (paper: 4.7-18.9 %),
and the window is only as large as the linear model stays accurate; the same
error estimates drive adaptive sampling.

Equations (Moon et al. 2015) and where they are computed:

* Eq. 1, the prediction ``f_hat(x_i) = beta_c^T z_i`` with
  ``z_i = (1, x_i - x_c)`` in TSVD coordinates: :meth:`core.lp_solve.Design.predict`;
  overlapping predictions are averaged by :class:`_Accumulator` (Sec. 5.1),
  with the mean offsets of :func:`_mean_offsets`.
* Eq. 2, the optimal window ``k_opt = argmin_k xi_c(k)`` with Eq. 4's
  estimate substituted: :func:`select_windows`, :func:`_optimal_models`.
* Eq. 3, recursive least squares from ``beta(0) = (y_c, 0, ..., 0)``,
  ``P(0) = I / delta`` (Sec. 7), solved at the ring boundaries as the
  equivalent regularised normal equations: :func:`core.lp_solve.ring_fits`.
* Eq. 4-5, the recursive prediction error (the model of k(r-1) tested on the
  8r pixels of ring r), and Eq. 7, its leave-one-out initialisation on k(1):
  :func:`core.lp_solve.ring_fits`; Eq. 4's normalisation: :func:`_estimated_errors`.
* Sec. 5.1, centre placement with granularities g, g/2, g/4, ...:
  :func:`_place_centres`.
* Sec. 5.2, adaptive sampling ``Delta n_i ~ xi n_i^(-4/(d+4)) / (f_hat^2 +
  epsilon)``: :func:`sample_map`.
* Sec. 7, the features normalised and prefiltered per filtering window by a
  truncated SVD (after Moon et al. 2014): :func:`feature_transform`.

(Eq. 6, the temporal extension of Sec. 6, is ``core/temporal.py``.)

Threads (:mod:`core.parallel`): the chunks of centres of a pass, the mean
offsets' re-blend, the input packing and the per-pixel passes run as pieces
on the shared pool.  The pieces are cut by the shape and parameters only;
each chunk has its own workspace and returns its sums over its band of rows,
which are added one chunk at a time in chunk order (:func:`core.parallel.ordered_reduce`),
so the output is bit-identical for any thread count and to the serial order.
Frames below ``THREAD_MIN_PIXELS`` run inline.

Choices where the paper leaves room (each also stated where it is made):

* **Error estimate against the truth.**  Eq. 2 defines the prediction error
  against the ground truth f, and ``xi(k(0))`` is initialised with the variance
  of the centre's mean (the error of the input against f), but the test terms
  of Eq. 5 and Eq. 7 compare predictions with *noisy* pixels y_i, so their
  expectation carries an extra ``Var(y_i)``: taken literally, every window
  larger than one pixel looks worse than the unfiltered pixel by about the
  noise variance and the method hardly filters.  By default
  (``Params.variance_corrected = True``) each squared test residual has the
  test pixel's estimated variance of the mean subtracted, which makes Eq. 4 an
  unbiased estimate of Eq. 2's error and comparable with ``xi(k(0))``; set it
  False for the literal equations.  The variance enters through one place,
  :func:`_inputs`.
* **Where the recursion starts.**  Eq. 7 at k(1) (9 pixels) is under- or
  exactly determined for 8-10 unknowns; the recursion starts at the first
  window with >= 2 usable pixels per unknown
  (:func:`core.lp_solve.start_rings`), smaller windows are no candidates.
* **Estimates >= 0, bounded by the model's variance.**  Negative estimates
  (noise) count as 0, and no window's error is taken below its own variance
  ``s_mean dof / |k(r)|`` (:func:`_estimated_errors`, :func:`_error_floor`);
  the chosen window's bounded estimate is the error map, never clipped to 0.
* **xi(k(0))** is ``max(var_c, median of the 3x3 variances)``: the centre's
  estimate alone (3 degrees of freedom) wins Eq. 2 by chance where it came
  out low (:func:`_window_observations`).
* **Ties** go to the larger window, statistically: the largest window within
  one standard error of the minimum (:func:`select_windows`).
* **Channels.**  The paper applies the method "to each channel independently":
  the models, errors and optimal windows are per RGB channel; the normal
  matrix (shared by the channels) is built once.
* **Coverage (Sec. 5.1).**  The paper counts a pixel as predicted when one
  model covers it.  Here all three channels must cover it with tapers
  (:func:`taper`) summing to at least ``COVER_WEIGHT`` = 0.5 (several
  overlapping models: the first grid of spacing 2R + 1 tiles the image with
  abutting windows, whose seams no blend can hide) and with a blended error
  of at most 4x the typical variance around it (a highlight's model must not
  stand in for its dark neighbours) (:meth:`_Accumulator.predicted`).
* **Blending** (Sec. 5.1 "simply averages" the overlapping predictions):
  weighted by a separable taper whose value, slope and curvature reach 0 at
  the window border (:func:`taper`), over the model's estimated error
  (:func:`blend_weights`), against seams and against a highlight's model
  overriding its neighbours'.
* **Mean-preserving blend.**  After the last pass every model's intercept
  is moved by its residual weighted with its share of the final blend
  (at most ``OFFSET_LIMIT`` = 10 standard errors of its window mean), so the
  blend keeps the input's sum instead of losing the energy of bright pixels
  that the models spread over their windows (:func:`_mean_offsets`).
* **The pixel's own value** enters where it lies more than
  ``OUTLIER_SIGMA`` = 10 typical standard deviations from the blend (a
  highlight smaller than any window), by the same inverse-error weighting,
  with the models' error there estimated from the residual (:func:`_own_pixel`).
  It keeps a one-pixel highlight the samples resolve, not a firefly.
* **Non-negative output.**  Predictions are bounded below by
  ``min(0, window minimum)`` (:func:`_lower_bound`; the paper is silent).
* **TSVD rank rule** (after the authors' WLR code, Moon et al. 2014): inside
  each filtering window the features are centred on the window mean, scaled
  (position by 1/R, depth by 1/max|d - mean|, normal and albedo by
  1/max||v - mean||, each maximum floored at ``svd_floor`` = 0.01), and the
  singular values ``sigma_j`` of that ``K x d`` matrix are kept when
  ``sigma_j > svd_floor + svd_noise_factor * ||E||_2``, where E is the feature
  noise matrix (its entries' variances are the scaled feature variances of the
  mean) and ``||E||_2 ~ 2 ||E||_F / sqrt(rank)``; the ``min_rank`` (2) leading
  directions are always kept.  Constant or degenerate features give zero
  singular values and drop out, so the model size follows the scene.
* **Window normalisation at borders.**  Eq. 4 divides by ``(2r+1)^2``; windows
  cut by the image border or holding missing pixels divide by the number of
  pixels actually in ``k(r)`` (the mean the error is defined as).
* **Granularity sequence.**  g, g // 2, g // 4, ..., 1 (integer halving; the
  last pass tests every pixel, which guarantees full coverage); g = 0 means the
  filtering window width 2R+1 (the paper's example).
* **Sampling exponent.**  ``n_i^(-4/(d_c+4))`` uses the TSVD rank d_c of each
  covering model's centre (Sec. 5.2 cites Moon et al. 2014 for the rate); the
  reported model dimension (``MethodResult.dimension``) is the mean rank.
* **Missing data.**  Pixels with no samples, or non-finite colour or features
  (or values beyond 1e150, whose squares overflow), enter no fit and no error
  sum; they are still predicted (from their features, or by the intercept when
  their features are non-finite).  A non-finite or negative variance counts as
  unknown.
* **One subset (k < 2, variance +inf).**  ``xi(k(0))`` is +inf, so the centre
  never keeps its unfiltered value while a larger window has a finite error,
  and no variance is subtracted from its test terms (the literal Eq. 5/7).
  Where no finite estimate exists at all, the reported error is the largest
  finite error of the image (0 if there is none).

Measurements and design notes: docs/notes/lp.md
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, fields
from functools import lru_cache, partial

import numpy as np

from . import parallel
from .buffers import Buffers
from .errormap import retained_noise, without_kept_noise
from .filters import box_sum
from .lp_solve import Design, ring_fits, ring_layout
from .method import MethodResult, allocate, gain_exponent, param, params_from_dict

NAME = "lp"
PASSES = ("normal", "albedo", "depth")
ADAPTIVE = True
#: sample_map reuses the reconstruction's fit (``MethodResult.fit``)
SAMPLER_USES_RESULT = True

#: feature groups in the order of the design matrix columns after position
_GROUPS = ("depth", "normal", "albedo")
_GROUP_CHANNELS = {"depth": 1, "normal": 3, "albedo": 3}
#: magnitude from which a colour or feature value counts as missing (its square,
#: summed over a window, would overflow float64)
_HUGE = 1e150


@dataclass
class Params:
    """Parameters of LP with the paper's defaults (Moon et al. 2015, Sec. 7)."""

    radius: int = param(
        9, "half width R of the filtering window (paper: 9, i.e. 19x19): the largest prediction "
        "window; larger smooths more and costs ~R^2 more time per centre", 1, 15, label="Window Radius")
    granularity: int = param(
        0, "spacing g of the first centre-pixel grid (Sec. 5.1), halved each pass; 0 = window "
        "width 2R+1 (paper); larger tries fewer, bigger models first (faster, maybe coarser)", 0, 256, label="Centre Spacing")
    delta: float = param(
        1e-3, "RLS initial confidence delta, P(0) = I/delta (paper: 0.001); larger regularises "
        "the models towards the centre value (stabler, more biased)", 1e-9, 1.0, label="Initial Confidence")
    epsilon: float = param(
        1e-3, "epsilon of the relative error xi/(f^2 + epsilon) that drives adaptive sampling "
        "(paper: 0.001); larger sends fewer samples to dark pixels", 1e-8, 1.0, label="Error Epsilon")
    svd_floor: float = param(
        0.01, "constant part of the truncated-SVD threshold on normalised feature singular values "
        "(Moon 2014: 0.01); larger drops more feature directions (faster, less detail)", 0.0, 10.0, label="Feature Threshold")
    svd_noise_factor: float = param(
        2.0, "TSVD threshold multiple of the feature-noise spectral norm (Moon 2014: 2); larger "
        "ignores noisier features (robust to DoF/motion noise, may lose edges)", 0.0, 100.0, label="Feature Noise Factor")
    min_rank: int = param(
        2, "feature directions always kept by the TSVD (Moon 2014: 2, the screen plane); "
        "smaller gives smaller, faster but blurrier models", 0, 9, label="Min Feature Rank")
    variance_corrected: bool = param(
        True, "subtract the test pixels' variance from the Eq. 5/7 errors so they estimate the "
        "error against the truth like xi(k(0)); off = literal paper (filters far less)", 0, 1, label="Variance Correction")
    chunk: int = param(
        0, "centre pixels processed per vectorised batch (0 = auto: pixels / 1024, "
        "between 32 and 256, so the workspace stays under ~80 bytes per pixel); "
        "larger has less Python overhead but uses ~80 KB more memory per centre", 0, 65536, label="Batch Size")
    kept_noise: bool = param(
        True, "add to the error map the noise the fit keeps from noisy features (defocus, motion), "
        "which Eq. 4-7 cannot see (core/errormap.py); off = the paper's estimate alone. The image "
        "and the sampling do not change", 0, 1, label="Kept Noise in Error")


@dataclass
class LPFit:
    """Everything LP computes for one frame.

    image : (H, W, 3) float64 reconstruction (average of the overlapping predictions).
    error : (H, W) float64 estimated squared error xi_c(k_opt) of the models
        covering each pixel, blended with their weights (:func:`blend_weights`),
        averaged over RGB, >= 0, finite.
    delta_error : (H, W, 3) float64 ``xi_c(k_opt) n_i^(-4/(d_c+4))`` (Sec. 5.2)
        blended over the covering models, per channel.
    radius : (H, W) float64 mean optimal radius r_opt of the covering models.
    centers : (M, 2) int64 (row, column) of the centre pixels, in creation order.
    center_radius : (M, 3) int64 optimal ring r_opt per channel (k_opt = (2 r_opt + 1)^2).
    center_rank : (M,) int64 TSVD rank d_c of each centre's features.
    center_error : (M, 3) float64 xi_c(k_opt) per channel.
    passes : int number of granularity passes run.
    models : dict or None, only with ``keep_models``: the RLS state of every
        centre at its optimal window, for a temporal extension (Eq. 6):
        ``beta`` (M, 3, D+1) coefficients, ``P`` (M, 3, D+1, D+1) inverse
        covariance ``(delta I + X^T X)^-1``, ``transform`` (M, D, D) feature map
        (z = [1, (x - x_c) @ transform]), ``center_features`` (M, D) raw x_c
        (position columns are pixel offsets, so 0); D is the raw feature count
        (position, depth, normal, albedo), and entries beyond a centre's rank
        d_c (``center_rank``) are zero; ``offset`` (M, 3) the blend's mean
        offset of each model (:func:`_mean_offsets`, not in ``beta``).
    """

    image: np.ndarray
    error: np.ndarray
    delta_error: np.ndarray
    radius: np.ndarray
    centers: np.ndarray
    center_radius: np.ndarray
    center_rank: np.ndarray
    center_error: np.ndarray
    passes: int
    models: dict | None = None

    @property
    def center_fraction(self) -> float:
        h, w = self.radius.shape
        return float(len(self.centers)) / float(max(h * w, 1))


# --------------------------------------------------------------------------- features
def feature_transform(feats: np.ndarray, valid: np.ndarray, noise_sum: np.ndarray,
                      groups, radius: int, svd_floor: float = 0.01,
                      svd_noise_factor: float = 2.0, min_rank: int = 2, work: np.ndarray | None = None):
    """Normalisation and truncated-SVD prefilter of the features of N filtering
    windows (Sec. 7 of Moon et al. 2015, following Moon et al. 2014).

    Parameters
    ----------
    feats : (N, D, K) float64
        Raw features of the K window pixels (pixel 0 the centre); rows 0-1 are
        the pixel offsets (dy, dx) from the centre.  Finite.
    valid : (N, K) float64 in {0, 1}
        1 where the pixel's features are usable.
    noise_sum : (N, G) float64
        Per window and feature group, the variance of the feature means summed
        over the group's channels and the window's valid pixels (0 where
        unknown): ``||E||_F^2`` of the unscaled group.  Finite, >= 0.
    groups : sequence of G (start, stop) row ranges, one per feature group
        (depth, normal, albedo); rows 0-1 (position) are scaled by 1/R and
        carry no noise.
    radius : int
        R (paper: 9).
    svd_floor, svd_noise_factor, min_rank :
        The rank rule (Moon 2014 code: 0.01, 2, 2), see the module docstring.
    work : (N, D, K) float64 scratch array or None.

    Returns
    -------
    transform : (N, D, D) float64
        ``z = transform^T (x - x_c)`` gives the prefiltered coordinates; the
        scaling is folded in and column j is zero when direction j is dropped.
        Kept directions come first (descending singular value).
    rank : (N,) int64
        Local dimensionality d_c (number of kept directions).
    sigma : (N, D) float64
        Singular values of the centred, scaled window feature matrix, descending.
    tol : (N,) float64
        Threshold ``svd_floor + svd_noise_factor * 2 ||E||_F / sqrt(rank0)``
        (rank0: numerical rank of the window's features).
    """
    n, d, k = feats.shape
    m0 = np.maximum(valid.sum(axis=1), 1.0)
    mean = np.matmul(feats, valid[:, :, None])[..., 0] / m0[:, None]     # (N, D)
    u = np.empty_like(feats) if work is None else work
    np.subtract(feats, mean[:, :, None], out=u)
    if not valid.all():
        u *= valid[:, None, :]
    scale = np.empty((n, d))
    scale[:, :2] = 1.0 / max(int(radius), 1)
    floor = svd_floor if svd_floor > 0 else 1e-12
    for (lo, hi) in groups:
        part = u[:, lo:hi]
        dist = np.sqrt(np.einsum("ngk,ngk->nk", part, part).max(axis=1))
        scale[:, lo:hi] = (1.0 / np.maximum(dist, floor))[:, None]
    u *= scale[:, :, None]
    cov = np.matmul(u, np.swapaxes(u, 1, 2))
    lam, vec = np.linalg.eigh(cov)
    lam, vec = lam[:, ::-1], vec[:, :, ::-1]
    sigma = np.sqrt(np.maximum(lam, 0.0))
    if groups:
        gscale2 = np.stack([scale[:, lo] ** 2 for (lo, _) in groups], axis=1)   # (N, G)
        e_fro = np.sqrt(np.maximum((noise_sum * gscale2).sum(axis=1), 0.0))
    else:
        e_fro = np.zeros(n)
    rank0 = (sigma > 1e-9 * np.maximum(sigma[:, :1], 1e-300)).sum(axis=1)
    tol = svd_floor + svd_noise_factor * 2.0 * e_fro / np.sqrt(np.maximum(rank0, 1))
    keep = sigma > tol[:, None]
    forced = np.arange(d)[None, :] < np.minimum(int(min_rank), rank0)[:, None]
    # kept directions form a prefix (sigma is sorted); make that exact
    keep = np.cumprod(keep | forced, axis=1).astype(bool)
    rank = keep.sum(axis=1).astype(np.int64)
    transform = scale[:, :, None] * vec * keep[:, None, :]
    return transform, rank, sigma, tol


# ---------------------------------------------------------------------- pixel packing
class _Frame:
    """The inputs of one frame, sanitised and stored plane by plane over the
    padded frame (``(ncol, Hp * Wp)``), so a window gather is one ``np.take``.

    Window planes: features (D - 2) | var0 (3, the variance of the mean, +inf
    where unknown: ``xi(k(0))`` of Sec. 7 at the centre and, where finite, the
    amount Eq. 5/7 subtract) | y (3) | w (fit weight) | fvalid.  Other planes
    (read per pixel or at centres only): ``logn`` (log of the samples, >= 0)
    and ``centre``: per feature group, the window sum of its variance (box
    filter, for the TSVD threshold).
    """

    def __init__(self, color, color_var, features, feature_var, n, radius, subtract, origin=0):
        h, w = color.shape[:2]
        r = self.pad = int(radius)
        self.h, self.w = h, w
        self.origin = int(origin)      # the frame's row 0 in the whole image (:func:`fit_band`)
        self.hp, self.wp = h + 2 * r, w + 2 * r
        names = [g for g in _GROUPS if g in features]
        cols, groups = 2, []
        for g in names:
            groups.append((cols, cols + _GROUP_CHANNELS[g]))
            cols += _GROUP_CHANNELS[g]
        self.groups, self.names, self.dim = groups, names, cols
        nf = cols - 2
        self.c_v, self.c_y, self.c_w, self.c_f = nf, nf + 3, nf + 6, nf + 7
        self.ncol = nf + 8
        self.subtract = bool(subtract)
        planes = np.zeros((self.ncol, self.hp, self.wp))
        centre = np.zeros((len(groups), self.hp, self.wp))
        inner = planes[:, r:r + h, r:r + w]
        noise = np.zeros((len(groups), h, w))
        logn = np.zeros((self.hp, self.wp))
        f_in, fv_in = [], []
        for g, (lo, hi) in zip(names, groups):
            f = np.asarray(features[g]).reshape(h, w, -1)       # converted band by band
            if f.shape[-1] < hi - lo:
                raise ValueError(f"feature {g!r} needs {hi - lo} channels, got {f.shape[-1]}")
            f_in.append(f)
            fv = feature_var.get(g) if feature_var else None
            fv_in.append(None if fv is None else np.asarray(fv).reshape(h, w, -1))
        color = np.asarray(color)
        n_in = None if n is None else np.broadcast_to(np.asarray(n), (h, w))
        var_in = np.broadcast_to(np.asarray(color_var), (h, w, 3))

        def band(rows):
            # every plane of rows y0 .. y1 (per pixel: bands on the pool, no full-size temporaries)
            y0, y1 = rows
            ins = inner[:, y0:y1]
            fvalid = np.ones((y1 - y0, w), bool)
            with np.errstate(invalid="ignore"):
                for gi, ((lo, hi), f, fv) in enumerate(zip(groups, f_in, fv_in)):
                    f = np.moveaxis(np.asarray(f[y0:y1, :, :hi - lo], np.float64), -1, 0)
                    ok = (np.abs(f) < _HUGE).all(axis=0)         # finite, squares stay finite
                    fvalid &= ok
                    np.copyto(ins[lo - 2:hi - 2], f, where=ok)
                    if fv is not None:
                        fv = np.asarray(fv[y0:y1, :, :hi - lo], np.float64)
                        noise[gi, y0:y1] = np.where((fv > 0) & (fv < _HUGE), fv, 0.0).sum(axis=-1)
            ins[:nf] *= fvalid
            col = np.moveaxis(np.asarray(color[y0:y1], np.float64), -1, 0)
            nn = np.ones((y1 - y0, w)) if n_in is None else np.asarray(n_in[y0:y1], np.float64)
            nn = np.where(np.isfinite(nn), nn, 0.0)
            with np.errstate(invalid="ignore"):
                cvalid = (np.abs(col) < _HUGE).all(axis=0) & (nn > 0)
            np.copyto(ins[self.c_y:self.c_y + 3], col, where=cvalid)
            var = np.moveaxis(np.asarray(var_in[y0:y1], np.float64), -1, 0)
            with np.errstate(invalid="ignore"):
                known = (var >= 0) & (var < _HUGE * _HUGE) & cvalid
            ins[self.c_v:self.c_v + 3] = np.inf
            np.copyto(ins[self.c_v:self.c_v + 3], var, where=known)
            ins[self.c_w] = cvalid & fvalid
            ins[self.c_f] = fvalid
            # log max(n, 1) (0 in the padding): all that Sec. 5.2's n_i^(-4/(d_c+4)) needs
            logn[r + y0:r + y1, r:r + w] = np.log(np.maximum(nn, 1.0))
            noise[:, y0:y1] *= fvalid

        parallel.run_bands(band, h, _BAND_ROWS, THREAD_MIN_PIXELS, w)
        self.logn = logn.ravel()
        # the typical variance around each pixel: Sec. 5.1's coverage test and xi(k(0))
        # (float32: a threshold, 12 bytes per pixel)
        typical = np.zeros((3, self.hp, self.wp), np.float32)
        _median3(inner[self.c_v:self.c_v + 3], out=typical[:, r:r + h, r:r + w])
        self.var_typical = typical.reshape(3, -1)
        # the feature-noise window sums, one group per piece
        parallel.map_ordered(lambda gi: _box_sum(np.pad(noise[gi], r), r, out=centre[gi]), range(len(groups)),
                             min_items=2 if h * w >= THREAD_MIN_PIXELS else len(groups) + 1)
        self.planes = planes.reshape(self.ncol, self.hp * self.wp)
        self.centre = centre.reshape(len(centre), self.hp * self.wp)

    def flat(self, rows, cols):
        return (rows + self.pad) * self.wp + (cols + self.pad)

    def release(self):
        self.planes = self.centre = self.logn = self.var_typical = None


def _median3(planes: np.ndarray, out: np.ndarray, band: int = 64) -> np.ndarray:
    """Median over each pixel's 3x3 neighbourhood (edges replicated) of
    (C, H, W) planes into ``out`` (C, H, W), channel by channel and in bands
    of rows (bounded temporaries, on :mod:`core.parallel`'s pool: every band
    writes only its own rows); +inf entries (unknown) sort last."""
    c, h, w = planes.shape

    def piece(job):
        i, (y0, y1) = job
        rows = np.clip(np.arange(y0 - 1, y1 + 1), 0, h - 1)
        pad = np.pad(planes[i, rows], ((0, 0), (1, 1)), mode="edge")
        stack = np.stack([pad[a:a + y1 - y0, b:b + w] for a in range(3) for b in range(3)])
        out[i, y0:y1] = np.median(stack, axis=0)

    jobs = [(i, b) for i in range(c) for b in parallel.bands(h, band)]
    parallel.map_ordered(piece, jobs, min_items=2 if h * w >= THREAD_MIN_PIXELS else len(jobs) + 1)
    return out


def _box_sum(plane: np.ndarray, r: int, out: np.ndarray | None = None) -> np.ndarray:
    """Sum over the (2r+1)^2 window around every pixel of a plane zero-padded
    by r (written into ``out`` when given; 0 in the padding); >= 0 for
    non-negative input.  Feeds the TSVD threshold's ``||E||_F`` (Sec. 7).

    By :func:`core.filters.box_sum` (binary doubling, no subtraction of
    partial sums): each sum depends on its window alone, also in its
    rounding, so a band of rows packed on its own (:func:`fit_band`) gives
    the bits of the whole frame; a summed-area table's rounding depends on
    every row above.
    """
    hp, wp = plane.shape
    out = np.zeros((hp, wp)) if out is None else out
    out[...] = 0.0
    if hp > 2 * r and wp > 2 * r:
        out[r:hp - r, r:wp - r] = box_sum(plane, r)[r:hp - r, r:wp - r]
    return np.maximum(out, 0.0, out=out)


#: pixels a chunk's band of rows may span (its scatter and the bincount
#: temporaries of ``_Accumulator.add``, 8 bytes per band pixel)
CHUNK_PIXELS = 1 << 17


def chunk_rows(width: int, radius: int) -> int:
    """Rows of the bands that chunks of centres never cross
    (:func:`_place_centres`): the scattered band of a chunk, its rows plus the
    window radius either side, stays under ``CHUNK_PIXELS`` pixels."""
    return max(1, min(CHUNK_PIXELS // (int(width) + 2 * int(radius)) - 2 * int(radius), int(radius) + 1))


def auto_chunk(pixels: int) -> int:
    """``Params.chunk = 0``: centres per batch, pixels / 1024 clamped to
    32..256 (workspace ~80 KB per centre, i.e. at most ~80 B per pixel above
    32 x 1024 pixels)."""
    return int(min(256, max(32, int(pixels) // 1024)))


class _Workspace:
    """Scratch arrays reused by every chunk: allocating fresh multi-megabyte
    temporaries per chunk costs more than the arithmetic (page faults).

    Two window buffers of D x K values per centre take turns (``a``: the raw
    feature gather, then the TSVD scratch, then the features sorted by model
    size; ``b``: the features, then the other gathered planes, var0 | y | w |
    fvalid, in sorted order), ``m``/``mw`` hold one ring of ``[z y']`` and its
    weighted copy (D + 4 rows of at most 8R pixels) and ``mom`` the ring
    moments (R + 1 matrices of (D + 4)^2): per centre
    ``8 (2 K max(D, 8) + 2 (D + 4) 8R + (R + 1) (D + 4)^2)`` bytes (80 KB with
    R = 9 and all passes, D = 9).
    """

    def __init__(self, nmax: int, k: int, d: int, radius: int):
        self.k, self.qmax, self.r1 = k, d + 4, radius + 1   # design (<= D + 1) + y' (3)
        rows = max(d, 8)
        self.a = np.empty(rows * nmax * k)
        self.b = np.empty(rows * nmax * k)
        self.m = np.empty(nmax * self.qmax * max(8 * radius, 1))
        self.mw = np.empty(nmax * self.qmax * max(8 * radius, 1))
        self.mom = np.empty(self.r1 * nmax * self.qmax ** 2)

    @staticmethod
    def view(buf, *shape):
        return buf[:int(np.prod(shape))].reshape(shape)

    def ring(self, n, p):
        """Views for ``ring_fits`` of n centres with p unknowns."""
        q = p + 3
        msize = self.r1 * n * q * q
        return {"m": self.m, "mw": self.mw,
                "mom": self.mom[:msize].reshape(self.r1, n, q, q)}


class _WorkspacePool:
    """:class:`_Workspace` s for the pieces running at the same time: a piece
    takes one (a new one when none is free) and gives it back, so there are
    at most as many as threads running pieces, and all go with the pool."""

    def __init__(self, *args):
        self.args, self.free, self.lock = args, [], threading.Lock()

    def take(self) -> _Workspace:
        with self.lock:
            if self.free:
                return self.free.pop()
        return _Workspace(*self.args)

    def give(self, ws: _Workspace) -> None:
        with self.lock:
            self.free.append(ws)


#: frames below this many pixels are reconstructed on the calling thread only
#: (measured: docs/notes/lp.md, "Threads")
THREAD_MIN_PIXELS = 1 << 16


# ------------------------------------------------------------------------ the models
def fit_centres(frame: _Frame, centre_flat: np.ndarray, params: Params, keep_models: bool = False,
                ws: _Workspace | None = None, all_rings: bool = False) -> dict:
    """Models of Sec. 4 at the given centre pixels (vectorised over centres).

    Builds each centre's TSVD-prefiltered design (Sec. 7), runs the ring-wise
    RLS (Eq. 3) and prediction-error recursion (Eq. 4, 5, 7), and picks per
    channel ``r_opt = argmin_r xi_c(k(r))`` (Eq. 2 with the estimate
    substituted, :func:`select_windows`; ties go to the larger window) with
    the estimates of :func:`_estimated_errors`.  Centres are processed in groups of equal
    model size p = d_c + 1, so each group's normal equations are only as large
    as its rank needs; they are sorted by p after the TSVD, so every group is a
    slice of the workspace (no copies), and each group's design is built one
    ring at a time (:class:`core.lp_solve.Design`).

    Returns a dict with ``index`` (N, K) flat padded pixel indices of every
    window, ``ring`` (K,), ``pred`` (N, 3, K) each model's prediction (Eq. 1)
    at every window pixel, ``beta`` (N, 3, D+1) optimal models (zero-padded),
    ``r_opt`` (N, 3), ``xi_opt`` (N, 3), ``xi`` (R+1, N, 3) all estimates,
    ``rank`` (N,), ``grad`` (N, 3, D) the slopes folded into raw ``x - x_c``,
    ``b0`` (N, 3) the intercepts, ``lower`` (N, 3) the bounds of
    :func:`_lower_bound` and, with ``keep_models``, ``P`` (N, 3, D+1, D+1) and
    ``transform`` (N, D, D); with ``all_rings`` (for tests and studies of the
    window choice) ``pred_rings`` (R+1, N, 3, K), the predictions of every
    ring's model ``beta(k(r))``, and ``w`` (N, K) the usable pixels.
    Predictions are bounded below by :func:`_lower_bound`.
    """
    radius = int(params.radius)
    dy, dx, ring, _ = ring_layout(radius)
    k = len(ring)
    n_c = len(centre_flat)
    d = frame.dim
    if ws is None:
        ws = _Workspace(n_c, k, d, radius)
    index = centre_flat[:, None] + (dy * frame.wp + dx)[None, :]
    x, transform, rank, order = _window_features(frame, centre_flat, index, dy, dx, params, ws)
    y, w, fvalid, s, beta0, xi0 = _window_observations(frame, index[order], ws)

    xi = np.empty((radius + 1, n_c, 3))
    se = np.zeros((radius + 1, n_c, 3))
    floor = np.zeros((radius + 1, n_c, 3))
    beta = np.zeros((n_c, 3, d + 1))
    grad = np.zeros((n_c, 3, d))
    pred = np.empty((n_c, 3, k))
    pinv = np.zeros((n_c, 3, d + 1, d + 1)) if keep_models else None
    rings = np.empty((radius + 1, n_c, 3, k)) if all_rings else None
    lower = _lower_bound(y, w)                                         # (N, 3), sorted order
    rank_s = rank[order]
    cuts = np.concatenate([[0], np.flatnonzero(np.diff(rank_s)) + 1, [n_c]])
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        p = int(rank_s[lo]) + 1
        sel = order[lo:hi]                                             # the group, in input order
        grp = slice(lo, hi)                                            # ... in sorted order
        design = Design(transform[sel][:, :, :p - 1], x[grp], fvalid[grp])
        fits = ring_fits(design, y[grp], w[grp], s[grp], beta0[grp], xi0[grp], radius, params.delta,
                         keep_gram=keep_models, work=ws.ring(hi - lo, p))
        fl = _error_floor(fits, xi0[grp])
        xg = np.maximum(_estimated_errors(fits, xi0[grp]), fl)
        xi[:, sel] = xg
        floor[:, sel] = fl
        se[:, sel] = _standard_errors(fits)
        bg, gram = _optimal_models(fits, xg, se[:, sel])
        beta[sel, :, :p] = bg
        grad[sel] = np.matmul(bg[:, :, 1:], design.t)                    # slopes in raw x - x_c
        pred[sel] = np.maximum(design.predict(bg), lower[grp][:, :, None])   # Eq. 1
        if keep_models:
            with parallel.lapack_lock():               # see parallel.lapack_lock
                pinv[sel, :, :p, :p] = np.linalg.inv(gram)
        if all_rings:
            for r in range(radius + 1):
                rings[r, sel] = np.maximum(design.predict(np.swapaxes(fits.beta[r], 1, 2)),
                                           lower[grp][:, :, None])
    r_opt = select_windows(xi, se)                                     # (N, 3)
    at = (r_opt, np.arange(n_c)[:, None], np.arange(3)[None, :])
    lower_in = np.empty_like(lower)
    lower_in[order] = lower
    out = {"index": index, "ring": ring, "pred": pred, "rank": rank, "r_opt": r_opt, "xi": xi,
           "xi_opt": np.maximum(xi[at], floor[at]), "beta": beta, "grad": grad, "b0": beta[:, :, 0].copy(), "lower": lower_in}
    if keep_models:
        out["P"] = pinv
        out["transform"] = transform
    if all_rings:
        out["pred_rings"] = rings
        inv = np.empty_like(order)
        inv[order] = np.arange(n_c)
        out["w"] = w[inv].copy()
    return out


def select_windows(xi: np.ndarray, se: np.ndarray | None = None) -> np.ndarray:
    """Eq. 2 with the estimate substituted: ``r_opt = argmin_r xi_c(k(r))``
    along axis 0 of ``xi`` (R+1, ...), ties going to the *larger* window.

    A tie is statistical when ``se`` (the standard errors of the estimates,
    :func:`_standard_errors`) is given: among the windows r >= 1 the largest
    one whose estimate is within one standard error of their minimum is taken
    (the one-standard-error rule of cross-validated model selection, Breiman
    et al. 1984; Hastie et al., ESL Sec. 7.10), because on smooth regions
    Eq. 4's noise (``~ s sqrt(2 / |k|)``) exceeds the error differences it
    ranks and the plain argmin scatters over all radii.  The unfiltered k(0)
    wins only when its error (the centre's variance) is below that minimum
    itself.  Without ``se`` (or with se = 0) it is the plain argmin with ties
    to the larger window.  Returns int64 radii of ``xi.shape[1:]``."""
    r1 = xi.shape[0]
    if r1 == 1:
        return np.zeros(xi.shape[1:], np.int64)
    rest = xi[1:]
    j = (r1 - 2) - np.argmin(rest[::-1], axis=0)                       # larger of equal minima
    low = np.take_along_axis(rest, j[None], axis=0)[0]
    tol = low
    if se is not None:
        tol = low + np.nan_to_num(np.take_along_axis(se[1:], j[None], axis=0)[0], nan=0.0, posinf=0.0)
    within = rest <= tol[None]
    big = (r1 - 2) - np.argmax(within[::-1], axis=0)                   # largest within the tolerance
    r = np.where(within.any(axis=0), big, j) + 1
    keep0 = ~(xi[0] >= low)                                            # k(0) strictly better (or no candidate)
    keep0 &= ~(np.isfinite(low) & ~np.isfinite(xi[0]))
    return np.where(keep0 | ~np.isfinite(low), 0, r).astype(np.int64)


def _standard_errors(fits) -> np.ndarray:
    """Standard error of Eq. 4's estimate ``xi_c(k(r))`` (R+1, N, 3): each
    test term ``(residual^2 - s_i)`` has variance ~ ``2 s_i^2`` (a Gaussian
    residual of variance s_i), so ``se = sqrt(2 sum_i s_i^2) / |k(r)|``
    (0 where no variance is known or subtracted; entry 0 unused)."""
    if fits.svar2 is None:
        return np.zeros_like(fits.xi_acc)
    with np.errstate(divide="ignore", invalid="ignore"):
        se = np.sqrt(2.0 * np.maximum(fits.svar2, 0.0)) / fits.count[..., None]
    return np.where(np.isfinite(se), se, 0.0)


def _lower_bound(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Lower bound of a model's predictions per centre and channel:
    ``min(0, min_i y_i)`` over the usable pixels of its filtering window.

    The paper is silent on the sign of the linear extrapolation; radiance is
    non-negative, and where the window's input is non-negative the truth is
    too, so clamping a prediction at 0 can only bring it closer to any
    non-negative truth (``|max(a, 0) - f| <= |a - f|`` for f >= 0).  Windows
    holding negative input (unusual passes, hostile data) are bounded at
    their own minimum, never above the data.  y (N, 3, K), w (N, K);
    returns (N, 3)."""
    low = np.min(y, axis=2, where=w[:, None, :] > 0, initial=np.inf)
    return np.minimum(np.where(np.isfinite(low), low, 0.0), 0.0)

def _window_features(frame: _Frame, centre_flat, index, dy, dx, params: Params, ws: _Workspace):
    """The features of every centre's filtering window and their TSVD
    prefilter (Sec. 7, :func:`feature_transform`).

    Returns ``x`` (N, D, K) the offsets ``x_i - x_c`` with the centres sorted
    by model size (a view of the workspace), ``transform`` (N, D, D) and
    ``rank`` (N,) in input order, and ``order`` (N,) the stable sort by rank.
    The gathers write straight into the workspace (``mode="clip"``: the
    indices are in range; ``mode="raise"`` would gather into a copy first).
    """
    n_c, k = index.shape
    d = frame.dim
    nf = d - 2
    feats = ws.view(ws.b, n_c, d, k)
    feats[:, 0] = dy
    feats[:, 1] = dx
    if nf:
        raw = ws.view(ws.a, nf, n_c, k)
        np.take(frame.planes[:nf], index, axis=1, out=raw, mode="clip")
        feats[:, 2:] = np.swapaxes(raw, 0, 1)
        del raw
    fvalid = np.take(frame.planes[frame.c_f], index, mode="clip")
    transform, rank, _, _ = feature_transform(
        feats, fvalid, frame.centre[:, centre_flat].T, frame.groups, int(params.radius),
        params.svd_floor, params.svd_noise_factor, params.min_rank,
        work=ws.view(ws.a, n_c, d, k))
    del fvalid
    feats -= feats[:, :, :1].copy()                                    # x_i - x_c
    # centres sorted by model size p = d_c + 1, so every group of fit_centres is a slice
    order = np.argsort(rank, kind="stable")
    x = np.take(feats, order, axis=0, out=ws.view(ws.a, n_c, d, k), mode="clip")
    return x, transform, rank, order


def _window_observations(frame: _Frame, index, ws: _Workspace):
    """The window pixels' observations and the initial conditions of the
    recursions (Sec. 7), for centres in the order of ``index`` (N, K).

    Returns ``y`` (N, 3, K) pixel means, ``w`` (N, K) fit weights, ``fvalid``
    (N, K), ``s`` (N, 3, K) the amount Eq. 5/7 subtract from each squared test
    residual (the known variances of the mean, 0 where unknown, or 0 for the
    literal equations), ``beta0`` (N, 3) the intercept ``y_c`` of ``beta(0)``
    and ``xi0`` (N, 3) ``xi_acc(k(0))``, the variance of the centre's mean
    (+inf where unknown or the centre is missing).  All but the last two are
    views of the workspace.

    ``xi0`` is ``max(var_c, median of the 3x3 variances around c)``: Sec. 7
    sets it to the centre's variance of the mean, but an estimate from 4
    subsets (3 degrees of freedom) falls below 0.25x its truth for 14 % of
    the pixels, and those then win Eq. 2 with the unfiltered pixel by chance
    (speckles, and a darker image, since a pixel's low variance estimate goes
    with a low mean); the neighbourhood median (below 0.3x in 1 % of cases)
    removes that low tail, while the centre's own value keeps a firefly's
    large variance.
    """
    n_c, k = index.shape
    g = ws.view(ws.b, 8, n_c, k)                                       # var0 | y | w | fvalid
    np.take(frame.planes[frame.c_v:], index, axis=1, out=g, mode="clip")
    var0, y = g[0:3], np.swapaxes(g[3:6], 0, 1)                        # (3, N, K), (N, 3, K)
    w, fvalid = g[6], g[7]
    centre_ok = w[:, 0] > 0
    beta0 = np.where(centre_ok[:, None], y[:, :, 0], 0.0)
    typical = frame.var_typical[:, index[:, 0]].T.astype(np.float64)  # (N, 3)
    xi0 = np.where(centre_ok[:, None], np.maximum(var0[:, :, 0].T, typical), np.inf)
    # s of Eq. 5/7, in place
    if frame.subtract:
        np.copyto(var0, 0.0, where=~np.isfinite(var0))
    else:
        var0[...] = 0.0
    return y, w, fvalid, np.swapaxes(var0, 0, 1), beta0, xi0


def _estimated_errors(fits, xi0: np.ndarray) -> np.ndarray:
    """Eq. 4: ``xi_c(k(r)) = max(xi_acc(k(r)), 0) / |k(r)|`` (R+1, N, 3), the
    estimate Eq. 2 minimises; |k(r)| is the number of usable pixels in k(r)
    (the paper's ``(2r+1)^2`` away from borders and holes).

    With the variances subtracted (``Params.variance_corrected``) the sum of
    Eq. 4 estimates ``bias^2 + variance`` and goes negative by chance where
    the bias is small; a negative estimate is no smaller an error than 0, so
    it is kept at 0 instead of letting the argmin pick the most negative
    draw, and :func:`fit_centres` bounds it further by the model's variance
    (:func:`_error_floor`) before Eq. 2's argmin (:func:`select_windows`:
    ties to the larger window), which makes the choice on smooth regions
    follow the variance ``s p / |k(r)|``, decreasing with the window.
    (Subtracting the training
    models' prediction variance from the test terms as well, which makes the
    estimate unbiased for a known variance, chose better windows on synthetic
    scenes but gave 1.1-2.7x the relMSE on the six sample scenes, also with a
    reference-derived variance.)  Entry 0 is ``xi0`` (the centre's variance);
    windows before the recursion's start (``RingFits.start``) and 0/0 (no
    usable pixel) are +inf, never chosen."""
    with np.errstate(divide="ignore", invalid="ignore"):
        xg = np.maximum(fits.xi_acc, 0.0) / fits.count[..., None]
    xg[0] = xi0
    return np.where(np.isnan(xg), np.inf, xg)


def _error_floor(fits, xi0: np.ndarray) -> np.ndarray:
    """The variance of the model of k(r), a lower bound of its error (R+1, N, 3).

    The error of a least-squares prediction is never below its variance, the
    window mean of ``Var(f_hat(x_i))``, which for uncorrelated pixel means is
    ``s_mean dof / |k(r)|`` (``dof = tr(P X^T X)``, the effective parameter
    count, p for a determined fit): the error LP reports for its chosen window
    is ``max(xi_c(k_opt), this)``, >= 0 and never a clipped 0 where noise is
    known (exactly the error of a model of a linear truth).  Entry 0 is
    ``xi0``; 0 where no variance is known or subtracted."""
    with np.errstate(divide="ignore", invalid="ignore"):
        cnt = fits.count[..., None]
        if fits.svar is None or fits.dof is None:
            floor = np.zeros(fits.xi_acc.shape)
        else:
            floor = fits.svar / cnt * (fits.dof[..., None] / cnt)
    floor = np.where(np.isfinite(floor), floor, 0.0)
    floor[0] = xi0
    return floor


def _optimal_models(fits, xi_est: np.ndarray, se: np.ndarray | None = None):
    """Eq. 2 with Eq. 4's estimate substituted: per centre and channel the
    model ``beta(k(r_opt))``, ``r_opt = argmin_r xi_c(k(r))``
    (:func:`select_windows`: ties go to the larger window).

    Returns ``beta`` (N, 3, p) and, when ``fits`` kept them, the Gram matrices
    ``delta I + X^T X`` of the chosen windows (N, 3, p, p) (else None).
    """
    r_g = select_windows(xi_est, se)                                   # (N, 3)
    idx_n = np.arange(r_g.shape[0])[:, None]
    idx_c = np.arange(3)[None, :]
    beta = np.swapaxes(fits.beta, 2, 3)[r_g, idx_n, idx_c]             # (N, 3, p)
    gram = None if fits.gram is None else fits.gram[r_g, idx_n]
    return beta, gram


def fit(color: np.ndarray, color_var: np.ndarray, features: dict, feature_var: dict | None = None,
        n: np.ndarray | None = None, params: Params | None = None, keep_models: bool = False) -> LPFit:
    """LP reconstruction of one frame (Moon et al. 2015, Sec. 4-5).

    Parameters
    ----------
    color : (H, W, 3) float64
        Pixel means y (non-finite values are treated as missing).
    color_var : (H, W, 3) float64
        Variance of each pixel mean (``Buffers.variance_of_mean``); +inf where
        unknown (one subset), see the module docstring.
    features : dict name -> (H, W, C) or None
        Any of 'depth', 'normal', 'albedo' (``PASSES``); absent ones are skipped.
    feature_var : dict name -> (H, W, C) or None
        Variance of the feature means, for the TSVD threshold (unknown = 0);
        only its sum over channels is used, so (H, W, 1) sums work too.
    n : (H, W) or None
        Samples per pixel (Sec. 5.2's ``n_i``; pixels with n = 0 are missing);
        None means one sample everywhere.
    params : Params (paper defaults when None).
    keep_models : bool
        Keep every centre's RLS state (see ``LPFit.models``).

    Returns
    -------
    LPFit
        Centres are placed with granularity g, g // 2, ..., 1 (Sec. 5.1): a
        pixel on the current grid becomes a centre unless a model of an earlier
        pass already predicts it in every channel; each centre predicts the
        ``(2 r_opt + 1)^2`` pixels of its optimal window with its optimal model
        (Eq. 1), and overlapping predictions (and their errors) are averaged.

    Notes
    -----
    Memory: the inputs are packed once into padded planes (:class:`_Frame`),
    every chunk of centres reuses one workspace (:class:`_Workspace`) into
    which the window planes are gathered, the design ``z`` is built one ring
    at a time (:class:`core.lp_solve.Design`), centres are sorted by model
    size so each size group is a slice, chunks are limited to a band of rows
    so their scatter stays local, and the derived inputs are dropped before
    the fit.  Byte counts and measured peaks: docs/notes/lp.md.  Each
    thread running a chunk holds one more workspace and its chunk's band
    sums (see the module docstring, "Threads").
    """
    params = params or Params()
    return _fit_frame(_pack(color, color_var, features, feature_var, n, params), params, keep_models)


def _pack(color, color_var, features, feature_var, n, params: Params, origin: int = 0) -> _Frame:
    color = np.asarray(color, np.float64)
    if color.ndim != 3 or color.shape[-1] != 3:
        raise ValueError(f"color must be (H, W, 3), got {color.shape}")
    return _Frame(color, color_var, features or {}, feature_var, n, int(params.radius),
                  params.variance_corrected, origin)


def _fit_buffers(buf: Buffers, params: Params) -> LPFit:
    """:func:`fit` of accumulated buffers; the derived inputs (variances of the
    means) are dropped once the frame is packed, before the models are fitted."""
    return _fit_frame(_pack(*_inputs(buf), buf.n, params), params)


def _chunk(params: Params, pixels: int) -> int:
    """Centres per batch for a frame of ``pixels`` (``Params.chunk``, 0 = :func:`auto_chunk`)."""
    chunk = int(params.chunk) if int(params.chunk) > 0 else auto_chunk(pixels)
    return max(1, min(chunk, int(pixels)))


def _fit_frame(frame: _Frame, params: Params, keep_models: bool = False) -> LPFit:
    """Sec. 4-5 on a packed frame (see :func:`fit`); releases the frame's planes."""
    h, w = frame.h, frame.w
    chunk = _chunk(params, h * w)
    acc = _Accumulator(frame)
    placed, passes = _place_centres(frame, acc, params, chunk, keep_models)
    offsets = _mean_offsets(frame, acc, placed, int(params.radius), chunk)
    centres = placed["centers"]
    if keep_models and centres:
        allc = np.concatenate(centres)
        cfeat = np.zeros((len(allc), frame.dim))
        cfeat[:, 2:] = frame.planes[:frame.dim - 2, frame.flat(allc[:, 0], allc[:, 1])].T
    image, error, dxi, radius = acc.averages()      # reads the pixels' own values (:func:`_own_pixel`)
    frame.release()                      # the inputs are no longer needed
    c_rad, c_rank, c_err = placed["r_opt"], placed["rank"], placed["xi_opt"]
    out = LPFit(
        image=image,
        error=error,
        delta_error=dxi,
        radius=radius,
        centers=np.concatenate(centres) if centres else np.zeros((0, 2), np.int64),
        center_radius=np.concatenate(c_rad) if c_rad else np.zeros((0, 3), np.int64),
        center_rank=np.concatenate(c_rank) if c_rank else np.zeros(0, np.int64),
        center_error=np.concatenate(c_err) if c_err else np.zeros((0, 3)),
        passes=passes,
    )
    if keep_models and centres:
        out.models = {key: np.concatenate(placed[key]) for key in ("beta", "P", "transform")}
        out.models["offset"] = offsets
        out.models["center_features"] = cfeat
    return out


def _granularities(granularity: int, radius: int) -> list:
    """Sec. 5.1's granularity factors g, g // 2, g // 4, ..., 1; g = 0 means
    the filtering window width 2R+1 (the paper's example)."""
    grans = [max(int(granularity) or (2 * int(radius) + 1), 1)]
    while grans[-1] > 1:
        grans.append(grans[-1] // 2)
    return grans


def _place_centres(frame: _Frame, acc: _Accumulator, params: Params, chunk: int, keep_models: bool):
    """Sec. 5.1: iterative construction of the models.  In the pass of
    granularity g every pixel whose row and column are multiples of g, that is
    no centre yet and that no earlier model predicts in every channel, becomes
    a centre; its model (:func:`fit_centres`) predicts its optimal window,
    accumulated into ``acc``.  The last pass (g = 1) covers every pixel.

    Returns (per-chunk lists ``centers`` (n, 2), ``r_opt``, ``rank``,
    ``xi_opt``, the models as :func:`_mean_offsets` re-evaluates them (``grad``
    (n, 3, D) slopes in ``x - x_c``, ``b0`` (n, 3) intercepts, ``lower``
    (n, 3) bounds) and, with ``keep_models``, ``beta``, ``P``, ``transform``;
    the number of passes that placed centres).
    """
    h, w = frame.h, frame.w
    radius = int(params.radius)
    pool = _WorkspacePool(chunk, (2 * radius + 1) ** 2, frame.dim, radius)
    inline = h * w < THREAD_MIN_PIXELS
    covered = np.zeros((h, w), bool)
    is_centre = np.zeros((h, w), bool)
    # rows and grids in the whole image's coordinates (a band of rows, :func:`fit_band`,
    # places the centres of the whole frame there)
    rows, cols = np.arange(h)[:, None] + frame.origin, np.arange(w)[None, :]
    band_rows = chunk_rows(w, radius)
    kept = ("r_opt", "rank", "xi_opt", "grad", "b0", "lower") + (("beta", "P", "transform") if keep_models else ())
    placed = {key: [] for key in ("centers", "pass") + kept}

    def compute(piece):
        # one chunk on a pool thread: its own workspace, its sums over its band
        yy, xx = piece
        ws = pool.take()
        try:
            res = fit_centres(frame, frame.flat(yy, xx), params, keep_models, ws)
        finally:
            pool.give(ws)
        return np.stack([yy, xx], axis=1), [res[key] for key in kept], acc.contributions(res)

    def reduce(out):
        acc.apply(out[2])                              # in chunk order: the serial sums
        return out[:2]

    passes = 0
    for g in _granularities(params.granularity, radius):
        cy, cx = np.nonzero((rows % g == 0) & (cols % g == 0) & ~is_centre & ~covered)
        if len(cy) == 0:
            continue
        passes += 1
        is_centre[cy, cx] = True
        # the chunks depend on the shape and parameters only, never on the thread
        # count: the centres of one band of ``band_rows`` rows (bands counted from
        # the image's row 0), ``chunk`` at a time from the band's first centre
        pieces, s0 = [], 0
        while s0 < len(cy):
            band_end = ((int(cy[s0]) + frame.origin) // band_rows + 1) * band_rows - frame.origin
            s1 = min(s0 + chunk, int(np.searchsorted(cy, band_end)))
            pieces.append((cy[s0:s1], cx[s0:s1]))
            s0 = s1
        for centres, values in parallel.ordered_reduce(compute, reduce, pieces, inline):
            placed["centers"].append(centres)
            placed["pass"].append(passes - 1)
            for key, value in zip(kept, values):
                placed[key].append(value)
        covered = acc.predicted()
    return placed, passes


# ------------------------------------------------------------- bands of rows
def band_halo(width: int, params: Params) -> int:
    """Rows above and below a band that :func:`fit_band` must see for the
    band's own rows to come out as the whole frame's, bit for bit.

    Each quantity depends on inputs within a known number of rows: a model on
    its window (R rows) and on the other centres of its chunk (their rank
    groups share arrays), so on its chunk's whole band of ``b`` =
    :func:`chunk_rows` rows; a centre of pass p > 1 exists where the models
    of passes < p leave its pixel uncovered (Sec. 5.1), so on every chunk
    within R rows of it.  Per pass that is at most ``L = R + b`` more rows
    (the 3x3 median of the typical variance included); after the P passes
    of :func:`_granularities`, the mean offsets (a model's final share reads
    the blend weights of every model over its window: two more levels) and
    the blend itself (one more) give ``(P + 3) L``.  Ours: the paper fits
    whole frames."""
    r = int(params.radius)
    return (len(_granularities(params.granularity, r)) + 3) * (r + chunk_rows(width, r))


def fit_band(job: dict) -> dict:
    """LP (:func:`fit`) of one band of rows of a frame, for a map spread over
    farm workers (:func:`fit_bands`): a pure function of ``job``, which holds
    the inputs of rows ``t0 .. t1`` of the frame (``color``, ``color_var``,
    ``features``, ``feature_var``, ``n``: the arrays :func:`fit` takes, cut
    to those rows), ``t0``, the band's own rows ``c0 .. c1`` (image rows,
    ``t0 + band_halo <= c0`` unless ``t0`` is 0, and the same below), the
    whole frame's ``chunk`` (:func:`_chunk`) and ``params`` (a dict).

    The grids of Sec. 5.1 and the chunk bands are counted from the image's
    row 0 (``origin``), so the band's own rows get the whole frame's values
    (:func:`band_halo`).  Returns those rows' ``image``, ``err`` and ``dxi``
    (raw, see :meth:`_Accumulator.averages`), ``radius``, ``tops``, and the
    centres placed in them, ``centers`` (image coordinates) with ``pass``,
    ``r_opt``, ``rank``, ``xi_opt`` (creation order)."""
    params = params_from_dict(Params, job["params"])
    t0, c0, c1 = int(job["t0"]), int(job["c0"]), int(job["c1"])
    frame = _pack(job["color"], job["color_var"], job["features"], job["feature_var"], job["n"], params,
                  origin=t0)
    acc = _Accumulator(frame)
    placed, _ = _place_centres(frame, acc, params, int(job["chunk"]), False)
    _mean_offsets(frame, acc, placed, int(params.radius), int(job["chunk"]))
    image, err, dxi, radius, tops = acc.averages(core=(c0 - t0, c1 - t0))
    frame.release()
    out = {"image": image, "err": err, "dxi": dxi, "radius": radius, "tops": tops}
    if placed["centers"]:
        centers = np.concatenate(placed["centers"])
        mine = (centers[:, 0] >= c0 - t0) & (centers[:, 0] < c1 - t0)
        out["centers"] = centers[mine] + np.array([t0, 0])
        out["pass"] = np.concatenate([np.full(len(c), i, np.int64)
                                      for c, i in zip(placed["centers"], placed["pass"])])[mine]
        for key in ("r_opt", "rank", "xi_opt"):
            out[key] = np.concatenate(placed[key])[mine]
    else:
        out["centers"] = np.zeros((0, 2), np.int64)
        out["pass"] = np.zeros(0, np.int64)
        out["r_opt"], out["rank"], out["xi_opt"] = (np.zeros((0, 3), np.int64), np.zeros(0, np.int64),
                                                   np.zeros((0, 3)))
    return out


def band_jobs(color, color_var, features, feature_var, n, params: Params, parts: int) -> list:
    """The jobs of :func:`fit_band` that cover a frame in ``parts`` bands of
    about equal height (fewer where the frame is short): each with its
    :func:`band_halo` rows either side, inputs cut (and copied) to them."""
    color = np.asarray(color)
    h, w = color.shape[:2]
    halo = band_halo(w, params)
    parts = max(1, min(int(parts), h))
    edges = [(h * i) // parts for i in range(parts + 1)]
    chunk = _chunk(params, h * w)
    plain = {f.name: getattr(params, f.name) for f in fields(Params)}

    def rows(a, t0, t1):
        if a is None:
            return None
        a = np.asarray(a)
        return np.ascontiguousarray(a[t0:t1]) if a.ndim >= 2 and a.shape[0] == h else a

    jobs = []
    for c0, c1 in zip(edges[:-1], edges[1:]):
        if c1 <= c0:
            continue
        t0, t1 = max(0, c0 - halo), min(h, c1 + halo)
        jobs.append({
            "t0": t0, "c0": c0, "c1": c1, "chunk": chunk, "params": plain,
            "color": rows(color, t0, t1), "color_var": rows(color_var, t0, t1),
            "features": {k: rows(v, t0, t1) for k, v in (features or {}).items()},
            "feature_var": None if feature_var is None else {k: rows(v, t0, t1) for k, v in feature_var.items()},
            "n": rows(n, t0, t1),
        })
    return jobs


def join_bands(outs: list, shape: tuple) -> LPFit:
    """The :class:`LPFit` of a frame from its bands' :func:`fit_band` results
    (in band order): rows stacked, errors finished with the frame's largest
    finite values, centres in the whole frame's creation order (by pass, then
    row by row)."""
    h, w = shape
    tops = [max((o["tops"][j] for o in outs if o["tops"][j] is not None), default=0.0) for j in range(2)]
    image = np.concatenate([o["image"] for o in outs])
    radius = np.concatenate([o["radius"] for o in outs])
    error, dxi = np.empty((h, w)), np.empty((h, w, 3))
    y = 0
    for o in outs:
        rows = o["image"].shape[0]
        error[y:y + rows], dxi[y:y + rows] = _finish_errors(o["err"], o["dxi"], tops)
        y += rows
    passes = np.concatenate([o["pass"] for o in outs])
    order = np.argsort(passes, kind="stable")
    pick = {key: np.concatenate([o[key] for o in outs])[order] for key in ("centers", "r_opt", "rank", "xi_opt")}
    return LPFit(image=image, error=error, delta_error=dxi, radius=radius, centers=pick["centers"],
                 center_radius=pick["r_opt"], center_rank=pick["rank"], center_error=pick["xi_opt"],
                 passes=int(len(np.unique(passes))))


def fit_bands(color, color_var, features, feature_var, n, params: Params, parts: int, run=None) -> LPFit:
    """:func:`fit` computed as ``parts`` bands of rows (:func:`fit_band`),
    each a pure function of its inputs, so a farm's workers can compute them;
    ``run(jobs) -> results in order`` (None: one after the other here).  The
    same bits as :func:`fit` (without ``keep_models``) for any ``parts``."""
    jobs = band_jobs(color, color_var, features, feature_var, n, params, parts)
    outs = list(map(fit_band, jobs)) if run is None else list(run(jobs))
    return join_bands(outs, np.asarray(color).shape[:2])


#: the blend's mean correction of a model (:func:`_mean_offsets`) is at most this
#: many standard errors of its window mean, ``sqrt(s_typ / |k|)``
OFFSET_LIMIT = 10.0


def _mean_offsets(frame: _Frame, acc: _Accumulator, placed: dict, radius: int, chunk: int) -> np.ndarray:
    """Re-blend every model with its intercept moved so that its residual,
    weighted by its share of the final blend, is zero; returns the offsets
    (M, 3) and rewrites ``acc.pred`` with the corrected predictions.

    Why: a least-squares model with an intercept keeps its window's sum
    (residuals sum to 0), but in the blend model c contributes to pixel i
    only its share ``a_ci = w_ci / sum_c' w_c'i`` (:func:`blend_weights`);
    the image's sum is the input's minus ``sum_c sum_i a_ci (y_i - f_c(x_i))``,
    and that is not 0 where shares and residuals correlate: a model spreads a
    bright pixel over its window, keeps a large share at the bright pixel and
    a small one at neighbours that their own (more accurate) models predict,
    so the blend darkens (Sec. 5.1's plain average too: 4.9 % on the glossy
    sample scene).  The offset ``m_c = sum_i a_ci w_i (y_i - f_c(x_i)) /
    sum_i a_ci w_i`` (w_i: usable pixels) is the intercept of the least
    squares fit weighted by the final shares (slopes kept); with it the
    blend keeps the input's sum exactly.  Ours (the paper averages as
    fitted).  It is bounded by ``OFFSET_LIMIT`` standard errors of the
    window mean, ``sqrt(s_typ / |k|)`` (s_typ the typical variance at the
    centre, 0 where unknown): a larger weighted residual is made by outliers
    (fireflies) that the fit treats as noise, and spreading their energy
    over the window costs more error than it saves (docs/notes/lp.md).
    Corrected predictions are bounded below as before (:func:`_lower_bound`).
    """
    dy, dx, ring, _ = ring_layout(radius)
    k = len(ring)
    offs = dy * frame.wp + dx
    table = _taper_table(radius)
    positions = np.arange(k)
    nf = frame.dim - 2
    wsum = acc.wsum
    acc.pred[...] = 0.0

    def compute(model):
        # one placed chunk on a pool thread: offsets and its sums over its band
        centers, r_opt, xi_opt, grad, b0, lower = model
        flat = frame.flat(centers[:, 0], centers[:, 1])
        offset = np.zeros((len(flat), 3))
        sums = []
        for s0 in range(0, len(flat), chunk):
            sl = slice(s0, min(s0 + chunk, len(flat)))
            index = flat[sl, None] + offs[None, :]
            n = len(index)
            x = np.empty((n, frame.dim, k))
            x[:, 0], x[:, 1] = dy, dx
            if nf:
                x[:, 2:] = np.swapaxes(np.take(frame.planes[:nf], index, axis=1), 0, 1)
            fvalid = np.take(frame.planes[frame.c_f], index)
            x -= x[:, :, :1].copy()
            pred = np.matmul(grad[sl], x)                                 # (N, 3, K), Eq. 1 as fitted
            pred *= fvalid[:, None, :]
            pred += b0[sl, :, None]
            del x
            usable = np.take(frame.planes[frame.c_w], index)
            lo = int(index.min())
            span = int(index.max()) + 1 - lo
            for c in range(3):
                r = r_opt[sl, c]
                inside = positions[None, :] < ((2 * r + 1) ** 2)[:, None]
                wt = _weight(table[r], xi_opt[sl, c, None])                  # blend_weights
                total = np.take(wsum[c], index)
                share = wt / np.where(total > 0, total, 1.0) * usable
                yc = np.take(frame.planes[frame.c_y + c], index)
                den = share.sum(axis=1)
                num = (share * (yc - pred[:, c])).sum(axis=1)
                m = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
                typ = frame.var_typical[c, index[:, 0]].astype(np.float64)
                cnt = np.maximum((usable * inside).sum(axis=1), 1.0)
                with np.errstate(invalid="ignore"):
                    cap = np.where(np.isfinite(typ) & (typ > 0), OFFSET_LIMIT * np.sqrt(np.maximum(typ, 0.0) / cnt), 0.0)
                m = np.clip(m, -cap, cap)
                offset[sl, c] = m
                val = np.maximum(pred[:, c] + m[:, None], lower[sl, c, None])
                sums.append((c, lo, span, np.bincount((index - lo)[inside], (val * wt)[inside], span)))
        return offset, sums

    def reduce(result):
        offset, sums = result
        for c, lo, span, part in sums:                 # in chunk order: the serial sums
            acc.pred[c, lo:lo + span] += part
        return offset

    models = list(zip(placed["centers"], placed["r_opt"], placed["xi_opt"], placed["grad"], placed["b0"],
                      placed["lower"]))
    out = parallel.ordered_reduce(compute, reduce, models, frame.h * frame.w < THREAD_MIN_PIXELS)
    return np.concatenate(out) if out else np.zeros((0, 3))


#: a pixel counts as predicted (Sec. 5.1) when its models' error is at most this
#: multiple of the typical variance around it (:meth:`_Accumulator.predicted`)
COVER_TOLERANCE = 4.0
#: a pixel counts as predicted (Sec. 5.1) when the tapers (:func:`taper`) of its
#: models sum to at least this (:meth:`_Accumulator.predicted`)
COVER_WEIGHT = 0.5
#: errors below / above which :func:`blend_weights` clips (squared radiance)
_XI_CLIP = 1e-30


def taper(dy: np.ndarray, dx: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """The spatial part of a model's blend weight at offset (dy, dx) from its
    centre, for a window of radius r: ``h(dy / (r + 1)) h(dx / (r + 1))``,
    ``h(t) = cos^3(pi t / 2)`` for |t| < 1, 0 outside the window
    (``max(|dy|, |dx|) > r``).  All arrays broadcast together.

    Separable and smooth: 1 at the centre with a flat top (no kink there or
    along the diagonals, as a taper of the Chebyshev distance has), and its
    value, slope and curvature reach 0 together where the window ends (at
    distance r + 1), so a model fades in and out of the blend without a step,
    a kink or a jump in curvature.  The power 3: a linear model's error grows
    towards its window border, so the blend is roughest where the shares bend
    there; cos^2 (a partition of unity on a grid of spacing r + 1) left 1.5x
    the interior roughness next to window borders on a noise-free gradient,
    cos^3 1.2x, cos^4 1.1x with 20-50 % more centres (docs/notes/lp.md)."""
    r1 = np.asarray(radius, np.float64) + 1.0
    ty = np.cos((0.5 * np.pi) * (np.asarray(dy, np.float64) / r1))
    tx = np.cos((0.5 * np.pi) * (np.asarray(dx, np.float64) / r1))
    inside = np.maximum(np.abs(dy), np.abs(dx)) <= np.asarray(radius)
    return np.where(inside, np.abs(ty * tx) ** 3, 0.0)


def blend_weights(dy: np.ndarray, dx: np.ndarray, radius: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Weight of a model's prediction at a pixel of its window, where several
    models overlap (Sec. 5.1 of Moon et al. 2015 "simply averages" them):
    ``taper(dy, dx, r) / xi_c(k_opt)`` (:func:`taper`), xi the model's
    estimated error (clipped to [1e-30, 1e30]).  All arrays broadcast together.

    Two departures from the plain average, both because it left artefacts:
    (1) the taper: a model entering the average at its window border with full
    weight makes a step of (its prediction - the others') / count, the
    rectangular seams on smooth walls; a weight that goes to 0 with a zero
    slope at the border removes the step and the kink, and Eq. 1 is a Taylor
    expansion at x_c whose remainder grows with the distance, so nearer models
    deserve more weight anyway; (2) the inverse estimated error
    (inverse-MSE weighting of unbiased-ish estimators): a model whose window
    holds a highlight has a large error everywhere in it (the mean error Eq. 2
    minimises is dominated by the highlight) and must not override the
    accurate models of its dark neighbours."""
    return _weight(taper(dy, dx, radius), xi)


def _weight(tap: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """:func:`blend_weights` from the taper: ``tap / clip(xi, 1e-30, 1e30)``."""
    return tap / np.clip(xi, _XI_CLIP, 1.0 / _XI_CLIP)


def _taper_table(radius: int) -> np.ndarray:
    """:func:`taper` of every window radius r = 0 .. R at the ring-ordered
    offsets of :func:`core.lp_solve.ring_layout` (R + 1, K), read-only."""
    return _taper_table_cached(int(radius))


@lru_cache(maxsize=None)
def _taper_table_cached(radius: int) -> np.ndarray:
    dy, dx, _, _ = ring_layout(radius)
    out = taper(dy[None, :], dx[None, :], np.arange(radius + 1)[:, None])
    out.flags.writeable = False
    return out


def _radius_of(k: int) -> int:
    """R of a ring-ordered window of K = (2R+1)^2 pixels."""
    return (int(round(np.sqrt(k))) - 1) // 2


class _Accumulator:
    """Per-pixel running sums over the padded frame: weighted predictions,
    errors and Sec. 5.2 error reductions, their weights (:func:`blend_weights`)
    and model counts per channel, and the sum of the covering models' radii."""

    def __init__(self, frame: _Frame):
        self.frame = frame
        size = frame.hp * frame.wp
        self.wsum = np.zeros((3, size))
        self.pred = np.zeros((3, size))
        # weighted errors sum w xi = taper^2 (xi clipped), so they stay <= the
        # model count: float32 holds them to ~1e-7 (12 bytes per pixel each)
        self.err = np.zeros((3, size), np.float32)
        self.dxi = np.zeros((3, size), np.float32)
        # the covering models' tapers (:func:`taper`), for Sec. 5.1's coverage test
        self.tsum = np.zeros((3, size), np.float32)
        self.cnt = np.zeros(size, np.float32)           # models x channels, exact below 2^24
        self.rad = np.zeros(size, np.float32)

    def crop(self, a):
        f = self.frame
        return a.reshape(a.shape[:-1] + (f.hp, f.wp))[..., f.pad:f.pad + f.h, f.pad:f.pad + f.w]

    def add(self, res: dict) -> None:
        """Add each centre's predictions over its optimal window (Eq. 1), with
        its error xi_c(k_opt) and ``xi_c(k_opt) n_i^(-4/(d_c+4))`` (Sec. 5.2):
        :meth:`apply` of :meth:`contributions`."""
        self.apply(self.contributions(res))

    def contributions(self, res: dict) -> tuple:
        """The sums :meth:`add` adds for one chunk of centres, over the band
        of padded pixels the chunk touches: ``(lo, span, sums)``, ``sums``
        the per-channel bincounts of weights, weighted predictions, errors and
        error reductions, then the model counts and radii (float64, as
        bincount gives them).  Reads only the frame, so chunks can compute
        theirs on several threads; :meth:`apply` in chunk order then gives the
        sums of a serial run bit for bit.

        Windows are prefixes of the ring-ordered pixel list, so only the
        ``(2 r_opt + 1)^2`` pixels inside are scattered."""
        index, r_opt = res["index"], res["r_opt"]
        table = _taper_table(_radius_of(index.shape[1]))                # (R+1, K)
        lo = int(index.min())
        span = int(index.max()) + 1 - lo
        k = index.shape[1]
        pred = res["pred"]                                               # (N, 3, K)
        expo = -gain_exponent(res["rank"])                               # (N,) -4/(d_c+4)
        positions = np.arange(k)
        logn = self.frame.logn
        per_channel, cnt, rad = [], [], []
        for c in range(3):
            length = (2 * r_opt[:, c] + 1) ** 2
            inside = positions[None, :] < length[:, None]                # (N, K), a prefix per row
            local = index[inside]                                        # entries, centre by centre
            xi = np.repeat(res["xi_opt"][:, c], length)
            tap = table[r_opt[:, c]][inside]                             # taper(dy, dx, r_opt)
            wt = _weight(tap, xi)                                        # blend_weights
            # xi n_i^(-4/(d_c+4)), the error reduction rate of Moon et al. 2014 (n clamped to >= 1)
            dxi = np.take(logn, local)
            dxi *= np.repeat(expo, length)
            np.exp(dxi, out=dxi)
            dxi *= xi
            local -= lo
            sums = [np.bincount(local, wt, span), np.bincount(local, pred[:, c][inside] * wt, span)]
            del inside
            xi *= wt
            dxi *= wt
            sums += [np.bincount(local, xi, span), np.bincount(local, dxi, span),
                     np.bincount(local, tap, span)]
            del xi, dxi, wt, tap
            per_channel.append(sums)
            # counts and radii: one bincount per channel, added in channel order
            cnt.append(np.bincount(local, None, span).astype(np.float32))
            rad.append(np.bincount(local, np.repeat(r_opt[:, c].astype(np.float64), length),
                                   span).astype(np.float32))
        return lo, span, per_channel, cnt, rad

    def apply(self, contrib: tuple) -> None:
        """Add one chunk's :meth:`contributions` to the running sums (in the
        order and with the roundings of the serial accumulation)."""
        lo, span, per_channel, cnt, rad = contrib
        sl = slice(lo, lo + span)
        for c, (wsum, pred, err, dxi, tsum) in enumerate(per_channel):
            self.wsum[c, sl] += wsum
            self.pred[c, sl] += pred
            self.err[c, sl] += err
            self.dxi[c, sl] += dxi
            self.tsum[c, sl] += tsum
            self.cnt[sl] += cnt[c]
            self.rad[sl] += rad[c]

    def predicted(self) -> np.ndarray:
        """(H, W) bool: the pixels Sec. 5.1 counts as predicted by the models
        so far: covered in every channel by models whose tapers
        (:func:`taper`) sum to at least ``COVER_WEIGHT``, with a blended
        estimated error of at most ``COVER_TOLERANCE`` times the typical
        variance of the mean around the pixel (the median over its 3x3
        neighbourhood; any covering model counts where that is unknown).

        The paper counts any covering model.  But (1) Sec. 5.1's first grid,
        spacing 2R + 1, tiles the image with windows of radius R that only
        abut, so on smooth regions every pixel had one model and the image was
        a mosaic of 19 x 19 blocks whose borders no blend weight can hide (the
        block seams on smooth walls); a taper sum of 0.5 (a pixel half-way
        between two models' centres, as a grid of spacing r + 1 would give)
        asks for the overlap, so models cross-fade; and (2) a model whose window holds a
        highlight has a large error over the whole window, and the dark pixels
        it covers then never get a model of their own (the glossy scene: 1.3
        predicted where the truth is 0.1).  The median of nine variance
        estimates of 3 degrees of freedom (4 subsets) falls below 0.3x the
        true variance in 1 % of cases, so with a tolerance of 4 a model as
        good as the unfiltered pixel is rarely rejected."""
        f = self.frame
        out = np.empty((f.h, f.w), bool)

        def band(rows):
            y0, y1 = rows
            wsum = self.crop(self.wsum)[:, y0:y1]
            cnt = self.crop(self.tsum)[:, y0:y1] >= COVER_WEIGHT
            with np.errstate(divide="ignore", invalid="ignore"):
                err = self.crop(self.err)[:, y0:y1] / wsum
                bad = err > COVER_TOLERANCE * self.crop(f.var_typical)[:, y0:y1]
            out[y0:y1] = (cnt & ~bad).all(axis=0)

        parallel.run_bands(band, f.h, _BAND_ROWS, THREAD_MIN_PIXELS, f.w)
        return out

    def averages(self, core: tuple | None = None):
        """The weighted averages over the models covering each pixel (Sec. 5.1,
        :func:`blend_weights`), the sums released once read: ``image`` (H, W, 3)
        (non-finite -> 0; with the pixels' own values where the models miss
        them, :func:`_own_pixel`, read from the frame's planes), ``error`` (H, W) (RGB mean), ``delta_error``
        (H, W, 3) (errors through :func:`_finite_errors`) and ``radius``
        (H, W) the plain mean r_opt over the covering models and channels.
        Per pixel, in bands of rows on :mod:`core.parallel`'s pool; the
        largest finite errors (:func:`_finite_errors`) are maxima over the
        bands, exact in any order.

        With ``core = (y0, y1)`` (a band's own rows, :func:`fit_band`): only
        those rows, and the errors unfinished: ``(image, err, dxi, radius,
        tops)`` with ``err``, ``dxi`` (3, y1 - y0, W) the raw blended ratios
        (non-finite kept) and ``tops`` their largest finite values (None where
        there is none), for :func:`_finish_errors` over the whole frame."""
        f = self.frame
        c0, c1 = (0, f.h) if core is None else (int(core[0]), int(core[1]))
        h, w = c1 - c0, f.w
        image = np.empty((h, w, 3))
        radius = np.empty((h, w), np.result_type(self.rad.dtype, self.cnt.dtype))
        raw = core is not None
        if raw:
            err_out, dx_out = np.empty((3, h, w)), np.empty((3, h, w))
        else:
            error, dxi = np.empty((h, w)), np.empty((h, w, 3))

        def ratios(y0, y1):
            wsum = self.crop(self.wsum)[:, c0 + y0:c0 + y1]
            safe = np.where(wsum > 0, wsum, 1.0)
            return (self.crop(self.err)[:, c0 + y0:c0 + y1] / safe,
                    self.crop(self.dxi)[:, c0 + y0:c0 + y1] / safe, safe)

        def tops(rows):
            # the image, the radii and each band's largest finite errors
            y0, y1 = rows
            err, dx, safe = ratios(y0, y1)
            g0, g1 = c0 + y0, c0 + y1
            img = self.crop(self.pred)[:, g0:g1] / safe
            img[~np.isfinite(img)] = 0.0
            planes = self.crop(f.planes)
            img = _own_pixel(img, planes[f.c_y:f.c_y + 3, g0:g1], planes[f.c_v:f.c_v + 3, g0:g1],
                             self.crop(f.var_typical)[:, g0:g1], planes[f.c_w, g0:g1] > 0)
            image[y0:y1] = np.moveaxis(img, 0, -1)
            radius[y0:y1] = self.crop(self.rad[None])[0, g0:g1] / np.maximum(self.crop(self.cnt[None])[0, g0:g1], 1.0)
            if raw:
                err_out[:, y0:y1], dx_out[:, y0:y1] = err, dx
            return [float(a[np.isfinite(a)].max()) if np.isfinite(a).any() else None for a in (err, dx)]

        found = parallel.run_bands(tops, h, _BAND_ROWS, THREAD_MIN_PIXELS, w)
        top = [max((t[j] for t in found if t[j] is not None), default=None) for j in range(2)]
        if raw:
            self.wsum = self.pred = self.err = self.dxi = self.tsum = None
            return image, err_out, dx_out, radius, top
        top = [0.0 if t is None else t for t in top]

        def errors(rows):
            y0, y1 = rows
            err, dx, _ = ratios(y0, y1)
            error[y0:y1], dxi[y0:y1] = _finish_errors(err, dx, top)

        parallel.run_bands(errors, h, _BAND_ROWS, THREAD_MIN_PIXELS, w)
        self.wsum = self.pred = self.err = self.dxi = self.tsum = None
        return image, error, dxi, radius


def _finish_errors(err: np.ndarray, dx: np.ndarray, top) -> tuple:
    """``error`` (h, W) and ``delta_error`` (h, W, 3) from the blended ratios
    ``err``, ``dx`` (3, h, W): non-finite ones replaced by the whole frame's
    largest finite ``top`` = (err, dx) maxima (:func:`_finite_errors`)."""
    return _finite_errors(err, top[0]).mean(axis=0), np.moveaxis(_finite_errors(dx, top[1]), 0, -1)


#: a pixel's own value enters its output (:func:`_own_pixel`) where it lies more
#: than this many typical standard deviations of the mean from the blend
OUTLIER_SIGMA = 10.0


def _own_pixel(blend: np.ndarray, y: np.ndarray, var: np.ndarray, typical: np.ndarray,
               usable: np.ndarray) -> np.ndarray:
    """Blend the models' prediction with the pixel's own value (its k(0)
    model) where the models clearly miss it, by inverse errors as in
    :func:`blend_weights`: ``f + (y - f) max(0, 1 - t s / (y - f)^2)``,
    t = ``COVER_TOLERANCE``.

    Why: a structure the features do not explain and smaller than any model's
    window (a one-pixel highlight) is inside every covering model's window,
    and the window-mean error of Eq. 4 (what the blend weights and Sec. 5.1's
    coverage read) hardly sees it, so the models predict the surroundings
    there and the highlight's energy is lost.  At such a pixel the models'
    squared error is estimated from its own residual, ``b^2 = (y - f)^2 -
    t s`` (s its variance of the mean, taken at the tolerance t the coverage
    test grants: a variance from a few subsets is often several times low,
    and a firefly is a pixel whose variance was underestimated), the pixel's
    own error as ``t s``, and their inverse-error blend ``(f / b^2 + y / (t
    s)) / (1 / b^2 + 1 / (t s))`` is the expression above (a positive-part
    Wiener gain: nothing of y where the residual is within its noise).  Only
    where ``|y - f| > OUTLIER_SIGMA sqrt(s_typ)`` (s_typ the 3x3 median
    variance): elsewhere the window estimates stand.  With t = 1 sparse
    fireflies kept 1.6-2x the error (docs/notes/lp.md).  Ours; the paper
    predicts every pixel from the models.  Arrays (3, ...) per channel;
    missing pixels (``usable`` False), unknown variances and a typical
    variance of 0 (no noise level known around the pixel: a dark region
    without hits, where a zero-variance pixel is no exact one) are left to
    the models."""
    res = y - blend
    known = usable & np.isfinite(var) & np.isfinite(typical) & (typical > 0)
    with np.errstate(invalid="ignore", over="ignore"):
        far = known & (res * res > OUTLIER_SIGMA * OUTLIER_SIGMA * np.where(known, typical, 0.0))
        r2 = np.where(far, res * res, 1.0)
        gain = np.where(far, np.clip(1.0 - COVER_TOLERANCE * np.where(far, var, 0.0) / r2, 0.0, 1.0), 0.0)
    return blend + np.where(far, res, 0.0) * gain


#: rows per band of the accumulator's per-pixel passes (:meth:`_Accumulator.predicted`,
#: :meth:`_Accumulator.averages`)
_BAND_ROWS = 64


def _finite_errors(err: np.ndarray, top: float | None = None) -> np.ndarray:
    """Clamp estimated errors to >= 0 and replace non-finite ones by ``top``,
    by default the largest finite estimate of ``err`` (0 when there is none;
    the whole image's when ``err`` is a band of it)."""
    fin = np.isfinite(err)
    if top is None:
        top = float(err[fin].max()) if fin.any() else 0.0
    return np.maximum(np.where(fin, err, top), 0.0)


# ------------------------------------------------------------------ method contract
def _inputs(buf: Buffers):
    color = buf.color.mean
    var = buf.variance_of_mean()
    feats, fvars = {}, {}
    for name in PASSES:
        if name in buf.features:
            feats[name] = buf.feature(name)
            fvars[name] = buf.feature_variance(name).sum(axis=-1, keepdims=True)
    return color, var, feats, fvars


def reconstruct(buf: Buffers, params: Params | None = None, run=None, parts: int = 1) -> MethodResult:
    """LP reconstruction (Moon et al. 2015) of the accumulated buffers.

    With ``run`` (an executor's ``run_jobs`` for :func:`fit_band`, e.g. farm
    workers) and ``parts`` > 1 the fit is computed as that many bands of rows
    (:func:`fit_bands`): the same bits, off the controller; the kept noise is
    computed here.

    Returns
    -------
    MethodResult
        ``image`` (H, W, 3), ``error`` (H, W) = estimated squared error
        ``xi_c(k_opt)`` (Eq. 4) of the covering models averaged over RGB,
        plus the kept noise (``Params.kept_noise``), ``fit`` the :class:`LPFit` (reused by :func:`sample_map`),
        ``dimension`` the mean TSVD rank of the centres (0 with none), and
        ``info`` with the scalars ``center_fraction`` (paper: 4.7-18.9 %),
        ``centers``, ``passes``, ``mean_radius``, ``mean_rank``.
    """
    params = params if isinstance(params, Params) else params_from_dict(Params, params)
    if run is None or int(parts) <= 1:
        res = _fit_buffers(buf, params)
    else:
        res = fit_bands(*_inputs(buf), buf.n, params, int(parts), run)
    kept = retained_noise(res.image, buf.color.mean, buf.calibrated_variance()) if params.kept_noise else None
    return _result(res, kept)


def _result(res: LPFit, kept: np.ndarray | None = None) -> MethodResult:
    """The MethodResult of a fit; ``kept`` (H, W), the kept noise
    (:func:`core.errormap.retained_noise`), is added to the error map only
    (``res.error`` and the sampler's ``delta_error`` stay Eq. 4-7's)."""
    mean_rank = float(res.center_rank.mean()) if len(res.centers) else 0.0
    info = {
        "center_fraction": res.center_fraction,
        "centers": int(len(res.centers)),
        "passes": int(res.passes),
        "mean_radius": float(res.center_radius.mean()) if len(res.centers) else 0.0,
        "mean_rank": mean_rank,
    }
    error = res.error if kept is None else res.error + kept
    return MethodResult(res.image, error, info, dimension=mean_rank, fit=res)


def map_result(buf: Buffers, params: Params | None = None, run=None, parts: int = 1) -> MethodResult:
    """The reconstruction the loop hands :func:`sample_map` between
    iterations (the optional member of ``core.method.Method``):
    :func:`reconstruct` without the kept noise, which only the error map
    shown and stored at the end reads (the sampler reads the Eq. 4-7
    estimate); the same image and the same sample map, without the
    calibrated variance the kept noise needs.

    With ``run`` (an executor's ``run_jobs`` for :func:`fit_band`, e.g. farm
    workers) and ``parts`` > 1 the fit is computed as that many bands of rows
    (:func:`fit_bands`): the same bits, off the controller."""
    spread = run is not None and int(parts) > 1
    return without_kept_noise(partial(reconstruct, run=run, parts=parts) if spread else reconstruct,
                              Params, buf, params)


def sample_map(buf: Buffers, result: MethodResult, budget: int, params: Params | None = None,
               state: dict | None = None) -> np.ndarray:
    """New samples per pixel for the next iteration (Sec. 5.2 of Moon et al. 2015).

    ``Delta_i xi = xi_c(k_opt) n_i^(-4/(d_c+4))`` (the error reduction one more
    sample brings, d_c the centre's TSVD rank, averaged over the models covering
    pixel i), relative error ``rho_i = Delta_i xi / (f_hat(x_i)^2 + epsilon)``
    per channel (averaged over RGB), and ``Delta n_i = T rho_i / sum_j rho_j``
    rounded by :func:`core.method.allocate` so the map sums to ``budget``.
    The fit is ``result.fit``; it is recomputed from ``buf`` when ``result``
    carries none of this frame's size.

    Returns
    -------
    (H, W) int64, >= 0, summing to ``budget``.
    """
    params = params if isinstance(params, Params) else params_from_dict(Params, params)
    fitres = result.fit if result is not None else None
    if not isinstance(fitres, LPFit) or fitres.image.shape[:2] != buf.shape:
        fitres = _fit_buffers(buf, params)
    if state is not None:
        state["iterations"] = int(state.get("iterations", 0)) + 1
    f = fitres.image
    rho = (fitres.delta_error / (f * f + params.epsilon)).mean(axis=-1)
    return allocate(rho, budget)


def denoise(color: np.ndarray, color_var: np.ndarray, features: dict | None = None,
            feature_var: dict | None = None, n: np.ndarray | None = None,
            params: Params | dict | None = None) -> MethodResult:
    """LP on plain arrays (see :func:`fit` for the arguments); returns the same
    :class:`~core.method.MethodResult` as :func:`reconstruct`.

    color : (H, W, 3) means; color_var : (H, W, 3) variance of the mean (+inf
    unknown); features : name -> (H, W, C) (any of ``PASSES``, None = none);
    feature_var : name -> (H, W, C) or None; n : (H, W) or scalar samples per
    pixel or None (one); params : Params or dict.
    """
    params = params if isinstance(params, Params) else params_from_dict(Params, params)
    res = fit(color, color_var, features, feature_var, n, params)
    return _result(res, retained_noise(res.image, color, color_var) if params.kept_noise else None)

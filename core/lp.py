"""LP: adaptive rendering with linear predictions (Moon, Iglesias-Guitian, Yoon, Mitchell 2015).

A first-order model ``f(x_i) ~ f(x_c) + grad f(x_c)^T (x_i - x_c)`` (Eq. 1) in
the features x = (pixel position, depth, normal, albedo) (Table 1) is fitted
by least squares at a sparse set of *centre* pixels c, inside a prediction
window ``k(r) = (2r+1)^2`` whose size is chosen per centre by a recursive
estimate of the prediction error, and it predicts every pixel of that window.

Pipeline (one function per step, all vectorised over centre pixels):

1. Features, normalised and prefiltered per filtering window by a truncated SVD
   (Sec. 7, after Moon et al. 2014): :func:`feature_transform`.
2. Recursive least squares over the rings of the 19x19 filtering window
   (Sec. 4.1, Eq. 3), computed as cumulative normal equations per ring with
   batched solves: :func:`core.lp_solve.ring_fits`.
3. Recursive prediction error (Sec. 4.2, Eq. 4-5; initialisation Eq. 7) and the
   optimal window per centre and colour channel: :func:`fit_centres`.
4. Centre placement with granularities g, g/2, g/4, ... (Sec. 5.1),
   overlapping predictions averaged: :func:`fit`.
5. Adaptive sampling (Sec. 5.2): :func:`sample_map`.

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
  False for the literal equations.
* **Channels.**  The paper applies the method "to each channel independently":
  the models, errors and optimal windows are per RGB channel; the normal
  matrix (shared by the channels) is built once.  A pixel counts as
  "predicted" in Sec. 5.1 when all three channels cover it.
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
* **Missing data.**  Pixels with no samples, or non-finite colour or features
  (or values beyond 1e150, whose squares overflow), enter no fit and no error sum; they are still predicted (from their features,
  or by the intercept when their features are non-finite).  A non-finite or
  negative variance counts as unknown.
* **One subset (k < 2, variance +inf).**  ``xi(k(0))`` is +inf, so the centre
  never keeps its unfiltered value while a larger window has a finite error,
  and no variance is subtracted from its test terms (the literal Eq. 5/7).
  Where no finite estimate exists at all, the reported error is the largest
  finite error of the image (0 if there is none).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .buffers import Buffers
from .lp_solve import Design, ring_fits, ring_layout
from .method import MethodResult, allocate, param, params_from_dict

PASSES = ("normal", "albedo", "depth")
ADAPTIVE = True

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
        "window; larger smooths more and costs ~R^2 more time per centre", 1, 15)
    granularity: int = param(
        0, "spacing g of the first centre-pixel grid (Sec. 5.1), halved each pass; 0 = window "
        "width 2R+1 (paper); larger tries fewer, bigger models first (faster, maybe coarser)", 0, 256)
    delta: float = param(
        1e-3, "RLS initial confidence delta, P(0) = I/delta (paper: 0.001); larger regularises "
        "the models towards the centre value (stabler, more biased)", 1e-9, 1.0)
    epsilon: float = param(
        1e-3, "epsilon of the relative error xi/(f^2 + epsilon) that drives adaptive sampling "
        "(paper: 0.001); larger sends fewer samples to dark pixels", 1e-8, 1.0)
    svd_floor: float = param(
        0.01, "constant part of the truncated-SVD threshold on normalised feature singular values "
        "(Moon 2014: 0.01); larger drops more feature directions (faster, less detail)", 0.0, 10.0)
    svd_noise_factor: float = param(
        2.0, "TSVD threshold multiple of the feature-noise spectral norm (Moon 2014: 2); larger "
        "ignores noisier features (robust to DoF/motion noise, may lose edges)", 0.0, 100.0)
    min_rank: int = param(
        2, "feature directions always kept by the TSVD (Moon 2014: 2, the screen plane); "
        "smaller gives smaller, faster but blurrier models", 0, 9)
    variance_corrected: bool = param(
        True, "subtract the test pixels' variance from the Eq. 5/7 errors so they estimate the "
        "error against the truth like xi(k(0)); off = literal paper (filters far less)", 0, 1)
    chunk: int = param(
        0, "centre pixels processed per vectorised batch (0 = auto: pixels / 1024, "
        "between 32 and 256, so the workspace stays under ~80 bytes per pixel); "
        "larger has less Python overhead but uses ~80 KB more memory per centre", 0, 65536)

    @classmethod
    def from_dict(cls, values):
        return params_from_dict(cls, values)


@dataclass
class LPFit:
    """Everything LP computes for one frame.

    image : (H, W, 3) float64 reconstruction (average of the overlapping predictions).
    error : (H, W) float64 estimated squared error xi_c(k_opt) of the models
        covering each pixel, averaged over models and RGB, >= 0, finite.
    delta_error : (H, W, 3) float64 ``xi_c(k_opt) n_i^(-4/(d_c+4))`` (Sec. 5.2)
        averaged over the covering models, per channel.
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
        d_c (``center_rank``) are zero.
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

    def __init__(self, color, color_var, features, feature_var, n, radius, subtract):
        h, w = color.shape[:2]
        r = self.pad = int(radius)
        self.h, self.w = h, w
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
        fvalid = np.ones((h, w), bool)
        with np.errstate(invalid="ignore"):
            for gi, (g, (lo, hi)) in enumerate(zip(names, groups)):
                f = np.asarray(features[g], np.float64).reshape(h, w, -1)
                if f.shape[-1] < hi - lo:
                    raise ValueError(f"feature {g!r} needs {hi - lo} channels, got {f.shape[-1]}")
                f = np.moveaxis(f[..., :hi - lo], -1, 0)
                ok = (np.abs(f) < _HUGE).all(axis=0)             # finite, squares stay finite
                fvalid &= ok
                np.copyto(inner[lo - 2:hi - 2], f, where=ok)    # (no full-size temporaries)
                fv = feature_var.get(g) if feature_var else None
                if fv is not None:
                    fv = np.asarray(fv, np.float64).reshape(h, w, -1)[..., :hi - lo]
                    noise[gi] = np.where((fv > 0) & (fv < _HUGE), fv, 0.0).sum(axis=-1)
        inner[:nf] *= fvalid
        color = np.moveaxis(np.asarray(color, np.float64), -1, 0)
        nn = np.ones((h, w)) if n is None else np.broadcast_to(np.asarray(n, np.float64), (h, w))
        nn = np.where(np.isfinite(nn), nn, 0.0)
        with np.errstate(invalid="ignore"):
            cvalid = (np.abs(color) < _HUGE).all(axis=0) & (nn > 0)
        np.copyto(inner[self.c_y:self.c_y + 3], color, where=cvalid)
        var = np.moveaxis(np.broadcast_to(np.asarray(color_var, np.float64), (h, w, 3)), -1, 0)
        with np.errstate(invalid="ignore"):
            known = (var >= 0) & (var < _HUGE * _HUGE) & cvalid
        inner[self.c_v:self.c_v + 3] = np.inf
        np.copyto(inner[self.c_v:self.c_v + 3], var, where=known)
        del known
        inner[self.c_w] = cvalid & fvalid
        inner[self.c_f] = fvalid
        # log max(n, 1) (0 in the padding): all that Sec. 5.2's n_i^(-4/(d_c+4)) needs
        self.logn = np.zeros((self.hp, self.wp))
        self.logn[r:r + h, r:r + w] = np.log(np.maximum(nn, 1.0))
        self.logn = self.logn.ravel()
        for gi in range(len(groups)):
            noise[gi] *= fvalid
            _box_sum(np.pad(noise[gi], r), r, out=centre[gi])
        self.planes = planes.reshape(self.ncol, self.hp * self.wp)
        self.centre = centre.reshape(len(centre), self.hp * self.wp)

    def flat(self, rows, cols):
        return (rows + self.pad) * self.wp + (cols + self.pad)

    def release(self):
        self.planes = self.centre = self.logn = None


def _box_sum(plane: np.ndarray, r: int, out: np.ndarray | None = None) -> np.ndarray:
    """Sum over the (2r+1)^2 window around every pixel of a plane zero-padded
    by r (summed-area table, written into ``out`` when given); >= 0 for
    non-negative input."""
    hp, wp = plane.shape
    sat = np.zeros((hp + 1, wp + 1))
    body = sat[1:, 1:]
    np.cumsum(plane, axis=0, out=body)
    np.cumsum(body, axis=1, out=body)
    out = np.zeros((hp, wp)) if out is None else out
    out[...] = 0.0
    k = 2 * r + 1
    if hp >= k and wp >= k:
        o = out[r:hp - r, r:wp - r]
        np.subtract(sat[k:, k:], sat[:hp + 1 - k, k:], out=o)
        o -= sat[k:, :wp + 1 - k]
        o += sat[:hp + 1 - k, :wp + 1 - k]
    return np.maximum(out, 0.0, out=out)


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


# ------------------------------------------------------------------------ the models
def fit_centres(frame: _Frame, centre_flat: np.ndarray, params: Params, keep_models: bool = False,
                ws: _Workspace | None = None) -> dict:
    """Models of Sec. 4 at the given centre pixels (vectorised over centres).

    Builds each centre's TSVD-prefiltered design (Sec. 7), runs the ring-wise
    RLS (Eq. 3) and prediction-error recursion (Eq. 4, 5, 7), and picks per
    channel ``r_opt = argmin_r xi_c(k(r))`` (Eq. 2 with the estimate
    substituted; ties go to the smaller window, so zero-variance input keeps
    k(0)).  ``xi_c(k(r)) = xi_acc(k(r)) / |k(r)|`` with |k(r)| the number of
    usable pixels in the window.  Centres are processed in groups of equal
    model size p = d_c + 1, so each group's normal equations are only as large
    as its rank needs; they are sorted by p after the TSVD, so every group is a
    slice of the workspace (no copies), and each group's design is built one
    ring at a time (:class:`core.lp_solve.Design`).

    Returns a dict with ``index`` (N, K) flat padded pixel indices of every
    window, ``ring`` (K,), ``pred`` (N, 3, K) each model's prediction (Eq. 1)
    at every window pixel, ``beta`` (N, 3, D+1) optimal models (zero-padded),
    ``r_opt`` (N, 3), ``xi_opt`` (N, 3), ``xi`` (R+1, N, 3) all estimates,
    ``rank`` (N,) and, with ``keep_models``, ``P`` (N, 3, D+1, D+1) and
    ``transform`` (N, D, D).
    """
    radius = int(params.radius)
    dy, dx, ring, _ = ring_layout(radius)
    k = len(ring)
    n_c = len(centre_flat)
    d = frame.dim
    if ws is None:
        ws = _Workspace(n_c, k, d, radius)
    index = centre_flat[:, None] + (dy * frame.wp + dx)[None, :]
    nf = d - 2
    # features and their TSVD (Sec. 7); mode="clip" (the indices are in range)
    # writes straight into the workspace, mode="raise" would gather into a copy first
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
        feats, fvalid, frame.centre[:, centre_flat].T, frame.groups, radius,
        params.svd_floor, params.svd_noise_factor, params.min_rank,
        work=ws.view(ws.a, n_c, d, k))
    del fvalid
    feats -= feats[:, :, :1].copy()                                    # x_i - x_c
    # centres sorted by model size p = d_c + 1, so every group below is a slice
    order = np.argsort(rank, kind="stable")
    x = np.take(feats, order, axis=0, out=ws.view(ws.a, n_c, d, k), mode="clip")
    del feats
    g = ws.view(ws.b, 8, n_c, k)                                       # var0 | y | w | fvalid
    np.take(frame.planes[frame.c_v:], index[order], axis=1, out=g, mode="clip")
    var0, y = g[0:3], np.swapaxes(g[3:6], 0, 1)                        # (3, N, K), (N, 3, K)
    w, fvalid = g[6], g[7]
    centre_ok = w[:, 0] > 0
    beta0 = np.where(centre_ok[:, None], y[:, :, 0], 0.0)
    xi0 = np.where(centre_ok[:, None], var0[:, :, 0].T, np.inf)
    # s of Eq. 5/7, in place: the known variances (0 where unknown), or 0 for the literal equations
    if frame.subtract:
        np.copyto(var0, 0.0, where=~np.isfinite(var0))
    else:
        var0[...] = 0.0
    s = np.swapaxes(var0, 0, 1)

    xi = np.empty((radius + 1, n_c, 3))
    beta = np.zeros((n_c, 3, d + 1))
    pred = np.empty((n_c, 3, k))
    pinv = np.zeros((n_c, 3, d + 1, d + 1)) if keep_models else None
    idx_c = np.arange(3)[None, :]
    rank_s = rank[order]
    cuts = np.concatenate([[0], np.flatnonzero(np.diff(rank_s)) + 1, [n_c]])
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        p = int(rank_s[lo]) + 1
        sel = order[lo:hi]                                             # the group, in input order
        grp = slice(lo, hi)                                            # ... in sorted order
        design = Design(transform[sel][:, :, :p - 1], x[grp], fvalid[grp])
        x0 = xi0[grp]
        fits = ring_fits(design, y[grp], w[grp], s[grp], beta0[grp], x0, radius, params.delta,
                         keep_gram=keep_models, work=ws.ring(hi - lo, p))
        with np.errstate(divide="ignore", invalid="ignore"):
            xg = fits.xi_acc / fits.count[..., None]
        xg[0] = x0
        xg = np.where(np.isnan(xg), np.inf, xg)
        xi[:, sel] = xg
        r_g = np.argmin(xg, axis=0)                                    # first minimum
        idx_n = np.arange(hi - lo)[:, None]
        bg = np.swapaxes(fits.beta, 2, 3)[r_g, idx_n, idx_c]            # (n, 3, p)
        beta[sel, :, :p] = bg
        pred[sel] = design.predict(bg)
        if keep_models:
            pinv[sel, :, :p, :p] = np.linalg.inv(fits.gram[r_g, idx_n])
    r_opt = np.argmin(xi, axis=0)                                      # (N, 3)
    out = {"index": index, "ring": ring, "pred": pred, "rank": rank, "r_opt": r_opt, "xi": xi,
           "xi_opt": xi[r_opt, np.arange(n_c)[:, None], idx_c], "beta": beta}
    if keep_models:
        out["P"] = pinv
        out["transform"] = transform
    return out


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
    features : dict name -> (H, W, C)
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
    Memory: the padded input planes (8 (D + 7 + G) bytes per pixel, D the
    feature count with position, G the feature groups: 152 bytes with all
    three passes), running sums (88 bytes per pixel) and one workspace reused
    by every chunk (``_Workspace``), about
    ``chunk * 8 * (2 K max(D, 8) + 16 R (D + 4) + (R+1) (D+4)^2)`` bytes
    (K = (2R+1)^2; 20.6 MB for a chunk of 256), plus per-chunk
    temporaries of a few MB.  The window planes are gathered straight into
    the workspace, the design ``z`` is built one ring at a time
    (:class:`core.lp_solve.Design`), centres are sorted by model size so each
    size group is a slice, and the inputs derived from the buffers (variances
    of the means) are dropped before the fit.  Measured peak (tracemalloc, one
    :func:`reconstruct`, inputs excluded, all passes, default parameters):
    about 360 bytes per pixel at 512x512 (370 on a textured scene of rank 8),
    280 at 1024x1024.  The automatic chunk (``chunk = 0``: pixels / 1024,
    clamped to 32..256) keeps the workspace under ~80 bytes per pixel, so
    small images do not pay a fixed 20 MB (a chunk of 256 cost ~680 bytes per
    pixel at 256x256; the automatic 64 ~400, ~25 % slower there).
    Chunks are also limited to a band of rows so their scatter stays local.
    """
    params = params or Params()
    return _fit_frame(_pack(color, color_var, features, feature_var, n, params), params, keep_models)


def _pack(color, color_var, features, feature_var, n, params: Params) -> _Frame:
    color = np.asarray(color, np.float64)
    if color.ndim != 3 or color.shape[-1] != 3:
        raise ValueError(f"color must be (H, W, 3), got {color.shape}")
    return _Frame(color, color_var, features, feature_var, n, int(params.radius), params.variance_corrected)


def _fit_buffers(buf: Buffers, params: Params) -> LPFit:
    """:func:`fit` of accumulated buffers; the derived inputs (variances of the
    means) are dropped once the frame is packed, before the models are fitted."""
    return _fit_frame(_pack(*_inputs(buf), buf.n, params), params)


def _fit_frame(frame: _Frame, params: Params, keep_models: bool = False) -> LPFit:
    """Sec. 4-5 on a packed frame (see :func:`fit`); releases the frame's planes."""
    h, w = frame.h, frame.w
    radius = int(params.radius)
    k = (2 * radius + 1) ** 2
    chunk = int(params.chunk) if int(params.chunk) > 0 else auto_chunk(h * w)
    chunk = max(1, min(chunk, h * w))
    ws = _Workspace(chunk, k, frame.dim, radius)
    acc = _Accumulator(frame)
    covered = np.zeros((h, w), bool)
    is_centre = np.zeros((h, w), bool)
    rows, cols = np.arange(h)[:, None], np.arange(w)[None, :]
    grans = [max(int(params.granularity) or (2 * radius + 1), 1)]
    while grans[-1] > 1:
        grans.append(grans[-1] // 2)
    # rows per chunk: keep the scattered band (and the bincount temporaries of
    # ``_Accumulator.add``, 8 bytes per band pixel) under ~2^17 pixels
    band_rows = max(1, (1 << 17) // frame.wp - 2 * radius)
    centres, c_rad, c_rank, c_err = [], [], [], []
    models = {"beta": [], "P": [], "transform": []} if keep_models else None
    passes = 0
    for g in grans:
        cy, cx = np.nonzero((rows % g == 0) & (cols % g == 0) & ~is_centre & ~covered)
        if len(cy) == 0:
            continue
        passes += 1
        is_centre[cy, cx] = True
        s0 = 0
        while s0 < len(cy):
            s1 = min(s0 + chunk, int(np.searchsorted(cy, cy[s0] + band_rows)))
            yy, xx = cy[s0:s1], cx[s0:s1]
            res = fit_centres(frame, frame.flat(yy, xx), params, keep_models, ws)
            acc.add(res)
            centres.append(np.stack([yy, xx], axis=1))
            c_rad.append(res["r_opt"])
            c_rank.append(res["rank"])
            c_err.append(res["xi_opt"])
            if keep_models:
                models["beta"].append(res["beta"])
                models["P"].append(res["P"])
                models["transform"].append(res["transform"])
            del res
            s0 = s1
        covered = (acc.crop(acc.cnt) > 0).all(axis=0)
    del ws

    if keep_models and centres:
        allc = np.concatenate(centres)
        cfeat = np.zeros((len(allc), frame.dim))
        cfeat[:, 2:] = frame.planes[:frame.dim - 2, frame.flat(allc[:, 0], allc[:, 1])].T
    frame.release()                      # the inputs are no longer needed: lower the peak
    safe = np.maximum(acc.crop(acc.cnt), 1.0)
    image = np.ascontiguousarray(np.moveaxis(acc.crop(acc.pred) / safe, 0, -1))
    acc.pred = None
    image[~np.isfinite(image)] = 0.0
    err = _finite_errors(acc.crop(acc.err) / safe)
    acc.err = None
    error = err.mean(axis=0)
    del err
    dxi = np.ascontiguousarray(np.moveaxis(_finite_errors(acc.crop(acc.dxi) / safe), 0, -1))
    acc.dxi = None
    out = LPFit(
        image=image,
        error=error,
        delta_error=dxi,
        radius=acc.crop(acc.rad[None])[0] / safe.sum(axis=0),
        centers=np.concatenate(centres) if centres else np.zeros((0, 2), np.int64),
        center_radius=np.concatenate(c_rad) if c_rad else np.zeros((0, 3), np.int64),
        center_rank=np.concatenate(c_rank) if c_rank else np.zeros(0, np.int64),
        center_error=np.concatenate(c_err) if c_err else np.zeros((0, 3)),
        passes=passes,
    )
    if keep_models and centres:
        models = {key: np.concatenate(v) for key, v in models.items()}
        models["center_features"] = cfeat
        out.models = models
    return out


class _Accumulator:
    """Per-pixel running sums over the padded frame: predictions, errors,
    Sec. 5.2 error reductions and model counts per channel, and the sum of the
    covering models' radii."""

    def __init__(self, frame: _Frame):
        self.frame = frame
        size = frame.hp * frame.wp
        self.pred = np.zeros((3, size))
        self.err = np.zeros((3, size))
        self.dxi = np.zeros((3, size))
        self.cnt = np.zeros((3, size), np.float32)      # exact integers below 2^24
        self.rad = np.zeros(size, np.float32)

    def crop(self, a):
        f = self.frame
        return a.reshape(a.shape[:-1] + (f.hp, f.wp))[..., f.pad:f.pad + f.h, f.pad:f.pad + f.w]

    def add(self, res: dict) -> None:
        """Add each centre's predictions over its optimal window (Eq. 1), with
        its error xi_c(k_opt) and ``xi_c(k_opt) n_i^(-4/(d_c+4))`` (Sec. 5.2).

        Windows are prefixes of the ring-ordered pixel list, so only the
        ``(2 r_opt + 1)^2`` pixels inside are scattered (bincount over the band
        of pixels the chunk touches)."""
        index, r_opt = res["index"], res["r_opt"]
        lo = int(index.min())
        span = int(index.max()) + 1 - lo
        sl = slice(lo, lo + span)
        k = index.shape[1]
        pred = res["pred"]                                               # (N, 3, K)
        expo = -4.0 / (res["rank"].astype(np.float64) + 4.0)             # (N,)
        positions = np.arange(k)
        logn = self.frame.logn
        for c in range(3):
            length = (2 * r_opt[:, c] + 1) ** 2
            inside = positions[None, :] < length[:, None]                # (N, K), a prefix per row
            local = index[inside]                                        # entries, centre by centre
            xi = np.repeat(res["xi_opt"][:, c], length)
            # xi n_i^(-4/(d_c+4)), the error reduction rate of Moon et al. 2014 (n clamped to >= 1)
            dxi = np.take(logn, local)
            dxi *= np.repeat(expo, length)
            np.exp(dxi, out=dxi)
            dxi *= xi
            local -= lo
            self.pred[c, sl] += np.bincount(local, pred[:, c][inside], span)
            del inside
            self.err[c, sl] += np.bincount(local, xi, span)
            self.dxi[c, sl] += np.bincount(local, dxi, span)
            del xi, dxi
            self.cnt[c, sl] += np.bincount(local, None, span).astype(np.float32)
            rad = np.repeat(r_opt[:, c].astype(np.float64), length)
            self.rad[sl] += np.bincount(local, rad, span).astype(np.float32)


def _finite_errors(err: np.ndarray) -> np.ndarray:
    """Clamp estimated errors to >= 0 and replace non-finite ones by the largest
    finite estimate of the image (0 when there is none)."""
    fin = np.isfinite(err)
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


def reconstruct(buf: Buffers, params: Params | None = None) -> MethodResult:
    """LP reconstruction (Moon et al. 2015) of the accumulated buffers.

    Returns
    -------
    MethodResult
        ``image`` (H, W, 3), ``error`` (H, W) = estimated squared error
        ``xi_c(k_opt)`` (Eq. 4) of the covering models averaged over RGB, and
        ``info`` with ``center_fraction`` (paper: 4.7-18.9 %), ``centers``,
        ``passes``, ``mean_radius``, ``mean_rank`` (scalars) and ``lp_fit``
        (the :class:`LPFit`, used by :func:`sample_map`).
    """
    params = params if isinstance(params, Params) else params_from_dict(Params, params)
    return _result(_fit_buffers(buf, params))


def _result(res: LPFit) -> MethodResult:
    info = {
        "center_fraction": res.center_fraction,
        "centers": int(len(res.centers)),
        "passes": int(res.passes),
        "mean_radius": float(res.center_radius.mean()) if len(res.centers) else 0.0,
        "mean_rank": float(res.center_rank.mean()) if len(res.centers) else 0.0,
        "lp_fit": res,
    }
    return MethodResult(res.image, res.error, info)


def sample_map(buf: Buffers, result: MethodResult, budget: int, params: Params | None = None,
               state: dict | None = None) -> np.ndarray:
    """New samples per pixel for the next iteration (Sec. 5.2 of Moon et al. 2015).

    ``Delta_i xi = xi_c(k_opt) n_i^(-4/(d_c+4))`` (the error reduction one more
    sample brings, d_c the centre's TSVD rank, averaged over the models covering
    pixel i), relative error ``rho_i = Delta_i xi / (f_hat(x_i)^2 + epsilon)``
    per channel (averaged over RGB), and ``Delta n_i = T rho_i / sum_j rho_j``
    rounded by :func:`core.method.allocate` so the map sums to ``budget``.

    Returns
    -------
    (H, W) int64, >= 0, summing to ``budget``.
    """
    params = params if isinstance(params, Params) else params_from_dict(Params, params)
    fitres = result.info.get("lp_fit") if result is not None else None
    if not isinstance(fitres, LPFit) or fitres.image.shape[:2] != buf.shape:
        fitres = _fit_buffers(buf, params)
    if state is not None:
        state["iterations"] = int(state.get("iterations", 0)) + 1
    f = fitres.image
    rho = (fitres.delta_error / (f * f + params.epsilon)).mean(axis=-1)
    return allocate(rho, budget)


def denoise(color: np.ndarray, color_var: np.ndarray, features: dict, params: Params | None = None,
            feature_var: dict | None = None, n: np.ndarray | None = None) -> MethodResult:
    """LP on plain arrays: ``color`` (H, W, 3), ``color_var`` (H, W, 3) variance
    of the mean, ``features`` name -> (H, W, C) (see :func:`fit`)."""
    params = params if isinstance(params, Params) else params_from_dict(Params, params)
    return _result(fit(color, color_var, features, feature_var, n, params))

"""Temporal accumulation of reconstructed frames (``--temporal blend``).

What and why: every method ends a frame with an image ``D_t`` and an estimated
per-pixel squared error ``E_t``.  With independent noise per frame (the
animated seed), the previous frame's output, warped into this frame where it
shows the same surface, is a second estimate of the pixel; combining the two
by their errors lowers both the per-frame error and the flicker.  This is the
temporal accumulation of real-time denoisers (Schied et al. 2017, SVGF: a
bilinear reprojection with depth / normal / object tests per tap and an
exponential moving average), with the fixed blend factor replaced by the
weights our error estimates give, and a change test that keeps moving
highlights and shadows from smearing.

Per frame (:func:`blend`):

1. :func:`warp` the history (previous output, its error, its length in frames)
   to the backward coordinates (``core.reproject.backward_coordinates``):
   bilinear over the four previous pixels around the point, each tap kept only
   where it is the same surface as the current pixel (both background, or
   positions within ``tolerance * distance + pixels * footprint``, normals within
   ``normal_cos``, the same object index) and renormalised over the kept taps;
   a pixel whose kept taps weigh less than ``min_tap_weight`` has no history.
   With ``resample="catmull-rom"`` (auto for denoisers) the image (not its
   error) is the separable Catmull-Rom spline over the 4x4 pixels around the
   point wherever every tap of non-zero weight passes the same-surface test
   (the outer taps with a slack grown by their distance), clamped per channel to
   the range of the 2x2 nearest values (the spline's overshoot would ring at
   edges and could turn negative); elsewhere bilinear.  Why: bilinear
   resampling low-pass filters a camera pan by up to half a pixel per frame,
   and the blur adds up over the carried frames (measured, docs/notes/flicker.md).
   The error stays the bilinear mean of the taps' errors: a conservative
   choice (errors of neighbouring pixels are correlated after a denoiser).
2. Change test: with ``d^2`` the RGB mean of ``(D - W)^2``, the history is
   dropped where ``d^2 > z^2 (E~ + e~)``, ``E~`` / ``e~`` the errors pooled over a
   ``(2 pool_radius + 1)^2`` window (the per-pixel estimates are too noisy to
   threshold alone; docs/notes/oidn.md), each at least its own pixel's value:
   a firefly's large error is its own, and the window's mean would both drop
   its history and give it the weight (measured: 2.5-5 % lower relMSE for
   uniform and var on both animated scenes, docs/notes/flicker.md).
3. Bias of the history: ``b^2 = max(d~^2 - E~ - e~, 0)``, ``d~^2`` the squared
   difference averaged over a ``(2 bias_radius + 1)^2`` window, is what the
   warped history adds beyond both errors (bilinear resampling of a panning
   camera's frame, view-dependent change below the test); it is added to the
   history's error.  Without it the history was weighted as if exact where
   resampling blurred it (measured: the warped 1024-spp reference of the
   previous frame is as far from this frame's reference as OIDN's own error).
4. Weights: the current frame's weight ``w = e~ / (E~ + e~)`` (inverse-variance),
   at least ``1 / max_frames``, so no history outweighs the last
   ``max_frames`` frames (with exact and equal per-frame errors the weight is
   ``1 / (n + 1)`` after n frames, the running mean).  Output ``w D + (1 - w) W``.
5. Error of the output: ``w^2 E + (1 - w)^2 (e + b^2)``, assuming the two errors
   independent.  Choice: the bias part of a denoiser's error (blur) is shared
   between frames and does not average; ``max_frames`` bounds what this
   underestimate can do, and the benchmark reports the estimate's correlation
   with the true error as for every method.

By default the history enters *before* the method instead:
:func:`accumulate` averages this frame's noisy samples with the previous
frames' (warped the same way, at most ``input_frames`` frames' worth), and
the method samples and reconstructs those buffers (its docstring has the
steps); the output blend above then is off (``max_frames`` auto 1).  It
runs with ``input_frames = 1`` (or an explicit ``max_frames``).  Measured
(docs/notes/flicker.md): the input history gave lower per-frame and
temporal error than the output blend for every method.

A frame where fewer than ``min_valid_fraction`` of the pixels find a history
(a camera cut) starts over everywhere.  Non-finite pixels of the current image
take the history where it is valid and 0 otherwise, with an infinite error
replaced by the largest finite one; the output is always finite.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .buffers import Buffers, is_background
from .filters import box_mean_finite
from .method import param


@dataclass(frozen=True)
class Params:
    """Blend settings (module docstring)."""

    z: float = param(3.0, "change test: the previous frame's output is dropped where it differs from this "
                     "frame's by more than this many (pooled) standard errors of the difference; smaller "
                     "reacts faster to moving light, larger reuses more", 0.0, 100.0, label="Change Test (sigma)")
    max_frames: int = param(-1, "longest history of the output blend, in frames: this frame keeps at least "
                            "1/max_frames of the weight; larger averages more frames on static parts, smaller "
                            "follows change sooner; 1 = no output blend; -1 = auto: 1 where the input "
                            "carries the history (Input History > 1: consecutive outputs share those "
                            "samples, and blending them again was measured worse; 2 for lp, which gained), "
                            "else 8",
                            -1, 1024, label="Max History (frames)")
    pool_radius: int = param(-1, "radius of the window over which both error estimates are averaged before "
                             "the change test and the weights; 0 = per pixel; -1 = auto: 3 for methods whose "
                             "image is the sample mean (uniform, var: their per-pixel variance has few degrees "
                             "of freedom), 0 for denoisers (their error maps are pooled already)", -1, 16,
                             label="Error Pooling")
    bias_radius: int = param(-1, "radius of the window over which the squared difference between this frame "
                             "and the history is averaged to estimate what the history adds beyond both "
                             "errors (resampling blur, slow change); 0 = per pixel; -1 = auto: 1 for the "
                             "sample mean (uniform, var), 0 for denoisers", -1, 16, label="Bias Window")
    tolerance: float = param(0.01, "same-surface test: largest position difference between a previous pixel "
                             "and this one, as a fraction of the camera distance", 0.0, 1.0,
                             label="Position Tolerance")
    pixels: float = param(1.0, "same-surface test slack in pixel footprints (sub-pixel offsets on slanted "
                          "surfaces)", 0.0, 16.0, label="Position Slack (px)")
    normal_cos: float = param(0.9, "same-surface test: smallest cosine between the previous and the current "
                              "normal; 0 disables", -1.0, 1.0, label="Normal Agreement")
    object_tolerance: float = param(1e-3, "largest object index change still counted as the same object",
                                    0.0, 1.0, label="Object Index Tolerance")
    min_tap_weight: float = param(0.25, "a pixel keeps its history only if the bilinear weights of its "
                                  "same-surface taps sum to at least this", 0.0, 1.0, label="Min Tap Weight")
    resample: str = param("auto", "how the previous frame is read between its pixels: catmull-rom "
                          "(4x4 pixels, keeps the detail of a panning camera; bilinear at silhouettes), "
                          "bilinear (2x2, blurs by up to half a pixel per frame, and averages noise), or auto: "
                          "bilinear for the sample mean (uniform, var), catmull-rom for denoisers",
                          choices=("auto", "catmull-rom", "bilinear"), label="Resampling")
    min_valid_fraction: float = param(0.01, "below this share of pixels with a history the frame counts as "
                                      "a camera cut and starts over", 0.0, 1.0, label="Min History Share")
    input_frames: int = param(-1, "longest history of the method's input, in frames' samples: the noisy "
                              "samples of the previous frames, warped, are averaged into this frame's before "
                              "the method samples and reconstructs, holding at most this many frames' worth; "
                              "1 = off (then the outputs are blended instead); -1 = auto: 2 for denoisers "
                              "(oidn, awr, rhf; longer histories made OIDN worse), 8 for lp, 4 for the sample "
                              "mean (uniform, var)", -1, 64, label="Input History (frames)")
    input_max_specular_share: float = param(1.0, "the input history is not carried where glossy + "
                                            "transmission light exceeds this share of the pixel's luminance "
                                            "(reflections move unlike their surface; Schalk's reprojection "
                                            "never reuses specular pixels); 1 = no limit (the default: 0.5 measured no better, the "
                                            "change test already drops what moved)", 0.0, 1.0,
                                            label="Input Max Specular Share")
    input_pool_radius: int = param(1, "radius of the window over which the variances are averaged for the "
                                   "input history's change test and weights; 0 = per pixel", 0, 16,
                                   label="Input Error Pooling")


#: methods whose image is the sample mean: their errors are pooled before use (``resolve``)
SAMPLE_MEAN_METHODS = ("uniform", "var")
#: denoisers whose auto history is longer: method -> (input frames, output blend frames).
#: LP's local regressions, which know the variance they are given, gained with 8 input
#: frames and a 2-frame output blend on both animated scenes, where OIDN lost with more
#: than 2 input frames (docs/notes/flicker.md)
LONG_INPUT_METHODS = {"lp": (8, 2)}


def resolve(params: Params, method: str | None) -> Params:
    """``params`` with the auto values set for ``method``: radii (-1) pooled
    (3, 1) and bilinear resampling for the sample mean; per pixel (0, 0) and
    Catmull-Rom for denoisers and for ``None``.  Measured on the animated
    scene (docs/notes/flicker.md): uniform gains 0.66x relMSE with (3, 1)
    against 0.78x with (0, 0); oidn 0.96x with (0, 0) against 1.0x with
    (3, 1).  Catmull-Rom: uniform / var 0.8-0.9 % worse than bilinear (its
    negative lobes pass more of the noise), lp / oidn 0.2-0.3 % better.
    Input history (-1): 2 frames for denoisers and ``None``, 4 for the
    sample mean, 8 for lp (``LONG_INPUT_METHODS``); the output blend's
    ``max_frames`` (-1): 1 (off) with input history (2 for lp), else 8
    (``None``: a direct call of :func:`blend`).  Measured
    (docs/notes/flicker.md): the input history beats the output blend for
    every method; OIDN lost with more than 2 frames, the sample mean gained
    most with 4, lp with 8 and a 2-frame output blend."""
    import dataclasses
    pooled = method in SAMPLE_MEAN_METHODS
    resample = params.resample if params.resample != "auto" else ("bilinear" if pooled else "catmull-rom")
    auto_input, auto_output = LONG_INPUT_METHODS.get(method, (4 if pooled else 2, 1))
    input_frames = params.input_frames if params.input_frames >= 1 else auto_input
    return dataclasses.replace(
        params, pool_radius=params.pool_radius if params.pool_radius >= 0 else (3 if pooled else 0),
        bias_radius=params.bias_radius if params.bias_radius >= 0 else (1 if pooled else 0), resample=resample,
        input_frames=input_frames,
        max_frames=params.max_frames if params.max_frames >= 1 else (auto_output if method is not None
                                                                     and input_frames > 1 else 8))


@dataclass
class Surface:
    """What the same-surface test compares, per pixel: world position (H, W, 3),
    background mask (H, W), unit normal (H, W, 3) or None, object index (H, W)
    or None, and the footprint (H, W): world distance to the nearest neighbour
    hit (a pixel's size on its surface)."""

    position: np.ndarray
    background: np.ndarray
    normal: np.ndarray | None
    object_index: np.ndarray | None
    footprint: np.ndarray

    @classmethod
    def from_buffers(cls, buf: Buffers) -> "Surface":
        """The Surface of a frame's buffers (needs the ``position`` feature)."""
        if "position" not in buf.features:
            raise ValueError("temporal blend needs the Position pass")
        pos = np.asarray(buf.features["position"].mean, np.float64)
        depth = buf.features["depth"].mean if "depth" in buf.features else None
        finite = np.all(np.isfinite(pos), axis=-1)
        pos = np.where(finite[..., None], pos, np.nan)
        bg = is_background(np.nan_to_num(pos, nan=1.0), depth) & finite
        normal = None
        if "normal" in buf.features:
            n = np.asarray(buf.features["normal"].mean, np.float64)
            length = np.linalg.norm(n, axis=-1, keepdims=True)
            with np.errstate(invalid="ignore", divide="ignore"):
                normal = np.where(length > 1e-6, n / np.where(length > 1e-6, length, 1.0), np.nan)
        oi = buf.features["object_index"].mean[..., 0].astype(np.float64) if "object_index" in buf.features \
            else None
        return cls(pos, bg, normal, oi, footprint(pos, bg))


def footprint(pos: np.ndarray, background: np.ndarray) -> np.ndarray:
    """(H, W) world distance from each surface pixel to its nearest surface
    neighbour (4-neighbourhood): the pixel's size on its surface.  The
    nearest, so that at a silhouette the other side does not count; NaN
    where no neighbour is a surface hit."""
    h, w = background.shape
    surf = np.where((~background)[..., None], pos, np.nan)
    best = np.full((h, w), np.inf)
    for axis in (0, 1):
        d = np.linalg.norm(np.diff(surf, axis=axis), axis=-1)  # NaN where either side is not a surface
        d = np.where(np.isfinite(d), d, np.inf)
        if axis == 0:
            best[1:] = np.minimum(best[1:], d)
            best[:-1] = np.minimum(best[:-1], d)
        else:
            best[:, 1:] = np.minimum(best[:, 1:], d)
            best[:, :-1] = np.minimum(best[:, :-1], d)
    return np.where(np.isfinite(best), best, np.nan)


@dataclass
class History:
    """The carried state: the last output (H, W, 3), its error (H, W), how many
    frames it averages (H, W), and the Surface of its frame.  The input
    history of :func:`accumulate` has the same shape of data: the
    accumulated means of both halves (H, W, 6), the variance of their mean
    (H, W) and the samples they hold (H, W)."""

    image: np.ndarray
    error: np.ndarray
    length: np.ndarray
    surface: Surface

    @property
    def shape(self):
        return self.error.shape


@dataclass
class Result:
    image: np.ndarray
    error: np.ndarray
    history: History
    info: dict


def catmull_rom_weights(t: np.ndarray) -> tuple:
    """The four Catmull-Rom spline weights of the pixels at offsets -1, 0, 1, 2
    from a point a fraction ``t`` in [0, 1) past pixel 0 (they sum to 1 and
    reproduce linear functions exactly)."""
    t2, t3 = t * t, t * t * t
    return ((-t + 2 * t2 - t3) / 2, (2 - 5 * t2 + 3 * t3) / 2, (t + 4 * t2 - 3 * t3) / 2, (t3 - t2) / 2)


def warp(history: History, coords: np.ndarray, current: Surface, camera_position, params: Params):
    """The history at each current pixel: (image (H, W, C), error (H, W), length
    (H, W), valid (H, W) bool, spline (H, W) bool: read by Catmull-Rom).
    ``coords`` (H, W, 2) continuous (row, col) in the previous frame (NaN:
    none), ``camera_position`` (3,) this frame's camera (the distance of the
    tolerance).  Bilinear, or Catmull-Rom for the image where every tap is
    the same surface (module docstring, step 1)."""
    h, w = current.background.shape
    hp, wp = history.shape
    r = coords[..., 0] - 0.5
    c = coords[..., 1] - 0.5
    has = np.isfinite(r) & np.isfinite(c)
    r = np.where(has, r, 0.0)
    c = np.where(has, c, 0.0)
    r0, c0 = np.floor(r).astype(np.int64), np.floor(c).astype(np.int64)
    fr, fc = r - r0, c - c0
    dist = np.linalg.norm(current.position - np.asarray(camera_position, np.float64), axis=-1)
    foot = np.nan_to_num(current.footprint, nan=0.0)
    tol = params.tolerance * dist + params.pixels * foot
    prev = history.surface
    # per previous pixel, flat: gathers by flat index (np.take) are the cost of every tap
    usable = (np.all(np.isfinite(history.image), axis=-1) & np.isfinite(history.error)).ravel()
    p_bg, p_pos = prev.background.ravel(), prev.position.reshape(-1, 3)
    use_normal = params.normal_cos > -1.0 and prev.normal is not None and current.normal is not None
    p_nrm = prev.normal.reshape(-1, 3) if use_normal else None
    use_oi = prev.object_index is not None and current.object_index is not None
    p_oi = prev.object_index.ravel() if use_oi else None
    p_img = history.image.reshape(hp * wp, -1)
    p_err, p_len = history.error.ravel(), history.length.ravel()

    def tap(dr, dc, outer=False):
        """(kept, flat index) of the previous pixel at (r0 + dr, c0 + dc); an
        ``outer`` tap of the spline is up to 2 px from the point, and its
        position slack grows by its distance beyond half a pixel (in
        footprints), the margin an inner tap half a pixel away has."""
        rr, cc = r0 + dr, c0 + dc
        t = tol + np.maximum(np.hypot(dr - fr, dc - fc) - 0.5, 0.0) * foot if outer else tol
        ok = has & (rr >= 0) & (rr < hp) & (cc >= 0) & (cc < wp)
        flat = np.clip(rr, 0, max(hp - 1, 0)) * wp + np.clip(cc, 0, max(wp - 1, 0))
        pbg = np.take(p_bg, flat)
        with np.errstate(invalid="ignore"):
            d = np.take(p_pos, flat, axis=0) - current.position
            near = np.einsum("...k,...k->...", d, d) <= t * t
            same = np.where(current.background, pbg, ~pbg & ~current.background & near)
            if use_normal:
                cos = np.einsum("...k,...k->...", np.take(p_nrm, flat, axis=0), current.normal)
                same &= current.background | (cos >= params.normal_cos)
            if use_oi:
                same &= np.abs(np.take(p_oi, flat) - current.object_index) <= params.object_tolerance
        ok &= same & np.take(usable, flat)
        return ok, flat

    img = np.zeros((h, w, history.image.shape[-1]))
    err = np.zeros((h, w))
    length = np.zeros((h, w))
    wsum = np.zeros((h, w))
    spline_on = resolve(params, None).resample == "catmull-rom"
    lo = np.full(img.shape, np.inf) if spline_on else None
    hi = np.full(img.shape, -np.inf) if spline_on else None
    for dr, dc in ((0, 0), (0, 1), (1, 0), (1, 1)):
        bw = (fr if dr else 1.0 - fr) * (fc if dc else 1.0 - fc)
        ok, flat = tap(dr, dc)
        ok &= bw > 0
        wt = np.where(ok, bw, 0.0)
        hv = np.where(ok[..., None], np.take(p_img, flat, axis=0), 0.0)
        img += wt[..., None] * hv
        err += wt * np.where(ok, np.take(p_err, flat), 0.0)
        length += wt * np.where(ok, np.take(p_len, flat), 0.0)
        wsum += wt
        if spline_on:  # the clamp range of the spline
            lo = np.where(ok[..., None], np.minimum(lo, hv), lo)
            hi = np.where(ok[..., None], np.maximum(hi, hv), hi)
    valid = wsum >= max(params.min_tap_weight, 1e-12)
    inv = np.where(valid, 1.0 / np.where(valid, wsum, 1.0), 0.0)
    img *= inv[..., None]
    whole = np.zeros((h, w), bool)
    if spline_on:
        wr, wc = catmull_rom_weights(fr), catmull_rom_weights(fc)
        spline = np.zeros(img.shape)
        whole = valid.copy()
        for i, dr in enumerate((-1, 0, 1, 2)):
            for j, dc in enumerate((-1, 0, 1, 2)):
                wt = wr[i] * wc[j]
                ok, flat = tap(dr, dc, outer=True)
                whole &= ok | (wt == 0)
                spline += np.where(ok, wt, 0.0)[..., None] * np.where(ok[..., None], np.take(p_img, flat, axis=0),
                                                                      0.0)
        img = np.where(whole[..., None], np.clip(spline, lo, hi), img)
    return img, err * inv, length * inv, valid, whole


def blend(image: np.ndarray, error: np.ndarray, current: Surface, history: History | None,
          coords: np.ndarray | None, camera_position, params: Params | None = None) -> Result:
    """This frame's output from its reconstruction (``image`` (H, W, 3), its
    ``error`` (H, W)) and the previous frame's ``history`` warped by ``coords``
    (module docstring, steps 1-5).  ``history`` None: the first frame."""
    params = resolve(params or Params(), None)
    image = np.asarray(image, np.float64)
    error = np.asarray(error, np.float64)
    h, w = error.shape
    bad = ~(np.all(np.isfinite(image), axis=-1) & np.isfinite(error))
    finite_err = error[np.isfinite(error)]
    big = float(finite_err.max()) if finite_err.size else 1.0
    D = np.where(bad[..., None], 0.0, image)
    E = np.where(bad, max(big, 1.0), np.maximum(error, 0.0))
    info = {"history_fraction": 0.0, "changed_fraction": 0.0, "cut": False, "history_weight": 0.0,
            "spline_fraction": 0.0}
    if history is None or coords is None or h * w == 0 or params.max_frames <= 1:  # 1: no output blend
        return _result(D, E, np.ones((h, w)), current, info)
    W, e, L, valid, spline = warp(history, np.asarray(coords, np.float64), current, camera_position, params)
    e = np.maximum(e, 0.0)
    if valid.mean() < params.min_valid_fraction:
        info["cut"] = True
        return _result(D, E, np.ones((h, w)), current, info)
    r = params.pool_radius
    Ep = box_mean_finite(np.where(bad, np.nan, E), r) if r > 0 else E
    ep = box_mean_finite(np.where(valid, e, np.nan), r) if r > 0 else e
    Ep = np.where(np.isfinite(Ep), Ep, E)
    ep = np.where(np.isfinite(ep), ep, e)
    Ep = np.maximum(Ep, E)   # pooling steadies a low-dof estimate; it must not hide a firefly's own error
    ep = np.maximum(ep, e)
    d2 = np.mean((D - W) ** 2, axis=-1)
    changed = valid & ~bad & (d2 > params.z ** 2 * (Ep + ep))
    use = valid & ~changed
    if params.bias_radius > 0:
        d2p = box_mean_finite(np.where(use, d2, np.nan), params.bias_radius)
        d2p = np.where(np.isfinite(d2p), d2p, d2)
    else:
        d2p = d2
    bias2 = np.maximum(d2p - Ep - ep, 0.0)   # what the history adds beyond both errors: resampling, change
    ep = ep + bias2
    e = e + bias2
    with np.errstate(invalid="ignore", divide="ignore"):
        wc = np.where(Ep + ep > 0, ep / np.where(Ep + ep > 0, Ep + ep, 1.0), 0.5)
    wc = np.clip(wc, 1.0 / params.max_frames, 1.0)
    wc = np.where(bad, 0.0, wc)
    wc = np.where(use, wc, 1.0)
    out_img = wc[..., None] * D + (1.0 - wc[..., None]) * np.where(use[..., None], W, 0.0)
    out_err = wc ** 2 * E + (1.0 - wc) ** 2 * np.where(use, e, 0.0)
    out_err = np.where(bad & ~use, max(big, 1.0), out_err)
    length = np.where(use, np.minimum(L, params.max_frames - 1) + 1.0, 1.0)
    info.update(history_fraction=float(use.mean()), changed_fraction=float(changed.mean()),
                history_weight=float(np.mean(1.0 - wc)), spline_fraction=float((use & spline).mean()))
    return _result(out_img, out_err, length, current, info)


def _result(image, error, length, surface, info) -> Result:
    image = np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
    error = np.nan_to_num(error, nan=0.0, posinf=np.finfo(np.float64).max, neginf=0.0)
    return Result(image, error, History(image, error, length, surface), info)


@dataclass
class Accumulated:
    """What :func:`accumulate` gives: the buffers a method reconstructs, the
    input history to carry to the next frame, and counts for the frame's info."""

    buffers: Buffers
    history: History
    info: dict


def accumulate(buf: Buffers, history: History | None, coords, camera_position,
               params: Params | None = None, cache: dict | None = None) -> Accumulated:
    """This frame's samples averaged with the previous frames' warped samples,
    as Buffers any method reconstructs (``--temporal blend`` for denoisers).

    Why: a denoiser fed one frame's samples leaves low-frequency residue that
    differs per frame (flicker); blending its *outputs* cannot remove what
    both outputs share.  Averaging the noisy *input* over frames, where the
    surface is the same and the samples agree, gives the denoiser more
    samples, as temporal accumulation before a denoiser does in real-time
    renderers (Schied et al. 2017, SVGF).  Measured offline on the animated
    scene (docs/notes/flicker.md): OIDN on the input accumulated over at
    most 2 frames 0.91x relMSE and 0.83x temporal error of OIDN per frame;
    longer histories lose (the carried, resampled samples have spatially
    correlated noise that OIDN keeps as detail), hence ``input_frames``.

    Per pixel, with ``C`` this frame's mean, ``v`` its variance of the mean
    (RGB mean; unknown where fewer than two groups), ``n`` its samples:

    1. both halves' accumulated means are warped together (:func:`warp`, the
       same-surface taps); ``W`` is their mix in this frame's half shares;
    2. change test ``d^2 <= z^2 (v~ + e~)`` (``d^2`` the RGB mean of ``(C -
       W)^2``, ``~``: pooled over ``input_pool_radius``, at least the pixel's
       own), as :func:`blend`'s step 2;
    3. bias ``b^2 = max(d~^2 - v~ - e~, 0)`` added to the history's variance;
    4. this frame's weight ``w = max(e_h / (v~ + e_h), n / (n + m))`` with
       ``e_h = e~ + b^2`` and ``m = min(L, (input_frames - 1) n)`` the
       history's samples ``L`` capped; each half ``w X + (1 - w) W_X``;
    5. the buffers: the accumulated halves, their mean in this frame's half
       shares, ``n / w`` samples (the effective count of the weighted mean),
       the colour's M2 scaled so the variance of the mean is ``w^2 v + (1 -
       w)^2 (e + b^2)`` per channel in proportion to this frame's, and this
       frame's features (their variance of the mean unchanged).

    The halves stay disjoint (half A's chain never meets half B's), so a
    dual-buffer error estimate (core/oidn.py) still holds.  Without stored
    halves (buffers read from a file) the whole mean is carried as both.
    A frame where fewer than ``min_valid_fraction`` of the pixels find a
    history starts over.  ``history`` None: the first frame (``buf`` is
    returned as it is).

    ``coords``: the backward coordinates (:func:`warp`), or a callable giving
    them (called only when the warp is computed).  ``cache``: a dict the
    caller keeps over one frame's calls (the sampler reads the buffers after
    every round): the warp, 20 taps of the same-surface test and most of the
    cost, is reused until the frame's samples have doubled since it was
    computed (the position and normal passes it tests change little with
    more samples); steps 2-5 are recomputed on every call."""
    params = resolve(params or Params(), None)
    h, w = buf.shape
    n = np.asarray(buf.n, np.float64)
    C = np.asarray(buf.color.mean, np.float64)
    halves = buf.color_halves()
    if halves is not None:
        (na, ca), (nb, cb) = halves
        with np.errstate(invalid="ignore", divide="ignore"):
            share = np.where(n > 0, na / np.where(n > 0, n, 1.0), 0.5)
    else:
        ca = cb = C
        share = np.full((h, w), 0.5)
    with np.errstate(invalid="ignore"):
        v = buf.variance_of_mean().mean(axis=-1)
    known = np.isfinite(v) & (n > 0) & np.all(np.isfinite(C), axis=-1)
    cur = np.concatenate([ca, cb], axis=-1)
    surface = Surface.from_buffers(buf)
    info = {"input_history_fraction": 0.0, "input_changed_fraction": 0.0, "input_history_weight": 0.0,
            "input_cut": False}

    def carried(halves6, var, samples):
        halves6 = np.nan_to_num(halves6, nan=0.0, posinf=0.0, neginf=0.0)
        var = np.where(known & np.isfinite(var), np.maximum(var, 0.0), np.inf)  # inf: warp drops the tap
        return History(halves6, var, samples, surface)

    if history is None or coords is None or h * w == 0 or params.input_frames <= 1:
        return Accumulated(buf, carried(cur, v, n), info)
    total = float(np.sum(n))
    warped = None
    if cache is not None and cache.get("history") is history and cache.get("shape") == (h, w) \
            and total < 2.0 * cache.get("samples", -np.inf):
        warped = cache["warp"]
    if warped is None:
        xy = coords() if callable(coords) else coords
        if xy is None:
            return Accumulated(buf, carried(cur, v, n), info)
        warped = warp(history, np.asarray(xy, np.float64), surface, camera_position, params)
        if cache is not None:
            cache.update(history=history, shape=(h, w), samples=total, warp=warped)
    W6, e, L, valid, _ = warped
    if valid.mean() < params.min_valid_fraction:
        info["input_cut"] = True
        return Accumulated(buf, carried(cur, v, n), info)
    e = np.maximum(e, 0.0)
    ok = valid & known & np.isfinite(e)
    if params.input_max_specular_share < 1.0:
        ok &= ~(specular_share(buf) > params.input_max_specular_share)
    WA, WB = W6[..., :3], W6[..., 3:]
    W = share[..., None] * WA + (1.0 - share[..., None]) * WB
    r = params.input_pool_radius

    def pooled(x, where):
        if r <= 0:
            return x
        p = box_mean_finite(np.where(where, x, np.nan), r)
        return np.maximum(np.where(np.isfinite(p), p, x), x)

    vz = np.where(known, v, 0.0)
    vp = pooled(vz, known)
    ep = pooled(e, ok)
    d2 = np.mean((C - W) ** 2, axis=-1)
    with np.errstate(invalid="ignore"):
        use = ok & (d2 <= params.z ** 2 * (vp + ep))
    changed = ok & ~use
    d2p = box_mean_finite(np.where(use, d2, np.nan), r) if r > 0 else d2
    d2p = np.where(np.isfinite(d2p), d2p, d2)
    bias2 = np.maximum(d2p - vp - ep, 0.0)
    eh = ep + bias2
    m = np.where(use, np.minimum(L, (params.input_frames - 1) * n), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(vp + eh > 0, eh / np.where(vp + eh > 0, vp + eh, 1.0), 1.0)
        floor = np.where(n + m > 0, n / np.where(n + m > 0, n + m, 1.0), 1.0)
    wc = np.where(use, np.clip(np.maximum(inv, floor), 0.0, 1.0), 1.0)
    wc3 = wc[..., None]
    acc6 = np.where(use[..., None], wc3 * cur + (1.0 - wc3) * W6, cur)
    var_acc = np.where(use, wc ** 2 * vz + (1.0 - wc) ** 2 * (e + bias2), v)
    out = _accumulated_buffers(buf, acc6, share, wc, var_acc, v, use, halves is not None)
    info.update(input_history_fraction=float(use.mean()), input_changed_fraction=float(changed.mean()),
                input_history_weight=float(np.mean(1.0 - wc)))
    return Accumulated(out, carried(acc6, var_acc, n + m), info)


def _accumulated_buffers(buf: Buffers, acc6, share, wc, var_acc, var, use, with_halves: bool) -> Buffers:
    """Buffers holding the accumulated halves (step 5 of :func:`accumulate`);
    new arrays throughout (``buf`` is not changed); pixels outside ``use``
    keep this frame's values exactly."""
    from .buffers import Half, Stat
    n = np.asarray(buf.n, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        grow = np.where(wc > 0, 1.0 / np.where(wc > 0, wc, 1.0), 1.0)   # n' / n
        ratio = np.where((var > 0) & np.isfinite(var), var_acc / np.where(var > 0, var, 1.0), 1.0)
    ratio = np.where(np.isfinite(ratio), ratio, 1.0)
    a, b = acc6[..., :3], acc6[..., 3:]
    s = share[..., None]
    mean = np.where(use[..., None], s * a + (1.0 - s) * b if with_halves else a, buf.color.mean)
    color = Stat(mean, buf.color.m2 * (ratio * grow)[..., None])
    feats = {k: Stat(st.mean, st.m2 * grow[..., None]) for k, st in buf.features.items()}
    half = None
    if with_halves:
        half = Half(buf.half.n * grow, a, dict(buf.half.features))
    return Buffers(n * grow, buf.k.copy(), color, feats, half, buf.exponent)


#: light passes whose radiance is view-dependent (Cycles divides them by their ``_color`` pass)
SPECULAR_PASSES = ("glossy", "transmission")


def specular_share(buf: Buffers) -> np.ndarray:
    """(H, W) share of view-dependent light, ``lum(glossy + transmission
    radiance) / lum(combined)``, each radiance the light pass times its colour
    pass (the light pass alone where the colour pass is missing: larger,
    conservative); 0 where the buffers have neither pass, +inf where there is
    view-dependent light but no positive combined luminance."""
    from .buffers import luminance
    h, w = buf.shape
    vd = np.zeros((h, w))
    for name in SPECULAR_PASSES:
        st = buf.features.get(name)
        if st is None:
            continue
        light = np.asarray(st.mean, np.float64)
        col = buf.features.get(name + "_color")
        rad = light * np.asarray(col.mean, np.float64) if col is not None and col.mean.shape == light.shape \
            else light
        with np.errstate(invalid="ignore"):
            vd += np.maximum(np.nan_to_num(luminance(rad[..., :3]), nan=np.inf), 0.0)
    lum = np.maximum(np.nan_to_num(luminance(np.asarray(buf.color.mean, np.float64)), nan=0.0), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(vd > 0, np.where(lum > 0, vd / np.where(lum > 0, lum, 1.0), np.inf), 0.0)

"""``var``: the adaptive samplers of Schalk 2018, "Reprojection for adaptive
sampling" (thesis Sec. 3.1, Algorithm 1; Sec. 3.3, Algorithm 2).

No reconstruction: the image is the sample mean.  What the method decides is
*where* the next samples go.  Two samplers share one state and one
reconstruction:

* :func:`sample_map`, Algorithm 1 (Sec. 3.1), the method ``var``;
* :func:`reprojected_sample_map`, Algorithm 2 (Sec. 3.3), the frame-to-frame
  combination with ``core.reproject``: :data:`REPROJECT`, the method
  ``var-reproject``.

Algorithm 1
-----------
Iterations ``itr = 0, 1, ...``; in each one, every pixel ``P`` is visited once
(scanline order) and traces one sample if it is *ready*:

* ``itr < max_spp``: ready if ``Pvariance >= tau`` or ``Pspp < min_spp``; a
  sample updates the Welford mean / M2 (Eq. 9-10) and
  ``Pvariance = (sqrt(Var_p) + eps) / (L(p) + eps)`` (Eq. 11-12).
* the threshold ``tau`` starts at 1 and, after each iteration with
  ``itr >= min_spp``, falls by ``1 / (max_spp - min_spp)``; it is 0 when
  ``itr == max_spp`` (:func:`threshold`).
* at ``itr == max_spp`` each pixel's ``Pvariance`` becomes the probability
  ``P_spp / max_spp``; from then on a pixel is ready with that probability
  (``RandomFloat() <= P``) and variance is no longer updated.

Because ``min_spp > 0`` every pixel keeps a probability ``>= min_spp/max_spp``
(table 1 of the thesis), so the sampler converges.

Algorithm 2
-----------
After a reprojection (``core.reproject``), reprojected pixels also carry the
probability their source had computed (``Reprojection.extra``, passed in
``state['probability']``, NaN where none).  Pixels with one wait while
``itr < max_spp`` (``else if !PprobabilityCalculated``), so the threshold
phase spends the budget on the other pixels first; at ``itr == max_spp`` the
carried probabilities are kept and the others get ``spp / max_spp``.  ``itr``
restarts with the frame.

Mapping onto the render loop (region renders, not single samples)
-----------------------------------------------------------------
Algorithm 1 is a sequence of (itr, pixel) samples, itr-major, scanline-minor.
One call of :func:`sample_map` with ``budget = B`` hands out **the next B
samples of that sequence**:

* ``state['itr']`` is the iteration in progress and ``state['cursor']`` the
  flat pixel index where it stopped when the previous budget ran out in the
  middle of an iteration (the rest of that iteration is served first, so
  partial iterations are exactly the scanline prefix Algorithm 1 would have
  traced before it was stopped).
* Readiness uses ``Pvariance`` computed once per call from the Buffers
  (variance can only change after Cycles has rendered): a pixel's variance is
  frozen for the block of iterations the call covers.  A pixel that is not
  sampled keeps its ``Pvariance`` in Algorithm 1 too, so for pixels waiting
  for ``tau`` to fall this is exact; only pixels sampled several times within
  one block react late to their own new samples.  ``Pspp`` is counted as the
  block proceeds (``buf.n`` plus samples handed out so far in the call), so
  the ``Pspp < min_spp`` rule is exact.
* ``tau`` advances with every iteration of the block (Alg. 1's schedule, one
  step per ``itr``), and iterations in which no pixel is ready cost nothing.
* On entering ``itr == max_spp`` the probabilities ``P_spp / max_spp`` are
  frozen in ``state['prob']``.  After that an iteration is one Bernoulli draw
  per pixel; many iterations at once are drawn as a Binomial (same law), with a
  6-sigma safety margin so the block never overruns, then single iterations,
  and the last iteration is again cut at a scanline position.
* The sum of the map is exactly ``budget`` (Algorithm 1 never stalls: once
  ``tau`` reaches 0 every pixel has a positive probability).
* The initial pass of ``n0`` uniform spp is taken as iterations ``0..n0-1``
  (``state['itr']`` starts at the smallest ``buf.n``; the loop may preset it).
  This is exact when ``n0 <= min_spp`` (every pixel is ready there anyway);
  a larger initial pass replaces iterations ``min_spp..n0-1`` by uniform ones.

The thesis runs open-ended (until the path tracer restarts); here the run
ends when the loop's ``--spp`` budget is spent.

Welford vs sample subsets (Eq. 9-11)
------------------------------------
Eq. 11 is ``Var_p = (M2_r + M2_g + M2_b) / ((spp - 1) * 3)``.  Our
:class:`~core.buffers.Buffers` merge sample *groups* (each region render is
one group) with Chan's update, Welford's with group means, so
``buf.sample_variance() = M2 / (k - 1)`` is the same unbiased per-sample
variance, and equals Eq. 11 exactly when every group holds one sample
(``k = spp``; the loop's default initial pass of 4 spp in 4 subsets does).

Choices
-------
* ``tau``'s update line in the pseudo code reads ``tau := 1/(max_spp -
  min_spp)``; we read it as a decrement (the text: tau "will linearly
  decrease to zero").
* Eq. 12 (``epsilon`` outside the root) is the default; Algorithm 1's form
  ``sqrt(Var + eps)`` is ``Params.epsilon_inside_sqrt``.
* ``k < 2`` (one group, no variance): Algorithm 1 would divide by
  ``Pspp - 1 = 0``; we take ``Pvariance = +inf`` (unknown counts as
  noisiest), so such pixels are always ready while ``tau > 0``.
* Non-finite means or ``M2`` (NaN/Inf samples): ``Pvariance = +inf`` as well;
  the image replaces them by 0 and ``info['nonfinite_pixels']`` counts them.
* Negative luminance (possible with negative pixels): clamped to 0 in Eq. 12,
  i.e. treated as dark.
* Zero variance and zero luminance: Eq. 12 gives ``eps / eps = 1``, as the
  thesis intends ("still can get samples").
* Algorithm 2: probabilities are clipped to ``[min_spp / max_spp, 1]`` (a
  pixel with carried samples may exceed ``max_spp``: the thesis' "incorrect
  probabilities", Sec. 3.3).

Measurements and design notes: docs/notes/var.md
"""
from __future__ import annotations

import hashlib
import threading
from dataclasses import dataclass

import numpy as np

from . import parallel
from .buffers import Buffers, luminance
from .method import MethodResult, param
from .variance import GUIDE_FEATURES

NAME = "var"
#: the guides of the calibrated variance its priorities read: declared so the
#: benchmark renders what the product does
PASSES: tuple = tuple(GUIDE_FEATURES)
ADAPTIVE = True
#: Algorithm 1 adapts on the raw statistics in the Buffers, never on ``result``
SAMPLER_USES_RESULT = False


@dataclass
class Params:
    """Parameters of the var sampler (thesis defaults: min 4, max 32)."""

    min_spp: int = param(
        4, "Samples every pixel gets before adapting (Alg. 1 min_spp); also the floor "
        "min_spp/max_spp of each pixel's probability. Higher = safer variance "
        "estimates and faster convergence everywhere, less adaptivity", 1, 4096, label="Min Samples")
    max_spp: int = param(
        32, "Iterations of the falling threshold (Alg. 1 max_spp); at most this many "
        "samples per pixel before probabilities are fixed. Higher = slower, "
        "better-informed probabilities", 1, 65536, label="Max Samples")
    epsilon: float = param(
        1e-3, "Eq. 12 epsilon (luminance units): keeps dark, noiseless pixels sampled. "
        "Larger = fewer samples to dark pixels", 1e-9, 10.0, label="Error Epsilon")
    epsilon_inside_sqrt: bool = param(
        False, "Use Algorithm 1's form sqrt(Var + eps) / (L + eps) instead of Eq. 12's "
        "(sqrt(Var) + eps) / (L + eps); the square-root form favours dark pixels "
        "much more strongly", label="Epsilon Inside Root")
    seed: int = param(
        0, "Seed of the per-pixel random draws after the threshold phase "
        "(combined with the run's --seed); same seed = same sample maps", 0, 2 ** 31 - 1, label="Seed")


# ------------------------------------------------------------------- pieces
def threshold(itr, params: Params) -> float:
    """Threshold tau at the start of iteration ``itr`` (Algorithm 1).

    tau = 1 for itr <= min_spp, then falls by 1/(max_spp - min_spp) per
    iteration: tau = 1 - (itr - min_spp)/(max_spp - min_spp), clamped to
    [0, 1]; 0 from itr = max_spp on.  ``max_spp <= min_spp`` (no threshold
    phase) gives 1 before ``max_spp`` and 0 from it on.

    The pseudo code's update line reads ``tau := 1/(max_spp - min_spp)``; we
    read it as a decrement (``tau -= ...``), as the text says tau "will
    linearly decrease to zero" and reaches 0 exactly when ``itr == max_spp``.
    """
    lo, hi = int(params.min_spp), int(params.max_spp)
    if itr >= hi:
        return 0.0
    if hi <= lo:
        return 1.0
    return float(min(1.0, max(0.0, 1.0 - max(0, itr - lo) / (hi - lo))))


#: rows per band of the per-pixel priority (about this many pixels a band)
BAND_PIXELS = 32768
#: below this many pixels the priority and the threshold phase run inline
#: (threads do not pay; measured: docs/notes/farm.md)
INLINE_PIXELS = 65536


def _rows(fn, h: int, w: int) -> list:
    """``fn((r0, r1))`` over row bands (:func:`core.parallel.run_bands`) of
    about :data:`BAND_PIXELS` pixels, inline below :data:`INLINE_PIXELS`;
    results in band order.  Bands depend on the shape only."""
    rows = max(1, BAND_PIXELS // max(1, w))
    if h * w < INLINE_PIXELS:
        return [fn(b) for b in parallel.bands(h, rows)]
    return parallel.run_bands(fn, h, rows)


def _pixel_variance_rows(buf: Buffers, r0: int, r1: int) -> np.ndarray:
    """:func:`pixel_variance` of rows ``r0:r1``."""
    s2 = buf.sample_variance(rows=(r0, r1))
    fin = np.isfinite(s2)
    ok = np.all(fin, axis=-1) & np.all(np.isfinite(buf.color.mean[r0:r1]), axis=-1)
    v = np.maximum(np.where(fin, s2, 0.0), 0.0).mean(axis=-1)
    return np.where(ok, v, np.inf)


def pixel_variance(buf: Buffers) -> np.ndarray:
    """Eq. 11 of Schalk 2018: per-sample variance averaged over RGB.

    ``mean_c(M2_c / (k - 1))`` from the group statistics (see module docstring
    for the correspondence with Welford's ``M2 / (spp - 1)``).  Per pixel, over
    row bands on the controller's threads (the same bits for any count).

    Returns (H, W) float64 >= 0; +inf where k < 2 or the statistics are not
    finite.
    """
    h, w = buf.shape
    out = np.empty((h, w))

    def band(b):
        out[b[0]:b[1]] = _pixel_variance_rows(buf, *b)

    _rows(band, h, w)
    return out


def relative_deviation(var: np.ndarray, lum: np.ndarray, params: Params) -> np.ndarray:
    """Eq. 12 of Schalk 2018: ``Pvariance = (sqrt(Var_p) + eps) / (L(p) + eps)``.

    With ``params.epsilon_inside_sqrt`` Algorithm 1's variant
    ``sqrt(Var_p + eps) / (L(p) + eps)``.  The thesis states both; Eq. 12 (the
    numbered equation, whose text explains the epsilon above the fraction) is
    the default.  ``L`` < 0 is clamped to 0; non-finite ``var`` or ``lum``
    gives +inf (unknown = sample it).

    var, lum : (H, W) -> (H, W) float64 in (0, inf].
    """
    eps = float(params.epsilon) if np.isfinite(params.epsilon) and params.epsilon > 0 else 1e-9
    var = np.asarray(var, np.float64)
    lum = np.asarray(lum, np.float64)
    bad = ~np.isfinite(var) | ~np.isfinite(lum)
    v = np.where(bad, 0.0, np.maximum(var, 0.0))
    l = np.where(bad, 0.0, np.maximum(lum, 0.0))
    if params.epsilon_inside_sqrt:
        num = np.sqrt(v + eps)
    else:
        num = np.sqrt(v) + eps
    with np.errstate(over="ignore", invalid="ignore"):
        out = num / (l + eps)
    return np.where(bad | ~np.isfinite(out), np.inf, out)


def _priority_rows(buf: Buffers, params: Params, r0: int, r1: int) -> np.ndarray:
    """:func:`pixel_priority` of rows ``r0:r1``."""
    mean = buf.color.mean[r0:r1]
    fin = np.isfinite(mean)
    lum = luminance(np.where(fin, mean, 0.0))
    lum = np.where(np.all(fin, axis=-1), lum, np.nan)
    return relative_deviation(_pixel_variance_rows(buf, r0, r1), lum, params)


def pixel_priority(buf: Buffers, params: Params) -> np.ndarray:
    """Pvariance of every pixel (Eq. 11 then Eq. 12) from the Buffers; (H, W).
    Per pixel, over row bands on the controller's threads (the same bits for
    any thread count)."""
    h, w = buf.shape
    out = np.empty((h, w))

    def band(b):
        out[b[0]:b[1]] = _priority_rows(buf, params, *b)

    _rows(band, h, w)
    return out


#: bytes per hashed piece of :func:`_priority_key` (shape only)
HASH_BYTES = 1 << 22


def _digest(a: np.ndarray) -> bytes:
    """SHA-256 over the SHA-256 digests of ``a``'s consecutive pieces of
    :data:`HASH_BYTES` bytes (C order): a content hash whose pieces hash on the
    controller's threads (hashlib releases the GIL); the pieces depend on the
    size only, so the digest does not depend on the thread count."""
    flat = memoryview(np.ascontiguousarray(a).reshape(-1)).cast("B")
    n = len(flat)
    pieces = parallel.bands(n, HASH_BYTES)
    work = lambda p: hashlib.sha256(flat[p[0]:p[1]]).digest()
    parts = parallel.map_ordered(work, pieces) if n >= 4 * HASH_BYTES else [work(p) for p in pieces]
    return hashlib.sha256(b"".join(parts)).digest()


def _priority_key(buf: Buffers, params: Params) -> tuple:
    """What :func:`pixel_priority` depends on: the exact bytes (a SHA-256
    tree, :func:`_digest`), dtype and shape of ``buf.color.mean``,
    ``buf.color.m2`` and ``buf.k``, and the two Eq. 12 parameters.  Contents,
    not identities: the loop merges renders into the same arrays in place."""
    parts, digests = [], []
    for a in (buf.color.mean, buf.color.m2, buf.k):
        a = np.asarray(a)
        parts.append((a.dtype.str, a.shape))
        digests.append(_digest(a))
    return (tuple(parts), tuple(digests), float(params.epsilon), bool(params.epsilon_inside_sqrt))


#: single entry (key, read-only priority): the loop's secant steps call the
#: sampler several times on the same Buffers (on copies of its state) before
#: the next render changes them.  Outside ``state``, so checkpoints and deep
#: copies never carry it.
_PRIORITY_CACHE: list = [None]
_PRIORITY_LOCK = threading.Lock()


def cached_priority(buf: Buffers, params: Params) -> np.ndarray:
    """:func:`pixel_priority`, reused while ``buf``'s statistics and the
    Eq. 12 parameters are unchanged (same values bit for bit: the entry is
    keyed on the contents, see :func:`_priority_key`).  Read-only (H, W)."""
    key = _priority_key(buf, params)
    with _PRIORITY_LOCK:
        entry = _PRIORITY_CACHE[0]
    if entry is not None and entry[0] == key:
        return entry[1]
    pv = pixel_priority(buf, params)
    pv.setflags(write=False)
    with _PRIORITY_LOCK:
        _PRIORITY_CACHE[0] = (key, pv)
    return pv


def clear_priority_cache() -> None:
    """Drop the cached priority (frees its (H, W) array)."""
    with _PRIORITY_LOCK:
        _PRIORITY_CACHE[0] = None


# ------------------------------------------------------------- reconstruction
def _result(mean: np.ndarray, var_of_mean: np.ndarray, n=None) -> MethodResult:
    mean = np.asarray(mean, np.float64)
    var_of_mean = np.asarray(var_of_mean, np.float64)
    finite_px = np.all(np.isfinite(mean), axis=-1)
    image = np.where(np.isfinite(mean), mean, 0.0)
    known = np.all(np.isfinite(var_of_mean), axis=-1) & finite_px
    err = np.where(known[..., None], np.maximum(np.where(np.isfinite(var_of_mean),
                                                         var_of_mean, 0.0), 0.0), 0.0).mean(-1)
    err = np.where(np.isfinite(err), err, 0.0)
    if not known.all():
        with np.errstate(over="ignore"):
            worst = float(err[known].max()) if known.any() else 0.0
            sq = (image * image).mean(-1)
        sq = np.where(np.isfinite(sq), sq, np.finfo(np.float64).max)
        err = np.where(known, err, np.maximum(worst, sq))
    info = {"pixels_without_variance": int((~known).sum()),
            "nonfinite_pixels": int((~finite_px).sum())}
    if n is not None:
        info["spp_mean"] = float(np.mean(n)) if np.size(n) else 0.0
    return MethodResult(image, err, info)


def reconstruct(buf: Buffers, params: Params | None = None) -> MethodResult:
    """The sample mean (var does no reconstruction) and its error.

    image : (H, W, 3) sample mean; non-finite values are replaced by 0
        (counted in ``info['nonfinite_pixels']``).
    error : (H, W) calibrated variance of the mean
        (:meth:`Buffers.calibrated_variance`: stratification-corrected, pooled
        over feature-guided 5x5 windows) averaged over RGB.  Where it is unknown (k < 2, n = 0, non-finite statistics) the
        error is the larger of the worst known error in the image and the
        pixel's mean squared value (a 100 % relative error), so it is finite
        and conservative; ``info['pixels_without_variance']`` counts them.
    Zero-variance input comes back unchanged with error 0.
    """
    return _result(buf.color.mean, buf.calibrated_variance(), buf.n)


def denoise(color, color_var, features=None, feature_var=None, n=None, params=None) -> MethodResult:
    """Same as :func:`reconstruct` from arrays.

    color : (H, W, 3) pixel means.
    color_var : (H, W, 3) variance of the mean (+inf = unknown).
    features, feature_var, params : ignored (PASSES is empty, nothing to tune).
    n : (H, W) or scalar samples per pixel, or None; only reported
        (``info['spp_mean']``), as :func:`reconstruct` does.
    """
    color = np.asarray(color, np.float64)
    color_var = np.broadcast_to(np.asarray(color_var, np.float64), color.shape)
    return _result(color, color_var, n)


# ------------------------------------------------------------------ sampling
def _init_state(buf: Buffers, params: Params, state: dict) -> None:
    """Start Algorithm 1 on a frame: ``itr`` at the smallest ``buf.n`` (the
    initial pass as iterations ``0..n0-1``) unless the loop preset it, no
    probabilities yet, the generator seeded from ``params.seed`` and
    ``state['seed']``."""
    n = np.asarray(buf.n, np.float64)
    n = np.where(np.isfinite(n) & (n > 0), n, 0.0)
    seed_seq = np.random.SeedSequence([int(params.seed) & 0x7FFFFFFF,
                                       int(state.get("seed", 0) or 0) & 0x7FFFFFFF])
    first = int(np.floor(n.min())) if n.size else 0
    if "var_shape" not in state and state.get("itr") is not None:
        first = int(state["itr"])          # preset by the loop
    state.update({
        "var_shape": tuple(buf.shape),
        "itr": first,
        "cursor": 0,
        "prob": None,
        "rng": np.random.default_rng(seed_seq),
        "var_params": (int(params.min_spp), int(params.max_spp)),
    })


def sample_map(buf: Buffers, result: MethodResult | None, budget: int,
               params: Params | None = None, state: dict | None = None) -> np.ndarray:
    """The next ``budget`` samples of Algorithm 1 (Schalk 2018), as a map.

    Parameters
    ----------
    buf : Buffers
        Accumulated samples (mean, M2, n, k) of the frame.
    result : MethodResult
        Unused (var adapts on the raw statistics).
    budget : int
        Samples to hand out in this call (pixel-samples).
    params : Params
    state : dict
        Kept by the loop across calls; holds ``itr``, ``cursor``, ``prob``
        (probabilities once ``itr`` reached ``max_spp``), ``rng`` (seeded
        generator, from ``params.seed`` and ``state['seed']``), ``tau``.

    Returns
    -------
    (H, W) int64 >= 0 summing exactly to ``budget`` (0 for an empty image).
    See the module docstring for how a call maps onto Algorithm 1's iterations.
    """
    params = params or Params()
    if state is None:
        state = {}
    h, w = buf.shape
    remaining = int(max(0, budget))
    if h * w == 0 or remaining == 0:
        return np.zeros((h, w), np.int64)
    if state.get("var_shape") != tuple(buf.shape) or "rng" not in state:
        _init_state(buf, params, state)
    return _next_samples(buf, params, state, remaining)


def _next_samples(buf: Buffers, params: Params, state: dict, remaining: int,
                  wait: np.ndarray | None = None, carried=None) -> np.ndarray:
    """Hand out ``remaining`` (> 0) samples from ``state``'s position in the
    (itr, pixel) sequence: threshold phase, then the probabilities.

    wait : flat (H*W,) bool or None; pixels never ready in the threshold phase
        (Algorithm 2's ``PprobabilityCalculated``).
    carried : (H, W) probabilities those pixels keep at ``itr == max_spp``.
    Returns the (H, W) int64 map; updates ``state`` (itr, cursor, prob, tau).
    """
    h, w = buf.shape
    out = np.zeros(h * w, np.int64)
    lo, hi = int(params.min_spp), int(params.max_spp)
    p_floor = min(1.0, max(lo, 1) / max(hi, 1))
    itr, cursor = int(state["itr"]), int(state["cursor"])
    n = np.asarray(buf.n, np.float64).ravel()
    spp = np.where(np.isfinite(n) & (n > 0), n, 0.0)
    if itr < hi:
        pv = cached_priority(buf, params).ravel()
        remaining, itr, cursor = threshold_phase(out, spp, pv, remaining, itr, cursor, params, wait)
    if itr >= hi and state.get("prob") is None:
        # Alg. 1: at itr == max_spp, Pvariance <- Pspp / max_spp (Alg. 2: carried ones kept)
        prob = spp / max(hi, 1)
        if wait is not None and wait.any():
            prob = np.where(wait, np.asarray(carried, np.float64).ravel(), prob)
        state["prob"] = np.clip(prob, p_floor, 1.0).reshape(h, w)
    if remaining > 0:
        itr, cursor = probability_phase(out, state["prob"], p_floor, remaining, itr, cursor, state["rng"])
    state["itr"], state["cursor"] = itr, cursor
    state["tau"] = threshold(itr, params)
    return out.reshape(h, w)


#: pixels per piece of the threshold phase's flat arrays (shape only)
FLAT_PIECE = 1 << 18


def threshold_phase(out, spp, pv, remaining, itr, cursor, params: Params, wait=None):
    """Hand out up to ``remaining`` samples of Algorithm 1's threshold phase
    (``itr < max_spp``: a pixel is ready if ``Pvariance >= tau`` or ``Pspp <
    min_spp``), in place into ``out`` and ``spp`` (flat arrays), continuing at
    scanline ``cursor`` of iteration ``itr``; ``pv`` (flat) is Pvariance,
    frozen for the call.  Pixels in ``wait`` (flat bool, Algorithm 2) are never
    ready.  Returns (remaining, itr, cursor).

    Each iteration marks the ready pixels and counts them per piece of
    :data:`FLAT_PIECE` pixels on the controller's threads, then adds them (or,
    when the budget ends inside the iteration, the first ``remaining`` in
    scanline order): integer counts, so the same map for any thread count."""
    lo, hi = int(params.min_spp), int(params.max_spp)
    npx = int(out.size)
    pieces = parallel.bands(npx, FLAT_PIECE)
    ready = np.empty(npx, bool)
    many = npx >= INLINE_PIXELS
    run = (lambda fn: parallel.map_ordered(fn, pieces)) if many else (lambda fn: [fn(p) for p in pieces])

    def mark(p, tau, cursor):
        a, b = p
        r = ready[a:b]
        np.greater_equal(pv[a:b], tau, out=r)
        r |= spp[a:b] < lo
        if wait is not None:
            r &= ~wait[a:b]
        if cursor > a:
            r[:min(cursor, b) - a] = False
        return int(np.count_nonzero(r))

    def add(p):
        a, b = p
        r = ready[a:b]
        out[a:b] += r
        spp[a:b] += r

    while remaining > 0 and itr < hi:
        tau = threshold(itr, params)
        counts = run(lambda p: mark(p, tau, cursor))
        cnt = sum(counts)
        if cnt > remaining:                 # budget ends inside this iteration
            idx, need = [], remaining
            for (a, b), c in zip(pieces, counts):
                if c == 0:
                    continue
                got = a + np.flatnonzero(ready[a:b])[:need]
                idx.append(got)
                need -= len(got)
                if need <= 0:
                    break
            idx = np.concatenate(idx)
            out[idx] += 1
            spp[idx] += 1
            return 0, itr, int(idx[-1]) + 1
        run(add)
        remaining -= cnt
        itr, cursor = itr + 1, 0
    return remaining, itr, cursor


def probability_phase(out, prob, p_floor, remaining, itr, cursor, rng):
    """Hand out ``remaining`` samples of Algorithm 1's probability phase
    (itr >= max_spp: a pixel is ready with probability ``prob``), in place into
    ``out`` (flat int array), continuing at scanline ``cursor`` of iteration
    ``itr``.  Many whole iterations at once are one Binomial draw (same law),
    kept 6 sigma under what remains so the block never overruns; the last
    iteration is cut at a scanline position.  Returns (itr, cursor)."""
    npx = out.size
    p = np.clip(np.asarray(prob, np.float64).ravel(), p_floor, 1.0)
    total_p = float(p.sum())
    while remaining > 0:
        if cursor == 0 and remaining >= 2 * total_p:
            x = -3.0 + np.sqrt(9.0 + remaining)       # m S + 6 sqrt(m S) <= remaining
            m = int(np.floor(x * x / total_p))
            if m >= 2:
                draw = rng.binomial(m, p)
                got = int(draw.sum())
                if got <= remaining:
                    out += draw
                    remaining -= got
                    itr += m
                    continue
        # one iteration (or the rest of one), scanline order
        hit = rng.random(npx - cursor) <= p[cursor:]
        cnt = int(np.count_nonzero(hit))
        if cnt > remaining:
            idx = cursor + np.flatnonzero(hit)[:remaining]
            out[idx] += 1
            cursor = int(idx[-1]) + 1
            break
        out[cursor:] += hit
        remaining -= cnt
        itr, cursor = itr + 1, 0
    return itr, cursor


# ------------------------------------------------------------- Algorithm 2
def _has_probability(probability, shape) -> np.ndarray:
    """(H, W) bool: pixels that carry a reprojected probability (finite
    entries of ``probability``); all False for None.  ValueError on a shape
    other than the frame's."""
    if probability is None:
        return np.zeros(shape, bool)
    p = np.asarray(probability, np.float64)
    if p.shape != tuple(shape):
        raise ValueError(f"probability map has shape {p.shape}, the frame is {tuple(shape)}")
    return np.isfinite(p)


def sampling_priority(buf: Buffers, probability: np.ndarray | None, var_params=None) -> np.ndarray:
    """Sampling priority of Algorithm 2 (thesis Sec. 3.3) after a reprojection.

    Pixels that carry a probability from the previous frame (reprojected from a
    pixel that had finished Algorithm 1's threshold phase) wait: they get no
    samples until ``itr`` reaches ``max_spp``; every other pixel (not
    reprojected, or reprojected before its probability was set) follows
    Algorithm 1: ready while ``spp < min_spp`` or ``Pvariance >= tau``.

    Parameters
    ----------
    buf : Buffers, the frame's statistics after merging the reprojection.
    probability : (H, W) reprojected probability (``Reprojection.extra`` of the
        state's ``prob``), NaN where none was calculated; None = none.
    var_params : Params.

    Returns
    -------
    (H, W) float64, larger = sampled first: ``+inf`` below ``min_spp``,
    ``Pvariance`` (Eq. 12, > 0) for pixels without a probability, ``-1`` for
    pixels that carry one (never ready in the threshold phase, where tau >= 0).
    """
    vp = var_params if var_params is not None else Params()
    pv = pixel_priority(buf, vp)
    pv = np.where(np.isnan(pv), np.inf, pv)
    has_prob = _has_probability(probability, buf.shape)
    spp = np.where(np.isfinite(buf.n), buf.n, 0.0)
    out = np.where(has_prob, -1.0, pv)
    return np.where(~has_prob & (spp < vp.min_spp), np.inf, out)


def reprojected_sample_map(buf: Buffers, result: MethodResult | None, budget: int, params=None,
                           state: dict | None = None) -> np.ndarray:
    """The next ``budget`` samples of Algorithm 2 (thesis Sec. 3.3) as a map.

    Same contract and mapping onto region iterations as :func:`sample_map`
    (Algorithm 1; ``result`` unused), with Algorithm 2's changes:

    * ``state['probability']`` (H, W): the reprojected probabilities (NaN where
      the pixel has none).  Pixels with one are never ready while
      ``itr < max_spp`` (``else if !PprobabilityCalculated``), so the threshold
      phase spends the budget on pixels that were not reprojected (or were
      reprojected before their probability was set): those have priority.
    * at ``itr == max_spp`` the pixels without a probability get
      ``spp / max_spp``; reprojected probabilities are kept ("they also copy
      the calculated variance/probability", Sec. 3.3).  Probabilities are
      clipped to ``[min_spp / max_spp, 1]``.
    * ``itr`` restarts at the frame: the loop's initial pass (which the
      occlusion test needs) counts as iterations ``0 .. n0-1`` of the pixels
      without a probability; ``state['itr']`` may be preset.

    Returns (H, W) int64 >= 0 summing exactly to ``budget``.
    """
    params = params if params is not None else Params()
    if state is None:
        state = {}
    h, w = buf.shape
    remaining = int(max(0, budget))
    if h * w == 0 or remaining == 0:
        return np.zeros((h, w), np.int64)
    has_prob = _has_probability(state.get("probability"), buf.shape)
    if state.get("var_shape") != tuple(buf.shape) or "rng" not in state:
        preset = state.get("itr")
        _init_state(buf, params, state)
        if preset is None:
            n = np.asarray(buf.n, np.float64)[~has_prob]
            n = n[np.isfinite(n)]
            state["itr"] = int(np.floor(n.min())) if n.size else 0
    return _next_samples(buf, params, state, remaining, has_prob.ravel(), state.get("probability"))


class _VarReproject:
    """The method ``var-reproject``: var with Algorithm 2's sampler (Schalk
    2018 Sec. 3.3) for frames that received reprojected samples.

    Same Params, passes and reconstruction (the sample mean) as ``var``; its
    sampler, :func:`reprojected_sample_map`, reads the reprojected per-pixel
    probability from ``state["probability"]`` ((H, W), NaN where the pixel
    carries none; the frame job hands ``Reprojection.extra['probability']`` to
    the run as its ``core.pipeline.Prior`` state) and samples the pixels
    without one first.
    """

    NAME = "var-reproject"
    PASSES = PASSES
    Params = Params
    ADAPTIVE = True
    SAMPLER_USES_RESULT = False
    reconstruct = staticmethod(reconstruct)
    sample_map = staticmethod(reprojected_sample_map)


#: var with Algorithm 2's sampler (a ``core.method.Method``)
REPROJECT = _VarReproject()

"""``var``: the adaptive sampler of Schalk 2018 (thesis section 3.1, Algorithm 1).

No reconstruction: the image is the sample mean.  What the method decides is
*where* the next samples go.

The algorithm (thesis Algorithm 1)
----------------------------------
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
* Fidelity improves with smaller blocks: with a budget of one iteration per
  call the mapping is Algorithm 1 except that a pixel's variance reflects its
  samples up to the previous call.

Relation to the user's budget: the thesis runs open-ended (until the path
tracer restarts); here the run ends when the loop's ``--spp`` budget is spent.
Reaching ``tau = 0`` costs between ``min_spp`` and ``max_spp`` samples per
pixel (on average ``max_spp`` times the mean final probability); a smaller
budget stops inside the threshold phase, a larger one spends the rest with the
per-pixel probabilities, about ``sum(P)`` samples per iteration.

Welford vs sample subsets (Eq. 9-11)
------------------------------------
Eq. 9-10 keep the per-sample running mean and ``M2``; Eq. 11 is
``Var_p = (M2_r + M2_g + M2_b) / ((spp - 1) * 3)``, the per-sample variance
averaged over RGB.  Our :class:`~core.buffers.Buffers` merge sample *groups*
(each region render is one group) with Chan's update, which is Welford's with
group means: ``M2`` is the between-group sum of squares with
``E[M2] = sigma^2 (k - 1)``, so ``buf.sample_variance() = M2 / (k - 1)`` is
the same unbiased per-sample variance, and equals Eq. 11 exactly when every
group holds one sample (``k = spp``; the loop's default initial pass of 4 spp
in 4 subsets does).  With fewer groups the estimate has ``k - 1`` instead of
``spp - 1`` degrees of freedom.

Special cases
-------------
* ``k < 2`` (one group, no variance): Algorithm 1 would divide by
  ``Pspp - 1 = 0``; we take ``Pvariance = +inf`` (unknown counts as
  noisiest), so such pixels are always ready while ``tau > 0`` and the
  ``tau`` phase then spends samples uniformly on them.
* Non-finite means or ``M2`` (NaN/Inf samples): ``Pvariance = +inf`` as well;
  the image replaces them by 0 and ``info['nonfinite_pixels']`` counts them.
* Negative luminance (possible with negative pixels): clamped to 0 in Eq. 12,
  i.e. treated as dark.
* Zero variance and zero luminance: Eq. 12 gives ``eps / eps = 1``, as the
  thesis intends ("still can get samples").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .buffers import Buffers, luminance
from .method import MethodResult, param

PASSES: tuple = ()
ADAPTIVE = True


@dataclass
class Params:
    """Parameters of the var sampler (thesis defaults: min 4, max 32)."""

    min_spp: int = param(
        4, "Samples every pixel gets before adapting (Alg. 1 min_spp); also the floor "
        "min_spp/max_spp of each pixel's probability. Higher = safer variance "
        "estimates and faster convergence everywhere, less adaptivity", 1, 4096)
    max_spp: int = param(
        32, "Iterations of the falling threshold (Alg. 1 max_spp); at most this many "
        "samples per pixel before probabilities are fixed. Higher = slower, "
        "better-informed probabilities", 1, 65536)
    epsilon: float = param(
        1e-3, "Eq. 12 epsilon (luminance units): keeps dark, noiseless pixels sampled. "
        "Larger = fewer samples to dark pixels", 1e-9, 10.0)
    epsilon_inside_sqrt: bool = param(
        False, "Use Algorithm 1's form sqrt(Var + eps) / (L + eps) instead of Eq. 12's "
        "(sqrt(Var) + eps) / (L + eps); the square-root form favours dark pixels "
        "much more strongly")
    seed: int = param(
        0, "Seed of the per-pixel random draws after the threshold phase "
        "(combined with the run's --seed); same seed = same sample maps", 0, 2 ** 31 - 1)


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


def pixel_variance(buf: Buffers) -> np.ndarray:
    """Eq. 11 of Schalk 2018: per-sample variance averaged over RGB.

    ``mean_c(M2_c / (k - 1))`` from the group statistics (see module docstring
    for the correspondence with Welford's ``M2 / (spp - 1)``).

    Returns (H, W) float64 >= 0; +inf where k < 2 or the statistics are not
    finite.
    """
    s2 = buf.sample_variance()
    ok = np.all(np.isfinite(s2), axis=-1) & np.all(np.isfinite(buf.color.mean), axis=-1)
    v = np.maximum(np.where(np.isfinite(s2), s2, 0.0), 0.0).mean(axis=-1)
    return np.where(ok, v, np.inf)


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


def pixel_priority(buf: Buffers, params: Params) -> np.ndarray:
    """Pvariance of every pixel (Eq. 11 then Eq. 12) from the Buffers; (H, W)."""
    mean = buf.color.mean
    lum = luminance(np.where(np.isfinite(mean), mean, 0.0))
    lum = np.where(np.all(np.isfinite(mean), axis=-1), lum, np.nan)
    return relative_deviation(pixel_variance(buf), lum, params)


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
    error : (H, W) variance of the mean (``M2 / ((k - 1) n)``) averaged over
        RGB.  Where it is unknown (k < 2, n = 0, non-finite statistics) the
        error is the larger of the worst known error in the image and the
        pixel's mean squared value (a 100 % relative error), so it is finite
        and conservative; ``info['pixels_without_variance']`` counts them.
    Zero-variance input comes back unchanged with error 0.
    """
    return _result(buf.color.mean, buf.variance_of_mean(), buf.n)


def denoise(color, color_var, features=None, params=None) -> MethodResult:
    """Same as :func:`reconstruct` from arrays: ``color`` (H, W, 3) pixel means,
    ``color_var`` (H, W, 3) variance of the mean (+inf = unknown).  ``features``
    are ignored (PASSES is empty)."""
    color = np.asarray(color, np.float64)
    color_var = np.broadcast_to(np.asarray(color_var, np.float64), color.shape)
    return _result(color, color_var)


# ------------------------------------------------------------------ sampling
def _init_state(buf: Buffers, params: Params, state: dict) -> None:
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
    npx = h * w
    out = np.zeros(npx, np.int64)
    remaining = int(max(0, budget))
    if npx == 0 or remaining == 0:
        return out.reshape(h, w)
    if state.get("var_shape") != tuple(buf.shape) or "rng" not in state:
        _init_state(buf, params, state)
    lo, hi = int(params.min_spp), int(params.max_spp)
    p_floor = min(1.0, max(lo, 1) / max(hi, 1))
    itr, cursor = int(state["itr"]), int(state["cursor"])
    n = np.asarray(buf.n, np.float64).ravel()
    spp = np.where(np.isfinite(n) & (n > 0), n, 0.0)

    # ---- threshold phase (itr < max_spp)
    if itr < hi:
        pv = pixel_priority(buf, params).ravel()
        while remaining > 0 and itr < hi:
            tau = threshold(itr, params)
            ready = pv >= tau
            ready |= spp < lo
            if cursor:
                ready[:cursor] = False
            cnt = int(np.count_nonzero(ready))
            if cnt > remaining:                 # budget ends inside this iteration
                idx = np.flatnonzero(ready)[:remaining]
                out[idx] += 1
                spp[idx] += 1
                cursor = int(idx[-1]) + 1
                remaining = 0
                break
            out += ready
            spp += ready
            remaining -= cnt
            itr, cursor = itr + 1, 0
    if itr >= hi and state.get("prob") is None:
        # Alg. 1: at itr == max_spp, Pvariance <- Pspp / max_spp
        state["prob"] = np.clip(spp / max(hi, 1), p_floor, 1.0).reshape(h, w)

    # ---- probability phase (itr >= max_spp)
    if remaining > 0:
        itr, cursor = probability_phase(out, state["prob"], p_floor, remaining, itr, cursor, state["rng"])
    state["itr"], state["cursor"] = itr, cursor
    state["tau"] = threshold(itr, params)
    return out.reshape(h, w)


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

"""Oracle sampling: a method whose sample map is driven by the *true* error.

The benchmark's oracle runs wrap a method (``core/var.py``, ``lp.py`` ...) so
that the render loop is unchanged except for one thing: where the wrapped
method spends the next samples.  The wrapped method still reconstructs (its
``reconstruct`` is called as is), but its estimated error is replaced, for
sampling only, by the true per-pixel error of the current reconstruction
against a known reference.  This is the limit the estimated maps chase: Moon et
al. 2015 (LP) report their estimated map at 1.36x the oracle's relMSE.

Map (:func:`oracle_weights`)
----------------------------
For the current reconstruction ``x`` and the reference ``r`` (both (H, W, 3)):

* true relative squared error, the quantity relMSE averages (``core/metrics.py``)::

      e_i = mean_c (x_ic - r_ic)^2 / (r_ic^2 + 0.01)

* ``e_i`` is one realisation of a random error (a squared difference), and a
  pixel whose error happens to be near zero *now* is not a pixel that needs no
  samples; so it is pooled over a ``(2 * radius + 1)^2`` box
  (:func:`core.filters.box_mean_finite`; ``radius = 1`` by default, ``0``
  turns pooling off).
* gain of one more sample: ``g_i = e_i * n_i^(-4/(d+4))``, the rule the
  estimated maps use (LP Sec. 5.2, :func:`core.method.sampling_gain`), with
  ``d`` the wrapped method's model dimension ``MethodResult.dimension`` (LP:
  mean rank, RHF: active features) and the Monte Carlo rate ``1/n`` for the
  methods without one (``var``).
* samples in proportion to ``g`` by :func:`core.method.allocate` (largest
  remainder, the map sums exactly to the budget).

Uniform sampling, same reconstruction (:class:`UniformSampling`)
----------------------------------------------------------------
The other end of the comparison: the wrapped method's reconstruction on the
budget rendered uniformly, so ``relMSE(uniform-<m>) / relMSE(oracle-<m>)`` is
what the placement of the samples gained, with the reconstruction held fixed
(issue goal: >= 1.3x on scenes with localised difficulty).

Hostile input: non-finite reconstructions count as the largest finite error of
the image (they need samples most), non-finite reference pixels (unknown truth)
get the mean weight, ``n <= 0`` counts as ``n = 1``; an image and a reference of
different sizes raise ``ValueError`` with both sizes.
"""
from __future__ import annotations

import numpy as np

from . import method as _method
from .filters import box_mean_finite
from .metrics import relative_squared_error
from .method import MethodResult, allocate, sampling_gain



def true_relative_error(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(H, W) per-pixel relative squared error ``mean_c (x-r)^2 / (r^2 + 0.01)``.

    Non-finite reconstructed values give the largest finite error of the image
    (1.0 when there is none); non-finite reference pixels give NaN (unknown),
    which callers replace.  (``core.metrics.per_pixel_relmse`` is the same
    formula with non-finite errors counted as 1e6.)
    """
    x = np.asarray(image, np.float64)[..., :3]
    r = np.asarray(reference, np.float64)[..., :3]
    if x.shape != r.shape:
        raise ValueError(f"oracle: image is {x.shape[1]}x{x.shape[0]} but the reference is "
                         f"{r.shape[1]}x{r.shape[0]}")
    ref_ok = np.isfinite(r).all(axis=-1)
    r0 = np.where(np.isfinite(r), r, 0.0)
    with np.errstate(over="ignore", invalid="ignore"):
        e = relative_squared_error(x, r0)
    bad = ~np.isfinite(e)
    fin = e[~bad]
    top = float(fin.max()) if fin.size else 0.0
    top = top if top > 0 else 1.0
    e = np.where(bad, top, e).mean(axis=-1)
    return np.where(ref_ok, e, np.nan)


def model_dimension(result: MethodResult | None) -> float | None:
    """``result.dimension`` when it is a finite number >= 0, else None (the
    Monte Carlo rate)."""
    d = None if result is None else result.dimension
    if d is None or np.ndim(d) != 0:
        return None
    d = float(d)
    return d if np.isfinite(d) and d >= 0 else None


def gain_exponent(result: MethodResult | None, default: float = 1.0) -> float:
    """``4 / (d + 4)`` (:func:`core.method.gain_exponent`) for the model
    dimension ``result.dimension``, else ``default``."""
    d = model_dimension(result)
    return default if d is None else float(_method.gain_exponent(d))


def oracle_weights(image: np.ndarray, reference: np.ndarray, n: np.ndarray,
                   dimension: float | None = None, radius: int = 1) -> np.ndarray:
    """(H, W) finite, >= 0 weights ``box(e)_i * max(n_i, 1)^(-4/(d+4))``
    (``1/n`` with ``dimension`` None)."""
    e = true_relative_error(image, reference)
    if int(radius) > 0:
        e = box_mean_finite(e, int(radius))
    fin = np.isfinite(e)
    fill = float(e[fin].mean()) if fin.any() else 1.0
    e = np.where(fin, e, fill)
    n = np.asarray(n, np.float64)
    if n.shape != e.shape:
        raise ValueError(f"oracle: sample counts are {n.shape[1]}x{n.shape[0]}, the image "
                         f"{e.shape[1]}x{e.shape[0]}")
    g = sampling_gain(e, n, dimension)
    return np.where(np.isfinite(g) & (g > 0), g, 0.0)


def oracle_map(image, reference, n, budget: int, dimension: float | None = None,
               radius: int = 1) -> np.ndarray:
    """(H, W) int64 new samples per pixel, summing to ``budget``, in proportion
    to :func:`oracle_weights` (uniform when the image matches the reference)."""
    return allocate(oracle_weights(image, reference, n, dimension, radius), int(budget))


class OracleMethod:
    """:class:`core.method.Method` around ``base`` with the oracle's map: the
    members are ``base``'s except ``NAME`` (``"oracle-" + base.NAME``),
    ``SAMPLER_USES_RESULT`` (True: the map needs the reconstruction to measure
    its true error) and ``sample_map``.

    base : a method (``core.methods.get(name)``)
    reference : (H, W, 3) reference of the image domain the loop renders
    radius : pooling radius of the true error (see the module notes)
    name : NAME to report instead of ``"oracle-" + base.NAME``
    """

    SAMPLER_USES_RESULT = True

    def __init__(self, base, reference: np.ndarray, radius: int = 1, name: str | None = None):
        ref = np.asarray(reference, np.float64)
        if ref.ndim != 3 or ref.shape[2] < 3:
            raise ValueError(f"oracle: the reference must be (H, W, 3), got {ref.shape}")
        self.base = base
        self.reference = ref[..., :3]
        self.radius = int(radius)
        self.NAME = name or "oracle-" + base.NAME
        self.PASSES = tuple(base.PASSES)
        self.Params = base.Params
        self.ADAPTIVE = base.ADAPTIVE

    def reconstruct(self, buf, params=None) -> MethodResult:
        """``base.reconstruct``, unchanged."""
        return self.base.reconstruct(buf, params)

    def sample_map(self, buf, result: MethodResult | None, budget: int, params=None,
                   state: dict | None = None) -> np.ndarray:
        """:func:`oracle_map` of ``result`` (reconstructed here when None)
        with ``result.dimension``; counts the calls in ``state``."""
        if result is None:
            result = self.base.reconstruct(buf, params)
        if tuple(buf.shape) != self.reference.shape[:2]:
            h, w = self.reference.shape[:2]
            raise ValueError(f"oracle: the render is {buf.width}x{buf.height} but the reference "
                             f"is {w}x{h}")
        counts = oracle_map(result.image, self.reference, buf.n, budget, model_dimension(result),
                            self.radius)
        if state is not None:
            state["oracle_calls"] = int(state.get("oracle_calls", 0)) + 1
        return counts


class UniformSampling:
    """:class:`core.method.Method` around ``base`` that keeps ``base``'s
    reconstruction but renders the budget uniformly: ``ADAPTIVE`` False (the
    loop renders the whole budget in its initial pass, as for ``uniform``),
    ``SAMPLER_USES_RESULT`` False and an even ``sample_map``.

    Choice: ``ADAPTIVE = False`` rather than an adaptive loop with an even
    map, so the comparison is against uniform sampling as plain Cycles does
    it (one pass, no region tasks, no planner rounding); the reconstruction
    then sees ``Options.subsets`` sample groups per pixel (its variance
    estimate has the initial pass's degrees of freedom everywhere).

    base : a method (``core.methods.get(name)``)
    name : NAME to report instead of ``"uniform-" + base.NAME``
    """

    ADAPTIVE = False
    SAMPLER_USES_RESULT = False

    def __init__(self, base, name: str | None = None):
        self.base = base
        self.NAME = name or "uniform-" + base.NAME
        self.PASSES = tuple(base.PASSES)
        self.Params = base.Params

    def reconstruct(self, buf, params=None) -> MethodResult:
        """``base.reconstruct``, unchanged."""
        return self.base.reconstruct(buf, params)

    def sample_map(self, buf, result: MethodResult | None, budget: int, params=None,
                   state: dict | None = None) -> np.ndarray:
        """Even map summing to ``budget`` (:func:`core.method.allocate` of
        equal weights); the loop asks for one only when a fractional spp
        leaves samples after the initial pass."""
        return allocate(np.ones(tuple(buf.shape), np.float64), int(budget))

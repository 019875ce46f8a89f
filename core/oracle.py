"""Oracle sampling: a method whose sample map is driven by the *true* error.

The benchmark's oracle runs wrap a method module (``core/var.py``, ``lp.py`` ...)
so that the render loop is unchanged except for one thing: where the wrapped
method spends the next samples.  The wrapped method still reconstructs (its
``reconstruct`` is called as is), but its estimated error is replaced, for
sampling only, by the true per-pixel error of the current reconstruction
against a known reference.  This is the limit the estimated maps chase: Moon et
al. 2015 (LP) report their estimated map at 1.36x the oracle's relMSE.

Map (:func:`oracle_weights`)
----------------------------
For the current reconstruction ``x`` and the reference ``r`` (both (H, W, 3)):

* true relative squared error, the quantity relMSE averages (DESIGN.md)::

      e_i = mean_c (x_ic - r_ic)^2 / (r_ic^2 + 0.01)

* ``e_i`` is one realisation of a random error (a squared difference), and a
  pixel whose error happens to be near zero *now* is not a pixel that needs no
  samples; so it is pooled over a ``(2 * radius + 1)^2`` box (``radius = 1`` by
  default, ``0`` turns pooling off).
* gain of one more sample: ``g_i = e_i * n_i^(-p)``, the same rule the
  estimated maps use (LP Sec. 5.2: ``xi_i * n_i^(-4/(d+4))``); ``p = 4/(d+4)``
  with ``d`` the method's reported model dimension (``info['mean_rank']`` for
  LP, ``info['active_features']`` for RHF) and ``p = 1`` for the methods that do
  not reconstruct (``var``: Monte Carlo error falls as 1/n).
* samples in proportion to ``g`` by :func:`core.method.allocate` (largest
  remainder, the map sums exactly to the budget).

Hostile input: non-finite reconstructions count as the largest finite error of
the image (they need samples most), non-finite reference pixels (unknown truth)
get the mean weight, ``n <= 0`` counts as ``n = 1``; an image and a reference of
different sizes raise ``ValueError`` with both sizes.
"""
from __future__ import annotations

import numpy as np

from .method import MethodResult, allocate

#: the relMSE denominator's epsilon (DESIGN.md)
REL_EPS = 0.01


def true_relative_error(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(H, W) per-pixel relative squared error ``mean_c (x-r)^2 / (r^2 + 0.01)``.

    Non-finite reconstructed values give the largest finite error of the image
    (1.0 when there is none); non-finite reference pixels give NaN (unknown),
    which callers replace.
    """
    x = np.asarray(image, np.float64)[..., :3]
    r = np.asarray(reference, np.float64)[..., :3]
    if x.shape != r.shape:
        raise ValueError(f"oracle: image is {x.shape[1]}x{x.shape[0]} but the reference is "
                         f"{r.shape[1]}x{r.shape[0]}")
    ref_ok = np.isfinite(r).all(axis=-1)
    r0 = np.where(np.isfinite(r), r, 0.0)
    with np.errstate(over="ignore", invalid="ignore"):
        e = (x - r0) ** 2 / (r0 * r0 + REL_EPS)
    bad = ~np.isfinite(e)
    fin = e[~bad]
    top = float(fin.max()) if fin.size else 0.0
    top = top if top > 0 else 1.0
    e = np.where(bad, top, e).mean(axis=-1)
    return np.where(ref_ok, e, np.nan)


def box_mean(a: np.ndarray, radius: int) -> np.ndarray:
    """Mean over a (2 radius + 1)^2 box (edges: over the pixels inside), via
    summed-area tables; NaN entries are left out of the mean."""
    if radius <= 0:
        return a
    ok = np.isfinite(a)
    v = np.where(ok, a, 0.0)
    c = ok.astype(np.float64)

    def boxsum(z):
        h, w = z.shape
        s = np.zeros((h + 1, w + 1))
        s[1:, 1:] = z.cumsum(0).cumsum(1)
        y0 = np.clip(np.arange(h) - radius, 0, h)
        y1 = np.clip(np.arange(h) + radius + 1, 0, h)
        x0 = np.clip(np.arange(w) - radius, 0, w)
        x1 = np.clip(np.arange(w) + radius + 1, 0, w)
        return s[y1][:, x1] - s[y0][:, x1] - s[y1][:, x0] + s[y0][:, x0]

    num, den = boxsum(v), boxsum(c)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


def gain_exponent(result: MethodResult | None, default: float = 1.0) -> float:
    """``4 / (d + 4)`` from the model dimension a method reports, else ``default``."""
    info = getattr(result, "info", None) or {}
    for key in ("mean_rank", "active_features"):
        d = info.get(key)
        if isinstance(d, (int, float)) and np.isfinite(d) and d >= 0:
            return 4.0 / (float(d) + 4.0)
    return default


def oracle_weights(image: np.ndarray, reference: np.ndarray, n: np.ndarray,
                   exponent: float = 1.0, radius: int = 1) -> np.ndarray:
    """(H, W) finite, >= 0 weights ``box(e)_i * max(n_i, 1)^(-exponent)``."""
    e = box_mean(true_relative_error(image, reference), int(radius))
    fin = np.isfinite(e)
    fill = float(e[fin].mean()) if fin.any() else 1.0
    e = np.where(fin, e, fill)
    n = np.asarray(n, np.float64)
    if n.shape != e.shape:
        raise ValueError(f"oracle: sample counts are {n.shape[1]}x{n.shape[0]}, the image "
                         f"{e.shape[1]}x{e.shape[0]}")
    n = np.where(np.isfinite(n) & (n >= 1.0), n, 1.0)
    g = e * n ** (-float(exponent))
    return np.where(np.isfinite(g) & (g > 0), g, 0.0)


def oracle_map(image, reference, n, budget: int, exponent: float = 1.0, radius: int = 1) -> np.ndarray:
    """(H, W) int64 new samples per pixel, summing to ``budget``, in proportion
    to :func:`oracle_weights` (uniform when the image matches the reference)."""
    return allocate(oracle_weights(image, reference, n, exponent, radius), int(budget))


class OracleMethod:
    """A method module's interface (``PASSES``, ``ADAPTIVE``, ``Params``,
    ``reconstruct``, ``sample_map``) around ``base`` with the oracle's map.

    base : a method module (``core.methods.get(name)``)
    reference : (H, W, 3) reference of the image domain the loop renders
    radius : pooling radius of the true error (see the module notes)
    """

    def __init__(self, base, reference: np.ndarray, radius: int = 1, name: str | None = None):
        ref = np.asarray(reference, np.float64)
        if ref.ndim != 3 or ref.shape[2] < 3:
            raise ValueError(f"oracle: the reference must be (H, W, 3), got {ref.shape}")
        self.base = base
        self.reference = ref[..., :3]
        self.radius = int(radius)
        self.name = name or ("oracle-" + getattr(base, "__name__", "method").rsplit(".", 1)[-1])
        self.PASSES = tuple(getattr(base, "PASSES", ()))
        self.ADAPTIVE = getattr(base, "ADAPTIVE", True)
        self.Params = base.Params

    def reconstruct(self, buf, params=None) -> MethodResult:
        return self.base.reconstruct(buf, params)

    def sample_map(self, buf, result: MethodResult, budget: int, params=None, state=None) -> np.ndarray:
        if result is None:
            result = self.base.reconstruct(buf, params)
        if tuple(buf.shape) != self.reference.shape[:2]:
            h, w = self.reference.shape[:2]
            raise ValueError(f"oracle: the render is {buf.width}x{buf.height} but the reference "
                             f"is {w}x{h}")
        p = gain_exponent(result, 1.0)
        counts = oracle_map(result.image, self.reference, buf.n, budget, p, self.radius)
        if state is not None:
            state["oracle_calls"] = int(state.get("oracle_calls", 0)) + 1
        return counts

"""The method contract, what every method returns, and the shared
sample-allocation helpers.

A method is any object satisfying :class:`Method`; the four seed methods and
``uniform`` are modules of ``core/`` registered in ``core/methods.py``, and
wrappers (``core.oracle.OracleMethod``, ``core.var.REPROJECT``) are objects
with the same members.  The render loop (``core/pipeline.py``) reads nothing
else.  Each method module also offers the array-level entry
``denoise(color, color_var, features=None, feature_var=None, n=None,
params=None) -> MethodResult`` (same signature everywhere): the method's
reconstruction of plain arrays, for callers without a Buffers object.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np

from .buffers import _tmp, luminance


@dataclass
class MethodResult:
    """image : (H, W, 3) float64 reconstructed image.
    error : (H, W) float64 estimated per-pixel squared error of ``image``
        (absolute, averaged over RGB).
    info : dict of scalar diagnostics (e.g. LP's centre-pixel fraction), for
        reports only: no sampler reads it.
    dimension : model dimension ``d`` of the reconstruction (LP: mean TSVD
        rank; RHF: active regression features), which sets the exponent of
        :func:`sampling_gain`; None for methods without a regression model.
    fit : the method's own model of this reconstruction, reused by its sampler
        (LP: the ``LPFit`` with per-pixel error reductions); None otherwise.
    """

    image: np.ndarray
    error: np.ndarray
    info: dict = field(default_factory=dict)
    dimension: float | None = None
    fit: Any = None


@runtime_checkable
class Method(Protocol):
    """What the render loop needs of a method; every member is declared by
    every method (no defaults read with ``getattr``).

    NAME : str, the name reports and checkpoints use.
    PASSES : tuple of feature pass names it reads (``buffers.FEATURE_CHANNELS``).
    Params : dataclass of its parameters with the paper's defaults; each field
        made by :func:`param` (help, min, max), from which the CLI and the
        panel are generated.
    ADAPTIVE : bool; False: the loop renders the whole budget uniformly in its
        initial pass and never asks for a map.
    SAMPLER_USES_RESULT : bool; False: ``sample_map`` ignores ``result`` and
        the loop does not reconstruct between iterations (AWR, var).

    One optional member, read with ``getattr`` (as ``methods.method_for``):
    ``map_result(buf, params) -> MethodResult``, the reconstruction the loop
    hands ``sample_map`` between iterations when it may be cheaper than the
    final one (oidn: its error estimate without the albedo / normal
    prefilter; lp, rhf: without the kept noise of the error map); without it
    the loop calls ``reconstruct``.  A method whose map splits into pure
    pieces (lp: ``fit_band``, bands of rows with the same bits as the whole
    frame) also takes ``map_result(buf, params, run=, parts=)`` and
    ``reconstruct(buf, params, run=, parts=)``, and the loop spreads both
    (maps, target checks, the final fit) over an executor's ``run_jobs``
    (farm workers).
    """

    NAME: str
    PASSES: tuple
    Params: type
    ADAPTIVE: bool
    SAMPLER_USES_RESULT: bool

    def reconstruct(self, buf, params) -> MethodResult:
        """The final image from the accumulated samples."""

    def sample_map(self, buf, result: MethodResult | None, budget: int, params,
                   state: dict) -> np.ndarray:
        """(H, W) int64 new samples per pixel summing to ``budget`` (ties and
        rounding may leave it off by a few samples).  ``result`` is the
        reconstruction of ``buf`` (None when ``SAMPLER_USES_RESULT`` is False);
        ``state`` is the method's own dict, kept by the loop between
        iterations and checkpointed."""


def gain_exponent(dimension) -> np.ndarray | float:
    """``4 / (d + 4)``: the rate at which a local regression's error falls with
    the sample count, ``n^(-4/(d+4))`` for a model of dimension ``d`` (Moon et
    al. 2014, used by LP Sec. 5.2).  ``d`` scalar or array, clamped to >= 0."""
    d = np.maximum(np.asarray(dimension, np.float64), 0.0)
    return 4.0 / (d + 4.0)


def sampling_gain(error: np.ndarray, n: np.ndarray, dimension=None) -> np.ndarray:
    """Error reduction of one more sample, ``err_i n_i^(-4/(d+4))`` (LP Sec.
    5.2); with ``dimension`` None the Monte Carlo rate ``err_i / n_i``.  ``n``
    is clamped to >= 1 (pixels without samples count as one)."""
    n = np.asarray(n, np.float64)
    n = np.where(np.isfinite(n) & (n >= 1.0), n, 1.0)
    p = 1.0 if dimension is None else gain_exponent(dimension)
    return np.asarray(error, np.float64) * n ** (-p)


def relative_error(error: np.ndarray, image: np.ndarray, eps: float = 1e-3) -> np.ndarray:
    """Relative squared error ``error / (lum(image)^2 + eps)`` (LP Sec. 5.2).

    error : (H, W), image : (H, W, 3) -> (H, W) finite, >= 0.
    """
    lum = luminance(image)
    lum = np.where(np.isfinite(lum), lum, 0.0)
    e = np.where(np.isfinite(error), np.maximum(error, 0.0), 0.0)
    return e / (lum * lum + eps)


def allocate(weights: np.ndarray, budget: int, cap: np.ndarray | None = None) -> np.ndarray:
    """Integer counts proportional to ``weights`` summing exactly to ``budget``.

    Largest-remainder rounding.  Non-finite or negative weights count as zero;
    all-zero weights fall back to uniform.  ``cap`` (optional, (H, W)) bounds
    each pixel's count; the excess is redistributed to uncapped pixels.  The
    element-wise passes run over pieces of :data:`ALLOCATE_PIECE` elements on
    the controller's threads; the weights' sum and the selection of the
    largest remainders (``argpartition``, whose order among tied remainders
    only the whole array defines) stay whole-array, so the counts do not
    depend on the thread count.

    weights : (H, W) -> (H, W) int64
    """
    src = np.asarray(weights)
    budget = int(max(budget, 0))
    out = np.zeros(src.shape, np.int64)
    if budget == 0 or src.size == 0:
        return out
    flat = src.reshape(-1)
    w = np.empty(flat.size)

    def clean(p):
        x = np.asarray(flat[p[0]:p[1]], np.float64)
        w[p[0]:p[1]] = np.where(np.isfinite(x) & (x > 0), x, 0.0)

    _pieces(clean, flat.size)
    if cap is None:
        _largest_remainder(w, budget, out.reshape(-1))
        return out
    cap_arr = np.broadcast_to(np.asarray(cap, np.int64), src.shape).reshape(-1)
    budget = min(budget, int(cap_arr.sum()))
    remaining = budget
    got = out.reshape(-1)
    add = np.empty(flat.size, np.int64)
    active = cap_arr > 0
    for _ in range(64):
        if remaining <= 0 or not active.any():
            break
        _largest_remainder(np.where(active, w, 0.0), remaining, add, active)
        np.minimum(add, cap_arr - got, out=add)
        got += add
        remaining -= int(add.sum())
        active = got < cap_arr
    return out


#: elements per piece of :func:`allocate`'s element-wise passes (size only)
ALLOCATE_PIECE = 1 << 18


def _pieces(fn, n: int) -> None:
    """``fn((a, b))`` over pieces of :data:`ALLOCATE_PIECE` elements of a flat
    array of ``n``, on the controller's threads from :data:`INLINE_PIXELS` on."""
    from . import parallel
    parallel.run_bands(fn, n, ALLOCATE_PIECE, min_work=INLINE_PIXELS)


def _largest_remainder(ww: np.ndarray, remaining: int, base: np.ndarray, active=None) -> None:
    """Hamilton's largest-remainder rounding of ``ww / sum(ww) * remaining``
    into ``base`` (flat int64, summing to ``remaining``): the floors, then one
    more for the ``rest`` largest remainders.  All-zero ``ww``: ``active``
    (default all) weighs 1."""
    total = ww.sum()
    if total <= 0:
        ww = np.ones(ww.size) if active is None else active.astype(np.float64)
        total = ww.sum()
    neg_frac = np.empty(ww.size)  # floor - share = -(share - floor), exactly

    def piece(p):
        a, b = p
        share = ww[a:b] / total * remaining
        floor = np.floor(share)
        base[a:b] = floor
        np.subtract(floor, share, out=neg_frac[a:b])

    _pieces(piece, ww.size)
    rest = remaining - int(base.sum())
    if rest > 0:
        idx = np.argpartition(neg_frac, rest - 1)[:rest] if rest < neg_frac.size else np.arange(neg_frac.size)
        base[idx] += 1


def param(default, help_: str, lo=None, hi=None, **extra):
    """A ``Params`` dataclass field with the metadata the panel, the CLI and
    :func:`params_from_dict` read: ``help``, ``min``, ``max`` and any extra
    keys (e.g. ``choices``)."""
    md = {"help": help_, "min": lo, "max": hi}
    md.update(extra)
    return field(default=default, metadata=md)


def params_from_dict(cls, values: dict | None):
    """Build a ``Params`` dataclass from a dict, ignoring unknown keys, and
    checking each value against the field's ``min``/``max`` metadata."""
    values = dict(values or {})
    kwargs = {f.name: values[f.name] for f in fields(cls)
              if f.name in values and values[f.name] is not None}
    obj = cls(**kwargs)
    check_ranges(obj)
    return obj


def fields_by_name(cls) -> dict:
    """name -> dataclass field of ``cls`` (Params or Options)."""
    return {f.name: f for f in fields(cls)}


def check_ranges(obj) -> None:
    """ValueError naming the first numeric field of dataclass ``obj`` outside
    its ``min``/``max`` metadata, or not finite where it has a bound (NaN
    compares false with every bound and would pass silently), the one range
    check of Params and Options."""
    for f in fields(obj):
        v = getattr(obj, f.name)
        lo, hi = f.metadata.get("min"), f.metadata.get("max")
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            if isinstance(v, float) and not np.isfinite(v) and (lo is not None or hi is not None):
                owner = getattr(obj, "OWNER", None) or type(obj).__module__.split(".")[-1] + " parameter"
                raise ValueError(f"{owner} {f.name}={v} must be a finite number")
            if lo is not None and v < lo or hi is not None and v > hi:
                owner = getattr(obj, "OWNER", None) or type(obj).__module__.split(".")[-1] + " parameter"
                bound = (f"in [{lo}, {hi}]" if lo is not None and hi is not None
                         else f">= {lo}" if lo is not None else f"<= {hi}")
                raise ValueError(f"{owner} {f.name}={v} must be {bound}")


def t_quantile(z: float, dof: np.ndarray) -> np.ndarray:
    """Student-t threshold with the two-sided tail of a normal ``z``.

    ``(x - mean) / s`` with ``s`` estimated from ``dof`` degrees of freedom is
    t-distributed, so a fixed ``z`` on the estimated standard error would flag
    far too many pixels when the variance comes from 3 degrees of freedom.
    Returns, per entry of ``dof`` (>= 1), the t value with the same two-sided
    tail probability as ``z`` under the normal law (numerical integration of
    the t density, tabulated for 1..256 degrees of freedom; the normal ``z``
    beyond).
    """
    dof = np.asarray(dof, np.float64)
    table = _t_table(float(z))
    idx = np.clip(np.nan_to_num(dof, nan=1.0), 1, len(table)).astype(np.int64) - 1
    return np.where(dof > len(table), z, table[idx])


_T_CACHE: dict = {}


def _t_table(z: float, max_dof: int = 256) -> np.ndarray:
    """Per degrees of freedom 1..``max_dof``, the t with one-sided tail
    ``P(T > t) = P(N > z)``: the tail integral of the t density, in ``u =
    1/t`` (a finite range), by the trapezoid rule on 4096 steps; rows whose
    tail at ``t = z`` is still too small (``z`` below the t value) are
    integrated again on a range 50x wider.  Rows of ``dof`` in blocks (one
    array per block: the same sums as one row at a time, bounded memory)."""
    if z in _T_CACHE:
        return _T_CACHE[z]
    import math
    tail = math.erfc(z / math.sqrt(2.0)) / 2.0  # one-sided tail probability

    def solve(nu, n, top):
        c = np.exp(np.array([math.lgamma((v + 1) / 2) - math.lgamma(v / 2) for v in nu])) \
            / np.sqrt(nu * math.pi)
        u = np.linspace(0.0, top, n)[1:]
        t = 1.0 / u
        f = c[:, None] * np.exp(np.log1p(t * t / nu[:, None]) * (-(nu[:, None] + 1) / 2)) / (u * u)
        # cumulative tail from t = inf (u = 0) downwards
        cum = np.cumsum((f[:, 1:] + f[:, :-1]) * 0.5 * np.diff(u), axis=1)
        cum = np.concatenate([np.zeros((len(nu), 1)), cum], axis=1)
        i = (cum < tail).sum(axis=1)  # searchsorted per row (cum is non-decreasing)
        return 1.0 / u[np.clip(i, 0, len(u) - 1)], cum[:, -1] >= tail

    out = np.empty(max_dof)
    block = 32
    for lo in range(1, max_dof + 1, block):
        nu = np.arange(lo, min(lo + block, max_dof + 1), dtype=np.float64)
        t, ok = solve(nu, 4097, 1.0 / max(z, 1e-6))
        for j in np.flatnonzero(~ok):  # threshold below z: refine on a wider range
            t[j] = solve(nu[j:j + 1], 200001, 1.0 / max(z / 50.0, 1e-6))[0][0]
        out[lo - 1:lo - 1 + len(nu)] = t
    _T_CACHE[z] = out
    return out


def _med3(a, b, c, out=None):
    """Median of three arrays, elementwise, by min/max (exact, ties included);
    into ``out`` when given (one scratch temporary)."""
    if out is None:
        return np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))
    t = np.maximum(a, b, out=_tmp("med3", out.shape, out.dtype))
    np.minimum(t, c, out=t)
    return np.maximum(np.minimum(a, b, out=out), t, out=out)


def _median_band(src: np.ndarray, idx: np.ndarray, out: np.ndarray) -> np.ndarray:
    """3x3 median, into ``out``, of the ``len(idx) - 2`` rows whose padded
    rows (the rows above, themselves, below; edges replicated) are
    ``src[idx]``; columns are edge-padded here.  The min/max network of
    :func:`median3x3`, on this thread's scratch arrays (no allocation per
    band)."""
    w = src.shape[1]
    r = len(idx) - 2
    dt = src.dtype
    pad = _tmp("m_pad", (r + 2, w + 2) + src.shape[2:], dt)
    np.take(src, idx, axis=0, out=pad[:, 1:w + 1], mode="clip")  # idx valid: no buffering
    pad[:, 0] = pad[:, 1]
    pad[:, w + 1] = pad[:, w]
    a, b, c = pad[:-2], pad[1:-1], pad[2:]
    shp = a.shape
    lo = np.minimum(a, b, out=_tmp("m_lo", shp, dt))
    hi = np.maximum(a, b, out=_tmp("m_hi", shp, dt))
    mid = np.minimum(hi, c, out=_tmp("m_mid", shp, dt))
    np.maximum(hi, c, out=hi)
    lo2 = np.minimum(lo, mid, out=_tmp("m_lo2", shp, dt))
    np.maximum(lo, mid, out=mid)
    lo = lo2
    cs = out.shape
    lo3 = np.maximum(lo[:, :w], lo[:, 1:w + 1], out=_tmp("m_lo3", cs, dt))
    np.maximum(lo3, lo[:, 2:], out=lo3)
    hi3 = np.minimum(hi[:, :w], hi[:, 1:w + 1], out=_tmp("m_hi3", cs, dt))
    np.minimum(hi3, hi[:, 2:], out=hi3)
    mid3 = _med3(mid[:, :w], mid[:, 1:w + 1], mid[:, 2:], out=_tmp("m_mid3", cs, dt))
    return _med3(lo3, mid3, hi3, out=out)


def _padded_rows(y0: int, y1: int, h: int, base: int = 0) -> np.ndarray:
    """Row indices ``y0 - 1 .. y1`` clipped to ``[0, h)`` (edge replication),
    minus ``base`` (the first row held by the array they index)."""
    return np.clip(np.arange(y0 - 1, y1 + 1), 0, h - 1) - base


#: relative difference below which the guard's correction is float rounding:
#: float32's machine epsilon (the finest an output file stores)
FLOAT32_EPS = float(np.finfo(np.float32).eps)

#: pixels below which the guard and the median run inline (threads do not pay;
#: measured: docs/notes/farm.md)
INLINE_PIXELS = 65536
#: pixels per row band of the guard and the median (at least MIN_ROWS rows):
#: a band's scratch arrays are about 360 bytes a pixel per thread
BAND_PIXELS = 32768
MIN_ROWS = 8


def _band_rows(rows, w: int) -> int:
    """``rows``, or by default about :data:`BAND_PIXELS` pixels of width ``w``."""
    if rows is not None:
        return max(1, int(rows))
    return max(MIN_ROWS, BAND_PIXELS // max(1, int(w)))


def _bands(fn, h: int, w: int, rows: int) -> list:
    """``fn((y0, y1))`` over row bands of ``rows`` rows, on the controller's
    threads from :data:`INLINE_PIXELS` pixels on; results in band order."""
    from . import parallel
    if h * w < INLINE_PIXELS:
        return [fn(b) for b in parallel.bands(h, rows)]
    return parallel.run_bands(fn, h, rows)


def median3x3(x: np.ndarray, rows: int | None = None) -> np.ndarray:
    """3x3 median of each channel of ``x`` (H, W, C), edges replicated.

    The same values as ``np.median`` over the 9 shifted planes of the
    edge-padded image: each column of three is sorted (min, mid, max), and
    the median of the 3x3 window is the median of (the largest of the three
    minima, the median of the three mids, the smallest of the three maxima)
    (Paeth, "Median finding on a 3x3 grid", Graphics Gems, 1990).  Only
    min/max, so the value is exact, ties included, and a NaN anywhere in the
    window gives NaN, as ``np.median`` does.  Row bands of ``rows`` rows
    (default :func:`_band_rows`; each padded by its neighbour rows, no
    whole-frame copy) keep the planes in cache and run on the controller's
    threads: the same values for any thread count.
    """
    x = np.asarray(x)
    h, w = x.shape[:2]
    out = np.empty_like(x)
    if h * w == 0:
        return out

    def band(b):
        y0, y1 = b
        _median_band(x, _padded_rows(y0, y1, h), out[y0:y1])

    _bands(band, h, w, _band_rows(rows, w))
    return out


def _guard_rows(buf, y0: int, y1: int):
    """Rows ``y0:y1`` of the guard's inputs, on this thread's scratch arrays:
    (variance of the mean, known, standard error); known = a variance
    estimate exists and mean and variance are finite, the standard error is
    ``sqrt(max(var, 0))`` where known, else 0.  The same values as
    :meth:`Buffers.variance_of_mean` and the whole-frame expressions."""
    k, n = buf.k[y0:y1], buf.n[y0:y1]
    m2 = buf.color.m2[y0:y1]
    shp = m2.shape
    ok = (k >= 2) & (n > 0)
    den = np.subtract(k, 1.0, out=_tmp("g_den", k.shape))
    np.multiply(den, n, out=den)
    np.copyto(den, 1.0, where=~ok)
    var = _tmp("g_var", shp)
    var.fill(np.inf)
    np.divide(m2, den[..., None], out=var, where=ok[..., None])
    known = np.isfinite(var, out=_tmp("g_known", shp, bool))
    known &= np.isfinite(buf.color.mean[y0:y1], out=_tmp("g_fin", shp, bool))
    known &= (k >= 2)[..., None]
    sd = np.maximum(var, 0.0, out=_tmp("g_sd", shp))
    np.copyto(sd, 0.0, where=~known)
    np.sqrt(sd, out=sd)
    return var, known, sd


def _floored_sd(buf, y0: int, y1: int, h: int):
    """Rows ``y0:y1`` of the guard's (known, standard error), the standard
    error floored at the 3x3 median of its neighbours' (computed from one row
    more on each side), so a pixel whose few subsets agreed by chance (e.g.
    all missed a rare light path) is judged with its neighbourhood's noise
    level, not with a near-zero one.  On this thread's scratch arrays."""
    e0, e1 = max(0, y0 - 1), min(h, y1 + 1)
    _, known, sd = _guard_rows(buf, e0, e1)
    shp = (y1 - y0,) + sd.shape[1:]
    med = _median_band(sd, _padded_rows(y0, y1, h, e0), _tmp("g_med", shp, sd.dtype))
    return known[y0 - e0:y1 - e0], np.maximum(sd[y0 - e0:y1 - e0], med, out=med)


def exact_pixels(buf, rows: int | None = None) -> np.ndarray:
    """(H, W) bool: pixels whose samples show no noise at all, as the
    consistency guard judges them: a variance estimate in every channel
    (k >= 2 subsets, finite) and a standard error of zero after the guard's
    3x3-median floor (its own subsets agree exactly, and so do most of its
    neighbours': a flat background lit by a constant world).  The guard
    sends any change at such a pixel back to the mean, so a method that
    changes them (OIDN shifts a flat background by ~0.3 %) should keep them
    itself; an isolated zero-variance pixel among noisy ones (subsets that
    agreed by chance) is not exact.  Row bands on the controller's threads,
    as the guard."""
    h, w = buf.n.shape[:2]
    out = np.zeros((h, w), bool)
    rows = _band_rows(rows, w)

    def judge(b):
        known, sd = _floored_sd(buf, b[0], b[1], h)
        np.logical_and(known.all(axis=-1), (sd == 0).all(axis=-1), out=out[b[0]:b[1]])

    _bands(judge, h, w, rows)
    return out


def consistency_guard(result: MethodResult, buf, z: float = 3.0, rows: int | None = None) -> MethodResult:
    """Reject reconstructed pixels that contradict their own samples.

    A pixel whose reconstruction differs from its own sample mean by more than
    ``t`` standard errors of that mean in some channel (``|x - mean| > t *
    sqrt(var_of_mean)``), where ``t`` is the Student-t value with the same
    two-sided tail as the normal ``z`` for the pixel's ``k - 1`` degrees of
    freedom (:func:`t_quantile`: about 9.2 for 3, 4.3 for 8, ``z`` for many),
    is replaced by its sample mean, and its estimated error by its variance of
    the mean.  The standard error used is at least the 3x3 median of its
    neighbours' (a pixel whose few subsets agreed by chance, e.g. all missed a
    rare light path, would otherwise be pinned to a wrong mean: that cost LP
    2.4x relMSE on cornell at 4 spp; with the floor 1.2x).  This is our safeguard, not part of any
    of the papers: local regressions and wavelet thresholds spread a bright
    highlight or firefly into neighbours whose own samples say otherwise (LP on
    the glossy scene put 1.2 on pixels whose 23 samples gave 0.137, reference
    0.138).  Pixels without a variance estimate (k < 2) or with non-finite
    input are left to the method.  Zero-variance pixels must come back
    unchanged, which the guard enforces too.  ``z <= 0`` disables it.

    Per pixel, so it runs over row bands of ``rows`` rows (default
    :func:`_band_rows`) on the controller's
    threads (each band computes the standard errors of one row more on each
    side for the median): the same bits for any thread count.

    Returns a new MethodResult; ``info['guard_fraction']`` is the share of
    pixels corrected: replaced, and off their mean by more than float32
    rounding in some channel (``|x - mean| > FLOAT32_EPS max(|x|, |mean|)``).
    ``info['guard_rounding']`` is the share replaced for a smaller difference
    only: a regression's float64 rounding at a zero-variance pixel (LP on a
    flat background: 1e-17), which no output file (at most float32) can hold
    and which is no contradiction; they are set back to the exact mean all
    the same.
    """
    if z is None or z <= 0:
        return result
    mean = buf.color.mean
    h, w = mean.shape[:2]
    image = np.broadcast_to(result.image, mean.shape)
    error = np.broadcast_to(result.error, (h, w))
    if not np.any((image != mean) & np.isfinite(mean)):
        # the reconstruction is the sample mean wherever the guard judges (uniform,
        # var): no pixel can contradict its samples
        return replace(result, info=dict(result.info, guard_fraction=0.0, guard_rounding=0.0))
    _t_table(float(z))  # fill the cache once, before the bands read it
    bad = np.zeros((h, w), bool)
    real = np.zeros((h, w), bool)
    rows = _band_rows(rows, w)

    def judge(b):
        y0, y1 = b
        known, sd = _floored_sd(buf, y0, y1, h)
        shp = sd.shape
        thr = t_quantile(z, np.maximum(buf.k[y0:y1] - 1.0, 1.0))[..., None]
        with np.errstate(invalid="ignore"):
            d = np.subtract(image[y0:y1], mean[y0:y1], out=_tmp("g_d", shp))
            np.abs(d, out=d)
            off = np.greater(d, np.multiply(thr, sd, out=sd), out=_tmp("g_off", shp, bool))
        off &= known
        np.logical_and(off.any(axis=-1), known.all(axis=-1), out=bad[y0:y1])
        # corrected beyond float32 rounding (d is still |x - mean|)
        with np.errstate(invalid="ignore"):
            scale = np.maximum(np.abs(image[y0:y1]), np.abs(mean[y0:y1]), out=_tmp("g_scale", shp))
            off &= np.greater(d, np.multiply(scale, FLOAT32_EPS, out=scale), out=_tmp("g_real", shp, bool))
        np.logical_and(off.any(axis=-1), bad[y0:y1], out=real[y0:y1])

    _bands(judge, h, w, rows)
    if not bad.any():
        info = dict(result.info, guard_fraction=0.0, guard_rounding=0.0)
        return replace(result, info=info)
    out_image = np.empty(mean.shape, np.result_type(mean, image))
    out_err = np.empty((h, w), np.result_type(np.float64, error))

    def fix(b):
        y0, y1 = b
        bb = bad[y0:y1]
        oi, oe = out_image[y0:y1], out_err[y0:y1]
        oi[...] = image[y0:y1]
        np.copyto(oi, mean[y0:y1], where=bb[..., None])
        oe[...] = error[y0:y1]
        ys, xs = np.nonzero(bb)
        if ys.size:  # the error of the replaced pixels: their variance of the mean
            yy = ys + y0
            k, n, m2 = buf.k[yy, xs], buf.n[yy, xs], buf.color.m2[yy, xs]
            ok = (k >= 2) & (n > 0)
            den = np.where(ok, (k - 1.0) * n, 1.0)[..., None]
            var = np.full(m2.shape, np.inf)
            np.divide(m2, den, out=var, where=ok[..., None])
            known = (k >= 2)[..., None] & np.isfinite(var) & np.isfinite(mean[yy, xs])
            oe[ys, xs] = np.where(known, var, 0.0).mean(axis=-1)

    _bands(fix, h, w, rows)
    info = dict(result.info, guard_fraction=float(real.mean()),
                guard_rounding=float(bad.mean() - real.mean()))
    return replace(result, image=out_image, error=out_err, info=info)

"""Wavelet filter banks and the non-standard 2D DWT of adaptive wavelet rendering.

Overbeck, Donner, Ramamoorthi 2009, "Adaptive Wavelet Rendering" (AWR), Sec. 3,
Appendix A (filter banks) and Appendix B (variance propagation, Eq. 9-10, 15).

Conventions (read these before comparing with other libraries)
----------------------------------------------------------------
* **Normalisation.**  The filters are exactly those of Appendix A: the analysis
  low-pass sums to ``sqrt(2)`` (so a constant image ``c`` has level-k scale
  coefficients ``c * 2**k`` in 2D) and the analysis/synthesis pair is
  biorthogonal, i.e. the transform is perfectly reconstructing.  Appendix A
  prints six digits; we use the exact CDF 9/7 filters (computed here by the
  spectral factorisation of Cohen, Daubechies, Feauveau 1992), which agree with
  the printed digits to 6 decimals, because the rounded ones reconstruct only
  to ~1e-6.  LeGall 5/3 and Haar are exact rationals / ``1/sqrt(2)``.
* **Signs.**  High-pass signs are the paper's: CDF 9/7 analysis high-pass has
  ``+1.115087/sqrt(2)`` at its centre, LeGall 5/3 ``-1/sqrt(2)``.  Compared with
  PyWavelets (``bior4.4``, ``bior2.2``, ``haar``) the scale coefficients are
  identical and the detail coefficients equal PyWavelets' times ``-1``
  (cdf97) or ``+1`` (legall53, haar) per high-pass filter (so ``W2``, with
  two, equals PyWavelets' ``cD``), after an index shift (PyWavelets'
  boundary modes keep extra, redundant boundary coefficients).  PyWavelets
  has no non-expansive symmetric mode, so its multi-level 'reflect' results
  differ near the borders; our transform of an axis of ``N`` samples is its
  ``'periodization'`` of the whole-sample mirror (period ``2N - 2``), which
  for ``N = 2**m + 1`` holds at every depth (tests/core/test_wavelets.py and
  the end-to-end reconstruction in tests/core/test_awr.py).
* **Alignment and boundaries.**  For the odd-length symmetric banks (cdf97,
  legall53) the low-pass output ``s[i]`` is centred on input sample ``2i`` and
  the high-pass output ``d[i]`` on sample ``2i + 1``; the signal is extended by
  whole-sample symmetry (``x[-m] = x[m]``, ``x[N-1+m] = x[N-1-m]``; PyWavelets
  mode ``'reflect'``).  Haar pairs samples ``(2i, 2i+1)`` and uses half-sample
  symmetry (PyWavelets mode ``'symmetric'``).  Both are non-expansive: a length
  ``N`` axis gives ``ceil(N/2)`` scale and ``floor(N/2)`` wavelet coefficients,
  for any ``N`` (odd, prime, non-power-of-two).  An axis of length 1 is not
  transformed (identity, no wavelet coefficients), so a 1 x N image gets a 1D
  DWT along its length.
* **Non-standard 2D DWT** (Sec. 3): each level filters along x (axis 1) and then
  along y (axis 0) and recurses on the low-low band.  The three wavelets of a
  level are, with the paper's ``Psi^0 = phi (x) psi^T``, ``Psi^1 = psi (x) phi^T``,
  ``Psi^2 = psi (x) psi^T``:

  ``W0`` low-pass along y, high-pass along x   (PyWavelets ``cV`` / ``'ad'``)
  ``W1`` high-pass along y, low-pass along x   (PyWavelets ``cH`` / ``'da'``)
  ``W2`` high-pass along both                  (PyWavelets ``cD`` / ``'dd'``)

* **Level indices** follow the paper: level 0 are the pixels, level ``k`` has
  dilation ``2**k``; ``Pyramid.details[k - 1]`` holds level ``k``.

Variance propagation (Eq. 9, 10 and Appendix B) runs the same DWT with the
*squared* filter taps, optionally renormalised so each squared 1D filter sums to
a given value (the paper's 1.05 for the sampler, 2**-1/2 for reconstruction).
For uncorrelated inputs this is exact for one level away from the boundary; at
deeper levels and at the boundaries it ignores covariances between overlapping
coefficients, which is the bias the paper accepts ("This biases our estimate of
sigma^2(S) when using filters with overlapping support, but it works well in
practice").  Haar has no overlap and is exact at every level.

All functions are pure numpy, vectorised over pixels (loops run over levels and
filter taps only), and accept (H, W) or (H, W, C) arrays (the trailing axes are
carried along; pass ``axes`` to transform other axes).

Precision and speed: float64 by default; ``dtype=np.float32`` for the
reconstruction's fast path (``core.awr``, "Precision").  Each 1D filter is one
contraction over a strided window of the symmetrically extended signal; along
the last axis of a 2D float32 array, where that contraction cannot vectorise
over rows, it is a blocked matrix product instead (16 outputs per block from a
window of 2 x 16 + K - 2 inputs: sgemm, more multiply-adds but faster; at most
128 rows per product, below OpenBLAS's own threading, whose spinning threads
would fight the caller's).  Filters, not lifting: lifting was slower in numpy
(more, smaller array operations).
Measurements and design notes: docs/notes/awr.md.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

__all__ = [
    "FilterBank", "BANKS", "get_bank", "squared_bank", "cdf97_halves",
    "Pyramid", "max_levels", "level_shapes", "axis_levels",
    "dwt2", "idwt2", "scale_coefficients", "dwt2_variance", "scale_variance",
    "idwt2_variance", "scale_function",
]

SQRT2 = np.sqrt(2.0)


# ----------------------------------------------------------------------------
# Filter banks (Appendix A)
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class FilterBank:
    """A two-channel filter bank.

    For ``kind == "symmetric"`` each filter is stored as its half, centre tap
    first, exactly as Appendix A lists them ("The rest can be obtained by
    reflecting about the first coefficient"); the full filter is
    ``f[m] = half[|m|]`` for ``|m| < len(half)``.  The analysis low-pass reads
    ``x[2i - m]``, the analysis high-pass ``x[2i + 1 - m]``.

    For ``kind == "haar"`` each filter is the pair of taps applied to / producing
    samples ``(2i, 2i + 1)``.

    Attributes
    ----------
    name : str
    lo_a, hi_a : (L,) float64 analysis low-pass / high-pass
    lo_s, hi_s : (L,) float64 synthesis low-pass / high-pass
    kind : "symmetric" or "haar"
    """

    name: str
    lo_a: np.ndarray
    hi_a: np.ndarray
    lo_s: np.ndarray
    hi_s: np.ndarray
    kind: str = "symmetric"

    def full(self, which: str) -> tuple[int, np.ndarray]:
        """Full filter ``(first_offset, taps)``; offsets are input offsets
        relative to ``2i`` for the low-pass (``2i + 1`` for the high-pass)."""
        half = np.asarray(getattr(self, which), np.float64)
        if self.kind == "haar":
            return 0, half.copy()
        return -(len(half) - 1), np.concatenate([half[:0:-1], half])


def cdf97_halves() -> dict:
    """Exact Cohen-Daubechies-Feauveau 9/7 halves in the Appendix A layout.

    Spectral factorisation: with ``y = sin^2(w/2)`` the Daubechies polynomial
    ``P(y) = 1 + 4y + 10y^2 + 20y^3`` splits into its real-root linear factor
    ``(1 - y/r)`` and a quadratic ``Q(y)``; the 9-tap analysis low-pass is
    ``sqrt(2) cos^4(w/2) Q(y)`` and the 7-tap synthesis low-pass
    ``sqrt(2) cos^4(w/2) (1 - y/r)``.  High-passes are the modulated
    opposite low-passes with the signs of Appendix A.

    Returns
    -------
    dict with keys ``lo_a`` (5,), ``hi_a`` (4,), ``lo_s`` (4,), ``hi_s`` (5,).
    """
    roots = np.roots([20.0, 10.0, 4.0, 1.0])
    r = float(np.real(roots[np.argmin(np.abs(np.imag(roots)))]))
    # P(y) / (1 - y / r): polynomial division, coefficients highest power first.
    quad, _ = np.polydiv([20.0, 10.0, 4.0, 1.0], [-1.0 / r, 1.0])
    m = 64
    w = 2.0 * np.pi * np.arange(m) / m
    y = np.sin(w / 2.0) ** 2
    c4 = np.cos(w / 2.0) ** 4
    h_a = SQRT2 * c4 * np.polyval(quad, y) / np.polyval(quad, 0.0)
    h_s = SQRT2 * c4 * (1.0 - y / r)
    # Real, even trigonometric polynomials: taps by the inverse DFT.
    taps_a = np.real(np.fft.ifft(h_a))
    taps_s = np.real(np.fft.ifft(h_s))
    lo_a = taps_a[:5].copy()
    lo_s = taps_s[:4].copy()
    sign = (-1.0) ** np.arange(5)
    return {"lo_a": lo_a, "hi_a": lo_s * sign[:4], "lo_s": lo_s, "hi_s": lo_a * sign}


def _make_banks() -> dict:
    c = cdf97_halves()
    s2 = SQRT2
    return {
        "cdf97": FilterBank("cdf97", c["lo_a"], c["hi_a"], c["lo_s"], c["hi_s"]),
        "legall53": FilterBank(
            "legall53",
            s2 / 8.0 * np.array([6.0, 2.0, -1.0]),
            1.0 / s2 / 2.0 * np.array([-2.0, 1.0]),
            1.0 / s2 / 2.0 * np.array([2.0, 1.0]),
            s2 / 8.0 * np.array([-6.0, 2.0, 1.0]),
        ),
        "haar": FilterBank(
            "haar",
            np.array([1.0, 1.0]) / s2,
            np.array([1.0, -1.0]) / s2,
            np.array([1.0, 1.0]) / s2,
            np.array([1.0, -1.0]) / s2,
            kind="haar",
        ),
    }


#: The filter banks of Appendix A (plus Haar, compared in Fig. 8).
BANKS: dict = _make_banks()


def get_bank(bank) -> FilterBank:
    """``FilterBank`` from a name (``"cdf97"``, ``"legall53"``, ``"haar"``) or itself."""
    if isinstance(bank, FilterBank):
        return bank
    try:
        return BANKS[str(bank).lower()]
    except KeyError:
        raise ValueError(f"unknown wavelet {bank!r}; choose one of {sorted(BANKS)}") from None


def _filter_sum(half: np.ndarray, kind: str) -> float:
    if kind == "haar":
        return float(np.sum(half))
    return float(half[0] + 2.0 * np.sum(half[1:]))


@lru_cache(maxsize=64)
def _squared_cached(name: str, lo_sum, hi_sum) -> FilterBank:
    b = BANKS[name]

    def sq(half, target):
        h2 = np.asarray(half, np.float64) ** 2
        if target is None:
            return h2
        return h2 * (float(target) / _filter_sum(h2, b.kind))

    return FilterBank(f"{name}^2[{lo_sum},{hi_sum}]", sq(b.lo_a, lo_sum), sq(b.hi_a, hi_sum),
                      sq(b.lo_s, lo_sum), sq(b.hi_s, hi_sum), kind=b.kind)


def squared_bank(bank, lo_sum: float | None = None, hi_sum: float | None = None) -> FilterBank:
    """Bank of squared taps, for propagating variances (Eq. 9, 10, 15).

    Parameters
    ----------
    bank : name or FilterBank (one of ``BANKS``)
    lo_sum, hi_sum : float or None
        Renormalise every squared low-pass (high-pass) 1D filter so its taps sum
        to this value; ``None`` keeps the natural squares, which give the exact
        variance of one level for uncorrelated inputs.  The paper renormalises
        the sampler's low-pass to 1.05 (Sec. 4.1) and the reconstruction's
        filters to ``2**-0.5`` (Sec. 4.2).  Synthesis filters get the same
        renormalisation.
    """
    b = get_bank(bank)
    key = lambda v: None if v is None else float(v)
    return _squared_cached(b.name, key(lo_sum), key(hi_sum))


# ----------------------------------------------------------------------------
# Shapes
# ----------------------------------------------------------------------------
def axis_levels(n: int) -> int:
    """Levels at which an axis of length ``n`` is actually halved (ceil(log2 n))."""
    n = int(n)
    t = 0
    while n > 1:
        n = (n + 1) // 2
        t += 1
    return t


def max_levels(shape) -> int:
    """Full depth: levels until both axes have length 1 (paper: ``n`` for 2^n images)."""
    return max(axis_levels(shape[0]), axis_levels(shape[1]))


def level_shapes(shape, levels: int) -> list:
    """``[(h_0, w_0), ..., (h_L, w_L)]`` scale-coefficient grid sizes, level 0 = pixels."""
    h, w = int(shape[0]), int(shape[1])
    out = [(h, w)]
    for _ in range(int(levels)):
        h, w = (h + 1) // 2, (w + 1) // 2
        out.append((h, w))
    return out


def _clamp_levels(shape, levels) -> int:
    full = max_levels(shape)
    if levels is None:
        return full
    return int(max(0, min(int(levels), full)))


# ----------------------------------------------------------------------------
# One axis
# ----------------------------------------------------------------------------
def _wss_index(pos: np.ndarray, n: int) -> np.ndarray:
    """Whole-sample symmetric extension index (period 2n - 2)."""
    if n == 1:
        return np.zeros_like(pos)
    p = 2 * n - 2
    j = np.mod(pos, p)
    return np.where(j >= n, p - j, j)


def _extend(x: np.ndarray, axis: int, pad: int) -> np.ndarray:
    """Whole-sample symmetric extension by ``pad`` samples on both ends."""
    n = x.shape[axis]
    if n <= pad + 1:
        return np.take(x, _wss_index(np.arange(-pad, n + pad), n), axis=axis)
    shp = list(x.shape)
    shp[axis] = n + 2 * pad
    out = np.empty(shp, x.dtype)
    nd = x.ndim
    out[_sl(axis, nd, slice(pad, pad + n))] = x
    out[_sl(axis, nd, slice(0, pad))] = x[_sl(axis, nd, slice(pad, 0, -1))]
    out[_sl(axis, nd, slice(pad + n, n + 2 * pad))] = x[_sl(axis, nd, slice(n - 2, n - 2 - pad, -1))]
    return out


def _sl(axis: int, ndim: int, s: slice) -> tuple:
    idx = [slice(None)] * ndim
    idx[axis] = s
    return tuple(idx)


#: outputs per filter and block of the matrix products (``_blocked_filter``;
#: block sizes compared in docs/notes/awr.md)
_BLOCK = 16
#: rows per matrix product: keeps every product below OpenBLAS's threading
#: thresholds (gemm 4 * 65536 multiply-adds, gemv 9216 entries, the latter for
#: one-column remainder blocks), whose threads spin in the kernel while they
#: wait and fight the reconstruction's own thread pool
_GEMM_ROWS = 128
_BLOCK_MATS: dict = {}


def _window(root: np.ndarray, offset: int, shape: tuple, strides: tuple,
            writeable: bool = False) -> np.ndarray:
    """Strided view of the C-contiguous ``root`` starting ``offset`` bytes in:
    what ``numpy.lib.stride_tricks.as_strided`` makes, at less cost per call,
    which counts here (thousands of calls per reconstruction, each holding the
    GIL).  numpy checks the view stays inside ``root``."""
    if not root.flags.c_contiguous:
        raise ValueError("window root must be C-contiguous")
    v = np.ndarray(shape, root.dtype, buffer=root, offset=offset, strides=strides)
    if not writeable:
        v.flags.writeable = False
    return v


def _gemm_blocks(src: np.ndarray, src_col: int, mat: np.ndarray, out: np.ndarray,
                 out_col: int, nblk: int, in_step: int, out_step: int) -> None:
    """``out[:, c + j*out_step : ... + w_out] = src[:, s + j*in_step : ... + w_in]
    @ mat`` for ``j < nblk`` (``mat`` is ``(w_in, w_out)``, ``s = src_col``,
    ``c = out_col``; ``src`` and ``out`` C-contiguous 2D), as stacked matrix
    products of at most ``_GEMM_ROWS`` rows each (strided views, no copies):
    one call for the whole row chunks, one for the rows left over, the GIL
    released throughout each."""
    if nblk <= 0:
        return
    w_in, w_out = mat.shape
    (rs_in, es_in), (rs_out, es_out) = src.strides, out.strides
    h = src.shape[0]
    hq = h // _GEMM_ROWS
    for y0, chunks, rows in ((0, hq, _GEMM_ROWS), (hq * _GEMM_ROWS, 1, h - hq * _GEMM_ROWS)):
        if not chunks or not rows:
            continue
        # (blocks, row chunks, rows, window)
        v = _window(src, y0 * rs_in + src_col * es_in, (nblk, chunks, rows, w_in),
                    (in_step * es_in, rows * rs_in, rs_in, es_in))
        o = _window(out, y0 * rs_out + out_col * es_out, (nblk, chunks, rows, w_out),
                    (out_step * es_out, rows * rs_out, rs_out, es_out), writeable=True)
        np.matmul(v, mat, out=o)


_FULL: dict = {}


def _full_taps(half: np.ndarray, dtype) -> np.ndarray:
    """``half[:0:-1] ++ half`` in ``dtype`` (cached: filters are few)."""
    key = (half.tobytes(), np.dtype(dtype).str)
    f = _FULL.get(key)
    if f is None:
        f = np.concatenate([half[:0:-1], half]).astype(dtype)
        f.setflags(write=False)
        _FULL[key] = f
    return f


def _block_matrix(fulls: tuple, dtype) -> np.ndarray:
    """Matrix of one block of decimated outputs from a window of inputs.

    With ``P = len(fulls)`` filters of ``K`` taps (all the same length), the
    ``P * B`` columns cycle through them and column ``q`` holds its filter at
    rows ``q * 2 / P ..``: ``P = 1`` is one analysis filter (``B`` outputs at
    input steps of 2), ``P = 2`` the polyphase synthesis pair (``2 B`` outputs,
    even and odd interleaved as they are stored).  The first ``m`` columns
    need the first ``(m - 1) * 2 / P + K`` rows."""
    key = tuple(f.tobytes() for f in fulls) + (np.dtype(dtype).str,)
    m = _BLOCK_MATS.get(key)
    if m is None:
        p, k = len(fulls), len(fulls[0])
        step = 2 // p
        m = np.zeros(((p * _BLOCK - 1) * step + k, p * _BLOCK), dtype)
        for q in range(p * _BLOCK):
            m[q * step:q * step + k, q] = fulls[q % p]
        m.setflags(write=False)
        _BLOCK_MATS[key] = m
    return m


def _blocked_filter(xe: np.ndarray, start: int, fulls: tuple, out: np.ndarray) -> np.ndarray:
    """Decimated filtering along the last axis of the C-contiguous 2D float32
    ``xe`` as blocked matrix products (BLAS sgemm) into the C-contiguous
    ``out``: output column ``q`` is filter ``fulls[q % P]`` applied to the
    window of ``xe`` starting at column ``start + q * 2 / P`` (``_block_matrix``).

    Along the contiguous axis the strided-window contraction cannot vectorise
    over rows (its inner loop is the ``K`` taps); this does, at about 2x the
    multiply-adds (timings: docs/notes/awr.md).  Same sums as the
    contraction, in a different rounding order."""
    mat = _block_matrix(fulls, xe.dtype)
    step, k = 2 // len(fulls), len(fulls[0])
    cols = mat.shape[1]
    n = out.shape[1]
    full_blocks = n // cols
    _gemm_blocks(xe, start, mat, out, 0, full_blocks, cols * step, cols)
    m = n - full_blocks * cols
    if m:
        _gemm_blocks(xe, start + full_blocks * cols * step,
                     np.ascontiguousarray(mat[:(m - 1) * step + k, :m]), out, full_blocks * cols,
                     1, 0, 0)
    return out


def _blocked(x: np.ndarray, axis: int) -> bool:
    """Whether filters along ``axis`` of ``x`` run as blocked matrix products."""
    return x.dtype == np.float32 and x.ndim == 2 and axis == 1


def _sym_filter(xe: np.ndarray, axis: int, half: np.ndarray, center: int, count: int,
                out: np.ndarray | None = None) -> np.ndarray:
    """``out[i] = sum_m f[m] * xe[center + 2i - m]`` for the symmetric filter
    ``f[m] = half[|m|]``; one strided-window contraction (no copies), or for
    float32 along the last axis of a 2D array, blocked matrix products."""
    length = len(half) - 1
    full = _full_taps(half, xe.dtype)
    if _blocked(xe, axis) and length > 0:
        if out is None:
            out = np.empty((xe.shape[0], count), xe.dtype)
        return _blocked_filter(xe, center - length, (full,), out)
    st = xe.strides
    shape = xe.shape[:axis] + (count,) + xe.shape[axis + 1:] + (2 * length + 1,)
    strides = st[:axis] + (2 * st[axis],) + st[axis + 1:] + (st[axis],)
    win = _window(xe, (center - length) * st[axis], shape, strides)
    return np.einsum("...k,k->...", win, full, out=out)


def _analysis_axis(x: np.ndarray, axis: int, bank: FilterBank):
    """One level of 1D analysis along ``axis``: (scale, wavelet) coefficients."""
    n = x.shape[axis]
    if n == 1:
        shp = list(x.shape)
        shp[axis] = 0
        return x.copy(), np.zeros(shp, x.dtype)
    ns, nd = (n + 1) // 2, n // 2
    nd_ = x.ndim
    if bank.kind == "haar":
        x0 = x[_sl(axis, nd_, slice(0, n, 2))]
        x1 = x[_sl(axis, nd_, slice(1, n, 2))]
        a0, a1 = bank.lo_a
        b0, b1 = bank.hi_a
        s = np.multiply(x0, a0)
        s[_sl(axis, nd_, slice(0, nd))] += a1 * x1
        if ns > nd:  # odd length: half-sample symmetry, x[n] = x[n - 1]
            s[_sl(axis, nd_, slice(nd, ns))] += a1 * x0[_sl(axis, nd_, slice(nd, ns))]
        d = np.multiply(x0[_sl(axis, nd_, slice(0, nd))], b0)
        d += b1 * x1
        return s, d
    pad = max(len(bank.lo_a), len(bank.hi_a)) + 1
    xe = _extend(x, axis, pad)
    s = _sym_filter(xe, axis, bank.lo_a, pad, ns)
    d = _sym_filter(xe, axis, bank.hi_a, pad + 1, nd)
    return s, d


def _synthesis_axis(s: np.ndarray, d: np.ndarray, axis: int, bank: FilterBank) -> np.ndarray:
    """Inverse of ``_analysis_axis`` (or, with a squared bank, the propagation of
    coefficient variances back to samples)."""
    ns, nd = s.shape[axis], d.shape[axis]
    n = ns + nd
    if nd == 0:
        return s.copy()
    nd_ = s.ndim
    shp = list(s.shape)
    shp[axis] = n
    out = np.empty(shp, np.result_type(s, d))
    if bank.kind == "haar":
        c0, c1 = bank.lo_s
        e0, e1 = bank.hi_s
        ev = out[_sl(axis, nd_, slice(0, n, 2))]
        od = out[_sl(axis, nd_, slice(1, n, 2))]
        np.multiply(s, c0, out=ev)
        ev[_sl(axis, nd_, slice(0, nd))] += e0 * d
        np.multiply(s[_sl(axis, nd_, slice(0, nd))], c1, out=od)
        od += e1 * d
        return out
    # Interleave (s at even, d at odd samples): the whole-sample symmetric
    # extension of this sequence is the correct extension of both subbands.
    out[_sl(axis, nd_, slice(0, n, 2))] = s
    out[_sl(axis, nd_, slice(1, n, 2))] = d
    f_even, f_odd = _poly_filters(bank)
    pad = max(len(f_even), len(f_odd)) + 1
    ye = _extend(out, axis, pad)
    if _blocked(out, axis):  # out[2i] = f_even * ye[pad + 2i - .], out[2i + 1] = f_odd * ...
        return _blocked_filter(ye, pad - (len(f_even) - 1),
                               (_full_taps(f_even, ye.dtype), _full_taps(f_odd, ye.dtype)), out)
    _sym_filter(ye, axis, f_even, pad, ns, out=out[_sl(axis, nd_, slice(0, n, 2))])
    _sym_filter(ye, axis, f_odd, pad + 1, nd, out=out[_sl(axis, nd_, slice(1, n, 2))])
    return out


_POLY: dict = {}


def _poly_filters(bank: FilterBank):
    """Polyphase synthesis halves: even outputs take the low-pass at even taps and
    the high-pass at odd taps; odd outputs the reverse."""
    cached = _POLY.get(bank.name)
    if cached is not None:
        return cached
    length = max(len(bank.lo_s), len(bank.hi_s))
    lo = np.zeros(length)
    hi = np.zeros(length)
    lo[:len(bank.lo_s)] = bank.lo_s
    hi[:len(bank.hi_s)] = bank.hi_s
    m = np.arange(length)
    f_even = np.where(m % 2 == 0, lo, hi)
    f_odd = np.where(m % 2 == 1, lo, hi)
    _POLY[bank.name] = (f_even, f_odd)
    return f_even, f_odd


# ----------------------------------------------------------------------------
# 2D non-standard DWT
# ----------------------------------------------------------------------------
@dataclass
class Pyramid:
    """Coefficients of a non-standard 2D DWT.

    Attributes
    ----------
    approx : (h_L, w_L, ...) scale coefficients ``S_L`` of the coarsest level
    details : list of (W0, W1, W2); ``details[k - 1]`` are the level-k wavelet
        coefficients (shapes ``(ceil(h/2), floor(w/2))``, ``(floor(h/2),
        ceil(w/2))``, ``(floor(h/2), floor(w/2))`` of the level-(k-1) grid
        ``(h, w)``)
    axes : the two transformed axes (y, x)
    """

    approx: np.ndarray
    details: list = field(default_factory=list)
    axes: tuple = (0, 1)

    @property
    def levels(self) -> int:
        return len(self.details)

    def copy(self) -> "Pyramid":
        return Pyramid(self.approx.copy(), [tuple(b.copy() for b in d) for d in self.details],
                       self.axes)


def _norm_axes(x: np.ndarray, axes) -> tuple:
    ay, ax = (int(a) % x.ndim for a in axes)
    if ay == ax:
        raise ValueError("axes must differ")
    return ay, ax


def _analysis_level(x, bank, ay, ax):
    lo, hi = _analysis_axis(x, ax, bank)
    s, w1 = _analysis_axis(lo, ay, bank)
    w0, w2 = _analysis_axis(hi, ay, bank)
    return s, (w0, w1, w2)


def _synthesis_level(s, det, bank, ay, ax):
    w0, w1, w2 = det
    lo = _synthesis_axis(s, w1, ay, bank)
    hi = _synthesis_axis(w0, w2, ay, bank)
    return _synthesis_axis(lo, hi, ax, bank)


def _float_dtype(dtype):
    dt = np.dtype(dtype)
    if dt not in (np.float64, np.float32):
        raise ValueError(f"dtype must be float64 or float32, not {dt}")
    return dt


def dwt2(x: np.ndarray, bank="cdf97", levels: int | None = None, axes=(0, 1),
         dtype=np.float64) -> Pyramid:
    """Non-standard 2D DWT analysis (Sec. 3, Eq. 1-2, 7).

    Parameters
    ----------
    x : (H, W) or (H, W, C) array (any H, W >= 1)
    bank : filter bank name or ``FilterBank`` (paper default ``"cdf97"``)
    levels : number of levels; ``None`` = full depth (``max_levels``); larger
        values are clamped to full depth
    axes : the (y, x) axes to transform
    dtype : float64 (default) or float32, the precision of every coefficient.
        float32 suits sums without cancellation (variances: a few ulp of each
        output) and values that may err by ~1e-7 of the largest input in a
        filter's support; it overflows above ~3e38.

    Returns
    -------
    Pyramid with ``levels`` detail levels and the coarsest scale coefficients.
    """
    bank = get_bank(bank)
    x = np.asarray(x, _float_dtype(dtype))
    ay, ax = _norm_axes(x, axes)
    levels = _clamp_levels((x.shape[ay], x.shape[ax]), levels)
    details = []
    s = x
    for _ in range(levels):
        s, det = _analysis_level(s, bank, ay, ax)
        details.append(det)
    if s is x:
        s = x.copy()
    return Pyramid(s, details, (ay, ax))


def idwt2(pyr: Pyramid, bank="cdf97") -> np.ndarray:
    """Non-standard 2D DWT synthesis, the exact inverse of ``dwt2`` (same bank),
    in the precision of the coefficients (float64 if any band is)."""
    bank = get_bank(bank)
    ay, ax = pyr.axes
    s = pyr.approx
    for det in reversed(pyr.details):
        s = _synthesis_level(s, det, bank, ay, ax)
    return s.copy() if s is pyr.approx else s


def scale_coefficients(x: np.ndarray, bank="cdf97", levels: int | None = None,
                       axes=(0, 1)) -> list:
    """Scale coefficients ``S_k`` of every level ``k = 0..levels`` (Eq. 1, 4).

    Only the low-pass filters run (the paper's "we only use the low-pass portion
    of the filter bank").  ``S_0`` is ``x`` itself (the pixels).

    Returns
    -------
    list of ``levels + 1`` arrays, shapes ``level_shapes``.
    """
    bank = get_bank(bank)
    x = np.asarray(x, np.float64)
    ay, ax = _norm_axes(x, axes)
    levels = _clamp_levels((x.shape[ay], x.shape[ax]), levels)
    out = [x]
    s = x
    for _ in range(levels):
        s = _lowpass_axis(_lowpass_axis(s, ax, bank), ay, bank)
        out.append(s)
    return out


def _lowpass_axis(x: np.ndarray, axis: int, bank: FilterBank) -> np.ndarray:
    n = x.shape[axis]
    if n == 1:
        return x
    if bank.kind == "haar":
        return _analysis_axis(x, axis, bank)[0]
    ns = (n + 1) // 2
    pad = len(bank.lo_a) + 1
    xe = _extend(x, axis, pad)
    return _sym_filter(xe, axis, bank.lo_a, pad, ns)


def dwt2_variance(var: np.ndarray, bank="cdf97", levels: int | None = None,
                  lo_sum: float | None = None, hi_sum: float | None = None,
                  axes=(0, 1), dtype=np.float64) -> Pyramid:
    """Variance of every DWT coefficient from per-pixel variances (Eq. 10, App. B).

    A full DWT of ``var`` with squared filter taps: the wavelet entries are
    ``<var, (Psi^alpha_k)^2>`` (the square of Eq. 10's Delta) and ``approx`` is
    ``<var, Phi_L^2>`` (Eq. 9).  Assumes uncorrelated pixels (Eq. 14); see the
    module docstring for the bias at deeper levels and boundaries.

    Parameters
    ----------
    var : (H, W) or (H, W, C) non-negative per-pixel variances
    lo_sum, hi_sum : renormalised sums of the squared 1D filters (``None``:
        natural squares = exact one-level variance).  Sec. 4.2 uses
        ``2**-0.5`` for both.
    dtype : float64 or float32 (every tap is positive, so float32 loses only a
        few ulp relative to each output; inputs above ~3e38 overflow)
    """
    return dwt2(var, squared_bank(bank, lo_sum, hi_sum), levels, axes, dtype)


def scale_variance(var: np.ndarray, bank="cdf97", levels: int | None = None,
                   lo_sum: float | None = 1.05, axes=(0, 1)) -> list:
    """``sigma^2(S_k) ~ <sigma^2(B), Phi_k^2>`` for ``k = 0..levels`` (Eq. 9).

    DWT analysis of the per-pixel variance with the squared low-pass filter,
    renormalised to sum to ``lo_sum`` (paper: 1.05, "tends to target levels
    0 <= k <= 4"; ``None`` keeps the natural squares).  Entry 0 is ``var``.
    """
    return scale_coefficients(var, squared_bank(bank, lo_sum, None), levels, axes)


def idwt2_variance(pyr: Pyramid, bank="cdf97", lo_sum: float | None = None,
                   hi_sum: float | None = None) -> np.ndarray:
    """Per-pixel variance of a synthesis whose coefficients are uncorrelated
    with the variances in ``pyr``: the DWT synthesis with squared synthesis taps
    (the synthesis analogue of Eq. 15)."""
    return idwt2(pyr, squared_bank(bank, lo_sum, hi_sum))


@lru_cache(maxsize=128)
def _scale_function_cached(name: str, level: int):
    b = BANKS[name]
    off, taps = b.full("lo_a")  # symmetric banks: f[m] == f[-m], offsets -L..L
    phi = np.array([1.0])
    start = 0
    for j in range(level):
        step = 2 ** j
        up = np.zeros((len(taps) - 1) * step + 1)
        up[::step] = taps
        phi = np.convolve(phi, up)
        start += off * step
    return start, phi


def scale_function(bank="cdf97", level: int = 1) -> tuple[int, np.ndarray]:
    """Discrete 1D analysis scale function ``phi_k`` (Fig. 5, Eq. 12).

    ``S_k[i] = sum_u phi_k[u] * x[2**k * i + start + u]`` away from the
    boundaries; the 2D ``Phi_k`` is the outer product (separable).  It is the
    cascade ``h * (h up 2) * ... * (h up 2**(k-1))`` of the analysis low-pass.

    Returns
    -------
    start : int, offset of the first tap relative to ``2**k * i``
    phi : ((len(h) - 1) * (2**k - 1) + 1,) float64 taps (sum ``sqrt(2)**k``)
    """
    level = int(level)
    if level < 0:
        raise ValueError("level must be >= 0")
    start, phi = _scale_function_cached(get_bank(bank).name, level)
    return start, phi.copy()

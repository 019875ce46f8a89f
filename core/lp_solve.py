"""Linear-algebra kernels of LP (Moon, Iglesias-Guitian, Yoon, Mitchell 2015).

The recursive least squares of Eq. 3 grows a prediction window one pixel at a
time.  Only the models at the ring boundaries ``k(r) = (2r+1)^2`` are ever used
(Eq. 4-5 test the model of ``k(r-1)`` on ring ``r``; the optimal model is one of
``beta(k(r))``), and RLS started from ``beta(0) = beta0``, ``P(0) = delta^-1 I``
is *exactly* the regularised normal equation

    beta(k) = (delta I + X_k^T X_k)^-1 (delta beta0 + X_k^T Y_k)

(Ljung & Soederstroem 1987; Woodbury identity), so here each ring adds its
``X^T X`` and ``X^T Y`` to running sums, and one batched SPD solve over all
rings and centres gives every ``beta(k(r))`` at once.  ``tests/core/test_lp.py`` checks this
against the pixel-by-pixel recursion of Eq. 3 and against batch least squares.

Everything is vectorised over the leading "centre" axis N; the only Python
loops run over rings and over the (at most 10) matrix dimensions.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


def ring_layout(radius: int):
    """Offsets of a ``(2R+1) x (2R+1)`` window ordered ring by ring.

    Parameters
    ----------
    radius : int
        R, the half width of the filtering window (paper: 9, a 19x19 window).

    Returns
    -------
    dy, dx : (K,) int64
        Row / column offsets, K = (2R+1)^2; entry 0 is the centre (0, 0).
    ring : (K,) int64
        Chebyshev distance max(|dy|, |dx|) of each offset (the ring index r).
    starts : (R+2,) int64
        Ring r occupies ``[starts[r], starts[r+1])`` = ``[(2r-1)^2, (2r+1)^2)``
        (ring 0 is the single centre pixel), so ``starts[r+1] = k(r)``.
        The arrays are cached per radius and read-only.
    """
    return _ring_layout(int(radius))


@lru_cache(maxsize=None)
def _ring_layout(radius: int):
    side = np.arange(-radius, radius + 1)
    dy, dx = np.meshgrid(side, side, indexing="ij")
    dy, dx = dy.ravel(), dx.ravel()
    ring = np.maximum(np.abs(dy), np.abs(dx))
    order = np.lexsort((dx, dy, ring))
    starts = np.array([0] + [(2 * q + 1) ** 2 for q in range(radius + 1)], np.int64)
    out = dy[order].astype(np.int64), dx[order].astype(np.int64), ring[order].astype(np.int64), starts
    for a in out:
        a.flags.writeable = False
    return out


def spd_solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``a x = b`` for a stack of symmetric positive definite matrices.

    A Cholesky factorisation vectorised over the stack (loops run over the
    matrix dimension only, p <= 10 here), much cheaper than LAPACK's per-matrix
    call overhead for millions of 10x10 systems.  Pivots are clamped to
    ``1e-300`` so a (numerically) semi-definite matrix gives a finite answer.

    Parameters
    ----------
    a : (N, p, p) float64, SPD (here ``delta I + X^T X`` with delta > 0).
    b : (N, p, C) float64.

    Returns
    -------
    x : (N, p, C) float64.
    """
    # stack axis last: every elementary step is one vector operation over all
    # systems (copies: the solve works in place)
    at = np.moveaxis(a, 0, -1).copy()
    bt = np.moveaxis(b, 0, -1).copy()
    return np.moveaxis(_spd_solve_t(at, bt), -1, 0)


def _spd_solve_t(at: np.ndarray, bt: np.ndarray) -> np.ndarray:
    """:func:`spd_solve` with the stack axis last, in place: ``at`` (p, p, M)
    is overwritten by its Cholesky factor and ``bt`` (p, C, M) by the
    solution, which is returned."""
    return _cho_solve_t(_cholesky_t(at), bt)


def _cholesky_t(at: np.ndarray) -> np.ndarray:
    """Cholesky factors L (``a = L L^T``) of a stack ``at`` (p, p, M), in place:
    the lower triangle is overwritten (the upper one is left as it was and is
    never read by :func:`_cho_solve_t`).  Pivots are clamped to 1e-300."""
    p = at.shape[0]
    low = at
    for j in range(p):
        if j:
            s = at[j, j] - (low[j, :j] * low[j, :j]).sum(0)
        else:
            s = at[j, j]
        d = np.sqrt(np.maximum(s, 1e-300))
        inv = 1.0 / d
        low[j, j] = d
        if j + 1 < p:
            off = at[j + 1:, j]
            if j:
                off = off - (low[j + 1:, :j] * low[j, :j][None]).sum(1)
            low[j + 1:, j] = off * inv
    return low


def _cho_solve_t(low: np.ndarray, bt: np.ndarray) -> np.ndarray:
    """Solve ``L L^T x = b`` given the factors of :func:`_cholesky_t` (p, p, M);
    ``bt`` (p, C, M) is overwritten by the solution, which is returned."""
    p = low.shape[0]
    y = bt                                   # forward substitution, in place
    for i in range(p):
        acc = y[i]
        if i:
            acc = acc - (low[i, :i, None] * y[:i]).sum(0)
        y[i] = acc / low[i, i]
    x = y                                    # back substitution, in place
    for i in range(p - 1, -1, -1):
        acc = x[i]
        if i + 1 < p:
            acc = acc - (low[i + 1:, i, None] * x[i + 1:]).sum(0)
        x[i] = acc / low[i, i]
    return x


class Design:
    """The design columns ``z_i = (1, v_i T^T (x_i - x_c))`` of Eq. 1 in the
    TSVD-prefiltered features (Sec. 7), produced a block of pixels at a time so
    the whole (N, p, K) design of a chunk of centres is never stored.

    Parameters
    ----------
    transform : (N, D, p - 1) float64
        Kept columns of the feature map T (``lp.feature_transform``).
    x : (N, D, K) float64
        ``x_i - x_c`` of the window pixels (may be a view).
    valid : (N, K) float64 in {0, 1}
        v_i: 0 where the pixel's features are unusable (its z_i is (1, 0, ..., 0)).
    """

    def __init__(self, transform: np.ndarray, x: np.ndarray, valid: np.ndarray):
        self.t = np.swapaxes(transform, 1, 2)
        self.x, self.valid = x, valid
        n, _, k = x.shape
        self.shape = (n, transform.shape[2] + 1, k)

    def columns(self, lo: int, hi: int, out: np.ndarray) -> np.ndarray:
        """Write ``z_i`` of pixels lo .. hi-1 into ``out`` (N, p, hi - lo)."""
        out[:, 0] = 1.0
        np.matmul(self.t, self.x[:, :, lo:hi], out=out[:, 1:])
        out[:, 1:] *= self.valid[:, None, lo:hi]
        return out

    def predict(self, beta: np.ndarray) -> np.ndarray:
        """Eq. 1 predictions ``beta^T z_i`` of every window pixel: beta (N, C, p)
        gives (N, C, K), evaluated as ``beta_0 + v_i (beta_1.. T^T) (x_i - x_c)``
        (the feature map folded into the model first, one product per centre)."""
        out = np.matmul(np.matmul(beta[:, :, 1:], self.t), self.x)
        out *= self.valid[:, None, :]
        out += beta[:, :, :1]
        return out


def _columns(z):
    """``columns(lo, hi, out)`` of a design given as an (N, p, K) array or a :class:`Design`."""
    if isinstance(z, np.ndarray):
        def columns(lo, hi, out):
            np.copyto(out, z[:, :, lo:hi])
            return out
        return columns
    return z.columns


@dataclass
class RingFits:
    """Per-centre RLS models and accumulated prediction errors for every ring.

    beta : (R+1, N, p, C) float64
        ``beta(k(r))``, the least-squares model of the window k(r) (Eq. 3).
    xi_acc : (R+1, N, C) float64
        Accumulated prediction error ``xi_acc(k(r))`` (Eq. 4); entry 0 is the
        caller's ``xi0``, entry ``start`` the leave-one-out sum of Eq. 7 over
        k(start), entries r > start add Eq. 5's ring errors; +inf for
        ``1 <= r < start`` (windows too small to determine the model: no
        candidates of Eq. 2).
    count : (R+1, N) float64
        Number of (weight-1) pixels inside k(r): the normaliser of Eq. 4.
    gram : (R+1, N, p, p) float64 or None
        ``delta I + X^T X`` of k(r) (the inverse of RLS's ``P(k(r))``), kept
        only when asked (for a temporal extension that continues the RLS).
    start : (N,) int64
        The ring where the recursion starts (:func:`start_rings`).
    dof : (R+1, N) float64
        Effective parameter count ``tr((delta I + X^T X)^-1 X^T X)`` of k(r)
        (p for a determined least-squares fit).
    svar : (R+1, N, C) float64
        ``sum_{i in k(r)} w_i s_i``, the window sum of the subtracted variances.
    svar2 : (R+1, N, C) float64
        ``sum_{i in k(r)} w_i s_i^2`` (for the standard error of Eq. 4's sum).
    """

    beta: np.ndarray
    xi_acc: np.ndarray
    count: np.ndarray
    gram: np.ndarray | None = None
    start: np.ndarray | None = None
    dof: np.ndarray | None = None
    svar: np.ndarray | None = None
    svar2: np.ndarray | None = None


#: the error recursion starts where a window holds this many pixels per unknown
START_MARGIN = 2.0


def start_rings(count: np.ndarray, p: int, margin: float = START_MARGIN) -> np.ndarray:
    """The ring r_s >= 1 where the error recursion of Eq. 4 starts with Eq. 7.

    Sec. 7 of Moon et al. 2015 starts at k(1) = 9 pixels, but with p = d + 1
    unknowns (up to 10 here) the 9-pixel fit is under- or exactly determined,
    every hat value ``z_i^T P z_i`` is near 1 and the leave-one-out error of
    Eq. 7 explodes, and Eq. 4 adds it to every larger window.  Choice: start
    at the first ring whose window holds at least ``margin * p`` usable pixels
    (margin 2: the mean hat value ``p / count`` is then <= 1/2, so Eq. 7's
    ``1 / (1 - h)^2`` amplifies the mean residual at most ~4x; with p <= 4 the
    paper's k(1) is kept).  Where no ring reaches it (tiny images, holes) the
    largest ring R starts, provided it has more pixels than unknowns;
    otherwise ``R + 1`` (no candidate window beyond k(0)).

    count : (R+1, N) usable pixels of k(r).  Returns (N,) int64.
    """
    r1 = count.shape[0]
    if r1 < 2:
        return np.full(count.shape[1], r1, np.int64)
    ok = count[1:] >= margin * p
    first = 1 + np.argmax(ok, axis=0)
    determined = count[-1] > p
    return np.where(ok.any(axis=0), first, np.where(determined, r1 - 1, r1)).astype(np.int64)



def ring_fits(z: np.ndarray, y: np.ndarray, w: np.ndarray, s: np.ndarray,
              beta0: np.ndarray, xi0: np.ndarray, radius: int, delta: float = 1e-3,
              keep_gram: bool = False, work: dict | None = None,
              margin: float = START_MARGIN) -> RingFits:
    """Recursive least squares (Eq. 3) and recursive prediction error (Eq. 4, 5, 7)
    of Moon et al. 2015, ring by ring, for N centres at once.

    Parameters
    ----------
    z : (N, p, K) float64 or :class:`Design`
        Design rows ``z_i = (1, (x_i - x_c)^T)`` (as columns) of the
        K = (2R+1)^2 window pixels in ``ring_layout`` order (pixel 0 is the
        centre).  Must be finite.  A :class:`Design` is evaluated one ring at
        a time and never stored whole.
    y : (N, C, K) float64
        Observations (pixel means), one row per colour channel.  Finite.
    w : (N, K) float64 in {0, 1}
        1 for pixels that enter the fit and the error sums; 0 for missing ones
        (outside the image, no samples, non-finite input).
    s : (N, C, K) float64
        Amount subtracted from every squared test residual of Eq. 5 and Eq. 7
        (the test pixel's variance of the mean, see ``lp.Params``); zeros give
        the literal equations.  Finite.
    beta0 : (N, C) float64
        Intercept of the initial model ``beta(0) = (y_1, 0, ..., 0)`` (Sec. 7),
        y_1 the centre pixel.
    xi0 : (N, C) float64
        ``xi_acc(k(0))``: the variance of the mean at the centre (Sec. 7);
        may be +inf.
    radius : int
        R; rings r = 0 .. R.
    delta : float
        Sec. 7's delta: ``P(0) = delta^-1 I`` (paper: 0.001).
    keep_gram : bool
        Also return ``delta I + X^T X`` per ring.
    work : dict or None
        Optional scratch: ``m`` and ``mw``, flat and contiguous with at least
        ``N (p + C) 8R`` entries each (one ring of ``[z y']`` and its weighted
        copy), ``mom`` (R+1, N, p + C, p + C).

    Returns
    -------
    margin : float
        Usable pixels per unknown at which the recursion starts (:func:`start_rings`).

    RingFits
        ``beta(k(r))`` solves ``(delta I + X^T X) beta = delta beta(0) + X^T Y``
        over the pixels of k(r), which is what the recursion of Eq. 3 reaches
        after the last pixel of ring r; at the start ring r_s
        (:func:`start_rings`; the paper's r_s = 1) ``xi_acc(k(r_s))`` is Eq. 7,
        ``sum_i w_i [((beta(k(r_s))^T z_i - y_i) / (1 - z_i^T P(k(r_s)) z_i))^2 - s_i]``
        over the pixels of k(r_s); for r > r_s
        ``xi_acc(k(r)) = xi_acc(k(r-1)) + sum_{i in ring r} w_i [(beta(k(r-1))^T z_i - y_i)^2 - s_i]``
        (Eq. 4-5); +inf for ``1 <= r < r_s``.

    Notes
    -----
    Observations are centred on ``beta0`` (``y' = y - y_c``: the prior becomes
    0 and ``beta(0)`` reproduces ``y_c`` exactly).  One matrix product per ring
    gives the ring's moments ``[z y'] W [z y']^T`` (``[z y']`` is built one
    ring at a time, so the scratch is 8R pixels wide, not K); the normal equations of
    all rings are their cumulative sums and are solved in one batch
    (:func:`_ring_models`); Eq. 7 is :func:`_loo_error` and Eq. 5's ring sums,
    evaluated from the same ring moments, :func:`_ring_errors`.
    """
    n, p, k = z.shape
    c = y.shape[1]
    radius = int(radius)
    starts = ring_layout(radius)[3]
    columns = _columns(z)
    mom = _ring_moments(columns, y, w, beta0, starts, p, work or {})
    beta, count, gram, low = _ring_models(mom, p, delta, keep_gram)
    start = start_rings(count, p, margin)
    linv = _inverse_factor(low)                                         # L^-1 of every k(r)
    dof = p - delta * (linv * linv).sum(axis=(0, 1)).reshape(radius + 1, n)
    svar = np.empty((radius + 1, n, c))                                 # ring sums, then cumulated
    svar2 = np.empty((radius + 1, n, c))
    for r in range(radius + 1):
        sr, wr = s[:, :, starts[r]:starts[r + 1]], w[:, None, starts[r]:starts[r + 1]]
        np.einsum("nck,nck->nc", sr, np.broadcast_to(wr, sr.shape), out=svar[r])
        np.einsum("nck,nck,nck->nc", sr, sr, np.broadcast_to(wr, sr.shape), out=svar2[r])
    np.cumsum(svar, axis=0, out=svar)
    np.cumsum(svar2, axis=0, out=svar2)
    xi_acc = np.full((radius + 1, n, c), np.inf)
    xi_acc[0] = xi0
    if radius >= 1:
        live = start <= radius
        rs = np.minimum(start, radius)
        idx = np.arange(n)
        # P(k(r_s)) z_i uses the Cholesky factors of k(r_s) from the solve above
        loo = _loo_error(columns, beta[rs, idx], low[:, :, rs * n + idx], y, w, s, beta0, starts[rs + 1])
        # Eq. 5's ring sums, cumulated over rings 2..r (0 for r <= 1)
        acc = np.zeros((radius + 1, n, c))
        if radius >= 2:
            np.cumsum(_ring_errors(mom, beta[1:-1], s, w, starts, p), axis=0, out=acc[2:])
        rings = np.arange(radius + 1)[:, None]
        use = ((rings >= rs[None, :]) & (rings >= 1) & live[None, :])[1:, :, None]
        xi_acc[1:] = np.where(use, (loo - acc[rs, idx])[None] + acc[1:], np.inf)
    beta[:, :, 0, :] += beta0
    return RingFits(beta, xi_acc, count, gram, start, dof, svar, svar2)


def _inverse_factor(low: np.ndarray) -> np.ndarray:
    """``L^-1`` of a stack of Cholesky factors (p, p, M) (:func:`_cholesky_t`
    layout) by forward substitution of the identity: ``tr(A^-1) = ||L^-1||_F^2``
    and ``A^-1 = L^-T L^-1``.  Returns (p, p, M), row i of L^-1 in ``[i]``."""
    p, _, m = low.shape
    inv = np.zeros((p, p, m))
    for i in range(p):
        row = np.zeros((p, m))
        row[i] = 1.0
        if i:
            row -= (low[i, :i, None, :] * inv[:i]).sum(0)
        inv[i] = row / low[i, i]
    return inv


def _ring_moments(columns, y, w, beta0, starts, p, work: dict) -> np.ndarray:
    """Moments ``[z y'] W [z y']^T`` of every ring (R+1, N, p + C, p + C), one
    batched matrix product per ring, with ``y' = y - beta0``; ``[z y']`` is
    built one ring at a time into the scratch ``work['m']`` / ``work['mw']``
    (and the result into ``work['mom']``) when given."""
    n, c = y.shape[:2]
    radius = len(starts) - 2
    q = p + c
    wide = int(np.diff(starts).max())                                   # the widest ring (8R)
    m = work.get("m")
    m = np.empty(n * q * wide) if m is None else m
    mw = work.get("mw")
    mw = np.empty(n * q * wide) if mw is None else mw
    mom = work.get("mom")
    mom = np.empty((radius + 1, n, q, q)) if mom is None else mom
    for r in range(radius + 1):
        lo, hi = starts[r], starts[r + 1]
        mr = m[:n * q * (hi - lo)].reshape(n, q, hi - lo)
        columns(lo, hi, mr[:, :p])
        np.subtract(y[:, :, lo:hi], beta0[:, :, None], out=mr[:, p:])
        mwr = mw[:n * q * (hi - lo)].reshape(n, q, hi - lo)
        np.multiply(mr, w[:, None, lo:hi], out=mwr)
        np.matmul(mwr, np.swapaxes(mr, 1, 2), out=mom[r])
    return mom


def _ring_models(mom: np.ndarray, p: int, delta: float, keep_gram: bool):
    """Eq. 3 at every ring boundary: ``beta(k(r))`` (R+1, N, p, C) for the
    centred observations, by one batched Cholesky solve of the regularised
    normal equations ``(delta I + X^T X) beta = X^T Y'`` of k(r), the running
    sums of the ring moments (accumulated straight into the stack-last layout
    of the in-place solve).

    Returns beta, count (R+1, N) the weight sum of k(r), gram (R+1, N, p, p)
    ``delta I + X^T X`` or None, and the Cholesky factors (p, p, (R+1) N).
    """
    r1, n, q = mom.shape[:3]
    c = q - p
    at = np.empty((p, p, r1, n))
    np.cumsum(np.moveaxis(mom[:, :, :p, :p], (0, 1), (2, 3)), axis=2, out=at)
    bt = np.empty((p, c, r1, n))
    np.cumsum(np.moveaxis(mom[:, :, :p, p:], (0, 1), (2, 3)), axis=2, out=bt)
    count = at[0, 0].copy()                                             # (R+1, N)
    for j in range(p):
        at[j, j] += delta
    gram = np.ascontiguousarray(np.moveaxis(at, (2, 3), (0, 1))) if keep_gram else None
    low = _cholesky_t(at.reshape(p, p, -1))                             # (p, p, (R+1) N)
    beta = np.moveaxis(_cho_solve_t(low, bt.reshape(p, c, -1)), -1, 0).reshape(r1, n, p, c)
    return beta, count, gram, low


def _loo_error(columns, beta1: np.ndarray, low1: np.ndarray, y: np.ndarray, w: np.ndarray,
               s: np.ndarray, beta0: np.ndarray, size=9) -> np.ndarray:
    """Eq. 7 of Moon et al. 2015: ``xi_acc(k(r_s))``, the closed-form
    leave-one-out error (Allen 1974) over the pixels of the start window
    k(r_s) (the paper's k(1), 9 pixels),
    ``sum_i w_i [((beta(k(r_s))^T z_i - y_i) / (1 - z_i^T P(k(r_s)) z_i))^2 - s_i]``.
    With P = (delta I + X^T X)^-1 this is the exact leave-one-out residual of
    the regularised fit (the ridge form of Allen's identity).

    columns : ``columns(lo, hi, out)`` of the design (see :class:`Design`).
    beta1 : (N, p, C) model of k(r_s) for the centred observations ``y - beta0``.
    low1 : (p, p, N) Cholesky factors of ``P(k(r_s))^-1 = delta I + X^T X``
        (:func:`_cholesky_t` layout).
    y, w, s, beta0 : as in :func:`ring_fits`.
    size : int or (N,) int, the pixel count ``(2 r_s + 1)^2`` of each centre's
        start window (a prefix of the ring-ordered pixels).  Returns (N, C).
    """
    n, p = beta1.shape[:2]
    size = np.broadcast_to(np.asarray(size, np.int64), (n,))
    kmax = int(size.max()) if n else 9
    zk = columns(0, kmax, np.empty((n, p, kmax)))
    pz = _cho_solve_t(low1, np.moveaxis(zk, 0, -1).copy())             # P(k(r_s)) z_i
    pz = np.moveaxis(pz, -1, 0)
    h = (zk * pz).sum(axis=1)                                           # (N, kmax)
    res = np.matmul(np.swapaxes(beta1, 1, 2), zk) - (y[:, :, :kmax] - beta0[:, :, None])
    res /= np.maximum(1.0 - h, 1e-12)[:, None, :]
    res *= res
    res -= s[:, :, :kmax]
    inside = w[:, :kmax] * (np.arange(kmax)[None, :] < size[:, None])
    res *= inside[:, None, :]
    return res.sum(axis=2)


def _ring_errors(mom: np.ndarray, beta_prev: np.ndarray, s: np.ndarray, w: np.ndarray,
                 starts: np.ndarray, p: int) -> np.ndarray:
    """Eq. 5 of Moon et al. 2015 for rings r = 2 .. R: the model of k(r-1)
    (training set) tested on the 8r pixels of ring r (test set),
    ``sum_{i in ring r} w_i [(beta(k(r-1))^T z_i - y_i)^2 - s_i]``.

    Evaluated from the ring moments ``mom`` (:func:`_ring_moments`) as
    ``beta^T A beta - 2 beta^T b + y'^T y'`` (clamped at 0 before the
    variance is subtracted, against rounding), so no second pass over the
    pixels is needed.  ``beta_prev`` (R-1, N, p, C): ``beta(k(r-1))`` for the
    centred observations.  Returns (R-1, N, C); Eq. 4 accumulates them.
    """
    quad = (np.matmul(mom[2:, :, :p, :p], beta_prev) * beta_prev).sum(axis=2)
    quad -= 2.0 * (mom[2:, :, :p, p:] * beta_prev).sum(axis=2)
    quad += np.diagonal(mom[2:, :, p:, p:], axis1=2, axis2=3)
    np.maximum(quad, 0.0, out=quad)
    # sum_{i in ring} w_i s_i
    ws_ring = np.add.reduceat(s[:, :, starts[2]:] * w[:, None, starts[2]:],
                              starts[2:-1] - starts[2], axis=2)         # (N, C, R-1)
    quad -= np.moveaxis(ws_ring, 2, 0)
    return quad

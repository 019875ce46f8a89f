"""LP's temporal extension (Moon, Iglesias-Guitian, Yoon, Mitchell 2015, Sec. 6, Eq. 6).

What and why: in an animation the static reconstruction (LP, Sec. 4-5) of
frame t, ``y(t)``, still carries noise that the neighbouring frames could
average out.  Every pixel i therefore keeps a linear model in time,
``y_i(t) ~ beta_i^T z_i(t)`` with ``z = (1, t)``, updated by lambda-weighted
recursive least squares (Eq. 6):

    G_i(t)    = P_i(t-1) z_i(t) / (lambda + z_i(t)^T P_i(t-1) z_i(t))
    P_i(t)    = lambda^-1 (P_i(t-1) - G_i(t) z_i(t)^T P_i(t-1))
    beta_i(t) = beta_i(t-1) + G_i(t) (y_i(t) - beta_i(t-1)^T z_i(t))

which minimises ``sum_j lambda^(t-j) (beta^T z(j) - y(j))^2`` (plus the
initial condition's ``lambda^t delta |beta - beta(0)|^2``, which is what makes
the recursion exact: :func:`closed_form` is that weighted least squares and
the tests compare the two).  The output is ``beta_i(t)^T z_i(t)``.  Before the
update, each pixel takes the model (beta, P) of the pixel o of frame t-1 in a
search window that maximises ``(|W_o(t-1) - W_i(t)|^2 |y_i(t) - beta_o(t-1)^T
z_i(t)|^2)^-1`` (W: world position of the primary hit), i.e. minimises the
product.  Initialisation as for the static models (Sec. 7):
``beta(0) = (y_i, 0)``, ``P(0) = I / delta``.

Call :func:`step` once per frame, in order, with the previous frame's state.
It runs, per chunk of pixels: :func:`_frame_inputs` (y, its error, W, the
background mask), :func:`previous_models` and :func:`search_origin` (where a
pixel's model may come from, following the backward coordinates),
:func:`best_previous` (the search above, with the position gate),
:func:`carry_models` (Eq. 6 via :func:`rls_update`, the resets
:func:`residual_reset` and :func:`sample_reset`, the error estimate),
:func:`new_models` (the initialisation), then over the whole frame
:func:`safe_choice` (the output never expected to be worse than y(t)) and
:func:`_finish` (the output assembly).

Choices where the paper is silent (each tested)
-----------------------------------------------
* **Time variable.**  ``t`` counts frames from the model's birth (``t = 1`` in
  the frame a model is initialised, as frame 1 of the paper's sequence), and a
  carried model keeps its own count.  A model born late in a shot would
  otherwise start with ``z = (1, 400)``, where ``P(0) = I/delta`` pins its slope
  to ~0 for dozens of frames.  Frame numbers that skip (``--frames`` with a
  step) advance ``t`` by the difference; lambda weights once per update.
* **Search window.**  ``search_radius`` (default 3, a 7x7 window) around the
  pixel itself, or around ``center`` (e.g. ``reproject.backward_coordinates``,
  the pixel's first hit projected into the previous camera) so camera motion
  larger than the window is followed.  Candidates are visited ring by ring
  from the centre; ties go to the smaller prediction error, then the nearer
  candidate.
* **Gates.**  The paper always carries the best candidate.  A model from an
  unrelated surface (a camera cut, a disocclusion) would then smear for
  ~1 / (1 - lambda) = 50 frames, so (a) candidates must lie within
  ``position_tolerance * depth_i`` of ``W_i`` (0 turns the gate off; it needs
  the depth pass) and be background exactly when pixel i is
  (``buffers.is_background``); (b) the chosen model is dropped when
  its prediction misses by more than ``reset_sigma`` standard deviations:
  ``mean_c e_c^2 > reset_sigma^2 ((sigma_i^2 + (0.01 y)^2) (1 + z^T P z /
  lambda) + v)``, ``v`` the model's own noise variance (below), so a fresh
  model (large ``P``) is never dropped for learning its slope, and a sudden
  illumination change (a moving shadow) restarts the model instead of being
  blurred in.  ``reset_sigma = 0`` turns it off; (c) the chosen model is
  dropped when its prediction fails a chi-square test against the frame's own
  samples (:func:`sample_reset`): ``sum_c (mean_c - pred_c)^2 / (V_c + (sigma^2
  + (0.01 pred_c)^2) (1 + z^T P z / lambda) + v) > sample_gate`` (``V`` the
  calibrated variance of the pixel mean, default 16.27 = the 0.999 quantile of
  chi-square with 3 degrees of freedom).  The samples are independent of the
  model and unfiltered, so a model that lags a moving highlight fails even where
  y(t), spatially filtered, partly agrees with it.  ``sample_gate = 0`` turns
  it off.  Without any usable candidate the pixel starts a new model (paper
  initialisation).
* **Never worse than the frame alone** (``safe_choice``, :func:`safe_choice`).
  Gates that only catch significant misses still let a carried model with a
  bias of one or two standard deviations through, and its output
  ``(1 - g) pred + g y`` is then worse than y(t) (a model whose prediction
  misses by k sigma has ``(1 - g)^2 k^2 sigma^2`` of squared bias against the
  ``sigma^2`` of y).  So the output of each carried pixel is y(t) (with its
  error) wherever the temporal error estimate, with this frame's excess
  residuals (against y and against the samples, averaged over a
  ``(2 bias_radius + 1)^2`` window) as the bias, is not below the window mean of
  ``sigma^2``.  The models are kept either way: only the output changes.
* **Error estimate** (the paper gives none).  With ``sigma_j^2`` the static
  estimate's error at frame j (LP's ``xi``; the variance of the mean with
  ``spatial = False``), treated as independent between frames, the covariance
  ``C = Var(beta)`` follows ``C(t) = A C(t-1) A^T + sigma_t^2 G G^T``,
  ``A = I - G z^T`` (``C = sigma^2 e_0 e_0^T`` for a new model, which is
  ``(y, 0)`` exactly).  The output ``(1 - g) beta(t-1)^T z + g y(t)``
  (``g = z^T G``) has variance ``z^T C(t) z``.  The carried prediction's
  squared bias is estimated from the a-priori residuals, whose expectation is
  ``b^2 + sigma_t^2 + v`` (``v = z^T C(t-1) z``): ``b^2 = max(0, B)`` with
  ``B`` the lambda-weighted mean over the model's life of
  ``mean_c(e_c^2) - sigma_t^2 - v`` (one frame's residual alone is too noisy
  to clamp at 0); it enters as ``(1 - g)^2 b^2``.  Averaged over RGB.
  The variance part is optimistic in a still scene, where LP's own bias
  repeats from frame to frame.
* **Missing data.**  A pixel with a non-finite ``y`` keeps its carried model
  unchanged and outputs its prediction (error ``v`` + the frame's largest
  error); a pixel with an unknown (non-finite) position outputs its ``y``
  unfiltered and keeps no model (nothing could find it again); with no model
  and no ``y`` the output is 0 with the frame's largest error.  The
  Position pass itself is required (``ValueError`` otherwise).

Measurements and design notes: docs/notes/temporal.md
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .buffers import FAR_DEPTH, Buffers, is_background
from .lp_solve import ring_layout
from .method import MethodResult, param, params_from_dict

PASSES = ("position", "depth")

#: relative floor of the residual gate's noise level (1 % of the value)
REL_FLOOR = 0.01

#: the safe choice counts this frame's pooled excess residual as bias only beyond
#: BIAS_Z standard errors of its noise (``sqrt(2 / (3 N))`` times the pooled noise
#: level for N pixels of 3 channels): clamping the noisy pooled mean at 0 alone
#: reads noise as bias in still scenes (docs/notes/temporal.md)
BIAS_Z = 1.0

#: counters of ``TemporalResult.info`` (fractions of the frame's pixels)
COUNTS = ("carried", "new", "reset_position", "reset_residual", "reset_samples", "fallback")


@dataclass
class Params:
    """Temporal extension parameters (LP paper Sec. 6; defaults from the paper where it gives one)."""

    lam: float = param(
        0.98, "forgetting factor lambda of Eq. 6 (paper: 0.98): weight of frame t-j is lambda^j; "
        "closer to 1 averages more frames (less noise, more lag on changes)", 0.5, 1.0, label="Forgetting Factor")
    delta: float = param(
        1e-3, "RLS initial confidence delta, P(0) = I/delta (paper Sec. 7: 0.001); larger keeps "
        "new models near (y, 0) longer", 1e-9, 1.0, label="Initial Confidence")
    search_radius: int = param(
        3, "half width of the window searched for the best previous model (paper: 'a search "
        "window', no size); larger follows faster motion, costs (2r+1)^2 tests per pixel", 0, 16, label="Search Radius")
    position_tolerance: float = param(
        0.05, "carried models must come from within this fraction of the pixel's depth of its "
        "world position (0 = no gate, the literal paper); smaller restarts more models", 0.0, 10.0, label="Position Tolerance")
    reset_sigma: float = param(
        4.0, "restart a model whose prediction misses by more than this many standard "
        "deviations (sudden lighting changes); 0 = never (the literal paper)", 0.0, 100.0, label="Reset Threshold")
    sample_gate: float = param(
        16.27, "restart a carried model whose prediction of this frame's pixel mean fails a chi-square "
        "test against the new samples: sum over RGB of (mean - prediction)^2 / (calibrated variance of the "
        "mean + the prediction's own error) above this value (16.27: p = 0.001 with 3 degrees of freedom); "
        "0 = off", 0.0, 1000.0, label="Sample Gate")
    safe_choice: bool = param(
        True, "output the frame's own static estimate wherever the temporal estimate's error "
        "(including this frame's residual bias) is not below it, so no pixel is expected to get worse", label="Never Worse")
    bias_radius: int = param(
        1, "half width of the window over which this frame's excess prediction residuals are averaged "
        "into the bias of the safe choice (1: 3x3); 0 = the pixel's own residual only", 0, 8, label="Bias Window")
    spatial: bool = param(
        True, "filter each frame with static LP first and feed its output to Eq. 6 (paper); off "
        "feeds the raw pixel means (faster, noisier)", label="Spatial Filter First")
    chunk: int = param(
        65536, "pixels processed per vectorised batch (memory ~ 0.5 KB per pixel in flight)", 256, 4194304, label="Batch Size")


@dataclass
class TemporalState:
    """Per-pixel temporal models after frame ``frame`` (arrays (H, W, ...)).

    beta : (H, W, 3, 2) model coefficients per RGB channel.
    P : (H, W, 2, 2) RLS matrix (shared by the channels: it depends on z only).
    C : (H, W, 2, 2) noise covariance of beta per unit of the frame's error
        (see the module docstring; shared by the channels).
    age : (H, W) int64 model time t of the last update (1 = born then); 0 = no model.
    bias_num, bias_den : (H, W) lambda-weighted sums of the excess squared
        residual and of the weights (the bias estimate B = num / den).
    position : (H, W, 3) world position W(t) the models belong to.
    background : (H, W) bool, no surface hit.
    """

    frame: int
    beta: np.ndarray
    P: np.ndarray
    C: np.ndarray
    age: np.ndarray
    position: np.ndarray
    background: np.ndarray
    bias_num: np.ndarray | None = None
    bias_den: np.ndarray | None = None

    def __post_init__(self):
        if self.bias_num is None:
            self.bias_num = np.zeros(self.age.shape)
        if self.bias_den is None:
            self.bias_den = np.zeros(self.age.shape)

    @property
    def shape(self):
        return self.age.shape


@dataclass
class TemporalResult:
    """image (H, W, 3), error (H, W) estimated squared error (absolute, RGB mean),
    state for the next frame, source (H, W) int64 flat index of the previous
    pixel whose model was carried (-1: new model), info (scalars)."""

    image: np.ndarray
    error: np.ndarray
    state: TemporalState
    source: np.ndarray
    info: dict = field(default_factory=dict)

    def method_result(self) -> MethodResult:
        return MethodResult(self.image, self.error, dict(self.info))


def _params(params) -> Params:
    if params is None:
        return Params()
    if isinstance(params, Params):
        return params
    return params_from_dict(Params, params)


# ----------------------------------------------------------------------------- RLS
def rls_update(beta, P, C, z, y, sigma2, lam):
    """One step of Eq. 6 for N models at once (and the covariance of the module docstring).

    beta (N, 3, 2), P (N, 2, 2), C (N, 2, 2), z (N, 2), y (N, 3), sigma2 (N,).
    Returns beta, P, C, prior prediction (N, 3), gain g = z^T G (N,), v = z^T C(t-1) z (N,).
    """
    pz = np.einsum("nij,nj->ni", P, z)
    s = np.einsum("ni,ni->n", z, pz)
    denom = lam + s
    gain = pz / denom[:, None]                                     # G (N, 2)
    pred = np.einsum("nci,ni->nc", beta, z)
    err = y - pred
    beta = beta + err[:, :, None] * gain[:, None, :]
    P = (P - gain[:, :, None] * pz[:, None, :]) / lam
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    v = np.einsum("ni,nij,nj->n", z, C, z)
    a = np.eye(2)[None] - gain[:, :, None] * z[:, None, :]
    C = np.einsum("nij,njk,nlk->nil", a, C, a) + sigma2[:, None, None] * gain[:, :, None] * gain[:, None, :]
    g = np.einsum("ni,ni->n", z, gain)
    return beta, P, C, pred, g, v


def new_models(y, sigma2, delta, lam):
    """Models born at this frame: beta(0) = (y, 0), P(0) = I/delta (Sec. 7), then
    Eq. 6 at t = 1 (its residual is 0, so beta stays (y, 0)).  Returns beta, P, C."""
    n = y.shape[0]
    beta = np.zeros((n, 3, 2))
    beta[:, :, 0] = y
    p0 = np.eye(2) / delta
    z = np.ones(2)                                               # z(1) = (1, 1)
    pz = p0 @ z
    gain = pz / (lam + z @ pz)
    P = np.broadcast_to((p0 - np.outer(gain, pz)) / lam, (n, 2, 2)).copy()
    C = np.zeros((n, 2, 2))
    C[:, 0, 0] = sigma2
    return beta, P, C


def closed_form(ys, lam: float, delta: float):
    """Weighted least squares that Eq. 6 solves exactly, for checking.

    ys : (T, ...) observations of frames t = 1..T of one model.
    Minimises ``sum_j lam^(T-j) (beta^T (1, j) - y_j)^2 + lam^T delta |beta - (y_1, 0)|^2``;
    returns beta (..., 2).
    """
    ys = np.asarray(ys, np.float64)
    t_n = ys.shape[0]
    z = np.stack([np.ones(t_n), np.arange(1, t_n + 1, dtype=np.float64)], 1)
    wts = lam ** (t_n - np.arange(1, t_n + 1, dtype=np.float64))
    a = lam ** t_n * delta * np.eye(2) + (z * wts[:, None]).T @ z
    b0 = np.zeros(ys.shape[1:] + (2,))
    b0[..., 0] = ys[0]
    rhs = lam ** t_n * delta * b0 + np.einsum("t,ti,t...->...i", wts, z, ys)
    return np.linalg.solve(a, rhs[..., None])[..., 0] if rhs.ndim > 1 else np.linalg.solve(a, rhs)


# ----------------------------------------------------------------------------- inputs
class FrameInputs(NamedTuple):
    """One frame's data for Eq. 6, cleaned: arrays (H, W, ...) or flattened (H*W, ...).

    y : (..., 3) static estimate y(t) (0 where not ``y_ok``); s2 : (...) its
    squared error sigma^2 (non-finite or negative -> ``top``); y_ok : bool, y
    finite and the pixel sampled; position : (..., 3) W(t) (0 where not
    ``pos_ok``); pos_ok : bool, W finite; depth : (...) finite surface depth
    (NaN elsewhere) or None without the depth pass; background : bool, no
    surface hit (and W known); top : float, the frame's largest finite error;
    mean : (..., 3) the pixel's sample mean and mean_var : (..., 3) its calibrated
    variance (``Buffers.calibrated_variance``; +inf where unknown), for the
    sample gate; None (no gate) when not given.
    """

    y: np.ndarray
    s2: np.ndarray
    y_ok: np.ndarray
    position: np.ndarray
    pos_ok: np.ndarray
    depth: np.ndarray | None
    background: np.ndarray
    top: float
    mean: np.ndarray | None = None
    mean_var: np.ndarray | None = None

    def flat(self) -> "FrameInputs":
        """The same arrays as (H*W, ...) views."""
        opt = lambda a, *shape: None if a is None else a.reshape(-1, *shape)
        return FrameInputs(self.y.reshape(-1, 3), self.s2.reshape(-1), self.y_ok.reshape(-1),
                           self.position.reshape(-1, 3), self.pos_ok.reshape(-1), opt(self.depth),
                           self.background.reshape(-1), self.top, opt(self.mean, 3), opt(self.mean_var, 3))

    def rows(self, idx) -> "FrameInputs":
        """Rows ``idx`` of the flattened inputs (one chunk)."""
        opt = lambda a: None if a is None else a[idx]
        return FrameInputs(self.y[idx], self.s2[idx], self.y_ok[idx], self.position[idx],
                           self.pos_ok[idx], opt(self.depth), self.background[idx], self.top,
                           opt(self.mean), opt(self.mean_var))


def _frame_inputs(buf: Buffers, params: Params, static, lp_params) -> FrameInputs:
    """The frame's y(t) and sigma^2(t) (Sec. 6: the static reconstruction's output
    and error, or the raw means and their variance with ``spatial = False``), world
    positions W(t) and the background mask, as :class:`FrameInputs` (H, W, ...)."""
    if "position" not in buf.features:
        raise ValueError("LP temporal needs the Position pass (world positions to carry models)")
    if static is not None:
        y = np.asarray(static.image, np.float64)
        s2 = np.asarray(static.error, np.float64)
    elif params.spatial:
        from . import lp
        res = lp.reconstruct(buf, lp_params)
        y, s2 = res.image, res.error
    else:
        y = np.asarray(buf.color.mean, np.float64)
        with np.errstate(invalid="ignore"):
            s2 = buf.variance_of_mean().mean(axis=-1)
    h, w = buf.shape
    if y.shape != (h, w, 3) or s2.shape != (h, w):
        raise ValueError(f"static result has shapes {y.shape}, {s2.shape}; the frame is {(h, w)}")
    y_ok = np.all(np.isfinite(y), axis=-1) & (buf.n > 0)
    fin = np.isfinite(s2) & (s2 >= 0)
    top = float(s2[fin].max()) if fin.any() else 0.0
    s2 = np.where(fin, s2, top)
    pos = buf.features["position"].mean
    pos_ok = np.all(np.isfinite(pos), axis=-1)
    depth = buf.features["depth"].mean[..., 0] if "depth" in buf.features else None
    bg = is_background(pos, depth)
    if depth is not None:
        depth = np.where(np.isfinite(depth) & (depth > 0) & (depth < FAR_DEPTH), depth, np.nan)
    mean = mean_var = None
    if params.sample_gate > 0 or params.safe_choice:
        mean = np.asarray(buf.color.mean, np.float64)
        mean_var = np.asarray(buf.calibrated_variance(), np.float64)
        fin = np.isfinite(mean)
        mean = np.where(fin, mean, 0.0)
        mean_var = np.where(fin & ~np.isnan(mean_var), mean_var, np.inf)   # +inf: no test there
    return FrameInputs(np.where(y_ok[..., None], y, 0.0), s2, y_ok, np.where(pos_ok[..., None], pos, 0.0),
                       pos_ok, depth, bg & pos_ok, top, mean, mean_var)


# ----------------------------------------------------------------------------- carrying models
class PreviousModels(NamedTuple):
    """Frame t-1's models flattened to (Hp*Wp, ...) rows, for the search and Eq. 6.

    shape : (Hp, Wp); beta (N, 3, 2), P (N, 2, 2), C (N, 2, 2), age (N,),
    bias_num, bias_den (N,): the state's arrays; dt : int, frames since then;
    packed : (N, 11) float32 ``[W (3) | beta_c0 (3) | beta_c1 (3) | age | class]``
    (class 0: no model, 1: surface, 2: background), the search's one gather;
    dy, dx : (K,) window offsets ring by ring (:func:`lp_solve.ring_layout`).
    """

    shape: tuple
    beta: np.ndarray
    P: np.ndarray
    C: np.ndarray
    age: np.ndarray
    bias_num: np.ndarray
    bias_den: np.ndarray
    dt: int
    packed: np.ndarray
    dy: np.ndarray
    dx: np.ndarray


def previous_models(state: TemporalState | None, frame: int, shape, has_center: bool,
                    search_radius: int):
    """The previous frame's models if they can be carried into frame ``frame`` of ``shape`` (H, W).

    They can when the state is older than the frame and either the resolution is
    unchanged or a centre map says where each pixel was in the previous frame
    (without one a resized frame starts fresh).  Returns (:class:`PreviousModels`
    or None, resized: bool, True when that refusal was for the resolution).
    """
    usable = state is not None and int(state.frame) < frame
    resized = state is not None and not has_center and state.shape != tuple(shape)
    if not usable or resized:
        return None, resized
    hp, wp = state.shape
    beta = state.beta.reshape(-1, 3, 2)
    age = state.age.reshape(-1)
    packed = np.empty((hp * wp, 11), np.float32)   # search only; updates use float64
    packed[:, 0:3] = state.position.reshape(-1, 3)
    packed[:, 3:6] = beta[:, :, 0]
    packed[:, 6:9] = beta[:, :, 1]
    packed[:, 9] = age
    packed[:, 10] = np.where(age > 0, np.where(state.background.reshape(-1), 2.0, 1.0), 0.0)
    dy, dx, _, _ = ring_layout(int(search_radius))
    return PreviousModels((hp, wp), beta, state.P.reshape(-1, 2, 2), state.C.reshape(-1, 2, 2), age,
                          state.bias_num.reshape(-1), state.bias_den.reshape(-1),
                          frame - int(state.frame), packed, dy, dx), False


def _center_rows(center, shape):
    """``center`` (H, W, 2) as (H*W, 2) float64 rows, or None; ValueError when its size is not the frame's."""
    if center is None:
        return None
    cen = np.asarray(center, np.float64).reshape(-1, 2)
    if cen.shape[0] != shape[0] * shape[1]:
        raise ValueError(f"center has shape {np.shape(center)}, the frame is {tuple(shape)}")
    return cen


def search_origin(idx, w: int, cen, same_shape: bool):
    """Centre (row, col) in frame t-1 of the search window of pixels ``idx`` (flat, frame width ``w``).

    The floor of the backward coordinates ``cen`` (m, 2) where they are finite;
    elsewhere, and with ``cen`` None, the pixel's own position when the
    resolution is unchanged, else nowhere (-10^9: no candidate).  Returns br, bc (m,) int64.
    """
    if cen is None:
        return idx // w, idx % w
    c = cen[idx]
    okc = np.all(np.isfinite(c), axis=1)
    br = np.where(okc, np.floor(np.where(okc, c[:, 0], 0.0)), -10 ** 9).astype(np.int64)
    bc = np.where(okc, np.floor(np.where(okc, c[:, 1], 0.0)), -10 ** 9).astype(np.int64)
    if same_shape:
        br = np.where(okc, br, idx // w)
        bc = np.where(okc, bc, idx % w)
    return br, bc


def gate_radius2(depth, tolerance: float, m: int):
    """Squared radius (m,) of the position gate: ``(tolerance * depth_i)^2``;
    0 (exact match only) where the depth is unknown; inf without a depth pass
    or with ``tolerance`` 0 (no gate, the literal paper)."""
    if depth is not None and tolerance > 0:
        tol = tolerance * depth
        tol = np.where(np.isfinite(tol), tol, 0.0)           # background / unknown: exact
    else:
        tol = np.full(m, np.inf)
    return tol * tol


def best_previous(prev: PreviousModels, br, bc, inp: FrameInputs, tol2):
    """The pixel o of frame t-1 whose model each pixel i of the chunk takes (Sec. 6).

    Among the window around (br, bc) (m,), candidates with a model of pixel i's
    class (surface / background) and ``|W_o - W_i|^2 <= tol2``, the one that
    minimises ``|W_o(t-1) - W_i(t)|^2 |y_i(t) - beta_o(t-1)^T z_i(t)|^2``, z in
    the candidate's own time; ties go to the smaller prediction error, then the
    earlier (nearer) ring.  Search in float32 (``prev.packed``).
    Returns best (m,) int64 flat index into frame t-1 (-1: none) and
    gated (m,) bool: a candidate of the right class existed but none passed the gate.
    """
    hp, wp = prev.shape
    yi, yoki, wi = inp.y, inp.y_ok, inp.position
    m = yi.shape[0]
    best = np.full(m, -1, np.int64)
    best_score = np.full(m, np.inf)
    best_e2 = np.full(m, np.inf)
    any_gate = np.zeros(m, bool)
    want = np.where(inp.background, 2.0, 1.0)
    for oy, ox in zip(prev.dy, prev.dx):
        r = br + oy
        cc = bc + ox
        inside = (r >= 0) & (r < hp) & (cc >= 0) & (cc < wp)
        j = np.where(inside, r * wp + cc, 0)
        g = prev.packed[j]                                # one gather per offset
        cand = inside & (g[:, 10] == want) & inp.pos_ok
        d2 = (g[:, 0] - wi[:, 0]) ** 2 + (g[:, 1] - wi[:, 1]) ** 2 + (g[:, 2] - wi[:, 2]) ** 2
        gate = cand & (d2 <= tol2)
        any_gate |= cand
        t_loc = g[:, 9] + prev.dt
        e0 = yi[:, 0] - g[:, 3] - g[:, 6] * t_loc
        e1 = yi[:, 1] - g[:, 4] - g[:, 7] * t_loc
        e2_ = yi[:, 2] - g[:, 5] - g[:, 8] * t_loc
        e2 = np.where(yoki, e0 * e0 + e1 * e1 + e2_ * e2_, 1.0)
        with np.errstate(over="ignore", invalid="ignore"):
            score = d2 * e2
        score = np.where(np.isnan(score), np.inf, score)
        better = gate & ((score < best_score) | ((score == best_score) & (e2 < best_e2)))
        best = np.where(better, j, best)
        best_score = np.where(better, score, best_score)
        best_e2 = np.where(better, e2, best_e2)
    return best, any_gate & (best < 0)


# ----------------------------------------------------------------------------- reset tests, bias
def residual_reset(z, P_o, pred, e, s2, v, has_y, lam: float, reset_sigma: float):
    """Carried models to drop (m,) bool: the prediction misses by more than ``reset_sigma`` deviations,
    ``mean_c e_c^2 > reset_sigma^2 ((sigma^2 + (REL_FLOOR pred)^2) (1 + z^T P z / lambda) + v)``
    (module docstring, gate (b)); never where there is no y, nor with ``reset_sigma`` 0.

    z (m, 2), P_o (m, 2, 2) the carried P(t-1), pred and e = y - pred (m, 3), s2, v (m,).
    """
    if not reset_sigma > 0:
        return np.zeros(z.shape[0], bool)
    s = np.einsum("ni,nij,nj->n", z, P_o, z)
    floor = (REL_FLOOR ** 2) * (pred * pred).mean(axis=1) + 1e-300
    lim = reset_sigma ** 2 * ((s2 + floor) * (1.0 + s / lam) + v)
    with np.errstate(invalid="ignore", over="ignore"):
        return has_y & ~((e * e).mean(axis=1) <= lim)


def sample_reset(z, P_o, pred, mean, mean_var, s2, v, has_y, lam: float, threshold: float):
    """Carried models to drop (m,) bool: the prediction fails a chi-square test against the frame's samples.

    ``q = sum_c (mean_c - pred_c)^2 / (V_c + (sigma^2 + (REL_FLOOR pred_c)^2) (1 + z^T P z / lambda) + v)
    > threshold`` with ``mean`` the pixel's sample mean and ``V`` its calibrated
    variance (``Buffers.calibrated_variance``): ``mean - pred`` is the samples'
    noise (``V``) plus the prediction's error, whose variance is the model's
    noise ``v`` plus the static estimate's error ``sigma^2`` that the model
    follows, widened by ``1 + z^T P z / lambda`` as in :func:`residual_reset` (a
    young model's slope is still unknown), so a valid model gives ``q`` about
    chi-square with 3 degrees of freedom; 16.27 is its 0.999 quantile.  The
    samples are independent of the model, so a model that lags a moving
    highlight fails even where y(t) (spatially filtered, perhaps blurred the
    same way) agrees with it.  Channels with unknown variance (+inf) add 0;
    a non-finite ``q`` is a miss; never without a y, a mean, or with
    ``threshold`` 0.  pred, mean, mean_var (m, 3), s2, v (m,).
    """
    if mean is None or mean_var is None or not threshold > 0:
        return np.zeros(pred.shape[0], bool)
    s = np.einsum("ni,nij,nj->n", z, P_o, z)
    d = mean - pred
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        model = (s2[:, None] + (REL_FLOOR * pred) ** 2 + 1e-300) * (1.0 + s / lam)[:, None] + v[:, None]
        q = (d * d / (mean_var + model)).sum(axis=1)
    return has_y & ~(q <= threshold)


def bias_estimate(bias_num, bias_den, e, s2, v, has_y, lam: float):
    """Squared bias of the carried prediction (module docstring, error estimate).

    Updates the lambda-weighted sums of ``mean_c e_c^2 - sigma^2 - v`` and of
    the weights (unchanged without a y); returns them and ``b^2 = max(0, num / den)``, all (m,).
    """
    excess = (e * e).mean(axis=1) - s2 - v
    bn = np.where(has_y, lam * bias_num + np.where(np.isfinite(excess), excess, 0.0), bias_num)
    bd = np.where(has_y, lam * bias_den + 1.0, bias_den)
    return bn, bd, np.maximum(bn / np.maximum(bd, 1e-300), 0.0)


class CarriedModels(NamedTuple):
    """Models of the carried pixels after frame t (n rows): beta (n, 3, 2), P, C
    (n, 2, 2), age (n,) int64, bias_num, bias_den (n,), image (n, 3) =
    beta(t)^T z(t), error (n,), drop (n,) bool (reset by a gate), drop_samples
    (n,) bool (of those, the ones only the sample gate reset); for the safe
    choice (:func:`safe_choice`): excess (n,) ``mean_c e_c^2 - sigma^2 - v`` of
    the a-priori residual e = y - pred and excess_s (n,) ``mean_c (d_c^2 - V_c) - v``
    of d = sample mean - pred (NaN without y, or without the samples' mean and
    variance), noise (n,) ``sigma^2 + v`` and noise_s (n,) ``mean_c V_c + v``, their
    noise levels, gain (n,) ``g = z^T G``, var_out (n,) ``z^T C(t) z``, bias2 (n,) ``b^2``."""

    beta: np.ndarray
    P: np.ndarray
    C: np.ndarray
    age: np.ndarray
    bias_num: np.ndarray
    bias_den: np.ndarray
    image: np.ndarray
    error: np.ndarray
    drop: np.ndarray
    drop_samples: np.ndarray
    excess: np.ndarray
    excess_s: np.ndarray
    noise: np.ndarray
    noise_s: np.ndarray
    gain: np.ndarray
    var_out: np.ndarray
    bias2: np.ndarray


def carry_models(prev: PreviousModels, j, y, s2, has_y, lam: float, reset_sigma: float,
                 top: float, mean=None, mean_var=None, sample_gate: float = 0.0) -> CarriedModels:
    """Eq. 6 for the models of frame t-1 rows ``j`` (n,) carried to pixels with y (n, 3), s2, has_y (n,).

    z = (1, age + dt) in the model's own time.  Where there is no y the model
    is kept unchanged and outputs its prediction, error ``v + b^2 + top``;
    elsewhere the error is ``z^T C(t) z + (1 - g)^2 b^2`` (module docstring).
    Models failing :func:`residual_reset` or :func:`sample_reset` (with the
    pixels' sample ``mean`` and calibrated ``mean_var`` (n, 3)) are marked ``drop``.
    """
    t_loc = (prev.age[j] + prev.dt).astype(np.float64)
    z = np.stack([np.ones(j.size), t_loc], 1)
    b_o, P_o, C_o = prev.beta[j], prev.P[j], prev.C[j]
    b1, P1, C1, pred, g, v = rls_update(b_o, P_o, C_o, z, y, s2, lam)
    e = y - pred
    drop_resid = residual_reset(z, P_o, pred, e, s2, v, has_y, lam, reset_sigma)
    drop_samples = sample_reset(z, P_o, pred, mean, mean_var, s2, v, has_y, lam, sample_gate) & ~drop_resid
    drop = drop_resid | drop_samples
    # pixels without a usable y: keep the carried model, output its prediction
    b1 = np.where(has_y[:, None, None], b1, b_o)
    P1 = np.where(has_y[:, None, None], P1, P_o)
    C1 = np.where(has_y[:, None, None], C1, C_o)
    y_hat = np.einsum("nci,ni->nc", b1, z)
    var_out = np.einsum("ni,nij,nj->n", z, C1, z)
    bn, bd, bias2 = bias_estimate(prev.bias_num[j], prev.bias_den[j], e, s2, v, has_y, lam)
    e_out = np.where(has_y, var_out + (1.0 - g) ** 2 * bias2, v + bias2 + top)
    with np.errstate(invalid="ignore", over="ignore"):
        excess = np.where(has_y, (e * e).mean(axis=1) - s2 - v, np.nan)
        noise = s2 + v
        if mean is not None and mean_var is not None:
            ds = mean - pred
            noise_s = mean_var.mean(axis=1) + v
            xs = (ds * ds).mean(axis=1) - noise_s
            excess_s = np.where(has_y & np.isfinite(xs), xs, np.nan)
        else:
            excess_s = np.full(excess.shape, np.nan)
            noise_s = np.full(excess.shape, np.nan)
    return CarriedModels(b1, P1, C1, t_loc.astype(np.int64), bn, bd, y_hat, e_out, drop, drop_samples,
                         excess, excess_s, noise, noise_s, g, var_out, bias2)


# ----------------------------------------------------------------------------- output assembly
class _Rows(NamedTuple):
    """One chunk's share (m rows) of the new state and of the output, and the
    terms of the safe choice: ``excess`` and ``excess_s`` of every pixel that
    had a candidate model and a y (NaN elsewhere), :data:`_CHOICE` of the carried ones."""

    beta: np.ndarray
    P: np.ndarray
    C: np.ndarray
    age: np.ndarray
    bias_num: np.ndarray
    bias_den: np.ndarray
    image: np.ndarray
    error: np.ndarray
    source: np.ndarray
    excess: np.ndarray
    excess_s: np.ndarray
    noise: np.ndarray
    noise_s: np.ndarray
    gain: np.ndarray
    var_out: np.ndarray
    bias2: np.ndarray


#: fields of the carried (kept) models that the safe choice reads
_CHOICE = ("gain", "var_out", "bias2")


def _step_chunk(idx, inp: FrameInputs, prev: PreviousModels | None, cen, w: int, same_shape: bool,
                params: Params, lam: float, delta: float, counts: dict) -> _Rows:
    """Frame t for the pixels ``idx`` (m,) of the flattened inputs: find each
    pixel's previous model, update it (Eq. 6) or start a new one; adds to ``counts``."""
    m = idx.size
    best = np.full(m, -1, np.int64)
    if prev is not None:
        br, bc = search_origin(idx, w, cen, same_shape)
        best, gated = best_previous(prev, br, bc, inp, gate_radius2(inp.depth, params.position_tolerance, m))
        counts["reset_position"] += int(np.count_nonzero(gated))
    carried = best >= 0
    rows = _Rows(np.zeros((m, 3, 2)), np.zeros((m, 2, 2)), np.zeros((m, 2, 2)), np.zeros(m, np.int64),
                 np.zeros(m), np.zeros(m), np.zeros((m, 3)), np.zeros(m), None,
                 np.full(m, np.nan), np.full(m, np.nan), np.full(m, np.nan), np.full(m, np.nan),
                 np.ones(m), np.zeros(m), np.zeros(m))
    ci = np.flatnonzero(carried)
    if ci.size:
        opt = lambda a: None if a is None else a[ci]
        cm = carry_models(prev, best[ci], inp.y[ci], inp.s2[ci], inp.y_ok[ci], lam, params.reset_sigma,
                          inp.top, opt(inp.mean), opt(inp.mean_var), params.sample_gate)
        n_samples = int(np.count_nonzero(cm.drop_samples))
        counts["reset_samples"] += n_samples
        counts["reset_residual"] += int(np.count_nonzero(cm.drop)) - n_samples
        for name in ("excess_s", "noise", "noise_s"):
            getattr(rows, name)[ci] = getattr(cm, name)
        rows.excess[ci] = cm.excess               # reset ones too: they warn their neighbours
        keep = ~cm.drop
        sel = ci[keep]
        for name in ("bias_num", "bias_den", "beta", "P", "C", "age", "image", "error") + _CHOICE:
            getattr(rows, name)[sel] = getattr(cm, name)[keep]
        carried[ci[cm.drop]] = False
        best[ci[cm.drop]] = -1
    # new models (paper initialisation)
    ni = np.flatnonzero(~carried & inp.y_ok & inp.pos_ok)
    if ni.size:
        b0, P0, C0 = new_models(inp.y[ni], inp.s2[ni], delta, lam)
        rows.beta[ni], rows.P[ni], rows.C[ni] = b0, P0, C0
        rows.age[ni] = 1
        rows.image[ni] = inp.y[ni]
        rows.error[ni] = inp.s2[ni]
    nothing = ~carried & ~(inp.y_ok & inp.pos_ok)
    rows.image[nothing] = np.where(inp.y_ok[nothing, None], inp.y[nothing], 0.0)
    rows.error[nothing] = np.where(inp.y_ok[nothing], inp.s2[nothing], inp.top)
    counts["carried"] += int(np.count_nonzero(carried))
    counts["new"] += int(ni.size)
    return rows._replace(source=np.where(carried, best, -1))


def _store(rows: _Rows, idx, state: TemporalState, image, error, source, terms: dict):
    """Write one chunk's rows into the (H, W, ...) state, outputs and safe-choice ``terms`` (H, W)."""
    for name in ("beta", "P", "C", "age", "bias_num", "bias_den"):
        a = getattr(state, name)
        a.reshape((-1,) + a.shape[2:])[idx] = getattr(rows, name)
    image.reshape(-1, 3)[idx] = rows.image
    error.reshape(-1)[idx] = rows.error
    source.reshape(-1)[idx] = rows.source
    for name, a in terms.items():
        a.reshape(-1)[idx] = getattr(rows, name)


def box_mean(x, radius: int, with_count: bool = False):
    """Mean of the finite entries of ``x`` (H, W) over the (2r+1)^2 window of each
    pixel (clipped at the border); NaN where the window has none.  With
    ``with_count``: (mean, number of finite entries)."""
    h, w = x.shape
    ok = np.isfinite(x)
    r = max(int(radius), 0)
    total = np.zeros((h + 2 * r, w + 2 * r))
    count = np.zeros((h + 2 * r, w + 2 * r))
    xv = np.where(ok, x, 0.0)
    for dy in range(2 * r + 1):                      # scatter each pixel into its window
        for dx in range(2 * r + 1):
            total[dy:dy + h, dx:dx + w] += xv
            count[dy:dy + h, dx:dx + w] += ok
    total, count = total[r:r + h, r:r + w], count[r:r + h, r:r + w]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1.0), np.nan)
    return (mean, count) if with_count else mean


def safe_choice(image, error, y, s2, carried, terms: dict, radius: int):
    """The output where the temporal estimate is not expected to beat the frame's own.

    For a carried pixel (with a y) the temporal output is ``(1 - g) pred + g
    y`` with error ``z^T C(t) z + (1 - g)^2 b^2`` (module docstring).  Here the
    squared bias is ``max(b^2, B_y, B_s)`` with this frame's excess residuals
    averaged over the (2r+1)^2 window: ``B_y`` of ``mean_c e_c^2 - sigma^2 -
    v`` (e = y - pred) and ``B_s`` of ``mean_c (d_c^2 - V_c) - v`` (d = sample
    mean - pred, V its calibrated variance: evidence that does not rest on the
    static estimate's own error).  A moving highlight or a misplaced model shows
    up in this frame's residuals before the lambda-weighted ``b^2`` catches up;
    the window averages their chi-square noise and includes the models the
    gates just reset; each pooled mean counts beyond :data:`BIAS_Z` standard
    errors of its noise only (``noise`` = ``sigma^2 + v``, ``noise_s`` =
    ``mean_c V_c + v``, window means).  The error is compared with the window mean of
    ``sigma^2``: a single pixel's ``sigma^2`` is noisy, and comparing with it
    would send exactly the pixels whose estimate is low by chance to the static
    result (docs/notes/temporal.md).
    Where the temporal error is not below it the pixel takes ``y`` and
    ``sigma^2`` (the model is kept: this changes the output only).
    carried (H, W) bool: carried models with a y; terms: (H, W) arrays
    ``excess``, ``excess_s``, ``noise``, ``noise_s`` (NaN where none), ``gain``,
    ``var_out``, ``bias2``.
    Returns image, error, fallback (H, W) bool.
    """
    b2 = terms["bias2"]
    for name, nname in (("excess", "noise"), ("excess_s", "noise_s")):
        pooled, cnt = box_mean(terms[name], radius, True)
        scale = box_mean(np.where(np.isfinite(terms[name]), terms[nname], np.nan), radius)
        with np.errstate(invalid="ignore", divide="ignore"):
            b_now = pooled - BIAS_Z * np.sqrt(2.0 / (3.0 * np.maximum(cnt, 1.0))) * scale
        b2 = np.maximum(b2, np.where(np.isfinite(b_now), np.maximum(b_now, 0.0), 0.0))
    s2_pool = box_mean(np.where(carried, s2, np.nan), radius)
    s2_ref = np.where(np.isfinite(s2_pool), s2_pool, s2)
    with np.errstate(invalid="ignore", over="ignore"):
        err_t = terms["var_out"] + (1.0 - terms["gain"]) ** 2 * b2
        use_t = err_t < s2_ref
    fallback = carried & ~use_t
    image = np.where(fallback[..., None], y, image)
    error = np.where(carried, np.where(use_t, err_t, s2), error)
    return image, error, fallback


def _finish(image, error, state: TemporalState):
    """Never emit NaN/Inf: non-finite image values become 0, errors the largest
    finite error (then >= 0), and a model with any non-finite entry is dropped
    (age 0, zeros) in ``state``.  Returns image, error."""
    h, w = state.shape
    image = np.where(np.isfinite(image), image, 0.0)
    fin = np.isfinite(error)
    error = np.maximum(np.where(fin, error, float(error[fin].max()) if fin.any() else 0.0), 0.0)
    for name in ("beta", "P", "C", "bias_num", "bias_den"):
        a = getattr(state, name)
        bad = ~np.all(np.isfinite(a.reshape(h, w, -1)), axis=-1)
        if bad.any():
            state.age[bad] = 0
            a[bad] = 0.0
    return image, error


# ----------------------------------------------------------------------------- step
def step(state: TemporalState | None, buf: Buffers, params: Params | dict | None = None, *,
         frame: int | None = None, static: MethodResult | None = None, lp_params=None,
         center: np.ndarray | None = None) -> TemporalResult:
    """One frame of LP's temporal extension (Sec. 6, Eq. 6).

    Parameters
    ----------
    state : TemporalState or None
        The state returned for the previous frame (None for the first frame of
        a range or after a cut: every pixel starts a new model).
    buf : Buffers (H, W)
        The frame's accumulated samples; needs ``position`` (and ``depth`` for
        the position gate).
    params : Params or dict.
    frame : int, the frame number (default: the previous state's + 1, or 1).
    static : MethodResult or None
        The frame's static reconstruction ``y(t)`` with its error (e.g. the
        ``lp.reconstruct`` result the loop already computed); None computes it
        (``lp.reconstruct(buf, lp_params)``, or the raw means with
        ``params.spatial = False``).
    lp_params : lp.Params or dict for the static reconstruction.
    center : (H, W, 2) or None
        Continuous (row, col) in the previous frame around which to search
        (``reproject.backward_coordinates``); NaN entries and None use the
        pixel's own position in the image.

    Returns
    -------
    TemporalResult
        ``image`` (H, W, 3) = beta(t)^T z(t) (y(t) where :func:`safe_choice`
        falls back), ``error`` (H, W) (module docstring), the new ``state``,
        ``source`` and ``info`` (``carried``, ``new``, ``reset_position``,
        ``reset_residual``, ``reset_samples`` (reset by the sample gate only),
        ``fallback`` (carried but output y) fractions, ``frame``,
        ``resized``).  All finite.
    """
    params = _params(params)
    h, w = buf.shape
    if frame is None:
        frame = 1 if state is None else int(state.frame) + 1
    frame = int(frame)
    inp = _frame_inputs(buf, params, static, lp_params)
    new_state = TemporalState(frame, np.zeros((h, w, 3, 2)), np.zeros((h, w, 2, 2)),
                              np.zeros((h, w, 2, 2)), np.zeros((h, w), np.int64),
                              inp.position.copy(), inp.background.copy())
    image = np.zeros((h, w, 3))
    error = np.zeros((h, w))
    source = np.full((h, w), -1, np.int64)
    info = {"frame": frame, **{k: 0.0 for k in COUNTS}, "resized": False}
    npx = h * w
    if npx == 0:
        return TemporalResult(image, error, new_state, source, info)
    prev, info["resized"] = previous_models(state, frame, (h, w), center is not None, params.search_radius)
    cen = _center_rows(center, (h, w))
    same_shape = prev is not None and prev.shape == (h, w)
    flat = inp.flat()
    counts = dict.fromkeys(COUNTS, 0)
    terms = {name: np.zeros((h, w)) for name in ("excess", "excess_s", "noise", "noise_s") + _CHOICE}
    chunk = max(int(params.chunk), 1)
    for s0 in range(0, npx, chunk):
        idx = np.arange(s0, min(npx, s0 + chunk))
        rows = _step_chunk(idx, flat.rows(idx), prev, cen, w, same_shape, params,
                           float(params.lam), float(params.delta), counts)
        _store(rows, idx, new_state, image, error, source, terms)
    if params.safe_choice and prev is not None:
        image, error, fallback = safe_choice(image, error, inp.y, inp.s2, (source >= 0) & inp.y_ok, terms,
                                             params.bias_radius)
        counts["fallback"] = int(np.count_nonzero(fallback))
    image, error = _finish(image, error, new_state)
    info.update({k: v / npx for k, v in counts.items()})
    return TemporalResult(image, error, new_state, source, info)

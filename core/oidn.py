"""Intel Open Image Denoise as a reconstruction, its dual-buffer error
estimate, and the method ``oidn``: adaptive sampling for the denoised image.

Reconstruction (:func:`oidn_filter`)
------------------------------------
OIDN's RT filter (Afra et al., Intel Open Image Denoise 2.5) on the sample
mean, HDR, with the albedo and normal feature passes as auxiliary images.
``quality`` (high / balanced / fast) picks the network, ``prefilter`` how the
auxiliary images are treated (``fast``: OIDN's ``cleanAux=False``, they may be
noisy; ``none``: ``cleanAux=True``, taken as noise-free; ``accurate``: they
are denoised by OIDN first, then ``cleanAux=True``, what Cycles does by
default).  Backends: the ``pyoidn`` wheel (PyPI, bundles OIDN 2.5.1) through
its low-level Filter API, every step followed by polling the device's error
(that API never raises: a failed filter leaves a black image), or a fallback
registered by the Blender layer (``addon/oidn_blender.py``: Blender's own OIDN
through the compositor) where the wheel is missing.  Nothing is imported
until the first call.

Error of the denoised image (:func:`dual_buffer_error`)
-------------------------------------------------------
The samples of each pixel are split into two disjoint halves A and B (whole
sample groups, ``core.buffers.Half``), and D, D(A), D(B) are the denoised
full mean and halves.  Two terms, per pixel and channel:

* variance ``s c |D(A) - D(B)|^2`` with ``c = n_A n_B / n^2`` (1/4 for
  equal halves; :func:`variance_constant` derives it for i.i.d. samples)
  and ``s`` the stratification scale measured on the run's own halves
  (:func:`stratification_scale`): Cycles' sequence makes the full mean of
  ``n`` consecutive samples converge faster than the halves, whole groups
  that are not adjacent, so ``c |x_A - x_B|^2`` over-states the variance
  of the mean; ``s`` is the ratio of the variance of the mean calibrated
  for the stratification (core/variance.py, exponent measured on the
  initial pass) to it, carried over to the denoised halves as for a
  linear denoiser;
* bias ``w |D - (n_A D(A) + n_B D(B)) / n|^2``: the weighted mean of the
  halves equals D exactly for a linear denoiser, so this term is what OIDN's
  nonlinearity adds: the change of its output with the sample count, which
  the variance term cannot see where the blur is the same in both halves
  (defocus, motion blur).  If the bias falls like ``1/m``, the halves' bias
  is twice D's and the difference is D's own bias: ``w = 1``.

Both are single noisy realisations per pixel, so they are pooled over a
``(2 r + 1)^2`` box (``r = 3``: 7x7) before any use, in the metric's
relative form (``t / (D^2 + 0.01)``): pooled in absolute units a bright
pixel's error lent to dim neighbours counted 1.5x in the relMSE estimate.
Without stored halves
(buffers read from a file, :func:`denoise` on plain arrays) the halves are
made by recorruption (Pang et al. 2021): ``A = x + s z``, ``B = x - s z``
with ``s^2`` the variance of the mean and ``z`` standard normal; for Gaussian
noise A and B are then independent with variance ``2 s^2`` each, like two real
halves (i.i.d.: no stratification scale).  Measurements (correlation with the
true error, calibration): docs/notes/oidn.md.

Sampling (:func:`sample_map`)
-----------------------------
The error made relative as the metric does, ``e_i = mean_c err_ic / (D_ic^2
+ 0.01)``, pooled; the denoised error of a pixel falls with its sample count
as ``n^-p`` with ``p = RATE`` measured on the sample scenes (not the Monte
Carlo 1/n; docs/notes/oidn.md).  With ``e_i(m) = a_i m^-p``, ``a_i = e_i
n_i^p``, the counts minimising ``sum_i e_i(m_i)`` for a fixed total satisfy
``p a_i m_i^(-p-1) = lambda``, i.e. ``m_i ~ a_i^(1/(p+1))`` (``p = 1``: the
square root of the error coefficient).  A round spreads its samples in
proportion to those targets (``allocation="proportional"``, the default:
measured the best, the estimate being noisy) or tops each block up towards
them, furthest below first (``"topup"``, water filling: ``sum_b area_b
max(T_b - n_b, 0) = budget``; optimal if the estimate were right).  Maps are
made on ``BLOCK`` x ``BLOCK`` blocks (the planner's smallest region), one
count per block, so the planner renders them as they are.  The loop's
iterations are the rounds; its final reconstruction denoises all samples.
"""
from __future__ import annotations

import dataclasses
import threading
import time
from dataclasses import dataclass

import numpy as np

from .buffers import Buffers
from .filters import box_mean
from .method import MethodResult, allocate, exact_pixels, param, params_from_dict
from .metrics import REL_EPS

NAME = "oidn"
#: albedo and normal guide OIDN; depth (with them) guides the pooling of the variance its error estimate
#: reads (``Buffers.calibrated_variance``): declared, so the result never depends on which other passes a
#: job happens to render (a depth pass rendered for ``--temporal`` changed the sample maps)
PASSES: tuple = ("albedo", "normal", "depth")
ADAPTIVE = True
SAMPLER_USES_RESULT = True

QUALITIES = ("high", "balanced", "fast")
PREFILTERS = ("fast", "accurate", "none")
BACKENDS = ("auto", "pyoidn", "blender")
ALLOCATIONS = ("proportional", "topup")

#: exponent p of the denoised relMSE's fall with the sample count, relMSE ~
#: n^-p: over the six sample scenes (OIDN high, accurate prefilter, 128x128,
#: reference floor subtracted) the median log-log slope is 1.01 from 4 to 32
#: spp and 0.84 from 8 to 64; per scene 0.3 (glossy) to 1.2 (docs/notes/oidn.md)
RATE = 0.9

#: seconds of one call with the fast prefilter over one with the accurate
#: prefilter (OIDN high quality, CPU): 0.09 at 512x512 (docs/notes/oidn.md,
#: cost per megapixel), 0.10-0.16 at 128x128 and 640x400; the cost model of
#: ``auto`` charges the error estimate's calls with it
FAST_CALL_SHARE = 0.15

#: largest colour value handed to OIDN (float32 input; HDR values beyond are
#: clipped, non-finite ones set to 0)
VALUE_LIMIT = 1e7


class OIDNError(RuntimeError):
    """OIDN failed or returned an unusable image; the message says why."""


class OIDNUnavailable(OIDNError):
    """No OIDN backend in this Python."""


@dataclass
class Params:
    """Parameters of ``oidn`` (OIDN 2.5 RT filter and the error-driven sampler)."""

    quality: str = param("high", "OIDN network: high is the most accurate; balanced is as fast here "
                         "(CPU); fast takes about half the time and keeps less detail",
                         choices=QUALITIES, label="Quality")
    prefilter: str = param("accurate", "albedo/normal passes: fast lets OIDN treat them as noisy "
                           "(cleanAux off); accurate denoises them first (two more OIDN passes per "
                           "image, sharper where they are noisy: defocus, motion blur); none takes "
                           "them as noise-free (cleanAux on: keeps their noise in the image)",
                           choices=PREFILTERS, label="Prefilter")
    map_prefilter: str = param("fast", "albedo/normal prefilter of the error estimates (the full "
                               "mean and both halves denoised) that place samples between rounds "
                               "and give the final Error pass: fast skips denoising the albedo and "
                               "normal first, 3 OIDN passes per estimate instead of 9; the image "
                               "itself always uses Prefilter",
                               choices=PREFILTERS, label="Map Prefilter")
    adaptive: bool = param(True, "place samples where the denoised image's estimated error falls "
                           "most per sample; off: uniform sampling, then OIDN (what Cycles' "
                           "Denoise checkbox does, run through this loop)", label="Adaptive")
    bias_weight: float = param(1.0, "weight of the bias term |D - mean of the denoised halves|^2 "
                               "in the error estimate; higher sends more samples where OIDN's "
                               "output still changes with the sample count (defocus, motion "
                               "blur), 0: variance term only", 0.0, 100.0, label="Bias Weight")
    pool_radius: int = param(3, "the estimated error is pooled over a (2r+1)^2 box (3: 7x7); "
                             "larger: steadier estimate, coarser sample map", 0, 32,
                             label="Pooling Radius")
    rate: float = param(RATE, "how fast the denoised error falls with samples (relMSE ~ n^-rate, "
                        "measured on the sample scenes); lower spreads samples more evenly",
                        0.05, 2.0, label="Error Rate")
    allocation: str = param("proportional", "how a round's samples follow the target counts ~ (error "
                            "coefficient)^(1/(1+rate)): topup fills the pixels furthest below "
                            "their target first (optimal if the estimate is right), proportional "
                            "spreads the round in proportion to the targets (robust to a noisy "
                            "estimate: measured better)", choices=ALLOCATIONS, label="Allocation")
    uniform_fraction: float = param(0.0, "share of each round spread uniformly, a floor against "
                                    "an estimate that misses a region; higher is safer and less "
                                    "adaptive", 0.0, 1.0, label="Uniform Share")
    error_estimate: bool = param(True, "estimate the denoised image's error from the two sample "
                                 "halves (two more OIDN calls per reconstruction; the adaptive sampler "
                                 "needs it); off: one call, and the Error pass holds the sample mean's "
                                 "variance, a bound for the denoised error away from edges",
                                 label="Error Estimate")
    backend: str = param("auto", "OIDN implementation: pyoidn (the pip wheel), blender "
                         "(Blender's compositor Denoise node), auto: pyoidn when installed",
                         choices=BACKENDS, label="Backend")

    def __post_init__(self):
        for name, choices in (("quality", QUALITIES), ("prefilter", PREFILTERS), ("map_prefilter", PREFILTERS),
                              ("allocation", ALLOCATIONS), ("backend", BACKENDS)):
            value = getattr(self, name)
            if value not in choices:
                raise ValueError(f"oidn parameter {name}={value!r} must be one of {', '.join(choices)}")
        if self.adaptive and not self.error_estimate:
            raise ValueError("oidn parameter error_estimate=False needs adaptive=False: the adaptive "
                             "sampler places samples by that estimate")


@dataclass
class OIDNFit:
    """What the sampler reuses of a reconstruction (``MethodResult.fit``).

    relative : (H, W) pooled relative squared error (metric form)
    variance : (H, W, 3) pooled variance term
    bias : (H, W, 3) pooled bias term
    halves : "split" (stored halves), "recorrupted" or "none" (no variance known)
    """

    relative: np.ndarray
    variance: np.ndarray
    bias: np.ndarray
    halves: str


# ============================================================== backends
_FALLBACKS: dict = {}
_LOCK = threading.RLock()
_DEVICE: dict = {}
_FILTERS: dict = {}


_MAIN_THREAD: set = set()


def register_backend(name: str, fn, main_thread: bool = False) -> None:
    """Register ``fn(color, albedo, normal, *, hdr, prefilter, quality) ->
    (H, W, 3)`` as backend ``name`` (the Blender layer registers ``blender``);
    ``main_thread``: it may only run on the application's main thread
    (Blender's compositor), see :func:`needs_main_thread`."""
    _FALLBACKS[name] = fn
    if main_thread:
        _MAIN_THREAD.add(name)
    else:
        _MAIN_THREAD.discard(name)


def unregister_backend(name: str) -> None:
    _FALLBACKS.pop(name, None)
    _MAIN_THREAD.discard(name)


def needs_main_thread(backend: str = "auto") -> bool:
    """True when a call with ``backend`` would run a backend registered as
    main-thread only (then a UI must not run it on a worker thread)."""
    try:
        return resolve_backend(backend) in _MAIN_THREAD
    except (OIDNError, ValueError):
        return False


def pyoidn_available() -> bool:
    """True when the ``pyoidn`` wheel imports."""
    try:
        import pyoidn  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_backend(backend: str = "auto") -> str:
    """The backend a call with ``backend`` uses; OIDNUnavailable (one line)
    when there is none."""
    if backend not in BACKENDS:
        raise ValueError(f"oidn backend {backend!r} must be one of {', '.join(BACKENDS)}")
    if backend in ("auto", "pyoidn") and pyoidn_available():
        return "pyoidn"
    if backend == "pyoidn":
        raise OIDNUnavailable("oidn: the pyoidn wheel is not installed (pip install pyoidn==2.5.1.0)")
    if backend == "blender" or backend == "auto":
        if "blender" in _FALLBACKS:
            return "blender"
        if backend == "blender":
            raise OIDNUnavailable("oidn: Blender's OIDN is reachable only inside Blender with the "
                                  "add-on enabled")
    if _FALLBACKS:
        return next(iter(_FALLBACKS))
    raise OIDNUnavailable("oidn: no OIDN available; install the pyoidn wheel (pip install "
                          "pyoidn==2.5.1.0) or run inside Blender with the add-on enabled")


def oidn_filter(color, albedo=None, normal=None, *, quality: str = "high", prefilter: str = "accurate",
                hdr: bool = True, backend: str = "auto") -> np.ndarray:
    """OIDN's RT filter on one image.

    color : (H, W, 3) linear HDR colour (non-finite -> 0, negative -> 0)
    albedo : optional (H, W, 3) in [0, 1] (clipped); normal : optional (H, W, 3)
        in [-1, 1] (clipped), used only with an albedo (OIDN's rule)
    quality, prefilter, backend : see :class:`Params`

    Returns (H, W, 3) float64.  ValueError for bad shapes or options,
    OIDNUnavailable without a backend, OIDNError when OIDN reports an error or
    returns non-finite or all-black output for a non-black input.
    """
    c = _clean(color, "color", 0.0, VALUE_LIMIT)
    a = None if albedo is None else _clean(albedo, "albedo", 0.0, 1.0, c.shape)
    nrm = None if normal is None or a is None else _clean(normal, "normal", -1.0, 1.0, c.shape)
    if quality not in QUALITIES:
        raise ValueError(f"oidn quality {quality!r} must be one of {', '.join(QUALITIES)}")
    if prefilter not in PREFILTERS:
        raise ValueError(f"oidn prefilter {prefilter!r} must be one of {', '.join(PREFILTERS)}")
    which = resolve_backend(backend)
    if which == "pyoidn":
        out = _pyoidn_filter(c, a, nrm, hdr, prefilter, quality)
    else:
        out = np.asarray(_FALLBACKS[which](c, a, nrm, hdr=hdr, prefilter=prefilter, quality=quality))
    out = np.asarray(out, np.float64)
    if out.shape != c.shape:
        raise OIDNError(f"oidn ({which}) returned a {out.shape} image for a {c.shape} input")
    if not np.isfinite(out).all():
        raise OIDNError(f"oidn ({which}) returned non-finite pixels")
    if c.max() > 0 and not np.any(out):
        raise OIDNError(f"oidn ({which}) returned a black image for a non-black input")
    return out


def _clean(x, name, lo, hi, shape=None) -> np.ndarray:
    x = np.asarray(x, np.float64)
    if x.ndim != 3 or x.shape[2] < 3 or x.shape[0] == 0 or x.shape[1] == 0:
        raise ValueError(f"oidn: {name} must be (H, W, 3), got {x.shape}")
    x = x[..., :3]
    if shape is not None and x.shape != shape:
        raise ValueError(f"oidn: {name} is {x.shape[1]}x{x.shape[0]}, the colour {shape[1]}x{shape[0]}")
    x = np.where(np.isfinite(x), x, 0.0)
    return np.ascontiguousarray(np.clip(x, lo, hi), np.float32)


def _device():
    """The process's committed OIDN CPU device (made once)."""
    import pyoidn
    with _LOCK:
        dev = _DEVICE.get("cpu")
        if dev is None:
            dev = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
            _check(dev, "device creation")
            dev.commit()
            _check(dev, "device commit")
            _DEVICE["cpu"] = dev
        return dev


def _check(dev, what: str) -> None:
    """Poll the device (the Filter API reports errors only this way)."""
    err = dev.get_error()
    if err:
        raise OIDNError(f"OIDN {what} failed: {err}")


def run_filter(images: dict, quality: str, hdr: bool = True, clean_aux: bool = False) -> np.ndarray:
    """One execution of OIDN's RT filter through pyoidn's Filter API.

    images : name ("color", "albedo", "normal") -> (H, W, 3) float32
        C-contiguous; without "color" it is the auxiliary prefilter (OIDN's
        documented way to denoise an albedo or normal image alone).
    Returns the (H, W, 3) float32 output; OIDNError naming the step when the
    device reports an error after any of them.  One filter per role (colour,
    albedo, normal prefilter) is kept and re-bound, as pyoidn's own
    ``denoise`` does (a new filter per call costs ~20 % more at 512x512).
    """
    import pyoidn
    q = {"high": pyoidn.OIDN_QUALITY_HIGH, "balanced": pyoidn.OIDN_QUALITY_BALANCED,
         "fast": pyoidn.OIDN_QUALITY_FAST}[quality]
    role = "color" if "color" in images else next(iter(images))
    first = next(iter(images.values()))
    out = np.zeros(first.shape, np.float32)
    bound = dict(images, output=out)
    with _LOCK:
        dev = _device()
        entry = _FILTERS.get(role)
        try:
            if entry is None:
                entry = {"filter": pyoidn.Filter(dev, pyoidn.OIDN_FILTER_TYPE_RT), "images": {}}
                _check(dev, "filter creation")
                _FILTERS[role] = entry
            flt = entry["filter"]
            for name in entry["images"]:
                if name not in bound:
                    flt.unset_image(name)
            for name, img in bound.items():
                flt.set_image(name, img, pyoidn.OIDN_FORMAT_FLOAT3)
            entry["images"] = bound  # keeps the shared arrays alive while bound
            _check(dev, "image setup")
            if role == "color":
                flt.set_bool("hdr", bool(hdr))
                flt.set_bool("cleanAux", bool(clean_aux))
            flt.set_quality(q)
            _check(dev, "filter configuration")
            flt.commit()
            _check(dev, "filter commit")
            flt.execute()
            _check(dev, "filter execution")
        except BaseException:
            gone = _FILTERS.pop(role, None)
            if gone is not None:
                gone["filter"].release()
            raise
    return out


def _pyoidn_filter(c, a, nrm, hdr, prefilter, quality) -> np.ndarray:
    """pyoidn on the images with their rows bottom to top, the order in which
    Blender (its compositor and Cycles) hands images to OIDN: OIDN's output
    is not exactly symmetric under a vertical flip (1.5e-3 relMSE between
    the two orders on a 4-spp render), and in this order it equals
    Blender's bit for bit (tests/test_oidn_blender.py)."""
    flip = lambda x: None if x is None else np.ascontiguousarray(x[::-1])
    c, a, nrm = flip(c), flip(a), flip(nrm)
    images = {"color": c}
    if a is not None:
        if prefilter == "accurate":
            a = run_filter({"albedo": a}, quality)
            if nrm is not None:
                nrm = run_filter({"normal": nrm}, quality)
        images["albedo"] = a
        if nrm is not None:
            images["normal"] = nrm
    out = run_filter(images, quality, hdr, clean_aux=prefilter != "fast" and a is not None)
    return out[::-1]


# ======================================================= dual-buffer error
def variance_constant(n_a, n_b, rate: float = 1.0) -> np.ndarray:
    """``c`` with ``Var[D(x)] = c E|D(A) - D(B)|^2`` for disjoint halves of
    ``n_a`` and ``n_b`` i.i.d. samples of the full mean ``x`` (``n = n_a +
    n_b``).

    Derivation: a denoiser whose output variance at ``m`` samples is ``V
    m^-q`` (``q = rate``; ``q = 1`` for any linear denoiser, whose output is a
    fixed weighted sum of the pixel means) gives independent halves with
    ``Var D(A) = V n_a^-q`` and ``Var D(B) = V n_b^-q`` and the same
    expectation (same weights), so ``E|D(A) - D(B)|^2 = V (n_a^-q + n_b^-q)``
    while ``Var D(x) = V n^-q``:

        c = n^-q / (n_a^-q + n_b^-q)        (q = 1: n_a n_b / n^2)

    Equal halves: ``2^-q / 2``, 1/4 for ``q = 1`` (each half has variance
    ``2 sigma^2`` against ``sigma^2`` for their mean, and the difference of
    two independent halves ``4 sigma^2``).  0 where a half is empty.
    Cycles' samples are not i.i.d.: :func:`stratification_scale` measures the
    factor the run's own halves need on top of this constant.
    """
    n_a = np.asarray(n_a, np.float64)
    n_b = np.asarray(n_b, np.float64)
    ok = (n_a > 0) & (n_b > 0)
    sa, sb = np.where(ok, n_a, 1.0), np.where(ok, n_b, 1.0)
    q = float(rate)
    return np.where(ok, (sa + sb) ** -q / (sa ** -q + sb ** -q), 0.0)


#: stratification_scale is clipped to this range (a ratio of frame sums;
#: beyond it the measurement is not trusted: 1 is i.i.d., and the sequence's
#: exponent range of core/variance.py bounds the correction of 4 subsets to
#: about 4^(1 - 3) = 1/16)
SCALE_RANGE = (1.0 / 16.0, 2.0)


def stratification_scale(var_of_mean, color_a, color_b, n_a, n_b, image) -> float:
    """Factor ``s`` with ``Var[x] = s c E|x_A - x_B|^2`` for the run's sample
    means (``c`` = :func:`variance_constant`, i.i.d.), measured on the frame.

    Why: Cycles' sequence is stratified.  The full mean of ``n`` consecutive
    samples has variance ``C n^-beta`` with ``beta > 1`` (core/variance.py),
    but the halves are whole groups that do not form stratified blocks
    (A = subsets 0 and 2 of the initial pass), so their difference sees the
    larger variance of the groups: ``c |x_A - x_B|^2`` over-states ``Var[x]``
    (on the sample scenes by 1.3-1.8x at 4 spp).  The variance of the mean
    calibrated for the stratification (``Buffers.calibrated_variance``,
    Eq. 2 of core/variance.py with the exponent measured on the initial
    pass) is the expectation of ``Var[x]``; the ratio of the frame sums

        s = sum_p,c w v_pc / sum_p,c w c_p |x_A - x_B|_pc^2,   w = 1 / (D^2 + 0.01)

    (metric weights, ``D`` the denoised image) is what the halves' spread
    must be scaled by to match it.  For a linear denoiser ``D = W x`` with
    pixel noise independent between pixels, ``Var D = sum_j w_j^2 Var x_j``
    and ``E|D(A) - D(B)|^2 = sum_j w_j^2 E|x_A - x_B|_j^2``, so the same
    ``s`` carries over to the denoised halves where it is constant over the
    filter's footprint.  i.i.d. samples: ``E s = 1``.  The sums are taken
    per ``BLOCK`` x ``BLOCK`` tile (192 terms each) and ``s`` is the median
    of the tiles' ratios: a firefly or highlight puts most of the frame's
    variance in a few pixels (glossy: 30x the sample mean's true error),
    which a single frame sum would follow.  ``var_of_mean``: (H, W, 3),
    non-finite where unknown (left out).  Returns ``s`` clipped to
    :data:`SCALE_RANGE`; 1.0 without data.
    """
    v = np.asarray(var_of_mean, np.float64)
    d = np.asarray(color_a, np.float64) - np.asarray(color_b, np.float64)
    img = np.asarray(image, np.float64)
    c = variance_constant(n_a, n_b)[..., None]
    ok = np.isfinite(v) & np.isfinite(d) & (c > 0)
    w = 1.0 / (img * img + REL_EPS)
    with np.errstate(invalid="ignore", over="ignore"):
        num = _blocks(np.where(ok, w * v, 0.0).sum(axis=-1), BLOCK)
        den = _blocks(np.where(ok, w * c * d * d, 0.0).sum(axis=-1), BLOCK)
    use = (num > 0) & (den > 0) & np.isfinite(num) & np.isfinite(den)
    if not use.any():
        return 1.0
    return float(np.clip(np.median(num[use] / den[use]), *SCALE_RANGE))


def dual_buffer_error(d, d_a, d_b, n_a, n_b, bias_weight: float = 1.0, radius: int = 3,
                      scale: float = 1.0):
    """The two terms of the module notes, each pooled over a ``(2 radius +
    1)^2`` box (0: per pixel) in the metric's relative form: a term ``t_c``
    is pooled as ``t_c / (d_c^2 + 0.01)`` and multiplied back by ``d_c^2 +
    0.01``.  Pooling the absolute error lends a bright pixel's error to its
    dim neighbours, where divided by their small values it counted 1.5x the
    true relMSE on the sample scenes (docs/notes/oidn.md); pooled relative,
    the mean relative error of the map is that of the unpooled terms.

    d, d_a, d_b : (H, W, 3) denoised full mean and halves; n_a, n_b : (H, W)
    scale : factor on the variance constant (:func:`stratification_scale`;
        1.0: i.i.d. samples)
    Returns (variance, bias), both (H, W, 3) float64, finite and >= 0.
    """
    n_a = np.asarray(n_a, np.float64)
    n_b = np.asarray(n_b, np.float64)
    c = float(scale) * variance_constant(n_a, n_b)[..., None]
    n = np.where(n_a + n_b > 0, n_a + n_b, 1.0)[..., None]
    var = c * (d_a - d_b) ** 2
    mix = (n_a[..., None] * d_a + n_b[..., None] * d_b) / n
    split = ((n_a > 0) & (n_b > 0))[..., None]
    bias = np.where(split, float(bias_weight) * (d - mix) ** 2, 0.0)
    d = np.asarray(d, np.float64)
    den = d * d + REL_EPS
    return _pool(var / den, radius) * den, _pool(bias / den, radius) * den


def relative_map(error3, image, radius: int = 0) -> np.ndarray:
    """(H, W) ``mean_c error_c / (image_c^2 + 0.01)`` (the metric's relative
    form, with the denoised image standing in for the unknown reference),
    pooled over a ``(2 radius + 1)^2`` box."""
    img = np.asarray(image, np.float64)
    rel = (np.asarray(error3, np.float64) / (img * img + REL_EPS)).mean(axis=-1)
    return _pool(rel, radius)


def _pool(x, radius: int) -> np.ndarray:
    x = np.where(np.isfinite(x), np.maximum(x, 0.0), 0.0)
    return box_mean(x, int(radius)) if int(radius) > 0 else x


def recorrupted_halves(color, var, rng):
    """Two halves from a mean and its variance (Pang et al. 2021): ``x + s
    z`` and ``x - s z`` with ``s = sqrt(var)``, ``z ~ N(0, 1)`` per entry;
    entries with unknown (non-finite) variance get ``s = 0`` (both halves
    equal).  Returns (color_A, color_B)."""
    x = np.asarray(color, np.float64)
    v = np.broadcast_to(np.asarray(var, np.float64), x.shape)
    z = rng.standard_normal(x.shape) * np.sqrt(np.where(np.isfinite(v) & (v > 0), v, 0.0))
    return x + z, x - z


# ============================================================== method
def _params(params) -> Params:
    return params if isinstance(params, Params) else Params()


def _aux(features: dict):
    """(albedo, normal) arrays from a name -> (H, W, C) dict (None if absent)."""
    get = lambda k: None if features is None or features.get(k) is None else np.asarray(features[k])
    return get("albedo"), get("normal")


def estimate(color, features, halves, n_a, n_b, params: Params | None = None,
             denoiser=None, var_of_mean=None) -> MethodResult:
    """Denoise the full mean and both halves; image = D(full), error = the
    pooled variance + bias terms as one absolute squared error per pixel,
    ``e / mean_c (1 / (D_c^2 + 0.01))`` with ``e`` the pooled relative error
    (so ``core.metrics.relative_error_map(image, error)`` is ``e`` exactly),
    ``fit`` an :class:`OIDNFit` with ``e`` for the sampler.

    The image uses ``Params.prefilter``; the error is estimated with
    ``Params.map_prefilter``: where the two differ, from a second denoise of
    the full mean and the halves, all three with ``map_prefilter``, so that
    the bias term compares like with like (a fast-prefilter half against an
    accurate-prefilter whole would count the prefilter's own effect as
    bias).  Choice: the error of the fast-prefilter image stands in for the
    accurate image's (the accurate prefilter removes the auxiliary passes'
    noise first, so its image is expected to be no noisier: the estimate
    should err high, not low): 1 accurate call + 3 fast ones cost ~1.45
    accurate calls instead of 3 (:data:`FAST_CALL_SHARE`; measured in
    docs/notes/oidn.md, "the final error estimate").

    color : (H, W, 3) full mean; features : name -> (H, W, C) full means
    halves : ((color_A, features_A), (color_B, features_B)) or None (error
        0).  Each half is denoised with its own guides (albedo, normal): with
        the full-sample guides shared, D(A) and D(B) follow the same guide and
        agree far more than independent halves do (the estimate fell to 1/10
        of the true error on soft_shadows at 4 spp; docs/notes/oidn.md).
    n_a, n_b : (H, W) samples in each half (scalars broadcast)
    denoiser : ``f(color, albedo, normal, prefilter) -> (H, W, 3)``; default
        OIDN with ``params`` (tests pass a linear filter to check the constant)
    var_of_mean : (H, W, 3) variance of the full mean calibrated for the
        sequence's stratification (``Buffers.calibrated_variance``): the
        variance constant is scaled by :func:`stratification_scale`; None:
        i.i.d. halves (recorrupted ones), no scale
    """
    p = _params(params)
    t0 = time.perf_counter()
    if denoiser is None:
        def denoiser(c, a, n, prefilter):
            return oidn_filter(c, a, n, quality=p.quality, prefilter=prefilter, backend=p.backend)
    d = np.asarray(denoiser(color, *_aux(features), p.prefilter), np.float64)
    calls = 1
    if halves is None:
        zero = np.zeros_like(d)
        var = bias = zero
        d_err = d
        kind = "none"
    else:
        pre = p.map_prefilter
        d_err = d if pre == p.prefilter else np.asarray(denoiser(color, *_aux(features), pre), np.float64)
        (ca, fa), (cb, fb) = halves
        d_a = np.asarray(denoiser(ca, *_aux(fa), pre), np.float64)
        d_b = np.asarray(denoiser(cb, *_aux(fb), pre), np.float64)
        calls = 3 if d_err is d else 4
        shape = d.shape[:2]
        na, nb = np.broadcast_to(n_a, shape), np.broadcast_to(n_b, shape)
        scale = 1.0 if var_of_mean is None else stratification_scale(var_of_mean, ca, cb, na, nb, d_err)
        var, bias = dual_buffer_error(d_err, d_a, d_b, na, nb, p.bias_weight, p.pool_radius, scale)
        kind = "split"
    err3 = var + bias
    rel = relative_map(err3, d_err)
    seconds = time.perf_counter() - t0
    info = {"oidn_calls": calls, "oidn_seconds": seconds, "estimated_relmse": float(rel.mean())}
    if halves is not None:
        info["variance_scale"] = scale
        info["error_prefilter"] = p.map_prefilter
    weight = (1.0 / (d * d + REL_EPS)).mean(axis=-1)  # > 0: d finite, REL_EPS > 0
    return MethodResult(d, rel / weight, info, None, OIDNFit(rel, var, bias, kind))


def reconstruct(buf: Buffers, params: Params | None = None) -> MethodResult:
    """OIDN on all samples of ``buf``; the error from its stored halves
    (``buf.halves()``), else from recorrupted halves of the variance of the
    mean (none where no variance is known).  Pixels without noise
    (``core.method.exact_pixels``) keep their sample mean, with error 0."""
    return _keep_exact(_reconstruct(buf, params), buf)


def _keep_exact(res: MethodResult, buf: Buffers) -> MethodResult:
    """``res`` with exact pixels set to their sample mean and their error to
    0 (their variance of the mean).  Why: OIDN moves a noiseless flat
    background by 0.3-0.5 % (animated: 9.4 % of the pixels), which the
    consistency guard then had to undo; the image after the guard is the
    same, and the guard's share counts real contradictions only.  The
    sampler's fit is left as it is (``info['exact_fraction']``: their share)."""
    exact = exact_pixels(buf)
    res.info["exact_fraction"] = float(exact.mean())
    if not exact.any():
        return res
    mean = buf.color.mean
    res.image = np.where(exact[..., None], mean, res.image)
    res.error = np.where(exact, 0.0, res.error)
    return res


def _reconstruct(buf: Buffers, params: Params | None = None) -> MethodResult:
    p = _params(params)
    feats = {k: buf.features[k].mean for k in PASSES if k in buf.features}
    if not p.error_estimate:  # one call; the error is the undenoised variance (see Params)
        res = estimate(buf.color.mean, feats, None, 0.0, 0.0, p)
        var = buf.variance_of_mean()
        res.error = np.where(np.isfinite(var), var, 0.0).mean(axis=-1)
        res.info["error"] = "sample variance (error_estimate off)"
        return res
    halves = buf.halves()
    if halves is not None and np.any((halves[0][0] > 0) & (halves[1][0] > 0)):
        (na, ca, fa), (nb, cb, fb) = halves
        return estimate(buf.color.mean, feats, ((ca, fa), (cb, fb)), na, nb, p,
                        var_of_mean=buf.calibrated_variance())
    fvar = {k: buf.feature_variance(k) for k in feats}
    return _recorrupted(buf.color.mean, buf.variance_of_mean(), feats, fvar, p)


def map_result(buf: Buffers, params: Params | None = None) -> MethodResult:
    """The reconstruction the sampler reads between rounds (the optional
    member of ``core.method.Method``): :func:`reconstruct` with
    ``Params.map_prefilter`` as the prefilter: the same error estimate as
    :func:`reconstruct`'s, without its image's albedo and normal prefilter
    passes.  A round's map needs only the pooled relative error, on 8x8
    blocks, of an image that the rounds after it will change
    (docs/notes/oidn.md, map prefilter)."""
    p = _params(params)
    if p.map_prefilter != p.prefilter:
        p = dataclasses.replace(p, prefilter=p.map_prefilter)
    return reconstruct(buf, p)


def denoise(color, color_var, features=None, feature_var=None, n=None, params=None) -> MethodResult:
    """OIDN on plain arrays (the unified entry of every method module).

    color : (H, W, 3) sample mean; color_var : (H, W, 3) variance of the mean
    (non-finite: unknown); features / feature_var : dicts name -> (H, W, C)
    (albedo and normal are used; a feature without variance is shared by the
    halves); n : unused (recorrupted halves are equal, so the constant is 1/4
    whatever the count).  The error comes from
    recorrupted halves (:func:`recorrupted_halves`, seed 0: the same input
    gives the same output).
    """
    color = np.asarray(color, np.float64)
    feats = {k: np.asarray(v) for k, v in (features or {}).items() if k in PASSES}
    fvar = {k: v for k, v in (feature_var or {}).items() if k in feats}
    return _recorrupted(color, color_var, feats, fvar, _params(params))


def _recorrupted(color, var, feats, fvar, p: Params) -> MethodResult:
    v = np.broadcast_to(np.asarray(var, np.float64), np.shape(color))
    known = np.isfinite(v) & (v > 0)
    if not known.any():
        return estimate(color, feats, None, 0.0, 0.0, p)
    rng = np.random.default_rng(0)
    ca, cb = recorrupted_halves(color, v, rng)
    fa, fb = {}, {}
    for name, f in feats.items():
        if name in fvar:
            fa[name], fb[name] = recorrupted_halves(f, fvar[name], rng)
        else:
            fa[name] = fb[name] = f
    halves = ((ca, fa), (cb, fb))
    split = known.any(axis=-1).astype(np.float64)
    res = estimate(color, feats, halves, split, split, p)
    res.fit.halves = "recorrupted"
    return res


def sample_map(buf: Buffers, result: MethodResult | None, budget: int, params=None,
               state: dict | None = None) -> np.ndarray:
    """(H, W) int64 new samples summing to ``budget``: the water-filling
    top-up of the module notes on ``BLOCK`` x ``BLOCK`` blocks, from
    ``result``'s pooled relative error (:func:`map_result` here when None); one
    count per block, so the planner renders the map as it is.  Uniform with
    ``adaptive`` off or when no error is known."""
    p = _params(params)
    if not p.adaptive or budget <= 0:
        return allocate(np.ones(buf.shape), budget)
    if result is None:
        result = map_result(buf, p)
    rel = result.fit.relative if isinstance(result.fit, OIDNFit) else \
        relative_map(np.repeat(result.error[..., None], 3, axis=-1), result.image, p.pool_radius)
    if state is not None:
        state["rounds"] = int(state.get("rounds", 0)) + 1
    n = np.where(np.isfinite(buf.n) & (buf.n >= 1.0), buf.n, 1.0)
    area = _blocks(np.ones(buf.shape), BLOCK)
    rel_b, n_b = _blocks(rel, BLOCK) / area, _blocks(n, BLOCK) / area
    u = float(p.uniform_fraction)
    adapt = int(round((1.0 - u) * budget))
    if p.allocation == "topup":
        add = topup(rel_b, n_b, adapt, p.rate, area)
    else:
        shape = (np.maximum(rel_b, 0.0) * n_b ** p.rate) ** (1.0 / (1.0 + p.rate))
        add = shape * adapt / max((shape * area).sum(), 1e-300)
    if not add.any():
        return allocate(np.ones(buf.shape), budget)
    add = add + (budget - adapt) / area.sum()
    return _block_counts(add, area, budget, buf.shape, BLOCK)


#: side of the blocks the map is made on: the planner's default smallest
#: region (``Options.min_task_size``); a map varying inside a block would be
#: rounded up to the block's maximum, and at ~1 spp per round the planner then
#: falls back to a uniform full-frame task (measured on the sample scenes)
BLOCK = 8


def _blocks(x, s: int) -> np.ndarray:
    """Sums of ``x`` (H, W) over ``s`` x ``s`` blocks aligned to the top-left
    corner (the last row/column of blocks may be smaller)."""
    h, w = x.shape
    hb, wb = -(-h // s), -(-w // s)
    pad = np.zeros((hb * s, wb * s))
    pad[:h, :w] = x
    return pad.reshape(hb, s, wb, s).sum(axis=(1, 3))


def _block_counts(add, area, budget: int, shape, s: int) -> np.ndarray:
    """Integer per-pixel counts, one per block, from the blocks' float
    additions per pixel ``add``: floors first, then +1 per pixel for the
    blocks with the largest remainders while a whole block fits the budget;
    the last few samples go to the first pixels of the next block in that
    order, so the total is exactly ``budget``."""
    base = np.floor(add).astype(np.int64)
    left = int(budget) - int((base * area).sum())
    order = np.argsort(-(add - base), axis=None, kind="stable")
    partial = None
    for idx in order:
        if left <= 0:
            break
        a = int(area.flat[idx])
        if a <= left:
            base.flat[idx] += 1
            left -= a
        elif partial is None:
            partial = (idx, left)
            left = 0
    h, w = shape
    out = np.repeat(np.repeat(base, s, axis=0), s, axis=1)[:h, :w].copy()
    if partial is not None:
        by, bx = np.unravel_index(partial[0], base.shape)
        blk = out[by * s:(by + 1) * s, bx * s:(bx + 1) * s].reshape(-1)
        blk[:partial[1]] += 1
        out[by * s:(by + 1) * s, bx * s:(bx + 1) * s] = blk.reshape(out[by * s:(by + 1) * s,
                                                                         bx * s:(bx + 1) * s].shape)
    if left < 0 or out.sum() > budget:  # more blocks than budget: fall back to pixels
        return allocate(np.repeat(np.repeat(add, s, 0), s, 1)[:h, :w], budget)
    return out


def topup(rel, n, budget: int, rate: float, area=None) -> np.ndarray:
    """Float additions per pixel ``max(T_i - n_i, 0)`` with targets ``T_i =
    lambda a_i^(1/(1+p))``, ``a_i = rel_i n_i^p`` (module notes; bisection on
    ``lambda``), such that ``sum_i area_i * add_i = budget`` (``area``: pixels
    each entry stands for, default 1).  ``n <= 0`` counts as one sample; a
    map without error gives zeros."""
    n = np.asarray(n, np.float64)
    n = np.where(np.isfinite(n) & (n >= 1.0), n, 1.0)
    area = np.ones(n.shape) if area is None else np.asarray(area, np.float64)
    rel = np.where(np.isfinite(rel) & (rel > 0), rel, 0.0)
    if budget <= 0 or not rel.any():
        return np.zeros(n.shape)
    p = float(rate)
    shape = (rel * n ** p) ** (1.0 / (1.0 + p))
    shape = shape / shape.max()
    spent = lambda lam: (np.maximum(lam * shape - n, 0.0) * area).sum()
    lo, hi = 0.0, 1.0
    while spent(hi) < budget:
        lo, hi = hi, hi * 2.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if spent(mid) >= budget:
            hi = mid
        else:
            lo = mid
        if hi - lo <= 1e-12 * hi:
            break
    return np.maximum(hi * shape - n, 0.0)


class _Uniform:
    """``oidn`` with uniform sampling (``Params.adaptive`` off): the loop
    renders the whole budget in its initial pass and OIDN denoises it, the
    peer of Cycles' Denoise checkbox run through our code."""

    NAME = "oidn-uniform"
    PASSES = PASSES
    Params = Params
    ADAPTIVE = False
    SAMPLER_USES_RESULT = False

    @staticmethod
    def reconstruct(buf, params=None) -> MethodResult:
        return reconstruct(buf, params)

    @staticmethod
    def sample_map(buf, result, budget, params=None, state=None) -> np.ndarray:
        return allocate(np.ones(buf.shape), budget)


#: the uniform variant as a Method object (module constants cannot follow a
#: parameter): pass it to ``AdaptiveRun(..., method=UNIFORM)``
UNIFORM = _Uniform()


def method_for(params) -> object:
    """The Method to run for ``params`` (a Params or a dict): this module, or
    :data:`UNIFORM` when ``adaptive`` is off."""
    p = params if isinstance(params, Params) else params_from_dict(Params, params or {})
    if not p.adaptive:   # through the Params: "false" from a job file or the command line is False
        return UNIFORM
    import sys
    return sys.modules[__name__]

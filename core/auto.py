"""Method ``auto``: choose per scene, from the initial pass's samples alone,
which reconstruction and which sampling pay at the run's budget.

Candidates are the reconstructions (sample mean, ``oidn``, ``lp``, ``awr``,
``rhf``), each with uniform sampling or its own adaptive sampler (the sample
mean's is ``var``).  Nothing here reads a reference.

Error at the initial pass, by cross-validation between sample halves
---------------------------------------------------------------------
The initial pass renders ``K >= 4`` sample subsets; the even ones form half A,
the odd ones half B (each with at least two groups, so every method sees a
variance estimate).  On a few tiles ``R(A)`` and ``R(B)`` are reconstructed
and scored against the *other* half's sample mean, with the metric's weights
``w = 1 / (m^2 + 0.01)`` (``m``: the 3x3 mean of all samples, a noise-free
stand-in for the reference):

    CV_R = E w [(R(A) - B)^2 + (R(B) - A)^2] / 2 = E w MSE(R at n/2) + E w Var(B)

since the scoring half is unbiased and R(A) does not read B.  The halves are
samples of one stratified sequence, so their noise is correlated:
``cov(A, B) = r Var(A)`` with ``r = 2^(1 - e) - 1`` from the stratification
exponent ``e`` the initial pass measures (:func:`halves_correlation`), and
``CV_mean = E w (A - B)^2 = 2 (1 - r) E w Var(A)``:

    relMSE_mean(n/2) = CV_mean / (2 (1 - r)),

the denoisers' terms in :func:`score_tile`, each mean clamped below by its
standard error (a reconstruction cannot be told from error-free by less).  This
is the dual-buffer cross-validation NFOR (Bitterli et al. 2016) uses to select
between filters, applied per method.  The tiles are small and spread over the
frame, a batch of them side by side in one image per reconstruction call
(:func:`mosaic`); the sample mean, which needs no reconstruction, is scored on
every stored tile.

Error at the budget
-------------------
``relMSE_R(N) = relMSE_R(n/2) (n / 2N)^p_R`` with the rate ``p_R`` of
:data:`RATES`: for the sample mean the stratification exponent the loop
measures on the initial pass (``Buffers.exponent``), for the denoisers the
slopes measured on the sample scenes (docs/notes/auto.md).  Adaptive sampling
divides it by the gain of the best allocation of the rest of the budget over
the frame's blocks, from the pooled relative variance of the initial pass
(:func:`adaptive_allocation`; capped per pixel as the loop caps it).

Time and the choice
-------------------
Render time ``t (N P + tasks c)`` with ``t`` seconds per pixel-sample from the
initial pass and ``c`` the loop's task cost (``Options.task_cost``); plus each
reconstruction's cost on this machine (``fixed + per_pixel * pixels``, measured
once on synthetic frames and cached: :func:`reconstruction_costs`), paid once
(uniform sampling) or once per iteration as well (adaptive samplers that read
the reconstruction).  The candidate with the largest predicted equal-error
speed-up over plain Cycles wins:

    S = T_mean(N) (relMSE_mean(N) / relMSE_R(N))^(1 / p_mean) / T_R(N),

the benchmark's measure (the time plain Cycles needs for the candidate's
error over the candidate's time).  The sample mean (S = 1) is a candidate, so a
choice never predicts worse than plain Cycles.  Batches of tiles are scored
(the first always) until the choice has spent ``Params.cv_share`` of the
predicted render time; within the first batch the candidates are scored in
the order ``Params.candidates`` lists them (OIDN first by default, the
strongest on the sample scenes) and those the budget leaves are not
candidates (reported as ``unscored``).  Choice: a frame that renders in a
fraction of a second cannot repay scoring every reconstruction
(docs/notes/auto.md), so its choice is between the sample mean and the first
denoiser listed.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from .buffers import Buffers
from .filters import box_mean
from .method import MethodResult, param
from .metrics import REL_EPS
from .oidn import FAST_CALL_SHARE

NAME = "auto"
ADAPTIVE = True
SAMPLER_USES_RESULT = False

#: reconstruction -> (adaptive method, its uniform variant) registered names;
#: "mean" is the sample mean (plain Cycles / Schalk's var sampler)
RECONSTRUCTIONS = ("mean", "oidn", "lp", "awr", "rhf")
SAMPLINGS = ("auto", "uniform", "adaptive")

#: relMSE ~ n^-p of each reconstruction under uniform sampling, over the span
#: auto extrapolates (half the initial pass, 2 spp in two 1-spp groups, to the
#: budget): slopes from the reconstruction of a half against the reference to
#: the benchmark's uniform-<method> runs at 8 and 16 spp, median over the six
#: sample scenes (docs/notes/auto.md); the sample mean's is measured per scene
#: (Buffers.exponent)
RATES = {"oidn": 0.89, "lp": 1.08, "awr": 1.09, "rhf": 1.33}

#: filter calls one reconstruction makes, relative to the one call the cost
#: model times (OIDN with the accurate prefilter): oidn's reconstruct makes
#: that call for its image and estimates the error from three calls with the
#: fast prefilter (the whole and both halves, ``Params.map_prefilter``),
#: except uniform + OIDN as auto runs it (candidate_params)
CALLS = {"oidn": 1.0 + 3.0 * FAST_CALL_SHARE}

#: the same for the reconstruction an adaptive round reads (the method's
#: ``map_result``): the three fast calls of the error estimate only
MAP_CALLS = {"oidn": 3.0 * FAST_CALL_SHARE}

CV_MARGIN = 4  # pixels of context around each scored tile
NOISELESS = 1e-10  # half-budget relMSE of the sample mean below which the image counts as noise-free


@dataclass
class Params:
    """Parameters of ``auto``."""

    candidates: str = param("mean,oidn,lp,awr,rhf", "reconstructions to choose from, comma separated "
                            "(mean: the plain sample mean); fewer: a faster choice",
                            label="Candidates")
    sampling: str = param("auto", "sampling to choose from: auto predicts whether adaptive sampling "
                          "pays; uniform or adaptive fixes it", choices=SAMPLINGS, label="Sampling")
    cv_share: float = param(0.1, "most time the choice may spend, as a share of the predicted "
                            "render time: candidates are scored in the order listed until it is "
                            "spent (one batch of tiles and the first candidate always); more: "
                            "more candidates and a steadier choice on fast renders",
                            0.0, 10.0, label="Choice Time Share")
    tile: int = param(16, "side of the square tiles the candidates are scored on, pixels", 8, 512,
                      label="Tile Size")
    max_tiles: int = param(32, "most tiles scored", 1, 4096, label="Max Tiles")
    batch: int = param(3, "tiles reconstructed together, side by side in one image (one call "
                       "per candidate and half pays the fixed costs once); the first batch is "
                       "always scored", 1, 64, label="Tiles per Batch")

    def __post_init__(self):
        if self.sampling not in SAMPLINGS:
            raise ValueError(f"auto parameter sampling={self.sampling!r} must be one of "
                             f"{', '.join(SAMPLINGS)}")
        names = candidate_names(self.candidates)
        bad = [n for n in names if n not in RECONSTRUCTIONS]
        if bad or not names:
            raise ValueError(f"auto parameter candidates={self.candidates!r}: choose from "
                             f"{', '.join(RECONSTRUCTIONS)}")


def candidate_names(text: str) -> list:
    return [t.strip() for t in str(text).split(",") if t.strip()]


def _module(name: str):
    from . import methods
    return methods.get("uniform" if name == "mean" else name)


#: every pass a candidate reads (the initial pass renders them all)
PASSES: tuple = ("normal", "albedo", "depth")


def method(reconstruction: str, sampling: str):
    """The Method object of a candidate (what the loop runs after the choice)."""
    from . import methods, oidn, oracle
    if reconstruction == "mean":
        return methods.get("var" if sampling == "adaptive" else "uniform")
    base = methods.get(reconstruction)
    if sampling == "adaptive":
        return base
    if reconstruction == "oidn":
        return oidn.UNIFORM
    return oracle.UniformSampling(base)


def resolve(chosen: str):
    """The Method of a candidate's name as :func:`candidate_label` wrote it
    (for ``--resume``)."""
    for r in RECONSTRUCTIONS:
        for s in ("uniform", "adaptive"):
            if candidate_label(r, s) == chosen:
                return method(r, s)
    raise ValueError(f"auto: unknown chosen method {chosen!r}")


def candidate_label(reconstruction: str, sampling: str) -> str:
    """The name a candidate runs under (the loop's method NAME)."""
    return method(reconstruction, sampling).NAME


# ------------------------------------------------------------------ costs
COST_SIZES = (48, 160)  # sides of the synthetic frames the cost model is fitted on


def cost_cache_path() -> str:
    """Where measured reconstruction costs are kept: ``$CYCLES_ADAPTIVE_CACHE``,
    else the platform's user cache folder (``%LOCALAPPDATA%``,
    ``~/Library/Caches``, ``$XDG_CACHE_HOME`` or ``~/.cache``)."""
    env = os.environ.get("CYCLES_ADAPTIVE_CACHE")
    if env:
        return os.path.join(env, "costs.json")
    home = os.path.expanduser("~")
    if sys.platform == "win32":
        base = os.environ.get("LOCALAPPDATA") or os.path.join(home, "AppData", "Local")
    elif sys.platform == "darwin":
        base = os.path.join(home, "Library", "Caches")
    else:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(home, ".cache")
    return os.path.join(base, "cycles_adaptive", "costs.json")


def _cost_key(name: str) -> str:
    """A machine and code fingerprint: a cost is re-measured when the
    method's source, numpy or the machine changes."""
    import platform
    mod = sys.modules.get(_module(name).__name__)
    src = getattr(mod, "__file__", "") or ""
    try:
        with open(src, "rb") as fh:
            digest = hashlib.sha256(fh.read()).hexdigest()[:16]
    except OSError:
        digest = "unknown"
    return f"{name}|{digest}|{np.__version__}|{platform.machine()}|{os.cpu_count()}"


def _synthetic(side: int, seed: int = 0) -> Buffers:
    """A noisy synthetic frame of four one-sample subsets with every pass
    (for timing only)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:side, 0:side] / max(side, 1)
    base = np.dstack([0.2 + 0.6 * xx, 0.3 + 0.4 * yy, 0.5 + 0.0 * xx])
    feats = {"albedo": np.clip(base, 0, 1), "depth": (1.0 + xx)[..., None],
             "normal": np.dstack([0.0 * xx, np.sin(yy), np.cos(yy)])}
    colors = [np.clip(base * (1.0 + 0.5 * rng.standard_normal(base.shape)), 0, None) for _ in range(4)]
    return Buffers.from_subsets(colors, [1] * 4, [feats] * 4)


def measure_cost(name: str) -> dict:
    """Seconds of one reconstruction as ``fixed + per_pixel * pixels``, fitted
    on synthetic frames of ``COST_SIZES`` (best of two after a warm-up)."""
    bufs = [_synthetic(s) for s in COST_SIZES]
    _reconstruct(name, bufs[0])  # warm-up: imports, OIDN device, caches
    times = []
    for b in bufs:
        best = np.inf
        for _ in range(2):
            t0 = time.perf_counter()
            _reconstruct(name, b)
            best = min(best, time.perf_counter() - t0)
        times.append(best)
    px = [s * s for s in COST_SIZES]
    per = max((times[1] - times[0]) / (px[1] - px[0]), 0.0)
    fixed = max(times[0] - per * px[0], 0.0)
    return {"fixed": float(fixed), "per_pixel": float(per)}


def reconstruction_costs(names) -> dict:
    """name -> {"fixed", "per_pixel"} seconds of one reconstruction on this
    machine: measured once (:func:`measure_cost`) and kept in
    :func:`cost_cache_path` (a JSON file; unreadable or stale entries are
    measured again)."""
    path = cost_cache_path()
    try:
        with open(path, encoding="utf-8") as fh:
            cache = json.load(fh)
        if not isinstance(cache, dict):
            cache = {}
    except (OSError, ValueError):
        cache = {}
    out, changed = {}, False
    for name in names:
        key = _cost_key(name)
        entry = cache.get(key)
        if not (isinstance(entry, dict) and all(isinstance(entry.get(k), (int, float))
                                                for k in ("fixed", "per_pixel"))):
            entry = measure_cost(name)
            cache[key] = entry
            changed = True
        out[name] = {"fixed": float(entry["fixed"]), "per_pixel": float(entry["per_pixel"])}
    if changed:
        try:
            from .io import write_text
            os.makedirs(os.path.dirname(path), exist_ok=True)
            write_text(path, json.dumps(cache, indent=1, sort_keys=True))
        except OSError:
            pass  # a read-only cache folder: measured again next time
    return out


def reconstruction_seconds(cost: dict, pixels: int) -> float:
    return float(cost["fixed"] + cost["per_pixel"] * pixels)


# ------------------------------------------------------------------ tiles
def cv_regions(height: int, width: int, params: Params | None = None) -> list:
    """Scoring tiles as ``(x0, y0, x1, y1)`` crops (interior plus up to
    ``CV_MARGIN`` pixels of context), in the order they are scored: a
    stratified sweep (a coarse grid first, then between), so any prefix
    spreads over the frame.  A frame no larger than one tile is one crop."""
    p = params or Params()
    t = int(p.tile)
    # a tiled frame keeps a pixel beyond every crop's margin, so no crop
    # touches the frame's edge (:func:`_interior` reads a touching side as unmargined)
    edge = 2 * CV_MARGIN + 2
    if height < t + edge or width < t + edge:
        return [(0, 0, int(width), int(height))]
    ny, nx = max(1, (height - edge) // t), max(1, (width - edge) // t)
    oy = (height - ny * t) // 2
    ox = (width - nx * t) // 2
    # van der Corput order over the grid cells: spread-out prefixes
    cells = [(i, j) for i in range(ny) for j in range(nx)]
    order = sorted(range(len(cells)), key=lambda c: _radical_inverse(c * 7919 % max(len(cells), 1) + 1))
    out = []
    for c in order[: int(p.max_tiles)]:
        i, j = cells[c]
        y0, x0 = oy + i * t, ox + j * t
        out.append((max(0, x0 - CV_MARGIN), max(0, y0 - CV_MARGIN),
                    min(width, x0 + t + CV_MARGIN), min(height, y0 + t + CV_MARGIN)))
    return out


def _radical_inverse(i: int) -> float:
    f, r = 0.5, 0.0
    while i:
        r += f * (i & 1)
        i >>= 1
        f *= 0.5
    return r


def _interior(crop, height: int, width: int):
    """Slices of the scored interior within a crop (the context margin cut
    where the crop does not touch the frame's edge)."""
    x0, y0, x1, y1 = crop
    top = 0 if y0 == 0 else CV_MARGIN
    left = 0 if x0 == 0 else CV_MARGIN
    bottom = (y1 - y0) - (0 if y1 == height else CV_MARGIN)
    right = (x1 - x0) - (0 if x1 == width else CV_MARGIN)
    return slice(top, max(top + 1, bottom)), slice(left, max(left + 1, right))


@dataclass
class Context:
    """What the loop knows when it asks for a choice.

    spp : the run's budget (mean samples per pixel); initial_spp : rendered so far
    render_seconds : the initial pass's render time; tasks : its renders
    iterations, task_cost, max_pixel_share, min_task_size : the loop's settings
    exponent : the stratification exponent measured on the initial pass
    """

    spp: float
    initial_spp: float
    pixels: int
    render_seconds: float
    tasks: int
    iterations: int
    task_cost: float
    max_pixel_share: float
    min_task_size: int
    exponent: float = 1.0
    target_error: float = 0.0


@dataclass
class Selection:
    """The choice: the Method to run, its parameters and the report
    (JSON-able; ``report["params"]`` repeats the parameters for ``--resume``)."""

    method: object
    report: dict = field(default_factory=dict)
    params: dict = field(default_factory=dict)


def _guard(reconstruction: str) -> dict:
    """OIDN runs without the loop's consistency guard: it removes fireflies,
    which the guard puts back, more so the more sample groups a pixel has
    (docs/notes/oidn.md: uniform + OIDN on cornell at 8 spp 2.29e-3 without,
    2.50e-3 with it); the other reconstructions keep ``Options.guard_z``."""
    return {"guard_z": 0.0} if reconstruction == "oidn" else {}


def candidate_params(reconstruction: str, sampling: str, target_error: float = 0.0) -> dict:
    """Parameters auto runs a candidate with: the defaults, except that
    uniform sampling + OIDN skips OIDN's own error estimate (two more calls
    per reconstruction, which only an adaptive sampler or a target needs):
    what Cycles' Denoise costs, one call."""
    if reconstruction == "oidn" and sampling == "uniform":
        return {"adaptive": False, "error_estimate": bool(target_error > 0)}
    return {}


# ------------------------------------------------------------- prediction
def _halves(subsets, features):
    """Half A (even subsets) and half B (odd) of one crop as Buffers."""
    out = []
    for part in (subsets[0::2], subsets[1::2]):
        colors = [s[0] for s in part]
        counts = [s[2] for s in part]
        feats = [{k: s[1][k] for k in features if k in s[1]} for s in part]
        out.append(Buffers.from_subsets(colors, counts, feats))
    return out


def mosaic(crops: list, subset_data: list, height: int, width: int):
    """Several crops side by side in one image, so that each candidate
    reconstructs a whole batch in one call per half (its fixed cost paid
    once, the tiles spread over the frame): ``(subsets, mask)`` with the
    mosaic's subsets as (color, features, count) and ``mask`` (h, w) True on
    the crops' scored interiors.  Cells of a grid (the fewest empty cells,
    then the squarest), each a crop
    padded to the largest by repeating its edge (padding is never scored);
    the crops' margins keep the interiors' context, so a seam lies at least
    ``CV_MARGIN`` pixels from a scored pixel."""
    k = len(crops)
    ch = max(y1 - y0 for x0, y0, x1, y1 in crops)
    cw = max(x1 - x0 for x0, y0, x1, y1 in crops)
    # the fewest empty cells, then the squarest grid
    cols = min(range(int(np.ceil(np.sqrt(k))), k + 1), key=lambda c: (-(-k // c) * c - k, c))
    rows = -(-k // cols)
    n_sub = len(subset_data[0])
    mask = np.zeros((rows * ch, cols * cw), bool)
    colors = [np.zeros((rows * ch, cols * cw, 3)) for _ in range(n_sub)]
    feats = [{key: np.zeros((rows * ch, cols * cw) + np.shape(v)[2:]) for key, v in subset_data[0][s][1].items()}
             for s in range(n_sub)]
    # empty cells (k not a multiple of cols) repeat the first crop, unscored
    cells = list(range(k)) + [0] * (rows * cols - k)
    for c, i in enumerate(cells):
        x0, y0, x1, y1 = crops[i]
        r0, c0 = (c // cols) * ch, (c % cols) * cw
        pad = ((0, ch - (y1 - y0)), (0, cw - (x1 - x0)))
        for s, (color, fs, _) in enumerate(subset_data[i]):
            colors[s][r0:r0 + ch, c0:c0 + cw] = np.pad(color, pad + ((0, 0),), mode="edge")
            for key, v in fs.items():
                v = np.asarray(v)
                feats[s][key][r0:r0 + ch, c0:c0 + cw] = np.pad(v, pad + ((0, 0),) * (v.ndim - 2), mode="edge")
        if c < k:
            iy, ix = _interior(crops[i], height, width)
            mask[r0:r0 + ch, c0:c0 + cw][iy, ix] = True
    counts = [subset_data[0][s][2] for s in range(n_sub)]
    return [(colors[s], feats[s], counts[s]) for s in range(n_sub)], mask


def score_tile(subsets, crop, height, width, names, exponent: float = 1.0, mask=None,
               deadline: float | None = None):
    """Per-pixel estimates of each reconstruction's relMSE at half the
    initial samples on one crop's interior (module notes), with the
    reconstruction's seconds and model dimension.

    ``subsets``: list of (color (h, w, 3), features dict, count).  The
    denoisers' terms carry a control variate: in ``d_R - d_mean/2`` the
    halves' squared noise cancels, but the product ``w (A - T)(B - T)`` of
    their noise stays and dominates the terms' spread; it is subtracted with
    ``T`` replaced by the best candidate's own reconstruction of each half,
    ``w (A - R*(A))(B - R*(B))``.  R*(A) reads only A, so that product's mean
    is the halves' covariance (the same share as in ``d_mean / 2``: the two
    cancel, whatever the stratification) plus the best candidate's squared
    bias ``b*^2``: ``E terms_R = MSE_R - b*^2``, the offset common to every
    candidate (the plain difference's lower bound guards a large one:
    :func:`combine_scores`).  The former stand-in ``T = (R*(A) + R*(B)) / 2``
    added ``c - v/2`` (``c`` the covariance of R*(A) with A): 1.3-1.9x over
    the true half-budget error on the sample scenes (docs/notes/auto.md).
    ``mask`` (a :func:`mosaic`'s): score these pixels of the subsets' image
    instead of the crop's interior.  ``deadline`` (a ``time.perf_counter``
    value): once it has passed, the candidates after the first reconstruction
    scored are left out of the returned dict (the choice's time budget)."""
    features = [k for k in subsets[0][1]]
    buf_a, buf_b = _halves(subsets, features)
    for b in (buf_a, buf_b):
        b.exponent = exponent
    idx = mask if mask is not None else _interior(crop, height, width)
    ca, cb = buf_a.color.mean[idx], buf_b.color.mean[idx]
    w, d_mean, var_half = _mean_terms(subsets, idx, ca, cb, exponent)
    out = {"mean": {"terms": var_half, "seconds": 0.0, "dimension": None}}
    images = {}
    for name in names:
        if name == "mean":
            continue
        t0 = time.perf_counter()
        if images and deadline is not None and t0 >= deadline:
            break
        ra, rb = _reconstruct(name, buf_a), _reconstruct(name, buf_b)
        seconds = time.perf_counter() - t0
        ia, ib = _image(ra)[idx], _image(rb)[idx]
        images[name] = (ia, ib)
        d = _finite(w * ((ia - cb) ** 2 + (ib - ca) ** 2) / 2.0)
        out[name] = {"terms": d - d_mean / 2.0, "plain": d - var_half, "seconds": seconds,
                     "dimension": _mean_dim(ra, rb), "raw": float(d.mean())}
    if images:
        best = min(images, key=lambda k: out[k]["raw"])
        cross = _finite(w * (ca - images[best][0]) * (cb - images[best][1]))
        for name in images:
            out[name]["terms"] = out[name]["terms"] - cross
    return out


def _mean_terms(subsets, idx, ca, cb, exponent: float):
    """(weights, ``w (A - B)^2``, the sample mean's per-pixel relMSE at half
    the samples) on the pixels ``idx``.  The halves' noise is correlated (one
    stratified sequence): ``E (A - B)^2 = 2 Var(A) (1 - r)`` with ``r`` of
    :func:`halves_correlation`."""
    n = sum(float(s[2]) for s in subsets)
    whole = sum(float(s[2]) * s[0] for s in subsets) / max(n, 1e-12)
    w = 1.0 / (box_mean(np.clip(whole, 0.0, None), 1)[idx] ** 2 + REL_EPS)
    d_mean = _finite(w * (ca - cb) ** 2)
    return w, d_mean, d_mean / (2.0 * (1.0 - halves_correlation(exponent)))


def mean_terms(subsets, crop, height: int, width: int, exponent: float = 1.0) -> np.ndarray:
    """The sample mean's per-pixel relMSE at half the samples on one crop's
    interior (no reconstruction: cheap on every stored crop)."""
    iy, ix = _interior(crop, height, width)
    a, b = (sum(float(s[2]) * s[0][iy, ix] for s in part) / max(sum(float(s[2]) for s in part), 1e-12)
            for part in (subsets[0::2], subsets[1::2]))
    return _mean_terms(subsets, (iy, ix), a, b, exponent)[2]


def halves_correlation(exponent: float) -> float:
    """Correlation ``r`` of the halves' noise, ``cov(A, B) / Var(A)``, from
    the stratification exponent ``e`` (``Var(mean of n) ~ n^-e``): the whole
    ``(A + B) / 2`` has variance ``Var(A) (1 + r) / 2 = Var(A) 2^-e``, so
    ``r = 2^(1 - e) - 1`` (0 for independent samples, e = 1; clamped to
    (-0.9, 0.9])."""
    e = float(exponent) if np.isfinite(exponent) else 1.0
    return float(np.clip(2.0 ** (1.0 - e) - 1.0, -0.9, 0.9))


def _reconstruct(name: str, buf: Buffers) -> MethodResult:
    """One candidate's image of ``buf``; oidn as one filter call (its error
    estimate, two more calls, is not scored: see ``CALLS``)."""
    if name == "oidn":
        from . import oidn
        p = oidn.Params()
        aux = [buf.features[k].mean if k in buf.features else None for k in ("albedo", "normal")]
        img = oidn.oidn_filter(buf.color.mean, *aux, quality=p.quality, prefilter=p.prefilter,
                               backend=p.backend)
        return MethodResult(img, np.zeros(buf.shape))
    return _module(name).reconstruct(buf, None)


def _image(res: MethodResult) -> np.ndarray:
    return np.where(np.isfinite(res.image), res.image, 0.0)


def _finite(x):
    return np.where(np.isfinite(x), x, 0.0)


def _mean_dim(ra, rb):
    dims = [r.dimension for r in (ra, rb) if r.dimension is not None and np.isfinite(r.dimension)]
    return float(np.mean(dims)) if dims else None


def _clamped(terms: np.ndarray) -> dict:
    """Mean of per-pixel terms clamped below by its standard error."""
    rel = float(terms.mean())
    err = float(terms.std() / np.sqrt(terms.size)) if terms.size > 1 else abs(rel)
    return {"relmse_half": max(rel, err, 1e-12), "stderr": err}


def combine_scores(tiles: list) -> dict:
    """Per reconstruction, over the scored tiles: the half-budget relMSE
    (mean of the per-pixel terms, clamped below by its standard error: an
    error that small cannot be told from zero), its standard error, the
    seconds spent and the model dimension.  The plain terms subtract the
    correlation-corrected variance of a half (``d_R - Var(A)``)."""
    out = {}
    for name in tiles[0]:
        terms = np.concatenate([t[name]["terms"].ravel() for t in tiles])
        rel = float(terms.mean()) if terms.size else 0.0
        err = float(terms.std() / np.sqrt(terms.size)) if terms.size > 1 else abs(rel)
        if "plain" in tiles[0][name]:
            # the control variate drops the best candidate's squared bias; the
            # plain difference keeps it, unbiased but noisy: its lower 2-sigma
            # bound takes over where it is the larger
            plain = np.concatenate([t[name]["plain"].ravel() for t in tiles])
            p_se = float(plain.std() / np.sqrt(plain.size)) if plain.size > 1 else 0.0
            lower = float(plain.mean()) - 2.0 * p_se if plain.size else 0.0
            if lower > rel:
                rel, err = lower, p_se
        dims = [t[name]["dimension"] for t in tiles if t[name]["dimension"] is not None]
        out[name] = {"relmse_half": max(rel, err, 1e-12), "stderr": err,
                     "seconds": float(sum(t[name]["seconds"] for t in tiles)),
                     "dimension": float(np.mean(dims)) if dims else None}
    return out


def adaptive_allocation(rel_var, initial_spp: float, spp: float, rate: float, max_share: float,
                        block: int):
    """Predicted error ratio uniform / adaptive for the rest of the budget,
    and the (H, W) extra samples per pixel of that allocation.

    ``rel_var`` (H, W): the initial pass's relative variance of the mean; its
    block means ``a_b`` are the error coefficients (``e_b(n) = a_b n^-p``).
    The rest, ``M = spp - initial_spp`` per pixel, goes to ``m_b = min(s M,
    lambda a_b^(1/(1+p)))`` (the optimum of ``sum a_b m_b^-p`` for a fixed
    total, capped at ``s`` = the loop's max pixel share), ``lambda`` set so
    the mean is M.  The gain is ``sum a_b spp^-p / sum a_b (n0 + m_b)^-p``
    (1.0 when nothing remains or nothing is known)."""
    v = np.where(np.isfinite(rel_var) & (rel_var > 0), rel_var, 0.0)
    n0, m_total = float(initial_spp), float(spp) - float(initial_spp)
    h, w = v.shape
    if m_total <= 0 or not np.any(v > 0):
        return 1.0, np.full((h, w), max(m_total, 0.0))
    bs = max(1, int(block))
    hb, wb = -(-h // bs), -(-w // bs)
    pad = np.zeros((hb * bs, wb * bs))
    cnt = np.zeros_like(pad)
    pad[:h, :w], cnt[:h, :w] = v, 1.0
    area = cnt.reshape(hb, bs, wb, bs).sum(axis=(1, 3))
    a = pad.reshape(hb, bs, wb, bs).sum(axis=(1, 3)) / np.maximum(area, 1.0)
    p = max(float(rate), 1e-3)
    shape_ = np.power(np.maximum(a, 1e-30), 1.0 / (1.0 + p))
    cap = max_share * m_total if max_share > 0 else np.inf
    total = m_total * area.sum()
    lo, hi = 0.0, 64.0 * total / max(float((shape_ * area).sum()), 1e-300)
    for _ in range(80):  # bisection on lambda: the capped allocation's mean = M
        lam = 0.5 * (lo + hi)
        if (np.minimum(cap, lam * shape_) * area).sum() > total:
            hi = lam
        else:
            lo = lam
    m = np.minimum(cap, hi * shape_)
    m *= total / max(float((m * area).sum()), 1e-300)
    uni = float((area * a).sum()) * float(spp) ** -p
    ada = float((area * a * np.power(n0 + m, -p)).sum())
    per_pixel = np.repeat(np.repeat(m, bs, axis=0), bs, axis=1)[:h, :w]
    return (float(uni / ada) if ada > 0 else 1.0), per_pixel


def planned_tasks(extra, iterations: int, min_size: int, task_cost: float) -> int:
    """Region renders the loop's planner makes for the allocation ``extra``
    spread over ``iterations`` equal rounds (:func:`core.regions.plan_within`
    on one round's map, times the rounds)."""
    from . import regions
    from .pipeline import MAX_BEYOND_MAP
    it = max(1, int(iterations))
    counts = np.floor(np.asarray(extra, np.float64) / it + 0.5).astype(np.int64)
    if counts.sum() <= 0:
        return it
    plan = regions.plan_within(counts, min_size=min_size, task_cost=task_cost, max_beyond=MAX_BEYOND_MAP)
    return it * max(1, len(plan.tasks))


def render_seconds(ctx: Context) -> tuple:
    """(seconds per pixel-sample, predicted seconds of plain Cycles at the
    budget) from the initial pass: its renders' time over their samples plus
    one task cost (``Options.task_cost`` pixel-samples) per render."""
    t_ps = ctx.render_seconds / max(ctx.initial_spp * ctx.pixels + ctx.tasks * ctx.task_cost, 1.0)
    return t_ps, t_ps * ctx.spp * ctx.pixels


def predict(scores: dict, ctx: Context, rel_var, params: Params, costs: dict) -> list:
    """Every candidate's predicted relMSE, seconds and speed-up at the budget
    (module notes); sorted best first.  ``costs``: :func:`reconstruction_costs`."""
    n_half = ctx.initial_spp / 2.0
    beta = max(float(ctx.exponent), 0.5)
    t_ps, t_plain = render_seconds(ctx)
    e_mean = scores["mean"]["relmse_half"] * (n_half / ctx.spp) ** beta
    samplings = ("uniform", "adaptive") if params.sampling == "auto" else (params.sampling,)
    rows = []
    # a first pass without measurable noise leaves nothing to reconstruct:
    # every candidate's error is the mean's, and time decides
    noiseless = scores["mean"]["relmse_half"] <= NOISELESS
    for name, s in scores.items():
        rate = beta if name == "mean" or noiseless else RATES[name]
        e_uni = (scores["mean"] if noiseless else s)["relmse_half"] * (n_half / ctx.spp) ** rate
        one = 0.0 if name == "mean" else reconstruction_seconds(costs[name], ctx.pixels)
        for sampling in samplings:
            mod = method(name, sampling)
            cheap = candidate_params(name, sampling, ctx.target_error).get("error_estimate", True) is False
            recon = one * (1.0 if cheap else CALLS.get(name, 1.0))
            if sampling == "uniform":
                e = e_uni
                # the rest of the budget in one full-frame render, then one reconstruction
                secs = t_plain + t_ps * ctx.task_cost + recon
            else:
                gain, extra = adaptive_allocation(rel_var, ctx.initial_spp, ctx.spp, rate,
                                                  ctx.max_pixel_share, ctx.min_task_size)
                e = e_uni / gain
                per_iter = (one * MAP_CALLS.get(name, CALLS.get(name, 1.0))) if mod.SAMPLER_USES_RESULT else 0.0
                tasks = planned_tasks(extra, ctx.iterations, ctx.min_task_size, ctx.task_cost)
                secs = t_plain + t_ps * ctx.task_cost * tasks + ctx.iterations * per_iter + recon
            speedup = (t_plain * (e_mean / max(e, 1e-300)) ** (1.0 / beta)) / max(secs, 1e-12)
            rows.append({"name": mod.NAME, "reconstruction": name, "sampling": sampling,
                         "relmse": float(e), "seconds": float(secs), "speedup": float(speedup),
                         "gain": float(e_uni / e),
                         "relmse_half": float(s["relmse_half"]), "stderr_half": float(s["stderr"]),
                         "rate": float(rate)})
    rows.sort(key=lambda r: -r["speedup"])
    return rows


def select(crops: list, subset_data: list, ctx: Context, rel_var, params: Params | None = None,
           height: int | None = None, width: int | None = None) -> Selection:
    """Score the candidates on the tiles (``crops[i]`` with ``subset_data[i]``
    = the initial subsets' (color, features, count) on that crop), predict,
    choose (module notes).  Fewer than two subsets per half: no
    cross-validation is possible and the choice is OIDN with uniform sampling
    (the strongest reconstruction measured on the sample scenes), said in the
    report."""
    p = params or Params()
    names = candidate_names(p.candidates)
    if "mean" not in names:
        names = ["mean"] + names
    if not crops or len(subset_data[0]) < 4:
        rec = "oidn" if "oidn" in names else (names[1] if len(names) > 1 else "mean")
        m = method(rec, "uniform")
        params = candidate_params(rec, "uniform", ctx.target_error)
        return Selection(m, {"chosen": m.NAME, "params": params, **_guard(rec), "candidates": [],
                             "why": f"the initial pass has {len(subset_data[0]) if subset_data else 0} "
                                    f"sample subsets; cross-validation needs 4 (--subsets 4): "
                                    f"{m.NAME} by default"}, params)
    t0 = time.perf_counter()
    t_plain = render_seconds(ctx)[1]
    tiles, scored = [], 0
    step = max(1, int(p.batch))
    listed = names
    for i in range(0, len(crops), step):
        subs, mask = mosaic(crops[i:i + step], subset_data[i:i + step], height, width)
        # the first batch scores the candidates in their listed order until the
        # budget is spent (the first reconstruction always); later batches the same ones
        deadline = t0 + p.cv_share * t_plain if i == 0 else None
        tiles.append(score_tile(subs, None, height, width, names, ctx.exponent, mask=mask,
                                deadline=deadline))
        names = [n for n in names if n in tiles[0]]
        scored += len(crops[i:i + step])
        if time.perf_counter() - t0 >= p.cv_share * t_plain:
            break
    unscored = [n for n in listed if n not in names]
    scores = combine_scores(tiles)
    # the sample mean needs no reconstruction: scored on every stored crop
    mean_all = np.concatenate([mean_terms(subs, crop, height, width, ctx.exponent).ravel()
                               for crop, subs in zip(crops, subset_data)])
    if mean_all.size:
        scores["mean"] = {**scores["mean"], **_clamped(mean_all)}
    rows = predict(scores, ctx, rel_var, p, reconstruction_costs([n for n in names if n != "mean"]))
    best = rows[0]
    chosen = method(best["reconstruction"], best["sampling"])
    params = candidate_params(best["reconstruction"], best["sampling"], ctx.target_error)
    extra = _guard(best["reconstruction"])
    runner = rows[1] if len(rows) > 1 else None
    why = (f"highest predicted equal-error speed-up over plain Cycles: {best['speedup']:.2f}x "
           f"(relMSE {best['relmse']:.2e} in {best['seconds']:.2f} s)")
    if runner is not None:
        why += f"; next {runner['name']} {runner['speedup']:.2f}x"
    why += f"; {scored} tile(s) cross-validated in {time.perf_counter() - t0:.2f} s"
    if unscored:
        why += (f"; not scored within the choice's time ({p.cv_share:g} of the predicted "
                f"{t_plain:.2f} s render): {', '.join(unscored)}")
    return Selection(chosen, {"chosen": chosen.NAME, "params": params, "candidates": rows, "why": why,
                              "tiles": scored, "seconds": time.perf_counter() - t0,
                              "unscored": unscored, **extra}, params)


# ---------------------------------------------------- Method members
NO_CHOICE = ("auto chooses from a render's initial pass (its separate sample subsets); "
             "to reconstruct saved buffers, name a method")


def reconstruct(buf: Buffers, params=None) -> MethodResult:
    """``auto`` has no reconstruction of its own: the loop replaces it by its
    choice after the initial pass (:func:`select`).  ValueError otherwise."""
    raise ValueError(NO_CHOICE)


def sample_map(buf: Buffers, result, budget: int, params=None, state=None) -> np.ndarray:
    """Never asked: the loop samples with the chosen method.  ValueError."""
    raise ValueError(NO_CHOICE)


def denoise(color, color_var, features=None, feature_var=None, n=None, params=None) -> MethodResult:
    """Plain arrays hold no separate sample subsets to cross-validate:
    ValueError (name a method)."""
    raise ValueError(NO_CHOICE)

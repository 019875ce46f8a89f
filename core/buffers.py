"""Per-pixel sample statistics: the one shape of data every method consumes.

Cycles gives no per-sample output and no variance pass.  We render K *sample
subsets* (disjoint ranges of the sample sequence, which merge exactly into one
render: tests/test_executor.py) and treat each
subset render as one group of ``n_i`` samples with mean ``mu_i``.  Groups are
merged with Chan's parallel update (Chan, Golub, LeVeque 1979)::

    n    = n_a + n_b
    mean = mean_a + (mean_b - mean_a) * n_b / n
    M2   = M2_a + M2_b + (mean_b - mean_a)^2 * n_a * n_b / n

Starting each group at ``M2 = 0`` makes ``M2`` the *between-group* sum of
squares, for which ``E[M2] = sigma^2 * (k - 1)`` where ``sigma^2`` is the
per-sample variance and ``k`` the number of merged groups (each merge adds one
degree of freedom whatever the group sizes).  Hence

    per-sample variance     s^2   = M2 / (k - 1)
    variance of the mean    s^2/n = M2 / ((k - 1) n)

With one group (k = 1) no variance estimate exists: ``sample_variance`` returns
``+inf`` there and ``has_variance`` is False, so methods can tell.

The same statistics are kept for every feature pass (albedo, normal, depth,
position ...), because the reconstruction methods need the variance of features
too (RHF Eq. 5, LP's feature prefilter).

Two disjoint halves (:class:`Half`): each merged group also goes, whole, to
one of two halves of the pixel's samples, the one with fewer samples so far
(ties: half A), decided before the group's samples are seen.  Only half A is
stored (count and means); half B is the rest, ``mean_B = (n mean - n_A
mean_A) / (n - n_A)``.  Dual-buffer estimates (``core/oidn.py``: denoise each
half, compare) need the halves to be independent, which whole groups are.
The statistics above do not depend on the halves.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Feature passes known to the pipeline: name -> channel count.
FEATURE_CHANNELS = {
    "albedo": 3,
    "normal": 3,
    "depth": 1,
    "position": 3,
    "vector": 4,
    "glossy": 3,
    "transmission": 3,
    "object_index": 1,
    "alpha": 1,
}

#: a depth at or above this is "infinite" (Blender's Z pass writes 1e10 where no
#: surface was hit)
FAR_DEPTH = 1e9

#: Luminance weights (Rec. 709), used for relative errors and the var sampler.
LUMA = np.array([0.2126, 0.7152, 0.0722])


@dataclass
class Stat:
    """Running mean and between-group sum of squares of one pass.

    mean : (H, W, C) float64
    m2   : (H, W, C) float64, Chan/Welford M2 over sample-subset groups
    """

    mean: np.ndarray
    m2: np.ndarray

    def copy(self) -> "Stat":
        return Stat(self.mean.copy(), self.m2.copy())


@dataclass
class Half:
    """Half A of each pixel's sample groups (see the module notes).

    n : (H, W) float64 samples in half A
    color : (H, W, 3) float64 mean of half A's samples (0 where n = 0)
    features : dict name -> (H, W, C) float64 half-A means of the feature passes
    """

    n: np.ndarray
    color: np.ndarray
    features: dict = field(default_factory=dict)

    def copy(self) -> "Half":
        return Half(self.n.copy(), self.color.copy(), {k: v.copy() for k, v in self.features.items()})


@dataclass
class Buffers:
    """Accumulated samples of one frame.

    Attributes
    ----------
    n : (H, W) float64
        Samples per pixel.
    k : (H, W) float64
        Number of sample-subset groups merged into each pixel.
    color : Stat
        Combined pass, RGB.
    features : dict[str, Stat]
        Feature passes by name (see ``FEATURE_CHANNELS``).
    half : Half or None
        Half A of the disjoint halves (module notes); None when unknown (e.g.
        buffers read from a file), and then :meth:`halves` returns None.
    exponent : float
        Convergence exponent of the sequence's error (``core/variance.py``),
        measured by the loop on its initial pass; 1.0 (i.i.d.) when unknown.
    """

    n: np.ndarray
    k: np.ndarray
    color: Stat
    features: dict = field(default_factory=dict)
    half: Half | None = None
    exponent: float = 1.0

    # ------------------------------------------------------------------ shape
    @property
    def shape(self) -> tuple:
        return self.n.shape

    @property
    def height(self) -> int:
        return int(self.n.shape[0])

    @property
    def width(self) -> int:
        return int(self.n.shape[1])

    # ------------------------------------------------------------ construction
    @classmethod
    def empty(cls, height: int, width: int, feature_names=()) -> "Buffers":
        """Buffers with no samples (n = 0, k = 0) for the given passes, with
        empty halves."""
        z = lambda c: Stat(np.zeros((height, width, c)), np.zeros((height, width, c)))
        chans = {f: FEATURE_CHANNELS.get(f, 3) for f in feature_names}
        return cls(
            n=np.zeros((height, width)),
            k=np.zeros((height, width)),
            color=z(3),
            features={f: z(c) for f, c in chans.items()},
            half=Half(np.zeros((height, width)), np.zeros((height, width, 3)),
                      {f: np.zeros((height, width, c)) for f, c in chans.items()}),
        )

    @classmethod
    def from_subsets(cls, colors, counts, features=None) -> "Buffers":
        """Merge K subset renders of one region.

        colors : sequence of K (H, W, 3) arrays, each the mean of its subset
        counts : sequence of K ints or (H, W) arrays, samples in each subset
        features : optional sequence of K dicts name -> (H, W, C)
        """
        if len(colors) == 0:
            raise ValueError("from_subsets needs at least one subset")
        h, w = np.asarray(colors[0]).shape[:2]
        names = list(features[0].keys()) if features else []
        out = cls.empty(h, w, names)
        for i, c in enumerate(colors):
            feats = features[i] if features else {}
            out.merge_group(np.asarray(c, np.float64), counts[i], feats)
        return out

    def copy(self) -> "Buffers":
        return Buffers(self.n.copy(), self.k.copy(), self.color.copy(),
                       {k: v.copy() for k, v in self.features.items()},
                       None if self.half is None else self.half.copy(), self.exponent)

    # ----------------------------------------------------------------- merging
    def merge_group(self, color, count, features=None, region=None) -> None:
        """Merge one subset render (a group of ``count`` samples) in place.

        color : (h, w, 3) mean of the group's samples
        count : int or (h, w) samples in the group (0 leaves a pixel as it is)
        features : dict name -> (h, w, C) group means of feature passes
        region : optional (x0, y0, x1, y1) pixel rectangle (top-left origin,
            exclusive upper bounds) the group covers; default the whole frame.
        """
        sl = _region_slice(region, self.shape)
        cnt = np.broadcast_to(np.asarray(count, np.float64), color.shape[:2])
        n_a = self.n[sl]
        n = n_a + cnt
        has = cnt > 0
        self._half_add(sl, cnt, np.asarray(color, np.float64), features)
        safe_n = np.where(n > 0, n, 1.0)
        wb = np.where(has, cnt / safe_n, 0.0)[..., None]
        cross = np.where(has, n_a * cnt / safe_n, 0.0)[..., None]
        _chan_update(self.color, sl, np.asarray(color, np.float64), wb, cross)
        for name, stat in self.features.items():
            if features is None or name not in features:
                raise KeyError(f"group lacks feature pass {name!r}")
            _chan_update(stat, sl, np.asarray(features[name], np.float64).reshape(
                stat.mean[sl].shape), wb, cross)
        self.n[sl] = n
        self.k[sl] = self.k[sl] + has

    def merge(self, other: "Buffers", region=None) -> None:
        """Merge accumulated buffers ``other`` (covering ``region``) in place.

        Chan's update for two groups each with their own M2; degrees of freedom
        add: k = k_a + k_b.
        """
        sl = _region_slice(region, self.shape)
        self._half_merge(sl, other)
        n_a, n_b = self.n[sl], other.n
        n = n_a + n_b
        safe_n = np.where(n > 0, n, 1.0)
        wb = (n_b / safe_n)[..., None]
        cross = (n_a * n_b / safe_n)[..., None]
        _chan_update(self.color, sl, other.color.mean, wb, cross, other.color.m2)
        for name, stat in self.features.items():
            o = other.features[name]
            _chan_update(stat, sl, o.mean, wb, cross, o.m2)
        self.n[sl] = n
        self.k[sl] = self.k[sl] + other.k

    # ------------------------------------------------------------------ halves
    def _half_add(self, sl, cnt, color, features, to_a=None) -> None:
        """Add a group (means ``color`` / ``features``, ``cnt`` samples) to
        half A where A has no more samples than B (or where ``to_a``), before
        ``self.n`` is updated."""
        h = self.half
        if h is None:
            return
        if to_a is None:
            to_a = 2.0 * h.n[sl] <= self.n[sl]
        add = np.where(to_a & (cnt > 0), cnt, 0.0)
        n_new = h.n[sl] + add
        w = np.where(add > 0, add / np.where(n_new > 0, n_new, 1.0), 0.0)[..., None]
        with np.errstate(invalid="ignore", over="ignore"):
            h.color[sl] = h.color[sl] + (color - h.color[sl]) * w
            for name, arr in h.features.items():
                f = features.get(name) if features else None
                if f is None:
                    continue
                f = np.asarray(f, np.float64).reshape(arr[sl].shape)
                arr[sl] = arr[sl] + (f - arr[sl]) * w
        h.n[sl] = n_new

    def _half_merge(self, sl, other: "Buffers") -> None:
        """Halves of ``self`` after merging ``other``: other's larger half goes
        to our smaller one where both are split; where ``other`` has no halves,
        it counts as one group (:meth:`_half_add`)."""
        if self.half is None:
            return
        oh = other.halves()
        if oh is None:
            feats = {k: v.mean for k, v in other.features.items()}
            self._half_add(sl, other.n, other.color.mean, feats)
            return
        (na, ca, fa), (nb, cb, fb) = oh
        a_small = 2.0 * self.half.n[sl] <= self.n[sl]
        big_is_a = na >= nb
        first = a_small == big_is_a  # where other's A goes to our A
        pick = lambda x, y, m: np.where(m[..., None] if x.ndim == 3 else m, x, y)
        n_to_a = pick(na, nb, first)
        c_to_a = pick(ca, cb, first)
        f_to_a = {k: pick(fa[k], fb[k], first) for k in fa if k in fb}
        self._half_add(sl, n_to_a, c_to_a, f_to_a, to_a=np.ones(n_to_a.shape, bool))

    def halves(self):
        """``((n_A, color_A, features_A), (n_B, color_B, features_B))`` of the
        disjoint halves, or None when they are unknown or inconsistent with
        the buffers (``n_A`` outside ``[0, n]``, shapes that differ).  Half B's
        means are ``(n mean - n_A mean_A) / n_B`` (0 where ``n_B = 0``)."""
        h = self.half
        if h is None or h.n.shape != self.n.shape or h.color.shape != self.color.mean.shape:
            return None
        if not np.all((h.n >= 0) & (h.n <= self.n)):
            return None
        nb = self.n - h.n
        safe = np.where(nb > 0, nb, 1.0)[..., None]
        rest = lambda whole, a: np.where(nb[..., None] > 0, (self.n[..., None] * whole
                                                             - h.n[..., None] * a) / safe, 0.0)
        with np.errstate(invalid="ignore", over="ignore"):
            cb = rest(self.color.mean, h.color)
            fa, fb = {}, {}
            for name, arr in h.features.items():
                st = self.features.get(name)
                if st is None or st.mean.shape != arr.shape:
                    continue
                fa[name] = arr
                fb[name] = rest(st.mean, arr)
        return (h.n, h.color, fa), (nb, cb, fb)

    # -------------------------------------------------------------- statistics
    @property
    def has_variance(self) -> np.ndarray:
        """(H, W) bool: at least two groups, so a variance estimate exists."""
        return self.k >= 2

    def sample_variance(self, stat: Stat | None = None) -> np.ndarray:
        """Per-sample variance s^2 = M2 / (k - 1); +inf where k < 2."""
        stat = self.color if stat is None else stat
        dof = (self.k - 1.0)[..., None]
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.where(dof > 0, stat.m2 / np.where(dof > 0, dof, 1.0), np.inf)
        return v

    def variance_of_mean(self, stat: Stat | None = None) -> np.ndarray:
        """Variance of the pixel mean, s^2 / n = M2 / ((k - 1) n); +inf where
        k < 2 or n = 0 (a NaN M2 stays NaN).  One (H, W, C) allocation: the
        methods call it on full frames."""
        stat = self.color if stat is None else stat
        ok = (self.k >= 2) & (self.n > 0)
        den = np.where(ok, (self.k - 1.0) * self.n, 1.0)[..., None]
        out = np.full(stat.m2.shape, np.inf)
        np.divide(stat.m2, den, out=out, where=ok[..., None])
        return out

    def calibrated_variance(self) -> np.ndarray:
        """Variance of the pixel mean corrected for the sequence's
        stratification (``exponent``) and pooled over feature-guided 5x5
        windows (:func:`core.variance.calibrated_variance_of_mean`); what the
        methods read.  +inf where no estimate exists, never NaN."""
        from .variance import calibrated_variance_of_mean
        return calibrated_variance_of_mean(self, self.exponent)

    def constant_features(self, names=None, rtol: float = 1e-6) -> tuple:
        """Feature passes (of ``names``, default all) that carry no
        information: on the pixels with samples every channel's finite means
        lie within ``rtol * (1 + max |value|)`` of each other (a flat floor's
        depth seen straight on, one material's albedo).  A pass with no finite
        value counts as constant."""
        has = self.n > 0
        out = []
        for name in (self.features if names is None else names):
            st = self.features.get(name)
            if st is None:
                continue
            v = st.mean[has]
            v = np.where(np.isfinite(v), v, np.nan)
            if v.size == 0 or np.all(np.isnan(v)):
                out.append(name)
                continue
            with np.errstate(invalid="ignore"):
                lo, hi = np.nanmin(v, axis=0), np.nanmax(v, axis=0)
            scale = 1.0 + np.nanmax(np.abs(v))
            if np.all(hi - lo <= rtol * scale):
                out.append(name)
        return tuple(out)

    def without(self, names) -> "Buffers":
        """A view of these buffers without the feature passes ``names`` (the
        arrays are shared, nothing is copied): what a method reads when those
        passes carry no information."""
        if not names:
            return self
        keep = {k: v for k, v in self.features.items() if k not in names}
        half = self.half
        if half is not None:
            half = Half(half.n, half.color, {k: v for k, v in half.features.items() if k not in names})
        return Buffers(self.n, self.k, self.color, keep, half, self.exponent)

    def feature(self, name: str) -> np.ndarray:
        return self.features[name].mean

    def feature_variance(self, name: str) -> np.ndarray:
        return self.variance_of_mean(self.features[name])


def _region_slice(region, shape):
    if region is None:
        return (slice(0, shape[0]), slice(0, shape[1]))
    x0, y0, x1, y1 = (int(v) for v in region)
    return (slice(y0, y1), slice(x0, x1))


def _chan_update(stat: Stat, sl, mean_b, wb, cross, m2_b=None):
    """Chan et al. parallel update of ``stat[sl]`` with group b, in place.
    Non-finite input propagates as it is (methods sanitise); no warnings."""
    with np.errstate(invalid="ignore", over="ignore"):
        mean_a = stat.mean[sl]
        delta = mean_b - mean_a
        stat.mean[sl] = mean_a + delta * wb
        upd = stat.m2[sl] + delta * delta * cross
        if m2_b is not None:
            upd = upd + m2_b
        stat.m2[sl] = upd


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) -> (...) Rec. 709 luminance."""
    return rgb @ LUMA


def is_background(position: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: pixels where no surface was hit.  Cycles writes Position
    exactly (0, 0, 0) there; with a depth pass the depth must also be 0 or
    "infinite" (>= ``FAR_DEPTH``), so a surface through the world origin is not
    taken for background.  ``position`` (H, W, 3), ``depth`` (H, W[, 1])."""
    bg = np.all(np.asarray(position) == 0.0, axis=-1)
    if depth is not None:
        d = np.asarray(depth)
        d = d[..., 0] if d.ndim == 3 else d
        bg &= (d == 0.0) | (d >= FAR_DEPTH)
    return bg

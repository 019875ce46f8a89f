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
    """

    n: np.ndarray
    k: np.ndarray
    color: Stat
    features: dict = field(default_factory=dict)

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
        """Buffers with no samples (n = 0, k = 0) for the given passes."""
        z = lambda c: Stat(np.zeros((height, width, c)), np.zeros((height, width, c)))
        return cls(
            n=np.zeros((height, width)),
            k=np.zeros((height, width)),
            color=z(3),
            features={f: z(FEATURE_CHANNELS.get(f, 3)) for f in feature_names},
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
                       {k: v.copy() for k, v in self.features.items()})

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

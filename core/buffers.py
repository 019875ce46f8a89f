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

import math
import threading
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
    # single-channel passes a scene's compositor may read (addon/compositor.py); the others have 3
    "z": 1,
    "mist": 1,
    "material_index": 1,
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
    gsum : (H, W) float64 or None
        ``sum_i n_i^(1 - exponent)`` over each pixel's groups (sizes ``n_i``),
        kept from :meth:`set_exponent` on, so the calibrated variance knows
        groups of unequal size (region renders after the initial pass);
        None: the groups are taken as equal (``n / k`` each).
    """

    n: np.ndarray
    k: np.ndarray
    color: Stat
    features: dict = field(default_factory=dict)
    half: Half | None = None
    exponent: float = 1.0
    gsum: np.ndarray | None = None

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
        z = lambda c: Stat(_zeros((height, width, c)), _zeros((height, width, c)))
        chans = {f: FEATURE_CHANNELS.get(f, 3) for f in feature_names}
        return cls(
            n=_zeros((height, width)),
            k=_zeros((height, width)),
            color=z(3),
            features={f: z(c) for f, c in chans.items()},
            half=Half(_zeros((height, width)), _zeros((height, width, 3)),
                      {f: _zeros((height, width, c)) for f, c in chans.items()}),
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
                       None if self.half is None else self.half.copy(), self.exponent,
                       None if self.gsum is None else self.gsum.copy())

    def set_exponent(self, exponent: float, sizes=None) -> None:
        """Set :attr:`exponent` and start keeping :attr:`gsum` for it.
        ``sizes``: the samples of the groups every pixel holds so far (the
        initial pass's full-frame subsets), used where a pixel has exactly
        that many groups; elsewhere the groups so far are taken as equal,
        ``k (n / k)^(1 - exponent)``."""
        self.exponent = float(exponent)
        g = self._equal_gsum(self.exponent)
        if sizes is not None and len(sizes) and all(float(m) > 0 for m in sizes):
            exact = float(sum(float(m) ** (1.0 - self.exponent) for m in sizes))
            same = (self.k == len(sizes)) & (self.n == float(sum(float(m) for m in sizes)))
            g = np.where(same, exact, g)
        self.gsum = g

    def _equal_gsum(self, exponent: float) -> np.ndarray:
        """:attr:`gsum` of these buffers with their groups taken as equal."""
        q = 1.0 - float(exponent)
        ok = (self.k > 0) & (self.n > 0)
        k = np.where(ok, self.k, 1.0)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            g = np.where(ok, k * np.power(np.where(ok, self.n, 1.0) / k, q), 0.0)
        return np.where(np.isfinite(g), g, 0.0)

    # ----------------------------------------------------------------- merging
    def merge_group(self, color, count, features=None, region=None) -> None:
        """Merge one subset render (a group of ``count`` samples) in place.

        color : (h, w, 3) mean of the group's samples
        count : int or (h, w) samples in the group (0 leaves a pixel as it is)
        features : dict name -> (h, w, C) group means of feature passes
        region : optional (x0, y0, x1, y1) pixel rectangle (top-left origin,
            exclusive upper bounds) the group covers; default the whole frame.

        Chan's update (module notes) per pixel, over row bands of the region
        on the controller's threads (:func:`core.parallel.run_bands`): each
        band updates its own rows, so the result is the same bit for bit for
        any thread count.  A missing feature pass is a KeyError raised before
        anything changes.
        """
        sl = _region_slice(region, self.shape)
        color = np.asarray(color)
        cnt = np.broadcast_to(np.asarray(count, np.float64), color.shape[:2])
        feats = {}
        for name, stat in self.features.items():
            if features is None or name not in features:
                raise KeyError(f"group lacks feature pass {name!r}")
            feats[name] = np.asarray(features[name]).reshape(stat.mean[sl].shape)
        hfeats = {}
        if self.half is not None and features:
            for name, arr in self.half.features.items():
                f = features.get(name)
                if f is not None:
                    hfeats[name] = feats[name] if name in feats else np.asarray(f).reshape(arr[sl].shape)
        y0 = sl[0].start

        def band(rows):
            r0, r1 = rows
            bs = (slice(y0 + r0, y0 + r1), sl[1])
            c = cnt[r0:r1]
            col = np.asarray(color[r0:r1], np.float64)
            shape = c.shape
            with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
                n_a = self.n[bs]
                n = np.add(n_a, c, out=_tmp("n", shape))
                has = np.greater(c, 0.0, out=_tmp("has", shape, bool))
                self._half_add(bs, c, col, {k: v[r0:r1] for k, v in hfeats.items()})
                safe_n = _where_positive(n, _tmp("safe", shape))
                wb = np.divide(c, safe_n, out=_tmp("wb", shape))
                lacks = np.logical_not(has, out=_tmp("lacks", shape, bool))
                np.copyto(wb, 0.0, where=lacks)
                cross = np.multiply(n_a, c, out=_tmp("cross", shape))
                np.divide(cross, safe_n, out=cross)
                np.copyto(cross, 0.0, where=lacks)
                wb, cross = wb[..., None], cross[..., None]
                _chan_update(self.color, bs, col, wb, cross)
                for name, stat in self.features.items():
                    _chan_update(stat, bs, np.asarray(feats[name][r0:r1], np.float64), wb, cross)
                self.n[bs] = n
                k = self.k[bs]
                np.add(k, has, out=k)
                if self.gsum is not None:  # this group's n_i^(1 - exponent)
                    g = self.gsum[bs]
                    np.add(g, np.where(has, np.power(np.where(has, c, 1.0), 1.0 - self.exponent), 0.0), out=g)

        _run_rows(band, self.n[sl].shape)

    def merge(self, other: "Buffers", region=None) -> None:
        """Merge accumulated buffers ``other`` (covering ``region``) in place.

        Chan's update for two groups each with their own M2; degrees of freedom
        add: k = k_a + k_b.  Over row bands as :meth:`merge_group` (the same
        bits for any thread count); a feature pass ``other`` lacks is a
        KeyError raised before anything changes.
        """
        sl = _region_slice(region, self.shape)
        for name in self.features:
            other.features[name]  # noqa: B018  (KeyError before any change)
        if self.gsum is not None:  # other's groups: its own record, else taken as equal
            same = other.gsum is not None and float(other.exponent) == self.exponent
            self.gsum[sl] += other.gsum if same else other._equal_gsum(self.exponent)
        # the halves of ``other`` exist for the whole region or not at all
        split = self.half is not None and other._halves_valid()
        y0 = sl[0].start

        def band(rows):
            r0, r1 = rows
            bs = (slice(y0 + r0, y0 + r1), sl[1])
            with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
                if self.half is not None:
                    self._half_merge(bs, other, rows, split)
                n_a, n_b = self.n[bs], other.n[r0:r1]
                shape = n_a.shape
                n = np.add(n_a, n_b, out=_tmp("n", shape))
                safe_n = _where_positive(n, _tmp("safe", shape))
                wb = np.divide(n_b, safe_n, out=_tmp("wb", shape))[..., None]
                cross = np.multiply(n_a, n_b, out=_tmp("cross", shape))
                np.divide(cross, safe_n, out=cross)
                cross = cross[..., None]
                _chan_update(self.color, bs, other.color.mean[r0:r1], wb, cross, other.color.m2[r0:r1])
                for name, stat in self.features.items():
                    o = other.features[name]
                    _chan_update(stat, bs, o.mean[r0:r1], wb, cross, o.m2[r0:r1])
                self.n[bs] = n
                k = self.k[bs]
                np.add(k, other.k[r0:r1], out=k)

        _run_rows(band, self.n[sl].shape)

    # ------------------------------------------------------------------ halves
    def _half_add(self, sl, cnt, color, features, to_a=None) -> None:
        """Add a group (means ``color`` / ``features``, ``cnt`` samples) to
        half A where A has no more samples than B (or where ``to_a``), before
        ``self.n`` is updated; in place on the rows ``sl``."""
        h = self.half
        if h is None:
            return
        hn = h.n[sl]
        shape = hn.shape
        if to_a is None:
            twice = np.multiply(hn, 2.0, out=_tmp("h_twice", shape))
            to_a = np.less_equal(twice, self.n[sl], out=_tmp("h_to_a", shape, bool))
        sel = np.greater(cnt, 0.0, out=_tmp("h_sel", shape, bool))
        np.logical_and(to_a, sel, out=sel)
        add = _tmp("h_add", shape)       # where(to_a & (cnt > 0), cnt, 0)
        add.fill(0.0)
        np.copyto(add, cnt, where=sel)
        n_new = np.add(hn, add, out=_tmp("h_n", shape))
        w = np.divide(add, _where_positive(n_new, _tmp("h_den", shape)), out=_tmp("h_w", shape))
        np.copyto(w, 0.0, where=np.logical_not(np.greater(add, 0.0, out=sel), out=sel))
        w = w[..., None]
        with np.errstate(invalid="ignore", over="ignore"):
            _toward(h.color[sl], color, w)
            for name, arr in h.features.items():
                f = features.get(name) if features else None
                if f is None:
                    continue
                a = arr[sl]
                _toward(a, np.asarray(f, np.float64).reshape(a.shape), w)
        h.n[sl] = n_new

    def _half_merge(self, sl, other: "Buffers", rows, split: bool) -> None:
        """Halves of ``self`` on rows ``sl`` after merging ``other`` (its rows
        ``rows``): other's larger half goes to our smaller one where both are
        split (``split``: :meth:`_halves_valid` of ``other``); otherwise
        ``other`` counts as one group (:meth:`_half_add`)."""
        if self.half is None:
            return
        r0, r1 = rows
        if not split:
            feats = {k: v.mean[r0:r1] for k, v in other.features.items()}
            self._half_add(sl, other.n[r0:r1], other.color.mean[r0:r1], feats)
            return
        (na, ca, fa), (nb, cb, fb) = other._halves_rows(r0, r1)
        a_small = 2.0 * self.half.n[sl] <= self.n[sl]
        big_is_a = na >= nb
        first = a_small == big_is_a  # where other's A goes to our A
        pick = lambda x, y, m: np.where(m[..., None] if x.ndim == 3 else m, x, y)
        n_to_a = pick(na, nb, first)
        c_to_a = pick(ca, cb, first)
        f_to_a = {k: pick(fa[k], fb[k], first) for k in fa if k in fb}
        self._half_add(sl, n_to_a, c_to_a, f_to_a, to_a=np.ones(n_to_a.shape, bool))

    def _halves_valid(self) -> bool:
        """Whether :meth:`halves` is defined: half A known, of the buffers'
        shapes, with ``0 <= n_A <= n`` everywhere."""
        h = self.half
        if h is None or h.n.shape != self.n.shape or h.color.shape != self.color.mean.shape:
            return False
        return bool(np.all((h.n >= 0) & (h.n <= self.n)))

    def _halves_rows(self, r0: int, r1: int, features: bool = True):
        """:meth:`halves` on rows ``r0:r1`` (validity not checked); without
        the feature passes' halves (empty dicts) unless ``features``."""
        h = self.half
        n, hn = self.n[r0:r1], h.n[r0:r1]
        nb = n - hn
        safe = np.where(nb > 0, nb, 1.0)[..., None]
        rest = lambda whole, a: np.where(nb[..., None] > 0, (n[..., None] * whole
                                                             - hn[..., None] * a) / safe, 0.0)
        with np.errstate(invalid="ignore", over="ignore"):
            cb = rest(self.color.mean[r0:r1], h.color[r0:r1])
            fa, fb = {}, {}
            for name, arr in (h.features.items() if features else ()):
                st = self.features.get(name)
                if st is None or st.mean.shape != arr.shape:
                    continue
                fa[name] = arr[r0:r1]
                fb[name] = rest(st.mean[r0:r1], arr[r0:r1])
        return (hn, h.color[r0:r1], fa), (nb, cb, fb)

    def halves(self):
        """``((n_A, color_A, features_A), (n_B, color_B, features_B))`` of the
        disjoint halves, or None when they are unknown or inconsistent with
        the buffers (``n_A`` outside ``[0, n]``, shapes that differ).  Half B's
        means are ``(n mean - n_A mean_A) / n_B`` (0 where ``n_B = 0``)."""
        if not self._halves_valid():
            return None
        return self._halves_rows(0, self.height)

    def color_halves(self):
        """``((n_A, color_A), (n_B, color_B))``: :meth:`halves` of the colour
        alone (the same values, without the feature passes' halves); None
        where :meth:`halves` is None."""
        if not self._halves_valid():
            return None
        (na, ca, _), (nb, cb, _) = self._halves_rows(0, self.height, features=False)
        return (na, ca), (nb, cb)

    # -------------------------------------------------------------- statistics
    @property
    def has_variance(self) -> np.ndarray:
        """(H, W) bool: at least two groups, so a variance estimate exists."""
        return self.k >= 2

    def sample_variance(self, stat: Stat | None = None, rows=None) -> np.ndarray:
        """Per-sample variance s^2 = M2 / (k - 1); +inf where k < 2.  ``rows``
        ``(r0, r1)``: those rows only (the same values)."""
        stat = self.color if stat is None else stat
        r = slice(None) if rows is None else slice(int(rows[0]), int(rows[1]))
        dof = (self.k[r] - 1.0)[..., None]
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.where(dof > 0, stat.m2[r] / np.where(dof > 0, dof, 1.0), np.inf)
        return v

    def variance_of_mean(self, stat: Stat | None = None, rows=None) -> np.ndarray:
        """Variance of the pixel mean, s^2 / n = M2 / ((k - 1) n); +inf where
        k < 2 or n = 0 (a NaN M2 stays NaN).  One (H, W, C) allocation: the
        methods call it on full frames.  ``rows`` ``(r0, r1)``: those rows
        only (the same values; row bands of the threaded callers)."""
        stat = self.color if stat is None else stat
        r = slice(None) if rows is None else slice(int(rows[0]), int(rows[1]))
        k, n, m2 = self.k[r], self.n[r], stat.m2[r]
        ok = (k >= 2) & (n > 0)
        den = np.where(ok, (k - 1.0) * n, 1.0)[..., None]
        out = np.full(m2.shape, np.inf)
        np.divide(m2, den, out=out, where=ok[..., None])
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
        has = (self.n > 0)[..., None]
        every = bool(has.all())
        out = []
        for name in (self.features if names is None else names):
            st = self.features.get(name)
            if st is None:
                continue
            # reductions in place, one plane at a time (numpy reduces a plane
            # ~20x faster than the (H, W) axes of an interleaved array); a
            # non-finite value anywhere makes lo or hi non-finite: then masked
            planes = [st.mean[..., c] for c in range(st.mean.shape[-1])]
            lo = hi = None
            if every and planes:
                lo, hi = np.array([p.min() for p in planes]), np.array([p.max() for p in planes])
            if lo is None or not (np.isfinite(lo).all() and np.isfinite(hi).all()):
                ok = has & np.isfinite(st.mean)
                counted = ok.any(axis=(0, 1))
                if not counted.any():
                    out.append(name)
                    continue
                if not counted.all():  # a channel with no finite value: its range is unknown
                    continue
                lo = np.min(st.mean, axis=(0, 1), where=ok, initial=np.inf)
                hi = np.max(st.mean, axis=(0, 1), where=ok, initial=-np.inf)
            if np.all(hi - lo <= rtol * (1.0 + max(np.abs(lo).max(), np.abs(hi).max()))):
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
        return Buffers(self.n, self.k, self.color, keep, half, self.exponent, self.gsum)

    def crop(self, x0: int, y0: int, x1: int, y1: int) -> "Buffers":
        """A copy of the rectangle [y0, y1) x [x0, x1) (clipped to the frame)
        as Buffers of its own: what a method reconstructs when a run measures
        its cost on part of the frame."""
        h, w = self.shape
        x0, x1 = max(0, int(x0)), min(w, int(x1))
        y0, y1 = max(0, int(y0)), min(h, int(y1))
        if x1 <= x0 or y1 <= y0:
            raise ValueError(f"crop ({x0}, {y0}, {x1}, {y1}) is empty in a {w}x{h} frame")
        sl = (slice(y0, y1), slice(x0, x1))
        stat = lambda s: Stat(s.mean[sl].copy(), s.m2[sl].copy())
        half = None if self.half is None else Half(self.half.n[sl].copy(), self.half.color[sl].copy(),
                                                   {k: v[sl].copy() for k, v in self.half.features.items()})
        return Buffers(self.n[sl].copy(), self.k[sl].copy(), stat(self.color),
                       {k: stat(v) for k, v in self.features.items()}, half, self.exponent,
                       None if self.gsum is None else self.gsum[sl].copy())

    def feature(self, name: str) -> np.ndarray:
        return self.features[name].mean

    def feature_variance(self, name: str) -> np.ndarray:
        return self.variance_of_mean(self.features[name])


def _region_slice(region, shape):
    if region is None:
        return (slice(0, shape[0]), slice(0, shape[1]))
    x0, y0, x1, y1 = (int(v) for v in region)
    return (slice(y0, y1), slice(x0, x1))


#: pixels per row band of the merges (rows = BAND_PIXELS // width): a band's
#: temporaries stay in the core's cache; shape only, never the thread count
BAND_PIXELS = 32768
#: below this many pixels a merge runs inline: threads do not pay (measured:
#: docs/notes/farm.md)
INLINE_PIXELS = 65536


def band_rows(width: int, pixels: int = BAND_PIXELS) -> int:
    """Rows per band for rows ``width`` pixels wide: about ``pixels`` per band."""
    return max(1, int(pixels) // max(1, int(width)))


def _run_rows(fn, shape) -> None:
    """``fn((r0, r1))`` over the row bands of an (h, w) region, on the
    controller's threads from :data:`INLINE_PIXELS` pixels on."""
    from . import parallel
    h, w = int(shape[0]), int(shape[1])
    if h * w == 0:
        return
    if h * w < INLINE_PIXELS:
        fn((0, h))
        return
    parallel.run_bands(fn, h, band_rows(w))


_SCRATCH = threading.local()
#: elements below which :func:`_tmp` allocates instead (no per-call lookups)
SCRATCH_MIN = 8192


def _tmp(name: str, shape, dtype=np.float64) -> np.ndarray:
    """This thread's scratch array ``name`` of ``shape`` (contents undefined):
    the merges' band temporaries, reused from band to band so they are not
    allocated (and page-faulted) again for every band.  Grows to the largest
    band seen; a few MB per thread."""
    size = math.prod(shape)
    if size < SCRATCH_MIN:  # small: malloc is cheap and faults nothing
        return np.empty(shape, dtype)
    pool = getattr(_SCRATCH, "arrays", None)
    if pool is None:
        pool = _SCRATCH.arrays = {}
    key = (name, dtype)
    buf = pool.get(key)
    if buf is None or buf.size < size:
        buf = pool[key] = np.empty(size, dtype)
    return buf[:size].reshape(shape)


def _zeros(shape) -> np.ndarray:
    """float64 zeros, written once here.  ``np.zeros`` maps its pages lazily,
    and the first merge's band threads then fault them in concurrently: at
    0.6 MP with the guides that merge took 0.57 s on two threads against
    0.21 s on one; written here (~0.07 s for the whole frame's buffers) it
    takes 0.08 s (docs/notes/loop-speed.md)."""
    out = np.empty(shape)
    out.fill(0.0)
    return out


def _where_positive(x: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``np.where(x > 0, x, 1.0)`` into ``out`` (the same values)."""
    out.fill(1.0)
    np.copyto(out, x, where=np.greater(x, 0.0, out=_tmp("positive", x.shape, bool)))
    return out


def _toward(a: np.ndarray, b, w) -> None:
    """``a <- a + (b - a) * w`` in place (one scratch temporary), the same
    bits as the expression."""
    d = np.subtract(b, a, out=_tmp("toward", a.shape))
    np.multiply(d, w, out=d)
    np.add(a, d, out=a)


def _chan_update(stat: Stat, sl, mean_b, wb, cross, m2_b=None):
    """Chan et al. parallel update of ``stat[sl]`` with group b, in place:
    ``mean += delta wb``, ``M2 += delta^2 cross (+ M2_b)`` with ``delta =
    mean_b - mean``, evaluated in the module notes' order (two of this thread's
    scratch arrays, :func:`_tmp`).  Non-finite input propagates as it is (methods
    sanitise); no warnings."""
    with np.errstate(invalid="ignore", over="ignore"):
        mean_a = stat.mean[sl]
        m2 = stat.m2[sl]
        delta = np.subtract(mean_b, mean_a, out=_tmp("delta", mean_a.shape))
        step = np.multiply(delta, wb, out=_tmp("step", mean_a.shape))
        np.add(mean_a, step, out=mean_a)
        np.multiply(delta, delta, out=delta)
        np.multiply(delta, cross, out=delta)
        np.add(m2, delta, out=m2)
        if m2_b is not None:
            np.add(m2, m2_b, out=m2)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) -> (...) float64 Rec. 709 luminance.

    Written out as ``r L0 + g L1 + b L2`` rather than ``rgb @ LUMA``: the
    matmul goes through BLAS, whose calls from two controller threads at once
    took twice as long as from one (OpenBLAS contends for its own threads),
    while element-wise products scale with the threads.  Same value up to
    the last bit (BLAS may fuse the multiply-adds)."""
    rgb = np.asarray(rgb, np.float64)
    if rgb.ndim < 1 or rgb.shape[-1] != 3:
        raise ValueError(f"luminance needs (..., 3) RGB, got shape {rgb.shape}")
    out = np.multiply(rgb[..., 0], LUMA[0])
    out += rgb[..., 1] * LUMA[1]
    out += rgb[..., 2] * LUMA[2]
    return out


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

"""Region re-render tasks: turn a per-pixel sample map into few Cycles border renders.

Cycles cannot render a per-pixel sample count, only a rectangle (border + crop)
with one sample count.  A pixel may be covered by several rectangles: the
samples add up, and because every task continues each pixel's sample sequence
(``sample_offset``, see :func:`assign_offsets`) the merged result is the same
as one render with the summed count.

Planner (:func:`plan`): a *layered quadtree* over blocks aligned to
``min_size`` pixels, chosen by an exact bottom-up cost minimisation, followed by
merging of equal tasks into bigger rectangles.

* Every quadtree node ``B`` with parent ``P`` either **splits**: it emits one
  task over ``B`` of ``min_B(counts) - min_P(counts)`` samples (the part shared
  by the whole block; the residual below it is handled by its four children), or
  **stops**: it emits one task of ``max_B(counts) - min_P(counts)`` samples, so
  every pixel of ``B`` gets ``max_B`` samples (the *overshoot* of ``B`` is
  ``sum_B(max_B - counts)``).  Leaves (``min_size`` blocks) always stop.  The
  sums telescope: a pixel's samples from its ancestors are ``min_P(counts)``
  of its deepest split ancestor, so the layered emission needs no residual map.
* Cost of a plan = ``task_cost * tasks + overshoot`` (both in pixel-samples).
  ``cost(B) = min(stop(B), split(B))`` with
  ``stop(B)  = task_cost*[max_B > min_P] + sum_B(max_B - counts)`` and
  ``split(B) = task_cost*[min_B > min_P] + sum_children cost(C)``;
  it is computed for all nodes of a level at once (bottom-up, ties stop), then
  the decisions are read top-down.  The plan is therefore the cheapest layered
  quadtree plan; in particular never worse than the fully split (exact at
  ``min_size``) plan.
* Merging: tasks with the same ``samples`` *and the same base* (the samples its
  pixels already received from earlier layers, ``min_P``) never overlap, so their
  union can be cut into rectangles freely: cells are joined into row runs and
  runs into rectangles ("rows then columns"), and also "columns then rows"; for
  each group the decomposition with fewer rectangles is kept.  Grouping by base
  keeps sample sequences contiguous: tasks are ordered by base, so when
  ``next_index`` is uniform beforehand (it is after the initial pass) every task
  sees a uniform ``next_index`` over its rectangle and :func:`assign_offsets`
  continues each pixel exactly, skipping no sample index.

Default ``task_cost``: measured with bpy 4.5 on this project's 2-core machine
(``tools/task_cost.py``): a least-squares line through border renders of 8x8 to
128x128 pixels at 1-8 spp gives a fixed cost of ~3 ms per render and ~3.2-3.8 us
per pixel-sample on the sample scenes (cornell, glossy), i.e. one render costs
as much as ~760-1040 pixel-samples.  The default is 1024; heavier scenes (more
us per pixel-sample) make a task relatively cheaper, so the value errs towards
fewer, larger renders only on light scenes.  (An earlier 0.02 s for a 32x32
border render included scene sync.)  The loop's ``Options.task_cost`` overrides it.

Border conversion: Blender computes the border in pixels as
``(int)(border_min_x * winx)`` in *single precision* with truncation (verified
under bpy 4.5: with ``border_max_x = 32/41`` on a 41-pixel-wide frame Cycles
renders 31 columns).  ``x0 / W`` rounded to float32 often lands one ulp below
``x0``, so :func:`border_from_pixels` nudges each coordinate up to the smallest
float32 whose product is ``>= x0``; truncation and rounding then both give back
exactly ``x0``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

#: default fixed cost of one region render, in pixel-samples (see module docstring)
DEFAULT_TASK_COST = 1024.0

_BIG = np.iinfo(np.int64).max // 4


# --------------------------------------------------------------------- border
def border_coord(p, n):
    """Normalised border coordinate for pixel boundary ``p`` of ``n`` pixels.

    Returns the smallest float32 value ``v >= p / n`` (as float64 array or float)
    such that Blender's ``(int)(v * n)`` in float32 arithmetic gives ``p``;
    ``float32(v * n)`` lies in ``[p, p + 1e-3)``, so rounding also gives ``p``.

    p : int or int array in [0, n];  n : int >= 1
    """
    p = np.asarray(p, np.int64)
    n32 = np.float32(n)
    v = (p / float(n)).astype(np.float32)
    for _ in range(4):
        low = (v * n32).astype(np.float32) < p.astype(np.float32)
        if not np.any(low):
            break
        v = np.where(low, np.nextafter(v, np.float32(np.inf)), v)
    v = np.clip(v, np.float32(0.0), np.float32(1.0))
    out = v.astype(np.float64)
    return float(out) if out.ndim == 0 else out


def blender_border_pixel(v, n):
    """Blender's pixel boundary for normalised border ``v`` of ``n`` pixels:
    ``(int)(float(v) * n)`` in float32 with truncation (render pipeline
    ``render_init_from_main``).  Array-friendly; used to check the conversion."""
    v32 = np.asarray(v, np.float64).astype(np.float32)
    prod = (v32 * np.float32(n)).astype(np.float32)
    out = np.trunc(prod).astype(np.int64)
    return int(out) if out.ndim == 0 else out


def border_from_pixels(x0: int, y0: int, x1: int, y1: int, width: int, height: int) -> dict:
    """Blender border (origin bottom-left, normalised) of a pixel rectangle.

    x0, y0, x1, y1 : rectangle, top-left origin, exclusive upper bounds, within
        the frame of ``width`` x ``height`` *rendered* pixels (resolution times
        percentage, ``resolution_x * resolution_percentage // 100``).
    Returns dict with ``border_min_x = x0/W``, ``border_max_x = x1/W``,
    ``border_min_y = (H - y1)/H``, ``border_max_y = (H - y0)/H``, each nudged
    (at most a few float32 ulps) so Blender's truncation gives these pixels back.
    """
    if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
        raise ValueError(f"rectangle {(x0, y0, x1, y1)} is empty or outside the "
                         f"{width}x{height} frame")
    return {
        "border_min_x": border_coord(x0, width),
        "border_max_x": border_coord(x1, width),
        "border_min_y": border_coord(height - y1, height),
        "border_max_y": border_coord(height - y0, height),
    }


def pixels_from_border(border: dict, width: int, height: int) -> tuple:
    """Inverse of :func:`border_from_pixels` as Blender computes it:
    (x0, y0, x1, y1), top-left origin."""
    bx0 = blender_border_pixel(border["border_min_x"], width)
    bx1 = blender_border_pixel(border["border_max_x"], width)
    by0 = blender_border_pixel(border["border_min_y"], height)
    by1 = blender_border_pixel(border["border_max_y"], height)
    return (bx0, height - by1, bx1, height - by0)


# ----------------------------------------------------------------------- task
@dataclass(frozen=True)
class RegionTask:
    """One region render.

    x0, y0, x1, y1 : pixel rectangle, top-left origin, exclusive upper bounds
        (x = column, y = row).
    samples : samples to render in it (> 0).
    frame : scene frame.
    offset : first sample index (Cycles ``sample_offset``) of the render.
    """

    x0: int
    y0: int
    x1: int
    y1: int
    samples: int
    frame: int = 0
    offset: int = 0

    @property
    def width(self) -> int:
        return self.x1 - self.x0

    @property
    def height(self) -> int:
        return self.y1 - self.y0

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def rect(self) -> tuple:
        return (self.x0, self.y0, self.x1, self.y1)

    def border(self, width: int, height: int) -> dict:
        """Blender's normalised border (origin bottom-left) for this task in a
        ``width`` x ``height`` frame; see :func:`border_from_pixels`."""
        return border_from_pixels(self.x0, self.y0, self.x1, self.y1, width, height)


@dataclass
class Plan:
    """Result of :func:`plan`.

    tasks : tuple of RegionTask, ordered by layer (base samples ascending), offset 0.
    covered : (H, W) int64, samples each pixel gets from ``tasks``.
    n_tasks : number of tasks.
    overshoot : ``covered.sum() - counts.sum()`` (>= 0), samples beyond the map.
    requested : ``counts.sum()`` of the (sanitised) map.
    """

    tasks: tuple
    covered: np.ndarray
    n_tasks: int
    overshoot: int
    requested: int


# ----------------------------------------------------------------------- plan
def _sanitize_counts(counts) -> np.ndarray:
    c = np.asarray(counts)
    if c.ndim != 2:
        raise ValueError(f"counts must be a 2-D (H, W) map, got shape {c.shape}")
    if c.dtype.kind in "fc":
        c = np.asarray(c, np.float64)
        c = np.where(np.isfinite(c) & (c > 0), np.ceil(np.minimum(c, 2.0 ** 52)), 0.0)
    c = np.asarray(c, np.int64)
    return np.maximum(c, 0)


def _pool2(a, op):
    """2x2 reduction of a (G, G) array with ``op`` (np.minimum / maximum / add)."""
    g = a.shape[0]
    if g == 1:
        return a
    b = a.reshape(g // 2, 2, g // 2, 2)
    return op(op(b[:, 0, :, 0], b[:, 0, :, 1]), op(b[:, 1, :, 0], b[:, 1, :, 1]))


def _up(a):
    """Nearest upsampling x2 in both axes."""
    return np.repeat(np.repeat(a, 2, axis=0), 2, axis=1)


def _runs(g, major, minor):
    """Join sorted cells (g, major, minor) into runs along ``minor``.

    Returns (g, major, lo, hi) with hi inclusive."""
    if g.size == 0:
        e = np.zeros(0, np.int64)
        return e, e, e, e
    order = np.lexsort((minor, major, g))
    g, major, minor = g[order], major[order], minor[order]
    start = np.ones(g.size, bool)
    start[1:] = (g[1:] != g[:-1]) | (major[1:] != major[:-1]) | (minor[1:] != minor[:-1] + 1)
    idx = np.flatnonzero(start)
    end = np.r_[idx[1:], g.size] - 1
    return g[idx], major[idx], minor[idx], minor[end]


def _rects(g, r, c):
    """Cells -> rectangles (g, r0, r1, c0, c1), inclusive, per group choosing the
    better of rows-then-columns and columns-then-rows."""
    out = []
    for rows_first in (True, False):
        if rows_first:
            rg, rmaj, lo, hi = _runs(g, r, c)         # row runs
        else:
            rg, rmaj, lo, hi = _runs(g, c, r)         # column runs
        # join runs with equal (lo, hi) in consecutive majors
        order = np.lexsort((rmaj, hi, lo, rg))
        rg, rmaj, lo, hi = rg[order], rmaj[order], lo[order], hi[order]
        start = np.ones(rg.size, bool)
        start[1:] = ((rg[1:] != rg[:-1]) | (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])
                     | (rmaj[1:] != rmaj[:-1] + 1))
        idx = np.flatnonzero(start)
        end = np.r_[idx[1:], rg.size] - 1
        gg, m0, m1, l0, l1 = rg[idx], rmaj[idx], rmaj[end], lo[idx], hi[idx]
        if rows_first:
            out.append((gg, m0, m1, l0, l1))
        else:
            out.append((gg, l0, l1, m0, m1))
    ngroups = int(g.max()) + 1 if g.size else 0
    n_a = np.bincount(out[0][0], minlength=ngroups)
    n_b = np.bincount(out[1][0], minlength=ngroups)
    use_b = n_b < n_a
    keep_a = ~use_b[out[0][0]]
    keep_b = use_b[out[1][0]]
    return tuple(np.concatenate([a[keep_a], b[keep_b]]) for a, b in zip(out[0], out[1]))


def paint(tasks, shape) -> np.ndarray:
    """(H, W) int64 samples per pixel from ``tasks`` (summed-area painting)."""
    h, w = shape
    diff = np.zeros((h + 1, w + 1), np.int64)
    if tasks:
        a = np.array([(t.x0, t.y0, t.x1, t.y1, t.samples) for t in tasks], np.int64)
        x0, y0, x1, y1, s = a.T
        np.add.at(diff, (y0, x0), s)
        np.add.at(diff, (y0, x1), -s)
        np.add.at(diff, (y1, x0), -s)
        np.add.at(diff, (y1, x1), s)
    return np.cumsum(np.cumsum(diff, axis=0), axis=1)[:h, :w]


def plan(counts, frame: int = 0, min_size: int = 8,
         task_cost: float = DEFAULT_TASK_COST) -> Plan:
    """Cover a per-pixel sample map with few region tasks (layered quadtree).

    Parameters
    ----------
    counts : (H, W) int
        Samples wanted per pixel.  Negative or non-finite entries count as 0;
        float entries are rounded up.
    frame : int
        Frame stored in every task.
    min_size : int, default 8
        Side of the smallest block (quadtree leaf, aligned to multiples of
        ``min_size`` from the top-left corner).  Smaller = closer to the map,
        more tasks.
    task_cost : float, default 1024
        Fixed cost of one task in pixel-samples; the planner minimises
        ``task_cost * tasks + overshoot`` (see module docstring).  0 gives the
        exact plan at ``min_size`` resolution.

    Returns
    -------
    Plan
        ``covered >= counts`` everywhere; ``covered == counts`` for a uniform
        map (one task) and, with ``task_cost = 0``, for any map constant on
        ``min_size``-aligned blocks; a zero map gives no tasks.  With
        ``task_cost > 0`` the plan's ``task_cost * tasks + overshoot`` is at
        most that of the exact ``min_size`` plan (merging only lowers it).
    """
    c = _sanitize_counts(counts)
    h, w = c.shape
    s = max(1, int(min_size))
    tc = float(task_cost) if np.isfinite(task_cost) and task_cost > 0 else 0.0
    requested = int(c.sum())
    if h == 0 or w == 0 or requested == 0:
        return Plan((), np.zeros((h, w), np.int64), 0, 0, requested)

    # ---- leaf statistics on the min_size grid (hl, wl), padded to (G, G)
    hl, wl = -(-h // s), -(-w // s)
    levels = int(np.ceil(np.log2(max(hl, wl)))) if max(hl, wl) > 1 else 0
    g = 1 << levels
    pad = np.zeros((hl * s, wl * s), bool)
    pad[:h, :w] = True
    cp = np.zeros((hl * s, wl * s), np.int64)
    cp[:h, :w] = c
    blocks = cp.reshape(hl, s, wl, s)
    valid = pad.reshape(hl, s, wl, s)
    mn = np.full((g, g), _BIG, np.int64)
    mx = np.full((g, g), -1, np.int64)
    sm = np.zeros((g, g), np.int64)
    cnt = np.zeros((g, g), np.int64)
    mn[:hl, :wl] = np.where(valid, blocks, _BIG).min(axis=(1, 3))
    mx[:hl, :wl] = np.where(valid, blocks, -1).max(axis=(1, 3))
    sm[:hl, :wl] = blocks.sum(axis=(1, 3))
    cnt[:hl, :wl] = valid.sum(axis=(1, 3))
    del cp, blocks, valid, pad

    # ---- pyramid: index 0 = leaves, index levels = root (1x1)
    pyr = [(mn, mx, sm, cnt)]
    for _ in range(levels):
        a, b, d, e = pyr[-1]
        pyr.append((_pool2(a, np.minimum), _pool2(b, np.maximum),
                    _pool2(d, np.add), _pool2(e, np.add)))

    def parent_min(lev):
        if lev == levels:
            return np.zeros((1, 1), np.int64)
        return _up(pyr[lev + 1][0])

    # ---- bottom-up cost, decisions
    split = [None] * (levels + 1)
    child_cost = None
    for lev in range(levels + 1):
        a, b, d, e = pyr[lev]
        mp = parent_min(lev)
        nonempty = e > 0
        over = np.where(nonempty, b.astype(np.float64) * e - d, 0.0)
        stop = np.where(nonempty, tc * (b > mp) + over, 0.0)
        if lev == 0:
            cost = stop
            split[lev] = np.zeros(a.shape, bool)
        else:
            spl = np.where(nonempty, tc * (a > mp) + _pool2(child_cost, np.add), 0.0)
            split[lev] = nonempty & (spl < stop)
            cost = np.where(split[lev], spl, stop)
        child_cost = cost

    # ---- top-down emission: (level, gi, gj, samples, base)
    emitted = []
    active = np.ones((1, 1), bool) & (pyr[levels][3] > 0)
    for lev in range(levels, -1, -1):
        a, b, d, e = pyr[lev]
        mp = parent_min(lev)
        sp = active & split[lev]
        st = active & ~split[lev]
        samples = np.where(sp, a - mp, np.where(st, b - mp, 0))
        gi, gj = np.nonzero((sp | st) & (samples > 0))
        if gi.size:
            emitted.append((lev, gi, gj, samples[gi, gj], mp[gi, gj]))
        if lev > 0:
            active = _up(sp)

    # ---- expand to leaf cells, group by (samples, base), merge into rectangles
    cg, cr, cc, keys_s, keys_b = [], [], [], [], []
    for lev, gi, gj, smp, base in emitted:
        size = 1 << lev
        br, bc = min(size, hl), min(size, wl)
        rr = gi[:, None, None] * size + np.arange(br)[None, :, None]
        col = gj[:, None, None] * size + np.arange(bc)[None, None, :]
        rr, col = np.broadcast_arrays(rr, col)
        ok = (rr < hl) & (col < wl)
        tid = np.broadcast_to(np.arange(gi.size)[:, None, None], rr.shape)
        cr.append(rr[ok])
        cc.append(col[ok])
        keys_s.append(smp[tid[ok]])
        keys_b.append(base[tid[ok]])
    cr = np.concatenate(cr)
    cc = np.concatenate(cc)
    ks = np.concatenate(keys_s)
    kb = np.concatenate(keys_b)
    pairs = np.stack([kb, ks], axis=1)
    uniq, grp = np.unique(pairs, axis=0, return_inverse=True)
    grp = grp.ravel()
    gg, r0, r1, c0, c1 = _rects(grp, cr, cc)
    x0 = c0 * s
    x1 = np.minimum((c1 + 1) * s, w)
    y0 = r0 * s
    y1 = np.minimum((r1 + 1) * s, h)
    base = uniq[gg, 0]
    smp = uniq[gg, 1]
    order = np.lexsort((x0, y0, smp, base))
    tasks = tuple(RegionTask(int(x0[i]), int(y0[i]), int(x1[i]), int(y1[i]), int(smp[i]),
                             int(frame), 0) for i in order)
    covered = paint(tasks, (h, w))
    return Plan(tasks, covered, len(tasks), int(covered.sum()) - requested, requested)


# -------------------------------------------------------------------- offsets
def assign_offsets(tasks, next_index):
    """Give each task its first sample index so no pixel reuses an index.

    Tasks are processed in order; a task's offset is the maximum of
    ``next_index`` over its rectangle (exact continuation when ``next_index``
    is uniform there, which :func:`plan`'s ordering ensures after a uniform
    pass), then ``next_index[rect] = offset + samples``.  Pure: returns
    ``(tasks_with_offsets, new_next_index)`` and copies ``next_index``.

    tasks : iterable of RegionTask;  next_index : (H, W) int
    """
    nxt = np.array(next_index, dtype=np.int64, copy=True)
    out = []
    for t in tasks:
        sub = nxt[t.y0:t.y1, t.x0:t.x1]
        off = int(sub.max()) if sub.size else 0
        nxt[t.y0:t.y1, t.x0:t.x1] = off + int(t.samples)
        out.append(replace(t, offset=off))
    return out, nxt


def plan_within(counts, frame: int = 0, min_size: int = 8, task_cost: float = DEFAULT_TASK_COST,
                max_beyond: float = 0.1) -> Plan:
    """The cheapest :func:`plan` at ``task_cost`` whose samples beyond the map
    stay within ``max_beyond`` of its samples: the task cost is quartered until
    they do (at 0 the plan is exact at ``min_size`` blocks, and is returned
    whatever it adds)."""
    cost = float(task_cost)
    while True:
        p = plan(counts, frame=frame, min_size=min_size, task_cost=cost)
        if cost <= 0 or p.overshoot <= max_beyond * p.covered.sum():
            return p
        cost = cost / 4.0 if cost > 4.0 else 0.0

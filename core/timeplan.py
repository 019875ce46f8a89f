"""Fitting a run's renders into a time limit (``Options.max_seconds``).

A limit checked only before each task bounds the overrun by one task, and one
task can be a whole frame at hundreds of samples: minutes past a limit of
seconds.  So a time-limited run measures what its own renders cost and plans
with it:

* :class:`RenderCost` fits ``seconds = overhead + per_sample * pixel_samples``
  to the run's renders (least squares; the first render, which also builds the
  scene, is left out once there are others);
* each round asks for no more samples than the time left holds, once the final
  reconstruction (measured on the run's own buffers) and the rounds still to
  come are set aside (``AdaptiveRun._time_cap``);
* :func:`slice_tasks` splits a task predicted to take longer than a slice of
  the limit into consecutive sample slices of the same rectangle, so the
  overrun is bounded by one slice.  Sample subsets merge exactly (the
  sequence is indexed by ``offset``), so a sliced task gives the image the
  unsliced one would.

Pure Python and numpy: the clock is the caller's.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

#: a task predicted to take longer than this share of the limit is sliced
SLICE_SHARE = 0.05
#: most bands of rows :func:`band_tasks` cuts a task into: a bound near the
#: renders' overhead, or a cost fitted from one render size (which counts the
#: overhead as sampling), cannot turn one render into hundreds
MAX_BANDS = 32


class RenderCost:
    """Seconds of one render as ``overhead + per_sample * pixel_samples``.

    Fitted by least squares on the renders :meth:`add` saw.  With one size
    only (all of an initial pass's subsets are alike) the two terms cannot be
    told apart and the fit is the ratio through the origin, which
    over-predicts a larger render by its share of the overhead: the error
    leaves time unused, not a limit overrun, and the next round's renders,
    of other sizes, separate the terms.  A negative intercept or slope (noise
    on a shared machine) falls back to that ratio as well.
    """

    def __init__(self):
        self.samples: list = []
        self.seconds: list = []

    def __len__(self) -> int:
        return len(self.samples)

    def add(self, pixel_samples: float, seconds: float) -> None:
        s = float(seconds)
        n = float(pixel_samples)
        if n > 0 and math.isfinite(s) and s >= 0:
            self.samples.append(n)
            self.seconds.append(s)

    def fit(self) -> tuple:
        """(overhead seconds, seconds per pixel-sample); (0, 0) before any render."""
        if not self.samples:
            return 0.0, 0.0
        n = np.asarray(self.samples, np.float64)
        t = np.asarray(self.seconds, np.float64)
        if n.size > 1:  # the first render also synced the scene
            n, t = n[1:], t[1:]
        ratio = float(t.sum() / n.sum())
        if n.size < 2 or np.ptp(n) <= 1e-9 * n.max():
            return 0.0, ratio
        a = np.stack([np.ones_like(n), n], axis=1)
        (c0, c1), *_ = np.linalg.lstsq(a, t, rcond=None)
        if not (np.isfinite(c0) and np.isfinite(c1)) or c0 < 0 or c1 <= 0:
            return 0.0, ratio
        return float(c0), float(c1)

    def predict(self, pixel_samples: float) -> float:
        """Predicted seconds of one render of ``pixel_samples``."""
        c0, c1 = self.fit()
        return c0 + c1 * max(float(pixel_samples), 0.0)

    def samples_within(self, seconds: float, renders_per_sample: float = 0.0) -> int:
        """Most pixel-samples that fit in ``seconds`` when they are rendered
        in ``max(1, renders_per_sample * samples)`` renders, each paying the
        overhead (a round's task count grows with its samples: the latest
        round's ratio).  0 when not even one render's overhead fits, and
        before any render (nothing is known)."""
        c0, c1 = self.fit()
        seconds = float(seconds)
        if c1 <= 0 or not seconds > c0:
            return 0
        rps = max(float(renders_per_sample), 0.0)
        n = seconds / (c1 + c0 * rps)
        if rps * n < 1.0:  # fewer than one render: one overhead
            n = (seconds - c0) / c1
        return int(n)


def extrapolate_seconds(pixels_small: float, seconds_small: float, pixels_large: float,
                        seconds_large: float, pixels: float) -> float:
    """Seconds of a computation over ``pixels`` from two timed crops: the
    line ``fixed + per_pixel * pixels`` through both, so a fixed cost (a
    library's set-up, Python overhead) is not scaled with the pixel count.
    Between the larger crop's seconds and that crop scaled by the pixel
    count: the line only takes the fixed cost out of the scaling (a method
    faster per pixel on the small crop, e.g. fewer levels, would make the
    line's slope, extrapolated 16x, over-state it: LP measured 10.2 s for a
    2.2 s reconstruction).  Noise that gives a negative term falls back to
    the scaled larger crop."""
    p1, t1, p2, t2, p = (float(pixels_small), float(seconds_small), float(pixels_large),
                         float(seconds_large), float(pixels))
    scaled = t2 * p / p2 if p2 > 0 else 0.0
    if not (p2 > p1 > 0) or not all(math.isfinite(x) for x in (t1, t2, scaled)):
        return scaled if math.isfinite(scaled) else 0.0
    slope = (t2 - t1) / (p2 - p1)
    fixed = t1 - slope * p1
    if slope <= 0 or fixed < 0:
        return scaled
    return min(max(fixed + slope * p, t2), scaled)


def rows_within(cost: RenderCost, seconds: float, width: int, samples: int) -> int:
    """Most rows of ``width`` pixels at ``samples`` each that one render is
    predicted (``cost``) to hold within ``seconds``; at least one (a row is
    the smallest band)."""
    c0, c1 = cost.fit()
    fits = max(float(seconds) - c0, 0.0) / c1 if c1 > 0 else 0.0
    return max(int(fits / max(int(width) * int(samples), 1)), 1)


def band_tasks(tasks, cost: RenderCost, seconds: float) -> list:
    """``tasks`` with each one predicted (``cost``) to take longer than
    ``seconds`` cut into full-width bands of rows that fit (one row and a
    ``MAX_BANDS``-th of the task at least).
    Unlike :func:`slice_tasks` no pixel's samples are split, so each pixel
    keeps one sample group and the merged buffers are the uncut task's, bit
    for bit (``Options.render_seconds``).  ``seconds <= 0`` or an empty
    cost: ``tasks`` unchanged."""
    if seconds <= 0 or not len(cost):
        return list(tasks)
    out = []
    for t in tasks:
        if cost.predict(t.pixels * t.samples) <= seconds:
            out.append(t)
            continue
        rows = max(rows_within(cost, seconds, t.width, t.samples), -(-t.height // MAX_BANDS))
        out.extend(replace(t, y0=y, y1=min(y + rows, t.y1)) for y in range(t.y0, t.y1, rows))
    return out


def slice_tasks(tasks, cost: RenderCost, seconds: float) -> list:
    """``tasks`` with each one predicted (``cost``) to take longer than
    ``seconds`` split, in place of it, into consecutive sample slices of its
    rectangle (as many as make each slice fit, at most one per sample), and
    a slice that still does not fit (one sample over a large region) into
    bands of rows, top to bottom.  The order, and so the offsets
    :func:`core.regions.assign_offsets` gives, continue each pixel's sequence
    as the unsliced task would: a band's rows start where the slice before
    ended.  ``seconds <= 0`` or an empty cost: ``tasks`` unchanged."""
    if seconds <= 0 or not len(cost):
        return list(tasks)
    c0, c1 = cost.fit()
    fits = max(float(seconds) - c0, 0.0) / c1 if c1 > 0 else 0.0  # pixel-samples a render may hold
    out = []
    for t in tasks:
        if cost.predict(t.pixels * t.samples) <= seconds:
            out.append(t)
            continue
        per_pixel = int(fits / t.pixels)  # samples of the whole rectangle that fit one render
        parts = min(t.samples, max(2, math.ceil(t.samples / max(per_pixel, 1))))
        base, extra = divmod(int(t.samples), parts)
        for i in range(parts):
            piece = replace(t, samples=base + (1 if i < extra else 0))
            if per_pixel >= 1 or rows_within(cost, seconds, piece.width, piece.samples) >= piece.height:
                out.append(piece)
                continue
            rows = rows_within(cost, seconds, piece.width, piece.samples)
            out.extend(replace(piece, y0=y, y1=min(y + rows, piece.y1))
                       for y in range(piece.y0, piece.y1, rows))
    return out

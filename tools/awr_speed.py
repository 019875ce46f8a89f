"""Time and trace the AWR reconstruction alone on synthetic statistics.

    .venv/bin/python tools/awr_speed.py                       # 256, 512, 1024; shifts 1, 4
    .venv/bin/python tools/awr_speed.py --sizes 1024 --precision float32,float64 --threads 1,0

Every configuration runs ``--reps`` times interleaved with the others (this
machine's speed drifts by tens of percent within minutes, so compare rows of
one run, not runs) and reports the fastest, in seconds and seconds per
megapixel (10^6 pixels, as the benchmark), plus the peak memory traced by
tracemalloc in one extra, untimed call (bytes per pixel, the float64 result's
32 included).  Inputs: uniform random means, variances and counts 8..39 (the
variance spread of an adaptive render; "sample" thresholds).  The benchmark's
scaling section (``./cycles-adaptive bench``) times the same function once on
a rendered scene.
"""
import argparse
import itertools
import os
import sys
import time
import tracemalloc

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from launch import load_package  # noqa: E402

load_package()
from cycles_adaptive.core import awr  # noqa: E402


def _list(text, kind):
    return [kind(v) for v in text.split(",") if v]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="256,512,1024", help="square image sizes")
    p.add_argument("--shifts", default="1,4")
    p.add_argument("--precision", default="float32")
    p.add_argument("--threads", default="0", help="0 = the default choice")
    p.add_argument("--reps", type=int, default=5)
    a = p.parse_args(argv)
    rng = np.random.default_rng(0)
    for size in _list(a.sizes, int):
        mean = rng.random((size, size, 3))
        var = rng.random((size, size, 3)) * 0.01
        n = rng.integers(8, 40, (size, size)).astype(float)
        configs = list(itertools.product(_list(a.shifts, int), _list(a.precision, str),
                                         _list(a.threads, int)))
        best = {c: float("inf") for c in configs}
        for _ in range(a.reps):
            for c in configs:
                params = awr.Params(shifts=c[0], precision=c[1], threads=c[2])
                t = time.perf_counter()
                awr.wavelet_reconstruct(mean, var, n, params)
                best[c] = min(best[c], time.perf_counter() - t)
        mp = size * size / 1e6
        for c in configs:
            params = awr.Params(shifts=c[0], precision=c[1], threads=c[2])
            tracemalloc.start()
            base = tracemalloc.get_traced_memory()[0]
            awr.wavelet_reconstruct(mean, var, n, params)
            peak = tracemalloc.get_traced_memory()[1] - base
            tracemalloc.stop()
            print(f"{size}x{size} shifts {c[0]} {c[1]} threads {c[2] or 'auto'}: "
                  f"{best[c]:.3f} s, {best[c] / mp:.2f} s/MP, {peak / size / size:.0f} B/px")


if __name__ == "__main__":
    main()

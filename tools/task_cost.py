"""Measure the fixed cost of one region render in pixel-samples (regions.DEFAULT_TASK_COST).

    .venv/bin/python tools/task_cost.py cornell glossy

Per scene: renders of squares of 8..128 pixels at 1..8 spp (best of three
each), then a least-squares line seconds = fixed + per_pixel_sample x
pixel-samples; the task cost is fixed / per_pixel_sample.
"""
import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from launch import load_package  # noqa: E402

load_package()
import bpy  # noqa: E402
import numpy as np  # noqa: E402

from cycles_adaptive.addon.executor import CyclesExecutor  # noqa: E402
from cycles_adaptive.bench import references as refs  # noqa: E402
from cycles_adaptive.core.regions import RegionTask  # noqa: E402

#: (square side in pixels, spp) of the timed renders
SIZES = [(8, 1), (8, 4), (16, 1), (16, 4), (32, 1), (32, 4), (64, 4), (128, 1), (128, 4), (128, 8)]


def task_cost(scene_name: str) -> tuple:
    """(fixed seconds, seconds per pixel-sample) of region renders of a sample scene."""
    refs.open_scene(refs.scene_path(scene_name), force=True)
    s = bpy.context.scene
    with CyclesExecutor(s, bpy.context.view_layer, (), seed=0) as ex:
        h, w = ex.size
        ex.render(RegionTask(0, 0, w, h, 1, frame=1))
        rows = []
        for size, spp in SIZES:
            ts = []
            for rep in range(3):
                t = time.perf_counter()
                ex.render(RegionTask(0, 0, size, size, spp, frame=1, offset=10 + rep * spp))
                ts.append(time.perf_counter() - t)
            rows.append((size * size * spp, min(ts)))
    ps, sec = np.array(rows).T
    A = np.stack([np.ones_like(ps), ps], 1)
    (a, b), *_ = np.linalg.lstsq(A, sec, rcond=None)
    return a, b


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", help="sample scene names (sample_blends/*.blend)")
    args = ap.parse_args(argv)
    for scene_name in args.scenes:
        a, b = task_cost(scene_name)
        print(scene_name, f"fixed {a*1000:.1f} ms, per pixel-sample {b*1e6:.2f} us, task cost = {a/b:.0f} pixel-samples")


if __name__ == "__main__":
    main()

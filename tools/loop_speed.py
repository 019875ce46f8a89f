"""Speed of ``uniform`` through our loop against one plain Cycles render (docs/notes/loop-speed.md).

Both render the same scene at the same spp in one process, alternating, so the
machine's load falls on both alike.  Plain Cycles is the benchmark's peer
(bench/peers.py: one full-frame render with the scene's own pattern, EXR
written and read back); ours is ``AdaptiveRun`` with ``uniform`` and the final
reconstruction, as the benchmark and a job run it (the scene's pattern with
Cycles' count held at the budget, ``core.pipeline.hold_samples``).  Every render is split into Cycles'
own time (``bpy.ops.render.render`` with the EXR write) and reading the EXR
back, so the note can say where the loop's extra time goes:

    .venv/bin/python tools/loop_speed.py [--scenes cornell,...] [--percent 100,600] [--spp 16] [--method auto]
        [--repeats 5] [--seed 0] [--subsets N] [--bare] [--out F.json]

Prints, per scene and size, the medians over repeats, the speed ratio
plain / ours (>= 1 would be as fast as plain Cycles) and how far our image is
from plain Cycles' (largest absolute difference, relMSE taking plain's as the
reference: 0 when the loop renders the same image).  ``--bare`` adds a third
arm in the same alternation: ours rendering no feature passes (what the
guides ``uniform`` reads cost the loop).  ``--method auto`` or
``oidn-uniform`` times that method instead, against plain Cycles with its
own OIDN (the peer an artist compares it with).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

load_package()
import bpy  # noqa: E402

from cycles_adaptive.addon import executor as ex  # noqa: E402
from cycles_adaptive.bench.peers import PlainCycles  # noqa: E402
from cycles_adaptive.core import io as imageio  # noqa: E402
from cycles_adaptive.core import methods  # noqa: E402
from cycles_adaptive.core.pipeline import AdaptiveRun, Options, hold_samples  # noqa: E402

SCENES = "cornell,dof,soft_shadows,glossy,motion_blur,animated"


class Clock:
    """Seconds spent in Cycles' render call (with its EXR write) and in reading
    the EXR back (ours: on the merge's thread, behind the next render, except
    the last), and the number of renders, since the last :meth:`reset`."""

    def __init__(self):
        self.reset()
        self._read = imageio.read_layers
        clock = self

        def read_layers(*a, **k):
            t0 = time.perf_counter()
            try:
                return clock._read(*a, **k)
            finally:
                clock.read += time.perf_counter() - t0

        def render_file(scene, view_layer, path, what=""):
            t0 = time.perf_counter()
            try:
                return original(scene, view_layer, path, what)
            finally:
                clock.cycles += time.perf_counter() - t0
                clock.renders += 1

        original = ex.render_file
        imageio.read_layers = read_layers
        ex.render_file = render_file

    def reset(self):
        self.cycles, self.read, self.renders = 0.0, 0.0, 0

    def split(self) -> dict:
        return {"renders": self.renders, "cycles": self.cycles, "read": self.read}


def plain(scene, vl, spp, seed, clock, denoise=False) -> dict:
    """One plain Cycles render (``denoise``: with Cycles' own OIDN, the peer
    of a method that denoises with OIDN)."""
    clock.reset()
    t0 = time.perf_counter()
    with PlainCycles(scene, vl, seed, scene.cycles.sampling_pattern) as pc:
        rgb = pc.render(spp, denoise=denoise)["rgb"]
    return {"wall": time.perf_counter() - t0, **clock.split(), "image": rgb}


#: --method: (registered method, its params, whether plain Cycles' peer denoises)
METHODS = {"uniform": ("uniform", {}, False), "auto": ("auto", {}, True),
           "oidn-uniform": ("oidn", {"adaptive": False, "error_estimate": False}, True)}


def ours(scene, vl, spp, seed, subsets, clock, passes=None, method="uniform") -> dict:
    """``passes``: the feature passes rendered (None: what the method declares)."""
    clock.reset()
    t0 = time.perf_counter()
    name, params, _ = METHODS[method]
    opts = Options(method=name, spp=float(spp), seed=seed, frame=scene.frame_current, params=dict(params),
                   **({"subsets": subsets} if subsets else {}))
    run_method = methods.method_for(name, opts.params)
    mod = methods.get(name)
    declared = mod.PASSES
    if passes is not None:  # the run reads what the method declares: declare these for this arm
        mod.PASSES = tuple(passes)
    try:
        exe = ex.CyclesExecutor(scene, vl, tuple(run_method.PASSES if passes is None else passes), seed=seed)
        hold_samples(exe, opts, run_method)  # the scene's pattern, as a job does
        with exe:
            run = AdaptiveRun(exe, opts, method=run_method)
            for _ in run.steps():
                pass
            image = run.reconstruct().image
    finally:
        mod.PASSES = declared
    wall = time.perf_counter() - t0
    tm = run.timing
    return {"wall": wall, **clock.split(), "loop_render": tm.render, "reconstruct": tm.reconstruct,
            "rest": wall - tm.render - tm.reconstruct, "image": image}


def image_gap(ours_rgb, plain_rgb) -> dict:
    """How far our image is from plain Cycles' at equal spp: the largest
    absolute difference and the relMSE of ours taking plain's as the
    reference (0 when the loop renders the same image)."""
    import numpy as np
    a, b = np.asarray(ours_rgb, np.float64)[..., :3], np.asarray(plain_rgb, np.float64)[..., :3]
    return {"max_abs_diff": float(np.max(np.abs(a - b))),
            "relmse_to_plain": float(np.mean((a - b) ** 2 / (b * b + 0.01)))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=SCENES)
    ap.add_argument("--percent", default="100", help="resolution percentages (comma list)")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--subsets", type=int, default=0, help="the loop's subsets (0: its default)")
    ap.add_argument("--bare", action="store_true",
                    help="also time ours without feature passes (the guides' cost)")
    ap.add_argument("--method", default="uniform", choices=sorted(METHODS),
                    help="ours' method; auto and oidn-uniform are timed against Cycles' own OIDN")
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    denoise = METHODS[args.method][2]
    clock = Clock()
    rows = []
    for name in args.scenes.split(","):
        for pct in (int(p) for p in args.percent.split(",")):
            bpy.ops.wm.open_mainfile(filepath=os.path.join(ROOT, "sample_blends", f"{name}.blend"))
            scene = bpy.context.scene
            scene.frame_set(scene.frame_start)
            scene.render.resolution_percentage = pct
            vl = scene.view_layers[0]
            plain(scene, vl, 1, args.seed, clock)  # warm-up: kernels, BVH, caches
            p, o, bare = [], [], []
            gaps = []
            for _ in range(args.repeats):
                p.append(plain(scene, vl, args.spp, args.seed, clock, denoise))
                o.append(ours(scene, vl, args.spp, args.seed, args.subsets, clock, method=args.method))
                gaps.append(image_gap(o[-1].pop("image"), p[-1].pop("image")))
                if args.bare:
                    bare.append(ours(scene, vl, args.spp, args.seed, args.subsets, clock, passes=(),
                                     method=args.method))
                    bare[-1].pop("image")
            arms = (("plain", p), ("ours", o)) + ((("bare", bare),) if bare else ())
            med = {side: {k: statistics.median(r[k] for r in runs) for k in runs[0]} for side, runs in arms}
            w, h = ex.full_size(scene)
            row = {"scene": name, "method": args.method, "width": w, "height": h, "spp": args.spp,
                   "repeats": args.repeats,
                   "ratio": med["plain"]["wall"] / med["ours"]["wall"],
                   "ratios": [a["wall"] / b["wall"] for a, b in zip(p, o)], "seed": args.seed,
                   "max_abs_diff": max(g["max_abs_diff"] for g in gaps),
                   "relmse_to_plain": max(g["relmse_to_plain"] for g in gaps), **med}
            if bare:
                row["bare_ratio"] = med["plain"]["wall"] / med["bare"]["wall"]
                row["bare_ratios"] = [a["wall"] / c["wall"] for a, c in zip(p, bare)]
            rows.append(row)
            print(f"{name:>12} {w}x{h} {args.spp} spp: plain {med['plain']['wall']:.3f} s "
                  f"(cycles {med['plain']['cycles']:.3f}, read {med['plain']['read']:.3f}) | ours "
                  f"{med['ours']['wall']:.3f} s ({int(med['ours']['renders'])} renders: cycles "
                  f"{med['ours']['cycles']:.3f}, read {med['ours']['read']:.3f}; reconstruct "
                  f"{med['ours']['reconstruct']:.3f}, rest {med['ours']['rest']:.3f}) | "
                  f"speed {row['ratio']:.3f}x (median of pairs {statistics.median(row['ratios']):.3f}x, "
                  f"Cycles' share {med['plain']['cycles'] / med['ours']['cycles']:.3f}x); image: max |ours - plain| "
                  f"{row['max_abs_diff']:.2e}, relMSE to plain {row['relmse_to_plain']:.2e}", flush=True)
            if bare:
                print(f"{'':>12} ours without feature passes {med['bare']['wall']:.3f} s (cycles "
                      f"{med['bare']['cycles']:.3f}, read {med['bare']['read']:.3f}; reconstruct "
                      f"{med['bare']['reconstruct']:.3f}) | speed {row['bare_ratio']:.3f}x (median of pairs "
                      f"{statistics.median(row['bare_ratios']):.3f}x)", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()

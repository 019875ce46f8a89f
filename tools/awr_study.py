"""AWR: why soft_shadows loses to plain sampling at 16 spp, measured
reproducibly.

    .venv/bin/python tools/awr_study.py [--scenes soft_shadows cornell ...] [--groups 32] [--shifts 1]

``--seeds 1,2,3`` instead replays the render loop at ``--spp`` (16) for those
Cycles seeds from 1-sample frames (uniform, AWR with 1 and 4 shifts): AWR
against uniform at equal spp away from the benchmark's seed 0 (about 10 s per
seed and scene).

``--shifts`` is AWR's cycle spinning (``awr.Params.shifts``); the default 1 is
the paper's single transform, which the figures in the README's facts section
describe (the product's default is 4).

Needs the 1024-spp references (cached): ./cycles-adaptive references
(``--scenes`` defaults to every sample scene, in the benchmark's order).

Per scene it prints
1. QMC variance ratios.  Renders ``--groups`` whole-frame groups of 1 sample,
   consecutive in the sequence (sample offsets 0, 1, ...), and compares the
   true squared error of the 16-sample mean (against the reference, relMSE
   weights) with the between-group variance estimate from 4 groups of 4 and 16
   groups of 1 (``true/est``), and the exponent ``alpha`` of a power law
   ``S(m) ~ m^-alpha`` of the per-sample variance at group size ``m``, estimated
   from the first 4 groups as ``-log2(S(2) / S(1))`` (what the render loop's
   initial pass could measure).  Also relMSE x N for N = 15, 16, 17: counts
   off a power of two lose part of the sequence's stratification.
2. AWR reconstruction of that 16-sample mean (4 groups of 4) with the variance
   scaled by 1, 0.7 and 0.5, through the consistency guard, against the mean;
   and the relMSE share of dark pixels (reference luminance < 0.1).
3. The render loop with ``--method awr`` at 16 spp, with the default task cost
   and with ``task_cost = 0`` (the sample map followed pixel-exactly): spread of
   the final sample counts, relMSE of the loop's reconstruction and of the same reconstruction
   with the variance of the mean scaled by ``k^-alpha`` (k = groups per pixel).
"""
import argparse
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

load_package()
import bpy  # noqa: E402
import numpy as np  # noqa: E402

from cycles_adaptive.addon.executor import CyclesExecutor  # noqa: E402
from cycles_adaptive.bench import references as refs  # noqa: E402
from cycles_adaptive.core import awr, metrics  # noqa: E402
from cycles_adaptive.core.buffers import LUMA, Buffers  # noqa: E402
from cycles_adaptive.core.method import consistency_guard  # noqa: E402
from cycles_adaptive.core.pipeline import AdaptiveRun, Options  # noqa: E402
from cycles_adaptive.core.regions import RegionTask  # noqa: E402

def subsets(g, n, m):
    """Buffers of the first ``n`` 1-sample frames ``g`` merged as ``n / m``
    groups of ``m`` consecutive samples: the estimator the methods see."""
    groups = g[:n].reshape(n // m, m, *g.shape[1:]).mean(axis=1)
    return Buffers.from_subsets(list(groups), [m] * (n // m))


def reconstruct(buf, scale, shifts):
    var = buf.variance_of_mean() * scale
    res = awr.wavelet_reconstruct(buf.color.mean, var, buf.n, awr.Params(shifts=shifts))
    return consistency_guard(res, buf, 3.0).image


def frames(scene, count, seed=0, ref_dir=None):
    """(reference, scene, ``count`` whole-frame renders of 1 sample each at
    sample offsets 0, 1, ... with Cycles seed ``seed``)."""
    refs.open_scene(refs.scene_path(scene), force=True)
    sc = bpy.context.scene
    ref_path = refs.reference_path(scene, sc.frame_current, 100, refs.DEFAULT_SPP, ref_dir)
    try:
        ref, _ = refs.load_checked_reference(ref_path)
    except refs.ReferenceFileError as exc:
        sys.exit(str(exc))
    with CyclesExecutor(sc, bpy.context.view_layer, (), seed=seed) as ex:
        h, wd = ex.size
        g = np.stack([np.asarray(ex.render(RegionTask(0, 0, wd, h, 1, frame=sc.frame_current,
                                                      offset=i))[0], np.float64)[..., :3]
                      for i in range(count)])
    return ref, sc, g


class ReplayExecutor:
    """Executor answering region tasks from whole-frame 1-sample renders: a
    region render of samples ``offset .. offset + samples - 1`` equals those
    frames' mean over the region (sample subsets and border renders merge
    exactly: tests/test_executor.py), so the render loop replays without Cycles."""

    def __init__(self, g):
        self.g = g
        self.size = g.shape[1:3]

    def render(self, task):
        if task.offset + task.samples > len(self.g):
            raise RuntimeError(f"the replay needs {task.offset + task.samples} frames, has {len(self.g)}")
        c = self.g[task.offset:task.offset + task.samples, task.y0:task.y1, task.x0:task.x1].mean(0)
        # the replay keeps colour only: flat guides (no information) for the methods that declare
        # them (uniform's calibrated variance); the images compared here do not read them
        h, w = c.shape[:2]
        flat = {"albedo": np.full((h, w, 3), 0.5), "normal": np.dstack([np.zeros((h, w, 2)), np.ones((h, w))]),
                "depth": np.ones((h, w, 1))}
        return np.concatenate([c, np.ones(c.shape[:2] + (1,))], axis=-1), flat


def replay(g, ref, method, spp, params=None):
    run = AdaptiveRun(ReplayExecutor(g), Options(method=method, spp=spp, params=params or {}))
    for _ in run.steps():
        pass
    return metrics.relmse(run.reconstruct().image, ref)


def seeds(scenes, seed_list, spp, ref_dir=None):
    """AWR against uniform at equal spp (default options) for other Cycles
    seeds, the loop replayed from 1-sample frames."""
    count = int(2 * spp + 8)  # the pixel cap (max_pixel_share 2) plus top-ups
    for seed in seed_list:
        for scene in scenes:
            ref, _, g = frames(scene, count, seed, ref_dir)
            u = replay(g, ref, "uniform", spp)
            a1 = replay(g, ref, "awr", spp, {"shifts": 1})
            a4 = replay(g, ref, "awr", spp, {"shifts": 4})
            print(f"seed {seed} {scene}: {spp} spp relMSE uniform {u:.3e}, awr (shifts 1) {a1:.3e}, "
                  f"awr (shifts 4, default) {a4:.3e}: {'beats' if a4 < u else 'LOSES TO'} uniform by "
                  f"{100 * abs(1 - a4 / u):.1f} %", flush=True)


def study(scene, n_groups, shifts, ref_dir=None):
    ref, sc, g = frames(scene, n_groups, ref_dir=ref_dir)
    w = 1.0 / (ref * ref + 0.01)  # the relMSE weights (core.metrics.relmse)
    weighted = lambda v: float((v * w).mean())  # noqa: E731

    def true_over_est(buf):
        return metrics.relmse(buf.color.mean, ref) / weighted(buf.variance_of_mean())

    s1 = weighted(subsets(g, 4, 1).sample_variance())
    s2 = weighted(subsets(g, 4, 2).sample_variance())
    alpha = float(np.clip(-np.log2(max(s2, 1e-300) / max(s1, 1e-300)), 0.0, 1.0))
    print(f"{scene}: true/est at 16 spp: groups of 4 {true_over_est(subsets(g, 16, 4)):.2f}, of 1 "
          f"{true_over_est(subsets(g, 16, 1)):.2f}; alpha from the first 4 groups {alpha:.2f} "
          f"(predicts {4 ** -alpha:.2f} for groups of 4)")
    eff = {n: metrics.relmse(g[:n].mean(0), ref) * n for n in (15, 16, 17)}
    print("  relMSE x N of the first N samples (QMC efficiency; lower is better): "
          + ", ".join(f"N={n}: {v:.3f}" for n, v in eff.items()))

    buf = subsets(g, 16, 4)
    mean = buf.color.mean
    row = [f"  16 spp (4 x 4): mean {metrics.relmse(mean, ref):.2e}"]
    images = {}
    for s in (1.0, 0.7, 0.5):
        images[s] = reconstruct(buf, s, shifts)
        row.append(f"awr var x{s}: {metrics.relmse(images[s], ref):.2e}")
    print(" | ".join(row))
    dark = (ref @ LUMA) < 0.1
    em, ea = metrics.per_pixel_relmse(mean, ref), metrics.per_pixel_relmse(images[1.0], ref)
    print(f"  dark pixels (luminance < 0.1, {dark.mean():.0%}): relMSE share mean "
          f"{em[dark].sum() / em.size:.2e} -> awr {ea[dark].sum() / ea.size:.2e}; other pixels "
          f"{em[~dark].sum() / em.size:.2e} -> {ea[~dark].sum() / ea.size:.2e}")

    for task_cost in (None, 0.0):
        extra = {} if task_cost is None else {"task_cost": task_cost}
        opts = Options(method="awr", spp=16, frame=sc.frame_current, params={"shifts": shifts},
                       **extra)
        with CyclesExecutor(sc, bpy.context.view_layer, (), seed=0) as ex:
            run = AdaptiveRun(ex, opts)
            for _ in run.steps():
                pass
        lb = run.buffers
        loop = run.reconstruct().image
        corrected = reconstruct(lb, (lb.k ** -alpha)[..., None], shifts)
        p = np.percentile(lb.n, [0, 50, 100])
        label = "default task cost" if task_cost is None else "task cost 0, map followed exactly"
        print(f"  loop (awr, 16 spp, {label}): samples per pixel min/median/max "
              f"{p[0]:.0f}/{p[1]:.0f}/{p[2]:.0f}, groups {lb.k.min():.0f}-{lb.k.max():.0f}, true/est "
              f"{true_over_est(lb):.2f}; relMSE mean {metrics.relmse(lb.color.mean, ref):.2e}, awr "
              f"{metrics.relmse(loop, ref):.2e}, awr with variance x k^-alpha "
              f"{metrics.relmse(corrected, ref):.2e}", flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="+", default=None,
                    help="sample scenes (default: every one in sample_blends/)")
    ap.add_argument("--groups", type=int, default=32)
    ap.add_argument("--shifts", type=int, default=1,
                    help="AWR grid translations (awr.Params.shifts; default 1, the paper's transform)")
    ap.add_argument("--seeds", default=None,
                    help="comma-separated Cycles seeds: instead of the study, replay the render loop "
                         "(uniform, awr with 1 and 4 shifts) for each seed and scene")
    ap.add_argument("--spp", type=float, default=16, help="budget of the --seeds replays (default 16)")
    ap.add_argument("--reference-dir", default=None, help="reference cache (default references/)")
    args = ap.parse_args()
    args.scenes = args.scenes or refs.scene_names(None)
    if args.seeds:
        seeds(args.scenes, [int(x) for x in args.seeds.split(",")], args.spp, args.reference_dir)
        return
    if args.groups < 16:
        sys.exit("--groups must be at least 16")
    for scene in args.scenes:
        study(scene, args.groups, args.shifts, args.reference_dir)


if __name__ == "__main__":
    main()

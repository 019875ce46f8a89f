"""How much can adaptive sampling gain once the map is cut into region renders?

    .venv/bin/python tools/planner_curve.py probe --scenes all --percentages 100,400
    .venv/bin/python tools/planner_curve.py curve --budgets 16,64

``probe`` renders each sample scene as ``PROBE_SUBSETS`` full-frame 1-spp
sample subsets (seed ``PROBE_SEED``, independent of the benchmark's runs and
references) and caches, per pixel, the mean and the per-sample variance
(``PROBE_SUBSETS - 1`` degrees of freedom) plus the loop's initial pass as the
first 4 subsets would give it (4 spp, 4 groups: 3 dof).

``curve`` is offline.  For the sample mean, a pixel with ``n`` samples has
expected relative squared error ``W / n`` with ``W = mean_c sigma_c^2 /
(r_c^2 + 0.01)`` (the benchmark's relMSE), so a sample map's expected relMSE
is ``mean(W / n)`` and needs no rendering.  The optimum for a total of ``N``
samples per pixel on average is ``n ~ sqrt(W)`` (Lagrange), clipped below at
the initial pass.  Each strategy below gives a map of extra samples; the
planner (:func:`core.regions.plan`) turns it into rectangles; the figures are
the gain ``relMSE(uniform) / relMSE(strategy)`` at equal samples (the planner's
overshoot is counted in the budget) and at equal cost (``REAL_TASK_COST``
pixel-samples added per render, whatever task cost the planner was given).  Results: docs/notes/planner.md.
"""
import argparse
import json
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

PROBE_SUBSETS = 64
PROBE_SEED = 7
PROBE_DIR = "/tmp/planner_probe"
INITIAL = 4
EPS = 0.01
#: what one region render really costs in pixel-samples (tools/task_cost.py,
#: core.regions.DEFAULT_TASK_COST): the equal-cost gains charge every plan this,
#: whatever task cost its planner was given
REAL_TASK_COST = 1024.0


# ------------------------------------------------------------------ probe
def probe(scenes, percentages, out_dir):
    from launch import load_package
    load_package()
    import bpy
    from cycles_adaptive.addon import executor as ex
    from cycles_adaptive.bench import references as refs
    from cycles_adaptive.core.buffers import Buffers
    from cycles_adaptive.core.pipeline import merge_render, subset_tasks

    os.makedirs(out_dir, exist_ok=True)
    for name in refs.scene_names(scenes):
        for pct in percentages:
            path = os.path.join(out_dir, f"{name}.r{pct}.npz")
            if os.path.exists(path):
                continue
            refs.open_scene(refs.scene_path(name), force=True)
            scene = bpy.context.scene
            guard = ex.SettingsGuard()
            guard.set(scene.render, "resolution_percentage", int(pct))
            try:
                with ex.CyclesExecutor(scene, bpy.context.view_layer, (), seed=PROBE_SEED) as exe:
                    h, w = exe.size
                    full = Buffers.empty(h, w, ())
                    init = Buffers.empty(h, w, ())
                    for i, task in enumerate(subset_tasks(w, h, PROBE_SUBSETS, PROBE_SUBSETS,
                                                          scene.frame_current)):
                        color, feats = exe.render(task)
                        merge_render(full, task, color, {})
                        if i < INITIAL:
                            merge_render(init, task, color, {})
            finally:
                guard.restore()
            np.savez_compressed(path, mean=full.color.mean, s2=full.sample_variance(),
                                init_mean=init.color.mean, init_s2=init.sample_variance())
            print(f"probe {name} {pct}%: {w}x{h}", flush=True)


# ------------------------------------------------------------------ model
def weights(mean, s2):
    """W per pixel: mean over channels of sigma^2 / (r^2 + eps)."""
    s2 = np.where(np.isfinite(s2), np.maximum(s2, 0.0), 0.0)
    return (s2 / (mean * mean + EPS)).mean(axis=-1)


def expected_relmse(w_true, n):
    return float((w_true / np.maximum(n, 1e-9)).mean())


def sqrt_allocation(w, total_extra, floor=INITIAL):
    """Real-valued optimum n = max(floor, lam sqrt(w)) with sum(n) = P floor +
    total_extra (bisection on lam); returns the extra samples beyond ``floor``."""
    s = np.sqrt(np.maximum(w, 0.0))
    target = w.size * floor + total_extra
    lo, hi = 0.0, 1.0
    while np.maximum(floor, hi * s).sum() < target:
        hi *= 2.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if np.maximum(floor, mid * s).sum() < target:
            lo = mid
        else:
            hi = mid
    return np.maximum(floor, hi * s) - floor


def integer_map(extra, total):
    from core.method import allocate
    return allocate(np.maximum(extra, 0.0), int(total))


def box(a, r):
    from core.filters import box_mean
    return box_mean(a, r) if r > 0 else a


def cap_map(counts, share):
    from core.maps import cap_share
    return cap_share(counts, share)


def evaluate(w_true, counts, min_size, task_cost, spp, planned=True):
    """(gain at equal samples, gain at equal cost, tasks, overshoot %) of a map
    of extra samples planned into rectangles (or pixel-exact when not planned)."""
    from core import regions
    if planned:
        plan = regions.plan(counts, min_size=min_size, task_cost=task_cost)
        cov, tasks = plan.covered, plan.n_tasks
    else:
        cov, tasks = counts, 0
    n = INITIAL + cov
    spent = n.mean()
    e = expected_relmse(w_true, n)
    e_uniform_same = float(w_true.mean()) / spent
    cost = spent + tasks * REAL_TASK_COST / w_true.size
    e_uniform_cost = float(w_true.mean()) / cost
    over = 100.0 * (cov.sum() - counts.sum()) / max(counts.sum(), 1)
    return e_uniform_same / e, e_uniform_cost / e, tasks, over


def evaluate_loop(w_true, counts, min_size, task_cost):
    """As :func:`evaluate`, with the loop's block pooling and its plan
    (task cost quartered until the samples beyond the map are <= 10 %)."""
    from core import maps, regions
    from core.pipeline import MAX_BEYOND_MAP
    counts = maps.pool_to_blocks(counts, min_size)
    plan = regions.plan_within(counts, min_size=min_size, task_cost=task_cost, max_beyond=MAX_BEYOND_MAP)
    n = INITIAL + plan.covered
    spent = n.mean()
    e = expected_relmse(w_true, n)
    cost_total = spent + plan.n_tasks * REAL_TASK_COST / w_true.size
    over = 100.0 * plan.overshoot / max(counts.sum(), 1)
    return (float(w_true.mean()) / spent / e, float(w_true.mean()) / cost_total / e, plan.n_tasks, over)


def curve(budgets, probe_dir, min_sizes, task_costs, out, only=None):
    rows = []
    for f in sorted(os.listdir(probe_dir)):
        if not f.endswith(".npz"):
            continue
        name = f[:-4]
        d = np.load(os.path.join(probe_dir, f))
        w_true = weights(d["mean"], d["s2"])
        w_est = weights(d["init_mean"], d["init_s2"])
        h, wd = w_true.shape
        for spp in budgets:
            extra_total = (spp - INITIAL) * w_true.size
            ideal = sqrt_allocation(w_true, extra_total)
            e_ideal = expected_relmse(w_true, INITIAL + ideal)
            base = dict(scene=name, size=f"{wd}x{h}", spp=spp,
                        ideal_gain=float(w_true.mean()) / spp / e_ideal)
            oracle = integer_map(ideal, extra_total)
            variants = {"oracle": oracle, "oracle cap2": cap_map(oracle, 2.0)}
            for r in (0, 1, 4):
                est = integer_map(sqrt_allocation(box(w_est, r), extra_total), extra_total)
                variants[f"estimate box{2 * r + 1}"] = est
                variants[f"estimate box{2 * r + 1} cap2"] = cap_map(est, 2.0)
            from core import maps
            shaped = maps.confidence_pool(variants["estimate box1"], np.full(w_true.shape, INITIAL - 1.0))
            variants["estimate loop"] = shaped  # core.maps as the loop applies it (then per min size)
            for label, counts in variants.items():
                if only and label not in only:
                    continue
                g_exact = evaluate(w_true, counts, 1, 0.0, spp, planned=False)[0]
                for ms in min_sizes:
                    for tc in task_costs:
                        if label == "estimate loop":
                            g_s, g_c, tasks, over = evaluate_loop(w_true, counts, ms, tc)
                        else:
                            g_s, g_c, tasks, over = evaluate(w_true, counts, ms, tc, spp)
                        rows.append(dict(base, map=label, exact_gain=g_exact, min_size=ms,
                                         task_cost=tc, gain_equal_spp=g_s, gain_equal_cost=g_c,
                                         tasks=tasks, overshoot_pct=over))
            print(f"{name} {spp} spp: ideal gain {base['ideal_gain']:.2f}", flush=True)
    with open(out, "w") as fh:
        json.dump(rows, fh, indent=1)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("probe")
    p.add_argument("--scenes", default="all")
    p.add_argument("--percentages", default="100,400")
    p.add_argument("--dir", default=PROBE_DIR)
    c = sub.add_parser("curve")
    c.add_argument("--budgets", default="16,64")
    c.add_argument("--dir", default=PROBE_DIR)
    c.add_argument("--min-sizes", default="1,4,8,16")
    c.add_argument("--task-costs", default="0,256,1024,4096")
    c.add_argument("--out", default=os.path.join(PROBE_DIR, "curve.json"))
    c.add_argument("--maps", default=None, help="comma-separated map variants (default: all)")
    a = ap.parse_args(argv)
    if a.cmd == "probe":
        probe(a.scenes, [int(x) for x in a.percentages.split(",")], a.dir)
    else:
        curve([int(x) for x in a.budgets.split(",")], a.dir, [int(x) for x in a.min_sizes.split(",")],
              [float(x) for x in a.task_costs.split(",")], a.out,
              a.maps.split(",") if a.maps else None)
    return 0


if __name__ == "__main__":
    sys.exit(main())

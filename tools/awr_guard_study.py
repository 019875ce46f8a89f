"""AWR and the consistency guard: how many pixels the guard sends back, and why.

    .venv/bin/python tools/awr_guard_study.py render [--scenes ...] [--budgets 4,8,16]
    .venv/bin/python tools/awr_guard_study.py analyse [--consistency 0,3] [--calibrated] > LINES
    .venv/bin/python tools/awr_guard_study.py table --lines LINES

``render`` runs the render loop (``AdaptiveRun`` + ``CyclesExecutor``, method
awr, the benchmark's options, seed 0) per scene and budget and caches the
final Buffers and the 1024-spp reference in ``--cache`` (pickles).
``analyse`` (numpy only) reconstructs from the cache and prints per run: the
guard's share (``core.method.consistency_guard``, z = 3), relMSE with and
without the guard, the share of pixels whose reconstruction is farther than
3 (and t_{k-1}) standard errors from the sample mean, how many of those are
nearer the reference than the sample mean is (the guard undoing a correct
smoothing), the true/estimated variance ratio of the sample mean, mean
brightness change, negative pixels, and the error-map correlation
(``core.metrics.error_correlation``: per pixel and 8x8 pooled).
Figures: docs/notes/awr.md.
"""
import argparse
import dataclasses
import os
import pickle
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
SCENES = ("cornell", "dof", "glossy", "motion_blur", "soft_shadows", "animated")


def cache_path(cache, scene, budget):
    return os.path.join(cache, f"{scene}_{budget}.pkl")


def render(scenes, budgets, cache):
    from launch import load_package
    load_package()
    import bpy
    from cycles_adaptive.addon import executor as ex
    from cycles_adaptive.bench import references as refs
    from cycles_adaptive.core.pipeline import AdaptiveRun, Options
    os.makedirs(cache, exist_ok=True)
    for scene_name in scenes:
        path = refs.scene_path(scene_name)
        refs.open_scene(path, force=True)
        sc, vl = bpy.context.scene, bpy.context.view_layer
        sc.render.use_persistent_data = True
        frame = sc.frame_current
        ref_path = refs.reference_path(scene_name, frame, 100, refs.DEFAULT_SPP, "/work/refs")
        for budget in budgets:
            with ex.CyclesExecutor(sc, vl, (), seed=0) as exe:
                ref, _ = refs.load_checked_reference(ref_path, exe.size)
                run = AdaptiveRun(exe, Options(method="awr", spp=float(budget), frame=frame, seed=0))
                for _ in run.steps():
                    pass
            with open(cache_path(cache, scene_name, budget), "wb") as f:
                pickle.dump({"buffers": run.buffers, "params": run.params, "ref": ref}, f)
            print(f"{scene_name} {budget}: cached, spp {run.samples_rendered / run.pixels:.2f}",
                  flush=True)


def pooled(x, b=8):
    """Mean over b x b blocks (the image cropped to whole blocks)."""
    h, w = x.shape[:2]
    return x[:h // b * b, :w // b * b].reshape(h // b, b, w // b, b).mean(axis=(1, 3))


def pearson(a, b):
    import numpy as np
    a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
    d = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / d) if d > 0 else 0.0


def analyse_one(buf, params, ref, scale=1.0):
    """Figures of one cached run; ``scale`` multiplies the variance (M2) for
    the methods and the guard alike (a stand-in for a calibrated variance)."""
    import numpy as np
    from core import awr, metrics
    from core.method import consistency_guard, t_quantile
    if scale != 1.0:
        buf = buf.copy()
        buf.color.m2 = buf.color.m2 * scale
    var = awr.variance_of_mean(buf)
    res = awr.reconstruct(buf, params)
    g = consistency_guard(res, buf, 3.0)
    mean = buf.color.mean
    sd = np.sqrt(np.maximum(buf.variance_of_mean(), 0.0))
    dev = np.abs(res.image - mean) / np.maximum(sd, 1e-30)
    tq = t_quantile(3.0, np.maximum(buf.k - 1.0, 1.0))[..., None]
    far = (dev > tq).any(-1)
    closer = (np.abs(res.image - ref) < np.abs(mean - ref)).all(-1)
    true_sq = ((mean - ref) ** 2).mean()
    est_sq = np.where(np.isfinite(var), var, 0).mean()
    bright = float(res.image.mean() / mean.mean() - 1.0)
    out = {
        "guard": g.info.get("guard_fraction", 0.0),
        "far3": float((dev > 3).any(-1).mean()),
        "far_t": float(far.mean()),
        "far_t_closer": float((far & closer).sum() / max(far.sum(), 1)),
        "relmse_mean": metrics.relmse(mean, ref),
        "relmse_awr": metrics.relmse(res.image, ref),
        "relmse_guard": metrics.relmse(g.image, ref),
        "true/est": float(true_sq / est_sq),
        "bright": bright,
        "bright_guard": float(g.image.mean() / mean.mean() - 1.0),
        "neg": int((res.image < 0).sum()),
        "min": float(res.image.min()),
        "corr": metrics.error_correlation(res.error, res.image, ref),
        "corr8": pearson(pooled(res.error), pooled(((res.image - ref) ** 2).mean(-1))),
        "clip": res.info.get("consistency_fraction", 0.0),
        "k_med": float(np.median(buf.k)),
    }
    return out


class _Unpickler(pickle.Unpickler):
    """Reads the cache with the repository's top-level packages (``core``)."""

    def find_class(self, module, name):
        if module.startswith("cycles_adaptive."):
            module = module[len("cycles_adaptive."):]
        return super().find_class(module, name)


def load(path):
    with open(path, "rb") as f:
        return _Unpickler(f).load()


def awr_variance(buf):
    import numpy as np
    from core import awr
    v = awr.variance_of_mean(buf)
    return np.where(np.isfinite(v), v, 0.0)


def analyse(scenes, budgets, cache, runs):
    sys.path.insert(0, ROOT)
    for scene_name in scenes:
        for budget in budgets:
            p = cache_path(cache, scene_name, budget)
            if not os.path.exists(p):
                continue
            d = load(p)
            for label, cons, scale in runs:
                params = dataclasses.replace(d["params"], consistency=cons)
                ratio = 1.0
                if scale == "true":  # the global true/estimated ratio of the sample mean
                    buf = d["buffers"]
                    ratio = float(((buf.color.mean - d["ref"]) ** 2).mean()
                                  / awr_variance(buf).mean())
                r = analyse_one(d["buffers"], params, d["ref"], ratio)
                print(scene_name, budget, label, {k: (round(v, 4) if isinstance(v, float) else v)
                                                  for k, v in r.items()}, flush=True)


def table(path):
    """Markdown table from the printed lines of ``analyse`` (saved to ``path``)."""
    import ast
    rows = ["| scene | spp | consistency | guard share | clipped | relMSE mean | awr | awr + guard "
            "| brightness awr | brightness awr + guard | negative px | corr px | corr 8x8 |",
            "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for line in open(path):
        scene, budget, label, rest = line.split(" ", 3)
        d = ast.literal_eval(rest)
        rows.append(f"| {scene} | {budget} | {label[5:]} | {100 * d['guard']:.1f} % | "
                    f"{100 * d['clip']:.1f} % | {d['relmse_mean']:.4f} | {d['relmse_awr']:.4f} | "
                    f"{d['relmse_guard']:.4f} | {100 * d['bright']:+.3f} % | "
                    f"{100 * d['bright_guard']:+.3f} % | {d['neg']} | {d['corr']:.2f} | {d['corr8']:.2f} |")
    print("\n".join(rows))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("what", choices=("render", "analyse", "table"))
    ap.add_argument("--lines", help="table: the saved output of analyse")
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--budgets", default="4,8,16")
    ap.add_argument("--cache", default="/tmp/awr_guard")
    ap.add_argument("--consistency", default="0,3",
                    help="awr.Params.consistency values to compare (0: the paper)")
    ap.add_argument("--calibrated", action="store_true",
                    help="also scale the variance by the true/estimated ratio of each run")
    a = ap.parse_args(argv)
    budgets = [int(b) for b in a.budgets.split(",")]
    if a.what == "table":
        table(a.lines)
        return
    if a.what == "render":
        render(a.scenes, budgets, a.cache)
        return
    runs = []
    for c in a.consistency.split(","):
        runs.append((f"cons={c}", float(c), None))
        if a.calibrated:
            runs.append((f"cons={c},var*true/est", float(c), "true"))
    analyse(a.scenes, budgets, a.cache, runs)


if __name__ == "__main__":
    main()

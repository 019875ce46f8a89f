"""Calibration of the variance of the mean on the sample scenes (docs/notes/variance.md).

For each scene and seed, 16 one-sample subsets (offsets 0..15) are rendered with
``CyclesExecutor`` exactly as ``core.pipeline.render_subsets`` does (its tasks,
``subset_tasks(w, h, 16, 16)``, each merged with ``merge_render``); subset renders
merge exactly (DESIGN.md), so the loop's initial pass of N spp in 4 consecutive
subsets is the merge of subsets [0, N/4), [N/4, N/2), ... of these.  For N = 4, 8,
16 the tool builds those Buffers and reports :func:`core.variance.calibration_ratio`
of the raw ``Buffers.variance_of_mean`` and of ``core.variance.calibrated_variance_of_mean``
against the 1024-spp reference (its own Variance layer subtracted from the true
squared error), plus the measured stratification exponent.

    .venv/bin/python tools/measure_variance.py render --seeds 0,1,2   # ~1 min a scene a seed
    .venv/bin/python tools/measure_variance.py measure --seeds 0,1,2  # table (markdown)
    .venv/bin/python tools/measure_variance.py guard --seeds 0,1 --spp 4  # guard share per method
    .venv/bin/python tools/measure_variance.py curve --seeds 0,1,2     # true v(x) and its slopes
    .venv/bin/python tools/measure_variance.py weights --seeds 0,1,2 --spp 4  # weights of beta

``--data`` (default /tmp/measure_variance) holds the renders; ``--refs`` (default
/work/refs) the references (bench/references.py names).
"""
import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

load_package()
from cycles_adaptive.core import io as imageio  # noqa: E402
from cycles_adaptive.core.buffers import Buffers  # noqa: E402
from cycles_adaptive.core.pipeline import merge_render, subset_tasks  # noqa: E402

SCENES = ("cornell", "dof", "soft_shadows", "glossy", "motion_blur", "animated")
FEATURES = ("albedo", "normal", "depth")
SUBSETS = 16
#: window radius of the local exponent map (31x31: ~2900 dof in S_pairs)
LOCAL_RADIUS = 15


def data_path(args, scene, seed):
    return os.path.join(args.data, f"{scene}.s{seed}.k{SUBSETS}.npz")


def exp_render(args):
    """One-sample subset renders (colour + features) of every scene at frame 1."""
    import bpy
    from cycles_adaptive.addon.executor import CyclesExecutor
    os.makedirs(args.data, exist_ok=True)
    for seed in args.seeds:
        for name in args.scenes:
            if os.path.isfile(data_path(args, name, seed)):
                continue
            bpy.ops.wm.open_mainfile(filepath=os.path.join(ROOT, "sample_blends", name + ".blend"),
                                     load_ui=False)
            scene = bpy.context.scene
            scene.frame_set(1)
            t0 = time.perf_counter()
            with CyclesExecutor(scene, bpy.context.view_layer, FEATURES, seed=seed) as exe:
                h, w = exe.size
                out = {k: [] for k in ("color",) + FEATURES}
                for task in subset_tasks(w, h, SUBSETS, SUBSETS, 1):
                    color, feats = exe.render(task)
                    one = Buffers.empty(h, w, FEATURES + ("alpha",))
                    merge_render(one, task, color, feats)  # what render_subsets does per task
                    out["color"].append(one.color.mean.astype(np.float32))
                    for f in FEATURES:
                        out[f].append(one.features[f].mean.astype(np.float32))
            np.savez(data_path(args, name, seed), **{k: np.stack(v) for k, v in out.items()})
            print(name, seed, f"{time.perf_counter() - t0:.1f} s", flush=True)


def initial_pass(d, spp, subsets=4):
    """Buffers of the loop's initial pass: ``spp`` samples in ``subsets``
    consecutive subsets, merged from the one-sample renders; also the subset
    means (for :func:`core.variance.stratification_exponent`)."""
    k1 = d["color"].shape[0]
    if spp > k1:
        raise ValueError(f"need {spp} one-sample renders, have {k1}")
    h, w = d["color"].shape[1:3]
    buf = Buffers.empty(h, w, FEATURES)
    m = spp // subsets
    groups = []
    for g in range(subsets):
        sl = slice(g * m, (g + 1) * m)
        c = d["color"][sl].mean(0)
        buf.merge_group(c, m, {f: d[f][sl].mean(0) for f in FEATURES})
        groups.append(c)
    return buf, groups


def exp_measure(args):
    from cycles_adaptive.core import variance
    rows = []
    for name in args.scenes:
        ref_path = os.path.join(args.refs, f"{name}.f0001.r100.s1024.exr")
        layers, _ = imageio.read_layers(ref_path)
        ref = imageio.read_reference(ref_path)
        ref_var = _ref_variance(layers, ref.shape)
        for spp in args.spp:
            raw_r, cal_r, pool_r, betas, noise = [], [], [], [], []
            calc_r, cal0_r, spread, loc_r = [], [], [], []
            for seed in args.seeds:
                d = {k: v.astype(np.float64) for k, v in np.load(data_path(args, name, seed)).items()}
                buf, groups = initial_pass(d, spp)
                mean = buf.color.mean
                beta = variance.stratification_exponent(groups, buf.color.mean)
                raw = buf.variance_of_mean()
                pooled = variance.calibrated_variance_of_mean(buf, exponent=1.0)
                cal = variance.calibrated_variance_of_mean(buf, exponent=beta)
                cal_c = variance.calibrated_variance_of_mean(buf, exponent=beta, color_guide=True)
                cal0 = variance.calibrated_variance_of_mean(buf, exponent=beta, radius=0)
                beta_map = variance.stratification_exponent(groups, buf.color.mean, radius=LOCAL_RADIUS)
                loc_r.append(variance.calibration_ratio(
                    variance.calibrated_variance_of_mean(buf, exponent=beta_map), mean, ref, ref_var))
                raw_r.append(variance.calibration_ratio(raw, mean, ref, ref_var))
                pool_r.append(variance.calibration_ratio(pooled, mean, ref, ref_var))
                cal_r.append(variance.calibration_ratio(cal, mean, ref, ref_var))
                calc_r.append(variance.calibration_ratio(cal_c, mean, ref, ref_var))
                cal0_r.append(variance.calibration_ratio(cal0, mean, ref, ref_var))
                spread.append(_log_spread(cal, cal0))
                betas.append(beta)
                err = (mean - ref) ** 2
                noise.append(float(ref_var.sum() / max(err.sum(), 1e-300)))
            row = {"scene": name, "spp": spp, "raw": raw_r, "pooled": pool_r, "calibrated": cal_r,
                   "calibrated_unpooled": cal0_r, "calibrated_local_exponent": loc_r, "calibrated_color_guide": calc_r,
                   "log_sd_pooled_over_unpooled": spread,
                   "exponent": betas, "ref_noise_share": noise}
            rows.append(row)
            print(json.dumps(row), flush=True)
    os.makedirs(args.data, exist_ok=True)
    with open(os.path.join(args.data, "measure.json"), "w") as f:
        json.dump(rows, f, indent=1)
    print()
    print("| scene | spp | exponent | raw | pooled, beta = 1 | calibrated, unpooled | **calibrated** "
          "| calibrated + colour guide | calibrated, local exponent | sd log pooled / unpooled "
          "| ref noise / true |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        fmt = lambda v: " / ".join(f"{x:.2f}" for x in v)
        print(f"| {r['scene']} | {r['spp']} | {fmt(r['exponent'])} | {fmt(r['raw'])} | {fmt(r['pooled'])} "
              f"| {fmt(r['calibrated_unpooled'])} | **{fmt(r['calibrated'])}** | {fmt(r['calibrated_color_guide'])} "
              f"| {fmt(r['calibrated_local_exponent'])} "
              f"| {np.mean(r['log_sd_pooled_over_unpooled']):.2f} | {max(r['ref_noise_share']):.3f} |")


def guard_share(image, buf, var, dof, z=3.0, floor=True):
    """Share of pixels the consistency guard (core.method.consistency_guard)
    would send back to their sample mean when judged with ``var`` and
    Student-t quantiles for ``dof`` degrees of freedom (its rule otherwise:
    standard error floored by its 3x3 median when ``floor``)."""
    from cycles_adaptive.core.method import median3x3, t_quantile
    mean = buf.color.mean
    known = buf.has_variance[..., None] & np.isfinite(var) & np.isfinite(mean)
    sd = np.sqrt(np.where(known, np.maximum(var, 0.0), 0.0))
    if floor:
        sd = np.maximum(sd, median3x3(sd))
    thr = t_quantile(z, np.maximum(dof, 1.0))
    off = np.abs(image - mean) > thr * sd
    bad = (off & known).any(axis=-1) & known.all(axis=-1)
    return float(bad.mean())


def exp_guard(args):
    """Guard share per method at the initial pass (4 spp in 4 subsets,
    default Params, no adaptive iterations): raw variance with k - 1 dof (the
    guard today) vs the calibrated variance with its effective dof."""
    from cycles_adaptive.core import methods as registry
    from cycles_adaptive.core import variance
    rows = []
    for name in args.scenes:
        for seed in args.seeds:
            d = {k: v.astype(np.float64) for k, v in np.load(data_path(args, name, seed)).items()}
            buf, groups = initial_pass(d, args.spp[0])
            beta = variance.stratification_exponent(groups, buf.color.mean)
            raw = buf.variance_of_mean()
            raw_dof = np.broadcast_to((buf.k - 1.0)[..., None], raw.shape)
            cal, cal_dof = variance.calibrated_variance_and_dof(buf, exponent=beta)
            for m in args.methods:
                mod = registry.get(m)
                t0 = time.perf_counter()
                res = mod.reconstruct(buf, mod.Params())
                sec = time.perf_counter() - t0
                row = {"scene": name, "seed": seed, "method": m, "seconds": sec,
                       "raw": guard_share(res.image, buf, raw, raw_dof),
                       "calibrated": guard_share(res.image, buf, cal, cal_dof),
                       "calibrated_no_floor": guard_share(res.image, buf, cal, cal_dof, floor=False)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    os.makedirs(args.data, exist_ok=True)
    with open(os.path.join(args.data, "guard.json"), "w") as f:
        json.dump(rows, f, indent=1)
    print()
    print("| scene | method | guard share, raw variance, k-1 dof | calibrated, effective dof | "
          "calibrated, no 3x3 floor |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['method']} | {100 * r['raw']:.1f} % | {100 * r['calibrated']:.1f} % "
              f"| {100 * r['calibrated_no_floor']:.1f} % |")


def exp_curve(args):
    """True error of the mean of x consecutive samples, v(x) (relMSE-weighted
    sum over pixels, reference noise subtracted), averaged over every aligned
    block of x samples and the seeds, and its local slopes -d log v / d log x:
    the exponent each octave really has."""
    print("| scene | v(1) | v(2) | v(4) | v(8) | v(16) | slope 1-2 | 2-4 | 4-8 | 8-16 |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in args.scenes:
        ref_path = os.path.join(args.refs, f"{name}.f0001.r100.s1024.exr")
        layers, _ = imageio.read_layers(ref_path)
        ref = imageio.read_reference(ref_path)
        ref_var = _ref_variance(layers, ref.shape)
        w = 1.0 / (ref * ref + 0.01)
        cols = [np.load(data_path(args, name, s))["color"].astype(np.float64) for s in args.seeds]
        v = []
        for x in (1, 2, 4, 8, 16):
            vals = [(w * ((c[g * x:(g + 1) * x].mean(0) - ref) ** 2 - ref_var)).sum()
                    for c in cols for g in range(SUBSETS // x)]
            v.append(float(np.mean(vals)))
        slopes = -np.diff(np.log(v)) / np.log(2.0)
        print(f"| {name} | " + " | ".join(f"{x:.3g}" for x in v) + " | "
              + " | ".join(f"{x:.2f}" for x in slopes) + " |", flush=True)


def exp_weights(args):
    """Sensitivity of the calibrated ratio to the weights of the exponent's
    frame sums: the noisy mean (default), a 5x5 box mean, the reference
    (not available in a run), none."""
    from cycles_adaptive.core import variance
    from cycles_adaptive.core.filters import box_mean
    print("| scene | spp | mean (default) | 5x5 box mean | reference | unweighted |")
    print("|---|---|---|---|---|---|")
    for name in args.scenes:
        ref_path = os.path.join(args.refs, f"{name}.f0001.r100.s1024.exr")
        layers, _ = imageio.read_layers(ref_path)
        ref = imageio.read_reference(ref_path)
        ref_var = _ref_variance(layers, ref.shape)
        for spp in args.spp:
            res = {}
            for seed in args.seeds:
                d = {k: v.astype(np.float64) for k, v in np.load(data_path(args, name, seed)).items()}
                buf, g = initial_pass(d, spp)
                m = buf.color.mean
                for key, w in (("mean", 1 / (m * m + 0.01)), ("box", 1 / (box_mean(m, 2) ** 2 + 0.01)),
                               ("ref", 1 / (ref * ref + 0.01)), ("none", None)):
                    s_k = variance.group_spread(g, w)
                    s_p = variance.group_spread([(g[0] + g[1]) / 2, (g[2] + g[3]) / 2], w)
                    b = variance._invert_ratio(s_k / s_p, 4)
                    est = variance.calibrated_variance_of_mean(buf, exponent=b)
                    res.setdefault(key, []).append(variance.calibration_ratio(est, m, ref, ref_var))
            print(f"| {name} | {spp} | " + " | ".join(f"{np.mean(res[k]):.2f}" for k in ("mean", "box", "ref", "none"))
                  + " |", flush=True)


def _log_spread(pooled, unpooled):
    """sd of log(pooled) over sd of log(unpooled) on pixels where both are
    finite and positive: how much the pooling narrows the estimate's noise."""
    ok = np.isfinite(pooled) & np.isfinite(unpooled) & (pooled > 0) & (unpooled > 0)
    if ok.sum() < 2:
        return float("nan")
    return float(np.std(np.log(pooled[ok])) / max(np.std(np.log(unpooled[ok])), 1e-300))


def _ref_variance(layers, shape):
    """The reference's Variance layer (variance of its mean), (H, W, 3); zeros
    when it has none."""
    for k, v in layers.items():
        if k.split(".")[0].lower() == "variance" or k.lower().startswith("variance"):
            v = np.asarray(v, np.float64)
            return np.where(np.isfinite(v), v, 0.0)[..., :3].reshape(shape)
    return np.zeros(shape)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("command", choices=("render", "measure", "guard", "curve", "weights"))
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--spp", default="4,8,16")
    ap.add_argument("--methods", default="awr,lp,rhf", help="guard: methods to reconstruct")
    ap.add_argument("--data", default="/tmp/measure_variance")
    ap.add_argument("--refs", default="/work/refs")
    args = ap.parse_args()
    args.seeds = [int(s) for s in args.seeds.split(",")]
    args.scenes = [s for s in args.scenes.split(",") if s]
    args.spp = [int(s) for s in args.spp.split(",")]
    args.methods = [m for m in args.methods.split(",") if m]
    {"render": exp_render, "measure": exp_measure, "guard": exp_guard, "curve": exp_curve, "weights": exp_weights}[args.command](args)


if __name__ == "__main__":
    main()

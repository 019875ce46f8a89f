"""Measurements behind docs/notes/oidn.md (developer tool, not shipped).

Exact per-pixel emulation (DESIGN.md): 128 one-sample subset renders of each
sample scene are stored once; any sample map is then answered from them (a
task's mean is a difference of cumulative sums), so OIDN's error vs spp, the
dual-buffer estimate and whole adaptive runs are measured without rendering
again.  Subcommands (from the repository root):

    .venv/bin/python tools/oidn_study.py render --seeds 11,12   # one-sample renders, ~20 s a scene
    .venv/bin/python tools/oidn_study.py rate --seeds 11        # OIDN relMSE vs spp per prefilter
    .venv/bin/python tools/oidn_study.py estimate --seeds 11    # dual-buffer estimate vs true error
    .venv/bin/python tools/oidn_study.py loop --seeds 11,12 --guard 0 --iterations 2 --task-cost 0 \
        --oracle --variants '[{}, {"allocation": "topup"}]'    # oidn vs uniform + OIDN, AdaptiveRun
    .venv/bin/python tools/oidn_study.py mc                     # constant + bias term, real OIDN
    .venv/bin/python tools/oidn_study.py cost --size 512        # s/MP: pyoidn vs Cycles' own OIDN
    .venv/bin/python tools/oidn_study.py calib --seeds 0 --spp 4,8,16 --reps 8
        # the estimate's terms against Var[D] and MSE over disjoint realisations
    .venv/bin/python tools/oidn_study.py peer --seeds 0,1 --spp 8,16   # pyoidn vs Cycles' OIDN, same render
    .venv/bin/python tools/oidn_study.py prefix --seeds 0,1 --spp 8,16 --holds 32,64,128
        # samples [0, L) of a count-held Blue Noise table against plain L-spp renders
    .venv/bin/python tools/oidn_study.py ceiling --reps 16 --spp 8,16
        # the best correlation any error map can have with one render's true error

``--data`` (default out/oidn_study) holds the renders and results; ``--refs``
(default /work/refs) the 1024-spp references (bench/references.py names).
"""
import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tests"))
from launch import load_package  # noqa: E402

load_package()
from cycles_adaptive.core import oidn  # noqa: E402
from cycles_adaptive.core.filters import box_mean  # noqa: E402
from cycles_adaptive.core.io import read_reference  # noqa: E402
from cycles_adaptive.core.metrics import relmse, per_pixel_relmse  # noqa: E402
from cycles_adaptive.core.oracle import OracleMethod  # noqa: E402
from cycles_adaptive.core.pipeline import AdaptiveRun, Options  # noqa: E402

ARGS = None


SCENES = ("cornell", "dof", "glossy", "motion_blur", "soft_shadows", "animated")


def load(scene, seed, n=128):
    d = np.load(f"{ARGS.data}/{scene}.s{seed}.n{n}.npz")
    return {k: d[k].astype(np.float64) for k in ("color", "albedo", "normal")}


def ref(scene):
    return read_reference(f"{ARGS.refs}/{scene}.f0001.r100.s1024.exr")


def floor(scene):
    return json.load(open(f"{ARGS.refs}/{scene}.f0001.r100.s1024.json"))["noise_relmse"]


class Emu:
    """Executor answering region tasks from stored one-sample renders."""

    def __init__(self, s):
        self.s = s
        self.size = s["color"].shape[1:3]
        self.cum = {k: np.concatenate([np.zeros((1,) + v.shape[1:]), np.cumsum(v, axis=0)])
                    for k, v in s.items()}
        self.max_index = 0

    def render(self, t):
        a, b = t.offset, t.offset + t.samples
        if b > self.s["color"].shape[0]:
            raise RuntimeError(f"emulation needs sample {b}")
        self.max_index = max(self.max_index, b)
        m = {k: (c[b, t.y0:t.y1, t.x0:t.x1] - c[a, t.y0:t.y1, t.x0:t.x1]) / t.samples
             for k, c in self.cum.items()}
        rgba = np.concatenate([m["color"], np.ones(m["color"].shape[:2] + (1,))], -1)
        return rgba, {"albedo": m["albedo"], "normal": m["normal"]}


def mean_of(s, idx):
    return {k: v[idx].mean(0) for k, v in s.items()}


def den(m, p):
    return oidn.oidn_filter(m["color"], m["albedo"], m["normal"], quality=p.quality,
                            prefilter=p.prefilter)


def exp_rate(args):
    """relMSE of OIDN on uniform n spp, per prefilter; slope 4..32."""
    rows = []
    for scene in SCENES:
        r = ref(scene)
        for seed in args.seeds:
            s = load(scene, seed)
            for pre in ("fast", "accurate", "none"):
                p = oidn.Params(prefilter=pre)
                errs = {}
                for n in (2, 4, 8, 16, 32, 64, 128):
                    errs[n] = relmse(den(mean_of(s, slice(0, n)), p), r)
                rows.append({"scene": scene, "seed": seed, "prefilter": pre, "relmse": errs,
                             "floor": floor(scene)})
                print(scene, seed, pre, {k: f"{v:.2e}" for k, v in errs.items()}, flush=True)
    json.dump(rows, open(f"{ARGS.data}/rate.json", "w"))


def corr(a, b):
    a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def exp_estimate(args):
    """The implementation's estimate (core.oidn.estimate: shared guides) vs the
    true error at uniform n spp; halves as the loop makes them from its 4
    initial subsets (A = subsets 0 and 2)."""
    rows = []
    for scene in SCENES:
        r = ref(scene)
        fl = floor(scene)
        for seed in args.seeds:
            s = load(scene, seed)
            for n in (4, 8, 16):
                g = n // 4
                ia = np.r_[0:g, 2 * g:3 * g]
                ib = np.r_[g:2 * g, 3 * g:4 * g]
                full, a, b = mean_of(s, slice(0, n)), mean_of(s, ia), mean_of(s, ib)
                res = oidn.estimate(full["color"], full, (a["color"], b["color"]), n / 2, n / 2,
                                    oidn.Params(pool_radius=0, bias_weight=1.0))
                d = res.image
                var0, bias0 = res.fit.variance, res.fit.bias
                true = per_pixel_relmse(d, r)
                row = {"scene": scene, "seed": seed, "n": n, "true": float(true.mean()), "floor": fl}
                blk = lambda x: x.reshape(x.shape[0] // 8, 8, x.shape[1] // 8, 8).mean((1, 3))
                for name, e3 in (("var", var0), ("var+bias", var0 + bias0)):
                    rel = oidn.relative_map(e3, d)
                    row[name] = float(rel.mean())
                    row[name + "_corr1"] = corr(rel, true)
                    row[name + "_corr7"] = corr(box_mean(rel, 3), box_mean(true, 3))
                    row[name + "_corr15"] = corr(box_mean(rel, 7), box_mean(true, 7))
                    row[name + "_corr_block8"] = corr(blk(rel), blk(true))
                rows.append(row)
                print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}),
                      flush=True)
    json.dump(rows, open(f"{ARGS.data}/estimate.json", "w"))


OPTION_KEYS = ("task_cost", "initial_spp", "subsets", "max_pixel_share", "min_task_size", "guard_z")


TASK_COST = [None]


def run_loop(s, method, spp, seed, params, iterations=4, guard=3.0):
    params = dict(params)
    if TASK_COST[0] is not None:
        params.setdefault("task_cost", TASK_COST[0])
    extra = {k: params.pop(k) for k in OPTION_KEYS if k in params}
    extra.setdefault("guard_z", guard)
    opts = Options(method="uniform", spp=spp, initial_spp=extra.pop("initial_spp", 4),
                   iterations=iterations, seed=seed, params=params, **extra)
    ex = Emu(s)
    run = AdaptiveRun(ex, opts, method=method)
    for _ in run.steps():
        pass
    res = run.reconstruct()
    return res, run, ex


def exp_loop(args):
    rows = []
    variants = json.loads(args.variants) if args.variants else [{}]
    for scene in args.scenes:
        r = ref(scene)
        for seed in args.seeds:
            s = load(scene, seed)
            for spp in args.spp:
                t0 = time.perf_counter()
                base, _, _ = run_loop(s, oidn.UNIFORM, spp, seed, {}, guard=args.guard)
                if args.guard > 0:
                    b0, _, _ = run_loop(s, oidn.UNIFORM, spp, seed, {}, guard=0.0)
                    row_guard0 = relmse(b0.image, r)
                else:
                    row_guard0 = None
                e_u = relmse(base.image, r)
                row = {"scene": scene, "seed": seed, "spp": spp, "uniform": e_u, "floor": floor(scene)}
                if row_guard0 is not None:
                    row["uniform_noguard"] = row_guard0
                if args.oracle:
                    orc = OracleMethod(oidn, r, radius=3)
                    res, run, ex = run_loop(s, orc, spp, seed, {}, 3, args.guard)
                    row["oracle"] = relmse(res.image, r)
                for i, v in enumerate(variants):
                    v = dict(v)
                    its = v.pop("iterations", args.iterations)
                    res, run, ex = run_loop(s, oidn, spp, seed, v, its, args.guard)
                    row[f"v{i}"] = relmse(res.image, r)
                    row[f"v{i}_spp"] = run.samples_rendered / run.pixels
                    row[f"v{i}_maxidx"] = ex.max_index
                rows.append(row)
                print(json.dumps({k: (round(x, 6) if isinstance(x, float) else x) for k, x in row.items()}),
                      f"{time.perf_counter() - t0:.1f}s", flush=True)
    out = args.out or f"{ARGS.data}/loop.json"
    json.dump({"variants": variants, "rows": rows}, open(out, "w"))
    gm = lambda key: float(np.exp(np.mean([np.log(rw["uniform"] / rw[key]) for rw in rows])))
    for i in range(len(variants)):
        print("variant", i, variants[i], "geomean gain over uniform+OIDN", round(gm(f"v{i}"), 3))
    if args.oracle:
        print("oracle gain", round(gm("oracle"), 3))


def exp_render(args):
    """128 one-sample subsets (offset i, length 1) of each scene at frame 1."""
    import bpy
    from cycles_adaptive.addon.executor import CyclesExecutor
    from cycles_adaptive.core import regions
    os.makedirs(args.data, exist_ok=True)
    for seed in args.seeds:
        for scene_name in args.scenes:
            bpy.ops.wm.open_mainfile(filepath=os.path.join(ROOT, "sample_blends", scene_name + ".blend"))
            scene = bpy.context.scene
            scene.frame_set(1)
            t0 = time.perf_counter()
            with CyclesExecutor(scene, bpy.context.view_layer, ("albedo", "normal"), seed=seed) as ex:
                h, w = ex.size
                arr = {k: np.zeros((args.samples, h, w, 3), np.float32) for k in ("color", "albedo", "normal")}
                for i in range(args.samples):
                    c, f = ex.render(regions.RegionTask(0, 0, w, h, 1, frame=1, offset=i))
                    arr["color"][i], arr["albedo"][i], arr["normal"][i] = c[:, :, :3], f["albedo"], f["normal"]
            np.savez(f"{args.data}/{scene_name}.s{seed}.n{args.samples}.npz", **arr)
            print(scene_name, seed, f"{time.perf_counter() - t0:.1f} s", flush=True)


def exp_mc(args):
    """Real OIDN on a synthetic image (checker albedo under a light blob),
    multiplicative Gaussian noise: empirical Var[D] and MSE over
    realisations against the variance and bias terms."""
    rng = np.random.default_rng(0)
    h = w = 64
    y, x = np.mgrid[0:h, 0:w] / 64.0
    alb = np.stack([0.2 + 0.6 * ((np.floor(x * 8) + np.floor(y * 8)) % 2), 0.5 + 0.0 * x, 0.3 + 0.4 * y], -1)
    light = 0.5 + 2.0 * np.exp(-((x - 0.5) ** 2 + (y - 0.4) ** 2) / 0.05)
    mu = alb * light[..., None]
    feats = {"albedo": alb, "normal": np.dstack([np.zeros((h, w))] * 2 + [np.ones((h, w))])}
    for n_half in (2, 4):
        ds, var_est, bias_est = [], [], []
        for _ in range(args.reps):
            sa = mu * (1 + rng.standard_normal((n_half, h, w, 3)).mean(0))
            sb = mu * (1 + rng.standard_normal((n_half, h, w, 3)).mean(0))
            res = oidn.estimate((sa + sb) / 2, feats, ((sa, feats), (sb, feats)), n_half, n_half,
                                oidn.Params(pool_radius=0))
            ds.append(res.image)
            var_est.append(res.fit.variance.mean())
            bias_est.append(res.fit.bias.mean())
        ds = np.array(ds)
        emp_var, emp_mse = ds.var(0, ddof=1).mean(), ((ds - mu) ** 2).mean()
        emp_bias2 = ((ds.mean(0) - mu) ** 2).mean()
        v, b = np.mean(var_est), np.mean(bias_est)
        print(f"n={2 * n_half} R={args.reps}: Var[D] {emp_var:.3e}, c|D(A)-D(B)|^2 {v:.3e} "
              f"(ratio {v / emp_var:.2f}); bias^2 {emp_bias2:.3e}, bias term {b:.3e}; "
              f"MSE {emp_mse:.3e}, estimate {v + b:.3e} (ratio {(v + b) / emp_mse:.2f})")


def exp_cost(args):
    """Seconds per megapixel of one OIDN call: Cycles' own OIDN (render with
    denoising minus without, accurate prefilter, high) against pyoidn and
    Blender's compositor node on the same passes, alternated, medians."""
    import tempfile
    import bpy
    from cycles_adaptive.addon import oidn_blender
    from cycles_adaptive.addon.executor import quiet_stdout
    from cycles_adaptive.core import io as imageio
    size = args.size
    bpy.ops.wm.open_mainfile(filepath=os.path.join(ROOT, "sample_blends", "cornell.blend"))
    s = bpy.context.scene
    s.render.resolution_x = s.render.resolution_y = size
    s.render.resolution_percentage = 100
    s.cycles.samples = 1
    s.cycles.use_adaptive_sampling = False
    s.render.use_compositing = False
    bpy.context.view_layer.cycles.denoising_store_passes = True
    s.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    s.render.image_settings.color_depth = "32"
    tmp = tempfile.mkdtemp()

    def render(denoise):
        s.cycles.use_denoising = denoise
        s.cycles.denoiser = "OPENIMAGEDENOISE"
        s.cycles.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        s.cycles.denoising_prefilter = "ACCURATE"
        if hasattr(s.cycles, "denoising_quality"):
            s.cycles.denoising_quality = "HIGH"
        s.render.filepath = os.path.join(tmp, "r.exr")
        t = time.perf_counter()
        with quiet_stdout():
            bpy.ops.render.render(write_still=True)
        dt = time.perf_counter() - t
        return dt, imageio.read_layers(s.render.filepath)[0]

    render(False)
    render(True)
    keys = ("cycles_plain", "cycles_oidn", "pyoidn_accurate", "pyoidn_fast", "pyoidn_none", "blender_accurate")
    rows = {k: [] for k in keys}
    oidn_blender.register()
    for _ in range(args.reps_cost):
        t0, p0 = render(False)
        t1, _ = render(True)
        rows["cycles_plain"].append(t0)
        rows["cycles_oidn"].append(t1)
        c, a, n = p0["Combined"][:, :, :3], p0["Denoising Albedo"], p0["Denoising Normal"]
        for pre in ("accurate", "fast", "none"):
            t = time.perf_counter()
            oidn.oidn_filter(c, a, n, prefilter=pre, backend="pyoidn")
            rows[f"pyoidn_{pre}"].append(time.perf_counter() - t)
        t = time.perf_counter()
        oidn.oidn_filter(c, a, n, prefilter="accurate", backend="blender")
        rows["blender_accurate"].append(time.perf_counter() - t)
    mp = size * size / 1e6
    med = {k: float(np.median(v)) for k, v in rows.items()}
    cyc = med["cycles_oidn"] - med["cycles_plain"]
    print(f"{bpy.app.version_string} {size}x{size} ({mp:.3f} MP), medians of {args.reps_cost}, "
          f"{os.cpu_count()} CPUs")
    print(f"Cycles 1 spp: {med['cycles_plain']:.3f} s; with its OIDN (accurate, high): {med['cycles_oidn']:.3f} s;"
          f" Cycles' OIDN {cyc:.3f} s = {cyc / mp:.2f} s/MP")
    for k in keys[2:]:
        print(f"{k}: {med[k]:.3f} s = {med[k] / mp:.2f} s/MP, {med[k] / cyc:.2f}x Cycles' OIDN")


def best_ref(scene):
    """The reference of ``scene`` with the most samples in ``--refs``."""
    import glob
    found = glob.glob(f"{ARGS.refs}/{scene}.f0001.r100.s*.exr")
    return read_reference(max(found, key=lambda p: int(p.rsplit(".s", 1)[1].split(".")[0])))[..., :3]


def exp_calib(args):
    """Calibration of the dual-buffer estimate over realisations: the stored
    one-sample renders give ``128 / n`` disjoint blocks of ``n`` consecutive
    samples (at most ``--reps``), each split as the loop's initial pass (4
    groups, A = 0 and 2).  Per scene and n (metric-weighted frame means):
    MSE and Var[D] over the realisations, the variance term with the i.i.d.
    constant and with the measured stratification scale (vs Var[D]), the
    bias term, the whole estimate pooled relative (the implementation) and
    pooled absolute (before), each over MSE, and for the sample means
    ``c |x_A - x_B|^2 / Var[x]`` (the stratification's effect)."""
    from cycles_adaptive.core.buffers import Buffers
    from cycles_adaptive.core.metrics import REL_EPS
    from cycles_adaptive.core.variance import stratification_exponent
    for scene in args.scenes:
        r = best_ref(scene)
        w = 1.0 / (r * r + REL_EPS)
        for seed in args.seeds:
            s = load(scene, seed)
            for n in [int(x) for x in args.spp]:
                reps, g = min(args.reps, s["color"].shape[0] // n), n // 4
                ds, var_iid, var_s, bias, rel_pool, abs_pool, xs, half2 = ([] for _ in range(8))
                for k in range(reps):
                    o = k * n
                    full = mean_of(s, slice(o, o + n))
                    a = mean_of(s, np.r_[o:o + g, o + 2 * g:o + 3 * g])
                    b = mean_of(s, np.r_[o + g:o + 2 * g, o + 3 * g:o + 4 * g])
                    res = oidn.estimate(full["color"], full, ((a["color"], a), (b["color"], b)), n / 2, n / 2,
                                        oidn.Params(pool_radius=0))
                    d = res.image
                    ds.append(d)
                    var_iid.append((res.fit.variance * w).mean())
                    bias.append((res.fit.bias * w).mean())
                    xs.append(full["color"])
                    half2.append(((a["color"] - b["color"]) ** 2 / 4 * w).mean())
                    # the scale as reconstruct measures it, from the subsets' calibrated variance
                    subs = [mean_of(s, slice(o + i * g, o + (i + 1) * g)) for i in range(4)]
                    buf = Buffers.from_subsets([u["color"] for u in subs], [g] * 4,
                                               [{"albedo": u["albedo"], "normal": u["normal"]} for u in subs])
                    buf.exponent = stratification_exponent([u["color"] for u in subs])
                    scale = oidn.stratification_scale(buf.calibrated_variance(), a["color"], b["color"],
                                                      np.full(d.shape[:2], n / 2), np.full(d.shape[:2], n / 2), d)
                    var_s.append(scale * var_iid[-1])
                    terms = res.fit.variance * scale + res.fit.bias
                    rel_pool.append(box_mean((terms / (d * d + REL_EPS)).mean(-1), 3).mean())
                    abs_pool.append(oidn.relative_map(box_mean(terms, 3), d).mean())
                ds, xs = np.array(ds), np.array(xs)
                mse = float((((ds - r) ** 2) * w).mean())
                vd = float((ds.var(0, ddof=1) * w).mean())
                vx = float((xs.var(0, ddof=1) * w).mean())
                row = {"scene": scene, "seed": seed, "n": n, "reps": reps, "mse": mse, "var_D": vd,
                       "var_iid/var_D": np.mean(var_iid) / vd, "var_scaled/var_D": np.mean(var_s) / vd,
                       "bias/mse": np.mean(bias) / mse, "estimate_pooled_rel/mse": np.mean(rel_pool) / mse,
                       "estimate_pooled_abs/mse": np.mean(abs_pool) / mse, "halves_x/var_x": np.mean(half2) / vx}
                print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}),
                      flush=True)


def exp_peer(args):
    """Our OIDN call against Cycles' own on the very same render: one plain
    render per scene, seed, pattern and spp with Cycles' OIDN on (accurate,
    high) that also stores its inputs (Noisy Image, Denoising Albedo and
    Normal); pyoidn then denoises those inputs as oidn_filter does.  Separates
    the denoiser call from the sampling pattern (Tabulated Sobol in our loop)
    in the gap between the ``oidn`` method and the cycles_oidn peer."""
    import tempfile
    import bpy
    tmp = tempfile.mkdtemp()
    rows = []
    for scene in args.scenes:
        truth = best_ref(scene)
        for seed in args.seeds:
            for pattern in args.patterns.split(","):
                for spp in args.spp:
                    bpy.ops.wm.open_mainfile(filepath=os.path.join(ROOT, "sample_blends", f"{scene}.blend"))
                    s = bpy.context.scene
                    s.frame_set(1)
                    c = s.cycles
                    c.samples, c.seed, c.use_animated_seed = int(spp), seed, False
                    c.sampling_pattern = pattern
                    c.use_adaptive_sampling = False
                    c.use_denoising, c.denoiser = True, "OPENIMAGEDENOISE"
                    c.denoising_input_passes, c.denoising_prefilter = "RGB_ALBEDO_NORMAL", "ACCURATE"
                    if hasattr(c, "denoising_quality"):
                        c.denoising_quality = "HIGH"
                    c.denoising_use_gpu = False
                    p = render_layers(s, tmp)
                    noisy = p["Noisy Image"][..., :3].astype(np.float64)
                    theirs = p["Combined"][..., :3].astype(np.float64)
                    ours = oidn.oidn_filter(noisy, p["Denoising Albedo"][..., :3], p["Denoising Normal"][..., :3],
                                            prefilter="accurate", quality="high", backend="pyoidn")
                    r = {"scene": scene, "seed": seed, "pattern": pattern, "spp": spp,
                         "noisy": relmse(noisy, truth), "cycles_oidn": relmse(theirs, truth),
                         "pyoidn": relmse(ours, truth), "apart": relmse(ours, theirs)}
                    rows.append(r)
                    print(f"{scene:>12} seed {seed} {pattern:>15} {spp:4.0f} spp: noisy {r['noisy']:.3e} | "
                          f"Cycles' OIDN {r['cycles_oidn']:.3e} | pyoidn on its inputs {r['pyoidn']:.3e} "
                          f"({r['pyoidn'] / r['cycles_oidn']:.3f}x) | the two apart {r['apart']:.2e}", flush=True)
    save_rows(rows, args.out)


_TMP: dict = {}


def save_rows(rows, out: str) -> None:
    """The experiment's rows as JSON to ``out`` (nothing when empty)."""
    if out:
        with open(out, "w") as f:
            json.dump(rows, f, indent=1)


def render_layers(s, tmp):
    """Render scene ``s`` with its denoising passes stored into a 32-bit
    multilayer EXR under ``tmp``; the first view layer's passes (name ->
    array)."""
    import bpy
    from cycles_adaptive.addon.executor import quiet_stdout
    from cycles_adaptive.core import io as imageio
    s.render.use_compositing = False
    bpy.context.view_layer.cycles.denoising_store_passes = True
    if hasattr(s.render.image_settings, "media_type"):
        s.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    s.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    s.render.image_settings.color_depth = "32"
    s.render.filepath = os.path.join(tmp, "r.exr")
    with quiet_stdout():
        bpy.ops.render.render(write_still=True)
    return imageio.read_layers(s.render.filepath)[0]


def plain_render(scene, seed, spp, pattern="TABULATED_SOBOL", hold=0, tmp=None):
    """One plain render of a sample scene in a freshly opened file: ``spp``
    samples (with ``hold``: samples [0, spp) of ``pattern`` held at ``hold``)
    with the denoising passes stored.  Returns (colour, albedo, normal)."""
    import tempfile
    import bpy
    if tmp is None:
        tmp = _TMP.setdefault("dir", tempfile.mkdtemp())
    bpy.ops.wm.open_mainfile(filepath=os.path.join(ROOT, "sample_blends", f"{scene}.blend"))
    s = bpy.context.scene
    s.frame_set(1)
    c = s.cycles
    c.seed, c.use_animated_seed = seed, False
    c.sampling_pattern = pattern
    c.use_adaptive_sampling = False
    c.use_denoising = False
    s.render.use_persistent_data = False
    if hold:
        c.samples, c.sample_offset = hold, 0
        c.use_sample_subset, c.sample_subset_length = True, int(spp)
    else:
        c.samples = int(spp)
    p = render_layers(s, tmp)
    return tuple(p[k][..., :3].astype(np.float64) for k in ("Combined", "Denoising Albedo", "Denoising Normal"))


def exp_prefix(args):
    """Is a prefix of a count-held Blue Noise sequence as good as the plain
    render of its length?  An adaptive run ends with unequal counts, so it
    cannot hold ``samples`` at every pixel's final count; it could hold it at
    one upper bound H (every pixel's samples [0, n_i) of the H-spp table).
    Per scene, seed and length L: plain renders of L spp with the scene's
    pattern and with Tabulated Sobol, and samples [0, L) of the scene's
    pattern held at each H of ``--holds``; relMSE before and after OIDN
    (pyoidn on the render's Noisy Image, Denoising Albedo and Normal, accurate
    prefilter), each render in a freshly opened file."""
    rows = []
    for scene in args.scenes:
        truth = best_ref(scene)
        for seed in args.seeds:
            for spp in args.spp:
                L = int(spp)
                cases = [("TABULATED_SOBOL", 0), ("AUTOMATIC", 0)] + [("AUTOMATIC", h) for h in args.holds if h > L]
                for pattern, hold in cases:
                    noisy, alb, nrm = plain_render(scene, seed, L, pattern, hold)
                    den_ = oidn.oidn_filter(noisy, alb, nrm, prefilter="accurate", quality="high", backend="pyoidn")
                    r = {"scene": scene, "seed": seed, "spp": L, "pattern": pattern, "hold": hold,
                         "noisy": relmse(noisy, truth), "oidn": relmse(den_, truth)}
                    rows.append(r)
                    print(f"{scene:>12} seed {seed} {L:3d} spp {pattern:>15} hold {hold:4d}: "
                          f"noisy {r['noisy']:.4e} oidn {r['oidn']:.4e}", flush=True)
    save_rows(rows, args.out)


def _pearson(a, b) -> float:
    a, b = np.ravel(a) - np.mean(a), np.ravel(b) - np.mean(b)
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else 0.0


def _blocks8(x):
    h, w = (x.shape[0] // 8) * 8, (x.shape[1] // 8) * 8
    return x[:h, :w].reshape(h // 8, 8, w // 8, 8).mean(axis=(1, 3))


def _pair_correlation(e) -> float:
    """Mean Pearson correlation between the error maps of two different
    renders, ``(K, ...)`` stacked."""
    flat = e.reshape(len(e), -1)
    c = np.corrcoef(flat)
    return float(c[~np.eye(len(e), dtype=bool)].mean())


def exp_ceiling(args):
    """How well can any error map correlate with the true error of one
    render?  The benchmark's figure is the Pearson correlation of the
    estimated squared error with the true one, ``mean_c (x - r)^2``, of a
    single render: one noisy realisation of the pixel's expected squared
    error ``E``.  Even ``E`` itself correlates with it below 1: for two
    independent renders j, k, ``cov(e_j, e_k) = Var(E)``, so
    ``corr(E, e_k) = sqrt(corr(e_j, e_k))``, the square root of the mean
    pairwise correlation of ``--reps`` renders' error maps (seeds 0..reps-1,
    Tabulated Sobol, and their OIDN with the accurate prefilter).  That is the
    ceiling any estimate reaches, per pixel and on 8x8 blocks (the
    benchmark's '8x8' column, the planner's scale), in the benchmark's
    absolute form and in the metric's relative one ``(x - r)^2 / (r^2 +
    0.01)`` (in the absolute form a single bright pixel can rule it)."""
    rows = []
    for scene in args.scenes:
        truth = best_ref(scene)
        for spp in args.spp:
            errs = {(m, f): [] for m in ("mean", "oidn") for f in ("absolute", "relative")}
            for seed in range(args.reps):
                x, alb, nrm = plain_render(scene, seed, int(spp))
                d = oidn.oidn_filter(x, alb, nrm, prefilter="accurate", quality="high", backend="pyoidn")
                for name, img in (("mean", x), ("oidn", d)):
                    errs[name, "absolute"].append(((img - truth) ** 2).mean(axis=-1))
                    errs[name, "relative"].append(per_pixel_relmse(img, truth))
            for (name, form), e in errs.items():
                e = np.stack(e)
                pix = _pair_correlation(e)
                blk = _pair_correlation(np.stack([_blocks8(x) for x in e]))
                r = {"scene": scene, "spp": spp, "method": name, "form": form, "reps": len(e),
                     "pair_pixel": pix, "pair_8x8": blk,
                     "ceiling_pixel": float(np.sqrt(max(pix, 0.0))), "ceiling_8x8": float(np.sqrt(max(blk, 0.0)))}
                rows.append(r)
                print(f"{scene:>12} {spp:4.0f} spp {name:>5} {form:>8}: ceiling per pixel {r['ceiling_pixel']:.3f} "
                      f"8x8 {r['ceiling_8x8']:.3f} ({len(e)} renders)", flush=True)
    save_rows(rows, args.out)


def main():
    global ARGS
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("exp", choices=("render", "rate", "estimate", "loop", "mc", "cost", "calib", "peer", "prefix", "ceiling"))
    ap.add_argument("--data", default=os.path.join(ROOT, "out", "oidn_study"))
    ap.add_argument("--refs", default="/work/refs")
    ap.add_argument("--samples", type=int, default=128)
    ap.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[11])
    ap.add_argument("--scenes", type=lambda s: s.split(","), default=list(SCENES))
    ap.add_argument("--spp", type=lambda s: [float(x) for x in s.split(",")], default=[8.0, 16.0])
    ap.add_argument("--variants", default="")
    ap.add_argument("--iterations", type=int, default=4)
    ap.add_argument("--guard", type=float, default=3.0)
    ap.add_argument("--oracle", action="store_true")
    ap.add_argument("--out", default="")
    ap.add_argument("--task-cost", type=float, default=None)
    ap.add_argument("--reps", type=int, default=48)
    ap.add_argument("--reps-cost", type=int, default=3)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--patterns", default="AUTOMATIC,TABULATED_SOBOL")
    ap.add_argument("--holds", type=lambda s: [int(x) for x in s.split(",")], default=[32, 64, 128])
    ARGS = args = ap.parse_args()
    TASK_COST[0] = args.task_cost
    {"render": exp_render, "rate": exp_rate, "estimate": exp_estimate, "loop": exp_loop, "mc": exp_mc,
     "cost": exp_cost, "calib": exp_calib, "peer": exp_peer,
     "prefix": exp_prefix, "ceiling": exp_ceiling}[args.exp](args)


if __name__ == "__main__":
    main()

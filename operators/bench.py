"""``./cycles-adaptive bench``: the speed/accuracy trade, per scene, against what
artists use today (issue 7).  Every figure the README quotes comes from here.

One benchmark *session* per invocation, one process, one scene file open at a
time (``bpy.ops.wm.open_mainfile`` once per scene).  Per scene:

1. the reference (``operators/references.py``: >= 1024 spp, seed 1000003, cached,
   refused when from another Blender version);
2. one warm-up render (persistent data stays on for the whole scene, so no run
   measured after it is charged the BVH build / kernel load);
3. the ``t_uniform(e)`` curve: plain Cycles (one render, the scene's own
   sampling pattern, no subsets) at several spp;
4. per budget: our methods through the real loop (``AdaptiveRun`` +
   ``CyclesExecutor``, as ``render`` runs them), the oracle runs (the same loop
   with :class:`core.oracle.OracleMethod` choosing where samples go from the true
   error), and the peers: OIDN on a plain uniform render, Cycles adaptive
   sampling with the noise threshold searched so its time matches our runs at
   that budget, and adaptive sampling + OIDN.

Then the scaling section (reconstruction seconds and peak traced memory per
method at three image sizes, next to OIDN's time at the same sizes) and the
outputs: ``results.json``, ``results.md``, ``plot_<scene>.png`` (relMSE against
seconds, log-log) and ``sheet_<scene>.png``.

Figures (DESIGN.md): relMSE = mean (x - r)^2 / (r^2 + 0.01); SMAPE; efficiency =
1 / (relMSE x seconds); equal-error speed-up = t_uniform(e) / t, t_uniform
interpolated log-log between the plain uniform renders of the same session and
extrapolated with slope -1.
"""
from __future__ import annotations

import json
import math
import os
import platform
import resource
import sys
import time
import tracemalloc
import traceback

import numpy as np

from ..core import io as imageio
from ..core import methods as methods_registry
from ..core import metrics
from ..core.buffers import LUMA
from ..core.pipeline import AdaptiveRun, Options
from . import references as refs

DEFAULT_BUDGETS = (4, 8, 16, 32)
DEFAULT_METHODS = ("uniform", "var", "awr", "lp", "rhf")
DEFAULT_OUT = os.path.join(refs.ROOT, "bench_out")
FEATURES_ALL = ("normal", "albedo", "depth")
#: first guess of Cycles' noise threshold (DESIGN.md anchor: 0.05 on the Cornell box)
FIRST_THRESHOLD = 0.05
THRESHOLD_RANGE = (1e-4, 0.5)
#: a time match within this factor ends the threshold search
TIME_MATCH = 1.2
SEARCH_TRIALS = 3
OIDN_SETTINGS = {"denoiser": "OPENIMAGEDENOISE", "denoising_input_passes": "RGB_ALBEDO_NORMAL",
                 "denoising_prefilter": "ACCURATE"}

QUICK = {"scenes": "cornell", "budgets": "8", "resolution_percentage": 25, "uniform_spp": "4,8,32",
         "scaling_percentages": "25,50", "max_samples_factor": 8}
DEFAULT_SCALING = "200,400,800"  # of a 128-pixel scene: 256^2, 512^2, 1024^2 = 0.066, 0.26, 1.05 MP


class BenchError(Exception):
    """Bad benchmark input; one line for the user."""


# ======================================================================= CLI
def add_arguments(p) -> None:
    p.add_argument("--scenes", help="comma-separated sample scenes (default: all of sample_blends/)")
    p.add_argument("--methods", help=f"comma-separated methods (default {','.join(DEFAULT_METHODS)})")
    p.add_argument("--budgets", help="comma-separated mean spp budgets (default 4,8,16,32)")
    p.add_argument("--out", default=None, help="output folder (default bench_out/ in the repo)")
    p.add_argument("--quick", action="store_true", help="smallest useful run: cornell at 25%% "
                   "(32x32), budget 8, every method, oracles and peers, uniform at 4/8/32 spp, "
                   "a tiny scaling section; under a minute on 2 cores")
    p.add_argument("--resolution-percentage", type=int, default=None,
                   help="render the scenes at this %% (default 100; --quick: 25)")
    p.add_argument("--uniform-spp", help="spp of the plain uniform renders of the t_uniform(e) "
                   "curve (default: the budgets plus 2x and 4x the largest)")
    p.add_argument("--reference-spp", type=int, default=refs.DEFAULT_SPP)
    p.add_argument("--reference-dir", default=None, help="reference cache (default references/)")
    p.add_argument("--no-render-references", action="store_true",
                   help="fail instead of rendering a missing reference")
    p.add_argument("--no-oracle", action="store_true", help="skip the oracle runs")
    p.add_argument("--oracle-budgets", help="budgets of the oracle runs (default: all budgets)")
    p.add_argument("--no-peers", action="store_true", help="skip OIDN and Cycles adaptive sampling")
    p.add_argument("--scaling-percentages", default=None,
                   help="resolution %% of the first scene for the scaling section, comma-separated "
                        f"(default {DEFAULT_SCALING}; 'none' skips it)")
    p.add_argument("--scaling-methods", help="methods of the scaling section (default: --methods "
                   "without uniform)")
    p.add_argument("--scaling-memory-mp", type=float, default=0.3, help="measure traced memory "
                   "(a second, untimed reconstruct) only up to this many megapixels (default 0.3)")
    p.add_argument("--scaling-max-seconds", type=float, default=120.0, help="skip a method at a "
                   "size when its time, extrapolated linearly in pixels from the previous size, "
                   "would exceed this (default 120)")
    p.add_argument("--max-samples-factor", type=int, default=None, help="Cycles adaptive sampling "
                   "peer: max samples = this x the largest budget, the threshold decides the rest "
                   "(default 16; --quick: 8)")
    p.add_argument("--run-max-seconds", type=float, default=60.0, help="time budget of one run of "
                   "our loop (Options.max_seconds): a run that reaches it stops sampling early, is "
                   "flagged partial and keeps the samples it has (default 60; 0: none)")
    p.add_argument("--seed", type=int, default=0, help="Cycles seed of the runs (not the references')")
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")


def _ints(text, what) -> list:
    try:
        vals = [int(float(v)) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise BenchError(f"--{what}: cannot read {text!r} (comma-separated numbers)") from None
    if not vals or any(v < 1 for v in vals):
        raise BenchError(f"--{what}: give positive whole numbers, got {text!r}")
    return sorted(set(vals))


def resolve_config(args) -> dict:
    """Validated settings of one session (presets applied, CLI values win)."""
    q = QUICK if args.quick else {}
    budgets = _ints(args.budgets or q.get("budgets") or ",".join(map(str, DEFAULT_BUDGETS)), "budgets")
    names = [m.strip() for m in (args.methods or ",".join(DEFAULT_METHODS)).split(",") if m.strip()]
    for m in names:
        if m not in methods_registry.METHODS:
            raise BenchError(f"unknown method {m!r}; choose from {', '.join(methods_registry.METHODS)}")
    try:
        scenes = refs.scene_names(args.scenes or q.get("scenes"))
    except ValueError as exc:
        raise BenchError(str(exc)) from None
    pct = args.resolution_percentage or q.get("resolution_percentage") or 100
    if not 1 <= pct <= 10000:
        raise BenchError("--resolution-percentage must be between 1 and 10000")
    if args.uniform_spp or q.get("uniform_spp"):
        uniform = _ints(args.uniform_spp or q["uniform_spp"], "uniform-spp")
    else:
        uniform = sorted(set(budgets) | {2 * max(budgets), 4 * max(budgets)})
    if len(uniform) < 2:
        raise BenchError("--uniform-spp: need at least two levels for the t_uniform(e) curve")
    if args.reference_spp < 1024:
        print(f"[bench] note: references at {args.reference_spp} spp (< 1024): relMSE below the "
              "reference's own noise floor is not measurable", file=sys.stderr)
    scal = args.scaling_percentages or q.get("scaling_percentages") or DEFAULT_SCALING
    scaling = [] if scal == "none" else _ints(scal, "scaling-percentages")
    oracle_budgets = budgets if not args.oracle_budgets else _ints(args.oracle_budgets, "oracle-budgets")
    scaling_methods = [m for m in (args.scaling_methods.split(",") if args.scaling_methods else names)
                       if m and m != "uniform"]
    for m in scaling_methods:
        if m not in methods_registry.METHODS:
            raise BenchError(f"unknown method {m!r} in --scaling-methods")
    out = os.path.abspath(args.out or DEFAULT_OUT)
    if os.path.exists(out) and not os.path.isdir(out):
        raise BenchError(f"--out {out} is a file, not a folder")
    return {"quick": bool(args.quick), "scenes": scenes, "methods": names, "budgets": budgets,
            "resolution_percentage": int(pct), "uniform_spp": uniform,
            "reference_spp": int(args.reference_spp), "reference_dir": args.reference_dir,
            "render_references": not args.no_render_references, "oracle": not args.no_oracle,
            "oracle_budgets": [b for b in oracle_budgets], "peers": not args.no_peers,
            "scaling_percentages": scaling, "scaling_methods": scaling_methods,
            "max_samples_factor": int(args.max_samples_factor or q.get("max_samples_factor") or 16),
            "scaling_memory_mp": float(args.scaling_memory_mp),
            "scaling_max_seconds": float(args.scaling_max_seconds),
            "run_max_seconds": float(args.run_max_seconds or 0.0),
            "seed": int(args.seed), "out": out}


def main(args) -> int:
    try:
        cfg = resolve_config(args)
    except BenchError as exc:
        raise ValueError(str(exc)) from None
    if cfg["seed"] == refs.REFERENCE_SEED:
        raise ValueError(f"--seed {cfg['seed']} is the references' seed; the runs need another")
    os.makedirs(cfg["out"], exist_ok=True)
    session = Session(cfg, argv=sys.argv[1:])
    results = session.run()
    paths = write_outputs(results, cfg["out"])
    print(f"[bench] done in {results['session_seconds']:.1f} s; results in {cfg['out']}", flush=True)
    if args.json:
        print(json.dumps({"out": cfg["out"], "seconds": results["session_seconds"], **paths}))
    return 0


# ================================================================== helpers
def log(msg: str) -> None:
    print(f"[bench] {msg}", flush=True)


def speedup_curve(points):
    """``t_uniform(e)`` from plain uniform renders ``[(relmse, seconds), ...]``.

    Log-log linear interpolation between the renders sorted by error; outside
    their range, slope -1 (time inversely proportional to error, as for Monte
    Carlo) from the nearest end.  Returns a function e -> seconds (NaN for a
    non-finite or non-positive e).
    """
    pts = sorted((float(e), float(t)) for e, t in points
                 if np.isfinite(e) and np.isfinite(t) and e > 0 and t > 0)
    if not pts:
        return lambda e: float("nan")
    le = np.log([p[0] for p in pts])
    lt = np.log([p[1] for p in pts])
    # errors must fall as time grows; enforce it (noisy timings) with a running max
    # of time from the large-error end, so the curve is a function
    lt = np.maximum.accumulate(lt[::-1])[::-1]

    def t_uniform(e):
        if not (np.isfinite(e) and e > 0):
            return float("nan")
        x = math.log(e)
        if x <= le[0]:
            return float(math.exp(lt[0] + (le[0] - x)))
        if x >= le[-1]:
            return float(math.exp(lt[-1] - (x - le[-1])))
        return float(math.exp(np.interp(x, le, lt)))

    return t_uniform


def display(rgb: np.ndarray) -> np.ndarray:
    """Scene-linear RGB -> display (the scenes' 'Standard' view transform: sRGB
    OETF on values clipped to [0, 1])."""
    x = np.clip(np.nan_to_num(np.asarray(rgb, np.float64)[..., :3]), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def relative_estimate(error: np.ndarray, image: np.ndarray) -> np.ndarray:
    """An estimated absolute squared error (H, W) made comparable to the true
    per-pixel relMSE: error / (lum(image)^2 + 0.01)."""
    lum = np.nan_to_num(np.asarray(image, np.float64)[..., :3]) @ LUMA
    e = np.where(np.isfinite(error), np.maximum(error, 0.0), 0.0)
    return e / (lum * lum + 0.01)


def _err_text(exc: BaseException) -> str:
    msg = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {msg[0] if msg else ''}"[:400]


def _finite(x):
    return float(x) if x is not None and np.isfinite(x) else None


def machine_info() -> dict:
    import bpy
    info = {"cpu_count": os.cpu_count(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(), "numpy": np.__version__,
            "blender": bpy.app.version_string}
    try:
        import OpenImageIO as oiio
        info["openimageio"] = oiio.__version__
    except Exception:  # pragma: no cover
        pass
    try:
        import matplotlib
        info["matplotlib"] = matplotlib.__version__
    except Exception:
        info["matplotlib"] = None
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return info


def loadavg():
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


# ============================================================ plain Cycles
class PlainCycles:
    """Plain Cycles renders of the open scene, as an artist gets them: one
    full-frame render, the scene's own sampling pattern (no sample subsets),
    optionally Cycles adaptive sampling and/or OIDN.  Built on CyclesExecutor
    (same output path, border, compositing and seed settings as our runs);
    every setting touched is restored on exit."""

    def __init__(self, scene, view_layer, seed: int, pattern: str):
        from ..addon import executor as ex
        self.ex = ex
        self.scene, self.vl = scene, view_layer
        self.exe = ex.CyclesExecutor(scene, view_layer, (), seed=seed)
        self.pattern = pattern
        self.guard = ex.SettingsGuard()

    def __enter__(self):
        self.exe.__enter__()
        try:
            c = self.scene.cycles
            g = self.guard
            if hasattr(c, "use_sample_subset"):
                c.use_sample_subset = False  # the executor's guard restores it
            try:
                c.sampling_pattern = self.pattern
            except TypeError:
                pass
            for k in ("use_denoising", "denoiser", "denoising_input_passes", "denoising_prefilter",
                      "denoising_use_gpu", "use_adaptive_sampling", "adaptive_threshold", "samples",
                      "time_limit"):
                if hasattr(c, k):
                    g.set(c, k, getattr(c, k))
            g.set(self.vl.cycles, "pass_debug_sample_count", False)
            g.set(self.scene.render, "filepath", self.scene.render.filepath)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc):
        self.guard.restore()
        self.exe.__exit__(*exc)
        return False

    def render(self, spp: int, denoise: bool = False, threshold: float | None = None,
               time_limit: float = 0.0) -> dict:
        """One full-frame render; returns rgb, seconds and (adaptive) mean spp."""
        from ..core import regions
        s, c, r = self.scene, self.scene.cycles, self.scene.render
        w, h = self.exe.full_w, self.exe.full_h
        x0, y0, x1, y1 = self.exe.domain
        for attr, value in regions.border_from_pixels(x0, y0, x1, y1, w, h).items():
            setattr(r, attr, float(value))
        c.samples = int(spp)
        if hasattr(c, "sample_offset"):
            c.sample_offset = 0
        c.use_denoising = bool(denoise)
        if denoise:
            for k, v in OIDN_SETTINGS.items():
                if hasattr(c, k):
                    setattr(c, k, v)
            if hasattr(c, "denoising_use_gpu"):
                c.denoising_use_gpu = False
        c.use_adaptive_sampling = threshold is not None
        if threshold is not None:
            c.adaptive_threshold = float(threshold)
        self.vl.cycles.pass_debug_sample_count = threshold is not None
        c.time_limit = float(time_limit)
        path = os.path.join(self.exe.tmpdir, f"plain{self.exe.renders:06d}.exr")
        r.filepath = path
        t0 = time.perf_counter()
        with self.ex.quiet_stdout():
            import bpy
            bpy.ops.render.render(write_still=True, scene=s.name, layer=self.vl.name)
        self.exe.renders += 1
        if not os.path.isfile(path):
            raise self.ex.SceneError("Cycles wrote no image")
        passes, _ = imageio.read_layers(path)
        seconds = time.perf_counter() - t0
        os.unlink(path)
        rgb = passes["Combined"][:, :, :3].astype(np.float64)
        out = {"rgb": rgb, "seconds": seconds, "spp_mean": float(spp)}
        if threshold is not None:
            # Cycles normalises its sample-count pass by the samples the render reached
            # (1.0 everywhere when every pixel stopped at the same count), so only the
            # relative map is known, not the mean spp
            out["spp_mean"] = None
            if "Debug Sample Count" in passes:
                out["samples_map"] = passes["Debug Sample Count"][:, :, 0].astype(np.float64)
                out["samples_relative"] = True
        return out


# ================================================================= session
class Session:
    """One benchmark session (see the module notes)."""

    def __init__(self, cfg: dict, argv=None):
        self.cfg = cfg
        self.argv = list(argv or [])
        self.sheet_budget = cfg["budgets"][len(cfg["budgets"]) // 2]

    # --------------------------------------------------------------- top
    def run(self) -> dict:
        t0 = time.perf_counter()
        res = {"version": 1, "command": "./cycles-adaptive " + " ".join(self.argv),
               "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "machine": machine_info(),
               "loadavg_start": loadavg(), "config": {k: v for k, v in self.cfg.items()},
               "protocol": self.protocol(), "scenes": {}, "errors": []}
        first = None
        for name in self.cfg["scenes"]:
            try:
                res["scenes"][name] = self.run_scene(name)
                first = first or name
            except ValueError:  # bad input (missing/other-version reference, size): stop
                raise
            except Exception as exc:  # a scene that cannot run is reported, not hidden
                traceback.print_exc()
                res["scenes"][name] = {"status": "error", "error": _err_text(exc)}
                res["errors"].append({"scene": name, "error": _err_text(exc)})
        res["scaling"] = self.run_scaling(first) if first and self.cfg["scaling_percentages"] else None
        res["loadavg_end"] = loadavg()
        res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        res["session_seconds"] = time.perf_counter() - t0
        res["targets"] = evaluate_targets(res)
        res["summary"] = summary_rows(res)
        return res

    def protocol(self) -> dict:
        c = self.cfg
        return {
            "relmse": "mean over pixels and RGB of (x - r)^2 / (r^2 + 0.01)",
            "smape": "mean over pixels and RGB of |x - r| / (|x| + |r| + 0.01)",
            "efficiency": "1 / (relMSE x total seconds)",
            "speedup": "t_uniform(e) / t: t_uniform = plain uniform Cycles renders of the same "
                       "session, log-log interpolation, slope -1 outside",
            "warmup": "one 1-spp render per scene before any timing, persistent data on for the "
                      "whole scene, so no measured run pays the BVH build or kernel load",
            "runs": f"our methods through AdaptiveRun + CyclesExecutor (initial 4 spp in 4 sample "
                    f"subsets, 4 iterations; Tabulated Sobol pattern), seed {c['seed']}; a run "
                    f"stops sampling after {c['run_max_seconds']:g} s (0: never) and is then "
                    "flagged partial",
            "oracle": "(budgets above the 4-spp initial pass only: below it nothing adapts) the same loop; the sample map is the true per-pixel relative error of the "
                      "current reconstruction against the reference (3x3 pooled) times "
                      "n^(-4/(d+4)) (core/oracle.py)",
            "reference": f"{c['reference_spp']} spp, seed {refs.REFERENCE_SEED} (independent of "
                         "the runs), Tabulated Sobol, same Blender",
            "uniform_curve": "plain Cycles: one full-frame render, the scene's own sampling "
                             "pattern, no subsets",
            "oidn": "Cycles denoiser OpenImageDenoise on CPU, albedo+normal, prefilter ACCURATE, "
                    "on a plain uniform render of the budget's spp",
            "cycles_adaptive": "Cycles adaptive sampling (its own default pattern, min samples "
                               f"auto), max samples {c['max_samples_factor']} x the largest budget, "
                               "noise threshold searched so its time matches the median time of "
                               "our methods at that budget (a render from an earlier budget's "
                               "search is reused when it is the closest; its mean spp is not "
                               "reported: Cycles normalises its sample-count pass by the samples "
                               "reached)",
            "seconds": "wall time of the whole run (executor set-up, renders incl. writing and "
                       "reading the EXR, adaptation, reconstruction); render/adapt/reconstruct from "
                       "the loop's own timers, overhead = the rest",
            "memory": "peak traced memory (tracemalloc) of one extra call of the method's "
                      "reconstruct on the run's final buffers (not timed); inputs excluded",
        }

    # ------------------------------------------------------------- scene
    def run_scene(self, name: str) -> dict:
        import bpy
        from ..addon import executor as ex
        cfg = self.cfg
        path = refs.scene_path(name)
        refs._open(path, force=True)
        scene, vl = bpy.context.scene, bpy.context.view_layer
        frame = scene.frame_current
        t_ref = time.perf_counter()
        ref_path = refs.ensure_reference(path, frame, cfg["resolution_percentage"], cfg["reference_spp"],
                                         directory=cfg["reference_dir"],
                                         render_missing=cfg["render_references"], log=log)
        t_ref = time.perf_counter() - t_ref
        t_scene = time.perf_counter()
        refs._open(path, force=True)  # a fresh file, whatever rendering the reference did
        scene, vl = bpy.context.scene, bpy.context.view_layer
        guard = ex.SettingsGuard()
        guard.set(scene.render, "resolution_percentage", cfg["resolution_percentage"])
        guard.set(scene.render, "use_persistent_data", True)
        pattern = scene.cycles.sampling_pattern
        try:
            with ex.CyclesExecutor(scene, vl, (), seed=cfg["seed"]) as exe:
                size = exe.size
            ref, ref_rec = refs.load_reference(ref_path, size)
            out = {"status": "ok", "file": path, "frame": frame, "width": size[1], "height": size[0],
                   "reference": {"path": ref_path, **{k: ref_rec.get(k) for k in (
                       "spp", "seed", "blender", "noise_relmse", "render_seconds", "created")}},
                   "sampling_pattern_plain": pattern}
            log(f"{name}: {size[1]}x{size[0]}, frame {frame}, reference {ref_path} "
                f"(noise floor relMSE {ref_rec.get('noise_relmse', float('nan')):.2e})")
            out["warmup_seconds"] = self.warmup(scene, vl)
            self._noisy = None
            curve = self.uniform_curve(scene, vl, pattern, ref)
            out["uniform_curve"] = curve
            t_uni = speedup_curve([(p["relmse"], p["seconds"]["total"]) for p in curve])
            runs, keep, search = [], {}, []
            for budget in cfg["budgets"]:
                for m in cfg["methods"]:
                    rec, pics = self.run_method(scene, vl, m, budget, frame, ref)
                    runs.append(rec)
                    self._keep(keep, budget, rec, pics)
                # at budgets <= the initial pass the loop never adapts: an oracle run
                # would repeat the method's run exactly, so it is not made
                if cfg["oracle"] and budget in cfg["oracle_budgets"] and budget > Options().initial_spp:
                    for m in cfg["methods"]:
                        if m == "uniform":
                            continue
                        base = next((r for r in runs if r["name"] == m and r["budget"] == budget), None)
                        if base is not None and base["status"] != "ok":
                            runs.append({"scene": name, "kind": "oracle", "name": "oracle-" + m,
                                         "method": m, "budget": budget, "status": "error",
                                         "error": "skipped: the method itself failed (" + base["error"] + ")"})
                            continue
                        rec, pics = self.run_method(scene, vl, m, budget, frame, ref, oracle=True)
                        runs.append(rec)
                        self._keep(keep, budget, rec, pics)
                if cfg["peers"]:
                    ours = [r["seconds"]["total"] for r in runs if r.get("kind") == "method"
                            and r["budget"] == budget and r["status"] == "ok"]
                    for rec, pics in self.run_peers(scene, vl, pattern, budget, ref, ours, search):
                        runs.append(rec)
                        self._keep(keep, budget, rec, pics)
            for r in runs:
                r["scene"] = name
                if r.get("status") == "ok":
                    tu = t_uni(r["relmse"])
                    r["t_uniform_equal_error"] = _finite(tu)
                    r["speedup"] = _finite(tu / r["seconds"]["total"])
            for p in curve:
                p["speedup"] = _finite(t_uni(p["relmse"]) / p["seconds"]["total"])
            plain = {p["spp"]: p for p in curve}
            for r in runs:  # proof that the denoiser ran: error of the same render without it
                if r["name"] == "oidn" and r.get("status") == "ok" and r["budget"] in plain:
                    r["relmse_without_denoiser"] = plain[r["budget"]]["relmse"]
            out["runs"] = runs
            out["reference_seconds_this_session"] = t_ref  # ~0 when cached
            out["scene_seconds"] = time.perf_counter() - t_scene
            out["threshold_search"] = [{k: v for k, v in s.items() if k not in ("rgb", "samples_map")}
                                       for s in search]
            if self._noisy is not None:
                keep = {"noisy": {"image": self._noisy}, **keep}
            out["sheet"] = {"budget": self.sheet_budget, "images": keep, "reference": ref}
            return out
        finally:
            guard.restore()

    def _keep(self, keep, budget, rec, pics):
        if budget == self.sheet_budget and pics is not None and rec.get("status") == "ok":
            keep[rec["name"]] = pics

    def warmup(self, scene, vl) -> float:
        from ..addon.executor import CyclesExecutor
        from ..core.regions import RegionTask
        t0 = time.perf_counter()
        with CyclesExecutor(scene, vl, FEATURES_ALL, seed=self.cfg["seed"]) as exe:
            h, w = exe.size
            exe.render(RegionTask(0, 0, w, h, 1, frame=scene.frame_current, offset=0))
        return time.perf_counter() - t0

    # ------------------------------------------------------ uniform curve
    def uniform_curve(self, scene, vl, pattern, ref) -> list:
        out = []
        with PlainCycles(scene, vl, self.cfg["seed"], pattern) as pc:
            for spp in self.cfg["uniform_spp"]:
                r = pc.render(spp)
                img = r["rgb"]
                e = metrics.relmse(img, ref)
                out.append({"kind": "uniform_curve", "name": "cycles_uniform", "spp": spp,
                            "spp_mean": float(spp), "relmse": e, "smape": metrics.smape(img, ref),
                            "seconds": {"total": r["seconds"], "render": r["seconds"]},
                            "efficiency": _finite(1.0 / (e * r["seconds"]))})
                log(f"  plain uniform {spp:4d} spp: relMSE {e:.3e} in {r['seconds']:.2f} s")
                if spp == self.sheet_budget:
                    self._noisy = img
        return out

    # ----------------------------------------------------------- methods
    def run_method(self, scene, vl, name, budget, frame, ref, oracle=False):
        """One run of our loop; returns (record, pictures for the sheet)."""
        from ..addon.executor import CyclesExecutor
        from ..core.oracle import OracleMethod
        label = ("oracle-" if oracle else "") + name
        rec = {"kind": "oracle" if oracle else "method", "name": label, "method": name,
               "budget": budget}
        try:
            mod = methods_registry.get(name)
            t0 = time.perf_counter()
            with CyclesExecutor(scene, vl, tuple(mod.PASSES), seed=self.cfg["seed"]) as exe:
                opts = Options(method=name, spp=float(budget), frame=frame, seed=self.cfg["seed"],
                               max_seconds=self.cfg["run_max_seconds"])
                run = AdaptiveRun(exe, opts)
                if oracle:
                    run.method = OracleMethod(mod, ref)
                capped = False
                for step in run.steps():
                    capped |= step.message == "time budget reached"
                result = run.reconstruct()
            wall = time.perf_counter() - t0
        except Exception as exc:
            rec.update(status="error", error=_err_text(exc))
            log(f"  {label:>14} @ {budget:3d}: ERROR {rec['error']}")
            return rec, None
        tm = run.timing
        image = np.where(np.isfinite(result.image), result.image, 0.0)
        err = np.where(np.isfinite(result.error), result.error, 0.0)
        e = metrics.relmse(result.image, ref)
        rec.update({
            "status": "ok", "spp_mean": run.samples_rendered / run.pixels,
            "relmse": e, "smape": metrics.smape(result.image, ref),
            "seconds": {"total": wall, "render": tm.render, "adapt": tm.adapt,
                        "reconstruct": tm.reconstruct,
                        "overhead": max(0.0, wall - tm.render - tm.adapt - tm.reconstruct)},
            "efficiency": _finite(1.0 / (e * wall)) if e > 0 else None,
            "error_correlation": metrics.error_correlation(err, image, ref),
            "center_fraction": _finite(result.info.get("center_fraction")),
            "regions": int(run.tasks_rendered), "iterations": int(run.iteration),
            "nonfinite_pixels": int((~np.isfinite(result.image)).any(axis=-1).sum()),
            "partial": bool(capped),
        })
        if not oracle:
            rec["memory"] = self.reconstruct_memory(mod, run.buffers, run.params)
        log(f"  {label:>14} @ {budget:3d}: relMSE {e:.3e} in {wall:6.2f} s "
            f"(render {tm.render:.2f}, adapt {tm.adapt:.2f}, reconstruct {tm.reconstruct:.2f}), "
            f"{run.tasks_rendered} renders" + (" [stopped by --run-max-seconds]" if rec["partial"] else ""))
        pics = {"image": image, "samples": run.buffers.n.copy(),
                "estimated": relative_estimate(err, image)}
        return rec, pics

    @staticmethod
    def reconstruct_memory(mod, buf, params) -> dict:
        """Peak traced memory of one reconstruct call (inputs excluded)."""
        tracemalloc.start()
        try:
            tracemalloc.reset_peak()
            base = tracemalloc.get_traced_memory()[0]
            mod.reconstruct(buf, params)
            peak = tracemalloc.get_traced_memory()[1] - base
        except Exception as exc:
            return {"error": _err_text(exc)}
        finally:
            tracemalloc.stop()
        px = buf.height * buf.width
        inputs = buf.n.nbytes + buf.k.nbytes + buf.color.mean.nbytes + buf.color.m2.nbytes + sum(
            s.mean.nbytes + s.m2.nbytes for s in buf.features.values())
        return {"reconstruct_peak_mb": peak / 2 ** 20, "bytes_per_pixel": peak / px,
                "input_bytes_per_pixel": inputs / px}

    # ------------------------------------------------------------- peers
    def run_peers(self, scene, vl, pattern, budget, ref, ours, search):
        """OIDN, Cycles adaptive sampling (time-matched), adaptive + OIDN."""
        cfg = self.cfg
        out = []
        target = float(np.median(ours)) if ours else None
        max_spp = cfg["max_samples_factor"] * max(cfg["budgets"])

        def rec_of(name, r, extra=None):
            e = metrics.relmse(r["rgb"], ref)
            d = {"kind": "peer", "name": name, "budget": budget, "status": "ok",
                 "spp_mean": r["spp_mean"], "relmse": e, "smape": metrics.smape(r["rgb"], ref),
                 "seconds": {"total": r["seconds"], "render": r["seconds"]},
                 "efficiency": _finite(1.0 / (e * r["seconds"])) if e > 0 else None}
            d.update(extra or {})
            log(f"  {name:>14} @ {budget:3d}: relMSE {e:.3e} in {r['seconds']:6.2f} s"
                + (f" (threshold {extra['threshold']:.3g})" if extra and "threshold" in extra else ""))
            pics = {"image": r["rgb"]}
            if "samples_map" in r:
                pics["samples"] = r["samples_map"]
                pics["samples_relative"] = True
            return d, pics

        try:
            with PlainCycles(scene, vl, cfg["seed"], pattern) as pc:
                try:
                    out.append(rec_of("oidn", pc.render(budget, denoise=True),
                                      {"settings": dict(OIDN_SETTINGS)}))
                except Exception as exc:
                    out.append(({"kind": "peer", "name": "oidn", "budget": budget, "status": "error",
                                 "error": _err_text(exc)}, None))
                if target is None:
                    err = "no successful run of our methods at this budget to match the time of"
                    for n in ("cycles_adaptive", "cycles_adaptive+oidn"):
                        out.append(({"kind": "peer", "name": n, "budget": budget, "status": "error",
                                     "error": err}, None))
                    return out
                best = self.search_threshold(pc, max_spp, target, search, ref)
                extra = {"threshold": best["threshold"], "max_samples": max_spp,
                         "target_seconds": target, "time_ratio": best["seconds"] / target,
                         "time_matched": abs(math.log(best["seconds"] / target)) <= math.log(TIME_MATCH)}
                out.append(rec_of("cycles_adaptive", best, extra))
                r = pc.render(max_spp, denoise=True, threshold=best["threshold"])
                out.append(rec_of("cycles_adaptive+oidn", r, {"threshold": best["threshold"],
                                                              "max_samples": max_spp,
                                                              "settings": dict(OIDN_SETTINGS)}))
        except Exception as exc:
            traceback.print_exc()
            have = {d["name"] for d, _ in out}
            for n in ("oidn", "cycles_adaptive", "cycles_adaptive+oidn"):
                if n not in have:
                    out.append(({"kind": "peer", "name": n, "budget": budget, "status": "error",
                                 "error": _err_text(exc)}, None))
        return out

    def search_threshold(self, pc, max_spp, target, search, ref) -> dict:
        """Cycles noise threshold whose render time matches ``target`` seconds.

        Secant steps on log(time) against log(threshold) over every render of
        this scene's search so far (they share max samples, so earlier budgets'
        renders are valid points); the first guess is 0.05; a trial is cut by
        Cycles' time limit at 4x the target (a bound, never chosen).  Returns
        the render whose time is closest to the target."""
        lo, hi = THRESHOLD_RANGE
        for _ in range(SEARCH_TRIALS):
            usable = [s for s in search if s["max_samples"] == max_spp]
            best = min((s for s in usable if not s["limited"]),
                       key=lambda s: abs(math.log(s["seconds"] / target)), default=None)
            if best is not None and abs(math.log(best["seconds"] / target)) <= math.log(TIME_MATCH):
                break
            if any(s["threshold"] >= hi * 0.999 and s["seconds"] > target * TIME_MATCH for s in usable):
                break  # even the loosest threshold is slower than the target: not matchable
            thr = _next_threshold(usable, target)
            if any(abs(math.log(thr / s["threshold"])) < 1e-3 for s in usable):
                break  # nothing new to try (clamped at the range's end)
            r = pc.render(max_spp, threshold=thr, time_limit=4.0 * target)
            limited = r["seconds"] >= 3.9 * target
            r.update({"threshold": thr, "max_samples": max_spp, "limited": limited,
                      "relmse": metrics.relmse(r["rgb"], ref)})
            search.append(r)
            log(f"     threshold {thr:.4g}: {r['seconds']:.2f} s (target {target:.2f} s)"
                + (" [time limit]" if limited else ""))
        usable = [s for s in search if s["max_samples"] == max_spp and not s["limited"]]
        if not usable:  # every trial hit the limit: give the fastest
            usable = [s for s in search if s["max_samples"] == max_spp]
        return min(usable, key=lambda s: abs(math.log(s["seconds"] / target)))

    # ----------------------------------------------------------- scaling
    def run_scaling(self, scene_name: str) -> dict:
        """Reconstruction time and peak traced memory per method at several
        sizes (the scene rendered at those sizes: 4 spp in 4 subsets with all
        feature passes), next to OIDN's time (a 4-spp render with OIDN minus the
        same render without)."""
        import bpy
        from ..addon import executor as ex
        cfg = self.cfg
        path = refs.scene_path(scene_name)
        refs._open(path, force=True)
        scene, vl = bpy.context.scene, bpy.context.view_layer
        pattern = scene.cycles.sampling_pattern
        rows = []
        t_start = time.perf_counter()
        guard = ex.SettingsGuard()
        guard.set(scene.render, "use_persistent_data", True)
        log(f"scaling on {scene_name} at {', '.join(str(p) + '%' for p in cfg['scaling_percentages'])}")
        try:
            for pct in cfg["scaling_percentages"]:
                scene.render.resolution_percentage = pct
                row = {"percentage": pct}
                try:
                    buf, size = self._scaling_buffers(scene, vl)
                except Exception as exc:
                    row.update(error=_err_text(exc))
                    rows.append(row)
                    continue
                h, w = size
                row.update(width=w, height=h, megapixels=w * h / 1e6)
                # OIDN: the same plain render with and without the denoiser
                try:
                    with PlainCycles(scene, vl, cfg["seed"], pattern) as pc:
                        pc.render(1)  # sync at this size
                        t_off = pc.render(4)["seconds"]
                        t_on = pc.render(4, denoise=True)["seconds"]
                    row["oidn"] = {"seconds": max(t_on - t_off, 0.0), "render_seconds": t_off,
                                   "render_denoise_seconds": t_on,
                                   "seconds_per_mp": max(t_on - t_off, 0.0) / (w * h / 1e6)}
                except Exception as exc:
                    row["oidn"] = {"error": _err_text(exc)}
                row["methods"] = {}
                for m in cfg["scaling_methods"]:
                    prev = next((r["methods"][m] for r in reversed(rows)
                                 if "seconds" in r.get("methods", {}).get(m, {})), None)
                    if prev is not None:
                        guess = prev["seconds_per_mp"] * w * h / 1e6
                        if guess > cfg["scaling_max_seconds"]:
                            row["methods"][m] = {"skipped": f"extrapolated {guess:.0f} s > "
                                                            f"{cfg['scaling_max_seconds']:.0f} s",
                                                 "extrapolated_seconds": guess}
                            continue
                    row["methods"][m] = self._scaling_method(
                        m, buf, memory=w * h / 1e6 <= cfg["scaling_memory_mp"])
                txt = ", ".join(f"{m} {v.get('seconds', float('nan')):.2f} s" for m, v in row["methods"].items())
                log(f"  {w}x{h}: OIDN {row['oidn'].get('seconds', float('nan')):.2f} s; {txt}")
                rows.append(row)
        finally:
            guard.restore()
        return {"scene": scene_name, "spp": 4, "rows": rows, "seconds": time.perf_counter() - t_start,
                "how": "scene rendered at each size (4 spp in 4 sample subsets with the normal, "
                       "albedo, depth passes); a method's reconstruct timed once, then (up to "
                       f"{cfg['scaling_memory_mp']} MP) its peak traced memory measured in a second, "
                       "untimed call; a method whose time extrapolated from the previous size "
                       f"exceeds {cfg['scaling_max_seconds']:.0f} s is skipped and says so; OIDN "
                       "seconds = (4-spp render with OIDN) - (the same without), after one sync "
                       "render at that size"}

    def _scaling_buffers(self, scene, vl):
        from ..addon.executor import CyclesExecutor
        from ..core.buffers import Buffers
        from ..core.regions import RegionTask
        with CyclesExecutor(scene, vl, FEATURES_ALL, seed=self.cfg["seed"]) as exe:
            h, w = exe.size
            buf = Buffers.empty(h, w, FEATURES_ALL + ("alpha",))
            for i in range(4):
                color, feats = exe.render(RegionTask(0, 0, w, h, 1, frame=scene.frame_current, offset=i))
                feats["alpha"] = color[:, :, 3:4]
                buf.merge_group(color[:, :, :3], 1, feats)
        return buf, (h, w)

    def _scaling_method(self, m, buf, memory=True) -> dict:
        try:
            mod = methods_registry.get(m)
            params = mod.Params()
            t0 = time.perf_counter()
            mod.reconstruct(buf, params)
            sec = time.perf_counter() - t0
        except Exception as exc:
            return {"error": _err_text(exc)}
        mp = buf.height * buf.width / 1e6
        d = {"seconds": sec, "seconds_per_mp": sec / mp}
        if memory:
            d.update(self.reconstruct_memory(mod, buf, params))
        return d


def _next_threshold(points, target) -> float:
    lo, hi = THRESHOLD_RANGE
    if not points:
        return FIRST_THRESHOLD
    lt = math.log(target)
    pts = sorted(((math.log(p["threshold"]), math.log(p["seconds"]), p["limited"]) for p in points))
    # bracket: a point too slow (small threshold) and one too fast (large threshold)
    slow = [p for p in pts if p[1] > lt]
    fast = [p for p in pts if p[1] <= lt and not p[2]]
    if slow and fast:
        a = max(slow, key=lambda p: p[0])
        b = min((p for p in fast if p[0] > a[0]), key=lambda p: p[0], default=None)
        if b is not None and b[0] > a[0]:
            slope = (b[1] - a[1]) / (b[0] - a[0])
            x = a[0] + (lt - a[1]) / slope if slope < 0 else 0.5 * (a[0] + b[0])
            x = min(max(x, a[0] + 0.1 * (b[0] - a[0])), b[0] - 0.1 * (b[0] - a[0]))
            return float(min(max(math.exp(x), lo), hi))
    near = min(pts, key=lambda p: abs(p[1] - lt))
    others = [p for p in pts if p is not near and abs(p[0] - near[0]) > 1e-6]
    slope = -1.0
    if others:
        o = min(others, key=lambda p: abs(p[0] - near[0]))
        s = (o[1] - near[1]) / (o[0] - near[0])
        if np.isfinite(s) and s < 0:
            slope = min(max(s, -3.0), -0.3)
    x = near[0] + (lt - near[1]) / slope
    x = min(max(x, near[0] - 2.5), near[0] + 2.5)
    return float(min(max(math.exp(x), lo), hi))


# ================================================================= targets
ADAPTIVE_METHODS = ("var", "awr", "lp", "rhf")


def _gmean(v):
    v = [x for x in v if x is not None and np.isfinite(x) and x > 0]
    return float(np.exp(np.mean(np.log(v)))) if v else None


def evaluate_targets(res: dict) -> list:
    """The issue's targets, each with met (True/False/None = not measured) and why."""
    scenes = {k: v for k, v in res["scenes"].items() if v.get("status") == "ok"}
    out = []

    def runs(kind=None, name=None):
        for s, d in scenes.items():
            for r in d["runs"]:
                if r.get("status") == "ok" and (kind is None or r["kind"] == kind) and \
                        (name is None or r["name"] == name):
                    yield s, r

    # 1. every method >= 5x on every scene
    per = {}
    for s, r in runs("method"):
        if r["method"] in ADAPTIVE_METHODS:
            per.setdefault(r["method"], {}).setdefault(s, []).append(r.get("speedup"))
    failed_methods = set()
    for s, d in scenes.items():
        for r in d["runs"]:
            if r["kind"] == "method" and r.get("status") != "ok" and r["method"] in ADAPTIVE_METHODS:
                failed_methods.add(r["method"])
    detail, ok_all = [], True
    for m in ADAPTIVE_METHODS:
        if m not in per:
            if m in failed_methods:
                ok_all = False
                detail.append(f"{m}: no successful run")
            continue
        g = {s: _gmean(v) for s, v in per[m].items()}
        low = [s for s, v in g.items() if v is None or v < 5]
        ok_all &= not low
        detail.append(f"{m}: " + ", ".join(f"{s} {v:.2f}x" if v else f"{s} n/a" for s, v in g.items()))
    out.append({"target": "every adaptive method >= 5x equal-error speed-up vs uniform on every scene "
                          "(geometric mean over budgets)",
                "met": bool(per) and ok_all if per else None, "detail": detail})

    # 2. best method >= OIDN on at least half of the scenes
    wins, counted, det = 0, 0, []
    for s in scenes:
        best = _gmean_by(runs_in(scenes[s], "method"), ADAPTIVE_METHODS + ("uniform",))
        oidn = _gmean([r.get("speedup") for r in runs_in(scenes[s], "peer") if r["name"] == "oidn"])
        if best and oidn:
            counted += 1
            wins += best[1] >= oidn
            det.append(f"{s}: best {best[0]} {best[1]:.2f}x vs OIDN {oidn:.2f}x")
    out.append({"target": "the best method >= OIDN's speed-up on at least half of the scenes",
                "met": (wins * 2 >= counted) if counted else None,
                "detail": det + [f"{wins} of {counted} scenes"]})

    # 3. estimated maps within 1.2x of the oracle's relMSE
    ratios, det = {}, []
    for s, d in scenes.items():
        ok = {(r["name"], r["budget"]): r for r in d["runs"] if r.get("status") == "ok"}
        for (n, b), r in ok.items():
            o = ok.get(("oracle-" + n, b))
            if r["kind"] == "method" and o is not None and o["relmse"] > 0:
                ratios.setdefault(n, []).append(r["relmse"] / o["relmse"])
    for n, v in ratios.items():
        det.append(f"{n}: relMSE / oracle's geometric mean {_gmean(v):.2f}, worst {max(v):.2f} "
                   f"({len(v)} runs)")
    out.append({"target": "estimated maps within 1.2x of the oracle's relMSE",
                "met": all(_gmean(v) <= 1.2 for v in ratios.values()) if ratios else None,
                "detail": det})

    # 4. reconstruction per megapixel vs OIDN; 5. memory
    sc = res.get("scaling") or {}
    rows = sorted((r for r in sc.get("rows", []) if "methods" in r),
                  key=lambda r: r["width"] * r["height"])
    det4, det5, met4, met5 = [], [], None, None
    if rows:
        met4 = True
        for m, bound in (("awr", 1.0), ("lp", 1.0), ("rhf", 2.0)):
            # the largest size where both the method and OIDN were timed
            row = next((r for r in reversed(rows) if "seconds_per_mp" in r["methods"].get(m, {})
                        and "seconds_per_mp" in r.get("oidn", {})), None)
            if row is None:
                errs = [r["methods"].get(m, {}).get("error") for r in rows if m in r["methods"]]
                errs = [e for e in errs if e]
                det4.append(f"{m}: not measured ({errs[0] if errs else 'not in this run'})")
                met4 = False if errs else met4
                continue
            v, oidn = row["methods"][m], row["oidn"]["seconds_per_mp"]
            ok = v["seconds_per_mp"] <= bound * oidn
            met4 &= ok
            det4.append(f"{m}: {v['seconds_per_mp']:.2f} s/MP vs OIDN {oidn:.2f} s/MP "
                        f"({v['seconds_per_mp'] / oidn:.2f}x, bound {bound:g}x) at "
                        f"{row['width']}x{row['height']}: {'met' if ok else 'NOT met'}")
            skipped = [r for r in rows if "skipped" in r["methods"].get(m, {})]
            if skipped:
                det4[-1] += f"; skipped at {skipped[-1]['width']}x{skipped[-1]['height']} (" \
                            f"{skipped[-1]['methods'][m]['skipped']})"
        met5 = True
        for m in dict.fromkeys(k for r in rows for k in r["methods"]):
            row = next((r for r in reversed(rows) if "bytes_per_pixel" in r["methods"].get(m, {})), None)
            if row is None:
                continue
            v = row["methods"][m]
            ok = v["bytes_per_pixel"] <= 400
            met5 &= ok
            det5.append(f"{m}: {v['bytes_per_pixel']:.0f} B/px working memory (+ "
                        f"{v['input_bytes_per_pixel']:.0f} B/px input buffers) at "
                        f"{row['width']}x{row['height']}: {'met' if ok else 'NOT met'}")
    out.append({"target": "reconstruction per megapixel <= OIDN's for awr and lp, <= 2x for rhf",
                "met": met4, "detail": det4 or ["no scaling section in this run"]})
    out.append({"target": "memory <= 400 bytes per pixel (reconstruct's peak traced memory)",
                "met": met5, "detail": det5 or ["no scaling section in this run"]})
    return out


def runs_in(scene_res, kind):
    return [r for r in scene_res.get("runs", []) if r.get("status") == "ok" and r["kind"] == kind]


def _gmean_by(runs, names):
    best = None
    for n in names:
        g = _gmean([r.get("speedup") for r in runs if r["name"] == n])
        if g and (best is None or g > best[1]):
            best = (n, g)
    return best


def summary_rows(res) -> list:
    """One row per scene x method/peer: speed-up and relMSE per budget."""
    rows = []
    for s, d in res["scenes"].items():
        if d.get("status") != "ok":
            rows.append({"scene": s, "name": "(scene failed)", "error": d.get("error")})
            continue
        names = list(dict.fromkeys(r["name"] for r in d["runs"]))
        for n in names:
            row = {"scene": s, "name": n, "speedup": {}, "relmse": {}, "seconds": {}, "errors": {}}
            for r in d["runs"]:
                if r["name"] != n:
                    continue
                b = str(r["budget"])
                if r.get("status") == "ok":
                    row["speedup"][b] = r.get("speedup")
                    row["relmse"][b] = r["relmse"]
                    row["seconds"][b] = r["seconds"]["total"]
                else:
                    row["errors"][b] = r.get("error")
            rows.append(row)
    return rows


# ================================================================= outputs
def write_outputs(res: dict, out: str) -> dict:
    paths = {"plots": [], "sheets": []}
    try:
        import matplotlib
        matplotlib.use("Agg")
        for s, d in res["scenes"].items():
            if d.get("status") != "ok":
                continue
            p = os.path.join(out, f"plot_{s}.png")
            plot_scene(s, d, p)
            paths["plots"].append(p)
            p = os.path.join(out, f"sheet_{s}.png")
            sheet_scene(s, d, p)
            paths["sheets"].append(p)
    except ImportError as exc:
        res["errors"].append({"error": f"no pictures: {_err_text(exc)}"})
    # the JSON keeps every figure, not the pixel arrays
    clean = json.loads(json.dumps(res, default=_json_default))
    for s, d in clean["scenes"].items():
        if isinstance(d, dict) and "sheet" in d:
            d["sheet"] = {"budget": d["sheet"]["budget"], "file": f"sheet_{s}.png"}
    clean["pictures"] = {"plots": [os.path.basename(p) for p in paths["plots"]],
                         "sheets": [os.path.basename(p) for p in paths["sheets"]]}
    jp = os.path.join(out, "results.json")
    _atomic_text(jp, json.dumps(clean, indent=1))
    mp = os.path.join(out, "results.md")
    _atomic_text(mp, markdown(clean))
    paths.update(results_json=jp, results_md=mp)
    return paths


def _json_default(o):
    if isinstance(o, np.ndarray):
        return None
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    return str(o)


def _atomic_text(path, text):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


STYLE = {"uniform": "C0", "var": "C1", "awr": "C2", "lp": "C3", "rhf": "C4",
         "oidn": "C5", "cycles_adaptive": "C6", "cycles_adaptive+oidn": "C8"}


def plot_scene(name, d, path):
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 5), dpi=110)
    cu = sorted(d["uniform_curve"], key=lambda p: p["spp"])
    ax.plot([p["seconds"]["total"] for p in cu], [p["relmse"] for p in cu], "k-o", lw=2,
            label="plain Cycles uniform")
    for p in cu:
        ax.annotate(f"{p['spp']}", (p["seconds"]["total"], p["relmse"]), fontsize=7,
                    textcoords="offset points", xytext=(3, 3))
    names = list(dict.fromkeys(r["name"] for r in d["runs"]))
    for n in names:
        pts = sorted(((r["seconds"]["total"], r["relmse"], r["budget"]) for r in d["runs"]
                      if r["name"] == n and r.get("status") == "ok"), key=lambda p: p[2])
        if not pts:
            continue
        base = n.replace("oracle-", "")
        style = "--" if n.startswith("oracle-") else "-"
        marker = "s" if n in ("oidn", "cycles_adaptive", "cycles_adaptive+oidn") else "o"
        ax.plot([p[0] for p in pts], [p[1] for p in pts], style, marker=marker, ms=4,
                color=STYLE.get(base, None), alpha=0.6 if n.startswith("oracle-") else 1.0, label=n)
    floor = d["reference"].get("noise_relmse")
    if floor:
        ax.axhline(floor, color="grey", ls=":", lw=1, label="reference noise floor")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("seconds (wall, whole run)")
    ax.set_ylabel("relMSE")
    ax.set_title(f"{name} ({d['width']}x{d['height']}): relMSE vs time, budgets "
                 f"{', '.join(str(b) for b in sorted({r['budget'] for r in d['runs']}))} spp", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def sheet_scene(name, d, path):
    """Reference / noisy / each result (row 1), sample maps (row 2), true error
    (row 3) and estimated error (row 4, relative, same colour scale)."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    sh = d["sheet"]
    ref = sh["reference"]
    imgs = sh["images"]
    order = [n for n in ["noisy"] + list(dict.fromkeys(r["name"] for r in d["runs"])) if n in imgs]
    cols = 1 + len(order)
    fig, axes = plt.subplots(4, cols, figsize=(1.9 * cols, 8.2), dpi=100, squeeze=False)
    for a in axes.ravel():
        a.set_xticks([])
        a.set_yticks([])
        a.axis("off")
    axes[0, 0].imshow(display(ref), interpolation="nearest")
    axes[0, 0].set_title(f"reference {d['reference'].get('spp')} spp", fontsize=7)
    axes[0, 0].axis("on")
    axes[1, 0].text(0.5, 0.5, f"sample maps\n(spp, budget {sh['budget']})", ha="center", va="center",
                    fontsize=8, transform=axes[1, 0].transAxes)
    axes[2, 0].text(0.5, 0.5, "true error\n(x-r)^2/(r^2+.01)", ha="center", va="center", fontsize=8,
                    transform=axes[2, 0].transAxes)
    axes[3, 0].text(0.5, 0.5, "estimated error\n(relative)", ha="center", va="center", fontsize=8,
                    transform=axes[3, 0].transAxes)
    true_maps = {n: metrics.per_pixel_relmse(np.asarray(imgs[n]["image"]), ref) for n in order}
    allv = np.concatenate([v[v > 0].ravel() for v in true_maps.values()] or [np.array([1e-4])])
    vmax = float(np.percentile(allv, 99.5)) if allv.size else 1.0
    vmin = max(vmax * 1e-4, 1e-8)
    norm = LogNorm(vmin=vmin, vmax=vmax)
    for j, n in enumerate(order, start=1):
        pic = imgs[n]
        if n == "noisy":  # plain uniform Cycles at the sheet's budget
            r = next((p for p in d["uniform_curve"] if p["spp"] == sh["budget"]), {})
        else:
            r = next((r for r in d["runs"] if r["name"] == n and r["budget"] == sh["budget"]), {})
        a = axes[0, j]
        a.imshow(display(pic["image"]), interpolation="nearest")
        a.set_title(f"{n}\nrelMSE {r.get('relmse', float('nan')):.2e}, {r.get('seconds', {}).get('total', float('nan')):.1f} s",
                    fontsize=6)
        a.axis("on")
        if "samples" in pic:  # each map on its own scale, printed under it
            smax = max(float(np.max(pic["samples"])), 1.0)
            axes[1, j].imshow(pic["samples"], cmap="viridis", vmin=0, vmax=smax, interpolation="nearest")
            axes[1, j].axis("on")
            axes[1, j].set_xlabel("relative (Cycles' sample-count pass)" if pic.get("samples_relative")
                                  else f"0..{smax:.0f} spp (mean {np.mean(pic['samples']):.1f})", fontsize=6)
        axes[2, j].imshow(np.maximum(true_maps[n], vmin), cmap="magma", norm=norm, interpolation="nearest")
        axes[2, j].axis("on")
        if "estimated" in pic:
            axes[3, j].imshow(np.maximum(pic["estimated"], vmin), cmap="magma", norm=norm,
                              interpolation="nearest")
            axes[3, j].axis("on")
    fig.suptitle(f"{name}: budget {sh['budget']} spp (rows 3-4: log colour scale "
                 f"{vmin:.1e}..{vmax:.1e})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _fmt(v, spec=".3g"):
    if v is None:
        return "-"
    if isinstance(v, float) and not np.isfinite(v):
        return "-"
    return format(v, spec)


def markdown(res: dict) -> str:
    m = res["machine"]
    cfg = res["config"]
    L = [f"# Benchmark results", "",
         f"Command: `{res['command'].strip()}`  ",
         f"Started {res['started']}, session {res['session_seconds']:.0f} s; Blender {m['blender']}, "
         f"numpy {m['numpy']}, Python {m['python']}; {m['cpu_count']} CPUs ({m.get('cpu_model', m['processor'])}), "
         f"{m['platform']}; load average at start {res.get('loadavg_start')}, at end "
         f"{res.get('loadavg_end')}; peak RSS {res['peak_rss_mb']:.0f} MB.", "",
         "## How it was measured", ""]
    for k, v in res["protocol"].items():
        L.append(f"- **{k}**: {v}")
    L += ["- Timings are single measurements on a shared machine (see the load averages); ratios "
          "within one session are what to compare.", ""]

    budgets = cfg["budgets"]
    L += ["## Summary: equal-error speed-up vs plain uniform Cycles (relMSE in brackets)", "",
          "| scene | method | " + " | ".join(f"{b} spp" for b in budgets) + " |",
          "|---|---|" + "---|" * len(budgets)]
    for row in res["summary"]:
        if "speedup" not in row:
            L.append(f"| {row['scene']} | scene failed: {row.get('error')} |" + " |" * len(budgets))
            continue
        cells = []
        for b in budgets:
            k = str(b)
            if k in row["speedup"]:
                cells.append(f"{_fmt(row['speedup'][k], '.2f')}x ({_fmt(row['relmse'][k], '.2e')})")
            elif k in row["errors"]:
                cells.append("error")
            else:
                cells.append("")
        L.append(f"| {row['scene']} | {row['name']} | " + " | ".join(cells) + " |")
    L.append("")

    L += ["## Targets (issue 7; goals, not test asserts)", ""]
    for t in res["targets"]:
        met = {True: "**met**", False: "**not met**", None: "not measured"}[t["met"]]
        L.append(f"- {t['target']}: {met}")
        for dline in t["detail"]:
            L.append(f"  - {dline}")
    L.append("")
    L += _why_section(res)

    for s, d in res["scenes"].items():
        L += [f"## {s}", ""]
        if d.get("status") != "ok":
            L += [f"Failed: {d.get('error')}", ""]
            continue
        rf = d["reference"]
        L += [f"{d['width']}x{d['height']}, frame {d['frame']}; reference {rf.get('spp')} spp seed "
              f"{rf.get('seed')} (noise floor relMSE {_fmt(rf.get('noise_relmse'), '.2e')}); warm-up "
              f"render {d['warmup_seconds']:.2f} s (not counted); scene measured in "
              f"{d.get('scene_seconds', 0):.0f} s (+ {d.get('reference_seconds_this_session', 0):.0f} s "
              f"for the reference); plain renders use the "
              f"'{d['sampling_pattern_plain']}' pattern.", "",
              "Plain uniform Cycles (the t_uniform curve):", "",
              "| spp | relMSE | SMAPE | seconds | efficiency |", "|---|---|---|---|---|"]
        for p in d["uniform_curve"]:
            L.append(f"| {p['spp']} | {p['relmse']:.3e} | {p['smape']:.4f} | {p['seconds']['total']:.2f} | "
                     f"{_fmt(p['efficiency'], '.1f')} |")
        L += ["", "| run | budget | spp | relMSE | SMAPE | seconds (render / adapt / recon / overhead) "
                  "| efficiency | speed-up | error corr. | LP centres | regions | recon. memory B/px | notes |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in d["runs"]:
            if r.get("status") != "ok":
                L.append(f"| {r['name']} | {r['budget']} | | | | | | | | | | | ERROR: {r.get('error')} |")
                continue
            sec = r["seconds"]
            split = " / ".join(_fmt(sec.get(k), ".2f") for k in ("render", "adapt", "reconstruct", "overhead"))
            notes = []
            if r.get("partial"):
                notes.append(f"PARTIAL: stopped at {r['spp_mean']:.1f} of {r['budget']} spp by the run time cap")
            if "threshold" in r:
                notes.append(f"threshold {r['threshold']:.3g}, max {r.get('max_samples')} spp")
            if "relmse_without_denoiser" in r:
                notes.append(f"plain render without OIDN: relMSE {r['relmse_without_denoiser']:.2e}")
            if "time_ratio" in r:
                notes.append(f"time {r['time_ratio']:.2f}x target" + ("" if r.get("time_matched") else
                                                                      " (not matched)"))
            mem = r.get("memory", {})
            L.append(f"| {r['name']} | {r['budget']} | {_fmt(r['spp_mean'], '.2f')} | {r['relmse']:.3e} | "
                     f"{r['smape']:.4f} | {sec['total']:.2f} ({split}) | {_fmt(r.get('efficiency'), '.1f')} | "
                     f"{_fmt(r.get('speedup'), '.2f')} | {_fmt(r.get('error_correlation'), '.2f')} | "
                     f"{_fmt(r.get('center_fraction'), '.3f')} | {r.get('regions', '-')} | "
                     f"{_fmt(mem.get('bytes_per_pixel'), '.0f')} | {'; '.join(notes)} |")
        L += ["", f"![relMSE vs seconds](plot_{s}.png)", "", f"![sheet](sheet_{s}.png)", ""]

    sc = res.get("scaling")
    if sc:
        L += ["## Scaling: reconstruction time and memory by image size", "", sc["how"] + ".", ""]
        meths = list(dict.fromkeys(m for r in sc["rows"] for m in r.get("methods", {})))
        L += ["| size | MP | OIDN s (s/MP) | " + " | ".join(f"{m} s (s/MP, B/px)" for m in meths) + " |",
              "|---|---|---|" + "---|" * len(meths)]
        for r in sc["rows"]:
            if "methods" not in r:
                L.append(f"| {r['percentage']}% | | error: {r.get('error')} |" + " |" * len(meths))
                continue
            o = r["oidn"]
            oc = f"{o['seconds']:.2f} ({o['seconds_per_mp']:.2f})" if "seconds" in o else f"error: {o.get('error')}"
            cells = []
            for m in meths:
                v = r["methods"].get(m, {})
                if "seconds" in v:
                    cells.append(f"{v['seconds']:.2f} ({v['seconds_per_mp']:.2f}, "
                                 f"{_fmt(v.get('bytes_per_pixel'), '.0f')})")
                else:
                    cells.append(f"skipped: {v['skipped']}" if "skipped" in v else f"error: {v.get('error')}")
            L.append(f"| {r['width']}x{r['height']} | {r['megapixels']:.3f} | {oc} | " + " | ".join(cells) + " |")
        L.append("")
    if res.get("errors"):
        L += ["## Errors", ""] + [f"- {e}" for e in res["errors"]] + [""]
    return "\n".join(L) + "\n"


def _why_section(res) -> list:
    """Measured reasons next to the targets: where the time goes, how good the
    estimated maps are."""
    L = ["### Where the time goes (our methods, all scenes and budgets)", "",
         "| method | runs | render | adapt | reconstruct | overhead | mean error corr. |",
         "|---|---|---|---|---|---|---|"]
    acc = {}
    for d in res["scenes"].values():
        for r in d.get("runs", []):
            if r.get("status") == "ok" and r["kind"] in ("method", "oracle"):
                a = acc.setdefault(r["name"], {"n": 0, "render": 0.0, "adapt": 0.0, "reconstruct": 0.0,
                                               "overhead": 0.0, "total": 0.0, "corr": []})
                a["n"] += 1
                for k in ("render", "adapt", "reconstruct", "overhead", "total"):
                    a[k] += r["seconds"].get(k, 0.0)
                a["corr"].append(r.get("error_correlation"))
    for n, a in acc.items():
        tot = a["total"] or 1.0
        corr = [c for c in a["corr"] if c is not None]
        L.append(f"| {n} | {a['n']} | " + " | ".join(f"{100 * a[k] / tot:.0f}%" for k in
                                                     ("render", "adapt", "reconstruct", "overhead"))
                 + f" | {_fmt(float(np.mean(corr)) if corr else None, '.2f')} |")
    L.append("")
    return L

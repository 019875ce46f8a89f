"""One benchmark session: per scene, the reference, a warm-up, the plain
uniform curve, our methods' runs, the oracle runs and the peers; then the
scaling section.

One process, one scene file open at a time (``bpy.ops.wm.open_mainfile`` once
per scene).  Per scene:

1. the reference (:mod:`bench.references`: >= 1024 spp, seed 1000003, cached,
   refused when from another Blender version);
2. one warm-up render (persistent data stays on for the whole scene, so no run
   measured after it is charged the BVH build / kernel load);
3. the ``t_uniform(e)`` curve: plain Cycles (one render, the scene's own
   sampling pattern, no subsets) at several spp;
4. per budget: our methods through the real loop (``AdaptiveRun`` +
   ``CyclesExecutor``, as ``render`` runs them), the oracle runs (the same loop
   with :class:`core.oracle.OracleMethod` choosing where samples go from the true
   error), the uniform-sampling runs (:class:`core.oracle.UniformSampling`: the
   method's reconstruction on the budget rendered uniformly) and the peers
   (:mod:`bench.peers`); then the figures across runs
   (:func:`bench.targets.compare_runs`: relMSE ratios, cost vs OIDN, goals).

Then the scaling section: reconstruction seconds and peak traced memory per
method at several image sizes, next to OIDN's time at the same sizes.
"""
from __future__ import annotations

import os
import platform
import time
import tracemalloc
import traceback

import numpy as np

from ..core import methods as methods_registry
from ..core import metrics
from ..core.method import relative_error
from ..core.pipeline import AdaptiveRun, Options, hold_samples, render_subsets
from ..core.resources import peak_rss_mb
from . import references as refs
from .peers import PlainCycles, run_peers
from .report import err_text, finite, log
from .targets import BLOCK, compare_runs, evaluate_targets, run_figures, speedup_curve, summary_rows

FEATURES_ALL = ("normal", "albedo", "depth")
#: the relMSE denominator's epsilon (core.metrics): estimated maps on the true error's scale
RELMSE_EPS = 0.01
#: spp of the scaling section's buffers (in as many 1-spp subsets)
SCALING_SPP = 4


def machine_info() -> dict:
    """Versions and CPU of this session, for results.json and results.md."""
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
    """The 1/5/15-minute load averages (None where the platform has none)."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def _selects(name: str) -> bool:
    """A method that chooses another from the initial pass (``auto``): no
    oracle or uniform-sampling variant of it exists."""
    from ..core.pipeline import selects
    return selects(methods_registry.get(name))


def _run_capped(run, cap: float) -> bool:
    """Step ``run`` to its end, or stop it like a cancel (the generator
    closed between two steps: every merged sample is kept) once ``cap``
    seconds (``--run-max-seconds``; 0: none) have passed since its first
    step; True when the cap stopped it.  A safety cap, not
    ``Options.max_seconds``: that one plans the run's rounds from its
    timings (core/timeplan.py) and would change what is measured."""
    steps = run.steps()
    start = time.perf_counter()
    for _ in steps:
        if cap and time.perf_counter() - start > cap:
            steps.close()
            return True
    return False

class Session:
    """One benchmark session (see the module notes)."""

    def __init__(self, cfg: dict, argv=None):
        self.cfg = cfg
        self.argv = list(argv or [])
        self.sheet_budget = cfg["budgets"][len(cfg["budgets"]) // 2]

    # --------------------------------------------------------------- top
    def run(self) -> dict:
        """Every scene, the scaling section, targets and summary: the results
        dict :func:`bench.report.write_outputs` writes."""
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
                res["scenes"][name] = {"status": "error", "error": err_text(exc)}
                res["errors"].append({"scene": name, "error": err_text(exc)})
        res["scaling"] = self.run_scaling(first) if first and self.cfg["scaling_percentages"] else None
        res["loadavg_end"] = loadavg()
        res["peak_rss_mb"] = peak_rss_mb()
        res["session_seconds"] = time.perf_counter() - t0
        res["targets"] = evaluate_targets(res)
        res["summary"] = summary_rows(res)
        return res

    def protocol(self) -> dict:
        """How each figure was measured, in words (results.md's first section)."""
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
                    f"subsets, 4 iterations; Tabulated Sobol pattern, except runs that end at one count "
                    f"(uniform, the uniform-<method> runs, auto choosing uniform sampling: the scene's own "
                    f"pattern with the count held, Blender 4.4+)), seed {c['seed']}; a run "
                    f"is stopped like a cancel after {c['run_max_seconds']:g} s (0: never) and is then "
                    "flagged partial",
            "oracle": "(budgets above the 4-spp initial pass only: below it nothing adapts) the same loop; the sample map is the true per-pixel relative error of the "
                      "current reconstruction against the reference (3x3 pooled) times "
                      "n^(-4/(d+4)) (core/oracle.py)",
            "uniform_sampling": "uniform-<method> (at the oracle budgets, adaptive methods only): "
                                "the method's own reconstruction on the whole budget rendered "
                                "uniformly in the initial pass (ADAPTIVE False, 4 sample subsets; "
                                "core/oracle.py UniformSampling); gains are relMSE(uniform-m) / "
                                "relMSE(oracle-m) and / relMSE(m) at equal budget",
            "error_maps": "error corr. = Pearson correlation of the estimated squared error "
                          "(MethodResult.error, after the guard) with the true squared error "
                          f"(mean over RGB of (x - r)^2) per pixel; '{BLOCK}x{BLOCK}' is the same "
                          f"correlation of both maps averaged over {BLOCK}x{BLOCK} tiles (the "
                          "planner's scale), the figure the goal (>= 0.8) judges: per pixel the true "
                          "error of one render is one noisy realisation, with which even the exact "
                          "expected error correlates only 0.37-0.66 on the firefly-free sample "
                          "scenes (docs/notes/error-maps.md)",
            "artefacts": "guard = share of pixels the consistency guard (guard_z) replaced by "
                         "their sample mean, off it by more than float32 rounding (the share set "
                         "back for rounding alone is the JSON's guard_rounding); negative = share of pixels with a channel < 0 where "
                         "the reference's is >= 0, and the most negative such value; brightness = "
                         "100 (mean luminance of the result / mean luminance of the sample mean "
                         "- 1), %",
            "sampling": "beyond map = samples the planner rendered beyond the method's map "
                        "(AdaptiveRun.overshoot) / samples rendered, %; map CV = coefficient of "
                        "variation of the final per-pixel sample count; uniform share = pixels "
                        "within 5 % of the mean count (100 %: a uniform map)",
            "oidn_cost": "(adapt + reconstruct seconds) / megapixels of each run of our loop, over "
                         "the same budget's OIDN denoise seconds per megapixel: the oidn peer's "
                         "render with the denoiser minus the same render without it, rendered "
                         "right after it",
            "reference": (f"two independent halves (seed {refs.REFERENCE_SEED} and its mask) from "
                          f"{c['reference_spp']} spp, doubled until their noise floor is below "
                          f"{c.get('reference_floor'):g} relMSE (at most {c.get('reference_max_spp')} spp)"
                          if c.get("reference_floor") else
                          f"{c['reference_spp']} spp, seed {refs.REFERENCE_SEED}")
                         + " (independent of the runs), Tabulated Sobol, same Blender",
            "uniform_curve": "plain Cycles: one full-frame render, the scene's own sampling "
                             "pattern, no subsets",
            "cycles_oidn": "Cycles denoiser OpenImageDenoise on CPU, albedo+normal, prefilter ACCURATE, "
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
        """Steps 1-4 of the module notes for one scene; its results dict."""
        import bpy
        from ..addon import executor as ex
        cfg = self.cfg
        path = refs.scene_path(name)
        refs.open_scene(path, force=True)
        scene, vl = bpy.context.scene, bpy.context.view_layer
        frame = scene.frame_current
        t_ref = time.perf_counter()
        ref_path = refs.ensure_reference(path, frame, cfg["resolution_percentage"], cfg["reference_spp"],
                                         directory=cfg["reference_dir"],
                                         render_missing=cfg["render_references"], log=log,
                                         floor=cfg.get("reference_floor"),
                                         max_spp=cfg.get("reference_max_spp", refs.DEFAULT_MAX_SPP))
        t_ref = time.perf_counter() - t_ref
        t_scene = time.perf_counter()
        refs.open_scene(path, force=True)  # a fresh file, whatever rendering the reference did
        scene, vl = bpy.context.scene, bpy.context.view_layer
        guard = ex.SettingsGuard()
        guard.set(scene.render, "resolution_percentage", cfg["resolution_percentage"])
        guard.set(scene.render, "use_persistent_data", True)
        pattern = scene.cycles.sampling_pattern
        try:
            with ex.CyclesExecutor(scene, vl, (), seed=cfg["seed"]) as exe:
                size = exe.size
            ref, ref_rec = refs.load_checked_reference(ref_path, size)
            out = {"status": "ok", "file": path, "frame": frame, "width": size[1], "height": size[0],
                   "reference": {"path": ref_path, **{k: ref_rec.get(k) for k in (
                       "spp", "seed", "blender", "noise_relmse", "noise_relmse_halves", "floor_target",
                       "half_spp", "render_seconds", "created")}},
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
                        if m == "uniform" or _selects(m):
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
                if cfg.get("uniform_sampling", True) and budget in cfg["oracle_budgets"] \
                        and budget > Options().initial_spp:
                    for m in cfg["methods"]:
                        if m == "uniform" or _selects(m) or not methods_registry.get(m).ADAPTIVE:
                            continue
                        rec, _ = self.run_method(scene, vl, m, budget, frame, ref, uniform=True)
                        runs.append(rec)
                if cfg["peers"]:
                    ours = [r["seconds"]["total"] for r in runs if r.get("kind") == "method"
                            and r["budget"] == budget and r["status"] == "ok"]
                    for rec, pics in run_peers(scene, vl, pattern, budget, ref, ours, search, cfg):
                        runs.append(rec)
                        self._keep(keep, budget, rec, pics)
            for r in runs:
                r["scene"] = name
                if r.get("status") == "ok":
                    tu = t_uni(r["relmse"])
                    r["t_uniform_equal_error"] = finite(tu)
                    r["speedup"] = finite(tu / r["seconds"]["total"])
            for p in curve:
                p["speedup"] = finite(t_uni(p["relmse"]) / p["seconds"]["total"])
            plain = {p["spp"]: p for p in curve}
            for r in runs:  # proof that the denoiser ran: error of the same render without it
                if r["name"] == "cycles_oidn" and r.get("status") == "ok" and r["budget"] in plain:
                    r["relmse_without_denoiser"] = plain[r["budget"]]["relmse"]
            out["runs"] = runs
            out["comparisons"] = compare_runs(name, runs, size[0] * size[1] / 1e6)
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
        """Keep a successful run's pictures for the sheet (its budget only)."""
        if budget == self.sheet_budget and pics is not None and rec.get("status") == "ok":
            keep[rec["name"]] = pics

    def warmup(self, scene, vl) -> float:
        """One 1-spp render with every pass (not counted); its seconds."""
        from ..addon.executor import CyclesExecutor
        from ..core.regions import RegionTask
        t0 = time.perf_counter()
        with CyclesExecutor(scene, vl, FEATURES_ALL, seed=self.cfg["seed"]) as exe:
            h, w = exe.size
            exe.render(RegionTask(0, 0, w, h, 1, frame=scene.frame_current, offset=0))
        return time.perf_counter() - t0

    # ------------------------------------------------------ uniform curve
    def uniform_curve(self, scene, vl, pattern, ref) -> list:
        """Plain Cycles at each ``uniform_spp``: the points of ``t_uniform(e)``."""
        out = []
        with PlainCycles(scene, vl, self.cfg["seed"], pattern) as pc:
            for spp in self.cfg["uniform_spp"]:
                r = pc.render(spp)
                img = r["rgb"]
                e = metrics.relmse(img, ref)
                out.append({"kind": "uniform_curve", "name": "cycles_uniform", "spp": spp,
                            "spp_mean": float(spp), "relmse": e, "smape": metrics.smape(img, ref),
                            "seconds": {"total": r["seconds"], "render": r["seconds"]},
                            "efficiency": finite(1.0 / (e * r["seconds"]))})
                log(f"  plain uniform {spp:4d} spp: relMSE {e:.3e} in {r['seconds']:.2f} s")
                if spp == self.sheet_budget:
                    self._noisy = img
        return out

    # ----------------------------------------------------------- methods
    def run_method(self, scene, vl, name, budget, frame, ref, oracle=False, uniform=False):
        """One run of our loop (``oracle``: the true-error map; ``uniform``:
        the method's reconstruction on uniform sampling); returns (record,
        pictures for the sheet)."""
        from ..addon.executor import CyclesExecutor
        from ..core.oracle import OracleMethod, UniformSampling
        kind = "oracle" if oracle else "uniform_sampling" if uniform else "method"
        label = {"oracle": "oracle-", "uniform_sampling": "uniform-"}.get(kind, "") + name
        rec = {"kind": kind, "name": label, "method": name, "budget": budget}
        try:
            mod = methods_registry.get(name)
            wrapped = OracleMethod(mod, ref) if oracle else UniformSampling(mod) if uniform else None
            t0 = time.perf_counter()
            opts = Options(method=name, spp=float(budget), frame=frame, seed=self.cfg["seed"])
            exe = CyclesExecutor(scene, vl, tuple(mod.PASSES), seed=self.cfg["seed"])
            # as the job does: the scene's pattern at the run's one count
            hold_samples(exe, opts, wrapped or methods_registry.method_for(name, opts.params))
            with exe:
                run = AdaptiveRun(exe, opts, method=wrapped)
                capped = _run_capped(run, self.cfg["run_max_seconds"])
                result = run.reconstruct()
            wall = time.perf_counter() - t0
        except Exception as exc:
            rec.update(status="error", error=err_text(exc))
            log(f"  {label:>14} @ {budget:3d}: ERROR {rec['error']}")
            return rec, None
        tm = run.timing
        image = np.where(np.isfinite(result.image), result.image, 0.0)
        err = np.where(np.isfinite(result.error), result.error, 0.0)
        # not metrics.summary: relMSE and SMAPE judge the image as it is (a
        # non-finite pixel counts as a large error), the correlation the finite one
        e = metrics.relmse(result.image, ref)
        rec.update({
            "status": "ok", "spp_mean": run.samples_rendered / run.pixels,
            "relmse": e, "smape": metrics.smape(result.image, ref),
            "seconds": {"total": wall, "render": tm.render, "adapt": tm.adapt,
                        "reconstruct": tm.reconstruct,
                        "overhead": max(0.0, wall - tm.render - tm.adapt - tm.reconstruct)},
            "efficiency": finite(1.0 / (e * wall)) if e > 0 else None,
            "center_fraction": finite(result.info.get("center_fraction")),
            "regions": int(run.tasks_rendered), "iterations": int(run.iteration),
            "nonfinite_pixels": int((~np.isfinite(result.image)).any(axis=-1).sum()),
            "partial": bool(capped),
        })
        rec.update(run_figures(result.image, result.error, result.info.get("guard_fraction"),
                               run.buffers.n, run.buffers.color.mean, ref, run.overshoot,
                               run.samples_rendered))
        rec["guard_rounding"] = finite(result.info.get("guard_rounding"))
        rec.update(self.extra_run_figures(run, result, ref))
        if kind == "method":
            rec["memory"] = self.reconstruct_memory(run.method, run.buffers, run.params)
        if run.selection is not None:  # auto: what it chose and each candidate's prediction
            rec.update(chosen=run.selection["chosen"], candidates=run.selection["candidates"],
                       chosen_why=run.selection["why"])
        if run.selection is not None:
            log(f"  {label:>14} @ {budget:3d}: chose {run.selection['chosen']} ({run.selection['why']})")
        log(f"  {label:>14} @ {budget:3d}: relMSE {e:.3e} in {wall:6.2f} s "
            f"(render {tm.render:.2f}, adapt {tm.adapt:.2f}, reconstruct {tm.reconstruct:.2f}), "
            f"{run.tasks_rendered} renders" + (" [stopped by --run-max-seconds]" if rec["partial"] else ""))
        pics = {"image": image, "samples": run.buffers.n.copy(),
                "estimated": relative_error(err, image[..., :3], eps=RELMSE_EPS)}
        return rec, pics

    @staticmethod
    def extra_run_figures(run, result, ref) -> dict:
        """The place for one more per-run figure of our loop's runs (the
        calibrated variance's calibration ratio); nothing yet."""
        return {}

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
            return {"error": err_text(exc)}
        finally:
            tracemalloc.stop()
        px = buf.height * buf.width
        inputs = buf.n.nbytes + buf.k.nbytes + buf.color.mean.nbytes + buf.color.m2.nbytes + sum(
            s.mean.nbytes + s.m2.nbytes for s in buf.features.values())
        return {"reconstruct_peak_mb": peak / 2 ** 20, "bytes_per_pixel": peak / px,
                "input_bytes_per_pixel": inputs / px}

    # ----------------------------------------------------------- scaling
    def run_scaling(self, scene_name: str) -> dict:
        """Reconstruction time and peak traced memory per method at several
        sizes (the scene rendered at those sizes: ``SCALING_SPP`` spp in as many
        1-spp subsets with all feature passes), next to OIDN's time (a render of
        that many spp with OIDN minus the same render without)."""
        import bpy
        from ..addon import executor as ex
        cfg = self.cfg
        path = refs.scene_path(scene_name)
        refs.open_scene(path, force=True)
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
                    row.update(error=err_text(exc))
                    rows.append(row)
                    continue
                h, w = size
                row.update(width=w, height=h, megapixels=w * h / 1e6)
                # OIDN: the same plain render with and without the denoiser
                try:
                    with PlainCycles(scene, vl, cfg["seed"], pattern) as pc:
                        pc.render(1)  # sync at this size
                        t_off = pc.render(SCALING_SPP)["seconds"]
                        t_on = pc.render(SCALING_SPP, denoise=True)["seconds"]
                    row["oidn"] = {"seconds": max(t_on - t_off, 0.0), "render_seconds": t_off,
                                   "render_denoise_seconds": t_on,
                                   "seconds_per_mp": max(t_on - t_off, 0.0) / (w * h / 1e6)}
                except Exception as exc:
                    row["oidn"] = {"error": err_text(exc)}
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
        n = SCALING_SPP
        return {"scene": scene_name, "spp": n, "rows": rows, "seconds": time.perf_counter() - t_start,
                "how": f"scene rendered at each size ({n} spp in {n} sample subsets with the normal, "
                       "albedo, depth passes); a method's reconstruct timed once, then (up to "
                       f"{cfg['scaling_memory_mp']} MP) its peak traced memory measured in a second, "
                       "untimed call; a method whose time extrapolated from the previous size "
                       f"exceeds {cfg['scaling_max_seconds']:.0f} s is skipped and says so; OIDN "
                       f"seconds = ({n}-spp render with OIDN) - (the same without), after one sync "
                       "render at that size"}

    def _scaling_buffers(self, scene, vl):
        """Buffers of the scene at its current size: ``SCALING_SPP`` spp in as
        many 1-spp subsets with every feature pass."""
        from ..addon.executor import CyclesExecutor
        from ..core.buffers import Buffers
        with CyclesExecutor(scene, vl, FEATURES_ALL, seed=self.cfg["seed"]) as exe:
            h, w = exe.size
            buf = Buffers.empty(h, w, FEATURES_ALL + ("alpha",))
            render_subsets(exe, buf, SCALING_SPP, SCALING_SPP, scene.frame_current)
        return buf, (h, w)

    def _scaling_method(self, m, buf, memory=True) -> dict:
        """Seconds (and per MP) of one reconstruct of method ``m`` with default
        parameters, plus its traced memory when ``memory``."""
        try:
            mod = methods_registry.get(m)
            params = mod.Params()
            t0 = time.perf_counter()
            mod.reconstruct(buf, params)
            sec = time.perf_counter() - t0
        except Exception as exc:
            return {"error": err_text(exc)}
        mp = buf.height * buf.width / 1e6
        d = {"seconds": sec, "seconds_per_mp": sec / mp}
        if memory:
            d.update(self.reconstruct_memory(mod, buf, params))
        return d

"""The peers the benchmark compares against: what artists use today.

:class:`PlainCycles` renders the open scene as an artist gets it (one full-frame
render, the scene's own sampling pattern, no sample subsets), optionally with
Cycles adaptive sampling and/or the OpenImageDenoise denoiser.  :func:`run_peers`
makes, per budget, OIDN on a plain uniform render, Cycles adaptive sampling with
its noise threshold searched (:func:`search_threshold`) so its time matches our
runs at that budget, and adaptive sampling + OIDN.
"""
from __future__ import annotations

import math
import os
import time
import traceback

import numpy as np

from ..core import metrics
from .report import err_text, finite, log

#: first guess of Cycles' noise threshold (about right on the Cornell box)
FIRST_THRESHOLD = 0.05
THRESHOLD_RANGE = (1e-4, 0.5)
#: a time match within this factor ends the threshold search
TIME_MATCH = 1.2
SEARCH_TRIALS = 3
OIDN_SETTINGS = {"denoiser": "OPENIMAGEDENOISE", "denoising_input_passes": "RGB_ALBEDO_NORMAL",
                 "denoising_prefilter": "ACCURATE"}
PEER_NAMES = ("cycles_oidn", "cycles_adaptive", "cycles_adaptive+oidn")


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
            # every render a fresh session, as an artist's render: with persistent
            # data Cycles keeps the blue-noise table of the session's first sample
            # count, and a later render with another count used that stale table
            # (bpy 4.5: 4 spp after 16 spp = the first 4 samples of the 16-spp
            # sequence, not Cycles' 4-spp render)
            g.set(self.scene.render, "use_persistent_data", False)
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
        """One full-frame render; returns rgb, seconds (render, writing and
        reading the EXR) and (adaptive) mean spp."""
        from ..core import regions
        c, r = self.scene.cycles, self.scene.render
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
        self.exe.renders += 1
        t0 = time.perf_counter()
        passes = self.ex.render_still(self.scene, self.vl, path)
        seconds = time.perf_counter() - t0
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


def denoise_timing(with_oidn: dict, without: dict) -> dict:
    """OIDN's own seconds: a render with the denoiser minus the same render
    (same spp, seed, size) without it, clamped at 0, and per megapixel."""
    h, w = with_oidn["rgb"].shape[:2]
    sec = max(with_oidn["seconds"] - without["seconds"], 0.0)
    return {"denoise_seconds": sec, "render_seconds_without_denoiser": without["seconds"],
            "denoise_s_per_mp": sec / (h * w / 1e6) if h * w else None}


def _peer_error(name: str, budget: int, error: str) -> tuple:
    return {"kind": "peer", "name": name, "budget": budget, "status": "error", "error": error}, None


def run_peers(scene, vl, pattern, budget, ref, ours, search, cfg) -> list:
    """OIDN, Cycles adaptive sampling (time-matched to the median of ``ours``,
    our methods' seconds at this budget), adaptive + OIDN: a list of
    (record, pictures for the sheet).  ``search`` collects every threshold
    trial of the scene (reused across budgets)."""
    out = []
    target = float(np.median(ours)) if ours else None
    max_spp = cfg["max_samples_factor"] * max(cfg["budgets"])

    def rec_of(name, r, extra=None):
        e = metrics.relmse(r["rgb"], ref)
        d = {"kind": "peer", "name": name, "budget": budget, "status": "ok",
             "spp_mean": r["spp_mean"], "relmse": e, "smape": metrics.smape(r["rgb"], ref),
             "seconds": {"total": r["seconds"], "render": r["seconds"]},
             "efficiency": finite(1.0 / (e * r["seconds"])) if e > 0 else None}
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
                on = pc.render(budget, denoise=True)
                out.append(rec_of("cycles_oidn", on, {"settings": dict(OIDN_SETTINGS),
                                               **denoise_timing(on, pc.render(budget))}))
            except Exception as exc:
                out.append(_peer_error("cycles_oidn", budget, err_text(exc)))
            if target is None:
                err = "no successful run of our methods at this budget to match the time of"
                for n in PEER_NAMES[1:]:
                    out.append(_peer_error(n, budget, err))
                return out
            best = search_threshold(pc, max_spp, target, search, ref)
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
        for n in PEER_NAMES:
            if n not in have:
                out.append(_peer_error(n, budget, err_text(exc)))
    return out


def search_threshold(pc: PlainCycles, max_spp: int, target: float, search: list, ref) -> dict:
    """Cycles noise threshold whose render time matches ``target`` seconds.

    Secant steps on log(time) against log(threshold) over every render of
    this scene's search so far (they share max samples, so earlier budgets'
    renders are valid points); the first guess is 0.05; a trial is cut by
    Cycles' time limit at 4x the target (a bound, never chosen).  Returns
    the render whose time is closest to the target."""
    hi = THRESHOLD_RANGE[1]
    for _ in range(SEARCH_TRIALS):
        usable = [s for s in search if s["max_samples"] == max_spp]
        best = min((s for s in usable if not s["limited"]),
                   key=lambda s: abs(math.log(s["seconds"] / target)), default=None)
        if best is not None and abs(math.log(best["seconds"] / target)) <= math.log(TIME_MATCH):
            break
        if any(s["threshold"] >= hi * 0.999 and s["seconds"] > target * TIME_MATCH for s in usable):
            break  # even the loosest threshold is slower than the target: not matchable
        thr = next_threshold(usable, target)
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


def next_threshold(points, target) -> float:
    """Next noise threshold to try for render time ``target``: a secant step
    in log-log between the bracketing trials ``points`` (threshold, seconds,
    limited), else a step of slope -1 (clamped to [-3, -0.3] when two trials
    give one) from the nearest; clamped to ``THRESHOLD_RANGE``."""
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

"""Sequence benchmark: per-frame relMSE and a flicker measure on animated scenes.

For each animated scene, each method x temporal mode (``none``, ``reproject``,
``lp`` where it applies) runs through :class:`operators.job.FramesJob` (the
``render --frames ... --temporal`` path), and the peers render every frame with
plain Cycles (uniform, OIDN, Cycles adaptive sampling + OIDN; :mod:`bench.peers`).
Each sequence is judged against per-frame references (:mod:`bench.references`).

Temporal error (flicker) of frames x_1..x_T against references r_1..r_T::

    TE = mean over t = 2..T, pixels and RGB of
         ((x_t - x_{t-1}) - (r_t - r_{t-1}))^2 / (r_t^2 + 0.01)

It is zero for any sequence whose frame-to-frame change equals the reference's
(a correct sequence, or one off by a constant), and grows with noise or
artefacts that change from frame to frame.  Measurements: docs/notes/flicker.md.
"""
from __future__ import annotations

import argparse
import dataclasses
import glob
import hashlib
import json
import os
import re
import shlex
import shutil
import sys
import tempfile
import time
import traceback

import numpy as np

from ..core import io as imageio
from ..core import metrics
from . import references as refs
from .report import err_text, finite, log

#: the relMSE denominator's epsilon (core.metrics)
REL_EPS = metrics.REL_EPS
#: a non-finite term counts as this error (as core.metrics.relmse does)
NONFINITE_TERM = 1e6
DEFAULT_SCENES = ("animated", "courtyard")
DEFAULT_METHODS = ("uniform", "var", "lp", "oidn")
TEMPORAL_MODES = ("none", "reproject", "lp", "blend")
DEFAULT_OUT = os.path.join(refs.ROOT, "bench_out", "sequence")
PEERS = ("cycles_uniform", "cycles_oidn", "cycles_adaptive+oidn")
FORMULA = ("temporal error = mean over frames t = 2..T, pixels and RGB of "
           "((x_t - x_{t-1}) - (r_t - r_{t-1}))^2 / (r_t^2 + 0.01); "
           "relMSE = mean over pixels and RGB of (x_t - r_t)^2 / (r_t^2 + 0.01), per frame")


class SequenceError(ValueError):
    """Bad input for the sequence benchmark (one line for the user)."""


# ------------------------------------------------------------------ figures
def _rgb(a) -> np.ndarray:
    a = np.asarray(a, np.float64)
    if a.ndim != 3 or a.shape[-1] < 3:
        raise ValueError(f"expected (H, W, 3+) images, got shape {a.shape}")
    return a[..., :3]


def _check_sequence(frames, refs_) -> None:
    if len(frames) != len(refs_):
        raise ValueError(f"{len(frames)} frames but {len(refs_)} references")
    shapes = {np.shape(f)[:2] for f in frames} | {np.shape(r)[:2] for r in refs_}
    if len(shapes) > 1:
        raise ValueError(f"frames and references differ in size: {sorted(shapes)}")


def temporal_terms(x_prev, x, r_prev, r) -> np.ndarray:
    """Per pixel and channel ``((x - x_prev) - (r - r_prev))^2 / (r^2 + 0.01)``.

    The frame-difference error against the reference's own difference, scaled
    as relMSE scales (by the current reference frame).  A non-finite term (NaN
    or Inf in a frame) counts as ``NONFINITE_TERM`` (as :func:`core.metrics.relmse`
    treats a non-finite pixel), so a broken frame is never silently ignored.
    """
    d = (_rgb(x) - _rgb(x_prev)) - (_rgb(r) - _rgb(r_prev))
    rr = _rgb(r)
    with np.errstate(over="ignore", invalid="ignore"):
        e = d * d / (rr * rr + REL_EPS)
    return np.where(np.isfinite(e), e, NONFINITE_TERM)


def temporal_error(frames, refs_) -> float:
    """Temporal error (flicker) of a sequence against per-frame references.

    Mean over frames t = 2..T, pixels and RGB channels of
    ``((x_t - x_{t-1}) - (r_t - r_{t-1}))^2 / (r_t^2 + 0.01)`` (issue's
    definition; the denominator is relMSE's).  Accumulated in float64 one
    frame pair at a time (memory: two frames).  Fewer than two frames have no
    frame-to-frame change: ValueError (the caller reports no figure).
    """
    _check_sequence(frames, refs_)
    if len(frames) < 2:
        raise ValueError("the temporal error needs at least two frames")
    total, count = 0.0, 0
    for t in range(1, len(frames)):
        e = temporal_terms(frames[t - 1], frames[t], refs_[t - 1], refs_[t])
        total += float(e.sum(dtype=np.float64))
        count += e.size
    return total / count if count else 0.0


#: share of each run's pixels left out of its trimmed temporal error
TRIM_SHARE = 0.001


def trimmed_temporal_error(frames, refs_, share: float = TRIM_SHARE) -> float:
    """The temporal error without the run's own ``share`` of pixels (at least
    one) with the largest error: the mean over the other pixels of each
    pixel's mean term (:func:`temporal_terms`, over frames t >= 2 and RGB),
    a trimmed mean.

    Why: on the courtyard scene 87-95 % of every run's temporal error comes
    from 0.1 % of the pixels, a sun glint on a moving chrome ball (one pixel
    went from 0.2 to 64 and back in our frame 5, 22 in the reference), so the
    full figure ranks runs by which of them a glint sample hit
    (docs/notes/flicker.md).  Beside the full figure, never instead of it."""
    _check_sequence(frames, refs_)
    if len(frames) < 2:
        raise ValueError("the temporal error needs at least two frames")
    h, w = np.shape(frames[0])[:2]
    acc = np.zeros((h, w))
    for t in range(1, len(frames)):
        acc += temporal_terms(frames[t - 1], frames[t], refs_[t - 1], refs_[t]).mean(axis=-1)
    acc /= len(frames) - 1
    flat = acc.ravel()
    if flat.size == 0:
        return 0.0
    k = min(flat.size - 1, max(1, int(round(share * flat.size))))
    keep = np.partition(flat, flat.size - k - 1)[:flat.size - k] if k > 0 else flat
    return float(keep.mean(dtype=np.float64))


def frame_relmse(frames, refs_) -> list:
    """relMSE of each frame against its reference (:func:`core.metrics.relmse`)."""
    _check_sequence(frames, refs_)
    return [metrics.relmse(_rgb(x), _rgb(r)) for x, r in zip(frames, refs_)]


def sequence_figures(frames, refs_) -> dict:
    """Per-frame relMSE, their mean, the temporal error and its trimmed mean
    (:func:`trimmed_temporal_error`; both None for one frame)."""
    per = frame_relmse(frames, refs_)
    two = len(frames) >= 2
    return {"relmse_per_frame": per, "relmse_mean": float(np.mean(per)) if per else None,
            "temporal_error": temporal_error(frames, refs_) if two else None,
            "temporal_error_trimmed": trimmed_temporal_error(frames, refs_) if two else None}


def reference_floor(refs_, variances) -> dict:
    """Noise floors of noisy references: the relMSE and temporal error a
    perfect sequence would still show against them.

    With independent reference noise of variance v_t per frame,
    E[relMSE_t] = mean v_t / (r_t^2 + 0.01) (``references.noise_relmse``) and
    E[TE] = mean over t >= 2 of (v_t + v_{t-1}) / (r_t^2 + 0.01), both to first
    order in the noise (the noisy reference in the denominator adds a relative
    O(v / r^2), negligible at reference spp).
    """
    per = [refs.noise_relmse(_rgb(v), _rgb(r)) for r, v in zip(refs_, variances)]
    te = None
    if len(refs_) >= 2:
        acc = []
        for t in range(1, len(refs_)):
            r = _rgb(refs_[t])
            acc.append(float(((_rgb(variances[t]) + _rgb(variances[t - 1])) / (r * r + REL_EPS)).mean()))
        te = float(np.mean(acc))
    return {"relmse": float(np.mean(per)) if per else None, "temporal_error": te}


# --------------------------------------------------------------- references
def cached_reference_spp(scene: str, frames, pct: int, directory: str) -> int | None:
    """Highest spp at which the cache holds a valid reference of every frame
    (sidecar matching this .blend and Blender); None when there is none."""
    path = refs.scene_path(scene)
    label = refs.scene_label(path)
    found = None
    pattern = os.path.join(directory, f"{label}.f{int(frames[0]):04d}.r{int(pct)}.s*.exr")
    for p in glob.glob(pattern):
        m = re.search(r"\.s(\d+)\.exr$", p)
        if not m:
            continue
        spp = int(m.group(1))
        ok = all(not refs.mismatch(refs.read_sidecar(refs.reference_path(path, f, pct, spp, directory)),
                                   refs.wanted_record(path, f, pct, spp, refs.REFERENCE_SEED))
                 for f in frames)
        if ok and (found is None or spp > found):
            found = spp
    return found


def load_references(scene: str, frames, pct: int, spp: int, directory: str, shape,
                    render_missing: bool) -> tuple:
    """(rgb list, variance list, sidecar list) of the per-frame references."""
    path = refs.scene_path(scene)
    rgbs, vars_, recs = [], [], []
    for f in frames:
        p = refs.ensure_reference(path, f, pct, spp, directory=directory,
                                  render_missing=render_missing, log=log)
        rgb, rec = refs.load_checked_reference(p, shape)
        passes, _ = imageio.read_layers(p)
        var = passes.get("Variance")
        var = np.zeros_like(rgb) if var is None else np.asarray(var[..., :3], np.float64)
        rgbs.append(rgb)
        vars_.append(np.where(np.isfinite(var), var, 0.0))
        recs.append(rec)
    return rgbs, vars_, recs


# -------------------------------------------------------------------- runs
def _seeded(name: str, seed_mode: str) -> str:
    return name if seed_mode == "animated" else f"{name} ({seed_mode} seed)"


def history_label(params: dict) -> str:
    """The run-name suffix of a ``--history`` variant ("" for the defaults)."""
    return "[" + ",".join(f"{k}={v}" for k, v in params.items()) + "]" if params else ""


def run_ours(scene, vl, method: str, temporal: str, budget: int, frames, seed: int, tmpdir: str,
             max_seconds: float = 0.0, seed_mode: str = "animated", history_params: dict | None = None) -> tuple:
    """One sequence of our loop through FramesJob; (record, list of images).
    ``method``: a method spec of ``--methods`` (a name, optionally with its
    parameters: ``oidn[adaptive=False]``, :func:`parse_method_spec`);
    ``history_params``: core.history.Params of ``blend`` (a ``--history``
    variant; its settings join the run's name).

    Seconds per frame are the job's total minus writing its EXR (the loop,
    executor set-up, renders, reconstruction: what the benchmark times)."""
    from ..core.pipeline import Options
    from ..operators.job import FramesJob
    history_params = dict(history_params or {}) if temporal == "blend" else {}
    method_name, method_params = parse_method_spec(method)
    label = method_name + history_label(method_params)
    name = (label if temporal == "none" else f"{label}+{temporal}") + history_label(history_params)
    rec = {"kind": "method", "name": _seeded(name, seed_mode),
           "method": method_name, "temporal": temporal, "budget": int(budget), "seed_mode": seed_mode}
    if method_params:
        rec["method_params"] = method_params
    if history_params:
        rec["history_params"] = history_params
    images, seconds, spp, reused = [], [], [], []
    try:
        opts = Options(method=method_name, spp=float(budget), frame=int(frames[0]), seed=int(seed),
                       max_seconds=float(max_seconds), params=dict(method_params))
        tag = hashlib.sha1(method.encode()).hexdigest()[:8]
        pattern = os.path.join(tmpdir, f"{method_name}_{tag}_{temporal}_{seed_mode}_####.exr")
        fj = FramesJob(scene, vl, opts, pattern, frames, temporal=temporal, overwrite=True,
                       preview=False, keep_denoise_passes=False, seed_mode=seed_mode,
                       history_params=history_params)
        before = 0.0
        for item in fj.steps():
            if isinstance(item, dict):
                job = fj.job
                write_s = max(0.0, job.run.timing.overhead - before)
                seconds.append(max(0.0, item["total_seconds"] - write_s))
                images.append(np.asarray(job.result.image, np.float64)[..., :3])
                spp.append(item["spp_mean"])
                reused.append(item.get("reprojected_fraction", 0.0))
                if job.out and os.path.exists(job.out):
                    os.unlink(job.out)  # the image is kept in memory; the EXR is not needed
            elif fj.run is not None:
                before = fj.run.timing.overhead
    except Exception as exc:
        traceback.print_exc()
        rec.update(status="error", error=err_text(exc))
        return rec, None
    rec.update(status="ok", seconds=float(sum(seconds)), seconds_per_frame=seconds,
               spp_mean=float(np.mean(spp)), reprojected_fraction=float(np.mean(reused)))
    return rec, images


def run_peers(scene, vl, budget: int, frames, seed: int, ref0, target_seconds, cfg,
              seed_mode: str = "animated") -> list:
    """The peers on every frame: plain Cycles uniform, OIDN, Cycles adaptive
    sampling + OIDN; a list of (record, images).

    Each frame gets the seed ``seed + frame`` (``seed`` with ``seed_mode``
    ``"fixed"``), as FramesJob's runs do.  The
    adaptive peer's noise threshold is searched once, on the first frame, so
    its render time matches ``target_seconds`` (the median per-frame time of
    our runs at this budget; :func:`bench.peers.search_threshold`), and then
    kept for the whole shot, as an artist sets one threshold per shot."""
    from . import peers as pe
    out = []
    c = scene.cycles
    pattern = c.sampling_pattern
    max_spp = int(cfg["max_samples_factor"]) * int(budget)

    def frame_seed(f):
        return int(seed + (f if seed_mode == "animated" else 0))

    def sequence(name, render, extra=None):
        rec = {"kind": "peer", "name": _seeded(name, seed_mode), "temporal": "none", "budget": int(budget),
               "seed_mode": seed_mode}
        rec.update(extra or {})
        images, seconds = [], []
        try:
            for f in frames:
                scene.frame_set(f)
                c.seed = frame_seed(f)
                r = render()
                images.append(r["rgb"])
                seconds.append(r["seconds"])
        except Exception as exc:
            traceback.print_exc()
            rec.update(status="error", error=err_text(exc))
            return rec, None
        rec.update(status="ok", seconds=float(sum(seconds)), seconds_per_frame=seconds,
                   spp_mean=float(budget) if name != "cycles_adaptive+oidn" else None)
        return rec, images

    try:
        with pe.PlainCycles(scene, vl, seed, pattern) as pc:
            scene.frame_set(frames[0])
            pc.render(1)  # sync at this frame (not counted)
            out.append(sequence("cycles_uniform", lambda: pc.render(budget)))
            out.append(sequence("cycles_oidn", lambda: pc.render(budget, denoise=True),
                                {"settings": dict(pe.OIDN_SETTINGS)}))
            if target_seconds is None:
                out.append(({"kind": "peer", "name": _seeded("cycles_adaptive+oidn", seed_mode),
                             "budget": int(budget), "status": "error",
                             "error": "no successful run of ours to match the time of"}, None))
                return out
            scene.frame_set(frames[0])
            c.seed = frame_seed(frames[0])
            search = []
            best = pe.search_threshold(pc, max_spp, target_seconds, search, ref0)
            thr = best["threshold"]
            out.append(sequence("cycles_adaptive+oidn",
                                lambda: pc.render(max_spp, denoise=True, threshold=thr),
                                {"threshold": thr, "max_samples": max_spp,
                                 "target_seconds_per_frame": target_seconds,
                                 "settings": dict(pe.OIDN_SETTINGS)}))
    except Exception as exc:
        traceback.print_exc()
        have = {d["name"] for d, _ in out}
        out += [({"kind": "peer", "name": _seeded(n, seed_mode), "budget": int(budget), "status": "error",
                  "error": err_text(exc)}, None) for n in PEERS if _seeded(n, seed_mode) not in have]
    return out


def configurations(methods, temporals, seed_modes=("animated",), history_variants=({},)) -> list:
    """(method, temporal, seed mode, history params) to run: ``lp`` temporal
    only with method lp, the modes of ``FramesJob.NEEDS_ANIMATED_SEED`` only
    with the animated seed (FramesJob refuses them fixed), each ``--history``
    variant with ``blend`` (the other modes once, with ``{}``)."""
    from ..operators.job import FramesJob
    animated_only = FramesJob.NEEDS_ANIMATED_SEED
    return [(m, t, sm, hv) for sm in seed_modes for m in methods for t in temporals
            for hv in (history_variants if t == "blend" else ({},))
            if (t != "lp" or method_name(m) == "lp") and (t not in animated_only or sm == "animated")]


def split_top_level(text: str, sep: str = ",") -> list:
    """``text`` split at ``sep`` outside square brackets (``a,b[x=1,y=2]``
    -> ``["a", "b[x=1,y=2]"]``); stripped, empty parts dropped."""
    parts, depth, cur = [], 0, []
    for ch in text:
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth = max(0, depth - 1)
        if ch == sep and depth == 0:
            parts.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    parts.append("".join(cur))
    return [p.strip() for p in parts if p.strip()]


def _settings(text: str, what: str) -> dict:
    """``key=value`` pairs separated by ``,`` (values as int, float or text)."""
    d = {}
    for item in filter(None, (x.strip() for x in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep:
            raise SequenceError(f"{what}: {item!r} is not key=value")
        d[key.strip().replace("-", "_")] = _scalar(value.strip())
    return d


def _checked(params_type, d: dict, what: str) -> None:
    """Refuse unknown keys and out-of-range values of ``params_type`` now,
    before any render."""
    from ..core.method import params_from_dict
    known = {f.name for f in dataclasses.fields(params_type)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise SequenceError(f"{what}: unknown setting(s) {', '.join(unknown)} "
                            f"(known: {', '.join(sorted(known))})")
    try:
        params_from_dict(params_type, d)
    except (TypeError, ValueError, KeyError) as exc:
        raise SequenceError(f"{what}: {exc}") from None


def method_name(spec: str) -> str:
    """The method name of a ``--methods`` spec (``oidn[adaptive=False]`` -> ``oidn``)."""
    return spec.partition("[")[0].strip()


def parse_method_spec(spec: str) -> tuple:
    """``name`` or ``name[key=value,...]`` (the method's Params) -> (name,
    params dict); unknown methods, keys and out-of-range values are refused."""
    from ..core import methods as registry
    spec = spec.strip()
    name, (_, bracket, rest) = method_name(spec), spec.partition("[")
    if name not in registry.METHODS:
        raise SequenceError(f"unknown method {name!r}; choose from {', '.join(registry.METHODS)}")
    if not bracket:
        return name, {}
    if not rest.endswith("]"):
        raise SequenceError(f"--methods {spec!r}: parameters go in [key=value,...]")
    params = _settings(rest[:-1], f"--methods {spec!r}")
    _checked(registry.get(name).Params, params, f"--methods {spec!r}")
    return name, params


def parse_history_variants(text: str | None) -> list:
    """``--history``: variants separated by ``;``, each ``key=value`` pairs
    separated by ``,`` of core.history.Params (``""``: the defaults); checked
    against the Params now, so a typo fails before any render."""
    from ..core import history
    if not text:
        return [{}]
    out = []
    for part in text.split(";"):
        d = _settings(part, "--history")
        _checked(history.Params, d, f"--history {part!r}")
        out.append(d)
    return out


def _scalar(text: str):
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def run_scene(name: str, cfg: dict, keep_images: bool = False, publish=None) -> dict:
    """Every configuration and peer on one animated scene; its results dict
    (``images``: name -> frames, when ``keep_images``).  ``publish(d)`` is
    called with the scene's dict so far after every run (partial outputs)."""
    import bpy
    from ..addon import executor as ex
    path = refs.scene_path(name)
    refs.open_scene(path, force=True)
    scene, vl = bpy.context.scene, bpy.context.view_layer
    frames = cfg["frames"] or list(range(scene.frame_start, scene.frame_end + 1))
    if cfg["max_frames"]:
        frames = frames[:cfg["max_frames"]]
    if len(frames) < 2:
        raise SequenceError(f"{name}: needs at least two frames, got {frames}")
    pct = cfg["resolution_percentage"]
    spp = cfg["reference_spp"]
    if spp == "auto":
        spp = cached_reference_spp(name, frames, pct, cfg["reference_dir"]) or refs.DEFAULT_SPP
    guard = ex.SettingsGuard()
    guard.set(scene.render, "resolution_percentage", pct)
    with ex.CyclesExecutor(scene, vl, ()) as exe:
        shape = exe.size
    guard.restore()
    t_ref = time.perf_counter()
    ref_rgb, ref_var, recs = load_references(name, frames, pct, int(spp), cfg["reference_dir"], shape,
                                             cfg["render_references"])
    t_ref = time.perf_counter() - t_ref
    refs.open_scene(path, force=True)  # a fresh file, whatever the references did
    scene, vl = bpy.context.scene, bpy.context.view_layer
    guard = ex.SettingsGuard()
    guard.set(scene.render, "resolution_percentage", pct)
    guard.set(scene.render, "use_persistent_data", True)
    floor = reference_floor(ref_rgb, ref_var)
    out = {"status": "ok", "file": path, "frames": frames, "width": shape[1], "height": shape[0],
           "reference": {"spp": int(spp), "seed": refs.REFERENCE_SEED, "noise_relmse": floor["relmse"],
                         "noise_temporal_error": floor["temporal_error"],
                         "render_seconds": float(sum(r.get("render_seconds") or 0.0 for r in recs)),
                         "seconds_this_session": t_ref}}
    log(f"{name}: {shape[1]}x{shape[0]}, frames {frames[0]}-{frames[-1]} ({len(frames)}), references "
        f"{spp} spp (noise floor relMSE {floor['relmse']:.2e}, temporal {floor['temporal_error']:.2e})")
    runs, images = [], {}
    out["runs"] = runs
    publish = publish or (lambda d: None)
    tmp = tempfile.mkdtemp(prefix="cycles-adaptive-seq-")
    try:
        seed_modes = cfg.get("seed_modes", ["animated"])
        for budget in cfg["budgets"]:
            ours = []
            variants = cfg.get("history_variants", [{}])
            for m, t, sm, hv in configurations(cfg["methods"], cfg["temporal"], seed_modes, variants):
                rec, imgs = run_ours(scene, vl, m, t, budget, frames, cfg["seed"], tmp,
                                     cfg["run_max_seconds"], sm, hv)
                runs.append(_judge(rec, imgs, ref_rgb, images, keep_images))
                publish(out)
                if rec["status"] == "ok":
                    ours.extend(rec["seconds_per_frame"])
            if cfg["peers"]:
                target = float(np.median(ours)) if ours else None
                for sm in seed_modes:
                    for rec, imgs in run_peers(scene, vl, budget, frames, cfg["seed"], ref_rgb[0], target, cfg,
                                               sm):
                        runs.append(_judge(rec, imgs, ref_rgb, images, keep_images))
                        publish(out)
    finally:
        guard.restore()
        shutil.rmtree(tmp, ignore_errors=True)
    if keep_images:
        out["images"] = images
        out["reference_images"] = ref_rgb
    return out


def _judge(rec, imgs, ref_rgb, images, keep) -> dict:
    """Add the sequence figures to a run's record (and log one line)."""
    if rec.get("status") == "ok" and imgs is not None:
        fig = sequence_figures(imgs, ref_rgb)
        rec.update({k: (finite(v) if not isinstance(v, list) else [finite(x) for x in v])
                    for k, v in fig.items()})
        if keep:
            images[f"{rec['name']}@{rec['budget']}"] = imgs
        trim = rec.get("temporal_error_trimmed")
        log(f"  {rec['name']:>22} @ {rec['budget']:3d}: relMSE {rec['relmse_mean']:.3e}, temporal "
            f"{rec['temporal_error']:.3e}" + ("" if trim is None else f" (trimmed {trim:.3e})")
            + f", {rec['seconds']:.1f} s")
    else:
        log(f"  {rec['name']:>22} @ {rec['budget']:3d}: ERROR {rec.get('error')}")
    return rec


# ------------------------------------------------------------------ report
def markdown(res: dict) -> str:
    """The tables of a session: per scene, every run's mean relMSE, temporal
    error, seconds and per-frame relMSE, with the reference's noise floors
    (kind ``method``: our loop through FramesJob; ``peer``: plain Cycles)."""
    m = res.get("machine") or {}
    lines = ["# Sequence benchmark: per-frame relMSE and temporal error", "",
             f"Command: `{res['command']}`", "", f"Formula: {FORMULA}.", "",
             f"Machine: {m.get('cpu_model', '?')}, {m.get('cpu_count')} cores, Blender {m.get('blender')}; "
             f"load average {res.get('loadavg_start')} at the start, {res.get('loadavg_end')} at the end "
             f"(other processes share the cores: seconds are wall times under that load); started "
             f"{res['started']}, {res['session_seconds']:.0f} s.", ""]
    for name, d in res["scenes"].items():
        if d.get("status") != "ok":
            lines += [f"## {name}", "", f"error: {d.get('error')}", ""]
            continue
        r = d["reference"]
        lines += [f"## {name} ({d['width']}x{d['height']}, frames {d['frames'][0]}-{d['frames'][-1]}, "
                  f"{len(d['frames'])} frames)", "",
                  f"References: {r['spp']} spp, seed {r['seed']}; noise floor (a perfect sequence "
                  f"against them): relMSE {r['noise_relmse']:.2e}, temporal error "
                  f"{r['noise_temporal_error']:.2e}. TE (trimmed): without each run's own "
                  f"{100 * TRIM_SHARE:g} % of pixels with the largest temporal error.", "",
                  "| kind | run | temporal | spp | relMSE (mean) | temporal error | TE (trimmed) | seconds | "
                  "s/frame | reused | per-frame relMSE |", "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
        for x in d["runs"]:
            if x.get("status") != "ok":
                lines.append(f"| {x.get('kind')} | {x['name']} | {x.get('temporal', 'none')} | {x['budget']} | "
                             "error | | | | | | "
                             f"{x.get('error', '')} |")
                continue
            per = " ".join(f"{v:.3g}" for v in x["relmse_per_frame"])
            reused = x.get("reprojected_fraction")
            conv = x.get("temporal_error_trimmed")
            lines.append(f"| {x.get('kind')} | {x['name']} | {x.get('temporal', 'none')} | {x['budget']} | "
                         f"{x['relmse_mean']:.3e} | {x['temporal_error']:.3e} | "
                         f"{'' if conv is None else f'{conv:.3e}'} | {x['seconds']:.1f} | "
                         f"{x['seconds'] / len(d['frames']):.2f} | "
                         f"{'' if reused is None else f'{100 * reused:.0f} %'} | {per} |")
        lines.append("")
    return "\n".join(lines) + "\n"


def write_outputs(res: dict, out: str) -> dict:
    """``sequence.json`` (every figure) and ``sequence.md`` in ``out`` (atomic writes)."""
    os.makedirs(out, exist_ok=True)
    clean = json.loads(json.dumps(res, default=lambda o: None if isinstance(o, np.ndarray) else
                                  o.item() if isinstance(o, np.generic) else str(o)))
    jp, mp = os.path.join(out, "sequence.json"), os.path.join(out, "sequence.md")
    imageio.write_text(jp, json.dumps(clean, indent=1))
    imageio.write_text(mp, markdown(clean))
    return {"json": jp, "markdown": mp}


# --------------------------------------------------------------------- CLI
def _ints(text, what) -> list:
    try:
        vals = [int(float(v)) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise SequenceError(f"--{what}: cannot read {text!r} (comma-separated numbers)") from None
    if not vals or any(v < 1 for v in vals):
        raise SequenceError(f"--{what}: give positive whole numbers, got {text!r}")
    return sorted(set(vals))


def parse_frame_range(text: str | None) -> list | None:
    """``"1-8"`` or ``"1,3,5"`` -> frames; None/empty -> None (each file's range)."""
    if not text:
        return None
    out = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        a, _, b = part.partition("-")
        if not a.isdigit() or (b and not b.isdigit()):
            raise SequenceError(f"--frames: cannot read {part!r} (use e.g. 1-8 or 1,2,3)")
        out.extend(range(int(a), int(b or a) + 1))
    return out or None


def add_arguments(p) -> None:
    """The flags of ``./cycles-adaptive bench-sequence``."""
    p.add_argument("--scenes", default=",".join(DEFAULT_SCENES),
                   help=f"comma-separated animated scenes or .blend paths (default {','.join(DEFAULT_SCENES)})")
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                   help=f"comma-separated methods (default {','.join(DEFAULT_METHODS)}), each optionally "
                        "with its parameters: 'oidn,oidn[adaptive=false,error_estimate=false]'")
    p.add_argument("--temporal", default=",".join(TEMPORAL_MODES),
                   help="temporal modes to run (default none,reproject,lp,blend; lp only with method lp)")
    p.add_argument("--budgets", default="8", help="comma-separated spp budgets (default 8)")
    p.add_argument("--frames", help="frame range for every scene, e.g. 1-8 (default: each file's range)")
    p.add_argument("--max-frames", type=int, default=0, help="use at most this many frames (0: all)")
    p.add_argument("--resolution-percentage", type=int, default=100, help="resolution %% (default 100)")
    p.add_argument("--reference-spp", default="auto", help="spp of the per-frame references; 'auto' "
                   "(default): the highest spp cached for every frame, else 1024")
    p.add_argument("--reference-dir", default=refs.DEFAULT_DIR, help="reference cache (default references/)")
    p.add_argument("--no-render-references", action="store_true",
                   help="stop instead of rendering a missing reference")
    p.add_argument("--no-peers", action="store_true", help="skip the plain Cycles / OIDN peers")
    p.add_argument("--seed", type=int, default=0, help="base Cycles seed of the runs (frame f: seed + f)")
    p.add_argument("--seed-modes", default="animated",
                   help="comma-separated: 'animated' (frame f renders with seed + f) and/or 'fixed' (every "
                        "frame with seed), for our runs and the peers (default animated)")
    p.add_argument("--max-samples-factor", type=int, default=16,
                   help="Cycles adaptive peer's max samples = this x the budget (default 16)")
    p.add_argument("--run-max-seconds", type=float, default=0.0,
                   help="time limit of each frame (render's --max-seconds, planned from the run's "
                        "timings: changes what the run renders; 0: none)")
    p.add_argument("--history", default="",
                   help="settings of --temporal blend (core.history.Params) to compare: variants separated "
                        "by ';', each key=value pairs separated by ',', e.g. 'input_frames=1;max_frames=1' "
                        "(default: the defaults)")
    p.add_argument("--out", default=DEFAULT_OUT, help="output folder (default bench_out/sequence)")
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")


def resolve_config(args) -> dict:
    """Validated settings of one sequence session."""
    methods = split_top_level(args.methods)
    for m in methods:
        parse_method_spec(m)
    temporal = [t.strip() for t in args.temporal.split(",") if t.strip()]
    for t in temporal:
        if t not in TEMPORAL_MODES:
            raise SequenceError(f"unknown temporal mode {t!r}; choose from {', '.join(TEMPORAL_MODES)}")
    seed_modes = list(dict.fromkeys(m.strip() for m in args.seed_modes.split(",") if m.strip()))
    for sm in seed_modes:
        if sm not in ("animated", "fixed"):
            raise SequenceError(f"unknown seed mode {sm!r}; choose animated and/or fixed")
    if not seed_modes:
        raise SequenceError("--seed-modes: give animated and/or fixed")
    history_variants = parse_history_variants(args.history)
    if not configurations(methods, temporal, seed_modes):
        raise SequenceError("no method x temporal configuration to run")
    try:
        scenes = refs.scene_names(args.scenes)
    except ValueError as exc:
        raise SequenceError(str(exc)) from None
    if not 1 <= args.resolution_percentage <= 10000:
        raise SequenceError("--resolution-percentage must be between 1 and 10000")
    rs = str(args.reference_spp)
    if rs != "auto":
        rs = _ints(rs, "reference-spp")[0]
    if args.seed == refs.REFERENCE_SEED:
        raise SequenceError(f"--seed {args.seed} is the references' seed; the runs need another")
    if args.max_frames < 0 or args.max_samples_factor < 1:
        raise SequenceError("--max-frames must be >= 0 and --max-samples-factor >= 1")
    return {"scenes": scenes, "methods": methods, "temporal": temporal,
            "budgets": _ints(args.budgets, "budgets"), "frames": parse_frame_range(args.frames),
            "max_frames": int(args.max_frames), "resolution_percentage": int(args.resolution_percentage),
            "reference_spp": rs, "reference_dir": os.path.abspath(args.reference_dir),
            "render_references": not args.no_render_references, "peers": not args.no_peers,
            "seed": int(args.seed), "seed_modes": seed_modes, "max_samples_factor": int(args.max_samples_factor),
            "run_max_seconds": float(args.run_max_seconds), "history_variants": history_variants,
            "out": os.path.abspath(args.out)}


def command_of(cfg: dict) -> str:
    """The command line that reproduces ``cfg`` (for the report)."""
    parts = ["./cycles-adaptive bench-sequence", "--scenes", ",".join(cfg["scenes"]),
             "--methods", shlex.quote(",".join(cfg["methods"])), "--temporal", ",".join(cfg["temporal"]),
             "--budgets", ",".join(map(str, cfg["budgets"]))]
    if cfg["frames"]:
        parts += ["--frames", ",".join(map(str, cfg["frames"]))]
    if cfg["max_frames"]:
        parts += ["--max-frames", str(cfg["max_frames"])]
    if cfg["resolution_percentage"] != 100:
        parts += ["--resolution-percentage", str(cfg["resolution_percentage"])]
    parts += ["--reference-spp", str(cfg["reference_spp"]), "--reference-dir", cfg["reference_dir"]]
    if not cfg["peers"]:
        parts.append("--no-peers")
    if cfg["seed"]:
        parts += ["--seed", str(cfg["seed"])]
    if cfg.get("seed_modes", ["animated"]) != ["animated"]:
        parts += ["--seed-modes", ",".join(cfg["seed_modes"])]
    if cfg["max_samples_factor"] != 16:
        parts += ["--max-samples-factor", str(cfg["max_samples_factor"])]
    if cfg["run_max_seconds"]:
        parts += ["--run-max-seconds", f"{cfg['run_max_seconds']:g}"]
    if cfg.get("history_variants", [{}]) != [{}]:
        text = ";".join(",".join(f"{k}={v}" for k, v in d.items()) for d in cfg["history_variants"])
        parts += ["--history", shlex.quote(text)]
    return " ".join(parts)


def run(cfg: dict, command: str = "", keep_images: bool = False, write: bool = False) -> dict:
    """Every scene of ``cfg``; the results dict (a scene that fails is reported).
    ``write``: rewrite the outputs in ``cfg["out"]`` after every run, so an
    interrupted session leaves what it measured."""
    from .session import loadavg, machine_info
    t0 = time.perf_counter()
    res = {"version": 1, "command": command, "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
           "formula": FORMULA, "machine": machine_info(), "config": cfg, "loadavg_start": loadavg(), "scenes": {}}
    def publish(name, d):
        res["scenes"][name] = d
        res["session_seconds"] = time.perf_counter() - t0
        if write:
            write_outputs(res, cfg["out"])

    for name in cfg["scenes"]:
        try:
            res["scenes"][name] = run_scene(name, cfg, keep_images, lambda d, n=name: publish(n, d))
        except ValueError:
            raise
        except Exception as exc:
            traceback.print_exc()
            res["scenes"][name] = {"status": "error", "error": err_text(exc)}
    res["loadavg_end"] = loadavg()
    res["session_seconds"] = time.perf_counter() - t0
    return res


def main(args) -> int:
    """``./cycles-adaptive bench-sequence``: run, write sequence.json/.md."""
    cfg = resolve_config(args)
    res = run(cfg, command_of(cfg), write=True)
    paths = write_outputs(res, cfg["out"])
    log(f"wrote {paths['markdown']} and {paths['json']}")
    if args.json:
        print(json.dumps({"out": cfg["out"], "seconds": res["session_seconds"], **paths}))
    bad = [n for n, d in res["scenes"].items() if d.get("status") != "ok"]
    return 1 if bad else 0


if __name__ == "__main__":  # pragma: no cover
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(ap)
    sys.exit(main(ap.parse_args()))

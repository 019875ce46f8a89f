"""One adaptive render job: scene -> loop -> outputs.  The same generator runs
behind the CLI (``./cycles-adaptive render``, ``blender -c cycles_adaptive``)
and the modal UI operator.

Outputs (written atomically; an existing file is never replaced unless
``overwrite``):
- ``OUT.exr``: multilayer EXR, layer = the view layer's name, passes
  ``Combined`` (result RGB + mean alpha), ``Noisy``, ``Variance`` (of the mean,
  0 where unknown), ``M2``, ``Samples``, ``Groups``, ``Error`` (estimated
  squared error), ``NextIndex`` and ``Feat_<name>`` / ``Feat_<name>_M2`` for every
  feature pass: all that ``denoise`` needs to re-run any method later.
- ``OUT.png``: preview in the scene's view transform.
- ``OUT.exr.checkpoint.npz`` after every iteration, removed after a complete
  run, kept after a cancel so ``--resume`` continues.
"""
from __future__ import annotations

import json
import os
import time

import numpy as np

from ..core import io as imageio
from ..core import metrics
from ..core.pipeline import AdaptiveRun, Options
from ..core.resources import peak_rss_mb
from ..core.storage import buffers_to_passes

OUTPUT_VERSION = "1"


class JobError(Exception):
    """Bad input for a job; the message is for the user, one line."""


def checkpoint_path(out: str) -> str:
    return out + ".checkpoint.npz"


def preview_path(out: str) -> str:
    return os.path.splitext(out)[0] + ".png"


def load_reference(path: str | None, shape) -> np.ndarray | None:
    """The ``--reference`` image checked against the render's (H, W); None
    without a path; JobError (one line) for an unreadable or mis-sized file."""
    if not path:
        return None
    try:
        return imageio.read_reference(path, shape)
    except imageio.ImageFileError as exc:
        raise JobError(str(exc)) from None


def pad_to_frame(arr: np.ndarray, domain, full_size) -> np.ndarray:
    """Place a border-domain image back into the full frame (zeros outside),
    as Cycles does for a border render without crop."""
    x0, y0, x1, y1 = domain
    w, h = full_size
    out = np.zeros((h, w) + arr.shape[2:], arr.dtype)
    out[y0:y1, x0:x1] = arr
    return out


class RenderJob:
    """Adaptive render of one frame of a scene.

    ``steps()`` yields ``Progress``; when it ends (or after a cancel) call
    ``finish(partial=...)``, which reconstructs, writes the outputs and returns
    the summary dict (the CLI's JSON line).
    """

    def __init__(self, scene, view_layer, options: Options, out: str, reference: str | None = None,
                 overwrite: bool = False, resume: bool = False, preview: bool = True,
                 keep_checkpoint: bool = False, method=None, prior=None, reconstructor=None):
        """``method``: a :class:`core.method.Method` object (default: the
        registered ``options.method``); ``prior``: the run's source of carried
        samples (``core.pipeline.Prior``); ``reconstructor(run) -> MethodResult``
        replaces the method's final reconstruction (LP's temporal extension)."""
        from ..addon import executor as ex
        from ..core import methods
        self.ex = ex
        ex.check_scene(scene, view_layer)
        self.scene, self.view_layer = scene, view_layer
        self.options = options
        self.out = os.path.abspath(bpy_path(out))
        self.ckpt = checkpoint_path(self.out)
        self.resume = resume
        if resume and not os.path.isfile(self.ckpt):
            raise JobError(f"--resume: no checkpoint {self.ckpt}")
        try:
            imageio.check_writable(self.out, overwrite or resume)
            if preview:
                imageio.check_writable(preview_path(self.out), overwrite or resume)
        except imageio.ImageFileError as exc:
            raise JobError(str(exc)) from None
        self.preview = preview
        self.keep_checkpoint = keep_checkpoint
        self.reference_path = reference
        self.run: AdaptiveRun | None = None
        self.executor = None
        self.method = methods.get(options.method) if method is None else method
        self.prior = prior
        self.reconstructor = reconstructor
        self.camera = None         # camera matrices of the rendered frame
        self.result = None         # the final MethodResult, once finish() ran
        self.t0 = time.perf_counter()
        self.summary: dict | None = None

    def steps(self):
        self.executor = self.ex.CyclesExecutor(self.scene, self.view_layer,
                                               tuple(self.method.PASSES) + tuple(self.options.features),
                                               seed=self.options.seed)
        self.reference = load_reference(self.reference_path, self.executor.size)
        with self.executor:
            self.camera = self.executor.camera_info(self.options.frame)
            self.run = AdaptiveRun(self.executor, self.options, checkpoint=self.ckpt, prior=self.prior,
                                   method=self.method)
            if self.resume:
                try:
                    self.run.load_checkpoint(self.ckpt)
                except ValueError as exc:
                    raise JobError(str(exc)) from None
            yield from self.run.steps()

    def finish(self, partial: bool = False) -> dict:
        """Reconstruct from what was rendered and write the outputs."""
        run = self.run
        if run is None or run.buffers is None:
            raise JobError("nothing was rendered")
        result = run.reconstruct(self.reconstructor)
        self.result = result
        image = np.where(np.isfinite(result.image), result.image, 0.0)
        error = np.where(np.isfinite(result.error), result.error, 0.0)
        t_write = time.perf_counter()
        passes = buffers_to_passes(run.buffers, image, error)
        passes["NextIndex"] = run.next_index.astype(np.float64)
        ex = self.executor
        if ex.domain != (0, 0, ex.full_w, ex.full_h) and not ex.user_crop:
            passes = {k: ((pad_to_frame(v[0], ex.domain, (ex.full_w, ex.full_h)), v[1])
                          if isinstance(v, tuple) else pad_to_frame(v, ex.domain, (ex.full_w, ex.full_h)))
                      for k, v in passes.items()}
        import bpy
        attrs = {"cycles_adaptive/version": OUTPUT_VERSION,
                 "cycles_adaptive/method": self.options.method,
                 "cycles_adaptive/options": json.dumps(_jsonable(vars(self.options))),
                 "cycles_adaptive/blender": bpy.app.version_string,
                 "cycles_adaptive/partial": str(bool(partial)).lower()}
        imageio.write_layers(self.out, passes, layer=self.view_layer.name, attributes=attrs)
        if self.preview:
            self.ex.write_preview(self.scene, passes["Combined"] if not isinstance(passes["Combined"], tuple)
                                  else passes["Combined"][0], preview_path(self.out))
        run.timing.overhead += time.perf_counter() - t_write
        if not partial and not self.keep_checkpoint and os.path.exists(self.ckpt):
            os.unlink(self.ckpt)
        h, w = run.height, run.width
        summary = {
            "method": self.options.method,
            "width": w, "height": h,
            "frame": self.options.frame,
            "spp_target": self.options.spp,
            "spp_mean": run.samples_rendered / run.pixels,
            "samples": run.samples_rendered,
            "budget_samples": run.budget,
            "iterations": run.iteration,
            "regions": run.tasks_rendered,
            "overshoot_samples": run.overshoot,
            "render_seconds": run.timing.render,
            "adapt_seconds": run.timing.adapt,
            "reconstruct_seconds": run.timing.reconstruct,
            "total_seconds": time.perf_counter() - self.t0,
            "peak_rss_mb": peak_rss_mb(),
            "out": self.out,
            "preview": preview_path(self.out) if self.preview else None,
            "partial": bool(partial),
            "reused_samples": int(run.reused.sum()),
            "reprojected_fraction": float((run.reused > 0).mean()),
            "blender": bpy.app.version_string,
        }
        for k, v in result.info.items():
            if isinstance(v, (int, float, str, bool)):
                summary[k] = v
        for k, v in run.prior_info.items():
            if isinstance(v, (int, float, str, bool)):
                summary[f"reproject_{k}"] = v
        if self.reference is not None:
            summary.update(metrics.summary(image, error, self.reference))
        self.summary = summary
        return summary


def bpy_path(path: str) -> str:
    """Expand Blender's ``//`` (relative to the .blend) when bpy is loaded."""
    if path.startswith("//"):
        import bpy
        return bpy.path.abspath(path)
    return path


def _jsonable(d):
    return json.loads(json.dumps(d, default=lambda o: list(o) if isinstance(o, tuple) else str(o)))


def frame_path(pattern: str, frame: int) -> str:
    """Output path of one frame: a run of '#' in ``pattern`` becomes the
    zero-padded frame number (Blender's convention); without '#', ``_####`` is
    inserted before the extension."""
    import re
    m = list(re.finditer(r"#+", pattern))
    if m:
        last = m[-1]
        return pattern[:last.start()] + str(frame).zfill(len(last.group())) + pattern[last.end():]
    stem, ext = os.path.splitext(pattern)
    return f"{stem}_{frame:04d}{ext or '.exr'}"


def parse_frames(text: str, scene) -> list:
    """'A-B' or 'A' (or 'A-B:STEP') -> frame list, inside the scene's range."""
    try:
        body, _, step = text.partition(":")
        a, _, b = body.partition("-")
        a, b = int(a), int(b or a)
        step = int(step or 1)
    except ValueError:
        raise JobError(f"--frames {text!r}: expected A-B, A or A-B:STEP") from None
    if b < a or step < 1:
        raise JobError(f"--frames {text!r}: empty range")
    lo, hi = scene.frame_start, scene.frame_end
    if a < lo or b > hi:
        raise JobError(f"--frames {a}-{b} is outside the scene's frame range {lo}-{hi}")
    return list(range(a, b + 1, step))


class FramesJob:
    """Adaptive render of a frame range, one RenderJob per frame.

    Each frame gets the seed ``options.seed + frame`` (like Cycles' animated
    seed), so samples reused from the previous frame are independent of the new
    frame's.  ``temporal``:
    - ``"none"``: frames are independent;
    - ``"reproject"``: after each frame's initial pass, the previous frame's
      accumulated samples are forward-reprojected into it where valid (Schalk
      2018 Sec. 3.2-3.3, core/reproject.py) and merged; reused samples do not
      count against the frame's budget; with ``var`` the sampler is Algorithm
      2's (``core.var.REPROJECT``: not-reprojected pixels first);
    - ``"lp"``: LP's temporal extension (Moon 2015 Sec. 6, core/temporal.py):
      per-pixel lambda-weighted RLS over frames on top of each frame's LP
      reconstruction (method must be ``lp``).
    """

    MODES = ("none", "reproject", "lp")

    def __init__(self, scene, view_layer, options: Options, out_pattern: str, frames: list,
                 reference_pattern: str | None = None, temporal: str = "none",
                 reproject_params: dict | None = None, temporal_params: dict | None = None, **job_kw):
        if temporal not in self.MODES:
            raise JobError(f"unknown temporal mode {temporal!r} (choose {', '.join(self.MODES)})")
        if temporal == "lp" and options.method != "lp":
            raise JobError("--temporal lp needs --method lp")
        self.scene, self.view_layer = scene, view_layer
        self.options, self.frames = options, list(frames)
        self.out_pattern, self.reference_pattern = out_pattern, reference_pattern
        self.temporal, self.job_kw = temporal, job_kw
        from ..core import reproject, temporal as temporal_mod
        from ..core.method import params_from_dict
        self.reproject_params = params_from_dict(reproject.Params, reproject_params)
        self.temporal_params = params_from_dict(temporal_mod.Params, temporal_params)
        self.summaries: list = []
        self.job: RenderJob | None = None
        self._prev = None  # (buffers, camera dict, method state) of the previous frame
        self._temporal_state = None
        for f in self.frames:  # refuse up front, before any frame is rendered
            out = frame_path(out_pattern, f)
            try:
                imageio.check_writable(out, job_kw.get("overwrite", False) or job_kw.get("resume", False))
            except imageio.ImageFileError as exc:
                raise JobError(str(exc)) from None

    def steps(self):
        import dataclasses
        for i, f in enumerate(self.frames):
            opts = dataclasses.replace(self.options, frame=f, seed=self.options.seed + f)
            if self.temporal != "none":
                opts.features = tuple(dict.fromkeys(tuple(opts.features) + REPROJECT_PASSES))
            ref = frame_path(self.reference_pattern, f) if self.reference_pattern else None
            kw = dict(self.job_kw)
            if self.temporal == "reproject":
                kw["prior"] = self._reproject_prior
                if self.options.method == "var" and self._prev is not None:
                    from ..core import var
                    kw["method"] = var.REPROJECT
            elif self.temporal == "lp":
                kw["reconstructor"] = self._lp_temporal
            self.job = RenderJob(self.scene, self.view_layer, opts, frame_path(self.out_pattern, f),
                                 reference=ref, **kw)
            for p in self.job.steps():
                p.message = f"frame {f} ({i + 1}/{len(self.frames)}): {p.message}"
                p.fraction = (i + p.fraction) / len(self.frames)
                yield p
            summary = self.job.finish()
            self.summaries.append(summary)
            self._prev = (self.job.run.buffers, self.job.camera, self.job.run.method_state)
            yield summary

    def _reproject_prior(self, buffers):
        """The previous frame's samples forward-reprojected into this frame
        (``core/reproject.py``), with Algorithm 2's carried probabilities for
        var, as the run's :class:`core.pipeline.Prior`."""
        from ..core import reproject
        from ..core.pipeline import Prior
        if self._prev is None:
            return None
        prev_buf, prev_cam, prev_state = self._prev
        extra = None
        if self.options.method == "var":
            prob = prev_state.get("prob")
            if prob is None or np.shape(prob) != prev_buf.shape:
                prob = np.full(prev_buf.shape, np.nan)
            extra = {"probability": np.asarray(prob, np.float64)}
        camera = reproject.Camera.from_render
        res = reproject.reproject(prev_buf, camera(prev_cam), buffers, camera(self.job.camera),
                                  params=self.reproject_params, extra=extra)
        info = {"fraction": res.fraction}
        info.update({k: v for k, v in res.counts.items() if isinstance(v, (int, float))})
        state = {"probability": res.extra["probability"]} if self.options.method == "var" else {}
        return Prior(res.buffers, state, info)

    def _lp_temporal(self, run):
        """Final reconstruction of a frame with LP's temporal extension."""
        from ..core import reproject, temporal
        static = run.method.reconstruct(run.buffers, run.params)
        center = None
        if self._prev is not None:
            prev_buf, prev_cam, _ = self._prev
            center = reproject.backward_coordinates(reproject.Camera.from_render(prev_cam),
                                                    reproject.Camera.from_render(self.job.camera),
                                                    run.buffers, prev_buf.shape)
        res = temporal.step(self._temporal_state, run.buffers, self.temporal_params,
                            frame=self.job.options.frame, static=static, center=center)
        self._temporal_state = res.state
        out = res.method_result()
        out.info.update({f"temporal_{k}": v for k, v in res.info.items() if isinstance(v, (int, float))})
        if "center_fraction" in static.info:
            out.info["center_fraction"] = static.info["center_fraction"]
        return out

    @property
    def run(self):
        """The run of the frame in progress (for the operator's stepper)."""
        return None if self.job is None else self.job.run

    def finish(self, partial: bool = False) -> dict:
        """After the last frame: the range summary.  On a cancel: write the
        frame in progress as a partial result, then the summary."""
        if partial and self.job is not None and self.job.run is not None and \
                (not self.summaries or self.summaries[-1]["out"] != self.job.out):
            self.summaries.append(self.job.finish(partial=True))
        summ = self.summary()
        summ["out"] = summ["outs"][-1] if summ["outs"] else ""
        return summ

    def summary(self) -> dict:
        s = self.summaries
        out = {"frames": len(s), "method": self.options.method, "temporal": self.temporal,
               "total_seconds": sum(x["total_seconds"] for x in s),
               "render_seconds": sum(x["render_seconds"] for x in s),
               "spp_mean": float(np.mean([x["spp_mean"] for x in s])) if s else 0.0,
               "reprojected_fraction": float(np.mean([x.get("reprojected_fraction", 0.0) for x in s]))
               if s else 0.0, "outs": [x["out"] for x in s]}
        if s and all("relmse" in x for x in s):
            out["relmse_mean"] = float(np.mean([x["relmse"] for x in s]))
        return out


#: passes the reprojection needs (world position, specular share, object ids)
REPROJECT_PASSES = ("position", "glossy", "transmission", "object_index", "normal", "depth")

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
import resource
import time

import numpy as np

from ..core import io as imageio
from ..core import metrics
from ..core.buffers import Buffers, Stat
from ..core.pipeline import AdaptiveRun, Options

OUTPUT_VERSION = "1"


class JobError(Exception):
    """Bad input for a job; the message is for the user, one line."""


def checkpoint_path(out: str) -> str:
    return out + ".checkpoint.npz"


def preview_path(out: str) -> str:
    return os.path.splitext(out)[0] + ".png"


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def buffers_to_passes(buf: Buffers, image, error) -> dict:
    """The output EXR passes of an accumulated buffer and a result."""
    var = buf.variance_of_mean()
    alpha = buf.features["alpha"].mean if "alpha" in buf.features else np.ones(buf.shape + (1,))
    combined = np.concatenate([image, alpha], axis=-1)
    passes = {
        "Combined": combined,
        "Noisy": buf.color.mean,
        "Variance": np.where(np.isfinite(var), var, 0.0),
        "M2": buf.color.m2,
        "Samples": buf.n,
        "Groups": buf.k,
        "Error": error,
    }
    for name, st in buf.features.items():
        passes[f"Feat_{name}"] = (st.mean, _letters(st.mean.shape[2]))
        passes[f"Feat_{name}_M2"] = (st.m2, _letters(st.m2.shape[2]))
    return passes


def _letters(c):
    return imageio.VECTOR_LETTERS.get(c) if c in (3, 4) else None


def buffers_from_passes(passes: dict, path: str) -> Buffers:
    """Rebuild Buffers from one of our output EXRs, or from a plain Blender
    multilayer render (Combined + Denoising passes; then no variance is known:
    one group, k = 1)."""
    if "Noisy" in passes and "Samples" in passes:
        shape = passes["Noisy"].shape[:2]
        for name, arr in passes.items():
            if arr.shape[:2] != shape:
                raise JobError(f"{path}: pass {name} is {arr.shape[1]}x{arr.shape[0]}, "
                               f"Noisy is {shape[1]}x{shape[0]}")
        need = ("M2", "Groups")
        miss = [n for n in need if n not in passes]
        if miss:
            raise JobError(f"{path}: missing pass {miss[0]} (not a complete cycles-adaptive output)")
        b = Buffers(passes["Samples"][:, :, 0].astype(np.float64),
                    passes["Groups"][:, :, 0].astype(np.float64),
                    Stat(passes["Noisy"][:, :, :3].astype(np.float64),
                         passes["M2"][:, :, :3].astype(np.float64)))
        for name in passes:
            if name.startswith("Feat_") and not name.endswith("_M2"):
                fname = name[len("Feat_"):]
                m2 = passes.get(name + "_M2", np.zeros_like(passes[name]))
                b.features[fname] = Stat(passes[name].astype(np.float64), m2.astype(np.float64))
        return b
    if "Combined" not in passes:
        raise JobError(f"{path}: no Combined or Noisy layer (passes: {', '.join(sorted(passes)) or 'none'})")
    rgba = passes["Combined"]
    h, w = rgba.shape[:2]
    sources = {"albedo": "Denoising Albedo", "normal": "Denoising Normal",
               "depth": "Denoising Depth", "position": "Position"}
    b = Buffers(np.ones((h, w)), np.ones((h, w)),
                Stat(rgba[:, :, :3].astype(np.float64), np.zeros((h, w, 3))))
    for fname, pname in sources.items():
        if pname in passes:
            arr = passes[pname].astype(np.float64)
            if arr.shape[:2] != (h, w):
                raise JobError(f"{path}: pass {pname} is {arr.shape[1]}x{arr.shape[0]}, "
                               f"Combined is {w}x{h}")
            b.features[fname] = Stat(arr, np.zeros_like(arr))
    if rgba.shape[2] >= 4:
        b.features["alpha"] = Stat(rgba[:, :, 3:4].astype(np.float64), np.zeros((h, w, 1)))
    return b


def load_reference(path: str | None, shape) -> np.ndarray | None:
    if not path:
        return None
    try:
        ref = imageio.read_rgb(path)
    except imageio.ImageFileError as exc:
        raise JobError(str(exc)) from None
    if ref.shape[:2] != tuple(shape):
        raise JobError(f"reference {path} is {ref.shape[1]}x{ref.shape[0]}, the render is "
                       f"{shape[1]}x{shape[0]}")
    return ref


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
                 keep_checkpoint: bool = False):
        from ..addon import executor as ex
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
        self.t0 = time.perf_counter()
        self.summary: dict | None = None

    def steps(self):
        from ..core import methods
        method = methods.get(self.options.method)
        self.executor = self.ex.CyclesExecutor(self.scene, self.view_layer,
                                               tuple(method.PASSES) + tuple(self.options.features),
                                               seed=self.options.seed)
        self.reference = load_reference(self.reference_path, self.executor.size)
        with self.executor:
            self.run = AdaptiveRun(self.executor, self.options, checkpoint=self.ckpt)
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
        result = run.reconstruct()
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
            "blender": bpy.app.version_string,
        }
        for k, v in result.info.items():
            if isinstance(v, (int, float, str, bool)):
                summary[k] = v
        if self.reference is not None:
            summary["relmse"] = metrics.relmse(image, self.reference)
            summary["smape"] = metrics.smape(image, self.reference)
            summary["error_correlation"] = metrics.error_correlation(error, image, self.reference)
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

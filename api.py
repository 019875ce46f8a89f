"""Python API for render regression tests under bpy: render, denoise, compare.

For a process that already has ``bpy`` (the PyPI module or Blender's own
Python).  Import it as

* installed extension: ``from bl_ext.<repo>.cycles_adaptive import api``
  (``<repo>`` is the module name of the extension repository it was installed
  into, ``user_default`` for the default user repository);
* repository checkout: ``from cycles_adaptive import api`` with the checkout's
  folder named ``cycles_adaptive`` and its parent on ``sys.path`` (or after
  ``launch.load_package()``).

``render`` runs the very job the CLI and the panel run (``operators/job.py``:
:class:`operators.job.RenderJob`, options built by
:func:`operators.job.make_options`), but writes nothing: :class:`Result`
holds the arrays of the EXR passes and the summary; :meth:`Result.save`
writes the same multilayer EXR as ``./cycles-adaptive render``.  ``compare``
checks a result against a reference the way Blender's own render tests do
(``idiff`` thresholds, through OpenImageIO's ``ImageBufAlgo.compare``) or with
our relMSE, and says from the render's estimated error map which differences
lie within its own noise.  Bad input raises :class:`Error` (one line naming
the problem) before anything is written.  See docs/regression-tests.md.
"""
from __future__ import annotations

import contextlib
import os
import sys

import numpy as np

from .core import io as imageio
from .core import metrics
from .core.pipeline import Options
from .core.storage import StorageError

__all__ = ["DEFAULT_METHOD", "Error", "Result", "Comparison", "render", "open_blend", "denoise", "compare",
           "write_png", "diff_picture"]

#: the method ``render`` uses by default: the loop's own default (``Options``),
#: ``auto`` (chooses the reconstruction and sampling per scene, core/auto.py).
DEFAULT_METHOD = Options().method

#: channel names of the image a Result (or one of our EXRs) is compared by
RGBA = ("R", "G", "B", "A")


class Error(Exception):
    """Bad input to the API: the message names the problem in one line."""


@contextlib.contextmanager
def _as_error():
    """Our input errors (job, scene, file, range) re-raised as :class:`Error`
    with the same message; anything else (a bug, Ctrl-C) passes through."""
    from .operators.job import JobError
    try:
        yield
    except Error:
        raise
    except (JobError, imageio.ImageFileError, StorageError, ValueError, FileNotFoundError) as exc:
        raise Error(str(exc)) from None
    except Exception as exc:
        if type(exc).__name__ == "SceneError":  # addon.executor (bpy only)
            raise Error(str(exc)) from None
        raise


def _quiet():
    """Blender's and Cycles' log lines ("Read blend", "Fra: ... Sample 3/4")
    kept off stdout while a file opens and a render runs, also under pytest's
    capture (``addon.executor.quiet_stdout``)."""
    from .addon.executor import quiet_stdout
    return quiet_stdout()


# ================================================================= result
def _array(passes: dict, name: str) -> np.ndarray:
    """Pass ``name`` as the float32 array the EXR holds (read only)."""
    v = passes[name]
    arr = np.asarray(v[0] if isinstance(v, tuple) else v, np.float32)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    arr.setflags(write=False)
    return arr


class Result:
    """What a render (or a denoise) produced, nothing written yet.

    Arrays are float32, exactly the values :meth:`save` writes (full frame,
    rows top to bottom): ``image`` (H, W, 3) the result, ``alpha`` (H, W),
    ``noisy`` (H, W, 3) the sample mean, ``variance`` (H, W, 3) of the mean
    (0 where unknown), ``samples`` (H, W) samples per pixel, ``groups`` (H, W)
    sample subsets merged, ``error`` (H, W) the method's estimated squared
    error of ``image`` (averaged over RGB), ``features`` name -> (H, W, C)
    feature pass means (albedo, normal, depth, ...).  ``summary`` has the
    fields of the CLI's JSON line (``out`` is None until saved); ``passes``
    all EXR passes by name.
    """

    def __init__(self, output, scene=None):
        self._output = output
        self._scene = scene
        p = self.passes = {k: _array(output.passes, k) for k in output.passes}
        self.image, self.alpha = p["Combined"][:, :, :3], p["Combined"][:, :, 3]
        self.noisy, self.variance, self.error = p["Noisy"], p["Variance"], p["Error"]
        self.samples, self.groups = p["Samples"], p["Groups"]
        self.features = {k[len("Feat_"):]: v for k, v in p.items()
                         if k.startswith("Feat_") and not k.endswith("_M2") and k != "Feat_alpha"}
        self.summary = dict(output.summary)

    @property
    def rgba(self) -> np.ndarray:
        """(H, W, 4) float32: ``image`` and ``alpha`` (the Combined pass)."""
        return self.passes["Combined"]

    @property
    def shape(self) -> tuple:
        """(H, W) in pixels."""
        return self.image.shape[:2]

    def __repr__(self):
        h, w = self.shape
        return f"<cycles_adaptive.api.Result {self.summary.get('method')} {w}x{h}>"

    def save(self, path: str, overwrite: bool = False, preview: bool = False) -> str:
        """Write the multilayer EXR the CLI writes (same passes and
        attributes), atomically; ``preview``: also ``PATH.png`` in the scene's
        view transform, as the CLI does.  An existing file is replaced only
        with ``overwrite``.  Returns the absolute path; ``summary['out']``
        (and ``['preview']``) then name it."""
        from .operators.job import preview_path, write_output
        path = os.path.abspath(os.fspath(path))
        targets = [path] + ([preview_path(path)] if preview else [])
        for t in targets:
            _check_writable(t, overwrite)
        with _as_error():
            write_output(self._output, path)
        self.summary["out"] = path
        if preview:
            self.save_preview(targets[1], overwrite=overwrite)
            self.summary["preview"] = targets[1]
        return path

    def save_preview(self, path: str, overwrite: bool = False) -> str:
        """Write ``rgba`` as an 8-bit PNG (:func:`write_png`) in the view
        transform of the scene it was rendered from, or of the active scene
        when that one is gone (another file was opened) or for a denoise."""
        return write_png(self.rgba, path, scene=self.scene, overwrite=overwrite)

    @property
    def scene(self):
        """The scene it was rendered from, None for a denoise or once another
        file replaced it."""
        try:
            if self._scene is not None:
                self._scene.name  # noqa: B018  (ReferenceError once removed)
                return self._scene
        except ReferenceError:
            pass
        return None


def write_png(rgba, path: str, scene=None, overwrite: bool = False) -> str:
    """Save (H, W, 3|4) scene-linear pixels as an 8-bit PNG through Blender's
    colour management: the view transform, look and exposure of ``scene``
    (default the active scene), as the CLI's preview; atomically, never over
    an existing file unless ``overwrite``.  Returns the absolute path."""
    import bpy
    from .addon.executor import write_preview
    path = os.path.abspath(os.fspath(path))
    _check_writable(path, overwrite)
    scene = scene if scene is not None else bpy.context.scene
    if scene is None:
        raise Error("no scene to take the PNG's view transform from")
    rgba = np.asarray(rgba)
    if rgba.ndim != 3 or rgba.shape[2] not in (3, 4):
        raise Error(f"expected (H, W, 3) or (H, W, 4) pixels, got shape {rgba.shape}")
    write_preview(scene, rgba, path)
    return path


def _check_writable(path: str, overwrite: bool) -> None:
    if os.path.exists(path) and not overwrite:
        raise Error(f"{path} exists; pass overwrite=True to replace it")
    with _as_error():
        imageio.check_writable(path, overwrite)


# ================================================================= render
def render(scene_or_path=None, method: str = DEFAULT_METHOD, spp: float = 16, frame: int | None = None,
           view_layer=None, seed: int = 0, resolution_percentage: int | None = None, **params) -> Result:
    """Adaptive render of one frame; the CLI's ``render`` without the files.

    Parameters
    ----------
    scene_or_path : a ``bpy.types.Scene``, the path of a .blend file, or None
        (the active scene).  A path is opened with ``wm.open_mainfile``: that
        **replaces the file open in this process** (unsaved changes in memory
        are gone; nothing is ever saved to any .blend) and renders its active
        scene.
    method : ``auto``, ``uniform``, ``var``, ``awr``, ``lp``, ``rhf`` or
        ``oidn``; default the loop's default (:data:`DEFAULT_METHOD`,
        ``auto``: the candidate it predicts fastest at equal error).
    spp : mean samples per pixel of the whole run (initial pass included).
    frame : frame to render (default: the scene's current frame).
    view_layer : a view layer or its name (default: the active one).
    seed : Cycles seed; the same arguments and seed give identical arrays.
    resolution_percentage : override of the scene's resolution percentage for
        this render only.
    **params : loop settings (``initial_spp``, ``subsets``, ``iterations``,
        ``task_cost``, ``guard_z``, ...: ``Options``) and the method's
        parameters (its ``Params``; ``<method>_<name>`` where a name is both,
        e.g. ``rhf_iterations``), as the CLI's flags.  Unknown names raise
        :class:`Error`.

    Every scene setting the render touches is restored afterwards (also after
    an error or Ctrl-C); no window is opened.  Error (nothing rendered) for a
    scene that is not Cycles, has no camera, or bad arguments.
    """
    import bpy
    from .addon.executor import SettingsGuard
    from .operators import job as jobs
    with _as_error():
        scene = _scene(scene_or_path)
        vl = view_layer if isinstance(view_layer, bpy.types.ViewLayer) else \
            jobs.resolve_view_layer(scene, view_layer)
        if vl.id_data != scene:
            raise Error(f"view layer {vl.name!r} is not in scene {scene.name!r}")
        settings, mparams = jobs.split_keywords(method, dict(params, spp=spp, seed=seed))
        opts = jobs.make_options(method, scene.frame_current if frame is None else frame, settings, mparams)
        guard = SettingsGuard()
        try:
            if resolution_percentage is not None:
                guard.set(scene.render, "resolution_percentage",
                          jobs.check_resolution_percentage(resolution_percentage))
            job = jobs.RenderJob(scene, vl, opts, None)
            with _quiet():
                for _ in job.steps():
                    pass
            output = job.output()
        finally:
            guard.restore()
    return Result(output, scene)


def open_blend(path) -> "bpy.types.Scene":
    """Open the .blend at ``path`` in this process and return its active
    scene (to change it in memory before :func:`render`).  This replaces the
    open file (unsaved changes in memory are gone); nothing is saved."""
    import bpy
    from .operators.job import open_blend as open_file
    with _as_error(), _quiet():
        open_file(os.fspath(path))
    return bpy.context.scene


def _scene(scene_or_path):
    import bpy
    if scene_or_path is None:
        if bpy.context.scene is None:
            raise Error("no active scene; pass a scene or a .blend path")
        return bpy.context.scene
    if isinstance(scene_or_path, bpy.types.Scene):
        return scene_or_path
    if isinstance(scene_or_path, (str, os.PathLike)):
        return open_blend(scene_or_path)
    raise Error(f"expected a bpy Scene or a .blend path, got {type(scene_or_path).__name__}")


# ================================================================ denoise
def denoise(exr_path, method: str = "lp", guard_z: float | None = None, **params) -> Result:
    """Re-run ``method`` (``awr``, ``lp``, ``rhf``) on the passes stored in
    ``exr_path`` (an EXR written by ``render``/:meth:`Result.save`, or a
    Blender multilayer render with Combined and Denoising passes): the CLI's
    ``denoise`` without the file.  ``params``: the method's parameters;
    ``guard_z``: the consistency guard (default the loop's).  Error for a bad
    file, a method whose passes it lacks, or unknown parameters."""
    from .core import methods
    from .operators.job import denoise_output
    if method not in methods.DENOISERS:
        raise Error(f"denoise method {method!r} is not one of {', '.join(methods.DENOISERS)}")
    with _as_error():
        return Result(denoise_output(os.fspath(exr_path), method, params, guard_z))


# ================================================================ compare
class Comparison:
    """The outcome of :func:`compare`.

    passed : bool, False when more than ``failpercent`` % of the pixels fail.
    status : ``"pass"``, ``"warn"`` (more than ``warnpercent`` % over
        ``warn``; passes, as in Blender's tests) or ``"fail"``.
    figures : dict of plain numbers: ``fail_pixels``, ``fail_percent``,
        ``warn_pixels``, ``warn_percent``, the metric's own (relmse: ``relmse``,
        ``smape``, ``max_error`` and where; idiff: ``mean_error``,
        ``rms_error``, ``psnr``, ``max_error``, ``max_x``, ``max_y``,
        ``max_channel``) and, with an error map, ``outside_noise_pixels``,
        ``outside_noise_percent``, ``z_max``, ``z_median``, ``z_threshold``
        (median over pixels of the threshold applied).
    diff : (H, W, C) float32 difference image (idiff: ``|render - reference|``
        per channel; relmse: ``|render - reference| / sqrt(reference^2 + 0.01)``
        per RGB channel, whose mean square is relMSE).
    failing : (H, W) bool, the pixels counted as failing.
    z : (H, W) float64 or None, ``sqrt(mean_rgb (x - r)^2 / (E_x + E_r))`` with
        the estimated squared errors of render and reference (a reference
        without an Error pass counts as exact); about 1 where a difference is
        the renders' noise.
    outside_noise : (H, W) bool or None, ``z`` over the noise threshold.
    """

    def __init__(self, metric, status, figures, diff, failing, z, outside_noise, render_name, reference_path,
                 limits):
        self.metric, self.status, self.figures = metric, status, figures
        self.diff, self.failing, self.z, self.outside_noise = diff, failing, z, outside_noise
        self.render_name, self.reference_path, self.limits = render_name, reference_path, limits

    @property
    def passed(self) -> bool:
        return self.status != "fail"

    def report(self) -> str:
        """A few readable lines: verdict, figures, noise."""
        f, lim = self.figures, self.limits
        h, w = self.failing.shape
        what = "a relative difference" if self.metric == "relmse" else "an absolute difference in a channel"
        lines = [f"{self.status.upper()}: {f['fail_percent']:.2f}% of {w}x{h} pixels ({f['fail_pixels']}) have "
                 f"{what} over {lim['fail']:g}; allowed {lim['failpercent']:g}%"
                 + (" (pixels within the render's noise not counted)" if lim.get("ignore_noise") else ""),
                 f"  render:    {self.render_name}", f"  reference: {self.reference_path}"]
        if self.metric == "relmse":
            x, y = f["max_at"]
            lines.append(f"  relMSE {f['relmse']:.4g}, SMAPE {f['smape']:.4g}; worst pixel ({x}, {y}) "
                         f"{f['max_error']:.4g}")
        else:
            lines.append(f"  mean error {f['mean_error']:.4g}, RMS {f['rms_error']:.4g}, PSNR {f['psnr']:.4g} dB; "
                         f"max {f['max_error']:.4g} at ({f['max_x']}, {f['max_y']}, {f['max_channel']})")
        if lim.get("warn") is not None:
            lines.append(f"  {f['warn_percent']:.2f}% over the warning level {lim['warn']:g} "
                         f"(allowed {lim['warnpercent']:g}%)")
        if self.z is not None:
            lines.append(f"  {f['outside_noise_percent']:.2f}% of pixels differ by more than the renders' own "
                         f"noise (z over {f['z_threshold']:.3g}, the t value of z={lim['z']:g}); "
                         f"z max {f['z_max']:.3g}, median {f['z_median']:.3g}")
        else:
            lines.append("  no error map: cannot tell noise from change")
        return "\n".join(lines)

    __str__ = report

    def __repr__(self):
        return f"<cycles_adaptive.api.Comparison {self.metric} {self.status} {self.figures['fail_percent']:.2f}%>"

    def write_diff(self, path: str, overwrite: bool = False, scale: float = 16.0) -> str:
        """Write the diff image atomically: ``.exr``: float passes ``Diff``,
        ``Failing`` (0/1) and ``Z`` (when known); any other extension (PNG):
        :func:`diff_picture` (grey ``min(1, scale * max channel of diff)``,
        failing pixels red, yellow where within the noise; ``scale`` 16 as
        Blender's test reports)."""
        path = os.path.abspath(os.fspath(path))
        _check_writable(path, overwrite)
        if path.lower().endswith(".exr"):
            passes = {"Diff": self.diff, "Failing": self.failing.astype(np.float32)}
            if self.z is not None:
                passes["Z"] = np.where(np.isfinite(self.z), self.z, 1e30)
                passes["OutsideNoise"] = self.outside_noise.astype(np.float32)
            with _as_error():
                imageio.write_layers(path, passes, layer="")
            return path
        with _as_error():
            outside = None if self.z is None else self.outside_noise
            _write_png8(path, diff_picture(self.diff, self.failing, outside, scale))
        return path


def diff_picture(diff: np.ndarray, failing: np.ndarray, outside: np.ndarray | None = None,
                 scale: float = 16.0) -> np.ndarray:
    """(H, W, 3) float in [0, 1] for a diff PNG: grey ``min(1, scale * max
    channel)``; failing pixels red, or yellow where the difference is within
    the renders' noise (``outside`` False), so a changed object stands out
    from a changed noise pattern."""
    grey = np.clip(scale * np.max(np.abs(diff[..., :3]), axis=-1), 0.0, 1.0)
    pic = np.repeat(grey[..., None], 3, axis=-1)
    real = failing if outside is None else failing & outside
    pic[failing & ~real] = (0.55, 0.45, 0.0)
    pic[real] = (1.0, 0.0, 0.0)
    return pic


def _write_png8(path: str, rgb: np.ndarray) -> None:
    """8-bit PNG of values in [0, 1] as they are (no colour transform), atomically."""
    import OpenImageIO as oiio
    data = np.ascontiguousarray(np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8))
    with imageio.atomic_path(path, ".png") as tmp:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, oiio.ImageSpec(data.shape[1], data.shape[0], data.shape[2],
                                                           "uint8")):
            raise imageio.ImageFileError(f"{path}: cannot write a PNG")
        ok = out.write_image(data)
        out.close()
        if not ok:
            raise imageio.ImageFileError(f"{path}: PNG write failed")


def compare(result_or_path, reference_path, fail: float = 0.016, failpercent: float = 1.0,
            warn: float | None = None, warnpercent: float = 0.0, metric: str = "relmse", z: float = 3.0,
            ignore_noise: bool = False, diff_path: str | None = None, overwrite: bool = False) -> Comparison:
    """Compare a render with an approved reference, as a regression test.

    A pixel *fails* when its difference exceeds ``fail``; the comparison
    fails when more than ``failpercent`` % of the pixels fail (``idiff``'s
    rule; Blender's render tests run ``idiff -fail 0.016 -failpercent 1``).
    ``metric``:

    * ``"idiff"``: the difference is the largest absolute difference of a
      channel (R, G, B and A, scene-linear values), counted by OpenImageIO's
      ``ImageBufAlgo.compare(A, B, failthresh, warnthresh)``, which also gives
      the mean, RMS, PSNR and maximum error;
    * ``"relmse"``: the difference is the pixel's relative difference
      ``sqrt(mean_rgb (x - r)^2 / (r^2 + 0.01))``, the root of the term our
      relMSE averages (``core.metrics``): dark and bright regions weigh alike.

    With an error map (every Result; an EXR of ours has an ``Error`` pass),
    each pixel gets a z-score ``sqrt(mean_rgb (x - r)^2 / (E_x + E_r))``: the
    difference in units of the two renders' own estimated noise (E: squared
    error estimates; a reference without one counts as exact).  Since E comes
    from k sample subsets, a pixel differs by more than noise when its z
    exceeds the Student-t value with the two-sided tail of a normal ``z`` at
    k - 1 degrees of freedom (``core.method.t_quantile``: 9.2 for z = 3 and
    4 subsets).  ``ignore_noise`` (relmse only) does not count failing pixels
    within the noise: a new noise pattern (another seed, sampler or Blender
    version) then passes while a changed object still fails; with the same
    seed leave it off, the comparison is then exact.

    ``warn`` / ``warnpercent``: the same for a warning (status ``"warn"``,
    still passed).  ``diff_path``: write the diff image there
    (:meth:`Comparison.write_diff`; refused if it exists unless
    ``overwrite``).  Error, with nothing written, for a missing or unreadable
    reference, one of another size or channel set, or with NaN / Inf.
    """
    if metric not in ("relmse", "idiff"):
        raise Error(f"metric {metric!r}: choose 'relmse' or 'idiff'")
    for name, v in (("fail", fail), ("failpercent", failpercent), ("warnpercent", warnpercent), ("z", z),
                    ("warn", 0.0 if warn is None else warn)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
            raise Error(f"{name}={v!r} must be a finite number >= 0")
    if failpercent > 100 or warnpercent > 100:
        raise Error("failpercent and warnpercent are percentages (0-100)")
    if ignore_noise and metric != "relmse":
        raise Error("ignore_noise needs metric='relmse' (idiff counts every pixel over the threshold)")
    img, channels, err, name = _image_of(result_or_path)
    ref, ref_err, ref_half = _reference(reference_path, img.shape[:2], channels)
    if ref_half and isinstance(result_or_path, Result):
        img = imageio.as_half(img)  # compared as the reference's file stores it
    if ignore_noise and err is None:
        raise Error(f"{name} has no error map (Error pass): cannot tell noise from change")
    if diff_path is not None:
        _check_writable(os.path.abspath(os.fspath(diff_path)), overwrite)
    zmap = _zscore(img, ref, err, ref_err) if err is not None else None
    zthr = None if zmap is None else _noise_threshold(z, err, ref_err)
    outside = None if zmap is None else zmap > zthr
    if metric == "idiff":
        figures, diff, failing, warning = _idiff(img, ref, fail, fail if warn is None else warn, channels)
    else:
        figures, diff, failing, warning = _relmse(img, ref, fail, warn, outside if ignore_noise else None)
    npix = failing.size
    if warn is None:
        warning = np.zeros_like(failing)
    figures.setdefault("fail_pixels", int(failing.sum()))
    figures["warn_pixels"] = figures.get("warn_pixels", int(warning.sum())) if warn is not None else 0
    figures.update(fail_percent=100.0 * figures["fail_pixels"] / npix,
                   warn_percent=100.0 * figures["warn_pixels"] / npix)
    if zmap is not None:
        fin = zmap[np.isfinite(zmap)]
        figures.update(outside_noise_pixels=int(outside.sum()), outside_noise_percent=100.0 * outside.mean(),
                       z_max=float(zmap.max()), z_median=float(np.median(fin)) if fin.size else float("inf"),
                       z_threshold=float(np.median(zthr)))
    status = "fail" if figures["fail_pixels"] > failpercent / 100.0 * npix else \
        "warn" if warn is not None and figures["warn_pixels"] > warnpercent / 100.0 * npix else "pass"
    limits = {"fail": fail, "failpercent": failpercent, "warn": warn, "warnpercent": warnpercent, "z": z,
              "ignore_noise": ignore_noise}
    out = Comparison(metric, status, figures, diff, failing, zmap, outside, name,
                     os.path.abspath(os.fspath(reference_path)), limits)
    if diff_path is not None:
        out.write_diff(diff_path, overwrite=overwrite)
    return out


def _image_of(result_or_path):
    """(rgba float32, channel names, error map or None, name) of a Result or
    of an EXR (its Combined pass, else its plain channels)."""
    if isinstance(result_or_path, Result):
        r = result_or_path
        out = r.summary.get("out")
        name = out or f"render ({r.summary.get('method')}, not saved)"
        return np.asarray(r.rgba), RGBA, (np.asarray(r.error, np.float64), np.asarray(r.groups)), name
    if not isinstance(result_or_path, (str, os.PathLike)):
        raise Error(f"expected a Result or an EXR path, got {type(result_or_path).__name__}")
    path = os.path.abspath(os.fspath(result_or_path))
    img, channels, err, _ = _read_image(path, "render")
    if not np.isfinite(img).all() or err is not None and not np.isfinite(err[0]).all():
        raise Error(f"render {path} has NaN or Inf values")
    return img, channels, err, path


def _read_image(path: str, what: str):
    if not os.path.isfile(path):
        raise Error(f"{what} {path}: no such file")
    try:
        passes, meta = imageio.read_layers(path)
    except imageio.ImageFileError as exc:
        raise Error(f"{what} {exc}") from None
    key = "Combined" if "Combined" in passes else "" if "" in passes else None
    if key is None:
        raise Error(f"{what} {path} has no Combined pass and no plain R, G, B channels "
                    f"(passes: {', '.join(sorted(passes))})")
    channels = tuple(meta["channels"][key])
    err, groups = passes.get("Error"), passes.get("Groups")
    if err is not None:
        err = (np.asarray(err[:, :, 0], np.float64), None if groups is None else groups[:, :, 0])
    return passes[key], channels, err, key in meta.get("half", ())


def _reference(path, shape, channels):
    """(reference rgba, its error map or None, whether it is stored in half
    float), checked against the render."""
    if path is None:
        raise Error("no reference path given")
    path = os.path.abspath(os.fspath(path))
    ref, ref_channels, ref_err, ref_half = _read_image(path, "reference")
    if ref.shape[:2] != tuple(shape):
        raise Error(f"reference {path} is {ref.shape[1]}x{ref.shape[0]}, the render is {shape[1]}x{shape[0]}")
    if tuple(ref_channels) != tuple(channels):
        raise Error(f"reference {path} has channels {', '.join(ref_channels)}, the render "
                    f"{', '.join(channels)}")
    bad = ~np.isfinite(ref)
    if bad.any():
        y, x, c = (int(v[0]) for v in np.nonzero(bad))
        raise Error(f"reference {path} has {int(bad.sum())} NaN or Inf values (first at pixel ({x}, {y}), "
                    f"channel {ref_channels[c]})")
    if ref_err is not None and not np.isfinite(ref_err[0]).all():
        ref_err = None  # an unusable error map: treat the reference as exact
    return ref, ref_err, ref_half


def _zscore(img, ref, err, ref_err) -> np.ndarray:
    """Per pixel ``sqrt(mean_rgb (x - r)^2 / (E_x + E_r))``: the difference in
    units of the estimated noise of render and reference (``err`` /
    ``ref_err``: (squared error map, sample groups or None); a reference
    without one counts as exact).  Differences below 1e-5 of the pixel's and
    the image's level count as exact (float rounding, other CPUs), so a
    noise-free pixel gives 0 there, not infinity."""
    x, r = img[..., :3].astype(np.float64), ref[..., :3].astype(np.float64)
    d2 = ((x - r) ** 2).mean(axis=-1)
    level = np.abs(r).mean(axis=-1)
    var = np.maximum(err[0], 0.0) + (0.0 if ref_err is None else np.maximum(ref_err[0], 0.0))
    var = var + (1e-5 * (level + level.mean())) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.sqrt(d2 / var)
    return np.where(var > 0, z, np.where(d2 > 0, np.inf, 0.0))


def _noise_threshold(z: float, err, ref_err):
    """The z above which a pixel differs by more than noise: the Student-t
    value with the two-sided tail of a normal ``z`` for the pixel's ``k - 1``
    degrees of freedom (its variance comes from ``k`` sample groups;
    :func:`core.method.t_quantile`: about 9.2 for 3), the fewer of render's
    and reference's; ``z`` itself where the groups are unknown."""
    from .core.method import t_quantile
    groups = [g for g in (err[1], None if ref_err is None else ref_err[1]) if g is not None]
    if not groups:
        return z
    k = np.minimum.reduce([np.asarray(g, np.float64) for g in groups])
    return t_quantile(z, np.maximum(k - 1.0, 1.0))


def _relmse(img, ref, fail, warn, outside):
    """Per pixel the relative difference ``sqrt(mean_rgb (x - r)^2 / (r^2 +
    0.01))``, the root of the term relMSE averages (``core.metrics``), so
    ``fail`` is a relative difference as idiff's is an absolute one."""
    x = img[..., :3].astype(np.float64)
    r = ref[..., :3].astype(np.float64)
    per_pixel = np.sqrt(metrics.per_pixel_relmse(x, r))
    diff = (np.abs(x - r) / np.sqrt(r * r + metrics.REL_EPS)).astype(np.float32)
    failing = per_pixel > fail
    warning = per_pixel > warn if warn is not None else np.zeros_like(failing)
    if outside is not None:
        failing &= outside
        warning &= outside
    y, xx = np.unravel_index(int(np.argmax(per_pixel)), per_pixel.shape)
    figures = {"relmse": metrics.relmse(x, r), "smape": metrics.smape(x, r),
               "max_error": float(per_pixel.max()), "max_at": (int(xx), int(y))}
    return figures, diff, failing, warning


def _idiff(img, ref, fail, warn, channels):
    """idiff's numbers through OpenImageIO: ``ImageBufAlgo.compare`` counts
    the pixels with some channel over ``fail`` / ``warn``; ``absdiff`` gives
    the difference image."""
    import OpenImageIO as oiio
    a = oiio.ImageBuf(np.ascontiguousarray(img, np.float32))
    b = oiio.ImageBuf(np.ascontiguousarray(ref, np.float32))
    cr = oiio.ImageBufAlgo.compare(a, b, float(fail), float(warn))
    d = oiio.ImageBufAlgo.absdiff(a, b)
    if d.has_error:
        raise Error(f"OpenImageIO could not compare the images: {d.geterror()}")
    diff = np.asarray(d.get_pixels(oiio.FLOAT), np.float32).reshape(img.shape)
    failing = (diff > fail).any(axis=-1)  # the picture's mask; the counts are OpenImageIO's
    warning = (diff > warn).any(axis=-1)
    figures = {"fail_pixels": int(cr.nfail), "warn_pixels": int(cr.nwarn),
               "mean_error": float(cr.meanerror), "rms_error": float(cr.rms_error), "psnr": float(cr.PSNR),
               "max_error": float(cr.maxerror), "max_x": int(cr.maxx), "max_y": int(cr.maxy),
               "max_channel": channels[int(cr.maxc)] if 0 <= int(cr.maxc) < len(channels) else str(cr.maxc)}
    return figures, diff, failing, warning

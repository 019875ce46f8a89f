"""One adaptive render job: scene -> loop -> result -> outputs.  The same
generator runs behind the CLI (``./cycles-adaptive render``, ``blender -c
cycles_adaptive``), the modal UI operator and the Python API (``api.py``).

A job first produces an :class:`Output` (the EXR passes, attributes and the
summary dict) without touching the disk; writing it is a separate step
(:func:`write_output`), which the CLI and the operator take at once and the API
takes on ``Result.save``.

Outputs (written atomically; an existing file is never replaced unless
``overwrite``):
- ``OUT.exr``: multilayer EXR, layer = the view layer's name, passes
  ``Combined`` (result RGB + mean alpha), ``Noisy``, ``Variance`` (of the mean,
  0 where unknown), ``M2``, ``Samples``, ``Groups``, ``Error`` (estimated
  squared error), ``NextIndex``, ``GroupPower`` (the groups' sizes for the
  header's ``cycles_adaptive/exponent/<layer>``) and ``Feat_<name>`` /
  ``Feat_<name>_M2`` for every
  feature pass: all that ``denoise`` needs to re-run any method later (every
  render keeps :func:`denoise_passes`, whatever its own method reads).
  When the scene composites its renders (``addon/compositor.py``), the
  composited image follows as a second layer, ``Composite`` (pass
  ``Combined``), and the passes the compositor reads are kept as features.
- ``OUT.png``: preview in the scene's view transform (of the composited image
  when there is one).
- ``OUT.exr.checkpoint.npz`` after every iteration, removed after a complete
  run, kept after a cancel so ``--resume`` continues.  A job without ``out``
  (the API's) writes no checkpoint and nothing else.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass, fields

import numpy as np

from ..core import cryptomatte
from ..core import io as imageio
from ..core import methods, metrics
from ..core.method import consistency_guard, params_from_dict
from ..core.pipeline import CRYPTOMATTE_SLACK, AdaptiveRun, Options, Progress, Work, hold_samples, option_fields
from ..core.resources import peak_rss_mb
from ..core.storage import buffers_from_passes, buffers_to_passes

OUTPUT_VERSION = "1"


class JobError(Exception):
    """Bad input for a job; the message is for the user, one line."""


def checkpoint_path(out: str) -> str:
    return out + ".checkpoint.npz"


def preview_path(out: str) -> str:
    return os.path.splitext(out)[0] + ".png"


def denoise_passes() -> tuple:
    """The feature passes some ``denoise`` method reads (the union of the
    denoisers' ``PASSES``: albedo, normal, depth).  A render keeps them in its
    output so that any method can be re-run on it later; the cost is measured
    in docs/notes/denoise-cli.md."""
    out = []
    for name in methods.DENOISERS:
        try:
            out.extend(methods.get(name).PASSES)
        except ImportError:
            continue
    return tuple(dict.fromkeys(out))


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


# ================================================================ options
def make_options(method: str, frame: int, settings: dict | None = None,
                 params: dict | None = None) -> Options:
    """The one place user arguments become :class:`Options` (CLI flags and
    API keywords alike).  ``settings``: loop settings (fields of ``Options``
    offered on the command line, e.g. ``spp``, ``initial_spp``); ``params``:
    the method's parameters (fields of its ``Params``).  JobError (one line)
    names an unknown method, setting or parameter, or a value out of range."""
    try:
        mod = methods.get(method)
    except ValueError as exc:
        raise JobError(str(exc)) from None
    known = {f.name: f for f in option_fields("cli")}
    for name in settings or {}:
        if name not in known:
            raise JobError(f"unknown loop setting {name!r} (have {', '.join(known)})")
    _check_param_names(method, mod.Params, params or {})
    own = {f.name: f for f in fields(mod.Params)}
    settings = {k: _typed(known[k], v, "option") for k, v in (settings or {}).items()}
    params = {k: _typed(own[k], v, f"{method} parameter") for k, v in (params or {}).items()}
    try:
        opts = Options(method=method, frame=int(frame), params=params, **settings)
        params_from_dict(mod.Params, params)  # range check now, before any render
    except (ValueError, TypeError) as exc:
        raise JobError(str(exc)) from None
    return opts


def split_keywords(method: str, keywords: dict) -> tuple[dict, dict]:
    """(settings, params) of flat keywords for :func:`make_options`: a loop
    setting's name goes to the settings, a method parameter's to the params;
    ``<method>_<name>`` always means the method's parameter (needed where a
    name is both, e.g. ``rhf_iterations`` or ``var_seed``, like the CLI's
    ``--rhf-iterations``).  JobError names anything else."""
    try:
        mod = methods.get(method)
    except ValueError as exc:
        raise JobError(str(exc)) from None
    known = {f.name for f in option_fields("cli")}
    own = {f.name for f in fields(mod.Params)}
    settings, params = {}, {}
    for name, value in keywords.items():
        if name.startswith(method + "_") and name[len(method) + 1:] in own:
            params[name[len(method) + 1:]] = value
        elif name in known:
            settings[name] = value
        elif name in own:
            params[name] = value
        else:
            _check_param_names(method, mod.Params, {name: value})
    return settings, params


def _typed(field, value, owner: str):
    """``value`` as the type of ``field``'s default, the type its CLI flag
    parses to (an API caller's ``spp=16`` becomes 16.0, as ``--spp 16``), so
    both paths build equal Options; JobError for a value of another kind."""
    default = field.default
    choices = field.metadata.get("choices")
    if choices and value not in choices:
        raise JobError(f"{owner} {field.name}={value!r}: choose one of {', '.join(map(str, choices))}")
    if value is None or default is None or isinstance(default, str) and isinstance(value, str):
        return value
    if isinstance(default, bool):
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
    elif isinstance(default, int):
        if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            return int(value)
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            return int(value)
    elif isinstance(default, float):
        if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
            return float(value)
    else:
        return value
    raise JobError(f"{owner} {field.name}={value!r}: expected {type(default).__name__}")


def _check_param_names(method: str, params_cls, params: dict) -> None:
    own = [f.name for f in fields(params_cls)]
    for name in params:
        if name not in own:
            have = ", ".join(own) if own else "none"
            raise JobError(f"unknown parameter {name!r} for method {method} (its parameters: {have}; "
                           f"loop settings: {', '.join(f.name for f in option_fields('cli'))})")


# ================================================================= scenes
def open_blend(path: str) -> None:
    """Open ``path`` in this process (``wm.open_mainfile``, no UI): it replaces
    the open file in memory; nothing is saved.  JobError for a missing or
    unreadable file."""
    import bpy
    if not os.path.isfile(path):
        raise JobError(f"{path}: no such .blend file")
    try:
        bpy.ops.wm.open_mainfile(filepath=os.path.abspath(path), load_ui=False)
    except RuntimeError as exc:
        raise JobError(f"{path}: cannot open ({str(exc).strip().splitlines()[-1]})") from None


def resolve_scene(scene_name: str | None = None, view_layer_name: str | None = None):
    """(scene, view layer) by name, default the active ones; JobError naming
    what exists when a name is not found."""
    import bpy
    scene = bpy.data.scenes.get(scene_name) if scene_name else bpy.context.scene
    if scene is None:
        raise JobError(f"no scene named {scene_name!r} (have {', '.join(s.name for s in bpy.data.scenes)})")
    return scene, resolve_view_layer(scene, view_layer_name)


def resolve_view_layers(scene, spec: str | None = None, active=None) -> list:
    """The view layers a render of ``scene`` covers: ``spec`` ``"all"`` (every
    layer enabled for rendering), ``"A,B"`` (those, in that order), or None:
    as Blender's own render does, every enabled layer, or only the active
    one (``active``, default :func:`resolve_view_layer`) when the scene's
    Render Single Layer is on.  JobError for unknown or disabled names."""
    if spec is None:
        if scene.render.use_single_layer:
            return [active or resolve_view_layer(scene)]
        spec = "all"
    if spec.strip() == "all":
        layers = [vl for vl in scene.view_layers if vl.use]
        if not layers:
            raise JobError(f"scene {scene.name!r} has no view layer enabled for rendering")
        return layers
    names = [n.strip() for n in spec.split(",") if n.strip()]
    if not names or len(set(names)) != len(names):
        raise JobError(f"--view-layers {spec!r}: expected all or distinct names separated by commas")
    layers = [resolve_view_layer(scene, n) for n in names]
    off = [vl.name for vl in layers if not vl.use]
    if off:
        raise JobError(f"view layer {off[0]!r} is disabled for rendering (Use for Rendering is off)")
    return layers


def resolve_view_layer(scene, name: str | None = None):
    """The view layer ``name`` of ``scene`` (default: the active one when the
    scene is the active scene, else its first)."""
    import bpy
    if name:
        vl = scene.view_layers.get(name)
        if vl is None:
            raise JobError(f"no view layer {name!r} in scene {scene.name!r} "
                           f"(have {', '.join(v.name for v in scene.view_layers)})")
        return vl
    return bpy.context.view_layer if bpy.context.scene == scene else scene.view_layers[0]


def check_resolution_percentage(value: int) -> int:
    """The resolution percentage override, checked (Blender's range 1-10000)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= 10000:
        raise JobError(f"resolution percentage must be an integer between 1 and 10000, got {value!r}")
    return int(value)


# ================================================================= output
@dataclass
class Output:
    """What a job produced, before anything is written.

    passes : the EXR passes (:func:`core.storage.buffers_to_passes`; arrays or
        ``(array, channel letters)``), full frame, exactly as written.
    layer : the EXR's layer name (the view layer's).
    attributes : string attributes of the EXR (``cycles_adaptive/...``).
    summary : the run's summary, the CLI's JSON line (``out`` is None until
        written).
    """

    passes: dict
    layer: str
    attributes: dict
    summary: dict
    extra_layers: list = dataclasses.field(default_factory=list)  # [(layer, passes)] after ours
    composite: np.ndarray | None = None  # the compositor's (H, W, 4) image, when it ran
    exr: "ExrFormat" = None  # how the EXR is stored (default: ExrFormat())


#: passes of our EXR that are results to look at (the result, the compositor's
#: image, the error and variance images), not statistics that ``denoise`` or a
#: resume reads: only these may be half float
RESULT_PASSES = frozenset({"Combined", "Error", "Variance"})

EXR_DEPTHS = imageio.EXR_DEPTHS
EXR_CONTENTS = imageio.EXR_CONTENTS

#: the passes an ``"image"`` EXR keeps: what compositing reads (the result, its
#: estimated error, samples per pixel and the feature means), not the statistics
#: that ``denoise`` re-runs from
IMAGE_PASSES = frozenset({"Combined", "Error", "Samples"})


@dataclasses.dataclass(frozen=True)
class ExrFormat:
    """How the output EXR stores its passes.  ``half``: the result passes
    (``RESULT_PASSES``) in half float, as Blender's Float (Half) stores colour
    passes while it keeps data passes full (checked with bpy 4.5: Combined and
    Denoising Albedo half, Depth and Normal float); the statistics that
    re-runs read stay full float always.  ``codec``: a lossless EXR codec."""

    half: bool = True
    codec: str = "zip"
    note: str = ""  # why the scene's own setting was not taken, if it was not
    contents: str = "full"  # "full": every pass; "image": IMAGE_PASSES and the feature means

    @property
    def label(self) -> str:
        text = f"{'half' if self.half else 'full'} float results, {self.codec.upper()}"
        return text + (", image passes only" if self.contents == "image" else "")

    def keeps(self, name: str) -> bool:
        """Whether pass ``name`` goes into the file."""
        if self.contents == "full":
            return True
        return (name in IMAGE_PASSES or (name.startswith("Feat_") and not name.endswith("_M2"))
                or name.startswith(CRYPTOMATTE_PREFIXES))


#: pass name prefixes of Cryptomatte layers (kept in every EXR: compositing reads them)
CRYPTOMATTE_PREFIXES = ("CryptoObject", "CryptoMaterial", "CryptoAsset")


def cryptomatte_output(run, layer: str, passes: dict) -> dict:
    """Add the run's merged Cryptomatte ranks to ``passes`` as Blender names
    them (``<base>00``, ``01``, ...; channels r, g, b, a; float32: ids are
    bit patterns) and return their header attributes
    (``cryptomatte/<key>/name|hash|conversion|manifest``, the key the
    MurmurHash3 of ``<layer>.<base>``), so Nuke / a compositor finds them."""
    attrs = {}
    for base, acc in getattr(run, "cryptomatte", {}).items():
        levels = max(1, acc.capacity // CRYPTOMATTE_SLACK)
        for i, arr in enumerate(acc.layers(levels)):
            passes[f"{base}{i:02d}"] = (arr, ("r", "g", "b", "a"))
        header = getattr(run, "cryptomatte_header", {}).get(base, {})
        name = f"{layer}.{base}"
        key = cryptomatte.header_key(name)
        attrs[f"cryptomatte/{key}/name"] = name
        attrs[f"cryptomatte/{key}/hash"] = header.get("hash", "MurmurHash3_32")
        attrs[f"cryptomatte/{key}/conversion"] = header.get("conversion", "uint32_to_float32")
        attrs[f"cryptomatte/{key}/manifest"] = header.get("manifest", "{}")
    return attrs


def exr_format(scene=None, depth: str = "scene", contents: str = "full") -> ExrFormat:
    """The :class:`ExrFormat` for ``depth`` (``EXR_DEPTHS``).  ``"scene"``: a
    scene whose output is OpenEXR gives its Color Depth and Codec (a lossy
    codec - PXR24, B44, DWA - becomes ZIP: the statistics must stay exact);
    any other output format (PNG by default), or no scene, gives half float
    results with ZIP.  Half's relative step, 2^-11, is 20x below the 1 % RMS
    error of the smallest relMSE the benchmark resolves (1e-4).  Main thread
    (reads the scene)."""
    if depth not in EXR_DEPTHS:
        raise JobError(f"EXR depth {depth!r} is not one of {', '.join(EXR_DEPTHS)}")
    if contents not in EXR_CONTENTS:
        raise JobError(f"EXR contents {contents!r} is not one of {', '.join(EXR_CONTENTS)}")
    if depth != "scene":
        return ExrFormat(half=depth == "half", contents=contents)
    settings = getattr(getattr(scene, "render", None), "image_settings", None)
    if settings is None or "OPEN_EXR" not in str(getattr(settings, "file_format", "")):
        return ExrFormat(contents=contents)
    half = str(getattr(settings, "color_depth", "32")) == "16"
    codec = str(getattr(settings, "exr_codec", "ZIP")).lower()
    if codec in imageio.LOSSLESS_CODECS:
        return ExrFormat(half, codec, contents=contents)
    return ExrFormat(half, "zip", f"the scene's EXR codec {codec.upper()} is lossy; ZIP keeps the "
                                   "statistics exact", contents)


def write_output(output: Output, path: str) -> None:
    """Write the multilayer EXR of ``output`` to ``path`` atomically
    (:func:`core.io.write_multilayer`: our layer first, then the others, e.g.
    ``Composite``), stored as ``output.exr`` says; the caller checked that
    it may."""
    fmt = output.exr or ExrFormat()
    layers = [(output.layer, output.passes)] + list(output.extra_layers)
    layers = [(name, {k: v for k, v in passes.items() if fmt.keeps(k)}) for name, passes in layers]
    imageio.write_multilayer(path, layers,
                             attributes=output.attributes,
                             half=RESULT_PASSES if fmt.half else False, codec=fmt.codec)


#: the run's own estimate of its relMSE (for the panel's summary and the CLI's JSON)
estimated_relmse = metrics.estimated_relmse


def _info_fields(summary: dict, info: dict, prefix: str = "") -> None:
    for k, v in info.items():
        if isinstance(v, (int, float, str, bool)):
            summary[prefix + k] = v


def composite_plan(scene, layers) -> tuple:
    """``(plan, note)``: what the scene's compositor reads
    (:func:`addon.compositor.plan`) when this job can feed it, with note
    ``"pending"``; else ``(None, note)``, note ``"none"`` (the scene does not
    composite) or ``"skipped: why"`` (a pass or view layer this job does
    not render: the result is written raw)."""
    from ..addon import compositor
    try:
        plan = compositor.plan(scene)
    except compositor.CompositorError as exc:
        return None, f"skipped: {exc}"
    if plan is None:
        return None, "none"
    missing = [n for n in plan.layers if n not in layers]
    if missing:
        return None, (f"skipped: the compositor also reads view layer(s) {', '.join(map(repr, missing))}, "
                      "which this render does not include (--view-layers all renders every one)")
    return plan, "pending"


def _array(value):
    return value[0] if isinstance(value, tuple) else value


def check_outputs(out: str, preview: bool, may_replace: bool) -> None:
    """JobError unless the EXR ``out`` (and its preview) may be written."""
    try:
        imageio.check_writable(out, may_replace)
        if preview:
            imageio.check_writable(preview_path(out), may_replace)
    except imageio.ImageFileError as exc:
        raise JobError(str(exc)) from None


def run_compositor(scene, plan, outputs, file_outputs: bool = True) -> tuple:
    """``(image, note)``: the scene's compositor (``plan``:
    :func:`composite_plan`) on ``outputs``, ``[(view layer name, Output)]``,
    each fed its result and the feature passes the plan names (main thread:
    bpy); ``(None, "skipped: why")`` when it cannot run.  ``file_outputs``:
    see :func:`addon.compositor.composite`."""
    from ..addon import compositor
    try:
        layers, attributes = {}, {}
        for name, out in outputs:
            feats = {f: _array(out.passes[f"Feat_{f}"]) for f in plan.features(name)}
            layers[name] = compositor.layer_passes(_array(out.passes["Combined"]), feats, plan.features(name))
            layers[name].update({k: v for k, v in out.passes.items() if k.startswith(CRYPTOMATTE_PREFIXES)})
            attributes.update({k: v for k, v in out.attributes.items() if k.startswith("cryptomatte/")})
        return compositor.composite(scene, layers, attributes=attributes, file_outputs=file_outputs), "applied"
    except (compositor.CompositorError, KeyError) as exc:
        return None, f"skipped: {exc}"


def output_seconds(scene, layer_names, buf, exr, out: str, plan=None, preview: bool = False) -> float:
    """Seconds the outputs of a frame are predicted to take, for a time
    limit's reserve: the EXR (one layer per name of ``layer_names``, each
    ``buf``'s passes, stored as ``exr`` says), then the scene's compositor
    on them when ``plan`` (:func:`composite_plan`) says it runs (File Output
    nodes removed from its copy: nothing is written where the user's tree
    says), then the preview PNG when ``preview``, all written to temporary
    files beside ``out`` and deleted.  Timed on two centre bands of rows (an
    eighth and a quarter of the frame, at least 16 and 32 rows: smaller bands
    gave slopes half the frame's) and extrapolated to the frame by the line
    through both (:func:`core.timeplan.extrapolate_seconds`: the
    compositor's fixed cost, a scene copy and a render call, is not scaled
    with the rows); a frame of at most 32 rows is timed whole.  Calls bpy
    when ``plan`` or ``preview`` (main thread)."""
    from ..addon.executor import write_preview
    from ..core import timeplan
    h, w = buf.shape

    def band_seconds(rows: int) -> float:
        y0 = (h - rows) // 2
        band = buf.crop(0, y0, w, y0 + rows)
        var = band.variance_of_mean().mean(axis=-1)
        passes = buffers_to_passes(band, band.color.mean, np.where(np.isfinite(var), var, 0.0))
        passes["NextIndex"] = np.zeros((rows, w))
        names = list(layer_names)
        result = Output(passes, names[0], {}, {}, [(n, passes) for n in names[1:]], exr=exr)
        tmp = imageio.temp_beside(out, ".exr")
        png = imageio.temp_beside(out, ".png")
        t0 = time.perf_counter()
        try:
            write_output(result, tmp)
            shown = None
            if plan is not None:
                shown, _ = run_compositor(scene, plan, [(n, result) for n in names], file_outputs=False)
            if preview:
                write_preview(scene, shown if shown is not None else _array(passes["Combined"]), png)
            return time.perf_counter() - t0
        finally:
            for path in (tmp, png):
                if os.path.exists(path):
                    os.unlink(path)

    large = min(h, max(32, h // 4))
    if large == h:
        return band_seconds(h)
    small = min(large - 1, max(16, h // 8))
    t_large = band_seconds(large)  # first: a one-time set-up it pays steepens the line (reserve more, not less)
    t_small = band_seconds(small)
    return timeplan.extrapolate_seconds(small * w, t_small, large * w, t_large, h * w)


class RenderJob:
    """Adaptive render of one frame of a scene.

    ``steps()`` yields ``Progress``; when it ends (or after a cancel) call
    ``finish(partial=...)``, which reconstructs, writes the outputs (when the
    job has an ``out``) and returns the summary dict (the CLI's JSON line);
    ``output(partial=...)`` gives the same result without writing anything.
    """

    def __init__(self, scene, view_layer, options: Options, out: str | None, reference: str | None = None,
                 overwrite: bool = False, resume: bool = False, preview: bool = True,
                 keep_checkpoint: bool = False, method=None, prior=None, reconstructor=None,
                 executor_factory=None, keep_denoise_passes: bool = True, compositor: bool = True,
                 checkpoint: str | None = None, exr_depth: str = "scene", exr_contents: str = "full",
                 view_transform=None):
        """``out``: the output EXR, or None to write nothing (no checkpoint,
        no outputs: the API); ``method``: a :class:`core.method.Method` object
        (default: the registered ``options.method``); ``prior``: the run's
        source of carried samples (``core.pipeline.Prior``);
        ``reconstructor(run) -> MethodResult`` replaces the method's final
        reconstruction (LP's temporal extension); ``keep_denoise_passes``:
        also render :func:`denoise_passes` so ``denoise`` can re-run any
        method on the output (False only to measure what they cost);
        ``compositor``: run the scene's compositor on the result when a final
        render of the scene would (``addon/compositor.py``); what it cannot
        run on is said in the summary's ``compositor`` and the EXR stays raw;
        ``checkpoint``: the checkpoint of a job without ``out`` (one view
        layer of a :class:`LayersJob`, which writes the outputs itself);
        ``exr_depth``, ``exr_contents``: how the EXR stores its result
        passes and which passes it keeps (:func:`exr_format`);
        ``view_transform``: the run's (``core.pipeline.AdaptiveRun``)."""
        from ..addon import executor as ex
        self.ex = ex
        ex.check_scene(scene, view_layer)
        self.exr = exr_format(scene, exr_depth, exr_contents)
        self.scene, self.view_layer = scene, view_layer
        self.layer_name = view_layer.name  # output() may run off the main thread: no RNA access there
        self.composite_plan, self.compositor_note = (composite_plan(scene, [view_layer.name])
                                                     if compositor else (None, "off"))
        extra = self.composite_plan.features(view_layer.name) if self.composite_plan else ()
        if keep_denoise_passes:
            extra = denoise_passes() + tuple(extra)
        if extra:
            options = dataclasses.replace(options, features=tuple(dict.fromkeys(tuple(options.features) + extra)))
        self.options = options
        self.out = os.path.abspath(bpy_path(out)) if out else None
        self.ckpt = checkpoint_path(self.out) if self.out else checkpoint
        self.resume = resume
        if resume and not (self.ckpt and os.path.isfile(self.ckpt)):
            raise JobError(f"--resume: no checkpoint {self.ckpt}")
        self.preview = preview and self.out is not None
        if self.out:
            check_outputs(self.out, self.preview, overwrite or resume)
        self.keep_checkpoint = keep_checkpoint
        self.reference_path = reference
        self.run: AdaptiveRun | None = None
        self.executor = None
        self.method = methods.method_for(options.method, options.params) if method is None else method
        self.prior = prior
        self.reconstructor = reconstructor
        self.view_transform = view_transform
        self.executor_factory = executor_factory or ex.CyclesExecutor
        self.camera = None         # camera matrices of the rendered frame
        self.result = None         # the final MethodResult, once output() ran
        self._final: Work | None = None  # the final reconstruction (reconstruct_work)
        self.t0 = time.perf_counter()
        self.summary: dict | None = None
        self._output: Output | None = None
        #: a job without ``out`` (one layer of a LayersJob): optional
        #: ``probe(buffers) -> seconds`` of the outputs written for it, called
        #: once by a time-limited run (main thread) and reserved
        self.output_probe = None

    def steps(self):
        self.executor = self.executor_factory(self.scene, self.view_layer,
                                              tuple(self.method.PASSES) + tuple(self.options.features),
                                              seed=self.options.seed)
        self.reference = load_reference(self.reference_path, self.executor.size)
        hold_samples(self.executor, self.options, self.method, self.prior)
        with self.executor:
            self.camera = self.executor.camera_info(self.options.frame)
            self.run = AdaptiveRun(self.executor, self.options, checkpoint=self.ckpt, prior=self.prior,
                                   method=self.method, started=self.t0, view_transform=self.view_transform)
            probe = self._time_output if self.out else self.output_probe
            if probe is not None and self.run.timed:
                self.run.reserve_probe = probe
                self.run.reserve_probe_main_thread = self.out is None or self.preview \
                    or self.composite_plan is not None
            if self.resume:
                try:
                    self.run.load_checkpoint(self.ckpt)
                except ValueError as exc:
                    raise JobError(str(exc)) from None
            yield from self.run.steps()
        # the scene is restored; the final reconstruction is pure numpy, so a
        # consumer may run it on a worker thread (the UI's stepper does)
        run = self.run
        work = self.reconstruct_work()
        fraction = min(1.0, run.samples_rendered / max(run.budget, 1))
        yield Progress("reconstruct", run.iteration, fraction, work.label, work=work)
        if self.out:  # finish() writes next: announced for the batch log and the status bar
            yield Progress("write", run.iteration, fraction, f"writing {self.out}")

    def _time_output(self, buf) -> float:
        """Seconds this job's outputs are predicted to take, for a time
        limit's reserve (:func:`output_seconds`: the EXR, the compositor when
        it runs, the preview)."""
        return output_seconds(self.scene, [self.layer_name], buf, self.exr, self.out,
                              self.composite_plan, self.preview)

    def reconstruct_work(self) -> Work:
        """The final reconstruction (``AdaptiveRun.reconstruct`` with this
        job's reconstructor, through the consistency guard) as one
        :class:`core.pipeline.Work`: computed once, by whoever runs it first
        (the UI's worker thread, or :meth:`output` inline)."""
        if self._final is None:
            run, rec = self.run, self.reconstructor
            self._final = Work(lambda: run.reconstruct(rec), f"reconstructing ({self.options.method})",
                               run.main_thread_only())
        return self._final

    def _result(self, reconstruct: bool):
        """(MethodResult, reconstructed) for the output: the final
        reconstruction when it has completed or ``reconstruct`` asks for it
        (computed inline then), else the sample mean with the variance of the
        mean as its error: what a cancel writes at once instead of waiting
        for a reconstruction (tens of seconds at 1920x1080); every sample and
        pass is in the EXR, so ``denoise`` (or ``--resume`` from the kept
        checkpoint) reconstructs it later.  The error there is the plain
        s^2 / n (``Buffers.variance_of_mean``), not the calibrated, pooled
        variance the methods read, which alone takes ~10 s at 1920x1080
        (docs/notes/responsive-ui.md)."""
        final = self._final
        if reconstruct or (final is not None and final.done):
            return self.reconstruct_work().result(), True
        from ..core import uniform
        buf = self.run.buffers
        return uniform.denoise(buf.color.mean, buf.variance_of_mean()), False

    def output(self, partial: bool = False, reconstruct: bool = True) -> Output:
        """Reconstruct from what was rendered: the passes, attributes and
        summary, nothing written.  Computed once (a reconstruction may carry
        state, e.g. LP's temporal one); later calls return the same Output.
        ``reconstruct=False`` (a cancel from the UI) takes the sample mean
        unless the final reconstruction has already completed (see
        :meth:`_result`)."""
        if self._output is not None:
            return self._output
        run = self.run
        if run is None or run.buffers is None:
            raise JobError("nothing was rendered")
        run.settle()  # a merge the loop left running when it stopped (Esc, Ctrl-C, an error)
        result, reconstructed = self._result(reconstruct)
        self.result = result
        image = np.where(np.isfinite(result.image), result.image, 0.0)
        error = np.where(np.isfinite(result.error), result.error, 0.0)
        passes = buffers_to_passes(run.buffers, image, error)
        passes["NextIndex"] = run.next_index.astype(np.float64)
        crypto_attrs = cryptomatte_output(run, self.layer_name, passes)
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
                 "cycles_adaptive/partial": str(bool(partial)).lower(),
                 "cycles_adaptive/reconstructed": str(bool(reconstructed)).lower(),
                 # the sequence's stratification exponent of this layer's buffers (with its
                 # GroupPower pass): what `denoise` calibrates the variance with
                 f"{EXPONENT_ATTRIBUTE}/{self.layer_name}": repr(float(run.buffers.exponent))}
        attrs.update(crypto_attrs)
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
            "reconstructed": bool(reconstructed),
            "estimated_relmse": estimated_relmse(image, error),
            "time_limited": bool(run.time_limited),
            "max_seconds": self.options.max_seconds,
            "sampling_seconds": run.sampling_seconds,
            "max_task_seconds": run.max_task_seconds,
        }
        if run.timed:  # how the limit was planned (core/timeplan.py)
            overhead, per_sample = run.cost.fit()
            summary.update({"render_overhead_seconds": overhead, "render_seconds_per_msample": per_sample * 1e6,
                            "reconstruct_estimate_seconds": float(run.reconstruct_estimate or 0.0),
                            "reserved_seconds": run.final_reserve(), "sliced_tasks": run.slices})
        summary.update({
            "reused_samples": int(run.reused.sum()),
            "reprojected_fraction": float((run.reused > 0).mean()),
            "blender": bpy.app.version_string,
        })
        pattern = getattr(self.executor, "pattern", None)
        if pattern:  # Tabulated Sobol, or the scene's own with the count held (hold_samples_at)
            summary["sampling_pattern"] = pattern
        initial = getattr(self.executor, "initial_pattern", None)
        if initial and initial != pattern:  # auto chose adaptive sampling after a held initial pass
            summary["initial_sampling_pattern"] = initial
        _info_fields(summary, result.info)
        _info_fields(summary, run.prior_info, "reproject_")
        if run.selection is not None:  # auto: what it chose, each candidate's prediction, why
            summary.update({"chosen": run.selection["chosen"], "candidates": run.selection["candidates"],
                            "chosen_why": run.selection["why"]})
            attrs["cycles_adaptive/chosen"] = json.dumps(_jsonable(run.selection))
        if run.dropped:
            summary["dropped_passes"] = list(run.dropped)
        summary["compositor"] = self.compositor_note
        summary["exr"] = self.exr.label + (f" ({self.exr.note})" if self.exr.note else "")
        if self.options.target_error > 0:  # the estimate at each check, and whether it got there
            summary.update(target_error=self.options.target_error, target_met=bool(run.target_met),
                           estimates=[{"spp": a, "estimated_relmse": b} for a, b in run.estimates])
        if self.reference is not None:
            summary.update(metrics.summary(image, error, self.reference))
        self._output = Output(passes, self.layer_name, attrs, summary, exr=self.exr)
        self.summary = summary
        return self._output

    def finish(self, partial: bool = False, reconstruct: bool = True) -> dict:
        """Reconstruct from what was rendered and, when the job has an
        ``out``, write the EXR, the PNG preview and drop the checkpoint
        (``reconstruct``: see :meth:`output`; the checkpoint is kept after a
        partial run).  Runs :meth:`write_steps` inline on this thread (the
        CLI, the API, a batch operator); once the outputs are written, a later
        call returns the same summary without writing again."""
        steps = self.write_steps(partial, reconstruct, threaded=False)
        while True:
            try:
                next(steps)  # a Work: write_steps calls its result(), which runs it here
            except StopIteration as stop:
                return stop.value

    def write_steps(self, partial: bool = False, reconstruct: bool = True, threaded: bool = True):
        """:meth:`finish` as a generator, for a caller that keeps a UI
        responsive: it yields each pure part (numpy and OpenImageIO, no bpy)
        as a :class:`core.pipeline.Work`, which the caller may run on a worker
        thread before resuming it, and runs the bpy part on the thread that
        resumes it (Blender's main thread).  Returns the summary (the
        generator's value).

        ``threaded``: 1. Work: :meth:`output` and the atomic EXR write
        (seconds at 1920x1080, docs/notes/responsive-ui.md); the view layer's
        name, the only bpy data ``output`` reads, is read before.  2. main
        thread: the preview through Blender's colour management
        (:meth:`_save_display_tiff`, an uncompressed 8-bit TIFF: the PNG
        save's pixels, without its zlib cost).  3. Work: that TIFF encoded as
        the PNG, atomically.  The EXR comes first, so a quit between the steps
        can lose only the preview.  ``threaded=False`` (:meth:`finish`):
        ``output`` and the preview run as before (one ``save_render`` PNG)."""
        if getattr(self, "_written", None) is not None:
            return self._written
        if self.out is None:  # the API's job: nothing to write
            return self.output(partial, reconstruct).summary

        composite = self.composite_plan is not None

        def write(out):
            t = time.perf_counter()
            write_output(out, self.out)
            px = self._preview_pixels(out) if self.preview and threaded else None
            return out, px, time.perf_counter() - t

        def compute_and_write():
            out = self.output(partial, reconstruct)
            return (out, None, 0.0) if composite else write(out)

        work = Work(compute_and_write, f"writing {self.out}")
        yield work  # output() reads no Blender data (the layer's name is kept from __init__)
        out, px, seconds = work.result()
        if composite:  # bpy: the compositor runs here, then the EXR holds its image too
            t = time.perf_counter()
            self._run_compositor(out)
            seconds += time.perf_counter() - t
            work = Work(lambda: write(out), f"writing {self.out}")
            yield work
            out, px, more = work.result()
            seconds += more
        if self.preview:
            t = time.perf_counter()
            png = preview_path(self.out)
            yield from self._preview_steps(out, px, png, threaded)
            del px
            seconds += time.perf_counter() - t
        self.run.timing.overhead += seconds
        if not partial and not self.keep_checkpoint and os.path.exists(self.ckpt):
            os.unlink(self.ckpt)
        out.summary["total_seconds"] = time.perf_counter() - self.t0
        self._written = out.summary
        return out.summary

    def _preview_steps(self, out: Output, px, png: str, threaded: bool):
        """Write the preview ``png`` of ``out``: threaded, the colour-managed
        TIFF here (bpy) from the pixels ``px`` prepared off the main thread,
        then its PNG encoding as a yielded Work; else one ``save_render`` PNG
        of the composite (or the Combined pass) here."""
        if not threaded:
            shown = out.composite if out.composite is not None else _array(out.passes["Combined"])
            self.ex.write_preview(self.scene, shown, png)
            return
        tmp = imageio.temp_beside(png, ".tif")
        try:
            self._save_display_tiff(px, tmp)
            encode = Work(lambda: self._encode_png(tmp, png), f"writing {png}")
            yield encode
            encode.result()
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)

    @property
    def composite(self):
        """The compositor's image once the outputs are written, else None."""
        return self._output.composite if self._output is not None else None

    def _run_compositor(self, out: Output) -> None:
        """The scene's compositor on ``out`` (main thread: bpy): sets
        ``out.composite`` and the EXR's ``Composite`` layer, or says in the
        summary why it was skipped (the EXR then stays raw)."""
        rgba, self.compositor_note = run_compositor(self.scene, self.composite_plan, [(self.layer_name, out)])
        if rgba is not None:
            out.composite = rgba
            out.extra_layers = [(imageio.COMPOSITE_LAYER, {"Combined": rgba})]
        out.summary["compositor"] = self.compositor_note

    @staticmethod
    def _preview_pixels(out: Output) -> tuple:
        """The image shown (the composite when the compositor ran, else the
        Combined pass) as the flat float32 RGBA buffer of a Blender
        image (rows bottom to top; non-finite values 0; alpha 1 where the pass
        has none) and its width and height (:func:`addon.display.float_pixels`,
        as :func:`addon.executor.write_preview` uses it): numpy only, so the
        writer thread prepares it."""
        from ..addon.display import float_pixels
        return float_pixels(out.composite if out.composite is not None else _array(out.passes["Combined"]))

    def _save_display_tiff(self, pixels: tuple, path: str) -> None:
        """The bpy part of the preview (main thread): ``pixels``
        (:meth:`_preview_pixels`) saved through the scene's colour management
        (view transform, look, exposure, gamma, dither: ``save_render``) as an
        uncompressed 8-bit RGBA TIFF, the same pixels a PNG save writes; the
        image and the scene's output settings are restored."""
        import bpy
        px, w, h = pixels
        img = bpy.data.images.new("cycles_adaptive_preview", w, h, alpha=True, float_buffer=True)
        guard = self.ex.SettingsGuard()
        try:
            img.pixels.foreach_set(px)
            st = self.scene.render.image_settings
            if hasattr(st, "media_type"):
                guard.set(st, "media_type", "IMAGE")
            guard.set(st, "file_format", "TIFF")
            guard.set(st, "color_mode", "RGBA")
            guard.set(st, "color_depth", "8")
            guard.set(st, "tiff_codec", "NONE")
            img.save_render(path, scene=self.scene)
        finally:
            guard.restore()
            bpy.data.images.remove(img)

    @staticmethod
    def _encode_png(tiff: str, png: str) -> None:
        """Re-encode the 8-bit TIFF of :meth:`_save_display_tiff` as the PNG
        preview ``png``, atomically (OpenImageIO, no bpy: the writer thread);
        the pixels are copied unchanged."""
        import OpenImageIO as oiio
        src = oiio.ImageInput.open(tiff)
        if src is None:
            raise imageio.ImageFileError(f"{tiff}: cannot read the preview ({oiio.geterror()})")
        try:
            spec = src.spec()
            pixels = src.read_image(0, 0, 0, spec.nchannels, oiio.UINT8)
        finally:
            src.close()
        if pixels is None:
            raise imageio.ImageFileError(f"{tiff}: cannot read the preview")
        with imageio.atomic_path(png, ".png") as tmp:
            dst = oiio.ImageOutput.create(tmp)
            if dst is None or not dst.open(tmp, oiio.ImageSpec(spec.width, spec.height, spec.nchannels,
                                                                 oiio.UINT8)):
                raise imageio.ImageFileError(f"{png}: cannot write ({oiio.geterror()})")
            ok = dst.write_image(pixels)
            dst.close()
            if not ok:
                raise imageio.ImageFileError(f"{png}: write failed ({dst.geterror()})")


# ================================================================ denoise
def layer_checkpoint_path(out: str, layer: str) -> str:
    """The checkpoint of view layer ``layer`` of a :class:`LayersJob`."""
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in layer)
    return f"{out}.{safe}.checkpoint.npz"


class LayersJob:
    """Adaptive render of several view layers of one frame, one
    :class:`RenderJob` each (same options and seed), written as one EXR with
    a layer per view layer (in the scene's order), then the scene's
    compositor on all of them (its ``Composite`` layer and the preview), as
    Blender's own render of the file gives.

    Each layer checkpoints on its own (:func:`layer_checkpoint_path`);
    ``--resume`` resumes every layer that has a checkpoint and starts the
    others; the checkpoints are removed once the EXR is written.  The
    interface is RenderJob's: ``steps()``, ``finish()``, ``write_steps()``,
    ``run``/``result``/``summary`` (of the last layer rendered, for the UI).
    """

    def __init__(self, scene, view_layers, options: Options, out: str, reference: str | None = None,
                 overwrite: bool = False, resume: bool = False, preview: bool = True,
                 keep_checkpoint: bool = False, executor_factory=None, compositor: bool = True, **job_kw):
        if not out:
            raise JobError("a render of several view layers needs an output path")
        if reference:
            raise JobError("--reference compares one view layer: choose it with --view-layer")
        self.scene = scene
        self.view_layers = list(view_layers)
        self.names = [vl.name for vl in self.view_layers]
        self.options = options
        self.out = os.path.abspath(bpy_path(out))
        self.preview = preview
        self.keep_checkpoint = keep_checkpoint
        check_outputs(self.out, preview, overwrite or resume)
        self.composite_plan, self.compositor_note = (composite_plan(scene, self.names) if compositor
                                                     else (None, "off"))
        self.jobs = []
        for vl in self.view_layers:
            extra = self.composite_plan.features(vl.name) if self.composite_plan else ()
            opts = dataclasses.replace(options, features=tuple(dict.fromkeys(tuple(options.features) + extra)))
            ckpt = layer_checkpoint_path(self.out, vl.name)
            self.jobs.append(RenderJob(scene, vl, opts, None, compositor=False,
                                       resume=resume and os.path.isfile(ckpt), checkpoint=ckpt,
                                       executor_factory=executor_factory, **job_kw))
        self.job = self.jobs[0]
        self.t0 = time.perf_counter()
        self.summary: dict | None = None
        self.composite = None  # the compositor's image, once written
        self._written = None

    @property
    def run(self):
        return self.job.run

    @property
    def result(self):
        return self.job.result

    @property
    def camera(self):
        return self.job.camera

    def steps(self):
        n = len(self.jobs)
        if self.options.max_seconds > 0 and self.out:
            self.jobs[0].output_probe = self._time_outputs
        for i, job in enumerate(self.jobs):
            self.job = job
            if self.options.max_seconds > 0:
                self._share_limit(i)
            for p in job.steps():
                p.message = f"view layer {job.layer_name} ({i + 1}/{n}): {p.message}"
                p.fraction = (i + p.fraction) / n
                yield p
        yield Progress("write", self.job.run.iteration, 1.0, f"writing {self.out}")

    def _time_outputs(self, buf) -> float:
        """Seconds the EXR of every layer, the compositor and the preview are
        predicted to take (:func:`output_seconds` with ``buf``, the first
        layer's buffers, standing in for each layer)."""
        return output_seconds(self.scene, self.names, buf, self.jobs[0].exr, self.out,
                              self.composite_plan, self.preview)

    def _share_limit(self, i: int) -> None:
        """Give layer ``i`` its share of ``Options.max_seconds``, which bounds
        the whole job: what is left (less the final reconstructions of the
        layers already sampled, which run at the end, and the outputs'
        reserve the first layer measured and kept in its own: each sampled
        layer's ``AdaptiveRun.final_reserve``) split evenly over the layers
        still to render, on a clock started now."""
        job = self.jobs[i]
        left = self.options.max_seconds - (time.perf_counter() - self.t0)
        left -= sum(j.run.final_reserve() for j in self.jobs[:i] if j.run is not None)
        share = max(left / (len(self.jobs) - i), 1e-3)  # > 0: 0 would mean no limit
        job.options = dataclasses.replace(job.options, max_seconds=share)
        job.t0 = time.perf_counter()

    def finish(self, partial: bool = False, reconstruct: bool = True) -> dict:
        """Reconstruct every layer, write the EXR and the preview (inline)."""
        steps = self.write_steps(partial, reconstruct, threaded=False)
        while True:
            try:
                next(steps)
            except StopIteration as stop:
                return stop.value

    def write_steps(self, partial: bool = False, reconstruct: bool = True, threaded: bool = True):
        """:meth:`RenderJob.write_steps` for all layers: a Work computes every
        layer's output; the compositor runs here (bpy); a Work writes the
        EXR (our layers, then ``Composite``) and prepares the preview; the
        preview is saved here through the colour management and encoded in
        a last Work.  Layers never rendered (a cancel before them) are left
        out and named in the summary."""
        if self._written is not None:
            return self._written
        done = [j for j in self.jobs if j.run is not None and j.run.buffers is not None]
        if not done:
            raise JobError("nothing was rendered")
        work = Work(lambda: [j.output(partial, reconstruct) for j in done], f"reconstructing {len(done)} view layers")
        yield work
        outs = work.result()
        extra, comp = [], None
        note = self.compositor_note
        if self.composite_plan is not None:
            if len(done) < len(self.jobs):
                note = "skipped: not every view layer was rendered"
            else:
                comp, note = run_compositor(self.scene, self.composite_plan,
                                            [(j.layer_name, o) for j, o in zip(done, outs)])
                if comp is not None:
                    extra = [(imageio.COMPOSITE_LAYER, {"Combined": comp})]
        first = outs[0]
        merged = Output(first.passes, first.layer, dict(first.attributes), self._summary(done, outs, note, partial),
                        [(o.layer, o.passes) for o in outs[1:]] + extra, comp, first.exr)
        merged.attributes["cycles_adaptive/view_layers"] = json.dumps([j.layer_name for j in done])
        for o in outs[1:]:  # each layer's exponent
            merged.attributes.update({k: v for k, v in o.attributes.items() if k.startswith(EXPONENT_ATTRIBUTE)})
        self.composite = comp
        t = time.perf_counter()

        def write():
            write_output(merged, self.out)
            return RenderJob._preview_pixels(merged) if self.preview and threaded else None

        work = Work(write, f"writing {self.out}")
        yield work
        px = work.result()
        if self.preview:
            yield from self.jobs[0]._preview_steps(merged, px, preview_path(self.out), threaded)
        self.job.run.timing.overhead += time.perf_counter() - t
        if not partial and not self.keep_checkpoint:
            for j in done:
                if os.path.exists(j.ckpt):
                    os.unlink(j.ckpt)
        merged.summary["total_seconds"] = time.perf_counter() - self.t0
        self.summary = self._written = merged.summary
        return merged.summary

    def _summary(self, jobs, outs, note: str, partial: bool) -> dict:
        """The first layer's summary with the totals of all layers, each
        layer's own figures under ``layers``, and the files written."""
        s = dict(outs[0].summary)
        per = {j.layer_name: o.summary for j, o in zip(jobs, outs)}
        for key in ("samples", "budget_samples", "regions", "overshoot_samples", "render_seconds",
                    "adapt_seconds", "reconstruct_seconds", "sampling_seconds"):
            s[key] = sum(v.get(key) or 0 for v in per.values())
        s["spp_mean"] = s["samples"] / max(1, sum(v["width"] * v["height"] for v in per.values()))
        s["estimated_relmse"] = max(v["estimated_relmse"] for v in per.values())
        s["reconstructed"] = all(v["reconstructed"] for v in per.values())
        s["max_seconds"] = self.options.max_seconds  # the job's limit (each layer ran on a share)
        s["time_limited"] = any(v.get("time_limited") for v in per.values())
        if self.options.max_seconds > 0:
            s["reserved_seconds"] = sum(v.get("reserved_seconds") or 0.0 for v in per.values())
        s.update(view_layers=[j.layer_name for j in jobs], out=self.out, compositor=note,
                 preview=preview_path(self.out) if self.preview else None, partial=bool(partial),
                 not_rendered=[j.layer_name for j in self.jobs if j not in jobs],
                 layers={k: {f: v.get(f) for f in ("spp_mean", "samples", "estimated_relmse", "chosen",
                                                   "render_seconds", "relmse") if f in v}
                         for k, v in per.items()})
        return s


#: header attribute (``<this>/<view layer>``) with the exponent of a layer's buffers
EXPONENT_ATTRIBUTE = "cycles_adaptive/exponent"


def stored_exponent(buf, meta: dict) -> None:
    """Set ``buf.exponent`` from the file's attribute for its layer (the
    render's measured stratification, core/variance.py), so a re-run
    calibrates the variance of the mean as the render did; 1.0 (i.i.d.)
    and no group record where the file has none (older outputs, plain
    Blender renders) or the value is unreadable."""
    raw = (meta.get("attributes") or {}).get(f"{EXPONENT_ATTRIBUTE}/{meta.get('layer') or ''}")
    try:
        value = float(raw) if raw is not None else None
    except (TypeError, ValueError):
        value = None
    if value is None or not np.isfinite(value) or value <= 0:
        buf.exponent, buf.gsum = 1.0, None
        return
    buf.exponent = value


def denoise_output(path: str, method: str, params: dict | None = None, guard_z: float | None = None,
                   reference: str | None = None, exr_depth: str = "half", exr_contents: str = "full") -> Output:
    """Re-run ``method`` on the passes stored in ``path`` (an output EXR of a
    render, or a Blender multilayer render with Combined and Denoising
    passes), through the consistency guard (``guard_z``, default the loop's):
    the output of ``denoise``, nothing written.  JobError for a method whose
    passes the file lacks; ImageFileError / StorageError for a bad file."""
    t0 = time.perf_counter()
    passes, meta = imageio.read_layers(path)
    buf = buffers_from_passes(passes, path)
    stored_exponent(buf, meta)
    mod = methods.get(method)
    missing = [f for f in mod.PASSES if f not in buf.features]
    if missing:
        raise JobError(f"{path}: method {method} needs the {missing[0]} pass, "
                       f"which the file lacks (have {', '.join(sorted(buf.features)) or 'none'})")
    ref = load_reference(reference, buf.shape)
    _check_param_names(method, mod.Params, params or {})
    try:
        params_obj = params_from_dict(mod.Params, params)
    except (ValueError, TypeError) as exc:
        raise JobError(str(exc)) from None
    warnings = input_warnings(path, buf, method)
    t1 = time.perf_counter()
    guard_z = Options().guard_z if guard_z is None else guard_z
    result = consistency_guard(mod.reconstruct(buf, params_obj), buf, guard_z)
    t_rec = time.perf_counter() - t1
    image = np.where(np.isfinite(result.image), result.image, 0.0)
    error = np.where(np.isfinite(result.error), result.error, 0.0)
    out_passes = buffers_to_passes(buf, image, error)
    h, w = buf.shape
    summary = {"method": method, "width": w, "height": h,
               "spp_mean": float(buf.n.mean()), "render_seconds": 0.0,
               "reconstruct_seconds": t_rec, "total_seconds": time.perf_counter() - t0,
               "regions": 0, "peak_rss_mb": peak_rss_mb(), "out": None, "preview": None,
               "preview_view_transform": None,
               "no_variance_fraction": float(1.0 - buf.has_variance.mean()), "warnings": warnings}
    _info_fields(summary, result.info)
    fmt = exr_format(None, "half" if exr_depth == "scene" else exr_depth, exr_contents)
    summary["exr"] = fmt.label
    if ref is not None:
        summary.update(metrics.summary(image, error, ref))
    return Output(out_passes, meta.get("layer") or "ViewLayer", {"cycles_adaptive/method": method}, summary,
                  exr=fmt)


#: what each denoiser does where a pixel has no variance estimate (one sample
#: group, e.g. a plain Blender render); read from each method's code
NO_VARIANCE = {
    "awr": "AWR thresholds its wavelets with Donoho's median estimate of the image's noise "
           "(finest diagonal wavelets) instead of per-pixel variance, and its error estimate rests on it",
    "lp": "LP's window selection subtracts no variance (the literal Eq. 5/7; the centre never keeps "
          "its own value) and its error estimate there is the largest finite one (0 if none)",
    "rhf": "RHF takes each missing variance from the nearest pixels that have one, or Immerkaer's "
           "noise estimate of the whole image where none has",
    "oidn": "OIDN denoises as usual but its error estimate is 0 there (no variance to recorrupt "
            "halves from)",
}


def input_warnings(path: str, buf, method: str) -> list:
    """One-line warnings about what ``path`` lacks for ``method``: pixels
    without a variance estimate (fewer than two sample groups), and what the
    method then does (:data:`NO_VARIANCE`); the consistency guard cannot check
    those pixels either."""
    missing = 1.0 - float(buf.has_variance.mean())
    if missing <= 0.0:
        return []
    what = ("has no variance (one sample group per pixel, e.g. a plain Blender render)"
            if missing >= 1.0 else f"has no variance on {100 * missing:.1f}% of its pixels (one sample group)")
    return [f"{path} {what}: {NO_VARIANCE.get(method, method + ' reconstructs without it')}; "
            "the consistency guard leaves those pixels unchecked"]


def bpy_path(path: str) -> str:
    """Expand Blender's ``//`` (relative to the .blend) when bpy is loaded."""
    if path.startswith("//"):
        import bpy
        return bpy.path.abspath(path)
    return path


def _jsonable(d):
    return json.loads(json.dumps(d, default=lambda o: list(o) if isinstance(o, tuple) else str(o)))


def frame_path(pattern: str, frame: int) -> str:
    """Output path of one frame: the last run of '#' in the file name of
    ``pattern`` becomes the frame number zero-padded to its length, a minus
    sign before a negative one (Blender's ``BLI_path_frame``: ``##`` with -3
    gives ``-03``); without '#' in the name, ``_####`` is inserted before the
    extension."""
    import re
    head = len(pattern) - len(os.path.basename(pattern))
    m = list(re.finditer(r"#+", pattern[head:]))
    if m:
        start, end = head + m[-1].start(), head + m[-1].end()
        digits = ("-" if frame < 0 else "") + str(abs(frame)).zfill(end - start)
        return pattern[:start] + digits + pattern[end:]
    stem, ext = os.path.splitext(pattern)
    return frame_path(f"{stem}_####{ext or '.exr'}", frame)


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

    ``seed_mode``: ``"animated"`` gives each frame the seed ``options.seed +
    frame`` (Cycles' animated seed), so samples reused from the previous frame
    are independent of the new frame's; ``"fixed"`` gives every frame
    ``options.seed`` (Cycles' default without the animated seed): the same
    noise pattern in every frame, which flickers less (docs/notes/seeds.md:
    temporal error 0.36-0.38x for uniform, 0.63-0.69x for oidn, 0.88-0.93x
    for lp at 1.03-1.08x its per-frame relMSE); refused with ``reproject``,
    whose reused samples would repeat the new frame's own.  ``"auto"``
    (default): fixed, animated with ``reproject``.  ``temporal``:
    - ``"none"``: frames are independent;
    - ``"reproject"``: after each frame's initial pass, the previous frame's
      accumulated samples are forward-reprojected into it where valid (Schalk
      2018 Sec. 3.2-3.3, core/reproject.py) and merged; reused samples do not
      count against the frame's budget; with ``var`` the sampler is Algorithm
      2's (``core.var.REPROJECT``: not-reprojected pixels first);
    - ``"lp"``: LP's temporal extension (Moon 2015 Sec. 6, core/temporal.py):
      per-pixel lambda-weighted RLS over frames on top of each frame's LP
      reconstruction (method must be ``lp``);
    - ``"blend"`` (core/history.py; any method): the frame's samples are
      averaged with the previous frames' samples, warped back, where both
      show the same surface and agree within their errors
      (``core.history.accumulate``, up to ``input_frames`` frames' worth),
      and the method samples and reconstructs those; with ``input_frames =
      1`` each frame's reconstruction is averaged with the previous frame's
      output instead (``core.history.blend``).
    ``history_params``: core.history.Params of ``blend``.
    """

    MODES = ("none", "reproject", "lp", "blend")
    SEED_MODES = ("auto", "animated", "fixed")
    #: modes refused with a fixed seed, and why (``auto`` gives them the animated seed)
    NEEDS_ANIMATED_SEED = {"reproject": "with a fixed seed the reused samples repeat the new frame's own",
                           "blend": "it averages frames whose noise must be independent"}

    def __init__(self, scene, view_layer, options: Options, out_pattern: str, frames: list,
                 reference_pattern: str | None = None, temporal: str = "none",
                 reproject_params: dict | None = None, temporal_params: dict | None = None,
                 history_params: dict | None = None,
                 view_layers=None, seed_mode: str = "auto", **job_kw):
        """``view_layers``: several view layers render each frame as a
        :class:`LayersJob` (default: ``[view_layer]``, a RenderJob)."""
        if temporal not in self.MODES:
            raise JobError(f"unknown temporal mode {temporal!r} (choose {', '.join(self.MODES)})")
        if seed_mode not in self.SEED_MODES:
            raise JobError(f"unknown seed mode {seed_mode!r} (choose {', '.join(self.SEED_MODES)})")
        if seed_mode == "fixed" and temporal in self.NEEDS_ANIMATED_SEED:
            raise JobError(f"--temporal {temporal} needs --seed-mode animated: "
                           f"{self.NEEDS_ANIMATED_SEED[temporal]}")
        self.seed_mode = seed_mode if seed_mode != "auto" else \
            ("animated" if temporal in self.NEEDS_ANIMATED_SEED else "fixed")
        self.view_layers = list(view_layers) if view_layers else [view_layer]
        if len(self.view_layers) > 1 and temporal != "none":
            raise JobError("--temporal works on one view layer: choose it with --view-layer")
        if temporal == "lp" and options.method != "lp":
            raise JobError("--temporal lp needs --method lp")
        self.scene, self.view_layer = scene, view_layer
        self.options, self.frames = options, list(frames)
        self.out_pattern, self.reference_pattern = out_pattern, reference_pattern
        self.temporal, self.job_kw = temporal, job_kw
        from ..core import history, reproject, temporal as temporal_mod
        from ..core.method import params_from_dict
        self.reproject_params = reproject.resolve_noise_limited(
            params_from_dict(reproject.Params, reproject_params), options.method)
        self.temporal_params = params_from_dict(temporal_mod.Params, temporal_params)
        self.history_params = history.resolve(params_from_dict(history.Params, history_params), options.method)
        self._history = None  # core.history.History of the previous frame (blend)
        self._input_history = None  # core.history.History of the previous frame's accumulated input (blend)
        self._accumulation = None   # core.history.Accumulated of the frame in progress (blend)
        self._warp_cache: dict = {}  # accumulate's cache (it holds the history it warped: one frame's)
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
            opts = dataclasses.replace(self.options, frame=f, seed=self.frame_seed(f))
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
            elif self.temporal == "blend":
                kw["reconstructor"] = self._blend
                if self.history_params.input_frames > 1:
                    kw["view_transform"] = self._accumulated
            if len(self.view_layers) > 1:
                self.job = LayersJob(self.scene, self.view_layers, opts, frame_path(self.out_pattern, f),
                                     reference=ref, **kw)
            else:
                self.job = RenderJob(self.scene, self.view_layer, opts, frame_path(self.out_pattern, f),
                                     reference=ref, **kw)
            for p in self.job.steps():
                p.message = f"frame {f} ({i + 1}/{len(self.frames)}): {p.message}"
                p.fraction = (i + p.fraction) / len(self.frames)
                yield p
            summary = yield from self._write_frame(i, f)
            self.summaries.append(summary)
            self._prev = (self.job.run.buffers, self.job.camera, self.job.run.method_state)
            yield summary

    def frame_seed(self, frame: int) -> int:
        """The Cycles seed of ``frame``'s renders (see ``seed_mode``)."""
        return self.options.seed + (frame if self.seed_mode == "animated" else 0)

    def _write_frame(self, i: int, frame: int):
        """The finished frame's outputs through its job's ``write_steps``:
        each pure part (EXR write, PNG encoding) is yielded as a Progress
        carrying its Work, so the UI's stepper runs it off the main thread
        (a plain consumer runs it inline when the generator resumes); returns
        the frame's summary."""
        steps = self.job.write_steps()
        fraction = (i + 1) / len(self.frames)
        while True:
            try:
                work = next(steps)
            except StopIteration as stop:
                return stop.value
            yield Progress("write", self.job.run.iteration, fraction,
                           f"frame {frame} ({i + 1}/{len(self.frames)}): {work.label}", work=work)

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
        from ..core import temporal
        static = run.method_reconstruction()
        center = self._backward_coordinates(run.buffers)
        res = temporal.step(self._temporal_state, run.buffers, self.temporal_params,
                            frame=self.job.options.frame, static=static, center=center)
        self._temporal_state = res.state
        out = res.method_result()
        out.info.update({f"temporal_{k}": v for k, v in res.info.items() if isinstance(v, (int, float))})
        if "center_fraction" in static.info:
            out.info["center_fraction"] = static.info["center_fraction"]
        return out

    def _backward_coordinates(self, buffers):
        """Where each pixel of this frame was in the previous one
        (``reproject.backward_coordinates``); None for the first frame."""
        from ..core import reproject
        if self._prev is None:
            return None
        prev_buf, prev_cam, _ = self._prev
        return reproject.backward_coordinates(reproject.Camera.from_render(prev_cam),
                                              reproject.Camera.from_render(self.job.camera),
                                              buffers, prev_buf.shape)

    def _blend(self, run):
        """Final reconstruction of a frame: the method's, of the view with the
        input history (:meth:`_accumulated`), which is then carried on; blended
        with the previous frame's output where the output blend is on
        (core/history.py)."""
        from ..core import history, reproject
        from ..core.method import MethodResult
        static = run.method_reconstruction()   # of the accumulated view, with input history
        acc = self._accumulation   # None without input history
        if acc is not None:
            self._input_history = acc.history
        blending = self._history is not None and self.history_params.max_frames > 1  # else blend() returns D
        coords = self._backward_coordinates(run.buffers) if blending else None
        camera = reproject.Camera.from_render(self.job.camera).position
        res = history.blend(static.image, static.error, history.Surface.from_buffers(run.buffers),
                            self._history, coords, camera, self.history_params)
        self._history = res.history
        info = dict(static.info)
        info.update({f"blend_{k}": float(v) for k, v in res.info.items()})
        if acc is not None:
            info.update({f"blend_{k}": float(v) for k, v in acc.info.items()})
        return MethodResult(res.image, res.error, info, static.dimension)

    def _accumulated(self, view):
        """The run's ``view_transform`` with input history: ``view`` with the
        previous frames' samples accumulated in (``core.history.accumulate``);
        the latest result is kept for :meth:`_blend`, which carries its
        history on."""
        from ..core import history, reproject
        coords = (lambda: self._backward_coordinates(view)) if self._input_history is not None else None
        camera = reproject.Camera.from_render(self.job.camera).position
        self._accumulation = history.accumulate(view, self._input_history, coords, camera, self.history_params,
                                                cache=self._warp_cache)
        return self._accumulation.buffers

    @property
    def run(self):
        """The run of the frame in progress (for the operator's stepper)."""
        return None if self.job is None else self.job.run

    def finish(self, partial: bool = False, reconstruct: bool = True) -> dict:
        """After the last frame: the range summary.  On a cancel: write the
        frame in progress as a partial result (``reconstruct``: see
        :meth:`RenderJob.output`), then the summary."""
        if partial and self.job is not None and self.job.run is not None and \
                self.job.run.buffers is not None and \
                (not self.summaries or self.summaries[-1]["out"] != self.job.out):
            self.summaries.append(self.job.finish(partial=True, reconstruct=reconstruct))
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
        if s and all("estimated_relmse" in x for x in s):
            out["estimated_relmse"] = float(np.mean([x["estimated_relmse"] for x in s]))
        return out


#: passes the reprojection needs (world position, specular share, object ids)
REPROJECT_PASSES = ("position", "glossy", "transmission", "glossy_color", "transmission_color", "object_index",
                    "normal", "depth")

"""Cycles executor: renders region tasks with border + crop + sample subsets.

Every setting touched is recorded first and restored on exit (also after an
error or a cancel), so the user's scene comes back exactly as it was.

Version paths (checked under the PyPI bpy 4.2, 4.5 and 5.0 modules; the tests
exercise each):
- Blender 4.4+: ``cycles.use_sample_subset``, ``sample_offset``,
  ``sample_subset_length``; ``cycles.samples`` must hold offset + length or the
  subset is cut short.
- Blender 4.2 / 4.3: only ``cycles.sample_offset``; ``cycles.samples`` is the
  number of samples rendered from that offset.
- Blender 5.0: ``image_settings.media_type = 'MULTI_LAYER_IMAGE'`` must be set
  before ``file_format = 'OPEN_EXR_MULTILAYER'`` (and ``'IMAGE'`` before PNG).
"""
from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile

import bpy
import numpy as np

from ..core import cryptomatte
from ..core import io as imageio
from ..core import regions
from ..core.pipeline import Work

#: feature name -> (EXR pass names summed, how to enable it)
PASS_SOURCES = {
    "albedo": (("Denoising Albedo",), "denoising"),
    "normal": (("Denoising Normal",), "denoising"),
    "depth": (("Denoising Depth",), "denoising"),
    "position": (("Position",), "use_pass_position"),
    "vector": (("Vector",), "use_pass_vector"),
    "object_index": (("IndexOB",), "use_pass_object_index"),
    "glossy": (("GlossDir", "GlossInd"), ("use_pass_glossy_direct", "use_pass_glossy_indirect")),
    "transmission": (("TransDir", "TransInd"),
                     ("use_pass_transmission_direct", "use_pass_transmission_indirect")),
    # passes a scene's compositor may read (addon/compositor.py), one Blender pass each;
    # "cycles." enables live on the view layer's Cycles settings
    "z": (("Depth",), "use_pass_z"),
    "mist": (("Mist",), "use_pass_mist"),
    "shading_normal": (("Normal",), "use_pass_normal"),
    "uv": (("UV",), "use_pass_uv"),
    "material_index": (("IndexMA",), "use_pass_material_index"),
    "diffuse_direct": (("DiffDir",), "use_pass_diffuse_direct"),
    "diffuse_indirect": (("DiffInd",), "use_pass_diffuse_indirect"),
    "diffuse_color": (("DiffCol",), "use_pass_diffuse_color"),
    "glossy_direct": (("GlossDir",), "use_pass_glossy_direct"),
    "glossy_indirect": (("GlossInd",), "use_pass_glossy_indirect"),
    "glossy_color": (("GlossCol",), "use_pass_glossy_color"),
    "transmission_direct": (("TransDir",), "use_pass_transmission_direct"),
    "transmission_indirect": (("TransInd",), "use_pass_transmission_indirect"),
    "transmission_color": (("TransCol",), "use_pass_transmission_color"),
    "volume_direct": (("VolumeDir",), "cycles.use_pass_volume_direct"),
    "volume_indirect": (("VolumeInd",), "cycles.use_pass_volume_indirect"),
    "emission": (("Emit",), "use_pass_emit"),
    "environment": (("Env",), "use_pass_environment"),
    "ambient_occlusion": (("AO",), "use_pass_ambient_occlusion"),
    "shadow_catcher": (("Shadow Catcher",), "cycles.use_pass_shadow_catcher"),
}


#: Blender 5.0's names of passes (in its EXR files and Render Layers sockets)
#: where they differ from 4.2-4.5's
PASS_NAMES_5 = {
    "IndexOB": "Object Index", "IndexMA": "Material Index",
    "DiffDir": "Diffuse Direct", "DiffInd": "Diffuse Indirect", "DiffCol": "Diffuse Color",
    "GlossDir": "Glossy Direct", "GlossInd": "Glossy Indirect", "GlossCol": "Glossy Color",
    "TransDir": "Transmission Direct", "TransInd": "Transmission Indirect",
    "TransCol": "Transmission Color", "VolumeDir": "Volume Direct", "VolumeInd": "Volume Indirect",
    "Emit": "Emission", "Env": "Environment", "AO": "Ambient Occlusion",
}


#: passes Cycles writes only in the render that holds sample 0 (a render with
#: sample_offset > 0 leaves them 0; checked with bpy 4.5): taken from that
#: render alone, never averaged with later ones (core.pipeline.merge_render)
SAMPLE_ZERO_PASSES = ("position", "object_index", "z", "material_index")


@contextlib.contextmanager
def quiet_stdout():
    """Silence Cycles' per-render log lines ("Fra: ... Sample 3/4", "Saved:")
    on the process's stdout while it renders; our progress lines stay readable.
    Set CYCLES_ADAPTIVE_VERBOSE=1 to keep them.  Where ``sys.stdout`` has no
    descriptor (pytest's capture, an embedding host) descriptor 1 is silenced,
    which is where Blender writes."""
    if os.environ.get("CYCLES_ADAPTIVE_VERBOSE"):
        yield
        return
    try:
        sys.stdout.flush()
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        fd = 1
    try:
        saved = os.dup(fd)
    except OSError:
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


class SceneError(Exception):
    """The scene cannot be rendered as asked; the message says why."""


def version() -> tuple:
    return tuple(bpy.app.version)


def check_scene(scene, view_layer=None) -> None:
    """Raise SceneError for a scene we cannot render (no silent fixes)."""
    if scene.render.engine != "CYCLES":
        raise SceneError(f"scene {scene.name!r} uses the {scene.render.engine} engine; "
                         "set Render Engine to Cycles (the add-on does not switch it for you)")
    if scene.camera is None:
        raise SceneError(f"scene {scene.name!r} has no active camera")
    w, h = full_size(scene)
    if w < 1 or h < 1:
        raise SceneError(f"resolution {w}x{h} is empty")
    if scene.render.use_border:
        x0, y0, x1, y1 = border_pixels(scene)
        if x1 <= x0 or y1 <= y0:
            raise SceneError("the render border lies outside the frame or is empty "
                             f"(min {scene.render.border_min_x:.3f},{scene.render.border_min_y:.3f} "
                             f"max {scene.render.border_max_x:.3f},{scene.render.border_max_y:.3f})")
    if view_layer is not None and not view_layer.use:
        raise SceneError(f"view layer {view_layer.name!r} is disabled for rendering")


def full_size(scene) -> tuple:
    """(width, height) in pixels after the resolution percentage (Blender's rule)."""
    r = scene.render
    return (r.resolution_x * r.resolution_percentage) // 100, \
           (r.resolution_y * r.resolution_percentage) // 100


def border_pixels(scene) -> tuple:
    """The scene's own render border as a pixel rectangle (x0, y0, x1, y1),
    top-left origin, clamped to the frame; the full frame when no border."""
    w, h = full_size(scene)
    r = scene.render
    if not r.use_border:
        return 0, 0, w, h
    cl = lambda v: min(max(float(v), 0.0), 1.0)
    border = {a: cl(getattr(r, a)) for a in ("border_min_x", "border_max_x", "border_min_y", "border_max_y")}
    return regions.pixels_from_border(border, w, h)


def alive(id_data) -> bool:
    """False once Blender freed the datablock ``id_data`` (another file was
    opened, or it was deleted): bpy then raises ReferenceError for the ID,
    while a struct inside it would point at freed memory."""
    try:
        id_data.name
    except ReferenceError:
        return False
    return True


class SettingsGuard:
    """Record attribute values, set new ones, restore them all on exit
    (skipping those of datablocks freed meanwhile: a run's generator closed
    after another file was opened must not touch the old one's memory)."""

    def __init__(self):
        self._saved = []

    def set(self, obj, attr, value):
        if not hasattr(obj, attr):
            return False
        self._saved.append((getattr(obj, "id_data", None), obj, attr, getattr(obj, attr)))
        if getattr(obj, attr) != value:
            setattr(obj, attr, value)
        return True

    def restore(self):
        for owner, obj, attr, value in reversed(self._saved):
            if owner is not None and not alive(owner):
                continue
            try:
                if getattr(obj, attr) != value:
                    setattr(obj, attr, value)
            except (AttributeError, TypeError, ReferenceError):
                pass
        self._saved.clear()


def set_exr_output(guard: SettingsGuard, settings) -> None:
    """Multilayer 32-bit EXR output, on every supported version, uncompressed:
    each render's file is read back once and deleted, and ZIP's compression
    cost up to 7 % of a one-sample 768x576 render (docs/notes/loop-speed.md)."""
    if hasattr(settings, "media_type"):  # Blender 5.0
        guard.set(settings, "media_type", "MULTI_LAYER_IMAGE")
    guard.set(settings, "file_format", "OPEN_EXR_MULTILAYER")
    guard.set(settings, "color_depth", "32")
    guard.set(settings, "exr_codec", "NONE")


def render_still(scene, view_layer, path: str, what: str = "", attributes: dict | None = None) -> dict:
    """Render ``scene`` / ``view_layer`` once with its current settings to
    ``path`` (``write_still``, Cycles' log silenced), read the file back and
    delete it: the passes dict of :func:`core.io.read_layers`.  SceneError
    (naming ``what``) when Cycles wrote no file.  ``attributes``: a dict
    that receives the file's string header attributes (Cryptomatte's)."""
    render_file(scene, view_layer, path, what)
    return read_still(path, view_layer.name, what, attributes)


def render_file(scene, view_layer, path: str, what: str = "") -> None:
    """The render half of :func:`render_still` (Blender's main thread):
    ``path`` holds the multilayer EXR afterwards, else SceneError."""
    scene.render.filepath = path
    with quiet_stdout():
        bpy.ops.render.render(write_still=True, scene=scene.name, layer=view_layer.name)
    if not os.path.isfile(path):
        raise SceneError("Cycles wrote no image" + (f" {what}" if what else ""))


def read_still(path: str, layer: str, what: str = "", attributes: dict | None = None) -> dict:
    """The reading half of :func:`render_still`: the passes of view layer
    ``layer`` in the EXR at ``path``, which is then deleted.  No Blender
    data is touched, so any thread may call it."""
    # a multilayer file of a scene with several view layers holds each (the others empty): read ours
    try:
        passes, meta = imageio.read_layers(path, layer)
    except imageio.ImageFileError as exc:
        raise SceneError(f"Cycles wrote no layer {layer!r}" + (f" {what}" if what else "")
                         + f" ({exc})") from None
    if attributes is not None:
        attributes.update(meta["attributes"])
    os.unlink(path)
    return passes


#: view-layer switch -> Cryptomatte pass base name (layers <base>00, 01, ...:
#: R=id0, G=cov0, B=id1, A=cov1; same names under 4.2, 4.5 and 5.0, which
#: write them in every border render, also with sample_offset > 0, with
#: coverage the fraction of that render's samples: core/cryptomatte.py)
CRYPTOMATTE_SWITCHES = {"use_pass_cryptomatte_object": "CryptoObject",
                        "use_pass_cryptomatte_material": "CryptoMaterial",
                        "use_pass_cryptomatte_asset": "CryptoAsset"}


def cryptomatte_bases(view_layer) -> tuple:
    """The Cryptomatte pass base names ``view_layer`` has on."""
    return tuple(b for a, b in CRYPTOMATTE_SWITCHES.items() if getattr(view_layer, a, False))


def cryptomatte_ranks(passes: dict, bases, attributes: dict) -> dict:
    """``{base: (ids uint32 (h, w, L), coverage (h, w, L), header)}`` from a
    render's passes: its layers ``<base>00``, ``01``, ... in order and its
    ``cryptomatte/<key>/...`` header attributes (``header``: those of the
    key whose ``name`` ends with ``.<base>``, keys without the prefix).
    SceneError when a base's layers are missing."""
    out = {}
    for base in bases:
        names = sorted(k for k in passes if k.startswith(base) and k[len(base):].isdigit())
        if not names:
            raise SceneError(f"Cryptomatte pass {base!r} missing from the render (have {sorted(passes)})")
        ids, cov = cryptomatte.layers_to_ranks([passes[n] for n in names])
        header = {}
        for key, value in attributes.items():
            parts = key.split("/")
            if len(parts) == 3 and parts[0] == "cryptomatte" and \
                    attributes.get(f"cryptomatte/{parts[1]}/name", "").endswith("." + base):
                header[parts[2]] = value
        out[base] = (ids, cov, header)
    return out


class CyclesExecutor:
    """Render RegionTasks of one scene / view layer / frame with Cycles.

    Use as a context manager: entering configures the scene, leaving restores
    it.  Pixel coordinates of tasks are relative to the image domain, which is
    the scene's own border when it has one (the add-on renders only what the
    user would render), else the full frame.
    """

    def __init__(self, scene, view_layer, features=(), seed: int | None = None, tmpdir=None):
        check_scene(scene, view_layer)
        self.scene = scene
        self.view_layer = view_layer
        self.features = tuple(f for f in features if f != "alpha")
        for f in self.features:
            if f not in PASS_SOURCES:
                raise SceneError(f"unknown pass {f!r}")
        if "vector" in self.features and scene.render.use_motion_blur:
            raise SceneError("the Vector pass is not available with motion blur on")
        self.seed = seed
        self.full_w, self.full_h = full_size(scene)
        self.domain = border_pixels(scene)
        self.user_crop = bool(scene.render.use_border and scene.render.use_crop_to_border)
        x0, y0, x1, y1 = self.domain
        self.size = (y1 - y0, x1 - x0)
        self._own_tmp = tmpdir is None
        self.tmpdir = tmpdir or tempfile.mkdtemp(prefix="cycles-adaptive-")
        self.guard = SettingsGuard()
        self.renders = 0
        self._reads: list = []           # render_deferred's reads (Works), some maybe not run yet
        self.hold = None             # hold_samples_at: the run's one final count
        self.pattern = None          # the sampling pattern the renders use (after entering)
        self.initial_pattern = None  # the pattern before release_hold, if it was called

    # -------------------------------------------------------------- lifecycle
    def hold_samples_at(self, count: int) -> None:
        """Before entering: every pixel of this run ends with samples ``[0,
        count)`` (uniform sampling at a known count), so on Blender 4.4+ the
        renders keep the scene's own sampling pattern with ``samples`` held at
        ``count`` (each subset through ``sample_subset_length``): the merged
        subsets are then that pattern's ``count``-spp render, Blue Noise's
        count-tuned table included (checked with bpy 4.5: equal within
        float32 rounding; with ``samples = offset + length`` they are not).
        Elsewhere (4.2 / 4.3, or not called) Tabulated Sobol, whose subsets of
        any length merge exactly."""
        self.hold = max(1, int(count))

    def release_hold(self) -> None:
        """End a held count (``hold_samples_at``): ``auto`` chose adaptive
        sampling after an initial pass rendered at the held count.  Renders
        from now on use Tabulated Sobol, whose samples ``[offset, offset +
        length)`` do not depend on the count; the initial pass keeps the
        scene pattern's first samples (``initial_pattern`` says which).
        Before entering it only drops the hold."""
        if self.hold is None:
            return
        self.hold = None
        if self.pattern is None:  # not entered yet: _configure picks Tabulated Sobol
            return
        self.initial_pattern = self.pattern
        self._count_independent_pattern()

    def _count_independent_pattern(self) -> None:
        """Tabulated Sobol (restored on exit), and :attr:`pattern` updated."""
        c = self.scene.cycles
        try:
            self.guard.set(c, "sampling_pattern", "TABULATED_SOBOL")
        except TypeError:  # a version without it: its only pattern is count-independent
            pass
        self.pattern = str(getattr(c, "sampling_pattern", ""))

    def __enter__(self):
        try:
            self._configure()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def close(self):
        # a deferred read not yet done (a merge still to come): read now,
        # before the files go; its consumer gets the arrays (or the error,
        # which the Work keeps)
        for work in self._reads:
            work.run()
        self._reads = []
        self.guard.restore()
        frame = getattr(self, "_frame", None)
        if frame is not None and alive(self.scene) and self.scene.frame_current != frame:
            self.scene.frame_set(frame)
        if self._own_tmp:
            shutil.rmtree(self.tmpdir, ignore_errors=True)

    def _configure(self):
        g, s = self.guard, self.scene
        r, c, vl = s.render, s.cycles, self.view_layer
        g.set(r, "use_compositing", False)
        g.set(r, "use_sequencer", False)
        # a fresh session: switching persistent data off frees the last one,
        # whose blue-noise table was built for its first render's sample count
        g.set(r, "use_persistent_data", False)
        g.set(r, "use_persistent_data", True)
        g.set(r, "use_single_layer", True)
        # and the other view layers off: Blender 5.0 fails to write the second
        # single-layer render of a file with several layers ("Error writing
        # render result"; checked with 5.0.1), not when only one is enabled
        for other in s.view_layers:
            if other != vl and other.use:
                g.set(other, "use", False)
        g.set(r, "use_border", True)
        g.set(r, "use_crop_to_border", True)
        for attr in ("border_min_x", "border_max_x", "border_min_y", "border_max_y"):
            g.set(r, attr, getattr(r, attr))
        g.set(r, "filepath", r.filepath)
        g.set(r, "use_file_extension", True)
        set_exr_output(g, r.image_settings)
        g.set(c, "use_adaptive_sampling", False)
        g.set(c, "use_denoising", False)
        g.set(c, "time_limit", 0.0)
        if self.seed is not None:
            g.set(c, "seed", int(self.seed))
            g.set(c, "use_animated_seed", False)
        # Blue-noise patterns (the 'AUTOMATIC' default of 4.2+) depend on the
        # total sample count and, with persistent data, on earlier renders:
        # subsets of different lengths then do not merge.  Tabulated Sobol
        # indexes samples independently of the count: exact merges (tested).
        # A count held for the whole run (hold_samples_at) keeps the scene's own pattern.
        if self.hold is None or not hasattr(c, "use_sample_subset"):
            self.hold = None
            self._count_independent_pattern()
        else:
            self.pattern = str(getattr(c, "sampling_pattern", ""))
        g.set(c, "samples", c.samples)
        g.set(c, "sample_offset", c.sample_offset)
        if hasattr(c, "use_sample_subset"):
            g.set(c, "use_sample_subset", True)
            g.set(c, "sample_subset_length", c.sample_subset_length)
        self._frame = s.frame_current
        if bpy.context.window is not None and bpy.context.view_layer != vl:
            g.set(bpy.context.window, "view_layer", vl)
        self._protect_render_result()
        g.set(vl, "use_pass_combined", True)
        need_denoise = any(PASS_SOURCES[f][1] == "denoising" for f in self.features)
        g.set(vl.cycles, "denoising_store_passes", need_denoise)
        for f in self.features:
            enable = PASS_SOURCES[f][1]
            if enable == "denoising":
                continue
            for attr in (enable if isinstance(enable, tuple) else (enable,)):
                g.set(*_pass_switch(vl, attr), True)

    def _protect_render_result(self):
        protect_render_result(self.guard)

    def drop_passes(self, names) -> None:
        """Stop rendering and reading the feature passes ``names`` (found to
        carry no information): they leave the result, and the view layer
        passes no remaining feature needs are switched off (Cycles' denoising
        data, albedo + normal + depth, is one switch: off only when all three
        are dropped).  The guard restores the scene's settings on exit."""
        names = set(names)
        dropped = [f for f in self.features if f in names]
        self.features = tuple(f for f in self.features if f not in names)
        needed = set()
        for f in self.features:
            enable = PASS_SOURCES[f][1]
            needed.update(enable if isinstance(enable, tuple) else (enable,))
        for f in dropped:
            enable = PASS_SOURCES[f][1]
            for attr in (enable if isinstance(enable, tuple) else (enable,)):
                if attr in needed:
                    continue
                if attr == "denoising":
                    self.guard.set(self.view_layer.cycles, "denoising_store_passes", False)
                else:
                    self.guard.set(*_pass_switch(self.view_layer, attr), False)

    # ----------------------------------------------------------------- render
    def render(self, task):
        """Render one task; returns (rgba (h, w, 4) float64, features dict)."""
        return self.render_deferred(task)()

    def render_deferred(self, task):
        """Render one task (main thread) and leave its file to be read back
        later: a call (``Work.result`` of :class:`core.pipeline.Work`: read
        once, from any thread, its error kept for every caller) that returns
        what :meth:`render` does.  The loop calls it on the merge's thread, so reading and
        converting the passes (~0.07 s per 0.6-megapixel render with the
        guides) hides behind the next render; :meth:`close` reads what is
        still unread before deleting the files."""
        s, r, c = self.scene, self.scene.render, self.scene.cycles
        if s.frame_current != task.frame:
            s.frame_set(task.frame)
        dx0, dy0 = self.domain[0], self.domain[1]
        x0, y0, x1, y1 = task.x0 + dx0, task.y0 + dy0, task.x1 + dx0, task.y1 + dy0
        for attr, value in regions.border_from_pixels(x0, y0, x1, y1, self.full_w, self.full_h).items():
            setattr(r, attr, float(value))
        if hasattr(c, "use_sample_subset"):  # 4.4+
            c.samples = max(int(task.offset + task.samples), self.hold or 0)
            c.sample_offset = int(task.offset)
            c.sample_subset_length = int(task.samples)
        else:  # 4.2 / 4.3
            c.samples = int(task.samples)
            c.sample_offset = int(task.offset)
        path = os.path.join(self.tmpdir, f"task{self.renders:06d}.exr")
        self.renders += 1
        render_file(s, self.view_layer, path, f"for {task}")
        # what the read needs from Blender's data, taken now (the read may run on another thread)
        layer, features, bases = self.view_layer.name, self.features, cryptomatte_bases(self.view_layer)
        work = Work(lambda: _read_task(path, layer, task, (y1 - y0, x1 - x0), features, bases),
                    f"reading {os.path.basename(path)}")
        self._reads = [w for w in self._reads if not w.done] + [work]
        return work.result

    def camera_info(self, frame: int) -> dict:
        """Camera of ``frame`` as numpy arrays (for reprojection):
        ``world_to_camera`` (4, 4), ``projection`` (4, 4) camera -> clip space
        (Blender's ``calc_matrix_camera`` for the full frame), ``position`` (3,)
        in world space, ``width``/``height`` of the full frame and ``domain``
        (x0, y0, x1, y1) of the rendered region in it."""
        s = self.scene
        if s.frame_current != frame:
            s.frame_set(frame)
        cam = s.camera
        depsgraph = bpy.context.evaluated_depsgraph_get()
        cam_eval = cam.evaluated_get(depsgraph)
        r = s.render
        proj = cam_eval.calc_matrix_camera(depsgraph, x=self.full_w, y=self.full_h,
                                           scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y)
        mw = cam_eval.matrix_world
        return {"world_to_camera": np.array(mw.inverted(), np.float64),
                "projection": np.array(proj, np.float64),
                "position": np.array(mw.translation, np.float64),
                "width": self.full_w, "height": self.full_h, "domain": tuple(self.domain),
                "frame": frame}

    # --------------------------------------------------------------- preview
    def write_preview(self, rgba: np.ndarray, path: str) -> None:
        """PNG in the scene's view transform (Blender applies it on save)."""
        write_preview(self.scene, rgba, path)


def _read_task(path: str, layer: str, task, size: tuple, features: tuple, bases: tuple):
    """(rgba (h, w, 4) float64, features dict) of one task's render at
    ``path`` (deleted after): :meth:`CyclesExecutor.render`'s result.  No
    Blender data is touched."""
    attributes = {}
    passes = read_still(path, layer, f"for {task}", attributes)
    color = passes.get("Combined")
    if color is None or color.shape[:2] != tuple(size):
        got = None if color is None else color.shape[:2]
        raise SceneError(f"border render gave {got}, expected {tuple(size)} for {task}")
    feats = {}
    for f in features:
        if f in SAMPLE_ZERO_PASSES and task.offset > 0:
            continue  # not written by this render: the merge keeps the value of sample 0's
        names = [n if n in passes else PASS_NAMES_5.get(n, n) for n in PASS_SOURCES[f][0]]
        missing = [n for n in names if n not in passes]
        if missing:
            raise SceneError(f"pass {missing[0]!r} missing from the render (have {sorted(passes)})")
        feats[f] = sum(passes[n].astype(np.float64) for n in names)
    if bases:  # ranked ids, not a mean: merged apart (core.pipeline.merge_cryptomatte)
        feats["cryptomatte"] = cryptomatte_ranks(passes, bases, attributes)
    return color.astype(np.float64), feats


def _pass_switch(view_layer, attr: str) -> tuple:
    """``(owner, name)`` of a pass's enable switch: ``"cycles.X"`` lives on
    the view layer's Cycles settings, anything else on the view layer."""
    if attr.startswith("cycles."):
        return view_layer.cycles, attr[len("cycles."):]
    return view_layer, attr


def protect_render_result(guard: SettingsGuard) -> None:
    """Render into a Render Result slot of our own ("Cycles Adaptive") so the
    user's last render survives; ``guard`` restores the active slot."""
    rr = bpy.data.images.get("Render Result")
    slots = getattr(rr, "render_slots", None) if rr is not None else None
    if not slots:
        return
    idx = next((i for i, sl in enumerate(slots) if sl.name == "Cycles Adaptive"), None)
    if idx is None:
        slots.new(name="Cycles Adaptive")
        idx = len(slots) - 1
    guard.set(slots, "active_index", idx)


def write_preview(scene, rgba: np.ndarray, path: str) -> None:
    """Save (H, W, 3|4) scene-linear pixels as an 8-bit PNG through Blender's
    colour management (the scene's view transform, look, exposure, gamma),
    atomically."""
    from .display import float_pixels
    flat, w, h = float_pixels(rgba)
    img = bpy.data.images.new("cycles_adaptive_preview", w, h, alpha=True, float_buffer=True)
    guard = SettingsGuard()
    try:
        with imageio.atomic_path(path, ".png") as tmp:
            img.pixels.foreach_set(flat)
            st = scene.render.image_settings
            if hasattr(st, "media_type"):
                guard.set(st, "media_type", "IMAGE")
            guard.set(st, "file_format", "PNG")
            guard.set(st, "color_mode", "RGBA")
            guard.set(st, "color_depth", "8")
            img.save_render(tmp, scene=scene)
    finally:
        guard.restore()
        bpy.data.images.remove(img)

"""Scene properties of the add-on (``scene.cycles_adaptive``).

The per-method parameter groups are generated from each method's ``Params``
dataclass (core/<method>.py), so every parameter a method has appears in the
panel with its paper default and its tooltip (the field's ``help`` metadata,
which says what it trades).
"""
from __future__ import annotations

from dataclasses import MISSING, fields

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty,
                       StringProperty)

from ..core import methods
from ..core.pipeline import Options, option_fields

METHOD_ITEMS = [
    ("auto", "Automatic", "Chooses per scene, from the first pass's samples, the reconstruction "
     "(sample mean, OIDN, LP, AWR, RHF) and sampling with the best predicted speed for its error"),
    ("var", "Variance (Schalk 2018)", "Welford variance sampler with min/max spp; no reconstruction"),
    ("awr", "Adaptive wavelets (Overbeck 2009)", "Wavelet-domain sampling and soft-threshold reconstruction"),
    ("lp", "Linear predictions (Moon 2015)", "Local linear models over features with adaptive windows"),
    ("rhf", "Robust high-order function (Liu 2018)", "First-order regression with prefiltered features"),
    ("oidn", "OIDN in the loop", "OpenImageDenoise as the reconstruction, samples where its dual-buffer "
     "error estimate is high"),
    ("uniform", "Uniform", "Plain Cycles at the same sample count (baseline)"),
]

_param_classes: dict = {}

#: options of a path property that may start with "//" (the .blend's folder):
#: Blender 5.0 warns on such a path without the flag, which 4.2 does not know
PATH_OPTIONS = {"PATH_SUPPORTS_BLEND_RELATIVE"} if bpy.app.version >= (4, 5, 0) else set()


def _label(f) -> str:
    return f.metadata.get("label") or f.name.replace("_", " ").title()


def prop_for(f):
    """A bpy property from a ``param()`` dataclass field (method Params or the
    loop's Options): its default (the metadata's ``ui_default`` where the
    panel wants another than the CLI), ``help`` as tooltip, ``min``/``max``
    (the metadata's ``ui_min``, ``soft_max``, ``subtype`` where given)."""
    md = f.metadata
    default = md.get("ui_default", f.default if f.default is not MISSING else None)
    desc = md.get("help", f.name)
    name = _label(f)
    lo = md.get("ui_min", md.get("min"))
    hi = md.get("max")
    if isinstance(default, bool):
        return BoolProperty(name=name, description=desc, default=default)
    if isinstance(default, (int, float)):
        num = int if isinstance(default, int) else float
        kw = {k: num(v) for k, v in (("min", lo), ("max", hi), ("soft_max", md.get("soft_max")))
              if v is not None}
        if md.get("subtype"):
            kw["subtype"] = md["subtype"]
        if num is int:
            return IntProperty(name=name, description=desc, default=default, **kw)
        return FloatProperty(name=name, description=desc, default=default, precision=4, **kw)
    choices = md.get("choices")
    if choices:
        return EnumProperty(name=name, description=desc, default=default,
                            items=[(c, c, desc) for c in choices])
    return StringProperty(name=name, description=desc, default=str(default or ""))


def _param_group(method: str):
    ann = {}
    try:
        for f in methods.param_fields(method):
            ann[f.name] = prop_for(f)
    except ImportError:
        pass
    return type(f"CYCLESADAPTIVE_PG_params_{method}", (bpy.types.PropertyGroup,),
                {"__annotations__": ann})


def method_params(settings, method: str) -> dict:
    """The panel's parameter values of ``method`` as a dict for Params."""
    group = getattr(settings, f"params_{method}", None)
    cls = _param_classes.get(method)
    if group is None or cls is None:
        return {}
    return {k: getattr(group, k) for k in cls.__annotations__}


def budget_spp(scene) -> float:
    """The run's mean samples per pixel: Cycles' own Render "Max Samples"
    (``scene.cycles.samples``) with "Use Scene Samples", else the panel's."""
    s = scene.cycles_adaptive
    return float(scene.cycles.samples) if s.use_scene_samples else float(s.spp)


def options(scene):
    """The loop's Options from the panel's settings of ``scene`` (the same
    fields the CLI's flags set; method parameters from their groups)."""
    s = scene.cycles_adaptive
    values = {f.name: getattr(s, f.name) for f in option_fields("ui")}
    values["spp"] = budget_spp(scene)
    return Options(method=s.method, frame=scene.frame_current, params=method_params(s, s.method), **values)


class CYCLESADAPTIVE_PG_settings(bpy.types.PropertyGroup):
    """Panel settings: the loop's Options (generated, see ``register``) plus
    output, frame range and progress."""

    method: EnumProperty(name="Method", items=METHOD_ITEMS, default=Options().method,
                         description="Adaptive method: where to put samples and how to reconstruct")
    output_path: StringProperty(name="Output", subtype="FILE_PATH", default="",
                                options=PATH_OPTIONS,
                                description="Multilayer EXR written after the run (a PNG preview "
                                            "goes beside it); empty: the scene's Output path, "
                                            "frame-numbered, with the method's suffix")
    frame_range: BoolProperty(name="Frame Range", default=False,
                              description="Render the scene's frame range (one output per frame, "
                                          "#### in the output path is the frame number)")
    temporal: EnumProperty(name="Reuse Frames", default="none",
                           items=[("none", "Independent", "Every frame from scratch"),
                                  ("reproject", "Reproject", "Reuse the previous frame's samples where "
                                   "reprojection is valid (Schalk 2018): fewer samples per frame, "
                                   "slight bias on moving highlights"),
                                  ("lp", "LP temporal", "LP's regression over frames (Moon 2015 "
                                   "Sec. 6; method LP): steadier animation, more memory"),
                                  ("blend", "Blend", "Average each frame's result with the previous "
                                   "frame's where they show the same surface and agree within their "
                                   "estimated errors (any method): less flicker on static parts")],
                           description="How frames of a range reuse earlier samples")
    seed_mode: EnumProperty(name="Noise Pattern", default="auto",
                            items=[("auto", "Auto", "Fixed, or Animated with Reproject (measured: fixed "
                                    "flickers less at about the same per-frame error)"),
                                   ("animated", "Animated", "A new seed every frame (Cycles' animated "
                                    "seed): independent noise per frame"),
                                   ("fixed", "Fixed", "The same seed every frame: the same noise pattern, "
                                    "less flicker where the image does not move (not with Reproject)")],
                            description="The Cycles seed of each frame of a range")
    overwrite: BoolProperty(name="Overwrite", default=False,
                            description="Replace an existing output file")
    use_compositor: BoolProperty(name="Compositor", default=True,
                                 description="Run the scene's compositor on the result when the scene "
                                             "composites its renders (the raw passes stay in the EXR)")
    exr_depth: EnumProperty(name="EXR Depth", default="scene",
                            items=[("scene", "As Output", "The Output properties' Color Depth when they "
                                    "save OpenEXR, else Half"),
                                   ("half", "Float (Half)", "Result, composite, error and variance in "
                                    "16-bit float: about half the file (the statistics a later denoise "
                                    "reads stay full float)"),
                                   ("full", "Float (Full)", "Every pass in 32-bit float")],
                            description="How the output EXR stores the result passes")
    exr_contents: EnumProperty(name="EXR Contents", default="full",
                               items=[("full", "All Passes", "Every pass a later denoise needs to re-run "
                                       "any method on this render"),
                                      ("image", "Image Only", "The result, composite, error, samples per "
                                       "pixel and feature passes: about a third of the file; no later "
                                       "denoise")],
                               description="Which passes the output EXR keeps")
    use_scene_samples: BoolProperty(name="Use Scene Samples", default=False,
                                    description="Take the budget (mean samples per pixel) from Cycles' "
                                                "Render Max Samples instead of Samples per Pixel below")
    # preferences applied once (addon/preferences.py: apply_defaults)
    configured: BoolProperty(default=False)
    # summary of the last run, drawn by the panel
    has_result: BoolProperty(default=False)
    last_method: StringProperty(name="Method", default="")
    last_spp: FloatProperty(name="Samples per Pixel", default=0.0, description="Mean samples per pixel rendered")
    last_seconds: FloatProperty(name="Time", default=0.0,
                                description="Wall time of the run, outputs included")
    last_error: FloatProperty(name="Estimated Error", default=0.0, precision=5,
                              description="relMSE predicted by the run's own error estimate (no reference)")
    last_chosen: StringProperty(name="Chosen", default="",
                                description="What Automatic chose for the last run, and why")
    last_reconstructed: BoolProperty(name="Reconstructed", default=True,
                                     description="False after a cancel: the output is the sample mean")
    # progress, shown by the panel while the operator runs
    running: BoolProperty(default=False, options={"SKIP_SAVE"})
    progress: FloatProperty(default=0.0, min=0.0, max=1.0, subtype="FACTOR", options={"SKIP_SAVE"})
    status: StringProperty(default="", options={"SKIP_SAVE"})


def register():
    for f in option_fields("ui"):
        CYCLESADAPTIVE_PG_settings.__annotations__[f.name] = prop_for(f)
    for m in list(methods.METHODS) + list(methods.STAGES):
        cls = _param_group(m)
        _param_classes[m] = cls
        bpy.utils.register_class(cls)
        CYCLESADAPTIVE_PG_settings.__annotations__[f"params_{m}"] = PointerProperty(type=cls)
    bpy.utils.register_class(CYCLESADAPTIVE_PG_settings)
    bpy.types.Scene.cycles_adaptive = PointerProperty(type=CYCLESADAPTIVE_PG_settings)


def unregister():
    del bpy.types.Scene.cycles_adaptive
    bpy.utils.unregister_class(CYCLESADAPTIVE_PG_settings)
    for m, cls in reversed(list(_param_classes.items())):
        bpy.utils.unregister_class(cls)
        CYCLESADAPTIVE_PG_settings.__annotations__.pop(f"params_{m}", None)
    _param_classes.clear()

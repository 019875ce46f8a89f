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

METHOD_ITEMS = [
    ("var", "Variance (Schalk 2018)", "Welford variance sampler with min/max spp; no reconstruction"),
    ("awr", "Adaptive wavelets (Overbeck 2009)", "Wavelet-domain sampling and soft-threshold reconstruction"),
    ("lp", "Linear predictions (Moon 2015)", "Local linear models over features with adaptive windows"),
    ("rhf", "Robust high-order function (Liu 2018)", "First-order regression with prefiltered features"),
    ("uniform", "Uniform", "Plain Cycles at the same sample count (baseline)"),
]

_param_classes: dict = {}


def _prop_for(f, method):
    default = f.default if f.default is not MISSING else None
    desc = f.metadata.get("help", f.name)
    name = f.name.replace("_", " ").title()
    lo, hi = f.metadata.get("min"), f.metadata.get("max")
    if isinstance(default, bool):
        return BoolProperty(name=name, description=desc, default=default)
    if isinstance(default, int):
        kw = {}
        if lo is not None:
            kw["min"] = int(lo)
        if hi is not None:
            kw["max"] = int(hi)
        return IntProperty(name=name, description=desc, default=default, **kw)
    if isinstance(default, float):
        kw = {}
        if lo is not None:
            kw["min"] = float(lo)
        if hi is not None:
            kw["max"] = float(hi)
        return FloatProperty(name=name, description=desc, default=default, precision=4, **kw)
    choices = f.metadata.get("choices")
    if choices:
        return EnumProperty(name=name, description=desc, default=default,
                            items=[(c, c, desc) for c in choices])
    return StringProperty(name=name, description=desc, default=str(default or ""))


def _param_group(method: str):
    ann = {}
    try:
        for f in methods.param_fields(method):
            ann[f.name] = _prop_for(f, method)
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


class CYCLESADAPTIVE_PG_settings(bpy.types.PropertyGroup):
    method: EnumProperty(name="Method", items=METHOD_ITEMS, default="lp",
                         description="Adaptive method: where to put samples and how to reconstruct")
    spp: FloatProperty(name="Samples per Pixel", default=16.0, min=1.0, soft_max=4096.0,
                       description="Mean samples per pixel of the whole run (initial pass included). "
                                   "More: slower, more accurate")
    initial_spp: IntProperty(name="Initial Samples", default=4, min=1, soft_max=64,
                             description="Samples per pixel of the first, uniform pass. More: better "
                                         "first error estimate, less budget left to adapt")
    subsets: IntProperty(name="Subsets", default=4, min=1, max=64,
                         description="Sample subsets of the first pass; the variance estimate has "
                                     "subsets-1 degrees of freedom. More: steadier estimate, a few "
                                     "more full-frame renders")
    iterations: IntProperty(name="Iterations", default=4, min=1, max=64,
                            description="Adaptive iterations after the first pass. More: sample map "
                                        "follows the error more closely, more per-render overhead")
    max_pixel_share: FloatProperty(name="Max Pixel Share", default=2.0, min=0.0, soft_max=64.0,
                                   description="Most samples one pixel may get in an iteration, as a "
                                               "multiple of the iteration's mean (0: no cap). Lower "
                                               "spreads samples evenly, higher follows the map's peaks")
    guard_z: FloatProperty(name="Consistency Guard", default=3.0, min=0.0, soft_max=10.0,
                           description="Pixels whose reconstruction is more than this many standard "
                                       "errors from their own samples keep their sample mean (0: off). "
                                       "Lower trusts the reconstruction less")
    seed: IntProperty(name="Seed", default=0, min=0, description="Cycles seed of the run")
    max_seconds: FloatProperty(name="Time Limit", default=0.0, min=0.0, subtype="TIME_ABSOLUTE",
                               description="Stop sampling after this many seconds (0: no limit)")
    output_path: StringProperty(name="Output", subtype="FILE_PATH", default="//adaptive.exr",
                                description="Multilayer EXR written after the run (a PNG preview "
                                            "goes beside it)")
    frame_range: BoolProperty(name="Frame Range", default=False,
                              description="Render the scene's frame range (one output per frame, "
                                          "#### in the output path is the frame number)")
    temporal: EnumProperty(name="Reuse Frames", default="none",
                           items=[("none", "Independent", "Every frame from scratch"),
                                  ("reproject", "Reproject", "Reuse the previous frame's samples where "
                                   "reprojection is valid (Schalk 2018): fewer samples per frame, "
                                   "slight bias on moving highlights"),
                                  ("lp", "LP temporal", "LP's regression over frames (Moon 2015 "
                                   "Sec. 6; method LP): steadier animation, more memory")],
                           description="How frames of a range reuse earlier samples")
    overwrite: BoolProperty(name="Overwrite", default=False,
                            description="Replace an existing output file")
    # progress, shown by the panel while the operator runs
    running: BoolProperty(default=False, options={"SKIP_SAVE"})
    progress: FloatProperty(default=0.0, min=0.0, max=1.0, subtype="FACTOR", options={"SKIP_SAVE"})
    status: StringProperty(default="", options={"SKIP_SAVE"})


def register():
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

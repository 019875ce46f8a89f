"""Render Properties panels, under Cycles' Sampling panel: "Cycles Adaptive
Render" (method, budget against the scene's samples, output, the button,
progress, the last run's summary) and its collapsed "Advanced" sub-panel (loop
settings and the method's parameters, labelled from each field's ``label``
metadata).

Cycles' Sampling panel is ``CYCLES_RENDER_PT_sampling`` in Blender 4.2, 4.5
and 5.0 (scripts/addons_core/cycles/ui.py); where it is not registered (Cycles
disabled) the panel stands on its own in Render Properties.
"""
from __future__ import annotations

import bpy

from ..core.pipeline import option_fields
from .props import METHOD_ITEMS, _param_classes

#: Cycles' Sampling panel (the same idname in Blender 4.2 to 5.0)
CYCLES_SAMPLING = "CYCLES_RENDER_PT_sampling"

#: loop settings on the main panel; every other UI setting is "Advanced"
MAIN_OPTIONS = ("spp", "max_seconds")


def parent_id() -> str:
    """Cycles' Sampling panel when registered, else "" (a top-level panel)."""
    return CYCLES_SAMPLING if hasattr(bpy.types, CYCLES_SAMPLING) else ""


def method_label(method: str) -> str:
    return next((label for key, label, _ in METHOD_ITEMS if key == method), method)


def param_groups(settings) -> list:
    """(title, property group, field names) of the parameter groups the
    current settings use: the method's, and the frame-range stage's."""
    keys = [settings.method]
    if settings.frame_range and settings.temporal != "none":
        keys.append({"reproject": "reproject", "lp": "temporal", "blend": "history"}[settings.temporal])
    titles = {"reproject": "Reprojection", "temporal": "LP Temporal", "history": "Frame Blend"}
    out = []
    for key in keys:
        cls = _param_classes.get(key)
        group = getattr(settings, f"params_{key}", None)
        if cls is not None and group is not None and cls.__annotations__:
            out.append((titles.get(key) or method_label(key), group, list(cls.__annotations__)))
    return out


def summary_lines(settings) -> list:
    """The last run's summary as short lines for the panel."""
    if not settings.has_result:
        return []
    method = method_label(settings.last_method)
    if settings.last_chosen:  # auto: the method it chose
        method += f": {settings.last_chosen}"
    lines = [method,
             f"{settings.last_spp:.1f} spp in {settings.last_seconds:.1f} s",
             f"Estimated relMSE {settings.last_error:.4g}"]
    if not settings.last_reconstructed:
        lines.append("Cancelled: sample mean, not reconstructed")
    return lines


class _RenderPanel:
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    COMPAT_ENGINES = {"CYCLES"}

    @classmethod
    def poll(cls, context):
        return context.scene is not None and context.scene.render.engine == "CYCLES"


class CYCLESADAPTIVE_PT_panel(_RenderPanel, bpy.types.Panel):
    bl_label = "Cycles Adaptive Render"

    def draw(self, context):
        from .preferences import apply_to_scene_later
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        scene = context.scene
        s = scene.cycles_adaptive
        if not s.configured:
            apply_to_scene_later(scene.name)
        col = layout.column()
        col.enabled = not s.running
        col.prop(s, "method")
        col.prop(s, "use_scene_samples")
        row = col.row()
        row.enabled = not s.use_scene_samples
        row.prop(s, "spp")
        col.label(text=f"Cycles Render Max Samples: {scene.cycles.samples}", icon="INFO")
        col.prop(s, "max_seconds")
        col.prop(s, "output_path")
        col.prop(s, "exr_depth")
        col.prop(s, "exr_contents")
        col.prop(s, "frame_range")
        if s.frame_range:
            col.prop(s, "temporal")
            col.prop(s, "seed_mode")
        col.prop(s, "overwrite")
        col.prop(s, "use_compositor")
        _draw_view_layers(layout, scene)
        if s.running:
            if hasattr(layout, "progress"):
                layout.progress(factor=s.progress, text=s.status or "Rendering...")
            else:
                layout.label(text=f"{100 * s.progress:.0f}% {s.status}")
            layout.label(text="Esc cancels and keeps what was rendered", icon="INFO")
            return
        layout.operator("cycles_adaptive.render", icon="RENDER_STILL")
        lines = summary_lines(s)
        if lines:
            box = layout.box()
            box.label(text="Last Result", icon="IMAGE_DATA")
            for line in lines:
                box.label(text=line)
        if s.status:
            layout.label(text=s.status)


def _draw_view_layers(layout, scene) -> None:
    """The view layers a render covers, with Blender's own Use for Rendering
    switches (an adaptive render covers what F12 would)."""
    if len(scene.view_layers) < 2:
        return
    box = layout.box()
    if scene.render.use_single_layer:
        box.label(text="View Layers: the active one (Render Single Layer is on)", icon="RENDERLAYERS")
        return
    box.label(text="View Layers (one EXR layer each)", icon="RENDERLAYERS")
    for vl in scene.view_layers:
        box.prop(vl, "use", text=vl.name)


class CYCLESADAPTIVE_PT_advanced(_RenderPanel, bpy.types.Panel):
    bl_label = "Advanced"
    bl_parent_id = "CYCLESADAPTIVE_PT_panel"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        s = context.scene.cycles_adaptive
        layout.enabled = not s.running
        col = layout.column(heading="Loop")
        for f in option_fields("ui"):
            if f.name not in MAIN_OPTIONS:
                col.prop(s, f.name)
        for title, group, names in param_groups(s):
            box = layout.box()
            box.label(text=title)
            for name in names:
                box.prop(group, name)


CLASSES = (CYCLESADAPTIVE_PT_panel, CYCLESADAPTIVE_PT_advanced)


def register():
    parent = parent_id()
    if parent:
        CYCLESADAPTIVE_PT_panel.bl_parent_id = parent
    elif "bl_parent_id" in CYCLESADAPTIVE_PT_panel.__dict__:
        del CYCLESADAPTIVE_PT_panel.bl_parent_id
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)

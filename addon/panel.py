"""Render Properties panel: method, budget, parameters, the button, progress."""
from __future__ import annotations

import bpy

from ..core.pipeline import option_fields
from .props import _param_classes


class CYCLESADAPTIVE_PT_panel(bpy.types.Panel):
    bl_label = "Adaptive Rendering"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    COMPAT_ENGINES = {"CYCLES"}

    @classmethod
    def poll(cls, context):
        return context.scene.render.engine == "CYCLES"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        s = context.scene.cycles_adaptive
        col = layout.column()
        col.prop(s, "method")
        for f in option_fields("ui"):
            col.prop(s, f.name)
        col.prop(s, "output_path")
        col.prop(s, "frame_range")
        if s.frame_range:
            col.prop(s, "temporal")
        col.prop(s, "overwrite")
        groups = [s.method]
        if s.frame_range and s.temporal != "none":
            groups.append("reproject" if s.temporal == "reproject" else "temporal")
        for key in groups:
            cls = _param_classes.get(key)
            group = getattr(s, f"params_{key}", None)
            if cls is not None and group is not None and cls.__annotations__:
                box = layout.box()
                box.label(text=f"{key.upper()} parameters")
                for name in cls.__annotations__:
                    box.prop(group, name)
        if s.running:
            if hasattr(layout, "progress"):
                layout.progress(factor=s.progress, text=s.status or "Rendering...")
            else:
                layout.label(text=f"{100 * s.progress:.0f}% {s.status}")
            layout.label(text="Esc cancels and keeps what was rendered", icon="INFO")
        else:
            layout.operator("cycles_adaptive.render", icon="RENDER_STILL")
            if s.status:
                layout.label(text=s.status)


register, unregister = bpy.utils.register_classes_factory((CYCLESADAPTIVE_PT_panel,))

"""Add-on preferences (Edit > Preferences > Add-ons > Cycles Adaptive): the
defaults a scene's settings start from.

A scene's ``cycles_adaptive`` settings are applied the preferences once, when
first seen (``configured`` is False: a new scene, or a file saved before the
add-on was enabled): on file load, when the panel first draws the scene (a
one-shot timer, since drawing may not write properties) and before a run.
After that the scene's own values rule, so a file renders the same wherever it
is opened.
"""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from ..core.method import fields_by_name
from ..core.pipeline import Options
from .props import METHOD_ITEMS, PATH_OPTIONS, prop_for

#: the package Blender knows the add-on by ("cycles_adaptive" from the
#: repository, "bl_ext.<repo>.cycles_adaptive" as an installed extension)
PACKAGE = __package__.rpartition(".")[0]

#: loop settings the preferences give a default for (their metadata from Options)
OPTION_DEFAULTS = ("spp", "initial_spp", "max_seconds", "render_seconds")

#: scene settings the preferences give a default for, beyond OPTION_DEFAULTS
SETTING_DEFAULTS = ("method", "use_scene_samples", "output_path")


class CYCLESADAPTIVE_AP_preferences(bpy.types.AddonPreferences):
    """Defaults for new scenes; the scene's panel values override them."""

    bl_idname = PACKAGE

    method: EnumProperty(name="Method", items=METHOD_ITEMS, default=Options().method,
                         description="Method a new scene starts with")
    use_scene_samples: BoolProperty(name="Use Scene Samples", default=False,
                                    description="New scenes take the budget from Cycles' Render Max Samples")
    output_path: StringProperty(name="Output", subtype="FILE_PATH", default="",
                                options=PATH_OPTIONS,
                                description="Output a new scene starts with (// is the .blend's folder; "
                                            "empty: the scene's Output path, frame-numbered)")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.label(text="Defaults for scenes that have not used the add-on yet")
        for name in SETTING_DEFAULTS[:2] + OPTION_DEFAULTS + SETTING_DEFAULTS[2:]:
            layout.prop(self, name)


def preferences(context=None):
    """This add-on's preferences, or None where Blender has no entry for it
    (e.g. the package imported by tests without being enabled)."""
    ctx = context or bpy.context
    addon = ctx.preferences.addons.get(PACKAGE) if getattr(ctx, "preferences", None) else None
    return None if addon is None else addon.preferences


def apply_defaults(settings, prefs) -> bool:
    """Copy the preferences' defaults into a scene's settings once (unless
    ``settings.configured``); True when it did.  ``prefs`` None (no entry)
    keeps the built-in defaults but still marks the scene configured."""
    if settings.configured:
        return False
    if prefs is not None:
        for name in SETTING_DEFAULTS + OPTION_DEFAULTS:
            setattr(settings, name, getattr(prefs, name))
    settings.configured = True
    return True


_scheduled: set = set()  # scene names waiting for apply_to_scene_later's timer


def apply_to_scene_later(scene_name: str) -> None:
    """Apply the defaults to the scene ``scene_name`` from a one-shot timer
    (the panel's draw may not write properties); once per scene however
    often the panel redraws before the timer fires."""
    if scene_name in _scheduled:
        return

    def apply():
        _scheduled.discard(scene_name)
        scene = bpy.data.scenes.get(scene_name)
        if scene is not None:
            apply_defaults(scene.cycles_adaptive, preferences())
        return None  # do not repeat
    _scheduled.add(scene_name)
    bpy.app.timers.register(apply, first_interval=0.0)


@bpy.app.handlers.persistent
def _on_load(_dummy=None):
    for scene in bpy.data.scenes:
        apply_defaults(scene.cycles_adaptive, preferences())


def register():
    for name in OPTION_DEFAULTS:
        f = fields_by_name(Options)[name]
        CYCLESADAPTIVE_AP_preferences.__annotations__[name] = prop_for(f)
    bpy.utils.register_class(CYCLESADAPTIVE_AP_preferences)
    bpy.app.handlers.load_post.append(_on_load)


def unregister():
    if _on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_on_load)
    bpy.utils.unregister_class(CYCLESADAPTIVE_AP_preferences)

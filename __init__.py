"""Cycles Adaptive: adaptive sampling and reconstruction for Cycles.

Blender extension entry point.  Each module that defines Blender classes has its
own register()/unregister(); this file only calls them in order (and in reverse
to unregister).  ``core/`` is pure numpy and never imported with bpy side effects.
"""

_cli_handle = None


def _modules():
    """Modules that define Blender classes, in registration order."""
    from .addon import oidn_blender, panel, preferences, props
    from .operators import render_op
    return (oidn_blender, props, preferences, render_op, panel)


def register():
    global _cli_handle
    import bpy
    for m in _modules():
        m.register()
    if hasattr(bpy.utils, "register_cli_command"):
        from .operators.cli import blender_command
        _cli_handle = bpy.utils.register_cli_command("cycles_adaptive", blender_command)


def unregister():
    global _cli_handle
    import bpy
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
    for m in reversed(_modules()):
        m.unregister()

"""Pure numpy core of the Cycles adaptive add-on (no bpy import anywhere here)."""

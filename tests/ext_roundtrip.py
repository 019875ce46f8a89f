"""Run by tests/test_extension.py in a fresh process:
install the built extension zip into a temporary user repository under bpy,
enable it, check the UI is registered, and run the render operator on a scene.

argv: ZIP REPO_DIR OUT_EXR
"""
import json
import os
import sys

import bpy

zip_path, repo_dir, out = sys.argv[1:4]
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from blend_util import build_scene  # noqa: E402

scene = build_scene(24, 16)  # first: it resets to factory settings
repo = bpy.context.preferences.extensions.repos.new(
    name="cycles_adaptive_test", module="cycles_adaptive_test", custom_directory=repo_dir, source="USER")
bpy.ops.extensions.package_install_files(filepath=zip_path, repo=repo.module, enable_on_install=True)

assert hasattr(scene, "cycles_adaptive"), "scene properties not registered"
assert hasattr(bpy.types, "CYCLESADAPTIVE_PT_panel"), "panel not registered"
s = scene.cycles_adaptive
s.method = "var"
s.spp = 6
s.initial_spp = 2
s.subsets = 2
s.output_path = out
s.params_var.min_spp = 2  # a method parameter exposed in the panel
rr_before = bpy.data.images.get("Render Result")
result = bpy.ops.cycles_adaptive.render()
# the scene's frame range through the same operator: one output per frame
scene.frame_start, scene.frame_end = 1, 2
s.frame_range = True
s.output_path = out.replace(".exr", "_####.exr")
result_range = bpy.ops.cycles_adaptive.render()
range_files = [os.path.isfile(out.replace(".exr", f"_{f:04d}.exr")) for f in (1, 2)]
images = sorted(i.name for i in bpy.data.images if i.name.startswith("Cycles Adaptive"))
# the installed command line offers what works installed: render and denoise
import argparse  # noqa: E402
import importlib  # noqa: E402
cli = importlib.import_module(f"bl_ext.{repo.module}.cycles_adaptive.operators.cli")
parser = cli.build_parser(blender_command=True)
commands = sorted(next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices)
print("RESULT " + json.dumps({"op": sorted(result), "exists": os.path.isfile(out),
                              "png": os.path.isfile(os.path.splitext(out)[0] + ".png"),
                              "images": images, "status": s.status,
                              "range_op": sorted(result_range), "range_files": range_files,
                              "border_restored": not scene.render.use_border,
                              "commands": commands}))

"""Run by tests/test_extension.py in a fresh process: install a built extension zip under bpy with
the venv's OpenImageIO and threadpoolctl hidden, enable it, check the UI is registered and run the
render operator.

argv: ZIP REPO_DIR OUT_EXR.  ``BLENDER_USER_EXTENSIONS`` (set by the test) is the user extensions
folder; Blender unpacks an extension's wheels into its ``.local/lib/pythonX.Y/site-packages``
(addon_utils._extension_sync_wheels), and only from there may OpenImageIO and threadpoolctl be
imported here.
"""
import importlib
import importlib.abc
import importlib.machinery
import json
import os
import sys

WHEEL_SITE = os.path.realpath(os.path.join(
    os.environ["BLENDER_USER_EXTENSIONS"], ".local", "lib",
    "python{}.{}".format(*sys.version_info[:2]), "site-packages"))


def _inside(path, root):
    path = os.path.realpath(path or ".")
    return path == root or path.startswith(root + os.sep)


BUNDLED = ("OpenImageIO", "threadpoolctl")   # the manifest's wheels


class OnlyBundledWheels(importlib.abc.MetaPathFinder):
    """Find the bundled distributions (and their submodules) only under the extension's wheel
    site-packages.

    Installed first on ``sys.meta_path``, before bpy loads anything: the venv's copies (and any
    other copy on ``sys.path``) cannot satisfy the import, so the add-on loads only if the wheels
    bundled in the zip were installed and put on ``sys.path`` by Blender.
    """

    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] not in BUNDLED:
            return None
        search = [p for p in (sys.path if path is None else path) if _inside(p, WHEEL_SITE)]
        spec = importlib.machinery.PathFinder.find_spec(name, search)
        if spec is None:
            raise ModuleNotFoundError(f"No module named {name!r} (the venv's copy is hidden by the "
                                      f"test; only {WHEEL_SITE} may provide it)", name=name)
        return spec


sys.meta_path.insert(0, OnlyBundledWheels())
hidden_before = True
for _name in BUNDLED:
    try:
        importlib.import_module(_name)
        hidden_before = False
    except ImportError:
        pass

import bpy  # noqa: E402
import numpy as np  # noqa: E402

zip_path, repo_dir, out = sys.argv[1:4]
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from blend_util import build_scene  # noqa: E402

scene = build_scene(24, 16)  # first: it resets to factory settings
repo = bpy.context.preferences.extensions.repos.new(
    name="cycles_adaptive_test", module="cycles_adaptive_test", custom_directory=repo_dir, source="USER")
install = bpy.ops.extensions.package_install_files(filepath=zip_path, repo=repo.module,
                                                   enable_on_install=True)
pkg = f"bl_ext.{repo.module}.cycles_adaptive"

assert hasattr(scene, "cycles_adaptive"), "scene properties not registered"
assert hasattr(bpy.types, "CYCLESADAPTIVE_PT_panel"), "panel not registered"
oiio = sys.modules.get("OpenImageIO")
io_mod = importlib.import_module(f"{pkg}.core.io")
s = scene.cycles_adaptive
s.method = "var"
s.spp = 6
s.initial_spp = 2
s.subsets = 2
s.output_path = out
s.params_var.min_spp = 2  # a method parameter exposed in the panel
result = bpy.ops.cycles_adaptive.render()
# the EXR the operator wrote, read back through the bundled OpenImageIO
passes, meta = io_mod.read_layers(out) if os.path.isfile(out) else ({}, {})
combined = passes.get("Combined")
# the scene's frame range through the same operator: one output per frame
scene.frame_start, scene.frame_end = 1, 2
s.frame_range = True
s.output_path = out.replace(".exr", "_####.exr")
result_range = bpy.ops.cycles_adaptive.render()
range_files = [os.path.isfile(out.replace(".exr", f"_{f:04d}.exr")) for f in (1, 2)]
images = sorted(i.name for i in bpy.data.images if i.name.startswith("Cycles Adaptive"))
# the installed command line offers what works installed: render and denoise
import argparse  # noqa: E402
cli = importlib.import_module(f"{pkg}.operators.cli")
parser = cli.build_parser(blender_command=True)
commands = sorted(next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices)
# the Python API as a studio's test imports it from the installed extension
api = importlib.import_module(f"{pkg}.api")
api_result = api.render(scene, method="uniform", spp=2)
api_ok = api.compare(api_result, api_result.save(out.replace(".exr", "_api.exr"))).passed
# the controller's pieces ran with one BLAS thread, through the bundled threadpoolctl
tpc = sys.modules.get("threadpoolctl")
par = importlib.import_module(f"{pkg}.core.parallel")
blas_in_pieces = par.map_ordered(
    lambda _: sorted({i["num_threads"] for i in tpc.threadpool_info() if i["user_api"] == "blas"}),
    range(2)) if tpc else None
print("RESULT " + json.dumps({
    "api": bool(api_ok),
    "version": list(bpy.app.version[:2]), "install": sorted(install),
    "enabled": pkg in bpy.context.preferences.addons,
    "hidden_before": hidden_before, "wheel_site": WHEEL_SITE,
    "wheel_site_on_path": any(_inside(p, WHEEL_SITE) for p in sys.path),
    "oiio_file": getattr(oiio, "__file__", None), "addon_oiio_file": io_mod.oiio.__file__,
    "tpc_file": getattr(tpc, "__file__", None), "blas_in_pieces": blas_in_pieces,
    "op": sorted(result), "exists": os.path.isfile(out),
    "png": os.path.isfile(os.path.splitext(out)[0] + ".png"),
    "exr_shape": list(combined.shape) if combined is not None else None,
    "exr_finite": bool(combined is not None and np.isfinite(combined).all()),
    "exr_passes": sorted(passes),
    "images": images, "status": s.status,
    "range_op": sorted(result_range), "range_files": range_files,
    "border_restored": not scene.render.use_border,
    "commands": commands}))

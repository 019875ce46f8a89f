"""The layers the folders promise: core/ is pure numpy (no bpy, importable
without Blender), and nothing platform-specific runs at import time."""
import ast
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

BLOCK = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {blocked!r}:
            raise ImportError('blocked for this test: ' + name)
sys.meta_path.insert(0, Block())
"""


def _modules(folder):
    return sorted(f[:-3] for f in os.listdir(os.path.join(ROOT, folder))
                  if f.endswith(".py") and f != "__init__.py")


def _run(code):
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


def test_core_source_never_imports_bpy():
    for name in _modules("core"):
        tree = ast.parse(open(os.path.join(ROOT, "core", name + ".py"), encoding="utf-8").read())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                assert all(a.name.split(".")[0] not in ("bpy", "mathutils") for a in node.names), name
            elif isinstance(node, ast.ImportFrom) and node.module:
                assert node.module.split(".")[0] not in ("bpy", "mathutils"), name


def test_every_core_module_imports_without_bpy():
    mods = ", ".join(f"core.{m}" for m in _modules("core"))
    code = BLOCK.format(blocked={"bpy", "mathutils", "bl_math"}) + (
        f"import {mods}\nassert 'bpy' not in sys.modules\nprint('ok')")
    r = _run(code)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_the_addon_registers_without_posix_only_modules():
    """Windows has no ``resource``, ``fcntl``, ``termios`` or ``pwd``: with them
    blocked, every shipped module imports and the add-on registers."""
    shipped = ["core." + m for m in _modules("core")] + ["addon." + m for m in _modules("addon")] + \
        ["operators." + m for m in _modules("operators")] + ["api"]
    code = BLOCK.format(blocked={"resource", "fcntl", "termios", "pwd", "grp"}) + (
        "sys.path.insert(0, 'tests')\nfrom launch import load_package\npkg = load_package()\n"
        "import importlib\n"
        + "".join(f"importlib.import_module('cycles_adaptive.{m}')\n" for m in shipped)
        + "pkg.register()\nimport bpy\nassert hasattr(bpy.ops.cycles_adaptive, 'render')\n"
        "from cycles_adaptive.core.resources import peak_rss_mb\nassert peak_rss_mb() == 0.0\n"
        "pkg.unregister()\nprint('ok')")
    r = _run(code)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-3000:]

"""bpy integration: Blender's own OIDN (compositor Denoise node on image
buffers, addon/oidn_blender.py) gives the image pyoidn gives, in background
mode, without touching the user's data."""
import os
import subprocess
import sys

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from blend_util import build_scene  # noqa: E402

from cycles_adaptive.addon import oidn_blender  # noqa: E402
from cycles_adaptive.addon.executor import CyclesExecutor  # noqa: E402
from cycles_adaptive.core import oidn, regions  # noqa: E402
from cycles_adaptive.core.metrics import relmse  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
needs_pyoidn = pytest.mark.skipif(not oidn.pyoidn_available(), reason="pyoidn not installed")


@pytest.fixture(scope="module")
def render():
    """A 4-spp render of the test scene with its albedo and normal passes."""
    scene = build_scene(40, 32)
    with CyclesExecutor(scene, bpy.context.view_layer, ("albedo", "normal"), seed=2) as ex:
        h, w = ex.size
        color, feats = ex.render(regions.RegionTask(0, 0, w, h, 4))
    return color[:, :, :3], feats["albedo"], feats["normal"]


@needs_pyoidn
@pytest.mark.parametrize("prefilter", oidn.PREFILTERS)
def test_blender_node_gives_the_pyoidn_image(render, prefilter):
    """relMSE between the two paths below 1e-4 (measured: 0 for fast and
    none, ~1e-12 for accurate) for every prefilter."""
    color, albedo, normal = render
    a = oidn.oidn_filter(color, albedo, normal, prefilter=prefilter, backend="pyoidn")
    oidn_blender.register()
    try:
        b = oidn.oidn_filter(color, albedo, normal, prefilter=prefilter, backend="blender")
    finally:
        oidn_blender.unregister()
    assert relmse(b, a) < 1e-4
    assert relmse(a, color) > 1e-3  # it did denoise


@needs_pyoidn
def test_blender_node_follows_quality_where_blender_has_it(render):
    color, albedo, normal = render
    a = oidn.oidn_filter(color, albedo, normal, quality="fast", prefilter="fast", backend="pyoidn")
    b = oidn_blender.denoise(oidn._clean(color, "c", 0, 1e7), oidn._clean(albedo, "a", 0, 1),
                             oidn._clean(normal, "n", -1, 1), prefilter="fast", quality="fast")
    if bpy.app.version >= (4, 4, 0):
        assert relmse(b, a) < 1e-4
    else:  # 4.2 has no quality setting: OIDN's default (high)
        hi = oidn.oidn_filter(color, albedo, normal, prefilter="fast", backend="pyoidn")
        assert relmse(b, hi) < 1e-4


def test_the_fallback_leaves_the_users_data_as_it_was(render):
    color, albedo, normal = render
    scene = bpy.context.scene
    before = {
        "scenes": sorted(s.name for s in bpy.data.scenes),
        "images": sorted(i.name for i in bpy.data.images),
        "groups": sorted(g.name for g in bpy.data.node_groups),
        "window_scene": bpy.context.scene.name,
        "filepath": scene.render.filepath,
        "resolution": (scene.render.resolution_x, scene.render.resolution_y),
        "format": scene.render.image_settings.file_format,
    }
    rr = bpy.data.images.get("Render Result")
    slot = rr.render_slots.active_index if rr is not None and rr.render_slots else None
    out = oidn_blender.denoise(oidn._clean(color, "c", 0, 1e7), oidn._clean(albedo, "a", 0, 1),
                               oidn._clean(normal, "n", -1, 1))
    assert out.shape == color.shape and np.isfinite(out).all()
    after = {
        "scenes": sorted(s.name for s in bpy.data.scenes),
        "images": sorted(i.name for i in bpy.data.images),
        "groups": sorted(g.name for g in bpy.data.node_groups),
        "window_scene": bpy.context.scene.name,
        "filepath": scene.render.filepath,
        "resolution": (scene.render.resolution_x, scene.render.resolution_y),
        "format": scene.render.image_settings.file_format,
    }
    if "Render Result" not in before["images"] and "Render Result" in after["images"]:
        after["images"].remove("Render Result")  # Blender's own, made by its first render
    assert after == before
    if slot is not None:
        assert bpy.data.images["Render Result"].render_slots.active_index == slot


BLOCKED = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] == 'pyoidn':
            raise ImportError('blocked for this test')
sys.meta_path.insert(0, Block())
sys.path.insert(0, 'tests')
from launch import load_package
pkg = load_package()
import numpy as np
from cycles_adaptive.core import oidn
from cycles_adaptive.addon import oidn_blender
oidn_blender.register()
backend = oidn.resolve_backend('auto')
rng = np.random.default_rng(0)
c = 0.5 + 0.2 * rng.standard_normal((24, 20, 3))
out = oidn.oidn_filter(c, np.full(c.shape, 0.5), None)
ok = out.shape == c.shape and bool(np.isfinite(out).all()) and float(np.abs(out - c).mean()) > 0.01
print('RESULT', backend, ok)
"""


def test_without_the_wheel_the_addon_denoises_through_blender():
    """A Blender Python without pyoidn: once the add-on registered its
    backend, ``auto`` resolves to Blender's OIDN and denoises."""
    r = subprocess.run([sys.executable, "-c", BLOCKED], cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    # Blender 5.0 may print its own memory report at exit: read our line only
    lines = [ln.split() for ln in r.stdout.splitlines() if ln.startswith("RESULT")]
    assert lines == [["RESULT", "blender", "True"]], r.stdout[-2000:]

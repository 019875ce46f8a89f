"""Extremes of the trade on a real scene at tiny resolution: a 1-spp initial
pass (no variance estimate) works for every method, and every method converges
to the reference as the budget grows (relMSE falls with spp)."""
import os

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from cycles_adaptive.addon.executor import CyclesExecutor  # noqa: E402
from cycles_adaptive.core import methods, metrics, regions  # noqa: E402
from cycles_adaptive.core.pipeline import AdaptiveRun, Options  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
METHODS = ("uniform", "var", "awr", "lp", "rhf")


@pytest.fixture(scope="module")
def scene():
    bpy.ops.wm.open_mainfile(filepath=os.path.join(ROOT, "sample_blends", "cornell.blend"))
    s = bpy.context.scene
    s.render.resolution_percentage = 12  # 15x15 pixels
    return s


def _run(scene, method, spp, initial=4, seed=0):
    feats = methods.get(method).PASSES
    with CyclesExecutor(scene, bpy.context.view_layer, feats, seed=seed) as ex:
        run = AdaptiveRun(ex, Options(method=method, spp=spp, initial_spp=initial, subsets=min(4, initial),
                                      iterations=3, task_cost=64, min_task_size=4, frame=1))
        for _ in run.steps():
            pass
        return run, run.reconstruct()


@pytest.fixture(scope="module")
def reference(scene):
    with CyclesExecutor(scene, bpy.context.view_layer, (), seed=1000003) as ex:
        h, w = ex.size
        color, _ = ex.render(regions.RegionTask(0, 0, w, h, 4096, frame=1))
    return color[:, :, :3]


@pytest.mark.parametrize("method", METHODS)
def test_one_spp_initial_pass_gives_a_finite_image(scene, method):
    run, res = _run(scene, method, spp=3, initial=1)
    assert not run.buffers.has_variance.all() or run.iteration > 0
    assert np.isfinite(res.image).all() and np.isfinite(res.error).all()
    assert abs(run.samples_rendered - 3 * run.pixels) <= 0.01 * 3 * run.pixels + 1


@pytest.mark.parametrize("method", METHODS)
def test_error_falls_with_spp_and_converges_to_the_reference(scene, reference, method):
    errs = []
    for spp in (4, 64, 1024):
        _, res = _run(scene, method, spp)
        errs.append(metrics.relmse(res.image, reference))
    assert errs[1] < errs[0] and errs[2] < errs[1], errs
    assert errs[2] < 0.2 * errs[0], errs

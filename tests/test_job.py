"""RenderJob in-process: a cancel restores the scene and writes the partial result."""
import os

import pytest

bpy = pytest.importorskip("bpy")

from blend_util import build_scene  # noqa: E402

from cycles_adaptive.core.pipeline import Options  # noqa: E402
from cycles_adaptive.operators.job import RenderJob  # noqa: E402
from cycles_adaptive.operators.stepper import Stepper  # noqa: E402


def _settings(scene):
    r, c = scene.render, scene.cycles
    return (r.use_border, r.use_crop_to_border, r.border_max_x, r.filepath, r.image_settings.file_format,
            r.use_compositing, r.use_persistent_data, c.samples, c.sample_offset, c.seed,
            c.sampling_pattern, scene.view_layers[0].cycles.denoising_store_passes, scene.frame_current)


@pytest.mark.parametrize("method", ["var", "lp"])
def test_cancel_mid_run_restores_the_scene_and_writes_the_partial_result(tmp_path, method):
    scene = build_scene(32, 24)
    scene.cycles.seed = 5
    before = _settings(scene)
    out = str(tmp_path / "part.exr")
    job = RenderJob(scene, bpy.context.view_layer, Options(method=method, spp=12, initial_spp=2, subsets=2,
                                                           frame=scene.frame_current, task_cost=64), out)
    st = Stepper(job, slice_seconds=0.0)
    for _ in range(6):  # initial pass and part of the first iteration
        assert not st.step()
    summary = st.cancel()
    assert _settings(scene) == before
    assert summary["partial"] and os.path.isfile(out) and os.path.isfile(out + ".checkpoint.npz")
    assert 0 < summary["spp_mean"] < 12


def test_a_failing_render_restores_the_scene(tmp_path):
    scene = build_scene(16, 16)
    before = _settings(scene)
    job = RenderJob(scene, bpy.context.view_layer, Options(method="var", spp=4, initial_spp=2, subsets=2,
                                                           frame=scene.frame_current), str(tmp_path / "x.exr"))
    steps = job.steps()
    next(steps)
    job.executor.render = None  # the next render call raises TypeError
    with pytest.raises(TypeError):
        for _ in steps:
            pass
    assert _settings(scene) == before
    assert not os.path.exists(str(tmp_path / "x.exr"))

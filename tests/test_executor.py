"""bpy integration: border renders of sample subsets merge exactly."""
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from blend_util import build_scene  # noqa: E402

from cycles_adaptive.addon.executor import CyclesExecutor, SceneError, border_pixels  # noqa: E402
from cycles_adaptive.core import regions  # noqa: E402
from cycles_adaptive.core.buffers import Buffers  # noqa: E402
from cycles_adaptive.core.pipeline import AdaptiveRun, Options  # noqa: E402


def _render_full(ex, samples, offset=0):
    color, _ = ex.render(regions.RegionTask(0, 0, ex.size[1], ex.size[0], samples, offset=offset))
    return color


def test_uniform_map_through_planner_and_merge_equals_one_render():
    scene = build_scene(37, 29)  # odd sizes: border rounding must still be exact
    with CyclesExecutor(scene, bpy.context.view_layer, ("albedo",), seed=3) as ex:
        h, w = ex.size
        one = _render_full(ex, 12)
        buf = Buffers.empty(h, w, ("albedo",))
        for off in (0, 2):  # initial pass: two subsets of 2 spp
            c, f = ex.render(regions.RegionTask(0, 0, w, h, 2, offset=off))
            buf.merge_group(c[:, :, :3], 2, f)
        counts = np.full((h, w), 8, np.int64)
        plan = regions.plan(counts, min_size=8)
        tasks, nxt = regions.assign_offsets(plan.tasks, np.full((h, w), 4, np.int64))
        for t in tasks:
            c, f = ex.render(t)
            buf.merge_group(c[:, :, :3], t.samples, f, region=(t.x0, t.y0, t.x1, t.y1))
    assert np.all(buf.n == 12) and np.all(nxt == 12)
    diff = np.abs(buf.color.mean - one[:, :, :3]).max()
    assert diff <= 1e-4 * one[:, :, :3].mean()


def test_blocky_map_tasks_merge_exactly_per_region():
    """A map constant on blocks gives several tasks; each region's merge equals
    the same region of a full-frame render with that many samples."""
    scene = build_scene(32, 24)
    with CyclesExecutor(scene, bpy.context.view_layer, (), seed=1) as ex:
        h, w = ex.size
        full4 = _render_full(ex, 4)
        full8 = _render_full(ex, 8)
        buf = Buffers.empty(h, w, ())
        c, _ = ex.render(regions.RegionTask(0, 0, w, h, 4, offset=0))
        buf.merge_group(c[:, :, :3], 4, {})
        counts = np.zeros((h, w), np.int64)
        counts[:16, :16] = 4
        plan = regions.plan(counts, min_size=8)
        tasks, _ = regions.assign_offsets(plan.tasks, np.full((h, w), 4, np.int64))
        for t in tasks:
            c, _ = ex.render(t)
            buf.merge_group(c[:, :, :3], t.samples, {}, region=(t.x0, t.y0, t.x1, t.y1))
    assert plan.overshoot == 0
    np.testing.assert_allclose(buf.color.mean[:16, :16], full8[:16, :16, :3], atol=1e-4 * full8.mean())
    np.testing.assert_allclose(buf.color.mean[16:, :], full4[16:, :, :3], atol=1e-6)


def test_scene_settings_are_restored_even_after_an_error():
    scene = build_scene(16, 16)
    r, c = scene.render, scene.cycles
    before = (r.use_border, r.filepath, r.image_settings.file_format, c.samples, c.sample_offset,
              getattr(c, "use_sample_subset", None), scene.view_layers[0].cycles.denoising_store_passes,
              r.use_compositing, scene.frame_current)
    with pytest.raises(RuntimeError):
        with CyclesExecutor(scene, bpy.context.view_layer, ("albedo", "normal"), seed=1) as ex:
            _render_full(ex, 2)
            raise RuntimeError("boom")
    after = (r.use_border, r.filepath, r.image_settings.file_format, c.samples, c.sample_offset,
             getattr(c, "use_sample_subset", None), scene.view_layers[0].cycles.denoising_store_passes,
             r.use_compositing, scene.frame_current)
    assert after == before


def test_existing_border_is_the_render_domain():
    scene = build_scene(40, 30)
    r = scene.render
    r.use_border, r.use_crop_to_border = True, False
    r.border_min_x, r.border_max_x, r.border_min_y, r.border_max_y = 0.25, 0.75, 0.0, 0.5
    assert border_pixels(scene) == (10, 15, 30, 30)
    with CyclesExecutor(scene, bpy.context.view_layer, (), seed=1) as ex:
        assert ex.size == (15, 20)
        c = _render_full(ex, 2)
        assert c.shape == (15, 20, 4) and np.isfinite(c).all()
    assert (r.border_min_x, r.border_max_x) == (0.25, 0.75) and not r.use_crop_to_border


@pytest.mark.parametrize("case", ["no_camera", "eevee", "border_outside"])
def test_bad_scenes_are_refused_with_a_message(case):
    if case == "no_camera":
        scene = build_scene(8, 8, camera=False)
        match = "no active camera"
    elif case == "eevee":
        scene = build_scene(8, 8, engine="EEVEE")
        match = "set Render Engine to Cycles"
    else:
        scene = build_scene(8, 8)
        scene.render.use_border = True
        scene.render.border_min_x = scene.render.border_max_x = 1.0
        match = "outside the frame"
    with pytest.raises(SceneError, match=match):
        CyclesExecutor(scene, bpy.context.view_layer)


def test_one_pixel_image_renders():
    # Blender's smallest resolution is 4x4; a one-pixel border gives a 1x1 image
    scene = build_scene(4, 4)
    r = scene.render
    r.use_border, r.use_crop_to_border = True, True
    r.border_min_x, r.border_max_x, r.border_min_y, r.border_max_y = 0.25, 0.5, 0.5, 0.75
    with CyclesExecutor(scene, bpy.context.view_layer, ("albedo", "normal", "depth"), seed=0) as ex:
        run = AdaptiveRun(ex, Options(method="uniform", spp=4, initial_spp=4, subsets=2))
        for _ in run.steps():
            pass
    assert run.buffers.shape == (1, 1)
    assert run.buffers.n.sum() == 4 and np.isfinite(run.reconstruct().image).all()


def test_the_users_last_render_keeps_its_slot():
    """Our renders go to a render slot of their own; the user's active slot
    (holding their last render) is active again afterwards."""
    scene = build_scene(16, 16)
    scene.render.filepath = "/tmp/cycles-adaptive-user-render.png"
    bpy.ops.render.render()  # the user's own render, into the active slot
    rr = bpy.data.images["Render Result"]
    rr.render_slots.active_index = 2
    with CyclesExecutor(scene, bpy.context.view_layer, (), seed=1) as ex:
        assert rr.render_slots.active.name == "Cycles Adaptive"
        _render_full(ex, 1)
    assert rr.render_slots.active_index == 2
    assert scene.render.filepath == "/tmp/cycles-adaptive-user-render.png"


def _merged_uniform(scene, spp, hold):
    """``uniform`` through the loop at ``spp`` (4 subsets); the executor
    holds the count when ``hold``.  (mean colour, executor)."""
    ex = CyclesExecutor(scene, bpy.context.view_layer, ("albedo", "normal", "depth"), seed=0)  # uniform's PASSES
    if hold:
        ex.hold_samples_at(spp)
    with ex:
        run = AdaptiveRun(ex, Options(method="uniform", spp=float(spp), subsets=4, seed=0))
        for _ in run.steps():
            pass
    return run.buffers.color.mean, ex


def _blue_noise_scene():
    """A 24x16 test scene with the Blue Noise pattern (skips where there is none)."""
    scene = build_scene(24, 16)
    try:
        scene.cycles.sampling_pattern = "BLUE_NOISE"
    except TypeError:
        pytest.skip("this Blender has no blue-noise pattern")
    return scene


def test_auto_choosing_uniform_sampling_renders_the_scene_patterns_image():
    """auto holds the budget's count: with a uniform choice its initial pass
    and the rest merge into the scene pattern's render at that count (what
    the chosen candidate run alone gives); an adaptive choice releases it."""
    from cycles_adaptive.bench.peers import PlainCycles
    from cycles_adaptive.core.pipeline import hold_samples
    scene = _blue_noise_scene()
    vl = bpy.context.view_layer
    runs = {}
    for sampling in ("uniform", "adaptive"):
        opts = Options(method="auto", spp=12.0, seed=0, params={"candidates": "mean", "sampling": sampling})
        ex = CyclesExecutor(scene, vl, ("normal", "albedo", "depth"), seed=0)
        held = hold_samples(ex, opts, AdaptiveRun(ex, opts).method)
        if sampling == "adaptive":  # forced adaptive holds nothing; held as when auto predicts it
            assert held is None
            ex.hold_samples_at(12)
        with ex:
            run = AdaptiveRun(ex, opts)
            for _ in run.steps():
                pass
        runs[sampling] = (run, ex, held)
    with PlainCycles(scene, vl, 0, "BLUE_NOISE") as pc:
        blue = pc.render(12)["rgb"]
    run, ex, held = runs["uniform"]
    assert run.method.NAME == "uniform" and np.all(run.buffers.n == 12)
    if hasattr(scene.cycles, "use_sample_subset"):  # 4.4+
        assert held == 12 and ex.pattern == "BLUE_NOISE" and ex.initial_pattern is None
        np.testing.assert_allclose(run.buffers.color.mean, blue, rtol=1e-5, atol=1e-6)
    else:
        assert ex.pattern == "TABULATED_SOBOL"
    run, ex, held = runs["adaptive"]
    assert run.method.NAME == "var" and ex.pattern == "TABULATED_SOBOL" and ex.hold is None
    if hasattr(scene.cycles, "use_sample_subset"):
        assert ex.initial_pattern == "BLUE_NOISE"
    assert scene.cycles.sampling_pattern == "BLUE_NOISE"


def test_a_released_hold_renders_the_samples_an_unheld_run_renders():
    """auto's adaptive choice after an initial pass at the held count: from
    ``release_hold`` on, the renders are Tabulated Sobol's samples [offset,
    offset + length), equal to those of an executor that never held (exact
    merges with any later task); the initial pass stays the scene pattern's,
    and the scene's own pattern is restored on exit."""
    scene = _blue_noise_scene()
    if not hasattr(scene.cycles, "use_sample_subset"):
        pytest.skip("a held count needs Blender 4.4+ (sample subsets)")
    vl = bpy.context.view_layer
    ex = CyclesExecutor(scene, vl, (), seed=0)
    ex.hold_samples_at(12)
    with ex:
        first = _render_full(ex, 4)
        assert ex.pattern == "BLUE_NOISE"
        ex.release_hold()
        assert ex.pattern == "TABULATED_SOBOL" and ex.initial_pattern == "BLUE_NOISE"
        rest = _render_full(ex, 8, offset=4)
        ex.release_hold()  # a second call changes nothing
        assert ex.pattern == "TABULATED_SOBOL"
    assert scene.cycles.sampling_pattern == "BLUE_NOISE"
    with CyclesExecutor(scene, vl, (), seed=0) as free:
        rest_free = _render_full(free, 8, offset=4)
        first_free = _render_full(free, 4)
    np.testing.assert_allclose(rest, rest_free, rtol=1e-5, atol=1e-6)
    assert np.abs(first - first_free).max() > 1e-3  # the initial pass was the held Blue Noise


def test_a_held_count_renders_the_scenes_own_pattern_and_merges_into_its_render():
    """With the run's one count held (Blender 4.4+), the subsets of a
    Blue Noise scene merge into Blue Noise's render at that count, the one
    plain Cycles gives; without it (or on 4.2 / 4.3) the loop renders
    Tabulated Sobol."""
    from cycles_adaptive.bench.peers import PlainCycles
    scene = _blue_noise_scene()
    held, ex = _merged_uniform(scene, 12, hold=True)
    free, ex_free = _merged_uniform(scene, 12, hold=False)
    assert scene.cycles.sampling_pattern == "BLUE_NOISE"  # restored
    assert ex_free.pattern == "TABULATED_SOBOL"
    with PlainCycles(scene, bpy.context.view_layer, 0, "BLUE_NOISE") as pc:
        blue = pc.render(12)["rgb"]
    with PlainCycles(scene, bpy.context.view_layer, 0, "TABULATED_SOBOL") as pc:
        sobol = pc.render(12)["rgb"]
    np.testing.assert_allclose(free, sobol, rtol=1e-5, atol=1e-6)
    if hasattr(scene.cycles, "use_sample_subset"):  # 4.4+
        assert ex.pattern == "BLUE_NOISE"
        np.testing.assert_allclose(held, blue, rtol=1e-5, atol=1e-6)
        assert np.abs(held - free).max() > 1e-3  # the patterns do differ here
    else:
        assert ex.pattern == "TABULATED_SOBOL" and ex.hold is None
        np.testing.assert_allclose(held, sobol, rtol=1e-5, atol=1e-6)


def test_a_deferred_read_gives_the_render_and_close_reads_what_is_left(monkeypatch):
    """``render_deferred`` renders now and reads the file on its call, from
    any thread, once: the arrays of ``render`` for the same samples, bit for
    bit.  A read never called before the executor closes is done by
    ``close`` before the files go, so the merge that comes later still gets
    its render; a read's error reaches every caller."""
    import os
    import threading
    from cycles_adaptive.addon import executor as exmod
    scene = build_scene(24, 20)
    task = regions.RegionTask(0, 0, 24, 20, 2, offset=0)
    with CyclesExecutor(scene, bpy.context.view_layer, ("albedo", "normal", "depth"), seed=5) as ex:
        color, feats = ex.render(task)
        pending = ex.render_deferred(task)
        files = os.listdir(ex.tmpdir)
        assert len(files) == 1  # rendered, not read yet
        got = {}
        worker = threading.Thread(target=lambda: got.setdefault("r", pending()))
        worker.start()
        worker.join()
        assert os.listdir(ex.tmpdir) == [] and pending() is got["r"]
        np.testing.assert_array_equal(got["r"][0], color)
        assert set(got["r"][1]) == set(feats)
        for k in feats:
            np.testing.assert_array_equal(got["r"][1][k], feats[k])
        unread = ex.render_deferred(regions.RegionTask(0, 0, 24, 20, 2, offset=2))
        tmp = ex.tmpdir
        calls = []
        monkeypatch.setattr(exmod, "read_still", lambda *a, **k: calls.append(1) or (_ for _ in ()).throw(
            SceneError("the file is unreadable")))
        failing = ex.render_deferred(regions.RegionTask(0, 0, 24, 20, 2, offset=4))
        for _ in range(2):
            with pytest.raises(SceneError, match="unreadable"):
                failing()
        assert calls == [1]  # read once, its error kept
        monkeypatch.undo()
    assert not os.path.exists(tmp)
    c2, f2 = unread()  # read by close, before the files went
    assert c2.shape == color.shape and not np.array_equal(c2, color) and set(f2) == set(feats)

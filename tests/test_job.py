"""RenderJob in-process: a cancel restores the scene and writes the partial result."""
import os
import time

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
    for _ in range(3000):  # the initial pass, its checkpoint and the start of the first iteration
        assert not st.step()
        if st.stage in ("adapt", "plan", "render"):
            break
        time.sleep(0.005)  # the initial pass's Works run on threads
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


# ------------------------------------------------------- responsive stepping
import threading  # noqa: E402

import numpy as np  # noqa: E402

from cycles_adaptive.addon import executor as ex  # noqa: E402
from cycles_adaptive.core import io as imageio  # noqa: E402
from cycles_adaptive.core import lp, metrics  # noqa: E402
from cycles_adaptive.operators import job as job_mod  # noqa: E402
from cycles_adaptive.operators.job import estimated_relmse  # noqa: E402


def _on_main():
    assert threading.current_thread() is threading.main_thread(), "bpy called off the main thread"


class MainThreadExecutor(ex.CyclesExecutor):
    """The Cycles executor, asserting every render (and scene change) runs on
    the main thread."""

    def __enter__(self):
        _on_main()
        return super().__enter__()

    def __exit__(self, *exc):
        _on_main()
        return super().__exit__(*exc)

    def render(self, task):
        _on_main()
        return super().render(task)


class GatedLP:
    """LP (every member of the Method contract delegated) whose
    reconstruction waits for ``gate`` and records the thread it ran on."""

    NAME, PASSES, Params = lp.NAME, lp.PASSES, lp.Params
    ADAPTIVE, SAMPLER_USES_RESULT = lp.ADAPTIVE, lp.SAMPLER_USES_RESULT

    def __init__(self):
        self.gate = threading.Event()
        self.threads = []

    def reconstruct(self, buf, params=None):
        self.threads.append(threading.current_thread())
        self.gate.wait(120)
        return lp.reconstruct(buf, params)

    def sample_map(self, buf, result, budget, params=None, state=None):
        return lp.sample_map(buf, result, budget, params, state)


class Threads:
    def __init__(self):
        self.threads = []

    def __call__(self, fn):
        from cycles_adaptive.operators.stepper import start_thread
        self.threads.append(start_thread(fn))

    def join(self):
        for t in self.threads:
            t.join(300)  # a guard against a hang, not a speed bound
            assert not t.is_alive()


@pytest.fixture
def main_thread_outputs(monkeypatch):
    """Assert that the outputs (EXR, PNG through bpy) are written on the main thread."""
    for mod, name in ((job_mod, "write_output"), (ex, "write_preview")):
        real = getattr(mod, name)

        def checked(*a, _real=real, **kw):
            _on_main()
            return _real(*a, **kw)
        monkeypatch.setattr(mod, name, checked)


def _gated_job(tmp_path, scene, method, name="g.exr"):
    opts = Options(method="lp", spp=8, initial_spp=2, subsets=2, iterations=2, frame=scene.frame_current,
                   task_cost=64)
    return RenderJob(scene, bpy.context.view_layer, opts, str(tmp_path / name), method=method,
                     executor_factory=MainThreadExecutor)


def test_esc_during_adaptation_returns_without_waiting_and_writes_the_sample_mean(tmp_path,
                                                                                 main_thread_outputs):
    scene = build_scene(24, 16)
    before = _settings(scene)
    method, threads = GatedLP(), Threads()
    job = _gated_job(tmp_path, scene, method)
    st = Stepper(job, slice_seconds=60.0, start=threads)  # only a Work ends a slice early
    assert st.step() is False
    for _ in range(20):  # the initial pass's measurements and checkpoint run as Works too
        if st.stage == "adapt":
            break
        threads.join()
        assert st.step() is False
    assert st.stage == "adapt" and st.pending is not None
    assert st.step() is False  # still adapting: the UI gets control back at once
    summary = st.cancel()
    pending_done = method.gate.is_set()
    method.gate.set()
    threads.join()
    assert not pending_done and _settings(scene) == before
    assert summary["partial"] and not summary["reconstructed"] and 0 < summary["spp_mean"] < 8
    assert np.isfinite(summary["estimated_relmse"]) and summary["estimated_relmse"] >= 0
    passes, meta = imageio.read_layers(job.out)
    # the sample mean (the result stored in half float)
    assert np.array_equal(passes["Combined"][..., :3], imageio.as_half(passes["Noisy"][..., :3]))
    assert os.path.isfile(job.out + ".checkpoint.npz")  # kept for --resume
    assert all(t is not threading.main_thread() for t in method.threads)


def test_stepped_run_reconstructs_off_the_main_thread_and_matches_an_inline_run(tmp_path,
                                                                               main_thread_outputs):
    results = []
    for name, stepped in (("inline.exr", False), ("stepped.exr", True)):
        scene = build_scene(24, 16)
        method = GatedLP()
        method.gate.set()
        job = _gated_job(tmp_path, scene, method, name)
        if stepped:
            threads = Threads()
            st = Stepper(job, slice_seconds=0.0, start=threads)
            stages = []
            while not st.step():
                stages.append(st.stage)
                threads.join()
            summary = st.summary
            assert "adapt" in stages and "reconstruct" in stages and "write" in stages
            assert method.threads and all(t is not threading.main_thread() for t in method.threads)
        else:
            for _ in job.steps():
                pass
            summary = job.finish()
            assert all(t is threading.main_thread() for t in method.threads)
        assert summary["reconstructed"] and not summary["partial"]
        results.append(imageio.read_layers(job.out)[0])
    a, b = results
    for p in ("Combined", "Samples", "Error", "Noisy"):
        assert np.array_equal(a[p], b[p]), p


def test_estimated_relmse_is_relmse_when_the_error_estimate_is_exact():
    rng = np.random.default_rng(3)
    ref = rng.uniform(0, 2, (6, 5, 3))
    d = rng.normal(0, 0.3, (6, 5))
    x = ref + d[..., None]  # the same error in every channel
    assert estimated_relmse(ref, d * d) == pytest.approx(metrics.relmse(x, ref), rel=1e-12)


def test_estimated_relmse_is_finite_for_hostile_input():
    img = np.array([[[np.nan, 1, np.inf], [0, 0, 0]]])
    err = np.array([[np.inf, np.nan]])
    v = estimated_relmse(img, err)
    assert np.isfinite(v) and v >= 0
    assert estimated_relmse(np.zeros((0, 0, 3)), np.zeros((0, 0))) == 0.0
    assert estimated_relmse(np.zeros((2, 2, 3)), np.full((2, 2), 1e300)) == pytest.approx(1e302)


def test_a_run_closed_after_another_file_was_opened_does_not_touch_the_old_scene():
    """A run's generator closed (or garbage-collected) after Blender opened
    another file restores nothing: the old scene's settings are freed memory
    (this crashed Blender with a segmentation fault before)."""
    scene = build_scene(24, 16)
    job = RenderJob(scene, bpy.context.view_layer, Options(method="var", spp=4, initial_spp=2, subsets=2), None)
    steps = job.steps()
    for st in steps:
        if st.stage == "initial":  # inside the executor: the scene's settings are changed
            break
    assert scene.cycles.samples != 16
    fresh = build_scene(20, 12)  # opens a new file: the old scene is freed
    steps.close()
    assert fresh.cycles.samples == 16 and fresh.render.resolution_x == 20


@pytest.mark.parametrize("fmt, depth, codec, half, stored", [
    ("OPEN_EXR", "32", "PIZ", False, "piz"),
    ("OPEN_EXR", "16", "ZIP", True, "zip"),
    ("OPEN_EXR", "16", "DWAA", True, "zip"),  # lossy: the statistics must stay exact
    ("PNG", "8", None, True, "zip"),
])
def test_the_exr_follows_the_scene_output_settings(fmt, depth, codec, half, stored):
    scene = build_scene(8, 8)
    im = scene.render.image_settings
    im.file_format = fmt
    im.color_depth = depth
    if codec:
        im.exr_codec = codec
    f = job_mod.exr_format(scene, "scene")
    assert (f.half, f.codec) == (half, stored)
    assert ("lossy" in f.note) == (codec == "DWAA")
    assert job_mod.exr_format(scene, "full").half is False and job_mod.exr_format(scene, "half").half is True
    with pytest.raises(job_mod.JobError, match="EXR depth"):
        job_mod.exr_format(scene, "double")


def test_half_results_halve_the_result_passes_and_keep_the_statistics_exact(tmp_path):
    """The same run written with ``exr_depth`` half and full: identical
    statistics, the result passes the half of the full file's, a smaller file."""
    scene = build_scene(32, 24)
    files = {}
    for depth in ("full", "half"):
        opts = Options(method="var", spp=4, initial_spp=2, subsets=2, iterations=1, seed=2)
        job = RenderJob(scene, bpy.context.view_layer, opts, str(tmp_path / f"{depth}.exr"), exr_depth=depth,
                        preview=False)
        for _ in job.steps():
            pass
        summary = job.finish()
        assert summary["exr"].startswith(f"{depth} float results")
        files[depth] = imageio.read_layers(job.out)
    (full, fmeta), (half, hmeta) = files["full"], files["half"]
    assert fmeta["half"] == [] and hmeta["half"] == sorted(job_mod.RESULT_PASSES)
    for name in full:
        expect = imageio.as_half(full[name]) if name in job_mod.RESULT_PASSES else full[name]
        assert np.array_equal(half[name], expect), name
    assert os.path.getsize(tmp_path / "half.exr") < os.path.getsize(tmp_path / "full.exr")


@pytest.mark.parametrize("mode", ["animated", "fixed"])
def test_a_fixed_seed_repeats_the_noise_of_a_still_shot_and_the_animated_one_does_not(tmp_path, mode):
    """Frames of a shot where nothing moves: with the fixed seed every frame is
    the same render (the same noise pattern: no flicker), with the animated
    seed each frame has its own noise."""
    from cycles_adaptive.operators.job import FramesJob
    scene = build_scene(24, 16)
    opts = Options(method="uniform", spp=2, initial_spp=2, subsets=2, seed=5)
    fj = FramesJob(scene, bpy.context.view_layer, opts, str(tmp_path / "f_####.exr"), [1, 2, 3],
                   seed_mode=mode, preview=False)
    images = []
    for item in fj.steps():
        if isinstance(item, dict):
            images.append(np.array(fj.job.result.image))
    assert [fj.frame_seed(f) for f in (1, 2, 3)] == ([6, 7, 8] if mode == "animated" else [5, 5, 5])
    same = [np.array_equal(images[0], x) for x in images[1:]]
    assert same == ([True, True] if mode == "fixed" else [False, False])


def test_a_fixed_seed_with_reprojection_is_refused_and_auto_picks_the_seed_by_mode(tmp_path):
    from cycles_adaptive.operators.job import FramesJob, JobError
    scene = build_scene(8, 8)
    vl, opts = bpy.context.view_layer, Options(method="var", spp=2, seed=3)
    auto = FramesJob(scene, vl, opts, str(tmp_path / "a_####.exr"), [1, 2])
    assert auto.seed_mode == "fixed" and auto.frame_seed(2) == 3
    rep = FramesJob(scene, vl, opts, str(tmp_path / "r_####.exr"), [1, 2], temporal="reproject")
    assert rep.seed_mode == "animated" and rep.frame_seed(2) == 5
    with pytest.raises(JobError, match="needs --seed-mode animated"):
        FramesJob(scene, bpy.context.view_layer, Options(method="var", spp=2), str(tmp_path / "f_####.exr"),
                  [1, 2], temporal="reproject", seed_mode="fixed")


@pytest.mark.parametrize("history_params, key", [({}, "blend_input_history_fraction"),
                                                  ({"input_frames": 1}, "blend_history_fraction")])
def test_blend_averages_frames_of_a_static_scene_and_needs_the_animated_seed(tmp_path, history_params, key):
    """``--temporal blend`` on a static scene, with the input history (the
    default) or blending the outputs: from the second frame on, the previous
    frame is found on (nearly) every pixel, the reported error falls with the
    frames, and the image is finite; a fixed seed is refused, auto picks the
    animated one."""
    from cycles_adaptive.operators.job import FramesJob, JobError
    scene = build_scene(24, 16)
    vl = bpy.context.view_layer
    opts = Options(method="uniform", spp=4, initial_spp=4, subsets=2, seed=5)
    fj = FramesJob(scene, vl, opts, str(tmp_path / "b_####.exr"), [1, 2, 3], temporal="blend", preview=False,
                   history_params=history_params)
    assert fj.seed_mode == "animated"
    infos, errors = [], []
    for item in fj.steps():
        if isinstance(item, dict):
            res = fj.job.result
            assert np.all(np.isfinite(res.image))
            infos.append(dict(res.info))
            errors.append(float(np.median(res.error)))
    assert key in infos[0] and infos[0][key] == 0.0
    assert infos[1][key] > 0.8 and infos[2][key] > 0.8
    assert errors[2] < errors[1] < errors[0]
    with pytest.raises(JobError, match="needs --seed-mode animated"):
        FramesJob(scene, vl, opts, str(tmp_path / "c_####.exr"), [1, 2], temporal="blend", seed_mode="fixed")


@pytest.mark.parametrize("method", ["oidn", "lp"])
def test_a_frame_without_history_is_the_method_alone(tmp_path, method):
    """The first frame of ``--temporal blend`` (no history yet) is exactly the
    frame rendered without history: the blend starts from the method's own
    reconstruction (the same view of the passes, the same spread)."""
    from cycles_adaptive.operators.job import FramesJob
    scene = build_scene(24, 16)
    vl = bpy.context.view_layer
    opts = Options(method=method, spp=4, initial_spp=2, subsets=2, seed=5)
    images = {}
    for temporal in ("none", "blend"):
        fj = FramesJob(scene, vl, opts, str(tmp_path / f"{temporal}_####.exr"), [1], temporal=temporal,
                       seed_mode="animated", preview=False)
        for item in fj.steps():
            if isinstance(item, dict):
                images[temporal] = fj.job.result.image.copy()
    np.testing.assert_array_equal(images["blend"], images["none"])


def test_blend_gives_a_denoiser_the_previous_frames_samples(tmp_path):
    """``--temporal blend`` with oidn on a still scene: from frame 2 on the
    method reconstructs this frame's samples with the previous frames'
    accumulated in (most pixels find their history), and the frames
    come out closer to a 512-spp render than the same frames without history;
    ``input_frames = 1`` turns it off."""
    from cycles_adaptive.core import metrics
    from cycles_adaptive.operators.job import FramesJob
    scene = build_scene(48, 32)
    vl = bpy.context.view_layer
    ref_job = RenderJob(scene, vl, Options(method="uniform", spp=512, seed=99), str(tmp_path / "ref.exr"),
                        preview=False)
    for _ in ref_job.steps():
        pass
    ref_job.finish()
    ref = np.asarray(ref_job.result.image, np.float64)[..., :3]
    opts = Options(method="oidn", spp=8, seed=5)
    errors, infos = {}, {}
    for name, temporal, hp in (("none", "none", None), ("input", "blend", {"max_frames": 1}),
                               ("off", "blend", {"input_frames": 1, "max_frames": 1})):
        fj = FramesJob(scene, vl, opts, str(tmp_path / f"{name}_####.exr"), [1, 2, 3], temporal=temporal,
                       seed_mode="animated", preview=False, history_params=hp)
        for item in fj.steps():
            if isinstance(item, dict):
                img = np.asarray(fj.job.result.image, np.float64)[..., :3]
                errors.setdefault(name, []).append(metrics.relmse(img, ref))
                infos.setdefault(name, []).append(dict(fj.job.result.info))
    assert all(i["blend_input_history_fraction"] >= 0.75 for i in infos["input"][1:])
    assert "blend_input_history_fraction" not in infos["off"][1]
    np.testing.assert_allclose(errors["off"], errors["none"], rtol=1e-9)  # nothing carried, nothing blended
    assert np.mean(errors["input"][1:]) < 0.9 * np.mean(errors["none"][1:])


def test_an_image_only_exr_keeps_the_image_passes_and_denoise_refuses_it(tmp_path):
    """``exr_contents="image"``: the result, error, samples per pixel and the
    feature means, bit for bit as in the full file, and nothing else; a
    smaller file; ``denoise`` on it says why it cannot re-run."""
    scene = build_scene(32, 24)
    files = {}
    for contents in ("full", "image"):
        opts = Options(method="var", spp=4, initial_spp=2, subsets=2, iterations=1, seed=2)
        job = RenderJob(scene, bpy.context.view_layer, opts, str(tmp_path / f"{contents}.exr"),
                        exr_contents=contents, preview=False)
        for _ in job.steps():
            pass
        job.finish()
        files[contents] = imageio.read_layers(job.out)[0]
    full, image = files["full"], files["image"]
    feats = {k for k in full if k.startswith("Feat_") and not k.endswith("_M2")}
    assert set(image) == {"Combined", "Error", "Samples"} | feats and "Noisy" in full
    assert all(np.array_equal(image[k], full[k]) for k in image)
    assert os.path.getsize(tmp_path / "image.exr") < 0.7 * os.path.getsize(tmp_path / "full.exr")
    from cycles_adaptive.core.storage import StorageError
    with pytest.raises(StorageError, match="image-only output"):
        job_mod.denoise_output(str(tmp_path / "image.exr"), "lp")


@pytest.mark.parametrize("method", ["uniform", "var"])
def test_merges_behind_real_renders_give_the_file_of_inline_merges(tmp_path, monkeypatch, method):
    """Cycles renders the next task while the last one merges on a background
    thread (every merge there, as from 256x256 pixels): the EXR equals that of
    inline merges, pass for pass, bit for bit."""
    from cycles_adaptive.core import pipeline
    results = []
    for name, threshold in (("inline.exr", 1 << 40), ("background.exr", 1)):
        monkeypatch.setattr(pipeline, "MERGE_WORK_PIXELS", threshold)
        scene = build_scene(24, 16)
        job = RenderJob(scene, bpy.context.view_layer,
                        Options(method=method, spp=8, initial_spp=2, subsets=2, frame=scene.frame_current,
                                task_cost=16, min_task_size=2), str(tmp_path / name))
        for _ in job.steps():
            pass
        job.finish()
        assert job.run.pending_merge is None
        results.append(imageio.read_layers(job.out)[0])
    a, b = results
    assert set(a) == set(b)
    for p in a:
        assert np.array_equal(a[p], b[p]), p


@pytest.mark.parametrize("method", ["uniform", "var"])
def test_renders_cut_into_bands_for_the_ui_give_the_same_file(tmp_path, method):
    """``render_seconds`` (the panel's Longest Render) far below what a render
    takes: every task, the initial subsets included, renders as bands of rows,
    and the EXR equals the uncut run's, pass for pass, bit for bit (Cycles
    samples a pixel by its own position and sample index, and each pixel's
    samples stay in one band)."""
    results, renders = [], []
    for name, seconds in (("whole.exr", 0.0), ("bands.exr", 1e-6)):
        scene = build_scene(24, 16)
        job = RenderJob(scene, bpy.context.view_layer,
                        Options(method=method, spp=8, initial_spp=2, subsets=2, frame=scene.frame_current,
                                task_cost=16, min_task_size=2, render_seconds=seconds), str(tmp_path / name))
        for _ in job.steps():
            pass
        job.finish()
        renders.append(job.run.tasks_rendered)
        results.append(imageio.read_layers(job.out)[0])
    assert renders[1] > renders[0]
    a, b = results
    assert set(a) == set(b)
    for p in a:
        assert np.array_equal(a[p], b[p]), p


def test_denoise_calibrates_the_variance_as_the_render_did(tmp_path):
    """The output keeps the layer's stratification exponent (header) and its
    groups' sizes (GroupPower), so ``denoise`` re-runs a method on the
    variance the render's reconstruction read (to the float32 rounding of
    the stored statistics), not the i.i.d. variance the file gave before
    (> 1.1x larger here).  LP's own image is not compared: its window and
    rank choices flip on that rounding (relMSE ~3e-2 between the two on this
    32x24 frame, from normals rounded by <= 3e-8)."""
    from cycles_adaptive.core.storage import buffers_from_passes
    from cycles_adaptive.core import variance
    scene = build_scene(32, 24)
    scene.cycles.seed = 3
    out = str(tmp_path / "lp.exr")
    job = RenderJob(scene, bpy.context.view_layer, Options(method="lp", spp=12, initial_spp=4, subsets=4,
                                                           frame=scene.frame_current, task_cost=16,
                                                           min_task_size=4), out)
    for _ in job.steps():
        pass
    job.finish()
    buf = job.run.buffers
    assert buf.exponent != 1.0 and buf.gsum is not None
    assert (buf.k > 4).any()  # the rounds' region groups: unequal sizes
    again = job_mod.denoise_output(out, "lp")
    passes, meta = imageio.read_layers(out)
    stored = buffers_from_passes(passes, out)
    job_mod.stored_exponent(stored, meta)
    assert stored.exponent == buf.exponent
    np.testing.assert_allclose(stored.gsum, buf.gsum, rtol=1e-6)
    v_render = buf.calibrated_variance()
    np.testing.assert_allclose(stored.calibrated_variance(), v_render, rtol=1e-4)
    stored.exponent, stored.gsum = 1.0, None  # what the file gave before
    noisy = v_render > 0
    assert np.median(stored.calibrated_variance()[noisy] / v_render[noisy]) > 1.1
    assert np.isfinite(again.passes["Combined"]).all()
    # uniform's error image is the calibrated variance itself: the re-run's equals the render's
    from cycles_adaptive.core import uniform
    want = uniform.reconstruct(job.run.view).error
    got = np.asarray(job_mod.denoise_output(out, "uniform").passes["Error"], np.float64).reshape(want.shape)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-12)

"""The modal operator's stepping logic (runs without a Blender window): time
slices, Work on a worker thread, Esc without waiting for it."""
import os
import threading
import time

import pytest

from cycles_adaptive.core.pipeline import Progress, Work
from cycles_adaptive.operators.stepper import Stepper, start_thread


class FakeRun:
    buffers = object()


def _main():
    assert threading.current_thread() is threading.main_thread(), "resumed off the main thread"


class FakeJob:
    """Yields ``n`` steps; step ``work_at`` carries ``work`` (a Work), and the
    loop then calls ``work.result()`` as AdaptiveRun does.  Every resume and
    ``finish`` asserts it runs on the main thread (where bpy lives)."""

    def __init__(self, n, work_at=None, work=None):
        self.n, self.closed, self.finished_with, self.run = n, False, None, None
        self.work_at, self.work = work_at, work
        self.resumed = 0
        self.results = []

    def steps(self):
        try:
            for i in range(self.n):
                _main()
                self.resumed += 1
                if i == 1:
                    self.run = FakeRun()
                w = self.work if i == self.work_at else None
                yield Progress("adapt" if w else "render", i, (i + 1) / self.n, f"step {i}", work=w)
                if w is not None:
                    self.results.append(w.result())
        finally:
            self.closed = True  # where the executor restores the scene

    def finish(self, partial=False, reconstruct=True):
        _main()
        self.finished_with = (partial, reconstruct)
        return {"partial": partial, "reconstructed": reconstruct}


class Threads:
    """``start`` for the Stepper that keeps the threads, so a test can join them."""

    def __init__(self):
        self.threads = []

    def __call__(self, fn):
        t = start_thread(fn)
        self.threads.append(t)
        return t

    def join(self):
        for t in self.threads:
            t.join(60)  # a guard against a hang, not a speed bound
            assert not t.is_alive()


def _blocked_work(release, seen):
    def fn():
        seen.append(threading.current_thread())
        release.wait(60)
        return 42
    return Work(fn, "adapting (test)")


def test_step_runs_to_the_end_and_writes_the_result():
    job = FakeJob(5)
    st = Stepper(job, slice_seconds=0.0)  # one step per tick
    ticks = 0
    while not st.step():
        ticks += 1
    assert ticks == 5 and st.fraction == 1.0 and job.finished_with == (False, True) and job.closed


def test_cancel_closes_the_generator_and_keeps_what_was_rendered():
    job = FakeJob(10)
    st = Stepper(job, slice_seconds=0.0)  # no writer thread: the write runs inside cancel()
    st.step(), st.step(), st.step()
    summary = st.cancel()
    assert job.closed and summary == {"partial": True, "reconstructed": False}
    assert job.finished_with == (True, False)  # the sample mean, written at once
    assert st.finished and not st.writing and st.summary is summary


def test_cancel_before_anything_rendered_writes_nothing():
    job = FakeJob(10)
    st = Stepper(job, slice_seconds=0.0)
    assert st.cancel() is None and job.finished_with is None and st.finished


def test_work_runs_on_a_worker_and_step_returns_while_it_is_pending():
    release, seen, threads = threading.Event(), [], Threads()
    work = _blocked_work(release, seen)
    job = FakeJob(4, work_at=2, work=work)
    st = Stepper(job, slice_seconds=10.0, start=threads)  # a long slice: only the Work stops it
    assert st.step() is False and st.stage == "adapt" and len(threads.threads) == 1
    resumed = job.resumed
    for _ in range(5):  # however often the timer ticks, the loop waits for the Work
        assert st.step() is False
    assert job.resumed == resumed and not work.done and st.pending is work
    release.set()
    threads.join()
    assert work.done and seen and seen[0] is not threading.main_thread()
    assert st.step() is True  # resumed on this thread: result() returns at once
    assert job.results == [42] and job.finished_with == (False, True)


def test_cancel_does_not_wait_for_a_running_work_and_writes_the_partial_result():
    release, seen, threads = threading.Event(), [], Threads()
    work = _blocked_work(release, seen)
    job = FakeJob(6, work_at=3, work=work)
    st = Stepper(job, slice_seconds=10.0, start=threads)
    assert st.step() is False and st.pending is work
    summary = st.cancel()
    assert not work.done  # Esc returned while the Work was still blocked
    assert job.closed and summary == {"partial": True, "reconstructed": False}
    assert job.results == []  # the loop never waited for it
    release.set()
    threads.join()
    assert st.step() is True and job.finished_with == (True, False)  # nothing more after a cancel


def test_a_failing_work_raises_on_the_main_thread():
    threads = Threads()

    def boom():
        raise ZeroDivisionError("adapt failed")
    job = FakeJob(4, work_at=1, work=Work(boom, "adapting"))
    st = Stepper(job, slice_seconds=10.0, start=threads)
    assert st.step() is False
    threads.join()
    with pytest.raises(ZeroDivisionError, match="adapt failed"):
        st.step()
    assert job.closed


def test_a_completed_work_is_not_started_again():
    work = Work(lambda: 7, "done already")
    work.run()
    started = []
    job = FakeJob(3, work_at=0, work=work)
    st = Stepper(job, slice_seconds=10.0, start=started.append)
    assert st.step() is True and started == [] and job.results == [7]


def test_message_counts_seconds_while_a_work_runs():
    release, seen, threads = threading.Event(), [], Threads()
    job = FakeJob(3, work_at=0, work=_blocked_work(release, seen))
    st = Stepper(job, slice_seconds=10.0, start=threads)
    st.step()
    assert st.message.startswith("step 0 (") and st.message.endswith(" s)")
    release.set()
    threads.join()
    assert st.step() is True and st.message == "step 2"


# ------------------------------------------------- outputs off the main thread
class WritingJob(FakeJob):
    """A FakeJob with ``write_steps`` as RenderJob has: one Work (the EXR
    write) that blocks until ``gate`` is set, then a part on the main thread."""

    def __init__(self, n):
        super().__init__(n)
        self.gate, self.writer_threads, self.main_part = threading.Event(), [], False

    def write_steps(self, partial=False, reconstruct=True):
        _main()

        def write():
            self.writer_threads.append(threading.current_thread())
            self.gate.wait(60)
        work = Work(write, "writing (test)")
        yield work
        work.result()
        _main()
        self.main_part = True
        return {"partial": partial, "reconstructed": reconstruct, "written": True}


def _writer_threads():
    threads = []

    def start(fn):
        from cycles_adaptive.operators.stepper import start_writer
        threads.append(start_writer(fn))
    return threads, start


def test_esc_returns_while_the_write_is_still_running_and_the_ui_ticks_until_it_ends():
    job = WritingJob(10)
    threads, start = _writer_threads()
    st = Stepper(job, slice_seconds=0.0, start_write=start)
    st.step(), st.step(), st.step()
    assert st.cancel() is None  # returned: the write is blocked on the gate
    assert job.closed and st.writing and st.cancelled and not job.main_part and st.stage == "write"
    for _ in range(5):
        assert st.step() is False and st.writing  # timer ticks meanwhile
    assert st.cancel() is None and len(threads) == 1  # a second Esc changes nothing
    assert job.writer_threads == threads and threads[0] is not threading.main_thread()
    assert not threads[0].daemon  # the interpreter's shutdown (Blender's quit) waits for it
    job.gate.set()
    threads[0].join(60)
    assert st.step() is True and job.main_part and not st.writing
    assert st.summary == {"partial": True, "reconstructed": False, "written": True}
    assert job.finished_with is None  # written through write_steps, not finish()


def test_the_end_of_a_run_is_written_off_the_main_thread_too():
    job = WritingJob(3)
    threads, start = _writer_threads()
    st = Stepper(job, slice_seconds=10.0, start_write=start)
    assert st.step() is False and st.writing and not st.cancelled
    assert st.message.startswith("writing")
    job.gate.set()
    threads[0].join(60)
    assert st.step() is True and st.summary["partial"] is False and st.summary["reconstructed"]


def test_wait_finishes_a_pending_write_on_the_calling_thread():
    job = WritingJob(4)
    threads, start = _writer_threads()
    st = Stepper(job, slice_seconds=0.0, start_write=start)
    st.step()
    st.step()
    st.cancel()
    job.gate.set()
    assert st.wait() == {"partial": True, "reconstructed": False, "written": True} and job.main_part


def test_a_failed_write_raises_once_and_is_not_retried():
    class Failing(WritingJob):
        def write_steps(self, partial=False, reconstruct=True):
            work = Work(lambda: 1 / 0, "writing (test)")
            yield work
            work.result()
    job = Failing(3)
    st = Stepper(job, slice_seconds=0.0, start_write=lambda fn: fn())  # "thread" that runs at once
    st.step(), st.step()
    st.cancel()
    with pytest.raises(ZeroDivisionError):
        st.step()
    assert st.finished and not st.writing and st.step() is True and st.summary is None


def test_esc_before_the_exr_is_written_then_complete_files_match_an_inline_write(tmp_path, monkeypatch):
    """A real (tiny) render: Esc returns while the EXR write is held back on
    the writer thread (no file yet); afterwards the EXR holds every pass of
    the job's output, the PNG preview has the pixels of Blender's direct PNG
    save (the main-thread path of the CLI), no temporary file is left, and
    finish() returns the same summary without writing again."""
    bpy = pytest.importorskip("bpy")
    import os

    import numpy as np
    from blend_util import build_scene

    from cycles_adaptive.addon import executor as ex
    from cycles_adaptive.core import io as imageio
    from cycles_adaptive.core.pipeline import Options
    from cycles_adaptive.operators import job as job_mod

    gate, exr_threads = threading.Event(), []
    real_write = job_mod.write_output

    def held_write(output, path):
        exr_threads.append(threading.current_thread())
        gate.wait(60)
        real_write(output, path)
    monkeypatch.setattr(job_mod, "write_output", held_write)
    real_tiff = job_mod.RenderJob._save_display_tiff

    def tiff_on_main(self, *a):
        _main()  # the preview's bpy part
        return real_tiff(self, *a)
    monkeypatch.setattr(job_mod.RenderJob, "_save_display_tiff", tiff_on_main)

    scene = build_scene(24, 16)
    out = str(tmp_path / "esc.exr")
    png = str(tmp_path / "esc.png")
    opts = Options(method="var", spp=8, initial_spp=2, subsets=2, frame=scene.frame_current, task_cost=64)
    job = job_mod.RenderJob(scene, bpy.context.view_layer, opts, out)
    threads, start = _writer_threads()
    loop_threads = Threads()
    st = Stepper(job, slice_seconds=0.0, start=loop_threads, start_write=start)
    for _ in range(40):  # past the initial pass and its checkpoint (Works on threads)
        assert st.step() is False
        loop_threads.join()
        if st.stage == "checkpoint" or st.stage == "adapt":
            break
    assert st.cancel() is None and st.writing
    assert not os.path.exists(out) and not os.path.exists(png)  # Esc came back before the write
    assert st.step() is False and job.view_layer is not bpy.context.view_layer  # name only, off-thread
    gate.set()
    while not st.step():
        for t in threads:
            t.join(60)
    summary = st.summary
    assert exr_threads and exr_threads[0] is not threading.main_thread() and not exr_threads[0].daemon
    assert job.view_layer == bpy.context.view_layer and summary["partial"] and not summary["reconstructed"]
    passes, meta = imageio.read_layers(out)
    expected = job.output().passes
    assert set(passes) == set(expected)
    for name, value in expected.items():
        arr = np.asarray(value[0] if isinstance(value, tuple) else value, np.float32)
        if name in job_mod.RESULT_PASSES:  # stored in half float (the scene saves PNG)
            arr = imageio.as_half(arr)
        assert np.array_equal(passes[name].reshape(arr.shape), arr), name
    # the sample mean
    assert np.array_equal(passes["Combined"][..., :3], imageio.as_half(passes["Noisy"][..., :3]))
    attrs = meta["attributes"]
    assert attrs["cycles_adaptive/partial"] == "true" and attrs["cycles_adaptive/reconstructed"] == "false"
    assert os.path.isfile(out + ".checkpoint.npz")  # kept for --resume
    direct = str(tmp_path / "direct.png")
    ex.write_preview(scene, expected["Combined"][0] if isinstance(expected["Combined"], tuple)
                     else expected["Combined"], direct)
    a, b = imageio.read_layers(png)[0][""], imageio.read_layers(direct)[0][""]
    assert a.shape == b.shape == (16, 24, 4) and np.array_equal(a, b)
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".tmp-")]
    assert job.finish(partial=True) is summary and len(exr_threads) == 1  # nothing written twice


def test_esc_in_a_frame_range_writes_the_frame_in_progress_on_the_writer_thread(tmp_path):
    bpy = pytest.importorskip("bpy")
    import os

    from blend_util import build_scene

    from cycles_adaptive.core import io as imageio
    from cycles_adaptive.core.pipeline import Options
    from cycles_adaptive.operators.job import FramesJob

    scene = build_scene(16, 12)
    scene.frame_start, scene.frame_end = 1, 2
    opts = Options(method="var", spp=6, initial_spp=2, subsets=2, frame=1, task_cost=64)
    job = FramesJob(scene, bpy.context.view_layer, opts, str(tmp_path / "f_####.exr"), [1, 2])
    threads, start = _writer_threads()
    st = Stepper(job, slice_seconds=0.0, start=Threads(), start_write=start)
    while job.job is None or job.job.options.frame != 2 or job.job.run is None or job.job.run.buffers is None:
        assert st.step() is False
    st.cancel()
    assert st.writing and threads  # the frame in progress is written on the writer thread
    while not st.step():
        for t in threads:
            t.join(60)
    summary = st.summary
    assert summary["outs"] == [str(tmp_path / "f_0001.exr"), str(tmp_path / "f_0002.exr")]
    meta = imageio.read_layers(str(tmp_path / "f_0002.exr"))[1]["attributes"]
    assert meta["cycles_adaptive/partial"] == "true" and os.path.isfile(str(tmp_path / "f_0002.png"))


def test_loop_works_are_daemons_joined_by_the_exit_hook():
    from cycles_adaptive.operators import stepper
    release, seen = threading.Event(), []
    t = start_thread(lambda: (release.wait(60), seen.append(1)))
    assert t.daemon and t in stepper._running
    release.set()
    stepper._join_running()  # what the interpreter's exit runs
    assert not t.is_alive() and seen == [1]


def test_a_work_that_must_run_on_the_main_thread_runs_inline():
    ran_on = []
    work = Work(lambda: ran_on.append(threading.current_thread()) or 5, "oidn (Blender's)", main_thread=True)
    started = []
    job = FakeJob(3, work_at=1, work=work)
    st = Stepper(job, slice_seconds=10.0, start=started.append)
    assert st.step() is True and started == [] and ran_on == [threading.main_thread()] and job.results == [5]


def test_frames_that_finish_mid_range_are_written_off_the_main_thread(tmp_path, monkeypatch):
    bpy = pytest.importorskip("bpy")
    from blend_util import build_scene

    from cycles_adaptive.core.pipeline import Options
    from cycles_adaptive.operators import job as jobs

    scene = build_scene(16, 12)
    scene.frame_start, scene.frame_end = 1, 2
    opts = Options(method="var", spp=4, initial_spp=2, subsets=2, frame=1, task_cost=64)
    written = []
    real = jobs.write_output

    def recording(output, path):
        written.append((path, threading.current_thread() is threading.main_thread()))
        real(output, path)

    monkeypatch.setattr(jobs, "write_output", recording)
    job = jobs.FramesJob(scene, bpy.context.view_layer, opts, str(tmp_path / "f_####.exr"), [1, 2])
    threads = Threads()
    st = Stepper(job, slice_seconds=0.0, start=threads, start_write=start_thread)
    for _ in range(10000):
        if st.step():
            break
        time.sleep(0.001)
    threads.join()
    assert [os.path.basename(p) for p, _ in written] == ["f_0001.exr", "f_0002.exr"]
    assert not any(on_main for _, on_main in written)  # neither frame's EXR was written on the main thread
    assert st.summary["outs"] == [str(tmp_path / "f_0001.exr"), str(tmp_path / "f_0002.exr")]


def test_after_write_work_runs_on_the_writer_thread_before_the_end():
    job = WritingJob(3)
    threads, start = _writer_threads()
    seen = []

    def after(j):
        assert j is job
        return Work(lambda: seen.append(threading.current_thread() is threading.main_thread()) or "pixels",
                    "preparing (test)")

    st = Stepper(job, slice_seconds=10.0, start_write=start, after_write=after)
    assert st.step() is False
    job.gate.set()
    while not st.step():
        for t in list(threads):
            t.join(60)
    assert seen == [False]  # ran once, on a writer thread, before step() said the end


def test_the_image_editor_pixels_are_prepared_without_blender_and_shown_as_given():
    bpy = pytest.importorskip("bpy")
    import numpy as np

    from cycles_adaptive.addon import display
    rng = np.random.default_rng(0)
    image = rng.random((6, 5, 3))
    samples = rng.integers(1, 9, (6, 5)).astype(float)
    error = rng.random((6, 5)) * 1e-2
    composite = rng.random((6, 5, 4)).astype(np.float32)
    prepared = display.prepare_result(image, samples, error, composite=composite)
    assert set(prepared) == {display.RESULT, display.SAMPLES, display.ERROR, display.COMPOSITE}
    shown = display.show_prepared(prepared)
    assert shown.name == display.COMPOSITE
    px = np.empty(6 * 5 * 4, np.float32)
    bpy.data.images[display.RESULT].pixels.foreach_get(px)
    np.testing.assert_allclose(px.reshape(6, 5, 4)[::-1][..., :3], image, atol=1e-6)  # rows bottom to top
    bpy.data.images[display.SAMPLES].pixels.foreach_get(px)
    np.testing.assert_allclose(px.reshape(6, 5, 4)[::-1][..., 0], samples / samples.max(), atol=1e-6)


def test_esc_during_a_merge_writes_the_partial_result_after_the_merge_ends(tmp_path, monkeypatch):
    """A large task's merge runs as a Work that changes the buffers: Esc
    returns at once, and the partial result is computed only once that merge
    has ended (never from half-merged buffers): its samples are those of
    every merged subset."""
    bpy = pytest.importorskip("bpy")
    import numpy as np
    from blend_util import build_scene

    from cycles_adaptive.core import io as imageio
    from cycles_adaptive.core import pipeline
    from cycles_adaptive.core.pipeline import Options
    from cycles_adaptive.operators import job as job_mod

    monkeypatch.setattr(pipeline, "MERGE_WORK_PIXELS", 1)  # every merge a background Work
    gate, events = threading.Event(), []
    real_merge = pipeline.merge_render

    def gated_merge(buf, task, color, feats):
        if task.offset > 0:  # the second subset's merge waits for the test
            gate.wait(60)
        real_merge(buf, task, color, feats)
        events.append(("merged", task.offset))
    monkeypatch.setattr(pipeline, "merge_render", gated_merge)
    real_output = job_mod.RenderJob.output

    def output(self, *a, **kw):
        events.append(("output", None))
        return real_output(self, *a, **kw)
    monkeypatch.setattr(job_mod.RenderJob, "output", output)

    scene = build_scene(24, 16)
    opts = Options(method="var", spp=8, initial_spp=2, subsets=2, frame=scene.frame_current, task_cost=64)
    job = job_mod.RenderJob(scene, bpy.context.view_layer, opts, str(tmp_path / "m.exr"), preview=False)
    loop_threads = Threads()
    threads, start = _writer_threads()
    st = Stepper(job, slice_seconds=0.0, start=loop_threads, start_write=start)
    for _ in range(3000):
        assert st.step() is False
        if st.stage == "merge" and st.pending is not None and not st.pending.done and events:
            break  # the second subset's merge is running (the first is done)
        time.sleep(0.01)
    assert st.stage == "merge" and events == [("merged", 0)]
    assert st.cancel() is None and st.writing  # Esc: back at once, the write waits
    assert events == [("merged", 0)]
    gate.set()
    while not st.step():
        for t in threads + loop_threads.threads:
            t.join(60)
    assert events == [("merged", 0), ("merged", 1), ("output", None)]
    passes, _ = imageio.read_layers(job.out)
    assert st.summary["partial"] and np.all(passes["Samples"] == 2)  # both 1-spp subsets

"""The modal operator's stepping logic (runs without a Blender window): time
slices, Work on a worker thread, Esc without waiting for it."""
import threading

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
    st = Stepper(job, slice_seconds=0.0)
    st.step(), st.step(), st.step()
    summary = st.cancel()
    assert job.closed and summary == {"partial": True, "reconstructed": False}
    assert job.finished_with == (True, False)  # the sample mean, written at once


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

"""The modal operator's stepping logic (runs without a Blender window)."""
from cycles_adaptive.operators.stepper import Stepper


class FakeRun:
    buffers = object()


class FakeJob:
    def __init__(self, n):
        self.n, self.closed, self.finished_with, self.run = n, False, None, None

    def steps(self):
        try:
            for i in range(self.n):
                if i == 1:
                    self.run = FakeRun()
                yield type("P", (), {"fraction": (i + 1) / self.n, "message": f"step {i}"})()
        finally:
            self.closed = True  # where the executor restores the scene

    def finish(self, partial=False):
        self.finished_with = partial
        return {"partial": partial}


def test_step_runs_to_the_end_and_writes_the_result():
    job = FakeJob(5)
    st = Stepper(job, slice_seconds=0.0)  # one step per tick
    ticks = 0
    while not st.step():
        ticks += 1
    assert ticks == 5 and st.fraction == 1.0 and job.finished_with is False and job.closed


def test_cancel_closes_the_generator_and_keeps_what_was_rendered():
    job = FakeJob(10)
    st = Stepper(job, slice_seconds=0.0)
    st.step(), st.step(), st.step()
    summary = st.cancel()
    assert job.closed and summary == {"partial": True} and job.finished_with is True


def test_cancel_before_anything_rendered_writes_nothing():
    job = FakeJob(10)
    st = Stepper(job, slice_seconds=0.0)
    assert st.cancel() is None and job.finished_with is None and st.finished

"""Time-sliced stepping of a job's progress generator (no bpy): the modal
operator calls ``step()`` from a timer so Blender's UI stays responsive, and
``cancel()`` on Esc, which closes the generator (the executor restores the
scene on the way out) and writes what was rendered."""
from __future__ import annotations

import time


class Stepper:
    def __init__(self, job, slice_seconds: float = 0.05):
        self.job = job
        self.slice = slice_seconds
        self.gen = job.steps()
        self.last = None       # last Progress seen
        self.finished = False  # generator ran to its end
        self.summary = None

    @property
    def fraction(self) -> float:
        return getattr(self.last, "fraction", 0.0)

    @property
    def message(self) -> str:
        return getattr(self.last, "message", "")

    def step(self) -> bool:
        """Advance for up to one time slice (at least one step); True once the
        loop has ended and the outputs are written."""
        if self.finished:
            return True
        t_end = time.perf_counter() + self.slice
        try:
            while True:
                item = next(self.gen)
                if not isinstance(item, dict):  # frame ranges also yield per-frame summaries
                    self.last = item
                if time.perf_counter() >= t_end:
                    return False
        except StopIteration:
            self.finished = True
        self.summary = self.job.finish(partial=False)
        return True

    def cancel(self):
        """Stop now; write the partial result if anything was rendered.
        Returns the summary, or None when nothing was rendered."""
        self.gen.close()
        run = getattr(self.job, "run", None)
        if not self.finished and run is not None and getattr(run, "buffers", None) is not None:
            self.summary = self.job.finish(partial=True)
        self.finished = True
        return self.summary

"""Time-sliced stepping of a job's progress generator (no bpy): the modal
operator calls ``step()`` from a timer so Blender's UI stays responsive, and
``cancel()`` on Esc.

The slow pure computations of a run (each iteration's adaptation, the final
reconstruction: up to tens of seconds at 1920x1080) arrive as
``Progress.work`` (:class:`core.pipeline.Work`).  The stepper runs each on a
daemon worker thread (numpy releases the GIL) and ``step()`` returns at once
while it runs; the generator, and with it every Cycles render and bpy call, is
only ever resumed on the caller's (main) thread, once the work is done.

Esc (``cancel()``) never waits for a running Work: it closes the generator (the
executor restores the scene) and writes the partial result at once, the sample
mean unless the final reconstruction had completed (``RenderJob.output`` with
``reconstruct=False``); nothing is lost, every sample and pass is in the EXR
and the checkpoint is kept for ``--resume``.  An abandoned Work finishes on its
thread and its result is dropped.  Measurements: docs/notes/responsive-ui.md.
"""
from __future__ import annotations

import threading
import time


def start_thread(fn) -> threading.Thread:
    """Run ``fn`` on a new daemon thread (a daemon, so quitting Blender never
    waits for an abandoned computation)."""
    t = threading.Thread(target=fn, name="cycles-adaptive-work", daemon=True)
    t.start()
    return t


class Stepper:
    """Steps ``job.steps()`` in time slices; ``start(fn)`` launches a Work's
    ``run`` off the calling thread (default :func:`start_thread`)."""

    def __init__(self, job, slice_seconds: float = 0.05, start=start_thread):
        self.job = job
        self.slice = slice_seconds
        self.start = start
        self.gen = job.steps()
        self.last = None       # last Progress seen
        self.pending = None    # the Work running on a worker thread, if any
        self.pending_since = 0.0
        self.finished = False  # generator ran to its end (or was cancelled)
        self.summary = None

    @property
    def fraction(self) -> float:
        return getattr(self.last, "fraction", 0.0)

    @property
    def stage(self) -> str:
        return getattr(self.last, "stage", "")

    @property
    def message(self) -> str:
        """The last step's message; while a Work runs, with its seconds so far
        (so the status bar shows the run is alive)."""
        msg = getattr(self.last, "message", "")
        if self.pending is not None:
            msg = f"{msg} ({time.perf_counter() - self.pending_since:.0f} s)"
        return msg

    def step(self) -> bool:
        """Advance for up to one time slice (at least one step unless a Work
        is running); True once the loop has ended and the outputs are written.
        A Work's exception is re-raised here, on the caller's thread."""
        if self.finished:
            return True
        if self.pending is not None:
            if not self.pending.done:
                return False
            self.pending = None  # the loop's work.result() now returns at once (or raises)
        t_end = time.perf_counter() + self.slice
        try:
            while True:
                item = next(self.gen)
                if isinstance(item, dict):  # frame ranges also yield per-frame summaries
                    continue
                self.last = item
                work = getattr(item, "work", None)
                if work is not None and not work.done:
                    self.pending, self.pending_since = work, time.perf_counter()
                    self.start(work.run)
                    return False
                if time.perf_counter() >= t_end:
                    return False
        except StopIteration:
            self.finished = True
        self.summary = self.job.finish(partial=False)
        return True

    def cancel(self):
        """Stop now, without waiting for a running Work; write the partial
        result if anything was rendered (the sample mean unless the final
        reconstruction had completed).  Returns the summary, or None when
        nothing was rendered."""
        self.gen.close()
        self.pending = None
        run = getattr(self.job, "run", None)
        if not self.finished and run is not None and getattr(run, "buffers", None) is not None:
            self.summary = self.job.finish(partial=True, reconstruct=False)
        self.finished = True
        return self.summary

"""Time-sliced stepping of a job's progress generator (no bpy): the modal
operator calls ``step()`` from a timer so Blender's UI stays responsive, and
``cancel()`` on Esc.

The slow pure computations of a run (each iteration's adaptation, the final
reconstruction: up to tens of seconds at 1920x1080) arrive as
``Progress.work`` (:class:`core.pipeline.Work`).  The stepper runs each on a
daemon worker thread (numpy releases the GIL) and ``step()`` returns at once
while it runs; the generator, and with it every Cycles render and bpy call, is
only ever resumed on the caller's (main) thread, once the work is done.

When the loop ends, or on Esc, the outputs are written the same way, through
the job's ``write_steps`` (``RenderJob.write_steps``): the result and the EXR
write (seconds at 1920x1080) and the PNG encoding run on a writer thread, the
short bpy part of the preview on the main thread; ``writing`` is True until
the files are complete and ``step()`` returns True.  The writer thread is not
a daemon: quitting Blender (``Py_Finalize``) waits for it, so a quit during the
write still leaves the complete EXR (files are written to a temporary name and
renamed, so a killed process leaves none half-written).

Esc (``cancel()``) never waits for a running Work: it closes the generator (the
executor restores the scene) and starts writing the partial result, the sample
mean unless the final reconstruction had completed (``RenderJob.output`` with
``reconstruct=False``); nothing is lost, every sample and pass is in the EXR
and the checkpoint is kept for ``--resume``.  An abandoned Work finishes on its
thread and its result is dropped.  Measurements: docs/notes/responsive-ui.md.
"""
from __future__ import annotations

import atexit
import threading
import time
import weakref

from ..core.pipeline import Work

_running: "weakref.WeakSet[threading.Thread]" = weakref.WeakSet()


def start_thread(fn) -> threading.Thread:
    """Run ``fn`` on a new daemon thread (a daemon: the interpreter does not
    join it, so an abandoned computation never blocks the write path); at
    exit :func:`_join_running` waits for it."""
    t = threading.Thread(target=fn, name="cycles-adaptive-work", daemon=True)
    t.start()
    _running.add(t)
    return t


@atexit.register
def _join_running() -> None:
    """At interpreter exit, wait for loop Works still running (an adaptation
    abandoned by Esc, seconds): the bpy module's process otherwise hangs in
    Blender's C exit handlers when one is still computing (measured,
    docs/notes/responsive-ui.md)."""
    for t in list(_running):
        t.join()


def start_writer(fn) -> threading.Thread:
    """Run ``fn`` (an output write) on a new thread that is not a daemon: the
    interpreter's shutdown, and so Blender's quit, waits for it to end."""
    t = threading.Thread(target=fn, name="cycles-adaptive-write", daemon=False)
    t.start()
    return t


class Stepper:
    """Steps ``job.steps()`` in time slices, then the job's outputs;
    ``start(fn)`` launches a loop Work's ``run`` off the calling thread
    (default :func:`start_thread`), ``start_write(fn)`` a write's (the modal
    operator passes :func:`start_writer`; default None: the write runs inline,
    within the ``step()`` or ``cancel()`` that begins it)."""

    def __init__(self, job, slice_seconds: float = 0.05, start=start_thread, start_write=None,
                 after_write=None):
        """``after_write(job)``: called once the outputs are written; a Work
        it returns (e.g. the Image Editor's pixels, numpy only) runs on the
        writer thread too, before ``step()`` returns True."""
        self.job = job
        self.after_write = after_write
        self.slice = slice_seconds
        self.start = start
        self.start_write = start_write
        self.gen = job.steps()
        self.last = None       # last Progress seen
        self.pending = None    # the Work running on a worker thread, if any
        self.pending_since = 0.0
        self.writer = None     # the outputs' write steps, once the loop ended or was cancelled
        self.cancelled = False
        self.finished = False  # outputs written (or nothing to write after a cancel)
        self.summary = None

    @property
    def writing(self) -> bool:
        """True from the end of the loop (or Esc) until the outputs are complete."""
        return self.writer is not None

    @property
    def fraction(self) -> float:
        return getattr(self.last, "fraction", 0.0)

    @property
    def stage(self) -> str:
        return "write" if self.writing else getattr(self.last, "stage", "")

    @property
    def message(self) -> str:
        """The last step's message (``writing OUT`` while the outputs are
        written); while a Work runs, with its seconds so far (so the status
        bar shows the run is alive)."""
        msg = getattr(self.last, "message", "")
        if self.writing:
            out = getattr(getattr(self.job, "job", None) or self.job, "out", None)
            msg = f"writing {out}..." if out else "writing..."
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
        if self.writer is not None:
            return self._advance_writer()
        t_end = time.perf_counter() + self.slice
        try:
            while True:
                item = next(self.gen)
                if isinstance(item, dict):  # frame ranges also yield per-frame summaries
                    continue
                self.last = item
                work = getattr(item, "work", None)
                if work is not None and not work.done:
                    if getattr(work, "main_thread", False):
                        work.run()  # it calls Blender (its own OIDN): inline, on this thread
                    else:
                        self._launch(work, self.start)
                        return False
                if time.perf_counter() >= t_end:
                    return False
        except StopIteration:
            pass
        self.writer = self._write_steps(partial=False, reconstruct=True)
        return self._advance_writer()

    def cancel(self):
        """Esc: stop now, without waiting for a running Work, and write the
        partial result if anything was rendered (the sample mean unless the
        final reconstruction had completed).  Returns the summary once the
        outputs are written, None otherwise: nothing was rendered, or the
        write goes on on a writer thread (``writing``; ``step()`` returns True
        once it is complete, ``summary`` then holds it).  While the outputs
        are already being written (the loop had ended) it changes nothing."""
        if self.finished or self.writer is not None:
            return self.summary
        # a Work that changes the buffers (a merge) must end before the partial
        # result reads them: the write waits for it, on the writer thread
        settle = self.pending if getattr(self.pending, "mutates", False) else None
        self.gen.close()
        self.pending = None
        self.cancelled = True
        run = getattr(self.job, "run", None)
        if run is None or getattr(run, "buffers", None) is None:
            self.finished = True
            return None
        # the loop's background merge (the last of any still to land), if any
        settle = getattr(run, "pending_merge", None) or settle
        self.writer = self._write_steps(partial=True, reconstruct=False, settle=settle)
        self._advance_writer()
        return self.summary

    def wait(self) -> dict | None:
        """Finish what is left (the loop, or after a cancel the write) on this
        thread, running each remaining Work inline; the summary (None when a
        cancel had nothing to write).  For a failure path or a batch caller."""
        while not self.step():
            if self.pending is not None:
                self.pending.run()  # waits for the thread already running it (Work.run is idempotent)
        return self.summary

    def _launch(self, work, start):
        self.pending, self.pending_since = work, time.perf_counter()
        start(work.run)

    def _advance_writer(self) -> bool:
        """Resume the write steps until their next Work (started on a writer
        thread; run here without ``start_write``) or their end (the
        summary)."""
        while True:
            try:
                work = next(self.writer)
            except StopIteration as stop:
                self.writer, self.summary, self.finished = None, stop.value, True
                return True
            except BaseException:  # a failed write is not retried
                self.writer, self.finished = None, True
                raise
            if work.done:
                continue
            if self.start_write is None or getattr(work, "main_thread", False):
                work.run()
                continue
            self._launch(work, self.start_write)
            return False

    def _write_steps(self, partial: bool, reconstruct: bool, settle=None):
        """The job's outputs as steps: a RenderJob's ``write_steps``; a frame
        range writes the frame in progress through its RenderJob's, then its
        own ``finish`` (which finds that frame written); any other job's
        ``finish`` inline.  ``settle``: a Work changing the buffers, still
        running after Esc; waited for first (``Work.run`` waits for the
        thread running it)."""
        if settle is not None:
            yield Work(settle.run, "finishing the merge in progress")
        summary = yield from self._job_write_steps(partial, reconstruct)
        work = self.after_write(self.job) if self.after_write is not None else None
        if work is not None:
            yield work
            work.result()
        return summary

    def _job_write_steps(self, partial: bool, reconstruct: bool):
        job = self.job
        inner = getattr(job, "job", None)
        if hasattr(job, "write_steps"):
            return (yield from job.write_steps(partial, reconstruct))
        if partial and hasattr(inner, "write_steps") and getattr(inner, "run", None) is not None \
                and inner.run.buffers is not None:
            yield from inner.write_steps(partial, reconstruct)
        return job.finish(partial=partial, reconstruct=reconstruct)

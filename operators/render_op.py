"""The Render Properties button: a modal operator that steps the render job
from a timer, so Blender never freezes; progress in the panel and the status
bar; Esc cancels and keeps (and writes) what was rendered.  The outputs are
written on a writer thread (``Stepper``/``RenderJob.write_steps``), after the
run as after Esc: Esc returns at once and the panel shows "writing..." until
the files are complete, then the result.

``execute()`` (no window, e.g. ``bpy.ops.cycles_adaptive.render()`` from a
script or under ``blender -b``) runs the same job synchronously.
"""
from __future__ import annotations

import traceback

import bpy

from ..addon.props import method_params, options
from .cli import default_out, default_out_pattern, ensure_output_folder
from .job import FramesJob, JobError, LayersJob, RenderJob, resolve_view_layers
from .stepper import Stepper, start_writer

STEP_SECONDS = 0.05  # work per timer tick before handing control back to the UI

#: status-bar words of the loop's stages (``core.pipeline.Progress.stage``)
STAGE_WORDS = {"initial": "Rendering", "adapt": "Adapting", "plan": "Planning", "render": "Rendering", "merge": "Merging",
               "saving": "Saving checkpoint", "checkpoint": "Iteration done", "done": "Sampling done", "reconstruct": "Reconstructing",
               "write": "Writing"}


def status_line(stepper) -> str:
    """The status bar's text: percentage of the budget, the stage in words
    and the loop's message (with seconds so far while a computation runs)."""
    word = STAGE_WORDS.get(stepper.stage, "Working")
    if stepper.writing:
        what = "cancelled, " if stepper.cancelled else ""
        return f"Cycles Adaptive: {what}{word}: {stepper.message}"
    return f"Cycles Adaptive: {100 * stepper.fraction:.0f}% {word}: {stepper.message}  (Esc cancels)"


def store_summary(settings, summary: dict, cancelled: bool) -> None:
    """Keep a run's summary on the scene's settings for the panel: mean spp,
    seconds, estimated relMSE (the run's own error estimate, no reference),
    whether it was reconstructed, and a one-line status."""
    settings.last_spp = float(summary.get("spp_mean", 0.0))
    settings.last_seconds = float(summary.get("total_seconds", 0.0))
    settings.last_error = float(summary.get("estimated_relmse", 0.0))
    settings.last_reconstructed = bool(summary.get("reconstructed", True))
    settings.last_method = str(summary.get("method", ""))
    settings.last_chosen = str(summary.get("chosen", ""))  # auto: what it ran
    settings.has_result = True
    what = "Cancelled" if cancelled else "Done"
    note = "" if settings.last_reconstructed else " (not reconstructed: sample mean)"
    settings.status = f"{what}: {settings.last_spp:.1f} spp{note}, wrote {summary.get('out')}"


def _display_work(job):
    """The Image Editor's pixels of ``job``'s result as a Work (numpy only:
    the stepper runs it on the writer thread), or None when there is none."""
    from ..addon.display import prepare_result
    from ..core.pipeline import Work
    run = job.run
    inner = getattr(job, "job", job)  # a FramesJob shows its last frame
    res = getattr(inner, "result", None)
    if run is None or run.buffers is None or res is None:
        return None
    alpha = run.buffers.features["alpha"].mean if "alpha" in run.buffers.features else None
    composite = getattr(inner, "composite", None)
    return Work(lambda: prepare_result(res.image, run.buffers.n, res.error, alpha, composite),
                "preparing the Image Editor's images")


def _show(job, prepared=None):
    """Show the result in the Image Editor: the pixels ``prepared`` off the
    main thread (:func:`_display_work`), else prepared here."""
    from ..addon.display import show_prepared
    if prepared is None:
        work = _display_work(job)
        if work is None:
            return
        prepared = work.result()
    show_prepared(prepared)


class CYCLESADAPTIVE_OT_render(bpy.types.Operator):
    """Adaptive render of the current frame with the chosen method and budget"""

    bl_idname = "cycles_adaptive.render"
    bl_label = "Adaptive Render"
    bl_options = {"REGISTER"}

    _timer = None
    _job = None
    _display = None
    _stepper = None

    @classmethod
    def poll(cls, context):
        return context.scene is not None and context.scene.render.engine == "CYCLES"

    # ------------------------------------------------------------- batch path
    def execute(self, context):
        scene = context.scene
        try:
            job = self._make_job(context)
            for _ in job.steps():
                pass
            summary = job.finish()
        except JobError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        except Exception as exc:  # the scene is restored by the executor already
            self.report({"ERROR"}, f"adaptive render failed: {exc}")
            traceback.print_exc()
            return {"CANCELLED"}
        _show(job)
        store_summary(scene.cycles_adaptive, summary, cancelled=False)
        self.report({"INFO"}, scene.cycles_adaptive.status)
        return {"FINISHED"}

    # ------------------------------------------------------------- modal path
    def invoke(self, context, event):
        if context.window is None:
            return self.execute(context)
        try:
            self._job = self._make_job(context)
        except Exception as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self._display = None
        self._stepper = Stepper(self._job, STEP_SECONDS, start_write=start_writer, after_write=self._prepare)
        s = context.scene.cycles_adaptive
        s.running, s.progress, s.status = True, 0.0, "Starting"
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.01, window=context.window)
        wm.progress_begin(0, 1000)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        st = self._stepper
        if event.type == "ESC" and event.value == "PRESS" and not st.writing:
            # returns at once: the partial result is written on a writer thread
            # while the timer keeps ticking (Esc during the write changes nothing)
            try:
                st.cancel()
            except Exception as exc:
                return self._failed(context, exc)
            if st.finished:  # nothing was rendered
                return self._end(context, cancelled=True)
            self._update(context)
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            ended = st.step()
        except Exception as exc:
            return self._failed(context, exc)
        if ended:
            return self._end(context, cancelled=st.cancelled)
        self._update(context)
        return {"RUNNING_MODAL"}

    def _prepare(self, job):
        self._display = _display_work(job)
        return self._display

    def _update(self, context):
        """Progress and stage into the panel, the progress bar and the status bar."""
        s, st = context.scene.cycles_adaptive, self._stepper
        s.progress, s.status = st.fraction, st.message
        if st.writing and st.cancelled:
            s.status = f"Cancelled: {st.message}"
        context.window_manager.progress_update(int(1000 * s.progress))
        if context.workspace:
            context.workspace.status_text_set(status_line(st))
        for area in context.screen.areas if context.screen else ():
            if area.type == "PROPERTIES":
                area.tag_redraw()

    def _failed(self, context, exc):
        self.report({"ERROR"}, f"adaptive render failed: {exc}")
        traceback.print_exc()
        return self._end(context, cancelled=True, failed=True)

    def _end(self, context, cancelled: bool, failed: bool = False):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        if context.workspace:
            context.workspace.status_text_set(None)
        s = context.scene.cycles_adaptive
        s.running = False
        try:
            st = self._stepper
            if failed and not st.finished:  # the loop failed: write what was rendered, here
                st.cancel()
                st.wait()
            summary = st.summary
            if summary is not None:
                _show(self._job, self._display.result() if self._display is not None else None)
                store_summary(s, summary, cancelled)
            else:
                s.status = "Failed: nothing written" if failed else "Cancelled before any sample was rendered"
        except Exception as exc:
            s.status = f"Could not write the result: {exc}"
            self.report({"ERROR"}, s.status)
        self.report({"WARNING" if cancelled else "INFO"}, s.status)
        return {"CANCELLED"} if cancelled or failed else {"FINISHED"}

    def _make_job(self, context):
        """The job of the panel's settings.  An empty Output field means the
        scene's Output path with Blender's frame numbering and the method
        suffix, as the command line's default (``cli.default_out_pattern``)."""
        scene = context.scene
        s = scene.cycles_adaptive
        opts = options(scene)
        path = s.output_path.strip()
        layers = resolve_view_layers(scene, None, context.view_layer)  # what F12 would render
        if s.frame_range:
            frames = list(range(scene.frame_start, scene.frame_end + 1, max(1, scene.frame_step)))
            if not path:
                out = ensure_output_folder(default_out_pattern(scene, opts.method))
            else:
                out = path if "#" in path else \
                    path.replace(".exr", "_####.exr") if path.endswith(".exr") else path + "_####.exr"
            return FramesJob(scene, layers[0], opts, out, frames,
                             temporal=s.temporal, overwrite=s.overwrite,
                             reproject_params=method_params(s, "reproject"),
                             temporal_params=method_params(s, "temporal"),
                             history_params=method_params(s, "history"),
                             view_layers=layers, compositor=s.use_compositor, exr_depth=s.exr_depth,
                             exr_contents=s.exr_contents, seed_mode=s.seed_mode)
        out = path or ensure_output_folder(default_out(scene, opts.method, scene.frame_current))
        kw = dict(overwrite=s.overwrite, compositor=s.use_compositor, exr_depth=s.exr_depth,
                  exr_contents=s.exr_contents)
        if len(layers) > 1:
            return LayersJob(scene, layers, opts, out, **kw)
        return RenderJob(scene, layers[0], opts, out, **kw)


register, unregister = bpy.utils.register_classes_factory((CYCLESADAPTIVE_OT_render,))

"""Command line: ``render`` and ``denoise``, as ``./cycles-adaptive`` and as the
Blender command ``blender -b scene.blend -c cycles_adaptive render ...`` (same
parser, same job function).  The repository's ``./cycles-adaptive`` adds the
developer commands ``bench`` and ``references`` (``bench/``, not shipped).

Exit codes: 0 done, 1 failed during the run, 2 bad input (one-line message,
no traceback), 130 interrupted (the partial result was written).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import MISSING

from ..core import methods
from ..core.io import EXR_CONTENTS, EXR_DEPTHS
from ..core.method import fields_by_name
from ..core.pipeline import Options, option_fields

EXIT_OK, EXIT_FAIL, EXIT_INPUT, EXIT_INTERRUPT = 0, 1, 2, 130


class UserError(Exception):
    """Bad input: printed as one line, exit code 2."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line argument errors (no usage dump); exit code 2."""

    def error(self, message):
        self.exit(EXIT_INPUT, f"{self.prog}: error: {message} (see --help)\n")


def add_dataclass_flags(group, flds, prefix: str = "", dest_prefix: str = "") -> None:
    """One flag per dataclass field (``--PREFIX-NAME``), typed from its default,
    with its ``help`` metadata and default in the help text.  Every flag
    defaults to None, so only values given on the command line reach the
    dataclass (whose own defaults and range checks then apply)."""
    for f in flds:
        default = f.default if f.default is not MISSING else None
        help_ = f.metadata.get("help", "") + (f" (default {default})" if default is not None else "")
        flag = "--" + (prefix + "-" if prefix else "") + f.name.replace("_", "-")
        dest = dest_prefix + f.name
        if isinstance(default, bool):
            group.add_argument(flag, dest=dest, default=None, action=argparse.BooleanOptionalAction,
                               help=help_)
        else:
            typ = type(default) if default is not None else str
            kw = {"choices": f.metadata["choices"]} if f.metadata.get("choices") else {}
            group.add_argument(flag, dest=dest, type=typ, default=None, metavar=typ.__name__.upper(),
                               help=help_, **kw)


def add_method_params(p: argparse.ArgumentParser, names=None) -> None:
    """One flag per method parameter, generated from each Params dataclass."""
    for m in names or methods.METHODS:
        try:
            flds = methods.param_fields(m)
        except ImportError:
            continue
        if flds:
            add_dataclass_flags(p.add_argument_group(f"{m} parameters"), flds, m, f"{m}__")


def method_params(args, method: str) -> dict:
    prefix = method + "__"
    return {k[len(prefix):]: v for k, v in vars(args).items() if k.startswith(prefix) and v is not None}


def options_from_args(args, method: str, frame: int) -> Options:
    """Options from the generated flags (only those given) and the method's
    flags, through :func:`operators.job.make_options` (the API's path too)."""
    from .job import make_options
    given = {f.name: getattr(args, f.name) for f in option_fields("cli")
             if getattr(args, f.name, None) is not None}
    return make_options(method, frame, given, method_params(args, method))


def build_parser(blender_command: bool = False, extra_commands=()) -> argparse.ArgumentParser:
    """The parser of the shipped commands (render, denoise), plus
    ``extra_commands``: objects with ``NAME``, ``HELP``, ``add_arguments(parser)``
    and ``main(args) -> int`` (the repository's developer tools add ``bench``
    and ``references`` this way; the extension ships without them)."""
    prog = "blender -b scene.blend -c cycles_adaptive" if blender_command else "cycles-adaptive"
    p = _Parser(prog=prog, description="Adaptive rendering and denoising for Cycles.")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="adaptive render of a .blend file")
    default_method = Options().method
    r.add_argument("blend", nargs="?" if blender_command else None,
                   help="the .blend file" + (" (default: the file Blender opened)" if blender_command else ""))
    r.add_argument("--method", default=default_method, choices=list(methods.METHODS),
                   help=f"{fields_by_name(Options)['method'].metadata['help']} (default {default_method})")
    r.add_argument("--out", help="output EXR (default: the scene's Output path with Blender's frame "
                   "numbering and the method suffix: //render/shot_#### -> render/shot_0001.METHOD.exr)")
    r.add_argument("--reference", help="reference EXR to measure relMSE against")
    r.add_argument("--resolution-percentage", type=int, help="override the scene's resolution %%")
    r.add_argument("--frame", type=int, help="frame to render (default: the scene's current frame)")
    r.add_argument("--frames", help="frame range A-B (or A-B:STEP): one output per frame, OUT_####.exr "
                   "(a run of # in --out is replaced by the frame number)")
    r.add_argument("--temporal", choices=["none", "reproject", "lp", "blend"], default="none",
                   help="frame ranges: 'reproject' reuses the previous frame's samples where "
                        "reprojection is valid (Schalk 2018); 'lp' adds LP's temporal regression "
                        "over frames (Moon 2015 Sec. 6, with --method lp); 'blend' averages each "
                        "frame's result with the previous frame's, warped, where they show the same "
                        "surface and agree within their estimated errors (any method)")
    r.add_argument("--seed-mode", choices=["auto", "animated", "fixed"], default="auto",
                   help="frame ranges: 'animated' gives frame F the seed SEED + F (independent noise per "
                        "frame, as Cycles' animated seed); 'fixed' renders every frame with SEED (the same "
                        "noise pattern: less flicker); 'auto': fixed, animated with --temporal reproject")
    r.add_argument("--scene", help="scene name (default: the active scene)")
    r.add_argument("--view-layer", help="render this one view layer")
    r.add_argument("--view-layers", metavar="all|A,B", help="render these view layers, one EXR layer each "
                   "(default: as Blender renders the file: every layer enabled for rendering, or the "
                   "active one with Render Single Layer on)")
    r.add_argument("--no-compositor", action="store_true", help="do not run the scene's compositor on the "
                   "result (by default it runs when the scene composites its renders)")
    r.add_argument("--exr-depth", choices=EXR_DEPTHS, default="scene",
                   help="the result passes (result, composite, error, variance) in half or full float; "
                        "'scene': the scene's Color Depth when its output is OpenEXR, else half. The "
                        "statistics that denoise and resume read are always full float")
    r.add_argument("--exr-contents", choices=EXR_CONTENTS, default="full",
                   help="'full': every pass denoise needs to re-run any method; 'image': only the result, "
                        "composite, error, samples per pixel and feature means (about a third of the size; "
                        "denoise cannot re-run on it)")
    r.add_argument("--overwrite", action="store_true", help="replace existing output files")
    r.add_argument("--resume", action="store_true", help="continue from OUT.exr.checkpoint.npz")
    r.add_argument("--no-preview", action="store_true", help="do not write the PNG preview")
    r.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    from . import farm
    farm.add_render_arguments(r)
    add_dataclass_flags(r.add_argument_group("loop settings"), option_fields("cli"))
    add_method_params(r, list(methods.METHODS) + list(methods.STAGES))

    d = sub.add_parser("denoise", help="reconstruct from a saved passes EXR")
    d.add_argument("passes", help="an output EXR of `render`, or a Blender multilayer EXR with "
                   "Combined and Denoising passes")
    d.add_argument("--method", default="lp", choices=list(methods.DENOISERS))
    d.add_argument("--out", help="output EXR (default NAME.METHOD.exr beside the input, its method "
                   "suffix replaced: shot.lp.exr -> shot.awr.exr; the input is never replaced)")
    d.add_argument("--reference", help="reference EXR to measure relMSE against")
    d.add_argument("--exr-depth", choices=[d for d in EXR_DEPTHS if d != "scene"], default="half",
                   help="the result passes (result, error, variance) in half or full float; the "
                        "statistics a later denoise reads are always full float")
    d.add_argument("--exr-contents", choices=EXR_CONTENTS, default="full",
                   help="'full': every pass a later denoise needs; 'image': only the result, error, samples "
                        "per pixel and feature means")
    d.add_argument("--overwrite", action="store_true", help="replace existing output files")
    d.add_argument("--no-preview", action="store_true",
                   help="do not write the PNG preview (default: OUT.png, in the colour management of "
                        "the open scene: the factory default's under ./cycles-adaptive)")
    d.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    add_dataclass_flags(d, [fields_by_name(Options)["guard_z"]])
    add_method_params(d, methods.DENOISERS)

    for cmd in extra_commands:
        cmd.add_arguments(sub.add_parser(cmd.NAME, help=cmd.HELP))
    return p


def main(argv=None, blender_command: bool = False, extra_commands=()) -> int:
    parser = build_parser(blender_command, extra_commands)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse prints its own message
        return int(exc.code or 0)
    try:
        if args.command == "render":
            return cmd_render(args, blender_command)
        if args.command == "denoise":
            return cmd_denoise(args)
        for cmd in extra_commands:
            if args.command == cmd.NAME:
                return cmd.main(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPT
    except Exception as exc:  # one line for the user; known input errors
        if _is_user_error(exc):
            print(f"error: {exc}", file=sys.stderr)
            return EXIT_INPUT
        from .farm import FarmError
        if isinstance(exc, FarmError):
            print(f"error: {exc}", file=sys.stderr)
            return EXIT_FAIL
        raise
    return EXIT_FAIL


def _is_user_error(exc) -> bool:
    from ..core.io import ImageFileError
    from ..addon.executor import SceneError
    from .job import JobError
    return isinstance(exc, (UserError, JobError, SceneError, ImageFileError, ValueError, FileNotFoundError))


#: image and movie extensions Blender replaces with its output format's
#: (``BKE_image_path_ext_from_imformat_ensure``); the default output swaps them
#: for ``.METHOD.exr``
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".tga", ".bmp", ".hdr", ".dpx",
                    ".cin", ".j2c", ".jp2", ".webp", ".rgb", ".sgi", ".bw", ".rgba", ".psd")


def default_out_pattern(scene, method: str) -> str:
    """The default output of ``render`` and of the panel (an empty Output
    field): the scene's Output path (``render.filepath``) as Blender resolves
    it for a render, ``scene.render.frame_path`` semantics: ``//`` relative to
    the .blend (to the working folder for an unsaved file), the last run of
    ``#`` in the file name is the zero-padded frame number, a name without
    ``#`` (or a folder, ``/tmp/``) gets four digits appended; then the method
    suffix of every output, ``.METHOD.exr``, replacing a trailing image
    extension (``//render/shot_####`` -> ``render/shot_0001.lp.exr``, ``/tmp/``
    -> ``/tmp/0001.lp.exr``).  Returned as a pattern with the ``#`` run, for
    :func:`operators.job.frame_path`."""
    import bpy
    path = bpy.path.abspath(scene.render.filepath)
    folder, name = os.path.split(path)
    if "#" not in name:
        name += "####"
    stem, ext = os.path.splitext(name)
    if ext.lower() in IMAGE_EXTENSIONS and "#" in stem:
        name = stem
    return os.path.abspath(os.path.join(folder, f"{name}.{method}.exr"))


def default_out(scene, method: str, frame: int) -> str:
    """The default output EXR of one frame (:func:`default_out_pattern`)."""
    from .job import frame_path
    return frame_path(default_out_pattern(scene, method), frame)


def ensure_output_folder(path: str) -> str:
    """Create the folder of a default output (``//render/`` in the scene's
    Output path), as Blender's render does; ``path`` returned.  An explicit
    ``--out`` in a missing folder stays an error."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    return path


def cmd_render(args, blender_command=False) -> int:
    import bpy
    from .job import RenderJob, check_resolution_percentage, open_blend, resolve_scene, resolve_view_layers
    if args.blend:
        open_blend(args.blend)
    elif not bpy.data.filepath and not blender_command:
        raise UserError("no .blend file given")
    scene, vl = resolve_scene(args.scene, args.view_layer)
    if args.view_layer and args.view_layers:
        raise UserError("give --view-layer or --view-layers, not both")
    layers = [vl] if args.view_layer else resolve_view_layers(scene, args.view_layers, vl)
    vl = layers[0]
    if args.resolution_percentage is not None:
        scene.render.resolution_percentage = check_resolution_percentage(args.resolution_percentage)
    frame = scene.frame_current if args.frame is None else args.frame
    opts = options_from_args(args, args.method, frame)
    from . import farm
    if args.skip_existing and not args.frames:
        raise UserError("--skip-existing needs --frames")
    with farm.open_farm(args, log=_log(args)) as cluster:
        if args.frames:
            return _render_frames(args, scene, layers, opts, cluster)
        return _render_frame(args, scene, layers, opts, cluster)


def _log(args):
    return (lambda *a: None) if args.quiet else (lambda msg: print(f"[cycles-adaptive] {msg}", flush=True))


def _render_frame(args, scene, layers, opts, cluster) -> int:
    from . import farm
    from .job import LayersJob, RenderJob
    out = args.out or ensure_output_folder(default_out(scene, args.method, opts.frame))
    kw = dict(reference=args.reference, overwrite=args.overwrite, resume=args.resume,
              preview=not args.no_preview, executor_factory=farm.executor_for(cluster, out),
              compositor=not args.no_compositor, exr_depth=args.exr_depth, exr_contents=args.exr_contents)
    job = (RenderJob(scene, layers[0], opts, out, **kw) if len(layers) == 1 else
           LayersJob(scene, layers, opts, out, **kw))
    last = 0.0

    def show(step):
        nonlocal last
        now = time.perf_counter()
        if not args.quiet and (step.stage != "render" or now - last > 0.5 or
                               step.tasks_done == step.tasks_total):
            print(f"[cycles-adaptive] {100 * step.fraction:5.1f}% {step.message}", flush=True)
            last = now

    interrupted = _run_steps(job.steps(), show)
    if interrupted:
        print("[cycles-adaptive] interrupted: writing the partial result", file=sys.stderr, flush=True)
    t_write = time.perf_counter()
    summary = job.finish(partial=interrupted)
    if not args.quiet:
        print(f"[cycles-adaptive] {_written(summary, time.perf_counter() - t_write)}", flush=True)
    _report(summary, args.json)
    return EXIT_INTERRUPT if interrupted else EXIT_OK


def _written(summary: dict, seconds: float) -> str:
    """The batch log's last progress line: what was written, in how long
    (the final reconstruction included when it had not run yet)."""
    outs = [p for p in (summary.get("out"), summary.get("preview")) if p]
    what = " and ".join(outs) if outs else "nothing (no output path)"
    return f"done: wrote {what} in {seconds:.2f} s"


def _run_steps(steps, show, stop=None) -> bool:
    """Run the generator ``steps``, ``show(step)`` for each, under
    :class:`_SigintFlag`: after Ctrl-C the run stops at the next step (the end
    of the current render), calling ``stop(steps)`` first if given.  The
    generator is closed at the end; returns True when interrupted."""
    with _SigintFlag() as flag:
        try:
            for step in steps:
                show(step)
                if flag.set:
                    if stop is not None:
                        stop(steps)
                    break
        except KeyboardInterrupt:
            flag.set = True
        finally:
            steps.close()
    return flag.set


class _SigintFlag:
    """Ctrl-C as a flag the render loop checks between tasks: Blender's render
    swallows a KeyboardInterrupt raised inside ``bpy.ops.render.render``
    (traceback, then the run went on), so SIGINT only sets ``set`` and the
    loop stops at the end of the current render.  The previous handler is
    restored on exit; a second Ctrl-C while stopping raises as usual."""

    def __init__(self):
        self.set = False
        self._previous = None

    def _handle(self, signum, frame):
        if self.set:
            raise KeyboardInterrupt
        self.set = True

    def __enter__(self):
        import signal
        import threading
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
            if self._previous is signal.SIG_IGN:  # started with Ctrl-C ignored: keep it so
                signal.signal(signal.SIGINT, signal.SIG_IGN)
        return self

    def __exit__(self, *exc):
        import signal
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False


def _render_frames(args, scene, layers, opts, cluster=None) -> int:
    from . import farm, farm_job
    from .job import FramesJob, frame_path, parse_frames
    if args.frame is not None:
        raise UserError("give --frame or --frames, not both")
    frames = parse_frames(args.frames, scene)
    out = os.path.abspath(args.out or ensure_output_folder(default_out_pattern(scene, args.method)))
    common = dict(reference_pattern=args.reference, temporal=args.temporal,
                  reproject_params=method_params(args, "reproject"),
                  temporal_params=method_params(args, "temporal"),
                  history_params=method_params(args, "history"), preview=not args.no_preview,
                  exr_depth=args.exr_depth, exr_contents=args.exr_contents, seed_mode=args.seed_mode)
    flags = dict(skip_existing=args.skip_existing, resume=args.resume, overwrite=args.overwrite)
    vl = layers[0]
    if cluster is not None:
        if len(layers) > 1 or args.no_compositor:
            raise UserError("frame ranges on a Dask farm render one view layer with the compositor: "
                            "choose the layer with --view-layer")
        job = farm.FarmFramesJob(cluster, scene, vl, opts, out, frames, **common, **flags)
    else:
        def make(fr, resume):
            return FramesJob(scene, vl, opts, out, fr, overwrite=args.overwrite, resume=resume,
                             view_layers=layers, compositor=not args.no_compositor, **common)
        job = farm_job.FrameRangeJob(make, frames, lambda f: frame_path(out, f), args.temporal,
                                     method=opts.method, **flags)
    def show(step):
        if isinstance(step, dict):  # a frame finished
            _report(step, args.json)
        elif not args.quiet and step.stage != "render":
            print(f"[cycles-adaptive] {100 * step.fraction:5.1f}% {step.message}", flush=True)

    # the range stops through its own interrupt path: the frame in progress is marked 130
    interrupted = _run_steps(job.steps(), show, stop=lambda steps: steps.throw(KeyboardInterrupt))
    if interrupted:
        print("[cycles-adaptive] interrupted: writing the frame in progress as a partial result",
              file=sys.stderr, flush=True)
    summary = job.finish(partial=interrupted)
    print(f"[cycles-adaptive] {summary['exit_summary']}", flush=True)
    _report(summary, args.json)
    return EXIT_INTERRUPT if interrupted else summary["exit_code"]


def denoise_out(passes: str, method: str) -> str:
    """Default output of ``denoise``: ``NAME.METHOD.exr`` beside the input,
    where a method suffix of the input is replaced, not doubled
    (``shot.lp.exr`` denoised with awr gives ``shot.awr.exr``)."""
    stem = os.path.splitext(os.path.abspath(passes))[0]
    base, dot, last = stem.rpartition(".")
    if dot and base and last in methods.METHODS:
        stem = base
    return f"{stem}.{method}.exr"


def _same_file(a: str, b: str) -> bool:
    if os.path.abspath(a) == os.path.abspath(b):
        return True
    return os.path.exists(a) and os.path.exists(b) and os.path.samefile(a, b)


def cmd_denoise(args) -> int:
    """``denoise``: :func:`operators.job.denoise_output` (the API's
    ``denoise`` too), then the EXR and its PNG preview written.  The input is
    never replaced, even with ``--overwrite``.  The preview uses the colour
    management of ``bpy.context.scene``: the factory scene's (AgX in Blender
    4.x) under ``./cycles-adaptive``, the opened file's under ``blender -b
    shot.blend -c cycles_adaptive denoise``."""
    from ..core import io as imageio
    from .job import denoise_output, preview_path, write_output
    t0 = time.perf_counter()
    out = os.path.abspath(args.out or denoise_out(args.passes, args.method))
    preview = None if args.no_preview else preview_path(out)
    for path in (out, preview):
        if path and _same_file(path, args.passes):
            raise UserError(f"{path}: the output would replace the input {args.passes}; give another --out")
    imageio.check_writable(out, args.overwrite)
    if preview:
        imageio.check_writable(preview, args.overwrite)
    output = denoise_output(args.passes, args.method, method_params(args, args.method), args.guard_z,
                            reference=args.reference, exr_depth=args.exr_depth,
                            exr_contents=args.exr_contents)
    for line in output.summary.get("warnings", ()):
        print(f"warning: {line}", file=sys.stderr, flush=True)
    write_output(output, out)
    if preview:
        import bpy
        from ..addon.executor import write_preview
        combined = output.passes["Combined"]
        write_preview(bpy.context.scene, combined[0] if isinstance(combined, tuple) else combined, preview)
        output.summary["preview_view_transform"] = bpy.context.scene.view_settings.view_transform
    output.summary["total_seconds"] = time.perf_counter() - t0
    output.summary["out"] = out
    output.summary["preview"] = preview
    _report(output.summary, args.json)
    return EXIT_OK


def _report(summary: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(summary), flush=True)
        return
    keys = ("method", "width", "height", "spp_mean", "regions", "render_seconds",
            "reconstruct_seconds", "total_seconds", "relmse", "out")
    for k in keys:
        if k in summary:
            v = summary[k]
            print(f"{k:>20}: {v:.4g}" if isinstance(v, float) else f"{k:>20}: {v}")


def blender_command(argv) -> int:
    """Entry point registered with ``bpy.utils.register_cli_command``."""
    return main(list(argv), blender_command=True)

"""Frame jobs on a farm: which frames a (re-queued) chunk renders, exit codes
per frame, and job templates for farm managers.

A farm re-runs chunks: a node dies, a chunk is re-queued, some of its frames
already exist.  :func:`plan_frames` decides per frame from the files alone
(``OUT.exr`` and ``OUT.exr.checkpoint.npz``, both written atomically, the
checkpoint removed last), so a killed node never leaves a frame that looks
done.  :func:`frame_runs` groups frames into runs one job renders in order
(temporal chains kept whole), :func:`drive` renders runs and records an exit
code per frame, and :func:`summary_line` reports them.

``./cycles-adaptive farm-job BLEND --frames A-B --format openjd|flamenco``
writes a job template that calls ``blender -b BLEND -c cycles_adaptive render
--frames CHUNK --skip-existing --resume``:

- ``openjd``: an Open Job Description template (``jobtemplate-2023-09``, the
  format Deadline Cloud runs) with one step whose tasks are frame chunks
  (``CHUNK[INT]``, extension ``TASK_CHUNKING``) and job parameters for the
  .blend, frames, chunk size, method, budget, output and Blender executable;
- ``flamenco``: a Flamenco job type, the JavaScript job compiler Flamenco's
  manager loads from its ``scripts/`` folder (``JOB_TYPE`` settings and
  ``compileJob`` authoring one ``blender-render`` task per chunk).

See docs/farm.md for installing the extension on render nodes.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass

EXIT_OK, EXIT_FAIL, EXIT_INPUT, EXIT_INTERRUPT = 0, 1, 2, 130
SKIPPED = "skipped"

NAME = "farm-job"
HELP = "write a farm job template (Open Job Description or Flamenco) for a frame range"


class FramePlanError(ValueError):
    """Frames whose existing outputs the flags do not cover; one line."""


# --------------------------------------------------------------- frame plans
@dataclass(frozen=True)
class FramePlan:
    """What one frame of a chunk does.

    state : ``"done"`` (the output exists and no checkpoint: complete),
        ``"checkpointed"`` (a checkpoint exists: a run was stopped or killed,
        the output, if any, is partial), ``"missing"`` (neither).
    action : ``"render"`` (from the start), ``"resume"`` (from its checkpoint)
        or ``"skip"``.
    """

    frame: int
    out: str
    state: str
    action: str


def frame_state(out: str) -> str:
    """``"done"``, ``"checkpointed"`` or ``"missing"`` for the output ``out``.

    ``RenderJob.finish`` writes the EXR, then the preview, then removes the
    checkpoint, each step atomic: a frame is complete only once its checkpoint
    is gone, so a node killed at any point leaves "checkpointed" or "missing".
    A render of several view layers checkpoints each layer
    (``OUT.<layer>.checkpoint.npz``, ``job.layer_checkpoint_path``).
    """
    import glob
    if os.path.exists(out + ".checkpoint.npz") or glob.glob(glob.escape(out) + ".*.checkpoint.npz"):
        return "checkpointed"
    return "done" if os.path.exists(out) else "missing"


def plan_frames(frames, out_for, skip_existing: bool = False, resume: bool = False,
                overwrite: bool = False) -> list:
    """One :class:`FramePlan` per frame, from the files on disk.

    - missing: render;
    - done: skip with ``skip_existing`` or ``resume`` (nothing is left to
      continue), render again with ``overwrite``;
    - checkpointed: resume with ``resume``, render from the start with
      ``overwrite``, or with ``skip_existing`` alone when no partial output is
      in the way.

    Anything else raises :class:`FramePlanError` naming the first frame, before
    any frame is rendered.  ``out_for(frame)`` gives a frame's output path.
    """
    plans = []
    for f in frames:
        out = out_for(f)
        state = frame_state(out)
        if state == "missing":
            action = "render"
        elif state == "done":
            action = "skip" if (skip_existing or resume) and not overwrite else \
                "render" if overwrite else None
        else:
            action = "render" if overwrite else "resume" if resume else \
                "render" if skip_existing and not os.path.exists(out) else None
        if action is None:
            hint = ("--skip-existing, --resume or --overwrite" if state == "done" else
                    "--resume to continue it or --overwrite to start it again")
            what = "exists" if state == "done" else "has a checkpoint of an unfinished run"
            raise FramePlanError(f"frame {f}: {out} {what}; pass {hint}")
        plans.append(FramePlan(int(f), out, state, action))
    return plans


def camera_cuts(markers) -> list:
    """Frames where the active camera changes, from ``(frame, camera)`` pairs
    (Blender's timeline markers bound to cameras), sorted by frame."""
    cuts, last = [], None
    for frame, camera in sorted(markers, key=lambda m: m[0]):
        if camera is None:
            continue
        if last is not None and camera != last:
            cuts.append(int(frame))
        last = camera
    return cuts


def chains(frames, temporal: str = "none", cuts=(), chain_length: int = 0) -> list:
    """Frames split into chains that must render in order on one node.

    Without a temporal mode every frame is its own chain.  With ``reproject``
    or ``lp`` a frame reuses the previous one, so a chain runs until a camera
    cut (a frame in ``cuts`` starts a new chain) or ``chain_length`` frames
    (0: no limit).  Each chain's first frame starts without history.
    """
    frames = [int(f) for f in frames]
    if temporal == "none":
        return [[f] for f in frames]
    cut = set(int(c) for c in cuts)
    out: list = []
    for f in frames:
        if not out or f in cut or (chain_length and len(out[-1]) >= chain_length):
            out.append([f])
        else:
            out[-1].append(f)
    return out


@dataclass(frozen=True)
class Run:
    """Consecutive frames of one chain that one frames job renders in order,
    all from the start (``resume`` False) or all from their checkpoints."""

    frames: tuple
    resume: bool


def frame_runs(plans, chain_list) -> list:
    """Split each chain at skipped frames and where the action changes; a
    list (one per chain) of lists of :class:`Run`.  A skipped frame inside a
    temporal chain breaks its history: the next run starts fresh (logged)."""
    by_frame = {p.frame: p for p in plans}
    out = []
    for chain in chain_list:
        runs: list = []
        cur: list = []
        cur_resume = None
        for f in chain:
            p = by_frame[f]
            if p.action == "skip":
                if cur:
                    runs.append(Run(tuple(cur), cur_resume))
                cur, cur_resume = [], None
                continue
            resume = p.action == "resume"
            if cur and resume != cur_resume:
                runs.append(Run(tuple(cur), cur_resume))
                cur = []
            cur.append(f)
            cur_resume = resume
        if cur:
            runs.append(Run(tuple(cur), cur_resume))
        out.append(runs)
    return out


def describe_chains(chain_list, cuts=(), chain_length: int = 0) -> str:
    """One log line: how the frames were split and why."""
    spans = ", ".join(_span(c) for c in chain_list[:8]) + (", ..." if len(chain_list) > 8 else "")
    why = []
    if cuts:
        why.append("camera cuts at " + ", ".join(str(c) for c in cuts))
    if chain_length:
        why.append(f"every {chain_length} frames")
    return (f"{len(chain_list)} chain{'s' if len(chain_list) != 1 else ''} kept in order on one worker "
            f"each ({spans})" + (f"; split at {' and '.join(why)}" if why else ""))


def _span(chain) -> str:
    return str(chain[0]) if len(chain) == 1 else f"{chain[0]}-{chain[-1]}"


# ------------------------------------------------------------ driving runs
def error_code(exc) -> int:
    """Exit code of a frame that raised ``exc``: 2 for bad input (the
    CLI's one-line errors), 130 for an interrupt, else 1."""
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPT
    names = {c.__name__ for c in type(exc).__mro__}
    if names & {"JobError", "SceneError", "ImageFileError", "UserError", "StorageError", "ValueError",
                "FileNotFoundError"}:
        return EXIT_INPUT
    return EXIT_FAIL


def drive(runs, make_job, codes: dict, errors: dict):
    """Render ``runs`` (lists of :class:`Run`, one list per chain) in order.

    ``make_job(frames, resume)`` returns a FramesJob-like object (``steps()``
    yielding Progress and one summary dict per finished frame).  Yields what
    the jobs yield; sets ``codes[frame]`` (0 for each frame that finished)
    and, when a run raises, the code of :func:`error_code` for the frame in
    progress (and ``errors[frame]``, one line), 1 for the frames of that chain
    it did not reach, and goes on with the next chain.  An interrupt marks the
    frame in progress and stops.
    """
    for chain in runs:
        pending = [f for run in chain for f in run.frames]
        for run in chain:
            try:
                job = make_job(list(run.frames), run.resume)
                for step in job.steps():
                    if isinstance(step, dict):
                        codes[int(step["frame"])] = EXIT_OK
                        pending.remove(int(step["frame"]))
                    yield step
            except GeneratorExit:      # the range's consumer closed it: not a frame failure
                raise
            except BaseException as exc:
                frame = pending[0] if pending else run.frames[-1]
                codes[frame] = error_code(exc)
                errors[frame] = _one_line(exc)
                for f in pending[1:]:
                    codes[f] = EXIT_FAIL
                    errors[f] = f"not rendered: frame {frame} of its chain failed"
                if isinstance(exc, KeyboardInterrupt):
                    raise
                break


def _one_line(exc) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[-1] if text else ''}".rstrip(": ")


def exit_code(codes: dict) -> int:
    """The process's exit code for per-frame ``codes`` (skipped frames count
    as done): 130 if any frame was interrupted, else 1 if any failed, else 2 if
    any had bad input, else 0."""
    vals = {c for c in codes.values() if c != SKIPPED}
    for c in (EXIT_INTERRUPT, EXIT_FAIL, EXIT_INPUT):
        if c in vals:
            return c
    return EXIT_OK


def summary_line(codes: dict) -> str:
    """``exit codes per frame: 1-3=0 4=skipped 5=1``: consecutive frames with
    the same code as one span, in frame order."""
    parts, start, prev, code = [], None, None, None
    for f in sorted(codes):
        c = codes[f]
        if start is not None and (c != code or f != prev + 1):
            parts.append(f"{_span([start, prev]) if prev != start else start}={code}")
            start = None
        if start is None:
            start, code = f, c
        prev = f
    if start is not None:
        parts.append(f"{_span([start, prev]) if prev != start else start}={code}")
    return "exit codes per frame: " + (" ".join(parts) if parts else "none")


class FrameRangeJob:
    """A frame range on this machine, re-queue safe, with ``FramesJob``'s
    interface (``steps`` yielding Progress and one summary dict per frame,
    ``finish``, ``summary``): frames planned from the files
    (:func:`plan_frames`), skipped ones left alone, the rest rendered in runs
    (:func:`frame_runs`; temporal modes keep the range one chain) by
    ``make_job(frames, resume)`` (a ``FramesJob``); a failing frame gets its
    exit code and the others go on.
    """

    def __init__(self, make_job, frames, out_for, temporal: str = "none", skip_existing: bool = False,
                 resume: bool = False, overwrite: bool = False, method: str = ""):
        self.make_job = make_job
        self.frames = [int(f) for f in frames]
        self.temporal, self.method = temporal, method
        self.plans = plan_frames(self.frames, out_for, skip_existing, resume, overwrite)
        self.runs = frame_runs(self.plans, chains(self.frames, temporal))
        self.codes = {p.frame: SKIPPED for p in self.plans if p.action == "skip"}
        self.errors: dict = {}
        self.summaries: list = []
        self.job = None  # the FramesJob in progress

    @property
    def run(self):
        """The run of the frame in progress (for the operator's stepper)."""
        return None if self.job is None else self.job.run

    def _make(self, frames, resume):
        self.job = self.make_job(frames, resume)
        self._before = len(self.codes)  # frames settled before this job: skipped, done, failed
        return self.job

    def steps(self):
        from ..core.pipeline import Progress
        skipped = [p.frame for p in self.plans if p.action == "skip"]
        if skipped:
            yield Progress("plan", 0, 0.0, skipped_message(skipped))
        n = len(self.frames)
        runs = drive(self.runs, self._make, self.codes, self.errors)
        for step in runs:
            if isinstance(step, dict):
                self.summaries.append(step)
            else:  # the job's fraction of its own frames -> of the range
                step.fraction = (self._before + step.fraction * len(self.job.frames)) / n
            try:
                yield step
            except KeyboardInterrupt:  # thrown in by the consumer (Ctrl-C): drive marks the frame, re-raises
                runs.throw(KeyboardInterrupt)
        for f, msg in sorted(self.errors.items()):
            yield Progress("plan", 0, 1.0, f"frame {f} failed: {msg}")

    def finish(self, partial: bool = False) -> dict:
        """The range summary; after a cancel, the frame in progress is first
        written as a partial result (its checkpoint kept for --resume)."""
        job = self.job
        if partial and job is not None and job.run is not None and job.run.buffers is not None:
            n = len(job.summaries)
            job.finish(partial=True)  # FramesJob writes the frame in progress
            self.summaries.extend(job.summaries[n:])
        return self.summary()

    def summary(self) -> dict:
        return range_summary(self.summaries, self.codes, self.errors, self.method, self.temporal)


def skipped_message(frames) -> str:
    return f"skipping {len(frames)} finished frame{'s' if len(frames) != 1 else ''}: {frames_text(frames)}"


def frames_text(frames) -> str:
    """``[1, 2, 3, 5]`` -> ``"1-3, 5"``."""
    spans, start, prev = [], None, None
    for f in sorted(frames):
        if start is not None and f == prev + 1:
            prev = f
            continue
        if start is not None:
            spans.append(_span([start, prev]) if prev != start else str(start))
        start = prev = f
    if start is not None:
        spans.append(_span([start, prev]) if prev != start else str(start))
    return ", ".join(spans)


def range_summary(summaries, codes: dict, errors: dict, method: str, temporal: str) -> dict:
    """The last line of a frame range: what ``FramesJob.summary`` reports plus
    ``exit_codes`` per frame, ``errors``, the process ``exit_code`` and the
    ``exit_summary`` line (:func:`summary_line`)."""
    import numpy as np
    s = sorted(summaries, key=lambda x: x["frame"])
    out = {"frames": len(s), "method": method, "temporal": temporal,
           "total_seconds": sum(x["total_seconds"] for x in s),
           "render_seconds": sum(x["render_seconds"] for x in s),
           "spp_mean": float(np.mean([x["spp_mean"] for x in s])) if s else 0.0,
           "reprojected_fraction": float(np.mean([x.get("reprojected_fraction", 0.0) for x in s]))
           if s else 0.0, "outs": [x["out"] for x in s],
           "exit_codes": {str(k): v for k, v in sorted(codes.items())},
           "errors": {str(k): v for k, v in sorted(errors.items())},
           "exit_code": exit_code(codes), "exit_summary": summary_line(codes)}
    if s and all("relmse" in x for x in s):
        out["relmse_mean"] = float(np.mean([x["relmse"] for x in s]))
    out["out"] = out["outs"][-1] if out["outs"] else ""
    return out


# --------------------------------------------------------------- templates
METHOD_CHOICES = ("uniform", "var", "awr", "lp", "rhf")


def parse_range(text: str) -> tuple:
    """``A``, ``A-B`` or ``A-B:STEP`` -> (a, b, step); ValueError otherwise
    (the syntax of ``render --frames``)."""
    try:
        body, _, step = text.partition(":")
        a, sep, b = body.strip().partition("-")
        a, b, step = int(a), int(b) if sep else int(a), int(step or 1)
    except ValueError:
        raise FramePlanError(f"--frames {text!r}: expected A-B, A or A-B:STEP") from None
    if b < a or step < 1:
        raise FramePlanError(f"--frames {text!r}: empty range")
    return a, b, step


def render_args(frames: str, method: str, spp: float, out: str, extra=()) -> list:
    """The ``render`` arguments of one chunk (after ``-c cycles_adaptive``):
    re-queue safe (``--skip-existing --resume``)."""
    return ["render", "--frames", frames, "--method", method, "--spp", str(spp), "--out", out,
            "--skip-existing", "--resume", *extra]


def openjd_template(blend: str, frames: str, out: str, method: str = "lp", spp: float = 16.0,
                    chunk_size: int = 1, blender: str = "blender", extra=(), name: str = "",
                    template_dir: str = ".") -> dict:
    """An Open Job Description job template (``jobtemplate-2023-09``).

    One step, ``Render``; its task parameter ``Frames`` is a ``CHUNK[INT]``
    over the job parameter ``Frames`` (contiguous chunks of ``ChunkSize``
    frames, rendered by ``blender -b BLEND -c cycles_adaptive render --frames
    CHUNK``).  A chunk the farm re-runs skips its finished frames and resumes
    checkpointed ones.  ``extra``: further ``render`` flags, fixed in the
    template.  Open Job Description resolves a PATH parameter's default
    against the template's folder, so the defaults of ``BlendFile`` and
    ``OutputPattern`` are written relative to ``template_dir`` (none when no
    relative path exists, e.g. another Windows drive: give them on submission).
    """
    parse_range(frames)
    rel = lambda p: _relative(p, template_dir)
    args = ["-b", "{{Param.BlendFile}}", "-c", "cycles_adaptive",
            *render_args("{{Task.Param.Frames}}", "{{Param.Method}}", "{{Param.Spp}}",
                         "{{Param.OutputPattern}}", extra)]
    return {
        "specificationVersion": "jobtemplate-2023-09",
        "extensions": ["TASK_CHUNKING"],
        "name": name or f"Cycles Adaptive {os.path.basename(blend)}",
        "description": "Adaptive Cycles render of a frame range (cycles_adaptive extension); "
                       "re-queued chunks skip finished frames and resume checkpointed ones.",
        "parameterDefinitions": [
            {"name": "BlendFile", "type": "PATH", "objectType": "FILE", "dataFlow": "IN",
             **rel(blend), "description": "the .blend file to render"},
            {"name": "Frames", "type": "STRING", "default": frames,
             "description": "frame range A-B (or A-B:STEP)"},
            {"name": "ChunkSize", "type": "INT", "default": int(chunk_size), "minValue": 1,
             "description": "frames per task"},
            {"name": "Method", "type": "STRING", "default": method, "allowedValues": list(METHOD_CHOICES),
             "description": "adaptive method"},
            {"name": "Spp", "type": "FLOAT", "default": float(spp), "minValue": 0.001,
             "description": "mean samples per pixel of each frame"},
            {"name": "OutputPattern", "type": "PATH", "objectType": "FILE", "dataFlow": "OUT",
             **rel(out), "description": "output EXR per frame; a run of # is the frame number"},
            {"name": "BlenderExecutable", "type": "STRING", "default": blender,
             "description": "Blender on the render nodes (with the cycles_adaptive extension)"},
        ],
        "steps": [{
            "name": "Render",
            "parameterSpace": {"taskParameterDefinitions": [{
                "name": "Frames", "type": "CHUNK[INT]", "range": "{{Param.Frames}}",
                "chunks": {"defaultTaskCount": "{{Param.ChunkSize}}", "rangeConstraint": "CONTIGUOUS"}}]},
            "script": {"actions": {"onRun": {"command": "{{Param.BlenderExecutable}}", "args": args}}},
        }],
    }


def _relative(path: str, folder: str) -> dict:
    """``{"default": path relative to folder}``, or ``{}`` where none exists."""
    try:
        return {"default": os.path.relpath(os.path.abspath(path), os.path.abspath(folder))}
    except ValueError:  # another drive
        return {}


FLAMENCO_JS = r"""// Flamenco job type: adaptive Cycles renders (the cycles_adaptive extension).
// Written by `cycles-adaptive farm-job --format flamenco`; copy it to the
// manager's scripts/ folder.  Each task renders one chunk of frames with
//   blender -b BLEND -c cycles_adaptive render --frames CHUNK ... --skip-existing --resume
// so a re-queued task skips finished frames and resumes checkpointed ones.

const JOB_TYPE = {
    label: __LABEL__,
    description: "Adaptive Cycles render of a frame range (cycles_adaptive extension)",
    settings: [
        { key: "frames", type: "string", required: true, default: __FRAMES__,
          eval: "f'{C.scene.frame_start}-{C.scene.frame_end}'",
          description: "Frame range A-B or A-B:STEP; several ranges separated by commas" },
        { key: "chunk_size", type: "int32", default: __CHUNK__, description: "Frames per task" },
        { key: "method", type: "string", default: __METHOD__, choices: __CHOICES__,
          description: "Adaptive method" },
        { key: "spp", type: "float", default: __SPP__, description: "Mean samples per pixel of each frame" },
        { key: "render_output_path", type: "string", subtype: "file_path", required: true,
          default: __OUT__, description: "Output EXR per frame; a run of # is the frame number" },
        { key: "blendfile", type: "string", required: true, visible: "web",
          description: "Path of the Blend file to render" },
    ]
};

const EXTRA_ARGS = __EXTRA__;

// "A", "A-B" or "A-B:STEP" -> {a, b, step}; throws on anything else.
function parseRange(text) {
    const m = /^\s*(-?\d+)(?:\s*-\s*(-?\d+))?(?::(\d+))?\s*$/.exec(text);
    if (!m) throw `frames ${JSON.stringify(text)}: expected A-B, A or A-B:STEP`;
    const a = parseInt(m[1]), b = m[2] === undefined ? a : parseInt(m[2]);
    const step = m[3] === undefined ? 1 : parseInt(m[3]);
    if (b < a || step < 1) throw `frames ${JSON.stringify(text)}: empty range`;
    return { a: a, b: b, step: step };
}

// Chunks of `size` frames as --frames values of the render command.
function frameChunks(frames, size) {
    if (!(size >= 1)) throw `chunk_size ${size} must be at least 1`;
    const chunks = [];
    for (const part of String(frames).split(",")) {
        const r = parseRange(part);
        for (let first = r.a; first <= r.b; first += size * r.step) {
            const last = Math.min(r.b, first + (size - 1) * r.step);
            chunks.push(first === last ? `${first}` :
                        r.step === 1 ? `${first}-${last}` : `${first}-${last}:${r.step}`);
        }
    }
    return chunks;
}

function compileJob(job) {
    const settings = job.settings;
    for (const chunk of frameChunks(settings.frames, settings.chunk_size)) {
        const task = author.Task(`adaptive-${chunk}`, "blender");
        task.addCommand(author.Command("blender-render", {
            exe: "{blender}",
            exeArgs: "{blenderArgs}",
            argsBefore: [],
            blendfile: settings.blendfile,
            args: ["-c", "cycles_adaptive", "render", "--frames", chunk,
                   "--method", settings.method, "--spp", `${settings.spp}`,
                   "--out", settings.render_output_path,
                   "--skip-existing", "--resume"].concat(EXTRA_ARGS),
        }));
        job.addTask(task);
    }
}
"""


def flamenco_job_type(frames: str, out: str, method: str = "lp", spp: float = 16.0,
                      chunk_size: int = 1, extra=(), label: str = "Cycles Adaptive Render") -> str:
    """The Flamenco job compiler script (JavaScript) with these defaults.

    Flamenco's ``blender-render`` command runs ``exe exeArgs argsBefore
    blendfile args``: here ``blender -b -y BLEND -c cycles_adaptive render
    --frames CHUNK ...``; the chunks split each comma-separated range of the
    ``frames`` setting (``A-B`` or ``A-B:STEP``, the syntax of ``render
    --frames``) into ``chunk_size`` frames.
    """
    parse_range(frames.split(",")[0])
    values = {"__LABEL__": label, "__FRAMES__": frames, "__CHUNK__": int(chunk_size), "__METHOD__": method,
              "__CHOICES__": list(METHOD_CHOICES), "__SPP__": float(spp), "__OUT__": out,
              "__EXTRA__": list(extra)}
    text = FLAMENCO_JS
    for key, value in values.items():
        text = text.replace(key, json.dumps(value))
    return text


# --------------------------------------------------------------- the command
def add_arguments(p) -> None:
    """Flags of ``farm-job``."""
    p.add_argument("blend", help="the .blend file, as the render nodes see it")
    p.add_argument("--frames", required=True, help="frame range A-B (or A-B:STEP)")
    p.add_argument("--format", required=True, choices=["openjd", "flamenco"],
                   help="openjd: Open Job Description template (Deadline Cloud); flamenco: a "
                        "Flamenco job type (JavaScript)")
    p.add_argument("--out", required=True, help="template file to write (openjd: JSON, which is "
                   "also valid YAML; flamenco: .js)")
    p.add_argument("--render-out", help="output EXR per frame on the nodes, a run of # is the frame "
                   "number (default: next to the .blend, NAME.METHOD_####.exr)")
    p.add_argument("--method", default="lp", choices=list(METHOD_CHOICES))
    p.add_argument("--spp", type=float, default=16.0, help="mean samples per pixel (default 16)")
    p.add_argument("--chunk-size", type=int, default=1, help="frames per task (default 1)")
    p.add_argument("--blender", default="blender", help="Blender executable on the nodes "
                   "(openjd; Flamenco uses its own {blender} variable)")
    p.add_argument("--render-arg", action="append", default=[], metavar="ARG",
                   help="extra flag for `render`, fixed in the template (repeat; e.g. "
                        "--render-arg=--initial-spp --render-arg=8)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing template file")


def main(args) -> int:
    """``farm-job``: write the template; one line naming the file."""
    from ..core import io as imageio
    if args.chunk_size < 1:
        raise FramePlanError("--chunk-size must be at least 1")
    if args.spp <= 0:
        raise FramePlanError("--spp must be positive")
    parse_range(args.frames)
    imageio.check_writable(args.out, args.overwrite)
    blend = os.path.abspath(args.blend) if not os.path.isabs(args.blend) else args.blend
    stem = os.path.splitext(blend)[0]
    render_out = args.render_out or f"{stem}.{args.method}_####.exr"
    if args.format == "openjd":
        text = json.dumps(openjd_template(blend, args.frames, render_out, args.method, args.spp,
                                          args.chunk_size, args.blender, args.render_arg,
                                          template_dir=os.path.dirname(os.path.abspath(args.out))),
                          indent=2) + "\n"
    else:
        text = flamenco_job_type(args.frames, render_out, args.method, args.spp, args.chunk_size,
                                 args.render_arg)
    imageio.write_text(args.out, text)
    print(f"wrote {args.format} job for frames {args.frames} of {blend}: {args.out}")
    return EXIT_OK

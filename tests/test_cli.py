"""The command line contract (README, "Command line"): JSON fields, bad input, interrupts,
resume.  Runs ./cycles-adaptive as a user would (subprocesses)."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CLI = os.path.join(ROOT, "cycles-adaptive")
ENV = dict(os.environ, CYCLES_ADAPTIVE_PYTHON=sys.executable)  # the CLI under this test's Blender
FIELDS = ("method", "width", "height", "spp_mean", "render_seconds", "reconstruct_seconds",
          "total_seconds", "regions", "peak_rss_mb", "out")


def _blend(tmp_path, name="s.blend", **kw):
    from blend_util import save_scene
    path = tmp_path / name
    save_scene(path, **kw)
    return str(path)


def _cli(*args, timeout=600):
    return subprocess.run([CLI, *args], capture_output=True, text=True, timeout=timeout, env=ENV)


def _last_json(stdout):
    return json.loads(stdout.strip().splitlines()[-1])


def test_render_json_has_the_contract_fields(tmp_path):
    blend = _blend(tmp_path, width=32, height=24)
    out = str(tmp_path / "o.exr")
    ref = str(tmp_path / "ref.exr")
    r = _cli("render", blend, "--method", "uniform", "--spp", "16", "--out", ref, "--json", "--seed", "7")
    assert r.returncode == 0, r.stderr
    r = _cli("render", blend, "--method", "var", "--spp", "6", "--initial-spp", "2", "--out", out,
             "--reference", ref, "--json", "--task-cost", "64")
    assert r.returncode == 0, r.stderr
    res = _last_json(r.stdout)
    for k in FIELDS + ("relmse",):
        assert k in res, k
    assert res["method"] == "var" and (res["width"], res["height"]) == (32, 24)
    assert abs(res["spp_mean"] - 6) <= 0.06
    assert res["relmse"] > 0 and os.path.isfile(out) and os.path.isfile(str(tmp_path / "o.png"))
    assert not os.path.exists(out + ".checkpoint.npz")
    assert "[cycles-adaptive]" in r.stdout  # batch progress lines, for every stage:
    log = [line for line in r.stdout.splitlines() if line.startswith("[cycles-adaptive]")]
    for words in ("adapting (var)", "sampling done", "reconstructing (var)", f"writing {out}",
                  f"done: wrote {out} and {tmp_path / 'o.png'}"):
        assert any(words in line for line in log), (words, log)
    assert log[-1].startswith("[cycles-adaptive] done: wrote")
    assert res["reconstructed"] and res["estimated_relmse"] >= 0
    from cycles_adaptive.core import io as imageio
    passes, meta = imageio.read_layers(out)
    for p in ("Combined", "Noisy", "Variance", "M2", "Samples", "Groups", "Error", "Feat_alpha"):
        assert p in passes, p
    assert passes["Samples"].sum() == pytest.approx(res["spp_mean"] * 32 * 24)


def test_resolution_percentage_and_frame(tmp_path):
    blend = _blend(tmp_path, width=40, height=20)
    r = _cli("render", blend, "--method", "uniform", "--spp", "2", "--resolution-percentage", "50",
             "--frame", "3", "--out", str(tmp_path / "h.exr"), "--json", "--no-preview")
    assert r.returncode == 0, r.stderr
    res = _last_json(r.stdout)
    assert (res["width"], res["height"], res["frame"]) == (20, 10, 3)


@pytest.mark.parametrize("case", ["exists", "folder", "eevee", "missing_blend", "bad_spp"])
def test_bad_input_gives_one_line_and_exit_2(tmp_path, case):
    blend = _blend(tmp_path, width=16, height=16, engine="EEVEE" if case == "eevee" else "CYCLES")
    out = tmp_path / "o.exr"
    args = ["render", blend, "--method", "uniform", "--spp", "2", "--out", str(out)]
    if case == "exists":
        out.write_bytes(b"precious")
    elif case == "folder":
        args[-1] = str(tmp_path / "no" / "such" / "o.exr")
    elif case == "missing_blend":
        args[1] = str(tmp_path / "nope.blend")
    elif case == "bad_spp":
        args[5] = "0"
    r = _cli(*args)
    assert r.returncode == 2, (r.returncode, r.stderr)
    err = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "Traceback" not in r.stderr
    if case == "exists":
        assert out.read_bytes() == b"precious"
        assert "--overwrite" in err[0]
    if case == "eevee":
        assert "Cycles" in err[0]


def _exr_arrays(path):
    from cycles_adaptive.core import io as imageio
    return imageio.read_layers(path)[0]


def _default_sigint():
    # a test run started in the background (e.g. `bash .ci/run &`) inherits
    # SIGINT ignored, and so would the CLI; a terminal's Ctrl-C is what we test
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(args):
    return subprocess.Popen([CLI, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
                            preexec_fn=_default_sigint)


def _wait_for(proc, needle, timeout=300):
    t_end = time.time() + timeout
    lines = []
    while time.time() < t_end:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if needle in line:
            return lines
    raise AssertionError(f"never saw {needle!r}: {''.join(lines)[-2000:]}")


RUN = ["--method", "var", "--spp", "12", "--initial-spp", "2", "--subsets", "2", "--iterations", "6",
       "--task-cost", "64", "--no-preview", "--json"]


def test_sigkill_then_resume_equals_uninterrupted_run(tmp_path):
    blend = _blend(tmp_path, width=48, height=32)
    full = str(tmp_path / "full.exr")
    r = _cli("render", blend, "--out", full, *RUN)
    assert r.returncode == 0, r.stderr
    out = str(tmp_path / "killed.exr")
    p = _start(["render", blend, "--out", out, *RUN])
    _wait_for(p, "iteration 2 done")
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert os.path.isfile(out + ".checkpoint.npz") and not os.path.exists(out)
    r = _cli("render", blend, "--out", out, "--resume", *RUN)
    assert r.returncode == 0, r.stderr
    a, b = _exr_arrays(full), _exr_arrays(out)
    for name in ("Combined", "Samples", "M2", "Noisy"):
        np.testing.assert_array_equal(a[name], b[name])


#: a run long enough (40 iterations of region renders) that Ctrl-C after
#: the first iteration always lands before the end, even on a fast machine
LONG_RUN = ["--method", "var", "--spp", "1000", "--initial-spp", "2", "--subsets", "2",
            "--iterations", "40", "--task-cost", "64", "--no-preview", "--json"]


def test_ctrl_c_writes_the_partial_result(tmp_path):
    blend = _blend(tmp_path, width=48, height=32)
    out = str(tmp_path / "part.exr")
    p = _start(["render", blend, "--out", out, *LONG_RUN])
    _wait_for(p, "iteration 1 done")
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=300)
    assert p.returncode == 130, stderr
    res = _last_json(stdout)
    assert res["partial"] is True and os.path.isfile(out)
    assert os.path.isfile(out + ".checkpoint.npz")  # kept, so --resume can continue
    assert res["spp_mean"] < 1000


def test_blender_cli_command_runs_the_same_job(tmp_path):
    """What `blender -b scene.blend -c cycles_adaptive render ...` calls."""
    from cycles_adaptive.operators import cli
    blend = _blend(tmp_path, width=16, height=16)
    bpy.ops.wm.open_mainfile(filepath=blend)
    out = str(tmp_path / "b.exr")
    rc = cli.blender_command(["render", "--method", "uniform", "--spp", "2", "--out", out, "--quiet"])
    assert rc == 0 and os.path.isfile(out)


def test_frame_range_writes_one_output_per_frame(tmp_path):
    blend = os.path.join(ROOT, "sample_blends", "animated.blend")
    out = str(tmp_path / "anim_####.exr")
    r = _cli("render", blend, "--frames", "2-3", "--method", "var", "--spp", "4", "--initial-spp", "2",
             "--resolution-percentage", "25", "--out", out, "--json", "--task-cost", "64")
    assert r.returncode == 0, r.stderr
    lines = [json.loads(ln) for ln in r.stdout.splitlines() if ln.startswith("{")]
    assert [ln.get("frame") for ln in lines[:-1]] == [2, 3]
    for ln in lines[:-1]:
        assert "reprojected_fraction" in ln and os.path.isfile(ln["out"])
    assert lines[-1]["frames"] == 2 and os.path.isfile(str(tmp_path / "anim_0003.png"))


def test_frame_range_outside_the_scene_is_refused(tmp_path):
    blend = os.path.join(ROOT, "sample_blends", "animated.blend")
    r = _cli("render", blend, "--frames", "10-40", "--method", "uniform", "--spp", "1",
             "--out", str(tmp_path / "x_####.exr"))
    assert r.returncode == 2 and "outside the scene's frame range" in r.stderr
    assert not list(tmp_path.iterdir())


def test_ctrl_c_mid_render_stops_at_its_end_and_writes_a_readable_partial_exr(tmp_path):
    """SIGINT while Cycles renders a subset: the run stops after that render
    (Blender would otherwise swallow the KeyboardInterrupt), exit 130."""
    blend = _blend(tmp_path, width=64, height=48)
    out = str(tmp_path / "mid.exr")
    p = _start(["render", blend, "--out", out, "--method", "var", "--spp", "1000", "--initial-spp", "64",
                "--subsets", "8", "--task-cost", "64", "--no-preview", "--json"])
    _wait_for(p, "initial pass: subset 1/8")  # subset 2 is rendering now
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=300)
    assert p.returncode == 130, stderr[-2000:]
    res = _last_json(stdout)
    assert res["partial"] is True and res["spp_mean"] < 64
    passes = _exr_arrays(out)
    assert np.isfinite(passes["Combined"]).all()
    assert passes["Samples"].sum() == pytest.approx(res["spp_mean"] * 64 * 48)


def test_ctrl_c_in_a_frame_range_stops_at_the_render_and_keeps_the_finished_frames(tmp_path):
    """SIGINT during the second frame's Cycles render of a range: that frame is written
    as a partial result, the first stays complete, the third is not started, exit 130 (Blender
    would swallow a KeyboardInterrupt raised in its render and go on)."""
    blend = os.path.join(ROOT, "sample_blends", "animated.blend")
    out = str(tmp_path / "f_####.exr")
    p = _start(["render", blend, "--frames", "1-3", "--out", out, "--method", "var", "--spp", "1000",
                "--initial-spp", "64", "--subsets", "8", "--task-cost", "64", "--resolution-percentage", "25",
                "--iterations", "1", "--no-preview", "--json"])
    seen = _wait_for(p, '"frame": 1,')                    # frame 1 written
    seen += _wait_for(p, "initial pass: subset 1/8")       # frame 2's subset 2 is rendering now
    p.send_signal(signal.SIGINT)
    rest, stderr = p.communicate(timeout=600)
    stdout = "".join(seen) + rest
    assert p.returncode == 130, stderr[-2000:]
    assert "interrupted" in stderr
    frames = [json.loads(ln) for ln in stdout.splitlines() if ln.startswith("{") and '"frame"' in ln]
    by_frame = {x["frame"]: x for x in frames}
    assert by_frame[1]["partial"] is False
    summary = _last_json(stdout)
    assert summary["exit_codes"] == {"1": 0, "2": 130} and summary["exit_code"] == 130
    assert summary["outs"] == [str(tmp_path / "f_0001.exr"), str(tmp_path / "f_0002.exr")]
    assert not os.path.exists(str(tmp_path / "f_0003.exr"))
    passes = _exr_arrays(str(tmp_path / "f_0002.exr"))     # the partial frame: readable, < 64 spp
    assert np.isfinite(passes["Combined"]).all() and 0 < passes["Samples"].mean() < 64


@pytest.mark.parametrize("method", ["var", "uniform"])
def test_max_seconds_bounds_the_wall_time(tmp_path, method):
    """A budget far beyond the limit: the run (final reconstruction and EXR
    included) ends within 10 % of the limit plus its longest render, which the
    plan keeps short (uniform rendered its whole budget in one initial pass
    before the plan: one render past any limit)."""
    blend = _blend(tmp_path, width=48, height=32)
    limit = 3.0
    # 1000 spp of 48x32 finished inside the 3 s limit on CI (uniform under
    # Blender 4.2 and 5.0, var under 4.2), so the budget is 100x larger
    spp = "100000"
    args = [method if a == "var" else spp if a == "1000" else a for a in LONG_RUN]
    r = _cli("render", blend, "--out", str(tmp_path / "t.exr"), *args, "--max-seconds", str(limit))
    assert r.returncode == 0, r.stderr
    res = _last_json(r.stdout)
    assert res["time_limited"] is True and res["max_seconds"] == limit and res["spp_mean"] < float(spp)
    assert res["total_seconds"] <= limit * 1.1 + res["max_task_seconds"], res
    assert res["max_task_seconds"] < limit / 2, res
    assert res["sampling_seconds"] + res["reserved_seconds"] <= limit + res["max_task_seconds"], res
    assert res["reserved_seconds"] > 0 and res["render_seconds_per_msample"] > 0
    assert res["spp_mean"] > 4, res  # the time was used, not given up after the first pass


# ------------------------------------------- default output: the scene's Output path
@pytest.mark.parametrize("filepath", ["//render/shot_####", "DIR/", "//", "//render/shot", "//shot_####.jpg",
                                      "//a_##_b", "//dir_##/x_###", "//shot.png", "rel/f_#"])
def test_default_output_is_blenders_frame_path_with_the_method_suffix(tmp_path, filepath):
    """Our resolution of render.filepath against Blender's own
    (``scene.render.frame_path``), whose format extension becomes .METHOD.exr."""
    from cycles_adaptive.operators import cli
    from cycles_adaptive.operators.job import frame_path
    blend = _blend(tmp_path, width=8, height=8)
    bpy.ops.wm.open_mainfile(filepath=blend)
    scene = bpy.context.scene
    scene.render.filepath = filepath.replace("DIR/", str(tmp_path / "flat") + os.sep)
    ext = scene.render.file_extension
    for frame in (1, 7, 12345, -3):
        blender = scene.render.frame_path(frame=frame)
        assert blender.endswith(ext)
        ours = cli.default_out(scene, "lp", frame)
        assert ours == os.path.abspath(blender[:-len(ext)] + ".lp.exr"), (filepath, frame)
        assert frame_path(cli.default_out_pattern(scene, "awr"), frame) == ours[:-len(".lp.exr")] + ".awr.exr"


def test_render_without_out_writes_to_the_scenes_output_path_and_never_overwrites(tmp_path):
    from blend_util import build_scene
    build_scene(16, 12)
    scene = bpy.context.scene
    scene.render.filepath = "//render/shot_####"
    scene.frame_start, scene.frame_end, scene.frame_current = 1, 3, 3
    blend = str(tmp_path / "shot.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend, compress=True)
    out = tmp_path / "render" / "shot_0003.uniform.exr"
    r = _cli("render", blend, "--method", "uniform", "--spp", "2", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    res = _last_json(r.stdout)
    assert res["out"] == str(out) and out.is_file() and (tmp_path / "render" / "shot_0003.uniform.png").is_file()
    assert not (tmp_path / "shot.uniform.exr").exists()  # no longer beside the .blend
    before = out.stat().st_mtime_ns
    r = _cli("render", blend, "--method", "uniform", "--spp", "2", "--quiet")
    assert r.returncode == 2 and "--overwrite" in r.stderr and out.stat().st_mtime_ns == before
    r = _cli("render", blend, "--method", "var", "--spp", "4", "--initial-spp", "2", "--frames", "1-2",
             "--quiet", "--task-cost", "64")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (tmp_path / "render").glob("*.exr")) == \
        ["shot_0001.var.exr", "shot_0002.var.exr", "shot_0003.uniform.exr"]


def test_the_panels_empty_output_field_follows_the_scenes_output_path(tmp_path):
    import types

    from blend_util import build_scene
    from launch import load_package
    from cycles_adaptive.operators.render_op import CYCLESADAPTIVE_OT_render
    pkg = load_package()
    pkg.register()
    try:
        build_scene(8, 8)
        scene = bpy.context.scene
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "p.blend"))
        scene.render.filepath = "//frames/f_###"
        scene.frame_current, scene.frame_start, scene.frame_end = 5, 4, 6
        s = scene.cycles_adaptive
        s.output_path, s.method = "", "awr"
        ctx = types.SimpleNamespace(scene=scene, view_layer=bpy.context.view_layer)
        job = CYCLESADAPTIVE_OT_render._make_job(None, ctx)
        blender = scene.render.frame_path(frame=5)
        assert job.out == str(tmp_path / "frames" / "f_005.awr.exr") == blender[:-4] + ".awr.exr"
        s.frame_range = True
        frames = CYCLESADAPTIVE_OT_render._make_job(None, ctx)
        assert frames.out_pattern == str(tmp_path / "frames" / "f_###.awr.exr") and frames.frames == [4, 5, 6]
        s.frame_range, s.output_path = False, "//mine.exr"  # a path in the field is used as given
        assert CYCLESADAPTIVE_OT_render._make_job(None, ctx).out == str(tmp_path / "mine.exr")
    finally:
        pkg.unregister()


def test_view_layers_and_the_compositor_from_the_command_line(tmp_path):
    """A file with two view layers whose compositor adds them: by default
    both render (one EXR layer each, and the composite), per frame of a
    range too; --view-layer picks one, and --no-compositor leaves it raw."""
    import bpy as _bpy
    from blend_util import add_images, compositor_tree, two_layer_scene
    from cycles_adaptive.core import io as imageio
    scene = two_layer_scene(24, 16)
    tree, out_node = compositor_tree(scene)
    fore, back = tree.nodes.new("CompositorNodeRLayers"), tree.nodes.new("CompositorNodeRLayers")
    fore.layer, back.layer = "ViewLayer", "Back"
    tree.links.new(add_images(tree, fore.outputs["Image"], back.outputs["Image"]), out_node.inputs[0])
    blend = str(tmp_path / "two.blend")
    _bpy.ops.wm.save_as_mainfile(filepath=blend)
    common = ("--method", "var", "--spp", "4", "--initial-spp", "2", "--json")
    out = str(tmp_path / "f_####.exr")
    r = _cli("render", blend, "--frames", "1-2", "--out", out, *common)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(ln) for ln in r.stdout.splitlines() if ln.startswith("{")]
    for ln in lines[:-1]:
        assert ln["view_layers"] == ["ViewLayer", "Back"] and ln["compositor"] == "applied"
        _, meta = imageio.read_layers(ln["out"])
        assert meta["layers"] == ["ViewLayer", "Back", "Composite"]
    assert [ln["frame"] for ln in lines[:-1]] == [1, 2]
    r = _cli("render", blend, "--view-layer", "Back", "--no-compositor", "--out", str(tmp_path / "b.exr"),
             *common)
    assert r.returncode == 0, r.stderr
    res = _last_json(r.stdout)
    assert res["compositor"] == "off" and "view_layers" not in res
    _, meta = imageio.read_layers(res["out"])
    assert meta["layers"] == ["Back"]
    r = _cli("render", blend, "--view-layers", "Nope", "--out", str(tmp_path / "n.exr"))
    assert r.returncode == 2 and "no view layer 'Nope'" in r.stderr

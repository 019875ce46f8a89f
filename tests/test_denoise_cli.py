"""`denoise` on saved passes: works on our outputs, refuses bad files cleanly."""
import os
import subprocess
import sys

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CLI = os.path.join(ROOT, "cycles-adaptive")
ENV = dict(os.environ, CYCLES_ADAPTIVE_PYTHON=sys.executable)  # the CLI under this test's Blender


def _cli(*args):
    return subprocess.run([CLI, *args], capture_output=True, text=True, timeout=600, env=ENV)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    from blend_util import save_scene
    d = tmp_path_factory.mktemp("den")
    blend = d / "s.blend"
    save_scene(blend, width=32, height=24)
    out = d / "lp.exr"  # lp keeps the albedo, normal and depth passes in its output
    r = _cli("render", str(blend), "--method", "lp", "--spp", "6", "--initial-spp", "2", "--out", str(out),
             "--no-preview", "--task-cost", "64")
    assert r.returncode == 0, r.stderr
    return d, out


def _write(path, passes):
    from cycles_adaptive.core import io as imageio
    imageio.write_layers(str(path), passes)


@pytest.mark.parametrize("case", ["truncated", "garbage", "wrong_layers", "mismatched", "missing"])
def test_bad_files_give_one_line_exit_2_and_write_nothing(rendered, tmp_path, case):
    _, good = rendered
    src = tmp_path / f"{case}.exr"
    if case == "truncated":
        data = good.read_bytes()
        src.write_bytes(data[: len(data) // 3])
    elif case == "garbage":
        src.write_bytes(os.urandom(4096))
    elif case == "wrong_layers":
        _write(src, {"Depth": np.ones((8, 8))})
    elif case == "mismatched":  # a reference of another size
        src.write_bytes(good.read_bytes())
        _write(tmp_path / "ref.exr", {"Combined": np.ones((5, 5, 4))})
    out = tmp_path / "den.exr"
    args = ["denoise", str(src), "--method", "awr", "--out", str(out)]
    if case == "mismatched":
        args += ["--reference", str(tmp_path / "ref.exr")]
    r = _cli(*args)
    assert r.returncode == 2, (r.returncode, r.stdout[-500:], r.stderr[-2000:])
    err = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()
    assert [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")] == []


@pytest.mark.parametrize("method", ["awr", "lp", "rhf"])
def test_denoise_reruns_a_method_on_saved_passes(rendered, method):
    d, good = rendered
    out = d / f"den_{method}.exr"
    r = _cli("denoise", str(good), "--method", method, "--out", str(out), "--json")
    assert r.returncode == 0, r.stderr
    from cycles_adaptive.core import io as imageio
    passes, _ = imageio.read_layers(str(out))
    assert np.isfinite(passes["Combined"]).all()
    src, _ = imageio.read_layers(str(good))
    np.testing.assert_array_equal(passes["Samples"], src["Samples"])  # inputs carried over
    assert "Feat_albedo" in passes


def test_denoise_refuses_a_method_whose_passes_are_missing(rendered, tmp_path):
    from cycles_adaptive.core import io as imageio
    _, good = rendered
    passes, _ = imageio.read_layers(str(good))
    slim = {k: v for k, v in passes.items() if not k.startswith("Feat_normal")}
    src = tmp_path / "slim.exr"
    _write(src, slim)
    r = _cli("denoise", str(src), "--method", "lp", "--out", str(tmp_path / "o.exr"))
    assert r.returncode == 2 and "needs the normal pass" in r.stderr

"""`denoise` on saved passes: works on our outputs, refuses bad files cleanly."""
import json
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


def _png_size(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def test_denoise_names_outputs_without_doubling_and_writes_a_preview(rendered, tmp_path):
    _, good = rendered
    shot = tmp_path / "shot.lp.exr"
    shot.write_bytes(good.read_bytes())
    r = _cli("denoise", str(shot), "--method", "awr", "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["out"] == str(tmp_path / "shot.awr.exr") and os.path.isfile(res["out"])
    assert res["preview"] == str(tmp_path / "shot.awr.png")
    assert _png_size(tmp_path / "shot.awr.png") == (32, 24)
    assert isinstance(res["preview_view_transform"], str) and res["preview_view_transform"]
    before = (tmp_path / "shot.awr.exr").read_bytes()
    r = _cli("denoise", str(shot), "--method", "awr")  # existing output: refused
    assert r.returncode == 2 and "--overwrite" in r.stderr
    assert (tmp_path / "shot.awr.exr").read_bytes() == before
    src = shot.read_bytes()
    for extra in ([], ["--overwrite"], ["--out", str(shot), "--overwrite"]):  # never the input
        r = _cli("denoise", str(shot), "--method", "lp", *extra)
        assert r.returncode == 2 and "replace the input" in r.stderr, r.stderr
        assert shot.read_bytes() == src
    r = _cli("denoise", str(shot), "--method", "rhf", "--no-preview", "--json")
    assert r.returncode == 0, r.stderr
    assert os.path.isfile(tmp_path / "shot.rhf.exr") and not os.path.exists(tmp_path / "shot.rhf.png")


def test_a_render_of_any_method_can_be_denoised_by_every_method(tmp_path):
    """A var render reads no feature pass itself; its output still keeps the
    ones the denoisers read, so lp / rhf / oidn run on it."""
    from blend_util import save_scene
    from cycles_adaptive.core import io as imageio
    blend = tmp_path / "s.blend"
    save_scene(blend, width=24, height=16)
    out = tmp_path / "v.var.exr"
    r = _cli("render", str(blend), "--method", "var", "--spp", "4", "--initial-spp", "2", "--out", str(out),
             "--no-preview", "--task-cost", "64")
    assert r.returncode == 0, r.stderr
    passes, _ = imageio.read_layers(str(out))
    for name in ("albedo", "normal", "depth"):
        assert f"Feat_{name}" in passes and np.isfinite(passes[f"Feat_{name}"]).all()
    for method in ("lp", "rhf", "oidn"):
        r = _cli("denoise", str(out), "--method", method, "--no-preview")
        assert r.returncode == 0, (method, r.stderr)
        assert "warning:" not in r.stderr  # two subsets everywhere: variance known
        res, _ = imageio.read_layers(str(tmp_path / f"v.{method}.exr"))
        assert np.isfinite(res["Combined"]).all()


@pytest.fixture(scope="module")
def plain_blender_exr(tmp_path_factory):
    """A multilayer EXR from Blender's own render (Combined + Denoising
    passes, one sample group per pixel)."""
    from blend_util import build_scene
    path = tmp_path_factory.mktemp("plain") / "plain.exr"
    scene = build_scene(width=24, height=16)
    scene.cycles.samples = 4
    scene.view_layers[0].cycles.denoising_store_passes = True
    settings = scene.render.image_settings
    if hasattr(settings, "media_type"):  # Blender 5.0: the media type comes first
        settings.media_type = "MULTI_LAYER_IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    assert path.is_file()
    return path


@pytest.mark.parametrize("method,says", [("awr", "Donoho"), ("lp", "Eq. 5/7"), ("rhf", "Immerkaer"),
                                         ("oidn", "error estimate is 0")])
def test_a_plain_blender_exr_says_what_the_method_does_without_variance(plain_blender_exr, tmp_path,
                                                                        method, says):
    out = tmp_path / f"p.{method}.exr"
    r = _cli("denoise", str(plain_blender_exr), "--method", method, "--out", str(out), "--json")
    assert r.returncode == 0, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1 and "no variance" in warn[0] and says in warn[0], r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["no_variance_fraction"] == 1.0 and res["warnings"] == [warn[0][len("warning: "):]]
    if method == "awr":  # what the line says is what AWR did
        assert res["unknown_variance_pixels"] == 24 * 16
    from cycles_adaptive.core import io as imageio
    assert np.isfinite(imageio.read_layers(str(out))[0]["Combined"]).all()

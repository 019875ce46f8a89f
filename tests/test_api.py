"""The Python API (api.py) and the pytest plugin (pytest_plugin.py): the same
results as the CLI, scenes left as they were, compare's figures against
independent counts, bad input as api.Error with nothing written, and the
regression workflow (a changed material fails with a report; references are
written only with --update-references)."""
import dataclasses
import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from blend_util import build_scene, save_scene  # noqa: E402

from cycles_adaptive import api  # noqa: E402
from cycles_adaptive.core import io as imageio  # noqa: E402
from cycles_adaptive.core.method import t_quantile  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CLI = os.path.join(ROOT, "cycles-adaptive")
ENV = dict(os.environ, CYCLES_ADAPTIVE_PYTHON=sys.executable)  # the CLI under this test's Blender
EXAMPLE_REFERENCE = os.path.join(ROOT, "tests", "references", "regression_example", "cornell_0001.exr")


def _cli(*args):
    return subprocess.run([CLI, *args], capture_output=True, text=True, timeout=600, env=ENV)


def _squeeze(a):
    return a[:, :, 0] if a.ndim == 3 and a.shape[2] == 1 else a


def _settings(scene):
    r, c = scene.render, scene.cycles
    return (r.use_border, r.use_crop_to_border, r.border_max_x, r.filepath, r.image_settings.file_format,
            r.use_compositing, r.use_persistent_data, r.resolution_percentage, c.samples, c.sample_offset,
            c.seed, c.sampling_pattern, scene.view_layers[0].cycles.denoising_store_passes, scene.frame_current)


def _write_rgba(path, rgba, error=None, groups=None):
    passes = {"Combined": rgba}
    if error is not None:
        passes["Error"] = error
    if groups is not None:
        passes["Groups"] = groups
    imageio.write_layers(str(path), passes)
    return str(path)


# ============================================================ same as the CLI
def _as_stored(name, arr):
    """``arr`` as the output EXR stores pass ``name`` by default."""
    from cycles_adaptive.operators.job import RESULT_PASSES
    arr = np.asarray(arr, np.float32)
    if name not in RESULT_PASSES:
        return arr
    return imageio.as_half(arr)


@pytest.mark.parametrize("method, params, flags", [
    ("lp", {}, []),
    ("var", {"min_spp": 2, "subsets": 2}, ["--var-min-spp", "2", "--subsets", "2"]),
])
def test_api_arrays_and_file_equal_the_cli_for_the_same_arguments(tmp_path, method, params, flags):
    blend = tmp_path / "s.blend"
    save_scene(blend, width=32, height=24)
    result = api.render(str(blend), method=method, spp=6, seed=3, initial_spp=2, task_cost=64, **params)
    cli_out = tmp_path / "cli.exr"
    r = _cli("render", str(blend), "--method", method, "--spp", "6", "--seed", "3", "--initial-spp", "2",
             "--task-cost", "64", *flags, "--out", str(cli_out), "--no-preview", "--json", "--quiet")
    assert r.returncode == 0, r.stderr
    cli_passes, cli_meta = imageio.read_layers(str(cli_out))
    assert sorted(result.passes) == sorted(cli_passes)
    # the file holds the API's arrays: the result passes rounded to half float
    # (the default for a scene that does not save OpenEXR), the statistics exactly
    for name, arr in cli_passes.items():
        assert np.array_equal(_as_stored(name, result.passes[name]), _squeeze(arr)), name
    assert np.array_equal(_as_stored("Combined", result.image), cli_passes["Combined"][:, :, :3])
    assert np.array_equal(result.samples, cli_passes["Samples"][:, :, 0])
    assert np.array_equal(_as_stored("Error", result.error), cli_passes["Error"][:, :, 0])
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert list(result.summary) == list(summary)
    assert result.summary["out"] is None and result.summary["spp_mean"] == summary["spp_mean"]
    # save() writes the CLI's file: same passes, channels, layer and attributes
    saved = tmp_path / "api.exr"
    assert result.save(str(saved)) == str(saved) and result.summary["out"] == str(saved)
    passes, meta = imageio.read_layers(str(saved))
    assert meta["channels"] == cli_meta["channels"] and meta["layer"] == cli_meta["layer"]
    assert all(np.array_equal(passes[k], cli_passes[k]) for k in cli_passes)
    ours = {k: v for k, v in meta["attributes"].items() if k.startswith("cycles_adaptive/")}
    theirs = {k: v for k, v in cli_meta["attributes"].items() if k.startswith("cycles_adaptive/")}
    # version, method, options, blender, partial, reconstructed, layers, the layer's exponent
    assert ours == theirs and len(ours) == 8


def test_denoise_equals_the_cli_denoise(tmp_path):
    scene = build_scene(24, 16)
    src = tmp_path / "lp.exr"
    api.render(scene, method="lp", spp=4, initial_spp=2, task_cost=64).save(str(src))
    res = api.denoise(str(src), method="awr", shifts=2)
    out = tmp_path / "den.exr"
    r = _cli("denoise", str(src), "--method", "awr", "--awr-shifts", "2", "--out", str(out), "--json")
    assert r.returncode == 0, r.stderr
    passes, _ = imageio.read_layers(str(out))
    assert sorted(res.passes) == sorted(passes)
    assert all(np.array_equal(_as_stored(k, res.passes[k]), _squeeze(passes[k])) for k in passes)
    assert list(res.summary) == list(json.loads(r.stdout.strip().splitlines()[-1]))


# ======================================================== scene and files
def test_render_restores_the_scene_writes_nothing_and_opens_no_window(tmp_path, monkeypatch):
    blend = tmp_path / "shot.blend"
    save_scene(blend, width=40, height=30)
    stat = (blend.read_bytes(), os.stat(blend).st_mtime_ns)
    monkeypatch.chdir(tmp_path)
    scene = api.open_blend(str(blend))
    scene.cycles.seed = 5
    before = _settings(scene)
    windows = len(bpy.context.window_manager.windows)
    result = api.render(scene, method="var", spp=4, initial_spp=2, subsets=2, resolution_percentage=50)
    assert result.shape == (15, 20) and result.alpha.shape == (15, 20)
    # every render keeps the passes the denoisers read, so any method can re-run on it
    assert set(result.features) == {"albedo", "normal", "depth"}
    assert _settings(scene) == before
    assert len(bpy.context.window_manager.windows) == windows
    assert (blend.read_bytes(), os.stat(blend).st_mtime_ns) == stat
    assert sorted(os.listdir(tmp_path)) == ["shot.blend"]
    with pytest.raises(ValueError):
        result.image[0, 0, 0] = 1.0  # the arrays are what save() writes: read only


def test_a_refused_render_restores_the_resolution_override():
    scene = build_scene(16, 16, engine="EEVEE")
    with pytest.raises(api.Error, match="Cycles"):
        api.render(scene, resolution_percentage=50)
    assert scene.render.resolution_percentage == 100


def test_save_never_replaces_a_file_unless_asked(tmp_path):
    result = api.render(build_scene(16, 12), method="uniform", spp=2)
    out = tmp_path / "r.exr"
    out.write_bytes(b"precious")
    with pytest.raises(api.Error, match="overwrite=True"):
        result.save(str(out))
    assert out.read_bytes() == b"precious"
    result.save(str(out), overwrite=True, preview=True)
    assert imageio.read_layers(str(out))[0]["Combined"].shape == (12, 16, 4)
    assert os.path.isfile(tmp_path / "r.png") and result.summary["preview"] == str(tmp_path / "r.png")


# ================================================================ bad input
@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A tiny uniform render saved as one of our EXRs."""
    d = tmp_path_factory.mktemp("api")
    result = api.render(build_scene(20, 16), method="uniform", spp=4)
    return result, result.save(str(d / "ok.exr"))


@pytest.mark.parametrize("case", ["missing", "size", "channels", "nan", "garbage", "no_rgb"])
def test_a_bad_reference_is_one_error_and_nothing_is_written(saved, tmp_path, case):
    result, _ = saved
    ref = tmp_path / "ref.exr"
    rgba = np.asarray(result.rgba).copy()
    if case == "size":
        _write_rgba(ref, np.ones((5, 7, 4)))
    elif case == "channels":
        _write_rgba(ref, rgba[:, :, :3])
    elif case == "nan":
        rgba[3, 4, 1] = np.nan
        _write_rgba(ref, rgba)
    elif case == "garbage":
        ref.write_bytes(os.urandom(2048))
    elif case == "no_rgb":
        imageio.write_layers(str(ref), {"Depth": np.ones((16, 20))})
    diff = tmp_path / "diff.png"
    with pytest.raises(api.Error) as err:
        api.compare(result, str(ref), diff_path=str(diff))
    msg = str(err.value)
    assert "\n" not in msg and str(ref) in msg
    assert {"missing": "no such file", "size": "7x5", "channels": "R, G, B", "nan": "NaN",
            "garbage": "cannot open", "no_rgb": "no Combined"}[case] in msg
    assert not diff.exists() and not [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")]


@pytest.mark.parametrize("call, needle", [
    (lambda s: api.render(s, method="lp", window=3), "unknown parameter 'window' for method lp"),
    (lambda s: api.render(s, method="nope"), "unknown method 'nope'"),
    (lambda s: api.render(s, spp=-1), "spp"),
    (lambda s: api.render(s, method="awr", wavelet="db2"), "choose one of"),
    (lambda s: api.render(s, initial_spp=2.5), "expected int"),
    (lambda s: api.render(s, view_layer="Nope"), "no view layer 'Nope'"),
    (lambda s: api.render(os.path.join(ROOT, "no_such.blend")), "no such .blend file"),
    (lambda s: api.render(42), "expected a bpy Scene"),
    (lambda s: api.denoise(os.path.join(ROOT, "README.md"), method="lp"), "cannot open"),
    (lambda s: api.denoise(os.path.join(ROOT, "README.md"), method="uniform"), "not one of"),
])
def test_bad_arguments_raise_api_error_naming_the_problem(call, needle):
    scene = build_scene(12, 8)
    with pytest.raises(api.Error, match=None) as err:
        call(scene)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_denoise_refuses_a_method_whose_passes_are_missing(saved, tmp_path):
    from cycles_adaptive.core import io as imageio
    _, path = saved
    passes, meta = imageio.read_layers(str(path))
    slim = tmp_path / "slim.exr"  # the same output without its normal pass
    imageio.write_layers(str(slim), {k: v for k, v in passes.items() if not k.startswith("Feat_normal")},
                         layer=meta.get("layer") or "ViewLayer")
    with pytest.raises(api.Error, match="needs the normal pass"):
        api.denoise(str(slim), method="lp")


def test_compare_refuses_bad_thresholds(saved):
    result, path = saved
    for kw in ({"metric": "psnr"}, {"fail": -1}, {"failpercent": 101}, {"fail": float("nan")},
               {"metric": "idiff", "ignore_noise": True}):
        with pytest.raises(api.Error):
            api.compare(result, path, **kw)


# ============================================================ compare figures
def _pair(seed=0, h=60, w=80):
    rng = np.random.default_rng(seed)
    ref = np.concatenate([rng.uniform(0.0, 2.0, (h, w, 3)), np.ones((h, w, 1))], axis=-1)
    return rng, ref


def test_idiff_counts_are_openimageio_and_follow_idiffs_rule(tmp_path):
    rng, ref = _pair()
    img = ref.copy()
    h, w = ref.shape[:2]
    npix = h * w
    flat = rng.permutation(npix)
    n_fail = npix // 100  # exactly 1 %: idiff passes (fails only when more)
    ys, xs = np.unravel_index(flat[:n_fail], (h, w))
    img[ys, xs, rng.integers(0, 4, n_fail)] += 0.05
    ys2, xs2 = np.unravel_index(flat[n_fail:n_fail + 7], (h, w))
    img[ys2, xs2, 1] += 0.01  # over warn 0.005, under fail 0.016
    a, b = _write_rgba(tmp_path / "a.exr", img), _write_rgba(tmp_path / "b.exr", ref)
    c = api.compare(a, b, metric="idiff", warn=0.005, warnpercent=5)
    f32 = np.abs(img.astype(np.float32) - ref.astype(np.float32))
    assert c.figures["fail_pixels"] == int((f32 > 0.016).any(-1).sum()) == n_fail
    assert c.figures["warn_pixels"] == n_fail + 7
    assert c.status == "pass" and c.passed
    assert c.figures["max_error"] == pytest.approx(f32.max(), rel=1e-6)
    assert c.figures["mean_error"] == pytest.approx(f32.mean(), rel=1e-5)
    np.testing.assert_allclose(c.diff, f32, atol=1e-7)
    img[ys2[0], xs2[0], 2] += 0.05  # one more failing pixel: over 1 %
    c2 = api.compare(_write_rgba(tmp_path / "c.exr", img), b, metric="idiff")
    assert c2.figures["fail_pixels"] == n_fail + 1 and c2.status == "fail" and not c2.passed
    assert "FAIL" in c2.report() and "1%" in c2.report()


def test_relmse_fails_pixels_by_relative_difference(tmp_path):
    rng, ref = _pair(1)
    img = ref.copy()
    img[:, :, :3] *= 1 + rng.normal(0, 0.02, img[:, :, :3].shape)
    a, b = _write_rgba(tmp_path / "a.exr", img), _write_rgba(tmp_path / "b.exr", ref)
    c = api.compare(a, b, fail=0.03, failpercent=100)
    x, r = img[:, :, :3].astype(np.float32).astype(np.float64), ref[:, :, :3].astype(np.float32)
    rel = np.sqrt(((x - r) ** 2 / (r.astype(np.float64) ** 2 + 0.01)).mean(-1))
    assert c.figures["fail_pixels"] == int((rel > 0.03).sum()) > 0
    assert c.figures["relmse"] == pytest.approx(float((rel ** 2).mean()), rel=1e-9)
    assert c.figures["max_error"] == pytest.approx(rel.max(), rel=1e-9)
    assert c.z is None and "no error map" in c.report()  # plain EXRs carry no Error pass
    with pytest.raises(api.Error, match="no error map"):
        api.compare(a, b, ignore_noise=True)


def test_zscores_tell_noise_from_a_change(tmp_path):
    """Two renders of the same truth with known noise: z follows the normal
    law (0.27 % beyond 3); a block shifted by 10 noise levels is outside the
    noise, and only it fails with ignore_noise."""
    rng, truth = _pair(2, 200, 200)
    sd = 0.05
    noise = lambda: rng.normal(0, sd, truth.shape[:2])[..., None] * np.array([1, 1, 1, 0])
    a, b = truth + noise(), truth + noise()
    err = np.full(truth.shape[:2], sd * sd)
    many = np.full(truth.shape[:2], 1000.0)  # groups: the t value is the normal z
    ref = _write_rgba(tmp_path / "ref.exr", b, err, many)
    c = api.compare(_write_rgba(tmp_path / "a.exr", a, err, many), ref, ignore_noise=True)
    assert c.figures["z_threshold"] == pytest.approx(3.0, abs=0.02)
    assert 0.1 < c.figures["outside_noise_percent"] < 0.5 and c.passed
    assert api.compare(str(tmp_path / "a.exr"), ref).status == "fail"  # strict: noise fails
    a[50:70, 50:70, :3] += 10 * sd * np.sqrt(2)
    changed = api.compare(_write_rgba(tmp_path / "c.exr", a, err, many), ref, ignore_noise=True, fail=0.0)
    assert changed.outside_noise[50:70, 50:70].mean() > 0.99 and changed.status == "fail"
    assert changed.failing[50:70, 50:70].mean() > 0.99
    assert changed.failing.sum() - changed.failing[50:70, 50:70].sum() < 0.005 * changed.failing.size
    # four groups: the threshold is the t value for 3 degrees of freedom
    four = api.compare(_write_rgba(tmp_path / "d.exr", a, err, np.full(truth.shape[:2], 4.0)), ref)
    assert four.figures["z_threshold"] == pytest.approx(float(t_quantile(3.0, np.array([3.0]))[0]))


def test_identical_renders_pass_and_the_diff_is_written_on_request(saved, tmp_path):
    result, path = saved
    for metric in ("relmse", "idiff"):
        c = api.compare(result, path, metric=metric, diff_path=str(tmp_path / f"{metric}.exr"))
        assert c.status == "pass" and c.figures["fail_pixels"] == 0 and c.figures["z_max"] == 0.0
        d, _ = imageio.read_layers(str(tmp_path / f"{metric}.exr"))
        assert not d["Diff"].any() and not d["Failing"].any() and not d["OutsideNoise"].any()
    c.write_diff(str(tmp_path / "d.png"))
    png, _ = imageio.read_layers(str(tmp_path / "d.png"))
    assert png[""].shape[:2] == result.shape and not png[""].any()
    with pytest.raises(api.Error, match="exists"):
        c.write_diff(str(tmp_path / "d.png"))


# ======================================================= plugin and example
def test_the_documented_example_is_the_example_test():
    doc = open(os.path.join(ROOT, "docs", "regression-tests.md"), encoding="utf-8").read()
    example = open(os.path.join(ROOT, "tests", "test_regression_example.py"), encoding="utf-8").read()
    blocks = [b.split("\n", 1)[1] for b in doc.split("```python")[1:]]
    assert any(b.split("```")[0] == example for b in blocks)


CHANGED = '''
import dataclasses, sys
sys.path.insert(0, {tests!r})
import bpy
from test_regression_example import CASES

def blue_wall(scene):  # the deliberate change: the red wall turns blue
    bsdf = bpy.data.materials["Red"].node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (0.05, 0.065, 0.63, 1.0)

def test_changed_material(render_regression):
    render_regression.check(dataclasses.replace(CASES[0], prepare=blue_wall, name="cornell_blue",
                                                reference={ref!r}))

def test_missing_reference(render_regression):
    render_regression.check(dataclasses.replace(CASES[0], name="cornell_new", reference={new!r}))
'''


def _pytest(cwd, *args, env=None):
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=600, env=env)


def _sha(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_a_changed_material_fails_with_a_report_and_references_change_only_when_asked(tmp_path):
    before = _sha(EXAMPLE_REFERENCE)
    work = tmp_path / "suite"
    work.mkdir()
    # the repository importable as the package cycles_adaptive (-p loads the plugin before any conftest)
    (tmp_path / "pkgroot").mkdir()
    os.symlink(ROOT, tmp_path / "pkgroot" / "cycles_adaptive")
    env = dict(os.environ, PYTHONPATH=str(tmp_path / "pkgroot"))
    (work / "test_changed.py").write_text(CHANGED.format(tests=os.path.join(ROOT, "tests"),
                                                         ref=EXAMPLE_REFERENCE, new=str(tmp_path / "new.exr")))
    report = tmp_path / "report"
    r = _pytest(work, "-p", "cycles_adaptive.pytest_plugin", "--render-report", str(report), env=env)
    out = r.stdout
    assert r.returncode == 1 and "2 failed" in out, out[-3000:] + r.stderr[-2000:]
    assert "render regression 'cornell_blue'" in out and "FAIL:" in out and "allowed 1%" in out
    assert "differ by more than the renders' own noise" in out and "Traceback" not in out
    assert f"report: {report / 'cornell_blue'}" in out and "reference" in out and "does not exist" in out
    for name in ("before.png", "after.png", "diff.png", "after.exr", "case.json"):
        assert (report / "cornell_blue" / name).is_file(), name
    rec = json.loads((report / "cornell_blue" / "case.json").read_text())
    assert rec["status"] == "fail" and rec["figures"]["fail_percent"] > 1
    assert (report / "index.html").is_file() and len(json.loads((report / "report.json").read_text())) == 2
    diff = imageio.read_layers(str(report / "cornell_blue" / "diff.png"))[0][""]
    red = (diff[:, :, 0] > 0.99) & (diff[:, :, 1] < 0.01)
    w = diff.shape[1]
    assert red[:, : w // 4].mean() > 5 * red[:, w // 4:].mean()  # the changed wall is the left one
    assert _sha(EXAMPLE_REFERENCE) == before and not (tmp_path / "new.exr").exists()  # never silently

    # --update-references through a top conftest.py (the other documented way to load the plugin)
    ref = tmp_path / "ref.exr"
    ref.write_bytes(open(EXAMPLE_REFERENCE, "rb").read())
    (work / "test_changed.py").write_text(CHANGED.format(tests=os.path.join(ROOT, "tests"), ref=str(ref),
                                                         new=str(tmp_path / "new.exr")))
    (work / "conftest.py").write_text(f"import sys\nsys.path.insert(0, {ROOT!r})\n"
                                      "from launch import load_package\nload_package()\n"
                                      "pytest_plugins = ['cycles_adaptive.pytest_plugin']\n")
    r = _pytest(work, "--update-references")
    assert r.returncode == 0 and "2 passed" in r.stdout, r.stdout[-3000:] + r.stderr[-2000:]
    assert f"reference updated: {ref}" in r.stdout and f"reference created: {tmp_path / 'new.exr'}" in r.stdout
    assert _sha(ref) != before and (tmp_path / "new.exr").is_file()
    r = _pytest(work)
    assert r.returncode == 0 and "2 passed" in r.stdout and "reference updated" not in r.stdout, r.stdout[-3000:]
    assert _sha(EXAMPLE_REFERENCE) == before


def test_the_plugin_reports_a_scene_it_cannot_render(tmp_path, pytestconfig):
    from cycles_adaptive.pytest_plugin import Case, Regression
    blend = tmp_path / "eevee.blend"
    save_scene(blend, width=8, height=8, engine="EEVEE")
    reg = Regression(pytestconfig, str(tmp_path / "rep"))
    out = reg.run(Case(str(blend), 1, str(tmp_path / "ref.exr")))
    assert out.failed and out.status == "error" and "Cycles" in out.message
    assert not (tmp_path / "ref.exr").exists()
    assert json.loads((tmp_path / "rep" / "ref" / "case.json").read_text())["status"] == "error"
    with pytest.raises(ValueError, match="names a folder"):
        dataclasses.replace(Case(str(blend), 1, "x.exr"), name="a/b")

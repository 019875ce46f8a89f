"""The extension as an artist gets it: one zip per platform carrying its OpenImageIO wheel and the
pure-Python threadpoolctl wheel, installed under this venv's bpy with the venv's copies hidden,
enabled, and rendering through the operator.

run-tests.sh runs this file under Blender 4.2, 4.5 and 5.0 (``.venv-4.2``, ``.venv``, ``.venv-5.0``).
The wheels are fetched once into the git-ignored ``wheels/`` by tools/build_extension.py; without them
and without a reachable package index the tests skip, except under ``CI=true``, where they fail.
"""
import hashlib
import importlib.util
import json
import os
import platform
import subprocess
import sys
import tomllib
import zipfile

import pytest

bpy = pytest.importorskip("bpy")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_spec = importlib.util.spec_from_file_location("build_extension",
                                               os.path.join(ROOT, "tools", "build_extension.py"))
build_extension = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(build_extension)

# Blender platform -> (prefix, suffix) of the wheel platform tag that belongs in its zip (PEP 425
# platform tags; written out here, independently of Blender's own mapping in blender_ext.py).
WHEEL_TAG = {"linux-x64": ("manylinux", "_x86_64"), "windows-x64": ("win", "_amd64"),
             "macos-arm64": ("macosx_", "_arm64"), "macos-x64": ("macosx_", "_x86_64")}


def this_platform():
    """This machine as a Blender platform name (``linux-x64``)."""
    system = {"darwin": "macos"}.get(platform.system().lower(), platform.system().lower())
    machine = {"x86_64": "x64", "amd64": "x64", "aarch64": "arm64"}.get(platform.machine().lower(),
                                                                       platform.machine().lower())
    return f"{system}-{machine}"


@pytest.fixture(scope="module")
def zips(tmp_path_factory):
    """Platform -> zip, built once per test session by the studio's build script."""
    out = tmp_path_factory.mktemp("extension")
    try:
        return build_extension.build(out_dir=str(out), log=lambda *_: None)
    except build_extension.BuildError as exc:
        if exc.code == build_extension.EXIT_OFFLINE and os.environ.get("CI") != "true":
            pytest.skip(f"wheels missing from wheels/ and {exc}")
        pytest.fail(f"tools/build_extension.py: {exc}")


def _ext_tool():
    return build_extension.extension_tool(sys.executable)


def _run_roundtrip(zip_path, tmp_path):
    """Install ``zip_path`` in a fresh bpy process with private user folders (tests/ext_roundtrip.py)."""
    env = dict(os.environ, BLENDER_USER_EXTENSIONS=str(tmp_path / "extensions"),
               BLENDER_USER_CONFIG=str(tmp_path / "config"), BLENDER_USER_SCRIPTS=str(tmp_path / "scripts"))
    repo_dir = tmp_path / "repo"
    repo_dir.mkdir()
    return subprocess.run([sys.executable, os.path.join(ROOT, "tests", "ext_roundtrip.py"), str(zip_path),
                           str(repo_dir), str(tmp_path / "op.exr")],
                          capture_output=True, text=True, timeout=300, env=env)


def _drop_wheels(manifest_text):
    """``manifest_text`` without its ``wheels = [...]`` arrays (one line or several)."""
    out, skipping = [], False
    for line in manifest_text.splitlines(keepends=True):
        if skipping:
            skipping = not line.strip().startswith("]")
        elif line.startswith("wheels = ["):
            skipping = not line.rstrip().endswith("]")
        else:
            out.append(line)
    return "".join(out)


def test_one_valid_zip_per_platform_each_with_only_its_wheel(zips):
    manifest = build_extension.read_manifest(ROOT)
    assert sorted(zips) == sorted(manifest["platforms"]) == sorted(WHEEL_TAG)
    for plat, path in zips.items():
        val = subprocess.run([sys.executable, _ext_tool(), "validate", path], capture_output=True, text=True)
        assert val.returncode == 0, val.stdout + val.stderr
        with zipfile.ZipFile(path) as zf:
            names = zf.namelist()
            wheels = [n for n in names if n.endswith(".whl")]
            pure = [n for n in wheels if n.endswith("-py3-none-any.whl")]
            assert [os.path.basename(n).split("-")[0] for n in pure] == ["threadpoolctl"], (plat, wheels)
            wheels = [n for n in wheels if n not in pure]
            assert len(wheels) == 1, (plat, wheels)
            tag = wheels[0][:-4].split("-")[-1]
            prefix, suffix = WHEEL_TAG[plat]
            assert all(t.startswith(prefix) and t.endswith(suffix) for t in tag.split(".")), (plat, tag)
            # bundled unmodified: the bytes are the cached download's
            for w in wheels + pure:
                with open(os.path.join(ROOT, w), "rb") as fh:
                    assert hashlib.sha256(zf.read(w)).digest() == hashlib.sha256(fh.read()).digest()
            generated = tomllib.loads(zf.read("blender_manifest.toml").decode())["build"]["generated"]
        assert generated["platforms"] == [plat]
        assert sorted(generated["wheels"]) == sorted("./" + w for w in wheels + pure)
        assert "blender_manifest.toml" in names and "core/pipeline.py" in names and "core/io.py" in names
        assert not any(n.startswith(("tests/", ".venv", "sample_blends/", "bench/", "tools/", "docs/",
                                     "build/", "run-tests.sh", "setup.sh")) for n in names), names
        # no benchmark code or reference images (path segments: addon/preferences.py is fine)
        assert not any(seg.startswith(("references", "bench")) for n in names for seg in n.split("/")), names


def test_installs_with_only_the_bundled_openimageio_enables_and_renders(zips, tmp_path):
    plat = this_platform()
    if plat not in zips:
        pytest.skip(f"no extension build for {plat}")
    run = _run_roundtrip(zips[plat], tmp_path)
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("RESULT ")]
    assert run.returncode == 0 and lines, run.stdout[-3000:] + run.stderr[-3000:]
    res = json.loads(lines[-1][len("RESULT "):])
    assert res["version"] == list(bpy.app.version[:2])
    # the venv's OpenImageIO was unreachable; the wheel Blender unpacked from the zip is what loaded
    assert res["hidden_before"], res
    assert res["wheel_site"].startswith(str(tmp_path / "extensions")), res
    assert res["wheel_site_on_path"], res
    assert res["oiio_file"] == res["addon_oiio_file"], res
    assert res["oiio_file"].startswith(res["wheel_site"] + os.sep), res
    assert res["tpc_file"] and res["tpc_file"].startswith(res["wheel_site"] + os.sep), res
    assert res["blas_in_pieces"] == [[1], [1]], res
    assert res["install"] == ["FINISHED"] and res["enabled"], res
    assert res["op"] == ["FINISHED"], res
    assert res["api"], res
    assert res["exists"] and res["png"], res
    assert res["exr_shape"] == [16, 24, 4] and res["exr_finite"], res
    assert {"Combined", "Noisy", "Variance", "Samples", "Error"} <= set(res["exr_passes"]), res
    assert res["images"] == ["Cycles Adaptive Error", "Cycles Adaptive Result", "Cycles Adaptive Samples"]
    assert res["border_restored"]
    assert res["range_op"] == ["FINISHED"] and res["range_files"] == [True, True], res
    assert res["commands"] == ["denoise", "render"], res


def test_without_its_wheel_the_same_zip_does_not_load(zips, tmp_path):
    """Control for the test above: OpenImageIO really is hidden, so the wheel is what made it load."""
    plat = this_platform()
    if plat not in zips:
        pytest.skip(f"no extension build for {plat}")
    stripped = tmp_path / "no_wheel.zip"
    with zipfile.ZipFile(zips[plat]) as src, zipfile.ZipFile(stripped, "w", zipfile.ZIP_DEFLATED) as dst:
        for name in src.namelist():
            data = src.read(name)
            if name.endswith(".whl"):
                continue
            if name == "blender_manifest.toml":
                data = _drop_wheels(data.decode()).encode()
                assert "wheels" not in tomllib.loads(data.decode())
                assert "wheels" not in tomllib.loads(data.decode())["build"]["generated"]
            dst.writestr(name, data)
    run = _run_roundtrip(stripped, tmp_path)
    out = run.stdout + run.stderr
    assert run.returncode != 0 and "RESULT " not in run.stdout, out[-3000:]
    assert "register()" in out and "OpenImageIO" in out, out[-3000:]

"""The extension round trip: build, validate, install under bpy, run the operator."""
import glob
import json
import os
import subprocess
import sys

import pytest

bpy = pytest.importorskip("bpy")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _ext_tool():
    base = bpy.utils.resource_path("LOCAL")  # .../bpy/<version>
    found = glob.glob(os.path.join(base, "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py"))
    assert found, "blender_ext.py not found in the bpy wheel"
    return found[0]


def test_build_validate_install_and_run_operator(tmp_path):
    tool = _ext_tool()
    build = subprocess.run([sys.executable, tool, "build", "--source-dir", ROOT, "--output-dir",
                            str(tmp_path)], capture_output=True, text=True)
    assert build.returncode == 0, build.stdout + build.stderr
    zips = glob.glob(str(tmp_path / "cycles_adaptive-*.zip"))
    assert len(zips) == 1
    val = subprocess.run([sys.executable, tool, "validate", zips[0]], capture_output=True, text=True)
    assert val.returncode == 0, val.stdout + val.stderr
    import zipfile
    names = zipfile.ZipFile(zips[0]).namelist()
    assert "blender_manifest.toml" in names and "core/pipeline.py" in names
    assert not any(n.startswith(("tests/", ".venv", "sample_blends/", "bench/", "tools/", "docs/"))
                   for n in names)
    assert not any("references" in n or "bench" in n for n in names), names

    out = str(tmp_path / "op.exr")
    repo_dir = tmp_path / "repo"
    repo_dir.mkdir()
    run = subprocess.run([sys.executable, os.path.join(ROOT, "tests", "ext_roundtrip.py"), zips[0],
                          str(repo_dir), out], capture_output=True, text=True, timeout=600)
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("RESULT ")]
    assert run.returncode == 0 and lines, run.stdout[-3000:] + run.stderr[-3000:]
    res = json.loads(lines[-1][len("RESULT "):])
    assert res["op"] == ["FINISHED"], res
    assert res["exists"] and res["png"], res
    assert res["images"] == ["Cycles Adaptive Error", "Cycles Adaptive Result", "Cycles Adaptive Samples"]
    assert res["border_restored"]
    assert res["range_op"] == ["FINISHED"] and res["range_files"] == [True, True], res
    assert res["commands"] == ["denoise", "render"], res

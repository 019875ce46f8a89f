"""``./cycles-adaptive bench --quick`` and ``references``: the harness runs end to
end and writes every file and field (never a timing assert)."""
import json
import os
import subprocess

import pytest

bpy = pytest.importorskip("bpy")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CLI = os.path.join(ROOT, "cycles-adaptive")
CORNELL = os.path.join(ROOT, "sample_blends", "cornell.blend")

needs_scene = pytest.mark.skipif(not os.path.isfile(CORNELL), reason="sample_blends/cornell.blend not built")

RUN_FIELDS = ("kind", "name", "budget", "status", "spp_mean", "relmse", "smape", "seconds",
              "efficiency", "speedup", "scene")
METHOD_FIELDS = ("error_correlation", "center_fraction", "regions", "iterations", "memory")
SECONDS = ("total", "render", "adapt", "reconstruct", "overhead")


def _cli(*args, timeout=900):
    return subprocess.run([CLI, *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    refdir = tmp_path_factory.mktemp("refs")
    r = _cli("bench", "--quick", "--out", str(out), "--reference-dir", str(refdir), "--json")
    assert r.returncode == 0, r.stderr[-3000:] + r.stdout[-3000:]
    return out, refdir, r


@needs_scene
def test_quick_writes_every_output(quick):
    out, _, r = quick
    last = json.loads(r.stdout.strip().splitlines()[-1])
    assert last["out"] == str(out)
    for name in ("results.json", "results.md", "plot_cornell.png", "sheet_cornell.png"):
        p = out / name
        assert p.is_file() and p.stat().st_size > 0, name
    with open(out / "plot_cornell.png", "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"


@needs_scene
def test_quick_results_json_has_the_figures(quick):
    out, _, _ = quick
    res = json.loads((out / "results.json").read_text())
    for key in ("machine", "config", "protocol", "scenes", "scaling", "targets", "summary",
                "session_seconds", "command"):
        assert key in res, key
    for key in ("cpu_count", "platform", "blender", "numpy", "python"):
        assert res["machine"][key], key
    sc = res["scenes"]["cornell"]
    assert sc["status"] == "ok"
    assert sc["reference"]["spp"] >= 1024 and sc["reference"]["seed"] != 0
    assert sc["reference"]["blender"] == res["machine"]["blender"]
    assert len(sc["uniform_curve"]) == 3
    for p in sc["uniform_curve"]:
        assert {"spp", "relmse", "smape", "seconds", "speedup"} <= set(p)

    runs = sc["runs"]
    names = {r["name"] for r in runs}
    # every method appears (ok or as an error entry with its message), never dropped
    for m in ("uniform", "var", "awr", "lp", "rhf"):
        assert m in names, m
    for peer in ("oidn", "cycles_adaptive", "cycles_adaptive+oidn"):
        assert peer in names, peer
    assert any(n.startswith("oracle-") for n in names)
    for r in runs:
        if r["status"] != "ok":
            assert r["error"], r
            continue
        for k in RUN_FIELDS:
            assert k in r, (r["name"], k)
        assert r["relmse"] > 0 and r["smape"] > 0
        for k in ("total", "render"):
            assert k in r["seconds"]
        if r["kind"] == "method":
            for k in METHOD_FIELDS:
                assert k in r, (r["name"], k)
            assert set(SECONDS) <= set(r["seconds"])
            assert "bytes_per_pixel" in r["memory"] or "error" in r["memory"]
    adaptive = next(r for r in runs if r["name"] == "cycles_adaptive")
    if adaptive["status"] == "ok":
        assert {"threshold", "max_samples", "target_seconds", "time_ratio"} <= set(adaptive)
    lp = next(r for r in runs if r["name"] == "lp")
    if lp["status"] == "ok":
        assert lp["center_fraction"] is not None

    scal = res["scaling"]
    assert scal and len(scal["rows"]) == 2
    for row in scal["rows"]:
        assert {"width", "height", "megapixels", "oidn", "methods"} <= set(row)
        assert "seconds" in row["oidn"] or "error" in row["oidn"]
        for m, v in row["methods"].items():
            assert "seconds_per_mp" in v or "error" in v or "skipped" in v, (m, v)

    targets = {t["target"] for t in res["targets"]}
    assert len(targets) == 5
    for t in res["targets"]:
        assert t["met"] in (True, False, None) and isinstance(t["detail"], list)


@needs_scene
def test_quick_markdown_has_the_tables(quick):
    out, _, _ = quick
    md = (out / "results.md").read_text()
    for heading in ("## Summary", "## Targets", "## cornell", "## Scaling", "## How it was measured"):
        assert heading in md, heading
    assert "warm-up" in md  # the warm-up render is stated
    for name in ("oidn", "cycles_adaptive", "lp", "rhf", "awr", "var", "uniform"):
        assert f"| {name} |" in md or f"| cornell | {name} |" in md, name


@needs_scene
def test_quick_reused_the_reference_cache(quick, tmp_path):
    """The reference rendered by the quick run is cached with its sidecar and
    reused by `references` (same spp, seed, resolution, frame, version)."""
    _, refdir, _ = quick
    side = [f for f in os.listdir(refdir) if f.endswith(".json")]
    assert side, os.listdir(refdir)
    rec = json.loads((refdir / side[0]).read_text())
    for k in ("spp", "seed", "resolution_percentage", "frame", "blender", "blend_sha256", "noise_relmse"):
        assert k in rec, k
    r = _cli("references", "--scenes", "cornell", "--resolution-percentage", "25",
             "--dir", str(refdir), "--json")
    assert r.returncode == 0, r.stderr[-2000:]
    rep = json.loads(r.stdout.strip().splitlines()[-1])
    assert rep["references"][0]["cached"] is True


def test_bad_input_is_one_line(tmp_path):
    r = _cli("bench", "--scenes", "no_such_scene", "--out", str(tmp_path))
    assert r.returncode == 2
    assert "unknown scene 'no_such_scene'" in r.stderr and "Traceback" not in r.stderr
    r = _cli("bench", "--methods", "nope", "--out", str(tmp_path))
    assert r.returncode == 2 and "unknown method 'nope'" in r.stderr
    r = _cli("bench", "--budgets", "0,4", "--out", str(tmp_path))
    assert r.returncode == 2 and "--budgets" in r.stderr
    r = _cli("references", "--scenes", "no_such_scene")
    assert r.returncode == 2 and "unknown scene" in r.stderr


@needs_scene
def test_missing_and_foreign_references_are_refused(tmp_path):
    r = _cli("bench", "--quick", "--no-render-references", "--reference-dir", str(tmp_path),
             "--out", str(tmp_path / "o"))
    assert r.returncode == 2, r.stderr[-2000:]
    assert "missing" in r.stderr and "references" in r.stderr and "Traceback" not in r.stderr


def test_reference_from_another_blender_version_is_refused(tmp_path):
    """check_reference (what the bench calls) refuses another version, naming both."""
    from cycles_adaptive.bench import references as refs
    exr = tmp_path / "x.f0001.r100.s1024.exr"
    exr.write_bytes(b"not read")
    (tmp_path / "x.f0001.r100.s1024.json").write_text(json.dumps({"blender": "3.6.0", "scene": "x"}))
    with pytest.raises(refs.ReferenceFileError, match="3.6.0.*" + bpy.app.version_string.split()[0]):
        refs.check_reference(str(exr))


def test_speedup_curve_interpolates_log_log_and_extrapolates_with_slope_minus_one():
    from cycles_adaptive.bench.targets import speedup_curve
    t = speedup_curve([(0.1, 1.0), (0.01, 10.0)])
    assert t(0.1) == pytest.approx(1.0)
    assert t(0.01) == pytest.approx(10.0)
    assert t(0.0316227766) == pytest.approx(10 ** 0.5, rel=1e-6)
    assert t(0.001) == pytest.approx(100.0)   # slope -1 beyond the best uniform render
    assert t(1.0) == pytest.approx(0.1)       # and beyond the worst
    assert t(float("nan")) != t(float("nan"))  # NaN for no error


def test_the_extension_ships_without_the_benchmark():
    """The build excludes the top-level bench/ package, and the shipped
    operators/ package has no bench or references module."""
    import tomllib
    with open(os.path.join(ROOT, "blender_manifest.toml"), "rb") as f:
        manifest = tomllib.load(f)
    assert "/bench/" in manifest["build"]["paths_exclude_pattern"]
    for name in ("bench", "references"):
        assert not os.path.exists(os.path.join(ROOT, "operators", name + ".py")), name
        assert not os.path.isdir(os.path.join(ROOT, "operators", name)), name

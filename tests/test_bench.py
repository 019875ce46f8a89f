"""``./cycles-adaptive bench --quick`` and ``references``: the harness runs end to
end and writes every file and field (never a timing assert)."""
import json
import os
import subprocess

import numpy as np
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


LOOP_FIGURES = ("error_correlation", "error_correlation_block", "guard_fraction", "negative_share",
                "negative_min", "brightness_percent", "beyond_map_percent", "map_cv", "map_uniform_share",
                "adapt_reconstruct_s_per_mp", "oidn_denoise_s_per_mp")
ADAPTIVE = ("var", "awr", "lp", "rhf")


@needs_scene
def test_quick_results_json_has_the_figures(quick):
    from cycles_adaptive.bench import targets
    out, _, _ = quick
    res = json.loads((out / "results.json").read_text())
    for key in ("machine", "config", "protocol", "scenes", "scaling", "targets", "summary",
                "session_seconds", "command"):
        assert key in res, key
    for key in ("cpu_count", "platform", "blender", "numpy", "python"):
        assert res["machine"][key], key
    assert res["errors"] == []
    sc = res["scenes"]["cornell"]
    assert sc["status"] == "ok"
    assert sc["reference"]["spp"] >= 1024 and sc["reference"]["seed"] != 0
    assert sc["reference"]["blender"] == res["machine"]["blender"]
    assert len(sc["uniform_curve"]) == 3
    for p in sc["uniform_curve"]:
        assert {"spp", "relmse", "smape", "seconds", "speedup"} <= set(p)

    runs = sc["runs"]
    # a successful tiny run: every run it made succeeded, and every run it should make is there
    assert [(r["name"], r.get("error")) for r in runs if r["status"] != "ok"] == []
    names = {r["name"] for r in runs}
    want = {"uniform", *ADAPTIVE, *("oracle-" + m for m in ADAPTIVE), *("uniform-" + m for m in ADAPTIVE),
            "cycles_oidn", "cycles_adaptive", "cycles_adaptive+oidn"}
    assert names == want, names ^ want
    for r in runs:
        for k in RUN_FIELDS:
            assert k in r, (r["name"], k)
        assert r["relmse"] > 0 and r["smape"] > 0
        assert np.isfinite(r["speedup"]) and r["speedup"] > 0, r["name"]
        if r["kind"] == "method":
            for k in METHOD_FIELDS:
                assert k in r, (r["name"], k)
            assert "bytes_per_pixel" in r["memory"], r["memory"]
        if r["kind"] in targets.LOOP_KINDS:
            sec = r["seconds"]
            assert set(SECONDS) <= set(sec)
            assert sec["render"] + sec["adapt"] + sec["reconstruct"] <= sec["total"] + 1e-9
            for k in LOOP_FIGURES:
                assert r[k] is not None and np.isfinite(r[k]), (r["name"], k, r[k])
            assert -1.0 <= r["error_correlation"] <= 1.0 and -1.0 <= r["error_correlation_block"] <= 1.0
            assert 0.0 <= r["guard_fraction"] <= 1.0 and 0.0 <= r["negative_share"] <= 1.0
            assert 0.0 <= r["guard_rounding"] <= 1.0 - r["guard_fraction"]
            assert (r["negative_min"] < 0) == (r["negative_share"] > 0)
            assert 0.0 <= r["map_uniform_share"] <= 1.0 and r["map_cv"] >= 0.0
            assert 0.0 <= r["beyond_map_percent"] <= 100.0
            # each verdict is the verdict of its figure
            assert set(targets.RUN_GOALS) <= set(r["goals"])
            for k, g in r["goals"].items():
                assert g["met"] == targets.met(k, r.get(k)), (r["name"], k)
                # every figure is measured here; the cost only where OIDN's own time was > 0
                unmeasured = k == "oidn_cost_ratio" and not r["oidn_denoise_s_per_mp"] > 0
                assert (g["met"] is None) == unmeasured, (r["name"], k, g)
    by = {r["name"]: r for r in runs}
    # uniform sampling renders every pixel equally: no spread, nothing beyond the map
    for n in ("uniform",) + tuple("uniform-" + m for m in ADAPTIVE):
        assert by[n]["map_cv"] == 0.0 and by[n]["map_uniform_share"] == 1.0, n
        assert by[n]["beyond_map_percent"] == 0.0 and by[n]["spp_mean"] == 8.0, n
    # the sample mean as the image: no brightness shift, no negative output
    assert abs(by["uniform"]["brightness_percent"]) < 1e-9 and by["uniform"]["negative_share"] == 0.0
    oidn = by["cycles_oidn"]
    assert oidn["denoise_seconds"] >= 0.0 and oidn["render_seconds_without_denoiser"] > 0.0
    assert oidn["denoise_s_per_mp"] == pytest.approx(oidn["denoise_seconds"] / (32 * 32 / 1e6))
    assert by["cycles_adaptive"]["time_ratio"] > 0 and {"threshold", "max_samples", "target_seconds"} <= \
        set(by["cycles_adaptive"])
    assert by["lp"]["center_fraction"] is not None

    # the comparisons are the relMSE ratios of the runs at equal budget
    comp = {c["method"]: c for c in sc["comparisons"]}
    assert set(comp) == set(ADAPTIVE)
    for m, c in comp.items():
        assert c["budget"] == 8
        assert c["estimated_over_oracle"] == pytest.approx(by[m]["relmse"] / by["oracle-" + m]["relmse"])
        assert c["uniform_over_oracle"] == pytest.approx(by["uniform-" + m]["relmse"] / by["oracle-" + m]["relmse"])
        assert c["uniform_over_method"] == pytest.approx(by["uniform-" + m]["relmse"] / by[m]["relmse"])
        assert c["goals"]["uniform_over_oracle"]["met"] is None  # cornell is not a localised scene

    scal = res["scaling"]
    assert scal and len(scal["rows"]) == 2
    for row in scal["rows"]:
        assert {"width", "height", "megapixels", "oidn", "methods"} <= set(row)
        assert "seconds" in row["oidn"], row["oidn"]
        for m, v in row["methods"].items():
            assert "seconds_per_mp" in v or "skipped" in v, (m, v)

    tg = {t["target"]: t for t in res["targets"]}
    assert len(tg) == len(res["targets"]) == 7 + len(targets.RUN_GOALS) + 2 + 4  # + auto's 2, oidn's 2
    for t in res["targets"]:
        assert isinstance(t["detail"], list) and t["detail"]
    # per-run targets: met exactly when every method run meets the goal
    for t in res["targets"]:
        if t.get("key") in targets.RUN_GOALS + ("speedup", "oidn_cost_ratio"):
            flags = [r["goals"][t["key"]]["met"] for r in runs if r["kind"] == "method"]
            assert t["met"] == all(flags), t


@needs_scene
def test_quick_markdown_has_the_tables(quick):
    out, _, _ = quick
    md = (out / "results.md").read_text()
    for heading in ("## Summary", "## Targets", "## cornell", "## Scaling", "## How it was measured",
                    "Estimates and artefacts", "Where the samples go", "Time split and cost vs OIDN"):
        assert heading in md, heading
    assert "warm-up" in md  # the warm-up render is stated
    for name in ("cycles_oidn", "cycles_adaptive", "lp", "rhf", "awr", "var", "uniform"):
        assert f"| {name} |" in md or f"| cornell | {name} |" in md, name
    for name in ("uniform-lp", "oracle-awr"):
        assert f"| {name} | 8 |" in md, name


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


# ----------------------------------------------------- goals on hand-made figures
#: per goal: (a figure that meets it, one that misses it), each close to the bound
SIDES = {"error_correlation_block": (0.8, 0.79), "guard_fraction": (0.049, 0.05),
         "negative_share": (0.0, 1e-6), "brightness_percent": (-0.5, 0.51),
         "beyond_map_percent": (9.99, 10.0), "speedup": (1.0, 0.99), "oidn_cost_ratio": (1.0, 1.01),
         "estimated_over_oracle": (1.15, 1.16), "uniform_over_oracle": (1.3, 1.29)}


def test_each_goal_is_met_on_one_side_of_its_bound_and_missed_on_the_other():
    from cycles_adaptive.bench import targets
    assert set(SIDES) == set(targets.GOALS)
    for key, (good, bad) in SIDES.items():
        assert targets.met(key, good) is True, key
        assert targets.met(key, bad) is False, key
        for unknown in (None, float("nan"), float("inf")):
            assert targets.met(key, unknown) is None, key
        assert targets.goal(key, bad) == {"value": bad, "met": False}
    assert targets.met("brightness_percent", 0.49) is True  # |shift|: both signs
    assert targets.met("brightness_percent", -0.51) is False


def _run(name, budget=8, kind="method", **figs):
    sec = figs.pop("seconds", {"total": 1.0, "render": 0.5, "adapt": 0.2, "reconstruct": 0.2,
                               "overhead": 0.1})
    return {"kind": kind, "name": name, "method": name.split("-")[-1], "budget": budget, "status": "ok",
            "relmse": figs.pop("relmse", 0.01), "seconds": sec, **figs}


def _scene(runs, name="glossy", w=100, h=100):
    from cycles_adaptive.bench import targets
    good = {k: SIDES[k][0] for k in targets.RUN_GOALS if k in SIDES}
    runs = [{**good, "speedup": 1.5, **r} if r["kind"] != "peer" else r for r in runs]
    return {"status": "ok", "width": w, "height": h, "runs": runs,
            "comparisons": targets.compare_runs(name, runs, w * h / 1e6)}


def test_compare_runs_ratios_cost_and_which_comparisons_are_judged():
    from cycles_adaptive.bench import targets
    runs = [_run("lp", relmse=0.012), _run("oracle-lp", kind="oracle", relmse=0.010),
            _run("uniform-lp", kind="uniform_sampling", relmse=0.0125),
            _run("rhf", relmse=0.02), _run("oracle-rhf", kind="oracle", relmse=0.01),
            _run("uniform-rhf", kind="uniform_sampling", relmse=0.04),
            {"kind": "peer", "name": "cycles_oidn", "budget": 8, "status": "ok", "relmse": 0.01,
             "seconds": {"total": 1.0}, "denoise_s_per_mp": 50.0}]
    comp = {c["method"]: c for c in targets.compare_runs("glossy", runs, 0.01)}
    lp = comp["lp"]
    assert lp["estimated_over_oracle"] == pytest.approx(1.2)
    assert lp["uniform_over_oracle"] == pytest.approx(1.25)
    assert lp["uniform_over_method"] == pytest.approx(0.0125 / 0.012)
    assert lp["goals"]["estimated_over_oracle"]["met"] is False      # 1.2 > 1.15
    assert lp["goals"]["uniform_over_oracle"]["met"] is False        # 1.25 < 1.3 on a localised scene
    assert comp["rhf"]["goals"]["uniform_over_oracle"]["met"] is None  # rhf: not one of lp, awr
    assert comp["rhf"]["goals"]["estimated_over_oracle"]["met"] is False
    # cornell is not a localised scene: the same ratios are reported, not judged
    c = {c["method"]: c for c in targets.compare_runs("cornell", runs, 0.01)}["lp"]
    assert c["uniform_over_oracle"] == pytest.approx(1.25) and c["goals"]["uniform_over_oracle"]["met"] is None
    runs[2]["relmse"] = 0.0131  # now 1.31x
    lp = {c["method"]: c for c in targets.compare_runs("dof", runs, 0.01)}["lp"]
    assert lp["goals"]["uniform_over_oracle"]["met"] is True
    # adapt + reconstruct = 0.4 s on 0.01 MP = 40 s/MP against OIDN's 50 s/MP
    assert runs[0]["adapt_reconstruct_s_per_mp"] == pytest.approx(40.0)
    assert runs[0]["oidn_cost_ratio"] == pytest.approx(0.8) and runs[0]["goals"]["oidn_cost_ratio"]["met"]
    runs[0]["seconds"]["adapt"] = 0.4  # 60 s/MP: 1.2x OIDN
    targets.compare_runs("dof", runs, 0.01)
    assert runs[0]["oidn_cost_ratio"] == pytest.approx(1.2) and not runs[0]["goals"]["oidn_cost_ratio"]["met"]
    # without an OIDN run (or with a zero denoise time) the cost is not judged
    targets.compare_runs("dof", runs[:-1], 0.01)
    assert runs[0]["oidn_cost_ratio"] is None and runs[0]["goals"]["oidn_cost_ratio"]["met"] is None


def test_targets_follow_the_per_run_goals():
    """A target is met when every method run meets its goal, missed when one
    misses (and names it), not measured without figures; oracle and
    uniform-sampling runs are reported but do not decide the targets."""
    from cycles_adaptive.bench import targets
    base = [_run("lp"), _run("awr"), _run("oracle-lp", kind="oracle"), _run("uniform-lp", kind="uniform_sampling")]
    for key in targets.RUN_GOALS + ("speedup",):
        good, bad = SIDES[key]
        sc = _scene([dict(r, **{key: good}) for r in base])
        t = targets.run_goal_target({"glossy": sc}, key, "t")
        assert t["met"] is True, key
        sc = _scene([dict(r) for r in base])
        for r in sc["runs"]:
            if r["kind"] != "method":
                r[key] = bad
        targets.compare_runs("glossy", sc["runs"], 0.01)
        assert targets.run_goal_target({"glossy": sc}, key, "t")["met"] is True, key
        sc["runs"][1][key] = bad
        targets.compare_runs("glossy", sc["runs"], 0.01)
        t = targets.run_goal_target({"glossy": sc}, key, "t")
        assert t["met"] is False and any("awr" in d and "glossy @ 8" in d for d in t["detail"]), (key, t)
        for r in sc["runs"]:
            r[key] = None
        targets.compare_runs("glossy", sc["runs"], 0.01)
        assert targets.run_goal_target({"glossy": sc}, key, "t")["met"] is None, key


def test_evaluate_targets_on_a_hand_made_session():
    from cycles_adaptive.bench import targets
    runs = [_run("awr", relmse=0.0110), _run("oracle-awr", kind="oracle", relmse=0.010),
            _run("uniform-awr", kind="uniform_sampling", relmse=0.014), _run("uniform", speedup=0.95)]
    res = {"scenes": {"soft_shadows": _scene(runs, "soft_shadows")}, "scaling": None}
    res["scenes"]["soft_shadows"]["runs"][-1]["speedup"] = 0.95
    tg = {t.get("key", t["target"]): t for t in targets.evaluate_targets(res)}
    assert tg["uniform_over_oracle"]["met"] is True            # 1.4x >= 1.3x
    est = next(t for t in tg.values() if t["target"].startswith("estimated maps within 1.15x"))
    assert est["met"] is True                                   # 1.1x <= 1.15x
    assert tg["loop_speed"]["met"] is True                      # 0.95x >= 0.9x at 0.01 MP
    assert tg["oidn_cost_ratio"]["met"] is None                 # no OIDN run
    res["scenes"]["soft_shadows"]["runs"][0]["relmse"] = 0.0120
    res["scenes"]["soft_shadows"]["comparisons"] = targets.compare_runs(
        "soft_shadows", res["scenes"]["soft_shadows"]["runs"], 0.01)
    est = next(t for t in targets.evaluate_targets(res) if t["target"].startswith("estimated maps"))
    assert est["met"] is False                                  # 1.2x > 1.15x
    # the loop's uniform: 0.97x from 0.5 MP
    big = _scene([_run("uniform")], "cornell", 1000, 500)
    big["runs"][0]["speedup"] = 0.96
    assert targets.loop_speed_target({"cornell": big})["met"] is False
    big["runs"][0]["speedup"] = 0.97
    assert targets.loop_speed_target({"cornell": big})["met"] is True
    small = _scene([_run("uniform")], "cornell", 128, 128)
    small["runs"][0]["speedup"] = 0.89
    assert targets.loop_speed_target({"cornell": small})["met"] is False
    assert targets.loop_speed_bound(0.5) == 0.97 and targets.loop_speed_bound(0.49) == 0.9


# ------------------------------------------------------------ per-run figures
def test_block_mean_and_pooled_correlation_closed_forms():
    from cycles_adaptive.bench import targets
    x = np.arange(20.0).reshape(4, 5)
    bm = targets.block_mean(x, 2)
    assert bm.shape == (2, 3)
    assert bm[0, 0] == pytest.approx(np.mean([0, 1, 5, 6])) and bm[1, 2] == pytest.approx(np.mean([14, 19]))
    x[0, 0] = np.nan
    assert targets.block_mean(x, 2)[0, 0] == pytest.approx(np.mean([1, 5, 6]))
    assert np.isnan(targets.block_mean(np.full((3, 3), np.nan), 2)).all()
    # an estimate proportional to the true error tile by tile, noisy inside tiles
    rng = np.random.default_rng(0)
    ref = np.full((32, 32, 3), 0.5)
    amp = np.kron(rng.uniform(0.01, 0.3, (4, 4)), np.ones((8, 8)))
    img = ref + (amp * rng.standard_normal((32, 32)))[..., None]
    true = ((img - ref) ** 2).mean(axis=-1)
    est = np.kron(targets.block_mean(true, 8), np.ones((8, 8))) * 3.0  # exact tile means, scaled
    assert targets.pooled_error_correlation(est, img, ref, 8) == pytest.approx(1.0)
    assert targets.pearson(est, true) < 0.99  # per pixel it is not exact
    assert targets.pearson(np.ones(5), np.arange(5.0)) == 0.0  # no variation
    assert targets.pearson(np.array([np.nan, 1.0]), np.array([1.0, 2.0])) == 0.0  # one finite pair


def test_negative_brightness_and_adaptivity_figures():
    from cycles_adaptive.bench import targets
    ref = np.full((4, 5, 3), 0.2)
    ref[0, 0] = -0.1  # a negative reference pixel: negative output there is not an artefact
    img = ref.copy()
    img[0, 0] = -0.3
    img[1, 1, 2] = -0.05
    img[2, 2] = [np.nan, -1.0, 0.1]  # non-finite channels are left out, the finite -1 counts
    share, low = targets.negative_output(img, ref)
    assert share == pytest.approx(2 / 20) and low == -1.0
    assert targets.negative_output(ref.clip(0), ref.clip(0)) == (0.0, 0.0)
    mean = np.full((4, 5, 3), 0.2)
    assert targets.brightness_percent(mean * 1.01, mean) == pytest.approx(1.0)
    assert targets.brightness_percent(mean * 0.995, mean) == pytest.approx(-0.5)
    assert targets.brightness_percent(mean, np.zeros_like(mean)) is None
    assert targets.brightness_percent(np.full((2, 2, 3), np.nan), mean[:2, :2]) is None
    cv, uni = targets.map_adaptivity(np.full((4, 4), 8.0))
    assert cv == 0.0 and uni == 1.0
    n = np.array([[4.0, 4.0], [4.0, 20.0]])  # mean 8, std sqrt(48)
    cv, uni = targets.map_adaptivity(n)
    assert cv == pytest.approx(np.sqrt(48) / 8) and uni == 0.0
    assert targets.map_adaptivity(np.zeros((2, 2))) == (None, None)


def test_run_figures_are_finite_for_hostile_input():
    from cycles_adaptive.bench import targets
    ref = np.full((8, 8, 3), 0.5)
    img = ref.copy()
    img[0, 0] = np.nan
    img[1, 1] = np.inf
    img[2, 2] = -1e300
    err = np.full((8, 8), 0.01)
    err[3, 3] = np.nan
    f = targets.run_figures(img, err, None, np.full((8, 8), 8.0), ref, ref, overshoot=64, samples_rendered=512)
    assert f["beyond_map_percent"] == pytest.approx(12.5) and f["samples_beyond_map"] == 64
    assert f["guard_fraction"] is None
    for k in ("error_correlation", "error_correlation_block", "negative_share", "negative_min",
              "brightness_percent", "map_cv", "map_uniform_share"):
        assert f[k] is not None and np.isfinite(f[k]), k
    assert f["negative_min"] == -1e300
    f = targets.run_figures(img, err, 0.02, np.zeros((8, 8)), ref, ref, 0, 0)
    assert f["beyond_map_percent"] is None and f["map_cv"] is None and f["guard_fraction"] == 0.02
    assert f["error_calibration"] is not None and np.isfinite(f["error_calibration"])
    # an exact image: no true error, no calibration
    assert targets.run_figures(ref, err, None, np.ones((8, 8)), ref, ref, 0, 1)["error_calibration"] is None


def test_error_calibration_is_estimated_over_true_relmse():
    """An error map equal to the realised squared error of a smooth offset is
    calibrated (1); twice it reads 2 (robust_relmse is the plain mean here)."""
    from cycles_adaptive.bench import targets
    ref = np.full((16, 16, 3), 0.5)
    img = ref + 0.01 * np.linspace(1.0, 2.0, 256).reshape(16, 16, 1)
    true_sq = ((img - ref) ** 2).mean(-1)
    # the estimate divides by the image, the truth by the reference: compare with the same denominator
    err = true_sq * (img[..., 0] ** 2 + 0.01) / (ref[..., 0] ** 2 + 0.01)
    f = targets.run_figures(img, err, None, np.ones((16, 16)), ref, ref, 0, 1)
    assert f["error_calibration"] == pytest.approx(1.0, rel=1e-9)
    f2 = targets.run_figures(img, 2 * err, None, np.ones((16, 16)), ref, ref, 0, 1)
    assert f2["error_calibration"] == pytest.approx(2.0, rel=1e-9)


def test_a_goal_added_later_gets_its_verdict_target_and_column(monkeypatch):
    """One more per-run figure (the calibration ratio, a range goal): one
    GOALS entry and its key in RUN_GOALS give the runs' verdicts, a target
    and a column of the estimates table."""
    from cycles_adaptive.bench import report, targets
    monkeypatch.setitem(targets.GOALS, "calibration_ratio", ("in", (0.8, 1.25), "variance calibration"))
    monkeypatch.setattr(targets, "RUN_GOALS", targets.RUN_GOALS + ("calibration_ratio",))
    for v, want in ((0.8, True), (1.25, True), (0.79, False), (1.26, False), (None, None)):
        assert targets.met("calibration_ratio", v) is want, v
    sc = _scene([_run("lp", calibration_ratio=1.0), _run("awr", calibration_ratio=1.3)])
    assert sc["runs"][1]["goals"]["calibration_ratio"] == {"value": 1.3, "met": False}
    t = next(t for t in targets.evaluate_targets({"scenes": {"glossy": sc}}) if t.get("key") == "calibration_ratio")
    assert t["met"] is False and "awr" in t["detail"][1]
    md = "\n".join(report.estimates_section(sc))
    assert "calibration_ratio (in (0.8, 1.25)) |" in md and "1.3 **missed** |" in md and "1 met |" in md


# ------------------------------------------------- reference noise floor (two halves)
def test_halves_floor_closed_form_and_simulation():
    """floor = relMSE(A, B) x n_a n_b / N^2: exact for a constant difference;
    on Gaussian halves of known variance it matches Var(full) / (r^2 + 0.01)
    and the relMSE of the full mean against the truth (core.metrics.relmse)."""
    from cycles_adaptive.bench import references as refs
    from cycles_adaptive.core import metrics
    r = np.full((8, 8, 3), 0.5)
    d = 0.2
    assert refs.halves_floor(r + d / 2, r - d / 2, full=r) == pytest.approx(d * d / (0.25 + 0.01) / 4)
    # unequal halves: weight n_a n_b / N^2 (3 and 1 samples: 3/16)
    assert refs.halves_floor(r + d, r, 3, 1, full=r) == pytest.approx(d * d / 0.26 * 3 / 16)
    rng = np.random.default_rng(7)
    truth = rng.uniform(0.05, 2.0, (384, 384, 3))
    for n_a, n_b in ((1, 1), (3, 1)):
        s2 = 0.01  # per-sample variance; half h has s2 / n_h
        a = truth + rng.normal(0, np.sqrt(s2 / n_a), truth.shape)
        b = truth + rng.normal(0, np.sqrt(s2 / n_b), truth.shape)
        full = (n_a * a + n_b * b) / (n_a + n_b)
        expect = float((s2 / (n_a + n_b) / (truth ** 2 + metrics.REL_EPS)).mean())
        got = refs.halves_floor(a, b, n_a, n_b, full=truth)
        assert got == pytest.approx(expect, rel=0.02)
        assert got == pytest.approx(metrics.relmse(full, truth), rel=0.03)
    # the default denominator (the noisy full mean, as the scoring uses) is close at low noise
    s2 = 1e-4
    a, b = (truth + rng.normal(0, np.sqrt(s2), truth.shape) for _ in range(2))
    expect = float((s2 / 2 / (truth ** 2 + metrics.REL_EPS)).mean())
    assert refs.halves_floor(a, b) == pytest.approx(expect, rel=0.03)
    with pytest.raises(ValueError):
        refs.halves_floor(r, r[:4])


class _FakeRenderer:
    """A renderer of known noise: sample i of half h is truth + N(0, s2), fixed
    per (half, i) (drawn once, up to ``most`` samples a half), so a half is one
    sample sequence however it is split into tasks."""

    def __init__(self, truth, s2, most=2048):
        self.truth, self.calls = truth, []
        rng = np.random.default_rng(11)
        self.noise = [rng.normal(0.0, np.sqrt(s2), (most,) + truth.shape).astype(np.float32)
                      for _ in range(2)]

    def __call__(self, half, task):
        self.calls.append((half, task.offset, task.samples))
        h, w = self.truth.shape[:2]
        part = self.noise[half][task.offset:task.offset + task.samples]
        assert len(part) == task.samples, "asked past the fake's samples"
        rgb = self.truth + part.astype(np.float64).mean(axis=0)
        return np.concatenate([rgb, np.ones((h, w, 1))], axis=-1), {}


def test_converge_halves_stops_at_the_first_spp_below_the_floor():
    """With per-sample variance s2 and truth 1, the floor at N spp is about
    s2 / (N (1 + 0.01)); the loop doubles from 1024 and stops at the first N
    below the target (placed at 0.7x of the 4096-spp floor: stops at 4096),
    each half continuing its own sample sequence without gaps or overlaps."""
    from cycles_adaptive.bench import references as refs
    truth = np.ones((24, 24, 3))
    s2 = 4.0
    floor_at = lambda n: s2 / n / 1.01
    fake = _FakeRenderer(truth, s2)
    res = refs.converge_halves(fake, truth.shape[:2], 1024, floor=floor_at(4096) / 0.7, max_spp=16384)
    assert [n for n, _ in res["history"]] == [1024, 2048, 4096]
    assert res["counts"] == (2048, 2048)
    for (n, f) in res["history"]:
        assert f == pytest.approx(floor_at(n), rel=0.15)
    for half in (0, 1):
        spans = sorted((o, o + k) for h, o, k in fake.calls if h == half)
        assert spans[0][0] == 0 and spans[-1][1] == 2048
        assert all(a[1] == b[0] for a, b in zip(spans, spans[1:]))  # contiguous, no overlap
    # merged exactly by sample count: the full mean is the mean of both halves' samples
    a, _ = fake(0, type("T", (), {"offset": 0, "samples": 2048})())
    b, _ = fake(1, type("T", (), {"offset": 0, "samples": 2048})())
    assert np.allclose(res["full"].color.mean, (a[..., :3] + b[..., :3]) / 2, atol=1e-9)
    assert np.allclose(res["full"].n, 4096)
    # the cap: a floor never reached stops at max_spp, the last step clamped to it
    fake = _FakeRenderer(truth, s2)
    res = refs.converge_halves(fake, truth.shape[:2], 1024, floor=1e-12, max_spp=3000)
    assert res["floor"] == pytest.approx(floor_at(3000), rel=0.15)
    assert [n for n, _ in res["history"]] == [1024, 2048, 3000] and res["counts"] == (1500, 1500)
    # no floor: exactly the spp asked for (odd: one more sample in half A)
    res = refs.converge_halves(_FakeRenderer(truth, s2), truth.shape[:2], 1025)
    assert res["counts"] == (513, 512) and len(res["history"]) == 1
    assert refs.next_half_spp(512, 16384) == 1024 and refs.next_half_spp(8192, 16384) == 8192


def _write_reference(tmp_path, blend, spp, record):
    """A reference EXR + sidecar in tmp_path as references.py names them."""
    from cycles_adaptive.bench import references as refs
    from cycles_adaptive.core import io as imageio
    path = refs.reference_path(str(blend), 1, 100, spp, str(tmp_path))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    rgb = np.full((4, 4, 4), 0.5, np.float32)
    imageio.write_layers(path, {"Combined": rgb})
    imageio.write_text(refs.sidecar_path(path), json.dumps(record))
    return path


def test_old_sidecars_still_load_and_floor_requests_pick_converged_ones(tmp_path):
    """A version-1 sidecar (one seed, no halves floor) still serves a fixed-spp
    request and loads; a floor request skips it and takes a version-2 reference
    whose halves floor is below the target, or one at the cap."""
    from cycles_adaptive.bench import references as refs
    from cycles_adaptive.bench import report
    blend = tmp_path / "x.blend"
    blend.write_bytes(b"a scene")
    old = refs.wanted_record(str(blend), 1, 100, 1024, refs.REFERENCE_SEED)
    old.update(version=1, noise_relmse=1e-4)
    p_old = _write_reference(tmp_path, blend, 1024, old)
    want = refs.wanted_record(str(blend), 1, 100, 1024, refs.REFERENCE_SEED)
    assert want["version"] == 2 and refs.mismatch(old, want) == []
    assert refs.ensure_reference(str(blend), 1, 100, 1024, directory=str(tmp_path),
                                 render_missing=False) == p_old
    rgb, rec = refs.load_checked_reference(p_old, (4, 4))
    assert rgb.shape == (4, 4, 3) and rec["version"] == 1
    assert refs.mismatch({**old, "version": 3}, want) == ["version"]
    # a floor request: the old one has no halves floor
    assert refs.find_floor_reference(str(blend), 1, 100, refs.REFERENCE_SEED, 1e-3, 16384,
                                     str(tmp_path)) is None
    with pytest.raises(refs.ReferenceFileError, match="--floor"):
        refs.ensure_reference(str(blend), 1, 100, 1024, directory=str(tmp_path), render_missing=False,
                              floor=1e-3)
    new = refs.wanted_record(str(blend), 1, 100, 4096, refs.REFERENCE_SEED)
    new.update(noise_relmse_halves=5e-4)
    p_new = _write_reference(tmp_path, blend, 4096, new)
    find = lambda f, cap: refs.find_floor_reference(str(blend), 1, 100, refs.REFERENCE_SEED, f, cap,
                                                     str(tmp_path))
    assert find(1e-3, 16384) == p_new      # 5e-4 < 1e-3
    assert find(1e-4, 16384) is None       # above the target, below the cap
    assert find(1e-4, 4096) == p_new       # at the cap
    assert refs.ensure_reference(str(blend), 1, 100, 1024, directory=str(tmp_path), render_missing=False,
                                 floor=1e-3) == p_new
    # the report: an old reference is not judged, a converged one is, a noisy one warns
    scene = lambda path, errs: {"status": "ok", "reference": {"path": path, "spp": None},
                                "runs": [{"status": "ok", "relmse": e} for e in errs],
                                "uniform_curve": [{"relmse": 1e-2}]}
    assert report.reference_check(scene(p_old, [3e-3]))["below"] is None
    c = report.reference_check(scene(p_new, [6e-3, 5.1e-3]))
    assert c["below"] is True and c["bound"] == pytest.approx(5.1e-4) and c["spp"] == 4096
    assert report.reference_check(scene(p_new, [4.9e-3]))["below"] is False
    md = "\n".join(report.references_section({"scenes": {"x": scene(p_new, [4.9e-3])}}))
    assert "| x | 4096 | 5.00e-04 |" in md and "Warning (x)" in md and "NOT below" in md
    # a converged reference from another Blender version is refused by name, not silently re-rendered
    other = tmp_path / "other"
    _write_reference(other, blend, 8192, {**new, "spp": 8192, "blender": "3.6.0"})
    with pytest.raises(refs.ReferenceFileError, match="3.6.0"):
        refs.ensure_reference(str(blend), 1, 100, 1024, directory=str(other), floor=1e-3)


def test_auto_and_oidn_targets_on_hand_made_runs():
    """auto is judged against the best other run of its scene and budget
    (0.95x) and plain Cycles (1.0x); oidn against uniform + OIDN (1.3x lower
    relMSE, geometric mean) and Cycles' OIDN (1.2x the speed-up, never < 1)."""
    from cycles_adaptive.bench import targets
    runs = [_run("auto", speedup=3.0, chosen="oidn-uniform"), _run("lp", speedup=2.0),
            _run("oidn", relmse=0.006, speedup=3.7), _run("uniform-oidn", kind="uniform_sampling", relmse=0.009),
            dict(_run("cycles_oidn", kind="peer", speedup=3.1), method="oidn")]
    sc = {"cornell": _scene(runs, "cornell")}
    for r, v in zip(sc["cornell"]["runs"], (3.0, 2.0, 3.7, None, 3.1)):
        r["speedup"] = v
    a_best, a_plain, o_uni, o_peer = targets.auto_targets(sc) + targets.oidn_targets(sc)
    assert a_best["met"] is False and "best oidn 3.70x: 0.81 of it" in a_best["detail"][0]
    assert a_plain["met"] is True
    assert o_uni["met"] is True and "1.50x" in o_uni["detail"][0]          # 0.009 / 0.006
    assert o_peer["met"] is False and "1.19x" in o_peer["detail"][0]       # 3.7 / 3.1 < 1.2
    sc["cornell"]["runs"][0]["speedup"] = 3.6                              # 0.97x of the best
    assert targets.auto_targets(sc)[0]["met"] is True
    sc["cornell"]["runs"][0]["speedup"] = 0.9
    assert targets.auto_targets(sc)[1]["met"] is False
    assert targets.auto_targets({"cornell": _scene([_run("lp")], "cornell")})[0]["met"] is None



def test_auto_and_oidn_targets_without_runs_say_so():
    from cycles_adaptive.bench import targets
    for t in targets.auto_targets({}) + targets.oidn_targets({}):
        assert t["met"] is None and t["detail"] and t["detail"][0].startswith("no ")


def test_the_runs_safety_cap_stops_like_a_cancel_and_keeps_the_samples(monkeypatch):
    """--run-max-seconds closes the run between two steps (nothing planned
    from timings): the samples merged so far stay, and without the cap the
    run is the plain one."""
    import types
    from cycles_adaptive.bench import session
    from cycles_adaptive.core import pipeline
    from cycles_adaptive.core.pipeline import AdaptiveRun, Options

    class Executor:  # each render moves the fake clock by 1 s
        size = (8, 12)

        def __init__(self, clock):
            self.clock, self.tasks = clock, []

        def render(self, task):
            self.clock[0] += 1.0
            self.tasks.append(task)
            h, w = task.y1 - task.y0, task.x1 - task.x0
            guides = {"albedo": np.full((h, w, 3), 0.5), "normal": np.full((h, w, 3), 0.5),
                      "depth": np.ones((h, w, 1))}   # var's PASSES
            return np.full((h, w, 4), 0.5), guides

    clock = [0.0]
    fake = types.SimpleNamespace(perf_counter=lambda: clock[0])
    monkeypatch.setattr(session, "time", fake)
    monkeypatch.setattr(pipeline, "time", fake)
    opts = dict(method="var", spp=64, initial_spp=4, subsets=4, task_cost=0, min_task_size=4)
    ex = Executor(clock)
    run = AdaptiveRun(ex, Options(**opts))
    assert session._run_capped(run, 5.5) is True
    assert len(ex.tasks) == 6 and run.tasks_rendered == 6 and not run.time_limited
    assert run.buffers.n.sum() == sum(t.pixels * t.samples for t in ex.tasks)
    ex2 = Executor(clock)
    full = AdaptiveRun(ex2, Options(**opts))
    assert session._run_capped(full, 0.0) is False
    assert abs(full.samples_rendered - 64 * 96) <= 0.01 * 64 * 96 + 1


def test_plain_cycles_renders_each_count_as_a_fresh_render(tmp_path):
    """The plain-Cycles peer renders every sample count with its own
    blue-noise table: 4 spp after 16 spp in one session equals a 4-spp render
    of a fresh session (with persistent data it was the first 4 samples of
    the 16-spp sequence)."""
    from blend_util import save_scene
    from cycles_adaptive.bench.peers import PlainCycles
    path = tmp_path / "s.blend"
    save_scene(path, width=24, height=16)
    bpy.ops.wm.open_mainfile(filepath=str(path))
    scene = bpy.context.scene
    try:
        scene.cycles.sampling_pattern = "BLUE_NOISE"
    except TypeError:
        pytest.skip("this Blender has no blue-noise pattern")
    vl = scene.view_layers[0]
    with PlainCycles(scene, vl, 0, "BLUE_NOISE") as pc:
        fresh = pc.render(4)["rgb"]
    with PlainCycles(scene, vl, 0, "BLUE_NOISE") as pc:
        sixteen = pc.render(16)["rgb"]
        after = pc.render(4)["rgb"]
    np.testing.assert_array_equal(after, fresh)
    assert not np.array_equal(sixteen, fresh)

"""The sequence benchmark (bench/sequence.py): the temporal error against a
direct loop and closed forms, hostile input, and one tiny end-to-end run."""
import argparse
import os

import numpy as np
import pytest

from cycles_adaptive.bench import sequence as seq

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ANIMATED = os.path.join(ROOT, "sample_blends", "animated.blend")


def _loop_temporal_error(frames, refs):
    """The definition written out term by term (an independent implementation)."""
    total, count = 0.0, 0
    for t in range(1, len(frames)):
        h, w = frames[t].shape[:2]
        for y in range(h):
            for x in range(w):
                for c in range(3):
                    d = (frames[t][y, x, c] - frames[t - 1][y, x, c]) - (refs[t][y, x, c] - refs[t - 1][y, x, c])
                    total += d * d / (refs[t][y, x, c] ** 2 + 0.01)
                    count += 1
    return total / count


def _sequence(rng, t=5, h=6, w=7, c=3):
    refs = [rng.uniform(0.0, 2.0, (h, w, c)) for _ in range(t)]
    frames = [r + rng.normal(0.0, 0.3, r.shape) for r in refs]
    return frames, refs


def test_matches_direct_loop():
    rng = np.random.default_rng(1)
    frames, refs = _sequence(rng)
    assert seq.temporal_error(frames, refs) == pytest.approx(_loop_temporal_error(frames, refs), rel=1e-12)


def test_trimmed_temporal_error_leaves_out_the_runs_worst_pixels():
    """The trimmed figure is the direct loop over every pixel but the run's
    own worst ``share`` (here one pixel of a huge flicker): far below the full
    figure, and near the trimmed figure of the same frames without it."""
    rng = np.random.default_rng(21)
    frames, refs = _sequence(rng, t=4, h=10, w=10)
    plain = seq.trimmed_temporal_error(frames, refs, share=0.01)
    frames[2][3, 7] += 50.0
    got = seq.trimmed_temporal_error(frames, refs, share=0.01)
    keep = [np.delete(f.reshape(-1, 3), 37, axis=0)[None] for f in frames]
    keep_r = [np.delete(r.reshape(-1, 3), 37, axis=0)[None] for r in refs]
    assert got == pytest.approx(_loop_temporal_error(keep, keep_r), rel=1e-12)
    assert got < 0.1 * seq.temporal_error(frames, refs)
    assert got == pytest.approx(plain, rel=0.15)
    assert seq.sequence_figures(frames, refs)["temporal_error_trimmed"] == got
    assert seq.sequence_figures(frames[:1], refs[:1])["temporal_error_trimmed"] is None


def test_extra_channels_are_ignored():
    rng = np.random.default_rng(2)
    frames, refs = _sequence(rng, c=4)
    a = seq.temporal_error(frames, refs)
    b = seq.temporal_error([f[..., :3] for f in frames], [r[..., :3] for r in refs])
    assert a == b


def test_static_correct_sequence_is_zero():
    r = np.random.default_rng(3).uniform(0, 1, (4, 5, 3))
    assert seq.temporal_error([r] * 6, [r] * 6) == 0.0


def test_moving_correct_sequence_is_zero():
    rng = np.random.default_rng(4)
    refs = [rng.uniform(0, 3, (4, 5, 3)) for _ in range(5)]
    assert seq.temporal_error(refs, refs) == 0.0


def test_constant_offset_is_zero_but_relmse_is_not():
    rng = np.random.default_rng(5)
    refs = [rng.uniform(0, 3, (4, 5, 3)) for _ in range(5)]
    frames = [r + 0.25 for r in refs]
    assert seq.temporal_error(frames, refs) == pytest.approx(0.0, abs=1e-25)
    assert min(seq.frame_relmse(frames, refs)) > 0.0


@pytest.mark.parametrize("d,r", [(0.1, 0.5), (0.02, 2.0), (1.0, 0.0)])
def test_alternating_flicker_closed_form(d, r):
    # x_t = r + (-1)^t d: every frame difference is off by 2d -> TE = 4 d^2 / (r^2 + 0.01)
    ref = np.full((3, 4, 3), r)
    frames = [ref + (d if t % 2 else -d) for t in range(7)]
    assert seq.temporal_error(frames, [ref] * 7) == pytest.approx(4 * d * d / (r * r + 0.01), rel=1e-12)
    # and every frame's relMSE is d^2 / (r^2 + 0.01)
    assert seq.frame_relmse(frames, [ref] * 7) == pytest.approx([d * d / (r * r + 0.01)] * 7, rel=1e-12)


def test_more_noise_more_flicker():
    rng = np.random.default_rng(6)
    refs = [rng.uniform(0, 1, (16, 16, 3)) for _ in range(6)]
    errs = [seq.temporal_error([r + rng.normal(0, s, r.shape) for r in refs], refs) for s in (0.01, 0.1, 1.0)]
    assert errs[0] < errs[1] < errs[2]


def test_hostile_input_is_finite_and_counted():
    ref = np.full((2, 2, 3), 0.5)
    bad = ref.copy()
    bad[0, 0, 0] = np.nan
    huge = ref.copy()
    huge[1, 1, 1] = 1e300
    for frames in ([ref, bad, ref], [ref, huge, ref], [ref, np.full_like(ref, np.inf), ref]):
        te = seq.temporal_error(frames, [ref] * 3)
        assert np.isfinite(te) and te > 0.0
    zeros = np.zeros((2, 2, 3))
    assert seq.temporal_error([zeros] * 3, [zeros] * 3) == 0.0


def test_bad_shapes_and_lengths():
    a = np.zeros((2, 2, 3))
    with pytest.raises(ValueError):
        seq.temporal_error([a], [a])
    with pytest.raises(ValueError):
        seq.temporal_error([a, a], [a])
    with pytest.raises(ValueError):
        seq.temporal_error([a, np.zeros((3, 2, 3))], [a, a])
    assert seq.sequence_figures([a], [a])["temporal_error"] is None


def test_reference_floor_closed_form():
    r = np.full((2, 3, 3), 1.0)
    v = np.full((2, 3, 3), 0.02)
    f = seq.reference_floor([r, r, r], [v, v, v])
    assert f["relmse"] == pytest.approx(0.02 / 1.01)
    assert f["temporal_error"] == pytest.approx(0.04 / 1.01)


def test_reference_floor_matches_simulation():
    # E[TE] of a perfect sequence against noisy references = (v_t + v_{t-1}) / (r^2 + 0.01), to
    # first order in the noise (the noisy denominator adds O(v / r^2): small noise here)
    rng = np.random.default_rng(7)
    truth = [np.full((64, 64, 3), 0.7)] * 4
    v = 1e-4
    noisy = [t + rng.normal(0, np.sqrt(v), t.shape) for t in truth]
    te = seq.temporal_error(truth, noisy)
    floor = seq.reference_floor(truth, [np.full_like(truth[0], v)] * 4)["temporal_error"]
    assert te == pytest.approx(floor, rel=0.05)


def test_configurations_lp_only_with_lp_and_reproject_only_animated():
    got = [c[:3] for c in seq.configurations(["uniform", "lp"], ["none", "reproject", "lp"])]
    assert ("uniform", "lp", "animated") not in got and ("lp", "lp", "animated") in got and len(got) == 5
    both = [c[:3] for c in seq.configurations(["uniform", "lp"], ["none", "reproject", "lp"], ["animated", "fixed"])]
    assert len(both) == 5 + 3 and ("lp", "reproject", "fixed") not in both and ("lp", "lp", "fixed") in both


def test_history_variants_apply_to_blend_only_and_typos_fail_early():
    """``--history``: each variant is one more blend run (named by its
    settings); the other modes run once; an unknown key or a value out of
    range is refused before any render."""
    variants = seq.parse_history_variants("input_frames=1;max_frames=2,z=2.5;")
    assert variants == [{"input_frames": 1}, {"max_frames": 2, "z": 2.5}, {}]
    got = seq.configurations(["oidn"], ["none", "blend"], ["animated"], variants)
    assert got == [("oidn", "none", "animated", {})] + [("oidn", "blend", "animated", v) for v in variants]
    assert seq.history_label({"max_frames": 2, "z": 2.5}) == "[max_frames=2,z=2.5]"
    assert seq.history_label({}) == "" and seq.parse_history_variants("") == [{}]
    with pytest.raises(seq.SequenceError, match="unknown setting"):
        seq.parse_history_variants("max_frame=2")
    with pytest.raises(seq.SequenceError, match="z"):
        seq.parse_history_variants("z=-1")
    with pytest.raises(seq.SequenceError, match="key=value"):
        seq.parse_history_variants("input_frames")


def test_method_specs_carry_parameters_and_typos_fail_early():
    """``--methods 'oidn,oidn[adaptive=False,error_estimate=False]'``: a
    method with its Params, split outside the brackets; unknown methods,
    keys and values out of range are refused before any render."""
    specs = seq.split_top_level("oidn, oidn[adaptive=False,error_estimate=False],lp")
    assert specs == ["oidn", "oidn[adaptive=False,error_estimate=False]", "lp"]
    assert seq.parse_method_spec(specs[1]) == ("oidn", {"adaptive": False, "error_estimate": False})
    from core import methods, oidn
    assert methods.method_for("oidn", seq.parse_method_spec(specs[1])[1]) is oidn.UNIFORM
    assert seq.parse_method_spec("lp") == ("lp", {})
    assert seq.parse_method_spec("var[max_spp=16]") == ("var", {"max_spp": 16})
    got = seq.configurations(["lp[rank_max=4]", "uniform"], ["none", "lp"])
    assert [c[:2] for c in got] == [("lp[rank_max=4]", "none"), ("lp[rank_max=4]", "lp"), ("uniform", "none")]
    with pytest.raises(seq.SequenceError, match="unknown method"):
        seq.parse_method_spec("oidnn")
    with pytest.raises(seq.SequenceError, match="unknown setting"):
        seq.parse_method_spec("oidn[adaptiv=False]")
    with pytest.raises(seq.SequenceError, match="min_spp"):
        seq.parse_method_spec("var[min_spp=0]")
    with pytest.raises(seq.SequenceError, match=r"\[key=value"):
        seq.parse_method_spec("var[min_spp=2")


def test_parse_frame_range():
    assert seq.parse_frame_range("1-3,5") == [1, 2, 3, 5]
    assert seq.parse_frame_range(None) is None
    with pytest.raises(ValueError):
        seq.parse_frame_range("a-b")


# ----------------------------------------------------------------- end to end
@pytest.mark.skipif(not os.path.isfile(ANIMATED), reason="sample_blends/animated.blend not built")
def test_tiny_end_to_end(tmp_path):
    pytest.importorskip("bpy")
    p = argparse.ArgumentParser()
    seq.add_arguments(p)
    args = p.parse_args(["--scenes", "animated", "--methods", "uniform", "--temporal", "none",
                         "--budgets", "2", "--frames", "1-3", "--resolution-percentage", "25",
                         "--reference-spp", "2", "--reference-dir", str(tmp_path / "refs"),
                         "--out", str(tmp_path / "out"), "--max-samples-factor", "2",
                         "--seed-modes", "animated,fixed"])
    cfg = seq.resolve_config(args)
    assert "--seed-modes animated,fixed" in seq.command_of(cfg)
    res = seq.run(cfg, seq.command_of(cfg), keep_images=True)
    d = res["scenes"]["animated"]
    assert d["status"] == "ok" and d["frames"] == [1, 2, 3]
    assert (d["width"], d["height"]) == (32, 24)
    runs = {r["name"]: r for r in d["runs"]}
    names = {"uniform", "cycles_uniform", "cycles_oidn", "cycles_adaptive+oidn"}
    assert set(runs) == names | {f"{n} (fixed seed)" for n in names}
    for r in runs.values():
        assert r["status"] == "ok", r
        assert len(r["relmse_per_frame"]) == 3
        for v in r["relmse_per_frame"] + [r["relmse_mean"], r["temporal_error"], r["seconds"]]:
            assert v is not None and np.isfinite(v) and v >= 0.0
    assert d["reference"]["noise_relmse"] > 0.0 and d["reference"]["noise_temporal_error"] > 0.0
    ours = d["images"]["uniform@2"]
    assert len(ours) == 3 and all(np.isfinite(x).all() for x in ours)
    assert seq.temporal_error(ours, ours) == 0.0
    # the frames differ (the camera moves), so a sequence is not its own neighbour
    assert seq.temporal_error(ours, [ours[0]] * 3) > 0.0
    paths = seq.write_outputs(res, str(tmp_path / "out"))
    text = open(paths["markdown"]).read()
    assert "temporal error" in text and "bench-sequence" in text and "cycles_adaptive+oidn" in text

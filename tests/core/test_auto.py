"""Method ``auto``: the cross-validated error between sample halves, the
predicted gain of adaptive sampling, the measured-cost cache, and the choice
through the loop (sample mean on a noiseless image, a denoiser on a noisy one)."""
import json

import numpy as np
import pytest

from core import auto
from core.metrics import REL_EPS
from core.pipeline import AdaptiveRun, Options
from conftest import FakeExecutor

PASSES = ("albedo", "normal", "depth")


@pytest.fixture(autouse=True)
def _cost_cache(tmp_path, monkeypatch):
    """Costs measured into a temporary cache; the measurement itself is
    replaced by fixed figures (its fit is tested on its own below)."""
    monkeypatch.setenv("CYCLES_ADAPTIVE_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(auto, "measure_cost", lambda name: {"fixed": 1e-3, "per_pixel": 1e-7})


def _scene(h, w):
    yy, xx = np.mgrid[0:h, 0:w]
    truth = np.full((h, w, 3), 0.3)
    truth[:, w // 2:] = 1.2
    truth[h // 3: h // 2, 4: w // 3] = 4.0
    feats = {"albedo": np.where(truth > 1.0, 0.8, 0.3),
             "normal": np.dstack([np.zeros((h, w)), np.zeros((h, w)), np.ones((h, w))]),
             "depth": (2.0 + 0.01 * xx)[..., None]}
    return truth, feats


class NoiselessExecutor(FakeExecutor):
    """Every sample equals the truth: any reconstruction can only lose."""

    def render(self, task):
        self.tasks.append(task)
        sl = (slice(task.y0, task.y1), slice(task.x0, task.x1))
        rgb = self.truth[sl]
        return (np.concatenate([rgb, np.ones(rgb.shape[:2] + (1,))], axis=-1),
                {k: v[sl] for k, v in self.features.items()})


def _run(executor, **kw):
    run = AdaptiveRun(executor, Options(method="auto", **kw))
    for _ in run.steps():
        pass
    return run


def test_a_noiseless_image_keeps_the_sample_mean():
    truth, feats = _scene(40, 48)
    run = _run(NoiselessExecutor(truth, feats), spp=8, params={"candidates": "mean,lp,awr"})
    assert run.selection["chosen"] == "uniform"
    assert run.method.NAME == "uniform"
    np.testing.assert_allclose(run.reconstruct().image, truth, atol=1e-12)


def test_a_noisy_smooth_image_gets_a_denoiser():
    truth, feats = _scene(40, 48)
    run = _run(FakeExecutor(truth, feats), spp=8, params={"candidates": "mean,lp,awr"})
    rows = {r["name"]: r for r in run.selection["candidates"]}
    assert run.selection["chosen"] in ("uniform-lp", "lp", "uniform-awr", "awr")
    assert rows[run.selection["chosen"]]["relmse"] < 0.5 * rows["uniform"]["relmse"]
    img = run.reconstruct().image
    err = lambda x: float(((x - truth) ** 2 / (truth ** 2 + REL_EPS)).mean())
    assert err(img) < err(run.buffers.color.mean)
    assert run.samples_rendered == 8 * 40 * 48


def test_every_candidate_is_reported_with_its_prediction():
    truth, feats = _scene(24, 24)
    run = _run(FakeExecutor(truth, feats), spp=6, params={"candidates": "mean,awr"})
    names = {r["name"] for r in run.selection["candidates"]}
    assert names == {"uniform", "var", "uniform-awr", "awr"}
    for r in run.selection["candidates"]:
        assert r["relmse"] > 0 and r["seconds"] > 0 and np.isfinite(r["speedup"])
    speed = [r["speedup"] for r in run.selection["candidates"]]
    assert speed == sorted(speed, reverse=True)
    assert run.selection["chosen"] == run.selection["candidates"][0]["name"]
    json.dumps(run.selection)


def _gamma_subsets(truth, feats, seed, k=0.7):
    """Four one-sample subsets of unbiased, non-negative noise (Gamma with
    mean 1, variance 1/k, multiplied by the truth)."""
    rng = np.random.default_rng(seed)
    return [(truth * rng.gamma(k, 1.0 / k, truth.shape), feats, 1) for _ in range(4)]


def test_cross_validated_error_matches_the_true_error_of_the_halves():
    """The half-budget estimate of every candidate against its true relMSE on
    the halves (known truth), averaged over seeds: within a factor 2 (the
    control variate's common offset, module notes; the sample mean's within
    20 %)."""
    truth, feats = _scene(48, 48)
    names = ["mean", "lp", "awr"]
    est = {n: [] for n in names}
    true = {n: [] for n in names}
    w = 1.0 / (truth ** 2 + REL_EPS)
    for seed in range(3):
        subs = _gamma_subsets(truth, feats, seed)
        sc = auto.score_tile(subs, (0, 0, 48, 48), 48, 48, names)
        halves = auto._halves(subs, list(feats))
        for n in names:
            est[n].append(sc[n]["terms"].mean())
            imgs = [b.color.mean if n == "mean" else auto._image(auto._reconstruct(n, b)) for b in halves]
            true[n].append(np.mean([(w * (x - truth) ** 2).mean() for x in imgs]))
    for n in names:
        ratio = np.mean(est[n]) / np.mean(true[n])
        lo, hi = (0.8, 1.25) if n == "mean" else (0.5, 2.0)
        assert lo < ratio < hi, (n, ratio)


def test_control_variate_lowers_the_spread_of_the_estimate():
    """The estimate's spread over noise realisations is lower with the
    control variate than the plain difference ``d_R - d_mean / 2``."""
    truth, feats = _scene(40, 40)
    with_cv, without = [], []
    for seed in range(4):
        subs = _gamma_subsets(truth, feats, 10 + seed)
        sc = auto.score_tile(subs, (0, 0, 40, 40), 40, 40, ["mean", "lp"])
        halves = auto._halves(subs, list(feats))
        ia, ib = (auto._image(auto._reconstruct("lp", b)) for b in halves)
        ca, cb = halves[0].color.mean, halves[1].color.mean
        from core.filters import box_mean
        whole = sum(s[0] for s in subs) / 4.0
        w = 1.0 / (box_mean(np.clip(whole, 0, None), 1) ** 2 + REL_EPS)
        plain = w * ((ia - cb) ** 2 + (ib - ca) ** 2) / 2.0 - w * (ca - cb) ** 2 / 2.0
        with_cv.append(sc["lp"]["terms"].mean())
        without.append(plain.mean())
    assert np.std(with_cv) < np.std(without)


def test_adaptive_gain_is_one_on_a_flat_map_and_the_closed_form_on_two_blocks():
    g, extra = auto.adaptive_allocation(np.ones((16, 16)), 4, 16, 1.0, 0.0, 8)
    assert g == pytest.approx(1.0)
    np.testing.assert_allclose(extra, 12.0)
    # two halves, a = 1 and 9, p = 1, no cap: m ~ sqrt(a) -> 6 and 18 (mean 12)
    v = np.ones((8, 16))
    v[:, 8:] = 9.0
    g, extra = auto.adaptive_allocation(v, 4, 16, 1.0, 0.0, 8)
    np.testing.assert_allclose(extra[:, :8], 6.0, rtol=1e-9)
    np.testing.assert_allclose(extra[:, 8:], 18.0, rtol=1e-9)
    closed = (1 + 9) / 16 / (1 / 10 + 9 / 22)
    assert g == pytest.approx(closed, rel=1e-9)
    # a cap of 1.25x the mean binds: 15 and 9
    g_cap, extra = auto.adaptive_allocation(v, 4, 16, 1.0, 1.25, 8)
    np.testing.assert_allclose(extra[:, 8:], 15.0, rtol=1e-9)
    np.testing.assert_allclose(extra[:, :8], 9.0, rtol=1e-9)
    assert 1.0 < g_cap < g


def test_nothing_left_to_adapt_gives_no_gain():
    g, extra = auto.adaptive_allocation(np.random.default_rng(0).random((8, 8)), 16, 16, 1.0, 2.0, 4)
    assert g == 1.0 and not extra.any()


def test_cost_fit_recovers_a_linear_cost(monkeypatch):
    """measure_cost's fit on a fake reconstruction whose seconds are
    ``0.2 + 3e-6 * pixels`` (a fake clock)."""
    monkeypatch.undo()  # the real measure_cost
    clock = [0.0]
    monkeypatch.setattr(auto.time, "perf_counter", lambda: clock[0])

    def fake(name, buf):
        clock[0] += 0.2 + 3e-6 * buf.n.size
    monkeypatch.setattr(auto, "_reconstruct", fake)
    c = auto.measure_cost("lp")
    assert c["fixed"] == pytest.approx(0.2, rel=1e-9)
    assert c["per_pixel"] == pytest.approx(3e-6, rel=1e-9)


def test_costs_are_measured_once_and_cached(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(auto, "measure_cost", lambda name: calls.append(name) or
                        {"fixed": 0.5, "per_pixel": 2e-6})
    first = auto.reconstruction_costs(["lp", "awr"])
    second = auto.reconstruction_costs(["lp", "awr"])
    assert calls == ["lp", "awr"] and first == second
    assert auto.reconstruction_seconds(first["lp"], 1000) == pytest.approx(0.502)
    path = auto.cost_cache_path()
    with open(path, "w") as fh:
        fh.write("{not json")
    auto.reconstruction_costs(["lp"])  # unreadable: measured again, rewritten
    assert calls == ["lp", "awr", "lp"]
    with open(path) as fh:
        assert any(k.startswith("lp|") for k in json.load(fh))


def test_cv_regions_lie_inside_the_frame_and_one_crop_covers_a_small_frame():
    side = auto.Params().tile + 2 * auto.CV_MARGIN
    assert auto.cv_regions(side - 2, side) == [(0, 0, side, side - 2)]
    crops = auto.cv_regions(200, 300, auto.Params(tile=32, max_tiles=8))
    assert len(crops) == 8
    interiors = set()
    for x0, y0, x1, y1 in crops:
        assert 0 <= x0 < x1 <= 300 and 0 <= y0 < y1 <= 200
        iy, ix = auto._interior((x0, y0, x1, y1), 200, 300)
        assert iy.stop - iy.start == 32 and ix.stop - ix.start == 32
        interiors.add((x0 + ix.start, y0 + iy.start))
    assert len(interiors) == 8  # distinct tiles
    ys = sorted(y for _, y in interiors)
    assert ys[-1] - ys[0] >= 64  # the first tiles spread over the frame


def test_the_choice_scores_candidates_in_order_within_its_time(monkeypatch):
    """With no time to spend (cv_share 0) only the first listed
    reconstruction is scored besides the sample mean, and the report names
    the others; with time for all (a render predicted to take an hour) every
    one is scored."""
    truth, feats = _scene(24, 24)
    quick = _run(FakeExecutor(truth, feats), spp=6, params={"candidates": "mean,awr,lp", "cv_share": 0.0})
    names = {r["name"] for r in quick.selection["candidates"]}
    assert names == {"uniform", "var", "uniform-awr", "awr"}
    assert quick.selection["unscored"] == ["lp"] and "not scored" in quick.selection["why"]
    assert quick.selection["chosen"] in names
    real = auto.render_seconds
    monkeypatch.setattr(auto, "render_seconds", lambda ctx: (real(ctx)[0], 3600.0))
    slow = _run(FakeExecutor(truth, feats), spp=6, params={"candidates": "mean,awr,lp"})
    assert {r["name"] for r in slow.selection["candidates"]} == names | {"uniform-lp", "lp"}
    assert slow.selection["unscored"] == [] and "not scored" not in slow.selection["why"]


def test_too_few_subsets_fall_back_and_say_why():
    truth, feats = _scene(16, 16)
    run = _run(FakeExecutor(truth, feats), spp=6, initial_spp=2, subsets=2,
               params={"candidates": "mean,awr"})
    assert run.selection["candidates"] == []
    assert "cross-validation needs 4" in run.selection["why"]
    assert run.method.NAME == "uniform-awr"


def test_resume_keeps_the_choice_and_ends_identical(tmp_path):
    truth, feats = _scene(24, 32)
    opts = dict(spp=10, task_cost=64, params={"candidates": "mean,awr"})
    full = _run(FakeExecutor(truth, feats), **opts)
    ckpt = str(tmp_path / "run.npz")
    first = AdaptiveRun(FakeExecutor(truth, feats), Options(method="auto", **opts), checkpoint=ckpt)
    steps = first.steps()
    for st in steps:  # "kill" after the first checkpoint (right after the choice)
        if st.stage == "checkpoint":
            break
    steps.close()
    resumed = AdaptiveRun(FakeExecutor(truth, feats), Options(method="auto", **opts), checkpoint=ckpt)
    resumed.load_checkpoint(ckpt)
    assert resumed.selection["chosen"] == first.selection["chosen"] == resumed.method.NAME
    for _ in resumed.steps():
        pass
    if full.selection["chosen"] == first.selection["chosen"]:  # the choice reads the clock
        np.testing.assert_array_equal(resumed.buffers.n, full.buffers.n)
        np.testing.assert_array_equal(resumed.buffers.color.mean, full.buffers.color.mean)


@pytest.mark.parametrize("bad", [{"candidates": "mean,bogus"}, {"candidates": ""},
                                 {"sampling": "sometimes"}, {"tile": 2}])
def test_bad_parameters_are_refused(bad):
    with pytest.raises(ValueError):
        from core.method import params_from_dict
        params_from_dict(auto.Params, bad)


def test_uniform_sampling_after_the_choice_renders_sample_subsets():
    """The rest of the budget under a uniform choice comes as the initial
    pass's number of equal subsets (groups of comparable size for the
    variance estimate), exactly the budget."""
    truth, feats = _scene(24, 24)
    ex = FakeExecutor(truth, feats)
    run = _run(ex, spp=12, params={"candidates": "mean", "sampling": "uniform"})
    assert run.method.NAME == "uniform"
    np.testing.assert_array_equal(run.buffers.k, 8)
    np.testing.assert_array_equal(run.buffers.n, 12)
    assert [t.samples for t in ex.tasks] == [1, 1, 1, 1, 2, 2, 2, 2]
    assert [t.offset for t in ex.tasks] == [0, 1, 2, 3, 4, 6, 8, 10]


def test_an_oidn_choice_runs_without_the_consistency_guard(monkeypatch):
    from core import pipeline
    seen = []
    real = pipeline.consistency_guard
    monkeypatch.setattr(pipeline, "consistency_guard", lambda res, buf, z: seen.append(z) or real(res, buf, z))
    truth, feats = _scene(16, 16)
    run = _run(FakeExecutor(truth, feats), spp=6, initial_spp=2, subsets=2, params={"candidates": "oidn"})
    assert run.selection["chosen"] == "oidn-uniform" and run.selection["guard_z"] == 0.0
    run.reconstruct()
    assert seen == [0.0]
    lp = _run(FakeExecutor(truth, feats), spp=6, initial_spp=2, subsets=2, params={"candidates": "awr"})
    lp.reconstruct()
    assert seen[-1] == Options().guard_z


class HoldingExecutor(FakeExecutor):
    """Records the held count, its release and every render, in order."""

    def __init__(self, truth, features=None):
        super().__init__(truth, features)
        self.events = []

    def hold_samples_at(self, count):
        self.events.append(("hold", count))

    def release_hold(self):
        self.events.append(("release",))

    def render(self, task):
        self.events.append(("render", task.offset, task.samples))
        return super().render(task)


def _held_run(spp, **params):
    from core.pipeline import hold_samples
    truth, feats = _scene(24, 24)
    ex = HoldingExecutor(truth, feats)
    opts = Options(method="auto", spp=spp, params=params)
    run = AdaptiveRun(ex, opts)
    held = hold_samples(ex, opts, run.method)
    for _ in run.steps():
        pass
    return run, ex, held


def test_a_uniform_choice_keeps_the_held_count_to_the_end():
    """auto holds the budget's count: its initial pass and the uniform rest
    are subsets tiling [0, spp) of one held table, never released."""
    run, ex, held = _held_run(12, candidates="mean", sampling="uniform")
    assert held == 12 and ex.events[0] == ("hold", 12)
    assert run.method.NAME == "uniform" and ("release",) not in ex.events
    spans = sorted((o, o + n) for kind, *rest in ex.events if kind == "render" for o, n in [rest])
    assert spans[0][0] == 0 and spans[-1][1] == 12
    assert all(a[1] == b[0] for a, b in zip(spans, spans[1:]))  # no gap, no overlap
    np.testing.assert_array_equal(run.buffers.n, 12)


def test_an_adaptive_choice_releases_the_hold_before_its_first_render(monkeypatch):
    from core import pipeline
    # an adaptive choice the sampling parameter does not force (that case holds nothing)
    monkeypatch.setattr(pipeline, "held_count", lambda options, method, prior=None: 12)
    run, ex, held = _held_run(12, candidates="mean", sampling="adaptive")
    assert held == 12 and run.method.NAME == "var"
    kinds = [e[0] for e in ex.events]
    assert kinds.count("release") == 1
    first_after = kinds.index("release")
    initial = [e for e in ex.events[:first_after] if e[0] == "render"]
    assert initial and max(o + n for _, o, n in initial) == run.initial_spp  # the initial pass only
    assert any(k == "render" for k in kinds[first_after:])


@pytest.mark.parametrize("extra", [{"max_seconds": 30.0}, {"target_error": 0.01}, {"spp": 7.5},
                                   {"scene_pattern": False}, {"params": {"sampling": "adaptive"}}])
def test_auto_holds_no_count_where_the_final_count_is_unknown(extra):
    from core.pipeline import held_count
    opts = Options(method="auto", **dict({"spp": 8.0}, **extra))
    assert held_count(opts, auto) is None
    assert held_count(Options(method="auto", spp=8.0), auto) == 8
    assert held_count(Options(method="auto", spp=8.0), auto, prior=lambda b: None) is None


def test_an_executor_that_cannot_release_is_not_held_for_auto():
    from core.pipeline import hold_samples

    class HoldOnly(FakeExecutor):
        def hold_samples_at(self, count):
            raise AssertionError("held without a way back")

    truth, feats = _scene(16, 16)
    assert hold_samples(HoldOnly(truth, feats), Options(method="auto", spp=8.0), auto) is None

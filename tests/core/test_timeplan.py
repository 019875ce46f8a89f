"""A time limit that plans: the renders' fitted cost, tasks sliced to fit a
share of the limit, and whole runs on a virtual clock whose renders cost
``overhead + per_sample * pixel-samples`` and whose reconstruction costs
seconds per pixel (no wall-clock bound in any test)."""
import types

import numpy as np
import pytest

from conftest import FakeExecutor
from core import methods, regions, timeplan
from core.buffers import Buffers
from core.pipeline import AdaptiveRun, Options, merge_render
from core.timeplan import RenderCost, slice_tasks


# ------------------------------------------------------------------ the cost
def test_fit_recovers_overhead_and_per_sample_cost_leaving_out_the_first_render():
    cost = RenderCost()
    cost.add(1000, 30.0)  # the first render also built the scene
    for n in (1000, 4000, 250, 64000, 9000):
        cost.add(n, 0.4 + 2e-5 * n)
    c0, c1 = cost.fit()
    assert c0 == pytest.approx(0.4, rel=1e-9) and c1 == pytest.approx(2e-5, rel=1e-9)
    assert cost.predict(10 ** 6) == pytest.approx(0.4 + 20.0, rel=1e-9)


def test_one_size_fits_the_ratio_which_over_predicts_larger_renders():
    cost = RenderCost()
    for _ in range(4):
        cost.add(1000, 0.5 + 1e-3 * 1000)
    c0, c1 = cost.fit()
    assert c0 == 0.0 and c1 == pytest.approx(1.5e-3)
    assert cost.predict(8000) >= 0.5 + 1e-3 * 8000  # conservative: time left over, no overrun


def test_noise_that_gives_a_negative_term_falls_back_to_the_ratio():
    cost = RenderCost()
    for n, t in [(10, 1.0), (100, 3.0), (1000, 2.0), (10000, 0.5)]:  # slower for fewer samples
        cost.add(n, t)
    c0, c1 = cost.fit()
    assert c0 == 0.0 and c1 == pytest.approx((3.0 + 2.0 + 0.5) / 11100)


def test_empty_and_hostile_observations():
    cost = RenderCost()
    assert cost.fit() == (0.0, 0.0) and cost.samples_within(100.0) == 0
    for n, t in [(0, 1.0), (10, float("nan")), (10, -1.0), (10, float("inf"))]:
        cost.add(n, t)
    assert len(cost) == 0
    cost.add(100, 1.0)
    assert cost.samples_within(-5.0) == 0 and cost.samples_within(float("nan")) == 0


@pytest.mark.parametrize("seconds,rps", [(10.0, 0.0), (10.0, 1e-3), (0.3, 0.0), (100.0, 1e-2), (0.05, 0.0)])
def test_samples_within_is_the_inverse_of_the_round_cost(seconds, rps):
    """n samples in max(1, rps * n) renders: the largest n whose predicted
    seconds fit."""
    cost = RenderCost()
    for n in (500, 5000, 50000):
        cost.add(n, 0.1 + 1e-4 * n)
    cost.add(500, 0.1 + 1e-4 * 500)
    c0, c1 = cost.fit()
    total = lambda n: c0 * max(1.0, rps * n) + c1 * n
    n = cost.samples_within(seconds, rps)
    if seconds <= c0:
        assert n == 0
    else:
        assert total(n) <= seconds + 1e-9 < total(n + 1) + 1e-9


# -------------------------------------------------------------------- slices
def _cost(c0, c1):
    cost = RenderCost()
    for n in (100, 100, 1000, 10000):
        cost.add(n, c0 + c1 * n)
    return cost


def test_slices_fit_the_share_and_keep_rect_samples_and_order():
    cost = _cost(0.2, 1e-4)
    tasks = [regions.RegionTask(0, 0, 64, 64, 40), regions.RegionTask(8, 8, 16, 16, 3),
             regions.RegionTask(0, 0, 64, 32, 90)]
    out = slice_tasks(tasks, cost, 2.0)
    assert [t.samples for t in out if t.rect == tasks[1].rect] == [3]  # fits: unchanged
    for t in tasks:
        parts = [s for s in out if s.rect == t.rect]
        assert sum(s.samples for s in parts) == t.samples
        assert max(s.samples for s in parts) - min(s.samples for s in parts) <= 1
        if cost.predict(t.pixels * t.samples) > 2.0:
            assert len(parts) > 1 and all(cost.predict(s.pixels * s.samples) <= 2.0 for s in parts)
    # in place: the rectangles keep their order
    rects = [t.rect for t in out]
    assert [r for i, r in enumerate(rects) if i == 0 or rects[i - 1] != r] == [t.rect for t in tasks]


def test_a_slice_holds_at_least_one_sample_and_no_limit_slices_nothing():
    cost = _cost(0.0, 1.0)  # one sample of a 64x64 task takes 4096 s
    t = regions.RegionTask(0, 0, 64, 64, 5)
    out = slice_tasks([t], cost, 1.0)  # one row of one sample is the smallest render
    assert len(out) == 5 * 64 and all(s.samples == 1 and s.height == 1 and s.width == 64 for s in out)
    assert slice_tasks([t], cost, 0.0) == [t]
    assert slice_tasks([t], RenderCost(), 1.0) == [t]


def test_sliced_tasks_merge_into_the_unsliced_render():
    """Slices get consecutive offsets (assign_offsets), so the merged mean is
    the one render's: same samples, same image."""
    truth = np.random.default_rng(3).random((16, 24, 3)) + 0.1
    task = regions.RegionTask(4, 2, 20, 14, 23)
    whole, sliced = [Buffers.empty(16, 24, ("alpha",)) for _ in range(2)]
    nxt = np.full((16, 24), 5, np.int64)
    for buf, tasks in ((whole, [task]), (sliced, slice_tasks([task], _cost(0.0, 1e-3), 1.0))):
        tasks, _ = regions.assign_offsets(tasks, nxt)
        ex = FakeExecutor(truth)
        for t in tasks:
            merge_render(buf, t, *ex.render(t))
    assert len(tasks) > 1 and [t.offset for t in tasks] == list(np.cumsum([5] + [t.samples for t in tasks])[:-1])
    np.testing.assert_array_equal(whole.n, sliced.n)
    np.testing.assert_allclose(sliced.color.mean, whole.color.mean, rtol=1e-12, atol=1e-14)


# ------------------------------------------------------- runs on a virtual clock
class _Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


class CostExecutor(FakeExecutor):
    """Each render advances the clock by overhead + per_sample * pixel-samples."""

    def __init__(self, truth, clock, overhead, per_sample):
        h, w = truth.shape[:2]
        xx = np.mgrid[0:h, 0:w][1]
        super().__init__(truth, {"albedo": np.where(truth > 1.0, 0.8, 0.3),
                                 "normal": np.dstack([np.zeros((h, w)), np.zeros((h, w)), np.ones((h, w))]),
                                 "depth": (2.0 + 0.01 * xx)[..., None]})
        self.clock, self.overhead, self.per_sample = clock, overhead, per_sample

    def render(self, task):
        self.clock.now += self.overhead + self.per_sample * task.pixels * task.samples
        return super().render(task)


class SlowReconstruction:
    """A registered method whose reconstruction takes ``per_pixel`` seconds a
    pixel on the clock (everything else is the method's own)."""

    def __init__(self, name, clock, per_pixel):
        self._m, self._clock, self._per_pixel = methods.method_for(name, {}), clock, per_pixel

    def __getattr__(self, attr):
        return getattr(self._m, attr)

    def reconstruct(self, buffers, params):
        self._clock.now += self._per_pixel * buffers.n.size
        return self._m.reconstruct(buffers, params)


def _truth(h, w):
    t = np.full((h, w, 3), 0.2)
    t[: h // 2, : w // 3] = 2.0
    return t


def _timed(monkeypatch, method="var", limit=20.0, spp=400, overhead=0.05, per_sample=1e-4,
           recon_per_pixel=0.0, shape=(32, 48), **kw):
    import core.pipeline as pipeline
    clock = _Clock()
    monkeypatch.setattr(pipeline, "time", types.SimpleNamespace(perf_counter=clock))
    ex = CostExecutor(_truth(*shape), clock, overhead, per_sample)
    opts = dict(method=method, spp=spp, initial_spp=4, subsets=4, iterations=4, task_cost=64,
                min_task_size=4, max_seconds=limit)
    opts.update(kw)
    m = SlowReconstruction(method, clock, recon_per_pixel) if recon_per_pixel else None
    run = AdaptiveRun(ex, Options(**opts), method=m, started=clock.now)
    steps = list(run.steps())
    run.reconstruct()
    return run, ex, clock, steps


@pytest.mark.parametrize("method", ["uniform", "var", "awr"])
@pytest.mark.parametrize("limit", [3.0, 20.0])
def test_the_limit_bounds_the_wall_time_within_a_slice(monkeypatch, method, limit):
    """A budget ~8x what the limit holds: the run ends within a slice of the
    limit (5 % of it plus one render's overhead), the final reconstruction
    included, and uses most of it."""
    run, ex, clock, _ = _timed(monkeypatch, method, limit, recon_per_pixel=2e-4)
    wall = run.elapsed()
    assert run.time_limited and run.samples_rendered < run.budget
    assert wall <= limit * (1 + timeplan.SLICE_SHARE) + ex.overhead, (wall, limit)
    assert wall >= 0.75 * limit, (wall, limit)
    per_task = [ex.overhead + ex.per_sample * t.pixels * t.samples for t in ex.tasks[1:]]
    assert max(per_task) <= max(timeplan.SLICE_SHARE * limit, ex.overhead + ex.per_sample * run.pixels) + 1e-9


def test_a_uniform_method_no_longer_renders_its_budget_in_one_pass(monkeypatch):
    """Without the plan, uniform rendered its whole budget as the initial
    pass's subsets: one subset took ~8x the limit."""
    run, ex, clock, _ = _timed(monkeypatch, "uniform", 3.0)
    assert ex.tasks[0].samples <= 4 and len(ex.tasks) > 4
    # still uniform: whole-frame sample slices, cut into row bands where one
    # sample over the frame exceeds a slice; a stop between bands leaves
    # whole rows one sample ahead
    n = run.buffers.n
    assert (n == n[:, :1]).all() and np.ptp(n) <= 1


def test_a_reconstruction_longer_than_the_time_left_is_not_paid_twice(monkeypatch):
    """LP-like: the sampler reconstructs every round.  When the time left
    cannot hold a round's reconstruction and the final one, the run stops
    after the initial pass, and the reconstruction that measured the cost
    (the whole of this small frame) is the final one: paid once, 0.8 + 1.5 s
    (twice would end at 3.8 s)."""
    pixels = 32 * 48
    run, ex, clock, _ = _timed(monkeypatch, "lp", 3.0, recon_per_pixel=1.5 / pixels)
    assert run.time_limited and run.iteration == 0
    assert run.elapsed() <= 3.0 * (1 + timeplan.SLICE_SHARE)
    assert run.reconstruct_estimate == pytest.approx(1.5, rel=0.05)


def test_a_loose_limit_changes_nothing_for_an_adaptive_method(monkeypatch):
    """A limit the budget fits in: the same tasks and image as no limit."""
    a, ex_a, _, _ = _timed(monkeypatch, "var", 0.0, spp=16)
    b, ex_b, _, _ = _timed(monkeypatch, "var", 1e6, spp=16)
    assert not b.time_limited
    assert [t for t in ex_a.tasks] == [t for t in ex_b.tasks]
    np.testing.assert_array_equal(a.buffers.color.mean, b.buffers.color.mean)


def test_reserve_probe_is_called_once_and_kept(monkeypatch):
    import core.pipeline as pipeline
    clock = _Clock()
    monkeypatch.setattr(pipeline, "time", types.SimpleNamespace(perf_counter=clock))
    ex = CostExecutor(_truth(32, 48), clock, 0.05, 1e-4)
    run = AdaptiveRun(ex, Options(method="var", spp=400, initial_spp=4, max_seconds=10.0), started=clock.now)
    seen = []
    run.reserve_probe = lambda buf: seen.append(buf.n.copy()) or 2.5
    list(run.steps())
    assert len(seen) == 1 and (seen[0] == 1).all()  # after the first subset, before the others
    assert run.reserve_seconds == 2.5 and run.final_reserve() >= 2.5
    assert run.elapsed() <= 10.0 - 2.5 + timeplan.SLICE_SHARE * 10.0 + ex.overhead


def test_an_adaptation_longer_than_the_samples_it_would_place_gives_a_uniform_round(monkeypatch):
    """LP-like: the time left after the initial pass holds less than two
    reconstructions (one to adapt, the samples it would place); the round
    samples uniformly with that time instead of adapting."""
    pixels = 32 * 48
    run, ex, clock, steps = _timed(monkeypatch, "lp", 6.0, recon_per_pixel=1.5 / pixels)
    assert run.history and run.history[0].get("uniform") is True
    assert any("sampling uniformly" in s.message for s in steps)
    assert run.samples_rendered > 4 * pixels and (run.buffers.n == run.buffers.n.flat[0]).all()
    assert run.elapsed() <= 6.0 * (1 + timeplan.SLICE_SHARE) + ex.overhead
    assert run.elapsed() >= 0.75 * 6.0


def test_a_one_sample_task_too_long_for_the_slice_is_cut_into_row_bands():
    """A render of one sample over a large region cannot be split in samples:
    it becomes bands of rows that each fit, cover the rectangle once, and
    merge into the unsliced render."""
    cost = _cost(0.0, 1e-3)  # 1 s holds 1000 pixel-samples
    task = regions.RegionTask(2, 3, 42, 30, 1)  # 40 x 27 = 1080 pixel-samples per sample
    two = regions.RegionTask(2, 3, 42, 30, 2)
    out = slice_tasks([task], cost, 0.5)
    assert len(out) > 1 and all(t.samples == 1 and t.x0 == 2 and t.x1 == 42 for t in out)
    assert all(cost.predict(t.pixels * t.samples) <= 0.5 for t in out)
    assert [t.y0 for t in out] == sorted(t.y0 for t in out) and out[0].y0 == 3 and out[-1].y1 == 30
    assert all(a.y1 == b.y0 for a, b in zip(out, out[1:]))
    truth = np.random.default_rng(4).random((32, 48, 3)) + 0.1
    nxt = np.zeros((32, 48), np.int64)
    nxt[3:30, 2:42] = 7
    for t_in in (task, two):
        whole, cut = [Buffers.empty(32, 48, ("alpha",)) for _ in range(2)]
        sliced = slice_tasks([t_in], cost, 0.5)
        for buf, ts in ((whole, [t_in]), (cut, sliced)):
            ts, after = regions.assign_offsets(ts, nxt)
            ex = FakeExecutor(truth)
            for t in ts:
                merge_render(buf, t, *ex.render(t))
        np.testing.assert_array_equal(whole.n, cut.n)
        np.testing.assert_allclose(cut.color.mean, whole.color.mean, rtol=1e-12, atol=1e-14)
        assert (after[3:30, 2:42] == 7 + t_in.samples).all()


def test_the_initial_pass_stops_before_a_subset_predicted_past_the_limit(monkeypatch):
    """Full-frame subsets of 2 s each under a 3 s limit: the second would
    end at 4 s, so the pass keeps one (an image) and stops."""
    run, ex, clock, _ = _timed(monkeypatch, "var", 3.0, overhead=0.0, per_sample=2.0 / (32 * 48))
    assert run.time_limited and len(ex.tasks) == 1
    assert run.elapsed() <= 3.0


def test_extrapolation_keeps_a_fixed_cost_fixed():
    from core.timeplan import extrapolate_seconds
    t = lambda p: 0.2 + 1e-6 * p  # 0.2 s of set-up, 1 us a pixel
    assert extrapolate_seconds(4096, t(4096), 16384, t(16384), 262144) == pytest.approx(t(262144))
    # scaling the larger crop alone would say 16x its 0.216 s
    assert 16 * t(16384) > 3 * t(262144)
    # noise: a smaller crop slower than the larger -> the scaled larger crop (over-estimate)
    assert extrapolate_seconds(4096, 0.5, 16384, 0.3, 262144) == pytest.approx(0.3 * 16)
    # never below the larger crop, nor NaN for hostile input
    assert extrapolate_seconds(4096, 0.1, 16384, 0.1000001, 262144) >= 0.1000001
    assert extrapolate_seconds(0, 0.1, 16384, 0.2, 262144) == pytest.approx(0.2 * 16)
    assert np.isfinite(extrapolate_seconds(4096, float("nan"), 16384, 0.2, 262144))


def test_extrapolation_never_exceeds_the_scaled_larger_crop():
    """A method cheaper per pixel on the small crop (a steep line) is
    estimated by scaling the larger crop, not by the line's 16x extrapolation."""
    from core.timeplan import extrapolate_seconds
    assert extrapolate_seconds(4096, 0.01, 16384, 0.2, 262144) == pytest.approx(0.2 * 16)


# ------------------------------------------------- a bound on each render (UI)
def _bounded(monkeypatch, method, render_seconds, spp=64, shape=(40, 48)):
    import core.pipeline as pipeline
    clock = _Clock()
    monkeypatch.setattr(pipeline, "time", types.SimpleNamespace(perf_counter=clock))
    ex = CostExecutor(_truth(*shape), clock, 0.01, 1e-4)
    run = AdaptiveRun(ex, Options(method=method, spp=spp, initial_spp=4, subsets=4, iterations=3,
                                  task_cost=64, min_task_size=4, render_seconds=render_seconds),
                      started=clock.now)
    list(run.steps())
    return run, ex, run.reconstruct()


@pytest.mark.parametrize("method", ["uniform", "var", "awr", "lp"])
def test_render_seconds_bounds_each_render_and_changes_no_bit(monkeypatch, method):
    """Every render after the first is predicted within the bound, so each
    one is (the clock's cost is exactly linear), but for bands at the
    ``MAX_BANDS`` floor, and the run's buffers
    (counts, groups, means, second moments, halves) and image are those of
    the run without the bound, bit for bit: bands split rows, never a
    pixel's samples."""
    free, ex_free, img_free = _bounded(monkeypatch, method, 0.0)
    bound = 0.06
    cut, ex_cut, img_cut = _bounded(monkeypatch, method, bound)
    cost = [ex_cut.overhead + ex_cut.per_sample * t.pixels * t.samples for t in ex_cut.tasks]
    longest_free = max(ex_free.overhead + ex_free.per_sample * t.pixels * t.samples for t in ex_free.tasks)
    assert longest_free > 2 * bound  # the bound has work to do
    fewest_rows = -(-40 // timeplan.MAX_BANDS)  # a band holds at least this many of the 40 rows
    assert all(c <= bound + 1e-9 or t.height <= fewest_rows for c, t in zip(cost[1:], ex_cut.tasks[1:]))
    assert cost[0] <= longest_free / 8 + ex_cut.overhead  # the first band, before any timing
    assert len(ex_cut.tasks) > len(ex_free.tasks)
    a, b = free.buffers, cut.buffers
    np.testing.assert_array_equal(a.n, b.n)
    np.testing.assert_array_equal(a.k, b.k)
    np.testing.assert_array_equal(a.color.mean, b.color.mean)
    np.testing.assert_array_equal(a.color.m2, b.color.m2)
    for name in a.features:
        np.testing.assert_array_equal(a.features[name].mean, b.features[name].mean)
    assert (a.half is None) == (b.half is None)
    if a.half is not None:
        np.testing.assert_array_equal(a.half.n, b.half.n)
    assert a.exponent == b.exponent
    np.testing.assert_array_equal(img_free.image, img_cut.image)


def test_render_seconds_below_the_overhead_cuts_no_task_into_more_than_max_bands(monkeypatch):
    """A bound below the renders' own overhead would make every band mostly
    overhead: once the fit separates the overhead, bands are held to twice
    it, and no task becomes more than ``MAX_BANDS`` renders."""
    free, ex_free, _ = _bounded(monkeypatch, "var", 0.0, shape=(96, 48))
    run, ex, _ = _bounded(monkeypatch, "var", 1e-4, shape=(96, 48))
    assert len(ex_free.tasks) < len(ex.tasks) <= timeplan.MAX_BANDS * len(ex_free.tasks)
    assert run._band_seconds() >= 2 * ex.overhead * 0.999
    np.testing.assert_array_equal(free.buffers.color.mean, run.buffers.color.mean)


def test_band_tasks_cover_each_task_once_in_full_width_rows():
    cost = _cost(0.0, 1e-3)
    tasks = [regions.RegionTask(2, 3, 42, 30, 3), regions.RegionTask(0, 0, 4, 4, 1)]
    out = timeplan.band_tasks(tasks, cost, 0.5)
    big = [t for t in out if t.x0 == 2]
    assert out[-1] == tasks[1] and all(t.samples == 3 and t.x1 == 42 for t in big)
    assert big[0].y0 == 3 and big[-1].y1 == 30 and all(a.y1 == b.y0 for a, b in zip(big, big[1:]))
    assert all(cost.predict(t.pixels * t.samples) <= 0.5 for t in big)
    assert timeplan.band_tasks(tasks, cost, 0.0) == tasks and timeplan.band_tasks(tasks, RenderCost(), 1) == tasks


@pytest.mark.parametrize("method", ["uniform", "lp"])
def test_a_stop_between_the_first_subsets_bands_keeps_finite_rows(monkeypatch, method):
    """Esc between two bands of the first subset: the rows rendered are kept,
    the rest hold no sample, and the image of what there is stays finite."""
    import core.pipeline as pipeline
    clock = _Clock()
    monkeypatch.setattr(pipeline, "time", types.SimpleNamespace(perf_counter=clock))
    ex = CostExecutor(_truth(40, 48), clock, 0.01, 1e-4)
    run = AdaptiveRun(ex, Options(method=method, spp=16, initial_spp=4, subsets=4, render_seconds=1e-3),
                      started=clock.now)
    steps = run.steps()
    for p in steps:
        if p.stage == "render" and "rows" in p.message:
            break
    steps.close()
    run.settle()
    n = run.buffers.n
    assert n[0, 0] > 0 and (n[:5] == n[0, 0]).all() and (n[5:] == 0).all()  # a first band of 40 / 8 rows
    assert np.isfinite(run.reconstruct().image).all()
    from core.pipeline import _options_key
    assert _options_key(Options(render_seconds=2.0)) == _options_key(Options())  # resumes either way

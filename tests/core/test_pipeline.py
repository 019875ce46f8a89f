import numpy as np
import pytest

from core.pipeline import AdaptiveRun, Options
from conftest import FakeExecutor, flat_guides, sample_values


def _truth(h, w, seed=0):
    rng = np.random.default_rng(seed)
    t = np.ones((h, w, 3)) * 0.2
    t[: h // 2, : w // 3] = 2.0  # a bright, noisier block
    return t + 0.05 * rng.random((h, w, 3))


def _run(h, w, **kw):
    ex = FakeExecutor(_truth(h, w))
    run = AdaptiveRun(ex, Options(**kw))
    for _ in run.steps():
        pass
    return run, ex


@pytest.mark.parametrize("shape", [(40, 56), (33, 17), (1, 9), (7, 1)])
@pytest.mark.parametrize("spp", [4, 8.5, 16])
def test_var_budget_is_met_within_one_percent(shape, spp):
    run, _ = _run(*shape, method="var", spp=spp, initial_spp=2, subsets=2, task_cost=64)
    budget = spp * shape[0] * shape[1]
    assert abs(run.samples_rendered - budget) <= 0.01 * budget + 1
    assert run.samples_rendered <= budget + 1


def test_no_sample_index_is_reused_and_merge_is_exact():
    """Every pixel's merged mean equals the mean of exactly the sample indices
    rendered for it, and no index is rendered twice for a pixel (tasks start at
    the highest index used in their rectangle: indices may be skipped where a
    rectangle's pixels had different counts, never repeated)."""
    run, ex = _run(24, 40, method="var", spp=8, initial_spp=2, subsets=2, task_cost=64)
    h, w = run.buffers.shape
    top = int(run.next_index.max())
    used = np.zeros((h, w, top), np.int64)
    for t in ex.tasks:
        used[t.y0:t.y1, t.x0:t.x1, t.offset:t.offset + t.samples] += 1
    assert used.max() == 1
    np.testing.assert_array_equal(used.sum(-1), run.buffers.n)
    ys, xs = np.mgrid[0:h, 0:w]
    expect = np.zeros((h, w, 3))
    for i in range(top):
        expect += np.where(used[:, :, i:i + 1] > 0, sample_values(ex.truth, ys, xs, i), 0.0)
    expect /= run.buffers.n[..., None]
    np.testing.assert_allclose(run.buffers.color.mean, expect, rtol=1e-10, atol=1e-12)


def test_uniform_renders_the_whole_budget_in_its_first_pass():
    run, ex = _run(16, 16, method="uniform", spp=8, initial_spp=2, subsets=4)
    assert np.all(run.buffers.n == 8) and np.all(run.buffers.k == 4)
    assert all((t.x0, t.y0, t.x1, t.y1) == (0, 0, 16, 16) for t in ex.tasks)


def test_adaptive_sampling_puts_more_samples_on_the_noisy_block():
    run, _ = _run(32, 48, method="var", spp=12, initial_spp=4, subsets=4, task_cost=16, min_task_size=4)
    n = run.buffers.n
    # bright block has larger absolute but equal relative noise; var uses the
    # luminance-relative deviation, so the dark region (relative noise equal,
    # epsilon-dominated) must not starve: every pixel has at least initial spp
    assert n.min() >= 4 and n.sum() <= 12 * n.size + 1


def test_checkpoint_resume_gives_identical_result(tmp_path):
    ckpt = str(tmp_path / "run.npz")
    full, _ = _run(24, 32, method="var", spp=10, initial_spp=2, subsets=2, task_cost=64)
    opts = Options(method="var", spp=10, initial_spp=2, subsets=2, task_cost=64)
    first = AdaptiveRun(FakeExecutor(_truth(24, 32)), opts, checkpoint=ckpt)
    steps = first.steps()
    for st in steps:  # stop ("kill") right after the second checkpoint
        if st.stage == "checkpoint" and st.iteration == 2:
            break
    steps.close()
    resumed = AdaptiveRun(FakeExecutor(_truth(24, 32)), opts, checkpoint=ckpt)
    resumed.load_checkpoint(ckpt)
    assert resumed.iteration == 2
    for _ in resumed.steps():
        pass
    np.testing.assert_array_equal(resumed.buffers.n, full.buffers.n)
    np.testing.assert_array_equal(resumed.buffers.color.mean, full.buffers.color.mean)
    np.testing.assert_array_equal(resumed.buffers.color.m2, full.buffers.color.m2)
    assert full.buffers.gsum is not None  # the groups' sizes, kept through the checkpoint
    np.testing.assert_array_equal(resumed.buffers.gsum, full.buffers.gsum)


def test_the_loop_keeps_each_pixels_group_sizes_for_the_calibrated_variance():
    """From the exponent's measurement on, the buffers hold ``sum_i
    n_i^(1 - beta)`` over each pixel's groups: the initial subsets and every
    region task that covered it (``Buffers.gsum``)."""
    ex = FakeExecutor(_truth(24, 32))
    run = AdaptiveRun(ex, Options(method="var", spp=12, initial_spp=4, subsets=4, task_cost=16,
                                  min_task_size=4, iterations=3))
    for _ in run.steps():
        pass
    b = run.buffers
    q = 1.0 - b.exponent
    want = np.zeros(b.shape)
    for t in ex.tasks:
        want[t.y0:t.y1, t.x0:t.x1] += float(t.samples) ** q
    assert len({(t.x0, t.y0, t.x1, t.y1) for t in ex.tasks}) > 1  # region tasks, not only whole frames
    np.testing.assert_allclose(b.gsum, want, rtol=1e-12)
    assert b.exponent != 1.0


def test_resume_refuses_other_settings(tmp_path):
    ckpt = str(tmp_path / "run.npz")
    run = AdaptiveRun(FakeExecutor(_truth(8, 8)), Options(method="var", spp=6, initial_spp=2, subsets=2),
                      checkpoint=ckpt)
    for _ in run.steps():
        pass
    other = AdaptiveRun(FakeExecutor(_truth(8, 8)), Options(method="var", spp=9, initial_spp=2, subsets=2))
    with pytest.raises(ValueError, match="other settings"):
        other.load_checkpoint(ckpt)


def test_cancel_keeps_what_was_rendered():
    run = AdaptiveRun(FakeExecutor(_truth(16, 16)), Options(method="var", spp=16, initial_spp=4, subsets=2))
    steps = run.steps()
    for st in steps:
        if st.stage == "plan":
            break
    steps.close()
    assert run.samples_rendered == 4 * 256
    res = run.reconstruct()
    assert np.isfinite(res.image).all() and res.image.shape == (16, 16, 3)


def test_bad_options_are_refused():
    ex = FakeExecutor(_truth(4, 4))
    with pytest.raises(ValueError, match="unknown method"):
        AdaptiveRun(ex, Options(method="nope"))
    with pytest.raises(ValueError, match="spp"):
        AdaptiveRun(ex, Options(method="var", spp=0))


def test_awr_loop_does_not_reconstruct_per_iteration(monkeypatch):
    """AWR's sampler reads the noisy means (Eq. 8), not the reconstruction, so
    the loop reconstructs only when asked for the final image (var's sampler
    does not read it either); LP's sampler uses it and gets one per iteration."""
    from core import awr, lp, var
    calls = {"awr": 0, "var": 0, "lp": 0}
    for name, mod in (("awr", awr), ("var", var), ("lp", lp)):
        orig = mod.reconstruct

        def counting(buf, params=None, _orig=orig, _name=name):
            calls[_name] += 1
            return _orig(buf, params)
        monkeypatch.setattr(mod, "reconstruct", counting)
    runs = {m: _run(16, 16, method=m, spp=12, initial_spp=4, subsets=4, task_cost=0)[0]
            for m in ("awr", "var")}
    feats = {p: np.random.default_rng(3).random((16, 16, 1 if p == "depth" else 3)) for p in lp.PASSES}
    runs["lp"] = AdaptiveRun(FakeExecutor(_truth(16, 16), feats),
                             Options(method="lp", spp=12, initial_spp=4, subsets=4, task_cost=0))
    for _ in runs["lp"].steps():
        pass
    assert calls["awr"] == 0 and runs["awr"].iteration >= 2
    assert calls["var"] == 0 and runs["var"].iteration >= 2
    assert calls["lp"] == runs["lp"].iteration >= 2
    runs["awr"].reconstruct()
    assert calls["awr"] == 1


def test_prior_samples_are_merged_reused_and_not_charged_to_the_budget():
    from core.buffers import Buffers
    from core.pipeline import Prior
    h, w = 16, 20
    truth = _truth(h, w)
    seen = {}
    ones = dict(flat_guides(h, w), alpha=np.ones((h, w, 1)))
    carried = Buffers.from_subsets([truth, truth * 1.01], [3, 3], [ones, ones])

    def prior(buffers):
        seen["n"] = buffers.n.copy()  # the initial pass, before anything is merged
        return Prior(carried, state={"probability": np.full((h, w), 0.5)}, info={"fraction": 1.0})

    run = AdaptiveRun(FakeExecutor(truth), Options(method="var", spp=6, initial_spp=2, subsets=2,
                                                   task_cost=64), prior=prior)
    for _ in run.steps():
        pass
    np.testing.assert_array_equal(seen["n"], np.full((h, w), 2.0))
    np.testing.assert_array_equal(run.reused, carried.n)
    assert run.prior_info == {"fraction": 1.0}
    assert "probability" in run.method_state
    budget = 6 * h * w
    assert abs(run.samples_rendered - budget) <= 0.01 * budget + 1
    assert run.buffers.n.sum() == run.samples_rendered + carried.n.sum()


def test_an_executor_rendering_tasks_in_batches_gives_the_identical_image():
    """``render_many`` (e.g. farm workers) yields results in task order; the
    loop merges in that order, so the image equals a one-by-one run's."""
    class Batched(FakeExecutor):
        def render_many(self, tasks):
            done = [self.render(t) for t in reversed(tasks)]  # rendered out of order ...
            return iter(done[::-1])                          # ... returned in task order

    opts = Options(method="var", spp=10, initial_spp=2, subsets=2, task_cost=64)
    runs = []
    for cls in (FakeExecutor, Batched):
        run = AdaptiveRun(cls(_truth(20, 24)), opts)
        for _ in run.steps():
            pass
        runs.append(run)
    a, b = runs
    np.testing.assert_array_equal(a.buffers.n, b.buffers.n)
    np.testing.assert_array_equal(a.buffers.color.mean, b.buffers.color.mean)
    np.testing.assert_array_equal(a.buffers.color.m2, b.buffers.color.m2)
    assert a.tasks_rendered == b.tasks_rendered


class _Clock:
    """A fake ``time.perf_counter``: time moves only when the slow executor
    renders (so the test has no wall-clock bound and is deterministic)."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


class SlowExecutor(FakeExecutor):
    """Every task takes ``seconds`` on the fake clock."""

    def __init__(self, truth, clock, seconds):
        super().__init__(truth)
        self.clock, self.seconds = clock, seconds

    def render(self, task):
        self.clock.now += self.seconds
        return super().render(task)


def _timed_run(monkeypatch, limit, seconds=1.0, **kw):
    import types
    import core.pipeline as pipeline
    clock = _Clock()
    monkeypatch.setattr(pipeline, "time", types.SimpleNamespace(perf_counter=clock))
    ex = SlowExecutor(_truth(24, 40), clock, seconds)
    opts = Options(method="var", spp=40, initial_spp=2, subsets=2, iterations=6, task_cost=0,
                   min_task_size=4, max_seconds=limit, **kw)
    run = AdaptiveRun(ex, opts, started=clock.now)
    steps = list(run.steps())
    return run, ex, clock, steps


def test_time_limit_is_checked_before_every_task(monkeypatch):
    """The loop stops before the task that would start past the limit, also
    inside an iteration: wall time <= limit + one task."""
    unlimited, ex_all, _, _ = _timed_run(monkeypatch, 0.0)
    iteration_tasks = max(h["tasks"] for h in unlimited.history)
    assert iteration_tasks >= 5  # so a limit can fall inside an iteration
    limit = 2 + iteration_tasks // 2 + 0.5  # initial pass (2 subsets) + half an iteration
    run, ex, clock, steps = _timed_run(monkeypatch, limit)
    assert run.time_limited and run.max_task_seconds == 1.0
    assert run.elapsed() <= limit + run.max_task_seconds
    assert len(ex.tasks) == int(np.ceil(limit))  # every task that started before the limit
    assert len(ex.tasks) < len(ex_all.tasks)
    assert any("time limit" in s.message for s in steps) and steps[-1].stage == "done"
    # the partial iteration's samples are kept and counted exactly
    n = np.zeros(run.buffers.shape)
    for t in ex.tasks:
        n[t.y0:t.y1, t.x0:t.x1] += t.samples
    np.testing.assert_array_equal(run.buffers.n, n)
    assert run.samples_rendered == int(n.sum()) and run.tasks_rendered == len(ex.tasks)
    assert sum(h["samples"] for h in run.history) == int(n.sum()) - 2 * run.pixels
    # next_index continues the rendered sequences only, so no index is skipped at an
    # untouched pixel and none is reused
    used = np.zeros(run.buffers.shape, np.int64)
    for t in ex.tasks:
        assert (run.next_index[t.y0:t.y1, t.x0:t.x1] >= t.offset + t.samples).all()
        used[t.y0:t.y1, t.x0:t.x1] = np.maximum(used[t.y0:t.y1, t.x0:t.x1], t.offset + t.samples)
    np.testing.assert_array_equal(run.next_index, used)


def test_time_limit_during_the_initial_pass_keeps_one_subset(monkeypatch):
    run, ex, _, _ = _timed_run(monkeypatch, 0.5, seconds=1.0)
    assert run.time_limited and len(ex.tasks) == 1
    assert (run.buffers.n == ex.tasks[0].samples).all()
    assert np.isfinite(run.reconstruct().image).all()


def test_no_time_limit_is_not_time_limited(monkeypatch):
    run, ex, _, _ = _timed_run(monkeypatch, 0.0)
    assert not run.time_limited
    assert abs(run.samples_rendered - 40 * run.pixels) <= 0.01 * 40 * run.pixels + 1


def test_adaptation_is_yielded_as_work_a_thread_may_run():
    """Each iteration's adaptation comes as a Progress("adapt") carrying a Work;
    running it on another thread gives the same run as running it inline."""
    import threading
    from core.pipeline import Work

    def run_with(threaded):
        run = AdaptiveRun(FakeExecutor(_truth(24, 24)), Options(method="var", spp=8, initial_spp=2,
                                                                subsets=2, task_cost=64))
        adapts = 0
        for st in run.steps():
            if st.stage == "adapt":
                assert isinstance(st.work, Work) and not st.work.done
                adapts += 1
                if threaded:
                    t = threading.Thread(target=st.work.run)
                    t.start()
                    t.join()
                    assert st.work.done
        return run, adapts

    a, na = run_with(False)
    b, nb = run_with(True)
    assert na == nb >= a.iteration >= 2  # the last iteration may take top-up rounds
    np.testing.assert_array_equal(a.buffers.n, b.buffers.n)
    np.testing.assert_array_equal(a.buffers.color.mean, b.buffers.color.mean)


def test_work_runs_once_and_reraises():
    from core.pipeline import Work
    calls = []
    w = Work(lambda: calls.append(1) or 7, "x")
    assert not w.done
    w.run()
    w.run()
    assert w.done and w.result() == 7 and calls == [1]
    bad = Work(lambda: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        bad.result()
    with pytest.raises(ZeroDivisionError):  # stored, raised again
        bad.result()


def _estimate_at(run, spp):
    return dict(run.estimates)[spp]


def _smooth(h, w):
    """A smooth image: the uniform method's error estimate (the calibrated,
    spatially pooled variance) pools only alike pixels."""
    yy, xx = np.mgrid[0:h, 0:w]
    return (0.5 + 0.3 * xx / w + 0.2 * yy / h)[..., None] * np.array([1.0, 0.8, 0.6])


def test_target_error_stops_at_the_first_check_below_it():
    """Uniform sampling of known noise (per-sample relative variance 0.8^2/3):
    far from the target every check doubles the samples (the most a step may
    grow); with the target between the 8- and the 16-spp estimates the fitted
    convergence steps from 8 spp to below 16, the run stops at the first check
    below the target, and the true relMSE lies within 1.5x of the target."""
    probe = AdaptiveRun(FakeExecutor(_smooth(32, 40)), Options(method="uniform", spp=64, target_error=1e-9))
    for _ in probe.steps():
        pass
    assert [s for s, _ in probe.estimates] == [4.0, 8.0, 16.0, 32.0]  # then the ceiling
    e8, e16 = _estimate_at(probe, 8.0), _estimate_at(probe, 16.0)
    assert e16 < e8
    target = np.sqrt(e8 * e16)
    run = AdaptiveRun(FakeExecutor(_smooth(32, 40)), Options(method="uniform", spp=64, target_error=target))
    for _ in run.steps():
        pass
    assert run.target_met
    spps = [s for s, _ in run.estimates]
    assert spps[:2] == [4.0, 8.0] and 8.0 < spps[-1] < 16.0
    assert run.samples_rendered == spps[-1] * 32 * 40
    assert run.estimates[-1][1] <= target < min(e for _, e in run.estimates[:-1])
    truth = _smooth(32, 40)
    img = run.reconstruct().image
    true = float(((img - truth) ** 2 / (truth ** 2 + 0.01)).mean())
    assert 1 / 1.5 < true / target < 1.5


def test_target_error_out_of_reach_spends_the_budget_and_says_so():
    run = AdaptiveRun(FakeExecutor(_truth(16, 16)), Options(method="var", spp=12, target_error=1e-12))
    messages = [p.message for p in run.steps()]
    assert not run.target_met
    assert abs(run.samples_rendered - 12 * 256) <= 0.01 * 12 * 256
    assert any("not reached within the budget" in m for m in messages)


def test_target_error_must_not_be_negative():
    with pytest.raises(ValueError, match="target_error"):
        Options(target_error=-0.1)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_bounded_options_refuse_non_finite_values(value):
    """NaN compares false with every bound: without an explicit check
    ``--target-error nan`` would silently turn the target off."""
    with pytest.raises(ValueError, match="target_error=.*finite"):
        Options(target_error=value)
    with pytest.raises(ValueError, match="max_seconds=.*finite"):
        Options(max_seconds=value)


class _DroppingExecutor(FakeExecutor):
    """A FakeExecutor that can stop rendering passes, as Cycles' can."""

    def drop_passes(self, names):
        self.dropped_calls = getattr(self, "dropped_calls", []) + [tuple(names)]
        self.features = {k: v for k, v in self.features.items() if k not in names}


class _Spy:
    """The lp method, recording which passes each of its calls saw."""

    def __init__(self):
        from core import lp
        self.base = lp
        self.NAME, self.PASSES, self.Params = lp.NAME, lp.PASSES, lp.Params
        self.ADAPTIVE, self.SAMPLER_USES_RESULT = lp.ADAPTIVE, lp.SAMPLER_USES_RESULT
        self.seen = []

    def reconstruct(self, buf, params=None):
        self.seen.append(set(buf.features))
        return self.base.reconstruct(buf, params)

    def sample_map(self, buf, result, budget, params=None, state=None):
        self.seen.append(set(buf.features))
        return self.base.sample_map(buf, result, budget, params, state)


def test_a_constant_pass_is_neither_read_nor_rendered():
    h, w = 24, 32
    yy, xx = np.mgrid[0:h, 0:w]
    feats = {"albedo": np.dstack([0.2 + 0.6 * (xx > w // 2)] * 3),
             "normal": np.dstack([np.sin(xx / 7.0), np.cos(xx / 7.0), 0 * xx]),
             "depth": np.full((h, w, 1), 3.5)}
    ex = _DroppingExecutor(_smooth(h, w), feats)
    spy = _Spy()
    run = AdaptiveRun(ex, Options(method="lp", spp=8, iterations=2), method=spy)
    messages = [p.message for p in run.steps()]
    run.reconstruct()
    assert run.dropped == ("depth",)
    assert ex.dropped_calls == [("depth",)]
    assert spy.seen and all("depth" not in s and {"albedo", "normal"} <= s for s in spy.seen)
    assert any("not read: depth" in m for m in messages)
    # the buffers keep the constant pass, exactly, for the output
    np.testing.assert_array_equal(run.buffers.features["depth"].mean, 3.5)
    assert run.samples_rendered == 8 * h * w


def test_a_pass_kept_for_the_output_is_still_rendered():
    h, w = 16, 16
    feats = {"albedo": np.random.default_rng(0).random((h, w, 3)), "normal": np.ones((h, w, 3)),
             "depth": np.full((h, w, 1), 2.0)}
    ex = _DroppingExecutor(_smooth(h, w), feats)
    run = AdaptiveRun(ex, Options(method="lp", spp=6, features=("depth",)))
    for _ in run.steps():
        pass
    assert "depth" in run.dropped  # normal is constant too, albedo is not
    assert not hasattr(ex, "dropped_calls") or all("depth" not in c for c in ex.dropped_calls)


def test_constant_features():
    from core.buffers import Buffers
    h, w = 6, 7
    flat = {"albedo": np.full((h, w, 3), 0.5), "normal": np.random.default_rng(1).random((h, w, 3)),
            "depth": np.full((h, w, 1), 1e3) * (1 + 1e-9 * np.random.default_rng(2).random((h, w, 1)))}
    buf = Buffers.from_subsets([np.ones((h, w, 3))] * 2, [1, 1], [flat] * 2)
    assert buf.constant_features() == ("albedo", "depth")
    nan = Buffers.from_subsets([np.ones((h, w, 3))], [1], [{"depth": np.full((h, w, 1), np.nan)}])
    assert nan.constant_features() == ("depth",)
    view = buf.without(("albedo",))
    assert set(view.features) == {"normal", "depth"} and view.color is buf.color


class _SampleZeroExecutor(FakeExecutor):
    """Writes the position pass only in the render holding sample 0, as
    Cycles does (renders with an offset carry no position)."""

    def render(self, task):
        rgba, feats = super().render(task)
        if task.offset > 0:
            feats = {k: v for k, v in feats.items() if k != "position"}
        return rgba, feats


def test_a_pass_written_only_with_sample_zero_keeps_that_value():
    h, w = 12, 16
    pos = np.random.default_rng(4).random((h, w, 3)) * 10
    ex = _SampleZeroExecutor(_smooth(h, w), {"position": pos})
    run = AdaptiveRun(ex, Options(method="var", spp=10, features=("position",)))
    for _ in run.steps():
        pass
    assert len(ex.tasks) > 4  # subsets and region renders with offsets
    np.testing.assert_allclose(run.buffers.features["position"].mean, pos, rtol=1e-12)


def test_a_pass_missing_from_a_first_render_is_an_error():
    from core.buffers import Buffers
    from core.pipeline import merge_render
    from core.regions import RegionTask
    buf = Buffers.empty(4, 4, ("depth",))
    with pytest.raises(KeyError, match="depth"):
        merge_render(buf, RegionTask(0, 0, 4, 4, 1), np.ones((4, 4, 4)), {})


def test_a_view_transform_is_what_the_sampler_and_the_reconstruction_read():
    """``view_transform`` (the frame's samples with earlier frames' accumulated
    in): where it says a pixel already holds four times the samples (a
    quarter of the variance of the mean), var's sampler sends fewer new
    samples there; the final image is the transformed view's mean; the
    budget still counts rendered samples only; the transform runs once per
    state of the samples."""
    from core.buffers import Buffers, Stat
    h, w = 16, 24
    truth = np.full((h, w, 3), 0.5)
    calls = []

    def transform(view):
        calls.append(float(view.n.sum()))
        left = np.zeros((h, w), bool)
        left[:, : w // 2] = True
        grow = np.where(left, 4.0, 1.0)
        mean = view.color.mean + np.where(left, 0.125, 0.0)[..., None]
        color = Stat(mean, view.color.m2)   # with 4x the samples: the variance of the mean / 4 on the left
        feats = {k: Stat(s.mean, s.m2 * grow[..., None]) for k, s in view.features.items()}
        return Buffers(view.n * grow, view.k.copy(), color, feats, None, view.exponent)

    opts = Options(method="var", spp=12, initial_spp=4, subsets=4, iterations=2, task_cost=0, min_task_size=1)
    run = AdaptiveRun(FakeExecutor(truth), opts, view_transform=transform)
    for _ in run.steps():
        pass
    n = run.buffers.n
    assert n[:, : w // 2].mean() < 0.9 * n[:, w // 2:].mean()
    budget = 12 * h * w
    assert abs(run.samples_rendered - budget) <= 0.01 * budget + 1
    res = run.reconstruct()
    np.testing.assert_allclose(res.image[:, : w // 2].mean() - res.image[:, w // 2:].mean(), 0.125, atol=0.03)
    assert len(calls) == len(set(calls))  # one call per state of the samples
    plain = AdaptiveRun(FakeExecutor(truth), opts)
    for _ in plain.steps():
        pass
    ratio = plain.buffers.n[:, : w // 2].mean() / plain.buffers.n[:, w // 2:].mean()
    assert abs(ratio - 1.0) < 0.06

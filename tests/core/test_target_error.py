"""--target-error: the schedule that fits the estimate's convergence
(core.pipeline.next_target_spp) and the firefly-robust estimate it stops on
(core.metrics.robust_relmse), with fake executors of known convergence."""
import numpy as np
import pytest

from core import metrics, uniform
from core.method import MethodResult
from core.pipeline import (TARGET_AIM, TARGET_MAX_GROWTH, TARGET_MIN_GROWTH, AdaptiveRun, Options,
                           convergence_rate, next_target_spp)
from conftest import FakeExecutor


def _smooth(h, w):
    yy, xx = np.mgrid[0:h, 0:w]
    return (0.5 + 0.3 * xx / w + 0.2 * yy / h)[..., None] * np.array([1.0, 0.8, 0.6])


def _finish(run):
    for _ in run.steps():
        pass
    return run


def _true_relmse(run, truth):
    return metrics.relmse(run.reconstruct().image, truth)


# ------------------------------------------------------------- the schedule
@pytest.mark.parametrize("q", [0.6, 1.0, 1.7])
def test_the_rate_of_an_exact_power_law_is_recovered(q):
    est = [(n, 3.0 * n ** -q) for n in (4.0, 8.0, 11.0, 13.0)]
    # the latest check against the latest one at most 1/1.5 its spp (8 for 13)
    assert convergence_rate(est) == pytest.approx(q, rel=1e-12)
    assert convergence_rate(est[:2]) == pytest.approx(q, rel=1e-12)
    assert convergence_rate(est[:1]) is None


def test_next_target_spp_is_the_closed_form_within_its_clamps():
    q, c = 1.4, 2.0
    est = [(n, c * n ** -q) for n in (4.0, 8.0)]
    e8 = c * 8.0 ** -q
    # a target the fit reaches within 2x: n' = 8 (e8 / (0.9 E))^(1/q)
    target = e8 / (1.6 ** q) / TARGET_AIM
    assert next_target_spp(est, target) == pytest.approx(8.0 * 1.6, rel=1e-12)
    # far away: one doubling at most; just above: the smallest growth
    assert next_target_spp(est, e8 / 1e3) == pytest.approx(8.0 * TARGET_MAX_GROWTH)
    assert next_target_spp(est, e8 / TARGET_AIM * 0.999) == pytest.approx(8.0 * TARGET_MIN_GROWTH)
    # one check: the prior rate 1; an estimate that grew: the largest step
    assert next_target_spp(est[:1], c * 4.0 ** -q / 1.5 / TARGET_AIM) == pytest.approx(6.0)
    assert next_target_spp([(4.0, 0.1), (8.0, 0.2)], 0.15) == pytest.approx(8.0 * TARGET_MAX_GROWTH)
    # beyond the float range (the rate clamped to its floor, a 1e600 ratio): still the clamp, no overflow
    assert next_target_spp([(4.0, 1e300), (8.0, 1e300)], 1e-300) == pytest.approx(8.0 * TARGET_MAX_GROWTH)


class _PowerLawMethod:
    """The sample mean with the error estimate of a known convergence: the
    relative error of every pixel is ``A n^-q`` (n: its samples), so the
    estimated relMSE is exactly ``A n^-q`` -- a noise model whose rate is
    not 1 (a stratified sequence converges faster, a denoiser slower)."""

    NAME, PASSES, Params = "power_law", (), uniform.Params
    ADAPTIVE, SAMPLER_USES_RESULT = False, False

    def __init__(self, a, q):
        self.a, self.q = a, q

    def reconstruct(self, buf, params=None):
        img = buf.color.mean
        n = np.maximum(buf.n, 1.0)
        rel = self.a * n ** -self.q
        return MethodResult(img, rel * (img * img + 0.01).mean(axis=-1), {})

    def sample_map(self, buf, result, budget, params=None, state=None):
        return uniform.sample_map(buf, result, budget)


@pytest.mark.parametrize("q", [0.55, 1.6, 2.4])
def test_the_run_stops_within_1_5x_of_the_target_where_doubling_did_not(q):
    """2.4: beyond the clamp of the fitted rate (steps then undershoot, the
    run takes one check more, never overshoots)."""
    h, w, a = 16, 20, 1.0
    model = lambda n: a * n ** -q
    # a target just below the 16-spp value: doubling (4, 8, 16, 32 ..) stops at
    # 32 spp, 2^-q of it -- outside 1.5x for the rates above 0.585
    target = 0.97 * model(16.0)
    assert (1 / 1.5 <= model(32.0) / target) == (q < 0.585)
    grey = _smooth(h, w)[..., :1].repeat(3, axis=-1)  # the RGB mean of the relative terms is exact
    run = _finish(AdaptiveRun(FakeExecutor(grey), Options(method="uniform", spp=256, target_error=target),
                              method=_PowerLawMethod(a, q)))
    spp = run.samples_rendered / (h * w)
    assert run.target_met
    assert 1 / 1.5 <= model(spp) / target <= 1.0
    assert run.estimates[-1][1] == pytest.approx(model(spp))
    steps = [b[0] / a_[0] for a_, b in zip(run.estimates, run.estimates[1:])]
    assert all(s <= TARGET_MAX_GROWTH + 1e-9 for s in steps)
    assert len(run.estimates) <= 5  # the checks (one reconstruction each) stay few
    # the iterations record the check that planned them (what a resumed run replans from)
    assert [tuple(e["target_check"]) for e in run.history] == run.estimates[:-1]


@pytest.mark.parametrize("spp", [12, 37.5])
def test_the_ceiling_is_never_exceeded(spp):
    h, w = 12, 14
    budget = spp * h * w
    for target in (1e-9, 0.9 * 1.0 * 30.0 ** -1.2):
        run = _finish(AdaptiveRun(FakeExecutor(_smooth(h, w)), Options(method="uniform", spp=spp,
                                                                         target_error=target),
                                  method=_PowerLawMethod(1.0, 1.2)))
        assert run.samples_rendered <= budget
        if not run.target_met:  # the whole ceiling, within the loop's 1 %
            assert run.samples_rendered >= 0.99 * budget - h * w


def test_an_adaptive_method_stops_within_1_5x_and_below_its_ceiling():
    """var (an adaptive sampler) on the fake noise: its own estimate, a
    ceiling it may not pass, and the true relMSE within 1.5x of the target."""
    h, w = 24, 32
    truth = _smooth(h, w)
    target = 4e-3
    run = _finish(AdaptiveRun(FakeExecutor(truth), Options(method="var", spp=96, target_error=target)))
    assert run.target_met and run.samples_rendered <= 96 * h * w
    assert 1 / 1.5 <= _true_relmse(run, truth) / target <= 1.5


def test_a_resumed_target_run_plans_the_same_steps(tmp_path):
    """Killed after its second checkpoint and resumed: the checks made before
    come back from the checkpoint's history, so the fit, the steps and the
    image are those of the uninterrupted run."""
    h, w = 24, 32
    # the step after the resume (from 16 spp) is not clamped: the fitted rate
    # sets it (29 spp; the prior rate of a run without its history: 31)
    opts = Options(method="uniform", spp=96, target_error=8.5e-3)
    full = _finish(AdaptiveRun(FakeExecutor(_smooth(h, w)), opts))
    assert [n for n, _ in full.estimates][:3] == [4.0, 8.0, 16.0] and len(full.estimates) == 4
    ckpt = str(tmp_path / "run.npz")
    first = AdaptiveRun(FakeExecutor(_smooth(h, w)), opts, checkpoint=ckpt)
    steps = first.steps()
    for st in steps:
        if st.stage == "checkpoint" and st.iteration == 2:
            break
    steps.close()
    resumed = AdaptiveRun(FakeExecutor(_smooth(h, w)), opts, checkpoint=ckpt)
    resumed.load_checkpoint(ckpt)
    _finish(resumed)
    assert resumed.estimates == full.estimates
    np.testing.assert_array_equal(resumed.buffers.n, full.buffers.n)
    np.testing.assert_array_equal(resumed.buffers.color.mean, full.buffers.color.mean)


# ------------------------------------------------------- the robust estimate
def test_robust_relmse_is_the_plain_mean_without_outliers():
    rng = np.random.default_rng(0)
    img = 0.2 + rng.random((40, 50, 3))
    err = (1.0 + rng.random((40, 50))) * 1e-3  # a bounded bulk: nothing beyond its spread
    assert metrics.robust_relmse(img, err) == pytest.approx(metrics.estimated_relmse(img, err), rel=1e-12)
    # homogeneous of degree 1 in the error, like the mean
    assert metrics.robust_relmse(img, 7.0 * err) == pytest.approx(7.0 * metrics.robust_relmse(img, err))


def test_robust_relmse_counts_outliers_at_the_bulks_bound():
    """1 % of the pixels with an error estimate 1e6 times the bulk's: the
    plain mean is their mass; the robust one counts them at the bound
    ``exp(median + k s)`` (s from the median and the 95th percentile of the
    logs), a few per cent above the bulk's mean."""
    rng = np.random.default_rng(1)
    h, w = 50, 60
    img = np.full((h, w, 3), 0.5)
    rel = np.exp(rng.normal(np.log(1e-3), 0.3, (h, w)))
    rel.flat[rng.choice(h * w, h * w // 100, replace=False)] = 1e3
    err = rel * 0.26
    plain, robust = metrics.estimated_relmse(img, err), metrics.robust_relmse(img, err)
    lo, hi = np.log(np.quantile(rel, [0.5, 0.95]))
    bound = np.exp(lo + metrics.ROBUST_SIGMAS * (hi - lo) / 1.6448536269514722)
    bulk = rel[rel < 1.0].mean()
    assert plain > 1e3 * bulk
    assert robust == pytest.approx(np.minimum(rel, bound).mean(), rel=1e-9)
    assert bulk * 0.99 < robust < bulk * 1.05


def test_robust_relmse_of_hostile_input_is_finite():
    img = np.array([[[np.nan, 1, 2], [np.inf, 0, 0]], [[1, 1, 1], [-1, 0, 0]]], np.float64)
    err = np.array([[np.inf, 1.0], [np.nan, -2.0]])
    assert np.isfinite(metrics.robust_relmse(img, err)) and metrics.robust_relmse(img, err) >= 0
    assert metrics.robust_relmse(np.zeros((0, 0, 3)), np.zeros((0, 0))) == 0.0
    assert metrics.robust_relmse(np.zeros((3, 3, 3)), np.zeros((3, 3))) == 0.0
    big = metrics.robust_relmse(np.zeros((2, 2, 3)), np.full((2, 2), 1e300))  # few pixels: the plain mean
    assert big == pytest.approx(1e302)


class _HighlightExecutor(FakeExecutor):
    """A smooth, dim image with three one-pixel highlights 200x brighter whose
    samples are heavy-tailed (Pareto-like ``u^-0.4``: relative variance 0.8
    per sample, rare values 10-100x the mean, as a caustic's).  The uniform method's error estimate pools
    a pixel's variance over alike neighbours, so each highlight lends its
    variance to the dim pixels around it, whose relative error it multiplies
    by ~1e4 while theirs stays that of the dim noise."""

    SPOTS = ((8, 9), (20, 40), (30, 17))

    def render(self, task):
        rgba, feats = super().render(task)
        for y, x in self.SPOTS:
            if task.y0 <= y < task.y1 and task.x0 <= x < task.x1:
                i = np.arange(task.offset, task.offset + task.samples)
                u = np.random.default_rng([y, x]).random(task.offset + task.samples)[i]
                vals = self.truth[y, x] * (0.6 * (1.0 - u[:, None]) ** -0.4)  # E[u^-0.4] = 1/0.6
                rgba[y - task.y0, x - task.x0, :3] = vals.mean(axis=0)
        return rgba, feats


def test_highlights_mislead_the_plain_mean_not_the_robust_one():
    h, w = 40, 56
    truth = _smooth(h, w) * 0.3
    for y, x in _HighlightExecutor.SPOTS:
        truth[y, x] = 40.0
    target = 4e-3
    run = _finish(AdaptiveRun(_HighlightExecutor(truth), Options(method="uniform", spp=128,
                                                                   target_error=target)))
    res = run.reconstruct()
    true = metrics.relmse(res.image, truth)
    plain, robust = metrics.estimated_relmse(res.image, res.error), metrics.robust_relmse(res.image, res.error)
    assert plain > 10 * true           # the highlights' pooled variance: the plain mean would never stop
    assert 1 / 1.5 < robust / true < 1.5
    assert run.target_met and run.samples_rendered < 128 * h * w
    assert 1 / 1.5 <= true / target <= 1.5

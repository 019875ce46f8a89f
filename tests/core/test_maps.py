import numpy as np
import pytest

from core import maps, regions
from core.pipeline import AdaptiveRun, Options
from conftest import FakeExecutor


def _pool_by_windows(c, dof):
    """Independent computation: explicit 3x3 windows, w_pp = nu_p, w_pq =
    nu_p nu_q / (nu_p + nu_q), scaled to the map's total."""
    h, w = c.shape
    ref = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            num = den = 0.0
            for yy in range(max(y - 1, 0), min(y + 2, h)):
                for xx in range(max(x - 1, 0), min(x + 2, w)):
                    wq = dof[y, x] if (yy, xx) == (y, x) else dof[y, x] * dof[yy, xx] / (dof[y, x] + dof[yy, xx])
                    num += wq * c[yy, xx]
                    den += wq
            ref[y, x] = num / den
    return ref * c.sum() / ref.sum()


def test_confidence_pool_matches_the_window_definition():
    rng = np.random.default_rng(1)
    c = rng.integers(0, 50, (11, 13))
    dof = rng.integers(1, 40, c.shape).astype(float)
    out = maps.confidence_pool(c, dof)
    assert out.sum() == c.sum()
    assert np.abs(out - _pool_by_windows(c, dof)).max() < 1.0 + 1e-9  # rounding only


def test_a_low_dof_outlier_gets_a_bounded_share_a_well_estimated_one_keeps_it():
    c = np.full((9, 9), 10)
    c[4, 4] = 10000
    dof = np.full((9, 9), 30.0)
    dof[4, 4] = 3.0
    out = maps.confidence_pool(c, dof)
    assert np.abs(out - _pool_by_windows(c, dof)).max() <= 1.0
    assert out.sum() == c.sum()
    # against the far field (1000x in the map) the 3-dof outlier keeps < 1/5 of its excess
    assert out[4, 4] / out[0, 0] < 0.2 * 1000
    dof[4, 4] = 30000.0  # well estimated: keeps its 1000x need
    keep = maps.confidence_pool(c, dof)
    assert np.abs(keep - _pool_by_windows(c, dof)).max() <= 1.0
    assert keep[4, 4] / keep[0, 0] > 0.9 * 1000


def test_confidence_pool_hostile_input():
    c = np.array([[np.nan, np.inf, -5.0], [3.0, 0.0, 7.0]])
    dof = np.array([[np.nan, 0.0, -1.0], [0.0, 0.0, 0.0]])
    out = maps.confidence_pool(c, dof)  # no dof anywhere: plain box mean of the valid counts
    assert out.dtype == np.int64 and out.sum() == 10 and (out >= 0).all()
    assert maps.confidence_pool(np.zeros((3, 3)), np.ones((3, 3))).sum() == 0


@pytest.mark.parametrize("shape,size", [((16, 16), 8), ((17, 30), 8), ((5, 3), 4), ((9, 9), 1)])
def test_pool_to_blocks_keeps_the_total_and_is_uniform_per_block(shape, size):
    rng = np.random.default_rng(2)
    c = rng.integers(0, 40, shape)
    out = maps.pool_to_blocks(c, size)
    assert out.sum() == c.sum() and (out >= 0).all()
    if size == 1:
        np.testing.assert_array_equal(out, c)
        return
    for y in range(0, shape[0], size):
        for x in range(0, shape[1], size):
            blk = out[y:y + size, x:x + size]
            assert blk.max() - blk.min() <= 1  # whole counts, one extra single sample at most
    # planned exactly at block scale, a block-uniform map needs few samples beyond it
    plan = regions.plan(out, min_size=size, task_cost=0.0)
    assert plan.overshoot <= out.size // 4 + 1


def test_pool_to_blocks_small_budget_is_not_lost():
    c = np.zeros((1, 9), np.int64)
    c[0, 6:] = 1
    out = maps.pool_to_blocks(c, 8)
    assert out.sum() == 3


def _truth(h, w):
    rng = np.random.default_rng(0)
    t = np.ones((h, w, 3)) * 0.2
    t[: h // 2, : w // 3] = 2.0
    return t + 0.05 * rng.random((h, w, 3))


@pytest.mark.parametrize("method", ["var", "lp", "awr"])
def test_iterations_mean_iterations_and_samples_beyond_the_map_stay_small(method):
    opts = Options(method=method, spp=12, initial_spp=4, subsets=4, iterations=3, task_cost=256)
    h, w = 48, 64
    feats = {"normal": np.dstack([np.zeros((h, w)), np.zeros((h, w)), np.ones((h, w))]),
             "albedo": np.full((h, w, 3), 0.5), "depth": np.linspace(1, 2, h * w).reshape(h, w, 1)}
    run = AdaptiveRun(FakeExecutor(_truth(h, w), feats), opts)
    seen = [st.iteration for st in run.steps() if st.stage in ("adapt", "plan", "render")]
    assert max(seen) + 1 <= 3 and run.iteration == 3 and len(run.history) == 3
    assert abs(run.samples_rendered - 12 * run.pixels) <= 0.01 * 12 * run.pixels + 1
    beyond = sum(h["overshoot"] for h in run.history)
    assert beyond <= 0.1 * run.samples_rendered + 1

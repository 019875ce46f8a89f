import numpy as np

from core.buffers import Buffers
from core.method import MethodResult, allocate, consistency_guard


def _buf(rng, h=6, w=7, sigma=0.1):
    subs = [1.0 + rng.normal(0, sigma, (h, w, 3)) for _ in range(4)]
    return Buffers.from_subsets(subs, [4] * 4)


def test_guard_reverts_pixels_that_contradict_their_samples():
    rng = np.random.default_rng(0)
    buf = _buf(rng)
    img = buf.color.mean.copy()
    img[2, 3] += 50.0  # a highlight spread into a pixel whose samples say otherwise
    res = consistency_guard(MethodResult(img, np.zeros(buf.shape)), buf, z=3.0)
    np.testing.assert_array_equal(res.image[2, 3], buf.color.mean[2, 3])
    assert res.error[2, 3] == buf.variance_of_mean()[2, 3].mean()
    assert res.info["guard_fraction"] == 1 / 42


def test_guard_keeps_a_reconstruction_within_the_noise():
    rng = np.random.default_rng(1)
    buf = _buf(rng)
    smooth = np.full(buf.color.mean.shape, 1.0)  # the truth: within a few sigma of each mean
    res = consistency_guard(MethodResult(smooth, np.zeros(buf.shape)), buf, z=5.0)
    assert res.info["guard_fraction"] < 0.05


def test_guard_returns_zero_variance_pixels_unchanged_and_skips_unknown_variance():
    buf = Buffers.from_subsets([np.full((3, 3, 3), 0.5)] * 2, [2, 2])
    res = consistency_guard(MethodResult(np.full((3, 3, 3), 0.7), np.zeros((3, 3))), buf, z=3.0)
    np.testing.assert_array_equal(res.image, buf.color.mean)
    one = Buffers.from_subsets([np.full((3, 3, 3), 0.5)], [4])  # k = 1: no variance estimate
    res = consistency_guard(MethodResult(np.full((3, 3, 3), 0.7), np.zeros((3, 3))), one, z=3.0)
    assert np.all(res.image == 0.7)
    off = consistency_guard(MethodResult(np.full((3, 3, 3), 0.7), np.zeros((3, 3))), buf, z=0)
    assert np.all(off.image == 0.7)


def test_allocate_sums_to_budget_and_respects_cap():
    w = np.array([[100.0, 1.0], [1.0, 0.0]])
    out = allocate(w, 40, cap=np.full((2, 2), 15))
    assert out.sum() == 40 and out.max() <= 15 and out[0, 0] == 15 and out[1, 1] == 0
    assert allocate(np.full((2, 2), np.nan), 8).sum() == 8


def test_t_quantile_matches_student_t_tables():
    from core.method import t_quantile
    got = t_quantile(1.959964, np.array([1, 3, 10, 1000]))  # two-sided 95 %
    np.testing.assert_allclose(got, [12.706, 3.182, 2.228, 1.96], rtol=5e-3)

import numpy as np

from core.buffers import Buffers
from core.method import MethodResult, allocate, consistency_guard, median3x3


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


def test_guard_on_the_sample_mean_changes_nothing_and_matches_the_full_judgement():
    """The sample mean itself (uniform, var) passes without a judgement; its
    result equals what judging every pixel gives (the mean nudged by 1e-12 on
    one pixel goes through the bands)."""
    rng = np.random.default_rng(2)
    buf = _buf(rng)
    buf.color.mean[1, 1, 0] = np.nan  # non-finite input is left to the method either way
    img = np.where(np.isfinite(buf.color.mean), buf.color.mean, 0.0)
    err = rng.random(buf.shape)
    fast = consistency_guard(MethodResult(img, err), buf, z=3.0)
    nudged = img.copy()
    nudged[4, 5, 2] += 1e-12
    full = consistency_guard(MethodResult(nudged, err), buf, z=3.0)
    assert fast.info["guard_fraction"] == full.info["guard_fraction"] == 0.0
    np.testing.assert_array_equal(fast.image, img)
    np.testing.assert_array_equal(fast.error, full.error)
    np.testing.assert_allclose(fast.image, full.image, rtol=0, atol=1e-12)


def test_allocate_sums_to_budget_and_respects_cap():
    w = np.array([[100.0, 1.0], [1.0, 0.0]])
    out = allocate(w, 40, cap=np.full((2, 2), 15))
    assert out.sum() == 40 and out.max() <= 15 and out[0, 0] == 15 and out[1, 1] == 0
    assert allocate(np.full((2, 2), np.nan), 8).sum() == 8


def test_t_quantile_matches_student_t_tables():
    from core.method import t_quantile
    got = t_quantile(1.959964, np.array([1, 3, 10, 1000]))  # two-sided 95 %
    np.testing.assert_allclose(got, [12.706, 3.182, 2.228, 1.96], rtol=5e-3)


def _median_stack(x):
    h, w = x.shape[:2]
    pad = np.pad(x, ((1, 1), (1, 1), (0, 0)), mode="edge")
    with np.errstate(invalid="ignore"):
        return np.median(np.stack([pad[i:i + h, j:j + w] for i in range(3) for j in range(3)], axis=-1),
                         axis=-1)


def test_median3x3_equals_np_median():
    """Bit for bit np.median over the 9 edge-padded shifted planes: random,
    tied, infinite, NaN and degenerate sizes (signed zeros aside, which the
    guard never produces: its input is sqrt(max(v, 0)))."""
    rng = np.random.default_rng(7)
    for t in range(120):
        h, w, c = (int(v) for v in rng.integers(1, 30, 3))
        c = c % 3 + 1
        x = [rng.random((h, w, c)), rng.integers(0, 3, (h, w, c)).astype(float),
             rng.choice([0.0, 1.0, np.inf, 5e-324, 1e308], (h, w, c)),
             np.where(rng.random((h, w, c)) < 0.05, np.nan, rng.random((h, w, c))),
             np.where(rng.random((h, w, c)) < 0.1, -np.inf, rng.standard_normal((h, w, c)))][t % 5]
        ref = _median_stack(x)
        for rows in (1, 4, 64):
            got = median3x3(x, rows)
            assert got.dtype == ref.dtype and got.shape == ref.shape
            assert np.array_equal(got.view(np.int64), ref.view(np.int64))


def test_guard_uses_the_exact_median_floor():
    """The guard's decisions with the stacked np.median floor, rebuilt here."""
    from core.method import t_quantile
    rng = np.random.default_rng(8)
    for t in range(20):
        buf = _buf(rng, h=int(rng.integers(1, 20)), w=int(rng.integers(1, 20)), sigma=[0.0, 0.1, 1.0][t % 3])
        img = buf.color.mean + rng.normal(0, 0.3, buf.color.mean.shape) * (rng.random(buf.shape) < 0.3)[..., None]
        res = consistency_guard(MethodResult(img, np.zeros(buf.shape)), buf, z=2.0)
        var = buf.variance_of_mean()
        known = buf.has_variance[..., None] & np.isfinite(var) & np.isfinite(buf.color.mean)
        sd = np.sqrt(np.where(known, np.maximum(var, 0.0), 0.0))
        sd = np.maximum(sd, _median_stack(sd))
        thr = t_quantile(2.0, np.maximum(buf.k - 1.0, 1.0))[..., None]
        bad = ((np.abs(img - buf.color.mean) > thr * sd) & known).any(-1) & known.all(-1)
        np.testing.assert_array_equal(res.image, np.where(bad[..., None], buf.color.mean, img))


def test_guard_counts_float_rounding_apart_from_corrections():
    """A regression's float64 rounding at zero-variance pixels (a flat
    background fitted exactly up to 1e-17) is set back to the exact mean but
    counted in ``guard_rounding``, not in ``guard_fraction``; a real
    contradiction of the same pixels' samples is counted as corrected."""
    flat = [np.full((4, 5, 3), 0.432)] * 4
    buf = Buffers.from_subsets(flat, [4] * 4)                  # zero variance everywhere
    img = buf.color.mean.copy()
    img[:2] = np.nextafter(img[:2], 1.0)                       # 1 ulp off: 10 of 20 pixels
    res = consistency_guard(MethodResult(img, np.zeros(buf.shape)), buf, z=3.0)
    np.testing.assert_array_equal(res.image, buf.color.mean)
    assert res.info["guard_fraction"] == 0.0
    assert res.info["guard_rounding"] == 0.5
    img[3, 4, 1] += 1e-6                                       # above float32 rounding of 0.432
    res = consistency_guard(MethodResult(img, np.zeros(buf.shape)), buf, z=3.0)
    np.testing.assert_array_equal(res.image, buf.color.mean)
    assert res.info["guard_fraction"] == 1 / 20
    assert res.info["guard_rounding"] == 0.5
    clean = consistency_guard(MethodResult(buf.color.mean.copy() * 1.0, np.zeros(buf.shape)), buf, z=3.0)
    assert clean.info["guard_fraction"] == clean.info["guard_rounding"] == 0.0


def test_exact_pixels_are_the_ones_the_guard_allows_no_change_at():
    """exact_pixels marks what the guard judges with a zero standard error
    (own subsets equal, 3x3-median floor zero): a flat noiseless block, not a
    pixel whose subsets agreed by chance among noisy ones, not a pixel without
    a variance estimate.  Any change there is reverted by the guard; a change
    elsewhere within the noise is not."""
    from core.method import exact_pixels
    rng = np.random.default_rng(21)
    h, w = 9, 12
    subs = [1.0 + rng.normal(0, 0.1, (h, w, 3)) for _ in range(4)]
    for s in subs:
        s[:, :5] = 0.3                                         # noiseless background, columns 0-4
    for s in subs[1:]:
        s[6, 9] = subs[0][6, 9]                                # chance agreement among noisy pixels
    buf = Buffers.from_subsets(subs, [2] * 4)
    ex = exact_pixels(buf, rows=2)                             # several bands
    assert ex[:, :4].all() and not ex[:, 6:].any()             # column 4's floor: its noisy neighbours
    assert buf.variance_of_mean()[6, 9].max() == 0 and not ex[6, 9]
    np.testing.assert_array_equal(ex, exact_pixels(buf))
    img = buf.color.mean + 1e-3                                # a small shift everywhere
    res = consistency_guard(MethodResult(img, np.zeros(buf.shape)), buf, z=3.0)
    reverted = (res.image != img).any(-1)
    assert (reverted[ex]).all()
    assert not reverted[:, 6:].any()
    one = Buffers.from_subsets([np.full((3, 3, 3), 0.5)], [4])  # k = 1: no variance estimate
    assert not exact_pixels(one).any()

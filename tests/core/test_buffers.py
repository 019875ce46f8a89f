import numpy as np
import pytest

from core.buffers import Buffers


def _groups(rng, h=5, w=7, sizes=(3, 1, 4, 2)):
    samples = [rng.normal(1.0, 0.5, size=(n, h, w, 3)) for n in sizes]
    return samples


def test_chan_merge_mean_equals_mean_of_all_samples():
    rng = np.random.default_rng(0)
    groups = _groups(rng)
    buf = Buffers.from_subsets([g.mean(0) for g in groups], [len(g) for g in groups],
                               [{} for _ in groups])
    allsamp = np.concatenate(groups, 0)
    np.testing.assert_allclose(buf.color.mean, allsamp.mean(0), atol=1e-12)
    assert np.all(buf.n == len(allsamp)) and np.all(buf.k == len(groups))


def test_m2_is_between_group_sum_of_squares():
    rng = np.random.default_rng(1)
    groups = _groups(rng)
    buf = Buffers.from_subsets([g.mean(0) for g in groups], [len(g) for g in groups])
    mu = np.concatenate(groups, 0).mean(0)
    expect = sum(len(g) * (g.mean(0) - mu) ** 2 for g in groups)
    np.testing.assert_allclose(buf.color.m2, expect, rtol=1e-10, atol=1e-12)


def test_variance_of_mean_is_sample_variance_over_n_with_edge_cases():
    """M2 / ((k - 1) n) in one allocation equals s^2 / n; +inf where k < 2 or
    n = 0, a NaN M2 stays NaN, for colour and feature stats."""
    rng = np.random.default_rng(3)
    groups = _groups(rng)
    feats = [{"albedo": g.mean(0) * 0.5} for g in groups]
    buf = Buffers.from_subsets([g.mean(0) for g in groups], [len(g) for g in groups], feats)
    buf.k[:2] = 1
    buf.n[3, 4] = 0
    buf.color.m2[4, 1] = np.nan
    for stat in (buf.color, buf.features["albedo"]):
        v = buf.variance_of_mean(stat)
        s2 = buf.sample_variance(stat)
        expect = np.where(buf.n[..., None] > 0, s2 / np.maximum(buf.n, 1.0)[..., None], np.inf)
        np.testing.assert_allclose(v, expect, rtol=1e-14)
        assert np.isinf(v[:2]).all() and np.isinf(v[3, 4]).all()
    assert np.isnan(buf.variance_of_mean()[4, 1]).all()


def test_merge_of_accumulated_buffers_equals_sequential_merge():
    rng = np.random.default_rng(2)
    groups = _groups(rng, sizes=(2, 3, 1, 5, 4))
    seq = Buffers.from_subsets([g.mean(0) for g in groups], [len(g) for g in groups])
    a = Buffers.from_subsets([g.mean(0) for g in groups[:2]], [len(g) for g in groups[:2]])
    b = Buffers.from_subsets([g.mean(0) for g in groups[2:]], [len(g) for g in groups[2:]])
    a.merge(b)
    np.testing.assert_allclose(a.color.mean, seq.color.mean, atol=1e-12)
    np.testing.assert_allclose(a.color.m2, seq.color.m2, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(a.k, seq.k)


def test_variance_of_mean_is_unbiased():
    # E[M2 / ((k-1) n)] = sigma^2 / n for unequal group sizes
    rng = np.random.default_rng(3)
    sizes = (1, 2, 5, 8)
    sigma = 0.7
    est = []
    for _ in range(400):
        groups = [rng.normal(0.0, sigma, size=(n, 4, 4, 3)) for n in sizes]
        buf = Buffers.from_subsets([g.mean(0) for g in groups], list(sizes))
        est.append(buf.variance_of_mean().mean())
    n = sum(sizes)
    assert abs(np.mean(est) - sigma ** 2 / n) < 0.03 * sigma ** 2 / n


def test_single_group_has_no_variance_estimate():
    buf = Buffers.from_subsets([np.ones((2, 3, 3))], [4])
    assert not buf.has_variance.any()
    assert np.all(np.isinf(buf.variance_of_mean()))


def test_region_merge_touches_only_the_region_and_zero_count_is_noop():
    buf = Buffers.from_subsets([np.ones((4, 6, 3)), np.full((4, 6, 3), 3.0)], [2, 2])
    before = buf.copy()
    buf.merge_group(np.full((2, 3, 3), 10.0), 4, {}, region=(1, 1, 4, 3))
    assert np.all(buf.n[1:3, 1:4] == 8) and buf.n.sum() == 4 * 24 + 4 * 6
    np.testing.assert_allclose(buf.color.mean[1:3, 1:4], (2 * 1 + 2 * 3 + 4 * 10) / 8)
    mask = np.ones((4, 6), bool)
    mask[1:3, 1:4] = False
    np.testing.assert_array_equal(buf.color.mean[mask], before.color.mean[mask])
    again = buf.copy()
    buf.merge_group(np.full((4, 6, 3), 99.0), 0, {})
    np.testing.assert_array_equal(buf.color.mean, again.color.mean)
    np.testing.assert_array_equal(buf.k, again.k)


def test_feature_passes_are_required_in_every_group():
    buf = Buffers.empty(2, 2, ("albedo",))
    with pytest.raises(KeyError):
        buf.merge_group(np.ones((2, 2, 3)), 1, {})


def test_crop_is_the_rectangle_of_every_statistic_and_a_copy():
    from core.buffers import Buffers
    rng = np.random.default_rng(5)
    b = Buffers.empty(12, 20, ("albedo", "depth"))
    for i in range(3):
        b.merge_group(rng.random((12, 20, 3)), 2 + i, {"albedo": rng.random((12, 20, 3)),
                                                        "depth": rng.random((12, 20, 1))})
    b.exponent = 1.3
    c = b.crop(4, 2, 15, 9)
    assert c.shape == (7, 11) and c.exponent == 1.3
    np.testing.assert_array_equal(c.variance_of_mean(), b.variance_of_mean()[2:9, 4:15])
    np.testing.assert_array_equal(c.feature_variance("depth"), b.feature_variance("depth")[2:9, 4:15])
    np.testing.assert_array_equal(c.halves()[0][0], b.halves()[0][0][2:9, 4:15])
    np.testing.assert_array_equal(c.halves()[1][1], b.halves()[1][1][2:9, 4:15])
    c.color.mean[:] = -1
    assert (b.color.mean >= 0).all()
    assert b.crop(-5, -5, 100, 100).shape == b.shape
    with pytest.raises(ValueError, match="empty"):
        b.crop(5, 5, 5, 9)


def test_luminance_is_the_rec709_sum_in_float64():
    """Rec. 709 weights (sum 1: grey keeps its value), float64 for float32
    input, within a rounding of the BLAS product, and one error for
    input that is not RGB."""
    from core.buffers import LUMA, luminance
    assert luminance(np.array([0.25, 0.25, 0.25])) == pytest.approx(0.25, abs=1e-16)
    assert np.array_equal(luminance(np.eye(3)), LUMA)
    rgb = np.random.default_rng(4).random((7, 5, 3)).astype(np.float32)
    lum = luminance(rgb)
    assert lum.dtype == np.float64 and lum.shape == (7, 5)
    assert np.allclose(lum, rgb.astype(np.float64) @ LUMA, rtol=4e-16, atol=0)
    with pytest.raises(ValueError, match="RGB"):
        luminance(np.ones((4, 4)))


def _constant_features_by_copy(buf, rtol=1e-6):
    """The definition, written out on a copy of the pixels with samples."""
    has = buf.n > 0
    out = []
    for name, st in buf.features.items():
        v = st.mean[has]
        v = np.where(np.isfinite(v), v, np.nan)
        if v.size == 0 or np.all(np.isnan(v)):
            out.append(name)
            continue
        with np.errstate(invalid="ignore"), __import__("warnings").catch_warnings():
            __import__("warnings").simplefilter("ignore", RuntimeWarning)
            lo, hi = np.nanmin(v, axis=0), np.nanmax(v, axis=0)
        if np.all(hi - lo <= rtol * (1.0 + np.nanmax(np.abs(v)))):
            out.append(name)
    return tuple(out)


def test_constant_features_match_the_definition_on_hostile_passes():
    """The in-place reductions give the definition's answer: NaN and +-inf
    pixels ignored, pixels without samples ignored, a channel with no finite
    value (never constant unless the whole pass has none), a frame without
    samples (every pass constant), spreads just below and above the tolerance."""
    rng = np.random.default_rng(7)
    h, w = 9, 11
    for trial in range(40):
        feats = {}
        for name, c in (("albedo", 3), ("normal", 3), ("depth", 1), ("alpha", 1)):
            base = rng.choice([0.0, 0.5, 1e3, -2.0])
            spread = rng.choice([0.0, 0.4e-6, 3e-6, 1.0]) * (1 + abs(base))
            x = base + spread * rng.random((h, w, c))
            bad = rng.random((h, w, c)) < rng.choice([0.0, 0.1, 1.0])
            x[bad] = rng.choice([np.nan, np.inf, -np.inf], size=int(bad.sum()))
            if c == 3 and trial % 7 == 0:
                x[..., 1] = np.nan  # one channel without any finite value
            feats[name] = x
        buf = Buffers.from_subsets([np.ones((h, w, 3))] * 2, [1, 1], [feats] * 2)
        if trial % 5 == 0:
            buf.n[rng.random((h, w)) < (1.0 if trial % 10 == 0 else 0.5)] = 0
        assert buf.constant_features() == _constant_features_by_copy(buf), trial

"""Tests of core/filters.py against direct (per-pixel, loop) implementations."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra import numpy as hnp

from core.filters import (box_count, box_mean, box_mean_finite, box_sum, guided_filter,
                          guided_filter_mean, nlm_center_weights, nlm_filter, nlm_pixel_distance,
                          sobel_gradient, window_offsets)

D_CLIP = 1e6


# ----------------------------------------------------------------- references
def direct_box_sum(x, r):
    h, w = x.shape[:2]
    out = np.zeros(x.shape)
    for i in range(h):
        for j in range(w):
            out[i, j] = x[max(0, i - r):i + r + 1, max(0, j - r):j + r + 1].sum(axis=(0, 1))
    return out


def direct_guided(p, I, r, eps):
    """He et al. 2010 by explicit ridge least squares in every (clipped) window."""
    h, w = I.shape
    C = p.shape[2]
    A = np.zeros((h, w, C))
    B = np.zeros((h, w, C))
    for i in range(h):
        for j in range(w):
            ys, xs = slice(max(0, i - r), i + r + 1), slice(max(0, j - r), j + r + 1)
            Iw = I[ys, xs].ravel()
            n = Iw.size
            X = np.vstack([np.stack([Iw, np.ones(n)], 1), [np.sqrt(n * eps), 0.0]])
            for c in range(C):
                sol = np.linalg.lstsq(X, np.append(p[ys, xs, c].ravel(), 0.0), rcond=None)[0]
                A[i, j, c], B[i, j, c] = sol
    q = np.zeros(p.shape)
    for i in range(h):
        for j in range(w):
            ys, xs = slice(max(0, i - r), i + r + 1), slice(max(0, j - r), j + r + 1)
            q[i, j] = A[ys, xs].reshape(-1, C).mean(0) * I[i, j] + B[ys, xs].reshape(-1, C).mean(0)
    return q


def direct_patch_distance(y, v, i, j, qi, qj, k, pr, channelwise, eps=1e-10):
    """Eq. 4 with Eq. 5, averaged over the in-image pixel pairs of the patch."""
    h, w, c = y.shape
    acc = np.zeros(c if channelwise else 1)
    cnt = 0
    for a in range(-pr, pr + 1):
        for b in range(-pr, pr + 1):
            pi, pj, ti, tj = i + a, j + b, qi + a, qj + b
            if 0 <= pi < h and 0 <= pj < w and 0 <= ti < h and 0 <= tj < w:
                d = ((y[pi, pj] - y[ti, tj]) ** 2 - (v[pi, pj] + np.minimum(v[pi, pj], v[ti, tj]))) \
                    / (eps + k * k * (v[pi, pj] + v[ti, tj]))
                acc += np.minimum(d, D_CLIP) if channelwise else min(d.mean(), D_CLIP)
                cnt += 1
    return np.maximum(acc / cnt, 0.0)


def direct_nlm(y, v, k, r, pr, sr, ss, g=None, gs=None, channelwise=False):
    h, w, c = y.shape
    out = np.zeros_like(y)
    for i in range(h):
        for j in range(w):
            num = np.zeros(c)
            den = np.zeros(c if channelwise else 1)
            for qi in range(max(0, i - r), min(h, i + r + 1)):
                for qj in range(max(0, j - r), min(w, j + r + 1)):
                    P = direct_patch_distance(y, v, i, j, qi, qj, k, pr, channelwise)
                    lw = -P / (2 * sr * sr)
                    if ss > 0:
                        lw = lw - ((qi - i) ** 2 + (qj - j) ** 2) / (2 * ss * ss)
                    if g is not None:
                        lw = lw - (((g[i, j] - g[qi, qj]) ** 2) / (2 * np.asarray(gs) ** 2)).sum()
                    wt = np.exp(lw)
                    num += wt * y[qi, qj]
                    den += wt
            out[i, j] = num / den
    return out


def direct_sobel(f):
    h, w = f.shape
    p = np.pad(f, 1, mode="edge")
    gx = np.zeros((h, w))
    gy = np.zeros((h, w))
    kx = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], float)
    for i in range(h):
        for j in range(w):
            win = p[i:i + 3, j:j + 3]
            gx[i, j] = (win * kx).sum()
            gy[i, j] = (win * kx.T).sum()
    return np.sqrt(gx ** 2 + gy ** 2)


# ------------------------------------------------------------------------- box
@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (7, 11), (13, 5, 2)])
@pytest.mark.parametrize("r", [0, 1, 3, 6, 17, 40])
def test_box_sum_matches_direct(shape, r):
    x = np.random.default_rng(0).normal(size=shape)
    np.testing.assert_allclose(box_sum(x, r), direct_box_sum(x, r), atol=1e-12)


def test_box_mean_and_count():
    x = np.random.default_rng(1).normal(size=(6, 8))
    cnt = direct_box_sum(np.ones_like(x), 2)
    np.testing.assert_allclose(box_mean(x, 2), direct_box_sum(x, 2) / cnt, atol=1e-12)
    np.testing.assert_array_equal(np.outer(box_count(6, 2), box_count(8, 2)), cnt)


@pytest.mark.parametrize("r", [2, 20])
def test_box_sum_huge_value_does_not_spoil_other_windows(r):
    """No subtraction of running sums: windows without the 1e30 stay exact."""
    x = np.ones((3, 120))
    x[1, 2] = 1e30
    s = box_sum(x, r)
    far = np.arange(120) > 2 + r
    np.testing.assert_array_equal(s[:, far], direct_box_sum(np.ones((3, 120)), r)[:, far])


@pytest.mark.parametrize("shape", [(1, 1), (5, 7), (9, 4, 2)])
@pytest.mark.parametrize("r", [0, 1, 2, 20])
def test_box_mean_finite_is_the_mean_over_finite_entries(shape, r):
    rng = np.random.default_rng(3)
    x = rng.normal(size=shape)
    x[rng.random(shape) < 0.3] = np.nan
    x.flat[0] = np.inf
    ok = np.isfinite(x)
    num = direct_box_sum(np.where(ok, x, 0.0), r)
    den = direct_box_sum(ok.astype(float), r)
    with np.errstate(invalid="ignore", divide="ignore"):
        want = np.where(den > 0, num / den, np.nan)
    got = box_mean_finite(x, r)
    np.testing.assert_array_equal(np.isnan(got), den == 0)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    # no NaN: the plain box mean
    y = np.where(ok, x, 0.0)
    np.testing.assert_allclose(box_mean_finite(y, r), box_mean(y, r), rtol=1e-12, atol=1e-14)


# --------------------------------------------------------------- guided filter
@pytest.mark.parametrize("shape,r", [((9, 13), 0), ((9, 13), 1), ((9, 13), 2), ((5, 4), 6),
                                     ((1, 7), 2)])
def test_guided_filter_matches_windowed_least_squares(shape, r):
    rng = np.random.default_rng(2)
    p = rng.normal(size=shape + (3,))
    I = rng.normal(size=shape)
    for eps in (1e-3, 0.3):
        np.testing.assert_allclose(guided_filter(p, I, r, eps), direct_guided(p, I, r, eps),
                                   atol=1e-10)


def test_guided_filter_single_channel_and_flat_guide():
    rng = np.random.default_rng(3)
    p = rng.normal(size=(8, 9))
    # a constant guide makes a = 0, so q is the box mean of the box means of p
    q = guided_filter(p, np.full((8, 9), 0.7), 2, 1e-3)
    np.testing.assert_allclose(q, box_mean(box_mean(p, 2), 2), atol=1e-12)
    # guided by itself with tiny eps, a ~ 1 and b ~ 0: edges and values are kept
    I = np.repeat(np.linspace(0, 5, 9)[None], 8, 0)
    np.testing.assert_allclose(guided_filter(I, I, 2, 1e-9), I, atol=1e-6)


@pytest.mark.parametrize("r", [0, 1, 3])
def test_guided_filter_mean_equals_mean_of_guided_filters(r):
    rng = np.random.default_rng(9)
    p = rng.normal(size=(37, 23, 3))
    g = rng.normal(size=(37, 23, 4))
    ref = np.mean([guided_filter(p, g[..., m], r, 1e-3) for m in range(4)], axis=0)
    for chunk in (23, 100, 1 << 15):                  # strips of 1, 4, all rows
        np.testing.assert_allclose(guided_filter_mean(p, g, r, 1e-3, chunk_pixels=chunk), ref,
                                   atol=1e-12)


@settings(max_examples=15, deadline=None)
@given(hnp.arrays(np.float64, (5, 6, 3), elements=st.sampled_from(
    [0.0, 1.0, -3.0, 1e30, -1e30, np.nan, np.inf, -np.inf, 1e6, 0.25])))
def test_guided_filter_hostile_input_is_finite(p):
    q = guided_filter(p, p[..., 0], 2, 1e-3)
    assert np.all(np.isfinite(q))
    assert np.all(np.isfinite(guided_filter_mean(p, p[..., :2], 1, 1e-3)))


# ---------------------------------------------------------------------- NL-means
def test_pixel_distance_formula():
    d = nlm_pixel_distance(np.array([1.0]), np.array([3.0]), np.array([0.5]), np.array([2.0]), 2.0)
    assert d[0] == pytest.approx((4.0 - (0.5 + 0.5)) / (1e-10 + 4.0 * 2.5))
    # a pixel against itself is never farther than 0
    v = np.array([0.0, 0.1, 7.0])
    assert np.all(nlm_pixel_distance(v, v, v, v, 0.5) <= 0)


@pytest.mark.parametrize("channelwise", [False, True])
@pytest.mark.parametrize("spatial,guided", [(0.0, False), (2.0, True)])
def test_nlm_filter_matches_direct(channelwise, spatial, guided):
    rng = np.random.default_rng(4)
    y = rng.normal(size=(6, 9, 3))
    v = rng.uniform(0, 0.5, size=(6, 9, 3))
    g = rng.normal(size=(6, 9, 2)) if guided else None
    gs = [0.8, 0.5] if guided else None
    ref = direct_nlm(y, v, 0.7, 2, 1, 1.0, spatial, g, gs, channelwise)
    for chunk in (9, 20, 1 << 14):                       # strips of 1, 2, all rows
        out = nlm_filter(y, v, 0.7, 2, 1, 1.0, spatial, guides=g, guide_sigmas=gs,
                         channelwise=channelwise, chunk_pixels=chunk)
        np.testing.assert_allclose(out, ref, atol=1e-12)
    out32 = nlm_filter(y, v, 0.7, 2, 1, 1.0, spatial, guides=g, guide_sigmas=gs,
                       channelwise=channelwise, dtype=np.float32)
    np.testing.assert_allclose(out32, ref, atol=1e-5)


def test_nlm_filter_window_larger_than_image_and_tiny_images():
    rng = np.random.default_rng(5)
    for shape in [(1, 1, 3), (1, 5, 3), (3, 5, 3)]:
        y = rng.normal(size=shape)
        v = rng.uniform(0.1, 1, size=shape)
        np.testing.assert_allclose(nlm_filter(y, v, 1.0, 6, 3), direct_nlm(y, v, 1.0, 6, 3, 1, 0),
                                   atol=1e-12)


def test_nlm_filter_zero_variance_distinct_patches_unchanged():
    y = np.random.default_rng(6).uniform(size=(7, 8, 3))
    np.testing.assert_array_equal(nlm_filter(y, np.zeros_like(y), 0.25, 3, 2), y)
    c = np.full((5, 6, 3), 0.3)
    np.testing.assert_allclose(nlm_filter(c, np.zeros_like(c) + 0.1, 1.0, 2, 1), c, atol=1e-15)


@settings(max_examples=15, deadline=None)
@given(hnp.arrays(np.float64, (4, 5, 3), elements=st.sampled_from(
           [0.0, 1.0, -2.0, 1e30, -1e30, np.nan, np.inf, -np.inf, 1e6])),
       hnp.arrays(np.float64, (4, 5, 3), elements=st.sampled_from(
           [0.0, 1.0, 1e60, np.inf, np.nan, -1.0])))
def test_nlm_filter_hostile_input_is_finite(y, v):
    for cw in (False, True):
        assert np.all(np.isfinite(nlm_filter(y, v, 0.5, 2, 1, guides=y, guide_sigmas=1.0,
                                             channelwise=cw)))
    assert np.all(np.isfinite(nlm_center_weights(y, v, [0, 3], [4, 1], 2, 1, [1.0, 4.0])))


def test_nlm_center_weights_match_direct():
    rng = np.random.default_rng(7)
    y = rng.normal(size=(6, 9, 3))
    v = rng.uniform(0, 0.5, size=(6, 9, 3))
    cy, cx, ks = np.array([0, 3, 5]), np.array([0, 4, 8]), [1.0, 2.5]
    W = nlm_center_weights(y, v, cy, cx, 2, 1, ks)
    oy, ox = window_offsets(2)
    for n in range(3):
        for ki, k in enumerate(ks):
            for o in range(25):
                qi, qj = cy[n] + oy[o], cx[n] + ox[o]
                if 0 <= qi < 6 and 0 <= qj < 9:
                    # Eq. 5 with eps scaled by k^2: the k = 1 distance over k^2 (nlm_center_weights)
                    P = direct_patch_distance(y, v, cy[n], cx[n], qi, qj, k, 1, False, eps=k * k * 1e-10)[0]
                    assert W[n, ki, o] == pytest.approx(np.exp(-P / 2), abs=1e-12)
                else:
                    assert W[n, ki, o] == 0
    centre = 12
    np.testing.assert_array_equal(W[:, :, centre], 1.0)
    assert np.all(W[:, 1] >= W[:, 0] - 1e-12)              # weights grow with k
    W32 = nlm_center_weights(y, v, cy, cx, 2, 1, ks, dtype=np.float32)
    np.testing.assert_allclose(W32, W, atol=1e-5)


def test_nlm_center_weights_spatial_term():
    y = np.zeros((5, 5, 3))
    W = nlm_center_weights(y, np.ones_like(y), [2], [2], 2, 1, [1.0], sigma_s=2.0)
    oy, ox = window_offsets(2)
    np.testing.assert_allclose(W[0, 0], np.exp(-(oy ** 2 + ox ** 2) / 8.0), atol=1e-12)


# ------------------------------------------------------------------------ Sobel
def test_sobel_matches_direct_and_step_response():
    rng = np.random.default_rng(8)
    f = rng.normal(size=(7, 10, 2))
    g = sobel_gradient(f)
    for c in range(2):
        np.testing.assert_allclose(g[..., c], direct_sobel(f[..., c]), atol=1e-12)
    step = np.repeat((np.arange(8) >= 4).astype(float)[None], 5, 0)
    gs = sobel_gradient(step)
    assert gs[:, 3:5].min() == pytest.approx(4.0) and gs[:, :2].max() == 0
    assert np.all(sobel_gradient(np.full((3, 4), 2.0)) == 0)
    np.testing.assert_array_equal(sobel_gradient(f, reduce_max=True), g.max(axis=2))
    assert sobel_gradient(np.ones((1, 1))).shape == (1, 1)

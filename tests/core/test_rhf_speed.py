"""RHF's hot paths after the speed work, against independent formulations.

* ``filters._center_patch_sums`` (all channels in one block per patch
  offset, one sum for every k) against a scalar loop over centres, window
  pixels, patch offsets and channels doing the same float operations: equal
  bits (the weights at each k against Eq. 5 per k: tests/core/test_filters.py).
* ``hat_bias_variance(lean=True)``'s bias^2 against the channel mean of the
  full bias: equal bits.
* the banded prefilter (``nlm_filter`` and ``guided_filter_mean`` row strips,
  the per-channel guided filters) and the whole reconstruction: the same bits
  on 1 and 3 threads.
"""
import dataclasses

import numpy as np
import pytest

from core import filters, parallel, rhf
from core.filters import D_CLIP, guided_filter_mean, nlm_filter

from test_rhf import scene


def gathered(y, v, cy, cx, r, pr, dtype):
    """(C, N, E, E) values / variances around each centre (clipped indices)
    and the (N, E, E) inside mask, E = 2 (r + pr) + 1, gathered by loops."""
    h, w, c = y.shape
    R = r + pr
    E = 2 * R + 1
    ye = np.zeros((c, cy.size, E, E), dtype)
    ve = np.zeros((c, cy.size, E, E), dtype)
    inside = np.zeros((cy.size, E, E), bool)
    for n in range(cy.size):
        for a in range(E):
            for b in range(E):
                i, j = cy[n] - R + a, cx[n] - R + b
                inside[n, a, b] = 0 <= i < h and 0 <= j < w
                ii, jj = min(max(i, 0), h - 1), min(max(j, 0), w - 1)
                ye[:, n, a, b] = y[ii, jj]
                ve[:, n, a, b] = v[ii, jj]
    return ye, ve, inside


def direct_patch_sums(ye, ve, inside, eps, r, pr):
    """Eq. 4-5 patch sums at k = 1 by scalar loops (per centre, window pixel,
    patch offset, channel), in the order of the vectorised code: the clipped
    channel sum min(sum_c d_c, C D_CLIP) summed over the patch, then / C."""
    c, N = ye.shape[:2]
    s = 2 * r + 1
    R = r + pr
    acc = np.zeros((N, s, s))
    cnt = np.zeros((N, s, s))
    t = ye.dtype.type
    for n in range(N):
        for oy in range(s):
            for ox in range(s):
                for ly in range(-pr, pr + 1):
                    for lx in range(-pr, pr + 1):
                        ai, aj = R + ly, R + lx                    # centre-patch pixel
                        bi, bj = pr + ly + oy, pr + lx + ox        # window-patch pixel
                        if not (inside[n, ai, aj] and inside[n, bi, bj]):
                            continue
                        cnt[n, oy, ox] += 1
                        dsum = None
                        for ch in range(c):
                            a, va = ye[ch, n, ai, aj], ve[ch, n, ai, aj]
                            b, vb = ye[ch, n, bi, bj], ve[ch, n, bi, bj]
                            nm = (a - b) * (a - b) - (va + min(va, vb))
                            q = nm / t(va + t(vb + eps))
                            dsum = q if dsum is None else t(dsum + q)
                        dsum = min(dsum, t(D_CLIP * c))
                        acc[n, oy, ox] += np.float64(dsum)
    return acc * (1.0 / c), cnt


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_center_patch_sums_equal_scalar_loop(dtype):
    rng = np.random.default_rng(11)
    h, w, r, pr = 20, 24, 3, 2
    y = rng.gamma(1.0, 1.0, size=(h, w, 3))
    v = rng.uniform(0.0, 0.3, size=(h, w, 3))
    v[4, 5] = 0.0                                            # zero variance: d ~ diff^2 / eps
    cy = np.array([0, 9, 19, 4, 12])
    cx = np.array([0, 11, 23, 22, 1])                         # corners, borders, interior
    ye, ve, inside = gathered(y, v, cy, cx, r, pr, dtype)
    eps = np.dtype(dtype).type(1e-10)
    s = 2 * r + 1
    acc = np.zeros((cy.size, s, s))
    cnt = np.zeros((cy.size, s, s))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        filters._center_patch_sums(ye, ve, inside, acc, cnt, eps, r, pr, 3)
        ref_acc, ref_cnt = direct_patch_sums(ye, ve, inside, eps, r, pr)
    np.testing.assert_array_equal(cnt, ref_cnt)
    np.testing.assert_array_equal(acc, ref_acc)
    full = (2 * pr + 1) ** 2                                 # outside, border and full patches
    assert cnt.min() == 0 and cnt.max() == full and ((cnt > 0) & (cnt < full)).any()
    assert np.all(acc[cnt == 0] == 0)


def test_lean_bias_is_channel_mean_of_full_bias():
    rng = np.random.default_rng(12)
    B, K, n, P = 3, 4, 25, 10
    X = np.concatenate([np.ones((B, n, 1)), rng.normal(size=(B, n, P - 1))], axis=2)
    wgt = rng.uniform(0, 1, size=(B, K, n))
    Y, Yp = rng.normal(size=(B, n, 3)), rng.normal(size=(B, n, 3))
    var = rng.uniform(0, 0.1, size=(B, n))
    pred, bias, v_full = rhf.hat_bias_variance(X, wgt, Y, Yp, var)
    beta, b2, v_lean = rhf.hat_bias_variance(X, wgt, Y, Yp, var, lean=True)
    # to rounding: the lean path multiplies by the prev-frame columns of beta only, and
    # BLAS may pick another kernel for that shape (1-ulp differences on some CPUs)
    np.testing.assert_allclose(b2, (bias[..., 0] * bias[..., 0] + bias[..., 1] * bias[..., 1]
                                    + bias[..., 2] * bias[..., 2]) / 3, rtol=1e-13, atol=0)
    np.testing.assert_array_equal(v_lean, v_full)
    np.testing.assert_allclose(np.einsum("bnp,bkpc->bknc", X, beta), pred, rtol=0, atol=1e-12)


@pytest.fixture
def threaded(monkeypatch):
    monkeypatch.delenv(parallel.ENV, raising=False)
    monkeypatch.setattr(filters, "THREAD_MIN_PIXELS", 0)
    monkeypatch.setattr(rhf, "THREAD_MIN_PIXELS", 0)
    yield
    parallel.set_threads(None)


def test_banded_prefilter_same_bits_on_any_thread_count(threaded):
    rng = np.random.default_rng(13)
    y = rng.normal(size=(37, 29, 4)).astype(np.float32)
    v = rng.uniform(0, 0.2, size=(37, 29, 4)).astype(np.float32)
    p = rng.normal(size=(37, 29, 3))
    out = {}
    for t in (1, 3):
        parallel.set_threads(t)
        out[t] = (nlm_filter(y, v, 0.25, 2, 1, 1.0, 2.0, guides=y, guide_sigmas=0.5,
                             channelwise=True, chunk_pixels=29 * 5, dtype=np.float32),
                  nlm_filter(y, v, 1.0, 2, 1, chunk_pixels=29 * 3),
                  guided_filter_mean(p, y, 1, 1e-3, chunk_pixels=29 * 4))
    for a, b in zip(out[1], out[3]):
        np.testing.assert_array_equal(a, b)
    # strips against one strip (the whole frame at once): Eq. 3-5 per output row
    one = nlm_filter(y, v, 1.0, 2, 1, chunk_pixels=1 << 20)
    np.testing.assert_allclose(out[1][1], one, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out[1][2], guided_filter_mean(p, y, 1, 1e-3, chunk_pixels=1 << 20),
                               rtol=0, atol=1e-12)


def test_reconstruction_same_bits_with_banded_prefilter(threaded):
    buf = scene(40, 44, spp=4, seed=3)[1]
    p = dataclasses.replace(rhf.Params(), chunk_centers=4, radius_small=3, radius_medium=5,
                            radius_large=7)
    res = {}
    for t in (1, 3):
        parallel.set_threads(t)
        feats, fvars = rhf._feature_arrays(buf)
        res[t] = rhf.rhf_reconstruct(buf.color.mean, buf.variance_of_mean(), feats, fvars, buf.n, p)
    for name in ("image", "error", "features", "guide"):
        np.testing.assert_array_equal(getattr(res[1], name), getattr(res[3], name))

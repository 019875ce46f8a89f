"""Tests for core/wavelets.py: Appendix A filter banks, the non-standard DWT and
squared-filter variance propagation (Overbeck et al. 2009, Eq. 9, 10, 15)."""
import numpy as np
import pytest
import pywt
from hypothesis import given, settings, strategies as st

from core import wavelets as wv

BANKS = ["cdf97", "legall53", "haar"]
# PyWavelets counterpart: (name, mode, detail sign, index offset of our first
# coefficient in PyWavelets' redundant output, for lengths >= 8)
PYWT = {
    "cdf97": ("bior4.4", "reflect", -1.0, 2),
    "legall53": ("bior2.2", "reflect", 1.0, 1),
    "haar": ("haar", "symmetric", 1.0, 0),
}
SHAPES = [(1, 1), (1, 9), (9, 1), (2, 2), (3, 5), (5, 3), (7, 7), (13, 17), (31, 37), (32, 32)]


# ----------------------------------------------------------------- filters
def test_cdf97_matches_appendix_a_digits():
    b = wv.BANKS["cdf97"]
    s2 = np.sqrt(2.0)
    np.testing.assert_allclose(b.lo_a / s2, [0.602949, 0.266864, -0.078223, -0.016864, 0.026749],
                               atol=1e-6)
    np.testing.assert_allclose(b.hi_a * s2, [1.115087, -0.591272, -0.057544, 0.091272], atol=1e-6)
    np.testing.assert_allclose(b.lo_s * s2, [1.115087, 0.591272, -0.057544, -0.091272], atol=1e-6)
    np.testing.assert_allclose(b.hi_s / s2, [0.602949, -0.266864, -0.078223, 0.016864, 0.026749],
                               atol=1e-6)


def test_legall53_matches_appendix_a():
    b = wv.BANKS["legall53"]
    s2 = np.sqrt(2.0)
    np.testing.assert_allclose(b.lo_a, s2 / 8 * np.array([6, 2, -1]))
    np.testing.assert_allclose(b.hi_a, 1 / s2 / 2 * np.array([-2, 1]))
    np.testing.assert_allclose(b.lo_s, 1 / s2 / 2 * np.array([2, 1]))
    np.testing.assert_allclose(b.hi_s, s2 / 8 * np.array([-6, 2, 1]))


@pytest.mark.parametrize("name", BANKS)
def test_filters_equal_pywavelets_up_to_sign(name):
    pw, _, sign, _ = PYWT[name]
    w = pywt.Wavelet(pw)
    b = wv.BANKS[name]
    trim = lambda f: np.trim_zeros(np.asarray(f, float))
    np.testing.assert_allclose(np.sort(b.full("lo_a")[1]), np.sort(trim(w.dec_lo)), atol=1e-11)
    np.testing.assert_allclose(np.sort(sign * b.full("hi_a")[1]), np.sort(trim(w.dec_hi)),
                               atol=1e-11)


@pytest.mark.parametrize("name", BANKS)
def test_lowpass_sums_to_sqrt2_and_highpass_kills_constants(name):
    b = wv.BANKS[name]
    for f in ("lo_a", "lo_s"):
        assert np.isclose(b.full(f)[1].sum(), np.sqrt(2.0))
    for f in ("hi_a", "hi_s"):
        assert abs(b.full(f)[1].sum()) < 1e-12


def test_cdf97_highpass_has_four_vanishing_moments():
    _, g = wv.BANKS["cdf97"].full("hi_a")
    m = np.arange(len(g)) - len(g) // 2
    for p in range(4):
        assert abs(np.sum(g * m ** p)) < 1e-9
    assert abs(np.sum(g * m ** 4)) > 1e-3


# ------------------------------------------------------- perfect reconstruction
@pytest.mark.parametrize("name", BANKS)
@pytest.mark.parametrize("shape", SHAPES)
def test_perfect_reconstruction_any_size(name, shape):
    x = np.random.default_rng(1).normal(size=shape + (2,))
    pyr = wv.dwt2(x, name)
    assert pyr.levels == wv.max_levels(shape)
    np.testing.assert_allclose(wv.idwt2(pyr, name), x, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(h=st.integers(1, 40), w=st.integers(1, 40), levels=st.integers(0, 8),
       name=st.sampled_from(BANKS))
def test_perfect_reconstruction_property(h, w, levels, name):
    x = np.random.default_rng(h * 41 + w).normal(size=(h, w))
    pyr = wv.dwt2(x, name, levels)
    assert pyr.levels == min(levels, wv.max_levels((h, w)))
    np.testing.assert_allclose(wv.idwt2(pyr, name), x, atol=1e-12)


# ----------------------------------------------------------- float32 path
# float32 runs the last-axis filters of 2D arrays as blocked matrix products
# (16 outputs per block, 128 rows per product): sizes around those boundaries
F32_SHAPES = [(1, 1), (1, 3), (3, 1), (2, 2), (5, 31), (17, 32), (33, 33), (129, 34), (40, 97),
              (130, 65), (257, 70)]


@pytest.mark.parametrize("name", BANKS)
@pytest.mark.parametrize("shape", F32_SHAPES)
def test_float32_transform_matches_float64(name, shape):
    x = np.random.default_rng(shape[0] * 7 + shape[1]).uniform(-1, 1, shape)
    p64, p32 = wv.dwt2(x, name), wv.dwt2(x, name, dtype=np.float32)
    bands64 = [p64.approx] + [b for d in p64.details for b in d]
    bands32 = [p32.approx] + [b for d in p32.details for b in d]
    for k, (a, b) in enumerate(zip(bands64, bands32)):
        assert b.dtype == np.float32 and a.shape == b.shape
        scale = max(1.0, float(np.abs(a).max(initial=0.0)))
        np.testing.assert_allclose(b, a, atol=3e-6 * scale, err_msg=f"band {k}")
    y = wv.idwt2(p32, name)
    assert y.dtype == np.float32
    np.testing.assert_allclose(y, x, atol=1e-5)
    # positive sums: float32 variance propagation is accurate entry by entry
    v = x * x
    for lo, hi in ((None, None), (2 ** -0.5, 2 ** -0.5)):
        q64 = wv.dwt2_variance(v, name, lo_sum=lo, hi_sum=hi)
        q32 = wv.dwt2_variance(v, name, lo_sum=lo, hi_sum=hi, dtype=np.float32)
        for a, b in zip([q64.approx] + [b for d in q64.details for b in d],
                        [q32.approx] + [b for d in q32.details for b in d]):
            np.testing.assert_allclose(b, a, rtol=2e-6, atol=1e-30)


@pytest.mark.parametrize("name", BANKS)
def test_blocked_float32_filters_equal_the_strided_contraction(name):
    """2D float32 arrays take the matrix-product path along x; a trailing
    channel axis takes the strided-window contraction: same values."""
    x = np.random.default_rng(4).normal(size=(150, 77)).astype(np.float32)
    p2 = wv.dwt2(x, name, dtype=np.float32)
    p3 = wv.dwt2(x[..., None], name, dtype=np.float32)
    for a, b in zip([p2.approx] + [b for d in p2.details for b in d],
                    [p3.approx] + [b for d in p3.details for b in d]):
        np.testing.assert_allclose(a, b[..., 0], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(wv.idwt2(p2, name), wv.idwt2(p3, name)[..., 0], atol=1e-5)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("shape", [(1, 3), (3, 1), (1, 2), (4, 5), (33, 40)])
def test_transforms_leave_their_input_untouched(dtype, shape):
    x = np.random.default_rng(5).normal(size=shape).astype(dtype)
    keep = x.copy()
    for name in BANKS:
        pyr = wv.dwt2(x, name, dtype=dtype)
        copies = [b.copy() for b in [pyr.approx] + [b for d in pyr.details for b in d]]
        wv.idwt2(pyr, name)
        assert all(np.array_equal(a, b) for a, b in
                   zip(copies, [pyr.approx] + [b for d in pyr.details for b in d]))
    assert np.array_equal(x, keep)


def test_dtype_must_be_float32_or_float64():
    for bad in (np.int32, np.float16, np.complex128):
        with pytest.raises(ValueError, match="dtype"):
            wv.dwt2(np.ones((4, 4)), dtype=bad)


@pytest.mark.parametrize("name", BANKS)
def test_subband_shapes_are_non_expansive(name):
    pyr = wv.dwt2(np.zeros((13, 6)), name)
    total = pyr.approx.size + sum(b.size for d in pyr.details for b in d)
    assert total == 13 * 6
    w0, w1, w2 = pyr.details[0]
    assert w0.shape == (7, 3) and w1.shape == (6, 3) and w2.shape == (6, 3)
    assert [s for s in wv.level_shapes((13, 6), 2)] == [(13, 6), (7, 3), (4, 2)]


def test_axis_of_length_one_is_not_transformed():
    x = np.random.default_rng(0).normal(size=(1, 16))
    pyr = wv.dwt2(x, "cdf97", 1)
    w0, w1, w2 = pyr.details[0]
    assert w1.size == 0 and w2.size == 0
    s1, d1 = pywt.dwt(x[0], "bior4.4", mode="reflect")
    np.testing.assert_allclose(pyr.approx[0], s1[2:2 + 8], atol=1e-12)
    np.testing.assert_allclose(w0[0], -d1[2:2 + 8], atol=1e-12)


def test_constant_image_has_no_wavelets_and_scaled_approx():
    pyr = wv.dwt2(np.full((12, 20), 3.0), "cdf97", 2)
    for det in pyr.details:
        for b in det:
            assert np.abs(b).max() < 1e-12
    np.testing.assert_allclose(pyr.approx, 3.0 * 2.0 ** 2)


def test_linearity():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(2, 11, 14))
    pa, pb, pab = (wv.dwt2(v, "legall53") for v in (a, b, 2 * a - 3 * b))
    np.testing.assert_allclose(pab.approx, 2 * pa.approx - 3 * pb.approx, atol=1e-12)
    for da, db, dab in zip(pa.details, pb.details, pab.details):
        for x, y, z in zip(da, db, dab):
            np.testing.assert_allclose(z, 2 * x - 3 * y, atol=1e-12)


# ---------------------------------------------------------- PyWavelets agreement
@pytest.mark.parametrize("name", BANKS)
@pytest.mark.parametrize("shape", [(16, 16), (17, 23), (24, 9 + 8)])
def test_one_level_matches_pywavelets(name, shape):
    pw, mode, sign, off = PYWT[name]
    x = np.random.default_rng(3).normal(size=shape)
    pyr = wv.dwt2(x, name, 1)
    ca, (ch, cv, cd) = pywt.dwt2(x, pw, mode=mode)
    cut = lambda a, ref: a[off:off + ref.shape[0], off:off + ref.shape[1]]
    w0, w1, w2 = pyr.details[0]
    np.testing.assert_allclose(pyr.approx, cut(ca, pyr.approx), atol=1e-10)
    np.testing.assert_allclose(w0, sign * cut(cv, w0), atol=1e-10)   # low y, high x
    np.testing.assert_allclose(w1, sign * cut(ch, w1), atol=1e-10)   # high y, low x
    np.testing.assert_allclose(w2, cut(cd, w2), atol=1e-10)          # two high-passes


@pytest.mark.parametrize("name", BANKS)
def test_every_level_matches_pywavelets_applied_to_previous_scale(name):
    pw, mode, sign, off = PYWT[name]
    x = np.random.default_rng(4).normal(size=(64, 48))
    pyr = wv.dwt2(x, name, 3)
    scales = wv.scale_coefficients(x, name, 3)
    for k in range(3):
        ca, (ch, cv, cd) = pywt.dwt2(scales[k], pw, mode=mode)
        w0, w1, w2 = pyr.details[k]
        cut = lambda a, ref: a[off:off + ref.shape[0], off:off + ref.shape[1]]
        np.testing.assert_allclose(scales[k + 1], cut(ca, scales[k + 1]), atol=1e-10)
        np.testing.assert_allclose(w2, cut(cd, w2), atol=1e-10)
        np.testing.assert_allclose(w0, sign * cut(cv, w0), atol=1e-10)
    np.testing.assert_allclose(pyr.approx, scales[3], atol=1e-12)


def test_haar_multilevel_equals_pywavelets_wavedec2():
    x = np.random.default_rng(5).normal(size=(32, 32))
    pyr = wv.dwt2(x, "haar")
    ref = pywt.wavedec2(x, "haar", mode="symmetric", level=5)
    np.testing.assert_allclose(pyr.approx, ref[0], atol=1e-12)
    for k in range(1, 6):
        ch, cv, cd = ref[6 - k]
        w0, w1, w2 = pyr.details[k - 1]
        np.testing.assert_allclose(w0, cv, atol=1e-12)
        np.testing.assert_allclose(w1, ch, atol=1e-12)
        np.testing.assert_allclose(w2, cd, atol=1e-12)


@pytest.mark.parametrize("name", BANKS)
@pytest.mark.parametrize("shape", [(64, 48), (37, 29), (40, 21)])
def test_pywavelets_analysis_round_trips_through_our_synthesis(name, shape):
    """End to end across libraries: three levels of PyWavelets analysis (each
    on the previous scale band, cut to our non-expansive layout with our detail
    signs) are our coefficients, and our ``idwt2`` of them returns the image."""
    pw, mode, sign, off = PYWT[name]
    x = np.random.default_rng(6).normal(size=shape)
    ours = wv.dwt2(x, name, 3)
    cut = lambda a, ref: a[off:off + ref.shape[0], off:off + ref.shape[1]]
    s, details = x, []
    for k in range(3):
        ca, (ch, cv, cd) = pywt.dwt2(s, pw, mode=mode)
        w0, w1, w2 = ours.details[k]
        details.append((sign * cut(cv, w0), sign * cut(ch, w1), cut(cd, w2)))
        s = cut(ca, np.empty(wv.level_shapes(shape, k + 1)[k + 1]))
        for a, b in zip(details[-1], ours.details[k]):
            np.testing.assert_allclose(a, b, atol=1e-10)
    np.testing.assert_allclose(s, ours.approx, atol=1e-10)
    np.testing.assert_allclose(wv.idwt2(wv.Pyramid(s, details), name), x, atol=1e-10)


@pytest.mark.parametrize("name", BANKS)
@pytest.mark.parametrize("shape", [(24, 32), (17, 23)])
def test_synthesis_matches_pywavelets_idwt2(name, shape):
    """Our synthesis filters and alignment against ``pywt.idwt2``.  PyWavelets
    keeps redundant boundary coefficients where we extend symmetrically, so
    the coefficients are random away from the borders and 0 within 3 of them;
    then both syntheses are the same everywhere (PyWavelets' output cropped to
    our length for odd sizes)."""
    pw, mode, sign, off = PYWT[name]
    rng = np.random.default_rng(7)
    tmpl = wv.dwt2(np.zeros(shape), name, 1)
    ca, (ch, cv, cd) = pywt.dwt2(np.zeros(shape), pw, mode=mode)

    def interior(b):
        z = np.zeros(b.shape)
        z[3:-3, 3:-3] = rng.normal(size=z[3:-3, 3:-3].shape)
        return z

    def embed(ref, a):
        z = np.zeros(ref.shape)
        z[off:off + a.shape[0], off:off + a.shape[1]] = a
        return z

    approx = interior(tmpl.approx)
    w0, w1, w2 = (interior(b) for b in tmpl.details[0])
    ours = wv.idwt2(wv.Pyramid(approx, [(w0, w1, w2)]), name)
    theirs = pywt.idwt2((embed(ca, approx), (embed(ch, sign * w1), embed(cv, sign * w0),
                                             embed(cd, w2))), pw, mode=mode)
    np.testing.assert_allclose(ours, theirs[:shape[0], :shape[1]], atol=1e-10)


# --------------------------------------------------------------- scale function
@pytest.mark.parametrize("name", BANKS)
@pytest.mark.parametrize("level", [1, 2, 3])
def test_scale_function_is_the_response_to_an_impulse(name, level):
    start, phi = wv.scale_function(name, level)
    n = 2 ** level * 8 + len(phi) * 2
    i = 4  # a coefficient far from both ends
    centre = 2 ** level * i
    # S_k[i] = sum_u phi[u] x[2^k i + start + u]: probe each pixel separately
    resp = []
    for u in range(len(phi)):
        x = np.zeros((1, n))
        x[0, centre + start + u] = 1.0
        resp.append(wv.scale_coefficients(x, name, level)[level][0, i])
    np.testing.assert_allclose(resp, phi, atol=1e-12)
    assert np.isclose(phi.sum(), np.sqrt(2.0) ** level)


def test_scale_function_2d_is_separable():
    start, phi = wv.scale_function("legall53", 2)
    x = np.zeros((40, 40))
    x[16 + start + 1, 16 + start + 3] = 1.0
    s2 = wv.scale_coefficients(x, "legall53", 2)[2]
    # 1 x 1D contributions along each axis (level 2 coefficient (4, 4) sits at pixel 16)
    assert np.isclose(s2[4, 4], phi[1] * phi[3])


# ------------------------------------------------------------ variance propagation
def _empirical(name, var, levels, reps=3000, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(var.shape + (reps,)) * np.sqrt(var)[..., None]
    return wv.dwt2(x, name, levels)


def test_haar_variance_propagation_is_exact_at_every_level():
    h = w = 16
    var = (0.5 + np.add.outer(np.arange(h), np.arange(w)) / 20.0) ** 2
    emp = _empirical("haar", var, 3)
    pred = wv.dwt2_variance(var, "haar", 3)
    for k in range(3):
        for a in range(3):
            r = emp.details[k][a].var(axis=-1) / pred.details[k][a]
            assert 0.85 < r.min() and r.max() < 1.15, (k, a)
    r = emp.approx.var(axis=-1) / pred.approx
    assert 0.85 < r.min() and r.max() < 1.15


@pytest.mark.parametrize("name", ["cdf97", "legall53"])
def test_level_one_variance_is_exact_in_the_interior(name):
    h, w = 20, 24
    rng = np.random.default_rng(7)
    var = rng.uniform(0.2, 3.0, size=(h, w))
    emp = _empirical(name, var, 1, reps=4000)
    pred = wv.dwt2_variance(var, name, 1)
    inner = (slice(3, -3), slice(3, -3))
    for a in range(3):
        r = emp.details[0][a].var(axis=-1)[inner] / pred.details[0][a][inner]
        assert abs(r.mean() - 1) < 0.02 and 0.85 < r.min() and r.max() < 1.15


def test_deeper_cdf97_variance_has_the_documented_small_bias():
    """Squared-filter DWT ignores covariances of overlapping level-(k-1)
    coefficients (the paper's accepted bias): within 25% on average."""
    var = np.full((48, 48), 2.0)
    emp = _empirical("cdf97", var, 3, reps=1500)
    pred = wv.dwt2_variance(var, "cdf97", 3)
    for k in (1, 2):
        for a in range(3):
            e = emp.details[k][a].var(axis=-1)[2:-2, 2:-2]
            p = pred.details[k][a][2:-2, 2:-2]
            assert 0.8 < (e / p).mean() < 1.25


@pytest.mark.parametrize("name", BANKS)
def test_renormalised_sampler_variance_scales_by_1_05_per_filter(name):
    var = np.random.default_rng(8).uniform(0.1, 2.0, size=(16, 16))
    nat = wv.scale_variance(var, name, 3, lo_sum=None)
    ren = wv.scale_variance(var, name, 3, lo_sum=1.05)
    a = float(np.sum(wv.squared_bank(name).full("lo_a")[1]))
    for k in range(4):
        np.testing.assert_allclose(ren[k], nat[k] * (1.05 / a) ** (2 * k), rtol=1e-12)
    # constant variance: each 1D squared filter multiplies by its sum
    const = wv.scale_variance(np.ones((16, 16)), name, 3, lo_sum=1.05)
    for k in range(4):
        np.testing.assert_allclose(const[k], 1.05 ** (2 * k), rtol=1e-12)


def test_reconstruction_filters_renormalised_to_inverse_sqrt2():
    sq = wv.squared_bank("cdf97", 2 ** -0.5, 2 ** -0.5)
    for f in ("lo_a", "hi_a", "lo_s", "hi_s"):
        assert np.isclose(sq.full(f)[1].sum(), 2 ** -0.5)
    pv = wv.dwt2_variance(np.ones((32, 32)), "cdf97", 3, 2 ** -0.5, 2 ** -0.5)
    for k in range(3):
        for b in pv.details[k]:
            np.testing.assert_allclose(b, 2.0 ** -(k + 1), rtol=1e-12)


def test_squared_synthesis_propagates_independent_coefficient_variances():
    """Synthesis of independent coefficients: Haar is exact at every pixel."""
    rng = np.random.default_rng(9)
    tmpl = wv.dwt2(np.zeros((16, 16)), "haar", 2)
    varp = wv.Pyramid(rng.uniform(0.5, 2, tmpl.approx.shape),
                      [tuple(rng.uniform(0.5, 2, b.shape) for b in d) for d in tmpl.details])
    reps = 4000
    draw = lambda v: rng.standard_normal(v.shape + (reps,)) * np.sqrt(v)[..., None]
    coefs = wv.Pyramid(draw(varp.approx), [tuple(draw(b) for b in d) for d in varp.details])
    emp = wv.idwt2(coefs, "haar").var(axis=-1)
    pred = wv.idwt2_variance(varp, "haar")
    r = emp / pred
    assert abs(r.mean() - 1) < 0.02 and 0.85 < r.min() and r.max() < 1.15


@settings(max_examples=20, deadline=None)
@given(h=st.integers(1, 20), w=st.integers(1, 20), name=st.sampled_from(BANKS))
def test_variance_propagation_is_non_negative_and_finite(h, w, name):
    var = np.random.default_rng(h + 100 * w).uniform(0, 1e30, size=(h, w))
    pv = wv.dwt2_variance(var, name, None, 2 ** -0.5, 2 ** -0.5)
    for arr in [pv.approx] + [b for d in pv.details for b in d]:
        assert np.isfinite(arr).all() and (arr >= 0).all()
    back = wv.idwt2_variance(pv, name)
    assert back.shape == (h, w) and np.isfinite(back).all() and (back >= 0).all()


def test_unknown_bank_is_rejected():
    with pytest.raises(ValueError):
        wv.get_bank("db4")


# ------------------------------------------- multi-level against PyWavelets
# PyWavelets has no non-expansive whole-sample symmetric mode: 'reflect' keeps
# (N + L - 1) // 2 coefficients per level and its deeper levels transform those
# redundant border coefficients, so multi-level results differ from ours near
# the borders for most sizes.  Our transform of an N-sample axis equals
# PyWavelets' 'periodization' of the whole-sample mirror (period 2N - 2), and
# for N = 2^m + 1 the period halves exactly at every level (the level-k grid has
# 2^(m-k) + 1 scale coefficients, the mirror 2^(m+1-k)), so on those sizes the
# two agree at every depth, to the digits of PyWavelets' tabulated bior4.4
# taps (~1e-11; bior2.2 to rounding).  Detail signs: -1 for cdf97 per high-pass
# filter (module notes), so +1 on the diagonal band W2.
MIRROR_PYWT = {"cdf97": ("bior4.4", -1.0, 1e-10), "legall53": ("bior2.2", 1.0, 1e-12)}


def _mirror(a):
    """Whole-sample mirror along both axes: (N, M) -> (2N - 2, 2M - 2)."""
    a = np.concatenate([a, a[-2:0:-1]], axis=0)
    return np.concatenate([a, a[:, -2:0:-1]], axis=1)


def _pywt_wavedec2(x, wavelet, levels):
    import warnings
    with warnings.catch_warnings():  # levels beyond dwt_max_level: fine for periodization
        warnings.simplefilter("ignore")
        return pywt.wavedec2(_mirror(x), wavelet, mode="periodization", level=levels)


def _squared_pywt(name, target):
    """PyWavelets filter bank of squared taps, each renormalised to sum to
    ``target`` (None: natural squares), built from PyWavelets' own taps."""
    w = pywt.Wavelet(name)

    def sq(f):
        f2 = np.asarray(f) ** 2
        return f2 if target is None else f2 * (target / f2.sum())

    return pywt.Wavelet(name + "^2", filter_bank=[sq(w.dec_lo), sq(w.dec_hi), sq(w.rec_lo),
                                                   sq(w.rec_hi)])


@pytest.mark.parametrize("name", list(MIRROR_PYWT))
@pytest.mark.parametrize("shape", [(17, 17), (33, 33), (33, 17), (9, 65)])
def test_full_depth_analysis_equals_pywavelets_wavedec2(name, shape):
    """Every level of the multi-level DWT (our recursion, not theirs applied
    to our scales) against ``pywt.wavedec2``; bands W0 = cV, W1 = cH, W2 = cD."""
    pw, sign, tol = MIRROR_PYWT[name]
    x = np.random.default_rng(sum(shape)).normal(size=shape)
    levels = min(wv.axis_levels(shape[0]), wv.axis_levels(shape[1]))
    ours = wv.dwt2(x, name, levels=levels)
    theirs = _pywt_wavedec2(x, pw, levels)
    h, w = ours.approx.shape
    np.testing.assert_allclose(ours.approx, theirs[0][:h, :w], atol=tol)
    for k in range(1, levels + 1):
        ch, cv, cd = theirs[-k]
        # one high-pass in W0 and W1, two in W2: signs sign, sign, sign^2
        for band, ref, sg in zip(ours.details[k - 1], (cv, ch, cd), (sign, sign, sign * sign)):
            np.testing.assert_allclose(band, sg * ref[:band.shape[0], :band.shape[1]], atol=tol)


@pytest.mark.parametrize("name", list(MIRROR_PYWT))
@pytest.mark.parametrize("target", [None, 2 ** -0.5, 1.05])
def test_squared_filter_variances_equal_pywavelets_with_squared_taps(name, target):
    """Eq. 10's Delta^2 = <var, Psi^2> (and Eq. 9's scale variances) by
    PyWavelets with a filter bank of squared, renormalised taps."""
    pw, _, tol = MIRROR_PYWT[name]
    var = np.random.default_rng(5).uniform(0.1, 2.0, (33, 33))
    ours = wv.dwt2_variance(var, name, lo_sum=target, hi_sum=target)
    theirs = _pywt_wavedec2(var, _squared_pywt(pw, target), ours.levels)
    np.testing.assert_allclose(ours.approx, theirs[0][:1, :1], rtol=tol)
    for k in range(1, ours.levels + 1):
        ch, cv, cd = theirs[-k]
        for band, ref in zip(ours.details[k - 1], (cv, ch, cd)):
            np.testing.assert_allclose(band, ref[:band.shape[0], :band.shape[1]], rtol=tol)
            assert (band > 0).all()


@pytest.mark.parametrize("name", list(MIRROR_PYWT))
def test_full_depth_synthesis_equals_pywavelets_waverec2(name):
    """Synthesis of an arbitrary (mirror-symmetric) pyramid: PyWavelets'
    coefficients of a mirrored image, each band scaled per level, through our
    idwt2 and through ``pywt.waverec2``."""
    pw, sign, tol = MIRROR_PYWT[name]
    x = np.random.default_rng(11).normal(size=(33, 33))
    levels = wv.max_levels(x.shape)
    theirs = _pywt_wavedec2(x, pw, levels)
    gains = np.linspace(0.1, 1.7, levels)  # level k (1 = finest) scaled by gains[k - 1]
    scaled = [theirs[0]] + [tuple(gains[levels - 1 - i] * b for b in d) for i, d in enumerate(theirs[1:])]
    want = pywt.waverec2(scaled, pw, mode="periodization")[:33, :33]
    ours = wv.dwt2(x, name)
    pyr = wv.Pyramid(ours.approx, [tuple(gains[k] * b for b in d) for k, d in enumerate(ours.details)],
                     ours.axes)
    np.testing.assert_allclose(wv.idwt2(pyr, name), want, atol=10 * tol)
    assert np.abs(wv.idwt2(pyr, name) - x).max() > 0.1  # the scaling did change the image

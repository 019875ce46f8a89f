"""The kept-noise term of the error maps (core/errormap.py, Eq. 2 of its notes).

* closed forms: the identity keeps all the noise (the pooled variance), and a
  reconstruction that keeps a fraction rho of each pixel's noise is estimated
  at rho^2 v, the error measured against the truth;
* a perfect denoiser keeps none;
* row bands and threads give the same bits as one whole-frame pass;
* hostile input (NaN, Inf, negative variances) gives finite, non-negative maps;
* LP and RHF: the term changes the error map only, never the image or the
  sampler's map.
"""
import numpy as np
import pytest

from core import errormap, lp, parallel, rhf
from core.buffers import Buffers


def _noisy(h=96, w=96, v=0.04, seed=0):
    rng = np.random.default_rng(seed)
    t = np.full((h, w, 3), 0.5)
    n = rng.normal(0.0, np.sqrt(v), (h, w, 3))
    return t, n, np.full((h, w, 3), v)


def test_the_identity_keeps_all_the_noise():
    """f = y: R = 0, rho = 1, N_i = v_i (each pixel its own variance)."""
    rng = np.random.default_rng(1)
    y = rng.random((40, 50, 3))
    var = rng.random((40, 50, 3)) * 0.1
    got = errormap.retained_noise(y, y, var, radius=2)
    np.testing.assert_allclose(got, var.mean(-1), rtol=1e-12)


def test_a_uniform_fraction_is_read_exactly_from_the_residual():
    """f - y = -(1 - rho) n exactly on every pixel of a window whose noise has
    the variance given: then R = (1 - rho)^2 V and N = rho^2 v, to rounding."""
    rng = np.random.default_rng(6)
    var = 0.02 + 0.01 * rng.random((30, 30, 3))
    sign = np.where(rng.random((30, 30, 3)) < 0.5, -1.0, 1.0)
    n = sign * np.sqrt(var)                     # |n|^2 = v exactly
    t = np.full((30, 30, 3), 0.4)
    for rho in (0.0, 0.25, 0.6, 1.0):
        got = errormap.retained_noise(t + rho * n, t + n, var)
        np.testing.assert_allclose(got, (rho * rho * var).mean(-1), rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("rho", [0.0, 0.3, 0.7, 1.0])
def test_a_kept_fraction_rho_is_estimated_at_rho_squared_v(rho):
    """f = t + rho n (+ a wide smoother's negligible output noise): the true
    squared error is rho^2 v; the estimate's frame mean matches the
    realised error within a few percent of v."""
    t, n, var = _noisy(v=0.04)
    f = t + rho * n
    y = t + n
    est = errormap.retained_noise(f, y, var).mean()
    true = ((f - t) ** 2).mean()
    assert abs(est - true) < 0.03 * 0.04, (rho, est, true)


def test_a_perfect_denoiser_keeps_almost_nothing():
    t, n, var = _noisy(v=0.04)
    est = errormap.retained_noise(t, t + n, var)
    # R pools 25 draws: sqrt(R / V) = 1 + d / 2, d of spread sqrt(2 / 25), so
    # rho^2, the positive part of (-d / 2)^2, averages ~ E[d^2] / 8 = 1 / 100
    assert est.mean() < 0.03 * 0.04
    assert est.max() < 0.25 * 0.04


def test_bias_in_the_residual_is_left_to_the_method():
    """R > V (the residual holds bias, not kept noise): the term is 0."""
    t, n, var = _noisy(v=0.01)
    f = t + 1.0                       # biased, noise-free: R = v + 1 > V
    assert np.all(errormap.retained_noise(f, t + n, var) == 0.0)


def test_bands_and_threads_give_the_same_bits():
    rng = np.random.default_rng(2)
    y = rng.random((301, 67, 3))
    f = y * rng.random((301, 67, 3))
    var = rng.random((301, 67, 3)) * 0.2
    var[5, 5] = np.inf
    whole = errormap.retained_noise(f, y, var, rows=10_000)
    for rows in (1, 7, 64, 300):
        assert np.array_equal(errormap.retained_noise(f, y, var, rows=rows), whole)
    big_y = np.tile(y, (2, 8, 1))                      # above the threads' threshold
    big_f, big_v = np.tile(f, (2, 8, 1)), np.tile(var, (2, 8, 1))
    outs = []
    for threads in (1, 2, 3):
        parallel.set_threads(threads)
        try:
            outs.append(errormap.retained_noise(big_f, big_y, big_v, rows=37))
        finally:
            parallel.set_threads(None)
    assert all(np.array_equal(o, outs[0]) for o in outs)
    assert np.array_equal(outs[0], errormap.retained_noise(big_f, big_y, big_v, rows=100_000))


def test_hostile_input_gives_finite_non_negative_maps():
    rng = np.random.default_rng(3)
    y = rng.random((20, 30, 3))
    f = y.copy()
    var = rng.random((20, 30, 3))
    y[0, 0] = np.nan
    f[1, 1] = np.inf
    f[2, 2] = 1e200                                    # squares overflow
    var[3, 3] = -1.0
    var[4, 4] = np.nan
    var[5, 5] = np.inf
    var[6, 6] = 1e308
    out = errormap.retained_noise(f, y, var)
    assert out.shape == (20, 30)
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    none = errormap.retained_noise(np.full((4, 4, 3), np.nan), np.zeros((4, 4, 3)), np.ones((4, 4, 3)))
    assert np.array_equal(none, np.zeros((4, 4)))
    with pytest.raises(ValueError):
        errormap.retained_noise(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)), np.ones((4, 4, 3)))


def _buffers(h=48, w=48, groups=4, seed=4):
    """Noisy colour with a noisy feature that follows it (defocus-like)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / float(w)
    truth = np.stack([0.2 + 0.6 * xx, 0.3 + 0.4 * yy, 0.5 + 0.0 * xx], -1)
    colors, feats = [], []
    for g in range(groups):
        noise = rng.normal(0.0, 0.15, (h, w, 1))
        colors.append(truth + noise)
        feats.append({"albedo": np.clip(truth + 0.5 * noise, 0, None),
                      "normal": np.dstack([0 * xx, 0 * xx, 1 + 0 * xx]),
                      "depth": (1 + 0 * xx)[..., None]})
    return Buffers.from_subsets(colors, [2] * groups, feats)


@pytest.mark.parametrize("mod", [lp, rhf], ids=["lp", "rhf"])
def test_the_term_changes_the_error_map_only(mod):
    buf = _buffers()
    on = mod.reconstruct(buf)
    off = mod.reconstruct(buf, mod.Params(kept_noise=False))
    assert np.array_equal(on.image, off.image)
    kept = errormap.retained_noise(on.image, buf.color.mean, buf.calibrated_variance())
    np.testing.assert_allclose(on.error, off.error + kept, rtol=1e-12, atol=0)
    assert kept.max() > 0                    # the feature follows the noise: some is kept
    m_on = mod.sample_map(buf, on, 5000, None, {})
    m_off = mod.sample_map(buf, off, 5000, None, {})
    assert np.array_equal(m_on, m_off)


@pytest.mark.parametrize("mod", [lp, rhf], ids=["lp", "rhf"])
def test_denoise_adds_the_term_from_the_given_variance(mod):
    t, n, var = _noisy(h=32, w=32, v=0.02, seed=5)
    y = t + n
    on = mod.denoise(y, var)
    off = mod.denoise(y, var, params={"kept_noise": False})
    assert np.array_equal(on.image, off.image)
    np.testing.assert_allclose(on.error, off.error + errormap.retained_noise(on.image, y, var), rtol=1e-12)


def test_map_result_is_the_reconstruction_without_the_kept_noise():
    """lp and rhf hand the sampler a reconstruction without the kept noise:
    the same image, the same sample map, the papers' error map."""
    from core import lp, rhf
    rng = np.random.default_rng(11)
    h, w = 24, 28
    yy, xx = np.mgrid[0:h, 0:w] / float(w)
    truth = np.stack([0.2 + 0.6 * xx, 0.3 + 0.4 * yy, 0.5 + 0.3 * np.sin(9 * xx)], -1)
    colors, feats = [], []
    for _ in range(4):
        noise = rng.normal(0.0, 0.1, (h, w, 3))
        colors.append(truth + noise)
        feats.append({"albedo": np.clip(truth + 0.5 * noise, 0, None), "normal": np.dstack([0 * xx, yy, 1 + 0 * xx]),
                      "depth": (1 + xx)[..., None]})
    buf = Buffers.from_subsets(colors, [2] * 4, feats)
    for mod in (lp, rhf):
        full = mod.reconstruct(buf, mod.Params())
        quick = mod.map_result(buf, mod.Params())
        plain = mod.reconstruct(buf, mod.Params(kept_noise=False))
        np.testing.assert_array_equal(quick.image, full.image)
        np.testing.assert_array_equal(quick.error, plain.error)
        assert np.all(full.error >= quick.error) and np.any(full.error > quick.error)
        np.testing.assert_array_equal(mod.sample_map(buf, quick, 500, mod.Params(), {}),
                                      mod.sample_map(buf, full, 500, mod.Params(), {}))

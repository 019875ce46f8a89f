"""Tests of core/lp.py and core/lp_solve.py (Moon, Iglesias-Guitian, Yoon, Mitchell 2015)."""
from dataclasses import fields

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core import errormap, lp
from core.buffers import Buffers
from core.lp_solve import Design, ring_fits, ring_layout, spd_solve
from core.method import allocate, params_from_dict


# ----------------------------------------------------------------------------- helpers
def scene_features(h, w, seed=0, texture=True):
    """Smooth depth, a hemisphere-ish normal field and (optionally) a random texture."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    depth = (3.0 + 0.02 * xx + 0.01 * yy)[..., None]
    nrm = np.stack([0.3 * np.sin(0.1 * xx), 0.3 * np.cos(0.13 * yy), np.ones((h, w))], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    if texture:
        alb = 0.2 + 0.6 * rng.random((h, w, 3))
    else:
        alb = np.full((h, w, 3), 0.5)
    return {"depth": depth, "normal": nrm, "albedo": alb}


def make_buffers(truth, feats, sigma=0.2, subsets=4, spp=4, seed=1, sigma_map=None):
    """Buffers from ``subsets`` noisy realisations (each a mean of ``spp``
    samples) of a known truth; features noise-free."""
    rng = np.random.default_rng(seed)
    scale = sigma if sigma_map is None else sigma_map[..., None]
    colors = [truth + rng.normal(0.0, 1.0, truth.shape) * scale / np.sqrt(spp) for _ in range(subsets)]
    return Buffers.from_subsets(colors, [spp] * subsets, [feats] * subsets)


def mse(a, b):
    return float(((a - b) ** 2).mean())


def rls_recursion(z, y, w, beta0, delta):
    """Eq. 3 of Moon et al. 2015, pixel by pixel: z (K, p), y (K, C).
    Returns the model after each pixel (pixels with w = 0 are skipped)."""
    k, p = z.shape
    pmat = np.eye(p) / delta
    beta = np.zeros((p, y.shape[1]))
    beta[0] = beta0
    out = []
    for i in range(k):
        if w[i] > 0:
            zi = z[i]
            pz = pmat @ zi
            gain = pz / (1.0 + zi @ pz)
            pmat = pmat - np.outer(gain, zi @ pmat)
            beta = beta + np.outer(gain, y[i] - beta.T @ zi)
        out.append(beta.copy())
    return out


def batch_ls(z, y, beta0, delta):
    """argmin delta ||beta - beta(0)||^2 + ||z beta - y||^2 by lstsq of the
    augmented system (the cost RLS minimises)."""
    p = z.shape[1]
    prior = np.zeros((p, y.shape[1]))
    prior[0] = beta0
    a = np.vstack([np.sqrt(delta) * np.eye(p), z])
    b = np.vstack([np.sqrt(delta) * prior, y])
    return np.linalg.lstsq(a, b, rcond=None)[0]


def random_rings(n, radius, p, c=3, seed=0, holes=True):
    rng = np.random.default_rng(seed)
    k = (2 * radius + 1) ** 2
    z = rng.normal(size=(n, p, k))
    z[:, 0] = 1.0
    z[:, 1:, 0] = 0.0                                   # the centre: x_c - x_c = 0
    y = rng.normal(size=(n, c, k)) + 3.0
    w = np.ones((n, k))
    if holes:
        w[rng.random((n, k)) < 0.15] = 0.0
        w[:, 0] = 1.0
    s = 0.01 * rng.random((n, c, k))
    beta0 = y[:, :, 0].copy()
    xi0 = 0.05 * np.ones((n, c))
    return z, y, w, s, beta0, xi0


# ------------------------------------------------------------------ linear algebra core
def test_ring_layout_orders_pixels_ring_by_ring():
    dy, dx, ring, starts = ring_layout(4)
    assert len(dy) == 81 and (dy[0], dx[0]) == (0, 0)
    assert np.array_equal(ring, np.maximum(np.abs(dy), np.abs(dx)))
    assert np.all(np.diff(ring) >= 0)
    for r in range(1, 5):
        assert starts[r + 1] - starts[r] == 8 * r
        assert np.all(ring[starts[r]:starts[r + 1]] == r)
    assert len({(a, b) for a, b in zip(dy, dx)}) == 81


def test_spd_solve_matches_lapack():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(50, 30, 6))
    a = np.swapaxes(x, 1, 2) @ x + 1e-3 * np.eye(6)
    b = rng.normal(size=(50, 6, 4))
    assert np.allclose(spd_solve(a, b), np.linalg.solve(a, b), rtol=1e-10, atol=1e-12)


def test_rls_equals_recursion_and_batch_least_squares():
    """Cumulative normal equations per ring == Eq. 3 recursion == batch LS, to 1e-6."""
    radius, p, delta = 4, 5, 1e-3
    z, y, w, s, beta0, xi0 = random_rings(6, radius, p)
    fits = ring_fits(z, y, w, s, beta0, xi0, radius, delta)
    starts = ring_layout(radius)[3]
    for n in range(z.shape[0]):
        zr, yr = z[n].T, y[n].T
        steps = rls_recursion(zr, yr, w[n], beta0[n], delta)
        for r in range(radius + 1):
            end = starts[r + 1]
            rec = steps[end - 1]
            keep = w[n, :end] > 0
            batch = batch_ls(zr[:end][keep], yr[:end][keep], beta0[n], delta)
            got = fits.beta[r, n]
            assert np.allclose(got, rec, rtol=1e-6, atol=1e-6), (n, r)
            assert np.allclose(got, batch, rtol=1e-6, atol=1e-6), (n, r)
        assert fits.count[radius, n] == w[n].sum()


def test_spd_solve_of_one_system_leaves_its_inputs_alone():
    """The batched Cholesky works in place on copies, also when a stack of one
    system is already contiguous in the solver's layout."""
    a = np.array([[[4.0, 1.0], [1.0, 3.0]]])
    b = np.array([[[1.0], [2.0]]])
    a0, b0 = a.copy(), b.copy()
    x = spd_solve(a, b)
    assert np.array_equal(a, a0) and np.array_equal(b, b0)
    assert np.allclose(a[0] @ x[0], b[0], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n, p", [(1, 1), (1, 4), (2, 10), (7, 5)])
def test_design_built_ring_by_ring_equals_the_whole_design(n, p):
    """ring_fits with a Design (z built one ring at a time from the feature map,
    never stored whole) == ring_fits with the materialised (N, p, K) design,
    including groups of one centre and intercept-only models; Design.predict
    == beta^T z."""
    radius, d = 4, 9
    rng = np.random.default_rng(n * 10 + p)
    k = (2 * radius + 1) ** 2
    t = rng.normal(size=(n, d, p - 1))
    x = rng.normal(size=(n, d, k))
    x[:, :, 0] = 0.0                                    # x_c - x_c
    valid = (rng.random((n, k)) > 0.1).astype(float)
    valid[:, 0] = 1.0
    z = np.concatenate([np.ones((n, 1, k)), np.matmul(np.swapaxes(t, 1, 2), x) * valid[:, None]], axis=1)
    _, y, w, s, beta0, xi0 = random_rings(n, radius, p, seed=p)
    w *= valid
    w[:, 0] = 1.0
    whole = ring_fits(z, y, w, s, beta0, xi0, radius, 1e-3, keep_gram=True)
    design = Design(t, x, valid)
    rings = ring_fits(design, y, w, s, beta0, xi0, radius, 1e-3, keep_gram=True)
    for name in ("beta", "xi_acc", "count", "gram"):
        assert np.allclose(getattr(rings, name), getattr(whole, name), rtol=1e-9, atol=1e-12), name
    beta = rng.normal(size=(n, 3, p))
    assert np.allclose(design.predict(beta), np.matmul(beta, z), rtol=1e-12, atol=1e-12)


def test_rls_with_tiny_delta_is_ordinary_least_squares():
    radius, p = 3, 4
    z, y, w, s, beta0, xi0 = random_rings(3, radius, p, holes=False)
    fits = ring_fits(z, y, w, s, beta0, xi0, radius, delta=1e-10)
    for n in range(3):
        ols = np.linalg.lstsq(z[n].T, y[n].T, rcond=None)[0]
        assert np.allclose(fits.beta[radius, n], ols, rtol=1e-6, atol=1e-6)


def test_first_model_reproduces_the_centre_pixel():
    z, y, w, s, beta0, xi0 = random_rings(4, 2, 3)
    fits = ring_fits(z, y, w, s, beta0, xi0, 2, 1e-3)
    assert np.array_equal(fits.beta[0][:, 0, :], beta0)       # beta(1)^T z_c = y_c (Sec. 7)
    assert np.all(fits.beta[0][:, 1:, :] == 0.0)


@pytest.mark.parametrize("p, margin", [(4, 2.0), (4, 1.0), (8, 2.0), (2, 2.0)])
def test_prediction_error_recursion_matches_explicit_computation(p, margin):
    """Eq. 7 (closed-form leave-one-out at the start window k(r_s)) and Eq. 4-5
    (ring test errors) against refitting explicitly, with and without the
    variance correction; windows before the start are no candidates (+inf)."""
    radius, delta = 4, 1e-3
    z, y, w, s, beta0, xi0 = random_rings(5, radius, p, seed=7 + p)
    starts = ring_layout(radius)[3]
    for corr in (s, np.zeros_like(s)):
        fits = ring_fits(z, y, w, corr, beta0, xi0, radius, delta, margin=margin)
        for n in range(z.shape[0]):
            zr, yr, sr = z[n].T, y[n].T, corr[n].T
            assert np.allclose(fits.xi_acc[0, n], xi0[n])
            # the start: the first ring with >= margin * p usable pixels
            counts = [w[n, :starts[r + 1]].sum() for r in range(radius + 1)]
            rs = next(r for r in range(1, radius + 1) if counts[r] >= margin * p)
            assert fits.start[n] == rs
            assert np.all(np.isinf(fits.xi_acc[1:rs, n]))
            # Eq. 7: leave each pixel of k(r_s) out, refit (with the prior), test it
            ks = starts[rs + 1]
            loo = np.zeros(y.shape[1])
            for i in range(ks):
                if w[n, i] == 0:
                    continue
                keep = (w[n, :ks] > 0) & (np.arange(ks) != i)
                b = batch_ls(zr[:ks][keep], yr[:ks][keep], beta0[n], delta)
                loo += (zr[i] @ b - yr[i]) ** 2 - sr[i]
            assert np.allclose(fits.xi_acc[rs, n], loo, rtol=1e-8, atol=1e-10)
            # Eq. 4-5: model of k(r-1) tested on the 8r new pixels
            acc = loo
            for r in range(rs + 1, radius + 1):
                lo, hi = starts[r], starts[r + 1]
                keep = w[n, :lo] > 0
                b = batch_ls(zr[:lo][keep], yr[:lo][keep], beta0[n], delta)
                ring = w[n, lo:hi] > 0
                acc = acc + (((zr[lo:hi] @ b - yr[lo:hi]) ** 2 - sr[lo:hi]) * ring[:, None]).sum(0)
                assert np.allclose(fits.xi_acc[r, n], acc, rtol=1e-8, atol=1e-9), (n, r)
            # the effective parameter count tr((delta I + X^T X)^-1 X^T X) and the variance sums
            for r in range(radius + 1):
                keep = w[n, :starts[r + 1]] > 0
                x = zr[:starts[r + 1]][keep]
                a = x.T @ x
                dof = np.trace(np.linalg.solve(delta * np.eye(p) + a, a))
                assert fits.dof[r, n] == pytest.approx(dof, rel=1e-9, abs=1e-9)
                assert np.allclose(fits.svar[r, n], sr[:starts[r + 1]][keep].sum(0), rtol=1e-12)
                assert np.allclose(fits.svar2[r, n], (sr[:starts[r + 1]][keep] ** 2).sum(0), rtol=1e-12)


def test_start_ring_needs_margin_times_the_unknowns():
    """start_rings: first ring with count >= margin p; else R if determined; else R + 1."""
    from core.lp_solve import start_rings
    count = np.array([[1, 1, 1, 1], [9, 9, 4, 3], [25, 25, 9, 5], [49, 30, 16, 6]], float)
    assert start_rings(count, 4).tolist() == [1, 1, 2, 3]
    assert start_rings(count, 10).tolist() == [2, 2, 3, 4]
    assert start_rings(count, 3, margin=1.0).tolist() == [1, 1, 1, 1]
    assert start_rings(count[:1], 3).tolist() == [1, 1, 1, 1]      # R = 0: only k(0)


# ------------------------------------------------------------------------- features
def _window_features(h, w, feats, radius):
    """Gather the (1, D, K) feature window around the image centre as lp does."""
    dy, dx, _, _ = ring_layout(radius)
    cy, cx = h // 2, w // 2
    cols = [dy.astype(float), dx.astype(float)]
    groups, start = [], 2
    for name in ("depth", "normal", "albedo"):
        f = feats[name][cy + dy, cx + dx]
        cols.extend(f.T)
        groups.append((start, start + f.shape[1]))
        start += f.shape[1]
    return np.array(cols)[None], groups


def test_tsvd_drops_constant_features_and_keeps_informative_ones():
    h = w = 21
    radius = 9
    flat = scene_features(h, w, texture=False)
    flat["normal"] = np.broadcast_to([0.0, 0.0, 1.0], (h, w, 3)).copy()
    flat["depth"] = np.full((h, w, 1), 4.0)
    f, groups = _window_features(h, w, flat, radius)
    valid = np.ones((1, f.shape[2]))
    t, rank, sigma, _ = lp.feature_transform(f, valid, np.zeros((1, 3)), groups, radius)
    assert rank[0] == 2                                   # only the screen plane
    assert np.all(t[0][:, 2:] == 0.0)
    textured = scene_features(h, w, texture=True)
    textured["normal"], textured["depth"] = flat["normal"], flat["depth"]
    f, groups = _window_features(h, w, textured, radius)
    t, rank, sigma, tol = lp.feature_transform(f, valid, np.zeros((1, 3)), groups, radius)
    assert rank[0] == 5                                   # + three albedo directions
    assert np.all(sigma[0, :5] > tol[0]) and np.all(sigma[0, 5:] <= tol[0])
    # the same texture declared very noisy is dropped (threshold 2 ||E||_2)
    t, rank, _, _ = lp.feature_transform(f, valid, np.array([[0.0, 0.0, 1e3]]), groups, radius)
    assert rank[0] == 2


def test_box_sum_matches_explicit_window_sums():
    rng = np.random.default_rng(0)
    plane = rng.random((7, 9))
    r = 2
    padded = np.pad(plane, r)
    got = lp._box_sum(padded, r)[r:-r, r:-r]
    want = np.array([[padded[i:i + 2 * r + 1, j:j + 2 * r + 1].sum() for j in range(9)] for i in range(7)])
    assert np.allclose(got, want)


# ------------------------------------------------------------------ reconstruction
def test_linear_truth_windows_grow_to_the_maximum_and_error_drops():
    """Truth linear in the features, variances estimated from 4 subsets: the
    centres' windows are k(R) in >= 80 % of the channels (measured 47 / 54)
    and none has 1 <= r <= 3 (the old selection: bimodal, [108, 98, 3, 1,
    1, 2, 3, 2, 11, 134]); a few r = 0 stay where the 3-dof variance estimates
    around the centre came out low (a calibrated variance removes those; with
    the known variance: tests/core/test_lp_windows.py)."""
    h, w = 48, 48
    feats = scene_features(h, w, seed=2)
    truth = 0.7 * feats["albedo"] + 0.05 * feats["depth"]           # linear in the features
    buf = make_buffers(truth, feats, sigma=0.3, seed=3)
    res = lp.reconstruct(buf)
    fit = res.fit
    r = fit.center_radius
    assert np.mean(r == 9) >= 0.8
    assert not np.any((r >= 1) & (r <= 3))
    assert np.mean(r == 0) <= 0.15
    assert mse(res.image, truth) < 0.05 * mse(buf.color.mean, truth)
    assert 0.0 < res.info["center_fraction"] < 0.2
    assert res.info["center_fraction"] == pytest.approx(len(fit.centers) / (h * w))


def test_windows_shrink_at_an_edge_the_features_do_not_explain():
    h, w = 40, 64
    feats = scene_features(h, w, seed=4)
    xx = np.arange(w)[None, :, None]
    truth = (0.6 * feats["albedo"]) * np.where(xx < 32, 1.0, 0.15)  # a shadow edge at x = 32
    buf = make_buffers(truth, feats, sigma=0.1, seed=5)
    fit = lp.reconstruct(buf).fit
    cx = fit.centers[:, 1]
    dist = np.abs(cx - 31.5)                                   # to the edge, between columns 31 and 32
    near, far = dist < 4, dist > 12
    # a window that crosses the edge is biased: centres near it keep theirs inside
    assert np.mean(fit.center_radius[near] < 4) >= 0.95
    assert np.mean(fit.center_radius[far] == 9) >= 0.8
    # centres are denser near the edge
    assert np.mean(near) > 2 * 8 / w


def test_step_in_a_feature_is_kept_sharp():
    """A texture step that the albedo feature explains stays sharp although
    windows stay large."""
    h, w = 40, 40
    feats = scene_features(h, w, texture=False)
    xx = np.arange(w)[None, :]
    feats["albedo"] = np.where((xx < 20)[..., None], 0.1, 0.9) * np.ones((h, w, 3))
    truth = 0.8 * feats["albedo"]
    buf = make_buffers(truth, feats, sigma=0.2, seed=6)
    res = lp.reconstruct(buf)
    edge = slice(17, 23)
    assert mse(res.image[:, edge], truth[:, edge]) < 0.2 * mse(buf.color.mean[:, edge], truth[:, edge])
    assert res.fit.radius.mean() > 4


def test_zero_variance_input_is_returned_unchanged():
    h, w = 23, 29
    feats = scene_features(h, w, seed=8)
    rng = np.random.default_rng(9)
    img = rng.random((h, w, 3)) * 5 - 1                 # arbitrary, not linear, negatives
    buf = Buffers.from_subsets([img] * 3, [4] * 3, [feats] * 3)
    res = lp.reconstruct(buf)
    # every pixel keeps k(0); overlapping larger models get weight ~xi0 / xi = 0
    np.testing.assert_allclose(res.image, img, rtol=1e-12, atol=1e-12)
    assert np.all(res.error >= 0.0) and np.all(res.error < 1e-20)


def test_estimated_error_correlates_with_true_error():
    h, w = 48, 64
    feats = scene_features(h, w, seed=10)
    xx = np.arange(w)[None, :]
    truth = 0.6 * feats["albedo"] * np.where((xx < 40)[..., None], 1.0, 0.3)
    sigma = 0.05 + 0.6 * (np.arange(h)[:, None] / h) * np.ones((1, w))   # noise grows downwards
    buf = make_buffers(truth, feats, seed=11, sigma_map=sigma)
    res = lp.reconstruct(buf)
    true_err = ((res.image - truth) ** 2).mean(axis=-1)
    blocks = lambda a: a.reshape(h // 8, 8, w // 8, 8).mean(axis=(1, 3)).ravel()
    est, true = blocks(res.error), blocks(true_err)
    assert np.corrcoef(est, true)[0, 1] > 0.45
    # errors span orders of magnitude: the pattern (log scale) matches closely
    assert np.corrcoef(np.log(est), np.log(true))[0, 1] > 0.75


def test_accumulation_matches_explicit_per_centre_predictions():
    """Eq. 1 predictions of every centre over its window (bounded below by
    min(0, window minimum)), with the blend's mean offset (the share-weighted
    mean residual, at most ``OFFSET_LIMIT`` standard errors), blended with
    the weights ``|cos(pi dy / (2 (r + 1))) cos(pi dx / (2 (r + 1)))|^3 / xi``,
    the pixel's own value where it lies beyond ``OUTLIER_SIGMA`` typical
    standard deviations (``f + (y - f) max(0, 1 - s / (y - f)^2)``), and the per-pixel error,
    Sec. 5.2 reduction and sampling map (``rho = Delta xi / (f^2 +
    epsilon)``), recomputed centre by centre, pixel by pixel, from the models
    alone."""
    h, w = 17, 13
    feats = scene_features(h, w, seed=12)
    truth = 0.5 * feats["albedo"] + 0.2 * feats["normal"][..., 2:3]
    buf = make_buffers(truth, feats, sigma=0.3, seed=13)
    buf.n[3, 4] = 9.0                                    # uneven sample counts
    params = lp.Params(radius=3)
    color, var, fts, fvars = lp._inputs(buf)
    fit = lp.fit(color, var, fts, fvars, buf.n, params, keep_models=True)
    raw = np.concatenate([feats["depth"], feats["normal"], feats["albedo"]], axis=-1)
    pred = np.zeros((h, w, 3))
    err = np.zeros((h, w, 3))
    dxi = np.zeros((h, w, 3))
    wsum = np.zeros((h, w, 3))
    cnt = np.zeros((h, w, 3))
    m = fit.models
    big = params.radius
    typical = np.stack([np.median(np.pad(var[..., c], 1, mode="edge")[
        np.arange(h)[:, None, None, None] + np.arange(3)[None, None, :, None],
        np.arange(w)[None, :, None, None] + np.arange(3)[None, None, None, :]].reshape(h, w, 9), axis=-1)
        for c in range(3)], axis=-1)

    def window(i, c):
        cy, cx = fit.centers[i]
        r = fit.center_radius[i, c]
        for yy in range(max(cy - r, 0), min(cy + r + 1, h)):
            for xx in range(max(cx - r, 0), min(cx + r + 1, w)):
                x = np.concatenate([[yy - cy, xx - cx], raw[yy, xx] - raw[cy, cx]])
                zv = np.concatenate([[1.0], x @ m["transform"][i]])
                tap = abs(np.cos(np.pi / 2 * (yy - cy) / (r + 1.0)) * np.cos(np.pi / 2 * (xx - cx) / (r + 1.0))) ** 3
                wt = tap / min(max(fit.center_error[i, c], 1e-30), 1e30)
                yield yy, xx, wt, m["beta"][i, c] @ zv

    for i in range(len(fit.centers)):
        for c in range(3):
            for yy, xx, wt, _ in window(i, c):
                wsum[yy, xx, c] += wt
    offset = np.zeros((len(fit.centers), 3))
    for i in range(len(fit.centers)):
        for c in range(3):
            num = den = k = 0.0
            for yy, xx, wt, f in window(i, c):
                a = wt / wsum[yy, xx, c]
                num, den, k = num + a * (color[yy, xx, c] - f), den + a, k + 1
            cap = lp.OFFSET_LIMIT * np.sqrt(typical[tuple(fit.centers[i])][c] / k)
            offset[i, c] = np.clip(num / den, -cap, cap)
    assert np.allclose(m["offset"], offset, rtol=1e-9, atol=1e-12)
    assert np.any(np.abs(offset) > 0)
    for i, (cy, cx) in enumerate(fit.centers):
        win = color[max(cy - big, 0):cy + big + 1, max(cx - big, 0):cx + big + 1]
        low = np.minimum(win.reshape(-1, 3).min(axis=0), 0.0)
        for c in range(3):
            xi = fit.center_error[i, c]
            for yy, xx, wt, f in window(i, c):
                pred[yy, xx, c] += wt * max(f + offset[i, c], low[c])
                err[yy, xx, c] += wt * xi
                dxi[yy, xx, c] += wt * xi * buf.n[yy, xx] ** (-4.0 / (fit.center_rank[i] + 4))
                cnt[yy, xx, c] += 1
    assert np.all(cnt > 0)
    # the pixel's own value where it lies beyond OUTLIER_SIGMA typical deviations (inverse-error blend)
    blend = pred / wsum
    image = blend.copy()
    for yy, xx, c in np.ndindex(h, w, 3):
        res_ = color[yy, xx, c] - blend[yy, xx, c]
        if res_ ** 2 > lp.OUTLIER_SIGMA ** 2 * typical[yy, xx, c]:
            image[yy, xx, c] += res_ * max(0.0, 1.0 - var[yy, xx, c] / res_ ** 2)
    assert np.allclose(fit.image, image, rtol=1e-9, atol=1e-12)
    # (the weighted error sums are float32: 1e-6)
    assert np.allclose(fit.error, (err / wsum).mean(-1), rtol=1e-6, atol=1e-15)
    assert np.allclose(fit.delta_error, dxi / wsum, rtol=1e-6, atol=1e-15)
    # Sec. 5.2's map from these independent sums
    f = image
    rho = (dxi / wsum / (f * f + params.epsilon)).mean(axis=-1)
    res = lp.reconstruct(buf, params)
    assert np.array_equal(lp.sample_map(buf, res, 4 * h * w, params, {}), allocate(rho, 4 * h * w))
    # P is the RLS inverse covariance: symmetric positive definite
    pm = m["P"]
    assert np.allclose(pm, np.swapaxes(pm, -1, -2))
    assert np.all(np.linalg.eigvalsh(pm[..., :1, :1]) > 0)


def test_chunking_does_not_change_the_result():
    h, w = 30, 37
    feats = scene_features(h, w, seed=14)
    truth = 0.6 * feats["albedo"] * (1 + 0.5 * np.sin(np.arange(w) / 3.0))[None, :, None]
    buf = make_buffers(truth, feats, sigma=0.2, seed=15)
    a = lp.reconstruct(buf, lp.Params(chunk=16))
    b = lp.reconstruct(buf, lp.Params(chunk=4096))
    assert np.allclose(a.image, b.image, rtol=1e-12, atol=1e-12)
    assert np.allclose(a.error, b.error, rtol=1e-6, atol=1e-15)         # float32 error sums


def test_automatic_chunk_follows_the_image_size():
    assert [lp.auto_chunk(p) for p in (1, 40 * 40, 256 * 256, 512 * 512, 4096 * 4096)] == \
        [32, 32, 64, 256, 256]
    h, w = 24, 20
    feats = scene_features(h, w, seed=11)
    buf = make_buffers(0.6 * feats["albedo"], feats, sigma=0.2, seed=12)
    a = lp.reconstruct(buf)                       # chunk 0: automatic (32)
    b = lp.reconstruct(buf, lp.Params(chunk=32))
    np.testing.assert_array_equal(a.image, b.image)


def test_chunk_size_does_not_change_the_result_at_any_rank():
    """Centres are sorted by model size inside a chunk and their design is
    built ring by ring: any chunk size (1 centre, a few, all) gives the same
    models and images to rounding, with every rank present and missing pixels."""
    h, w = 36, 44
    feats = scene_features(h, w, seed=42)
    left, top = np.arange(w)[None, :, None] < 15, np.arange(h)[:, None, None] < 12
    feats["albedo"] = np.where(left, 0.5, feats["albedo"])            # ranks from 2 to 8
    feats["normal"] = np.where(top, [0.0, 0.0, 1.0], feats["normal"])
    feats["depth"] = np.where(top & left, 3.0, feats["depth"])
    truth = 0.6 * feats["albedo"] * (1 + 0.5 * np.sin(np.arange(w) / 3.0))[None, :, None]
    buf = make_buffers(truth, feats, sigma=0.2, seed=44)
    buf.n[5:8, 30:33] = 0
    buf.k[5:8, 30:33] = 0
    buf.color.mean[5:8, 30:33] = np.nan
    color, var, fts, fvars = lp._inputs(buf)
    fits = [lp.fit(color, var, fts, fvars, buf.n, lp.Params(chunk=c, radius=5), keep_models=True)
            for c in (16, 37, 65536)]
    a = fits[0]
    assert len(np.unique(a.center_rank)) >= 3
    for b in fits[1:]:
        assert np.array_equal(a.centers, b.centers)
        assert np.array_equal(a.center_radius, b.center_radius)
        assert np.array_equal(a.center_rank, b.center_rank)
        assert np.allclose(a.center_error, b.center_error, rtol=1e-9, atol=1e-15)
        assert np.allclose(a.image, b.image, rtol=1e-9, atol=1e-12)
        assert np.allclose(a.error, b.error, rtol=1e-6, atol=1e-15)
        for key in ("beta", "P", "transform"):
            assert np.allclose(a.models[key], b.models[key], rtol=1e-9, atol=1e-12), key


def test_literal_error_estimate_prefers_smaller_windows():
    h, w = 40, 40
    feats = scene_features(h, w, seed=16)
    truth = 0.7 * feats["albedo"]
    buf = make_buffers(truth, feats, sigma=0.3, seed=17)
    corrected = lp.reconstruct(buf, lp.Params(variance_corrected=True))
    literal = lp.reconstruct(buf, lp.Params(variance_corrected=False))
    assert np.all(np.isfinite(literal.image)) and np.all(literal.error >= 0)
    assert literal.fit.radius.mean() < corrected.fit.radius.mean()
    assert literal.info["center_fraction"] > corrected.info["center_fraction"]
    assert mse(literal.image, truth) < mse(buf.color.mean, truth)


def test_single_subset_has_infinite_variance_and_still_filters():
    h, w = 40, 40
    feats = scene_features(h, w, seed=18)
    truth = 0.7 * feats["albedo"]
    buf = make_buffers(truth, feats, sigma=0.3, subsets=1, spp=4, seed=19)
    assert np.all(np.isinf(buf.variance_of_mean()))
    res = lp.reconstruct(buf)
    assert np.all(np.isfinite(res.image)) and np.all(np.isfinite(res.error))
    assert np.all(res.fit.center_radius > 0)   # xi(k(0)) = inf is never chosen
    assert mse(res.image, truth) < 0.3 * mse(buf.color.mean, truth)


def test_pixels_without_samples_are_predicted_from_their_neighbours():
    h, w = 32, 32
    feats = scene_features(h, w, seed=20)
    truth = 0.7 * feats["albedo"] + 0.1
    buf = make_buffers(truth, feats, sigma=0.2, seed=21)
    holes = np.zeros((h, w), bool)
    holes[10:13, 5:9] = True
    holes[25, 25] = True
    buf.n[holes] = 0
    buf.k[holes] = 0
    buf.color.mean[holes] = np.nan
    res = lp.reconstruct(buf)
    assert np.all(np.isfinite(res.image))
    assert mse(res.image[holes], truth[holes]) < 0.01


def test_firefly_stays_local_and_finite():
    """A single 1e6 sample: output finite; it changes the models whose window
    holds it (radius R) and, through coverage, at most one more R per pass;
    the blend's mean offsets (which read the blend weights over a model's
    window, set by the models overlapping it) reach two more R."""
    h, w = 64, 64
    feats = scene_features(h, w, seed=22)
    truth = 0.7 * feats["albedo"]
    params = lp.Params(radius=3)
    clean = make_buffers(truth, feats, sigma=0.2, seed=23)
    rng = np.random.default_rng(23)
    colors = [truth + rng.normal(0.0, 1.0, truth.shape) * 0.2 / 2 for _ in range(4)]
    colors[2][32, 32] = 1e6
    fire = Buffers.from_subsets(colors, [4] * 4, [feats] * 4)
    a, b = lp.reconstruct(clean, params), lp.reconstruct(fire, params)
    assert np.all(np.isfinite(b.image)) and np.all(np.isfinite(b.error))
    reach = (b.info["passes"] + 3) * 3
    yy, xx = np.mgrid[0:h, 0:w]
    far = np.maximum(np.abs(yy - 32), np.abs(xx - 32)) > reach
    assert far.sum() > 0.5 * h * w
    # equal up to the summation order of overlapping predictions
    assert np.allclose(a.image[far], b.image[far], rtol=1e-12, atol=1e-12)
    assert np.allclose(a.error[far], b.error[far], rtol=1e-6, atol=1e-15)      # float32 error sums


@pytest.mark.parametrize("value", [0.0, 0.37])
def test_constant_images(value):
    """A noise-free constant image comes back unchanged (every model predicts
    the constant; the blend ``sum w c / sum w`` of unequal weights is exact to
    one rounding, 1.1e-16 at 0.37); a noisy one is smoothed."""
    h, w = 24, 24
    feats = scene_features(h, w, seed=24)
    truth = np.full((h, w, 3), value)
    exact = Buffers.from_subsets([truth] * 2, [2, 2], [feats] * 2)
    out = lp.reconstruct(exact).image
    assert np.all(np.abs(out - truth) <= 2.0 * np.spacing(truth + 1e-300))
    noisy = make_buffers(truth, feats, sigma=0.2, seed=25)
    res = lp.reconstruct(noisy)
    assert mse(res.image, truth) < 0.1 * mse(noisy.color.mean, truth)


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (3, 5), (7, 11), (13, 17)])
def test_tiny_and_prime_sized_images_with_windows_larger_than_the_image(shape):
    h, w = shape
    feats = scene_features(h, w, seed=26)
    truth = 0.5 * feats["albedo"]
    buf = make_buffers(truth, feats, sigma=0.2, seed=27)
    res = lp.reconstruct(buf, lp.Params(radius=9))
    assert res.image.shape == (h, w, 3) and res.error.shape == (h, w)
    assert np.all(np.isfinite(res.image)) and np.all(np.isfinite(res.error)) and np.all(res.error >= 0)
    if h * w == 1:
        assert np.array_equal(res.image, buf.color.mean)
    counts = lp.sample_map(buf, res, 50, lp.Params(), {})
    assert counts.sum() == 50 and counts.min() >= 0


_BAD = st.sampled_from([np.nan, np.inf, -np.inf, 1e30, -1e30, -5.0, 1e6])


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(shape=st.sampled_from([(1, 1), (1, 7), (5, 3), (11, 13), (24, 24)]),
       bad=st.lists(st.tuples(st.integers(0, 10 ** 6), _BAD, st.sampled_from(["color", "depth", "normal", "albedo"])),
                    min_size=0, max_size=12),
       subsets=st.integers(1, 3), seed=st.integers(0, 1000), radius=st.sampled_from([1, 2, 4]))
def test_hostile_input_gives_finite_output(shape, bad, subsets, seed, radius):
    h, w = shape
    rng = np.random.default_rng(seed)
    feats = scene_features(h, w, seed=seed)
    truth = 0.5 * feats["albedo"]
    colors, fl = [], []
    for _ in range(subsets):
        c = truth + rng.normal(0, 0.1, truth.shape)
        f = {k: v.copy() for k, v in feats.items()}
        for pos, val, where in bad:
            arr = c if where == "color" else f[where]
            arr.reshape(-1)[pos % arr.size] = val
        colors.append(c)
        fl.append(f)
    buf = Buffers.from_subsets(colors, [3] * subsets, fl)
    with np.errstate(all="ignore"):
        res = lp.reconstruct(buf, lp.Params(radius=radius))
        counts = lp.sample_map(buf, res, 3 * h * w, lp.Params(radius=radius), {})
    assert np.all(np.isfinite(res.image)) and np.all(np.isfinite(res.error)) and np.all(res.error >= 0)
    assert counts.dtype == np.int64 and counts.sum() == 3 * h * w and counts.min() >= 0


# ------------------------------------------------------------------------- sampling
def test_sample_map_is_sec_5_2_and_sums_to_the_budget():
    h, w = 32, 40
    feats = scene_features(h, w, seed=28)
    truth = 0.6 * feats["albedo"]
    buf = make_buffers(truth, feats, sigma=0.3, seed=29)
    params = lp.Params()
    res = lp.reconstruct(buf, params)
    state = {}
    counts = lp.sample_map(buf, res, 4 * h * w, params, state)
    assert counts.dtype == np.int64 and counts.shape == (h, w)
    assert counts.sum() == 4 * h * w and counts.min() >= 0
    # (the map itself is recomputed independently in
    # test_accumulation_matches_explicit_per_centre_predictions)
    assert state["iterations"] == 1
    # without the stored fit, sample_map recomputes it
    from core.method import MethodResult
    assert np.array_equal(lp.sample_map(buf, MethodResult(res.image, res.error, {}), 4 * h * w, params, {}),
                          counts)


def test_sample_map_sends_samples_where_the_error_is():
    h, w = 32, 48
    feats = scene_features(h, w, seed=30)
    truth = 0.5 * feats["albedo"]
    sigma = np.where(np.arange(w)[None, :] < 24, 0.6, 0.05) * np.ones((h, 1))
    buf = make_buffers(truth, feats, seed=31, sigma_map=sigma)
    res = lp.reconstruct(buf)
    counts = lp.sample_map(buf, res, 8 * h * w, lp.Params(), {})
    assert counts[:, :24].sum() > 3 * counts[:, 24:].sum()


def test_more_samples_give_a_smaller_error_estimate():
    h, w = 32, 32
    feats = scene_features(h, w, seed=32)
    truth = 0.5 * feats["albedo"] * (1 + 0.3 * np.sin(np.arange(w) / 2.0))[None, :, None]
    few = make_buffers(truth, feats, sigma=0.4, spp=2, seed=33)
    many = make_buffers(truth, feats, sigma=0.4, spp=64, seed=33)
    ef, em = lp.reconstruct(few), lp.reconstruct(many)
    assert em.error.mean() < ef.error.mean()
    assert mse(em.image, truth) < mse(ef.image, truth)


# --------------------------------------------------------------------------- contract
def test_params_metadata_and_validation():
    assert lp.PASSES == ("normal", "albedo", "depth")
    for f in fields(lp.Params):
        assert f.type in ("int", "float", "bool", "str", int, float, bool, str)
        assert f.metadata["help"] and "min" in f.metadata and "max" in f.metadata
    p = params_from_dict(lp.Params, {"radius": 5, "delta": 0.01, "unknown": 1})
    assert (p.radius, p.delta) == (5, 0.01)
    with pytest.raises(ValueError):
        params_from_dict(lp.Params, {"radius": 99})
    d = lp.Params()
    assert (d.radius, d.delta, d.epsilon) == (9, 1e-3, 1e-3)


def test_denoise_equals_reconstruct():
    h, w = 20, 26
    feats = scene_features(h, w, seed=34)
    truth = 0.5 * feats["albedo"]
    buf = make_buffers(truth, feats, sigma=0.2, seed=35)
    a = lp.reconstruct(buf)
    fv = {k: buf.feature_variance(k) for k in feats}
    b = lp.denoise(buf.color.mean, buf.variance_of_mean(), {k: buf.feature(k) for k in feats},
                   feature_var=fv, n=buf.n, params={"kept_noise": False})
    assert np.array_equal(a.image, b.image)
    # the error map: Eq. 4-7's, plus the kept noise from the Buffers' calibrated variance
    # (denoise has only the variance it is given)
    kept = errormap.retained_noise(a.image, buf.color.mean, buf.calibrated_variance())
    assert np.array_equal(a.error, b.error + kept)
    assert set(a.info) >= {"center_fraction", "centers", "passes", "mean_radius", "mean_rank"}


def test_missing_feature_passes_are_skipped():
    h, w = 24, 24
    feats = scene_features(h, w, seed=36)
    truth = 0.5 * feats["albedo"]
    buf = make_buffers(truth, {"albedo": feats["albedo"]}, sigma=0.2, seed=37)
    res = lp.reconstruct(buf)
    assert np.all(np.isfinite(res.image))
    assert mse(res.image, truth) < 0.2 * mse(buf.color.mean, truth)


def test_noisy_feature_is_dropped_by_the_tsvd():
    """A feature that is pure noise (e.g. depth of field on a texture) carries a
    large variance of its mean; the TSVD threshold drops it and the model shrinks."""
    h, w = 32, 32
    feats = scene_features(h, w, texture=False, seed=38)
    truth = np.full((h, w, 3), 0.4) + 0.01 * np.arange(w)[None, :, None]
    rng = np.random.default_rng(39)
    colors, fl = [], []
    for _ in range(4):
        colors.append(truth + rng.normal(0, 0.05, truth.shape))
        f = dict(feats)
        f["albedo"] = 0.5 + rng.normal(0, 0.3, (h, w, 3))       # noise only, different per subset
        fl.append(f)
    noisy = Buffers.from_subsets(colors, [4] * 4, fl)
    quiet = Buffers.from_subsets(colors, [4] * 4, [dict(fl[0])] * 4)   # same values, no variance
    rn = lp.reconstruct(noisy).fit.center_rank.mean()
    rq = lp.reconstruct(quiet).fit.center_rank.mean()
    assert rn < rq - 2


def test_granularity_one_places_a_model_at_every_pixel():
    h, w = 20, 20
    feats = scene_features(h, w, seed=40)
    buf = make_buffers(0.5 * feats["albedo"], feats, sigma=0.2, seed=41)
    res = lp.reconstruct(buf, lp.Params(granularity=1, radius=3))
    assert res.info["center_fraction"] == 1.0 and res.info["passes"] == 1
    coarse = lp.reconstruct(buf, lp.Params(radius=3))
    assert coarse.info["center_fraction"] < 1.0 and coarse.info["passes"] > 1


def test_empty_buffers_give_zeros():
    buf = Buffers.empty(6, 7, lp.PASSES)
    res = lp.reconstruct(buf)
    assert np.array_equal(res.image, np.zeros((6, 7, 3))) and np.array_equal(res.error, np.zeros((6, 7)))
    counts = lp.sample_map(buf, res, 42, lp.Params(), {})
    assert counts.sum() == 42 and np.all(counts == 1)

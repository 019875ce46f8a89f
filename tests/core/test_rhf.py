"""Tests of the RHF method (core/rhf.py, Liu, Zheng, Yuan 2018)."""
import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra import numpy as hnp

from core import rhf
from core.buffers import Buffers
from core.filters import box_mean, sobel_gradient
from core.method import MethodResult, params_from_dict


# ------------------------------------------------------------------ scenes
def relmse(x, ref):
    return float((((x - ref) ** 2) / (ref ** 2 + 0.01)).mean())


def scene(h=48, w=48, seed=0, K=4, spp=4, noise=0.3, feat_noise=0.02):
    """Albedo edge, a lit sphere (normals, depth), a colour-only shadow edge."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    alb = np.where((xx + 0.5 * yy) < 0.6 * w, 0.8, 0.3)[..., None] * np.array([1.0, 0.9, 0.7])
    cy, cx, R = h * 0.6, w * 0.35, min(h, w) * 0.25
    d2 = ((yy - cy) ** 2 + (xx - cx) ** 2) / R ** 2
    ins = d2 < 1
    nrm = np.zeros((h, w, 3))
    nrm[..., 2] = 1.0
    nrm[ins, 0] = (xx - cx)[ins] / R
    nrm[ins, 1] = (yy - cy)[ins] / R
    nrm[ins, 2] = np.sqrt(1 - d2[ins])
    depth = (5 + yy / h * 3 - ins * 1.0)[..., None]
    light = 0.3 + 0.7 * np.clip(nrm @ np.array([0.3, -0.5, 0.8]), 0, None)
    truth = alb * (light * np.where(xx > 0.75 * w, 0.4, 1.0))[..., None]
    subs, feats = [], []
    for _ in range(K):
        subs.append(truth + rng.normal(size=truth.shape) * noise * truth.mean(-1, keepdims=True)
                    / np.sqrt(spp))
        feats.append({"albedo": alb + rng.normal(size=alb.shape) * feat_noise,
                      "normal": nrm + rng.normal(size=nrm.shape) * feat_noise,
                      "depth": depth + rng.normal(size=depth.shape) * feat_noise / 2})
    return truth, Buffers.from_subsets(subs, [spp] * K, feats)


def flat_features(h, w):
    return {"albedo": np.full((h, w, 3), 0.5), "normal": np.tile([0.0, 0.0, 1.0], (h, w, 1)),
            "depth": np.full((h, w, 1), 2.0)}


def buffers_from(truth_or_subsets, feats, spp=4):
    subs = truth_or_subsets
    return Buffers.from_subsets(subs, [spp] * len(subs), [feats] * len(subs))


def run(buf, **kw):
    p = dataclasses.replace(rhf.Params(), **kw)
    feats, fvars = rhf._feature_arrays(buf)
    return rhf.rhf_reconstruct(buf.color.mean, buf.variance_of_mean(), feats, fvars, buf.n, p)


# ------------------------------------------------------------------ params
def test_params_metadata_complete_and_typed():
    for f in dataclasses.fields(rhf.Params):
        assert isinstance(f.metadata.get("help"), str) and len(f.metadata["help"]) > 10, f.name
        assert "min" in f.metadata and "max" in f.metadata, f.name
        assert f.type in ("int", "float", "bool", "str", int, float, bool, str), f.name
        default = f.default
        if isinstance(default, (int, float)) and not isinstance(default, bool):
            lo, hi = f.metadata["min"], f.metadata["max"]
            assert (lo is None or default >= lo) and (hi is None or default <= hi), f.name


def test_paper_defaults():
    p = rhf.Params()
    np.testing.assert_array_equal(rhf.parse_bandwidths(p.bandwidths), [1.0, 1.5, 2.0, 3.5, 4.0])
    assert (p.iterations, p.patch_radius, p.edge_threshold) == (2, 3, 0.4)
    assert (p.radius_small, p.radius_medium, p.radius_large) == (5, 10, 15)
    assert (p.sigma_s, p.sigma_r, p.sigma_normal, p.sigma_albedo, p.sigma_depth) == \
        (2.0, 1.0, 0.8, 0.25, 0.6)
    assert (p.feature_k, p.guided_eps) == (0.25, 0.001)
    assert rhf.PASSES == ("normal", "albedo", "depth")


def test_params_from_dict_and_bad_bandwidths():
    p = params_from_dict(rhf.Params, {"iterations": 3, "bandwidths": "2, 1", "unknown": 1})
    assert p.iterations == 3
    np.testing.assert_array_equal(rhf.parse_bandwidths(p.bandwidths), [1.0, 2.0])
    with pytest.raises(ValueError):
        params_from_dict(rhf.Params, {"iterations": 99})
    for bad in ("", "1,-2", "a", "nan"):
        with pytest.raises(ValueError):
            rhf.parse_bandwidths(bad)


def test_iteration_weights_eq12():
    np.testing.assert_allclose(rhf.iteration_weights(3), [1 - 1 / 4, 1 - 1 / 9, 1 - 1 / 16])


# --------------------------------------------------------------- hat matrix
def dense_hat(X, w, ridge):
    Lam = rhf.regularizer(np.array(w.sum()), X.shape[1], ridge)
    W = np.diag(w)
    return X @ np.linalg.inv(X.T @ W @ X + Lam) @ X.T @ W


def test_hat_bias_variance_matches_dense_hat_matrix():
    """Eq. 2 and Eq. 11 against an explicit n x n hat matrix."""
    rng = np.random.default_rng(0)
    n, P, K, B = 30, 10, 3, 2
    X = np.concatenate([np.ones((B, n, 1)), rng.uniform(-1, 1, (B, n, P - 1))], axis=2)
    w = rng.uniform(0, 1, (B, K, n))
    Y = rng.normal(size=(B, n, 3))
    yp = rng.normal(size=(B, n, 3))
    v = rng.uniform(0, 2, (B, K, n))
    pred, bias, var = rhf.hat_bias_variance(X, w, Y, yp, v, ridge=1e-3)
    for b in range(B):
        for k in range(K):
            H = dense_hat(X[b], w[b, k], 1e-3)
            np.testing.assert_allclose(pred[b, k], H @ Y[b], atol=1e-9)
            np.testing.assert_allclose(bias[b, k], H @ yp[b] - yp[b], atol=1e-9)
            np.testing.assert_allclose(var[b, k], (H ** 2) @ v[b, k], atol=1e-9)
    # k-independent variance input broadcasts the same way
    _, _, var2 = rhf.hat_bias_variance(X, w, Y, yp, v[:, 0], ridge=1e-3)
    np.testing.assert_allclose(var2[:, 0], var[:, 0], atol=1e-12)


def test_hat_bias_variance_lean_and_cached_match_full():
    """``lean`` (coefficients and bias^2, used by rhf_reconstruct) and a reused
    (X^T W X + Lambda)^-1 give the same numbers as the full output."""
    rng = np.random.default_rng(3)
    n, P, K, B = 25, 6, 4, 3
    X = np.concatenate([np.ones((B, n, 1)), rng.uniform(-1, 1, (B, n, P - 1))], axis=2)
    w = rng.uniform(0, 1, (B, K, n))
    Y, yp = rng.normal(size=(B, n, 3)), rng.normal(size=(B, n, 3))
    v, u = rng.uniform(0, 2, (B, K, n)), rng.uniform(0, 2, (B, n))
    pred, bias, var, noise = rhf.hat_bias_variance(X, w, Y, yp, v, 1e-3, pilot_var=u)
    cache = {}
    for _ in range(2):                       # first fills the cache, second reuses it
        beta, b2, var2, noise2 = rhf.hat_bias_variance(X, w, Y, yp, v, 1e-3, pilot_var=u,
                                                       cache=cache, lean=True)
        assert cache["Ainv"].shape == (B, K, P, P)
        np.testing.assert_allclose(np.einsum("bnp,bkpc->bknc", X, beta), pred, atol=1e-12)
        np.testing.assert_allclose(b2, (bias ** 2).mean(-1), atol=1e-12)
        np.testing.assert_allclose(var2, var, atol=1e-12)
        np.testing.assert_allclose(noise2, noise, atol=1e-12)


def test_hat_matrix_exact_for_linear_data_and_idempotent():
    rng = np.random.default_rng(1)
    n = 25
    X = np.concatenate([np.ones((1, n, 1)), rng.uniform(-1, 1, (1, n, 4))], axis=2)
    beta = rng.normal(size=(5, 3))
    Y = X[0] @ beta
    w = rng.uniform(0.2, 1, (1, 1, n))
    pred, bias, _ = rhf.hat_bias_variance(X, w, Y[None], Y[None], np.zeros((1, n)), ridge=1e-12)
    np.testing.assert_allclose(pred[0, 0], Y, atol=1e-8)
    np.testing.assert_allclose(bias[0, 0], 0, atol=1e-8)


def test_hat_singular_and_degenerate_systems_stay_finite():
    n = 16
    X = np.zeros((2, n, 10))
    X[..., 0] = 1.0                          # every feature constant: only the intercept
    w = np.zeros((2, 1, n))                  # all weights zero -> uniform fallback
    w[1, 0, 3] = 1.0                         # one pixel only
    Y = np.arange(2 * n * 3, dtype=float).reshape(2, n, 3)
    pred, bias, var = rhf.hat_bias_variance(X, w, Y, Y, np.ones((2, n)))
    assert np.all(np.isfinite(pred)) and np.all(np.isfinite(var)) and np.all(np.isfinite(bias))
    np.testing.assert_allclose(pred[0, 0], np.broadcast_to(Y[0].mean(0), (n, 3)), rtol=1e-6)
    np.testing.assert_allclose(pred[1, 0], np.broadcast_to(Y[1, 3], (n, 3)), rtol=1e-6)


def test_block_error_and_bandwidth_choice():
    w = np.array([[1.0, 1.0, 0.0], [2.0, 2.0, 0.0]])
    err = np.array([[1.0, 3.0, 100.0], [1.0, 3.0, 100.0]])
    np.testing.assert_allclose(rhf.block_error(w, err), [2.0, 2.0])   # scale-free mean
    assert rhf.block_error(np.zeros(3), np.ones(3)) == 0
    np.testing.assert_array_equal(rhf.choose_bandwidth(np.array([[3.0, 1.0, 2.0],
                                                                 [1.0, 1.0, 1.0]])), [1, 2])


# ------------------------------------------------------------- pieces
def test_feature_gradient_is_max_sobel_and_colour_guide_eq8():
    rng = np.random.default_rng(2)
    f = rng.normal(size=(9, 11, 7))
    np.testing.assert_allclose(rhf.feature_gradient(f), sobel_gradient(f).max(axis=2))
    y = rng.normal(size=(9, 11, 3))
    const = np.ones((9, 11, 7))
    # constant guides: each GUID(y, f_m) is the box mean of box means
    r = rhf.Params().guided_radius
    np.testing.assert_allclose(rhf.prefilter_color(y, const, rhf.Params()),
                               box_mean(box_mean(y, r), r), atol=1e-12)


def test_prefilter_features_denoises_and_keeps_edges():
    rng = np.random.default_rng(3)
    h, w = 32, 32
    clean = np.zeros((h, w, 7))
    clean[..., 2] = 1.0
    clean[:, 16:, 3:6] = 0.8                       # albedo edge
    clean[..., 6] = 0.5
    noisy = clean + rng.normal(size=clean.shape) * 0.05
    var = np.full(clean.shape, 0.05 ** 2)
    out = rhf.prefilter_features(noisy, var, rhf.Params())
    assert ((out - clean) ** 2).mean() < 0.2 * ((noisy - clean) ** 2).mean()
    assert out[:, 18:, 3].mean() - out[:, :14, 3].mean() > 0.7     # edge kept


def test_select_centers_cover_and_window_sizes():
    p = rhf.Params()
    for h, w in [(1, 1), (3, 5), (31, 37), (70, 45)]:
        gra = np.zeros((h, w))
        if h > 40:
            gra[10, 10] = 1.0                      # one edge pixel in the first patch
        cy, cx, cr, det = rhf.select_centers(gra, p)
        cover = np.zeros((h, w), bool)
        for a, b, r in zip(cy, cx, cr):
            cover[max(0, a - r):a + r + 1, max(0, b - r):b + r + 1] = True
        assert cover.all()
        assert np.all((cy >= 0) & (cy < h) & (cx >= 0) & (cx < w))
        if h > 40:
            assert det[0, 0] and not det[1, 0]
            assert 5 in cr[(cy == 10) & (cx == 10)]            # r_s on the detail pixel
            assert 15 not in cr[(cy == 15) & (cx == 15)]       # detailed patch: no r_l
            assert 15 in cr[(cy == 46) & (cx == 15)]           # smooth patch: r_l
    cy, cx, cr, det = rhf.select_centers(gra, dataclasses.replace(p, detail_cover=False))
    assert 5 in cr[(cy == 15) & (cx == 15)]                    # former placement: centre


@pytest.mark.parametrize("r", [1, 2, 4])
def test_guide_variance_matches_dense_operator(r):
    """Var(M) = sum_j W_ij^2 Var_j for W = box_mean o box_mean (flat guide)."""
    h, w = 7, 9
    W = np.zeros((h * w, h * w))
    for j in range(h * w):
        e = np.zeros((h, w))
        e.flat[j] = 1.0
        W[:, j] = box_mean(box_mean(e, r), r).ravel()
    v = np.random.default_rng(5).uniform(size=(h, w, 2))
    ref = np.stack([(W ** 2) @ v[..., c].ravel() for c in range(2)], -1).reshape(h, w, 2)
    np.testing.assert_allclose(rhf.guide_variance(v, r), ref, atol=1e-14)
    np.testing.assert_array_equal(rhf.guide_variance(v, 0), v)


def test_fill_centers_are_uncovered_pixels():
    rng = np.random.default_rng(4)
    unc = rng.uniform(size=(40, 50)) < 0.05
    cy, cx = rhf._fill_centers(unc, 10)
    assert unc[cy, cx].all()
    cells = {(a // 21, b // 21) for a, b in zip(*np.nonzero(unc))}
    assert len(cy) == len(cells)


# -------------------------------------------------------------- behaviour
def test_zero_variance_input_is_returned_unchanged():
    truth, _ = scene(24, 24)
    h, w = truth.shape[:2]
    feats = flat_features(h, w)
    buf = buffers_from([truth] * 3, feats)
    res = rhf.reconstruct(buf)
    np.testing.assert_array_equal(res.image, truth)
    np.testing.assert_array_equal(res.error, 0)


def test_error_drops_well_below_input():
    truth, buf = scene(64, 64)
    res = rhf.reconstruct(buf)
    assert isinstance(res, MethodResult) and res.image.shape == (64, 64, 3)
    mse = lambda x: float(((x - truth) ** 2).mean())
    assert mse(res.image) < 0.25 * mse(buf.color.mean)
    assert relmse(res.image, truth) < 0.8 * relmse(buf.color.mean, truth)
    true_err = ((res.image - truth) ** 2).mean(-1).mean()
    assert 0.2 < res.error.mean() / true_err < 5          # estimate in the right range


def test_input_weight_pulls_toward_the_input_monotonically():
    """Eq. 13 with the pixel's own input at weight ``input_weight`` (our
    guard against extrapolated predictions): the further from 0, the closer
    the output to the input; 0 is the paper's Eq. 13 and stays finite."""
    truth, buf = scene(40, 40, seed=2)
    dist = []
    for iw in (0.0, 0.001, 0.02, 0.2, 1.0):
        res = rhf.reconstruct(buf, rhf.Params(input_blend="fixed", input_weight=iw))
        assert np.isfinite(res.image).all() and np.isfinite(res.error).all()
        dist.append(float(np.abs(res.image - buf.color.mean).mean()))
    assert all(a > b for a, b in zip(dist, dist[1:]))


def test_more_samples_less_error():
    errs = []
    for spp in (2, 32):
        truth, buf = scene(32, 32, spp=spp, seed=5)
        errs.append(relmse(rhf.reconstruct(buf).image, truth))
    assert errs[1] < 0.5 * errs[0]


def _edge_scene():
    h, w = 40, 96
    rng = np.random.default_rng(6)
    truth = np.where(np.arange(w)[None, :, None] < 48, 0.2, 0.8) * np.ones((h, w, 3))
    buf = buffers_from([truth + rng.normal(size=truth.shape) * 0.1 for _ in range(4)],
                       flat_features(h, w))
    return truth, buf


def test_bandwidth_small_at_edges_flat_elsewhere():
    """Colour-only edge (features flat).  With Eq. 11 as written, models
    centred on the edge choose the smallest k and their block error grows
    steeply with k; in the flat parts the error hardly depends on k (the
    weights are ~1 for every k), so there the choice does not matter."""
    truth, buf = _edge_scene()
    res = run(buf)
    on_edge = np.abs(res.cx - 47.5) <= 1.5
    far = np.abs(res.cx - 47.5) > res.cr + 6
    assert on_edge.any() and far.any()
    assert res.k_opt[on_edge].max() <= 1.5 and np.median(res.k_opt[on_edge]) == 1.0
    be = res.block_error
    assert np.all(be[on_edge, -1] > 3 * be[on_edge, 0])
    assert np.all(be[far, -1] < 1.1 * be[far, 0])
    assert res.image[:, 52:, 0].mean() - res.image[:, :44, 0].mean() > 0.55   # edge kept
    assert ((res.image - truth) ** 2).mean() < 0.1 * ((buf.color.mean - truth) ** 2).mean()


def test_bias_noise_correction_gives_large_k_away_from_edges():
    truth, buf = _edge_scene()
    res = run(buf, bias_noise_correction=True)
    on_edge = np.abs(res.cx - 47.5) <= 1.5
    off = np.abs(res.cx - 47.5) >= 3
    assert res.k_opt[on_edge].max() <= 1.5 and np.median(res.k_opt[on_edge]) == 1.0
    assert res.k_opt[off].mean() > 2.0
    assert ((res.image - truth) ** 2).mean() < 0.1 * ((buf.color.mean - truth) ** 2).mean()


def test_pilot_noise_term_matches_dense_hat_matrix():
    rng = np.random.default_rng(14)
    n = 20
    X = np.concatenate([np.ones((1, n, 1)), rng.uniform(-1, 1, (1, n, 3))], axis=2)
    w = rng.uniform(0.1, 1, (1, 2, n))
    u = rng.uniform(0, 1, (1, n))
    v = rng.uniform(0, 1, (1, n))
    Y = rng.normal(size=(1, n, 3))
    *_, noise = rhf.hat_bias_variance(X, w, Y, Y, v, 1e-3, pilot_var=u)
    for k in range(2):
        H = dense_hat(X[0], w[0, k], 1e-3)
        np.testing.assert_allclose(noise[0, k], ((H - np.eye(n)) ** 2) @ u[0], atol=1e-10)


def test_iterations_and_options_run():
    truth, buf = scene(48, 48, seed=7)
    mse = lambda x: float(((x - truth) ** 2).mean())
    base = mse(buf.color.mean)
    for kw in ({"iterations": 1}, {"iterations": 3}, {"regress_guide": True},
               # a spatial term makes every regression weight small, so the
               # input weight (0.02 by default) must shrink with them
               {"regression_sigma_s": 2.0, "input_weight": 0.001},
               {"fill_rounds": 0, "coverage_weight": 0.0},
               {"bandwidths": "2.0"}, {"patch_radius": 0, "feature_radius": 0,
                                        "guided_radius": 0}, {"bias_noise_correction": True}):
        res = run(buf, **kw)
        assert np.all(np.isfinite(res.image)) and np.all(np.isfinite(res.error)), kw
        assert mse(res.image) < 0.5 * base, kw


@pytest.mark.parametrize("kw", [{}, {"iterations": 3, "bias_noise_correction": True}])
def test_results_do_not_depend_on_chunking(monkeypatch, kw):
    """Models are regressed in chunks (``chunk_centers`` centres for the
    weights, at most ``CHUNK_PIXELS`` window pixels per regression); the
    result must not depend on either (up to float rounding), including the
    Eq. 12 error whose earlier-iteration terms are recomputed at k_opt."""
    truth, buf = scene(40, 40, seed=3)
    a = run(buf, **kw)
    monkeypatch.setattr(rhf, "CHUNK_PIXELS", 300)
    b = run(buf, chunk_centers=3, **kw)
    assert a.info["models"] == b.info["models"]
    np.testing.assert_array_equal(b.k_opt, a.k_opt)
    # with T > 2 the middle pass's input blend reads the float32 Var_t maps
    tol = 1e-10 if a.info.get("iterations", 2) <= 2 and not kw else 1e-6
    np.testing.assert_allclose(b.image, a.image, rtol=tol, atol=1e-12)
    # (the per-k variance maps of Eq. 11 are float32 sums: rounding ~1e-7)
    np.testing.assert_allclose(b.error, a.error, rtol=1e-6, atol=1e-15)


def test_reconstruct_accepts_callable_colour_variance():
    truth, buf = scene(24, 24, seed=5)
    feats, fvars = rhf._feature_arrays(buf)
    v = buf.variance_of_mean()
    a = rhf.rhf_reconstruct(buf.color.mean, v, feats, fvars, buf.n)
    b = rhf.rhf_reconstruct(buf.color.mean, lambda: v, feats, fvars, buf.n)
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.error, b.error)


# ------------------------------------------------------------- special input
def test_noise_variance_estimate_is_robust_to_edges():
    rng = np.random.default_rng(15)
    img = np.where(np.arange(64)[None, :, None] < 32, 0.0, 5.0) * np.ones((64, 64, 2))
    est = rhf.noise_variance_estimate(img + rng.normal(size=img.shape) * 0.1)
    np.testing.assert_allclose(est, 0.01, rtol=0.15)
    assert rhf.noise_variance_estimate(np.ones((2, 2, 3))).shape == (3,)


def test_single_subset_uses_estimated_variance():
    truth, _ = scene(48, 48)
    rng = np.random.default_rng(8)
    buf = buffers_from([truth + rng.normal(size=truth.shape) * 0.05], flat_features(48, 48))
    assert np.all(np.isinf(buf.variance_of_mean()))
    res = rhf.reconstruct(buf)
    assert res.info["variance_filled_fraction"] == 1.0
    assert np.all(np.isfinite(res.image)) and np.all(np.isfinite(res.error))
    assert relmse(res.image, truth) < relmse(buf.color.mean, truth)


def test_partial_variance_and_missing_pixels_filled():
    truth, buf = scene(24, 24, seed=9)
    buf.k[:5, :5] = 1                               # no variance here
    buf.color.mean[10, 10] = np.nan                  # missing sample
    buf.n[12, 3] = 0                                 # never rendered
    res = rhf.reconstruct(buf)
    assert res.info["missing_pixels"] == 2
    assert np.all(np.isfinite(res.image)) and np.all(np.isfinite(res.error))
    assert abs(res.image[10, 10] - truth[10, 10]).max() < 0.2


def test_firefly_stays_finite_local_and_reduces_error():
    """A 1e6 sample in one subset: its estimated variance is huge, so Eq. 5
    treats it as noise; its energy is spread over nearby models (not kept as
    a spike), which lowers the squared error, and pixels far away are untouched."""
    h, w = 48, 64
    rng = np.random.default_rng(10)
    truth = np.full((h, w, 3), 0.5)
    subs = [truth + rng.normal(size=truth.shape) * 0.05 for _ in range(4)]
    subs[0][16, 16] = 1e6
    buf = buffers_from(subs, flat_features(h, w))
    res = rhf.reconstruct(buf)
    assert np.all(np.isfinite(res.image)) and np.all(np.isfinite(res.error))
    assert res.image[16, 16].max() < 0.2 * buf.color.mean[16, 16].max()
    assert ((res.image - truth) ** 2).sum() < ((buf.color.mean - truth) ** 2).sum()
    assert np.abs(res.image[:, 50:] - 0.5).max() < 0.1


def test_empty_buffers():
    buf = Buffers.empty(6, 7, rhf.PASSES)
    res = rhf.reconstruct(buf)
    assert np.all(np.isfinite(res.image)) and np.all(np.isfinite(res.error))


def test_black_and_constant_images():
    for val in (0.0, 0.37):
        img = np.full((13, 17, 3), val)
        res = rhf.reconstruct(buffers_from([img, img], flat_features(13, 17)))
        np.testing.assert_array_equal(res.image, img)


@pytest.mark.parametrize("h,w", [(1, 1), (1, 9), (3, 5), (7, 13), (31, 37)])
def test_small_and_prime_sizes(h, w):
    rng = np.random.default_rng(h * 100 + w)
    truth = rng.uniform(0.2, 0.8, size=(h, w, 3))
    feats = {"albedo": rng.uniform(size=(h, w, 3)), "normal": rng.normal(size=(h, w, 3)),
             "depth": rng.uniform(1, 2, size=(h, w, 1))}
    buf = buffers_from([truth + rng.normal(size=truth.shape) * 0.05 for _ in range(3)], feats)
    res = rhf.reconstruct(buf)
    assert res.image.shape == (h, w, 3) and res.error.shape == (h, w)
    assert np.all(np.isfinite(res.image)) and np.all(res.error >= 0)


def test_windows_larger_than_image_and_missing_feature_pass():
    truth, buf = scene(12, 10, seed=11)
    res = run(buf, radius_small=20, radius_medium=30, radius_large=40, feature_radius=16,
              guided_radius=20)
    assert np.all(np.isfinite(res.image))
    del buf.features["depth"]
    res2 = rhf.reconstruct(buf)
    assert np.all(np.isfinite(res2.image))


_hostile = st.sampled_from([0.0, 0.5, -1.0, 1e30, -1e30, np.nan, np.inf, -np.inf, 1e6, -5.0])


@settings(max_examples=12, deadline=None)
@given(hnp.arrays(np.float64, (2, 6, 7, 3), elements=_hostile),
       hnp.arrays(np.float64, (6, 7, 3), elements=_hostile))
def test_hostile_input_gives_finite_output(colors, albedo):
    feats = flat_features(6, 7)
    feats["albedo"] = albedo
    buf = Buffers.from_subsets(list(colors), [2, 2], [feats, feats])
    res = rhf.reconstruct(buf)
    assert np.all(np.isfinite(res.image)) and np.all(np.isfinite(res.error))
    assert np.all(res.error >= 0)
    smap = rhf.sample_map(buf, res, 50, rhf.Params(), {})
    assert smap.sum() == 50 and smap.min() >= 0


@settings(max_examples=8, deadline=None)
@given(st.integers(1, 9), st.integers(1, 9), st.integers(0, 2 ** 31))
def test_random_shapes_and_noise_are_finite(h, w, seed):
    rng = np.random.default_rng(seed)
    truth = rng.uniform(-1, 2, size=(h, w, 3))
    buf = buffers_from([truth + rng.normal(size=truth.shape) for _ in range(2)],
                       flat_features(h, w))
    res = rhf.reconstruct(buf)
    assert np.all(np.isfinite(res.image)) and np.all(np.isfinite(res.error))


# ------------------------------------------------------------- sampling
def test_sample_map_budget_and_preference():
    truth, buf = scene(32, 32, seed=12)
    res = rhf.reconstruct(buf)
    err = np.full((32, 32), 1e-6)
    err[:, 16:] = 1e-2
    res = MethodResult(res.image, err, res.info, dimension=res.dimension)
    for budget in (0, 1, 1000, 4096):
        m = rhf.sample_map(buf, res, budget, rhf.Params(), {})
        assert m.dtype == np.int64 and m.shape == (32, 32)
        assert m.sum() == budget and m.min() >= 0
    m = rhf.sample_map(buf, res, 4096, rhf.Params(), {})
    assert m[:, 16:].sum() > 10 * m[:, :16].sum()


def test_denoise_matches_reconstruct():
    truth, buf = scene(20, 20, seed=13)
    feats, fvars = rhf._feature_arrays(buf)
    fvars = {k: v() for k, v in fvars.items()}
    a = rhf.reconstruct(buf)
    b = rhf.denoise(buf.color.mean, buf.variance_of_mean(), feats, feature_var=fvars, n=buf.n)
    np.testing.assert_allclose(a.image, b.image)
    c = rhf.denoise(buf.color.mean, buf.variance_of_mean(), feats)
    assert np.all(np.isfinite(c.image))


# ------------------------------------------------------------- contract
def test_method_contract_and_dimension():
    assert rhf.NAME == "rhf" and rhf.ADAPTIVE is True and rhf.SAMPLER_USES_RESULT is True
    truth, buf = scene(24, 24, seed=16)
    res = rhf.reconstruct(buf)
    assert res.dimension == res.info["active_features"] == 9
    del buf.features["depth"]                       # a missing pass is a constant feature
    assert rhf.reconstruct(buf).dimension == 8


def test_sample_map_reads_dimension_not_info():
    """The exponent of n comes from ``result.dimension`` (9 when None); the
    info dict is ignored."""
    truth, buf = scene(24, 24, seed=17)
    buf.n[:, :12] *= 8.0                             # unequal n: the exponent matters
    img = buf.color.mean
    err = np.random.default_rng(0).uniform(0.1, 1.0, (24, 24))
    m = lambda **kw: rhf.sample_map(buf, MethodResult(img, err, **kw), 5000, rhf.Params(), {})
    np.testing.assert_array_equal(m(info={"active_features": 2}, dimension=9.0), m(info={}))
    np.testing.assert_array_equal(m(info={"active_features": 9}, dimension=2.0),
                                  m(info={}, dimension=2.0))
    assert not np.array_equal(m(info={}, dimension=0.0), m(info={}, dimension=9.0))


def test_denoise_unified_signature():
    truth, buf = scene(16, 16, seed=18)
    feats, _ = rhf._feature_arrays(buf)
    a = rhf.denoise(buf.color.mean, buf.variance_of_mean(), feats, None, 4.0, {"iterations": 1})
    b = rhf.denoise(buf.color.mean, buf.variance_of_mean(), features=feats,
                    n=np.full((16, 16), 4.0), params=rhf.Params(iterations=1))
    np.testing.assert_array_equal(a.image, b.image)
    assert a.dimension == 9


# ----------------------------------------------- separated regression steps
def _windows(rng, c, n, P, K):
    X = np.concatenate([np.ones((c, n, 1)), rng.uniform(-1, 1, (c, n, P - 1))], axis=2)
    w = rng.uniform(0.05, 1, (c, K, n))
    return X, w


def test_window_error_terms_match_batch_least_squares_and_dense_hat():
    """Eq. 2: X @ beta is the ridge-regularised weighted least-squares fit
    (independent ``lstsq`` on the augmented system); Eq. 11: err_t =
    mean_c (H P - P)^2 + (H^2) Var; Eq. 9-10: the block error is its
    weighted mean."""
    rng = np.random.default_rng(20)
    c, n, P, K, ridge = 3, 21, 6, 4, 1e-3
    X, w = _windows(rng, c, n, P, K)
    Y, Pq = rng.normal(size=(c, n, 3)), rng.normal(size=(c, n, 3))
    vq = rng.uniform(0, 1, (c, K, n))
    cache = {}
    beta, err_t, blk, var = rhf.window_error_terms(X, w, Y, Pq, vq, None, ridge, cache)
    assert beta.shape == (c, K, P, 3) and err_t.shape == var.shape == (c, K, n)
    assert blk.shape == (c, K) and cache["Ainv"].shape == (c, K, P, P)
    for b in range(c):
        for k in range(K):
            lam = np.diag(rhf.regularizer(np.array(w[b, k].sum()), P, ridge))
            sw = np.sqrt(w[b, k])[:, None]
            A = np.concatenate([sw * X[b], np.diag(np.sqrt(lam))])
            rhs = np.concatenate([sw * Y[b], np.zeros((P, 3))])
            ref = np.linalg.lstsq(A, rhs, rcond=None)[0]
            np.testing.assert_allclose(X[b] @ beta[b, k], X[b] @ ref, atol=1e-9)
            H = dense_hat(X[b], w[b, k], ridge)
            e = ((H @ Pq[b] - Pq[b]) ** 2).mean(-1) + (H ** 2) @ vq[b, k]
            np.testing.assert_allclose(err_t[b, k], e, atol=1e-9)
            np.testing.assert_allclose(blk[b, k], (w[b, k] * e).sum() / w[b, k].sum(),
                                       atol=1e-9)


def test_window_error_terms_linear_data_has_no_bias():
    rng = np.random.default_rng(21)
    c, n, P, K = 2, 16, 5, 3
    X, w = _windows(rng, c, n, P, K)
    Y = np.einsum("cnp,cpq->cnq", X, rng.normal(size=(c, P, 3)))
    v = rng.uniform(0, 1, (c, n))
    beta, err_t, _, var = rhf.window_error_terms(X, w, Y, Y, v, None, 1e-12, {})
    np.testing.assert_allclose(np.einsum("cnp,ckpq->cknq", X, beta), Y[:, None].repeat(K, 1),
                               atol=1e-8)
    np.testing.assert_allclose(err_t, var, atol=1e-12)           # bias^2 = 0


def test_bandwidth_choice_picks_minimum_of_error_curve_and_its_prediction():
    """Eq. 10 on a known error curve (a parabola in k with a random minimum
    per model): k_opt is its argmin, and the prediction and Eq. 13 weight
    are those of that candidate."""
    rng = np.random.default_rng(22)
    ks = rhf.parse_bandwidths(rhf.Params().bandwidths)
    c, n, P, K = 6, 9, 4, ks.size
    best = rng.integers(0, K, c)
    curve = (ks[None, :] - ks[best][:, None]) ** 2 + 0.5
    kk = rhf.choose_bandwidth(curve)
    np.testing.assert_array_equal(kk, best)
    X, wk = _windows(rng, c, n, P, K)
    beta = rng.normal(size=(c, K, P, 3))
    wm, yk = rhf.predict_at_bandwidth(wk, X, beta, kk)
    for i in range(c):
        np.testing.assert_array_equal(wm[i], wk[i, best[i]] + rhf.MODEL_WEIGHT_FLOOR)
        np.testing.assert_allclose(yk[i], X[i] @ beta[i, best[i]], atol=1e-14)


def test_accumulate_and_combine_models_are_eq13():
    """Overlapping windows: the sums equal a dense per-pixel loop, the output
    is (sum_i w_ij y_ij + fw y_j) / (sum_i w_ij + fw), and equal inputs give
    back that value (a convex combination: the weights are normalised)."""
    rng = np.random.default_rng(23)
    h, w, c, n = 4, 5, 3, 8
    npx = h * w
    idx = rng.integers(0, npx, (c, n))
    inside = rng.uniform(size=(c, n)) < 0.8
    inside[:, 0] = True
    wm = rng.uniform(0, 1, (c, n))
    yk = rng.normal(size=(c, n, 3))
    y = rng.normal(size=(h, w, 3))
    num, den = np.zeros((npx, 3)), np.zeros(npx)
    flat = idx[inside]
    rhf.accumulate_predictions(num, den, flat, wm[inside], yk, inside, int(flat.min()),
                               int(flat.max()) + 1)
    ref_num, ref_den = np.zeros((npx, 3)), np.zeros(npx)
    for i in range(c):
        for m in range(n):
            if inside[i, m]:
                ref_num[idx[i, m]] += wm[i, m] * yk[i, m]
                ref_den[idx[i, m]] += wm[i, m]
    np.testing.assert_allclose(num, ref_num, atol=1e-12)
    np.testing.assert_allclose(den, ref_den, atol=1e-12)
    fw = 0.02
    out, dd = rhf.combine_models(num, den, y, fw)
    ref = (ref_num + fw * y.reshape(npx, 3)) / (ref_den + fw)[:, None]
    np.testing.assert_allclose(out, ref.reshape(h, w, 3), atol=1e-12)
    np.testing.assert_allclose(dd, ref_den + fw, atol=1e-12)
    # constant predictions and input: Eq. 13 returns the constant
    num, den = np.zeros((npx, 3)), np.zeros(npx)
    rhf.accumulate_predictions(num, den, flat, wm[inside], np.full((c, n, 3), 0.7), inside,
                               0, npx)
    out, _ = rhf.combine_models(num, den, np.full((h, w, 3), 0.7), fw)
    np.testing.assert_allclose(out, 0.7, rtol=1e-14)


def test_error_at_bandwidth_equals_eq12_of_full_iterations():
    """The last iteration recomputes the earlier Eq. 11 terms at k_opt only;
    that must equal the Eq. 12 combination of the full per-k terms."""
    rng = np.random.default_rng(24)
    h, w, c, n, P, K, T = 5, 6, 3, 9, 5, 3, 3
    npx = h * w
    X, wfit = _windows(rng, c, n, P, K)
    idx = rng.integers(0, npx, (c, n))
    Yq = rng.normal(size=(c, n, 3))
    var0 = rng.uniform(0, 1, npx)
    pilots = [(rng.normal(size=(h, w, 3)), None)]
    pilots += [(rng.normal(size=(h, w, 3)), rng.uniform(0, 1, (h, w, K)).astype(np.float32))
               for _ in range(T - 1)]
    data = rhf.RegressionData(fhat=np.zeros((h, w, 7), np.float32), target=None, y=None,
                              valid=None, var0=var0, guide_var=None, cy=None, cx=None,
                              weis=rhf.iteration_weights(T), ridge=1e-3, input_weight=0.02)
    full, cache = [], {}
    for t in range(T):
        Pq, vq, uq = rhf.gather_pilot(pilots[t], idx, var0, None)
        full.append(rhf.window_error_terms(X, wfit, Yq, Pq, vq, uq, 1e-3, cache)[1])
    kk = rng.integers(0, K, c)
    ek = rhf.error_at_bandwidth(X, wfit, Yq, idx, pilots, cache["Ainv"], kk, full[-1], data)
    ar = np.arange(c)
    ref = sum(data.weis[t] * full[t][ar, kk] for t in range(T)) / data.weis.sum()
    np.testing.assert_allclose(ek, ref, rtol=1e-10, atol=1e-14)


def test_regression_weights_and_model_chunks():
    """w(i, j) = NLM(M, k, false) (Sec. 3.3): in [0, 1], 1 at the centre, 0
    outside the image; every model lands in exactly one chunk of at most
    CHUNK_PIXELS window pixels (or one model)."""
    truth, buf = scene(40, 36, seed=25)
    M = buf.color.mean
    vM = buf.variance_of_mean()
    p = rhf.Params()
    ks = rhf.parse_bandwidths(p.bandwidths)
    cy, cx = np.array([0, 20, 39]), np.array([0, 17, 35])
    wk = rhf.regression_weights(M, vM, cy, cx, 5, ks, p)
    assert wk.shape == (3, ks.size, 121) and wk.dtype == np.float32
    assert wk.min() >= 0 and wk.max() <= 1
    np.testing.assert_array_equal(wk[:, :, 60], 1.0)                # window centre
    _, inside = rhf._window_index(cy, cx, 5, 40, 36)
    assert np.all(wk[~np.broadcast_to(inside[:, None], wk.shape)] == 0)
    cy, cx, cr, _ = rhf.select_centers(np.zeros((40, 36)), p)
    models = rhf.place_models(M.astype(np.float32), vM.astype(np.float32), cy, cx, cr, ks, p)
    ids = np.sort(np.concatenate([ch.ids for ch in models.chunks]))
    np.testing.assert_array_equal(ids, np.arange(models.cy.size))
    for ch in models.chunks:
        assert ch.weights.shape == (ch.ids.size, ks.size, (2 * ch.radius + 1) ** 2)
        assert ch.ids.size == 1 or ch.weights[:, 0].size <= rhf.CHUNK_PIXELS


# ------------------------------------------------- windows, input blend, range
def window_radius_map(cy, cx, cr, shape):
    """Smallest radius of the windows covering each pixel (inf: none)."""
    out = np.full(shape, np.inf)
    for a, b, r in zip(cy, cx, cr):
        sl = (slice(max(0, a - r), a + r + 1), slice(max(0, b - r), b + r + 1))
        out[sl] = np.minimum(out[sl], r)
    return out


def _offcentre_edge_scene(seed=11, spp=4):
    """Albedo step at column 24 (patch centres at 15 and 46): detail off the
    centre of its r_l patch; features carry the edge, noise on the colour."""
    h, w = 62, 62
    rng = np.random.default_rng(seed)
    alb = np.where(np.arange(w)[None, :, None] < 24, 0.2, 0.8) * np.ones((h, w, 3))
    truth = alb * 0.9
    feats = flat_features(h, w)
    feats["albedo"] = alb
    subs = [truth + rng.normal(size=truth.shape) * 0.25 / np.sqrt(spp) for _ in range(4)]
    return truth, Buffers.from_subsets(subs, [spp] * 4, [feats] * 4)


def test_detail_pixels_get_small_windows_and_lower_error():
    """Sec. 3.5 / Fig. 4: the detail pixels of a detailed patch are
    reconstructed with r_s windows.  An edge 9 px off its patch centre was
    left to r_m fill windows by the former placement (one r_s window at the
    centre); now every edge pixel lies in an r_s window and the error on the
    edge columns drops."""
    truth, buf = _offcentre_edge_scene()
    new = run(buf, input_blend="fixed", clamp_predictions=False)
    old = run(buf, input_blend="fixed", clamp_predictions=False, detail_cover=False)
    edge = new.gradient > rhf.Params().edge_threshold
    assert edge[:, 22:26].any() and not edge[:, :20].any()
    rad_new = window_radius_map(new.cy, new.cx, new.cr, edge.shape)
    rad_old = window_radius_map(old.cy, old.cx, old.cr, edge.shape)
    assert np.all(rad_new[edge] == 5)
    assert np.mean(rad_old[edge] == 5) < 0.5
    cols = slice(21, 27)
    e_new = ((new.image[:, cols] - truth[:, cols]) ** 2).mean()
    e_old = ((old.image[:, cols] - truth[:, cols]) ** 2).mean()
    assert e_new < 0.8 * e_old


def test_blend_input_is_inverse_mse_combination():
    """out = (1 - a) m + a y with a = E / (E + V), error E V / (E + V);
    a pixel no model weights keeps its input, E = V = 0 keeps the models."""
    rng = np.random.default_rng(3)
    npx = 7
    y = rng.uniform(0, 1, (1, npx, 3))
    den = np.array([2.0, 0.5, 1.0, 0.0, 1.0, 3.0, 1.0])
    m = rng.uniform(0, 1, (npx, 3))
    E = np.array([0.1, 0.0, 4.0, 0.3, 0.0, 1e-3, 0.2])
    V = np.array([0.1, 0.2, 0.01, 0.3, 0.0, 1e-3, 0.0])
    img, err = rhf.blend_input(m * den[:, None], den.copy(), E * den, y, V)
    eps = rhf.FALLBACK_WEIGHT
    mm = (m * den[:, None] + eps * y[0]) / (den + eps)[:, None]
    EE = (E * den + eps * V) / (den + eps)
    a = np.where(EE + V > 0, EE / np.where(EE + V > 0, EE + V, 1), 0.0)
    a[den == 0] = 1.0
    np.testing.assert_allclose(img[0], mm + a[:, None] * (y[0] - mm), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(err, (1 - a) ** 2 * EE + a * a * V, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(img[0, 3], y[0, 3])                      # no model: input
    np.testing.assert_allclose(img[0, 4], m[4], rtol=1e-9)              # E = V = 0: models
    assert a[2] > 0.99 and a[5] == pytest.approx(0.5)
    assert np.all(err <= np.minimum(EE, V) + 1e-15)                     # never worse than either


def test_blend_variance_is_robust_median_of_neighbours():
    v = np.full((9, 9), 0.01)
    n = np.full((9, 9), 4.0)
    v[4, 4] = 1e6                                         # a firefly's variance
    out = rhf.blend_variance(v, n)
    assert out[4, 4] == 1e6                               # the firefly keeps its own
    out[4, 4] = 0.01
    np.testing.assert_allclose(out, 0.01)                 # its neighbours ignore it
    v2 = np.random.default_rng(0).uniform(0, 1, (9, 9))
    ref = np.median(np.lib.stride_tricks.sliding_window_view(np.pad(v2 * 4, 1, mode="edge"),
                                                             (3, 3)).reshape(9, 9, 9), -1)
    ref = np.maximum(ref, v2 * 4) / 4
    np.testing.assert_allclose(rhf.blend_variance(v2, n), ref)


def test_clamp_to_support_keeps_interpolation_and_bounds_extrapolation():
    rng = np.random.default_rng(1)
    Yq = rng.uniform(0.2, 0.5, (2, 9, 3))
    w = np.ones((2, 9))
    w[1, :4] = 0.0                                        # not fitted: their colours ignored
    Yq[1, :4] = 9.0
    yk = np.concatenate([rng.uniform(0.25, 0.45, (2, 5, 3)),
                         np.full((2, 4, 3), -3.0)], axis=1)
    yk[0, :5] = np.clip(yk[0, :5], Yq[0].min(0), Yq[0].max(0))
    out = rhf.clamp_to_support(yk, w, Yq, 0.01)
    np.testing.assert_array_equal(out[0, :5], yk[0, :5])            # inside the range: kept
    np.testing.assert_array_equal(out[0, 5:], np.broadcast_to(Yq[0].min(0), (4, 3)))
    np.testing.assert_array_equal(out[1, 5:], np.broadcast_to(Yq[1, 4:].min(0), (4, 3)))
    assert np.all(out[1] <= Yq[1, 4:].max(axis=0))                  # ignores unfitted pixels
    none = rhf.clamp_to_support(yk, np.zeros((2, 9)), Yq, 0.01)     # nothing fitted: unclipped
    np.testing.assert_array_equal(none, yk)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_non_negative_input_gives_non_negative_output(seed):
    """Dark, high-contrast stripes with heavy-tailed non-negative noise:
    with the models clipped to their data's range the output is never
    negative; without the clip, the paper's fit extrapolates below 0 here.
    With fireflies added the output stays non-negative.  (The mean is not
    asserted here: with noise this skewed RHF darkens, docs/notes/rhf.md.)"""
    rng = np.random.default_rng(seed)
    h, w = 48, 48
    truth, _ = scene(h, w, seed=seed)
    truth = truth * np.where(np.arange(w)[None, :, None] % 16 < 8, 1.0, 0.02)
    subs = [truth * rng.exponential(1.0, truth.shape) for _ in range(4)]
    feats = flat_features(h, w)
    buf = Buffers.from_subsets(subs, [2] * 4, [feats] * 4)
    res = rhf.reconstruct(buf)
    assert res.image.min() >= 0.0
    assert relmse(res.image, truth) < relmse(buf.color.mean, truth)
    raw = rhf.reconstruct(buf, rhf.Params(clamp_predictions=False, input_blend="fixed"))
    assert raw.image.min() < 0.0
    subs[0][rng.uniform(size=(h, w)) < 0.01] = 20.0
    buf = Buffers.from_subsets(subs, [2] * 4, [feats] * 4)
    assert rhf.reconstruct(buf).image.min() >= 0.0


def test_new_options_off_give_the_former_algorithm_and_finite_output():
    """With the three additions off the output is the former algorithm's;
    they are all finite on hostile input (NaN, Inf, huge, negative)."""
    truth, buf = scene(40, 40, seed=4)
    a = run(buf, detail_cover=False, input_blend="fixed", clamp_predictions=False)
    b = run(buf)
    assert not np.array_equal(a.image, b.image)
    for res in (a, b):
        assert np.isfinite(res.image).all() and np.isfinite(res.error).all()
    bad = buf.color.mean.copy()
    bad[3, 3] = np.nan
    bad[5, 5] = 1e30
    bad[7, 7] = -2.0
    var = buf.variance_of_mean()
    var[9, 9] = np.inf
    feats, fvars = rhf._feature_arrays(buf)
    out = rhf.rhf_reconstruct(bad, var, feats, fvars, buf.n, rhf.Params())
    assert np.isfinite(out.image).all() and np.isfinite(out.error).all() and out.error.min() >= 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mean_brightness_kept_and_error_below_former_algorithm(seed):
    """Mean within 0.5 % of the sample mean, and the relMSE below the former
    algorithm's (centre r_s windows, fixed input weight, no clip)."""
    truth, buf = scene(48, 48, seed=seed)
    res = rhf.reconstruct(buf)
    old = rhf.reconstruct(buf, rhf.Params(detail_cover=False, input_blend="fixed",
                                          clamp_predictions=False))
    assert abs(res.image.mean() / buf.color.mean.mean() - 1) < 0.005
    assert relmse(res.image, truth) < 0.9 * relmse(old.image, truth)

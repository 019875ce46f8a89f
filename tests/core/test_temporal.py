"""LP temporal extension (core/temporal.py): Moon et al. 2015, Sec. 6, Eq. 6."""
from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from core import temporal as tp
from core.buffers import Buffers

H, W = 12, 16


#: world size of one pixel: 0.05 % of the depth (20), about a 1000-pixel-wide 50-degree view
PIX = 0.01


def plane_positions(h=H, w=W, shift=(0, 0)):
    """World positions of a plane seen from above: pixel (r, c) at frame with
    image shift (sy, sx) shows the point PIX * (c - sx, r - sy, 0) + offset."""
    r, c = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([PIX * (c - shift[1]) + 1.0, PIX * (r - shift[0]) + 0.5, np.zeros_like(r)], -1)


def frame_buffers(truth, rng, pos, k=4, spp=4, noise=0.2, depth=20.0):
    h, w = truth.shape[:2]
    feats = {"position": pos, "depth": np.full((h, w, 1), depth)}
    colors = [truth * (1 + noise * rng.standard_normal(truth.shape) / np.sqrt(spp)) for _ in range(k)]
    return Buffers.from_subsets(colors, [spp] * k, [feats] * k)


def smooth_truth(pos):
    return np.stack([0.5 + 0.3 * np.sin(pos[..., 0] * 30), 0.4 + 0.2 * np.cos(pos[..., 1] * 20),
                     0.3 + 0.0 * pos[..., 0]], -1)


def test_params_metadata():
    for f in fields(tp.Params):
        assert "help" in f.metadata and f.metadata["help"]
    p = tp.Params()
    assert p.lam == 0.98 and p.delta == 1e-3


def test_rls_equals_closed_form_weighted_least_squares():
    rng = np.random.default_rng(0)
    pos = plane_positions()
    params = tp.Params(spatial=False, reset_sigma=0.0, sample_gate=0.0, safe_choice=False)  # the literal paper
    state, ys = None, []
    for f in range(101, 113):                   # frame numbers need not start at 1
        truth = 0.5 + 0.02 * (f - 100) + 0.1 * rng.random((H, W, 3))
        buf = frame_buffers(truth, rng, pos)
        ys.append(buf.color.mean.copy())
        res = tp.step(state, buf, params, frame=f)
        state = res.state
        beta = tp.closed_form(np.stack(ys), params.lam, params.delta)     # (H, W, 3, 2)
        np.testing.assert_allclose(state.beta, beta, rtol=1e-6, atol=1e-9)
        t = len(ys)
        np.testing.assert_allclose(res.image, beta[..., 0] + beta[..., 1] * t, rtol=1e-6, atol=1e-9)
        np.testing.assert_array_equal(state.age, t)
    # P is (lam^T delta I + sum lam^(T-j) z z^T)^-1
    t_n = len(ys)
    z = np.stack([np.ones(t_n), np.arange(1, t_n + 1.0)], 1)
    wts = params.lam ** (t_n - np.arange(1, t_n + 1.0))
    p_inv = params.lam ** t_n * params.delta * np.eye(2) + (z * wts[:, None]).T @ z
    np.testing.assert_allclose(state.P[3, 4], np.linalg.inv(p_inv), rtol=1e-6)
    # and with a tiny delta it is plain weighted least squares
    tiny = tp.closed_form(np.stack(ys), 0.98, 1e-12)
    a = (z * wts[:, None]).T @ z
    plain = np.linalg.solve(a, np.einsum("t,ti,thwc->hwci", wts, z, np.stack(ys))[..., None])[..., 0]
    np.testing.assert_allclose(tiny, plain, rtol=1e-6, atol=1e-9)


def test_static_scene_converges():
    rng = np.random.default_rng(1)
    pos = plane_positions()
    truth = smooth_truth(pos)
    state = None
    true_err, est_err = [], []
    for f in range(1, 31):
        buf = frame_buffers(truth, rng, pos, noise=0.5)
        res = tp.step(state, buf, tp.Params(spatial=False), frame=f)
        state = res.state
        true_err.append(float(((res.image - truth) ** 2).mean()))
        est_err.append(float(res.error.mean()))
    assert res.info["carried"] == 1.0
    # a linear fit over n frames: endpoint variance ~ 4 sigma^2 / n
    assert true_err[-1] < 0.25 * true_err[0]
    assert np.mean(true_err[-5:]) < np.mean(true_err[5:10])
    assert est_err[-1] < 0.3 * est_err[0]
    # the estimate tracks the true error within a factor of 2
    assert 0.5 < np.mean(est_err[-10:]) / np.mean(true_err[-10:]) < 2.0


def test_static_scene_converges_with_lp():
    rng = np.random.default_rng(2)
    pos = plane_positions(24, 24)
    truth = smooth_truth(pos)
    state = None
    errs = []
    for f in range(1, 7):
        buf = frame_buffers(truth, rng, pos, noise=0.6)
        res = tp.step(state, buf, tp.Params(), frame=f, lp_params={"radius": 3})
        state = res.state
        errs.append(float(((res.image - truth) ** 2).mean()))
        assert np.isfinite(res.image).all() and np.isfinite(res.error).all()
    assert errs[-1] < errs[0]


def test_linear_ramp_is_followed_without_lag():
    """z = (1, t): a brightness ramp is predicted exactly once two frames are in
    (noise-free input), and the residual gate does not restart the models."""
    pos = plane_positions()
    state = None
    for f in range(1, 8):
        truth = np.full((H, W, 3), 0.2 + 0.05 * f)
        buf = Buffers.from_subsets([truth, truth], [2, 2], [{"position": pos,
                                                             "depth": np.full((H, W, 1), 20.0)}] * 2)
        res = tp.step(state, buf, tp.Params(spatial=False), frame=f)
        state = res.state
        np.testing.assert_allclose(res.image, truth, rtol=1e-3)     # the delta prior's pull
    assert res.info["reset_residual"] == 0 and res.info["carried"] == 1.0
    np.testing.assert_allclose(state.beta[..., 1], 0.05, rtol=1e-3)


def test_model_carried_to_the_right_pixel_under_a_known_shift():
    rng = np.random.default_rng(3)
    shift = (1, 2)                               # image moves down 1, right 2 per frame
    state = None
    for f in range(4):
        s = (shift[0] * f, shift[1] * f)
        pos = plane_positions(shift=s)
        truth = smooth_truth(pos)
        res = tp.step(state, frame_buffers(truth, rng, pos), tp.Params(spatial=False), frame=f + 1)
        if state is not None:
            r, c = np.mgrid[0:H, 0:W]
            inside = (r - shift[0] >= 0) & (c - shift[1] >= 0)
            np.testing.assert_array_equal(res.source[inside], ((r - shift[0]) * W + c - shift[1])[inside])
            # pixels entering the view have no true source: a fresh model, or (as in the
            # paper, which always carries) a neighbour's within the position gate
            src = res.source[~inside]
            got = src >= 0
            d = np.linalg.norm(state.position.reshape(-1, 3)[src[got]] - pos[~inside][got], axis=1)
            assert (d <= tp.Params().position_tolerance * 20.0).all()
            np.testing.assert_array_equal(res.state.age[inside], f + 1)
        state = res.state


def test_large_motion_followed_with_center_map():
    rng = np.random.default_rng(4)
    big = (0, 6)                                 # beyond the 7x7 search window
    pos0 = plane_positions()
    s0 = tp.step(None, frame_buffers(smooth_truth(pos0), rng, pos0), tp.Params(spatial=False), frame=1)
    pos1 = plane_positions(shift=big)
    buf1 = frame_buffers(smooth_truth(pos1), rng, pos1)
    lost = tp.step(s0.state, buf1, tp.Params(spatial=False), frame=2)
    r, c = np.mgrid[0:H, 0:W].astype(np.float64)
    true_src = (r * W + c - big[1]).astype(np.int64)
    assert not (lost.source == true_src).any()             # the true source is out of reach
    center = np.stack([r + 0.5 - big[0], c + 0.5 - big[1]], -1)
    center[:, :big[1]] = np.nan                            # no previous pixel there
    found = tp.step(s0.state, buf1, tp.Params(spatial=False), frame=2, center=center)
    ok = c >= big[1]
    np.testing.assert_array_equal(found.source[ok], true_src[ok])


def test_camera_cut_starts_fresh_models_no_smear():
    rng = np.random.default_rng(5)
    pos0 = plane_positions()
    state = None
    for f in range(1, 6):
        state = tp.step(state, frame_buffers(smooth_truth(pos0), rng, pos0), tp.Params(spatial=False),
                        frame=f).state
    pos1 = pos0 + np.array([50.0, -30.0, 7.0])            # another place of the world
    buf = frame_buffers(np.full((H, W, 3), 2.0), rng, pos1)
    res = tp.step(state, buf, tp.Params(spatial=False), frame=6)
    assert res.info["carried"] == 0.0 and res.info["new"] == 1.0
    np.testing.assert_array_equal(res.image, buf.color.mean)
    assert (res.source == -1).all() and (res.state.age == 1).all()


def test_sudden_illumination_change_restarts_models():
    rng = np.random.default_rng(6)
    pos = plane_positions()
    truth = smooth_truth(pos)
    state = None
    for f in range(1, 11):
        state = tp.step(state, frame_buffers(truth, rng, pos, noise=0.1), tp.Params(spatial=False),
                        frame=f).state
    dark = truth.copy()
    dark[:, :W // 2] *= 0.2                                 # a shadow falls on the left half
    buf = frame_buffers(dark, rng, pos, noise=0.1)
    res = tp.step(state, buf, tp.Params(spatial=False), frame=11)
    left = np.zeros((H, W), bool)
    left[:, :W // 2] = True
    assert res.info["reset_residual"] == pytest.approx(0.5, abs=0.02)
    assert (res.state.age[left] == 1).all() and (res.state.age[~left] == 11).all()
    np.testing.assert_array_equal(res.image[left], buf.color.mean[left])
    # the literal paper (no gate) blurs the change in
    lit = tp.step(state, buf, tp.Params(spatial=False, reset_sigma=0.0, sample_gate=0.0, safe_choice=False),
                  frame=11)
    assert np.abs(lit.image[left] - dark[left]).mean() > 5 * np.abs(res.image[left] - dark[left]).mean()


def test_background_models_only_match_background():
    rng = np.random.default_rng(7)
    pos = plane_positions()
    pos[:, :4] = 0.0                                        # sky on the left
    feats_depth = np.full((H, W, 1), 20.0)
    feats_depth[:, :4] = 0.0
    truth = smooth_truth(plane_positions())
    def buf_():
        colors = [truth * (1 + 0.1 * rng.standard_normal(truth.shape)) for _ in range(4)]
        return Buffers.from_subsets(colors, [4] * 4, [{"position": pos, "depth": feats_depth}] * 4)
    s1 = tp.step(None, buf_(), tp.Params(spatial=False), frame=1)
    assert s1.state.background[:, :4].all() and not s1.state.background[:, 4:].any()
    s2 = tp.step(s1.state, buf_(), tp.Params(spatial=False), frame=2)
    src = s2.source
    assert (src[:, :4] >= 0).all()
    assert ((src[:, :4] % W) < 4).all()                    # sky models come from the sky
    assert ((src[:, 4:] % W) >= 4).all()


def test_hostile_input_finite():
    rng = np.random.default_rng(8)
    pos = plane_positions()
    buf = frame_buffers(smooth_truth(pos), rng, pos)
    s1 = tp.step(None, buf, tp.Params(spatial=False), frame=1)
    bad = buf.copy()
    bad.color.mean[2:4, 2:6] = np.nan
    bad.color.mean[5, 5] = np.inf
    bad.features["position"].mean[7:9, 1:3] = np.nan
    bad.n[10, 10] = 0
    res = tp.step(s1.state, bad, tp.Params(spatial=False), frame=2)
    for a in (res.image, res.error, res.state.beta, res.state.P, res.state.C):
        assert np.isfinite(a).all()
    assert (res.source[2:4, 2:6] >= 0).all()               # kept the carried models
    assert (res.state.age[7:9, 1:3] == 0).all()            # no position: no model
    # with LP as the static filter too
    res_lp = tp.step(s1.state, bad, tp.Params(), frame=2, lp_params={"radius": 2})
    assert np.isfinite(res_lp.image).all() and np.isfinite(res_lp.error).all()
    # everything non-finite
    allbad = buf.copy()
    allbad.color.mean[...] = np.nan
    allbad.features["position"].mean[...] = np.nan
    r2 = tp.step(None, allbad, tp.Params(spatial=False), frame=1)
    assert np.isfinite(r2.image).all() and np.isfinite(r2.error).all()
    # zero size
    e = Buffers.empty(0, 4, ("position",))
    r3 = tp.step(None, e, tp.Params(spatial=False))
    assert r3.image.shape == (0, 4, 3)
    # resolution change without a center map: fresh models
    small = frame_buffers(smooth_truth(plane_positions(6, 8)), rng, plane_positions(6, 8))
    r4 = tp.step(s1.state, small, tp.Params(spatial=False), frame=2)
    assert r4.info["resized"] and r4.info["carried"] == 0.0
    # missing Position pass: clear error
    nopos = Buffers.from_subsets([buf.color.mean], [1])
    with pytest.raises(ValueError, match="Position"):
        tp.step(None, nopos, tp.Params(spatial=False))
    # same frame again (state not older than the frame): fresh, not a crash
    r5 = tp.step(s1.state, buf, tp.Params(spatial=False), frame=1)
    assert r5.info["carried"] == 0.0


# ----------------------------------------------------------------------------- the separated steps
def test_rls_update_recursion_equals_batch_weighted_least_squares():
    """new_models (t = 1) then rls_update for t = 2..T give the closed form over
    the frames (Eq. 6 is exact), and P(T) = (lam^T delta I + sum lam^(T-j) z z^T)^-1."""
    rng = np.random.default_rng(10)
    n, t_n = 9, 15
    for lam, delta in ((0.98, 1e-3), (1.0, 1e-2), (0.7, 0.5)):
        ys = rng.normal(1.0, 0.3, (t_n, n, 3)) + 0.05 * np.arange(t_n)[:, None, None]
        s2 = rng.random((t_n, n))
        beta, P, C = tp.new_models(ys[0], s2[0], delta, lam)
        for t in range(2, t_n + 1):
            z = np.stack([np.ones(n), np.full(n, float(t))], 1)
            beta, P, C, pred, g, v = tp.rls_update(beta, P, C, z, ys[t - 1], s2[t - 1], lam)
            np.testing.assert_allclose(beta, tp.closed_form(ys[:t], lam, delta), rtol=1e-7, atol=1e-9)
            # the gain of the output: beta(t)^T z = (1 - g) pred + g y
            np.testing.assert_allclose(np.einsum("nci,ni->nc", beta, z),
                                       (1 - g)[:, None] * pred + g[:, None] * ys[t - 1], rtol=1e-9)
        z = np.stack([np.ones(t_n), np.arange(1, t_n + 1.0)], 1)
        wts = lam ** (t_n - np.arange(1, t_n + 1.0))
        p_ref = np.linalg.inv(lam ** t_n * delta * np.eye(2) + (z * wts[:, None]).T @ z)
        np.testing.assert_allclose(P, np.broadcast_to(p_ref, P.shape), rtol=1e-7)


def test_new_models_is_the_first_rls_step_from_the_paper_initialisation():
    """beta stays (y, 0) (the residual of the first update is 0), P(1) is
    (lam delta I + z z^T)^-1 with z = (1, 1), and C = sigma^2 e0 e0^T."""
    rng = np.random.default_rng(11)
    y, s2 = rng.random((6, 3)), rng.random(6)
    lam, delta = 0.98, 1e-3
    beta, P, C = tp.new_models(y, s2, delta, lam)
    np.testing.assert_array_equal(beta[..., 0], y)
    np.testing.assert_array_equal(beta[..., 1], 0.0)
    z = np.ones(2)
    np.testing.assert_allclose(P, np.broadcast_to(np.linalg.inv(lam * delta * np.eye(2) + np.outer(z, z)),
                                                  P.shape), rtol=1e-9)
    b_rls, P_rls, _, _, _, _ = tp.rls_update(np.stack([np.stack([y[:, c], np.zeros(6)], -1)
                                                       for c in range(3)], 1),
                                             np.broadcast_to(np.eye(2) / delta, (6, 2, 2)),
                                             np.zeros((6, 2, 2)), np.ones((6, 2)), y, s2, lam)
    np.testing.assert_allclose(b_rls, beta, atol=1e-12)
    np.testing.assert_allclose(P_rls, P, rtol=1e-12)
    np.testing.assert_array_equal(C[:, 0, 0], s2)
    assert not C.reshape(6, -1)[:, 1:].any()


def test_residual_reset_threshold():
    """A model is dropped exactly when mean_c e^2 exceeds
    reset_sigma^2 ((sigma^2 + (0.01 pred)^2) (1 + z^T P z / lam) + v), never without a y or with 0."""
    rng = np.random.default_rng(12)
    n, lam, k = 8, 0.98, 3.0
    z = np.stack([np.ones(n), rng.integers(1, 30, n).astype(float)], 1)
    a = rng.random((n, 2, 2))
    P = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(2)
    pred, s2, v = rng.random((n, 3)), 0.01 * rng.random(n), 0.01 * rng.random(n)
    lim = k ** 2 * ((s2 + tp.REL_FLOOR ** 2 * (pred ** 2).mean(1)) * (1 + np.einsum("ni,nij,nj->n", z, P, z) / lam)
                    + v)
    has_y = np.ones(n, bool)
    for scale, dropped in ((0.999, False), (1.001, True)):
        e = np.repeat(np.sqrt(scale * lim)[:, None], 3, 1)
        np.testing.assert_array_equal(tp.residual_reset(z, P, pred, e, s2, v, has_y, lam, k), dropped)
        assert not tp.residual_reset(z, P, pred, e, s2, v, ~has_y, lam, k).any()
        assert not tp.residual_reset(z, P, pred, e, s2, v, has_y, lam, 0.0).any()
    e = np.full((n, 3), np.nan)                                 # a NaN residual is a miss
    assert tp.residual_reset(z, P, pred, e, s2, v, has_y, lam, k).all()


def test_reset_model_equals_a_fresh_one():
    """Where the residual gate drops the carried model, the new state is the
    paper initialisation: bit for bit what a first frame (no state) gives there."""
    rng = np.random.default_rng(13)
    pos = plane_positions()
    truth = smooth_truth(pos)
    state = None
    params = tp.Params(spatial=False)
    for f in range(1, 6):
        state = tp.step(state, frame_buffers(truth, rng, pos, noise=0.1), params, frame=f).state
    dark = truth.copy()
    dark[:, :W // 2] *= 0.2
    buf = frame_buffers(dark, rng, pos, noise=0.1)
    res = tp.step(state, buf, params, frame=6)
    fresh = tp.step(None, buf, params, frame=6)
    reset = res.source == -1
    assert reset[:, :W // 2].all() and not reset[:, W // 2:].any()
    for name in ("beta", "P", "C", "age", "bias_num", "bias_den"):
        np.testing.assert_array_equal(getattr(res.state, name)[reset], getattr(fresh.state, name)[reset])
    np.testing.assert_array_equal(res.image[reset], fresh.image[reset])
    np.testing.assert_array_equal(res.error[reset], fresh.error[reset])
    beta0, P0, C0 = tp.new_models(buf.color.mean[reset], fresh.error[reset], params.delta, params.lam)
    np.testing.assert_array_equal(res.state.beta[reset], beta0)
    np.testing.assert_array_equal(res.state.P[reset], P0)
    np.testing.assert_array_equal(res.state.C[reset], C0)


def _state_of(position, beta, age, background=None):
    h, w = age.shape
    return tp.TemporalState(1, beta, np.broadcast_to(np.eye(2), (h, w, 2, 2)).copy(),
                            np.zeros((h, w, 2, 2)), age, position,
                            np.zeros((h, w), bool) if background is None else background)


def test_best_previous_minimises_the_paper_product_within_the_gates():
    """Sec. 6: the chosen o minimises |W_o - W_i|^2 |y_i - beta_o^T z|^2 among
    candidates of the pixel's class inside the position gate; with none inside
    the gate the pixel is flagged (a fresh model), with none of its class it is not."""
    hp, wp = 3, 3
    position = np.zeros((hp, wp, 3))
    beta = np.zeros((hp, wp, 3, 2))
    age = np.zeros((hp, wp), np.int64)                           # 0: no model
    age[[1, 0, 1, 2], [1, 1, 0, 2]] = 1
    background = np.zeros((hp, wp), bool)
    # pixel i: W = 0 (a surface point at the origin, not background: its class comes from the mask), y = 1
    position[1, 1] = (0.001, 0, 0); beta[1, 1, :, 0] = 0.0       # nearest, prediction misses by 1
    position[0, 1] = (0.01, 0, 0); beta[0, 1, :, 0] = 0.95       # product 1e-4 * 3 * 0.0025: the best
    position[1, 0] = (0.0, 0, 0); beta[1, 0, :, 0] = 1.0         # product 0 but background
    background[1, 0] = True
    position[2, 2] = (0.5, 0, 0); beta[2, 2, :, 0] = 1.0         # product 0 but outside the gate
    prev, resized = tp.previous_models(_state_of(position, beta, age, background), 2, (1, 1), False, 1)
    assert prev is None and resized                              # another resolution, no centre map
    prev, resized = tp.previous_models(_state_of(position, beta, age, background), 2, (1, 1), True, 1)
    assert not resized and prev.dt == 1
    inp = tp.FrameInputs(np.ones((3, 3)), np.zeros(3), np.ones(3, bool), np.zeros((3, 3)),
                         np.ones(3, bool), None, np.array([False, True, False]), 0.0)
    br, bc = np.array([1, 1, 1]), np.array([1, 1, 1])
    tol2 = np.array([0.1 ** 2, 0.1 ** 2, 1e-6 ** 2])
    # beta_c1 = 0, so the prediction at z = (1, age + dt) is beta_c0
    best, gated = tp.best_previous(prev, br, bc, inp, tol2)
    np.testing.assert_array_equal(best, [0 * wp + 1, 1 * wp + 0, -1])
    np.testing.assert_array_equal(gated, [False, False, True])
    # without a background model in reach the background pixel finds nothing, and is not flagged
    prev_nobg = tp.previous_models(_state_of(position, beta, age), 2, (3, 3), False, 1)[0]
    best, gated = tp.best_previous(prev_nobg, br, bc, inp, tol2)
    assert best[1] == -1 and not gated[1]
    # the window is the window: from a centre out of reach nothing is found
    best, gated = tp.best_previous(prev, br + 5, bc, inp, np.full(3, np.inf))
    assert (best == -1).all() and not gated.any()


def test_search_origin_follows_the_backward_coordinates():
    w = 5
    idx = np.arange(10)
    br, bc = tp.search_origin(idx, w, None, True)
    np.testing.assert_array_equal(br, idx // w)
    np.testing.assert_array_equal(bc, idx % w)
    cen = np.tile([[2.7, -0.2]], (10, 1))
    cen[3] = np.nan
    cen[4] = (1.0, np.inf)
    for same, fallback in ((True, (idx // w, idx % w)), (False, (np.full(10, -10 ** 9),) * 2)):
        br, bc = tp.search_origin(idx, w, cen, same)
        ok = np.ones(10, bool)
        ok[[3, 4]] = False
        assert (br[ok] == 2).all() and (bc[ok] == -1).all()    # the floor, even below 0
        np.testing.assert_array_equal(br[~ok], fallback[0][~ok])
        np.testing.assert_array_equal(bc[~ok], fallback[1][~ok])


def test_bias_estimate_is_the_weighted_mean_excess():
    """B = num / den is the lambda-weighted mean of mean_c e^2 - sigma^2 - v over
    the updates; b^2 = max(0, B); a pixel without y keeps its sums."""
    rng = np.random.default_rng(14)
    lam, n, t_n = 0.9, 5, 7
    num, den = np.zeros(n), np.zeros(n)
    excesses = []
    for _ in range(t_n):
        e, s2, v = rng.normal(0, 1, (n, 3)), rng.random(n), rng.random(n)
        excesses.append((e * e).mean(1) - s2 - v)
        num, den, b2 = tp.bias_estimate(num, den, e, s2, v, np.ones(n, bool), lam)
    wts = lam ** np.arange(t_n - 1, -1, -1.0)
    mean = (wts[:, None] * np.array(excesses)).sum(0) / wts.sum()
    np.testing.assert_allclose(num / den, mean, rtol=1e-12)
    np.testing.assert_allclose(b2, np.maximum(mean, 0.0), rtol=1e-12)
    n2, d2, _ = tp.bias_estimate(num, den, e, s2, v, np.zeros(n, bool), lam)
    np.testing.assert_array_equal(n2, num)
    np.testing.assert_array_equal(d2, den)


# ----------------------------------------------------------------------------- never worse than the frame alone
def _highlight_truth(pos, f, speed, h):
    """smooth_truth plus a bright Gaussian highlight (sigma 2 px, peak 3) moving
    ``speed`` pixels per frame along the middle row: the non-linear change in
    time that Eq. 6's linear model smears (paper Sec. 6, limitations)."""
    r, c = np.mgrid[0:pos.shape[0], 0:pos.shape[1]].astype(np.float64)
    hl = 3.0 * np.exp(-((c - 4.0 - speed * f) ** 2 + (r - h // 2) ** 2) / (2 * 2.0 ** 2))
    return smooth_truth(pos) + hl[..., None]


def _sequence(truths, params, spatial, seed, noise=0.5):
    """Per-frame relMSE (against the known truth) of the temporal output and of
    the frame's own static estimate (LP, or the raw mean), and the last result."""
    from core import lp, metrics
    rng = np.random.default_rng(seed)
    state, out_t, out_s = None, [], []
    for f, truth in enumerate(truths, 1):
        pos = plane_positions(*truth.shape[:2])
        buf = frame_buffers(truth, rng, pos, noise=noise)
        static = lp.reconstruct(buf, {"radius": 2}) if spatial else None
        res = tp.step(state, buf, tp.Params(spatial=spatial, **params), frame=f, static=static)
        state = res.state
        assert np.isfinite(res.image).all() and np.isfinite(res.error).all()
        out_t.append(metrics.relmse(res.image, truth))
        out_s.append(metrics.relmse(static.image if spatial else buf.color.mean, truth))
    return np.array(out_t), np.array(out_s), res


LITERAL = dict(reset_sigma=0.0, sample_gate=0.0, safe_choice=False)


@pytest.mark.parametrize("spatial,speed", [(True, 1.0), (False, 2.0)])
def test_moving_highlight_never_worse_than_the_frame_alone(spatial, speed):
    """A highlight moving 1-2 px per frame over a still plane: with the gates and
    the safe choice the temporal output's error is <= the static estimate's on
    every frame (and lower at the end); the literal paper (no gate, no choice)
    smears the highlight and is worse on most frames."""
    h, w = 24, 32
    pos = plane_positions(h, w)
    truths = [_highlight_truth(pos, f, speed, h) for f in range(1, 11)]
    err_t, err_s, res = _sequence(truths, {}, spatial, seed=21)
    assert (err_t <= err_s).all(), (err_t / err_s).round(3)
    assert err_t[-1] < 0.8 * err_s[-1]
    assert res.info["fallback"] > 0 or res.info["reset_samples"] + res.info["reset_residual"] > 0
    lit_t, lit_s, _ = _sequence(truths, LITERAL, spatial, seed=21)
    np.testing.assert_array_equal(lit_s, err_s)                 # the same frames and samples
    assert (lit_t > lit_s).sum() >= 5 and lit_t[-1] > 2 * lit_s[-1]


def test_still_sequence_strictly_better_after_a_few_frames():
    """Nothing moves: from the third frame on the temporal output beats the
    static LP estimate on every frame, by more each frame, and the safe choice
    keeps most pixels on the temporal output."""
    pos = plane_positions(24, 24)
    truths = [smooth_truth(pos)] * 8
    err_t, err_s, res = _sequence(truths, {}, True, seed=22, noise=0.6)
    assert err_t[0] == err_s[0]                                  # frame 1: new models output y
    assert (err_t[2:] < err_s[2:]).all()
    assert (err_t / err_s)[-1] < 0.7
    assert res.info["fallback"] < 0.2 and res.info["carried"] == 1.0


def test_sample_reset_is_the_chi_square_test_against_the_samples():
    """Dropped exactly when sum_c (mean_c - pred_c)^2 / (V_c + (sigma^2 +
    (0.01 pred_c)^2)(1 + z^T P z / lambda) + v) exceeds the threshold; channels
    with unknown variance add 0; never without a y, a mean, or with threshold 0."""
    rng = np.random.default_rng(15)
    n, lam, thr = 10, 0.98, 16.27
    z = np.stack([np.ones(n), rng.integers(1, 20, n).astype(float)], 1)
    a = rng.random((n, 2, 2))
    P = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(2)
    pred, V = rng.random((n, 3)) + 0.1, 0.01 * rng.random((n, 3))
    s2, v = 0.01 * rng.random(n), 0.01 * rng.random(n)
    s = np.einsum("ni,nij,nj->n", z, P, z)
    den = V + (s2[:, None] + (0.01 * pred) ** 2) * (1 + s / lam)[:, None] + v[:, None]
    unit = rng.normal(size=(n, 3))
    unit /= np.sqrt((unit ** 2 / den).sum(1, keepdims=True))     # q(pred + unit) = 1
    has = np.ones(n, bool)
    for scale, dropped in ((0.999, False), (1.001, True)):
        mean = pred + np.sqrt(scale * thr) * unit
        np.testing.assert_array_equal(tp.sample_reset(z, P, pred, mean, V, s2, v, has, lam, thr), dropped)
        assert not tp.sample_reset(z, P, pred, mean, V, s2, v, ~has, lam, thr).any()
        assert not tp.sample_reset(z, P, pred, mean, V, s2, v, has, lam, 0.0).any()
        assert not tp.sample_reset(z, P, pred, None, None, s2, v, has, lam, thr).any()
    mean = pred + 10 * np.sqrt(thr) * unit
    assert not tp.sample_reset(z, P, pred, mean, np.full((n, 3), np.inf), s2, v, has, lam, thr).any()
    pred_bad = pred.copy()
    pred_bad[0, 1] = np.nan                                       # a NaN prediction is a miss
    assert tp.sample_reset(z, P, pred_bad, pred, V, s2, v, has, lam, thr)[0]


def test_box_mean_equals_a_direct_window_average():
    rng = np.random.default_rng(16)
    x = rng.normal(size=(7, 9))
    x[rng.random((7, 9)) < 0.3] = np.nan
    x[0, 0] = np.inf
    for r in (0, 1, 2):
        got, cnt = tp.box_mean(x, r, True)
        for i in range(7):
            for j in range(9):
                win = x[max(0, i - r):i + r + 1, max(0, j - r):j + r + 1]
                fin = win[np.isfinite(win)]
                assert cnt[i, j] == fin.size
                if fin.size:
                    assert got[i, j] == pytest.approx(fin.mean(), rel=1e-12)
                else:
                    assert np.isnan(got[i, j])


def test_safe_choice_takes_the_static_estimate_where_the_temporal_error_is_not_lower():
    """err_T = z^T C z + (1 - g)^2 max(b^2, pooled excess beyond BIAS_Z standard
    errors); a carried pixel keeps the temporal output iff err_T < the window mean
    of sigma^2, else takes y with sigma^2; pixels not carried are untouched."""
    h, w = 5, 6
    rng = np.random.default_rng(17)
    image, y = rng.random((h, w, 3)), rng.random((h, w, 3))
    error, s2 = rng.random((h, w)), np.full((h, w), 0.01)
    carried = np.ones((h, w), bool)
    carried[0, :] = False
    terms = {"excess": np.zeros((h, w)), "excess_s": np.full((h, w), np.nan), "noise": np.full((h, w), 0.01),
             "noise_s": np.full((h, w), np.nan), "gain": np.full((h, w), 0.5),
             "var_out": np.full((h, w), 0.004), "bias2": np.zeros((h, w))}
    terms["excess"][0, :] = np.nan
    terms["excess"][3, 4] = 1.0                                   # a big miss: it and its 3x3 window
    terms["bias2"][1, 0] = 0.03                                   # a known bias: 0.004 + 0.25 * 0.03 > 0.01
    img, err, fb = tp.safe_choice(image, error, y, s2, carried, terms, 1)
    expect = np.zeros((h, w), bool)
    expect[2:5, 3:6] = True
    expect[1, 0] = True
    np.testing.assert_array_equal(fb, expect)
    np.testing.assert_array_equal(img[fb], y[fb])
    np.testing.assert_array_equal(img[~fb], image[~fb])
    np.testing.assert_array_equal(err[~carried], error[~carried])
    np.testing.assert_array_equal(err[fb], s2[fb])
    keep = carried & ~fb
    pooled, cnt = tp.box_mean(terms["excess"], 1, True)
    b_now = np.maximum(pooled - tp.BIAS_Z * np.sqrt(2 / (3 * cnt)) * 0.01, 0)
    np.testing.assert_allclose(err[keep], (0.004 + 0.25 * np.maximum(b_now, terms["bias2"]))[keep], rtol=1e-12)

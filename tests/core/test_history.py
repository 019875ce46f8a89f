"""Temporal blend of reconstructed frames (core/history.py)."""
from __future__ import annotations

import numpy as np
import pytest

from core import history as hi
from core.buffers import Buffers

H, W = 24, 32
CAM = np.array([0.0, 0.0, 20.0])
PIX = 0.01


def plane(shift=(0.0, 0.0), h=H, w=W, z=0.0):
    """A plane z = const seen from above: pixel (r, c) with image shift (sy, sx)
    shows the world point PIX * (c + 0.5 - sx, r + 0.5 - sy, z)."""
    r, c = np.mgrid[0:h, 0:w].astype(np.float64)
    pos = np.stack([PIX * (c + 0.5 - shift[1]), PIX * (r + 0.5 - shift[0]), np.full_like(r, z)], -1)
    normal = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (h, w, 3)).copy()
    bg = np.zeros((h, w), bool)
    return hi.Surface(pos, bg, normal, None, hi.footprint(pos, bg))


def identity(h=H, w=W, shift=(0.0, 0.0)):
    """Backward coordinates of a pure image translation: current pixel (r, c)
    was at (r + 0.5 - sy, c + 0.5 - sx) in the previous frame."""
    r, c = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([r + 0.5 - shift[0], c + 0.5 - shift[1]], -1)


def noisy(truth, sd, rng):
    return truth + sd * rng.standard_normal(truth.shape)


def run_sequence(truth, sd, frames, params, rng, surface=None):
    surface = surface or plane()
    state, out = None, []
    for _ in range(frames):
        img = noisy(truth, sd, rng)
        res = hi.blend(img, np.full(truth.shape[:2], sd ** 2), surface, state, identity(), CAM, params)
        state = res.history
        out.append(res)
    return out


def test_first_frame_is_the_reconstruction():
    rng = np.random.default_rng(0)
    img = rng.random((H, W, 3))
    err = rng.random((H, W))
    res = hi.blend(img, err, plane(), None, None, CAM)
    np.testing.assert_array_equal(res.image, img)
    np.testing.assert_array_equal(res.error, err)
    np.testing.assert_array_equal(res.history.length, 1.0)


def test_two_frames_with_equal_errors_give_their_mean():
    rng = np.random.default_rng(1)
    a, b = rng.random((H, W, 3)), rng.random((H, W, 3))
    err = np.full((H, W), 1.0)  # large: the change test passes everywhere
    first = hi.blend(a, err, plane(), None, None, CAM)
    second = hi.blend(b, err, plane(), first.history, identity(), CAM)
    np.testing.assert_allclose(second.image, (a + b) / 2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(second.error, 0.5, rtol=0, atol=1e-12)  # (1/4 + 1/4) * 1
    assert second.info["history_fraction"] == 1.0


def test_static_sequence_error_falls_like_the_running_mean_and_the_estimate_follows():
    """Independent noise, exact per-frame errors: after n frames the output is
    the running mean of min(n, max_frames) frames (error sd^2 / n), measured
    over pixels, and the reported error says so.  (A wide bias window: with
    many degrees of freedom the bias estimate of pure noise is ~0.)"""
    rng = np.random.default_rng(2)
    truth = np.full((H, W, 3), 0.5)
    sd = 0.05
    out = run_sequence(truth, sd, 6, hi.Params(max_frames=8, pool_radius=3, bias_radius=8), rng)
    mse = [float(np.mean((r.image - truth) ** 2)) for r in out]
    for n in range(1, 7):
        assert mse[n - 1] == pytest.approx(sd ** 2 / n, rel=0.25)
        assert 0.98 <= float(np.mean(out[n - 1].error)) / (sd ** 2 / n) <= 1.2  # conservative, bounded
    assert all(b < a for a, b in zip(mse, mse[1:]))


@pytest.mark.parametrize("method", ["uniform", "oidn"])
def test_the_bias_estimate_of_pure_noise_is_conservative(method):
    """With the auto windows (small), the bias estimated from pure noise is
    positive on some pixels: the reported error stays at or above the true
    one, and the output still beats the frame alone."""
    rng = np.random.default_rng(7)
    truth = np.full((H, W, 3), 0.5)
    sd = 0.05
    out = run_sequence(truth, sd, 4, hi.resolve(hi.Params(input_frames=1), method), rng)  # the output blend
    for n, res in enumerate(out, 1):
        true = float(np.mean((res.image - truth) ** 2))
        assert float(np.mean(res.error)) >= 0.9 * true
        if n > 1:
            assert true < 0.75 * sd ** 2


def test_max_frames_bounds_the_history():
    rng = np.random.default_rng(3)
    truth = np.full((H, W, 3), 0.5)
    sd = 0.05
    out = run_sequence(truth, sd, 12, hi.Params(max_frames=3, pool_radius=3, bias_radius=8), rng)
    # the weight of the current frame never drops below 1/3: error at least that of an EMA with alpha 1/3
    ema = (1 / 3) ** 2 / (1 - (2 / 3) ** 2) * sd ** 2  # 0.2 sd^2
    assert float(np.mean(out[-1].error)) == pytest.approx(ema, rel=0.06)
    assert float(np.mean((out[-1].image - truth) ** 2)) == pytest.approx(ema, rel=0.3)
    one = run_sequence(truth, sd, 3, hi.Params(max_frames=1), np.random.default_rng(3))
    np.testing.assert_array_equal(one[-1].history.length, 1.0)
    assert one[-1].info["history_weight"] == 0.0


def test_a_change_beyond_the_errors_drops_the_history_there():
    """A highlight that moves: where the new frame differs by 10 sigma, the
    output is the new frame's own, exactly; elsewhere the history is used."""
    rng = np.random.default_rng(4)
    sd = 0.01
    truth0 = np.full((H, W, 3), 0.5)
    truth1 = truth0.copy()
    truth1[8:16, 10:20] += 10 * sd * np.sqrt(2) * 3
    err = np.full((H, W), sd ** 2)
    first = hi.blend(noisy(truth0, sd, rng), err, plane(), None, None, CAM, hi.Params(pool_radius=0))
    cur = noisy(truth1, sd, rng)
    second = hi.blend(cur, err, plane(), first.history, identity(), CAM, hi.Params(pool_radius=0))
    np.testing.assert_array_equal(second.image[8:16, 10:20], cur[8:16, 10:20])
    assert second.info["changed_fraction"] >= 80 / (H * W)
    outside = np.ones((H, W), bool)
    outside[8:16, 10:20] = False
    assert np.mean(second.history.length[outside] == 2.0) > 0.99


def test_a_firefly_with_its_own_large_error_takes_the_history():
    """A firefly in this frame whose per-pixel error says so (pooling over 7x7
    would dilute it 49 times): the history is kept there and outweighs it, so
    the output is much closer to the truth than the firefly."""
    rng = np.random.default_rng(8)
    sd = 0.01
    truth = np.full((H, W, 3), 0.5)
    err = np.full((H, W), sd ** 2)
    params = hi.Params(pool_radius=3, bias_radius=1, max_frames=8)
    first = hi.blend(noisy(truth, sd, rng), err, plane(), None, None, CAM, params)
    cur = noisy(truth, sd, rng)
    cur[12, 16] = 20.0
    err_cur = err.copy()
    err_cur[12, 16] = 20.0 ** 2  # its estimate: a one-sample spike of ~20
    second = hi.blend(cur, err_cur, plane(), first.history, identity(), CAM, params)
    assert second.history.length[12, 16] == 2.0  # not dropped by the change test
    assert abs(second.image[12, 16, 0] - 0.5) <= (20.0 - 0.5) / params.max_frames + 1e-9


def test_another_surface_is_never_blended():
    """Disocclusion: where the previous frame saw a surface 1 unit closer (an
    occluder that moved away), the history is not used, even if it agrees."""
    rng = np.random.default_rng(5)
    img = np.full((H, W, 3), 0.5)
    err = np.full((H, W), 1.0)
    prev_surface = plane()
    prev_surface.position[:, :12, 2] = 1.0
    first = hi.blend(img, err, prev_surface, None, None, CAM)
    cur = noisy(img, 0.1, rng)
    second = hi.blend(cur, err, plane(), first.history, identity(), CAM)
    np.testing.assert_array_equal(second.image[:, :11], cur[:, :11])  # col 11 has one tap on the plane
    assert np.all(second.history.length[:, 13:] == 2.0)


def test_normals_and_object_ids_separate_surfaces():
    img = np.full((H, W, 3), 0.5)
    err = np.full((H, W), 1.0)
    prev = plane()
    prev.normal[:, :8] = [1.0, 0.0, 0.0]
    prev.object_index = np.zeros((H, W))
    prev.object_index[:, 24:] = 3.0
    first = hi.blend(img, err, prev, None, None, CAM)
    cur = plane()
    cur.object_index = np.zeros((H, W))
    second = hi.blend(img + 0.1, err, cur, first.history, identity(), CAM)
    assert np.all(second.history.length[:, :8] == 1.0)
    assert np.all(second.history.length[:, 24:] == 1.0)
    assert np.all(second.history.length[:, 8:24] == 2.0)


@pytest.mark.parametrize("resample", ["bilinear", "catmull-rom"])
def test_warp_is_exact_on_a_translated_linear_image(resample):
    """History linear in the previous frame's pixel coordinates, camera moved
    by a fractional shift: the warped value is that linear function at the
    shifted point (closed form; both resamplings reproduce linear functions),
    away from the border."""
    r, c = np.mgrid[0:H, 0:W].astype(np.float64)
    lin = np.stack([0.01 * r + 0.02 * c, 0.03 * r, 0.5 + 0.0 * r], -1)
    shift = (0.3, -0.6)
    prev = plane()
    hist = hi.History(lin, np.full((H, W), 0.1), np.ones((H, W)), prev)
    cur = plane(shift)
    W_, e, L, valid, _ = hi.warp(hist, identity(shift=shift), cur, CAM, hi.Params(resample=resample))
    inner = (slice(2, H - 2), slice(2, W - 2))
    rr, cc = r - shift[0], c - shift[1]
    expect = np.stack([0.01 * rr + 0.02 * cc, 0.03 * rr, 0.5 + 0.0 * rr], -1)
    assert valid[inner].all()
    np.testing.assert_allclose(W_[inner], expect[inner], atol=1e-12)
    np.testing.assert_allclose(e[inner], 0.1, atol=1e-12)


def test_catmull_rom_weights_sum_to_one_and_interpolate():
    t = np.linspace(0.0, 0.999, 50)
    w = hi.catmull_rom_weights(t)
    np.testing.assert_allclose(sum(w), 1.0, atol=1e-12)
    np.testing.assert_allclose(sum(wi * k for wi, k in zip(w, (-1, 0, 1, 2))), t, atol=1e-12)  # linear exact
    np.testing.assert_allclose([wi[0] for wi in w], [0.0, 1.0, 0.0, 0.0], atol=1e-12)  # t = 0: the pixel


def _warp_1d(image, shift, resample):
    """Warp ``image`` on the plane moved by ``shift`` px along x, with no
    distance tolerance: only the footprint slack lets the spline's outer taps
    (1.5 px away) count as the same surface."""
    hist = hi.History(image, np.full((H, W), 0.1), np.ones((H, W)), plane())
    return hi.warp(hist, identity(shift=(0.0, shift)), plane((0.0, shift)), CAM,
                   hi.Params(resample=resample, tolerance=0.0))


def test_catmull_rom_keeps_the_detail_bilinear_blurs():
    """A sinusoid of period 8 px moved by half a pixel (bilinear's worst
    case: it averages two neighbours): Catmull-Rom's error, clamp included,
    is well under half of bilinear's, against the closed form."""
    c = np.arange(W, dtype=np.float64)
    wave = lambda x: 0.5 + 0.4 * np.cos(2 * np.pi * x / 8.0)  # noqa: E731
    img = np.broadcast_to(wave(c)[None, :, None], (H, W, 3)).copy()
    shift = -0.5
    truth = wave(c - shift)[None, :, None]
    inner = (slice(None), slice(3, W - 3))
    errs = {}
    for resample in ("bilinear", "catmull-rom"):
        out, _, _, valid, spline = _warp_1d(img, shift, resample)
        assert valid[inner].all() and spline[inner].all() == (resample == "catmull-rom")
        errs[resample] = np.mean((out - truth)[inner] ** 2)
    assert errs["catmull-rom"] < 0.5 * errs["bilinear"]


def test_catmull_rom_never_rings_and_is_bilinear_at_silhouettes():
    """A step from 0 to 1: the spline would overshoot below 0 and above 1; the
    clamp to the 2x2 nearest values keeps the output in [0, 1].  Where a
    tap of the 4x4 window is another object but the 2x2 taps are not, the
    value is the bilinear one."""
    img = np.zeros((H, W, 3))
    img[:, W // 2:] = 1.0
    out, _, _, valid, _ = _warp_1d(img, -0.3, "catmull-rom")
    assert valid[:, 2:-2].all() and out.min() >= 0.0 and out.max() <= 1.0
    # the spline unclamped would ring: check the test can fail
    w = hi.catmull_rom_weights(np.array(0.3))
    assert w[0] < 0 and w[3] < 0
    smooth = np.broadcast_to((np.arange(W, dtype=np.float64) ** 2 / W ** 2)[None, :, None], (H, W, 3)).copy()
    prev = plane()
    prev.object_index = np.zeros((H, W))
    prev.object_index[:, 20:] = 2.0
    cur = plane((0.0, -0.3))
    cur.object_index = np.zeros((H, W))
    cur.object_index[:, 20:] = 2.0
    hist = hi.History(smooth, np.full((H, W), 0.1), np.ones((H, W)), prev)
    coords = identity(shift=(0.0, -0.3))
    cr, *_ = hi.warp(hist, coords, cur, CAM, hi.Params(resample="catmull-rom"))
    bl, *_ = hi.warp(hist, coords, cur, CAM, hi.Params(resample="bilinear"))
    # current col 18 reads previous cols 17-20 (20: the other object): bilinear there, spline at col 10
    np.testing.assert_array_equal(cr[:, 18], bl[:, 18])
    assert np.abs(cr[:, 10] - bl[:, 10]).max() > 1e-6


def test_camera_cut_starts_over():
    img = np.full((H, W, 3), 0.5)
    err = np.full((H, W), 1.0)
    first = hi.blend(img, err, plane(), None, None, CAM)
    cur = img + 0.01
    res = hi.blend(cur, err, plane(), first.history, np.full((H, W, 2), np.nan), CAM)
    np.testing.assert_array_equal(res.image, cur)
    assert res.info["cut"]
    far = hi.blend(cur, err, plane(z=5.0), first.history, identity(), CAM)  # every tap another surface
    assert far.info["cut"]
    np.testing.assert_array_equal(far.image, cur)


def test_hostile_input_gives_finite_output():
    rng = np.random.default_rng(6)
    img = rng.random((H, W, 3))
    img[0, 0] = np.nan
    img[1, 1] = np.inf
    err = rng.random((H, W))
    err[2, 2] = np.nan
    err[3, 3] = np.inf
    first = hi.blend(img, err, plane(), None, None, CAM)
    assert np.all(np.isfinite(first.image)) and np.all(np.isfinite(first.error))
    coords = identity()
    coords[4, 4] = [np.inf, 1.0]
    coords[5, 5] = [-100.0, 1e9]
    second = hi.blend(img, err, plane(), first.history, coords, CAM)
    assert np.all(np.isfinite(second.image)) and np.all(np.isfinite(second.error))
    assert np.all(second.error >= 0)
    empty = hi.blend(np.zeros((0, 0, 3)), np.zeros((0, 0)), plane(h=0, w=0), None, None, CAM)
    assert empty.image.shape == (0, 0, 3)


def test_surface_from_buffers_reads_the_passes_and_refuses_without_position():
    pos = plane().position
    feats = {"position": pos, "normal": 2.0 * plane().normal, "object_index": np.zeros((H, W, 1))}
    buf = Buffers.from_subsets([np.full((H, W, 3), 0.5)] * 2, [2, 2], [feats] * 2)
    s = hi.Surface.from_buffers(buf)
    np.testing.assert_allclose(s.normal[..., 2], 1.0)
    np.testing.assert_allclose(s.footprint, PIX)
    assert not s.background.any()
    bare = Buffers.from_subsets([np.full((H, W, 3), 0.5)] * 2, [2, 2], [{}] * 2)
    with pytest.raises(ValueError, match="Position"):
        hi.Surface.from_buffers(bare)


def test_auto_resampling_follows_the_method():
    assert hi.resolve(hi.Params(), "uniform").resample == "bilinear"
    assert hi.resolve(hi.Params(), "oidn").resample == "catmull-rom"
    assert hi.resolve(hi.Params(resample="bilinear"), "lp").resample == "bilinear"
    assert hi.resolve(hi.Params(), "oidn").input_frames == 2
    assert hi.resolve(hi.Params(), "var").input_frames == 4
    assert hi.resolve(hi.Params(input_frames=3), "uniform").input_frames == 3
    # the output blend: off where the input carries the history, else 8 frames
    assert hi.resolve(hi.Params(), "oidn").max_frames == 1
    assert hi.resolve(hi.Params(input_frames=1), "oidn").max_frames == 8
    assert hi.resolve(hi.Params(), "uniform").max_frames == 1
    assert hi.resolve(hi.Params(input_frames=1), "uniform").max_frames == 8
    assert hi.resolve(hi.Params(), None).max_frames == 8
    assert hi.resolve(hi.Params(max_frames=3), "lp").max_frames == 3
    # lp: a longer input history and a 2-frame output blend on top (measured better for it alone)
    lp = hi.resolve(hi.Params(), "lp")
    assert (lp.input_frames, lp.max_frames) == (8, 2)
    assert hi.resolve(hi.Params(input_frames=2), "lp").max_frames == 2
    assert hi.resolve(hi.Params(input_frames=1), "lp").max_frames == 8


# ------------------------------------------------------- input accumulation
def frame_buffers(truth, sd, rng, groups=8, per=2, surface=None, exact=True):
    """Buffers of one frame of the plane: ``groups`` sample groups of ``per``
    samples, each group's mean ``truth + N(0, sd^2 / per)``; ``exact``: the
    colour's M2 set so the variance of the mean is the true one, sd^2 / n."""
    s = surface or plane()
    feats = {"position": s.position, "normal": s.normal}
    colors = [truth + sd / np.sqrt(per) * rng.standard_normal(truth.shape) for _ in range(groups)]
    buf = Buffers.from_subsets(colors, [per] * groups, [feats] * groups)
    if exact:
        n = groups * per
        buf.color.m2 = np.full(truth.shape, sd ** 2 / n * (groups - 1) * n)
    return buf


def accumulate_sequence(truth, sd, frames, params, rng, shift=(0.0, 0.0)):
    state, out = None, []
    for _ in range(frames):
        buf = frame_buffers(truth, sd, rng)
        res = hi.accumulate(buf, state, identity(shift=shift), CAM, params)
        state = res.history
        out.append((buf, res))
    return out


def test_input_accumulation_first_frame_is_the_frame_and_two_frames_average():
    """Frame 1 is returned as it is; with two frames of equal, exact variances
    the accumulated buffers are their mean, half by half, with twice the
    samples and half the variance of the mean, and the halves still add up
    to the whole."""
    rng = np.random.default_rng(10)
    truth = np.full((H, W, 3), 0.5)
    p = hi.Params(input_frames=2, input_pool_radius=8, z=100.0)  # wide: the bias of pure noise ~ 0
    (b1, r1), (b2, r2) = accumulate_sequence(truth, 0.05, 2, p, rng)
    assert r1.buffers is b1 and r1.info["input_history_fraction"] == 0.0
    (na1, ca1, _), (nb1, cb1, _) = b1.halves()
    (na2, ca2, _), (nb2, cb2, _) = b2.halves()
    acc = r2.buffers
    assert r2.info["input_history_fraction"] == 1.0
    (na, ca, _), (nb, cb, _) = acc.halves()
    # this frame's weight per pixel, n / n': 1/2 up to the (small) bias estimate of pure noise
    w = (b2.n / acc.n)[..., None]
    assert np.median(w) == pytest.approx(0.5, abs=1e-9) and np.mean(w) == pytest.approx(0.5, abs=0.01)
    np.testing.assert_allclose(acc.color.mean, w * b2.color.mean + (1 - w) * b1.color.mean, rtol=1e-12)
    np.testing.assert_allclose(ca, w * ca2 + (1 - w) * ca1, rtol=1e-12)
    np.testing.assert_allclose(cb, w * cb2 + (1 - w) * cb1, rtol=1e-12)
    np.testing.assert_allclose(na[..., None] * ca + nb[..., None] * cb, acc.n[..., None] * acc.color.mean,
                               rtol=1e-12)
    np.testing.assert_allclose(np.median(acc.n / b2.n), 2.0, rtol=0.03)
    ratio = acc.variance_of_mean() / b2.variance_of_mean()
    assert np.median(ratio) == pytest.approx(0.5, rel=0.05)
    assert acc.features["normal"].mean is b2.features["normal"].mean  # this frame's features
    np.testing.assert_allclose(acc.feature_variance("position"), b2.feature_variance("position"))
    assert not np.shares_memory(acc.color.mean, b2.color.mean)  # the frame's buffers are not changed


def test_input_history_is_bounded_and_its_error_follows():
    """With ``input_frames = 2`` the current frame keeps at least half of the
    weight: a static sequence settles at the moving average with factor 1/2,
    whose variance is sd^2 / n * (1/2) / (2 - 1/2) = sd^2 / (3 n); the
    reported variance of the mean says the same, and the halves stay
    independent (their errors uncorrelated, as a dual-buffer estimate needs)."""
    rng = np.random.default_rng(11)
    truth = np.full((H, W, 3), 0.5)
    sd = 0.05
    out = accumulate_sequence(truth, sd, 10, hi.Params(input_frames=2, input_pool_radius=8, z=100.0), rng)
    n = out[0][0].n[0, 0]
    errs = [float(np.mean((r.buffers.color.mean - truth) ** 2)) for _, r in out[5:]]
    assert np.mean(errs) == pytest.approx(sd ** 2 / (3 * n), rel=0.15)
    reported = np.mean([np.median(r.buffers.variance_of_mean()) for _, r in out[5:]])
    assert reported == pytest.approx(sd ** 2 / (3 * n), rel=0.15)
    (_, ca, _), (_, cb, _) = out[-1][1].buffers.halves()
    corr = np.corrcoef((ca - truth).ravel(), (cb - truth).ravel())[0, 1]
    assert abs(corr) < 0.1
    longer = accumulate_sequence(truth, sd, 10, hi.Params(input_frames=8, input_pool_radius=8, z=100.0), rng)
    assert np.mean([np.mean((r.buffers.color.mean - truth) ** 2) for _, r in longer[7:]]) < 0.7 * np.mean(errs)


def test_input_accumulation_off_and_on_a_change_keeps_the_frame():
    """``input_frames = 1`` carries nothing; where the scene changed beyond
    the errors the frame's own samples are kept exactly."""
    rng = np.random.default_rng(12)
    truth = np.full((H, W, 3), 0.5)
    b1 = frame_buffers(truth, 0.01, rng)
    first = hi.accumulate(b1, None, None, CAM, hi.Params())
    changed = truth.copy()
    changed[:, : W // 2] = 2.0
    b2 = frame_buffers(changed, 0.01, rng)
    off = hi.accumulate(b2, first.history, identity(), CAM, hi.Params(input_frames=1))
    assert off.buffers is b2
    res = hi.accumulate(b2, first.history, identity(), CAM, hi.Params(input_pool_radius=0))
    left = (slice(None), slice(0, W // 2 - 1))
    np.testing.assert_array_equal(res.buffers.color.mean[left], b2.color.mean[left])
    np.testing.assert_array_equal(res.buffers.n[left], b2.n[left])
    assert res.info["input_changed_fraction"] >= 0.45
    right = (slice(None), slice(W // 2 + 1, None))
    assert np.all(res.buffers.n[right] > b2.n[right])


def test_input_accumulation_on_a_camera_cut_or_another_surface_starts_over():
    rng = np.random.default_rng(13)
    truth = np.full((H, W, 3), 0.5)
    first = hi.accumulate(frame_buffers(truth, 0.01, rng), None, None, CAM)
    b2 = frame_buffers(truth, 0.01, rng)
    cut = hi.accumulate(b2, first.history, np.full((H, W, 2), np.nan), CAM)
    assert cut.buffers is b2 and cut.info["input_cut"]
    far = frame_buffers(truth, 0.01, rng, surface=plane(z=5.0))
    other = hi.accumulate(far, first.history, identity(), CAM)
    assert other.buffers is far and other.info["input_cut"]


def test_input_accumulation_of_hostile_input_is_finite():
    rng = np.random.default_rng(14)
    truth = np.full((H, W, 3), 0.5)
    b1 = frame_buffers(truth, 0.05, rng)
    b1.color.mean[0, 0] = np.nan
    b1.color.m2[1, 1] = np.inf
    b1.k[2, 2] = 1.0  # no variance
    b1.n[3, 3] = 0.0
    first = hi.accumulate(b1, None, None, CAM)
    assert np.all(np.isfinite(first.history.image)) and not np.any(np.isnan(first.history.error))
    b2 = frame_buffers(truth, 0.05, rng)
    b2.color.mean[4, 4] = np.inf
    coords = identity()
    coords[5, 5] = [np.inf, 1.0]
    res = hi.accumulate(b2, first.history, coords, CAM)
    acc = res.buffers
    ok = np.ones((H, W), bool)
    ok[4, 4] = False
    assert np.all(np.isfinite(acc.color.mean[ok])) and np.all(np.isfinite(acc.n))
    assert np.all(acc.n >= b2.n) and not np.any(np.isnan(acc.variance_of_mean()))
    assert np.all(np.isfinite(res.history.image)) and not np.any(np.isnan(res.history.error))
    # the pixels whose previous value was not usable keep this frame's samples
    for r, c in ((0, 0), (1, 1), (2, 2), (3, 3), (5, 5)):
        assert acc.n[r, c] == b2.n[r, c]


def test_input_history_skips_mostly_specular_pixels():
    """With a limit of 0.5: where glossy light (light pass x colour pass) is
    most of the pixel's luminance the samples are not carried (reflections
    move unlike their surface); a share of 1 (the default) lifts the limit."""
    rng = np.random.default_rng(15)
    truth = np.full((H, W, 3), 0.5)
    s = plane()
    light = np.zeros((H, W, 3))
    light[:, : W // 2] = 0.8     # x colour 0.5 = 0.4 of 0.5: share 0.8 on the left
    light[:, W // 2:] = 0.2      # 0.1 of 0.5: share 0.2 on the right
    feats = {"position": s.position, "normal": s.normal, "glossy": light, "glossy_color": np.full((H, W, 3), 0.5)}

    def frame():
        colors = [truth + 0.05 * rng.standard_normal(truth.shape) for _ in range(8)]
        return Buffers.from_subsets(colors, [2] * 8, [feats] * 8)

    b1 = frame()
    share = hi.specular_share(b1)
    assert np.median(share[:, : W // 2]) == pytest.approx(0.8, rel=0.2)
    assert np.median(share[:, W // 2:]) == pytest.approx(0.2, rel=0.2)
    first = hi.accumulate(b1, None, None, CAM)
    b2 = frame()
    res = hi.accumulate(b2, first.history, identity(), CAM, hi.Params(z=100.0, input_max_specular_share=0.5))
    np.testing.assert_array_equal(res.buffers.n[:, : W // 2], b2.n[:, : W // 2])
    assert np.mean(res.buffers.n[:, W // 2:] > b2.n[:, W // 2:]) > 0.9
    free = hi.accumulate(b2, first.history, identity(), CAM, hi.Params(z=100.0))
    assert np.mean(free.buffers.n[:, : W // 2] > b2.n[:, : W // 2]) > 0.9
    assert not hi.specular_share(Buffers.from_subsets([truth] * 2, [2, 2], [{"position": s.position}] * 2)).any()


def test_the_warp_is_reused_within_a_frame_until_its_samples_double():
    """``cache``: a second call of the same frame with under twice the samples
    reuses the warp (the coordinates are not asked for again) and gives the
    same buffers as a fresh call (the surface did not change); at twice the
    samples the warp is computed again."""
    rng = np.random.default_rng(16)
    truth = np.full((H, W, 3), 0.5)
    first = hi.accumulate(frame_buffers(truth, 0.05, rng), None, None, CAM)
    asked = []

    def coords():
        asked.append(1)
        return identity()

    cache = {}
    small = frame_buffers(truth, 0.05, rng, groups=4)
    hi.accumulate(small, first.history, coords, CAM, cache=cache)
    more = frame_buffers(truth, 0.05, rng, groups=6)
    again = hi.accumulate(more, first.history, coords, CAM, cache=cache)
    assert len(asked) == 1
    fresh = hi.accumulate(more, first.history, identity(), CAM)
    np.testing.assert_array_equal(again.buffers.color.mean, fresh.buffers.color.mean)
    np.testing.assert_array_equal(again.buffers.n, fresh.buffers.n)
    hi.accumulate(frame_buffers(truth, 0.05, rng, groups=8), first.history, coords, CAM, cache=cache)
    assert len(asked) == 2

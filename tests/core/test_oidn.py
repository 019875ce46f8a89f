"""core/oidn.py: OIDN as a reconstruction, the dual-buffer error estimate and
its constant (Monte Carlo), the water-filling sampler, the method in the
loop, and the disjoint halves it reads from core/buffers.py."""
import subprocess
import sys
import os

import numpy as np
import pytest

from core import methods, oidn
from core.buffers import Buffers
from core.filters import box_mean
from core.method import params_from_dict
from core.pipeline import AdaptiveRun, Options

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
needs_pyoidn = pytest.mark.skipif(not oidn.pyoidn_available(), reason="pyoidn not installed")


def _truth(h=32, w=32):
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    base = 0.2 + 0.6 * (x > 0.5) + 0.3 * np.sin(6 * y)
    return np.stack([base, 0.8 * base, 0.5 + 0.2 * x], axis=-1)


def _box(r):
    return lambda c, a=None, n=None: box_mean(c, r)


# ------------------------------------------------------- the variance constant
@pytest.mark.parametrize("n_a,n_b", [(4, 4), (5, 3), (1, 7)])
def test_variance_constant_matches_monte_carlo_for_a_linear_denoiser(n_a, n_b):
    """Var[D(x)] over many noise realisations equals c E|D(A) - D(B)|^2 with
    c = n_a n_b / n^2, for a 5x5 box filter (linear) on a synthetic image."""
    rng = np.random.default_rng(7)
    mu = _truth(24, 24)
    reps, sigma = 400, 0.3
    sa = mu + sigma * rng.standard_normal((reps, n_a) + mu.shape).mean(axis=1) * 1.0
    sb = mu + sigma * rng.standard_normal((reps, n_b) + mu.shape).mean(axis=1) * 1.0
    full = (n_a * sa + n_b * sb) / (n_a + n_b)
    den = _box(2)
    d = np.stack([den(f) for f in full])
    d_a = np.stack([den(f) for f in sa])
    d_b = np.stack([den(f) for f in sb])
    empirical = d.var(axis=0, ddof=1).mean()
    c = oidn.variance_constant(n_a, n_b)
    predicted = (c * (d_a - d_b) ** 2).mean()
    assert c == pytest.approx(n_a * n_b / (n_a + n_b) ** 2)
    assert predicted == pytest.approx(empirical, rel=0.05)


def test_variance_constant_per_pixel_with_varying_counts():
    """Per-pixel (identity) denoiser, counts varying over the image: the
    per-pixel constant gives each pixel's variance of the mean."""
    rng = np.random.default_rng(3)
    h, w, reps, sigma = 8, 8, 3000, 0.5
    n_a = rng.integers(1, 9, (h, w)).astype(float)
    n_b = rng.integers(1, 9, (h, w)).astype(float)
    sa = sigma * rng.standard_normal((reps, h, w)) / np.sqrt(n_a)
    sb = sigma * rng.standard_normal((reps, h, w)) / np.sqrt(n_b)
    full = (n_a * sa + n_b * sb) / (n_a + n_b)
    pred = (oidn.variance_constant(n_a, n_b) * (sa - sb) ** 2).mean(axis=0)
    np.testing.assert_allclose(pred, full.var(axis=0), rtol=0.12)
    np.testing.assert_allclose(pred.mean(), (sigma ** 2 / (n_a + n_b)).mean(), rtol=0.03)


def test_variance_constant_general_rate_and_empty_halves():
    assert oidn.variance_constant(4, 4, rate=1.0) == pytest.approx(0.25)
    assert oidn.variance_constant(4, 4, rate=0.5) == pytest.approx(2 ** -0.5 / 2)
    assert oidn.variance_constant(0, 4) == 0.0 and oidn.variance_constant(4, 0) == 0.0


def test_bias_term_vanishes_for_a_linear_denoiser():
    """D(full) is the count-weighted mean of D(A) and D(B) when the denoiser is
    linear and the halves' share is the same everywhere: no bias term."""
    rng = np.random.default_rng(1)
    mu = _truth()
    a = mu + 0.2 * rng.standard_normal(mu.shape)
    b = mu + 0.1 * rng.standard_normal(mu.shape)
    full = (5 * a + 3 * b) / 8
    den = _box(3)
    var, bias = oidn.dual_buffer_error(den(full), den(a), den(b), np.full(mu.shape[:2], 5.0),
                                       np.full(mu.shape[:2], 3.0), 1.0, 0)
    assert np.abs(bias).max() < 1e-24
    assert var.mean() > 0


def test_bias_term_sees_a_blur_shared_by_both_halves():
    """A denoiser that blurs more at a higher noise level (as OIDN does) has a
    bias at an edge that both halves share: the variance term misses it.  Its
    blur weight grows like the noise level, n^-1/2, so the halves' bias is
    sqrt(2) times the full one's and the bias term's weight for that rate is
    1 / (sqrt(2) - 1)^2 (module notes): with it the estimate is the true
    error's size."""
    rng = np.random.default_rng(5)
    mu = np.zeros((16, 64, 3))
    mu[:, 32:] = 1.0
    sigma, n = 0.6, 8

    def noise_adaptive(c, a=None, nn=None):
        s = np.median(np.abs(np.diff(c, axis=0))) / 0.954  # noise level from the image
        t = np.clip(2.4 * s, 0.0, 1.0)
        return (1 - t) * c + t * box_mean(c, 4)

    weight = 1.0 / (np.sqrt(2.0) - 1.0) ** 2
    est_var, est_all, true = [], [], []
    for _ in range(60):
        sa = mu + sigma * rng.standard_normal(mu.shape) / np.sqrt(n / 2)
        sb = mu + sigma * rng.standard_normal(mu.shape) / np.sqrt(n / 2)
        d = noise_adaptive((sa + sb) / 2)
        var, bias = oidn.dual_buffer_error(d, noise_adaptive(sa), noise_adaptive(sb),
                                           np.full(mu.shape[:2], n / 2), np.full(mu.shape[:2], n / 2),
                                           weight, 0)
        edge = slice(29, 35)
        est_var.append(var[:, edge].mean())
        est_all.append((var + bias)[:, edge].mean())
        true.append(((d - mu) ** 2)[:, edge].mean())
    t, v, a = np.mean(true), np.mean(est_var), np.mean(est_all)
    assert v < 0.5 * t          # variance alone underestimates at the edge
    assert 0.6 * t < a < 1.6 * t, (v, a, t)


# -------------------------------------------------------------- real OIDN
@needs_pyoidn
def test_estimate_with_real_oidn_tracks_the_empirical_error():
    """A small Monte Carlo with the real OIDN: over 16 noise realisations of
    a synthetic image, the frame's mean estimated error (variance + bias)
    is within a factor of 3 of the mean true squared error (the full-scale
    figures are in docs/notes/oidn.md)."""
    rng = np.random.default_rng(2)
    mu = _truth(48, 48)
    alb = np.clip(mu, 0, 1)
    nrm = np.dstack([np.zeros(mu.shape[:2]), np.zeros(mu.shape[:2]), np.ones(mu.shape[:2])])
    feats = {"albedo": alb, "normal": nrm}
    est, true = [], []
    for _ in range(16):
        sa = mu * (1 + 0.5 * rng.standard_normal(mu.shape))
        sb = mu * (1 + 0.5 * rng.standard_normal(mu.shape))
        res = oidn.estimate((sa + sb) / 2, feats, ((sa, feats), (sb, feats)), 1.0, 1.0,
                            oidn.Params(pool_radius=0))
        est.append(res.error.mean())
        true.append(((res.image - mu) ** 2).mean())
    ratio = np.mean(est) / np.mean(true)
    assert 1 / 3 < ratio < 3, ratio


@needs_pyoidn
def test_oidn_output_is_finite_for_hostile_input():
    c = _truth()
    c[0, 0] = np.nan
    c[1, 1] = np.inf
    c[2, 2] = -5.0
    c[3, 3] = 1e30
    out = oidn.oidn_filter(c, np.full(c.shape, 0.5), np.full(c.shape, 2.0))
    assert out.shape == c.shape and np.isfinite(out).all() and (out >= 0).all()
    black = oidn.oidn_filter(np.zeros((8, 8, 3)))
    assert np.abs(black).max() < 1e-3


@needs_pyoidn
def test_a_device_error_is_raised_never_a_black_image():
    """pyoidn's Filter API does not raise: a bad call leaves a black output.
    run_filter polls the device after every step and raises instead."""
    c = np.ones((16, 16, 3), np.float32)
    a = np.ones((8, 8, 3), np.float32)
    with pytest.raises(oidn.OIDNError, match="OIDN filter commit failed: image size mismatch"):
        oidn.run_filter({"color": c, "albedo": a}, "high")


@needs_pyoidn
def test_prefilters_and_qualities_run_and_differ():
    rng = np.random.default_rng(0)
    mu = _truth()
    c = mu * (1 + 0.5 * rng.standard_normal(mu.shape))
    alb = np.clip(mu + 0.1 * rng.standard_normal(mu.shape), 0, 1)
    nrm = np.dstack([np.zeros(mu.shape[:2])] * 2 + [np.ones(mu.shape[:2])])
    outs = {(q, p): oidn.oidn_filter(c, alb, nrm, quality=q, prefilter=p)
            for q in oidn.QUALITIES for p in oidn.PREFILTERS}
    assert all(np.isfinite(o).all() for o in outs.values())
    assert not np.array_equal(outs[("high", "fast")], outs[("high", "none")])
    assert not np.array_equal(outs[("high", "fast")], outs[("fast", "fast")])
    # OIDN works on the image with its rows bottom to top (as Blender does)
    import pyoidn
    flip = lambda x: np.ascontiguousarray(x[::-1], np.float32)
    ref = pyoidn.denoise(flip(np.clip(c, 0, None)), flip(alb), flip(nrm), hdr=True, quality="high")[::-1]
    np.testing.assert_array_equal(outs[("high", "fast")], ref.astype(np.float64))


# ------------------------------------------------------------------ backends
BLOCK = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] == 'pyoidn':
            raise ImportError('blocked for this test')
sys.meta_path.insert(0, Block())
"""


def _run(code):
    return subprocess.run([sys.executable, "-c", BLOCK + code], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


def test_a_missing_wheel_gives_one_clear_error_line():
    r = _run("import numpy as np\nfrom core import oidn\n"
             "try:\n    oidn.oidn_filter(np.ones((4, 4, 3)))\n"
             "except oidn.OIDNUnavailable as e:\n    print('ERR', e)\n")
    assert r.returncode == 0, r.stderr
    line = r.stdout.strip()
    assert line.startswith("ERR oidn: no OIDN available") and "pip install pyoidn==2.5.1.0" in line
    assert "\n" not in line


def test_a_missing_wheel_uses_a_registered_fallback():
    """Without the wheel, a backend registered by the Blender layer is used
    (here a plain box filter stands in for Blender's node, whose equivalence
    is tested under bpy in tests/test_oidn_blender.py)."""
    r = _run("import numpy as np\nfrom core import oidn\nfrom core.filters import box_mean\n"
             "oidn.register_backend('blender', lambda c, a, n, **kw: box_mean(c, 1))\n"
             "print(oidn.resolve_backend('auto'))\n"
             "out = oidn.oidn_filter(np.eye(6)[..., None].repeat(3, -1))\n"
             "print(np.allclose(out, box_mean(np.eye(6)[..., None].repeat(3, -1), 1)))\n")
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["blender", "True"]


def test_bad_parameters_get_one_error_line():
    with pytest.raises(ValueError, match=r"^oidn parameter quality='ultra' must be one of high, "
                                         r"balanced, fast$"):
        oidn.Params(quality="ultra")
    with pytest.raises(ValueError, match="prefilter"):
        params_from_dict(oidn.Params, {"prefilter": "sharp"})
    with pytest.raises(ValueError, match="bias_weight=-1"):
        params_from_dict(oidn.Params, {"bias_weight": -1.0})
    with pytest.raises(ValueError, match=r"color must be \(H, W, 3\)"):
        oidn.oidn_filter(np.ones((4, 4)))
    with pytest.raises(ValueError, match="albedo is 2x2, the colour 4x4"):
        oidn.oidn_filter(np.ones((4, 4, 3)), np.ones((2, 2, 3)))


# ------------------------------------------------------------------- sampler
def test_topup_is_water_filling():
    """Additions sum to the budget; every pixel that gets samples ends at the
    common target lambda a^(1/(1+p)); pixels left out are already above it."""
    rng = np.random.default_rng(4)
    rel = rng.gamma(0.5, 1.0, (20, 30))
    n = rng.integers(1, 12, (20, 30)).astype(float)
    p = 0.8
    add = oidn.topup(rel, n, 3000, p)
    assert add.sum() == pytest.approx(3000, rel=1e-9) and (add >= 0).all()
    shape = (rel * n ** p) ** (1 / (1 + p))
    lam = (n + add)[add > 0] / shape[add > 0]
    assert lam.std() / lam.mean() < 1e-9
    assert (n[add == 0] >= lam.mean() * shape[add == 0] * (1 - 1e-9)).all()


@pytest.mark.parametrize("allocation", ["topup", "proportional"])
@pytest.mark.parametrize("shape,budget", [((64, 48), 3000), ((37, 29), 1234)])
def test_sample_map_is_one_count_per_block_and_sums_to_the_budget(allocation, shape, budget):
    """The planner renders a block-constant map as it is: every 8x8 block
    holds one count, except the one block that takes the last few samples."""
    rng = np.random.default_rng(11)
    h, w = shape
    buf = Buffers.from_subsets([np.ones((h, w, 3))] * 4, [1, 1, 1, 1])
    rel = box_mean(rng.gamma(0.3, 1.0, (h, w)), 3)
    res = oidn.MethodResult(np.ones((h, w, 3)), rel, {}, None, oidn.OIDNFit(rel, None, None, "split"))
    counts = oidn.sample_map(buf, res, budget, oidn.Params(allocation=allocation, uniform_fraction=0.2),
                             {})
    assert counts.sum() == budget and (counts >= 0).all() and counts.std() > 0
    s = oidn.BLOCK
    uneven = [(by, bx) for by in range(0, h, s) for bx in range(0, w, s)
              if np.ptp(counts[by:by + s, bx:bx + s]) > 0]
    assert len(uneven) <= 1
    if uneven:
        by, bx = uneven[0]
        assert np.ptp(counts[by:by + s, bx:bx + s]) == 1


def test_sample_map_spends_the_budget_and_is_uniform_when_not_adaptive():
    buf = Buffers.from_subsets([np.ones((16, 16, 3))] * 2, [2, 2])
    rel = np.ones((16, 16))
    rel[:, 8:] = 50.0
    res = oidn.MethodResult(np.ones((16, 16, 3)), rel * 1.01, {}, None,
                            oidn.OIDNFit(rel, None, None, "split"))
    counts = oidn.sample_map(buf, res, 1000, oidn.Params(), {})
    assert counts.sum() == 1000 and counts[:, 12:].mean() > 2 * counts[:, :4].mean()
    flat = oidn.sample_map(buf, res, 1024, oidn.Params(adaptive=False), {})
    assert (flat == 4).all()


# ---------------------------------------------------------------- the halves
def test_halves_are_disjoint_groups_of_the_samples():
    """Each group goes whole to the half with fewer samples (ties: A); half
    A's mean and half B's (derived) equal the means of their groups."""
    rng = np.random.default_rng(8)
    h, w = 6, 5
    sizes = [1, 1, 1, 1, 3, 2, 5]
    groups = [rng.normal(1.0, 0.5, (s, h, w, 3)) for s in sizes]
    buf = Buffers.empty(h, w, ("albedo",))
    mine_a, mine_b = [], []
    na = nb = 0
    for g in groups:
        (mine_a if na <= nb else mine_b).append(g)
        if na <= nb:
            na += len(g)
        else:
            nb += len(g)
        buf.merge_group(g.mean(0), len(g), {"albedo": 0.5 * g.mean(0)})
    (n_a, c_a, f_a), (n_b, c_b, f_b) = buf.halves()
    assert np.all(n_a == na) and np.all(n_b == nb)
    np.testing.assert_allclose(c_a, np.concatenate(mine_a).mean(0), atol=1e-12)
    np.testing.assert_allclose(c_b, np.concatenate(mine_b).mean(0), atol=1e-12)
    np.testing.assert_allclose(f_b["albedo"], 0.5 * np.concatenate(mine_b).mean(0), atol=1e-12)
    np.testing.assert_allclose(buf.copy().halves()[1][1], c_b)
    (cn_a, cc_a), (cn_b, cc_b) = buf.color_halves()  # the colour alone: the same values
    np.testing.assert_array_equal(cn_a, n_a)
    np.testing.assert_array_equal(cn_b, n_b)
    np.testing.assert_array_equal(cc_a, c_a)
    np.testing.assert_allclose(cc_b, c_b, rtol=1e-15, atol=1e-15)
    buf.half = None
    assert buf.color_halves() is None and buf.halves() is None


def test_merging_buffers_keeps_halves_disjoint_and_balanced():
    rng = np.random.default_rng(9)
    groups = [rng.normal(0.0, 1.0, (s, 4, 4, 3)) for s in (2, 2, 3, 1)]
    a = Buffers.from_subsets([g.mean(0) for g in groups[:2]], [2, 2])
    b = Buffers.from_subsets([g.mean(0) for g in groups[2:]], [3, 1])
    a.merge(b)  # b's larger half (3) joins a's (tied) half A
    (n_a, c_a, _), (n_b, c_b, _) = a.halves()
    assert np.all(n_a == 5) and np.all(n_b == 3)
    np.testing.assert_allclose(c_a, np.concatenate([groups[0], groups[2]]).mean(0), atol=1e-12)
    c = Buffers(np.full((4, 4), 4.0), np.full((4, 4), 1.0),
                type(a.color)(np.full((4, 4, 3), 2.0), np.zeros((4, 4, 3))))
    assert c.halves() is None  # e.g. read from a file
    a.merge(c)  # one group without halves: to the smaller half B
    (n_a, _, _), (n_b, c_b, _) = a.halves()
    assert np.all(n_a == 5) and np.all(n_b == 7)
    np.testing.assert_allclose(c_b, (3 * np.concatenate([groups[1], groups[3]]).mean(0) + 4 * 2.0) / 7,
                               atol=1e-12)


# ------------------------------------------------------------------- method
def test_the_module_and_its_uniform_variant_declare_the_contract():
    for m in (oidn, oidn.UNIFORM):
        assert all(hasattr(m, k) for k in methods.MEMBERS)
    assert oidn.ADAPTIVE and not oidn.UNIFORM.ADAPTIVE and oidn.NAME == "oidn"
    assert oidn.method_for(oidn.Params(adaptive=False)) is oidn.UNIFORM
    assert oidn.method_for({"adaptive": True}) is oidn
    assert oidn.PASSES == ("albedo", "normal", "depth")


@needs_pyoidn
def test_depth_guides_the_error_estimate_so_it_is_declared():
    """Depth guides the pooling of the variance OIDN's error estimate reads,
    which is why ``PASSES`` holds it (that no undeclared pass changes the
    result is tests/core/test_methods.py's contract test, for every method)."""
    rng = np.random.default_rng(31)
    h, w = 24, 32
    truth = np.linspace(0.1, 2.0, h * w * 3).reshape(h, w, 3)
    feats = {"albedo": np.full((h, w, 3), 0.5), "normal": np.dstack([np.zeros((h, w, 2)), np.ones((h, w))]),
             "depth": np.linspace(1.0, 3.0, h * w).reshape(h, w, 1)}
    groups = [truth * (1 + 0.3 * rng.standard_normal(truth.shape)) for _ in range(4)]
    a = oidn.reconstruct(Buffers.from_subsets(groups, [2] * 4, [feats] * 4))
    bare = Buffers.from_subsets(groups, [2] * 4, [{k: v for k, v in feats.items() if k != "depth"}] * 4)
    assert not np.array_equal(oidn.reconstruct(bare).error, a.error)  # depth does guide the estimate


@needs_pyoidn
def test_denoise_of_plain_arrays_is_deterministic_with_recorrupted_error():
    rng = np.random.default_rng(6)
    mu = _truth()
    c = mu * (1 + 0.3 * rng.standard_normal(mu.shape))
    var = (0.3 * mu) ** 2
    r1 = oidn.denoise(c, var, {"albedo": np.clip(mu, 0, 1)}, None, 4)
    r2 = oidn.denoise(c, var, {"albedo": np.clip(mu, 0, 1)}, None, 4)
    assert np.array_equal(r1.image, r2.image) and np.array_equal(r1.error, r2.error)
    assert r1.fit.halves == "recorrupted" and (r1.error > 0).all() and np.isfinite(r1.error).all()
    none = oidn.denoise(c, np.full(c.shape, np.inf))
    assert none.fit.halves == "none" and not none.error.any()


@needs_pyoidn
def test_adaptive_run_spends_the_budget_and_the_uniform_variant_samples_evenly(fake_executor):
    h, w = 32, 32
    truth = _truth(h, w)
    feats = {"albedo": np.clip(truth, 0, 1), "normal": np.dstack([np.zeros((h, w))] * 2 +
                                                                  [np.ones((h, w))]),
             "depth": np.ones((h, w, 1))}
    opts = Options(method="uniform", spp=8, initial_spp=4, iterations=3, seed=1, min_task_size=4,
                   task_cost=0.0)
    run = AdaptiveRun(fake_executor(truth, feats), opts, method=oidn)
    for _ in run.steps():
        pass
    res = run.reconstruct()
    assert abs(run.samples_rendered - run.budget) <= 0.01 * run.budget
    assert np.isfinite(res.image).all() and np.isfinite(res.error).all()
    assert run.buffers.n.std() > 0 and run.method_state["rounds"] >= 1
    assert res.fit.halves == "split"
    (n_a, _, _), (n_b, _, _) = run.buffers.halves()
    assert (np.abs(n_a - n_b) <= np.maximum(n_a, n_b)).all() and (n_a > 0).all() and (n_b > 0).all()
    uni = AdaptiveRun(fake_executor(truth, feats), opts, method=oidn.UNIFORM)
    for _ in uni.steps():
        pass
    assert (uni.buffers.n == 8).all() and uni.reconstruct().fit.halves == "split"


def _flat_aux_buffers(seed, h, w, lo, span):
    """Four one-sample subsets of colour ``lo + span * U(0, 1)`` with a flat
    albedo (0.5) and normal (+z)."""
    from core.buffers import Buffers
    rng = np.random.default_rng(seed)
    feats = [{"albedo": np.full((h, w, 3), 0.5), "normal": np.dstack([np.zeros((h, w))] * 2 + [np.ones((h, w))])}
             for _ in range(4)]
    return Buffers.from_subsets([lo + span * rng.random((h, w, 3)) for _ in range(4)], [1] * 4, feats)


def test_without_its_error_estimate_oidn_makes_one_call_and_bounds_the_error(monkeypatch):
    from core import oidn
    buf = _flat_aux_buffers(3, 10, 12, 0.4, 0.1)
    calls = []
    monkeypatch.setattr(oidn, "oidn_filter", lambda c, a=None, n=None, **kw: calls.append(1) or np.asarray(c))
    full = oidn.reconstruct(buf, oidn.Params(adaptive=False))
    assert len(calls) == 4  # the image, then the whole and both halves for the error (fast prefilter)
    calls.clear()
    one = oidn.reconstruct(buf, oidn.Params(adaptive=False, error_estimate=False))
    assert len(calls) == 1
    np.testing.assert_array_equal(one.image, full.image)
    np.testing.assert_allclose(one.error, buf.variance_of_mean().mean(axis=-1))
    with pytest.raises(ValueError, match="needs adaptive=False"):
        oidn.Params(error_estimate=False)


def test_a_main_thread_backend_marks_the_loops_work(monkeypatch):
    """Where only a main-thread backend (Blender's compositor) is there, the
    loop's Work of an OIDN method says so, so a UI runs it inline."""
    from core import oidn
    from core.pipeline import AdaptiveRun, Options
    from conftest import FakeExecutor
    monkeypatch.setattr(oidn, "pyoidn_available", lambda: False)
    monkeypatch.setattr(oidn, "_FALLBACKS", {})
    monkeypatch.setattr(oidn, "_MAIN_THREAD", set())
    assert not oidn.needs_main_thread()
    oidn.register_backend("blender", lambda c, a, n, **kw: np.asarray(c), main_thread=True)
    assert oidn.needs_main_thread() and oidn.resolve_backend() == "blender"
    h, w = 8, 8
    feats = {"albedo": np.full((h, w, 3), 0.5), "normal": np.ones((h, w, 3)), "depth": np.ones((h, w, 1))}
    run = AdaptiveRun(FakeExecutor(np.full((h, w, 3), 0.5), feats), Options(method="oidn", spp=8))
    # the Works that call the method (the initial pass's measurements are numpy only)
    works = [p.work for p in run.steps() if p.work is not None and p.stage == "adapt"]
    assert works and all(wk.main_thread for wk in works)
    lp = AdaptiveRun(FakeExecutor(np.full((h, w, 3), 0.5), feats), Options(method="lp", spp=8))
    assert not any(p.work.main_thread for p in lp.steps() if p.work is not None)
    oidn.unregister_backend("blender")
    assert not oidn.needs_main_thread()


def _recording_filter(monkeypatch, calls):
    """oidn_filter replaced by a 3x3 box filter that records each call's prefilter."""
    def fake(c, a=None, n=None, **kw):
        calls.append(kw.get("prefilter"))
        return box_mean(np.asarray(c, np.float64), 1)
    monkeypatch.setattr(oidn, "oidn_filter", fake)


def test_the_map_estimate_is_the_reconstruction_with_the_map_prefilter(monkeypatch):
    buf = _flat_aux_buffers(5, 12, 16, 0.3, 0.2)
    calls = []
    _recording_filter(monkeypatch, calls)
    full = oidn.reconstruct(buf, oidn.Params())
    assert calls == ["accurate"] + ["fast"] * 3     # the image; its error from the fast estimate
    calls.clear()
    cheap = oidn.map_result(buf, oidn.Params())
    assert calls == ["fast"] * 3                     # the full mean and both halves, no aux prefilter
    calls.clear()
    alike = oidn.reconstruct(buf, oidn.Params(map_prefilter="accurate"))
    assert calls == ["accurate"] * 3                 # one prefilter: the image is the estimate's whole
    calls.clear()
    same = oidn.map_result(buf, oidn.Params(map_prefilter="accurate"))
    assert calls == ["accurate"] * 3
    for a, b in ((full, same), (full, cheap), (full, alike)):  # the box filter ignores the prefilter
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.error, b.error)
    with pytest.raises(ValueError, match="map_prefilter"):
        oidn.Params(map_prefilter="sharp")


def test_the_loop_places_samples_by_the_map_estimate_and_ends_with_the_full_reconstruction(
        monkeypatch, fake_executor):
    """Between rounds the loop reads ``map_result`` (fast prefilter); the
    final image is ``reconstruct``'s (the accurate prefilter; its error from
    the fast estimate)."""
    h, w = 16, 16
    truth = _truth(h, w)
    feats = {"albedo": np.clip(truth, 0, 1), "normal": np.dstack([np.zeros((h, w))] * 2 + [np.ones((h, w))]),
             "depth": np.ones((h, w, 1))}
    calls = []
    _recording_filter(monkeypatch, calls)
    opts = Options(method="oidn", spp=8, initial_spp=4, iterations=3, seed=1, min_task_size=4, task_cost=0.0)
    run = AdaptiveRun(fake_executor(truth, feats), opts, method=oidn)
    for _ in run.steps():
        pass
    rounds = run.method_state["rounds"]
    assert rounds >= 1 and calls == ["fast"] * (3 * rounds)
    calls.clear()
    run.reconstruct()
    assert calls == ["accurate"] + ["fast"] * 3      # the image, then its error estimate


def test_oidn_keeps_noiseless_pixels_at_their_mean_and_the_guard_finds_nothing_there(monkeypatch):
    """A denoiser that shifts every pixel by 0.5 % (as OIDN does on a flat
    background): the noiseless pixels come back exactly at their sample mean
    with error 0, so the consistency guard has nothing to correct there; the
    noisy ones keep the denoiser's output."""
    from core.method import consistency_guard, exact_pixels
    buf = _flat_aux_buffers(5, 12, 16, 0.4, 0.1)
    buf.color.mean[:, :6] = 0.25                               # the left 6 columns noiseless
    buf.color.m2[:, :6] = 0.0
    buf.half = None                                            # recorrupted halves: no stored groups
    monkeypatch.setattr(oidn, "oidn_filter", lambda c, a=None, n=None, **kw: 1.005 * np.asarray(c))
    res = oidn.reconstruct(buf, oidn.Params(adaptive=False))
    ex = exact_pixels(buf)
    assert ex[:, :5].all() and not ex[:, 7:].any()
    np.testing.assert_array_equal(res.image[ex], buf.color.mean[ex])
    assert (res.error[ex] == 0).all() and res.info["exact_fraction"] == ex.mean()
    np.testing.assert_allclose(res.image[:, 7:], 1.005 * buf.color.mean[:, 7:])
    g = consistency_guard(res, buf)
    np.testing.assert_array_equal(g.image[ex], res.image[ex])
    assert g.info["guard_fraction"] == 0.0

"""core/oracle.py: the sample map driven by the true error (the benchmark's oracle)."""
import numpy as np
import pytest

from cycles_adaptive.core import awr, lp, oracle, uniform, var
from cycles_adaptive.core.buffers import Buffers
from cycles_adaptive.core.method import Method, MethodResult
from cycles_adaptive.core.pipeline import AdaptiveRun, Options


def _scene(h=32, w=48, seed=0):
    rng = np.random.default_rng(seed)
    ref = 0.2 + 0.6 * rng.random((h, w, 3))
    return ref


def test_map_concentrates_samples_where_the_true_error_is():
    ref = _scene()
    img = ref.copy()
    img[4:12, 8:20] += 0.5  # a wrong block; the rest is exact
    n = np.full(ref.shape[:2], 4.0)
    budget = 5000
    counts = oracle.oracle_map(img, ref, n, budget, radius=0)
    inside = counts[4:12, 8:20].sum()
    assert counts.sum() == budget
    assert inside == budget  # exact pixels have zero true error


def test_pooling_spreads_to_neighbours_and_keeps_the_sum():
    ref = _scene()
    img = ref.copy()
    img[10, 10] += 1.0
    counts = oracle.oracle_map(img, ref, np.ones(ref.shape[:2]), 900, radius=1)
    assert counts.sum() == 900
    assert (counts[9:12, 9:12] > 0).all()
    assert counts[9:12, 9:12].sum() == 900


def test_map_follows_error_and_sample_count():
    ref = _scene(16, 16)
    rng = np.random.default_rng(1)
    err = np.zeros(ref.shape)
    err[:, :8] = 0.05 * rng.standard_normal((16, 8, 3))   # small error on the left
    err[:, 8:] = 0.20 * rng.standard_normal((16, 8, 3))   # large on the right
    img = ref + err
    n = np.full((16, 16), 8.0)
    c = oracle.oracle_map(img, ref, n, 20000, radius=1)
    assert c.sum() == 20000
    assert c[:, 8:].sum() > 4 * c[:, :8].sum()
    # same error, more samples already there -> fewer new samples (gain n^-p)
    img2 = ref + 0.1
    n2 = np.full((16, 16), 4.0)
    n2[:, 8:] = 64.0
    c2 = oracle.oracle_map(img2, ref, n2, 10000, dimension=None, radius=0)
    assert c2[:, :8].sum() > 4 * c2[:, 8:].sum()


@pytest.mark.parametrize("budget", [0, 1, 7, 12345])
def test_sums_to_the_budget(budget):
    ref = _scene(20, 20)
    img = ref + 0.01 * np.random.default_rng(2).standard_normal(ref.shape)
    c = oracle.oracle_map(img, ref, np.full((20, 20), 4.0), budget)
    assert c.dtype == np.int64
    assert c.sum() == budget and (c >= 0).all()


def test_hostile_input_gives_finite_maps():
    ref = _scene(12, 12)
    img = ref.copy()
    img[0, 0] = np.nan
    img[1, 1] = np.inf
    img[2, 2] = -np.inf
    img[3, 3] = 1e300
    ref_bad = ref.copy()
    ref_bad[5, 5] = np.nan
    ref_bad[6, 6] = np.inf
    n = np.full((12, 12), 4.0)
    n[7, 7] = 0.0
    n[8, 8] = np.nan
    n[9, 9] = -3.0
    for r in (ref, ref_bad):
        w = oracle.oracle_weights(img, r, n)
        assert np.isfinite(w).all() and (w >= 0).all()
        c = oracle.oracle_map(img, r, n, 1000)
        assert c.sum() == 1000 and (c >= 0).all()
        # non-finite reconstructions are the worst pixels: they get samples
        assert c[0, 0] > 0 and c[1, 1] > 0
    # an exact image: no error anywhere -> an even map, still the full budget
    c = oracle.oracle_map(ref, ref, n, 144 * 3)
    assert c.sum() == 144 * 3 and c.min() == 3 and c.max() == 3
    # everything non-finite
    allnan = np.full((4, 4, 3), np.nan)
    c = oracle.oracle_map(allnan, allnan, np.full((4, 4), np.nan), 50)
    assert c.sum() == 50


def test_size_mismatch_is_a_clear_error():
    with pytest.raises(ValueError, match="reference is 8x4"):
        oracle.true_relative_error(np.zeros((4, 6, 3)), np.zeros((4, 8, 3)))
    with pytest.raises(ValueError, match="sample counts"):
        oracle.oracle_weights(np.zeros((4, 6, 3)), np.zeros((4, 6, 3)), np.zeros((5, 6)))


def test_gain_exponent_from_the_model_dimension():
    assert oracle.gain_exponent(MethodResult(np.zeros((1, 1, 3)), np.zeros((1, 1)), {})) == 1.0
    r = MethodResult(np.zeros((1, 1, 3)), np.zeros((1, 1)), {}, dimension=4.0)  # LP: mean rank
    assert oracle.gain_exponent(r) == pytest.approx(0.5)
    r = MethodResult(np.zeros((1, 1, 3)), np.zeros((1, 1)), {}, dimension=9)  # RHF: features
    assert oracle.gain_exponent(r) == pytest.approx(4 / 13)


def test_wrapper_drives_the_real_loop(fake_executor):
    """OracleMethod has a method module's interface: the loop runs with it,
    spends the budget and puts more samples where the (known) truth is noisy."""
    h, w = 32, 32
    truth = np.full((h, w, 3), 0.05)
    truth[:, 16:] = 1.0  # bright half: the fake noise is relative, so more absolute error...
    ex = fake_executor(truth)
    run = AdaptiveRun(ex, Options(method="var", spp=16, initial_spp=4, subsets=4, min_task_size=4,
                                  task_cost=0.0), method=oracle.OracleMethod(var, truth))
    for _ in run.steps():
        pass
    assert abs(run.samples_rendered - 16 * h * w) <= 0.01 * 16 * h * w
    n = run.buffers.n
    assert np.isfinite(n).all()
    # relative error (x-r)^2/(r^2+0.01) of relative noise is larger where r is large
    assert n[:, 16:].mean() > n[:, :16].mean()
    assert run.method.reconstruct(run.buffers).image.shape == (h, w, 3)


def test_wrapper_refuses_a_reference_of_another_size():
    b = Buffers.empty(8, 8, ())
    b.merge_group(np.ones((8, 8, 3)), 1)
    m = oracle.OracleMethod(uniform, np.ones((8, 9, 3)))
    with pytest.raises(ValueError, match="reference is 9x8"):
        m.sample_map(b, uniform.reconstruct(b), 10)
    with pytest.raises(ValueError):
        oracle.OracleMethod(uniform, np.ones((8, 8)))


def test_wrapper_declares_the_method_contract():
    """Every member of the Method protocol is declared, the wrapped method's
    except NAME and SAMPLER_USES_RESULT (the map needs the reconstruction)."""
    m = oracle.OracleMethod(var, np.ones((4, 4, 3)))
    assert isinstance(m, Method)
    assert m.NAME == "oracle-" + var.NAME
    assert m.PASSES == tuple(var.PASSES) and m.Params is var.Params
    assert m.ADAPTIVE == var.ADAPTIVE and m.SAMPLER_USES_RESULT is True
    assert oracle.OracleMethod(var, np.ones((4, 4, 3)), name="mine").NAME == "mine"


def test_map_gain_follows_the_model_dimension():
    """The map is the pooled true error times sampling_gain's n^(-4/(d+4))."""
    ref = _scene(8, 8)
    img = ref + 0.1
    n = np.arange(1.0, 65.0).reshape(8, 8)
    e = oracle.true_relative_error(img, ref)
    for d in (None, 0.0, 4.0, 9.0):
        w = oracle.oracle_weights(img, ref, n, dimension=d, radius=0)
        p = 1.0 if d is None else 4.0 / (d + 4.0)
        np.testing.assert_allclose(w, e * n ** -p, rtol=1e-14)
    bad = MethodResult(np.zeros((1, 1, 3)), np.zeros((1, 1)), {}, dimension=float("nan"))
    assert oracle.model_dimension(bad) is None and oracle.gain_exponent(bad) == 1.0


# ------------------------------------------------------ UniformSampling
def test_uniform_sampling_declares_the_method_contract():
    """Same members as the wrapped method except NAME, ADAPTIVE (False: the
    whole budget in the initial pass) and SAMPLER_USES_RESULT (False)."""
    for base in (var, awr, lp):
        m = oracle.UniformSampling(base)
        assert isinstance(m, Method)
        assert m.NAME == "uniform-" + base.NAME
        assert m.PASSES == tuple(base.PASSES) and m.Params is base.Params
        assert m.ADAPTIVE is False and m.SAMPLER_USES_RESULT is False
    assert oracle.UniformSampling(var, name="mine").NAME == "mine"


def test_uniform_sampling_keeps_the_reconstruction_exactly():
    ref = _scene(12, 16)
    rng = np.random.default_rng(3)
    b = Buffers.empty(12, 16, ())
    for _ in range(4):
        b.merge_group(ref * (1.0 + 0.3 * rng.standard_normal(ref.shape)), 2)
    got = oracle.UniformSampling(awr).reconstruct(b, awr.Params())
    want = awr.reconstruct(b, awr.Params())
    np.testing.assert_array_equal(got.image, want.image)
    np.testing.assert_array_equal(got.error, want.error)


@pytest.mark.parametrize("budget", [0, 1, 191, 192, 1000])
def test_uniform_sampling_map_is_even_and_sums_to_the_budget(budget):
    b = Buffers.empty(12, 16, ())
    b.merge_group(np.ones((12, 16, 3)), 1)
    c = oracle.UniformSampling(var).sample_map(b, None, budget)
    assert c.dtype == np.int64 and c.sum() == budget
    assert c.max() - c.min() <= 1


def test_uniform_sampling_renders_every_pixel_equally_in_the_loop(fake_executor):
    """Through the real loop: the budget is spent, every pixel gets the same
    count (no adaptation), nothing beyond the map, and the image is the
    wrapped method's reconstruction of those buffers; the adaptive run of the
    same method on the same scene does adapt (its counts vary)."""
    h, w = 32, 32
    truth = np.full((h, w, 3), 0.05)
    truth[:, 16:] = 1.0
    opts = dict(method="var", spp=16, initial_spp=4, subsets=4, min_task_size=4, task_cost=0.0)
    run = AdaptiveRun(fake_executor(truth), Options(**opts), method=oracle.UniformSampling(var))
    for _ in run.steps():
        pass
    n = run.buffers.n
    assert run.samples_rendered == 16 * h * w
    assert n.min() == n.max() == 16
    assert run.overshoot == 0
    res = run.method.reconstruct(run.buffers, run.params)
    np.testing.assert_array_equal(res.image, var.reconstruct(run.buffers, run.params).image)
    adaptive = AdaptiveRun(fake_executor(truth), Options(**opts), method=oracle.OracleMethod(var, truth))
    for _ in adaptive.steps():
        pass
    assert adaptive.buffers.n.std() > 0

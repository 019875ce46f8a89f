"""LP on core.parallel's pool: bit-identical output for any thread count.

The chunks of centres are cut by shape and parameters only, each piece has
its own workspace and its own sums over its band, and the sums are added in
chunk order, so threads = 1 and threads = n must agree bit for bit.  The
frames here are small, so the inline threshold is lowered to 0 (else they
would never reach the pool) and the chunk is small (many pieces per pass).
"""
import threading

import numpy as np
import pytest

from core import lp, parallel
from core.buffers import Buffers
from test_lp import scene_features

THREADS = (2, 3, 5)


@pytest.fixture(autouse=True)
def _threads(monkeypatch):
    monkeypatch.delenv(parallel.ENV, raising=False)
    monkeypatch.setattr(lp, "THREAD_MIN_PIXELS", 0)
    yield
    parallel.set_threads(None)


def buffers(h, w, seed=0, hostile=False, constant=False):
    """4 subsets of a textured scene (noisy colour); ``hostile``: NaN / Inf /
    huge colour and feature values and pixels without samples."""
    rng = np.random.default_rng(seed)
    feats = scene_features(h, w, seed=seed)
    yy, xx = np.mgrid[0:h, 0:w]
    truth = feats["albedo"] * (0.5 + 0.5 * np.sin(xx / 7.0) * np.cos(yy / 5.0))[..., None]
    if constant:
        truth = np.full((h, w, 3), 0.25)
        feats = {k: np.full_like(v, 0.5) for k, v in feats.items()}
    colors, counts, fl = [], [], []
    for _ in range(4):
        c = truth + (0.0 if constant else 0.1) * rng.normal(size=truth.shape)
        f = {k: v.copy() for k, v in feats.items()}
        n = np.full((h, w), 4)
        if hostile:
            c[rng.random((h, w)) < 0.02] = np.nan
            c[rng.random((h, w)) < 0.01] = np.inf
            c[3, 5] = 1e200
            f["normal"][rng.random((h, w)) < 0.02] = np.inf
            f["depth"][rng.random((h, w)) < 0.02] = np.nan
            n[rng.random((h, w)) < 0.03] = 0
        colors.append(c)
        counts.append(n)
        fl.append(f)
    return Buffers.from_subsets(colors, counts, fl)


def run(buf, threads, params):
    parallel.set_threads(threads)
    res = lp.reconstruct(buf, params)
    smap = lp.sample_map(buf, res, 5 * buf.shape[0] * buf.shape[1], params)
    fresh = lp.sample_map(buf, None, 3 * buf.shape[0] * buf.shape[1], params)   # recomputes the fit
    return res, smap, fresh


def assert_same(a, b):
    (ra, sa, fa), (rb, sb, fb) = a, b
    assert np.array_equal(ra.image, rb.image)
    assert np.array_equal(ra.error, rb.error)
    assert np.array_equal(ra.fit.delta_error, rb.fit.delta_error)
    assert np.array_equal(ra.fit.radius, rb.fit.radius)
    assert np.array_equal(ra.fit.centers, rb.fit.centers)
    assert np.array_equal(ra.fit.center_error, rb.fit.center_error)
    assert ra.info == rb.info
    assert np.array_equal(sa, sb) and np.array_equal(fa, fb)


@pytest.mark.parametrize("shape", [(53, 71), (70, 33)])
def test_thread_counts_give_identical_output(shape, monkeypatch):
    """Frames whose height is no multiple of the bands (64 rows, the chunks'
    row bands), radius 4, 8 centres a chunk: many pieces per pass."""
    seen = set()
    fit = lp.fit_centres

    def spy(*a, **k):
        seen.add(threading.current_thread().name)
        return fit(*a, **k)

    monkeypatch.setattr(lp, "fit_centres", spy)
    params = {"radius": 4, "chunk": 8}
    buf = buffers(*shape, seed=shape[0])
    one = run(buf, 1, params)
    assert one[0].info["passes"] >= 2 and np.isfinite(one[0].image).all()
    seen.clear()
    for n in THREADS:
        assert_same(one, run(buf, n, params))
    assert any(name.startswith("cycles-adaptive") for name in seen)   # the pool did run pieces


def test_hostile_input_identical_and_finite():
    """NaN, Inf, 1e200 colour, non-finite features and empty pixels."""
    params = {"radius": 3, "chunk": 16}
    buf = buffers(45, 67, seed=3, hostile=True)
    one = run(buf, 1, params)
    assert np.isfinite(one[0].image).all() and np.isfinite(one[0].error).all()
    assert (one[0].error >= 0).all()
    for n in THREADS:
        assert_same(one, run(buf, n, params))


def test_constant_frame_identical_and_exact():
    """A noise-free constant frame: every model predicts the constant, with
    any thread count."""
    params = {"radius": 3, "chunk": 16}
    buf = buffers(40, 50, constant=True)
    one = run(buf, 1, params)
    assert np.allclose(one[0].image, 0.25, rtol=0, atol=1e-12)
    for n in THREADS:
        assert_same(one, run(buf, n, params))


def test_kept_models_identical():
    """``keep_models`` (the temporal extension's RLS state, with the LAPACK
    inverse serialised) is identical too."""
    buf = buffers(41, 59, seed=5)
    color, var, feats, fvars = lp._inputs(buf)
    params = lp.Params(radius=3, chunk=16)
    parallel.set_threads(1)
    one = lp.fit(color, var, feats, fvars, buf.n, params, keep_models=True)
    for n in THREADS:
        parallel.set_threads(n)
        other = lp.fit(color, var, feats, fvars, buf.n, params, keep_models=True)
        assert one.models.keys() == other.models.keys()
        for key in one.models:
            assert np.array_equal(one.models[key], other.models[key]), key
        assert np.array_equal(one.image, other.image)


def test_failing_piece_raises_without_hanging(monkeypatch):
    """An exception in one piece propagates (pieces after it skip their
    reduction and nothing waits forever)."""
    calls = {"n": 0}
    lock = threading.Lock()
    fit = lp.fit_centres

    def flaky(*a, **k):
        with lock:
            calls["n"] += 1
            bad = calls["n"] == 3
        if bad:
            raise RuntimeError("piece failed")
        return fit(*a, **k)

    monkeypatch.setattr(lp, "fit_centres", flaky)
    parallel.set_threads(3)
    with pytest.raises(RuntimeError, match="piece failed"):
        lp.reconstruct(buffers(40, 40), {"radius": 3, "chunk": 8})


def test_ordered_reduce_keeps_item_order():
    """The reductions run one at a time in item order, whichever piece ends
    first; the results come back in order."""
    import time
    parallel.set_threads(4)
    order, active, peak = [], [0], [0]
    lock = threading.Lock()

    def compute(i):
        time.sleep(0.001 * (7 - i % 7))          # later items finish first
        return i

    def reduce(i):
        with lock:
            active[0] += 1
            peak[0] = max(peak[0], active[0])
        order.append(i)
        with lock:
            active[0] -= 1
        return i * i

    assert parallel.ordered_reduce(compute, reduce, range(30)) == [i * i for i in range(30)]
    assert order == list(range(30)) and peak[0] == 1


def test_inline_below_threshold(monkeypatch):
    """Below ``THREAD_MIN_PIXELS`` no piece runs on the pool."""
    monkeypatch.setattr(lp, "THREAD_MIN_PIXELS", 10 ** 9)
    seen = set()
    fit = lp.fit_centres

    def spy(*a, **k):
        seen.add(threading.current_thread().name)
        return fit(*a, **k)

    monkeypatch.setattr(lp, "fit_centres", spy)
    parallel.set_threads(4)
    lp.reconstruct(buffers(30, 30), {"radius": 3, "chunk": 8})
    assert seen == {threading.current_thread().name}


def test_ordered_reduce_raises_the_first_failure_in_order():
    """Item 3 fails late, item 9 fails early: item 3's exception is raised,
    and nothing from item 3 on is reduced."""
    import time
    parallel.set_threads(4)
    reduced = []

    def compute(i):
        if i == 3:
            time.sleep(0.02)
            raise ValueError("item 3")
        if i == 9:
            raise KeyError("item 9")
        return i

    with pytest.raises(ValueError, match="item 3"):
        parallel.ordered_reduce(compute, reduced.append, range(20))
    assert reduced == [0, 1, 2]

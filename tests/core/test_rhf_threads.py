"""RHF on core.parallel's pool: bit-identical output for any thread count.

The regression weights and the model chunks run as pieces cut by the data
only; each chunk writes only its own models' rows and returns its Eq. 13
sums, which are added in chunk order.  Small frames, so the inline
threshold is lowered to 0 and the chunks are small (many pieces).
"""
import dataclasses
import threading

import numpy as np
import pytest

from core import parallel, rhf
from test_rhf import flat_features, scene

THREADS = (2, 3, 5)


@pytest.fixture(autouse=True)
def _threads(monkeypatch):
    monkeypatch.delenv(parallel.ENV, raising=False)
    monkeypatch.setattr(rhf, "THREAD_MIN_PIXELS", 0)
    yield
    parallel.set_threads(None)


def params(**kw):
    return dataclasses.replace(rhf.Params(), chunk_centers=4, radius_small=3, radius_medium=5,
                               radius_large=7, **kw)


def run(buf, threads, p):
    parallel.set_threads(threads)
    res = rhf.reconstruct(buf, p)
    smap = rhf.sample_map(buf, res, 4 * buf.shape[0] * buf.shape[1], p, {})
    return res, smap


def assert_same(a, b):
    (ra, sa), (rb, sb) = a, b
    assert np.array_equal(ra.image, rb.image)
    assert np.array_equal(ra.error, rb.error)
    assert ra.dimension == rb.dimension
    assert np.array_equal(sa, sb)


@pytest.mark.parametrize("shape", [(37, 45), (50, 29)])
def test_thread_counts_give_identical_output(shape, monkeypatch):
    seen = set()
    terms = rhf.chunk_terms

    def spy(*a, **k):
        seen.add(threading.current_thread().name)
        return terms(*a, **k)

    monkeypatch.setattr(rhf, "chunk_terms", spy)
    _, buf = scene(*shape, seed=shape[0])
    p = params()
    one = run(buf, 1, p)
    assert np.isfinite(one[0].image).all() and one[0].info["models"] > 8
    seen.clear()
    for n in THREADS:
        assert_same(one, run(buf, n, p))
    assert any(name.startswith("cycles-adaptive") for name in seen)   # the pool did run pieces


def test_fixed_blend_and_three_iterations_identical():
    """The other Eq. 13 branch (fixed input weight) and T = 3 (two pilots)."""
    _, buf = scene(33, 41, seed=2)
    p = params(input_blend="fixed", iterations=3)
    one = run(buf, 1, p)
    for n in THREADS:
        assert_same(one, run(buf, n, p))


def test_hostile_input_identical_and_finite():
    """NaN / Inf colour, non-finite features, empty pixels."""
    rng = np.random.default_rng(4)
    h, w = 36, 43
    truth, _ = scene(h, w, seed=4)
    feats = flat_features(h, w)
    subs, fl, counts = [], [], []
    for _ in range(4):
        c = truth + 0.1 * rng.normal(size=truth.shape)
        c[rng.random((h, w)) < 0.03] = np.nan
        c[rng.random((h, w)) < 0.02] = np.inf
        f = {k: v.copy() for k, v in feats.items()}
        f["normal"][rng.random((h, w)) < 0.03] = np.inf
        f["depth"][rng.random((h, w)) < 0.03] = np.nan
        n = np.full((h, w), 4)
        n[rng.random((h, w)) < 0.03] = 0
        subs.append(c)
        fl.append(f)
        counts.append(n)
    from core.buffers import Buffers
    buf = Buffers.from_subsets(subs, counts, fl)
    p = params()
    one = run(buf, 1, p)
    assert np.isfinite(one[0].image).all() and np.isfinite(one[0].error).all()
    for n in THREADS:
        assert_same(one, run(buf, n, p))


def test_constant_frame_identical_and_exact():
    from core.buffers import Buffers
    h, w = 30, 38
    buf = Buffers.from_subsets([np.full((h, w, 3), 0.4)] * 4, [4] * 4, [flat_features(h, w)] * 4)
    p = params()
    one = run(buf, 1, p)
    assert np.allclose(one[0].image, 0.4, rtol=0, atol=1e-12)
    for n in THREADS:
        assert_same(one, run(buf, n, p))


def test_apply_parts_matches_direct_accumulation():
    """``accumulate_predictions`` / ``accumulate_variances`` (parts applied at
    once) equal the plain scatter ``np.add.at``."""
    rng = np.random.default_rng(0)
    c, n, K, npx = 5, 9, 3, 60
    flat_all = rng.integers(10, 50, size=(c, n))
    inside = rng.random((c, n)) < 0.8
    flat = flat_all[inside]
    lo, hi = int(flat.min()), int(flat.max()) + 1
    wsel = rng.random(flat.size)
    yk = rng.random((c, n, 3))
    num, den = np.zeros((npx, 3)), np.zeros(npx)
    rhf.accumulate_predictions(num, den, flat, wsel, yk, inside, lo, hi)
    ref_num, ref_den = np.zeros((npx, 3)), np.zeros(npx)
    for ch in range(3):
        np.add.at(ref_num[:, ch], flat, wsel * yk[..., ch][inside])
    np.add.at(ref_den, flat, wsel)
    assert np.allclose(num, ref_num, rtol=1e-14, atol=0) and np.allclose(den, ref_den, rtol=1e-14, atol=0)
    wk, var = rng.random((c, K, n)), rng.random((c, K, n))
    v_num, v_den = np.zeros((npx, K), np.float32), np.zeros((npx, K), np.float32)
    rhf.accumulate_variances(v_num, v_den, flat, wk, var, inside, lo, hi)
    for kq in range(K):
        ref = np.zeros(npx)
        np.add.at(ref, flat, (wk[:, kq][inside] + rhf.MODEL_WEIGHT_FLOOR) * var[:, kq][inside])
        assert np.allclose(v_num[:, kq], ref, rtol=1e-6, atol=0)

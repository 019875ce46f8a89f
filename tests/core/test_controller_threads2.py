"""Confidence pooling and the calibrated variance on the controller's threads
(core.parallel): the same bits for any thread count and band size, and equal
to independent whole-frame formulas written out here."""
import numpy as np
import pytest

from core import maps, parallel, variance as V
from core.buffers import Buffers
from core.method import allocate

THREADS = (2, 3, 5)
SHAPES = [(1, 1), (2, 5), (23, 17), (41, 64), (67, 13)]  # no shape a multiple of the bands below


@pytest.fixture(autouse=True)
def _small_bands(monkeypatch):
    """Bands of a few rows and no inline size, so small arrays are cut into
    many uneven bands and really go through the pool."""
    monkeypatch.delenv(parallel.ENV, raising=False)
    monkeypatch.setattr(maps, "BAND_PIXELS", 97)
    monkeypatch.setattr(maps, "INLINE_PIXELS", 0)
    monkeypatch.setattr(V, "CHUNK_ROWS", 3)
    monkeypatch.setattr(V, "INLINE_PIXELS", 0)
    yield
    parallel.set_threads(None)


def _hostile(rng, x, frac=0.03):
    x = x.copy()
    u = rng.random(x.shape)
    x[u < frac] = np.nan
    x[(u >= frac) & (u < 2 * frac)] = np.inf
    x[(u >= 2 * frac) & (u < 3 * frac)] = -np.inf
    return x


def _each_thread_count(fn):
    parallel.set_threads(1)
    ref = fn()
    for t in THREADS:
        parallel.set_threads(t)
        yield ref, fn()


def _pool_direct(c, dof, r):
    """confidence_pool's unrounded map written out pixel by pixel (the
    definition: w_pp = nu_p, w_pq = nu_p nu_q / (nu_p + nu_q), plain window
    mean where no weight)."""
    c = np.where(np.isfinite(c) & (c > 0), c, 0.0)
    nu = np.where(np.isfinite(dof) & (dof > 0), dof, 0.0)
    h, w = c.shape
    out = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            num = den = plain = area = 0.0
            for qy in range(max(0, y - r), min(h, y + r + 1)):
                for qx in range(max(0, x - r), min(w, x + r + 1)):
                    if (qy, qx) == (y, x):
                        wq = nu[y, x]
                    else:
                        s = nu[y, x] + nu[qy, qx]
                        wq = nu[y, x] * nu[qy, qx] / s if s > 0 else 0.0
                    num += wq * c[qy, qx]
                    den += wq
                    plain += c[qy, qx]
                    area += 1
            out[y, x] = num / den if den > 0 else plain / area
    return out


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("radius", [1, 2])
def test_confidence_pool_same_bits_for_any_thread_count(shape, radius):
    rng = np.random.default_rng(shape[0] * 7 + radius)
    c = _hostile(rng, rng.gamma(0.5, 30.0, shape))
    dof = _hostile(rng, rng.integers(-1, 6, shape).astype(float))
    for ref, got in _each_thread_count(lambda: maps.confidence_pool(c, dof, radius)):
        assert got.dtype == np.int64 and np.array_equal(ref, got)
    finite = np.where(np.isfinite(c) & (c > 0), c, 0.0)
    assert ref.sum() == int(round(finite.sum()))


def test_confidence_pool_equals_the_definition_and_any_band_size(monkeypatch):
    """Banded pooling = the pixel-by-pixel definition (the same sums in the
    same order, zeros added outside the image), bit for bit, then rounded by
    allocate; whatever the band's rows (1 row, a few, the whole frame)."""
    rng = np.random.default_rng(3)
    shape = (19, 23)
    c = _hostile(rng, rng.gamma(0.7, 10.0, shape))
    dof = _hostile(rng, rng.integers(-1, 5, shape).astype(float))
    clean = np.where(np.isfinite(c) & (c > 0), c, 0.0)
    total = int(round(clean.sum()))
    for r in (1, 2):
        direct = _pool_direct(c, dof, r)
        rows = np.empty(shape)
        for y in range(shape[0]):  # one band per row
            maps._pool_rows(clean, dof, r, y, y + 1, rows)
        assert np.array_equal(rows, direct)
    expect = allocate(_pool_direct(c, dof, 1), total)
    parallel.set_threads(3)
    for band_pixels in (1, 23 * 4, 10 ** 9):
        monkeypatch.setattr(maps, "BAND_PIXELS", band_pixels)
        assert np.array_equal(maps.confidence_pool(c, dof, 1), expect)


def _buffers(rng, shape, hostile):
    h, w = shape
    groups = [rng.gamma(1.0, 1.0, (h, w, 3)) for _ in range(4)]
    feats = {"albedo": rng.uniform(0, 1, (h, w, 3)), "normal": rng.normal(0, 1, (h, w, 3)),
             "depth": rng.uniform(0.5, 9.0, (h, w, 1))}
    if hostile:
        groups = [_hostile(rng, g, 0.01) for g in groups]
        feats = {k: _hostile(rng, v, 0.01) for k, v in feats.items()}
    buf = Buffers.from_subsets(groups, [2] * 4, [feats] * 4)
    if hostile:
        buf.n[:1, :2] = 0
        buf.k[:1, :2] = 0
        buf.k[-1, -1:] = 1
    return buf


@pytest.mark.parametrize("shape", SHAPES[1:])
@pytest.mark.parametrize("hostile", [False, True])
@pytest.mark.parametrize("kw", [dict(exponent=1.4), dict(exponent="map", radius=3), dict(radius=0),
                                dict(exponent=1.2, color_guide=True)])
def test_calibrated_variance_same_bits_for_any_thread_count(shape, hostile, kw):
    rng = np.random.default_rng(shape[1] + 11 * hostile)
    buf = _buffers(rng, shape, hostile)
    kw = dict(kw)
    if kw.get("exponent") == "map":
        kw["exponent"] = rng.uniform(0.8, 2.0, shape)
    for ref, got in _each_thread_count(lambda: V.calibrated_variance_and_dof(buf, **kw)):
        assert np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1])
    v, dof = ref
    assert not np.isnan(v).any() and not np.isnan(dof).any()
    assert np.all(dof[~np.isfinite(v)] == 0)


def test_calibrated_variance_any_band_size_and_unpooled_formula(monkeypatch):
    """Bands of 1, 3 and all rows give the same bits; radius 0 is Eq. 2 per
    pixel, M2 / (n (k^beta - 1)), with +inf where k < 2 or n = 0."""
    rng = np.random.default_rng(5)
    shape = (29, 31)
    buf = _buffers(rng, shape, True)
    parallel.set_threads(3)
    outs = []
    for rows in (1, 3, 1000):
        monkeypatch.setattr(V, "CHUNK_ROWS", rows)
        outs.append(V.calibrated_variance_and_dof(buf, exponent=1.3, radius=2))
    for o in outs[1:]:
        assert np.array_equal(outs[0][0], o[0]) and np.array_equal(outs[0][1], o[1])
    b = 1.3
    got = V.calibrated_variance_of_mean(buf, exponent=b, radius=0)
    n, k = buf.n.astype(float), buf.k.astype(float)
    ok = (n > 0) & (k >= 2)
    with np.errstate(all="ignore"):
        direct = buf.color.m2 / (np.where(ok, n, 1.0) * (np.where(ok, k, 2.0) ** b - 1.0))[..., None]
    m2 = buf.color.m2
    fine = ok[..., None] & np.isfinite(m2) & (m2 >= 0)
    assert np.allclose(got[fine], direct[fine], rtol=1e-12, atol=0)
    assert np.all(np.isinf(got[~ok]))


def test_pool_m2_same_bits_for_any_thread_count():
    rng = np.random.default_rng(8)
    shape = (37, 26)
    m2 = _hostile(rng, rng.gamma(1.0, 1.0, shape + (3,)))
    fac = rng.uniform(-0.5, 2.0, shape)
    dof = rng.integers(0, 4, shape).astype(float)
    guides = [(rng.uniform(0, 1, shape + (3,)), rng.uniform(0, 0.01, shape + (3,)), 0.05)]
    for ref, got in _each_thread_count(lambda: V.pool_m2(m2, fac, guides, 2, dof=dof)):
        assert np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1])


def _allocate_whole(weights, budget, cap=None):
    """Largest-remainder rounding written out over the whole array at once
    (the definition allocate's pieces must reproduce bit for bit)."""
    w = np.asarray(weights, np.float64)
    w = np.where(np.isfinite(w) & (w > 0), w, 0.0)
    budget = int(max(budget, 0))
    out = np.zeros(w.shape, np.int64)
    if budget == 0 or w.size == 0:
        return out
    cap_arr = None if cap is None else np.broadcast_to(np.asarray(cap, np.int64), w.shape)
    if cap_arr is not None:
        budget = min(budget, int(cap_arr.sum()))
    remaining = budget
    active = np.ones(w.shape, bool) if cap_arr is None else cap_arr > 0
    for _ in range(64):
        if remaining <= 0 or not active.any():
            break
        ww = np.where(active, w, 0.0)
        if ww.sum() <= 0:
            ww = active.astype(np.float64)
        share = ww / ww.sum() * remaining
        base = np.floor(share).astype(np.int64)
        rest = remaining - int(base.sum())
        if rest > 0:
            frac = (share - base).ravel()
            idx = np.argpartition(-frac, rest - 1)[:rest] if rest < frac.size else np.arange(frac.size)
            base.ravel()[idx] += 1
        add = base if cap_arr is None else np.minimum(base, cap_arr - out)
        out += add
        remaining -= int(add.sum())
        if cap_arr is None:
            break
        active = out < cap_arr
    return out


@pytest.mark.parametrize("shape", SHAPES + [(40, 50)])
@pytest.mark.parametrize("kind", ["gamma", "ties", "zeros", "float32"])
def test_allocate_in_pieces_is_the_whole_array_rounding(shape, kind, monkeypatch):
    """allocate over pieces of 7 elements on 1-5 threads gives the counts of
    the whole-array definition, ties among the remainders included (pooled
    maps are full of them), for hostile weights, all-zero weights, float32
    input and with a cap."""
    from core import method
    monkeypatch.setattr(method, "ALLOCATE_PIECE", 7)
    monkeypatch.setattr(method, "INLINE_PIXELS", 0)
    rng = np.random.default_rng(shape[0] * 31 + len(kind))
    if kind == "ties":
        w = rng.integers(0, 4, shape).astype(float)
    elif kind == "zeros":
        w = np.zeros(shape)
    else:
        w = _hostile(rng, rng.gamma(0.5, 3.0, shape))
    if kind == "float32":
        w = w.astype(np.float32)
    n = int(np.prod(shape))
    for budget in (0, 1, 3 * n + 2, n // 3 + 1):
        cap = np.full(shape, 4, np.int64)
        for c in (None, cap):
            expect = _allocate_whole(w, budget, c)
            for ref, got in _each_thread_count(lambda: method.allocate(w, budget, c)):
                assert got.dtype == np.int64 and np.array_equal(expect, got) and np.array_equal(ref, got)
            assert expect.sum() == (budget if c is None else min(budget, int(cap.sum())))

"""The controller's per-pixel work on threads (core.parallel): merges, var's
priority and sample map, the 3x3 median and the consistency guard give the
same bits for any thread count, and equal independent whole-frame formulas."""
import numpy as np
import pytest

from core import buffers, method, parallel, var
from core.buffers import Buffers
from core.method import MethodResult, consistency_guard, median3x3

FEATS = {"albedo": 3, "normal": 3, "depth": 1, "alpha": 1}
THREADS = (2, 3, 5)


@pytest.fixture(autouse=True)
def _small_bands(monkeypatch):
    """Bands of a few rows and no inline size, so small arrays are cut into
    many uneven bands and really go through the pool."""
    monkeypatch.delenv(parallel.ENV, raising=False)
    monkeypatch.setattr(buffers, "BAND_PIXELS", 97)
    monkeypatch.setattr(buffers, "INLINE_PIXELS", 0)
    monkeypatch.setattr(var, "BAND_PIXELS", 83)
    monkeypatch.setattr(var, "INLINE_PIXELS", 0)
    monkeypatch.setattr(var, "FLAT_PIECE", 211)
    monkeypatch.setattr(var, "HASH_BYTES", 1000)
    monkeypatch.setattr(method, "INLINE_PIXELS", 0)
    var.clear_priority_cache()
    yield
    parallel.set_threads(None)
    var.clear_priority_cache()


def _arrays(b: Buffers) -> list:
    out = [b.n, b.k, b.color.mean, b.color.m2]
    for k in sorted(b.features):
        out += [b.features[k].mean, b.features[k].m2]
    if b.half is not None:
        out += [b.half.n, b.half.color] + [b.half.features[k] for k in sorted(b.half.features)]
    return out


def _same(a, b) -> bool:
    """Bit for bit (NaN payloads included)."""
    a, b = np.atleast_1d(a), np.atleast_1d(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if a.dtype.kind == "f":
        return np.array_equal(a.view(np.uint8), b.view(np.uint8))
    return np.array_equal(a, b)


def _same_buffers(a: Buffers, b: Buffers) -> bool:
    xa, xb = _arrays(a), _arrays(b)
    return len(xa) == len(xb) and all(_same(x, y) for x, y in zip(xa, xb))


def _accumulate(h=37, w=29, seed=0, halves=True):
    """Buffers after whole-frame and region groups with zero counts, scalar
    and per-pixel counts, NaN/Inf samples, float32 passes, a (h, w) depth, a
    group whose pass is the accumulated mean itself (merge_render's missing
    pass), and merges of accumulated buffers with, without and with invalid
    halves."""
    rng = np.random.default_rng(seed)
    b = Buffers.empty(h, w, tuple(FEATS))
    if not halves:
        b.half = None
    for it in range(7):
        if it < 2:
            reg, hh, ww = None, h, w
        else:
            x0, y0 = int(rng.integers(0, w - 4)), int(rng.integers(0, h - 4))
            x1, y1 = int(rng.integers(x0 + 1, w + 1)), int(rng.integers(y0 + 1, h + 1))
            reg, hh, ww = (x0, y0, x1, y1), y1 - y0, x1 - x0
        col = rng.gamma(0.7, 1.0, (hh, ww, 3))
        if it == 3:
            col[0, 0, 0], col[-1, -1, 1], col[hh // 2, 0, 2] = np.nan, np.inf, -np.inf
        cnt = rng.integers(0, 4, (hh, ww)) if it % 2 else (0 if it == 2 else int(rng.integers(1, 5)))
        feats = {k: rng.random((hh, ww, c)) for k, c in FEATS.items()}
        if it == 4:
            feats = {k: v.astype(np.float32) for k, v in feats.items()}
        if it == 5:
            feats["depth"] = rng.random((hh, ww))
        if it == 6:
            sl = buffers._region_slice(reg, b.shape)
            feats["normal"] = b.features["normal"].mean[sl]
        b.merge_group(col, cnt, feats, region=reg)
    o = Buffers.empty(h // 2, w // 3, tuple(FEATS))
    for _ in range(3):
        o.merge_group(rng.random((h // 2, w // 3, 3)), rng.integers(0, 3, (h // 2, w // 3)),
                      {k: rng.random((h // 2, w // 3, c)) for k, c in FEATS.items()})
    b.merge(o, region=(1, 2, 1 + w // 3, 2 + h // 2))
    plain = o.copy()
    plain.half = None
    b.merge(plain, region=(0, 0, w // 3, h // 2))
    broken = o.copy()
    broken.half.n[0, 0] = -1.0  # halves() is None: counts as one group
    b.merge(broken, region=(2, 1, 2 + w // 3, 1 + h // 2))
    b.merge(Buffers.empty(h, w, tuple(FEATS)))  # counts 0 everywhere
    return b


@pytest.mark.parametrize("halves", [True, False])
def test_merges_are_bit_identical_for_any_thread_count(halves):
    parallel.set_threads(1)
    ref = _accumulate(halves=halves)
    assert np.isnan(ref.color.mean).any() and np.isnan(ref.color.m2).any()
    for t in THREADS:
        parallel.set_threads(t)
        got = _accumulate(halves=halves)
        assert _same_buffers(ref, got), t
        if halves:
            (na, ca, fa), (nb, cb, fb) = got.halves()
            (ra, rca, rfa), (rb, rcb, rfb) = ref.halves()
            assert _same(na, ra) and _same(cb, rcb) and all(_same(fb[k], rfb[k]) for k in rfb)


def test_banded_merge_equals_plain_chan_update():
    """Chan, Golub, LeVeque (1979) written out on whole arrays: bit-equal to
    the banded in-place update, and the mean / M2 of all samples (two-pass)."""
    parallel.set_threads(3)
    rng = np.random.default_rng(4)
    h, w = 23, 31
    b = Buffers.empty(h, w, ("depth",))
    mean, m2, n, k = (np.zeros((h, w, 3)), np.zeros((h, w, 3)), np.zeros((h, w)), np.zeros((h, w)))
    samples = [[[] for _ in range(w)] for _ in range(h)]
    for _ in range(5):
        cnt = rng.integers(0, 4, (h, w)).astype(np.float64)
        x = rng.normal(1.0, 0.3, (h, w, 3))
        b.merge_group(x, cnt, {"depth": rng.random((h, w, 1))})
        nn = n + cnt
        has = cnt > 0
        safe = np.where(nn > 0, nn, 1.0)
        delta = x - mean
        mean = np.where(has[..., None], mean + delta * (cnt / safe)[..., None], mean)
        m2 = np.where(has[..., None], m2 + delta * delta * (n * cnt / safe)[..., None], m2)
        n, k = nn, k + has
        for y, xx in zip(*np.nonzero(has)):
            samples[y][xx].append((cnt[y, xx], x[y, xx]))
    assert _same(b.color.mean, mean) and _same(b.color.m2, m2)
    assert _same(b.n, n) and _same(b.k, k)
    for y in range(0, h, 5):
        for xx in range(0, w, 7):
            g = samples[y][xx]
            if not g:
                assert np.all(b.color.mean[y, xx] == 0) and b.n[y, xx] == 0
                continue
            c = np.array([s[0] for s in g])
            v = np.array([s[1] for s in g])
            mu = (c[:, None] * v).sum(0) / c.sum()
            np.testing.assert_allclose(b.color.mean[y, xx], mu, rtol=1e-12)
            np.testing.assert_allclose(b.color.m2[y, xx], (c[:, None] * (v - mu) ** 2).sum(0),
                                       rtol=1e-9, atol=1e-12)


def test_missing_pass_is_an_error_before_any_change():
    parallel.set_threads(2)
    b = Buffers.empty(9, 8, ("albedo", "depth"))
    b.merge_group(np.ones((9, 8, 3)), 1, {"albedo": np.ones((9, 8, 3)), "depth": np.ones((9, 8, 1))})
    before = b.copy()
    with pytest.raises(KeyError):
        b.merge_group(np.full((9, 8, 3), 2.0), 1, {"albedo": np.ones((9, 8, 3))})
    other = Buffers.empty(9, 8, ("albedo",))
    with pytest.raises(KeyError):
        b.merge(other)
    assert _same_buffers(b, before)


def _stats(h=41, w=53, seed=2):
    rng = np.random.default_rng(seed)
    b = Buffers.empty(h, w, ())
    for i in range(4):
        c = rng.gamma(0.5, 1.0, (h, w, 3)) * (1 + 5 * (rng.random((h, w, 1)) < 0.02))
        b.merge_group(c, rng.integers(0, 3, (h, w)) if i else 1, {})
    b.color.mean[0, 0, 1] = np.nan
    b.color.m2[1, 2, 0] = np.inf
    b.color.mean[-1, 3, 2] = -np.inf
    b.color.mean[2, -1] = -0.3
    b.k[3, :5] = 1
    return b


def _var_run(b):
    p = var.Params()
    out = [var.pixel_variance(b), var.pixel_priority(b, p),
           var.pixel_priority(b, var.Params(epsilon_inside_sqrt=True))]
    state = {}
    for budget in (b.n.size // 2, 3 * b.n.size, 7, 20 * b.n.size, 1234, 40 * b.n.size):
        out.append(var.sample_map(b, None, budget, p, state))
    st2 = {"probability": np.where(np.random.default_rng(3).random(b.shape) < 0.3, 0.5, np.nan)}
    for budget in (b.n.size, 5 * b.n.size, 30 * b.n.size):
        out.append(var.reprojected_sample_map(b, None, budget, p, st2))
    out.append(var.threshold(state["itr"], p))
    return out, var._priority_key(b, p)


def test_var_priority_and_maps_are_bit_identical_for_any_thread_count():
    b = _stats()
    parallel.set_threads(1)
    ref, key = _var_run(b)
    assert np.isinf(ref[0]).any() and all(m.sum() > 0 for m in ref[3:-1])
    for t in THREADS:
        parallel.set_threads(t)
        var.clear_priority_cache()
        got, k = _var_run(b)
        assert k == key
        assert all(_same(x, y) for x, y in zip(ref, got)), t


def test_var_priority_equals_whole_frame_formula_and_key_follows_contents():
    """Eq. 11 and 12 on the whole frame at once; the content key changes with
    one bit of one array and not with a copy."""
    parallel.set_threads(3)
    b = _stats()
    p = var.Params()
    s2 = b.sample_variance()
    v = np.where(np.all(np.isfinite(s2), -1) & np.all(np.isfinite(b.color.mean), -1),
                 np.maximum(np.where(np.isfinite(s2), s2, 0.0), 0.0).mean(-1), np.inf)
    assert _same(var.pixel_variance(b), v)
    m = b.color.mean
    mf = np.where(np.isfinite(m), m, 0.0)
    L = buffers.LUMA
    lum = np.where(np.all(np.isfinite(m), -1), mf[..., 0] * L[0] + mf[..., 1] * L[1] + mf[..., 2] * L[2], np.nan)
    assert _same(var.pixel_priority(b, p), var.relative_deviation(v, lum, p))
    key = var._priority_key(b, p)
    assert var._priority_key(b.copy(), p) == key
    b.color.m2[40, 52, 2] = np.nextafter(b.color.m2[40, 52, 2], np.inf)
    assert var._priority_key(b, p) != key


def _median_reference(x):
    pad = np.pad(x, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = x.shape[:2]
    planes = [pad[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)]
    return np.median(np.stack(planes), axis=0)


def test_median3x3_matches_np_median_for_any_thread_count():
    rng = np.random.default_rng(7)
    x = rng.integers(0, 4, (29, 17, 2)).astype(np.float64)  # many ties
    x[rng.random(x.shape) < 0.02] = np.nan
    x[0, 0, 0] = np.inf
    ref = _median_reference(x)
    for t in (1,) + THREADS:
        parallel.set_threads(t)
        for rows in (1, 2, 5, 64):
            got = median3x3(x, rows=rows)
            assert np.array_equal(got, ref, equal_nan=True), (t, rows)
    assert median3x3(np.zeros((0, 4, 3))).shape == (0, 4, 3)


def _guard_reference(result, buf, z):
    """The guard on whole frames (np.median for the floor)."""
    mean, var_ = buf.color.mean, buf.variance_of_mean()
    known = buf.has_variance[..., None] & np.isfinite(var_) & np.isfinite(mean)
    sd = np.sqrt(np.where(known, np.maximum(var_, 0.0), 0.0))
    sd = np.maximum(sd, _median_reference(sd))
    thr = method.t_quantile(z, np.maximum(buf.k - 1.0, 1.0))[..., None]
    bad = ((np.abs(result.image - mean) > thr * sd) & known).any(-1) & known.all(-1)
    image = np.where(bad[..., None], mean, result.image)
    err = np.where(bad, np.where(known, var_, 0.0).mean(-1), result.error)
    return image, err, float(bad.mean())


def test_consistency_guard_is_bit_identical_for_any_thread_count():
    b = _stats(47, 39, seed=5)
    rng = np.random.default_rng(8)
    img = b.color.mean + rng.normal(0, 1, b.color.mean.shape) * (rng.random(b.shape + (1,)) < 0.05)
    img[5, 5] = np.nan
    res = MethodResult(img, rng.random(b.shape), {"a": 1})
    with np.errstate(invalid="ignore"):
        ref_img, ref_err, frac = _guard_reference(res, b, 3.0)
    assert frac > 0
    for rows in (3, 64):
        for t in (1,) + THREADS:
            parallel.set_threads(t)
            g = consistency_guard(res, b, 3.0, rows=rows)
            assert _same(g.image, ref_img) and _same(g.error, ref_err), (t, rows)
            assert g.info == {"a": 1, "guard_fraction": frac, "guard_rounding": 0.0}
            same = consistency_guard(MethodResult(b.color.mean, np.zeros(b.shape)), b, 3.0, rows=rows)
            assert same.info["guard_fraction"] == 0.0 and same.image is b.color.mean

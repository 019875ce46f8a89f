"""core.cryptomatte against an independent per-pixel dict implementation."""
import math

import numpy as np
import pytest

from core import storage
from core.cryptomatte import CryptoAccumulator, as_id_bits, layers_to_ranks


def _ref_merge(state, ids, cov, n, cap):
    """Reference: one pixel's dict id -> weighted coverage, top ``cap``."""
    d = dict(state)
    for i, c in zip(ids, cov):
        c = float(c)
        if not math.isfinite(c) or c <= 0:
            continue
        d[int(i)] = d.get(int(i), 0.0) + c * n
    top = sorted(d.items(), key=lambda kv: (-kv[1], kv[0]))[:cap]
    return dict(top)


def _random_render(rng, h, w, lv, pool):
    ids = rng.choice(pool, size=(h, w, lv)).astype(np.uint32)
    cov = rng.integers(0, 9, size=(h, w, lv)) / 16.0  # exact in float64 sums
    cov[rng.random((h, w, lv)) < 0.1] = np.nan
    cov[rng.random((h, w, lv)) < 0.05] = np.inf
    cov[rng.random((h, w, lv)) < 0.05] = -0.25
    ids[cov == 0] = 0  # Blender's empty rank
    return ids, cov


@pytest.mark.parametrize("cap,lv", [(2, 2), (3, 4), (6, 4), (1, 3)])
def test_merge_matches_dict_reference(cap, lv):
    rng = np.random.default_rng(cap * 10 + lv)
    h, w = 7, 9
    pool = np.array([0, 1, 5, 7, 0xFFFFFFFF, 0x3F800000, 12345], np.uint32)
    acc = CryptoAccumulator(h, w, cap)
    ref = [[{} for _ in range(w)] for _ in range(h)]
    wsum = np.zeros((h, w))
    for _ in range(6):
        x0, x1 = sorted(rng.choice(w + 1, 2, replace=False))
        y0, y1 = sorted(rng.choice(h + 1, 2, replace=False))
        n = int(rng.integers(1, 9))
        ids, cov = _random_render(rng, y1 - y0, x1 - x0, lv, pool)
        acc.merge(ids, cov, n, region=(x0, y0, x1, y1))
        for y in range(y0, y1):
            for x in range(x0, x1):
                ref[y][x] = _ref_merge(ref[y][x], ids[y - y0, x - x0], cov[y - y0, x - x0], n, cap)
                wsum[y, x] += n
    out_id, out_cov = acc.ranks()
    assert np.all(np.isfinite(out_cov))
    for y in range(h):
        for x in range(w):
            items = sorted(ref[y][x].items(), key=lambda kv: (-kv[1], kv[0]))
            exp_id = [i for i, _ in items] + [0] * (cap - len(items))
            exp_cov = [c / wsum[y, x] for _, c in items] + [0.0] * (cap - len(items))
            assert out_id[y, x].tolist() == exp_id
            assert out_cov[y, x].tolist() == exp_cov


def test_rank_order_of_input_does_not_matter():
    rng = np.random.default_rng(3)
    ids, cov = _random_render(rng, 5, 5, 4, np.arange(6, dtype=np.uint32))
    a, b = CryptoAccumulator(5, 5, 4), CryptoAccumulator(5, 5, 4)
    a.merge(ids, cov, 3)
    perm = rng.permutation(4)
    b.merge(ids[:, :, perm], cov[:, :, perm], 3)
    assert np.array_equal(a.ids, b.ids) and np.array_equal(a.wcov, b.wcov)


def test_weighted_by_samples_closed_form():
    acc = CryptoAccumulator(1, 1, 2)
    acc.merge(np.array([[[7, 9]]], np.uint32), np.array([[[1.0, 0.0]]]), 4)   # 4 samples all id 7
    acc.merge(np.array([[[9, 7]]], np.uint32), np.array([[[0.5, 0.5]]]), 12)  # 12 samples half/half
    ids, cov = acc.ranks()
    assert ids[0, 0].tolist() == [7, 9]
    assert cov[0, 0].tolist() == [(4 + 6) / 16, 6 / 16]


def test_empty_and_unmerged_pixels_are_zero_and_bad_samples_ignored():
    acc = CryptoAccumulator(2, 2, 2)
    acc.merge(np.zeros((1, 1, 2), np.uint32), np.zeros((1, 1, 2)), 5, region=(0, 0, 1, 1))
    acc.merge(np.ones((1, 1, 2), np.uint32), np.ones((1, 1, 2)), float("nan"), region=(1, 1, 2, 2))
    ids, cov = acc.ranks(3)
    assert ids.shape == (2, 2, 3) and not ids.any() and not cov.any()
    assert acc.weight.tolist() == [[5.0, 0.0], [0.0, 0.0]]


def test_float_id_bits_and_layers_round_trip():
    rng = np.random.default_rng(5)
    bits = rng.integers(1, 2 ** 32, size=(3, 4, 3), dtype=np.uint64).astype(np.uint32)
    fl = bits.view(np.float32)
    assert np.array_equal(as_id_bits(fl), bits)
    acc = CryptoAccumulator(3, 4, 3)
    acc.merge(fl, np.tile([0.5, 0.25, 0.125], (3, 4, 1)), 2)
    layers = acc.layers(3)
    assert len(layers) == 2 and all(layer.dtype == np.float32 and layer.shape == (3, 4, 4) for layer in layers)
    back_ids, back_cov = layers_to_ranks(layers)
    ids, cov = acc.ranks(3)
    assert np.array_equal(back_ids[:, :, :3], ids) and np.array_equal(back_cov[:, :, :3], cov)
    assert not back_ids[:, :, 3].any() and not back_cov[:, :, 3].any()


def test_state_round_trips_through_pack_array():
    rng = np.random.default_rng(9)
    acc = CryptoAccumulator(16, 16, 4)
    for _ in range(3):
        ids, cov = _random_render(rng, 16, 16, 4, np.arange(1, 40, dtype=np.uint32))
        acc.merge(ids, cov, int(rng.integers(1, 5)))
    restored = {k: storage.unpack_array(*storage.pack_array(v)) for k, v in acc.state().items()}
    back = CryptoAccumulator.from_state(restored)
    for k, v in acc.state().items():
        assert np.array_equal(back.state()[k], v) and back.state()[k].dtype == v.dtype
    with pytest.raises(ValueError):
        CryptoAccumulator.from_state({"ids": acc.ids, "wcov": acc.wcov[:, :, :2], "weight": acc.weight})


def test_murmurhash3_matches_blenders_manifest_and_key():
    from core.cryptomatte import header_key, murmurhash3_32
    # values Blender 4.2 / 4.5 / 5.0 wrote for a scene with these objects
    assert f"{murmurhash3_32('Plane'):08x}" == "4159b52a"
    assert f"{murmurhash3_32('Sphere'):08x}" == "e5e9b0db"
    assert f"{murmurhash3_32('Cube'):08x}" == "a8fce865"
    assert header_key("ViewLayer.CryptoObject") == "542cafa"


class _CryptoExecutor:
    """A FakeExecutor whose renders also carry Cryptomatte ranks: sample i of
    pixel (y, x) covers id 1 + (x + 2y + i) % 3, so a render's coverage of
    an id is its count among the render's samples / samples."""

    def __init__(self, h, w):
        from conftest import FakeExecutor
        ys, xs = np.mgrid[0:h, 0:w]
        truth = np.where(xs[..., None] < w // 2, 0.05, 3.0) * np.ones((h, w, 3))  # unequal noise
        self.inner = FakeExecutor(truth)
        self.size = (h, w)

    def render(self, task):
        rgba, feats = self.inner.render(task)
        ys, xs = np.mgrid[task.y0:task.y1, task.x0:task.x1]
        counts = np.zeros(ys.shape + (3,))
        for i in range(task.offset, task.offset + task.samples):
            counts[..., 0] += (xs + 2 * ys + i) % 3 == 0
            counts[..., 1] += (xs + 2 * ys + i) % 3 == 1
            counts[..., 2] += (xs + 2 * ys + i) % 3 == 2
        ids = np.broadcast_to(np.array([1, 2, 3], np.uint32), counts.shape)
        header = {"name": "ViewLayer.CryptoObject", "manifest": '{"a":"00000001"}'}
        feats = dict(feats, cryptomatte={"CryptoObject": (ids, counts / task.samples, header)})
        return rgba, feats


def _expected(tasks, h, w):
    """Coverage of ids 1, 2, 3 over the samples of every task rendered."""
    counts, n = np.zeros((h, w, 3)), np.zeros((h, w, 1))
    for t in tasks:
        ys, xs = np.mgrid[t.y0:t.y1, t.x0:t.x1]
        for i in range(t.offset, t.offset + t.samples):
            for k in range(3):
                counts[t.y0:t.y1, t.x0:t.x1, k] += (xs + 2 * ys + i) % 3 == k
        n[t.y0:t.y1, t.x0:t.x1] += t.samples
    return counts / n


def test_adaptive_run_merges_ranks_of_every_task_and_resumes(tmp_path):
    from core.pipeline import AdaptiveRun, Options
    opts = Options(method="var", spp=12, initial_spp=4, subsets=2, task_cost=16, min_task_size=4)
    ex = _CryptoExecutor(16, 24)
    full = AdaptiveRun(ex, opts)
    for _ in full.steps():
        pass
    acc = full.cryptomatte["CryptoObject"]
    assert np.array_equal(acc.weight, full.buffers.n) and full.buffers.n.max() > full.buffers.n.min()
    ids, cov = acc.ranks(3)
    exp = _expected(ex.inner.tasks, 16, 24)
    got = np.stack([np.where(ids == k + 1, cov, 0).sum(axis=2) for k in range(3)], axis=-1)
    np.testing.assert_allclose(got, exp, rtol=0, atol=1e-12)
    assert full.cryptomatte_header["CryptoObject"]["name"] == "ViewLayer.CryptoObject"
    ckpt = str(tmp_path / "run.npz")
    first = AdaptiveRun(_CryptoExecutor(16, 24), opts, checkpoint=ckpt)
    steps = first.steps()
    for st in steps:  # stop right after the second checkpoint, then resume
        if st.stage == "checkpoint" and st.iteration == 2:
            break
    steps.close()
    resumed = AdaptiveRun(_CryptoExecutor(16, 24), opts, checkpoint=ckpt)
    resumed.load_checkpoint(ckpt)
    assert resumed.cryptomatte["CryptoObject"].weight.max() > 0
    for _ in resumed.steps():
        pass
    for k, v in acc.state().items():
        np.testing.assert_array_equal(resumed.cryptomatte["CryptoObject"].state()[k], v)
    assert resumed.cryptomatte_header == full.cryptomatte_header

"""Region planner (core/regions.py): border conversion, layered quadtree plan,
sample offsets."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from core import regions as R
from core.regions import RegionTask

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


# ------------------------------------------------------------------ helpers
def paint_loops(tasks, shape):
    """Independent painter: plain slicing per task."""
    out = np.zeros(shape, np.int64)
    for t in tasks:
        out[t.y0:t.y1, t.x0:t.x1] += t.samples
    return out


def optimal_cost(c, s, tc, force_split=False):
    """Independent recursive layered-quadtree optimum: task_cost * tasks +
    overshoot of the cheapest plan before merging (``force_split``: the plan
    that splits down to the leaves, exact at ``min_size`` resolution)."""
    h, w = c.shape
    hl, wl = -(-h // s), -(-w // s)
    g = 1
    while g < max(hl, wl):
        g *= 2

    def rec(i, j, size, mp):          # block of size x size leaf cells at (i, j)
        y0, x0 = i * size * s, j * size * s
        blk = c[y0:min(y0 + size * s, h), x0:min(x0 + size * s, w)]
        if blk.size == 0:
            return 0.0
        mn, mx = int(blk.min()), int(blk.max())
        stop = tc * (mx > mp) + float(mx * blk.size - blk.sum())
        if size == 1:
            return stop
        half = size // 2
        split = tc * (mn > mp) + sum(rec(2 * i + a, 2 * j + b, half, mn)
                                     for a in (0, 1) for b in (0, 1))
        return split if force_split else min(stop, split)

    return rec(0, 0, g, 0)


def check_plan(c, p, frame=0):
    h, w = c.shape
    assert p.covered.shape == (h, w) and p.covered.dtype == np.int64
    assert (p.covered >= c).all()
    assert p.overshoot == int(p.covered.sum() - c.sum()) >= 0
    assert p.n_tasks == len(p.tasks)
    assert p.requested == int(c.sum())
    for t in p.tasks:
        assert 0 <= t.x0 < t.x1 <= w and 0 <= t.y0 < t.y1 <= h
        assert t.samples > 0 and t.frame == frame and t.offset == 0
    np.testing.assert_array_equal(paint_loops(p.tasks, (h, w)), p.covered)


SHAPES = [(1, 1), (1, 9), (1, 64), (9, 1), (3, 5), (7, 7), (13, 17), (31, 37), (24, 64), (61, 2)]


# ----------------------------------------------------------------- task
def test_region_task_properties_and_frozen():
    t = RegionTask(2, 3, 10, 7, 5, frame=4, offset=9)
    assert (t.width, t.height, t.pixels, t.rect) == (8, 4, 32, (2, 3, 10, 7))
    with pytest.raises(Exception):
        t.x0 = 1  # frozen


def test_border_round_trip_every_size_to_2000():
    """border_coord(p, n) gives back p under Blender's float32 truncation (and
    under rounding) for every boundary of every size 1..2000."""
    naive_wrong = 0
    for n in range(1, 2001):
        p = np.arange(n + 1)
        v = R.border_coord(p, n)
        assert np.all((v >= 0) & (v <= 1)) and np.all(np.diff(v) > 0)
        np.testing.assert_array_equal(R.blender_border_pixel(v, n), p)
        prod = (v.astype(np.float32) * np.float32(n)).astype(np.float32)
        np.testing.assert_array_equal(np.rint(prod).astype(np.int64), p)
        naive_wrong += int(np.sum(R.blender_border_pixel(p / n, n) != p))
    assert naive_wrong > 0   # the nudge is needed: x/W alone loses pixels


@pytest.mark.parametrize("w,h", [(1, 1), (1, 7), (41, 37), (22, 23), (1920, 1080), (1999, 3)])
def test_task_border_pixels_round_trip(w, h):
    rng = np.random.default_rng(w * 7 + h)
    for _ in range(50):
        x0, x1 = sorted(rng.choice(w + 1, 2, replace=False)) if w > 1 else (0, 1)
        y0, y1 = sorted(rng.choice(h + 1, 2, replace=False)) if h > 1 else (0, 1)
        t = RegionTask(int(x0), int(y0), int(x1), int(y1), 1)
        b = t.border(w, h)
        assert b["border_min_x"] < b["border_max_x"] and b["border_min_y"] < b["border_max_y"]
        assert R.pixels_from_border(b, w, h) == t.rect


def test_border_rejects_outside_rectangles():
    with pytest.raises(ValueError):
        RegionTask(0, 0, 5, 5, 1).border(4, 4)
    with pytest.raises(ValueError):
        RegionTask(3, 0, 3, 2, 1).border(4, 4)


@pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="bpy not installed")
def test_border_against_blender(tmp_path):
    """Cycles crops exactly the task's pixels, in cases where x/W alone is off."""
    cases = [[41, 37, [0, 13, 32, 37, 1]],   # max_x 32/41 and max_y 24/37
             [22, 23, [13, 0, 22, 16, 1]]]   # min_x 13/22 and min_y 7/23
    for w, h, t in cases:   # the naive formula is wrong on each
        x0, y0, x1, y1, _ = t
        naive = (R.blender_border_pixel(x0 / w, w), R.blender_border_pixel(x1 / w, w),
                 R.blender_border_pixel((h - y1) / h, h), R.blender_border_pixel((h - y0) / h, h))
        assert naive != (x0, x1, h - y1, h - y0)
    script = tmp_path / "b.py"
    script.write_text(
        "import sys, json\nsys.path.insert(0, sys.argv[1])\nimport bpy\nimport OpenImageIO as oiio\n"
        "from core.regions import RegionTask\n"
        "bpy.ops.wm.read_factory_settings(use_empty=False)\ns = bpy.context.scene\n"
        "s.render.engine = 'CYCLES'; s.cycles.samples = 1; s.cycles.device = 'CPU'\n"
        "s.render.resolution_percentage = 100\n"
        "s.render.use_border = True; s.render.use_crop_to_border = True\n"
        "s.render.image_settings.file_format = 'OPEN_EXR'\nout = []\n"
        "for W, H, t in json.loads(sys.argv[2]):\n"
        "    task = RegionTask(*t)\n"
        "    s.render.resolution_x, s.render.resolution_y = W, H\n"
        "    for k, v in task.border(W, H).items():\n        setattr(s.render, k, v)\n"
        "    s.render.filepath = sys.argv[3]\n"
        "    bpy.ops.render.render(write_still=True)\n"
        "    i = oiio.ImageInput.open(sys.argv[3]); sp = i.spec(); i.close()\n"
        "    out.append([sp.width, sp.height])\n"
        "print('RESULT', json.dumps(out))\n")
    res = subprocess.run([sys.executable, str(script), ROOT, json.dumps(cases),
                          str(tmp_path / "x.exr")], capture_output=True, text=True, timeout=300)
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT")]
    assert line, res.stdout[-2000:] + res.stderr[-2000:]
    got = json.loads(line[0][len("RESULT"):])
    assert got == [[t[2] - t[0], t[3] - t[1]] for _, _, t in cases]


# ----------------------------------------------------------------- plan
@pytest.mark.parametrize("shape", SHAPES)
def test_plan_uniform_one_task_exact(shape):
    for tc in (0.0, R.DEFAULT_TASK_COST):
        c = np.full(shape, 7, np.int64)
        p = R.plan(c, frame=3, task_cost=tc)
        check_plan(c, p, frame=3)
        assert p.n_tasks == 1 and p.overshoot == 0
        assert p.tasks[0].rect == (0, 0, shape[1], shape[0]) and p.tasks[0].samples == 7


@pytest.mark.parametrize("shape", SHAPES)
def test_plan_zero_map_no_tasks(shape):
    p = R.plan(np.zeros(shape, np.int64))
    assert p.n_tasks == 0 and p.tasks == () and p.overshoot == 0 and not p.covered.any()


@pytest.mark.parametrize("shape", SHAPES + [(64, 64), (40, 56)])
@pytest.mark.parametrize("s", [1, 2, 4, 8])
def test_plan_exact_on_aligned_blocks(shape, s):
    rng = np.random.default_rng(shape[0] * 100 + shape[1] + s)
    h, w = shape
    cells = rng.integers(0, 6, (-(-h // s), -(-w // s)))
    c = np.kron(cells, np.ones((s, s), np.int64))[:h, :w]
    p = R.plan(c, min_size=s, task_cost=0)
    check_plan(c, p)
    np.testing.assert_array_equal(p.covered, c)


def test_plan_is_cheapest_layered_quadtree():
    """tc * tasks + overshoot <= the recursive optimum (merging only removes
    tasks), which is itself <= the exact fully split plan."""
    rng = np.random.default_rng(5)
    for shape in [(5, 7), (16, 16), (24, 40), (33, 17)]:
        for s in (1, 4, 8):
            for tc in (0.0, 3.0, 50.0, 4096.0):
                c = rng.integers(0, 9, shape) * (rng.random(shape) < 0.5)
                p = R.plan(c, min_size=s, task_cost=tc)
                check_plan(c, p)
                best = optimal_cost(c, s, tc)
                assert tc * p.n_tasks + p.overshoot <= best + 1e-9
                assert best <= optimal_cost(c, s, tc, force_split=True) + 1e-9


@settings(max_examples=40, deadline=None)
@given(h=st.integers(1, 40), w=st.integers(1, 40), s=st.sampled_from([1, 2, 3, 8]),
       tc=st.sampled_from([0.0, 10.0, 4096.0]), hi=st.integers(1, 50),
       seed=st.integers(0, 2 ** 16), frame=st.integers(0, 9))
def test_plan_invariants_random_maps(h, w, s, tc, hi, seed, frame):
    rng = np.random.default_rng(seed)
    c = rng.integers(0, hi + 1, (h, w))
    p = R.plan(c, frame=frame, min_size=s, task_cost=tc)
    check_plan(c, p, frame)
    # overshoot bounded by the cheapest plan's cost (tasks cost >= 0)
    assert p.overshoot <= optimal_cost(c, s, tc) + 1e-9
    if tc == 0.0 and s == 1:
        assert p.overshoot == 0


@settings(max_examples=25, deadline=None)
@given(h=st.integers(1, 30), w=st.integers(1, 30), seed=st.integers(0, 2 ** 16),
       bad=st.sampled_from([np.nan, np.inf, -np.inf, -5.0, 1e30]))
def test_plan_hostile_maps(h, w, seed, bad):
    rng = np.random.default_rng(seed)
    c = rng.integers(0, 5, (h, w)).astype(np.float64)
    c[rng.random((h, w)) < 0.2] = bad
    c[rng.random((h, w)) < 0.2] += 0.25       # fractional: rounded up
    p = R.plan(c)
    want = np.where(np.isfinite(c) & (c > 0), np.ceil(np.minimum(c, 2.0 ** 52)), 0).astype(np.int64)
    assert (p.covered >= want).all()
    assert p.overshoot == int(p.covered.sum() - want.sum())


def test_plan_rejects_non_2d():
    with pytest.raises(ValueError):
        R.plan(np.ones(5, np.int64))


def test_plan_smooth_map_few_tasks():
    h = w = 64
    y, x = np.mgrid[:h, :w]
    c = (2 + 6 * np.exp(-((x - 32) ** 2 + (y - 32) ** 2) / 2000.0)).astype(np.int64)
    p = R.plan(c, task_cost=R.DEFAULT_TASK_COST)     # 24k samples: tasks cost a lot
    check_plan(c, p)
    assert p.n_tasks <= 2
    p0 = R.plan(c, task_cost=0.0)                    # exact at 8x8: 64 leaves
    check_plan(c, p0)
    assert p0.n_tasks <= 40 and p0.overshoot <= 0.1 * c.sum()
    p1 = R.plan(c, task_cost=256.0)
    check_plan(c, p1)
    assert p1.n_tasks <= 10 and p1.overshoot <= 0.25 * c.sum()
    # a map constant on two halves is two or fewer tasks at any task cost
    c2 = np.where(x < 32, 3, 9)
    for tc in (0.0, 4096.0):
        p2 = R.plan(c2, task_cost=tc)
        check_plan(c2, p2)
        assert p2.n_tasks <= 2


def test_plan_merges_equal_neighbours():
    """Stripes constant on 8-pixel columns: exact, one rectangle per distinct
    increment layer instead of one per 8x8 block."""
    c = np.repeat(np.array([1, 1, 2, 2, 2, 5, 5, 5]), 8)[None, :].repeat(40, 0)
    p = R.plan(c, task_cost=0.0)
    check_plan(c, p)
    np.testing.assert_array_equal(p.covered, c)
    assert p.n_tasks <= 4     # 40 leaves at 8x8 before merging


# --------------------------------------------------------------- offsets
def per_pixel_indices(tasks, shape):
    idx = [[[] for _ in range(shape[1])] for _ in range(shape[0])]
    for t in tasks:
        for yy in range(t.y0, t.y1):
            for xx in range(t.x0, t.x1):
                idx[yy][xx].extend(range(t.offset, t.offset + t.samples))
    return idx


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (13, 17), (24, 24)])
def test_assign_offsets_contiguous_after_uniform_pass(shape):
    rng = np.random.default_rng(sum(shape))
    for s in (1, 4):
        c = rng.integers(0, 7, shape)
        p = R.plan(c, min_size=s, task_cost=5.0)
        nxt0 = np.full(shape, 4, np.int64)
        tasks, nxt = R.assign_offsets(p.tasks, nxt0)
        assert (nxt0 == 4).all()                       # pure
        np.testing.assert_array_equal(nxt, 4 + p.covered)
        idx = per_pixel_indices(tasks, shape)
        for yy in range(shape[0]):
            for xx in range(shape[1]):
                assert sorted(idx[yy][xx]) == list(range(4, 4 + p.covered[yy, xx]))
        assert [t.rect for t in tasks] == [t.rect for t in p.tasks]


def test_assign_offsets_never_reuses_index():
    rng = np.random.default_rng(1)
    shape = (9, 11)
    nxt0 = rng.integers(0, 20, shape)
    tasks = [RegionTask(int(a), int(b), int(a) + int(dw), int(b) + int(dh), int(s))
             for a, b, dw, dh, s in zip(rng.integers(0, 8, 30), rng.integers(0, 6, 30),
                                        rng.integers(1, 4, 30), rng.integers(1, 4, 30),
                                        rng.integers(1, 5, 30))]
    out, nxt = R.assign_offsets(tasks, nxt0)
    idx = per_pixel_indices(out, shape)
    for yy in range(shape[0]):
        for xx in range(shape[1]):
            got = idx[yy][xx]
            assert len(got) == len(set(got))
            assert all(i >= nxt0[yy, xx] for i in got)
            assert nxt[yy, xx] == (max(got) + 1 if got else nxt0[yy, xx])
    # uniform rectangle: exact continuation
    out, _ = R.assign_offsets([RegionTask(0, 0, 3, 3, 2)], np.full((5, 5), 6))
    assert out[0].offset == 6


def test_plan_within_keeps_samples_beyond_the_map_under_the_limit():
    """plan_within lowers the task cost until the plan adds at most max_beyond
    of its samples beyond a block map; the plan at the given cost adds more."""
    from core.regions import plan, plan_within
    rng = np.random.default_rng(4)
    # as the loop plans it: one count per 8x8 block, here 1 or 4 at random
    c = np.kron(rng.choice([1, 4], (8, 8)), np.ones((8, 8), np.int64))
    loose = plan(c, min_size=8, task_cost=4096)
    assert loose.overshoot > 0.1 * loose.covered.sum()
    p = plan_within(c, min_size=8, task_cost=4096, max_beyond=0.1)
    assert p.overshoot <= 0.1 * p.covered.sum()
    assert (p.covered >= c).all() and p.n_tasks >= loose.n_tasks
    # a map that a cheap plan already follows closely is planned at the given cost
    even = np.full((32, 32), 3)
    assert plan_within(even, min_size=8, task_cost=4096).n_tasks == plan(even, min_size=8, task_cost=4096).n_tasks

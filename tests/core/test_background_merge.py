"""Merges on a background thread while the next task renders
(``core.pipeline.AdaptiveRun._merge_steps``): the same bits as merging
inline, real overlap with the render, and nothing lost or half-read when the
loop stops during one."""
import threading

import numpy as np
import pytest

from core import pipeline
from core.pipeline import AdaptiveRun, Options
from conftest import FakeExecutor

INLINE = 1 << 40  # no task reaches it: every merge inline


def _truth(h, w):
    rng = np.random.default_rng(3)
    t = np.full((h, w, 3), 0.3) + 0.1 * rng.random((h, w, 3))
    t[h // 3:, w // 2:] = 4.0
    return t


def _features(h, w):
    rng = np.random.default_rng(4)
    return {"albedo": rng.random((h, w, 3)), "normal": rng.random((h, w, 3)) * 2 - 1,
            "depth": 1 + rng.random((h, w, 1))}


def _run(monkeypatch, threshold, method, **kw):
    monkeypatch.setattr(pipeline, "MERGE_WORK_PIXELS", threshold)
    h, w = 20, 28
    run = AdaptiveRun(FakeExecutor(_truth(h, w), _features(h, w)), Options(method=method, **kw))
    fractions = [p.fraction for p in run.steps()]
    return run, fractions, run.reconstruct()


@pytest.mark.parametrize("method,kw", [
    ("uniform", dict(spp=8, subsets=4)),
    ("var", dict(spp=10, initial_spp=2, subsets=2, task_cost=16, min_task_size=2, iterations=3)),
    ("lp", dict(spp=8, initial_spp=4, subsets=4, task_cost=16, min_task_size=2, iterations=2)),
])
def test_background_merges_give_the_bits_of_inline_ones(monkeypatch, method, kw):
    inline, f_inline, r_inline = _run(monkeypatch, INLINE, method, **kw)
    background, f_back, r_back = _run(monkeypatch, 1, method, **kw)
    a, b = inline.buffers, background.buffers
    for x, y in [(a.n, b.n), (a.k, b.k), (a.color.mean, b.color.mean), (a.color.m2, b.color.m2),
                 (a.half.n, b.half.n), (a.half.color, b.half.color), (inline.next_index, background.next_index),
                 (r_inline.image, r_back.image), (r_inline.error, r_back.error)]:
        np.testing.assert_array_equal(x, y)
    for name in a.features:
        np.testing.assert_array_equal(a.features[name].mean, b.features[name].mean)
        np.testing.assert_array_equal(a.features[name].m2, b.features[name].m2)
    assert a.exponent == b.exponent
    assert inline.tasks_rendered == background.tasks_rendered and background.pending_merge is None
    # progress counts a running merge as landed: it never goes back, and ends where inline's does
    assert all(q >= p for p, q in zip(f_back, f_back[1:])) and f_back[-1] == f_inline[-1]


def test_a_merge_runs_while_the_next_task_renders(monkeypatch):
    """Each merge waits until the next render has begun: inline merges would
    wait out the timeout on the loop's own thread."""
    monkeypatch.setattr(pipeline, "MERGE_WORK_PIXELS", 1)
    rendering, waits, threads = [threading.Event()], [], []
    real_merge = pipeline.merge_render

    def merge(buf, task, color, feats):
        threads.append(threading.current_thread() is threading.main_thread())
        event = rendering[-1]
        waits.append(event.wait(10) if task.offset + task.samples < 8 else True)  # the last has no next
        real_merge(buf, task, color, feats)
    monkeypatch.setattr(pipeline, "merge_render", merge)

    class Signalling(FakeExecutor):
        def render(self, task):
            rendering[-1].set()  # the merge before this render may go on
            rendering.append(threading.Event())
            return super().render(task)

    run = AdaptiveRun(Signalling(_truth(12, 16)), Options(method="uniform", spp=8, subsets=4))
    for _ in run.steps():
        pass
    assert waits == [True] * 4 and not any(threads)
    assert np.all(run.buffers.n == 8) and np.all(run.buffers.k == 4)


def test_stopping_the_loop_during_a_merge_loses_nothing(monkeypatch):
    """Closing the loop (Esc, Ctrl-C) while a merge runs returns at once;
    :attr:`pending_merge` is that merge, and :meth:`settle` lands it: every
    rendered sample is in the buffers."""
    monkeypatch.setattr(pipeline, "MERGE_WORK_PIXELS", 1)
    gate = threading.Event()
    real_merge = pipeline.merge_render

    def merge(buf, task, color, feats):
        if task.offset == 2:  # the second subset's merge waits for the test
            assert gate.wait(30)
        real_merge(buf, task, color, feats)
    monkeypatch.setattr(pipeline, "merge_render", merge)
    ex = FakeExecutor(_truth(12, 16))
    run = AdaptiveRun(ex, Options(method="uniform", spp=8, subsets=4))
    steps = run.steps()
    for p in steps:
        if p.work is not None and p.work.mutates and not p.work.done:
            break  # the loop waits for the gated merge
    else:
        pytest.fail("no merge was left to wait for")
    steps.close()
    pending = run.pending_merge
    assert pending is not None and not pending.done
    gate.set()
    run.settle()
    assert run.pending_merge is None and pending.done
    rendered = sum(t.pixels * t.samples for t in ex.tasks)
    assert run.buffers.n.sum() == rendered == run.samples_rendered
    np.testing.assert_array_equal(run.buffers.k, len(ex.tasks))


def test_a_failing_merge_stops_the_loop_with_its_error(monkeypatch):
    monkeypatch.setattr(pipeline, "MERGE_WORK_PIXELS", 1)
    real_merge = pipeline.merge_render

    def merge(buf, task, color, feats):
        if task.offset == 4:
            raise ValueError("merge failed")
        real_merge(buf, task, color, feats)
    monkeypatch.setattr(pipeline, "merge_render", merge)
    run = AdaptiveRun(FakeExecutor(_truth(12, 16)), Options(method="uniform", spp=8, subsets=4))
    with pytest.raises(ValueError, match="merge failed"):
        for _ in run.steps():
            pass
    assert run.pending_merge is None


@pytest.mark.parametrize("threshold", [INLINE, 1])
@pytest.mark.parametrize("with_prior", [False, True])
def test_the_kept_sample_count_is_the_buffers_count_at_every_step(monkeypatch, threshold, with_prior):
    """``samples_rendered`` is kept by the merges instead of summed per task:
    wherever the buffers are whole it equals their count less the reused
    samples, with merges inline or in the background and after a reuse."""
    from core.buffers import Buffers
    from core.pipeline import Prior
    monkeypatch.setattr(pipeline, "MERGE_WORK_PIXELS", threshold)
    h, w = 20, 28
    truth = _truth(h, w)
    prior = None
    if with_prior:
        ones = {k: np.ones(v.shape) for k, v in _features(h, w).items()} | {"alpha": np.ones((h, w, 1))}
        carried = Buffers.from_subsets([truth, truth * 1.01], [3, 3], [ones, ones])
        prior = lambda buffers: Prior(carried, state={}, info={})  # noqa: E731
    run = AdaptiveRun(FakeExecutor(truth, _features(h, w)),
                      Options(method="var", spp=10, initial_spp=2, subsets=2, task_cost=16, min_task_size=2,
                              iterations=3), prior=prior)
    checked = 0
    for _ in run.steps():
        work = run.pending_merge
        if run.buffers is not None and (work is None or work.done):
            assert run.samples_rendered == int(run.buffers.n.sum() - run.reused.sum())
            checked += 1
    run.settle()
    assert checked > 10 and run.samples_rendered == int(run.buffers.n.sum() - run.reused.sum())
    assert run.reused.sum() == (6 * h * w if with_prior else 0)


class Deferring(FakeExecutor):
    """An executor that reads its renders back later (``render_deferred``):
    each result is computed on its first call, and the thread of that call
    recorded."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.reads = []  # (task offset, on the main thread)

    def render_deferred(self, task):
        rendered, lock = [], threading.Lock()
        result = super().render(task)

        def take():
            with lock:
                if not rendered:
                    self.reads.append((task.offset, threading.current_thread() is threading.main_thread()))
                    rendered.append(result)
            return rendered[0]
        return take


@pytest.mark.parametrize("method,kw", [
    ("uniform", dict(spp=8, subsets=4)),
    ("lp", dict(spp=8, initial_spp=4, subsets=4, task_cost=16, min_task_size=2, iterations=2)),
])
def test_deferred_reads_happen_in_the_merges_and_give_the_same_bits(monkeypatch, method, kw):
    """A task large enough to merge in the background is rendered through
    ``render_deferred``, and its result taken on the merge's thread, once;
    the buffers and the image are those of plain ``render`` calls.  Smaller
    tasks (inline merges) keep ``render``."""
    h, w = 20, 28
    plain, _, r_plain = _run(monkeypatch, 1, method, **kw)
    monkeypatch.setattr(pipeline, "MERGE_WORK_PIXELS", 1)
    ex = Deferring(_truth(h, w), _features(h, w))
    run = AdaptiveRun(ex, Options(method=method, **kw))
    for _ in run.steps():
        pass
    r = run.reconstruct()
    assert len(ex.reads) == len(ex.tasks) and not any(main for _, main in ex.reads)
    for x, y in [(plain.buffers.n, run.buffers.n), (plain.buffers.color.mean, run.buffers.color.mean),
                 (plain.buffers.color.m2, run.buffers.color.m2), (r_plain.image, r.image), (r_plain.error, r.error)]:
        np.testing.assert_array_equal(x, y)
    monkeypatch.setattr(pipeline, "MERGE_WORK_PIXELS", INLINE)
    ex = Deferring(_truth(h, w), _features(h, w))
    for _ in AdaptiveRun(ex, Options(method=method, **kw)).steps():
        pass
    assert ex.reads == [] and ex.tasks

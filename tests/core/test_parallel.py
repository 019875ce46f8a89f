"""core.parallel: order, bounded submission, errors, thread-count settings."""
import threading
import time

import numpy as np
import pytest

from cycles_adaptive.core import parallel


@pytest.fixture(autouse=True)
def _reset(monkeypatch):
    monkeypatch.delenv(parallel.ENV, raising=False)
    yield
    parallel.set_threads(None)


def test_bands_cover_rows_once_and_ignore_thread_count():
    for h, r in [(0, 8), (1, 8), (64, 64), (65, 64), (1000, 7)]:
        b = parallel.bands(h, r)
        rows = [y for y0, y1 in b for y in range(y0, y1)]
        assert rows == list(range(h))
        assert all(0 < y1 - y0 <= r for y0, y1 in b)
    parallel.set_threads(1)
    one = parallel.bands(300, 64)
    parallel.set_threads(7)
    assert parallel.bands(300, 64) == one


def test_map_ordered_keeps_order_and_uses_threads():
    parallel.set_threads(4)
    seen = set()

    def fn(i):
        seen.add(threading.current_thread().name)
        time.sleep(0.002 * (10 - i % 10))  # later items finish first
        return i * i

    assert parallel.map_ordered(fn, range(40)) == [i * i for i in range(40)]
    assert any(name.startswith("cycles-adaptive") for name in seen)


def test_map_ordered_bounds_what_is_submitted_ahead():
    parallel.set_threads(3)
    lock = threading.Lock()
    state = {"running": 0, "peak": 0, "consumed": 0}

    def fn(i):
        with lock:
            state["running"] += 1
            state["peak"] = max(state["peak"], state["running"])
        time.sleep(0.001)
        with lock:
            state["running"] -= 1
        return i

    assert parallel.map_ordered(fn, range(50), ahead=2) == list(range(50))
    assert state["peak"] <= 2


def test_single_thread_and_nested_calls_run_inline():
    parallel.set_threads(1)
    names = parallel.map_ordered(lambda i: threading.current_thread().name, range(5))
    assert set(names) == {threading.current_thread().name}
    parallel.set_threads(3)
    inner = parallel.map_ordered(lambda i: parallel.map_ordered(lambda j: (i, j, parallel.in_pool()), range(3)),
                                 range(4))
    assert [[(i, j) for i, j, _ in row] for row in inner] == [[(i, j) for j in range(3)] for i in range(4)]
    assert all(flag for row in inner for _, _, flag in row)


def test_first_error_propagates_and_nothing_is_left_running():
    parallel.set_threads(4)
    done = []

    def fn(i):
        if i == 5:
            raise RuntimeError("piece 5")
        time.sleep(0.005)
        done.append(i)
        return i

    with pytest.raises(RuntimeError, match="piece 5"):
        parallel.map_ordered(fn, range(30))
    settled = len(done)
    time.sleep(0.05)
    assert len(done) == settled  # no piece still running after the raise


def test_thread_count_settings(monkeypatch):
    parallel.set_threads(3)
    assert parallel.threads() == 3
    monkeypatch.setenv(parallel.ENV, "5")
    assert parallel.threads() == 5
    monkeypatch.setenv(parallel.ENV, "zero")
    assert parallel.threads() == 3
    monkeypatch.setenv(parallel.ENV, "-2")
    assert parallel.threads() == 3
    with pytest.raises(ValueError):
        parallel.set_threads(0)
    parallel.set_threads(None)
    monkeypatch.delenv(parallel.ENV)
    assert parallel.threads() >= 1


def test_default_thread_count_is_the_cpus_up_to_the_ceiling(monkeypatch):
    """By default the CPU count, at most DEFAULT_MAX_THREADS (more threads
    were slower on a 16-core machine); asking for more still gets more."""
    monkeypatch.delenv(parallel.ENV, raising=False)
    parallel.set_threads(None)
    top = parallel.DEFAULT_MAX_THREADS
    for cpus, want in ((None, 1), (1, 1), (3, 3), (top, top), (2 * top, top), (64, top)):
        monkeypatch.setattr(parallel.os, "cpu_count", lambda c=cpus: c)
        assert parallel.threads() == want
    monkeypatch.setenv(parallel.ENV, str(2 * top))
    assert parallel.threads() == 2 * top
    monkeypatch.delenv(parallel.ENV)
    parallel.set_threads(3 * top)
    assert parallel.threads() == 3 * top
    parallel.set_threads(None)


def test_band_reduction_is_identical_for_any_thread_count():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((517, 33)) * 1e8
    sums = []
    for n in (1, 2, 5):
        parallel.set_threads(n)
        parts = parallel.run_bands(lambda b: x[b[0]:b[1]].sum(axis=0), x.shape[0], rows=16)
        total = np.zeros(33)
        for p in parts:
            total += p
        sums.append(total)
    assert all(np.array_equal(sums[0], s) for s in sums[1:])



def _blas_threads():
    from threadpoolctl import threadpool_info
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_pieces_run_with_one_blas_thread_and_the_count_comes_back():
    pytest.importorskip("threadpoolctl")
    before = _blas_threads()
    if not before:
        pytest.skip("no BLAS library that threadpoolctl knows is loaded")
    parallel.set_threads(2)
    seen = parallel.map_ordered(lambda _: (_blas_threads(), parallel.lapack_lock()), range(6))
    assert all(t == [1] * len(before) for t, _ in seen)
    # one-threaded LAPACK calls need no lock; outside the pieces they take it again
    assert all(lock is not parallel.LAPACK_LOCK for _, lock in seen)
    assert _blas_threads() == before
    assert parallel.lapack_lock() is parallel.LAPACK_LOCK


def test_one_blas_thread_nests_and_restores_only_at_the_outermost_exit():
    pytest.importorskip("threadpoolctl")
    before = _blas_threads()
    if not before:
        pytest.skip("no BLAS library that threadpoolctl knows is loaded")
    with parallel.one_blas_thread():
        with parallel.one_blas_thread():
            assert _blas_threads() == [1] * len(before)
        assert _blas_threads() == [1] * len(before)       # the outer scope still holds
        inner = parallel.map_ordered(lambda _: _blas_threads(), range(3))
        assert inner == [[1] * len(before)] * 3
    assert _blas_threads() == before
    with pytest.raises(RuntimeError):                      # an error restores it too
        with parallel.one_blas_thread():
            raise RuntimeError("boom")
    assert _blas_threads() == before


def test_without_threadpoolctl_the_work_runs_unchanged_under_the_lock(monkeypatch):
    monkeypatch.setitem(parallel._BLAS, "looked", True)
    monkeypatch.setitem(parallel._BLAS, "controller", None)
    parallel.set_threads(2)
    a = np.arange(400.0).reshape(4, 10, 10) + 50 * np.eye(10)
    got = parallel.map_ordered(lambda i: (parallel.lapack_lock(), np.linalg.inv(a[i])), range(4))
    assert all(lock is parallel.LAPACK_LOCK for lock, _ in got)
    for i, (_, inv) in enumerate(got):
        np.testing.assert_allclose(inv @ a[i], np.eye(10), atol=1e-9)

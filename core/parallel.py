"""Controller threads: independent pieces of numpy work on one shared pool.

The controller's own work between renders (merging tiles, sample maps,
reconstructions, the consistency guard) is numpy on arrays of megapixels,
and numpy releases the GIL inside its loops, so threads over disjoint row
bands use the controller's cores.  Two rules keep results identical whatever
the thread count:

* work is cut by :func:`bands` into pieces that depend on the data's shape
  only, never on :func:`threads`;
* results come back in piece order (:func:`map_ordered`), and any reduction
  over pieces is done in that order (by the caller, or by
  :func:`ordered_reduce` as the pieces finish).

So ``threads() == 1`` and ``threads() == 16`` give bit-identical output (the
tests compare them), and a checkpoint resumed on another machine continues
exactly.  The thread count is ``$CYCLES_ADAPTIVE_THREADS`` when set (a
positive integer), else :func:`set_threads`'s value, else the machine's CPU
count up to :data:`DEFAULT_MAX_THREADS`; below ``min_items`` pieces or
``min_work`` elements the work runs inline, since small arrays gain nothing
from threads.
"""
from __future__ import annotations

import os
import threading
from collections import deque
from contextlib import contextmanager, nullcontext
from concurrent.futures import ThreadPoolExecutor

ENV = "CYCLES_ADAPTIVE_THREADS"

#: the default thread count's ceiling: on a 16-core machine the controller's
#: work at 4K took longer on 16 threads than on 8 (var's adapt 16.5 s vs
#: 9.9 s, its merges 7.9 s vs 3.7 s; lp's adapt at 1080p 26.8 s on 16 vs
#: 17.6 s on 4), as more threads contend for the GIL between numpy calls
#: (docs/notes/farm.md, part 10); more only when asked for
DEFAULT_MAX_THREADS = 8

_LOCK = threading.Lock()
_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_SET: int | None = None
_LOCAL = threading.local()  # marks the pool's own threads (no nested pools)


def threads() -> int:
    """Threads the controller uses: ``$CYCLES_ADAPTIVE_THREADS``, else
    :func:`set_threads`'s value, else ``os.cpu_count()`` up to
    :data:`DEFAULT_MAX_THREADS`; at least 1.  An unparsable or non-positive
    environment value is ignored."""
    env = os.environ.get(ENV, "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            n = 0
        if n > 0:
            return n
    if _SET is not None:
        return _SET
    return max(1, min(os.cpu_count() or 1, DEFAULT_MAX_THREADS))


def set_threads(n: int | None) -> None:
    """Set the thread count (None: back to the CPU count).  ``n < 1`` is an
    error: a ValueError, not a silent single thread."""
    global _SET
    if n is not None:
        n = int(n)
        if n < 1:
            raise ValueError(f"threads must be at least 1, got {n}")
    _SET = n


def bands(height: int, rows: int = 64) -> list:
    """``[(y0, y1), ...]``: ``height`` rows cut into bands of ``rows`` rows
    (the last one shorter); depends only on its arguments, so a reduction over
    bands in this order is the same for any thread count."""
    height, rows = int(height), max(1, int(rows))
    return [(y0, min(y0 + rows, height)) for y0 in range(0, max(height, 0), rows)]


def _pool(n: int) -> ThreadPoolExecutor:
    global _POOL, _POOL_SIZE
    with _LOCK:
        if _POOL is None or _POOL_SIZE != n:
            if _POOL is not None:
                _POOL.shutdown(wait=False)
            _POOL = ThreadPoolExecutor(n, thread_name_prefix="cycles-adaptive",
                                       initializer=_mark_pool_thread)
            _POOL_SIZE = n
        return _POOL


def _mark_pool_thread() -> None:
    _LOCAL.in_pool = True


def in_pool() -> bool:
    """True on one of the pool's threads (nested calls then run inline, so a
    piece that itself maps pieces cannot deadlock the pool)."""
    return bool(getattr(_LOCAL, "in_pool", False))


def map_ordered(fn, items, min_items: int = 2, ahead: int | None = None):
    """``[fn(item) for item in items]``, computed on the pool, in order.

    Inline (no pool) with one thread, fewer than ``min_items`` items, or on a
    pool thread.  At most ``ahead`` items (default ``2 * threads()``) are
    in flight (submitted and not yet consumed), so a long item list does not
    queue all its pieces at once; every result is kept for the returned list
    (pieces that return large arrays should reduce them instead:
    :func:`ordered_reduce`).  BLAS runs on one thread meanwhile
    (:func:`one_blas_thread`).  The first exception raised by ``fn`` propagates after the pieces
    already submitted have finished (none is left running)."""
    items = list(items)
    n = threads()
    if in_pool():
        return [fn(item) for item in items]
    with one_blas_thread():
        if n <= 1 or len(items) < max(2, int(min_items)):
            return [fn(item) for item in items]
        return _map_on_pool(fn, items, n, ahead)


def _map_on_pool(fn, items, n, ahead):
    pool = _pool(n)
    ahead = max(1, int(ahead) if ahead else 2 * n)
    out = []
    pending = deque()
    it = iter(items)
    try:
        for item in it:
            pending.append(pool.submit(fn, item))
            if len(pending) >= ahead:
                break
        while pending:
            out.append(pending.popleft().result())
            nxt = next(it, _END)
            if nxt is not _END:
                pending.append(pool.submit(fn, nxt))
    finally:
        for fut in pending:  # an exception: wait for what was submitted
            fut.cancel()
        for fut in pending:
            if not fut.cancelled():
                try:
                    fut.result()
                except Exception:
                    pass
    return out


_END = object()


def run_bands(fn, height: int, rows: int = 64, min_work: int = 0, work_per_row: int = 1) -> list:
    """``map_ordered(fn, bands(height, rows))``: ``fn((y0, y1))`` per band, in
    band order; inline when ``height * work_per_row < min_work``."""
    pieces = bands(height, rows)
    if height * max(1, int(work_per_row)) < int(min_work):
        return [fn(b) for b in pieces]
    return map_ordered(fn, pieces)


#: np.linalg.inv (LAPACK getrf/getri) runs one call at a time while BLAS has
#: threads of its own: OpenBLAS's LAPACK called from several threads at once
#: then contends for its buffers (a batched 10x10 inverse took 2x, 5x, 30x
#: longer with 2, 3, 5 threads; matmul and eigh did not).  core/lp.py and
#: core/rhf.py take it through :func:`lapack_lock`.
LAPACK_LOCK = threading.Lock()

_BLAS_LOCK = threading.Lock()
_BLAS = {"depth": 0, "limiter": None, "single": False, "controller": None, "looked": False}


def _blas_controller():
    """threadpoolctl's view of the BLAS libraries loaded in this process, made
    once (it walks the loaded libraries); None without threadpoolctl."""
    if not _BLAS["looked"]:
        _BLAS["looked"] = True
        try:
            from threadpoolctl import ThreadpoolController
            _BLAS["controller"] = ThreadpoolController()
        except Exception:                      # not installed, or an odd platform
            _BLAS["controller"] = None
    return _BLAS["controller"]


@contextmanager
def one_blas_thread():
    """Run the enclosed work with BLAS / LAPACK on one thread of their own.

    Why: our pieces are small (a 10x10 inverse per window, products of
    (n, 10) blocks) and already run one per controller thread; OpenBLAS
    threading each small LU on top of that made numpy's batched 10x10
    inverse 5x slower (2.61 ms vs 0.48 ms for 185 of them) and RHF's
    regression ~25 % slower.  The environment variable
    ``OPENBLAS_NUM_THREADS`` cannot do this inside Blender, where numpy is
    loaded before any add-on, so threadpoolctl sets the loaded library's
    count and restores it on exit.  Re-entrant and shared by threads: the
    first to enter sets the limit, the last to leave restores it.  Without
    threadpoolctl (or without a BLAS it knows) nothing changes: same results,
    only slower.  Results agree to rounding either way (RHF's image within
    3e-12 relative: a threaded LU blocks its updates differently); for one
    setting they do not depend on :func:`threads`."""
    with _BLAS_LOCK:
        if _BLAS["depth"] == 0:
            ctl = _blas_controller()
            limiter = single = None
            if ctl is not None:
                try:
                    blas = ctl.select(user_api="blas")
                    if blas.lib_controllers:
                        limiter = blas.limit(limits=1)
                        single = all(c.num_threads == 1 for c in blas.lib_controllers)
                except Exception:
                    limiter = None
            _BLAS["limiter"], _BLAS["single"] = limiter, bool(limiter is not None and single)
        _BLAS["depth"] += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS["depth"] -= 1
            if _BLAS["depth"] == 0:
                limiter, _BLAS["limiter"], _BLAS["single"] = _BLAS["limiter"], None, False
                if limiter is not None:
                    limiter.restore_original_limits()


def lapack_lock():
    """The context a batched LAPACK call (np.linalg.inv) runs in: nothing
    while :func:`one_blas_thread` holds BLAS at one thread (single-threaded
    LAPACK calls from several threads do not contend: two threads' 10x10
    inverses took 0.18 ms each unlocked, 0.27 ms locked), else
    :data:`LAPACK_LOCK`."""
    return nullcontext() if _BLAS["single"] else LAPACK_LOCK


class _Failure:
    """A piece's exception, kept until its turn (:func:`ordered_reduce`)."""

    def __init__(self, exc: BaseException):
        self.exc = exc


def ordered_reduce(compute, reduce, items, inline: bool = False) -> list:
    """``[reduce(compute(item)) for item in items]`` with the ``compute`` s on
    :mod:`core.parallel`'s pool and the ``reduce`` s one at a time in item
    order, so a reduction into shared sums sees the serial order and gives
    the same bits for any thread count.  ``inline``: all on the calling thread.

    A piece whose ``compute`` is done leaves its result and returns; the
    thread that finds the next result in order ready reduces it and every
    consecutive ready one after it (no thread waits for another's turn), so
    only the results in flight (``map_ordered`` 's bound) are held.  The
    first exception, in item order, is raised once all pieces are done; the
    pieces after it are neither computed nor reduced."""
    jobs = list(enumerate(items))
    results = [None] * len(jobs)
    ready = {}
    lock = threading.Lock()
    state = {"next": 0, "busy": False, "error": None}
    skipped = object()

    def piece(job):
        i, item = job
        out = skipped
        if state["error"] is None:
            try:
                out = compute(item)
            except BaseException as exc:              # raised in order, below
                out = _Failure(exc)
        with lock:
            ready[i] = out
            if state["busy"]:
                return                                # the reducing thread takes it
            state["busy"] = True
        while True:
            with lock:
                j = state["next"]
                if j not in ready:
                    state["busy"] = False
                    return
                out = ready.pop(j)
            try:
                if isinstance(out, _Failure):
                    raise out.exc
                if state["error"] is None and out is not skipped:
                    results[j] = reduce(out)
            except BaseException as exc:
                if state["error"] is None:
                    state["error"] = exc
            with lock:
                state["next"] = j + 1

    map_ordered(piece, jobs, min_items=len(jobs) + 1 if inline else 2)
    if state["error"] is not None:
        raise state["error"]
    return results

"""Scale of the Dask farm (operators/farm.py): measured costs and the projected
speed-up of one frame over W workers (docs/notes/farm.md).

    .venv/bin/python tools/farm_scale.py overhead        # scheduler overhead per region task
    .venv/bin/python tools/farm_scale.py merge           # controller merge rate at 4K
    .venv/bin/python tools/farm_scale.py cycles          # Cycles task cost local vs on a worker
    .venv/bin/python tools/farm_scale.py plan --method var --width 3840 --height 2160
    .venv/bin/python tools/farm_scale.py kernels         # var's adapt kernels at 4K, 1 vs 2 threads
    .venv/bin/python tools/farm_scale.py project         # from the JSON files the others wrote
    .venv/bin/python tools/farm_scale.py project --controller-threads 1 2 8 16

Each command writes its figures to ``bench_out/farm/<command>*.json`` and prints
them.  ``overhead`` runs tasks of a known cost (a sleep: the render happens
elsewhere) that return buffers of a region's size through the same calls as
``DaskExecutor.render_many`` (``client.map``, results in task order);
``plan`` runs ``AdaptiveRun`` with a synthetic executor (no rendering) and
records every iteration's tasks and the controller's own time (adapt: sample
map and planner; reconstruct when the method's sampler uses it).

``merge`` and ``plan`` run on the controller's thread count
(``$CYCLES_ADAPTIVE_THREADS``, ``core.parallel``), record it and write
``<name>_t<threads>.json``.  ``plan --bands N`` hands the method's fit
(lp) to a stand-in of the farm's ``run_jobs`` in N bands, computed and
timed here one after the other (``<name>_b<N>_t<threads>.json``);
``project`` then takes for W workers the slowest band of the plan whose
bands have a 4K frame's W bands' height, the transfers at ``--network``
B/s, and the controller's remaining adapt.  ``project --controller-threads C ...`` projects
the serial controller part on a C-core controller from the 1- and 2-thread
files, or from ``--fractions`` (a projection, not a measurement; see
:func:`amdahl`).  Without ``cycles_<scene>.json`` / ``overhead_w2.json`` pass
``--cycles-cost`` and ``--chunk-overhead``.
"""
import argparse
import json
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

load_package()
import numpy as np  # noqa: E402

from cycles_adaptive.core import buffers as core_buffers, methods, parallel  # noqa: E402
from cycles_adaptive.core.buffers import Buffers  # noqa: E402
from cycles_adaptive.core.pipeline import AdaptiveRun, Options, merge_render  # noqa: E402
from cycles_adaptive.core.regions import RegionTask  # noqa: E402

OUT = os.path.join(ROOT, "bench_out", "farm")  # ignored by git, left out of the extension
LP_CHANNELS = {"albedo": 3, "normal": 3, "depth": 1, "alpha": 1}  # what an lp task returns besides RGBA


def _save(name, data):
    os.makedirs(OUT, exist_ok=True)
    with open(os.path.join(OUT, name + ".json"), "w") as f:
        json.dump(data, f, indent=1)
    print(json.dumps(data, indent=1))


# ----------------------------------------------------------------- overhead
def fake_render(tasks, cost):
    """Region tasks of known cost: each sleeps ``cost`` s and returns float32
    RGBA and lp's feature passes of its size (what render_regions returns)."""
    out = []
    for task in tasks:
        time.sleep(cost)
        h, w = task[3] - task[1], task[2] - task[0]
        rng = np.random.default_rng(task[6])
        out.append((rng.random((h, w, 4), dtype=np.float32),
                    {k: rng.random((h, w, c), dtype=np.float32) for k, c in LP_CHANNELS.items() if k != "alpha"}))
    return out


def overhead(args):
    """Per region task: wall time beyond n x cost / workers, for one Dask task
    per region task and for DaskExecutor's chunks (farm.chunk_tasks)."""
    from cycles_adaptive.operators import farm
    rows = []
    with farm.Farm(farm.FarmSettings(workers=args.workers), log=lambda *a: None) as f:
        client = f.client
        client.gather(client.map(fake_render, [[(0, 0, 8, 8, 1, 1, i)] for i in range(8)], [0.0] * 8,
                                 pure=False))  # warm
        for side in (16, 64):
            for cost in (0.0, 0.02):
                for chunked in (False, True):
                    n = args.tasks if cost == 0 else max(40, args.tasks // 10)
                    tasks = [RegionTask(0, 0, side, side, 4, 1, i) for i in range(n)]
                    chunks = (farm.chunk_tasks(tasks, farm.CHUNKS_PER_WORKER * args.workers) if chunked
                              else [[t] for t in tasks])
                    t0 = time.perf_counter()
                    futures = client.map(fake_render, [[farm.task_tuple(t) for t in c] for c in chunks],
                                         [cost] * len(chunks),
                                         key=[f"t-{side}-{cost}-{chunked}-{i}-{t0}" for i in range(len(chunks))])
                    for fut in futures:  # as DaskExecutor.render_many: in task order
                        for color, feats in fut.result():
                            farm.restore(color)
                        fut.release()
                    wall = time.perf_counter() - t0
                    ideal = n * cost / args.workers
                    rows.append({"side": side, "cost_s": cost, "tasks": n, "chunks": len(chunks),
                                 "workers": args.workers, "wall_s": wall,
                                 "overhead_ms_per_task": 1000 * (wall - ideal) / n, "tasks_per_s": n / wall})
    _save(f"overhead_w{args.workers}", rows)


# -------------------------------------------------------------------- merge
def merge(args):
    """``merge_render`` into 4K Buffers (lp's passes): the first whole-frame
    merge (page faults), a warm one, then regions of 16^2 .. 1024^2; regions
    from ``core.buffers.INLINE_PIXELS`` pixels on run over row bands on the
    controller's threads."""
    w, h = args.width, args.height
    buf = Buffers.empty(h, w, tuple(LP_CHANNELS))
    rng = np.random.default_rng(0)
    rows = []
    full = RegionTask(0, 0, w, h, 1)
    color = rng.random((h, w, 4)).astype(np.float32).astype(np.float64)
    feats = {k: rng.random((h, w, c)) for k, c in LP_CHANNELS.items() if k != "alpha"}
    for side in ("full", "full_warm"):
        t0 = time.perf_counter()
        merge_render(buf, full, color, feats)
        dt = time.perf_counter() - t0
        rows.append({"side": side, "pixels": w * h, "ms_per_task": 1000 * dt, "mpix_per_s": w * h / 1e6 / dt})
    for side in (s for s in (16, 32, 64, 128, 256, 512, 1024) if s < min(w, h)):
        c = color[:side, :side].copy()
        fs = {k: v[:side, :side].copy() for k, v in feats.items()}
        n = max(5, int(2e7 // (side * side * 50)))
        t0 = time.perf_counter()
        for i in range(n):
            x0 = (i * side) % (w - side)
            y0 = ((i * side) // (w - side) * side) % (h - side)
            merge_render(buf, RegionTask(x0, y0, x0 + side, y0 + side, 2), c, fs)
        dt = (time.perf_counter() - t0) / n
        rows.append({"side": side, "pixels": side * side, "ms_per_task": 1000 * dt,
                     "mpix_per_s": side * side / 1e6 / dt})
    _save(f"merge_t{parallel.threads()}", {"threads": parallel.threads(), "width": w, "height": h,
                                           "inline_pixels": getattr(core_buffers, "INLINE_PIXELS", None), "rows": rows})


# ------------------------------------------------------------------- cycles
def cycles(args):
    import bpy
    from cycles_adaptive.addon.executor import CyclesExecutor
    from cycles_adaptive.bench import references as refs
    from cycles_adaptive.operators import farm
    refs.open_scene(refs.scene_path(args.scene), force=True)
    scene, vl = bpy.context.scene, bpy.context.view_layer
    feats = tuple(methods.get("lp").PASSES)
    sizes = [(16, 4), (32, 4), (64, 4), (128, 4)]
    rows = []
    with farm.Farm(farm.FarmSettings(workers=1), log=lambda *a: None) as f:
        with f.executor_factory()(scene, vl, feats, seed=0) as dex:
            h, w = dex.size
            dex.render(RegionTask(0, 0, w, h, 1, frame=1))
            remote = {}
            for side, spp in sizes:
                ts = []
                for rep in range(5):
                    t = time.perf_counter()
                    dex.render(RegionTask(0, 0, side, side, spp, frame=1, offset=10 + rep * spp))
                    ts.append(time.perf_counter() - t)
                remote[side] = min(ts)
        with CyclesExecutor(scene, vl, feats, seed=0) as ex:
            ex.render(RegionTask(0, 0, w, h, 1, frame=1))
            for side, spp in sizes:
                ts = []
                for rep in range(5):
                    t = time.perf_counter()
                    ex.render(RegionTask(0, 0, side, side, spp, frame=1, offset=10 + rep * spp))
                    ts.append(time.perf_counter() - t)
                rows.append({"scene": args.scene, "side": side, "spp": spp, "pixel_samples": side * side * spp,
                             "local_ms": 1000 * min(ts), "worker_ms": 1000 * remote[side],
                             "farm_overhead_ms": 1000 * (remote[side] - min(ts))})
    ps = np.array([r["pixel_samples"] for r in rows], float)
    sec = np.array([r["local_ms"] for r in rows]) / 1000
    (a, b), *_ = np.linalg.lstsq(np.stack([np.ones_like(ps), ps], 1), sec, rcond=None)
    _save(f"cycles_{args.scene}", {"rows": rows, "fixed_s": a, "per_pixel_sample_s": b})


# --------------------------------------------------------------------- plan
class SyntheticExecutor:
    """Renders nothing: a structured image (smooth shading, edges, a few
    bright spots) plus per-sample noise, fast enough for 4K plans."""

    def __init__(self, w, h, features):
        yy, xx = np.mgrid[0:h, 0:w] / max(w, h)
        base = 0.2 + 0.6 * (np.sin(12 * xx) * np.cos(9 * yy)) ** 2 + (xx > 0.5) * 0.3
        base[(np.hypot(xx - 0.3, yy - 0.2) < 0.02)] = 20.0
        self.truth = np.repeat(base[:, :, None], 3, 2)
        self.size = (h, w)
        self.features = features
        self.calls = []

    def render(self, task):
        self.calls.append(task)
        t = self.truth[task.y0:task.y1, task.x0:task.x1]
        rng = np.random.default_rng([task.offset, task.x0, task.y0])
        noise = rng.standard_normal(t.shape[:2])[..., None] / np.sqrt(task.samples)
        rgba = np.concatenate([t * np.abs(1 + 0.8 * noise), np.ones(t.shape[:2] + (1,))], 2)
        shape = t.shape[:2]
        feats = {"albedo": np.full(shape + (3,), 0.5), "normal": np.zeros(shape + (3,)) + [0, 0, 1],
                 "depth": np.ones(shape + (1,))}
        return rgba, {k: v for k, v in feats.items() if k in self.features}


class BandedSyntheticExecutor(SyntheticExecutor):
    """:class:`SyntheticExecutor` with the farm's ``run_jobs`` / ``map_parts``
    (``DaskExecutor``: one band per worker), computing the jobs here one
    after the other and timing each: what each worker would compute, and the
    bytes Dask would move (``distributed.protocol.serialize_bytes`` of the
    inputs and of the results, timed too: the controller serialises the one
    and deserialises the other; counted apart from the controller's adapt)."""

    def __init__(self, w, h, features, parts):
        super().__init__(w, h, features)
        self.map_parts = parts
        self.band_calls = []

    def run_jobs(self, module, name, jobs, local_fallback=False):
        import importlib
        from distributed.protocol import serialize_bytes
        fn = getattr(importlib.import_module(module), name)
        outs, secs, sent, back = [], [], [], []
        t_ser = 0.0
        for job in jobs:
            t = time.perf_counter()
            sent.append(len(serialize_bytes(job)))
            t_ser += time.perf_counter() - t
            t = time.perf_counter()
            outs.append(fn(job))
            secs.append(time.perf_counter() - t)
            t = time.perf_counter()
            back.append(len(serialize_bytes(outs[-1])))  # the controller's deserialisation: about as long
            t_ser += time.perf_counter() - t
        self.band_calls.append({"band_s": secs, "sent_bytes": sent, "back_bytes": back, "serialize_s": t_ser,
                                "rows": [int(j["color"].shape[0]) for j in jobs]})
        return outs


def _band_summary(calls):
    """Sum of the band-call records of one stage: every band time (what the
    workers compute), the controller's serialisation, the bytes each way."""
    return {"calls": len(calls), "band_s": [c["band_s"] for c in calls],
            "rows": [c["rows"] for c in calls],
            "serialize_s": sum(c["serialize_s"] for c in calls),
            "sent_bytes": sum(sum(c["sent_bytes"]) for c in calls),
            "back_bytes": sum(sum(c["back_bytes"]) for c in calls),
            "bands_total_s": sum(sum(c["band_s"]) for c in calls)}


def plan(args):
    m = methods.get(args.method)
    opts = Options(method=args.method, spp=args.spp, seed=0)
    if args.bands > 1:
        if not hasattr(m, "fit_band"):
            raise SystemExit(f"--bands: method {args.method} has no fit_band")
        ex = BandedSyntheticExecutor(args.width, args.height, tuple(m.PASSES), args.bands)
    else:
        ex = SyntheticExecutor(args.width, args.height, tuple(m.PASSES))
    banded = [0]  # band calls already attributed to a stage
    run = AdaptiveRun(ex, opts)
    merged = [0.0]
    merge_one = run._merge

    def timed_merge(*a):  # the controller's merges, timed apart from adapt
        t = time.perf_counter()
        merge_one(*a)
        merged[0] += time.perf_counter() - t
    run._merge = timed_merge
    start = time.perf_counter()
    seen, adapt0, stages = 0, 0.0, []
    current = {"iteration": 0, "adapt_s": 0.0}  # the initial pass: no controller time before it

    def close():
        nonlocal seen
        current["tasks"] = [[t.pixels, t.samples] for t in ex.calls[seen:]]
        seen = len(ex.calls)
        if current["tasks"]:
            stages.append(dict(current))
    for p in run.steps():
        if p.stage == "plan" and p.tasks_total:  # iteration p.iteration + 1 is planned: a barrier
            close()
            current = {"iteration": p.iteration + 1, "adapt_s": run.timing.adapt - adapt0}
            if args.bands > 1:  # the bands this adapt handed the workers
                current["bands"] = _band_summary(ex.band_calls[banded[0]:])
                banded[0] = len(ex.band_calls)
            adapt0 = run.timing.adapt
    close()
    stage_tasks = stages
    t0 = time.perf_counter()
    run.reconstruct()
    rec = time.perf_counter() - t0
    wall = time.perf_counter() - start
    extra = {}
    if args.bands > 1:
        extra = {"bands": args.bands, "reconstruct_bands": _band_summary(ex.band_calls[banded[0]:])}
    suffix = f"_b{args.bands}" if args.bands > 1 else ""
    _save(f"plan_{args.method}_{args.width}x{args.height}{suffix}_t{parallel.threads()}",
          {"method": args.method, "width": args.width, "height": args.height, "spp": args.spp, **extra,
           "threads": parallel.threads(), "stages": stage_tasks, "reconstruct_s": rec,
           "adapt_s": sum(st["adapt_s"] for st in stage_tasks), "merge_s": merged[0], "wall_s": wall,
           # the loop's own time besides adapt, merges, the final reconstruction and the executor's renders
           "loop_s": wall - rec - run.timing.adapt - merged[0] - run.timing.render,
           "uses_result": bool(m.SAMPLER_USES_RESULT)})


# ------------------------------------------------------------------ kernels
def kernels(args):
    """var's adapt kernels on the Buffers of a synthetic initial pass, at 1
    and 2 controller threads alternating, best of ``--repeats``: which of
    them gain from a second thread (docs/notes/farm.md, part 10)."""
    from cycles_adaptive.core import maps, method as core_method, var
    h, w = args.height, args.width
    ex = SyntheticExecutor(w, h, tuple(methods.get("var").PASSES))
    run = AdaptiveRun(ex, Options(method="var", spp=16, seed=0))
    for p in run.steps():  # the initial pass only: stop when the first iteration is planned
        if p.stage == "plan" and p.tasks_total:
            break
    buf, params = run.buffers, var.Params()
    counts = core_method.allocate(var.pixel_priority(buf, params), 4 * h * w)
    dof = buf.k - 1.0
    weights = np.random.default_rng(0).random((h, w))
    kern = {
        "pixel_priority": lambda: var.pixel_priority(buf, params),
        "pixel_variance": lambda: var.pixel_variance(buf),
        "confidence_pool": lambda: maps.confidence_pool(counts, dof),
        "allocate": lambda: core_method.allocate(weights, 4 * h * w),
        "pool_to_blocks": lambda: maps.pool_to_blocks(counts, 16),
    }
    best = {k: {1: float("inf"), 2: float("inf")} for k in kern}
    try:
        for _ in range(args.repeats):
            for t in (1, 2):
                parallel.set_threads(t)
                for k, fn in kern.items():
                    t0 = time.perf_counter()
                    fn()
                    best[k][t] = min(best[k][t], time.perf_counter() - t0)
    finally:
        parallel.set_threads(None)
    _save("kernels", {"width": w, "height": h, "repeats": args.repeats,
                      "kernels": {k: {"t1_s": v[1], "t2_s": v[2], "gain": v[1] / v[2]} for k, v in best.items()}})


# ------------------------------------------------------------------ project
def makespan(costs, workers):
    """Greedy list schedule in submission order (Dask hands a free worker the
    next task): the time the last task ends."""
    import heapq
    free = [0.0] * workers
    for c in costs:
        t = heapq.heappop(free)
        heapq.heappush(free, t + c)
    return max(free)


def stage_seconds(tasks, workers, a, b, o_chunk, merge_cost, scale):
    """One stage (the initial pass or an iteration) of a frame on ``workers``:
    tasks cut into tiles and chunks as ``DaskExecutor.render_many`` does
    (4 chunks per worker), rendered at ``a + b * pixel-samples`` per tile,
    ``o_chunk`` scheduler overhead per chunk; the controller merges each task
    (``merge_cost(pixels)`` seconds) as it completes, so the stage lasts
    the longer of rendering and merging plus the last task's merge.
    ``scale``: pixel factor from the planned frame to the projected one."""
    from cycles_adaptive.operators import farm
    from cycles_adaptive.core.regions import DEFAULT_TASK_COST
    n_chunks = farm.CHUNKS_PER_WORKER * workers
    scaled = [(px * scale, s) for px, s in tasks]  # the same tasks, larger: task size follows the frame
    total = sum(px * s + DEFAULT_TASK_COST for px, s in scaled)
    target = total / n_chunks
    tiles = []
    for px, s in scaled:
        n = max(1, int(np.ceil((px * s + DEFAULT_TASK_COST) / target)))
        n = min(n, max(1, int(px // farm.MIN_TILE ** 2)))
        tiles += [px / n * s] * n
    costs = np.array([a + b * ps for ps in tiles])
    # contiguous chunks of about equal cost, as farm.chunk_tasks cuts them
    cum = np.cumsum([ps + DEFAULT_TASK_COST for ps in tiles])
    edges = np.unique(np.concatenate([[0], np.searchsorted(cum, cum[-1] * np.arange(1, n_chunks) / n_chunks)
                                      + 1, [len(tiles)]]).clip(0, len(tiles)))
    chunks = [costs[i:j].sum() + o_chunk for i, j in zip(edges[:-1], edges[1:]) if j > i]
    render = makespan(chunks, workers)
    merges = [merge_cost(px) for px, _ in scaled]
    return max(render, sum(merges)) + merges[-1], render, sum(merges) + merges[-1]


def amdahl(t1, t2, c):
    """Projected time on ``c`` threads from the measured times on 1 and 2:
    Amdahl's law ``T(c) = T1 (1 - f + f / c)`` with the parallel fraction
    measured from ``T2 = T1 (1 - f / 2)``, i.e. ``f = 2 (1 - T2 / T1)``,
    clipped to [0, 1].  Returns (T(c), f).  A projection: it assumes the
    parallel part keeps scaling (no memory-bandwidth limit, free cores)."""
    f = float(np.clip(2.0 * (1.0 - t2 / t1), 0.0, 1.0)) if t1 > 0 else 0.0
    return t1 * (1.0 - f + f / c), f


def _load(name, threads=None):
    """``<name>_t<threads>.json``, else ``<name>.json`` (files from before
    the thread count was recorded: one thread); None when neither exists."""
    for fn in ([f"{name}_t{threads}"] if threads else []) + [name]:
        path = os.path.join(OUT, fn + ".json")
        if os.path.exists(path):
            return json.load(open(path))
    return None


def _merge_fit(mg):
    """(fixed, per-pixel) seconds of ``merge_render``: least squares over the
    regions run inline (below ``inline_pixels``) and over the banded ones
    (the regions from it on and the warm whole frame); returns (inline fit,
    banded fit, inline_pixels)."""
    rows = mg["rows"] if isinstance(mg, dict) else mg
    inline = (mg.get("inline_pixels") if isinstance(mg, dict) else None) or 1 << 62
    def fit(sel):
        px = np.array([r["pixels"] for r in sel], float)
        sec = np.array([r["ms_per_task"] for r in sel]) / 1000
        if len(sel) == 1:
            return 0.0, float(sec[0] / px[0])
        (f0, f1), *_ = np.linalg.lstsq(np.stack([np.ones_like(px), px], 1), sec, rcond=None)
        return float(f0), float(f1)
    small = [r for r in rows if r["side"] not in ("full", "full_warm") and r["pixels"] < inline]
    big = [r for r in rows if r["side"] != "full" and r["pixels"] >= inline]
    return fit(small), (fit(big) if big else fit(small)), inline


def _band_plans(name):
    """The ``<name>_b<N>`` plan files (``plan --bands N``) by band count."""
    import glob
    import re
    found = {}
    for path in glob.glob(os.path.join(OUT, f"{name}_b*_t*.json")):
        m = re.fullmatch(re.escape(name) + r"_b(\d+)_t(\d+)\.json", os.path.basename(path))
        if m:
            found[int(m.group(1))] = json.load(open(path))
    return found


def banded_seconds(summary, wscale, byte_scale, bandwidth):
    """Time one adapt's (or the final reconstruction's) band calls take on
    the farm: per call the slowest band (every worker computes one band at
    once; a 4K band has the rows of the planned frame's band, ``wscale``
    times as wide) plus moving the inputs and results through the
    controller's network link (``byte_scale`` x the planned bytes at
    ``bandwidth`` B/s) and the controller's serialisation.  Returns
    (worker seconds, transfer seconds)."""
    work = sum(max(b) * wscale for b in summary["band_s"])
    moved = (summary["sent_bytes"] + summary["back_bytes"]) * byte_scale / bandwidth
    return work, moved + summary["serialize_s"] * byte_scale


def project(args):
    cyc = _load(f"cycles_{args.scene}")
    ov = _load("overhead_w2")
    if args.cycles_cost:
        a_fixed, b_ps = args.cycles_cost
    elif cyc is not None:
        a_fixed, b_ps = cyc["fixed_s"], cyc["per_pixel_sample_s"]
    else:
        raise SystemExit(f"no {OUT}/cycles_{args.scene}.json: run `cycles` or pass --cycles-cost A B")
    if args.chunk_overhead is not None:
        o_chunk = args.chunk_overhead
    elif ov is not None:
        # scheduler overhead per Dask task: the unchunked zero-cost runs (one Dask task per region task)
        o_chunk = min(r["overhead_ms_per_task"] for r in ov
                      if r["cost_s"] == 0 and r["chunks"] == r["tasks"]) / 1000
    else:
        raise SystemExit(f"no {OUT}/overhead_w2.json: run `overhead` or pass --chunk-overhead S")
    mg1, mg2 = _load("merge", 1), _load("merge", 2)
    (m0, m1), (b0, b1), inline = _merge_fit(mg1)
    b1_2 = _merge_fit(mg2)[1][1] if mg2 is not None else b1
    out, fractions = {}, {}
    for name in args.plans:
        p1, p2 = _load(name, 1), _load(name, 2)
        p2 = p2 if p2 is not None else p1
        scale = 3840 * 2160 / (p1["width"] * p1["height"])
        a1 = sum(st["adapt_s"] for st in p1["stages"])
        a2 = sum(st["adapt_s"] for st in p2["stages"])
        bands = _band_plans(name)
        wscale = 3840 / p1["width"]

        def band_plan(W):
            """The band plan a 4K frame on W workers (W bands of 2160 / W
            rows) matches: the planned frame cut into the same band height,
            or the nearest with fewer (taller, slower) bands."""
            want = W * p1["height"] / 2160
            fit = [n for n in bands if n <= want + 1e-9]
            return bands[max(fit)] if fit else None
        for c in args.controller_threads:
            _, fa = amdahl(a1, a2, c)

            def on_c(seconds, threads):  # a time measured on ``threads`` threads, on c (Amdahl, fraction fa)
                return seconds / (1.0 - fa + fa / threads) * (1.0 - fa + fa / c)
            rec_c, fr = amdahl(p1["reconstruct_s"], p2["reconstruct_s"], c)
            mpx_c, fm = amdahl(b1, b1_2, c)
            if args.fractions:  # given parallel fractions instead of the measured ones
                fa, fr, fm = args.fractions
                rec_c = p1["reconstruct_s"] * (1.0 - fr + fr / c)
                mpx_c = b1 * (1.0 - fm + fm / c)
            fractions[name] = {"adapt": round(fa, 3), "reconstruct": round(fr, 3), "merge_per_pixel": round(fm, 3),
                               "adapt_s_t1": round(a1, 2), "adapt_s_t2": round(a2, 2),
                               "reconstruct_s_t1": round(p1["reconstruct_s"], 2),
                               "reconstruct_s_t2": round(p2["reconstruct_s"], 2),
                               "merge_us_per_px_t1": round(1e6 * b1, 4), "merge_us_per_px_t2": round(1e6 * b1_2, 4)}
            for factor in args.scene_factors:
                a, b = a_fixed, b_ps * factor
                rows = {}
                for W in args.workers:
                    bp = band_plan(W)
                    ctrl = rec_c * scale  # the final reconstruction
                    ctrl += p1.get("loop_s", 0.0) * scale  # the loop's own per-task work (serial)
                    worker_fit = moved = 0.0
                    if bp is not None:  # the fits on the workers: the controller keeps the rest
                        rb = bp["reconstruct_bands"]
                        ctrl = on_c(bp["reconstruct_s"] - rb["bands_total_s"] - rb["serialize_s"], bp["threads"]) * scale
                        ctrl += p1.get("loop_s", 0.0) * scale
                        wf, mv = banded_seconds(rb, wscale, scale, args.network)
                        worker_fit, moved = worker_fit + wf, moved + mv
                    render = merge = stages = 0.0
                    for i, st in enumerate(p1["stages"]):
                        mf = lambda px: (m0 + m1 * px) if px < inline else (b0 + mpx_c * px)
                        t, r, m = stage_seconds(st["tasks"], W, a, b, o_chunk, mf, scale)
                        stages += t
                        render += r
                        merge += m
                        sb = bp["stages"][i] if bp is not None else None
                        if sb is not None and sb.get("bands"):
                            ctrl += on_c(sb["adapt_s"] - sb["bands"]["bands_total_s"] - sb["bands"]["serialize_s"],
                                         bp["threads"]) * scale
                            wf, mv = banded_seconds(sb["bands"], wscale, scale, args.network)
                            worker_fit, moved = worker_fit + wf, moved + mv
                        else:
                            ctrl += st["adapt_s"] * (1.0 - fa + fa / c) * scale  # adapt holds per-iteration fits
                    rows[W] = {"seconds": stages + ctrl + worker_fit + moved, "render_s": render, "merge_s": merge,
                               "controller_s": ctrl, "worker_fit_s": worker_fit, "transfer_s": moved,
                               "bands": bp["bands"] if bp is not None else 1}
                t1 = rows[args.workers[0]]["seconds"]
                serial = rows[args.workers[0]]["controller_s"] + rows[args.workers[0]]["merge_s"]
                render1 = rows[args.workers[0]]["render_s"] * args.workers[0]
                entry = {"barrier_W": round(render1 / serial, 1), "serial_s": round(serial, 1)}
                for r in rows.values():  # with the fits on the workers the rest depends on W
                    r["rest_s"] = r["controller_s"] + r["merge_s"] + r["worker_fit_s"] + r["transfer_s"]
                out[f"{name} x{factor:g} C={c}"] = {
                    **entry,
                    **{str(W): {"seconds": round(r["seconds"], 1), "speedup": round(t1 / r["seconds"], 2),
                                "render_s": round(r["render_s"], 1), "merge_s": round(r["merge_s"], 1),
                                "adapt_reconstruct_s": round(r["controller_s"], 1),
                                "worker_fit_s": round(r["worker_fit_s"], 1), "transfer_s": round(r["transfer_s"], 1),
                                "bands": r["bands"],
                                # the barrier W if the time outside rendering stayed at this W's: rendering
                                # still dominates at W while this is >= W
                                "barrier_W_here": round(render1 / r["rest_s"], 1)} for W, r in rows.items()}}
    source = ("given parallel fractions (--fractions)" if args.fractions
              else "parallel fractions measured from the 1- and 2-thread files")
    _save("project", {"projection": f"Amdahl on C controller cores, {source}; not measured on C cores",
                      "o_chunk_s": o_chunk, "merge_fixed_s": m0, "merge_s_per_pixel": m1,
                      "merge_banded_fixed_s": b0, "merge_banded_s_per_pixel": b1, "inline_pixels": inline,
                      "cycles_fixed_s": a_fixed, "cycles_s_per_pixel_sample": b_ps,
                      "parallel_fractions": fractions, "plans": out})


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    o = sub.add_parser("overhead")
    o.add_argument("--workers", type=int, default=2)
    o.add_argument("--tasks", type=int, default=400)
    m = sub.add_parser("merge")
    m.add_argument("--width", type=int, default=3840)
    m.add_argument("--height", type=int, default=2160)
    c = sub.add_parser("cycles")
    c.add_argument("--scene", default="cornell")
    p = sub.add_parser("plan")
    p.add_argument("--method", default="var")
    p.add_argument("--spp", type=float, default=16)
    p.add_argument("--width", type=int, default=3840)
    p.add_argument("--height", type=int, default=2160)
    p.add_argument("--bands", type=int, default=1,
                   help="spread the method's fit over this many bands (lp; the farm's one band per worker), "
                        "each computed and timed here one after the other")
    k = sub.add_parser("kernels")
    k.add_argument("--width", type=int, default=3840)
    k.add_argument("--height", type=int, default=2160)
    k.add_argument("--repeats", type=int, default=3)
    j = sub.add_parser("project")
    j.add_argument("--scene", default="cornell")
    j.add_argument("--plans", nargs="+", default=["plan_var_3840x2160"],
                   help="plan names without the _t<threads> suffix")
    j.add_argument("--controller-threads", nargs="+", type=int, default=[1],
                   help="controller core counts C to project (Amdahl from the 1- and 2-thread files)")
    j.add_argument("--workers", nargs="+", type=int, default=[1, 4, 8, 16, 64])
    j.add_argument("--fractions", nargs=3, type=float, metavar=("ADAPT", "RECONSTRUCT", "MERGE"),
                   help="parallel fractions to project with instead of the measured 1-/2-thread ones")
    j.add_argument("--cycles-cost", nargs=2, type=float, metavar=("FIXED_S", "S_PER_PIXEL_SAMPLE"),
                   help="Cycles task cost instead of cycles_<scene>.json")
    j.add_argument("--chunk-overhead", type=float, help="seconds per Dask chunk instead of overhead_w2.json")
    j.add_argument("--network", type=float, default=1.25e9,
                   help="controller network bytes per second for banded fits' inputs and results (10 GbE)")
    j.add_argument("--scene-factors", nargs="+", type=float, default=[1.0, 10.0, 100.0],
                   help="multiples of the measured per-pixel-sample cost (heavier production scenes)")
    args = ap.parse_args(argv)
    {"overhead": overhead, "merge": merge, "cycles": cycles, "plan": plan, "kernels": kernels,
     "project": project}[args.cmd](args)


if __name__ == "__main__":
    main()

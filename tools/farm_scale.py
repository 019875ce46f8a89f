"""Scale of the Dask farm (operators/farm.py): measured costs and the projected
speed-up of one frame over W workers (docs/notes/farm.md).

    .venv/bin/python tools/farm_scale.py overhead        # scheduler overhead per region task
    .venv/bin/python tools/farm_scale.py merge           # controller merge rate at 4K
    .venv/bin/python tools/farm_scale.py cycles          # Cycles task cost local vs on a worker
    .venv/bin/python tools/farm_scale.py plan --method var --width 3840 --height 2160
    .venv/bin/python tools/farm_scale.py project         # from the JSON files the others wrote

Each command writes its figures to ``bench_out/farm/<command>*.json`` and prints
them.  ``overhead`` runs tasks of a known cost (a sleep: the render happens
elsewhere) that return buffers of a region's size through the same calls as
``DaskExecutor.render_many`` (``client.map``, results in task order);
``plan`` runs ``AdaptiveRun`` with a synthetic executor (no rendering) and
records every iteration's tasks and the controller's own time (adapt: sample
map and planner; reconstruct when the method's sampler uses it).
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

from cycles_adaptive.core import methods  # noqa: E402
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
    w, h = args.width, args.height
    buf = Buffers.empty(h, w, tuple(LP_CHANNELS))
    rng = np.random.default_rng(0)
    rows = []
    full = RegionTask(0, 0, w, h, 1)
    color = rng.random((h, w, 4)).astype(np.float32).astype(np.float64)
    feats = {k: rng.random((h, w, c)) for k, c in LP_CHANNELS.items() if k != "alpha"}
    t0 = time.perf_counter()
    merge_render(buf, full, color, feats)
    rows.append({"side": "full", "pixels": w * h, "ms_per_task": 1000 * (time.perf_counter() - t0),
                 "mpix_per_s": w * h / 1e6 / (time.perf_counter() - t0)})
    for side in (16, 32, 64, 128, 256):
        c = color[:side, :side].copy()
        fs = {k: v[:side, :side].copy() for k, v in feats.items()}
        n = max(20, int(2e7 // (side * side * 50)))
        t0 = time.perf_counter()
        for i in range(n):
            x0 = (i * side) % (w - side)
            y0 = ((i * side) // (w - side) * side) % (h - side)
            merge_render(buf, RegionTask(x0, y0, x0 + side, y0 + side, 2), c, fs)
        dt = (time.perf_counter() - t0) / n
        rows.append({"side": side, "pixels": side * side, "ms_per_task": 1000 * dt,
                     "mpix_per_s": side * side / 1e6 / dt})
    _save("merge", rows)


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


def plan(args):
    m = methods.get(args.method)
    opts = Options(method=args.method, spp=args.spp, seed=0)
    ex = SyntheticExecutor(args.width, args.height, tuple(m.PASSES))
    run = AdaptiveRun(ex, opts)
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
            adapt0 = run.timing.adapt
    close()
    stage_tasks = stages
    t0 = time.perf_counter()
    run.reconstruct()
    rec = time.perf_counter() - t0
    _save(f"plan_{args.method}_{args.width}x{args.height}",
          {"method": args.method, "width": args.width, "height": args.height, "spp": args.spp,
           "stages": stage_tasks, "reconstruct_s": rec, "uses_result": bool(m.SAMPLER_USES_RESULT)})


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


def stage_seconds(tasks, workers, a, b, o_chunk, merge_fixed, merge_px, scale):
    """One stage (the initial pass or an iteration) of a frame on ``workers``:
    tasks cut into tiles and chunks as ``DaskExecutor.render_many`` does
    (4 chunks per worker), rendered at ``a + b * pixel-samples`` per tile,
    ``o_chunk`` scheduler overhead per chunk; the controller merges each task
    (``merge_fixed + merge_px * pixels``) as it completes, so the stage lasts
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
    merges = [merge_fixed + merge_px * px for px, _ in scaled]
    return max(render, sum(merges)) + merges[-1], render, sum(merges) + merges[-1]


def project(args):
    cyc = json.load(open(os.path.join(OUT, f"cycles_{args.scene}.json")))
    ov = json.load(open(os.path.join(OUT, "overhead_w2.json")))
    mg = json.load(open(os.path.join(OUT, "merge.json")))
    # scheduler overhead per Dask task: the unchunked zero-cost runs (one Dask task per region task)
    o_chunk = min(r["overhead_ms_per_task"] for r in ov if r["cost_s"] == 0 and r["chunks"] == r["tasks"]) / 1000
    regional = [r for r in mg if r["side"] != "full"]
    px = np.array([r["pixels"] for r in regional], float)
    sec = np.array([r["ms_per_task"] for r in regional]) / 1000
    (m0, m1), *_ = np.linalg.lstsq(np.stack([np.ones_like(px), px], 1), sec, rcond=None)
    out = {}
    for name in args.plans:
        p = json.load(open(os.path.join(OUT, name + ".json")))
        scale = 3840 * 2160 / (p["width"] * p["height"])
        for factor in args.scene_factors:
            a, b = cyc["fixed_s"], cyc["per_pixel_sample_s"] * factor
            rows = {}
            for W in (1, 4, 16, 64):
                ctrl = p["reconstruct_s"] * scale  # the final reconstruction
                render = merge = stages = 0.0
                for st in p["stages"]:
                    t, r, m = stage_seconds(st["tasks"], W, a, b, o_chunk, m0, m1, scale)
                    stages += t
                    render += r
                    merge += m
                    ctrl += st["adapt_s"] * scale  # adapt already holds per-iteration reconstructions
                rows[W] = {"seconds": stages + ctrl, "render_s": render, "merge_s": merge, "controller_s": ctrl}
            t1 = rows[1]["seconds"]
            out[f"{name} x{factor:g}"] = {
                str(W): {"seconds": round(r["seconds"], 1), "speedup": round(t1 / r["seconds"], 2),
                         "render_s": round(r["render_s"], 1), "merge_s": round(r["merge_s"], 1),
                         "adapt_reconstruct_s": round(r["controller_s"], 1)} for W, r in rows.items()}
    _save("project", {"o_chunk_s": o_chunk, "merge_fixed_s": m0, "merge_s_per_pixel": m1,
                      "cycles_fixed_s": cyc["fixed_s"], "cycles_s_per_pixel_sample": cyc["per_pixel_sample_s"],
                      "plans": out})


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
    j = sub.add_parser("project")
    j.add_argument("--scene", default="cornell")
    j.add_argument("--plans", nargs="+", default=["plan_var_3840x2160"])
    j.add_argument("--scene-factors", nargs="+", type=float, default=[1.0, 10.0, 100.0],
                   help="multiples of the measured per-pixel-sample cost (heavier production scenes)")
    args = ap.parse_args(argv)
    {"overhead": overhead, "merge": merge, "cycles": cycles, "plan": plan, "project": project}[args.cmd](args)


if __name__ == "__main__":
    main()

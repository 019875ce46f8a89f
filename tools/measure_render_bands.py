"""The longest single Cycles render of a run (what blocks Blender's main
thread in the panel: every other stage runs off it) and the run's wall time,
with and without ``Options.render_seconds`` (the panel's Longest Render),
alternated in one process on the same scene, method and seed:

    .venv/bin/python tools/measure_render_bands.py --scenes cornell --percent 400 \\
        --method lp --spp 16 --bounds 0,1 --repeats 2

Prints one JSON line per run and a Markdown table of medians."""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

load_package()
import bpy  # noqa: E402

from cycles_adaptive.core.pipeline import Options  # noqa: E402
from cycles_adaptive.operators.job import RenderJob  # noqa: E402


def run_once(scene_name: str, percent: int, method: str, spp: int, bound: float, out_dir: str) -> dict:
    bpy.ops.wm.open_mainfile(filepath=os.path.join(ROOT, "sample_blends", f"{scene_name}.blend"))
    scene = bpy.context.scene
    scene.render.resolution_percentage = percent
    out = os.path.join(out_dir, f"{scene_name}_{method}_{bound:g}_{time.monotonic_ns()}.exr")
    t0 = time.perf_counter()
    job = RenderJob(scene, bpy.context.view_layer,
                    Options(method=method, spp=spp, frame=scene.frame_current, render_seconds=bound), out)
    for _ in job.steps():
        pass
    job.finish()
    wall = time.perf_counter() - t0
    run = job.run
    w = scene.render.resolution_x * percent // 100
    h = scene.render.resolution_y * percent // 100
    return {"scene": scene_name, "size": f"{w}x{h}", "method": method, "spp": spp, "render_seconds": bound,
            "longest_render": round(run.max_task_seconds, 3), "renders": run.tasks_rendered,
            "render_total": round(run.timing.render, 2), "wall": round(wall, 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="cornell")
    ap.add_argument("--percent", type=int, default=400)
    ap.add_argument("--method", default="lp")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--bounds", default="0,1", help="render_seconds values, alternated (0: no bound)")
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    bounds = [float(b) for b in args.bounds.split(",")]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene_name in args.scenes.split(","):
            for _ in range(args.repeats):
                for bound in bounds:
                    r = run_once(scene_name, args.percent, args.method, args.spp, bound, tmp)
                    print(json.dumps(r), flush=True)
                    rows.append(r)
    print("\n| scene | size | method | spp | Longest Render | longest render (s) | renders | render s | wall s |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for scene_name in args.scenes.split(","):
        for bound in bounds:
            rs = [r for r in rows if r["scene"] == scene_name and r["render_seconds"] == bound]
            med = {k: statistics.median(r[k] for r in rs) for k in ("longest_render", "renders", "render_total", "wall")}
            print(f"| {scene_name} | {rs[0]['size']} | {args.method} | {args.spp} | {bound:g} | "
                  f"{med['longest_render']:.2f} | {med['renders']:g} | {med['render_total']:.1f} | {med['wall']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

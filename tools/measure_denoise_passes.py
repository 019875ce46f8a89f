"""Render seconds of a var run with and without the feature passes every denoiser reads
(docs/notes/denoise-cli.md).  Run from the repository root: .venv/bin/python tools/measure_denoise_passes.py"""
import sys, time, os
sys.path.insert(0, os.getcwd()); import launch; launch.load_package()
import bpy
from cycles_adaptive.operators.job import RenderJob, make_options, open_blend, resolve_scene
for blend in ("cornell", "glossy"):
    for rep in range(2):
        for keep in (False, True):
            open_blend(f"sample_blends/{blend}.blend")
            scene, vl = resolve_scene()
            scene.render.resolution_x = scene.render.resolution_y = 128
            scene.render.resolution_percentage = 100
            opts = make_options("var", scene.frame_current, {"spp": 16.0})
            job = RenderJob(scene, vl, opts, None, keep_denoise_passes=keep)
            t0 = time.perf_counter()
            for _ in job.steps():
                pass
            s = job.finish()
            print(blend, rep, "keep" if keep else "none", f"render_seconds={s['render_seconds']:.3f}",
                  f"total={time.perf_counter()-t0:.3f}", "feats", job.run.feature_names, flush=True)

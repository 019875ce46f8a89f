"""A time limit's reserve for the outputs against what they took
(docs/notes/time-limit.md): a 960x540 test scene, without a compositor and
with one running a Glare (fog glow) node; one time-limited var run each.

  PYTHONPATH=. .venv/bin/python tools/output_reserve.py   # from the repository root
"""
import sys, os, time, tempfile, json
sys.path.insert(0, "tests")
import conftest  # noqa: F401  (loads the package)
import bpy
from blend_util import build_scene, compositor_tree
from cycles_adaptive.core.pipeline import Options
from cycles_adaptive.operators import job as J

for comp in (False, True):
    scene = build_scene(960, 540)
    if comp:
        tree, out = compositor_tree(scene)
        rl = tree.nodes.new("CompositorNodeRLayers")
        g = tree.nodes.new("CompositorNodeGlare")
        if hasattr(g, "glare_type"):
            g.glare_type = "FOG_GLOW"
        tree.links.new(rl.outputs["Image"], g.inputs[0])
        tree.links.new(g.outputs[0], out.inputs[0])
    d = tempfile.mkdtemp()
    opts = Options(method="var", spp=10000, seed=1, max_seconds=20.0)
    job = J.RenderJob(scene, bpy.context.view_layer, opts, os.path.join(d, "o.exr"))
    for _ in job.steps():
        pass
    t_end_sampling = time.perf_counter()
    t = time.perf_counter()
    job.reconstruct_work().result()
    t_rec = time.perf_counter() - t
    t = time.perf_counter()
    s = job.finish()
    t_out = time.perf_counter() - t
    print(json.dumps(dict(compositor=s["compositor"], reserve_outputs=round(job.run.reserve_seconds, 3),
                          outputs_took=round(t_out, 3), recon_est=round(job.run.reconstruct_estimate or 0, 3),
                          recon_took=round(t_rec, 3), total=round(s["total_seconds"], 2), limit=20.0)))

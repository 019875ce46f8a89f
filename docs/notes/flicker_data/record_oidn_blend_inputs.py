"""Record, per frame, what oidn+blend's final reconstruction sees (animated, 8 spp, seed 0, frames 1-8) into /tmp/w/rec.pkl: colour mean, variance of the mean, samples, albedo, normal, Surface, backward coordinates, camera, and the blended output."""
import sys, pickle; sys.path.insert(0, "tests"); sys.path.insert(0, "."); import conftest
import bpy, numpy as np
from cycles_adaptive.operators.job import FramesJob, open_blend
from cycles_adaptive.core.pipeline import Options
from cycles_adaptive.core import history, reproject
open_blend("sample_blends/animated.blend")
scene = bpy.context.scene
opts = Options(method="oidn", spp=8, seed=0)
fj = FramesJob(scene, bpy.context.view_layer, opts, "/tmp/w/rec/f_####.exr", list(range(1, 9)), temporal="blend",
               seed_mode="animated", preview=False)
rec = []
orig = fj._blend
def spy(run):
    buf = run.buffers
    coords = fj._backward_coordinates(buf) if fj._history is not None else None
    out = orig(run)
    rec.append(dict(color=buf.color.mean.copy(), var=buf.variance_of_mean().copy() if hasattr(buf, "variance_of_mean") else None,
                    n=buf.n.copy(), albedo=buf.features["albedo"].mean.copy(), normal=buf.features["normal"].mean.copy(),
                    surface=history.Surface.from_buffers(buf), coords=coords,
                    cam=reproject.Camera.from_render(fj.job.camera).position, blend=out.image.copy()))
    return out
fj._blend = spy
for item in fj.steps():
    pass
pickle.dump(rec, open("/tmp/w/rec.pkl", "wb"))
print(len(rec), rec[0]["color"].shape, rec[0]["var"] is None)

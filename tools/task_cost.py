"""Measure the fixed cost of one region render in pixel-samples (regions.DEFAULT_TASK_COST).

    .venv/bin/python tools/task_cost.py cornell glossy
"""
import sys, time; sys.path.insert(0,'.')
from launch import load_package; load_package()
import bpy, numpy as np
from cycles_adaptive.addon.executor import CyclesExecutor
from cycles_adaptive.core.regions import RegionTask
for scene_name in sys.argv[1:]:
    bpy.ops.wm.open_mainfile(filepath=f'sample_blends/{scene_name}.blend')
    s=bpy.context.scene
    with CyclesExecutor(s, bpy.context.view_layer, (), seed=0) as ex:
        h,w=ex.size
        ex.render(RegionTask(0,0,w,h,1,frame=1))
        rows=[]
        for size,spp in [(8,1),(8,4),(16,1),(16,4),(32,1),(32,4),(64,4),(128,1),(128,4),(128,8)]:
            ts=[]
            for rep in range(3):
                t=time.perf_counter(); ex.render(RegionTask(0,0,size,size,spp,frame=1,offset=10+rep*spp)); ts.append(time.perf_counter()-t)
            rows.append((size*size*spp, min(ts)))
    ps,sec=np.array(rows).T
    A=np.stack([np.ones_like(ps),ps],1); (a,b),*_=np.linalg.lstsq(A,sec,rcond=None)
    print(scene_name, f"fixed {a*1000:.1f} ms, per pixel-sample {b*1e6:.2f} us, task cost = {a/b:.0f} pixel-samples")

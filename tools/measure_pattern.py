"""relMSE of plain Cycles renders per sampling pattern, over seeds (docs/notes/sampling-pattern.md).

Our loop renders with Tabulated Sobol (addon/executor.py: its subsets merge exactly for any
subset length, so ``uniform`` through the loop is this pattern's plain render); Blender 4.2+
renders with AUTOMATIC (blue noise) by default.  This measures what the pattern alone costs,
at equal spp, against the converged references:

    .venv/bin/python tools/measure_pattern.py [--scenes cornell,...] [--spp 8,16] [--seeds 0,1,2,3]
        [--patterns AUTOMATIC,TABULATED_SOBOL] [--reference-dir /work/refs] [--out F.json]
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

load_package()
import bpy  # noqa: E402

from cycles_adaptive.core import io as imageio  # noqa: E402
from cycles_adaptive.core import metrics  # noqa: E402

SCENES = "cornell,dof,soft_shadows,glossy,motion_blur,animated"


def reference(scene, ref_dir):
    paths = sorted(glob.glob(os.path.join(ref_dir, f"{scene}.f0001.r100.s*.exr")),
                   key=lambda p: int(p.rsplit(".s", 1)[1].split(".")[0]))
    if not paths:
        raise SystemExit(f"no reference for {scene} in {ref_dir}")
    return imageio.read_reference(paths[-1])[..., :3]


def render(scene_name, pattern, spp, seed, tmp):
    bpy.ops.wm.open_mainfile(filepath=os.path.join(ROOT, "sample_blends", f"{scene_name}.blend"))
    s = bpy.context.scene
    c = s.cycles
    s.frame_set(1)
    c.sampling_pattern = pattern
    c.samples = spp
    c.seed = seed
    c.use_animated_seed = False
    c.use_adaptive_sampling = False
    c.use_denoising = False
    s.render.image_settings.file_format = "OPEN_EXR"
    s.render.image_settings.color_depth = "32"
    s.render.use_file_extension = False
    s.render.filepath = os.path.join(tmp, f"{scene_name}_{pattern}_{spp}_{seed}.exr")
    bpy.ops.render.render(write_still=True)
    return imageio.read_rgb(s.render.filepath)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default=SCENES)
    ap.add_argument("--spp", default="8,16")
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--patterns", default="AUTOMATIC,TABULATED_SOBOL")
    ap.add_argument("--reference-dir", default=os.path.join(ROOT, "references"))
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    spps = [int(x) for x in args.spp.split(",")]
    seeds = [int(x) for x in args.seeds.split(",")]
    patterns = args.patterns.split(",")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes.split(","):
            ref = reference(scene, args.reference_dir)
            for spp in spps:
                per = {}
                for pattern in patterns:
                    errs = [metrics.relmse(render(scene, pattern, spp, seed, tmp), ref) for seed in seeds]
                    per[pattern] = errs
                    rows.append({"scene": scene, "spp": spp, "pattern": pattern, "relmse": errs,
                                 "mean": float(np.mean(errs))})
                base = float(np.mean(per[patterns[0]]))
                print(f"{scene:13s} {spp:4d} spp  " + "  ".join(
                    f"{p} {np.mean(e):.4e} ({np.mean(e) / base:.3f}x)" for p, e in per.items()), flush=True)
    if args.out:
        imageio.write_text(args.out, json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    from launch import leave
    leave(main())

"""How much of OIDN's error on the sample scenes is the noise of its albedo /
normal inputs? (developer tool, not shipped; docs/notes/oidn.md)

    RHF_STUDY_CACHE=DIR .venv/bin/python tools/oidn_aux_study.py spp [--refs R]
    RHF_STUDY_CACHE=DIR .venv/bin/python tools/oidn_aux_study.py prefilter [--refs R]

``spp``: the cached 16-spp colour (``tools/rhf_study.py render``, seed 0) is
denoised (pyoidn, high quality, accurate prefilter) with its own auxiliaries
and with albedo / normal of independent renders (seed 5) at 32, 64 and 128
spp; beside it, a plain 32-spp render denoised with its own auxiliaries, the
same time as 16-spp colour plus a 16-spp auxiliary render.  Times are
single full-frame renders of the scene as it is (128x128, after a warm-up).

``prefilter``: the auxiliaries prefiltered by RHF's Eq. 7 (NL-means + guided
filter, ``core/rhf.py``) instead of OIDN's own prefilter, then given to OIDN
as noise-free (prefilter none) or prefiltered once more (accurate).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import rhf_study as rs  # noqa: E402  (cache, references, package loading)

from cycles_adaptive.core import metrics, oidn, rhf  # noqa: E402

SCENES = "cornell,dof,soft_shadows,glossy,motion_blur,animated"


def denoise(color, albedo, normal, prefilter="accurate"):
    """pyoidn, high quality, ``prefilter`` (accurate: OIDN's own on the guides)."""
    return oidn.oidn_filter(color[..., :3], albedo, normal, quality="high", prefilter=prefilter)


def _render(scene, spp: int, seed: int):
    """(colour, features, seconds) of one full-frame render of the current frame."""
    import bpy
    from cycles_adaptive.addon.executor import CyclesExecutor
    from cycles_adaptive.core.regions import RegionTask
    with CyclesExecutor(scene, bpy.context.view_layer, ("albedo", "normal"), seed=seed) as ex:
        h, w = ex.size
        frame = scene.frame_current
        ex.render(RegionTask(0, 0, w, h, 1, frame=frame))  # warm-up: kernels, BVH
        t0 = time.perf_counter()
        color, feats = ex.render(RegionTask(0, 0, w, h, spp, frame=frame))
        return color, feats, time.perf_counter() - t0


def study_spp(scenes):
    import bpy
    from cycles_adaptive.bench import references as refs
    print("| scene | c16 + own aux16 | c16 + aux32 | c16 + aux64 | c16 + aux128 | c32 + own aux32 | "
          "time c32 / c16 | time 128 / 16 |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in scenes:
        refs.open_scene(refs.scene_path(name), force=True)
        scene = bpy.context.scene
        scene.render.resolution_percentage = 100
        b16 = rs.load(name, 16)
        ref = rs.reference(name, b16.n.shape)
        c16 = b16.color.mean
        row = [metrics.relmse(denoise(c16, b16.feature("albedo"), b16.feature("normal")), ref)]
        times = {}
        for spp in (32, 64, 128):
            _, aux, times[spp] = _render(scene, spp, seed=5)
            row.append(metrics.relmse(denoise(c16, aux["albedo"], aux["normal"]), ref))
        _, _, times[16] = _render(scene, 16, seed=5)
        c32, f32, _ = _render(scene, 32, seed=0)
        row.append(metrics.relmse(denoise(c32, f32["albedo"], f32["normal"]), ref))
        print(f"| {name} | " + " | ".join(f"{e:.3e}" for e in row)
              + f" | {times[32] / times[16]:.2f} | {times[128] / times[16]:.2f} |", flush=True)


def study_prefilter(scenes):
    p = rhf.Params()
    print("| scene | spp | OIDN accurate | RHF Eq. 7, none | RHF Eq. 7, then accurate |")
    print("|---|---:|---:|---:|---:|")
    for name in scenes:
        for spp in (8, 16):
            b = rs.load(name, spp)
            ref = rs.reference(name, b.n.shape)
            feats, fvars = rhf._feature_arrays(b)
            F, V = rhf.prepare_features(feats, fvars, b.n.astype(np.float64), np.zeros(b.n.shape, bool))
            fh = rhf.prefilter_features(F, V, p).astype(np.float64)
            nrm, alb = fh[..., 0:3], fh[..., 3:6]
            c = b.color.mean
            errs = [metrics.relmse(denoise(c, b.feature("albedo"), b.feature("normal")), ref),
                    metrics.relmse(denoise(c, alb, nrm, "none"), ref),
                    metrics.relmse(denoise(c, alb, nrm, "accurate"), ref)]
            print(f"| {name} | {spp} | " + " | ".join(f"{e:.3e}" for e in errs) + " |", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("spp", "prefilter"))
    ap.add_argument("--scenes", default=SCENES)
    ap.add_argument("--refs", default=rs.REFS, help="reference folder (default %(default)s)")
    args = ap.parse_args(argv)
    rs.REFS = args.refs
    scenes = args.scenes.split(",")
    (study_spp if args.what == "spp" else study_prefilter)(scenes)


if __name__ == "__main__":
    main()

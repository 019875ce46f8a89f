"""RHF measurements (docs/notes/rhf.md): sample-scene buffers at low spp
against the cached 1024-spp references, speed against OIDN, quality figures.

  python tools/rhf_study.py render            # cache buffers of the six scenes (8, 16 spp)
  python tools/rhf_study.py quality [--set input_blend=fixed ...] [--before]
  python tools/rhf_study.py speed [--compare] [--profile]   # 512x512 (tiled cornell 16 spp)

Buffers are cached in $RHF_STUDY_CACHE (default /tmp/rhf_study); --before and
--compare load the pre-change module from $RHF_BEFORE (default
/work/before/core/rhf.py).
"""
from __future__ import annotations

import argparse
import cProfile
import os
import pickle
import pstats
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

load_package()
from cycles_adaptive.core import metrics, rhf  # noqa: E402

CACHE = os.environ.get("RHF_STUDY_CACHE", "/tmp/rhf_study")
SCENES = ("cornell", "soft_shadows", "glossy", "dof", "motion_blur", "animated")
REFS = "/work/refs"


def cache_path(scene, spp, seed=0):
    return os.path.join(CACHE, f"{scene}.s{spp}.seed{seed}.pkl")


def render(scenes, spps, seed=0, subsets=4):
    """Render each scene at each spp (``subsets`` sample subsets, every
    feature pass) with the benchmark's executor; pickles the Buffers."""
    import bpy
    from cycles_adaptive.addon.executor import CyclesExecutor
    from cycles_adaptive.bench import references as refs
    from cycles_adaptive.core.buffers import Buffers
    from cycles_adaptive.core.pipeline import render_subsets
    os.makedirs(CACHE, exist_ok=True)
    feats = ("normal", "albedo", "depth")
    for s in scenes:
        refs.open_scene(refs.scene_path(s), force=True)
        scene, vl = bpy.context.scene, bpy.context.view_layer
        scene.render.resolution_percentage = 100
        for spp in spps:
            p = cache_path(s, spp, seed)
            if os.path.exists(p):
                continue
            with CyclesExecutor(scene, vl, feats, seed=seed) as exe:
                h, w = exe.size
                buf = Buffers.empty(h, w, feats + ("alpha",))
                render_subsets(exe, buf, spp, subsets, scene.frame_current)
            with open(p, "wb") as f:
                pickle.dump(buf, f)
            print(f"{s} {spp} spp -> {p}", flush=True)


def load(scene, spp, seed=0):
    with open(cache_path(scene, spp, seed), "rb") as f:
        return pickle.load(f)


def reference(scene, shape):
    from cycles_adaptive.core.io import read_reference
    return read_reference(os.path.join(REFS, f"{scene}.f0001.r100.s1024.exr"), shape)


BEFORE = os.environ.get("RHF_BEFORE", "/work/before/core/rhf.py")


def before_rhf(path=BEFORE):
    """A pre-change copy of ``core/rhf.py`` (default /work/before; env
    RHF_BEFORE), loaded beside the current one (same helpers)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("cycles_adaptive.core.rhf_before", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def pooled(x, s=8):
    """Mean over s x s blocks (trailing rows / columns cut)."""
    h, w = x.shape[0] // s * s, x.shape[1] // s * s
    return x[:h, :w].reshape(h // s, s, w // s, s).mean(axis=(1, 3))


def corr(a, b):
    a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else 0.0


def figures(res, buf, ref):
    """relMSE, negatives, brightness and error-map correlations of one result."""
    img, y = res.image, buf.color.mean
    true = ((img - ref) ** 2).mean(-1)
    return {"relmse": metrics.relmse(img, ref), "input_relmse": metrics.relmse(y, ref),
            "neg_px": int((img < 0).any(-1).sum()), "min": float(img.min()),
            "bright": float(img.mean() / max(y.mean(), 1e-12) - 1.0),
            "corr": corr(res.error, true), "corr8": corr(pooled(res.error), pooled(true))}


def quality(mod, spps=(8, 16), scenes=SCENES, **kw):
    rows = []
    for s in scenes:
        for spp in spps:
            buf = load(s, spp)
            ref = reference(s, buf.shape)
            p = mod.Params(**kw)
            t0 = time.perf_counter()
            res = mod.reconstruct(buf, p)
            f = figures(res, buf, ref)
            f.update(scene=s, spp=spp, seconds=time.perf_counter() - t0)
            rows.append(f)
            print(f"{s:13s} {spp:3d} relMSE {f['relmse']:.3e} (input {f['input_relmse']:.3e}) "
                  f"neg {f['neg_px']:4d} min {f['min']:+.3f} bright {100 * f['bright']:+.2f}% "
                  f"corr {f['corr']:.2f} corr8 {f['corr8']:.2f} {f['seconds']:.1f}s", flush=True)
    return rows


def tiled(buf, reps=4):
    """Buffers tiled reps x reps (a 512x512 input from a 128x128 render)."""
    import copy
    out = copy.deepcopy(buf)
    t = lambda a: np.tile(a, (reps, reps) + (1,) * (a.ndim - 2))
    out.n, out.k = t(buf.n), t(buf.k)
    for st in [out.color] + list(out.features.values()):
        st.mean, st.m2 = t(st.mean), t(st.m2)
    out.half = None
    return out


def _best(fn, reps):
    """Least wall seconds of ``reps`` calls (the machine is shared) and the last result."""
    best, out = np.inf, None
    for _ in range(reps):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def speed(profile=False, compare_before=False, scene="cornell", spp=16, reps=2):
    """Seconds per megapixel of RHF and OIDN on the same 512x512 buffers
    (least of ``reps`` interleaved runs each); with ``compare_before`` also
    the pre-change module (RHF_BEFORE) and the bit-exactness of the current
    one with the new options off."""
    from cycles_adaptive.core import oidn
    buf = tiled(load(scene, spp))
    mp = buf.n.size / 1e6
    feats = {k: buf.features[k].mean for k in ("albedo", "normal")}
    old = before_rhf() if compare_before else None
    t = {"oidn_one": [], "oidn_denoise": [], "rhf": [], "before": []}
    for _ in range(reps):
        t["oidn_one"].append(_best(lambda: oidn.oidn_filter(buf.color.mean, feats["albedo"],
                                                            feats["normal"]), 1)[0])
        t["oidn_denoise"].append(_best(lambda: oidn.reconstruct(buf), 1)[0])
        sec, res = _best(lambda: rhf.reconstruct(buf), 1)
        t["rhf"].append(sec)
        if old is not None:
            sec, ro = _best(lambda: old.reconstruct(buf), 1)
            t["before"].append(sec)
    b = {k: min(v) / mp for k, v in t.items() if v}
    print(f"{buf.n.shape}, least of {reps}: OIDN one call {b['oidn_one']:.2f} s/MP, "
          f"oidn.reconstruct (3 calls, recorrupted halves) {b['oidn_denoise']:.2f} s/MP, "
          f"RHF {b['rhf']:.2f} s/MP -> RHF / oidn.reconstruct {b['rhf'] / b['oidn_denoise']:.2f}, "
          f"RHF / one OIDN call {b['rhf'] / b['oidn_one']:.2f}; models {res.info['models']}")
    if old is not None:
        print(f"before {b['before']:.2f} s/MP (before / oidn.reconstruct "
              f"{b['before'] / b['oidn_denoise']:.2f}); models {ro.info['models']}")
        p = rhf.Params(detail_cover=False, input_blend="fixed", clamp_predictions=False)
        rn = rhf.reconstruct(buf, p)
        print("new options off == before: image", np.array_equal(rn.image, ro.image),
              "error", np.array_equal(rn.error, ro.error))
    if profile:
        pr = cProfile.Profile()
        pr.enable()
        rhf.reconstruct(buf)
        pr.disable()
        pstats.Stats(pr).sort_stats("tottime").print_stats(15)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd", choices=("render", "quality", "speed"))
    ap.add_argument("--before", action="store_true", help="quality: the /work/before module")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--compare", action="store_true")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--spp", default="8,16")
    ap.add_argument("--set", action="append", default=[], help="Params field=value")
    a = ap.parse_args(argv)
    scenes = a.scenes.split(",")
    spps = tuple(int(s) for s in a.spp.split(","))
    if a.cmd == "render":
        render(scenes, spps)
    elif a.cmd == "quality":
        kw = {}
        for kv in a.set:
            k, v = kv.split("=")
            kw[k] = type(getattr(rhf.Params(), k))(v) if not isinstance(getattr(rhf.Params(), k), bool) \
                else v.lower() in ("1", "true")
        quality(before_rhf() if a.before else rhf, spps, scenes, **kw)
    else:
        speed(a.profile, a.compare)


if __name__ == "__main__":
    main()

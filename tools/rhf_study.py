"""RHF measurements (docs/notes/rhf.md): sample-scene buffers at low spp
against the cached 1024-spp references, speed against OIDN, quality figures.

  python tools/rhf_study.py render            # cache buffers of the six scenes (8, 16 spp)
  python tools/rhf_study.py quality [--set input_blend=fixed ...] [--before]
  python tools/rhf_study.py speed [--compare] [--profile]   # 512x512 (tiled cornell 16 spp)
  python tools/rhf_study.py exact             # RHF, LP, oracle map == the before tree's

Buffers are cached in $RHF_STUDY_CACHE (default /tmp/rhf_study); --before,
--compare and exact load the pre-change tree holding $RHF_BEFORE (default
/work/before/core/rhf.py) as its own package.
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
    """The scene's cached frame-1 reference with the most samples in REFS."""
    import glob
    import re
    from cycles_adaptive.core.io import read_reference
    paths = glob.glob(os.path.join(REFS, f"{scene}.f0001.r100.s*.exr"))
    spp = lambda p: int(re.search(r"\.s(\d+)\.exr$", p).group(1))
    path = max(paths, key=spp) if paths else os.path.join(REFS, f"{scene}.f0001.r100.s1024.exr")
    return read_reference(path, shape)


BEFORE = os.environ.get("RHF_BEFORE", "/work/before/core/rhf.py")


def before_tree(path=BEFORE):
    """The whole pre-change tree holding ``path`` (its core/rhf.py; default
    /work/before, env RHF_BEFORE) imported as package ``rhf_before_tree``, so
    its rhf uses its own filters and parallel: {"rhf", "lp", "oracle"}
    modules."""
    import importlib
    root = os.path.dirname(os.path.dirname(os.path.abspath(path)))
    load_package("rhf_before_tree", root)
    return {m: importlib.import_module(f"rhf_before_tree.core.{m}") for m in ("rhf", "lp", "oracle")}


def before_rhf(path=BEFORE):
    """The pre-change ``core/rhf.py`` (``before_tree``)."""
    return before_tree(path)["rhf"]


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
    the pre-change tree's RHF (RHF_BEFORE), interleaved, and whether the
    current outputs equal its (``same_outputs``)."""
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
              f"{b['before'] / b['oidn_denoise']:.2f}, before / one OIDN call "
              f"{b['before'] / b['oidn_one']:.2f}); models {ro.info['models']}")
        print("RHF == before:", same_outputs(rhf, old, buf, res, ro))
    if profile:
        # on one thread: cProfile sees only the calling thread, not the pool's
        from cycles_adaptive.core import parallel
        parallel.set_threads(1)
        pr = cProfile.Profile()
        pr.enable()
        rp = rhf.reconstruct(buf)
        pr.disable()
        parallel.set_threads(None)
        print("one thread:", {k: round(v, 2) for k, v in rp.info.items() if k.startswith("seconds")})
        pstats.Stats(pr).sort_stats("tottime").print_stats(15)


def _max_rel(a, b):
    """Largest |a - b| / max(|a|, |b|) over the entries (0 where both are 0)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    den = np.maximum(np.abs(a), np.abs(b))
    return float(np.max(np.where(den > 0, np.abs(a - b) / np.where(den > 0, den, 1.0), 0.0),
                        initial=0.0))


def same_outputs(new, old, buf, rn=None, ro=None, budget_per_px=4):
    """Compare one method module against its pre-change copy on ``buf``:
    image, error, dimension and the sample map (``budget_per_px`` samples
    per pixel) -> {name: (np.array_equal, max relative difference)}."""
    rn = new.reconstruct(buf) if rn is None else rn
    ro = old.reconstruct(buf) if ro is None else ro
    budget = budget_per_px * buf.n.size
    mn = new.sample_map(buf, rn, budget, None, {})
    mo = old.sample_map(buf, ro, budget, None, {})
    out = {}
    for name, a, b in (("image", rn.image, ro.image), ("error", rn.error, ro.error),
                       ("dimension", np.float64(rn.dimension if rn.dimension is not None else np.nan),
                        np.float64(ro.dimension if ro.dimension is not None else np.nan)),
                       ("sample_map", mn, mo)):
        out[name] = (bool(np.array_equal(a, b, equal_nan=True)), _max_rel(a, b))
    return out


def exact(scenes=("soft_shadows", "glossy"), spp=16):
    """Bit-exactness of the current RHF, LP and oracle map against the
    pre-change tree (RHF_BEFORE): cornell tiled to 512x512 and ``scenes`` at
    their cached 128x128; prints np.array_equal and the max relative
    difference of every output."""
    from cycles_adaptive.core import lp, oracle
    bt = before_tree()
    inputs = [("cornell 512x512", tiled(load("cornell", spp)), "cornell")]
    inputs += [(f"{s} 128x128", load(s, spp), s) for s in scenes]
    ok = True
    from cycles_adaptive.core.filters import box_mean
    from cycles_adaptive.core.io import ImageFileError
    for label, buf, scene in inputs:
        try:
            ref = reference(scene, load(scene, spp).shape)
            ref = np.tile(ref, (buf.shape[0] // ref.shape[0], buf.shape[1] // ref.shape[1], 1))
        except ImageFileError:        # no cached reference: a fixed stand-in (same for both trees)
            ref = box_mean(buf.color.mean, 2)
            label += " (stand-in ref)"
        for name, new, old in (("rhf", rhf, bt["rhf"]), ("lp", lp, bt["lp"])):
            rn, ro = new.reconstruct(buf), old.reconstruct(buf)
            res = same_outputs(new, old, buf, rn, ro)
            on = oracle.oracle_map(rn.image, ref, buf.n, 4 * buf.n.size, rn.dimension)
            oo = bt["oracle"].oracle_map(ro.image, ref, buf.n, 4 * buf.n.size, ro.dimension)
            res["oracle_map"] = (bool(np.array_equal(on, oo)), _max_rel(on, oo))
            ok &= all(v[0] for v in res.values())
            print(f"{label:18s} {name:3s} " + "  ".join(
                f"{k} {'equal' if e else 'DIFF'} (max rel {d:.1e})" for k, (e, d) in res.items()),
                flush=True)
    print("all equal:", ok)
    return ok


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd", choices=("render", "quality", "speed", "exact"))
    ap.add_argument("--before", action="store_true", help="quality: the /work/before module")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--compare", action="store_true")
    ap.add_argument("--reps", type=int, default=2, help="speed: interleaved repeats")
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
    elif a.cmd == "exact":
        exact()
    else:
        speed(a.profile, a.compare, reps=a.reps)


if __name__ == "__main__":
    main()

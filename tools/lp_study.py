"""LP measurements (docs/notes/lp.md): the sample scenes' low-spp buffers
against references (/work/refs' renders, else private ones from ``refs``),
before/after a change of core/lp.py.

  python tools/lp_study.py render                      # cache buffers (8, 16 spp, 4 subsets)
  python tools/lp_study.py refs [--ref-spp 1024]       # private references where /work/refs has none
  python tools/lp_study.py quality [--before DIR] [--spps 8,16] [--scenes ...]
  python tools/lp_study.py speed [--before DIR]         # 512x512 (cornell 16 spp tiled 4x4)
  python tools/lp_study.py threads [--sizes 1920x1080,512x512,128x128] [--threads 1,2] [--repeats 3]
                                   [--method lp|rhf] [--min-pixels N] [--before DIR]

``quality`` prints one row per scene and spp: relMSE (input and LP), mean
brightness of the output relative to the sample mean, the smallest output (and
the reference there), the Pearson correlation of the estimated error map with
the true squared error per pixel and pooled over 8x8 blocks, the median ratio
of estimated to true error (8x8 blocks), the centres' radius histogram and the
seconds.  ``threads`` times LP's reconstruction and sample map (cornell 16 spp tiled to
each size) with each thread count, interleaved (size by size, repeat by repeat,
thread count by thread count), and prints the medians, the CPU seconds per
wall second and whether every thread count (and ``--before``'s LP) gave the
same bits.  ``--before DIR`` runs a second checkout's LP (e.g. /work/before) on
the same inputs.  Buffers come from ``$LP_STUDY_CACHE`` (default
/tmp/lp_study), or from tools/rhf_study.py's cache when that has them.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import pickle
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

load_package()
from cycles_adaptive.core import lp, metrics  # noqa: E402

CACHE = os.environ.get("LP_STUDY_CACHE", "/tmp/lp_study")
OTHER_CACHES = ("/tmp/rhf_study",)
SCENES = ("cornell", "soft_shadows", "glossy", "dof", "motion_blur", "animated")
REFS = "/work/refs"


def cache_path(scene, spp, seed=0, root=CACHE):
    return os.path.join(root, f"{scene}.s{spp}.seed{seed}.pkl")


def render(scenes, spps, seed=0, subsets=4):
    """Render each scene at each spp (``subsets`` sample subsets, LP's passes)
    with the benchmark's executor; pickles the Buffers."""
    import bpy
    from cycles_adaptive.addon.executor import CyclesExecutor
    from cycles_adaptive.bench import references as refs
    from cycles_adaptive.core.buffers import Buffers
    from cycles_adaptive.core.pipeline import render_subsets
    os.makedirs(CACHE, exist_ok=True)
    feats = ("normal", "albedo", "depth")
    for s in scenes:
        if all(find(s, spp, seed) for spp in spps):
            continue
        refs.open_scene(refs.scene_path(s), force=True)
        scene, vl = bpy.context.scene, bpy.context.view_layer
        scene.render.resolution_percentage = 100
        for spp in spps:
            if find(s, spp, seed):
                continue
            with CyclesExecutor(scene, vl, feats, seed=seed) as exe:
                h, w = exe.size
                buf = Buffers.empty(h, w, feats + ("alpha",))
                render_subsets(exe, buf, spp, subsets, scene.frame_current)
            with open(cache_path(s, spp, seed), "wb") as f:
                pickle.dump(buf, f)
            print(f"{s} {spp} spp -> {cache_path(s, spp, seed)}", flush=True)


def render_refs(scenes, spp=1024, seed=1):
    """Private references where /work/refs has none: ``spp`` samples of each
    scene with another seed than the inputs' (one subset), the colour mean
    saved as ``CACHE/<scene>.ref<spp>.npy``."""
    import bpy
    from cycles_adaptive.addon.executor import CyclesExecutor
    from cycles_adaptive.bench import references as refs
    from cycles_adaptive.core.buffers import Buffers
    from cycles_adaptive.core.pipeline import render_subsets
    os.makedirs(CACHE, exist_ok=True)
    for s in scenes:
        path = os.path.join(CACHE, f"{s}.ref{spp}.npy")
        if os.path.exists(path):
            continue
        refs.open_scene(refs.scene_path(s), force=True)
        scene, vl = bpy.context.scene, bpy.context.view_layer
        scene.render.resolution_percentage = 100
        t = time.perf_counter()
        with CyclesExecutor(scene, vl, (), seed=seed) as exe:
            h, w = exe.size
            buf = Buffers.empty(h, w, ("alpha",))
            render_subsets(exe, buf, spp, 1, scene.frame_current)
        np.save(path, buf.color.mean)
        print(f"{s} reference {spp} spp -> {path} ({time.perf_counter() - t:.0f} s)", flush=True)


def find(scene, spp, seed=0):
    for root in (CACHE,) + OTHER_CACHES:
        p = cache_path(scene, spp, seed, root)
        if os.path.exists(p):
            return p
    return None


def load(scene, spp, seed=0):
    with open(find(scene, spp, seed), "rb") as f:
        return pickle.load(f)


def reference(scene, shape):
    """(reference image, its name): /work/refs' 1024-spp render when there is
    one, else the private one of ``refs`` (CACHE/<scene>.ref<spp>.npy, the
    most samples), else (None, "none")."""
    from cycles_adaptive.core.io import read_reference
    import glob
    shared = sorted(glob.glob(os.path.join(REFS, f"{scene}.f0001.r100.s*.exr")),
                    key=lambda p: int(p.rsplit(".s", 1)[1].split(".")[0]))
    if shared:
        return read_reference(shared[-1], shape), os.path.basename(shared[-1])
    own = sorted(glob.glob(os.path.join(CACHE, f"{scene}.ref*.npy")),
                 key=lambda p: int(p.rsplit(".ref", 1)[1].split(".")[0]))
    if own:
        return np.load(own[-1]), os.path.basename(own[-1])
    return None, "none"


def load_before(root):
    """The lp module of another checkout, imported as its own package."""
    name = "lp_before_pkg"
    spec = importlib.util.spec_from_file_location(name, os.path.join(root, "__init__.py"),
                                                  submodule_search_locations=[root])
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return importlib.import_module(name + ".core.lp")


def pooled(x, s=8):
    """Mean over s x s blocks (trailing rows / columns cut)."""
    h, w = x.shape[0] // s * s, x.shape[1] // s * s
    return x[:h, :w].reshape(h // s, s, w // s, s).mean(axis=(1, 3))


def corr(a, b):
    a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else 0.0


def figures(res, y, ref):
    """relMSE, negatives, brightness and error-map figures of one result."""
    img = res.image
    true = ((img - ref) ** 2).mean(-1)
    at = np.unravel_index(np.argmin(img), img.shape)
    pe, pt = pooled(res.error), pooled(true)
    radii = getattr(getattr(res, "fit", None), "center_radius", None)
    radii = np.zeros((0, 3), np.int64) if radii is None else radii
    return {"relmse": metrics.relmse(img, ref), "input_relmse": metrics.relmse(y, ref),
            "neg_px": int((img < 0).any(-1).sum()), "min": float(img.min()), "ref_at_min": float(ref[at]),
            "bright": float(img.mean() / max(y.mean(), 1e-12) - 1.0),
            "corr": corr(res.error, true), "corr8": corr(pe, pt),
            "ratio8": float(np.median(pe / np.maximum(pt, 1e-12))),
            "radius_hist": np.bincount(radii.ravel(), minlength=10).tolist(),
            "centres": float(res.info.get("center_fraction", 0.0))}


def quality(mods, spps=(8, 16), scenes=SCENES):
    for s in scenes:
        for spp in spps:
            if not find(s, spp):
                print(f"{s} {spp}: no buffers (run `render`)")
                continue
            buf = load(s, spp)
            ref, ref_name = reference(s, buf.shape)
            if ref is None:
                print(f"{s} {spp}: no reference (run `refs`); relMSE and error figures are against the input")
                ref = buf.color.mean
            color, var, feats, fvars = lp._inputs(buf)
            for label, mod in mods:
                t = time.perf_counter()
                res = mod.denoise(color, var, feats, feature_var=fvars, n=buf.n)
                sec = time.perf_counter() - t
                f = figures(res, color, ref)
                print(f"{s:13s} {spp:3d} {label:6s} in {f['input_relmse']:.4f} lp {f['relmse']:.4f} "
                      f"bright {100 * f['bright']:+.2f}% min {f['min']:+.3f} (ref {f['ref_at_min']:.3f}) "
                      f"neg {f['neg_px']:4d} corr {f['corr']:.2f} corr8 {f['corr8']:.2f} "
                      f"est/true8 {f['ratio8']:.2f} centres {100 * f['centres']:.1f}% "
                      f"r {f['radius_hist']} {sec:.1f}s [{ref_name if ref is not buf.color.mean else 'no ref'}]",
                      flush=True)


def speed(mods, scene="cornell", spp=16, reps=4):
    """Seconds and traced peak memory (bytes per pixel, inputs excluded) of one
    reconstruction of a 512x512 frame: the scene's buffers tiled reps x reps."""
    import tracemalloc
    buf = load(scene, spp)
    color, var, feats, fvars = lp._inputs(buf)
    tile = lambda a: np.tile(a, (reps, reps) + (1,) * (a.ndim - 2))
    color, var, n = tile(color), tile(var), tile(buf.n)
    feats = {k: tile(v) for k, v in feats.items()}
    fvars = {k: tile(v) for k, v in fvars.items()}
    px = color.shape[0] * color.shape[1]
    for label, mod in mods:
        t = time.perf_counter()
        mod.denoise(color, var, feats, feature_var=fvars, n=n)
        sec = time.perf_counter() - t
        tracemalloc.start()
        mod.denoise(color, var, feats, feature_var=fvars, n=n)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        print(f"{label:6s} {color.shape[1]}x{color.shape[0]}: {sec:.2f} s ({sec / px * 1e6:.2f} s/MP), "
              f"peak {peak / px:.0f} B/px", flush=True)


def tiled_inputs(width, height, scene="cornell", spp=16):
    """LP's inputs of the scene's cached buffers tiled (and cropped) to
    width x height: realistic structure at any size."""
    buf = load(scene, spp)
    color, var, feats, fvars = lp._inputs(buf)

    def tile(a):
        reps = (-(-height // a.shape[0]), -(-width // a.shape[1])) + (1,) * (a.ndim - 2)
        return np.ascontiguousarray(np.tile(a, reps)[:height, :width])
    return tile(color), tile(var), {k: tile(v) for k, v in feats.items()}, \
        {k: tile(v) for k, v in fvars.items()}, tile(buf.n)


def threads(mods, sizes, counts, repeats=3, method="lp", min_pixels=None):
    """Median seconds of ``denoise`` (reconstruct on arrays) and of
    ``sample_map`` on its result per size and thread count, interleaved;
    ``method`` lp or rhf (``mods``' modules are then their rhf);
    ``min_pixels`` overrides the method's ``THREAD_MIN_PIXELS``."""
    from types import SimpleNamespace
    from cycles_adaptive.core import parallel, rhf
    mod_now = lp if method == "lp" else rhf
    if min_pixels is not None:
        mod_now.THREAD_MIN_PIXELS = int(min_pixels)
    for width, height in sizes:
        color, var, feats, fvars, n = tiled_inputs(width, height)
        if method == "rhf":                                   # rhf wants per-channel variances
            fvars = {k: np.repeat(v, feats[k].shape[-1], axis=-1) / feats[k].shape[-1] for k, v in fvars.items()}
        shim = SimpleNamespace(shape=(height, width), n=n)    # what sample_map reads of the buffers
        times = {c: [] for c in counts}
        cpu = {c: [] for c in counts}
        smap = {c: [] for c in counts}
        outputs = {}
        for _ in range(repeats):
            for c in counts:
                parallel.set_threads(c)
                t, p = time.perf_counter(), time.process_time()
                res = mod_now.denoise(color, var, feats, feature_var=fvars, n=n)
                sec = time.perf_counter() - t
                times[c].append(sec)
                cpu[c].append((time.process_time() - p) / max(sec, 1e-9))
                t = time.perf_counter()
                alloc = mod_now.sample_map(shim, res, 4 * width * height, None, {})
                smap[c].append(time.perf_counter() - t)
                outputs.setdefault(c, (res.image, res.error, alloc))
        parallel.set_threads(None)
        same = all(all(np.array_equal(a, b) for a, b in zip(outputs[counts[0]], outputs[c])) for c in counts)
        line = f"{method} {width}x{height}: " + ", ".join(
            f"{c} thr {np.median(times[c]):.2f} s (cpu/wall {np.median(cpu[c]):.2f}, sample_map "
            f"{np.median(smap[c]) * 1e3:.0f} ms)" for c in counts) + f"; identical across threads: {same}"
        for label, mod in mods:
            if mod is lp:
                continue
            if method == "rhf":
                mod = importlib.import_module(mod.__name__.rsplit(".", 1)[0] + ".rhf")
            t = time.perf_counter()
            old = mod.denoise(color, var, feats, feature_var=fvars, n=n)
            sec = time.perf_counter() - t
            ref = outputs[counts[0]]
            line += (f"; {label} {sec:.2f} s, identical to {label}: "
                     f"{np.array_equal(old.image, ref[0]) and np.array_equal(old.error, ref[1])}")
        print(line, flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("command", choices=("render", "refs", "quality", "speed", "threads"))
    ap.add_argument("--sizes", default="1920x1080,512x512,128x128", help="threads: WxH,...")
    ap.add_argument("--threads", default="1,2", help="threads: thread counts")
    ap.add_argument("--repeats", type=int, default=3, help="threads: interleaved repeats")
    ap.add_argument("--method", default="lp", choices=("lp", "rhf"), help="threads: which method")
    ap.add_argument("--min-pixels", type=int, default=None, help="threads: override THREAD_MIN_PIXELS")
    ap.add_argument("--ref-spp", type=int, default=1024, help="samples of the private references (refs)")
    ap.add_argument("--spps", default="8,16")
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--before", default=None, help="another checkout whose LP runs on the same inputs")
    a = ap.parse_args(argv)
    spps = tuple(int(x) for x in a.spps.split(","))
    if a.command == "render":
        render(a.scenes, spps)
        return 0
    if a.command == "refs":
        render_refs(a.scenes, a.ref_spp)
        return 0
    mods = ([("before", load_before(a.before))] if a.before else []) + [("after", lp)]
    if a.command == "speed":
        speed(mods)
        return 0
    if a.command == "threads":
        sizes = [tuple(int(v) for v in z.split("x")) for z in a.sizes.split(",")]
        threads(mods, sizes, [int(c) for c in a.threads.split(",")], a.repeats, a.method, a.min_pixels)
        return 0
    quality(mods, spps, a.scenes)
    return 0


if __name__ == "__main__":
    sys.exit(main())

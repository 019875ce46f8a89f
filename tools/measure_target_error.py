"""``--target-error`` on the sample scenes: for every (scene, method, target)
one ``render --target-error`` run against a cached reference, and its true
relMSE over the target, the spp it used, the number of error checks (one
reconstruction each) and whether the target was met by the run's estimate.

    .venv/bin/python tools/measure_target_error.py [--scenes cornell,dof,...]
        [--methods uniform,lp,oidn-uniform] [--targets 0.01,0.003] [--spp 128]
        [--reference-dir /work/refs] [--results /tmp/h7/after.json]
    .venv/bin/python tools/measure_target_error.py --compare BEFORE.json AFTER.json
    .venv/bin/python tools/measure_target_error.py --estimates [--scenes ...]

``oidn-uniform`` is ``--method oidn --no-oidn-adaptive`` (uniform sampling,
OIDN's dual-buffer error).  The results file keeps one JSON object per run
(appended as they finish, so an interrupted table keeps its rows, and a rerun
skips the rows already there); ``--compare`` prints the before/after table of
two such files.  The goal it reports: true relMSE within 1.5x of the target.

``--estimates`` (in this process, with bpy): per scene one uniform render
with checks at 4, 8, .. 128 spp; at each, the uniform, lp and oidn
reconstructions of the same samples, and their plain and robust estimated
relMSE (``core.metrics.estimated_relmse``, ``robust_relmse`` with 3 and 4
sigmas) over the true relMSE against the reference.
"""
import argparse
import glob
import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = "cornell,dof,soft_shadows,glossy,motion_blur,animated"
METHODS = "uniform,lp,oidn-uniform"
#: method label -> extra CLI arguments
METHOD_ARGS = {"oidn-uniform": ["--method", "oidn", "--no-oidn-adaptive"]}
GOAL = 1.5


def reference(scene, ref_dir):
    """The cached reference of ``scene`` with the most samples (None if none)."""
    found = glob.glob(os.path.join(ref_dir, f"{scene}.f0001.r100.s*.exr"))
    return max(found, key=lambda p: int(p.rsplit(".s", 1)[1].split(".")[0])) if found else None


def render(scene, method, target, args, ref):
    """One run: its JSON summary, or a dict with ``error`` on failure."""
    out = os.path.join(args.tmp, f"{scene}_{method}_{target:g}.exr")
    cmd = [os.path.join(ROOT, "cycles-adaptive"), "render", os.path.join(ROOT, "sample_blends", f"{scene}.blend"),
           *METHOD_ARGS.get(method, ["--method", method]), "--spp", str(args.spp), "--target-error", f"{target:g}",
           "--reference", ref, "--out", out, "--overwrite", "--json", "--quiet", "--no-preview"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    if r.returncode != 0 or not lines:
        return {"error": (r.stderr or r.stdout).strip().splitlines()[-1:] or ["no output"]}
    return json.loads(lines[-1])


def row(res):
    """The table's figures of one result: (true/target, spp, checks, estimate/true)."""
    s = res["summary"]
    if "error" in s:
        return None
    true = float(s.get("relmse", float("nan")))
    est = s.get("estimates") or []
    last = est[-1]["estimated_relmse"] if est else float("nan")
    return {"ratio": true / res["target"], "spp": float(s["spp_mean"]), "checks": len(est),
            "met": bool(s.get("target_met")), "true": true, "estimate": last,
            "seconds": float(s.get("total_seconds", float("nan")))}


def load(path):
    rows = {}
    if os.path.exists(path):
        with open(path) as f:
            for ln in f:
                if ln.strip():
                    r = json.loads(ln)
                    rows[(r["scene"], r["method"], r["target"])] = r
    return rows


def fmt(r):
    if r is None:
        return "failed"
    mark = "" if 1 / GOAL <= r["ratio"] <= GOAL else " **x**"
    reached = "" if r["met"] else ", not reached"
    return f"{r['ratio']:.2f}{mark} ({r['spp']:.0f} spp, {r['checks']} checks{reached})"


def compare(before_path, after_path):
    """Markdown: one row per (scene, method, target), before and after."""
    before, after = load(before_path), load(after_path)
    keys = sorted(set(before) | set(after), key=lambda k: (k[1], k[2], SCENES.split(",").index(k[0])
                                                           if k[0] in SCENES.split(",") else 99))
    print("| method | target | scene | before: true/target (spp, checks) | after: true/target (spp, checks) "
          "| after: stopping estimate/true |")
    print("|---|---|---|---|---|---|")
    met = {"before": 0, "after": 0}
    totals = {}  # method -> [checks before, checks after, spp before, spp after]
    for k in keys:
        b = row(before[k]) if k in before else None
        a = row(after[k]) if k in after else None
        for name, r in (("before", b), ("after", a)):
            met[name] += r is not None and 1 / GOAL <= r["ratio"] <= GOAL
        if b and a:
            t = totals.setdefault(k[1], [0, 0, 0.0, 0.0])
            t[0] += b["checks"]
            t[1] += a["checks"]
            t[2] += b["spp"]
            t[3] += a["spp"]
        # the estimate the run stopped on (at the final spp only when the target was met)
        ea = f"{a['estimate'] / a['true']:.2f}" if a and a["met"] and a["true"] > 0 else "-"
        print(f"| {k[1]} | {k[2]:g} | {k[0]} | {fmt(b) if k in before else '-'} | "
              f"{fmt(a) if k in after else '-'} | {ea} |")
    print(f"\nwithin {GOAL}x of the target: before {met['before']}/{len(keys)}, after {met['after']}/{len(keys)}")
    for m, (cb, ca, sb, sa) in totals.items():
        print(f"{m}: checks before {cb}, after {ca}; spp summed before {sb:.0f}, after {sa:.0f}")


ESTIMATE_SPP = (4, 16, 32, 64, 128)


def estimates_table(scenes, ref_dir):
    """Markdown: estimate / true relMSE per scene, reconstruction and spp."""
    sys.path.insert(0, ROOT)
    from launch import load_package
    load_package()
    import bpy
    from cycles_adaptive.addon import executor as ex
    from cycles_adaptive.core import lp, metrics, oidn, uniform
    from cycles_adaptive.core.pipeline import AdaptiveRun, Options
    from cycles_adaptive.operators.job import load_reference
    recs = (("uniform", uniform), ("lp", lp), ("oidn-uniform", oidn.UNIFORM))
    passes = tuple(dict.fromkeys(tuple(lp.PASSES) + tuple(oidn.PASSES)))
    print("plain / robust (3 sigmas) / robust (4 sigmas), each over the true relMSE\n")
    print("| scene | reconstruction | " + " | ".join(f"{n} spp" for n in ESTIMATE_SPP) + " |")
    print("|---|---|" + "---|" * len(ESTIMATE_SPP))
    for scene_name in scenes:
        ref_path = reference(scene_name, ref_dir)
        if ref_path is None:
            continue
        bpy.ops.wm.open_mainfile(filepath=os.path.join(ROOT, "sample_blends", f"{scene_name}.blend"))
        scene = bpy.context.scene
        cells = {name: {} for name, _ in recs}
        with ex.CyclesExecutor(scene, bpy.context.view_layer, passes, seed=0) as exe:
            ref = load_reference(ref_path, exe.size)[..., :3]
            # a target never reached: checks at 4, 8, .. and a ceiling past 128 so 128 is checked
            run = AdaptiveRun(exe, Options(method="uniform", spp=2 * max(ESTIMATE_SPP), frame=1,
                                           target_error=1e-12, features=passes))
            check = run._target_reached

            def measured():
                spp = int(round(run.samples_rendered / run.pixels))
                if spp in ESTIMATE_SPP:
                    for name, m in recs:
                        r = m.reconstruct(run.buffers, None)
                        t = metrics.relmse(r.image, ref)
                        cells[name][spp] = " / ".join(f"{f(r.image, r.error) / t:.2g}" for f in (
                            metrics.estimated_relmse, lambda i, e: metrics.robust_relmse(i, e, 3.0),
                            lambda i, e: metrics.robust_relmse(i, e, 4.0)))
                return (yield from check())
            run._target_reached = measured
            for _ in run.steps():
                if run.samples_rendered > max(ESTIMATE_SPP) * run.pixels:
                    break
        for name, _ in recs:
            print(f"| {scene_name} | {name} | " + " | ".join(cells[name].get(n, "-") for n in ESTIMATE_SPP) + " |",
                  flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default=SCENES)
    ap.add_argument("--methods", default=METHODS)
    ap.add_argument("--targets", default="0.01,0.003")
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--reference-dir", default="/work/refs")
    ap.add_argument("--results", default="/tmp/h7/results.json", help="JSON lines, appended")
    ap.add_argument("--tmp", default="/tmp/h7", help="folder of the rendered EXRs")
    ap.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"))
    ap.add_argument("--estimates", action="store_true", help="the estimate / true table (needs bpy)")
    args = ap.parse_args()
    if args.compare:
        compare(*args.compare)
        return
    if args.estimates:
        estimates_table(args.scenes.split(","), args.reference_dir)
        return
    os.makedirs(args.tmp, exist_ok=True)
    done = load(args.results)
    for target in [float(t) for t in args.targets.split(",")]:
        for method in args.methods.split(","):
            for scene in args.scenes.split(","):
                if (scene, method, target) in done:
                    continue
                ref = reference(scene, args.reference_dir)
                if ref is None:
                    print(f"{scene}: no reference in {args.reference_dir}", file=sys.stderr)
                    continue
                res = {"scene": scene, "method": method, "target": target,
                       "summary": render(scene, method, target, args, ref)}
                with open(args.results, "a") as f:
                    f.write(json.dumps(res) + "\n")
                print(f"{method} {target:g} {scene}: {fmt(row(res))}", flush=True)


if __name__ == "__main__":
    main()

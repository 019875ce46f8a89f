"""LP seams and brightness (docs/notes/lp.md, "2026-12-02: seams and brightness").

  python tools/lp_seams.py seams [--before DIR] [--seeds 0,1,2]
  python tools/lp_seams.py cli --tag NAME [--tree DIR] [--spps 8,16] [--scenes ...]
  python tools/lp_seams.py table TAG_BEFORE TAG_AFTER

``seams`` prints, on the synthetic seam scene of tests/core/test_lp_windows.py
(a smooth gradient with a 4x-sample region on the left half; noisy and
noise-free input, same claimed variance), the border / interior ratio of the
second difference of (output - truth) next to window borders
(``border_excess``), the same ratio for the region boundary columns (the two
columns next to x = W/2) against the rest (``region_excess``), the MSE
against the truth, the centre count, and the brightness (mean output / mean
input - 1) on the highlight scene of the tests (a dark wall with a one-pixel
highlight the features do not explain).  ``--before DIR`` runs another checkout's
LP on the same inputs.

``cli`` runs ``DIR/cycles-adaptive render <scene>.blend --method lp --spp N
--seed 0 --reference /work/refs/<ref>`` (128x128, the project's .venv) for each
scene and spp, writes ``/tmp/h6/<tag>/<scene>.s<N>.exr`` and a JSON line per
run to ``/tmp/h6/<tag>/runs.jsonl``: relMSE and the mean brightness of the
result (EXR ``Combined``) relative to the sample mean (``Noisy``).  ``table``
prints the two tags side by side.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tests", "core"))
from launch import load_package  # noqa: E402

load_package()
from cycles_adaptive.core import lp  # noqa: E402

SCENES = ("cornell", "dof", "soft_shadows", "glossy", "motion_blur", "animated")
REFS = "/work/refs"
OUT = "/tmp/h6"
PY = os.path.join(ROOT, ".venv", "bin", "python")


def reference_path(scene):
    refs = sorted(glob.glob(os.path.join(REFS, f"{scene}.f0001.r100.s*.exr")))
    return refs[-1] if refs else None


def cli(tag, tree, spps, scenes):
    from cycles_adaptive.core.io import read_layers
    out_dir = os.path.join(OUT, tag)
    os.makedirs(out_dir, exist_ok=True)
    env = dict(os.environ, CYCLES_ADAPTIVE_PYTHON=PY)
    with open(os.path.join(out_dir, "runs.jsonl"), "a") as log:
        for scene in scenes:
            for spp in spps:
                exr = os.path.join(out_dir, f"{scene}.s{spp}.exr")
                cmd = [os.path.join(tree, "cycles-adaptive"), "render",
                       os.path.join(tree, "sample_blends", f"{scene}.blend"), "--method", "lp",
                       "--spp", str(spp), "--seed", "0", "--reference", reference_path(scene),
                       "--out", exr, "--overwrite", "--json", "--quiet"]
                run = subprocess.run(cmd, capture_output=True, text=True, env=env)
                lines = [ln for ln in run.stdout.splitlines() if ln.startswith("{")]
                if run.returncode or not lines:
                    print(f"{scene} {spp}: failed ({run.returncode}) {run.stderr[-500:]}", flush=True)
                    continue
                res = json.loads(lines[-1])
                layers, _ = read_layers(exr)
                noisy = np.asarray(layers["Noisy"][..., :3], np.float64)
                comb = np.asarray(layers["Combined"][..., :3], np.float64)
                row = {"scene": scene, "spp": spp, "relmse": res["relmse"],
                       "bright": float(comb.mean() / max(noisy.mean(), 1e-12) - 1.0),
                       "centers": res.get("center_fraction"), "seconds": res.get("total_seconds")}
                log.write(json.dumps(row) + "\n")
                log.flush()
                print(f"{scene:13s} {spp:3d} relMSE {row['relmse']:.5f} bright {100 * row['bright']:+.2f}% "
                      f"centres {100 * (row['centers'] or 0):.1f}%", flush=True)


def table(before, after):
    def rows(tag):
        out = {}
        with open(os.path.join(OUT, tag, "runs.jsonl")) as f:
            for line in f:
                r = json.loads(line)
                out[(r["scene"], r["spp"])] = r
        return out
    a, b = rows(before), rows(after)
    print("| scene spp | relMSE before -> after | change | brightness before -> after |")
    print("|---|---|---|---|")
    for key in sorted(set(a) & set(b), key=lambda k: (SCENES.index(k[0]), k[1])):
        ra, rb = a[key], b[key]
        print(f"| {key[0]} {key[1]} | {ra['relmse']:.5f} -> {rb['relmse']:.5f} | "
              f"{100 * (rb['relmse'] / ra['relmse'] - 1):+.1f} % | "
              f"{100 * ra['bright']:+.2f} -> {100 * rb['bright']:+.2f} % |")


def seams(mods, seeds):
    """Border / interior and region-column ratios and MSE on the seam scene,
    brightness on the highlight scene, per module and seed."""
    import test_lp_windows as tw
    for label, mod in mods:
        for seed in seeds:
            truth, color, var, feats = tw.seam_scene(seed=seed)
            figs = []
            for clean in (False, True):
                fit = mod.fit(truth if clean else color, var, feats, None, None, mod.Params())
                figs.append((tw.border_excess(fit, truth), tw.region_excess(fit, truth),
                             float(((fit.image - truth) ** 2).mean()), len(fit.centers)))
            htruth, hbuf = tw.highlight_scene(seed)
            out = mod.reconstruct(hbuf).image
            bright = 100 * (out.mean() / hbuf.color.mean.mean() - 1)
            (bn, rn, mn, cn), (bc, rc, mc, cc) = figs
            print(f"{label:6s} seed {seed}: border/interior noisy {bn:.2f} clean {bc:.2f}; "
                  f"region column noisy {rn:.2f} clean {rc:.2f}; mse noisy {mn:.3e} clean {mc:.3e}; "
                  f"centres {cn} / {cc}; highlight scene brightness {bright:+.2f}% "
                  f"(highlight {out[20, 30].mean():.2f}, truth {htruth[20, 30].mean():.2f})", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("command", choices=("seams", "cli", "table"))
    ap.add_argument("tags", nargs="*")
    ap.add_argument("--tag", default="after")
    ap.add_argument("--tree", default=ROOT)
    ap.add_argument("--spps", default="8,16")
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--before", default=None)
    a = ap.parse_args(argv)
    if a.command == "cli":
        cli(a.tag, os.path.abspath(a.tree), [int(s) for s in a.spps.split(",")], a.scenes)
    elif a.command == "table":
        table(*a.tags)
    else:
        from lp_study import load_before  # another checkout's LP, as lp_study imports it
        mods = ([("before", load_before(a.before))] if a.before else []) + [("after", lp)]
        seams(mods, [int(s) for s in a.seeds.split(",")])
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Measure auto's predictions offline.

``dump``: render each scene's initial pass in-process (the CLI's ``render``
with ``--method auto``) and keep what :func:`core.auto.select` receives (the
crops' subsets, the Context, the relative variance) plus the whole frame's
subsets, in one pickle per scene.  ``predict``: run ``select`` of a code tree
(``--root``, e.g. a copy of the committed tree) on the dumps at each budget,
and compare each candidate's prediction with its true relMSE from a bench
results JSON (``--bench``, the runs at each budget) and, at half the initial
samples, with the reference (each reconstruction of half A scored against the
reference on the scored crops and on the whole frame).

    .venv/bin/python tools/measure_auto.py dump --out /tmp/dumps
    .venv/bin/python tools/measure_auto.py predict --dumps /tmp/dumps --bench B.json --root /tmp/before
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import pickle
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

SCENES = "cornell,dof,soft_shadows,glossy,motion_blur,animated"


def reference(refs: str, scene: str) -> str:
    return sorted(glob.glob(os.path.join(refs, f"{scene}.f0001.*.exr")))[0]


def dump(a):
    pkg = load_package("cycles_adaptive", ROOT)
    from cycles_adaptive.core import auto
    from cycles_adaptive.operators import cli
    os.makedirs(a.out, exist_ok=True)
    orig_regions, orig_select = auto.cv_regions, auto.select
    box = {}

    def regions(h, w, p=None):
        return list(orig_regions(h, w, p)) + [(0, 0, int(w), int(h))]  # the whole frame last

    def select(crops, data, ctx, rel_var, params=None, height=None, width=None):
        box.update(crops=crops[:-1], data=data[:-1], full=data[-1], ctx=ctx.__dict__.copy(),
                   rel_var=np.asarray(rel_var), height=height, width=width)
        return orig_select(crops[:-1], data[:-1], ctx, rel_var, params, height, width)

    auto.cv_regions, auto.select = regions, select
    del pkg
    for scene in a.scenes.split(","):
        box.clear()
        cli.main(["render", os.path.join(ROOT, "sample_blends", f"{scene}.blend"), "--method", "auto",
                  "--spp", "16", "--quiet", "--out", f"/tmp/measure_auto_{scene}.exr"])
        box["reference"] = reference(a.refs, scene)
        with open(os.path.join(a.out, f"{scene}.pkl"), "wb") as fh:
            pickle.dump(box, fh)
        print("dumped", scene, flush=True)


#: the bench's run names of auto's candidate labels where they differ
BENCH_NAMES = {"oidn-uniform": "uniform-oidn"}


def bench_truth(path: str) -> dict:
    """(scene, spp) -> {candidate label: true relMSE} from a bench results.json."""
    with open(path) as fh:
        d = json.load(fh)
    back = {v: k for k, v in BENCH_NAMES.items()}
    out = {}
    for scene, v in d["scenes"].items():
        for r in v.get("runs", []):
            if r.get("relmse") is None:
                continue
            out.setdefault((scene, int(r["budget"])), {})[back.get(r["name"], r["name"])] = float(r["relmse"])
    return out


def predict(a):
    load_package("auto_tree", a.root)
    from auto_tree.core import auto
    from auto_tree.core.io import read_reference
    truth = bench_truth(a.bench) if a.bench else {}
    table = []
    for scene in a.scenes.split(","):
        with open(os.path.join(a.dumps, f"{scene}.pkl"), "rb") as fh:
            box = pickle.load(fh)
        ref = read_reference(box["reference"], (box["height"], box["width"]))[..., :3]
        params = auto.Params(**({"cv_share": a.cv_share} if a.cv_share is not None else {}))
        # the tree's own tiles, cut from the whole frame's subsets as the pipeline cuts them
        crops = auto.cv_regions(box["height"], box["width"], params)
        data = [[(c[y0:y1, x0:x1], {k: v[y0:y1, x0:x1] for k, v in f.items()}, n) for c, f, n in box["full"]]
                for x0, y0, x1, y1 in crops]
        for spp in [int(b) for b in a.budgets.split(",")]:
            ctx = auto.Context(**{**box["ctx"], "spp": float(spp)})
            t0 = time.perf_counter()
            sel = auto.select(crops, data, ctx, box["rel_var"], params, box["height"], box["width"])
            secs = time.perf_counter() - t0
            true = truth.get((scene, spp), {})
            rows = sel.report["candidates"]
            best_true = min((true[r["name"]] for r in rows if r["name"] in true), default=None)
            line = {"scene": scene, "spp": spp, "chosen": sel.report["chosen"], "seconds": secs,
                    "tiles": sel.report.get("tiles"),
                    "chosen_true": true.get(sel.report["chosen"]), "best_true": best_true,
                    "best": min((r["name"] for r in rows if r["name"] in true), key=lambda n: true[n],
                                default=None),
                    "candidates": {r["name"]: (r["relmse"], true.get(r["name"])) for r in rows}}
            table.append(line)
            print(f"{scene:13s} {spp:3d} chose {line['chosen']:13s} true {line['chosen_true'] or 0:.2e} "
                  f"best {line['best']} {best_true or 0:.2e} ({secs:.2f} s, {line['tiles']} tiles)")
            for name, (p, t) in sorted(line["candidates"].items()):
                ratio = f"{p / t:5.2f}" if t else "  -  "
                print(f"    {name:13s} pred {p:.2e} true {t or 0:.2e} pred/true {ratio}")
        if a.half:
            half_truth(auto, box, ref)
    if a.out:
        with open(a.out, "w") as fh:
            json.dump(table, fh, indent=1)


def half_truth(auto, box, ref):
    """Each reconstruction of half A (and B) at n/2 scored against the
    reference, on the whole frame and on each crop, beside the CV estimate
    of the same crop (the estimator's bias apart from the rate)."""
    from auto_tree.core.metrics import relative_squared_error
    h, w = box["height"], box["width"]
    full = box["full"]
    feats = list(full[0][1])
    names = [n for n in auto.RECONSTRUCTIONS]
    fa, fb = auto._halves(full, feats)
    err_full = {}
    for name in names:
        imgs = [fa.color.mean, fb.color.mean] if name == "mean" else \
            [auto._image(auto._reconstruct(name, b)) for b in (fa, fb)]
        err_full[name] = [relative_squared_error(i, ref) for i in imgs]
    print("   half-budget (2 spp) true relMSE, whole frame: " +
          " ".join(f"{n} {0.5 * (e[0].mean() + e[1].mean()):.2e}" for n, e in err_full.items()))
    for crop, subs in zip(box["crops"], box["data"]):
        x0, y0, x1, y1 = crop
        iy, ix = auto._interior(crop, h, w)
        s = auto.score_tile(subs, crop, h, w, names, box["ctx"]["exponent"])
        parts = []
        for n in names:
            t = 0.5 * (err_full[n][0][y0:y1, x0:x1][iy, ix].mean() + err_full[n][1][y0:y1, x0:x1][iy, ix].mean())
            parts.append(f"{n} cv {float(np.mean(s[n]['terms'])):.1e}/true {t:.1e}")
        print(f"   crop {crop}: " + "  ".join(parts))


def main(argv=None):
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("dump")
    d.add_argument("--scenes", default=SCENES)
    d.add_argument("--refs", default="/work/refs")
    d.add_argument("--out", required=True)
    p = sub.add_parser("predict")
    p.add_argument("--scenes", default=SCENES)
    p.add_argument("--budgets", default="8,16")
    p.add_argument("--dumps", required=True)
    p.add_argument("--bench", default=None)
    p.add_argument("--root", default=ROOT)
    p.add_argument("--cv-share", type=float, default=None)
    p.add_argument("--half", action="store_true", help="also score each reconstruction at n/2 on the reference")
    p.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    return dump(a) if a.cmd == "dump" else predict(a)


if __name__ == "__main__":
    sys.exit(main())

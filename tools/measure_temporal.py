"""Per-frame relMSE and total time on the animated sample scene for
independent frames, reprojection and LP's temporal extension, at equal rendered
samples per frame; with both ``lp none`` and ``lp lp`` among the cases, also the
per-frame ratio of LP temporal to per-frame LP and how many frames got worse.

    .venv/bin/python tools/measure_temporal.py [--frames 1-8] [--spp 8] [--percentage 50]
        [--cases var:none,var:reproject,lp:none,lp:reproject,lp:lp] [--reference-spp 1024]

Needs the references (cached):
    ./cycles-adaptive references --scenes animated --frames 1-8 --resolution-percentage 50
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

load_package()
from cycles_adaptive.bench import references as refs  # noqa: E402

SCENE = "animated"
CASES = "var:none,var:reproject,lp:none,lp:reproject,lp:lp"
#: per-frame counters of LP temporal reported under the table (fractions of the pixels)
TEMPORAL_INFO = ("carried", "reset_position", "reset_residual", "reset_samples", "fallback")


def render_case(method, temporal, args, ref, tmp):
    """One ``render --frames`` run: (per-frame JSON lines, the range's summary) or None on failure."""
    out = os.path.join(tmp, f"{method}_{temporal}_####.exr")
    cmd = [os.path.join(ROOT, "cycles-adaptive"), "render", refs.scene_path(SCENE),
           "--frames", args.frames,
           "--method", method, "--temporal", temporal, "--spp", args.spp,
           "--resolution-percentage", args.percentage, "--out", out, "--reference", ref,
           "--json", "--quiet", "--no-preview"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        print(r.stderr, file=sys.stderr)
        return None
    lines = [json.loads(ln) for ln in r.stdout.splitlines() if ln.startswith("{")]
    return lines[:-1], lines[-1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", default="1-8")
    ap.add_argument("--spp", default="8")
    ap.add_argument("--percentage", default="50")
    ap.add_argument("--cases", default=CASES, help="comma-separated method:temporal pairs")
    ap.add_argument("--reference-dir", default=None, help="reference cache (default references/)")
    ap.add_argument("--reference-spp", type=int, default=refs.DEFAULT_SPP)
    args = ap.parse_args()
    cases = [tuple(c.split(":")) for c in args.cases.split(",") if c.strip()]
    ref = refs.reference_pattern(SCENE, int(args.percentage), args.reference_spp, args.reference_dir)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for method, temporal in cases:
            got = render_case(method, temporal, args, ref, tmp)
            if got is None:
                return 1
            rows.append((method, temporal) + got)
    frames = [f["frame"] for f in rows[0][2]]
    print("| method | temporal | " + " | ".join(f"f{f}" for f in frames) + " | mean relMSE | total s | "
          "rendered spp/frame | reprojected pixels per frame |")
    print("|---|---|" + "---|" * (len(frames) + 4))
    by_case = {}
    for method, temporal, per, summ in rows:
        by_case[(method, temporal)] = per
        rel = " | ".join(f"{x['relmse']:.4f}" for x in per)
        rendered = sum(x["samples"] for x in per) / sum(x["width"] * x["height"] for x in per)
        repro = ", ".join(f"{100 * x['reprojected_fraction']:.0f}%" for x in per)
        print(f"| {method} | {temporal} | {rel} | {summ.get('relmse_mean', float('nan')):.4f} | "
              f"{summ['total_seconds']:.2f} | {rendered:.2f} | {repro} |")
    if ("lp", "none") in by_case and ("lp", "lp") in by_case:
        alone, temp = by_case[("lp", "none")], by_case[("lp", "lp")]
        ratios = [t["relmse"] / a["relmse"] if a["relmse"] > 0 else float("inf") for a, t in zip(alone, temp)]
        print()
        print("| LP temporal / per-frame LP | " + " | ".join(f"f{f}" for f in frames) + " | frames worse |")
        print("|---|" + "---|" * (len(frames) + 1))
        print("| relMSE ratio | " + " | ".join(f"{r:.3f}" for r in ratios) +
              f" | {sum(r > 1 for r in ratios)} of {len(ratios)} |")
        for key in TEMPORAL_INFO:
            vals = [t.get(f"temporal_{key}") for t in temp]
            if all(v is not None for v in vals):
                print(f"| {key} | " + " | ".join(f"{100 * v:.1f}%" for v in vals) + " | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Per-frame relMSE and total time on the animated sample scene for
independent frames, reprojection and LP's temporal extension, at equal rendered
samples per frame.

    .venv/bin/python tools/measure_temporal.py [--frames 1-8] [--spp 8] [--percentage 50]

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
CASES = [("var", "none"), ("var", "reproject"), ("lp", "none"), ("lp", "reproject"), ("lp", "lp")]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", default="1-8")
    ap.add_argument("--spp", default="8")
    ap.add_argument("--percentage", default="50")
    ap.add_argument("--reference-dir", default=None, help="reference cache (default references/)")
    args = ap.parse_args()
    ref = refs.reference_pattern(SCENE, int(args.percentage), refs.DEFAULT_SPP, args.reference_dir)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for method, temporal in CASES:
            out = os.path.join(tmp, f"{method}_{temporal}_####.exr")
            cmd = [os.path.join(ROOT, "cycles-adaptive"), "render", refs.scene_path(SCENE),
                   "--frames", args.frames,
                   "--method", method, "--temporal", temporal, "--spp", args.spp,
                   "--resolution-percentage", args.percentage, "--out", out, "--reference", ref,
                   "--json", "--quiet", "--no-preview"]
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode != 0:
                print(r.stderr, file=sys.stderr)
                return 1
            lines = [json.loads(ln) for ln in r.stdout.splitlines() if ln.startswith("{")]
            rows.append((method, temporal, lines[:-1], lines[-1]))
    frames = [f["frame"] for f in rows[0][2]]
    print("| method | temporal | " + " | ".join(f"f{f}" for f in frames) + " | mean relMSE | total s | "
          "rendered spp/frame | reprojected pixels per frame |")
    print("|---|---|" + "---|" * (len(frames) + 4))
    for method, temporal, per, summ in rows:
        rel = " | ".join(f"{x['relmse']:.4f}" for x in per)
        rendered = sum(x["samples"] for x in per) / sum(x["width"] * x["height"] for x in per)
        repro = ", ".join(f"{100 * x['reprojected_fraction']:.0f}%" for x in per)
        print(f"| {method} | {temporal} | {rel} | {summ.get('relmse_mean', float('nan')):.4f} | "
              f"{summ['total_seconds']:.2f} | {rendered:.2f} | {repro} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

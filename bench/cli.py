"""The developer commands ``./cycles-adaptive bench`` and ``./cycles-adaptive
references``: arguments, the validated session settings and the entry points.

The repository's launcher (``launch.py``) hands :data:`COMMANDS` to
:func:`operators.cli.main`; the built extension ships without this package.

``bench`` measures the speed/accuracy trade per scene against what artists use
today (:mod:`bench.session`); every figure the README quotes comes from it.
Figures: relMSE = mean (x - r)^2 / (r^2 + 0.01); SMAPE; efficiency =
1 / (relMSE x seconds); equal-error speed-up (:mod:`bench.targets`).
"""
from __future__ import annotations

import json
import os
import sys
from typing import Callable, NamedTuple

from ..core import methods as methods_registry
from . import references as refs
from . import sequence
from .report import write_outputs
from .session import Session

DEFAULT_BUDGETS = (4, 8, 16, 32)
DEFAULT_METHODS = ("uniform", "var", "awr", "lp", "rhf")
DEFAULT_OUT = os.path.join(refs.ROOT, "bench_out")

QUICK = {"scenes": "cornell", "budgets": "8", "resolution_percentage": 25, "uniform_spp": "4,8,32",
         "scaling_percentages": "25,50", "max_samples_factor": 8, "reference_floor": "none"}
#: the references' noise-floor target (relMSE of a perfect image against them);
#: results.md checks it against 1/10 of the smallest error scored (docs/notes/references.md)
DEFAULT_REFERENCE_FLOOR = 1.5e-4
DEFAULT_SCALING = "200,400,800"  # of a 128-pixel scene: 256^2, 512^2, 1024^2 = 0.066, 0.26, 1.05 MP


class BenchError(Exception):
    """Bad benchmark input; one line for the user."""


def add_arguments(p) -> None:
    """The flags of ``./cycles-adaptive bench``."""
    p.add_argument("--scenes", help="comma-separated sample scenes (default: all of sample_blends/)")
    p.add_argument("--methods", help=f"comma-separated methods (default {','.join(DEFAULT_METHODS)})")
    p.add_argument("--budgets", help="comma-separated mean spp budgets (default 4,8,16,32)")
    p.add_argument("--out", default=None, help="output folder (default bench_out/ in the repo)")
    p.add_argument("--quick", action="store_true", help="smallest useful run: cornell at 25%% "
                   "(32x32), budget 8, every method, oracles, uniform-sampling runs and peers, "
                   "uniform at 4/8/32 spp, "
                   "a tiny scaling section; under a minute on 2 cores")
    p.add_argument("--resolution-percentage", type=int, default=None,
                   help="render the scenes at this %% (default 100; --quick: 25)")
    p.add_argument("--uniform-spp", help="spp of the plain uniform renders of the t_uniform(e) "
                   "curve (default: the budgets plus 2x and 4x the largest)")
    p.add_argument("--reference-spp", type=int, default=refs.DEFAULT_SPP, help="spp of each reference "
                   f"(with --reference-floor: the spp it starts from; default {refs.DEFAULT_SPP})")
    p.add_argument("--reference-floor", default=None, help="render each reference, doubling its spp, "
                   "until its noise floor (two independent halves) is below this relMSE "
                   f"(default {DEFAULT_REFERENCE_FLOOR:g}; --quick: none; 'none': exactly "
                   "--reference-spp)")
    p.add_argument("--reference-max-spp", type=int, default=refs.DEFAULT_MAX_SPP,
                   help=f"cap of --reference-floor (default {refs.DEFAULT_MAX_SPP})")
    p.add_argument("--reference-dir", default=None, help="reference cache (default references/)")
    p.add_argument("--no-render-references", action="store_true",
                   help="fail instead of rendering a missing reference")
    p.add_argument("--no-oracle", action="store_true", help="skip the oracle runs")
    p.add_argument("--oracle-budgets", help="budgets of the oracle and uniform-sampling runs "
                   "(default: all budgets)")
    p.add_argument("--no-uniform-sampling", action="store_true", help="skip the uniform-<method> "
                   "runs (each adaptive method's reconstruction on uniformly rendered samples)")
    p.add_argument("--no-peers", action="store_true", help="skip OIDN and Cycles adaptive sampling")
    p.add_argument("--scaling-percentages", default=None,
                   help="resolution %% of the first scene for the scaling section, comma-separated "
                        f"(default {DEFAULT_SCALING}; 'none' skips it)")
    p.add_argument("--scaling-methods", help="methods of the scaling section (default: --methods "
                   "without uniform)")
    p.add_argument("--scaling-memory-mp", type=float, default=0.3, help="measure traced memory "
                   "(a second, untimed reconstruct) only up to this many megapixels (default 0.3)")
    p.add_argument("--scaling-max-seconds", type=float, default=120.0, help="skip a method at a "
                   "size when its time, extrapolated linearly in pixels from the previous size, "
                   "would exceed this (default 120)")
    p.add_argument("--max-samples-factor", type=int, default=None, help="Cycles adaptive sampling "
                   "peer: max samples = this x the largest budget, the threshold decides the rest "
                   "(default 16; --quick: 8)")
    p.add_argument("--run-max-seconds", type=float, default=60.0, help="safety cap of one run of "
                   "our loop: a run that reaches it is stopped like a cancel (between two steps), is "
                   "flagged partial and keeps the samples it has (default 60; 0: none); not the "
                   "planned --max-seconds of render, which would change what is measured")
    p.add_argument("--seed", type=int, default=0, help="Cycles seed of the runs (not the references')")
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")


def _ints(text, what) -> list:
    """``"4,8"`` -> sorted distinct positive ints; BenchError naming ``--what``."""
    try:
        vals = [int(float(v)) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise BenchError(f"--{what}: cannot read {text!r} (comma-separated numbers)") from None
    if not vals or any(v < 1 for v in vals):
        raise BenchError(f"--{what}: give positive whole numbers, got {text!r}")
    return sorted(set(vals))


def _reference_floor(text) -> float | None:
    """``--reference-floor``: None (default) -> ``DEFAULT_REFERENCE_FLOOR``;
    ``"none"`` -> None (fixed spp); else a relMSE > 0."""
    if text is None:
        return DEFAULT_REFERENCE_FLOOR
    if str(text).strip().lower() == "none":
        return None
    try:
        v = float(text)
    except ValueError:
        raise BenchError(f"--reference-floor: cannot read {text!r} (a relMSE such as 1.5e-4, or none)") from None
    if not v > 0 or not v < float("inf"):
        raise BenchError(f"--reference-floor must be a relMSE > 0, got {text!r}")
    return v


def resolve_config(args) -> dict:
    """Validated settings of one session (presets applied, CLI values win)."""
    q = QUICK if args.quick else {}
    budgets = _ints(args.budgets or q.get("budgets") or ",".join(map(str, DEFAULT_BUDGETS)), "budgets")
    names = [m.strip() for m in (args.methods or ",".join(DEFAULT_METHODS)).split(",") if m.strip()]
    for m in names:
        if m not in methods_registry.METHODS:
            raise BenchError(f"unknown method {m!r}; choose from {', '.join(methods_registry.METHODS)}")
    try:
        scenes = refs.scene_names(args.scenes or q.get("scenes"))
    except ValueError as exc:
        raise BenchError(str(exc)) from None
    pct = args.resolution_percentage or q.get("resolution_percentage") or 100
    if not 1 <= pct <= 10000:
        raise BenchError("--resolution-percentage must be between 1 and 10000")
    if args.uniform_spp or q.get("uniform_spp"):
        uniform = _ints(args.uniform_spp or q["uniform_spp"], "uniform-spp")
    else:
        uniform = sorted(set(budgets) | {2 * max(budgets), 4 * max(budgets)})
    if len(uniform) < 2:
        raise BenchError("--uniform-spp: need at least two levels for the t_uniform(e) curve")
    if args.reference_spp < 1024:
        print(f"[bench] note: references at {args.reference_spp} spp (< 1024): relMSE below the "
              "reference's own noise floor is not measurable", file=sys.stderr)
    floor = _reference_floor(getattr(args, "reference_floor", None) or q.get("reference_floor"))
    max_ref = int(getattr(args, "reference_max_spp", refs.DEFAULT_MAX_SPP))
    if floor is not None and max_ref < args.reference_spp:
        raise BenchError(f"--reference-max-spp {max_ref} is below --reference-spp {args.reference_spp}")
    scal = args.scaling_percentages or q.get("scaling_percentages") or DEFAULT_SCALING
    scaling = [] if scal == "none" else _ints(scal, "scaling-percentages")
    oracle_budgets = budgets if not args.oracle_budgets else _ints(args.oracle_budgets, "oracle-budgets")
    scaling_methods = [m for m in (args.scaling_methods.split(",") if args.scaling_methods else names)
                       if m and m != "uniform"]
    for m in scaling_methods:
        if m not in methods_registry.METHODS:
            raise BenchError(f"unknown method {m!r} in --scaling-methods")
    out = os.path.abspath(args.out or DEFAULT_OUT)
    if os.path.exists(out) and not os.path.isdir(out):
        raise BenchError(f"--out {out} is a file, not a folder")
    return {"quick": bool(args.quick), "scenes": scenes, "methods": names, "budgets": budgets,
            "resolution_percentage": int(pct), "uniform_spp": uniform,
            "reference_spp": int(args.reference_spp), "reference_dir": args.reference_dir,
            "reference_floor": floor, "reference_max_spp": max_ref,
            "render_references": not args.no_render_references, "oracle": not args.no_oracle,
            "uniform_sampling": not args.no_uniform_sampling,
            "oracle_budgets": [b for b in oracle_budgets], "peers": not args.no_peers,
            "scaling_percentages": scaling, "scaling_methods": scaling_methods,
            "max_samples_factor": int(args.max_samples_factor or q.get("max_samples_factor") or 16),
            "scaling_memory_mp": float(args.scaling_memory_mp),
            "scaling_max_seconds": float(args.scaling_max_seconds),
            "run_max_seconds": float(args.run_max_seconds or 0.0),
            "seed": int(args.seed), "out": out}


def main(args) -> int:
    """``./cycles-adaptive bench``: one session, its outputs; bad input raises
    ValueError (one line, exit 2, in :func:`operators.cli.main`)."""
    try:
        cfg = resolve_config(args)
    except BenchError as exc:
        raise ValueError(str(exc)) from None
    if cfg["seed"] in refs.half_seeds(refs.REFERENCE_SEED):
        raise ValueError(f"--seed {cfg['seed']} is a seed of the references' halves; the runs need another")
    os.makedirs(cfg["out"], exist_ok=True)
    session = Session(cfg, argv=sys.argv[1:])
    results = session.run()
    paths = write_outputs(results, cfg["out"])
    print(f"[bench] done in {results['session_seconds']:.1f} s; results in {cfg['out']}", flush=True)
    if args.json:
        print(json.dumps({"out": cfg["out"], "seconds": results["session_seconds"], **paths}))
    return 0


def add_reference_arguments(p) -> None:
    """The flags of ``./cycles-adaptive references``."""
    p.add_argument("--scenes", help="comma-separated sample scene names or .blend paths "
                   "(default: every scene in sample_blends/)")
    p.add_argument("--spp", type=int, default=refs.DEFAULT_SPP, help="samples per pixel of each "
                   "reference (>= 1024 for the benchmark)")
    p.add_argument("--resolution-percentage", type=int, default=100, help="resolution %% to render at")
    p.add_argument("--frames", help="frames to render: 'all' (frame range of the file), '1-12', "
                   "'1,3'; default: each file's current frame. Only scenes with more than one "
                   "frame render more than one.")
    p.add_argument("--dir", default=refs.DEFAULT_DIR,
                   help="cache folder (default: references/ in the repo)")
    p.add_argument("--seed", type=int, default=refs.REFERENCE_SEED,
                   help="Cycles seed of the references; must differ from the runs' seed (0)")
    p.add_argument("--floor", type=float, default=None, help="render until the noise floor "
                   "(relMSE of a perfect image, from two independent halves) is below this: from "
                   "--spp, doubling, up to --max-spp (default: exactly --spp samples)")
    p.add_argument("--max-spp", type=int, default=refs.DEFAULT_MAX_SPP,
                   help=f"cap of --floor (default {refs.DEFAULT_MAX_SPP})")
    p.add_argument("--force", action="store_true", help="re-render even when a matching one is cached")
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")


def references_main(args) -> int:
    """``./cycles-adaptive references``: render (or find cached) the references
    of the given scenes and frames; bad input raises ValueError."""
    import bpy
    if args.spp < 1:
        raise ValueError("--spp must be >= 1")
    if args.spp < 1024:
        print(f"[references] note: {args.spp} spp is below the benchmark's 1024", file=sys.stderr)
    if 0 in refs.half_seeds(args.seed):
        raise ValueError(f"--seed {args.seed}: its halves' seeds {refs.half_seeds(args.seed)} include "
                         "the runs' seed 0; a reference must use another seed")
    if args.floor is not None and not args.floor > 0:
        raise ValueError("--floor must be > 0")
    if args.floor is not None and args.max_spp < args.spp:
        raise ValueError(f"--max-spp {args.max_spp} is below --spp {args.spp}")
    names = refs.scene_names(args.scenes)
    done = []
    for name in names:
        path = refs.scene_path(name)
        refs.open_scene(path)
        scene = bpy.context.scene
        frames = refs.parse_reference_frames(args.frames, scene)
        if len(frames) > 1 and scene.frame_end <= scene.frame_start:
            frames = [scene.frame_current]  # a still: one frame
        for fr in frames:
            if args.floor is None:
                want = refs.wanted_record(path, fr, args.resolution_percentage, args.spp, args.seed)
                cached_path = refs.reference_path(path, fr, args.resolution_percentage, args.spp, args.dir)
                cached = not args.force and not refs.mismatch(refs.read_sidecar(cached_path), want)
            else:
                cached = not args.force and refs.find_floor_reference(
                    path, fr, args.resolution_percentage, args.seed, args.floor, args.max_spp,
                    args.dir) is not None
            ref = refs.ensure_reference(path, fr, args.resolution_percentage, args.spp, args.seed,
                                        args.dir, force=args.force, other_version="render",
                                        log=lambda m: print(m, flush=True), floor=args.floor,
                                        max_spp=args.max_spp)
            rec = refs.read_sidecar(ref) or {}
            print(f"[references] {refs.scene_label(path)} frame {fr}: {ref} "
                  f"({'cached' if cached else 'rendered'}, {rec.get('width')}x{rec.get('height')}, "
                  f"{rec.get('spp')} spp, noise floor relMSE {_fmt(rec.get('noise_relmse_halves'))} "
                  f"(two halves), {_fmt(rec.get('noise_relmse'))} (variance of the mean), "
                  f"{_fmt(rec.get('render_seconds'), '.1f')} s)", flush=True)
            done.append({"scene": refs.scene_label(path), "frame": fr, "path": ref, "cached": cached,
                         **{k: rec.get(k) for k in ("spp", "seed", "width", "height", "blender",
                                                   "render_seconds", "noise_relmse",
                                                   "noise_relmse_halves", "floor_target")}})
    if args.json:
        print(json.dumps({"references": done}))
    return 0


def _fmt(value, spec: str = ".2e") -> str:
    """A sidecar figure for the log; "n/a" when absent (an old sidecar)."""
    return format(value, spec) if isinstance(value, (int, float)) else "n/a"


class Command(NamedTuple):
    """A developer command for :func:`operators.cli.main` (``extra_commands``)."""

    NAME: str
    HELP: str
    add_arguments: Callable
    main: Callable


COMMANDS = (
    Command("bench", "measure the speed/accuracy trade against uniform, Cycles adaptive sampling "
            "and OIDN", add_arguments, main),
    Command("references", "render (and cache) the high-spp references of the sample scenes",
            add_reference_arguments, references_main),
    Command("bench-sequence", "per-frame relMSE and temporal error (flicker) of animated scenes, ours and "
            "the peers", sequence.add_arguments, sequence.main),
)

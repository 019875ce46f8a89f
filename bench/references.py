"""High-spp references of the sample scenes, rendered once and cached.

A reference is rendered through :class:`~addon.executor.CyclesExecutor` (the same
settings as our runs: Tabulated Sobol pattern, no adaptive sampling, no
denoising, compositing off) with a **different seed** (``REFERENCE_SEED``)
from the runs it judges.  Runs use seed 0 and sample indices from 0; a reference
sharing them would share their noise, and the runs' relMSE would look smaller
than it is.

Noise floor (the expected relMSE a *perfect* image still shows against the
reference).  The reference is the sample-count-weighted mean of two
**independent halves**, rendered with two seeds (``half_seeds``); the floor is
estimated from their difference (:func:`halves_floor`, recorded as
``noise_relmse_halves``).  Under Cycles' QMC sampling the variance of the mean
from consecutive sample subsets of one seed (``noise_relmse``, still recorded)
is not the error of the mean; two independently scrambled halves are.  With
``floor`` given (``references --floor``, the benchmark), each half continues its
own sample sequence, doubling the total, until the floor is below the target or
``max_spp`` is reached (:func:`converge_halves`).

Cache: ``DIR/<scene>.f<frame>.r<percent>.s<spp>.exr`` (multilayer EXR: ``Combined``,
``Variance`` of the mean and the two halves ``HalfA``/``HalfB``) with a JSON
sidecar ``.json`` recording spp, seed, resolution, frame, Blender version, the
SHA-256 of the .blend and both floors.  A cached reference is reused only when all
of these match (a floor request: any spp whose floor meets it, or at the cap);
sidecars of version 1 (one seed, no halves) still load and match a fixed-spp
request; ``./cycles-adaptive references``
(:mod:`bench.cli`) re-renders one that does not, the benchmark refuses one from
another Blender version.

Also the sample scene list (``sample_blends/*.blend``) the benchmark and the
developer tools (``tools/``) share.
"""
from __future__ import annotations

import json
import os
import time

import numpy as np

from ..core import io as imageio
from ..core.metrics import REL_EPS

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SAMPLE_DIR = os.path.join(ROOT, "sample_blends")
DEFAULT_DIR = os.path.join(ROOT, "references")
REFERENCE_SEED = 1000003
DEFAULT_SPP = 1024
#: cap of the render-until-floor loop (``references --max-spp``)
DEFAULT_MAX_SPP = 16384
#: sample subsets a reference is rendered in (variance of the reference's mean),
#: half of them per half, at every doubling
SUBSETS = 8
#: 2: two independent halves, ``noise_relmse_halves``; 1: one seed, no halves
SIDECAR_VERSION = 2
#: sidecar versions a fixed-spp request accepts (older references still load)
COMPATIBLE_VERSIONS = (1, 2)
#: XORed into the reference seed for half B (many bits flipped: Cycles mixes the
#: seed into per-pixel scrambling hashes, a distant seed is a fresh scramble)
HALF_B_SEED_MASK = 0x2545F491
#: the frame-number placeholder of a reference pattern (``render --frames --reference``)
FRAME_PLACEHOLDER = "####"


class ReferenceFileError(ValueError):
    """A reference is missing, stale, of another size or from another Blender
    version; the message is one line for the user."""


# ------------------------------------------------------------------ scenes
def available_scenes() -> list:
    """Names of the sample scenes (``sample_blends/*.blend``), sorted."""
    if not os.path.isdir(SAMPLE_DIR):
        return []
    return sorted(os.path.splitext(f)[0] for f in os.listdir(SAMPLE_DIR) if f.endswith(".blend"))


#: the order the benchmark and the README use
SCENE_ORDER = ("cornell", "dof", "soft_shadows", "glossy", "motion_blur", "animated")
#: production-scale animated scenes: the sequence benchmark's (``bench-sequence``),
#: not in the still benchmark's default "all" (a 1024-spp reference frame of
#: courtyard takes ~30 CPU minutes)
SEQUENCE_SCENES = ("courtyard",)


def scene_path(name: str) -> str:
    """A sample scene name (``cornell``) or a path to a .blend -> absolute path.
    ValueError naming the available scenes for an unknown name."""
    if name.endswith(".blend") or os.sep in name:
        if not os.path.isfile(name):
            raise ValueError(f"{name}: no such .blend file")
        return os.path.abspath(name)
    path = os.path.join(SAMPLE_DIR, name + ".blend")
    if not os.path.isfile(path):
        have = available_scenes()
        raise ValueError(f"unknown scene {name!r}; available: {', '.join(have) or 'none (run sample_blends/build_scenes.py)'}")
    return path


def scene_names(text: str | None) -> list:
    """``"cornell,dof"`` -> validated list; None/empty/"all" -> every sample scene
    (in ``SCENE_ORDER`` first) except the production-scale ``SEQUENCE_SCENES``."""
    if not text or text == "all":
        have = [s for s in available_scenes() if s not in SEQUENCE_SCENES]
        names = [s for s in SCENE_ORDER if s in have] + [s for s in have if s not in SCENE_ORDER]
        if not names:
            raise ValueError(f"no sample scenes in {SAMPLE_DIR} (run sample_blends/build_scenes.py)")
        return names
    names = [s.strip() for s in text.split(",") if s.strip()]
    for n in names:
        scene_path(n)
    return names


def scene_label(path: str) -> str:
    """``.../cornell.blend`` (or ``cornell``) -> ``cornell``."""
    return os.path.splitext(os.path.basename(path))[0]




def open_scene(path: str, force: bool = False) -> None:
    """Open a .blend (skipped when it is the open file, unless ``force``);
    ValueError with Blender's last message when it cannot be opened."""
    import bpy
    if not force and os.path.abspath(bpy.data.filepath or "") == os.path.abspath(path):
        return
    try:
        bpy.ops.wm.open_mainfile(filepath=path, load_ui=False)
    except RuntimeError as exc:
        raise ValueError(f"{path}: cannot open ({str(exc).strip().splitlines()[-1]})") from None


# ------------------------------------------------------------------- cache
def _cache_name(scene: str, frame_text: str, resolution_percentage: int, spp: int) -> str:
    return f"{scene_label(scene)}.f{frame_text}.r{int(resolution_percentage)}.s{int(spp)}.exr"


def reference_path(scene: str, frame: int, resolution_percentage: int, spp: int,
                   directory: str | None = None) -> str:
    """Cache path of the reference of ``scene`` (name or .blend path) at ``frame``."""
    d = os.path.abspath(directory or DEFAULT_DIR)
    return os.path.join(d, _cache_name(scene, f"{int(frame):04d}", resolution_percentage, spp))


def reference_pattern(scene: str, resolution_percentage: int, spp: int,
                      directory: str | None = None) -> str:
    """:func:`reference_path` with ``####`` for the frame number: the per-frame
    reference pattern ``./cycles-adaptive render --frames ... --reference`` takes."""
    d = os.path.abspath(directory or DEFAULT_DIR)
    return os.path.join(d, _cache_name(scene, FRAME_PLACEHOLDER, resolution_percentage, spp))


def sidecar_path(exr: str) -> str:
    return os.path.splitext(exr)[0] + ".json"


def wanted_record(scene: str, frame: int, resolution_percentage: int, spp: int, seed: int) -> dict:
    """The sidecar fields a cached reference must match (``MATCH_KEYS``)."""
    import bpy
    return {"version": SIDECAR_VERSION, "scene": scene_label(scene), "blend_sha256": imageio.file_sha256(scene),
            "frame": int(frame), "resolution_percentage": int(resolution_percentage),
            "spp": int(spp), "seed": int(seed), "blender": bpy.app.version_string}


MATCH_KEYS = ("version", "scene", "blend_sha256", "frame", "resolution_percentage", "spp", "seed",
              "blender")


def read_sidecar(exr: str) -> dict | None:
    """The JSON sidecar of a reference EXR; None when either file is missing
    or the sidecar is unreadable."""
    p = sidecar_path(exr)
    if not (os.path.isfile(exr) and os.path.isfile(p)):
        return None
    try:
        with open(p) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def mismatch(record: dict | None, wanted: dict, ignore=()) -> list:
    """Keys where a cached record differs from what is wanted ([] = reusable).

    ``version`` matches any of ``COMPATIBLE_VERSIONS`` (a version-1 sidecar, one
    seed and no halves floor, still serves a fixed-spp request); ``ignore``:
    keys not compared (``blender``: a floor request looking for a reference
    from another version, to refuse it by name)."""
    if record is None:
        return ["missing"]
    out = []
    for k in MATCH_KEYS:
        if k in ignore:
            continue
        if k == "version":
            if record.get(k) not in COMPATIBLE_VERSIONS:
                out.append(k)
        elif record.get(k) != wanted.get(k):
            out.append(k)
    return out


def half_seeds(seed: int) -> tuple:
    """Cycles seeds of half A and half B of a reference with ``seed``."""
    return int(seed), int((int(seed) ^ HALF_B_SEED_MASK) & 0x7FFFFFFF)


def meets_floor(record: dict, floor: float, max_spp: int) -> bool:
    """A cached reference serves a floor request: its halves floor is below
    ``floor``, or it reached ``max_spp`` (rendering again would stop there too)."""
    f = record.get("noise_relmse_halves")
    if not isinstance(f, (int, float)) or not np.isfinite(f):
        return False
    return f < floor or int(record.get("spp", 0)) >= int(max_spp)


def find_floor_reference(scene: str, frame: int, resolution_percentage: int, seed: int, floor: float,
                         max_spp: int, directory: str | None = None, ignore=()) -> str | None:
    """Cached reference of ``scene`` at ``frame`` matching everything but spp
    (and the keys in ``ignore``) that :func:`meets_floor`; the one with the
    lowest floor, None when none."""
    import glob
    import re
    d = os.path.abspath(directory or DEFAULT_DIR)
    pattern = os.path.join(d, f"{glob.escape(scene_label(scene))}.f{int(frame):04d}."
                              f"r{int(resolution_percentage)}.s*.exr")
    best, best_floor = None, np.inf
    for p in sorted(glob.glob(pattern)):
        m = re.search(r"\.s(\d+)\.exr$", p)
        rec = read_sidecar(p)
        if not m or rec is None or rec.get("spp") != int(m.group(1)):
            continue
        want = wanted_record(scene, frame, resolution_percentage, rec["spp"], seed)
        if mismatch(rec, want, ignore) or not meets_floor(rec, floor, max_spp):
            continue
        if rec["noise_relmse_halves"] < best_floor:
            best, best_floor = p, rec["noise_relmse_halves"]
    return best


def check_reference(path: str) -> dict:
    """The sidecar of a reference EXR, refusing one from another Blender version
    (ReferenceFileError with both versions)."""
    import bpy
    rec = read_sidecar(path)
    if rec is None:
        raise ReferenceFileError(f"missing reference {path} (or its .json sidecar); "
                             f"run ./cycles-adaptive references")
    if rec.get("blender") != bpy.app.version_string:
        raise ReferenceFileError(f"reference {path} was rendered with Blender {rec.get('blender')}, this is "
                             f"{bpy.app.version_string}; re-render it with ./cycles-adaptive references "
                             f"--scenes {rec.get('scene')} --force")
    return rec


def ensure_reference(scene_path_: str, frame: int | None = None, resolution_percentage: int = 100,
                     spp: int = DEFAULT_SPP, seed: int = REFERENCE_SEED, directory: str | None = None,
                     render_missing: bool = True, force: bool = False, other_version: str = "refuse",
                     log=print, floor: float | None = None, max_spp: int = DEFAULT_MAX_SPP) -> str:
    """Path of a reference EXR of ``scene_path_`` at ``frame`` (default: the scene's
    current frame), ``resolution_percentage`` and ``spp``, rendering it when the
    cache has none that matches.

    floor : None renders exactly ``spp`` samples; a relMSE renders from ``spp``
        samples, doubling, until the halves floor is below it or ``max_spp``
        is reached (:func:`converge_halves`); a cached reference of any spp
        that :func:`meets_floor` is reused.

    other_version : what to do with a cached reference from another Blender
        version: ``"refuse"`` (ReferenceFileError; the benchmark) or ``"render"``
        (re-render it; the ``references`` command).
    render_missing : False raises ReferenceFileError instead of rendering.
    """
    import bpy
    scene_path_ = os.path.abspath(scene_path_)
    if not os.path.isfile(scene_path_):
        raise ValueError(f"{scene_path_}: no such .blend file")
    if spp < 1:
        raise ValueError("reference spp must be >= 1")
    if not 1 <= int(resolution_percentage) <= 10000:
        raise ValueError("resolution percentage must be between 1 and 10000")
    if frame is None:
        open_scene(scene_path_)
        frame = bpy.context.scene.frame_current
    if floor is not None:
        if not floor > 0:
            raise ValueError("reference floor must be > 0")
        if max_spp < spp:
            raise ValueError(f"reference max spp {max_spp} is below the starting spp {spp}")
        found = None if force else find_floor_reference(scene_path_, frame, resolution_percentage, seed,
                                                        floor, max_spp, directory)
        if found is not None:
            return found
        if other_version == "refuse" and not force:
            other = find_floor_reference(scene_path_, frame, resolution_percentage, seed, floor, max_spp,
                                         directory, ignore=("blender",))
            if other is not None:
                check_reference(other)  # raises with both versions
        if not render_missing:
            raise ReferenceFileError(
                f"no reference of {scene_label(scene_path_)} frame {frame} at "
                f"{int(resolution_percentage)}% in {os.path.abspath(directory or DEFAULT_DIR)} with a "
                f"halves floor below {floor:.2e} (or at {max_spp} spp); run ./cycles-adaptive references "
                f"--scenes {scene_label(scene_path_)} --floor {floor:g} --max-spp {max_spp}")
        return render_reference(scene_path_, frame, resolution_percentage, spp, seed, None,
                                wanted_record(scene_path_, frame, resolution_percentage, spp, seed),
                                log=log, floor=floor, max_spp=max_spp, directory=directory)["path"]
    path = reference_path(scene_path_, frame, resolution_percentage, spp, directory)
    wanted = wanted_record(scene_path_, frame, resolution_percentage, spp, seed)
    rec = read_sidecar(path)
    diff = mismatch(rec, wanted)
    if not diff and not force:
        return path
    if rec is not None and "blender" in diff and other_version == "refuse" and not force:
        check_reference(path)  # raises with both versions
    if not render_missing:
        why = "missing" if rec is None else "stale (" + ", ".join(diff) + " differ)"
        raise ReferenceFileError(f"reference {path} is {why}; run ./cycles-adaptive references "
                             f"--scenes {scene_label(scene_path_)} --spp {spp}")
    render_reference(scene_path_, frame, resolution_percentage, spp, seed, path, wanted, log=log)
    return path


def noise_relmse(variance_of_mean: np.ndarray, mean: np.ndarray) -> float:
    """Noise floor from the variance of the mean of one seed's sample subsets:
    mean of var / (r^2 + 0.01).  Under QMC sampling this is not the error of
    the mean (:func:`halves_floor` is); kept for comparison and old sidecars."""
    return float((variance_of_mean / (mean * mean + REL_EPS)).mean())


def halves_floor(a: np.ndarray, b: np.ndarray, n_a: float = 1.0, n_b: float = 1.0,
                 full: np.ndarray | None = None) -> float:
    """Expected relMSE of a perfect image against the mean of two independent
    halves ``a`` (``n_a`` samples) and ``b`` (``n_b``): the reference's floor.

    With half errors e_a, e_b independent, zero-mean, Var(e_h) = s^2 / n_h:
    E(a - b)^2 = s^2 (1/n_a + 1/n_b) = s^2 N / (n_a n_b) and the full mean
    (n_a a + n_b b) / N has Var = s^2 / N, so Var(full) = E(a - b)^2 n_a n_b / N^2;
    equal halves: E(a - b)^2 = 2 Var(half), Var(full) = Var(half) / 2 =
    E(a - b)^2 / 4 (whatever the convergence rate, so also under QMC).  Weighted
    as relMSE weights (``core.metrics``): floor = mean (a - b)^2 / (r^2 + 0.01)
    x n_a n_b / N^2 over pixels and RGB, r = ``full`` (default the weighted mean).
    Non-finite terms count 0 (the render refuses non-finite references)."""
    a = np.asarray(a, np.float64)[..., :3]
    b = np.asarray(b, np.float64)[..., :3]
    if a.shape != b.shape or a.size == 0:
        raise ValueError(f"halves differ in shape or are empty: {a.shape} vs {b.shape}")
    n_a, n_b = float(n_a), float(n_b)
    n = n_a + n_b
    if not (n_a > 0 and n_b > 0):
        raise ValueError("each half needs samples")
    r = (n_a * a + n_b * b) / n if full is None else np.asarray(full, np.float64)[..., :3]
    e = (a - b) ** 2 / (r * r + REL_EPS)
    e = np.where(np.isfinite(e), e, 0.0)
    return float(e.mean() * n_a * n_b / (n * n))


def next_half_spp(per_half: int, max_spp: int) -> int:
    """Samples per half of the next round: double, clamped so the total stays
    within ``max_spp``; ``per_half`` itself when no round is left."""
    return max(int(per_half), min(2 * int(per_half), int(max_spp) // 2))


def converge_halves(render, shape, spp: int, floor: float | None = None, max_spp: int = DEFAULT_MAX_SPP,
                    subsets: int = SUBSETS, frame: int = 0, features=("alpha",), log=None) -> dict:
    """Render two independent halves, doubling, until their floor is below ``floor``.

    render(half, task) -> (rgba, features) renders ``task`` (a RegionTask:
    ``task.offset``.. ``task.offset + task.samples`` of that half's own sample
    sequence) with half 0's or half 1's seed.  Starts at ``spp`` in all
    (``ceil(spp/2)`` and ``floor(spp/2)`` per half); with ``floor`` None that is
    all, else every round doubles each half's samples, continuing its sequence
    (merged exactly by sample count: the cost of a final N-sample reference is N;
    a fresh pair per round would cost ~2N), until :func:`halves_floor` < ``floor``
    or the total reaches ``max_spp``.  Each half's new samples are rendered in
    ``subsets // 2`` subsets, so the full mean's variance (``noise_relmse``) is
    known too.  Returns ``{"halves": [Buffers, Buffers], "full": Buffers,
    "counts": (n_a, n_b), "floor": float or None, "history": [(spp, floor), ...]}``."""
    from ..core.buffers import Buffers
    from ..core.pipeline import merge_render, subset_tasks
    h, w = shape
    spp = int(spp)
    if spp < 1:
        raise ValueError("reference spp must be >= 1")
    if floor is not None and spp < 2:
        raise ValueError("a floor needs at least 2 spp (one per half)")
    halves = [Buffers.empty(h, w, features), Buffers.empty(h, w, features)]
    target = [(spp + 1) // 2, spp // 2]
    done = [0, 0]
    history = []
    while True:
        for i in (0, 1):
            if target[i] > done[i]:
                for task in subset_tasks(w, h, target[i] - done[i], max(1, subsets // 2), frame,
                                         offset=done[i]):
                    merge_render(halves[i], task, *render(i, task))
                done[i] = target[i]
        fl = halves_floor(halves[0].color.mean, halves[1].color.mean, done[0], done[1]) \
            if done[1] > 0 else None
        history.append((done[0] + done[1], fl))
        if log is not None:
            log(done[0] + done[1], fl)
        if floor is None or fl < floor:
            break
        nxt = next_half_spp(target[1], max_spp)
        if nxt <= target[1]:
            break
        target = [nxt, nxt]
    full = halves[0].copy()
    if done[1] > 0:
        full.merge(halves[1])
    return {"halves": halves, "full": full, "counts": (done[0], done[1]), "floor": fl,
            "history": history}


def render_reference(scene_path_: str, frame: int, resolution_percentage: int, spp: int, seed: int,
                     path: str | None, record: dict, log=print, floor: float | None = None,
                     max_spp: int = DEFAULT_MAX_SPP, directory: str | None = None) -> dict:
    """Render and write one reference (EXR + sidecar); returns the sidecar
    record with ``path`` added.

    Two independent halves (seeds :func:`half_seeds`) through
    :func:`converge_halves`: exactly ``spp`` samples when ``floor`` is None,
    else from ``spp`` until the halves floor is below ``floor`` or ``max_spp``;
    ``path`` None: the cache path of the final spp in ``directory``.  The open
    file's settings are restored afterwards."""
    import bpy
    from ..addon import executor as ex
    open_scene(scene_path_)
    scene = bpy.context.scene
    vl = bpy.context.view_layer
    seeds = half_seeds(seed)
    label = scene_label(scene_path_)
    guard = ex.SettingsGuard()
    guard.set(scene.render, "resolution_percentage", int(resolution_percentage))
    t0 = time.perf_counter()

    def progress(total, fl):
        fl_text = "n/a" if fl is None else f"{fl:.2e}"
        log(f"[references] {label} frame {frame}: {total} spp, halves floor {fl_text}"
            + ("" if floor is None else f" (target {floor:.2e})") + f" ({time.perf_counter() - t0:.1f} s)")

    try:
        with ex.CyclesExecutor(scene, vl, (), seed=seeds[0]) as exe:
            current = [seeds[0]]

            def render(half, task):
                if current[0] != seeds[half]:
                    exe.scene.cycles.seed = seeds[half]  # restored by the executor's guard
                    current[0] = seeds[half]
                return exe.render(task)

            res = converge_halves(render, exe.size, spp, floor, max_spp, SUBSETS, frame, log=progress)
    finally:
        guard.restore()
    seconds = time.perf_counter() - t0
    buf = res["full"]
    h, w = buf.shape
    total = int(sum(res["counts"]))
    mean = buf.color.mean
    var = buf.variance_of_mean()
    var = np.where(np.isfinite(var), var, 0.0)
    nonfinite = int((~np.isfinite(mean)).any(axis=-1).sum())
    if nonfinite:
        raise ReferenceFileError(f"reference of {label} has {nonfinite} non-finite pixels")
    if path is None:
        path = reference_path(scene_path_, frame, resolution_percentage, total, directory)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    rec = dict(record)
    rec.update({"version": SIDECAR_VERSION, "spp": total, "width": int(w), "height": int(h),
                "subsets": int(buf.k.max()), "render_seconds": seconds,
                "noise_relmse": noise_relmse(var, mean),
                "noise_relmse_halves": res["floor"], "half_seeds": list(seeds),
                "half_spp": list(res["counts"]), "floor_target": floor,
                "max_spp": int(max_spp) if floor is not None else None,
                "floor_history": [[int(n), f] for n, f in res["history"]],
                "sampling_pattern": "TABULATED_SOBOL", "created": time.strftime("%Y-%m-%dT%H:%M:%S")})
    combined = np.concatenate([mean, buf.features["alpha"].mean], axis=-1)
    layers = {"Combined": combined, "Variance": var}
    if res["counts"][1] > 0:
        layers.update({"HalfA": res["halves"][0].color.mean, "HalfB": res["halves"][1].color.mean})
    imageio.write_layers(path, layers, attributes={"cycles_adaptive/reference": json.dumps(rec)})
    imageio.write_text(sidecar_path(path), json.dumps(rec, indent=1))
    return {**rec, "path": path}


def load_checked_reference(path: str, shape=None) -> tuple:
    """(rgb (H, W, 3) float64, sidecar dict) of a checked reference
    (:func:`check_reference`, then :func:`core.io.read_reference`).

    A size that differs from ``shape`` (H, W) raises ReferenceFileError (bad
    input: the benchmark stops); an unreadable file raises ImageFileError as
    any broken image does."""
    rec = check_reference(path)
    rgb = imageio.read_reference(path)
    if shape is not None and rgb.shape[:2] != tuple(shape):
        raise ReferenceFileError(f"reference {path} is {rgb.shape[1]}x{rgb.shape[0]}, the render is "
                             f"{shape[1]}x{shape[0]}")
    return rgb, rec


def parse_reference_frames(text: str | None, scene) -> list:
    """Frames of ``references --frames``: ``None`` -> [current frame]; ``"all"``
    -> frame_start..frame_end; ``"1-12"``, ``"1,3,5"`` -> those frames (whole
    numbers >= 0).  (``render --frames A-B:STEP`` is ``operators.job.parse_frames``.)"""
    if not text:
        return [scene.frame_current]
    if text == "all":
        return list(range(scene.frame_start, scene.frame_end + 1))
    out = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        a, _, b = part.partition("-")
        if not a.isdigit() or (b and not b.isdigit()):
            raise ValueError(f"--frames: cannot read {part!r} (use e.g. 1-12, 1,3,5 or all)")
        out.extend(range(int(a), int(b or a) + 1))
    if not out:
        raise ValueError("--frames: no frames given")
    return out

"""High-spp references of the sample scenes, rendered once and cached.

A reference is rendered through :class:`~addon.executor.CyclesExecutor` (the same
settings as our runs: Tabulated Sobol pattern, no adaptive sampling, no
denoising, compositing off) with a **different seed** (``REFERENCE_SEED``)
from the runs it judges.  Runs use seed 0 and sample indices from 0; a reference
sharing them would share their noise, and the runs' relMSE would look smaller
than it is.  The reference is rendered in ``SUBSETS`` sample subsets, so its own
noise is estimated too: the sidecar records ``noise_relmse``, the expected relMSE
a *perfect* image would still show against this reference (its noise floor).

Cache: ``DIR/<scene>.f<frame>.r<percent>.s<spp>.exr`` (multilayer EXR: ``Combined``
and ``Variance`` of the mean) with a JSON sidecar ``.json`` recording spp, seed,
resolution, frame, Blender version and the SHA-256 of the .blend.  A cached
reference is reused only when all of these match; ``./cycles-adaptive references``
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

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SAMPLE_DIR = os.path.join(ROOT, "sample_blends")
DEFAULT_DIR = os.path.join(ROOT, "references")
REFERENCE_SEED = 1000003
DEFAULT_SPP = 1024
#: sample subsets a reference is rendered in (variance of the reference's mean)
SUBSETS = 8
SIDECAR_VERSION = 1
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


def mismatch(record: dict | None, wanted: dict) -> list:
    """Keys where a cached record differs from what is wanted ([] = reusable)."""
    if record is None:
        return ["missing"]
    return [k for k in MATCH_KEYS if record.get(k) != wanted.get(k)]


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
                     log=print) -> str:
    """Path of a reference EXR of ``scene_path_`` at ``frame`` (default: the scene's
    current frame), ``resolution_percentage`` and ``spp``, rendering it when the
    cache has none that matches.

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
    """Expected relMSE of a perfect image against a reference with this
    variance of the mean (its noise floor): mean of var / (r^2 + 0.01)."""
    return float((variance_of_mean / (mean * mean + 0.01)).mean())


def render_reference(scene_path_: str, frame: int, resolution_percentage: int, spp: int, seed: int,
                     path: str, record: dict, log=print) -> dict:
    """Render and write one reference (EXR + sidecar); returns the sidecar record.

    ``spp`` samples in ``min(SUBSETS, spp)`` consecutive sample subsets
    (:func:`core.pipeline.subset_tasks`), so the variance of the mean is known.
    The open file's settings are restored afterwards."""
    import bpy
    from ..addon import executor as ex
    from ..core.buffers import Buffers
    from ..core.pipeline import merge_render, subset_tasks
    open_scene(scene_path_)
    scene = bpy.context.scene
    vl = bpy.context.view_layer
    os.makedirs(os.path.dirname(path), exist_ok=True)
    guard = ex.SettingsGuard()
    guard.set(scene.render, "resolution_percentage", int(resolution_percentage))
    t0 = time.perf_counter()
    try:
        with ex.CyclesExecutor(scene, vl, (), seed=seed) as exe:
            h, w = exe.size
            buf = Buffers.empty(h, w, ("alpha",))
            tasks = subset_tasks(w, h, spp, SUBSETS, frame)
            for task in tasks:
                merge_render(buf, task, *exe.render(task))
                log(f"[references] {scene_label(scene_path_)} frame {frame}: "
                    f"{task.offset + task.samples}/{spp} spp ({time.perf_counter() - t0:.1f} s)")
    finally:
        guard.restore()
    seconds = time.perf_counter() - t0
    mean = buf.color.mean
    var = buf.variance_of_mean()
    var = np.where(np.isfinite(var), var, 0.0)
    nonfinite = int((~np.isfinite(mean)).any(axis=-1).sum())
    if nonfinite:
        raise ReferenceFileError(f"reference of {scene_label(scene_path_)} has {nonfinite} non-finite pixels")
    rec = dict(record)
    rec.update({"width": int(w), "height": int(h), "subsets": len(tasks), "render_seconds": seconds,
                "noise_relmse": noise_relmse(var, mean), "sampling_pattern": "TABULATED_SOBOL",
                "created": time.strftime("%Y-%m-%dT%H:%M:%S")})
    combined = np.concatenate([mean, buf.features["alpha"].mean], axis=-1)
    imageio.write_layers(path, {"Combined": combined, "Variance": var},
                         attributes={"cycles_adaptive/reference": json.dumps(rec)})
    imageio.write_text(sidecar_path(path), json.dumps(rec, indent=1))
    return rec


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

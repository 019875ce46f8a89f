"""Forward reprojection of accumulated samples between animation frames
(Schalk 2018, thesis Sec. 3.2-3.3, Algorithm 2).

Each pixel of the previous frame ``t-1`` keeps its accumulated statistics
(``Buffers``: mean, between-group M2, samples n, groups k, feature passes).  Its
stored first intersection point (Cycles' Position pass) is projected into the
camera of frame ``t``; where the thesis' validations pass, the statistics are
copied ("each pixel is copied to a new assigned pixel depending on the camera
matrix", Sec. 3.2) and Chan-merged into the new frame.  :func:`reproject` does
this for a whole frame (vectorised, chunked over source pixels),
:func:`sample_map` is Algorithm 2's sampler (pixels that were not reprojected
first), :func:`backward_coordinates` maps current pixels back into the previous
frame (for ``core.temporal``'s search window).

Conventions (what the frame loop passes)
----------------------------------------
Cameras (:class:`Camera`): ``view`` is the 4x4 world-to-camera matrix (Blender:
``camera.matrix_world.inverted()``; the camera looks down -Z), ``proj`` the 4x4
camera-to-clip matrix (Blender: ``camera.calc_matrix_camera(depsgraph, x=W,
y=H, scale_x=..., scale_y=...)``).  NDC = clip.xyz / clip.w, x and y in
[-1, 1]; a point lies at continuous pixel coordinates ``col = (x + 1) / 2 * W``,
``row = (1 - y) / 2 * H`` (row 0 at the top) and in pixel
``(floor(row), floor(col))``.  ``position`` is the camera's world position (by
default the translation of ``inv(view)``).  Perspective and orthographic
projections work; panoramic cameras cannot be written as a matrix and are not
supported.

Passes (:data:`PASSES`): ``position`` world-space first hit (Position pass),
``depth`` Cycles' Denoising Depth (ray length to the first hit; a camera
z-depth pass is accepted too), ``glossy`` = Glossy Direct + Indirect,
``transmission`` = Transmission Direct + Indirect, ``object_index`` (IndexOB).
Every feature pass of ``current`` must also be in ``prev`` (the output Buffers
carries the same passes as ``current``, so ``current.merge(result.buffers)``
works).  A missing Position pass in ``prev`` or ``current`` raises
``ValueError`` (old outputs rendered without it cannot be reprojected).

Validation (each previous pixel gets the first reason that applies; the counts
are in ``Reprojection.counts``)
--------------------------------------------------------------------------
``empty``          no samples, or non-finite statistics.
``no_position``    non-finite position (NaN/Inf) or depth.
``background``     no surface was hit (Position exactly (0, 0, 0): Cycles writes
                   nothing there; with a depth pass also depth 0 or >= 1e9) and
                   ``Params.background`` is off.  With it on (default) a
                   background pixel is reprojected *by direction*: the
                   environment is at infinity, so the direction of the pixel's
                   centre ray (a point with homogeneous w = 0) is projected, and
                   the target must be background too.  Its radiance depends on
                   the direction only, so there is no view-dependence error.
                   (Orthographic cameras map every direction to w = 0: such
                   background pixels fail as ``outside``.)
``inconsistent``   the pixel is not a single clean first hit: its mean position
                   disagrees with its mean depth (``| |P - C| - depth | >
                   consistency_tolerance * |P - C|``, tested against the ray
                   length and the camera z-depth).  This catches pixels that
                   mix surfaces or background at an edge (the Position pass is
                   a pixel mean, so a half-covered pixel's position is pulled
                   towards the origin) and Cycles' denoising depth that keeps
                   adding path length through specular bounces (mirrors,
                   glass): the aliasing case of Sec. 3.2.2 and part of "never
                   reproject specular".  Skipped without a depth pass.
``outside``        (a) behind the new camera or outside the screen.
``occluded``       (b) the thesis casts a ray from the new camera towards the
                   stored point and requires the hit within epsilon of it.  The
                   current frame's initial pass gives that hit, averaged over
                   the target pixel: with ``d = |P - C_t|`` and ``s`` the
                   pixel's footprint at that distance (one pixel's width in world
                   units, from the projection), the test is
                   ``|P - W_t(target)| <= occlusion_tolerance * d +
                   occlusion_pixels * s``.  The footprint term admits the
                   sub-pixel offset (at most 0.71 pixel) between the projected
                   point and the target's centroid on surfaces up to ~45 degrees
                   from facing (defaults 1 % and 1 pixel); an occluder nearer
                   to the surface than this tolerance is not detected.  A target without samples or position, or a
                   background target for a surface source (and vice versa),
                   counts as occluded.  Where the four pixel centres around the
                   projected point are known surface hits, the point is also
                   compared with their bilinear interpolation (the hit of the
                   ray through the projected sub-pixel position, to second
                   order), and passes if either comparison does: this keeps
                   grazing surfaces valid without widening the tolerance.
``object_index``   (d) |index_prev - index_target| > ``object_index_tolerance``:
                   the object under the pixel changed (moving objects, if the
                   scene gives them pass indices; Cycles' default index is 0).
                   Skipped when either frame lacks the pass.
``specular``       the pixel is mostly view-dependent: ``lum(glossy +
                   transmission) / lum(combined) > max_specular_share`` in the
                   previous frame or at the target in the current one.  The
                   thesis never reprojects specular (alpha < 0.01) or
                   refractive materials; Cycles has no roughness pass, so
                   "mostly specular or refractive" is read from the light passes.
``view_dependence``(c) the Eq. 15 error bound exceeds ``max_error`` (1/256),
                   see below.
``changed``        (addition, Sec. 3 assumes a static scene and restarts on any
                   change) the reprojected mean and the current frame's own
                   initial-pass mean at the target differ beyond noise:
                   ``|m_prev - m_t| > changed_sigma * s * sqrt(1/n_prev + 1/n_t)
                   + max_error`` in some channel, with the per-sample variance
                   pooled over both frames, ``s^2 = (M2_prev + M2_t) /
                   (k_prev - 1 + k_t - 1)`` (unchanged pixels sample the same
                   integrand; pooling gives the variance estimate more degrees
                   of freedom than the initial pass alone, so fewer false
                   alarms).  This catches what no geometric test sees: moving
                   shadows and lights, animated textures -- but per pixel, so
                   only changes large against the initial pass's noise (with
                   5 sigma and ~30 % per-sample noise at 4 spp, changes of more
                   than ~80 %).  Skipped where no variance exists (one group
                   in both frames); ``changed_sigma = 0`` turns it off.  Its
                   false-alarm rate on unchanged pixels is that of a
                   t-test with ``k_prev + k_t - 2`` degrees of freedom at 5 sigma
                   (< 0.1 % per channel from 10 on), costing only efficiency.
``camera_cut``     valid, but fewer than ``min_valid_fraction`` of the new frame's
                   pixels received anything: the frame is treated as a cut and
                   renders fresh (nothing is reprojected, never a smear).

The view-dependence bound (c), Eq. 15
-------------------------------------
Eq. 15 is ``eps = |f_r(V_t, L, N) - f_r(V_{t-1}, L, N)| * A * I``: the change of
the pixel's *view-dependent* outgoing radiance between the two viewpoints.
Cycles has no per-pixel roughness or BRDF value, but it does write that
radiance: the Glossy and Transmission light passes ``S`` (direct + indirect).
For each channel, with ``S_p`` the previous pixel's value, ``S_t`` the current
frame's initial-pass value at the target, ``sigma`` their standard errors and
``z = confidence``:

* if the view direction to the point did not change (``C_t == C_{t-1}``, e.g.
  a static camera or a pure rotation) ``f_r(V_t) = f_r(V_{t-1})`` and
  ``eps = 0`` exactly;
* otherwise ``eps <= min(|S_t - S_p| + z sqrt(sigma_t^2 + sigma_p^2),
  max(S_p + z sigma_p, S_t + z sigma_t))``.  The first term is a direct
  (upper-confidence) estimate of Eq. 15's difference measured by the renderer
  itself; the second holds for every BRDF because both radiances are >= 0 (a
  pixel whose view-dependent light is below 1/256 in both views cannot change
  by more).  Glossy and transmission are bounded separately and added
  (triangle inequality); the channel maximum is compared with ``max_error``.

Why it is conservative: Cycles writes light passes *divided by their colour
pass*, so ``S`` is at least the real contribution ``S * colour`` whenever the
BSDF colour is <= 1 (energy-conserving materials); the confidence terms are
upper bounds at level ``z``; a pass whose mean is exactly 0 (all its samples
0, the passes are non-negative) counts as noise-free even with one subset,
otherwise an unknown variance makes the bound infinite (rejected).  A missing
glossy or transmission pass makes the bound infinite unless the camera kept its
position (or ``assume_diffuse`` is set).  Caveat: the thesis' error is
absolute, in the units of the image; 1/256 is one 8-bit step of a display value
of 1.

Several previous pixels on one new pixel
----------------------------------------
All validated sources landing on one target pixel are *Chan-merged* (pooled):
``n = sum n_s``, ``mean = sum n_s m_s / n``, ``M2 = sum M2_s + sum n_s (m_s -
mean)^2``, ``k = sum k_s`` -- exactly what sequential :meth:`Buffers.merge`
calls give.  Occluded sources were already rejected by (b), so the survivors
all lie on the visible surface within the tolerance; pooling them is the
estimate of the new (larger) footprint when zooming out, and keeps every
sample.  A single source is copied bit for bit.

Camera-dependent features are transformed: ``depth`` is shifted by the change
of distance (or z-depth) of the point, the camera-space ``normal`` is rotated
by ``R_t R_{t-1}^T`` (its M2 is bounded by ``(sum_j |R_ij| sqrt(M2_j))^2``,
the off-diagonal scatter being unknown); ``vector`` (motion) is per-frame data
and is carried unchanged (do not rely on it); the rest are view-independent on
validated pixels and are carried as they are.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .buffers import Buffers, Stat, luminance
from .method import MethodResult, param

#: passes the reprojection reads (position is required, the rest are optional)
PASSES = ("position", "depth", "glossy", "transmission", "object_index")

#: rejection reasons, in the order they are tested (code = index)
REASONS = ("ok", "empty", "no_position", "background", "inconsistent", "outside", "occluded",
           "object_index", "specular", "view_dependence", "changed", "camera_cut")
_R = {name: i for i, name in enumerate(REASONS)}

#: a depth at or above this is "infinite" (Blender's Z pass writes 1e10 for the background)
FAR_DEPTH = 1e9


# --------------------------------------------------------------------------- params
@dataclass
class Params:
    """Validation thresholds (thesis Sec. 3.2-3.3; see the module docstring)."""

    max_error: float = param(
        1.0 / 256.0, "Algorithm 2's maximum reprojection error epsilon (thesis: 1/256), absolute in image "
        "units: the Eq. 15 view-dependence bound must stay below it. Larger reprojects more "
        "glossy pixels (faster, risks stale highlights)", 0.0, 1.0)
    max_specular_share: float = param(
        0.5, "pixels whose glossy + transmission light exceeds this share of the combined "
        "luminance are never reprojected (thesis: no specular/refractive reprojection). "
        "Smaller is safer, larger reuses more", 0.0, 1.0)
    confidence: float = param(
        2.0, "z of the upper confidence bounds on noisy glossy/transmission passes in the Eq. 15 "
        "bound; larger is more conservative (fewer glossy pixels reprojected)", 0.0, 10.0)
    occlusion_tolerance: float = param(
        0.01, "occlusion test epsilon as a fraction of the camera distance (added to "
        "occlusion_pixels footprints); larger accepts more but misses occluders closer "
        "to the surface", 0.0, 1.0)
    occlusion_pixels: float = param(
        1.0, "occlusion test slack in pixel footprints at the point's distance (sub-pixel "
        "offsets on slanted surfaces); larger accepts more grazing surfaces", 0.0, 16.0)
    consistency_tolerance: float = param(
        0.01, "relative mismatch allowed between a pixel's position and its depth before it "
        "counts as mixed (edges) or a specular chain; 0 disables the test", 0.0, 1.0)
    object_index_tolerance: float = param(
        1e-3, "largest change of the (pixel-mean) object index still counted as the same object", 0.0, 1.0)
    changed_sigma: float = param(
        5.0, "reject pixels whose reprojected mean differs from the new frame's own samples by "
        "more than this many standard errors (+ max_error): moving shadows, lights, "
        "animated textures; 0 disables (thesis: static scenes only)", 0.0, 100.0)
    background: bool = param(
        True, "reproject background (environment) pixels by direction; off leaves them to be "
        "rendered fresh")
    assume_diffuse: bool = param(
        False, "treat missing glossy/transmission passes as zero (everything diffuse); off "
        "rejects every pixel whose view changed when they are missing")
    min_valid_fraction: float = param(
        0.01, "if fewer than this fraction of the new frame's pixels receive reprojected "
        "samples the frame is treated as a camera cut and nothing is reprojected", 0.0, 1.0)
    chunk: int = param(
        65536, "source pixels processed per vectorised batch (memory ~ 1 KB per pixel in flight)",
        256, 4194304)


def _params(params) -> Params:
    if params is None:
        return Params()
    if isinstance(params, Params):
        return params
    from .method import params_from_dict
    return params_from_dict(Params, params)


# --------------------------------------------------------------------------- cameras
@dataclass
class Camera:
    """One frame's camera.

    view : (4, 4) world-to-camera matrix (camera looks down -Z).
    proj : (4, 4) camera-to-clip matrix; NDC = clip.xyz / clip.w.
    position : (3,) world position of the camera; default ``inv(view)[:3, 3]``.

    Raises ``ValueError`` for a wrong shape, non-finite entries or a singular
    matrix.
    """

    view: np.ndarray
    proj: np.ndarray
    position: np.ndarray | None = None

    def __post_init__(self):
        self.view = _matrix(self.view, "view (world-to-camera)")
        self.proj = _matrix(self.proj, "projection (camera-to-clip)")
        self.view_inv = np.linalg.inv(self.view)
        self.proj_inv = np.linalg.inv(self.proj)
        if self.position is None:
            self.position = self.view_inv[:3, 3] / self.view_inv[3, 3]
        pos = np.asarray(self.position, np.float64).reshape(-1)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise ValueError(f"camera position must be 3 finite numbers, got {self.position!r}")
        self.position = pos
        self.full = self.proj @ self.view
        # camera rotation (polar part of the 3x3 block, in case the object is scaled)
        u, _, vt = np.linalg.svd(self.view[:3, :3])
        self.rotation = u @ vt

    def clip(self, points: np.ndarray, w: float | np.ndarray = 1.0) -> np.ndarray:
        """(N, 3) world points (w = 1) or directions (w = 0) -> (N, 4) clip coordinates."""
        pts = np.asarray(points, np.float64)
        out = pts @ self.full[:, :3].T
        out += np.asarray(w, np.float64).reshape(-1, 1) * self.full[:, 3][None, :]
        return out

    def pixel_coordinates(self, clip: np.ndarray, height: int, width: int):
        """Clip coordinates -> continuous (row, col) and a front mask (w > 0)."""
        wv = clip[:, 3]
        front = wv > 1e-12 * (np.abs(clip).max(axis=1) + 1e-300)
        safe = np.where(front, wv, 1.0)
        x = clip[:, 0] / safe
        y = clip[:, 1] / safe
        col = (x + 1.0) * 0.5 * width
        row = (1.0 - y) * 0.5 * height
        ok = front & np.isfinite(col) & np.isfinite(row)
        return np.where(ok, row, np.nan), np.where(ok, col, np.nan), ok

    def footprint(self, clip: np.ndarray, height: int, width: int) -> np.ndarray:
        """World size of one pixel at each clip point: ``2 w / (W |P00|)`` (x) and
        ``2 w / (H |P11|)`` (y), the larger of the two; (N,)."""
        wv = np.abs(clip[:, 3])
        sx = 2.0 * wv / max(width * abs(self.proj[0, 0]), 1e-300)
        sy = 2.0 * wv / max(height * abs(self.proj[1, 1]), 1e-300)
        return np.maximum(sx, sy)

    def ray_directions(self, rows: np.ndarray, cols: np.ndarray, height: int, width: int) -> np.ndarray:
        """World directions (unit, (N, 3)) of the rays through pixel centres
        ``(rows + 0.5, cols + 0.5)``; NaN where the projection gives none."""
        x = 2.0 * (cols + 0.5) / max(width, 1) - 1.0
        y = 1.0 - 2.0 * (rows + 0.5) / max(height, 1)
        pts = []
        for zn in (-1.0, 0.0):
            ndc = np.stack([x, y, np.full_like(x, zn), np.ones_like(x)], axis=1)
            cam = ndc @ self.proj_inv.T
            with np.errstate(divide="ignore", invalid="ignore"):
                pts.append(cam[:, :3] / cam[:, 3:4])
        d_cam = pts[1] - pts[0]
        with np.errstate(invalid="ignore"):
            d_cam = np.where(d_cam[:, 2:3] > 0, -d_cam, d_cam)      # the camera looks down -Z
            d = d_cam @ self.view_inv[:3, :3].T
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
        return np.where(np.isfinite(d), d, np.nan)


def _matrix(m, what: str) -> np.ndarray:
    a = np.asarray(m, np.float64)
    if a.shape != (4, 4):
        raise ValueError(f"camera {what} matrix must be 4x4, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"camera {what} matrix has non-finite entries")
    scale = np.abs(a).max()
    if scale == 0 or abs(np.linalg.det(a / scale)) < 1e-12:
        raise ValueError(f"camera {what} matrix is singular (degenerate camera)")
    return a


def perspective(fov_x: float, width: int, height: int, near: float = 0.1, far: float = 100.0,
                shift_x: float = 0.0, shift_y: float = 0.0) -> np.ndarray:
    """OpenGL-style perspective projection like Blender's ``calc_matrix_camera``
    with horizontal field of view ``fov_x`` (radians, sensor fit horizontal)."""
    fx = 1.0 / np.tan(0.5 * fov_x)
    fy = fx * width / height
    p = np.zeros((4, 4))
    p[0, 0], p[1, 1] = fx, fy
    p[0, 2], p[1, 2] = 2.0 * shift_x, 2.0 * shift_y
    p[2, 2] = -(far + near) / (far - near)
    p[2, 3] = -2.0 * far * near / (far - near)
    p[3, 2] = -1.0
    return p


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera matrix of a camera at ``eye`` looking at ``target``
    (camera -Z towards the target, +Y up as close to ``up`` as possible)."""
    eye = np.asarray(eye, np.float64)
    f = np.asarray(target, np.float64) - eye
    f = f / np.linalg.norm(f)
    r = np.cross(f, np.asarray(up, np.float64))
    if np.linalg.norm(r) < 1e-9:
        r = np.cross(f, np.array([0.0, 1.0, 0.0]))
    r = r / np.linalg.norm(r)
    u = np.cross(r, f)
    rot = np.stack([r, u, -f])
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = -rot @ eye
    return m


# --------------------------------------------------------------------------- result
@dataclass
class Reprojection:
    """What :func:`reproject` returns.

    buffers : Buffers of the current frame's shape holding only the reprojected
        statistics (n = k = 0 and zero means where nothing is valid), with the
        same feature passes as ``current``: ``current.merge(buffers)`` pools them.
    valid : (H, W) bool, True where the current pixel received samples.
    counts : dict reason -> number of previous-frame pixels (every name of
        :data:`REASONS`; ``ok`` = reprojected), plus ``source_pixels``,
        ``target_pixels`` (current pixels with samples) and ``samples``
        (reprojected samples, sum of n).
    target : (Hp, Wp) int64 flat index (row * W + col) of the current pixel
        each previous pixel went to, -1 where rejected.
    reason : (Hp, Wp) int8 code into :data:`REASONS` per previous pixel.
    extra : dict name -> (H, W) or (H, W, C) reprojected auxiliary arrays (the
        n-weighted mean of the finite source values; NaN where none).
    info : dict of scalars: ``fraction`` of the current frame reprojected,
        ``camera_cut`` (True when fewer than ``min_valid_fraction`` of the
        current pixels validated: the frame renders fresh), ``view_changed``
        (the camera moved, so Eq. 15 applied), ``used_<pass>`` for the
        optional passes found in both frames.
    """

    buffers: Buffers
    valid: np.ndarray
    counts: dict
    target: np.ndarray
    reason: np.ndarray
    extra: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    @property
    def fraction(self) -> float:
        return float(self.info.get("fraction", 0.0))


# --------------------------------------------------------------------------- helpers
def _feature(buf: Buffers, name: str):
    st = buf.features.get(name)
    return None if st is None else st


def _background(pos: np.ndarray, depth: np.ndarray | None) -> np.ndarray:
    """Background = no surface hit: position exactly 0 (and depth 0 or >= FAR_DEPTH)."""
    bg = np.all(pos == 0.0, axis=-1)
    if depth is not None:
        d = depth[..., 0]
        bg &= (d == 0.0) | (d >= FAR_DEPTH)
    return bg


def _var_of_mean(buf: Buffers, stat: Stat, idx: np.ndarray) -> np.ndarray:
    """(N, C) variance of the mean at flat pixels ``idx``; +inf where unknown,
    0 where the mean is exactly 0 (non-negative light passes: all samples 0)."""
    c = stat.mean.shape[-1]
    k = buf.k.reshape(-1)[idx]
    n = buf.n.reshape(-1)[idx]
    m2 = stat.m2.reshape(-1, c)[idx]
    mean = stat.mean.reshape(-1, c)[idx]
    ok = (k >= 2) & (n > 0)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        v = m2 / (np.where(ok, k - 1.0, 1.0) * np.where(ok, n, 1.0))[:, None]
    v = np.where(ok[:, None] & np.isfinite(v), np.maximum(v, 0.0), np.inf)
    return np.where(mean == 0.0, 0.0, v)


def _bound(s_p, v_p, s_t, v_t, z):
    """Eq. 15 bound for one light pass, per channel (see module docstring)."""
    sp_ = np.sqrt(v_p)
    st_ = np.sqrt(v_t)
    with np.errstate(invalid="ignore", over="ignore"):
        direct = np.abs(s_t - s_p) + z * np.sqrt(v_p + v_t)
        nonneg = np.maximum(s_p + z * sp_, s_t + z * st_)
        b = np.minimum(direct, nonneg)
    return np.where(np.isnan(b), np.inf, b)


# --------------------------------------------------------------------------- reprojection
def reproject(prev: Buffers, prev_camera: Camera, current: Buffers, current_camera: Camera,
              params: Params | dict | None = None, extra: dict | None = None) -> Reprojection:
    """Forward-reproject the previous frame's accumulated samples into the current frame
    (thesis Sec. 3.2 with the validations of Sec. 3.2/3.2.1 and Algorithm 2's
    ``ReprojectError(P) <= eps``).

    Parameters
    ----------
    prev : Buffers (Hp, Wp)
        Frame t-1's accumulated statistics; needs the ``position`` pass and
        every feature pass ``current`` has.
    prev_camera, current_camera : Camera
        The two frames' cameras (see the module docstring for conventions).
    current : Buffers (H, W)
        Frame t's own initial pass (at least one full-frame subset): its
        position / depth / object index / glossy / transmission / colour at the
        target pixels are what the occlusion, object, view-dependence and
        change tests compare with.  It is not modified.
    params : Params or dict (defaults: thesis values and the module docstring).
    extra : dict name -> (Hp, Wp) or (Hp, Wp, C) arrays to carry along (e.g. the
        var sampler's per-pixel probability), see ``Reprojection.extra``.

    Returns
    -------
    Reprojection
        Merge with ``current.merge(result.buffers)`` (Chan; n, mean, M2 and k
        equal pooling all samples).  Never contains NaN/Inf in its buffers.
    """
    params = _params(params)
    if not isinstance(prev_camera, Camera) or not isinstance(current_camera, Camera):
        raise TypeError("prev_camera and current_camera must be reproject.Camera objects")
    for name, b in (("previous", prev), ("current", current)):
        if "position" not in b.features:
            raise ValueError(f"reprojection needs the Position pass in the {name} frame "
                             "(render with use_pass_position; outputs without it cannot be reused)")
    missing = [f for f in current.features if f not in prev.features]
    if missing:
        raise ValueError(f"previous frame lacks feature pass(es) {missing} that the current frame has")
    hp, wp = prev.shape
    h, w = current.shape
    out = Buffers.empty(h, w, tuple(current.features))
    for name, st in current.features.items():       # keep the channel counts of ``current``
        c = st.mean.shape[-1]
        out.features[name] = Stat(np.zeros((h, w, c)), np.zeros((h, w, c)))
    counts = {r: 0 for r in REASONS}
    counts.update(source_pixels=hp * wp, target_pixels=0, samples=0)
    reason = np.zeros((hp, wp), np.int8)
    target = np.full((hp, wp), -1, np.int64)
    info = {"fraction": 0.0, "camera_cut": False}
    move = float(np.linalg.norm(current_camera.position - prev_camera.position))
    scale = max(float(np.linalg.norm(current_camera.position)), float(np.linalg.norm(prev_camera.position)), 1.0)
    view_changed = move > 1e-12 * scale
    info["view_changed"] = bool(view_changed)
    have = {p: (p in prev.features and p in current.features) for p in PASSES}
    info.update({f"used_{p}": bool(have[p]) for p in PASSES})
    if hp * wp == 0 or h * w == 0:
        return Reprojection(out, np.zeros((h, w), bool), counts, target, reason,
                            _empty_extra(extra, h, w), info)

    # ---- current-frame data, flat
    cur_pos = current.features["position"].mean.reshape(-1, 3)
    cur_depth = current.features["depth"].mean.reshape(-1, current.features["depth"].mean.shape[-1]) \
        if "depth" in current.features else None
    cur_bg = _background(cur_pos, cur_depth)
    cur_n = current.n.reshape(-1)
    cur_known = np.all(np.isfinite(cur_pos), axis=1) & (cur_n > 0)
    prev_pos_all = prev.features["position"].mean.reshape(-1, 3)
    prev_depth_all = prev.features["depth"].mean.reshape(-1, prev.features["depth"].mean.shape[-1]) \
        if "depth" in prev.features else None

    chunk = max(int(params.chunk), 1)
    npx = hp * wp
    for s0 in range(0, npx, chunk):
        idx = np.arange(s0, min(npx, s0 + chunk))
        code, tgt = _validate_chunk(idx, prev, prev_camera, current, current_camera, params,
                                    prev_pos_all, prev_depth_all, cur_pos, cur_bg, cur_known,
                                    view_changed, have, (hp, wp), (h, w))
        reason.reshape(-1)[idx] = code
        target.reshape(-1)[idx] = np.where(code == 0, tgt, -1)

    ok_src = np.flatnonzero(reason.reshape(-1) == 0)
    tgt_ok = target.reshape(-1)[ok_src]
    n_targets = np.unique(tgt_ok).size if ok_src.size else 0
    if n_targets < params.min_valid_fraction * h * w:
        info["camera_cut"] = True
        reason.reshape(-1)[ok_src] = _R["camera_cut"]
        target.reshape(-1)[ok_src] = -1
        ok_src = ok_src[:0]
        tgt_ok = tgt_ok[:0]
    for i, r in enumerate(REASONS):
        counts[r] = int(np.count_nonzero(reason == i))
    if ok_src.size:
        _scatter(prev, out, ok_src, tgt_ok, h * w, prev_camera, current_camera)
    valid = out.n > 0
    counts["target_pixels"] = int(valid.sum())
    counts["samples"] = int(round(float(out.n.sum())))
    info["fraction"] = float(valid.mean())
    ex = _carry_extra(extra, prev, ok_src, tgt_ok, (hp, wp), (h, w))
    return Reprojection(out, valid, counts, target, reason, ex, info)


def _validate_chunk(idx, prev, pcam, cur, ccam, params, prev_pos_all, prev_depth_all,
                    cur_pos, cur_bg, cur_known, view_changed, have, pshape, cshape):
    """Reason code (int8) and target flat index for the previous pixels ``idx``."""
    hp, wp = pshape
    h, w = cshape
    m = idx.size
    code = np.zeros(m, np.int8)

    def reject(mask, name):
        sel = (code == 0) & mask
        code[sel] = _R[name]

    # empty / non-finite statistics
    n = prev.n.reshape(-1)[idx]
    k = prev.k.reshape(-1)[idx]
    cm = prev.color.mean.reshape(-1, 3)[idx]
    c2 = prev.color.m2.reshape(-1, 3)[idx]
    stats_ok = np.isfinite(n) & (n > 0) & np.isfinite(k) & (k > 0) & np.all(np.isfinite(cm), 1) \
        & np.all(np.isfinite(c2), 1)
    for name, st in prev.features.items():
        if name in ("position", "depth"):
            continue                          # tested as ``no_position``
        c = st.mean.shape[-1]
        stats_ok &= np.all(np.isfinite(st.mean.reshape(-1, c)[idx]), 1) \
            & np.all(np.isfinite(st.m2.reshape(-1, c)[idx]), 1)
    reject(~stats_ok, "empty")
    # positions
    pos = prev_pos_all[idx]
    pos_ok = np.all(np.isfinite(pos), axis=1)
    depth = prev_depth_all[idx] if prev_depth_all is not None else None
    if depth is not None:
        pos_ok &= np.all(np.isfinite(depth), axis=1)
    reject(~pos_ok, "no_position")
    pos = np.where(pos_ok[:, None], pos, 0.0)
    bg = _background(pos, depth) & pos_ok
    if not params.background:
        reject(bg, "background")
    # consistency of position and depth (single clean first hit)
    dist_p = np.linalg.norm(pos - pcam.position[None, :], axis=1)
    if depth is not None and params.consistency_tolerance > 0:
        d = depth[:, 0]
        zdep = -(pos @ pcam.view[2, :3] + pcam.view[2, 3])
        tol = params.consistency_tolerance * dist_p
        consistent = (np.abs(dist_p - d) <= tol) | (np.abs(zdep - d) <= tol)
        reject(~bg & ~consistent, "inconsistent")
    # (a) projection into the new camera
    rows = idx // wp
    cols = idx % wp
    clip = ccam.clip(pos, 1.0)
    if bg.any():
        dirs = pcam.ray_directions(rows[bg].astype(np.float64), cols[bg].astype(np.float64), hp, wp)
        clip[bg] = ccam.clip(np.where(np.isfinite(dirs), dirs, 0.0), 0.0)
        bad_dir = ~np.all(np.isfinite(dirs), axis=1)
        tmp = np.zeros(m, bool)
        tmp[np.flatnonzero(bg)[bad_dir]] = True
        reject(tmp, "outside")
    row, col, front = ccam.pixel_coordinates(clip, h, w)
    inside = front & (row >= 0) & (row < h) & (col >= 0) & (col < w)
    reject(~inside, "outside")
    ti = np.clip(np.floor(np.where(inside, row, 0.0)), 0, h - 1).astype(np.int64)
    tj = np.clip(np.floor(np.where(inside, col, 0.0)), 0, w - 1).astype(np.int64)
    tgt = ti * w + tj
    # (b) occlusion: compare with the new frame's first hit at the target
    known = cur_known[tgt]
    tbg = cur_bg[tgt]
    wt = np.where(known[:, None], cur_pos[tgt], 0.0)
    dist_c = np.linalg.norm(pos - ccam.position[None, :], axis=1)
    fp = ccam.footprint(clip, h, w)
    tol = params.occlusion_tolerance * dist_c + params.occlusion_pixels * fp
    same_surface = np.linalg.norm(pos - wt, axis=1) <= tol
    # the ray towards P passes through the sub-pixel point (row, col): where the four
    # surrounding pixel centres are known surface hits, their bilinear interpolation
    # approximates that ray's hit (to second order on smooth surfaces), which keeps
    # slanted and grazing surfaces (first-order variation s / cos(theta)) from failing
    interp = _interpolate_position(row, col, cur_pos, cur_known & ~cur_bg, h, w)
    with np.errstate(invalid="ignore"):
        same_surface |= np.linalg.norm(pos - interp, axis=1) <= tol
    visible = known & np.where(bg, tbg, ~tbg & same_surface)
    reject(~visible, "occluded")
    # (d) object index
    if have["object_index"]:
        oi_p = prev.features["object_index"].mean.reshape(-1, prev.features["object_index"].mean.shape[-1])[idx, 0]
        oi_t = cur.features["object_index"].mean.reshape(-1, cur.features["object_index"].mean.shape[-1])[tgt, 0]
        with np.errstate(invalid="ignore"):
            same = np.abs(oi_p - oi_t) <= params.object_index_tolerance
        reject(~same, "object_index")
    # specular share and the Eq. 15 bound (surfaces only: the environment is not view dependent)
    surf = ~bg
    lum_p = np.maximum(luminance(cm), 0.0)
    cur_cm = cur.color.mean.reshape(-1, 3)[tgt]
    lum_t = np.maximum(luminance(np.where(np.isfinite(cur_cm), cur_cm, 0.0)), 0.0)
    vd_p = np.zeros(m)
    vd_t = np.zeros(m)
    eps = np.zeros(m)
    complete = True
    for pname in ("glossy", "transmission"):
        if not have[pname]:
            complete = False
            continue
        sp = prev.features[pname]
        stc = cur.features[pname]
        c = sp.mean.shape[-1]
        s_p = sp.mean.reshape(-1, c)[idx]
        s_t = stc.mean.reshape(-1, stc.mean.shape[-1])[tgt]
        s_t = np.where(np.isfinite(s_t), s_t, np.inf)
        vd_p += np.maximum(luminance(s_p[:, :3]) if c >= 3 else s_p[:, 0], 0.0)
        vd_t += np.maximum(luminance(s_t[:, :3]) if s_t.shape[1] >= 3 else s_t[:, 0], 0.0)
        v_p = _var_of_mean(prev, sp, idx)
        v_t = _var_of_mean(cur, stc, tgt)
        eps = eps + _bound(s_p, v_p, s_t, v_t, params.confidence).max(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        share_p = np.where(vd_p > 0, vd_p / np.where(lum_p > 0, lum_p, 0.0), 0.0)
        share_t = np.where(vd_t > 0, vd_t / np.where(lum_t > 0, lum_t, 0.0), 0.0)
    share_p = np.where(np.isnan(share_p), np.inf, share_p)
    share_t = np.where(np.isnan(share_t), np.inf, share_t)
    reject(surf & (np.maximum(share_p, share_t) > params.max_specular_share), "specular")
    if view_changed:
        if not complete and not params.assume_diffuse:
            eps = np.full(m, np.inf)
        reject(surf & ~(eps <= params.max_error), "view_dependence")
    # change of the radiance itself (moving shadows, lights, animated textures): Welch-free
    # two-sample test with the per-sample variance pooled over both frames (under "unchanged"
    # both frames sample the same pixel integrand), s^2 = (M2_p + M2_t) / (k_p - 1 + k_t - 1)
    if params.changed_sigma > 0:
        k_t = cur.k.reshape(-1)[tgt]
        n_t = cur.n.reshape(-1)[tgt]
        m2_t = cur.color.m2.reshape(-1, 3)[tgt]
        dof = np.maximum(k - 1.0, 0.0) + np.maximum(k_t - 1.0, 0.0)
        known_v = (dof > 0) & (n > 0) & (n_t > 0) & np.all(np.isfinite(m2_t), axis=1)
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            s2 = (c2 + m2_t) / np.where(known_v, dof, 1.0)[:, None]
            v = s2 * (1.0 / np.where(n > 0, n, 1.0) + 1.0 / np.where(n_t > 0, n_t, 1.0))[:, None]
            diff = np.abs(cm - np.where(np.isfinite(cur_cm), cur_cm, np.inf))
            lim = params.changed_sigma * np.sqrt(np.maximum(v, 0.0)) + params.max_error
            bad = known_v[:, None] & ~(diff <= lim)
        reject(bad.any(axis=1), "changed")
    return code, tgt


def _interpolate_position(row, col, cur_pos, usable, h, w):
    """Bilinear interpolation of the current frame's positions at continuous
    pixel coordinates (pixel centres at +0.5); NaN where one of the four
    surrounding pixels is outside, unknown or background."""
    r = np.where(np.isfinite(row), row, 0.0) - 0.5
    c = np.where(np.isfinite(col), col, 0.0) - 0.5
    r0 = np.floor(r).astype(np.int64)
    c0 = np.floor(c).astype(np.int64)
    fr = (r - r0)[:, None]
    fc = (c - c0)[:, None]
    ok = np.isfinite(row) & np.isfinite(col) & (r0 >= 0) & (c0 >= 0) & (r0 + 1 < h) & (c0 + 1 < w)
    out = np.zeros((row.size, 3))
    for dr, dc, wgt in ((0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc),
                        (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
        rr = np.clip(r0 + dr, 0, max(h - 1, 0))
        cc = np.clip(c0 + dc, 0, max(w - 1, 0))
        f = rr * w + cc
        ok &= usable[f]
        out += wgt * np.where(usable[f][:, None], cur_pos[f], 0.0)
    return np.where(ok[:, None], out, np.nan)


def _scatter(prev: Buffers, out: Buffers, src: np.ndarray, tgt: np.ndarray, size: int,
             pcam: Camera, ccam: Camera) -> None:
    """Pool the statistics of the sources ``src`` (flat previous indices) into
    the targets ``tgt`` of ``out`` (Chan's pooled update; a single source is
    copied exactly).  Sources are sorted by target once; every pass is then a
    segmented sum (``np.add.reduceat``) over the groups."""
    order = np.argsort(tgt, kind="stable")
    src = src[order]
    ts = tgt[order]
    starts = np.flatnonzero(np.r_[True, ts[1:] != ts[:-1]])
    uniq = ts[starts]
    counts = np.diff(np.r_[starts, ts.size])
    n_s = prev.n.reshape(-1)[src]
    k_s = prev.k.reshape(-1)[src]
    n_t = np.add.reduceat(n_s, starts)
    out.n.reshape(-1)[uniq] = n_t
    out.k.reshape(-1)[uniq] = np.add.reduceat(k_s, starts)
    safe_n = np.where(n_t > 0, n_t, 1.0)[:, None]
    multi = counts > 1                                    # targets hit by several sources
    msel = np.repeat(multi, counts)                       # their sources (sorted)
    mstarts = np.r_[0, np.cumsum(counts[multi])[:-1]].astype(np.int64)

    # camera-dependent feature transforms
    pos = prev.features["position"].mean.reshape(-1, 3)[src]
    transforms = {}
    if "depth" in prev.features:
        d = prev.features["depth"].mean.reshape(-1, prev.features["depth"].mean.shape[-1])[src]
        dist_p = np.linalg.norm(pos - pcam.position, axis=1)
        dist_c = np.linalg.norm(pos - ccam.position, axis=1)
        z_p = -(pos @ pcam.view[2, :3] + pcam.view[2, 3])
        z_c = -(pos @ ccam.view[2, :3] + ccam.view[2, 3])
        use_z = np.abs(z_p - d[:, 0]) < np.abs(dist_p - d[:, 0])
        shift = np.where(use_z, z_c - z_p, dist_c - dist_p)
        bg = _background(pos, d)
        shift = np.where(bg | ~np.isfinite(shift), 0.0, shift)
        transforms["depth"] = ("shift", shift)
    rot = ccam.rotation @ pcam.rotation.T
    if not np.allclose(rot, np.eye(3), atol=1e-14):
        transforms["normal"] = ("rotate", rot)

    def pool(stat_src: Stat, stat_out: Stat, name=None):
        c = stat_src.mean.shape[-1]
        m = stat_src.mean.reshape(-1, c)[src]
        m2 = stat_src.m2.reshape(-1, c)[src]
        tr = transforms.get(name)
        if tr is not None and tr[0] == "shift":
            m = m + tr[1][:, None]
        elif tr is not None and tr[0] == "rotate" and c == 3:
            r = tr[1]
            m = m @ r.T
            m2 = (np.sqrt(np.maximum(m2, 0.0)) @ np.abs(r).T) ** 2
        mean = m[starts]                                  # single sources: copied exactly
        ss = m2[starts]
        if multi.any():
            ref = mean[multi]                             # one source's mean per target
            dm = m[msel] - np.repeat(ref, counts[multi], axis=0)
            mm = ref + np.add.reduceat(n_s[msel, None] * dm, mstarts, axis=0) / safe_n[multi]
            dev = m[msel] - np.repeat(mm, counts[multi], axis=0)
            mean[multi] = mm
            ss[multi] = np.add.reduceat(m2[msel] + n_s[msel, None] * dev * dev, mstarts, axis=0)
        mean = np.where(np.isfinite(mean), mean, 0.0)
        ss = np.where(np.isfinite(ss), np.maximum(ss, 0.0), 0.0)
        stat_out.mean.reshape(-1, c)[uniq] = mean
        stat_out.m2.reshape(-1, c)[uniq] = ss

    for name, st in out.features.items():
        c_out = st.mean.shape[-1]
        if prev.features[name].mean.shape[-1] != c_out:
            raise ValueError(f"feature pass {name!r} has {prev.features[name].mean.shape[-1]} channels "
                             f"in the previous frame and {c_out} in the current one")
    pool(prev.color, out.color)
    for name, st in out.features.items():
        pool(prev.features[name], st, name)


def _empty_extra(extra, h, w):
    out = {}
    for name, arr in (extra or {}).items():
        a = np.asarray(arr, np.float64)
        out[name] = np.full((h, w) + a.shape[2:], np.nan)
    return out


def _carry_extra(extra, prev, src, tgt, pshape, cshape):
    """n-weighted mean of finite source values per target; NaN where none."""
    h, w = cshape
    out = _empty_extra(extra, h, w)
    if not extra or src.size == 0:
        return out
    n_s = prev.n.reshape(-1)[src]
    for name, arr in extra.items():
        a = np.asarray(arr, np.float64)
        if a.shape[:2] != pshape:
            raise ValueError(f"extra array {name!r} has shape {a.shape}, the previous frame is {pshape}")
        flat = a.reshape(pshape[0] * pshape[1], -1)[src]
        res = np.full((h * w, flat.shape[1]), np.nan)
        for ch in range(flat.shape[1]):
            v = flat[:, ch]
            fin = np.isfinite(v)
            wsum = np.bincount(tgt[fin], weights=n_s[fin], minlength=h * w)
            vsum = np.bincount(tgt[fin], weights=n_s[fin] * v[fin], minlength=h * w)
            with np.errstate(invalid="ignore", divide="ignore"):
                res[:, ch] = np.where(wsum > 0, vsum / np.where(wsum > 0, wsum, 1.0), np.nan)
        out[name] = res.reshape((h, w) + a.shape[2:])
    return out


# --------------------------------------------------------------------------- backward map
def backward_coordinates(prev_camera: Camera, current_camera: Camera, current: Buffers,
                         prev_shape: tuple) -> np.ndarray:
    """Where each current pixel's first hit was in the previous frame.

    Projects the current frame's Position (background pixels: their ray
    direction) with the previous camera.  Returns (H, W, 2) float64
    continuous (row, col) in the previous frame (pixel ``(floor(row),
    floor(col))``), NaN where the point was behind that camera, off its screen,
    or the position is unknown.  (Occlusion in the previous frame is not
    tested: this is a search centre, e.g. for ``temporal.step(center=...)``.)
    """
    h, w = current.shape
    hp, wp = int(prev_shape[0]), int(prev_shape[1])
    out = np.full((h, w, 2), np.nan)
    if h * w == 0 or "position" not in current.features:
        return out
    pos = current.features["position"].mean.reshape(-1, 3)
    depth = current.features["depth"].mean.reshape(-1, current.features["depth"].mean.shape[-1]) \
        if "depth" in current.features else None
    ok = np.all(np.isfinite(pos), axis=1)
    pos0 = np.where(ok[:, None], pos, 0.0)
    bg = _background(pos0, depth) & ok
    clip = prev_camera.clip(pos0, 1.0)
    if bg.any():
        idx = np.flatnonzero(bg)
        dirs = current_camera.ray_directions((idx // w).astype(np.float64), (idx % w).astype(np.float64), h, w)
        fin = np.all(np.isfinite(dirs), axis=1)
        clip[idx] = prev_camera.clip(np.where(fin[:, None], dirs, 0.0), 0.0)
        ok[idx[~fin]] = False
    row, col, front = prev_camera.pixel_coordinates(clip, hp, wp)
    good = ok & front & (row >= 0) & (row < hp) & (col >= 0) & (col < wp)
    out.reshape(-1, 2)[good, 0] = row[good]
    out.reshape(-1, 2)[good, 1] = col[good]
    return out


# --------------------------------------------------------------------------- Algorithm 2
def sampling_priority(buf: Buffers, probability: np.ndarray | None, var_params=None) -> np.ndarray:
    """Sampling priority of Algorithm 2 (thesis Sec. 3.3) after a reprojection.

    Pixels that carry a probability from the previous frame (reprojected from a
    pixel that had finished Algorithm 1's threshold phase) wait: they get no
    samples until ``itr`` reaches ``max_spp``; every other pixel (not
    reprojected, or reprojected before its probability was set) follows
    Algorithm 1: ready while ``spp < min_spp`` or ``Pvariance >= tau``.

    Parameters
    ----------
    buf : Buffers, the frame's statistics after merging the reprojection.
    probability : (H, W) reprojected probability (``Reprojection.extra`` of the
        var state's ``prob``), NaN where none was calculated; None = none.
    var_params : ``var.Params``.

    Returns
    -------
    (H, W) float64, larger = sampled first: ``+inf`` below ``min_spp``,
    ``Pvariance`` (Eq. 12, > 0) for pixels without a probability, ``-1`` for
    pixels that carry one (never ready in the threshold phase, where tau >= 0).
    """
    from . import var
    vp = var_params if var_params is not None else var.Params()
    pv = var.pixel_priority(buf, vp)
    pv = np.where(np.isnan(pv), np.inf, pv)
    has_prob = _has_probability(probability, buf.shape)
    spp = np.where(np.isfinite(buf.n), buf.n, 0.0)
    out = np.where(has_prob, -1.0, pv)
    return np.where(~has_prob & (spp < vp.min_spp), np.inf, out)


def _has_probability(probability, shape):
    if probability is None:
        return np.zeros(shape, bool)
    p = np.asarray(probability, np.float64)
    if p.shape != tuple(shape):
        raise ValueError(f"probability map has shape {p.shape}, the frame is {tuple(shape)}")
    return np.isfinite(p)


def sample_map(buf: Buffers, result: MethodResult | None, budget: int, params=None,
               state: dict | None = None) -> np.ndarray:
    """The next ``budget`` samples of Algorithm 2 (thesis Sec. 3.3) as a map.

    Same contract and mapping onto region iterations as ``var.sample_map``
    (Algorithm 1; ``params`` is a ``var.Params``), with Algorithm 2's changes:

    * ``state['probability']`` (H, W): the reprojected probabilities (NaN where
      the pixel has none).  Pixels with one are never ready while
      ``itr < max_spp`` (``else if !PprobabilityCalculated``), so the threshold
      phase spends the budget on pixels that were not reprojected (or were
      reprojected before their probability was set): those have priority.
    * at ``itr == max_spp`` the pixels without a probability get
      ``spp / max_spp``; reprojected probabilities are kept ("they also copy
      the calculated variance/probability", Sec. 3.3).  Probabilities are
      clipped to ``[min_spp / max_spp, 1]`` (a pixel with carried samples may
      exceed ``max_spp``: the thesis' "incorrect probabilities", clipped).
    * ``itr`` restarts at the frame: the loop's initial pass (which the
      occlusion test needs) counts as iterations ``0 .. n0-1``; ``state['itr']``
      may be preset.

    Returns (H, W) int64 >= 0 summing exactly to ``budget``.
    """
    from . import var
    params = params if params is not None else var.Params()
    if state is None:
        state = {}
    h, w = buf.shape
    npx = h * w
    out = np.zeros(npx, np.int64)
    remaining = int(max(0, budget))
    if npx == 0 or remaining == 0:
        return out.reshape(h, w)
    has_prob = _has_probability(state.get("probability"), buf.shape).ravel()
    if state.get("var_shape") != tuple(buf.shape) or "rng" not in state:
        preset = state.get("itr")
        var._init_state(buf, params, state)
        if preset is None:
            n = np.asarray(buf.n, np.float64)[~has_prob.reshape(h, w)]
            n = n[np.isfinite(n)]
            state["itr"] = int(np.floor(n.min())) if n.size else 0
    lo, hi = int(params.min_spp), int(params.max_spp)
    p_floor = min(1.0, max(lo, 1) / max(hi, 1))
    itr, cursor = int(state["itr"]), int(state["cursor"])
    n = np.asarray(buf.n, np.float64).ravel()
    spp = np.where(np.isfinite(n) & (n > 0), n, 0.0)
    if itr < hi:
        pv = var.pixel_priority(buf, params).ravel()
        while remaining > 0 and itr < hi:
            tau = var.threshold(itr, params)
            ready = ((pv >= tau) | (spp < lo)) & ~has_prob
            if cursor:
                ready[:cursor] = False
            cnt = int(np.count_nonzero(ready))
            if cnt > remaining:
                idx = np.flatnonzero(ready)[:remaining]
                out[idx] += 1
                spp[idx] += 1
                cursor = int(idx[-1]) + 1
                remaining = 0
                break
            out += ready
            spp += ready
            remaining -= cnt
            itr, cursor = itr + 1, 0
    if itr >= hi and state.get("prob") is None:
        carried = np.asarray(state["probability"], np.float64).ravel() if has_prob.any() else None
        prob = spp / max(hi, 1)
        if carried is not None:
            prob = np.where(has_prob, carried, prob)
        state["prob"] = np.clip(prob, p_floor, 1.0).reshape(h, w)
    if remaining > 0:
        itr, cursor = var.probability_phase(out, state["prob"], p_floor, remaining, itr, cursor,
                                            state["rng"])
    state["itr"], state["cursor"] = itr, cursor
    state["tau"] = var.threshold(itr, params)
    return out.reshape(h, w)

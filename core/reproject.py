"""Forward reprojection of accumulated samples between animation frames
(Schalk 2018, "Reprojection for adaptive sampling", thesis Sec. 3.2-3.3).

Each pixel of the previous frame ``t-1`` keeps its accumulated statistics
(``Buffers``: mean, between-group M2, samples n, groups k, feature passes).  Its
stored first intersection point (Cycles' Position pass) is projected into the
camera of frame ``t``; where the thesis' validations pass, the statistics are
copied ("each pixel is copied to a new assigned pixel depending on the camera
matrix", Sec. 3.2) and Chan-merged into the new frame.  :func:`reproject` does
this for a whole frame (vectorised, chunked over source pixels);
:func:`backward_coordinates` maps current pixels back into the previous frame
(for ``core.temporal``'s search window).  This module is the geometry only:
Algorithm 2's sampler, which gives the pixels that were not reprojected
priority, is ``core.var.REPROJECT``.

Conventions (what the frame loop passes)
----------------------------------------
Cameras (:class:`Camera`, :meth:`Camera.from_render` from the executor's
record): ``view`` is the 4x4 world-to-camera matrix (Blender:
``camera.matrix_world.inverted()``; the camera looks down -Z), ``proj`` the 4x4
camera-to-clip matrix of the rendered region (Blender's
``calc_matrix_camera(depsgraph, x=W, y=H, scale_x=..., scale_y=...)``, cropped
to a render border by :func:`crop_projection`).  NDC = clip.xyz / clip.w, x and
y in [-1, 1]; a point lies at continuous pixel coordinates ``col = (x + 1) / 2
* W``, ``row = (1 - y) / 2 * H`` (row 0 at the top) and in pixel
``(floor(row), floor(col))``.  ``position`` is the camera's world position (by
default the translation of ``inv(view)``).  Perspective and orthographic
projections work; panoramic cameras cannot be written as a matrix and are not
supported.

Passes (:data:`PASSES`): ``position`` world-space first hit (Position pass),
``depth`` Cycles' Denoising Depth (ray length to the first hit; a camera
z-depth pass is accepted too), ``glossy`` = Glossy Direct + Indirect,
``transmission`` = Transmission Direct + Indirect, ``glossy_color`` /
``transmission_color`` (their colour passes), ``object_index`` (IndexOB),
``normal`` (Denoising Normal, camera space).  Facts measured with bpy 4.5:
Position (like Depth and IndexOB) is written by sample 0 alone, one hit at one
sub-pixel offset (identical at 1 and 16 spp), while Denoising Depth and Normal
are pixel means; the light passes are divided by their colour pass (Combined
equals the sum of colour x (direct + indirect) + emission + environment to
6e-8), and Cycles' camera space looks down +Z (Blender's down -Z).
Every feature pass of ``current`` must also be in ``prev`` (the output Buffers
carries the same passes as ``current``, so ``current.merge(result.buffers)``
works).  A missing Position pass in ``prev`` or ``current`` raises
``ValueError`` (old outputs rendered without it cannot be reprojected).
Background (no surface hit) is ``core.buffers.is_background``.

Validation
----------
Each previous pixel gets the first reason that applies, in the order of
:data:`REASONS` (counts in ``Reprojection.counts``); the function named
applies the test and documents it:

``empty``            no samples, or non-finite statistics (:func:`_empty_statistics`).
``no_position``      non-finite position or depth (:func:`_source_points`).
``background``       no surface was hit and ``Params.background`` is off.  With
                     it on (default) background pixels are reprojected *by
                     direction* (:func:`_clip_coordinates`) and their target
                     must be background too.
``inconsistent``     position and depth disagree by more than one surface's
                     depth change over the pixel: a pixel mixing surfaces at an
                     edge (Sec. 3.2.2's aliasing) or a specular chain
                     (:func:`_inconsistent`); skipped without a depth pass.
``outside``          (a) behind the new camera or off its screen (:func:`_inside_frame`).
``occluded``         (b) the stored point is not the new frame's first hit at
                     the target, within ``occlusion_tolerance * d +
                     occlusion_pixels * footprint`` (:func:`_occluded`).
``object_index``     (d) the object under the pixel changed (:func:`_object_changed`);
                     skipped when either frame lacks the pass.
``specular``         mostly view-dependent light, ``lum(glossy + transmission
                     radiance) / lum(combined) > max_specular_share`` in either
                     frame: the thesis never reprojects specular or refractive
                     materials (:func:`_specular_share`).
``view_dependence``  (c) the Eq. 15 error bound exceeds ``max_error`` (1/256)
                     (:func:`_view_dependence_error`), on radiances pooled
                     over the pixel's surface (:func:`_pooled_light`), and,
                     with ``noise_limited``, the estimated change is not below
                     the noise of the two means (:func:`_change_below_noise`).
``changed``          (addition: Sec. 3 assumes a static scene) the reprojected
                     mean and the new frame's own samples differ by more than
                     ``changed_sigma`` (5) standard errors (:func:`_radiance_changed`);
                     ``changed_sigma = 0`` turns it off.
``camera_cut``       valid, but fewer than ``min_valid_fraction`` of the new
                     frame's pixels received anything: the frame is treated as
                     a cut and renders fresh (nothing is reprojected, never a
                     smear).

The view-dependence bound (c), Eq. 15
-------------------------------------
Eq. 15 is ``eps = |f_r(V_t, L, N) - f_r(V_{t-1}, L, N)| * A * I``: the change of
the pixel's *view-dependent* outgoing radiance between the two viewpoints.
Cycles has no per-pixel roughness or BRDF value, but it does write that
radiance: ``S`` = colour pass x (direct + indirect) light pass, for Glossy and
for Transmission (:func:`_radiance`).  For each channel, with ``S_p`` the
previous pixel's value, ``S_t`` the current
frame's initial-pass value at the target, ``sigma`` their standard errors and
``z = confidence``:

* if the view direction to the point did not change (``C_t == C_{t-1}``, e.g.
  a static camera or a pure rotation) ``f_r(V_t) = f_r(V_{t-1})`` and
  ``eps = 0`` exactly;
* otherwise ``eps <= min(|S_t - S_p| + z sqrt(sigma_t^2 + sigma_p^2),
  max(S_p + z sigma_p, S_t + z sigma_t))``: a direct (upper-confidence)
  estimate of Eq. 15's difference measured by the renderer itself, or, for
  every BRDF since both radiances are >= 0, the larger radiance.  Glossy and
  transmission are bounded separately and added (triangle inequality); the
  channel maximum is compared with ``max_error``.

Without the colour passes (outputs rendered before they were requested)
``S`` is the light pass alone, which overstates the radiance by 1 / colour
(conservative: far fewer pixels validate); an unknown variance makes the bound infinite,
except for a pass whose mean is exactly 0; a missing glossy or transmission
pass makes it infinite unless the camera kept its position (or
``assume_diffuse`` is set).  The thesis' error is absolute, in image units:
1/256 is one 8-bit step of a display value of 1.

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
by ``R_t R_{t-1}^T`` (written in Cycles' camera space, ``F R_t R_{t-1}^T F``
with F the z flip; its M2 is bounded by ``(sum_j |R_ij| sqrt(M2_j))^2``,
the off-diagonal scatter being unknown); ``vector`` (motion) is per-frame data
and is carried unchanged (do not rely on it); the rest are view-independent on
validated pixels and are carried as they are.

Measurements and design notes: docs/notes/reproject.md
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .buffers import Buffers, Stat, is_background, luminance
from .method import param

#: passes the reprojection reads (position is required, the rest are optional)
PASSES = ("position", "depth", "glossy", "transmission", "glossy_color", "transmission_color",
          "object_index", "normal")

#: rejection reasons, in the order they are tested (code = index)
REASONS = ("ok", "empty", "no_position", "background", "inconsistent", "outside", "occluded",
           "object_index", "specular", "view_dependence", "changed", "camera_cut")
_R = {name: i for i, name in enumerate(REASONS)}


#: ``Params.noise_limited``: ``auto`` is resolved by the caller (:func:`resolve_noise_limited`)
NOISE_LIMITED = ("auto", "on", "off")

#: methods whose image is the sample mean: ``noise_limited = auto`` means on for them
SAMPLE_MEAN_METHODS = ("uniform", "var")


# --------------------------------------------------------------------------- params
@dataclass
class Params:
    """Validation thresholds (thesis Sec. 3.2-3.3; see the module docstring)."""

    max_error: float = param(
        1.0 / 256.0, "Algorithm 2's maximum reprojection error epsilon (thesis: 1/256), absolute in image "
        "units: the Eq. 15 view-dependence bound must stay below it. Larger reprojects more "
        "glossy pixels (faster, risks stale highlights)", 0.0, 1.0, label="Max Reprojection Error")
    max_specular_share: float = param(
        0.5, "pixels whose glossy + transmission light exceeds this share of the combined "
        "luminance are never reprojected (thesis: no specular/refractive reprojection). "
        "Smaller is safer, larger reuses more", 0.0, 1.0, label="Max Specular Share")
    noise_limited: str = param(
        "auto", "also reproject where the estimated view-dependent change is below the noise of "
        "the two sample means being merged (addition: the merged sample mean then has a lower "
        "expected squared error); off = the thesis' Eq. 15 bound against Max Reprojection Error "
        "alone; auto = on for methods whose image is the sample mean (uniform, var), off for "
        "denoisers, which remove the noise it trades against and keep the bias",
        choices=NOISE_LIMITED, label="Noise-Limited Reuse")
    view_dependence_radius: int = param(
        2, "radius of the window over which the glossy / transmission radiance is pooled "
        "(same object, normal and depth) before the Eq. 15 bound: the thesis evaluates the BRDF "
        "noise-free, a few samples' radiance is not; 0 = per pixel", 0, 8, label="View Dependence Window")
    confidence: float = param(
        2.0, "z of the upper confidence bounds on noisy glossy/transmission passes in the Eq. 15 "
        "bound; larger is more conservative (fewer glossy pixels reprojected)", 0.0, 10.0, label="Confidence")
    occlusion_tolerance: float = param(
        0.01, "occlusion test epsilon as a fraction of the camera distance (added to "
        "occlusion_pixels footprints); larger accepts more but misses occluders closer "
        "to the surface", 0.0, 1.0, label="Occlusion Tolerance")
    occlusion_pixels: float = param(
        1.0, "occlusion test slack in pixel footprints at the point's distance (sub-pixel "
        "offsets on slanted surfaces); larger accepts more grazing surfaces", 0.0, 16.0, label="Occlusion Slack (px)")
    consistency_tolerance: float = param(
        0.01, "relative mismatch allowed between a pixel's position and its depth before it "
        "counts as mixed (edges) or a specular chain; 0 disables the test", 0.0, 1.0, label="Depth Consistency")
    consistency_pixels: float = param(
        1.0, "slack of the depth consistency test in pixel footprints times tan(incidence): the "
        "Position pass is one sample's hit anywhere under the pixel filter (0.75 px radius at "
        "Blender's default 1.5 px), the depth the pixel mean, so a slanted surface differs by "
        "up to 0.75 footprints x tan(incidence); 0 = the relative tolerance alone", 0.0, 16.0,
        label="Depth Consistency Slack (px)")
    object_index_tolerance: float = param(
        1e-3, "largest change of the (pixel-mean) object index still counted as the same object", 0.0, 1.0, label="Object Index Tolerance")
    changed_sigma: float = param(
        5.0, "reject pixels whose reprojected mean differs from the new frame's own samples by "
        "more than this many standard errors (+ max_error): moving shadows, lights, "
        "animated textures; 0 disables (thesis: static scenes only)", 0.0, 100.0, label="Change Rejection")
    background: bool = param(
        True, "reproject background (environment) pixels by direction; off leaves them to be "
        "rendered fresh", label="Reproject Background")
    assume_diffuse: bool = param(
        False, "treat missing glossy/transmission passes as zero (everything diffuse); off "
        "rejects every pixel whose view changed when they are missing", label="Assume Diffuse")
    min_valid_fraction: float = param(
        0.01, "if fewer than this fraction of the new frame's pixels receive reprojected "
        "samples the frame is treated as a camera cut and nothing is reprojected", 0.0, 1.0, label="Min Reused Fraction")
    chunk: int = param(
        65536, "source pixels processed per vectorised batch (memory ~ 1 KB per pixel in flight)",
        256, 4194304, label="Batch Size")


def resolve_noise_limited(params: Params, method: str) -> Params:
    """``params`` with ``noise_limited = auto`` resolved for ``method``: on
    where the image is the sample mean (:data:`SAMPLE_MEAN_METHODS`), off
    for denoisers (measured on the animated scene, docs/notes/reproject.md:
    uniform 0.67x the relMSE without history, OIDN 1.7x worse with it)."""
    if params.noise_limited != "auto":
        return params
    from dataclasses import replace
    return replace(params, noise_limited="on" if method in SAMPLE_MEAN_METHODS else "off")


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

    @classmethod
    def from_render(cls, info: dict) -> "Camera":
        """The camera of a rendered frame from the executor's camera record.

        info : dict with ``world_to_camera`` (4, 4), ``projection`` (4, 4)
            camera-to-clip for the FULL frame (Blender's
            ``calc_matrix_camera``), ``position`` (3,), ``width`` and
            ``height`` of the full frame, ``domain`` (x0, y0, x1, y1) the
            rendered region in top-left pixel coordinates (the scene's
            border, if any).  The projection is cropped to the domain
            (:func:`crop_projection`), so NDC [-1, 1] spans the rendered
            pixels, as the Buffers do.
        """
        proj = crop_projection(info["projection"], info["width"], info["height"], info["domain"])
        return cls(info["world_to_camera"], proj, info["position"])

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


def crop_projection(projection, width, height, domain) -> np.ndarray:
    """Camera-to-clip matrix of a rendered sub-region (a render border).

    ``projection`` (4, 4) maps the full ``width`` x ``height`` frame to NDC
    [-1, 1]; ``domain`` (x0, y0, x1, y1) is the rendered region in top-left
    pixel coordinates (exclusive upper bounds).  The result maps the domain's
    pixels to NDC [-1, 1] instead: ``x' = a x + b w`` in clip space, with
    ``a = W / w`` and ``b = (W - 2 x0) / w - 1`` (y likewise, flipped since
    rows grow downwards).  A full-frame domain gives ``projection`` unchanged.
    """
    w_full, h_full = width, height
    x0, y0, x1, y1 = domain
    w, h = x1 - x0, y1 - y0
    crop = np.eye(4)
    crop[0, 0], crop[0, 3] = w_full / w, (w_full - 2 * x0) / w - 1.0
    crop[1, 1], crop[1, 3] = h_full / h, 1.0 - (h_full - 2 * y0) / h
    return crop @ projection


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
    cur_bg = is_background(cur_pos, None if cur_depth is None else cur_depth[:, 0])
    cur_n = current.n.reshape(-1)
    cur_known = np.all(np.isfinite(cur_pos), axis=1) & (cur_n > 0)
    prev_pos_all = prev.features["position"].mean.reshape(-1, 3)
    prev_depth_all = prev.features["depth"].mean.reshape(-1, prev.features["depth"].mean.shape[-1]) \
        if "depth" in prev.features else None

    pooled = _pooled_light(prev, prev_camera, current, current_camera, have,
                           params.view_dependence_radius) if view_changed else {}
    chunk = max(int(params.chunk), 1)
    npx = hp * wp
    for s0 in range(0, npx, chunk):
        idx = np.arange(s0, min(npx, s0 + chunk))
        code, tgt = _validate_chunk(idx, prev, prev_camera, current, current_camera, params,
                                    prev_pos_all, prev_depth_all, cur_pos, cur_bg, cur_known,
                                    view_changed, have, (hp, wp), (h, w), pooled)
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
                    cur_pos, cur_bg, cur_known, view_changed, have, pshape, cshape, pooled=None):
    """Reason code (N,) int8 (index into :data:`REASONS`, 0 = valid) and target
    flat index (N,) int64 of the previous pixels ``idx`` (N,): the validations
    in the order of :data:`REASONS`, each pixel keeping the first that rejects it."""
    code = np.zeros(idx.size, np.int8)
    _reject(code, _empty_statistics(prev, idx), "empty")
    pos, depth, pos_ok = _source_points(prev_pos_all, prev_depth_all, idx)
    _reject(code, ~pos_ok, "no_position")
    bg = is_background(pos, None if depth is None else depth[:, 0]) & pos_ok
    if not params.background:
        _reject(code, bg, "background")
    if depth is not None and params.consistency_tolerance > 0:
        normal = prev.features["normal"].mean.reshape(-1, 3)[idx] if "normal" in prev.features else None
        _reject(code, _inconsistent(pos, depth[:, 0], bg, pcam, params.consistency_tolerance,
                                    normal, pshape, params.consistency_pixels), "inconsistent")
    clip, no_direction = _clip_coordinates(pos, bg, idx, pcam, ccam, pshape)
    row, col, inside = _inside_frame(clip, ccam, cshape)
    _reject(code, no_direction | ~inside, "outside")
    tgt = _target_pixels(row, col, inside, cshape)
    _reject(code, _occluded(pos, bg, clip, row, col, tgt, ccam, cur_pos, cur_bg, cur_known, cshape,
                            params.occlusion_tolerance, params.occlusion_pixels), "occluded")
    if have["object_index"]:
        _reject(code, _object_changed(prev, cur, idx, tgt, params.object_index_tolerance), "object_index")
    surf = ~bg                                  # the environment is not view dependent
    share = _specular_share(prev, cur, idx, tgt, have)
    _reject(code, surf & (share > params.max_specular_share), "specular")
    if view_changed:
        eps = _view_dependence_error(prev, cur, idx, tgt, have, params.confidence, params.assume_diffuse,
                                     pooled, params.max_error)
        fails = ~(eps <= params.max_error)
        if params.noise_limited != "off" and pooled:     # auto unresolved: on
            fails &= ~_change_below_noise(prev, cur, idx, tgt, pooled)
        _reject(code, surf & fails, "view_dependence")
    if params.changed_sigma > 0:
        _reject(code, _radiance_changed(prev, cur, idx, tgt, params.changed_sigma, params.max_error),
                "changed")
    return code, tgt


def _reject(code: np.ndarray, fails: np.ndarray, reason: str) -> None:
    """Give ``reason`` to the pixels still valid in ``code`` ((N,) int8, 0 =
    valid) where ``fails`` ((N,) bool), in place: a pixel keeps the first
    reason that applies."""
    code[(code == 0) & fails] = _R[reason]


def _empty_statistics(prev: Buffers, idx: np.ndarray) -> np.ndarray:
    """``empty``: the source has no samples, or non-finite statistics (n, k,
    colour mean / M2, or a feature pass other than position and depth, which
    :func:`_source_points` tests).  A precondition of copying a pixel's samples
    (Sec. 3.2).  prev (Hp, Wp), idx (N,) flat source pixels -> (N,) bool,
    True = rejected."""
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
    return ~stats_ok


def _source_points(prev_pos: np.ndarray, prev_depth: np.ndarray | None, idx: np.ndarray):
    """``no_position``: the stored first intersection points of the sources
    (Sec. 3.2: "each pixel should store their first intersection point").

    prev_pos (Hp*Wp, 3), prev_depth (Hp*Wp, C) or None: the previous frame's
    Position and depth passes, flat; idx (N,).  Returns ``pos`` (N, 3) (0 where
    unusable), ``depth`` (N, C) or None (as stored), ``ok`` (N,) bool: position
    and depth finite.
    """
    pos = prev_pos[idx]
    pos_ok = np.all(np.isfinite(pos), axis=1)
    depth = prev_depth[idx] if prev_depth is not None else None
    if depth is not None:
        pos_ok &= np.all(np.isfinite(depth), axis=1)
    return np.where(pos_ok[:, None], pos, 0.0), depth, pos_ok


def _inconsistent(pos: np.ndarray, depth: np.ndarray, bg: np.ndarray, camera: Camera,
                  tolerance: float, normal: np.ndarray | None = None, pshape: tuple = (1, 1),
                  pixels: float = 0.0) -> np.ndarray:
    """``inconsistent``: the source is not a single clean surface, its
    position disagrees with its mean depth, ``| |P - C| - depth | > tolerance *
    |P - C| + slack`` against both the ray length and the camera z-depth.

    Position is the hit of sample 0 alone (module docstring), the Denoising
    Depth the mean over the pixel's samples: a pixel mixing two surfaces, or a
    surface and the background, at an edge has a mean depth between them while
    its position lies on one (the thesis' Sec. 3.2.2 depth test against
    aliasing), and Cycles' Denoising Depth adds path length through specular
    bounces (mirrors, glass: part of "never reproject specular", Sec. 3.2.1).
    On one slanted surface the two differ too, by the depth change between
    sample 0's sub-pixel offset and the pixel mean: ``slack = pixels * s *
    tan(theta)`` (:func:`_slant_slack`), with ``s`` the pixel's footprint and
    theta the incidence from the pixel's normal; without normals the slack is
    0.

    pos (N, 3), depth (N,) the depth pass, bg (N,) bool (exempt), camera the
    previous frame's, normal (N, 3) camera-space mean normals or None, pshape
    the previous frame's (H, W) -> (N,) bool, True = rejected.
    """
    dist_p = np.linalg.norm(pos - camera.position[None, :], axis=1)
    zdep = -(pos @ camera.view[2, :3] + camera.view[2, 3])
    tol = tolerance * dist_p + _slant_slack(pos, normal, camera, pshape, pixels)
    consistent = (np.abs(dist_p - depth) <= tol) | (np.abs(zdep - depth) <= tol)
    return ~bg & ~consistent


#: Blender camera space <-> Cycles camera space (the Denoising Normal's): z flipped
_CYCLES_FLIP = np.diag([1.0, 1.0, -1.0])

#: incidence cosine below which tan(theta) is not grown further (tan <= ~20: 87 degrees)
_MIN_COS = 0.05


def _slant_slack(pos: np.ndarray, normal: np.ndarray | None, camera: Camera, pshape: tuple,
                 pixels: float) -> np.ndarray:
    """(N,) depth slack ``pixels * s * tan(theta)``: how much a surface's ray
    length changes over ``pixels`` footprints ``s`` (:meth:`Camera.footprint`)
    when the ray meets it at incidence theta.  First order in the offset; theta
    from ``normal`` (Cycles' camera space, +Z forward: z is flipped into
    Blender's) against the ray to ``pos``, cos clamped at :data:`_MIN_COS`.  0
    where the normal is unknown or too short to say (|n| < 0.5: normals of
    several surfaces averaged), so those pixels keep the relative test alone."""
    if normal is None or pixels <= 0:
        return np.zeros(pos.shape[0])
    p_cam = pos @ camera.view[:3, :3].T + camera.view[:3, 3][None, :]
    n_b = np.asarray(normal, np.float64) @ _CYCLES_FLIP
    nn = np.linalg.norm(n_b, axis=1)
    pn = np.linalg.norm(p_cam, axis=1)
    usable = np.isfinite(nn) & np.isfinite(pn) & (nn >= 0.5) & (pn > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs(np.sum(n_b * p_cam, axis=1)) / np.where(usable, nn * pn, 1.0)
    cos = np.clip(np.where(usable & np.isfinite(cos), cos, 1.0), _MIN_COS, 1.0)
    tan = np.sqrt(np.maximum(1.0 - cos * cos, 0.0)) / cos
    fp = camera.footprint(camera.clip(pos), pshape[0], pshape[1])
    slack = pixels * np.where(np.isfinite(fp), fp, 0.0) * tan
    return np.where(usable, slack, 0.0)


def _clip_coordinates(pos: np.ndarray, bg: np.ndarray, idx: np.ndarray, pcam: Camera, ccam: Camera,
                      pshape: tuple):
    """Clip coordinates of the sources in the new camera (Sec. 3.2: "a
    direction from the new camera position towards the stored intersection
    point"); background pixels are reprojected *by direction*.

    A surface point is projected with homogeneous w = 1.  The environment is at
    infinity, so a background pixel's radiance depends on its direction only:
    the direction of its centre ray in the previous camera is projected with
    w = 0 (orthographic cameras map every direction to w = 0, so there it
    fails as ``outside``).

    pos (N, 3), bg (N,) bool, idx (N,) flat pixels of the previous frame
    (Hp, Wp) = ``pshape``.  Returns clip (N, 4) and ``no_direction`` (N,) bool:
    background pixels whose ray direction is undefined (rejected as
    ``outside``).
    """
    hp, wp = pshape
    clip = ccam.clip(pos, 1.0)
    no_direction = np.zeros(idx.size, bool)
    if bg.any():
        rows = idx[bg] // wp
        cols = idx[bg] % wp
        dirs = pcam.ray_directions(rows.astype(np.float64), cols.astype(np.float64), hp, wp)
        clip[bg] = ccam.clip(np.where(np.isfinite(dirs), dirs, 0.0), 0.0)
        no_direction[np.flatnonzero(bg)[~np.all(np.isfinite(dirs), axis=1)]] = True
    return clip, no_direction


def _inside_frame(clip: np.ndarray, camera: Camera, cshape: tuple):
    """``outside``, validation (a) of Sec. 3.2 ("within the screen limits"):
    in front of the new camera and inside its (H, W) = ``cshape`` screen.

    clip (N, 4) -> continuous (row, col) (N,) each (NaN behind the camera) and
    ``inside`` (N,) bool, True = passes.
    """
    h, w = cshape
    row, col, front = camera.pixel_coordinates(clip, h, w)
    inside = front & (row >= 0) & (row < h) & (col >= 0) & (col < w)
    return row, col, inside


def _target_pixels(row: np.ndarray, col: np.ndarray, inside: np.ndarray, cshape: tuple) -> np.ndarray:
    """Flat index (N,) int64 of the current pixel ``(floor(row), floor(col))``
    each source lands in; clamped into the frame (pixel 0 where not ``inside``,
    those are rejected already)."""
    h, w = cshape
    ti = np.clip(np.floor(np.where(inside, row, 0.0)), 0, h - 1).astype(np.int64)
    tj = np.clip(np.floor(np.where(inside, col, 0.0)), 0, w - 1).astype(np.int64)
    return ti * w + tj


def _occluded(pos, bg, clip, row, col, tgt, camera: Camera, cur_pos, cur_bg, cur_known, cshape,
              tolerance: float, pixels: float) -> np.ndarray:
    """``occluded``, validation (b) of Sec. 3.2: the first hit of the new
    camera's ray towards the stored point must lie within epsilon of it.

    The current frame's initial pass gives that hit, averaged over the target
    pixel: with ``d = |P - C_t|`` and ``s`` the pixel's footprint at that
    distance (:meth:`Camera.footprint`), the test is ``|P - W_t(target)| <=
    tolerance * d + pixels * s``; the footprint term admits the sub-pixel
    offset between the projected point and the target's centroid on slanted
    surfaces.  Where the four pixel centres around the projected point are
    known surface hits, the point is also compared with their bilinear
    interpolation (the hit of the ray through the projected sub-pixel
    position, to second order), and passes if either comparison does: grazing
    surfaces stay valid without widening the tolerance.  A target without
    samples or position, or a background target for a surface source (and
    vice versa), counts as occluded.

    pos (N, 3), bg (N,) bool, clip (N, 4), row / col (N,) continuous pixel
    coordinates, tgt (N,) flat target pixels; cur_pos (H*W, 3), cur_bg and
    cur_known (H*W,) bool: the current frame's positions, background and
    "has samples and a finite position" -> (N,) bool, True = rejected.
    """
    h, w = cshape
    known = cur_known[tgt]
    tbg = cur_bg[tgt]
    wt = np.where(known[:, None], cur_pos[tgt], 0.0)
    dist_c = np.linalg.norm(pos - camera.position[None, :], axis=1)
    fp = camera.footprint(clip, h, w)
    tol = tolerance * dist_c + pixels * fp
    same_surface = np.linalg.norm(pos - wt, axis=1) <= tol
    interp = _interpolate_position(row, col, cur_pos, cur_known & ~cur_bg, h, w)
    with np.errstate(invalid="ignore"):
        same_surface |= np.linalg.norm(pos - interp, axis=1) <= tol
    visible = known & np.where(bg, tbg, ~tbg & same_surface)
    return ~visible


def _object_changed(prev: Buffers, cur: Buffers, idx: np.ndarray, tgt: np.ndarray,
                    tolerance: float) -> np.ndarray:
    """``object_index``, validation (d): the object under the pixel changed,
    ``|index_prev - index_target| > tolerance`` (moving objects, where the
    scene gives them pass indices; Cycles' default index is 0).  An addition
    to Sec. 3.2, which assumes a static scene.

    idx (N,) flat source pixels, tgt (N,) flat target pixels -> (N,) bool,
    True = rejected.
    """
    oi_p = prev.features["object_index"].mean.reshape(-1, prev.features["object_index"].mean.shape[-1])[idx, 0]
    oi_t = cur.features["object_index"].mean.reshape(-1, cur.features["object_index"].mean.shape[-1])[tgt, 0]
    with np.errstate(invalid="ignore"):
        same = np.abs(oi_p - oi_t) <= tolerance
    return ~same


#: Cycles' light passes holding the view-dependent light (direct + indirect)
_LIGHT_PASSES = ("glossy", "transmission")


def _radiance(buf: Buffers, name: str, flat: np.ndarray, use_color: bool):
    """Mean (N, C) and variance of the mean (N, C) of light pass ``name``'s
    *radiance* at flat pixels ``flat``: Cycles divides its light passes by
    their colour pass (module docstring), so the radiance is ``colour x
    light`` (``<name>_color``, where ``use_color``); the product of the pooled
    means (exact for one render; over several renders it ignores the
    covariance of colour and light between renders, second order for a pixel
    on one surface).  Its variance by the delta method, ``c^2 v_L + L^2 v_c``,
    an exact-zero factor contributing 0.  Without colour: the light pass
    itself (overstates the radiance by 1 / colour: conservative).  Non-finite
    means -> +inf."""
    st = buf.features[name]
    c = st.mean.shape[-1]
    light = st.mean.reshape(-1, c)[flat]
    v_l = _var_of_mean(buf, st, flat)
    if use_color:
        cs = buf.features[name + "_color"]
        col = cs.mean.reshape(-1, cs.mean.shape[-1])[flat]
        if col.shape[1] != c:
            col = np.broadcast_to(col[:, :1], light.shape)
        v_c = _var_of_mean(buf, cs, flat)
        if v_c.shape[1] != c:
            v_c = np.broadcast_to(v_c[:, :1], light.shape)
        with np.errstate(invalid="ignore", over="ignore"):
            mean = col * light
            var = np.where(col == 0.0, 0.0, col * col * v_l) + np.where(light == 0.0, 0.0, light * light * v_c)
    else:
        mean, var = light, v_l
    ok = np.isfinite(mean)
    return np.where(ok, mean, np.inf), np.where(ok & ~np.isnan(var), var, np.inf)


def _light_pass(prev: Buffers, cur: Buffers, name: str, idx: np.ndarray, tgt: np.ndarray, have: dict):
    """Radiance of light pass ``name`` (:func:`_radiance`) at the sources and
    at their targets in the current frame: ``(s_p, v_p, s_t, v_t)``, each (N, C).
    The colour pass is used only when both frames have it, so both sides are
    in the same units."""
    use_color = bool(have.get(name + "_color"))
    s_p, v_p = _radiance(prev, name, idx, use_color)
    s_t, v_t = _radiance(cur, name, tgt, use_color)
    return s_p, v_p, s_t, v_t


def _specular_share(prev: Buffers, cur: Buffers, idx: np.ndarray, tgt: np.ndarray, have: dict) -> np.ndarray:
    """Share of view-dependent light, for ``specular``: ``lum(glossy +
    transmission radiance) / lum(combined)``, the larger of the previous
    pixel's and the target's in the current frame.

    The thesis never reprojects specular (alpha < 0.01) or refractive
    materials (Sec. 3.2.1); Cycles has no roughness pass, so "mostly specular
    or refractive" is read from the radiance passes (:func:`_radiance`; missing
    passes count as 0).  idx, tgt (N,) -> (N,) float64 >= 0; +inf where there
    is view-dependent light but no positive combined luminance, or the ratio
    is undefined.
    """
    m = idx.size
    lum_p = np.maximum(luminance(prev.color.mean.reshape(-1, 3)[idx]), 0.0)
    cur_cm = cur.color.mean.reshape(-1, 3)[tgt]
    lum_t = np.maximum(luminance(np.where(np.isfinite(cur_cm), cur_cm, 0.0)), 0.0)
    vd_p = np.zeros(m)
    vd_t = np.zeros(m)
    for pname in _LIGHT_PASSES:
        if not have[pname]:
            continue
        s_p, _, s_t, _ = _light_pass(prev, cur, pname, idx, tgt, have)
        with np.errstate(invalid="ignore"):
            vd_p += np.maximum(luminance(s_p[:, :3]) if s_p.shape[1] >= 3 else s_p[:, 0], 0.0)
            vd_t += np.maximum(luminance(s_t[:, :3]) if s_t.shape[1] >= 3 else s_t[:, 0], 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        share_p = np.where(vd_p > 0, vd_p / np.where(lum_p > 0, lum_p, 0.0), 0.0)
        share_t = np.where(vd_t > 0, vd_t / np.where(lum_t > 0, lum_t, 0.0), 0.0)
    share_p = np.where(np.isnan(share_p), np.inf, share_p)
    share_t = np.where(np.isnan(share_t), np.inf, share_t)
    return np.maximum(share_p, share_t)


def _view_dependence_error(prev: Buffers, cur: Buffers, idx: np.ndarray, tgt: np.ndarray, have: dict,
                           confidence: float, assume_diffuse: bool, pooled: dict | None = None,
                           max_error: float = 0.0) -> np.ndarray:
    """Upper bound (N,) of Eq. 15's view-dependence error for ``view_dependence``
    (validation (c) of Sec. 3.2; Sec. 3.2.1), when the camera moved.

    Glossy and transmission radiance (:func:`_radiance`) are bounded
    separately by :func:`_bound` and added (triangle inequality), each the
    maximum over its channels.  With ``pooled`` (:func:`_pooled_light`) the
    bound is taken on the window-pooled radiances, and a pixel whose own
    radiance changed beyond its noise (``|S_t - S_p| > max_error + z sqrt(v_p
    + v_t)`` in a channel: a highlight moving inside the window, which pooling
    would average away) gets +inf.  A missing light pass makes the bound +inf
    unless ``assume_diffuse`` (then it counts as 0).  idx, tgt (N,) -> (N,)
    float64 in [0, inf].
    """
    eps = np.zeros(idx.size)
    complete = True
    for pname in _LIGHT_PASSES:
        if not have[pname]:
            complete = False
            continue
        s_p, v_p, s_t, v_t = _light_pass(prev, cur, pname, idx, tgt, have)
        if pooled and pname in pooled:
            mp, vp, mt, vt = pooled[pname]
            with np.errstate(invalid="ignore", over="ignore"):
                moved = ~(np.abs(s_t - s_p) <= max_error + confidence * np.sqrt(v_p + v_t))
            b = _bound(mp[idx], vp[idx], mt[tgt], vt[tgt], confidence).max(axis=1)
            eps = eps + np.where(moved.any(axis=1), np.inf, b)
        else:
            eps = eps + _bound(s_p, v_p, s_t, v_t, confidence).max(axis=1)
    if not complete and not assume_diffuse:
        return np.full(idx.size, np.inf)
    return eps


def _change_below_noise(prev: Buffers, cur: Buffers, idx: np.ndarray, tgt: np.ndarray,
                        pooled: dict) -> np.ndarray:
    """(N,) bool: the view-dependent change is estimated below the noise of the
    means the merge pools (``noise_limited``, an addition to Eq. 15).

    Merging m reprojected samples whose mean is off by delta into n own
    samples trades a bias ``m/(m+n) delta`` for the variance ``sigma^2/n ->
    sigma^2/(n+m)``; the squared error falls whenever ``delta^2 < v_p + v_t``,
    the variances of the two Combined means.  delta per channel is estimated
    from the window-pooled radiances (:func:`_pooled_light`), unbiased in the
    square: ``max(0, dS^2 - var(dS))``, glossy and transmission added; every
    channel must pass, with finite variances (unknown variance: False).
    """
    delta = np.zeros((idx.size, 3))
    for mp, vp, mt, vt in pooled.values():
        with np.errstate(invalid="ignore", over="ignore"):
            d = mt[tgt] - mp[idx]
            d2 = np.maximum(d * d - (vp[idx] + vt[tgt]), 0.0)
        if d2.shape[1] != 3:
            d2 = np.broadcast_to(d2[:, :1], (idx.size, 3))
        delta = delta + np.sqrt(d2)
    v = _var_of_mean(prev, prev.color, idx) + _var_of_mean(cur, cur.color, tgt)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(v) & np.isfinite(delta) & (delta * delta <= v)
    return ok.all(axis=1)


def _pooled_light(prev: Buffers, prev_camera: Camera, cur: Buffers, cur_camera: Camera, have: dict,
                  radius: int) -> dict:
    """name -> (mean_prev, var_prev, mean_cur, var_cur), flat (H*W, C): each
    frame's light-pass radiance (:func:`_radiance`) pooled over (2 radius + 1)^2
    windows by :func:`_guided_pool` (all passes of a frame in one sweep).
    Empty for radius 0; a pass that is exactly 0 with zero variance in both
    frames (no transmission in the scene) is passed through unpooled."""
    if radius <= 0:
        return {}
    names = [n for n in _LIGHT_PASSES if have[n]]
    per_frame = []
    for buf in (prev, cur):
        flat = np.arange(buf.n.size)
        per_frame.append({n: _radiance(buf, n, flat, bool(have.get(n + "_color"))) for n in names})
    trivial = {n: all(not np.any(f[n][0]) and not np.any(f[n][1]) for f in per_frame) for n in names}
    pooled = []
    for (buf, cam), rad in zip(((prev, prev_camera), (cur, cur_camera)), per_frame):
        todo = [n for n in names if not trivial[n]]
        if todo:
            m = np.concatenate([rad[n][0] for n in todo], axis=1)
            v = np.concatenate([rad[n][1] for n in todo], axis=1)
            pm, pv = _guided_pool(buf, cam, m, v, radius)
        out, c0 = {}, 0
        for n in names:
            if trivial[n]:
                out[n] = rad[n]
                continue
            c = rad[n][0].shape[1]
            out[n] = (pm[:, c0:c0 + c], pv[:, c0:c0 + c])
            c0 += c
        pooled.append(out)
    return {n: pooled[0][n] + pooled[1][n] for n in names}


#: neighbours pooled with a pixel must share its surface: normals within ~25 degrees, and
#: within this share of the camera distance of the pixel's tangent plane (log depth without normals)
_POOL_NORMAL_DOT = 0.9
_POOL_PLANE = 0.02


def _guided_pool(buf: Buffers, camera: Camera, mean: np.ndarray, var: np.ndarray, radius: int):
    """Mean and variance of the mean of ``mean`` (H*W, C) over the window
    pixels on the pixel's own surface: same object index, normal within
    :data:`_POOL_NORMAL_DOT`, position within :data:`_POOL_PLANE` of the
    camera distance from the pixel's tangent plane (a slanted plane's
    neighbours stay in; a parallel surface behind does not), each guide used
    where the buffer has it; finite values only.  Pixels' noise is
    independent, so ``var = sum v_q / m^2`` for the m pooled pixels.  A pixel
    whose own value is not finite stays +inf (it is never pooled from
    neighbours alone)."""
    h, w = buf.shape
    c = mean.shape[1]
    m3 = mean.reshape(h, w, c)
    v3 = var.reshape(h, w, c)
    fin = np.all(np.isfinite(m3), axis=2) & np.all(np.isfinite(v3), axis=2)
    feats = buf.features
    oid = feats["object_index"].mean[..., 0] if "object_index" in feats else None
    nrm = None
    if "normal" in feats:                          # camera space (Cycles) -> world
        nrm = feats["normal"].mean @ _CYCLES_FLIP @ camera.view[:3, :3]
        nn = np.linalg.norm(nrm, axis=2, keepdims=True)
        nrm = np.where(nn > 0, nrm / np.where(nn > 0, nn, 1.0), 0.0)
    pos = feats["position"].mean
    lim = _POOL_PLANE * np.linalg.norm(pos - camera.position[None, None, :], axis=2)
    ld = None
    if nrm is None and "depth" in feats:
        d = feats["depth"].mean[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            ld = np.where(d > 0, np.log(np.where(d > 0, d, 1.0)), np.nan)
    both = np.concatenate([np.where(fin[..., None], m3, 0.0), np.where(fin[..., None], v3, 0.0)], axis=2)
    acc = np.zeros((h, w, 2 * c))
    cnt = np.zeros((h, w))
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
            xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
            ok = fin[ys, xs] & fin[yd, xd]
            if dy or dx:                    # a pixel always pools itself
                if oid is not None:
                    ok &= np.abs(oid[ys, xs] - oid[yd, xd]) <= 1e-3
                with np.errstate(invalid="ignore"):
                    if nrm is not None:
                        nd = nrm[yd, xd]
                        ok &= np.einsum("ijk,ijk->ij", nrm[ys, xs], nd) >= _POOL_NORMAL_DOT
                        off = np.abs(np.einsum("ijk,ijk->ij", nd, pos[ys, xs] - pos[yd, xd]))
                        ok &= off <= lim[yd, xd]
                    elif ld is not None:
                        ok &= np.abs(ld[ys, xs] - ld[yd, xd]) <= _POOL_PLANE
            acc[yd, xd] += both[ys, xs] * ok[..., None]
            cnt[yd, xd] += ok
    safe = np.where(cnt > 0, cnt, 1.0)[..., None]
    pm = np.where(fin[..., None], acc[..., :c] / safe, np.inf)
    pv = np.where(fin[..., None], acc[..., c:] / (safe * safe), np.inf)
    return pm.reshape(-1, c), pv.reshape(-1, c)


def _radiance_changed(prev: Buffers, cur: Buffers, idx: np.ndarray, tgt: np.ndarray, sigma: float,
                      max_error: float) -> np.ndarray:
    """``changed``: the sigma-test (default 5 sigma) on the radiance itself, an
    addition (Sec. 3 assumes a static scene and restarts on any change).

    The reprojected mean and the current frame's own initial-pass mean at the
    target differ beyond noise: ``|m_prev - m_t| > sigma * s * sqrt(1/n_prev +
    1/n_t) + max_error`` in some channel, with the per-sample variance pooled
    over both frames, ``s^2 = (M2_prev + M2_t) / (k_prev - 1 + k_t - 1)``
    (unchanged pixels sample the same integrand, so pooling is valid and gives
    more degrees of freedom than the initial pass alone).  Catches what no
    geometric test sees (moving shadows and lights, animated textures), but
    only changes large against the initial pass's noise.  Skipped (passes)
    where no variance exists (one group in both frames).

    idx, tgt (N,) -> (N,) bool, True = rejected.
    """
    n = prev.n.reshape(-1)[idx]
    k = prev.k.reshape(-1)[idx]
    cm = prev.color.mean.reshape(-1, 3)[idx]
    c2 = prev.color.m2.reshape(-1, 3)[idx]
    k_t = cur.k.reshape(-1)[tgt]
    n_t = cur.n.reshape(-1)[tgt]
    m2_t = cur.color.m2.reshape(-1, 3)[tgt]
    cur_cm = cur.color.mean.reshape(-1, 3)[tgt]
    dof = np.maximum(k - 1.0, 0.0) + np.maximum(k_t - 1.0, 0.0)
    known_v = (dof > 0) & (n > 0) & (n_t > 0) & np.all(np.isfinite(m2_t), axis=1)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        s2 = (c2 + m2_t) / np.where(known_v, dof, 1.0)[:, None]
        v = s2 * (1.0 / np.where(n > 0, n, 1.0) + 1.0 / np.where(n_t > 0, n_t, 1.0))[:, None]
        diff = np.abs(cm - np.where(np.isfinite(cur_cm), cur_cm, np.inf))
        lim = sigma * np.sqrt(np.maximum(v, 0.0)) + max_error
        bad = known_v[:, None] & ~(diff <= lim)
    return bad.any(axis=1)


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
        bg = is_background(pos, d[:, 0])
        shift = np.where(bg | ~np.isfinite(shift), 0.0, shift)
        transforms["depth"] = ("shift", shift)
    # R_t R_{t-1}^T in Blender's camera space, conjugated by the z flip into Cycles' (+Z forward)
    rot = _CYCLES_FLIP @ (ccam.rotation @ pcam.rotation.T) @ _CYCLES_FLIP
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
    bg = is_background(pos0, None if depth is None else depth[:, 0]) & ok
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

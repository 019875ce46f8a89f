"""Show results in Blender's Image Editor: the reconstructed image, the
sample-count map and the estimated-error map, as float images."""
from __future__ import annotations

import bpy
import numpy as np

from ..core.buffers import luminance

RESULT, SAMPLES, ERROR = "Cycles Adaptive Result", "Cycles Adaptive Samples", "Cycles Adaptive Error"
COMPOSITE = "Cycles Adaptive Composite"


def float_pixels(rgba: np.ndarray) -> tuple:
    """(H, W, 1|3|4) pixels (top row first) as a Blender float image's flat
    RGBA buffer (rows bottom to top, non-finite values 0) and its size:
    numpy only, so a worker thread may prepare it."""
    h, w = rgba.shape[:2]
    px = np.ones((h, w, 4), np.float32)
    c = rgba.shape[2]
    if c == 1:
        px[:, :, :3] = rgba
    else:
        px[:, :, :min(c, 4)] = rgba[:, :, :4]
    px = np.nan_to_num(px, nan=0.0, posinf=0.0, neginf=0.0)
    return px[::-1].ravel(), w, h


def set_float_image(name: str, prepared: tuple):
    """Create or update a float image from a :func:`float_pixels` buffer."""
    flat, w, h = prepared
    img = bpy.data.images.get(name)
    if img is not None and (tuple(img.size) != (w, h) or not img.is_float):
        bpy.data.images.remove(img)
        img = None
    if img is None:
        img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    img.pixels.foreach_set(flat)
    img.update()
    return img


def prepare_result(image: np.ndarray, samples: np.ndarray, error: np.ndarray, alpha=None,
                   composite=None) -> dict:
    """The Image Editor images of a result as :func:`float_pixels` buffers,
    name -> buffer (numpy only: the writer thread computes it, the main
    thread only hands the pixels to Blender, :func:`show_prepared`).

    The sample map is shown divided by its maximum and the error map as the
    relative error sqrt(err) / (luminance + 0.01), scaled to its 99th percentile.
    """
    rgba = image if alpha is None else np.concatenate([image, alpha], axis=-1)
    out = {RESULT: float_pixels(rgba)}
    smax = max(float(np.max(samples)), 1.0)
    out[SAMPLES] = float_pixels((samples / smax)[:, :, None])
    lum = luminance(image)
    rel = np.sqrt(np.maximum(error, 0.0)) / (np.abs(lum) + 0.01)
    p99 = float(np.percentile(rel, 99)) if rel.size else 1.0
    out[ERROR] = float_pixels((np.clip(rel / max(p99, 1e-12), 0, 1))[:, :, None])
    if composite is not None:
        out[COMPOSITE] = float_pixels(composite)
    return out


def show_prepared(prepared: dict):
    """Put :func:`prepare_result`'s images in bpy.data and point Image
    Editors at the result (the composite when there is one)."""
    shown = None
    for name, buf in prepared.items():
        img = set_float_image(name, buf)
        if name in (RESULT, COMPOSITE):
            shown = img
    wm = getattr(bpy.context, "window_manager", None)
    for window in (wm.windows if wm else ()):
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = shown
                area.tag_redraw()
    return shown


def show_result(image: np.ndarray, samples: np.ndarray, error: np.ndarray, alpha=None, composite=None):
    """Put the three images in bpy.data (four with the compositor's image)
    and point Image Editors at the result (the composite when there is one):
    :func:`prepare_result` then :func:`show_prepared`, here."""
    return show_prepared(prepare_result(image, samples, error, alpha, composite))

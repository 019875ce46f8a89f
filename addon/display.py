"""Show results in Blender's Image Editor: the reconstructed image, the
sample-count map and the estimated-error map, as float images."""
from __future__ import annotations

import bpy
import numpy as np

from ..core.buffers import LUMA

RESULT, SAMPLES, ERROR = "Cycles Adaptive Result", "Cycles Adaptive Samples", "Cycles Adaptive Error"
COMPOSITE = "Cycles Adaptive Composite"


def set_float_image(name: str, rgba: np.ndarray):
    """Create or update a float image from (H, W, 1|3|4) pixels (top row first)."""
    h, w = rgba.shape[:2]
    px = np.ones((h, w, 4), np.float32)
    c = rgba.shape[2]
    if c == 1:
        px[:, :, :3] = rgba
    else:
        px[:, :, :min(c, 4)] = rgba[:, :, :4]
    px = np.nan_to_num(px, nan=0.0, posinf=0.0, neginf=0.0)
    img = bpy.data.images.get(name)
    if img is not None and (tuple(img.size) != (w, h) or not img.is_float):
        bpy.data.images.remove(img)
        img = None
    if img is None:
        img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    img.pixels.foreach_set(px[::-1].ravel())  # Blender rows run bottom to top
    img.update()
    return img


def show_result(image: np.ndarray, samples: np.ndarray, error: np.ndarray, alpha=None, composite=None):
    """Put the three images in bpy.data (four with the compositor's image)
    and point Image Editors at the result (the composite when there is one).

    The sample map is shown divided by its maximum and the error map as the
    relative error sqrt(err) / (luminance + 0.01), scaled to its 99th percentile.
    """
    rgba = image if alpha is None else np.concatenate([image, alpha], axis=-1)
    res = set_float_image(RESULT, rgba)
    if composite is not None:
        res = set_float_image(COMPOSITE, composite)
    smax = max(float(np.max(samples)), 1.0)
    set_float_image(SAMPLES, (samples / smax)[:, :, None])
    lum = image @ LUMA
    rel = np.sqrt(np.maximum(error, 0.0)) / (np.abs(lum) + 0.01)
    p99 = float(np.percentile(rel, 99)) if rel.size else 1.0
    set_float_image(ERROR, (np.clip(rel / max(p99, 1e-12), 0, 1))[:, :, None])
    wm = getattr(bpy.context, "window_manager", None)
    for window in (wm.windows if wm else ()):
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = res
                area.tag_redraw()
    return res

"""Blender's own Open Image Denoise, for a Blender whose Python lacks ``pyoidn``.

The same call as :func:`core.oidn.oidn_filter` (RT filter, HDR, albedo +
normal), run through the compositor's Denoise node on image buffers: float
images hold the colour and the auxiliary passes, Image nodes feed a
``CompositorNodeDenoise`` whose output is rendered with ``write_still=True`` to
a 32-bit EXR and read back.  With no Render Layers node in the tree Blender
composites without rendering a view layer, so it needs no camera or objects
and runs in background mode (DESIGN.md, second round of checked facts).

Prefilter mapping (checked against pyoidn in tests/test_oidn_blender.py):
``NONE`` = OIDN ``cleanAux=True``, ``FAST`` = ``cleanAux=False``,
``ACCURATE`` = the auxiliary images denoised first, then ``cleanAux=True``.

Nothing of the user's is touched: a temporary scene, node tree and images are
made and removed again (also after an error), the last render stays in its
Render Result slot (we composite into a slot of our own), and the active
window scene never changes.

Version paths: 4.2 has no quality setting (OIDN's default, high); 4.5 has the
node's ``quality``; 5.0 takes HDR, Prefilter and Quality as input sockets and
composites a node group (``scene.compositing_node_group``, Group Output node).
"""
from __future__ import annotations

import os
import shutil
import tempfile

import bpy
import numpy as np

from ..core import io as imageio
from ..core import oidn
from .executor import SettingsGuard, protect_render_result, quiet_stdout

BACKEND = "blender"
_NAME = "cycles_adaptive_oidn"
_PREFILTER = {"none": ("NONE", "None"), "fast": ("FAST", "Fast"), "accurate": ("ACCURATE", "Accurate")}
_QUALITY = {"high": ("HIGH", "High"), "balanced": ("BALANCED", "Balanced"), "fast": ("FAST", "Fast")}


def denoise(color, albedo=None, normal=None, *, hdr: bool = True, prefilter: str = "fast",
            quality: str = "high") -> np.ndarray:
    """(H, W, 3) float32 output of Blender's OIDN for ``color`` (H, W, 3) and
    the optional ``albedo`` and ``normal`` (same shape); ``prefilter`` one of
    none / fast / accurate, ``quality`` high / balanced / fast.  Inputs are
    validated by the caller (:func:`core.oidn.oidn_filter`).
    :class:`core.oidn.OIDNError` when Blender wrote no image."""
    color = np.asarray(color, np.float32)
    h, w = color.shape[:2]
    tmp = tempfile.mkdtemp(prefix="cycles-adaptive-oidn-")
    made = {"images": [], "scene": None, "group": None}
    guard = SettingsGuard()
    try:
        scene = bpy.data.scenes.new(_NAME)
        made["scene"] = scene
        _configure_output(scene, w, h, os.path.join(tmp, "denoised.exr"))
        tree, out_socket = _tree(scene, made)
        images = {"Image": color}
        if albedo is not None:
            images["Albedo"] = albedo
        if normal is not None:
            images["Normal"] = normal
        den = tree.nodes.new("CompositorNodeDenoise")
        for name, arr in images.items():
            img = _float_image(f"{_NAME}_{name.lower()}", arr, data=name != "Image")
            made["images"].append(img)
            node = tree.nodes.new("CompositorNodeImage")
            node.image = img
            tree.links.new(node.outputs["Image"], den.inputs[name])
        _set_options(den, hdr, prefilter, quality)
        tree.links.new(den.outputs["Image"], out_socket)
        protect_render_result(guard)
        with quiet_stdout():
            bpy.ops.render.render(write_still=True, scene=scene.name)
        path = scene.render.filepath
        if not os.path.isfile(path):
            raise oidn.OIDNError("Blender's compositor wrote no denoised image")
        passes, _ = imageio.read_layers(path)
        out = next(iter(passes.values()))[:, :, :3]
        if out.shape[:2] != (h, w):
            raise oidn.OIDNError(f"Blender's compositor gave a {out.shape[1]}x{out.shape[0]} image "
                                 f"for a {w}x{h} input")
        return np.ascontiguousarray(out, np.float32)
    finally:
        guard.restore()
        _remove(made)
        shutil.rmtree(tmp, ignore_errors=True)


def _configure_output(scene, w: int, h: int, path: str) -> None:
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = int(w), int(h), 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.use_border = False
    r.use_compositing = True
    r.use_sequencer = False
    r.dither_intensity = 0.0
    if hasattr(r, "compositor_precision"):
        r.compositor_precision = "FULL"
    if hasattr(r, "compositor_device"):
        r.compositor_device = "CPU"
    st = r.image_settings
    if hasattr(st, "media_type"):  # Blender 5.0
        st.media_type = "IMAGE"
    st.file_format = "OPEN_EXR"
    st.color_mode = "RGBA"
    st.color_depth = "32"
    st.exr_codec = "NONE"
    r.use_file_extension = False
    r.filepath = path


def _tree(scene, made):
    """The compositor tree of ``scene`` and the socket its result goes to."""
    if hasattr(scene, "compositing_node_group"):  # Blender 5.0: a node group with a Group Output
        group = bpy.data.node_groups.new(_NAME, "CompositorNodeTree")
        made["group"] = group
        group.interface.new_socket(name="Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        scene.compositing_node_group = group
        out = group.nodes.new("NodeGroupOutput")
        return group, out.inputs[0]
    scene.use_nodes = True
    tree = scene.node_tree
    for node in list(tree.nodes):
        tree.nodes.remove(node)
    comp = tree.nodes.new("CompositorNodeComposite")
    if "use_alpha" in comp.bl_rna.properties:
        comp.use_alpha = True
    return tree, comp.inputs["Image"]


def _float_image(name: str, arr, data: bool):
    a = np.asarray(arr, np.float32)
    h, w = a.shape[:2]
    px = np.ones((h, w, 4), np.float32)
    px[:, :, :3] = a[:, :, :3]
    img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    if data:  # albedo and normal are data: no colour-space conversion
        img.colorspace_settings.name = "Non-Color"
    img.pixels.foreach_set(px[::-1].ravel())  # Blender rows run bottom to top
    img.update()
    return img


def _set_options(den, hdr: bool, prefilter: str, quality: str) -> None:
    pre, qual = _PREFILTER[prefilter], _QUALITY[quality]
    if "prefilter" in den.bl_rna.properties:  # 4.2 - 4.5
        den.use_hdr = bool(hdr)
        den.prefilter = pre[0]
        if "quality" in den.bl_rna.properties:
            den.quality = qual[0]
        if "HDR" in den.inputs:
            den.inputs["HDR"].default_value = bool(hdr)
        return
    den.inputs["HDR"].default_value = bool(hdr)  # 5.0: options are input sockets
    den.inputs["Prefilter"].default_value = pre[1]
    den.inputs["Quality"].default_value = qual[1]


def _remove(made: dict) -> None:
    scene = made.get("scene")
    if scene is not None:
        try:
            bpy.data.scenes.remove(scene)
        except ReferenceError:
            pass
    group = made.get("group")
    if group is not None:
        try:
            bpy.data.node_groups.remove(group)
        except ReferenceError:
            pass
    for img in made.get("images", ()):
        try:
            bpy.data.images.remove(img)
        except ReferenceError:
            pass


def register() -> None:
    """Make Blender's OIDN the fallback of :mod:`core.oidn` (used only when
    ``pyoidn`` does not import)."""
    oidn.register_backend(BACKEND, denoise, main_thread=True)  # bpy: Blender's main thread only


def unregister() -> None:
    oidn.unregister_backend(BACKEND)

"""The scene's compositor applied to an adaptive result.

A scene that composites its renders (Render Properties > Post Processing >
Compositing, with a compositor node tree) expects glare, colour grading,
layer mixes and File Output nodes to apply to the final image.  An adaptive
render has no Render Result for the compositor's Render Layers nodes to read,
so :func:`composite` runs the compositor on a temporary copy of the scene
whose Render Layers nodes are replaced by Image nodes reading our passes
(one multilayer EXR, one layer per view layer, passes named as Blender names
them).  A compositor without Render Layers nodes renders nothing (checked
under 4.2, 4.5 and 5.0: a composite-only render), so this costs only the
compositor itself.  The user's scene, node tree and files are not touched;
the temporary scene, its node tree copy and the image are removed afterwards.

:func:`plan` says, before rendering, which view layers and passes the
compositor reads, so the adaptive render accumulates them as feature passes
(``addon.executor.PASS_SOURCES``).  What an adaptive render cannot produce
(the Noisy Image, another scene's layers, Render Layers nodes inside node
groups) is a :class:`CompositorError` naming it; the job then writes the
raw result and says the compositor was skipped.

Cryptomatte: a Cryptomatte node (``CompositorNodeCryptomatteV2``) whose
source is the render is switched to the Image source on the same EXR, which
carries the merged Cryptomatte layers and header (``core/cryptomatte.py``),
with the same layer (``<view layer>.CryptoObject``...): the node reads the
mattes Blender's own render would give (checked under 4.2, 4.5 and 5.0).
The legacy Cryptomatte node (picking by colour from Render Layers sockets)
reads sockets we do not feed: a CompositorError.

Version paths: 4.2-4.5 keep the tree in ``scene.node_tree`` (used when
``scene.use_nodes``), copied with the scene; 5.0 keeps it in the data-block
``scene.compositing_node_group``, shared by a scene copy, so the copy gets
its own copy of the group.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass, field

import bpy
import numpy as np

from ..core import io as imageio
from .executor import PASS_NAMES_5

#: feature pass (``addon.executor.PASS_SOURCES``) -> Blender's pass name, which
#: is the Render Layers socket in 4.2-4.5 and the name in EXR files everywhere
PASS_NAMES = {
    "z": "Depth", "mist": "Mist", "shading_normal": "Normal", "uv": "UV", "vector": "Vector",
    "position": "Position", "object_index": "IndexOB", "material_index": "IndexMA",
    "normal": "Denoising Normal", "albedo": "Denoising Albedo", "depth": "Denoising Depth",
    "diffuse_direct": "DiffDir", "diffuse_indirect": "DiffInd", "diffuse_color": "DiffCol",
    "glossy_direct": "GlossDir", "glossy_indirect": "GlossInd", "glossy_color": "GlossCol",
    "transmission_direct": "TransDir", "transmission_indirect": "TransInd",
    "transmission_color": "TransCol", "volume_direct": "VolumeDir", "volume_indirect": "VolumeInd",
    "emission": "Emit", "environment": "Env", "ambient_occlusion": "AO",
    "shadow_catcher": "Shadow Catcher",
}
#: Render Layers output socket (4.2-4.5's name, or 5.0's: ``PASS_NAMES_5``) -> feature pass
SOCKET_FEATURES = {**{v: k for k, v in PASS_NAMES.items()},
                   **{PASS_NAMES_5[v]: k for k, v in PASS_NAMES.items() if v in PASS_NAMES_5}}
RESULT_SOCKETS = ("Image", "Alpha")


class CompositorError(Exception):
    """The compositor reads something an adaptive render cannot give; one line."""


@dataclass
class Plan:
    """What the scene's compositor reads: ``layers`` maps each view layer
    name to the feature passes it needs beyond the result (in node order)."""

    layers: dict = field(default_factory=dict)

    def features(self, layer: str) -> tuple:
        return tuple(self.layers.get(layer, ()))


def node_tree(scene):
    """The compositor node tree a final render of ``scene`` runs, or None
    (compositing off, or no tree)."""
    if not scene.render.use_compositing:
        return None
    if hasattr(scene, "compositing_node_group"):  # 5.0
        return scene.compositing_node_group
    return scene.node_tree if getattr(scene, "use_nodes", False) else None


def _render_layer_nodes(tree) -> list:
    return [n for n in tree.nodes if n.bl_idname == "CompositorNodeRLayers" and not n.mute]


def _cryptomatte_nodes(tree) -> list:
    """Cryptomatte nodes of ``tree`` that read the render (not an image)."""
    return [n for n in tree.nodes if n.bl_idname == "CompositorNodeCryptomatteV2" and not n.mute
            and n.source == "RENDER"]


def _groups_reading_layers(tree, seen=None) -> list:
    """Names of node groups (nested too) that hold a Render Layers node."""
    seen = set() if seen is None else seen
    found = []
    for n in tree.nodes:
        sub = getattr(n, "node_tree", None) if n.bl_idname in ("CompositorNodeGroup", "NodeGroup") else None
        if sub is None or sub.name in seen:
            continue
        seen.add(sub.name)
        if _render_layer_nodes(sub):
            found.append(sub.name)
        found += _groups_reading_layers(sub, seen)
    return found


def plan(scene) -> Plan | None:
    """The view layers and passes the compositor of ``scene`` reads, or None
    when a final render would not composite (or the compositor reads no
    render).  CompositorError for what an adaptive render cannot produce."""
    tree = node_tree(scene)
    if tree is None:
        return None
    groups = _groups_reading_layers(tree)
    if groups:
        raise CompositorError(f"the compositor reads render layers inside node group {groups[0]!r}, "
                              "which an adaptive render cannot feed")
    nodes = _render_layer_nodes(tree)
    crypto = _cryptomatte_nodes(tree)
    for node in crypto:
        if node.scene is not None and node.scene != scene:
            raise CompositorError(f"a Cryptomatte node reads scene {node.scene.name!r}; an adaptive render "
                                  f"renders only {scene.name!r}")
        layer, _, base = str(node.layer_name).rpartition(".")
        vl = scene.view_layers.get(layer)
        if vl is None or not getattr(vl, f"use_pass_cryptomatte_{base[len('Crypto'):].lower()}", False):
            raise CompositorError(f"a Cryptomatte node reads {node.layer_name!r}, which the render does "
                                  "not have (enable it on the view layer)")
    if not nodes and not crypto:
        return None
    out = Plan()
    for node in crypto:
        out.layers.setdefault(str(node.layer_name).rpartition(".")[0], [])
    for node in nodes:
        if node.scene is not None and node.scene != scene:
            raise CompositorError(f"the compositor reads scene {node.scene.name!r}; an adaptive render "
                                  f"renders only {scene.name!r}")
        if scene.view_layers.get(node.layer) is None:
            raise CompositorError(f"the compositor reads view layer {node.layer!r}, which scene "
                                  f"{scene.name!r} does not have")
        used = [o.name for o in node.outputs if o.is_linked]
        unknown = [s for s in used if s not in RESULT_SOCKETS and s not in SOCKET_FEATURES]
        if unknown:
            raise CompositorError(f"the compositor reads {', '.join(map(repr, unknown))} of view layer "
                                  f"{node.layer!r}, which an adaptive render does not produce")
        feats = out.layers.setdefault(node.layer, [])
        for s in used:
            f = SOCKET_FEATURES.get(s)
            if f is not None and f not in feats:
                feats.append(f)
    if "vector" in {f for fs in out.layers.values() for f in fs} and scene.render.use_motion_blur:
        raise CompositorError("the compositor reads the Vector pass, which Cycles does not render "
                              "with motion blur on")
    return out


def layer_passes(result_rgba: np.ndarray, features: dict, names) -> dict:
    """The passes of one view layer as the compositor's Image node names them:
    ``Combined`` (the result, RGBA) and each of ``names`` (feature passes)
    under its Blender pass name.  ``features`` maps feature name to its
    (H, W, C) mean; KeyError for a feature that was not rendered."""
    passes = {"Combined": result_rgba}
    for f in names:
        passes[PASS_NAMES[f]] = features[f]
    return passes


def composite(scene, layers: dict, tmpdir: str | None = None, attributes: dict | None = None,
              file_outputs: bool = True) -> np.ndarray:
    """Run the compositor of ``scene`` on ``layers`` (view layer name -> the
    :func:`layer_passes` of that layer, all one size) and return the
    composited (H, W, 4) float32 image.  The scene is not modified: a
    temporary copy composites it, and File Output nodes write where the
    user's tree says (``file_outputs`` False: the copy's File Output nodes
    are removed, so nothing is written there: a time limit's trial run on a
    band of rows).  CompositorError when the compositor gave no image.
    ``attributes``: header attributes of the layers' file (the result's
    ``cryptomatte/<key>/...``, which Cryptomatte nodes read)."""
    from .executor import quiet_stdout
    own = tmpdir is None
    tmpdir = tmpdir or tempfile.mkdtemp(prefix="cycles-adaptive-comp-")
    shape = next(iter(next(iter(layers.values())).values())).shape[:2]
    src = os.path.join(tmpdir, "layers.exr")
    imageio.write_multilayer(src, layers.items(), attributes=attributes)
    dst = os.path.join(tmpdir, "composite.exr")
    img = copy = group = None
    try:
        img = bpy.data.images.load(src, check_existing=False)
        img.name = "cycles_adaptive_layers"
        # a Cryptomatte node's layer name reads empty in a scene copy: taken from the user's tree
        crypto_names = {n.name: str(n.layer_name) for n in _cryptomatte_nodes(node_tree(scene))} \
            if node_tree(scene) is not None else {}
        copy = scene.copy()
        copy.name = "cycles_adaptive_composite"
        if hasattr(copy, "compositing_node_group"):
            group = scene.compositing_node_group.copy()
            copy.compositing_node_group = group
            tree = group
        else:
            tree = copy.node_tree
        _feed(tree, img, crypto_names)
        if not file_outputs:
            for node in [n for n in tree.nodes if n.bl_idname == "CompositorNodeOutputFile"]:
                tree.nodes.remove(node)
        r = copy.render
        r.use_compositing, r.use_sequencer = True, False
        r.use_border, r.use_crop_to_border = False, False
        r.resolution_x, r.resolution_y, r.resolution_percentage = shape[1], shape[0], 100
        r.filepath = dst
        r.use_file_extension = True
        st = r.image_settings  # one RGBA layer: a multilayer file would add the empty render layers
        if hasattr(st, "media_type"):  # 5.0
            st.media_type = "IMAGE"
        st.file_format, st.color_mode, st.color_depth = "OPEN_EXR", "RGBA", "32"
        with quiet_stdout():
            bpy.ops.render.render(write_still=True, scene=copy.name)
        if not os.path.isfile(dst):
            raise CompositorError("the compositor gave no image (no Composite / Group Output node?)")
        passes, _ = imageio.read_layers(dst)
        rgba = passes.get("")
        if rgba is None or rgba.shape[:2] != tuple(shape):
            raise CompositorError(f"the compositor's image is {None if rgba is None else rgba.shape[:2]}, "
                                  f"expected {tuple(shape)}")
        out = np.ones(shape + (4,), np.float32)
        out[..., :min(4, rgba.shape[2])] = rgba[..., :4]
        return np.where(np.isfinite(out), out, 0.0).astype(np.float32)
    finally:
        if copy is not None:
            bpy.data.scenes.remove(copy)
        if group is not None:
            bpy.data.node_groups.remove(group)
        if img is not None:
            bpy.data.images.remove(img)
        if own:
            shutil.rmtree(tmpdir, ignore_errors=True)


def _feed(tree, img, crypto_names: dict | None = None) -> None:
    """Replace each Render Layers node of ``tree`` by an Image node reading
    the same view layer of ``img`` (its links moved socket by socket: the
    result's "Image" is the EXR's "Combined"); switch each Cryptomatte node
    reading the render to ``img`` with the layer set ``crypto_names`` (node
    name -> ``<view layer>.CryptoObject``...) gives it."""
    for node in _render_layer_nodes(tree):
        inode = tree.nodes.new("CompositorNodeImage")
        inode.image = img
        inode.layer = node.layer
        inode.location = node.location
        for link in [lk for lk in tree.links if lk.from_node == node]:
            socket = link.from_socket.name
            name = "Combined" if socket == "Image" else PASS_NAMES.get(SOCKET_FEATURES.get(socket), socket)
            sock = inode.outputs.get(name)
            if sock is None:
                raise CompositorError(f"pass {link.from_socket.name!r} of view layer {node.layer!r} "
                                      "is missing from the result")
            tree.links.new(sock, link.to_socket)
        tree.nodes.remove(node)
    for node in [n for n in tree.nodes if n.bl_idname == "CompositorNodeRLayers"]:
        tree.nodes.remove(node)  # muted ones: a muted node reads nothing, but would still render
    for node in _cryptomatte_nodes(tree):  # the same layer set, from our file's layers and header
        name = (crypto_names or {}).get(node.name) or str(node.layer_name)
        node.source = "IMAGE"
        node.image = img
        try:
            node.layer_name = name
        except TypeError:
            raise CompositorError(f"Cryptomatte {name!r} is missing from the result") from None

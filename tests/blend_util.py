"""Tiny Cycles scenes for the bpy tests (built in code, rendered in ~10 ms)."""
import bpy


def build_scene(width=40, height=32, engine="CYCLES", camera=True):
    """Reset Blender to an empty file and build: ground plane with a checker
    texture, a glossy sphere, a diffuse cube, an area light, a camera."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    if engine == "EEVEE":  # 4.2-4.5 call it BLENDER_EEVEE_NEXT, 5.0 BLENDER_EEVEE again
        items = scene.render.bl_rna.properties["engine"].enum_items.keys()
        engine = "BLENDER_EEVEE_NEXT" if "BLENDER_EEVEE_NEXT" in items else "BLENDER_EEVEE"
    scene.render.engine = engine
    if engine == "CYCLES":
        scene.cycles.device = "CPU"
        scene.cycles.samples = 16
        scene.cycles.use_adaptive_sampling = False
        scene.cycles.use_denoising = False
        scene.cycles.max_bounces = 4
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"

    mat = bpy.data.materials.new("checker")
    mat.use_nodes = True
    nt = mat.node_tree
    tex = nt.nodes.new("ShaderNodeTexChecker")
    tex.inputs["Scale"].default_value = 8.0
    nt.links.new(tex.outputs["Color"], nt.nodes["Principled BSDF"].inputs["Base Color"])
    bpy.ops.mesh.primitive_plane_add(size=10)
    bpy.context.object.data.materials.append(mat)

    gloss = bpy.data.materials.new("gloss")
    gloss.use_nodes = True
    gloss.node_tree.nodes["Principled BSDF"].inputs["Roughness"].default_value = 0.15
    gloss.node_tree.nodes["Principled BSDF"].inputs["Metallic"].default_value = 1.0
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.8, location=(-0.8, 0, 0.8))
    bpy.context.object.data.materials.append(gloss)
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(1.0, 0.5, 0.5))

    bpy.ops.object.light_add(type="AREA", location=(0, -1, 4))
    bpy.context.object.data.energy = 400
    bpy.context.object.data.size = 2.0
    world = bpy.data.worlds.new("w")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.3
    scene.world = world
    if camera:
        bpy.ops.object.camera_add(location=(0, -6, 3), rotation=(1.15, 0, 0))
        scene.camera = bpy.context.object
    return scene


def save_scene(path, **kw):
    scene = build_scene(**kw)
    bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=True)
    return scene


def compositor_tree(scene):
    """A fresh compositor node tree for ``scene`` (compositing on) and its
    output node: the Composite node in 4.2-4.5, the node group's Group Output
    (one "Image" socket) in 5.0, where the tree is a data-block of its own."""
    scene.render.use_compositing = True
    if hasattr(scene, "compositing_node_group"):
        tree = bpy.data.node_groups.new("Compositing", "CompositorNodeTree")
        tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        scene.compositing_node_group = tree
        out = tree.nodes.new("NodeGroupOutput")
    else:
        scene.use_nodes = True
        tree = scene.node_tree
        for node in list(tree.nodes):
            tree.nodes.remove(node)
        out = tree.nodes.new("CompositorNodeComposite")
    return tree, out


def add_images(tree, a, b):
    """The output socket of a node adding colour sockets ``a`` and ``b``
    (MixRGB Add in 4.2-4.5; the Mix node in RGBA mode in 5.0)."""
    if hasattr(bpy.types, "CompositorNodeMixRGB"):
        mix = tree.nodes.new("CompositorNodeMixRGB")
        mix.blend_type = "ADD"
        mix.inputs["Fac"].default_value = 1.0
        tree.links.new(a, mix.inputs[1])
        tree.links.new(b, mix.inputs[2])
        return mix.outputs["Image"]
    mix = tree.nodes.new("ShaderNodeMix")
    mix.data_type, mix.blend_type = "RGBA", "ADD"
    mix.clamp_result = False
    colour = [s for s in mix.inputs if s.type == "RGBA"]
    mix.inputs[0].default_value = 1.0
    tree.links.new(a, colour[0])
    tree.links.new(b, colour[1])
    return next(s for s in mix.outputs if s.type == "RGBA")


def two_layer_scene(width=24, height=16):
    """:func:`build_scene` with a second view layer, "Back", whose material
    override (plain white diffuse) makes its image differ from "ViewLayer"'s."""
    scene = build_scene(width, height)
    back = scene.view_layers.new("Back")
    white = bpy.data.materials.new("white")
    white.use_nodes = True
    white.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (1, 1, 1, 1)
    back.material_override = white
    return scene

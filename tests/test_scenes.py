"""Checks on the committed sample scenes in sample_blends/ (built by sample_blends/build_scenes.py).

Each scene opens, uses Cycles with the common settings, has a camera, holds the property it exists to
stress, and renders a tiny (25 %, 1 spp) finite, non-constant image.  The build script is deterministic:
running it into a temporary folder gives the same objects, materials and transforms.
"""

import os
import subprocess
import sys

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
oiio = pytest.importorskip("OpenImageIO")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BLENDS = os.path.join(ROOT, "sample_blends")
BUILD = os.path.join(BLENDS, "build_scenes.py")
SCENES = ("cornell", "dof", "soft_shadows", "glossy", "motion_blur", "animated", "courtyard")


def blend_path(name, folder=BLENDS):
    return os.path.join(folder, name + ".blend")


def open_blend(path):
    bpy.ops.wm.open_mainfile(filepath=path)
    return bpy.context.scene


def camera_object(scene):
    cam = scene.camera
    assert cam is not None and cam.type == "CAMERA"
    return cam


def glossy_materials():
    """Materials with a low-roughness glossy lobe: metallic Principled, coated Principled, Glossy BSDF."""
    out = []
    for mat in bpy.data.materials:
        if not (mat.use_nodes and mat.node_tree):
            continue
        for node in mat.node_tree.nodes:
            if node.type == "BSDF_PRINCIPLED":
                rough = node.inputs["Roughness"].default_value
                metal = node.inputs["Metallic"].default_value
                coat = node.inputs["Coat Weight"].default_value
                if (metal >= 0.5 and rough <= 0.15) or coat >= 0.5:
                    out.append(mat.name)
            elif node.type in ("BSDF_GLOSSY", "BSDF_ANISOTROPIC") and \
                    node.inputs["Roughness"].default_value <= 0.15:
                out.append(mat.name)
    return out


def matrix_at(scene, obj, frame, subframe=0.0):
    scene.frame_set(frame, subframe=subframe)
    return np.array(obj.matrix_world, dtype=np.float64)


def render_tiny(scene, path):
    scene.render.resolution_percentage = 25
    scene.cycles.samples = 1
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    inp = oiio.ImageInput.open(path)
    assert inp is not None, oiio.geterror()
    try:
        pixels = inp.read_image("float")
    finally:
        inp.close()
    return np.asarray(pixels)


# ----------------------------------------------------------------------------------- common checks

@pytest.mark.parametrize("name", SCENES)
def test_scene_common_settings(name):
    path = blend_path(name)
    assert os.path.isfile(path), "missing %s: run sample_blends/build_scenes.py" % path
    assert os.path.getsize(path) < 1_000_000
    scene = open_blend(path)
    assert scene.render.engine == "CYCLES"
    assert scene.cycles.device == "CPU"
    assert scene.cycles.samples == 16
    assert not scene.cycles.use_adaptive_sampling
    assert not scene.cycles.use_denoising
    assert scene.cycles.seed == 0
    assert scene.render.resolution_percentage == 100
    assert (scene.render.resolution_x, scene.render.resolution_y) in ((128, 128), (128, 96), (640, 400))
    assert scene.view_settings.view_transform == "Standard"
    assert not scene.use_nodes  # no compositing nodes
    camera_object(scene)
    # Procedural only: no images, no linked libraries, nothing packed.
    assert len(bpy.data.images) == 0
    assert len(bpy.data.libraries) == 0
    assert not any(getattr(d, "packed_file", None) for d in bpy.data.fonts)


# ----------------------------------------------------------------------------------- per-scene property

def test_cornell_is_a_gi_box():
    scene = open_blend(blend_path("cornell"))
    areas = [o for o in scene.objects if o.type == "LIGHT" and o.data.type == "AREA"]
    assert areas, "no area light"
    ceiling = bpy.data.objects["Ceiling"]
    ceiling_z = max((ceiling.matrix_world @ v.co).z for v in ceiling.data.vertices)
    assert any(abs(o.matrix_world.translation.z - ceiling_z) < 0.1 for o in areas)
    colours = {m.name for m in bpy.data.materials}
    assert {"Red", "Green", "White"} <= colours
    assert {"TallBox", "ShortBox"} <= set(bpy.data.objects.keys())
    assert scene.cycles.max_bounces >= 4 and scene.cycles.diffuse_bounces >= 2


def test_dof_is_on_with_focus():
    scene = open_blend(blend_path("dof"))
    dof = camera_object(scene).data.dof
    assert dof.use_dof
    assert dof.focus_object is not None or dof.focus_distance > 0.0
    assert dof.aperture_fstop <= 2.8
    # Textured objects nearer and farther than the focus object.
    cam_pos = camera_object(scene).matrix_world.translation
    focus_dist = (dof.focus_object.matrix_world.translation - cam_pos).length
    dists = [(o.matrix_world.translation - cam_pos).length for o in scene.objects
             if o.type == "MESH" and o is not dof.focus_object and o.name != "Ground"]
    assert min(dists) < 0.7 * focus_dist and max(dists) > 1.5 * focus_dist


def test_soft_shadows_has_large_area_light():
    scene = open_blend(blend_path("soft_shadows"))
    areas = [o.data for o in scene.objects if o.type == "LIGHT" and o.data.type == "AREA"]
    assert areas and max(a.size for a in areas) >= 2.0
    ground = bpy.data.objects["Ground"].active_material
    kinds = {n.type for n in ground.node_tree.nodes}
    assert kinds & {"TEX_CHECKER", "TEX_NOISE", "TEX_VORONOI"}


def test_glossy_has_glossy_materials_and_small_lights():
    scene = open_blend(blend_path("glossy"))
    assert len(glossy_materials()) >= 2
    small = [o for o in scene.objects if o.type == "LIGHT" and o.data.type in ("POINT", "SPOT")
             and o.data.shadow_soft_size <= 0.1]
    assert small, "no small bright light"
    assert scene.world is not None and scene.world.use_nodes


def test_motion_blur_is_on_with_moving_object():
    scene = open_blend(blend_path("motion_blur"))
    assert scene.render.use_motion_blur and scene.render.motion_blur_shutter > 0.0
    animated = [o for o in scene.objects if o.animation_data and o.animation_data.action]
    assert animated
    frame = scene.frame_current
    half = scene.render.motion_blur_shutter / 2.0
    moving = [o for o in animated
              if not np.allclose(matrix_at(scene, o, frame - 1, 1.0 - half), matrix_at(scene, o, frame, half))]
    assert moving, "no object moves during the shutter interval"


def test_animated_camera_moves_every_frame():
    scene = open_blend(blend_path("animated"))
    assert scene.frame_end - scene.frame_start + 1 >= 8
    cam = camera_object(scene)
    mats = [matrix_at(scene, cam, f) for f in range(scene.frame_start, scene.frame_end + 1)]
    for a, b in zip(mats, mats[1:]):
        assert not np.allclose(a, b), "camera does not move between two frames"
    assert glossy_materials(), "expected some glossy objects"


def test_courtyard_is_a_production_scale_shot():
    """>= 24 frames at >= 0.25 MP, a moving camera and a moving object every frame."""
    scene = open_blend(blend_path("courtyard"))
    assert scene.frame_end - scene.frame_start + 1 >= 24
    assert scene.render.resolution_x * scene.render.resolution_y >= 250_000
    cam = camera_object(scene)
    frames = range(scene.frame_start, scene.frame_end + 1)
    mats = [matrix_at(scene, cam, f) for f in frames]
    for a, b in zip(mats, mats[1:]):
        assert not np.allclose(a, b), "camera does not move between two frames"
    others = [o for o in scene.objects if o.type == "MESH" and o.animation_data is not None]
    assert others, "no animated object"
    for o in others[:1]:
        pos = [matrix_at(scene, o, f) for f in frames]
        assert any(not np.allclose(a, b) for a, b in zip(pos, pos[1:]))
    assert glossy_materials(), "expected some glossy objects"


# ----------------------------------------------------------------------------------- tiny render

@pytest.mark.parametrize("name", SCENES)
def test_tiny_render_is_finite_and_not_constant(name, tmp_path):
    scene = open_blend(blend_path(name))
    w = scene.render.resolution_x // 4
    h = scene.render.resolution_y // 4
    img = render_tiny(scene, str(tmp_path / (name + ".exr")))
    assert img.shape[:2] == (h, w)
    rgb = img[..., :3]
    assert np.all(np.isfinite(rgb))
    assert rgb.std() > 1e-3
    assert rgb.mean() > 1e-3


# ----------------------------------------------------------------------------------- determinism

def scene_signature(path):
    open_blend(path)
    objects = {}
    for o in bpy.data.objects:
        objects[o.name] = (o.type, o.data.name if o.data else None,
                           tuple(round(x, 5) for x in o.location),
                           tuple(round(x, 5) for x in o.rotation_euler))
    return objects, sorted(bpy.data.materials.keys()), sorted(bpy.data.lights.keys())


def test_build_script_is_deterministic(tmp_path):
    out = tmp_path / "built"
    proc = subprocess.run([sys.executable, BUILD, "--out", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    for name in SCENES:
        built = blend_path(name, str(out))
        assert os.path.isfile(built)
        assert scene_signature(built) == scene_signature(blend_path(name)), name

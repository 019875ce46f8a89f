"""The scene's compositor on the adaptive result (addon/compositor.py): the
composited image equals the compositor applied to our passes, the raw result
stays in the EXR, the user's scene is untouched, and what cannot be fed is
said, not faked."""
import os

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from blend_util import add_images, build_scene, compositor_tree  # noqa: E402

from cycles_adaptive.core import io as imageio  # noqa: E402
from cycles_adaptive.core.pipeline import Options  # noqa: E402
from cycles_adaptive.operators.job import RenderJob  # noqa: E402


def _job(scene, tmp_path, name="out.exr", **kw):
    opts = Options(method="var", spp=4, initial_spp=2, subsets=2, iterations=1, seed=1)
    kw.setdefault("exr_depth", "full")  # exact comparisons with the composite
    job = RenderJob(scene, bpy.context.view_layer, opts, str(tmp_path / name), **kw)
    for _ in job.steps():
        pass
    return job, job.finish()


def _nodes(tree):
    return sorted((n.bl_idname, n.name) for n in tree.nodes), \
        sorted((lk.from_node.name, lk.from_socket.name, lk.to_node.name, lk.to_socket.name) for lk in tree.links)


def test_the_composite_is_the_compositor_applied_to_the_result(tmp_path):
    scene = build_scene(24, 16)
    tree, out = compositor_tree(scene)
    rl = tree.nodes.new("CompositorNodeRLayers")
    inv = tree.nodes.new("CompositorNodeInvert")
    tree.links.new(rl.outputs["Image"], inv.inputs["Color"])
    tree.links.new(inv.outputs["Color"], out.inputs[0])
    before = _nodes(tree)
    scenes = len(bpy.data.scenes)
    job, summary = _job(scene, tmp_path)
    assert summary["compositor"] == "applied"
    raw, meta = imageio.read_layers(summary["out"])
    assert meta["layers"] == ["ViewLayer", "Composite"]
    comp, _ = imageio.read_layers(summary["out"], "Composite")
    result = raw["Combined"][..., :3]
    assert np.ptp(result) > 0.05  # a real image, not a constant
    np.testing.assert_allclose(comp["Combined"][..., :3], 1.0 - result, atol=1e-5)
    assert os.path.isfile(summary["preview"])
    # the user's scene is as it was: no extra scene, the same nodes and links
    assert len(bpy.data.scenes) == scenes
    assert _nodes(tree) == before
    assert not any(img.name.startswith("cycles_adaptive") for img in bpy.data.images)


def test_passes_the_compositor_reads_are_rendered_and_fed(tmp_path):
    scene = build_scene(24, 16)
    vl = bpy.context.view_layer
    assert not vl.use_pass_diffuse_color
    tree, out = compositor_tree(scene)
    rl = tree.nodes.new("CompositorNodeRLayers")
    vl.use_pass_diffuse_color = True  # the socket shows once the pass is on, as in the UI
    tree.links.new(rl.outputs.get("DiffCol") or rl.outputs["Diffuse Color"], out.inputs[0])
    vl.use_pass_diffuse_color = False  # the link stays; the adaptive render turns the pass on itself
    job, summary = _job(scene, tmp_path)
    assert summary["compositor"] == "applied"
    raw, _ = imageio.read_layers(summary["out"])
    comp, _ = imageio.read_layers(summary["out"], "Composite")
    col = raw["Feat_diffuse_color"]
    assert col.max() > 0.1
    np.testing.assert_allclose(comp["Combined"][..., :3], col, atol=1e-6)
    assert not vl.use_pass_diffuse_color  # restored


def test_what_cannot_be_fed_is_said_and_the_result_stays_raw(tmp_path):
    scene = build_scene(24, 16)
    vl = bpy.context.view_layer
    vl.use_pass_cryptomatte_object = True
    tree, out = compositor_tree(scene)
    rl = tree.nodes.new("CompositorNodeRLayers")
    crypto = next(o for o in rl.outputs if o.name.startswith("CryptoObject"))
    tree.links.new(crypto, out.inputs[0])
    job, summary = _job(scene, tmp_path)
    assert summary["compositor"].startswith("skipped:") and "CryptoObject" in summary["compositor"]
    _, meta = imageio.read_layers(summary["out"])
    assert meta["layers"] == ["ViewLayer"]


def test_no_compositor_and_compositor_off(tmp_path):
    scene = build_scene(24, 16)
    _, summary = _job(scene, tmp_path, "a.exr")
    assert summary["compositor"] == "none"
    tree, out = compositor_tree(scene)
    rl = tree.nodes.new("CompositorNodeRLayers")
    tree.links.new(rl.outputs["Image"], out.inputs[0])
    _, summary = _job(scene, tmp_path, "b.exr", compositor=False)
    assert summary["compositor"] == "off"
    scene.render.use_compositing = False
    _, summary = _job(scene, tmp_path, "c.exr")
    assert summary["compositor"] == "none"


def _mix_layers(scene):
    from blend_util import add_images
    tree, out = compositor_tree(scene)
    fore = tree.nodes.new("CompositorNodeRLayers")
    fore.layer = "ViewLayer"
    back = tree.nodes.new("CompositorNodeRLayers")
    back.layer = "Back"
    tree.links.new(add_images(tree, fore.outputs["Image"], back.outputs["Image"]), out.inputs[0])


def test_two_view_layers_one_exr_layer_each_and_the_compositor_mixes_them(tmp_path):
    from blend_util import two_layer_scene
    from cycles_adaptive.operators.job import LayersJob, resolve_view_layers
    scene = two_layer_scene()
    _mix_layers(scene)
    layers = resolve_view_layers(scene)  # as Blender renders the file: both
    assert [vl.name for vl in layers] == ["ViewLayer", "Back"]
    opts = Options(method="var", spp=4, initial_spp=2, subsets=2, iterations=1, seed=1)
    out = str(tmp_path / "two.exr")
    job = LayersJob(scene, layers, opts, out, exr_depth="full")
    msgs = [p.message for p in job.steps()]
    assert any(m.startswith("view layer Back (2/2)") for m in msgs)
    summary = job.finish()
    assert summary["view_layers"] == ["ViewLayer", "Back"] and summary["compositor"] == "applied"
    _, meta = imageio.read_layers(out)
    assert meta["layers"] == ["ViewLayer", "Back", "Composite"]
    fore, _ = imageio.read_layers(out, "ViewLayer")
    back, _ = imageio.read_layers(out, "Back")
    comp, _ = imageio.read_layers(out, "Composite")
    assert np.all(fore["Samples"] >= 4) and np.all(back["Samples"] >= 4)
    assert np.abs(fore["Combined"][..., :3] - back["Combined"][..., :3]).max() > 0.05  # two different images
    np.testing.assert_allclose(comp["Combined"][..., :3],
                               fore["Combined"][..., :3] + back["Combined"][..., :3], rtol=1e-5, atol=1e-5)
    assert summary["samples"] == int(fore["Samples"].sum() + back["Samples"].sum())
    assert os.path.isfile(summary["preview"])
    assert not [f for f in os.listdir(tmp_path) if "checkpoint" in f]


def test_one_layer_of_a_mixing_compositor_says_the_compositor_was_skipped(tmp_path):
    from blend_util import two_layer_scene
    scene = two_layer_scene()
    _mix_layers(scene)
    _, summary = _job(scene, tmp_path)
    assert summary["compositor"].startswith("skipped:") and "'Back'" in summary["compositor"]


def test_view_layer_choice_follows_blender_and_refuses_bad_names():
    from blend_util import two_layer_scene
    from cycles_adaptive.operators.job import JobError, resolve_view_layers
    scene = two_layer_scene()
    names = lambda spec, **kw: [vl.name for vl in resolve_view_layers(scene, spec, **kw)]
    assert names(None) == names("all") == ["ViewLayer", "Back"]
    assert names("Back,ViewLayer") == ["Back", "ViewLayer"]
    scene.render.use_single_layer = True
    assert names(None, active=scene.view_layers["Back"]) == ["Back"]
    scene.render.use_single_layer = False
    scene.view_layers["Back"].use = False
    assert names(None) == ["ViewLayer"]
    for bad, msg in [("Back", "disabled"), ("Nope", "no view layer 'Nope'"), ("ViewLayer,ViewLayer", "distinct"),
                     (",", "expected all")]:
        with pytest.raises(JobError, match=msg):
            resolve_view_layers(scene, bad)


def test_single_channel_passes_are_fed_depth_from_the_first_sample_mist_averaged(tmp_path):
    scene = build_scene(24, 16)
    vl = bpy.context.view_layer
    tree, out = compositor_tree(scene)
    rl = tree.nodes.new("CompositorNodeRLayers")
    vl.use_pass_z = vl.use_pass_mist = True
    tree.links.new(add_images(tree, rl.outputs["Depth"], rl.outputs["Mist"]), out.inputs[0])
    vl.use_pass_z = vl.use_pass_mist = False
    _, summary = _job(scene, tmp_path)
    assert summary["compositor"] == "applied"
    raw, _ = imageio.read_layers(summary["out"])
    comp, _ = imageio.read_layers(summary["out"], "Composite")
    z, mist = raw["Feat_z"][..., 0], raw["Feat_mist"][..., 0]
    hit = z < 1e3  # background depth is 1e10
    assert hit.any() and (0 < mist[hit]).all() and (mist <= 1).all()
    assert 2 < z[hit].min() < z[hit].max() < 20  # camera 6.7 units from the origin
    np.testing.assert_allclose(comp["Combined"][..., 0][hit], (z + mist)[hit], rtol=1e-5)


def _file_output_node(tree, image_socket, folder):
    """A File Output node writing ``image_socket`` into ``folder`` (4.2-4.5:
    ``base_path`` and its default "Image" input; 5.0: ``directory``, one item)."""
    node = tree.nodes.new("CompositorNodeOutputFile")
    if hasattr(node, "directory"):  # 5.0
        node.directory, node.file_name = folder + os.sep, "fo_"
        if not len(node.file_output_items):  # a new node has only the virtual "add" socket
            node.file_output_items.new("RGBA", "Image")
    else:
        node.base_path = os.path.join(folder, "fo_")
    tree.links.new(image_socket, node.inputs[0])
    return node


def test_a_trial_composite_writes_nothing_where_the_users_file_outputs_point(tmp_path):
    """``file_outputs=False`` (the time limit's trial on a band) removes the
    copy's File Output nodes: the user's folder stays empty, while a real
    composite writes there; the user's tree keeps its node either way."""
    from cycles_adaptive.addon import compositor
    scene = build_scene(24, 16)
    tree, out = compositor_tree(scene)
    rl = tree.nodes.new("CompositorNodeRLayers")
    tree.links.new(rl.outputs["Image"], out.inputs[0])
    folder = str(tmp_path / "file_outputs")
    _file_output_node(tree, rl.outputs["Image"], folder)
    rgba = np.random.default_rng(0).random((16, 24, 4)).astype(np.float32)
    layers = {"ViewLayer": compositor.layer_passes(rgba, {}, ())}
    img = compositor.composite(scene, layers, file_outputs=False)
    np.testing.assert_allclose(img[..., :3], rgba[..., :3], atol=1e-6)
    assert not os.path.isdir(folder) or not os.listdir(folder)
    compositor.composite(scene, layers)
    assert os.listdir(folder)  # the real composite does write there
    assert any(n.bl_idname == "CompositorNodeOutputFile" for n in tree.nodes)


def test_the_time_limit_bounds_a_two_layer_job_and_reserves_its_outputs(tmp_path):
    """``max_seconds`` bounds the whole job, not each view layer: the layers
    share it (each gets at most what is left when it starts), the first layer
    reserves the outputs (EXR of both layers, the compositor, the preview:
    ``output_seconds``, trial files removed, nothing written where the
    user's File Output node points), and the job ends within 10 % of the limit
    plus its longest render."""
    from blend_util import two_layer_scene
    from cycles_adaptive.operators.job import LayersJob, resolve_view_layers
    scene = two_layer_scene()
    _mix_layers(scene)
    folder = str(tmp_path / "file_outputs")
    tree = getattr(scene, "compositing_node_group", None) or scene.node_tree
    rl = next(n for n in tree.nodes if n.bl_idname == "CompositorNodeRLayers")
    _file_output_node(tree, rl.outputs["Image"], folder)
    limit = 8.0
    opts = Options(method="var", spp=100000, initial_spp=2, subsets=2, iterations=4, seed=1, max_seconds=limit)
    out = str(tmp_path / "two.exr")
    job = LayersJob(scene, resolve_view_layers(scene), opts, out, exr_depth="full")
    for _ in job.steps():
        pass
    shares = [j.options.max_seconds for j in job.jobs]
    first = job.jobs[0].run
    figures = dict(shares=shares, reserve=first.reserve_seconds, spp=[j.run.samples_rendered / j.run.pixels
                                                                     for j in job.jobs])
    assert first.reserve_seconds > 0 and job.jobs[1].run.reserve_seconds == 0, figures
    assert not os.path.isdir(folder) or not os.listdir(folder)  # the trial wrote nothing there
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".tmp-")]  # trial files removed
    summary = job.finish()
    # each layer's limit is at most what was left when it started (a layer that ends early leaves its rest
    # to the next), the first one half of the whole
    started = [j.t0 - job.t0 for j in job.jobs]
    assert 0 < shares[0] <= limit / 2 + 1e-9, shares
    assert all(sh + st <= limit + 1e-9 for sh, st in zip(shares, started)), (shares, started)
    assert summary["time_limited"] is True and summary["max_seconds"] == limit
    longest = max(j.run.max_task_seconds for j in job.jobs)
    assert summary["total_seconds"] <= limit * 1.1 + longest, (summary, figures)
    assert summary["compositor"] == "applied" and os.path.isfile(summary["preview"])
    assert all(j.run.samples_rendered > 2 * j.run.pixels for j in job.jobs), figures  # both layers got time

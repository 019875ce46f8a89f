"""bpy integration: Cryptomatte ranks merged across region renders equal one
plain render of the same samples, and the result EXR carries them as Blender
names them (layers and header), so a compositor / Nuke finds the mattes."""
import json

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from blend_util import build_scene  # noqa: E402

from cycles_adaptive.addon.executor import CyclesExecutor  # noqa: E402
from cycles_adaptive.core import cryptomatte, regions  # noqa: E402
from cycles_adaptive.core import io as imageio  # noqa: E402
from cycles_adaptive.core.pipeline import Options, merge_cryptomatte  # noqa: E402
from cycles_adaptive.operators.job import RenderJob  # noqa: E402


def _crypto_scene(w=32, h=32, levels=4):
    scene = build_scene(w, h)
    vl = bpy.context.view_layer
    vl.use_pass_cryptomatte_object = True
    vl.pass_cryptomatte_depth = levels
    return scene, vl


def _matte(ids, cov, hash_id):
    """Coverage of one id per pixel (the Cryptomatte node's matte)."""
    return np.where(ids == hash_id, cov, 0.0).sum(axis=2)


def _object_id(manifest: str, name: str) -> int:
    return int(json.loads(manifest)[name], 16)


def test_region_renders_merge_to_the_one_render_of_the_same_samples():
    scene, vl = _crypto_scene()
    with CyclesExecutor(scene, vl, (), seed=3) as ex:
        h, w = ex.size
        _, one = ex.render(regions.RegionTask(0, 0, w, h, 12, offset=0))
        ids1, cov1, header = one["cryptomatte"]["CryptoObject"]
        accs, headers = {}, {}
        for off in (0, 2):  # initial pass: two subsets of 2 spp
            t = regions.RegionTask(0, 0, w, h, 2, offset=off)
            merge_cryptomatte(accs, headers, t, ex.render(t)[1]["cryptomatte"], (h, w))
        m = w // 2  # the rest in region renders: left half 8 spp at once, right half 4 + 4
        tasks = [regions.RegionTask(0, 0, m, h, 8, offset=4), regions.RegionTask(m, 0, w, h, 4, offset=4),
                 regions.RegionTask(m, 0, w, h // 2, 4, offset=8), regions.RegionTask(m, h // 2, w, h, 4, offset=8)]
        for t in tasks:
            merge_cryptomatte(accs, headers, t, ex.render(t)[1]["cryptomatte"], (h, w))
    assert header["name"] == "ViewLayer.CryptoObject" and header["hash"] == "MurmurHash3_32"
    assert headers["CryptoObject"]["manifest"] == header["manifest"]
    ids, cov = accs["CryptoObject"].ranks(4)
    assert np.all(accs["CryptoObject"].weight == 12)
    # Tabulated Sobol samples are indexed independently of the render split, so
    # the union of the sample subsets is the 12-sample render: each object's
    # matte agrees to float32 rounding of coverage (k / n stored in float32)
    for name in ("Plane", "Sphere", "Cube"):
        hid = _object_id(header["manifest"], name)
        a, b = _matte(ids, cov, hid), _matte(ids1, cov1, hid)
        assert b.max() > 0.5
        np.testing.assert_allclose(a, b, atol=1e-6)


def test_adaptive_run_writes_cryptomatte_layers_and_header(tmp_path):
    scene, vl = _crypto_scene(24, 16, levels=2)
    out = str(tmp_path / "crypto.exr")
    opts = Options(method="var", spp=6, initial_spp=2, subsets=2, iterations=1, seed=1)
    job = RenderJob(scene, vl, opts, out, exr_depth="full")
    for _ in job.steps():
        pass
    job.finish()
    passes, meta = imageio.read_layers(out, "ViewLayer")
    assert "CryptoObject00" in passes and meta["channels"]["CryptoObject00"] == ["r", "g", "b", "a"]
    key = cryptomatte.header_key("ViewLayer.CryptoObject")
    at = meta["attributes"]
    assert at[f"cryptomatte/{key}/name"] == "ViewLayer.CryptoObject"
    assert at[f"cryptomatte/{key}/conversion"] == "uint32_to_float32"
    man = json.loads(at[f"cryptomatte/{key}/manifest"])
    assert {"Plane", "Sphere", "Cube"} <= set(man)
    ids, cov = cryptomatte.layers_to_ranks([passes["CryptoObject00"]])
    assert np.all(np.isfinite(cov)) and np.all(cov >= 0)
    total = cov.sum(axis=2)
    assert total.max() <= 1 + 1e-6 and total.max() > 0.99  # fractions of each pixel's samples
    present = {int(v) for v in np.unique(ids[cov > 0])}
    assert present <= {int(v, 16) for v in man.values()}  # every id is a manifest entry


def test_a_cryptomatte_node_of_the_render_gets_our_merged_matte(tmp_path):
    from blend_util import compositor_tree
    scene, vl = _crypto_scene(24, 16, levels=2)
    tree, comp = compositor_tree(scene)
    node = tree.nodes.new("CompositorNodeCryptomatteV2")  # source: the render (default)
    node.scene = scene
    assert node.source == "RENDER" and node.layer_name == "ViewLayer.CryptoObject"
    node.matte_id = "Cube"
    tree.links.new(node.outputs["Matte"], comp.inputs[0])
    out = str(tmp_path / "comp.exr")
    opts = Options(method="var", spp=6, initial_spp=2, subsets=2, iterations=1, seed=1)
    job = RenderJob(scene, vl, opts, out, exr_depth="full")
    for _ in job.steps():
        pass
    summary = job.finish()
    assert summary["compositor"] == "applied"
    assert node.source == "RENDER" and node.image is None  # the user's tree is untouched
    passes, meta = imageio.read_layers(out, "ViewLayer")
    key = cryptomatte.header_key("ViewLayer.CryptoObject")
    hid = _object_id(meta["attributes"][f"cryptomatte/{key}/manifest"], "Cube")
    ids, cov = cryptomatte.layers_to_ranks([passes["CryptoObject00"]])
    ours = _matte(ids, cov, hid)
    assert ours.max() > 0.99 and ours.min() == 0
    composite, _ = imageio.read_layers(out, "Composite")
    # the node's matte is the sum of the coverages of the picked id (float32 throughout)
    np.testing.assert_allclose(composite["Combined"][..., 0], ours, atol=1e-5)

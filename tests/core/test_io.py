import os

import numpy as np
import pytest

from core import io as imageio


def test_multilayer_roundtrip_keeps_passes_and_channels(tmp_path):
    rng = np.random.default_rng(0)
    passes = {"Combined": rng.random((5, 7, 4)), "Samples": rng.random((5, 7)),
              "Feat_normal": (rng.random((5, 7, 3)), ("X", "Y", "Z"))}
    path = str(tmp_path / "a.exr")
    imageio.write_layers(path, passes, layer="ViewLayer", attributes={"cycles_adaptive/method": "lp"})
    got, meta = imageio.read_layers(path)
    assert meta["layer"] == "ViewLayer" and (meta["width"], meta["height"]) == (7, 5)
    np.testing.assert_allclose(got["Combined"], passes["Combined"].astype(np.float32))
    np.testing.assert_allclose(got["Samples"][:, :, 0], passes["Samples"].astype(np.float32))
    assert meta["channels"]["Feat_normal"] == ["X", "Y", "Z"]
    assert meta["attributes"]["cycles_adaptive/method"] == "lp"
    np.testing.assert_allclose(imageio.read_rgb(path), passes["Combined"][:, :, :3].astype(np.float32))


def test_write_is_atomic_and_leaves_no_temporary(tmp_path):
    path = str(tmp_path / "b.exr")
    imageio.write_layers(path, {"Combined": np.zeros((2, 2, 4))})
    assert os.listdir(tmp_path) == ["b.exr"]


def test_truncated_file_gives_clear_error(tmp_path):
    path = str(tmp_path / "c.exr")
    imageio.write_layers(path, {"Combined": np.random.default_rng(1).random((64, 64, 4))})
    data = open(path, "rb").read()
    bad = tmp_path / "trunc.exr"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(imageio.ImageFileError) as exc:
        imageio.read_layers(str(bad))
    assert "trunc.exr" in str(exc.value)
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"not an image at all" * 10)
    with pytest.raises(imageio.ImageFileError):
        imageio.read_layers(str(junk))
    with pytest.raises(imageio.ImageFileError, match="no such file"):
        imageio.read_layers(str(tmp_path / "missing.exr"))


def test_reference_without_rgb_is_refused(tmp_path):
    path = str(tmp_path / "d.exr")
    imageio.write_layers(path, {"Depth": np.ones((3, 3))})
    with pytest.raises(imageio.ImageFileError, match="no Combined"):
        imageio.read_rgb(path)


def test_check_writable(tmp_path):
    p = tmp_path / "e.exr"
    imageio.check_writable(str(p), overwrite=False)
    p.write_bytes(b"x")
    with pytest.raises(imageio.ImageFileError, match="--overwrite"):
        imageio.check_writable(str(p), overwrite=False)
    imageio.check_writable(str(p), overwrite=True)
    with pytest.raises(imageio.ImageFileError, match="does not exist"):
        imageio.check_writable(str(tmp_path / "nope" / "f.exr"), overwrite=False)


def test_written_files_get_ordinary_permissions(tmp_path):
    path = str(tmp_path / "p.exr")
    imageio.write_layers(path, {"Combined": np.zeros((2, 2, 4))})
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(path).st_mode & 0o777 == 0o666 & ~umask


def test_several_layers_read_one_at_a_time_in_the_written_order(tmp_path):
    path = str(tmp_path / "layers.exr")
    h, w = 3, 4
    a = np.full((h, w, 4), 1.0)
    b = np.full((h, w, 4), 2.0)
    c = np.full((h, w, 4), 3.0)
    imageio.write_multilayer(path, [("Zebra", {"Combined": a, "Depth": np.ones((h, w))}),
                               ("Apple", {"Combined": b}), ("Composite", {"Combined": c})])
    passes, meta = imageio.read_layers(path)
    assert meta["layers"] == ["Zebra", "Apple", "Composite"]  # not EXR's sorted channel order
    assert meta["layer"] == "Zebra" and sorted(passes) == ["Combined", "Depth"]
    assert np.all(passes["Combined"] == 1.0)
    passes, meta = imageio.read_layers(path, "Apple")
    assert sorted(passes) == ["Combined"] and np.all(passes["Combined"] == 2.0)
    with pytest.raises(imageio.ImageFileError, match="no layer 'Nope'"):
        imageio.read_layers(path, "Nope")
    with pytest.raises(ValueError, match="share a name"):
        imageio.write_multilayer(str(tmp_path / "twice.exr"), [("L", {"Combined": a}), ("L", {"Combined": b})])


def test_a_file_without_our_order_reads_its_first_layer_other_than_composite(tmp_path):
    import OpenImageIO as oiio
    path = str(tmp_path / "blender.exr")
    spec = oiio.ImageSpec(2, 2, 2, oiio.FLOAT)
    spec.channelnames = ("Composite.Combined.R", "ViewLayer.Combined.R")
    px = np.zeros((2, 2, 2), np.float32)
    px[..., 1] = 5.0
    out = oiio.ImageOutput.create(path)
    out.open(path, spec)
    out.write_image(px)
    out.close()
    passes, meta = imageio.read_layers(path)
    assert meta["layer"] == "ViewLayer" and np.all(passes["Combined"] == 5.0)


def test_half_passes_are_stored_as_half_and_the_rest_exactly(tmp_path):
    """``half`` names the passes stored in 16-bit float (every layer's):
    they read back as the nearest half, clamped to half's range instead of
    becoming inf; every other pass reads back bit for bit."""
    rng = np.random.default_rng(1)
    result = rng.random((6, 5, 4)).astype(np.float32) * 3
    result[0, 0, 0], result[0, 1, 0] = 1e6, -1e6  # beyond half's largest finite value
    stats = (rng.random((6, 5, 3)) * 1e-7).astype(np.float32)  # would underflow in half
    path = str(tmp_path / "h.exr")
    imageio.write_multilayer(path, [("A", {"Combined": result, "M2": stats}), ("B", {"Combined": result})],
                             half={"Combined"})
    for layer in ("A", "B"):
        passes, meta = imageio.read_layers(path, layer)
        assert meta["half"] == ["Combined"]
        assert np.array_equal(passes["Combined"], imageio.as_half(result))
        assert np.isfinite(passes["Combined"]).all() and passes["Combined"][0, 0, 0] == imageio.HALF_MAX
        assert np.abs(passes["Combined"] - result)[1:].max() <= 2.0 ** -11 * np.abs(result[1:]).max()
    passes, meta = imageio.read_layers(path, "A")
    assert np.array_equal(passes["M2"], stats)
    imageio.write_layers(path, {"Combined": result}, half=False)
    assert imageio.read_layers(path)[1]["half"] == []


@pytest.mark.parametrize("codec", ["dwaa", "b44", "pxr24", "jpeg"])
def test_lossy_or_unknown_codecs_are_refused(tmp_path, codec):
    with pytest.raises(ValueError, match="not one of"):
        imageio.write_layers(str(tmp_path / "x.exr"), {"Combined": np.zeros((2, 2, 4))}, codec=codec)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("codec", ["zip", "piz", "none"])
def test_lossless_codecs_keep_every_value(tmp_path, codec):
    arr = np.random.default_rng(2).random((8, 9, 3)).astype(np.float32)
    path = str(tmp_path / f"{codec}.exr")
    imageio.write_layers(path, {"Noisy": arr}, codec=codec)
    passes, meta = imageio.read_layers(path)
    assert np.array_equal(passes["Noisy"], arr) and meta["attributes"].get("compression", codec) == codec

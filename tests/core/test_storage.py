import json
import os
import pickle

import numpy as np
import pytest

from core import storage
from core.buffers import Buffers


def _buffers(h=5, w=7, seed=0):
    rng = np.random.default_rng(seed)
    colors = [rng.random((h, w, 3)) for _ in range(3)]
    feats = [{"albedo": rng.random((h, w, 3)), "depth": rng.random((h, w, 1)),
              "alpha": np.ones((h, w, 1))} for _ in range(3)]
    return Buffers.from_subsets(colors, [1, 2, 1], feats)


def _same_buffers(a, b):
    for x, y in ((a.n, b.n), (a.k, b.k), (a.color.mean, b.color.mean), (a.color.m2, b.color.m2)):
        np.testing.assert_array_equal(x, y)
    assert sorted(a.features) == sorted(b.features)
    for name in a.features:
        np.testing.assert_array_equal(a.features[name].mean, b.features[name].mean)
        np.testing.assert_array_equal(a.features[name].m2, b.features[name].m2)


def test_passes_round_trip_keeps_every_statistic():
    buf = _buffers()
    passes = storage.buffers_to_passes(buf, buf.color.mean, np.zeros(buf.shape))
    plain = {k: (v[0] if isinstance(v, tuple) else v) for k, v in passes.items()}
    plain = {k: (v[:, :, None] if v.ndim == 2 else v) for k, v in plain.items()}
    _same_buffers(buf, storage.buffers_from_passes(plain, "x.exr"))


def test_plain_blender_render_reads_as_one_group_without_variance():
    h, w = 3, 4
    passes = {"Combined": np.full((h, w, 4), 0.5), "Denoising Normal": np.zeros((h, w, 3))}
    b = storage.buffers_from_passes(passes, "x.exr")
    assert np.all(b.k == 1) and not b.has_variance.any()
    assert set(b.features) == {"normal", "alpha"}


def test_missing_and_missized_passes_name_the_problem():
    with pytest.raises(storage.StorageError, match="no Combined or Noisy"):
        storage.buffers_from_passes({"Foo": np.zeros((2, 2, 3))}, "x.exr")
    bad = {"Combined": np.zeros((2, 2, 4)), "Denoising Albedo": np.zeros((3, 2, 3))}
    with pytest.raises(storage.StorageError, match="Denoising Albedo is 2x3"):
        storage.buffers_from_passes(bad, "x.exr")


def test_checkpoint_round_trip_restores_buffers_arrays_and_state(tmp_path):
    buf = _buffers()
    rng = np.random.default_rng(42)
    rng.random(5)  # advance: the restored generator must continue from here
    state = {"seed": 3, "itr": np.int64(2), "shape": (5, 7), "prob": np.linspace(0, 1, 35).reshape(5, 7),
             "none": None, "rng": rng, "nested": {"chosen": [1, 2, (3, 4.5)], "flag": True},
             "mt": np.random.Generator(np.random.MT19937(1))}
    path = str(tmp_path / "c.npz")
    storage.save_checkpoint(path, buf, {"next_index": np.arange(35).reshape(5, 7)}, {"iteration": 2}, state)
    b, arrays, meta, got = storage.load_checkpoint(path)
    _same_buffers(buf, b)
    np.testing.assert_array_equal(arrays["next_index"], np.arange(35).reshape(5, 7))
    assert meta["iteration"] == 2 and meta["version"] == storage.CHECKPOINT_VERSION
    assert got["seed"] == 3 and got["itr"] == 2 and got["shape"] == (5, 7) and got["none"] is None
    assert got["nested"] == {"chosen": [1, 2, (3, 4.5)], "flag": True}
    np.testing.assert_array_equal(got["prob"], state["prob"])
    np.testing.assert_array_equal(got["rng"].random(8), rng.random(8))
    np.testing.assert_array_equal(got["mt"].random(4), state["mt"].random(4))


def test_checkpoint_with_a_pickled_payload_is_refused_without_loading_it(tmp_path):
    class Boom:
        def __reduce__(self):
            return (exec, ("raise SystemExit('pickle ran')",))

    path = str(tmp_path / "evil.npz")
    storage.save_checkpoint(path, _buffers(), {}, {}, {})
    data = dict(np.load(path))
    data["method_state"] = np.frombuffer(pickle.dumps(Boom()), np.uint8)
    np.savez(path, **data)
    with pytest.raises(storage.StorageError, match="pickled method state; refused") as exc:
        storage.load_checkpoint(path)
    assert "\n" not in str(exc.value)


def test_old_versions_and_unreadable_files_are_refused(tmp_path):
    path = str(tmp_path / "c.npz")
    storage.save_checkpoint(path, _buffers(), {}, {}, {})
    data = dict(np.load(path))
    data["meta"] = np.frombuffer(b'{"version": 1}', np.uint8)
    np.savez(path, **data)
    with pytest.raises(storage.StorageError, match="version 1 is not"):
        storage.load_checkpoint(path)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(storage.StorageError, match="not a readable checkpoint"):
        storage.load_checkpoint(str(junk))


def test_state_that_cannot_be_stored_fails_at_save_and_leaves_no_file(tmp_path):
    path = tmp_path / "c.npz"
    with pytest.raises(TypeError, match="cannot be stored"):
        storage.save_checkpoint(str(path), _buffers(), {}, {}, {"f": lambda: 0})
    assert not path.exists() and not list(tmp_path.iterdir())


# ============================================================ compact arrays
def _packed_cases():
    rng = np.random.default_rng(7)
    h, w = 96, 80
    flat = np.repeat(np.repeat(rng.random((6, 5, 3)), 16, 0), 16, 1)  # flat albedo patches
    counts = rng.integers(0, 300, (h, w)).astype(np.float64)
    return {
        "ones": np.ones((h, w, 1)), "zeros": np.zeros((h, w, 3)), "minus_zero": np.full((h, w), -0.0),
        "nan": np.full((h, w), np.nan), "counts_u8": rng.integers(0, 200, (h, w)).astype(np.float64),
        "counts_u16": counts, "counts_u32": counts * 1000, "counts_big": counts * 2.0 ** 40,
        "counts_with_minus_zero": np.where(counts > 150, counts, -0.0), "int64": np.arange(h * w).reshape(h, w),
        "negative_int": np.arange(h * w).reshape(h, w) - 5, "halves": counts + 0.5, "flat": flat,
        "noise": rng.random((h, w, 3)), "noise_with_inf": np.where(counts > 290, np.inf, rng.random((h, w))),
        "bool": counts > 100, "small": rng.random((3, 4)), "float32": rng.random((h, w)).astype(np.float32),
    }


@pytest.mark.parametrize("name", sorted(_packed_cases()))
def test_packed_arrays_restore_bit_for_bit(name):
    arr = _packed_cases()[name]
    stored, enc = storage.pack_array(arr)
    back = storage.unpack_array(stored, enc)
    assert back.dtype == arr.dtype and back.shape == arr.shape
    assert back.tobytes() == arr.tobytes()  # bitwise: -0.0, NaN payloads, infinities
    assert stored.nbytes <= arr.nbytes


def test_packing_chooses_the_compact_form_the_data_allows():
    cases = _packed_cases()
    form = {k: (storage.pack_array(v)[1] or {}).get("form") for k, v in cases.items()}
    assert form["ones"] == form["zeros"] == form["minus_zero"] == form["nan"] == "constant"
    assert {form[k] for k in ("counts_u8", "counts_u16", "counts_u32", "int64")} == {"unsigned"}
    assert storage.pack_array(cases["counts_u8"])[0].dtype == np.uint8
    assert storage.pack_array(cases["counts_u16"])[0].dtype == np.uint16
    assert storage.pack_array(cases["counts_u32"])[0].dtype == np.uint32
    # not counts: too large, a -0.0 (would come back +0.0), negative, fractional, non-finite
    for k in ("counts_big", "counts_with_minus_zero", "negative_int", "halves", "noise_with_inf"):
        assert form[k] != "unsigned", k
    assert form["flat"] == "deflate" and storage.pack_array(cases["flat"])[0].nbytes < 0.1 * cases["flat"].nbytes
    assert form["noise"] is None and form["small"] is None  # noise does not compress; small is not worth it


@pytest.mark.parametrize("enc, stored, match", [
    ({"dtype": "<f8", "shape": [64, 64], "form": "deflate"}, None, "does not hold"),  # inflates past its size
    ({"dtype": "<f8", "shape": [4], "form": "deflate"}, np.frombuffer(b"junk", np.uint8), "damaged"),
    ({"dtype": "|O", "shape": [4], "form": "constant"}, np.zeros(1), "refused"),
    ({"dtype": "<f8", "shape": [4], "form": "pickle"}, np.zeros(1), "unknown array encoding"),
    ({"dtype": "<f8", "shape": [5], "form": "unsigned"}, np.zeros(4, np.uint8), "do not fill"),
    ({"dtype": "<f8", "form": "constant"}, np.zeros(1), "unreadable array encoding"),
])
def test_a_crafted_or_damaged_encoding_is_refused(enc, stored, match):
    import zlib
    if stored is None:  # a small stated shape, a large payload: never inflated beyond the shape
        stored = np.frombuffer(zlib.compress(bytes(10 ** 6)), np.uint8)
    with pytest.raises(storage.StorageError, match=match):
        storage.unpack_array(stored, enc)


def test_a_compact_checkpoint_resumes_exactly_and_is_smaller(tmp_path):
    """Counts narrowed, constants folded, flat features deflated; the buffers
    and arrays come back bit for bit, and a version-2 file (arrays as they
    were) still reads."""
    h, w = 64, 96
    rng = np.random.default_rng(3)
    flat = np.repeat(rng.random((4, 6, 3)), 16, 0).repeat(16, 1)
    colors = [rng.random((h, w, 3)) for _ in range(4)]
    feats = [{"albedo": flat, "normal": flat[..., ::-1], "alpha": np.ones((h, w, 1))} for _ in range(4)]
    buf = Buffers.from_subsets(colors, [1, 1, 2, 4], feats)
    arrays = {"next_index": np.full((h, w), 8, np.int64), "reused": np.zeros((h, w))}
    path = str(tmp_path / "c.npz")
    storage.save_checkpoint(path, buf, arrays, {"iteration": 1}, {"prob": np.linspace(0, 1, h * w)})
    b, got, meta, state = storage.load_checkpoint(path)
    _same_buffers(buf, b)
    assert all(got[k].dtype == v.dtype and got[k].tobytes() == v.tobytes() for k, v in arrays.items())
    raw = sum(a.nbytes for a in [buf.n, buf.k, buf.color.mean, buf.color.m2, *arrays.values()]
              + [x for st in buf.features.values() for x in (st.mean, st.m2)])
    noisy = buf.color.mean.nbytes + buf.color.m2.nbytes  # what does not compress
    assert os.path.getsize(path) < noisy + 0.1 * (raw - noisy)
    # version 2: the same names, every array stored as it is
    data = {k: v for k, v in np.load(path).items()}
    meta2 = dict(meta, version=2)
    meta2.pop("encoding")
    for key, enc in meta["encoding"].items():
        data[key] = storage.unpack_array(data[key], enc)
    data["meta"] = np.frombuffer(json.dumps(meta2).encode(), np.uint8)
    np.savez(path, **data)
    b2, got2, _, state2 = storage.load_checkpoint(path)
    _same_buffers(buf, b2)
    assert np.array_equal(state2["prob"], state["prob"])

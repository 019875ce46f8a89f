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

"""Buffers on disk: the output EXR's pass format and the render loop's checkpoint.

Two serialisations of the same per-pixel statistics (``core/buffers.py``):

* **passes** (:func:`buffers_to_passes`, :func:`buffers_from_passes`): the
  passes of our multilayer output EXR, ``Combined`` (result RGB + mean alpha),
  ``Noisy`` (sample mean), ``Variance`` (of the mean, 0 where unknown), ``M2``,
  ``Samples``, ``Groups``, ``Error``, ``GroupPower`` (``Buffers.gsum``, where
  kept; its exponent is the header's) and ``Feat_<name>`` / ``Feat_<name>_M2``:
  everything ``denoise`` needs to re-run any method.  A plain Blender
  multilayer render (Combined + Denoising passes) reads too, with one sample
  group (no variance known).
* **checkpoint** (:func:`save_checkpoint`, :func:`load_checkpoint`): an ``.npz``
  of plain arrays plus JSON, written atomically after every iteration.  The
  method's sampler state is stored as JSON with tagged arrays, tuples and numpy
  random generators; nothing is unpickled when a checkpoint is read, so a
  tampered file on shared storage cannot run code.  Arrays are stored compactly
  and losslessly (:func:`pack_array`: constants as one value, counts in the
  smallest unsigned integer type, compressible arrays deflated), so a resumed
  run is bit-identical to an uninterrupted one.
"""
from __future__ import annotations

import json
import zlib

import numpy as np

from . import parallel
from .buffers import Buffers, Stat
from .io import VECTOR_LETTERS, atomic_path

CHECKPOINT_VERSION = 3
#: versions :func:`load_checkpoint` reads (2: every array stored as it was)
READABLE_VERSIONS = (2, 3)

#: arrays smaller than this are stored as they are (packing would not pay)
PACK_MIN_ELEMENTS = 4096
#: an array is deflated when a sample of it compresses below this fraction
DEFLATE_BELOW = 0.5
#: bytes of the sample that decides (from the array's start, middle and end)
DEFLATE_SAMPLE = 3 * 65536
#: dtypes a packed array may restore to (numeric only: nothing else is read)
_KINDS = "biuf"

#: random generators a checkpoint may restore (numpy's own bit generators)
_BIT_GENERATORS = ("PCG64", "PCG64DXSM", "Philox", "SFC64", "MT19937")


class StorageError(ValueError):
    """A file that is not what it should be; the message names it and why."""


# ======================================================================== passes
def buffers_to_passes(buf: Buffers, image: np.ndarray, error: np.ndarray) -> dict:
    """The output EXR passes of an accumulated buffer and a result (see the
    module notes); values are arrays or ``(array, channel letters)``."""
    var = buf.variance_of_mean()
    alpha = buf.features["alpha"].mean if "alpha" in buf.features else np.ones(buf.shape + (1,))
    passes = {
        "Combined": np.concatenate([image, alpha], axis=-1),
        "Noisy": buf.color.mean,
        "Variance": np.where(np.isfinite(var), var, 0.0),
        "M2": buf.color.m2,
        "Samples": buf.n,
        "Groups": buf.k,
        "Error": error,
    }
    if buf.gsum is not None:  # the groups' sizes for the exponent (denoise calibrates alike)
        passes["GroupPower"] = buf.gsum
    for name, st in buf.features.items():
        passes[f"Feat_{name}"] = (st.mean, _letters(st.mean.shape[2]))
        passes[f"Feat_{name}_M2"] = (st.m2, _letters(st.m2.shape[2]))
    return passes


def _letters(c):
    return VECTOR_LETTERS.get(c) if c in (3, 4) else None


#: Blender pass name of each feature a plain render may carry
_BLENDER_FEATURES = {"albedo": "Denoising Albedo", "normal": "Denoising Normal",
                     "depth": "Denoising Depth", "position": "Position"}


def buffers_from_passes(passes: dict, path: str) -> Buffers:
    """Buffers from one of our output EXRs' passes, or from a plain Blender
    multilayer render (Combined + Denoising passes: one group, k = 1, so no
    variance is known).  StorageError names the missing or mis-sized pass."""
    if "Noisy" in passes and "Samples" in passes:
        return _from_output(passes, path)
    if "Samples" in passes and "Error" in passes:  # ours, written with the image passes only
        raise StorageError(f"{path}: an image-only output (--exr-contents image) holds the result, not "
                           "the samples' statistics a re-run needs; denoise a render written with "
                           "--exr-contents full")
    if "Combined" not in passes:
        raise StorageError(f"{path}: no Combined or Noisy layer "
                           f"(passes: {', '.join(sorted(passes)) or 'none'})")
    rgba = passes["Combined"]
    h, w = rgba.shape[:2]
    b = Buffers(np.ones((h, w)), np.ones((h, w)),
                Stat(rgba[:, :, :3].astype(np.float64), np.zeros((h, w, 3))))
    for fname, pname in _BLENDER_FEATURES.items():
        if pname in passes:
            arr = passes[pname].astype(np.float64)
            if arr.shape[:2] != (h, w):
                raise StorageError(f"{path}: pass {pname} is {arr.shape[1]}x{arr.shape[0]}, "
                                   f"Combined is {w}x{h}")
            b.features[fname] = Stat(arr, np.zeros_like(arr))
    if rgba.shape[2] >= 4:
        b.features["alpha"] = Stat(rgba[:, :, 3:4].astype(np.float64), np.zeros((h, w, 1)))
    return b


def _from_output(passes: dict, path: str) -> Buffers:
    shape = passes["Noisy"].shape[:2]
    for name, arr in passes.items():
        if arr.shape[:2] != shape:
            raise StorageError(f"{path}: pass {name} is {arr.shape[1]}x{arr.shape[0]}, "
                               f"Noisy is {shape[1]}x{shape[0]}")
    miss = [n for n in ("M2", "Groups") if n not in passes]
    if miss:
        raise StorageError(f"{path}: missing pass {miss[0]} (not a complete cycles-adaptive output)")
    b = Buffers(passes["Samples"][:, :, 0].astype(np.float64),
                passes["Groups"][:, :, 0].astype(np.float64),
                Stat(passes["Noisy"][:, :, :3].astype(np.float64),
                     passes["M2"][:, :, :3].astype(np.float64)))
    if "GroupPower" in passes:  # valid with the exponent it was kept for (the caller sets both)
        b.gsum = passes["GroupPower"][:, :, 0].astype(np.float64)
    for name in passes:
        if name.startswith("Feat_") and not name.endswith("_M2"):
            m2 = passes.get(name + "_M2", np.zeros_like(passes[name]))
            b.features[name[len("Feat_"):]] = Stat(passes[name].astype(np.float64), m2.astype(np.float64))
    return b


# ==================================================================== checkpoint
def save_checkpoint(path: str, buf: Buffers, arrays: dict, meta: dict, state: dict) -> None:
    """Write ``buf``, extra ``arrays`` (name -> ndarray), JSON ``meta`` and the
    sampler ``state`` to ``path`` (.npz) atomically."""
    out = {"n": buf.n, "k": buf.k, "color_mean": buf.color.mean, "color_m2": buf.color.m2}
    for name, st in buf.features.items():
        out[f"feat_mean__{name}"] = st.mean
        out[f"feat_m2__{name}"] = st.m2
    for name, arr in arrays.items():
        out[f"array__{name}"] = np.asarray(arr)
    state_json = _encode(state, out, "state")
    keys = list(out)
    packed = parallel.map_ordered(lambda k: pack_array(out[k]), keys)
    stored, encoding = {}, {}
    for key, (arr, enc) in zip(keys, packed):
        stored[key] = arr
        if enc is not None:
            encoding[key] = enc
    meta = dict(meta, version=CHECKPOINT_VERSION, encoding=encoding)
    stored["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    stored["state"] = np.frombuffer(json.dumps(state_json).encode(), np.uint8)
    with atomic_path(path, ".npz") as tmp:
        np.savez(tmp, **stored)


def pack_array(arr: np.ndarray):
    """``(stored, encoding)``: a lossless compact form of ``arr`` for the
    checkpoint, and the JSON that :func:`unpack_array` restores it from (None:
    stored as it is).  In order: a constant array (bitwise) is one element; a
    non-negative integer-valued array (counts: samples, groups, next offsets;
    no -0.0) is the smallest unsigned type that holds it; an array whose
    sample (start, middle, end) deflates below ``DEFLATE_BELOW`` is deflated
    whole (zlib level 1: flat albedo, normals, alpha; noisy colour does not
    compress and is not tried in full).  Arrays under ``PACK_MIN_ELEMENTS``
    and non-numeric ones stay as they are."""
    arr = np.asarray(arr)
    if arr.dtype.kind not in _KINDS or arr.size < PACK_MIN_ELEMENTS:
        return arr, None
    arr = np.ascontiguousarray(arr)
    enc = {"dtype": arr.dtype.str, "shape": list(arr.shape)}
    flat = arr.reshape(-1)
    bits = flat.view(np.dtype(f"u{arr.dtype.itemsize}")) if arr.dtype.kind != "b" else flat
    if np.all(bits == bits[0]):
        return flat[:1].copy(), dict(enc, form="constant")
    if arr.dtype.kind in "iuf":
        lo, hi = (flat.min(), flat.max()) if arr.dtype.kind != "f" or np.isfinite(flat).all() else (-1, -1)
        if lo >= 0 and hi < 2 ** 32 and (arr.dtype.kind != "f" or (np.array_equal(flat, np.floor(flat))
                                                                    and not np.signbit(flat).any())):
            small = next(t for t in (np.uint8, np.uint16, np.uint32) if hi <= np.iinfo(t).max)
            if np.dtype(small).itemsize < arr.dtype.itemsize:
                return arr.astype(small), dict(enc, form="unsigned")
    raw = memoryview(flat.view(np.uint8))
    n = len(raw)
    if n > DEFLATE_SAMPLE:
        third = DEFLATE_SAMPLE // 3
        sample = b"".join(bytes(raw[i:i + third]) for i in (0, (n - third) // 2, n - third))
    else:
        sample = bytes(raw)
    if len(zlib.compress(sample, 1)) >= DEFLATE_BELOW * len(sample):
        return arr, None
    return np.frombuffer(zlib.compress(raw, 1), np.uint8), dict(enc, form="deflate")


def unpack_array(stored: np.ndarray, enc: dict | None) -> np.ndarray:
    """The array :func:`pack_array` packed (a new array).  StorageError for
    an encoding it does not know, a non-numeric dtype, or data that does not
    fill the stated shape (a damaged or crafted file: nothing is trusted, a
    deflated array never inflates past its stated size)."""
    if enc is None:
        return stored.copy()
    try:
        dtype = np.dtype(enc["dtype"])
        shape = tuple(int(v) for v in enc["shape"])
        form = enc["form"]
    except (KeyError, TypeError, ValueError) as exc:
        raise StorageError(f"unreadable array encoding {enc!r} ({exc})") from None
    if dtype.kind not in _KINDS or any(v < 0 for v in shape):
        raise StorageError(f"array encoding with dtype {dtype} and shape {shape} refused")
    count = int(np.prod(shape, dtype=np.int64))
    if form == "constant":
        if stored.size != 1:
            raise StorageError("a constant array must store one value")
        return np.full(shape, stored.reshape(-1)[0].astype(dtype), dtype)
    if form == "unsigned":
        if stored.dtype.kind != "u" or stored.size != count:
            raise StorageError(f"packed counts do not fill {shape}")
        return stored.reshape(shape).astype(dtype)
    if form == "deflate":
        size = count * dtype.itemsize
        try:
            d = zlib.decompressobj()
            raw = d.decompress(stored.tobytes(), size + 1)
        except zlib.error as exc:
            raise StorageError(f"deflated array is damaged ({exc})") from None
        if len(raw) != size or d.unconsumed_tail:
            raise StorageError(f"deflated array does not hold {shape} {dtype}")
        return np.frombuffer(raw, dtype).reshape(shape).copy()
    raise StorageError(f"unknown array encoding {form!r}")


def load_checkpoint(path: str):
    """(Buffers, arrays dict, meta dict, state dict) of a checkpoint written by
    :func:`save_checkpoint`.  StorageError for anything else: an unreadable
    file, another version, or a pickled payload (refused, never loaded)."""
    try:
        data = np.load(path, allow_pickle=False)
        files = set(data.files)
        meta = json.loads(bytes(data["meta"]).decode())
    except Exception as exc:
        raise StorageError(f"{path}: not a readable checkpoint ({exc})") from None
    if "method_state" in files:
        raise StorageError(f"{path}: the checkpoint holds a pickled method state; refused (a "
                           "checkpoint is read as plain arrays and JSON only, it never runs code)")
    if meta.get("version") not in READABLE_VERSIONS:
        raise StorageError(f"{path}: checkpoint version {meta.get('version')} is not "
                           f"{' or '.join(map(str, READABLE_VERSIONS))}")
    try:
        encoding = meta.get("encoding") or {}
        if not isinstance(encoding, dict):
            raise StorageError("its array encodings are not a mapping")
        data = _Unpacked(data, encoding)
        b = Buffers(data["n"], data["k"], Stat(data["color_mean"], data["color_m2"]))
        for key in sorted(files):
            if key.startswith("feat_mean__"):
                name = key[len("feat_mean__"):]
                b.features[name] = Stat(data[key], data["feat_m2__" + name])
        arrays = {k[len("array__"):]: data[k] for k in files if k.startswith("array__")}
        state = _decode(json.loads(bytes(data["state"]).decode()), data)
    except StorageError as exc:  # raised by the decoding below, which does not know the path
        raise StorageError(f"{path}: damaged checkpoint ({exc})") from None
    except Exception as exc:
        raise StorageError(f"{path}: damaged checkpoint ({type(exc).__name__}: {exc})") from None
    return b, arrays, meta, state


class _Unpacked:
    """``data[key]``: a new, unpacked copy of the checkpoint's array ``key``."""

    def __init__(self, data, encoding: dict):
        self.data, self.encoding = data, encoding

    def __getitem__(self, key):
        return unpack_array(self.data[key], self.encoding.get(key))


def _encode(value, arrays: dict, key: str):
    """JSON form of a sampler state value; arrays go to ``arrays`` under
    ``key`` and are referenced by name."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.ndarray):
        arrays[key] = value
        return {"__array__": key}
    if isinstance(value, np.random.Generator):
        name = type(value.bit_generator).__name__
        if name not in _BIT_GENERATORS:
            raise TypeError(f"sampler state {key}: random generator {name} cannot be stored")
        return {"__generator__": name, "state": _encode(value.bit_generator.state, arrays, key + ".g")}
    if isinstance(value, tuple):
        return {"__tuple__": [_encode(v, arrays, f"{key}.{i}") for i, v in enumerate(value)]}
    if isinstance(value, list):
        return [_encode(v, arrays, f"{key}.{i}") for i, v in enumerate(value)]
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise TypeError(f"sampler state {key}: dict keys must be strings")
        return {"__dict__": {k: _encode(v, arrays, f"{key}.{k}") for k, v in value.items()}}
    raise TypeError(f"sampler state {key}: a {type(value).__name__} cannot be stored in a checkpoint")


def _decode(obj, data):
    if isinstance(obj, list):
        return [_decode(v, data) for v in obj]
    if not isinstance(obj, dict):
        return obj
    if "__array__" in obj:
        return data[obj["__array__"]]
    if "__tuple__" in obj:
        return tuple(_decode(v, data) for v in obj["__tuple__"])
    if "__dict__" in obj:
        return {k: _decode(v, data) for k, v in obj["__dict__"].items()}
    if "__generator__" in obj:
        name = obj["__generator__"]
        if name not in _BIT_GENERATORS:
            raise StorageError(f"checkpoint names an unknown random generator {name!r}")
        bg = getattr(np.random, name)()
        bg.state = _decode(obj["state"], data)
        return np.random.Generator(bg)
    raise StorageError(f"checkpoint state holds an untagged object {sorted(obj)[:3]}")

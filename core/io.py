"""Image files through OpenImageIO: multilayer EXR in and out, atomic writes.

No bpy here.  Channel names follow Blender's multilayer convention
``<view layer>.<pass>.<channel>`` (e.g. ``ViewLayer.Combined.R``); a plain EXR
(``R, G, B[, A]``) reads as the single pass ``""``.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile

import numpy as np

try:  # OpenImageIO is a hard dependency, but fail with a clear message.
    import OpenImageIO as oiio
except ImportError as exc:  # pragma: no cover - exercised only on broken installs
    raise ImportError("OpenImageIO is missing: install the extension zip built for this platform "
                      "(docs/install.md), or pip install OpenImageIO for the command line") from exc


class ImageFileError(Exception):
    """A file that cannot be read or written as asked; the message says why."""


CHANNEL_LETTERS = {1: ("V",), 2: ("X", "Y"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
VECTOR_LETTERS = {3: ("X", "Y", "Z"), 4: ("X", "Y", "Z", "W")}


#: the file's layers in their intended order (EXR sorts channels by name)
LAYERS_ATTRIBUTE = "cycles_adaptive/layers"
#: the layer Blender (and our outputs) keep the composited image in
COMPOSITE_LAYER = "Composite"


def read_layers(path: str, layer: str | None = None) -> tuple[dict, dict]:
    """Read the channels of one layer of an EXR (or any OIIO-readable image).

    Returns ``(passes, meta)``: ``passes`` maps pass name (view-layer prefix
    removed; ``""`` for un-prefixed channels) to an (H, W, C) float32 array with
    channels in file order; ``meta`` holds ``width``, ``height``, ``layer``
    (the view-layer name, or ``""``), ``layers`` (every layer of the file, in
    file order), ``channels`` per pass, ``half`` (the passes stored in half
    float) and the file's string attributes.
    ``layer``: which layer (ImageFileError when absent); default the first
    one as :func:`write_multilayer` ordered them (its ``LAYERS_ATTRIBUTE``;
    EXR itself sorts channels by name), else the first other than Blender's
    ``Composite``, so a file with several layers reads as one, never as a mix.
    """
    if not os.path.isfile(path):
        raise ImageFileError(f"{path}: no such file")
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ImageFileError(f"{path}: cannot open as an image ({_oiio_error()})")
    # Every part of a multi-part EXR: Blender 5.0 writes multilayer EXRs as one
    # part per pass unless ``use_exr_interleave`` is set (reading part 0 alone
    # gives only Combined).
    planes, where, names, attrs, halves = [], [], [], {}, set()
    size = None
    try:
        sub = 0
        while inp.seek_subimage(sub, 0):
            spec = inp.spec()
            if size is None:
                size = (spec.height, spec.width)
            elif (spec.height, spec.width) != size:
                raise ImageFileError(f"{path}: part {sub} is {spec.width}x{spec.height}, part 0 is "
                                     f"{size[1]}x{size[0]}")
            px = inp.read_image(sub, 0, 0, spec.nchannels, "float")
            if px is None:
                raise ImageFileError(f"{path}: unreadable pixel data, the file is truncated or "
                                     f"corrupt ({_oiio_error(inp)})")
            px = np.asarray(px, np.float32).reshape(spec.height, spec.width, spec.nchannels)
            planes.append(px)
            formats = list(spec.channelformats) or [spec.format] * spec.nchannels
            for c, name in enumerate(spec.channelnames):
                where.append((sub, c))
                names.append(name)
                if str(formats[c]) == "half":
                    halves.add(name)
            for a in spec.extra_attribs:
                if isinstance(a.value, str):
                    attrs.setdefault(a.name, a.value)
            sub += 1
    finally:
        inp.close()
    if not names:
        raise ImageFileError(f"{path}: no image data")
    spec_w, spec_h = size[1], size[0]
    groups: dict = {}
    layers = list(dict.fromkeys(n.split(".")[0] for n in names if n.count(".") >= 2))
    try:
        order = [x for x in json.loads(attrs.get(LAYERS_ATTRIBUTE, "[]")) if x in layers]
    except (ValueError, TypeError):
        order = []
    layers = order + sorted((x for x in layers if x not in order), key=lambda x: x == COMPOSITE_LAYER)
    if layer is not None and layer not in layers:
        raise ImageFileError(f"{path}: no layer {layer!r} (layers: {', '.join(layers) or 'none'})")
    layer = layer if layer is not None else (layers[0] if layers else "")
    for i, name in enumerate(names):
        parts = name.split(".")
        if len(parts) >= 3:
            if parts[0] != layer:
                continue
            pname, ch = ".".join(parts[1:-1]), parts[-1]
        elif len(parts) == 2:
            pname, ch = parts
        else:
            pname, ch = "", parts[0]
        groups.setdefault(pname, []).append((i, ch))
    passes = {k: _gather(planes, [where[i] for i, _ in v]) for k, v in groups.items()}
    half = sorted(k for k, v in groups.items() if any(names[i] in halves for i, _ in v))
    meta = {"width": spec_w, "height": spec_h, "layer": layer, "layers": layers,
            "channels": {k: [c for _, c in v] for k, v in groups.items()}, "attributes": attrs,
            "half": half}
    return passes, meta


def _gather(parts, where) -> np.ndarray:
    """(H, W, C) float32 copy of the channels ``where`` [(part, channel)]:
    one fancy-index copy when they share a part (every pass in Blender's
    files), else channel by channel."""
    if len({p for p, _ in where}) == 1:
        return parts[where[0][0]][:, :, [c for _, c in where]]
    return np.stack([parts[p][:, :, c] for p, c in where], axis=-1)


def read_rgb(path: str) -> np.ndarray:
    """(H, W, 3) float64 image of a reference: the Combined pass of a multilayer
    EXR, else the R, G, B channels of a plain image."""
    passes, meta = read_layers(path)
    for key in ("Combined", ""):
        if key in passes and passes[key].shape[2] >= 3:
            return passes[key][:, :, :3].astype(np.float64)
    raise ImageFileError(f"{path}: no Combined layer and no R, G, B channels "
                         f"(passes: {sorted(passes)})")


#: EXR codecs that keep every value (the others quantise: PXR24 floats to 24
#: bits, B44 and DWA halves and colour channels)
LOSSLESS_CODECS = ("zip", "zips", "piz", "rle", "none")
#: how an output EXR may store its result passes: as the scene's output
#: settings say, or half or full float for every render
EXR_DEPTHS = ("scene", "half", "full")
#: which passes an output EXR keeps: every statistic a re-run needs, or the image
#: passes only (result, error, samples per pixel, feature means)
EXR_CONTENTS = ("full", "image")
#: the largest finite half float
HALF_MAX = 65504.0


def as_half(arr) -> np.ndarray:
    """``arr`` (float32) as a half-float EXR channel stores it: clamped to
    +-``HALF_MAX``, rounded to the nearest half."""
    arr = np.clip(np.asarray(arr, np.float32), -HALF_MAX, HALF_MAX)
    return arr.astype(np.float16).astype(np.float32)


def write_layers(path: str, passes: dict, layer: str = "ViewLayer", attributes: dict | None = None,
                 half=False, codec: str = "zip") -> None:
    """Write a multilayer EXR atomically (temporary file in the same folder, then
    rename).  ``passes`` maps pass name to (H, W) or (H, W, C) arrays, or to
    ``(array, channel_letters)`` to choose channel names."""
    write_multilayer(path, [(layer, passes)], attributes, half, codec)


def write_multilayer(path: str, layers, attributes: dict | None = None, half=False,
                     codec: str = "zip") -> None:
    """:func:`write_layers` for several layers: ``layers`` is a sequence of
    ``(layer name, passes)``, written in that order (readers take the first
    as the file's own, :func:`read_layers`).  All passes share one size.
    ``half``: True writes every channel as half float, a collection of pass
    names only those passes (any layer), False none; ``codec``: one of
    ``LOSSLESS_CODECS`` (ValueError otherwise)."""
    if codec not in LOSSLESS_CODECS:
        raise ValueError(f"EXR codec {codec!r} is not one of {', '.join(LOSSLESS_CODECS)}")
    layers = list(layers)
    arrays, names, formats = [], [], []
    shape = None
    for layer, pname, value in [(ly, k, v) for ly, passes in layers for k, v in passes.items()]:
        arr, letters = value if isinstance(value, tuple) else (value, None)
        arr = np.asarray(arr, np.float32)
        if arr.ndim == 2:
            arr = arr[:, :, None]
        if shape is None:
            shape = arr.shape[:2]
        elif arr.shape[:2] != shape:
            raise ValueError(f"pass {pname!r} is {arr.shape[:2]}, others {shape}")
        letters = letters or CHANNEL_LETTERS.get(arr.shape[2]) or tuple(str(i) for i in range(arr.shape[2]))
        in_half = half is True or (not isinstance(half, bool) and pname in half)
        if in_half:  # beyond half's largest finite value a value would become inf
            arr = as_half(arr)
        for c, letter in enumerate(letters):
            names.append(f"{layer}.{pname}.{letter}" if layer else f"{pname}.{letter}")
            arrays.append(arr[:, :, c])
            formats.append("half" if in_half else "float")
    if len(set(names)) != len(names):
        raise ValueError("two channels share a name (a layer given twice?)")
    attributes = dict(attributes or {})
    attributes[LAYERS_ATTRIBUTE] = json.dumps([name for name, _ in layers])
    data = np.ascontiguousarray(np.stack(arrays, axis=-1))
    spec = oiio.ImageSpec(shape[1], shape[0], len(names), "half" if half is True else "float")
    spec.channelnames = names
    if len(set(formats)) > 1:
        spec.channelformats = [oiio.TypeDesc(f) for f in formats]
    spec.attribute("compression", codec)
    for k, v in (attributes or {}).items():
        spec.attribute(k, str(v))
    _atomic_write(path, spec, data)


def check_writable(path: str, overwrite: bool) -> None:
    """Raise ImageFileError unless ``path`` can be created (or replaced when
    ``overwrite``): existing file, missing or unwritable folder."""
    folder = os.path.dirname(os.path.abspath(path)) or "."
    if os.path.exists(path) and not overwrite:
        raise ImageFileError(f"{path} exists; pass --overwrite to replace it")
    if os.path.isdir(path):
        raise ImageFileError(f"{path} is a folder, not a file")
    if not os.path.isdir(folder):
        raise ImageFileError(f"{folder}: output folder does not exist")
    if not os.access(folder, os.W_OK):
        raise ImageFileError(f"{folder}: output folder is not writable")


def temp_beside(path: str, suffix: str) -> str:
    """A new temporary file in ``path``'s folder (for write-then-rename), with
    the permissions a plain ``open(path, 'w')`` would give (mkstemp's are 0600)."""
    folder = os.path.dirname(os.path.abspath(path)) or "."
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=suffix, dir=folder)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    return tmp


@contextlib.contextmanager
def atomic_path(path: str, suffix: str | None = None):
    """Write-then-rename: yields a temporary path in ``path``'s folder; when the
    block ends normally it replaces ``path``, otherwise it is removed, so a
    reader never sees a half-written file.  ``suffix`` defaults to ``path``'s
    extension (writers that pick the format from the name need it)."""
    tmp = temp_beside(path, os.path.splitext(path)[1] if suffix is None else suffix)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_text(path: str, text: str) -> None:
    """Write a text file atomically (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)


def file_sha256(path: str) -> str:
    """SHA-256 of a file's bytes (hex), read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_reference(path: str, shape=None) -> np.ndarray:
    """(H, W, 3) float64 reference image (:func:`read_rgb`) checked against the
    render's ``shape`` (H, W); ImageFileError names both sizes on a mismatch."""
    ref = read_rgb(path)
    if shape is not None and ref.shape[:2] != tuple(shape):
        raise ImageFileError(f"reference {path} is {ref.shape[1]}x{ref.shape[0]}, the render is "
                             f"{shape[1]}x{shape[0]}")
    return ref


def _atomic_write(path: str, spec, data) -> None:
    with atomic_path(path, os.path.splitext(path)[1] or ".exr") as tmp:
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise ImageFileError(f"{path}: no writer for this format ({_oiio_error()})")
        if not out.open(tmp, spec):
            raise ImageFileError(f"{path}: cannot write ({out.geterror()})")
        ok = out.write_image(data)
        out.close()
        if not ok:
            raise ImageFileError(f"{path}: write failed ({out.geterror()})")


def _oiio_error(obj=None) -> str:
    msg = ""
    try:
        msg = obj.geterror() if obj is not None else oiio.geterror()
    except Exception:
        pass
    return (msg or "unknown error").strip().splitlines()[0] if msg else "unknown error"

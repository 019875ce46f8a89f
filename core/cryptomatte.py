"""Cryptomatte ranks merged across region renders (pure numpy, no bpy).

What: a per-pixel accumulator of up to ``capacity`` ranked (id, weighted
coverage) pairs.  Why: a Cryptomatte pixel is not a mean of samples but a
ranked list of (MurmurHash3 id, coverage) pairs, so it cannot go through the
feature-mean accumulators.  A render of ``n`` samples whose rank ``k`` at a
pixel is ``(id_k, c_k)`` adds ``n * c_k`` to that id's weighted coverage; the
output coverage of an id is ``sum_r n_r c_{r,id} / sum_r n_r`` (the fraction
of all merged samples covered by that id), i.e. the coverage one render of
``sum_r n_r`` samples would report, up to the per-render truncation to its
top ``levels`` ranks.

Facts measured with bpy 4.5, 4.2 and 5.0 (32x32 scene, plane / sphere /
cube, depth 4, border renders of 8 spp at offsets 0 and 8, 16 spp at 0):

- switches: ``view_layer.use_pass_cryptomatte_object`` / ``_material`` /
  ``_asset``; ``view_layer.pass_cryptomatte_depth`` is the number of ranks
  (levels), written as ``ceil(levels / 2)`` RGBA layers of 2 ranks each.
- names (all three versions alike): multilayer-EXR layers
  ``<ViewLayer>.CryptoObject00``, ``01``, ... (``CryptoMaterial``,
  ``CryptoAsset``), channels in lower case ``r, g, b, a`` = id0, cov0, id1,
  cov1; ids are float32 bit patterns of uint32 MurmurHash3 hashes.  The
  header carries ``cryptomatte/<key>/name`` (``ViewLayer.CryptoObject``),
  ``hash`` (``MurmurHash3_32``), ``conversion`` (``uint32_to_float32``) and
  ``manifest`` (JSON name -> 8 hex digits); ``<key>`` is the first 7 hex
  digits of the MurmurHash3 of the name (``542cafa``; :func:`header_key`).
- a border render with ``sample_offset > 0`` writes them (unlike Position /
  IndexOB), and a render's coverages are multiples of 1 / its samples (8 spp:
  k/8; 16 spp: k/16), summing to at most 1: the fraction of that render's
  samples, so renders merge weighted by their sample counts.

Ids are compared by their 32-bit pattern (a float id is viewed, not
converted).  A rank whose coverage is not finite or not > 0 is empty (id 0,
coverage 0 on output); an id whose pattern is 0 with coverage > 0 is kept.
Ties in coverage are broken by the smaller id pattern, so the result does
not depend on the rank order of the input.
"""
from __future__ import annotations

import numpy as np


def as_id_bits(ids) -> np.ndarray:
    """uint32 bit patterns of ``ids`` (float32 Cryptomatte ids are viewed,
    integer ids are taken modulo 2**32)."""
    a = np.asarray(ids)
    if a.dtype == np.float32:
        return a.view(np.uint32)
    if a.dtype.kind == "f":
        return a.astype(np.float32).view(np.uint32)
    return a.astype(np.uint64).astype(np.uint32) if a.dtype.kind == "i" else a.astype(np.uint32)


def _reduce(ids: np.ndarray, cov: np.ndarray, keep: int):
    """Per row of ``(P, K)`` candidates: sum the coverage of equal ids and
    keep the ``keep`` largest (ties: smaller id first); empty slots are
    (0, 0).  Returns ``(ids (P, keep) uint32, cov (P, keep) float64)``."""
    p, k = ids.shape
    cov = np.where(np.isfinite(cov) & (cov > 0), cov, 0.0)
    ids = np.where(cov > 0, ids, np.uint32(0))
    # group equal ids (sorted by id; empty candidates get a key past every id)
    empty = cov <= 0
    key = np.where(empty, np.uint64(1) << np.uint64(32), ids.astype(np.uint64))
    order = np.argsort(key, axis=1, kind="stable")
    sid = np.take_along_axis(key, order, axis=1)
    scov = np.take_along_axis(cov, order, axis=1)
    start = np.ones((p, k), bool)
    if k > 1:
        start[:, 1:] = sid[:, 1:] != sid[:, :-1]
    group = np.cumsum(start, axis=1) - 1
    label = (np.arange(p)[:, None] * k + group).ravel()
    gcov = np.bincount(label, weights=scov.ravel(), minlength=p * k).reshape(p, k)
    gid = np.zeros(p * k, np.uint64)
    gid[label[start.ravel()]] = sid.ravel()[start.ravel()]
    gid = gid.reshape(p, k)
    valid = (gid < (np.uint64(1) << np.uint64(32))) & (gcov > 0)
    gid = np.where(valid, gid, np.uint64(0))
    gcov = np.where(valid, gcov, 0.0)
    # rank: coverage descending, then id ascending; empty slots last
    rank_key_id = np.where(valid, gid, np.uint64(1) << np.uint64(32))
    idx = np.lexsort((rank_key_id, -gcov, ~valid), axis=-1)
    idx = idx[:, :keep]
    out_id = np.take_along_axis(gid, idx, axis=1).astype(np.uint32)
    out_cov = np.take_along_axis(gcov, idx, axis=1)
    if keep > k:  # fewer candidates than slots: pad with empty ranks
        out_id = np.concatenate([out_id, np.zeros((p, keep - k), np.uint32)], axis=1)
        out_cov = np.concatenate([out_cov, np.zeros((p, keep - k))], axis=1)
    return out_id, out_cov


class CryptoAccumulator:
    """Ranked (id, weighted coverage) pairs per pixel for one Cryptomatte
    layer set (e.g. ``CryptoObject``), merged render by render.

    State is plain arrays (checkpoint-friendly, see :meth:`state`):
    ``ids`` (H, W, capacity) uint32, ``wcov`` (H, W, capacity) float64 (sum
    of samples x coverage), ``weight`` (H, W) float64 (samples merged)."""

    def __init__(self, height: int, width: int, capacity: int):
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.ids = np.zeros((height, width, capacity), np.uint32)
        self.wcov = np.zeros((height, width, capacity), np.float64)
        self.weight = np.zeros((height, width), np.float64)

    @property
    def capacity(self) -> int:
        return self.ids.shape[2]

    def merge(self, ids, coverage, samples: float, region=None) -> None:
        """Merge one render's ranks ``ids``/``coverage`` (h, w, L) over
        ``region = (x0, y0, x1, y1)`` (whole image when None) with weight
        ``samples``: weighted coverages of equal ids add, the top
        ``capacity`` by coverage stay (ties: smaller id)."""
        h, w, _ = self.ids.shape
        x0, y0, x1, y1 = region if region is not None else (0, 0, w, h)
        bits = as_id_bits(ids)
        cov = np.asarray(coverage, np.float64)
        if bits.shape != cov.shape or bits.shape[:2] != (y1 - y0, x1 - x0):
            raise ValueError(f"ranks {bits.shape}/{cov.shape} do not fit region {region}")
        n = float(samples)
        if not np.isfinite(n) or n <= 0:
            return
        sl = (slice(y0, y1), slice(x0, x1))
        c = self.capacity
        cand_id = np.concatenate([self.ids[sl], bits], axis=2).reshape(-1, c + bits.shape[2])
        cov = np.where(np.isfinite(cov) & (cov > 0), cov, 0.0) * n
        cand_cov = np.concatenate([self.wcov[sl], cov], axis=2).reshape(-1, c + bits.shape[2])
        out_id, out_cov = _reduce(cand_id, cand_cov, c)
        self.ids[sl] = out_id.reshape(y1 - y0, x1 - x0, c)
        self.wcov[sl] = out_cov.reshape(y1 - y0, x1 - x0, c)
        self.weight[sl] += n

    def ranks(self, levels: int | None = None):
        """``(ids uint32 (H, W, levels), coverage float64 (H, W, levels))``:
        the top ``levels`` ranks with coverage = weighted coverage / samples
        merged (0 where nothing was merged; empty ranks are (0, 0))."""
        levels = self.capacity if levels is None else int(levels)
        k = min(levels, self.capacity)
        wt = self.weight[:, :, None]
        cov = np.divide(self.wcov[:, :, :k], wt, out=np.zeros_like(self.wcov[:, :, :k]), where=wt > 0)
        ids = np.where(cov > 0, self.ids[:, :, :k], np.uint32(0))
        if levels > k:
            pad = (self.ids.shape[0], self.ids.shape[1], levels - k)
            ids = np.concatenate([ids, np.zeros(pad, np.uint32)], axis=2)
            cov = np.concatenate([cov, np.zeros(pad)], axis=2)
        return ids, cov

    def layers(self, levels: int | None = None) -> list[np.ndarray]:
        """The ranks as Blender writes them: ``ceil(levels / 2)`` float32
        (H, W, 4) RGBA arrays, R=id0 (float32 bit pattern), G=cov0, B=id1,
        A=cov1 (layer 00, 01, ...)."""
        ids, cov = self.ranks(levels)
        lv = ids.shape[2]
        if lv % 2:
            ids = np.concatenate([ids, np.zeros(ids.shape[:2] + (1,), np.uint32)], axis=2)
            cov = np.concatenate([cov, np.zeros(cov.shape[:2] + (1,))], axis=2)
        out = []
        for j in range(0, ids.shape[2], 2):
            layer = np.empty(ids.shape[:2] + (4,), np.float32)
            layer[:, :, 0] = ids[:, :, j].view(np.float32)
            layer[:, :, 1] = cov[:, :, j]
            layer[:, :, 2] = ids[:, :, j + 1].view(np.float32)
            layer[:, :, 3] = cov[:, :, j + 1]
            out.append(layer)
        return out

    def state(self) -> dict[str, np.ndarray]:
        """Plain arrays for a checkpoint (``storage.pack_array`` each)."""
        return {"ids": self.ids, "wcov": self.wcov, "weight": self.weight}

    @classmethod
    def from_state(cls, state: dict) -> "CryptoAccumulator":
        """The accumulator :meth:`state` saved; ValueError when the arrays
        do not fit together (a damaged checkpoint)."""
        ids = np.asarray(state["ids"])
        wcov = np.asarray(state["wcov"], np.float64)
        weight = np.asarray(state["weight"], np.float64)
        if ids.ndim != 3 or wcov.shape != ids.shape or weight.shape != ids.shape[:2]:
            raise ValueError(f"cryptomatte state shapes {ids.shape}/{wcov.shape}/{weight.shape} do not fit")
        acc = cls(ids.shape[0], ids.shape[1], ids.shape[2])
        acc.ids[...] = ids.astype(np.uint32)
        acc.wcov[...] = np.where(np.isfinite(wcov) & (wcov > 0), wcov, 0.0)
        acc.weight[...] = np.where(np.isfinite(weight) & (weight > 0), weight, 0.0)
        return acc


def layers_to_ranks(layers) -> tuple[np.ndarray, np.ndarray]:
    """A render's Cryptomatte RGBA layers (00, 01, ...; each (h, w, 4)
    float32) as ``(ids uint32 (h, w, 2*len), coverage float64 (h, w, 2*len))``."""
    arrs = [np.asarray(a, np.float32) for a in layers]
    if not arrs:
        raise ValueError("no Cryptomatte layers")
    stack = np.concatenate([a[:, :, [0, 2]] for a in arrs], axis=2)
    covs = np.concatenate([a[:, :, [1, 3]] for a in arrs], axis=2)
    return np.ascontiguousarray(stack).view(np.uint32), covs.astype(np.float64)


def murmurhash3_32(data: str | bytes, seed: int = 0) -> int:
    """MurmurHash3 x86 32-bit of ``data`` (UTF-8), the hash Cryptomatte uses
    for names and for the header key (``cryptomatte/<7 hex digits>/``)."""
    key = data.encode() if isinstance(data, str) else bytes(data)
    c1, c2, m = 0xCC9E2D51, 0x1B873593, 0xFFFFFFFF
    h = seed & m
    n4 = len(key) // 4 * 4
    for i in range(0, n4, 4):
        k = int.from_bytes(key[i:i + 4], "little")
        k = (k * c1) & m
        k = ((k << 15) | (k >> 17)) & m
        h ^= (k * c2) & m
        h = ((h << 13) | (h >> 19)) & m
        h = (h * 5 + 0xE6546B64) & m
    tail = key[n4:]
    if tail:
        k = int.from_bytes(tail, "little")
        k = (k * c1) & m
        k = ((k << 15) | (k >> 17)) & m
        h ^= (k * c2) & m
    h ^= len(key)
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & m
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & m
    return h ^ (h >> 16)


def header_key(name: str) -> str:
    """The ``<key>`` of ``cryptomatte/<key>/...`` for layer set ``name``
    (e.g. ``ViewLayer.CryptoObject``): the hash's first 7 hex digits."""
    return f"{murmurhash3_32(name):08x}"[:7]

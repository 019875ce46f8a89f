"""Does OIDN denoise an image whose pixels have unequal sample counts worse
than each part alone? (developer tool, not shipped; docs/notes/oidn.md)

The left half of each frame takes the 16-spp render, the right half the 8-spp
one (the cached buffers of ``tools/rhf_study.py render``: Tabulated Sobol,
same seed, so the 16 samples include the 8, as in an adaptive run), then the
mixed image is denoised once (pyoidn, high quality, accurate prefilter).
Each half's relMSE is printed beside the same half of the 8- and the 16-spp
image denoised alone, twice: with the auxiliary albedo / normal mixed like the
colour (what the loop's merged buffers hold), and with the 8-spp auxiliaries
everywhere (the colour alone mixed).

    RHF_STUDY_CACHE=DIR .venv/bin/python tools/oidn_mixed_counts.py [--refs /work/refs_conv]
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import oidn_aux_study  # noqa: E402  (the denoise call both studies make)
import rhf_study as rs  # noqa: E402  (cache, references, package loading)

from cycles_adaptive.core import metrics  # noqa: E402

SCENES = "cornell,dof,soft_shadows,glossy,motion_blur,animated"


def denoise(color, aux_from, aux_other=None, mask=None):
    """OIDN of ``color`` with the albedo / normal of ``aux_from`` (Buffers),
    taken from ``aux_other`` where ``mask``."""
    albedo, normal = aux_from.features["albedo"].mean, aux_from.features["normal"].mean
    if aux_other is not None:
        albedo = np.where(mask[..., None], aux_other.features["albedo"].mean, albedo)
        normal = np.where(mask[..., None], aux_other.features["normal"].mean, normal)
    return oidn_aux_study.denoise(color, albedo, normal)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=SCENES)
    ap.add_argument("--refs", default=rs.REFS, help="reference folder (default %(default)s)")
    args = ap.parse_args(argv)
    rs.REFS = args.refs
    print("| scene | features | left (16 spp) in the mix | D16 alone | right (8 spp) in the mix | D8 alone |")
    print("|---|---|---:|---:|---:|---:|")
    for scene in args.scenes.split(","):
        b8, b16 = rs.load(scene, 8), rs.load(scene, 16)
        h, w = b8.n.shape
        ref = rs.reference(scene, (h, w))
        left = np.arange(w)[None, :].repeat(h, 0) < w // 2
        mixed = np.where(left[..., None], b16.color.mean, b8.color.mean)
        d8, d16 = denoise(b8.color.mean, b8), denoise(b16.color.mean, b16)
        L, R = slice(0, w // 2), slice(w // 2, w)
        err = lambda d, s: metrics.relmse(d[:, s], ref[:, s])
        for label, dm in (("mixed like the colour", denoise(mixed, b8, b16, left)),
                          ("8 spp everywhere", denoise(mixed, b8))):
            print(f"| {scene} | {label} | {err(dm, L):.3e} | {err(d16, L):.3e} | {err(dm, R):.3e} | "
                  f"{err(d8, R):.3e} |", flush=True)


if __name__ == "__main__":
    main()

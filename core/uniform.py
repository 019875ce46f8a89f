"""Uniform sampling, no reconstruction: the baseline (plain Cycles).

The loop renders the whole budget in its initial pass for this method
(``ADAPTIVE = False``), exactly what a user gets from plain Cycles at the same
sample count; ``sample_map`` still gives an even map for callers that ask.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .buffers import Buffers
from .method import MethodResult, allocate
from .variance import GUIDE_FEATURES

NAME = "uniform"
#: the guides of the calibrated variance (its error image): declared so the
#: benchmark renders what the product does
PASSES: tuple = tuple(GUIDE_FEATURES)
ADAPTIVE = False
SAMPLER_USES_RESULT = False


@dataclass
class Params:
    """Uniform sampling has no parameters."""


def reconstruct(buf: Buffers, params: Params | None = None) -> MethodResult:
    """The sample mean; error = the calibrated variance of the mean
    (:meth:`Buffers.calibrated_variance`) averaged over RGB (0 where no
    variance estimate exists)."""
    return denoise(buf.color.mean, buf.calibrated_variance())


def denoise(color, color_var, features=None, feature_var=None, n=None, params=None) -> MethodResult:
    """The sample mean of plain arrays (non-finite values -> 0); error = the
    variance of the mean averaged over RGB (0 where unknown)."""
    color = np.asarray(color, np.float64)
    var = np.broadcast_to(np.asarray(color_var, np.float64), color.shape)
    err = np.where(np.isfinite(var), var, 0.0).mean(axis=-1)
    return MethodResult(np.where(np.isfinite(color), color, 0.0), err, {})


def sample_map(buf: Buffers, result: MethodResult, budget: int, params=None, state=None) -> np.ndarray:
    """Even map: ``budget // pixels`` everywhere, the remainder spread evenly."""
    return allocate(np.ones(buf.shape), budget)

"""Shared test helpers for the pure core: a deterministic fake executor that
renders region tasks the way Cycles does (sample i of pixel p is a fixed
function of p and i), so sample subsets and border renders merge exactly."""
import numpy as np
import pytest


def sample_values(truth, ys, xs, index):
    """Value of sample ``index`` at pixels (ys, xs): truth + hashed noise."""
    h = (xs.astype(np.uint64) * np.uint64(73856093)) ^ (ys.astype(np.uint64) * np.uint64(19349663)) \
        ^ (np.uint64(index) * np.uint64(83492791) + np.uint64(12345))
    h = (h * np.uint64(2654435761)) % np.uint64(1 << 32)
    u = h.astype(np.float64) / float(1 << 32)  # in [0, 1)
    noise = (u - 0.5) * 2.0  # variance 1/3
    base = truth[ys, xs]
    return base * (1.0 + 0.8 * noise[..., None])


def flat_guides(h, w):
    """Noise-free guide passes of one flat surface facing the camera (grey
    albedo, normal +z, depth 1): what the fake renders unless given others."""
    return {"albedo": np.full((h, w, 3), 0.5), "normal": np.dstack([np.zeros((h, w, 2)), np.ones((h, w))]),
            "depth": np.ones((h, w, 1))}


class FakeExecutor:
    """Renders (x0, y0, x1, y1, samples, offset) tasks of a synthetic image.
    ``features``: name -> (H, W, C) pass values; the guides a method may read
    (albedo, normal, depth) default to :func:`flat_guides`, as a job renders
    them for every method."""

    def __init__(self, truth, features=None):
        self.truth = np.asarray(truth, np.float64)
        self.size = self.truth.shape[:2]
        self.features = dict(flat_guides(*self.size), **(features or {}))
        self.tasks = []

    def render(self, task):
        self.tasks.append(task)
        ys, xs = np.mgrid[task.y0:task.y1, task.x0:task.x1]
        acc = np.zeros((task.y1 - task.y0, task.x1 - task.x0, 3))
        for i in range(task.offset, task.offset + task.samples):
            acc += sample_values(self.truth, ys, xs, i)
        rgb = acc / task.samples
        rgba = np.concatenate([rgb, np.ones(rgb.shape[:2] + (1,))], axis=-1)
        feats = {k: v[task.y0:task.y1, task.x0:task.x1] for k, v in self.features.items()}
        return rgba, feats


@pytest.fixture
def fake_executor():
    return FakeExecutor

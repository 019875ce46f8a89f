"""LP computed in bands of rows (the farm's split of a map) gives the whole
frame's bits, and a band without enough halo rows does not."""
import numpy as np
import pytest

from core import lp


def _scene(h=420, w=64, seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / 50.0
    depth = (1 + 0.5 * np.sin(yy) + 0.3 * xx)[..., None]
    normal = np.stack([np.sin(xx), np.cos(yy), np.ones_like(xx)], -1)
    albedo = np.stack([(xx > 0.6) * 0.8 + 0.1, 0.5 + 0.2 * np.sin(3 * yy), 0.3 + 0 * xx], -1)
    truth = albedo * (0.5 + 0.5 * normal[..., :1]) + 0.2 * (((yy * 7).astype(int) % 3) == 0)[..., None]
    var = 0.01 * truth ** 2 + 1e-3
    color = truth + rng.normal(size=truth.shape) * np.sqrt(var)
    var_est = var * rng.chisquare(3, size=var.shape) / 3
    var_est[5, 7] = np.inf                      # unknown variances and missing pixels too
    color[200, 30] = np.nan
    feats = {"depth": depth + rng.normal(size=depth.shape) * 1e-3, "normal": normal, "albedo": albedo}
    fvar = {k: np.full(v.shape[:2] + (1,), 1e-6) for k, v in feats.items()}
    n = np.full((h, w), 16.0)
    n[100:110, 10:20] = 0
    return color, var_est, feats, fvar, n


FIELDS = ("image", "error", "delta_error", "radius", "centers", "center_radius", "center_rank", "center_error")


@pytest.fixture
def small_chunks(monkeypatch):
    # bands of 6 rows at this width, so the halo (120 rows) is shorter than the frame
    monkeypatch.setattr(lp, "CHUNK_PIXELS", 2048)
    assert lp.band_halo(64, lp.Params()) < 420 // 3


@pytest.mark.parametrize("parts", [1, 3])
def test_bands_give_the_whole_frame_bit_for_bit(small_chunks, parts):
    args = _scene()
    whole = lp.fit(*args, params=lp.Params())
    jobs = lp.band_jobs(*args, lp.Params(), parts)
    assert len(jobs) == parts
    assert any(j["t0"] > 0 for j in jobs) or parts == 1      # bands really start inside the frame
    banded = lp.fit_bands(*args, lp.Params(), parts, run=lambda js: [lp.fit_band(j) for j in js])
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(banded, name), getattr(whole, name), err_msg=name)
    assert banded.passes == whole.passes
    assert np.isfinite(banded.image).all() and np.isfinite(banded.error).all()


def test_too_short_a_halo_changes_the_image(small_chunks, monkeypatch):
    # the halo is what makes the bands exact: with 10 rows the bands' edges show
    args = _scene()
    whole = lp.fit(*args, params=lp.Params())
    monkeypatch.setattr(lp, "band_halo", lambda width, params: 10)
    banded = lp.fit_bands(*args, lp.Params(), 5)
    assert (banded.image != whole.image).any()


def test_the_loop_spreads_lp_maps_over_an_executors_jobs_with_the_same_bits(monkeypatch):
    # an executor with ``run_jobs`` (the farm's: here in-process, with a record
    # of what it ran) gets LP's map as bands, and the run ends with the bits of
    # a run whose map was fitted whole
    import importlib
    from conftest import FakeExecutor
    from core.pipeline import AdaptiveRun, Options
    monkeypatch.setattr(lp, "CHUNK_PIXELS", 512)          # 1-row chunk bands: a halo of 80 rows
    h, w = 200, 28
    rng = np.random.default_rng(5)
    truth = 0.3 + 0.1 * rng.random((h, w, 3))
    truth[h // 3:, w // 2:] = 4.0
    feats = {"albedo": rng.random((h, w, 3)), "normal": rng.random((h, w, 3)) * 2 - 1,
             "depth": 1 + rng.random((h, w, 1))}
    seen = []

    class Spreading(FakeExecutor):
        map_parts = 3

        def run_jobs(self, module, name, jobs, local_fallback=False):
            seen.append(([(j["t0"], j["c0"], j["c1"]) for j in jobs], local_fallback))
            fn = getattr(importlib.import_module(module), name)
            return [fn(j) for j in jobs]

    opts = dict(method="lp", spp=8, initial_spp=4, subsets=4, task_cost=16, min_task_size=2, iterations=2)
    runs = []
    for ex in (FakeExecutor(truth, feats), Spreading(truth, feats)):
        run = AdaptiveRun(ex, Options(**opts))
        for _ in run.steps():
            pass
        runs.append((run, run.reconstruct()))
    (a, ra), (b, rb) = runs
    assert seen and all(len(s) == 3 and any(t0 > 0 for t0, _, _ in s) for s, _ in seen)
    # one map before each adaptive iteration, then the final fit (which may fall back to this machine)
    assert [fallback for _, fallback in seen] == [False] * b.iteration + [True]
    for x, y in [(a.buffers.n, b.buffers.n), (a.buffers.color.mean, b.buffers.color.mean),
                 (ra.image, rb.image), (ra.error, rb.error)]:
        np.testing.assert_array_equal(x, y)
    assert a.tasks_rendered == b.tasks_rendered

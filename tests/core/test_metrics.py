import numpy as np
import pytest

from core import metrics


def test_relmse_matches_definition():
    rng = np.random.default_rng(0)
    r = rng.random((4, 5, 3))
    x = r + rng.normal(0, 0.1, r.shape)
    expect = np.mean((x - r) ** 2 / (r ** 2 + 0.01))
    assert metrics.relmse(x, r) == pytest.approx(expect, rel=1e-12)
    assert metrics.relmse(r, r) == 0.0
    assert metrics.per_pixel_relmse(x, r).mean() == pytest.approx(expect, rel=1e-12)


def test_relmse_counts_nan_as_large_error_and_rejects_shape_mismatch():
    r = np.ones((2, 2, 3))
    x = r.copy()
    x[0, 0, 0] = np.nan
    assert metrics.relmse(x, r) > 1e4
    with pytest.raises(ValueError):
        metrics.relmse(np.ones((2, 3, 3)), r)


def test_error_correlation_is_one_for_the_true_error():
    rng = np.random.default_rng(1)
    r = rng.random((8, 8, 3))
    x = r + rng.normal(0, 0.2, r.shape)
    true = ((x - r) ** 2).mean(-1)
    assert metrics.error_correlation(true, x, r) == pytest.approx(1.0)
    assert metrics.error_correlation(np.zeros((8, 8)), x, r) == 0.0

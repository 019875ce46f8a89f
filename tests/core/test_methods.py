"""The method contract (core/method.py) holds for every registered method."""
import inspect

import numpy as np
import pytest

from core import methods
from core.buffers import Buffers
from core.method import Method, MethodResult
from core.pipeline import selects

DENOISE_SIGNATURE = ["color", "color_var", "features", "feature_var", "n", "params"]


@pytest.mark.parametrize("name", list(methods.METHODS))
def test_every_method_declares_the_whole_contract(name):
    mod = methods.get(name)
    assert isinstance(mod, Method)
    for member in methods.MEMBERS:
        assert member in vars(mod), f"{name} does not declare {member} itself"
    assert mod.NAME == name
    assert isinstance(mod.ADAPTIVE, bool) and isinstance(mod.SAMPLER_USES_RESULT, bool)


@pytest.mark.parametrize("name", list(methods.METHODS))
def test_denoise_has_one_signature_and_matches_reconstruct(name):
    mod = methods.get(name)
    assert list(inspect.signature(mod.denoise).parameters) == DENOISE_SIGNATURE
    rng = np.random.default_rng(1)
    h, w = 12, 10
    feats = [{p: rng.random((h, w, 3 if p != "depth" else 1)) for p in mod.PASSES} for _ in range(4)]
    buf = Buffers.from_subsets([0.5 + 0.1 * rng.random((h, w, 3)) for _ in range(4)], [2] * 4, feats)
    if selects(mod):  # auto: no reconstruction of its own, a clear error
        with pytest.raises(ValueError, match="name a method"):
            mod.denoise(buf.color.mean, buf.variance_of_mean())
        with pytest.raises(ValueError, match="name a method"):
            mod.reconstruct(buf, mod.Params())
        return
    res = mod.denoise(buf.color.mean, buf.variance_of_mean(), {p: buf.feature(p) for p in mod.PASSES},
                      {p: buf.feature_variance(p) for p in mod.PASSES}, buf.n, mod.Params())
    assert isinstance(res, MethodResult) and res.image.shape == (h, w, 3) and res.error.shape == (h, w)
    assert np.isfinite(res.image).all() and np.isfinite(res.error).all()


def test_unknown_method_names_the_choices():
    with pytest.raises(ValueError, match="choose one of uniform"):
        methods.get("no-such-method")


@pytest.mark.parametrize("name", [m for m in methods.METHODS if m != "auto"])
def test_results_do_not_depend_on_passes_the_method_does_not_declare(name):
    """The image, its error and the sample map are the same with passes the
    method does not declare in the buffers (the product renders denoise's
    guides and --temporal's position for every method; the benchmark renders
    a method's PASSES only): whatever a method reads, the calibrated
    variance's pooling guides included, is in PASSES."""
    mod = methods.get(name)
    if name == "oidn":
        from core import oidn
        if not oidn.pyoidn_available():
            pytest.skip("pyoidn not installed")
    rng = np.random.default_rng(5)
    h, w = 24, 28
    truth = 0.2 + np.linspace(0.0, 1.5, h * w * 3).reshape(h, w, 3)
    truth[:, w // 2:] *= 3.0   # an edge for the guides and the maps
    all_feats = {"albedo": np.where(np.arange(w)[None, :, None] < w // 2, 0.3, 0.8) * np.ones((h, w, 3)),
                 "normal": np.dstack([np.zeros((h, w, 2)), np.ones((h, w))]),
                 "depth": np.linspace(1.0, 3.0, h * w).reshape(h, w, 1),
                 "position": rng.random((h, w, 3))}
    groups = [truth * (1 + 0.3 * rng.standard_normal(truth.shape)) for _ in range(4)]
    declared = {p: all_feats[p] for p in mod.PASSES if p in all_feats}
    missing = [p for p in mod.PASSES if p not in all_feats]
    assert not missing, f"the test builds no {missing}"
    plain = Buffers.from_subsets(groups, [2] * 4, [declared] * 4)
    more = Buffers.from_subsets(groups, [2] * 4, [dict(all_feats)] * 4)
    params = mod.Params()
    a, b = mod.reconstruct(plain, params), mod.reconstruct(more, params)
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.error, b.error)
    if mod.ADAPTIVE:
        np.testing.assert_array_equal(mod.sample_map(plain, a, 4 * h * w, params, {}),
                                      mod.sample_map(more, b, 4 * h * w, params, {}))

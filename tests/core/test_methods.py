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

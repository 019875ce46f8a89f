"""Registry of methods: name -> core module implementing
:class:`core.method.Method`.

A new method is one module in core/ and one line here.
"""
from __future__ import annotations

import importlib
from dataclasses import fields

from .method import Method

#: every member of the Method contract (core/method.py)
MEMBERS = ("NAME", "PASSES", "Params", "ADAPTIVE", "SAMPLER_USES_RESULT", "reconstruct", "sample_map")

METHODS = {
    "uniform": "uniform",
    "var": "var",
    "awr": "awr",
    "lp": "lp",
    "rhf": "rhf",
    "oidn": "oidn",
    "auto": "auto",
}

#: parameter groups that are not methods (frame ranges): name -> core module
STAGES = {"reproject": "reproject", "temporal": "temporal", "history": "history"}

#: methods that reconstruct (usable by ``denoise``)
DENOISERS = ("awr", "lp", "rhf", "oidn")


def get(name: str) -> Method:
    """The method module for ``name``; ValueError naming the choices if unknown,
    TypeError if the module does not declare every member of the contract."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}")
    mod = importlib.import_module("." + METHODS[name], __package__)
    missing = [m for m in MEMBERS if not hasattr(mod, m)]
    if missing:
        raise TypeError(f"method module {mod.__name__} does not declare {', '.join(missing)}")
    return mod


def method_for(name: str, params: dict | None = None) -> Method:
    """The Method to run for ``name`` with ``params``: the registered module,
    or the variant its ``method_for(params)`` picks where a parameter selects
    one (oidn: adaptive sampling or uniform sampling + OIDN)."""
    mod = get(name)
    pick = getattr(mod, "method_for", None)  # optional module member, see the docstring
    return mod if pick is None else pick(params or {})


def param_fields(name: str):
    """The dataclass fields of a method's (or a stage's) Params."""
    if name in STAGES:
        return list(fields(importlib.import_module("." + STAGES[name], __package__).Params))
    return list(fields(get(name).Params))

"""Registry of methods: name -> core module (see core/method.py for the contract).

A new method is one module in core/ and one line here.
"""
from __future__ import annotations

import importlib
from dataclasses import fields

METHODS = {
    "uniform": "uniform",
    "var": "var",
    "awr": "awr",
    "lp": "lp",
    "rhf": "rhf",
}

#: parameter groups that are not methods (frame ranges): name -> core module
STAGES = {"reproject": "reproject", "temporal": "temporal"}

#: methods that reconstruct (usable by ``denoise``)
DENOISERS = ("awr", "lp", "rhf")


def get(name: str):
    """The method module for ``name``; ValueError naming the choices if unknown."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}")
    return importlib.import_module("." + METHODS[name], __package__)


def param_fields(name: str):
    """The dataclass fields of a method's (or a stage's) Params."""
    if name in STAGES:
        return list(fields(importlib.import_module("." + STAGES[name], __package__).Params))
    return list(fields(get(name).Params))

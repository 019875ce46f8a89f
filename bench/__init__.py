"""The benchmark and its references: developer tools of the repository, not
part of the built extension (``blender_manifest.toml`` excludes ``/bench/``).

Roles: :mod:`bench.cli` (arguments, settings, the ``bench`` and ``references``
commands), :mod:`bench.session` (one session: per-scene runs of our methods,
oracle runs, scaling), :mod:`bench.peers` (plain Cycles, Cycles adaptive
sampling, OIDN, the threshold search), :mod:`bench.targets` (speed-up curve,
targets), :mod:`bench.report` (results.json, results.md, plots, sheets),
:mod:`bench.references` (sample scenes, the reference cache).

``COMMANDS`` is what ``launch.py`` hands to :func:`operators.cli.main`.
"""
from .cli import COMMANDS

__all__ = ["COMMANDS"]

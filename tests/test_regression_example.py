"""Render regression test of a shot: the complete example of docs/regression-tests.md.

Checks that frame 1 of the Cornell box still renders as approved: plain Cycles
("uniform", so the test checks the shot and Blender, not a reconstruction) at
16 spp and a quarter of its resolution, against an approved EXR.

    pytest -p cycles_adaptive.pytest_plugin tests/test_regression_example.py
    pytest -p cycles_adaptive.pytest_plugin --update-references tests/test_regression_example.py

The second command approves the current look: it writes every reference that
is missing or no longer matches (and lists them); look at the report folder's
before/after/diff PNGs first.
"""
import os

import pytest

from cycles_adaptive.pytest_plugin import Case

pytest_plugins = ["cycles_adaptive.pytest_plugin"]  # or load it with -p

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = os.path.join(os.path.dirname(HERE), "sample_blends")
REFERENCES = os.path.join(HERE, "references", "regression_example")

CASES = [
    Case(os.path.join(SCENES, "cornell.blend"), 1, os.path.join(REFERENCES, "cornell_0001.exr"),
         method="uniform", spp=16, seed=0, resolution_percentage=25,
         # Tabulated Sobol: one approved image for Blender 4.2, 4.5 and 5.0 (the scene's
         # Blue Noise is used only from 4.4 on)
         params={"scene_pattern": False},
         compare={"metric": "relmse", "fail": 0.016, "failpercent": 1}),
]


@pytest.mark.parametrize("case", CASES, ids=str)
def test_shot_renders_as_approved(render_regression, case):
    render_regression.check(case)

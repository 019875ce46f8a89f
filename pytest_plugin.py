"""pytest plugin for render regression tests: render cases, compare them with
approved references, write a report folder, update references on request.

Load it with ``pytest -p cycles_adaptive.pytest_plugin`` (installed extension:
``-p bl_ext.<repo>.cycles_adaptive.pytest_plugin``), or with ``pytest_plugins
= ["cycles_adaptive.pytest_plugin"]`` in the top ``conftest.py`` or in a test
module (then ``--update-references`` needs ``-p`` too: options are read before
test modules are).  It adds

* the fixture ``render_regression``: ``render_regression.check(case)``
  renders a :class:`Case` (a .blend, a frame, a reference EXR and how to
  render it) with :func:`api.render`, compares it with :func:`api.compare`
  and fails the test with the comparison's report when it fails;
* ``--render-report DIR``: the report folder (default ``render-report`` in
  pytest's temporary folder; printed at the end): per case ``before.png``
  (the reference), ``after.png`` (the render), ``diff.png`` (failing pixels
  red), ``after.exr`` and ``case.json``, and ``index.html`` / ``report.json``
  over all cases.  Its case folders are replaced on every run;
* ``--update-references``: a missing reference, or one the render no longer
  matches, is replaced by the render (the test passes, the terminal summary
  and the report list every reference written).  Without it a reference is
  never written: a missing one fails the test.

See docs/regression-tests.md.  (PYTEST_DONT_REWRITE: no asserts here, and a
test module may import :class:`Case` before pytest loads the plugin.)
"""
from __future__ import annotations

import dataclasses
import html
import json
import os
import re
from typing import Callable

import pytest


@dataclasses.dataclass
class Case:
    """One render regression case: render frame ``frame`` of ``blend`` and
    compare it with the EXR ``reference``.

    ``method``, ``spp``, ``seed``, ``resolution_percentage``, ``view_layer``
    and ``params`` (method parameters and loop settings) go to
    :func:`api.render` (``method`` None: its default); ``compare`` holds
    keywords for :func:`api.compare` (``fail``, ``failpercent``, ``metric``,
    ``ignore_noise``, ...).  ``prepare(scene)``, when given, runs on the opened
    scene before the render (a test that changes the scene on purpose).
    ``name`` (default: the reference's file name without extension) names the
    report folder and the test id.
    """

    blend: str
    frame: int | None
    reference: str
    method: str | None = None
    spp: float = 16
    seed: int = 0
    resolution_percentage: int | None = None
    view_layer: str | None = None
    params: dict = dataclasses.field(default_factory=dict)
    compare: dict = dataclasses.field(default_factory=dict)
    prepare: Callable | None = None
    name: str | None = None

    def __post_init__(self):
        if self.name is None:
            self.name = os.path.splitext(os.path.basename(os.fspath(self.reference)))[0]
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", self.name):
            raise ValueError(f"case name {self.name!r}: use letters, digits, '_', '.', '-' (it names a folder)")

    def __str__(self):
        return self.name


@dataclasses.dataclass
class Outcome:
    """What :meth:`Regression.check` found for one case."""

    case: Case
    status: str          # "pass", "warn", "fail", "created", "updated", "error"
    message: str         # the readable report
    folder: str          # the case's report folder
    figures: dict = dataclasses.field(default_factory=dict)

    @property
    def failed(self) -> bool:
        return self.status in ("fail", "error")


def _api():
    from . import api
    return api


# ================================================================= options
def pytest_addoption(parser):
    group = parser.getgroup("cycles-adaptive", "render regression tests (cycles_adaptive)")
    group.addoption("--update-references", action="store_true", default=False,
                    help="write the render as the new reference where it is missing or no longer matches "
                         "(every reference written is listed at the end)")
    group.addoption("--render-report", default=None, metavar="DIR",
                    help="folder for the before/after/diff report (default: render-report in pytest's "
                         "temporary folder)")


def pytest_configure(config):
    config.stash[_SESSION] = None


_SESSION = pytest.StashKey()


class Regression:
    """The session's regression runner (the ``render_regression`` fixture)."""

    def __init__(self, config, folder: str):
        self.config = config
        self.folder = folder
        self.update = bool(config.getoption("update_references", default=False))
        self.outcomes: list = []

    # ---------------------------------------------------------------- check
    def check(self, case: Case, **compare) -> Outcome:
        """Render ``case``, compare it with its reference, write its report
        folder; fail the calling test (``pytest.fail``, the report as message)
        when it fails.  ``compare`` overrides ``case.compare``."""
        outcome = self.run(case, **compare)
        self.outcomes.append(outcome)
        if outcome.failed:
            pytest.fail(outcome.message, pytrace=False)
        return outcome

    def run(self, case: Case, **compare) -> Outcome:
        """:meth:`check` without failing the test (returns the Outcome)."""
        api = _api()
        folder = os.path.join(self.folder, case.name)
        os.makedirs(folder, exist_ok=True)
        for name in ("before.png", "after.png", "diff.png", "after.exr", "case.json"):
            if os.path.exists(os.path.join(folder, name)):
                os.unlink(os.path.join(folder, name))
        try:
            result = self._render(case)
        except api.Error as exc:
            return self._finish(case, folder, "error", f"render regression {case.name!r}: cannot render: {exc}")
        result.save(os.path.join(folder, "after.exr"))
        result.save_preview(os.path.join(folder, "after.png"))
        reference = os.path.abspath(os.fspath(case.reference))
        if not os.path.isfile(reference):
            if self.update:
                return self._write_reference(case, folder, result, reference, "created", None)
            return self._finish(case, folder, "fail",
                                f"render regression {case.name!r}: reference {reference} does not exist\n"
                                f"  report: {folder}{os.sep} (after.png, after.exr)\n"
                                "  to create it from this render: pytest --update-references "
                                "(with -p cycles_adaptive.pytest_plugin)")
        self._before_png(result, reference, folder)
        try:
            cmp = api.compare(result, reference, **{**case.compare, **compare})
        except api.Error as exc:
            if self.update:
                return self._write_reference(case, folder, result, reference, "updated", None, str(exc))
            return self._finish(case, folder, "error", f"render regression {case.name!r}: {exc}\n"
                                f"  report: {folder}{os.sep}")
        cmp.write_diff(os.path.join(folder, "diff.png"))
        if not cmp.passed and self.update:
            return self._write_reference(case, folder, result, reference, "updated", cmp)
        head = f"render regression {case.name!r} ({case.blend}, frame {case.frame})"
        msg = (f"{head}\n{cmp.report()}\n  report: {folder}{os.sep} (before.png, after.png, diff.png)")
        if not cmp.passed:
            msg += "\n  to approve this render as the new reference: pytest --update-references"
        return self._finish(case, folder, cmp.status, msg, cmp.figures)

    # -------------------------------------------------------------- helpers
    def _render(self, case: Case):
        api = _api()
        scene = api.open_blend(case.blend)
        if case.prepare is not None:
            case.prepare(scene)
        kw = dict(case.params)
        if case.method is not None:
            kw["method"] = case.method
        return api.render(scene, spp=case.spp, frame=case.frame, view_layer=case.view_layer, seed=case.seed,
                          resolution_percentage=case.resolution_percentage, **kw)

    def _before_png(self, result, reference: str, folder: str) -> None:
        """The reference through the view transform of the render's scene."""
        from .core import io as imageio
        try:
            passes, _ = imageio.read_layers(reference)
        except imageio.ImageFileError:
            return  # compare() reports it
        rgba = passes.get("Combined", passes.get(""))
        if rgba is not None and rgba.shape[2] in (3, 4):
            _api().write_png(rgba, os.path.join(folder, "before.png"), scene=result.scene)

    def _write_reference(self, case, folder, result, reference, status, cmp, why=None):
        os.makedirs(os.path.dirname(reference), exist_ok=True)
        result.save(reference, overwrite=True)
        if why is None and cmp is not None:
            why = cmp.report()
        msg = f"render regression {case.name!r}: reference {status}: {reference}" + (f"\n{why}" if why else "")
        return self._finish(case, folder, status, msg, cmp.figures if cmp is not None else {})

    def _finish(self, case, folder, status, message, figures=None) -> Outcome:
        outcome = Outcome(case, status, message, folder, dict(figures or {}))
        from .core.io import write_text
        write_text(os.path.join(folder, "case.json"), json.dumps(_case_record(outcome), indent=1) + "\n")
        return outcome

    # --------------------------------------------------------------- report
    def write_index(self) -> None:
        """``index.html`` and ``report.json`` over every case checked."""
        from .core.io import write_text
        records = [_case_record(o) for o in self.outcomes]
        write_text(os.path.join(self.folder, "report.json"), json.dumps(records, indent=1) + "\n")
        rows = []
        for o in self.outcomes:
            imgs = "".join(f'<td><img src="{html.escape(o.case.name)}/{n}" width="256" '
                           f'style="image-rendering: pixelated"></td>' if os.path.isfile(os.path.join(o.folder, n))
                           else "<td>-</td>" for n in ("before.png", "after.png", "diff.png"))
            rows.append(f"<tr><td><b>{html.escape(o.case.name)}</b><br>{html.escape(o.status.upper())}</td>{imgs}"
                        f"<td><pre>{html.escape(o.message)}</pre></td></tr>")
        page = ("<!doctype html><meta charset='utf-8'><title>render regression report</title>"
                "<table border='1' cellpadding='4'><tr><th>case</th><th>before (reference)</th>"
                "<th>after (render)</th><th>diff</th><th>report</th></tr>" + "".join(rows) + "</table>\n")
        write_text(os.path.join(self.folder, "index.html"), page)


def _case_record(o: Outcome) -> dict:
    c = o.case
    return {"name": c.name, "status": o.status, "blend": os.fspath(c.blend), "frame": c.frame,
            "reference": os.path.abspath(os.fspath(c.reference)), "folder": o.folder, "figures": o.figures,
            "report": o.message}


# ================================================================ fixtures
@pytest.fixture
def render_regression(request, tmp_path_factory) -> Regression:
    """The session's :class:`Regression`: ``render_regression.check(case)``."""
    config = request.config
    reg = config.stash.get(_SESSION, None)
    if reg is None:
        folder = config.getoption("render_report", default=None)
        folder = os.path.abspath(folder) if folder else str(tmp_path_factory.getbasetemp() / "render-report")
        os.makedirs(folder, exist_ok=True)
        reg = Regression(config, folder)
        config.stash[_SESSION] = reg
    return reg


def pytest_sessionfinish(session):
    reg = session.config.stash.get(_SESSION, None)
    if reg is not None and reg.outcomes:
        reg.write_index()


def pytest_terminal_summary(terminalreporter, config):
    reg = config.stash.get(_SESSION, None)
    if reg is None or not reg.outcomes:
        return
    tr = terminalreporter
    failed = [o for o in reg.outcomes if o.failed]
    tr.write_sep("-", "render regression")
    tr.write_line(f"{len(reg.outcomes)} case(s), {len(failed)} failed; report: "
                  f"{os.path.join(reg.folder, 'index.html')}")
    for o in reg.outcomes:
        if o.status in ("created", "updated"):
            tr.write_line(f"reference {o.status}: {os.path.abspath(os.fspath(o.case.reference))}")

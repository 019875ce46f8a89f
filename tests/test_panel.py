"""The panel speaks Blender: a sub-panel of Cycles' Sampling panel, the budget
against the scene's samples, parameters in a collapsed "Advanced" sub-panel
with their labels, the last run's summary, preferences for new scenes.  Runs
under every bpy version (integration)."""
import sys
import types
from dataclasses import fields

import pytest

bpy = pytest.importorskip("bpy")

from blend_util import build_scene  # noqa: E402
from launch import load_package  # noqa: E402

from cycles_adaptive.core import methods  # noqa: E402
from cycles_adaptive.core.pipeline import option_fields  # noqa: E402


class Layout:
    """Records what a panel's draw() puts in its layout (props, labels,
    operators), flattening columns, rows and boxes."""

    def __init__(self, log=None):
        self.log = [] if log is None else log
        self.enabled = True
        self.use_property_split = self.use_property_decorate = False

    def prop(self, data, name, **kw):
        assert name in data.bl_rna.properties, name  # a real property of ``data``
        self.log.append(("prop", data, name))

    def label(self, text="", icon="NONE"):
        self.log.append(("label", text))

    def operator(self, idname, **kw):
        self.log.append(("operator", idname))

    def progress(self, factor=0.0, text=""):
        self.log.append(("progress", text))

    def _child(self, *a, **kw):
        return Layout(self.log)

    column = row = box = split = _child

    def props(self):
        return [e[2] for e in self.log if e[0] == "prop"]

    def labels(self):
        return [e[1] for e in self.log if e[0] == "label"]


@pytest.fixture(scope="module")
def addon():
    pkg = load_package()
    pkg.register()
    yield pkg
    pkg.unregister()


def _draw(panel_cls, scene):
    layout = Layout()
    panel_cls.draw(types.SimpleNamespace(layout=layout), types.SimpleNamespace(scene=scene))
    return layout


def _scene():
    scene = build_scene(16, 16)
    scene.cycles_adaptive.configured = True  # no preferences to apply here
    return scene


def test_the_panel_is_a_sub_panel_of_cycles_sampling_with_a_collapsed_advanced_child(addon):
    main, adv = bpy.types.CYCLESADAPTIVE_PT_panel, bpy.types.CYCLESADAPTIVE_PT_advanced
    assert main.bl_parent_id == "CYCLES_RENDER_PT_sampling"
    assert getattr(bpy.types, main.bl_parent_id).bl_label == "Sampling"
    assert "adaptive sampling" not in main.bl_label.lower()
    assert adv.bl_parent_id == "CYCLESADAPTIVE_PT_panel" and "DEFAULT_CLOSED" in adv.bl_options
    assert main.bl_context == adv.bl_context == "render"


def test_the_main_panel_shows_the_budget_against_the_scenes_samples(addon):
    scene = _scene()
    scene.cycles.samples = 77
    lay = _draw(bpy.types.CYCLESADAPTIVE_PT_panel, scene)
    drawn = lay.props()
    for name in ("method", "use_scene_samples", "spp", "max_seconds", "output_path"):
        assert name in drawn, name
    assert "Cycles Render Max Samples: 77" in lay.labels()
    assert ("operator", "cycles_adaptive.render") in lay.log
    advanced = {f.name for f in option_fields("ui")} - {"spp", "max_seconds"}
    assert not advanced & set(drawn)  # the rest is under "Advanced"


def test_use_scene_samples_takes_the_budget_from_cycles(addon):
    from cycles_adaptive.addon.props import options
    scene = _scene()
    s = scene.cycles_adaptive
    scene.cycles.samples, s.spp = 48, 12.0
    assert options(scene).spp == 12.0
    s.use_scene_samples = True
    assert options(scene).spp == 48.0


def test_the_panel_bounds_each_render_where_the_cli_does_not(addon):
    """Longest Render: 1 s in the panel (Cycles blocks Blender's main thread
    while it renders), off for the command line, where no UI waits."""
    from cycles_adaptive.addon.props import options
    from cycles_adaptive.core.pipeline import Options
    scene = _scene()
    assert Options().render_seconds == 0.0
    assert scene.cycles_adaptive.render_seconds == pytest.approx(1.0)
    assert options(scene).render_seconds == pytest.approx(1.0)
    scene.cycles_adaptive.render_seconds = 0.0
    assert options(scene).render_seconds == 0.0


@pytest.mark.parametrize("method", ["var", "awr", "lp", "rhf"])
def test_advanced_lists_the_other_loop_settings_and_every_method_parameter_with_its_label(addon, method):
    from cycles_adaptive.addon.props import _label
    scene = _scene()
    s = scene.cycles_adaptive
    s.method = method
    lay = _draw(bpy.types.CYCLESADAPTIVE_PT_advanced, scene)
    group = getattr(s, f"params_{method}")
    drawn = [e[2] for e in lay.log if e[0] == "prop" and e[1] == group]
    flds = methods.param_fields(method)
    assert drawn == [f.name for f in flds]
    for f in flds:
        assert group.bl_rna.properties[f.name].name == _label(f)
        if f.metadata.get("label"):
            assert group.bl_rna.properties[f.name].name == f.metadata["label"]
    loop = [e[2] for e in lay.log if e[0] == "prop" and e[1] == s]
    assert loop == [f.name for f in option_fields("ui") if f.name not in ("spp", "max_seconds")]


@pytest.mark.parametrize("method, temporal, title, stage", [("var", "reproject", "Reprojection", "reproject"),
                                                          ("oidn", "blend", "Frame Blend", "history")])
def test_advanced_adds_the_frame_range_stage_parameters(addon, method, temporal, title, stage):
    scene = _scene()
    s = scene.cycles_adaptive
    s.method, s.frame_range, s.temporal = method, True, temporal
    lay = _draw(bpy.types.CYCLESADAPTIVE_PT_advanced, scene)
    assert title in lay.labels()
    drawn = [e[2] for e in lay.log if e[0] == "prop" and e[1] == getattr(s, f"params_{stage}")]
    assert drawn == [f.name for f in methods.param_fields(stage)]


def test_labels_come_from_the_field_metadata():
    from cycles_adaptive.addon.props import _label
    f = {x.name: x for x in fields(methods.get("oidn").Params)}["quality"]
    assert _label(f) == f.metadata["label"] == "Quality"
    loop = {x.name: x for x in option_fields("ui")}
    assert _label(loop["spp"]) == "Samples per Pixel"


def test_the_summary_of_a_run_is_stored_and_drawn(addon):
    from cycles_adaptive.operators.render_op import store_summary
    scene = _scene()
    s = scene.cycles_adaptive
    assert not s.has_result and "Last Result" not in _draw(bpy.types.CYCLESADAPTIVE_PT_panel, scene).labels()
    store_summary(s, {"method": "lp", "spp_mean": 31.96, "total_seconds": 12.34, "estimated_relmse": 0.0123,
                      "reconstructed": True, "out": "/tmp/x.exr"}, cancelled=False)
    labels = _draw(bpy.types.CYCLESADAPTIVE_PT_panel, scene).labels()
    assert "Last Result" in labels and "32.0 spp in 12.3 s" in labels and "Estimated relMSE 0.0123" in labels
    assert s.status == "Done: 32.0 spp, wrote /tmp/x.exr"
    store_summary(s, {"method": "rhf", "spp_mean": 3.0, "total_seconds": 1.0, "estimated_relmse": 0.5,
                      "reconstructed": False, "out": "/tmp/y.exr"}, cancelled=True)
    labels = _draw(bpy.types.CYCLESADAPTIVE_PT_panel, scene).labels()
    assert "Cancelled: sample mean, not reconstructed" in labels
    assert s.status.startswith("Cancelled: 3.0 spp (not reconstructed")


def test_the_status_line_names_the_stage():
    from cycles_adaptive.core.pipeline import Progress
    from cycles_adaptive.operators.render_op import status_line
    st = types.SimpleNamespace(stage="adapt", fraction=0.25, message="iteration 2: adapting (lp) (3 s)",
                               writing=False, cancelled=False)
    assert status_line(st).startswith("Cycles Adaptive: 25% Adapting: iteration 2: adapting (lp) (3 s)")
    st.stage = "reconstruct"
    assert "Reconstructing" in status_line(st)
    st.stage, st.writing, st.cancelled, st.message = "write", True, True, "writing out.exr"
    assert status_line(st) == "Cycles Adaptive: cancelled, Writing: writing out.exr"
    assert Progress("write", 0, 1.0, "w").stage == "write"


@pytest.fixture
def prefs(addon):
    """A preferences entry for the package, as enabling the extension makes
    (after the factory reset: it resets the preferences too)."""
    from cycles_adaptive.addon import preferences
    build_scene(8, 8)
    assert bpy.context.scene.cycles_adaptive.configured  # a loaded file's scenes: configured on load
    entry = bpy.context.preferences.addons.new()
    entry.module = preferences.PACKAGE
    yield preferences.preferences()
    entry = bpy.context.preferences.addons.get(preferences.PACKAGE)
    if entry is not None:
        bpy.context.preferences.addons.remove(entry)


def test_preferences_give_new_scenes_their_defaults_once(prefs):
    from cycles_adaptive.addon import preferences
    assert isinstance(prefs, preferences.CYCLESADAPTIVE_AP_preferences)
    assert preferences.CYCLESADAPTIVE_AP_preferences.bl_idname == preferences.PACKAGE == "cycles_adaptive"
    prefs.method, prefs.spp, prefs.use_scene_samples, prefs.max_seconds = "rhf", 9.0, True, 30.0
    prefs.output_path = "//shots/a.exr"
    s = bpy.data.scenes.new("New Scene").cycles_adaptive  # Scene > New: not yet
    assert not s.configured
    assert preferences.apply_defaults(s, preferences.preferences()) is True
    assert (s.method, s.spp, s.use_scene_samples, s.max_seconds, s.output_path) == \
        ("rhf", 9.0, True, 30.0, "//shots/a.exr")
    s.method = "var"  # the scene's own choice then rules
    assert preferences.apply_defaults(s, prefs) is False and s.method == "var"
    assert preferences._on_load in bpy.app.handlers.load_post


def test_without_a_preferences_entry_the_built_in_defaults_stay(addon):
    from cycles_adaptive.addon import preferences
    from cycles_adaptive.core.pipeline import Options
    assert preferences.preferences() is None  # the package is not an enabled add-on here
    build_scene(8, 8)
    s = bpy.data.scenes.new("New Scene").cycles_adaptive
    assert preferences.apply_defaults(s, None) is True and s.configured
    assert s.method == Options().method and s.spp == Options().spp


def test_the_panel_schedules_the_defaults_once_per_scene(addon):
    from cycles_adaptive.addon import preferences
    build_scene(8, 8)
    scene = bpy.data.scenes.new("New Scene")
    preferences._scheduled.clear()
    _draw(bpy.types.CYCLESADAPTIVE_PT_panel, scene)
    _draw(bpy.types.CYCLESADAPTIVE_PT_panel, scene)
    assert preferences._scheduled == {scene.name}
    preferences._scheduled.clear()


def test_register_unregister_register_again(addon):
    addon.unregister()
    assert not hasattr(bpy.types, "CYCLESADAPTIVE_PT_panel")
    addon.register()
    assert bpy.types.CYCLESADAPTIVE_PT_panel.bl_parent_id == "CYCLES_RENDER_PT_sampling"
    assert "cycles_adaptive" in sys.modules


def test_the_last_result_names_autos_choice(addon):
    from cycles_adaptive.addon.panel import summary_lines
    from cycles_adaptive.operators.render_op import store_summary
    s = build_scene(8, 8).cycles_adaptive
    store_summary(s, {"method": "auto", "chosen": "uniform-lp", "spp_mean": 16.0, "total_seconds": 2.0,
                      "estimated_relmse": 0.01, "reconstructed": True, "out": "x.exr"}, False)
    assert summary_lines(s)[0] == "Automatic: uniform-lp"
    store_summary(s, {"method": "lp", "spp_mean": 8.0, "total_seconds": 1.0, "out": "y.exr"}, False)
    assert summary_lines(s)[0].startswith("Linear predictions")


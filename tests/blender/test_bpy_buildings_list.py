"""The Buildings panel's building list and options: two box buildings and a report written with the core's writers.

Checked: the list holds one item per building with the path, closed solid, status, seconds and surface count of
the report and the models, failures included with their reason; making an item active selects that building's
object and frames it in the 3D viewport (a failure selects nothing); the Refresh operator fills the list again
(from the models alone when the report is unreadable); the panel and the list's rows draw with the list, the
active building's details and the options; the options read and write ``[stages.buildings]`` of ``project.toml``
as the CLI's ``--set`` does (other keys and stages kept), and the runner's config sees them.
"""

from __future__ import annotations

import tomllib
from types import SimpleNamespace

import numpy as np
import pytest
from test_bpy_buildings import two_box_workspace
from test_bpy_ui import RecordingLayout

from oblique_city.core.buildings.attributes import building_attributes
from oblique_city.core.buildings.model import load_buildings
from oblique_city.core.pipeline import Workspace
from oblique_city.core.pipeline.atomic import write_json
from oblique_city.core.pipeline.registry import get_stage

pytestmark = pytest.mark.xdist_group("bpy")

REPORT = {
    "detection": {},
    "buildings": [{"id": "B0001", "path": "2d", "reason": "test", "closed": True, "solid_problem": None,
                   "seconds": 1.25, "dormers": ["gabled", "shed"]},
                  {"id": "B0002", "path": "volumetric", "reason": "test", "closed": False,
                   "solid_problem": "2 open edges", "seconds": 3.5}],
    "failures": [{"id": "B0007", "reason": "only 12 points"},
                 {"id": "B0009", "reason": "roof: no roof plane found"}],
}


@pytest.fixture
def ws(tmp_path, utm_block):
    w, _ = two_box_workspace(tmp_path, utm_block)
    write_json(w.stage_dir("buildings") / "report.json", REPORT)
    return w


class ListLayout(RecordingLayout):
    """A recording layout that also takes ``template_list`` (checking the list type and its data paths)."""

    def _sub(self, *args, **kwargs):
        return ListLayout(self.log)

    row = column = box = _sub

    def template_list(self, listtype, list_id, data, propname, active_data, active_propname, **kwargs):
        import bpy

        assert getattr(bpy.types, listtype).bl_idname == listtype
        assert hasattr(data, propname) and hasattr(active_data, active_propname)
        self.log.append(("list", listtype, propname, active_propname))


def built_scene(bpy, w: Workspace):
    from oblique_city.addon import builders

    scene = bpy.context.scene
    scene.oblique_city.workspace = str(w.root)
    builders.build_scene(scene, w)
    return scene


def test_list_holds_buildings_and_failures(addon, ws):
    scene = built_scene(addon, ws)
    items = scene.oblique_city.building_list
    rows = [(i.name, i.path, i.closed, i.failed, i.status, i.seconds, i.surfaces, i.dormers) for i in items]
    assert rows == [("B0001", "2d", True, False, "closed solid", 1.25, 8, 2),
                    ("B0002", "volumetric", False, False, "open: 2 open edges", 3.5, 8, 0),
                    ("B0007", "", False, True, "failed: only 12 points", 0.0, 0, 0),
                    ("B0009", "", False, True, "failed: roof: no roof plane found", 0.0, 0, 0)]
    assert scene.oblique_city.building_index == -1


def test_active_item_selects_the_building(addon, ws):
    bpy = addon
    from mathutils import Vector

    scene = built_scene(bpy, ws)
    settings = scene.oblique_city
    view_layer = bpy.context.view_layer
    names = [i.name for i in settings.building_list]
    settings.building_index = names.index("B0002")
    obj = view_layer.objects.active
    assert obj.name == "B0002"
    assert [o.name for o in view_layer.objects.selected] == ["B0002"]
    view3d = next(a for a in bpy.context.window.screen.areas if a.type == "VIEW_3D")  # framed on the building
    centre = np.mean([obj.matrix_world @ Vector(c) for c in obj.bound_box], axis=0)
    assert np.allclose(view3d.spaces.active.region_3d.view_location, centre, atol=1e-3)
    settings.building_index = names.index("B0001")
    assert view_layer.objects.active.name == "B0001"
    assert [o.name for o in view_layer.objects.selected] == ["B0001"]
    settings.building_index = names.index("B0009")  # a failure has no object: the selection stays
    assert [o.name for o in view_layer.objects.selected] == ["B0001"]


def test_refresh_operator_fills_the_list(addon, ws):
    bpy = addon
    scene = bpy.context.scene
    scene.oblique_city.workspace = str(ws.root)
    assert len(scene.oblique_city.building_list) == 0
    assert bpy.ops.city.refresh_buildings() == {"FINISHED"}
    assert [i.name for i in scene.oblique_city.building_list] == ["B0001", "B0002", "B0007", "B0009"]
    assert scene.oblique_city.building_list[1].surfaces == 8  # from buildings.json, without building objects
    (ws.root / "buildings" / "report.json").write_text("{", encoding="utf-8")  # unreadable: the models alone
    assert bpy.ops.city.refresh_buildings() == {"FINISHED"}
    assert [(i.name, i.status) for i in scene.oblique_city.building_list] == [
        ("B0001", "closed solid"), ("B0002", "open: 2 open edges")]
    scene.oblique_city.workspace = ""
    with pytest.raises(RuntimeError, match="no workspace"):
        bpy.ops.city.refresh_buildings()


def test_panel_draws_the_list_and_the_options(addon, ws):
    bpy = addon
    from oblique_city.addon.properties import option_fields
    from oblique_city.panels import STAGE_PANEL_CLASSES, CITY_UL_buildings

    scene = built_scene(bpy, ws)
    settings = scene.oblique_city
    panel = next(c for c in STAGE_PANEL_CLASSES if c.bl_label == "Buildings")
    settings.building_index = 1
    layout = ListLayout()
    panel.draw(SimpleNamespace(layout=layout), bpy.context)
    log = layout.log
    assert ("list", "CITY_UL_buildings", "building_list", "building_index") in log
    labels = [e[1] for e in log if e[0] == "label"]
    assert "2 buildings (2D 1, volumetric 1), 1 closed, 2 failed" in labels
    assert "B0002: open: 2 open edges" in labels and "volumetric path, 8 surfaces, 3.5 s" in labels
    assert not any(t.startswith("B0009  failed") for t in labels)  # the list replaces the attention lines
    assert [e[1] for e in log if e[0] == "operator"] == ["city.run_stages", "city.refresh_buildings"]
    assert [e[1] for e in log if e[0] == "prop"] == option_fields("buildings")
    assert option_fields("buildings") == ["min_height", "min_area", "use_masks", "footprints", "voxel",
                                          "force_path", "max_overhang", "overhang_thickness", "dormers",
                                          "dormer_min_rise", "max_roof_fit"]
    settings.building_index = 0
    layout = ListLayout()
    panel.draw(SimpleNamespace(layout=layout), bpy.context)
    labels = [e[1] for e in layout.log if e[0] == "label"]
    assert "2d path, 8 surfaces, 2 dormers, 1.2 s" in labels
    item = settings.building_list[0]
    a = building_attributes(next(m for m in load_buildings(ws.path("buildings", "buildings.json"))[0]
                                 if m.id == item.name))
    assert item.roof_type == a["roof_type"] and item.volume == pytest.approx(a["volume"], rel=1e-6)
    h = a["roof_height_70p"] - a["ground_height"]
    assert f"{a['roof_type']} roof, {h:.1f} m high (70 %), {a['volume']:.0f} m3" in labels

    rows = []
    for item in settings.building_list:
        row = RecordingLayout()
        CITY_UL_buildings.draw_item(SimpleNamespace(layout_type="DEFAULT"), bpy.context, row, settings, item, 0,
                                    settings, "building_index")
        rows.append([e[1] for e in row.log])
    assert rows[0] == ["B0001", "2d", "closed solid", "1.2 s, 8 surf."]
    assert rows[3] == ["B0009", "-", "failed: roof: no roof plane found"]


def test_options_round_trip_through_project_toml(addon, ws):
    bpy = addon
    scene = bpy.context.scene
    opts = scene.oblique_city.stage_options.buildings
    defaults = get_stage("buildings").config()
    assert opts.min_height == defaults.min_height and opts.force_path == "AUTO"
    opts.min_height = 3.0  # without a workspace nothing is written
    assert opts.min_height == defaults.min_height

    ws.project["stages"]["buildings"] = {"max_overhang": 2.0}
    ws.project["stages"]["dense"] = {"step": 2}
    ws.save_project()
    scene.oblique_city.workspace = str(ws.root)
    assert opts.max_overhang == 2.0 and opts.use_masks is True
    opts.min_height = 2.7
    opts.use_masks = False
    opts.footprints = "footprints.geojson"
    opts.force_path = "volumetric"
    opts.voxel = 0.3
    doc = tomllib.loads((ws.root / "project.toml").read_text(encoding="utf-8"))
    assert doc["stages"]["buildings"] == {"max_overhang": 2.0, "min_height": 2.7, "use_masks": False,
                                          "footprints": "footprints.geojson", "force_path": "volumetric",
                                          "voxel": 0.3}
    assert doc["stages"]["dense"] == {"step": 2}
    cfg = get_stage("buildings").make_config(Workspace.open(ws.root).stage_options("buildings"))
    assert (cfg.min_height, cfg.use_masks, cfg.force_path, cfg.voxel, cfg.min_area) == (
        2.7, False, "volumetric", 0.3, defaults.min_area)
    opts.force_path = "AUTO"
    assert Workspace.open(ws.root).stage_options("buildings")["force_path"] == ""

    # an edit of project.toml outside Blender (the CLI's --set) shows in the panel
    w = Workspace.open(ws.root)
    w.project["stages"]["buildings"]["min_area"] = 40
    w.save_project()
    assert opts.min_area == 40.0 and opts.min_height == pytest.approx(2.7)


def test_window_cue_round_trips_through_project_toml(addon, ws):
    from oblique_city.addon.properties import option_fields  # bpy is loaded by the addon fixture

    bpy = addon
    scene = bpy.context.scene
    scene.oblique_city.workspace = str(ws.root)
    opts = scene.oblique_city.stage_options.windows
    assert opts.polarity == "auto" and "polarity" in option_fields("windows")
    opts.polarity = "colour"
    doc = tomllib.loads((ws.root / "project.toml").read_text(encoding="utf-8"))
    assert doc["stages"]["windows"]["polarity"] == "colour"
    assert get_stage("windows").make_config(Workspace.open(ws.root).stage_options("windows")).polarity == "colour"

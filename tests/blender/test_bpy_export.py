"""Export City Model: the operator writes the workspace's buildings through the core export (as the CLI does).

Checked: a CityGML file the core's schema validator accepts with both buildings in it, the format's extension
added, a CityJSON file that passes the core's structure check, the File > Export entries, the Export panel's
buttons, a core error (no buildings yet) reported as one line, and the oriented block exported as Metashape XML
and BlocksExchange (read back with the same orientations), a wrong writer option reported.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_bpy_buildings import two_box_workspace
from test_bpy_ui import draw

pytestmark = pytest.mark.xdist_group("bpy")


@pytest.fixture
def ws(tmp_path, utm_block):
    return two_box_workspace(tmp_path, utm_block)


def test_export_citygml_and_cityjson(addon, ws, tmp_path):
    bpy = addon
    from lxml import etree

    from oblique_city.core.export.citygml import validate_citygml
    from oblique_city.core.export.cityjson import check_cityjson, read_cityjson

    w, models = ws
    bpy.context.scene.oblique_city.workspace = str(w.root)
    out = tmp_path / "out" / "city"
    out.parent.mkdir()
    assert bpy.ops.city.export_city_model(filepath=str(out), format="citygml") == {"FINISHED"}
    gml = tmp_path / "out" / "city.gml"
    assert validate_citygml(gml) == []
    doc = etree.parse(str(gml), etree.XMLParser(resolve_entities=False, no_network=True))
    ids = sorted(e.get("{http://www.opengis.net/gml}id") for e in doc.iter("{*}Building"))
    assert ids == ["B0001", "B0002"]
    pos = np.array([float(v) for e in doc.iter("{*}posList") for v in e.text.split()]).reshape(-1, 3)
    assert np.abs(pos.min(0) - np.concatenate([m.vertices for m in models]).min(0)).max() < 1e-3

    assert bpy.ops.city.export_city_model(filepath=str(gml), format="cityjson") == {"FINISHED"}
    cj = read_cityjson(tmp_path / "out" / "city.city.json")
    assert check_cityjson(cj) == [] and len(cj["CityObjects"]) >= 2


def test_export_reports_core_errors(addon, ws, tmp_path):
    bpy = addon
    w = ws[0]
    (w.root / "buildings" / "buildings.json").unlink()
    bpy.context.scene.oblique_city.workspace = str(w.root)
    with pytest.raises(RuntimeError, match="no buildings file"):
        bpy.ops.city.export_city_model(filepath=str(tmp_path / "a.gml"), format="citygml")
    assert not (tmp_path / "a.gml").exists()


def test_export_menu_and_panel(addon, ws):
    bpy = addon
    from oblique_city.operators import menu_export
    from oblique_city.panels import STAGE_PANEL_CLASSES

    assert menu_export in bpy.types.TOPBAR_MT_file_export._dyn_ui_initialize()
    bpy.context.scene.oblique_city.workspace = str(ws[0].root)
    panel = next(c for c in STAGE_PANEL_CLASSES if c.bl_label == "Export")
    log = draw(panel, bpy.context)
    assert any(e[0] == "operator" and e[1] == "city.export_city_model" for e in log)
    assert any(e[0] == "operator" and e[1] == "city.export_block" for e in log)


def test_export_block(addon, ws, tmp_path):
    bpy = addon
    from oblique_city.core.io.formats import read_block

    w = ws[0]
    bpy.context.scene.oblique_city.workspace = str(w.root)
    assert bpy.ops.city.export_block(filepath=str(tmp_path / "cams"), format="metashape") == {"FINISHED"}
    block, back = w.load_block(), read_block("metashape", tmp_path / "cams.xml")
    assert set(back.images) == set(block.images)
    for iid, img in block.images.items():
        assert np.abs(back.images[iid].pose.C - img.pose.C).max() < 1e-7
        assert np.abs(back.images[iid].pose.R - img.pose.R).max() < 1e-12
    assert bpy.ops.city.export_block(filepath=str(tmp_path / "b.xml"), format="bex", options="rotation=opk") \
        == {"FINISHED"}
    assert len(read_block("bex", tmp_path / "b.xml").images) == len(block.images)
    with pytest.raises(RuntimeError, match="unknown option"):
        bpy.ops.city.export_block(filepath=str(tmp_path / "c.xml"), format="bex", options="angle=gon")


def test_file_names_per_format(addon):
    from oblique_city.operators.export import with_extension

    assert with_extension("/x/city", "citygml") == "/x/city.gml"
    assert with_extension("/x/city.gml", "cityjson") == "/x/city.city.json"
    assert with_extension("/x/city.city.json", "obj") == "/x/city.obj"
    assert with_extension("/x/city.obj", "3dtiles") == "/x/city"  # a folder: the extension goes
    assert with_extension("/x/tiles", "3dtiles") == "/x/tiles"

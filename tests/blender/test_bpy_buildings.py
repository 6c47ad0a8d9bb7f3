"""Builder of the ``buildings`` stage: a box building with an overhang, written with the core's own writer.

Checked: one object per building in the "Buildings" collection, one polygon per surface ring, the material of
each polygon's surface type, vertices back in world coordinates within 1 mm (UTM northings), custom properties.
"""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.buildings.attributes import building_attributes
from oblique_city.core.buildings.model import BuildingModel, Surface, save_buildings
from oblique_city.core.pipeline import Workspace

pytestmark = pytest.mark.xdist_group("bpy")

X0, Y0, Z0 = 500123.25, 5400077.75, 301.5


def box_building(bid: str, dx: float, path: str, closed: bool) -> BuildingModel:
    """A 10 x 8 x 6 m box (ground, 4 walls, flat roof) plus a 1 m overhang strip on the south side."""
    x0, y0 = X0 + dx, Y0
    xy = np.array([[0, 0], [10, 0], [10, 8], [0, 8]], float) + [x0, y0]
    verts = np.vstack([np.c_[xy, np.full(4, Z0)], np.c_[xy, np.full(4, Z0 + 6)],
                       [[x0, y0 - 1, Z0 + 6], [x0 + 10, y0 - 1, Z0 + 6]]])
    surfaces = [Surface(f"{bid}_ground_0", "ground", (0, 3, 2, 1))]
    surfaces += [Surface(f"{bid}_wall_{i}", "wall", (i, (i + 1) % 4, 4 + (i + 1) % 4, 4 + i)) for i in range(4)]
    surfaces += [Surface(f"{bid}_roof_0", "roof", (4, 5, 6, 7)),
                 Surface(f"{bid}_overhang_roof_0", "overhang_roof", (8, 9, 5, 4), in_solid=False),
                 Surface(f"{bid}_overhang_underside_0", "overhang_underside", (8, 4, 5, 9), in_solid=False)]
    info = {"closed": closed} if closed else {"closed": False, "solid_problem": "2 open edges"}
    return BuildingModel(bid, verts, surfaces, path, "test", xy, np.zeros(4), np.array([[0, 0, 1, -Z0 - 6]]),
                         info)


def two_box_workspace(tmp_path, block) -> tuple[Workspace, list[BuildingModel]]:
    """A workspace with ``block`` and two box buildings (B0001 closed, 2D path; B0002 open, volumetric), the
    buildings stage marked done (other tests add their stage's files)."""
    w = Workspace.create(tmp_path / "ws", crs=block.crs)
    w.save_block(block)
    models = [box_building("B0001", 0.0, "2d", True), box_building("B0002", 30.0, "volumetric", False)]
    save_buildings(w.stage_dir("buildings") / "buildings.json", models, block.crs)
    w.write_state({"buildings": {"status": "done"}})
    return w, models


@pytest.fixture
def ws(tmp_path, utm_block):
    return two_box_workspace(tmp_path, utm_block)


def test_buildings_layer(addon, ws):
    bpy = addon
    from oblique_city.addon import builders, georef

    w, models = ws
    scene = bpy.context.scene
    messages = builders.build_scene(scene, w)
    assert messages[-1] == "buildings: 2 buildings (2d 1, volumetric 1), 1 closed solids"
    coll = next(c for c in bpy.data.collections if c.name == "Buildings")
    assert sorted(o.name for o in coll.objects) == ["B0001", "B0002"]
    expected_material = {"ground": "Oblique City ground", "wall": "Oblique City wall", "roof": "Oblique City roof",
                         "overhang_roof": "Oblique City roof",
                         "overhang_underside": "Oblique City overhang underside"}
    for m in models:
        obj = bpy.data.objects[m.id]
        assert np.abs(georef.mesh_vertices_world(scene, obj) - m.vertices).max() < 1e-3
        mesh = obj.data
        assert len(mesh.polygons) == len(m.surfaces) and not any(p.use_smooth for p in mesh.polygons)
        for poly, s in zip(mesh.polygons, m.surfaces):
            assert tuple(poly.vertices) == s.ring
            assert mesh.materials[poly.material_index].name == expected_material[s.kind]
        assert obj["oc_building_id"] == m.id and obj["oc_path"] == m.path
        attrs = building_attributes(m)
        assert {k: obj[f"oc_{k}"] for k in attrs} == attrs and attrs["volume"] > 0
    assert bpy.data.objects["B0001"]["oc_status"] == "closed solid"
    assert bpy.data.objects["B0002"]["oc_status"] == "open: 2 open edges"
    colours = {bpy.data.materials[n].diffuse_color[:3] for n in set(expected_material.values())}
    assert len(colours) == 4
    # normals of the rings (counter-clockwise seen from outside): ground down, roof up, underside down
    normals = {s.kind: np.array(p.normal) for p, s in zip(bpy.data.objects["B0001"].data.polygons, models[0].surfaces)}
    assert normals["ground"][2] < -0.99 and normals["roof"][2] > 0.99 and normals["overhang_underside"][2] < -0.99
    # rebuilding replaces the objects
    builders.build_scene(scene, w, stages=["buildings"])
    assert len(coll.objects) == 2 and "B0001.001" not in bpy.data.objects


def test_buildings_panel_lists_the_buildings_that_need_attention(addon, ws):
    bpy = addon
    import json

    from test_bpy_ui import draw

    from oblique_city.panels import STAGE_PANEL_CLASSES

    w = ws[0]
    report = {"buildings": [{"id": "B0001", "path": "2d", "closed": True, "solid_problem": ""},
                            {"id": "B0002", "path": "volumetric", "closed": False, "solid_problem": "2 open edges"}],
              "failures": [{"id": f"B{i:04d}", "reason": "roof: no roof plane found"} for i in range(10, 30)]}
    (w.root / "buildings" / "report.json").write_text(json.dumps(report))
    bpy.context.scene.oblique_city.workspace = str(w.root)
    panel = next(c for c in STAGE_PANEL_CLASSES if c.bl_label == "Buildings")
    labels = [e[1] for e in draw(panel, bpy.context) if e[0] == "label"]
    assert "2 buildings (2D 1, volumetric 1), 1 closed, 20 failed" in labels
    assert "B0002  open solid: 2 open edges" in labels and "B0010  failed: roof: no roof plane found" in labels
    assert "... and 6 more (buildings/report.json)" in labels and not any(lb.startswith("B0001") for lb in labels)

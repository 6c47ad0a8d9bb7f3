"""Builder and panel of the ``windows`` stage: two box buildings and a windows.json written with the stage's writer.

Checked: one object per building with windows in the "Windows" collection, one quad per window whose world corners
match the file within 1 mm (UTM northings), the glass material, the score attribute, the custom properties, the
parent building, the displayed offset out of the wall, rebuilding without duplicates, a malformed file reported as
a one-line builder message, and the Windows panel's counts.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_bpy_buildings import X0, Y0, Z0, two_box_workspace

from oblique_city.core.windows.store import Window, load_windows, write_windows_json

pytestmark = pytest.mark.xdist_group("bpy")


def south_window(dx: float, x: float, z: float) -> np.ndarray:
    """Corners of a 1.2 x 1.4 m window on the south wall (y = Y0) of the box at ``dx``: outward normal -y."""
    x0 = X0 + dx + x
    return np.array([[x0, Y0, z], [x0 + 1.2, Y0, z], [x0 + 1.2, Y0, z + 1.4], [x0, Y0, z + 1.4]])


def east_window(dx: float, y: float, z: float) -> np.ndarray:
    """Corners of a 0.9 x 1.3 m window on the east wall (x = X0 + dx + 10): outward normal +x."""
    xe, y0 = X0 + dx + 10, Y0 + y
    return np.array([[xe, y0, z], [xe, y0 + 0.9, z], [xe, y0 + 0.9, z + 1.3], [xe, y0, z + 1.3]])


def windows_of_the_test() -> list[Window]:
    out = []
    for k, x in enumerate((1.137, 4.0123, 7.25)):
        out.append(Window(f"B0001_wall_0_w{k:03d}", "B0001_wall_0", "B0001",
                          south_window(0.0, x, Z0 + 1.0371), 0.9 - 0.1 * k, "blob"))
    out.append(Window("B0001_wall_1_w000", "B0001_wall_1", "B0001", east_window(0.0, 3.3, Z0 + 3.21), 0.7, "grid"))
    out.append(Window("B0002_wall_0_w000", "B0002_wall_0", "B0002", south_window(30.0, 2.5, Z0 + 1.5),
                      0.8, "blob"))
    return out


@pytest.fixture
def ws(tmp_path, utm_block):
    w, _ = two_box_workspace(tmp_path, utm_block)
    write_windows_json(w.stage_dir("windows") / "windows.json", windows_of_the_test(), utm_block.crs,
                       {"config": {}, "stats": {"windows": 5}})
    w.write_state({"buildings": {"status": "done"}, "windows": {"status": "done"}})
    return w


def test_windows_layer(addon, ws):
    bpy = addon
    from oblique_city.addon import builders, georef, layers_windows

    scene = bpy.context.scene
    messages = builders.build_scene(scene, ws)
    assert messages[-1] == "windows: 5 windows on 2 buildings"
    coll = next(c for c in bpy.data.collections if c.name == "Windows")
    root = next(c for c in bpy.data.collections if c.name == "Oblique City")
    assert coll.name in root.children
    assert sorted(o.name for o in coll.objects) == ["B0001 windows", "B0002 windows"]
    in_file = load_windows(ws.path("windows", "windows.json"))  # the corners as written (rounded to 0.1 mm)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for bid in ("B0001", "B0002"):
        expected = [w for w in in_file if w.building_id == bid]
        obj = bpy.data.objects[f"{bid} windows"]
        mesh = obj.data
        assert obj["oc_building_id"] == bid and obj["oc_window_count"] == len(expected)
        assert obj.parent is bpy.data.objects[bid]
        assert len(mesh.polygons) == len(expected) and all(p.loop_total == 4 for p in mesh.polygons)
        xyz = georef.mesh_vertices_world(scene, obj)
        for poly, w in zip(mesh.polygons, expected, strict=True):
            assert np.abs(xyz[list(poly.vertices)] - w.corners).max() < 1e-3
            assert mesh.materials[poly.material_index].name == layers_windows.MATERIAL
        scores = np.zeros(len(mesh.polygons), np.float32)
        mesh.attributes[layers_windows.SCORE_ATTRIBUTE].data.foreach_get("value", scores)
        assert np.allclose(scores, [w.score for w in expected])
        # displayed: every quad stands OFFSET_M out of its wall (outward: -y on the south wall, +x on the east)
        shown = obj.evaluated_get(depsgraph).data
        co = np.array([v.co for v in shown.vertices], np.float64)
        outward = np.array([[0, -1, 0] if "wall_0" in w.surface_id else [1, 0, 0] for w in expected], float)
        local = georef.world_to_local(scene, np.concatenate([w.corners for w in expected]))
        assert np.abs(co - local - np.repeat(outward, 4, axis=0) * layers_windows.OFFSET_M).max() < 1e-3
    glass = bpy.data.materials[layers_windows.MATERIAL]
    assert max(glass.diffuse_color[:3]) < 0.1
    # rebuilding replaces the objects
    builders.build_scene(scene, ws, stages=["windows"])
    assert len(coll.objects) == 2 and "B0001 windows.001" not in bpy.data.objects


def test_a_malformed_windows_file_is_reported_in_one_line(addon, ws):
    bpy = addon
    from oblique_city.addon import builders

    path = ws.path("windows", "windows.json")
    doc = json.loads(path.read_text())
    doc["buildings"]["B0001"]["B0001_wall_0"][0]["corners"] = [[0, 0, 0]] * 3
    path.write_text(json.dumps(doc))
    messages = builders.build_scene(bpy.context.scene, ws)
    assert messages[-1].startswith("windows: not built (") and "windows.json" in messages[-1]
    assert "\n" not in messages[-1]
    assert messages[-2].startswith("buildings: 2 buildings")
    assert "B0001" in bpy.data.objects and "B0001 windows" not in bpy.data.objects


def test_windows_panel_shows_the_counts(addon, ws):
    bpy = addon
    from test_bpy_ui import draw

    from oblique_city.panels import STAGE_PANEL_CLASSES

    bpy.context.scene.oblique_city.workspace = str(ws.root)
    panel = next(c for c in STAGE_PANEL_CLASSES if c.bl_label == "Windows")
    labels = [e[1] for e in draw(panel, bpy.context) if e[0] == "label"]
    assert any(t.startswith("windows: done") for t in labels)
    assert "5 windows on 3 walls of 2 buildings (1 from the facade grid)" in labels
    assert labels[-2:] == ["    B0001: 4", "    B0002: 1"]

"""Builders of stage results: dense display points and the DSM with its true ortho, at UTM coordinates.

The stage outputs are written with the core's own writers (PLY, GeoTIFF, PNG) and marked done in ``state.json``;
"Build Scene from Workspace" then creates their layers. Checked: world positions back from Blender within 1 mm,
colours, holes where the DSM has no height, upward normals, the ortho texture on the right cells, and the
classified points coloured by class (hidden).
"""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.io.geotiff import write_geotiff, write_png
from oblique_city.core.io.pointcloud import PointCloud, read_las, write_las, write_ply
from oblique_city.core.model import Raster
from oblique_city.core.pipeline import Workspace

pytestmark = pytest.mark.xdist_group("bpy")

ROWS, COLS, CELL = 40, 50, 0.5
X0, Y0 = 500100.0, 5400050.0


@pytest.fixture
def ws(tmp_path, utm_block):
    rng = np.random.default_rng(5)
    w = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
    w.save_block(utm_block)
    n = 2000
    xyz = np.c_[rng.uniform(X0, X0 + 25, n), rng.uniform(Y0 - 20, Y0, n), rng.uniform(300, 330, n)]
    xyz += rng.uniform(0, 1e-3, (n, 3))
    cloud = PointCloud(xyz, rng.integers(0, 256, (n, 3)), np.zeros((n, 3)), rng.integers(0, 5, n),
                       np.zeros(n), ["img0"], utm_block.crs)
    write_ply(w.stage_dir("dense") / "points_display.ply", cloud)
    dsm = 300.0 + rng.uniform(0, 20, (ROWS, COLS)).astype(np.float32)
    dsm[10:14, 20:25] = np.nan  # a hole (no height)
    write_geotiff(w.stage_dir("surface") / "dsm.tif", Raster(dsm, X0, Y0, CELL, utm_block.crs))
    dtm = (298.0 + 0.01 * np.add.outer(np.arange(ROWS), np.arange(COLS))).astype(np.float32)  # a gentle slope
    write_geotiff(w.stage_dir("surface") / "dtm.tif", Raster(dtm, X0, Y0, CELL, utm_block.crs))
    r, c = np.mgrid[0:ROWS, 0:COLS]
    ortho = np.stack([r * 5, c * 5, np.full_like(r, 128)], axis=-1).astype(np.uint8)  # colour encodes the cell
    write_png(w.path("surface", "ortho.png"), ortho)
    classified = PointCloud(xyz[:500], cloud.rgb[:500], np.zeros((500, 3)), np.zeros(500), np.zeros(500), ["img0"],
                            utm_block.crs, classification=rng.choice([1, 2, 5, 6, 7], 500))
    write_las(w.path("surface", "points_classified_display.laz"), classified)
    w.write_state({"dense": {"status": "done"}, "surface": {"status": "done"}})
    return w, cloud, dsm, ortho


def test_dense_and_surface_layers(addon, ws):
    bpy = addon
    from oblique_city.addon import builders, georef, layers

    w, cloud, dsm, ortho = ws
    scene = bpy.context.scene
    messages = builders.build_scene(scene, w)
    assert [m.split(":")[0] for m in messages] == ["block", "dense", "surface"]

    points = bpy.data.objects["Dense points"]
    assert np.abs(georef.mesh_vertices_world(scene, points) - cloud.xyz).max() < 1e-3
    col = np.empty(len(cloud) * 4, np.float32)
    points.data.color_attributes["Col"].data.foreach_get("color_srgb", col)
    assert np.abs(col.reshape(-1, 4)[:, :3] * 255 - cloud.rgb).max() < 0.51
    assert points.modifiers["Points"].type == "NODES"

    obj = bpy.data.objects["DSM"]
    mesh = obj.data
    valid = np.isfinite(dsm)
    n_quads = int((valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]).sum())
    assert len(mesh.polygons) == n_quads == (ROWS - 1) * (COLS - 1) - 6 * 5
    xyz = georef.mesh_vertices_world(scene, obj)
    cr = np.round(np.c_[(xyz[:, 0] - X0) / CELL - 0.5, (Y0 - xyz[:, 1]) / CELL - 0.5]).astype(int)
    assert np.abs(np.c_[X0 + (cr[:, 0] + 0.5) * CELL, Y0 - (cr[:, 1] + 0.5) * CELL] - xyz[:, :2]).max() < 1e-3
    assert np.abs(dsm[cr[:, 1], cr[:, 0]] - xyz[:, 2]).max() < 1e-3
    normals = np.empty(len(mesh.polygons) * 3, np.float32)
    mesh.polygons.foreach_get("normal", normals)
    assert normals.reshape(-1, 3)[:, 2].min() > 0.0

    # texture: the ortho pixel at each loop's UV is the colour of the loop vertex's cell
    uv = np.empty(len(mesh.loops) * 2, np.float32)
    mesh.uv_layers["ortho"].data.foreach_get("uv", uv)
    uv = uv.reshape(-1, 2)
    vi = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", vi)
    image = mesh.materials[0].node_tree.nodes["Ortho"].image
    px = np.empty(COLS * ROWS * 4, np.float32)
    image.pixels.foreach_get(px)
    px = px.reshape(ROWS, COLS, 4)[::-1]  # Blender stores rows bottom-up
    col_px = np.round(uv[:, 0] * COLS - 0.5).astype(int)
    row_px = np.round((1.0 - uv[:, 1]) * ROWS - 0.5).astype(int)
    assert np.array_equal(np.c_[col_px, row_px], cr[vi])
    assert np.abs(px[row_px, col_px, :3] * 255 - ortho[cr[vi, 1], cr[vi, 0]]).max() < 0.51

    # the DTM: a full grid mesh at the DTM's heights, hidden in the view layer and in renders
    dtm = bpy.data.objects["DTM"]
    assert len(dtm.data.polygons) == (ROWS - 1) * (COLS - 1)
    xyz = georef.mesh_vertices_world(scene, dtm)
    cr = np.round(np.c_[(xyz[:, 0] - X0) / CELL - 0.5, (Y0 - xyz[:, 1]) / CELL - 0.5]).astype(int)
    assert np.abs(298.0 + 0.01 * (cr[:, 0] + cr[:, 1]) - xyz[:, 2]).max() < 1e-3
    assert dtm.hide_get() and dtm.hide_render and not obj.hide_get()
    assert "DTM as 2000 vertices (hidden)" in messages[2]

    # the classified points: coloured by class, the code in an attribute, hidden like the DTM
    cls_obj = bpy.data.objects["Classified points"]
    classified = read_las(w.path("surface", "points_classified_display.laz"))
    assert np.abs(georef.mesh_vertices_world(scene, cls_obj) - classified.xyz).max() < 1e-3
    code = np.empty(len(classified), np.int32)
    cls_obj.data.attributes["class"].data.foreach_get("value", code)
    assert np.array_equal(code, classified.classification)
    col = np.empty(len(classified) * 4, np.float32)
    cls_obj.data.color_attributes["Col"].data.foreach_get("color_srgb", col)
    want = np.array([layers.CLASS_COLOURS[int(c)] for c in classified.classification])
    assert np.abs(col.reshape(-1, 4)[:, :3] - want).max() < 0.003
    assert cls_obj.hide_get() and cls_obj.hide_render
    assert "500 classified display points (hidden)" in messages[2]


def test_large_dsm_is_subsampled(addon, ws, monkeypatch):
    bpy = addon
    from oblique_city.addon import georef, layers

    w, _, dsm, _ = ws
    monkeypatch.setattr(layers, "MAX_DSM_VERTICES", 600)  # 40 x 50 cells -> every 2nd row and column
    layers.build_surface(bpy.context.scene, w)
    xyz = georef.mesh_vertices_world(bpy.context.scene, bpy.data.objects["DSM"])
    cr = np.round(np.c_[(xyz[:, 0] - X0) / CELL - 0.5, (Y0 - xyz[:, 1]) / CELL - 0.5]).astype(int)
    assert len(xyz) <= 600 and np.all(cr % 2 == 0)
    assert np.abs(dsm[cr[:, 1], cr[:, 0]] - xyz[:, 2]).max() < 1e-3


def test_a_broken_layer_does_not_stop_the_others(addon, ws):
    bpy = addon
    from oblique_city.addon import builders

    w = ws[0]
    (w.root / "dense" / "points_display.ply").write_bytes(b"not a ply")
    messages = builders.build_scene(bpy.context.scene, w)
    assert messages[1].startswith("dense: not built (") and "points_display.ply" in messages[1]
    assert messages[2].startswith("surface: DSM 50x40")
    assert "DSM" in bpy.data.objects and "Dense points" not in bpy.data.objects

"""The aerotri quality layers (CBA ray count, standard deviations, intersection errors) as image planes in Blender.

The layers are written by the core's own writer (:func:`core.aerotri.report.write_layers`: GeoTIFF + coloured PNG)
from a grid whose values change along both axes, so any flip or transposition shows. Checked: the plane's four
corners in world coordinates against the GeoTIFF transform read back independently with tifffile (tie point +
pixel scale tags, PixelIsArea), its height, the UV layout and the texture (the colour Blender samples at each
corner's UV equals the PNG's pixel in that corner), rebuilding without duplicates, and the errors.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tifffile

from oblique_city.core.errors import InputError
from oblique_city.core.model import Raster, TiePoints
from oblique_city.core.pipeline import Workspace

pytestmark = pytest.mark.xdist_group("bpy")

ROWS, COLS, CELL = 7, 11, 25.0
X0, Y0 = 500012.5, 5400290.0


@pytest.fixture
def ws(tmp_path, utm_block):
    from oblique_city.core.aerotri.report import write_layers

    w = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
    w.save_block(utm_block)
    rr, cc = np.mgrid[0:ROWS, 0:COLS]
    rays = (2.0 + cc + 3.0 * rr).astype(np.float64)  # grows to the east and to the south
    rays[3, 4] = np.nan
    layers = {"cba_rays": Raster(data=rays, x0=X0, y0=Y0, cell=CELL, crs=utm_block.crs),
              "cba_std_z": Raster(data=0.01 * (1.0 + rr) / (1.0 + cc), x0=X0, y0=Y0, cell=CELL, crs=utm_block.crs)}
    write_layers(layers, w.stage_dir("aerotri") / "layers")
    rng = np.random.default_rng(5)
    xyz = np.c_[rng.uniform(X0, X0 + COLS * CELL, 50), rng.uniform(Y0 - ROWS * CELL, Y0, 50), rng.uniform(300, 320, 50)]
    xyz[::9] = np.nan
    ties = TiePoints(xyz=xyz, obs_track=np.repeat(np.arange(50), 2), obs_image=np.zeros(100, np.int64),
                     obs_uv=np.zeros((100, 2)), image_ids=["img0"], obs_blunder=np.zeros(100, bool))
    ties.save(str(w.stage_dir("aerotri") / "ties.npz"))
    return w, float(np.median(xyz[np.isfinite(xyz[:, 2]), 2]))


def _transform(path):
    """(x0, y0, cell) from the GeoTIFF tags, read without the project's reader."""
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        tie = tags[33922].value
        scale = tags[33550].value
    assert tie[0] == 0 and tie[1] == 0 and scale[0] == scale[1]
    return tie[3], tie[4], scale[0]


def test_plane_corners_follow_the_geotiff_transform(addon, ws):
    bpy = addon
    from oblique_city.addon import georef, layers_aerotri

    w, z_med = ws
    scene = bpy.context.scene
    summary = layers_aerotri.build_quality_layer(scene, w, "cba_rays")
    assert summary.startswith(f"cba_rays: {COLS}x{ROWS} cells of 25 m")
    obj = bpy.data.objects["cba_rays layer"]
    x0, y0, cell = _transform(w.path("aerotri/layers/cba_rays.tif"))
    assert (x0, y0, cell) == (X0, Y0, CELL)
    expected = np.array([[x0, y0 - ROWS * cell], [x0 + COLS * cell, y0 - ROWS * cell], [x0 + COLS * cell, y0],
                         [x0, y0]])
    corners = georef.mesh_vertices_world(scene, obj)
    assert np.abs(corners[:, :2] - expected).max() < 1e-3
    assert np.abs(corners[:, 2] - z_med).max() < 1e-3
    assert len(obj.data.polygons) == 1 and obj.data.polygons[0].normal.z > 0.99

    # texture: the colour at each corner's UV is the PNG's pixel in that corner of the grid
    image = obj.data.materials[0].node_tree.nodes["Layer"].image
    assert tuple(image.size) == (COLS, ROWS)
    px = np.array(image.pixels[:], np.float64).reshape(ROWS, COLS, 4)[::-1, :, :3]  # Blender stores rows bottom-up
    png = cv2.imread(str(w.path("aerotri/layers/cba_rays.png")))[:, :, ::-1] / 255.0
    assert np.abs(px - png).max() < 1.5 / 255
    uv = np.empty(8, np.float32)
    obj.data.uv_layers["layer"].data.foreach_get("uv", uv)
    uv = uv.reshape(4, 2)
    loops = [obj.data.loops[i].vertex_index for i in range(4)]
    for loop, (u, v) in zip(loops, uv):
        world = corners[loop]
        col = int(np.clip(np.floor((world[0] - x0) / cell), 0, COLS - 1))
        row = int(np.clip(np.floor((y0 - world[1]) / cell), 0, ROWS - 1))
        sampled = px[int(np.clip((1.0 - v) * ROWS, 0, ROWS - 1)), int(np.clip(u * COLS, 0, COLS - 1))]
        assert np.abs(sampled - png[row, col]).max() < 1.5 / 255, (loop, u, v)
    # the corner colours differ (the grid is not symmetric), so a flip would have been caught above
    assert np.abs(png[0, 0] - png[-1, -1]).max() > 0.2


def test_rebuild_replaces_and_other_layers_sit_beside(addon, ws):
    bpy = addon
    from oblique_city.addon import georef, layers_aerotri

    w, _ = ws
    scene = bpy.context.scene
    layers_aerotri.build_quality_layer(scene, w, "cba_rays")
    layers_aerotri.build_quality_layer(scene, w, "cba_rays")
    layers_aerotri.build_quality_layer(scene, w, "cba_std_z", z=250.0)
    coll = next(c for c in bpy.data.collections if c.get("oc_role") == "quality_layers")
    assert sorted(o.get("oc_layer") for o in coll.objects) == ["cba_rays", "cba_std_z"]
    std = next(o for o in coll.objects if o.get("oc_layer") == "cba_std_z")
    assert np.abs(georef.mesh_vertices_world(scene, std)[:, 2] - 250.0).max() < 1e-3


def test_missing_or_unknown_layer(addon, ws):
    bpy = addon
    from oblique_city.addon import layers_aerotri

    w, _ = ws
    with pytest.raises(InputError, match="run the 'aerotri' stage"):
        layers_aerotri.build_quality_layer(bpy.context.scene, w, "cba_std_xy")
    with pytest.raises(InputError, match="unknown quality layer"):
        layers_aerotri.build_quality_layer(bpy.context.scene, w, "ortho")

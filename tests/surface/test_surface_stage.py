"""The dense and surface stages end to end on the rendered synthetic scene, checked against its truth."""

from __future__ import annotations

import json

import dense_scene
import numpy as np
import pytest
from scipy import ndimage

from oblique_city.core.evaluate.surface import error_shares, roof_edge_displacement, surface_table, wall_cells
from oblique_city.core.io.geotiff import read_geotiff
from oblique_city.core.io.pointcloud import read_las, read_ply
from oblique_city.core.model import GroundPoint
from oblique_city.core.pipeline import RunContext, Workspace
from oblique_city.core.pipeline.runner import run_stages
from oblique_city.core.surface.dtm import LAS_CLASSES


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("surface_ws")
    (root / "images").mkdir()
    block, scene = dense_scene.make_block(root / "images",
                                          dense_scene.nadir_poses() + dense_scene.oblique_poses("north"))
    for i, xy in enumerate(((-45.0, -40.0), (40.0, 42.0))):  # ground points give the height prior
        block.add_ground_point(GroundPoint(f"gcp{i}", np.r_[np.add(xy, dense_scene.ORIGIN[:2]),
                                                           dense_scene.GROUND_Z]))
    ws = Workspace.create(root, "EPSG:32632")
    ws.save_block(block)
    ws.project["stages"]["dense"] = {"max_object_height": 40.0}
    ws.save_project()
    records = run_stages(ws, ["surface"], RunContext())
    state = json.loads((root / "state.json").read_text())
    dsm = read_geotiff(root / "surface" / "dsm.tif")
    xs, ys = dsm.cell_centers()
    x, y = np.meshgrid(xs - dense_scene.ORIGIN[0], ys - dense_scene.ORIGIN[1])
    return ws, scene, records, state, dsm, scene.true_dsm(x, y), (x, y)


def test_stages_write_their_outputs(run):
    ws, _, records, state, *_ = run
    assert [r.status for r in records] == ["done", "done"]
    for name in ("dense", "surface"):
        for p in state[name]["outputs"]:
            assert ws.path(p).exists(), p
    las = read_las(ws.path("dense", "points.laz"))
    ply = read_ply(ws.path("dense", "points.ply"))
    assert len(las) == len(ply) == state["dense"]["metrics"]["points"] > 50_000
    assert "UTM zone 32N" in las.crs
    assert np.abs(las.xyz - ply.xyz).max() < 1e-3
    assert set(np.unique(ply.view)) == {0, 1}  # nadir and north masters
    assert len(read_ply(ws.path("dense", "points_display.ply"))) <= 300_000
    assert state["dense"]["metrics"]["removed_mixed"] > 0


def test_dsm_against_truth(run):
    *_, dsm, truth, _ = run
    walls = wall_cells(truth)
    roofs = (truth > dense_scene.GROUND_Z + 2) & ~ndimage.binary_dilation(walls)
    ground = (truth < dense_scene.GROUND_Z + 0.1) & ~ndimage.binary_dilation(walls, iterations=3)
    t = surface_table(dsm.data, truth, {"roofs": roofs, "ground": ground}, 3 * dsm.cell)
    # measured: roofs NMAD 0.08 m, completeness 0.95; ground RMSE 0.04 m, completeness 0.93 (GSD 0.32 m)
    assert t["roofs"]["nmad"] < 0.2 and t["roofs"]["completeness"] > 0.85
    assert t["ground"]["rmse"] < 0.3 and t["ground"]["completeness"] > 0.8


def test_dtm_masks_and_classes(run):
    ws, scene, _, _, dsm, truth, (x, y) = run
    dtm = read_geotiff(ws.path("surface", "dtm.tif"))
    assert np.sqrt(np.mean((dtm.data - dense_scene.GROUND_Z) ** 2)) < 0.3
    bld = read_geotiff(ws.path("surface", "buildings.tif")).data.astype(bool)
    veg = read_geotiff(ws.path("surface", "vegetation.tif")).data.astype(bool)
    tree = np.zeros_like(bld)
    for x0, y0, x1, y1, _, is_tree in dense_scene.BOXES:
        if is_tree:
            tree |= (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    true_bld = (truth > dense_scene.GROUND_Z + 2) & ~tree
    iou = (bld & true_bld).sum() / (bld | true_bld).sum()
    assert iou > 0.8
    if tree.any():
        assert (veg & tree).sum() > 0.5 * tree.sum()
        assert (bld & tree).sum() < 0.1 * tree.sum()
    with np.load(ws.path("dense", "points.npz")) as z:
        xyz = z["xyz"][z["removed"] == 0]
    classes = np.load(ws.path("surface", "point_classes.npy"))
    h = scene.true_dsm(xyz[:, 0] - dense_scene.ORIGIN[0], xyz[:, 1] - dense_scene.ORIGIN[1])
    on_roof = np.abs(xyz[:, 2] - h) < 0.5
    high = on_roof & (h > dense_scene.GROUND_Z + 5)
    assert (classes[high] == 1).mean() > 0.97
    low = on_roof & (h < dense_scene.GROUND_Z + 0.1)
    assert (classes[low] == 0).mean() > 0.97
    # the classified LAS: the same points, ASPRS codes against the scene's boxes
    las = read_las(ws.path("surface", "points_classified.laz"))
    assert len(las) == len(xyz) and np.abs(las.xyz - xyz).max() < 1e-3
    code = las.classification
    assert (code[low] == LAS_CLASSES["ground"]).mean() > 0.97
    in_tree = np.zeros(len(xyz), bool)
    for x0, y0, x1, y1, _, is_tree in dense_scene.BOXES:
        if is_tree:
            lx, ly = xyz[:, 0] - dense_scene.ORIGIN[0], xyz[:, 1] - dense_scene.ORIGIN[1]
            in_tree |= (lx >= x0) & (lx <= x1) & (ly >= y0) & (ly <= y1)
    # raised points beyond the surface grid (the area of interest) have no masks: unclassified
    r, c = np.floor((dsm.y0 - xyz[:, 1]) / dsm.cell), np.floor((xyz[:, 0] - dsm.x0) / dsm.cell)
    inside = (r >= 0) & (r < dsm.data.shape[0]) & (c >= 0) & (c < dsm.data.shape[1])
    assert np.all(code[high & ~inside] == LAS_CLASSES["unclassified"])
    high &= inside
    roofs = high & ~in_tree
    assert (code[roofs] == LAS_CLASSES["building"]).mean() > 0.95
    if (high & in_tree).any():
        assert np.isin(code[high & in_tree], [LAS_CLASSES["medium_vegetation"],
                                              LAS_CLASSES["high_vegetation"]]).mean() > 0.8


def test_true_ortho_roof_edges(run):
    ws, scene, _, _, dsm, truth, (x, y) = run
    ortho = read_geotiff(ws.path("surface", "ortho.tif")).data
    assert ortho.shape[2] == 4 and (ortho[..., 3] > 0).mean() > 0.8
    ref = dense_scene.reference_ortho(scene, x, y)
    edges = wall_cells(truth) & (truth > dense_scene.GROUND_Z + 2)
    shift = roof_edge_displacement(ortho, ref, edges, window=24)
    assert len(shift) > 20
    assert np.median(shift) < 1.0  # cells; a plain ortho on the terrain would shift roofs by metres


def test_quality_maps(run):
    ws, *_ = run
    q = read_geotiff(ws.path("surface", "quality_adjusted.tif")).data
    assert np.isfinite(q).mean() > 0.5
    assert 0 < np.nanmean(q) < 0.1  # multi-slave intersection with the true orientation: centimetres


def test_error_shares_name_the_building_the_error_comes_from():
    """Two buildings of 100 cells: one 0.1 m off everywhere, one with 4 cells 2 m off and the rest exact; cells
    owned by nobody count in the total only. Shares are of the summed squared error, largest first."""
    err = np.zeros((10, 30))
    owner = np.full((10, 30), -1)
    owner[:, :10], owner[:, 10:20] = 0, 1
    err[:, :10] = 0.1                   # building 0: 99 x 0.01 (one cell without estimate below)
    err[0, 10:14] = 2.0                 # building 1: 4 x 4 = 16
    err[0, 25] = 1.0                    # nobody's: 1
    err[5, 5] = np.nan                  # no estimate: not counted
    mask = np.ones(err.shape, bool)
    s = error_shares(err, mask, owner)
    assert list(s) == [1, 0]
    assert s[1]["share"] == pytest.approx(16 / 17.99) and s[0]["share"] == pytest.approx(0.99 / 17.99)
    assert s[1]["cells"] == 100 and s[0]["cells"] == 99
    assert s[1]["rmse"] == pytest.approx(np.sqrt(16 / 100)) and s[0]["rmse"] == pytest.approx(0.1)

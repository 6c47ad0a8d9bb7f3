"""Pair matching on rendered images, multi-slave fusion, filters, image selection."""

from __future__ import annotations

import dense_scene
import numpy as np
import pytest

from oblique_city.core.dense.fusion import (
    FusionConfig,
    depth_to_points,
    erode_far_edges,
    fuse_depths,
    grid_normals,
    incidence_deg,
    intersection_errors,
    local_outliers,
    smooth_depth,
)
from oblique_city.core.dense.pairs import PairTask, match_pair
from oblique_city.core.dense.selection import SelectionConfig, select_pairs
from oblique_city.core.model import Pose


def _true_depth(block, scene, iid):
    img = block.images[iid]
    local = Pose(img.pose.R, img.pose.C - dense_scene.ORIGIN)
    return dense_scene.render(scene, block.camera_of(img), local, supersample=1)[1]


def _task(block, m, s):
    im, is_ = block.images[m], block.images[s]
    root = block.image_root
    return PairTask(m, s, block.camera_of(im), im.pose, block.camera_of(is_), is_.pose, f"{root}/{im.file}",
                    f"{root}/{is_.file}", dense_scene.GROUND_Z - 5, dense_scene.GROUND_Z + 30)


def test_pair_depth_matches_truth(nadir_oblique_block):
    block, scene = nadir_oblique_block
    for m, s, med_tol in (("img01", "img00", 0.1), ("img01", "img04", 0.1), ("img07", "img06", 0.5)):
        r = match_pair(_task(block, m, s))
        err = r.depth - _true_depth(block, scene, m)
        ok = np.isfinite(err)
        assert ok.mean() > 0.4, (m, s)
        assert np.median(np.abs(err[ok])) < med_tol, (m, s)
        assert (np.abs(err[ok]) < 1.0).mean() > 0.9, (m, s)


def test_fusion_keeps_agreeing_slaves():
    d = np.full((3, 4, 5), 100.0, np.float32)
    d[1] += 0.05
    d[2, 0] = 130.0          # one slave wrong in row 0: the other two still agree
    d[1:, 1] = np.nan        # only one slave in row 1: not enough
    d[1, 2] = 80.0           # three different answers in row 2
    d[2, 2] = 120.0
    fb = np.full(3, 100.0 * 100.0 / 0.5)  # tolerance = 1 px = 0.5 m at 100 m
    fused, agree = fuse_depths(d, fb, FusionConfig(min_agree=2, tol_px=1.0))
    assert np.allclose(fused[0], 100.025) and not agree[2, 0].any()
    assert np.isnan(fused[1]).all() and np.isnan(fused[2]).all()
    assert np.allclose(fused[3], (100.0 + 100.05 + 100.0) / 3, atol=1e-4)   # equal baselines: plain mean


def test_fusion_weights_long_baselines():
    d = np.stack([np.full((2, 2), 100.0), np.full((2, 2), 100.2)]).astype(np.float32)
    fb = np.array([1000.0, 3000.0])   # the second pair has 3x the baseline: 9x the weight
    fused, _ = fuse_depths(d, fb, FusionConfig(min_agree=2, tol_px=10.0))
    assert np.allclose(fused, (100.0 + 9 * 100.2) / 10, atol=1e-4)


def test_far_side_of_depth_edges_is_eroded():
    """A roof (depth 190 m) beside ground (200 m) seen from above: ground pixels within the radius of the
    roof go, the roof stays; a smooth slanted surface (oblique ground, 0.3 m per pixel) loses nothing."""
    d = np.full((20, 20), 200.0, np.float32)
    d[:, :10] = 190.0
    out = erode_far_edges(d, 1, FusionConfig(edge_radius_px=2.0, near_edge_radius_px=0.0, edge_jump_m=1.0,
                                                 edge_jump_rel=0.01))
    assert np.isfinite(out[:, :10]).all() and np.isnan(out[:, 10:12]).all() and np.isfinite(out[:, 12:]).all()
    ramp = (300.0 + 0.3 * np.arange(20, dtype=np.float32))[:, None].repeat(20, 1)
    assert np.isfinite(erode_far_edges(ramp, 1, FusionConfig())).all()
    assert np.isnan(erode_far_edges(d, 2, FusionConfig(edge_radius_px=2.0, near_edge_radius_px=0.0))[:, 10]).all()
    both = erode_far_edges(d, 1, FusionConfig(edge_radius_px=2.0, near_edge_radius_px=1.0))
    assert np.isfinite(both[:, :9]).all() and np.isnan(both[:, 9:12]).all() and np.isfinite(both[:, 12:]).all()


def test_bilateral_keeps_edges_and_holes():
    rng = np.random.default_rng(0)
    d = np.where(np.arange(40)[None, :] < 20, 100.0, 80.0) + rng.normal(0, 0.05, (30, 40))
    d = d.astype(np.float32)
    d[5:8, 5:8] = np.nan
    s = smooth_depth(d, FusionConfig(bilateral_sigma_m=0.2))
    assert np.isnan(s[5:8, 5:8]).all()
    assert np.nanstd(s[:, 2:17] - 100.0) < 0.6 * np.nanstd(d[:, 2:17] - 100.0)
    assert np.abs(s[:, 19] - 100.0).max() < 0.3 and np.abs(s[:, 20] - 80.0).max() < 0.3


def test_mixed_pixels_are_grazing(nadir_oblique_block):
    block, _ = nadir_oblique_block
    img = block.images["img01"]
    cam = block.camera_of(img)
    depth = np.full((cam.height, cam.width), 160.0, np.float32)
    depth[:, 200:] = 140.0
    depth[:, 199] = 150.0  # a blend of foreground and background at the edge
    xyz, _, rays = depth_to_points(cam, img.pose, depth, 1)
    inc = incidence_deg(grid_normals(xyz, rays, 1), rays)
    assert np.nanmax(inc[50:250, 20:180]) < 25.0  # a plane facing the camera: the off-axis angle
    assert (inc[50:250, 199] > 82.0).all()


def test_local_outliers_keep_sparse_surfaces():
    """Blunders above a plane are found; a part of the plane sampled ten times more sparsely (a facade seen by
    one master next to a roof seen by many) is kept, which a global distance threshold removes."""
    rng = np.random.default_rng(2)
    dense = np.column_stack([rng.uniform(0, 50, 20000), rng.uniform(0, 50, 20000), rng.normal(0, 0.02, 20000)])
    sparse = np.column_stack([rng.uniform(50, 100, 2000), rng.uniform(0, 50, 2000), rng.normal(0, 0.02, 2000)])
    blunders = np.column_stack([rng.uniform(0, 100, 20), rng.uniform(0, 50, 20), rng.uniform(5, 20, 20)])
    xyz = np.vstack([blunders, dense, sparse]) + [500000.0, 5400000.0, 100.0]
    out = local_outliers(xyz)
    assert out[:20].all()
    assert out[20:20020].mean() < 0.01 and out[20020:].mean() < 0.01
    o3d = pytest.importorskip("open3d")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz - xyz.mean(axis=0)))
    _, keep = pcd.remove_statistical_outlier(nb_neighbors=16, std_ratio=2.5)
    global_out = np.ones(len(xyz), bool)
    global_out[np.asarray(keep)] = False
    assert global_out[20020:].mean() > 0.2  # the global threshold takes a quarter of the sparse surface for noise


def test_intersection_error_grows_with_orientation_error(nadir_oblique_block):
    block, _ = nadir_oblique_block
    m = block.images["img01"]
    cam = block.camera_of(m)
    rng = np.random.default_rng(3)
    uv = np.column_stack([rng.uniform(50, 350, 200), rng.uniform(50, 250, 200)])
    depth = np.full(200, 160.0)
    slaves = [(block.images[s].pose, depth) for s in ("img00", "img02")]
    used = [p for p, _ in slaves]
    shifted = [Pose(p.R, p.C + [0.3, -0.2, 0.0]) for p in used]
    exact, worse = intersection_errors(uv, cam, m.pose, slaves, [(m.pose, used), (m.pose, shifted)])
    assert np.nanmax(exact) < 1e-6
    assert 0.05 < np.nanmean(worse) < 0.4


def test_selection_covers_and_pairs_are_rectifiable(nadir_oblique_block):
    block, _ = nadir_oblique_block
    sel = select_pairs(block, dense_scene.GROUND_Z)
    views = {s.view for s in sel}
    assert views == {"nadir", "north"}
    for s in sel:
        assert 1 <= len(s.slaves) <= SelectionConfig().slaves_per_master
        assert all(block.images[x].view == s.view for x in s.slaves)
    nadir_masters = [s.master for s in sel if s.view == "nadir"]
    assert 2 <= len(nadir_masters) <= 4


def test_height_prior_leaves_room_for_a_tower(tmp_path):
    """Tie points of a town: ground at 100 m, roofs up to 112 m, and a 4 m x 4 m tower top at 128 m that only a
    handful of tie points see: the searched interval covers the tower, which the 99.5th percentile alone misses."""
    from oblique_city.core.dense.stage import DenseConfig, height_prior
    from oblique_city.core.model.tiepoints import TiePoints
    from oblique_city.core.pipeline import Workspace

    rng = np.random.default_rng(2)
    z = np.concatenate([100.0 + rng.normal(0, 0.3, 7000), rng.uniform(104, 112, 2990), np.full(10, 128.0)])
    ws = Workspace.create(tmp_path / "ws", crs="EPSG:32632")
    xyz = np.column_stack([rng.uniform(0, 100, len(z)), rng.uniform(0, 100, len(z)), z])
    (ws.root / "matching").mkdir()
    TiePoints(xyz, np.zeros(0), np.zeros(0), np.zeros((0, 2)), []).save(str(ws.path("matching", "ties.npz")))
    lo, hi, ground = height_prior(ws, None, DenseConfig())
    assert np.percentile(z, 99.5) + 10.0 < 128.0 < hi < 150.0
    assert lo < 99.0 and abs(ground - 100.0) < 1.0

"""Connectivity graph, guided matching, verification, tracks and SIFT on rendered views of a textured plane; the
stage's pair matching in worker processes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from oblique_city.core.geometry.projection import intersect_with_plane_z, project
from oblique_city.core.matching.features import (
    MatchOptions,
    band_candidates,
    descriptor_distances,
    epipolar_segments,
    guided_match,
    segment_distance,
    sift_features,
    verify,
)
from oblique_city.core.matching.graph import GraphOptions, build_graph, convex_overlap, footprints
from oblique_city.core.matching.stage import FEATURES_VERSION, PAIRS_PER_UNIT, MatchConfig, pair_counts, run
from oblique_city.core.matching.tracks import build_tracks
from oblique_city.core.model import CameraModel, Image, ImageBlock, Pose, TiePoints
from oblique_city.core.pipeline import RunContext, Workspace
from oblique_city.core.pipeline.executor import Executor
from oblique_city.core.simulate.observations import SimulationConfig, look_rotation, simulate_block


@pytest.fixture(scope="module")
def small_sim():
    return simulate_block(SimulationConfig(n_images=150, strips=2, tie_density=0.0002, n_ground_points=0, seed=4))


def test_graph_edges_are_exactly_the_overlapping_similar_pairs(small_sim):
    block = small_sim.block
    opt = GraphOptions(min_overlap=0.25, max_axis_angle_deg=50.0, z_ref=100.0, max_neighbours=1000)
    g = build_graph(block, opt)
    ids = g.image_ids
    fps = footprints(block, ids, 100.0)
    expected = set()
    for a in range(len(ids)):
        for b in range(a + 1, len(ids)):
            ia, ib = block.images[ids[a]], block.images[ids[b]]
            similar = (ia.pose.R[2] @ ib.pose.R[2] >= np.cos(np.radians(50.0))) or "nadir" in (ia.view, ib.view)
            if similar and convex_overlap(fps[a], fps[b]) >= 0.25:
                expected.add((a, b))
    assert set(map(tuple, g.edges.tolist())) == expected
    assert len(expected) > 50
    # an east view never pairs with a west view; nadir images pair with obliques
    views = {(block.images[ids[a]].view, block.images[ids[b]].view) for a, b in g.edges}
    assert ("east", "west") not in views and ("west", "east") not in views
    assert any("nadir" in v and v != ("nadir", "nadir") for v in views)
    # edges carry the shared tracks of the tie points; weak ones are dropped
    g.matches = pair_counts(small_sim.ties, ids, g.edges)
    n_before = len(g.edges)
    dropped = g.drop_weak(10)
    assert len(g.edges) == n_before - dropped and np.all(g.matches >= 10)
    assert g.from_dict(g.to_dict(block)).edges.tolist() == g.edges.tolist()


def _two_views():
    cam = CameraModel(id="c", width=1200, height=900, fx=1500.0, fy=1500.0, cx=599.5, cy=449.5, k1=-0.03)
    down = np.array([0.0, 0.0, -1.0])
    pa = Pose(look_rotation(down, np.array([0.0, -1.0, 0.0])), [0.0, 0.0, 500.0])
    pb = Pose(look_rotation(down + np.array([0.15, 0.0, 0.0]), np.array([0.0, -1.0, 0.0])), [90.0, 10.0, 505.0])
    return cam, pa, pb


def _seen_by_both(cam: CameraModel, pa: Pose, pb: Pose, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(k, 2)`` in A and in B of the points among ``n`` random ones over the scene that both images see."""
    xyz = np.column_stack([rng.uniform(-100, 180, n), rng.uniform(-120, 120, n), rng.uniform(0, 30, n)])
    uva, _ = project(cam, pa, xyz)
    uvb, _ = project(cam, pb, xyz)
    ok = cam.contains(uva) & cam.contains(uvb)
    return uva[ok], uvb[ok]


def test_guided_matching_rejects_planted_wrong_matches():
    rng = np.random.default_rng(1)
    cam, pa, pb = _two_views()
    uva, uvb = _seen_by_both(cam, pa, pb, 800, rng)
    uva, uvb = uva + rng.normal(0, 0.3, uva.shape), uvb + rng.normal(0, 0.3, uvb.shape)
    n = len(uva)
    des = rng.normal(size=(n, 128)).astype(np.float32)
    des_b = des + rng.normal(0, 0.05, des.shape).astype(np.float32)
    # plant wrong correspondences: 60 points of B exchange descriptors with points far away (a permutation)
    wrong = rng.choice(n, 60, replace=False)
    wrong = wrong[np.argsort(uvb[wrong, 0])]
    partner = np.roll(wrong, 30)
    assert np.all(np.linalg.norm(uvb[wrong] - uvb[partner], axis=1) > 100)
    des_b[wrong] = des[partner] + rng.normal(0, 0.05, (len(wrong), 128)).astype(np.float32)
    opt = MatchOptions(band_px=15.0, z_lo=-5.0, z_hi=40.0)
    m = guided_match(uva, des, uvb, des_b, cam, pa, cam, pb, opt)
    correct = m[:, 0] == m[:, 1]
    assert correct.all(), f"{(~correct).sum()} wrong matches survived"
    assert len(m) >= 0.9 * (n - 2 * len(wrong))
    # without the guidance the descriptors alone would accept the planted pairs
    d = np.linalg.norm(des[partner][:, None] - des_b[None], axis=2)
    assert np.all(np.argmin(d, axis=1) == wrong)
    # verification keeps the right ones and drops matches moved off the epipolar geometry
    a, b = uva[m[:, 0]], uvb[m[:, 1]].copy()
    b[:20] += rng.choice([-1, 1], (20, 2)) * rng.uniform(6, 12, (20, 2))
    inl = verify(a, b, cam, cam, 1.5)
    assert not inl[:20].any() and inl[20:].mean() > 0.95


def test_epipolar_band_widens_with_coarse_navigation_data():
    """A low-grade GNSS/IMU (1 degree, 10 m) moves the epipolar segments by tens of pixels: the fixed 25 px band
    loses the matches, the band from the images' prior sigmas (3 sigma) keeps them, all correct. Images with
    survey-grade sigmas, or none, keep ``band_px``."""
    from oblique_city.core.geometry.rotations import rotvec_to_matrix
    from oblique_city.core.matching.stage import pair_bands, pair_sigmas

    rng = np.random.default_rng(3)
    cam, pa, pb = _two_views()
    uva, uvb = _seen_by_both(cam, pa, pb, 1500, rng)
    des = rng.normal(size=(len(uva), 128)).astype(np.float32)
    # the navigation data: image B turned by 1 degree and moved 10 m
    pb_nav = Pose(rotvec_to_matrix(np.radians([0.0, 1.0, 0.0])) @ pb.R, pb.C + np.array([0.0, 10.0, 0.0]))
    block = ImageBlock(crs="EPSG:25832")
    block.add_camera(cam)
    coarse = {"sigma_position": np.full(3, 10.0), "sigma_attitude": np.radians(np.full(3, 1.0))}
    block.add_image(Image("a", "c", pose_approx=pa, **coarse))
    block.add_image(Image("b", "c", pose_approx=pb_nav, **coarse))
    band = pair_bands(block, ["a", "b"], np.array([[0, 1]]), 25.0, 0.0)[0]
    assert 160.0 < band < 170.0  # 3 sqrt(2) x 1500 px x hypot(1 deg, 10 m / 500 m)
    # the pair's relative navigation errors, which coarse_guided_match takes as its correction's prior
    np.testing.assert_allclose(pair_sigmas(block, ["a", "b"], np.array([[0, 1]])),
                               [[np.radians(1.0) * np.sqrt(2), 10.0 * np.sqrt(2)]])
    found = {}
    for width in (25.0, band):
        m = guided_match(uva, des, uvb, des, cam, pa, cam, pb_nav, MatchOptions(band_px=width, z_lo=-5.0, z_hi=40.0))
        found[width] = (int(np.sum(m[:, 0] == m[:, 1])), int(np.sum(m[:, 0] != m[:, 1])))
    assert found[25.0][0] < 0.5 * len(uva), found  # most true partners lie outside the narrow band
    assert found[band][0] > 0.95 * len(uva) and found[band][1] == 0, found
    for img in block.images.values():
        img.sigma_position, img.sigma_attitude = np.full(3, 0.05), np.radians(np.full(3, 0.005))
    assert pair_bands(block, ["a", "b"], np.array([[0, 1]]), 25.0, 0.0)[0] == 25.0
    for img in block.images.values():
        img.sigma_position = img.sigma_attitude = None
    assert pair_bands(block, ["a", "b"], np.array([[0, 1]]), 25.0, 0.0)[0] == 25.0


def _coarse_pair(rng, n: int):
    """Two views, their ``n`` random scene points' pixels with 0.3 px noise, descriptors, and B's navigation data
    turned by 1 degree and moved by 10 m."""
    from oblique_city.core.geometry.rotations import rotvec_to_matrix

    cam, pa, pb = _two_views()
    uva, uvb = _seen_by_both(cam, pa, pb, n, rng)
    uva, uvb = uva + rng.normal(0, 0.3, uva.shape), uvb + rng.normal(0, 0.3, uvb.shape)
    des = rng.normal(size=(len(uva), 128)).astype(np.float32)
    pb_nav = Pose(rotvec_to_matrix(np.radians([0.6, 1.0, -0.4])) @ pb.R, pb.C + np.array([-6.0, 10.0, 4.0]))
    return cam, pa, pb_nav, uva, uvb, des


def test_coarse_navigation_data_corrected_from_a_few_matches_then_matched_in_the_narrow_band():
    """With B's navigation data 1 degree and 10 m off, the matches by descriptor alone over the whole image correct
    B's pose, and the 25 px band around the corrected epipolar segments finds the matches. A repeated element
    (keypoints of B sharing a descriptor, far apart) fails the ratio test over the whole image but is matched in
    the narrow band."""
    from oblique_city.core.matching.navigation import coarse_guided_match, corrected_pose, descriptor_matches

    rng = np.random.default_rng(5)
    cam, pa, pb_nav, uva, uvb, des = _coarse_pair(rng, 1500)
    n = len(uva)
    far = np.flatnonzero(np.linalg.norm(uvb[:100] - uvb[100:200], axis=1) > 150)
    repeats = np.r_[far, 100 + far]
    des[100 + far] = des[far]  # a repeated element: pairs of points far apart share a descriptor (up to noise)
    des_a = des + rng.normal(0, 0.05, des.shape).astype(np.float32)
    des_b = des + rng.normal(0, 0.05, des.shape).astype(np.float32)
    coarse = descriptor_matches(des_a, des_b, 0.85)
    assert len(far) > 50 and np.isin(repeats, coarse[:, 0]).mean() < 0.05  # the repeats fail the ratio test
    opt = MatchOptions(z_lo=-5.0, z_hi=40.0)
    s0, s1 = epipolar_segments(uva, cam, pa, cam, pb_nav, opt.z_lo, opt.z_hi)
    assert np.median(segment_distance(uvb, s0, s1)) > 20.0  # the navigation data's segments miss the matches
    sigma_att, sigma_pos = np.radians(1.0) * np.sqrt(2), 10.0 * np.sqrt(2)
    pose, sigma = corrected_pose(uva[:60], uvb[:60], cam, pa, cam, pb_nav, opt.z_lo, opt.z_hi, sigma_att,
                                 sigma_pos)
    s0, s1 = epipolar_segments(uva, cam, pa, cam, pose, opt.z_lo, opt.z_hi)
    off = segment_distance(uvb, s0, s1)
    assert np.median(off) < 1.0 and np.percentile(off, 99) < 3.0 * 25.0 / 3.0, np.percentile(off, [50, 99])
    assert sigma < 25.0 / 3.0
    m = coarse_guided_match(uva, des_a, uvb, des_b, cam, pa, cam, pb_nav, opt, 165.0, sigma_att, sigma_pos)
    right = m[:, 0] == m[:, 1]
    assert right.all() and len(m) > 0.95 * n, (len(m), n, int((~right).sum()))
    assert np.isin(repeats, m[:, 0]).mean() > 0.95


def test_coarse_pair_without_enough_matches_gets_none():
    """Fewer shared points than the correction needs: no matches rather than matches from the wide band."""
    from oblique_city.core.matching.navigation import MIN_COARSE, coarse_guided_match

    rng = np.random.default_rng(6)
    cam, pa, pb_nav, uva, uvb, des = _coarse_pair(rng, 1500)
    des_b = rng.normal(size=des.shape).astype(np.float32)  # unrelated features ...
    des_b[:MIN_COARSE - 2] = des[:MIN_COARSE - 2]  # ... but for a few shared ones
    m = coarse_guided_match(uva, des, uvb, des_b, cam, pa, cam, pb_nav, MatchOptions(z_lo=-5.0, z_hi=40.0), 165.0,
                            np.radians(1.4), 14.0)
    assert len(m) == 0


def test_descriptor_matches_are_the_mutual_ratio_test_matches_of_brute_force():
    from oblique_city.core.matching.navigation import descriptor_matches

    rng = np.random.default_rng(7)
    des_b = np.round(rng.uniform(0, 60, (700, 128))).astype(np.float32)
    des_a = des_b[rng.permutation(700)[:500]] + np.round(rng.normal(0, 8, (500, 128))).astype(np.float32)
    des_a[:40] = np.round(rng.uniform(0, 60, (40, 128)))  # no partner
    d = np.linalg.norm(des_a[:, None].astype(np.float64) - des_b[None], axis=2)
    order = np.argsort(d, axis=1)
    nearest = order[:, 0]
    passed = d[np.arange(500), nearest] <= 0.85 * d[np.arange(500), order[:, 1]]
    mutual = np.argmin(d, axis=0)[nearest] == np.arange(500)
    expected = np.stack([np.flatnonzero(passed & mutual), nearest[passed & mutual]], 1)
    got = descriptor_matches(des_a, des_b, 0.85, rows=64)
    assert 300 < len(expected) < 500
    np.testing.assert_array_equal(got, expected)


def test_verification_without_a_model_keeps_no_match():
    """68 coarse matches of a demo pair, for which OpenCV's MAGSAC++ asserts that no sample gave a model: no inlier,
    no exception (it stopped the ``match`` stage)."""
    from pathlib import Path

    with np.load(Path(__file__).parents[1] / "data" / "usac_no_model.npz") as z:
        a, b = z["a"], z["b"]
    cam = CameraModel(id="c", width=1400, height=1050, fx=2087.0, fy=2087.0, cx=699.5, cy=524.5)
    assert not verify(a, b, cam, cam, 1.5).any()


def test_tracks_join_chains_and_drop_inconsistent_ones():
    kp = [np.arange(8, dtype=float).reshape(4, 2) + 10 * i for i in range(4)]
    matches = {
        (0, 1): np.array([[0, 0], [1, 1], [2, 2]]),
        (1, 2): np.array([[0, 0], [1, 1], [2, 3]]),
        (2, 3): np.array([[0, 0], [3, 3]]),
        (0, 2): np.array([[2, 2]]),  # track of keypoint 2 now holds keypoints 2 and 3 of image 2: inconsistent
    }
    t = build_tracks(kp, matches, ["a", "b", "c", "d"])
    rays = t.ray_counts()
    assert sorted(rays.tolist()) == [3, 4]
    four = np.flatnonzero(rays == 4)[0]
    obs = t.obs_track == four
    assert t.obs_image[obs].tolist() == [0, 1, 2, 3]
    np.testing.assert_array_equal(t.obs_uv[obs][0], kp[0][0])
    t3 = build_tracks(kp, matches, ["a", "b", "c", "d"], min_rays=4)
    assert t3.n_tracks == 1


def test_sift_guided_matching_on_rendered_views():
    """Two views of a textured plane (rendered by the plane homography); SIFT + guided matching + verification
    give correspondences that agree with the true geometry to a pixel."""
    import cv2

    rng = np.random.default_rng(3)
    cam = CameraModel(id="c", width=640, height=480, fx=800.0, fy=800.0, cx=319.5, cy=239.5)
    down = np.array([0.0, 0.0, -1.0])
    pa = Pose(look_rotation(down, np.array([0.0, -1.0, 0.0])), [0.0, 0.0, 300.0])
    pb = Pose(look_rotation(down + np.array([0.1, 0.05, 0.0]), np.array([0.0, -1.0, 0.0])), [60.0, 0.0, 300.0])
    tex = cv2.GaussianBlur((rng.random((1200, 1200)) * 255).astype(np.uint8), (0, 0), 2.0)
    tex = cv2.equalizeHist(tex)

    def render(pose):
        uv = np.stack(np.meshgrid(np.arange(640.0), np.arange(480.0)), -1).reshape(-1, 2)
        g = intersect_with_plane_z(cam, pose, uv, 0.0)
        mx = ((g[:, 0] + 300) / 0.5).reshape(480, 640).astype(np.float32)
        my = ((300 - g[:, 1]) / 0.5).reshape(480, 640).astype(np.float32)
        return cv2.remap(tex, mx, my, cv2.INTER_LINEAR)

    ua, da = sift_features(render(pa), 3000)
    ub, db = sift_features(render(pb), 3000)
    m = guided_match(ua, da, ub, db, cam, pa, cam, pb, MatchOptions(band_px=8.0, z_lo=-2.0, z_hi=2.0))
    m = m[verify(ua[m[:, 0]], ub[m[:, 1]], cam, cam, 1.0)]
    assert len(m) > 200
    pred, _ = project(cam, pb, intersect_with_plane_z(cam, pa, ua[m[:, 0]], 0.0))
    err = np.linalg.norm(pred - ub[m[:, 1]], axis=1)
    assert np.median(err) < 0.5 and np.percentile(err, 99) < 2.0


def test_sift_keypoints_use_the_pixel_centre_origin():
    """A keypoint of an image and the same keypoint found in the image turned by 180 degrees map onto each other
    (``x -> w - 1 - x``) only when the keypoints are in the pixel-centre origin: OpenCV's raw positions, 0.25 px
    off in both axes, would differ by 0.5 px. Median over thousands of keypoints, so 0.05 px is a wide margin."""
    import cv2

    rng = np.random.default_rng(5)
    img = cv2.GaussianBlur((rng.random((480, 640)) * 255).astype(np.uint8), (0, 0), 1.5)
    img = cv2.equalizeHist(img)
    ua, _ = sift_features(img, 4000)
    ub, _ = sift_features(np.ascontiguousarray(img[::-1, ::-1]), 4000)
    ub = np.array([639.0, 479.0]) - ub
    from scipy.spatial import cKDTree

    d, i = cKDTree(ub).query(ua)
    close = d < 1.0
    assert close.sum() > 500
    assert np.all(np.abs(np.median(ua[close] - ub[i[close]], axis=0)) < 0.05)


def _feature_workspace(path) -> tuple[Workspace, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """A workspace with a 4 x 5 grid of nadir views and their feature cache files: noisy projections of 3000 points
    (descriptors of their point plus noise) among 300 random keypoints, in shuffled order. Returns the workspace and
    each image's keypoints and descriptors."""
    rng = np.random.default_rng(7)
    cam = CameraModel(id="c", width=1200, height=900, fx=1500.0, fy=1500.0, cx=599.5, cy=449.5, k1=-0.03)
    block = ImageBlock(crs="EPSG:25832")
    block.add_camera(cam)
    xyz = np.column_stack([rng.uniform(-250, 550, 3000), rng.uniform(-200, 650, 3000), rng.uniform(0, 30, 3000)])
    des = rng.normal(size=(3000, 128)).astype(np.float32)
    feats = {}
    for k in range(20):
        tilt = rng.normal(0, 0.02, 3) + [0.0, 0.0, -1.0]
        pose = Pose(look_rotation(tilt, np.array([0.0, -1.0, 0.0])), [100.0 * (k % 4), 120.0 * (k // 4), 500.0])
        block.add_image(Image(id=f"i{k:02d}", camera_id="c", pose_approx=pose))
        uv, _ = project(cam, pose, xyz)
        seen = np.flatnonzero(cam.contains(uv))
        uv = np.vstack([uv[seen] + rng.normal(0, 0.3, (len(seen), 2)), rng.uniform([0, 0], [1199, 899], (300, 2))])
        d = np.vstack([des[seen] + rng.normal(0, 0.3, (len(seen), 128)), rng.normal(size=(300, 128))])
        order = rng.permutation(len(uv))
        feats[f"i{k:02d}"] = uv[order], d[order].astype(np.float32)
    ws = Workspace.create(path, "EPSG:25832")
    ws.save_block(block)
    (path / "matching" / "features").mkdir(parents=True)
    for k, iid in enumerate(ws.load_block(adjusted=False).images):
        np.savez(path / "matching" / "features" / f"{k:06d}.npz", uv=feats[iid][0], des=feats[iid][1], image=iid,
                 max_features=6000, version=FEATURES_VERSION)
    return ws, feats


def test_match_stage_in_worker_processes_gives_the_tie_points_of_pairs_matched_one_by_one(tmp_path):
    """The stage's pair matching, cut into executor units, gives in worker processes and inline the matches of
    the graph edges matched one after the other: the same graph counts and tie point arrays."""
    ws, feats = _feature_workspace(tmp_path / "ws")
    cfg = MatchConfig(z_ref=0.0, height_range=40.0, lsm_refine=False, max_features=6000)
    got = {}
    for mode in ("inline", "processes"):
        with Executor(mode, workers=2) as ex:
            run(ws, cfg, RunContext(executor=ex))
        graph = json.loads(ws.path("matching", "graph.json").read_text())
        got[mode] = graph, TiePoints.load(str(ws.path("matching", "ties.npz")))
    block = ws.load_block(adjusted=False)
    g = build_graph(block, GraphOptions(min_overlap=cfg.min_overlap, max_axis_angle_deg=cfg.max_axis_angle_deg,
                                        z_ref=0.0, max_neighbours=cfg.max_neighbours))
    assert len(g.edges) > 3 * PAIRS_PER_UNIT  # several units, finishing in any order in the processes
    opt = MatchOptions(ratio=cfg.ratio, band_px=cfg.band_px, z_lo=-5.0, z_hi=40.0, ransac_px=cfg.ransac_px)
    ids, matches, counts = g.image_ids, {}, {}
    for a, b in g.edges:
        (ua, da), (ub, db) = feats[ids[a]], feats[ids[b]]
        ca, pa, pb = block.camera_of(ids[a]), block.images[ids[a]].pose_approx, block.images[ids[b]].pose_approx
        m = guided_match(ua, da, ub, db, ca, pa, ca, pb, opt)
        m = m[verify(ua[m[:, 0]], ub[m[:, 1]], ca, ca, opt.ransac_px)]
        counts[(int(a), int(b))] = len(m)
        if len(m) >= cfg.min_matches:
            matches[(int(a), int(b))] = m
    ref = build_tracks([feats[i][0] for i in ids], matches, ids, min_rays=cfg.min_rays)
    assert ref.n_tracks > 1000
    for graph, ties in got.values():
        assert {(e["a"], e["b"]): e["matches"] for e in graph["edges"]} == {
            k: n for k, n in counts.items() if n >= cfg.min_matches}
        for name in ("xyz", "obs_track", "obs_image", "obs_uv"):
            np.testing.assert_array_equal(getattr(ties, name), getattr(ref, name))
        assert ties.image_ids == ref.image_ids


def test_match_stage_from_coarse_navigation_data_finds_the_tie_points_of_the_true_poses(tmp_path):
    """Every image's navigation data turned by 1 degree and moved by 10 m, with those sigmas: every pair is matched
    after correcting its pose (the band the sigmas give is about 180 px), and the stage finds the tie point
    observations that matching from the true poses finds."""
    from oblique_city.core.geometry.rotations import rotvec_to_matrix

    ws, _ = _feature_workspace(tmp_path / "ws")
    cfg = MatchConfig(z_ref=0.0, height_range=40.0, lsm_refine=False, max_features=6000)
    run(ws, cfg, RunContext())
    ref = TiePoints.load(str(ws.path("matching", "ties.npz")))
    block = ws.load_block(adjusted=False)
    rng = np.random.default_rng(8)
    for img in block.images.values():
        p = img.pose_approx
        img.pose_approx = Pose(rotvec_to_matrix(np.radians(rng.normal(0, 1.0, 3))) @ p.R, p.C + rng.normal(0, 10, 3))
        img.sigma_position, img.sigma_attitude = np.full(3, 10.0), np.radians(np.full(3, 1.0))
    ws.save_block(block)
    result = run(ws, cfg, RunContext())
    got = TiePoints.load(str(ws.path("matching", "ties.npz")))
    assert result.metrics["corrected_pairs"] == result.metrics["edges"] > 20

    def observations(t: TiePoints) -> set:
        return {(int(i), round(float(u), 3), round(float(v), 3)) for i, (u, v) in zip(t.obs_image, t.obs_uv)}

    found, truth = observations(got), observations(ref)
    assert len(found & truth) > 0.95 * len(truth), (len(found & truth), len(truth))
    assert len(found - truth) < 0.01 * len(truth), len(found - truth)


def test_segments_clipped_to_the_image_and_rays_through_the_projection_centre_cost_nothing():
    """Liang-Barsky clipping against brute-force sampling; a pair where A's rays pass next to B's projection centre
    (segments millions of pixels long, one through the centre itself) is matched without sampling them (it
    exhausted the memory)."""
    from oblique_city.core.matching.features import clip_segments

    rng = np.random.default_rng(9)
    s0, s1 = rng.uniform(-300, 1300, (400, 2)), rng.uniform(-300, 1300, (400, 2))
    s1[:20] = s0[:20]  # points
    s1[20:40, 0] = s0[20:40, 0]  # vertical
    s1[40] = [np.nan, 3.0]
    lo, hi = np.array([0.0, 0.0]), np.array([999.0, 799.0])
    c0, c1, inside = clip_segments(s0, s1, lo, hi)
    t = np.linspace(0, 1, 2001)
    for k in range(400):
        pts = s0[k] + t[:, None] * (s1[k] - s0[k])
        hit = np.all((pts >= lo) & (pts <= hi), axis=1)
        if k == 40:
            assert not inside[k]
            continue
        assert inside[k] == hit.any() or abs(t[hit].min(initial=0) - t[hit].max(initial=0)) < 1e-3, k
        if hit.any():
            length = np.linalg.norm(s1[k] - s0[k])
            tol = max(length * 1e-3, 1e-6)
            assert np.linalg.norm(c0[k] - pts[hit][0]) <= tol and np.linalg.norm(c1[k] - pts[hit][-1]) <= tol, k
    cam = CameraModel(id="c", width=1000, height=800, fx=1200.0, fy=1200.0, cx=499.5, cy=399.5)
    pa = Pose(look_rotation(np.array([0.0, 0.0, -1.0]), np.array([0.0, -1.0, 0.0])), [0.0, 0.0, 500.0])
    pb = Pose(look_rotation(np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])), [0.0, 0.0, 100.0])
    uu, vv = np.meshgrid(np.linspace(480, 520, 41), np.linspace(380, 420, 41))
    # and rays that meet z = 100 m a few nanometres in front of B's centre
    uva = np.vstack([np.column_stack([uu.ravel(), vv.ravel()]), [[cam.cx + 1e-9, cam.cy + 5.0]] * 3])
    s0, s1 = epipolar_segments(uva, cam, pa, cam, pb, 0.0, 100.0)
    assert np.nanmax(np.linalg.norm(s1 - s0, axis=1)) > 1e12
    des = rng.normal(size=(len(uva), 128)).astype(np.float32)
    uvb = rng.uniform([0, 0], [999, 799], (len(uva), 2))
    m = guided_match(uva, des, uvb, des, cam, pa, cam, pb, MatchOptions(band_px=25.0, z_lo=0.0, z_hi=100.0))
    assert m.shape[1] == 2


def test_band_candidates_hold_every_keypoint_in_the_band_once_and_descriptor_distances_are_exact():
    """Against brute force on random keypoints and segments (short, long, degenerate, some not searched): every
    keypoint within the band is a candidate, none twice, grouped by segment in ascending order. The matrix-product
    descriptor distances equal the rows' differences exactly for whole-number descriptors (as OpenCV's SIFT gives)
    and closely for others."""
    rng = np.random.default_rng(5)
    uv_b = rng.uniform(0, 1200, (3000, 2))
    s0 = rng.uniform(-50, 1250, (400, 2))
    s1 = s0 + rng.normal(0, 1, (400, 2)) * rng.choice([0.0, 10.0, 150.0, 600.0], (400, 1))
    ia = np.flatnonzero(rng.random(400) < 0.8)
    band = 25.0
    a, b = band_candidates(uv_b, s0, s1, ia, band)
    key = a * len(uv_b) + b
    assert np.all(np.diff(a) >= 0) and len(np.unique(key)) == len(key)  # grouped by segment, no repeats
    assert set(np.unique(a)) <= set(ia)
    aa, bb = np.repeat(ia, len(uv_b)), np.tile(np.arange(len(uv_b)), len(ia))
    within = segment_distance(uv_b[bb], s0[aa], s1[aa]) <= band
    assert np.isin(aa[within] * len(uv_b) + bb[within], key).all()
    assert len(key) < 3 * within.sum()  # cells, not the whole image
    des_a = np.round(rng.uniform(0, 60, (400, 128))).astype(np.float32)  # |d|^2 < 2^22, as SIFT
    des_b = np.round(rng.uniform(0, 60, (3000, 128))).astype(np.float32)
    ref = np.linalg.norm(des_a[a] - des_b[b], axis=1)
    assert np.array_equal(descriptor_distances(des_a, des_b, a, b, rows=64), ref)
    frac = des_a + 0.25
    assert np.allclose(descriptor_distances(frac, des_b, a, b), np.linalg.norm(frac[a] - des_b[b], axis=1))

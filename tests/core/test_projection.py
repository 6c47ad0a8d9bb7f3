"""Projection agrees with OpenCV (pixel origin at the centre of the top-left pixel), distortion inverts,
rays intersect back to the points."""

import cv2
import numpy as np

from oblique_city.core.geometry.intersection import intersect_rays, intersect_tracks
from oblique_city.core.geometry.projection import (
    backproject_depth,
    image_footprint,
    intersect_with_plane_z,
    pixel_rays,
    project,
)
from oblique_city.core.model import CameraModel, Pose


def _points(pose: Pose, n: int = 500, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.35, 0.35, (n, 2))
    z = rng.uniform(400.0, 900.0, n)
    xc = np.concatenate([xy * z[:, None], z[:, None]], axis=1)
    return xc @ pose.R + pose.C


def test_projection_equals_opencv(camera: CameraModel, utm_block) -> None:
    for img in utm_block.images.values():
        pose = img.pose_approx
        xyz = _points(pose)
        uv, depth = project(camera, pose, xyz)
        rvec = cv2.Rodrigues(pose.R)[0]
        ref = cv2.projectPoints(xyz - pose.C, rvec, np.zeros(3), camera.K, camera.dist_coeffs)[0][:, 0]
        assert np.abs(uv - ref).max() < 1e-6
        assert np.all(depth > 0)


def test_pixel_origin_is_centre_of_top_left_pixel() -> None:
    cam = CameraModel(id="c", width=4, height=3, fx=100.0, fy=100.0, cx=1.5, cy=1.0)
    pose = Pose(np.eye(3), np.zeros(3))
    # the principal point at (1.5, 1.0) is the image centre for a 4x3 image whose first pixel centre is 0
    uv, _ = project(cam, pose, np.array([[0.0, 0.0, 10.0]]))
    assert np.allclose(uv, [[1.5, 1.0]])
    assert np.allclose(cam.contains(np.array([[-0.5, -0.5], [3.5, 2.5], [-0.6, 0.0]])), [True, True, False])


def test_distortion_inverts(camera: CameraModel) -> None:
    uv = np.stack(np.meshgrid(np.linspace(0, camera.width - 1, 25), np.linspace(0, camera.height - 1, 19)),
                  -1).reshape(-1, 2)
    back = camera.normalized_to_pixel(camera.pixel_to_normalized(uv))
    assert np.abs(back - uv).max() < 1e-8
    ref = cv2.undistortPointsIter(uv[:, None], camera.K, camera.dist_coeffs, None, None,
                                  (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))[:, 0]
    assert np.abs(camera.pixel_to_normalized(uv) - ref).max() < 1e-7


def test_rays_and_depth_round_trip(camera: CameraModel, utm_block) -> None:
    pose = utm_block.images["img1"].pose_approx
    xyz = _points(pose, 200, 1)
    uv, depth = project(camera, pose, xyz)
    assert np.abs(backproject_depth(camera, pose, uv, depth) - xyz).max() < 1e-6
    d = pixel_rays(camera, pose, uv)
    v = (xyz - pose.C) / np.linalg.norm(xyz - pose.C, axis=1, keepdims=True)
    assert np.abs(d - v).max() < 1e-9


def test_forward_intersection_recovers_points(camera: CameraModel, utm_block) -> None:
    rng = np.random.default_rng(3)
    xyz = np.column_stack([rng.uniform(500050, 500400, 200), rng.uniform(5399700, 5400000, 200),
                           rng.uniform(0, 40, 200)])
    origins, dirs, track = [], [], []
    for img in utm_block.images.values():
        uv, _ = project(camera, img.pose_approx, xyz)
        # distortion is only invertible inside the image (far outside, the polynomial folds back in)
        seen = camera.contains(uv) & camera.contains(project(camera, img.pose_approx, xyz, distort=False)[0])
        origins.append(np.repeat(img.pose_approx.C[None], seen.sum(), 0))
        dirs.append(pixel_rays(camera, img.pose_approx, uv[seen]))
        track.append(np.flatnonzero(seen))
    o, d, t = np.concatenate(origins), np.concatenate(dirs), np.concatenate(track)
    xyz_hat, dist = intersect_tracks(o, d, t, len(xyz))
    multi = np.bincount(t, minlength=len(xyz)) >= 2
    assert multi.sum() >= 10
    assert np.abs(xyz_hat[multi] - xyz[multi]).max() < 1e-5 and dist[multi[t]].max() < 1e-5
    assert np.isnan(xyz_hat[~multi]).all()
    k = int(np.flatnonzero(multi)[0])
    one, dist1 = intersect_rays(o[t == k], d[t == k])
    assert np.allclose(one, xyz[k], atol=1e-5) and dist1.max() < 1e-5


def test_footprint_of_nadir_image(camera: CameraModel) -> None:
    pose = Pose.from_opk(0.0, 0.0, 0.0, [100.0, 200.0, 1000.0])
    fp = image_footprint(camera, pose, 0.0)
    half_w = 1000.0 * (camera.width - 1 - camera.cx) / camera.fx
    assert fp[:, 0].max() < 100.0 + half_w * 1.1 and fp[:, 0].max() > 100.0 + half_w * 0.9
    pts = intersect_with_plane_z(camera, pose, np.array([[camera.cx, camera.cy]]), 0.0)
    assert np.allclose(pts, [[100.0, 200.0, 0.0]], atol=1e-9)

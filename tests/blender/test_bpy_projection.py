"""Blender's projection through an imported camera equals the core's within 0.01 px; the undistorted background
lines up with it.

Blender cameras are ideal pinholes, so the reference is the core's projection without distortion
(``project(..., distort=False)``); cameras with distortion show an image undistorted to that pinhole
(``addon.backgrounds``), checked here by moving a mark from its distorted to its ideal position.
"""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.geometry.projection import backproject_depth, project
from oblique_city.core.geometry.rotations import opk_to_cam_from_world
from oblique_city.core.model import CameraModel, Image, ImageBlock, Pose

pytestmark = pytest.mark.xdist_group("bpy")

CAMERAS = [
    # fx > fy, principal point left of and above the centre, pixel size known (real sensor width in Blender)
    CameraModel(id="a", width=1200, height=900, fx=1500.0, fy=1497.3, cx=611.3, cy=437.8, pixel_size_mm=0.0046),
    # fx < fy, principal point right of and below the centre, no pixel size (36 mm sensor)
    CameraModel(id="b", width=1000, height=1400, fx=2200.0, fy=2210.5, cx=480.6, cy=731.2),
    # a Maltese-cross-like oblique head with distortion (Blender ignores it; the test compares undistorted)
    CameraModel(id="c", width=1600, height=1200, fx=4000.0, fy=4001.0, cx=805.0, cy=590.5, k1=-0.05, k2=0.01),
]
POSES = [  # omega, phi, kappa (degrees), centre (UTM 32N)
    (0.0, 0.0, 12.0, (500000.0, 5400000.0, 1100.0)),
    (45.0, 3.0, -2.0, (500120.0, 5399300.0, 1100.0)),
    (-4.0, -44.0, 91.0, (500800.0, 5400050.0, 1100.0)),
    (1.0, 46.0, -88.0, (499300.0, 5399950.0, 1100.0)),
]


def make_block() -> ImageBlock:
    block = ImageBlock(crs="EPSG:32632")
    for cam in CAMERAS:
        block.add_camera(cam)
    for i in range(8):
        cam, (o, p, k, c) = CAMERAS[i % len(CAMERAS)], POSES[i % len(POSES)]
        block.add_image(Image(id=f"{cam.id}{i}", camera_id=cam.id,
                              pose_approx=Pose(opk_to_cam_from_world(*np.radians([o, p, k])), c)))
    return block


def test_blender_projection_equals_core(addon):
    bpy = addon
    from oblique_city.addon import builders, cameras

    block = make_block()
    scene = bpy.context.scene
    objects = builders.build_cameras(scene, block)
    rng = np.random.default_rng(7)
    worst = 0.0
    n_points = 0
    for image_id, obj in objects.items():
        cam, pose = block.camera_of(image_id), block.images[image_id].pose
        cameras.apply_render_settings(scene, obj)
        bpy.context.view_layer.update()
        # points seen inside the image (and a margin around it) at depths of a city below an aerial camera
        uv = rng.uniform([-50, -50], [cam.width + 50, cam.height + 50], (300, 2))
        xyz = backproject_depth(cam, pose, uv, rng.uniform(600.0, 2000.0, 300))
        uv_core, _ = project(cam, pose, xyz, distort=False)
        uv_blender = cameras.pixel_from_blender(scene, obj, xyz)
        worst = max(worst, float(np.abs(uv_blender - uv_core).max()))
        n_points += len(xyz)
    assert n_points == 2400  # 8 images x 300 points
    assert worst < 0.01, worst


def test_intrinsics_as_blender_shows_them(addon):
    """The focal length in millimetres is the real one when the pixel size is known."""
    bpy = addon
    from oblique_city.addon import cameras

    data = bpy.data.cameras.new("x")
    cameras.set_intrinsics(data, CAMERAS[0])
    assert data.lens == pytest.approx(1500.0 * 0.0046, rel=1e-6)
    assert data.sensor_width == pytest.approx(1200 * 0.0046, rel=1e-6)
    cameras.set_intrinsics(data, CAMERAS[1])
    assert data.sensor_width == 36.0 and data.lens == pytest.approx(2200.0 * 36.0 / 1000.0, rel=1e-6)


def _blob_centroid(image: np.ndarray, uv: np.ndarray, r: int = 8) -> np.ndarray:
    u0, v0 = np.round(uv).astype(int)
    win = image[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1].astype(np.float64)
    vv, uu = np.mgrid[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
    return np.array([(win * uu).sum() / win.sum(), (win * vv).sum() / win.sum()])


def test_undistorted_background_matches_blender_camera(tmp_path):
    """Marks drawn where the *distorted* camera sees world points land, after undistortion, where the Blender
    (pinhole) camera projects them: within 0.05 px, while the original image is off by pixels."""
    import cv2

    from oblique_city.addon.backgrounds import undistort_array

    cam = CameraModel(id="d", width=1200, height=900, fx=1500.0, fy=1502.5, cx=611.3, cy=437.8,
                      k1=-0.08, k2=0.02, p1=3e-4, p2=-2e-4)
    pose = Pose(opk_to_cam_from_world(0.0, 0.0, 0.0), (0.0, 0.0, 1000.0))
    uv_ideal = np.array([[60.0, 50.0], [1130.0, 70.0], [600.0, 450.0], [90.0, 840.0], [1120.0, 830.0]])
    xyz = backproject_depth(cam.with_distortion(), pose, uv_ideal, np.full(len(uv_ideal), 1000.0))
    uv_distorted, _ = project(cam, pose, xyz, distort=True)
    assert np.abs(uv_distorted - uv_ideal).max() > 3.0  # the distortion matters at the corners

    # Gaussian marks (sigma 1.5 px) at the distorted positions, integrated over each pixel (8 x 8 samples)
    s, r = 8, 12
    image = np.zeros((cam.height, cam.width), np.uint16)
    for u, v in uv_distorted:
        u0, v0 = int(round(u)) - r, int(round(v)) - r
        vv, uu = np.mgrid[0:(2 * r + 1) * s, 0:(2 * r + 1) * s]
        u_hi, v_hi = u0 + (uu + 0.5) / s - 0.5, v0 + (vv + 0.5) / s - 0.5
        g = np.exp(-((u_hi - u) ** 2 + (v_hi - v) ** 2) / (2 * 1.5 ** 2))
        win = g.reshape(2 * r + 1, s, 2 * r + 1, s).mean(axis=(1, 3))
        image[v0:v0 + 2 * r + 1, u0:u0 + 2 * r + 1] = (win * 60000).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "marks.png"), image)

    undistorted = undistort_array(cv2.imread(str(tmp_path / "marks.png"), cv2.IMREAD_UNCHANGED), cam)
    found = np.array([_blob_centroid(undistorted, uv) for uv in uv_ideal])
    assert np.abs(found - uv_ideal).max() < 0.05

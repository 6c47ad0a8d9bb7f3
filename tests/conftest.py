"""Shared fixtures: temporary workspaces and small synthetic cameras/blocks built from known geometry."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.geometry.rotations import opk_to_cam_from_world
from oblique_city.core.model import CameraModel, Image, ImageBlock, Pose


@pytest.fixture
def camera() -> CameraModel:
    """A camera with fx != fy, an off-centre principal point and aerial-size distortion."""
    return CameraModel(id="cam", width=1200, height=900, fx=1500.0, fy=1502.5, cx=611.3, cy=437.8,
                       k1=-0.05, k2=0.01, k3=-0.001, p1=2e-4, p2=-1e-4, pixel_size_mm=0.0046)


@pytest.fixture
def utm_block(camera: CameraModel) -> ImageBlock:
    """Three images over UTM 32N coordinates (500000, 5400000), one nadir and two obliques."""
    block = ImageBlock(crs="EPSG:32632")
    block.add_camera(camera)
    poses = [
        (0.0, 0.0, 0.3, (500000.0, 5400000.0, 800.0)),
        (np.radians(45.0), 0.0, 0.0, (500010.0, 5399500.0, 800.0)),
        (0.0, np.radians(-45.0), np.radians(90.0), (500500.0, 5400020.0, 800.0)),
    ]
    for i, (o, p, k, c) in enumerate(poses):
        block.add_image(Image(id=f"img{i}", camera_id="cam", file=f"img{i}.jpg",
                              pose_approx=Pose(opk_to_cam_from_world(o, p, k), c),
                              sigma_position=np.array([0.05, 0.05, 0.1]),
                              sigma_attitude=np.radians([0.005, 0.005, 0.008])))
    return block

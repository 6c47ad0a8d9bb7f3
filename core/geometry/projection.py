"""Projection of world points into images and back-projection of pixels to rays (the collinearity model)."""

from __future__ import annotations

import numpy as np

from ..model.camera import CameraModel
from ..model.pose import Pose


def project(camera: CameraModel, pose: Pose, xyz_world: np.ndarray,
            distort: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into an image.

    Parameters
    ----------
    xyz_world : (n, 3) float64

    Returns
    -------
    uv_px : (n, 2) float64 pixel positions (origin at the centre of the top-left pixel), NaN behind the camera
    depth : (n,) float64 z in the camera frame (distance along the optical axis)
    """
    xc = pose.transform(np.atleast_2d(xyz_world))
    depth = xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = xc[:, :2] / depth[:, None]
    uv = camera.normalized_to_pixel(xy, distort=distort)
    uv[depth <= 0] = np.nan
    return uv, depth


def pixel_rays(camera: CameraModel, pose: Pose, uv_px: np.ndarray) -> np.ndarray:
    """Unit ray directions in world coordinates through pixels ``uv_px : (n, 2)`` -> ``(n, 3)``.

    The rays start at ``pose.C``; lens distortion is removed first.
    """
    xy = camera.pixel_to_normalized(uv_px)
    d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    d = d_cam @ pose.R  # R^T d_cam for each row
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def backproject_depth(camera: CameraModel, pose: Pose, uv_px: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World points ``(n, 3)`` at z-depth ``depth : (n,)`` along the rays of pixels ``uv_px : (n, 2)``."""
    xy = camera.pixel_to_normalized(uv_px)
    xc = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) * np.asarray(depth, np.float64)[:, None]
    return xc @ pose.R + pose.C


def intersect_with_plane_z(camera: CameraModel, pose: Pose, uv_px: np.ndarray, z: float) -> np.ndarray:
    """Intersect pixel rays with the horizontal plane ``Z = z``: ``(n, 2)`` pixels -> ``(n, 3)`` world.

    Rays parallel to or pointing away from the plane give NaN.
    """
    d = pixel_rays(camera, pose, uv_px)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (z - pose.C[2]) / d[:, 2]
    s[s <= 0] = np.nan
    return pose.C + d * s[:, None]


def image_footprint(camera: CameraModel, pose: Pose, z: float, samples_per_side: int = 8) -> np.ndarray:
    """Polygon ``(k, 2)`` of the image border projected onto the plane ``Z = z`` (counter-clockwise order not
    guaranteed); border points whose rays miss the plane are dropped."""
    w, h = camera.width - 1.0, camera.height - 1.0
    s = np.linspace(0.0, 1.0, samples_per_side, endpoint=False)
    border = np.concatenate([
        np.stack([s * w, np.zeros_like(s)], 1), np.stack([np.full_like(s, w), s * h], 1),
        np.stack([w - s * w, np.full_like(s, h)], 1), np.stack([np.zeros_like(s), h - s * h], 1),
    ])
    xyz = intersect_with_plane_z(camera, pose, border, z)
    return xyz[np.isfinite(xyz[:, 0]), :2]

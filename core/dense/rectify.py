"""Epipolar rectification of any image pair (nadir, oblique, vertical or diagonal baselines) from its orientation.

The rectified frame is built from the poses alone (Fusiello's calibrated rectification): its x axis is the
baseline from the master's projection centre to the slave's, so the master is always the *left* image and
disparities ``d = u_master - u_slave`` are positive whatever the flight direction; a baseline that is vertical in
the images (e.g. two obliques of one strip looking across it) needs no special case, because the frame is
rotated to put the baseline along the rows. Its z axis is the mean optical axis made orthogonal to the
baseline. Both rectified images share the focal length and the principal row ``cy``; each has its own ``cx``
(a shift of the disparity by ``cx_m - cx_s``), chosen so that its own footprint starts at column 0.

Lens distortion is removed by the same remapping (``cv2.initUndistortRectifyMap``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ComputationError
from ..model.camera import CameraModel
from ..model.pose import Pose


class PairImages:
    """What every rectification of a pair shares: the baseline and the remapping of both images (the attributes
    ``c_master``, ``c_slave``, ``map_master``, ``map_slave`` come from the subclass)."""

    c_master: np.ndarray
    c_slave: np.ndarray
    map_master: np.ndarray
    map_slave: np.ndarray

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.c_slave - self.c_master))

    def remap(self, master_img: np.ndarray, slave_img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rectified master and slave images (bilinear, black outside the originals)."""
        m = cv2.remap(master_img, self.map_master, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        s = cv2.remap(slave_img, self.map_slave, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return m, s


@dataclass(frozen=True, eq=False)
class RectifiedPair(PairImages):
    """The geometry of a rectified master/slave pair.

    Attributes
    ----------
    rect_from_world : (3, 3) float64 rotation of the common rectified frame (x along the baseline)
    c_master, c_slave : (3,) float64 projection centres in world coordinates
    f : focal length of both rectified images, pixels
    cx_master, cx_slave : principal columns of the rectified master and slave
    cy : principal row of both
    width, height : size of both rectified images
    map_master, map_slave : (height, width, 2) float32 maps rectified pixel -> original pixel (for cv2.remap)
    """

    rect_from_world: np.ndarray
    c_master: np.ndarray
    c_slave: np.ndarray
    f: float
    cx_master: float
    cx_slave: float
    cy: float
    width: int
    height: int
    map_master: np.ndarray
    map_slave: np.ndarray

    @property
    def focal_baseline(self) -> float:
        """``f B``: ``depth^2 / (f B)`` is the depth change of one pixel of disparity."""
        return self.f * self.baseline

    @property
    def disparity_offset(self) -> float:
        """``cx_master - cx_slave``: the disparity of a point at infinity."""
        return self.cx_master - self.cx_slave

    def depth_to_disparity(self, z_rect: np.ndarray) -> np.ndarray:
        """Rectified depth (along the rectified z axis, metres) to disparity, pixels."""
        return self.f * self.baseline / np.asarray(z_rect, np.float64) + self.disparity_offset

    def rect_depth(self, xyz_world: np.ndarray) -> np.ndarray:
        """Depth of world points ``(n, 3)`` along the rectified z axis, ``(n,)``."""
        return (np.asarray(xyz_world, np.float64) - self.c_master) @ self.rect_from_world[2]

    def disparity_of(self, xyz_world: np.ndarray) -> np.ndarray:
        """Disparity ``(n,)`` of world points ``(n, 3)``."""
        return self.depth_to_disparity(self.rect_depth(xyz_world))

    def master_rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """World directions ``(n, 3)`` of the rays through master rectified pixels ``u, v : (n,)``."""
        d_rect = np.stack([(np.asarray(u, np.float64) - self.cx_master) / self.f,
                           (np.asarray(v, np.float64) - self.cy) / self.f, np.ones(np.size(u))], axis=1)
        return d_rect @ self.rect_from_world

    def triangulate(self, u: np.ndarray, v: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """World points ``(n, 3)`` from master rectified pixels ``u, v : (n,)`` and disparities ``(n,)``."""
        d = np.asarray(disparity, np.float64) - self.disparity_offset
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(d > 0, self.f * self.baseline / d, np.nan)
        x_rect = np.stack([(np.asarray(u, np.float64) - self.cx_master) * z / self.f,
                           (np.asarray(v, np.float64) - self.cy) * z / self.f, z], axis=1)
        return x_rect @ self.rect_from_world + self.c_master

    def master_to_rect(self, camera: CameraModel, pose: Pose, uv_px: np.ndarray) -> np.ndarray:
        """Original master pixels ``(n, 2)`` to rectified master pixels ``(n, 2)``."""
        return _to_rect(camera, pose, uv_px, self.rect_from_world, self.f, self.cx_master, self.cy)


def _to_rect(camera: CameraModel, pose: Pose, uv_px: np.ndarray, rect_from_world: np.ndarray, f: float,
             cx: float, cy: float) -> np.ndarray:
    xy = camera.pixel_to_normalized(uv_px)
    d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    d_rect = d_cam @ (rect_from_world @ pose.R.T).T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([f * d_rect[:, 0] / d_rect[:, 2] + cx, f * d_rect[:, 1] / d_rect[:, 2] + cy], axis=1)
    uv[d_rect[:, 2] <= 1e-6] = np.nan
    return uv


def _border(camera: CameraModel, n: int = 16) -> np.ndarray:
    w, h = camera.width - 0.5, camera.height - 0.5
    s = np.linspace(0.0, 1.0, n)
    return np.concatenate([np.stack([-0.5 + s * (w + 0.5), np.full(n, -0.5)], 1),
                           np.stack([np.full(n, w), -0.5 + s * (h + 0.5)], 1),
                           np.stack([-0.5 + s * (w + 0.5), np.full(n, h)], 1),
                           np.stack([np.full(n, -0.5), -0.5 + s * (h + 0.5)], 1)])


def rectification_frame(pose_master: Pose, pose_slave: Pose, min_angle_deg: float = 15.0) -> np.ndarray:
    """The rotation ``rect_from_world`` (3, 3) of a pair: x along the baseline master -> slave, z the mean
    optical axis made orthogonal to it.

    Raises :class:`ComputationError` when the baseline is within ``min_angle_deg`` of the mean viewing direction
    (forward motion: the epipoles lie inside the images and planar rectification cannot work).
    """
    b = pose_slave.C - pose_master.C
    nb = np.linalg.norm(b)
    if nb <= 0:
        raise ComputationError("rectification: the two images have the same projection centre")
    x = b / nb
    z = pose_master.R[2] + pose_slave.R[2]
    z = z / np.linalg.norm(z)
    if abs(float(z @ x)) > np.cos(np.radians(min_angle_deg)):
        raise ComputationError("rectification: baseline nearly parallel to the viewing direction")
    z = z - (z @ x) * x
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def rectify_pair(cam_master: CameraModel, pose_master: Pose, cam_slave: CameraModel, pose_slave: Pose,
                 scale: float = 1.0, max_size_factor: float = 2.0) -> RectifiedPair:
    """Rectify a master/slave pair.

    Parameters
    ----------
    scale : rectified focal length relative to the mean focal length of the two cameras (0.5 halves the size)
    max_size_factor : the rectified width and height are clipped to this multiple of the larger original size
        (strongly converging oblique pairs would otherwise give huge images); the rows are those common to both
    """
    r = rectification_frame(pose_master, pose_slave)
    f = scale * 0.25 * (cam_master.fx + cam_master.fy + cam_slave.fx + cam_slave.fy)
    bm = _to_rect(cam_master, pose_master, _border(cam_master), r, f, 0.0, 0.0)
    bs = _to_rect(cam_slave, pose_slave, _border(cam_slave), r, f, 0.0, 0.0)
    if not (np.isfinite(bm).all() and np.isfinite(bs).all()):
        raise ComputationError("rectification: an image border looks away from the rectified frame")
    limit = max_size_factor * scale * max(cam_master.width, cam_master.height, cam_slave.width, cam_slave.height)
    v0, v1 = max(bm[:, 1].min(), bs[:, 1].min()), min(bm[:, 1].max(), bs[:, 1].max())
    if v1 - v0 < 8:
        raise ComputationError("rectification: the two images share no rows")
    mid = 0.5 * (v0 + v1)
    v0, v1 = max(v0, mid - limit / 2), min(v1, mid + limit / 2)

    def cols(b: np.ndarray) -> tuple[float, float]:
        u0, u1 = b[:, 0].min(), b[:, 0].max()
        m = 0.5 * (u0 + u1)
        return max(u0, m - limit / 2), min(u1, m + limit / 2)

    um0, um1 = cols(bm)
    us0, us1 = cols(bs)
    width = int(np.ceil(max(um1 - um0, us1 - us0))) + 1
    height = int(np.ceil(v1 - v0)) + 1
    cx_m, cx_s, cy = -um0, -us0, -v0
    maps = []
    for cam, pose, cx in ((cam_master, pose_master, cx_m), (cam_slave, pose_slave, cx_s)):
        k_new = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        m1, _ = cv2.initUndistortRectifyMap(cam.K, cam.dist_coeffs, r @ pose.R.T, k_new, (width, height),
                                            cv2.CV_32FC2)
        maps.append(m1)
    return RectifiedPair(r, pose_master.C.copy(), pose_slave.C.copy(), float(f), float(cx_m), float(cx_s),
                         float(cy), width, height, maps[0], maps[1])


def disparity_range(pair, z_world_min: float, z_world_max: float, cam_slave: CameraModel,
                    pose_slave: Pose, margin_px: float = 8.0, grid: int = 24) -> tuple[float, float]:
    """Disparity interval for terrain heights between ``z_world_min`` and ``z_world_max`` (the DSM/terrain prior).

    ``pair`` is a :class:`RectifiedPair` or a :class:`.polar.PolarPair` (both give ``master_rays`` and
    ``disparity_of``). Rays through a grid of rectified master pixels are intersected with the two horizontal
    planes; points that the slave sees give the extreme disparities, widened by ``margin_px``.
    """
    u = np.linspace(0, pair.width - 1, grid)
    v = np.linspace(0, pair.height - 1, grid)
    uu, vv = np.meshgrid(u, v)
    d_world = pair.master_rays(uu.ravel(), vv.ravel())
    disps = []
    for z in (z_world_min, z_world_max):
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (z - pair.c_master[2]) / d_world[:, 2]
        ok = s > 0
        xyz = pair.c_master + d_world[ok] * s[ok, None]
        xc = pose_slave.transform(xyz)
        front = xc[:, 2] > 0
        uv = cam_slave.normalized_to_pixel(xc[front, :2] / xc[front, 2:3])
        seen = cam_slave.contains(uv)
        if seen.any():
            disps.append(pair.disparity_of(xyz[front][seen]))
    if not disps:
        raise ComputationError("disparity range: the slave sees none of the master's terrain")
    d = np.concatenate(disps)
    return float(d.min() - margin_px), float(d.max() + margin_px)

"""Log-polar epipolar rectification for pairs whose baseline runs near the viewing direction.

Two consecutive images of a forward- or backward-looking oblique head are taken along the head's look direction.
Planar rectification (:mod:`.rectify`) must then turn both images to look perpendicular to the baseline, i.e.
straight down for a 45-degree head: the facades the head sees are squeezed into slivers and cannot be matched.
Polar rectification (the idea of Pollefeys, Koch and Van Gool, 1999) keeps the images' own perspective: every
epipolar line through the epipole becomes one row, and the position along the line one column.

Here both images are first turned to the master's orientation (a rotation about the slave's centre, so only
translation is left between them). Then the two images share one epipole ``e`` (the image of the baseline) and
the same epipolar lines (the lines through ``e``), and a point at depth ``Z`` (along the master's axis) moves
along its line from radius ``r_m`` in the master to ``r_s = r_m Z / (Z - b_z)`` in the slave, where ``b_z`` is
the baseline component along the axis. Columns sample ``log r``: the motion becomes a shift, ``log r_s - log
r_m = -log(1 - b_z / Z)``, which depends on the depth only, as a disparity must for semi-global matching.
Rows sample the angle of the line. Steps of ``1 / r_max`` in both keep every original pixel (no detail is lost
on the far side; the near side is oversampled by ``r_max / r_min``).

The column direction is chosen so that disparities ``d = u_master - u_slave`` are positive, and each image gets
its own column offset so its footprint starts at column 0 (as in the planar case). Lens distortion is applied by
the maps, so the original images are remapped once. The epipole must lie outside both images (the image
selection ensures it: the baseline is kept at least 35 degrees from the viewing direction).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ComputationError
from ..model.camera import CameraModel
from ..model.pose import Pose
from .rectify import PairImages


@dataclass(frozen=True, eq=False)
class PolarPair(PairImages):
    """The geometry of a log-polar rectified master/slave pair (same interface as ``RectifiedPair``).

    Attributes
    ----------
    R : (3, 3) float64 master ``cam_from_world`` rotation (the common orientation of both rectified images)
    K : (3, 3) float64 virtual pinhole of the common orientation (the master's focal lengths and principal point)
    c_master, c_slave : (3,) float64 projection centres
    epipole : (2,) float64 epipole in the virtual image, pixels
    theta_ref : direction (radians) from the epipole towards the images, the origin of the line angles
    theta0, dtheta : row ``v`` has the epipolar line at angle ``theta_ref + theta0 + v * dtheta``
    dlogr : column step in ``log r``; sign : +1 when columns grow with the radius, -1 when they shrink
    logr_master, logr_slave : ``log r`` at column 0 of each image
    width, height : size of both rectified images
    map_master, map_slave : (height, width, 2) float32 maps rectified pixel -> original pixel (for cv2.remap)
    """

    R: np.ndarray
    K: np.ndarray
    c_master: np.ndarray
    c_slave: np.ndarray
    epipole: np.ndarray
    theta_ref: float
    theta0: float
    dtheta: float
    dlogr: float
    sign: float
    logr_master: float
    logr_slave: float
    width: int
    height: int
    map_master: np.ndarray
    map_slave: np.ndarray

    @property
    def b_z(self) -> float:
        """Baseline component along the master's optical axis, metres (signed)."""
        return float(self.R[2] @ (self.c_slave - self.c_master))

    @property
    def focal_baseline(self) -> float:
        """The pair's ``f B`` equivalent: ``depth^2 / (f B)`` is the depth change of one pixel of disparity (at the
        depths where ``b_z`` is small against them), as for a planar pair."""
        return abs(self.b_z) / self.dlogr

    def _polar(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and ``log r`` of virtual image points ``p : (n, 2)``."""
        q = p - self.epipole
        theta = np.arctan2(q[:, 1], q[:, 0]) - self.theta_ref
        theta = (theta + np.pi) % (2 * np.pi) - np.pi
        return (theta - self.theta0) / self.dtheta, np.log(np.maximum(np.hypot(q[:, 0], q[:, 1]), 1e-12))

    def _virtual(self, v: np.ndarray, logr: np.ndarray) -> np.ndarray:
        """Virtual image points ``(n, 2)`` of rows ``v`` and ``log r``."""
        th = self.theta_ref + self.theta0 + np.asarray(v, np.float64) * self.dtheta
        r = np.exp(logr)
        return self.epipole + np.stack([r * np.cos(th), r * np.sin(th)], axis=1)

    def _project(self, xyz: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Virtual image points ``(n, 2)`` of world points seen from ``centre`` in the common orientation, and their
        depths ``(n,)``."""
        xc = (np.asarray(xyz, np.float64) - centre) @ self.R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            p = (xc @ self.K.T)[:, :2] / xc[:, 2:3]
        return p, xc[:, 2]

    def disparity_of(self, xyz: np.ndarray) -> np.ndarray:
        """Disparity ``(n,)`` (master column minus slave column) of world points ``(n, 3)``."""
        pm, _ = self._project(xyz, self.c_master)
        ps, _ = self._project(xyz, self.c_slave)
        _, lm = self._polar(pm)
        _, ls = self._polar(ps)
        return self.sign * ((lm - self.logr_master) - (ls - self.logr_slave)) / self.dlogr

    def master_rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """World directions ``(n, 3)`` of the rays through master rectified pixels ``u, v : (n,)``."""
        logr = self.logr_master + self.sign * np.asarray(u, np.float64) * self.dlogr
        p = self._virtual(v, logr)
        d = np.concatenate([p, np.ones((len(p), 1))], axis=1) @ np.linalg.inv(self.K).T
        return d @ self.R

    def triangulate(self, u: np.ndarray, v: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """World points ``(n, 3)`` from master rectified pixels ``u, v : (n,)`` and disparities ``(n,)``.

        The slave's point lies on the same epipolar line at ``log r_s``; with ``k = r_s / r_m`` the master depth is
        ``Z = b_z k / (k - 1)`` (from ``r_s = r_m Z / (Z - b_z)``)."""
        u = np.asarray(u, np.float64)
        lm = self.logr_master + self.sign * u * self.dlogr
        ls = self.logr_slave + self.sign * (u - np.asarray(disparity, np.float64)) * self.dlogr
        k = np.exp(ls - lm)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = self.b_z * k / (k - 1.0)
        z = np.where(np.isfinite(z) & (z > 0), z, np.nan)
        rays = np.concatenate([self._virtual(v, lm), np.ones((len(u), 1))], axis=1) @ np.linalg.inv(self.K).T
        return (rays * z[:, None]) @ self.R + self.c_master

    def master_to_rect(self, camera: CameraModel, pose: Pose, uv_px: np.ndarray) -> np.ndarray:
        """Original master pixels ``(n, 2)`` to rectified master pixels ``(n, 2)``."""
        xy = camera.pixel_to_normalized(np.asarray(uv_px, np.float64))
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ (self.R @ pose.R.T).T
        with np.errstate(divide="ignore", invalid="ignore"):
            p = (d @ self.K.T)[:, :2] / d[:, 2:3]
        row, logr = self._polar(p)
        out = np.stack([self.sign * (logr - self.logr_master) / self.dlogr, row], axis=1)
        out[d[:, 2] <= 1e-9] = np.nan
        return out


def _border_virtual(camera: CameraModel, pose: Pose, R: np.ndarray, K: np.ndarray, n: int = 24) -> np.ndarray:
    """The image border of a camera ``(4n, 2)``, in order around the image, in the virtual image of orientation
    ``R``."""
    w, h = camera.width - 0.5, camera.height - 0.5
    s = np.linspace(0.0, 1.0, n)
    uv = np.concatenate([np.stack([-0.5 + s * (w + 0.5), np.full(n, -0.5)], 1),
                         np.stack([np.full(n, w), -0.5 + s * (h + 0.5)], 1),
                         np.stack([w - s * (w + 0.5), np.full(n, h)], 1),
                         np.stack([np.full(n, -0.5), h - s * (h + 0.5)], 1)])
    xy = camera.pixel_to_normalized(uv)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ (R @ pose.R.T).T
    if (d[:, 2] <= 1e-6).any():
        raise ComputationError("polar rectification: an image border looks away from the master's orientation")
    return (d @ K.T)[:, :2] / d[:, 2:3]


def _contains(poly: np.ndarray, p: np.ndarray) -> bool:
    return cv2.pointPolygonTest(poly.astype(np.float32).reshape(-1, 1, 2), (float(p[0]), float(p[1])), False) >= 0


def polar_rectify_pair(cam_master: CameraModel, pose_master: Pose, cam_slave: CameraModel, pose_slave: Pose,
                       scale: float = 1.0, max_size_factor: float = 2.0, margin_px: float = 32.0) -> PolarPair:
    """Log-polar rectification of a master/slave pair (see the module docstring).

    Parameters
    ----------
    scale : sampling relative to one step of ``1 / r_max`` (0.5 halves the rows and columns)
    max_size_factor : the rectified width and height are clipped to this multiple of the larger original size
    margin_px : the epipole must lie at least this far outside both images

    Raises :class:`ComputationError` when the epipole lies inside (or too near) an image, or the images share no
    epipolar lines.
    """
    R = pose_master.R
    K = np.array([[cam_master.fx, 0.0, cam_master.cx], [0.0, cam_master.fy, cam_master.cy], [0.0, 0.0, 1.0]])
    b = pose_slave.C - pose_master.C
    eh = K @ (R @ b)
    if np.linalg.norm(b) <= 0 or abs(eh[2]) < 1e-9 * np.linalg.norm(eh):
        raise ComputationError("polar rectification: the epipole is at infinity (use planar rectification)")
    e = eh[:2] / eh[2]
    bm = _border_virtual(cam_master, pose_master, R, K)
    bs = _border_virtual(cam_slave, pose_slave, R, K)
    for poly in (bm, bs):
        if _contains(poly, e) or np.min(np.hypot(*(poly - e).T)) < margin_px:
            raise ComputationError("polar rectification: the epipole lies inside an image")
    theta_ref = float(np.arctan2(*(0.5 * (bm.mean(0) + bs.mean(0)) - e)[::-1]))
    # the border polygons are sampled densely enough for their angular and radial extremes (the extremes of a
    # convex-ish footprint lie on its border)
    tm, lm = _angles_logr(bm, e, theta_ref)
    ts, ls = _angles_logr(bs, e, theta_ref)
    t0, t1 = max(tm.min(), ts.min()), min(tm.max(), ts.max())
    if t1 <= t0:
        raise ComputationError("polar rectification: the two images share no epipolar lines")
    r_max = float(np.exp(max(lm.max(), ls.max())))
    step = 1.0 / (r_max * scale)
    limit = max_size_factor * scale * max(cam_master.width, cam_master.height, cam_slave.width, cam_slave.height)
    height = int(min(np.ceil((t1 - t0) / step) + 1, limit))
    dtheta = (t1 - t0) / max(height - 1, 1)
    expanding = eh[2] > 0  # the slave lies ahead: points move away from the epipole
    sign = -1.0 if expanding else 1.0
    span = max(lm.max() - lm.min(), ls.max() - ls.min())
    width = int(min(np.ceil(span / step) + 1, limit))
    dlogr = span / max(width - 1, 1) if width >= limit else step

    def start(lr: np.ndarray) -> float:
        return float(lr.max() if sign < 0 else lr.min())

    pair = PolarPair(R, K, pose_master.C.copy(), pose_slave.C.copy(), e, theta_ref, float(t0), float(dtheta),
                     float(dlogr), sign, start(lm), start(ls), width, height,
                     np.empty((0, 0, 2), np.float32), np.empty((0, 0, 2), np.float32))
    maps = [_map(pair, cam, pose, pair.logr_master if i == 0 else pair.logr_slave)
            for i, (cam, pose) in enumerate(((cam_master, pose_master), (cam_slave, pose_slave)))]
    return PolarPair(R, K, pair.c_master, pair.c_slave, e, theta_ref, float(t0), float(dtheta), float(dlogr), sign,
                     pair.logr_master, pair.logr_slave, width, height, maps[0], maps[1])


def _angles_logr(poly: np.ndarray, e: np.ndarray, theta_ref: float) -> tuple[np.ndarray, np.ndarray]:
    q = poly - e
    t = np.arctan2(q[:, 1], q[:, 0]) - theta_ref
    return (t + np.pi) % (2 * np.pi) - np.pi, np.log(np.hypot(q[:, 0], q[:, 1]))


def _map(pair: PolarPair, cam: CameraModel, pose: Pose, logr0: float) -> np.ndarray:
    """The (height, width, 2) float32 map rectified pixel -> original pixel of one image."""
    vv, uu = np.mgrid[0:pair.height, 0:pair.width]
    p = pair._virtual(vv.ravel(), logr0 + pair.sign * uu.ravel() * pair.dlogr)
    d = np.concatenate([p, np.ones((len(p), 1))], axis=1) @ np.linalg.inv(pair.K).T  # common orientation
    d = d @ (pose.R @ pair.R.T).T
    out = np.full((len(p), 2), -1.0)
    front = d[:, 2] > 1e-9
    out[front] = cam.normalized_to_pixel(d[front, :2] / d[front, 2:3])
    return out.reshape(pair.height, pair.width, 2).astype(np.float32)

"""One dense-matching unit: rectify a master/slave pair, run SGM, and return depth in the master's image grid.

:func:`match_pair` is a module-level function over a picklable :class:`PairTask`, so pairs run in parallel
through the executor (processes or Dask). The result is the master's depth map sampled on a regular grid of
master pixels (every ``step``-th pixel), plus the world points it came from, so fusion can check slaves against
each other and quality maps can re-intersect the rays.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import InputError
from ..io.photos import read_photo
from ..model.camera import CameraModel
from ..model.pose import Pose
from .polar import PolarPair, polar_rectify_pair
from .rectify import RectifiedPair, disparity_range, rectify_pair
from .sgm import SgmConfig, coarse_range, sgm_disparity


@dataclass(frozen=True, eq=False)
class PairTask:
    """Everything a worker needs to match one pair (no workspace access).

    Attributes
    ----------
    master, slave : image ids
    cam_master, cam_slave, pose_master, pose_slave : interior and exterior orientation
    path_master, path_slave : image files
    z_min, z_max : terrain/object height prior (world Z, metres) giving the disparity range
    step : sampling step of the master grid of the result (1 = every pixel)
    scale : rectified image scale (1 = full resolution)
    sgm : SGM settings
    coarse_above : a prior disparity interval wider than this (pixels) is first narrowed on a reduced pair
    max_size_factor : rectified images are clipped to this multiple of the original size
    threads : OpenCV threads of the worker (0 = OpenCV's default; 1 when pairs run in parallel processes)
    bits_master, bits_slave : the cameras' significant bits (:func:`..io.photos.camera_bits`)
    polar_below_deg : pairs whose baseline is closer than this to the mean viewing direction (the along-track
        pairs of forward and backward oblique heads) are rectified in log-polar form (:mod:`.polar`), which keeps
        their facades; others planar (:mod:`.rectify`); 0 rectifies every pair planar
    """

    master: str
    slave: str
    cam_master: CameraModel
    pose_master: Pose
    cam_slave: CameraModel
    pose_slave: Pose
    path_master: str
    path_slave: str
    z_min: float
    z_max: float
    step: int = 1
    scale: float = 1.0
    sgm: SgmConfig = SgmConfig()
    coarse_above: float = 96.0
    max_size_factor: float = 1.5
    threads: int = 0
    polar_below_deg: float = 60.0
    bits_master: int | None = None
    bits_slave: int | None = None


@dataclass(frozen=True, eq=False)
class PairDepth:
    """The result of one pair.

    Attributes
    ----------
    master, slave : image ids
    depth : (rows, cols) float32 z-depth in the master camera on the grid ``v = step*i, u = step*j``, NaN empty
    focal_baseline : rectified focal length times baseline, pixel metres (depth sigma = z^2 / fB * sigma_d)
    seconds : wall time of rectification and matching
    megapixels : rectified pixels matched, millions
    disparities : width of the disparity search at full resolution, pixels
    """

    master: str
    slave: str
    depth: np.ndarray
    focal_baseline: float
    seconds: float
    megapixels: float
    disparities: float


def master_grid(camera: CameraModel, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``u, v`` (rows, cols) of the master grid sampled every ``step`` pixels."""
    return np.meshgrid(np.arange(0, camera.width, step, dtype=np.float64),
                       np.arange(0, camera.height, step, dtype=np.float64))


def baseline_view_angle(pose_master: Pose, pose_slave: Pose) -> float:
    """Angle in degrees (0 to 90) between the baseline and the mean viewing direction of a pair."""
    b = pose_slave.C - pose_master.C
    view = pose_master.R[2] + pose_slave.R[2]
    c = abs(float(b @ view)) / max(float(np.linalg.norm(b) * np.linalg.norm(view)), 1e-12)
    return float(np.degrees(np.arccos(min(c, 1.0))))


def rectify(task: PairTask) -> RectifiedPair | PolarPair:
    """The rectification of a pair: log-polar when its baseline runs within ``task.polar_below_deg`` of the
    viewing direction, planar otherwise."""
    if baseline_view_angle(task.pose_master, task.pose_slave) < task.polar_below_deg:
        return polar_rectify_pair(task.cam_master, task.pose_master, task.cam_slave, task.pose_slave,
                                  scale=task.scale, max_size_factor=task.max_size_factor)
    return rectify_pair(task.cam_master, task.pose_master, task.cam_slave, task.pose_slave, scale=task.scale,
                        max_size_factor=task.max_size_factor)


def near_is_high(pair: RectifiedPair | PolarPair, z_min: float, z_max: float) -> bool:
    """Whether the high disparities of ``pair`` (a rectified or polar pair) are the near side: the disparity of
    the master's central ray at height ``z_max`` against ``z_min``."""
    ray = pair.master_rays(np.array([pair.width / 2.0]), np.array([pair.height / 2.0]))[0]
    pts = np.array([pair.c_master + ray * (z - pair.c_master[2]) / ray[2] for z in (z_min, z_max)])
    d = pair.disparity_of(pts)
    return bool(d[1] > d[0])


def match_pair(task: PairTask) -> PairDepth:
    """Rectify, match (padded SGM with left-right check) and convert to master depth."""
    if task.threads > 0:
        cv2.setNumThreads(task.threads)
    t0 = time.perf_counter()
    img_m = read_photo(task.path_master, True, task.master, task.bits_master)
    img_s = read_photo(task.path_slave, True, task.slave, task.bits_slave)
    for img, cam, path in ((img_m, task.cam_master, task.path_master), (img_s, task.cam_slave, task.path_slave)):
        if img.shape[1] != cam.width or img.shape[0] != cam.height:
            raise InputError(f"image is {img.shape[1]}x{img.shape[0]}, camera says {cam.width}x{cam.height}",
                             path=path, field="size")
    pair = rectify(task)
    d_lo, d_hi = disparity_range(pair, task.z_min, task.z_max, task.cam_slave, task.pose_slave)
    rect_m, rect_s = pair.remap(img_m, img_s)
    if d_hi - d_lo > task.coarse_above:
        d_lo, d_hi = coarse_range(rect_m, rect_s, d_lo, d_hi, task.sgm,
                                  near_high=near_is_high(pair, task.z_min, task.z_max))
    disp = sgm_disparity(rect_m, rect_s, d_lo, d_hi, task.sgm)
    # master grid -> rectified master pixels -> disparity (nearest, so depth edges stay sharp)
    uu, vv = master_grid(task.cam_master, task.step)
    uv_rect = pair.master_to_rect(task.cam_master, task.pose_master, np.stack([uu.ravel(), vv.ravel()], 1))
    ur, vr = np.rint(uv_rect[:, 0]), np.rint(uv_rect[:, 1])
    inside = np.isfinite(ur) & (ur >= 0) & (ur < pair.width) & (vr >= 0) & (vr < pair.height)
    d = np.full(len(ur), np.nan)
    d[inside] = disp[vr[inside].astype(np.int64), ur[inside].astype(np.int64)]
    ok = np.isfinite(d)
    depth = np.full(len(ur), np.nan, np.float32)
    xyz = pair.triangulate(uv_rect[ok, 0], uv_rect[ok, 1], d[ok])
    depth[ok] = task.pose_master.transform(xyz)[:, 2]
    depth[depth <= 0] = np.nan
    return PairDepth(task.master, task.slave, depth.reshape(uu.shape), pair.focal_baseline,
                     time.perf_counter() - t0, pair.width * pair.height / 1e6, d_hi - d_lo)

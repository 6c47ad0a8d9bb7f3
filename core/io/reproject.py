"""Move a block into another CRS: centres and ground points transformed, rotations corrected for the local
rotation of grid north (meridian convergence) between the two CRSs."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..geometry.crs import parse_crs
from ..geometry.rotations import rot_z
from ..model import ImageBlock, Pose


def _north_angle(xyz: np.ndarray, transform: Callable, src: str, dst: str) -> float:
    """Angle (radians, counter-clockwise) of the source's north direction at ``xyz`` seen in the destination grid.

    Measured with a short northward step in the source's own units (1e-6 of the coordinate: about 5 m for UTM
    northings, 5e-5 deg for latitudes).
    """
    step = 1e-6 * max(1.0, abs(float(xyz[1])))
    p = np.array([xyz, xyz + [0.0, step, 0.0]])
    q = transform(p, src, dst)
    d = q[1] - q[0]
    return float(np.arctan2(-d[0], d[1]))


def _grid_rotation(xyz: np.ndarray, transform: Callable, src: str, dst: str) -> float:
    """Angle (radians, counter-clockwise) by which the destination grid is rotated against the source at xyz.

    It equals the difference of the meridian convergences, ``gamma_dst - gamma_src``. A geographic CRS stands
    for the local east-north-up frame (convergence 0): its north step is true north, so the angle is always
    measured from the geographic side, where degrees of longitude and latitude never have to be compared.
    """
    if parse_crs(dst).is_geographic:
        if parse_crs(src).is_geographic:
            return 0.0
        q = transform(np.asarray(xyz, dtype=np.float64)[None], src, dst)[0]
        return -_north_angle(q, transform, dst, src)
    return _north_angle(np.asarray(xyz, dtype=np.float64), transform, src, dst)


def reproject_block(block: ImageBlock, dst_crs: str, transform: Callable) -> ImageBlock:
    """A copy of ``block`` in ``dst_crs``; ``transform(xyz, src, dst)`` maps (n, 3) points."""
    import copy

    out = copy.deepcopy(block)
    src = block.crs
    for img in out.images.values():
        for attr in ("pose_approx", "pose_adjusted"):
            p: Pose | None = getattr(img, attr)
            if p is None:
                continue
            c = transform(p.C[None], src, dst_crs)[0]
            gamma = _grid_rotation(p.C, transform, src, dst_crs)
            # world_dst = Rz(gamma) world_src (locally): R_cam_from_dst = R_cam_from_src Rz(gamma)^T
            setattr(img, attr, Pose(p.R @ rot_z(gamma).T, c))
    for g in out.ground_points.values():
        if g.xyz is not None:
            g.xyz = transform(g.xyz[None], src, dst_crs)[0]
    out.crs = dst_crs
    return out

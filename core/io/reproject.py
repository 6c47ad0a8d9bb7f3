"""Move a block into another CRS: centres and ground points transformed, rotations corrected for the local
rotation of grid north (meridian convergence) between the two CRSs."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..geometry.rotations import rot_z
from ..model import ImageBlock, Pose


def _grid_rotation(xyz: np.ndarray, transform: Callable, src: str, dst: str) -> float:
    """Angle (radians, counter-clockwise) by which the destination grid is rotated against the source at xyz."""
    p = np.array([xyz, xyz + [0.0, 10.0, 0.0]])
    q = transform(p, src, dst)
    d = q[1] - q[0]
    return float(np.arctan2(-d[0], d[1]))


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

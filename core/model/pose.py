"""Exterior orientation: ``cam_from_world`` rotation plus projection centre, in float64."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rotations import cam_from_world_to_opk, opk_to_cam_from_world


@dataclass(frozen=True, eq=False)
class Pose:
    """A camera pose in the world frame.

    Attributes
    ----------
    R : (3, 3) float64, ``cam_from_world`` rotation (OpenCV camera frame: x right, y down, z forward)
    C : (3,) float64, projection centre in world coordinates (metres of the block's CRS)
    """

    R: np.ndarray
    C: np.ndarray

    def __post_init__(self) -> None:
        r = np.array(self.R, dtype=np.float64).reshape(3, 3)
        c = np.array(self.C, dtype=np.float64).reshape(3)
        r.setflags(write=False)
        c.setflags(write=False)
        object.__setattr__(self, "R", r)
        object.__setattr__(self, "C", c)

    @property
    def t(self) -> np.ndarray:
        """Translation of ``cam_from_world``: ``x_cam = R x_world + t``, (3,)."""
        return -self.R @ self.C

    @property
    def viewing_direction(self) -> np.ndarray:
        """Unit optical axis in world coordinates, (3,)."""
        return self.R[2].copy()

    @classmethod
    def from_opk(cls, omega: float, phi: float, kappa: float, center: np.ndarray) -> Pose:
        """Pose from omega-phi-kappa radians (PATB convention, see ``geometry.rotations``) and centre."""
        return cls(opk_to_cam_from_world(omega, phi, kappa), center)

    @classmethod
    def from_rt(cls, r_cam_from_world: np.ndarray, t: np.ndarray) -> Pose:
        """Pose from OpenCV ``(R, t)``."""
        r = np.asarray(r_cam_from_world, dtype=np.float64)
        return cls(r, -r.T @ np.asarray(t, dtype=np.float64))

    def opk(self) -> tuple[float, float, float]:
        """Omega, phi, kappa in radians."""
        return cam_from_world_to_opk(self.R)

    def transform(self, xyz_world: np.ndarray) -> np.ndarray:
        """World points ``(n, 3)`` to camera-frame points ``(n, 3)``."""
        return (np.asarray(xyz_world, dtype=np.float64) - self.C) @ self.R.T

    def as_matrix(self) -> np.ndarray:
        """4x4 homogeneous ``cam_from_world``."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Pose) and np.array_equal(self.R, other.R) and np.array_equal(self.C, other.C)

    def __hash__(self) -> int:
        return hash((self.R.tobytes(), self.C.tobytes()))

"""Plane coordinates of a planar surface and its texel grid.

A surface ring ``(k, 3)`` gets an orthonormal frame ``(e1, e2, normal)``: ``e1`` is horizontal (along a wall,
east for horizontal faces), ``e2 = normal x e1`` points up the surface (north for flat roofs), so a ring that
is counter-clockwise seen from outside is counter-clockwise in ``(s, t)`` and textures appear upright.

The texel grid covers the ring's bounding rectangle in ``(s, t)`` with square texels of ``texel`` metres.
Texel ``(row j, column i)`` has its centre at ``s = s0 + (i + 0.5) texel``, ``t = t1 - (j + 0.5) texel`` (row 0 at
the top); continuous texel coordinates ``x = (s - s0) / texel``, ``y = (t1 - t) / texel`` put texel centres at
half integers (the convention of texture samplers, so UVs derive from them without offsets).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..buildings.model import ring_normal


@dataclass(frozen=True, eq=False)
class PlaneFrame:
    """An orthonormal frame on a plane.

    origin : (3,) float64 world point at ``(s, t) = (0, 0)``; e1, e2, normal : (3,) float64 unit vectors
    """

    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    normal: np.ndarray

    def to_plane(self, xyz: np.ndarray) -> np.ndarray:
        """World points ``(n, 3)`` -> plane coordinates ``(n, 2)`` (their orthogonal projection)."""
        d = np.asarray(xyz, np.float64) - self.origin
        return np.stack([d @ self.e1, d @ self.e2], axis=1)

    def to_world(self, st: np.ndarray) -> np.ndarray:
        """Plane coordinates ``(n, 2)`` -> world points ``(n, 3)`` on the plane."""
        st = np.asarray(st, np.float64)
        return self.origin + st[:, :1] * self.e1 + st[:, 1:2] * self.e2


def plane_frame(ring_xyz: np.ndarray) -> PlaneFrame:
    """The frame of a planar ring ``(k, 3)`` (Newell normal, origin at the vertex mean)."""
    xyz = np.asarray(ring_xyz, np.float64)
    n = ring_normal(xyz)
    if not np.any(n):
        raise ValueError("degenerate ring: no normal")
    up = np.array([0.0, 0.0, 1.0])
    e1 = np.cross(up, n)
    if np.linalg.norm(e1) < 1e-6:  # horizontal face: s runs east
        e1 = np.array([1.0, 0.0, 0.0]) - n[0] * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return PlaneFrame(xyz.mean(0), e1, e2 / np.linalg.norm(e2), n)


@dataclass(frozen=True, eq=False)
class TexelGrid:
    """The texel raster of one surface.

    frame : its plane frame; texel : texel size (m); s0, t1 : plane coordinates of the grid's top-left corner;
    shape : (rows, cols); ring_xy : (k, 2) float64 continuous texel coordinates of the ring vertices;
    mask : (rows, cols) bool, texels whose centre lies inside the ring
    """

    frame: PlaneFrame
    texel: float
    s0: float
    t1: float
    shape: tuple[int, int]
    ring_xy: np.ndarray
    mask: np.ndarray

    def centres(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """World points ``(n, 3)`` of the texel centres at integer ``rows, cols : (n,)``."""
        s = self.s0 + (cols + 0.5) * self.texel
        t = self.t1 - (rows + 0.5) * self.texel
        return self.frame.to_world(np.stack([s, t], axis=1))

    def texel_xy(self, xyz: np.ndarray) -> np.ndarray:
        """Continuous texel coordinates ``(n, 2)`` (x along columns, y along rows) of world points ``(n, 3)``."""
        st = self.frame.to_plane(xyz)
        return np.stack([(st[:, 0] - self.s0) / self.texel, (self.t1 - st[:, 1]) / self.texel], axis=1)


def texel_grid(ring_xyz: np.ndarray, texel: float) -> TexelGrid:
    """The texel grid of a ring ``(k, 3)`` at ``texel`` metres, centred on the ring's bounding rectangle."""
    import cv2

    frame = plane_frame(ring_xyz)
    st = frame.to_plane(ring_xyz)
    lo, hi = st.min(0), st.max(0)
    cols, rows = (max(1, int(np.ceil((hi[k] - lo[k]) / texel - 1e-9))) for k in (0, 1))
    s0 = 0.5 * (lo[0] + hi[0]) - 0.5 * cols * texel
    t1 = 0.5 * (lo[1] + hi[1]) + 0.5 * rows * texel
    ring_xy = np.stack([(st[:, 0] - s0) / texel, (t1 - st[:, 1]) / texel], axis=1)
    mask = np.zeros((rows, cols), np.uint8)
    shift = 8  # sub-texel precision of the polygon fill; OpenCV puts pixel centres at integers
    pts = np.round((ring_xy - 0.5) * (1 << shift)).astype(np.int32)
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=shift)
    if not mask.any():  # a sliver thinner than a texel still gets the texels it touches
        cv2.polylines(mask, [pts], True, 1, lineType=cv2.LINE_8, shift=shift)
    return TexelGrid(frame, float(texel), float(s0), float(t1), (rows, cols), ring_xy, mask.astype(bool))


def ring_area(ring_xyz: np.ndarray) -> float:
    """Area of a planar 3-D ring ``(k, 3)`` (Newell)."""
    c = np.asarray(ring_xyz, np.float64)
    c = c - c.mean(0)
    return 0.5 * float(np.linalg.norm(np.cross(c, np.roll(c, -1, axis=0)).sum(0)))

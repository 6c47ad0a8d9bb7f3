"""Camera models: a pinhole with focal length in pixels, principal point and Brown distortion.

Pixel convention: ``(u, v)`` with the origin at the *centre* of the top-left pixel, u to the right and v down
(OpenCV). Formats that put the origin at the pixel's corner (COLMAP, BlocksExchange) convert at the reader.

Distortion is the Brown-Conrady model in OpenCV's form, applied to normalised coordinates ``x = X/Z, y = Y/Z``
of the OpenCV camera frame::

    r2 = x^2 + y^2
    x_d = x (1 + k1 r2 + k2 r2^2 + k3 r2^3) + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y (1 + k1 r2 + k2 r2^2 + k3 r2^3) + p1 (r2 + 2 y^2) + 2 p2 x y
    u = fx x_d + cx,  v = fy y_d + cy
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def distort(x: float | np.ndarray, y: float | np.ndarray, k1: float, k2: float, k3: float, p1: float, p2: float
            ) -> tuple[float | np.ndarray, float | np.ndarray]:
    """The distortion of the module docstring: normalised ``x, y`` (scalars, or arrays of one shape) -> ``x_d, y_d``
    (compiled: the bundle adjustment's projections call it per observation)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


@dataclass(frozen=True)
class CameraModel:
    """Interior orientation of one physical camera (one head of a multi-head system).

    Attributes
    ----------
    id : identifier, unique in a block
    width, height : image size in pixels
    fx, fy : focal length in pixels along u and v
    cx, cy : principal point in pixels (origin at the centre of the top-left pixel)
    k1, k2, k3, p1, p2 : Brown distortion, OpenCV convention
    pixel_size_mm : physical pixel pitch, when known (for focal lengths in mm and sensor sizes)
    """

    id: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    pixel_size_mm: float | None = None
    name: str = field(default="", compare=False)

    @property
    def K(self) -> np.ndarray:
        """Calibration matrix, (3, 3) float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """Distortion in OpenCV order ``(k1, k2, p1, p2, k3)``, (5,) float64."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in (self.k1, self.k2, self.k3, self.p1, self.p2))

    @property
    def focal_mm(self) -> float | None:
        """Focal length in millimetres along u, if the pixel size is known."""
        return None if self.pixel_size_mm is None else self.fx * self.pixel_size_mm

    def with_distortion(self, k1: float = 0.0, k2: float = 0.0, k3: float = 0.0, p1: float = 0.0,
                        p2: float = 0.0) -> CameraModel:
        """A copy with other distortion coefficients."""
        return replace(self, k1=k1, k2=k2, k3=k3, p1=p1, p2=p2)

    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply distortion to normalised coordinates. ``xy : (n, 2)`` -> ``(n, 2)``."""
        xy = np.asarray(xy, dtype=np.float64)
        xd, yd = distort(np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1]), self.k1, self.k2, self.k3,
                         self.p1, self.p2)
        return np.stack([xd, yd], axis=1)

    def undistort_normalized(self, xy_d: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Invert :meth:`distort_normalized` by fixed-point iteration. ``xy_d : (n, 2)`` -> ``(n, 2)``.

        Converges to better than 1e-10 for the distortions of aerial cameras (a few pixels at the corners).
        """
        xy_d = np.asarray(xy_d, dtype=np.float64)
        if not self.has_distortion:
            return xy_d.copy()
        xy = xy_d.copy()
        for _ in range(iterations):
            x, y = xy[:, 0], xy[:, 1]
            r2 = x * x + y * y
            radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
            dx = 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
            dy = self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
            xy = np.stack([(xy_d[:, 0] - dx) / radial, (xy_d[:, 1] - dy) / radial], axis=1)
        return xy

    def normalized_to_pixel(self, xy: np.ndarray, distort: bool = True) -> np.ndarray:
        """Normalised camera coordinates ``(n, 2)`` to pixels ``(n, 2)``."""
        xy = self.distort_normalized(xy) if distort and self.has_distortion else np.asarray(xy, np.float64)
        return np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], axis=1)

    def pixel_to_normalized(self, uv: np.ndarray, undistort: bool = True) -> np.ndarray:
        """Pixels ``(n, 2)`` to normalised (undistorted) camera coordinates ``(n, 2)``."""
        uv = np.asarray(uv, dtype=np.float64)
        xy = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)
        return self.undistort_normalized(xy) if undistort and self.has_distortion else xy

    def contains(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Mask of pixels inside the image (pixel centres from 0 to size-1, widened by ``margin``)."""
        uv = np.asarray(uv, dtype=np.float64)
        return (
            (uv[:, 0] >= -0.5 + margin) & (uv[:, 0] <= self.width - 0.5 - margin)
            & (uv[:, 1] >= -0.5 + margin) & (uv[:, 1] <= self.height - 0.5 - margin)
        )

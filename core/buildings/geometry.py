"""Small geometric helpers of the building reconstruction: planes, lines, point-in-polygon, edge distance."""

from __future__ import annotations

import numpy as np


def fit_plane(xyz: np.ndarray, robust: bool = False) -> tuple[np.ndarray, float]:
    """Total-least-squares plane of points (n, 3) -> ((4,) plane n.x + d = 0 with unit n, RMS residual).

    ``robust`` refits twice without the points beyond 2.5 robust sigmas (walls under an eave, chimneys).
    """
    p = np.asarray(xyz, dtype=np.float64)
    keep = np.ones(len(p), bool)
    for it in range(3 if robust else 1):
        c = p[keep].mean(0)
        _, _, vt = np.linalg.svd(p[keep] - c, full_matrices=False)
        n = vt[2]
        r = (p - c) @ n
        if it < 2 and robust:
            s = 1.4826 * np.median(np.abs(r[keep])) + 1e-6
            new = np.abs(r) < 2.5 * s
            if new.sum() < 4:
                break
            keep = new
    rms = float(np.sqrt(np.mean(r[keep] ** 2)))
    return np.append(n, -n @ c), rms


def plane_line(p1: np.ndarray, p2: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Intersection line of two planes (4,) as (point (3,), unit direction (3,)); None when parallel."""
    d = np.cross(p1[:3], p2[:3])
    nd = np.linalg.norm(d)
    if nd < 1e-6:
        return None
    d = d / nd
    A = np.stack([p1[:3], p2[:3], d])
    x = np.linalg.solve(A, np.array([-p1[3], -p2[3], 0.0]))
    return x, d


def line_line_closest(l1: tuple[np.ndarray, np.ndarray],
                      l2: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """End points of the shortest segment between two lines (point, direction)."""
    p, u = l1
    q, v = l2
    w = p - q
    a, b, c = u @ u, u @ v, v @ v
    d, e = u @ w, v @ w
    den = a * c - b * b
    if abs(den) < 1e-12:
        return p, q + v * (e / c)
    s = (b * e - c * d) / den
    t = (a * e - b * d) / den
    return p + s * u, q + t * v


def points_in_polygon(xy: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd test of points (n, 2) against a polygon (m, 2) -> (n,) bool."""
    x, y = xy[:, 0], xy[:, 1]
    inside = np.zeros(len(xy), bool)
    m = len(polygon)
    for i in range(m):
        x1, y1 = polygon[i]
        x2, y2 = polygon[(i + 1) % m]
        cond = (y1 > y) != (y2 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xi = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
        inside ^= cond & (x < xi)
    return inside


def distance_to_edges(xy: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Distance ``(n,)`` of points ``xy (n, 2)`` to the nearest edge of the closed polygon ``polygon (m, 2)``."""
    from ..matching.features import segment_distance

    d = np.full(len(xy), np.inf)
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0)):
        d = np.minimum(d, segment_distance(xy, np.broadcast_to(a, xy.shape), np.broadcast_to(b, xy.shape)))
    return d


def polygon_area(polygon: np.ndarray) -> float:
    """Signed area of a 2D polygon (m, 2): positive when counter-clockwise."""
    x, y = polygon[:, 0], polygon[:, 1]
    return float(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def top_of_rings(vertices: np.ndarray, rings: list[list[int]], xy: np.ndarray) -> np.ndarray:
    """Height ``(n,)`` of the highest of the planar ``rings`` (indices into ``vertices (v, 3)``) above points
    ``xy (n, 2)``, NaN where none covers a point; vertical rings are skipped."""
    top = np.full(len(xy), -np.inf)
    for ring in rings:
        r = vertices[list(ring)]
        n = np.cross(r[1:-1] - r[0], r[2:] - r[0]).sum(0)
        if abs(n[2]) < 1e-9 * max(np.linalg.norm(n), 1e-300):
            continue
        m = points_in_polygon(xy, r[:, :2])
        if m.any():
            c = r.mean(0)
            top[m] = np.maximum(top[m], c[2] - ((xy[m] - c[:2]) @ n[:2]) / n[2])
    return np.where(np.isfinite(top), top, np.nan)

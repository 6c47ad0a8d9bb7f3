"""Small exact 2-D helpers for the synthetic city: convex clipping and unions of axis-aligned rectangles.

The city's footprints are unions of rectangles in each building's local frame, so their outlines are computed
exactly on the grid of the rectangles' own edges (no polygon library needed).
"""

from __future__ import annotations

import numpy as np


def clip_halfplane(poly: np.ndarray, a: float, b: float, c: float, eps: float = 1e-12) -> np.ndarray:
    """Keep the part of a convex polygon where ``a x + b y + c <= 0`` (Sutherland-Hodgman, one edge).

    poly : (k, 2) float64 vertices in order; returns (k', 2), possibly empty.
    """
    if len(poly) == 0:
        return poly
    f = poly[:, 0] * a + poly[:, 1] * b + c
    out = []
    k = len(poly)
    for i in range(k):
        p, q = poly[i], poly[(i + 1) % k]
        fp, fq = f[i], f[(i + 1) % k]
        if fp <= eps:
            out.append(p)
        if (fp < -eps and fq > eps) or (fp > eps and fq < -eps):
            s = fp / (fp - fq)
            out.append(p + s * (q - p))
    return dedupe_ring(np.array(out, dtype=np.float64).reshape(-1, 2))


def dedupe_ring(poly: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Drop consecutive (cyclic) duplicate vertices. ``poly : (k, 2)``."""
    if len(poly) < 2:
        return poly
    keep = np.linalg.norm(poly - np.roll(poly, -1, axis=0), axis=1) > tol
    return poly[keep]


def polygon_area(poly: np.ndarray) -> float:
    """Signed area (counter-clockwise positive) of a polygon ``(k, 2)``."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def rect_union_outline(rects: list[tuple[float, float, float, float]]) -> list[np.ndarray]:
    """Outline rings of a union of axis-aligned rectangles ``(x0, y0, x1, y1)``.

    Returns a list of rings ``(k, 2)``; outer rings counter-clockwise, holes clockwise; collinear vertices
    removed. Exact: the union is rasterised on the grid of all rectangle edges and its boundary edges are chained.
    """
    xs = np.unique(np.array([v for r in rects for v in (r[0], r[2])], dtype=np.float64))
    ys = np.unique(np.array([v for r in rects for v in (r[1], r[3])], dtype=np.float64))
    occ = np.zeros((len(xs) - 1, len(ys) - 1), dtype=bool)
    for x0, y0, x1, y1 in rects:
        i0, i1 = np.searchsorted(xs, x0), np.searchsorted(xs, x1)
        j0, j1 = np.searchsorted(ys, y0), np.searchsorted(ys, y1)
        occ[i0:i1, j0:j1] = True
    pad = np.zeros((occ.shape[0] + 2, occ.shape[1] + 2), dtype=bool)
    pad[1:-1, 1:-1] = occ
    nxt: dict[tuple[int, int], tuple[int, int]] = {}
    # pad[i, j] spans x in [xs[i-1], xs[i]], y in [ys[j-1], ys[j]]; boundary edges keep the union on their left
    for i in range(pad.shape[0] - 1):
        for j in range(pad.shape[1] - 1):
            c = pad[i, j]
            if c != pad[i + 1, j]:  # vertical edge at x = xs[i]: northward when the west cell is occupied
                a, b = (i, j - 1), (i, j)
                if c:
                    nxt[a] = b
                else:
                    nxt[b] = a
            if c != pad[i, j + 1]:  # horizontal edge at y = ys[j]: westward when the south cell is occupied
                a, b = (i - 1, j), (i, j)
                if c:
                    nxt[b] = a
                else:
                    nxt[a] = b
    rings = []
    while nxt:
        start = next(iter(nxt))
        ring = [start]
        cur = nxt.pop(start)
        while cur != start:
            ring.append(cur)
            cur = nxt.pop(cur)
        pts = np.array([[xs[i], ys[j]] for i, j in ring], dtype=np.float64)
        # drop collinear vertices
        prev, nx_ = np.roll(pts, 1, axis=0), np.roll(pts, -1, axis=0)
        cross = (pts[:, 0] - prev[:, 0]) * (nx_[:, 1] - pts[:, 1]) - (pts[:, 1] - prev[:, 1]) * (nx_[:, 0] - pts[:, 0])
        rings.append(pts[np.abs(cross) > 1e-12])
    return rings


def point_in_rects(xy: np.ndarray, rects: list[tuple[float, float, float, float]], margin: float = 0.0) -> np.ndarray:
    """Mask ``(n,)`` of points ``xy : (n, 2)`` inside any rectangle grown by ``margin``."""
    xy = np.atleast_2d(xy)
    m = np.zeros(len(xy), dtype=bool)
    for x0, y0, x1, y1 in rects:
        m |= ((xy[:, 0] >= x0 - margin) & (xy[:, 0] <= x1 + margin)
              & (xy[:, 1] >= y0 - margin) & (xy[:, 1] <= y1 + margin))
    return m

"""The synthetic city: terrain, streets, trees and western-style buildings as one triangle mesh with semantics.

``make_city(seed)`` builds the embedded default scene deterministically. Every triangle carries a semantic code
(:data:`SEMANTIC`), a building id (-1 for none), a material id (see :class:`Material`) and texture coordinates in
metres for the procedural textures of :mod:`.render`. Ground truth objects (footprints, roof planes, eave and
ridge heights, overhang widths, windows, signalised targets) are kept beside the mesh in :class:`City`.

Coordinates are world metres of a projected CRS (default EPSG:25832) in float64, with a *local origin*
``City.origin`` near the city: renderers and ray casters work in ``xyz - origin`` (Open3D casts rays in float32,
which at E 500000 would only resolve a few centimetres).

Buildings are unions of *parts*: boxes with a roof made of planes (flat, gabled, hipped, shed, pyramid). A part is
one closed mesh: walls from below the terrain up to the roof slab, the roof top surface extended by the overhang
(0.2-1.2 m), vertical fascia, and the overhang underside; windows are recessed 0.12 m into the walls. Parts of one
building may overlap (an L-wing runs into the main house until its gable is hidden under the main roof), so the
building is the union of closed part meshes; the faces hidden inside another part are still labelled with their
semantics (they are never seen by a camera or the DSM).

Large areas (for the observation-only simulator): ``make_city(seed, tiles=(nx, ny), ground_cell=8.0)`` repeats
the 192 m x 144 m city tile on an nx x ny grid (each tile with its own seed, so buildings vary), with a coarser
terrain grid. Cost is about 1.3 s of CPU per tile (Python mesh building); ``City.scene()`` gives one Open3D
``RaycastingScene`` for visibility tests (in local coordinates: subtract ``City.origin``).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ComputationError, InputError
from ..pipeline.atomic import atomic_path, write_json
from .geometry2d import clip_halfplane, point_in_rects, polygon_area, rect_union_outline

SEMANTIC = {"ground": 0, "street": 1, "wall": 2, "roof": 3, "overhang_underside": 4, "window": 5, "tree": 6,
            "roof_installation": 7, "roof_edge": 8}
"""Semantic code per triangle. ``roof_installation``: chimneys and dormers (their windows are ``window``);
``roof_edge``: the vertical fascia at the border of a roof slab."""
SEMANTIC_NAMES = {v: k for k, v in SEMANTIC.items()}

TILE_SIZE = (192.0, 144.0)
"""Size of one city tile in metres (x, y); streets run along x = 96 k and y = 72 k (local coordinates)."""
STREET_HALF_WIDTH = 4.0
WINDOW_RECESS = 0.12
SLAB = 0.25
"""Vertical thickness of roof slabs, metres: walls end ``SLAB`` below the roof surface."""


@dataclass(frozen=True)
class Material:
    """A procedural material. ``kind`` selects the texture function of :mod:`.render`; colours are linear RGB
    albedo in [0, 1]; ``scale`` is the pattern size in metres (tiles: 0.73 x scale wide in rows of 1.1 x scale;
    bricks: length; wood: board width; metal: seam spacing; fields: field width; other kinds ignore it);
    ``seed`` offsets the noise so materials look different; ``param`` is kind-specific (the centre line coordinate
    of a street, NaN for none); ``axis`` 0/1 is a street's direction (along x / along y)."""

    name: str
    kind: str
    color: tuple[float, float, float]
    color2: tuple[float, float, float]
    scale: float = 1.0
    seed: int = 0
    param: float = float("nan")
    axis: int = 0


@dataclass
class Part:
    """One box of a building in the building's local frame (metres; z absolute).

    rect : (x0, y0, x1, y1); roof : flat, gable, hip, shed; axis : ridge direction ``x``/``y`` (gable, hip) or rise
    direction ``+x``, ``-x``, ``+y``, ``-y`` (shed); eave : absolute z of the roof surface above the wall line;
    slope : degrees; overhang : widths beyond the walls at edges x0, x1, y0, y1; base : z of the bottom face;
    kind : body, tower, dormer or chimney; windows : per wall edge (0 south y=y0, 1 east x=x1, 2 north y=y1,
    3 west x=x0) a list of ``(s0, s1, z0, z1)`` along the edge (counter-clockwise) and in absolute z.
    """

    rect: tuple[float, float, float, float]
    roof: str
    eave: float
    slope: float = 0.0
    axis: str = "x"
    overhang: tuple[float, float, float, float] = (0.3, 0.3, 0.3, 0.3)
    base: float = 0.0
    kind: str = "body"
    thickness: float = SLAB
    windows: dict[int, list[tuple[float, float, float, float]]] = field(default_factory=dict)

    def planes(self) -> list[tuple[float, float, float]]:
        """Roof planes ``z = a x + b y + c`` (local x, y); the roof surface is their lower envelope."""
        x0, y0, x1, y1 = self.rect
        s = float(np.tan(np.radians(self.slope)))
        e = self.eave
        px = [(s, 0.0, e - s * x0), (-s, 0.0, e + s * x1)]
        py = [(0.0, s, e - s * y0), (0.0, -s, e + s * y1)]
        if self.roof == "flat":
            return [(0.0, 0.0, e)]
        if self.roof == "gable":
            return py if self.axis == "x" else px
        if self.roof == "hip":
            return px + py
        if self.roof == "shed":
            return {"+x": [px[0]], "-x": [px[1]], "+y": [py[0]], "-y": [py[1]]}[self.axis]
        raise InputError(f"unknown roof type '{self.roof}'", field="roof")

    def z_top(self, xy: np.ndarray) -> np.ndarray:
        """Roof surface height at local points ``xy : (n, 2)`` (overhang included) -> ``(n,)``."""
        xy = np.atleast_2d(np.asarray(xy, np.float64))
        return np.min([a * xy[:, 0] + b * xy[:, 1] + c for a, b, c in self.planes()], axis=0)

    def ridge(self) -> float:
        """Highest roof point above the footprint (absolute z)."""
        x0, y0, x1, y1 = self.rect
        g = np.stack(np.meshgrid(np.linspace(x0, x1, 41), np.linspace(y0, y1, 41)), -1).reshape(-1, 2)
        return float(self.z_top(g).max())


@dataclass
class Building:
    """Ground truth of one building.

    id : building id (the ``building`` value of its triangles); name : recipe name; center : (2,) world xy of the
    local origin; rotation : degrees, local x axis counter-clockwise from east; ground_z : terrain at the centre;
    parts : the parts in local coordinates; footprint : world rings ``(k, 2)`` of the union of the wall
    rectangles of body/tower parts (outer rings counter-clockwise; overhangs excluded); roof_planes : dicts with
    ``part``, ``normal`` (3,), ``d`` (plane ``normal . x = d``), ``polygon`` (k, 3) world (overhang included),
    ``slope_deg``, ``kind`` (roof or roof_installation); windows : dicts with ``part``, ``edge``, ``corners``
    (4, 3) world corners in the facade plane (counter-clockwise seen from outside), ``recess``, ``normal``.
    """

    id: int
    name: str
    center: np.ndarray
    rotation: float
    ground_z: float
    parts: list[Part]
    footprint: list[np.ndarray] = field(default_factory=list)
    roof_planes: list[dict] = field(default_factory=list)
    windows: list[dict] = field(default_factory=list)

    def to_world(self, xy_local: np.ndarray) -> np.ndarray:
        """Local ``(n, 2)`` to world ``(n, 2)``."""
        c, s = np.cos(np.radians(self.rotation)), np.sin(np.radians(self.rotation))
        xy = np.atleast_2d(xy_local)
        return np.stack([c * xy[:, 0] - s * xy[:, 1], s * xy[:, 0] + c * xy[:, 1]], 1) + self.center

    def to_local(self, xy_world: np.ndarray) -> np.ndarray:
        """World ``(n, 2)`` to local ``(n, 2)``."""
        c, s = np.cos(np.radians(self.rotation)), np.sin(np.radians(self.rotation))
        d = np.atleast_2d(xy_world) - self.center
        return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1)

    def eave_ridge(self) -> list[dict]:
        """Per part: kind, roof type, eave z, ridge z (absolute), overhang widths per edge (x0, x1, y0, y1)."""
        return [{"part": i, "kind": p.kind, "roof": p.roof, "eave_z": p.eave, "ridge_z": p.ridge(),
                 "overhang": list(p.overhang)} for i, p in enumerate(self.parts)]

    def overhang_edges(self) -> list[dict]:
        """Per wall edge of body/tower parts: world segment (2, 2), overhang width, and whether the edge is
        exposed (not inside another part of the building, so its overhang can be seen)."""
        out = []
        rects = [p.rect for p in self.parts if p.kind in ("body", "tower")]
        for i, p in enumerate(self.parts):
            if p.kind not in ("body", "tower"):
                continue
            x0, y0, x1, y1 = p.rect
            corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
            widths = (p.overhang[2], p.overhang[1], p.overhang[3], p.overhang[0])
            others = [r for r in rects if r != p.rect]
            for e in range(4):
                a, b = corners[e], corners[(e + 1) % 4]
                mid = 0.5 * (a + b)
                out.append({"part": i, "edge": e, "segment": self.to_world(np.stack([a, b])).tolist(),
                            "width": float(widths[e]),
                            "exposed": not bool(point_in_rects(mid[None], others, margin=0.05)[0])})
        return out


class Terrain:
    """The known DTM: a tensor grid (dense in the city, growing outwards) split into triangles along the
    ``(i, j) -> (i+1, j+1)`` diagonal. :meth:`z` interpolates exactly as the mesh does (local coordinates)."""

    def __init__(self, xs: np.ndarray, ys: np.ndarray, z: np.ndarray) -> None:
        self.xs, self.ys, self.zg = np.asarray(xs, np.float64), np.asarray(ys, np.float64), np.asarray(z, np.float64)

    def z(self, xy_local: np.ndarray) -> np.ndarray:
        """Terrain height at local points ``(n, 2)`` -> ``(n,)`` (NaN outside the grid)."""
        xy = np.atleast_2d(np.asarray(xy_local, np.float64))
        i = np.clip(np.searchsorted(self.xs, xy[:, 0]) - 1, 0, len(self.xs) - 2)
        j = np.clip(np.searchsorted(self.ys, xy[:, 1]) - 1, 0, len(self.ys) - 2)
        fx = (xy[:, 0] - self.xs[i]) / (self.xs[i + 1] - self.xs[i])
        fy = (xy[:, 1] - self.ys[j]) / (self.ys[j + 1] - self.ys[j])
        z00, z10 = self.zg[i, j], self.zg[i + 1, j]
        z01, z11 = self.zg[i, j + 1], self.zg[i + 1, j + 1]
        low = fx >= fy
        out = np.where(low, z00 + fx * (z10 - z00) + fy * (z11 - z10), z00 + fy * (z01 - z00) + fx * (z11 - z01))
        outside = ((xy[:, 0] < self.xs[0]) | (xy[:, 0] > self.xs[-1])
                   | (xy[:, 1] < self.ys[0]) | (xy[:, 1] > self.ys[-1]))
        out[outside] = np.nan
        return out

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices ``(n, 3)`` local and triangles ``(m, 3)`` (counter-clockwise seen from above)."""
        nx, ny = len(self.xs), len(self.ys)
        gx, gy = np.meshgrid(self.xs, self.ys, indexing="ij")
        v = np.stack([gx.ravel(), gy.ravel(), self.zg.ravel()], 1)
        idx = np.arange(nx * ny).reshape(nx, ny)
        a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
        c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        tri = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
        return v, tri


class _MeshBuilder:
    """Collects triangles as explicit corner coordinates with their attributes, welds vertices at the end."""

    def __init__(self) -> None:
        self.tri: list[np.ndarray] = []
        self.uv: list[np.ndarray] = []
        self.sem: list[int] = []
        self.mat: list[int] = []

    def add_poly(self, pts: np.ndarray, uv: np.ndarray, normal: np.ndarray, sem: int, mat: int) -> None:
        """A planar polygon ``pts : (k, 3)`` with texture coordinates ``uv : (k, 2)``, wound so its normal
        agrees with ``normal``; fanned from its centroid when k > 3."""
        pts, uv = np.asarray(pts, np.float64), np.asarray(uv, np.float64)
        k = len(pts)
        if k < 3:
            return
        n = np.sum(np.cross(pts - pts.mean(0), np.roll(pts, -1, 0) - pts.mean(0)), axis=0)
        if np.linalg.norm(n) < 1e-10:
            return
        if np.dot(n, normal) < 0:
            pts, uv = pts[::-1], uv[::-1]
        if k == 3:
            self._add(pts, uv, sem, mat)
            return
        c, cu = pts.mean(0), uv.mean(0)
        for i in range(k):
            j = (i + 1) % k
            self._add(np.stack([c, pts[i], pts[j]]), np.stack([cu, uv[i], uv[j]]), sem, mat)

    def add_tri(self, pts: np.ndarray, uv: np.ndarray, normal: np.ndarray, sem: int, mat: int) -> None:
        n = np.cross(pts[1] - pts[0], pts[2] - pts[0])
        if np.dot(n, normal) < 0:
            pts, uv = pts[::-1], uv[::-1]
        self._add(pts, uv, sem, mat)

    def _add(self, pts: np.ndarray, uv: np.ndarray, sem: int, mat: int) -> None:
        if np.linalg.norm(np.cross(pts[1] - pts[0], pts[2] - pts[0])) < 1e-9:
            return
        self.tri.append(pts)
        self.uv.append(uv)
        self.sem.append(sem)
        self.mat.append(mat)

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Welded vertices (n, 3), triangles (m, 3), semantic (m,), material (m,), uv (m, 3, 2)."""
        corners = np.concatenate(self.tri).reshape(-1, 3)
        key = np.round(corners * 1e5).astype(np.int64)
        _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
        return (corners[first], inv.reshape(-1, 3), np.array(self.sem, np.uint8), np.array(self.mat, np.int32),
                np.stack(self.uv).astype(np.float32))


def _roof_uv(plane: tuple[float, float, float], xy: np.ndarray) -> np.ndarray:
    """Texture coordinates on a roof plane: u along the eave, v up the slope (slope distance), metres."""
    a, b, _ = plane
    g = float(np.hypot(a, b))
    if g < 1e-9:
        return xy.copy()
    up = np.array([a, b]) / g
    return np.stack([xy @ np.array([-up[1], up[0]]), (xy @ up) * np.sqrt(1.0 + g * g)], 1)


def _part_mesh(mb: _MeshBuilder, part: Part, mats: dict[str, int], installation: bool,
               uv_offset: np.ndarray) -> dict[int, np.ndarray]:
    """Add one closed part to ``mb`` (local coordinates). Returns the roof polygons per plane index."""
    x0, y0, x1, y1 = part.rect
    wx0, wx1, wy0, wy1 = part.overhang
    t = part.thickness
    planes = part.planes()
    sem_wall = SEMANTIC["roof_installation"] if installation else SEMANTIC["wall"]
    sem_roof = SEMANTIC["roof_installation"] if installation else SEMANTIC["roof"]
    sem_under = SEMANTIC["roof_installation"] if installation else SEMANTIC["overhang_underside"]
    sem_edge = SEMANTIC["roof_installation"] if installation else SEMANTIC["roof_edge"]
    ext = np.array([[x0 - wx0, y0 - wy0], [x1 + wx1, y0 - wy0], [x1 + wx1, y1 + wy1], [x0 - wx0, y1 + wy1]])
    roof_polys: dict[int, np.ndarray] = {}
    pieces: list[tuple[int, np.ndarray]] = []
    for i, (a, b, c) in enumerate(planes):
        poly = ext
        for j, (a2, b2, c2) in enumerate(planes):
            if j != i:
                poly = clip_halfplane(poly, a - a2, b - b2, c - c2)
        if abs(polygon_area(poly)) < 1e-9:
            continue
        roof_polys[i] = poly
        sub = [poly]
        for la, lb, lc in ((1.0, 0.0, -x0), (1.0, 0.0, -x1), (0.0, 1.0, -y0), (0.0, 1.0, -y1)):
            nxt = []
            for p in sub:
                for sg in (1.0, -1.0):
                    q = clip_halfplane(p, sg * la, sg * lb, sg * lc)
                    if abs(polygon_area(q)) > 1e-9:
                        nxt.append(q)
            sub = nxt
        pieces += [(i, q) for q in sub]
    up = np.array([0.0, 0.0, 1.0])
    all_pts = []
    for i, q in pieces:
        a, b, c = planes[i]
        z = a * q[:, 0] + b * q[:, 1] + c
        uv = _roof_uv(planes[i], q) + uv_offset
        mb.add_poly(np.column_stack([q, z]), uv, up, sem_roof, mats["roof"])
        cx, cy = q.mean(0)
        if not (x0 < cx < x1 and y0 < cy < y1):
            mb.add_poly(np.column_stack([q, z - t]), uv, -up, sem_under, mats["under"])
        all_pts.append(q)
    pts = np.concatenate(all_pts)

    def breakpoints(p_a: np.ndarray, p_b: np.ndarray) -> np.ndarray:
        """Sorted distinct positions along segment a->b of piece vertices lying on it."""
        d = p_b - p_a
        ln = float(np.linalg.norm(d))
        e = d / ln
        rel = pts - p_a
        off = np.abs(rel[:, 0] * e[1] - rel[:, 1] * e[0])
        s = rel @ e
        s = np.sort(np.concatenate([[0.0, ln], np.clip(s[(off < 1e-7) & (s > -1e-7) & (s < ln + 1e-7)], 0, ln)]))
        s = s[np.concatenate([[True], np.diff(s) > 1e-7])]
        s[-1] = ln
        return s

    # fascia along the extended border
    for k in range(4):
        pa, pb = ext[k], ext[(k + 1) % 4]
        e = (pb - pa) / np.linalg.norm(pb - pa)
        nrm = np.array([e[1], -e[0], 0.0])
        s = breakpoints(pa, pb)
        xy = pa + s[:, None] * e
        z = part.z_top(xy)
        for m in range(len(s) - 1):
            quad = np.array([[*xy[m], z[m]], [*xy[m + 1], z[m + 1]], [*xy[m + 1], z[m + 1] - t], [*xy[m], z[m] - t]])
            uv = np.array([[s[m], z[m]], [s[m + 1], z[m + 1]], [s[m + 1], z[m + 1] - t], [s[m], z[m] - t]])
            mb.add_poly(quad, uv + uv_offset, nrm, sem_edge, mats["fascia"])

    # walls with recessed windows; rows shared by the four walls so corners have no T-junctions
    fp = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    tops = []
    for k in range(4):
        pa, pb = fp[k], fp[(k + 1) % 4]
        s = breakpoints(pa, pb)
        e = (pb - pa) / np.linalg.norm(pb - pa)
        tops.append((s, part.z_top(pa + s[:, None] * e) - t))
    z_band = min(float(h.min()) for _, h in tops) - 0.1
    rows = {part.base, z_band}
    for wins in part.windows.values():
        for _, _, wz0, wz1 in wins:
            rows |= {wz0, wz1}
    rows_z = np.array(sorted(rows))
    bottom_ring = []
    for k in range(4):
        pa, pb = fp[k], fp[(k + 1) % 4]
        ln = float(np.linalg.norm(pb - pa))
        e2 = (pb - pa) / ln
        s_start = float(pa @ e2) + 50.0 * float(pa @ np.array([e2[1], -e2[0]]))  # same for coplanar walls
        e = np.array([e2[0], e2[1], 0.0])
        nrm = np.array([e2[1], -e2[0], 0.0])
        p3 = np.array([pa[0], pa[1], 0.0])
        wins = part.windows.get(k, [])
        cols = {0.0, ln}
        for ws0, ws1, _, _ in wins:
            cols |= {ws0, ws1}
        cols_s = np.array(sorted(cols))

        def at(s: float, z: float, depth: float = 0.0, e=e, p3=p3, nrm=nrm) -> np.ndarray:
            return p3 + s * e + np.array([0.0, 0.0, z]) - depth * nrm

        def win_of(sc: float, zc: float, wins=wins) -> tuple | None:
            for w in wins:
                if w[0] < sc < w[1] and w[2] < zc < w[3]:
                    return w
            return None

        nc, nr = len(cols_s) - 1, len(rows_z) - 1
        is_win = np.zeros((nc, nr), dtype=bool)
        for ci in range(nc):
            for ri in range(nr):
                is_win[ci, ri] = win_of(0.5 * (cols_s[ci] + cols_s[ci + 1]), 0.5 * (rows_z[ri] + rows_z[ri + 1])) \
                    is not None
        for ci in range(nc):
            sa, sb = cols_s[ci], cols_s[ci + 1]
            for ri in range(nr):
                za, zb = rows_z[ri], rows_z[ri + 1]
                if not is_win[ci, ri]:
                    quad = np.array([at(sa, za), at(sb, za), at(sb, zb), at(sa, zb)])
                    uv = np.array([[sa, za], [sb, za], [sb, zb], [sa, zb]]) + [s_start, 0.0]
                    mb.add_poly(quad, uv + uv_offset, nrm, sem_wall, mats["wall"])
                    continue
                d = WINDOW_RECESS
                w = win_of(0.5 * (sa + sb), 0.5 * (za + zb))
                hw, hh = 0.5 * (w[1] - w[0]), 0.5 * (w[3] - w[2])
                sc, zc = 0.5 * (w[0] + w[1]), 0.5 * (w[2] + w[3])
                quad = np.array([at(sa, za, d), at(sb, za, d), at(sb, zb, d), at(sa, zb, d)])
                uv = np.array([[(sa - sc) / hw, (za - zc) / hh], [(sb - sc) / hw, (za - zc) / hh],
                               [(sb - sc) / hw, (zb - zc) / hh], [(sa - sc) / hw, (zb - zc) / hh]])
                mb.add_poly(quad, uv, nrm, SEMANTIC["window"], mats["glass"])
                sides = (  # (neighbour is window?, edge endpoints, inward normal)
                    (ci > 0 and is_win[ci - 1, ri], (sa, za), (sa, zb), e),
                    (ci < nc - 1 and is_win[ci + 1, ri], (sb, za), (sb, zb), -e),
                    (ri > 0 and is_win[ci, ri - 1], (sa, za), (sb, za), np.array([0.0, 0.0, 1.0])),
                    (ri < nr - 1 and is_win[ci, ri + 1], (sa, zb), (sb, zb), np.array([0.0, 0.0, -1.0])),
                )
                for nb_win, (s1, z1), (s2, z2), inward in sides:
                    if nb_win:
                        continue
                    quad = np.array([at(s1, z1), at(s2, z2), at(s2, z2, d), at(s1, z1, d)])
                    uv = np.array([[s1, z1], [s2, z2], [s2 + d, z2 + d], [s1 + d, z1 + d]]) + [s_start, 0.0]
                    mb.add_poly(quad, uv + uv_offset, inward, sem_wall, mats["wall"])
        # band between the last row and the roof slab: zipper of the two chains
        s_top, h_top = tops[k]
        bot = [(s, z_band) for s in cols_s]
        top = list(zip(s_top, h_top, strict=True))
        i = j = 0
        while i < len(bot) - 1 or j < len(top) - 1:
            if j == len(top) - 1 or (i < len(bot) - 1 and bot[i + 1][0] <= top[j + 1][0]):
                tri = [bot[i], bot[i + 1], top[j]]
                i += 1
            else:
                tri = [bot[i], top[j + 1], top[j]]
                j += 1
            p = np.array([at(s, z) for s, z in tri])
            uv = np.array(tri) + [s_start, 0.0]
            if np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0])) > 1e-9:
                mb.add_tri(p, uv + uv_offset, nrm, sem_wall, mats["wall"])
        bottom_ring += [at(s, part.base) for s in cols_s[:-1]]
    ring = np.array(bottom_ring)
    mb.add_poly(ring, ring[:, :2], -up, sem_wall, mats["wall"])
    return roof_polys


# ----------------------------------------------------------------------------------------------------------------
# building recipes (local frame, metres); each returns parts with absolute z from the building's ground level g


def _gable(rect, eave, slope, axis="x", ov=(0.5, 0.5, 0.5, 0.5), kind="body") -> Part:
    return Part(rect=tuple(map(float, rect)), roof="gable", eave=eave, slope=slope, axis=axis,
                overhang=tuple(map(float, ov)), kind=kind)


def _embed(main: Part, wing: Part, side: str) -> Part:
    """Extend ``wing`` into ``main`` (across main's wall on ``side`` of main: y0, y1, x0 or x1) until the wing's
    highest point is hidden under main's roof slab (or the wing reaches 70 % across main)."""
    x0, y0, x1, y1 = main.rect
    wx0, wy0, wx1, wy1 = wing.rect
    span = (y1 - y0) if side in ("y0", "y1") else (x1 - x0)
    for d in np.arange(0.6, 0.7 * span, 0.1):
        r = {"y0": (wx0, wy0, wx1, y0 + d), "y1": (wx0, y1 - d, wx1, wy1),
             "x0": (wx0, wy0, x0 + d, wy1), "x1": (x1 - d, wy0, wx1, wy1)}[side]
        trial = Part(**{**wing.__dict__, "rect": r})
        edge = {"y0": [(r[0], r[3]), (r[2], r[3])], "y1": [(r[0], r[1]), (r[2], r[1])],
                "x0": [(r[2], r[1]), (r[2], r[3])], "x1": [(r[0], r[1]), (r[0], r[3])]}[side]
        probe = np.linspace(edge[0], edge[1], 9)
        probe = probe + np.array({"y0": (0, 0.2), "y1": (0, -0.2), "x0": (0.2, 0), "x1": (-0.2, 0)}[side])
        if main.z_top(probe).min() - main.thickness > trial.ridge() + 0.05:
            return trial
    return trial


def _recipes() -> list[tuple[str, object]]:
    """(name, builder(rng, g) -> parts) for the 15 buildings of a tile; dimensions jittered by ``rng``."""

    def j(rng, v, f=0.1):
        return float(v * (1.0 + rng.uniform(-f, f)))

    def gable_house(rng, g):
        p = _gable((-6, -4.5, 6, 4.5), g + j(rng, 6.0), j(rng, 40, 0.1), "x", (0.4, 0.4, 0.7, 0.7))
        return [p]

    def hip_house(rng, g):
        return [Part((-7.0, -5.0, 7.0, 5.0), "hip", g + j(rng, 6.5), j(rng, 30), "x", (0.8, 0.8, 0.8, 0.8))]

    def flat_office(rng, g):
        return [Part((-12.0, -7.0, 12.0, 7.0), "flat", g + j(rng, 12.0), 0.0, "x", (0.25,) * 4)]

    def shed_house(rng, g):
        return [Part((-6.0, -4.0, 6.0, 4.0), "shed", g + j(rng, 5.0), j(rng, 15), "+y", (0.5, 0.5, 1.0, 0.3))]

    def l_gable(rng, g):
        main = _gable((-10, -5, 10, 5), g + 7.0, 42, "x", (0.4, 0.4, 0.6, 0.6))
        wing = _gable((2, -14, 10, -5), g + 5.5, 42, "y", (0.5, 0.5, 0.4, 0.2))
        return [main, _embed(main, wing, "y0")]

    def t_mixed(rng, g):
        main = Part((-11.0, -5.0, 11.0, 5.0), "hip", g + 7.0, 35.0, "x", (0.6,) * 4)
        stem = _gable((-4, -13, 4, -5), g + 7.0, 35, "y", (0.5, 0.5, 0.5, 0.2))
        return [main, _embed(main, stem, "y0")]

    def u_mixed(rng, g):
        main = _gable((-12, -4, 12, 4), g + 8.0, 40, "x", (0.3, 0.3, 0.5, 0.5))
        w1 = Part((-12.0, -14.0, -5.0, -2.0), "flat", g + 6.0, 0.0, "x", (0.2, 0.2, 0.2, 0.0))
        w2 = Part((5.0, -14.0, 12.0, -2.0), "flat", g + 6.0, 0.0, "x", (0.2, 0.2, 0.2, 0.0))
        return [main, w1, w2]

    def stepped_flat(rng, g):
        return [Part((-15.0, -6.0, -4.5, 6.0), "flat", g + 15.0, 0.0, "x", (0.2,) * 4),
                Part((-5.0, -5.0, 5.0, 5.0), "flat", g + 11.0, 0.0, "x", (0.0, 0.2, 0.2, 0.2)),
                Part((4.5, -4.0, 14.0, 4.0), "flat", g + 7.0, 0.0, "x", (0.0, 0.2, 0.2, 0.2))]

    def church(rng, g):
        nave = _gable((-12, -5, 10, 5), g + 9.0, 50, "x", (0.4, 0.2, 0.5, 0.5))
        tower = Part((9.5, -3.0, 15.5, 3.0), "hip", g + 22.0, 65.0, "x", (0.3,) * 4, kind="tower")
        return [nave, tower]

    def l_flat_shed(rng, g):
        main = Part((-9.0, -6.0, 9.0, 6.0), "flat", g + 9.0, 0.0, "x", (0.3,) * 4)
        wing = Part((-9.0, 6.0, -1.0, 13.0), "shed", g + 4.0, 15.0, "-y", (0.4, 0.4, 0.0, 0.9))
        return [main, _embed(main, wing, "y1")]

    def split_gable(rng, g):
        return [_gable((-10, -5, 0.5, 5), g + 7.0, 40, "x", (0.5, 0.0, 0.6, 0.6)),
                _gable((0, -4.5, 10, 4.5), g + 5.5, 40, "x", (0.0, 0.5, 0.5, 0.5))]

    def hip_dormers(rng, g):
        return [Part((-9.0, -6.0, 9.0, 6.0), "hip", g + 6.0, 38.0, "x", (0.9,) * 4)]

    def gable_dormers(rng, g):
        return [_gable((-8, -5.5, 8, 5.5), g + 5.0, 48, "x", (0.3, 0.3, 0.5, 0.5))]

    def alpine(rng, g):
        return [_gable((-7, -6, 7, 6), g + 6.0, 25, "y", (1.2, 1.2, 1.2, 1.2))]

    def l_hip(rng, g):
        main = Part((-10.0, -5.0, 10.0, 5.0), "hip", g + 7.0, 35.0, "x", (0.6,) * 4)
        wing = Part((3.0, -13.0, 10.0, -5.0), "hip", g + 4.5, 35.0, "y", (0.6, 0.6, 0.6, 0.2))
        return [main, _embed(main, wing, "y0")]

    return [("gable_house", gable_house), ("hip_house", hip_house), ("flat_office", flat_office),
            ("shed_house", shed_house), ("l_gable", l_gable), ("t_mixed", t_mixed), ("u_mixed", u_mixed),
            ("stepped_flat", stepped_flat), ("church", church), ("l_flat_shed", l_flat_shed),
            ("split_gable", split_gable), ("hip_dormers", hip_dormers), ("gable_dormers", gable_dormers),
            ("alpine", alpine), ("l_hip", l_hip)]


DORMERS = {"hip_dormers": [(-2.5, "y0"), (2.5, "y0")], "gable_dormers": [(-3.5, "y0"), (3.0, "y0"), (0.0, "y1")],
           "l_gable": [(-5.0, "y1")]}
CHIMNEYS = {"gable_house": [(2.5, 1.2)], "hip_dormers": [(-1.0, 1.5)], "alpine": [(1.5, -2.0)],
            "flat_office": [(6.0, 2.0)], "church": [(-6.0, -2.0)]}


def _dormer(main: Part, xc: float, side: str) -> Part:
    """A gabled dormer on the y0 (south) or y1 (north) slope of ``main`` (gable along x or hip), centred at
    local x = ``xc``; its back runs into the main roof until hidden."""
    x0, y0, x1, y1 = main.rect
    wd, front = 2.2, 1.0
    yf = y0 + front if side == "y0" else y1 - front
    zf = float(main.z_top(np.array([[xc, yf]]))[0])
    eave = zf + 1.4
    if side == "y0":
        part = Part((xc - wd / 2, yf, xc + wd / 2, yf + 0.5), "gable", eave, 45.0, "y", (0.15, 0.15, 0.15, 0.0),
                    base=zf - 0.6, kind="dormer", thickness=0.12)
    else:
        part = Part((xc - wd / 2, yf - 0.5, xc + wd / 2, yf), "gable", eave, 45.0, "y", (0.15, 0.15, 0.0, 0.15),
                    base=zf - 0.6, kind="dormer", thickness=0.12)
    # grow the dormer backwards (into the roof) until its ridge is below the main roof slab
    for d in np.arange(0.5, 0.6 * (y1 - y0), 0.1):
        r = (part.rect[0], yf, part.rect[2], yf + d) if side == "y0" else (part.rect[0], yf - d, part.rect[2], yf)
        back_y = r[3] - 0.15 if side == "y0" else r[1] + 0.15
        trial = Part(**{**part.__dict__, "rect": r})
        probe = np.stack([np.linspace(r[0] - 0.2, r[2] + 0.2, 7), np.full(7, back_y)], 1)
        if main.z_top(probe).min() - main.thickness > trial.ridge() + 0.1:
            part = trial
            break
    else:
        raise ComputationError(f"dormer at x={xc} does not fit under the main roof")
    # one window in the dormer's front wall (edge 0 faces y0, edge 2 faces y1)
    sill = zf + 0.25
    top = eave - part.thickness - 0.35
    edge = 0 if side == "y0" else 2
    part.windows = {edge: [(0.6, 1.6, sill, top)]}
    return part


def _chimney(main: Part, xc: float, yc: float) -> Part:
    r = (xc - 0.35, yc - 0.35, xc + 0.35, yc + 0.35)
    sq = np.array([[r[0], r[1]], [r[2], r[1]], [r[2], r[3]], [r[0], r[3]]])
    zmin, zmax = float(main.z_top(sq).min()), float(main.z_top(sq).max())
    return Part(r, "flat", max(zmax, main.ridge() - 1.0) + 1.0, 0.0, "x", (0.06,) * 4, base=zmin - 0.6,
                kind="chimney", thickness=0.1)


def _free_intervals(a: np.ndarray, b: np.ndarray, others: list, margin: float) -> list[tuple[float, float]]:
    """Intervals of segment a->b (as arc lengths) not within ``margin`` of any rectangle of ``others``."""
    ln = float(np.linalg.norm(b - a))
    s = np.linspace(0.0, ln, int(ln / 0.05) + 1)
    pts = a + np.outer(s / ln, b - a)
    free = ~point_in_rects(pts, others, margin)
    out, start = [], None
    for k in range(len(s)):
        if free[k] and start is None:
            start = s[k]
        if (not free[k] or k == len(s) - 1) and start is not None:
            end = s[k] if free[k] else s[k - 1]
            out.append((float(start), float(end)))
            start = None
    return out


def _auto_windows(parts: list[Part], g: float, terrain_max: float, rng: np.random.Generator) -> None:
    """Window grids on the exposed walls of body/tower parts: floors every 3 m, columns every ~2.6-3.2 m."""
    spacing = float(rng.uniform(2.6, 3.2))
    wwidth = float(rng.uniform(1.0, 1.3))
    wheight = float(rng.uniform(1.3, 1.5))
    for p in parts:
        if p.kind not in ("body", "tower"):
            continue
        others = [q.rect for q in parts if q is not p and q.kind in ("body", "tower")]
        x0, y0, x1, y1 = p.rect
        fp = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        for k in range(4):
            a, b = fp[k], fp[(k + 1) % 4]
            wall_top = p.eave - p.thickness
            floors = []
            z = max(g + 1.0, terrain_max + 0.8)
            while z + wheight < wall_top - 0.6:
                floors.append(z)
                z += 3.0
            if p.kind == "tower" and floors:
                floors = floors[-2:]
            wins = []
            for s0, s1 in _free_intervals(a, b, others, 0.4):
                s0, s1 = s0 + 0.7, s1 - 0.7
                n = int((s1 - s0 + spacing - wwidth) // spacing)
                if n < 1:
                    continue
                start = 0.5 * (s0 + s1) - 0.5 * ((n - 1) * spacing + wwidth)
                for c in range(n):
                    ws = start + c * spacing
                    for fz in floors:
                        wins.append((round(ws, 6), round(ws + wwidth, 6), round(fz, 6), round(fz + wheight, 6)))
            if wins:
                p.windows[k] = wins


# ----------------------------------------------------------------------------------------------------------------


@dataclass(eq=False)
class City:
    """The synthetic city (see the module docstring).

    Attributes
    ----------
    crs : EPSG code of the world coordinates
    origin : (3,) float64 local origin (world x, y, 0): renderers use ``vertices - origin``
    vertices : (n, 3) float64 world coordinates
    triangles : (m, 3) int64
    semantic : (m,) uint8 codes of :data:`SEMANTIC`
    building : (m,) int32 building id, -1 for none
    material : (m,) int32 index into ``materials``
    uv : (m, 3, 2) float32 texture coordinates per corner, metres (windows: [-1, 1] across the opening)
    materials : procedural materials
    buildings : ground truth per building
    terrain : the DTM (local coordinates); use :meth:`terrain_z` for world coordinates
    streets : dicts with ``axis`` (0: along x, 1: along y), ``center`` (local), ``half_width``, ``range``
    trees : (k, 5) local x, y, ground z, crown radius, total height
    targets : (t, 3) float64 world centres of the signalised ground targets (painted discs)
    target_names : their names
    target_pattern : ``disc`` (a white disc on a black square) or ``cross`` (two white bars, :data:`TARGET_BAR` wide
        on either side of their axes, reaching :data:`TARGET_HALF` from the centre, along the grid)
    core : (4,) world bbox (xmin, ymin, xmax, ymax) of the built-up area
    extent : (4,) world bbox of the terrain
    seed : the seed it was built from
    """

    crs: str
    origin: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    semantic: np.ndarray
    building: np.ndarray
    material: np.ndarray
    uv: np.ndarray
    materials: list[Material]
    buildings: list[Building]
    terrain: Terrain
    streets: list[dict]
    trees: np.ndarray
    targets: np.ndarray
    target_names: list[str]
    core: np.ndarray
    extent: np.ndarray
    seed: int = 0
    target_pattern: str = "disc"
    _scene: object = field(default=None, repr=False)

    TARGET_RADIUS = 0.5
    """Radius of the white disc of a signalised target, metres (on a 1.6 m black square)."""
    TARGET_HALF = 0.8
    TARGET_BAR = 0.15
    """Half width of a cross target's bars, metres."""

    def __getstate__(self) -> dict:
        """Pickle without the Open3D scene (rebuilt on demand in the receiving process)."""
        return {**self.__dict__, "_scene": None}

    def terrain_z(self, xy_world: np.ndarray) -> np.ndarray:
        """The known DTM: terrain height at world points ``(n, 2)`` -> ``(n,)`` (NaN outside)."""
        return self.terrain.z(np.atleast_2d(xy_world)[:, :2] - self.origin[:2])

    def scene(self):
        """One Open3D ``RaycastingScene`` of the whole city in *local* coordinates (``xyz - origin``, float32);
        geometry ids are 0 and primitive ids index ``triangles``."""
        if self._scene is None:
            import open3d as o3d

            sc = o3d.t.geometry.RaycastingScene()
            sc.add_triangles((self.vertices - self.origin).astype(np.float32), self.triangles.astype(np.uint32))
            self._scene = sc
        return self._scene

    def face_normals(self) -> np.ndarray:
        """Unit normals ``(m, 3)`` of the triangles (outward for closed parts, up for the ground)."""
        v = self.vertices - self.origin
        t = self.triangles
        n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    def all_windows(self) -> list[dict]:
        """Every window of every building (dicts of :class:`Building` plus ``building``)."""
        return [{**w, "building": b.id} for b in self.buildings for w in b.windows]

    def part_mesh(self, building_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Vertices and triangles of one building (all parts)."""
        sel = np.flatnonzero(self.building == building_id)
        tri = self.triangles[sel]
        used, inv = np.unique(tri, return_inverse=True)
        return self.vertices[used], inv.reshape(-1, 3)

    # -------------------------------------------------------------------------------- persistence

    def save(self, folder: str | Path) -> None:
        """Write ``city.npz`` (arrays), ``city.json`` (materials, buildings, streets, targets) and ``city.ply``."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_path(folder / "city.npz") as tmp:
            np.savez_compressed(tmp, origin=self.origin, vertices=self.vertices, triangles=self.triangles,
                                semantic=self.semantic, building=self.building, material=self.material, uv=self.uv,
                                trees=self.trees, targets=self.targets, core=self.core, extent=self.extent,
                                terrain_xs=self.terrain.xs, terrain_ys=self.terrain.ys, terrain_z=self.terrain.zg)
        write_json(folder / "city.json", {
            "format": "oblique_city.city", "version": 1, "crs": self.crs, "seed": self.seed,
            "semantic": SEMANTIC, "materials": [asdict(m) for m in self.materials],
            "streets": self.streets, "target_names": self.target_names,
            "buildings": [_building_to_dict(b) for b in self.buildings],
        })
        write_ply(folder / "city.ply", self.vertices, self.triangles,
                  {"semantic": self.semantic, "building": self.building, "material": self.material})

    @classmethod
    def load(cls, folder: str | Path) -> City:
        """Read a city written by :meth:`save`."""
        folder = Path(folder)
        try:
            z = np.load(folder / "city.npz")
            with open(folder / "city.json", encoding="utf-8") as f:
                d = json.load(f)
        except FileNotFoundError as e:
            raise InputError("city file missing", path=e.filename) from None
        if d.get("format") != "oblique_city.city":
            raise InputError("not an Oblique City city file", path=folder / "city.json", field="format")
        mats = [Material(**{**m, "color": tuple(m["color"]), "color2": tuple(m["color2"])}) for m in d["materials"]]
        return cls(crs=d["crs"], origin=z["origin"], vertices=z["vertices"], triangles=z["triangles"],
                   semantic=z["semantic"], building=z["building"], material=z["material"], uv=z["uv"],
                   materials=mats, buildings=[_building_from_dict(b) for b in d["buildings"]],
                   terrain=Terrain(z["terrain_xs"], z["terrain_ys"], z["terrain_z"]), streets=d["streets"],
                   trees=z["trees"], targets=z["targets"], target_names=d["target_names"], core=z["core"],
                   extent=z["extent"], seed=int(d["seed"]))


def _building_to_dict(b: Building) -> dict:
    return {"id": b.id, "name": b.name, "center": b.center.tolist(), "rotation": b.rotation, "ground_z": b.ground_z,
            "parts": [{**p.__dict__, "windows": {str(k): v for k, v in p.windows.items()}} for p in b.parts],
            "footprint": [r.tolist() for r in b.footprint],
            "roof_planes": [{k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()}
                            for r in b.roof_planes],
            "windows": [{k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in w.items()}
                        for w in b.windows],
            "eave_ridge": b.eave_ridge(), "overhang_edges": b.overhang_edges()}


def _building_from_dict(d: dict) -> Building:
    parts = []
    for p in d["parts"]:
        p = dict(p)
        p["rect"] = tuple(p["rect"])
        p["overhang"] = tuple(p["overhang"])
        p["windows"] = {int(k): [tuple(w) for w in v] for k, v in p["windows"].items()}
        parts.append(Part(**p))
    return Building(
        id=d["id"], name=d["name"], center=np.asarray(d["center"]), rotation=d["rotation"], ground_z=d["ground_z"],
        parts=parts, footprint=[np.asarray(r) for r in d["footprint"]],
        roof_planes=[{**r, "normal": np.asarray(r["normal"]), "polygon": np.asarray(r["polygon"])}
                     for r in d["roof_planes"]],
        windows=[{**w, "corners": np.asarray(w["corners"]), "normal": np.asarray(w["normal"])} for w in d["windows"]])


def write_ply(path: str | Path, vertices: np.ndarray, triangles: np.ndarray, face_attrs: dict[str, np.ndarray]) -> None:
    """Binary little-endian PLY with float64 vertices and int32 face attributes (e.g. semantic, building)."""
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}",
              "property double x", "property double y", "property double z", f"element face {len(triangles)}",
              "property list uchar int vertex_indices"]
    header += [f"property int {k}" for k in face_attrs]
    header.append("end_header")
    dt = np.dtype([("n", "u1"), ("v", "<i4", (3,))] + [(k, "<i4") for k in face_attrs])
    faces = np.empty(len(triangles), dtype=dt)
    faces["n"] = 3
    faces["v"] = triangles
    for k, v in face_attrs.items():
        faces[k] = v
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(np.asarray(vertices, "<f8").tobytes())
        f.write(faces.tobytes())


# ----------------------------------------------------------------------------------------------------------------


_PLASTER = [(0.85, 0.80, 0.68), (0.88, 0.82, 0.55), (0.85, 0.62, 0.50), (0.88, 0.88, 0.85), (0.70, 0.75, 0.80),
            (0.80, 0.65, 0.40), (0.75, 0.78, 0.65)]
_BRICK = [(0.55, 0.27, 0.18), (0.78, 0.66, 0.45), (0.50, 0.32, 0.25)]
_TILES = [(0.62, 0.25, 0.15), (0.45, 0.25, 0.15), (0.22, 0.22, 0.24), (0.72, 0.38, 0.20), (0.55, 0.30, 0.25)]
_FLAT = [(0.50, 0.50, 0.48), (0.28, 0.28, 0.29), (0.35, 0.45, 0.25)]


def _lin(c: tuple[float, float, float], rng: np.random.Generator, jitter: float = 0.04) -> tuple[float, ...]:
    """sRGB-ish colour with a little jitter to linear albedo."""
    return tuple(float(np.clip(v + rng.uniform(-jitter, jitter), 0.02, 0.98) ** 2.2) for v in c)


def _terrain(seed: int, x_lo: float, x_hi: float, y_lo: float, y_hi: float, margin: float,
             cell: float) -> Terrain:
    """Gentle relief (a few metres over hundreds of metres) on a grid dense over the core, growing outside."""
    rng = np.random.default_rng(seed + 7919)

    def axis(lo: float, hi: float) -> np.ndarray:
        core = np.arange(lo, hi + 0.5 * cell, cell)
        out_l, out_r, step, a, b = [], [], cell, core[0], core[-1]
        while a > lo - margin:
            step = min(step * 1.25, 40.0)
            a, b = a - step, b + step
            out_l.append(a)
            out_r.append(b)
        return np.concatenate([out_l[::-1], core, out_r])

    xs, ys = axis(x_lo, x_hi), axis(y_lo, y_hi)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    z = np.full(gx.shape, 108.0)
    for _ in range(4):
        k = rng.uniform(2 * np.pi / 700, 2 * np.pi / 250, 2) * rng.choice([-1, 1], 2)
        z += rng.uniform(0.8, 2.5) * np.sin(k[0] * gx + k[1] * gy + rng.uniform(0, 2 * np.pi))
    z += rng.uniform(-0.01, 0.01) * gx + rng.uniform(-0.01, 0.01) * gy
    return Terrain(xs, ys, z)


def make_city(seed: int = 0, tiles: tuple[int, int] = (1, 1), crs: str = "EPSG:25832",
              center: tuple[float, float] = (500000.0, 5400000.0), margin: float = 700.0,
              ground_cell: float = 2.0) -> City:
    """Build the synthetic city deterministically from ``seed``.

    Parameters
    ----------
    seed : all random choices (dimensions, heights, colours, trees, terrain) follow from it
    tiles : (nx, ny) copies of the 192 m x 144 m city tile (15 buildings, a park, streets), each with its own
        variation; (1, 1) is the embedded default
    crs, center : world CRS and the world position of the centre of the built-up area
    margin : terrain extends this far (metres) beyond the built-up area, with cells growing to 40 m, so oblique
        views see ground up to their horizon limit
    ground_cell : terrain cell size in the built-up area (2 m by default; use 4-8 m for big tiled areas)

    Returns
    -------
    City, with about 200k triangles per tile at the defaults.
    """
    nx, ny = tiles
    tx, ty = TILE_SIZE
    hw = STREET_HALF_WIDTH
    x_lo, x_hi, y_lo, y_hi = -hw - 12.0, nx * tx + hw + 12.0, -hw - 12.0, ny * ty + hw + 12.0
    # snap the built-up box to the ground grid so street edges fall on grid lines
    x_lo, y_lo = np.floor(x_lo / ground_cell) * ground_cell, np.floor(y_lo / ground_cell) * ground_cell
    x_hi, y_hi = np.ceil(x_hi / ground_cell) * ground_cell, np.ceil(y_hi / ground_cell) * ground_cell
    origin = np.array([center[0] - nx * tx / 2, center[1] - ny * ty / 2, 0.0])
    terrain = _terrain(seed, x_lo, x_hi, y_lo, y_hi, margin, ground_cell)
    rng = np.random.default_rng(seed)
    materials: list[Material] = []

    def mat(name, kind, c1, c2=None, scale=1.0, param=float("nan"), axis=0) -> int:
        materials.append(Material(name, kind, c1, c2 if c2 is not None else c1, scale, len(materials), param, axis))
        return len(materials) - 1

    # ground materials
    m_lawn = mat("lawn", "grass", _lin((0.36, 0.50, 0.22), rng), _lin((0.55, 0.55, 0.30), rng), 3.0)
    m_field = mat("fields", "field", _lin((0.52, 0.48, 0.30), rng), _lin((0.35, 0.48, 0.20), rng), 60.0)
    m_cross = mat("intersection", "asphalt", _lin((0.33, 0.33, 0.34), rng, 0.01), _lin((0.25, 0.25, 0.26), rng, 0.01))
    streets = []
    for k in range(2 * nx + 1):
        streets.append({"axis": 1, "center": 96.0 * k, "half_width": hw, "range": [-hw, ny * ty + hw]})
    for k in range(2 * ny + 1):
        streets.append({"axis": 0, "center": 72.0 * k, "half_width": hw, "range": [-hw, nx * tx + hw]})
    for s in streets:
        s["material"] = mat(f"street_{s['axis']}_{s['center']:g}", "asphalt", _lin((0.33, 0.33, 0.34), rng, 0.01),
                            _lin((0.25, 0.25, 0.26), rng, 0.01), 1.0, s["center"], s["axis"])
    m_glass = mat("glass", "glass", _lin((0.18, 0.22, 0.27), rng, 0.01), _lin((0.85, 0.85, 0.82), rng, 0.01))
    m_bark = mat("bark", "bark", _lin((0.30, 0.22, 0.15), rng), _lin((0.2, 0.15, 0.1), rng))

    # terrain triangles with street / ground classes
    tv, tt = terrain.mesh()
    cen = tv[tt].mean(1)
    t_sem = np.zeros(len(tt), np.uint8)
    t_mat = np.where((cen[:, 0] > x_lo) & (cen[:, 0] < x_hi) & (cen[:, 1] > y_lo) & (cen[:, 1] < y_hi),
                     m_lawn, m_field).astype(np.int32)
    in_street = np.zeros((len(tt), len(streets)), dtype=bool)
    for si, s in enumerate(streets):
        a = s["axis"]
        across, along = cen[:, 1 - a], cen[:, a]
        in_street[:, si] = (np.abs(across - s["center"]) < hw) & (along > s["range"][0]) & (along < s["range"][1])
    n_in = in_street.sum(1)
    t_sem[n_in > 0] = SEMANTIC["street"]
    t_mat[n_in == 1] = np.array([s["material"] for s in streets])[np.argmax(in_street[n_in == 1], axis=1)]
    t_mat[n_in > 1] = m_cross
    parts_v, parts_t = [tv], [tt]
    sem, bld, mats_l, uvs = [t_sem], [np.full(len(tt), -1, np.int32)], [t_mat], [tv[tt][:, :, :2]]
    nv = len(tv)

    recipes = _recipes()
    buildings: list[Building] = []
    trees: list[tuple[float, float, float, float, float]] = []
    targets: list[tuple[float, float]] = []
    for tj in range(ny):
        for ti in range(nx):
            trng = np.random.default_rng([seed, ti, tj])
            order = trng.permutation(16) if (ti, tj) != (0, 0) else np.arange(16)
            for slot in range(16):  # 4 x 4 slots of 44 m x 32 m in the four blocks between the streets
                sx = ti * tx + (26.0, 70.0, 122.0, 166.0)[slot % 4]
                sy = tj * ty + (20.0, 52.0, 92.0, 124.0)[slot // 4]
                r = order[slot]
                if r == 15:  # the park: trees and open ground for targets
                    for _ in range(8):
                        trees.append((sx + trng.uniform(-17, 17), sy + trng.uniform(-12, 12), 0.0,
                                      trng.uniform(2.2, 3.8), trng.uniform(8.0, 13.0)))
                    targets.append((sx + trng.uniform(-2, 2), sy + trng.uniform(-2, 2)))
                    continue
                name, builder = recipes[r]
                rot = float(trng.choice([0.0, 0.0, 90.0, 180.0]) + trng.uniform(-8.0, 8.0))
                bc_local = np.array([sx + trng.uniform(-1.5, 1.5), sy + trng.uniform(-1.0, 1.0)])
                g = float(terrain.z(bc_local[None])[0])
                parts = builder(trng, g)
                if name in ("l_gable", "t_mixed", "u_mixed", "l_flat_shed", "l_hip", "stepped_flat", "church"):
                    rot = float(trng.choice([0.0, 180.0]) + trng.uniform(-6.0, 6.0))
                b = Building(id=len(buildings), name=name, center=bc_local + origin[:2], rotation=rot, ground_z=g,
                             parts=parts)
                cr, sr = np.cos(np.radians(rot)), np.sin(np.radians(rot))
                big = [p for p in parts if p.kind in ("body", "tower")]
                tmax = -np.inf
                for p in parts:  # bases below the terrain under the (extended) footprint
                    x0, y0, x1, y1 = p.rect
                    gxy = np.stack(np.meshgrid(np.linspace(x0 - 1, x1 + 1, 9), np.linspace(y0 - 1, y1 + 1, 9)),
                                   -1).reshape(-1, 2)
                    tz = terrain.z(b.to_world(gxy) - origin[:2])
                    p.base = float(np.nanmin(tz)) - 0.5
                    tmax = max(tmax, float(np.nanmax(tz)))
                for xc, side in DORMERS.get(name, []):
                    parts.append(_dormer(parts[0], xc, side))
                for xc, yc in CHIMNEYS.get(name, []):
                    parts.append(_chimney(parts[0], xc, yc))
                _auto_windows(parts, g, tmax, trng)
                wall_c = trng.choice(len(_PLASTER) + len(_BRICK))
                wall_kind = "plaster" if wall_c < len(_PLASTER) else "brick"
                wc = (_PLASTER + _BRICK)[wall_c]
                m_wall = mat(f"b{b.id}_wall", wall_kind, _lin(wc, trng), _lin(tuple(v * 0.8 for v in wc), trng),
                             0.25 if wall_kind == "brick" else 1.0)
                tc = _TILES[trng.integers(len(_TILES))]
                m_tiles = mat(f"b{b.id}_tiles", "tiles", _lin(tc, trng), _lin(tuple(v * 0.7 for v in tc), trng), 0.3)
                fc = _FLAT[trng.integers(len(_FLAT))]
                m_flat = mat(f"b{b.id}_flat", "gravel", _lin(fc, trng), _lin(tuple(v * 0.8 for v in fc), trng), 1.0)
                m_metal = mat(f"b{b.id}_metal", "metal", _lin((0.42, 0.50, 0.46), trng), _lin((0.3, 0.36, 0.33), trng),
                              0.5)
                m_under = mat(f"b{b.id}_soffit", "wood", _lin((0.62, 0.48, 0.32), trng), _lin((0.45, 0.33, 0.2), trng),
                              0.14)
                m_fascia = mat(f"b{b.id}_fascia", "plaster", _lin((0.85, 0.85, 0.82), trng),
                               _lin((0.6, 0.6, 0.58), trng), 1.0)
                m_chim = mat(f"b{b.id}_chimney", "brick", _lin((0.55, 0.27, 0.18), trng), _lin((0.4, 0.2, 0.14), trng),
                             0.25)
                mb = _MeshBuilder()
                uv_off = trng.uniform(0, 500, 2)
                for pi, p in enumerate(parts):
                    inst = p.kind in ("dormer", "chimney")
                    roof_m = {"flat": m_flat, "shed": m_metal}.get(p.roof, m_tiles)
                    if p.kind == "chimney":
                        pm = {"roof": m_chim, "wall": m_chim, "under": m_chim, "fascia": m_chim, "glass": m_glass}
                    else:
                        pm = {"roof": m_tiles if p.kind == "dormer" else roof_m, "wall": m_wall, "under": m_under,
                              "fascia": m_fascia, "glass": m_glass}
                    polys = _part_mesh(mb, p, pm, inst, uv_off)
                    for i, poly in polys.items():
                        a, bb, c = p.planes()[i]
                        n_loc = np.array([-a, -bb, 1.0]) / np.sqrt(a * a + bb * bb + 1.0)
                        n_w = np.array([cr * n_loc[0] - sr * n_loc[1], sr * n_loc[0] + cr * n_loc[1], n_loc[2]])
                        poly3 = np.column_stack([b.to_world(poly), a * poly[:, 0] + bb * poly[:, 1] + c])
                        b.roof_planes.append({"part": pi, "plane": i, "normal": n_w, "d": float(n_w @ poly3[0]),
                                              "polygon": poly3, "slope_deg": float(p.slope if abs(a) + abs(bb) > 0
                                                                                   else 0.0),
                                              "kind": "roof_installation" if inst else "roof"})
                    x0, y0, x1, y1 = p.rect
                    fpc = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
                    for k, wins in p.windows.items():
                        a2, b2 = fpc[k], fpc[(k + 1) % 4]
                        e = (b2 - a2) / np.linalg.norm(b2 - a2)
                        nrm_l = np.array([e[1], -e[0]])
                        for s0, s1, z0, z1 in wins:
                            c2 = np.array([a2 + s0 * e, a2 + s1 * e, a2 + s1 * e, a2 + s0 * e])
                            corners = np.column_stack([b.to_world(c2), [z0, z0, z1, z1]])
                            n_w = np.array([cr * nrm_l[0] - sr * nrm_l[1], sr * nrm_l[0] + cr * nrm_l[1], 0.0])
                            b.windows.append({"part": pi, "edge": k, "corners": corners, "recess": WINDOW_RECESS,
                                              "normal": n_w})
                v, t, s_, m_, uv = mb.build()
                vw = np.column_stack([b.to_world(v[:, :2]) - origin[:2], v[:, 2]])
                parts_v.append(vw)
                parts_t.append(t + nv)
                nv += len(vw)
                sem.append(s_)
                bld.append(np.full(len(t), b.id, np.int32))
                mats_l.append(m_)
                uvs.append(uv)
                b.footprint = [b.to_world(r) for r in rect_union_outline([p.rect for p in big])]
                buildings.append(b)
            # street trees along the southern E-W street of the tile and targets at intersections
            for k in range(10):
                x = ti * tx + 10.0 + k * 19.0
                if abs((x % 96.0) - 0.0) < 8 or abs((x % 96.0) - 96.0) < 8:
                    continue
                trees.append((x + trng.uniform(-1, 1), tj * ty + 72.0 + hw + 1.3, 0.0, trng.uniform(1.8, 2.6),
                              trng.uniform(7.0, 10.0)))
    # signalised targets: one near the centre of every street intersection (plus one per park)
    irng = np.random.default_rng(seed + 15485863)
    for k in range(2 * nx + 1):
        for m in range(2 * ny + 1):
            targets.append((96.0 * k + irng.uniform(-1.5, 1.5), 72.0 * m + irng.uniform(-1.5, 1.5)))
    # periphery trees (groups in the fields)
    prng = np.random.default_rng(seed + 104729)
    for _ in range(40 * max(1, nx * ny // 4)):
        ang, dist = prng.uniform(0, 2 * np.pi), prng.uniform(30.0, 250.0)
        cx_ = np.clip(0.5 * (x_lo + x_hi) + np.cos(ang) * (0.5 * (x_hi - x_lo) + dist), x_lo - 300, x_hi + 300)
        cy_ = np.clip(0.5 * (y_lo + y_hi) + np.sin(ang) * (0.5 * (y_hi - y_lo) + dist), y_lo - 300, y_hi + 300)
        if x_lo - 5 < cx_ < x_hi + 5 and y_lo - 5 < cy_ < y_hi + 5:
            continue
        for _ in range(prng.integers(1, 6)):
            trees.append((cx_ + prng.uniform(-10, 10), cy_ + prng.uniform(-10, 10), 0.0, prng.uniform(2.5, 4.5),
                          prng.uniform(9.0, 16.0)))
    trees = [t for t in trees if _clear_of_buildings(t, buildings, origin)]
    m_crown = mat("crown", "tree", _lin((0.20, 0.35, 0.12), rng), _lin((0.35, 0.45, 0.18), rng), 0.8)
    tree_arr = np.array(trees, np.float64)
    tree_arr[:, 2] = terrain.z(tree_arr[:, :2])
    tv_, tt_, ts_, tm_ = _tree_meshes(tree_arr, seed, m_crown, m_bark)
    parts_v.append(tv_)
    parts_t.append(tt_ + nv)
    sem.append(ts_)
    bld.append(np.full(len(tt_), -1, np.int32))
    mats_l.append(tm_)
    uvs.append(tv_[tt_][:, :, :2].astype(np.float32))
    tg = np.array(targets, np.float64)
    tg = np.column_stack([tg, terrain.z(tg)]) + origin
    verts = np.concatenate(parts_v) + origin
    core = np.array([x_lo, y_lo, x_hi, y_hi]) + np.tile(origin[:2], 2)
    extent = np.array([terrain.xs[0], terrain.ys[0], terrain.xs[-1], terrain.ys[-1]]) + np.tile(origin[:2], 2)
    return City(crs=crs, origin=origin, vertices=verts, triangles=np.concatenate(parts_t).astype(np.int64),
                semantic=np.concatenate(sem), building=np.concatenate(bld), material=np.concatenate(mats_l),
                uv=np.concatenate(uvs).astype(np.float32), materials=materials, buildings=buildings,
                terrain=terrain, streets=streets, trees=tree_arr, targets=tg,
                target_names=[f"T{i + 1:02d}" for i in range(len(tg))], core=core, extent=extent, seed=seed)


def _clear_of_buildings(tree: tuple, buildings: list[Building], origin: np.ndarray) -> bool:
    """True when a tree's crown (plus 0.8 m) stays off every building part and its overhang."""
    xy = np.array([[tree[0] + origin[0], tree[1] + origin[1]]])
    for b in buildings:
        if np.linalg.norm(xy[0] - b.center) > 60.0:
            continue
        rects = [(p.rect[0] - p.overhang[0], p.rect[1] - p.overhang[2], p.rect[2] + p.overhang[1],
                  p.rect[3] + p.overhang[3]) for p in b.parts]
        if point_in_rects(b.to_local(xy), rects, tree[3] + 0.8)[0]:
            return False
    return True


def _tree_meshes(trees: np.ndarray, seed: int, m_crown: int, m_bark: int):
    """Crowns (noisy ellipsoids) and trunks (octagonal prisms) in local coordinates."""
    import trimesh

    rng = np.random.default_rng(seed + 31)
    sphere = trimesh.creation.icosphere(subdivisions=2)
    cyl = trimesh.creation.cylinder(radius=1.0, height=1.0, sections=8)
    vs, ts, sems, ms = [], [], [], []
    n = 0
    for x, y, z, r, h in trees:
        trunk_h = 0.35 * h
        cv = cyl.vertices * [0.22, 0.22, trunk_h + 0.6] + [x, y, z + trunk_h / 2 - 0.3]
        vs.append(cv)
        ts.append(cyl.faces + n)
        n += len(cv)
        sems.append(np.full(len(cyl.faces), SEMANTIC["tree"], np.uint8))
        ms.append(np.full(len(cyl.faces), m_bark, np.int32))
        crown_h = 0.5 * (h - trunk_h) + 0.3
        bump = 1.0 + 0.18 * rng.standard_normal(len(sphere.vertices))
        sv = sphere.vertices * bump[:, None] * [r, r, crown_h] + [x, y, z + h - crown_h]
        vs.append(sv)
        ts.append(sphere.faces + n)
        n += len(sv)
        sems.append(np.full(len(sphere.faces), SEMANTIC["tree"], np.uint8))
        ms.append(np.full(len(sphere.faces), m_crown, np.int32))
    return np.concatenate(vs), np.concatenate(ts), np.concatenate(sems), np.concatenate(ms)

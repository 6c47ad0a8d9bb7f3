"""Parametric test buildings with exact ground truth, sampled as noisy oblique-like point clouds and a DSM.

A building is a union of rectangular parts in a rotated local frame, each with a flat, gabled or hipped roof and
an overhang. The ground truth (wall outline, roof planes, overhang width per outline edge) is analytic, so the
reconstruction steps can be tested against it without the full city simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.raster import Raster


@dataclass(frozen=True)
class Part:
    """A rectangular part in the building's local frame (metres).

    Attributes
    ----------
    u0, v0, u1, v1 : wall rectangle
    eave : eave height above ground
    ridge : ridge height above ground (== eave for flat roofs)
    roof : ``flat``, ``gable_u`` (ridge along u), ``gable_v`` or ``hip`` (ridge along the longer side)
    overhang : roof overhang beyond the walls
    """

    u0: float
    v0: float
    u1: float
    v1: float
    eave: float
    ridge: float
    roof: str = "gable_u"
    overhang: float = 0.0

    def roof_z(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Roof height over local (u, v) (n,) -> (n,), the planes continued over the overhang."""
        hu, hv = (self.u1 - self.u0) / 2, (self.v1 - self.v0) / 2
        du, dv = np.abs(u - (self.u0 + hu)), np.abs(v - (self.v0 + hv))
        rise = self.ridge - self.eave
        if self.roof == "flat":
            return np.full(np.shape(u), self.eave, dtype=np.float64)
        if self.roof == "gable_u":
            return self.eave + rise * (1 - dv / hv)
        if self.roof == "gable_v":
            return self.eave + rise * (1 - du / hu)
        if self.roof == "hip":
            s = rise / min(hu, hv)
            return self.eave + s * np.minimum(hv - dv, hu - du)
        raise ValueError(f"unknown roof type {self.roof}")

    def roof_planes_local(self) -> list[np.ndarray]:
        """The roof planes (a, b, c, d), ``a u + b v + c z + d = 0``, unit normal with c > 0."""
        hu, hv = (self.u1 - self.u0) / 2, (self.v1 - self.v0) / 2
        rise = self.ridge - self.eave
        if self.roof == "flat":
            return [np.array([0.0, 0.0, 1.0, -self.eave])]
        sides = []  # (axis, sign, eave coordinate, slope): z = eave + slope * sign * (coord - eave coord)
        if self.roof in ("gable_u", "hip"):
            s = rise / (hv if self.roof == "gable_u" else min(hu, hv))
            sides += [(1, 1.0, self.v0, s), (1, -1.0, self.v1, s)]
        if self.roof in ("gable_v", "hip"):
            s = rise / (hu if self.roof == "gable_v" else min(hu, hv))
            sides += [(0, 1.0, self.u0, s), (0, -1.0, self.u1, s)]
        out = []
        for axis, sign, c0, s in sides:
            n = np.zeros(3)
            n[axis] = -sign * s
            n[2] = 1.0
            d = -self.eave + sign * s * c0
            k = np.linalg.norm(n)
            out.append(np.append(n / k, d / k))
        return out

    def contains(self, u: np.ndarray, v: np.ndarray, margin: float = 0.0) -> np.ndarray:
        return ((u > self.u0 - margin) & (u < self.u1 + margin) & (v > self.v0 - margin) & (v < self.v1 + margin))


@dataclass(frozen=True)
class SyntheticBuilding:
    """A building: parts in a local frame placed at ``origin`` and turned by ``angle_deg`` (counter-clockwise).

    ``footprint_local`` is the wall outline of the union of the parts (counter-clockwise, local frame) and
    ``overhang_local`` the overhang width of each outline edge.
    """

    name: str
    parts: tuple[Part, ...]
    footprint_local: tuple[tuple[float, float], ...]
    overhang_local: tuple[float, ...]
    origin: tuple[float, float] = (0.0, 0.0)
    angle_deg: float = 0.0
    ground: float = 0.0
    stepped: bool = False

    def _rot(self) -> np.ndarray:
        a = np.radians(self.angle_deg)
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    def to_world(self, uv: np.ndarray) -> np.ndarray:
        """Local (n, 2) -> world (n, 2)."""
        return uv @ self._rot().T + np.asarray(self.origin)

    def to_local(self, xy: np.ndarray) -> np.ndarray:
        return (np.asarray(xy) - np.asarray(self.origin)) @ self._rot()

    @property
    def footprint(self) -> np.ndarray:
        """(m, 2) world wall outline, counter-clockwise."""
        return self.to_world(np.asarray(self.footprint_local, dtype=np.float64))

    @property
    def overhangs(self) -> np.ndarray:
        return np.asarray(self.overhang_local, dtype=np.float64)

    def roof_planes(self) -> np.ndarray:
        """(k, 4) world roof planes with unit normals pointing up."""
        R3 = np.eye(3)
        R3[:2, :2] = self._rot()
        out = []
        for p in self.parts:
            for pl in p.roof_planes_local():
                n = R3 @ pl[:3]
                # shift the plane to the world frame: x_world = R x_local + t, z shifted by ground
                t = np.array([self.origin[0], self.origin[1], self.ground])
                out.append(np.append(n, pl[3] - n @ t))
        return np.asarray(out)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Top surface height (roofs incl. overhangs, else ground) at world points (n, 2)."""
        uv = self.to_local(xy)
        z = np.full(len(uv), -np.inf)
        for p in self.parts:
            m = p.contains(uv[:, 0], uv[:, 1], p.overhang)
            z[m] = np.maximum(z[m], p.roof_z(uv[m, 0], uv[m, 1]))
        return np.where(np.isfinite(z), z + self.ground, self.ground)

    def inside_body(self, uvz: np.ndarray, eps: float = 1e-3) -> np.ndarray:
        """Local (n, 3) points strictly inside a part's body (under its roof, within its walls)."""
        m = np.zeros(len(uvz), bool)
        for p in self.parts:
            c = p.contains(uvz[:, 0], uvz[:, 1], -eps)
            c &= uvz[:, 2] < p.roof_z(uvz[:, 0], uvz[:, 1]) - eps
            m |= c
        return m

    def sample(self, density: float, noise: float, rng: np.random.Generator, outlier_share: float = 0.0,
               ground_margin: float = 3.0) -> np.ndarray:
        """An oblique-like point cloud: roofs (with overhangs), walls and the ground around.

        Parameters
        ----------
        density : points per square metre of surface
        noise : standard deviation of the isotropic Gaussian noise (m)
        outlier_share : share of extra points spread uniformly in the bounding box (planted outliers)

        Returns
        -------
        xyz : (n, 3) float64 world points
        """
        pts = []
        for p in self.parts:
            w = p.overhang
            area = (p.u1 - p.u0 + 2 * w) * (p.v1 - p.v0 + 2 * w)
            n = rng.poisson(density * area * 1.15)
            u = rng.uniform(p.u0 - w, p.u1 + w, n)
            v = rng.uniform(p.v0 - w, p.v1 + w, n)
            z = p.roof_z(u, v)
            top = self.height(self.to_world(np.column_stack([u, v]))) - self.ground
            keep = z >= top - 1e-6
            pts.append(np.stack([u[keep], v[keep], z[keep]], 1))
            corners = [(p.u0, p.v0), (p.u1, p.v0), (p.u1, p.v1), (p.u0, p.v1)]
            for i in range(4):
                a, b = np.array(corners[i]), np.array(corners[(i + 1) % 4])
                length = float(np.linalg.norm(b - a))
                zmax = p.ridge
                n = rng.poisson(density * length * zmax)
                s = rng.uniform(0, 1, n)
                z = rng.uniform(0, zmax, n)
                uv = a + s[:, None] * (b - a)
                keep = z < p.roof_z(uv[:, 0], uv[:, 1])
                pts.append(np.column_stack([uv[keep], z[keep]]))
        xyz = np.concatenate(pts)
        # ground ring around the building
        lo = np.min([[p.u0, p.v0] for p in self.parts], 0) - ground_margin
        hi = np.max([[p.u1, p.v1] for p in self.parts], 0) + ground_margin
        n = rng.poisson(density * float(np.prod(hi - lo)))
        g = np.column_stack([rng.uniform(lo[0], hi[0], n), rng.uniform(lo[1], hi[1], n), np.zeros(n)])
        covered = np.zeros(n, bool)
        for p in self.parts:
            covered |= p.contains(g[:, 0], g[:, 1], p.overhang)
        xyz = np.concatenate([xyz, g[~covered]])
        # hidden surfaces: inside another part, or roof points under another part's roof
        xyz = xyz[~self.inside_body(xyz)]
        xyz = xyz + rng.normal(0, noise, xyz.shape)
        if outlier_share > 0:
            k = int(outlier_share * len(xyz))
            zmax = max(p.ridge for p in self.parts)
            out = np.column_stack([rng.uniform(lo[0], hi[0], k), rng.uniform(lo[1], hi[1], k),
                                   rng.uniform(-1.0, zmax + 4.0, k)])
            xyz = np.concatenate([xyz, out])
        world = np.column_stack([self.to_world(xyz[:, :2]), xyz[:, 2] + self.ground])
        return world

    def dsm(self, cell: float, noise: float, rng: np.random.Generator, margin: float = 4.0,
            crs: str = "EPSG:25832") -> tuple[Raster, Raster]:
        """Ortho DSM and DTM over the building: per cell the highest of 4 x 4 samples of the top surface inside it
        (as the surface stage's DSM holds each cell's highest point), plus noise."""
        fp = np.concatenate([self.footprint, self.to_world(np.array([[p.u0, p.v0] for p in self.parts])),
                             self.to_world(np.array([[p.u1, p.v1] for p in self.parts]))])
        lo = np.floor((fp.min(0) - margin) / cell) * cell
        hi = np.ceil((fp.max(0) + margin) / cell) * cell
        cols, rows = int(round((hi[0] - lo[0]) / cell)), int(round((hi[1] - lo[1]) / cell))
        r = Raster(np.zeros((rows, cols)), float(lo[0]), float(hi[1]), cell, crs)
        xc, yc = r.cell_centers()
        X, Y = np.meshgrid(xc, yc)
        z = np.full((rows, cols), -np.inf)
        for dx in (np.arange(4) - 1.5) * cell / 4:
            for dy in (np.arange(4) - 1.5) * cell / 4:
                z = np.maximum(z, self.height(np.column_stack([X.ravel() + dx, Y.ravel() + dy])).reshape(rows, cols))
        z = z + rng.normal(0, noise, z.shape)
        dtm = Raster(np.full((rows, cols), self.ground), r.x0, r.y0, cell, crs)
        return Raster(z, r.x0, r.y0, cell, crs), dtm


def _rect(u0, v0, u1, v1):
    return ((u0, v0), (u1, v0), (u1, v1), (u0, v1))


def parametric_buildings() -> tuple[SyntheticBuilding, ...]:
    """Gabled, hipped, flat, an L-shape, a two-part building with different eave heights, a stepped flat one."""
    return (
        SyntheticBuilding("gabled", (Part(0, 0, 12, 8, 6, 9, "gable_u", 0.6),), _rect(0, 0, 12, 8), (0.6,) * 4,
                          origin=(100.0, 200.0), angle_deg=17.0),
        SyntheticBuilding("hipped", (Part(0, 0, 14, 9, 5.5, 8.5, "hip", 0.5),), _rect(0, 0, 14, 9), (0.5,) * 4,
                          origin=(140.0, 190.0), angle_deg=-32.0),
        SyntheticBuilding("flat", (Part(0, 0, 16, 10, 9, 9, "flat", 0.0),), _rect(0, 0, 16, 10), (0.0,) * 4,
                          origin=(100.0, 150.0), angle_deg=5.0),
        SyntheticBuilding("lshape", (Part(0, 0, 16, 8, 6, 9, "gable_u", 0.5), Part(0, 4, 8, 16, 6, 9, "gable_v", 0.5)),
                          ((0, 0), (16, 0), (16, 8), (8, 8), (8, 16), (0, 16)), (0.5,) * 6,
                          origin=(150.0, 130.0), angle_deg=40.0),
        SyntheticBuilding("twopart", (Part(0, 0, 10, 9, 7, 10, "gable_u", 0.0),
                                      Part(10, 0, 18, 9, 3.5, 3.5, "flat", 0.0)),
                          _rect(0, 0, 18, 9), (0.0,) * 4, origin=(60.0, 120.0), angle_deg=-8.0,
                          stepped=True),
        SyntheticBuilding("stepped_flat", (Part(0, 0, 9, 10, 10, 10, "flat", 0.0),
                                           Part(9, 0, 18, 10, 5, 5, "flat", 0.0)),
                          _rect(0, 0, 18, 10), (0.0,) * 4, origin=(60.0, 170.0), angle_deg=25.0, stepped=True),
    )


VIEW_DIRECTIONS = np.array([[0.0, 0.0, 1.0], [0.0, 0.7071, 0.7071], [0.0, -0.7071, 0.7071],
                            [0.7071, 0.0, 0.7071], [-0.7071, 0.0, 0.7071]])
"""Directions towards the cameras of a Maltese-cross system: nadir and four 45-degree obliques."""


def city_point_cloud(city, density: float, noise: float, seed: int = 0,
                     area: tuple[float, float, float, float] | None = None,
                     outlier_share: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """An oblique-like point cloud of the simulator's city from its ground-truth mesh.

    Triangles are sampled by area (``density`` points per m^2); a sample is kept when at least one of the
    :data:`VIEW_DIRECTIONS` sees it (the surface faces that way and a ray cast towards it escapes the city),
    so hidden faces (inside parts, under neighbours) are dropped; Gaussian ``noise`` (m) is then added.

    Returns
    -------
    xyz : (n, 3) float64 world points; semantic : (n,) uint8 codes of the triangles they came from
    """
    import open3d as o3d

    rng = np.random.default_rng(seed)
    V = city.vertices - city.origin
    T = city.triangles
    a, b, c = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    if area is not None:
        lo = np.asarray(area[:2]) - city.origin[:2]
        hi = np.asarray(area[2:]) - city.origin[:2]
        cen = (a + b + c)[:, :2] / 3
        sel = np.all((cen >= lo) & (cen <= hi), axis=1)
        a, b, c, sem = a[sel], b[sel], c[sel], city.semantic[sel]
    else:
        sem = city.semantic
    cr = np.cross(b - a, c - a)
    areas = 0.5 * np.linalg.norm(cr, axis=1)
    normals = cr / np.maximum(2 * areas[:, None], 1e-12)
    counts = rng.poisson(areas * density)
    tri = np.repeat(np.arange(len(a)), counts)
    r1, r2 = rng.random(len(tri)), rng.random(len(tri))
    s = np.sqrt(r1)
    p = (1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri]
    n = normals[tri]
    scene = city.scene()
    visible = np.zeros(len(p), bool)
    for d in VIEW_DIRECTIONS:
        facing = n @ d > 0.05
        idx = np.nonzero(facing & ~visible)[0]
        if len(idx) == 0:
            continue
        origin = p[idx] + 0.02 * n[idx]
        rays = np.hstack([origin, np.broadcast_to(d, (len(idx), 3))]).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        visible[idx[~np.isfinite(hit)]] = True
    p, sem_p = p[visible], sem[tri][visible]
    p = p + rng.normal(0, noise, p.shape)
    if outlier_share > 0:
        k = int(outlier_share * len(p))
        lo, hi = p.min(0), p.max(0)
        p = np.vstack([p, rng.uniform(lo, hi, (k, 3))])
        sem_p = np.concatenate([sem_p, np.full(k, 255, np.uint8)])
    return p + city.origin, sem_p

"""The LOD2 building model: planar polygons over shared vertices, a closed body solid, typed surfaces.

A :class:`BuildingModel` holds one building: a vertex array in world coordinates and a list of
:class:`Surface` rings indexing it. Surfaces with ``in_solid=True`` form the closed body (ground, walls, roofs);
overhang surfaces (the roof extension, its fascia and its underside) hang on the body and are not part of the
solid. Ids are stable: ``<building id>_<kind>_<n>`` numbered in a deterministic order.

Stored in the workspace as ``buildings/buildings.json`` (:func:`save_buildings` / :func:`load_buildings`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.validate import read_json
from ..pipeline.atomic import write_json

SURFACE_KINDS = ("ground", "wall", "roof", "overhang_roof", "overhang_fascia", "overhang_underside")
"""Surface roles. CityGML: ground -> GroundSurface, wall/overhang_fascia -> WallSurface, roof/overhang_roof ->
RoofSurface, overhang_underside -> OuterCeilingSurface."""

FORMAT_VERSION = 1


@dataclass(frozen=True)
class Surface:
    """One planar polygon.

    Attributes
    ----------
    id : stable id, unique in the file
    kind : one of :data:`SURFACE_KINDS`
    ring : vertex indices (into the building's vertices), counter-clockwise seen from outside, not closed
    in_solid : True for the faces of the closed body
    """

    id: str
    kind: str
    ring: tuple[int, ...]
    in_solid: bool = True


@dataclass
class BuildingModel:
    """A reconstructed building.

    Attributes
    ----------
    id : stable building id (``B0001`` ...)
    vertices : (n, 3) float64 world coordinates, shared by the surfaces
    surfaces : the polygons
    path : ``2d`` or ``volumetric``: which reconstruction produced the body
    reason : why that path was taken (the disagreement that triggered the fallback, if any)
    footprint : (m, 2) float64 wall outline (counter-clockwise) from the facade analysis
    overhangs : (m,) float64 overhang width per footprint edge (edge i runs from corner i to i+1)
    roof_planes : (k, 4) float64 roof planes ``n . x + d = 0`` with unit normals pointing up
    info : timings, counts and diagnostics
    """

    id: str
    vertices: np.ndarray
    surfaces: list[Surface]
    path: str
    reason: str
    footprint: np.ndarray
    overhangs: np.ndarray
    roof_planes: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    def triangles(self, in_solid_only: bool = False) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Ear-clipping triangulation of every ring.

        Returns
        -------
        vertices : (n, 3) float64, the building's vertices
        faces : (t, 3) int64 triangles
        kinds : surface kind per triangle
        """
        tris: list[tuple[int, int, int]] = []
        kinds: list[str] = []
        for s in self.surfaces:
            if in_solid_only and not s.in_solid:
                continue
            for t in triangulate_ring(self.vertices, s.ring):
                tris.append(t)
                kinds.append(s.kind)
        return self.vertices, np.asarray(tris, dtype=np.int64).reshape(-1, 3), kinds

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id, "path": self.path, "reason": self.reason,
            "vertices": self.vertices.tolist(),
            "surfaces": [{"id": s.id, "kind": s.kind, "ring": list(s.ring), "in_solid": s.in_solid}
                         for s in self.surfaces],
            "footprint": self.footprint.tolist(), "overhangs": self.overhangs.tolist(),
            "roof_planes": self.roof_planes.tolist(), "info": self.info,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], path: str | Path | None = None) -> BuildingModel:
        try:
            verts = np.asarray(d["vertices"], dtype=np.float64).reshape(-1, 3)
            surfaces = [Surface(s["id"], s["kind"], tuple(int(i) for i in s["ring"]), bool(s["in_solid"]))
                        for s in d["surfaces"]]
            b = cls(str(d["id"]), verts, surfaces, str(d["path"]), str(d["reason"]),
                    np.asarray(d["footprint"], dtype=np.float64).reshape(-1, 2),
                    np.asarray(d["overhangs"], dtype=np.float64).reshape(-1),
                    np.asarray(d["roof_planes"], dtype=np.float64).reshape(-1, 4), dict(d.get("info", {})))
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"building {d.get('id', '?')}: malformed record ({e})", path,
                             field=str(e) if isinstance(e, KeyError) else None) from None
        for s in b.surfaces:
            if s.kind not in SURFACE_KINDS:
                raise InputError(f"building {b.id}: unknown surface kind '{s.kind}'", path, field="kind")
            if len(s.ring) < 3 or max(s.ring) >= len(verts) or min(s.ring) < 0:
                raise InputError(f"building {b.id}: surface {s.id} has a bad ring", path, field="ring")
        return b


def ring_area_vector(xyz: np.ndarray) -> np.ndarray:
    """Area vector ``(3,)`` of a planar ring ``xyz (k, 3)`` (Newell): its length is the ring's area, its direction
    the normal of its counter-clockwise side."""
    c = xyz - xyz.mean(0)
    return 0.5 * np.cross(c, np.roll(c, -1, axis=0)).sum(0)


def ring_normal(xyz: np.ndarray) -> np.ndarray:
    """Newell normal of a ring ``(k, 3)`` (unit, zero for degenerate rings)."""
    n = ring_area_vector(xyz)
    norm = np.linalg.norm(n)
    return n / norm if norm > 0 else n


def triangulate_ring(vertices: np.ndarray, ring: tuple[int, ...] | list[int]) -> list[tuple[int, int, int]]:
    """Ear clipping of a planar simple polygon given by indices into ``vertices (n, 3)``."""
    idx = list(ring)
    if len(idx) == 3:
        return [tuple(idx)]
    xyz = vertices[idx]
    n = ring_normal(xyz)
    k = int(np.argmax(np.abs(n)))
    axes = [a for a in range(3) if a != k]
    uv = xyz[:, axes]
    if n[k] < 0:
        uv = uv[:, ::-1]
    rem = list(range(len(idx)))
    out: list[tuple[int, int, int]] = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(rem) > 3 and guard < 10000:
        guard += 1
        m = len(rem)
        for i in range(m):
            a, b, c = rem[i - 1], rem[i], rem[(i + 1) % m]
            if cross(uv[a], uv[b], uv[c]) <= 1e-12:
                continue
            inside = False
            for j in rem:
                if j in (a, b, c):
                    continue
                p = uv[j]
                if cross(uv[a], uv[b], p) >= 0 and cross(uv[b], uv[c], p) >= 0 and cross(uv[c], uv[a], p) >= 0:
                    inside = True
                    break
            if not inside:
                out.append((idx[a], idx[b], idx[c]))
                rem.pop(i)
                break
        else:  # degenerate (collinear) remainder: fan it
            break
    for i in range(1, len(rem) - 1):
        out.append((idx[rem[0]], idx[rem[i]], idx[rem[i + 1]]))
    return out


def save_buildings(path: str | Path, buildings: list[BuildingModel], crs: str) -> None:
    """Write the buildings of a workspace atomically."""
    write_json(path, {"format": "oblique-city-buildings", "version": FORMAT_VERSION, "crs": crs,
                      "buildings": [b.to_dict() for b in buildings]}, indent=None)


def load_buildings(path: str | Path) -> tuple[list[BuildingModel], str]:
    """Read ``buildings.json``: the buildings and the CRS."""
    path = Path(path)
    doc = read_json(path, "no buildings file (run the 'buildings' stage first)")
    if doc.get("format") != "oblique-city-buildings":
        raise InputError("not an Oblique City buildings file", path, field="format")
    return [BuildingModel.from_dict(d, path) for d in doc.get("buildings", [])], str(doc.get("crs", ""))

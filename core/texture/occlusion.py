"""Occlusion tests by ray casting (Open3D ``RaycastingScene``) against the building models and the terrain.

Open3D works in float32, so the scene lives in a local frame (world minus ``origin``), which keeps millimetres
in projected coordinates. The terrain is a grid mesh of a height raster: the DSM with the cells under and near
the reconstructed buildings replaced by the DTM (the DSM's own building shapes are blurred and would hide the
walls in front of them), so trees and unmodelled objects still occlude while buildings occlude through their
models.
"""

from __future__ import annotations

import numpy as np

from ..model.raster import Raster


def grid_mesh(height: Raster, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh of a height raster sampled every ``step`` cells.

    Returns vertices ``(n, 3)`` float64 at cell centres (world) and triangles ``(t, 3)`` int64; quads with an
    empty (NaN) corner are left out.
    """
    z = np.asarray(height.data, np.float64)[::step, ::step]
    rows, cols = z.shape
    xs = height.x0 + (np.arange(0, height.shape[1], step) + 0.5) * height.cell
    ys = height.y0 - (np.arange(0, height.shape[0], step) + 0.5) * height.cell
    gx, gy = np.meshgrid(xs[:cols], ys[:rows])
    verts = np.column_stack([gx.ravel(), gy.ravel(), z.ravel()])
    if rows < 2 or cols < 2:
        return verts, np.zeros((0, 3), np.int64)
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    ok = np.isfinite(z.ravel())
    quad = ok[a] & ok[b] & ok[c] & ok[d]
    tris = np.concatenate([np.stack([a, c, b], 1)[quad], np.stack([b, c, d], 1)[quad]])
    return verts, tris.astype(np.int64)


def terrain_without_buildings(dsm: Raster, dtm: Raster, footprints: list[np.ndarray], margin: float) -> Raster:
    """The DSM with cells inside the footprints ``(k, 2)`` grown by ``margin`` metres set to the DTM
    (both rasters on the same grid); NaN DSM cells also take the DTM."""
    import cv2

    out = np.asarray(dsm.data, np.float64).copy()
    mask = np.zeros(out.shape, np.uint8)
    for fp in footprints:
        cr = np.stack([(fp[:, 0] - dsm.x0) / dsm.cell - 0.5, (dsm.y0 - fp[:, 1]) / dsm.cell - 0.5], 1)
        cv2.fillPoly(mask, [np.round(cr * 16).astype(np.int32)], 1, shift=4)
    r = int(np.ceil(margin / dsm.cell))
    if r > 0:
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    ground = np.asarray(dtm.data, np.float64)
    replace = (mask > 0) | ~np.isfinite(out)
    out[replace] = ground[replace]
    return Raster(out, dsm.x0, dsm.y0, dsm.cell, dsm.crs)


class OcclusionScene:
    """A ray-casting scene of triangle meshes in a local float32 frame.

    Parameters
    ----------
    meshes : list of (vertices (n, 3) float64 world, triangles (t, 3) int) pairs
    origin : (3,) world point subtracted before casting (default: the first vertex)
    """

    def __init__(self, meshes: list[tuple[np.ndarray, np.ndarray]], origin: np.ndarray | None = None) -> None:
        import open3d as o3d

        meshes = [(np.asarray(v, np.float64), np.asarray(t, np.int64)) for v, t in meshes if len(t)]
        if origin is None:
            origin = meshes[0][0][0] if meshes else np.zeros(3)
        self.origin = np.asarray(origin, np.float64)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.triangles = 0
        for v, t in meshes:
            m = o3d.t.geometry.TriangleMesh()
            m.vertex.positions = o3d.core.Tensor((v - self.origin).astype(np.float32))
            m.triangle.indices = o3d.core.Tensor(t.astype(np.int32))
            self.scene.add_triangles(m)
            self.triangles += len(t)

    def visible(self, xyz: np.ndarray, normals: np.ndarray, centre: np.ndarray, offset: float) -> np.ndarray:
        """Whether the segment from each point to a camera centre is free.

        Parameters
        ----------
        xyz : (n, 3) float64 world points on surfaces; normals : (n, 3) or (3,) their outward unit normals
        centre : (3,) camera centre; offset : the rays start this far along the normal (metres), clear of
        the surface itself

        Returns
        -------
        (n,) bool
        """
        import open3d as o3d

        if self.triangles == 0 or len(xyz) == 0:
            return np.ones(len(xyz), bool)
        start = np.asarray(xyz, np.float64) + offset * np.asarray(normals, np.float64) - self.origin
        d = (np.asarray(centre, np.float64) - self.origin) - start
        dist = np.linalg.norm(d, axis=1)
        rays = np.empty((len(start), 6), np.float32)
        rays[:, :3] = start
        rays[:, 3:] = d / dist[:, None]
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        return ~(hit < dist - 0.5)

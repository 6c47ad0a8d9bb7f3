"""True orthophoto: differential rectification onto the DSM with occlusion detection and seamlines.

* Every DSM cell centre is projected into every candidate image (the nadir images by default).
* Occlusion (the depth test of a z-buffer, done exactly): the DSM is turned into a triangle mesh and the ray from
  the projection centre towards the cell is cast with Open3D; the cell is visible when the first hit is the cell
  itself (within a tolerance), so roofs hide the ground behind them and walls are never smeared over it.
* Preference: among the images that see a cell, the cost is the off-nadir angle of the ray plus the distance from
  the image centre, so the most nadir, central part of each image wins.
* Seamlines: around the preferred regions, images compete in a band of overlap; OpenCV's graph-cut seam finder
  (colour-gradient cost) puts the seams along low-difference paths, so they avoid buildings and cars whose lean
  differs between images. It runs on a reduced grid and the labels are upsampled.
* Mosaic: bilinear resampling of each cell from its image; cells no image sees stay empty (alpha 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry.projection import project
from ..model.camera import CameraModel
from ..model.pose import Pose
from ..model.raster import Raster


@dataclass(frozen=True)
class OrthoConfig:
    """Attributes
    ----------
    occlusion_tol : a cell is visible when the ray's first hit is at most this far (metres) before it
    centre_weight : weight of the distance from the image centre (0 at the centre, 1 at the corner) against the
        off-nadir angle in units of 45 degrees
    seam_band : width in cells of the band around each preferred region where seams may run
    seam_max_cells : the seam finder works on a grid of at most this many cells
    """

    occlusion_tol: float = 0.5
    centre_weight: float = 0.5
    seam_band: int = 12
    seam_max_cells: int = 120_000


@dataclass(frozen=True, eq=False)
class OrthoSource:
    """One candidate image: id, camera, pose and the BGR image (h, w, 3) uint8."""

    id: str
    camera: CameraModel
    pose: Pose
    image: np.ndarray


def dsm_mesh(dsm: Raster, origin: np.ndarray):
    """Open3D ``RaycastingScene`` of the DSM as a triangle mesh through the cell centres (local = world -
    origin); NaN cells are dropped with their triangles."""
    import open3d as o3d

    rows, cols = dsm.shape
    xs, ys = dsm.cell_centers()
    xx, yy = np.meshgrid(xs, ys)
    z = np.asarray(dsm.data, np.float64)
    verts = np.stack([xx.ravel(), yy.ravel(), z.ravel()], 1) - origin
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    ok = np.isfinite(verts[tris][:, :, 2]).all(axis=1)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.nan_to_num(verts).astype(np.float32)),
                        o3d.core.Tensor(tris[ok].astype(np.uint32)))
    return scene


def visibility(scene, origin: np.ndarray, src: OrthoSource, xyz: np.ndarray, tol: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(n, 2)`` of the points ``xyz (n, 3)`` in ``src`` and a mask of those inside the image and not
    occluded by the DSM ``scene``."""
    import open3d as o3d

    uv, depth = project(src.camera, src.pose, xyz)
    inside = np.isfinite(uv[:, 0]) & src.camera.contains(uv, margin=1.0) & (depth > 0)
    vis = np.zeros(len(xyz), bool)
    idx = np.flatnonzero(inside)
    if len(idx):
        c = src.pose.C - origin
        d = xyz[idx] - src.pose.C
        dist = np.linalg.norm(d, axis=1)
        rays = np.concatenate([np.broadcast_to(c, d.shape), d / dist[:, None]], 1).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        vis[idx] = t >= dist - tol
    return uv, vis


def sample_bilinear(image: np.ndarray, uv_px: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Bilinear colours ``(n, channels)`` of ``image`` at pixels ``uv_px (n, 2)`` (cv2.remap on a map folded into
    rows of ``chunk``, since remap maps are limited to 32767 columns)."""
    n = len(uv_px)
    rows = max(1, -(-n // chunk))
    m = np.zeros((rows * chunk, 2), np.float32)
    m[:n] = uv_px
    out = cv2.remap(image, m.reshape(rows, chunk, 2), None, cv2.INTER_LINEAR)
    return out.reshape(rows * chunk, -1)[:n]


def preference_cost(src: OrthoSource, xyz: np.ndarray, uv: np.ndarray, centre_weight: float) -> np.ndarray:
    """Cost ``(n,)`` of taking points from ``src``: off-nadir angle / 45 deg + centre_weight * radial distance."""
    d = xyz - src.pose.C
    off_nadir = np.degrees(np.arccos(np.clip(-d[:, 2] / np.linalg.norm(d, axis=1), -1, 1)))
    half_diag = 0.5 * np.hypot(src.camera.width, src.camera.height)
    r = np.hypot(uv[:, 0] - src.camera.cx, uv[:, 1] - src.camera.cy) / half_diag
    return off_nadir / 45.0 + centre_weight * r


def true_ortho(dsm: Raster, sources: list[OrthoSource], cfg: OrthoConfig = OrthoConfig(), progress=None
               ) -> tuple[Raster, np.ndarray]:
    """True orthophoto on the DSM grid.

    Parameters
    ----------
    dsm : the (hole-filled) DSM; NaN cells stay empty in the ortho
    sources : candidate images
    progress : optional ``progress(done, total, message)``

    Returns
    -------
    ortho : Raster (rows, cols, 4) uint8 RGBA (alpha 0 where no image sees the cell)
    label : (rows, cols) int16 index of the source of each cell, -1 where none
    """
    rows, cols = dsm.shape
    xs, ys = dsm.cell_centers()
    xx, yy = np.meshgrid(xs, ys)
    z = np.asarray(dsm.data, np.float64)
    valid = np.isfinite(z).ravel()
    xyz = np.stack([xx.ravel(), yy.ravel(), np.nan_to_num(z).ravel()], 1)
    origin = np.array([xs.mean(), ys.mean(), 0.0])
    scene = dsm_mesh(dsm, origin)
    n = len(sources)
    cost = np.full((n, rows * cols), np.inf, np.float32)
    colours = np.zeros((n, rows * cols, 3), np.uint8)
    idx = np.flatnonzero(valid)
    for k, src in enumerate(sources):
        uv, vis = visibility(scene, origin, src, xyz[idx], cfg.occlusion_tol)
        sel = idx[vis]
        cost[k, sel] = preference_cost(src, xyz[sel], uv[vis], cfg.centre_weight)
        colours[k, sel] = sample_bilinear(src.image, uv[vis])
        if progress is not None:
            progress(k + 1, n + 1, f"ortho: projected {src.id}")
    best = np.argmin(cost, axis=0)
    seen = np.isfinite(cost.min(axis=0))
    label = np.where(seen, best, -1).reshape(rows, cols)
    label = seamlines(label, cost.reshape(n, rows, cols), colours.reshape(n, rows, cols, 3), cfg)
    out = np.zeros((rows * cols, 4), np.uint8)
    flat = label.ravel()
    have = flat >= 0
    out[have, :3] = colours[flat[have], np.flatnonzero(have)][:, ::-1]
    out[have, 3] = 255
    if progress is not None:
        progress(n + 1, n + 1, "ortho: mosaic")
    return Raster(out.reshape(rows, cols, 4), dsm.x0, dsm.y0, dsm.cell, dsm.crs), label.astype(np.int16)


def seamlines(label: np.ndarray, cost: np.ndarray, colours: np.ndarray, cfg: OrthoConfig) -> np.ndarray:
    """Move the borders between preferred regions onto low-difference paths (OpenCV graph-cut seam finder).

    Parameters
    ----------
    label : (rows, cols) preferred source per cell (-1 none)
    cost : (n, rows, cols) preference cost (inf where a source does not see the cell)
    colours : (n, rows, cols, 3) uint8 each source's resampled colour

    Returns
    -------
    label : (rows, cols) int, the source per cell after seam finding
    """
    n, rows, cols = cost.shape
    used = [k for k in range(n) if (label == k).any()]
    if len(used) < 2:
        return label
    f = min(1.0, np.sqrt(cfg.seam_max_cells / (rows * cols)))
    size = (max(1, int(round(cols * f))), max(1, int(round(rows * f))))
    band = max(1, int(round(cfg.seam_band * f)))
    imgs, masks = [], []
    for k in used:
        own = cv2.resize((label == k).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
        sees = cv2.resize(np.isfinite(cost[k]).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
        grown = cv2.dilate(own, np.ones((2 * band + 1, 2 * band + 1), np.uint8)) & sees
        masks.append(cv2.UMat((grown * 255).astype(np.uint8)))
        imgs.append(cv2.UMat(cv2.resize(colours[k], size, interpolation=cv2.INTER_AREA).astype(np.float32)))
    finder = cv2.detail_GraphCutSeamFinder("COST_COLOR_GRAD")
    res = finder.find(imgs, [(0, 0)] * len(used), masks)
    masks = res if res is not None else masks
    small = np.full((size[1], size[0]), -1, np.int32)
    for k, m in zip(used, masks):
        mm = m.get() if isinstance(m, cv2.UMat) else np.asarray(m)
        small[(mm > 0) & (small < 0)] = k
    up = cv2.resize(small, (cols, rows), interpolation=cv2.INTER_NEAREST)
    ok = up >= 0
    ok[ok] = np.isfinite(cost[up[ok], np.nonzero(ok)[0], np.nonzero(ok)[1]])
    out = np.where(ok, up, label)
    out[label < 0] = -1
    return out

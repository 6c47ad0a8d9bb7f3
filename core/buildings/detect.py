"""Building detection from the nDSM and masks, and one point set per building.

Cells higher than ``min_height`` above the DTM form candidate objects; vegetation is rejected by roughness (the
height's deviation from its local median: tree crowns are rough, roofs are piecewise planar): with the surface
stage's vegetation mask, its cells are rejected where the surface is rough (a smooth green surface is a green
roof), without it whole rough components are rejected. Added robustness: crowns whose height noise stays under
that test still scatter their normals, so a mostly green component must also be planar: the median, over its
interior, of the normal variation in a 1 m window (``1 - |mean unit normal|`` of the smoothed DSM: 0 on a plane,
0.002 on a flat roof with 5 cm noise, 0.03 on the own-AT demo's tree groups, 0.004-0.03 on its roofs, the
noisiest where matching left gaps) must stay under ``max_green_curvature``, else it is vegetation. The margin
is small: a green roof as noisy as the demo's worst roofs would be rejected too. Connected components larger
than ``min_area`` are buildings; each gets the points that fall on its (slightly dilated) cells, and the ground
height is the DTM's median over it.
Optional user footprints (GeoJSON polygons) replace the components: each polygon, enlarged about its centroid
so that its nearest edge moves out by ``dilate``, collects its points.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..errors import InputError
from ..io.validate import read_json
from ..model.raster import Raster
from ..surface.dtm import normal_variation
from .geometry import points_in_polygon


@dataclass(frozen=True)
class DetectConfig:
    """min_height : above the DTM (m); min_area : smallest building (m^2); rough_tol : deviation from the 5x5
    median (m) that marks a rough cell; max_rough_share : components rougher than this are vegetation;
    dilate : margin added around a building to collect its facade points (m); max_green_curvature : largest
    median normal variation of a mostly green component (see the module docstring)."""

    min_height: float = 2.5
    min_area: float = 25.0
    rough_tol: float = 0.35
    max_rough_share: float = 0.35
    dilate: float = 1.5
    max_green_curvature: float = 0.025


@dataclass(frozen=True)
class DetectedBuilding:
    """label : component label in the grid; indices : (k,) indices of its points; ground_z : DTM height;
    area : m^2 of its cells; footprint : (m, 2) user footprint or None."""

    label: int
    indices: np.ndarray
    ground_z: float
    area: float
    footprint: np.ndarray | None = None


def building_labels(dsm: Raster, dtm: Raster, cfg: DetectConfig = DetectConfig(),
                    building_mask: np.ndarray | None = None,
                    vegetation_mask: np.ndarray | None = None) -> tuple[np.ndarray, int, dict]:
    """Label grid (rows, cols) int32 of buildings on the DSM grid (0 = none), their count, and statistics."""
    z = np.asarray(dsm.data, dtype=np.float64)
    g = np.asarray(dtm.data, dtype=np.float64)
    ndsm = z - g
    high = np.nan_to_num(ndsm, nan=0.0) > cfg.min_height
    filled = np.where(np.isfinite(z), z, np.nanmedian(z))
    rough = np.abs(filled - ndimage.median_filter(filled, size=5)) > cfg.rough_tol
    veg = None
    if vegetation_mask is not None:
        # green but smooth and planar is a (green) roof, not a tree: only rough vegetation cells are rejected
        near_rough = ndimage.uniform_filter(rough.astype(np.float64), size=7) > 0.15
        veg = vegetation_mask.astype(bool) & near_rough
        high &= ~veg
    if building_mask is not None:
        bmask = building_mask.astype(bool)
        if vegetation_mask is not None:  # green roofs the mask gave to vegetation come back
            bmask |= vegetation_mask.astype(bool) & ~veg
        high &= bmask
    lab, n = ndimage.label(ndimage.binary_opening(high, np.ones((3, 3))), np.ones((3, 3)))
    curv = normal_variation(filled, dsm.cell) if vegetation_mask is not None else None
    win = max(int(round(1.0 / dsm.cell)), 1)
    out = np.zeros_like(lab, dtype=np.int32)
    stats = {"components": int(n), "too_small": 0, "vegetation": 0}
    k = 0
    cell_area = dsm.cell * dsm.cell
    for i, sl in enumerate(ndimage.find_objects(lab), start=1):
        m = lab[sl] == i
        area = m.sum() * cell_area
        if area < cfg.min_area:
            stats["too_small"] += 1
            continue
        if vegetation_mask is None and rough[sl][m].mean() > cfg.max_rough_share:
            stats["vegetation"] += 1
            continue
        if curv is not None and vegetation_mask[sl][m].mean() > 0.5:
            inner = ndimage.binary_erosion(m, iterations=2 * win)
            if float(np.median(curv[sl][inner if inner.any() else m])) > cfg.max_green_curvature:
                stats["vegetation"] += 1
                continue
        k += 1
        out[sl][m] = k
    return out, k, stats


def points_per_building(xyz: np.ndarray, labels: np.ndarray, grid: Raster, dtm: Raster,
                        cfg: DetectConfig = DetectConfig()) -> list[DetectedBuilding]:
    """Split points ``(n, 3)`` by the building label of their cell, labels grown by ``cfg.dilate``."""
    dist, (ri, ci) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    grown = np.where(dist * grid.cell <= cfg.dilate, labels[ri, ci], 0)
    cr = np.floor(grid.world_to_cell(xyz[:, :2]) + 0.5).astype(np.int64)
    rows, cols = labels.shape
    ok = (cr[:, 0] >= 0) & (cr[:, 0] < cols) & (cr[:, 1] >= 0) & (cr[:, 1] < rows)
    lab = np.zeros(len(xyz), np.int32)
    lab[ok] = grown[cr[ok, 1], cr[ok, 0]]
    order = np.argsort(lab, kind="stable")
    bounds = np.searchsorted(lab[order], np.arange(labels.max() + 2))
    gz = np.asarray(dtm.data, dtype=np.float64)
    out = []
    for k in range(1, int(labels.max()) + 1):
        idx = order[bounds[k]:bounds[k + 1]]
        cells = labels == k
        ground = float(np.nanmedian(gz[cells])) if cells.any() else float(np.nanmedian(gz))
        out.append(DetectedBuilding(k, idx, ground, float(cells.sum() * grid.cell ** 2)))
    return out


def read_footprints(path: str | Path) -> list[np.ndarray]:
    """Outer rings (m, 2) of the Polygon / MultiPolygon features of a GeoJSON file (project CRS)."""
    path = Path(path)
    doc = read_json(path, "footprint file not found")
    feats = None
    if isinstance(doc, dict):
        feats = doc.get("features", [doc] if doc.get("type") == "Feature" else None)
    if not isinstance(feats, list):
        raise InputError("expected a FeatureCollection or a Feature", path, field="type")
    rings = []
    for i, f in enumerate(feats):
        geom = (f.get("geometry") if isinstance(f, dict) else None) or {}
        kind, coords = (geom.get("type"), geom.get("coordinates")) if isinstance(geom, dict) else (None, None)
        try:
            polys = [coords] if kind == "Polygon" else coords if kind == "MultiPolygon" else None
            if polys is None:
                raise InputError(f"feature {i}: geometry type {kind!r} is not a polygon", path, field="geometry")
            for poly in polys:
                ring = np.asarray(poly[0], dtype=np.float64)[:, :2]
                if len(ring) > 1 and np.allclose(ring[0], ring[-1]):
                    ring = ring[:-1]
                if len(ring) < 3:
                    raise InputError(f"feature {i}: ring with fewer than 3 corners", path, field="coordinates")
                if not np.all(np.isfinite(ring)):
                    raise InputError(f"feature {i}: coordinates not finite", path, field="coordinates")
                rings.append(ring)
        except (TypeError, ValueError, IndexError):
            raise InputError(f"feature {i}: malformed coordinates", path, field="coordinates") from None
    return rings


def points_per_footprint(xyz: np.ndarray, footprints: list[np.ndarray], dtm: Raster,
                         cfg: DetectConfig = DetectConfig()) -> list[DetectedBuilding]:
    """One point set per user footprint, the ring enlarged about its centroid so that the edge nearest to the
    centroid moves out by about ``cfg.dilate``."""
    out = []
    for k, ring in enumerate(footprints, start=1):
        area = 0.5 * np.sum(ring[:, 0] * np.roll(ring[:, 1], -1) - np.roll(ring[:, 0], -1) * ring[:, 1])
        ring = ring if area > 0 else ring[::-1]
        c = ring.mean(0)
        grown = c + (ring - c) * (1 + cfg.dilate / max(np.linalg.norm(ring - c, axis=1).min(), 1e-6))
        lo, hi = grown.min(0), grown.max(0)
        box = np.nonzero(np.all((xyz[:, :2] >= lo) & (xyz[:, :2] <= hi), axis=1))[0]
        idx = box[points_in_polygon(xyz[box, :2], grown)]
        gz = dtm.sample(ring)
        out.append(DetectedBuilding(k, idx, float(np.nanmedian(gz)), float(abs(area)), ring))
    return out

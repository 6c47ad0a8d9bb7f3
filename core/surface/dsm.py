"""Ortho-DSM from a point cloud: robust per-cell height on a north-up grid, small holes filled.

Per cell the height is the median of the points in the top band of the cell (within ``band`` metres below the
cell's 90th percentile): on a roof this is the median of the roof points (robust against noise and the odd
blunder), in a cell crossed by a wall it is the roof, not the middle of the wall, because the DSM is the top
surface. Isolated blunders (cells with almost no neighbour at their height) are removed. Holes up to
``max_hole_m2`` (occlusions, poor texture) are filled: by inpainting where their surroundings are nearly
level, with the low side's height where they lie between a roof and the ground; larger holes stay empty (NaN).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from ..model.raster import Raster


@dataclass(frozen=True)
class GridSpec:
    """A north-up grid: outer corner ``x0, y0`` of the top-left cell, cell size, rows, cols."""

    x0: float
    y0: float
    cell: float
    rows: int
    cols: int

    @classmethod
    def around(cls, xmin: float, ymin: float, xmax: float, ymax: float, cell: float) -> GridSpec:
        """The grid of cells aligned to multiples of ``cell`` that covers the box."""
        x0, y0 = np.floor(xmin / cell) * cell, np.ceil(ymax / cell) * cell
        cols = int(np.ceil((xmax - x0) / cell))
        rows = int(np.ceil((y0 - ymin) / cell))
        return cls(float(x0), float(y0), float(cell), max(rows, 1), max(cols, 1))

    def cell_index(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row, column ``(n,)`` int64 of world points ``(n, 2)`` and a mask of those inside the grid."""
        c = np.floor((xy[:, 0] - self.x0) / self.cell).astype(np.int64)
        r = np.floor((self.y0 - xy[:, 1]) / self.cell).astype(np.int64)
        inside = (r >= 0) & (r < self.rows) & (c >= 0) & (c < self.cols)
        return r, c, inside

    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World X ``(rows, cols)`` and Y ``(rows, cols)`` of the cell centres."""
        x = self.x0 + (np.arange(self.cols) + 0.5) * self.cell
        y = self.y0 - (np.arange(self.rows) + 0.5) * self.cell
        return np.meshgrid(x, y)

    def raster(self, data: np.ndarray, crs: str, nodata: float | None = None) -> Raster:
        return Raster(data, self.x0, self.y0, self.cell, crs, nodata)


@dataclass(frozen=True)
class DsmConfig:
    """Attributes
    ----------
    cell : cell size in metres (0 = the nadir GSD of the block)
    top_quantile : quantile defining the top of a cell's points
    band : points within this many metres below the top quantile form the cell's top band
    min_points : cells with fewer points are empty
    spike : cells with fewer than two of their 8 neighbours within this many metres are removed as blunders
    max_hole_m2 : holes up to this area are filled
    max_hole_step : holes whose surroundings span less than this (metres) are inpainted; others (occlusions
        between a roof and the ground) take the height of their low surroundings
    """

    cell: float = 0.0
    top_quantile: float = 0.9
    band: float = 0.5
    min_points: int = 1
    spike: float = 1.0
    max_hole_m2: float = 50.0
    max_hole_step: float = 1.0


def _group_quantile(key: np.ndarray, z: np.ndarray, q: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per group (sorted unique keys) the ``q`` quantile (lower element) of ``z``, and the counts."""
    order = np.lexsort((z, key))
    k, zs = key[order], z[order]
    uniq, start, counts = np.unique(k, return_index=True, return_counts=True)
    return uniq, zs[start + np.floor(q * (counts - 1)).astype(np.int64)], counts


def grid_points(grid: GridSpec, xyz: np.ndarray, cfg: DsmConfig = DsmConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Robust per-cell heights of points ``xyz : (n, 3)``.

    Returns
    -------
    height : (rows, cols) float64, NaN for cells with fewer than ``min_points``
    top : (n,) bool, the points in their cell's top band (the ones that made the height)
    """
    r, c, inside = grid.cell_index(xyz[:, :2])
    key = np.where(inside, r * grid.cols + c, -1)
    z = xyz[:, 2]
    idx = np.flatnonzero(inside)
    uniq, ztop, _ = _group_quantile(key[idx], z[idx], cfg.top_quantile)
    top_of = np.full(grid.rows * grid.cols, np.nan)
    top_of[uniq] = ztop
    top = np.zeros(len(xyz), bool)
    top[idx] = z[idx] >= top_of[key[idx]] - cfg.band
    sel = np.flatnonzero(top)
    uniq2, zmed, counts = _group_quantile(key[sel], z[sel], 0.5)
    height = np.full(grid.rows * grid.cols, np.nan)
    keep = counts >= cfg.min_points
    height[uniq2[keep]] = zmed[keep]
    return height.reshape(grid.rows, grid.cols), top


def remove_spikes(height: np.ndarray, threshold: float, min_support: int = 2) -> np.ndarray:
    """Empty the cells (rows, cols) with fewer than ``min_support`` of their 8 neighbours within ``threshold``
    metres (isolated blunders; a roof corner keeps three neighbours at its height)."""
    pad = np.pad(height, 1, constant_values=np.nan)
    rows, cols = height.shape
    support = np.zeros(height.shape, np.int32)
    with np.errstate(invalid="ignore"):
        for dr in (0, 1, 2):
            for dc in (0, 1, 2):
                if dr == 1 and dc == 1:
                    continue
                support += np.abs(pad[dr:dr + rows, dc:dc + cols] - height) <= threshold
    out = height.copy()
    out[np.isfinite(height) & (support < min_support)] = np.nan
    return out


def fill_small_holes(height: np.ndarray, max_cells: int, max_step: float = np.inf) -> np.ndarray:
    """Fill NaN regions of at most ``max_cells`` cells (not touching the border).

    A hole whose surrounding cells span less than ``max_step`` metres is inpainted (Navier-Stokes) from them. A
    hole between a high and a low surface (an occlusion beside a building, seen from above) takes the median of
    its low surrounding cells (those within ``max_step`` of the lowest): the ground hidden behind the wall,
    rather than a made-up slope from the roof down to the ground ("low" is taken near the lower quartile of
    the surrounding cells, so a few blunder cells below the ground do not decide it).
    """
    holes = ~np.isfinite(height)
    if not holes.any() or holes.all():
        return height
    labels, n = ndimage.label(holes)
    idx = np.arange(1, n + 1)
    sizes = ndimage.sum(holes, labels, index=idx)
    ring = ndimage.grey_dilation(labels, size=3) * ~holes  # border cells carry the label of the hole they touch
    ring_lo = np.full(n + 1, np.nan)
    ring_hi = np.full(n + 1, np.nan)
    ring_lo[1:] = ndimage.minimum(height, ring, index=idx)
    ring_hi[1:] = ndimage.maximum(height, ring, index=idx)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    small = np.zeros(n + 1, bool)
    small[1:] = sizes <= max_cells
    small[border] = False
    small &= np.isfinite(ring_lo)
    level = small & (ring_hi - ring_lo < max_step)
    step = small & ~level
    result = height.copy()
    fill = level[labels]
    if fill.any():
        lo = float(np.nanmin(height))
        span = max(float(np.nanmax(height)) - lo, 1e-6)
        norm = np.nan_to_num((height - lo) / span, nan=0.0).astype(np.float32)
        out = cv2.inpaint(norm, fill.astype(np.uint8), 3, cv2.INPAINT_NS).astype(np.float64) * span + lo
        result[fill] = out[fill]
    if step.any():
        # the low side: ring cells near the ring's lower quartile (a few blunder cells in the ring do not count)
        rk = np.flatnonzero((ring.ravel() > 0) & step[ring.ravel()])
        uniq, q25, _ = _group_quantile(ring.ravel()[rk], height.ravel()[rk], 0.25)
        low_ref = np.full(n + 1, np.nan)
        low_ref[uniq] = q25
        near = (ring > 0) & step[ring] & (np.abs(height - low_ref[ring]) <= max_step)
        ground = np.full(n + 1, np.nan)
        ground[1:] = ndimage.median(height, np.where(near, ring, 0), index=idx)
        sel = step[labels]
        result[sel] = ground[labels[sel]]
    return result


def cell_colours(grid: GridSpec, xyz: np.ndarray, rgb: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Mean colour ``(rows, cols, 3)`` float64 of the points selected by ``use : (n,)`` per cell (NaN empty)."""
    r, c, inside = grid.cell_index(xyz[:, :2])
    ok = inside & use
    key = r[ok] * grid.cols + c[ok]
    n = np.bincount(key, minlength=grid.rows * grid.cols).astype(np.float64)
    out = np.stack([np.bincount(key, weights=rgb[ok, i].astype(np.float64), minlength=grid.rows * grid.cols)
                    for i in range(3)], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out /= n[:, None]
    return out.reshape(grid.rows, grid.cols, 3)


def make_dsm(grid: GridSpec, xyz: np.ndarray, crs: str, cfg: DsmConfig = DsmConfig()) -> tuple[Raster, np.ndarray]:
    """The DSM raster (holes filled) and the top-band mask of the points."""
    height, top = grid_points(grid, xyz, cfg)
    height = remove_spikes(height, cfg.spike) if cfg.spike > 0 else height
    filled = fill_small_holes(height, int(cfg.max_hole_m2 / grid.cell ** 2), cfg.max_hole_step)
    return grid.raster(filled.astype(np.float32), crs), top

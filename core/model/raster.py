"""Georeferenced rasters (DSM, DTM, orthophoto, quality layers) as numpy arrays with a north-up transform."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(eq=False)
class Raster:
    """A north-up grid.

    Attributes
    ----------
    data : (rows, cols) or (rows, cols, bands) array; NaN (float) or ``nodata`` marks empty cells
    x0, y0 : world coordinates of the *outer corner* of the top-left cell (GeoTIFF PixelIsArea convention)
    cell : cell size in metres (square cells)
    crs : EPSG:nnnn or WKT
    nodata : value for empty cells in integer rasters, or None
    """

    data: np.ndarray
    x0: float
    y0: float
    cell: float
    crs: str
    nodata: float | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape[0], self.data.shape[1]

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World X of column centres (cols,) and Y of row centres (rows,)."""
        rows, cols = self.shape
        return (self.x0 + (np.arange(cols) + 0.5) * self.cell,
                self.y0 - (np.arange(rows) + 0.5) * self.cell)

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """World ``(n, 2)`` to fractional (col, row) ``(n, 2)`` with cell centres at integers."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.stack([(xy[:, 0] - self.x0) / self.cell - 0.5, (self.y0 - xy[:, 1]) / self.cell - 0.5], 1)

    def sample(self, xy: np.ndarray, order: int = 1) -> np.ndarray:
        """Values at world points ``(n, 2)`` (bilinear for ``order=1``, nearest for 0); NaN outside."""
        from scipy.ndimage import map_coordinates

        cr = self.world_to_cell(xy)
        data = np.asarray(self.data, dtype=np.float64)
        if data.ndim != 2:
            raise ValueError("sample() works on single-band rasters")
        out = map_coordinates(data, [cr[:, 1], cr[:, 0]], order=order, mode="constant", cval=np.nan)
        rows, cols = self.shape
        outside = (cr[:, 0] < -0.5) | (cr[:, 0] > cols - 0.5) | (cr[:, 1] < -0.5) | (cr[:, 1] > rows - 0.5)
        out[outside] = np.nan
        return out

    def geotransform(self) -> tuple[float, float, float, float, float, float]:
        """GDAL-style geotransform ``(x0, cell, 0, y0, 0, -cell)``."""
        return (self.x0, self.cell, 0.0, self.y0, 0.0, -self.cell)

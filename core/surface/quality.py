"""Quality maps: per-cell mean of a per-point quantity (the forward intersection error), as a raster and as a
colour-coded picture with its scale."""

from __future__ import annotations

import cv2
import numpy as np

from .dsm import GridSpec


def mean_per_cell(grid: GridSpec, xyz: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(rows, cols) mean of ``values (n,)`` over the points ``xyz (n, 3)`` of each cell (NaN empty)."""
    r, c, inside = grid.cell_index(xyz[:, :2])
    ok = inside & np.isfinite(values)
    key = r[ok] * grid.cols + c[ok]
    s = np.bincount(key, weights=values[ok], minlength=grid.rows * grid.cols)
    n = np.bincount(key, minlength=grid.rows * grid.cols)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (s / n).reshape(grid.rows, grid.cols)


def colour_map(values: np.ndarray, vmax: float) -> np.ndarray:
    """(rows, cols, 3) uint8 RGB picture of ``values`` from 0 (blue) to ``vmax`` (red) with the turbo colour map;
    empty cells are black."""
    scaled = np.clip(np.nan_to_num(values, nan=0.0) / max(vmax, 1e-12), 0, 1)
    bgr = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    bgr[~np.isfinite(values)] = 0
    return np.ascontiguousarray(bgr[..., ::-1])

"""DTM by robust grey-scale morphology, point classification, robust interpolation; nDSM and object masks.

The production method for urban point clouds:

1. Grid the point cloud at ``cell`` metres (a low quantile of the points per cell; empty cells take their
   nearest neighbour).
2. Grey-scale opening with a square structuring element of about ``se_size`` metres (larger than the largest
   building): the erosion takes the k-th *sorted* element of the window (k = 3 %, robust against points below the
   ground, which a plain minimum would spread over the whole window), the dilation takes the maximum.
3. Every point is classified ``above``, ``on`` or ``below`` the opened surface with a threshold (1.5 m).
4. The DTM is a robust interpolation of the ground ("on") points: per cell their median, then iterated
   normalised Gaussian interpolation with the asymmetric weights of Kraus and Pfeifer (1998): points far above
   the current surface get small weights (remaining vegetation and building points), points below keep full
   weight.

The nDSM is DSM - DTM; raised objects are vegetation when green (excess-green index ``(2G - R - B) / (R + G +
B)``) and rough, else buildings (see :func:`object_masks`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from ..model.raster import Raster
from .dsm import GridSpec

ABOVE, ON, BELOW = 1, 0, -1


@dataclass(frozen=True)
class DtmConfig:
    """Attributes
    ----------
    cell : grid cell of the morphological filter, metres (coarsened so the window stays <= 61 cells)
    cell_quantile : height of a grid cell as this quantile of its points (a low one: ground where it shows,
        yet single blunders below the ground do not make the cell)
    se_size : side of the square structuring element, metres
    erosion_rank : k of the k-th sorted element for the erosion, as a fraction of the window (0.03)
    threshold : above/on/below classification threshold, metres
    interp_sigma : Gaussian radius of the robust interpolation, cells
    iterations : robust interpolation iterations
    building_min_height, vegetation_min_height : nDSM thresholds of the masks, metres
    greenness_min : excess-green threshold of a vegetation cell
    roughness_min : least median roughness (metres) of a vegetation object
    curvature_min : least median normal variation (:func:`normal_variation`) of a vegetation object smooth enough
        to pass ``roughness_min``
    min_object_m2 : objects smaller than this are removed from the masks
    """

    cell: float = 1.0
    cell_quantile: float = 0.25
    se_size: float = 60.0
    erosion_rank: float = 0.03
    threshold: float = 1.5
    interp_sigma: float = 2.0
    iterations: int = 4
    building_min_height: float = 2.5
    vegetation_min_height: float = 1.0
    greenness_min: float = 0.3
    roughness_min: float = 0.06
    curvature_min: float = 0.025
    min_object_m2: float = 10.0


def _fill_nearest(a: np.ndarray) -> np.ndarray:
    bad = ~np.isfinite(a)
    if not bad.any() or bad.all():
        return a
    idx = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
    return a[tuple(idx)]


def low_quantile_per_cell(grid: GridSpec, xyz: np.ndarray, q: float) -> np.ndarray:
    """(rows, cols) ``q``-quantile of the point heights per cell (0 = the lowest point), NaN for empty cells."""
    r, c, inside = grid.cell_index(xyz[:, :2])
    key = r[inside] * grid.cols + c[inside]
    z = xyz[inside, 2]
    order = np.lexsort((z, key))
    k, zs = key[order], z[order]
    uniq, start, counts = np.unique(k, return_index=True, return_counts=True)
    out = np.full(grid.rows * grid.cols, np.nan)
    out[uniq] = zs[start + np.floor(q * (counts - 1)).astype(np.int64)]
    return out.reshape(grid.rows, grid.cols)


def robust_opening(surface: np.ndarray, window: int, rank: float) -> np.ndarray:
    """Grey-scale opening of ``surface (rows, cols)`` (no NaN) with a square ``window``: erosion by the
    ``rank``-quantile element of the window, dilation by the maximum."""
    eroded = ndimage.percentile_filter(surface, 100.0 * rank, size=window, mode="nearest")
    return ndimage.maximum_filter(eroded, size=window, mode="nearest")


def classify_points(opened: Raster, xyz: np.ndarray, threshold: float) -> np.ndarray:
    """(n,) int8 class of each point: ``ABOVE`` (1), ``ON`` (0) or ``BELOW`` (-1) the opened surface."""
    x1, y1 = opened.x0 + opened.shape[1] * opened.cell, opened.y0 - opened.shape[0] * opened.cell
    eps = 1e-6 * opened.cell
    xy = np.column_stack([np.clip(xyz[:, 0], opened.x0 + eps, x1 - eps), np.clip(xyz[:, 1], y1 + eps, opened.y0 - eps)])
    ref = opened.sample(xy)  # points beyond the grid take the value at its border
    dz = xyz[:, 2] - ref
    out = np.zeros(len(xyz), np.int8)
    out[dz > threshold] = ABOVE
    out[dz < -threshold] = BELOW
    return out


def robust_interpolation(grid: GridSpec, xyz: np.ndarray, sigma: float, iterations: int,
                         g: float = -0.2, w_half: float = 0.3) -> np.ndarray:
    """Robust surface ``(rows, cols)`` through ground points ``xyz (n, 3)``.

    Per cell the median of the points, then ``iterations`` rounds of normalised Gaussian interpolation with
    Kraus-Pfeifer weights ``w = 1 / (1 + (a (r - g))^4)`` for residuals ``r`` above the shift ``g`` (a chosen so
    a residual of ``g + w_half`` metres has weight 1/2) and ``w = 1`` below it.
    """
    obs = low_quantile_per_cell(grid, xyz, 0.5)  # the (lower) median per cell
    have = np.isfinite(obs)
    if not have.any():
        return obs
    w = have.astype(np.float64)
    z0 = np.nan_to_num(obs)
    a = 1.0 / w_half
    surf = obs
    for _ in range(max(1, iterations)):
        num = ndimage.gaussian_filter(w * z0, sigma, mode="nearest")
        den = ndimage.gaussian_filter(w, sigma, mode="nearest")
        with np.errstate(invalid="ignore", divide="ignore"):
            surf = np.where(den > 1e-3, num / den, np.nan)
        surf = _fill_nearest(surf)
        res = obs - surf
        w = np.where(have, np.where(res <= g, 1.0, 1.0 / (1.0 + (a * (res - g)) ** 4)), 0.0)
    return surf


def make_dtm(xyz: np.ndarray, grid_out: GridSpec, crs: str, cfg: DtmConfig = DtmConfig()
             ) -> tuple[Raster, np.ndarray, Raster]:
    """DTM on ``grid_out`` from points ``xyz (n, 3)``.

    Returns
    -------
    dtm : Raster on ``grid_out`` (float32)
    classes : (n,) int8 point classes (ABOVE / ON / BELOW)
    opened : Raster of the opened surface on the filter grid
    """
    cell = max(cfg.cell, cfg.se_size / 61.0)
    x1 = grid_out.x0 + grid_out.cols * grid_out.cell
    y1 = grid_out.y0 - grid_out.rows * grid_out.cell
    # the filter grid reaches one structuring element beyond the output grid (where there are points), so
    # buildings cut by the border of the output grid are seen whole
    lo, hi = np.percentile(xyz[:, :2], [0.1, 99.9], axis=0) if len(xyz) else (np.full(2, np.inf), -np.full(2, np.inf))
    m = cfg.se_size
    g = GridSpec.around(max(min(grid_out.x0, lo[0]), grid_out.x0 - m), max(min(y1, lo[1]), y1 - m),
                        min(max(x1, hi[0]), x1 + m), min(max(grid_out.y0, hi[1]), grid_out.y0 + m), cell)
    low = _fill_nearest(low_quantile_per_cell(g, xyz, cfg.cell_quantile))
    window = max(3, int(round(cfg.se_size / cell)) | 1)
    opened = g.raster(robust_opening(low, window, cfg.erosion_rank), crs)
    classes = classify_points(opened, xyz, cfg.threshold)
    coarse = g.raster(robust_interpolation(g, xyz[classes == ON], cfg.interp_sigma, cfg.iterations), crs)
    xs, ys = grid_out.centers()
    fine = coarse.sample(np.stack([xs.ravel(), ys.ravel()], 1)).reshape(xs.shape)
    # cells near the border of the coarse grid fall outside its cell centres: take the nearest value there
    fine = _fill_nearest(fine)
    return grid_out.raster(fine.astype(np.float32), crs), classes, opened


def greenness(rgb: np.ndarray) -> np.ndarray:
    """Excess-green index ``(2G - R - B) / (R + G + B)`` of ``rgb (..., 3)`` (NaN where black or unknown)."""
    rgb = np.asarray(rgb, np.float64)
    s = rgb.sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(s > 0, (2 * rgb[..., 1] - rgb[..., 0] - rgb[..., 2]) / s, np.nan)


def roughness(ndsm: np.ndarray, window: int = 5) -> np.ndarray:
    """Mean absolute deviation (metres) of the surface from its ``window`` x ``window`` median, averaged over the
    same window: near zero on planar roofs (and along their straight edges, which a median keeps), large in tree
    crowns. (rows, cols)."""
    z = np.nan_to_num(ndsm).astype(np.float32)
    return ndimage.uniform_filter(np.abs(z - cv2.medianBlur(z, window)), window)


def normal_variation(z: np.ndarray, cell: float, window: float = 1.0) -> np.ndarray:
    """``1 - |mean unit normal|`` over a ``window`` (m) of a height grid ``z (rows, cols)`` smoothed with a
    one-cell Gaussian: 0 on a plane, growing with curvature and small-scale roughness."""
    gy, gx = np.gradient(ndimage.gaussian_filter(z, 1.0), cell)
    nz = 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)
    k = max(int(round(window / cell)) | 1, 3)
    mean = [ndimage.uniform_filter(c, k) for c in (-gx * nz, -gy * nz, nz)]
    return 1.0 - np.sqrt(mean[0] ** 2 + mean[1] ** 2 + mean[2] ** 2)


def object_masks(ndsm: np.ndarray, rgb: np.ndarray | None, cell: float, cfg: DtmConfig = DtmConfig()
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Building and vegetation masks ``(rows, cols)`` bool from the nDSM and, when given, cell colours
    ``rgb (rows, cols, 3)``.

    Raised objects (connected cells above ``vegetation_min_height``) are classified whole: vegetation when most
    of their cells are green (excess-green index above ``greenness_min``) and their surface is rough (median
    :func:`roughness` above ``roughness_min``) or bumpy at the metre scale (median :func:`normal_variation`
    above ``curvature_min``: crowns smooth enough to pass the roughness test still scatter their normals, a
    green roof is planar; as noisy as the demo's worst roofs it would count as vegetation too), else their cells
    above ``building_min_height`` are building. Without colour every raised object counts as a building.
    """
    with np.errstate(invalid="ignore"):
        raised = ndsm > cfg.vegetation_min_height
    raised = ndimage.binary_opening(raised, iterations=1)
    lab, n = ndimage.label(raised)
    idx = np.arange(1, n + 1)
    veg_obj = np.zeros(n + 1, bool)
    if rgb is not None and n:
        green = (greenness(rgb) > cfg.greenness_min).astype(np.float64)
        green_share = ndimage.mean(green, lab, index=idx)
        rough = ndimage.median(roughness(ndsm), lab, index=idx)
        curved = ndimage.median(normal_variation(np.nan_to_num(ndsm), cell), lab, index=idx)
        veg_obj[1:] = (green_share > 0.5) & ((rough > cfg.roughness_min) | (curved > cfg.curvature_min))
    veg = veg_obj[lab] & raised
    with np.errstate(invalid="ignore"):
        bld = raised & ~veg & (ndsm > cfg.building_min_height)
    min_cells = max(1, int(cfg.min_object_m2 / cell ** 2))
    out = []
    for m in (bld, veg):
        lab2, k = ndimage.label(m)
        if k:
            sizes = ndimage.sum(m, lab2, index=np.arange(1, k + 1))
            keep = np.zeros(k + 1, bool)
            keep[1:] = sizes >= min_cells
            m = keep[lab2]
        out.append(m)
    return out[0], out[1]


LAS_CLASSES = {"unclassified": 1, "ground": 2, "medium_vegetation": 4, "high_vegetation": 5, "building": 6,
               "low_point": 7}
"""ASPRS LAS 1.4 classification codes the surface stage assigns."""


def las_classes(classes: np.ndarray, xyz: np.ndarray, normal: np.ndarray, grid: GridSpec, building: np.ndarray,
                vegetation: np.ndarray, dtm: np.ndarray, facade_nz: float = 0.3, facade_reach_m: float = 1.0,
                high_vegetation_m: float = 2.0) -> np.ndarray:
    """ASPRS codes ``(n,) uint8`` (:data:`LAS_CLASSES`) of points ``xyz (n, 3)``.

    Ground (2) where the morphological filter put the point ``ON`` the terrain, low point (7) ``BELOW`` it. A point
    ``ABOVE`` it is building (6) in a cell of the ``building (rows, cols)`` mask of ``grid``, or within
    ``facade_reach_m`` of the mask when its ``normal (n, 3)`` is near horizontal (``|n_z| < facade_nz``: a facade
    point, which stands on the mask's outer edge); vegetation in a ``vegetation`` cell, high (5) from
    ``high_vegetation_m`` above the ``dtm (rows, cols)``, else medium (4); anything else raised (vehicles, street
    furniture, points beyond the grid) stays unclassified (1).
    """
    out = np.full(len(xyz), LAS_CLASSES["unclassified"], np.uint8)
    out[classes == ON] = LAS_CLASSES["ground"]
    out[classes == BELOW] = LAS_CLASSES["low_point"]
    r, c, inside = grid.cell_index(xyz[:, :2])
    above = np.flatnonzero((classes == ABOVE) & inside)
    r, c = r[above], c[above]
    reach = max(1, int(np.ceil(facade_reach_m / grid.cell)))
    near_building = ndimage.binary_dilation(building, iterations=reach)
    facade = (np.abs(normal[above, 2]) < facade_nz) & np.any(normal[above] != 0, axis=1)
    is_bld = building[r, c] | (facade & near_building[r, c])
    is_veg = vegetation[r, c] & ~is_bld
    out[above[is_bld]] = LAS_CLASSES["building"]
    high = xyz[above, 2] - dtm[r, c] >= high_vegetation_m
    out[above[is_veg & high]] = LAS_CLASSES["high_vegetation"]
    out[above[is_veg & ~high]] = LAS_CLASSES["medium_vegetation"]
    return out

"""The ``surface`` stage: DSM, DTM, nDSM, building/vegetation masks, true orthophoto and quality maps.

Reads ``dense/points.npz`` and the block; writes GeoTIFFs (with CRS and transform) and PNG previews into
``surface/``: ``dsm.tif``, ``dtm.tif``, ``ndsm.tif``, ``buildings.tif``, ``vegetation.tif`` (uint8 masks),
``ortho.tif`` (RGBA true orthophoto), ``ortho_source.tif`` (index of the image each cell came from),
``quality_adjusted.tif`` / ``quality_approx.tif`` (mean forward intersection error per cell, with the
orientation used for matching and with the approximate one), ``*.png`` previews, ``point_classes.npy`` (the
above/on/below class of every kept dense point) and ``points_classified.laz``: the kept dense points with their
ASPRS classes (:func:`.dtm.las_classes`: ground, low point, building with its facades, medium and high
vegetation, unclassified), with a display subset ``points_classified_display.laz``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..errors import WorkspaceError
from ..geometry.views import VIEWS
from ..io.geotiff import write_geotiff, write_png
from ..io.photos import camera_bits, read_photo
from ..io.pointcloud import PointCloud, display_subset, write_las
from ..io.validate import resolve_image
from ..pipeline.stage import (
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    CheckedOptions,
    Range,
    Rule,
    Stage,
    StageResult,
    area_error,
)
from .dsm import DsmConfig, GridSpec, cell_colours, make_dsm
from .dtm import ABOVE, BELOW, LAS_CLASSES, ON, DtmConfig, las_classes, make_dtm, object_masks
from .ortho import OrthoConfig, OrthoSource, true_ortho
from .quality import colour_map, mean_per_cell

DISPLAY_POINTS = 300_000
"""Size of the classified points' display subset."""


@dataclass(frozen=True)
class SurfaceConfig(CheckedOptions):
    """Options of the ``surface`` stage (``[stages.surface]`` in project.toml).

    cell : DSM/ortho cell in metres (0 = the nadir GSD)
    aoi : ``[x0, y0, x1, y1]`` area of interest (empty = the ground the nadir images see, cut to the points)
    dsm_min_support, dsm_band, max_hole_m2 : DSM gridding and hole filling (:class:`.dsm.DsmConfig`; support 0 =
        from the point density)
    pit_size_m, pit_depth : enclosed pits narrower and deeper than these are removed from the DSM (0 size: kept)
    dsm_facade_nz : points whose normal lies within this of horizontal (``|n_z|`` below it: facade points) are
        left out of the DSM, whose cells hold the top of the surface (0 keeps them)
    dsm_roof_hole_sides : holes bounded by roofs on this many sides are roof (:class:`.dsm.DsmConfig`; 5: never)
    dsm_wall_step : a measured DSM cell more than this (metres) below one neighbour and above the opposite one lies
        on a wall: it is emptied and filled from its surroundings, roof or ground (:class:`.dsm.DsmConfig`; 0: off)
    dtm_cell, se_size, erosion_rank, threshold : DTM by robust morphological opening
    building_min_height, vegetation_min_height, greenness_min : object masks
    high_vegetation_m : vegetation points this high above the DTM are high vegetation (LAS class 5), lower ones
        medium (4)
    ortho_views : views used for the true orthophoto
    quality_vmax : top of the colour scale of the quality maps, metres (0 = the 98th percentile)
    """

    cell: float = 0.0
    aoi: tuple[float, ...] = ()
    dsm_min_support: int = 0
    dsm_band: float = 0.5
    max_hole_m2: float = 50.0
    pit_size_m: float = 3.2
    pit_depth: float = 2.0
    dsm_facade_nz: float = 0.3
    dsm_roof_hole_sides: int = 3
    dsm_wall_step: float = 1.0
    dtm_cell: float = 1.0
    se_size: float = 60.0
    erosion_rank: float = 0.03
    threshold: float = 1.5
    building_min_height: float = 2.5
    vegetation_min_height: float = 1.0
    greenness_min: float = 0.3
    high_vegetation_m: float = 2.0
    ortho_views: tuple[str, ...] = ("nadir",)
    quality_vmax: float = 0.0

    RULES: ClassVar[dict[str, Rule]] = {
        "cell": NON_NEGATIVE, "aoi": area_error, "dsm_min_support": NON_NEGATIVE, "dsm_band": POSITIVE,
        "max_hole_m2": NON_NEGATIVE, "pit_size_m": NON_NEGATIVE, "pit_depth": NON_NEGATIVE, "dsm_facade_nz": FRACTION,
        "dsm_roof_hole_sides": Range(1.0, 5.0), "dsm_wall_step": NON_NEGATIVE, "dtm_cell": POSITIVE,
        "se_size": POSITIVE, "erosion_rank": FRACTION, "threshold": POSITIVE, "building_min_height": NON_NEGATIVE,
        "vegetation_min_height": NON_NEGATIVE, "greenness_min": Range(-1.0, 1.0), "high_vegetation_m": NON_NEGATIVE,
        "ortho_views": VIEWS, "quality_vmax": NON_NEGATIVE}


def nadir_gsd(block, z_ground: float) -> float:
    """Median ground sampling distance of the nadir images at height ``z_ground`` (all images if none)."""
    by_view = block.images_by_view()
    ids = by_view.get("nadir") or [i for v in by_view.values() for i in v]
    g = [(block.images[i].pose.C[2] - z_ground) / block.camera_of(i).fx for i in ids]
    return float(np.median(g))


def run(ws, cfg: SurfaceConfig, ctx) -> StageResult:
    from ..dense.selection import area_of_interest

    path = ws.path("dense", "points.npz")
    if not path.exists():
        raise WorkspaceError(f"{path}: no dense points (run the 'dense' stage)")
    block = ws.load_block()
    with np.load(path) as z:
        kept = z["removed"] == 0
        xyz, rgb, normal = z["xyz"][kept], z["rgb"][kept], z["normal"][kept]
        view, master, masters = z["view"][kept], z["master"][kept], [str(m) for m in z["masters"]]
        err_used, err_approx = z["err_used"][kept], z["err_approx"][kept]
    if len(xyz) == 0:
        raise WorkspaceError(f"{path}: the dense point cloud is empty")
    z_ground = float(np.percentile(xyz[:, 2], 5))
    cell = cfg.cell if cfg.cell > 0 else nadir_gsd(block, z_ground)
    if len(cfg.aoi) == 4:
        aoi = tuple(float(v) for v in cfg.aoi)
    else:
        a = area_of_interest(block, z_ground)
        lo, hi = np.percentile(xyz[:, :2], [0.5, 99.5], axis=0)
        aoi = (max(a[0], lo[0]), max(a[1], lo[1]), min(a[2], hi[0]), min(a[3], hi[1]))
    grid = GridSpec.around(*aoi, cell)
    crs = block.crs
    steps = 6
    ctx.progress(0, steps, "DTM")
    dcfg = DtmConfig(cell=cfg.dtm_cell, se_size=cfg.se_size, erosion_rank=cfg.erosion_rank, threshold=cfg.threshold,
                     building_min_height=cfg.building_min_height, vegetation_min_height=cfg.vegetation_min_height,
                     greenness_min=cfg.greenness_min)
    dtm, classes, _ = make_dtm(xyz, grid, crs, dcfg)
    ctx.progress(1, steps, "DSM")
    # points below the opened ground surface are blunders (nothing is under the terrain): not in the DSM
    above_ground = classes != BELOW
    xyz_s, rgb_s = xyz[above_ground], rgb[above_ground]
    n_s = normal[above_ground]
    in_dsm = ~((np.abs(n_s[:, 2]) < cfg.dsm_facade_nz) & np.any(n_s != 0, axis=1))  # points without a normal stay
    dsm_cfg = DsmConfig(cell=cell, min_support=cfg.dsm_min_support, band=cfg.dsm_band, max_hole_m2=cfg.max_hole_m2,
                        pit_size_m=cfg.pit_size_m, pit_depth=cfg.pit_depth, roof_hole_sides=cfg.dsm_roof_hole_sides,
                        wall_step=cfg.dsm_wall_step)
    dsm, top_in = make_dsm(grid, xyz_s[in_dsm], crs, dsm_cfg)
    top = np.zeros(len(xyz_s), bool)
    top[in_dsm] = top_in
    ndsm = grid.raster((dsm.data - dtm.data).astype(np.float32), crs)
    ctx.progress(2, steps, "true orthophoto")
    by_view = block.images_by_view()
    ortho_ids = [i for v in cfg.ortho_views for i in by_view.get(v, [])]
    bits = camera_bits(block, {block.images[i].camera_id for i in ortho_ids})
    sources = [OrthoSource(i, block.camera_of(i), block.images[i].pose,
                           read_photo(resolve_image(block, block.images[i].file), True, i,
                                      bits.get(block.images[i].camera_id)))
               for i in ortho_ids]
    ortho, label = true_ortho(dsm, sources, OrthoConfig(),
                              progress=lambda d, t, m: ctx.progress(2 + d / t, steps, m)) if sources else (None, None)
    ctx.progress(4, steps, "masks and quality maps")
    colours = cell_colours(grid, xyz_s, rgb_s, top)
    if ortho is not None:
        seen = ortho.data[..., 3] > 0
        colours[seen] = ortho.data[seen, :3]
    bld, veg = object_masks(ndsm.data, colours, cell, dcfg)
    q_used = mean_per_cell(grid, xyz, err_used)
    q_approx = mean_per_cell(grid, xyz, err_approx)
    out = ws.stage_dir("surface")
    outputs = []

    def tif(name: str, data: np.ndarray, nodata: float | None = None) -> None:
        write_geotiff(out / name, grid.raster(data, crs, nodata))
        outputs.append(f"surface/{name}")

    tif("dsm.tif", dsm.data)
    tif("dtm.tif", dtm.data)
    tif("ndsm.tif", ndsm.data)
    tif("buildings.tif", bld.astype(np.uint8))
    tif("vegetation.tif", veg.astype(np.uint8))
    tif("quality_adjusted.tif", q_used.astype(np.float32))
    tif("quality_approx.tif", q_approx.astype(np.float32))
    if ortho is not None:
        tif("ortho.tif", ortho.data)
        tif("ortho_source.tif", label, nodata=-1)
        write_png(out / "ortho.png", ortho.data[..., :3])
        outputs.append("surface/ortho.png")
    vmax = cfg.quality_vmax
    if vmax <= 0:
        finite = np.concatenate([q_used[np.isfinite(q_used)], q_approx[np.isfinite(q_approx)]])
        vmax = float(np.percentile(finite, 98)) if len(finite) else 1.0
    for name, q in (("quality_adjusted.png", q_used), ("quality_approx.png", q_approx)):
        write_png(out / name, colour_map(q, vmax))
        outputs.append(f"surface/{name}")
    np.save(out / "point_classes.npy", classes)
    outputs.append("surface/point_classes.npy")
    las = las_classes(classes, xyz, normal, grid, bld, veg, dtm.data, facade_nz=cfg.dsm_facade_nz,
                      high_vegetation_m=cfg.high_vegetation_m)
    classified = PointCloud(xyz, rgb, normal, view, master, masters, crs, las)
    write_las(out / "points_classified.laz", classified)
    write_las(out / "points_classified_display.laz", display_subset(classified, DISPLAY_POINTS))
    outputs += ["surface/points_classified.laz", "surface/points_classified_display.laz"]
    ctx.progress(steps, steps, "written")

    def mean(a: np.ndarray) -> float | None:
        v = float(np.nanmean(a)) if np.isfinite(a).any() else math.nan
        return v if math.isfinite(v) else None

    metrics = {
        "cell": cell, "rows": grid.rows, "cols": grid.cols, "aoi": list(aoi),
        "dsm_filled_fraction": float(np.isfinite(dsm.data).mean()),
        "points_above": int((classes == ABOVE).sum()), "points_on": int((classes == ON).sum()),
        "points_below": int((classes == BELOW).sum()),
        "las_classes": {name: int((las == code).sum()) for name, code in LAS_CLASSES.items()},
        "building_area_m2": float(bld.sum() * cell ** 2), "vegetation_area_m2": float(veg.sum() * cell ** 2),
        "quality_adjusted_mean_m": mean(q_used), "quality_approx_mean_m": mean(q_approx),
        "quality_vmax_m": vmax,
    }
    return StageResult(tuple(outputs), metrics,
                       f"DSM {grid.cols}x{grid.rows} at {cell:.3f} m, {bld.sum() * cell ** 2:.0f} m2 of buildings")


STAGE = Stage(name="surface", run=run, config=SurfaceConfig, requires=("dense",),
              description="DSM, DTM by robust morphology, nDSM, masks, classified points, true orthophoto, "
                          "quality maps", version="13")

"""The ``dense`` stage: image selection, pair matching through the executor, fusion, filters, point cloud files.

Reads ``ws.load_block()`` (the adjusted block once aerial triangulation has run, else the imported one) and
writes into ``dense/``:

* ``points.npz``: every fused point with colour, normal, view, master, incidence angle, the forward
  intersection error with the matching orientation and with the approximate one, and why it was removed
  (0 kept, 1 mixed pixel, 2 isolated point) -- the input of the ``surface`` stage and the benchmarks;
* ``points.laz`` and ``points.ply``: the kept points (colour, normal, source view, master id);
* ``points_display.ply``: a random subsample for display (Blender);
* ``selection.json``: masters and slaves per view, with per-pair timings.
"""

from __future__ import annotations

import glob
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..errors import ComputationError, ConfigError
from ..geometry.views import VIEWS
from ..io.photos import camera_bits, read_photo
from ..io.pointcloud import PointCloud, display_subset, write_las, write_ply
from ..io.validate import resolve_image
from ..model.block import ImageBlock
from ..model.camera import CameraModel
from ..model.pose import Pose
from ..model.tiepoints import TiePoints
from ..pipeline.atomic import atomic_path, write_json
from ..pipeline.stage import (
    AT_LEAST_ONE,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    CheckedOptions,
    Range,
    Rule,
    Stage,
    StageResult,
    area_error,
    odd_error,
)
from .fusion import (
    FusionConfig,
    erode_far_edges,
    fuse_depths,
    intersection_errors,
    local_outliers,
    master_points,
    smooth_depth,
)
from .pairs import PairTask, match_pair
from .selection import SelectionConfig, select_pairs
from .sgm import MODES as SGM_MODES
from .sgm import SgmConfig

KEPT, MIXED, OUTLIER = 0, 1, 2


@dataclass(frozen=True)
class DenseConfig(CheckedOptions):
    """Options of the ``dense`` stage (``[stages.dense]`` in project.toml).

    aoi : ``[x0, y0, x1, y1]`` area the masters must cover (empty = the ground below the nadir image centres)
    z_min, z_max : height prior (world Z) for the disparity range; NaN = from tie points or ground points
    max_object_height : height above the ground prior allowed for objects when only ground points are known
    step : points are made on every ``step``-th pixel of nadir masters
    oblique_step : the same for oblique masters (their points serve the facades; roofs and ground come from nadir)
    scale : rectified image scale (1 = full resolution)
    views : views to reconstruct
    master_overlap, slaves_per_master : image selection
    block_size, sgm_mode, p1, p2, uniqueness, lr_max_diff : SGM settings (:class:`.sgm.SgmConfig`)
    min_agree, tol_px : multi-slave consistency
    bilateral, bilateral_sigma_m : depth smoothing
    max_incidence_deg : mixed-pixel filter (90 disables it)
    edge_radius_px : far-side erosion at depth edges, image pixels (0 disables it)
    near_edge_radius_px : near-side erosion at depth edges (the foreground fattened by the matching window),
        image pixels (0 disables it)
    polar_below_deg : pairs whose baseline lies within this angle of the viewing direction are rectified in
        log-polar form (0: all planar; see :mod:`.polar`)
    outlier_neighbours, outlier_ratio : isolated points removed by their local density ratio
        (:func:`.fusion.local_outliers`; 0 neighbours disables it)
    display_points : size of the display subsample
    """

    aoi: tuple[float, ...] = ()
    z_min: float = math.nan
    z_max: float = math.nan
    max_object_height: float = 80.0
    step: int = 1
    oblique_step: int = 2
    scale: float = 1.0
    views: tuple[str, ...] = ("nadir", "north", "east", "south", "west")
    master_overlap: float = 0.35
    slaves_per_master: int = 4
    block_size: int = 5
    sgm_mode: str = "sgbm_3way"
    p1: int = 8
    p2: int = 32
    uniqueness: int = 10
    lr_max_diff: float = 1.0
    min_agree: int = 2
    tol_px: float = 1.0
    bilateral: bool = True
    bilateral_sigma_m: float = 0.3
    max_incidence_deg: float = 82.0
    edge_radius_px: float = 2.0
    near_edge_radius_px: float = 2.0
    outlier_neighbours: int = 16
    outlier_ratio: float = 2.0
    display_points: int = 300_000
    polar_below_deg: float = 60.0

    RULES: ClassVar[dict[str, Rule]] = {
        "aoi": area_error, "z_min": Range(nan=True), "z_max": Range(nan=True), "max_object_height": POSITIVE,
        "step": AT_LEAST_ONE, "oblique_step": AT_LEAST_ONE, "scale": Range(0.0, 1.0, lo_open=True), "views": VIEWS,
        "master_overlap": FRACTION, "slaves_per_master": AT_LEAST_ONE, "block_size": odd_error,
        "sgm_mode": tuple(SGM_MODES), "p1": NON_NEGATIVE, "p2": NON_NEGATIVE, "uniqueness": Range(0.0, 100.0),
        "lr_max_diff": NON_NEGATIVE, "min_agree": AT_LEAST_ONE, "tol_px": POSITIVE, "bilateral_sigma_m": POSITIVE,
        "max_incidence_deg": Range(0.0, 90.0), "edge_radius_px": NON_NEGATIVE, "near_edge_radius_px": NON_NEGATIVE,
        "outlier_neighbours": NON_NEGATIVE, "outlier_ratio": Range(1.0), "display_points": AT_LEAST_ONE,
        "polar_below_deg": Range(0.0, 90.0)}
    ORDERED: ClassVar[tuple[tuple[str, str, bool], ...]] = (("p1", "p2", True), ("z_min", "z_max", True))


def master_step(cfg: DenseConfig, view: str) -> int:
    return cfg.step if view == "nadir" else cfg.oblique_step


def height_prior(ws, block: ImageBlock, cfg: DenseConfig) -> tuple[float, float, float]:
    """``(z_min, z_max, z_ground)``: the height interval searched by matching and a typical ground height, from
    the config, else the tie points of matching/aerotri (their 0.5th percentile minus 10 m up to their 99.5th
    percentile plus twice its height above the ground), else the ground points."""
    if math.isfinite(cfg.z_min) and math.isfinite(cfg.z_max):
        return cfg.z_min, cfg.z_max, cfg.z_min
    for path in sorted(glob.glob(str(ws.path("aerotri", "*.npz"))) + glob.glob(str(ws.path("matching", "*.npz")))):
        try:
            tp = TiePoints.load(path)
        except (KeyError, ValueError, OSError):
            continue
        z = tp.xyz[:, 2]
        z = z[np.isfinite(z)]
        if len(z) > 20:
            lo, hi, ground = np.percentile(z, [0.5, 99.5, 10.0])
            # few tie points lie on the tallest objects (a tower top is a few square metres): room above the
            # 99.5th percentile for objects three times as tall above the ground (coarse-to-fine matching narrows
            # the search of each pair again)
            return float(lo - 10.0), float(hi + max(10.0, 2.0 * (hi - ground))), float(ground)
    zs = [p.xyz[2] for p in block.ground_points.values() if p.xyz is not None]
    if zs:
        return float(min(zs) - 10.0), float(max(zs) + cfg.max_object_height), float(np.median(zs))
    raise ConfigError("dense: no height prior (no tie points, no ground points): set [stages.dense] z_min and z_max")


@dataclass(frozen=True)
class FuseTask:
    """One master's fusion (:func:`fuse_master`): its camera, orientation, image file and grid step, its view and
    index (stored with its points), the depth maps ``(k, h, w)`` and ``f B`` ``(k,)`` of its ``k`` pairs, the
    slaves' orientations, optionally the approximate orientations of master and slaves (their quality map), its
    camera's significant bits (:func:`..io.photos.camera_bits`)."""

    camera: CameraModel
    pose: Pose
    image_path: str
    step: int
    view_index: int
    master_index: int
    depths: np.ndarray
    focal_baselines: np.ndarray
    slave_poses: tuple[Pose, ...]
    approx: tuple[Pose, tuple[Pose, ...]] | None
    fusion: FusionConfig
    min_bits: int | None = None


def fuse_master(task: FuseTask) -> dict[str, np.ndarray]:
    """Executor unit: fuse one master's depth maps, smooth, make its points with colour, normal, incidence and
    mixed-pixel flag, and the forward intersection error of each point under the orientations used (and the
    approximate ones when given; else the same values). Returns arrays by name, ``(n, ...)`` per point."""
    fcfg = task.fusion
    fused, agree = fuse_depths(task.depths, task.focal_baselines, fcfg)
    fused = erode_far_edges(fused, task.step, fcfg)
    valid_before = np.isfinite(fused)
    depth = smooth_depth(fused, fcfg)
    photo = read_photo(task.image_path, True, None, task.min_bits)
    pts = master_points(task.camera, task.pose, depth, task.step, photo, fcfg)
    slave_depths = [np.where(a, d, np.nan)[valid_before] for d, a in zip(task.depths, agree)]
    evaluations = [(task.pose, list(task.slave_poses))]
    if task.approx is not None:
        evaluations.append((task.approx[0], list(task.approx[1])))
    errors = intersection_errors(pts.uv_px, task.camera, task.pose, list(zip(task.slave_poses, slave_depths)),
                                 evaluations)
    n = len(pts.xyz)
    return {"xyz": pts.xyz, "rgb": pts.rgb, "normal": pts.normal,
            "view": np.full(n, task.view_index, np.uint8), "master": np.full(n, task.master_index, np.uint16),
            "incidence": pts.incidence, "mixed": pts.mixed, "err_used": errors[0].astype(np.float32),
            "err_approx": errors[-1].astype(np.float32)}


def run(ws, cfg: DenseConfig, ctx) -> StageResult:
    block = ws.load_block()
    z_min, z_max, z_ground = height_prior(ws, block, cfg)
    aoi = tuple(float(v) for v in cfg.aoi) if len(cfg.aoi) == 4 else None
    selection = select_pairs(block, z_ground, aoi, cfg=SelectionConfig(master_overlap=cfg.master_overlap,
                                                               slaves_per_master=cfg.slaves_per_master,
                                                               views=tuple(cfg.views)))
    selection = [s for s in selection if len(s.slaves) >= cfg.min_agree]
    if not selection:
        raise ComputationError("dense: no master has enough slaves (check the overlap and the views)")
    sgm = SgmConfig(block_size=cfg.block_size, p1=cfg.p1, p2=cfg.p2, uniqueness=cfg.uniqueness, mode=cfg.sgm_mode,
                    lr_max_diff=cfg.lr_max_diff)
    executor = ctx.get_executor()
    threads = 1 if getattr(executor, "mode", "inline") != "inline" else 0  # one OpenCV thread per process
    tasks = []
    bits = camera_bits(block)
    for sel in selection:
        m = block.images[sel.master]
        for sid in sel.slaves:
            s = block.images[sid]
            tasks.append(PairTask(m.id, s.id, block.camera_of(m), m.pose, block.camera_of(s), s.pose,
                                  str(resolve_image(block, m.file)), str(resolve_image(block, s.file)),
                                  z_min, z_max, master_step(cfg, sel.view), cfg.scale, sgm, threads=threads,
                                  polar_below_deg=cfg.polar_below_deg, bits_master=bits.get(m.camera_id),
                                  bits_slave=bits.get(s.camera_id)))
    total = len(tasks) + len(selection)
    results = executor.map(match_pair, tasks,
                                     on_done=lambda d, t: ctx.progress(d, total, f"matched {d}/{t} pairs"))
    by_master: dict[str, list] = {}
    for r in results:
        by_master.setdefault(r.master, []).append(r)

    fcfg = FusionConfig(min_agree=cfg.min_agree, tol_px=cfg.tol_px, bilateral=cfg.bilateral,
                        bilateral_sigma_m=cfg.bilateral_sigma_m, max_incidence_deg=cfg.max_incidence_deg,
                        edge_radius_px=cfg.edge_radius_px, near_edge_radius_px=cfg.near_edge_radius_px)
    masters = [s.master for s in selection]
    adjusted = any(img.pose_adjusted is not None for img in block.images.values())
    fuse_tasks = []
    for mi, sel in enumerate(selection):
        img = block.images[sel.master]
        res = by_master[sel.master]
        slaves = [block.images[r.slave] for r in res]
        approx = (adjusted and img.pose_approx is not None and all(s.pose_approx is not None for s in slaves))
        fuse_tasks.append(FuseTask(
            block.camera_of(img), img.pose, str(resolve_image(block, img.file)), master_step(cfg, sel.view),
            VIEWS.index(sel.view), mi, np.stack([r.depth for r in res]), np.array([r.focal_baseline for r in res]),
            tuple(s.pose for s in slaves),
            (img.pose_approx, tuple(s.pose_approx for s in slaves)) if approx else None, fcfg, bits.get(img.camera_id)))
    done_pairs = len(tasks)
    fused = executor.map(fuse_master, fuse_tasks, on_done=lambda d, t: ctx.progress(
        done_pairs + d, total, f"fused {d}/{t} masters"))
    del fuse_tasks
    arr = {k: np.concatenate([f[k] for f in fused]) for k in fused[0]}
    del fused
    removed = np.where(arr.pop("mixed"), MIXED, KEPT).astype(np.uint8)
    if cfg.outlier_neighbours > 0:
        cand = np.flatnonzero(removed == KEPT)
        out = local_outliers(arr["xyz"][cand], cfg.outlier_neighbours, cfg.outlier_ratio)
        removed[cand[out]] = OUTLIER
    return _write(ws, block, cfg, selection, results, masters, arr, removed, adjusted)


def _write(ws, block, cfg, selection, results, masters, arr, removed, adjusted) -> StageResult:
    out_dir = ws.stage_dir("dense")
    with atomic_path(out_dir / "points.npz") as tmp, open(tmp, "wb") as f:
        np.savez(f, removed=removed, masters=np.array(masters), **arr)
    kept = removed == KEPT
    cloud = PointCloud(arr["xyz"][kept], arr["rgb"][kept], arr["normal"][kept], arr["view"][kept],
                       arr["master"][kept], masters, block.crs)
    write_las(out_dir / "points.laz", cloud)
    write_ply(out_dir / "points.ply", cloud)
    write_ply(out_dir / "points_display.ply", display_subset(cloud, cfg.display_points))
    secs = sum(r.seconds for r in results)
    mpx = sum(r.megapixels for r in results)
    write_json(out_dir / "selection.json", {
        "masters": [{"master": s.master, "view": s.view, "slaves": list(s.slaves)} for s in selection],
        "pairs": [{"master": r.master, "slave": r.slave, "seconds": r.seconds, "megapixels": r.megapixels,
                   "disparities": r.disparities, "valid": float(np.isfinite(r.depth).mean())} for r in results]})
    metrics = {
        "masters": len(selection), "pairs": len(results), "points": int(kept.sum()),
        "points_fused": int(len(removed)), "removed_mixed": int((removed == MIXED).sum()),
        "removed_outliers": int((removed == OUTLIER).sum()),
        "matching_mpx_per_s_per_pair": mpx / secs if secs > 0 else None,
        "intersection_error_m": float(np.nanmean(arr["err_used"][kept])) if kept.any() else None,
        "intersection_error_approx_m": float(np.nanmean(arr["err_approx"][kept])) if adjusted and kept.any()
        else None,
        "points_per_view": {v: int((arr["view"][kept] == i).sum()) for i, v in enumerate(VIEWS)},
    }
    outputs = ("dense/points.npz", "dense/points.laz", "dense/points.ply", "dense/points_display.ply",
               "dense/selection.json")
    return StageResult(outputs, metrics, f"{kept.sum()} points from {len(selection)} masters, {len(results)} pairs")


STAGE = Stage(name="dense", run=run, config=DenseConfig, requires=("block",),
              description="dense matching: image selection, SGM, multi-slave fusion, filtered point cloud",
              version="7")

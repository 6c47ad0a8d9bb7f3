"""The ``buildings`` stage: LOD2 buildings with discontinuities, roof overhangs and dormers.

Reads ``dense/points.npz`` (the kept dense points) and ``surface/dsm.tif``, ``dtm.tif``, ``buildings.tif`` and
``vegetation.tif``; detects the buildings (or takes user footprints from a GeoJSON file), reconstructs each one
through the executor (in-process, processes or Dask) and writes ``buildings/buildings.json`` (the models, see
:mod:`.model`) and ``buildings/report.json`` (per building: path, reason, closed solid, mean miss of its roof points,
timings, dormers and the candidates not taken with why; failures with their reason).
"""

from __future__ import annotations

import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import WorkspaceError
from ..model.raster import Raster
from ..pipeline.atomic import write_json
from ..pipeline.stage import NON_NEGATIVE, POSITIVE, CheckedOptions, Rule, Stage, StageResult
from .detect import DetectConfig, building_labels, points_per_building, points_per_footprint, read_footprints
from .dormers import DormerConfig
from .model import BuildingModel, save_buildings
from .overhang import OverhangConfig
from .reconstruct import ReconstructionConfig, reconstruct_building


@dataclass(frozen=True)
class BuildingsConfig(CheckedOptions):
    """Options of the ``buildings`` stage (``[stages.buildings]`` in project.toml).

    min_height, min_area : detection on the nDSM (m, m^2); use_masks : use the surface stage's building and
    vegetation masks (else roughness rejects vegetation); footprints : GeoJSON file of user footprints (empty:
    detect); voxel : noise filter cube (m, 0 = guessed); force_path : '' (automatic), '2d' or 'volumetric';
    max_overhang, overhang_thickness : overhang search range and slab thickness (m); dormers : model dormers
    on the sloped roofs (:mod:`.dormers`); dormer_min_rise : height above its slope that marks a dormer (m);
    max_roof_fit : models that miss their roof points by more than this on average are refused as no building
    (m, 0 = keep all; :class:`.reconstruct.ReconstructionConfig`)
    """

    min_height: float = 2.5
    min_area: float = 25.0
    use_masks: bool = True
    footprints: str = ""
    voxel: float = 0.0
    force_path: str = ""
    max_overhang: float = 1.5
    overhang_thickness: float = 0.2
    dormers: bool = True
    dormer_min_rise: float = 0.4
    max_roof_fit: float = 0.5

    RULES: ClassVar[dict[str, Rule]] = {
        "min_height": NON_NEGATIVE, "min_area": POSITIVE, "voxel": NON_NEGATIVE, "force_path": ("", "2d", "volumetric"),
        "max_overhang": NON_NEGATIVE, "overhang_thickness": POSITIVE, "dormer_min_rise": POSITIVE,
        "max_roof_fit": NON_NEGATIVE}


def _window(r: Raster, xy: np.ndarray, margin: float) -> Raster:
    """The part of a raster around points (n, 2), ``margin`` metres wide."""
    lo, hi = xy.min(0) - margin, xy.max(0) + margin
    c0 = max(int(np.floor((lo[0] - r.x0) / r.cell)), 0)
    c1 = min(int(np.ceil((hi[0] - r.x0) / r.cell)), r.shape[1])
    r0 = max(int(np.floor((r.y0 - hi[1]) / r.cell)), 0)
    r1 = min(int(np.ceil((r.y0 - lo[1]) / r.cell)), r.shape[0])
    return Raster(np.asarray(r.data[r0:r1, c0:c1]), r.x0 + c0 * r.cell, r.y0 - r0 * r.cell, r.cell, r.crs)


def reconstruct_unit(unit: tuple) -> tuple[str, dict | None, str]:
    """Executor unit: ``(id, xyz, ground_z, dsm window, config, dtm window)`` -> (id, model dict or None, error)."""
    bid, xyz, ground_z, dsm, cfg, dtm = unit
    try:
        return bid, reconstruct_building(xyz, ground_z, dsm, bid, cfg, dtm).to_dict(), ""
    except ValueError as e:  # a step could not do its job on this building: the message says which
        return bid, None, str(e)
    except (ArithmeticError, IndexError, np.linalg.LinAlgError) as e:
        # one degenerate building must not stop the city: reported with the failing line, never hidden
        tb = traceback.extract_tb(e.__traceback__)[-1]
        return bid, None, f"{type(e).__name__} at {Path(tb.filename).name}:{tb.lineno}: {e}"


def run(ws, cfg: BuildingsConfig, ctx) -> StageResult:
    from ..io.geotiff import read_geotiff

    pts_path = ws.path("dense", "points.npz")
    if not pts_path.exists():
        raise WorkspaceError(f"{pts_path}: no dense points (run the 'dense' stage)")
    for name in ("dsm.tif", "dtm.tif"):
        if not ws.path("surface", name).exists():
            raise WorkspaceError(f"{ws.path('surface', name)}: missing (run the 'surface' stage)")
    with np.load(pts_path) as z:
        xyz = z["xyz"][z["removed"] == 0].astype(np.float64)
    dsm = read_geotiff(ws.path("surface", "dsm.tif"))
    dtm = read_geotiff(ws.path("surface", "dtm.tif"))
    bmask = vmask = None
    if cfg.use_masks:
        if ws.path("surface", "buildings.tif").exists():
            bmask = read_geotiff(ws.path("surface", "buildings.tif")).data > 0
        if ws.path("surface", "vegetation.tif").exists():
            vmask = read_geotiff(ws.path("surface", "vegetation.tif")).data > 0
    dcfg = DetectConfig(min_height=cfg.min_height, min_area=cfg.min_area)
    ctx.progress(0, 1, "detecting buildings")
    if cfg.footprints:
        dets = points_per_footprint(xyz, read_footprints(ws.path(cfg.footprints)), dtm, dcfg)
        stats = {"footprints": len(dets)}
    else:
        labels, n, stats = building_labels(dsm, dtm, dcfg, bmask, vmask)
        dets = points_per_building(xyz, labels, dsm, dtm, dcfg)
    rcfg = ReconstructionConfig(voxel=cfg.voxel, force_path=cfg.force_path, max_roof_fit=cfg.max_roof_fit,
                                overhang=OverhangConfig(max_width=cfg.max_overhang, thickness=cfg.overhang_thickness),
                                dormers=DormerConfig(enabled=cfg.dormers, min_rise=cfg.dormer_min_rise))
    units = [(f"B{d.label:04d}", xyz[d.indices], d.ground_z, _window(dsm, xyz[d.indices, :2], 5.0), rcfg,
              _window(dtm, xyz[d.indices, :2], 5.0)) for d in dets if len(d.indices) >= 50]
    skipped = [{"id": f"B{d.label:04d}", "reason": f"only {len(d.indices)} points"} for d in dets
               if len(d.indices) < 50]
    results = ctx.get_executor().map(reconstruct_unit, units,
                                     on_done=lambda k, t: ctx.progress(k, t, f"building {k}/{t}"))
    models = [BuildingModel.from_dict(m) for _, m, _ in results if m is not None]
    failures = skipped + [{"id": bid, "reason": err} for bid, m, err in results if m is None]
    out = ws.stage_dir("buildings")
    save_buildings(out / "buildings.json", models, ws.crs)
    report = {
        "detection": stats,
        "buildings": [{"id": m.id, "path": m.path, "reason": m.reason, "closed": m.info.get("closed"),
                       "solid_problem": m.info.get("solid_problem"), "roof_fit": m.info.get("roof_fit"),
                       "seconds": m.info.get("seconds"),
                       "corners": len(m.footprint), "roof_planes": len(m.roof_planes),
                       "overhangs": m.overhangs.tolist(), "dormers": m.info.get("dormers", []),
                       "dormer_candidates_rejected": m.info.get("dormer_candidates_rejected", [])} for m in models],
        "failures": failures,
    }
    write_json(out / "report.json", report)
    closed = sum(bool(m.info.get("closed")) for m in models)
    metrics = {"buildings": len(models), "closed": closed, "failures": len(failures),
               "dormers": sum(len(m.info.get("dormers", [])) for m in models),
               "path_2d": sum(m.path == "2d" for m in models),
               "path_volumetric": sum(m.path == "volumetric" for m in models)}
    return StageResult(("buildings/buildings.json", "buildings/report.json"), metrics,
                       f"{len(models)} buildings ({closed} closed solids), {len(failures)} failed")


STAGE = Stage(name="buildings", run=run, config=BuildingsConfig, requires=("surface",),
              description="LOD2 buildings with discontinuities, roof overhangs and dormers", version="43")

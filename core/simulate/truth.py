"""Ground-truth products of a simulated block and :func:`load_truth` for the other stages' tests and benchmarks.

Layout of ``<block>/truth/``::

    block_true.json     native block: true interior and exterior orientation (pose_approx = true pose), true rig
    city/               the city: city.npz (mesh arrays, semantics, building ids, materials, uv), city.json, city.ply
    dsm.tif dtm.tif     GT rasters (float32, metres): first surface seen from above; the known terrain
    classes.tif         uint8 semantic code of the DSM's surface (codes of ``city.SEMANTIC``)
    buildings.tif       int32 building id of the DSM's surface (-1: none)
    footprints.json     per building: wall footprint rings (world), parts, eave/ridge heights, overhang edges
    roof_planes.json    per building: roof planes (normal, d, polygon with overhang, slope, kind)
    windows.json        every window's 3-D rectangle (facade plane), recess depth and normal
    targets.json        true centres of the signalised targets (the ground points' true coordinates)
    depth/<image>.npz   z-depth maps (float32, metres, inf = sky) when requested
    simulation.json     the configuration and figures of the simulation run
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import native
from ..io.geotiff import read_geotiff, write_geotiff
from ..model import ImageBlock, Raster
from ..pipeline.atomic import atomic_path, write_json
from .city import City


def gt_surface(city: City, bbox: np.ndarray, cell: float) -> tuple[Raster, Raster, Raster]:
    """Cast one vertical ray per cell centre from above: DSM (float32 z), semantic class (uint8) and building id
    (int32) of the first surface; ``bbox = (xmin, ymin, xmax, ymax)`` world, north-up grid of ``cell`` metres."""
    import open3d as o3d

    xmin, ymin, xmax, ymax = (float(v) for v in bbox)
    cols, rows = max(1, round((xmax - xmin) / cell)), max(1, round((ymax - ymin) / cell))
    tmpl = Raster(np.zeros((rows, cols)), xmin, ymax, cell, city.crs)
    xs, ys = tmpl.cell_centers()
    gx, gy = np.meshgrid(xs - city.origin[0], ys - city.origin[1])
    top = float(city.vertices[:, 2].max()) + 10.0
    rays = np.zeros((gx.size, 6), np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 5] = gx.ravel(), gy.ravel(), top, -1.0
    r = city.scene().cast_rays(o3d.core.Tensor(rays))
    t, ids = r["t_hit"].numpy(), r["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t)
    z = np.full(gx.size, np.nan, np.float32)
    z[hit] = top - t[hit]
    cls = np.full(gx.size, 255, np.uint8)
    cls[hit] = city.semantic[ids[hit]]
    bid = np.full(gx.size, -1, np.int32)
    bid[hit] = city.building[ids[hit]]
    mk = lambda a, nodata: Raster(a.reshape(rows, cols), xmin, ymax, cell, city.crs, nodata)  # noqa: E731
    return mk(z, None), mk(cls, 255), mk(bid, -1)


def gt_dtm(city: City, bbox: np.ndarray, cell: float) -> Raster:
    """The known terrain at cell centres (float32 metres), same grid as :func:`gt_surface`."""
    xmin, ymin, xmax, ymax = (float(v) for v in bbox)
    cols, rows = max(1, round((xmax - xmin) / cell)), max(1, round((ymax - ymin) / cell))
    r = Raster(np.zeros((rows, cols), np.float32), xmin, ymax, cell, city.crs)
    xs, ys = r.cell_centers()
    gx, gy = np.meshgrid(xs, ys)
    r.data = city.terrain_z(np.column_stack([gx.ravel(), gy.ravel()])).reshape(rows, cols).astype(np.float32)
    return r


def write_truth(folder: str | Path, city: City, true_block: ImageBlock, bbox: np.ndarray, cell: float,
                config: dict) -> None:
    """Write the ground truth folder (see the module docstring), except depth maps (written while rendering)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    native.write_block(true_block, folder / "block_true.json")
    city.save(folder / "city")
    dsm, cls, bid = gt_surface(city, bbox, cell)
    write_geotiff(folder / "dsm.tif", dsm)
    write_geotiff(folder / "classes.tif", cls)
    write_geotiff(folder / "buildings.tif", bid)
    write_geotiff(folder / "dtm.tif", gt_dtm(city, bbox, cell))
    write_json(folder / "footprints.json", {"crs": city.crs, "buildings": [
        {"id": b.id, "name": b.name, "footprint": [r.tolist() for r in b.footprint], "ground_z": b.ground_z,
         "rotation_deg": b.rotation, "parts": b.eave_ridge(), "overhang_edges": b.overhang_edges()}
        for b in city.buildings]})
    write_json(folder / "roof_planes.json", {"crs": city.crs, "buildings": [
        {"id": b.id, "planes": [{**p, "normal": np.asarray(p["normal"]).tolist(), "polygon": p["polygon"].tolist()}
                                for p in b.roof_planes]} for b in city.buildings]})
    write_json(folder / "windows.json", {"crs": city.crs, "windows": [
        {**w, "corners": w["corners"].tolist(), "normal": w["normal"].tolist()} for w in city.all_windows()]})
    write_json(folder / "targets.json", {"crs": city.crs, "radius": city.TARGET_RADIUS, "square_half": city.TARGET_HALF,
                                         "pattern": city.target_pattern, "bar_half": city.TARGET_BAR,
                                         "targets": {n: xyz.tolist() for n, xyz in zip(city.target_names, city.targets,
                                                                                        strict=True)}})
    write_json(folder / "simulation.json", config)


def write_depth(folder: str | Path, image_id: str, depth: np.ndarray) -> None:
    """Save one z-depth map as ``depth/<image_id>.npz`` (float32, inf where the ray sees the sky)."""
    path = Path(folder) / "depth" / f"{image_id}.npz"
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, depth=depth.astype(np.float32))


@dataclass(eq=False)
class Truth:
    """Ground truth of a simulated block, as loaded by :func:`load_truth`.

    block : true orientations (``pose_approx`` holds the true pose); city : mesh with semantics and per-building
    truth; dsm, dtm, classes, buildings : GT rasters; windows, roof_planes, footprints, targets : the JSON files
    as dicts; config : the simulation settings; folder : the truth folder.
    """

    folder: Path
    block: ImageBlock
    city: City
    dsm: Raster
    dtm: Raster
    classes: Raster
    buildings: Raster
    footprints: dict
    roof_planes: dict
    windows: dict
    targets: dict
    config: dict

    def depth(self, image_id: str) -> np.ndarray:
        """The z-depth map of one image (written with ``depth=True``)."""
        path = self.folder / "depth" / f"{image_id}.npz"
        if not path.exists():
            raise InputError("no depth map for this image (simulate with depth maps on)", path=path)
        return np.load(path)["depth"]


def load_truth(path: str | Path) -> Truth:
    """Load ``<block>/truth`` (``path`` may be the block folder or its ``truth`` folder)."""
    folder = Path(path)
    if (folder / "truth").is_dir():
        folder = folder / "truth"
    if not (folder / "block_true.json").exists():
        raise InputError("not a simulated block's truth folder (block_true.json missing)", path=folder)

    def js(name: str) -> dict:
        with open(folder / name, encoding="utf-8") as f:
            return json.load(f)

    return Truth(folder=folder, block=native.read_block(folder / "block_true.json"), city=City.load(folder / "city"),
                 dsm=read_geotiff(folder / "dsm.tif"), dtm=read_geotiff(folder / "dtm.tif"),
                 classes=read_geotiff(folder / "classes.tif"), buildings=read_geotiff(folder / "buildings.tif"),
                 footprints=js("footprints.json"), roof_planes=js("roof_planes.json"), windows=js("windows.json"),
                 targets=js("targets.json"), config=js("simulation.json"))

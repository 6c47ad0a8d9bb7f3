"""Simulate a complete oblique block over the synthetic city: plan, render, write block + ground truth.

Output folder::

    images/<exposure>_<head>.jpg     rendered images (true orientation, Brown distortion, radiometry, noise)
    block.xml                        BlocksExchange XML: cameras, approximate poses (GNSS/IMU), control points
                                     (written last: its presence marks a complete simulation)
    block.json                       the same block in the native format, with rig, exposures and prior sigmas
    events.txt, events_cameras.toml  the navigation solution per exposure (GNSS/IMU event list, headings against
                                     true north) and the cameras with the heads' nominal mounting
    gcp.csv, gcp_measurements.csv    ground points (surveyed) and their image measurements (pixel centre origin)
    preview/city_overview.png        an oblique overview of the city; preview/head_<head>.png one image per head
    truth/                           ground truth (see :mod:`.truth`)

The default (``SimulationConfig()``): penta camera 1400 x 1050 px, nadir GSD 0.155 m (flying height ~200 m), one
east-west strip and one north-south cross strip, 67 % forward / 60 % side overlap, each strip extended by 1.1 x the
flying height beyond the area: 125 images. The extension is what the 45-degree heads need: a head looking east
sees the ground from ~0.4 to ~2.4 flying heights ahead, so the strips must start well before the area for the
forward heads to see its western facades (and end as far beyond it for the backward heads), and dense matching
fuses a facade point only where the master and two slaves of the same view see it. Measured on the wall
triangles of the default city's core (ray cast, incidence < 70 deg), the share seen by >= 3 images of the view
facing them, north / south / east / west facades: 0.66 / 0.65 / 0.63 / 0.60 at 1.1 flying heights (125 images),
0.38 / 0.23 / 0.51 / 0.48 at 0.85 (105 images), 0.68 / 0.66 / 0.64 / 0.61 at 1.3 (145 images); seen by >= 2
images: 0.61-0.70 in all three (the rest is hidden by neighbours, trees and overhangs). At 0.85 the masters of
the outer facades had a single slave, and their points were not fused. Nadir sees every roof 15 times on
average.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import ConfigError
from ..geometry.views import cardinal_view
from ..io import native
from ..io.formats import write_block
from ..io.gcp import write_ground_points, write_measurements
from ..io.photos import read_photo
from ..model import CameraModel, Pose
from ..pipeline.atomic import atomic_path
from ..pipeline.stage import AT_LEAST_ONE, NON_NEGATIVE, POSITIVE, CheckedOptions, Range, Rule
from .cameras import CameraSystem, penta, preset, three_head
from .city import City, make_city
from .flight import (
    FlightConfig,
    NavErrors,
    approximate_block,
    coverage_map,
    flying_height,
    ground_points,
    perturbed_rig,
    plan_flight,
    true_block,
)
from .render import RenderConfig, Renderer
from .truth import write_depth, write_truth


@dataclass(frozen=True)
class SimulationConfig(CheckedOptions):
    """Everything that defines a simulated block (all deterministic from the seeds).

    system : ``penta`` or ``three-head`` (or use :func:`simulate` with a custom CameraSystem)
    width, height : image size of every head in pixels (the presets keep their real fields of view)
    seed : city, flight jitter, navigation errors, noise
    gsd : nadir GSD in metres; flight : overlaps, direction, cross strips, extensions (as fractions of the flying
    height in ``extend_along_h`` / ``extend_across_h``)
    depth_maps : also write per-image depth maps to truth/depth; truth_cell : GT raster cell (m)
    workers : rendering processes; image_format : jpg, png or tif12 (16-bit TIFF with 12 significant bits, as
    aerial cameras deliver them)
    target_pattern : the signalised targets, ``disc`` (a white disc on a black square) or ``cross`` (white bars)
    """

    system: str = "penta"
    width: int = 1400
    height: int = 1050
    seed: int = 0
    gsd: float = 0.155
    forward_overlap: float = 0.67
    side_overlap: float = 0.6
    direction_deg: float = 90.0
    cross_strips: bool = True
    extend_along_h: float = 1.1
    extend_across_h: float = 0.0
    area_inset: float = 20.0
    depth_maps: bool = False
    truth_cell: float = 0.25
    workers: int = 2
    image_format: str = "jpg"
    jpeg_quality: int = 93
    target_pattern: str = "disc"
    nav: NavErrors = field(default_factory=NavErrors)
    render: RenderConfig = field(default_factory=RenderConfig)

    RULES: ClassVar[dict[str, Rule]] = {
        "width": Range(16.0), "height": Range(16.0), "seed": NON_NEGATIVE, "gsd": POSITIVE,
        "forward_overlap": Range(0.0, 0.95), "side_overlap": Range(0.0, 0.95), "extend_along_h": NON_NEGATIVE,
        "extend_across_h": NON_NEGATIVE, "area_inset": NON_NEGATIVE, "truth_cell": POSITIVE, "workers": AT_LEAST_ONE,
        "image_format": ("jpg", "png", "tif12"), "jpeg_quality": Range(1.0, 100.0), "target_pattern": ("disc", "cross")}


def camera_system(cfg: SimulationConfig) -> CameraSystem:
    """The configured camera system at the configured image size."""
    if cfg.system == "penta":
        return penta(cfg.width, cfg.height)
    if cfg.system == "three-head":
        return three_head(cfg.width, cfg.height)
    return preset(cfg.system)


# -------------------------------------------------------------------------------------------- worker processes

_WORKER: dict = {}


def _init_worker(city: City, render_cfg: RenderConfig) -> None:
    _WORKER["renderer"] = Renderer(city, render_cfg)


def _render_job(job: tuple) -> tuple[str, float]:
    """Render one image and write it (and its depth map); returns (image id, seconds)."""
    iid, camera, pose, head, seed, path, quality, depth_folder = job
    import cv2

    t0 = time.perf_counter()
    rgb, depth = _WORKER["renderer"].render(camera, pose, head, seed=seed, depth=depth_folder is not None)
    with atomic_path(path) as tmp:
        params = [cv2.IMWRITE_JPEG_QUALITY, quality] if str(path).endswith(".jpg") else []
        if not cv2.imwrite(tmp, rgb[:, :, ::-1], params):
            raise ConfigError(f"could not write image {path}")
    if depth_folder is not None:
        write_depth(depth_folder, iid, depth)
    return iid, time.perf_counter() - t0


def render_images(city: City, jobs: list[tuple], render_cfg: RenderConfig, workers: int,
                  progress: Callable[[int, int, str], None] | None = None) -> list[tuple[str, float]]:
    """Render ``jobs`` (see :func:`_render_job`) in ``workers`` processes (inline when 1)."""
    done = []
    if workers <= 1:
        _init_worker(city, render_cfg)
        for k, job in enumerate(jobs):
            done.append(_render_job(job))
            if progress:
                progress(k + 1, len(jobs), job[0])
        return done
    import multiprocessing as mp

    ex = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                             initargs=(city, render_cfg))
    try:
        for k, res in enumerate(ex.map(_render_job, jobs, chunksize=1)):
            done.append(res)
            if progress:  # may raise Cancelled: pending images are then dropped, not rendered
                progress(k + 1, len(jobs), res[0])
    except BaseException:
        ex.shutdown(wait=True, cancel_futures=True)
        raise
    ex.shutdown(wait=True)
    return done


def overview_camera(city: City, width: int = 1600, height: int = 1000) -> tuple[CameraModel, Pose]:
    """A virtual oblique camera looking at the city centre from the south-east, 40 deg below the horizon."""
    from ..geometry.rotations import mount_rotation, ypr_to_cam_from_world

    cx, cy = 0.5 * (city.core[0] + city.core[2]), 0.5 * (city.core[1] + city.core[3])
    span = max(city.core[2] - city.core[0], city.core[3] - city.core[1])
    cz = float(city.terrain_z(np.array([[cx, cy]]))[0])
    dist = 1.25 * span
    az = np.radians(315.0)  # looking north-west
    tilt = 50.0
    c = np.array([cx - np.sin(az) * dist * np.sin(np.radians(tilt)), cy - np.cos(az) * dist * np.sin(np.radians(tilt)),
                  cz + dist * np.cos(np.radians(tilt))])
    cam = CameraModel("overview", width, height, 0.9 * width, 0.9 * width, (width - 1) / 2, (height - 1) / 2)
    r = ypr_to_cam_from_world(az, 0.0, 0.0, mount_rotation(tilt, 0.0))
    return cam, Pose(r, c)


def simulate(out: str | Path, cfg: SimulationConfig = SimulationConfig(), city: City | None = None,
             progress: Callable[[int, int, str], None] | None = None) -> dict:
    """Simulate the block into folder ``out`` and return a summary (images, timings, coverage figures)."""
    import cv2

    t_start = time.perf_counter()
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    city = city if city is not None else make_city(cfg.seed)
    city = replace(city, target_pattern=cfg.target_pattern)
    system = camera_system(cfg)
    ground_z = float(np.nanmean(city.terrain_z(city.core.reshape(2, 2))))
    h = flying_height(system, cfg.gsd)
    area = city.core + np.array([cfg.area_inset, cfg.area_inset, -cfg.area_inset, -cfg.area_inset])
    fcfg = FlightConfig(gsd=cfg.gsd, forward_overlap=cfg.forward_overlap, side_overlap=cfg.side_overlap,
                        direction_deg=cfg.direction_deg, cross_strips=cfg.cross_strips,
                        extend_along=cfg.extend_along_h * h, extend_across=cfg.extend_across_h * h, seed=cfg.seed)
    exposures = plan_flight(system, area, ground_z, fcfg)
    nominal = system.rig()
    true_rig = perturbed_rig(nominal, cfg.nav)
    ext = ".tif" if cfg.image_format == "tif12" else "." + cfg.image_format
    render_cfg = replace(cfg.render, bits=12 if cfg.image_format == "tif12" else 8)
    truth = true_block(system, exposures, city.crs, rig=true_rig, image_ext=ext)
    approx = approximate_block(truth, exposures, nominal, cfg.nav)
    for gp in ground_points(truth, city.target_names, city.targets, city.scene(), city.origin, seed=cfg.seed):
        approx.add_ground_point(gp)
    truth.image_root = approx.image_root = "."
    t_plan = time.perf_counter() - t_start

    depth_folder = str(out / "truth") if cfg.depth_maps else None
    jobs = [(img.id, truth.camera_of(img), img.pose_approx, img.head, cfg.seed * 100003 + k,
             str(out / img.file), cfg.jpeg_quality, depth_folder) for k, img in enumerate(truth.images.values())]
    t0, c0 = time.perf_counter(), os.times()
    done = render_images(city, jobs, render_cfg, cfg.workers, progress)
    t_render, c1 = time.perf_counter() - t0, os.times()
    cpu_render = (c1.user + c1.system + c1.children_user + c1.children_system
                  - c0.user - c0.system - c0.children_user - c0.children_system)

    # previews: the overview and, per head, the image seeing the most buildings
    preview = out / "preview"
    preview.mkdir(exist_ok=True)
    renderer = Renderer(city, cfg.render)
    cam, pose = overview_camera(city)
    rgb, _ = renderer.render(cam, pose, "nadir", seed=1)
    with atomic_path(preview / "city_overview.png") as tmp:
        cv2.imwrite(tmp, rgb[:, :, ::-1])
    from ..geometry.projection import project

    b_xyz = np.array([[*b.center, b.ground_z + 3.0] for b in city.buildings])
    for head in nominal.heads:
        imgs = [i for i in truth.images.values() if i.head == head.name]

        def seen(i, b_xyz=b_xyz):
            uv, d = project(truth.camera_of(i), i.pose_approx, b_xyz)
            return int(np.sum((d > 0) & truth.camera_of(i).contains(np.nan_to_num(uv, nan=-1e9), margin=50)))

        best = max(imgs, key=seen)
        pic = read_photo(out / best.file, True)
        with atomic_path(preview / f"head_{head.name}.png") as tmp:
            cv2.imwrite(tmp, pic)

    cov = coverage_map(truth, area, 2.0, city.terrain_z)
    views = {v: int(sum(cardinal_view(i.pose_approx.R) == v for i in truth.images.values()))
             for v in ("nadir", "north", "east", "south", "west")}
    cov_flat = cov.data.reshape(-1, cov.data.shape[2])
    n_px = sum(c.width * c.height for c in (truth.camera_of(i) for i in truth.images.values()))
    summary = {
        "images": len(truth.images), "exposures": len(exposures), "megapixels": n_px / 1e6,
        "flying_height_m": h, "gsd_m": cfg.gsd, "views": views, "ground_points": len(approx.ground_points),
        "render_seconds": t_render, "images_per_second": len(done) / max(t_render, 1e-9),
        "render_cpu_seconds": cpu_render, "load_average_1min": os.getloadavg()[0],
        "plan_seconds": t_plan, "workers": cfg.workers, "cpu_count": os.cpu_count(),
        "coverage_median_per_view": {v: float(np.median(cov_flat[:, k])) for k, v in
                                     enumerate(("nadir", "north", "east", "south", "west"))},
        "coverage_ge2_fraction": {v: float(np.mean(cov_flat[:, k] >= 2)) for k, v in
                                  enumerate(("nadir", "north", "east", "south", "west"))},
        "area": area.tolist(),
    }
    config = {"config": _jsonable(asdict(cfg)), "summary": summary}
    write_truth(out / "truth", city, truth, city.core, cfg.truth_cell, config)
    from ..io.geotiff import write_geotiff

    write_geotiff(out / "truth" / "coverage.tif", cov)
    native.write_block(approx, out / "block.json")
    write_block("gnssimu", approx, out / "events.txt")
    write_ground_points(approx, out / "gcp.csv")
    write_measurements(approx, out / "gcp_measurements.csv")
    write_block("bex", approx, out / "block.xml")  # last: a folder with block.xml is a complete simulation
    summary["total_seconds"] = time.perf_counter() - t_start
    return summary


def _jsonable(d):
    if isinstance(d, dict):
        return {k: _jsonable(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_jsonable(v) for v in d]
    if isinstance(d, float) and not np.isfinite(d):
        return None
    return d

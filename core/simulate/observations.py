"""Observation-only simulator for aerial triangulation: tie-point image measurements without rendering.

It produces what a bundle adjustment sees from a block of thousands of images: the real synthetic city of
:func:`.city.make_city` (tiled to cover the block), a camera system of :mod:`.cameras` (the penta preset by
default) flown by :func:`.flight.plan_flight`, true and navigation-grade orientations from
:func:`.flight.true_block` / :func:`.flight.approximate_block`, tie points on the city surfaces with their image
measurements (Gaussian noise and a labelled fraction of blunders), and signalised control / check points measured
by :func:`.flight.ground_points`.

Tie points
----------
Points are drawn uniformly by 3-D area on the triangles of the sampled surface classes (by default ground,
street, roof, wall, roof installation and roof edge; trees, glass and overhang undersides are left out as a
matcher would). ``tie_density`` is given per ground pixel (``gsd**2``), so a block has the same number of tie
points per image at any GSD: at 0.0008 a 3,000-image penta block (1200 x 900 px, GSD 0.1 m, flying height 112 m)
has about 870 measurements per image (97 k points, 2.6 M observations).

Visibility (exact ray casting)
------------------------------
A point is measured in an image when (1) it projects inside the frame (``border_px`` from its edge), (2) its
surface faces the camera at an incidence below ``max_incidence_deg`` (features are not matched at grazing
angles), (3) the Open3D ray cast from the projection centre towards it hits the city mesh no earlier than
``visibility_tolerance`` before the point (the first surface hit is the point's own; the city is cast in local
float32 coordinates, good to 0.1 mm here), and (4) a matcher detects it (probability ``p_detect``). Candidate
points of an image come from a grid index of the points queried with the bounding box of the image's footprint
between the lowest and highest city surface; rays are cast in chunks of ``ray_chunk``.

Ray counts
----------
At 80/60 overlap a point lies in 1 / (0.2 * 0.4) = 12.5 nadir frames, fewer the higher it lies (the footprint
shrinks as ``(H - dz)**2``: a 15 m roof about 9.4 at the default 112 m flying height). Measured on the 3,000-image
block away from its border (``p_detect`` 0.9): nadir rays per point 11.3 on streets, 10.3 on other ground, 9.3 on
roofs, 1.6 on walls; each oblique view adds 8-9 on average (3-3.5 on walls); 44 rays per point in all, 20 % of them
nadir.

Scale
-----
Building the tiled city dominates (about 1.1-1.3 s per 192 m x 144 m tile): 3,000 images need 30 tiles, 33 s for
the city plus 4 s for the simulation, 1.0 GB; 33,000 images need 234 tiles (9.4 M triangles), 294 s plus 82 s,
4.8 GB peak for 28.7 M observations (2 cores).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from ..geometry.projection import project
from ..geometry.views import VIEWS
from ..model import CameraModel, ImageBlock, Pose, TiePoints
from .cameras import CameraSystem, penta
from .city import SEMANTIC, TILE_SIZE, City, make_city
from .flight import (
    FlightConfig,
    NavErrors,
    approximate_block,
    flying_height,
    ground_points,
    perturbed_rig,
    plan_flight,
    true_block,
)


def look_rotation(axis_world: np.ndarray, down_world: np.ndarray) -> np.ndarray:
    """OpenCV ``cam_from_world`` (3, 3) whose optical axis is ``axis_world`` and whose image ``y`` (down) axis is
    as close as possible to ``down_world``."""
    z = np.asarray(axis_world, np.float64)
    z = z / np.linalg.norm(z)
    y = np.asarray(down_world, np.float64) - z * np.dot(down_world, z)
    y = y / np.linalg.norm(y)
    x = np.cross(y, z)
    return np.stack([x, y, z])


@dataclass(frozen=True)
class SimulationConfig:
    """What to simulate.

    Attributes
    ----------
    n_images : approximate total image count (one image per head and exposure)
    strips : number of flight strips (0: as many as make the block about square)
    gsd : nadir ground sampling distance, metres (sets the flying height of the camera system)
    forward_overlap, side_overlap : of the nadir images
    tie_density : tie points per ground pixel (``gsd**2``) of city surface (3-D area)
    surfaces : semantic classes of :data:`.city.SEMANTIC` that carry tie points
    p_detect : probability that a visible point is measured in an image
    max_incidence_deg : largest angle between the surface normal and the ray to the camera of a measurement
    border_px : measurements keep this distance from the image border
    visibility_tolerance : metres; a ray is unobstructed when its first hit is at most this much before the point
    noise_px : standard deviation of image measurements (tie and ground points)
    blunder_fraction : share of tie observations moved by gross errors of ``blunder_px`` (min, max) pixels
    gnss_sigma : (3,) GNSS centre noise, metres; gnss_bias : (3,) constant datum offset of the GNSS frame
    gnss_strip_sigma : metres, an offset per flight strip (3-D, normal), as a trajectory whose ambiguities are fixed
        again after each turn has; gnss_drift_sigma : metres per km, a drift per strip along it (normal), the error
        linear in the along-track position from the strip's middle (0: none, the default)
    imu_sigma_deg : (3,) attitude noise (roll, pitch, yaw), degrees
    boresight_sigma_deg, lever_arm_sigma : per-head mounting errors of the true rig against the calibrated one
        (0: the heads are exactly at their calibrated mounting)
    attitude_jitter_deg, position_jitter : true deviations of the aircraft from the plan (1 sigma)
    n_ground_points : signalised control + check points, alternating (half of them check points)
    ground_cell : terrain grid cell of the city, metres
    ray_chunk : rays cast per Open3D call (bounds the memory of the visibility test)
    seed : city, flight, errors, sampling and noise all follow from it
    system : the camera system (default: the penta preset)
    """

    n_images: int = 500
    strips: int = 0
    gsd: float = 0.10
    forward_overlap: float = 0.8
    side_overlap: float = 0.6
    tie_density: float = 0.0008
    surfaces: tuple[str, ...] = ("ground", "street", "roof", "wall", "roof_installation", "roof_edge")
    p_detect: float = 0.9
    max_incidence_deg: float = 75.0
    border_px: float = 2.0
    visibility_tolerance: float = 0.02
    noise_px: float = 0.3
    blunder_fraction: float = 0.03
    blunder_px: tuple[float, float] = (4.0, 40.0)
    gnss_sigma: tuple[float, float, float] = (0.05, 0.05, 0.08)
    gnss_bias: tuple[float, float, float] = (0.06, -0.04, 0.10)
    gnss_strip_sigma: float = 0.0
    gnss_drift_sigma: float = 0.0
    imu_sigma_deg: tuple[float, float, float] = (0.004, 0.004, 0.006)
    boresight_sigma_deg: float = 0.0
    lever_arm_sigma: float = 0.0
    attitude_jitter_deg: float = 0.5
    position_jitter: float = 1.0
    n_ground_points: int = 50
    ground_cell: float = 8.0
    ray_chunk: int = 2_000_000
    seed: int = 7
    system: CameraSystem = field(default_factory=penta)


@dataclass(eq=False)
class SimulatedBlock:
    """A simulated block with its ground truth.

    Attributes
    ----------
    block : cameras, nominal rig, images with ``pose_approx`` (navigation) and prior sigmas, ground points
    ties : tie observations (``obs_blunder`` = planted blunders, ``xyz`` NaN: not yet intersected)
    true_poses : image id -> true pose
    true_xyz : (n, 3) float64 true tie point coordinates
    true_normal : (n, 3) float64 unit normals of the surfaces the tie points lie on
    true_semantic : (n,) uint8 semantic class (:data:`.city.SEMANTIC`) of those surfaces
    gsd : nadir ground sample distance, metres
    city : the city the block was flown over
    area : (4,) world bbox (xmin, ymin, xmax, ymax) given to the flight planner
    true_gnss_strip : image id -> (3,) the strip offset and drift in its GNSS centre (see
        ``SimulationConfig.gnss_strip_sigma`` and :func:`plant_strip_errors`; zeros without them)
    """

    block: ImageBlock
    ties: TiePoints
    true_poses: dict[str, Pose]
    true_xyz: np.ndarray
    true_normal: np.ndarray
    true_semantic: np.ndarray
    gsd: float
    city: City
    area: np.ndarray
    config: SimulationConfig
    true_gnss_strip: dict[str, np.ndarray] = field(default_factory=dict)


@lru_cache(maxsize=1)
def _city(seed: int, tiles: tuple[int, int], ground_cell: float) -> City:
    """The tiled city (cached: tests and benchmarks simulate several blocks over one city)."""
    return make_city(seed, tiles=tiles, ground_cell=ground_cell)


def flight_layout(cfg: SimulationConfig) -> tuple[float, float, tuple[int, int]]:
    """Along-track (x, the strips fly east-west) and across-track extents of the planned area in metres, and the
    city tiles that cover the nadir images of a block of about ``cfg.n_images`` images."""
    cam = cfg.system.camera(cfg.system.nadir_head)
    h = flying_height(cfg.system, cfg.gsd)
    swath, along_fp = h * cam.width / cam.fx, h * cam.height / cam.fy
    base, spacing = (1 - cfg.forward_overlap) * along_fp, (1 - cfg.side_overlap) * swath
    n_exp = max(4, round(cfg.n_images / len(cfg.system.heads)))
    strips = cfg.strips or max(1, round(math.sqrt(n_exp * base / spacing)))
    per_strip = max(2, round(n_exp / strips))
    # just below whole multiples, so plan_flight's ceil() gives exactly ``strips`` x ``per_strip`` exposures
    along = (per_strip - 1) * base - 1e-6
    across = (strips - 1) * spacing + swath - 1e-6
    tiles = (max(1, math.ceil((along + along_fp) / TILE_SIZE[0])), max(1, math.ceil(across / TILE_SIZE[1])))
    return along, across, tiles


def sample_surface_points(city: City, bbox: np.ndarray, density_m2: float, surfaces: tuple[str, ...],
                          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points uniform by area on the city triangles of classes ``surfaces`` whose centroid lies in ``bbox``
    (world xmin, ymin, xmax, ymax), ``density_m2`` per square metre (Poisson count).

    Returns ``xyz (n, 3)`` world, ``normal (n, 3)`` unit face normals and ``triangle (n,)`` indices.
    """
    codes = [SEMANTIC[s] for s in surfaces]
    v = city.vertices - city.origin
    sel = np.flatnonzero(np.isin(city.semantic, codes))
    t = city.triangles[sel]
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    cen = (a + b + c)[:, :2] / 3.0 + city.origin[:2]
    inside = (cen[:, 0] >= bbox[0]) & (cen[:, 0] <= bbox[2]) & (cen[:, 1] >= bbox[1]) & (cen[:, 1] <= bbox[3])
    sel, a, b, c = sel[inside], a[inside], b[inside], c[inside]
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    n = rng.poisson(density_m2 * area.sum())
    pick = rng.choice(len(sel), size=n, p=area / area.sum())
    s, r = np.sqrt(rng.random(n))[:, None], rng.random(n)[:, None]
    xyz = (1 - s) * a[pick] + s * (1 - r) * b[pick] + s * r * c[pick] + city.origin
    normal = cross[pick] / (2.0 * area[pick, None])
    return xyz, normal, sel[pick]


def _ground_sites(city: City, bbox: np.ndarray, n: int, rng: np.random.Generator) -> tuple[list[str], np.ndarray]:
    """Names and world ``(n, 3)`` centres of ``n`` signalised points spread over ``bbox``: the city's targets
    inside it first, then marks on open ground (a vertical ray first hits the terrain), chosen by farthest-point
    sampling."""
    import open3d as o3d

    t_in = np.flatnonzero((city.targets[:, 0] > bbox[0]) & (city.targets[:, 0] < bbox[2])
                          & (city.targets[:, 1] > bbox[1]) & (city.targets[:, 1] < bbox[3]))
    names = [city.target_names[i] for i in t_in]
    xyz = city.targets[t_in]
    if len(names) < n:
        m = 8 * n
        xy = np.column_stack([rng.uniform(bbox[0], bbox[2], m), rng.uniform(bbox[1], bbox[3], m)])
        z = city.terrain_z(xy)
        rays = np.zeros((m, 6), np.float32)
        rays[:, :2] = xy - city.origin[:2]
        rays[:, 2], rays[:, 5] = z + 1000.0, -1.0
        hit = city.scene().cast_rays(o3d.core.Tensor(rays))
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        t_hit = hit["t_hit"].numpy()
        open_ground = np.isfinite(t_hit) & (np.abs(t_hit - 1000.0) < 0.01)
        open_ground &= np.isin(city.semantic[np.clip(prim, 0, len(city.semantic) - 1)],
                               [SEMANTIC["ground"], SEMANTIC["street"]])
        extra = np.column_stack([xy, z])[open_ground]
        names += [f"G{i + 1:03d}" for i in range(len(extra))]
        xyz = np.concatenate([xyz, extra])
    n_t = len(t_in)
    if n_t >= n:  # enough targets: spread a subset, starting at the one nearest the centre
        chosen = [int(np.argmin(np.linalg.norm(xyz[:n_t, :2] - 0.5 * (bbox[:2] + bbox[2:]), axis=1)))]
        pool = np.arange(n_t)
    else:  # all targets, then open-ground marks farthest from the points chosen so far
        chosen, pool = list(range(n_t)), np.arange(n_t, len(xyz))
    dist = np.full(len(pool), np.inf)
    for k in chosen:
        dist = np.minimum(dist, np.linalg.norm(xyz[pool, :2] - xyz[k, :2], axis=1))
    while len(chosen) < min(n, len(xyz)) and len(pool):
        k = int(pool[np.argmax(dist)])
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(xyz[pool, :2] - xyz[k, :2], axis=1))
    chosen.sort()
    return [names[i] for i in chosen], xyz[chosen]


def _border_rays(camera: CameraModel) -> np.ndarray:
    """Undistorted camera-frame directions ``(k, 3)`` through the image border (32 samples), for footprints."""
    w, h = camera.width - 1.0, camera.height - 1.0
    s = np.linspace(0.0, 1.0, 8, endpoint=False)
    border = np.concatenate([np.stack([s * w, 0 * s], 1), np.stack([w + 0 * s, s * h], 1),
                             np.stack([w - s * w, h + 0 * s], 1), np.stack([0 * s, h - s * h], 1)])
    return np.column_stack([camera.pixel_to_normalized(border), np.ones(len(border))])


def footprint_bbox(border_rays: np.ndarray, pose: Pose, z_lo: float, z_hi: float) -> np.ndarray | None:
    """World bbox ``(xmin, ymin, xmax, ymax)`` of the part of the frame between the planes ``Z = z_lo`` and
    ``Z = z_hi`` (rays of :func:`_border_rays`), None when no border ray reaches them."""
    d = border_rays @ pose.R
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = np.concatenate([pose.C[:2] + d[:, :2] * ((z - pose.C[2]) / d[:, 2])[:, None] for z in (z_lo, z_hi)])
        s = np.concatenate([(z - pose.C[2]) / d[:, 2] for z in (z_lo, z_hi)])
    xy = xy[np.isfinite(s) & (s > 0)]
    return np.r_[xy.min(0), xy.max(0)] if len(xy) else None


def visible_observations(city: City, block: ImageBlock, image_ids: list[str], xyz: np.ndarray, normal: np.ndarray,
                         cfg: SimulationConfig, rng: np.random.Generator,
                         progress: Callable[[int, int, str], None] | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise-free measurements of points ``xyz (n, 3)`` with normals ``normal (n, 3)`` in the images of ``block``
    (orientation in ``pose_approx``), visible as described in the module docstring.

    Returns ``point (m,)`` int64, ``image (m,)`` int64 index into ``image_ids`` and ``uv (m, 2)`` float64.
    """
    import open3d as o3d

    scene = city.scene()
    cell = 32.0
    lo = xyz[:, :2].min(0) if len(xyz) else np.zeros(2)
    ij = np.floor((xyz[:, :2] - lo) / cell).astype(np.int64)
    nx, ny = (ij.max(0) + 1) if len(xyz) else (1, 1)
    key = ij[:, 1] * nx + ij[:, 0]
    order = np.argsort(key, kind="stable")
    starts = np.searchsorted(key[order], np.arange(nx * ny + 1))
    z_lo, z_hi = (float(xyz[:, 2].min()), float(xyz[:, 2].max())) if len(xyz) else (0.0, 0.0)
    cos_max = math.cos(math.radians(cfg.max_incidence_deg))
    pending: list[tuple[np.ndarray, ...]] = []
    n_pending = 0
    out: list[tuple[np.ndarray, ...]] = []

    def flush() -> None:
        if not pending:
            return
        p, k, uv, c, d, dist = (np.concatenate(x) for x in zip(*pending, strict=True))
        pending.clear()
        rays = np.column_stack([c - city.origin, d]).astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        keep = (t_hit >= dist - cfg.visibility_tolerance) & (rng.random(len(p)) < cfg.p_detect)
        out.append((p[keep], k[keep], uv[keep]))

    border = {cid: _border_rays(cam) for cid, cam in block.cameras.items()}
    for k, iid in enumerate(image_ids):
        img = block.images[iid]
        cam, pose = block.camera_of(img), img.pose_approx
        fp = footprint_bbox(border[cam.id], pose, z_lo, z_hi)
        if fp is None or len(xyz) == 0:
            continue
        i0, j0 = np.clip(np.floor((fp[:2] - lo) / cell).astype(np.int64), 0, [nx - 1, ny - 1])
        i1, j1 = np.clip(np.floor((fp[2:] - lo) / cell).astype(np.int64), 0, [nx - 1, ny - 1])
        cand = np.concatenate([order[starts[j * nx + i0]:starts[j * nx + i1 + 1]] for j in range(j0, j1 + 1)])
        to_cam = pose.C - xyz[cand]
        dist = np.linalg.norm(to_cam, axis=1)
        facing = np.einsum("ij,ij->i", normal[cand], to_cam) > cos_max * dist
        cand, to_cam, dist = cand[facing], to_cam[facing], dist[facing]
        uv, depth = project(cam, pose, xyz[cand])
        inside = (depth > 0) & cam.contains(np.nan_to_num(uv, nan=-1e9), margin=cfg.border_px)
        if not inside.any():
            continue
        cand, dist = cand[inside], dist[inside]
        pending.append((cand, np.full(len(cand), k, np.int64), uv[inside], np.broadcast_to(pose.C, (len(cand), 3)),
                        -to_cam[inside] / dist[:, None], dist))
        n_pending += len(cand)
        if n_pending >= cfg.ray_chunk:
            flush()
            n_pending = 0
        if progress is not None and k % 500 == 0:
            progress(k, len(image_ids), "ray casting tie point visibility")
    flush()
    if not out:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
    p, k, uv = (np.concatenate(x) for x in zip(*out, strict=True))
    return p, k, uv


def simulate_block(cfg: SimulationConfig = SimulationConfig(), city: City | None = None,
                   progress: Callable[[int, int, str], None] | None = None) -> SimulatedBlock:
    """Simulate a block with tie points, blunders, GNSS/IMU priors and ground points over the synthetic city.

    ``city`` defaults to ``make_city(cfg.seed)`` tiled to cover the nadir images (see :func:`flight_layout`); a
    given city must cover the planned area around its core's centre.
    """
    along, across, tiles = flight_layout(cfg)
    if city is None:
        city = _city(cfg.seed, tiles, cfg.ground_cell)
    centre = 0.5 * (city.core[:2] + city.core[2:])
    area = np.array([centre[0] - along / 2, centre[1] - across / 2, centre[0] + along / 2, centre[1] + across / 2])
    system = cfg.system
    fcfg = FlightConfig(gsd=cfg.gsd, forward_overlap=cfg.forward_overlap, side_overlap=cfg.side_overlap,
                        direction_deg=90.0, attitude_jitter_deg=cfg.attitude_jitter_deg,
                        position_jitter=cfg.position_jitter, seed=cfg.seed)
    exposures = plan_flight(system, area, float(np.nanmean(city.terrain.zg)), fcfg)
    nav = NavErrors(gnss_sigma=cfg.gnss_sigma, datum_bias_sigma=0.0, imu_sigma_deg=cfg.imu_sigma_deg,
                    boresight_sigma_deg=cfg.boresight_sigma_deg, lever_arm_sigma=cfg.lever_arm_sigma, seed=cfg.seed)
    nominal = system.rig()
    truth = true_block(system, exposures, city.crs, rig=perturbed_rig(nominal, nav))
    block = approximate_block(truth, exposures, nominal, nav)
    bias = np.asarray(cfg.gnss_bias, np.float64)
    for img in block.images.values():  # the datum offset of the GNSS frame, the same for every exposure
        img.pose_approx = Pose(img.pose_approx.R, img.pose_approx.C + bias)
    strip_error = plant_strip_errors(block, cfg.gnss_strip_sigma, cfg.gnss_drift_sigma, cfg.seed)
    true_poses = {iid: img.pose_approx for iid, img in truth.images.items()}
    ids = list(truth.images)

    # tie points on the surfaces the images can see
    z_lo = float(np.nanmin(city.terrain.zg))
    border = {cid: _border_rays(cam) for cid, cam in truth.cameras.items()}
    fps = np.array([footprint_bbox(border[truth.images[i].camera_id], true_poses[i], z_lo, z_lo) for i in ids])
    ext = city.extent
    bbox = np.r_[np.maximum(fps[:, :2].min(0), ext[:2]), np.minimum(fps[:, 2:].max(0), ext[2:])]
    rng = np.random.default_rng([cfg.seed, 101])
    xyz, normal, tri = sample_surface_points(city, bbox, cfg.tie_density / cfg.gsd**2, cfg.surfaces, rng)
    point, image, uv = visible_observations(city, truth, ids, xyz, normal, cfg, rng, progress)

    # multi-ray points only, renumbered, observations ordered by track then image
    counts = np.bincount(point, minlength=len(xyz))
    used = counts >= 2
    sel = used[point]
    point, image, uv = point[sel], image[sel], uv[sel]
    track = (np.cumsum(used) - 1)[point]
    order = np.lexsort((image, track))
    track, image, uv = track[order], image[order], uv[order]
    uv = uv + rng.normal(0.0, cfg.noise_px, uv.shape)
    blunder = rng.random(len(track)) < cfg.blunder_fraction
    ang = rng.uniform(0, 2 * np.pi, blunder.sum())
    mag = rng.uniform(cfg.blunder_px[0], cfg.blunder_px[1], blunder.sum())
    offset = np.stack([np.cos(ang), np.sin(ang)], 1) * mag[:, None]
    size = np.array([[truth.camera_of(i).width, truth.camera_of(i).height] for i in ids], np.float64)[image[blunder]]
    outside = (uv[blunder] + offset < -0.5) | (uv[blunder] + offset > size - 0.5)
    uv[blunder] += np.where(outside, -offset, offset)  # mirrored where needed: a wrong match lies in the image too
    ties = TiePoints(xyz=np.full((int(used.sum()), 3), np.nan), obs_track=track, obs_image=image, obs_uv=uv,
                     image_ids=ids, obs_blunder=blunder)

    # signalised control and check points over the nadir-covered area
    if cfg.n_ground_points > 0:
        names, gp_xyz = _ground_sites(city, area, cfg.n_ground_points, np.random.default_rng([cfg.seed, 202]))
        for gp in ground_points(truth, names, gp_xyz, city.scene(), city.origin, sigma_px=cfg.noise_px,
                                check_every=2, seed=cfg.seed):
            block.add_ground_point(gp)
    return SimulatedBlock(block=block, ties=ties, true_poses=true_poses, true_xyz=xyz[used], true_normal=normal[used],
                          true_semantic=city.semantic[tri[used]], gsd=cfg.gsd, city=city, area=area, config=cfg,
                          true_gnss_strip=strip_error)


def plant_strip_errors(block: ImageBlock, strip_sigma: float, drift_sigma: float, seed: int) -> dict[str, np.ndarray]:
    """Add to the GNSS centres of a simulated block an error per flight strip: an offset (3-D, normal with
    ``strip_sigma`` metres) plus a drift (normal with ``drift_sigma`` metres per km) times the exposure's along-track
    position from the strip's middle (km, in the flight direction: the time from the middle at the strip's mean speed
    along the line from its first to its last exposure where the images have times, as a GNSS drift grows with time,
    else the position projected on that line). Strips and their order are the flight plan's
    (:func:`.flight.plan_flight` names the exposures ``S<strip>_E<number>``, numbered in flight order). Returns image
    id -> its error ``(3,)`` (zeros for both sigmas 0, the block untouched)."""
    rng = np.random.default_rng([seed, 303])
    by_strip: dict[str, dict[str, list[str]]] = {}
    for iid, img in block.images.items():
        strip, _, number = (img.exposure or "").partition("_E")
        if number and img.pose_approx is not None:
            by_strip.setdefault(strip, {}).setdefault(img.exposure, []).append(iid)
    out = {iid: np.zeros(3) for iid in block.images}
    if strip_sigma <= 0 and drift_sigma <= 0:
        return out
    for strip in sorted(by_strip):
        exposures = sorted(by_strip[strip], key=lambda e: int(e.partition("_E")[2]))  # in flight order
        shift = rng.normal(0.0, strip_sigma, 3)
        drift = rng.normal(0.0, drift_sigma, 3)
        xy = np.array([np.mean([block.images[i].pose_approx.C[:2] for i in by_strip[strip][e]], axis=0)
                       for e in exposures])
        direction = xy[-1] - xy[0]
        length = max(float(np.linalg.norm(direction)), 1e-9)
        times = [[block.images[i].time for i in by_strip[strip][e]] for e in exposures]
        if len(exposures) > 1 and all(t is not None for ts in times for t in ts):
            t = np.array([np.mean(ts) for ts in times])
            u = (t - 0.5 * (t[0] + t[-1])) * length / max(float(t[-1] - t[0]), 1e-9) / 1000.0
        else:
            u = xy @ (direction / length) / 1000.0
            u -= 0.5 * (u.min() + u.max())
        for e, uk in zip(exposures, u):
            for iid in by_strip[strip][e]:
                out[iid] = shift + uk * drift
                p = block.images[iid].pose_approx
                block.images[iid].pose_approx = Pose(p.R, p.C + out[iid])
    return out


def ray_statistics(sim: SimulatedBlock) -> dict:
    """Rays per tie point by view: for every view of :data:`..geometry.views.VIEWS` the points it sees, their
    mean and median rays in that view and the view's share of all observations; overall mean and median rays."""
    t = sim.ties
    views = np.array([sim.block.images[i].view for i in t.image_ids])[t.obs_image]
    out: dict = {"points": t.n_tracks, "observations": t.n_obs, "mean_rays": float(t.ray_counts().mean()),
                 "median_rays": float(np.median(t.ray_counts())), "views": {}}
    for v in VIEWS:
        n = np.bincount(t.obs_track[views == v], minlength=t.n_tracks)
        seen = n > 0
        out["views"][v] = {"points": int(seen.sum()), "mean_rays": float(n[seen].mean()) if seen.any() else 0.0,
                           "median_rays": float(np.median(n[seen])) if seen.any() else 0.0,
                           "share": float((views == v).mean()) if t.n_obs else 0.0}
    return out

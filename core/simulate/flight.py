"""Flight planning, true and approximate orientations, navigation errors, signalised ground points, coverage.

Use for large blocks (the observation-only simulator)::

    city = make_city(seed, tiles=(8, 8), ground_cell=8.0)
    system = preset("penta")
    exposures = plan_flight(system, city.core, ground_z=float(np.nanmean(city.terrain.zg)),
                            config=FlightConfig(gsd=0.10))
    truth = true_block(system, exposures, city.crs)            # ImageBlock with true poses, no files
    approx = approximate_block(truth, system, NavErrors(seed=1))  # GNSS/IMU poses with prior sigmas

Planning costs microseconds per exposure; nothing here renders. Image views (nadir/north/east/south/west) are
always derived from the actual orientation (:mod:`..geometry.views`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import ConfigError
from ..geometry.projection import project
from ..geometry.rotations import rotvec_to_matrix, world_from_body
from ..geometry.views import VIEWS, cardinal_view
from ..model import GroundPoint, Image, ImageBlock, Pose, Raster, Rig, RigHead
from .cameras import CameraSystem
from .geometry2d import clip_halfplane


@dataclass(frozen=True)
class FlightConfig:
    """A photo flight over a rectangular area.

    gsd : nadir ground sampling distance at the reference ground height, metres -> flying height
    forward_overlap, side_overlap : of the nadir images, fractions (0.8 / 0.6 = 80 % / 60 %)
    direction_deg : strip azimuth, degrees clockwise from grid north (90: strips flown east-west)
    alternate : fly every other strip in the opposite direction
    cross_strips : add a second set of strips perpendicular to the first
    extend_along, extend_across : metres added beyond the area at both strip ends / both sides, so oblique heads
        also cover the area's border (about the flying height is needed for full oblique coverage)
    attitude_jitter_deg, position_jitter : true deviations of the aircraft from the plan (1 sigma)
    ground_speed, turn_s, start_time : the exposures' times (seconds): the strips are flown at ``ground_speed``
        (m/s) in plan order from ``start_time``, with ``turn_s`` from the end of one strip to the start of the next
    seed : seeds the jitter
    """

    gsd: float = 0.12
    forward_overlap: float = 0.80
    side_overlap: float = 0.60
    direction_deg: float = 90.0
    alternate: bool = True
    cross_strips: bool = False
    extend_along: float = 0.0
    extend_across: float = 0.0
    attitude_jitter_deg: float = 0.5
    position_jitter: float = 1.0
    ground_speed: float = 60.0
    turn_s: float = 90.0
    start_time: float = 36000.0
    seed: int = 0

    def __post_init__(self) -> None:
        for k in ("forward_overlap", "side_overlap"):
            v = getattr(self, k)
            if not 0.0 <= v < 0.95:
                raise ConfigError(f"{k} must be a fraction in [0, 0.95), got {v}")
        if self.gsd <= 0:
            raise ConfigError(f"gsd must be positive, got {self.gsd}")
        if self.ground_speed <= 0 or self.turn_s < 0:
            raise ConfigError(f"ground_speed must be positive and turn_s not negative, got {self.ground_speed} and "
                              f"{self.turn_s}")


@dataclass(frozen=True)
class Exposure:
    """One trigger of the camera system: true rig (body) pose.

    name : ``S<strip>_E<index>``; center : (3,) world position of the rig origin; yaw, pitch, roll : radians,
    navigation convention of :mod:`..geometry.rotations` (yaw = heading clockwise from grid north); time : seconds
    """

    name: str
    strip: int
    index: int
    center: np.ndarray
    yaw: float
    pitch: float
    roll: float
    time: float = 0.0

    def world_from_body(self) -> np.ndarray:
        """(3, 3) rotation of body vectors (x forward, y right, z down) into the world (east, north, up)."""
        return world_from_body(self.yaw, self.pitch, self.roll)


def flying_height(system: CameraSystem, gsd: float) -> float:
    """Height above ground (m) giving nadir ground sampling distance ``gsd``."""
    return gsd * system.camera(system.nadir_head).fx


def plan_flight(system: CameraSystem, area: np.ndarray, ground_z: float, config: FlightConfig = FlightConfig()
                ) -> list[Exposure]:
    """Strips over ``area`` at the flying height for ``config.gsd``.

    ``area`` is a bbox ``(xmin, ymin, xmax, ymax)`` or a polygon ``(k, 2)`` (world). Strip spacing is
    ``(1 - side_overlap)`` times the nadir swath, exposure spacing ``(1 - forward_overlap)`` times the nadir
    along-track footprint (the image's v axis runs along track). Strips are centred across the area; each strip
    covers the part of the area under its swath (the whole area's extent for strips outside it) plus
    ``extend_along`` at both ends.
    """
    cam = system.camera(system.nadir_head)
    h = flying_height(system, config.gsd)
    swath, along_fp = h * cam.width / cam.fx, h * cam.height / cam.fy
    base, spacing = (1 - config.forward_overlap) * along_fp, (1 - config.side_overlap) * swath
    rng = np.random.default_rng(config.seed)
    area = np.asarray(area, np.float64)
    if area.shape == (4,):
        xmin, ymin, xmax, ymax = area
        corners = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])
    elif area.ndim == 2 and area.shape[1] == 2 and len(area) >= 3:
        corners = area
    else:
        raise ConfigError(f"area must be (xmin, ymin, xmax, ymax) or a polygon (k, 2), got shape {area.shape}")
    centre = 0.5 * (corners.min(0) + corners.max(0))
    out: list[Exposure] = []
    azimuths = [config.direction_deg] + ([config.direction_deg + 90.0] if config.cross_strips else [])
    strip_no = 0
    clock = config.start_time
    for az_deg in azimuths:
        az = math.radians(az_deg)
        a = np.array([math.sin(az), math.cos(az)])   # along track
        c = np.array([math.cos(az), -math.sin(az)])  # across track (to the right)
        pa, pc = (corners - centre) @ a, (corners - centre) @ c
        span_c = pc.max() - pc.min() + 2 * config.extend_across
        n_s = max(1, math.ceil(max(span_c - swath, 0.0) / spacing) + 1)
        off_c = (np.arange(n_s) - (n_s - 1) / 2) * spacing + 0.5 * (pc.max() + pc.min())
        local = np.stack([pa, pc], 1)
        for si, oc in enumerate(off_c):
            band = clip_halfplane(clip_halfplane(local, 0.0, 1.0, -(oc + swath / 2)), 0.0, -1.0, oc - swath / 2)
            lo, hi = (band[:, 0].min(), band[:, 0].max()) if len(band) >= 3 else (pa.min(), pa.max())
            n_e = max(2, math.ceil((hi - lo + 2 * config.extend_along) / base) + 1)
            off_a = (np.arange(n_e) - (n_e - 1) / 2) * base + 0.5 * (lo + hi)
            reverse = config.alternate and si % 2 == 1
            yaw = az + (math.pi if reverse else 0.0)
            seq = off_a[::-1] if reverse else off_a
            strip_no += 1
            for ei, oa in enumerate(seq):
                xy = centre + oa * a + oc * c + rng.normal(0, config.position_jitter, 2)
                z = ground_z + h + rng.normal(0, config.position_jitter)
                att = np.radians(rng.normal(0, config.attitude_jitter_deg, 3))
                out.append(Exposure(f"S{strip_no:02d}_E{ei + 1:03d}", strip_no, ei + 1, np.array([*xy, z]),
                                    float((yaw + att[0] + math.pi) % (2 * math.pi) - math.pi), float(att[1]),
                                    float(att[2]), clock + ei * base / config.ground_speed))
            clock = out[-1].time + config.turn_s
    return out


def image_pose(exposure: Exposure, head: RigHead) -> Pose:
    """Pose of one head's image: ``R = sensor_from_rig @ world_from_body.T``, centre = rig centre + lever arm."""
    return head.image_pose(exposure.world_from_body(), exposure.center)


IMAGE_NAME_PATTERN = r"(?P<exposure>S\d+_E\d+)_(?P<head>.+)"
"""The simulator's image ids (``<exposure>_<head>``, see :func:`true_block`) as an ``exposure_pattern`` for the import
(``-o exposures=name``): what restores the exposures from a format that does not carry them (BlocksExchange)."""


def true_block(system: CameraSystem, exposures: list[Exposure], crs: str, rig: Rig | None = None,
               image_ext: str = ".jpg") -> ImageBlock:
    """The block with true poses in ``pose_approx`` (``rig`` defaults to the nominal rig of ``system``).

    Image ids are ``<exposure>_<head>``; files ``images/<id><image_ext>``.
    """
    rig = rig if rig is not None else system.rig()
    block = ImageBlock(crs=crs)
    for cam in system.cameras().values():
        block.add_camera(cam)
    block.rigs[rig.name] = rig
    for ex in exposures:
        for head in rig.heads:
            iid = f"{ex.name}_{head.name}"
            block.add_image(Image(id=iid, camera_id=head.camera_id, file=f"images/{iid}{image_ext}", head=head.name,
                                  exposure=ex.name, time=ex.time, pose_approx=image_pose(ex, head)))
    return block


@dataclass(frozen=True)
class NavErrors:
    """Navigation and calibration errors (1 sigma unless stated), drawn from ``seed``.

    gnss_sigma : (3,) metres, random per exposure; datum_bias_sigma : metres, one 3-D offset for the whole block
    (a datum or antenna offset error); imu_sigma_deg : (roll, pitch, yaw) degrees, random per exposure;
    boresight_sigma_deg : per-head fixed misalignment of the true head against the nominal rig;
    lever_arm_sigma : metres, per-head fixed error of the nominal lever arm.
    """

    gnss_sigma: tuple[float, float, float] = (0.05, 0.05, 0.08)
    datum_bias_sigma: float = 0.10
    imu_sigma_deg: tuple[float, float, float] = (0.005, 0.005, 0.008)
    boresight_sigma_deg: float = 0.03
    lever_arm_sigma: float = 0.01
    seed: int = 1


def perturbed_rig(rig: Rig, errors: NavErrors) -> Rig:
    """The *true* rig: the nominal rig with each head's boresight misalignment and lever-arm error applied."""
    rng = np.random.default_rng([errors.seed, 17])
    heads = []
    for h in rig.heads:
        d_rot = rotvec_to_matrix(np.radians(rng.normal(0, errors.boresight_sigma_deg, 3)))
        heads.append(replace(h, sensor_from_rig=d_rot @ h.sensor_from_rig,
                             lever_arm=h.lever_arm + rng.normal(0, errors.lever_arm_sigma, 3)))
    return Rig(rig.name, tuple(heads))


def approximate_block(truth: ImageBlock, exposures: list[Exposure], nominal_rig: Rig,
                      errors: NavErrors = NavErrors()) -> ImageBlock:
    """The block a user receives: poses from noisy GNSS/IMU through the nominal rig, with prior sigmas.

    ``truth`` supplies cameras and image ids/files; its ground points are not copied (see :func:`ground_points`).
    """
    rng = np.random.default_rng([errors.seed, 29])
    bias = rng.normal(0, errors.datum_bias_sigma, 3)
    block = ImageBlock(crs=truth.crs, image_root=truth.image_root)
    for cam in truth.cameras.values():
        block.add_camera(cam)
    block.rigs[nominal_rig.name] = nominal_rig
    sig_pos = np.asarray(errors.gnss_sigma, np.float64)
    sig_att = np.radians(np.sqrt(np.asarray(errors.imu_sigma_deg, np.float64) ** 2 + errors.boresight_sigma_deg ** 2))
    by_name = {ex.name: ex for ex in exposures}
    noisy = {}
    for ex in exposures:
        att = np.radians(rng.normal(0, 1, 3) * np.asarray(errors.imu_sigma_deg))
        noisy[ex.name] = replace(ex, center=ex.center + bias + rng.normal(0, 1, 3) * sig_pos,
                                 roll=ex.roll + att[0], pitch=ex.pitch + att[1], yaw=ex.yaw + att[2])
    for img in truth.images.values():
        ex = noisy[img.exposure] if img.exposure in by_name else None
        pose = image_pose(ex, nominal_rig.head(img.head)) if ex is not None else img.pose_approx
        block.add_image(Image(id=img.id, camera_id=img.camera_id, file=img.file, head=img.head, exposure=img.exposure,
                              time=img.time, pose_approx=pose, sigma_position=sig_pos.copy(),
                              sigma_attitude=sig_att.copy()))
    return block


def visible_in(block: ImageBlock, xyz_world: np.ndarray, scene, origin: np.ndarray, margin_px: float = 8.0,
               tolerance: float = 0.05) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per image: indices of points ``xyz_world : (n, 3)`` inside the image (``margin_px`` from the border) and
    not occluded (ray cast in the Open3D ``scene`` of local coordinates ``xyz - origin``), and their true
    pixel positions ``(k, 2)``."""
    import open3d as o3d

    out = {}
    for img in block.images.values():
        cam, pose = block.camera_of(img), img.pose_approx
        uv, depth = project(cam, pose, xyz_world)
        ok = (depth > 0) & cam.contains(np.nan_to_num(uv, nan=-1e9), margin=margin_px)
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            continue
        d = xyz_world[idx] - pose.C
        dist = np.linalg.norm(d, axis=1)
        rays = np.column_stack([np.tile(pose.C - origin, (len(idx), 1)), d / dist[:, None]]).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        vis = t >= dist - tolerance
        if vis.any():
            out[img.id] = (idx[vis], uv[idx[vis]])
    return out


def ground_points(truth: ImageBlock, names: list[str], xyz_true: np.ndarray, scene, origin: np.ndarray,
                  sigma_px: float = 0.3, survey_sigma: tuple[float, float, float] = (0.01, 0.01, 0.015),
                  check_every: int = 3, seed: int = 2) -> list[GroundPoint]:
    """Signalised control and check points: surveyed coordinates (true + survey noise) and image measurements
    (true projection + Gaussian noise ``sigma_px``) in every image that sees them unoccluded. Every
    ``check_every``-th point (2, 5, 8, ... counting from 0) is a check point."""
    rng = np.random.default_rng([seed, 3])
    survey = np.asarray(survey_sigma, np.float64)
    obs: dict[int, dict[str, np.ndarray]] = {i: {} for i in range(len(names))}
    for iid, (idx, uv) in visible_in(truth, xyz_true, scene, origin).items():
        for i, p in zip(idx, uv, strict=True):
            obs[int(i)][iid] = p + rng.normal(0, sigma_px, 2)
    pts = []
    for i, name in enumerate(names):
        kind = "check" if check_every and i % check_every == check_every - 1 else "control"
        pts.append(GroundPoint(name=name, xyz=xyz_true[i] + rng.normal(0, 1, 3) * survey, sigma=survey.copy(),
                               kind=kind, observations=obs[i], sigma_px=sigma_px))
    return pts


def coverage_map(block: ImageBlock, bbox: np.ndarray, cell: float, z_of, crs: str | None = None,
                 adjusted: bool = False) -> Raster:
    """Five-view coverage: per ground cell and view (``VIEWS`` order: nadir, north, east, south, west) the number
    of images whose frame contains the cell centre at ground height ``z_of(xy (n, 2)) -> (n,)``.

    Occlusion is ignored (this is the planning view). Returns a Raster ``(rows, cols, 5)`` int32.
    """
    xmin, ymin, xmax, ymax = (float(v) for v in bbox)
    cols, rows = max(1, round((xmax - xmin) / cell)), max(1, round((ymax - ymin) / cell))
    r = Raster(np.zeros((rows, cols, len(VIEWS)), np.int32), xmin, ymax, cell, crs or block.crs)
    xs, ys = r.cell_centers()
    gx, gy = np.meshgrid(xs, ys)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    xyz = np.column_stack([xy, z_of(xy)])
    flat = r.data.reshape(-1, len(VIEWS))
    for img in block.images.values():
        pose = img.pose_adjusted if adjusted else img.pose_approx
        if pose is None:
            continue
        cam = block.camera_of(img)
        uv, depth = project(cam, pose, xyz)
        inside = (depth > 0) & cam.contains(np.nan_to_num(uv, nan=-1e9))
        flat[inside, VIEWS.index(cardinal_view(pose.R))] += 1
    return r

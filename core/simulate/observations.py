"""Observation-only simulator for aerial triangulation: image measurements without rendering.

It produces what a bundle adjustment sees from a block of thousands of images in seconds: true and
navigation-grade (noisy) exterior orientations of a penta (Maltese-cross) camera flown in strips, tie points
on the surfaces of a city, their image measurements with Gaussian noise and a labelled fraction of blunders,
and ground control / check points with image measurements.

Surface model (stated simplification)
-------------------------------------
The city is a 2.5D height field evaluated analytically, so a block of any size costs no memory: a gently
undulating terrain with flat-roofed rectangular buildings, one per city block cell of ``block_size`` metres
(some cells are empty squares). Its parameters come from an integer hash of the cell index, so every call sees
the same city. Tie points lie on the terrain, on roofs and on facades (facade points carry their wall normal).

Visibility (stated approximation instead of full ray casting)
------------------------------------------------------------
A point is observed in an image when it projects inside the frame, faces the camera (facade points), and the
straight segment from the point towards the projection centre stays above the height field at samples every
``occlusion_step`` metres up to the highest roof. A detection probability ``p_detect`` thins the observations
as a feature matcher would. At 80/60 overlap a terrain point gets about 12 nadir rays.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model import CameraModel, GroundPoint, Image, ImageBlock, Pose, Rig, RigHead, TiePoints


@dataclass(frozen=True)
class CityModel:
    """The analytic city surface (see the module docstring). Units: metres."""

    ground_z: float = 100.0
    terrain_amplitude: float = 3.0
    block_size: float = 80.0
    street_width: float = 16.0
    min_height: float = 6.0
    max_height: float = 40.0
    empty_share: float = 0.2
    seed: int = 1

    def _cell_random(self, i: np.ndarray, j: np.ndarray, k: int) -> np.ndarray:
        """Uniform [0, 1) numbers from cell indices (deterministic hash), same shape as ``i``."""
        h = (i.astype(np.int64) * 73856093) ^ (j.astype(np.int64) * 19349663) ^ (self.seed * 83492791 + k * 2654435761)
        h = h & 0xFFFFFFFF
        h = (h ^ (h >> 16)) * 0x45D9F3B & 0xFFFFFFFF
        h = (h ^ (h >> 16)) * 0x45D9F3B & 0xFFFFFFFF
        h = h ^ (h >> 16)
        return (h & 0xFFFFFF) / float(0x1000000)

    def terrain(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bare-earth height at ``x, y`` (same shapes)."""
        return self.ground_z + self.terrain_amplitude * np.sin(x / 700.0) * np.cos(y / 530.0)

    def buildings(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, ...]:
        """Per cell ``(i, j)``: building ``x0, x1, y0, y1, roof_z`` (roof NaN for an empty cell)."""
        b, s = self.block_size, self.street_width / 2.0
        u = [self._cell_random(i, j, k) for k in range(5)]
        inner = b - 2 * s
        wx = inner * (0.45 + 0.55 * u[0])
        wy = inner * (0.45 + 0.55 * u[1])
        x0 = i * b + s + (inner - wx) * u[2]
        y0 = j * b + s + (inner - wy) * u[3]
        h = self.min_height + (self.max_height - self.min_height) * u[4] ** 1.5
        base = self.terrain((i + 0.5) * b, (j + 0.5) * b)
        roof = np.where(self._cell_random(i, j, 7) < self.empty_share, np.nan, base + h)
        return x0, x0 + wx, y0, y0 + wy, roof

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Surface height (roof or terrain) at ``x, y`` (same shapes)."""
        i = np.floor(x / self.block_size)
        j = np.floor(y / self.block_size)
        x0, x1, y0, y1, roof = self.buildings(i, j)
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1) & np.isfinite(roof)
        return np.where(inside, roof, self.terrain(x, y))

    @property
    def z_max(self) -> float:
        return self.ground_z + self.terrain_amplitude + self.max_height + 1.0

    def sample_points(self, rng: np.random.Generator, xmin: float, xmax: float, ymin: float, ymax: float,
                      density: float, facade_share: float) -> tuple[np.ndarray, np.ndarray]:
        """Random surface points: ``xyz (n, 3)`` and outward ``normal (n, 3)`` (zero for horizontal surfaces)."""
        area = (xmax - xmin) * (ymax - ymin)
        n_top = rng.poisson(density * area * (1.0 - facade_share))
        x = rng.uniform(xmin, xmax, n_top)
        y = rng.uniform(ymin, ymax, n_top)
        top = np.stack([x, y, self.height(x, y)], 1)
        n_fac = rng.poisson(density * area * facade_share)
        i = np.floor(rng.uniform(xmin, xmax, n_fac) / self.block_size)
        j = np.floor(rng.uniform(ymin, ymax, n_fac) / self.block_size)
        x0, x1, y0, y1, roof = self.buildings(i, j)
        ok = np.isfinite(roof)
        i, j, x0, x1, y0, y1, roof = (a[ok] for a in (i, j, x0, x1, y0, y1, roof))
        side = rng.integers(0, 4, len(i))
        t = rng.uniform(0.02, 0.98, len(i))
        fx = np.choose(side, [x0 + t * (x1 - x0), x1, x0 + t * (x1 - x0), x0])
        fy = np.choose(side, [y0, y0 + t * (y1 - y0), y1, y0 + t * (y1 - y0)])
        nrm = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])[side]
        zb = self.terrain(fx, fy)
        fz = zb + rng.uniform(0.05, 0.95, len(i)) * (roof - zb)
        xyz = np.concatenate([top, np.stack([fx, fy, fz], 1)])
        normal = np.concatenate([np.zeros_like(top), nrm])
        return xyz, normal


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
class PentaCamera:
    """A Maltese-cross camera: one nadir head and four heads tilted ``tilt_deg`` forward, backward, left and
    right. The rig (body) frame is the nadir camera's frame; image tops point forward."""

    width: int = 6000
    height: int = 4000
    f_nadir_px: float = 10000.0
    f_oblique_px: float = 14000.0
    tilt_deg: float = 45.0
    k1: float = -0.02
    k2: float = 0.005

    def cameras(self) -> list[CameraModel]:
        cx, cy = (self.width - 1) / 2.0, (self.height - 1) / 2.0
        out = [CameraModel(id="nadir", width=self.width, height=self.height, fx=self.f_nadir_px,
                           fy=self.f_nadir_px, cx=cx, cy=cy, k1=self.k1, k2=self.k2, name="penta nadir")]
        for h in ("forward", "backward", "left", "right"):
            out.append(CameraModel(id=h, width=self.width, height=self.height, fx=self.f_oblique_px,
                                   fy=self.f_oblique_px, cx=cx + 3.0, cy=cy - 2.0, k1=self.k1, k2=self.k2,
                                   name=f"penta {h}"))
        return out

    def rig(self) -> Rig:
        """Heads with ``sensor_from_rig`` built for a flight heading grid north (any heading gives the same)."""
        fwd, up = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
        right = np.cross(fwd, up)
        r_nadir = look_rotation(-up, -fwd)
        t = np.radians(self.tilt_deg)
        axes = {"nadir": -up, "forward": -up * np.cos(t) + fwd * np.sin(t),
                "backward": -up * np.cos(t) - fwd * np.sin(t), "left": -up * np.cos(t) - right * np.sin(t),
                "right": -up * np.cos(t) + right * np.sin(t)}
        heads = []
        for name, axis in axes.items():
            down = -up if name in ("forward", "backward") else -fwd
            if name == "nadir":
                down = -fwd
            r = look_rotation(axis, down)
            heads.append(RigHead(name=name, camera_id=name, sensor_from_rig=r @ r_nadir.T))
        return Rig(name="penta", heads=tuple(heads))


@dataclass(frozen=True)
class SimulationConfig:
    """What to simulate.

    Attributes
    ----------
    n_images : approximate total image count (5 per exposure)
    strips : number of flight strips (0: as many as make the block about square)
    flying_height : above the mean terrain, metres
    forward_overlap, side_overlap : of the nadir images
    tie_density : tie points per square metre of ground
    facade_share : share of tie points sampled on facades
    p_detect : probability that a visible point is measured in an image
    noise_px : standard deviation of image measurements (tie and ground points)
    blunder_fraction : share of tie observations replaced by gross errors of ``blunder_px`` (min, max) pixels
    gnss_sigma : (3,) GNSS centre noise, metres; gnss_bias : (3,) constant datum offset of the GNSS frame
    imu_sigma_deg : (3,) attitude noise about world X, Y, Z, degrees
    n_ground_points : control + check points, alternating (about half each)
    """

    n_images: int = 500
    strips: int = 0
    flying_height: float = 1000.0
    forward_overlap: float = 0.8
    side_overlap: float = 0.6
    tie_density: float = 0.0015
    facade_share: float = 0.15
    p_detect: float = 0.9
    noise_px: float = 0.3
    blunder_fraction: float = 0.03
    blunder_px: tuple[float, float] = (4.0, 40.0)
    gnss_sigma: tuple[float, float, float] = (0.05, 0.05, 0.08)
    gnss_bias: tuple[float, float, float] = (0.06, -0.04, 0.10)
    imu_sigma_deg: tuple[float, float, float] = (0.004, 0.004, 0.006)
    attitude_jitter_deg: float = 1.0
    n_ground_points: int = 50
    occlusion_step: float = 2.0
    seed: int = 7
    camera: PentaCamera = field(default_factory=PentaCamera)
    city: CityModel = field(default_factory=CityModel)


@dataclass(eq=False)
class SimulatedBlock:
    """A simulated block with its ground truth.

    Attributes
    ----------
    block : cameras, rig, images with ``pose_approx`` (navigation) and prior sigmas, ground points
    ties : tie observations (``obs_blunder`` = planted blunders, ``xyz`` NaN: not yet intersected)
    true_poses : image id -> true pose
    true_xyz : (n, 3) float64 true tie point coordinates
    gsd : nadir ground sample distance, metres
    """

    block: ImageBlock
    ties: TiePoints
    true_poses: dict[str, Pose]
    true_xyz: np.ndarray
    gsd: float
    config: SimulationConfig


def _flight_plan(cfg: SimulationConfig) -> tuple[np.ndarray, np.ndarray]:
    """Exposure centres ``(e, 3)`` and headings ``(e,)`` (radians, clockwise from north) of an about square
    block with strips along Y flown alternately north and south."""
    cam = cfg.camera
    gsd = cfg.flying_height / cam.f_nadir_px
    base = (1.0 - cfg.forward_overlap) * cam.height * gsd
    spacing = (1.0 - cfg.side_overlap) * cam.width * gsd
    n_exp = max(4, int(round(cfg.n_images / 5)))
    n_strips = cfg.strips or max(2, int(round(np.sqrt(n_exp * base / spacing))))
    per_strip = max(2, int(round(n_exp / n_strips)))
    z = cfg.city.ground_z + cfg.flying_height
    centres, headings = [], []
    for s in range(n_strips):
        ys = np.arange(per_strip) * base
        heading = 0.0
        if s % 2:
            ys = ys[::-1]
            heading = np.pi
        for y in ys:
            centres.append((s * spacing, y, z))
            headings.append(heading)
    return np.array(centres), np.array(headings)


def _rig_from_world(heading: float, jitter: np.ndarray) -> np.ndarray:
    """Nadir-camera (rig) rotation for a heading plus small attitude angles ``jitter (3,)`` radians."""
    from ..geometry.rotations import rotvec_to_matrix

    fwd = np.array([np.sin(heading), np.cos(heading), 0.0])
    r = look_rotation(np.array([0.0, 0.0, -1.0]), -fwd)
    return r @ rotvec_to_matrix(jitter).T


def _visible(city: CityModel, pose: Pose, xyz: np.ndarray, normal: np.ndarray, step: float) -> np.ndarray:
    """Occlusion test of points ``xyz (n, 3)`` seen from ``pose`` against the height field (see module doc)."""
    d = pose.C - xyz
    facing = (np.einsum("ij,ij->i", d, normal) > 0) | (np.abs(normal).sum(1) == 0)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    start = xyz + 0.3 * normal + 0.05 * d
    s_max = np.maximum(city.z_max - start[:, 2], 0.0) / np.maximum(d[:, 2], 1e-6)
    horiz = s_max * np.hypot(d[:, 0], d[:, 1])
    k = int(np.clip(np.ceil(horiz.max(initial=0.0) / step), 1, 60))
    ok = facing.copy()
    for m in range(1, k + 1):
        s = s_max * (m / k)
        p = start + d * s[:, None]
        ok &= p[:, 2] > city.height(p[:, 0], p[:, 1]) - 1e-3
    return ok


def simulate_block(cfg: SimulationConfig = SimulationConfig()) -> SimulatedBlock:
    """Simulate a penta-camera block with tie points, blunders, GNSS/IMU priors and ground points."""
    from ..geometry.projection import image_footprint, project
    from ..geometry.rotations import rotvec_to_matrix

    rng = np.random.default_rng(cfg.seed)
    cams = {c.id: c for c in cfg.camera.cameras()}
    rig = cfg.camera.rig()
    block = ImageBlock(crs="EPSG:32632")
    for c in cams.values():
        block.add_camera(c)
    block.rigs[rig.name] = rig
    offset = np.array([500000.0, 5400000.0, 0.0])
    centres, headings = _flight_plan(cfg)
    centres = centres + offset
    gsd = cfg.flying_height / cfg.camera.f_nadir_px
    sig_pos = np.asarray(cfg.gnss_sigma, np.float64)
    sig_att = np.radians(np.asarray(cfg.imu_sigma_deg, np.float64))
    true_poses: dict[str, Pose] = {}
    for e, (c, hd) in enumerate(zip(centres, headings)):
        jitter = np.radians(cfg.attitude_jitter_deg) * rng.standard_normal(3) * np.array([1.0, 1.0, 2.0])
        r_rig = _rig_from_world(hd, jitter)
        c_true = c + rng.normal(0.0, 2.0, 3)
        err_c = rng.normal(0.0, sig_pos) + np.asarray(cfg.gnss_bias)
        err_r = rotvec_to_matrix(rng.normal(0.0, sig_att))
        for h in rig.heads:
            r_true = h.sensor_from_rig @ r_rig
            iid = f"e{e:05d}_{h.name}"
            true_poses[iid] = Pose(r_true, c_true)
            block.add_image(Image(id=iid, camera_id=h.camera_id, head=h.name, exposure=f"e{e:05d}",
                                  pose_approx=Pose(h.sensor_from_rig @ r_rig @ err_r.T, c_true + err_c),
                                  sigma_position=sig_pos.copy(), sigma_attitude=sig_att.copy()))
    ids = list(block.images)

    # tie points bucketed in a grid for per-image look-up
    z_ref = cfg.city.ground_z
    # the city extends beyond the flight area as far as the oblique image centres reach
    reach = cfg.flying_height * np.tan(np.radians(cfg.camera.tilt_deg))
    lo = centres[:, :2].min(0) - max(reach, 0.5 * cfg.camera.width * gsd)
    hi = centres[:, :2].max(0) + max(reach, 0.5 * cfg.camera.width * gsd)
    xyz, normal = cfg.city.sample_points(rng, lo[0], hi[0], lo[1], hi[1], cfg.tie_density, cfg.facade_share)
    bucket = 100.0
    bij = np.floor((xyz[:, :2] - lo) / bucket).astype(np.int64)
    nbx = int(bij[:, 0].max(initial=0)) + 1
    key = bij[:, 1] * nbx + bij[:, 0]
    order = np.argsort(key, kind="stable")
    starts = np.searchsorted(key[order], np.arange(nbx * (int(bij[:, 1].max(initial=0)) + 2)))

    obs_track, obs_image, obs_uv = [], [], []
    for k, iid in enumerate(ids):
        pose, cam = true_poses[iid], cams[block.images[iid].camera_id]
        fp = image_footprint(cam, pose, z_ref)
        fp = np.concatenate([fp, image_footprint(cam, pose, cfg.city.z_max)])
        b0 = np.clip(np.floor((fp.min(0) - lo) / bucket).astype(int), 0, None)
        b1 = np.floor((fp.max(0) - lo) / bucket).astype(int)
        cand = []
        for by in range(b0[1], min(b1[1], int(bij[:, 1].max(initial=0))) + 1):
            a = by * nbx + b0[0]
            b = by * nbx + min(b1[0], nbx - 1) + 1
            cand.append(order[starts[a]:starts[b]])
        cand = np.concatenate(cand) if cand else np.zeros(0, np.int64)
        uv, depth = project(cam, pose, xyz[cand])
        inside = (depth > 0) & cam.contains(uv, margin=2.0)
        cand, uv = cand[inside], uv[inside]
        vis = _visible(cfg.city, pose, xyz[cand], normal[cand], cfg.occlusion_step)
        keep = vis & (rng.random(len(cand)) < cfg.p_detect)
        obs_track.append(cand[keep])
        obs_image.append(np.full(keep.sum(), k, np.int64))
        obs_uv.append(uv[keep])
    track = np.concatenate(obs_track)
    image = np.concatenate(obs_image)
    uv = np.concatenate(obs_uv)
    # keep multi-ray points only, renumber
    counts = np.bincount(track, minlength=len(xyz))
    used = counts >= 2
    sel = used[track]
    track, image, uv = track[sel], image[sel], uv[sel]
    new_index = np.cumsum(used) - 1
    track = new_index[track]
    true_xyz = xyz[used]
    order = np.lexsort((image, track))
    track, image, uv = track[order], image[order], uv[order]
    uv = uv + rng.normal(0.0, cfg.noise_px, uv.shape)
    blunder = rng.random(len(track)) < cfg.blunder_fraction
    ang = rng.uniform(0, 2 * np.pi, blunder.sum())
    mag = rng.uniform(cfg.blunder_px[0], cfg.blunder_px[1], blunder.sum())
    uv[blunder] += np.stack([np.cos(ang), np.sin(ang)], 1) * mag[:, None]
    ties = TiePoints(xyz=np.full((len(true_xyz), 3), np.nan), obs_track=track, obs_image=image, obs_uv=uv,
                     image_ids=ids, obs_blunder=blunder)

    # ground control and check points on open terrain, on a jittered grid
    n_gp = cfg.n_ground_points
    if n_gp > 0:
        inner_lo, inner_hi = centres[:, :2].min(0), centres[:, :2].max(0)
        g = int(np.ceil(np.sqrt(n_gp)))
        gx, gy = np.meshgrid(np.linspace(0.05, 0.95, g), np.linspace(0.05, 0.95, g))
        pts = inner_lo + np.stack([gx.ravel(), gy.ravel()], 1)[:n_gp] * (inner_hi - inner_lo)
        for p, (x, y) in enumerate(pts):
            for _ in range(50):  # move off roofs onto the terrain
                if abs(cfg.city.height(np.array([x]), np.array([y]))[0] - cfg.city.terrain(x, y)) < 1e-6:
                    break
                x, y = x + rng.uniform(-15, 15), y + rng.uniform(-15, 15)
            gp_xyz = np.array([x, y, cfg.city.terrain(x, y) + 0.1])
            obs = {}
            for iid in ids:
                pose, cam = true_poses[iid], cams[block.images[iid].camera_id]
                uvp, depth = project(cam, pose, gp_xyz[None])
                if depth[0] > 0 and cam.contains(uvp, margin=5.0)[0] and _visible(
                        cfg.city, pose, gp_xyz[None], np.zeros((1, 3)), cfg.occlusion_step)[0]:
                    obs[iid] = uvp[0] + rng.normal(0.0, cfg.noise_px, 2)
            block.add_ground_point(GroundPoint(name=f"GP{p:03d}", xyz=gp_xyz, sigma=np.array([0.02, 0.02, 0.03]),
                                               kind="control" if p % 2 == 0 else "check", observations=obs,
                                               sigma_px=cfg.noise_px))
    return SimulatedBlock(block=block, ties=ties, true_poses=true_poses, true_xyz=true_xyz, gsd=gsd, config=cfg)

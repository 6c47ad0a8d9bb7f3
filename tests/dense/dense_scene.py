"""A small synthetic scene with known geometry for the dense and surface tests.

A textured ground plane with a few box buildings (and one "tree" box painted green), rendered by Open3D ray
casting into pinhole cameras (nadir and 45 deg obliques) at UTM-size coordinates. The texture is a sum of random
plane waves in the surface's own coordinates, so stereo matching has structure everywhere. Truth: the true DSM
by vertical ray casting, the terrain height, the box outlines.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from oblique_city.core.model import CameraModel, Image, ImageBlock, Pose

ORIGIN = np.array([500000.0, 5400000.0, 0.0])
GROUND_Z = 100.0
# (x0, y0, x1, y1, height above ground, is_tree), local metres
BOXES = [(-30.0, -25.0, -5.0, 5.0, 18.0, False), (10.0, -30.0, 35.0, -10.0, 10.0, False),
         (5.0, 10.0, 30.0, 30.0, 24.0, False), (-18.0, 9.0, -8.0, 19.0, 8.0, True)]


def _box(x0, y0, x1, y1, z0, z1) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_box(x1 - x0, y1 - y0, z1 - z0)
    m.translate((x0, y0, z0))
    return m


@dataclass
class Scene:
    """The ray-casting scene in local coordinates (world = local + ORIGIN)."""

    rc: o3d.t.geometry.RaycastingScene
    tree_ids: set

    @classmethod
    def build(cls) -> Scene:
        rc = o3d.t.geometry.RaycastingScene()
        ground = _box(-150.0, -150.0, 150.0, 150.0, GROUND_Z - 1.0, GROUND_Z)
        rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(ground))
        trees = set()
        rng = np.random.default_rng(3)
        for x0, y0, x1, y1, h, tree in BOXES:
            if not tree:
                rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(_box(x0, y0, x1, y1, GROUND_Z, GROUND_Z + h)))
                continue
            # a crown: 5 x 5 columns of random height, rough as vegetation is
            xs, ys = np.linspace(x0, x1, 6), np.linspace(y0, y1, 6)
            for i in range(5):
                for j in range(5):
                    top = GROUND_Z + h + rng.uniform(-1.5, 1.5)
                    box = _box(xs[i], ys[j], xs[i + 1], ys[j + 1], GROUND_Z, top)
                    trees.add(rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box)))
        return cls(rc, trees)

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> dict:
        rays = np.concatenate([origins, dirs], 1).astype(np.float32)
        return {k: v.numpy() for k, v in self.rc.cast_rays(o3d.core.Tensor(rays)).items()}

    def true_dsm(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Surface height at local ``x, y`` (same shape)."""
        o = np.stack([x.ravel(), y.ravel(), np.full(x.size, 500.0)], 1)
        hit = self.cast(o, np.tile([0.0, 0.0, -1.0], (x.size, 1)))
        return (500.0 - hit["t_hit"].astype(np.float64)).reshape(x.shape)


_rng = np.random.default_rng(7)
_FREQ = np.geomspace(0.3, 5.0, 48)
_ANGLE = _rng.uniform(0, 2 * np.pi, 48)
_WAVES = [(f * np.array([np.cos(t), np.sin(t)]), _rng.uniform(0, 2 * np.pi), f ** -0.6)
          for f, t in zip(_FREQ, _ANGLE)]
_NORM = np.sqrt(0.5 * sum(w[2] ** 2 for w in _WAVES))


def texture(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Grey texture in [0, 1] of surface coordinates ``a, b`` (metres): random plane waves in all directions,
    amplitude falling with frequency (blobs of every size, no dominant direction)."""
    a, b = np.where(np.isfinite(a), a, 0.0), np.where(np.isfinite(b), b, 0.0)  # rays into the sky
    s = sum(amp * np.sin(k[0] * a + k[1] * b + p) for k, p, amp in _WAVES) / _NORM
    return 0.5 + 0.5 * np.tanh(s / 1.5)


def look_at(c_local: np.ndarray, target_local: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``cam_from_world`` (OpenCV axes) looking from ``c`` at ``target`` with the image up towards ``up``."""
    z = target_local - c_local
    z = z / np.linalg.norm(z)
    u = np.asarray(up, float)
    y = -(u - (u @ z) * z)
    y /= np.linalg.norm(y)
    return np.stack([np.cross(y, z), y, z])


def render(scene: Scene, cam: CameraModel, pose_local: Pose, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """BGR uint8 image (h, w, 3) and z-depth (h, w) of a local-frame pose."""
    s = supersample
    uu, vv = np.meshgrid((np.arange(cam.width * s) + 0.5) / s - 0.5, (np.arange(cam.height * s) + 0.5) / s - 0.5)
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    xy = cam.pixel_to_normalized(uv)
    d_cam = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    d = d_cam @ pose_local.R
    hit = scene.cast(np.broadcast_to(pose_local.C, d.shape), d)
    t = hit["t_hit"].astype(np.float64)
    rgb = _colour(scene, hit, pose_local.C + d * t[:, None])
    img = (rgb.reshape(cam.height, s, cam.width, s, 3).mean(axis=(1, 3)) * 255).clip(0, 255).astype(np.uint8)
    depth = (d_cam[:, 2] * t).reshape(cam.height * s, cam.width * s)[::s, ::s]
    return np.ascontiguousarray(img[..., ::-1]), depth


def _colour(scene: Scene, hit: dict, p: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] ``(n, 3)`` of ray hits at local points ``p (n, 3)`` (sky grey)."""
    n = hit["primitive_normals"]
    ax = np.argmax(np.abs(n), axis=1)
    a = np.where(ax == 2, p[:, 0], np.where(ax == 0, p[:, 1], p[:, 0]))
    b = np.where(ax == 2, p[:, 1], p[:, 2])
    g = texture(a, b)
    shade = 0.55 + 0.45 * np.clip(n @ np.array([0.3, -0.4, 0.85]), 0, 1)
    tree = np.isin(hit["geometry_ids"], list(scene.tree_ids))
    roof = (ax == 2) & (p[:, 2] > GROUND_Z + 1) & ~tree
    rgb = np.stack([g, g, g], 1) * shade[:, None]
    rgb[tree] *= np.array([0.35, 1.0, 0.3])
    rgb[roof] *= np.array([1.0, 0.6, 0.5])
    rgb[~np.isfinite(hit["t_hit"])] = 0.7
    return rgb


def reference_ortho(scene: Scene, x_local: np.ndarray, y_local: np.ndarray, supersample: int = 3) -> np.ndarray:
    """The ideal true orthophoto (vertical rays, ``supersample``^2 per cell) at local cell centres
    ``(rows, cols)`` on a regular grid: RGB uint8."""
    cell = abs(float(x_local[0, 1] - x_local[0, 0]))
    off = ((np.arange(supersample) + 0.5) / supersample - 0.5) * cell
    acc = np.zeros((*x_local.shape, 3))
    for dx in off:
        for dy in off:
            n = x_local.size
            o = np.stack([x_local.ravel() + dx, y_local.ravel() + dy, np.full(n, 500.0)], 1)
            hit = scene.cast(o, np.tile([0.0, 0.0, -1.0], (n, 1)))
            acc += _colour(scene, hit, o - np.outer(hit["t_hit"], [0.0, 0.0, 1.0])).reshape(acc.shape)
    return (acc / supersample ** 2 * 255).clip(0, 255).astype(np.uint8)


def camera(width: int = 400, height: int = 300, f: float = 500.0) -> CameraModel:
    return CameraModel(id="cam", width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2 + 3.2,
                       cy=(height - 1) / 2 - 2.1, k1=-0.02, k2=0.004)


def nadir_poses(height: float = 160.0, spacing: float = 40.0) -> list[Pose]:
    """Local poses of a 3 x 2 nadir grid (image up = north)."""
    out = []
    for y in (-spacing / 2, spacing / 2):
        for x in (-spacing, 0.0, spacing):
            c = np.array([x, y, GROUND_Z + height])
            out.append(Pose(look_at(c, c - [0, 0, 1], up=(0, 1, 0)), c))
    return out


def oblique_poses(look: str = "north", height: float = 160.0, tilt_deg: float = 45.0,
                  spacing: float = 40.0) -> list[Pose]:
    """Local poses of three obliques in one strip across the look direction, aimed at the scene centre."""
    fwd = {"north": np.array([0, 1.0, 0]), "east": np.array([1.0, 0, 0]), "south": np.array([0, -1.0, 0]),
           "west": np.array([-1.0, 0, 0])}[look]
    side = np.array([fwd[1], -fwd[0], 0.0])
    back = height / np.tan(np.radians(tilt_deg))
    out = []
    for k in (-1, 0, 1):
        c = np.array([0.0, 0.0, GROUND_Z + height]) - fwd * back + side * k * spacing
        target = c + fwd * back
        target[2] = GROUND_Z
        out.append(Pose(look_at(c, target), c))
    return out


def make_block(folder: Path, poses_local: list[Pose], cam: CameraModel | None = None) -> tuple[ImageBlock, Scene]:
    """Render the poses into ``folder`` and return the block (world = local + ORIGIN, poses as adjusted)."""
    scene = Scene.build()
    cam = cam or camera()
    block = ImageBlock(crs="EPSG:32632", image_root=str(folder))
    block.add_camera(cam)
    for i, p in enumerate(poses_local):
        img, _ = render(scene, cam, p)
        path = folder / f"img{i:02d}.png"
        cv2.imwrite(str(path), img)
        pose_world = Pose(p.R, p.C + ORIGIN)
        block.add_image(Image(id=f"img{i:02d}", camera_id=cam.id, file=path.name, pose_approx=pose_world,
                              pose_adjusted=pose_world))
    return block, scene

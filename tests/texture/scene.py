"""A small synthetic scene with a known answer: two box buildings in UTM coordinates, a smooth colour pattern
that is a function of the world position, and pinhole cameras with Brown distortion rendered by ray casting.

The small box stands in front of the large one's south wall and hides part of it from the first camera; the
second camera sees that part. The occluder is painted a flat green that appears nowhere in the pattern.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from oblique_city.core.buildings.model import BuildingModel, Surface
from oblique_city.core.model import CameraModel, Image, ImageBlock, Pose

OFFSET = np.array([500000.0, 5400000.0, 100.0])
GREEN = np.array([20.0, 200.0, 20.0])


def pattern(xyz: np.ndarray) -> np.ndarray:
    """The true colour (n, 3) float64 (0-255) of the large building and the ground at world points (n, 3)."""
    p = np.asarray(xyz, np.float64) - OFFSET
    r = 128 + 90 * np.sin(2 * np.pi * (p[:, 0] + p[:, 2]) / 1.7)
    g = 120 + 70 * np.sin(2 * np.pi * (p[:, 1] - 0.5 * p[:, 2] + 0.3 * p[:, 0]) / 1.1)
    b = 128 + 90 * np.sin(2 * np.pi * (0.6 * p[:, 0] + 0.8 * p[:, 1] + p[:, 2]) / 2.3)
    return np.stack([r, np.minimum(g, 150.0), b], axis=1)


def box(bid: str, x0: float, y0: float, x1: float, y1: float, h: float) -> BuildingModel:
    """A flat-roofed box over ``[x0, x1] x [y0, y1]`` (local metres), ``h`` high, in world coordinates."""
    v = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0],
                  [x0, y0, h], [x1, y0, h], [x1, y1, h], [x0, y1, h]], np.float64) + OFFSET
    rings = [("ground", (0, 3, 2, 1)), ("wall", (0, 1, 5, 4)), ("wall", (1, 2, 6, 5)), ("wall", (2, 3, 7, 6)),
             ("wall", (3, 0, 4, 7)), ("roof", (4, 5, 6, 7))]
    surfaces = [Surface(f"{bid}_{k}_{i}", k, r) for i, (k, r) in enumerate(rings)]
    return BuildingModel(bid, v, surfaces, "2d", "", v[:4, :2].copy(), np.zeros(4),
                         np.array([[0.0, 0.0, 1.0, -(OFFSET[2] + h)]]), {"closed": True})


def buildings() -> list[BuildingModel]:
    """The large building B0001 (10 x 8 x 6 m) and the occluder B0002 in front of its south wall."""
    return [box("B0001", 0.0, 0.0, 10.0, 8.0, 6.0), box("B0002", 2.0, -4.0, 5.0, -3.0, 5.0)]


def look_at(centre: np.ndarray, target: np.ndarray) -> Pose:
    """OpenCV pose at ``centre`` looking at ``target`` with image x towards world east-ish."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose(np.stack([x, y, z]), centre)


CAMERA = CameraModel(id="cam", width=800, height=600, fx=900.0, fy=900.0, cx=401.7, cy=297.2, k1=-0.08, k2=0.02,
                     p1=3e-4, p2=-2e-4)
VIEWS = {"south": (np.array([5.0, -32.0, 28.0]), 1.0), "southwest": (np.array([-16.0, -26.0, 24.0]), 1.25),
         "nadir": (np.array([5.0, 2.0, 60.0]), 0.9)}
"""Camera centre (local) and the exposure gain of each image."""


def render(models: list[BuildingModel], pose: Pose, gain: float) -> np.ndarray:
    """Ray-cast image (h, w, 3) uint8 of the scene (the ground is a plane at the offset height with the
    pattern)."""
    import open3d as o3d

    from oblique_city.core.geometry.projection import pixel_rays

    scene = o3d.t.geometry.RaycastingScene()
    owner = []
    for i, b in enumerate(models):
        v, t, _ = b.triangles()
        m = o3d.t.geometry.TriangleMesh()
        m.vertex.positions = o3d.core.Tensor((v - OFFSET).astype(np.float32))
        m.triangle.indices = o3d.core.Tensor(t.astype(np.int32))
        scene.add_triangles(m)
        owner.append(np.full(len(t), i))
    gv = np.array([[-200, -200, 0], [200, -200, 0], [200, 200, 0], [-200, 200, 0]], np.float32)
    g = o3d.t.geometry.TriangleMesh()
    g.vertex.positions = o3d.core.Tensor(gv)
    g.triangle.indices = o3d.core.Tensor(np.array([[0, 1, 2], [0, 2, 3]], np.int32))
    scene.add_triangles(g)
    vv, uu = np.mgrid[0:CAMERA.height, 0:CAMERA.width]
    d = pixel_rays(CAMERA, pose, np.column_stack([uu.ravel(), vv.ravel()]).astype(np.float64))
    rays = np.concatenate([np.tile(pose.C - OFFSET, (len(d), 1)), d], axis=1).astype(np.float32)
    r = scene.cast_rays(o3d.core.Tensor(rays))
    t = r["t_hit"].numpy().astype(np.float64)
    geom = r["geometry_ids"].numpy()
    col = np.full((len(t), 3), 90.0)
    hit = np.isfinite(t)
    # recompute the hit point in float64 from the float32 distance (sub-millimetre here)
    xyz = pose.C + d * t[:, None]
    col[hit] = pattern(xyz[hit])
    col[hit & (geom == 1)] = GREEN
    img = np.clip(np.rint(col * gain), 0, 255).astype(np.uint8)
    return img.reshape(CAMERA.height, CAMERA.width, 3)


def make_block(folder: str | Path, views: tuple[str, ...] = ("south", "southwest", "nadir")) -> ImageBlock:
    """Render the chosen views into ``folder`` and return the block (absolute image paths)."""
    import cv2

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    block = ImageBlock(crs="EPSG:25832")
    block.add_camera(CAMERA)
    models = buildings()
    for name in views:
        c, gain = VIEWS[name]
        target = np.array([5.0, 0.0, 2.0]) if name != "nadir" else np.array([5.0, 4.0, 0.0])
        pose = look_at(c + OFFSET, target + OFFSET)
        path = folder / f"{name}.png"
        cv2.imwrite(str(path), render(models, pose, gain)[:, :, ::-1])
        block.add_image(Image(id=name, camera_id="cam", file=str(path), pose_approx=pose))
    return block

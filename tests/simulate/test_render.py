"""Rendered images agree with the geometry: targets project where they are drawn, depths lie on the GT surfaces."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.geometry.projection import backproject_depth, intersect_with_plane_z, project
from oblique_city.core.geometry.rotations import mount_rotation, ypr_to_cam_from_world
from oblique_city.core.model import CameraModel, Pose
from oblique_city.core.simulate.city import SEMANTIC
from oblique_city.core.simulate.render import DEFAULT_HEADS

CAM = CameraModel("t", 640, 480, 900.0, 900.0, 322.7, 236.4, k1=-0.06, k2=0.02, k3=0.0, p1=3e-4, p2=-2e-4)


def _pose_seeing(xyz: np.ndarray, tilt: float, azimuth: float, dist: float, uv_target: tuple[float, float]) -> Pose:
    """A camera tilted ``tilt`` deg looking towards ``azimuth``, placed so ``xyz`` lands near ``uv_target``."""
    r = ypr_to_cam_from_world(np.radians(azimuth), 0.0, 0.0, mount_rotation(tilt, 0.0))
    ray_cam = np.array([(uv_target[0] - CAM.cx) / CAM.fx, (uv_target[1] - CAM.cy) / CAM.fy, 1.0])
    ray_w = r.T @ (ray_cam / np.linalg.norm(ray_cam))
    return Pose(r, xyz - dist * ray_w)


def _disc_centroid(rgb: np.ndarray, pose: Pose, xyz: np.ndarray, uv0: np.ndarray) -> np.ndarray:
    """Intensity-weighted centroid of the white disc: pixels whose ground point is within 0.68 m of the target
    (inside its black square), weights above the black level."""
    gray = rgb.astype(np.float64).mean(2)
    u0, v0 = np.round(uv0).astype(int)
    vv, uu = np.mgrid[v0 - 25:v0 + 26, u0 - 25:u0 + 26]
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(np.float64)
    g = intersect_with_plane_z(CAM, pose, uv, float(xyz[2]))
    near = np.linalg.norm(g[:, :2] - xyz[:2], axis=1) < 0.68
    val = gray[vv.ravel(), uu.ravel()][near]
    black, white = np.percentile(val, 5), val.max()
    w = np.clip((val - black) / (white - black) - 0.05, 0, None)
    return (uv[near] * w[:, None]).sum(0) / w.sum()


@pytest.mark.parametrize("tilt,azimuth,dist,uv_target", [
    (0.0, 0.0, 85.0, (560.0, 410.0)),      # nadir, near the lower-right corner (strong distortion)
    (45.0, 0.0, 120.0, (90.0, 70.0)),       # looking north, upper-left corner
    (45.0, 250.0, 110.0, (330.0, 240.0)),   # looking west-south-west, centre
])
def test_targets_project_onto_their_drawn_centres(city, renderer, tilt, azimuth, dist, uv_target):
    errs = []
    for k in (0, 4, 8):
        xyz = city.targets[k]
        pose = _pose_seeing(xyz, tilt, azimuth, dist, uv_target)
        uv, _ = project(CAM, pose, xyz[None])
        rgb, _ = renderer.render(CAM, pose, "nadir", seed=k)
        c = _disc_centroid(rgb, pose, xyz, uv[0])
        errs.append(np.linalg.norm(c - uv[0]))
    assert max(errs) < 0.1, errs  # the issue asks for < 0.5 px; analytic edge coverage gives ~0.03 px


def test_supersampled_image_is_not_shifted(city):
    """With 8 jittered rays per pixel (the same sub-pixel offsets for every pixel) the target is still drawn
    where it projects: the offsets average to zero (seed 0 drew a mean of (0.10, -0.08) px before)."""
    from oblique_city.core.simulate.render import RenderConfig, Renderer

    fine = Renderer(city, RenderConfig(samples=8))
    errs = []
    for k in (0, 4):
        xyz = city.targets[k]
        pose = _pose_seeing(xyz, 0.0, 0.0, 85.0, (330.0, 240.0))
        uv, _ = project(CAM, pose, xyz[None])
        rgb, _ = fine.render(CAM, pose, "nadir", seed=k)
        errs.append(np.linalg.norm(_disc_centroid(rgb, pose, xyz, uv[0]) - uv[0]))
    assert max(errs) < 0.05, errs


def test_texture_mip_levels_show_the_surface_in_place():
    """A coarser mip level of the surface texture is the box-filtered fine texture at the same place: the best
    alignment along u is at zero lag for levels 1-3 (before the half-texel terms: 0.5, 1.75 and 4.0 texels, so a
    far oblique view saw the ground texture up to 0.5 m away from where a near view saw it)."""
    from oblique_city.core.simulate.render import _NoiseTexture

    tex = _NoiseTexture()
    u = np.arange(0.0, 400.0, 0.25)
    v = np.full_like(u, 100.3)
    lags = np.arange(-40, 41)                       # quarter texels
    for level in (1, 2, 3):
        k = 2 ** level
        coarse = tex.sample(u, v, np.full(len(u), float(k)))[:, 0]
        offs = np.arange(k) - (k - 1) / 2.0
        box = sum(tex.sample(u + du, v + dv, np.ones(len(u)))[:, 0] for du in offs for dv in offs) / k ** 2
        cc = [np.corrcoef(np.roll(coarse, lag)[50:-50], box[50:-50])[0, 1] for lag in lags]
        assert lags[int(np.argmax(cc))] == 0 and max(cc) > 0.95, (level, lags[int(np.argmax(cc))] * 0.25)


def test_depth_lies_on_ground_truth_surfaces(city, renderer):
    b = city.buildings[8]  # the church: gabled nave and a pyramid tower
    target = np.array([*b.center, b.ground_z + 5.0])
    pose = _pose_seeing(target, 45.0, 30.0, 140.0, (320.0, 240.0))
    depth, ids = renderer.trace(CAM, pose)
    vv, uu = np.mgrid[0:CAM.height, 0:CAM.width]
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(np.float64)
    hit = ids.ravel() >= 0
    xyz = backproject_depth(CAM, pose, uv[hit], depth.ravel()[hit])
    tri = ids.ravel()[hit]
    sem = city.semantic[tri]
    ground = sem <= SEMANTIC["street"]
    assert ground.sum() > 50000
    np.testing.assert_allclose(xyz[ground, 2], city.terrain_z(xyz[ground, :2]), atol=3e-3)
    roof_px = 0
    for bb in city.buildings:
        sel = (sem == SEMANTIC["roof"]) & (city.building[tri] == bb.id)
        if not sel.any():
            continue
        planes = [p for p in bb.roof_planes if p["kind"] == "roof"]
        dist = np.min([np.abs(xyz[sel] @ p["normal"] - p["d"]) for p in planes], axis=0)
        assert dist.max() < 3e-3, bb.name
        roof_px += int(sel.sum())
    assert roof_px > 3000
    # the rendered image's depth output is the same z-depth, and it re-projects onto its own pixels
    _, z = renderer.render(CAM, pose, "forward", depth=True)
    np.testing.assert_array_equal(z, depth)
    uvp, zp = project(CAM, pose, xyz[::97])
    np.testing.assert_allclose(uvp, uv[hit][::97], atol=1e-3)
    np.testing.assert_allclose(zp, depth.ravel()[hit][::97], rtol=1e-6)


def test_render_is_deterministic_and_heads_differ(city, renderer):
    xyz = city.targets[4]
    pose = _pose_seeing(xyz, 0.0, 0.0, 150.0, (320.0, 240.0))
    a, _ = renderer.render(CAM, pose, "nadir", seed=3)
    b, _ = renderer.render(CAM, pose, "nadir", seed=3)
    c, _ = renderer.render(CAM, pose, "nadir", seed=4)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert abs(a.astype(float).mean() - c.astype(float).mean()) < 0.2
    r, _ = renderer.render(CAM, pose, "right", seed=3)
    centre = (slice(180, 300), slice(240, 400), 1)  # green channel: same tint, vignetting negligible
    ratio = (r[centre].astype(float).mean() - 2.0) / (a[centre].astype(float).mean() - 2.0)
    expected = (DEFAULT_HEADS["right"].gain / DEFAULT_HEADS["nadir"].gain) ** (1 / 2.2)
    assert abs(ratio - expected) < 0.006
    # textures have structure for matching: local contrast on the ground and roofs
    gray = a.astype(float).mean(2)
    assert np.std(np.diff(gray, axis=1)) > 3.0


def test_twelve_bit_render_is_the_eight_bit_picture_on_a_finer_scale(city, renderer):
    """``bits=12``: uint16 values up to 4095 (as aerial cameras deliver them) that read back (:mod:`..io.photos`)
    as the 8-bit render of the same seed within one level; the noise is the same in 8-bit levels."""
    from dataclasses import replace

    from oblique_city.core.io.photos import to_8bit
    from oblique_city.core.simulate.render import Renderer

    pose = _pose_seeing(city.targets[4], 30.0, 120.0, 150.0, (320.0, 240.0))
    eight, _ = renderer.render(CAM, pose, "left", seed=5)
    deep, _ = Renderer(city, replace(renderer.config, bits=12)).render(CAM, pose, "left", seed=5)
    assert deep.dtype == np.uint16 and 2048 <= deep.max() <= 4095
    assert np.abs(to_8bit(deep).astype(int) - eight).max() <= 1

"""Fixtures for the block format tests: a multi-camera oblique block with ground points, and block comparison."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.geometry.projection import project
from oblique_city.core.geometry.rotations import opk_to_cam_from_world
from oblique_city.core.model import CameraModel, GroundPoint, Image, ImageBlock, Pose


@pytest.fixture
def oblique_block(camera: CameraModel) -> ImageBlock:
    """Two cameras (nadir with distortion, oblique without), 8 images at UTM coordinates, 3 ground points."""
    rng = np.random.default_rng(42)
    block = ImageBlock(crs="EPSG:32632")
    block.add_camera(camera)
    block.add_camera(CameraModel(id="obl", width=1000, height=750, fx=2100.0, fy=2100.0, cx=499.5, cy=374.5,
                                 pixel_size_mm=0.004))
    for i in range(8):
        tilt = 0.0 if i < 4 else np.radians(45.0)
        r = opk_to_cam_from_world(tilt + rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02),
                                  rng.uniform(-np.pi, np.pi))
        c = (500000.0 + 123.456789 * i, 5400000.0 + rng.uniform(-50, 50), 800.0 + rng.uniform(-5, 5))
        block.add_image(Image(id=f"img{i}", camera_id="cam" if i < 4 else "obl", file=f"img{i}.jpg",
                              pose_approx=Pose(r, c), sigma_position=np.array([0.05, 0.05, 0.1]),
                              sigma_attitude=np.radians([0.005, 0.005, 0.008])))
    for j, kind in enumerate(("control", "control", "check")):
        block.add_ground_point(GroundPoint(name=f"P{j}", xyz=np.array([500150.0 + 40 * j, 5400010.0 - 15 * j,
                                                                       102.25]),
                                           sigma=np.array([0.02, 0.02, 0.04]), kind=kind))
    for g in block.ground_points.values():
        for img in list(block.images.values())[:4]:
            uv, _ = project(block.camera_of(img), img.pose, g.xyz[None])
            if block.camera_of(img).contains(uv)[0]:
                g.observations[img.id] = uv[0]
    return block


def _world_points(block: ImageBlock) -> np.ndarray:
    rng = np.random.default_rng(3)
    c = block.centers()
    lo, hi = np.nanmin(c, axis=0) - [300, 300, 0], np.nanmax(c, axis=0) + [300, 300, 0]
    return np.column_stack([rng.uniform(lo[0], hi[0], 400), rng.uniform(lo[1], hi[1], 400),
                            rng.uniform(50.0, 150.0, 400)])


@pytest.fixture
def same_block():
    """A checker: same cameras, images, poses (to tol_m / tol_rad), ground points, and equal projections."""

    def check(a: ImageBlock, b: ImageBlock, tol_m: float = 1e-9, tol_rad: float = 1e-12,
              tol_px: float = 1e-6, ground_points: bool = True, camera_ids: dict | None = None) -> None:
        camera_ids = camera_ids or {k: k for k in a.cameras}
        assert a.crs == b.crs
        assert set(a.images) == set(b.images)
        for cid, ca in a.cameras.items():
            cb = b.cameras[camera_ids[cid]]
            assert (ca.width, ca.height) == (cb.width, cb.height)
            for k in ("fx", "fy", "cx", "cy"):
                assert abs(getattr(ca, k) - getattr(cb, k)) < 1e-9, k
            for k in ("k1", "k2", "k3", "p1", "p2"):
                assert abs(getattr(ca, k) - getattr(cb, k)) < 1e-15, k
        xyz = _world_points(a)
        for iid, ia in a.images.items():
            ib = b.images[iid]
            assert camera_ids[ia.camera_id] == ib.camera_id
            pa, pb = ia.pose, ib.pose
            assert np.abs(pa.C - pb.C).max() <= tol_m, (iid, pa.C - pb.C)
            # element differences (not arccos of the trace, which cannot resolve angles below ~1e-8 rad)
            assert np.abs(pa.R - pb.R).max() <= tol_rad, (iid, np.abs(pa.R - pb.R).max())
            ua, _ = project(a.camera_of(ia), pa, xyz)
            ub, _ = project(b.camera_of(ib), pb, xyz)
            ok = np.isfinite(ua[:, 0])
            assert ok.sum() > 50
            assert np.abs(ua[ok] - ub[ok]).max() <= tol_px
        if ground_points:
            assert set(a.ground_points) == set(b.ground_points)
            for name, ga in a.ground_points.items():
                gb = b.ground_points[name]
                assert ga.kind == gb.kind
                assert np.allclose(ga.xyz, gb.xyz, atol=tol_m, rtol=0, equal_nan=True)
                assert set(ga.observations) == set(gb.observations)
                for k, uv in ga.observations.items():
                    assert np.abs(uv - gb.observations[k]).max() <= 1e-9

    return check

"""Shared fixtures: temporary workspaces and small synthetic cameras/blocks built from known geometry."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.geometry.rotations import opk_to_cam_from_world
from oblique_city.core.model import CameraModel, Image, ImageBlock, Pose


@pytest.fixture
def camera() -> CameraModel:
    """A camera with fx != fy, an off-centre principal point and aerial-size distortion."""
    return CameraModel(id="cam", width=1200, height=900, fx=1500.0, fy=1502.5, cx=611.3, cy=437.8,
                       k1=-0.05, k2=0.01, k3=-0.001, p1=2e-4, p2=-1e-4, pixel_size_mm=0.0046)


@pytest.fixture
def utm_block(camera: CameraModel) -> ImageBlock:
    """Three images over UTM 32N coordinates (500000, 5400000), one nadir and two obliques."""
    block = ImageBlock(crs="EPSG:32632")
    block.add_camera(camera)
    poses = [
        (0.0, 0.0, 0.3, (500000.0, 5400000.0, 800.0)),
        (np.radians(45.0), 0.0, 0.0, (500010.0, 5399500.0, 800.0)),
        (0.0, np.radians(-45.0), np.radians(90.0), (500500.0, 5400020.0, 800.0)),
    ]
    for i, (o, p, k, c) in enumerate(poses):
        block.add_image(Image(id=f"img{i}", camera_id="cam", file=f"img{i}.jpg",
                              pose_approx=Pose(opk_to_cam_from_world(o, p, k), c),
                              sigma_position=np.array([0.05, 0.05, 0.1]),
                              sigma_attitude=np.radians([0.005, 0.005, 0.008])))
    return block


@pytest.fixture(scope="session")
def penta_block() -> ImageBlock:
    """A penta camera flown over 600 m x 400 m in strips (image ids ``S01_E001_nadir`` ...) in UTM 32N 200 km east
    of its central meridian (a grid convergence of 2 degrees), navigation orientations through the nominal rig
    ``penta``, exposure times from the flight."""
    from oblique_city.core.simulate.cameras import penta
    from oblique_city.core.simulate.flight import FlightConfig, NavErrors, approximate_block, plan_flight, true_block

    system = penta()
    exposures = plan_flight(system, np.array([700000.0, 5400000.0, 700600.0, 5400400.0]), 300.0,
                            FlightConfig(gsd=0.1))
    truth = true_block(system, exposures, "EPSG:25832")
    return approximate_block(truth, exposures, system.rig(), NavErrors(seed=5))


@pytest.fixture
def plain_opk():
    """``plain_opk(block, dest, jitter_s=0.0)`` writes ``block`` as an OPK list without its exposure and head columns
    (as most exchanged lists are: one orientation and a time per image), each time moved by up to ``jitter_s`` (the
    heads' triggers are not exactly simultaneous); returns the path of the list."""
    from oblique_city.core.io.formats import write_block

    def write(block: ImageBlock, dest, jitter_s: float = 0.0):
        write_block("opk", block, dest)
        lines = dest.read_text().splitlines()
        head = next(k for k, t in enumerate(lines) if not t.startswith("#"))
        cols = lines[head].split()
        keep = [k for k, c in enumerate(cols) if c not in ("exposure", "head")]
        rng = np.random.default_rng(1)
        out = lines[:head] + [" ".join(cols[k] for k in keep)]
        for t in lines[head + 1:]:
            f = t.split()
            f[cols.index("time")] = repr(float(f[cols.index("time")]) + rng.uniform(-jitter_s, jitter_s))
            out.append(" ".join(f[k] for k in keep))
        dest.write_text("\n".join(out) + "\n")
        return dest

    return write

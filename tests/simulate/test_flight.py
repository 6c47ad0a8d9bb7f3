"""Flight planner, camera systems, navigation errors and ground points against their definitions."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.geometry.projection import intersect_with_plane_z, project
from oblique_city.core.geometry.rotations import mount_rotation, rotation_angle
from oblique_city.core.geometry.views import VIEWS, cardinal_view
from oblique_city.core.simulate.cameras import penta, system_from_dict, three_head
from oblique_city.core.simulate.flight import (
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

CRS = "EPSG:25832"
AREA = np.array([500000.0, 5400000.0, 500600.0, 5400500.0])
STILL = dict(attitude_jitter_deg=0.0, position_jitter=0.0)


def test_mount_rotations():
    nadir = mount_rotation(0.0, 0.0)
    np.testing.assert_allclose(nadir, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-15)
    fwd = mount_rotation(45.0, 0.0)
    np.testing.assert_allclose(fwd[2], [np.sqrt(0.5), 0, np.sqrt(0.5)], atol=1e-15)  # looks forward and down
    assert fwd[1] @ np.array([1.0, 0, 0]) < 0  # image top (-y) points away from the nadir
    for a in (0.0, 90.0, 180.0, 270.0):
        r = mount_rotation(36.0, a)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
        assert abs(np.linalg.det(r) - 1) < 1e-14
        assert abs(np.degrees(np.arccos(r[2] @ nadir[2])) - 36.0) < 1e-9  # optical axis tilt


def test_gsd_and_views_from_actual_orientation():
    system = penta()
    ex = plan_flight(system, AREA, 100.0, FlightConfig(gsd=0.1, **STILL))
    block = true_block(system, ex, CRS)
    img = next(i for i in block.images.values() if i.head == "nadir")
    cam = block.camera_of(img)
    c = np.array([[cam.cx, cam.cy], [cam.cx + 1.0, cam.cy]])
    g = intersect_with_plane_z(cam, img.pose_approx, c, 100.0)
    assert abs(np.linalg.norm(g[1] - g[0]) - 0.1) < 1e-3
    assert abs(img.pose_approx.C[2] - 100.0 - flying_height(system, 0.1)) < 1e-9
    # strips run east-west, alternating: the forward head looks east on odd strips and west on even ones
    for i in block.images.values():
        strip = int(i.exposure[1:3])
        want = {"nadir": "nadir", "forward": "east", "backward": "west", "left": "north", "right": "south"}[i.head]
        if strip % 2 == 0:
            want = {"east": "west", "west": "east", "north": "south", "south": "north"}.get(want, want)
        assert cardinal_view(i.pose_approx.R) == want


def test_coverage_matches_planned_overlap():
    """Without jitter, over flat ground, every interior point is seen on average by 1/(1-0.8) = 5 nadir images of
    a strip and by 1/(1-0.6) = 2.5 strips."""
    system = penta(400, 300)
    ex = plan_flight(system, AREA, 100.0, FlightConfig(gsd=0.5, **STILL))
    block = true_block(system, ex, CRS)
    cam = block.cameras["penta_nadir"]
    h = flying_height(system, 0.5)
    base, spacing = 0.2 * h * cam.height / cam.fy, 0.4 * h * cam.width / cam.fx
    # one full period of the pattern (4 exposure bases x 1 strip spacing) in the middle of the block
    c = np.array([e.center for e in ex])
    x0, y0 = np.median(c[:, 0]), np.median(np.unique(np.round(c[:, 1], 6)))
    inner = np.array([x0, y0, x0 + 4 * base, y0 + spacing])
    cov = coverage_map(block, inner, 1.0, lambda xy: np.full(len(xy), 100.0))
    nadir = cov.data[..., VIEWS.index("nadir")].ravel()
    assert abs(nadir.mean() - 12.5) < 0.35
    assert nadir.min() >= 8
    strips = sorted({i.exposure[:3] for i in block.images.values()})
    per_strip = []
    for s in strips:
        sub = true_block(system, [e for e in ex if e.name.startswith(s)], CRS)
        per_strip.append(coverage_map(sub, inner, 1.0, lambda xy: np.full(len(xy), 100.0)).data[..., 0].ravel())
    per_strip = np.array(per_strip)
    seen = per_strip > 0
    assert abs(seen.sum(0).mean() - 2.5) < 0.06
    assert abs(per_strip[seen].mean() - 5.0) < 0.06
    # obliques see the area too once the strips are extended
    ex2 = plan_flight(system, AREA, 100.0, FlightConfig(gsd=0.5, extend_along=1.2 * h, extend_across=1.2 * h, **STILL))
    cov2 = coverage_map(true_block(system, ex2, CRS), AREA + np.array([60, 60, -60, -60]), 4.0,
                        lambda xy: np.full(len(xy), 100.0))
    assert cov2.data.reshape(-1, 5).min(0).min() >= 4


def test_plan_deterministic_and_cross_strips():
    system = three_head()
    a = plan_flight(system, AREA, 50.0, FlightConfig(seed=4))
    b = plan_flight(system, AREA, 50.0, FlightConfig(seed=4))
    assert [e.name for e in a] == [e.name for e in b]
    assert all(np.array_equal(x.center, y.center) and x.yaw == y.yaw for x, y in zip(a, b, strict=True))
    c = plan_flight(system, AREA, 50.0, FlightConfig(seed=4, cross_strips=True))
    assert len(c) > len(a)
    headings = {round(np.degrees(e.yaw)) % 180 for e in c}
    assert any(abs(h - 90) <= 3 for h in headings) and any(h <= 3 or h >= 177 for h in headings)


def test_custom_system():
    s = system_from_dict({"name": "duo", "heads": [
        {"name": "n", "tilt_deg": 0, "azimuth_deg": 0, "focal_mm": 35, "pixel_mm": 0.01, "width": 300, "height": 200,
         "k1": -0.02},
        {"name": "o", "tilt_deg": 30, "azimuth_deg": 90, "focal_mm": 50, "pixel_mm": 0.01, "width": 300,
         "height": 200, "lever_arm": [0, 0.2, 0]}]})
    assert s.nadir_head == "n" and s.camera("o").fx == pytest.approx(5000.0) and s.camera("n").k1 == -0.02
    assert s.rig().head("o").lever_arm[1] == 0.2


def test_navigation_errors_and_ground_points(city):
    system = penta(300, 225)
    area = city.core + np.array([30, 30, -30, -30])
    ex = plan_flight(system, area, 110.0, FlightConfig(gsd=0.6, seed=2))
    nominal = system.rig()
    err = NavErrors(seed=5, gnss_sigma=(0.05, 0.05, 0.08), boresight_sigma_deg=0.05)
    true_rig = perturbed_rig(nominal, err)
    angles = [np.degrees(rotation_angle(a.sensor_from_rig, b.sensor_from_rig))
              for a, b in zip(true_rig.heads, nominal.heads, strict=True)]
    assert 0.005 < np.mean(angles) < 0.2
    truth = true_block(system, ex, city.crs, rig=true_rig)
    approx = approximate_block(truth, ex, nominal, err)
    nadir = [i for i in truth.images if truth.images[i].head == "nadir"]
    d = np.array([approx.images[i].pose_approx.C - truth.images[i].pose_approx.C for i in nadir])
    rng = np.random.default_rng([5, 29])
    bias = rng.normal(0, err.datum_bias_sigma, 3)
    # nominal vs true lever arm (~1 cm) adds to the GNSS noise; the mean is the datum bias
    np.testing.assert_allclose(d.mean(0), bias, atol=0.05)
    assert 0.02 < d[:, 0].std() < 0.09
    assert all(np.allclose(approx.images[i].sigma_position, err.gnss_sigma) for i in nadir)
    gps = ground_points(truth, city.target_names, city.targets, city.scene(), city.origin, sigma_px=0.3, seed=1)
    kinds = [g.kind for g in gps]
    assert kinds.count("check") == len(gps) // 3 and kinds.count("control") > 0
    res = []
    for g, xyz in zip(gps, city.targets, strict=True):
        assert np.linalg.norm(g.xyz - xyz) < 0.08
        for iid, uv in g.observations.items():
            img = truth.images[iid]
            uv_true, _ = project(truth.camera_of(img), img.pose_approx, xyz[None])
            res.append(uv - uv_true[0])
    res = np.array(res)
    assert len(res) > 50
    assert 0.22 < res.std() < 0.38


def test_polygon_area_strips_follow_the_outline():
    """A triangle: strips over its narrow end are shorter than over its base; a bbox gives equal strips."""
    system = penta(400, 300)
    tri = np.array([[500000.0, 5400000.0], [501000.0, 5400000.0], [500000.0, 5400800.0]])
    ex = plan_flight(system, tri, 100.0, FlightConfig(gsd=0.5, **STILL))
    per = {}
    for e in ex:
        per.setdefault(e.strip, []).append(e.center[0])
    ys = {s: np.mean([e.center[1] for e in ex if e.strip == s]) for s in per}
    south, north = min(ys, key=ys.get), max(ys, key=ys.get)
    assert max(per[south]) - min(per[south]) > 2 * (max(per[north]) - min(per[north]))
    box = plan_flight(system, np.array([500000.0, 5400000.0, 501000.0, 5400800.0]), 100.0,
                      FlightConfig(gsd=0.5, **STILL))
    counts = np.bincount([e.strip for e in box])[1:]
    assert len(set(counts)) == 1 and len(per) == len(counts)
    with pytest.raises(Exception, match="area must be"):
        plan_flight(system, np.zeros(3), 100.0)


def test_three_head_views():
    """Three-head system on east-west strips: left/right heads give north/south views, no east/west views."""
    system = three_head(300, 225)
    block = true_block(system, plan_flight(system, AREA, 100.0, FlightConfig(gsd=0.5)), CRS)
    views = {cardinal_view(i.pose_approx.R) for i in block.images.values()}
    assert views == {"nadir", "north", "south"}

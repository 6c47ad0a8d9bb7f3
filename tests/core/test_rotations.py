"""Rotation conventions: round trips, agreement with OpenCV, the documented frames and cardinal views."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from oblique_city.core.geometry import rotations as rt
from oblique_city.core.geometry.views import cardinal_view, tilt_and_azimuth
from oblique_city.core.model import Pose

angle = st.floats(-3.1, 3.1)
half = st.floats(-1.5, 1.5)


@settings(max_examples=200, deadline=None)
@given(angle, half, angle)
def test_opk_round_trip(o: float, p: float, k: float) -> None:
    r = rt.opk_to_cam_from_world(o, p, k)
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(r), 1.0)
    o2, p2, k2 = rt.cam_from_world_to_opk(r)
    assert np.allclose(rt.opk_to_cam_from_world(o2, p2, k2), r, atol=1e-12)
    assert np.allclose([o2, p2, k2], [o, p, k], atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(angle, half, angle)
def test_ypr_round_trip(y: float, p: float, r: float) -> None:
    m = rt.ypr_to_cam_from_world(y, p, r)
    y2, p2, r2 = rt.cam_from_world_to_ypr(m)
    assert np.allclose(rt.ypr_to_cam_from_world(y2, p2, r2), m, atol=1e-12)
    assert np.allclose([y2, p2, r2], [y, p, r], atol=1e-9)


def test_identity_opk_looks_down_with_image_top_north() -> None:
    # omega = phi = kappa = 0: photo frame = world frame, camera looks down (-Z), image y-up is north.
    r = rt.opk_to_cam_from_world(0.0, 0.0, 0.0)
    assert np.allclose(r[2], [0, 0, -1])  # optical axis (OpenCV z) in world = down
    assert np.allclose(r[1], [0, -1, 0])  # OpenCV y (image down) points south
    assert np.allclose(r[0], [1, 0, 0])   # image right = east


def test_ypr_heading_east_nadir() -> None:
    # Flying east (yaw 90 deg), a nadir camera's image top points east, image right points south.
    r = rt.ypr_to_cam_from_world(np.radians(90.0), 0.0, 0.0)
    assert np.allclose(r[2], [0, 0, -1], atol=1e-12)
    assert np.allclose(-r[1], [1, 0, 0], atol=1e-12)
    assert np.allclose(r[0], [0, -1, 0], atol=1e-12)


def test_opk_matches_blender_zyx_euler() -> None:
    # Blender's rotation_mode 'ZYX' with euler (x, y, z) composes as Rx(x) @ Ry(y) @ Rz(z).
    o, p, k = 0.3, -0.2, 1.1
    m = rt.rot_x(o) @ rt.rot_y(p) @ rt.rot_z(k)
    assert np.allclose(rt.opk_to_world_from_photo(o, p, k), m)
    assert np.allclose(rt.opk_to_cam_from_world(o, p, k), np.diag([1, -1, -1]) @ m.T)


def test_units() -> None:
    assert rt.to_radians(200.0, "gon") == pytest.approx(np.pi)
    assert rt.to_radians(180.0, "deg") == pytest.approx(np.pi)
    assert rt.from_radians(np.pi / 2, "gon") == pytest.approx(100.0)
    with pytest.raises(Exception, match="unknown angle unit"):
        rt.to_radians(1.0, "mil")


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3))
def test_rotvec_matches_opencv(v: list) -> None:
    r = rt.rotvec_to_matrix(np.array(v))
    assert np.allclose(r, cv2.Rodrigues(np.array(v))[0], atol=1e-12)
    assert np.allclose(rt.rotvec_to_matrix(rt.matrix_to_rotvec(r)), r, atol=1e-9)


def test_orthonormalize_recovers_rotation_from_rounded_matrix() -> None:
    r = rt.opk_to_cam_from_world(0.1, 0.2, 0.3)
    noisy = np.round(r, 5)
    assert rt.rotation_angle(rt.orthonormalize(noisy), r) < 2e-5


@pytest.mark.parametrize("azimuth,expected", [(0, "north"), (90, "east"), (180, "south"), (270, "west"),
                                              (44, "north"), (46, "east"), (359, "north")])
def test_cardinal_view_from_actual_direction(azimuth: float, expected: str) -> None:
    # camera tilted 45 deg from nadir, looking towards the given azimuth
    a = np.radians(azimuth)
    d = np.array([np.sin(a) * np.sin(np.pi / 4), np.cos(a) * np.sin(np.pi / 4), -np.cos(np.pi / 4)])
    x = np.cross(d, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(d, x)
    r = np.stack([x, y, d])
    assert np.isclose(np.linalg.det(r), 1.0)
    tilt, az = tilt_and_azimuth(r)
    assert tilt == pytest.approx(45.0) and az == pytest.approx(azimuth % 360, abs=1e-9)
    assert cardinal_view(r) == expected


def test_nadir_view_and_head_independence() -> None:
    assert cardinal_view(rt.opk_to_cam_from_world(0.05, -0.03, 2.0)) == "nadir"
    # a head tilted forward looks north when flying north and south when flying south
    fwd = rt.rot_x(np.radians(-45.0))  # tilt about the camera x axis in the body frame
    north = fwd @ rt.ypr_to_cam_from_world(0.0, 0.0, 0.0)
    south = fwd @ rt.ypr_to_cam_from_world(np.pi, 0.0, 0.0)
    assert {cardinal_view(north), cardinal_view(south)} == {"north", "south"}


def test_pose_opk_and_rt_round_trip() -> None:
    p = Pose.from_opk(0.1, -0.2, 2.5, [500000.0, 5400000.0, 300.0])
    q = Pose.from_rt(p.R, p.t)
    assert np.allclose(q.C, p.C, atol=1e-9) and np.allclose(q.R, p.R)
    assert np.allclose(p.opk(), (0.1, -0.2, 2.5))


@pytest.mark.parametrize(("build", "axes", "angles", "exact"), [
    (rt.opk_to_world_from_photo, rt.opk_axes, (np.radians(45.0), np.radians(2.0), np.radians(30.0)), False),  # north
    (rt.opk_to_world_from_photo, rt.opk_axes, (np.radians(1.0), np.radians(-44.0), np.radians(-95.0)), True),  # east
    (lambda r, p, y: rt.world_from_body(y, p, r), lambda r, p, y: rt.ypr_axes(y, p, r),
     (np.radians(3.0), np.radians(-8.0), np.radians(130.0)), True),  # roll, pitch, yaw
])
def test_angle_sigmas_in_the_world(build, axes, angles, exact) -> None:
    """Angles drawn with independent sigmas turn the orientation about the world's axes as ``world_axis_sigmas``
    says: 20,000 draws of 0.01, 0.02 and 0.05 degrees, the sample standard deviations of the world rotation vectors
    within 3 % (the sampling error of a standard deviation is 0.5 % here). ``angle_sigmas`` inverts it where the
    axes keep the world's apart (the east view, the body); for the north view phi and kappa turn about Y and Z
    alike, and the world sigmas they give back are those given."""
    rng = np.random.default_rng(5)
    sig = np.radians([0.01, 0.02, 0.05])
    m0 = build(*angles)
    d = rng.normal(0.0, 1.0, (20000, 3)) * sig
    rv = np.array([rt.matrix_to_rotvec(build(*(np.asarray(angles) + di)) @ m0.T) for di in d])
    world = rt.world_axis_sigmas(axes(*angles), sig)
    assert np.allclose(rv.std(0), world, rtol=0.03)
    back = rt.angle_sigmas(axes(*angles), world)
    assert np.allclose(rt.world_axis_sigmas(axes(*angles), back), world, rtol=0.02)
    if exact:
        assert np.allclose(back, sig, rtol=1e-9)


def test_angle_sigmas_that_no_independent_angles_give() -> None:
    """Equal world sigmas on an image tilted 45 degrees about Y: omega and kappa turn about axes 45 degrees apart,
    so no independent angle sigmas give them (least squares would want a negative variance). The angles' sigmas
    written are then their marginal ones: 20,000 world rotations drawn with those sigmas change omega, phi and kappa
    by the standard deviations ``angle_sigmas`` gives, within 3 % (omega's and kappa's 1.4 times the world's)."""
    rng = np.random.default_rng(9)
    angles = np.radians([0.5, -45.0, -90.0])
    world = np.radians([0.03, 0.03, 0.031])
    m0 = rt.opk_to_world_from_photo(*angles)
    drawn = np.array([rt.world_from_photo_to_opk(rt.rotvec_to_matrix(d) @ m0)
                      for d in rng.normal(0.0, 1.0, (20000, 3)) * world])
    sig = rt.angle_sigmas(rt.opk_axes(*angles), world)
    assert np.allclose((drawn - angles).std(0), sig, rtol=0.03)
    assert sig[0] > 1.35 * world[0] and sig[2] > 1.35 * world[2]


def test_metashape_reference_angles() -> None:
    """Metashape's reference rotation: the matrix the Agisoft forum prints for ``ypr2mat(30, 91, 0)`` (to 1e-15,
    as printed), a nadir view at yaw 90 has its image top east, pitch 90 looks horizontally along the yaw."""
    forum = np.array([[0.8660254037844387, -0.008726203218641737, -0.4999238475781956],
                      [-0.49999999999999994, -0.01511422733185856, -0.8658935039207541],
                      [0.0, 0.9998476951563913, -0.017452406437283477]])
    assert np.abs(rt.metashape_ypr_to_photo(*np.radians([30.0, 91.0, 0.0])) - forum).max() < 1e-15
    east = rt.metashape_ypr_to_photo(np.radians(90.0), 0.0, 0.0)
    assert np.allclose(east[:, 1], [1.0, 0.0, 0.0]) and np.allclose(east[:, 2], [0.0, 0.0, 1.0])  # top east, down
    level = rt.metashape_ypr_to_photo(0.0, np.radians(90.0), 0.0)
    assert np.allclose(-level[:, 2], [0.0, 1.0, 0.0])  # looks north
    # the inverse: 500 random orientations and a horizontal view (yaw and roll about one axis: roll 0)
    for a in [*np.random.default_rng(3).uniform(-1.5, 1.5, (500, 3)), np.array([0.3, np.pi / 2, 0.2])]:
        m = rt.metashape_ypr_to_photo(*a)
        assert np.abs(rt.metashape_ypr_to_photo(*rt.photo_to_metashape_ypr(m)) - m).max() < 1e-12

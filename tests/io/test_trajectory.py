"""GNSS/IMU event lists: the images' orientations from the navigation solution and the heads' mounting, against the
simulator's, the grid convergence against the closed formula, and errors naming file, line and field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from oblique_city.core.errors import InputError
from oblique_city.core.geometry.crs import transform_points, true_north_angles
from oblique_city.core.geometry.rotations import matrix_to_rotvec, mount_rotation, rotation_angle
from oblique_city.core.io.camerafile import read_camera_file
from oblique_city.core.io.formats import read_block, write_block


def test_event_list_gives_every_head_its_orientation(tmp_path, penta_block):
    """The simulated penta block written as events (one row per exposure, headings against true north, 2 degrees
    from grid north there) and read back: every head's image has the simulator's orientation, exposure, head and
    time, and the block the rig of the camera file. The headings written are the grid's plus the convergence (the
    sphere's formula, within 0.01 degree of the ellipsoid's)."""
    write_block("gnssimu", penta_block, tmp_path / "events.txt")
    rows = [t for t in (tmp_path / "events.txt").read_text().splitlines() if not t.startswith("#")]
    exposures = {img.exposure for img in penta_block.images.values()}
    assert len(rows) == 1 + len(exposures)
    back = read_block("gnssimu", str(tmp_path / "events.txt"))
    assert set(back.images) == set(penta_block.images)
    for iid, img in penta_block.images.items():
        got = back.images[iid]
        assert (got.exposure, got.head, got.time, got.camera_id, got.file) == \
            (img.exposure, img.head, img.time, img.camera_id, img.file)
        assert np.abs(got.pose_approx.C - img.pose_approx.C).max() < 1e-6
        assert rotation_angle(got.pose_approx.R, img.pose_approx.R) < 1e-9
        assert np.allclose(got.sigma_position, img.sigma_position)
        assert np.allclose(got.sigma_attitude, img.sigma_attitude, rtol=1e-9)
    rig, nominal = back.rigs["system"], penta_block.rigs["penta"]
    assert [h.name for h in rig.heads] == [h.name for h in nominal.heads]
    assert all(np.allclose(h.sensor_from_rig, n.sensor_from_rig, atol=1e-15) and np.allclose(h.lever_arm, n.lever_arm)
               for h, n in zip(rig.heads, nominal.heads, strict=True))
    # the headings written are against true north: the grid's ones plus the convergence
    cols = rows[0].split()
    first = rows[1].split()
    ex = first[cols.index("exposure")]
    nadir = penta_block.images[f"{ex}_nadir"].pose_approx
    top = -nadir.R[1]  # the nadir image's top points forward
    grid_heading = math.degrees(math.atan2(top[0], top[1]))
    written = float(first[cols.index("heading")])
    body = np.array([[float(first[cols.index(c)]) for c in "xyz"]])
    lon, lat, _ = transform_points(body, penta_block.crs, "EPSG:4326")[0]
    convergence = math.degrees(math.atan(math.tan(math.radians(lon - 9.0)) * math.sin(math.radians(lat))))
    assert written - grid_heading == pytest.approx(convergence, abs=0.01) and convergence > 1.9


def test_grid_convergence_against_the_closed_formula(tmp_path, penta_block):
    """A heading of 0 (true north) at 48 N 12 E (3 degrees east of UTM 32N's central meridian) points at grid
    bearing -atan(tan(3 deg) sin(48 deg)) = -2.2305 degrees (the sphere's formula, within 0.01 degree of the
    ellipsoid's); with heading=grid it points at grid north."""
    write_block("gnssimu", penta_block, tmp_path / "full.txt")
    (tmp_path / "events.txt").write_text("# cameras: full_cameras.toml\n# crs: EPSG:25832\n"
                                         "exposure lat lon h roll pitch heading\nE1 48.0 12.0 900.0 0 0 0\n")
    expected = -math.degrees(math.atan(math.tan(math.radians(3.0)) * math.sin(math.radians(48.0))))
    for heading, want in (("true", expected), ("grid", 0.0)):
        block = read_block("gnssimu", str(tmp_path / "events.txt"), heading=heading)
        top = -block.images["E1_nadir"].pose_approx.R[1]
        assert math.degrees(math.atan2(top[0], top[1])) == pytest.approx(want, abs=0.01)
        assert block.images["E1_nadir"].pose_approx.C[2] == pytest.approx(900.0 + penta_block.rigs["penta"]
                                                                           .head("nadir").lever_arm[2] * -1.0, abs=1e-6)
    assert np.degrees(true_north_angles(np.array([[500000.0, 5300000.0, 0.0]]), "EPSG:25832")) == \
        pytest.approx(0.0, abs=1e-6)


def test_camera_file_heads_by_tilt_and_azimuth(tmp_path):
    """Heads given by tilt and azimuth with a boresight correction: the mount turns the camera towards the azimuth,
    the boresight turns it about its own axes after that."""
    (tmp_path / "cams.toml").write_text(
        'crs = "EPSG:25832"\n[cameras.c]\nwidth = 100\nheight = 80\nfocal_px = 120.0\n'
        '[heads.nadir]\ncamera = "c"\n[heads.fwd]\ncamera = "c"\ntilt_deg = 45.0\nazimuth_deg = 0.0\n'
        'boresight_deg = [0.0, 0.0, 0.5]\nlever_arm_m = [0.2, 0.0, 0.0]\n')
    heads = read_camera_file(tmp_path / "cams.toml").heads
    assert [h.name for h in heads] == ["nadir", "fwd"]
    nadir, fwd = heads
    assert np.allclose(nadir.sensor_from_rig @ [0, 0, 1], [0, 0, 1])  # looks down the body's z
    view = fwd.sensor_from_rig.T @ [0, 0, 1]  # the forward head's viewing direction in the body frame
    assert np.allclose(view, [math.sqrt(0.5), 0.0, math.sqrt(0.5)])
    turn = matrix_to_rotvec(fwd.sensor_from_rig @ mount_rotation(45.0, 0.0).T)  # the boresight, camera axes
    assert np.allclose(np.degrees(turn), [0.0, 0.0, 0.5])
    assert np.allclose(fwd.lever_arm, [0.2, 0, 0])


def test_bad_event_lists_name_the_file_line_and_field(tmp_path, penta_block):
    write_block("gnssimu", penta_block, tmp_path / "events.txt")
    text = (tmp_path / "events.txt").read_text()
    lines = text.splitlines()
    first = next(k for k, t in enumerate(lines) if t.startswith("S01_E001 "))
    src = tmp_path / "bad.txt"
    src.write_text("\n".join(lines[:first + 1] + [lines[first]]) + "\n")  # one exposure twice
    with pytest.raises(InputError) as e:
        read_block("gnssimu", str(src))
    assert (e.value.path, e.value.line, e.value.field) == (str(src), first + 2, "exposure")
    src.write_text("\n".join(lines[:first] + [lines[first].replace(" 36000.0 ", " noon ")]) + "\n")
    with pytest.raises(InputError) as e:
        read_block("gnssimu", str(src))
    assert (e.value.line, e.value.field) == (first + 1, "time")
    cams = (tmp_path / "events_cameras.toml").read_text()
    (tmp_path / "events_cameras.toml").write_text(cams.replace("lever_arm_m", "lever_arm", 1))
    with pytest.raises(InputError) as e:
        read_block("gnssimu", str(tmp_path / "events.txt"))
    assert e.value.field.endswith(".lever_arm") and e.value.line is not None and "unknown key" in str(e.value)
    (tmp_path / "events_cameras.toml").write_text(cams.split("[heads.")[0])
    with pytest.raises(InputError) as e:
        read_block("gnssimu", str(tmp_path / "events.txt"))
    assert e.value.field == "cameras" and "heads" in str(e.value)
    (tmp_path / "events_cameras.toml").write_text(cams)
    with pytest.raises(InputError) as e:
        read_block("gnssimu", str(tmp_path / "events.txt"), heading="magnetic")
    assert e.value.field == "heading"


def test_writer_refuses_what_an_event_list_cannot_carry(tmp_path, penta_block):
    """One orientation per exposure: a head moved 5 mm off its rig mounting (as an adjustment moves them) is refused,
    naming the image; so are names that follow no pattern of exposure and head. Nothing is written."""
    import copy

    from oblique_city.core.model import Pose

    moved = copy.deepcopy(penta_block)
    img = moved.images["S01_E002_left"]
    img.pose_adjusted = Pose(img.pose_approx.R, img.pose_approx.C + [0.005, 0.0, 0.0])
    with pytest.raises(InputError) as e:
        write_block("gnssimu", moved, tmp_path / "a.txt")
    assert e.value.field == "rig" and "S01_E002_left" in str(e.value) and "0.0050 m" in str(e.value)
    renamed = copy.deepcopy(penta_block)
    img = renamed.images.pop("S01_E002_left")
    img.id = "IMG_0042"
    renamed.images[img.id] = img
    with pytest.raises(InputError) as e:
        write_block("gnssimu", renamed, tmp_path / "b.txt")
    assert e.value.field == "image_name"
    assert not list(tmp_path.iterdir())


def test_imu_sigmas_turn_with_the_heading():
    """The IMU's roll, pitch and heading sigmas are the angles'; the priors' are about the world's axes: flown east
    the roll is about X, flown north about Y, at 45 degrees roll and pitch share both; the heading stays about Z,
    also when the body is pitched (the heading turns about the vertical, the roll about the dipping x axis). The
    writer's inverse recovers the angles' sigmas where the heading keeps the axes apart."""
    from oblique_city.core.geometry.rotations import angle_sigmas, world_axis_sigmas, ypr_axes

    body = np.array([0.004, 0.006, 0.010])
    east = ypr_axes(math.pi / 2, 0.0, 0.0)
    assert np.allclose(world_axis_sigmas(east, body), [0.004, 0.006, 0.010])
    assert np.allclose(world_axis_sigmas(ypr_axes(0.0, 0.0, 0.0), body), [0.006, 0.004, 0.010])
    diagonal = world_axis_sigmas(ypr_axes(math.pi / 4, 0.0, 0.0), body)
    assert np.allclose(diagonal[:2], math.sqrt((0.004**2 + 0.006**2) / 2)) and diagonal[2] == pytest.approx(0.010)
    pitched = world_axis_sigmas(ypr_axes(0.0, math.radians(10.0), 0.0), body)
    assert pitched[2] == pytest.approx(math.hypot(0.010, 0.004 * math.sin(math.radians(10.0))))  # the roll axis dips
    assert np.allclose(angle_sigmas(east, world_axis_sigmas(east, body)), body)

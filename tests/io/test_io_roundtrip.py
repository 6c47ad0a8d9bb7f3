"""Round trips through every block format: write, read back, same block and same projections."""

from __future__ import annotations

import copy

import numpy as np
import pycolmap
import pytest

from oblique_city.core.geometry.projection import project
from oblique_city.core.geometry.rotations import angle_sigmas, cam_from_world_to_opk, opk_axes, world_axis_sigmas
from oblique_city.core.io.formats import read_block, write_block
from oblique_city.core.io.gcp import write_ground_points, write_measurements
from oblique_city.core.model import Pose


@pytest.mark.parametrize("angles", ["deg", "gon", "rad"])
@pytest.mark.parametrize("delimiter", ["whitespace", "comma", "semicolon", "tab"])
def test_opk_round_trip(tmp_path, oblique_block, same_block, angles, delimiter):
    """The attitude sigmas travel as the angles' (``somega sphi skappa``): the nadir images' come back exactly; the
    45-degree ones (their phi and kappa both turn about Y and Z) come back as the world sigmas their angles can give,
    which a second round trip keeps."""
    write_block("opk", oblique_block, tmp_path / "block.txt", angles=angles, delimiter=delimiter)
    assert (tmp_path / "block_cameras.toml").is_file()
    back = read_block("opk", tmp_path / "block.txt")  # header directives name crs, angles and camera file
    same_block(oblique_block, back, ground_points=False)
    for iid, img in oblique_block.images.items():
        assert np.allclose(back.images[iid].sigma_position, img.sigma_position, rtol=1e-15)
        axes = opk_axes(*cam_from_world_to_opk(img.pose_approx.R))
        expected = world_axis_sigmas(axes, angle_sigmas(axes, img.sigma_attitude))
        assert np.allclose(back.images[iid].sigma_attitude, expected, rtol=1e-12)
        if img.camera_id == "cam":
            assert np.allclose(expected, img.sigma_attitude, rtol=1e-12)
    write_block("opk", back, tmp_path / "again.txt", angles=angles, delimiter=delimiter)
    again = read_block("opk", tmp_path / "again.txt")
    for iid, img in back.images.items():
        assert np.allclose(again.images[iid].sigma_attitude, img.sigma_attitude, rtol=1e-12)
    assert back.images["img0"].file == "img0.jpg"


def test_opk_kappa_sigma_of_an_oblique_image(tmp_path):
    """kappa turns an image about its viewing axis: a nadir image's sigma of kappa is about the world's Z, a
    north-looking 45-degree image's about Y and Z by halves (and its phi's too), an east-looking one's about X and
    Z."""
    (tmp_path / "cams.toml").write_text('crs = "EPSG:25832"\n[camera]\nid = "cam"\nwidth = 4000\nheight = 3000\n'
                                        'focal_px = 5000.0\n')
    (tmp_path / "list.txt").write_text("name x y z omega phi kappa somega sphi skappa\n"
                                       "nadir 512000 5404000 1000 0 0 0 0.002 0.003 0.010\n"
                                       "north 512100 5404000 1000 45 0 0 0.002 0.003 0.010\n"
                                       "east 512200 5404000 1000 0 -45 90 0.002 0.003 0.010\n")
    block = read_block("opk", tmp_path / "list.txt", cameras=str(tmp_path / "cams.toml"))
    half = np.sqrt(0.5)
    deg = np.radians
    assert np.allclose(block.images["nadir"].sigma_attitude, deg([0.002, 0.003, 0.010]))
    assert np.allclose(block.images["north"].sigma_attitude,
                       deg([0.002, np.hypot(0.003, 0.010) * half, np.hypot(0.003, 0.010) * half]))
    assert np.allclose(block.images["east"].sigma_attitude,
                       deg([np.hypot(0.002, 0.010 * half), 0.003, 0.010 * half]))


def test_opk_with_ground_point_lists(tmp_path, oblique_block, same_block):
    write_block("opk", oblique_block, tmp_path / "b.opk")
    write_ground_points(oblique_block, tmp_path / "gcp.csv")
    write_measurements(oblique_block, tmp_path / "meas.csv", origin="corner")
    # options as the CLI passes them: strings
    back = read_block("opk", tmp_path / "b.opk", gcps=str(tmp_path / "gcp.csv"),
                      measurements=str(tmp_path / "meas.csv"), measurement_origin="corner")
    same_block(oblique_block, back)
    for name, g in oblique_block.ground_points.items():
        assert np.array_equal(back.ground_points[name].sigma, g.sigma)
    assert sum(len(g.observations) for g in back.ground_points.values()) > 3


@pytest.mark.parametrize("rotation", ["matrix", "opk"])
def test_bex_round_trip(tmp_path, oblique_block, same_block, rotation):
    write_block("bex", oblique_block, tmp_path / "block.xml", rotation=rotation)
    back = read_block("bex", tmp_path / "block.xml")
    same_block(oblique_block, back, tol_rad=1e-12 if rotation == "opk" else 1e-15)
    assert back.image_root == str(tmp_path.resolve())


def test_bex_through_opk_and_back(tmp_path, oblique_block, same_block):
    """A block travels bex -> opk -> bex unchanged (ground points go through the lists)."""
    write_block("bex", oblique_block, tmp_path / "a.xml")
    a = read_block("bex", tmp_path / "a.xml")
    write_block("opk", a, tmp_path / "a.txt", angles="gon")
    b = read_block("opk", tmp_path / "a.txt")
    write_block("bex", b, tmp_path / "b.xml")
    same_block(oblique_block, read_block("bex", tmp_path / "b.xml"), ground_points=False)


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_round_trip(tmp_path, oblique_block, same_block, binary):
    write_block("colmap", oblique_block, tmp_path / "sparse", binary=binary)
    back = read_block("colmap", tmp_path / "sparse", crs="EPSG:32632")
    # COLMAP stores (quaternion, t = -R C): at UTM northings (5.4e6 m, 1 ulp = 0.9 nm) the centre comes back
    # within a few ulps, not bit-exact.
    same_block(oblique_block, back, tol_m=4e-9, tol_rad=1e-15, ground_points=False,
               camera_ids={"cam": "1", "obl": "2"})


def test_colmap_projection_matches_pycolmap(tmp_path, oblique_block):
    """COLMAP's own projection equals ours + 0.5 px (its pixel origin is the corner of the top-left pixel)."""
    write_block("colmap", oblique_block, tmp_path / "sparse")
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse"))
    xyz = np.array([[500100.0, 5400020.0, 100.0], [500300.0, 5399980.0, 60.0], [500050.0, 5400000.0, 120.0]])
    n = 0
    for im in rec.images.values():
        img = oblique_block.images[im.name.split(".")[0]]
        uv, depth = project(oblique_block.camera_of(img), img.pose, xyz)
        for k in range(len(xyz)):
            if depth[k] > 0:
                ref = im.project_point(xyz[k])
                assert np.abs(np.asarray(ref) - (uv[k] + 0.5)).max() < 1e-6
                n += 1
    assert n >= 8


def test_colmap_georeference(tmp_path, oblique_block, same_block):
    """With a sim3 the model is written in a local frame and read back to the world frame."""
    q = np.array([np.cos(0.3), 0.0, 0.0, np.sin(0.3)])  # 0.6 rad about z
    (tmp_path / "sim3.txt").write_text(f"2.5 {q[0]!r} 0 0 {q[3]!r} 500000 5400000 300\n")
    write_block("colmap", oblique_block, tmp_path / "sparse", sim3=str(tmp_path / "sim3.txt"))
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse"))
    centres = np.array([im.projection_center() for im in rec.images.values()])
    assert np.abs(centres).max() < 1000.0  # local frame, metres / 2.5
    back = read_block("colmap", tmp_path / "sparse", crs="EPSG:32632", sim3=str(tmp_path / "sim3.txt"))
    same_block(oblique_block, back, tol_m=4e-9, tol_rad=1e-15, ground_points=False,
               camera_ids={"cam": "1", "obl": "2"})
    # the same transform given as options (rotation as a quaternion w x y z, JSON-decoded from the CLI)
    back2 = read_block("colmap", tmp_path / "sparse", crs="EPSG:32632", sim3_scale="2.5",
                       sim3_rotation=f"[{q[0]!r}, 0, 0, {q[3]!r}]", sim3_translation="[500000, 5400000, 300]")
    same_block(oblique_block, back2, tol_m=4e-9, tol_rad=1e-15, ground_points=False,
               camera_ids={"cam": "1", "obl": "2"})


def test_pose_adjusted_option(tmp_path, oblique_block):
    write_block("bex", oblique_block, tmp_path / "b.xml")
    back = read_block("bex", tmp_path / "b.xml", pose="adjusted")
    assert all(i.pose_adjusted is not None for i in back.images.values())
    assert back.summary()["adjusted"] == 8


@pytest.mark.parametrize("fmt", ["opk", "bex"])
def test_image_root_travels(tmp_path, oblique_block, fmt):
    oblique_block.image_root = str(tmp_path / "images")
    write_block(fmt, oblique_block, tmp_path / "block.out")
    assert read_block(fmt, tmp_path / "block.out").image_root == str(tmp_path / "images")


@pytest.mark.parametrize("scaled", [False, True])
def test_colmap_rig_and_frames(tmp_path, penta_block, scaled):
    """A penta block from the navigation data goes to COLMAP as one rig (the nadir camera its reference) with a frame
    per exposure, and comes back with the same exposures, a head per camera, the rig's relative mounting (1e-12 and
    1e-9 m) and every image's pose (1e-7 m, 1e-9 rad: each is the frame's pose composed with its sensor's
    mounting); in a model frame at 2.5 model units per metre the lever arms are written in the model's units."""
    opts = {}
    if scaled:
        (tmp_path / "sim3.txt").write_text("0.4 1 0 0 0 700000 5400000 0\n")
        opts = {"sim3": str(tmp_path / "sim3.txt")}
    write_block("colmap", penta_block, tmp_path / "sparse", **opts)
    assert "CAMERA" in (tmp_path / "sparse" / "rigs.txt").read_text().splitlines()[-1]
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse"))
    assert len(rec.rigs) == 1 and rec.num_frames() == len({i.exposure for i in penta_block.images.values()})
    (model_rig,) = rec.rigs.values()
    arms = [np.linalg.norm(t.translation) for t in model_rig.non_ref_sensors.values()]
    (rig0,) = penta_block.rigs.values()
    nadir = next(h for h in rig0.heads if h.camera_id == "penta_nadir")
    metres = [np.linalg.norm(h.relative_to(nadir)[1]) for h in rig0.heads if h is not nadir]
    assert np.allclose(sorted(arms), sorted(np.array(metres) * (2.5 if scaled else 1.0)))
    back = read_block("colmap", tmp_path / "sparse", crs=penta_block.crs, **opts)
    ids = {c: str(k) for k, c in enumerate(penta_block.cameras, start=1)}
    frames = {}
    for iid, img in penta_block.images.items():
        got = back.images[iid]
        frames.setdefault(got.exposure, set()).add(img.exposure)
        assert got.head == ids[img.camera_id]
        assert np.abs(got.pose.C - img.pose.C).max() < 1e-7
        assert np.abs(got.pose.R - img.pose.R).max() < 1e-9
    assert all(len(v) == 1 for v in frames.values()) and len(frames) == rec.num_frames()
    (rig,) = back.rigs.values()
    nominal = {ids[h.camera_id]: h for h in penta_block.rigs["penta"].heads}
    assert rig.heads[0].name == ids["penta_nadir"]
    for h in rig.heads:
        rot, off = h.relative_to(rig.heads[0])
        rot0, off0 = nominal[h.name].relative_to(nominal[rig.heads[0].name])
        assert np.abs(rot - rot0).max() < 1e-12 and np.abs(off - off0).max() < 1e-9


def test_colmap_without_the_rig_where_the_heads_left_it(tmp_path, penta_block):
    """An image 1 cm off where its exposure's rig puts it (as after a triangulation): COLMAP gets a rig per camera
    and a frame per image, which carry every pose exactly, and the block comes back without exposures."""
    block = copy.deepcopy(penta_block)
    img = block.images["S01_E003_left"]
    img.pose_approx = Pose(img.pose_approx.R, img.pose_approx.C + [0.01, 0.0, 0.0])
    write_block("colmap", block, tmp_path / "sparse")
    back = read_block("colmap", tmp_path / "sparse", crs=block.crs)
    assert all(i.exposure is None for i in back.images.values()) and not back.rigs
    assert np.abs(back.images["S01_E003_left"].pose.C - img.pose_approx.C).max() < 4e-9

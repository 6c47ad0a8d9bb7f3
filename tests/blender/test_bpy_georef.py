"""A block at UTM (500000, 5400000, 300) keeps 1 mm through Blender objects (and a .blend save/load)."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.geometry.rotations import opk_to_cam_from_world, rotation_angle
from oblique_city.core.model import CameraModel, GroundPoint, Image, ImageBlock, Pose

pytestmark = pytest.mark.xdist_group("bpy")


def utm_block_at_300m() -> ImageBlock:
    rng = np.random.default_rng(3)
    block = ImageBlock(crs="EPSG:32632")
    block.add_camera(CameraModel(id="c", width=1000, height=800, fx=1200.0, fy=1201.0, cx=499.2, cy=401.7))
    for i in range(40):
        c = np.array([500000.0, 5400000.0, 300.0]) + rng.uniform([-3000, -3000, 500], [3000, 3000, 900])
        c += rng.uniform(0, 1e-3, 3)  # sub-millimetre digits that float32 at UTM magnitudes would lose
        angles = np.radians(rng.uniform([-50, -50, -180], [50, 50, 180]))
        block.add_image(Image(id=f"i{i:02d}", camera_id="c", pose_approx=Pose(opk_to_cam_from_world(*angles), c)))
    for j in range(15):
        xyz = np.array([500000.0, 5400000.0, 300.0]) + rng.uniform([-3000, -3000, -20], [3000, 3000, 80])
        block.add_ground_point(GroundPoint(f"g{j}", xyz + rng.uniform(0, 1e-3, 3),
                                           kind="control" if j % 3 else "check"))
    return block


def check(scene, block, bpy) -> None:
    from oblique_city.addon import cameras, georef

    for img in block.images.values():
        pose = cameras.pose_of(scene, bpy.data.objects[img.id])
        assert np.abs(pose.C - img.pose.C).max() < 1e-3
        assert rotation_angle(pose.R, img.pose.R) < 2e-6
    for g in block.ground_points.values():
        assert np.abs(georef.object_location_world(scene, bpy.data.objects[g.name]) - g.xyz).max() < 1e-3


def test_utm_round_trip_keeps_a_millimetre(addon, tmp_path):
    bpy = addon
    from oblique_city.addon import builders, georef

    block = utm_block_at_300m()
    scene = bpy.context.scene
    builders.build_cameras(scene, block)
    builders.build_ground_points(scene, block)
    origin = georef.get_origin(scene)
    assert origin.dtype == np.float64 and origin[2] == 0.0
    assert np.abs(origin[:2] - [500000.0, 5400000.0]).max() < 3000.0
    bpy.context.view_layer.update()
    check(scene, block, bpy)

    # without the origin, float32 object locations would miss by decimetres at these magnitudes
    naive = np.array([np.float32(img.pose.C) for img in block.images.values()], np.float64)
    assert np.abs(naive - block.centers()).max() > 0.05

    # the origin (a float64 ID property) survives a save and load of the .blend
    path = tmp_path / "utm.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_homefile(app_template="")
    assert not georef.has_georef(bpy.context.scene)
    bpy.ops.wm.open_mainfile(filepath=str(path))
    scene = bpy.context.scene
    assert np.array_equal(georef.get_origin(scene), origin)
    check(scene, block, bpy)


def test_mesh_vertices_back_to_world(addon):
    """Export direction: mesh vertices of a moved and rotated object back to world coordinates within 1 mm."""
    bpy = addon
    from oblique_city.addon import georef

    scene = bpy.context.scene
    georef.set_georef(scene, "EPSG:32632", [500000.0, 5400000.0, 0.0])
    xyz_world = np.array([[500123.4567, 5400987.6543, 301.2345], [498765.4321, 5399012.3456, 299.8765]])
    mesh = bpy.data.meshes.new("m")
    mesh.from_pydata((georef.world_to_local(scene, xyz_world) - [100.0, 200.0, 10.0]).tolist(), [], [])
    obj = bpy.data.objects.new("m", mesh)
    obj.location = (100.0, 200.0, 10.0)
    scene.collection.objects.link(obj)
    bpy.context.view_layer.update()
    assert np.abs(georef.mesh_vertices_world(scene, obj) - xyz_world).max() < 1e-3


def test_scene_in_another_crs_is_refused(addon):
    bpy = addon
    from oblique_city.addon import builders, georef
    from oblique_city.core.errors import WorkspaceError

    scene = bpy.context.scene
    georef.set_georef(scene, "EPSG:25833", [400000.0, 5800000.0, 0.0])
    with pytest.raises(WorkspaceError, match="EPSG:25833"):
        builders.build_cameras(scene, utm_block_at_300m())

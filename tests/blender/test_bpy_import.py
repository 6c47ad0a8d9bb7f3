"""The import operator on a block in every registered format: one camera per image, in collections by cardinal
view, with the block's intrinsics and poses, the image file as background, and the block saved in a workspace."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from oblique_city.core.geometry.rotations import rotation_angle
from oblique_city.core.io.formats import READERS, WRITERS

pytestmark = pytest.mark.xdist_group("bpy")

DEST = {"native": "block.json", "opk": "block.txt", "bex": "block.xml", "colmap": "colmap", "metashape": "cameras.xml",
        "gnssimu": "events.txt"}
"""Where each format's writer puts the test block (a file, or a folder for COLMAP)."""
OPTIONS = {"colmap": "crs=EPSG:32632"}
"""Operator "Options" a format needs (COLMAP models carry no CRS)."""


def write_images(folder: Path, block) -> None:
    import cv2

    rng = np.random.default_rng(2)
    for img in block.images.values():
        cam = block.camera_of(img)
        cv2.imwrite(str(folder / img.file), rng.integers(0, 255, (cam.height, cam.width, 3), dtype=np.uint8))


@pytest.mark.parametrize("auto", [False, True])
@pytest.mark.parametrize("fmt", sorted(READERS))
def test_import_every_format(addon, tmp_path, utm_block, fmt, auto):
    """Each format chosen, or told from the file (Auto; a COLMAP model by picking its cameras.txt)."""
    bpy = addon
    from oblique_city.addon import cameras, georef
    from oblique_city.core.pipeline import Workspace

    source = tmp_path / "src" / DEST[fmt]
    source.parent.mkdir()
    block = utm_block
    if fmt == "gnssimu":  # an event list holds a camera system: here each image an exposure of a one-head rig
        from oblique_city.core.model import Rig, RigHead

        block = copy.deepcopy(utm_block)
        for img in block.images.values():
            img.exposure, img.head = img.id, "cam"
        block.rigs["system"] = Rig("system", (RigHead("cam", "cam", np.eye(3)),))
    WRITERS[fmt](block, str(source))
    write_images(source if source.is_dir() else source.parent, utm_block)
    ws_root = tmp_path / "ws"
    picked = source / "cameras.txt" if auto and source.is_dir() else source
    result = bpy.ops.city.import_block(filepath=str(picked), block_format="auto" if auto else fmt,
                                       workspace=str(ws_root), options=OPTIONS.get(fmt, ""))
    assert result == {"FINISHED"}
    scene = bpy.context.scene
    assert Workspace.open(ws_root).load_block().summary()["images"] == len(utm_block.images)
    assert scene.oblique_city.workspace == str(ws_root.resolve())
    assert georef.get_crs(scene) == "EPSG:32632"

    objs = {o["oc_image_id"]: o for o in bpy.data.objects if o.type == "CAMERA" and "oc_image_id" in o}
    assert sorted(objs) == sorted(utm_block.images)
    for image_id, img in utm_block.images.items():
        obj = objs[image_id]
        assert obj.users_collection[0].name == f"Cameras {img.view}"
        assert obj["oc_view"] == img.view
        cam, ref = cameras.intrinsics_of(obj.data), utm_block.camera_of(img)
        for k in ("width", "height", "fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2"):
            assert getattr(cam, k) == pytest.approx(getattr(ref, k), rel=1e-9, abs=1e-9), k
        pose = cameras.pose_of(scene, obj)
        assert np.abs(pose.C - img.pose.C).max() < 1e-3
        assert rotation_angle(pose.R, img.pose.R) < 1e-6
        bg = obj.data.background_images
        assert obj.data.show_background_images and len(bg) == 1
        assert Path(bpy.path.abspath(bg[0].image.filepath)).name == img.file
        assert bg[0].image.size[:] == (ref.width, ref.height)
    views = {img.view for img in utm_block.images.values()}
    assert {c.name for c in bpy.data.collections if c.name.startswith("Cameras ")} == {f"Cameras {v}" for v in views}


def test_import_error_is_one_line_report(addon, tmp_path):
    bpy = addon
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "oblique_city.block", "crs": "EPSG:32632", "cameras": [], "images": [{"id": "a"}]}')
    with pytest.raises(RuntimeError) as e:
        bpy.ops.city.import_block(filepath=str(bad), block_format="native", workspace=str(tmp_path / "ws"))
    assert "bad.json" in str(e.value) and "camera_id" in str(e.value)
    assert not [o for o in bpy.data.objects if "oc_image_id" in o]
    assert not (tmp_path / "ws" / "block" / "block.json").exists()


def test_import_into_existing_workspace_in_another_crs(addon, tmp_path, utm_block):
    """A workspace in ETRS89 / UTM 32N (EPSG:25832) receives a WGS84 / UTM 32N block reprojected."""
    bpy = addon
    from oblique_city.core.io.native import write_block
    from oblique_city.core.pipeline import Workspace

    Workspace.create(tmp_path / "ws", crs="EPSG:25832")
    write_block(utm_block, tmp_path / "b.json")
    assert bpy.ops.city.import_block(filepath=str(tmp_path / "b.json"), block_format="native",
                                     workspace=str(tmp_path / "ws")) == {"FINISHED"}
    from oblique_city.addon import georef

    assert georef.get_crs(bpy.context.scene) == "EPSG:25832"
    assert Workspace.open(tmp_path / "ws").load_block().crs == "EPSG:25832"


def test_default_workspace_beside_the_block(addon, tmp_path, utm_block):
    """Without a workspace (operator field or scene), the block goes to ``<stem>_city`` beside the source; a second
    import then reuses the scene's workspace."""
    bpy = addon
    from oblique_city.core.io.native import write_block

    write_block(utm_block, tmp_path / "flight7.json")
    assert bpy.ops.city.import_block(filepath=str(tmp_path / "flight7.json"), block_format="native") == {"FINISHED"}
    ws_root = tmp_path / "flight7_city"
    assert (ws_root / "block" / "block.json").is_file()
    assert bpy.context.scene.oblique_city.workspace == str(ws_root.resolve())
    write_block(utm_block, tmp_path / "again.json")
    assert bpy.ops.city.import_block(filepath=str(tmp_path / "again.json"), block_format="native") == {"FINISHED"}
    assert not (tmp_path / "again_city").exists()


def test_opk_operator_fields(addon, tmp_path, utm_block):
    """Angle unit, camera file, ground points and image measurements given in the operator's fields reach the
    reader: without the unit a gon list reads as degrees (wrong attitudes), with it the poses are exact."""
    bpy = addon
    from oblique_city.addon import cameras
    from oblique_city.core.geometry.projection import project
    from oblique_city.core.io.gcp import write_ground_points, write_measurements
    from oblique_city.core.model import GroundPoint
    from oblique_city.core.pipeline import Workspace

    for j, xyz in enumerate([(500100.0, 5399900.0, 310.0), (500300.0, 5400000.0, 305.0)]):
        g = GroundPoint(f"P{j}", np.array(xyz), kind="control" if j == 0 else "check")
        for img in utm_block.images.values():
            uv, _ = project(utm_block.camera_of(img), img.pose, g.xyz[None])
            if utm_block.camera_of(img).contains(uv)[0]:
                g.observations[img.id] = uv[0]
        utm_block.add_ground_point(g)
    n_obs = sum(len(g.observations) for g in utm_block.ground_points.values())
    assert n_obs > 0
    (tmp_path / "intr").mkdir()
    WRITERS["opk"](utm_block, str(tmp_path / "eo.txt"), angles="gon", cameras=str(tmp_path / "intr" / "cams.toml"))
    lines = (tmp_path / "eo.txt").read_text().splitlines()
    (tmp_path / "eo.txt").write_text("\n".join(s for s in lines if not s.startswith(("# angles", "# cameras"))))
    cams = (tmp_path / "intr" / "cams.toml").read_text().splitlines()
    (tmp_path / "intr" / "cams.toml").write_text("\n".join(s for s in cams if not s.startswith("angles")))
    write_ground_points(utm_block, tmp_path / "gcp.csv")
    write_measurements(utm_block, tmp_path / "meas.csv")

    def run(ws: str, **fields):
        return bpy.ops.city.import_block(filepath=str(tmp_path / "eo.txt"), block_format="opk",
                                         workspace=str(tmp_path / ws), **fields)

    with pytest.raises(RuntimeError, match="camera"):
        run("ws0")
    common = {"camera_file": str(tmp_path / "intr" / "cams.toml"), "gcp_file": str(tmp_path / "gcp.csv"),
              "measurements_file": str(tmp_path / "meas.csv")}
    assert run("ws1", **common) == {"FINISHED"}
    scene = bpy.context.scene
    worst = max(rotation_angle(cameras.pose_of(scene, bpy.data.objects[i]).R, img.pose.R)
                for i, img in utm_block.images.items())
    assert worst > 0.01  # 45 gon read as 45 degrees

    assert run("ws2", angle_unit="gon", **common) == {"FINISHED"}
    for image_id, img in utm_block.images.items():
        assert rotation_angle(cameras.pose_of(scene, bpy.data.objects[image_id]).R, img.pose.R) < 1e-6
    points = {o["oc_ground_point"]: o["oc_kind"] for o in bpy.data.objects if "oc_ground_point" in o}
    assert points == {"P0": "control", "P1": "check"}
    block = Workspace.open(tmp_path / "ws2").load_block()
    assert sum(len(g.observations) for g in block.ground_points.values()) == n_obs


def test_adjusted_orientations_only_while_current(addon, tmp_path, utm_block):
    """After aerial triangulation the cameras show the adjusted poses; a block imported later makes them stale,
    and the cameras then show the new imported poses."""
    import copy
    from dataclasses import dataclass

    bpy = addon
    from oblique_city.addon import builders, cameras
    from oblique_city.core.model import Pose
    from oblique_city.core.pipeline import Stage, StageResult, Workspace
    from oblique_city.core.pipeline.registry import register, unregister
    from oblique_city.core.pipeline.runner import fingerprint
    from oblique_city.core.pipeline.workspace import ADJUSTED_BLOCK_FILE

    @dataclass(frozen=True)
    class NoConfig:
        pass

    register(Stage("aerotri", run=lambda ws, cfg, ctx: StageResult(), config=NoConfig))
    try:
        ws = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
        ws.save_block(utm_block)
        adjusted = copy.deepcopy(utm_block)
        for img in adjusted.images.values():
            img.pose_adjusted = Pose(img.pose_approx.R, img.pose_approx.C + [1.0, 0.0, 0.0])
        ws.save_block(adjusted, ADJUSTED_BLOCK_FILE)
        ws.write_state({"aerotri": {"status": "done", "fingerprint": fingerprint(ws, "aerotri", {}),
                                    "outputs": [ADJUSTED_BLOCK_FILE]}})
        scene = bpy.context.scene

        def centre(image_id):
            bpy.context.view_layer.update()  # matrix_world of objects created by a script
            return cameras.pose_of(scene, bpy.data.objects[image_id]).C

        builders.build_scene(scene, ws)
        assert np.abs(centre("img0") - adjusted.images["img0"].pose.C).max() < 1e-3

        moved = copy.deepcopy(utm_block)
        moved.images["img0"].pose_approx = Pose(moved.images["img0"].pose_approx.R,
                                                moved.images["img0"].pose_approx.C + [0.0, 5.0, 0.0])
        ws.save_block(moved)
        builders.build_scene(scene, ws)
        assert np.abs(centre("img0") - moved.images["img0"].pose_approx.C).max() < 1e-3
    finally:
        unregister("aerotri")


def test_exposures_field_restores_the_camera_system(addon, tmp_path, penta_block, plain_opk):
    """A penta block's OPK list without exposure and head columns: the Exposures field (by name, by time) gives the
    workspace's block its exposures and a rig estimated from the orientations; left as given, it has neither."""
    bpy = addon
    from oblique_city.core.pipeline import Workspace

    plain_opk(penta_block, tmp_path / "eo.txt")
    exposures = {img.id: img.exposure for img in penta_block.images.values()}
    for k, fields in enumerate(({"exposures": "name", "exposure_pattern": r"(S\d+_E\d+)_(?P<head>[a-z]+)"},
                                {"exposures": "time", "exposure_tolerance": 0.001}, {})):
        ws = tmp_path / f"ws{k}"
        assert bpy.ops.city.import_block(filepath=str(tmp_path / "eo.txt"), block_format="opk", workspace=str(ws),
                                         **fields) == {"FINISHED"}
        block = Workspace.open(ws).load_block()
        if not fields:
            assert not block.rigs and all(img.exposure is None for img in block.images.values())
            continue
        groups = {}
        for img in block.images.values():
            groups.setdefault(img.exposure, set()).add(exposures[img.id])
        assert all(len(g) == 1 for g in groups.values()) and len(groups) == len(set(exposures.values()))
        assert [h.name for h in block.rigs["system"].heads][0] in ("nadir", "penta_nadir")


def test_gnssimu_heading_field(addon, tmp_path, penta_block):
    """GNSS/IMU events with headings against true north: read as such (the list says so) every image has the
    simulator's orientation; the Heading field set to Grid North turns them all by the grid convergence (2 degrees
    there)."""
    bpy = addon
    from oblique_city.core.pipeline import Workspace

    WRITERS["gnssimu"](penta_block, str(tmp_path / "events.txt"))
    for k, heading in enumerate(("file", "grid")):
        ws = tmp_path / f"ws{k}"
        assert bpy.ops.city.import_block(filepath=str(tmp_path / "events.txt"), block_format="gnssimu",
                                         workspace=str(ws), heading=heading) == {"FINISHED"}
        block = Workspace.open(ws).load_block()
        turn = np.degrees([rotation_angle(block.images[i].pose_approx.R, img.pose_approx.R)
                           for i, img in penta_block.images.items()])
        if heading == "file":
            assert turn.max() < 1e-6
        else:
            assert 1.9 < turn.min() and turn.max() < 2.2


def test_metashape_orientation_field(addon, tmp_path, utm_block):
    """A Metashape file whose first camera's reference (navigation data) lies 11.1 m north of its alignment: the
    Orientation field's Alignment keeps the transform, Reference takes the reference position and angles."""
    bpy = addon
    from lxml import etree

    from oblique_city.core.pipeline import Workspace

    WRITERS["metashape"](utm_block, str(tmp_path / "cameras.xml"))  # the chunk in the block's CRS
    tree = etree.parse(str(tmp_path / "cameras.xml"))
    first = next(tree.iter("camera"))
    ref = first.find("reference")  # the writer's, from the approximate pose
    ref.set("y", repr(float(ref.get("y")) + 11.1))
    ref.set("z", "650")
    tree.write(str(tmp_path / "cameras.xml"))
    label = first.get("label")
    for k, orientation in enumerate(("alignment", "reference")):
        ws = tmp_path / f"ws{k}"
        assert bpy.ops.city.import_block(filepath=str(tmp_path / "cameras.xml"), block_format="metashape",
                                         workspace=str(ws), orientation=orientation) == {"FINISHED"}
        got = Workspace.open(ws).load_block().images[label].pose_approx.C
        moved = np.abs(got - utm_block.images[label].pose.C)
        if orientation == "alignment":
            assert moved.max() < 1e-6
        else:
            assert abs(moved[1] - 11.1) < 1e-6 and moved[0] < 1e-6 and abs(got[2] - 650.0) < 1e-6


def test_fields_of_other_formats_are_left_out(addon, tmp_path, utm_block):
    """A Metashape XML, told from the file or chosen, ignores the OPK fields (angles, camera file) an earlier import
    left set (Blender keeps an operator's last values; the fields are hidden for Metashape), while an option typed
    into the Options field that Metashape does not take is still refused."""
    bpy = addon
    WRITERS["metashape"](utm_block, str(tmp_path / "cameras.xml"))
    kw = {"filepath": str(tmp_path / "cameras.xml"), "angle_unit": "gon", "camera_file": str(tmp_path / "c.toml")}
    for k, fmt in enumerate(("auto", "metashape")):
        assert bpy.ops.city.import_block(block_format=fmt, workspace=str(tmp_path / f"ws{k}"), **kw) == {"FINISHED"}
    with pytest.raises(RuntimeError, match="unknown option.*angles"):
        bpy.ops.city.import_block(block_format="metashape", workspace=str(tmp_path / "ws2"), options="angles=gon",
                                  **kw)

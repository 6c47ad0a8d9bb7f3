"""Measuring ground points by hand in Blender: a click in the camera view becomes the image's own pixel, the
operators record, remove and reset measurements, and the Ground Point Measurement panel lists them."""

from __future__ import annotations

import numpy as np
import pytest
from test_bpy_ui import draw

from oblique_city.core.geometry.projection import project
from oblique_city.core.model import GroundPoint

pytestmark = pytest.mark.xdist_group("bpy")


@pytest.fixture
def gws(grid_ws):
    """The three-image workspace of the UI tests (distorted camera, grid images) with two ground points in sight of
    ``img0``, one measured there by the import."""
    ws = grid_ws
    block = ws.load_block(adjusted=False)
    block.add_ground_point(GroundPoint(name="G1", kind="control", xyz=np.array([500020.0, 5400030.0, 0.0]),
                                       observations={"img0": np.array([640.0, 420.0])}))
    block.add_ground_point(GroundPoint(name="G2", kind="check", xyz=np.array([499900.0, 5399950.0, 0.0])))
    ws.save_block(block)
    return ws


def test_a_click_in_the_camera_view_gives_the_pixel_of_the_original_image(addon, gws, utm_block):
    """The direction through a point of Blender's own camera frame (``view_frame``, with the shift and pixel aspect
    of the image) is the pinhole ray of that pixel (within 1e-3 px); the pixel the click gives is that ray's pixel in
    the original, distorted image, up to pixels away from the pinhole's at the corners."""
    bpy = addon
    from mathutils import Vector

    from oblique_city.addon import cameras

    assert bpy.ops.city.open_workspace(directory=str(gws.root)) == {"FINISHED"}
    assert bpy.ops.city.view_image(camera="img1") == {"FINISHED"}
    scene = bpy.context.scene
    obj = bpy.data.objects["img1"]
    cam = utm_block.camera_of("img1")
    tr, br, bl, tl = (Vector(c) for c in obj.data.view_frame(scene=scene))
    rot = obj.matrix_world.to_3x3().normalized()
    pose = cameras.pose_of(scene, obj)
    moved = []
    for u, v in [(0.0, 0.0), (1199.0, 899.0), (611.3, 437.8), (100.0, 800.0), (1000.5, 50.25)]:
        x, y = (u + 0.5) / cam.width, (v + 0.5) / cam.height
        d = np.array(rot @ (tl + x * (tr - tl) + y * (bl - tl)))
        point = pose.C + 50.0 * d / np.linalg.norm(d)
        assert np.allclose(project(cam, pose, point[None], distort=False)[0][0], (u, v), atol=1e-3)
        uv = cameras.pixel_from_direction(scene, obj, d)
        assert np.allclose(uv, project(cam, pose, point[None])[0][0], atol=1e-6)
        moved.append(np.hypot(*(uv - (u, v))))
    assert max(moved) > 5.0 and min(moved) < 1e-6  # the corners move, the principal point does not


def test_measure_remove_and_reset_from_the_panel(addon, gws):
    """Measure G2 (not measured by the import) at a clicked pixel, remove G1's imported measurement, reset both:
    the manual file and the panel's rows follow each step; without an image looked through the operators ask for
    one."""
    bpy = addon
    from oblique_city.core.matching.manual import MANUAL_FILE, read_manual
    from oblique_city.panels import CITY_PT_ground_points

    ws = gws
    bpy.context.scene.oblique_city.workspace = str(ws.root)
    with pytest.raises(RuntimeError, match="look through an image first"):
        bpy.ops.city.measure_ground_point(point="G2", u=10.0, v=20.0)
    labels = [e[1] for e in draw(CITY_PT_ground_points, bpy.context) if e[0] == "label"]
    assert labels == ["Look through an image (View Through Image) to measure its ground points"]
    assert bpy.ops.city.open_workspace(directory=str(ws.root)) == {"FINISHED"}
    assert bpy.ops.city.view_image(camera="img0") == {"FINISHED"}
    bpy.context.scene.oblique_city.measure_refine = False

    def rows() -> dict[str, str]:
        return {e[1].split(" ")[0]: e[1] for e in draw(CITY_PT_ground_points, bpy.context) if e[0] == "label"
                and e[1].startswith("G")}

    assert rows() == {"G1": "G1 (control): (640.0, 420.0), imported", "G2": "G2 (check): not measured, none"}
    assert bpy.ops.city.measure_ground_point(point="G2", u=512.25, v=300.5) == {"FINISHED"}
    assert bpy.ops.city.edit_ground_measurement(point="G1", action="remove") == {"FINISHED"}
    manual = read_manual(ws.path(MANUAL_FILE))
    assert manual == {"G2": {"img0": {"uv": [512.25, 300.5], "method": "click", "score": None}}, "G1": {"img0": None}}
    assert rows() == {"G1": "G1 (control): not measured, removed", "G2": "G2 (check): (512.2, 300.5), manual"}
    log = draw(CITY_PT_ground_points, bpy.context)
    assert [e[2].action for e in log if e[0] == "operator" and e[1] == "city.edit_ground_measurement"
            and e[2].point == "G2"] == ["remove", "reset"]
    bpy.context.scene.oblique_city.measure_refine = True
    with pytest.raises(RuntimeError, match="no target of 'G2'"):  # between the grid's lines: nothing to fit
        bpy.ops.city.measure_ground_point(point="G2", u=530.0, v=320.0)
    for name in ("G1", "G2"):
        assert bpy.ops.city.edit_ground_measurement(point=name, action="reset") == {"FINISHED"}
    assert read_manual(ws.path(MANUAL_FILE)) == {}
    assert rows() == {"G1": "G1 (control): (640.0, 420.0), imported", "G2": "G2 (check): not measured, none"}


def test_the_overlay_marks_each_ground_point_over_its_pixel(addon, gws, utm_block):
    """The overlay's marks (predicted positions, imported and manual measurements) are scene points that the core
    projects back onto their pixels of the original image (within 1e-6 px) and that Blender's own camera projection
    puts on the same pixels of the undistorted background (within 1e-3 px); its draw handler is installed while the
    add-on is registered."""
    bpy = addon
    from oblique_city.addon import cameras, georef
    from oblique_city.panels import overlay

    assert overlay._handle is not None
    assert bpy.ops.city.open_workspace(directory=str(gws.root)) == {"FINISHED"}
    assert bpy.ops.city.view_image(camera="img0") == {"FINISHED"}
    scene = bpy.context.scene
    scene.oblique_city.measure_refine = False
    assert bpy.ops.city.measure_ground_point(point="G2", u=512.25, v=300.5) == {"FINISHED"}
    cam_obj = bpy.data.objects["img0"]
    cam = utm_block.camera_of("img0")
    pose = cameras.pose_of(scene, cam_obj)
    block = gws.load_block()
    marks = overlay.overlay_points(scene, gws.root, "img0")
    assert {(n, k) for n, k, _ in marks} == {("G1", "predicted"), ("G1", "imported"), ("G2", "predicted"),
                                             ("G2", "measured")}
    expected = {("G1", "imported"): (640.0, 420.0), ("G2", "measured"): (512.25, 300.5),
                **{(n, "predicted"): project(cam, pose, block.ground_points[n].xyz[None])[0][0] for n in ("G1", "G2")}}
    for name, kind, xyz in marks:
        world = georef.local_to_world(scene, xyz[None])
        assert np.allclose(project(cam, pose, world)[0][0], expected[name, kind], atol=1e-6)
        assert np.allclose(cameras.pixel_from_blender(scene, cam_obj, world)[0],
                           project(cam, pose, world, distort=False)[0][0], atol=1e-3)


def test_the_click_tool_records_the_pixel_under_the_mouse(addon, gws, utm_block):
    """The click tool's modal handler, driven by events on a stand-in camera view whose region shows exactly the
    camera's frame (its projection matrix from Blender's own ``calc_matrix_camera``): a click where Blender draws a
    ground point records that point's pixel in the original, distorted image within 0.1 px (measured: 0.04 px, what
    Blender's single-precision view matrices leave when ``view3d_utils`` takes the ray from a point at the clipping
    plane, 800 m from the scene origin; a click is a pixel or so, and "Fit Target" refines it); clicks on the sidebar
    and mouse moves pass through; Esc cancels."""
    from types import SimpleNamespace

    bpy = addon
    from bpy_extras.view3d_utils import location_3d_to_region_2d
    from mathutils import Vector

    from oblique_city.addon import cameras, georef
    from oblique_city.core.matching.manual import MANUAL_FILE, read_manual
    from oblique_city.operators.measure import CITY_OT_measure_ground_point

    assert bpy.ops.city.open_workspace(directory=str(gws.root)) == {"FINISHED"}
    assert bpy.ops.city.view_image(camera="img0") == {"FINISHED"}
    scene = bpy.context.scene
    scene.oblique_city.measure_refine = False
    cam_obj = bpy.data.objects["img0"]
    w, h = scene.render.resolution_x, scene.render.resolution_y
    view = cam_obj.matrix_world.inverted()
    window = cam_obj.calc_matrix_camera(bpy.context.evaluated_depsgraph_get(), x=w, y=h,
                                        scale_x=scene.render.pixel_aspect_x, scale_y=scene.render.pixel_aspect_y)
    rv3d = SimpleNamespace(is_perspective=True, perspective_matrix=window @ view, view_matrix=view)
    main = SimpleNamespace(type="WINDOW", x=0, y=0, width=w, height=h)
    sidebar = SimpleNamespace(type="UI", x=w - 200, y=0, width=200, height=h)
    area = SimpleNamespace(regions=[main, sidebar], spaces=SimpleNamespace(active=SimpleNamespace(region_3d=rv3d)),
                           tag_redraw=lambda: None)
    context = SimpleNamespace(scene=scene, workspace=SimpleNamespace(status_text_set=lambda text: None))
    reports = []
    op = SimpleNamespace(_area=area, point="G2", u=0.0, v=0.0, report=lambda kind, text: reports.append(text))
    op.execute = lambda ctx: CITY_OT_measure_ground_point.execute(op, ctx)

    def event(kind, xy, value="PRESS"):
        return SimpleNamespace(type=kind, value=value, mouse_x=xy[0], mouse_y=xy[1])

    g2 = gws.load_block().ground_points["G2"].xyz
    at = location_3d_to_region_2d(main, rv3d, Vector(georef.world_to_local(scene, g2[None])[0]))
    assert at is not None and 0 < at.x < w - 200 and 0 < at.y < h
    assert CITY_OT_measure_ground_point.modal(op, context, event("MOUSEMOVE", at, "NOTHING")) == {"PASS_THROUGH"}
    assert CITY_OT_measure_ground_point.modal(op, context, event("LEFTMOUSE", (w - 100, h / 2))) == {"PASS_THROUGH"}
    assert CITY_OT_measure_ground_point.modal(op, context, event("LEFTMOUSE", at)) == {"FINISHED"}, reports
    cam = utm_block.camera_of("img0")
    true_uv = project(cam, cameras.pose_of(scene, cam_obj), g2[None])[0][0]
    recorded = read_manual(gws.path(MANUAL_FILE))["G2"]["img0"]
    assert recorded["method"] == "click" and np.allclose(recorded["uv"], true_uv, atol=0.1), (recorded, true_uv)
    assert CITY_OT_measure_ground_point.modal(op, context, event("ESC", at)) == {"CANCELLED"}

"""Workspace operators: Open Workspace, Build Scene from Workspace, View Through Image, Colour Tie Points."""

from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import EnumProperty, StringProperty

from ..addon import backgrounds, builders, cameras
from ..addon.layers_aerotri import REPORT_FILE, TIE_COLOURINGS, colour_tie_points, report_summary
from ..core.errors import CityError
from ..core.pipeline import Workspace
from .run import scene_workspace


def build(context, root: str, report) -> set[str]:
    try:
        ws = Workspace.open(root)
        messages = builders.build_scene(context.scene, ws)
    except CityError as e:
        report({"ERROR"}, str(e).splitlines()[0])
        return {"CANCELLED"}
    report({"INFO"}, "; ".join(messages) or f"{ws.root}: nothing to build yet")
    return {"FINISHED"}


class CITY_OT_open_workspace(bpy.types.Operator):
    """Choose a workspace folder for this scene and build its objects"""

    bl_idname = "city.open_workspace"
    bl_label = "Open Workspace"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Workspace", subtype="DIR_PATH")

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        root = Path(bpy.path.abspath(self.directory))
        if not (root / "project.toml").is_file():
            self.report({"ERROR"}, f"{root}: not a workspace (no project.toml)")
            return {"CANCELLED"}
        context.scene.oblique_city.workspace = str(root)
        return build(context, str(root), self.report)


class CITY_OT_build_scene(bpy.types.Operator):
    """(Re)create the scene objects from the workspace: cameras, and the layers of every finished stage"""

    bl_idname = "city.build_scene"
    bl_label = "Build Scene from Workspace"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        try:
            root = scene_workspace(context)
        except CityError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        return build(context, root, self.report)


class CITY_OT_view_image(bpy.types.Operator):
    """Look through an image's camera: scene camera, render size and pixel aspect of that image, and its
    background undistorted to Blender's pinhole when the lens has distortion"""

    bl_idname = "city.view_image"
    bl_label = "View Through Image"

    camera: StringProperty(name="Camera", description="Camera object name; empty: the active object")

    def execute(self, context):
        obj = bpy.data.objects.get(self.camera) if self.camera else context.active_object
        if obj is None or obj.type != "CAMERA" or "oc_image_id" not in obj:
            self.report({"ERROR"}, "select a camera imported by Oblique City")
            return {"CANCELLED"}
        cameras.apply_render_settings(context.scene, obj)
        settings = context.scene.oblique_city
        if settings.undistort_backgrounds and settings.workspace:
            try:
                ws = Workspace.open(bpy.path.abspath(settings.workspace))
                block = ws.load_block()
                path = backgrounds.background_file(ws.root, block, obj["oc_image_id"], create=True)
            except (CityError, KeyError) as e:
                self.report({"WARNING"}, f"background not undistorted: {str(e).splitlines()[0]}")
            else:
                backgrounds.set_background(obj.data, path)
        area = context.area if context.area is not None and context.area.type == "VIEW_3D" else None
        if area is not None:
            area.spaces.active.region_3d.view_perspective = "CAMERA"
        return {"FINISHED"}


class CITY_OT_colour_tie_points(bpy.types.Operator):
    """Colour the tie point cloud by the rays the adjustment kept of each point, or by its RMS image residual in
    units of the adjustment's sigma0"""

    bl_idname = "city.colour_tie_points"
    bl_label = "Colour Tie Points"
    bl_options = {"REGISTER", "UNDO"}

    colouring: EnumProperty(name="Colour By", items=TIE_COLOURINGS, default="rays")

    def execute(self, context):
        obj = next((o for o in context.scene.objects if "oc_tie_points" in o), None)
        if obj is None:
            self.report({"ERROR"}, "no tie points in the scene (build it once the 'aerotri' stage has run)")
            return {"CANCELLED"}
        try:
            sigma0_px = 1.0
            if self.colouring == "residual":
                sigma0_px = report_summary(Path(scene_workspace(context)) / REPORT_FILE)["sigma0_px"]
            message = colour_tie_points(obj, self.colouring, sigma0_px)
        except CityError as e:
            self.report({"ERROR"}, str(e).splitlines()[0])
            return {"CANCELLED"}
        self.report({"INFO"}, message)
        return {"FINISHED"}

"""Ground point measurement by hand: click a point's target in the image the viewport looks through, remove or
reset a measurement. The core (:mod:`..core.matching.manual`) records them; the next ``aerotri`` run uses them."""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, StringProperty

from ..addon import cameras
from ..core.errors import CityError
from ..core.matching.manual import reset_manual, set_manual
from ..core.pipeline import Workspace
from .run import scene_workspace


def _edit(operator, context, edit) -> set[str]:
    """Run ``edit(ws, image_id)`` (a core edit of the manual measurements) and report its message or error."""
    viewed = cameras.viewed_image(context.scene)
    if viewed is None:
        operator.report({"ERROR"}, "look through an image first (View Through Image)")
        return {"CANCELLED"}
    try:
        message = edit(Workspace.open(Path(scene_workspace(context))), viewed[1])
    except CityError as e:
        operator.report({"ERROR"}, str(e).splitlines()[0])
        return {"CANCELLED"}
    operator.report({"INFO"}, message + "; run 'aerotri' to adjust with it")
    return {"FINISHED"}


class CITY_OT_measure_ground_point(bpy.types.Operator):
    """Measure a ground point in the image the viewport looks through: click its target (Esc cancels). With Fit
    Target the target's centre is fitted near the click"""

    bl_idname = "city.measure_ground_point"
    bl_label = "Measure Ground Point"

    point: StringProperty(name="Point", description="Ground point name")
    u: FloatProperty(name="u", description="Pixel column (centre of the top-left pixel at 0)", precision=3)
    v: FloatProperty(name="v", description="Pixel row (centre of the top-left pixel at 0)", precision=3)

    def execute(self, context):
        refine = context.scene.oblique_city.measure_refine
        return _edit(self, context, lambda ws, iid: set_manual(ws, self.point, iid, np.array([self.u, self.v]),
                                                               refine=refine))

    def invoke(self, context, event):
        viewed = cameras.viewed_image(context.scene)
        area = context.area
        if viewed is None or area is None or area.type != "VIEW_3D" \
                or area.spaces.active.region_3d.view_perspective != "CAMERA":
            self.report({"ERROR"}, "look through an image first (View Through Image), then click the target")
            return {"CANCELLED"}
        self._area = area
        context.workspace.status_text_set(f"Click the target of {self.point} in {viewed[1]}; Esc cancels")
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type in {"ESC", "RIGHTMOUSE"} and event.value == "PRESS":
            context.workspace.status_text_set(None)
            return {"CANCELLED"}
        if event.type != "LEFTMOUSE" or event.value != "PRESS":
            return {"PASS_THROUGH"}  # zoom and pan the view to find the target
        # the view's main region under the mouse (the operator may have been started from the sidebar); the sidebar,
        # header and toolbar drawn over it keep their clicks
        under = {r.type: r for r in self._area.regions
                 if r.x <= event.mouse_x < r.x + r.width and r.y <= event.mouse_y < r.y + r.height}
        region = under.get("WINDOW")
        if region is None or set(under) - {"WINDOW"}:
            return {"PASS_THROUGH"}
        from bpy_extras import view3d_utils

        direction = view3d_utils.region_2d_to_vector_3d(region, self._area.spaces.active.region_3d,
                                                        (event.mouse_x - region.x, event.mouse_y - region.y))
        context.workspace.status_text_set(None)
        viewed = cameras.viewed_image(context.scene)
        if viewed is None:  # the scene camera changed meanwhile
            self.report({"ERROR"}, "look through an image first (View Through Image)")
            return {"CANCELLED"}
        uv = cameras.pixel_from_direction(context.scene, viewed[0], np.array(direction))
        if not np.all(np.isfinite(uv)):
            self.report({"ERROR"}, "the click is not in front of the camera")
            return {"CANCELLED"}
        self.u, self.v = float(uv[0]), float(uv[1])
        self._area.tag_redraw()  # the overlay shows the new measurement
        return self.execute(context)


class CITY_OT_edit_ground_measurement(bpy.types.Operator):
    """Remove a ground point's measurement in the image the viewport looks through, or drop the manual one (the
    imported or automatic measurement applies again)"""

    bl_idname = "city.edit_ground_measurement"
    bl_label = "Edit Ground Point Measurement"

    point: StringProperty(name="Point", description="Ground point name")
    action: EnumProperty(name="Action", items=[
        ("remove", "Remove", "The point is not measured in this image"),
        ("reset", "Reset", "Drop the manual measurement: the imported or automatic one applies again")])
    all_images: BoolProperty(name="All Images", default=False, description="Reset in every image")

    def execute(self, context):
        if self.action == "remove":
            return _edit(self, context, lambda ws, iid: set_manual(ws, self.point, iid, None))
        return _edit(self, context, lambda ws, iid: reset_manual(ws, self.point, None if self.all_images else iid))

"""Refresh Building List: fill the Buildings panel's list from the workspace without rebuilding the objects."""

from __future__ import annotations

import bpy

from ..addon import layers_buildings
from ..core.errors import CityError
from ..core.pipeline import Workspace
from .run import scene_workspace


class CITY_OT_refresh_buildings(bpy.types.Operator):
    """Read buildings/report.json and buildings.json again into the Buildings panel's list"""

    bl_idname = "city.refresh_buildings"
    bl_label = "Refresh Building List"

    def execute(self, context):
        try:
            n = layers_buildings.fill_building_list(context.scene, Workspace.open(scene_workspace(context)))
        except (CityError, OSError, ValueError) as e:
            self.report({"ERROR"}, str(e).splitlines()[0])
            return {"CANCELLED"}
        self.report({"INFO"}, f"{n} buildings listed")
        return {"FINISHED"}

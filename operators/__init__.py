"""Operators: import a block, run stages as cancellable jobs, open / build / view a workspace, export (buildings and
the oriented block), open the triangulation report and the project report, refresh the building list, colour
the tie points, measure ground points by hand."""

from __future__ import annotations

from .buildings import CITY_OT_refresh_buildings
from .export import CITY_OT_export_block, CITY_OT_export_city_model, menu_export
from .import_block import CITY_OT_import_block
from .measure import CITY_OT_edit_ground_measurement, CITY_OT_measure_ground_point
from .report import CITY_OT_open_project_report, CITY_OT_open_report
from .run import CITY_OT_cancel_job, CITY_OT_run_stages
from .workspace import CITY_OT_build_scene, CITY_OT_colour_tie_points, CITY_OT_open_workspace, CITY_OT_view_image

CLASSES = (CITY_OT_import_block, CITY_OT_run_stages, CITY_OT_cancel_job, CITY_OT_open_workspace,
           CITY_OT_build_scene, CITY_OT_view_image, CITY_OT_export_city_model, CITY_OT_export_block,
           CITY_OT_open_report, CITY_OT_open_project_report, CITY_OT_refresh_buildings, CITY_OT_colour_tie_points,
           CITY_OT_measure_ground_point, CITY_OT_edit_ground_measurement)

__all__ = ["CLASSES", "menu_export", "menu_import"]


def menu_import(self, context) -> None:
    """File > Import entry."""
    self.layout.operator(CITY_OT_import_block.bl_idname, text="Oriented Image Block (Oblique City)")

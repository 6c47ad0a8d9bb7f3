"""Open Report: the aerial triangulation's HTML report (``aerotri/report.html``) in the system's web browser
(:mod:`webbrowser`, which also works where Blender has no window manager); Project Report: the workspace's project
report (:func:`core.report.write_project_report`, as ``oblique-city report``) written anew and opened the same way."""

from __future__ import annotations

import webbrowser
from pathlib import Path

import bpy

from ..addon.layers_aerotri import REPORT_HTML
from ..core.errors import CityError
from ..core.report import write_project_report
from .run import scene_workspace


def open_in_browser(op: bpy.types.Operator, path: Path, done: str) -> set[str]:
    """Open the HTML file ``path`` in the web browser and report ``done`` (or that no browser was found)."""
    if not webbrowser.open(path.resolve().as_uri()):
        op.report({"WARNING"}, f"no web browser found: open {path} by hand")
        return {"CANCELLED"}
    op.report({"INFO"}, f"{done} {path}")
    return {"FINISHED"}


class CITY_OT_open_report(bpy.types.Operator):
    """Open the aerial triangulation report (HTML) of the scene's workspace in the web browser"""

    bl_idname = "city.open_report"
    bl_label = "Open Report"

    def execute(self, context):
        try:
            path = Path(scene_workspace(context)) / REPORT_HTML
        except CityError as e:
            self.report({"ERROR"}, str(e).splitlines()[0])
            return {"CANCELLED"}
        if not path.is_file():
            self.report({"ERROR"}, f"{path}: no triangulation report (run the 'aerotri' stage)")
            return {"CANCELLED"}
        return open_in_browser(self, path, "opened")


class CITY_OT_open_project_report(bpy.types.Operator):
    """Write the project report of the scene's workspace (block, stages, metrics, pictures) and open it in the web
    browser"""

    bl_idname = "city.open_project_report"
    bl_label = "Project Report"

    def execute(self, context):
        try:
            path = write_project_report(scene_workspace(context))
        except CityError as e:
            self.report({"ERROR"}, str(e).splitlines()[0])
            return {"CANCELLED"}
        return open_in_browser(self, path, "wrote and opened")

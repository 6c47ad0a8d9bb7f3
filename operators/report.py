"""Open Report: the aerial triangulation's HTML report (``aerotri/report.html``) in the system's web browser
(:mod:`webbrowser`, which also works where Blender has no window manager)."""

from __future__ import annotations

import webbrowser
from pathlib import Path

import bpy

from ..addon.layers_aerotri import REPORT_HTML
from ..core.errors import CityError
from .run import scene_workspace


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
        if not webbrowser.open(path.resolve().as_uri()):
            self.report({"WARNING"}, f"no web browser found: open {path} by hand")
            return {"CANCELLED"}
        self.report({"INFO"}, f"opened {path}")
        return {"FINISHED"}

"""File > Export > City Model: the workspace's buildings as OBJ, CityGML 2.0 LoD2 or CityJSON 2.0; File > Export >
Oriented Image Block: its block in another software's format.

The operators call :func:`core.export.command.export_buildings` and :func:`core.export.command.export_block`,
the functions behind ``oblique-city export`` and ``oblique-city export-block``, on the scene's workspace, so the
files are the same as the CLI's; CityGML is schema-validated and CityJSON structure-checked unless "Validate" is
off. A core error is reported as one line.
"""

from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, StringProperty
from bpy_extras.io_utils import ExportHelper

from ..core.errors import CityError
from ..core.export.command import export_block, export_buildings
from ..core.io.formats import WRITERS
from .import_block import enum_items, parse_options
from .run import scene_workspace

EXTENSIONS = {"citygml": ".gml", "cityjson": ".city.json", "obj": ".obj", "3dtiles": "", "geojson": ".geojson"}
FORMAT_ITEMS = [
    ("citygml", "CityGML 2.0", "CityGML 2.0 LoD2 buildings with typed surfaces (.gml), schema-validated"),
    ("cityjson", "CityJSON 2.0", "CityJSON 2.0 LoD2 buildings with semantic surfaces (.city.json)"),
    ("obj", "Wavefront OBJ", "Triangulated meshes with one group per building (.obj)"),
    ("3dtiles", "3D Tiles 1.1", "tileset.json and glTF tiles for web globes (a folder)"),
    ("geojson", "GeoJSON footprints", "Building footprints with heights, areas, volume and roof type (WGS 84)"),
]


def with_extension(path: str, fmt: str) -> str:
    """``path`` with the format's extension (``.city.json`` counts as one extension; 3D Tiles, a folder, get none:
    a known extension is taken off)."""
    ext = EXTENSIONS[fmt]
    if ext and path.endswith(ext):
        return path
    p = Path(path)
    stem = p.name
    for e in sorted((e for e in EXTENSIONS.values() if e), key=len, reverse=True):
        if stem.endswith(e):
            stem = stem[: -len(e)]
            break
    else:
        stem = p.stem if p.suffix and ext else stem
    return str(p.with_name(stem + ext))


class CITY_OT_export_city_model(bpy.types.Operator, ExportHelper):
    """Export the workspace's reconstructed buildings (OBJ, CityGML 2.0 LoD2, CityJSON 2.0)"""

    bl_idname = "city.export_city_model"
    bl_label = "Export City Model"

    filename_ext = ".gml"
    filter_glob: StringProperty(default="*.gml;*.json;*.obj;*.geojson", options={"HIDDEN"})
    format: EnumProperty(name="Format", items=FORMAT_ITEMS, default="citygml")
    validate: BoolProperty(name="Validate", default=True,
                           description="Check the written file (CityGML 2.0 schema, CityJSON structure)")
    height_offset: FloatProperty(name="Height Offset", default=0.0, unit="LENGTH",
                                 description="3D Tiles: metres added to the heights to make them ellipsoidal (the "
                                             "geoid undulation when the project's heights are orthometric)")

    def check(self, context) -> bool:
        new = with_extension(self.filepath, self.format)
        changed = new != self.filepath
        self.filepath = new
        return changed

    def invoke(self, context, event):
        if not self.filepath:
            try:
                name = Path(scene_workspace(context)).name or "city"
            except CityError:
                name = "city"
            self.filepath = name + EXTENSIONS[self.format]
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        if not self.filepath:
            self.report({"ERROR"}, "no output file given")
            return {"CANCELLED"}
        out = bpy.path.abspath(with_extension(self.filepath, self.format))
        try:
            summary = export_buildings(scene_workspace(context), self.format, out, validate=self.validate,
                                       height_offset=self.height_offset)
        except CityError as e:
            self.report({"ERROR"}, str(e).splitlines()[0])
            return {"CANCELLED"}
        self.report({"INFO"}, summary)
        return {"FINISHED"}


BLOCK_EXTENSIONS = {"bex": ".xml", "metashape": ".xml", "opk": ".txt", "native": ".json", "colmap": "",
                    "gnssimu": ".txt"}
"""Block format -> file extension (COLMAP writes a folder)."""

_block_items: list[tuple[str, str, str]] = []


def block_format_items(self, context) -> list[tuple[str, str, str]]:
    """Enum items from the registered block writers."""
    return enum_items(WRITERS, _block_items)


class CITY_OT_export_block(bpy.types.Operator, ExportHelper):
    """Export the workspace's oriented image block (adjusted after aerial triangulation) for other software"""

    bl_idname = "city.export_block"
    bl_label = "Export Oriented Image Block"

    filename_ext = ""
    filter_glob: StringProperty(default="*.xml;*.txt;*.json", options={"HIDDEN"})
    format: EnumProperty(name="Format", items=block_format_items)
    imported: BoolProperty(name="Imported Orientation", default=False,
                           description="Write the imported block even when aerial triangulation adjusted it")
    options: StringProperty(name="Options", default="",
                            description="Writer options as key=value; key=value (e.g. rotation=opk, angles=gon)")

    def execute(self, context):
        if not self.filepath:
            self.report({"ERROR"}, "no output file given")
            return {"CANCELLED"}
        path = bpy.path.abspath(self.filepath)
        ext = BLOCK_EXTENSIONS.get(self.format, "")
        if ext and not path.lower().endswith(ext):
            path += ext
        try:
            summary = export_block(scene_workspace(context), self.format, path, adjusted=not self.imported,
                                   **parse_options(self.options))
        except CityError as e:
            self.report({"ERROR"}, str(e).splitlines()[0])
            return {"CANCELLED"}
        self.report({"INFO"}, summary)
        return {"FINISHED"}


def menu_export(self, context) -> None:
    """File > Export entries: the city model, one per format, and the oriented image block."""
    for fmt, label, _ in FORMAT_ITEMS:
        op = self.layout.operator(CITY_OT_export_city_model.bl_idname, text=f"City Model: {label} (Oblique City)")
        op.format = fmt
    self.layout.operator(CITY_OT_export_block.bl_idname, text="Oriented Image Block (Oblique City)")

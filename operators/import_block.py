"""File > Import > Oriented Image Block: read a block in any registered format into a workspace and build it.

The format list is :data:`core.io.formats.READERS`, so a reader registered there appears here without changes.
Reader options the user leaves empty are not passed at all (readers reject options they do not know, so a wrong
option is a clear error rather than silently ignored); anything else goes through the "Options" field as
``key=value`` pairs separated by ``;``, exactly as ``-o key=value`` on the CLI.
"""

from __future__ import annotations

import json
from pathlib import Path

import bpy
from bpy.props import EnumProperty, FloatProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ..addon import builders
from ..core.errors import CityError, ConfigError
from ..core.geometry.crs import normalize_crs, transform_points
from ..core.io.formats import READERS, detect_format, read_block
from ..core.io.formats import reader_options as format_options
from ..core.io.reproject import reproject_block
from ..core.model import ImageBlock
from ..core.model.exposures import describe_system
from ..core.pipeline import Workspace

FORMAT_LABELS = {
    "auto": ("Auto", "Told from the file: a JSON block, BlocksExchange or Metashape XML, a COLMAP model folder, an "
                     "OPK list or GNSS/IMU events by their header"),
    "native": ("Oblique City JSON", "The workspace's own block file (block.json)"),
    "opk": ("OPK List", "Text/CSV list: image, X, Y, Z, omega, phi, kappa, with a camera file"),
    "bex": ("BlocksExchange XML", "ContextCapture / iTwin Capture BlocksExchange"),
    "colmap": ("COLMAP Model", "COLMAP text or binary model folder (cameras, images, points3D)"),
    "metashape": ("Metashape Camera XML", "Agisoft Metashape cameras exported as Agisoft XML"),
    "gnssimu": ("GNSS/IMU Events", "Per exposure: position, roll, pitch, heading; a camera file with the heads' "
                                   "mounts and lever arms"),
}
FOLDER_FORMATS = {"colmap"}
"""Formats whose source is a folder: picking a file inside it imports the folder."""

COLMAP_FILES = {f"{name}.{ext}" for name in ("cameras", "images", "points3D", "rigs", "frames")
                for ext in ("txt", "bin")}
"""A COLMAP model's files: with the format told from the file, picking one imports its folder."""

FIELD_OPTIONS = ("angles", "heading", "cameras", "orientation")
"""Reader options of the dialog's fields that only some formats take: left out for a format (chosen or told from
the file) that does not take them."""

_format_items: list[tuple[str, str, str]] = []


def enum_items(names, store: list) -> list[tuple[str, str, str]]:
    """Enum items of block format ``names`` with their labels, written into ``store`` (a module-level list kept
    alive, as Blender requires for dynamic enums)."""
    store[:] = [(name, *FORMAT_LABELS.get(name, (name, f"Block format '{name}'"))) for name in names]
    return store


def format_items(self, context) -> list[tuple[str, str, str]]:
    """Enum items from the registered readers, after Auto (the format told from the file)."""
    return enum_items(["auto", *READERS], _format_items)


def parse_options(text: str) -> dict[str, object]:
    """``"angles=gon; crs=EPSG:25832"`` -> dict; values are JSON when they parse as JSON, else strings."""
    out: dict[str, object] = {}
    for part in text.replace("\n", ";").split(";"):
        part = part.strip()
        if not part:
            continue
        if "=" not in part:
            raise ConfigError(f"option '{part}' should look like key=value")
        k, v = (s.strip() for s in part.split("=", 1))
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def import_into_workspace(fmt: str, source: str | Path, ws_root: str | Path, **options) -> tuple[Workspace,
                                                                                                   ImageBlock]:
    """Read a block and save it into a workspace (created if needed, in the block's CRS; an existing workspace in
    another CRS gets the block reprojected). Relative image paths are anchored at the source's folder."""
    source = Path(source)
    block = read_block(fmt, source, **options)
    if block.image_root is None:
        block.image_root = str((source if source.is_dir() else source.parent).resolve())
    elif not Path(block.image_root).is_absolute():
        block.image_root = str(((source if source.is_dir() else source.parent) / block.image_root).resolve())
    root = Path(ws_root)
    ws = Workspace.open(root) if (root / "project.toml").exists() else Workspace.create(root, crs=block.crs)
    if normalize_crs(block.crs) != normalize_crs(ws.crs):
        block = reproject_block(block, ws.crs, transform_points)
    ws.save_block(block)
    return ws, block


class CITY_OT_import_block(bpy.types.Operator, ImportHelper):
    """Import an oriented image block: one camera per image, grouped by cardinal view"""

    bl_idname = "city.import_block"
    bl_label = "Import Oriented Image Block"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filter_glob: StringProperty(default="*.json;*.xml;*.txt;*.csv;*.opk;*.dat;*.bin", options={"HIDDEN"})
    block_format: EnumProperty(name="Format", items=format_items)
    angle_unit: EnumProperty(
        name="Angles", description="Unit of omega, phi, kappa (OPK lists) or roll, pitch, heading (GNSS/IMU events)",
        items=[("file", "From File", "Use the file's header or camera file (default degrees)"),
               ("deg", "Degrees", ""), ("gon", "Gon", ""), ("rad", "Radians", "")],
        default="file",
    )
    heading: EnumProperty(
        name="Heading", description="What the GNSS/IMU events' headings are measured from",
        items=[("file", "From File", "The list's '# heading:' line, else true north"),
               ("true", "True North", "As an inertial system gives it: the grid convergence is applied"),
               ("grid", "Grid North", "Already against the map grid's north")],
        default="file",
    )
    orientation: EnumProperty(
        name="Orientation", description="Which orientation of a Metashape camera the block takes",
        items=[("alignment", "Alignment", "Metashape's aligned transform where the camera has one, else its "
                                          "reference (navigation data)"),
               ("reference", "Reference", "The camera's reference position and yaw, pitch, roll (the navigation "
                                          "data, for a triangulation of its own) where it has one")],
        default="alignment",
    )
    camera_file: StringProperty(name="Camera File", subtype="FILE_PATH",
                                description="Intrinsics (TOML or JSON) for OPK lists, with the heads for GNSS/IMU "
                                            "events; empty: beside the list")
    gcp_file: StringProperty(name="Ground Points", subtype="FILE_PATH",
                             description="Ground control / check point list (optional)")
    measurements_file: StringProperty(name="Image Measurements", subtype="FILE_PATH",
                                      description="Ground point measurements in the images (optional)")
    image_folder: StringProperty(name="Image Folder", subtype="DIR_PATH",
                                 description="Folder relative image paths start from (optional)")
    exposures: EnumProperty(
        name="Exposures", description="Which images one trigger of a multi-head camera took (HAT and rig constraints "
                                       "need them); the rig is the file's (COLMAP, GNSS/IMU events) or estimated from "
                                       "the orientations",
        items=[("given", "As Given", "As the file gives them (OPK columns exposure and head, COLMAP frames, "
                                     "Metashape multi-camera systems, GNSS/IMU events; Oblique City blocks)"),
               ("time", "By Time", "Images whose times (OPK column time) lie within the tolerance of each other"),
               ("name", "By Name", "A regular expression over the image name; its first group (or the group "
                                   "named exposure) names the exposure, a group named head the head")],
        default="given",
    )
    exposure_pattern: StringProperty(name="Name Pattern", default=r"(?P<exposure>.+)_(?P<head>[^_]+)",
                                     description="Regular expression matched against the whole image name")
    exposure_tolerance: FloatProperty(name="Tolerance", default=0.01, min=0.0, unit="TIME_ABSOLUTE",
                                      description="Largest time step between the images of one exposure, seconds")
    options: StringProperty(name="Options", description="More reader options: key=value; key=value (each "
                                                        "format's are listed by oblique-city import --help)")
    workspace: StringProperty(name="Workspace", subtype="DIR_PATH",
                              description="Workspace folder (created if needed); empty: the scene's workspace, "
                                          "else a folder beside the block named <block>_city")

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "block_format")
        fmt = self.block_format
        if fmt in ("opk", "gnssimu", "auto"):
            layout.prop(self, "angle_unit")
        if fmt in ("gnssimu", "auto"):
            layout.prop(self, "heading")
        if fmt in ("opk", "gnssimu", "auto"):
            layout.prop(self, "camera_file")
        if fmt in ("metashape", "auto"):
            layout.prop(self, "orientation")
        layout.prop(self, "gcp_file")
        layout.prop(self, "measurements_file")
        layout.prop(self, "image_folder")
        layout.prop(self, "exposures")
        if self.exposures == "name":
            layout.prop(self, "exposure_pattern")
        elif self.exposures == "time":
            layout.prop(self, "exposure_tolerance")
        layout.prop(self, "options")
        layout.prop(self, "workspace")

    def reader_options(self, fmt: str) -> dict[str, object]:
        """The dialog's fields as the options of the reader of ``fmt`` (the format told from the file for Auto)."""
        opts: dict[str, object] = {}
        if self.angle_unit != "file":
            opts["angles"] = self.angle_unit
        if fmt == "gnssimu" and self.heading != "file":
            opts["heading"] = self.heading
        if fmt == "metashape" and self.orientation != "alignment":
            opts["orientation"] = self.orientation
        if self.camera_file:
            opts["cameras"] = bpy.path.abspath(self.camera_file)
        if self.gcp_file:
            opts["gcps"] = bpy.path.abspath(self.gcp_file)
        if self.measurements_file:
            opts["measurements"] = bpy.path.abspath(self.measurements_file)
        if self.image_folder:
            opts["image_root"] = bpy.path.abspath(self.image_folder)
        if self.exposures == "time":
            opts.update(exposures="time", exposure_tolerance=self.exposure_tolerance)
        elif self.exposures == "name":
            opts.update(exposures="name", exposure_pattern=self.exposure_pattern)
        takes = format_options(fmt)  # a hidden field keeps the value of an earlier import in another format
        opts = {k: v for k, v in opts.items() if k not in FIELD_OPTIONS or k in takes}
        opts.update(parse_options(self.options))
        return opts

    def source_path(self) -> Path:
        path = Path(bpy.path.abspath(self.filepath))
        if path.is_file() and (self.block_format in FOLDER_FORMATS
                               or (self.block_format == "auto" and path.name in COLMAP_FILES)):
            return path.parent
        return path

    def workspace_path(self, context, source: Path) -> Path:
        if self.workspace:
            return Path(bpy.path.abspath(self.workspace))
        if context.scene.oblique_city.workspace:
            return Path(bpy.path.abspath(context.scene.oblique_city.workspace))
        return source.parent / f"{source.name if source.is_dir() else source.stem}_city"

    def execute(self, context):
        try:
            source = self.source_path()
            fmt = detect_format(source) if self.block_format == "auto" else self.block_format
            ws, block = import_into_workspace(fmt, source, self.workspace_path(context, source),
                                              **self.reader_options(fmt))
            messages = builders.build_scene(context.scene, ws, stages=["block"])
        except CityError as e:
            self.report({"ERROR"}, str(e).splitlines()[0])
            return {"CANCELLED"}
        s = block.summary()
        system = describe_system(block)
        self.report({"INFO"}, f"Imported {s['images']} images into {ws.root}: {'; '.join(messages)}"
                    + (f"; {system}" if system else ""))
        return {"FINISHED"}

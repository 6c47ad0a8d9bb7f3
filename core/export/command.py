"""``oblique-city export WS --format obj|citygml|cityjson|3dtiles|geojson --out PATH``: the buildings of a workspace
to a file (a folder for 3D Tiles; footprints with attributes for GeoJSON);
``oblique-city export-block WS --format bex|metashape|opk|colmap|native|gnssimu --out PATH``: its oriented image block
(the aerial triangulation's adjusted orientations and cameras when it has run, else the imported ones), for other
photogrammetry software.

When the ``texture`` stage has run (``texture/textures.json``), the export carries its atlases (pages copied
beside the output) unless ``--no-textures``; without it the export is untextured. When the ``windows`` stage has
run (``windows/windows.json``), the detected windows go along unless ``--no-windows``: an OBJ group
``<building>_windows``, CityGML ``bldg:opening/bldg:Window`` (LoD3 openings of the LoD2 wall surfaces), CityJSON
``BuildingInstallation`` children with ``Window`` semantic surfaces.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from ..errors import ComputationError, ConfigError

FORMATS = ("obj", "citygml", "cityjson", "3dtiles", "geojson")

MAX_HEIGHT_OFFSET = 200.0
"""The largest height offset (m) the export takes: the geoid's undulation stays within -107 and +86 m."""


def export_buildings(workspace: str | Path, fmt: str, out: str | Path, validate: bool = True,
                     with_textures: bool = True, with_windows: bool = True, height_offset: float = 0.0) -> str:
    """Write the workspace's ``buildings/buildings.json`` as ``fmt`` (textured when the texture stage's output
    exists and ``with_textures``, with the detected windows when the windows stage's output exists and
    ``with_windows``); returns a one-line summary."""
    from ..buildings.model import load_buildings
    from ..pipeline import Workspace

    out = Path(out)
    if fmt != "3dtiles" and out.is_dir():  # (checked by the atomic writes too, but only after the work)
        raise ConfigError(f"{out} is a folder: give the {fmt} file's name")
    if not (math.isfinite(height_offset) and abs(height_offset) <= MAX_HEIGHT_OFFSET):
        raise ConfigError(f"the height offset is the geoid undulation in metres, within +-{MAX_HEIGHT_OFFSET:.0f}; "
                          f"got {height_offset}")
    ws = Workspace.open(workspace)
    buildings, crs = load_buildings(ws.path("buildings", "buildings.json"))
    crs = crs or ws.crs
    textures = None
    if with_textures and ws.path("texture", "textures.json").exists():
        from ..texture.atlas import load_textures

        textures = load_textures(ws.path("texture", "textures.json"))
    note = (f", {len(textures.surfaces)} textured surfaces on {len(textures.pages)} atlas pages"
            if textures is not None else "")
    windows = None
    if with_windows and ws.path("windows", "windows.json").exists():
        from ..windows.store import load_windows, windows_by_surface

        windows = windows_by_surface(load_windows(ws.path("windows", "windows.json")))
        note += f", {sum(len(v) for v in windows.values())} windows"
    if fmt == "obj":
        from .obj import write_obj

        origin = np.floor(np.concatenate([b.vertices for b in buildings]).min(0)) if buildings else None
        write_obj(out, buildings, origin, textures, windows)
        return f"{len(buildings)} buildings written to {out} (origin {origin}{note})"
    if fmt == "citygml":
        from .citygml import validate_citygml, write_citygml

        write_citygml(out, buildings, crs, textures, windows)
        if validate:
            errors = validate_citygml(out)
            if errors:
                raise ComputationError(f"{out}: CityGML 2.0 schema validation failed: {errors[0]} "
                                       f"({len(errors)} errors)")
        return f"{len(buildings)} buildings written to {out}" + (" (valid CityGML 2.0)" if validate else "") + note
    if fmt == "cityjson":
        from .cityjson import check_cityjson, read_cityjson, write_cityjson

        write_cityjson(out, buildings, crs, textures, windows)
        if validate:
            errors = check_cityjson(read_cityjson(out))
            if errors:
                raise ComputationError(f"{out}: CityJSON structure check failed: {errors[0]}")
        return f"{len(buildings)} buildings written to {out}" + (" (structure checked)" if validate else "") + note
    if fmt == "geojson":
        from .geojson import write_footprints_geojson

        write_footprints_geojson(out, buildings, crs)
        return f"{len(buildings)} building footprints with their attributes written to {out} (WGS 84)"
    if fmt == "3dtiles":
        from .tiles import write_3dtiles

        if out.exists() and not out.is_dir():
            raise ConfigError(f"{out} is a file: 3D Tiles go into a folder (tileset.json and .glb tiles)")
        files = write_3dtiles(out, buildings, crs, textures, windows, height_offset=height_offset)
        return (f"{len(buildings)} buildings written to {out / 'tileset.json'} ({(len(files) - 1) // 2} tiles, each "
                f"as LoD 1.2 blocks and LoD2 models in glTF{note})")
    raise ConfigError(f"unknown export format '{fmt}' (known: {', '.join(FORMATS)})")


def export_block(workspace: str | Path, fmt: str, out: str | Path, adjusted: bool = True, **options) -> str:
    """Write the workspace's block in block format ``fmt`` (see :data:`..io.formats.WRITERS`; ``options`` go to
    the writer) and return a one-line summary. ``adjusted``: the aerial triangulation's block when it exists
    (adjusted orientations and cameras), else the imported one."""
    from ..io.formats import WRITERS, write_block
    from ..pipeline import Workspace
    from ..pipeline.workspace import ADJUSTED_BLOCK_FILE

    if fmt not in WRITERS:
        raise ConfigError(f"unknown block format '{fmt}' (known: {', '.join(sorted(WRITERS))})")
    ws = Workspace.open(workspace)
    block = ws.load_block(adjusted=adjusted)
    which = "adjusted" if adjusted and (ws.root / ADJUSTED_BLOCK_FILE).exists() else "imported"
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_block(fmt, block, out, **options)
    s = block.summary()
    return (f"{which} block written to {out} ({fmt}): {s['images']} images, {s['cameras']} cameras, "
            f"{s['control_points']} control and {s['check_points']} check points")


def cmd_export(args: argparse.Namespace) -> int:
    print(export_buildings(args.workspace, args.format, args.out, validate=not args.no_validate,
                           with_textures=not args.no_textures, with_windows=not args.no_windows,
                           height_offset=args.height_offset))
    return 0


def add_commands(sub) -> None:
    s = sub.add_parser("export", help="export the reconstructed buildings (OBJ, CityGML 2.0 LoD2, CityJSON 2.0, "
                                      "3D Tiles 1.1, GeoJSON footprints)")
    s.add_argument("workspace")
    s.add_argument("--format", required=True, choices=FORMATS)
    s.add_argument("--out", required=True, help="output file (a folder for 3dtiles)")
    s.add_argument("--no-validate", action="store_true", help="skip the schema / structure check")
    s.add_argument("--no-textures", action="store_true", help="leave out the texture stage's atlases")
    s.add_argument("--no-windows", action="store_true", help="leave out the windows stage's windows")
    s.add_argument("--height-offset", type=float, default=0.0, metavar="M",
                   help="3dtiles: metres added to the heights to make them ellipsoidal (the geoid undulation when "
                        "the project's heights are orthometric)")
    s.set_defaults(func=cmd_export)

    from ..io.formats import WRITERS, writer_options

    s = sub.add_parser("export-block", help="export the oriented image block (adjusted after aerial triangulation) "
                                            "for other software",
                       epilog="writer options (-o KEY=VALUE) and their defaults:\n" + "\n".join(
                           f"  {fmt:10s} " + (", ".join(f"{k}={v}" for k, v in writer_options(fmt).items()) or "none")
                           for fmt in sorted(WRITERS)), formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("workspace")
    s.add_argument("--format", required=True, choices=sorted(WRITERS))
    s.add_argument("--out", required=True, help="output file (a folder for colmap)")
    s.add_argument("--imported", action="store_true", help="the imported block even when an adjusted one exists")
    s.add_argument("-o", "--option", action="append", metavar="KEY=VALUE",
                   help="writer option (e.g. rotation=opk for bex, angles=gon for opk, binary=true for colmap)")
    s.set_defaults(func=cmd_export_block)


def cmd_export_block(args: argparse.Namespace) -> int:
    from ..cli import parse_options

    print(export_block(args.workspace, args.format, args.out, adjusted=not args.imported,
                       **parse_options(args.option)))
    return 0

"""``oblique-city export WS --format obj|citygml|cityjson --out PATH``: the buildings of a workspace to a file."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..errors import ComputationError, ConfigError

FORMATS = ("obj", "citygml", "cityjson")


def export_buildings(workspace: str | Path, fmt: str, out: str | Path, validate: bool = True) -> str:
    """Write the workspace's ``buildings/buildings.json`` as ``fmt``; returns a one-line summary."""
    from ..buildings.model import load_buildings
    from ..pipeline import Workspace

    ws = Workspace.open(workspace)
    buildings, crs = load_buildings(ws.path("buildings", "buildings.json"))
    crs = crs or ws.crs
    out = Path(out)
    if fmt == "obj":
        from .obj import write_obj

        origin = np.floor(np.concatenate([b.vertices for b in buildings]).min(0)) if buildings else None
        write_obj(out, buildings, origin)
        return f"{len(buildings)} buildings written to {out} (origin {origin})"
    if fmt == "citygml":
        from .citygml import validate_citygml, write_citygml

        write_citygml(out, buildings, crs)
        if validate:
            errors = validate_citygml(out)
            if errors:
                raise ComputationError(f"{out}: CityGML 2.0 schema validation failed: {errors[0]} "
                                       f"({len(errors)} errors)")
        return f"{len(buildings)} buildings written to {out}" + (" (valid CityGML 2.0)" if validate else "")
    if fmt == "cityjson":
        from .cityjson import check_cityjson, read_cityjson, write_cityjson

        write_cityjson(out, buildings, crs)
        if validate:
            errors = check_cityjson(read_cityjson(out))
            if errors:
                raise ComputationError(f"{out}: CityJSON structure check failed: {errors[0]}")
        return f"{len(buildings)} buildings written to {out}" + (" (structure checked)" if validate else "")
    raise ConfigError(f"unknown export format '{fmt}' (known: {', '.join(FORMATS)})")


def cmd_export(args: argparse.Namespace) -> int:
    print(export_buildings(args.workspace, args.format, args.out, validate=not args.no_validate))
    return 0


def add_commands(sub) -> None:
    s = sub.add_parser("export", help="export the reconstructed buildings (OBJ, CityGML 2.0 LoD2, CityJSON 2.0)")
    s.add_argument("workspace")
    s.add_argument("--format", required=True, choices=FORMATS)
    s.add_argument("--out", required=True, help="output file")
    s.add_argument("--no-validate", action="store_true", help="skip the schema / structure check")
    s.set_defaults(func=cmd_export)

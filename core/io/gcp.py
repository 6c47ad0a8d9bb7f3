"""Ground point lists and image measurement lists (plain text / CSV), and their merge into a block.

Ground points: one point per row, ``name X Y Z`` plus optional ``sx sy sz`` (metres; ``sxy`` sets sx and sy)
and ``kind`` (``control``/``gcp`` or ``check``/``chk``). Default column order ``name,x,y,z``; a header row
with known column names sets the order, as does the ``columns`` option.

Measurements: one observation per row, ``point image u v`` in pixels, u to the right and v down. The pixel
origin is the centre of the top-left pixel (``origin=center``, OpenCV, the core's convention) or its outer
corner (``origin=corner``, e.g. COLMAP, many digitising tools); corner values are shifted by -0.5 px.

The merge checks every measurement against the block: unknown image ids, unknown point names, pixels outside the
image and duplicate (point, image) pairs are errors naming the file, line and field.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..geometry.crs import transform_points
from ..model import GroundPoint, ImageBlock
from ..pipeline.atomic import write_text
from .validate import (
    check_crs,
    parse_bool,
    parse_columns,
    parse_float,
    read_text_lines,
    sniff_delimiter,
    split_row,
    table_columns,
)
from .validate import delimiter as parse_delimiter

POINT_ALIASES = {
    "name": "name", "point": "name", "id": "name", "point_id": "name", "label": "name",
    "x": "x", "easting": "x", "east": "x", "e": "x",
    "y": "y", "northing": "y", "north": "y", "n": "y",
    "z": "z", "h": "z", "height": "z", "elevation": "z",
    "sx": "sx", "sigma_x": "sx", "sy": "sy", "sigma_y": "sy", "sz": "sz", "sigma_z": "sz", "sxy": "sxy",
    "sigma_xy": "sxy",
    "kind": "kind", "type": "kind", "role": "kind", "use": "kind",
}
MEASUREMENT_ALIASES = {
    "point": "point", "name": "point", "point_id": "point", "gcp": "point", "label": "point",
    "image": "image", "image_id": "image", "photo": "image", "photo_id": "image", "img": "image",
    "u": "u", "x": "u", "col": "u", "column": "u", "px": "u",
    "v": "v", "y": "v", "row": "v", "py": "v",
}
KIND_WORDS = {"control": "control", "gcp": "control", "c": "control", "full": "control", "ctrl": "control",
              "check": "check", "chk": "check", "ck": "check", "checkpoint": "check", "ichk": "check"}


@dataclass(frozen=True)
class PointRow:
    """One ground point as read, with the line it came from."""

    point: GroundPoint
    line: int


@dataclass(frozen=True)
class MeasurementRow:
    """One image measurement as read (pixel origin already converted to the core's), with its line."""

    point: str
    image: str
    uv_px: tuple[float, float]
    line: int


def _numbers_missing(first: list[str], cols: list[str] | None) -> bool:
    """A first row whose coordinate fields (x, y or u, v) are not numbers is a header."""
    idx = [2, 3] if cols is None else [i for i, c in enumerate(cols) if c in ("x", "y", "u", "v")]
    for i in idx:
        try:
            float(first[i])
        except (ValueError, IndexError):
            return True
    return False


def _table(path: Path, columns: Any, aliases: dict[str, str], required: tuple[str, ...], default: str,
           delimiter: Any, header: Any, comment: str) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """Columns and split data rows of a text table (header detection as in the OPK reader)."""
    lines = read_text_lines(path)
    sep = parse_delimiter(delimiter, path)
    rows = [(i + 1, t) for i, t in enumerate(lines) if t.strip() and not t.strip().startswith(comment)]
    if not rows:
        raise InputError("no data rows", path=path)
    if delimiter is None:
        sep = sniff_delimiter([t for _, t in rows[1:] or rows])
    cols = None if columns is None else parse_columns(columns, aliases, required, path)
    is_header = None if str(header).lower() == "auto" else parse_bool(header, path, None, "header")
    cols, rows = table_columns(rows, sep, cols, is_header, _numbers_missing, aliases, required, default, path)
    out = []
    for line, text in rows:
        fields = split_row(text, sep)
        if len(fields) != len(cols):
            raise InputError(f"expected {len(cols)} fields ({','.join(cols)}), got {len(fields)}", path=path,
                             line=line)
        out.append((line, fields))
    return cols, out


def read_ground_points(path: str | Path, columns: Any = None, delimiter: Any = None, header: Any = "auto",
                       comment: str = "#", sigma: Any = None, kind: str = "control") -> list[PointRow]:
    """Read a ground point list. ``sigma`` (metres) applies where the file has no sigma columns."""
    p = Path(path)
    cols, rows = _table(p, columns, POINT_ALIASES, ("name", "x", "y", "z"), "name,x,y,z", delimiter, header,
                        comment)
    default_kind = KIND_WORDS.get(str(kind).lower())
    if default_kind is None:
        raise InputError(f"unknown point kind '{kind}' (use control or check)", path=p, field="kind")
    default_sigma = None if sigma is None else float(sigma)
    out: list[PointRow] = []
    seen: dict[str, int] = {}
    for line, fields in rows:
        rec = dict(zip(cols, fields, strict=True))
        name = rec["name"]
        if not name:
            raise InputError("empty point name", path=p, line=line, field="name")
        if name in seen:
            raise InputError(f"duplicate ground point '{name}' (first on line {seen[name]})", path=p, line=line,
                             field="name")
        seen[name] = line
        xyz = [parse_float(rec[c], p, line, c) for c in ("x", "y", "z")]
        sig = np.full(3, 0.02 if default_sigma is None else default_sigma)
        if "sxy" in rec:
            sig[:2] = parse_float(rec["sxy"], p, line, "sxy")
        for i, c in enumerate(("sx", "sy", "sz")):
            if c in rec:
                sig[i] = parse_float(rec[c], p, line, c)
        if np.any(sig <= 0):
            raise InputError("standard deviations must be positive", path=p, line=line,
                             field=("sx", "sy", "sz")[int(np.argmin(sig))])
        k = default_kind
        if "kind" in rec:
            k = KIND_WORDS.get(rec["kind"].lower())
            if k is None:
                raise InputError(f"unknown point kind '{rec['kind']}' (use control or check)", path=p, line=line,
                                 field="kind")
        out.append(PointRow(GroundPoint(name=name, xyz=np.array(xyz), sigma=sig, kind=k), line))
    return out


def read_measurements(path: str | Path, columns: Any = None, delimiter: Any = None, header: Any = "auto",
                      comment: str = "#", origin: str = "center") -> list[MeasurementRow]:
    """Read an image measurement list; pixels come back with the origin at the centre of the top-left pixel."""
    p = Path(path)
    cols, rows = _table(p, columns, MEASUREMENT_ALIASES, ("point", "image", "u", "v"), "point,image,u,v",
                        delimiter, header, comment)
    o = str(origin).lower()
    if o not in ("center", "centre", "corner"):
        raise InputError(f"pixel origin must be center or corner, got '{origin}'", path=p, field="origin")
    shift = -0.5 if o == "corner" else 0.0
    out = []
    for line, fields in rows:
        rec = dict(zip(cols, fields, strict=True))
        for c in ("point", "image"):
            if not rec[c]:
                raise InputError(f"empty {c} name", path=p, line=line, field=c)
        u = parse_float(rec["u"], p, line, "u") + shift
        v = parse_float(rec["v"], p, line, "v") + shift
        out.append(MeasurementRow(rec["point"], rec["image"], (u, v), line))
    return out


def merge_ground_points(block: ImageBlock, points: list[PointRow], source: str | Path,
                        crs: str | None = None) -> None:
    """Add ground points to ``block`` (transformed from ``crs`` to the block's CRS when they differ)."""
    if crs is not None:
        src = check_crs(crs, source, "gcp_crs")
        if src != check_crs(block.crs, source, "crs"):
            xyz = transform_points(np.array([r.point.xyz for r in points]), src, block.crs, str(source),
                                   [r.line for r in points])
            for r, x in zip(points, xyz, strict=True):
                r.point.xyz = x
    for r in points:
        if r.point.name in block.ground_points:
            raise InputError(f"ground point '{r.point.name}' is already in the block", path=source, line=r.line,
                             field="name")
        block.add_ground_point(r.point)


def merge_measurements(block: ImageBlock, rows: list[MeasurementRow], source: str | Path,
                       sigma_px: float | None = None) -> None:
    """Attach image measurements to the block's ground points, checking ids and image bounds."""
    seen: dict[tuple[str, str], int] = {}
    for r in rows:
        if r.point not in block.ground_points:
            raise InputError(f"unknown ground point '{r.point}'", path=source, line=r.line, field="point")
        if r.image not in block.images:
            raise InputError(f"unknown image id '{r.image}'", path=source, line=r.line, field="image")
        key = (r.point, r.image)
        if key in seen:
            raise InputError(f"point '{r.point}' measured twice in image '{r.image}' (first on line {seen[key]})",
                             path=source, line=r.line, field="image")
        seen[key] = r.line
        cam = block.camera_of(r.image)
        u, v = r.uv_px
        if not -0.5 <= u <= cam.width - 0.5:
            raise InputError(f"u = {u} px is outside image '{r.image}' (width {cam.width})", path=source,
                             line=r.line, field="u")
        if not -0.5 <= v <= cam.height - 0.5:
            raise InputError(f"v = {v} px is outside image '{r.image}' (height {cam.height})", path=source,
                             line=r.line, field="v")
    for r in rows:
        gp = block.ground_points[r.point]
        gp.observations[r.image] = np.array(r.uv_px, dtype=np.float64)
        if sigma_px is not None:
            gp.sigma_px = float(sigma_px)


def _fmt(v: float) -> str:
    return repr(float(v))


def write_ground_points(block: ImageBlock, path: str | Path, delimiter: str = ",") -> None:
    """Write the block's ground points that have coordinates (``name,x,y,z,sx,sy,sz,kind`` with a header)."""
    sep = parse_delimiter(delimiter) or " "
    out = [f"# crs: {block.crs}", sep.join(["name", "x", "y", "z", "sx", "sy", "sz", "kind"])]
    for g in block.ground_points.values():
        if g.xyz is None:
            continue
        out.append(sep.join([g.name, *(_fmt(c) for c in g.xyz), *(_fmt(s) for s in g.sigma), g.kind]))
    write_text(path, "\n".join(out) + "\n")


def write_measurements(block: ImageBlock, path: str | Path, delimiter: str = ",", origin: str = "center") -> None:
    """Write all ground point image measurements (``point,image,u,v`` with a header)."""
    sep = parse_delimiter(delimiter) or " "
    shift = 0.5 if str(origin).lower() == "corner" else 0.0
    out = [f"# pixel origin: {origin} of the top-left pixel", sep.join(["point", "image", "u", "v"])]
    for g in block.ground_points.values():
        for img, uv in g.observations.items():
            out.append(sep.join([g.name, img, _fmt(uv[0] + shift), _fmt(uv[1] + shift)]))
    write_text(path, "\n".join(out) + "\n")

"""Plain OPK lists: one image per row with its projection centre and omega-phi-kappa angles.

Rows hold ``name X Y Z omega phi kappa`` (order set by the ``columns`` option or a header row) and optionally
``sx sy sz`` (metres), ``somega sphi skappa`` (same unit as the angles; the standard deviations of the angles,
turned into the adjustment's sigmas about the world's X, Y, Z by :func:`..geometry.rotations.world_axis_sigmas`:
an oblique image's kappa turns about its viewing axis, so its sigma counts in Y and Z), ``camera`` (camera id), ``file``
(image path, default: the name plus the ``image_ext`` option), and for a multi-head camera system ``exposure``
(the trigger's id, shared by its heads' images), ``head`` and ``time`` (seconds; with ``-o exposures=time`` the
exposures are found from it, see :mod:`.common`); ``-`` or an empty field leaves one of these unknown.
Omega-phi-kappa follow the PATB/BINGO convention (``M = Rx(omega) Ry(phi) Rz(kappa)`` maps the image frame x
right/y up/z back into the world, see ``core.geometry.rotations``), in the unit given by the ``angles`` option
(``deg``, ``gon`` or ``rad``).

The intrinsics come from a camera file (``cameras`` option, see :mod:`.camerafile`). Lines starting with the
comment character (``#``) are skipped, except directives the writer puts there and the reader honours when no
option overrides them: ``# crs: EPSG:25832``, ``# angles: deg``, ``# cameras: block_cameras.toml``,
``# image_root: /data/images`` (relative paths start at the list's folder).

Reader options (all accept strings, as given on the CLI with ``-o key=value``):
``cameras`` camera file (default: ``<stem>_cameras.toml`` or ``.json`` beside the list), ``angles`` (default
``deg``, or the camera file's / header's), ``columns`` (default ``name,x,y,z,omega,phi,kappa`` or the header
row), ``delimiter`` (``comma``, ``semicolon``, ``tab``, ``whitespace``; default: sniffed), ``header``
(``auto``/``true``/``false``), ``comment`` (default ``#``), ``crs`` (EPSG:nnnn or WKT; else from the header or the
camera file), ``image_ext`` (appended to names to form file names when there is no ``file`` column).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..geometry.rotations import (
    angle_sigmas,
    cam_from_world_to_opk,
    from_radians,
    opk_axes,
    opk_to_cam_from_world,
    to_radians,
    world_axis_sigmas,
)
from ..model import Image, ImageBlock, Pose
from ..pipeline.atomic import write_text
from .camerafile import CameraFile, read_camera_file, write_camera_file
from .common import finish_block
from .validate import (
    angle_unit,
    check_crs,
    parse_bool,
    parse_columns,
    parse_float,
    read_text_lines,
    reject_unknown,
    sniff_delimiter,
    split_row,
    table_columns,
)
from .validate import delimiter as parse_delimiter

COLUMN_ALIASES = {
    "name": "name", "image": "name", "image_name": "name", "imagename": "name", "id": "name", "photo": "name",
    "image_id": "name", "label": "name",
    "x": "x", "easting": "x", "east": "x", "e": "x",
    "y": "y", "northing": "y", "north": "y", "n": "y",
    "z": "z", "h": "z", "height": "z", "elevation": "z", "alt": "z", "altitude": "z",
    "omega": "omega", "om": "omega", "o": "omega",
    "phi": "phi", "ph": "phi", "p": "phi",
    "kappa": "kappa", "ka": "kappa", "k": "kappa",
    "sx": "sx", "sigma_x": "sx", "sy": "sy", "sigma_y": "sy", "sz": "sz", "sigma_z": "sz",
    "somega": "somega", "sigma_omega": "somega", "sphi": "sphi", "sigma_phi": "sphi",
    "skappa": "skappa", "sigma_kappa": "skappa",
    "camera": "camera", "cam": "camera", "camera_id": "camera", "sensor": "camera",
    "file": "file", "path": "file", "image_path": "file", "filename": "file",
    "exposure": "exposure", "exposure_id": "exposure", "event": "exposure", "shot": "exposure",
    "trigger": "exposure",
    "head": "head", "camera_head": "head",
    "time": "time", "gps_time": "time", "gpstime": "time", "gnss_time": "time", "timestamp": "time",
    "seconds": "time",
}
LIST_OPTIONS: dict[str, str] = {
    "cameras": "camera file (TOML or JSON; default: <stem>_cameras.toml beside the list)",
    "angles": "deg, gon or rad (default: the list's or camera file's, else deg)",
    "columns": "the columns' order, comma-separated (default: the header row, else the format's order)",
    "delimiter": "comma, semicolon, tab or whitespace (default: sniffed)",
    "header": "auto, true or false",
    "comment": "comment character (default #)",
    "crs": "EPSG:nnnn or WKT (default: the list's or camera file's)",
    "image_ext": "appended to names to form file names where there is no file column",
}
"""The options of text lists (OPK lists and GNSS/IMU event lists, :func:`read_list`)."""

READER_OPTIONS = LIST_OPTIONS
"""The OPK reader's own options (see the module docstring)."""

REQUIRED = ("name", "x", "y", "z", "omega", "phi", "kappa")
DEFAULT_COLUMNS = "name,x,y,z,omega,phi,kappa"
DIRECTIVES = ("crs", "angles", "cameras", "image_root", "heading", "image_name", "image_file")
"""The ``# key: value`` comments text lists may carry (the last three for :mod:`.trajectory`'s event lists)."""


def _directives(lines: list[str], comment: str) -> dict[str, tuple[str, int]]:
    """``# key: value`` comment directives -> (value, line)."""
    out: dict[str, tuple[str, int]] = {}
    for i, text in enumerate(lines):
        s = text.strip()
        if not s.startswith(comment):
            continue
        body = s[len(comment):].strip()
        key, sep, value = body.partition(":")
        key = key.strip().lower()
        if sep and key in DIRECTIVES and key not in out:
            out[key] = (value.strip(), i + 1)
    return out


def _default_camera_file(source: Path) -> Path | None:
    for suffix in ("_cameras.toml", "_cameras.json"):
        p = source.with_name(source.stem + suffix)
        if p.is_file():
            return p
    return None


def optional_field(rec: dict[str, str], column: str) -> str | None:
    """An optional column's value (None where the column is missing, ``-`` or empty)."""
    v = rec.get(column, "").strip()
    return None if v in ("", "-") else v


@dataclass(frozen=True)
class ListFile:
    """What every text list reader (OPK lists, GNSS/IMU event lists) takes from its file, options and camera file:
    the file's ``path`` and ``lines``, its ``# key: value`` ``directives``, the camera file ``cams`` read from
    ``cam_path``, the angle ``unit``, the ``crs``, the ``columns`` and the data ``rows`` ((line, text)) with their
    delimiter ``sep``, and the ``image_ext`` option."""

    path: Path
    lines: list[str]
    directives: dict[str, tuple[str, int]]
    cams: CameraFile
    cam_path: Path
    unit: str
    crs: str
    columns: list[str]
    rows: list[tuple[int, str]]
    sep: str | None
    image_ext: str

    def records(self, key: str, what: str) -> Iterator[tuple[int, dict[str, str]]]:
        """The data rows as ``(line, column -> text)``; each has one field per column and a ``key`` column that is
        not empty and not repeated (``what`` names it in the errors)."""
        seen: dict[str, int] = {}
        for line_no, text in self.rows:
            fields = split_row(text, self.sep)
            if len(fields) != len(self.columns):
                raise InputError(f"expected {len(self.columns)} fields ({','.join(self.columns)}), got "
                                 f"{len(fields)}", path=self.path, line=line_no)
            rec = dict(zip(self.columns, fields, strict=True))
            value = rec[key]
            if not value:
                raise InputError(f"empty {what}", path=self.path, line=line_no, field=key)
            if value in seen:
                raise InputError(f"duplicate {what} '{value}' (first on line {seen[value]})", path=self.path,
                                 line=line_no, field=key)
            seen[value] = line_no
            yield line_no, rec

    def check_sigma_columns(self, *groups: tuple[str, str, str]) -> None:
        """Each group of sigma columns is given whole or not at all."""
        for group in groups:
            given = [c for c in group if c in self.columns]
            if given and len(given) != 3:
                raise InputError(f"sigma columns must come in threes ({', '.join(group)}), got {', '.join(given)}",
                                 path=self.path, field="columns")

    def image_root(self, block: ImageBlock, options: dict[str, Any]) -> None:
        """The list's ``# image_root:`` directive into ``block`` (relative to the list's folder), unless the
        ``image_root`` option overrides it."""
        if "image_root" in self.directives and "image_root" not in options:
            root = Path(self.directives["image_root"][0])
            block.image_root = str(root if root.is_absolute() else (self.path.parent / root).resolve())

    def sigmas(self, rec: dict[str, str], names: tuple[str, str, str], line: int,
               angular: bool) -> np.ndarray | None:
        """Three standard deviations from a row (``-`` or empty in all three: unknown; radians for ``angular``
        ones, from the list's unit); negative ones are refused."""
        if names[0] not in rec:
            return None
        raw = [rec[c].strip() for c in names]
        if all(r in ("", "-") for r in raw):
            return None
        vals = np.array([parse_float(r, self.path, line, c) for r, c in zip(raw, names, strict=True)])
        if np.any(vals < 0):
            raise InputError("standard deviations must not be negative", path=self.path, line=line,
                             field=names[int(np.argmin(vals))])
        return np.array([to_radians(v, self.unit) for v in vals]) if angular else vals


def read_list(source: str, options: dict[str, Any], aliases: dict[str, str], required: tuple[str, ...],
              default_columns: str, numeric: tuple[str, ...]) -> ListFile:
    """The common part of a text list (see :class:`ListFile`); consumes the options ``comment``, ``cameras``,
    ``angles``, ``crs``, ``delimiter``, ``header``, ``columns`` and ``image_ext`` from ``options``. Without the
    ``header`` option the first row is a header when its ``numeric`` columns (by the ``columns`` option, else by
    ``default_columns``) are not numbers."""
    path = Path(source)
    comment = str(options.pop("comment", "#"))
    lines = read_text_lines(path)
    directives = _directives(lines, comment)

    cam_opt = options.pop("cameras", None) or directives.get("cameras", (None, None))[0]
    if cam_opt:
        cam_path = Path(str(cam_opt))
        if not cam_path.is_absolute() and not cam_path.is_file():
            cam_path = path.parent / cam_path
    else:
        cam_path = _default_camera_file(path)
        if cam_path is None:
            raise InputError("no camera file: give one with -o cameras=FILE (TOML or JSON)", path=path,
                             field="cameras")
    cams = read_camera_file(cam_path)

    unit_opt, crs_opt = options.pop("angles", None), options.pop("crs", None)
    if unit_opt is not None:
        unit = angle_unit(unit_opt, path, "angles")
    elif "angles" in directives:
        unit = angle_unit(directives["angles"][0], path, "angles", directives["angles"][1])
    else:
        unit = cams.angles or "deg"
    if crs_opt is not None:
        crs = check_crs(crs_opt, path, "crs")
    elif "crs" in directives:
        crs = check_crs(directives["crs"][0], path, "crs", directives["crs"][1])
    else:
        crs = check_crs(cams.crs, cams.path, "crs")
    sep_opt = options.pop("delimiter", None)
    sep = parse_delimiter(sep_opt, path)
    header_opt = str(options.pop("header", "auto")).lower()
    header = None if header_opt == "auto" else parse_bool(header_opt, path, None, "header")
    col_opt = options.pop("columns", None)
    image_ext = str(options.pop("image_ext", "") or "")

    rows = [(i + 1, t) for i, t in enumerate(lines) if t.strip() and not t.strip().startswith(comment)]
    if not rows:
        raise InputError("no data rows", path=path)
    if sep_opt is None:
        sep = sniff_delimiter([t for _, t in rows[1:] or rows])

    def looks_like_header(fields: list[str], cols: list[str] | None) -> bool:
        names = cols if cols is not None else default_columns.split(",")
        try:
            for i in (i for i, c in enumerate(names) if c in numeric):
                float(fields[i])
        except (ValueError, IndexError):
            return True
        return False

    columns = None if col_opt is None else parse_columns(col_opt, aliases, required, path)
    columns, rows = table_columns(rows, sep, columns, header, looks_like_header, aliases, required, default_columns,
                                  path)
    return ListFile(path, lines, directives, cams, cam_path, unit, crs, columns, rows, sep, image_ext)


def read_opk(source: str, **options: Any) -> ImageBlock:
    """Read an OPK list and its camera file into an :class:`ImageBlock` (poses as ``pose_approx``)."""
    lf = read_list(source, options, COLUMN_ALIASES, REQUIRED, DEFAULT_COLUMNS, ("x", "y", "z"))
    path, cams, cam_path, unit, crs = lf.path, lf.cams, lf.cam_path, lf.unit, lf.crs
    lf.check_sigma_columns(("sx", "sy", "sz"), ("somega", "sphi", "skappa"))
    block = ImageBlock(crs=crs)
    for cam in cams.cameras.values():
        block.add_camera(cam)
    seen: dict[str, int] = {}
    for line_no, rec in lf.records("name", "image id"):
        name = rec["name"]
        seen[name] = line_no
        xyz = [parse_float(rec[c], path, line_no, c) for c in ("x", "y", "z")]
        angles = [to_radians(parse_float(rec[c], path, line_no, c), unit) for c in ("omega", "phi", "kappa")]
        cam_id = rec.get("camera") or cams.camera_for(name, str(path), line_no)
        if cam_id not in block.cameras:
            raise InputError(f"unknown camera '{cam_id}' (camera file {cam_path} defines "
                             f"{', '.join(block.cameras)})", path=path, line=line_no, field="camera")
        sig_pos = lf.sigmas(rec, ("sx", "sy", "sz"), line_no, False)
        sig_att = lf.sigmas(rec, ("somega", "sphi", "skappa"), line_no, True)
        if sig_att is not None:
            axes = opk_axes(*angles)
            sig_att = world_axis_sigmas(axes, sig_att)
            if not np.all(sig_att > 0.0):
                exact = int(np.argmin(sig_att))
                col = ("somega", "sphi", "skappa")[int(np.argmax(axes[exact] ** 2))]
                raise InputError(f"a zero standard deviation leaves the attitude exact about the world's "
                                 f"{'XYZ'[exact]} axis; give each angle its sigma", path=path, line=line_no,
                                 field=col)
        exposure, head, time = (optional_field(rec, c) for c in ("exposure", "head", "time"))
        block.add_image(Image(id=name, camera_id=cam_id, file=rec.get("file") or name + lf.image_ext,
                              head=head, exposure=exposure,
                              time=None if time is None else parse_float(time, path, line_no, "time"),
                              pose_approx=Pose(opk_to_cam_from_world(*angles), xyz),
                              sigma_position=sig_pos, sigma_attitude=sig_att))
    if not block.images:
        raise InputError("no image rows after the header", path=path)
    lf.image_root(block, options)
    return finish_block(block, path, options, "opk", lines=seen)


def _fmt(v: float) -> str:
    return repr(float(v))


def write_opk(block: ImageBlock, dest: str, angles: str = "deg", delimiter: str = "whitespace",
              cameras: str | None = None, sigmas: Any = True, **unknown: Any) -> None:
    """Write the block's images (adjusted pose if any, else approximate) as an OPK list plus a camera file.

    The camera file goes to ``cameras`` (default ``<stem>_cameras.toml`` beside ``dest``); the list's header
    comments name it, the CRS and the angle unit, so :func:`read_opk` needs no options to read it back.
    Images without any orientation are skipped (OPK lists always carry EO).
    """
    reject_unknown(unknown, "opk")
    sep = parse_delimiter(delimiter)
    sigmas = parse_bool(sigmas, None, None, "sigmas")
    unit = angle_unit(angles)
    dest_path = Path(dest)
    cam_path = Path(cameras) if cameras else dest_path.with_name(dest_path.stem + "_cameras.toml")
    write_camera_file(cam_path, list(block.cameras.values()), crs=block.crs, angles=unit)
    images = [img for img in block.images.values() if img.pose is not None]
    with_pos = sigmas and any(img.sigma_position is not None for img in images)
    with_att = sigmas and any(img.sigma_attitude is not None for img in images)
    cols = ["name", "x", "y", "z", "omega", "phi", "kappa", "camera", "file"]
    if with_pos:
        cols += ["sx", "sy", "sz"]
    if with_att:
        cols += ["somega", "sphi", "skappa"]
    system = [c for c, on in (("exposure", any(img.exposure is not None for img in images)),
                              ("head", any(img.head is not None for img in images)),
                              ("time", any(img.time is not None for img in images))) if on]
    cols += system
    join = (lambda f: " ".join(f)) if sep is None else sep.join
    rel_cam = cam_path.name if cam_path.parent.resolve() == dest_path.parent.resolve() else str(cam_path)
    out = ["# Oblique City OPK list: omega-phi-kappa as PATB (M = Rx(omega) Ry(phi) Rz(kappa), image x right, "
           "y up, z back)", f"# crs: {block.crs}", f"# angles: {unit}", f"# cameras: {rel_cam}"]
    if block.image_root:
        out.append(f"# image_root: {block.image_root}")
    out.append(join(cols))
    for img in images:
        text = img.id + (img.file or "") + img.camera_id + (img.exposure or "") + (img.head or "")
        if any(ch.isspace() for ch in text) if sep is None else sep in text:
            raise InputError(f"image '{img.id}': its name, file, camera, exposure or head contains the delimiter; "
                             "choose another delimiter", path=dest, field="delimiter")
        o, p, k = cam_from_world_to_opk(img.pose.R)
        row = [img.id, *(_fmt(c) for c in img.pose.C), *(_fmt(from_radians(a, unit)) for a in (o, p, k)),
               img.camera_id, img.file or img.id]
        if with_pos:
            s = img.sigma_position
            row += ["-"] * 3 if s is None else [_fmt(v) for v in s]
        if with_att:
            s = None if img.sigma_attitude is None else angle_sigmas(opk_axes(o, p, k), img.sigma_attitude)
            row += ["-"] * 3 if s is None else [_fmt(from_radians(v, unit)) for v in s]
        for c in system:
            v = getattr(img, c)
            row.append("-" if v is None else _fmt(v) if c == "time" else v)
        out.append(join(row))
    write_text(dest, "\n".join(out) + "\n")

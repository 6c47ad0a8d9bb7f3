"""Checks shared by every block reader: numbers, units, CRS, options, XML safety, image files and sizes, and
the one JSON file reader of the workspace's own files.

Every check raises :class:`InputError` naming the file, the line (1-based, for text files and XML elements) and
the field, so a user can go straight to the offending place. Readers build the whole block in memory first and
hand it over only when everything passed, so nothing is ever half-imported.
"""

from __future__ import annotations

import json
import math
import re
import struct
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, InputError
from ..geometry.crs import normalize_crs
from ..geometry.rotations import ANGLE_UNITS
from ..model import ImageBlock

DELIMITERS = {"comma": ",", "semicolon": ";", "tab": "\t", "whitespace": None, ",": ",", ";": ";", "\t": "\t",
              "\\t": "\t", " ": None, "space": None}
"""Delimiter option values -> the separator (None splits on any run of whitespace)."""

TRUE_WORDS = {"1", "true", "yes", "on"}
FALSE_WORDS = {"0", "false", "no", "off"}


# ----------------------------------------------------------------------------------------------- numbers, words

def parse_float(text: str, path: str | Path | None, line: int | None, field: str) -> float:
    """A finite float from ``text``; InputError naming path, line and field otherwise."""
    try:
        value = float(str(text).strip())
    except ValueError:
        raise InputError(f"'{str(text).strip()[:40]}' is not a number", path=path, line=line, field=field) from None
    if not math.isfinite(value):
        raise InputError(f"'{str(text).strip()}' is not a finite number (NaN or infinity)", path=path, line=line,
                         field=field)
    return value


def parse_bool(value: Any, path: str | Path | None, line: int | None, field: str) -> bool:
    """``true/false/yes/no/1/0`` (any case) or a bool."""
    if isinstance(value, bool):
        return value
    s = str(value).strip().lower()
    if s in TRUE_WORDS:
        return True
    if s in FALSE_WORDS:
        return False
    raise InputError(f"'{value}' is not true or false", path=path, line=line, field=field)


def angle_unit(value: Any, path: str | Path | None = None, field: str = "angles", line: int | None = None) -> str:
    """A known angle unit name (``deg``, ``gon``/``grad``, ``rad``)."""
    s = str(value).strip().lower()
    aliases = {"degree": "deg", "degrees": "deg", "radian": "rad", "radians": "rad", "gons": "gon"}
    s = aliases.get(s, s)
    if s not in ANGLE_UNITS:
        raise InputError(f"unknown angle unit '{value}' (use deg, gon or rad)", path=path, line=line, field=field)
    return s


def check_crs(text: Any, path: str | Path | None = None, field: str = "crs", line: int | None = None) -> str:
    """Canonical CRS text (``EPSG:nnnn`` or WKT) or an InputError naming where the bad CRS came from."""
    if text is None or not str(text).strip():
        raise InputError("no coordinate reference system given (EPSG:nnnn or WKT)", path=path, line=line,
                         field=field)
    try:
        return normalize_crs(str(text))
    except InputError as e:
        raise InputError(e.reason, path=path, line=line, field=field) from None


def delimiter(value: Any, path: str | Path | None = None) -> str | None:
    """The separator for a delimiter option (``comma``, ``semicolon``, ``tab``, ``whitespace`` or the character)."""
    if value is None:
        return None
    key = str(value) if str(value) in DELIMITERS else str(value).strip().lower()
    if key not in DELIMITERS:
        raise ConfigError(f"unknown delimiter '{value}' (use comma, semicolon, tab or whitespace)"
                          + (f" for {path}" if path else ""))
    return DELIMITERS[key]


# ----------------------------------------------------------------------------------------------- options

def option_value(value: Any) -> Any:
    """Options arrive from the CLI as strings (JSON-decoded when possible): decode JSON strings here too."""
    if isinstance(value, str):
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    return value


def reject_unknown(options: dict[str, Any], fmt: str) -> None:
    """ConfigError listing options no reader consumed (catches typos such as ``angle=gon``)."""
    if options:
        raise ConfigError(f"unknown option(s) for format '{fmt}': {', '.join(sorted(options))}")


# ----------------------------------------------------------------------------------------------- text tables

def read_text_lines(path: str | Path) -> list[str]:
    """All lines of a UTF-8 text file (BOM tolerated); InputError if missing or not text."""
    p = Path(path)
    if not p.is_file():
        raise InputError("file not found", path=path)
    try:
        return p.read_text(encoding="utf-8-sig").splitlines()
    except UnicodeDecodeError as e:
        line = p.read_bytes()[: e.start].count(b"\n") + 1
        raise InputError("not a UTF-8 text file", path=path, line=line) from None


def split_row(text: str, sep: str | None) -> list[str]:
    """Split one row; ``sep=None`` splits on whitespace. Fields are stripped of blanks and double quotes."""
    parts = text.split() if sep is None else text.split(sep)
    return [p.strip().strip('"').strip() for p in parts]


def sniff_delimiter(rows: list[str]) -> str | None:
    """Guess the delimiter of data rows: tab, semicolon or comma if every row has it, else whitespace."""
    for sep in ("\t", ";", ","):
        if rows and all(sep in r for r in rows):
            return sep
    return None


def parse_columns(spec: Any, known: dict[str, str], required: Iterable[str], path: str | Path | None,
                  option: str = "columns") -> list[str]:
    """Column names from a ``"name,x,y,..."`` option or header; ``known`` maps aliases to canonical names.

    ``-`` or ``skip`` marks a column to ignore. Raises InputError naming the missing required columns.
    """
    names = spec if isinstance(spec, list) else re.split(r"[,;\s]+", str(spec).strip())
    out: list[str] = []
    for raw in names:
        n = str(raw).strip().lower()
        if n in ("-", "skip", "_", ""):
            out.append("-")
            continue
        if n not in known:
            raise InputError(f"unknown column '{raw}' (known: {', '.join(sorted(set(known.values())))})",
                             path=path, field=option)
        out.append(known[n])
    dup = {c for c in out if c != "-" and out.count(c) > 1}
    if dup:
        raise InputError(f"column(s) given twice: {', '.join(sorted(dup))}", path=path, field=option)
    missing = [c for c in required if c not in out]
    if missing:
        raise InputError(f"missing column(s): {', '.join(missing)}", path=path, field=option)
    return out



def table_columns(rows: list[tuple[int, str]], sep: str | None, columns: list[str] | None, header: bool | None,
                  looks_like_header: Callable[[list[str], list[str] | None], bool], known: dict[str, str],
                  required: Iterable[str], default: str, path: str | Path) -> tuple[list[str], list[tuple[int, str]]]:
    """The columns of a text table and its data rows (the header row removed when there is one).

    ``rows`` are ``(line number, text)``; ``columns`` come from an option (or None); ``header`` True/False, or None
    to decide with ``looks_like_header(first_row_fields, columns)``. Without columns the header names them, else
    ``default`` does. A bad header name raises InputError naming the header's line.
    """
    first_line, first_text = rows[0]
    first = split_row(first_text, sep)
    if looks_like_header(first, columns) if header is None else header:
        rows = rows[1:]
        if columns is None:
            try:
                columns = parse_columns(first, known, required, path, option="header")
            except InputError as e:
                raise InputError(e.reason, path=path, line=first_line, field=e.field) from None
    if columns is None:
        columns = parse_columns(default, known, required, path)
    return columns, rows


# ----------------------------------------------------------------------------------------------- XML

ENTITY_RE = re.compile(rb"<!ENTITY", re.IGNORECASE)
DOCTYPE_RE = re.compile(rb"<!DOCTYPE", re.IGNORECASE)


MAX_ZIPPED_XML_BYTES = 4_000_000_000
"""The largest XML member of a zip archive that :func:`parse_xml` unpacks (a block of 100,000 photos takes about
0.2 GB): a larger one is refused before it fills the memory (a zip bomb)."""


def parse_xml(path: str | Path):
    """Parse an XML file (or a zip holding one, like BlocksExchange ``.xmlz``) safely with lxml; return its root.

    No network, no DTD loading, no entity resolution; a DOCTYPE that declares entities (the "billion laughs"
    and external-entity attacks) is refused before parsing. Syntax errors name the line.
    """
    from lxml import etree

    p = Path(path)
    if not p.is_file():
        raise InputError("file not found", path=path)
    data = p.read_bytes()
    if data[:4] == b"PK\x03\x04":  # a zipped XML (BlocksExchange .xmlz): its first .xml member
        import io
        import zipfile
        import zlib

        try:
            with zipfile.ZipFile(io.BytesIO(data)) as z:
                members = [n for n in z.namelist() if n.lower().endswith(".xml")]
                if not members:
                    raise InputError("zip archive without an .xml file", path=path)
                size = z.getinfo(members[0]).file_size
                if size > MAX_ZIPPED_XML_BYTES:
                    raise InputError(f"the zipped {members[0]} would unpack to {size / 1e9:.1f} GB (at most "
                                     f"{MAX_ZIPPED_XML_BYTES / 1e9:.0f} GB are read)", path=path)
                data = z.read(members[0])
        except (zipfile.BadZipFile, zlib.error, EOFError) as e:
            raise InputError(f"broken zip archive ({e})", path=path) from None
    m = DOCTYPE_RE.search(data)
    if m is not None:
        ent = ENTITY_RE.search(data, m.start())
        if ent is not None:
            line = data[: ent.start()].count(b"\n") + 1
            raise InputError("XML with a DOCTYPE declaring entities is refused (entity expansion attack)",
                             path=path, line=line, field="DOCTYPE")
    parser = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, dtd_validation=False,
                             huge_tree=False, remove_comments=True)
    try:
        root = etree.fromstring(data, parser)
    except etree.XMLSyntaxError as e:
        line = e.lineno if e.lineno else None
        raise InputError(f"malformed XML: {e.msg}", path=path, line=line) from None
    return root


# ----------------------------------------------------------------------------------------------- images

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
"""The first bytes of a PNG file, and of a TIFF or BigTIFF one (either byte order)."""


def image_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) of an image file read from its header (PNG, JPEG, TIFF), else through OpenCV.

    Returns None when the file is not a readable image.
    """
    p = Path(path)
    with open(p, "rb") as f:
        head = f.read(32)
        if head[:8] == PNG_SIGNATURE and head[12:16] == b"IHDR":
            w, h = struct.unpack(">II", head[16:24])
            return int(w), int(h)
        if head[:2] == b"\xff\xd8":
            size = _jpeg_size(f)
            if size is not None:
                return size
        if head[:4] in TIFF_SIGNATURES:
            try:
                import tifffile

                with tifffile.TiffFile(p) as t:
                    shape = t.pages[0].shape
                    axes = t.pages[0].axes
                return int(shape[axes.index("X")]), int(shape[axes.index("Y")])
            except (ValueError, OSError, KeyError):
                return None
    import cv2

    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    return None if img is None else (int(img.shape[1]), int(img.shape[0]))


def _jpeg_size(f) -> tuple[int, int] | None:
    """Walk the JPEG markers to the first start-of-frame and read its size."""
    f.seek(2)
    while True:
        b = f.read(1)
        while b and b != b"\xff":
            b = f.read(1)
        while b == b"\xff":
            b = f.read(1)
        if not b:
            return None
        marker = b[0]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            continue
        seg = f.read(2)
        if len(seg) < 2:
            return None
        length = struct.unpack(">H", seg)[0]
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
            data = f.read(5)
            if len(data) < 5:
                return None
            h, w = struct.unpack(">HH", data[1:5])
            return int(w), int(h)
        f.seek(length - 2, 1)


def resolve_image(block: ImageBlock, file: str) -> Path:
    """The path of an image file: absolute, or relative to ``block.image_root``."""
    p = Path(file)
    if not p.is_absolute() and block.image_root:
        p = Path(block.image_root) / p
    return p


def check_image_files(block: ImageBlock, source: str | Path, lines: dict[str, int] | None = None) -> None:
    """Every image file exists and has its camera's size (header only). ``lines``: image id -> source line."""
    lines = lines or {}
    for img in block.images.values():
        line = lines.get(img.id)
        if not img.file:
            raise InputError(f"image '{img.id}' has no file name", path=source, line=line, field="file")
        p = resolve_image(block, img.file)
        if not p.is_file():
            raise InputError(f"image file of '{img.id}' not found: {p}", path=source, line=line, field="file")
        size = image_size(p)
        cam = block.cameras[img.camera_id]
        if size is None:
            raise InputError(f"image file of '{img.id}' is not a readable image: {p}", path=source, line=line,
                             field="file")
        if size != (cam.width, cam.height):
            raise InputError(f"image '{img.id}' is {size[0]} x {size[1]} px but camera '{cam.id}' says "
                             f"{cam.width} x {cam.height}", path=source, line=line, field="file")


# ----------------------------------------------------------------------------------------------- whole block

def check_block(block: ImageBlock, source: str | Path) -> None:
    """Consistency of a complete block: cameras are valid, poses finite, rotations orthonormal."""
    for cam in block.cameras.values():
        where = f"camera '{cam.id}'"
        if cam.width <= 0 or cam.height <= 0:
            raise InputError(f"{where} has image size {cam.width} x {cam.height}", path=source, field="width")
        for k in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2"):
            if not math.isfinite(getattr(cam, k)):
                raise InputError(f"{where}: {k} is not finite", path=source, field=k)
        if cam.fx <= 0 or cam.fy <= 0:
            raise InputError(f"{where} has a non-positive focal length", path=source, field="fx")
    for img in block.images.values():
        for attr in ("pose_approx", "pose_adjusted"):
            pose = getattr(img, attr)
            if pose is None:
                continue
            if not (np.all(np.isfinite(pose.R)) and np.all(np.isfinite(pose.C))):
                raise InputError(f"image '{img.id}': orientation contains NaN", path=source, field=attr)
            if np.abs(pose.R @ pose.R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(pose.R) < 0:
                raise InputError(f"image '{img.id}': rotation is not a proper rotation matrix", path=source,
                                 field=attr)


def read_json(path: str | Path, missing: str = "file not found") -> Any:
    """The content of a JSON file; :class:`InputError` naming the file with ``missing`` when it is not there, or
    the line of a syntax error."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(missing, path) from None
    except json.JSONDecodeError as e:
        raise InputError(f"not valid JSON ({e.msg})", path, line=e.lineno) from None

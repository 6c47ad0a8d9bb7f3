"""Camera files (TOML or JSON) holding interior orientations and the image -> camera assignment.

Used by the plain-text formats (OPK lists) that carry no intrinsics themselves. Layout (TOML; JSON has the same
keys)::

    crs = "EPSG:25832"          # optional: the block's CRS (an option or the OPK header may give it instead)
    angles = "deg"              # optional: unit of omega/phi/kappa in the OPK file (deg, gon, rad)

    [cameras.nadir]             # one table per camera; the key is the camera id
    width = 11608               # image size, pixels
    height = 8708
    focal_px = 13824.0          # focal length in pixels ...
    # focal_mm = 100.5          # ... or in millimetres together with the pixel pitch
    # pixel_size_mm = 0.0046    # (pixel_size_um = 4.6 works too)
    # fy_px = 13824.0           # optional second focal length (default: focal_px)
    cx_px = 5803.5              # principal point, pixels; default: the image centre
    cy_px = 4353.5
    # ppx_mm = 0.01             # or the principal point as an offset from the image centre in mm (x right, y down)
    # ppy_mm = -0.02
    pixel_origin = "center"     # principal point origin: centre (default) or corner of the top-left pixel
    k1 = -0.05                  # Brown distortion in OpenCV's convention (see core.model.camera)
    k2 = 0.01
    k3 = 0.0
    p1 = 0.0
    p2 = 0.0

    [assign]                    # optional: image name pattern (fnmatch) -> camera id, first match wins
    "*_N_*" = "north"

    [heads.nadir]               # optional: the heads of a multi-head camera system, the first the reference
    camera = "nadir"            # (the GNSS/IMU event lists of :mod:`.trajectory` need them); its camera id
    tilt_deg = 0.0              # the nominal mount: tilted from the body's down axis towards ...
    azimuth_deg = 0.0           # ... this azimuth, clockwise from the body's forward axis
    # cam_from_body = [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]   # or the mount as a rotation matrix (rows: the camera's
    #                           # x right, y down, z forward axes in the body frame: x forward, y right, z down)
    boresight_deg = [0.0, 0.0, 0.0]   # optional: a small rotation about the camera's x, y, z axes after the mount
    lever_arm_m = [0.0, 0.0, 0.0]     # the projection centre in the body frame (forward, right, down), metres

A single camera may be written as ``[camera]`` (id from its ``id`` key, default ``camera``). Images are given
a camera by the OPK file's ``camera`` column, else by the first matching ``[assign]`` pattern, else by the only
camera of the file.
"""

from __future__ import annotations

import fnmatch
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..geometry.rotations import mount_rotation, rotvec_to_matrix
from ..model import CameraModel, RigHead
from ..pipeline.atomic import write_text
from .validate import angle_unit, check_crs

HEAD_KEYS = {"camera", "tilt_deg", "azimuth_deg", "cam_from_body", "boresight_deg", "lever_arm_m"}

CAMERA_KEYS = {"id", "name", "width", "height", "focal_px", "fx", "fy_px", "fy", "focal_mm", "pixel_size_mm",
               "pixel_size_um", "cx_px", "cy_px", "cx", "cy", "ppx_mm", "ppy_mm", "pixel_origin", "k1", "k2", "k3",
               "p1", "p2", "distortion"}


@dataclass
class CameraFile:
    """Contents of a camera file."""

    path: str
    cameras: dict[str, CameraModel]
    assign: list[tuple[str, str]] = field(default_factory=list)
    crs: str | None = None
    angles: str | None = None
    heads: list[RigHead] = field(default_factory=list)

    def camera_for(self, image_name: str, source: str, line: int | None) -> str:
        """Camera id of an image without a camera column."""
        for pattern, cam in self.assign:
            if fnmatch.fnmatchcase(image_name, pattern):
                return cam
        if len(self.cameras) == 1:
            return next(iter(self.cameras))
        raise InputError(f"image '{image_name}' matches no [assign] pattern of {self.path} and the camera file "
                         f"holds {len(self.cameras)} cameras: add a camera column or an [assign] table",
                         path=source, line=line, field="camera")


def _line_of(lines: list[str], cam_id: str, key: str, table: str = "cameras") -> int | None:
    """Best-effort 1-based line of ``key`` inside the table/object ``cam_id`` of ``table`` (``cameras``, ``heads``)."""
    start = None
    for i, text in enumerate(lines):
        s = text.strip()
        if start is None and (re.match(rf"^\[\s*{table}\.\"?{re.escape(cam_id)}\"?\s*\]", s)
                              or s.startswith(f'"{cam_id}"') or (table == "cameras" and s == "[camera]")):
            start = i
        elif start is not None and re.match(rf'^"?{re.escape(key)}"?\s*[=:]', s):
            return i + 1
    return None if start is None else start + 1


def _load(path: Path) -> tuple[dict[str, Any], list[str]]:
    text_lines = []
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError("camera file not found", path=path) from None
    text_lines = text.splitlines()
    if path.suffix.lower() == ".json":
        try:
            return json.loads(text), text_lines
        except json.JSONDecodeError as e:
            raise InputError(f"invalid JSON: {e.msg}", path=path, line=e.lineno) from None
    import tomllib

    try:
        return tomllib.loads(text), text_lines
    except tomllib.TOMLDecodeError as e:
        m = re.search(r"line (\d+)", str(e))
        raise InputError(f"invalid TOML: {str(e).split(' (at')[0]}", path=path,
                         line=int(m.group(1)) if m else None) from None


def _number(d: dict, key: str, cam_id: str, path: Path, lines: list[str], required: bool = False,
            default: float | None = None) -> float | None:
    if key not in d:
        if required:
            raise InputError(f"camera '{cam_id}' lacks '{key}'", path=path, line=_line_of(lines, cam_id, "width"),
                             field=f"cameras.{cam_id}.{key}")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(float(v)):
        raise InputError(f"'{v}' is not a finite number", path=path, line=_line_of(lines, cam_id, key),
                         field=f"cameras.{cam_id}.{key}")
    return float(v)


def _camera(cam_id: str, d: dict[str, Any], path: Path, lines: list[str]) -> CameraModel:
    if not isinstance(d, dict):
        raise InputError(f"camera '{cam_id}' must be a table", path=path, field=f"cameras.{cam_id}")
    unknown = sorted(set(d) - CAMERA_KEYS)
    if unknown:
        raise InputError(f"unknown key(s) {', '.join(unknown)} in camera '{cam_id}'", path=path,
                         line=_line_of(lines, cam_id, unknown[0]), field=f"cameras.{cam_id}.{unknown[0]}")
    fld = f"cameras.{cam_id}"
    width = _number(d, "width", cam_id, path, lines, required=True)
    height = _number(d, "height", cam_id, path, lines, required=True)
    if width <= 0 or height <= 0 or not width.is_integer() or not height.is_integer():
        raise InputError(f"image size must be positive integers, got {width} x {height}", path=path,
                         line=_line_of(lines, cam_id, "width"), field=fld + ".width")
    pixel_mm = _number(d, "pixel_size_mm", cam_id, path, lines)
    if pixel_mm is None and "pixel_size_um" in d:
        pixel_mm = _number(d, "pixel_size_um", cam_id, path, lines) / 1000.0
    if pixel_mm is not None and pixel_mm <= 0:
        raise InputError("pixel size must be positive", path=path, line=_line_of(lines, cam_id, "pixel_size_mm"),
                         field=fld + ".pixel_size_mm")
    fx = _number(d, "focal_px", cam_id, path, lines, default=_number(d, "fx", cam_id, path, lines))
    if fx is None:
        focal_mm = _number(d, "focal_mm", cam_id, path, lines)
        if focal_mm is None:
            raise InputError(f"camera '{cam_id}' needs focal_px, or focal_mm with pixel_size_mm", path=path,
                             line=_line_of(lines, cam_id, "width"), field=fld + ".focal_px")
        if pixel_mm is None:
            raise InputError(f"camera '{cam_id}' gives focal_mm but no pixel_size_mm", path=path,
                             line=_line_of(lines, cam_id, "focal_mm"), field=fld + ".pixel_size_mm")
        fx = focal_mm / pixel_mm
    fy = _number(d, "fy_px", cam_id, path, lines, default=_number(d, "fy", cam_id, path, lines, default=fx))
    if fx <= 0 or fy <= 0:
        raise InputError("focal length must be positive", path=path, line=_line_of(lines, cam_id, "focal_px"),
                         field=fld + ".focal_px")
    origin = str(d.get("pixel_origin", "center")).lower()
    if origin not in ("center", "centre", "corner"):
        raise InputError(f"pixel_origin must be center or corner, got '{origin}'", path=path,
                         line=_line_of(lines, cam_id, "pixel_origin"), field=fld + ".pixel_origin")
    shift = -0.5 if origin == "corner" else 0.0
    cx = _number(d, "cx_px", cam_id, path, lines, default=_number(d, "cx", cam_id, path, lines))
    cy = _number(d, "cy_px", cam_id, path, lines, default=_number(d, "cy", cam_id, path, lines))
    if cx is None or cy is None:
        ppx = _number(d, "ppx_mm", cam_id, path, lines, default=0.0)
        ppy = _number(d, "ppy_mm", cam_id, path, lines, default=0.0)
        if (ppx or ppy) and pixel_mm is None:
            raise InputError("ppx_mm/ppy_mm need pixel_size_mm", path=path, line=_line_of(lines, cam_id, "ppx_mm"),
                             field=fld + ".pixel_size_mm")
        cx = (width - 1.0) / 2.0 + (ppx / pixel_mm if ppx else 0.0)
        cy = (height - 1.0) / 2.0 + (ppy / pixel_mm if ppy else 0.0)
    else:
        cx, cy = cx + shift, cy + shift
    model = str(d.get("distortion", "opencv")).lower()
    if model != "opencv":
        raise InputError(f"distortion model '{model}' is not supported (only 'opencv' Brown k1 k2 k3 p1 p2)",
                         path=path, line=_line_of(lines, cam_id, "distortion"), field=fld + ".distortion")
    dist = {k: _number(d, k, cam_id, path, lines, default=0.0) for k in ("k1", "k2", "k3", "p1", "p2")}
    return CameraModel(id=cam_id, width=int(width), height=int(height), fx=fx, fy=fy, cx=cx, cy=cy,
                       pixel_size_mm=pixel_mm, name=str(d.get("name", "")), **dist)


def _head(name: str, d: Any, cams: dict[str, CameraModel], path: Path, lines: list[str]) -> RigHead:
    """One ``[heads.<name>]`` table (see the module docstring)."""
    fld = f"heads.{name}"

    def line_of(key: str) -> int | None:
        return _line_of(lines, name, key, "heads")

    def numbers(key: str, shape: tuple[int, ...], default: Any = None) -> np.ndarray | None:
        if key not in d:
            return None if default is None else np.asarray(default, np.float64)
        try:
            a = np.asarray(d[key], np.float64)
        except (TypeError, ValueError):
            a = None
        if a is None or a.shape != shape or not np.all(np.isfinite(a)):
            raise InputError(f"{key} must be {' x '.join(map(str, shape))} finite numbers", path=path,
                             line=line_of(key), field=f"{fld}.{key}")
        return a

    if not isinstance(d, dict):
        raise InputError(f"head '{name}' must be a table", path=path, field=fld)
    unknown = sorted(set(d) - HEAD_KEYS)
    if unknown:
        raise InputError(f"unknown key(s) {', '.join(unknown)} in head '{name}'", path=path,
                         line=line_of(unknown[0]), field=f"{fld}.{unknown[0]}")
    cam = str(d.get("camera", name))
    if cam not in cams:
        raise InputError(f"head '{name}' uses unknown camera '{cam}'", path=path, line=line_of("camera"),
                         field=f"{fld}.camera")
    matrix = numbers("cam_from_body", (3, 3))
    if matrix is not None:
        if "tilt_deg" in d or "azimuth_deg" in d:
            raise InputError("give the mount as cam_from_body or as tilt_deg and azimuth_deg, not both", path=path,
                             line=line_of("cam_from_body"), field=f"{fld}.cam_from_body")
        if np.abs(matrix @ matrix.T - np.eye(3)).max() > 1e-6 or np.linalg.det(matrix) < 0:
            raise InputError("cam_from_body is not a rotation matrix", path=path, line=line_of("cam_from_body"),
                             field=f"{fld}.cam_from_body")
    else:
        matrix = mount_rotation(float(numbers("tilt_deg", (), 0.0)), float(numbers("azimuth_deg", (), 0.0)))
    boresight = numbers("boresight_deg", (3,), [0.0, 0.0, 0.0])
    return RigHead(name, cam, rotvec_to_matrix(np.radians(boresight)) @ matrix, numbers("lever_arm_m", (3,), [0.0] * 3))


def read_camera_file(path: str | Path) -> CameraFile:
    """Parse a camera file (``.toml`` or ``.json``)."""
    p = Path(path)
    data, lines = _load(p)
    cams: dict[str, CameraModel] = {}
    if "camera" in data and "cameras" in data:
        raise InputError("give either [camera] or [cameras.<id>] tables, not both", path=p, field="camera")
    if "camera" in data:
        single = data["camera"]
        if not isinstance(single, dict):
            raise InputError("[camera] must be a table", path=p, field="camera")
        cid = str(single.get("id", "camera"))
        cams[cid] = _camera(cid, single, p, lines)
    elif isinstance(data.get("cameras"), dict) and data["cameras"]:
        for cid, d in data["cameras"].items():
            cams[str(cid)] = _camera(str(cid), d, p, lines)
    else:
        raise InputError("no camera defined: add a [camera] or [cameras.<id>] table", path=p, field="cameras")
    assign_raw = data.get("assign", {})
    if not isinstance(assign_raw, dict):
        raise InputError("[assign] must map image name patterns to camera ids", path=p, field="assign")
    assign = []
    for pattern, cid in assign_raw.items():
        if str(cid) not in cams:
            line = next((i + 1 for i, t in enumerate(lines) if pattern in t and "=" in t), None)
            raise InputError(f"pattern '{pattern}' assigns unknown camera '{cid}'", path=p, line=line,
                             field="assign")
        assign.append((str(pattern), str(cid)))
    crs = None if data.get("crs") is None else check_crs(data["crs"], p, "crs")
    angles = None if data.get("angles") is None else angle_unit(data["angles"], p, "angles")
    heads_raw = data.get("heads", {})
    if not isinstance(heads_raw, dict):
        raise InputError("[heads.<name>] must be tables", path=p, field="heads")
    heads = [_head(str(n), d, cams, p, lines) for n, d in heads_raw.items()]
    return CameraFile(path=str(p), cameras=cams, assign=assign, crs=crs, angles=angles, heads=heads)


def _toml_value(v: Any) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, float):
        return repr(v)
    return str(v)


def write_camera_file(path: str | Path, cameras: list[CameraModel], crs: str | None = None,
                      angles: str | None = None, heads: list[RigHead] | None = None) -> None:
    """Write cameras (and the heads of a camera system, their mounts as matrices) as a TOML camera file
    (atomically); floats keep full precision."""
    out = ["# Oblique City camera file: focal lengths and principal points in pixels, principal point origin at",
           "# the centre of the top-left pixel, Brown distortion in OpenCV's convention.", ""]
    if crs is not None:
        out.append(f"crs = {_toml_value(crs)}")
    if angles is not None:
        out.append(f"angles = {_toml_value(angles)}")
    for cam in cameras:
        out += ["", f"[cameras.{json.dumps(cam.id)}]"]
        vals: dict[str, Any] = {"width": cam.width, "height": cam.height, "focal_px": float(cam.fx),
                                "fy_px": float(cam.fy), "cx_px": float(cam.cx), "cy_px": float(cam.cy),
                                "pixel_origin": "center", "k1": float(cam.k1), "k2": float(cam.k2),
                                "k3": float(cam.k3), "p1": float(cam.p1), "p2": float(cam.p2)}
        if cam.pixel_size_mm is not None:
            vals["pixel_size_mm"] = float(cam.pixel_size_mm)
        if cam.name:
            vals["name"] = cam.name
        out += [f"{k} = {_toml_value(v)}" for k, v in vals.items()]
    for h in heads or []:
        rows = ", ".join("[" + ", ".join(repr(float(v)) for v in row) + "]" for row in h.sensor_from_rig)
        out += ["", f"[heads.{json.dumps(h.name)}]", f"camera = {json.dumps(h.camera_id)}",
                f"cam_from_body = [{rows}]",
                "lever_arm_m = [" + ", ".join(repr(float(v)) for v in h.lever_arm) + "]"]
    write_text(path, "\n".join(out) + "\n")

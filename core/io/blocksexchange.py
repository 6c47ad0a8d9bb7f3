"""ContextCapture / iTwin Capture BlocksExchange XML (and zipped .xmlz): read and write.

Conventions, from Bentley's format specification (the commented sample of "BlocksExchange XML/XMLZ format" in the
ContextCapture user guide) and checked against its own numeric example:

* Pixels (``PrincipalPoint`` x/y, ``Measurement`` x/y): "the origin is the center of the upper-left image pixel,
  the x-axis is oriented to the right side of the image, and the y-axis to the bottom". That is the core's
  convention, so pixel values pass unchanged. (Some third-party writers put the origin at the pixel's outer
  corner; read those with ``pixel_origin=corner``, which subtracts 0.5 px.)
* ``Rotation`` ``M_ij`` is "the rotation matrix transforming world coordinates (in the specified SRS) into camera
  coordinates (with axes defined by the CameraOrientation of the photogroup)", row i, column j. With the default
  ``XRightYDown`` the camera axes are OpenCV's (x right, y down, z forward), so ``M`` is our ``cam_from_world``;
  other ``CameraOrientation`` values are permutations handled by :data:`CAMERA_ORIENTATIONS`.
* ``Omega/Phi/Kappa`` (degrees) give ``M^T = Rx(omega) Ry(phi) Rz(kappa)``: the spec's example (a nadir photo with
  ``M`` close to diag(-1, 1, -1) and ``Omega 179.652, Phi 0.0499, Kappa 179.907``, XRightYDown) satisfies this
  to 1e-9, and the test suite checks it. So the angles refer to the photogroup's camera axes: with
  ``XRightYUp`` they are the classical PATB angles, with the default ``XRightYDown`` omega differs by 180 deg.
  ``Heading/Pitch/Roll`` rotations are refused (their formula is not published in the specification).
* ``Distortion`` K1 K2 K3 P1 P2: the specification refers to "the classical Brown's distortion model, as
  described in http://en.wikipedia.org/wiki/Distortion_(optics)", whose tangential terms are
  ``x += 2 P1 x y + P2 (r^2 + 2 x^2)`` and ``y += P1 (r^2 + 2 y^2) + 2 P2 x y``: OpenCV's order, so P1/P2 map to
  our p1/p2 unchanged (as the public COLMAP<->ContextCapture converters also do). Metashape swaps the two; a file
  that came through such a tool can be read with ``tangential=swapped``. Distortion applies in image axes
  (x right, y down) whatever the CameraOrientation.
* ``FocalLength`` + ``SensorSize`` are millimetres, SensorSize being the sensor's largest dimension;
  ``PixelSize`` (mm) may replace SensorSize; ``FocalLengthPixels`` replaces both. ``AspectRatio`` is fy/fx.
  A non-zero ``Skew`` is refused (the core's camera has none).
* ControlPoint ``Category`` Horizontal (no z) / Vertical (no x, y): the missing coordinates are stored as NaN
  with an infinite standard deviation. ``HorizontalAccuracy`` -> sigma x and y, ``VerticalAccuracy`` -> sigma z.

Reader options: ``block`` (name or 0-based index when the file holds several blocks), ``crs`` (required when the
block has no SRS, i.e. a local Cartesian frame; otherwise overrides nothing and must agree), ``image_id``
(``stem`` of ImagePath (default), ``name`` = file name with extension, or ``id`` = the Photo Id),
``pixel_origin`` (``center``/``corner``), ``tangential`` (``opencv``/``swapped``), plus the shared options of
:mod:`.common`. Writer options: ``rotation`` (``matrix`` (default, exact) or ``opk``).
"""

from __future__ import annotations

import math
from pathlib import Path, PureWindowsPath
from typing import Any

import numpy as np

from ..errors import InputError
from ..geometry.crs import parse_crs, transform_points
from ..geometry.rotations import (
    from_radians,
    opk_to_world_from_photo,
    orthonormalize,
    to_radians,
    world_from_photo_to_opk,
)
from ..model import CameraModel, GroundPoint, Image, ImageBlock, Pose
from ..pipeline.atomic import write_bytes
from .common import finish_block
from .validate import check_crs, parse_bool, parse_xml, reject_unknown

CAMERA_ORIENTATIONS: dict[str, np.ndarray] = {
    "XRightYDown": np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], float),
    "XRightYUp": np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], float),
    "XLeftYDown": np.array([[-1, 0, 0], [0, 1, 0], [0, 0, -1]], float),
    "XLeftYUp": np.array([[-1, 0, 0], [0, -1, 0], [0, 0, 1]], float),
    "XDownYRight": np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], float),
    "XDownYLeft": np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float),
    "XUpYLeft": np.array([[0, -1, 0], [-1, 0, 0], [0, 0, -1]], float),
    "XUpYRight": np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1]], float),
}
"""CameraOrientation -> ``opencv_from_bex`` axis matrix O: ``x_opencv = O @ x_bex``, so ``R = O @ M``."""


class _Xml:
    """Small helpers that read typed children of an lxml element and name the line on errors."""

    def __init__(self, path: str) -> None:
        self.path = path

    def child(self, el, tag: str, required: bool = False):
        c = el.find(tag)
        if c is None and required:
            raise InputError(f"<{el.tag}> lacks <{tag}>", path=self.path, line=el.sourceline, field=tag)
        return c

    def text(self, el, tag: str, required: bool = False, default: str | None = None) -> str | None:
        c = self.child(el, tag, required)
        if c is None:
            return default
        t = (c.text or "").strip()
        if not t and required:
            raise InputError(f"<{tag}> is empty", path=self.path, line=c.sourceline, field=tag)
        return t if t else default

    def number(self, el, tag: str, required: bool = False, default: float | None = None) -> float | None:
        c = self.child(el, tag, required)
        if c is None:
            return default
        t = (c.text or "").strip()
        try:
            v = float(t)
        except ValueError:
            raise InputError(f"'{t[:40]}' is not a number", path=self.path, line=c.sourceline,
                             field=f"{el.tag}/{tag}") from None
        if not math.isfinite(v):
            raise InputError(f"'{t}' is not a finite number", path=self.path, line=c.sourceline,
                             field=f"{el.tag}/{tag}")
        return v

    def integer(self, el, tag: str, required: bool = False) -> int | None:
        c = self.child(el, tag, required)
        if c is None:
            return None
        t = (c.text or "").strip()
        try:
            return int(t)
        except ValueError:
            raise InputError(f"'{t[:40]}' is not an integer", path=self.path, line=c.sourceline,
                             field=f"{el.tag}/{tag}") from None

    def boolean(self, el, tag: str, default: bool) -> bool:
        c = self.child(el, tag)
        if c is None:
            return default
        return parse_bool((c.text or "").strip(), self.path, c.sourceline, f"{el.tag}/{tag}")


def _srs_table(root, x: _Xml) -> dict[str, tuple[str, int]]:
    """SRS Id -> (definition text, line)."""
    out: dict[str, tuple[str, int]] = {}
    srs_root = root.find("SpatialReferenceSystems")
    if srs_root is None:
        return out
    for srs in srs_root.findall("SRS"):
        sid = x.text(srs, "Id", required=True)
        definition = x.text(srs, "Definition", default="") or ""
        out[sid] = (definition, x.child(srs, "Definition").sourceline if x.child(srs, "Definition") is not None
                    else srs.sourceline)
    return out


READER_OPTIONS: dict[str, str] = {
    "block": "name or 0-based index when the file holds several blocks",
    "crs": "the block's CRS where it has no SRS (a local frame)",
    "image_id": "stem (of ImagePath), name (with extension) or id (the Photo Id)",
    "pixel_origin": "center or corner (files whose pixels start at the corner)",
    "tangential": "opencv or swapped (tangential terms swapped by another tool)",
}
"""The BlocksExchange reader's own options (see the module docstring)."""

def _crs_of(srs_id: str | None, table: dict[str, tuple[str, int]], x: _Xml, line: int | None) -> str | None:
    """Canonical CRS for an SRSId, None for a local frame (no SRS or empty definition)."""
    if srs_id is None:
        return None
    if srs_id not in table:
        raise InputError(f"SRSId {srs_id} is not defined in <SpatialReferenceSystems>", path=x.path, line=line,
                         field="SRSId")
    definition, def_line = table[srs_id]
    if not definition:
        return None
    if definition.upper().startswith("ENU:"):
        raise InputError(f"local ENU frame '{definition}' is not supported: export the block in a projected SRS",
                         path=x.path, line=def_line, field="Definition")
    return check_crs(definition, x.path, "Definition", def_line)


def _camera(pg, x: _Xml, name: str, pixel_shift: float, tangential: str) -> tuple[CameraModel, np.ndarray]:
    """Camera model and CameraOrientation matrix of a Photogroup element."""
    dims = x.child(pg, "ImageDimensions", required=True)
    width = x.integer(dims, "Width", required=True)
    height = x.integer(dims, "Height", required=True)
    if width <= 0 or height <= 0:
        raise InputError(f"image size {width} x {height}", path=x.path, line=dims.sourceline,
                         field="ImageDimensions")
    model_type = x.text(pg, "CameraModelType", default="Perspective")
    if model_type != "Perspective":
        raise InputError(f"camera model '{model_type}' is not supported (only Perspective)", path=x.path,
                         line=x.child(pg, "CameraModelType").sourceline, field="CameraModelType")
    orient_name = x.text(pg, "CameraOrientation", default="XRightYDown")
    if orient_name not in CAMERA_ORIENTATIONS:
        raise InputError(f"unknown CameraOrientation '{orient_name}' (known: {', '.join(CAMERA_ORIENTATIONS)})",
                         path=x.path, line=x.child(pg, "CameraOrientation").sourceline, field="CameraOrientation")
    orient = CAMERA_ORIENTATIONS[orient_name]
    sensor = x.number(pg, "SensorSize")
    pixel_mm = x.number(pg, "PixelSize")
    if pixel_mm is None and sensor is not None:
        pixel_mm = sensor / max(width, height)
    if pixel_mm is not None and pixel_mm <= 0:
        raise InputError("pixel size must be positive", path=x.path, line=pg.sourceline, field="SensorSize")
    fx = x.number(pg, "FocalLengthPixels")
    if fx is None:
        focal_mm = x.number(pg, "FocalLength")
        if focal_mm is None:
            raise InputError(f"photogroup '{name}' needs <FocalLengthPixels> or <FocalLength> with <SensorSize>",
                             path=x.path, line=pg.sourceline, field="FocalLength")
        if pixel_mm is None:
            raise InputError(f"photogroup '{name}' gives <FocalLength> (mm) without <SensorSize> or <PixelSize>",
                             path=x.path, line=x.child(pg, "FocalLength").sourceline, field="SensorSize")
        fx = focal_mm / pixel_mm
    if fx <= 0:
        raise InputError("focal length must be positive", path=x.path, line=pg.sourceline, field="FocalLength")
    aspect = x.number(pg, "AspectRatio", default=1.0)
    skew = x.number(pg, "Skew", default=0.0)
    if abs(skew) > 1e-9 * fx:
        raise InputError(f"non-zero Skew {skew} is not supported", path=x.path,
                         line=x.child(pg, "Skew").sourceline, field="Skew")
    pp = x.child(pg, "PrincipalPoint")
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    if pp is not None:
        if pp.find("x") is not None or pp.find("y") is not None:
            cx = x.number(pp, "x", required=True) + pixel_shift
            cy = x.number(pp, "y", required=True) + pixel_shift
        elif pp.find("xmm") is not None:
            if pixel_mm is None:
                raise InputError("principal point in mm needs <SensorSize> or <PixelSize>", path=x.path,
                                 line=pp.sourceline, field="PrincipalPoint")
            d = orient @ np.array([x.number(pp, "xmm", required=True), x.number(pp, "ymm", required=True), 0.0])
            cx, cy = cx + d[0] / pixel_mm, cy + d[1] / pixel_mm
    dist = {"k1": 0.0, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0}
    de = x.child(pg, "Distortion")
    if de is not None:
        for k in ("K1", "K2", "K3", "P1", "P2"):
            dist[k.lower()] = x.number(de, k, default=0.0)
        if tangential == "swapped":
            dist["p1"], dist["p2"] = dist["p2"], dist["p1"]
    cam = CameraModel(id=name, width=width, height=height, fx=fx, fy=fx * aspect, cx=cx, cy=cy,
                      pixel_size_mm=pixel_mm, name=x.text(pg, "Description", default="") or "", **dist)
    return cam, orient


def _rotation(rot, x: _Xml, orient: np.ndarray) -> np.ndarray:
    """OpenCV ``cam_from_world`` from a <Rotation> element (matrix or omega/phi/kappa degrees)."""
    if rot.find("M_00") is not None:
        m = np.array([[x.number(rot, f"M_{i}{j}", required=True) for j in range(3)] for i in range(3)])
        err = np.abs(m @ m.T - np.eye(3)).max()
        if err > 1e-5 or np.linalg.det(m) < 0:
            raise InputError(f"<Rotation> is not a rotation matrix (|M M^T - I| = {err:.2g}, det "
                             f"{np.linalg.det(m):.3f})", path=x.path, line=rot.sourceline, field="Rotation")
        m = orthonormalize(m)
    elif rot.find("Omega") is not None:
        angles = [to_radians(x.number(rot, t, required=True), "deg") for t in ("Omega", "Phi", "Kappa")]
        m = opk_to_world_from_photo(*angles).T
    elif rot.find("Heading") is not None or rot.find("Yaw") is not None:
        raise InputError("Heading/Pitch/Roll rotations are not supported: export the block with a rotation "
                         "matrix or Omega/Phi/Kappa", path=x.path, line=rot.sourceline, field="Rotation")
    else:
        raise InputError("<Rotation> has neither M_00..M_22 nor Omega/Phi/Kappa", path=x.path, line=rot.sourceline,
                         field="Rotation")
    return orient @ m


def _image_id(photo_id: int, image_path: str, mode: str) -> str:
    name = PureWindowsPath(image_path).name if "\\" in image_path else Path(image_path).name
    if mode == "id":
        return str(photo_id)
    if mode == "name":
        return name
    return Path(name).stem


def _select_block(root, x: _Xml, which: Any):
    blocks = root.findall("Block")
    if not blocks:
        raise InputError("no <Block> in the file", path=x.path, line=root.sourceline, field="Block")
    if which is None:
        if len(blocks) > 1:
            names = [x.text(b, "Name", default=str(i)) for i, b in enumerate(blocks)]
            raise InputError(f"the file holds {len(blocks)} blocks ({', '.join(names)}): choose one with "
                             f"-o block=NAME", path=x.path, field="Block")
        return blocks[0]
    for i, b in enumerate(blocks):
        if str(which) == str(i) or str(which) == x.text(b, "Name", default=None):
            return b
    raise InputError(f"no block named '{which}'", path=x.path, field="block")


def read_bex(source: str, **options: Any) -> ImageBlock:
    """Read a BlocksExchange XML file into an :class:`ImageBlock` (poses as ``pose_approx``)."""
    path = str(source)
    x = _Xml(path)
    root = parse_xml(path)
    if root.tag != "BlocksExchange":
        raise InputError(f"root element is <{root.tag}>, expected <BlocksExchange>", path=path,
                         line=root.sourceline, field=root.tag)
    origin = str(options.pop("pixel_origin", "center")).lower()
    if origin not in ("center", "centre", "corner"):
        raise InputError(f"pixel_origin must be center or corner, got '{origin}'", path=path, field="pixel_origin")
    shift = -0.5 if origin == "corner" else 0.0
    tangential = str(options.pop("tangential", "opencv")).lower()
    if tangential not in ("opencv", "swapped"):
        raise InputError(f"tangential must be opencv or swapped, got '{tangential}'", path=path, field="tangential")
    id_mode = str(options.pop("image_id", "stem")).lower()
    if id_mode not in ("stem", "name", "id"):
        raise InputError(f"image_id must be stem, name or id, got '{id_mode}'", path=path, field="image_id")
    crs_opt = options.pop("crs", None)
    el = _select_block(root, x, options.pop("block", None))

    srs = _srs_table(root, x)
    block_srs = x.text(el, "SRSId")
    crs = _crs_of(block_srs, srs, x, x.child(el, "SRSId").sourceline if block_srs else el.sourceline)
    if crs is None:
        if crs_opt is None:
            raise InputError("the block has no SRS (local Cartesian frame): give its CRS with -o crs=EPSG:nnnn",
                             path=path, line=el.sourceline, field="SRSId")
        crs = check_crs(crs_opt, path, "crs")
    elif crs_opt is not None and check_crs(crs_opt, path, "crs") != crs:
        raise InputError(f"option crs={crs_opt} contradicts the block's SRS {crs[:60]}", path=path, field="crs")
    pcrs = parse_crs(crs)
    if not pcrs.is_projected:
        raise InputError(f"the block's SRS {crs[:60]} is not a projected CRS; photo rotations need a projected "
                         "SRS (export the block in e.g. UTM)", path=path, field="SRSId")

    base = x.text(root, "BaseImagePath")
    block = ImageBlock(crs=crs, image_root=base if base else str(Path(path).resolve().parent))
    by_photo_id: dict[int, str] = {}
    by_path: dict[str, str] = {}
    lines: dict[str, int] = {}
    orients: dict[str, np.ndarray] = {}
    groups = el.find("Photogroups")
    for gi, pg in enumerate([] if groups is None else groups.findall("Photogroup")):
        name = x.text(pg, "Name", default=f"photogroup{gi}")
        pg_srs = x.text(pg, "SRSId")
        if pg_srs is not None and pg_srs != block_srs:
            if _crs_of(pg_srs, srs, x, pg.sourceline) != crs:
                raise InputError(f"photogroup '{name}' uses another SRS than its block (not supported)", path=path,
                                 line=x.child(pg, "SRSId").sourceline, field="SRSId")
        if name in block.cameras:
            raise InputError(f"duplicate photogroup name '{name}'", path=path, line=pg.sourceline, field="Name")
        cam, orient = _camera(pg, x, name, shift, tangential)
        block.add_camera(cam)
        orients[cam.id] = orient
        for ph in pg.findall("Photo"):
            pid = x.integer(ph, "Id", required=True)
            if pid in by_photo_id:
                raise InputError(f"duplicate photo Id {pid}", path=path, line=ph.sourceline, field="Id")
            image_path = x.text(ph, "ImagePath", required=True)
            iid = _image_id(pid, image_path, id_mode)
            if iid in block.images:
                raise InputError(f"duplicate image id '{iid}' (first on line {lines[iid]}); try -o image_id=id",
                                 path=path, line=ph.sourceline, field="ImagePath")
            pose = None
            pe = ph.find("Pose")
            if pe is not None and pe.find("Rotation") is not None and pe.find("Center") is not None:
                r = _rotation(pe.find("Rotation"), x, orient)
                ce = pe.find("Center")
                c = [x.number(ce, t, required=True) for t in ("x", "y", "z")]
                pose = Pose(r, c)
            block.add_image(Image(id=iid, camera_id=cam.id, file=image_path.replace("\\", "/"), pose_approx=pose))
            by_photo_id[pid] = iid
            by_path[image_path] = iid
            lines[iid] = ph.sourceline
    if not block.images:
        raise InputError("the block has no <Photo>", path=path, line=el.sourceline, field="Photo")
    _control_points(el, x, block, srs, crs, by_photo_id, by_path, shift, orients)
    return finish_block(block, path, options, "bex", lines=lines)


def _control_points(el, x: _Xml, block: ImageBlock, srs: dict, crs: str, by_photo_id: dict[int, str],
                    by_path: dict[str, str], shift: float, orients: dict[str, np.ndarray]) -> None:
    """ControlPoints of a Block element into ground points with their image measurements."""
    cps = el.find("ControlPoints")
    if cps is None:
        return
    container_srs = x.text(cps, "SRSId")
    for i, cp in enumerate(cps.findall("ControlPoint")):
        name = x.text(cp, "Name", default=f"CP{i + 1}")
        if name in block.ground_points:
            raise InputError(f"duplicate control point name '{name}'", path=x.path, line=cp.sourceline, field="Name")
        category = x.text(cp, "Category", default="Full")
        if category not in ("Full", "Horizontal", "Vertical"):
            raise InputError(f"unknown Category '{category}' (Full, Horizontal or Vertical)", path=x.path,
                             line=x.child(cp, "Category").sourceline, field="Category")
        kind = "check" if x.boolean(cp, "CheckPoint", False) else "control"
        pos = x.child(cp, "Position", required=True)
        xyz = np.array([np.nan if (t == "z" and category == "Horizontal") or (t != "z" and category == "Vertical")
                        else x.number(pos, t, required=True) for t in ("x", "y", "z")])
        point_srs = x.text(cp, "SRSId", default=container_srs)
        if point_srs is not None:
            pcrs = _crs_of(point_srs, srs, x, cp.sourceline)
            if pcrs is not None and pcrs != crs:
                if category != "Full":
                    raise InputError("Horizontal/Vertical control points in another SRS than the block's are not "
                                     "supported", path=x.path, line=cp.sourceline, field="SRSId")
                xyz = transform_points(xyz[None], pcrs, crs, x.path, [cp.sourceline])[0]
        h = x.number(cp, "HorizontalAccuracy", default=0.02)
        v = x.number(cp, "VerticalAccuracy", default=0.02)
        if h <= 0 or v <= 0:
            raise InputError("accuracies must be positive", path=x.path, line=cp.sourceline,
                             field="HorizontalAccuracy" if h <= 0 else "VerticalAccuracy")
        sigma = np.array([h, h, v])
        sigma[np.isnan(xyz)] = np.inf
        gp = GroundPoint(name=name, xyz=xyz, sigma=sigma, kind=kind)
        for m in cp.findall("Measurement"):
            pid = x.integer(m, "PhotoId")
            if pid is not None:
                if pid not in by_photo_id:
                    raise InputError(f"measurement refers to unknown PhotoId {pid}", path=x.path,
                                     line=x.child(m, "PhotoId").sourceline, field="PhotoId")
                iid = by_photo_id[pid]
            else:
                ip = x.text(m, "ImagePath", required=True)
                if ip not in by_path:
                    raise InputError(f"measurement refers to unknown ImagePath '{ip}'", path=x.path,
                                     line=x.child(m, "ImagePath").sourceline, field="ImagePath")
                iid = by_path[ip]
            if iid in gp.observations:
                raise InputError(f"control point '{name}' measured twice in photo '{iid}'", path=x.path,
                                 line=m.sourceline, field="PhotoId")
            cam = block.camera_of(iid)
            if m.find("x") is not None:
                uv = np.array([x.number(m, "x", required=True), x.number(m, "y", required=True)]) + shift
            else:
                if cam.pixel_size_mm is None:
                    raise InputError("measurement in mm needs the photogroup's pixel size", path=x.path,
                                     line=m.sourceline, field="xmm")
                mm = [x.number(m, "xmm", required=True), x.number(m, "ymm", required=True), 0.0]
                d = orients[cam.id] @ np.array(mm)
                uv = np.array([cam.cx, cam.cy]) + d[:2] / cam.pixel_size_mm
            for axis, val, size in (("x", uv[0], cam.width), ("y", uv[1], cam.height)):
                if not -0.5 <= val <= size - 0.5:
                    raise InputError(f"measurement {axis} = {val} px lies outside photo '{iid}' ({cam.width} x "
                                     f"{cam.height})", path=x.path, line=m.sourceline, field=axis)
            gp.observations[iid] = uv
        block.add_ground_point(gp)


def _fmt(v: float) -> str:
    return repr(float(v))


def write_bex(block: ImageBlock, dest: str, rotation: str = "matrix", name: str = "Oblique City block",
              **unknown: Any) -> None:
    """Write ``block`` as BlocksExchange XML (CameraOrientation XRightYDown, pixel origin as the spec states).

    Images get their adjusted pose if any, else the approximate one; images without pose are written without
    <Pose>. The block's ``image_root`` becomes <BaseImagePath>. ``rotation="opk"`` writes Omega/Phi/Kappa
    degrees instead of the exact matrix.
    """
    from lxml import etree

    reject_unknown(unknown, "bex")

    if rotation not in ("matrix", "opk"):
        raise InputError(f"rotation must be matrix or opk, got '{rotation}'", path=dest, field="rotation")

    def sub(parent, tag: str, text: Any = None):
        e = etree.SubElement(parent, tag)
        if text is not None:
            e.text = text if isinstance(text, str) else _fmt(text)
        return e

    root = etree.Element("BlocksExchange", version="3.2")
    srs_root = sub(root, "SpatialReferenceSystems")
    srs = sub(srs_root, "SRS")
    sub(srs, "Id", "0")
    sub(srs, "Name", parse_crs(block.crs).name)
    sub(srs, "Definition", block.crs)
    if block.image_root:
        sub(root, "BaseImagePath", block.image_root)
    b = sub(root, "Block")
    sub(b, "Name", name)
    sub(b, "SRSId", "0")
    groups = sub(b, "Photogroups")
    photo_ids: dict[str, int] = {}
    for cam in block.cameras.values():
        pg = sub(groups, "Photogroup")
        sub(pg, "Name", cam.id)
        if cam.name:
            sub(pg, "Description", cam.name)
        dims = sub(pg, "ImageDimensions")
        sub(dims, "Width", str(cam.width))
        sub(dims, "Height", str(cam.height))
        sub(pg, "CameraModelType", "Perspective")
        sub(pg, "FocalLengthPixels", cam.fx)
        if cam.pixel_size_mm is not None:
            sub(pg, "FocalLength", cam.fx * cam.pixel_size_mm)
            sub(pg, "PixelSize", cam.pixel_size_mm)
        sub(pg, "CameraOrientation", "XRightYDown")
        pp = sub(pg, "PrincipalPoint")
        sub(pp, "x", cam.cx)
        sub(pp, "y", cam.cy)
        d = sub(pg, "Distortion")
        for k in ("k1", "k2", "k3", "p1", "p2"):
            sub(d, k.upper(), getattr(cam, k))
        sub(pg, "AspectRatio", cam.fy / cam.fx)
        sub(pg, "Skew", "0")
        for img in block.images.values():
            if img.camera_id != cam.id:
                continue
            photo_ids[img.id] = len(photo_ids)
            ph = sub(pg, "Photo")
            sub(ph, "Id", str(photo_ids[img.id]))
            sub(ph, "ImagePath", img.file or img.id)
            pose = img.pose
            sub(ph, "Component", "1" if pose is not None else "0")
            if pose is None:
                continue
            pe = sub(ph, "Pose")
            rot = sub(pe, "Rotation")
            if rotation == "matrix":
                for i in range(3):
                    for j in range(3):
                        sub(rot, f"M_{i}{j}", pose.R[i, j])
            else:
                for tag, a in zip(("Omega", "Phi", "Kappa"), world_from_photo_to_opk(pose.R.T), strict=True):
                    sub(rot, tag, from_radians(a, "deg"))
            ce = sub(pe, "Center")
            for t, v in zip("xyz", pose.C, strict=True):
                sub(ce, t, v)
    cps = sub(b, "ControlPoints")
    for g in block.ground_points.values():
        if g.xyz is None:
            continue
        cp = sub(cps, "ControlPoint")
        sub(cp, "Name", g.name)
        nan = np.isnan(g.xyz)
        category = "Horizontal" if nan[2] and not nan[0] else "Vertical" if nan[0] and not nan[2] else "Full"
        sub(cp, "Category", category)
        pos = sub(cp, "Position")
        for t, v, missing in zip("xyz", g.xyz, nan, strict=True):
            if not missing:
                sub(pos, t, v)
        sub(cp, "CheckPoint", "true" if g.kind == "check" else "false")
        if category != "Vertical":
            sub(cp, "HorizontalAccuracy", float(np.sqrt((g.sigma[0] ** 2 + g.sigma[1] ** 2) / 2.0)))
        if category != "Horizontal":
            sub(cp, "VerticalAccuracy", g.sigma[2])
        for iid, uv in g.observations.items():
            if iid not in photo_ids:
                continue
            m = sub(cp, "Measurement")
            sub(m, "PhotoId", str(photo_ids[iid]))
            sub(m, "x", uv[0])
            sub(m, "y", uv[1])
    data = etree.tostring(root, xml_declaration=True, encoding="utf-8", pretty_print=True)
    write_bytes(dest, data)

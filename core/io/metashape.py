"""Agisoft Metashape camera XML (Export Cameras > Agisoft XML): read and write.

Conventions, from the Metashape user manual (appendix "Camera models", frame cameras) and its Python API
reference (``Chunk.transform``, ``Camera.transform``, ``Calibration``):

* A ``<sensor type="frame">`` has ``<resolution width height>`` and a ``<calibration>`` (class ``adjusted``
  preferred over ``initial``) with ``f``, ``cx``, ``cy`` (pixels; the principal point's offset from the image
  centre), ``b1`` (affinity), ``b2`` (non-orthogonality), ``k1``..``k4`` and ``p1``..``p4``::

      x = X / Z,  y = Y / Z,  r2 = x^2 + y^2
      x' = x (1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4) + p1 (r2 + 2 x^2) + 2 p2 x y
      y' = y (1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4) + p2 (r2 + 2 y^2) + 2 p1 x y
      u = w / 2 + cx + x' (f + b1) + y' b2,   v = h / 2 + cy + y' f

  in pixels from the image's top-left corner (the centre of the top-left pixel is (0.5, 0.5)). In the core's
  camera (:mod:`..model.camera`): ``fx = f + b1``, ``fy = f``, ``cx = w / 2 + cx - 0.5`` (likewise ``cy``), and
  Metashape's p1, p2 are OpenCV's p2, p1. Non-zero ``b2``, ``k4``, ``p3``, ``p4`` are refused (the core's camera
  has none of them). A sensor without ``<calibration>`` takes ``f`` from its ``focal_length`` and
  ``pixel_width`` properties (millimetres) and its principal point at the centre.
* Camera axes are OpenCV's (x right, y down, z forward). ``<camera><transform>`` (16 numbers, row by row) maps
  the camera frame to its component's frame; ``<component><transform>`` (``rotation`` 9 numbers, ``translation``,
  ``scale``: ``x' = scale rotation x + translation``) maps that to the chunk's internal frame, and the chunk's
  ``<transform>`` maps the internal frame to geocentric coordinates of the datum of the chunk's CRS (WKT in
  ``<reference>``), or straight to that CRS when it is a ``LOCAL_CS``.
* The block CRS is the chunk's when it is a projected CRS in metres; option ``crs`` chooses another (required for
  a geographic or local chunk CRS). Centres are transformed by pyproj. A rotation is turned by the rotation of the
  block CRS's axes against the geocentric ones at its centre: the rotation nearest to the Jacobian of the
  transformation there (grid convergence and the local vertical), which is the local frame an omega-phi-kappa
  export from Metashape refers to as well. Transformations that pyproj could only do as a "ballpark" for heights
  (a geoid model it does not have) are refused rather than leave heights off by the geoid undulation.
* ``<markers>``: ``<reference x y z enabled>`` in the chunk's CRS; enabled markers are control points, disabled
  ones check points (Metashape's meaning of the check box); ``sx sy sz`` (metres) when present, else option
  ``gcp_sigma``'s default of 0.02 m. Their image positions are ``<frames><frame><markers><marker marker_id>
  <location camera_id x y>``.
* A camera's ``<reference x y z yaw pitch roll>`` (the navigation data: position in the chunk's CRS, angles in
  degrees as ``camera.reference.rotation``, see :mod:`..geometry.rotations`, the yaw against true north, turned
  into the block CRS's grid by the grid convergence) orients a camera without ``<transform>`` (not aligned), or
  with option ``orientation=reference`` every camera that has one (the navigation data as the approximate
  orientation of an aligned project, for a triangulation of its own). Its ``enabled`` flags and accuracies are not
  read (the triangulation's default sigmas apply). Cameras with neither are imported without orientation.
* The cameras of a multi-camera system (Metashape's multi-camera layout: a slave camera's ``master_id`` is its
  master camera's ``id``) are one exposure each, named by the master's label, with each sensor as a head; the
  shared option ``rig=auto`` estimates the system's rig from their orientations (the slave sensors' own offsets are
  not read). Slave cameras that lack both a ``<transform>`` and a reference are refused: their pose would have to
  come from those offsets. The writer writes independent cameras (no multi-camera layout).
* The file holds no image paths: a camera's ``label`` is its image file name, looked up under ``image_root`` and
  its subfolders (without that option, in the XML file's own folder only) by name, else by name without
  extension.

Reader options: ``crs``, ``chunk`` (label or 0-based index when the document holds several), ``orientation``
(``alignment``, the default, or ``reference``), plus the shared
options of :mod:`.common` (``pose=adjusted`` for a block Metashape has already aligned). The writer puts the chunk's
internal frame at the mean camera centre, axes along the block CRS's local axes, scale 1.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..geometry.crs import (
    crs_transformer,
    geocentric_crs,
    grid_rotations,
    is_projected_metric,
    parse_crs,
    true_north_angles,
)
from ..geometry.rotations import FLIP_YZ, metashape_ypr_to_photo, photo_to_metashape_ypr
from ..model import CameraModel, GroundPoint, Image, ImageBlock, Pose
from ..pipeline.atomic import write_bytes
from .common import finish_block
from .validate import check_crs, parse_bool, parse_xml, reject_unknown

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".tif", ".tiff", ".png")
"""Suffixes tried when a camera label names its image without extension."""

READER_OPTIONS: dict[str, str] = {
    "crs": "the block's CRS (required for a geographic or local chunk)",
    "chunk": "label or 0-based index when the document holds several",
    "orientation": "alignment (the aligned transform, else the reference) or reference (the navigation data)",
}
"""The Metashape reader's own options (see the module docstring)."""

_REFUSED_TERMS = ("b2", "k4", "p3", "p4")


class _Xml:
    """Typed attribute and text readers for lxml elements that name the line on errors."""

    def __init__(self, path: str) -> None:
        self.path = path

    def fail(self, el, reason: str, field: str) -> InputError:
        return InputError(reason, path=self.path, line=el.sourceline, field=field)

    def number(self, el, attr: str, default: float | None = None) -> float | None:
        t = el.get(attr)
        if t is None:
            if default is None:
                raise self.fail(el, f"<{el.tag}> lacks attribute {attr}", attr)
            return default
        try:
            v = float(t)
        except ValueError:
            raise self.fail(el, f"'{t[:40]}' is not a number", f"{el.tag}/@{attr}") from None
        if not math.isfinite(v):
            raise self.fail(el, f"'{t}' is not a finite number", f"{el.tag}/@{attr}")
        return v

    def numbers(self, el, count: int) -> np.ndarray:
        parts = (el.text or "").split()
        try:
            v = np.array([float(p) for p in parts])
        except ValueError:
            raise self.fail(el, f"<{el.tag}> holds something that is not a number", el.tag) from None
        if len(v) != count or not np.all(np.isfinite(v)):
            raise self.fail(el, f"<{el.tag}> needs {count} finite numbers, has {len(parts)}", el.tag)
        return v

    def child_number(self, el, tag: str, default: float = 0.0) -> float:
        c = el.find(tag)
        return default if c is None else float(self.numbers(c, 1)[0])


def _similarity(el, x: _Xml) -> np.ndarray:
    """A ``<transform>`` of rotation, translation and scale as a 4x4 matrix (missing parts: identity)."""
    m = np.eye(4)
    rot, tr, sc = el.find("rotation"), el.find("translation"), el.find("scale")
    r = np.eye(3) if rot is None else x.numbers(rot, 9).reshape(3, 3)
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) <= 0:
        raise x.fail(rot, "the rotation is not a rotation matrix", "rotation")
    s = 1.0 if sc is None else float(x.numbers(sc, 1)[0])
    if s <= 0:
        raise x.fail(sc, f"scale {s} is not positive", "scale")
    m[:3, :3] = s * r
    m[:3, 3] = 0.0 if tr is None else x.numbers(tr, 3)
    return m


def _sensor(el, x: _Xml, cam_id: str) -> CameraModel:
    """A ``<sensor>`` as a core camera (see the module docstring)."""
    stype = el.get("type", "frame")
    if stype != "frame":
        raise x.fail(el, f"sensor type '{stype}' is not supported (frame cameras only)", "type")
    res = el.find("resolution")
    if res is None:
        raise x.fail(el, "<sensor> lacks <resolution>", "resolution")
    w, h = int(x.number(res, "width")), int(x.number(res, "height"))
    props = {p.get("name"): p for p in el.findall("property")}
    pixel_mm = x.number(props["pixel_width"], "value") if "pixel_width" in props else None
    if pixel_mm is not None and "pixel_height" in props and \
            abs(x.number(props["pixel_height"], "value") - pixel_mm) > 1e-9 * pixel_mm:
        raise x.fail(props["pixel_height"], "non-square pixels are not supported", "pixel_height")
    cals = el.findall("calibration")
    cal = next((c for c in cals if c.get("class") == "adjusted"), cals[0] if cals else None)
    if cal is None:
        if pixel_mm is None or "focal_length" not in props:
            raise x.fail(el, "sensor has neither <calibration> nor focal_length and pixel_width properties",
                         "calibration")
        f = x.number(props["focal_length"], "value") / pixel_mm
        return CameraModel(id=cam_id, width=w, height=h, fx=f, fy=f, cx=w / 2 - 0.5, cy=h / 2 - 0.5,
                           pixel_size_mm=pixel_mm, name=el.get("label", ""))
    if cal.get("type", "frame") != "frame":
        raise x.fail(cal, f"calibration type '{cal.get('type')}' is not supported", "type")
    cres = cal.find("resolution")
    if cres is not None and (int(x.number(cres, "width")), int(x.number(cres, "height"))) != (w, h):
        raise x.fail(cres, "the calibration's resolution differs from the sensor's", "resolution")
    f = x.child_number(cal, "f", default=float("nan"))
    if not f > 0:
        raise x.fail(cal, "<calibration> lacks a positive <f>", "f")
    for term in _REFUSED_TERMS:
        if x.child_number(cal, term) != 0.0:
            raise x.fail(cal.find(term), f"calibration term {term} is not supported (the camera model has no "
                         f"{term}); recalibrate without it", term)
    v = {k: x.child_number(cal, k) for k in ("cx", "cy", "b1", "k1", "k2", "k3", "p1", "p2")}
    return CameraModel(id=cam_id, width=w, height=h, fx=f + v["b1"], fy=f, cx=w / 2 + v["cx"] - 0.5,
                       cy=h / 2 + v["cy"] - 0.5, k1=v["k1"], k2=v["k2"], k3=v["k3"], p1=v["p2"], p2=v["p1"],
                       pixel_size_mm=pixel_mm, name=el.get("label", ""))


def _select_chunk(root, x: _Xml, which: Any):
    chunks = root.findall("chunk")
    if not chunks:
        raise x.fail(root, "the document has no <chunk>", "chunk")
    if which is None:
        if len(chunks) > 1:
            raise x.fail(root, f"the document holds {len(chunks)} chunks: choose one with -o chunk=LABEL or index",
                         "chunk")
        return chunks[0]
    for c in chunks:
        if c.get("label") == str(which):
            return c
    if str(which).isdigit() and int(which) < len(chunks):
        return chunks[int(which)]
    raise x.fail(root, f"no chunk '{which}' (chunks: {', '.join(c.get('label', '?') for c in chunks)})", "chunk")


def _image_files(root: str | None, recursive: bool) -> dict[str, str]:
    """File name and stem -> path relative to ``root``, for the image files in it (and its subfolders when
    ``recursive``); empty without root."""
    out: dict[str, str] = {}
    if root is None or not Path(root).is_dir():
        return out
    base = Path(root).expanduser().resolve()
    for p in sorted(base.rglob("*") if recursive else base.glob("*")):
        if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file():
            rel = p.relative_to(base).as_posix()
            out.setdefault(p.name, rel)
            out.setdefault(p.stem, rel)
    return out


def read_metashape(source: str, **options: Any) -> ImageBlock:
    """Read a Metashape camera XML file into an :class:`ImageBlock` (see the module docstring)."""
    path = str(source)
    x = _Xml(path)
    root = parse_xml(path)
    if root.tag != "document":
        raise x.fail(root, f"root element is <{root.tag}>, expected <document> (Metashape camera XML)", root.tag)
    crs_opt = options.pop("crs", None)
    chunk = _select_chunk(root, x, options.pop("chunk", None))
    orientation = str(options.pop("orientation", "alignment")).lower()
    if orientation not in ("alignment", "reference"):
        raise InputError(f"orientation must be alignment or reference, got '{orientation}'", path=path,
                         field="orientation")

    ref = chunk.find("reference")
    chunk_crs = None
    if ref is not None and (ref.text or "").strip():
        chunk_crs = parse_crs(ref.text.strip(), path, "reference")
    local = chunk_crs is None or chunk_crs.type_name == "Engineering CRS"
    if crs_opt is not None:
        crs = check_crs(crs_opt, path, "crs")
    elif not local and is_projected_metric(chunk_crs.to_wkt()):
        crs = check_crs(chunk_crs.to_wkt(), path, "reference")
    else:
        what = "a local frame" if local else f"{chunk_crs.name}, not a projected CRS in metres"
        raise InputError(f"the chunk's CRS is {what}: give the block's CRS with -o crs=EPSG:nnnn", path=path,
                         line=chunk.sourceline if ref is None else ref.sourceline, field="reference")
    if not is_projected_metric(crs):
        raise InputError(f"crs {crs[:60]} is not a projected CRS in metres", path=path, field="crs")
    target = parse_crs(crs)
    if local:  # the chunk transform gives coordinates of the block CRS itself
        to_world: Callable[..., np.ndarray] = lambda xyz, lines=None: np.asarray(xyz, np.float64).reshape(-1, 3)  # noqa: E731
    else:
        to_world = crs_transformer(geocentric_crs(chunk_crs), target, path, "reference")
    chunk_t = np.eye(4) if chunk.find("transform") is None else _similarity(chunk.find("transform"), x)

    block = ImageBlock(crs=crs)
    sensors: dict[str, str] = {}
    sensors_el = chunk.find("sensors")
    sensor_els = [] if sensors_el is None else sensors_el.findall("sensor")
    labels = [s.get("label", "") for s in sensor_els]
    for s in sensor_els:
        sid = s.get("id")
        if sid is None or sid in sensors:
            raise x.fail(s, f"sensor id {sid!r} missing or repeated", "id")
        label = s.get("label", "")
        cam_id = label if label and labels.count(label) == 1 else f"sensor{sid}"
        block.add_camera(_sensor(s, x, cam_id))
        sensors[sid] = cam_id
    components = {}
    comp_el = chunk.find("components")
    for c in [] if comp_el is None else comp_el.findall("component"):
        t = c.find("transform")
        components[c.get("id")] = np.eye(4) if t is None else _similarity(t, x)

    root = options.get("image_root")
    files = _image_files(str(root), True) if root else _image_files(str(Path(path).resolve().parent), False)
    lines: dict[str, int] = {}
    by_id: dict[str, str] = {}
    masters: dict[str, str] = {}  # image -> the id of its multi-camera system's master camera (its own without one)
    references: dict[str, np.ndarray] = {}  # image -> x, y, z (chunk CRS), yaw, pitch, roll (radians)
    cams_el = chunk.find("cameras")
    centres, rots, posed = [], [], []
    for c in [] if cams_el is None else cams_el.iter("camera"):
        cid, label, sid = c.get("id"), c.get("label"), c.get("sensor_id")
        if cid is None or not label:
            raise x.fail(c, "<camera> needs id and label attributes", "label")
        if cid in by_id:
            raise x.fail(c, f"camera id {cid} repeated", "id")
        if label in block.images:
            raise x.fail(c, f"camera label '{label}' repeated (first on line {lines[label]})", "label")
        if sid not in sensors:
            raise x.fail(c, f"camera refers to unknown sensor_id {sid!r}", "sensor_id")
        orient = c.find("orientation")
        if orient is not None and (orient.text or "1").strip() != "1":
            raise x.fail(orient, "rotated images (EXIF orientation other than 1) are not supported", "orientation")
        t_el = c.find("transform")
        nav = _camera_reference(c, x)
        if nav is not None:
            references[label] = nav
            if orientation == "reference":
                t_el = None
        if t_el is None and nav is None and c.get("master_id") not in (None, cid):
            raise x.fail(c, "slave camera of a multi-camera sensor without <transform>: its pose would come from "
                         "the rig offsets, which this reader does not apply; export with every camera's transform",
                         "transform")
        if t_el is not None:
            m = x.numbers(t_el, 16).reshape(4, 4)
            if np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-12:
                raise x.fail(t_el, "the last row of a camera transform must be 0 0 0 1", "transform")
            comp = c.get("component_id")
            if comp is not None and comp not in components:
                raise x.fail(c, f"camera refers to unknown component_id {comp}", "component_id")
            world = chunk_t @ components.get(comp, np.eye(4)) @ m
            scale = np.cbrt(np.linalg.det(world[:3, :3]))
            r = world[:3, :3] / scale if scale > 0 else world[:3, :3]
            if not scale > 0 or np.abs(r @ r.T - np.eye(3)).max() > 1e-6:
                raise x.fail(t_el, "the camera transform is not a rotation and translation", "transform")
            centres.append(world[:3, 3])
            rots.append(r)
            posed.append(label)
        block.add_image(Image(id=label, camera_id=sensors[sid], file=files.get(label, label)))
        by_id[cid] = label
        lines[label] = c.sourceline
        masters[label] = c.get("master_id") or cid
    if not block.images:
        raise x.fail(chunk, "the chunk has no <camera>", "cameras")
    if any(masters[label] != cid for cid, label in by_id.items()):
        _exposures(block, masters, by_id, lines, x.path)
    aligned = set(posed)
    navigated = [label for label in references if label not in aligned]
    if navigated:
        nav = np.array([references[label] for label in navigated])
        if local:
            world = nav[:, :3]
        else:
            world = crs_transformer(chunk_crs, target, path, "reference")(nav[:, :3], [lines[k] for k in navigated])
        north = np.zeros(len(world)) if local else true_north_angles(world, crs, path, [lines[k] for k in navigated])
        for label, c_w, (yaw, pitch, roll), n in zip(navigated, world, nav[:, 3:], north, strict=True):
            block.images[label].pose_approx = Pose(FLIP_YZ @ metashape_ypr_to_photo(yaw - n, pitch, roll).T, c_w)
    if posed:
        src = np.array(centres)
        world_c = to_world(src, [lines[k] for k in posed])
        if not local:
            _check_heights(world_c, chunk, path)
        q = np.repeat(np.eye(3)[None], len(src), 0) if local else grid_rotations(src, to_world, path=path)
        for label, c_w, q_k, r_k in zip(posed, world_c, q, rots, strict=True):
            block.images[label].pose_approx = Pose((q_k @ r_k).T, c_w)
    _markers(chunk, x, block, by_id, chunk_crs if not local else None, target)
    return finish_block(block, path, options, "metashape", lines=lines)


def _check_heights(world: np.ndarray, chunk, path: str) -> None:
    """Refuse aligned cameras that the chunk's ``<transform>`` puts far from the earth's surface (heights
    ``world[:, 2]`` beyond 100 km, or no position at all): a geocentric transform without its translation, or a
    chunk that was never georeferenced."""
    z = world[:, 2]
    if not np.all(np.isfinite(world)) or np.abs(z).max() > 1e5:
        worst = float(np.nanmax(np.abs(z))) if np.isfinite(z).any() else math.inf
        t = chunk.find("transform")
        raise InputError(f"the chunk's transform puts the aligned cameras {worst / 1e3:.0f} km from the earth's "
                         "surface (a geocentric transform without its translation, or a chunk that is not "
                         "georeferenced)",
                         path=path, line=(chunk if t is None else t).sourceline, field="transform")


def _camera_reference(c, x: _Xml) -> np.ndarray | None:
    """A camera's ``<reference>`` as ``x, y, z, yaw, pitch, roll`` ``(6,)`` (chunk CRS, radians), or None when it
    lacks one of them (a position alone does not orient a camera)."""
    ref = c.find("reference")
    keys = ("x", "y", "z", "yaw", "pitch", "roll")
    if ref is None or any(ref.get(k) is None for k in keys):
        return None
    v = np.array([x.number(ref, k) for k in keys])
    v[3:] = np.radians(v[3:])
    return v


def _exposures(block: ImageBlock, masters: dict[str, str], by_id: dict[str, str], lines: dict[str, int],
               path: str) -> None:
    """The multi-camera layout's exposures: each image's is its master camera's label (``masters`` maps an image to
    its master's camera id, ``by_id`` camera ids to labels); a system has one image per sensor."""
    seen: dict[tuple[str, str], str] = {}
    for label, master in masters.items():
        if master not in by_id:
            raise InputError(f"camera '{label}' refers to unknown master_id {master}", path=path,
                             line=lines[label], field="master_id")
        img = block.images[label]
        img.exposure = by_id[master]
        key = (img.exposure, img.camera_id)
        if key in seen:
            raise InputError(f"cameras '{seen[key]}' and '{label}' are both sensor '{img.camera_id}' of the "
                             f"multi-camera system of '{img.exposure}'", path=path, line=lines[label],
                             field="master_id")
        seen[key] = label


def _markers(chunk, x: _Xml, block: ImageBlock, by_id: dict[str, str], chunk_crs, target) -> None:
    """``<markers>`` and their ``<frames>`` image positions into ground points."""
    m_el = chunk.find("markers")
    to_world = None if chunk_crs is None else crs_transformer(chunk_crs, target, x.path, "marker")
    names: dict[str, str] = {}
    for mk in [] if m_el is None else m_el.findall("marker"):
        mid, name = mk.get("id"), mk.get("label") or f"marker{mk.get('id')}"
        if mid is None or mid in names:
            raise x.fail(mk, f"marker id {mid!r} missing or repeated", "id")
        if name in block.ground_points:
            raise x.fail(mk, f"marker label '{name}' repeated", "label")
        r = mk.find("reference")
        xyz, kind, sigma = None, "control", np.full(3, 0.02)
        if r is not None and r.get("x") is not None:
            xyz = np.array([x.number(r, a) for a in ("x", "y", "z")])
            if to_world is not None:
                xyz = to_world(xyz, [r.sourceline])[0]
            kind = "control" if parse_bool(r.get("enabled", "true"), x.path, r.sourceline, "enabled") else "check"
            sigma = np.array([x.number(r, a, default=0.02) for a in ("sx", "sy", "sz")])
            if np.any(sigma <= 0):
                raise x.fail(r, "marker accuracies must be positive", "sx")
        block.add_ground_point(GroundPoint(name=name, xyz=xyz, sigma=sigma, kind=kind))
        names[mid] = name
    frames = chunk.find("frames")
    for fm in [] if frames is None else frames.iter("marker"):
        mid = fm.get("marker_id")
        if mid is None:
            continue
        if mid not in names:
            raise x.fail(fm, f"projection of unknown marker_id {mid}", "marker_id")
        g = block.ground_points[names[mid]]
        for loc in fm.findall("location"):
            cam = loc.get("camera_id")
            if cam not in by_id:
                raise x.fail(loc, f"marker position in unknown camera_id {cam!r}", "camera_id")
            if loc.get("valid", "true").lower() == "false":
                continue
            iid = by_id[cam]
            uv = np.array([x.number(loc, "x"), x.number(loc, "y")]) - 0.5
            cm = block.camera_of(iid)
            if not (-0.5 <= uv[0] <= cm.width - 0.5 and -0.5 <= uv[1] <= cm.height - 0.5):
                raise x.fail(loc, f"marker position ({uv[0] + 0.5}, {uv[1] + 0.5}) lies outside camera '{iid}'",
                             "x")
            if iid in g.observations:
                raise x.fail(loc, f"marker '{g.name}' placed twice in camera '{iid}'", "camera_id")
            g.observations[iid] = uv


def _fmt(v: float) -> str:
    return repr(float(v))


def write_metashape(block: ImageBlock, dest: str, **unknown: Any) -> None:
    """Write ``block`` as Metashape camera XML (adjusted poses where known, else approximate ones; images without
    a pose get no ``<transform>``), each approximate pose (the navigation data) as the camera's ``<reference>``
    (yaw against true north). Ground points become markers (check points disabled), with their image positions."""
    from lxml import etree

    reject_unknown(unknown, "metashape")
    crs = parse_crs(block.crs)
    from_world = crs_transformer(crs, geocentric_crs(crs), dest, "crs")
    to_world = crs_transformer(geocentric_crs(crs), crs, dest, "crs")

    def sub(parent, tag: str, text: str | None = None, **attrs: Any):
        e = etree.SubElement(parent, tag, {k: str(v) for k, v in attrs.items()})
        if text is not None:
            e.text = text
        return e

    posed = [img for img in block.images.values() if img.pose is not None]
    centres = from_world(np.array([img.pose.C for img in posed])) if posed else np.zeros((0, 3))
    q = grid_rotations(centres, to_world) if posed else np.zeros((0, 3, 3))
    origin = np.round(centres.mean(0)) if posed else np.zeros(3)
    r_chunk = grid_rotations(origin[None], to_world)[0].T  # geocentric_from_internal: block CRS axes

    root = etree.Element("document", version="2.0.0")
    chunk = sub(root, "chunk", label="Oblique City block", enabled="true")
    sensors = sub(chunk, "sensors", next_id=len(block.cameras))
    sensor_ids = {}
    for i, cam in enumerate(block.cameras.values()):
        sensor_ids[cam.id] = i
        s = sub(sensors, "sensor", id=i, label=cam.id, type="frame")
        sub(s, "resolution", width=cam.width, height=cam.height)
        if cam.pixel_size_mm is not None:
            sub(s, "property", name="pixel_width", value=_fmt(cam.pixel_size_mm))
            sub(s, "property", name="pixel_height", value=_fmt(cam.pixel_size_mm))
            sub(s, "property", name="focal_length", value=_fmt(cam.fy * cam.pixel_size_mm))
        cal = sub(s, "calibration", type="frame", **{"class": "adjusted"})
        sub(cal, "resolution", width=cam.width, height=cam.height)
        for tag, v in (("f", cam.fy), ("cx", cam.cx + 0.5 - cam.width / 2), ("cy", cam.cy + 0.5 - cam.height / 2),
                       ("b1", cam.fx - cam.fy), ("k1", cam.k1), ("k2", cam.k2), ("k3", cam.k3), ("p1", cam.p2),
                       ("p2", cam.p1)):
            sub(cal, tag, _fmt(v))
    cams = sub(chunk, "cameras", next_id=len(block.images))
    cam_ids = {}
    pose_of = {img.id: k for k, img in enumerate(posed)}
    navigated = [img for img in block.images.values() if img.pose_approx is not None]
    north = dict(zip([img.id for img in navigated], true_north_angles(
        np.array([img.pose_approx.C for img in navigated]).reshape(-1, 3), block.crs), strict=True))
    for i, img in enumerate(block.images.values()):
        cam_ids[img.id] = i
        c = sub(cams, "camera", id=i, sensor_id=sensor_ids[img.camera_id], label=img.id)
        if img.id in pose_of:
            k = pose_of[img.id]
            m = np.eye(4)
            m[:3, :3] = r_chunk.T @ q[k].T @ img.pose.R.T
            m[:3, 3] = r_chunk.T @ (centres[k] - origin)
            sub(c, "transform", " ".join(_fmt(v) for v in m.ravel()))
        if img.id in north:
            nav = img.pose_approx
            yaw, pitch, roll = np.degrees(photo_to_metashape_ypr((FLIP_YZ @ nav.R).T))
            sub(c, "reference", x=_fmt(nav.C[0]), y=_fmt(nav.C[1]), z=_fmt(nav.C[2]),
                yaw=_fmt(yaw + np.degrees(north[img.id])), pitch=_fmt(pitch), roll=_fmt(roll), enabled="true",
                rotation_enabled="true")
    markers = sub(chunk, "markers", next_id=len(block.ground_points))
    frame_markers = []
    for j, g in enumerate(block.ground_points.values()):
        mk = sub(markers, "marker", id=j, label=g.name)
        if g.xyz is not None and np.all(np.isfinite(g.xyz)):
            sub(mk, "reference", x=_fmt(g.xyz[0]), y=_fmt(g.xyz[1]), z=_fmt(g.xyz[2]), sx=_fmt(g.sigma[0]),
                sy=_fmt(g.sigma[1]), sz=_fmt(g.sigma[2]), enabled="true" if g.kind == "control" else "false")
        obs = [(cam_ids[iid], uv) for iid, uv in g.observations.items() if iid in cam_ids]
        if obs:
            frame_markers.append((j, obs))
    frames = sub(chunk, "frames", next_id=1)
    fr = sub(sub(frames, "frame", id=0), "markers")
    for j, obs in frame_markers:
        fm = sub(fr, "marker", marker_id=j)
        for cid, uv in obs:
            sub(fm, "location", camera_id=cid, pinned="true", x=_fmt(uv[0] + 0.5), y=_fmt(uv[1] + 0.5))
    t = sub(chunk, "transform")
    sub(t, "rotation", " ".join(_fmt(v) for v in r_chunk.ravel()), locked="true")
    sub(t, "translation", " ".join(_fmt(v) for v in origin), locked="true")
    sub(t, "scale", "1", locked="true")
    sub(chunk, "reference", crs.to_wkt("WKT1_GDAL") or crs.to_wkt())
    data = etree.tostring(root, xml_declaration=True, encoding="utf-8", pretty_print=True)
    write_bytes(dest, data)

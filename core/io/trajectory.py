"""GNSS/IMU event lists: per trigger of a multi-head camera system the navigation solution (position and roll,
pitch, heading), turned into every head's image orientation through the system's mounting (direct georeferencing).

This is what a photo flight delivers before any triangulation: the trajectory processor's solution at each camera
event and the camera system's calibration (each head's mount, boresight and lever arm). The format ``gnssimu`` reads
and writes it:

* rows ``exposure x y z roll pitch heading`` (order set by the ``columns`` option or a header row), positions in the
  block's CRS, or ``exposure lat lon h roll pitch heading`` with positions in ``position_crs`` (default EPSG:4979,
  ellipsoidal heights, passed on unchanged unless the block's CRS has a vertical datum); optional ``time``
  (seconds), ``sx sy sz`` (metres) and ``sroll spitch sheading`` (same unit as the angles);
* the navigation convention of :mod:`..geometry.rotations` (body x forward, y right, z down;
  ``R_ned_from_body = Rz(heading) Ry(pitch) Rx(roll)``), in the ``angles`` unit (default degrees);
* ``heading`` option or directive: ``true`` (default: clockwise from true north, as an inertial system gives it;
  the grid convergence at each exposure, from the CRS by pyproj, turns it into the grid heading) or ``grid``;
* the camera file (``cameras`` option, see :mod:`.camerafile`) holds the cameras and the ``[heads.<name>]`` of the
  system: an image per head and exposure, named ``image_name`` (option or directive, default
  ``{exposure}_{head}``), its file
  ``image_file`` (option or directive, default ``{image}``: the name; ``{exposure}`` and ``{head}`` work too) plus
  ``image_ext``. The position is the body frame's origin; a head's centre is at its lever arm from there.

The block gets the exposures, heads and times and a rig ``system`` with the heads as calibrated, the first head of
the camera file as its reference. The position sigmas are the images' ones. The IMU's roll, pitch and heading sigmas
are those of the angles (roll about the body's x axis, pitch about the levelled y axis, heading about the vertical);
the adjustment's attitude priors are about the world's X, Y, Z (:mod:`..aerotri.bundle`), so each exposure's are
turned into the world (:func:`..geometry.rotations.world_axis_sigmas` with :func:`..geometry.rotations.ypr_axes`,
the diagonal of the rotated covariance; the writer inverts that in the least-squares sense).

The writer takes a block with a rig and exposures: each exposure's body pose comes from the image of the rig's first
head it has (its mount undone), its heading against true north (or grid), with a camera file holding the rig's heads;
``# image_name:`` and ``# image_file:`` lines give the images' names and files (when every file is its id between one
prefix and suffix, ``images/<id>.jpg``). It refuses a block whose images an event list cannot carry: one without an
exposure or a head of the rig, names that follow no pattern of exposure and head, or heads whose orientations do not
follow the rig (:data:`RIG_TOLERANCE`: an adjusted block, whose heads the triangulation moved apart).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..geometry.crs import transform_points, true_north_angles
from ..geometry.rotations import (
    angle_sigmas,
    cam_from_world_to_ypr,
    from_radians,
    rotation_angle,
    to_radians,
    world_axis_sigmas,
    world_from_body,
    ypr_axes,
)
from ..model import Image, ImageBlock, Rig
from ..pipeline.atomic import write_text
from .camerafile import write_camera_file
from .common import finish_block
from .opk import LIST_OPTIONS, optional_field, read_list
from .validate import angle_unit, parse_float, reject_unknown
from .validate import delimiter as parse_delimiter

COLUMN_ALIASES = {
    "exposure": "exposure", "event": "exposure", "id": "exposure", "name": "exposure", "exposure_id": "exposure",
    "shot": "exposure", "trigger": "exposure",
    "x": "x", "easting": "x", "east": "x", "e": "x",
    "y": "y", "northing": "y", "north": "y", "n": "y",
    "z": "z", "height": "z", "elevation": "z", "alt": "z", "altitude": "z",
    "lat": "lat", "latitude": "lat", "lon": "lon", "long": "lon", "longitude": "lon", "h": "h", "ellh": "h",
    "roll": "roll", "pitch": "pitch", "heading": "heading", "yaw": "heading",
    "time": "time", "gps_time": "time", "gpstime": "time", "gnss_time": "time", "timestamp": "time",
    "sx": "sx", "sy": "sy", "sz": "sz", "sroll": "sroll", "spitch": "spitch", "sheading": "sheading",
    "syaw": "sheading",
}
REQUIRED = ("exposure", "roll", "pitch", "heading")
DEFAULT_COLUMNS = "exposure,x,y,z,roll,pitch,heading"
HEADINGS = ("true", "grid")
NAME_TEMPLATES = ("{exposure}_{head}", "{exposure}-{head}", "{exposure}{head}", "{head}_{exposure}", "{exposure}")
"""The image name patterns the writer recognises (the first that names every image)."""
READER_OPTIONS: dict[str, str] = {
    **LIST_OPTIONS,
    "position_crs": "CRS of lat lon h positions (default EPSG:4979)",
    "heading": "true (against true north: the grid convergence is applied) or grid",
    "image_name": "template of the images' ids, {exposure} and {head} (default {exposure}_{head})",
    "image_file": "template of their files, {image}, {exposure} and {head} (default {image})",
}
"""The event list reader's own options (see the module docstring)."""

RIG_TOLERANCE = (1e-3, 1e-5)
"""Metres and radians: the most a head's orientation may differ from its exposure's reference head through the rig
for the writer (an event list carries one orientation per exposure)."""


def read_gnssimu(source: str, **options: Any) -> ImageBlock:
    """Read a GNSS/IMU event list and its camera file (with heads) into an :class:`ImageBlock` whose images'
    ``pose_approx`` are the heads' orientations from the navigation solution (see the module docstring)."""
    position_crs = options.pop("position_crs", None)
    name_opt = options.pop("image_name", None)
    file_opt = options.pop("image_file", None)
    heading_opt = options.pop("heading", None)
    lf = read_list(source, options, COLUMN_ALIASES, REQUIRED, DEFAULT_COLUMNS, ("roll", "pitch", "heading"))
    name_line = None
    if name_opt is None and "image_name" in lf.directives:
        name_opt, name_line = lf.directives["image_name"]
    name_fmt = str(name_opt or "{exposure}_{head}")
    path, cams, columns = lf.path, lf.cams, lf.columns
    if heading_opt is None and "heading" in lf.directives:
        heading_opt, line = lf.directives["heading"]
    else:
        line = None
    heading = str(heading_opt or "true").lower()
    if heading not in HEADINGS:
        raise InputError(f"heading must be true or grid, got '{heading}'", path=path, line=line, field="heading")
    if not cams.heads:
        raise InputError(f"the camera file {cams.path} has no [heads.<name>] tables: a GNSS/IMU event list needs "
                         "the camera system's heads (mount and lever arm)", path=path, field="cameras")
    geographic = "lat" in columns or "lon" in columns
    need = ("lat", "lon", "h") if geographic else ("x", "y", "z")
    missing = [c for c in need if c not in columns]
    if missing:
        raise InputError(f"no {', '.join(missing)} column (positions are x y z, or lat lon h)", path=path,
                         field="columns")
    lf.check_sigma_columns(("sx", "sy", "sz"), ("sroll", "spitch", "sheading"))
    file_line = None
    if file_opt is None and "image_file" in lf.directives:
        file_opt, file_line = lf.directives["image_file"]
    file_fmt = str(file_opt or "{image}")
    for fmt, key, line_no in ((name_fmt, "image_name", name_line), (file_fmt, "image_file", file_line)):
        try:
            fmt.format(exposure="e", head="h", image="i")
        except (KeyError, IndexError, ValueError) as e:
            raise InputError(f"{key} '{fmt}' may use only {{exposure}}, {{head}} and {{image}} ({e})", path=path,
                             line=line_no, field=key) from None

    records = []
    for line_no, rec in lf.records("exposure", "exposure"):
        pos = [parse_float(rec[c], path, line_no, c) for c in need]
        att = [to_radians(parse_float(rec[c], path, line_no, c), lf.unit) for c in ("roll", "pitch", "heading")]
        t = optional_field(rec, "time")
        t = None if t is None else parse_float(t, path, line_no, "time")
        records.append((line_no, rec["exposure"], pos, att, t, lf.sigmas(rec, ("sx", "sy", "sz"), line_no, False),
                        lf.sigmas(rec, ("sroll", "spitch", "sheading"), line_no, True)))
    xyz = np.array([r[2] for r in records], np.float64)
    rows = [r[0] for r in records]
    if geographic:
        src = str(position_crs or "EPSG:4979")
        xyz = transform_points(xyz[:, [1, 0, 2]], src, lf.crs, path, rows)  # (lon, lat, h)
    north = true_north_angles(xyz, lf.crs, path, rows) if heading == "true" else np.zeros(len(records))

    block = ImageBlock(crs=lf.crs)
    for cam in cams.cameras.values():
        block.add_camera(cam)
    rig = Rig("system", tuple(cams.heads))
    block.rigs[rig.name] = rig
    lines: dict[str, int] = {}
    for k, (line_no, ex, _, (roll, pitch, hdg), t, s_pos, s_att) in enumerate(records):
        wfb = world_from_body(hdg - north[k], pitch, roll)
        for h in rig.heads:
            iid = name_fmt.format(exposure=ex, head=h.name)
            if iid in lines:
                raise InputError(f"image name '{iid}' twice (image_name '{name_fmt}')", path=path, line=line_no,
                                 field="image_name")
            lines[iid] = line_no
            file = file_fmt.format(exposure=ex, head=h.name, image=iid) + lf.image_ext
            block.add_image(Image(id=iid, camera_id=h.camera_id, file=file, head=h.name, exposure=ex,
                                  time=t, pose_approx=h.image_pose(wfb, xyz[k]),
                                  sigma_position=None if s_pos is None else s_pos.copy(),
                                  sigma_attitude=None if s_att is None else world_axis_sigmas(
                                      ypr_axes(hdg - north[k], pitch, roll), s_att)))
    lf.image_root(block, options)
    return finish_block(block, path, options, "gnssimu", lines=lines)


def _file_template(block: ImageBlock) -> str | None:
    """``prefix{image}suffix`` when every image's file is its id between one prefix and suffix (else None; None for
    files equal to the ids, the reader's default)."""
    first = next(iter(block.images.values()))
    at = (first.file or "").find(first.id)
    if at < 0:
        return None
    prefix, suffix = first.file[:at], first.file[at + len(first.id):]
    if not (prefix or suffix) or any(img.file != prefix + img.id + suffix for img in block.images.values()):
        return None
    return prefix + "{image}" + suffix


def write_gnssimu(block: ImageBlock, dest: str, angles: str = "deg", delimiter: str = "whitespace",
                  cameras: str | None = None, heading: str = "true", **unknown: Any) -> None:
    """Write the block's exposures as a GNSS/IMU event list plus a camera file with the rig's heads (see the module
    docstring). Raises :class:`InputError` for a block without a rig or exposures."""
    reject_unknown(unknown, "gnssimu")
    sep = parse_delimiter(delimiter)
    unit = angle_unit(angles)
    if heading not in HEADINGS:
        raise InputError(f"heading must be true or grid, got '{heading}'", field="heading")
    if len(block.rigs) != 1:
        raise InputError(f"a GNSS/IMU event list needs one rig, the block has {len(block.rigs)} (import it with its "
                         "exposures: a rig is then estimated)", path=dest, field="rig")
    rig = next(iter(block.rigs.values()))
    heads = {h.name: h for h in rig.heads}
    exposures: dict[str, list[Image]] = {}
    for img in block.images.values():
        if img.exposure is not None and img.head in heads and img.pose is not None:
            exposures.setdefault(img.exposure, []).append(img)
    if not exposures:
        raise InputError("no image of the block has an exposure and a head of its rig", path=dest, field="exposure")
    left = len(block.images) - sum(len(v) for v in exposures.values())
    if left:
        raise InputError(f"{left} images have no orientation, exposure or head of the rig '{rig.name}': an event "
                         "list cannot carry them (export opk or bex)", path=dest, field="exposure")
    names = next((t for t in NAME_TEMPLATES if all(i.id == t.format(exposure=i.exposure, head=i.head)
                                                   for i in block.images.values())), None)
    if names is None:
        raise InputError("the image names follow no pattern of exposure and head (" + ", ".join(NAME_TEMPLATES)
                         + "): an event list cannot name them", path=dest, field="image_name")
    rows = []
    order = [h.name for h in rig.heads]
    for ex, imgs in exposures.items():
        img = min(imgs, key=lambda i: order.index(i.head))
        h = heads[img.head]
        wfb = img.pose.R.T @ h.sensor_from_rig
        body = img.pose.C - wfb @ h.lever_arm
        for other in imgs:
            there = heads[other.head].image_pose(wfb, body)
            dc = float(np.linalg.norm(other.pose.C - there.C))
            da = rotation_angle(other.pose.R, there.R)
            if dc > RIG_TOLERANCE[0] or da > RIG_TOLERANCE[1]:
                raise InputError(f"image '{other.id}' is {dc:.4f} m and {np.degrees(da):.5f} deg from where the rig "
                                 f"puts it from '{img.id}': an event list holds one orientation per exposure (an "
                                 "adjusted block: export the imported one, --imported, or opk or bex)", path=dest,
                                 field="rig")
        ypr = cam_from_world_to_ypr(img.pose.R, h.sensor_from_rig)
        rows.append((ex, body, ypr, img.time, img.sigma_position,
                     None if img.sigma_attitude is None else angle_sigmas(ypr_axes(*ypr), img.sigma_attitude)))
    xyz = np.array([r[1] for r in rows])
    north = true_north_angles(xyz, block.crs) if heading == "true" else np.zeros(len(rows))
    dest_path = Path(dest)
    cam_path = Path(cameras) if cameras else dest_path.with_name(dest_path.stem + "_cameras.toml")
    write_camera_file(cam_path, list(block.cameras.values()), crs=block.crs, angles=unit, heads=list(rig.heads))
    with_time = any(r[3] is not None for r in rows)
    with_pos = any(r[4] is not None for r in rows)
    with_att = any(r[5] is not None for r in rows)
    cols = ["exposure", "x", "y", "z", "roll", "pitch", "heading"] + (["time"] if with_time else []) + (
        ["sx", "sy", "sz"] if with_pos else []) + (["sroll", "spitch", "sheading"] if with_att else [])
    join = (lambda f: " ".join(f)) if sep is None else sep.join
    rel_cam = cam_path.name if cam_path.parent.resolve() == dest_path.parent.resolve() else str(cam_path)
    out = ["# Oblique City GNSS/IMU event list: body x forward, y right, z down; R_ned_from_body = Rz(heading) "
           "Ry(pitch) Rx(roll)", f"# crs: {block.crs}", f"# angles: {unit}", f"# heading: {heading}",
           f"# cameras: {rel_cam}", f"# image_name: {names}"] + (
        [f"# image_file: {files}"] if (files := _file_template(block)) else []) + [join(cols)]
    for k, (ex, c, (yaw, pitch, roll), t, s_pos, s_att) in enumerate(rows):
        if (any(ch.isspace() for ch in ex)) if sep is None else sep in ex:
            raise InputError(f"exposure '{ex}' contains the delimiter; choose another delimiter", path=dest,
                             field="delimiter")
        row = [ex, *(repr(float(v)) for v in c),
               *(repr(float(from_radians(a, unit))) for a in (roll, pitch, yaw + north[k]))]
        if with_time:
            row.append("-" if t is None else repr(float(t)))
        if with_pos:
            row += ["-"] * 3 if s_pos is None else [repr(float(v)) for v in s_pos]
        if with_att:
            row += ["-"] * 3 if s_att is None else [repr(float(from_radians(v, unit))) for v in s_att]
        out.append(join(row))
    write_text(dest, "\n".join(out) + "\n")

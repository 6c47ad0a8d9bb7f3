"""Results of the ``aerotri`` stage in Blender: the adjusted tie points as a point cloud, and the report's figures.

* :func:`build_tie_points`: ``aerotri/ties.npz`` (:class:`core.model.TiePoints`) as a vertex-only mesh "Tie points"
  in the "Tie points" collection, at ``world - origin`` (:mod:`.georef`), with an INT point attribute ``rays``
  (observations per track not rejected as blunders), a FLOAT one ``residual_px`` (the track's RMS image residual
  after adjustment, NaN without one) and a ``Col`` colour attribute from the ray count (:data:`RAY_RAMP`: 2 rays
  blue ... 12 and more red), drawn as points like the dense cloud; :func:`colour_tie_points` colours them by either.
  Tracks without an intersected position are left out; above :data:`MAX_TIE_POINTS` a fixed random subset is
  shown.
* :func:`build_quality_layer`: one quality layer of ``aerotri/layers`` (CBA ray count, tie point standard deviation
  XY or Z, intersection error before/after) as a georeferenced image plane: a single quad whose corners are the
  outer corners of the GeoTIFF grid (``x0``, ``y0`` and ``cell`` of the PixelIsArea transform), at the median
  height of the adjusted tie points, textured with the layer's coloured PNG (nearest-cell sampling, emission so
  the colours read as they are). Objects are named "<layer> layer" in the "Quality layers" collection; building
  a layer again replaces its plane.
* :func:`report_summary`: the key figures of ``aerotri/report.json`` for the Triangulation panel.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..core.aerotri.report import (
    estimated_control_sigma,
    estimated_prior_sigma,
    estimated_tie_sigma,
    largest_corner_shift,
    largest_systematic,
)
from ..core.errors import InputError
from ..core.io.geotiff import read_geotiff
from ..core.io.validate import read_json
from ..core.model import Raster, TiePoints
from ..core.pipeline import Workspace
from . import georef
from .layers import mesh_from_arrays, point_display
from .scene_tree import layer_collection

TIES_FILE = "aerotri/ties.npz"
REPORT_FILE = "aerotri/report.json"
REPORT_HTML = "aerotri/report.html"
LAYERS_DIR = "aerotri/layers"
QUALITY_LAYERS = ("cba_rays", "cba_std_xy", "cba_std_z", "intersection_error_before", "intersection_error_after")
"""Layer names written by the aerotri stage (``<name>.tif`` with the values, ``<name>.png`` coloured)."""
MAX_TIE_POINTS = 300_000

RAY_RAMP = ((2, (0.10, 0.25, 0.90)), (3, (0.00, 0.75, 0.90)), (5, (0.10, 0.80, 0.20)), (8, (0.95, 0.85, 0.10)),
            (12, (0.90, 0.15, 0.10)))
"""Ray count -> sRGB colour stops (linear in between, clamped outside)."""
RESIDUAL_RAMP = ((0.0, (0.10, 0.25, 0.90)), (0.5, (0.00, 0.75, 0.90)), (1.0, (0.10, 0.80, 0.20)),
                 (2.0, (0.95, 0.85, 0.10)), (3.0, (0.90, 0.15, 0.10)))
"""A tie point's RMS image residual in units of the adjustment's sigma0 (pixels) -> sRGB colour stops: 1 is
what the noise leaves, 3 and more a point whose rays do not meet as the others do."""
NO_VALUE_COLOUR = (0.5, 0.5, 0.5)
"""The colour of a tie point without the value coloured (no residual kept)."""
TIE_COLOURINGS = (("rays", "Ray Count", "Colour the tie points by the rays the adjustment kept of them"),
                  ("residual", "Residual", "Colour the tie points by their RMS image residual, in units of the "
                                           "adjustment's sigma0"))
"""The colourings of the tie point cloud (:func:`colour_tie_points`): value, label, description."""


def ramp_colours(values: np.ndarray, ramp: tuple) -> np.ndarray:
    """sRGB colours ``(n, 3)`` float in [0, 1] of ``values (n,)`` along a ramp of (value, colour) stops (linear in
    between, clamped outside); NaN values get :data:`NO_VALUE_COLOUR`."""
    stops = np.array([s for s, _ in ramp], np.float64)
    rgb = np.array([c for _, c in ramp], np.float64)
    v = np.asarray(values, np.float64)
    out = np.stack([np.interp(v, stops, rgb[:, k]) for k in range(3)], axis=1)
    out[~np.isfinite(v)] = NO_VALUE_COLOUR
    return out


def ray_colours(rays: np.ndarray) -> np.ndarray:
    """sRGB colours ``(n, 3)`` float in [0, 1] of ray counts ``(n,)`` along :data:`RAY_RAMP`."""
    return ramp_colours(rays, RAY_RAMP)


def colour_tie_points(obj, colouring: str, sigma0_px: float) -> str:
    """Colour the tie point cloud ``obj`` (made by :func:`build_tie_points`) by ``colouring`` (see
    :data:`TIE_COLOURINGS`) from its point attributes ``rays`` and ``residual_px``, the residuals in units of the
    adjustment's ``sigma0_px``. Raises :class:`InputError` for an unknown colouring. Returns a one-line summary."""
    mesh = obj.data
    n = len(mesh.vertices)
    if colouring == "rays":
        values = np.zeros(n, np.int32)
        mesh.attributes["rays"].data.foreach_get("value", values)
        rgb = ray_colours(values)
        summary = f"{n} tie points coloured by ray count"
    elif colouring == "residual":
        if "residual_px" not in mesh.attributes:
            raise InputError("these tie points were built without their residuals: build the scene again")
        values = np.zeros(n, np.float32)
        mesh.attributes["residual_px"].data.foreach_get("value", values)
        rgb = ramp_colours(values / sigma0_px, RESIDUAL_RAMP)
        high = int(np.sum(values > RESIDUAL_RAMP[-1][0] * sigma0_px))
        summary = (f"{n} tie points coloured by RMS residual (sigma0 {sigma0_px:.3f} px; {high} at "
                   f"{RESIDUAL_RAMP[-1][0]:g} sigma0 or more)")
    else:
        names = ", ".join(c for c, _, _ in TIE_COLOURINGS)
        raise InputError(f"unknown tie point colouring '{colouring}' (use {names})")
    rgba = np.concatenate([rgb, np.ones((n, 1))], axis=1)
    mesh.color_attributes["Col"].data.foreach_set("color_srgb", rgba.astype(np.float32).ravel())
    mesh.update()
    return summary


def load_ties(path: Path) -> TiePoints:
    """The adjusted tie points; a missing file raises :class:`InputError`, an unreadable one the core's
    :class:`WorkspaceError` (the core never unpickles)."""
    if not path.is_file():
        raise InputError("no adjusted tie points (run the 'aerotri' stage first)", path)
    return TiePoints.load(str(path))


def build_tie_points(scene, ws: Workspace) -> str:
    """The adjusted tie points as a coloured point cloud; returns a one-line summary."""
    import bpy

    ties = load_ties(ws.path(TIES_FILE))
    good = ~np.asarray(ties.obs_blunder, bool)
    rays = np.bincount(ties.obs_track[good], minlength=ties.n_tracks)
    keep = np.flatnonzero(np.all(np.isfinite(ties.xyz), axis=1))
    n_valid = len(keep)
    if n_valid > MAX_TIE_POINTS:
        keep = np.sort(np.random.default_rng(0).choice(keep, MAX_TIE_POINTS, replace=False))
    xyz = ties.xyz[keep]
    georef.ensure_georef(scene, ws.crs, xyz)
    coll = layer_collection(scene, "ties", "Tie points")
    mesh = mesh_from_arrays("Tie points", georef.world_to_local(scene, xyz))
    mesh.attributes.new("rays", "INT", "POINT").data.foreach_set("value", rays[keep].astype(np.int32))
    residual = ties.extra.get("residual_px", np.full(ties.n_tracks, np.nan))
    mesh.attributes.new("residual_px", "FLOAT", "POINT").data.foreach_set("value",
                                                                          residual[keep].astype(np.float32))
    mesh.color_attributes.new("Col", "BYTE_COLOR", "POINT")
    obj = bpy.data.objects.new("Tie points", mesh)
    colour_tie_points(obj, "rays", 1.0)
    obj["oc_tie_points"] = n_valid
    coll.objects.link(obj)
    if len(xyz) > 1:
        extent = np.ptp(xyz[:, :2], axis=0)
        spacing = math.sqrt(max(float(extent[0] * extent[1]), 1e-6) / len(xyz))
        point_display(obj, radius=max(0.05, 0.3 * spacing))
    shown = f"{len(keep)} of {n_valid}" if len(keep) < n_valid else f"{n_valid}"
    median = int(np.median(rays[keep])) if len(keep) else 0
    return f"{shown} tie points shown (median {median} rays)"


def raster_corners(raster: Raster, z: float) -> np.ndarray:
    """World corners ``(4, 3)`` of a raster's whole grid at height ``z``: south-west, south-east, north-east,
    north-west (counter-clockwise seen from above)."""
    rows, cols = raster.shape
    x1, y1 = raster.x0 + cols * raster.cell, raster.y0 - rows * raster.cell
    return np.array([[raster.x0, y1, z], [x1, y1, z], [x1, raster.y0, z], [raster.x0, raster.y0, z]])


def build_quality_layer(scene, ws: Workspace, name: str = "cba_rays", z: float | None = None) -> str:
    """The quality layer ``name`` (one of :data:`QUALITY_LAYERS`) as a textured plane; ``z`` defaults to the median
    height of the adjusted tie points. Returns a one-line summary; a missing or unreadable layer raises
    :class:`InputError` naming the file."""
    import bpy

    if name not in QUALITY_LAYERS:
        raise InputError(f"unknown quality layer '{name}' (use one of {', '.join(QUALITY_LAYERS)})", field="name")
    tif, png = ws.path(f"{LAYERS_DIR}/{name}.tif"), ws.path(f"{LAYERS_DIR}/{name}.png")
    for f in (tif, png):
        if not f.is_file():
            raise InputError("no quality layer (run the 'aerotri' stage first)", f)
    raster = read_geotiff(tif)
    rows, cols = raster.shape
    if z is None:
        ties = load_ties(ws.path(TIES_FILE))
        heights = ties.xyz[np.isfinite(ties.xyz[:, 2]), 2]
        z = float(np.median(heights)) if len(heights) else 0.0
    corners = raster_corners(raster, z)
    georef.ensure_georef(scene, ws.crs, corners)
    image = bpy.data.images.load(str(png), check_existing=True)
    if tuple(image.size) != (cols, rows):
        raise InputError(f"picture {tuple(image.size)} does not match the layer's grid {(cols, rows)}", png)
    coll = layer_collection(scene, "quality_layers", "Quality layers", clear=False)
    for old in [o for o in coll.objects if o.get("oc_layer") == name]:  # rebuilding replaces the plane
        data = old.data
        bpy.data.objects.remove(old)
        if data is not None and data.users == 0:
            bpy.data.meshes.remove(data)
    label = f"{name} layer"
    mesh = mesh_from_arrays(label, georef.world_to_local(scene, corners), np.array([[0, 1, 2, 3]]))
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], np.float32)
    mesh.uv_layers.new(name="layer").data.foreach_set("uv", uv.ravel())
    mat = bpy.data.materials.get(label) or bpy.data.materials.new(label)
    if mat.node_tree is None:  # Blender 4.x; from 5.0 every material has its node tree
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    nodes.clear()
    tex = nodes.new("ShaderNodeTexImage")
    tex.name, tex.image, tex.interpolation = "Layer", image, "Closest"
    emit = nodes.new("ShaderNodeEmission")
    out = nodes.new("ShaderNodeOutputMaterial")
    mat.node_tree.links.new(tex.outputs["Color"], emit.inputs["Color"])
    mat.node_tree.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    mesh.materials.append(mat)
    obj = bpy.data.objects.new(label, mesh)
    obj["oc_layer"] = name
    obj["oc_cell_m"] = float(raster.cell)
    coll.objects.link(obj)
    return f"{name}: {cols}x{rows} cells of {raster.cell:g} m at {z:.1f} m"


def report_summary(path: Path) -> dict:
    """Key figures of ``aerotri/report.json``: mode, connection, images, sigma0 (unitless and px), check point
    RMS XY / Z (m) and their count, rejected observations (%), of a mounting calibration the camera with the
    largest boresight correction and its angle in degrees (``mounting``: ``(cameras, camera, angle)`` or None), and
    the camera with the largest systematic image residual (``systematic``: ``(camera, px)`` or None; reports
    written before it existed have none), and the control points whose coordinates the adjustment rejected with the
    number of control measurements it rejected (``control_rejected``: ``(names, measurements)``), and the GNSS
    positions and IMU attitudes it rejected (``priors_rejected``: ``(positions, attitudes, images)``, two counts and
    the images concerned in order, None when none), and the GNSS offsets per strip (``gnss_strips``: ``(strips,
    strip, metres)``, their number and the strip with the largest offset, None when none were estimated), and without
    them the strips whose GNSS positions share an offset (``strips_suspected``: the same triple, the strip with the
    largest normalised offset, None when none), and the control point axis with the largest error its test can miss
    (``weakest_control``: ``(point, axis, metres)``, None without one; see :func:`.core.aerotri.report.reliability`),
    and how far a GNSS position and an IMU attitude error its test can miss moves an image at most
    (``prior_effect``: ``(metres, degrees)``, either None where no such prior was tested), and the oblique images
    HAT could not start from the nadir run's corrections (``oblique_without_nadir``: no nadir image in their
    exposure; 0 in reports written before it existed), and HAT's fusion of each exposure's heads on the rig
    (``rig_fusion``: ``(exposures, degrees, metres)``, the heads' RMS moves from their runs; None without one), and
    of a self-calibration the camera whose image corner it moves the most (``self_calibration``: ``(cameras, camera,
    px, std px or None, significant, tested)``, the last two counting the corrections with a standard deviation;
    None without one), and the tie measurements' sigma
    when the adjustment estimated one other than the given (``tie_sigma``: ``(given px, estimated px)`` of its first
    run, None otherwise and in reports written before it existed), the factors it scaled the GNSS/IMU prior sigmas by
    (``prior_sigma``: words -> factors along X Y Z, {} when it kept them), the factor it scaled the control points'
    image measurement sigmas by (``control_sigma``, None when it kept them), and the block's datum shift (``datum``:
    ``(shift (3,) m, its standard deviations (3,) m or None)``, None without one and in reports written before it
    existed).
    Raises :class:`InputError` naming the file."""
    doc = read_json(path, "no triangulation report (run the 'aerotri' stage)")
    try:
        check = doc["check_points"]["all"]
        angles = {c: float(math.sqrt(sum(float(a) ** 2 for a in m["boresight_deg"])))
                  for c, m in (doc.get("mounting") or {}).items()}
        largest = max(angles, key=angles.get) if angles else None
        ground = doc.get("ground_points") or []
        rejected = ([str(g["name"]) for g in ground if g.get("rejected_coordinates")],
                    sum(len(g.get("rejected_images") or []) for g in ground))
        priors = [(str(i), part) for r in doc.get("runs") or [] for i, part in r.get("priors_rejected") or []]
        parts = [part for _, part in priors]
        offsets = {n: float(math.sqrt(sum(float(a) ** 2 for a in d["offset_m"])))
                   for n, d in (doc.get("gnss_strips") or {}).items()}
        strip = max(offsets, key=offsets.get) if offsets else None
        suspect = {n: d for n, d in (doc.get("gnss_strip_check") or {}).items() if d.get("flagged")}
        worst = max(suspect, key=lambda n: max(float(w) for w in suspect[n]["w"])) if suspect else None
        weak = doc.get("weakest_control")
        tested = [((r.get("reliability") or {}).get("priors") or {}) for r in doc.get("runs") or []]
        effect = {key: max((float(a) for p in tested for a in (p.get(key) or {}).get("effect_max", [])), default=None)
                  for key in ("position_m", "attitude_deg")}
        calib = doc.get("self_calibration") or {}
        moved = largest_corner_shift(calib)
        tested = [p["significant"] for c in calib.values() for p in c["parameters"] if p.get("significant") is not None]
        return {"mounting": (len(angles), largest, angles[largest]) if largest else None,
                "self_calibration": (len(calib), moved, float(calib[moved]["corner_shift_px"]),
                                     calib[moved].get("corner_shift_std_px"), sum(tested), len(tested))
                if moved else None,
                "priors_rejected": (parts.count("position"), parts.count("attitude"),
                                    sorted({i for i, _ in priors})) if priors else None,
                "systematic": largest_systematic(doc.get("image_residual_fields") or {}),
                "gnss_strips": (len(offsets), strip, offsets[strip]) if strip else None,
                "strips_suspected": (len(suspect), worst, float(math.sqrt(sum(float(a) ** 2
                                                                              for a in suspect[worst]["mean_m"]))))
                if worst else None,
                "control_rejected": rejected if rejected[0] or rejected[1] else None,
                "weakest_control": (str(weak["name"]), str(weak["axis"]), float(weak["mdb_m"])) if weak else None,
                "prior_effect": (effect["position_m"], effect["attitude_deg"])
                if effect["position_m"] is not None or effect["attitude_deg"] is not None else None,
                "oblique_without_nadir": int(doc.get("oblique_without_nadir") or 0),
                "rig_fusion": (int(doc["rig_fusion"]["exposures"]), float(doc["rig_fusion"]["moved_deg"]),
                               float(doc["rig_fusion"]["moved_m"])) if doc.get("rig_fusion") else None,
                "tie_sigma": estimated_tie_sigma(doc),
                "prior_sigma": estimated_prior_sigma(doc),
                "control_sigma": estimated_control_sigma(doc),
                "datum": ([float(v) for v in doc["datum"]["shift_m"]],
                          None if doc["datum"]["std_m"] is None else [float(v) for v in doc["datum"]["std_m"]])
                if doc.get("datum") else None,
                "mode": str(doc["mode"]), "connection": str(doc.get("connection") or ""),
                "images": int(doc["images"]), "sigma0": float(doc["sigma0"]), "sigma0_px": float(doc["sigma0_px"]),
                "check_n": int(check["n"]), "check_rms_xy_m": check["rms_xy_m"], "check_rms_z_m": check["rms_z_m"],
                "blunder_percent": float(doc["blunder_percent"])}
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"triangulation report lacks a figure ({e})", path, field=str(e)) from None

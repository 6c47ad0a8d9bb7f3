"""Results of the ``aerotri`` stage in Blender: the adjusted tie points as a point cloud, and the report's figures.

* :func:`build_tie_points`: ``aerotri/ties.npz`` (:class:`core.model.TiePoints`) as a vertex-only mesh "Tie points"
  in the "Tie points" collection, at ``world - origin`` (:mod:`.georef`), with an INT point attribute ``rays``
  (observations per track not rejected as blunders) and a ``Col`` colour attribute from that count
  (:data:`RAY_RAMP`: 2 rays blue ... 12 and more red), drawn as points like the dense cloud. Tracks without an
  intersected position are left out; above :data:`MAX_TIE_POINTS` a fixed random subset is shown.
* :func:`report_summary`: the key figures of ``aerotri/report.json`` for the Triangulation panel.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..core.model import TiePoints
from ..core.pipeline import Workspace
from . import georef
from .layers import mesh_from_arrays, point_display
from .scene_tree import layer_collection

TIES_FILE = "aerotri/ties.npz"
REPORT_FILE = "aerotri/report.json"
REPORT_HTML = "aerotri/report.html"
MAX_TIE_POINTS = 300_000

RAY_RAMP = ((2, (0.10, 0.25, 0.90)), (3, (0.00, 0.75, 0.90)), (5, (0.10, 0.80, 0.20)), (8, (0.95, 0.85, 0.10)),
            (12, (0.90, 0.15, 0.10)))
"""Ray count -> sRGB colour stops (linear in between, clamped outside)."""


def ray_colours(rays: np.ndarray) -> np.ndarray:
    """sRGB colours ``(n, 3)`` float in [0, 1] of ray counts ``(n,)`` along :data:`RAY_RAMP`."""
    stops = np.array([s for s, _ in RAY_RAMP], np.float64)
    rgb = np.array([c for _, c in RAY_RAMP], np.float64)
    r = np.asarray(rays, np.float64)
    return np.stack([np.interp(r, stops, rgb[:, k]) for k in range(3)], axis=1)


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
    rgba = np.concatenate([ray_colours(rays[keep]), np.ones((len(keep), 1))], axis=1)
    mesh.color_attributes.new("Col", "BYTE_COLOR", "POINT").data.foreach_set(
        "color_srgb", rgba.astype(np.float32).ravel())
    obj = bpy.data.objects.new("Tie points", mesh)
    obj["oc_tie_points"] = n_valid
    coll.objects.link(obj)
    if len(xyz) > 1:
        extent = np.ptp(xyz[:, :2], axis=0)
        spacing = math.sqrt(max(float(extent[0] * extent[1]), 1e-6) / len(xyz))
        point_display(obj, radius=max(0.05, 0.3 * spacing))
    shown = f"{len(keep)} of {n_valid}" if len(keep) < n_valid else f"{n_valid}"
    median = int(np.median(rays[keep])) if len(keep) else 0
    return f"{shown} tie points shown (median {median} rays)"


def report_summary(path: Path) -> dict:
    """Key figures of ``aerotri/report.json``: mode, connection, images, sigma0 (unitless and px), check point
    RMS XY / Z (m) and their count, rejected observations (%). Raises :class:`InputError` naming the file."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError:
        raise InputError("no triangulation report (run the 'aerotri' stage)", path) from None
    except json.JSONDecodeError as e:
        raise InputError(f"not valid JSON ({e.msg})", path, line=e.lineno) from None
    try:
        check = doc["check_points"]["all"]
        return {"mode": str(doc["mode"]), "connection": str(doc.get("connection") or ""),
                "images": int(doc["images"]), "sigma0": float(doc["sigma0"]), "sigma0_px": float(doc["sigma0_px"]),
                "check_n": int(check["n"]), "check_rms_xy_m": check["rms_xy_m"], "check_rms_z_m": check["rms_z_m"],
                "blunder_percent": float(doc["blunder_percent"])}
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"triangulation report lacks a figure ({e})", path, field=str(e)) from None

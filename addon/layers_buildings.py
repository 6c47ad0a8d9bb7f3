"""Builder of the ``buildings`` stage: one mesh object per LoD2 building, coloured by surface type.

Reads ``buildings/buildings.json`` with the core loader (:func:`core.buildings.model.load_buildings`) and creates,
in the "Buildings" collection, one mesh per building whose polygons are the model's planar polygons (n-gons, not
triangles) over its shared vertices, placed at ``world - origin`` through :mod:`.georef`. Every polygon gets the
material of its surface type (:data:`KIND_MATERIAL`: roof, wall, ground, overhang underside; the overhang's roof
extension and fascia share the roof and wall materials as in CityGML). Custom properties on each object: the
building id, the reconstruction path (``2d`` / ``volumetric``), the status (closed solid or the solid problem),
the reason of the path, and the building's attributes as exported (:func:`core.buildings.attributes
.building_attributes`: ground and roof heights, areas, volume, roof type, each as ``oc_<name>``).

The builder also fills the Buildings panel's list (``Scene.oblique_city.building_list``, :func:`fill_building_list`)
from ``buildings/report.json`` and the models: one item per building, failures included with their reason;
:func:`select_building` selects (and in a 3D viewport frames) one building's object.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

import numpy as np

from ..core.buildings.attributes import building_attributes
from ..core.buildings.model import BuildingModel, load_buildings
from ..core.pipeline import Workspace
from . import georef
from .layers import _material
from .scene_tree import layer_collection

if TYPE_CHECKING:
    import bpy

BUILDINGS_FILE = "buildings/buildings.json"
REPORT_FILE = "buildings/report.json"

MATERIALS: dict[str, tuple[float, float, float]] = {
    "Oblique City roof": (0.60, 0.12, 0.08),
    "Oblique City wall": (0.85, 0.82, 0.74),
    "Oblique City ground": (0.25, 0.25, 0.25),
    "Oblique City overhang underside": (0.15, 0.35, 0.70),
}
"""Material name -> linear RGB base colour."""

KIND_MATERIAL = {"roof": "Oblique City roof", "overhang_roof": "Oblique City roof",
                 "wall": "Oblique City wall", "overhang_fascia": "Oblique City wall",
                 "ground": "Oblique City ground", "overhang_underside": "Oblique City overhang underside"}
"""Surface kind (``core.buildings.model.SURFACE_KINDS``) -> material name."""


def surface_materials() -> list:
    """The four surface materials (created once, reused), in :data:`MATERIALS` order."""
    out = []
    for name, rgb in MATERIALS.items():
        mat, bsdf = _material(name)
        bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
        mat.diffuse_color = (*rgb, 1.0)  # the solid viewport colour
        out.append(mat)
    return out


def building_status(b: BuildingModel) -> str:
    """``closed solid``, or ``open: <problem>`` from the stage's solid check."""
    if b.info.get("closed"):
        return "closed solid"
    return f"open: {b.info.get('solid_problem') or 'not checked'}"


def building_mesh(scene, b: BuildingModel, materials: list):
    """A mesh of one building: vertices at ``world - origin``, one polygon per surface ring, material per kind."""
    import bpy

    names = list(MATERIALS)
    mesh = bpy.data.meshes.new(b.id)
    rings = [s.ring for s in b.surfaces]
    loops = np.fromiter((i for r in rings for i in r), np.int32)
    sizes = np.array([len(r) for r in rings], np.int32)
    mesh.vertices.add(len(b.vertices))
    mesh.vertices.foreach_set("co", georef.world_to_local(scene, b.vertices).astype(np.float32).ravel())
    mesh.loops.add(len(loops))
    mesh.loops.foreach_set("vertex_index", loops)
    mesh.polygons.add(len(rings))
    mesh.polygons.foreach_set("loop_start", (np.cumsum(sizes) - sizes).astype(np.int32))
    for mat in materials:
        mesh.materials.append(mat)
    mesh.polygons.foreach_set("material_index",
                              np.array([names.index(KIND_MATERIAL[s.kind]) for s in b.surfaces], np.int32))
    mesh.polygons.foreach_set("use_smooth", np.zeros(len(rings), bool))  # planar faces: flat shading
    mesh.update()
    return mesh


def build_buildings(scene, ws: Workspace) -> str:
    """Builder of the ``buildings`` stage: one object per building in the "Buildings" collection."""
    import bpy

    buildings, crs = load_buildings(ws.path(BUILDINGS_FILE))
    xyz = np.concatenate([b.vertices for b in buildings]) if buildings else np.zeros((0, 3))
    georef.ensure_georef(scene, crs or ws.crs, xyz)
    coll = layer_collection(scene, "buildings", "Buildings")
    materials = surface_materials()
    paths: dict[str, int] = {}
    closed = 0
    for b in buildings:
        obj = bpy.data.objects.new(b.id, building_mesh(scene, b, materials))
        obj["oc_building_id"] = b.id
        obj["oc_path"] = b.path
        obj["oc_status"] = building_status(b)
        obj["oc_reason"] = b.reason
        for key, value in building_attributes(b).items():
            obj[f"oc_{key}"] = value
        coll.objects.link(obj)
        paths[b.path] = paths.get(b.path, 0) + 1
        closed += bool(b.info.get("closed"))
    fill_building_list(scene, ws, buildings)
    by_path = ", ".join(f"{p} {n}" for p, n in sorted(paths.items()))
    return f"{len(buildings)} buildings ({by_path}), {closed} closed solids" if buildings else "0 buildings"


def fill_building_list(scene, ws: Workspace, buildings: list[BuildingModel] | None = None) -> int:
    """Fill ``scene.oblique_city.building_list`` from ``buildings/report.json`` (path, closed solid, solid
    problem, seconds, dormers; failures with their reason) and the models (``buildings``, else ``buildings.json``) for
    the surface counts; models the report does not list (or all, without a readable report) are added from the
    models alone. The active index is reset (nothing selected). Returns the number of items."""
    if buildings is None:
        buildings = load_buildings(ws.path(BUILDINGS_FILE))[0] if ws.path(BUILDINGS_FILE).exists() else []
    report_path = ws.path(REPORT_FILE)
    try:  # an unreadable report leaves the models' own status (the panel shows the report's error)
        report = json.loads(report_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        report = {}
    models = {b.id: b for b in buildings}
    rows = [dict(r) for r in report.get("buildings", [])]
    listed = {r.get("id") for r in rows}
    rows += [{"id": b.id, "path": b.path, "closed": b.info.get("closed"), "solid_problem": b.info.get("solid_problem"),
              "seconds": b.info.get("seconds"), "dormers": b.info.get("dormers", [])}
             for b in buildings if b.id not in listed]
    settings = scene.oblique_city
    settings.building_index = -1
    items = settings.building_list
    items.clear()
    for r in rows:
        item = items.add()
        item.name, item.path, item.closed = str(r["id"]), str(r.get("path") or ""), bool(r.get("closed"))
        item.status = "closed solid" if item.closed else f"open: {r.get('solid_problem') or 'not checked'}"
        item.seconds = float(r["seconds"]) if isinstance(r.get("seconds"), (int, float)) else 0.0
        item.surfaces = len(models[item.name].surfaces) if item.name in models else 0
        if item.name in models:
            a = building_attributes(models[item.name])
            item.roof_type, item.volume = str(a["roof_type"]), float(a["volume"])
            item.height_70p = float(a["roof_height_70p"]) - float(a["ground_height"])
        item.dormers = len(r.get("dormers") or [])
    for f in report.get("failures", []):
        item = items.add()
        item.name, item.failed, item.status = str(f["id"]), True, f"failed: {f.get('reason') or '?'}"
    return len(items)


def building_object(scene, bid: str) -> bpy.types.Object | None:
    """The scene's object of building ``bid`` (found by its ``oc_building_id``), or None."""
    return next((o for o in scene.objects if o.get("oc_building_id") == bid and o.type == "MESH"), None)


def select_building(context, scene, bid: str) -> bpy.types.Object | None:
    """Make the object of building ``bid`` the only selected and the active object of the view layer, and frame
    it in every 3D viewport of the window; returns the object, or None when the building has none (a failure, or
    the layer is not built). Without a view layer in the context (background mode) the scene's first is used;
    without a window nothing is framed."""
    import bpy

    obj = building_object(scene, bid)
    view_layer = getattr(context, "view_layer", None) or (scene.view_layers[0] if scene.view_layers else None)
    if obj is None or view_layer is None:
        return None
    try:  # select_set first: it brings the view layer up to date with collections linked since its last sync
        obj.select_set(True, view_layer=view_layer)
    except RuntimeError:  # the object is not in this view layer (its collection is excluded)
        return None
    for o in list(view_layer.objects.selected):
        if o != obj:
            o.select_set(False, view_layer=view_layer)
    view_layer.objects.active = obj
    window = getattr(context, "window", None)
    for area in window.screen.areas if window is not None and window.screen is not None else ():
        region = next((r for r in area.regions if r.type == "WINDOW"), None)
        if area.type == "VIEW_3D" and region is not None:
            with context.temp_override(window=window, area=area, region=region):
                bpy.ops.view3d.view_selected()
    return obj

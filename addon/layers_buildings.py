"""Builder of the ``buildings`` stage: one mesh object per LoD2 building, coloured by surface type.

Reads ``buildings/buildings.json`` with the core loader (:func:`core.buildings.model.load_buildings`) and creates,
in the "Buildings" collection, one mesh per building whose polygons are the model's planar polygons (n-gons, not
triangles) over its shared vertices, placed at ``world - origin`` through :mod:`.georef`. Every polygon gets the
material of its surface type (:data:`KIND_MATERIAL`: roof, wall, ground, overhang underside; the overhang's roof
extension and fascia share the roof and wall materials as in CityGML). Custom properties on each object: the
building id, the reconstruction path (``2d`` / ``volumetric``), the status (closed solid or the solid problem)
and the reason of the path.
"""

from __future__ import annotations

import numpy as np

from ..core.buildings.model import BuildingModel, load_buildings
from ..core.pipeline import Workspace
from . import georef
from .layers import _material
from .scene_tree import layer_collection

BUILDINGS_FILE = "buildings/buildings.json"

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
        coll.objects.link(obj)
        paths[b.path] = paths.get(b.path, 0) + 1
        closed += bool(b.info.get("closed"))
    by_path = ", ".join(f"{p} {n}" for p, n in sorted(paths.items()))
    return f"{len(buildings)} buildings ({by_path}), {closed} closed solids" if buildings else "0 buildings"

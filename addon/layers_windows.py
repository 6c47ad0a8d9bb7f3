"""Builder of the ``windows`` stage: one mesh object per building holding its detected windows as quads.

Reads ``windows/windows.json`` with the core loader (:func:`core.windows.store.load_windows`) and creates, in the
"Windows" collection, one mesh object per building with windows, named ``"<building id> windows"``: one quad per
window over its four corners (bottom-left, bottom-right, top-right, top-left, so the normal points out of the wall),
at ``world - origin`` through :mod:`.georef`, with a dark glass material. The mesh holds the exact corners, which lie
on the wall plane; a Displace modifier lifts the displayed quads :data:`OFFSET_M` out of the wall so they do not
flicker against the wall polygon. Each window's score is a face attribute (:data:`SCORE_ATTRIBUTE`). An object is
parented to its building's object when that exists (both sit at the identity transform, so nothing moves) and
carries the building id and its window count as custom properties.

:func:`windows_summary` gives the panel's figures.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.pipeline import Workspace
from ..core.windows.store import Window, load_windows
from . import georef
from .layers import _material
from .scene_tree import layer_collection

WINDOWS_FILE = "windows/windows.json"
MATERIAL = "Oblique City window glass"
GLASS_RGB = (0.02, 0.03, 0.05)
"""Linear RGB base colour of the glass material."""
OFFSET_M = 0.02
"""How far the displayed window quads stand out of the wall plane (metres, along the window normal)."""
SCORE_ATTRIBUTE = "oc_score"


def glass_material():
    """The dark glass material of all windows (created once, reused)."""
    mat, bsdf = _material(MATERIAL)
    bsdf.inputs["Base Color"].default_value = (*GLASS_RGB, 1.0)
    bsdf.inputs["Roughness"].default_value = 0.05
    mat.diffuse_color = (*GLASS_RGB, 1.0)  # the solid viewport colour
    mat.roughness = 0.05
    return mat


def windows_mesh(scene, name: str, windows: list[Window], material):
    """A mesh of quads, one per window: vertices ``4 i .. 4 i + 3`` are window ``i``'s corners at
    ``world - origin``, with the window's score as a face attribute."""
    import bpy

    mesh = bpy.data.meshes.new(name)
    corners = np.concatenate([w.corners for w in windows])
    n = len(windows)
    mesh.vertices.add(4 * n)
    mesh.vertices.foreach_set("co", georef.world_to_local(scene, corners).astype(np.float32).ravel())
    mesh.loops.add(4 * n)
    mesh.loops.foreach_set("vertex_index", np.arange(4 * n, dtype=np.int32))
    mesh.polygons.add(n)
    mesh.polygons.foreach_set("loop_start", np.arange(0, 4 * n, 4, dtype=np.int32))
    mesh.polygons.foreach_set("use_smooth", np.zeros(n, bool))
    mesh.materials.append(material)
    score = mesh.attributes.new(SCORE_ATTRIBUTE, "FLOAT", "FACE")
    score.data.foreach_set("value", np.array([w.score for w in windows], np.float32))
    mesh.update()
    return mesh


def offset_from_wall(obj) -> None:
    """Display the quads :data:`OFFSET_M` in front of the wall (a Displace modifier along the normals; the mesh
    data keeps the exact corners)."""
    mod = obj.modifiers.new("Offset from wall", "DISPLACE")
    mod.direction, mod.mid_level, mod.strength = "NORMAL", 0.0, OFFSET_M


def build_windows(scene, ws: Workspace) -> str:
    """Builder of the ``windows`` stage: one object per building with windows in the "Windows" collection."""
    import bpy

    windows = load_windows(ws.path(WINDOWS_FILE))
    by_building: dict[str, list[Window]] = {}
    for w in windows:
        by_building.setdefault(w.building_id, []).append(w)
    if windows:
        georef.ensure_georef(scene, ws.crs, np.concatenate([w.corners for w in windows]))
    coll = layer_collection(scene, "windows", "Windows")
    material = glass_material()
    for bid, group in by_building.items():
        name = f"{bid} windows"
        obj = bpy.data.objects.new(name, windows_mesh(scene, name, group, material))
        obj["oc_building_id"] = bid
        obj["oc_window_count"] = len(group)
        offset_from_wall(obj)
        coll.objects.link(obj)
        building = bpy.data.objects.get(bid)
        if building is not None and building.get("oc_building_id") == bid:
            obj.parent = building
            obj.matrix_parent_inverse = building.matrix_world.inverted()
    return f"{len(windows)} windows on {len(by_building)} buildings"


def windows_summary(path: str | Path) -> dict:
    """The panel's figures of ``windows.json``: ``windows`` (total), ``walls`` (walls with windows), ``grid``
    (windows filled in from a facade grid) and ``buildings`` (building id -> window count, most windows first)."""
    windows = load_windows(path)
    counts: dict[str, int] = {}
    for w in windows:
        counts[w.building_id] = counts.get(w.building_id, 0) + 1
    return {"windows": len(windows), "walls": len({w.surface_id for w in windows}),
            "grid": sum(w.source == "grid" for w in windows),
            "buildings": dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))}

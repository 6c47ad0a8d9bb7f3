"""The scene georeference: the one place where world coordinates become Blender coordinates and back.

Blender stores object locations, matrices and vertices in float32: at UTM northings of 5 400 000 m a float32 step
is 0.5 m. So the scene carries a float64 *origin* and its CRS, and every Blender object sits at
``xyz_local = xyz_world - origin``. Within 8 km of the origin float32 keeps better than 0.5 mm.

Storage: two scene custom properties (ID properties), ``oblique_city_crs`` (a string: ``EPSG:nnnn`` or WKT) and
``oblique_city_origin``, an ID property array of three doubles (typecode ``'d'``). ID properties keep float64;
``bpy.props.FloatProperty`` would not, so the origin is deliberately not a registered property.

Every import (builders) and export (reading Blender objects back into world coordinates) goes through the
functions of this module; nothing else adds or subtracts the origin.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import WorkspaceError

CRS_KEY = "oblique_city_crs"
ORIGIN_KEY = "oblique_city_origin"


def has_georef(scene) -> bool:
    """Whether the scene already carries a CRS and an origin."""
    return CRS_KEY in scene and ORIGIN_KEY in scene


def get_crs(scene) -> str | None:
    """The scene's CRS, or None when the scene is not georeferenced."""
    return str(scene[CRS_KEY]) if CRS_KEY in scene else None


def get_origin(scene) -> np.ndarray:
    """The scene's float64 origin, (3,). Raises :class:`WorkspaceError` when the scene has none."""
    if ORIGIN_KEY not in scene:
        raise WorkspaceError(f"scene '{scene.name}' has no georeference (import a block first)")
    origin = np.array(list(scene[ORIGIN_KEY]), dtype=np.float64)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise WorkspaceError(f"scene '{scene.name}': custom property '{ORIGIN_KEY}' is not three finite numbers")
    return origin


def set_georef(scene, crs: str, origin: np.ndarray) -> None:
    """Store the CRS and the float64 origin on the scene (replacing any previous georeference)."""
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    scene[CRS_KEY] = str(crs)
    scene[ORIGIN_KEY] = [float(v) for v in origin]


def choose_origin(xyz_world: np.ndarray) -> np.ndarray:
    """A round origin near the data: the centre of the bounding box in X and Y rounded to whole metres, Z = 0.

    ``xyz_world : (n, 3) float64`` (NaN rows ignored). Whole metres keep local coordinates easy to read and make the
    origin exactly representable; Z = 0 keeps heights above the datum visible as they are.
    """
    xyz = np.asarray(xyz_world, dtype=np.float64).reshape(-1, 3)
    xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
    if len(xyz) == 0:
        return np.zeros(3)
    centre = (xyz.min(axis=0) + xyz.max(axis=0)) / 2.0
    return np.array([np.round(centre[0]), np.round(centre[1]), 0.0])


def ensure_georef(scene, crs: str, xyz_world: np.ndarray) -> np.ndarray:
    """Use the scene's georeference, or set one for data in ``crs`` around ``xyz_world : (n, 3)``.

    Raises :class:`WorkspaceError` when the scene is already in another CRS (mixing CRSs in one scene would put
    objects in the wrong place silently).
    """
    from ..core.geometry.crs import normalize_crs

    current = get_crs(scene)
    if current is not None and ORIGIN_KEY in scene:
        if normalize_crs(current) != normalize_crs(crs):
            raise WorkspaceError(f"scene '{scene.name}' is in {current}, the data is in {crs}: use a new scene "
                                 "or reproject the workspace")
        return get_origin(scene)
    origin = choose_origin(xyz_world)
    set_georef(scene, crs, origin)
    return origin


def world_to_local(scene, xyz_world: np.ndarray) -> np.ndarray:
    """World coordinates ``(n, 3)`` or ``(3,)`` float64 to scene-local coordinates (same shape, float64)."""
    return np.asarray(xyz_world, dtype=np.float64) - get_origin(scene)


def local_to_world(scene, xyz_local: np.ndarray) -> np.ndarray:
    """Scene-local coordinates ``(n, 3)`` or ``(3,)`` to world coordinates, float64."""
    return np.asarray(xyz_local, dtype=np.float64) + get_origin(scene)


def object_location_world(scene, obj) -> np.ndarray:
    """The world position of an object's origin (its ``matrix_world`` translation, current once the depsgraph
    has been evaluated), (3,) float64."""
    return local_to_world(scene, np.array(obj.matrix_world.translation, dtype=np.float64))


def mesh_vertices_world(scene, obj) -> np.ndarray:
    """World coordinates of a mesh object's vertices, ``(n, 3)`` float64 (object transform applied in float64)."""
    mesh = obj.data
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    m = np.array(obj.matrix_world, dtype=np.float64)
    xyz_local = co.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3]
    return local_to_world(scene, xyz_local)

"""3D Tiles 1.1 export: ``tileset.json`` and glTF 2.0 binary tiles (``.glb``) of the buildings, for web globes and
viewers (CesiumJS, iTwin.js, deck.gl) that stream city models.

The buildings are grouped into square tiles of ``tile_size`` metres (from the south-west corner of their extent) by
the centre of their footprint, each a child of one root tile whose ``transform`` places a local Cartesian frame on
the earth: its origin on the ground at the centre of the buildings, its axes those of the project CRS there (east
and north of the grid, up), in geocentric coordinates (EPSG:4978 for WGS 84 datums). Every vertex is transformed
exactly (pyproj, the project's heights taken as ellipsoidal heights, as the project CRS has no other vertical
reference; ``height_offset`` adds the geoid undulation to orthometric heights) to geocentric coordinates and then
rotated into that frame, so the tiles carry the true geometry rather than the projection's distortion. glTF is y-up:
positions are written as ``(x, z, -y)`` of the frame, which the 3D Tiles runtime turns back to z-up.

Each tile's content has one mesh primitive per atlas page (the ``texture`` stage's pages embedded as PNG, UVs with
``v`` down as glTF wants) and per surface kind without texture (the colours of the OBJ export), flat-shaded (each
surface has its own vertices), and the detected windows when given, lifted :data:`WINDOW_LIFT_M` off their wall.
Every tile comes in two levels, refined by replacement: the LoD 1.2 blocks (``tile_i_j_lod12.glb``: the footprints
extruded to the 70th percentile roof height, untextured) with the largest height difference between a block and its
roof as geometric error, and the textured LoD2 models (``tile_i_j.glb``, geometric error 0), so a viewer streams
blocks from afar and the models close by. Bounding volumes are boxes in the frame; the root's geometric error is its
box's diagonal. Each tile has its own ``transform``, a shift to its centre in the root frame, so its float32 glTF
positions stay within a tile's size (0.03 mm steps at 250 m).
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..buildings.attributes import building_attributes, lod12_block
from ..buildings.model import BuildingModel, Surface, ring_normal, triangulate_ring
from ..errors import ComputationError
from ..geometry.crs import crs_transformer, geocentric_crs, grid_rotations, parse_crs
from ..pipeline.atomic import write_bytes, write_text
from .obj import KIND_COLOURS, WINDOW_COLOUR
from .textures import textured

WINDOW_LIFT_M = 0.02
"""Windows stand this far in front of their wall in the tiles (coplanar faces would flicker in a viewer)."""

GLTF_FROM_LOCAL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""glTF (y-up) from the tile frame (z-up): ``(x, y, z) -> (x, z, -y)``."""


def local_frame(crs: str, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tile frame at ``origin (3,)`` (project CRS): its rotation ``local_from_geocentric (3, 3)`` and its
    origin in geocentric coordinates ``(3,)``."""
    c = parse_crs(crs)
    geo = geocentric_crs(c)
    o = crs_transformer(c, geo)(np.asarray(origin, np.float64)[None])
    return grid_rotations(o, crs_transformer(geo, c))[0], o[0]


def to_local(crs: str, xyz: np.ndarray, rotation: np.ndarray, origin_geo: np.ndarray) -> np.ndarray:
    """Project CRS points ``xyz (n, 3)`` in the tile frame ``(n, 3)`` (exact, through geocentric coordinates)."""
    c = parse_crs(crs)
    return (crs_transformer(c, geocentric_crs(c))(xyz) - origin_geo) @ rotation.T


def _primitives(buildings, textures, windows) -> dict[str, tuple[list, list, list]]:
    """Material key -> (world positions, UVs or None, triangles) per surface, before the frame change."""
    groups: dict[str, tuple[list, list, list]] = {}
    for b in buildings:
        for s in b.surfaces:
            ring = list(s.ring)
            pos = {v: k for k, v in enumerate(ring)}
            tris = np.array([[pos[i] for i in t] for t in triangulate_ring(b.vertices, s.ring)], np.int64)
            if textured(textures, s):
                st = textures.surfaces[s.id]
                key, uv = f"page{st.page}", st.uv  # v up, as trimesh takes it (it writes glTF's v down)
            else:
                key, uv = s.kind, None
            g = groups.setdefault(key, ([], [], []))
            g[0].append(b.vertices[ring])
            g[1].append(uv)
            g[2].append(tris)
        for s in b.surfaces:
            wins = (windows or {}).get(s.id, []) if s.kind == "wall" else []
            out = WINDOW_LIFT_M * ring_normal(b.vertices[list(s.ring)]) if wins else None
            for w in wins:
                g = groups.setdefault("window", ([], [], []))
                g[0].append(np.asarray(w.corners, np.float64) + out)
                g[1].append(None)
                g[2].append(np.array([[0, 1, 2], [0, 2, 3]]))
    return groups


def tile_glb(buildings, crs: str, rotation: np.ndarray, origin_geo: np.ndarray, offset: np.ndarray, textures=None,
             windows: dict | None = None) -> tuple[bytes, np.ndarray, np.ndarray]:
    """The glTF binary of ``buildings`` in the tile frame moved by ``offset (3,)`` (glTF positions are float32:
    each tile keeps them small), and their bounding box there (min (3,), max (3,))."""
    import trimesh
    from PIL import Image as PILImage

    scene = trimesh.Scene()
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for key, (parts, uvs, tris) in _primitives(buildings, textures, windows).items():
        counts = np.cumsum([0] + [len(p) for p in parts])
        local = to_local(crs, np.concatenate(parts), rotation, origin_geo) - offset
        lo, hi = np.minimum(lo, local.min(0)), np.maximum(hi, local.max(0))
        faces = np.concatenate([t + counts[i] for i, t in enumerate(tris)])
        if key.startswith("page"):
            image = PILImage.open(textures.pages[int(key[4:])][0]).convert("RGB")
            material = trimesh.visual.material.PBRMaterial(name=key, baseColorTexture=image, metallicFactor=0.0,
                                                           roughnessFactor=1.0)
            visual = trimesh.visual.TextureVisuals(uv=np.concatenate(uvs), material=material)
        else:
            colour = [*{**KIND_COLOURS, **WINDOW_COLOUR}[key], 1.0]
            visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(
                name=key, baseColorFactor=colour, metallicFactor=0.0, roughnessFactor=1.0))
        scene.add_geometry(trimesh.Trimesh(vertices=local @ GLTF_FROM_LOCAL.T, faces=faces, visual=visual,
                                           process=False), geom_name=key)
    return scene.export(file_type="glb"), lo, hi


def lod12_models(buildings) -> tuple[list[BuildingModel], float]:
    """The LoD 1.2 blocks of ``buildings`` as models (:func:`..buildings.attributes.lod12_block` at the 70th
    percentile roof height) and their geometric error for the tileset: the largest height difference between a
    block's top and its building's roof (m, at least 0.5)."""
    blocks, error = [], 0.5
    for b in buildings:
        a = building_attributes(b)
        v, rings, kinds = lod12_block(b, a["roof_height_70p"])
        surfaces = [Surface(f"{b.id}_lod12_{k}", kind, tuple(r)) for k, (r, kind) in enumerate(zip(rings, kinds))]
        blocks.append(BuildingModel(b.id, v, surfaces, b.path, "LoD 1.2 block", np.asarray(b.footprint),
                                    np.zeros(len(b.footprint)), np.zeros((0, 4))))
        error = max(error, a["roof_height_max"] - a["roof_height_70p"], a["roof_height_70p"] - a["roof_height_min"])
    return blocks, float(error)


def _box(lo: np.ndarray, hi: np.ndarray) -> list[float]:
    c, h = (lo + hi) / 2.0, (hi - lo) / 2.0
    return [*c.tolist(), float(h[0]), 0.0, 0.0, 0.0, float(h[1]), 0.0, 0.0, 0.0, float(h[2])]


def write_3dtiles(folder: str | Path, buildings, crs: str, textures=None, windows: dict | None = None,
                  tile_size: float = 250.0, height_offset: float = 0.0) -> list[str]:
    """Write ``folder/tileset.json`` and one ``.glb`` per tile (see the module docstring); returns the file names
    written. ``height_offset`` (m) is added to every height before the geocentric step: the geoid undulation
    turns orthometric project heights into the ellipsoidal ones a globe places models by."""
    if not buildings:
        raise ComputationError("no buildings to write as 3D Tiles (the buildings stage found none)")
    if height_offset:
        buildings = [replace(b, vertices=b.vertices + [0.0, 0.0, height_offset]) for b in buildings]
        windows = {k: [replace(w, corners=w.corners + [0.0, 0.0, height_offset]) for w in v]
                   for k, v in (windows or {}).items()}
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    allv = np.concatenate([b.vertices for b in buildings])
    origin = np.array([*np.round((allv[:, :2].min(0) + allv[:, :2].max(0)) / 2.0), np.floor(allv[:, 2].min())])
    rotation, origin_geo = local_frame(crs, origin)
    cells: dict[tuple[int, int], list] = {}
    for b in buildings:
        c = (np.asarray(b.footprint, np.float64).mean(0) - allv[:, :2].min(0)) / tile_size
        cells.setdefault((int(c[0]), int(c[1])), []).append(b)
    children, files = [], []
    lo_all, hi_all = np.full(3, np.inf), np.full(3, -np.inf)
    for (i, j), members in sorted(cells.items()):
        name, coarse = f"tile_{i}_{j}.glb", f"tile_{i}_{j}_lod12.glb"
        corners = to_local(crs, np.concatenate([b.vertices for b in members]), rotation, origin_geo)
        offset = np.round((corners.min(0) + corners.max(0)) / 2.0)
        glb, lo, hi = tile_glb(members, crs, rotation, origin_geo, offset, textures, windows)
        blocks, error = lod12_models(members)
        glb12, lo12, hi12 = tile_glb(blocks, crs, rotation, origin_geo, offset)
        write_bytes(folder / name, glb)
        write_bytes(folder / coarse, glb12)
        files += [coarse, name]
        lo_t, hi_t = np.minimum(lo, lo12), np.maximum(hi, hi12)
        lo_all, hi_all = np.minimum(lo_all, lo_t + offset), np.maximum(hi_all, hi_t + offset)
        move = np.eye(4)
        move[:3, 3] = offset
        children.append({"transform": move.T.ravel().tolist(), "boundingVolume": {"box": _box(lo_t, hi_t)},
                         "geometricError": error, "refine": "REPLACE", "content": {"uri": coarse},
                         "children": [{"boundingVolume": {"box": _box(lo, hi)}, "geometricError": 0.0,
                                       "content": {"uri": name}}]})
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rotation.T, origin_geo
    tileset = {"asset": {"version": "1.1", "generator": "Oblique City"},
               "geometricError": float(np.linalg.norm(hi_all - lo_all)),
               "root": {"transform": transform.T.ravel().tolist(),  # column-major
                        "boundingVolume": {"box": _box(lo_all, hi_all)},
                        "geometricError": float(np.linalg.norm(hi_all - lo_all)), "refine": "ADD",
                        "children": children}}
    write_text(folder / "tileset.json", json.dumps(tileset, indent=1))
    return ["tileset.json", *files]

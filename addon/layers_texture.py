"""Builder of the ``texture`` stage: the building objects get the atlas UVs and image materials.

Reads ``texture/textures.json`` with the core loader (:func:`core.texture.atlas.load_textures`). The building
objects of the ``buildings`` builder (one polygon per surface ring, in surface order, loops in ring order) get a
UV map "Atlas" holding every textured ring vertex's UV, and the textured polygons the material of their atlas page
(an Image Texture node with the page PNG, linear filtering, extended edges, into the Principled BSDF's base
colour); untextured polygons keep their surface-type material. The buildings are built first when they are not in
the scene yet.
"""

from __future__ import annotations

import numpy as np

from ..core.buildings.model import load_buildings
from ..core.pipeline import Workspace
from . import layers_buildings
from .layers import _material

TEXTURES_FILE = "texture/textures.json"
UV_MAP = "Atlas"


def atlas_material(index: int, path: str):
    """The material of atlas page ``index`` showing the image at ``path`` (created or updated)."""
    import bpy

    mat, bsdf = _material(f"Oblique City atlas {index:03d}")
    nodes = mat.node_tree.nodes
    tex = nodes.get("Atlas") or nodes.new("ShaderNodeTexImage")
    tex.name = "Atlas"
    img = bpy.data.images.load(path, check_existing=True)
    img.reload()
    tex.image, tex.interpolation, tex.extension = img, "Linear", "EXTEND"
    mat.node_tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    mat.diffuse_color = (1.0, 1.0, 1.0, 1.0)
    return mat


def texture_mesh(mesh, surfaces, textures, page_materials: list) -> int:
    """Give one building mesh the atlas UVs and materials; returns the number of textured polygons."""
    uv_layer = mesh.uv_layers.get(UV_MAP) or mesh.uv_layers.new(name=UV_MAP)
    uv = np.zeros((len(mesh.loops), 2), np.float32)
    mat_index = np.zeros(len(mesh.polygons), np.int32)
    mesh.polygons.foreach_get("material_index", mat_index)
    slots = {m.name: i for i, m in enumerate(mesh.materials)}
    n = 0
    for poly, s in zip(mesh.polygons, surfaces, strict=True):
        st = textures.surfaces.get(s.id)
        if st is None or len(st.uv) != poly.loop_total:
            continue
        uv[poly.loop_start:poly.loop_start + poly.loop_total] = st.uv
        mat = page_materials[st.page]
        if mat.name not in slots:
            mesh.materials.append(mat)
            slots[mat.name] = len(mesh.materials) - 1
        mat_index[poly.index] = slots[mat.name]
        n += 1
    uv_layer.data.foreach_set("uv", uv.ravel())
    mesh.polygons.foreach_set("material_index", mat_index)
    mesh.update()
    return n


def build_texture(scene, ws: Workspace) -> str:
    """Builder of the ``texture`` stage: atlas UVs and materials on the building objects."""
    import bpy

    from ..core.texture.atlas import load_textures

    textures = load_textures(ws.path(TEXTURES_FILE))
    buildings, _ = load_buildings(ws.path(layers_buildings.BUILDINGS_FILE))
    if any(bpy.data.objects.get(b.id) is None for b in buildings):
        layers_buildings.build_buildings(scene, ws)
    pages = [atlas_material(i, str(p)) for i, (p, _, _) in enumerate(textures.pages)]
    n = 0
    for b in buildings:
        obj = bpy.data.objects[b.id]
        if len(obj.data.polygons) == len(b.surfaces):
            n += texture_mesh(obj.data, b.surfaces, textures, pages)
    return f"{n} textured surfaces on {len(pages)} atlas pages"

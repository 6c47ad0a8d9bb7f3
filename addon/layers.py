"""Builders of later stages' results: the dense point cloud and the DSM with the true orthophoto.

* ``dense``: ``dense/points_display.ply`` (the stage's display subset, read with :func:`core.io.pointcloud.read_ply`)
  as a mesh of vertices with a ``Col`` colour attribute (sRGB bytes) and a ``view`` attribute (index into
  ``VIEWS``), drawn as points by a Geometry Nodes modifier (Mesh to Points, radius from the point spacing) with a
  material that shows ``Col``.
* ``surface``: ``surface/dsm.tif`` as a grid mesh through the cell centres (subsampled to at most
  :data:`MAX_DSM_VERTICES`; cells without height leave holes), textured with ``surface/ortho.png`` when that image
  covers the same grid (as the surface stage writes it); ``surface/dtm.tif`` the same way as a second mesh, and
  the display subset of the classified points (``surface/points_classified_display.laz``) coloured by ASPRS class
  (:data:`CLASS_COLOURS`, the code in a ``class`` attribute), both hidden in the view layer until the user shows
  them.

Positions go through :mod:`.georef` like everything else: the float64 world coordinates are offset by the scene
origin before Blender stores them in float32.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.io.geotiff import read_geotiff
from ..core.io.pointcloud import read_las, read_ply
from ..core.pipeline import Workspace
from . import georef
from .scene_tree import layer_collection

DENSE_DISPLAY_FILE = "dense/points_display.ply"
DSM_FILE = "surface/dsm.tif"
DTM_FILE = "surface/dtm.tif"
ORTHO_FILE = "surface/ortho.png"
CLASSIFIED_DISPLAY_FILE = "surface/points_classified_display.laz"
CLASS_COLOURS = {1: (0.6, 0.6, 0.6), 2: (0.55, 0.4, 0.25), 3: (0.6, 0.85, 0.4), 4: (0.35, 0.7, 0.25),
                 5: (0.1, 0.45, 0.1), 6: (0.85, 0.3, 0.2), 7: (0.9, 0.2, 0.9)}
"""ASPRS class -> display colour (sRGB): grey unclassified, brown ground, greens vegetation (low to high), red
buildings, magenta low points; other codes grey."""
MAX_DSM_VERTICES = 1_000_000


def mesh_from_arrays(name: str, xyz_local: np.ndarray, quads: np.ndarray | None = None):
    """A mesh from vertices ``(n, 3)`` and optional quads ``(m, 4)`` (vertex indices, counter-clockwise seen from
    the side their normal points to), built with ``foreach_set`` (fast for millions of vertices)."""
    import bpy

    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(xyz_local))
    mesh.vertices.foreach_set("co", np.asarray(xyz_local, np.float32).ravel())
    if quads is not None and len(quads):
        mesh.loops.add(quads.size)
        mesh.loops.foreach_set("vertex_index", np.asarray(quads, np.int32).ravel())
        mesh.polygons.add(len(quads))
        mesh.polygons.foreach_set("loop_start", np.arange(0, quads.size, 4, dtype=np.int32))
    mesh.update()
    return mesh


def _material(name: str):
    import bpy

    mat = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender 4.x; from 5.0 every material has its node tree
        mat.use_nodes = True
    return mat, mat.node_tree.nodes.get("Principled BSDF")


def point_display(obj, radius: float) -> None:
    """Draw a vertex-only mesh as points coloured by its ``Col`` attribute (Geometry Nodes: Mesh to Points)."""
    import bpy

    mat, bsdf = _material("Oblique City points")
    attr = mat.node_tree.nodes.get("Col") or mat.node_tree.nodes.new("ShaderNodeAttribute")
    attr.name, attr.attribute_name = "Col", "Col"
    mat.node_tree.links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
    tree = bpy.data.node_groups.new("Oblique City points", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    group_in, group_out = tree.nodes.new("NodeGroupInput"), tree.nodes.new("NodeGroupOutput")
    to_points = tree.nodes.new("GeometryNodeMeshToPoints")
    to_points.inputs["Radius"].default_value = radius
    set_mat = tree.nodes.new("GeometryNodeSetMaterial")
    set_mat.inputs["Material"].default_value = mat
    tree.links.new(group_in.outputs[0], to_points.inputs["Mesh"])
    tree.links.new(to_points.outputs["Points"], set_mat.inputs["Geometry"])
    tree.links.new(set_mat.outputs["Geometry"], group_out.inputs[0])
    obj.modifiers.new("Points", "NODES").node_group = tree


def points_object(scene, coll, name: str, xyz: np.ndarray, rgb: np.ndarray, attributes: dict[str, np.ndarray]):
    """A vertex-only mesh object of points ``xyz (n, 3)`` (world) with colours ``rgb (n, 3)`` (sRGB, 0-1) in the
    ``Col`` attribute and integer point ``attributes``, drawn as points (:func:`point_display`)."""
    import bpy

    mesh = mesh_from_arrays(name, georef.world_to_local(scene, xyz))
    col = mesh.color_attributes.new("Col", "BYTE_COLOR", "POINT")
    rgba = np.concatenate([rgb, np.ones((len(xyz), 1))], axis=1)
    col.data.foreach_set("color_srgb", rgba.astype(np.float32).ravel())
    for key, values in attributes.items():
        mesh.attributes.new(key, "INT", "POINT").data.foreach_set("value", values.astype(np.int32))
    obj = bpy.data.objects.new(name, mesh)
    coll.objects.link(obj)
    if len(xyz) > 1:
        extent = np.ptp(xyz[:, :2], axis=0)
        spacing = math.sqrt(max(float(extent[0] * extent[1]), 1e-6) / len(xyz))
        point_display(obj, radius=max(0.01, 0.5 * spacing))
    return obj


def build_dense_points(scene, ws: Workspace) -> str:
    """Builder of the ``dense`` stage: the display subset of the point cloud."""
    cloud = read_ply(ws.path(DENSE_DISPLAY_FILE))
    georef.ensure_georef(scene, ws.crs, cloud.xyz)
    coll = layer_collection(scene, "dense", "Dense points")
    points_object(scene, coll, "Dense points", cloud.xyz, cloud.rgb / 255.0, {"view": cloud.view})
    return f"{len(cloud)} display points"


def hide_in_view(scene, obj) -> None:
    """Hide ``obj`` in renders and in every view layer of ``scene`` (the user shows it when wanted)."""
    obj.hide_render = True
    for layer in scene.view_layers:
        layer.update()  # the new object enters the view layer's object list
        if obj.name in layer.objects:
            obj.hide_set(True, view_layer=layer)


def grid_quads(valid: np.ndarray) -> np.ndarray:
    """Quads ``(m, 4)`` of a row-major grid of vertices whose four corners are ``valid : (rows, cols) bool``.

    Row 0 is the northern edge, so (bottom-left, bottom-right, top-right, top-left) is counter-clockwise seen from
    above: normals point up.
    """
    rows, cols = valid.shape
    idx = np.arange(rows * cols).reshape(rows, cols)
    tl, tr, bl, br = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    ok = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    return np.stack([bl[ok], br[ok], tr[ok], tl[ok]], axis=1)


def _grid_mesh(scene, name: str, raster) -> tuple[object, np.ndarray, int, int]:
    """A grid mesh through the cell centres of a height raster (subsampled to at most :data:`MAX_DSM_VERTICES`;
    cells without height leave holes). Returns the mesh, the quads ``(m, 4)`` on the subsampled grid, the grid
    width and the step."""
    rows, cols = raster.shape
    step = max(1, math.ceil(math.sqrt(rows * cols / MAX_DSM_VERTICES)))
    z = np.asarray(raster.data, np.float64)[::step, ::step]
    if raster.nodata is not None:
        z[z == raster.nodata] = np.nan
    xs, ys = raster.cell_centers()
    gx, gy = np.meshgrid(xs[::step], ys[::step])
    xyz = np.stack([gx, gy, z], axis=-1).reshape(-1, 3)
    quads = grid_quads(np.isfinite(z))
    used = np.zeros(len(xyz), bool)
    used[quads.ravel()] = True
    new_index = np.cumsum(used) - 1
    georef.ensure_georef(scene, raster.crs, xyz[used])
    mesh = mesh_from_arrays(name, georef.world_to_local(scene, xyz[used]), new_index[quads])
    return mesh, quads, z.shape[1], step


def build_surface(scene, ws: Workspace) -> str:
    """Builder of the ``surface`` stage: the DSM as a mesh, textured with the true orthophoto, and the DTM as a
    second mesh (hidden at first: the bare ground under the DSM)."""
    import bpy

    dsm = read_geotiff(ws.path(DSM_FILE))
    rows, cols = dsm.shape
    coll = layer_collection(scene, "surface", "Surface")
    mesh, quads, width, step = _grid_mesh(scene, "DSM", dsm)
    summary = f"DSM {cols}x{rows} at {dsm.cell:g} m as {len(mesh.vertices)} vertices"
    ortho_path = ws.path(ORTHO_FILE)
    if ortho_path.is_file():
        image = bpy.data.images.load(str(ortho_path), check_existing=True)
        if tuple(image.size) == (cols, rows):
            r, c = np.divmod(quads.ravel(), width)  # grid row and column of every loop's vertex
            uv = np.stack([(c * step + 0.5) / cols, 1.0 - (r * step + 0.5) / rows], axis=1)
            mesh.uv_layers.new(name="ortho").data.foreach_set("uv", uv.astype(np.float32).ravel())
            mat, bsdf = _material("Oblique City ortho")
            tex = mat.node_tree.nodes.get("Ortho") or mat.node_tree.nodes.new("ShaderNodeTexImage")
            tex.name, tex.image = "Ortho", image
            mat.node_tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
            mesh.materials.append(mat)
            summary += ", textured with the true ortho"
        else:
            summary += f", ortho {tuple(image.size)} does not match the DSM grid: not textured"
    obj = bpy.data.objects.new("DSM", mesh)
    coll.objects.link(obj)
    dtm_path = ws.path(DTM_FILE)
    if dtm_path.is_file():
        dtm_mesh, _, _, _ = _grid_mesh(scene, "DTM", read_geotiff(dtm_path))
        dtm_mesh.materials.append(_material("Oblique City DTM")[0])
        dtm = bpy.data.objects.new("DTM", dtm_mesh)
        coll.objects.link(dtm)
        hide_in_view(scene, dtm)
        summary += f", DTM as {len(dtm_mesh.vertices)} vertices (hidden)"
    classified_path = ws.path(CLASSIFIED_DISPLAY_FILE)
    if classified_path.is_file():
        cloud = read_las(classified_path)
        rgb = np.array([CLASS_COLOURS.get(int(c), CLASS_COLOURS[1]) for c in range(256)])[cloud.classification]
        hide_in_view(scene, points_object(scene, coll, "Classified points", cloud.xyz, rgb,
                                          {"class": cloud.classification}))
        summary += f", {len(cloud)} classified display points (hidden)"
    return summary

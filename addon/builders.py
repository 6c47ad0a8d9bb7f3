"""Builders: workspace results -> Blender objects, one small function per stage, in a registry.

A builder is ``builder(scene, ws) -> str``: it (re)creates the objects of one stage's results in that stage's own
collection under the scene's "Oblique City" collection (:func:`.scene_tree.layer_collection`) and returns a one-line
summary. :data:`BUILDERS` maps a stage name to its builder; ``block`` is the imported block (cameras and ground
points, also rebuilt after ``aerotri`` with the adjusted orientations, together with the adjusted tie points of
:mod:`.layers_aerotri`); :mod:`.layers_match` has the connectivity graph of ``match``, :mod:`.layers` has the dense
points and the DSM, :mod:`.layers_buildings` the buildings, :mod:`.layers_windows` the windows. Later stages add
theirs with :func:`register_builder` (buildings, textures, ...); "Build Scene from Workspace" and the end of a job
run every builder whose stage has finished, so new layers appear without touching the operators.

All positions go through :mod:`.georef` (objects at ``world - origin``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..core.errors import CityError
from ..core.geometry.views import VIEWS
from ..core.model import ImageBlock
from ..core.pipeline import Workspace
from ..core.pipeline.registry import stage_names
from ..core.pipeline.runner import is_up_to_date
from . import (
    backgrounds,
    cameras,
    georef,
    layers,
    layers_aerotri,
    layers_buildings,
    layers_match,
    layers_texture,
    layers_windows,
)
from .scene_tree import child_collection, layer_collection

Builder = Callable[..., str]
"""``builder(scene, ws) -> summary``."""

BUILDERS: dict[str, Builder] = {}
"""Stage name (or ``block``) -> builder."""

CLIP_END_M = 20000.0


def register_builder(stage: str, builder: Builder) -> None:
    """Add (or replace) the builder of ``stage``'s results."""
    BUILDERS[stage] = builder


def unregister_builder(stage: str) -> None:
    BUILDERS.pop(stage, None)


# --- the block: cameras and ground points ----------------------------------------------------------------
def view_collection(scene, view: str):
    """The camera collection of one cardinal view (under the block's collection)."""
    return child_collection(layer_collection(scene, "block", "Block", clear=False), "view:" + view,
                            f"Cameras {view}")


def build_cameras(scene, block: ImageBlock, ws_root=None) -> dict[str, object]:
    """One camera object per oriented image, in one collection per cardinal view. Returns image id -> object.

    The scene's georeference is set from the block when the scene has none (see :func:`georef.ensure_georef`).
    """
    import bpy

    centres = np.array([img.pose.C for img in block.images.values() if img.pose is not None]).reshape(-1, 3)
    gcps = np.array([g.xyz for g in block.ground_points.values() if g.xyz is not None]).reshape(-1, 3)
    georef.ensure_georef(scene, block.crs, np.concatenate([centres, gcps]))
    layer_collection(scene, "block", "Block", clear=True)
    extent = float(np.ptp(centres[:, :2], axis=0).max()) if len(centres) > 1 else 100.0
    objects: dict[str, object] = {}
    for view in VIEWS:
        ids = [i for i, img in block.images.items() if img.pose is not None and img.view == view]
        if not ids:
            continue
        coll = view_collection(scene, view)
        for image_id in ids:
            img = block.images[image_id]
            data = bpy.data.cameras.new(image_id)
            cameras.set_intrinsics(data, block.camera_of(img))
            data.clip_start = 1.0
            data.clip_end = CLIP_END_M
            data.display_size = max(1.0, extent / 60.0)
            obj = bpy.data.objects.new(image_id, data)
            obj["oc_image_id"] = image_id
            obj["oc_view"] = view
            if img.head:
                obj["oc_head"] = img.head
            cameras.set_pose(scene, obj, img.pose)
            backgrounds.set_background(data, backgrounds.background_file(ws_root, block, image_id, create=False))
            coll.objects.link(obj)
            objects[image_id] = obj
    return objects


def build_ground_points(scene, block: ImageBlock) -> dict[str, object]:
    """One empty per ground point with all three coordinates (plain axes: control, sphere: check); points known
    only in plan or only in height are left out. Name -> object."""
    import bpy

    points = [g for g in block.ground_points.values() if g.xyz is not None and np.all(np.isfinite(g.xyz))]
    if not points:
        return {}
    coll = child_collection(layer_collection(scene, "block", "Block", clear=False), "ground_points", "Ground points")
    out = {}
    for g in points:
        obj = bpy.data.objects.new(g.name, None)
        obj.empty_display_type = "PLAIN_AXES" if g.kind == "control" else "SPHERE"
        obj.empty_display_size = 2.0
        obj.location = tuple(georef.world_to_local(scene, g.xyz))
        obj["oc_ground_point"] = g.name
        obj["oc_kind"] = g.kind
        coll.objects.link(obj)
        out[g.name] = obj
    return out


def show_first_camera(scene, objects: dict[str, object]) -> None:
    """Make the first nadir camera (else the first camera) the scene camera, with matching render settings."""
    if not objects:
        return
    nadir = [o for o in objects.values() if o.get("oc_view") == "nadir"]
    cameras.apply_render_settings(scene, (nadir or list(objects.values()))[0])


def adjusted_is_current(ws: Workspace) -> bool:
    """Whether ``aerotri`` finished on the block that is imported now (a block imported after the adjustment
    makes the adjusted one stale: it is then not shown)."""
    state = ws.read_state()
    if state.get("aerotri", {}).get("status") != "done":
        return False
    try:
        return is_up_to_date(ws, "aerotri", state)
    except (CityError, ImportError):  # the stage is not registered or cannot load here
        return False


def build_block(scene, ws: Workspace) -> str:
    """Builder of the block: the adjusted orientations when aerial triangulation is up to date, else the
    imported ones."""
    block = ws.load_block(adjusted=adjusted_is_current(ws))
    objects = build_cameras(scene, block, ws.root)
    points = build_ground_points(scene, block)
    show_first_camera(scene, objects)
    views = ", ".join(f"{v} {n}" for v, n in sorted(block.summary()["views"].items()))
    return f"{len(objects)} cameras ({views}), {len(points)} ground points"


def build_aerotri(scene, ws: Workspace) -> str:
    """Builder of ``aerotri``: the block (adjusted when current, see :func:`build_block`) and the adjusted tie
    points (:func:`.layers_aerotri.build_tie_points`) when the adjustment is current. A tie point file that cannot
    be read is reported in the summary; the block's errors are raised."""
    summary = build_block(scene, ws)
    if not adjusted_is_current(ws):
        layer_collection(scene, "ties", "Tie points", clear=True)  # tie points of a stale adjustment go
        return summary
    try:
        return f"{summary}; {layers_aerotri.build_tie_points(scene, ws)}"
    except CityError as e:
        return f"{summary}; tie points not built ({str(e).splitlines()[0]})"


register_builder("block", build_block)
register_builder("match", layers_match.build_graph)
register_builder("aerotri", build_aerotri)
register_builder("dense", layers.build_dense_points)
register_builder("surface", layers.build_surface)
register_builder("buildings", layers_buildings.build_buildings)
register_builder("texture", layers_texture.build_texture)
register_builder("windows", layers_windows.build_windows)


# --- the whole scene -------------------------------------------------------------------------------------
def build_scene(scene, ws: Workspace, stages: list[str] | None = None) -> list[str]:
    """Run the builders of the block and of every finished stage (or only of ``stages``), each at most once.

    Returns the builders' summaries (``"stage: summary"``). A stage layer that cannot be built (a missing or bad
    output file) is reported as ``"stage: not built (reason)"`` and the other layers are still built; an error in
    the block itself is raised. The workspace path is remembered in the scene's settings.
    """
    state = ws.read_state()
    keys = ["block"] + stage_names() if stages is None else list(stages)
    if "aerotri" in keys and state.get("aerotri", {}).get("status") == "done":
        keys = [k for k in keys if k != "block"]  # the aerotri builder builds the block too
    done: set[int] = set()
    messages = []
    for key in keys:
        fn = BUILDERS.get(key)
        if fn is None or id(fn) in done:
            continue
        if key != "block" and state.get(key, {}).get("status") != "done":
            continue
        done.add(id(fn))
        try:
            messages.append(f"{key}: {fn(scene, ws)}")
        except CityError as e:
            if key in ("block", "aerotri"):  # the block itself (tie point errors are in the aerotri summary)
                raise
            messages.append(f"{key}: not built ({str(e).splitlines()[0]})")
    if hasattr(scene, "oblique_city"):  # the add-on's scene settings (registered by the add-on and make_blend)
        scene.oblique_city.workspace = str(ws.root)
    return messages

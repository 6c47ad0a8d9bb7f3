"""The ground point overlay of the camera view: over the image the viewport looks through, each ground point's
predicted position (a circle) and the measurement the adjustment takes (a cross: green when measured in the images
or by hand, white when imported), with its name.

:func:`overlay_points` computes the positions (testable without a window); :func:`draw` is the ``POST_PIXEL`` draw
handler of the 3D view that :func:`add_handler` installs when the add-on is registered. Positions come from the
same cache as the Ground Point Measurement panel, so drawing never reads the workspace.
"""

from __future__ import annotations

import bpy
import numpy as np

from ..addon import cameras, georef
from ..core.errors import CityError
from . import ground_point_rows, workspace_root

MEASURED_COLOUR = (0.2, 1.0, 0.3, 1.0)
IMPORTED_COLOUR = (1.0, 1.0, 1.0, 1.0)
PREDICTED_COLOUR = (1.0, 0.8, 0.1, 1.0)
MARK_PX = 7.0
"""Half size of the crosses and radius of the circles, screen pixels."""

_handle = None


def overlay_points(scene, root, image_id: str) -> list[tuple[str, str, np.ndarray]]:
    """``(name, kind, xyz_local (3,))`` to draw for the image ``image_id`` the scene camera shows: ``kind``
    ``predicted``, ``measured`` (targets or manual) or ``imported``; each position a scene-local point 100 m along the
    ray of that pixel of the original image, so that Blender's camera shows it over that pixel of the background."""
    viewed = cameras.viewed_image(scene)
    found = ground_point_rows(root, image_id)
    if viewed is None or viewed[1] != image_id or "error" in found:
        return []
    cam_obj = viewed[0]
    marks = []
    for r in found["rows"]:
        if np.all(np.isfinite(r.predicted)):
            marks.append((r.name, "predicted", r.predicted))
        if r.uv is not None:
            marks.append((r.name, "measured" if r.source in ("targets", "manual") else "imported", r.uv))
    if not marks:
        return []
    d = cameras.direction_from_pixel(scene, cam_obj, np.array([m[2] for m in marks]))
    centre = georef.world_to_local(scene, cameras.pose_of(scene, cam_obj).C)
    return [(name, kind, centre + 100.0 * dk) for (name, kind, _), dk in zip(marks, d, strict=True)]


def draw() -> None:
    """Draw handler: the marks of :func:`overlay_points` in a 3D view looking through an imported image."""
    context = bpy.context
    scene, rv3d, region = context.scene, context.region_data, context.region
    settings = getattr(scene, "oblique_city", None)
    viewed = cameras.viewed_image(scene)
    root = workspace_root(context) if settings is not None else None
    if (root is None or viewed is None or not settings.show_ground_points or rv3d is None
            or rv3d.view_perspective != "CAMERA"):
        return
    import blf
    import gpu
    from bpy_extras.view3d_utils import location_3d_to_region_2d
    from gpu_extras.batch import batch_for_shader
    from mathutils import Vector

    try:
        marks = overlay_points(scene, root, viewed[1])
    except CityError:
        return
    shader = gpu.shader.from_builtin("UNIFORM_COLOR")
    circle = MARK_PX * np.column_stack([np.cos(np.linspace(0, 2 * np.pi, 17)), np.sin(np.linspace(0, 2 * np.pi, 17))])
    for name, kind, xyz in marks:
        xy = location_3d_to_region_2d(region, rv3d, Vector(xyz))
        if xy is None:
            continue
        x, y = float(xy[0]), float(xy[1])
        if kind == "predicted":
            ring = circle + (x, y)
            coords = [tuple(p) for pair in zip(ring[:-1], ring[1:], strict=True) for p in pair]
            colour = PREDICTED_COLOUR
        else:
            coords = [(x - MARK_PX, y), (x + MARK_PX, y), (x, y - MARK_PX), (x, y + MARK_PX)]
            colour = MEASURED_COLOUR if kind == "measured" else IMPORTED_COLOUR
        shader.uniform_float("color", colour)
        batch_for_shader(shader, "LINES", {"pos": coords}).draw(shader)
        if kind != "predicted":
            blf.color(0, *colour)
            blf.position(0, x + MARK_PX + 2, y + MARK_PX + 2, 0)
            blf.draw(0, name)


def add_handler() -> None:
    """Install :func:`draw` in every 3D view (once)."""
    global _handle
    if _handle is None:
        _handle = bpy.types.SpaceView3D.draw_handler_add(draw, (), "WINDOW", "POST_PIXEL")


def remove_handler() -> None:
    """Remove the draw handler (add-on unregistered)."""
    global _handle
    if _handle is not None:
        bpy.types.SpaceView3D.draw_handler_remove(_handle, "WINDOW")
        _handle = None

"""Core cameras as Blender cameras: intrinsics, pose, render settings, and the way back.

Intrinsics (derived from Blender's view-plane computation, ``BKE_camera_params_compute_viewplane``, with
``sensor_fit='HORIZONTAL'``; checked against the core's projection in ``tests/blender``)::

    lens / sensor_width = fx / W
    pixel_aspect_y / pixel_aspect_x = fx / fy      (Blender's aspects are >= 1: the larger one carries the ratio)
    shift_x = (W/2 - (cx + 0.5)) / W
    shift_y = ((cy + 0.5) - H/2) / W * (fx / fy)

with the render resolution set to the image size W x H. The sensor width is the physical one (``W *
pixel_size_mm``) when the pixel size is known, so the lens shows the real focal length in millimetres, else 36 mm.
A pixel from ``bpy_extras.object_utils.world_to_camera_view`` ``(x, y)`` is ``(x W - 0.5, (1 - y) H - 0.5)``
(the core's origin is the centre of the top-left pixel).

Blender cameras are ideal pinholes: they have no lens distortion. A Blender camera reproduces the core's
projection *without* distortion (``core.geometry.projection.project(..., distort=False)``); the Brown coefficients
are kept as custom properties on the camera data (``oc_k1`` ... ``oc_p2``) and :mod:`.backgrounds` shows an
image undistorted to the same pinhole, so what the camera shows lines up with the scene.

Pose: omega-phi-kappa from :mod:`core.geometry.rotations` with ``rotation_mode='ZYX'`` (Blender's camera frame is
the photogrammetric one: x right, y up, z back), location = centre - scene origin (:mod:`.georef`).

Render resolution and pixel aspect are per scene, not per camera, so :func:`apply_render_settings` sets them for
the camera the user looks through (the "View Through Image" operator does it).
"""

from __future__ import annotations

import numpy as np

from ..core.geometry.rotations import FLIP_YZ, cam_from_world_to_opk, orthonormalize
from ..core.model import CameraModel, Pose
from . import georef

DEFAULT_SENSOR_MM = 36.0
INTRINSIC_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2")


def sensor_width_mm(camera: CameraModel) -> float:
    """Physical sensor width when the pixel size is known (and at least Blender's 1 mm minimum), else 36 mm."""
    if camera.pixel_size_mm is not None and camera.width * camera.pixel_size_mm >= 1.0:
        return float(camera.width * camera.pixel_size_mm)
    return DEFAULT_SENSOR_MM


def set_intrinsics(cam_data, camera: CameraModel) -> None:
    """Set a ``bpy.types.Camera`` from a core camera model; the model is also stored as ``oc_*`` custom
    properties (float64 ID properties), distortion included, so it can be read back exactly."""
    sensor = sensor_width_mm(camera)
    cam_data.type = "PERSP"
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.sensor_width = sensor
    cam_data.lens_unit = "MILLIMETERS"
    cam_data.lens = camera.fx * sensor / camera.width
    ycor = camera.fx / camera.fy
    cam_data.shift_x = (camera.width / 2.0 - (camera.cx + 0.5)) / camera.width
    cam_data.shift_y = ((camera.cy + 0.5) - camera.height / 2.0) / camera.width * ycor
    for k in INTRINSIC_KEYS:
        cam_data["oc_" + k] = float(getattr(camera, k))
    cam_data["oc_camera_id"] = camera.id


def intrinsics_of(cam_data) -> CameraModel:
    """The core camera model stored on a camera built by :func:`set_intrinsics`."""
    vals = {k: float(cam_data["oc_" + k]) for k in INTRINSIC_KEYS}
    vals["width"], vals["height"] = int(vals["width"]), int(vals["height"])
    return CameraModel(id=str(cam_data.get("oc_camera_id", cam_data.name)), **vals)


def apply_render_settings(scene, cam_obj) -> None:
    """Make ``cam_obj`` the scene camera and set the render resolution and pixel aspect to its image, so that
    Blender's projection through it equals the core's."""
    cam = intrinsics_of(cam_obj.data)
    r = scene.render
    r.resolution_x = cam.width
    r.resolution_y = cam.height
    r.resolution_percentage = 100
    ycor = cam.fx / cam.fy
    if ycor >= 1.0:
        r.pixel_aspect_x, r.pixel_aspect_y = 1.0, ycor
    else:
        r.pixel_aspect_x, r.pixel_aspect_y = 1.0 / ycor, 1.0
    scene.camera = cam_obj


def set_pose(scene, cam_obj, pose: Pose) -> None:
    """Place a camera object at ``pose`` (float64 world) relative to the scene origin."""
    omega, phi, kappa = cam_from_world_to_opk(pose.R)
    cam_obj.rotation_mode = "ZYX"
    cam_obj.rotation_euler = (omega, phi, kappa)
    cam_obj.location = tuple(georef.world_to_local(scene, pose.C))


def pose_of(scene, cam_obj) -> Pose:
    """The world pose of a camera object (inverse of :func:`set_pose`), float64, from its world matrix (which
    Blender updates when the depsgraph is evaluated: call ``view_layer.update()`` in a script that has just
    moved the object)."""
    m = np.array(cam_obj.matrix_world, dtype=np.float64)
    world_from_photo = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)
    r_cam_from_world = FLIP_YZ @ orthonormalize(world_from_photo).T
    return Pose(r_cam_from_world, georef.local_to_world(scene, m[:3, 3]))


def pixel_from_blender(scene, cam_obj, xyz_world: np.ndarray) -> np.ndarray:
    """Blender's own projection of world points ``(n, 3)`` through ``cam_obj`` into pixels ``(n, 2)``
    (core convention), via ``world_to_camera_view`` with the scene's current render settings."""
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    cam = intrinsics_of(cam_obj.data)
    xyz_local = georef.world_to_local(scene, np.atleast_2d(xyz_world))
    out = np.empty((len(xyz_local), 2))
    for i, p in enumerate(xyz_local):
        v = world_to_camera_view(scene, cam_obj, Vector(p))
        out[i] = (v.x * cam.width - 0.5, (1.0 - v.y) * cam.height - 0.5)
    return out


def pixel_from_direction(scene, cam_obj, direction: np.ndarray) -> np.ndarray:
    """The pixel ``(2,)`` (core convention, lens distortion included) of the image ``cam_obj`` shows in the direction
    ``direction (3,)`` (scene axes, from the camera: what ``view3d_utils.region_2d_to_vector_3d`` gives for a click
    in the camera view). The background Blender draws is the image undistorted to the pinhole, so the click's
    pinhole position is distorted back to the image's own pixel, where its measurements live."""
    from ..core.geometry.projection import project

    pose = pose_of(scene, cam_obj)
    d = np.asarray(direction, np.float64).reshape(3)
    uv, depth = project(intrinsics_of(cam_obj.data), pose, (pose.C + 100.0 * d / np.linalg.norm(d))[None])
    return uv[0] if depth[0] > 0 else np.full(2, np.nan)


def viewed_image(scene) -> tuple[object, str] | None:
    """The scene camera and its image id when it is a camera imported by Oblique City, else None."""
    cam = scene.camera
    if cam is None or cam.type != "CAMERA" or "oc_image_id" not in cam:
        return None
    return cam, str(cam["oc_image_id"])


def direction_from_pixel(scene, cam_obj, uv: np.ndarray) -> np.ndarray:
    """Unit directions ``(n, 3)`` (scene axes, from the camera) of pixels ``uv (n, 2)`` of the original, distorted
    image ``cam_obj`` shows (the inverse of :func:`pixel_from_direction`): where its measurements appear over the
    undistorted background Blender draws."""
    from ..core.geometry.projection import pixel_rays

    return pixel_rays(intrinsics_of(cam_obj.data), pose_of(scene, cam_obj), np.atleast_2d(uv))

"""Image files as camera backgrounds, undistorted to the Blender camera's pinhole when the lens has distortion.

Blender cameras have no lens distortion (see :mod:`.cameras`). For a camera without distortion the original image
file is the background. With distortion, the original would be off by the distortion itself (several pixels at the
corners of aerial cameras), so :func:`undistorted_image` writes a copy resampled with OpenCV to the *same*
intrinsics without distortion (``cv2.initUndistortRectifyMap(K, dist, None, K)`` + ``remap``, bilinear): pixel
``(u, v)`` of the copy shows the ray through ``(u, v)`` of the ideal pinhole, which is exactly what Blender draws.
Copies are cached in ``<workspace>/block/undistorted/`` under a name keyed by the intrinsics, and written
atomically. Building a scene uses a cached copy when there is one (else the original); "View Through Image"
creates the copy for the image it shows, so a block of thousands of images is never undistorted all at once.
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..core.model import CameraModel, ImageBlock
from ..core.pipeline.atomic import atomic_path

UNDISTORTED_DIR = "block/undistorted"


def image_path(block: ImageBlock, image_id: str, ws_root: str | Path | None = None) -> Path | None:
    """The image file of ``image_id`` if it exists: absolute paths as they are, relative ones under the block's
    ``image_root`` (itself relative to the workspace when not absolute) or the workspace. None when missing."""
    img = block.images[image_id]
    if not img.file:
        return None
    f = Path(img.file)
    if f.is_absolute():
        candidates = [f]
    else:
        roots = []
        if block.image_root:
            root = Path(block.image_root)
            roots.append(root if root.is_absolute() or ws_root is None else Path(ws_root) / root)
        if ws_root is not None:
            roots.append(Path(ws_root))
        candidates = [r / f for r in roots]
    return next((c for c in candidates if c.is_file()), None)


def _cache_name(image_id: str, camera: CameraModel, suffix: str) -> str:
    key = repr((camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
                camera.k1, camera.k2, camera.k3, camera.p1, camera.p2)).encode()
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", image_id)
    return f"{safe}-{hashlib.sha256(key).hexdigest()[:10]}{suffix}"


def cached_undistorted(ws_root: str | Path, image_id: str, camera: CameraModel, source: Path) -> Path:
    """Where the undistorted copy of ``source`` lives (it may not exist yet)."""
    suffix = source.suffix.lower() if source.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff") else ".png"
    return Path(ws_root) / UNDISTORTED_DIR / _cache_name(image_id, camera, suffix)


def undistort_array(image: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Resample an image ``(H, W[, C])`` with distortion to the same ``K`` without distortion (bilinear)."""
    import cv2

    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise InputError(f"image is {w} x {h} px, camera '{camera.id}' expects {camera.width} x {camera.height}",
                         field="width/height")
    map_x, map_y = cv2.initUndistortRectifyMap(camera.K, camera.dist_coeffs, None, camera.K, (w, h), cv2.CV_32FC1)
    return cv2.remap(image, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def undistorted_image(ws_root: str | Path, image_id: str, camera: CameraModel, source: Path) -> Path:
    """The undistorted copy of ``source`` (written once, atomically, then reused)."""
    import cv2

    out = cached_undistorted(ws_root, image_id, camera, source)
    if out.is_file() and out.stat().st_mtime >= source.stat().st_mtime:
        return out
    image = cv2.imread(str(source), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError("cannot read the image file", path=source)
    try:
        resampled = undistort_array(image, camera)
    except InputError as e:
        raise InputError(e.reason, path=source, field=e.field) from None
    with atomic_path(out) as tmp:
        if not cv2.imwrite(tmp, resampled):
            raise InputError("cannot write the undistorted copy", path=out)
    return out


def background_file(ws_root: str | Path | None, block: ImageBlock, image_id: str, create: bool) -> Path | None:
    """The file to show behind the camera of ``image_id``: the original for distortion-free cameras, else the
    undistorted copy (created when ``create``; without it the original until a copy exists). None if missing."""
    source = image_path(block, image_id, ws_root)
    if source is None:
        return None
    camera = block.camera_of(image_id)
    if not camera.has_distortion or ws_root is None:
        return source
    if create:
        return undistorted_image(ws_root, image_id, camera, source)
    cached = cached_undistorted(ws_root, image_id, camera, source)
    return cached if cached.is_file() else source


def set_background(cam_data, path: Path | None) -> None:
    """Show ``path`` behind the camera (stretched to the camera frame, which is the image's pixel grid), or clear
    the background when ``path`` is None. Blender loads the pixels only when the background is drawn."""
    import bpy

    cam_data.background_images.clear()
    cam_data.show_background_images = path is not None
    if path is None:
        if "oc_background" in cam_data:
            del cam_data["oc_background"]
        return
    bg = cam_data.background_images.new()
    bg.image = bpy.data.images.load(os.fspath(path), check_existing=True)
    bg.frame_method = "STRETCH"
    bg.alpha = 1.0
    bg.display_depth = "BACK"
    cam_data["oc_background"] = os.fspath(path)

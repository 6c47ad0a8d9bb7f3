"""Source images of a surface: which oriented images see it, and how well, per texel.

The quality of an image at a surface point is its resolution there in the worst direction,
``q = f cos(theta) / range`` (image pixels per metre of surface; ``theta`` is the angle between the surface normal
and the direction to the camera, ``f`` the focal length in pixels), times a mild preference for the image centre
(vignetting and lens quality fall towards the corners) that goes to zero over a thin band at the border, so
seams never run along an image edge. Points behind the camera, outside the image, seen from behind or at more
than the grazing limit get zero.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.projection import project
from ..io.photos import camera_bits, read_photo
from ..model.camera import CameraModel
from ..model.pose import Pose


@dataclass(frozen=True, eq=False)
class ImageSource:
    """One oriented image that can texture surfaces: id, camera, (adjusted) pose, file path and its camera's
    significant bits (:func:`..io.photos.camera_bits`)."""

    id: str
    camera: CameraModel
    pose: Pose
    path: str
    min_bits: int | None = None


def block_sources(block) -> list[ImageSource]:
    """The oriented images of an :class:`~..model.block.ImageBlock` with a file (relative paths resolved
    against ``block.image_root``)."""
    out = []
    bits = camera_bits(block, {img.camera_id for img in block.images.values() if img.pose is not None})
    for img in block.images.values():
        if img.pose is None or img.file is None:
            continue
        p = Path(img.file)
        if not p.is_absolute() and block.image_root:
            p = Path(block.image_root) / p
        out.append(ImageSource(img.id, block.cameras[img.camera_id], img.pose, str(p), bits.get(img.camera_id)))
    return out


class ImageCache:
    """Least-recently-used cache of decoded RGB images (uint8, (h, w, 3)) and their 2x pyramid levels."""

    def __init__(self, max_images: int = 32) -> None:
        self.max_images = max_images
        self._cache: OrderedDict[tuple[str, int], np.ndarray] = OrderedDict()

    def get(self, src: ImageSource, level: int = 0) -> np.ndarray:
        """The image at pyramid ``level`` (0 = full resolution)."""
        import cv2

        key = (src.id, level)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        if level == 0:
            img = read_photo(src.path, True, src.id, src.min_bits)
            if img.shape[:2] != (src.camera.height, src.camera.width):
                raise InputError(f"image '{src.id}' is {img.shape[1]}x{img.shape[0]} px, its camera says "
                                 f"{src.camera.width}x{src.camera.height}", path=src.path, field="file")
            img = np.ascontiguousarray(img[:, :, ::-1])
        else:
            img = cv2.pyrDown(self.get(src, level - 1))
        self._cache[key] = img
        while len(self._cache) > self.max_images:
            self._cache.popitem(last=False)
        return img


def image_quality(src: ImageSource, xyz: np.ndarray, normal: np.ndarray, min_cos: float = 0.15,
                  centre_weight: float = 0.25, border: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """Per-point quality of one image for surface points.

    Parameters
    ----------
    xyz : (n, 3) float64 world points; normal : (3,) outward unit normal of their plane
    min_cos : smallest accepted cosine between the normal and the direction to the camera
    centre_weight : relative quality loss at the image corner (quadratic in the radius)
    border : width of the band (fraction of the image diagonal) over which the quality falls to zero

    Returns
    -------
    quality : (n,) float64 pixels per metre in the worst direction (0 where unusable)
    uv_px : (n, 2) float64 image positions (exact projection with distortion; NaN behind the camera)
    """
    cam = src.camera
    uv, depth = project(cam, src.pose, xyz)
    to_cam = src.pose.C - xyz
    rng = np.linalg.norm(to_cam, axis=1)
    cos = (to_cam @ normal) / np.maximum(rng, 1e-9)
    q = cam.fx * np.maximum(cos, 0.0) / np.maximum(rng, 1e-9)
    half = np.array([cam.width, cam.height]) / 2.0
    with np.errstate(invalid="ignore"):
        r = np.linalg.norm((uv - (half - 0.5)) / half, axis=1) / np.sqrt(2.0)  # 1 at the corners
        edge = np.minimum.reduce([uv[:, 0] + 0.5, cam.width - 0.5 - uv[:, 0], uv[:, 1] + 0.5,
                                  cam.height - 0.5 - uv[:, 1]])
        band = border * np.hypot(cam.width, cam.height)
        inside = np.clip(edge / band, 0.0, 1.0) if band > 0 else (edge >= 0).astype(np.float64)
        w = (1.0 - centre_weight * r ** 2) * inside
    ok = (depth > 0) & (cos >= min_cos) & np.isfinite(w) & (w > 0)
    return np.where(ok, q * np.where(ok, w, 0.0), 0.0), uv


def candidate_sources(sources: list[ImageSource], ring_xyz: np.ndarray, normal: np.ndarray, max_sources: int,
                      min_cos: float = 0.15) -> list[tuple[ImageSource, float]]:
    """The best images for a surface, best first, with their quality at the best sampled point.

    The ring ``(k, 3)`` is sampled at its vertices, its centroid and the midpoints towards it; an image is a
    candidate when it sees any sample from the front, and candidates are ranked by their best sample's quality
    (occlusion is decided per texel later).
    """
    c = ring_xyz.mean(0)
    pts = np.concatenate([ring_xyz, c[None], 0.5 * (ring_xyz + c)])
    scored = []
    for src in sources:
        q, _ = image_quality(src, pts, normal, min_cos=min_cos, centre_weight=0.0, border=0.0)
        if q.max() > 0:
            scored.append((src, float(q.max())))
    scored.sort(key=lambda x: -x[1])
    return scored[:max_sources]

"""The image block: cameras, images with exterior orientation, rigs and ground points, in one CRS.

These are the in-memory objects every stage shares. Bulk observations (tie points) live in
:mod:`.tiepoints`; rasters in :mod:`.raster`.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..geometry.views import cardinal_view
from .camera import CameraModel
from .pose import Pose


@dataclass(frozen=True, eq=False)
class RigHead:
    """One head of a multi-head camera system.

    Attributes
    ----------
    name : head name (e.g. ``nadir``, ``forward``, ``left``)
    camera_id : the camera model this head uses
    sensor_from_rig : (3, 3) float64 rotation of the head in the rig (body) frame, boresight included
    lever_arm : (3,) float64 position of the head's projection centre in the rig frame, metres
    """

    name: str
    camera_id: str
    sensor_from_rig: np.ndarray
    lever_arm: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensor_from_rig", np.asarray(self.sensor_from_rig, np.float64).reshape(3, 3))
        object.__setattr__(self, "lever_arm", np.asarray(self.lever_arm, np.float64).reshape(3))

    def image_pose(self, world_from_rig: np.ndarray, rig_centre: np.ndarray) -> Pose:
        """This head's image orientation for the rig (body) at ``rig_centre (3,)`` turned by ``world_from_rig
        (3, 3)``: ``R = sensor_from_rig @ world_from_rig.T``, centre at the lever arm from the rig's."""
        return Pose(self.sensor_from_rig @ world_from_rig.T, np.asarray(rig_centre) + world_from_rig @ self.lever_arm)

    def relative_to(self, ref: RigHead) -> tuple[np.ndarray, np.ndarray]:
        """This head's mounting seen from head ``ref``: the rotation ``(3, 3)`` with which the two images of one
        exposure relate (``R_self = rotation @ R_ref``, cam_from_world) and this head's centre in ``ref``'s camera
        frame ``(3,)``."""
        return (self.sensor_from_rig @ ref.sensor_from_rig.T,
                ref.sensor_from_rig @ (self.lever_arm - ref.lever_arm))


@dataclass(frozen=True, eq=False)
class Rig:
    """A camera system: heads fixed to one body, exposed together."""

    name: str
    heads: tuple[RigHead, ...]

    def head(self, name: str) -> RigHead:
        for h in self.heads:
            if h.name == name:
                return h
        raise KeyError(name)


@dataclass(eq=False)
class Image:
    """One oriented image.

    Attributes
    ----------
    id : image name, unique in the block
    camera_id : key into ``ImageBlock.cameras``
    file : image file path (relative to the block's ``image_root`` or absolute), or None
    head : name of the rig head that took it, if any
    exposure : id shared by the images of one rig exposure, if any
    time : time of the exposure, seconds (GNSS time, any epoch), if known
    pose_approx : approximate exterior orientation (GNSS/IMU or imported), or None
    pose_adjusted : orientation after aerial triangulation, or None
    sigma_position : (3,) prior standard deviation of the centre, metres (X, Y, Z), or None
    sigma_attitude : (3,) prior standard deviation of small rotations about the world's X, Y, Z axes, radians, or
        None (formats giving the angles' sigmas are converted, see ``geometry.rotations.world_axis_sigmas``)
    """

    id: str
    camera_id: str
    file: str | None = None
    head: str | None = None
    exposure: str | None = None
    time: float | None = None
    pose_approx: Pose | None = None
    pose_adjusted: Pose | None = None
    sigma_position: np.ndarray | None = None
    sigma_attitude: np.ndarray | None = None

    @property
    def pose(self) -> Pose | None:
        """The best orientation known: adjusted if available, else approximate."""
        return self.pose_adjusted if self.pose_adjusted is not None else self.pose_approx

    @property
    def view(self) -> str | None:
        """Cardinal view (``nadir``, ``north``, ``east``, ``south``, ``west``) from the actual orientation."""
        p = self.pose
        return None if p is None else cardinal_view(p.R)


@dataclass(eq=False)
class GroundPoint:
    """A ground control or check point with its image measurements.

    Attributes
    ----------
    name : point name, unique in the block
    xyz : (3,) float64 world coordinates, or None for a point only measured in images
    sigma : (3,) standard deviation of X, Y, Z in metres
    kind : ``control`` (used in the adjustment) or ``check`` (measured, never used, reported separately)
    observations : image id -> (2,) pixel position (OpenCV origin: centre of the top-left pixel)
    sigma_px : standard deviation of the image measurements, pixels
    """

    name: str
    xyz: np.ndarray | None
    sigma: np.ndarray = field(default_factory=lambda: np.full(3, 0.02))
    kind: str = "control"
    observations: dict[str, np.ndarray] = field(default_factory=dict)
    sigma_px: float = 0.5

    KINDS = ("control", "check")

    def __post_init__(self) -> None:
        if self.kind not in self.KINDS:
            raise InputError(f"ground point '{self.name}' has kind '{self.kind}', expected control or check",
                             field="kind")
        if self.xyz is not None:
            self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(3)
        self.sigma = np.asarray(self.sigma, dtype=np.float64).reshape(3)


@dataclass(eq=False)
class ImageBlock:
    """A photogrammetric block in one coordinate reference system.

    Attributes
    ----------
    crs : the world CRS as ``EPSG:nnnn`` or WKT (see :mod:`..geometry.crs`); metres, Z up
    cameras : camera id -> model
    images : image id -> image, in acquisition order
    rigs : rig name -> rig
    ground_points : name -> point
    image_root : folder the image ``file`` paths are relative to, or None
    """

    crs: str
    cameras: dict[str, CameraModel] = field(default_factory=dict)
    images: dict[str, Image] = field(default_factory=dict)
    rigs: dict[str, Rig] = field(default_factory=dict)
    ground_points: dict[str, GroundPoint] = field(default_factory=dict)
    image_root: str | None = None

    def add_camera(self, camera: CameraModel) -> None:
        if camera.id in self.cameras:
            raise InputError(f"duplicate camera id '{camera.id}'", field="camera")
        self.cameras[camera.id] = camera

    def add_image(self, image: Image) -> None:
        if image.id in self.images:
            raise InputError(f"duplicate image id '{image.id}'", field="image")
        if image.camera_id not in self.cameras:
            raise InputError(f"image '{image.id}' refers to unknown camera '{image.camera_id}'", field="camera")
        self.images[image.id] = image

    def add_ground_point(self, point: GroundPoint) -> None:
        if point.name in self.ground_points:
            raise InputError(f"duplicate ground point '{point.name}'", field="name")
        self.ground_points[point.name] = point

    def camera_of(self, image: Image | str) -> CameraModel:
        img = self.images[image] if isinstance(image, str) else image
        return self.cameras[img.camera_id]

    def images_by_view(self) -> dict[str, list[str]]:
        """View name -> image ids, for the images that have an orientation."""
        out: dict[str, list[str]] = {}
        for img in self.images.values():
            v = img.view
            if v is not None:
                out.setdefault(v, []).append(img.id)
        return out

    def summary(self) -> dict:
        """Counts for display: images per view, cameras, ground points by kind, CRS."""
        views = Counter(img.view or "unoriented" for img in self.images.values())
        kinds = Counter(p.kind for p in self.ground_points.values())
        return {
            "crs": self.crs,
            "images": len(self.images),
            "views": dict(sorted(views.items())),
            "cameras": len(self.cameras),
            "rigs": len(self.rigs),
            "exposures": len({img.exposure for img in self.images.values() if img.exposure is not None}),
            "control_points": kinds.get("control", 0),
            "check_points": kinds.get("check", 0),
            "adjusted": sum(img.pose_adjusted is not None for img in self.images.values()),
        }

    def centers(self, adjusted: bool = False) -> np.ndarray:
        """Projection centres ``(n, 3)`` in image order (approximate or adjusted, NaN where missing)."""
        out = np.full((len(self.images), 3), np.nan)
        for i, img in enumerate(self.images.values()):
            p = img.pose_adjusted if adjusted else img.pose_approx
            if p is not None:
                out[i] = p.C
        return out

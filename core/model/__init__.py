"""Data model shared by every stage: cameras, poses, images, rigs, ground points, blocks, tie points, rasters."""

from .block import GroundPoint, Image, ImageBlock, Rig, RigHead
from .camera import CameraModel
from .pose import Pose
from .raster import Raster
from .tiepoints import TiePoints

__all__ = ["CameraModel", "GroundPoint", "Image", "ImageBlock", "Pose", "Raster", "Rig", "RigHead", "TiePoints"]

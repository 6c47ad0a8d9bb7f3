"""Camera systems: multi-head aerial cameras as :class:`~..model.Rig` plus one :class:`~..model.CameraModel` per
head.

Presets
-------
* ``penta``: a Maltese-cross system after the Leica RCD30 Penta (nadir 50 mm, four obliques 80 mm tilted 45 deg
  forward, right, backward, left; 10320 x 7752 px of 5.2 um), scaled down to 1200 x 900 px with the pixel pitch
  scaled up so the fields of view stay those of the real system.
* ``three-head``: nadir (50 mm) plus left and right obliques (70 mm) tilted 36 deg, same scaled sensor.
* a custom system: :func:`system_from_dict` with heads given as tilt, azimuth, focal length, pixel size, image
  size, principal point offset and Brown distortion.

Frames: the rig (body) frame is the navigation body frame of :mod:`..geometry.rotations` (x forward, y right,
z down). A head with tilt ``t`` and azimuth ``a`` (clockwise from forward in the body's horizontal plane) looks
along ``cos t * z + sin t * (cos a * x + sin a * y)``; the top of its image points away from the nadir (far
ground at the top), and the nadir head's image top points forward. ``sensor_from_rig`` is the OpenCV camera's
rotation from the body frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..geometry.rotations import mount_rotation
from ..model import CameraModel, Rig, RigHead


@dataclass(frozen=True)
class HeadSpec:
    """One head: name, tilt and azimuth in degrees, focal length and pixel pitch in mm, image size in pixels,
    principal point offset from the image centre in pixels, Brown distortion (OpenCV), lever arm (m, body)."""

    name: str
    tilt_deg: float
    azimuth_deg: float
    focal_mm: float
    pixel_mm: float
    width: int
    height: int
    pp_offset: tuple[float, float] = (0.0, 0.0)
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class CameraSystem:
    """A multi-head camera system."""

    name: str
    heads: tuple[HeadSpec, ...]
    nadir_head: str = "nadir"

    def camera(self, head: str) -> CameraModel:
        """The interior orientation of one head (camera id ``<system>_<head>``)."""
        h = next((x for x in self.heads if x.name == head), None)
        if h is None:
            raise ConfigError(f"camera system '{self.name}' has no head '{head}'")
        f = h.focal_mm / h.pixel_mm
        return CameraModel(id=f"{self.name}_{h.name}", width=h.width, height=h.height, fx=f, fy=f,
                           cx=(h.width - 1) / 2 + h.pp_offset[0], cy=(h.height - 1) / 2 + h.pp_offset[1],
                           k1=h.k1, k2=h.k2, k3=h.k3, p1=h.p1, p2=h.p2, pixel_size_mm=h.pixel_mm,
                           name=f"{self.name} {h.name} {h.focal_mm:g} mm")

    def cameras(self) -> dict[str, CameraModel]:
        """Camera id -> model, one per head."""
        return {c.id: c for c in (self.camera(h.name) for h in self.heads)}

    def rig(self) -> Rig:
        """The nominal rig: head rotations from tilt/azimuth, lever arms as specified."""
        return Rig(self.name, tuple(RigHead(h.name, f"{self.name}_{h.name}", mount_rotation(h.tilt_deg, h.azimuth_deg),
                                            np.asarray(h.lever_arm, np.float64)) for h in self.heads))

    @property
    def nadir(self) -> HeadSpec:
        return next(h for h in self.heads if h.name == self.nadir_head)


_W, _H = 1200, 900
_PIX = 5.2e-3 * 10320 / _W  # 44.7 um: the RCD30 sensor's field of view at 1200 px


def penta(width: int = _W, height: int = _H) -> CameraSystem:
    """The Maltese-cross preset (RCD30 Penta geometry scaled to ``width`` x ``height`` pixels)."""
    pix = 5.2e-3 * 10320 / width
    obl = dict(focal_mm=80.0, pixel_mm=pix, width=width, height=height)
    return CameraSystem("penta", (
        HeadSpec("nadir", 0.0, 0.0, 50.0, pix, width, height, (2.1, -1.4), k1=-0.015, k2=0.004, p1=1e-4, p2=-5e-5),
        HeadSpec("forward", 45.0, 0.0, **obl, pp_offset=(-1.2, 0.8), k1=-0.01, k2=0.002, lever_arm=(0.12, 0.0, 0.0)),
        HeadSpec("right", 45.0, 90.0, **obl, pp_offset=(0.7, 1.5), k1=-0.012, k2=0.003, lever_arm=(0.0, 0.12, 0.0)),
        HeadSpec("backward", 45.0, 180.0, **obl, pp_offset=(1.6, -0.5), k1=-0.009, k2=0.001,
                 lever_arm=(-0.12, 0.0, 0.0)),
        HeadSpec("left", 45.0, 270.0, **obl, pp_offset=(-0.9, -1.1), k1=-0.011, k2=0.002,
                 lever_arm=(0.0, -0.12, 0.0)),
    ))


def three_head(width: int = _W, height: int = _H) -> CameraSystem:
    """Nadir plus left/right obliques at 36 deg."""
    pix = 5.2e-3 * 10320 / width
    obl = dict(focal_mm=70.0, pixel_mm=pix, width=width, height=height)
    return CameraSystem("three_head", (
        HeadSpec("nadir", 0.0, 0.0, 50.0, pix, width, height, (1.0, -0.6), k1=-0.015, k2=0.004),
        HeadSpec("right", 36.0, 90.0, **obl, pp_offset=(0.5, 1.0), k1=-0.01, k2=0.002, lever_arm=(0.0, 0.1, 0.0)),
        HeadSpec("left", 36.0, 270.0, **obl, pp_offset=(-0.8, 0.4), k1=-0.01, k2=0.002, lever_arm=(0.0, -0.1, 0.0)),
    ))


PRESETS = {"penta": penta, "three-head": three_head}


def preset(name: str) -> CameraSystem:
    """A camera system by preset name (``penta``, ``three-head``)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown camera system '{name}' (known: {', '.join(sorted(PRESETS))})")
    return PRESETS[name]()


def system_from_dict(d: dict) -> CameraSystem:
    """A custom system: ``{"name": ..., "heads": [{"name", "tilt_deg", "azimuth_deg", "focal_mm", "pixel_mm",
    "width", "height", optional "pp_offset", "k1", "k2", "k3", "p1", "p2", "lever_arm"}, ...]}``; exactly one
    head with tilt below 20 deg is the nadir head."""
    try:
        heads = []
        for i, h in enumerate(d["heads"]):
            unknown = set(h) - set(HeadSpec.__dataclass_fields__)
            if unknown:
                raise ConfigError(f"heads[{i}]: unknown keys {sorted(unknown)}")
            h = dict(h)
            for k in ("pp_offset", "lever_arm"):
                if k in h:
                    h[k] = tuple(float(v) for v in h[k])
            heads.append(HeadSpec(**h))
        nadir = [h.name for h in heads if h.tilt_deg < 20.0]
        if len(nadir) != 1:
            raise ConfigError("a custom camera system needs exactly one nadir head (tilt < 20 deg)")
        return CameraSystem(str(d.get("name", "custom")), tuple(heads), nadir[0])
    except (KeyError, TypeError) as e:
        raise ConfigError(f"bad camera system definition: {e}") from None

"""Cardinal views (``nadir``, ``north``, ``east``, ``south``, ``west``) from an image's actual orientation.

The view is where the camera *looks*: an image whose optical axis points towards north is a ``north`` view
(it sees the south-facing facades). A head of a Maltese-cross camera looks north on one strip and south on the
next, so the view is computed from each image's rotation, never taken from the head's name.
"""

from __future__ import annotations

import numpy as np

VIEWS = ("nadir", "north", "east", "south", "west")
OBLIQUE_VIEWS = ("north", "east", "south", "west")


def tilt_and_azimuth(r_cam_from_world: np.ndarray) -> tuple[float, float]:
    """Tilt from the vertical and azimuth (clockwise from grid north) of the optical axis, in degrees."""
    d = np.asarray(r_cam_from_world, dtype=np.float64)[2]
    tilt = float(np.degrees(np.arccos(np.clip(-d[2], -1.0, 1.0))))
    azimuth = float(np.degrees(np.arctan2(d[0], d[1])) % 360.0)
    return tilt, azimuth


def cardinal_view(r_cam_from_world: np.ndarray, nadir_max_tilt_deg: float = 20.0) -> str:
    """``nadir`` when the optical axis is within ``nadir_max_tilt_deg`` of straight down, else the cardinal
    direction (north, east, south, west) nearest to the axis's azimuth."""
    tilt, azimuth = tilt_and_azimuth(r_cam_from_world)
    if tilt <= nadir_max_tilt_deg:
        return "nadir"
    return OBLIQUE_VIEWS[int(((azimuth + 45.0) % 360.0) // 90.0)]

"""Coordinate reference systems through pyproj: validation and transformation of world coordinates."""

from __future__ import annotations

import numpy as np

from ..errors import InputError


def parse_crs(text: str, source: str | None = None, field: str = "crs"):
    """A ``pyproj.CRS`` from ``EPSG:nnnn``, a bare EPSG number or WKT; raise InputError naming ``source``."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    s = str(text).strip()
    if s.isdigit():
        s = "EPSG:" + s
    try:
        crs = CRS.from_user_input(s)
    except CRSError as e:
        raise InputError(f"unknown coordinate reference system '{text[:80]}' ({e})", path=source,
                         field=field) from None
    return crs


def normalize_crs(text: str, source: str | None = None) -> str:
    """Canonical text for a CRS: ``EPSG:nnnn`` when it has an EPSG code, else WKT2."""
    crs = parse_crs(text, source)
    code = crs.to_epsg(min_confidence=90)
    return f"EPSG:{code}" if code is not None else crs.to_wkt()


def is_projected_metric(text: str) -> bool:
    """True for a projected CRS in metres (what the core's world frame needs)."""
    crs = parse_crs(text)
    if not crs.is_projected:
        return False
    return all(ax.unit_name in ("metre", "meter") for ax in crs.axis_info[:2])


def transform_points(xyz: np.ndarray, src: str, dst: str) -> np.ndarray:
    """Transform ``(n, 3)`` coordinates from CRS ``src`` to ``dst`` (x = easting/longitude, always_xy)."""
    from pyproj import Transformer

    if normalize_crs(src) == normalize_crs(dst):
        return np.array(xyz, dtype=np.float64)
    t = Transformer.from_crs(parse_crs(src), parse_crs(dst), always_xy=True)
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    if n == 1:  # pyproj takes size-1 arrays for scalars (a NumPy deprecation): pad to two points
        xyz = np.repeat(xyz, 2, axis=0)
    x, y, z = t.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2])
    return np.stack([x, y, z], axis=1)[:n]

"""Coordinate reference systems through pyproj: validation and transformation of world coordinates."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

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


def transform_points(xyz: np.ndarray, src: str, dst: str, path: str | None = None,
                     lines: Sequence[int | None] | None = None) -> np.ndarray:
    """Transform ``(n, 3)`` coordinates from CRS ``src`` to ``dst`` (x = easting/longitude, always_xy; see
    :func:`crs_transformer` for what is refused; ``path`` and the points' ``lines`` name the first point refused)."""
    if normalize_crs(src) == normalize_crs(dst):
        return np.array(xyz, dtype=np.float64)
    return crs_transformer(parse_crs(src), parse_crs(dst), path)(xyz, lines)


def geocentric_crs(crs):
    """The geocentric CRS (Cartesian X, Y, Z in metres) on the datum of ``crs`` (a pyproj CRS)."""
    from pyproj import CRS

    d = crs.geodetic_crs.to_json_dict()
    d["type"] = "GeodeticCRS"
    d["name"] = f"{d.get('name', 'datum')} (geocentric)"
    d.pop("id", None)
    d["coordinate_system"] = {"subtype": "Cartesian", "axis": [
        {"name": f"Geocentric {a}", "abbreviation": a, "direction": f"geocentric{a}", "unit": "metre"}
        for a in "XYZ"]}
    return CRS.from_json_dict(d)


def missing_grids(group) -> list[str]:
    """The grid files (PROJ's names, with their download address) that the best transformations of a pyproj
    ``TransformerGroup`` need and PROJ does not find here."""
    found: dict[str, str] = {}
    for op in group.unavailable_operations:
        for g in op.grids:
            if not g.available:
                found.setdefault(g.short_name, g.url)
    return [f"{name} ({url})" if url else name for name, url in found.items()]


def crs_transformer(src, dst, path: str | None = None, field: str = "crs") -> Callable[..., np.ndarray]:
    """``f(xyz (n, 3), lines=None) -> (n, 3)`` from pyproj CRS ``src`` to ``dst``; refuses points it cannot
    transform, naming the first (its line from ``lines``, one per point, when given), and ballpark height
    transformations.

    Heights between ellipsoidal and a vertical datum need a geoid grid (e.g. ``de_bkg_gcg2016.tif`` for DHHN2016).
    PROJ finds grid files in its user directory (``pyproj.datadir.get_user_data_dir()``, or the folder the
    environment variable ``PROJ_USER_WRITABLE_DIRECTORY`` names); without one the transformation is refused, naming
    the grid and where to put it, rather than heights left off by the geoid undulation. Ballpark operations are
    never chosen where a better one exists: a point outside the grid is refused, not moved by a ballpark."""
    from pyproj import Transformer
    from pyproj.datadir import get_user_data_dir
    from pyproj.exceptions import ProjError
    from pyproj.transformer import TransformerGroup

    with warnings.catch_warnings():  # pyproj's warning of a missing grid: named in the refusal below
        warnings.simplefilter("ignore", UserWarning)
        try:
            t = Transformer.from_crs(src, dst, always_xy=True, allow_ballpark=False)
            ballpark_heights = False
        except ProjError:  # ballpark operations only: accepted for positions, not for heights
            t = Transformer.from_crs(src, dst, always_xy=True)
            group = TransformerGroup(src, dst, always_xy=True)
            ballpark_heights = any("ballpark vertical" in op.description.lower() for op in group.transformers)
        if ballpark_heights:
            grids = missing_grids(group)
            need = f"the geoid grid {' or '.join(grids)}" if grids else "a geoid model"
            raise InputError(f"heights from {src.name} to {dst.name} need {need}, which PROJ does not find here: put "
                             f"the grid file in {get_user_data_dir()} (or the folder PROJ_USER_WRITABLE_DIRECTORY "
                             f"names), or choose a CRS with ellipsoidal heights (-o crs=EPSG:nnnn)", path=path,
                             field=field)

    def apply(xyz: np.ndarray, lines: Sequence[int | None] | None = None) -> np.ndarray:
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        n = len(xyz)
        padded = np.repeat(xyz, 2, axis=0) if n == 1 else xyz  # pyproj takes size-1 arrays for scalars: pad
        out = np.stack(t.transform(padded[:, 0], padded[:, 1], padded[:, 2]), axis=1)[:n]
        bad = np.flatnonzero(~np.all(np.isfinite(out), axis=1))
        if len(bad):
            k = bad[0]
            raise InputError(f"coordinates from {src.name} to {dst.name} could not be transformed ({len(bad)} of "
                             f"{n} points, the first {' '.join(f'{v:.3f}' for v in xyz[k])})", path=path,
                             line=None if lines is None else lines[k], field=field)
        return out

    return apply


def grid_rotations(xyz: np.ndarray, to_grid: Callable[[np.ndarray], np.ndarray], step: float = 1.0,
                   path: str | None = None) -> np.ndarray:
    """Rotations ``(n, 3, 3)`` ``grid_from_source`` of a coordinate transformation at points ``xyz (n, 3)``.

    Each is the rotation nearest (polar decomposition) to the transformation's Jacobian at the point, taken by
    central differences over ``step`` (source units). For a conformal map projection with heights that is the
    turn by the grid convergence and the local vertical; the Jacobian's scale (projection and height scale
    factors) is left out, as in every omega-phi-kappa export. A mirroring transformation is refused, naming the file
    ``path`` the coordinates came from.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    offsets = np.concatenate([np.eye(3), -np.eye(3)]) * step
    g = to_grid((xyz[None, :, :] + offsets[:, None, :]).reshape(-1, 3)).reshape(6, n, 3)
    jac = ((g[:3] - g[3:]) / (2.0 * step)).transpose(1, 2, 0)  # (n, grid axis, source axis)
    u, _, vt = np.linalg.svd(jac)
    q = u @ vt
    if np.any(np.linalg.det(q) < 0):
        raise InputError("the coordinate transformation mirrors the axes (left-handed CRS?)", path=path, field="crs")
    return q


def true_north_angles(xyz: np.ndarray, crs: str, path: str | None = None,
                      lines: Sequence[int | None] | None = None) -> np.ndarray:
    """Per point of ``xyz (n, 3)`` in ``crs`` the angle (radians, counter-clockwise) of true north seen in the
    grid (the grid convergence, from a northward step of 1e-5 degrees): a heading against true north minus this angle
    is the heading against grid north. 0 for a geographic CRS."""
    src = parse_crs(crs)
    if src.is_geographic:
        return np.zeros(len(xyz))
    wgs84 = parse_crs("EPSG:4326")
    geo = crs_transformer(src, wgs84, path)(xyz, lines)
    d = np.diff(crs_transformer(wgs84, src)(np.concatenate([geo, geo + [0.0, 1e-5, 0.0]])).reshape(2, -1, 3), axis=0)[0]
    return np.arctan2(-d[:, 0], d[:, 1])

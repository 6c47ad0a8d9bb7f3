"""Building attributes and the LoD 1.2 block model derived from an LoD2 model, as 3D city registries publish them.

Heights follow the practice of the Dutch 3D building registry (3DBAG): roof heights are percentiles of the top
surface sampled evenly over the footprint (so they are area-weighted: the 70th percentile is the usual height of
a block model), the ground height is that of the model's ground surface. Areas and the volume are exact for the
model's planar polygons (the volume by the divergence theorem over the closed solid).

The roof type sorts the roof into ``horizontal`` (one flat level), ``multiple horizontal`` (flat levels more than
``level_step`` apart) and ``slanted`` (at least ``slanted_share`` of the roof area steeper than
``flat_deg``).
"""

from __future__ import annotations

import numpy as np

from .geometry import points_in_polygon, polygon_area, top_of_rings
from .model import BuildingModel, ring_area_vector


def model_top_height(model: BuildingModel, xy: np.ndarray) -> np.ndarray:
    """Height of the model's highest roof surface over points ``xy (n, 2)`` (NaN where no roof covers one); the
    roof overhangs count (an upper roof's overhang over a lower one is the top surface there)."""
    return top_of_rings(model.vertices, [list(s.ring) for s in model.surfaces if s.kind in ("roof", "overhang_roof")],
                        xy)


def solid_volume(model: BuildingModel) -> float:
    """Volume (m^3) enclosed by the model's solid faces (rings counter-clockwise seen from outside)."""
    v = model.vertices - model.vertices.mean(0)  # well-conditioned sums
    return float(sum(v[list(s.ring)][0] @ ring_area_vector(v[list(s.ring)]) for s in model.surfaces if s.in_solid)
                 / 3.0)


def ground_height(model: BuildingModel) -> float:
    """Height of the model's ground surface (its lowest vertex; the lowest vertex of all without one)."""
    ground = [s for s in model.surfaces if s.kind == "ground"]
    if ground:
        return float(min(model.vertices[list(s.ring), 2].min() for s in ground))
    return float(model.vertices[:, 2].min())


def footprint_samples(footprint: np.ndarray, step: float) -> np.ndarray:
    """Cell centres ``(k, 2)`` of a ``step`` grid inside the polygon ``footprint (m, 2)``."""
    lo, hi = footprint.min(0), footprint.max(0)
    x, y = np.meshgrid(np.arange(lo[0] + step / 2, hi[0], step), np.arange(lo[1] + step / 2, hi[1], step))
    xy = np.column_stack([x.ravel(), y.ravel()])
    return xy[points_in_polygon(xy, footprint)]


def building_attributes(model: BuildingModel, step: float = 0.25, flat_deg: float = 3.0,
                        level_step: float = 0.5, slanted_share: float = 0.1) -> dict[str, float | str]:
    """Attributes of an LoD2 model: ``ground_height``, ``roof_height_min / _50p / _70p / _max`` (absolute
    heights of the top surface over the footprint, sampled every ``step`` m), ``measured_height`` (highest point
    above the ground), ``footprint_area``, ``roof_area``, ``wall_area``, ``volume`` and ``roof_type`` (see the
    module docstring)."""
    fp = np.asarray(model.footprint, dtype=np.float64)
    z0 = ground_height(model)
    top = model_top_height(model, footprint_samples(fp, step)) if len(fp) >= 3 else np.zeros(0)
    top = top[np.isfinite(top)]
    if not len(top):
        top = np.array([float(model.vertices[:, 2].max())])
    areas = {"roof": 0.0, "wall": 0.0}
    flat_z, flat_a, slanted = [], [], 0.0
    for s in model.surfaces:
        if s.kind not in areas or not s.in_solid:
            continue
        a = ring_area_vector(model.vertices[list(s.ring)])
        area = float(np.linalg.norm(a))
        areas[s.kind] += area
        if s.kind == "roof":
            if abs(a[2]) >= np.cos(np.radians(flat_deg)) * area:
                flat_z.append(float(model.vertices[list(s.ring), 2].mean()))
                flat_a.append(area)
            else:
                slanted += area
    if slanted > slanted_share * max(areas["roof"], 1e-9):
        roof_type = "slanted"
    else:
        z = np.sort(np.asarray(flat_z))
        roof_type = "multiple horizontal" if len(z) > 1 and np.any(np.diff(z) > level_step) else "horizontal"
    q = np.percentile(top, [0, 50, 70, 100])
    return {"ground_height": round(z0, 3), "roof_height_min": round(float(q[0]), 3),
            "roof_height_50p": round(float(q[1]), 3), "roof_height_70p": round(float(q[2]), 3),
            "roof_height_max": round(float(q[3]), 3),
            "measured_height": round(float(model.vertices[:, 2].max()) - z0, 3),
            "footprint_area": round(abs(polygon_area(fp)), 2) if len(fp) >= 3 else 0.0,
            "roof_area": round(areas["roof"], 2), "wall_area": round(areas["wall"], 2),
            "volume": round(solid_volume(model), 1), "roof_type": roof_type}


def lod12_block(model: BuildingModel, top: float) -> tuple[np.ndarray, list[list[int]], list[str]]:
    """The LoD 1.2 block of a model: its footprint extruded from the ground height to ``top`` (usually the 70th
    percentile roof height). Returns vertices ``(2m, 3)``, rings (counter-clockwise seen from outside) and their
    kinds (``ground``, ``roof``, ``wall``)."""
    fp = np.asarray(model.footprint, dtype=np.float64)
    if polygon_area(fp) < 0:
        fp = fp[::-1]
    m, z0 = len(fp), ground_height(model)
    vertices = np.vstack([np.column_stack([fp, np.full(m, z0)]), np.column_stack([fp, np.full(m, top)])])
    rings = [list(range(m - 1, -1, -1)), list(range(m, 2 * m))]
    rings += [[i, (i + 1) % m, m + (i + 1) % m, m + i] for i in range(m)]
    return vertices, rings, ["ground", "roof"] + ["wall"] * m

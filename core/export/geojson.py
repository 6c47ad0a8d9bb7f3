"""Building footprints as GeoJSON (RFC 7946) for GIS: one Polygon Feature per building with its attributes.

RFC 7946 coordinates are WGS 84 longitude and latitude (degrees, 8 decimals: about a millimetre), so the
footprints are transformed from the project CRS with pyproj; the exterior ring is counter-clockwise (the RFC's
right-hand rule) and closed. Each Feature's ``id`` is the building id and its ``properties`` hold the
reconstruction path, whether the model is a closed solid and the attributes of
:func:`..buildings.attributes.building_attributes` (heights in the project's vertical reference, metres).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..buildings.attributes import building_attributes
from ..buildings.geometry import polygon_area
from ..geometry.crs import crs_transformer, parse_crs
from ..pipeline.atomic import write_text

WGS84 = "EPSG:4326"


def footprint_features(buildings, crs: str) -> dict:
    """The GeoJSON FeatureCollection of the buildings' footprints (see the module docstring)."""
    to_wgs84 = crs_transformer(parse_crs(crs), parse_crs(WGS84))
    features = []
    for b in buildings:
        fp = np.asarray(b.footprint, np.float64)
        if polygon_area(fp) < 0:
            fp = fp[::-1]
        lonlat = to_wgs84(np.column_stack([fp, np.zeros(len(fp))]))[:, :2]
        ring = np.round(np.vstack([lonlat, lonlat[:1]]), 8).tolist()
        features.append({"type": "Feature", "id": b.id, "geometry": {"type": "Polygon", "coordinates": [ring]},
                         "properties": {"id": b.id, "path": b.path, "closed_solid": bool(b.info.get("closed")),
                                        **building_attributes(b)}})
    return {"type": "FeatureCollection", "features": features}


def write_footprints_geojson(path: str | Path, buildings, crs: str) -> None:
    """Write the footprints of ``buildings`` as a GeoJSON file, atomically."""
    write_text(path, json.dumps(footprint_features(buildings, crs)))

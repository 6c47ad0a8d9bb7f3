"""GeoJSON footprints: RFC 7946 lon/lat rings that pyproj takes back onto the model's footprint (1 mm),
counter-clockwise and closed, with the building attributes."""

from __future__ import annotations

import json

import numpy as np
from pyproj import Transformer

from oblique_city.core.buildings.attributes import building_attributes
from oblique_city.core.buildings.geometry import polygon_area
from oblique_city.core.buildings.model import BuildingModel, Surface
from oblique_city.core.export.geojson import write_footprints_geojson


def _box(bid: str, clockwise: bool) -> BuildingModel:
    xy = np.array([[0, 0], [12, 0], [12, 9], [5, 9], [5, 4], [0, 4]], float) + [512000.0, 5403000.0]
    v = np.vstack([np.c_[xy, np.full(6, 150.0)], np.c_[xy, np.full(6, 158.0)]])
    surfaces = [Surface("g", "ground", tuple(range(5, -1, -1))), Surface("r", "roof", tuple(range(6, 12)))]
    surfaces += [Surface(f"w{i}", "wall", (i, (i + 1) % 6, 6 + (i + 1) % 6, 6 + i)) for i in range(6)]
    return BuildingModel(bid, v, surfaces, "2d", "", xy[::-1] if clockwise else xy, np.zeros(6), np.zeros((0, 4)),
                         {"closed": True})


def test_footprints_round_trip(tmp_path):
    models = [_box("B1", False), _box("B2", True)]
    write_footprints_geojson(tmp_path / "f.geojson", models, "EPSG:25832")
    doc = json.loads((tmp_path / "f.geojson").read_text())
    assert doc["type"] == "FeatureCollection" and [f["id"] for f in doc["features"]] == ["B1", "B2"]
    back = Transformer.from_crs("EPSG:4326", "EPSG:25832", always_xy=True)
    for f, m in zip(doc["features"], models, strict=True):
        ring = np.array(f["geometry"]["coordinates"][0])
        assert f["geometry"]["type"] == "Polygon" and np.array_equal(ring[0], ring[-1])
        assert 8.0 < ring[0, 0] < 12.0 and 47.0 < ring[0, 1] < 56.0  # longitude, latitude (UTM 32 N)
        assert polygon_area(ring[:-1]) > 0  # counter-clockwise: RFC 7946's right-hand rule
        x, y = back.transform(ring[:-1, 0], ring[:-1, 1])
        xy = np.column_stack([x, y])
        d = np.linalg.norm(xy[:, None, :] - m.footprint[None, :, :], axis=2)
        assert d.min(1).max() < 1e-3 and d.min(0).max() < 1e-3
        props = f["properties"]
        # 12 x 4 + 7 x 5 m^2 of footprint, 8 m high
        assert props["closed_solid"] and props["volume"] == building_attributes(m)["volume"] == 83.0 * 8

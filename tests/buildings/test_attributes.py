"""Building attributes and the LoD 1.2 block, on hand-built models whose heights, areas and volume are known."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.buildings.attributes import building_attributes, lod12_block, solid_volume
from oblique_city.core.buildings.model import BuildingModel, Surface


def _gable_house(z0: float = 100.0) -> BuildingModel:
    """10 m (x) by 8 m (y), eaves 6 m, ridge 9 m along x at y = 4: volume 480 + 120 m^3, roof 2 x 10 x 5 m^2,
    walls 2 x 60 + 2 x 60 m^2."""
    v = np.array([[0, 0, 0], [10, 0, 0], [10, 8, 0], [0, 8, 0],
                  [0, 0, 6], [10, 0, 6], [10, 8, 6], [0, 8, 6], [0, 4, 9], [10, 4, 9]], float) + [500.0, 20.0, z0]
    rings = {"ground": [(3, 2, 1, 0)], "roof": [(4, 5, 9, 8), (6, 7, 8, 9)],
             "wall": [(0, 1, 5, 4), (1, 2, 6, 9, 5), (2, 3, 7, 6), (3, 0, 4, 8, 7)]}
    surfaces = [Surface(f"s{k}_{i}", k, r) for k, rs in rings.items() for i, r in enumerate(rs)]
    return BuildingModel("B0001", v, surfaces, "2d", "", v[:4, :2].copy(), np.zeros(4), np.zeros((0, 4)))


def _flat_blocks(step: float) -> BuildingModel:
    """Two flat blocks side by side, 6 x 5 m each, roofs 5 m and 5 + ``step`` m above the ground at 0."""
    h1, h2 = 5.0, 5.0 + step
    v = np.array([[0, 0, 0], [6, 0, 0], [12, 0, 0], [12, 5, 0], [6, 5, 0], [0, 5, 0],
                  [0, 0, h1], [6, 0, h1], [6, 5, h1], [0, 5, h1],
                  [6, 0, h2], [12, 0, h2], [12, 5, h2], [6, 5, h2]], float)
    rings = {"ground": [(5, 4, 3, 2, 1, 0)], "roof": [(6, 7, 8, 9), (10, 11, 12, 13)],
             "wall": [(0, 1, 7, 6), (1, 2, 11, 10, 7), (2, 3, 12, 11), (3, 4, 13, 12), (4, 5, 9, 8, 13),
                      (5, 0, 6, 9), (7, 10, 13, 8)]}
    surfaces = [Surface(f"s{k}_{i}", k, r) for k, rs in rings.items() for i, r in enumerate(rs)]
    return BuildingModel("B0002", v, surfaces, "2d", "", v[[0, 2, 3, 5], :2].copy(), np.zeros(4), np.zeros((0, 4)))


def test_gable_house_attributes():
    a = building_attributes(_gable_house())
    assert a["ground_height"] == 100.0 and a["measured_height"] == 9.0
    assert a["footprint_area"] == 80.0 and a["roof_area"] == pytest.approx(100.0)
    assert a["wall_area"] == pytest.approx(240.0) and a["volume"] == pytest.approx(600.0)
    # the top surface rises evenly from 106 to 109 m across the footprint: its percentiles are those of a uniform
    # distribution, to the 0.25 m sampling (3 m over 4 m: 0.1 m)
    assert a["roof_height_50p"] == pytest.approx(107.5, abs=0.1)
    assert a["roof_height_70p"] == pytest.approx(108.1, abs=0.1)
    assert a["roof_height_min"] == pytest.approx(106.0, abs=0.1) and a["roof_height_max"] == pytest.approx(109.0,
                                                                                                          abs=0.1)
    assert a["roof_type"] == "slanted"


def test_flat_roof_types_and_volume():
    one, two = building_attributes(_flat_blocks(0.2)), building_attributes(_flat_blocks(3.0))
    assert one["roof_type"] == "horizontal" and two["roof_type"] == "multiple horizontal"
    assert two["volume"] == pytest.approx(30 * 5 + 30 * 8) and one["volume"] == pytest.approx(30 * 5 + 30 * 5.2)
    assert two["roof_height_min"] == 5.0 and two["roof_height_max"] == 8.0


def test_lod12_block_is_a_closed_prism_at_the_given_height():
    m = _gable_house()
    v, rings, kinds = lod12_block(m, 108.1)
    assert kinds.count("wall") == 4 and kinds[:2] == ["ground", "roof"]
    block = BuildingModel("b", v, [Surface(str(i), k, tuple(r)) for i, (r, k) in enumerate(zip(rings, kinds))],
                          "2d", "", m.footprint, np.zeros(4), np.zeros((0, 4)))
    assert solid_volume(block) == pytest.approx(80.0 * 8.1)  # positive: every ring faces outwards
    # every edge is shared by exactly two faces, in opposite directions
    edges = [(r[i], r[(i + 1) % len(r)]) for r in rings for i in range(len(r))]
    assert sorted(edges) == sorted((b, a) for a, b in edges)

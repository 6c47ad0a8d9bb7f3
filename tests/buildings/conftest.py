"""Parametric buildings with exact ground truth, sampled once per test session."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.buildings.synthetic import parametric_buildings

NOISE = 0.04
DENSITY = 25.0
DSM_CELL = 0.1


@pytest.fixture(scope="session")
def synthetic():
    """{name: (SyntheticBuilding, points (n, 3), dsm, dtm)} with 4 cm noise, 25 points/m^2, a 10 cm DSM."""
    out = {}
    for b in parametric_buildings():
        rng = np.random.default_rng(7)
        xyz = b.sample(DENSITY, NOISE, rng)
        dsm, dtm = b.dsm(DSM_CELL, 0.03, rng)
        out[b.name] = (b, xyz, dsm, dtm)
    return out

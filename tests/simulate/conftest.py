"""The default city, built once per test session for the simulator tests."""

from __future__ import annotations

import pytest

from oblique_city.core.simulate.city import make_city
from oblique_city.core.simulate.render import Renderer


@pytest.fixture(scope="session")
def city():
    return make_city(0)


@pytest.fixture(scope="session")
def renderer(city):
    return Renderer(city)

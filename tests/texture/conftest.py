"""A workspace holding the synthetic scene's block (rendered images) and buildings."""

from __future__ import annotations

import pytest

from oblique_city.core.buildings.model import save_buildings
from oblique_city.core.pipeline import Workspace

from .scene import buildings, make_block


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    root = tmp_path_factory.mktemp("ws")
    ws = Workspace.create(root / "ws", crs="EPSG:25832")
    ws.save_block(make_block(root / "images"))
    save_buildings(ws.path("buildings", "buildings.json"), buildings(), ws.crs)
    return ws

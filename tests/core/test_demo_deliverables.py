"""The demo's deliverables: the city in every format and the block for other software, read back, and the project
report; without buildings only the block and the report."""

from __future__ import annotations

import json

import numpy as np

from oblique_city.core.buildings.model import BuildingModel, Surface, save_buildings
from oblique_city.core.demo import deliverables
from oblique_city.core.export.citygml import validate_citygml
from oblique_city.core.io.formats import read_block
from oblique_city.core.pipeline import Workspace


def _box() -> BuildingModel:
    xy = np.array([[0, 0], [10, 0], [10, 8], [0, 8]], float) + [500100.0, 5400050.0]
    v = np.vstack([np.c_[xy, np.full(4, 100.0)], np.c_[xy, np.full(4, 106.0)]])
    surfaces = [Surface("g", "ground", (0, 3, 2, 1)), Surface("r", "roof", (4, 5, 6, 7))]
    surfaces += [Surface(f"w{i}", "wall", (i, (i + 1) % 4, 4 + (i + 1) % 4, 4 + i)) for i in range(4)]
    return BuildingModel("B0001", v, surfaces, "2d", "", xy, np.zeros(4), np.zeros((0, 4)), {"closed": True})


def test_deliverables(tmp_path, utm_block):
    ws = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
    ws.save_block(utm_block)
    got = deliverables(ws, tmp_path / "export")
    assert len(got["exports"]) == 2 and (ws.root / "report.html").exists()
    assert set(read_block("metashape", tmp_path / "export" / "cameras.xml").images) == set(utm_block.images)
    save_buildings(ws.path("buildings", "buildings.json"), [_box()], ws.crs)
    ws.write_state({"buildings": {"status": "done", "seconds": 1.0, "message": "1 building"}})
    got = deliverables(ws, tmp_path / "export")
    assert len(got["exports"]) == 7
    assert validate_citygml(tmp_path / "export" / "city.gml") == []
    assert json.loads((tmp_path / "export" / "tiles" / "tileset.json").read_text())["asset"]["version"] == "1.1"
    assert "1 building" in (ws.root / "report.html").read_text()

"""The demo limits dense matching and surfaces to the simulated city, keeping an AOI the user set."""

from __future__ import annotations

import json

from oblique_city.core.demo import _set_area_of_interest
from oblique_city.core.pipeline import Workspace


def test_demo_area_of_interest_is_the_city(tmp_path):
    sim = tmp_path / "sim"
    (sim / "truth").mkdir(parents=True)
    (sim / "truth" / "simulation.json").write_text(json.dumps(
        {"summary": {"area": [100.0, 200.0, 300.0, 350.0]}, "config": {"area_inset": 20.0}}))
    ws = Workspace.create(tmp_path / "ws", crs="EPSG:25832")
    ws.project.setdefault("stages", {})["surface"] = {"aoi": [1.0, 2.0, 3.0, 4.0]}
    _set_area_of_interest(ws, sim)
    again = Workspace.open(tmp_path / "ws")
    assert again.project["stages"]["dense"]["aoi"] == [80.0, 180.0, 320.0, 370.0]
    assert again.project["stages"]["surface"]["aoi"] == [1.0, 2.0, 3.0, 4.0]

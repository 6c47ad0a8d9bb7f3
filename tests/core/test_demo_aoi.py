"""The demo limits dense matching and surfaces to the simulated city and calibrates the mounting, keeping what the
user set."""

from __future__ import annotations

import json

from oblique_city.core.demo import _set_demo_options
from oblique_city.core.pipeline import Workspace


def test_demo_options_area_of_interest_and_mounting(tmp_path):
    sim = tmp_path / "sim"
    (sim / "truth").mkdir(parents=True)
    (sim / "truth" / "simulation.json").write_text(json.dumps(
        {"summary": {"area": [100.0, 200.0, 300.0, 350.0]}, "config": {"area_inset": 20.0}}))
    ws = Workspace.create(tmp_path / "ws", crs="EPSG:25832")
    ws.project.setdefault("stages", {})["surface"] = {"aoi": [1.0, 2.0, 3.0, 4.0]}
    ws.project["stages"]["aerotri"] = {"mode": "hierarchical"}
    _set_demo_options(ws, sim)
    again = Workspace.open(tmp_path / "ws")
    assert again.project["stages"]["dense"]["aoi"] == [80.0, 180.0, 320.0, 370.0]
    assert again.project["stages"]["surface"]["aoi"] == [1.0, 2.0, 3.0, 4.0]
    assert again.project["stages"]["aerotri"] == {"mode": "hierarchical", "mounting": True}
    again.project["stages"]["aerotri"]["mounting"] = False
    _set_demo_options(again, sim)
    assert again.project["stages"]["aerotri"]["mounting"] is False

"""The demo limits dense matching and surfaces to the simulated city, calibrates the mounting, ties the heads by
the rig and gives the GNSS/IMU priors the simulated navigation system's sigmas, keeping what the user set."""

from __future__ import annotations

import json

from oblique_city.core.demo import _set_demo_options
from oblique_city.core.pipeline import Workspace


def test_demo_options_area_of_interest_mounting_and_navigation_sigmas(tmp_path):
    sim = tmp_path / "sim"
    (sim / "truth").mkdir(parents=True)
    (sim / "truth" / "simulation.json").write_text(json.dumps(
        {"summary": {"area": [100.0, 200.0, 300.0, 350.0]},
         "config": {"area_inset": 20.0,
                    "nav": {"gnss_sigma": [0.05, 0.05, 0.08], "imu_sigma_deg": [0.005, 0.005, 0.008]}}}))
    ws = Workspace.create(tmp_path / "ws", crs="EPSG:25832")
    ws.project.setdefault("stages", {})["surface"] = {"aoi": [1.0, 2.0, 3.0, 4.0]}
    ws.project["stages"]["aerotri"] = {"mode": "hierarchical"}
    _set_demo_options(ws, sim)
    again = Workspace.open(tmp_path / "ws")
    assert again.project["stages"]["dense"]["aoi"] == [80.0, 180.0, 320.0, 370.0]
    assert again.project["stages"]["surface"]["aoi"] == [1.0, 2.0, 3.0, 4.0]
    assert again.project["stages"]["aerotri"] == {"mode": "hierarchical", "mounting": True, "rig": True,
                                                  "default_sigma_position": 0.08, "default_sigma_attitude_deg": 0.008}
    again.project["stages"]["aerotri"]["mounting"] = False
    _set_demo_options(again, sim)
    assert again.project["stages"]["aerotri"]["mounting"] is False

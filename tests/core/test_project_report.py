"""The project report: stages and their metrics from state.json, the pictures of the surface with the building
outlines where the buildings stand, stages not run listed as such, the CLI."""

from __future__ import annotations

import base64
import re

import cv2
import numpy as np
import pytest

from oblique_city.core.buildings.model import BuildingModel, Surface, save_buildings
from oblique_city.core.cli import main
from oblique_city.core.io.geotiff import write_geotiff
from oblique_city.core.model import Raster
from oblique_city.core.pipeline import Workspace
from oblique_city.core.report import hillshade, project_report

X0, Y0, CELL = 500000.0, 5400060.0, 0.5  # a 120 x 100 cell grid: 60 m east, 50 m south


def _box(x0: float, y0: float) -> BuildingModel:
    xy = np.array([[0, 0], [10, 0], [10, 8], [0, 8]], float) + [x0, y0]
    v = np.vstack([np.c_[xy, np.full(4, 100.0)], np.c_[xy, np.full(4, 106.0)]])
    surfaces = [Surface("g", "ground", (0, 3, 2, 1)), Surface("r", "roof", (4, 5, 6, 7))]
    surfaces += [Surface(f"w{i}", "wall", (i, (i + 1) % 4, 4 + (i + 1) % 4, 4 + i)) for i in range(4)]
    return BuildingModel("B0001", v, surfaces, "2d", "", xy, np.zeros(4), np.zeros((0, 4)), {"closed": True})


@pytest.fixture
def ws(tmp_path, utm_block):
    w = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
    w.save_block(utm_block)
    dsm = np.full((100, 120), 100.0, np.float32)
    dsm[40:56, 40:60] = 106.0  # the box: x 20-30 m, y 10-18 m south of Y0 - 20
    write_geotiff(w.stage_dir("surface") / "dsm.tif", Raster(dsm, X0, Y0, CELL, w.crs))
    ortho = np.zeros((100, 120, 4), np.uint8)
    ortho[..., 1], ortho[..., 3] = 90, 255  # green ground
    write_geotiff(w.path("surface", "ortho.tif"), Raster(ortho, X0, Y0, CELL, w.crs))
    save_buildings(w.stage_dir("buildings") / "buildings.json", [_box(X0 + 20.0, Y0 - 28.0)], w.crs)
    w.write_state({"dense": {"status": "done", "seconds": 12.5, "message": "1000 points",
                             "metrics": {"points": 1000, "points_per_view": {"nadir": 600, "north": 400}}},
                   "surface": {"status": "done", "seconds": 3.0, "message": "DSM 120x100",
                               "metrics": {"las_classes": {"ground": 800, "building": 200}}},
                   "buildings": {"status": "failed", "message": "boom"}})
    return w


def _images(page: str) -> dict[str, np.ndarray]:
    out = {}
    for alt, data in re.findall(r"alt='([^']*)' src='data:image/png;base64,([^']*)'", page):
        img = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
        out[alt] = img
    return out


def test_report_lists_stages_metrics_and_pictures(ws):
    page = project_report(ws)
    assert "<h2>Block</h2><p>3 images (" in page
    for text in ("<td>match</td><td>not run</td>", "<td>dense</td><td>done</td><td>12.5</td>",
                 "<td>buildings</td><td>failed</td>", "points_per_view.north</td><td>400",
                 "las_classes.building</td><td>200", "UTM zone 32N"):
        assert text in page, text
    images = _images(page)
    ortho = images["true orthophoto, 0.500 m cells, 1 building outlines"]
    assert ortho.shape == (100, 120, 3)
    # the outline runs along the footprint: row (Y0 - y) / cell, columns (x - X0) / cell
    assert ortho[40, 45, 0] > 200 and ortho[56, 50, 0] > 200 and ortho[48, 40, 0] > 200
    assert ortho[48, 50, 0] < 50 and ortho[20, 20, 0] < 50  # inside the building and far from it: no line
    assert any(k.startswith("DSM, 100.0 to 106.0 m") for k in images)
    # the building table: the box's roof type, height above its ground, footprint and volume
    assert ("<td>B0001</td><td>2d</td><td>yes</td><td>horizontal</td><td>100</td><td>6</td><td>6</td><td>80</td>"
            "<td>480</td>") in page


def test_hillshade_lights_slopes_facing_the_sun():
    x = np.arange(50) * 1.0
    facing_west = np.tile(x, (50, 1)) * 0.5  # rises to the east: faces west, towards a sun in the north-west
    facing_east = facing_west[:, ::-1]
    flat = np.zeros((50, 50))
    sw, se, sf = (hillshade(z, 1.0)[10:40, 10:40].mean() for z in (facing_west, facing_east, flat))
    assert sw > sf > se
    assert sf == pytest.approx(np.sin(np.radians(45.0)))


def test_cli_writes_the_report(ws, capsys):
    assert main(["report", str(ws.root)]) == 0
    assert (ws.root / "report.html").stat().st_size > 1000
    assert "project report written" in capsys.readouterr().out
    assert main(["report", str(ws.root), "--out", str(ws.root)]) == 2  # a folder: refused with a message

"""The ``windows`` stage on a tiny workspace (a box building whose south wall texture holds a known window grid,
written as the texture stage would), and the window exports (OBJ group, CityGML openings, CityJSON children)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from oblique_city.core.buildings.model import BuildingModel, Surface, save_buildings
from oblique_city.core.errors import Cancelled, InputError, WorkspaceError
from oblique_city.core.evaluate.windows import window_scores
from oblique_city.core.export.command import export_buildings
from oblique_city.core.export.obj import read_obj
from oblique_city.core.io.geotiff import write_png
from oblique_city.core.pipeline import Workspace
from oblique_city.core.pipeline.context import RunContext
from oblique_city.core.pipeline.registry import get_stage, stage_names
from oblique_city.core.texture.atlas import write_textures_json
from oblique_city.core.texture.plane import texel_grid
from oblique_city.core.windows.store import load_windows

from .facade import render_facade, window_grid

OFFSET = np.array([500000.0, 5400000.0, 100.0])
TEXEL = 0.1
L, H = 13.0, 10.0


def box() -> BuildingModel:
    v = np.array([[0, 0, 0], [L, 0, 0], [L, 8, 0], [0, 8, 0], [0, 0, H], [L, 0, H], [L, 8, H], [0, 8, H]],
                 np.float64) + OFFSET
    rings = [("ground", (0, 3, 2, 1)), ("wall", (0, 1, 5, 4)), ("wall", (1, 2, 6, 5)), ("wall", (2, 3, 7, 6)),
             ("wall", (3, 0, 4, 7)), ("roof", (4, 5, 6, 7))]
    surfaces = [Surface(f"B0001_{k}_{i}", k, r) for i, (k, r) in enumerate(rings)]
    return BuildingModel("B0001", v, surfaces, "2d", "", v[:4, :2].copy(), np.zeros(4),
                         np.array([[0.0, 0.0, 1.0, -(OFFSET[2] + H)]]), {"closed": True})


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """Buildings plus a textures.json whose south wall ``B0001_wall_1`` shows the 4 x 3 grid (one missing). No
    image saw the wall above 7.7 m (an eave), 0.8 m of the top row's windows: there the atlas repeats the last seen
    row upwards, as a nearest-colour fill would, and the seen mask says so."""
    ws = Workspace.create(tmp_path_factory.mktemp("ws") / "ws", crs="EPSG:25832")
    b = box()
    save_buildings(ws.path("buildings", "buildings.json"), [b], ws.crs)
    wall = b.surfaces[1]
    grid = texel_grid(b.vertices[list(wall.ring)], TEXEL)
    img = render_facade(window_grid(), L, H, TEXEL, noise=6.0)
    assert img.shape[:2] == grid.shape
    hidden = int(round((H - 7.7) / TEXEL))
    img[:hidden] = img[hidden]
    page = np.full((256, 256, 3), 128, np.uint8)
    page[4:4 + grid.shape[0], 4:4 + grid.shape[1]] = img
    seen = np.zeros((256, 256), np.uint8)
    seen[4 + hidden:4 + grid.shape[0], 4:4 + grid.shape[1]] = 255
    write_png(ws.stage_dir("texture") / "atlas_000.png", page)
    write_png(ws.stage_dir("texture") / "atlas_000_seen.png", seen)
    f = grid.frame
    write_textures_json(ws.path("texture", "textures.json"), {
        "crs": ws.crs, "pages": [{"file": "atlas_000.png", "seen": "atlas_000_seen.png", "width": 256,
                                  "height": 256}],
        "surfaces": {wall.id: {"building": b.id, "page": 0, "rect": [4, 4, grid.shape[1], grid.shape[0]],
                               "uv": [[0.1, 0.1]] * 4, "texel": TEXEL, "coverage": 1.0, "sources": {"x": 1.0},
                               "frame": {"origin": f.origin.tolist(), "e1": f.e1.tolist(), "e2": f.e2.tolist(),
                                         "s0": grid.s0, "t1": grid.t1}}},
        "untextured": {}, "gains": {}, "config": {}, "stats": {}})
    return ws


def truth() -> list[np.ndarray]:
    """The true windows of the south wall (y = 0 facing -y) in world coordinates."""
    return [np.array([[a, 0, b], [c, 0, b], [c, 0, d], [a, 0, d]], np.float64) + OFFSET
            for a, b, c, d in window_grid()]


def test_stage_is_registered_after_texture():
    names = stage_names()
    assert names.index("windows") == names.index("texture") + 1
    assert "texture" in get_stage("windows").requires


def test_stage_finds_the_grid_on_the_wall_plane(workspace):
    stage = get_stage("windows")
    seen = []
    res = stage.run(workspace, stage.make_config({"grow_m": 0.0}),
                    RunContext(on_progress=lambda s, d, t, m: seen.append((d, t))))
    assert res.outputs == ("windows/windows.json",) and seen[-1][0] == seen[-1][1]
    wins = load_windows(workspace.path("windows", "windows.json"))
    assert {w.surface_id for w in wins} == {"B0001_wall_1"} and len({w.id for w in wins}) == len(wins)
    corners = [w.corners for w in wins]
    assert np.allclose([c[:, 1] for c in corners], OFFSET[1], atol=1e-6)  # on the wall plane y = y0
    s = window_scores(corners, truth())
    # the top row, cut by the unseen band, as tall as the others: not up to the wall's top, not cut at 7.7 m
    assert s.precision == 1.0 and s.recall == 1.0 and s.corner_rmse_m < TEXEL
    doc = json.loads(workspace.path("windows", "windows.json").read_text())
    assert doc["stats"]["windows"] == 11 and doc["config"]["grow_m"] == 0.0


def test_stage_needs_the_seen_masks(workspace, tmp_path):
    import shutil

    ws = Workspace.open(shutil.copytree(workspace.root, tmp_path / "ws"))
    ws.path("texture", "atlas_000_seen.png").unlink()
    stage = get_stage("windows")
    with pytest.raises(InputError, match="atlas_000_seen.png"):
        stage.run(ws, stage.make_config({}), RunContext())


def test_exports_carry_the_windows(workspace, tmp_path):
    get_stage("windows").run(workspace, get_stage("windows").make_config({}), RunContext())
    n = len(load_windows(workspace.path("windows", "windows.json")))
    msg = export_buildings(workspace.root, "citygml", tmp_path / "c.gml")
    assert "valid CityGML 2.0" in msg and f"{n} windows" in msg
    assert (tmp_path / "c.gml").read_text().count("<bldg:Window ") == n
    export_buildings(workspace.root, "cityjson", tmp_path / "c.json")
    doc = json.loads((tmp_path / "c.json").read_text())
    inst = doc["CityObjects"]["B0001-windows"]
    assert inst["type"] == "BuildingInstallation" and inst["parents"] == ["B0001"]
    assert doc["CityObjects"]["B0001"]["children"] == ["B0001-windows"]
    assert [s["type"] for s in inst["geometry"][0]["semantics"]["surfaces"]] == ["Window"] * n
    export_buildings(workspace.root, "obj", tmp_path / "c.obj")
    v, groups, _ = read_obj(tmp_path / "c.obj")
    assert len(groups["B0001_windows"]) == n
    assert np.allclose(v[np.array(groups["B0001_windows"]).ravel(), 1], OFFSET[1], atol=1e-5)
    assert " windows" not in export_buildings(workspace.root, "obj", tmp_path / "d.obj", with_windows=False)


def test_stage_cancels_and_needs_textures(workspace, tmp_path):
    stage = get_stage("windows")
    ctx = RunContext()
    ctx.cancel()
    with pytest.raises(Cancelled):
        stage.run(workspace, stage.make_config({}), ctx)
    empty = Workspace.create(tmp_path / "empty", crs="EPSG:25832")
    save_buildings(empty.path("buildings", "buildings.json"), [box()], empty.crs)
    with pytest.raises(WorkspaceError, match="texture"):
        stage.run(empty, stage.make_config({}), RunContext())

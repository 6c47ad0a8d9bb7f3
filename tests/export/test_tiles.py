"""3D Tiles 1.1 export: every glTF vertex, taken through the tileset's frame to geocentric coordinates and back to
the project CRS with pyproj, lands on a model vertex (1 mm); boxes hold the tiles; tiles split by size."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from pyproj import Transformer

from oblique_city.core.buildings.model import BuildingModel, Surface
from oblique_city.core.errors import ComputationError, ConfigError
from oblique_city.core.export.tiles import GLTF_FROM_LOCAL, write_3dtiles

CRS = "EPSG:25832"


def _box(bid: str, x0: float, y0: float, h: float) -> BuildingModel:
    xy = np.array([[0, 0], [12, 0], [12, 9], [0, 9]], float) + [x0, y0]
    v = np.vstack([np.c_[xy, np.full(4, 150.0)], np.c_[xy, np.full(4, 150.0 + h)]])
    surfaces = [Surface(f"{bid}g", "ground", (0, 3, 2, 1)), Surface(f"{bid}r", "roof", (4, 5, 6, 7))]
    surfaces += [Surface(f"{bid}w{i}", "wall", (i, (i + 1) % 4, 4 + (i + 1) % 4, 4 + i)) for i in range(4)]
    return BuildingModel(bid, v, surfaces, "2d", "", xy, np.zeros(4), np.zeros((0, 4)), {"closed": True})


def _world_vertices(folder, name: str, transform: np.ndarray) -> np.ndarray:
    scene = trimesh.load(folder / name, force="scene", process=False)
    gl = np.concatenate([g.vertices for g in scene.geometry.values()])
    local = gl @ GLTF_FROM_LOCAL  # back to the z-up frame (the runtime's y-up -> z-up turn)
    ecef = local @ transform[:3, :3].T + transform[:3, 3]
    x, y, z = Transformer.from_crs("EPSG:4978", CRS, always_xy=True).transform(*ecef.T)
    return np.column_stack([x, y, z]), local


def test_tiles_carry_the_true_geometry(tmp_path):
    models = [_box("B1", 512000.0, 5403000.0, 7.0), _box("B2", 512040.0, 5403020.0, 12.0),
              _box("B3", 512600.0, 5403010.0, 9.0)]  # 600 m east: a tile of its own
    files = write_3dtiles(tmp_path, models, CRS, tile_size=250.0)
    ts = json.loads((tmp_path / "tileset.json").read_text())
    assert ts["asset"]["version"] == "1.1" and files[0] == "tileset.json" and len(files) == 5
    root = ts["root"]
    transform = np.array(root["transform"]).reshape(4, 4).T  # column-major
    assert np.abs(transform[:3, :3] @ transform[:3, :3].T - np.eye(3)).max() < 1e-12
    assert np.linalg.norm(transform[:3, 3]) == pytest.approx(6.37e6, rel=0.01)  # on the earth's surface
    # each tile: the LoD 1.2 blocks, replaced by the LoD2 models within their geometric error
    tiles = root["children"]
    assert [t["refine"] for t in tiles] == ["REPLACE"] * 2 and all(t["children"][0]["geometricError"] == 0
                                                                   for t in tiles)
    assert tiles[0]["geometricError"] == pytest.approx(0.5)  # flat roofs: the blocks are the models
    contents = [t["children"][0]["content"]["uri"] for t in tiles]
    for child, uri, members in zip(tiles, contents, (models[:2], models[2:]), strict=True):
        tile = transform @ np.array(child["transform"]).reshape(4, 4).T  # the tile's shift within the root frame
        blocks, _ = _world_vertices(tmp_path, child["content"]["uri"], tile)
        assert np.abs(np.unique(np.round(blocks[:, 2], 2)) - sorted({150.0, *(m.vertices[:, 2].max() for m in
                                                                             members)})).max() < 2e-3
        child = child["children"][0]
        world, local = _world_vertices(tmp_path, uri, tile)
        truth = np.concatenate([m.vertices for m in members])
        d = np.linalg.norm(world[:, None, :] - truth[None, :, :], axis=2)
        assert d.min(1).max() < 1e-3 and d.min(0).max() < 1e-3  # every vertex on a model vertex and back
        box = np.array(child["boundingVolume"]["box"])
        assert np.all(np.abs(local - box[:3]) <= np.abs(box[[3, 7, 11]]) + 1e-4)  # float32 positions
        assert np.abs(local).max() < 30.0  # small numbers around the tile's own centre
    # up in the frame is up on the earth: roofs stand 7-12 m above the ground in the frame's z
    world, local = _world_vertices(tmp_path, contents[0], transform @ np.array(tiles[0]["transform"]).reshape(4, 4).T)
    assert np.ptp(local[:, 2]) == pytest.approx(12.0, abs=0.01)


def test_export_command_writes_a_folder(tmp_path):
    from oblique_city.core.buildings.model import save_buildings
    from oblique_city.core.export.command import export_buildings
    from oblique_city.core.pipeline import Workspace

    ws = Workspace.create(tmp_path / "ws", crs=CRS)
    save_buildings(ws.path("buildings", "buildings.json"), [_box("B1", 512000.0, 5403000.0, 7.0)], ws.crs)
    summary = export_buildings(ws.root, "3dtiles", tmp_path / "tiles")
    assert "(1 tiles, each as LoD 1.2 blocks and LoD2 models" in summary
    assert (tmp_path / "tiles" / "tileset.json").exists()
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ConfigError, match="folder"):
        export_buildings(ws.root, "3dtiles", tmp_path / "afile")
    with pytest.raises(ComputationError, match="no buildings"):
        write_3dtiles(tmp_path / "empty", [], CRS)


def test_height_offset_lifts_the_tiles_along_the_vertical(tmp_path):
    """Orthometric heights plus the geoid undulation: the same tiles 47.5 m higher on the ellipsoid."""
    model = _box("B1", 512000.0, 5403000.0, 7.0)
    write_3dtiles(tmp_path / "a", [model], CRS)
    write_3dtiles(tmp_path / "b", [model], CRS, height_offset=47.5)
    worlds = []
    for folder in ("a", "b"):
        ts = json.loads((tmp_path / folder / "tileset.json").read_text())
        child = ts["root"]["children"][0]
        tile = np.array(ts["root"]["transform"]).reshape(4, 4).T @ np.array(child["transform"]).reshape(4, 4).T
        worlds.append(_world_vertices(tmp_path / folder, child["content"]["uri"], tile)[0])
    d = worlds[1] - worlds[0]
    assert np.abs(d[:, :2]).max() < 1e-3 and np.abs(d[:, 2] - 47.5).max() < 1e-3


@pytest.mark.parametrize(("fmt", "name", "offset", "message"), [
    ("3dtiles", "t", float("nan"), "the height offset is the geoid undulation in metres, within \\+-200; got nan"),
    ("3dtiles", "t", 1e30, "within \\+-200; got 1e\\+30"),
    ("obj", "", 0.0, "is a folder: give the obj file's name"),
])
def test_export_refuses_a_bad_offset_or_a_folder_for_a_file(tmp_path, fmt, name, offset, message):
    """A height offset that is no geoid undulation (NaN, 1e30 m) and a folder given for a file are refused before
    anything is read or written (a NaN offset failed in the coordinate transformation, 1e30 m was written, a folder
    raised IsADirectoryError)."""
    from oblique_city.core.export.command import export_buildings

    with pytest.raises(ConfigError, match=message):
        export_buildings(tmp_path / "no-workspace", fmt, tmp_path / name, height_offset=offset)
    assert sorted(p.name for p in tmp_path.iterdir()) == []

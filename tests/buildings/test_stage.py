"""Detection on a small scene and the ``buildings`` stage on a workspace with dense points and surface rasters."""

from __future__ import annotations

import json

import numpy as np
import pytest

from oblique_city.core.buildings.detect import building_labels, points_per_building
from oblique_city.core.buildings.model import load_buildings
from oblique_city.core.buildings.synthetic import parametric_buildings
from oblique_city.core.io.geotiff import write_geotiff
from oblique_city.core.model.raster import Raster
from oblique_city.core.pipeline import RunContext, Workspace
from oblique_city.core.pipeline.registry import get_stage

CELL = 0.2


@pytest.fixture(scope="module")
def scene():
    """A gabled and a stepped building with a 'tree' (a rough 6 m blob) between them: points, DSM and DTM."""
    rng = np.random.default_rng(5)
    blds = [b for b in parametric_buildings() if b.name in ("gabled", "stepped_flat")]
    xyz = np.concatenate([b.sample(20.0, 0.04, rng) for b in blds])
    x0, y0, x1, y1 = 40.0, 110.0, 130.0, 230.0
    cols, rows = int((x1 - x0) / CELL), int((y1 - y0) / CELL)
    grid = Raster(np.zeros((rows, cols)), x0, y1, CELL, "EPSG:25832")
    xc, yc = grid.cell_centers()
    X, Y = np.meshgrid(xc, yc)
    xy = np.column_stack([X.ravel(), Y.ravel()])
    z = np.max([b.height(xy) for b in blds], axis=0).reshape(rows, cols)
    tree = (X - 100.0) ** 2 + (Y - 180.0) ** 2 < 3.5 ** 2
    z[tree] = 6.0 + rng.uniform(-1.5, 1.5, tree.sum())
    dsm = Raster(z + rng.normal(0, 0.02, z.shape), grid.x0, grid.y0, CELL, grid.crs)
    dtm = Raster(np.zeros_like(z), grid.x0, grid.y0, CELL, grid.crs)
    return blds, xyz, dsm, dtm


def test_detection_finds_the_buildings_and_rejects_the_tree(scene):
    blds, xyz, dsm, dtm = scene
    labels, n, stats = building_labels(dsm, dtm)
    assert n == 2 and stats["vegetation"] == 1
    dets = points_per_building(xyz, labels, dsm, dtm)
    for d in dets:
        centre = xyz[d.indices, :2].mean(0)
        # each point set belongs to one building: its points lie around that building's footprint
        dist = [np.linalg.norm(b.footprint.mean(0) - centre) for b in blds]
        assert min(dist) < 3.0
    above = xyz[:, 2] > 0.5  # every roof and wall point is assigned (ground beyond the margin is not)
    assigned = np.zeros(len(xyz), bool)
    for d in dets:
        assigned[d.indices] = True
    assert assigned[above].mean() > 0.99


def test_buildings_stage_writes_models_and_report(scene, tmp_path):
    blds, xyz, dsm, dtm = scene
    ws = Workspace.create(tmp_path / "ws", crs="EPSG:25832")
    ws.stage_dir("dense")
    np.savez(ws.path("dense", "points.npz"), xyz=xyz, removed=np.zeros(len(xyz), np.uint8))
    ws.stage_dir("surface")
    write_geotiff(ws.path("surface", "dsm.tif"), Raster(dsm.data.astype(np.float32), dsm.x0, dsm.y0, CELL, dsm.crs))
    write_geotiff(ws.path("surface", "dtm.tif"), Raster(dtm.data.astype(np.float32), dtm.x0, dtm.y0, CELL, dtm.crs))
    stage = get_stage("buildings")
    res = stage.run(ws, stage.make_config({}), RunContext())
    assert res.metrics["buildings"] == 2 and res.metrics["closed"] == 2
    models, crs = load_buildings(ws.path("buildings", "buildings.json"))
    assert crs == "EPSG:25832"
    assert sorted(m.path for m in models) == ["2d", "volumetric"]
    report = json.loads(ws.path("buildings", "report.json").read_text())
    assert report["failures"] == [] and len(report["buildings"]) == 2
    gable = next(m for m in models if m.path == "2d")
    assert np.allclose(np.sort(gable.overhangs), 0.6, atol=2 * CELL)


def test_user_footprints_collect_the_points_and_bad_files_name_the_field(scene, tmp_path):
    from oblique_city.core.buildings.detect import points_per_footprint, read_footprints
    from oblique_city.core.errors import InputError

    blds, xyz, _, dtm = scene
    gj = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Polygon",
                                         "coordinates": [b.footprint.tolist() + [b.footprint[0].tolist()]]}}
        for b in blds]}
    path = tmp_path / "fp.geojson"
    path.write_text(json.dumps(gj))
    rings = read_footprints(path)
    assert len(rings) == 2 and np.allclose(rings[0], blds[0].footprint)
    dets = points_per_footprint(xyz, rings, dtm)
    for b, d in zip(blds, dets):
        p = xyz[d.indices]
        assert np.linalg.norm(p[:, :2].mean(0) - b.footprint.mean(0)) < 2.0
        assert (p[:, 2] > 0.5).sum() > 1000
    gj["features"][1]["geometry"] = {"type": "LineString", "coordinates": [[0, 0], [1, 1]]}
    path.write_text(json.dumps(gj))
    with pytest.raises(InputError, match="fp.geojson.*geometry"):
        read_footprints(path)
    ring = [[0, 0], [1, 0], [1, None]]
    for bad, field in (([gj], "type"), ({"type": "FeatureCollection", "features": [7]}, "geometry"),
                       ({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [ring]}}, "coordinates")):
        path.write_text(json.dumps(bad))
        with pytest.raises(InputError, match=f"fp.geojson, field '{field}'"):
            read_footprints(path)

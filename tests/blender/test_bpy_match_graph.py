"""The connectivity graph of the ``match`` stage in Blender: lines between camera centres.

A graph written by the core's own writer (:meth:`ConnectivityGraph.to_dict`) over a three-image UTM block, and a
fourth image without a centre: checked are the vertices at the camera centres within 1 mm, the edges between the right
centres with their match counts and overlaps, the pairs of the unplaced image left out, Build Scene running the
builder once ``match`` is done, the Triangulation panel's line on the graph, and bad files refused with the file and
line named."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_bpy_ui import draw

from oblique_city.core.errors import InputError
from oblique_city.core.matching.graph import ConnectivityGraph
from oblique_city.core.pipeline import Workspace
from oblique_city.core.pipeline.atomic import write_json

pytestmark = pytest.mark.xdist_group("bpy")


@pytest.fixture
def ws(tmp_path, utm_block):
    w = Workspace.create(tmp_path / "ws", crs=utm_block.crs)
    w.save_block(utm_block)
    graph = ConnectivityGraph(image_ids=list(utm_block.images), edges=np.array([[0, 1], [0, 2], [1, 2], [2, 3]]),
                              overlap=np.array([0.61, 0.42, 0.25, 0.5]), matches=np.array([812, 455, -1, 90]))
    doc = graph.to_dict(utm_block)
    doc["nodes"].append({"id": "lost", "view": None, "centre": None})  # an image without a centre
    w.stage_dir("matching")
    write_json(w.path("matching/graph.json"), doc)
    w.write_state({"match": {"status": "done"}})
    return w, utm_block


def test_graph_is_drawn_between_camera_centres(addon, ws):
    bpy = addon
    from oblique_city.addon import builders, georef, layers_match

    w, block = ws
    scene = bpy.context.scene
    summary = layers_match.build_graph(scene, w)
    assert summary == "3 image pairs between 3 cameras, median 633 matches"
    obj = bpy.data.objects["Connectivity graph"]
    mesh = obj.data
    centres = np.array([img.pose_approx.C for img in block.images.values()])
    assert np.abs(georef.mesh_vertices_world(scene, obj) - centres).max() < 1e-3
    verts = np.empty(len(mesh.edges) * 2, np.int32)
    mesh.edges.foreach_get("vertices", verts)
    assert verts.reshape(-1, 2).tolist() == [[0, 1], [0, 2], [1, 2]]
    matches = np.empty(3, np.int32)
    mesh.attributes["matches"].data.foreach_get("value", matches)
    overlap = np.empty(3, np.float32)
    mesh.attributes["overlap"].data.foreach_get("value", overlap)
    assert matches.tolist() == [812, 455, -1] and np.allclose(overlap, [0.61, 0.42, 0.25])
    assert obj["oc_graph_pairs"] == 3
    # Build Scene runs the builder of a finished match stage
    messages = builders.build_scene(scene, w)
    assert "match: 3 image pairs between 3 cameras, median 633 matches" in messages
    assert len([o for o in bpy.data.objects if o.name.startswith("Connectivity graph")]) == 1


def test_bad_graph_files_are_refused(addon, ws):
    bpy = addon
    from oblique_city.addon import layers_match

    w = ws[0]
    path = w.path("matching/graph.json")
    path.write_text('{"nodes": [\n  {"id": "a"},\n  oops\n]}')
    with pytest.raises(InputError) as e:
        layers_match.build_graph(bpy.context.scene, w)
    assert e.value.line == 3 and str(path) in str(e.value)
    path.write_text(json.dumps({"nodes": [{"id": "a", "centre": [1.0, 2.0, 3.0]}],
                                "edges": [{"a": 0, "b": 4, "overlap": 0.3, "matches": 10}]}))
    with pytest.raises(InputError, match="beyond the 1 nodes"):
        layers_match.build_graph(bpy.context.scene, w)
    path.unlink()
    with pytest.raises(InputError, match="run the 'match' stage"):
        layers_match.build_graph(bpy.context.scene, w)


def test_triangulation_panel_shows_the_graph(addon, ws):
    """Before any adjustment the Triangulation panel already tells the graph's size: 4 pairs of 4 images, the median
    of the three matched pairs' counts (812, 455, 90)."""
    bpy = addon
    from oblique_city.panels import STAGE_PANEL_CLASSES

    bpy.context.scene.oblique_city.workspace = str(ws[0].root)
    panel = next(c for c in STAGE_PANEL_CLASSES if c.bl_label == "Triangulation")
    labels = [e[1] for e in draw(panel, bpy.context) if e[0] == "label"]
    assert "Connectivity graph: 4 image pairs of 4 images, median 455 matches" in labels
    assert "no triangulation report yet" in labels


def test_triangulation_panel_shows_the_target_measurements_and_match_options_reach_the_project(addon, ws):
    """With ``matching/targets.json`` written by the core (``all`` mode: two measurements, one of them beside an
    imported one 0.3 px away, one image without the target), the panel tells what was measured; the match stage's
    options are edited in its panel and land in ``project.toml``."""
    bpy = addon
    from oblique_city.core.pipeline.registry import get_stage
    from oblique_city.panels import STAGE_PANEL_CLASSES

    w = ws[0]
    record = {"mode": "all", "points": {"T1": {"kind": "control", "imported": ["a"], "missed": ["c"], "measured": {
        "a": {"uv": [10.3, 20.0], "predicted": [11, 19], "score": 0.97, "std_px": 0.02, "imported_difference_px": 0.3},
        "b": {"uv": [30.0, 40.0], "predicted": [31, 39], "score": 0.95, "std_px": 0.03}}}},
        "observations": {"T1": {"a": [10.3, 20.0], "b": [30.0, 40.0]}}}
    write_json(w.path("matching/targets.json"), record)
    bpy.context.scene.oblique_city.workspace = str(w.root)
    panel = next(c for c in STAGE_PANEL_CLASSES if c.bl_label == "Triangulation")
    labels = [e[1] for e in draw(panel, bpy.context) if e[0] == "label"]
    assert "Targets measured: 2 (1 not found, 0.30 px RMS from imported)" in labels
    opts = bpy.context.scene.oblique_city.stage_options.match
    opts.targets = "missing"
    opts.target_search_px = 12.0
    stored = Workspace.open(w.root).stage_options("match")
    assert stored["targets"] == "missing" and stored["target_search_px"] == 12.0
    assert get_stage("match").make_config(stored).targets == "missing"

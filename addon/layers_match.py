"""Results of the ``match`` stage in Blender: the connectivity graph as lines between camera centres.

:func:`build_graph` draws ``matching/graph.json`` (:func:`core.matching.graph.read_graph`) as one mesh of loose
edges, "Connectivity graph" in the "Connectivity graph" collection: a vertex per image at its camera centre (at
``world - origin``, :mod:`.georef`) and an edge per image pair the tie points were matched on, with EDGE attributes
``matches`` (INT, the pair's verified matches; -1 when not matched) and ``overlap`` (FLOAT, the footprints' overlap
share). Images without a centre are left out with their pairs. :func:`graph_summary` gives the Triangulation panel
its line on the graph.
"""

from __future__ import annotations

import numpy as np

from ..core.io.validate import read_json
from ..core.matching import targets
from ..core.matching.graph import read_graph
from ..core.pipeline import Workspace
from . import georef
from .layers import mesh_from_arrays
from .scene_tree import layer_collection

GRAPH_FILE = "matching/graph.json"
TARGETS_FILE = targets.TARGETS_FILE


def build_graph(scene, ws: Workspace) -> str:
    """The connectivity graph as lines between camera centres; returns a one-line summary. A missing or bad graph
    file raises the core's :class:`InputError`."""
    import bpy

    graph, centres = read_graph(ws.path(GRAPH_FILE))
    placed = np.all(np.isfinite(centres), axis=1)
    keep = placed[graph.edges].all(axis=1) if len(graph.edges) else np.zeros(0, bool)
    index = np.cumsum(placed) - 1  # node -> vertex
    edges = index[graph.edges[keep]]
    xyz = centres[placed]
    coll = layer_collection(scene, "graph", "Connectivity graph")
    if len(xyz):
        georef.ensure_georef(scene, ws.crs, xyz)
    mesh = mesh_from_arrays("Connectivity graph", georef.world_to_local(scene, xyz) if len(xyz) else xyz)
    mesh.edges.add(len(edges))
    mesh.edges.foreach_set("vertices", edges.astype(np.int32).ravel())
    mesh.attributes.new("matches", "INT", "EDGE").data.foreach_set("value", graph.matches[keep].astype(np.int32))
    mesh.attributes.new("overlap", "FLOAT", "EDGE").data.foreach_set("value",
                                                                     graph.overlap[keep].astype(np.float32))
    mesh.update()
    obj = bpy.data.objects.new("Connectivity graph", mesh)
    obj["oc_graph_pairs"] = len(edges)
    coll.objects.link(obj)
    matched = graph.matches[keep][graph.matches[keep] >= 0]
    median = f", median {int(np.median(matched))} matches" if len(matched) else ""
    return f"{len(edges)} image pairs between {len(xyz)} cameras{median}"


def graph_summary(path) -> dict:
    """Of a graph file: its image pairs (``pairs``), the images they join (``images``) and the median of the matched
    pairs' match counts (``median_matches``, None when none was matched). Raises the core's :class:`InputError`."""
    graph, _ = read_graph(path)
    matched = graph.matches[graph.matches >= 0]
    return {"pairs": len(graph.edges), "images": len(np.unique(graph.edges)),
            "median_matches": int(np.median(matched)) if len(matched) else None}


def targets_summary(path) -> dict:
    """Of the match stage's target measurements (``matching/targets.json``): :func:`.core.matching.targets.
    target_summary`. Raises the core's :class:`InputError` for a file that is missing or not JSON."""
    return targets.target_summary(read_json(path))

"""Connectivity graph of an image block from its approximate exterior orientation.

Each image's footprint is its border projected on a reference height (or, with a DTM, on the DTM's mean
height under the image). Two images are connected when their footprints overlap by at least
``min_overlap`` (intersection area over the smaller footprint) and they look in similar directions (optical
axes within ``max_axis_angle_deg``) or one of them is nadir. Edges later carry their match counts; pairs with
fewer than ``min_matches`` are dropped. The graph is saved as JSON (nodes with centres and views, edges with
overlap and matches) so Blender can draw it as lines between camera centres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.projection import image_footprint
from ..io.validate import read_json
from ..model import ImageBlock, Raster


@dataclass(frozen=True)
class GraphOptions:
    """min_overlap : share of the smaller footprint; max_axis_angle_deg : similar look directions;
    z_ref : reference height (None: DTM mean or 0); max_neighbours : per image, the most overlapping kept."""

    min_overlap: float = 0.2
    max_axis_angle_deg: float = 50.0
    z_ref: float | None = None
    max_neighbours: int = 40


@dataclass(eq=False)
class ConnectivityGraph:
    """Nodes are image ids; ``edges (e, 2)`` index ``image_ids``; ``overlap (e,)``; ``matches (e,)`` (-1: not
    matched yet)."""

    image_ids: list[str]
    edges: np.ndarray
    overlap: np.ndarray
    matches: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __post_init__(self) -> None:
        self.edges = np.asarray(self.edges, np.int64).reshape(-1, 2)
        self.overlap = np.asarray(self.overlap, np.float64)
        if len(self.matches) != len(self.edges):
            self.matches = np.full(len(self.edges), -1, np.int64)

    def drop_weak(self, min_matches: int) -> int:
        """Remove matched edges with fewer than ``min_matches`` matches; returns how many were removed."""
        keep = (self.matches < 0) | (self.matches >= min_matches)
        n = int((~keep).sum())
        self.edges, self.overlap, self.matches = self.edges[keep], self.overlap[keep], self.matches[keep]
        return n

    def to_dict(self, block: ImageBlock) -> dict:
        nodes = []
        for iid in self.image_ids:
            img = block.images[iid]
            p = img.pose
            nodes.append({"id": iid, "view": img.view, "centre": None if p is None else p.C.tolist()})
        return {"format": "oblique_city.graph", "nodes": nodes,
                "edges": [{"a": int(a), "b": int(b), "overlap": round(float(o), 4), "matches": int(m)}
                          for (a, b), o, m in zip(self.edges, self.overlap, self.matches)]}

    @classmethod
    def from_dict(cls, d: dict) -> ConnectivityGraph:
        e = d.get("edges", [])
        return cls(image_ids=[n["id"] for n in d["nodes"]], edges=np.array([[x["a"], x["b"]] for x in e]),
                   overlap=np.array([x["overlap"] for x in e]), matches=np.array([x["matches"] for x in e]))


def read_graph(path: str | Path) -> tuple[ConnectivityGraph, np.ndarray]:
    """The graph of ``matching/graph.json`` (as :meth:`ConnectivityGraph.to_dict` writes it) and its nodes' camera
    centres ``(n, 3)`` (world; NaN for a node without one). Raises :class:`InputError` naming the file, and the line
    or the field, for a missing, malformed or inconsistent file."""
    doc = read_json(path, "no connectivity graph (run the 'match' stage)")
    try:
        graph = ConnectivityGraph.from_dict(doc)
        centres = np.array([np.full(3, np.nan) if n.get("centre") is None else np.asarray(n["centre"], np.float64)
                            for n in doc["nodes"]]).reshape(-1, 3)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"not a connectivity graph ({e})", path, field=str(e)) from None
    if len(graph.edges) and (graph.edges.min() < 0 or graph.edges.max() >= len(graph.image_ids)):
        raise InputError(f"an edge names a node beyond the {len(graph.image_ids)} nodes", path, field="edges")
    return graph, centres


def _polygon_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def convex_overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection area of two convex polygons ``(k, 2)`` over the smaller one's area."""
    import cv2

    if len(a) < 3 or len(b) < 3:
        return 0.0
    ca = cv2.convexHull(a.astype(np.float32))
    cb = cv2.convexHull(b.astype(np.float32))
    area, _ = cv2.intersectConvexConvex(ca, cb)
    small = min(cv2.contourArea(ca), cv2.contourArea(cb))
    return float(area / small) if small > 0 else 0.0


def footprints(block: ImageBlock, image_ids: list[str], z_ref: float | None = None,
               dtm: Raster | None = None) -> list[np.ndarray]:
    """Footprint polygons ``(k, 2)`` of the images on ``z_ref`` (or the DTM's mean height)."""
    z = z_ref
    if z is None:
        z = float(np.nanmean(dtm.data)) if dtm is not None else 0.0
    out = []
    for iid in image_ids:
        img = block.images[iid]
        pose = img.pose
        out.append(np.zeros((0, 2)) if pose is None else image_footprint(block.camera_of(img), pose, z))
    return out


def build_graph(block: ImageBlock, opt: GraphOptions = GraphOptions(), dtm: Raster | None = None,
                image_ids: list[str] | None = None) -> ConnectivityGraph:
    """The connectivity graph (see the module docstring)."""
    from scipy.spatial import cKDTree

    ids = list(block.images) if image_ids is None else list(image_ids)
    fps = footprints(block, ids, opt.z_ref, dtm)
    centre = np.array([f.mean(0) if len(f) else [np.nan, np.nan] for f in fps])
    radius = np.array([np.linalg.norm(f - f.mean(0), axis=1).max() if len(f) else 0.0 for f in fps])
    axes = np.array([block.images[i].pose.R[2] if block.images[i].pose is not None else [0, 0, 0] for i in ids])
    nadir = np.array([block.images[i].view == "nadir" for i in ids])
    ok = np.isfinite(centre[:, 0])
    tree = cKDTree(centre[ok])
    idx = np.flatnonzero(ok)
    cos_max = np.cos(np.radians(opt.max_axis_angle_deg))
    edges, overlaps = [], []
    rmax = radius.max(initial=0.0)
    for k in idx:
        cand = idx[tree.query_ball_point(centre[k], radius[k] + rmax)]
        cand = cand[cand > k]
        cand = cand[np.linalg.norm(centre[cand] - centre[k], axis=1) < radius[cand] + radius[k]]
        similar = (axes[cand] @ axes[k] >= cos_max) | nadir[cand] | nadir[k]
        mine = []
        for j in cand[similar]:
            o = convex_overlap(fps[k], fps[j])
            if o >= opt.min_overlap:
                mine.append((o, j))
        mine.sort(reverse=True)
        for o, j in mine[:opt.max_neighbours]:
            edges.append((k, j))
            overlaps.append(o)
    return ConnectivityGraph(image_ids=ids, edges=np.array(edges, np.int64).reshape(-1, 2),
                             overlap=np.array(overlaps))

"""A closed polyhedral hull from a set of planes: the arrangement of the planes inside a box, cells kept by an
occupancy test (and, where points on the surface are given, barely kept cells dropped when the points say the
surface runs below them), the boundary between kept and dropped cells.

Every plane splits every cell it crosses (a full arrangement), so two neighbouring cells share exactly the same
facet and vertices are the intersections of plane triplets (k-nodes where more planes meet, consolidated by
distance). The boundary facets of the kept cells form a closed 2-manifold surface; facets of one plane are
merged into polygons and vertices that only subdivide a straight edge are removed where no other polygon uses
them. Used by both reconstruction paths: the 2D path passes wall planes from the contour and roof planes from
the label grid with an occupancy from the contour and the labels; the volumetric fallback passes the planes it
found in the voxels with an occupancy from the points.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .model import ring_area_vector

EPS = 1e-7


@dataclass
class Hull:
    """vertices : (n, 3) float64; faces : list of (plane id, ring of vertex indices, counter-clockwise seen from
    outside); plane ids index the input planes, negative ids are the box's sides."""

    vertices: np.ndarray
    faces: list[tuple[int, list[int]]]
    n_cells: int
    n_inside: int


@dataclass(frozen=True)
class SurfaceSupport:
    """The observed surface's points ``xyz (n, 3)`` as a second judge of the cells the occupancy keeps barely: a
    kept cell whose occupancy is below ``max_occupancy`` is dropped when its faces shared with kept cells carry more
    than ``ratio`` times the points per square metre (within ``tol`` of a face, over its polygon) that its other
    faces carry. Points lie on the surface, so the surface runs through the faces that carry them."""

    xyz: np.ndarray = field(repr=False)
    tol: float
    ratio: float
    max_occupancy: float


def face_density(poly: np.ndarray, xyz: np.ndarray, tol: float) -> tuple[int, float]:
    """The points of ``xyz (n, 3)`` within ``tol`` of the convex polygon ``poly (k, 3)`` (across its plane, inside
    its outline) and the polygon's area (m^2)."""
    av = ring_area_vector(poly)
    area = float(np.linalg.norm(av))
    if area < EPS:
        return 0, 0.0
    n = av / area
    q = xyz[np.abs((xyz - poly[0]) @ n) < tol]
    edges = np.roll(poly, -1, axis=0) - poly
    inside = np.ones(len(q), bool)
    for a, e in zip(poly, edges):
        inside &= np.cross(e, q - a) @ n >= -EPS
    return int(inside.sum()), area


def _drop_unsupported(cells: list[Cell], frac: np.ndarray, keep: np.ndarray, neighbour: list[list[int]],
                      surface: SurfaceSupport) -> np.ndarray:
    """``keep (c,)`` with the barely kept cells the surface points refuse dropped (:class:`SurfaceSupport`), the
    least occupied first and again until none changes: a dropped cell turns its neighbours' shared faces into
    boundary. ``neighbour[ci][j]``: the cell across face ``j`` of cell ``ci`` (-1: none)."""
    keep = keep.copy()
    xyz = surface.xyz
    density: dict[int, list[tuple[int, float]]] = {}
    for _ in range(len(cells)):
        changed = False
        for ci in sorted(np.flatnonzero(keep & (frac < surface.max_occupancy)), key=lambda c: frac[c]):
            if ci not in density:
                v = np.concatenate([f for _, f in cells[ci]])
                near = xyz[np.all((xyz >= v.min(0) - surface.tol) & (xyz <= v.max(0) + surface.tol), axis=1)]
                density[ci] = [face_density(f, near, surface.tol) for _, f in cells[ci]]
            shared = np.array([nb >= 0 and keep[nb] for nb in neighbour[ci]])
            if not shared.any() or shared.all():
                continue
            n, a = np.array(density[ci], dtype=np.float64).T
            inner = n[shared].sum() / max(a[shared].sum(), EPS)
            if inner > surface.ratio * n[~shared].sum() / max(a[~shared].sum(), EPS):
                keep[ci] = False
                changed = True
        if not changed:
            break
    return keep


def _clip(poly: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Split a convex polygon (k, 3) with signed distances s (k,) into its s >= 0 and s <= 0 parts."""
    pos, neg, cut = [], [], []
    k = len(poly)
    for i in range(k):
        a, b = poly[i], poly[(i + 1) % k]
        sa, sb = s[i], s[(i + 1) % k]
        if sa >= -EPS:
            pos.append(a)
        if sa <= EPS:
            neg.append(a)
        if abs(sa) <= EPS:
            cut.append(a)
        if (sa > EPS and sb < -EPS) or (sa < -EPS and sb > EPS):
            t = sa / (sa - sb)
            x = a + t * (b - a)
            pos.append(x)
            neg.append(x)
            cut.append(x)
    return np.asarray(pos), np.asarray(neg), cut


def _order_on_plane(pts: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Points on a plane ordered counter-clockwise seen from the side ``normal`` points to (duplicates dropped)."""
    c = pts.mean(0)
    u = pts[np.argmax(np.linalg.norm(pts - c, axis=1))] - c
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    ang = np.arctan2((pts - c) @ v, (pts - c) @ u)
    pts = pts[np.argsort(ang)]
    keep = [0]
    for i in range(1, len(pts)):
        if np.linalg.norm(pts[i] - pts[keep[-1]]) > 1e-9:
            keep.append(i)
    if len(keep) > 1 and np.linalg.norm(pts[keep[-1]] - pts[keep[0]]) <= 1e-9:
        keep.pop()
    return pts[keep]


Cell = list[tuple[int, np.ndarray]]


def _split(cell: Cell, plane: np.ndarray, pid: int) -> tuple[Cell, Cell] | None:
    allv = np.concatenate([f for _, f in cell])
    s_all = allv @ plane[:3] + plane[3]
    if s_all.min() > -1e-6 or s_all.max() < 1e-6:
        return None
    pos: Cell = []
    neg: Cell = []
    cut_pts: list[np.ndarray] = []
    for fid, poly in cell:
        s = poly @ plane[:3] + plane[3]
        p, n, cut = _clip(poly, s)
        if len(p) >= 3 and np.abs(s).max() > EPS and (s > EPS).any():
            pos.append((fid, p))
        if len(n) >= 3 and (s < -EPS).any():
            neg.append((fid, n))
        cut_pts.extend(cut)
    if len(cut_pts) < 3:
        return None
    cap = _order_on_plane(np.asarray(cut_pts), plane[:3])
    if len(cap) < 3:
        return None
    pos.append((pid, cap[::-1]))  # outward of the positive cell is -n
    neg.append((pid, cap))
    return pos, neg


def _box(lo: np.ndarray, hi: np.ndarray) -> Cell:
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    P = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]])
    rings = [(-1, [0, 3, 2, 1]), (-2, [4, 5, 6, 7]), (-3, [0, 1, 5, 4]), (-4, [1, 2, 6, 5]),
             (-5, [2, 3, 7, 6]), (-6, [3, 0, 4, 7])]
    return [(fid, P[r]) for fid, r in rings]


def unique_planes(planes: np.ndarray, angle_deg: float = 1.0, offset: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """The planes of ``planes (n, 4)`` that do not repeat an earlier one (either orientation, within ``angle_deg``
    and ``offset`` m) -> ``(k, 4)``, and for each given plane the index ``(n,) int`` of the kept one it repeats (its
    own where it is kept)."""
    out: list[np.ndarray] = []
    index = np.zeros(len(planes), np.int64)
    cos_t = np.cos(np.radians(angle_deg))
    for i, p in enumerate(planes):
        for j, q in enumerate(out):
            c = p[:3] @ q[:3]
            if abs(c) > cos_t and abs(p[3] - np.sign(c) * q[3]) < offset:
                index[i] = j
                break
        else:
            index[i] = len(out)
            out.append(p)
    return np.asarray(out).reshape(-1, 4), index


def dedupe_planes(planes: np.ndarray, angle_deg: float = 1.0, offset: float = 0.02) -> np.ndarray:
    """Drop planes (k, 4) that repeat an earlier one (either orientation): :func:`unique_planes`' planes."""
    return unique_planes(planes, angle_deg, offset)[0]


def _volume_samples(cells: list[Cell]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples of the convex ``cells`` weighted by the volume they stand for: each cell cut into tetrahedra from
    its centroid over its faces (fan-triangulated), four samples per tetrahedron (halfway between its centroid
    and each corner), a quarter of its volume each. Samples spread over the corners instead (the centroid and
    points towards each vertex) out-voted the bulk of a wedge with their many samples near its thick end: the
    part of a lower roof's cell under an upper roof's overhang kept the whole wedge up to where the upper roof's
    plane, carried on, met the lower roof 2 m further out.

    Returns the samples (s, 3), their weights (s,) and the index of their cell (s,)."""
    tris, own = [], []
    centroids = np.empty((len(cells), 3))
    for ci, cell in enumerate(cells):
        centroids[ci] = np.concatenate([f for _, f in cell]).mean(0)
        for _, poly in cell:
            k = len(poly) - 2
            tris.append(np.stack([np.repeat(poly[:1], k, axis=0), poly[1:-1], poly[2:]], 1))
            own.append(np.full(k, ci))
    t = np.concatenate(tris)  # (q, 3 corners, 3)
    cell_of = np.concatenate(own)
    c = centroids[cell_of]
    vol = np.abs(np.einsum("ij,ij->i", t[:, 0] - c, np.cross(t[:, 1] - c, t[:, 2] - c))) / 6.0
    g = (t.sum(1) + c) / 4.0
    corners = np.concatenate([t[:, 0], t[:, 1], t[:, 2], c])
    return (np.tile(g, (4, 1)) + corners) / 2.0, np.tile(vol / 4.0, 4), np.tile(cell_of, 4)


def build_hull(planes: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               inside: Callable[[np.ndarray], np.ndarray], merge_tol: float = 1e-5,
               surface: SurfaceSupport | None = None) -> Hull:
    """The closed surface of the occupied cells of the arrangement of ``planes (k, 4)`` in the box [lo, hi].

    Parameters
    ----------
    inside : ``inside(xyz (n, 3)) -> (n,) bool`` occupancy of sample points; a cell is kept when most of its
        volume is inside (:func:`_volume_samples`)
    surface : the observed surface's points, which may drop cells kept barely (:class:`SurfaceSupport`)
    """
    cells: list[Cell] = [_box(np.asarray(lo, float), np.asarray(hi, float))]
    for pid, pl in enumerate(planes):
        nxt: list[Cell] = []
        for cell in cells:
            r = _split(cell, pl, pid)
            if r is None:
                nxt.append(cell)
            else:
                nxt.extend(r)
        cells = nxt
    # occupancy: the share of each cell's volume whose samples are inside
    S, weight, own = _volume_samples(cells)
    occ = inside(S).astype(np.float64)
    frac = np.bincount(own, weight * occ, minlength=len(cells)) / np.maximum(
        np.bincount(own, weight, minlength=len(cells)), 1e-300)
    keep = frac > 0.5
    # facets of all cells; vertices consolidated by distance
    facets = [(ci, fid, poly) for ci, cell in enumerate(cells) for fid, poly in cell]
    if not keep.any():
        return Hull(np.zeros((0, 3)), [], len(cells), 0)
    allv = np.concatenate([p for _, _, p in facets])
    tree = cKDTree(allv)
    pairs = tree.query_pairs(merge_tol, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(allv), len(allv)))
    _, comp = connected_components(graph, directed=False)
    _, first = np.unique(comp, return_index=True)
    vid = comp
    vertices = allv[first]
    rings, k = [], 0
    facet_key = []  # the vertex set of each facet: the faces of two neighbouring cells on one plane share it
    for ci, fid, poly in facets:
        ring = [int(x) for x in vid[k:k + len(poly)]]
        k += len(poly)
        ring = [v for i, v in enumerate(ring) if v != ring[i - 1]]
        facet_key.append(frozenset(ring))
        if len(set(ring)) >= 3:
            rings.append((ci, fid, ring))
    if surface is not None:
        across: dict[frozenset, list[int]] = {}
        for (ci, _, _), key in zip(facets, facet_key):
            across.setdefault(key, []).append(ci)
        neighbour: list[list[int]] = [[] for _ in cells]
        for (ci, _, _), key in zip(facets, facet_key):
            neighbour[ci].append(next((c for c in across[key] if c != ci), -1) if len(key) >= 3 else -1)
        keep = _drop_unsupported(cells, frac, keep, neighbour, surface)
    volume = np.zeros(len(cells))
    for ci, _, ring in rings:
        p = vertices[ring]
        volume[ci] += float(np.einsum("j,ij->", p[0], np.cross(p[1:-1], p[2:]))) / 6.0
    cells_at_edge: dict[tuple[int, int], set[int]] = {}
    for ci, _, ring in rings:
        for a, b in zip(ring, ring[1:] + ring[:1]):
            cells_at_edge.setdefault((min(a, b), max(a, b)), set()).add(ci)
    # the boundary between kept and dropped cells; where kept cells touch only along an edge (a checkerboard of
    # sliver cells) the smallest dropped cell at that edge is added, until the surface is a 2-manifold; a cell on
    # the search box is outside the building by construction and never added (it would open the hull there)
    on_box = np.zeros(len(cells), bool)
    on_box[[ci for ci, fid, _ in facets if fid < 0]] = True
    for _ in range(50):
        count: dict[frozenset, int] = {}
        for ci, _, ring in rings:
            if keep[ci]:
                key = frozenset(ring)
                count[key] = count.get(key, 0) + 1
        boundary = [(fid, ring) for ci, fid, ring in rings if keep[ci] and count[frozenset(ring)] == 1]
        directed: dict[tuple[int, int], int] = {}
        for _, ring in boundary:
            for a, b in zip(ring, ring[1:] + ring[:1]):
                directed[(a, b)] = directed.get((a, b), 0) + 1
        bad = [e for e, n in directed.items() if n > 1]
        flips = set()
        for a, b in bad:
            dropped = [c for c in cells_at_edge.get((min(a, b), max(a, b)), ()) if not keep[c] and not on_box[c]]
            if dropped:
                flips.add(min(dropped, key=lambda c: abs(volume[c])))
        if not flips:
            break
        keep[list(flips)] = True
    faces = _merge_coplanar(vertices, boundary)
    faces = _drop_straight_vertices(vertices, faces)
    used = sorted({v for _, r in faces for v in r})
    remap = {v: i for i, v in enumerate(used)}
    return Hull(vertices[used], [(fid, [remap[v] for v in r]) for fid, r in faces], len(cells), int(keep.sum()))


def _single_loop(rings: list[list[int]], members: list[int]) -> list[int] | None:
    """The boundary of the union of facets ``members`` (rings of one plane) as one loop, or None when it is not
    one simple loop (a hole, a pinched vertex, an open chain)."""
    edges = {(a, b) for i in members for a, b in zip(rings[i], rings[i][1:] + rings[i][:1])}
    nxt: dict[int, int] = {}
    for a, b in edges:
        if (b, a) in edges:
            continue
        if a in nxt:
            return None
        nxt[a] = b
    if not nxt:
        return None
    start = next(iter(nxt))
    loop, v = [start], nxt[start]
    while v != start:
        if v not in nxt or len(loop) > len(nxt):
            return None
        loop.append(v)
        v = nxt[v]
    return loop if len(loop) == len(nxt) else None


def _merge_coplanar(vertices: np.ndarray, facets: list[tuple[int, list[int]]]) -> list[tuple[int, list[int]]]:
    """Merge boundary facets (rings into ``vertices (n, 3)``) of one plane into polygons without holes: facets
    sharing an edge are joined as long as the union stays one simple loop (a plane's region around a hole, such as
    a roof around a dormer, ends up in a few pieces)."""
    by_plane: dict[int, list[list[int]]] = {}
    for fid, ring in facets:
        by_plane.setdefault(fid, []).append(ring)
    out = []
    for fid, rings in by_plane.items():
        edge_owner: dict[tuple[int, int], int] = {}
        for i, r in enumerate(rings):
            for a, b in zip(r, r[1:] + r[:1]):
                edge_owner[(a, b)] = i
        shared: dict[tuple[int, int], float] = {}
        for (a, b), i in edge_owner.items():
            j = edge_owner.get((b, a))
            if j is not None and i < j:
                shared[(i, j)] = shared.get((i, j), 0.0) + float(np.linalg.norm(vertices[a] - vertices[b]))
        # the longest shared boundaries first: the cuts left where a hole forbids a merge are short ones
        pairs = sorted(shared, key=lambda ij: (-shared[ij], ij))
        region = list(range(len(rings)))  # facet -> region id (a member facet)
        members = {i: [i] for i in range(len(rings))}
        loops = {i: r for i, r in enumerate(rings)}
        changed = True
        while changed:
            changed = False
            for i, j in pairs:
                ri, rj = region[i], region[j]
                if ri == rj:
                    continue
                loop = _single_loop(rings, members[ri] + members[rj])
                if loop is None:
                    continue
                for k in members[rj]:
                    region[k] = ri
                members[ri] += members.pop(rj)
                loops[ri] = loop
                loops.pop(rj)
                changed = True
        out.extend((fid, loops[r]) for r in sorted(loops))
    return out


def _drop_straight_vertices(vertices: np.ndarray, faces: list[tuple[int, list[int]]],
                            tol: float = 1e-6) -> list[tuple[int, list[int]]]:
    """Remove ring vertices lying on a straight edge when no polygon but the two along that edge uses them."""
    faces = [(fid, list(r)) for fid, r in faces]
    changed = True
    while changed:
        changed = False
        usage: dict[int, list[int]] = {}
        for fi, (_, r) in enumerate(faces):
            for v in r:
                usage.setdefault(v, []).append(fi)
        for v, fs in usage.items():
            if len(fs) != 2:
                continue
            ok = True
            for fi in fs:
                r = faces[fi][1]
                i = r.index(v)
                a, b = vertices[r[i - 1]], vertices[r[(i + 1) % len(r)]]
                d = b - a
                t = np.clip((vertices[v] - a) @ d / (d @ d), 0, 1)
                if len(r) <= 3 or np.linalg.norm(a + t * d - vertices[v]) > tol:
                    ok = False
            if ok:
                for fi in fs:
                    faces[fi][1].remove(v)
                changed = True
                break
    return faces

"""Roof planes and roof topology of a monolithic building (the seed's 2D initial reconstruction, roof).

Cells keep their heights; a regression plane per cell (from its 3x3 block, with one robust re-weighting); roof
cells by a smoothness threshold; labelled groups by normal direction (region growing that also checks the height,
so parallel roofs at different heights stay apart); region growing over roof installations and the unlabelled
cells along ridges (each cell takes the neighbouring label whose plane fits its points best); planes fitted per
group; the topology by a 2x2 window over the label grid (edges and nodes tables, label 0 = outside the contour);
roof-to-facade arrises by scanning the contour; edges by plane intersections; nodes at the centre of the shortest
segment between the edge lines. :func:`check_topology` compares the topology with the intersections and says why
the building must go to the volumetric fallback when they disagree.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .geometry import fit_plane, line_line_closest, plane_line, points_in_polygon

EXPLAINED_SHARE = 1.1
"""A roof group's points are explained by a neighbour's plane (:func:`merge_coplanar`) when their median distance
from it is at most this share of their median distance from their own plane: a robust fit of their own is near the
best plane for them, so a plane within 10 % of it is one the points cannot tell from it (on the demo's church, a
patch of the nave's north slope lay 0.204 m from its own plane, turned 9 degrees, and 0.204 m from the slope's)."""


@dataclass(frozen=True)
class RoofConfig:
    """cell : grid (m); smooth_tol : max RMS of a roof cell's plane (m, 0 = 3 x noise); angle_deg : normal
    grouping threshold; step_tol : height jump that separates groups / marks a discontinuity (m);
    min_group_area : smallest roof plane (m^2); node_tol : allowed distance between a topology node and the
    plane-intersection node (m); segment_tol : longest shortest-segment between edge lines at a node (m);
    edge_tol : largest median distance (m) of a labelled boundary from its plane intersection line (else step);
    absorb_angle_deg : largest normal difference of a small patch absorbed by its neighbour's plane."""

    cell: float = 0.5
    smooth_tol: float = 0.0
    angle_deg: float = 8.0
    step_tol: float = 0.35
    min_group_area: float = 3.0
    absorb_angle_deg: float = 20.0
    node_tol: float = 1.5
    segment_tol: float = 0.5
    edge_tol: float = 1.0


@dataclass
class RoofTopology:
    """Label grid and the topology derived from it.

    Attributes
    ----------
    labels : (rows, cols) int grid, 0 outside the contour, -1 unresolved, 1.. roof groups
    origin : (2,) world xy of the grid's lower-left corner; row index grows with y
    cell : grid size
    planes : {label: (4,) plane n.x + d = 0, unit n with n_z > 0}
    edges : {(a, b): list of (2,) xy window centres} for a < b (a may be 0 = facade)
    nodes : {frozenset(labels): (2,) mean xy} for windows holding three or more labels
    arrises : list of (contour edge index, (2,) xy, label before, label after) along the contour
    """

    labels: np.ndarray
    origin: np.ndarray
    cell: float
    planes: dict[int, np.ndarray]
    edges: dict[tuple[int, int], list[np.ndarray]] = field(default_factory=dict)
    nodes: dict[frozenset, np.ndarray] = field(default_factory=dict)
    arrises: list[tuple[int, np.ndarray, int, int]] = field(default_factory=list)

    def label_at(self, xy: np.ndarray) -> np.ndarray:
        """Label of the cell under each world point (n, 2); 0 outside the grid."""
        cr = np.floor((xy - self.origin) / self.cell).astype(np.int64)
        rows, cols = self.labels.shape
        ok = (cr[:, 0] >= 0) & (cr[:, 0] < cols) & (cr[:, 1] >= 0) & (cr[:, 1] < rows)
        out = np.zeros(len(xy), np.int64)
        out[ok] = self.labels[cr[ok, 1], cr[ok, 0]]
        return out


def _block_planes(xyz: np.ndarray, pt: np.ndarray, cell: np.ndarray,
                  ncell: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust total-least-squares plane per cell from (point, cell) pairs, all cells at once.

    Three fits like :func:`.geometry.fit_plane` with ``robust=True``: after the first and the second, pairs
    beyond 2.5 robust sigmas of their cell are dropped. Returns planes (ncell, 4) with n_z >= 0, the RMS of the
    kept residuals (ncell,) and the number of pairs per cell (ncell,).
    """
    ref = xyz[pt].mean(0) if len(pt) else np.zeros(3)
    rel = xyz[pt] - ref
    keep = np.ones(len(pt), bool)
    npts = np.bincount(cell, minlength=ncell)
    planes = np.full((ncell, 4), np.nan)
    rms = np.full(ncell, np.inf)
    for it in range(3):
        w = keep.astype(np.float64)
        n = np.bincount(cell, w, ncell)
        s1 = np.stack([np.bincount(cell, w * rel[:, d], ncell) for d in range(3)], 1)
        s2 = np.stack([np.bincount(cell, w * rel[:, d] * rel[:, e], ncell) for d in range(3) for e in range(3)], 1)
        nn = np.maximum(n, 1.0)
        mean = s1 / nn[:, None]
        cov = s2.reshape(ncell, 3, 3) / nn[:, None, None] - mean[:, :, None] * mean[:, None, :]
        _, vec = np.linalg.eigh(cov)
        nrm = vec[:, :, 0]
        nrm[nrm[:, 2] < 0] *= -1
        r = np.einsum("ij,ij->i", rel - mean[cell], nrm[cell])
        if it < 2:
            a = np.abs(r)
            a_kept = np.where(keep, a, np.inf)
            order = np.lexsort((a_kept, cell))
            st = np.searchsorted(cell[order], np.arange(ncell))
            k = np.bincount(cell[keep], minlength=ncell)
            med = np.zeros(ncell)
            ok = k > 0
            med[ok] = a_kept[order[st[ok] + k[ok] // 2]]
            new = a < 2.5 * (1.4826 * med[cell] + 1e-6)
            enough = np.bincount(cell[new], minlength=ncell) >= 4
            keep = np.where(enough[cell], new, keep)
        else:
            w = keep.astype(np.float64)
            rms = np.sqrt(np.bincount(cell, w * r * r, ncell) / np.maximum(np.bincount(cell, w, ncell), 1.0))
            planes = np.column_stack([nrm, -np.einsum("ij,ij->i", nrm, mean + ref)])
    return planes, rms, npts


def plane_z(plane: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Height of a non-vertical plane over points (n, 2)."""
    return -(plane[0] * xy[:, 0] + plane[1] * xy[:, 1] + plane[3]) / plane[2]


def roof_labels(xyz: np.ndarray, polygon: np.ndarray, noise: float, cfg: RoofConfig = RoofConfig()) -> RoofTopology:
    """Cells, per-cell planes, smoothness, normal groups, region growing, group planes.

    Parameters
    ----------
    xyz : (n, 3) building points (denoised)
    polygon : (m, 2) wall outline, counter-clockwise
    noise : noise level of the points (m), for the smoothness threshold
    """
    c = cfg.cell
    origin = polygon.min(0) - c
    cols, rows = (np.ceil((polygon.max(0) - origin) / c).astype(int) + 2)
    xc = origin[0] + (np.arange(cols) + 0.5) * c
    yc = origin[1] + (np.arange(rows) + 0.5) * c
    X, Y = np.meshgrid(xc, yc)
    inside = points_in_polygon(np.column_stack([X.ravel(), Y.ravel()]), polygon).reshape(rows, cols)
    # top points per cell (walls below the roof are dropped: keep points within 1.5 m of the cell's top)
    cr = np.floor((xyz[:, :2] - origin) / c).astype(np.int64)
    ok = (cr[:, 0] >= 0) & (cr[:, 0] < cols) & (cr[:, 1] >= 0) & (cr[:, 1] < rows)
    pidx = np.nonzero(ok)[0]
    flat = cr[ok, 1] * cols + cr[ok, 0]
    order = np.argsort(flat, kind="stable")
    pidx, flat = pidx[order], flat[order]
    starts = np.searchsorted(flat, np.arange(rows * cols + 1))

    # 90th percentile height per cell
    ncell = rows * cols
    zf = xyz[pidx, 2]
    o2 = np.lexsort((zf, flat))
    cnt = starts[1:] - starts[:-1]
    top = np.full(ncell, np.nan)
    has = cnt > 0
    top[has] = zf[o2[starts[:-1][has] + np.floor(0.9 * (cnt[has] - 1)).astype(np.int64)]]
    top = top.reshape(rows, cols)
    # roof points of each cell's 3x3 block (walls below the roof dropped: within 1.5 m of their cell's top)
    is_top = zf > top.ravel()[flat] - 1.5
    is_top &= inside.ravel()[flat]
    tp, tf = pidx[is_top], flat[is_top]
    tr, tq = tf // cols, tf % cols
    pair_pt, pair_cell = [], []
    for i in (-1, 0, 1):
        for j in (-1, 0, 1):
            rr, qq = tr + i, tq + j
            ok2 = (rr >= 0) & (rr < rows) & (qq >= 0) & (qq < cols)
            pair_pt.append(tp[ok2])
            pair_cell.append(rr[ok2] * cols + qq[ok2])
    pair_pt = np.concatenate(pair_pt)
    pair_cell = np.concatenate(pair_cell)
    sel = inside.ravel()[pair_cell]
    pair_pt, pair_cell = pair_pt[sel], pair_cell[sel]
    cell_plane, rms, npts = _block_planes(xyz, pair_pt, pair_cell, ncell)
    smooth_tol = cfg.smooth_tol if cfg.smooth_tol > 0 else max(3.0 * noise, 0.05)
    valid = npts >= 8
    cell_plane[~valid] = np.nan
    smooth = valid & (rms < smooth_tol) & (cell_plane[:, 2] > np.cos(np.radians(70)))
    cell_plane = cell_plane.reshape(rows, cols, 4)
    normals = cell_plane[..., :3]
    smooth = smooth.reshape(rows, cols)

    def cell_points(r: int, q: int) -> np.ndarray:
        f = r * cols + q
        return pidx[starts[f]:starts[f + 1]]

    labels = np.where(inside, -1, 0).astype(np.int64)
    cos_t = np.cos(np.radians(cfg.angle_deg))
    next_label = 1
    # seeds in order of flatness of their fit
    cand = [(r, q) for r in range(rows) for q in range(cols) if smooth[r, q]]
    for r0, q0 in cand:
        if labels[r0, q0] != -1:
            continue
        group = [(r0, q0)]
        labels[r0, q0] = next_label
        n0 = normals[r0, q0]
        queue = deque([(r0, q0)])
        while queue:
            r, q = queue.popleft()
            pl = cell_plane[r, q]
            for i, j in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                rr, qq = r + i, q + j
                if not (0 <= rr < rows and 0 <= qq < cols) or labels[rr, qq] != -1 or not smooth[rr, qq]:
                    continue
                if normals[rr, qq] @ n0 < cos_t or normals[rr, qq] @ pl[:3] < cos_t:
                    continue
                zc = plane_z(pl, np.array([[xc[qq], yc[rr]]]))[0]
                zn = plane_z(cell_plane[rr, qq], np.array([[xc[qq], yc[rr]]]))[0]
                if abs(zc - zn) > cfg.step_tol:
                    continue
                labels[rr, qq] = next_label
                group.append((rr, qq))
                queue.append((rr, qq))
        if len(group) * c * c < cfg.min_group_area:
            for r, q in group:
                labels[r, q] = -2  # too small: resolved by growing, never a seed again
        else:
            next_label += 1
    labels[labels == -2] = -1
    # planes per group
    planes: dict[int, np.ndarray] = {}
    for lab in range(1, next_label):
        rr, qq = np.nonzero(labels == lab)
        idx = np.concatenate([cell_points(r, q)[xyz[cell_points(r, q), 2] > top[r, q] - 1.0]
                              for r, q in zip(rr, qq)])
        pl, _ = fit_plane(xyz[idx], robust=True)
        planes[lab] = pl if pl[2] > 0 else -pl
    # region growing over installations and unresolved cells: the neighbouring label whose plane fits best
    for _ in range(rows + cols):
        todo = np.argwhere(labels == -1)
        if len(todo) == 0:
            break
        changed = False
        new = labels.copy()
        for r, q in todo:
            nb = {labels[r + i, q + j] for i in (-1, 0, 1) for j in (-1, 0, 1)
                  if 0 <= r + i < rows and 0 <= q + j < cols and labels[r + i, q + j] > 0}
            if not nb:
                continue
            idx = cell_points(r, q)
            if len(idx):
                p = xyz[idx]
                p = p[p[:, 2] > top[r, q] - 1.0]
                best = min(nb, key=lambda k: float(np.median(np.abs(p @ planes[k][:3] + planes[k][3]))))
            else:
                best = min(nb)
            new[r, q] = best
            changed = True
        labels = new
        if not changed:
            break
    if planes:
        labels = _relabel_by_planes(labels, planes, xyz[tp], tf)
    return merge_coplanar(RoofTopology(labels, origin, c, planes), xyz, cfg)


def _relabel_by_planes(labels: np.ndarray, planes: dict[int, np.ndarray], pts: np.ndarray, cell: np.ndarray,
                       rounds: int = 3) -> np.ndarray:
    """Each labelled cell takes the label, among those in its 3x3 neighbourhood, whose plane fits its roof
    points best (mean distance, clipped at 1 m), a few rounds.

    Added robustness for noisy dense clouds: region growing stops where the cell normals get noisy, so the label
    boundaries wander (a ridge end or a valley drawn metres off); after this step two faces meet where their
    planes cross, which is what the topology check compares them with, while a step between roofs stays a step
    (the lower plane fits nothing above it). The planes stay those fitted on the grown groups (a cell on a ridge
    holds points of both faces). ``labels (rows, cols)``; ``pts (n, 3)`` roof points with their flat cell index
    ``cell (n,)``.
    """
    from scipy import ndimage

    rows, cols = labels.shape
    ncell = rows * cols
    labs = sorted(planes)
    cnt = np.bincount(cell, minlength=ncell)
    cost = np.stack([np.bincount(cell, np.minimum(np.abs(pts @ planes[k][:3] + planes[k][3]), 1.0), ncell)
                     for k in labs]) / np.maximum(cnt, 1)
    L = labels.copy()
    for _ in range(rounds):
        near = np.stack([ndimage.binary_dilation(L == k, np.ones((3, 3), bool)).ravel() for k in labs])
        c = np.where(near, cost, np.inf)
        best = np.asarray(labs)[np.argmin(c, axis=0)].reshape(rows, cols)
        new = np.where((L > 0) & (cnt.reshape(rows, cols) > 0), best, L)
        if np.array_equal(new, L):
            break
        L = new
    return L


def topology(roof: RoofTopology, polygon: np.ndarray) -> RoofTopology:
    """Edges and nodes tables from a 2x2 window over the label grid, arrises by scanning the contour."""
    L = roof.labels
    rows, cols = L.shape
    c = roof.cell
    win = np.stack([L[:-1, :-1], L[:-1, 1:], L[1:, :-1], L[1:, 1:]], -1)
    edges: dict[tuple[int, int], list[np.ndarray]] = {}
    node_pts: dict[frozenset, list[np.ndarray]] = {}
    for r in range(rows - 1):
        for q in range(cols - 1):
            s = {int(v) for v in win[r, q] if v >= 0}
            if len(s) < 2:
                continue
            xy = roof.origin + np.array([q + 1, r + 1]) * c
            w = win[r, q]
            for i, j in ((0, 1), (2, 3), (0, 2), (1, 3)):  # 4-adjacent cells of the window only
                a, b = int(w[i]), int(w[j])
                if a != b and a >= 0 and b >= 0:
                    edges.setdefault((min(a, b), max(a, b)), []).append(xy)
            if len(s) >= 3:
                node_pts.setdefault(frozenset(s), []).append(xy)
    roof.edges = edges
    roof.nodes = {k: np.mean(v, 0) for k, v in node_pts.items()}
    # arrises: walk every contour edge just inside the wall
    arrises = []
    m = len(polygon)
    for i in range(m):
        p0, p1 = polygon[i], polygon[(i + 1) % m]
        d = p1 - p0
        length = np.linalg.norm(d)
        d = d / length
        inward = np.array([-d[1], d[0]])  # counter-clockwise polygon: interior on the left
        t = np.arange(0.0, length + c / 4, c / 2)
        if len(t) == 0:
            continue
        pts = p0 + t[:, None] * d + 1.5 * c * inward
        lab = roof.label_at(pts)
        # runs along the edge; single-sample runs are label flicker at a corner or a ridge end
        runs: list[list[int]] = []
        for k, v in enumerate(lab):
            if runs and runs[-1][0] == v:
                runs[-1][2] = k
            else:
                runs.append([int(v), k, k])
        runs = [r for r in runs if r[0] > 0 and r[2] - r[1] + 1 >= 2]
        for r, s in zip(runs, runs[1:]):
            if r[0] != s[0]:
                k = (r[2] + s[1] + 1) // 2
                xy = (pts[min(k, len(pts) - 1)] + pts[max(k - 1, 0)]) / 2 - 1.5 * c * inward
                arrises.append((i, xy, r[0], s[0]))
    roof.arrises = arrises
    return roof


@dataclass(frozen=True)
class TopologyCheck:
    """agree : the 2D path can be trusted; reason : why not; step_edges : label pairs with a height jump;
    node_errors : {node labels: distance between the topology node and the intersection node (m)}."""

    agree: bool
    reason: str
    step_edges: tuple[tuple[int, int], ...]
    node_errors: dict


def _boundary_offset(pa: np.ndarray, pb: np.ndarray, xy: np.ndarray) -> float:
    """Median distance (m) of observed boundary points (n, 2) to the plane intersection line seen from above
    (inf when the planes are parallel): small for ridges, hips and valleys, large for steps."""
    ln = plane_line(pa, pb)
    if ln is None or np.linalg.norm(ln[1][:2]) < 1e-6:
        return float("inf")
    p, d = ln[0][:2], ln[1][:2] / np.linalg.norm(ln[1][:2])
    nrm = np.array([-d[1], d[0]])
    return float(np.median(np.abs((xy - p) @ nrm)))


def merge_coplanar(roof: RoofTopology, xyz: np.ndarray, cfg: RoofConfig) -> RoofTopology:
    """Merge labels whose planes coincide (same normal within ``angle_deg``, heights within ``step_tol`` over
    both regions), neighbours first, and refit the merged plane on the points of both.

    Added robustness for dense clouds from matching: a group at most half the size of a neighbour it touches,
    with a normal within ``absorb_angle_deg`` of the neighbour's, is absorbed when the neighbour's plane runs
    within ``step_tol`` (median) of its own plane over its cells: a patch of one roof face whose normal the
    matching noise tilted (on the own-AT demo such a patch split a gable's slope into two labels and sent the
    building to the volumetric fallback). The two faces of a gable are not merged: comparable in size, and their
    normals differ by twice the pitch.

    A group is merged into a larger neighbour it touches, with a normal within ``absorb_angle_deg``, when its
    points lie at least as close to the neighbour's plane as to its own (median distance, the points within a
    metre of either): the neighbour's plane explains them as well, and their own was pulled off by a roof
    installation and the matching's smear beside it. On the demo's gable_dormers a dormer lifted the plane of
    the northern half of a slope 0.38 m above the truth (a step for the plane comparison, 0.31 m from the
    southern half's plane against 0.37 m from its own); on its church a chimney turned two patches of the nave's
    north slope by 9 degrees. A real face lies on its own plane: away from their intersection, or a step's height
    from it, the neighbour's plane misses its points."""
    if not roof.planes:
        return roof
    L = roof.labels
    cos_t = np.cos(np.radians(cfg.angle_deg))
    cos_absorb = np.cos(np.radians(cfg.absorb_angle_deg))
    def explained(big: int, small: int, lab: np.ndarray) -> bool:
        ps, pb = roof.planes[small], roof.planes[big]
        pts = xyz[lab == small]
        own, other = np.abs(pts @ ps[:3] + ps[3]), np.abs(pts @ pb[:3] + pb[3])
        near = (own < 1.0) | (other < 1.0)
        return int(near.sum()) >= 10 and float(np.median(other[near])) <= EXPLAINED_SHARE * float(np.median(own[near]))

    while True:
        pairs = {}
        for a_, b_ in ((L[:, :-1], L[:, 1:]), (L[:-1, :], L[1:, :])):
            m = (a_ > 0) & (b_ > 0) & (a_ != b_)
            for x, y in zip(a_[m], b_[m]):
                pairs[(min(x, y), max(x, y))] = pairs.get((min(x, y), max(x, y)), 0) + 1
        best = None
        labs = sorted(roof.planes)
        for a in labs:  # coplanar groups that do not touch (a roof interrupted by a wing) share one plane too
            for b in labs:
                if a < b and (a, b) not in pairs:
                    pairs[(a, b)] = 0
        lab = roof.label_at(xyz[:, :2])  # L is roof.labels, relabelled in place
        for (a, b), touch in sorted(pairs.items(), key=lambda kv: -kv[1]):
            pa, pb = roof.planes[a], roof.planes[b]
            if pa[:3] @ pb[:3] < cos_absorb:
                continue
            na, nb = int((L == a).sum()), int((L == b).sum())
            big, small = (a, b) if na >= nb else (b, a)
            if pa[:3] @ pb[:3] >= cos_t:
                rr, qq = np.nonzero((L == a) | (L == b))
                xy = roof.origin + (np.column_stack([qq, rr]) + 0.5) * roof.cell
                if np.median(np.abs(plane_z(pa, xy) - plane_z(pb, xy))) < cfg.step_tol:
                    best = (a, b)
                    break
            if touch:
                # a small patch whose normal the matching noise tilted: the neighbour's plane explains it
                if min(na, nb) <= 0.5 * max(na, nb):
                    rr, qq = np.nonzero(L == small)
                    xy = roof.origin + (np.column_stack([qq, rr]) + 0.5) * roof.cell
                    dz = plane_z(roof.planes[big], xy) - plane_z(roof.planes[small], xy)
                    if np.median(np.abs(dz)) < cfg.step_tol:
                        best = (big, small)
                        break
                if explained(big, small, lab):
                    best = (big, small)
                    break
        if best is None:
            break
        a, b = best
        L[L == b] = a
        pts = xyz[roof.label_at(xyz[:, :2]) == a]
        pa = roof.planes[a]
        pts = pts[np.abs(pts @ pa[:3] + pa[3]) < cfg.step_tol]
        pl, _ = fit_plane(pts, robust=True)
        roof.planes[a] = pl if pl[2] > 0 else -pl
        del roof.planes[b]
    # renumber 1..k
    old = sorted(roof.planes)
    new = np.zeros(max(old) + 2, np.int64)
    new[-1] = -1
    for i, k in enumerate(old):
        new[k] = i + 1
    roof.labels = np.where(L > 0, new[np.clip(L, 0, None)], L)
    roof.planes = {i + 1: roof.planes[k] for i, k in enumerate(old)}
    return roof


def _wall_plane(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    n = np.array([d[1], -d[0], 0.0])  # outward for a counter-clockwise polygon
    return np.append(n, -n[:2] @ p0)


def check_topology(roof: RoofTopology, polygon: np.ndarray, cfg: RoofConfig = RoofConfig()) -> TopologyCheck:
    """Compare the label topology with the plane intersections.

    Each roof-roof edge: the two planes must meet where the labels meet (the observed boundary within
    ``edge_tol`` of the intersection line seen from above), else it is a step (discontinuity). Each node: the
    centre of the shortest segment between two of its edge lines (roof-roof lines, or a roof line and a wall's
    eave line for arrises) must lie within ``node_tol`` of the node seen in the label grid, with that segment
    shorter than ``segment_tol``.
    """
    steps = []
    for (a, b), pts in roof.edges.items():
        if a <= 0 or b <= 0:
            continue
        if _boundary_offset(roof.planes[a], roof.planes[b], np.asarray(pts)) > cfg.edge_tol:
            steps.append((a, b))
    node_err: dict = {}
    bad = []
    m = len(polygon)
    walls = [_wall_plane(polygon[i], polygon[(i + 1) % m]) for i in range(m)]
    node_items = [(k, v, None) for k, v in roof.nodes.items() if 0 not in k]
    node_items += [(frozenset((0, a, b)), xy, i) for i, xy, a, b in roof.arrises]
    for labs, xy, wall_i in node_items:
        roofs = sorted(k for k in labs if k > 0)
        if any((min(a, b), max(a, b)) in steps for a in roofs for b in roofs if a != b):
            continue
        lines = []
        for ia in range(len(roofs)):
            for ib in range(ia + 1, len(roofs)):
                ln = plane_line(roof.planes[roofs[ia]], roof.planes[roofs[ib]])
                if ln is not None:
                    lines.append(ln)
        if wall_i is not None:
            ln = plane_line(roof.planes[roofs[0]], walls[wall_i])
            if ln is not None:
                lines.append(ln)
        if len(lines) < 2:
            continue
        p, q = line_line_closest(lines[0], lines[1])
        centre = (p + q) / 2
        err = float(np.linalg.norm(centre[:2] - xy))
        node_err[tuple(sorted(labs))] = err
        tol = cfg.node_tol
        if wall_i is not None:
            # an arris is scanned 1.5 cells inside the wall: along the wall it is off by that offset over the
            # tangent of the angle between the roof edge and the wall
            u, w = lines[0][1][:2], lines[-1][1][:2]
            sin = abs(u[0] * w[1] - u[1] * w[0]) / max(np.linalg.norm(u) * np.linalg.norm(w), 1e-12)
            tol += 1.5 * roof.cell * np.sqrt(max(1.0 - sin * sin, 0.0)) / max(sin, 0.2)
        if err > tol or np.linalg.norm(p - q) > cfg.segment_tol:
            bad.append((tuple(sorted(labs)), err, float(np.linalg.norm(p - q))))
    if steps:
        return TopologyCheck(False, f"height discontinuity between roof planes {steps}", tuple(steps), node_err)
    if bad:
        labs, err, seg = max(bad, key=lambda t: t[1])
        return TopologyCheck(False, f"node {labs} off by {err:.2f} m (segment {seg:.2f} m) from the plane "
                                    f"intersections", (), node_err)
    return TopologyCheck(True, "topology and plane intersections agree", (), node_err)

"""Volumetric fallback for buildings with discontinuities: planes found in 3D voxels.

Voxels of about half the noise filter's size; a PCA plane per voxel from the points of its 3x3x3 block;
neighbouring voxels with coplanar planes merged by region growing into plane segments, and segments that lie on
the same plane merged into one infinite plane; roof faces too small and noisy for the growing (a tower's pyramid)
found by a vote over the outline's edges and over the tops of interior walls (:func:`eave_planes`,
:func:`interior_eave_lines`); walls that rise inside the outline (a tower's wall above the nave) found on their own
facade points (:func:`interior_walls`), whose points are then kept out of the top grid the occupancy is judged on;
rounded eaves left out of the roof faces (:func:`eave_bevels`). The planes, the contour walls and the ground then
go to :func:`.hull.build_hull`, whose arrangement intersects every plane triplet inside the building's box,
consolidates the vertices into k-nodes and keeps the hull of the occupied cells with its structural breaks (step
walls between roofs of different heights).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .denoise import voxel_blocks
from .geometry import distance_to_edges, fit_plane, points_in_polygon
from .roof import plane_z


@dataclass(frozen=True)
class VolumetricConfig:
    """voxel : voxel edge (m, 0 = half the noise filter's voxel); angle_deg : coplanarity of neighbours;
    min_points : points of a voxel with a plane; min_area : smallest plane segment (m^2); min_wall_points : facade
    points of a wall inside the outline (:func:`interior_walls`); support_tol, support_ratio,
    support_max_occupancy : how the points judge the hull's barely kept cells (:class:`.hull.SurfaceSupport`);
    bevel_min_steeper_deg, bevel_max_width, bevel_min_overlap, bevel_min_ratio, bevel_direction_deg : what makes a
    segment a rounded eave (:func:`eave_bevels`)."""

    voxel: float = 0.0
    angle_deg: float = 10.0
    min_points: int = 6
    min_area: float = 3.0
    min_wall_points: int = 40
    support_tol: float = 0.3
    support_ratio: float = 1.2
    support_max_occupancy: float = 0.85
    bevel_min_steeper_deg: float = 8.0
    bevel_max_width: float = 1.2
    bevel_min_overlap: float = 0.3
    bevel_min_ratio: float = 3.0
    bevel_direction_deg: float = 20.0


@dataclass(frozen=True)
class InteriorWall:
    """plane : (4,) vertical plane n.x + d = 0 (n horizontal, unit); run : (lo, hi) the extent of its facade
    points along it, as ``xy @ (-n_y, n_x)``."""

    plane: np.ndarray
    run: tuple[float, float]


def along_wall(plane: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Position ``(n,)`` of points ``xy (n, 2)`` along the vertical ``plane (4,)``: ``xy @ (-n_y, n_x)``."""
    return xy @ np.array([-plane[1], plane[0]])


@dataclass(frozen=True)
class PlaneSegment:
    """plane : (4,) n.x + d = 0; n_points : support; area : approximate (m^2) from the voxel count; centre : (3,)
    mean of its points; points : (n_points, 3) the points themselves, where the segment was found in points
    (:func:`eave_bevels` needs them)."""

    plane: np.ndarray
    n_points: int
    area: float
    centre: np.ndarray
    points: np.ndarray | None = field(default=None, compare=False, repr=False)


def voxel_planes(xyz: np.ndarray, voxel: float, noise: float,
                 cfg: VolumetricConfig = VolumetricConfig()) -> list[PlaneSegment]:
    """Plane segments of points ``xyz (n, 3)``: a plane per voxel from the points of its 3x3x3 block, voxels
    merged over 26-neighbourhoods by region growing.

    The block, not the voxel alone, carries the normal: cut into cubes, a matched surface whose points spread
    across it about as much as a cube is wide (steep roofs seen from afar) gives each cube a random normal (on the
    demo church's north slope, 33 degrees off the roof's median). Blocks that straddle a ridge, an eave or a step
    do not fit a plane and seed nothing; a voxel joins a segment when its block's normal agrees with the
    segment's plane and its own points lie on it.
    """
    vb = voxel_blocks(xyz, voxel)
    order = np.argsort(vb.inv, kind="stable")
    starts = np.searchsorted(vb.inv[order], np.arange(len(vb.keys) + 1))
    planes = np.column_stack([vb.normal, -np.einsum("ij,ij->i", vb.normal, vb.mean + vb.lo)])
    tol = max(3.0 * noise, 0.05)
    ok = vb.count >= cfg.min_points
    # the blocks' own noise level: a matched cloud is noisier on steep and poorly seen roofs than the filter's
    tol_b = max(tol, 2.0 * float(np.median(vb.rms[ok]))) if ok.any() else tol
    vox = {}
    for k in np.flatnonzero(ok & (vb.rms < tol_b)):
        idx = order[starts[k]:starts[k + 1]]
        vox[tuple(vb.keys[k])] = (planes[k], idx, xyz[idx].mean(0), vb.rms[k])
    cos_t = np.cos(np.radians(cfg.angle_deg))
    offsets = [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)]
    label: dict[tuple, int] = {}
    segments: list[list[tuple]] = []
    for seed in sorted(vox, key=lambda k: vox[k][3]):
        if seed in label:
            continue
        lab = len(segments)
        label[seed] = lab
        members = [seed]
        ref, fitted = vox[seed][0], 1
        q = deque([seed])
        while q:
            v = q.popleft()
            for o in offsets:
                w = (v[0] + o[0], v[1] + o[1], v[2] + o[2])
                if w in label or w not in vox:
                    continue
                pw, _, cw, _ = vox[w]
                if abs(pw[:3] @ ref[:3]) < cos_t or abs(cw @ ref[:3] + ref[3]) > 2 * tol_b:
                    continue
                label[w] = lab
                members.append(w)
                q.append(w)
            if len(members) >= 1.3 * fitted:  # follow the segment's plane as it grows
                ref, _ = fit_plane(xyz[np.concatenate([vox[m][1] for m in members])])
                fitted = len(members)
        segments.append(members)
    out: list[PlaneSegment] = []
    for members in segments:
        area = len(members) * voxel * voxel
        if area < cfg.min_area:
            continue
        idx = np.concatenate([vox[m][1] for m in members])
        pl, _ = fit_plane(xyz[idx], robust=True)
        if pl[2] < -1e-9 or (abs(pl[2]) <= 1e-9 and pl[0] < 0):
            pl = -pl
        out.append(PlaneSegment(pl, len(idx), area, xyz[idx].mean(0), xyz[idx]))
    return merge_plane_segments(out, cfg.angle_deg, tol_b * 2)


def eave_planes(top: np.ndarray, polygon: np.ndarray, voxel: float, tol: float,
                cfg: VolumetricConfig = VolumetricConfig(), depth: float = 8.0,
                slopes_deg: np.ndarray = np.arange(10.0, 76.0), normals: np.ndarray | None = None,
                normal_deg: float = 30.0, tie: float = 0.8,
                lines: list[tuple[np.ndarray, np.ndarray]] = ()) -> list[PlaneSegment]:
    """Roof planes rising from the outline's edges, and from further ``lines`` ``(p0 (2,), p1 (2,))`` voted like an
    edge (the face rising on the left of ``p0 -> p1``: a tower's eave above the nave, :func:`interior_eave_lines`),
    found in the roof points ``top (n, 3)`` by a vote.

    Over each edge of the counter-clockwise outline ``polygon (m, 2)`` (the points within its extent and up to
    ``depth`` inwards), a plane through a horizontal line parallel to the edge is an eave height and a slope;
    each slope's heights ``h = z - tan(slope) v`` (``v`` inward distance) are counted in a window of ``tol``
    across the plane, and the best pair kept when its points run along most of the edge at the eave (60 % of
    it within 1.5 m of the wall, so that a band along a ridge is no roof face), cover ``min_area``, and refit
    within half ``angle_deg`` of it (a flat roof's band under a 10 degree vote refits flat).

    For faces whose points are too few and noisy for region growing: the pyramid roof of the demo church's
    tower holds 12-28 points per m^2 at 0.15-0.2 m noise, and every 3x3x3 block on it straddles a hip.

    With ``normals (n, 3)`` (the top surface's, :func:`grid_normals`) a second vote counts only the points on a
    slope that falls outwards across the edge (the normal's horizontal part within ``normal_deg`` of the outward
    direction, the slope over half the least one searched). Its winner is taken when ``min_area`` worth of them
    agree and all points find a slope within 2 degrees of it at least ``tie`` times as good as theirs: a band
    across a pyramid's other faces (on seed 7's church tower a 40 degree band over the east and west faces, 311
    points against the sparse 65 degree north face's 272) holds none of them, while the few facade points along a
    flat roof's edge do not outvote the roof. The face's points are then all those near its plane.
    """
    out: list[PlaneSegment] = []
    tan = np.tan(np.radians(slopes_deg))
    cos = np.cos(np.radians(slopes_deg))
    cos_n = np.cos(np.radians(normal_deg))
    sin_min = np.sin(np.radians(0.5 * slopes_deg[0]))
    min_vox = int(np.ceil(cfg.min_area / voxel**2))
    m = len(polygon)
    for p0, p1 in [(polygon[i], polygon[(i + 1) % m]) for i in range(m)] + list(lines):
        length = float(np.linalg.norm(p1 - p0))
        if length < 2.0:
            continue
        d = (p1 - p0) / length
        inward = np.array([-d[1], d[0]])
        u = (top[:, :2] - p0) @ d
        v = (top[:, :2] - p0) @ inward
        zone = np.flatnonzero((u >= 0) & (u <= length) & (v >= 0) & (v <= depth))
        if len(zone) < min_vox:
            continue
        z, vz = top[zone, 2], v[zone]
        cnt, h = _slope_vote(z, vz, tan, cos, tol)
        k = int(np.argmax(cnt))
        if normals is not None:  # points on a slope falling outwards across the edge, every slope the same set
            nh = normals[zone, :2]
            agree = (nh @ -inward > cos_n * np.linalg.norm(nh, axis=1)) & (np.linalg.norm(nh, axis=1) > sin_min)
            cnt_a, h_a = _slope_vote(z[agree], vz[agree], tan, cos, tol)
            ka = int(np.argmax(cnt_a))
            # the agreeing points choose among the slopes that all points find nearly as good (within 2 degrees)
            if cnt_a[ka] >= min_vox and cnt[max(ka - 2, 0):ka + 3].max() >= tie * cnt[k]:
                k, h = ka, h_a
        n_in, h0 = int(cnt[k]), float(h[k])
        if n_in < min_vox:
            continue
        inl = zone[np.abs(z - h0 - tan[k] * vz) * cos[k] < tol]
        eave = inl[v[inl] <= 1.5]
        covered = np.unique(np.floor(u[eave] / 0.5).astype(np.int64)).size * 0.5
        area = np.unique(np.floor(top[inl] / voxel).astype(np.int64), axis=0).shape[0] * voxel**2
        if covered < 0.6 * length or area < cfg.min_area:
            continue
        pl, _ = fit_plane(top[inl], robust=True)
        pl = pl if pl[2] > 0 else -pl
        want = np.append(-np.sin(np.radians(slopes_deg[k])) * inward, cos[k])
        if pl[:3] @ want < np.cos(np.radians(cfg.angle_deg / 2)):
            continue
        out.append(PlaneSegment(pl, len(inl), float(area), top[inl].mean(0), top[inl]))
    return out


def _slope_vote(z: np.ndarray, v: np.ndarray, tan: np.ndarray, cos: np.ndarray, tol: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`eave_planes`' vote over points at heights ``z (n,)`` and inward distances ``v (n,)``: per slope
    ``(s,)`` the most points in a band of ``tol`` across its plane, and that band's eave height ``(s,)``."""
    cnt, h0 = np.zeros(len(tan), np.int64), np.zeros(len(tan))
    if not len(z):
        return cnt, h0
    for k in range(len(tan)):
        h = np.sort(z - tan[k] * v)
        w = tol / cos[k]
        c = np.searchsorted(h, h + 2 * w) - np.arange(len(h))
        j = int(np.argmax(c))
        cnt[k], h0[k] = c[j], h[j] + w
    return cnt, h0


def wall_sides(H: np.ndarray, origin: np.ndarray, cell: float, wall: InteriorWall, rise: float = 1.5,
               reach: float = 2.0, margin: float = 0.5) -> tuple[np.ndarray, float, float] | None:
    """The two sides of an interior ``wall`` on the top grid ``H`` (rows = y index, cell ``(0, 0)`` at ``origin``,
    ``cell`` m): their median heights from ``margin`` to ``reach`` + 1.5 m off the wall (mostly beyond a spill on
    either side), within 0.5 m of its run's ends. None when they differ by less than ``rise`` metres (or either has
    fewer than 4 cells); else the cells' signed distances to the wall ``(rows, cols)``, the higher side's sign of
    that distance (+1 or -1) and the middle of the two heights."""
    rows, cols = H.shape
    cy, cx = np.mgrid[0:rows, 0:cols]
    centres = origin + (np.column_stack([cx.ravel(), cy.ravel()]) + 0.5) * cell
    w = wall.plane
    dist = (centres @ w[:2] + w[3]).reshape(rows, cols)
    t = along_wall(w, centres).reshape(rows, cols)
    near = ((np.abs(dist) > margin) & (np.abs(dist) < reach + 1.5)
            & (t > wall.run[0] - 0.5) & (t < wall.run[1] + 0.5))
    a, b = H[near & (dist > 0)], H[near & (dist < 0)]
    if len(a) < 4 or len(b) < 4 or abs(np.median(a) - np.median(b)) < rise:
        return None
    return dist, (1.0 if np.median(a) > np.median(b) else -1.0), 0.5 * float(np.median(a) + np.median(b))


def interior_eave_lines(H: np.ndarray, origin: np.ndarray, cell: float, walls: list[InteriorWall]
                        ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The eave lines of the upper roofs beside interior ``walls``, for :func:`eave_planes`: each wall whose sides
    differ in height (:func:`wall_sides`, on the top grid ``H``) gives its run ``(p0 (2,), p1 (2,))``, ordered so
    that the higher side lies on the left. A tower's face that falls towards the nave rises from there: the vote
    over the outline's edges never sees it, and on seed 5's church (own dense cloud) the region growing did not
    find it either, so the tower's west face was carried on over it, up to 6 m too high."""
    out = []
    for wall in walls:
        sides = wall_sides(H, origin, cell, wall)
        if sides is None:
            continue
        n = wall.plane[:2]
        foot, t = -wall.plane[3] * n, np.array([-n[1], n[0]])
        p0, p1 = foot + wall.run[0] * t, foot + wall.run[1] * t
        # the left of p0 -> p1 is (-t_y, t_x) = -n: the side where the distance is negative
        out.append((p0, p1) if sides[1] < 0 else (p1, p0))
    return out


def clip_spill_over_walls(H: np.ndarray, origin: np.ndarray, cell: float, walls: list[InteriorWall],
                           rise: float = 1.5, reach: float = 2.0, margin: float = 0.5) -> np.ndarray:
    """The top grid ``H`` (rows = y index, cell ``(0, 0)`` at ``origin``, ``cell`` m) without the upper roof's
    heights spilled over an interior wall: beside each wall whose sides along its run (their median heights from
    ``margin`` to ``reach`` + 1.5 m off it, within 0.5 m of the run's ends) differ by over ``rise`` metres, the
    cells on its lower side between ``margin`` (the wall's own uncertainty) and ``reach`` metres from it that stand
    above the middle height take the lower of their height and that of the cell ``reach`` metres further from
    the wall.

    Dense matching fattens a tower's top edge over the lower roof beside it (on the seed-3 church, points at the
    tower's height stand 1-1.5 m in front of its wall over the nave), and the hull, whose cells are inside below
    the grid, carried the tower out over the nave. The sides are compared along the run only: beyond a tower's
    corners its side of the wall's line is the ground, and medians over the whole line mixed the two."""
    rows, cols = H.shape
    out = H.copy()
    for wall in walls:
        sides = wall_sides(H, origin, cell, wall, rise, reach, margin)
        if sides is None:
            continue
        dist, high, middle = sides
        low = -high  # the lower side's sign of ``dist``
        band = (low * dist > margin) & (low * dist < reach) & (H > middle)
        r, c = np.nonzero(band)
        # the cell ``reach`` metres further out along the wall's normal, towards the lower side
        shift = low * reach * wall.plane[:2] / np.linalg.norm(wall.plane[:2]) / cell
        r2 = np.clip(np.rint(r + shift[1]).astype(np.int64), 0, rows - 1)
        c2 = np.clip(np.rint(c + shift[0]).astype(np.int64), 0, cols - 1)
        out[r, c] = np.minimum(H[r, c], H[r2, c2])
    return out


def grid_normals(H: np.ndarray, cell: float) -> np.ndarray:
    """Unit normals ``(rows, cols, 3)`` (up) of a top surface grid ``H`` (:func:`height_grid`, rows = y index)
    from its central differences."""
    gy, gx = np.gradient(H, cell)
    n = np.stack([-gx, -gy, np.ones_like(H)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def same_plane(a: PlaneSegment, b: PlaneSegment, angle_deg: float, offset: float) -> bool:
    """Normals within ``angle_deg`` and each segment's centre within ``offset`` of the other's plane."""
    return bool(abs(a.plane[:3] @ b.plane[:3]) > np.cos(np.radians(angle_deg))
                and abs(a.centre @ b.plane[:3] + b.plane[3]) < offset
                and abs(b.centre @ a.plane[:3] + a.plane[3]) < offset)


def merge_plane_segments(segs: list[PlaneSegment], angle_deg: float, offset: float) -> list[PlaneSegment]:
    """Segments on the same plane (normals within ``angle_deg``, each one's centre within ``offset`` of the
    other's plane) become one plane, through their common centre. The centres, not the planes' constants, are
    compared: far from the origin (absolute heights) a tiny tilt moves the constant by metres."""
    segs = sorted(segs, key=lambda s: -s.n_points)
    out: list[PlaneSegment] = []
    for s in segs:
        for i, o in enumerate(out):
            if same_plane(s, o, angle_deg, offset):
                c = s.plane[:3] @ o.plane[:3]
                w = o.n_points + s.n_points
                n = o.plane[:3] * o.n_points + np.sign(c) * s.plane[:3] * s.n_points
                n = n / np.linalg.norm(n)
                centre = (o.centre * o.n_points + s.centre * s.n_points) / w
                points = (None if o.points is None or s.points is None
                          else np.concatenate([o.points, s.points]))
                out[i] = PlaneSegment(np.append(n, -n @ centre), w, o.area + s.area, centre, points)
                break
        else:
            out.append(s)
    return out


def eave_bevels(segs: list[PlaneSegment], cfg: VolumetricConfig = VolumetricConfig()) -> np.ndarray:
    """Which segments are a rounded eave, not a roof face -> (len(segs),) bool.

    Dense matching and its smoothing round a convex eave off: between the facade and the roof the points run on a
    steeper band, which the region growing finds as a plane of its own (on the demo church's north eave a 63 degree
    band over the 50 degree slope, 1 m wide in plan). Its plane, carried on into the hull, raises the roof by up to
    2 m over the slope behind it. Such a band, against a roof segment falling the same way (horizontal normals
    within ``bevel_direction_deg``) with ``bevel_min_ratio`` times its points:

    * is steeper by at least ``bevel_min_steeper_deg`` and narrower in plan than ``bevel_max_width``;
    * overlaps the roof's lower end in plan: along the roof's fall it starts more than ``bevel_min_overlap`` inside
      the roof's points (their 95th percentile) and ends beyond that;
    * holds the roof's lowest points in its height range (5th to 95th percentiles).

    A mansard's steep lower face meets the upper roof along a line, and its points start where the roof's end, so
    it stays. Segments without points (``PlaneSegment.points`` None) are neither bevels nor the roofs they are
    judged against.
    """
    out = np.zeros(len(segs), bool)
    sloped = []
    for i, s in enumerate(segs):
        n = s.plane[:3] / np.linalg.norm(s.plane[:3])
        horizontal = float(np.linalg.norm(n[:2]))
        if s.points is not None and 1e-6 < horizontal < 1.0 - 1e-6:
            sloped.append((i, np.degrees(np.arcsin(horizontal)), n[:2] / horizontal))
    cos_dir = np.cos(np.radians(cfg.bevel_direction_deg))
    for i, slope, fall in sloped:
        s = segs[i]
        z5, z95 = np.percentile(s.points[:, 2], [5.0, 95.0])
        for j, r_slope, r_fall in sloped:
            r = segs[j]
            if (j == i or r.n_points < cfg.bevel_min_ratio * s.n_points or slope < r_slope + cfg.bevel_min_steeper_deg
                    or fall @ r_fall < cos_dir):
                continue
            u5, u95 = np.percentile(s.points[:, :2] @ r_fall, [5.0, 95.0])
            inner = float(np.percentile(r.points[:, :2] @ r_fall, 95.0)) - cfg.bevel_min_overlap
            if u95 - u5 < cfg.bevel_max_width and u5 < inner < u95 and z5 < np.percentile(r.points[:, 2], 5.0) < z95:
                out[i] = True
                break
    return out


def snap_heights(H: np.ndarray, top: np.ndarray, roofs: list[np.ndarray], origin: np.ndarray, cell: float,
                  tol: float, max_shift: float = 1.0) -> np.ndarray:
    """The top surface grid ``H (rows, cols)`` on the roof planes: a cell whose roof points ``top (n, 3)`` lie on
    one of ``roofs`` (mean vertical distance, clipped at 1 m, below ``tol``) takes that plane's height at its
    centre, unless that moves it by more than ``max_shift`` metres. The percentile height of a noisy matched roof
    stands above it by about twice the noise, and the hull's cells between the roof plane and that height would
    count as inside. A larger move is no such bias: beside a tower the roof points (within 1 m of the grid's
    height before :func:`clip_spill_over_walls` lowered it) lay on the tower's roof plane, carried on over the
    nave, and snapping put the tower's height back where the clip had taken it away (seed 6's church, 1.13 m roof
    RMSE)."""
    if not roofs or not len(top):
        return H
    rows, cols = H.shape
    cr = np.floor((top[:, :2] - origin) / cell).astype(np.int64)
    ok = (cr[:, 0] >= 0) & (cr[:, 0] < cols) & (cr[:, 1] >= 0) & (cr[:, 1] < rows)
    flat = cr[ok, 1] * cols + cr[ok, 0]
    n = np.bincount(flat, minlength=rows * cols)
    P = np.asarray(roofs)
    res = np.minimum(np.abs(top[ok, 2:3] - np.stack([plane_z(p, top[ok, :2]) for p in P], 1)), 1.0)
    cost = np.stack([np.bincount(flat, res[:, k], rows * cols) for k in range(len(P))], 1) / np.maximum(n, 1)[:, None]
    best = np.argmin(cost, 1)
    snap = (n >= 3) & (cost[np.arange(rows * cols), best] < tol)
    X, Y = np.meshgrid(origin[0] + (np.arange(cols) + 0.5) * cell, origin[1] + (np.arange(rows) + 0.5) * cell)
    xy = np.column_stack([X.ravel(), Y.ravel()])
    z = np.stack([plane_z(p, xy) for p in P], 1)[np.arange(rows * cols), best]
    snap &= np.abs(z - H.ravel()) <= max_shift
    return np.where(snap, z, H.ravel()).reshape(rows, cols)


def step_walls(boundaries: list[np.ndarray], tol: float = 0.35, min_points: int = 4, max_lines: int = 3,
               hypotheses: int = 300) -> list[np.ndarray]:
    """Vertical planes (4,) along the label boundaries of roof steps (each ``(k, 2)``: the window centres between
    two labels whose planes do not meet there): up to ``max_lines`` straight runs per boundary, each the line
    with most points within ``tol`` among ``hypotheses`` lines through two of them (fixed seed), refitted, kept
    with ``min_points`` points. The step wall between a tower's roof and the lower roof beside it, or between the
    two heights of a split gable, stands above the lower roof only and often holds too few facade points for a
    plane of its own."""
    rng = np.random.default_rng(0)
    out = []
    for pts in boundaries:
        left = np.asarray(pts, dtype=np.float64)
        for _ in range(max_lines):
            if len(left) < min_points:
                break
            i, j = rng.integers(0, len(left), (2, hypotheses))
            d = left[j] - left[i]
            ok = np.linalg.norm(d, axis=1) > 1e-9
            if not ok.any():
                break
            d = d[ok] / np.linalg.norm(d[ok], axis=1)[:, None]
            nrm = np.column_stack([-d[:, 1], d[:, 0]])
            dist = np.abs(nrm @ left.T - np.einsum("hk,hk->h", nrm, left[i[ok]])[:, None])
            inl = dist[int(np.argmax((dist < tol).sum(1)))] < tol
            if inl.sum() < min_points:
                break
            q = left[inl]
            c = q.mean(0)
            _, _, vt = np.linalg.svd(q - c)
            n2 = np.array([-vt[0, 1], vt[0, 0]])
            out.append(np.array([n2[0], n2[1], 0.0, -n2 @ c]))
            left = left[~inl]
    return out


def interior_facade_points(xyz: np.ndarray, polygon: np.ndarray, voxel: float, margin: float = 1.0,
                           max_nz: float = 0.15, min_block: int = 12) -> np.ndarray:
    """``(n,) bool``: the points of ``xyz (n, 3)`` that lie on vertical surfaces (their 3x3x3 block's plane within
    ``asin(max_nz)`` of vertical, from at least ``min_block`` points) more than ``margin`` inside the outline
    ``polygon (m, 2)``: the walls that rise inside the footprint above a lower roof, a tower's wall above the nave.
    In plan they gather on the walls' lines (:func:`step_walls` finds those)."""
    vb = voxel_blocks(xyz, voxel)
    out = ((np.abs(vb.normal[:, 2]) < max_nz) & (vb.n_block >= min_block))[vb.inv]
    xy = xyz[out, :2]
    out[np.flatnonzero(out)] = (distance_to_edges(xy, polygon) > margin) & points_in_polygon(xy, polygon)
    return out


def interior_walls(xyz: np.ndarray, polygon: np.ndarray, ground_z: float, voxel: float, min_points: int,
                   tol: float = 0.35) -> tuple[list[InteriorWall], np.ndarray]:
    """Walls that rise inside the outline ``polygon (m, 2)``, from their own facade points among ``xyz (n, 3)``
    (:func:`interior_facade_points` in ``voxel`` cubes, then up to four straight runs of ``min_points`` points by
    :func:`step_walls`).

    Returns
    -------
    walls : the walls with the run of their facade points within ``tol``; on_wall : (n,) bool, every point more
        than 2 m above the ground within ``tol`` of a wall along its run (0.5 m beyond either end): the blocks at a
        wall's foot mix wall and roof, so the run, not the block normals, says which points are the wall's.
    """
    facade = xyz[:, 2] > ground_z + 0.5
    facade[facade] = interior_facade_points(xyz[facade], polygon, voxel)
    walls = []
    on_wall = np.zeros(len(xyz), bool)
    for w in step_walls([xyz[facade, :2]], tol=tol, min_points=min_points, max_lines=4):
        d = np.abs(xyz[:, :2] @ w[:2] + w[3])
        t = along_wall(w, xyz[:, :2])
        run = t[facade & (d < tol)]
        walls.append(InteriorWall(w, (float(run.min()), float(run.max()))))
        on_wall |= (d < tol) & (t > run.min() - 0.5) & (t < run.max() + 0.5) & (xyz[:, 2] > ground_z + 2.0)
    return walls, on_wall


def height_grid(xyz: np.ndarray, origin: np.ndarray, cell: float, shape: tuple[int, int]) -> np.ndarray:
    """Top surface grid (rows = y index): 95th percentile height per cell, empty cells from the nearest filled
    one, then a 3x3 median."""
    from scipy import ndimage

    rows, cols = shape
    cr = np.floor((xyz[:, :2] - origin) / cell).astype(np.int64)
    ok = (cr[:, 0] >= 0) & (cr[:, 0] < cols) & (cr[:, 1] >= 0) & (cr[:, 1] < rows)
    flat = cr[ok, 1] * cols + cr[ok, 0]
    z = xyz[ok, 2]
    order = np.lexsort((z, flat))
    flat, z = flat[order], z[order]
    starts = np.searchsorted(flat, np.arange(rows * cols + 1))
    H = np.full(rows * cols, np.nan)
    cnt = starts[1:] - starts[:-1]
    nz = np.nonzero(cnt)[0]
    H[nz] = z[starts[nz] + np.floor(0.95 * (cnt[nz] - 1)).astype(np.int64)]
    H = H.reshape(rows, cols)
    miss = np.isnan(H)
    if miss.all():
        return H
    _, (ri, ci) = ndimage.distance_transform_edt(miss, return_indices=True)
    H = H[ri, ci]
    return ndimage.median_filter(H, size=3)


def grid_cell(xy: np.ndarray, origin: np.ndarray, cell: float, shape: tuple[int, int]
              ) -> tuple[np.ndarray, np.ndarray]:
    """Row and column ``(n,)`` of the grid cell (rows = y index, cell ``(0, 0)`` at ``origin``) under each point
    ``xy (n, 2)``; points off the grid take its nearest edge cell."""
    cr = np.floor((xy - origin) / cell).astype(np.int64)
    return np.clip(cr[:, 1], 0, shape[0] - 1), np.clip(cr[:, 0], 0, shape[1] - 1)


def top_points(xyz: np.ndarray, origin: np.ndarray, cell: float, shape: tuple[int, int], ground_z: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """The roof points of ``xyz (n, 3)``: within 1 m of the top surface grid (:func:`height_grid` on ``origin``,
    ``cell``, ``shape``) and over 2 m above the ground. Returns them ``(k, 3)`` and the grid."""
    H = height_grid(xyz, origin, cell, shape)
    z_top = H[grid_cell(xyz[:, :2], origin, cell, H.shape)]
    return xyz[(xyz[:, 2] > z_top - 1.0) & (xyz[:, 2] > ground_z + 2.0)], H

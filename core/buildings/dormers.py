"""Dormers: gabled or shed blocks standing on a sloped roof plane, found as blobs of roof points above it.

The roof labels absorb a dormer into the slope it stands on (region growing over installations), so the body's
roof passes under it. Here the points of each sloped roof plane are compared with that plane on the roof grid;
connected cells more than ``DormerConfig.min_rise`` above it, of a dormer's size and away from the outline, form a
candidate. In the frame of its slope (``u`` downslope, ``v`` across) the candidate is modelled as a block: a front
wall at its downslope end, two side walls, and a roof fitted to its points, either two slopes meeting at a ridge
along ``u`` in the middle (gabled) or one plane (shed or flat), whichever fits better; its bottom is the slope,
so behind it ends where its roof runs into the slope. The walls stand where the points' height above the slope
steps from the roof's to zero (least squares, so a blurred edge is placed at its middle); a gabled dormer's sides
are then centred on its ridge, keeping their distance: the roof's two slopes place the ridge, while the matching's
smear beside a dormer (0.3-0.9 m high over a metre or so of the slope) shifts the side it lies on.

A wall's points under the eaves (a facade's, from the slope up to the eaves) are neither roof nor slope. The roof
is fitted to the points on the top surface alone (:func:`on_top`), and where the points under the top surface at an
edge stand as a wall (:func:`_wall_span`: a compact column across the edge; the matching's smear is a ramp, and
there all points count as before), that edge is placed on the top surface's points: at the roof's edge, its
overhang included. The block's front then stands on its wall's points and its roof overhangs it by the difference
(:attr:`Dormer.front_overhang`, built as the outline's overhangs are); its sides stand at the roof's edge. Taken
with the roof's, a facade's points drew the fronts of the simulated city's dormers 0.28 m (mean) behind their roofs'
edges on its sampled surfaces, behind the walls themselves. Without an overhang, the edge comes out about 0.1 m
beyond the wall (the noisiest of the eave's points place it, the slope's beside it being under the eave), an
overhang of that width. Each dormer is
a convex polytope (the intersection of half-spaces), so the body hull takes its planes and its occupancy as a union with
the body's (:func:`.hull.build_hull`): the dormer becomes part of the closed solid, with walls and roofs of its
own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .geometry import distance_to_edges, points_in_polygon
from .roof import RoofTopology, plane_z


@dataclass(frozen=True)
class DormerConfig:
    """enabled : look for dormers at all; min_rise : height above the slope that marks a dormer cell (m);
    fit_min_rise : the roof is fitted to the points at least this high above the slope (the slope's own points
    stay out); min_area / max_area : blob size (m^2); min_slope_deg : flatter roof planes carry no dormers (their
    blocks are roof steps); edge_margin : a blob keeps this far inside the outline (m); min_wall : the dormer's
    eaves stand at least this high above the slope at its front (m); max_rmse : largest RMS of the roof fit (m;
    dense matching rounds a dormer's ridge and edges); gable_gain : a single plane is taken instead of the gabled
    roof only when its RMS is below this share of the gable's; min_shed_drop_deg : a single roof plane is at least
    this much flatter than the slope it stands on (a layer parallel to the slope is a bump in the points, e.g. the
    matching's smear beside a dormer, not a shed dormer: its back would run far up the slope, past the ridge);
    top_radius, top_gap : a point is on the top surface unless a point within ``top_radius`` across stands more
    than ``top_gap`` above it (m); wall_min_points, wall_max_iqr : the points under the top surface at an edge
    (between a quarter and three quarters of the dormer roof's height above the slope) stand as a wall when at
    least this many lie within this interquartile range across the edge (m)."""

    enabled: bool = True
    min_rise: float = 0.4
    fit_min_rise: float = 0.25
    min_area: float = 2.0
    max_area: float = 40.0
    min_slope_deg: float = 15.0
    edge_margin: float = 0.4
    min_wall: float = 0.4
    max_rmse: float = 0.45
    gable_gain: float = 0.8
    min_shed_drop_deg: float = 10.0
    top_radius: float = 0.25
    top_gap: float = 0.5
    wall_min_points: int = 15
    wall_max_iqr: float = 0.15


@dataclass(frozen=True)
class Dormer:
    """A dormer as half-spaces ``planes (k, 4)``, ``n . x + d <= 0`` inside: the front wall, two sides, one or
    two roof planes, and last the roof plane it stands on (its bottom); ``label`` is that plane's roof label,
    ``kind`` gabled or shed, ``rmse`` the roof fit's RMS (m); ``front_overhang`` how far its roof reaches beyond its
    front wall (m; 0 where no wall showed under the eave)."""

    planes: np.ndarray
    label: int
    kind: str
    rmse: float
    front_overhang: float = 0.0

    def inside(self, xyz: np.ndarray) -> np.ndarray:
        """Occupancy of points (n, 3): inside every half-space."""
        return np.all(xyz @ self.planes[:, :3].T + self.planes[:, 3] < 0.0, axis=1)


def _fit_roof(u: np.ndarray, v: np.ndarray, z: np.ndarray, v0: float, v1: float,
              gabled: bool) -> tuple[np.ndarray, float]:
    """Robust least squares: gabled ``z = a - s |v - vc|`` (coefficients a, s, vc; the ridge ``vc`` searched
    over the middle half of ``[v0, v1]``) or a plane ``z = a + b u + c v``; returns the coefficients and the RMS
    of the inliers."""
    vc = 0.5 * (v0 + v1)
    if gabled:
        best = np.inf
        for c in np.arange(0.75 * v0 + 0.25 * v1, 0.25 * v0 + 0.75 * v1, 0.05):
            A = np.column_stack([np.ones_like(v), -np.abs(v - c)])
            sse = np.linalg.lstsq(A, z, rcond=None)[1]
            if len(sse) and sse[0] < best:
                best, vc = float(sse[0]), float(c)
    A = (np.column_stack([np.ones_like(v), -np.abs(v - vc)]) if gabled
         else np.column_stack([np.ones_like(u), u, v]))
    keep = np.ones(len(z), bool)
    coef = np.zeros(A.shape[1])
    for _ in range(3):
        coef = np.linalg.lstsq(A[keep], z[keep], rcond=None)[0]
        r = z - A @ coef
        s = 1.4826 * np.median(np.abs(r[keep])) + 1e-3
        keep = np.abs(r) < 3.0 * s
    return (np.append(coef, vc) if gabled else coef), float(np.sqrt(np.mean(r[keep] ** 2)))


def find_dormers(xyz: np.ndarray, roof: RoofTopology, polygon: np.ndarray,
                 cfg: DormerConfig = DormerConfig()) -> tuple[list[Dormer], list[str]]:
    """Dormers on the sloped roof planes of ``roof`` from the building's points ``xyz (n, 3)`` (the frame of
    ``roof`` and ``polygon (m, 2)``, the wall outline), and why the other candidates were not taken."""
    c = roof.cell
    rows, cols = roof.labels.shape
    xy = xyz[:, :2]
    lab = roof.label_at(xy)
    cr = np.floor((xy - roof.origin) / c).astype(np.int64)
    ok = (lab > 0) & points_in_polygon(xy, polygon)
    cell_id = cr[:, 1] * cols + cr[:, 0]
    # median rise of each cell's points over its label's plane
    rise = np.full(len(xyz), np.nan)
    for k, pl in roof.planes.items():
        m = ok & (lab == k)
        rise[m] = xyz[m, 2] - plane_z(pl, xy[m])
    med = np.full(rows * cols, np.nan)
    ids = cell_id[ok]
    order = np.argsort(ids, kind="stable")
    ids_s, rise_s = ids[order], rise[ok][order]
    starts = np.flatnonzero(np.r_[True, ids_s[1:] != ids_s[:-1]])
    counts = np.diff(np.r_[starts, len(ids_s)])
    for s0, n in zip(starts, counts):
        if n >= 2:
            med[ids_s[s0]] = np.median(rise_s[s0:s0 + n])
    high = (med.reshape(rows, cols) > cfg.min_rise)
    # away from the outline: the cell centres at least edge_margin inside
    yc, xc = np.mgrid[0:rows, 0:cols]
    centres = roof.origin + (np.column_stack([xc.ravel(), yc.ravel()]) + 0.5) * c
    inner = (points_in_polygon(centres, polygon) & (distance_to_edges(centres, polygon) >= cfg.edge_margin)
             ).reshape(rows, cols)
    blobs, n_blobs = ndimage.label(high, structure=np.ones((3, 3)))
    out: list[Dormer] = []
    rejected: list[str] = []
    for b in range(1, n_blobs + 1):
        mask = blobs == b
        area = mask.sum() * c * c
        if not (cfg.min_area <= area <= cfg.max_area) or not inner[mask].all():
            continue
        labels, votes = np.unique(roof.labels[mask], return_counts=True)
        k = int(labels[np.argmax(votes)])
        if k not in roof.planes:
            continue
        if votes.max() < 0.9 * votes.sum():  # across a ridge or a step: its slope would not be its bottom
            rejected.append(f"{area:.1f} m^2 on roofs {labels.tolist()}: on more than one roof plane")
            continue
        d = _dormer(xyz, cell_id, mask, roof.planes[k], k, c, cfg)
        if isinstance(d, Dormer):
            out.append(d)
        else:
            rejected.append(f"{area:.1f} m^2 on roof {k}: {d}")
    return out, rejected


def _roof_z(coef: np.ndarray, gabled: bool, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Height of a dormer roof over slope coordinates ``u, v (n,)``: gabled ``a - s |v - vc|`` or a plane
    (coefficients of :func:`_fit_roof`)."""
    return coef[0] - coef[1] * np.abs(v - coef[2]) if gabled else coef[0] + coef[1] * u + coef[2] * v


def _roof_model(u: np.ndarray, v: np.ndarray, z: np.ndarray, rise: np.ndarray, u_f: float, v0: float, v1: float,
                tan_slope: float, cfg: DormerConfig) -> tuple[bool, np.ndarray, float] | str:
    """The roof over the points on top (above the slope, inside the sides, behind the front), gabled or one
    plane: ``(gabled, coefficients, RMS)``, or why neither fits. A gable's slopes are 10 to 65 deg; a single plane
    slopes down to the front (or is flat), not sideways, and at least ``cfg.min_shed_drop_deg`` less than the roof
    it stands on (``tan_slope``)."""
    top = (rise > cfg.fit_min_rise) & (v > v0 + 0.2) & (v < v1 - 0.2) & (u < u_f - 0.3)
    if top.sum() < 10:
        return f"{int(top.sum())} roof points"
    g, rms_g = _fit_roof(u[top], v[top], z[top], v0, v1, True)
    p, rms_p = _fit_roof(u[top], v[top], z[top], v0, v1, False)
    g_ok = np.tan(np.radians(10.0)) < g[1] < np.tan(np.radians(65.0))
    steepest = -np.tan(np.arctan(tan_slope) - np.radians(cfg.min_shed_drop_deg))  # dz/du of the steepest shed roof
    p_shape = abs(p[2]) < np.tan(np.radians(8.0)) and p[1] < 0.05 and (rms_p < cfg.gable_gain * rms_g or not g_ok)
    p_ok = p_shape and steepest < p[1]
    if g_ok and not p_ok and rms_g <= cfg.max_rmse:
        return True, g, rms_g
    if p_ok and rms_p <= cfg.max_rmse:
        return False, p, rms_p
    if p_shape and rms_p <= cfg.max_rmse:
        return (f"its roof plane runs within {cfg.min_shed_drop_deg:.0f} deg of the slope's pitch "
                f"({np.degrees(np.arctan(-p[1])):.0f} against {np.degrees(np.arctan(tan_slope)):.0f} deg)")
    return f"roof fit RMS {min(rms_g, rms_p):.2f} m"


def _edge_costs(t: np.ndarray, rise: np.ndarray, r_model: np.ndarray, cand: np.ndarray, side: int) -> np.ndarray:
    """Least-squares cost of each candidate edge position ``cand (k,)`` along a coordinate ``t (n,)``: the points'
    ``rise`` above the slope against the dormer's (``r_model``) on its side and zero beyond (``side`` +1: the
    dormer lies at t < e). A blurred edge costs least at its middle."""
    inside = (t[None, :] < cand[:, None]) if side > 0 else (t[None, :] > cand[:, None])
    return np.where(inside, (rise - r_model)[None, :] ** 2, rise[None, :] ** 2).sum(1)


def on_top(xy: np.ndarray, z: np.ndarray, radius: float, gap: float) -> np.ndarray:
    """Which points ``xy (n, 2)``, heights ``z (n,)``, lie on the top surface: none within ``radius`` across
    stands more than ``gap`` above them (a wall's points stand under its eave) -> ``(n,) bool``."""
    pairs = cKDTree(xy).query_pairs(radius, output_type="ndarray")
    above = np.full(len(z), -np.inf)
    np.maximum.at(above, pairs[:, 0], z[pairs[:, 1]])
    np.maximum.at(above, pairs[:, 1], z[pairs[:, 0]])
    return above - z <= gap


def _wall_span(t: np.ndarray, cfg: DormerConfig) -> tuple[float, float] | None:
    """Where the points under the top surface at an edge, positions ``t (n,)`` across it, form a wall: their
    quartiles, when there are at least ``cfg.wall_min_points`` of them within ``cfg.wall_max_iqr`` (a facade's
    points stand so; the matching's smear is a ramp), else None."""
    if len(t) < cfg.wall_min_points:
        return None
    q1, q3 = np.percentile(t, [25, 75])
    return (float(q1), float(q3)) if q3 - q1 <= cfg.wall_max_iqr else None


def _dormer(xyz: np.ndarray, cell_id: np.ndarray, mask: np.ndarray, plane: np.ndarray, label: int, cell: float,
            cfg: DormerConfig) -> Dormer | str:
    """The block of one blob of cells ``mask`` on the roof ``plane``, or why it does not fit as a dormer."""
    n = plane[:3]
    slope = np.degrees(np.arccos(np.clip(n[2], -1.0, 1.0)))
    if slope < cfg.min_slope_deg:
        return f"on a {slope:.0f} deg roof"
    du = n[:2] / np.linalg.norm(n[:2])  # downslope
    dv = np.array([-du[1], du[0]])
    tan_s = np.tan(np.radians(slope))

    def slope_z(u_pos: float) -> float:  # the slope's height at u (constant across v)
        return float(plane_z(plane, (u_pos * du)[None])[0])

    grown = ndimage.binary_dilation(mask, np.ones((5, 5)))  # the slope around it too, for the edges
    sel = np.isin(cell_id, np.flatnonzero(grown.ravel()))
    pts = xyz[sel]
    rise = pts[:, 2] - plane_z(plane, pts[:, :2])
    u, v = pts[:, :2] @ du, pts[:, :2] @ dv
    high = (rise > cfg.min_rise) & np.isin(cell_id[sel], np.flatnonzero(mask.ravel()))
    top = on_top(pts[:, :2], rise, cfg.top_radius, cfg.top_gap)
    if high.sum() < 12:
        return f"{int(high.sum())} points above the slope"
    v0, v1 = np.percentile(v[high], [2, 98])
    u_f = float(np.percentile(u[high], 98))
    for k in range(3):  # the roof within the first extents, the extents from that roof (twice), the final roof
        if v1 - v0 < 1.0:
            return f"{v1 - v0:.1f} m wide"
        fit = _roof_model(u[top], v[top], pts[top, 2], rise[top], u_f, v0, v1, tan_s, cfg)
        if isinstance(fit, str):
            return fit
        gabled, coef, rmse = fit
        if k == 2:
            break
        # the walls where the points' height above the slope steps from the roof's to zero: the sides in a strip
        # behind the front, the front in a band inside the sides
        r_model = np.maximum(_roof_z(coef, gabled, u, v) - (pts[:, 2] - rise), 0.0)  # under the slope: the slope
        vc = 0.5 * (v0 + v1)
        eave = float(min(_roof_z(coef, gabled, np.array([u_f]), np.array([w]))[0] for w in (v0, v1)))
        # where a wall shows under an eave, its points are not the roof's edge: that is the top surface's (the
        # sides' strip then leaves the front wall's points out)
        wall = ~top & (rise > 0.25 * r_model) & (rise < 0.75 * r_model)
        band = (v > v0 + 0.3) & (v < v1 - 0.3)
        front_wall = _wall_span(u[band & wall & (np.abs(u - u_f) < 1.0)], cfg)
        # (the strip where the eaves stand at least 0.3 m above the slope: behind, the roof runs into the slope
        # and a wider block would look the same)
        st = (u > u_f - max((eave - slope_z(u_f) - 0.3) / tan_s, 0.5)) & (u < u_f - 0.15)
        if front_wall is not None:  # without the front wall's points
            st &= top | (u < front_wall[0] - 0.1) | (u > front_wall[1] + 0.1)
        # candidates from the inside out: where the costs tie (the roof has come down to the slope), the innermost
        left, right = np.arange(vc, v0 - 1.0, -0.05), np.arange(vc, v1 + 1.0, 0.05)
        use = [st & (top | (_wall_span(v[st & wall & (np.abs(v - e) < 1.0)], cfg) is None)) for e in (v0, v1)]
        v0 = float(left[np.argmin(_edge_costs(v[use[0]], rise[use[0]], r_model[use[0]], left, -1))])
        v1 = float(right[np.argmin(_edge_costs(v[use[1]], rise[use[1]], r_model[use[1]], right, 1))])
        fronts = np.arange(u_f - 1.0, u_f + 1.0, 0.05)  # from the inside out
        use_f = band & (top | (front_wall is None))
        u_f = float(fronts[np.argmin(_edge_costs(u[use_f], rise[use_f], r_model[use_f], fronts, 1))])
    vc = coef[2] if gabled else 0.5 * (v0 + v1)
    if gabled:  # its sides as far apart as found, centred on the ridge (the smear beside a dormer shifts a side)
        v0, v1 = vc - 0.5 * (v1 - v0), vc + 0.5 * (v1 - v0)
    z_main_f = slope_z(u_f)  # the slope rises behind: z = z_main_f + tan_s * (u_f - u)
    roofs = []
    if gabled:
        a, s, _ = coef
        z_eave = a - s * (vc - v0)
        u_meet = u_f - (a - z_main_f) / tan_s  # where the ridge runs into the slope
        for side in (-1.0, 1.0):  # z <= a - s * side * (v - vc): n = (s * side * dv, 1)
            roofs.append(np.append(np.append(s * side * dv, 1.0), -(a + s * side * vc)))
    else:
        a, bu, bv = coef
        z_eave = float(min(a + bu * u_f + bv * v0, a + bu * u_f + bv * v1))
        u_meet = min((z_main_f + tan_s * u_f - a - bv * w) / (bu + tan_s) for w in (v0, v1))
        roofs.append(np.append(np.append(-(bu * du + bv * dv), 1.0), -a))
    if z_eave - z_main_f < cfg.min_wall:
        return f"eaves {z_eave - z_main_f:.2f} m above the slope"
    if u_f - u_meet > 10.0:
        return f"runs {u_f - u_meet:.1f} m into the slope"
    # front, sides, the roof, and the slope it stands on as its bottom: behind, the block ends where its roof
    # runs into the slope
    # (where the front's wall showed under the eave, the block's front stands on it and the roof overhangs it)
    u_wall = u_f if front_wall is None else min(u_f, 0.5 * (front_wall[0] + front_wall[1]))
    walls = [np.array([du[0], du[1], 0.0, -u_wall]), np.array([dv[0], dv[1], 0.0, -v1]),
             np.array([-dv[0], -dv[1], 0.0, v0])]
    planes = np.array([*walls, *roofs, -plane])
    planes /= np.linalg.norm(planes[:, :3], axis=1)[:, None]
    return Dormer(planes, label, "gabled" if gabled else "shed", rmse, u_f - u_wall)

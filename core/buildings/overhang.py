"""Roof overhangs from the ortho DSM.

The wall outline (from the facade points) is projected onto the DSM; each outline edge is moved along its
outward normal to the eave, measured on profiles across the edge and reduced by the median: on each profile the
sub-pixel zero crossing of the second directional derivative of the smoothed height map taken in the gradient
direction (where the height drops fastest) finds the step, and a fit of a straight run on either side of it in
the unsmoothed heights places it (the smoothed inflection is drawn towards a steep roof behind the eave). A DSM
cell holds its highest point, which puts a step half a cell outward on average: that is taken off. The offset
is the overhang width of that edge; :func:`overhang_surfaces` extends the roof polygons over it and closes the
underside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..model.raster import Raster
from .geometry import plane_line

MIN_EDGE = 1e-3
"""Metres: eave points closer than this are one point (CityJSON stores vertices to the millimetre)."""


@dataclass(frozen=True)
class OverhangConfig:
    """max_width : search range beyond the wall (m); smooth_px : Gaussian sigma (px) before derivatives;
    min_width : narrower overhangs are set to 0 (m); thickness : overhang slab thickness (m); edge_shift_px :
    how far outward the DSM puts a step edge (px), taken off the measured width: a cell of the surface stage's DSM
    holds its highest supported point, so the eave's step lies at the outer side of the cell the eave crosses,
    half a cell outward on average (without it the simulated city's widths came out 0.117 m = 0.75 px too wide)."""

    max_width: float = 1.5
    smooth_px: float = 1.0
    min_width: float = 0.15
    thickness: float = 0.2
    edge_shift_px: float = 0.5


def _derivatives(z: np.ndarray, cell: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Gradient magnitude and the second derivative along the gradient of a north-up grid (world units)."""
    zs = ndimage.gaussian_filter(z, sigma)
    gy_r, gx = np.gradient(zs, cell)
    gy = -gy_r  # rows run south
    gxy_r, gxx = np.gradient(gx, cell)
    gyy_r, _ = np.gradient(gy, cell)
    gxy = -gxy_r
    gyy = -gyy_r
    g2 = gx * gx + gy * gy
    with np.errstate(invalid="ignore", divide="ignore"):
        d2 = (gx * gx * gxx + 2 * gx * gy * gxy + gy * gy * gyy) / g2
    return np.sqrt(g2), np.nan_to_num(d2)


def edge_offsets(polygon: np.ndarray, dsm: Raster, start: float, stop: float,
                 smooth_px: float = 1.0) -> np.ndarray:
    """Signed offset (m, outward positive) of the DSM's eave from each edge of a counter-clockwise
    ``polygon (m, 2)``: on profiles across the edge (every DSM cell along its middle 70 %, sampled from ``start``
    to ``stop`` metres outward), the sub-pixel zero crossing of the second derivative along the gradient next to
    the steepest drop, placed by :func:`_step_fit`, reduced by the median over the profiles. NaN where no profile
    finds one."""
    lo = polygon.min(0) - max(abs(start), abs(stop)) - 5 * dsm.cell
    hi = polygon.max(0) + max(abs(start), abs(stop)) + 5 * dsm.cell
    c0, r0 = np.floor(dsm.world_to_cell(np.array([[lo[0], hi[1]]]))[0]).astype(int)
    c1, r1 = np.ceil(dsm.world_to_cell(np.array([[hi[0], lo[1]]]))[0]).astype(int)
    rows, cols = dsm.shape
    c0, r0 = max(c0, 0), max(r0, 0)
    c1, r1 = min(c1, cols - 1), min(r1, rows - 1)
    m = len(polygon)
    out = np.full(m, np.nan)
    if c1 - c0 < 3 or r1 - r0 < 3:
        return out
    sub = np.asarray(dsm.data[r0:r1 + 1, c0:c1 + 1], dtype=np.float64)
    if np.isnan(sub).all():
        return out
    if np.isnan(sub).any():
        _, (ri, ci) = ndimage.distance_transform_edt(np.isnan(sub), return_indices=True)
        sub = sub[ri, ci]
    win = Raster(sub, dsm.x0 + c0 * dsm.cell, dsm.y0 - r0 * dsm.cell, dsm.cell, dsm.crs)
    G, D2 = _derivatives(sub, dsm.cell, smooth_px)
    gw = Raster(G, win.x0, win.y0, win.cell, win.crs)
    dw = Raster(D2, win.x0, win.y0, win.cell, win.crs)
    step = dsm.cell / 4
    s = np.arange(start, stop, step)
    for i in range(m):
        p0, p1 = polygon[i], polygon[(i + 1) % m]
        d = p1 - p0
        length = float(np.linalg.norm(d))
        if length < 1e-9:  # a repeated vertex: no edge to measure
            continue
        d /= length
        nrm = np.array([d[1], -d[0]])  # outward for a counter-clockwise outline
        ts = np.arange(0.15 * length, 0.85 * length + 1e-9, dsm.cell)
        if len(ts) == 0:
            continue
        pts = p0 + ts[:, None, None] * d + s[None, :, None] * nrm  # (profiles, samples, 2)
        g = gw.sample(pts.reshape(-1, 2)).reshape(len(ts), len(s))
        dd = dw.sample(pts.reshape(-1, 2)).reshape(len(ts), len(s))
        zr = win.sample(pts.reshape(-1, 2)).reshape(len(ts), len(s))
        found = []
        for gp, dp, zp in zip(g, dd, zr):
            if np.isnan(gp).all():
                continue
            k = int(np.nanargmax(gp))
            # zero crossing of D2 next to the gradient maximum
            j = np.arange(max(k - 8, 0), min(k + 8, len(s) - 1))
            hit = j[(dp[j] == 0) | (dp[j] * dp[j + 1] < 0)]
            if len(hit):
                den = dp[hit] - dp[hit + 1]
                frac = np.where(den != 0, dp[hit] / np.where(den != 0, den, 1.0), 0.0)
                cand = s[hit] + frac * step
                found.append(_step_fit(s, zp, float(cand[np.argmin(np.abs(cand - s[k]))]), dsm.cell))
        if found:
            out[i] = float(np.median(found))
    return out


def _step_fit(s: np.ndarray, z: np.ndarray, guess: float, cell: float, reach: float = 1.0) -> float:
    """Where a height profile ``z`` over ``s (k,)`` steps: the position within two cells of ``guess`` that best
    splits it into a straight run on either side (each ``reach`` long, least squares). Unlike the smoothed
    profile's inflection it is not drawn towards a steep roof behind the eave. The candidates are scored at once:
    a line's squared residuals are ``S_zz - S_sz^2 / S_ss`` from its window's centred sums."""
    cand = s[(s > guess - 2 * cell) & (s < guess + 2 * cell)]
    if not len(cand):
        return guess
    e = cand[:, None]
    sse = np.zeros(len(cand))
    for w in ((s >= e - reach) & (s < e), (s > e) & (s <= e + reach)):  # (candidates, samples) windows
        n = w.sum(1)
        bad = (n < 3) | (w & np.isnan(z)).any(1)
        zw = np.where(w, np.nan_to_num(z), 0.0)
        nn = np.maximum(n, 1)
        ds = np.where(w, s - (w @ s / nn)[:, None], 0.0)
        dz = np.where(w, zw - (zw.sum(1) / nn)[:, None], 0.0)
        s_ss, s_sz, s_zz = (ds * ds).sum(1), (ds * dz).sum(1), (dz * dz).sum(1)
        sse += np.where(bad, np.inf, s_zz - s_sz**2 / np.where(s_ss > 0, s_ss, 1.0))
    k = int(np.argmin(sse))
    return float(cand[k]) if np.isfinite(sse[k]) else guess


def overhang_widths(polygon: np.ndarray, dsm: Raster, cfg: OverhangConfig = OverhangConfig()) -> np.ndarray:
    """Overhang width (m) of each outline edge (edge i from corner i to i+1 of the counter-clockwise
    ``polygon (m, 2)``); NaN where no eave was found."""
    w = edge_offsets(polygon, dsm, -2 * dsm.cell, cfg.max_width + 2 * dsm.cell, cfg.smooth_px)
    w = w - cfg.edge_shift_px * dsm.cell
    return np.where(np.isnan(w), np.nan, np.where(w < cfg.min_width, 0.0, np.minimum(w, cfg.max_width)))


def within_edge(xy: np.ndarray, p0: np.ndarray, p1: np.ndarray, tol: float = 1e-3) -> bool:
    """Whether the points ``xy (n, 2)`` of a wall face on the plane of the outline edge ``p0``-``p1`` (2,) lie
    between the edge's ends (within ``tol`` m): a face on the plane beyond them stands inside the outline."""
    d = p1 - p0
    length = float(np.linalg.norm(d))
    t = (xy - p0) @ d / length
    return bool(t.min() >= -tol and t.max() <= length + tol)


def _offset_corners(polygon: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Mitred corners of the outline offset outward by a width per edge (m, 2). A two-corner ``polygon`` is an open
    run (a wall inside the outline): both ends move straight out by the first edge's width."""
    m = len(polygon)
    if m == 2:
        d = (polygon[1] - polygon[0]) / np.linalg.norm(polygon[1] - polygon[0])
        return polygon + widths[0] * np.array([d[1], -d[0]])
    out = np.zeros_like(polygon)
    for i in range(m):
        a0, a1 = polygon[i - 1], polygon[i]
        b0, b1 = polygon[i], polygon[(i + 1) % m]
        da = (a1 - a0) / np.linalg.norm(a1 - a0)
        db = (b1 - b0) / np.linalg.norm(b1 - b0)
        na, nb = np.array([da[1], -da[0]]), np.array([db[1], -db[0]])
        pa, pb = a0 + widths[i - 1] * na, b0 + widths[i] * nb
        A = np.column_stack([da, -db])
        if abs(np.linalg.det(A)) < 1e-9:
            out[i] = polygon[i] + widths[i] * nb
        else:
            t = np.linalg.solve(A, pb - pa)
            out[i] = pa + t[0] * da
    return out


def _ring(*idx: int) -> list[int]:
    """A ring's vertex indices without a repeat of the one before (a quadrilateral whose two corners are one vertex
    -> its triangle)."""
    return [v for k, v in enumerate(idx) if v != idx[k - 1]]


def _orient(V: list[np.ndarray], ring: list[int], want: np.ndarray) -> list[int]:
    """The ring, reversed if its normal points away from ``want``."""
    P = np.asarray([V[i] for i in ring])
    c = P - P.mean(0)
    n = np.cross(c, np.roll(c, -1, axis=0)).sum(0)
    return ring if n @ want >= 0 else ring[::-1]


def overhang_surfaces(vertices: np.ndarray, faces: list[tuple[str, list[int]]], polygon: np.ndarray,
                      widths: np.ndarray, wall_of_edge: dict[int, list[int]], roof_plane_of_face: dict[int, np.ndarray],
                      thickness: float) -> tuple[np.ndarray, list[tuple[str, list[int]]]]:
    """Extend the roof over each outline edge with an overhang and close the overhang's underside.

    Parameters
    ----------
    vertices : (n, 3) body vertices; faces : body faces as (kind, ring)
    wall_of_edge : outline edge index -> indices (into ``faces``) of the wall faces on that edge's plane
    roof_plane_of_face : face index -> its plane (4,) for the roof faces

    Returns
    -------
    vertices : (n + k, 3) with the new vertices appended; new faces (kind, ring) of kinds ``overhang_roof``,
    ``overhang_fascia`` and ``overhang_underside``
    """
    V = [v for v in vertices]
    new: list[tuple[str, list[int]]] = []
    mitre = _offset_corners(polygon, widths)
    m = len(polygon)
    edge_owner: dict[tuple[int, int], int] = {}
    for fi, (_, ring) in enumerate(faces):
        for a, b in zip(ring, ring[1:] + ring[:1]):
            edge_owner[(a, b)] = fi

    def add(p: np.ndarray) -> int:
        V.append(np.asarray(p, dtype=np.float64))
        return len(V) - 1

    for i in range(m):
        w = widths[i]
        if not np.isfinite(w) or w <= 0:
            continue
        p0, p1 = polygon[i], polygon[(i + 1) % m]
        d = (p1 - p0) / np.linalg.norm(p1 - p0)
        nrm = np.array([d[1], -d[0]])
        outer = np.append(nrm, -(nrm @ p0) - w)  # vertical plane of the eave line
        outer = np.array([outer[0], outer[1], 0.0, outer[2]])
        length = float(np.linalg.norm(p1 - p0))
        for wf in wall_of_edge.get(i, []):
            ring = faces[wf][1]
            if not within_edge(vertices[ring, :2], p0, p1):
                continue  # on the edge's plane beyond its ends: a wall inside the outline (above a lower roof)
            for a, b in zip(ring, ring[1:] + ring[:1]):
                rf = edge_owner.get((b, a))
                if rf is None or rf not in roof_plane_of_face:
                    continue
                if (vertices[faces[rf][1], :2].mean(0) - p0) @ nrm > 0:
                    continue  # a roof in front of the wall (the lower roof at an interior wall's foot)
                qs = []
                for v in (a, b):
                    pv = vertices[v]
                    t = (pv[:2] - p0) @ d
                    planes_here = [roof_plane_of_face[f] for (x, y), f in edge_owner.items()
                                   if x == v and f in roof_plane_of_face]
                    if abs(t) < 1e-3:
                        xy = mitre[i]
                    elif abs(t - length) < 1e-3:
                        xy = mitre[(i + 1) % m]
                    else:
                        xy = pv[:2] + w * nrm
                    q = None
                    if len(planes_here) >= 2 and abs(t) > 1e-3 and abs(t - length) > 1e-3:
                        # the roofs' meeting line (a hip, a valley) carried out to the eave line; one running
                        # nearly along the eave (two roofs sloping the same way) meets it far off, or never
                        ln = plane_line(planes_here[0], planes_here[1])
                        if ln is not None and abs(ln[1] @ outer[:3]) > 1e-6:
                            s = -(outer[:3] @ ln[0] + outer[3]) / (outer[:3] @ ln[1])
                            q = ln[0] + s * ln[1]
                            if np.linalg.norm(q[:2] - xy) > 2 * w + 0.1:
                                q = None
                    if q is None:
                        pl = roof_plane_of_face[rf]
                        q = np.array([xy[0], xy[1], -(pl[0] * xy[0] + pl[1] * xy[1] + pl[3]) / pl[2]])
                    qs.append(q)
                pa, pb = vertices[a], vertices[b]
                qa, qb = qs
                # the eave points of a short wall segment between converging edges can meet: its fascia would have
                # no width (a 0.2 mm one on the rendered demo, which CityJSON's 1 mm vertices cannot hold), and the
                # overhang over it is a triangle
                meet = np.linalg.norm(qa - qb) < MIN_EDGE
                if meet and np.linalg.norm(pa - pb) < MIN_EDGE:
                    continue
                down = np.array([0.0, 0.0, thickness])
                ia, ib, iqa = a, b, add(qa)
                ua, ub, uqa = add(pa - down), add(pb - down), add(qa - down)
                iqb, uqb = (iqa, uqa) if meet else (add(qb), add(qb - down))
                new.append(("overhang_roof", _orient(V, _ring(ia, ib, iqb, iqa), np.array([0.0, 0.0, 1.0]))))
                if not meet:
                    new.append(("overhang_fascia", _orient(V, [iqa, iqb, uqb, uqa], np.append(nrm, 0.0))))
                new.append(("overhang_underside", _orient(V, _ring(ua, ub, uqb, uqa), np.array([0.0, 0.0, -1.0]))))
    return np.asarray(V), new

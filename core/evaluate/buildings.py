"""Metrics of reconstructed buildings against ground truth (tests, benchmark, reports).

Per building: outline corner deviation (each true footprint corner to the nearest reconstructed corner),
roof plane normal error (each true roof plane against the reconstructed roof surface over it), overhang width
error (each exposed true wall edge against the reconstructed outline edge that runs along it), whether the body
is a closed valid solid, which path it took, the time it needed, and how many of its walls no facade point
showed (placed by an assumed overhang, see :func:`..buildings.contour.walls_under_roof_outline`); where the
building has dormers, how far the model's dormer walls stand from the true ones (:class:`DormerProbe`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..buildings.attributes import building_attributes, footprint_samples, model_top_height
from ..buildings.geometry import points_in_polygon
from ..buildings.model import BuildingModel
from ..matching.features import segment_distance

DORMER_RISE = 0.3
"""A dormer's walls are where the top surface rises this far (m) above the slope it stands on."""


@dataclass(frozen=True)
class DormerProbe:
    """Where a true dormer's walls stand, measured on two lines of world points: ``across (k, 2)`` from beyond one
    side to beyond the other, 0.3 m behind its front, and ``along (j, 2)`` down its middle from behind to beyond its
    front; ``across_t``, ``along_t`` the lines' coordinates (m, along grows outwards); ``slope_across``,
    ``slope_along`` the height of the roof it stands on there; ``sides (2,)`` and ``front`` the coordinates where
    the true top surface stands over :data:`DORMER_RISE` above that roof (the roof's edge, its overhang included)."""

    across: np.ndarray
    across_t: np.ndarray
    slope_across: np.ndarray
    along: np.ndarray
    along_t: np.ndarray
    slope_along: np.ndarray
    sides: np.ndarray
    front: float

    def walls(self, top_height) -> tuple[np.ndarray, float] | None:
        """The sides ``(2,)`` and front that ``top_height(xy (n, 2)) -> (n,)`` gives on the probe's lines, or None
        where it nowhere rises over :data:`DORMER_RISE` above the roof (no dormer there)."""
        on_a = self.across_t[top_height(self.across) - self.slope_across > DORMER_RISE]
        on_f = self.along_t[top_height(self.along) - self.slope_along > DORMER_RISE]
        if not len(on_a) or not len(on_f):
            return None
        return np.array([on_a.min(), on_a.max()]), float(on_f.max())


def _dormer_probe(b, part, step: float = 0.01) -> DormerProbe | None:
    """The probe of a simulator dormer ``part`` on ``b``'s main body (its front faces the nearer of the body's
    y0 / y1 walls, its ridge runs across that slope, :func:`..simulate.city._dormer`)."""
    main = b.parts[0]
    x0, y0, x1, y1 = part.rect
    south = abs(y0 - main.rect[1]) < abs(y1 - main.rect[3])
    front, out = (y0, -1.0) if south else (y1, 1.0)  # the front's y and the outward direction along y
    t_a = np.arange(x0 - 1.0, x1 + 1.0, step)
    across = np.column_stack([t_a, np.full(len(t_a), front - 0.3 * out)])
    t_f = np.arange(-1.5, 1.0, step)  # outwards from the front
    along = np.column_stack([np.full(len(t_f), 0.5 * (x0 + x1)), front + out * t_f])
    probe = DormerProbe(b.to_world(across), t_a, main.z_top(across), b.to_world(along), t_f, main.z_top(along),
                        np.zeros(2), 0.0)  # the true walls follow, measured on the probe's own lines
    walls = probe.walls(lambda xy: _top_height(b, xy))
    return None if walls is None else replace(probe, sides=walls[0], front=walls[1])


@dataclass(frozen=True)
class BuildingTruth:
    """Ground truth of one building.

    name : label; footprint : list of (m, 2) wall outline rings; planes : list of ((3,) unit normal up,
    (3,) a point on the plane inside its face); edges : list of ((2, 2) wall segment, overhang width) for the
    exposed outline edges; top : (k, 3) the true top surface on a 0.5 m grid over the footprint, 0.5 m inside
    its walls (roof installations included); roof_70p : 70th percentile of the top surface over the whole
    footprint (absolute height, m); volume : of the body between the ground height and the top surface (m^3);
    dormers : one :class:`DormerProbe` per dormer of the simulator's (those its lines find)
    """

    name: str
    footprint: list[np.ndarray]
    planes: list[tuple[np.ndarray, np.ndarray]]
    edges: list[tuple[np.ndarray, float]]
    top: np.ndarray | None = None
    roof_70p: float = float("nan")
    volume: float = float("nan")
    dormers: tuple[DormerProbe, ...] = ()

    @classmethod
    def from_city(cls, b) -> BuildingTruth:
        """From a :class:`oblique_city.core.simulate.city.Building` (roof installations left out)."""
        planes = []
        for rp in b.roof_planes:
            if rp.get("kind", "roof") != "roof":
                continue
            n = np.asarray(rp["normal"], dtype=np.float64)
            n = n if n[2] > 0 else -n
            p = _visible_point(b, np.asarray(rp["polygon"], dtype=np.float64), n)
            if p is not None:  # planes entirely hidden under other parts are not measurable
                planes.append((n, p))
        edges = [(np.asarray(e["segment"], dtype=np.float64), float(e["width"]))
                 for e in b.overhang_edges() if e["exposed"]]
        rings = [np.asarray(r, dtype=np.float64) for r in b.footprint]
        xy = _inner_grid(rings)
        step = 0.25
        full = np.concatenate([footprint_samples(r, step) for r in rings])
        top = _top_height(b, full)
        probes = [_dormer_probe(b, p) for p in b.parts if p.kind == "dormer"]
        return cls(f"{b.id}:{b.name}", rings, planes, edges, np.column_stack([xy, _top_height(b, xy)]),
                   float(np.percentile(top, 70)), float(np.sum(top - b.ground_z) * step**2),
                   tuple(p for p in probes if p is not None))

    @classmethod
    def from_synthetic(cls, sb) -> BuildingTruth:
        """From a :class:`oblique_city.core.buildings.synthetic.SyntheticBuilding`."""
        fp = sb.footprint
        lo, hi = fp.min(0), fp.max(0)
        X, Y = np.meshgrid(np.arange(lo[0], hi[0], 0.25), np.arange(lo[1], hi[1], 0.25))
        xy = np.column_stack([X.ravel(), Y.ravel()])
        xy = xy[points_in_polygon(xy, fp)]
        z = sb.height(xy)
        P = np.column_stack([xy, z])
        planes = []
        for pl in sb.roof_planes():
            on = np.abs(P @ pl[:3] + pl[3]) < 1e-6
            if on.sum() == 0:
                continue
            q = P[on]
            planes.append((pl[:3], q[np.argmin(np.linalg.norm(q - np.median(q, 0), axis=1))]))
        m = len(fp)
        edges = [(np.stack([fp[i], fp[(i + 1) % m]]), float(sb.overhangs[i])) for i in range(m)]
        xy = _inner_grid([fp])
        return cls(sb.name, [fp], planes, edges, np.column_stack([xy, sb.height(xy)]))


def _inner_grid(rings: list[np.ndarray], step: float = 0.5, margin: float = 0.5) -> np.ndarray:
    """Grid points (k, 2) inside the footprint ``rings`` and at least ``margin`` from their walls."""
    allp = np.concatenate(rings)
    lo, hi = allp.min(0), allp.max(0)
    X, Y = np.meshgrid(np.arange(lo[0] + step / 2, hi[0], step), np.arange(lo[1] + step / 2, hi[1], step))
    xy = np.column_stack([X.ravel(), Y.ravel()])
    inside = np.zeros(len(xy), bool)
    for r in rings:
        inside |= points_in_polygon(xy, r)
    xy = xy[inside]
    d = np.full(len(xy), np.inf)
    for r in rings:
        for a, b in zip(r, np.roll(r, -1, axis=0)):
            d = np.minimum(d, segment_distance(xy, np.broadcast_to(a, xy.shape), np.broadcast_to(b, xy.shape)))
    return xy[d >= margin]


def _top_height(b, xy: np.ndarray) -> np.ndarray:
    """Highest roof surface of any part of a simulator building over world points (n, 2)."""
    uv = b.to_local(xy)
    top = np.full(len(xy), -np.inf)
    for part in b.parts:
        x0, y0, x1, y1 = part.rect
        o = part.overhang  # edges x0, x1, y0, y1
        m = (uv[:, 0] >= x0 - o[0]) & (uv[:, 0] <= x1 + o[1]) & (uv[:, 1] >= y0 - o[2]) & (uv[:, 1] <= y1 + o[3])
        if m.any():
            top[m] = np.maximum(top[m], part.z_top(uv[m]))
    return top


def _visible_point(b, poly: np.ndarray, n: np.ndarray, step: float = 0.25) -> np.ndarray | None:
    """The point of a roof plane polygon (k, 3) where that plane is the top surface that lies deepest inside the
    visible region (farthest from hidden or outside samples); None when under 1 m^2 of it is visible."""
    from scipy.spatial import cKDTree

    lo, hi = poly[:, :2].min(0) - step, poly[:, :2].max(0) + step
    X, Y = np.meshgrid(np.arange(lo[0], hi[0], step), np.arange(lo[1], hi[1], step))
    xy = np.column_stack([X.ravel(), Y.ravel()])
    d = n @ poly[0]
    z = (d - n[0] * xy[:, 0] - n[1] * xy[:, 1]) / n[2]
    vis = points_in_polygon(xy, poly[:, :2]) & (z >= _top_height(b, xy) - 0.05)
    if vis.sum() * step * step < 1.0 or vis.all():
        return None
    depth, _ = cKDTree(xy[~vis]).query(xy[vis])
    k = int(np.argmax(depth))
    return np.array([xy[vis][k, 0], xy[vis][k, 1], z[vis][k]])


@dataclass(frozen=True)
class BuildingScore:
    """Figures of one building (NaN where not measurable)."""

    name: str
    id: str
    path: str
    reason: str
    closed: bool
    seconds: float
    corner_median: float
    corner_mean: float
    corner_max: float
    n_corners_true: int
    n_corners_est: int
    normal_median_deg: float
    normal_max_deg: float
    overhang_errors: list[float]
    overhang_median: float
    walls_inferred: int = 0
    roof_rmse: float = float("nan")
    roof_coverage: float = float("nan")
    roof_rmse_off_steps: float = float("nan")
    roof_70p_error: float = float("nan")
    volume_error: float = float("nan")
    wall_direction_deg: float = float("nan")
    dormer_side_errors: list[float] = field(default_factory=list)
    dormer_front_errors: list[float] = field(default_factory=list)
    dormers_missed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def corner_deviation(truth: list[np.ndarray], est: np.ndarray) -> np.ndarray:
    """Distance (m) of each true corner (all rings) to the nearest estimated corner (k, 2)."""
    gt = np.concatenate(truth)
    return np.linalg.norm(gt[:, None, :] - est[None, :, :], axis=2).min(1)


def wall_direction_errors(truth: list[np.ndarray], est: np.ndarray, min_edge: float = 3.0
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Angle (deg) between each estimated outline edge of at least ``min_edge`` m (``est (m, 2)``, a ring) and the true
    edge (of the rings ``truth``) nearest to its midpoint, and the edges' lengths (m): ``(k,)``, ``(k,)``."""
    a0 = np.concatenate(truth)
    td = np.concatenate([np.roll(r, -1, axis=0) - r for r in truth])
    tl2 = np.maximum(np.sum(td**2, axis=1), 1e-12)
    ed = np.roll(est, -1, axis=0) - est
    length = np.linalg.norm(ed, axis=1)
    keep = length >= min_edge
    mid = est[keep] + 0.5 * ed[keep]
    t = np.clip(np.einsum("kij,ij->ki", mid[:, None, :] - a0[None], td) / tl2, 0.0, 1.0)
    near = np.argmin(np.linalg.norm(mid[:, None, :] - (a0[None] + t[..., None] * td[None]), axis=2), axis=1)
    c = np.abs(np.sum(ed[keep] * td[near], axis=1)) / (length[keep] * np.sqrt(tl2[near]))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0))), length[keep]


def normal_errors(truth: BuildingTruth, model: BuildingModel) -> np.ndarray:
    """Angle (deg) between each true roof plane and the reconstructed roof surface over its inner point (the
    nearest roof surface where none covers it)."""
    roofs = [(model.vertices[list(s.ring)]) for s in model.surfaces if s.kind == "roof"]
    if not roofs:
        return np.full(len(truth.planes), np.nan)
    out = []
    for n, p in truth.planes:
        best, best_d = None, np.inf
        for ring in roofs:
            if points_in_polygon(p[None, :2], ring[:, :2])[0]:
                d = abs(np.mean(ring[:, 2]) - p[2]) * 0.0
            else:
                d = float(np.min(np.linalg.norm(ring[:, :2] - p[:2], axis=1)))
            if d < best_d:
                best, best_d = ring, d
        c = best - best.mean(0)
        nn = np.cross(c, np.roll(c, -1, axis=0)).sum(0)
        nn /= np.linalg.norm(nn)
        out.append(float(np.degrees(np.arccos(np.clip(abs(nn @ n), 0, 1)))))
    return np.asarray(out)


def overhang_errors(truth: BuildingTruth, model: BuildingModel, max_offset: float = 1.0) -> np.ndarray:
    """|estimated - true| overhang width (m) for each exposed true edge matched to a parallel reconstructed edge
    whose line passes within ``max_offset`` of the true edge's midpoint and overlaps it."""
    fp = model.footprint
    m = len(fp)
    out = []
    for seg, w in truth.edges:
        d = seg[1] - seg[0]
        length = np.linalg.norm(d)
        d = d / length
        mid = seg.mean(0)
        best, best_off = None, max_offset
        for i in range(m):
            a, b = fp[i], fp[(i + 1) % m]
            e = (b - a) / np.linalg.norm(b - a)
            if abs(e @ d) < np.cos(np.radians(10)):
                continue
            off = abs((mid - a) @ np.array([-e[1], e[0]]))
            t = (mid - a) @ e
            if off < best_off and -0.25 * length <= t <= np.linalg.norm(b - a) + 0.25 * length:
                best, best_off = i, off
        if best is not None:
            out.append(abs(float(model.overhangs[best]) - w))
    return np.asarray(out)


def roof_height_errors(truth: BuildingTruth, model: BuildingModel) -> np.ndarray:
    """Model top height minus true top height (m) at the truth's grid over the footprint (NaN where the model has
    no roof there)."""
    if truth.top is None or not len(truth.top):
        return np.zeros(0)
    return model_top_height(model, truth.top[:, :2]) - truth.top[:, 2]


def near_steps(top: np.ndarray, radius: float = 0.75, min_jump: float = 1.0, min_slope: float = 3.0) -> np.ndarray:
    """Samples ``top (k, 3)`` of a top surface next to a vertical step (a wall between roofs of different
    heights): some sample within ``radius`` m lies over ``min_jump`` m higher or lower and steeper than
    ``min_slope`` (3: 72 degrees, beyond any roof) -> (k,) bool. A step wall placed a decimetre off turns the
    samples beside it by the step's height (12 m beside the demo church's tower), so that the roof RMSE measures
    where the step stands more than how well the roofs fit; :func:`score_building` gives both."""
    from scipy.spatial import cKDTree

    out = np.zeros(len(top), bool)
    if len(top) < 2:
        return out
    pairs = cKDTree(top[:, :2]).query_pairs(radius, output_type="ndarray")
    if len(pairs):
        dz = np.abs(top[pairs[:, 0], 2] - top[pairs[:, 1], 2])
        d = np.linalg.norm(top[pairs[:, 0], :2] - top[pairs[:, 1], :2], axis=1)
        step = pairs[(dz > min_jump) & (dz > min_slope * d)]
        out[step.ravel()] = True
    return out


def dormer_wall_errors(truth: BuildingTruth, model: BuildingModel) -> tuple[list[float], list[float], int]:
    """|model - truth| (m) of each true dormer's two sides and of its front, on its probe's lines
    (:class:`DormerProbe`), and how many true dormers the model does not rise over."""
    sides: list[float] = []
    fronts: list[float] = []
    missed = 0
    for probe in truth.dormers:
        walls = probe.walls(lambda xy: model_top_height(model, xy))
        if walls is None:
            missed += 1
            continue
        sides += [float(v) for v in np.abs(walls[0] - probe.sides)]
        fronts.append(abs(walls[1] - probe.front))
    return sides, fronts, missed


def score_building(truth: BuildingTruth, model: BuildingModel) -> BuildingScore:
    c = corner_deviation(truth.footprint, model.footprint)
    ne = normal_errors(truth, model)
    oe = overhang_errors(truth, model)
    he = roof_height_errors(truth, model)
    seen = he[np.isfinite(he)]
    off = he[np.isfinite(he) & ~near_steps(truth.top)] if len(he) else he

    def med(a):
        return float(np.nanmedian(a)) if len(a) and np.isfinite(a).any() else float("nan")

    def rms(a):
        return float(np.sqrt(np.mean(a**2))) if len(a) else float("nan")

    attrs = building_attributes(model)
    we, wl = wall_direction_errors(truth.footprint, model.footprint)
    sides, fronts, missed = dormer_wall_errors(truth, model)
    return BuildingScore(truth.name, model.id, model.path, model.reason, bool(model.info.get("closed", False)),
                         float(model.info.get("seconds", np.nan)), med(c), float(np.mean(c)), float(np.max(c)),
                         int(sum(len(r) for r in truth.footprint)), int(len(model.footprint)), med(ne),
                         float(np.nanmax(ne)) if len(ne) and np.isfinite(ne).any() else float("nan"),
                         [float(x) for x in oe], med(oe), int(model.info.get("walls_inferred", 0)),
                         rms(seen), float(len(seen) / len(he)) if len(he) else float("nan"), rms(off),
                         float(attrs["roof_height_70p"]) - truth.roof_70p,
                         float(attrs["volume"]) / truth.volume - 1.0 if truth.volume > 0 else float("nan"),
                         float(np.sqrt(np.sum(wl * we**2) / np.sum(wl))) if len(we) else float("nan"),
                         sides, fronts, missed)


def match_truth(model: BuildingModel, truths: list[BuildingTruth]) -> int | None:
    """Index of the true building whose footprint holds the reconstructed outline's centroid (else the one with
    the nearest footprint centroid within 10 m)."""
    c = model.footprint.mean(0)
    for i, t in enumerate(truths):
        if any(points_in_polygon(c[None], r)[0] for r in t.footprint):
            return i
    d = [min(np.linalg.norm(r.mean(0) - c) for r in t.footprint) for t in truths]
    i = int(np.argmin(d))
    return i if d[i] < 10.0 else None


def summary(scores: list[BuildingScore], n_truth: int) -> dict:
    """Overall figures: pooled corner deviations (median, mean), normal and overhang errors, closed share."""
    def pool(attr):
        v = np.array([getattr(s, attr) for s in scores], dtype=np.float64)
        return v[np.isfinite(v)]

    cm = pool("corner_median")
    nm = pool("normal_median_deg")
    oh = np.array([e for s in scores for e in s.overhang_errors])
    ds = np.array([e for s in scores for e in s.dormer_side_errors])
    df = np.array([e for s in scores for e in s.dormer_front_errors])
    return {
        "buildings_true": n_truth, "buildings_reconstructed": len(scores),
        "corner_median_of_medians": float(np.median(cm)) if len(cm) else None,
        "corner_mean_of_means": float(np.mean(pool("corner_mean"))) if len(cm) else None,
        "normal_median_deg": float(np.median(nm)) if len(nm) else None,
        "wall_direction_median_deg": (float(np.median(pool("wall_direction_deg")))
                                      if len(pool("wall_direction_deg")) else None),
        "roof_rmse_median": float(np.median(pool("roof_rmse"))) if len(pool("roof_rmse")) else None,
        "roof_rmse_mean": float(np.mean(pool("roof_rmse"))) if len(pool("roof_rmse")) else None,
        "roof_rmse_off_steps_mean": (float(np.mean(pool("roof_rmse_off_steps")))
                                     if len(pool("roof_rmse_off_steps")) else None),
        "roof_70p_abs_error_median": (float(np.median(np.abs(pool("roof_70p_error"))))
                                      if len(pool("roof_70p_error")) else None),
        "volume_abs_error_median": (float(np.median(np.abs(pool("volume_error"))))
                                    if len(pool("volume_error")) else None),
        "overhang_median_error": float(np.median(oh)) if len(oh) else None,
        "overhang_p90_error": float(np.percentile(oh, 90)) if len(oh) else None,
        "dormers_found": len(df), "dormers_missed": int(sum(s.dormers_missed for s in scores)),
        "dormer_side_mean_error": float(np.mean(ds)) if len(ds) else None,
        "dormer_front_mean_error": float(np.mean(df)) if len(df) else None,
        "closed_share": float(np.mean([s.closed for s in scores])) if scores else 0.0,
        "closed_share_of_true": float(sum(s.closed for s in scores) / n_truth) if n_truth else 0.0,
        "paths": {p: sum(s.path == p for s in scores) for p in ("2d", "volumetric")},
        "seconds_median": float(np.median(pool("seconds"))) if scores else None,
        "seconds_max": float(np.max(pool("seconds"))) if scores else None,
    }

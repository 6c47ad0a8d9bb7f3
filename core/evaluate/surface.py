"""Metrics of surfaces against ground truth: DSM and DTM accuracy and completeness per surface class, point
classification shares, facade point density, mixed-pixel filter effect and true-ortho roof edge displacement,
and which buildings the DSM error comes from.

All functions work on arrays on one grid (the evaluated raster's); building the truth on that grid (by vertical
ray casting of the true city, with the semantic class of the hit surface) is the caller's job.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class HeightStats:
    """Accuracy of a height raster on one class of cells.

    cells : cells of the class in the AOI; rmse, mean, nmad : metres over cells with a value;
    completeness : share of the class's cells with a value within ``tol`` of the truth; filled : share with a value
    """

    cells: int
    rmse: float
    mean: float
    nmad: float
    completeness: float
    filled: float

    def as_dict(self) -> dict:
        return asdict(self)


def height_stats(est: np.ndarray, truth: np.ndarray, mask: np.ndarray, tol: float) -> HeightStats:
    """:class:`HeightStats` of ``est`` against ``truth`` (both (rows, cols)) on the cells of ``mask``."""
    m = mask & np.isfinite(truth)
    have = m & np.isfinite(est)
    err = (est - truth)[have]
    n = int(m.sum())
    if n == 0 or len(err) == 0:
        return HeightStats(n, float("nan"), float("nan"), float("nan"), 0.0, float(have.sum()) / max(n, 1))
    nmad = 1.4826 * float(np.median(np.abs(err - np.median(err))))
    return HeightStats(n, float(np.sqrt(np.mean(err ** 2))), float(np.mean(err)), nmad,
                       float((np.abs(err) <= tol).sum()) / n, float(have.sum()) / n)


def wall_cells(true_dsm: np.ndarray, min_step: float = 2.0) -> np.ndarray:
    """Cells next to a height step of at least ``min_step`` metres in the true DSM (building outlines: the cells
    where walls are seen by the obliques)."""
    t = np.nan_to_num(true_dsm, nan=np.nanmin(true_dsm))
    step = np.maximum(ndimage.maximum_filter(t, size=3) - t, t - ndimage.minimum_filter(t, size=3))
    return step >= min_step


def wall_error(est: np.ndarray, true_dsm: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Height error on wall cells allowing one cell of position tolerance: for each cell the truth value of its
    3 x 3 neighbourhood closest to the estimate (a wall falls anywhere inside its cell). (rows, cols), NaN off
    ``mask`` or without estimate."""
    best = np.full(est.shape, np.inf)
    out = np.full(est.shape, np.nan)
    pad = np.pad(true_dsm, 1, mode="edge")
    rows, cols = est.shape
    for dr in (0, 1, 2):
        for dc in (0, 1, 2):
            e = est - pad[dr:dr + rows, dc:dc + cols]
            better = np.abs(e) < best
            best = np.where(better, np.abs(e), best)
            out = np.where(better, e, out)
    out[~mask | ~np.isfinite(est)] = np.nan
    return out


def surface_table(dsm: np.ndarray, true_dsm: np.ndarray, classes: dict[str, np.ndarray], tol: float) -> dict:
    """DSM statistics per class name (``classes``: name -> mask); the ``walls`` class, if present, uses
    :func:`wall_error` (one cell of position tolerance)."""
    out = {}
    for name, mask in classes.items():
        if name == "walls":
            e = wall_error(dsm, true_dsm, mask)
            out[name] = height_stats(e, np.zeros_like(e), mask, tol).as_dict()
        else:
            out[name] = height_stats(dsm, true_dsm, mask, tol).as_dict()
    return out


def error_shares(err: np.ndarray, mask: np.ndarray, owner: np.ndarray) -> dict[int, dict]:
    """Where a class's error comes from: per owner id (a building, say) of the cells of ``mask`` with an error,
    their count, RMSE and share of the class's summed squared error, largest share first.

    err : (rows, cols) estimate minus truth (NaN without estimate); mask : (rows, cols) bool, the class;
    owner : (rows, cols) int, owner of each cell (negative: none; those cells count in the total only)
    """
    m = mask & np.isfinite(err)
    e2, ids = err[m] ** 2, owner[m]
    total = float(e2.sum())
    out = {}
    for k in np.unique(ids[ids >= 0]):
        sel = ids == k
        out[int(k)] = {"cells": int(sel.sum()), "rmse": float(np.sqrt(e2[sel].mean())),
                       "share": float(e2[sel].sum()) / total if total > 0 else 0.0}
    return dict(sorted(out.items(), key=lambda kv: -kv[1]["share"]))


def classification_shares(classes: np.ndarray, is_object: np.ndarray, is_ground: np.ndarray) -> dict:
    """Shares of true object points (buildings, vegetation) classified above, and of true ground points
    classified on the ground. ``classes``: (n,) int8 with 1 above, 0 on, -1 below."""
    obj = classes[is_object]
    gnd = classes[is_ground]
    return {"object_points": int(len(obj)), "object_above": float((obj == 1).mean()) if len(obj) else float("nan"),
            "ground_points": int(len(gnd)), "ground_on": float((gnd == 0).mean()) if len(gnd) else float("nan")}


def facade_density(normals: np.ndarray, on_wall: np.ndarray, wall_area_m2: float, max_nz: float = 0.3) -> float:
    """Points per square metre of wall: points on true walls (``on_wall (n,)``) with a near-horizontal normal
    (``|nz| <= max_nz``), divided by the visible wall area."""
    sel = on_wall & (np.abs(normals[:, 2]) <= max_nz)
    return float(sel.sum()) / wall_area_m2 if wall_area_m2 > 0 else float("nan")


def filter_effect(dist_before: np.ndarray, removed: np.ndarray) -> dict:
    """Effect of a point filter: points removed and error statistics (distance to the true surface) before and
    after. ``dist_before``: (n,) distances of all points; ``removed``: (n,) bool."""
    after = dist_before[~removed]

    def stats(d: np.ndarray) -> dict:
        return {"rmse": float(np.sqrt(np.mean(d ** 2))) if len(d) else float("nan"),
                "p95": float(np.percentile(d, 95)) if len(d) else float("nan"),
                "share_over_1m": float((d > 1.0).mean()) if len(d) else float("nan")}

    return {"points": int(len(dist_before)), "removed": int(removed.sum()),
            "removed_share": float(removed.mean()) if len(removed) else 0.0,
            "removed_over_1m_share": float((dist_before[removed] > 1.0).mean()) if removed.any() else float("nan"),
            "before": stats(dist_before), "after": stats(after)}


def roof_edge_displacement(ortho_rgb: np.ndarray, reference_rgb: np.ndarray, edges: np.ndarray,
                           window: int = 24, search: int = 12, samples: int = 400, min_valid: float = 0.8,
                           min_score: float = 0.5, seed: int = 0) -> np.ndarray:
    """Displacement (cells) of the orthophoto against a reference true ortho around roof edges.

    A ``window``-cell patch of the ortho centred on each of (a random sample of) the true roof edge cells
    ``edges (rows, cols)`` is searched in the reference within +-``search`` cells by normalised cross-correlation
    (``cv2.matchTemplate``, sub-cell peak by a parabola fit); a leaning, non-true ortho shows roofs shifted by
    their relief displacement, a true ortho none. Empty ortho cells (occlusions) take the patch mean; patches
    with less than ``min_valid`` of their cells filled or a peak below ``min_score`` are skipped.
    Returns the shift magnitudes ``(k,)`` in cells.
    """
    def grey(a: np.ndarray) -> np.ndarray:
        return cv2.cvtColor(np.ascontiguousarray(a[..., :3]), cv2.COLOR_RGB2GRAY).astype(np.float32)

    g, r = grey(ortho_rgb), grey(reference_rgb)
    valid = ortho_rgb[..., 3] > 0 if ortho_rgb.shape[-1] == 4 else np.ones(g.shape, bool)
    rows, cols = g.shape
    h = window // 2
    m = h + search
    rr, cc = np.nonzero(edges)
    keep = (rr >= m) & (rr < rows - m) & (cc >= m) & (cc < cols - m)
    rr, cc = rr[keep], cc[keep]
    if len(rr) == 0:
        return np.zeros(0)
    pick = np.random.default_rng(seed).choice(len(rr), size=min(samples, len(rr)), replace=False)

    def peak(v: np.ndarray, i: int) -> float:
        if 0 < i < len(v) - 1:
            den = v[i - 1] - 2 * v[i] + v[i + 1]
            return i + (0.5 * (v[i - 1] - v[i + 1]) / den if den < 0 else 0.0)
        return float(i)

    out = []
    for i in pick:
        sl = (slice(rr[i] - h, rr[i] + h), slice(cc[i] - h, cc[i] + h))
        ok = valid[sl]
        if ok.mean() < min_valid or g[sl][ok].std() < 1.0:
            continue
        patch = np.where(ok, g[sl], g[sl][ok].mean()).astype(np.float32)
        area = np.ascontiguousarray(r[rr[i] - m:rr[i] + m, cc[i] - m:cc[i] + m])
        score = cv2.matchTemplate(area, patch, cv2.TM_CCOEFF_NORMED)
        y, x = np.unravel_index(int(np.argmax(score)), score.shape)
        if score[y, x] < min_score:
            continue
        dy, dx = peak(score[:, x], y) - search, peak(score[y, :], x) - search
        out.append(float(np.hypot(dx, dy)))
    return np.array(out)

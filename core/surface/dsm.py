"""Ortho-DSM from a point cloud: robust per-cell height on a north-up grid, small holes filled.

Per cell the height is the median of the points in the top band of the cell (within ``band`` metres below the
cell's 90th percentile): on a roof this is the median of the roof points (robust against noise and the odd
blunder), in a cell crossed by a wall it is the roof, not the middle of the wall, because the DSM is the top
surface. Isolated blunders (cells with almost no neighbour at their height) and narrow deep pits (matching
blunders inside roofs) are removed. Holes up to ``max_hole_m2`` (occlusions, poor texture) are filled: by a
harmonic surface spanned by their own border cells where those are nearly level, by their border's plane in a
sloped roof, with the low side's height where they lie between a roof and the ground; larger holes stay empty.
A measured cell between a much higher and a much lower neighbour sits on a wall (a facade point): it is emptied
before the holes are filled, so its surroundings decide between roof and ground; a fill that still bridges such a
step takes the nearer of the two surfaces.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from ..model.raster import Raster


@dataclass(frozen=True)
class GridSpec:
    """A north-up grid: outer corner ``x0, y0`` of the top-left cell, cell size, rows, cols."""

    x0: float
    y0: float
    cell: float
    rows: int
    cols: int

    @classmethod
    def around(cls, xmin: float, ymin: float, xmax: float, ymax: float, cell: float) -> GridSpec:
        """The grid of cells aligned to multiples of ``cell`` that covers the box."""
        x0, y0 = np.floor(xmin / cell) * cell, np.ceil(ymax / cell) * cell
        cols = int(np.ceil((xmax - x0) / cell))
        rows = int(np.ceil((y0 - ymin) / cell))
        return cls(float(x0), float(y0), float(cell), max(rows, 1), max(cols, 1))

    def cell_index(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row, column ``(n,)`` int64 of world points ``(n, 2)`` and a mask of those inside the grid."""
        c = np.floor((xy[:, 0] - self.x0) / self.cell).astype(np.int64)
        r = np.floor((self.y0 - xy[:, 1]) / self.cell).astype(np.int64)
        inside = (r >= 0) & (r < self.rows) & (c >= 0) & (c < self.cols)
        return r, c, inside

    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World X ``(rows, cols)`` and Y ``(rows, cols)`` of the cell centres."""
        x = self.x0 + (np.arange(self.cols) + 0.5) * self.cell
        y = self.y0 - (np.arange(self.rows) + 0.5) * self.cell
        return np.meshgrid(x, y)

    def raster(self, data: np.ndarray, crs: str, nodata: float | None = None) -> Raster:
        return Raster(data, self.x0, self.y0, self.cell, crs, nodata)


@dataclass(frozen=True)
class DsmConfig:
    """Attributes
    ----------
    cell : cell size in metres (0 = the nadir GSD of the block)
    min_support : the top of a cell is its highest point with at least this many points (itself included) within
        ``band`` of its height in the cell and its 8 neighbours: an isolated high blunder is passed over, and a
        roof seen by a few points wins over more numerous mismatched points at ground level under it (nothing can
        be seen below a roof from above); 0 (the default) takes ``support_share`` of the median number of points
        in the 3 x 3 neighbourhoods of occupied cells (at least 2): with the several points per cell of a dense
        cloud the top also passes over the thin fringe a matching window fattens a roof edge with
    support_share : share of the typical neighbourhood point count that supports a top when ``min_support`` is 0
    band : points within this many metres below the top form the cell's top band
    min_points : cells with fewer points are empty
    spike : cells with fewer than two of their 8 neighbours within this many metres are removed as blunders
    max_hole_m2 : holes up to this area are filled
    max_hole_step : holes whose surroundings span less than this (metres) are inpainted; others (occlusions
        between a roof and the ground) take the height of their low surroundings, unless their surroundings lie on
        one plane within ``hole_plane_tol`` (a hole in a sloped roof), which then fills them
    hole_plane_tol : RMS distance (metres) of a hole's surrounding cells to their plane for a planar fill
    pit_size_m, pit_depth : cells lower by more than ``pit_depth`` metres than the grey closing of the DSM with a
        ``pit_size_m`` square (pits narrower than that in every direction) are removed before the holes are
        filled (0 size disables it)
    roof_hole_sides : a hole bounded by high cells on this many of its four sides is filled as an unmatched part
        of a roof (see :func:`fill_small_holes`; 5 disables it)
    wall_step : a measured cell more than this many metres below one neighbour and above the opposite one is emptied
        before the holes are filled, and a filled one takes the nearer side (:func:`wall_steps`,
        :func:`snap_wall_steps`; 0 disables both)
    """

    cell: float = 0.0
    min_support: int = 0
    support_share: float = 0.2
    band: float = 0.5
    min_points: int = 1
    spike: float = 1.0
    max_hole_m2: float = 50.0
    max_hole_step: float = 1.0
    hole_plane_tol: float = 0.2
    pit_size_m: float = 3.2
    pit_depth: float = 2.0
    roof_hole_sides: int = 3
    wall_step: float = 1.0


def _group_quantile(key: np.ndarray, z: np.ndarray, q: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per group (sorted unique keys) the ``q`` quantile (lower element) of ``z``, and the counts."""
    order = np.lexsort((z, key))
    k, zs = key[order], z[order]
    uniq, start, counts = np.unique(k, return_index=True, return_counts=True)
    return uniq, zs[start + np.floor(q * (counts - 1)).astype(np.int64)], counts


def auto_support(grid: GridSpec, keys: np.ndarray, share: float) -> int:
    """``share`` of the median number of points in the 3 x 3 neighbourhoods of the occupied cells (cell indices
    ``keys (n,)`` of the points), at least 2."""
    counts = np.bincount(keys, minlength=grid.rows * grid.cols).reshape(grid.rows, grid.cols).astype(np.float64)
    around = ndimage.uniform_filter(counts, size=3, mode="constant") * 9.0
    return max(2, int(round(share * float(np.median(around[counts > 0])))))


def grid_points(grid: GridSpec, xyz: np.ndarray, cfg: DsmConfig = DsmConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Robust per-cell heights of points ``xyz : (n, 3)``.

    Returns
    -------
    height : (rows, cols) float64, NaN for cells with fewer than ``min_points``
    top : (n,) bool, the points in their cell's top band (the ones that made the height)
    """
    r, c, inside = grid.cell_index(xyz[:, :2])
    key = np.where(inside, r * grid.cols + c, -1)
    z = xyz[:, 2]
    idx = np.flatnonzero(inside)
    top_of = np.full(grid.rows * grid.cols, np.nan)
    if len(idx):
        k, zz = key[idx], z[idx]
        min_support = cfg.min_support if cfg.min_support > 0 else auto_support(grid, k, cfg.support_share)
        order = np.lexsort((zz, k))
        k, zz = k[order], zz[order]
        # support of each point: points within ``band`` of its height in its cell and the 8 around it (cells are
        # spaced apart in sort_val by more than twice the band, so a search never reaches into another cell)
        span = np.ptp(zz) + 4.0 * cfg.band + 1.0
        sort_val = k * span + (zz - zz.min())
        pos = np.arange(len(zz))
        support = np.zeros(len(zz), np.int64)
        rr, cc = k // grid.cols, k % grid.cols
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                ok = (rr + dr >= 0) & (rr + dr < grid.rows) & (cc + dc >= 0) & (cc + dc < grid.cols)
                nk = (k + dr * grid.cols + dc) * span + (zz - zz.min())
                n = np.searchsorted(sort_val, nk + cfg.band, side="right") - np.searchsorted(sort_val, nk - cfg.band)
                support += np.where(ok, n, 0)
        within = pos - np.searchsorted(k, k, side="left")
        # per cell: the highest point with enough support, else the best-supported point (the highest of those)
        rank = np.where(support >= min_support, 1e12 + within, support * 1e6 + within)
        best = np.full(grid.rows * grid.cols, -1.0)
        np.maximum.at(best, k, rank)
        pick = rank == best[k]
        top_of[k[pick]] = zz[pick]
    top = np.zeros(len(xyz), bool)
    top[idx] = (z[idx] >= top_of[key[idx]] - cfg.band) & (z[idx] <= top_of[key[idx]])
    sel = np.flatnonzero(top)
    uniq2, zmed, counts = _group_quantile(key[sel], z[sel], 0.5)
    height = np.full(grid.rows * grid.cols, np.nan)
    keep = counts >= cfg.min_points
    height[uniq2[keep]] = zmed[keep]
    return height.reshape(grid.rows, grid.cols), top


def remove_spikes(height: np.ndarray, threshold: float, min_support: int = 2) -> np.ndarray:
    """Empty the cells (rows, cols) with fewer than ``min_support`` of their 8 neighbours within ``threshold``
    metres (isolated blunders; a roof corner keeps three neighbours at its height)."""
    pad = np.pad(height, 1, constant_values=np.nan)
    rows, cols = height.shape
    support = np.zeros(height.shape, np.int32)
    with np.errstate(invalid="ignore"):
        for dr in (0, 1, 2):
            for dc in (0, 1, 2):
                if dr == 1 and dc == 1:
                    continue
                support += np.abs(pad[dr:dr + rows, dc:dc + cols] - height) <= threshold
    out = height.copy()
    out[np.isfinite(height) & (support < min_support)] = np.nan
    return out


def hole_rings(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ring of every hole of ``labels (rows, cols)`` (holes labelled ``1..n``, 0 elsewhere): each pair of a
    hole's label and a non-hole cell among the 8 neighbours of its cells, once.

    A cell between two holes belongs to both rings (a dilated label image would give it to one of them only, and
    a hole among many small holes would keep a ring of a few cells that misjudges its surroundings).

    Returns
    -------
    lab, rr, cc : (m,) int64 label, row and column of each ring cell
    """
    rows, cols = labels.shape
    hr, hc = np.nonzero(labels > 0)
    hl = labels[hr, hc].astype(np.int64)
    keys = []
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r2, c2 = hr + dr, hc + dc
            ok = (r2 >= 0) & (r2 < rows) & (c2 >= 0) & (c2 < cols)
            ok[ok] = labels[r2[ok], c2[ok]] == 0
            keys.append(hl[ok] * (rows * cols) + r2[ok] * cols + c2[ok])
    u = np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)
    cell = u % (rows * cols)
    return u // (rows * cols), cell // cols, cell % cols


def ring_planes(z: np.ndarray, rr: np.ndarray, cc: np.ndarray, lab: np.ndarray,
                n: int) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane ``z = a*col + b*row + c`` per label ``1..n`` of ring cells with heights ``z (m,)``, rows
    ``rr (m,)``, columns ``cc (m,)`` and labels ``lab (m,)``.

    Returns
    -------
    coef : (n + 1, 3) float64 ``(a, b, c)`` per label (row 0 and degenerate labels NaN)
    rms : (n + 1,) float64 RMS distance in height of each label's cells to its plane
    """
    ok = np.isfinite(z)
    rr, cc, lab, z = rr[ok].astype(np.float64), cc[ok].astype(np.float64), lab[ok], z[ok]
    # centred per label for conditioning
    cnt = np.bincount(lab, minlength=n + 1).astype(np.float64)
    safe = np.maximum(cnt, 1)
    mr, mc = np.bincount(lab, rr, n + 1) / safe, np.bincount(lab, cc, n + 1) / safe
    mz = np.bincount(lab, z, n + 1) / safe
    dr, dc, dz = rr - mr[lab], cc - mc[lab], z - mz[lab]
    a = np.zeros((n + 1, 2, 2))
    a[:, 0, 0] = np.bincount(lab, dc * dc, n + 1)
    a[:, 0, 1] = a[:, 1, 0] = np.bincount(lab, dc * dr, n + 1)
    a[:, 1, 1] = np.bincount(lab, dr * dr, n + 1)
    rhs = np.stack([np.bincount(lab, dc * dz, n + 1), np.bincount(lab, dr * dz, n + 1)], 1)
    det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] ** 2
    good = (cnt >= 6) & (det > 1e-9 * np.maximum(a[:, 0, 0] + a[:, 1, 1], 1e-12) ** 2)
    coef = np.full((n + 1, 3), np.nan)
    sol = np.linalg.solve(a[good], rhs[good][:, :, None])[:, :, 0]
    coef[good, 0], coef[good, 1] = sol[:, 0], sol[:, 1]
    coef[good, 2] = mz[good] - coef[good, 0] * mc[good] - coef[good, 1] * mr[good]
    res = z - (coef[lab, 0] * cc + coef[lab, 1] * rr + coef[lab, 2])
    rms = np.sqrt(np.bincount(lab, np.nan_to_num(res, nan=0.0) ** 2, n + 1) / safe)
    rms[~good] = np.inf
    return coef, rms


def fill_small_holes(height: np.ndarray, max_cells: int, max_step: float = np.inf,
                     plane_tol: float = 0.0, roof_sides: int = 3) -> np.ndarray:
    """Fill NaN regions of at most ``max_cells`` cells (not touching the border).

    A hole whose surrounding cells span less than ``max_step`` metres takes the harmonic surface with its border
    cells as boundary values (:func:`harmonic_fill`: only its own border, never a cell across a wall). A
    hole whose surroundings span more but lie on one plane (RMS <= ``plane_tol`` metres: a hole in a sloped
    roof) takes the plane's heights. A hole between a high and a low surface whose border is high on at least
    ``roof_sides`` of its four sides (north, east, south, west of its centre; 5 disables it), a part of a roof
    matching missed that is open to the ground at an eave, takes the harmonic surface over its high border
    cells. Any other hole between a high and a low surface (an occlusion beside a building, seen from above)
    takes the median of its low surrounding cells (those within ``max_step`` of the lowest): the ground hidden
    behind the wall, rather than a made-up slope from the roof down to the ground ("low" is taken near the lower
    quartile of the surrounding cells, so a few blunder cells below the ground do not decide it).
    """
    holes = ~np.isfinite(height)
    if not holes.any() or holes.all():
        return height
    labels, n = ndimage.label(holes)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    lab_r, rr, cc = hole_rings(labels)
    z_r = height[rr, cc]
    ring_lo = np.full(n + 1, np.inf)
    ring_hi = np.full(n + 1, -np.inf)
    np.minimum.at(ring_lo, lab_r, z_r)
    np.maximum.at(ring_hi, lab_r, z_r)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    small = sizes <= max_cells
    small[0] = False
    small[border] = False
    small &= np.isfinite(ring_lo)
    level = small & (ring_hi - ring_lo < max_step)
    planar = np.zeros(n + 1, bool)
    result = height.copy()
    if plane_tol > 0 and (small & ~level).any():
        on = (small & ~level)[lab_r]
        coef, rms = ring_planes(z_r[on], rr[on], cc[on], lab_r[on], n)
        planar = small & ~level & (rms <= plane_tol)
        sel = planar[labels]
        if sel.any():
            pr, pc = np.nonzero(sel)
            lab = labels[pr, pc]
            result[pr, pc] = coef[lab, 0] * pc + coef[lab, 1] * pr + coef[lab, 2]
    step = small & ~level & ~planar
    if step.any():
        # a hole enclosed by high cells on at least ``roof_sides`` of its four sides (north, east, south, west of
        # its centre) is a part of a roof that matching missed (a dark or sparsely measured roof, a tower top), not
        # ground hidden behind a wall, which leaves the wall on one side (two at a corner): the membrane over
        # its high border cells fills it
        on = step[lab_r]
        lab_s, rs, cs, zs = lab_r[on], rr[on], cc[on], z_r[on]
        high_cell = zs > ring_lo[lab_s] + max_step
        hr, hc = np.nonzero(step[labels])
        hl = labels[hr, hc]
        cnt = np.maximum(np.bincount(hl, minlength=n + 1), 1)
        mr, mc = np.bincount(hl, hr, n + 1) / cnt, np.bincount(hl, hc, n + 1) / cnt
        sector = (np.floor((np.arctan2(mr[lab_s] - rs, cs - mc[lab_s]) / (np.pi / 2)) + 0.5).astype(np.int64)) % 4
        key = lab_s * 4 + sector
        high_share = np.bincount(key, high_cell, 4 * (n + 1)) / np.maximum(np.bincount(key, minlength=4 * (n + 1)), 1)
        high_sides = (high_share > 0.5).reshape(n + 1, 4).sum(axis=1)
        roof = step & (high_sides >= roof_sides)
        if roof.any():
            sel = roof[labels]
            low = roof[lab_s] & ~high_cell
            result[sel] = harmonic_fill(_with_nan(height, rs[low], cs[low]), sel)[sel]
        step &= ~roof
    fill = level[labels]
    if fill.any():
        result[fill] = harmonic_fill(height, fill)[fill]
    if step.any():
        # the low side: ring cells near the ring's lower quartile (a few blunder cells in the ring do not count)
        on = step[lab_r]
        lab_s, zs = lab_r[on], z_r[on]
        uniq, q25, _ = _group_quantile(lab_s, zs, 0.25)
        low_ref = np.full(n + 1, np.nan)
        low_ref[uniq] = q25
        near = np.abs(zs - low_ref[lab_s]) <= max_step
        uniq, med, _ = _group_quantile(lab_s[near], zs[near], 0.5)
        ground = np.full(n + 1, np.nan)
        ground[uniq] = med
        sel = step[labels]
        result[sel] = ground[labels[sel]]
    return result


def _with_nan(height: np.ndarray, rr: np.ndarray, cc: np.ndarray) -> np.ndarray:
    out = height.copy()
    out[rr, cc] = np.nan
    return out


def harmonic_fill(height: np.ndarray, fill: np.ndarray) -> np.ndarray:
    """``height (rows, cols)`` with the cells of ``fill`` (bool, same shape; regions not touching the border)
    replaced by the solution of Laplace's equation whose boundary values are the 4-neighbours of the regions
    (a membrane stretched over each hole: linear ramps and planes are kept, nothing beyond the hole's own border
    enters the fill, unlike a windowed inpainting that reaches across a wall).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    rr, cc = np.nonzero(fill)
    n = len(rr)
    out = height.copy()
    if n == 0:
        return out
    index = np.full(height.shape, -1, np.int64)
    index[rr, cc] = np.arange(n)
    rows_i, cols_i, vals = [np.arange(n)], [np.arange(n)], [np.zeros(n)]
    rhs = np.zeros(n)
    deg = np.zeros(n)
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        r2, c2 = rr + dr, cc + dc
        ok = (r2 >= 0) & (r2 < height.shape[0]) & (c2 >= 0) & (c2 < height.shape[1])
        r2, c2 = np.where(ok, r2, rr), np.where(ok, c2, cc)
        nb = index[r2, c2]
        inner = ok & (nb >= 0)
        border = ok & (nb < 0) & np.isfinite(height[r2, c2])
        deg += inner | border
        rows_i.append(np.flatnonzero(inner))
        cols_i.append(nb[inner])
        vals.append(-np.ones(int(inner.sum())))
        rhs[border] += height[r2[border], c2[border]]
    vals[0] = np.maximum(deg, 1.0)
    a = coo_matrix((np.concatenate(vals), (np.concatenate(rows_i), np.concatenate(cols_i))), shape=(n, n)).tocsr()
    out[rr, cc] = spsolve(a, rhs)
    return out


def cell_colours(grid: GridSpec, xyz: np.ndarray, rgb: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Mean colour ``(rows, cols, 3)`` float64 of the points selected by ``use : (n,)`` per cell (NaN empty)."""
    r, c, inside = grid.cell_index(xyz[:, :2])
    ok = inside & use
    key = r[ok] * grid.cols + c[ok]
    n = np.bincount(key, minlength=grid.rows * grid.cols).astype(np.float64)
    out = np.stack([np.bincount(key, weights=rgb[ok, i].astype(np.float64), minlength=grid.rows * grid.cols)
                    for i in range(3)], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out /= n[:, None]
    return out.reshape(grid.rows, grid.cols, 3)


def pits(height: np.ndarray, size_cells: int, depth: float) -> np.ndarray:
    """Mask ``(rows, cols)`` of enclosed pits in ``height`` (NaN-free): patches more than ``depth`` metres below
    the grey closing with a ``size_cells`` square (narrower than the square in every direction) whose border is
    higher nearly all round (its lower quartile more than ``depth`` above the patch's median). Within a roof such
    a patch is a blunder (matching that slid to the ground on a dark or repetitive roof, a spot only one master
    saw). A short passage between two buildings is open at its ends (more than a quarter of its border is
    ground) and stays; a passage narrower than ``size_cells`` and more than about three times as long as wide is
    taken for a pit and bridged at roof height."""
    k = np.ones((size_cells, size_cells), np.uint8)
    closed = cv2.erode(cv2.dilate(height.astype(np.float32), k), k)
    cand = closed - height > depth
    labels, n = ndimage.label(cand)
    if n == 0:
        return cand
    idx = np.arange(1, n + 1)
    ring = ndimage.grey_dilation(labels, size=3) * ~cand
    rk = np.flatnonzero(ring.ravel() > 0)
    lab_r, q25, _ = _group_quantile(ring.ravel()[rk], height.ravel()[rk], 0.25)
    border = np.full(n + 1, -np.inf)
    border[lab_r] = q25
    inner = np.full(n + 1, np.inf)
    inner[1:] = ndimage.median(height, labels, idx)
    enclosed = border - inner > depth
    enclosed[0] = False
    return enclosed[labels]


def wall_steps(height: np.ndarray, step: float) -> np.ndarray:
    """Mask ``(rows, cols)`` of the cells of ``height`` that lie more than ``step`` metres below a neighbour and
    more than ``step`` above the opposite neighbour (along a row, a column or a diagonal; NaN cells and NaN
    neighbours never count).

    A 2.5D surface steeper than ``2 * step`` over two cells is a wall, whose top cell belongs to the roof and
    whose foot cell to the ground: a cell in between holds a point of the wall itself (a facade point whose normal
    was lost, an edge the matching window rounded) or a hole fill that bridged the step.
    """
    rows, cols = height.shape
    pad = np.pad(height, 1, constant_values=np.nan)
    found = np.zeros(height.shape, bool)
    with np.errstate(invalid="ignore"):
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
            a = pad[1 + dr:1 + dr + rows, 1 + dc:1 + dc + cols]
            b = pad[1 - dr:1 - dr + rows, 1 - dc:1 - dc + cols]
            found |= ((a > height + step) & (b < height - step)) | ((b > height + step) & (a < height - step))
    return found


def snap_wall_steps(height: np.ndarray, step: float, rounds: int = 2) -> np.ndarray:
    """``height (rows, cols)`` with each cell of :func:`wall_steps` set to the nearer of its two sides (the
    highest and the lowest of its 8 neighbours): the DSM steps from the roof to the ground at the wall instead of
    passing through a height no surface has there. ``rounds`` passes (a two-cell slope needs two); NaN cells stay
    NaN."""
    out = height.copy()
    for _ in range(rounds):
        wall = wall_steps(out, step)
        if not wall.any():
            break
        finite = np.isfinite(out)
        hi = ndimage.maximum_filter(np.where(finite, out, -np.inf), size=3)[wall]
        lo = ndimage.minimum_filter(np.where(finite, out, np.inf), size=3)[wall]
        out[wall] = np.where(hi - out[wall] < out[wall] - lo, hi, lo)
    return out


def finish_dsm(height: np.ndarray, cell: float, cfg: DsmConfig = DsmConfig()) -> np.ndarray:
    """The DSM grid from per-cell heights ``(rows, cols)`` (NaN empty): spikes and cells on wall steps emptied,
    pits removed, holes filled, cells on wall steps left by the filling snapped to the roof or the ground."""
    height = remove_spikes(height, cfg.spike) if cfg.spike > 0 else height
    if cfg.wall_step > 0:
        # a measured cell between a roof and the ground holds a point of the wall, not the top surface: its height
        # is unknown, and the hole rules judge it from its surroundings (a roof edge enclosed by roof becomes
        # roof, a wall foot the ground beside it) instead of the nearer of its two neighbours
        height = np.where(wall_steps(height, cfg.wall_step), np.nan, height)
    max_cells = int(cfg.max_hole_m2 / cell ** 2)
    filled = fill_small_holes(height, max_cells, cfg.max_hole_step, cfg.hole_plane_tol, cfg.roof_hole_sides)
    size = int(round(cfg.pit_size_m / cell)) | 1
    if cfg.pit_size_m > 0 and size >= 3 and np.isfinite(height).any():
        base = np.where(np.isfinite(filled), filled, np.nanmin(height))
        pit = np.isfinite(height) & pits(base, size, cfg.pit_depth)
        if pit.any():
            filled = fill_small_holes(np.where(pit, np.nan, height), max_cells, cfg.max_hole_step,
                                      cfg.hole_plane_tol, cfg.roof_hole_sides)
    if cfg.wall_step > 0:
        filled = snap_wall_steps(filled, cfg.wall_step)
    return filled


def make_dsm(grid: GridSpec, xyz: np.ndarray, crs: str, cfg: DsmConfig = DsmConfig()) -> tuple[Raster, np.ndarray]:
    """The DSM raster (:func:`grid_points`, then :func:`finish_dsm`) and the top-band mask of the points."""
    height, top = grid_points(grid, xyz, cfg)
    return grid.raster(finish_dsm(height, grid.cell, cfg).astype(np.float32), crs), top

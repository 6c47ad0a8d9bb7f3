"""Volumetric fallback for buildings with discontinuities: planes found in 3D voxels.

Voxels of about half the noise filter's size; a PCA plane per voxel from the points of its 3x3x3 block;
neighbouring voxels with coplanar planes merged by region growing into plane segments, and segments that lie on
the same plane merged into one infinite plane. The planes, the contour walls and the ground then go to
:func:`.hull.build_hull`, whose arrangement intersects every plane triplet inside the building's box, consolidates
the vertices into k-nodes and keeps the hull of the occupied cells with its structural breaks (step walls between
roofs of different heights).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from .denoise import voxel_blocks
from .geometry import fit_plane


@dataclass(frozen=True)
class VolumetricConfig:
    """voxel : voxel edge (m, 0 = half the noise filter's voxel); angle_deg : coplanarity of neighbours;
    min_points : points of a voxel with a plane; min_area : smallest plane segment (m^2)."""

    voxel: float = 0.0
    angle_deg: float = 10.0
    min_points: int = 6
    min_area: float = 3.0


@dataclass(frozen=True)
class PlaneSegment:
    """plane : (4,) n.x + d = 0; n_points : support; area : approximate (m^2) from the voxel count; centre : (3,)
    mean of its points."""

    plane: np.ndarray
    n_points: int
    area: float
    centre: np.ndarray


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
        out.append(PlaneSegment(pl, len(idx), area, xyz[idx].mean(0)))
    return merge_plane_segments(out, cfg.angle_deg, tol_b * 2)


def merge_plane_segments(segs: list[PlaneSegment], angle_deg: float, offset: float) -> list[PlaneSegment]:
    """Segments on the same plane (normals within ``angle_deg``, each one's centre within ``offset`` of the
    other's plane) become one plane, through their common centre. The centres, not the planes' constants, are
    compared: far from the origin (absolute heights) a tiny tilt moves the constant by metres."""
    segs = sorted(segs, key=lambda s: -s.n_points)
    cos_t = np.cos(np.radians(angle_deg))
    out: list[PlaneSegment] = []
    for s in segs:
        for i, o in enumerate(out):
            c = s.plane[:3] @ o.plane[:3]
            if (abs(c) > cos_t and abs(s.centre @ o.plane[:3] + o.plane[3]) < offset
                    and abs(o.centre @ s.plane[:3] + s.plane[3]) < offset):
                w = o.n_points + s.n_points
                n = o.plane[:3] * o.n_points + np.sign(c) * s.plane[:3] * s.n_points
                n = n / np.linalg.norm(n)
                centre = (o.centre * o.n_points + s.centre * s.n_points) / w
                out[i] = PlaneSegment(np.append(n, -n @ centre), w, o.area + s.area, centre)
                break
        else:
            out.append(s)
    return out


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

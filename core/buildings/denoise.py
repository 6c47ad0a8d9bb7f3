"""Voxel noise filter of a building's point set (the seed's step before the reconstruction).

Cube size ``a`` (given, or guessed by a sparse dry run over a subset); per voxel a PCA plane from the points of its
3x3x3 neighbourhood; the points inside the voxel's circumscribed sphere (r = a/2 * sqrt(3)) give a histogram of
point-to-plane distances; points of the voxel beyond the modal class are removed. The class width is three times
the robust noise level of the whole set, so the modal class holds the Gaussian inliers of a planar voxel; where a
voxel is not planar (ridges, corners: the modal class holds under half of the sphere) the cut moves to the first
empty class after the mode, which still drops points separated from the surface by a gap. Voxels whose
neighbourhood is nearly empty are isolated and removed whole; a voxel whose sphere is sparse (an outlier's own
voxel next to a surface) takes its histogram from the whole neighbourhood.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class NoiseFilterResult:
    """keep : (n,) bool; voxel : cube size used (m); sigma : robust noise level (m); class_width : (m)."""

    keep: np.ndarray
    voxel: float
    sigma: float
    class_width: float


def guess_voxel_size(xyz: np.ndarray, points_per_voxel: float = 10.0, sample: int = 2000,
                     seed: int = 0) -> float:
    """Sparse dry run: the cube edge that holds about ``points_per_voxel`` points of a surface.

    The surface density comes from the 8-nearest-neighbour radius of a random subset: ``rho = 8 / (pi r^2)``;
    a cube cut by a surface holds about ``rho * a^2`` points.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    rng = np.random.default_rng(seed)
    sub = xyz[rng.choice(len(xyz), min(sample, len(xyz)), replace=False)]
    tree = cKDTree(xyz)
    d, _ = tree.query(sub, k=9)
    r = float(np.median(d[:, 8]))
    rho = 8.0 / (np.pi * r * r)
    return float(np.sqrt(points_per_voxel / rho))


def _pca_plane(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = p.mean(0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    return c, vt[2]


def voxel_noise_filter(xyz: np.ndarray, a: float | None = None, min_neighbours: int = 10,
                       sigma: float | None = None) -> NoiseFilterResult:
    """Remove noise points with the voxel / PCA plane / sphere / distance-histogram test.

    Parameters
    ----------
    xyz : (n, 3) float64 points
    a : voxel edge (m); guessed with :func:`guess_voxel_size` when None
    min_neighbours : voxels whose 3x3x3 neighbourhood holds fewer points are removed whole
    sigma : noise level (m); estimated robustly from the PCA residuals when None

    Returns
    -------
    NoiseFilterResult with ``keep (n,) bool``
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    if a is None:
        a = guess_voxel_size(xyz)
    lo = xyz.min(0)
    ijk = np.floor((xyz - lo) / a).astype(np.int64)
    keys, inv = np.unique(ijk, axis=0, return_inverse=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    starts = np.searchsorted(inv[order], np.arange(len(keys) + 1))
    index = {tuple(k): i for i, k in enumerate(keys)}
    offsets = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])
    r = a / 2 * np.sqrt(3)

    planes: list[tuple[np.ndarray, np.ndarray] | None] = []
    spheres: list[np.ndarray] = []
    for key in keys:
        nb = [index.get(tuple(key + o)) for o in offsets]
        idx = np.concatenate([order[starts[j]:starts[j + 1]] for j in nb if j is not None])
        if len(idx) < min_neighbours:
            planes.append(None)
            spheres.append(idx)
            continue
        p = xyz[idx]
        planes.append(_pca_plane(p))
        centre = lo + (key + 0.5) * a
        in_sphere = idx[np.linalg.norm(p - centre, axis=1) <= r]
        # a sparse sphere (an outlier's own voxel) cannot hold a meaningful mode: use the neighbourhood
        spheres.append(in_sphere if len(in_sphere) >= min_neighbours else idx)

    if sigma is None:
        # per voxel robust residual scale of its own points; planar voxels are the majority, edges the tail
        scales = [1.4826 * float(np.median(np.abs((xyz[order[starts[v]:starts[v + 1]]] - pl[0]) @ pl[1])))
                  for v, pl in enumerate(planes) if pl is not None and starts[v + 1] - starts[v] >= 5]
        sigma = float(np.percentile(scales, 30)) if scales else a / 10
        sigma = max(sigma, 1e-4)
    width = 3.0 * sigma

    keep = np.ones(n, bool)
    for vi, pl in enumerate(planes):
        own = order[starts[vi]:starts[vi + 1]]
        if pl is None:
            keep[own] = False
            continue
        c, nrm = pl
        d_sphere = np.abs((xyz[spheres[vi]] - c) @ nrm)
        nbins = max(int(np.ceil(d_sphere.max() / width)) + 1, 1)
        hist = np.bincount((d_sphere / width).astype(np.int64), minlength=nbins)
        mode = int(np.argmax(hist))
        if hist[mode] >= 0.5 * len(d_sphere):
            cut = (mode + 1) * width
        else:
            empty = np.nonzero(hist[mode:] == 0)[0]
            cut = (mode + empty[0]) * width if len(empty) else np.inf
        keep[own] &= np.abs((xyz[own] - c) @ nrm) < cut
    return NoiseFilterResult(keep, float(a), float(sigma), float(width))

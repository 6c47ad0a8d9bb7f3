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


@dataclass(frozen=True)
class VoxelBlocks:
    """Points in cubes of edge ``a`` with a PCA plane per voxel from the points of its 3x3x3 block.

    lo : (3,) grid origin (the points' minimum); keys : (v, 3) int64 voxel indices, lexicographic; inv : (n,) voxel
    of each point; nb : (v, 27) neighbour voxels (-1: empty), itself included; count : (v,) own points;
    n_block : (v,) points of the block; mean : (v, 3) block centroid relative to ``lo``; normal : (v, 3) unit
    normal of the block's plane; rms : (v,) block RMS across that plane.
    """

    lo: np.ndarray
    keys: np.ndarray
    inv: np.ndarray
    nb: np.ndarray
    count: np.ndarray
    n_block: np.ndarray
    mean: np.ndarray
    normal: np.ndarray
    rms: np.ndarray


def voxel_blocks(xyz: np.ndarray, a: float) -> VoxelBlocks:
    """:class:`VoxelBlocks` of points ``xyz (n, 3)`` in cubes of edge ``a``, from the first and second moments of
    each voxel summed over its 3x3x3 neighbourhood."""
    lo = xyz.min(0)
    keys, inv = np.unique(np.floor((xyz - lo) / a).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.ravel()
    nv = len(keys)
    # neighbour table (nv, 27) by linear keys (np.unique sorts lexicographically, so ``lin`` is increasing)
    dims = keys.max(0) + 3
    lin = ((keys[:, 0] + 1) * dims[1] + keys[:, 1] + 1) * dims[2] + keys[:, 2] + 1
    offsets = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])
    q = lin[:, None] + ((offsets[:, 0] * dims[1] + offsets[:, 1]) * dims[2] + offsets[:, 2])[None, :]
    pos = np.clip(np.searchsorted(lin, q), 0, nv - 1)
    nb = np.where(lin[pos] == q, pos, -1)
    valid = nb >= 0
    nbc = np.where(valid, nb, 0)
    rel = xyz - lo
    cnt = np.bincount(inv, minlength=nv).astype(np.float64)
    s1 = np.stack([np.bincount(inv, rel[:, d], nv) for d in range(3)], 1)
    s2 = np.stack([np.bincount(inv, rel[:, d] * rel[:, e], nv) for d in range(3) for e in range(3)], 1)
    n_block = (cnt[nbc] * valid).sum(1)
    nn = np.maximum(n_block, 1.0)
    mean = (s1[nbc] * valid[..., None]).sum(1) / nn[:, None]
    cov = (s2[nbc] * valid[..., None]).sum(1).reshape(nv, 3, 3) / nn[:, None, None]
    cov -= mean[:, :, None] * mean[:, None, :]
    val, vec = np.linalg.eigh(cov)
    return VoxelBlocks(lo, keys, inv, nb, cnt, n_block, mean, vec[:, :, 0], np.sqrt(np.maximum(val[:, 0], 0.0)))


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
    vb = voxel_blocks(xyz, a)
    lo, keys, inv, nb, mean, normal = vb.lo, vb.keys, vb.inv, vb.nb, vb.mean, vb.normal
    nv, cnt = len(keys), vb.count
    rel = xyz - lo
    has_plane = vb.n_block >= min_neighbours
    d_own = np.abs(np.einsum("ij,ij->i", rel - mean[inv], normal[inv]))

    if sigma is None:
        # per voxel robust residual scale of its own points; planar voxels are the majority, edges the tail
        order = np.lexsort((d_own, inv))
        starts = np.searchsorted(inv[order], np.arange(nv))
        ok = has_plane & (cnt >= 5)
        med = d_own[order[starts[ok] + (cnt[ok].astype(np.int64) // 2)]]
        sigma = float(np.percentile(1.4826 * med, 30)) if ok.any() else a / 10
        sigma = max(sigma, 1e-4)
    width = 3.0 * sigma

    # sphere test and distance histograms: every point against the voxels whose neighbourhood holds it
    r = a / 2 * np.sqrt(3)
    nbins = 64
    pv = nb[inv]  # (n, 27)
    pt = np.repeat(np.arange(n), 27)[pv.ravel() >= 0]
    w = pv.ravel()[pv.ravel() >= 0]
    d = np.abs(np.einsum("ij,ij->i", rel[pt] - mean[w], normal[w]))
    in_sphere = np.linalg.norm(rel[pt] - (keys[w] + 0.5) * a, axis=1) <= r
    b = np.minimum((d / width).astype(np.int64), nbins - 1)
    h_nb = np.bincount(w * nbins + b, minlength=nv * nbins).reshape(nv, nbins)
    h_sp = np.bincount(w[in_sphere] * nbins + b[in_sphere], minlength=nv * nbins).reshape(nv, nbins)
    # a sparse sphere (an outlier's own voxel) cannot hold a meaningful mode: use the neighbourhood
    hist = np.where((h_sp.sum(1) >= min_neighbours)[:, None], h_sp, h_nb)
    mode = hist.argmax(1)
    share = hist[np.arange(nv), mode] / np.maximum(hist.sum(1), 1)
    empty = (hist == 0) & (np.arange(nbins)[None, :] >= mode[:, None])
    first_empty = np.where(empty.any(1), empty.argmax(1) * width, np.inf)
    cut = np.where(share >= 0.5, (mode + 1) * width, first_empty)
    keep = has_plane[inv] & (d_own < cut[inv])
    return NoiseFilterResult(keep, float(a), float(sigma), float(width))

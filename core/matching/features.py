"""SIFT features, matching guided by the approximate orientation, and geometric verification.

* Features: OpenCV SIFT on the grey image. OpenCV reports keypoints of its doubled first octave halved, but its
  doubling (``resize``, pixel-centre aligned) puts source pixel ``x`` at ``2x + 0.5``: every keypoint comes out
  0.25 px right of and below the feature in the pixel-centre origin of the core. The shift is removed
  (:data:`SIFT_OFFSET_PX`); left in, it tilts each camera by 0.25 px / f against its control point measurements,
  and the opposite headings of neighbouring strips turn that into height errors.
* Guided matching: a keypoint of image A, intersected with the planes ``z_lo`` and ``z_hi`` (the height range
  of the scene), projects into image B as a segment of the epipolar line. Only keypoints of B within
  ``band_px`` of that segment are candidates; among them the best descriptor must pass Lowe's ratio test
  against the second best candidate, and the match must be mutual. Wrong matches outside the band are
  rejected before any robust estimation.
  The band is at least ``band_px``, and wider for a pair whose navigation data are coarse: three times the
  standard deviation with which the two images' prior sigmas move a ground point across the epipolar line
  (:func:`pose_sigma_px`), so that a low-grade GNSS/IMU still finds its matches (with 1 degree and 10 m, 25 px lost
  every match of a pair in two of three simulated error directions).
* Verification: a fundamental matrix by MAGSAC++ on distortion-free pixel coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.projection import intersect_with_plane_z, project
from ..model import CameraModel, Pose


@dataclass(frozen=True)
class MatchOptions:
    """max_features : SIFT features per image; ratio : Lowe ratio; band_px : epipolar band half-width;
    z_lo, z_hi : scene height range for the guided search (metres); ransac_px : verification threshold;
    min_matches : fewer verified matches drop the pair."""

    max_features: int = 8000
    ratio: float = 0.85
    band_px: float = 25.0
    z_lo: float = 0.0
    z_hi: float = 100.0
    ransac_px: float = 1.5
    min_matches: int = 15


BAND_SIGMAS = 3.0
"""The epipolar band's half-width in standard deviations of the two images' navigation errors, where that is wider
than ``band_px``."""


def pose_sigma_px(camera: CameraModel, sigma_position: np.ndarray | None, sigma_attitude: np.ndarray | None,
                  distance: float) -> float:
    """Standard deviation (pixels, at the image centre, in one image direction) with which an image's navigation
    errors move the image of a point ``distance`` metres away: the focal length times the attitude sigma
    (world-axis rotations, radians, their RMS over the axes) and the position sigma (RMS over the axes) over the
    distance, added in quadrature; 0 without sigmas."""
    att, pos = rms_sigma(sigma_attitude), rms_sigma(sigma_position) / max(distance, 1.0)
    return float(np.sqrt(camera.fx * camera.fy)) * float(np.hypot(att, pos))


def rms_sigma(sigma: np.ndarray | None) -> float:
    """RMS over the axes of a prior sigma ``(3,)``; 0 without one."""
    return 0.0 if sigma is None else float(np.sqrt(np.mean(np.square(sigma))))


SIFT_OFFSET_PX = 0.25
"""Shift of OpenCV's SIFT keypoints against the pixel-centre origin (both axes), subtracted by :func:`sift_features`."""


def sift_features(grey: np.ndarray, max_features: int = 8000) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints ``uv (n, 2) float64`` (pixel-centre origin) and descriptors ``(n, 128) float32`` of a uint8
    image."""
    import cv2

    sift = cv2.SIFT_create(nfeatures=max_features)
    kps, des = sift.detectAndCompute(grey, None)
    if des is None:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    return np.array([k.pt for k in kps], np.float64) - SIFT_OFFSET_PX, des.astype(np.float32)


def epipolar_segments(uv_a: np.ndarray, cam_a: CameraModel, pose_a: Pose, cam_b: CameraModel, pose_b: Pose,
                      z_lo: float, z_hi: float) -> tuple[np.ndarray, np.ndarray]:
    """End points ``(n, 2), (n, 2)`` in image B of the rays of ``uv_a`` between heights ``z_lo`` and ``z_hi``."""
    p_lo = intersect_with_plane_z(cam_a, pose_a, uv_a, z_lo)
    p_hi = intersect_with_plane_z(cam_a, pose_a, uv_a, z_hi)
    s0, _ = project(cam_b, pose_b, p_lo)
    s1, _ = project(cam_b, pose_b, p_hi)
    return s0, s1


def clip_segments(s0: np.ndarray, s1: np.ndarray, lo: np.ndarray, hi: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The parts of the segments ``s0 -> s1`` (``(n, 2)``) inside the rectangle ``lo..hi`` (``(2,)``, Liang-Barsky):
    clipped end points and whether any part is inside ``(n,)`` (false for non-finite segments).

    A ray of A that passes close to B's projection centre projects to a segment millions of pixels long; clipped
    to the image it costs what any other does (unclipped, sampling it exhausted the memory)."""
    d = s1 - s0
    t0, t1 = np.zeros(len(s0)), np.ones(len(s0))
    inside = np.all(np.isfinite(s0), 1) & np.all(np.isfinite(s1), 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for p, q in ((-d, s0 - lo), (d, hi - s0)):
            for ax in (0, 1):
                pa, qa = p[:, ax], q[:, ax]
                inside &= ~((pa == 0) & (qa < 0))  # parallel to this border and beyond it
                t = qa / pa
                t0 = np.where(pa < 0, np.maximum(t0, t), t0)
                t1 = np.where(pa > 0, np.minimum(t1, t), t1)
    inside &= t0 <= t1
    return s0 + t0[:, None] * d, s0 + t1[:, None] * d, inside


def segment_distance(p: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
    """Distance of points ``p (k, 2)`` to segments ``s0, s1 (k, 2)`` (row-wise), by columns (no (k, 2)
    temporaries beyond the differences)."""
    dx, dy = s1[:, 0] - s0[:, 0], s1[:, 1] - s0[:, 1]
    px, py = p[:, 0] - s0[:, 0], p[:, 1] - s0[:, 1]
    t = np.clip((px * dx + py * dy) / np.maximum(dx * dx + dy * dy, 1e-12), 0, 1)
    ex, ey = p[:, 0] - (s0[:, 0] + t * dx), p[:, 1] - (s0[:, 1] + t * dy)
    return np.sqrt(ex * ex + ey * ey)


def descriptor_distances(des_a: np.ndarray, des_b: np.ndarray, a_idx: np.ndarray, b_idx: np.ndarray,
                         rows: int = 1024) -> np.ndarray:
    """Euclidean distances ``(k,) float32`` between descriptors ``des_a[a_idx]`` and ``des_b[b_idx]``
    (``des_a (n, d)``, ``des_b (m, d)`` float32; ``a_idx`` ascending, as the guided search gives them).

    OpenCV's SIFT descriptors hold whole numbers up to a few hundred. Then every term of
    ``|a|^2 + |b|^2 - 2 a.b`` is a whole number below 2^24, which float32 arithmetic adds exactly in any order, and
    the squared distances come from one matrix product per ``rows`` rows of A and the columns of B they need: the
    same values as the rows' differences, several times faster than gathering two 128-float rows per candidate (a
    demo pair has 0.7 million candidates). Numbered in space (:func:`guided_match`), the rows of a block need a
    part of B only. Other descriptors take the differences, in chunks of 200,000 candidates."""
    d = np.empty(len(a_idx), np.float32)
    if len(a_idx) == 0:
        return d
    na = np.einsum("ij,ij->i", des_a, des_a, dtype=np.float64)
    nb = np.einsum("ij,ij->i", des_b, des_b, dtype=np.float64)
    whole = (np.array_equal(des_a, np.round(des_a)) and np.array_equal(des_b, np.round(des_b))
             and 2.0 * (na.max(initial=0.0) + nb.max(initial=0.0)) < 2.0**24)
    if not whole:
        for k in range(0, len(a_idx), 200000):
            sl = slice(k, k + 200000)
            d[sl] = np.linalg.norm(des_a[a_idx[sl]] - des_b[b_idx[sl]], axis=1)
        return d
    na32, nb32 = na.astype(np.float32), nb.astype(np.float32)
    cuts = np.searchsorted(a_idx, np.arange(0, len(des_a) + rows, rows))
    need = np.zeros(len(des_b), bool)
    for r0, (k0, k1) in enumerate(zip(cuts[:-1], cuts[1:])):
        if k1 == k0:
            continue
        lo = r0 * rows
        need[:] = False
        need[b_idx[k0:k1]] = True  # the columns these rows need, and each candidate's among them
        cols = np.flatnonzero(need)
        b_k = (np.cumsum(need) - 1)[b_idx[k0:k1]]
        dots = des_a[lo:lo + rows] @ des_b[cols].T
        d[k0:k1] = na32[a_idx[k0:k1]] + nb32[b_idx[k0:k1]] - 2.0 * dots[a_idx[k0:k1] - lo, b_k]
    return np.sqrt(np.maximum(d, 0.0, out=d), out=d)


def band_candidates(uv_b: np.ndarray, s0: np.ndarray, s1: np.ndarray, ia: np.ndarray, band: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints of image B that may lie within ``band`` of the segments ``s0[ia] -> s1[ia]`` (``(n, 2)`` end
    points, ``ia (k,)`` the segments to search): index pairs ``(a, b)``, ``a`` ascending (each segment's
    keypoints by cell, then by index), without repeats; a superset of the pairs within the band (the caller tests
    the distance).

    B's keypoints are binned in square cells of ``4/3 band``; each segment is sampled every half cell, and the 3 x 3
    cells around each sample are taken. A point within the band lies within ``band`` of the segment, so within
    ``band + cell/4 = cell`` of a sample along both axes, inside that sample's 3 x 3 block. Per segment each cell
    is taken once, and each keypoint lies in one cell, so no pair repeats (the kd-tree balls this replaces covered
    about 3.5 times the band's area, with repeats where the balls overlapped)."""
    c = 4.0 / 3.0 * band
    lo = uv_b.min(0) - c
    cb = np.floor((uv_b - lo) / c).astype(np.int64)
    nx, ny = int(cb[:, 0].max()) + 2, int(cb[:, 1].max()) + 2
    cell_of_b = cb[:, 1] * nx + cb[:, 0]
    order_b = np.argsort(cell_of_b, kind="stable")  # keypoints of a cell in ascending index
    counts_b = np.bincount(cell_of_b, minlength=nx * ny)
    first_b = np.cumsum(counts_b) - counts_b
    length = np.linalg.norm(s1[ia] - s0[ia], axis=1)
    n_s = np.ceil(length / (c / 2)).astype(np.int64) + 1
    rep = np.repeat(ia, n_s)
    t = (np.arange(len(rep)) - np.repeat(np.cumsum(n_s) - n_s, n_s)) / np.repeat(np.maximum(n_s - 1, 1), n_s)
    cs = np.floor((s0[rep] + t[:, None] * (s1[rep] - s0[rep]) - lo) / c).astype(np.int64)
    again = np.r_[False, (rep[1:] == rep[:-1]) & np.all(cs[1:] == cs[:-1], axis=1)]  # the cell of the last sample
    rep, cs = rep[~again], cs[~again]
    keys = []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            x, y = cs[:, 0] + dx, cs[:, 1] + dy
            inside = (x >= 0) & (x < nx) & (y >= 0) & (y < ny)
            cell = y[inside] * nx + x[inside]
            keep = counts_b[cell] > 0
            keys.append(rep[inside][keep] * (nx * ny) + cell[keep])
    key = np.unique(np.concatenate(keys))
    a_cell, cell = key // (nx * ny), key % (nx * ny)
    k = counts_b[cell]
    a_idx = np.repeat(a_cell, k)
    pos = np.repeat(first_b[cell] - (np.cumsum(k) - k), k) + np.arange(int(k.sum()))
    return a_idx, order_b[pos]


def guided_match(uv_a: np.ndarray, des_a: np.ndarray, uv_b: np.ndarray, des_b: np.ndarray,
                 cam_a: CameraModel, pose_a: Pose, cam_b: CameraModel, pose_b: Pose,
                 opt: MatchOptions = MatchOptions()) -> np.ndarray:
    """Mutual ratio-test matches inside the epipolar band (module docstring). Returns ``(k, 2)`` index pairs."""
    if len(uv_a) == 0 or len(uv_b) == 0:
        return np.zeros((0, 2), np.int64)
    s0, s1 = epipolar_segments(uv_a, cam_a, pose_a, cam_b, pose_b, opt.z_lo, opt.z_hi)
    s0, s1, ok = clip_segments(s0, s1, np.full(2, -opt.band_px),
                               np.array([cam_b.width - 1 + opt.band_px, cam_b.height - 1 + opt.band_px]))
    # A's keypoints numbered by where their segments lie in B (rows of 64 px cells), so that consecutive ones
    # share candidates (descriptor_distances)
    mid = np.where(ok[:, None], (s0 + s1) / 2, 0.0) // 64.0
    perm = np.lexsort((mid[:, 0], mid[:, 1]))
    s0, s1 = s0[perm], s1[perm]
    a_idx, b_idx = band_candidates(uv_b, s0, s1, np.flatnonzero(ok[perm]), max(opt.band_px, 0.5))
    inside = segment_distance(uv_b[b_idx], s0[a_idx], s1[a_idx]) <= opt.band_px
    a_idx, b_idx = a_idx[inside], b_idx[inside]
    if len(a_idx) == 0:
        return np.zeros((0, 2), np.int64)
    d = descriptor_distances(des_a[perm], des_b, a_idx, b_idx)
    # per keypoint of A (its candidates are consecutive): the nearest candidate (the lowest index of B among equal
    # distances) and the next distance, for the ratio test; group minima instead of sorting every candidate
    first = np.r_[True, a_idx[1:] != a_idx[:-1]]
    pos = np.flatnonzero(first)
    group = np.cumsum(first) - 1
    near = np.minimum.reduceat(d, pos)
    is_near = d == near[group]
    near_b = np.minimum.reduceat(np.where(is_near, b_idx, len(uv_b)), pos)
    second = np.minimum.reduceat(np.where(is_near & (b_idx == near_b[group]), np.inf, d), pos)
    passed = near <= opt.ratio * second
    a_pass = perm[a_idx[pos[passed]]]
    best = np.full(len(uv_a), -1, np.int64)
    best_d = np.full(len(uv_a), np.inf)
    best[a_pass] = near_b[passed]
    best_d[a_pass] = near[passed]
    pairs = np.stack([np.flatnonzero(best >= 0), best[best >= 0]], 1)
    if len(pairs) == 0:
        return pairs
    # mutual: each keypoint of B keeps only its closest A partner
    order = np.lexsort((best_d[pairs[:, 0]], pairs[:, 1]))
    first = np.r_[True, pairs[order][1:, 1] != pairs[order][:-1, 1]]
    return pairs[order[first]]


def verify(uv_a: np.ndarray, uv_b: np.ndarray, cam_a: CameraModel, cam_b: CameraModel,
           threshold_px: float = 1.5) -> np.ndarray:
    """Inlier mask ``(k,)`` of matches under a fundamental matrix (MAGSAC++) on undistorted pixels."""
    import cv2

    if len(uv_a) < 8:
        return np.zeros(len(uv_a), bool)
    a = cam_a.normalized_to_pixel(cam_a.pixel_to_normalized(uv_a), distort=False)
    b = cam_b.normalized_to_pixel(cam_b.pixel_to_normalized(uv_b), distort=False)
    try:
        _, mask = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, threshold_px, 0.9999, 10000)
    except cv2.error:  # USAC asserts when no sample of the matches gives a model (tests/data/usac_no_model.npz)
        return np.zeros(len(uv_a), bool)
    return np.zeros(len(uv_a), bool) if mask is None else mask.ravel().astype(bool)

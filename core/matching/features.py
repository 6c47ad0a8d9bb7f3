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
* Verification: a fundamental matrix by MAGSAC++ on distortion-free pixel coordinates.
"""

from __future__ import annotations

import itertools
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


def segment_distance(p: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
    """Distance of points ``p (k, 2)`` to segments ``s0, s1 (k, 2)`` (row-wise)."""
    d = s1 - s0
    t = np.clip(np.einsum("ij,ij->i", p - s0, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0, 1)
    return np.linalg.norm(p - (s0 + t[:, None] * d), axis=1)


def descriptor_distances(des_a: np.ndarray, des_b: np.ndarray, a_idx: np.ndarray, b_idx: np.ndarray,
                         rows: int = 1024) -> np.ndarray:
    """Euclidean distances ``(k,) float32`` between descriptors ``des_a[a_idx]`` and ``des_b[b_idx]``
    (``des_a (n, d)``, ``des_b (m, d)`` float32; ``a_idx`` ascending, as the guided search gives them).

    OpenCV's SIFT descriptors hold whole numbers up to a few hundred. Then every term of
    ``|a|^2 + |b|^2 - 2 a.b`` is a whole number below 2^24, which float32 arithmetic adds exactly in any order, and
    the squared distances come from one matrix product per ``rows`` rows of A: the same values as the rows'
    differences, about ten times faster than gathering two 128-float rows per candidate (a demo pair has 0.7
    million candidates). Other descriptors take the differences, in chunks of 200,000 candidates."""
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
    for r0, (k0, k1) in enumerate(zip(cuts[:-1], cuts[1:])):
        if k1 == k0:
            continue
        lo = r0 * rows
        dots = des_a[lo:lo + rows] @ des_b.T
        a_k, b_k = a_idx[k0:k1] - lo, b_idx[k0:k1]
        d[k0:k1] = na32[a_idx[k0:k1]] + nb32[b_k] - 2.0 * dots[a_k, b_k]
    return np.sqrt(np.maximum(d, 0.0, out=d), out=d)


def guided_match(uv_a: np.ndarray, des_a: np.ndarray, uv_b: np.ndarray, des_b: np.ndarray,
                 cam_a: CameraModel, pose_a: Pose, cam_b: CameraModel, pose_b: Pose,
                 opt: MatchOptions = MatchOptions()) -> np.ndarray:
    """Mutual ratio-test matches inside the epipolar band (module docstring). Returns ``(k, 2)`` index pairs."""
    from scipy.spatial import cKDTree

    if len(uv_a) == 0 or len(uv_b) == 0:
        return np.zeros((0, 2), np.int64)
    s0, s1 = epipolar_segments(uv_a, cam_a, pose_a, cam_b, pose_b, opt.z_lo, opt.z_hi)
    ok = np.all(np.isfinite(s0), 1) & np.all(np.isfinite(s1), 1)
    half = np.linalg.norm(s1 - s0, axis=1) / 2
    tree = cKDTree(uv_b)
    ia = np.flatnonzero(ok)
    # each segment queried in pieces about four band widths long: one ball around a long segment holds mostly
    # points far outside its band (every point within the band lies within its piece's ball)
    n_piece = np.maximum(1, np.ceil(2 * half[ia] / (4 * max(opt.band_px, 0.5)))).astype(np.int64)
    rep = np.repeat(ia, n_piece)
    n_rep = np.repeat(n_piece, n_piece)
    t = (np.arange(len(rep)) - np.repeat(np.cumsum(n_piece) - n_piece, n_piece) + 0.5) / n_rep
    lists = tree.query_ball_point(s0[rep] + t[:, None] * (s1[rep] - s0[rep]), half[rep] / n_rep + opt.band_px,
                                  return_sorted=False)
    counts = np.fromiter(map(len, lists), np.int64, len(lists))
    if counts.sum() == 0:
        return np.zeros((0, 2), np.int64)
    hits = np.fromiter(itertools.chain.from_iterable(lists), np.int64, int(counts.sum()))
    key = np.unique(np.repeat(rep, counts) * len(uv_b) + hits)
    a_idx, b_idx = key // len(uv_b), key % len(uv_b)
    inside = segment_distance(uv_b[b_idx], s0[a_idx], s1[a_idx]) <= opt.band_px
    a_idx, b_idx = a_idx[inside], b_idx[inside]
    d = descriptor_distances(des_a, des_b, a_idx, b_idx)
    order = np.lexsort((d, a_idx))
    a_idx, b_idx, d = a_idx[order], b_idx[order], d[order]
    first = np.r_[True, a_idx[1:] != a_idx[:-1]]
    pos = np.flatnonzero(first)
    nxt = pos + 1
    has_second = np.r_[nxt[:-1] < pos[1:], nxt[-1:] < len(a_idx)]
    second = np.full(len(pos), np.inf, np.float32)
    second[has_second] = d[nxt[has_second]]
    passed = d[pos] <= opt.ratio * second
    best = np.full(len(uv_a), -1, np.int64)
    best_d = np.full(len(uv_a), np.inf)
    best[a_idx[pos[passed]]] = b_idx[pos[passed]]
    best_d[a_idx[pos[passed]]] = d[pos[passed]]
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
    _, mask = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, threshold_px, 0.9999, 10000)
    return np.zeros(len(uv_a), bool) if mask is None else mask.ravel().astype(bool)
